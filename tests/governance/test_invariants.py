"""§8 invariants: clamping and >10 % denial, finiteness, workspace, e-stop latch, idempotency."""

from __future__ import annotations

import asyncio
import logging
import math
import uuid
from pathlib import Path
from typing import Any

import pytest
from govhelpers import PLANNER, Harness, command
from hypothesis import given, settings
from hypothesis import strategies as st

from rcan_rtps.governance import outcomes
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.estop import EstopMachine, LatchFile
from rcan_rtps.governance.governor import Governor
from rcan_rtps.governance.idempotency import CONFLICT, DECIDED_BEFORE, Idempotency
from rcan_rtps.governance.invariants import (
    AccelerationLimit,
    AllOf,
    Check,
    DurationLimit,
    EstopGuard,
    JointGroups,
    VelocityLimit,
    Violation,
    Workspace,
    finite_numbers,
    strictly_inside,
)
from rcan_rtps.governance.streams import AccelLimits, Velocity
from rcan_rtps.rcan import (
    ActionParams,
    ArmJointParams,
    MoveParams,
    NavigateParams,
    NoParams,
    NormalizedCommand,
    Outcome,
)

finite = st.floats(min_value=-1e9, max_value=1e9, allow_nan=False)
limits = st.floats(min_value=0.01, max_value=10.0)
MOVE = command("move")


@settings(max_examples=300)
@given(lin=limits, ang=limits, x=finite, y=finite, z=finite, deny=st.booleans())
def test_applied_velocity_never_exceeds_its_limit(
    lin: float, ang: float, x: float, y: float, z: float, deny: bool
) -> None:
    check = VelocityLimit(lin, ang, deny)
    try:
        applied = check(MOVE, MoveParams(linear_x=x, linear_y=y, angular_z=z))
    except Violation as v:
        assert v.rejection == outcomes.VELOCITY_LIMIT
        assert deny and (abs(x) > lin * 1.1 or abs(y) > lin * 1.1 or abs(z) > ang * 1.1)
        return
    assert isinstance(applied, MoveParams)
    assert abs(applied.linear_x) <= lin and abs(applied.linear_y) <= lin
    assert abs(applied.angular_z) <= ang
    if deny:
        assert max(abs(x), abs(y)) <= lin * 1.1 and abs(z) <= ang * 1.1
    if abs(x) <= lin:
        assert applied.linear_x == x  # within limits nothing changes


@given(bad=st.sampled_from([math.nan, math.inf, -math.inf]), field=st.integers(0, 2))
def test_non_finite_never_passes_the_invariants(bad: float, field: int) -> None:
    values = [0.0, 0.0, 0.0]
    values[field] = bad
    params = MoveParams(*values)  # built directly: as if the schema had been bypassed
    policy = AllOf(finite_numbers, VelocityLimit(1.0, 1.0, False))
    with pytest.raises(Violation) as info:
        policy(MOVE, params)
    assert info.value.rejection == outcomes.INVALID_VALUE
    with pytest.raises(Violation):
        VelocityLimit(1.0, 1.0, False)(MOVE, params)  # even alone


def test_bools_posing_as_numbers_are_refused() -> None:
    with pytest.raises(Violation):
        finite_numbers(MOVE, MoveParams(linear_x=True))  # type: ignore[arg-type]


SQUARE = [(-10.0, -10.0), (10.0, -10.0), (10.0, 10.0), (-10.0, 10.0)]
NAV = command("navigate", {"x": 0, "y": 0, "yaw": 0})


@pytest.mark.parametrize(
    ("point", "inside"),
    [((0, 0), True), ((9.99, 9.99), True), ((10, 0), False), ((10, 10), False),
     ((-10.01, 0), False), ((0, 1e9), False)],
)
def test_point_in_square(point: tuple[float, float], inside: bool) -> None:
    assert strictly_inside(point, SQUARE) is inside


def test_concave_workspace() -> None:
    ell = [(0.0, 0.0), (4.0, 0.0), (4.0, 1.0), (1.0, 1.0), (1.0, 4.0), (0.0, 4.0)]
    assert strictly_inside((0.5, 3.0), ell) and strictly_inside((3.0, 0.5), ell)
    assert not strictly_inside((3.0, 3.0), ell)


@pytest.mark.parametrize(
    "polygon",
    [[(0.0, 0.0), (1.0, 1.0)], [(0.0, 0.0), (1.0, 1.0), (2.0, 2.0)],
     [(0.0, 0.0), (2.0, 2.0), (2.0, 0.0), (0.0, 2.0)], [(0.0, 0.0), (1.0, 0.0), (1.0, math.nan)]],
)
def test_degenerate_workspace_fails_closed(polygon: list[tuple[float, float]]) -> None:
    with pytest.raises(Violation) as info:
        Workspace(polygon, "map")(NAV, NavigateParams(x=0.5, y=0.1, yaw=0))
    assert info.value.rejection == outcomes.WORKSPACE_VIOLATION


def test_goal_in_another_frame_is_refused() -> None:
    check = Workspace(SQUARE, "map")
    assert check(NAV, NavigateParams(x=1, y=1, yaw=0, frame_id="map"))
    with pytest.raises(Violation):
        check(NAV, NavigateParams(x=1, y=1, yaw=0, frame_id="odom"))
    assert Workspace(None, "map")(NAV, NavigateParams(x=1e6, y=0, yaw=0))  # none configured


@pytest.mark.logs_traceback  # (a fault injected on purpose)
def test_any_exception_in_a_check_denies() -> None:
    def broken(*_: object) -> NoParams:
        raise KeyError("oops")

    with pytest.raises(Violation) as info:
        AllOf(finite_numbers, broken)(command("stop"), NoParams())
    assert info.value.rejection == outcomes.SAFETY_CHECK_ERROR


# -- parameters a check cannot read: refused, never passed -------------------------------------


class Standstill:
    commanded = Velocity()


class TextVelocity(ActionParams, frozen=True):
    linear_x: str = "fast"  # the right name, a kind the velocity check cannot limit
    linear_y: float = 0.0
    angular_z: float = 0.0
    duration_s: float | None = None


class Blob(ActionParams, frozen=True):
    data: bytes = b"\x00"  # no number the finite check could walk to


ARM = ArmJointParams(joints=["elbow"], positions=[0.1], duration_s=1.0)
GOAL = NavigateParams(x=1.0, y=1.0, yaw=0.0)
FOREIGN: list[tuple[str, Check, Any]] = [
    ("velocity", VelocityLimit(1.0, 1.0, True), GOAL),
    ("velocity", VelocityLimit(1.0, 1.0, True), TextVelocity()),
    ("duration", DurationLimit(30.0), GOAL),
    ("acceleration", AccelerationLimit(AccelLimits(1.0, 1.0), Standstill()), ARM),
    ("workspace", Workspace(SQUARE, "map"), MoveParams(linear_x=0.5)),
    ("workspace", Workspace(None, "map"), MoveParams(linear_x=0.5)),  # no fence: still read
    ("joint_group", JointGroups({}), GOAL),
    ("finite", finite_numbers, {"linear_x": 9.0}),  # not an action's parameters at all
    ("finite", finite_numbers, Blob()),
]


@pytest.mark.parametrize(("name", "check", "params"), FOREIGN,
                         ids=[f"{n}-{type(p).__name__}" for n, _, p in FOREIGN])
def test_a_check_refuses_parameters_it_cannot_read(name: str, check: Check, params: Any,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    with pytest.raises(Violation) as info:
        check(command("move"), params)
    assert info.value.rejection == outcomes.PARAMS_NOT_UNDERSTOOD
    assert info.value.rejection.deny_reason == "COMMAND_REJECTED:params_not_understood"
    assert f"{name} check" in str(info.value)
    [record] = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert record.exc_info is None  # a clear line, no traceback


def test_checks_that_read_nothing_need_nothing() -> None:
    class Latch:
        latched = False

    assert EstopGuard(Latch())(command("navigate", {"x": 0, "y": 0, "yaw": 0}), NoParams())


async def test_the_governor_refuses_and_audits_unreadable_parameters(
    harness: Harness, gov: Governor
) -> None:
    """A navigate carrying a move's parameters: on main the workspace check passed it."""
    mixed = NormalizedCommand(action="navigate", params=MoveParams(linear_x=0.3),
                              requested={"linear_x": 0.3}, message_id=str(uuid.uuid4()))
    decision = await gov.decide(mixed, PLANNER)
    assert (decision.http_status, decision.outcome, decision.reason) == (
        409, Outcome.DENIED, "params_not_understood")
    assert harness.dispatcher.calls == []
    entry = harness.entries[-1]
    assert (entry["event"], entry["action_type"], entry["deny_reason"]) == (
        "COMMAND_REJECTED", "navigate", "COMMAND_REJECTED:params_not_understood")
    assert entry["audit_id"] == decision.audit_id
    assert "COMMAND_DISPATCHED" not in [e["event"] for e in harness.entries]


def _loaded(path: Path, first_start: bool = False) -> bool:
    return LatchFile(path).load(first_start=first_start)[0]


async def test_estop_latch_persists(tmp_path: Path) -> None:
    state = tmp_path / "estop.state"
    assert not _loaded(state, first_start=True)
    await LatchFile(state).write(True, "ops", 1)
    assert _loaded(state)
    await LatchFile(state).write(False, "ops", 2)
    assert not _loaded(state)
    state.write_text('{"latched": "no"}')
    assert _loaded(state)  # anything odd: latched


async def test_a_latch_found_at_start_says_it_is_the_e_stop(tmp_path: Path) -> None:
    # `run` logs this reason as an ERROR line of its own: "latched by ops …" named no e-stop
    state = tmp_path / "estop.state"
    await LatchFile(state).write(True, "ops", 1)
    latched, why = LatchFile(state).load(first_start=False)
    assert latched and why == "e-stop latched by ops before this start; held until a clear_estop"


async def test_missing_latch_file_is_latched_unless_first_start(tmp_path: Path) -> None:
    state = tmp_path / "estop.state"
    latched, why = LatchFile(state).load(first_start=False)
    assert latched and why is not None and "missing" in why
    assert LatchFile(state).load(first_start=True) == (False, None)


async def test_clear_that_cannot_persist_stays_latched(tmp_path: Path) -> None:
    from rcan_rtps.governance.errors import EstopStateError

    file = LatchFile(tmp_path / "missing-dir" / "estop.state")
    machine = EstopMachine(file, latched=True)

    async def clear() -> bool:
        await file.write(False, "ops", 1)
        return machine.unlatch()

    with pytest.raises(EstopStateError):
        await machine.clear(clear)
    assert machine.latched
    await machine.close()  # its worker must not be left pending for the collector


async def test_clear_followed_by_an_estop_stays_latched(tmp_path: Path) -> None:
    machine = EstopMachine(LatchFile(tmp_path / "estop.state"), latched=True)
    order: list[str] = []

    async def clear() -> bool:
        await asyncio.sleep(0.01)  # an e-stop arrives meanwhile
        order.append("clear")
        return machine.unlatch()

    async def engage() -> None:
        order.append("estop")

    cleared = machine.clear(clear)
    await asyncio.sleep(0)
    engaged = machine.engage(engage)
    assert await cleared is False and machine.latched
    await engaged
    assert order == ["clear", "estop"] and machine.latched
    await machine.close()


async def test_idempotency_window_and_abandon() -> None:
    clock = ManualClock()
    cache: Idempotency[str, int] = Idempotency(clock, ttl_s=600)
    assert cache.claim("a", b"f") is None
    assert cache.claim("a", b"other") is CONFLICT
    waiting = cache.claim("a", b"f")
    assert waiting is not None and not waiting.done()
    cache.resolve("a", 7)
    assert await waiting == 7
    clock.advance(600.5)
    assert cache.claim("a", b"f") is None  # window over: a new first time
    cache.abandon("a", RuntimeError("x"))
    assert cache.claim("a", b"f") is None  # an abandoned attempt may run again
    await asyncio.sleep(0)


async def test_idempotency_is_bounded_in_size() -> None:
    cache: Idempotency[int, int] = Idempotency(ManualClock(), ttl_s=600, max_entries=100)
    for key in range(10_000):
        assert cache.claim(key, b"f") is None
        cache.resolve(key, key)
    assert len(cache) <= 100
    assert cache.claim(9_999, b"f") is not None  # the newest are still remembered


async def test_keys_an_earlier_run_decided_are_refused_for_the_rest_of_their_ttl() -> None:
    clock = ManualClock()
    cache: Idempotency[str, int] = Idempotency(clock, ttl_s=600, max_entries=3)
    assert cache.remember_decided([("old", 590.0), ("gone", 600.0), ("ahead", -5.0),
                                   ("b", 1.0), ("c", 2.0), ("d", 3.0)]) == 3
    assert cache.claim("gone", b"f") is None  # its ttl was over at start
    assert cache.claim("ahead", b"f") is DECIDED_BEFORE  # logged by a clock ahead: its ttl
    assert cache.claim("old", b"f") is DECIDED_BEFORE
    assert cache.claim("old", b"other") is DECIDED_BEFORE  # whatever it is now
    assert cache.claim("d", b"f") is None  # past max_entries: not remembered
    clock.advance(10.0)
    assert cache.claim("old", b"f") is None  # its 600 s are over: a new first time
    assert cache.claim("b", b"f") is DECIDED_BEFORE


def test_a_declared_flag_is_no_number_posing_as_one() -> None:
    """A `bool` field (dock's navigate_to_staging_pose) passes the finite check; a bool in
    a number's field still does not (above)."""
    dock = command("dock", {"dock_id": "home", "navigate_to_staging_pose": False})
    assert finite_numbers(dock, dock.params) is dock.params
