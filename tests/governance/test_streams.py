"""Velocity streams (issue 11) through the governor, on a manual loop timer.

Properties over random sequences of move / replace / stop / estop / clear / session loss /
time passing: every velocity on the wire is within the velocity limits, changes by at most one
acceleration step per sample unless it is a stop (zero), and nothing but zero goes out from an
e-stop's reply until a clear. Then many interleavings of an e-stop racing moves.
"""

from __future__ import annotations

import asyncio
import math
import random
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from govhelpers import OPS, PLANNER, VIEWER, audit_entries, command, principal
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from streamhelpers import (
    ANGULAR_ACCEL,
    LINEAR_ACCEL,
    MAX_ANGULAR,
    MAX_LINEAR,
    RATE_HZ,
    ManualTimer,
    Wire,
    stream_governor,
)

from rcan_rtps.governance.audit import AuditLog
from rcan_rtps.governance.governor import Governor
from rcan_rtps.governance.streams import Velocity
from rcan_rtps.rcan import Outcome, Role

EPS = 1e-9
STEP_LIN, STEP_ANG = LINEAR_ACCEL / RATE_HZ, ANGULAR_ACCEL / RATE_HZ

speeds = st.floats(-1.05 * MAX_LINEAR, 1.05 * MAX_LINEAR)  # up to the clamp, short of a denial
turns = st.floats(-1.05 * MAX_ANGULAR, 1.05 * MAX_ANGULAR)
moves = st.tuples(st.just("move"), st.fixed_dictionaries(
    {"linear_x": speeds, "angular_z": turns},
    optional={"linear_y": speeds, "duration_s": st.floats(0.05, 3.0)}))
operations = st.one_of(
    moves,
    st.tuples(st.sampled_from(["stop", "estop", "clear_estop", "session_lost"]), st.just({})),
    st.tuples(st.just("wait"), st.floats(0.0, 1.5)),
)


def check_wire(wire: list[Velocity]) -> None:
    previous = Velocity()
    for i, v in enumerate(wire):
        assert abs(v.linear_x) <= MAX_LINEAR + EPS and abs(v.linear_y) <= MAX_LINEAR + EPS, (i, v)
        assert abs(v.angular_z) <= MAX_ANGULAR + EPS, (i, v)
        if v != Velocity():  # a stop is zero at once; anything else ramps
            assert abs(v.linear_x - previous.linear_x) <= STEP_LIN + EPS, (i, previous, v)
            assert abs(v.linear_y - previous.linear_y) <= STEP_LIN + EPS, (i, previous, v)
            assert abs(v.angular_z - previous.angular_z) <= STEP_ANG + EPS, (i, previous, v)
        previous = v


async def _run(ops: list[tuple[str, Any]], tmp: Path) -> None:
    gov, wire, timer, log = await stream_governor(tmp)
    estopped_at: int | None = None  # wire length when the e-stop replied
    try:
        for name, arg in ops:
            if name == "wait":
                timer.advance(arg)
            elif name == "session_lost":
                await gov.safe_stop(PLANNER, "test")
            else:
                who = VIEWER if name == "estop" else OPS if name == "clear_estop" else PLANNER
                body = dict(arg)
                d = await gov.decide(command(name, body), who)
                if name == "estop":
                    assert d.outcome is Outcome.EXECUTED
                    estopped_at = len(wire.wire) if estopped_at is None else estopped_at
                elif name == "clear_estop" and estopped_at is not None:
                    assert all(v == Velocity() for v in wire.wire[estopped_at:])
                    estopped_at = None
            if estopped_at is not None:
                assert all(v == Velocity() for v in wire.wire[estopped_at:]), (name, arg)
                assert gov.streams.active is None
            check_wire(wire.wire)
    finally:
        gov.end_streams()
        await asyncio.gather(*gov._tasks)
        await gov.latch.close()
        await log.close()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(operations, min_size=1, max_size=25))
def test_every_sample_is_within_the_velocity_and_acceleration_limits(
        ops: list[tuple[str, Any]]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        asyncio.run(_run(ops, Path(tmp)))


# -- plain cases --------------------------------------------------------------------------------


# What `_governor` made in the test under way, ended after it (`_end_governors`).
_made: list[tuple[Governor, AuditLog]] = []


@pytest.fixture(autouse=True)
async def _end_governors() -> AsyncIterator[None]:
    """Each governor a test made ends after it, its tasks and e-stop machine done: one
    dropped with its machine's worker pending leaves it to the garbage collector, which logs
    'Task was destroyed but it is pending!' (tests/asyncio_log_guard.py)."""
    yield
    made = list(_made)
    _made.clear()
    for gov, log in made:
        gov.end_streams()
        await asyncio.gather(*gov._tasks, return_exceptions=True)
        await gov.latch.close()
        await log.close()


async def _governor(tmp: Path, **kw: Any) -> tuple[Governor, Wire, ManualTimer]:
    gov, wire, timer, log = await stream_governor(tmp, **kw)
    _made.append((gov, log))
    return gov, wire, timer


async def _settled(gov: Governor) -> list[dict[str, Any]]:
    await asyncio.gather(*gov._tasks)
    return audit_entries(Path(gov.audit.path))


async def test_a_timed_move_streams_at_the_rate_then_sends_zero(tmp_path: Path) -> None:
    gov, wire, timer = await _governor(tmp_path, linear_accel=1000.0)
    d = await gov.decide(command("move", {"linear_x": 0.5, "duration_s": 2.0}), PLANNER)
    assert d.outcome is Outcome.EXECUTED and d.applied is not None
    assert d.applied["duration_s"] == 2.0
    timer.advance(3.0)
    nonzero = [v for v in wire.wire if v != Velocity()]
    assert len(nonzero) == round(2.0 * RATE_HZ)  # one each 1/rate s, the first at once
    assert all(v.linear_x == 0.5 for v in nonzero)
    assert wire.wire[-1] == Velocity() and wire.wire.index(Velocity()) == len(nonzero)
    ended = [e for e in await _settled(gov) if e["event"] == "STREAM_ENDED"]
    assert [(e["params"]["reason"], e["params"]["samples"], e["message_id"]) for e in ended] == [
        ("completed", len(nonzero), d.message_id)]
    assert ended[0]["applied"] == {"last": {"linear_x": 0.5, "linear_y": 0.0, "angular_z": 0.0},
                                   "zero_sent": True}


async def test_the_ramp_is_what_is_applied_and_audited(tmp_path: Path) -> None:
    gov, wire, timer = await _governor(tmp_path)
    d = await gov.decide(command("move", {"linear_x": 1.0}), PLANNER)
    assert d.applied is not None
    assert (d.applied["ramp_from"], d.applied["ramp_s"]) == ([0.0, 0.0, 0.0], 1.0 / LINEAR_ACCEL)
    timer.advance(0.2)
    now = wire.wire[-1].linear_x  # still ramping up
    d2 = await gov.decide(command("move", {"linear_x": -1.0}), PLANNER)  # replaces, ramps down
    assert d2.applied is not None
    assert 0 < now < 1.0 and d2.applied["ramp_from"] == [now, 0.0, 0.0]
    assert math.isclose(wire.wire[-1].linear_x, now - STEP_LIN)
    assert math.isclose(d2.applied["ramp_s"], (now + 1.0) / LINEAR_ACCEL)
    entry = next(e for e in await _settled(gov) if e["audit_id"] == d2.audit_id)
    assert entry["applied"] == d2.applied
    timer.advance(2.0)
    assert wire.wire[-1].linear_x == -1.0  # held: it got there within the limits
    check_wire(wire.wire)


async def test_a_timed_move_longer_than_the_limit_is_denied(tmp_path: Path) -> None:
    gov, wire, _ = await _governor(tmp_path)
    d = await gov.decide(command("move", {"linear_x": 0.5, "duration_s": 10.5}), PLANNER)
    assert (d.http_status, d.outcome, d.reason) == (409, Outcome.SAFETY_VIOLATION,
                                                    "duration_limit")
    assert wire.wire == []


@pytest.mark.parametrize("how", ["stop", "estop", "session_lost"])
async def test_every_end_sends_zero_at_once_and_is_audited(tmp_path: Path, how: str) -> None:
    gov, wire, timer = await _governor(tmp_path)
    d = await gov.decide(command("move", {"linear_x": 0.5}), PLANNER)
    timer.advance(1.0)
    if how == "session_lost":
        await gov.safe_stop(PLANNER, "test")
    else:
        await gov.decide(command(how), VIEWER if how == "estop" else PLANNER)
    sent = len(wire.wire)
    timer.advance(5.0)
    assert len(wire.wire) == sent and wire.wire[-1] == Velocity()  # nothing after the zero
    reason = {"stop": "stopped", "estop": "estopped", "session_lost": "session_lost"}[how]
    ended = [e for e in await _settled(gov) if e["event"] == "STREAM_ENDED"]
    assert [(e["params"]["reason"], e["message_id"]) for e in ended] == [(reason, d.message_id)]


# -- e-stop racing moves ------------------------------------------------------------------------


async def _after(turns: int, coro: Any) -> Any:
    for _ in range(turns):
        await asyncio.sleep(0)
    return await coro


async def _estop(gov: Governor, wire: Wire, turns: int, replied: list[int]) -> None:
    await _after(turns, gov.decide(command("estop"), VIEWER))
    replied.append(len(wire.wire))  # what had been sent when the e-stop replied


async def test_estop_racing_moves_leaves_nothing_moving(tmp_path: Path) -> None:
    gov, wire, timer = await _governor(tmp_path)
    rng = random.Random(20261125)
    for trial in range(200):
        moves = [_after(rng.randrange(12), gov.decide(
            command("move", {"linear_x": rng.uniform(-1, 1)}),
            principal(f"p{trial}-{i}", Role.USER))) for i in range(rng.randrange(1, 4))]
        replied: list[int] = []
        await asyncio.gather(_estop(gov, wire, rng.randrange(12), replied), *moves)
        timer.advance(rng.uniform(0, 0.5))
        assert all(v == Velocity() for v in wire.wire[replied[0]:]), trial
        assert gov.streams.active is None and gov.latch.latched, trial
        await gov.decide(command("clear_estop"), OPS)
        check_wire(wire.wire)
    await _settled(gov)


async def test_robot_loss_ends_the_stream_and_is_audited(tmp_path: Path) -> None:
    gov, wire, timer = await _governor(tmp_path)
    d = await gov.decide(command("move", {"linear_x": 0.5}), PLANNER)
    timer.advance(0.5)
    wire.available = False  # the robot's reader left: the next sample cannot go
    timer.advance(0.5)
    assert gov.streams.active is None
    sent = len(wire.wire)
    timer.advance(2.0)
    assert len(wire.wire) == sent
    ended = [e for e in await _settled(gov) if e["event"] == "STREAM_ENDED"]
    assert [(e["params"]["reason"], e["message_id"]) for e in ended] == [
        ("robot_lost", d.message_id)]
