"""Bridge lifecycle: states, a start that fails at any step unwinds, and every close is
idempotent. These create DDS entities: run them inside `scripts/netns`."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from aiohttp import web
from interop.bridge_rig import bridge_config
from waiting import eventually

from rcan_rtps.api import ApiServer
from rcan_rtps.bridge.mdns import Advert, RcanAdvertiser, RcanBrowser
from rcan_rtps.bridge.navigation import GoalTracker
from rcan_rtps.bridge.runtime import Bridge, BridgeOptions, BridgeState, BridgeStateError
from rcan_rtps.bridge.telemetry import TelemetryState
from rcan_rtps.bridge.watchdog import LoopWatchdog
from rcan_rtps.config import RcanConfig
from rcan_rtps.events import EventsFrozenError
from rcan_rtps.governance import AuditLog
from rcan_rtps.governance.estop import EstopMachine, LatchFile
from rcan_rtps.ros import participant
from rcan_rtps.ros.actions import ActionClient, ActionServer
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.readers import ReaderThread
from rcan_rtps.ros.services import ServiceClient, ServiceServer

TOKEN = "t" * 32
# What advertises over mDNS runs in the serial phase, like every mDNS test (test_mdns.py).
ADVERTISES = pytest.mark.serial

# Bridge.start's steps, in order; each registers its own cleanup.
START_STEPS = [
    "_join_domain",
    "_open_audit",
    "_robot_side",
    "_governance",
    "_start_governor",
    "_serve",
    "_advertise_soon",
]


class Boom(Exception):
    pass


def _bridge(config: RcanConfig, *, mdns: bool = False) -> Bridge:
    return Bridge(
        config,
        BridgeOptions(
            port=0,
            host="127.0.0.1",
            mdns=mdns,
            mdns_interfaces=["127.0.0.1"],
            env={"RCAN_BRIDGE_TOKEN": TOKEN},
        ),
    )


def _ours(threads: list[threading.Thread]) -> set[threading.Thread]:
    # The test's event loop keeps its default executor's threads: not the bridge's.
    return {t for t in threads if not t.name.startswith("asyncio_")}


async def _threads_back_to(before: set[threading.Thread], timeout: float = 5.0) -> None:
    """Every thread started since `before` ends within `timeout`."""
    def left() -> set[str]:
        return {t.name for t in _ours(threading.enumerate()) - before}

    await eventually(lambda: not left(), timeout=timeout,
                     what=lambda: f"threads started since are gone: {sorted(left())}")


def _can_bind(port: int) -> bool:
    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _events(config: RcanConfig) -> list[str]:
    path = Path(config.bridge.audit.path)
    if not path.exists():
        return []
    return [json.loads(line)["event"] for line in path.read_text().splitlines()]


def _fail(step: str, when: str) -> Callable[..., Any]:
    original = getattr(Bridge, step)

    def fail_before(self: Bridge, *args: Any) -> Any:
        raise Boom(step)

    if when == "before":
        return fail_before
    if asyncio.iscoroutinefunction(original):

        async def fail_after_async(self: Bridge, *args: Any) -> Any:
            await original(self, *args)
            raise Boom(step)

        return fail_after_async

    def fail_after(self: Bridge, *args: Any) -> Any:
        original(self, *args)
        raise Boom(step)

    return fail_after


def test_every_start_step_is_listed() -> None:
    for step in START_STEPS:
        assert callable(getattr(Bridge, step)), step


@pytest.mark.parametrize("when", ["before", "after"])
@pytest.mark.parametrize("step", [
    pytest.param(step, marks=ADVERTISES) if step == "_advertise_soon" else step
    for step in START_STEPS])
async def test_a_start_failing_at_any_step_releases_what_it_acquired(
    step: str, when: str, tmp_path: Path, domain_id: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = bridge_config(tmp_path, domain_id)
    threads_before = _ours(threading.enumerate())
    bridge = _bridge(config, mdns=step == "_advertise_soon")
    bridge.prepare()
    port = bridge._sock.getsockname()[1]
    monkeypatch.setattr(Bridge, step, _fail(step, when))
    with pytest.raises(Boom):
        await bridge.start()
    assert bridge.state is BridgeState.FAILED
    assert bridge.node is None or bridge.node.closed
    assert domain_id not in participant._domains  # no DDS participant left in the process
    await _threads_back_to(threads_before)
    assert _can_bind(port), "the API port is still bound"
    events = _events(config)
    # BRIDGE_STARTED only if the governor got to start; then BRIDGE_STOPPED answers it.
    assert events.count("BRIDGE_STARTED") == events.count("BRIDGE_STOPPED") <= 1
    if events:
        assert events[0] == "BRIDGE_STARTED" and events[-1] == "BRIDGE_STOPPED"
    reopened = await AuditLog.open(config.bridge.audit.path, config.bridge.audit.key_path)
    await reopened.close()  # the failed start released the log's lock
    await bridge.stop()  # a no-op after a failed start
    assert bridge.state is BridgeState.FAILED
    with pytest.raises(BridgeStateError, match="failed"):
        await bridge.start()


async def test_states_of_a_start_and_a_stop(tmp_path: Path, domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id)
    threads_before = _ours(threading.enumerate())
    bridge = _bridge(config)
    assert bridge.state is BridgeState.NEW
    bridge.prepare()
    bridge.prepare()  # again: nothing to do
    assert bridge.state is BridgeState.PREPARED
    starting = asyncio.ensure_future(bridge.start())
    await asyncio.sleep(0)
    assert bridge.state is BridgeState.STARTING
    await starting
    assert bridge.state is BridgeState.RUNNING
    with pytest.raises(BridgeStateError, match="running"):
        await bridge.start()
    with pytest.raises(BridgeStateError, match="running"):
        bridge.prepare()
    assert bridge.node is not None and not bridge.node.closed
    # Every listener was wired while starting; a late one is a wiring bug, refused.
    assert bridge.events.frozen
    with pytest.raises(EventsFrozenError):
        bridge.events.governance.subscribe(lambda: None)
    stopping = asyncio.ensure_future(bridge.stop())
    await asyncio.sleep(0)
    assert bridge.state is BridgeState.STOPPING
    await asyncio.gather(stopping, bridge.stop())  # a second stop waits for the first
    assert bridge.state is BridgeState.STOPPED and bridge.node.closed
    await bridge.stop()
    assert bridge.state is BridgeState.STOPPED
    assert _events(config) == ["BRIDGE_STARTED", "BRIDGE_STOPPED"]
    await _threads_back_to(threads_before)
    with pytest.raises(BridgeStateError, match="stopped"):
        await bridge.start()


async def test_stop_while_starting_waits_then_stops(tmp_path: Path, domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id)
    bridge = _bridge(config)
    starting = asyncio.ensure_future(bridge.start())
    await asyncio.sleep(0)
    await bridge.stop()
    assert starting.done() and bridge.state is BridgeState.STOPPED
    assert _events(config) == ["BRIDGE_STARTED", "BRIDGE_STOPPED"]


async def test_stop_before_start_is_a_noop(tmp_path: Path, domain_id: int) -> None:
    bridge = _bridge(bridge_config(tmp_path, domain_id))
    await bridge.stop()
    assert bridge.state is BridgeState.NEW
    await bridge.start()  # still startable
    await bridge.stop()
    assert bridge.state is BridgeState.STOPPED


async def test_a_prepared_bridge_stopped_releases_its_port(tmp_path: Path, domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id)
    bridge = _bridge(config)
    bridge.prepare()
    port = bridge._sock.getsockname()[1]
    assert not _can_bind(port)
    await bridge.stop()
    assert bridge.state is BridgeState.STOPPED and _can_bind(port)
    assert _events(config) == []


async def test_a_failed_prepare_leaves_a_failed_bridge(tmp_path: Path, domain_id: int) -> None:
    bridge = Bridge(
        bridge_config(tmp_path, domain_id), BridgeOptions(port=0, mdns=False, env={})
    )  # no token
    with pytest.raises(Exception, match="unset or empty"):
        await bridge.start()
    assert bridge.state is BridgeState.FAILED and bridge.node is None
    await bridge.stop()
    assert bridge.state is BridgeState.FAILED


# -- close() twice --------------------------------------------------------------------------


async def _twice(close: Callable[[], object]) -> None:
    for _ in range(2):
        result = close()
        if isinstance(result, Awaitable):
            await result


async def test_ros_entities_close_twice(domain_id: int) -> None:
    node = RosNode("lifecycle_close", "/t", domain_id=domain_id)
    pub = node.create_publisher("chatter", "std_msgs/msg/String")
    sub = node.create_subscription("chatter", "std_msgs/msg/String")
    callback_sub = node.create_subscription(
        "chatter", "std_msgs/msg/String", callback=lambda _m: None
    )

    async def echo(request: Any) -> dict[str, Any]:
        return {}

    server = ServiceServer(node, "empty", "std_srvs/srv/Empty", echo)
    client = ServiceClient(node, "empty", "std_srvs/srv/Empty")
    await client.call({}, timeout=10)

    async def execute(goal: Any) -> dict[str, Any]:
        return {}

    action_server = ActionServer(node, "nav", "nav2_msgs/action/NavigateToPose", execute)
    action_client = ActionClient(node, "nav", "nav2_msgs/action/NavigateToPose")
    goals = GoalTracker(node, "navigate_to_pose")
    for close in (
        pub.close,
        sub.close,
        callback_sub.close,
        server.close,
        client.close,
        action_server.close,
        action_client.close,
        goals.close,
    ):
        await _twice(close)
    with pytest.raises(Exception, match="closed"):
        await client.call({}, timeout=1)
    await _twice(node.close)
    await _twice(node.reader_thread.close)
    assert not node.reader_thread.alive()


async def test_a_half_made_node_leaves_nothing(
    domain_id: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(self: RosNode) -> Any:
        raise Boom("discovery writer")

    monkeypatch.setattr(RosNode, "_discovery_writer", broken)
    with pytest.raises(Boom):
        RosNode("half_made", domain_id=domain_id)
    assert domain_id not in participant._domains


async def test_reader_thread_closes_twice_unstarted(domain_id: int) -> None:
    with RosNode("reader_thread", domain_id=domain_id) as node:
        thread = ReaderThread(node.participant, "unused")
        await _twice(thread.close)


async def test_telemetry_closes_twice(tmp_path: Path, domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id)
    with RosNode("telemetry_close", "/robot1", domain_id=domain_id) as node:
        telemetry = TelemetryState(node, config, estop_latched=lambda: False, active_goals=list)
        await _twice(telemetry.close)


async def test_governance_closes_twice(tmp_path: Path) -> None:
    audit = await AuditLog.open(tmp_path / "audit.jsonl", tmp_path / "audit.key")
    latch = EstopMachine(LatchFile(tmp_path / "estop.state"), latched=False)
    await latch.engage(_nothing)
    await _twice(latch.close)
    await _twice(latch.file.close)
    await _twice(audit.close)


async def _nothing() -> None:
    return None


async def test_governor_stops_once(tmp_path: Path, domain_id: int) -> None:
    bridge = _bridge(bridge_config(tmp_path, domain_id))
    await bridge.start()
    assert bridge.governor is not None
    await _twice(bridge.governor.stop)  # one BRIDGE_STOPPED
    await bridge.stop()
    assert _events(bridge.config) == ["BRIDGE_STARTED", "BRIDGE_STOPPED"]


async def test_api_server_closes_twice_and_unstarted(tmp_path: Path, domain_id: int) -> None:
    bridge = _bridge(bridge_config(tmp_path, domain_id))
    await bridge.start()
    assert bridge.server is not None
    await _twice(bridge.server.close)
    await bridge.stop()
    await _twice(ApiServer(web.Application(), host="127.0.0.1", port=0).close)  # unstarted


@ADVERTISES
async def test_mdns_closes_twice(tmp_path: Path, domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id)
    advert = Advert.for_server(config, host="127.0.0.1", port=8000, tls=False)
    advertiser = RcanAdvertiser(advert, interfaces=["127.0.0.1"])
    await _twice(advertiser.close)  # never started
    advertiser = RcanAdvertiser(advert, interfaces=["127.0.0.1"])
    await advertiser.start()
    advertiser.follow(lambda: advert)
    await _twice(advertiser.close)
    browser = RcanBrowser(interfaces=["127.0.0.1"])
    await browser.start()
    await _twice(browser.close)


async def test_watchdog_stops_twice() -> None:
    watchdog = LoopWatchdog(asyncio.get_running_loop(), 1.0)
    await _twice(watchdog.stop)  # never started
    watchdog = LoopWatchdog(asyncio.get_running_loop(), 1.0)
    watchdog.start()
    await _twice(watchdog.stop)
    assert "loop-watchdog" not in {t.name for t in threading.enumerate()}
