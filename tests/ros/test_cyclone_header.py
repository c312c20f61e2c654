"""The rmw_cyclonedds in-band request header: byte layout, and an rmw_cyclonedds-shaped peer.

The peer below is written from the documented layout (ros2-wire.md §3), independently of
`_cyclone_header`: `{uint64 guid; int64 seq; <fields>}` under the plain type's name.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from cyclonedds.core import Policy
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import make_idl_struct
from cyclonedds.idl import types as t
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from oracle.client import RclpyOracle
from waiting import eventually

from rcan_rtps.ros import _cyclone_header as cyclone
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.services import ServiceClient, ServiceServer, format_endpoint_id
from rcan_rtps.ros.typesys.cdr import CdrCodecs
from rcan_rtps.ros.typesys.ddstypes import DdsTypes
from rcan_rtps.ros.typesys.store import TypeStore
from rcan_rtps.ros.typesys.values import MessageValues

CASES = [
    ("std_srvs/srv/SetBool_Request", {"data": True}),
    ("std_srvs/srv/SetBool_Response", {"success": True, "message": "ok"}),
    ("action_msgs/srv/CancelGoal_Request",
     {"goal_info": {"goal_id": {"uuid": list(range(16))}, "stamp": {"sec": 7, "nanosec": 9}}}),
]
GUID, SEQ = 0x0102030405060708, 0x1122334455667788


@pytest.fixture(scope="module")
def values() -> MessageValues:
    return MessageValues(DdsTypes(TypeStore(distro="jazzy")))


@pytest.mark.parametrize(("type_name", "value"), CASES)
def test_header_layout_matches_the_documented_bytes(jazzy_python: Path, values: MessageValues,
                                                   type_name: str, value: Any) -> None:
    plain = values.build(type_name, value)
    raw = cyclone.wrap_cdr(cyclone.RequestHeader(GUID, SEQ), plain.serialize())
    # the same bytes as the wrapper struct cyclonedds itself would write
    wrapper = cyclone.wrapper_struct(_NodeLike(values), type_name)  # type: ignore[arg-type]
    fields = {f: getattr(plain, f) for f in plain.__dataclass_fields__}
    assert raw == wrapper(rmw_request_client_guid=GUID, rmw_request_seq=SEQ, **fields).serialize()
    assert raw[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
    assert raw[4:12] == struct.pack("<Q", GUID) == bytes.fromhex("0807060504030201")
    assert raw[12:20] == struct.pack("<q", SEQ)
    assert raw[20:] == plain.serialize()[4:]  # then exactly the plain fields
    with RclpyOracle(jazzy_python, "layout") as oracle:  # which rclpy reads as the message
        assert oracle.call("deserialize", type=type_name, hex=(raw[:4] + raw[20:]).hex()) == value


def test_big_endian_samples_carry_a_big_endian_header(values: MessageValues) -> None:
    decode = cyclone.decoder(_NodeLike(values), "std_srvs/srv/SetBool_Request")  # type: ignore[arg-type]
    for raw in (b"\x00\x00\x00\x00" + struct.pack(">Qq", GUID, 5) + b"\x01",
                b"\x00\x01\x00\x00" + struct.pack("<Qq", GUID, 5) + b"\x01"):
        sample = decode(raw)
        assert sample.header == cyclone.RequestHeader(GUID, 5) and sample.payload.data is True


class _NodeLike:
    """The attributes `wrapper_struct` and `decoder` read from a node."""

    def __init__(self, values: MessageValues) -> None:
        self.types = values.types
        self.store = values.types.store
        self.codecs = CdrCodecs(values.types, values)


# -- an rmw_cyclonedds-shaped peer ----------------------------------------------------
RequestWire = make_idl_struct("SetBool_Request_", "std_srvs::srv::dds_::SetBool_Request_", {
    "guid": t.uint64, "seq": t.int64, "data": bool})
ReplyWire = make_idl_struct("SetBool_Response_", "std_srvs::srv::dds_::SetBool_Response_", {
    "guid": t.uint64, "seq": t.int64, "success": bool, "message": str})


def _qos(user_data: str) -> Qos:
    # Jazzy rmw_cyclonedds announces no XTypes type, so peers match by type name alone;
    # ignoring member names is the closest cyclonedds-python gets to that.
    return Qos(Policy.Reliability.Reliable(duration(infinite=True)),
               Policy.History.KeepLast(10), Policy.Userdata(user_data.encode()),
               Policy.TypeConsistency.AllowTypeCoercion(ignore_member_names=True))


class CyclonePeer:
    def __init__(self, domain_id: int, service: str, role: str, ident: str) -> None:
        self.participant = DomainParticipant(domain_id)
        request = Topic(self.participant, f"rq{service}Request", RequestWire)
        reply = Topic(self.participant, f"rr{service}Reply", ReplyWire)
        qos = _qos(f"{role}={ident};")
        if role == "serviceid":
            self.reader: DataReader[Any] = DataReader(self.participant, request, qos=qos)
            self.writer: DataWriter[Any] = DataWriter(self.participant, reply, qos=qos)
        else:
            self.reader = DataReader(self.participant, reply, qos=qos)
            self.writer = DataWriter(self.participant, request, qos=qos)

    async def take(self, timeout: float = 10.0) -> Any:
        got = await eventually(lambda: self.reader.take(N=1), timeout=timeout,
                               what="the peer receives a request")
        return got[0]

    async def matched(self) -> None:
        await eventually(lambda: self.writer.get_publication_matched_status().current_count
                         and self.reader.get_subscription_matched_status().current_count,
                         what="the peer matched both ways")


@pytest.fixture
async def node(domain_id: int) -> AsyncIterator[RosNode]:
    with RosNode("rcan_peer_test", "/", domain_id=domain_id, distro="jazzy") as n:
        yield n


async def test_our_client_echo_and_foreign_guid_replies_ignored(domain_id: int,
                                                               node: RosNode) -> None:
    peer = CyclonePeer(domain_id, "/peer_srv", "serviceid", "01.10.aa.0.0.0.0.0.0.0.0.0.0.0.0.1")
    client = ServiceClient(node, "/peer_srv", "std_srvs/srv/SetBool")
    await client.wait_for_service(15)
    await peer.matched()
    pending = asyncio.ensure_future(client.call({"data": True}, timeout=15))
    request = await peer.take()
    assert request.data is True and request.seq == 1
    guid = request.guid
    # A reply for another client (same seq), then one for a request never made: ignored.
    peer.writer.write(ReplyWire(guid=guid ^ 1, seq=request.seq, success=False, message="foreign"))
    peer.writer.write(ReplyWire(guid=guid, seq=request.seq + 100, success=False, message="stale"))
    # Sentinel: the client counts what it drops, so both are in (and ignored) once it says 2.
    await eventually(lambda: client.dropped_replies == 2)
    assert not pending.done()
    peer.writer.write(ReplyWire(guid=guid, seq=request.seq, success=True, message="mine"))
    reply = await pending
    assert (reply.success, reply.message) == (True, "mine")
    assert client.dropped_replies == 2
    # The next request carries the same guid and the next sequence number.
    pending = asyncio.ensure_future(client.call({"data": False}, timeout=15))
    second = await peer.take()
    assert (second.guid, second.seq, second.data) == (guid, 2, False)
    peer.writer.write(ReplyWire(guid=guid, seq=2, success=False, message="second"))
    assert (await pending).message == "second"


async def test_our_server_echoes_the_header(domain_id: int, node: RosNode) -> None:
    async def handle(request: Any) -> dict[str, object]:
        return {"success": not request.data, "message": "flipped"}

    server = ServiceServer(node, "/flip", "std_srvs/srv/SetBool", handle)
    ident = format_endpoint_id(bytes(range(16)))
    assert ident == "00.1.2.3.4.5.6.7.8.9.a.b.c.d.e.f"  # rmw_cyclonedds' csid_to_string form
    peer = CyclonePeer(domain_id, "/flip", "clientid", ident)
    await peer.matched()
    peer.writer.write(RequestWire(guid=0xDEADBEEF00C0FFEE, seq=41, data=True))
    reply = await peer.take()
    assert (reply.guid, reply.seq) == (0xDEADBEEF00C0FFEE, 41)
    assert (reply.success, reply.message) == (False, "flipped")
    await server.close()
