"""Issue 23 item 3: one arbiter for the base. Streams and goals share owners, priorities and
locks; a refused command opens no control session; a timed move is held like any other.

The config (streamhelpers): USER 10, OWNER and CREATOR 50, principal `low-agent` 1; locks
`teleop` (50) and `top` (1000); session timeout 2 s (the default).
"""

from __future__ import annotations

import asyncio
import shutil
import tempfile
from pathlib import Path
from typing import Any

import pytest
from govhelpers import ADMIN, OPS, PLANNER, VIEWER, audit_entries, command, principal
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule
from streamhelpers import ManualTimer, stream_governor

from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.governor import MAX_IN_FLIGHT, Governor
from rcan_rtps.governance.streams import ZERO
from rcan_rtps.rcan import ErrorCode, Outcome, Role

LOW = principal("low-agent", Role.USER)
GOAL = {"x": 1.0, "y": 1.0, "yaw": 0.0}


def _advance(gov: Governor, timer: ManualTimer, seconds: float) -> None:
    clock = gov._clock
    assert isinstance(clock, ManualClock)
    clock.advance(seconds)
    timer.advance(seconds)


async def _settled(gov: Governor) -> None:
    await asyncio.gather(*gov._tasks)


async def test_a_higher_lock_cancels_a_lower_goal(tmp_path: Path) -> None:
    gov, wire, _, _ = await stream_governor(tmp_path)
    goal = await gov.decide(command("navigate", GOAL), PLANNER)
    assert goal.outcome is Outcome.EXECUTED and goal.goal_id == "goal-1"
    lock = await gov.decide(command("lock", {"name": "teleop"}), OPS)
    assert lock.outcome is Outcome.EXECUTED
    await _settled(gov)
    assert wire.cancelled == ["goal-1"]
    gov.goal_finished("goal-1", "canceled", server="/robot1/navigate_to_pose",
                      message_id=goal.message_id)
    await _settled(gov)
    finished = audit_entries(tmp_path / "audit.jsonl")[-1]
    assert (finished["event"], finished["deny_reason"]) == (
        "GOAL_FINISHED", "locked out by 'teleop' by ops")


@pytest.mark.parametrize("lower", [("navigate", GOAL), ("move", {"linear_x": 0.2})])
async def test_nothing_lower_is_accepted_while_a_higher_goal_runs(
        tmp_path: Path, lower: tuple[str, dict[str, Any]]) -> None:
    gov, wire, _, _ = await stream_governor(tmp_path)
    assert (await gov.decide(command("navigate", GOAL), OPS)).outcome is Outcome.EXECUTED
    sent = len(wire.calls)
    d = await gov.decide(command(*lower), PLANNER)
    assert (d.http_status, d.reason) == (409, "lower_priority")
    assert len(wire.calls) == sent and wire.cancelled == []
    gov.goal_finished("goal-1", "succeeded", server="nav", message_id=None)  # base free again
    assert (await gov.decide(command(*lower), PLANNER)).outcome is Outcome.EXECUTED


async def test_a_higher_move_preempts_a_lower_goal_and_an_equal_goal_replaces(
        tmp_path: Path) -> None:
    gov, wire, _, _ = await stream_governor(tmp_path)
    await gov.decide(command("navigate", GOAL), PLANNER)
    assert (await gov.decide(command("move", {"linear_x": 0.3}), OPS)).outcome is \
        Outcome.EXECUTED
    await _settled(gov)
    assert wire.cancelled == ["goal-1"]
    second = await gov.decide(command("navigate", GOAL), ADMIN)  # 50, like ops: replaces
    assert second.outcome is Outcome.EXECUTED
    assert gov.streams.active is None and set(gov.streams.goals) == {"goal-2"}


async def test_a_refused_move_opens_no_session(tmp_path: Path) -> None:
    """599eb3c: the refused lower move's session lapsed 2 s later and halted the locked,
    higher-priority stream."""
    gov, wire, timer, _ = await stream_governor(tmp_path)
    await gov.decide(command("lock", {"name": "teleop"}), OPS)
    assert (await gov.decide(command("move", {"linear_x": 0.4}), OPS)).outcome is \
        Outcome.EXECUTED
    refused = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert refused.reason == "motion_locked"
    for _ in range(10):  # ops heartbeats; planner is silent
        _advance(gov, timer, 0.5)
        gov.heartbeat(OPS)
        await gov.sweep()
    await _settled(gov)
    assert gov.streams.active is not None and gov.streams.active.owner == "ops"
    events = [e["event"] for e in audit_entries(tmp_path / "audit.jsonl")]
    assert "NETWORK_LOSS_SAFE_STOP" not in events
    assert wire.wire[-1].linear_x > 0  # still driving


async def test_a_lower_senders_lost_session_leaves_the_higher_stream(tmp_path: Path) -> None:
    gov, wire, timer, _ = await stream_governor(tmp_path)
    low_goal = await gov.decide(command("navigate", GOAL), LOW)  # low-agent: 1
    assert low_goal.outcome is Outcome.EXECUTED
    await gov.decide(command("move", {"linear_x": 0.4}), OPS)  # preempts the goal
    for _ in range(6):
        _advance(gov, timer, 0.5)
        gov.heartbeat(OPS)
        await gov.sweep()
    await _settled(gov)
    assert gov.streams.active is not None and gov.streams.active.owner == "ops"
    [lost] = [e for e in audit_entries(tmp_path / "audit.jsonl")
              if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert (lost["principal"], lost["applied"]["scope"]) == ("low-agent", "own")
    assert [a for a, _ in wire.calls].count("stop") == 0  # no halt of the base


async def test_a_timed_move_ends_when_its_sender_goes_silent(tmp_path: Path) -> None:
    """599eb3c: a 30 s timed move streamed on for its whole duration with nobody there."""
    gov, wire, timer, _ = await stream_governor(tmp_path)
    d = await gov.decide(command("move", {"linear_x": 0.3, "duration_s": 8}), PLANNER)
    assert d.outcome is Outcome.EXECUTED
    for _ in range(5):
        _advance(gov, timer, 0.5)
        await gov.sweep()
    await _settled(gov)
    assert gov.streams.active is None
    ended = [e for e in audit_entries(tmp_path / "audit.jsonl") if e["event"] == "STREAM_ENDED"]
    assert [e["params"]["reason"] for e in ended] == ["session_lost"]
    assert wire.wire[-1] == ZERO


async def test_a_heartbeating_timed_move_runs_to_its_end(tmp_path: Path) -> None:
    gov, _, timer, _ = await stream_governor(tmp_path)
    await gov.decide(command("move", {"linear_x": 0.3, "duration_s": 3}), PLANNER)
    for _ in range(8):
        _advance(gov, timer, 0.5)
        gov.heartbeat(PLANNER)
        await gov.sweep()
    await _settled(gov)
    ended = [e for e in audit_entries(tmp_path / "audit.jsonl") if e["event"] == "STREAM_ENDED"]
    assert [e["params"]["reason"] for e in ended] == ["completed"]


# -- the model --------------------------------------------------------------------------------

WHO = [LOW, PLANNER, OPS, ADMIN]
MOVERS = set(WHO)  # the principals whose role may move (VIEWER, a GUEST, may not)


class BaseModel(RuleBasedStateMachine):
    """Streams, goals, arm trajectories, locks, priorities, e-stop, clear and session loss (with
    moves waiting their turn, or not), in any order: the base never has two owners, nothing
    moves while the e-stop is latched, a stop leaves no arm running, and a session loss holds
    its principal's arms (and only theirs, unless it halts the robot)."""

    def __init__(self) -> None:
        super().__init__()
        self.loop = asyncio.new_event_loop()
        self.tmp = Path(tempfile.mkdtemp(prefix="base-model-"))
        self.gov, self.wire, self.timer, _ = self.run(stream_governor(self.tmp))
        self.run(self.gov.start())
        self.latched_at: int | None = None  # wire length when the e-stop latched
        self.arm_owner: dict[str, str] = {}  # an arm trajectory's message id → who sent it

    def run(self, coro: Any) -> Any:
        return self.loop.run_until_complete(coro)

    def decide(self, action: str, params: dict[str, Any], who: Any) -> Any:
        d = self.run(self.gov.decide(command(action, params), who))
        self.run(_settled(self.gov))
        return d

    @rule(who=st.sampled_from(WHO), x=st.floats(-1.0, 1.0),
          timed=st.sampled_from([None, 1.0, 5.0]))
    def move(self, who: Any, x: float, timed: float | None) -> None:
        params: dict[str, Any] = {"linear_x": x}
        if timed:
            params["duration_s"] = timed
        self.decide("move", params, who)

    @rule(who=st.sampled_from(WHO))
    def navigate(self, who: Any) -> None:
        self.decide("navigate", GOAL, who)

    @rule(who=st.sampled_from(WHO), joint=st.sampled_from(["elbow", "wrist"]))
    def arm(self, who: Any, joint: str) -> None:
        """A trajectory on one of two arms (the double gives each its own topic): it runs on
        until a stop holds it, its time is up, or the next on that arm replaces it."""
        decided = self.decide("arm_joint", {"joints": [joint], "positions": [0.5],
                                            "duration_s": 30.0}, who)
        if decided.outcome is Outcome.EXECUTED:
            self.arm_owner[decided.message_id] = who.name

    @precondition(lambda self: bool(self.wire.running))
    @rule(data=st.data())
    def a_trajectory_s_time_is_up(self, data: st.DataObject) -> None:
        self.wire.running.remove(data.draw(st.sampled_from(self.wire.running)))

    @rule(name=st.sampled_from(["teleop", "top"]), who=st.sampled_from([OPS, ADMIN]))
    def lock(self, name: str, who: Any) -> None:
        self.decide("lock", {"name": name}, who)

    @rule(name=st.sampled_from(["teleop", "top"]))
    def unlock(self, name: str) -> None:
        self.decide("unlock", {"name": name}, ADMIN)

    @rule(who=st.sampled_from([VIEWER, *WHO]))
    def estop(self, who: Any) -> None:
        assert self.decide("estop", {}, who).outcome is Outcome.EXECUTED
        self.latched_at = len(self.wire.wire)
        assert not self.wire.running  # every arm held

    @rule()
    def clear(self) -> None:
        assert self.decide("clear_estop", {}, OPS).outcome is Outcome.EXECUTED
        self.latched_at = None

    @rule(who=st.sampled_from(WHO))
    def stop(self, who: Any) -> None:
        self.decide("stop", {}, who)
        assert not self.wire.running  # every arm held

    @precondition(lambda self: bool(self.gov.streams.goals))
    @rule(data=st.data())
    def a_goal_ends(self, data: st.DataObject) -> None:
        goal_id = data.draw(st.sampled_from(sorted(self.gov.streams.goals)))

        async def finish() -> None:
            self.gov.goal_finished(goal_id, "succeeded", server="nav", message_id=None)
            await _settled(self.gov)

        self.run(finish())

    @rule(seconds=st.sampled_from([0.2, 1.0, 2.5]), beating=st.sets(st.sampled_from(WHO)))
    def time_passes(self, seconds: float, beating: set[Any]) -> None:
        async def passes() -> None:  # stream ticks run on the loop, as they do for real
            _advance(self.gov, self.timer, seconds)
            for who in beating:
                self.gov.heartbeat(who)
            await self.gov.sweep()
            await _settled(self.gov)

        self.run(passes())

    @rule(lost=st.sampled_from(WHO), waiting=st.sets(st.sampled_from([VIEWER, *WHO])))
    def a_session_is_lost_while_moves_wait(self, lost: Any, waiting: set[Any]) -> None:
        """`lost`'s session ends while moves of `waiting` wait their turn: a halt of the whole
        robot unless someone else's stream or goal holds the base or a move of someone else's
        whose role may move (not VIEWER's: a GUEST) is on its way. `lost`'s move never starts."""
        streams = self.gov.streams
        driving = {g.owner for g in streams.goals.values()}
        driving |= {streams.active.owner} if streams.active is not None else set()
        driving |= {self.arm_owner[m] for m in self.wire.running}  # an arm runs on
        others_arms = [m for m in self.wire.running if self.arm_owner[m] != lost.name]
        on_its_way = {w.name for w in waiting if w in MOVERS}
        narrowed = bool((driving | on_its_way) - {lost.name})

        async def lost_while_waiting() -> tuple[bool, dict[str, Any]]:
            for _ in range(MAX_IN_FLIGHT):  # every place taken: the moves wait their turn
                await self.gov._admission.acquire()
            moves = {w.name: asyncio.ensure_future(self.gov.decide(
                command("move", {"linear_x": 0.1}), w)) for w in waiting}
            await asyncio.sleep(0)  # each has arrived
            calls = len(self.wire.calls)
            await self.gov.safe_stop(lost, "silent")
            halted = "stop" in [a for a, _ in self.wire.calls[calls:]]
            for _ in range(MAX_IN_FLIGHT):
                self.gov._admission.release()
            decided = {name: await move for name, move in moves.items()}
            await _settled(self.gov)
            return halted, decided

        halted, decided = self.run(lost_while_waiting())
        assert halted is not narrowed, (lost.name, driving, [w.name for w in waiting])
        # Its arms are held, whoever else drives; a halt holds everyone's, else theirs run on.
        assert not any(self.arm_owner[m] == lost.name for m in self.wire.running)
        if not halted:
            assert set(others_arms) <= set(self.wire.running), (others_arms, self.wire.running)
        if VIEWER in waiting:
            assert decided[VIEWER.name].error_code is ErrorCode.INSUFFICIENT_PRIVILEGES
        if lost.name in decided:
            assert decided[lost.name].outcome is not Outcome.EXECUTED, decided[lost.name]

    @precondition(lambda self: bool(self.wire.running))
    @rule(data=st.data(), waiting=st.sets(st.sampled_from([VIEWER, *WHO])))
    def an_arm_s_sender_s_session_is_lost(self, data: st.DataObject, waiting: set[Any]) -> None:
        """As above, `lost` one whose arm runs (else rare): its arm is held, and another
        principal's arm, a stream or a goal makes it a stop of `lost`'s motion alone."""
        senders = sorted({self.arm_owner[m] for m in self.wire.running})
        name = data.draw(st.sampled_from(senders))
        self.a_session_is_lost_while_moves_wait(next(w for w in WHO if w.name == name), waiting)

    @invariant()
    def one_owner_of_the_base(self) -> None:
        streams = self.gov.streams
        drivers = len(streams.goals) + (streams.active is not None)
        assert drivers <= 1, (streams.active, streams.goals)

    @invariant()
    def nothing_moves_while_latched(self) -> None:
        if self.latched_at is None:
            return
        assert self.gov.latch.latched
        streams = self.gov.streams
        assert streams.active is None and not streams.goals
        assert all(v == ZERO for v in self.wire.wire[self.latched_at:])

    @invariant()
    def nothing_outranked_holds_the_base(self) -> None:
        streams = self.gov.streams
        held = [g.priority for g in streams.goals.values()]
        if streams.active is not None:
            held.append(streams.active.priority)
        assert all(p >= max(streams.locks.values(), default=0) for p in held)

    def teardown(self) -> None:
        self.run(self.gov.stop())
        self.run(self.gov.audit.close())
        self.loop.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


BaseModel.TestCase.settings = settings(
    max_examples=60, stateful_step_count=30, deadline=None,
    suppress_health_check=[HealthCheck.too_slow])
test_base_model = BaseModel.TestCase


async def test_cancelled_goals_that_never_end_are_not_remembered_forever(tmp_path: Path) -> None:
    """A goal the arbiter cancels is remembered until its end names who ended it; a server
    that vanished never reports that end, so what is remembered is bounded."""
    from rcan_rtps.governance.arbiter import ENDED_BY_KEPT
    from rcan_rtps.governance.streams import HeldGoal

    gov, wire, _, _ = await stream_governor(tmp_path)
    goals = [HeldGoal(f"lost-{n}", PLANNER.name, 10, f"m{n}") for n in range(ENDED_BY_KEPT + 50)]
    gov._base.cancel_goals(goals, OPS)
    await _settled(gov)
    assert len(wire.cancelled) == len(goals)  # every one was still cancelled
    assert len(gov._base._ended_by) == ENDED_BY_KEPT
    assert gov._base.goal_ended("lost-0") is None  # the oldest were let go
    assert gov._base.goal_ended(f"lost-{len(goals) - 1}") == "preempted by ops"


async def test_goals_cancelled_at_their_sender_s_request_are_not_remembered_forever(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same bound for a goal cancelled at its sender's request (INVOKE_CANCEL, an
    INVOKE's timeout): its end was remembered with no bound at all."""
    from rcan_rtps.governance import arbiter

    monkeypatch.setattr(arbiter, "ENDED_BY_KEPT", 8)
    gov, wire, _, _ = await stream_governor(tmp_path)
    for n in range(20):
        decided = await gov._base.cancel_requested(f"lost-{n}", OPS, message_id=f"m{n}",
                                                   why="invoke_cancel")
        assert decided.outcome is Outcome.EXECUTED
    assert len(wire.cancelled) == 20  # every one was still cancelled
    assert len(gov._base._ended_by) == 8
    assert gov._base.goal_ended("lost-0") is None  # the oldest were let go
    assert gov._base.goal_ended("lost-19") == "invoke_cancel by ops"


async def test_a_senders_end_of_one_stream_ends_that_stream_alone(tmp_path: Path) -> None:
    """`Governor.end_stream` (an INVOKE_CANCEL of a move, its timeout): the stream the named
    command of that principal started, never a move that replaced it nor anyone else's; its
    STREAM_ENDED says `cancelled`, by whom and why. Every end, recorded in an entry of its own
    or in the replacing move's, is told on `Events.stream_ended`."""
    gov, wire, _, _ = await stream_governor(tmp_path)
    told: list[tuple[str, str]] = []
    gov.events.stream_ended.subscribe(
        lambda ended: told.append((ended.stream.message_id, ended.reason.value)))
    one, two = command("move", {"linear_x": 0.2}), command("move", {"linear_x": 0.3})
    m1, m2 = one.message_id, two.message_id
    first, second = await gov.decide(one, PLANNER), await gov.decide(two, PLANNER)
    assert first.outcome is second.outcome is Outcome.EXECUTED
    assert told == [(m1, "replaced")]
    assert not gov.end_stream(m1, PLANNER, why="INVOKE_CANCEL")  # m-2 replaced it
    assert not gov.end_stream(m2, OPS, why="INVOKE_CANCEL")  # not ops's
    assert gov.streams.active is not None and gov.streams.active.message_id == m2
    assert wire.wire[-1] != ZERO and gov.stream_running(m2, PLANNER)
    assert gov.end_stream(m2, PLANNER, why="INVOKE_CANCEL")
    assert (gov.streams.active, wire.wire[-1], told[-1]) == (None, ZERO, (m2, "cancelled"))
    assert not gov.stream_running(m2, PLANNER)
    await _settled(gov)
    [ended] = [e for e in audit_entries(tmp_path / "audit.jsonl")
               if e["event"] == "STREAM_ENDED"]
    assert (ended["message_id"], ended["params"]["reason"], ended["params"]["ended_by"],
            ended["params"]["why"], ended["applied"]["zero_sent"]) == (
        m2, "cancelled", "planner", "INVOKE_CANCEL", True), ended
