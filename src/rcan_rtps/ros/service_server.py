"""The server side of ROS 2 services (`ServiceServer`, Cyclone mapping only; see
`services.py`).

Apart from the client: a bridge only calls services, so it never loads this (the simulated
robot, `ActionServer`, parameter services and tests serve with it; issue 27, idle memory).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

from cyclonedds.idl import IdlStruct

from . import qos as qos_mod
from .errors import SampleTooLarge
from .handshake import matched_subscriptions, matched_writers
from .participant import RosNode
from .qos import QosProfile
from .services import (
    RequestMapping,
    _Pair,
    _Role,
    _ServiceEnd,
    _user_data,
    mapping_of_vendor,
)

log = logging.getLogger(__name__)

CLIENT_READER_WAIT = 1.0  # s a server waits for the client's reply reader (rmw_cyclonedds: 0.1)
Handler = Callable[[IdlStruct], Awaitable["IdlStruct | Mapping[str, Any]"]]


class ServiceServer(_ServiceEnd):
    """Serves one service with an async handler (Cyclone mapping; see the module docs)."""

    _ROLE = _Role.SERVER

    def __init__(self, node: RosNode, service: str, type_name: str, handler: Handler, *,
                 qos: QosProfile = qos_mod.SERVICES) -> None:
        super().__init__(node, service, type_name, qos)
        self._handler = handler
        self._tasks: set[asyncio.Task[None]] = set()
        self._warned: set[bytes] = set()
        self._pair = self._make_pair(RequestMapping.CYCLONE, self._deliver)

    def _deliver(self, pair: _Pair, samples: list[Any]) -> None:
        for sample in samples:
            task = asyncio.get_running_loop().create_task(self._serve(sample))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _serve(self, sample: Any) -> None:
        writer_handle = int(sample.sample_info.publication_handle)
        client = self._pair.reader.get_matched_publication_data(writer_handle)
        if client is None:
            return  # the client left before we got to its request
        guid = bytes(client.key.bytes)
        if mapping_of_vendor(guid, _user_data(client).get("clientid", "")) \
                is not RequestMapping.CYCLONE:
            self._warn_once(guid)
            return
        header, request = sample.header, sample.payload
        try:
            response = await self._handler(request)
            if not isinstance(response, IdlStruct):
                response = self.node.values.build(self.response_type, response)
        except Exception:  # a failing handler sends no reply, like rclpy; the client times out
            log.exception("service %s: the handler failed", self.name)
            return
        if not await self._client_reader_ready(_user_data(client).get("clientid"),
                                               writer_handle):
            return
        try:
            self._pair.write(response, header)
        except SampleTooLarge as exc:  # no reply, as for a failing handler: said here
            log.warning("service %s: the reply was not sent: %s", self.name, exc)

    def _warn_once(self, guid: bytes) -> None:
        """Says once per client request writer that its requests are ignored. Only the
        writers still matched are remembered (looked at when a new one comes): each `ros2
        service call` is a new one, and a server that runs for weeks must not keep them all.
        A request of a writer gone is dropped before this (`_serve`), so forgetting it costs
        at most a second warning."""
        if guid in self._warned:
            return
        self._warned &= set(matched_writers(self._pair.reader).values())
        self._warned.add(guid)
        log.warning("service %s: ignoring requests of a %s client; it cannot use the "
                    "Cyclone request-reply mapping", self.name, guid[:2].hex("."))

    async def _client_reader_ready(self, client_id: str | None, writer_handle: int) -> bool:
        """Like rmw_cyclonedds: wait briefly until the client's reply reader is matched, so
        the reply is not lost to a reader that discovery has not delivered yet."""
        if client_id is None:
            return True
        loop = asyncio.get_running_loop()
        deadline = loop.time() + CLIENT_READER_WAIT
        writer, reader = self._pair.writer, self._pair.reader
        while loop.time() < deadline:
            for handle in matched_subscriptions(writer):
                found = writer.get_matched_subscription_data(handle)
                if found is not None and _user_data(found).get("clientid") == client_id:
                    return True
            if reader.get_matched_publication_data(writer_handle) is None:
                return False  # the client is gone
            await asyncio.sleep(0.01)
        return False

    async def close(self) -> None:
        """Cancels the requests being served, then deletes the endpoints; idempotent."""
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._pair.close()
