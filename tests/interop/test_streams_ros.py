"""Velocity streams (issue 11) on the wire, as a real rclpy Jazzy subscriber receives them.

cmd_vel is one reliable writer matched with one reliable reader: samples arrive in the order
they were written. That order is what these tests check, never wall-clock latency: a sentinel
velocity sent after the event under test bounds "everything written after it".
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from waiting import eventually, take

from rcan_rtps.rcan import validate_command

from .bridge_rig import AGENT, OPS, VIEWER, Rig, bridge_config, close_rig, make_rig
from .test_bridge_ros import CMD_VEL, SENTINEL_X, TWIST, subscribe, xs

RATE_HZ = 20.0


@pytest.fixture
async def rig(tmp_path: Path, jazzy_python: Path, domain_id: int) -> AsyncIterator[Rig]:
    config = bridge_config(tmp_path, domain_id, extra_ros2=f"cmd_rate_hz: {RATE_HZ}\n")
    r = await make_rig(config, jazzy_python, domain_id)
    yield r
    await close_rig(r)


async def after_sentinel_stream(rig: Rig) -> list[float]:
    """Every linear_x received up to a sentinel move sent now (then stopped)."""
    sentinel = await rig.command(AGENT, {"action": "move", "params": {"linear_x": SENTINEL_X}})
    assert sentinel.http_status == 200, sentinel
    got = xs(await take(rig.oracle, CMD_VEL, until=lambda got: SENTINEL_X in xs(got)))
    await rig.command(AGENT, {"action": "stop"})
    return got[:got.index(SENTINEL_X)]


def ended(rig: Rig) -> list[tuple[str, str]]:
    return [(e["message_id"], e["params"]["reason"]) for e in rig.entries()
            if e["event"] == "STREAM_ENDED"]


async def _heartbeats(rig: Rig) -> None:
    while True:  # a timed move is held: its sender stays heard from (issue 23)
        rig.governor.heartbeat(AGENT)
        await asyncio.sleep(0.25)


async def test_a_timed_move_streams_at_the_rate_then_zero(rig: Rig) -> None:
    # A history no burst overwrites: the counts below compare what was sent with what came
    # (with rclpy's default depth of 10, a loaded oracle's reader kept 37 of 38 once in CI).
    await subscribe(rig, CMD_VEL, TWIST, qos="deep")
    d = await rig.command(AGENT, {"action": "move",
                                  "params": {"linear_x": 0.5, "duration_s": 2.0}})
    assert d.http_status == 200, d
    beating = asyncio.create_task(_heartbeats(rig))

    def complete() -> bool:
        return (d.message_id, "completed") in ended(rig)

    try:
        await eventually(complete, timeout=15)
    finally:
        beating.cancel()
    got = xs(await take(rig.oracle, CMD_VEL, until=lambda got: 0.0 in xs(got)))
    moving = got[:got.index(0.0)]
    assert moving and set(moving) == {0.5}  # samples per second: bench/streams.py
    samples = next(e for e in rig.entries() if e["event"] == "STREAM_ENDED")["params"]["samples"]
    assert samples == len(moving)  # what the audit counts is what rclpy received
    assert all(x == 0.0 for x in await after_sentinel_stream(rig))  # and then only zero


async def test_a_timed_move_whose_sender_vanished_ends_on_the_wire(rig: Rig) -> None:
    """599eb3c: 160 nonzero Twists over 7.95 s with nobody there and a 2 s timeout."""
    await subscribe(rig, CMD_VEL, TWIST)
    d = await rig.command(AGENT, {"action": "move",
                                  "params": {"linear_x": 0.5, "duration_s": 20.0}})
    assert d.http_status == 200, d
    await eventually(lambda: (d.message_id, "session_lost") in ended(rig), timeout=15)
    got = xs(await take(rig.oracle, CMD_VEL, until=lambda got: 0.0 in xs(got)))
    assert set(got[:got.index(0.0)]) == {0.5}
    assert all(x == 0.0 for x in await after_sentinel_stream(rig))


async def test_no_nonzero_sample_after_the_estop_reply(rig: Rig) -> None:
    await subscribe(rig, "/robot1/emergency_stop", "std_msgs/msg/Bool")
    await subscribe(rig, CMD_VEL, TWIST)
    await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.5}})
    await take(rig.oracle, CMD_VEL, until=lambda got: len(got) >= 5)  # streaming now
    estop = await rig.command(VIEWER, {"action": "estop"})
    assert estop.http_status == 200, estop
    await asyncio.sleep(10 / RATE_HZ)  # ten periods: any stray tick would be written by now
    assert (await rig.command(OPS, {"action": "clear_estop"})).http_status == 200
    got = await after_sentinel_stream(rig)
    first_zero = got.index(0.0)
    assert set(got[:first_zero]) <= {0.5}  # what was still in flight before it
    assert set(got[first_zero:]) == {0.0}, got  # after the e-stop: zero, and only zero
    assert [r for _, r in ended(rig)][:1] == ["estopped"]


@pytest.mark.parametrize("raw", [
    b'{"action": "estop", "params": {"reason": "person in path", "speed": 0}}',
    b'{"action": "estop", "action": "move", "params": {"linear_x": 0.3}}',
    b'{"message_type": 6, "safety_event": "ESTOP", "message_id": "not-a-uuid", "x": 1}',
], ids=["unknown-param", "duplicate-keys", "safety-with-junk"])
async def test_an_estop_with_junk_stops_the_robot(rig: Rig, raw: bytes) -> None:
    """Issue 23: on 599eb3c each of these was a 400 and the robot went on at 0.3 m/s."""
    await subscribe(rig, "/robot1/emergency_stop", "std_msgs/msg/Bool")
    await subscribe(rig, CMD_VEL, TWIST)
    await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.3}})
    await take(rig.oracle, CMD_VEL, until=lambda got: len(got) >= 3)  # streaming now
    estop = await rig.governor.decide(validate_command(raw), VIEWER)
    assert (estop.http_status, bool(estop.warnings)) == (200, True), estop
    bools = await take(rig.oracle, "/robot1/emergency_stop", until=lambda got: len(got) >= 1)
    assert bools[-1]["data"] is True
    assert (await rig.command(OPS, {"action": "clear_estop"})).http_status == 200
    got = await after_sentinel_stream(rig)
    assert 0.0 in got and set(got[got.index(0.0):]) == {0.0}, got


async def test_session_loss_mid_stream_sends_zero_and_nothing_after(rig: Rig) -> None:
    await subscribe(rig, CMD_VEL, TWIST)
    d = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.4}})  # held
    # No heartbeat: after session_timeout_s (1 s) the stream ends and zero goes out.
    got: list[Any] = await take(rig.oracle, CMD_VEL, until=lambda got: 0.0 in xs(got),
                                timeout=10)
    assert set(xs(got)[:xs(got).index(0.0)]) == {0.4}
    await eventually(lambda: (d.message_id, "session_lost") in ended(rig), timeout=10)
    assert any(e["event"] == "NETWORK_LOSS_SAFE_STOP" for e in rig.entries())
    await asyncio.sleep(10 / RATE_HZ)
    rest = xs(got)[xs(got).index(0.0):] + await after_sentinel_stream(rig)
    assert set(rest) == {0.0}, rest
