"""How much a process's anonymous memory grows per DDS entity made and deleted, by kind.

    scripts/netns .venv/bin/python bench/entity_churn.py KIND [N] [WARM_UP]

KIND is one of the functions in `kinds` below: a whole ServiceClient (made, called once
against a ServiceServer of another node of this process, closed), or one entity of the
kinds a client makes, alone. Prints kB grown over N (after WARM_UP) and bytes per operation.
Memory is RssAnon from /proc/self/status; with TRACE=1, what Python allocated and still
holds is printed too (tracemalloc; C growth is the difference).

Settings (environment): REMOTE=1 the servers in a process of their own; TRACE=1 Python's
share (tracemalloc, a run of its own: its traces count in RssAnon); CURVE=K RssAnon every K
operations; SMALL_CACHES=1 the packet capture's bounded tables shrunk, SERVER_KEEP=16 the
action server's kept goals (both fill over the first ~1,500 clients, which looks like
growth per client until they are full); SETTLE=S seconds before the last read; TRIM=1 glibc's
free pages handed back (malloc_trim) before each read, so that freed memory the allocator
keeps is not counted as growth. The node's
shared graph is read after each operation, as a bridge's commander watch reads it.
"""

from __future__ import annotations

import asyncio
import ctypes
import gc
import os
import sys
import tracemalloc
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from cyclonedds.core import GuardCondition, ReadCondition, WaitSet
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

from rcan_rtps.ros import _cyclone_header as cyclone
from rcan_rtps.ros import qos as qos_mod
from rcan_rtps.ros import rtps_capture
from rcan_rtps.ros.action_server import ActionServer, ServerGoal
from rcan_rtps.ros.actions import KEEP_FINISHED, ActionClient
from rcan_rtps.ros.graph import Direction, shared_graph
from rcan_rtps.ros.handshake import peers_know_our_readers
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.readers import ANY_SAMPLE
from rcan_rtps.ros.services import ServiceClient, ServiceServer

DOMAIN = 77
TRACE = os.environ.get("TRACE") == "1"
TRIM = os.environ.get("TRIM") == "1"  # malloc_trim before each read (glibc)
SETTLE = float(os.environ.get("SETTLE", "0"))  # s before the last read
CURVE = int(os.environ.get("CURVE", "0"))  # print RssAnon every CURVE operations
REMOTE = os.environ.get("REMOTE") == "1"  # the server in a process of its own
SERVICE, TYPE = "/churn_probe", "std_srvs/srv/Trigger"
ACTION, NAV = "/churn_nav", "nav2_msgs/action/NavigateToPose"
TOPIC, MSG = "rt/churn_probe_topic", "std_msgs/msg/String"


if os.environ.get("SMALL_CACHES") == "1":
    # The packet capture's bounded tables (thousands of reader/writer pairs, each new client
    # adds some) fill over the first ~1,500 action clients: shrunk, a short warm-up fills
    # them, and what grows after is growth for good.
    rtps_capture.KEPT_HEARTBEATS = rtps_capture.KEPT_ACKNACKS = 64
    rtps_capture.KEPT_IDENTITIES = 64


def rss_anon_kb() -> int:
    if TRIM:
        ctypes.CDLL(None).malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssAnon:"):
            return int(line.split()[1])
    raise RuntimeError("no RssAnon")


Op = Callable[[], Awaitable[None]]


def kinds(client: RosNode, server: RosNode) -> dict[str, Op]:
    topic = client.topic(TOPIC, MSG)

    async def service_client() -> None:
        c = ServiceClient(client, SERVICE, TYPE)
        await c.call({}, timeout=10)
        c.close()

    async def service_client_reused() -> None:
        if not reused:
            reused.append(ServiceClient(client, SERVICE, TYPE))
        await reused[0].call({}, timeout=10)

    async def bare_reader() -> None:
        DataReader(client.subscriber, topic).__del__()

    async def bare_writer() -> None:
        DataWriter(client.publisher, topic).__del__()

    async def reader_with_qos() -> None:
        reader = client.create_reader(TOPIC, MSG, qos_mod.SERVICES, "clientid=01.02;")
        client.forget_reader(reader)
        reader.__del__()

    async def writer_with_qos() -> None:
        writer = client.create_writer(TOPIC, MSG, qos_mod.SERVICES, "clientid=01.02;")
        client.forget_writer(writer)
        writer.__del__()

    async def read_condition() -> None:
        ReadCondition(fixed_reader, ANY_SAMPLE).__del__()

    async def waitset() -> None:
        ws = WaitSet(client.participant)
        cond = ReadCondition(fixed_reader, ANY_SAMPLE)
        ws.attach(cond)
        ws.detach(cond)
        cond.__del__()
        ws.__del__()

    async def guard_condition() -> None:
        GuardCondition(client.participant).__del__()

    async def watched_reader() -> None:
        reader = DataReader(client.subscriber, topic)
        watch = client.watch(reader, lambda samples: None, "probe")
        client.unwatch(watch)
        reader.__del__()

    async def discovery_reader() -> None:
        client.discovery_reader().__del__()

    async def announce() -> None:
        client.announce()

    async def get_guid() -> None:
        fixed_reader.guid  # noqa: B018

    async def instance_handle() -> None:
        fixed_writer.get_instance_handle()

    async def matched_status() -> None:
        fixed_writer.get_publication_matched_status()  # type: ignore[no-untyped-call]
        fixed_reader.get_subscription_matched_status()  # type: ignore[no-untyped-call]

    async def set_status_mask() -> None:
        fixed_writer.set_status_mask(0)

    async def _matched_reader() -> Any:
        if not reused:
            reused.append(ServiceClient(client, SERVICE, TYPE))
            await reused[0].call({}, timeout=10)
        return next(iter(reused[0]._pairs.values())).reader

    async def matched_publication_data() -> None:
        reader = await _matched_reader()
        for handle in reader.get_matched_publications():
            reader.get_matched_publication_data(handle)

    async def matched_publications() -> None:
        (await _matched_reader()).get_matched_publications()

    async def handshake() -> None:
        await peers_know_our_readers(client, {await server_prefix()}, 10)

    async def server_prefix() -> bytes:
        graph = shared_graph(client)
        while True:  # (until discovery shows the server)
            graph.refresh()
            for e in graph.endpoints():
                if e.dds_topic.endswith("churn_probeReply") and \
                        e.direction is Direction.PUBLISHER:
                    return e.gid[:12]
            await asyncio.sleep(0.05)

    async def cyclone_reader() -> None:
        reader = cyclone.create_reader(client, "rr/churn_probeReply",
                                       TYPE + "_Response", qos_mod.SERVICES, "clientid=1;")
        client.forget_reader(reader)
        reader.__del__()

    async def cyclone_writer() -> None:
        writer = cyclone.create_writer(client, "rq/churn_probeRequest",
                                       TYPE + "_Request", qos_mod.SERVICES, "clientid=1;")
        client.forget_writer(writer)
        writer.__del__()

    async def action_client() -> None:
        a = ActionClient(client, ACTION, NAV)
        goal = await a.send_goal({}, timeout=10)
        await goal.result(timeout=10)
        a.close()

    async def action_goal_reused() -> None:
        if not reused_action:
            reused_action.append(ActionClient(client, ACTION, NAV))
        goal = await reused_action[0].send_goal({}, timeout=10)
        await goal.result(timeout=10)

    async def action_wait_for_server() -> None:
        a = ActionClient(client, ACTION, NAV)
        await a.wait_for_server(10)
        a.close()

    async def action_client_cancel_only() -> None:
        a = ActionClient(client, ACTION, NAV)
        await a.cancel_all(10, server_wide=True)
        a.close()

    async def action_client_idle() -> None:
        ActionClient(client, ACTION, NAV).close()

    async def subscription() -> None:
        client.create_subscription("/churn_probe_sub", MSG).close()

    async def publisher() -> None:
        client.create_publisher("/churn_probe_pub", MSG).close()

    fixed_reader = DataReader(client.subscriber, topic)
    fixed_writer = DataWriter(client.publisher, topic)
    reused: list[ServiceClient] = []  # (made by the first call)
    reused_action: list[ActionClient] = []
    return {name: op for name, op in locals().items() if callable(op) and
            name not in ("topic",) and not name.startswith("fixed")}


async def trigger(_request: Any) -> dict[str, Any]:
    return {"success": True, "message": "ok"}


async def navigate(_goal: ServerGoal) -> dict[str, Any]:
    return {}


async def serve() -> None:
    """The servers alone, in a process of its own, until stdin closes."""
    with RosNode("churn_server", "/", domain_id=DOMAIN, localhost=True) as server_node:
        servers = servers_on(server_node)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
        for server in servers:
            await server.close()


def servers_on(node: RosNode) -> list[Any]:
    return [ServiceServer(node, SERVICE, TYPE, trigger),
            # SERVER_KEEP=16: keeping few ended goals (a server's status array lists every goal
            # it keeps, up to 1,000 by default, and each client's status reader gets it whole)
            ActionServer(node, ACTION, NAV, navigate,
                         keep_finished=int(os.environ.get("SERVER_KEEP", KEEP_FINISHED)))]


async def run(kind: str, count: int, warm_up: int) -> None:
    other = None
    if REMOTE:
        other = await asyncio.create_subprocess_exec(
            sys.executable, __file__, "serve", stdin=asyncio.subprocess.PIPE)
    with RosNode("churn_server", "/", domain_id=DOMAIN, localhost=True) as server_node, \
            RosNode("churn_client", "/", domain_id=DOMAIN, localhost=True) as client_node:
        servers = [] if REMOTE else servers_on(server_node)
        op = kinds(client_node, server_node)[kind]

        # Read after each operation, as a bridge's commander watch reads it every poll: its
        # builtin readers keep every endpoint that came and went until it is read.
        graph = shared_graph(client_node)

        async def ops(n: int) -> None:
            for i in range(n):
                await op()
                graph.refresh()
                if CURVE and i % CURVE == CURVE - 1:
                    print(f"  after {i + 1}: RssAnon {rss_anon_kb()} kB", flush=True)

        await ops(warm_up)
        gc.collect()
        if TRACE:  # (its own traces count in RssAnon: a separate run)
            tracemalloc.start(8)
            first = tracemalloc.take_snapshot()
        before = rss_anon_kb()
        await ops(count)
        await asyncio.sleep(SETTLE)  # Cyclone frees deleted entities on a thread of its own
        gc.collect()
        grown = rss_anon_kb() - before
        py_grown = tracemalloc.get_traced_memory()[0]
        if TRACE:
            top = tracemalloc.take_snapshot().compare_to(first, "traceback")
            for stat in top[:8]:
                print(stat)
                for line in stat.traceback.format()[-16:]:
                    print("   ", line)
        print(f"{kind}: {count} ops, RssAnon +{grown} kB = {grown * 1024 / count:.0f} B/op"
              + (f"; Python heap +{py_grown >> 10} kB = {py_grown / count:.0f} B/op"
                 if TRACE else ""))
        for server in servers:
            await server.close()
    if other is not None:
        assert other.stdin is not None
        other.stdin.close()
        await other.wait()


if __name__ == "__main__":
    kind = sys.argv[1]
    if kind == "serve":
        asyncio.run(serve())
        sys.exit()
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 2000
    warm_up = int(sys.argv[3]) if len(sys.argv) > 3 else 200
    asyncio.run(run(kind, count, warm_up))
