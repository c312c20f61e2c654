"""E-stop and clear as one serialized state machine, attacked with many interleavings.

After every interleaving of an e-stop (any principal) and a clear (OWNER), four views must agree
with the audit order: the latch in memory, the latch file, the last value published to the robot,
and whether a motion command passes. The last of the two in the audit decides.
"""

from __future__ import annotations

import asyncio
import json
import random
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from govhelpers import ADMIN, OPS, PLANNER, VIEWER, Harness, command
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from rcan_rtps.governance import estop
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.governor import Decision, Governor
from rcan_rtps.rcan import Outcome, Reason

TRIALS = 1000
MOVE = {"linear_x": 0.1}


def _published(harness: Harness) -> bool | None:
    """The last e-stop value the robot was sent (True for estop, False for clear_estop)."""
    sent = [a == "estop" for a, _ in harness.dispatcher.calls if a in ("estop", "clear_estop")]
    return sent[-1] if sent else None


def _persisted(harness: Harness) -> bool:
    return bool(json.loads((harness.tmp / "estop.state").read_bytes())["latched"])


def _seq(harness: Harness, decision: Decision) -> int:
    return next(e["seq"] for e in harness.entries if e["audit_id"] == decision.audit_id)


async def _after(delay: float, coro: Any) -> Any:
    await asyncio.sleep(delay)
    return await coro


async def _race(gov: Governor, rng: random.Random, acks: list[str]) -> tuple[Decision, Decision]:
    async def estop() -> Decision:
        d = await _after(rng.uniform(0, 0.004), gov.decide(command("estop"), VIEWER))
        acks.append("estop")
        return d

    async def clear() -> Decision:
        d = await _after(rng.uniform(0, 0.004), gov.decide(command("clear_estop"), OPS))
        acks.append("clear")
        return d

    e, c = await asyncio.gather(estop(), clear())
    return e, c


def _estop_won(harness: Harness, estopped: Decision, cleared: Decision) -> bool:
    """Whether the e-stop of a race came last: after the clear in the log, or before the
    clear was decided (the clear refused then: it cleared nothing)."""
    if cleared.outcome is not Outcome.EXECUTED:
        assert (cleared.http_status, cleared.reason) == (409, Reason.ESTOP_ACTIVE.value)
        return True
    return _seq(harness, estopped) > _seq(harness, cleared)


@pytest.mark.slow  # a thousand races, each through the latch file: about a minute
async def test_estop_and_clear_interleavings_agree_everywhere(harness: Harness) -> None:
    gov = await harness.governor()
    rng = random.Random(20261124)
    outcomes: dict[bool, int] = {True: 0, False: 0}
    for trial in range(TRIALS):
        acks: list[str] = []
        e, c = await _race(gov, rng, acks)
        assert e.outcome is Outcome.EXECUTED, trial
        estop_last = _estop_won(harness, e, c)
        outcomes[estop_last] += 1
        # Acknowledgements in audit order; the later transition decides everything.
        assert acks == (["clear", "estop"] if estop_last else ["estop", "clear"]), trial
        assert gov.latch.latched is estop_last, trial
        assert _persisted(harness) is estop_last, trial
        assert _published(harness) is estop_last, trial
        moved = await gov.decide(command("move", MOVE), ADMIN)  # ADMIN: no rate limit
        assert (moved.outcome is Outcome.EXECUTED) is (not estop_last), trial
        if estop_last:
            assert moved.reason == Reason.ESTOP_ACTIVE.value
    assert min(outcomes.values()) > TRIALS // 10  # both orders were really exercised
    await gov.stop()
    assert _latched_by_the_log(harness.entries) == []


async def test_estop_arriving_during_a_clear_wins(harness: Harness,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """The exact shape of the reported bug: clear in progress, e-stop acknowledged after it.
    The clear's latch file is slow on the disk (its writer thread): the e-stop's, written
    after it on that thread, is the one that stays."""
    gov = await harness.governor()
    await gov.decide(command("estop"), VIEWER)
    held = _HeldClear(harness, monkeypatch, "latch_file")
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.wait_for(held.entered.wait(), 10)
    estopping = asyncio.ensure_future(gov.decide(command("estop"), VIEWER))
    await asyncio.sleep(0.01)
    assert not estopping.done()  # answered after the clear
    held.release()
    c, e = await clearing, await estopping
    assert _seq(harness, c) < _seq(harness, e)
    assert gov.latch.latched and _persisted(harness) and _published(harness) is True
    d = await gov.decide(command("move", MOVE), PLANNER)
    assert d.reason == Reason.ESTOP_ACTIVE.value
    assert [a for a, _ in harness.dispatcher.calls] == ["estop", "estop"]  # no `false` sent
    await gov.stop()


# -- a stateful model: estop / clear / race / move / stop / restart / lost latch file --------


class EstopModel(RuleBasedStateMachine):
    """Never movable after an acknowledged e-stop that no later clear follows."""

    def __init__(self) -> None:
        super().__init__()
        self.loop = asyncio.new_event_loop()
        self.tmp = Path(tempfile.mkdtemp(prefix="estop-model-"))
        self.harness = Harness(self.tmp, ManualClock())
        self.gov = self.run(self.harness.governor())
        self.run(self.gov.start())
        self.latched = False  # what the acknowledged transitions say, in audit order
        self.rng = random.Random(7)

    def run(self, coro: Any) -> Any:
        return self.loop.run_until_complete(coro)

    @rule(who=st.sampled_from([VIEWER, PLANNER, OPS]))
    def estop(self, who: Any) -> None:
        d = self.run(self.gov.decide(command("estop"), who))
        assert d.outcome is Outcome.EXECUTED
        self.latched = True

    @rule()
    def clear(self) -> None:
        d = self.run(self.gov.decide(command("clear_estop"), OPS))
        assert d.outcome is Outcome.EXECUTED
        self.latched = False

    @rule()
    def race(self) -> None:
        e, c = self.run(_race(self.gov, self.rng, []))
        self.latched = _estop_won(self.harness, e, c)

    @rule(delay=st.floats(min_value=0, max_value=0.004))
    def race_on_a_slow_disk(self, delay: float) -> None:
        """An e-stop, a clear and a move 0-6 ms apart, latch files taking `delay` to write: a
        move refused for the latch after the e-stop came is listed after its ESTOP entry."""
        write, came = estop.atomic_write, []

        def slow_write(path: Any, data: bytes, *args: Any) -> None:
            time.sleep(delay)
            write(path, data, *args)

        async def arriving(what: str, body: Any, who: Any) -> tuple[Decision, bool]:
            await asyncio.sleep(self.rng.uniform(0, 0.006))
            after_estop = "estop" in came
            came.append(what)  # the decision's first step (an e-stop's latch) is this one
            return await self.gov.decide(body, who), after_estop

        async def race() -> tuple[tuple[Decision, bool], ...]:
            return tuple(await asyncio.gather(
                arriving("estop", command("estop"), VIEWER),
                arriving("clear", command("clear_estop"), OPS),
                arriving("move", command("move", MOVE), ADMIN)))

        estop.atomic_write = slow_write  # type: ignore[assignment]
        try:
            (e, _), (c, _), (m, move_after_estop) = self.run(race())
        finally:
            estop.atomic_write = write
        self.latched = _estop_won(self.harness, e, c)
        if move_after_estop and m.reason == Reason.ESTOP_ACTIVE.value and e.reason is None:
            assert _seq(self.harness, e) < _seq(self.harness, m)
        self.run(self.gov.decide(command("stop"), ADMIN))  # a move that ran is stopped

    @rule(delay=st.floats(min_value=0, max_value=0.004),
          crowd=st.lists(st.sampled_from(["estop", "clear", "move", "sweep"]), min_size=2,
                         max_size=7))
    def crowd_on_a_slow_disk(self, delay: float, crowd: list[str]) -> None:
        """E-stops, clears, moves and the sweep that records e-stop repeats, 0-6 ms apart,
        latch files taking `delay` to write (two clears queued and an e-stop after them; an
        e-stop flood; repeats recorded while a clear waits). Whatever the order, the log
        agrees with itself (no refusal for the latch where it says unlatched, no motion where
        it says latched) and with the latch (the invariants); its last word decides it."""
        write = estop.atomic_write

        def slow_write(path: Any, data: bytes, *args: Any) -> None:
            time.sleep(delay)
            write(path, data, *args)

        bodies = {"estop": (command("estop"), VIEWER), "clear": (command("clear_estop"), OPS),
                  "move": (command("move", MOVE), ADMIN)}

        async def arriving(what: str) -> None:
            await asyncio.sleep(self.rng.uniform(0, 0.006))
            if what == "sweep":
                self.harness.clock.advance(61.0)  # the repeats have waited their minute
                await self.gov.sweep()
            else:
                await self.gov.decide(*bodies[what])

        async def crowd_arrives() -> None:
            await asyncio.gather(*(arriving(what) for what in crowd))
            await self.gov.latch.settled()

        estop.atomic_write = slow_write  # type: ignore[assignment]
        try:
            self.run(crowd_arrives())
        finally:
            estop.atomic_write = write
        self.latched = _latched_at_the_end(self.harness.entries, self.latched)
        self.run(self.gov.decide(command("stop"), ADMIN))  # a move that ran is stopped

    @invariant()
    def the_log_agrees_with_itself(self) -> None:
        entries = self.harness.entries
        shown = [(e["seq"], e["event"], e["action_type"], e["deny_reason"]) for e in entries]
        assert _refused_once_moving(entries) == [], shown
        assert _moved_while_latched(entries) == [], shown

    @rule(x=st.floats(min_value=-1.0, max_value=1.0))
    def move(self, x: float) -> None:
        d = self.run(self.gov.decide(command("move", {"linear_x": x}), ADMIN))
        if self.latched:
            assert (d.http_status, d.reason) == (409, Reason.ESTOP_ACTIVE.value)
        else:
            assert d.outcome is Outcome.EXECUTED

    @rule()
    def stop(self) -> None:
        assert self.run(self.gov.decide(command("stop"), PLANNER)).outcome is Outcome.EXECUTED

    @rule()
    def restart(self) -> None:
        self._restart()

    @precondition(lambda self: (self.tmp / "estop.state").exists())
    @rule()
    def lose_latch_file_and_restart(self) -> None:
        (self.tmp / "estop.state").unlink()
        self.latched = True  # a missing latch file fails closed
        self._restart()

    def _restart(self) -> None:
        self.run(self.gov.stop())
        self.run(self.harness.restart())
        before = len(self.harness.dispatcher.calls)
        self.gov = self.run(self.harness.governor())
        self.run(self.gov.start())
        self.run(self.gov.latch.settled())
        republished = [a for a, _ in self.harness.dispatcher.calls[before:]]
        assert ("estop" in republished) is self.latched  # a latched start tells the robot

    @invariant()
    def latch_agrees(self) -> None:
        assert self.gov.latch.latched is self.latched
        if (self.tmp / "estop.state").exists() and self.harness.entries:
            assert _persisted(self.harness) is self.latched

    def teardown(self) -> None:
        self.run(self.gov.stop())
        self.run(self.harness.restart())
        self.loop.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


EstopModel.TestCase.settings = settings(max_examples=30, stateful_step_count=25, deadline=None)
test_estop_model = EstopModel.TestCase


# -- an e-stop arriving while a clear is under way ---------------------------------------------


def _latched_by_the_log(entries: list[dict[str, Any]]) -> list[int]:
    """The seqs of commands refused for the latch at a point where the log says it was not
    latched (the last ESTOP, or a latched start, before them is followed by an ESTOP_CLEARED):
    none, if the log lists e-stops and refusals where they took effect."""
    latched, wrong = False, []
    for entry in entries:
        if entry["event"] == "BRIDGE_STARTED":  # a latch file lost: latched at start
            latched = entry["params"]["estop_latched"]
        elif entry["event"] == "ESTOP":
            latched = True
        elif entry["event"] == "ESTOP_CLEARED" and entry["outcome"] == "executed":
            latched = False
        elif entry["deny_reason"] == f"COMMAND_REJECTED:{Reason.ESTOP_ACTIVE.value}" and (
                entry["action_type"] != "clear_estop" and not latched):
            wrong.append(entry["seq"])
    return wrong


def _refused_once_moving(entries: list[dict[str, Any]]) -> list[int]:
    """The seqs of commands refused for the latch after the log shows motion sent since its
    last executed clear: none. (Refusals between that clear's entry and the first motion are
    not judged: a clear is sealed first and unlatches only once its latch file is durable,
    and a command refused meanwhile is listed after it — docs/governance.md. A refusal is
    sealed in the step it is decided, and no motion is sent before the unlatch.)"""
    from govhelpers import MOTION_ACTIONS

    latched, moving, wrong = False, False, []
    for entry in entries:
        if entry["event"] == "BRIDGE_STARTED":
            latched, moving = entry["params"]["estop_latched"], False
        elif entry["event"] == "ESTOP":
            latched, moving = True, False
        elif entry["event"] == "ESTOP_CLEARED" and entry["outcome"] == "executed":
            latched = False
        elif entry["event"] == "COMMAND_DISPATCHED" and entry["action_type"] in MOTION_ACTIONS:
            moving = True
        elif entry["deny_reason"] == f"COMMAND_REJECTED:{Reason.ESTOP_ACTIVE.value}" and (
                entry["action_type"] != "clear_estop" and not latched and moving):
            wrong.append(entry["seq"])
    return wrong


def _latched_at_the_end(entries: list[dict[str, Any]], before: bool) -> bool:
    """Latched or not, as the log's last e-stop or executed clear says (`before` if none)."""
    latched = before
    for entry in entries:
        if entry["event"] in ("ESTOP", "ESTOP_REPEATED"):
            latched = True
        elif entry["event"] == "ESTOP_CLEARED" and entry["outcome"] == "executed":
            latched = False
        elif entry["event"] == "BRIDGE_STARTED":
            latched = entry["params"]["estop_latched"]
    return latched


class _HeldClear:
    """Holds a clear at one point of its transition until released: `ready` (waiting for the
    robot, not yet decided), `latch_file` (audited, its latch file being written on the
    writer's thread: a slow disk) or `publish` (unlatched, `false` published and its send not
    yet returned)."""

    def __init__(self, harness: Harness, monkeypatch: pytest.MonkeyPatch, at: str) -> None:
        self.entered, self._release = asyncio.Event(), threading.Event()
        loop, dispatcher = asyncio.get_running_loop(), harness.dispatcher
        ready, dispatch, write = dispatcher.ready, dispatcher.dispatch, estop.atomic_write

        async def held_ready(command: Any) -> str | None:
            if command.action == "clear_estop" and at == "ready":
                await self._held()
            return await ready(command)

        async def held_dispatch(command: Any, applied: Any) -> Any:
            result = await dispatch(command, applied)  # published (recorded) first
            if command.action == "clear_estop" and at == "publish":
                await self._held()
            return result

        def held_write(path: Any, data: bytes, *args: Any) -> None:
            if b'"latched":false' in data and at == "latch_file":
                loop.call_soon_threadsafe(self.entered.set)
                assert self._release.wait(60), "never released"
            write(path, data, *args)

        monkeypatch.setattr(dispatcher, "ready", held_ready)
        monkeypatch.setattr(dispatcher, "dispatch", held_dispatch)
        monkeypatch.setattr(estop, "atomic_write", held_write)

    async def _held(self) -> None:
        self.entered.set()
        await asyncio.to_thread(self._release.wait, 60)

    def release(self) -> None:
        self._release.set()


@pytest.mark.parametrize("held_at", ["ready", "latch_file", "publish"])
async def test_an_estop_during_a_clear_wins_and_is_listed_where_it_took_effect(
        harness: Harness, monkeypatch: pytest.MonkeyPatch, held_at: str) -> None:
    """A clear under way (held at `held_at`), then an e-stop, then a move (refused: latched).
    The e-stop wins, whenever it came: latched in memory, in the latch file and on the robot.
    And the log says so where it happened: came before the clear was decided, the clear is
    refused (it cleared nothing); after, its ESTOP entry is sealed as it arrives, right after
    the clear's, before the move's refusal. It was sealed at its turn, once the clear was
    done: the move's refusal, and whatever else came meanwhile, was listed after
    ESTOP_CLEARED and before the ESTOP, as if refused while unlatched."""
    gov = await harness.governor()
    await gov.decide(command("estop"), VIEWER)
    held = _HeldClear(harness, monkeypatch, held_at)
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.wait_for(held.entered.wait(), 60)
    estopping = asyncio.ensure_future(gov.decide(command("estop"), VIEWER))
    await asyncio.sleep(0)  # the e-stop has arrived
    moved = await gov.decide(command("move", MOVE), ADMIN)
    assert moved.reason == Reason.ESTOP_ACTIVE.value, moved
    held.release()
    cleared, estopped = await clearing, await estopping
    await gov.stop()
    assert gov.latch.latched and _persisted(harness) and _published(harness) is True
    assert estopped.outcome is Outcome.EXECUTED, estopped
    entries = harness.entries
    assert _latched_by_the_log(entries) == [], [
        (e["seq"], e["event"], e["action_type"], e["deny_reason"]) for e in entries]
    if held_at == "ready":  # not decided when the e-stop came: nothing cleared
        assert (cleared.http_status, cleared.reason) == (409, Reason.ESTOP_ACTIVE.value)
        assert "ESTOP_CLEARED" not in [e["event"] for e in entries]
    else:
        assert cleared.outcome is Outcome.EXECUTED, cleared
        assert _seq(harness, cleared) < _seq(harness, estopped) < _seq(harness, moved)


async def test_a_move_refused_for_an_estop_arriving_during_a_clear_is_listed_after_it(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    """Unlatched; a clear under way, not yet decided (held waiting for the robot); an e-stop
    arrives — latched at once — and a move is refused for it. The refusal is listed after
    the ESTOP entry: before, that entry waited for its turn behind the clear, and the move's
    refusal was listed before it, where the log says the robot was unlatched (a clean-clone
    CI under load, the stateful model's race_on_a_slow_disk: ESTOP seq 4, the move's refusal
    3). A refusal then waited for the entry at most 2 s: a clear held longer (its disk
    stuck) still let it through first. Now the e-stop does not wait for a clear at all: its
    entry is sealed as it arrives, and a refusal waits for nothing."""
    gov = await harness.governor()
    held = _HeldClear(harness, monkeypatch, "ready")
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.wait_for(held.entered.wait(), 60)
    estopping = asyncio.ensure_future(gov.decide(command("estop"), VIEWER))
    await asyncio.sleep(0)  # the e-stop has arrived: latched
    assert gov.latch.latched
    moving = asyncio.ensure_future(gov.decide(command("move", MOVE), ADMIN))
    await asyncio.sleep(0.05)  # the move's decision under way (its refusal, before: sealed)
    held.release()
    _, estopped, moved = await clearing, await estopping, await moving
    await gov.stop()
    assert moved.reason == Reason.ESTOP_ACTIVE.value, moved
    entries = harness.entries
    assert _latched_by_the_log(entries) == [], [
        (e["seq"], e["event"], e["action_type"], e["deny_reason"]) for e in entries]
    assert _seq(harness, estopped) < _seq(harness, moved)


async def test_a_fifo_where_the_latch_file_is_written_holds_up_no_estop(
        harness: Harness) -> None:
    """A FIFO at the latch file's temporary name (`.estop.state.<pid>.tmp`, put there by
    whoever can write the directory): the e-stop is persisted all the same (before: the
    writer thread's open waited for a reader for good, and the e-stop never answered)."""
    import os

    gov = await harness.governor()
    await gov.start()
    fifo = harness.tmp / f".estop.state.{os.getpid()}.tmp"
    os.mkfifo(fifo)
    try:
        decided = await asyncio.wait_for(gov.decide(command("estop"), VIEWER), 30)
    except TimeoutError:
        decided = None
        os.close(os.open(fifo, os.O_RDONLY | os.O_NONBLOCK))  # (let the writer go)
    assert decided is not None and decided.outcome is Outcome.EXECUTED, decided
    assert json.loads((harness.tmp / "estop.state").read_text())["latched"] is True
    await gov.stop()


def test_a_latch_file_that_is_no_regular_file_starts_latched(tmp_path: Path) -> None:
    """A FIFO in the latch file's place: the start does not wait on it for a writer (before:
    `read_bytes` held the start, and every e-stop after it, for good); unreadable, it starts
    latched (fails closed), and says why."""
    import os

    path = tmp_path / "estop.state"
    os.mkfifo(path)
    latch = estop.LatchFile(path)
    found: list[tuple[bool, str | None]] = []
    loading = threading.Thread(target=lambda: found.append(latch.load(first_start=False)),
                               daemon=True)
    loading.start()
    loading.join(30)
    blocked = loading.is_alive()
    if blocked:  # (let the blocked open go, so the thread ends)
        os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
        loading.join(30)
    latch.close()
    assert not blocked
    [(latched, why)] = found
    assert latched and why is not None and "not a regular file" in why


async def test_an_estop_behind_a_clear_and_recorded_repeats_is_listed_where_it_took_effect(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    """Latched, an e-stop repeated while latched; a clear under way, waiting for the robot,
    when the sweep finds the repeats due and queues their recording behind it (a `then`
    job). The clear goes on: records the repeats itself, is decided (ESTOP_CLEARED sealed)
    and its latch file sticks on the disk. Now an e-stop, and a move refused for it. The
    e-stop waited for its turn behind the `then` job — so behind the clear after all — and
    the move's refusal, once its wait for the ESTOP entry (at most 2 s) ran out, was listed
    between ESTOP_CLEARED and that ESTOP, as if refused while unlatched. An e-stop begins
    at once behind recorded repeats too: only another e-stop holds it, and only one that
    latched nothing."""
    gov = await harness.governor()
    await gov.decide(command("estop"), VIEWER)
    repeated = await gov.decide(command("estop"), PLANNER)
    assert repeated.reason == "already_latched", repeated
    harness.clock.advance(61)  # the repeats are due to be recorded
    at_ready = _HeldClear(harness, monkeypatch, "ready")
    at_latch_file = _HeldClear(harness, monkeypatch, "latch_file")
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.wait_for(at_ready.entered.wait(), 60)
    sweeping = asyncio.ensure_future(gov.sweep())
    for _ in range(100):  # until the sweep has queued the repeats' recording
        if gov.latch._unfinished == 2:
            break
        await asyncio.sleep(0)
    assert gov.latch._unfinished == 2
    at_ready.release()
    await asyncio.wait_for(at_latch_file.entered.wait(), 60)  # decided, its file stuck
    estopping = asyncio.ensure_future(gov.decide(command("estop"), VIEWER))
    await asyncio.sleep(0)  # the e-stop has arrived: latched
    assert gov.latch.latched
    moved = await gov.decide(command("move", MOVE), ADMIN)
    assert moved.reason == Reason.ESTOP_ACTIVE.value, moved
    at_latch_file.release()
    cleared, estopped = await clearing, await estopping
    await sweeping
    await gov.stop()
    assert cleared.outcome is Outcome.EXECUTED, cleared
    assert estopped.outcome is Outcome.EXECUTED and estopped.reason is None, estopped
    assert gov.latch.latched and _persisted(harness) and _published(harness) is True
    entries = harness.entries
    assert _latched_by_the_log(entries) == [], [
        (e["seq"], e["event"], e["action_type"], e["deny_reason"]) for e in entries]
    assert _seq(harness, cleared) < _seq(harness, estopped) < _seq(harness, moved)
    assert [e["event"] for e in entries].count("ESTOP_REPEATED") == 1


# -- adversarial: what an e-stop begun at once, past clears, must not break ----------------


def _moved_while_latched(entries: list[dict[str, Any]]) -> list[int]:
    """The seqs of motion written ahead (sent) at a point where the log says latched: none."""
    from govhelpers import MOTION_ACTIONS

    latched, wrong = False, []
    for entry in entries:
        if entry["event"] == "BRIDGE_STARTED":
            latched = entry["params"]["estop_latched"]
        elif entry["event"] == "ESTOP":
            latched = True
        elif entry["event"] == "ESTOP_CLEARED" and entry["outcome"] == "executed":
            latched = False
        elif (entry["event"] == "COMMAND_DISPATCHED" and latched
              and entry["action_type"] in MOTION_ACTIONS):
            wrong.append(entry["seq"])
    return wrong


def _log_agrees(entries: list[dict[str, Any]]) -> None:
    shown = [(e["seq"], e["event"], e["action_type"], e["deny_reason"]) for e in entries]
    assert _latched_by_the_log(entries) == [], shown
    assert _moved_while_latched(entries) == [], shown


async def _until(check: Any, what: str) -> None:
    for _ in range(1000):
        if check():
            return
        await asyncio.sleep(0)
    raise AssertionError(f"never {what}")


@pytest.mark.parametrize("held_at", ["ready", "latch_file", "publish"])
async def test_two_clears_queued_then_an_estop(
        harness: Harness, monkeypatch: pytest.MonkeyPatch, held_at: str) -> None:
    """Latched; a clear under way (held at `held_at`) and a second one queued behind it; then
    an e-stop, which begins at once (no e-stop ahead), and a move refused for it. The second
    clear came before the e-stop: it is refused for it at its turn (cleared nothing), listed
    after the ESTOP; the first clears only if decided before the e-stop came, and then
    neither unlatches (latch_file) nor, past its publish, stays the last word. Replies in
    order: first clear, second clear, e-stop."""
    gov = await harness.governor()
    await gov.decide(command("estop"), VIEWER)
    held = _HeldClear(harness, monkeypatch, held_at)
    acks: list[str] = []

    async def acked(name: str, coro: Any) -> Decision:
        d = await coro
        acks.append(name)
        return d

    first = asyncio.ensure_future(acked("c1", gov.decide(command("clear_estop"), OPS)))
    await asyncio.wait_for(held.entered.wait(), 60)
    second = asyncio.ensure_future(acked("c2", gov.decide(command("clear_estop"), ADMIN)))
    await _until(lambda: gov.latch._unfinished == 2, "queued")
    estopping = asyncio.ensure_future(acked("e", gov.decide(command("estop"), VIEWER)))
    await asyncio.sleep(0)
    assert gov.latch.latched
    moved = await gov.decide(command("move", MOVE), ADMIN)
    assert moved.reason == Reason.ESTOP_ACTIVE.value, moved
    held.release()
    c1, c2, e = await first, await second, await estopping
    await gov.stop()
    assert acks == ["c1", "c2", "e"]
    assert e.outcome is Outcome.EXECUTED, e
    assert (c2.http_status, c2.reason) == (409, Reason.ESTOP_ACTIVE.value), c2
    assert gov.latch.latched and _persisted(harness) and _published(harness) is True
    _log_agrees(harness.entries)
    if held_at == "ready":
        assert (c1.http_status, c1.reason) == (409, Reason.ESTOP_ACTIVE.value), c1
        assert e.reason == "already_latched"  # the first ESTOP holds the latch still
    else:
        assert c1.outcome is Outcome.EXECUTED and e.reason is None, (c1, e)
        assert _seq(harness, c1) < _seq(harness, e) < _seq(harness, moved) < _seq(harness, c2)


@pytest.mark.parametrize("held_at", ["ready", "latch_file"])
async def test_a_flood_of_estops_during_a_clear_is_one_entry(
        harness: Harness, monkeypatch: pytest.MonkeyPatch, held_at: str) -> None:
    """Latched; a clear under way; 30 e-stops arrive at once. The first begins at once, the
    others wait behind it (an e-stop ahead) and are repeats of it: at most one new ESTOP
    entry (a clear decided before them), the rest recorded together (ESTOP_REPEATED, one per
    principal), never one entry each."""
    gov = await harness.governor()
    await gov.decide(command("estop"), VIEWER)
    held = _HeldClear(harness, monkeypatch, held_at)
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.wait_for(held.entered.wait(), 60)
    flood = [asyncio.ensure_future(gov.decide(command("estop"), who))
             for who in [VIEWER, PLANNER, ADMIN] * 10]
    await asyncio.sleep(0)
    held.release()
    cleared, estops = await clearing, await asyncio.gather(*flood)
    await gov.stop()
    assert all(d.outcome is Outcome.EXECUTED for d in estops), estops
    events = [e["event"] for e in harness.entries]
    assert events.count("ESTOP") == (1 if held_at == "ready" else 2), events
    assert events.count("ESTOP_REPEATED") <= 3, events
    repeated = sum(e["params"]["count"] for e in harness.entries
                   if e["event"] == "ESTOP_REPEATED")
    assert repeated == (30 if held_at == "ready" else 29)
    assert gov.latch.latched and _persisted(harness) and _published(harness) is True
    _log_agrees(harness.entries)
    assert (cleared.outcome is Outcome.EXECUTED) is (held_at != "ready")


async def test_an_estop_while_a_clear_records_repeats_is_a_repeat_and_wins(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    """Latched, a repeat tallied; a clear under way, not yet decided, held while it records
    that repeat (ESTOP_REPEATED on a slow disk). An e-stop comes: begun at once, it is a
    repeat of the ESTOP holding the latch (no entry of its own, none needed: the log says
    latched), tallied anew; the clear, overtaken, is refused; the new tally is recorded
    later on its own, not lost and not merged into the one already written."""
    gov = await harness.governor()
    await gov.decide(command("estop"), VIEWER)
    await gov.decide(command("estop"), PLANNER)
    entered, release = asyncio.Event(), asyncio.Event()
    record_event = gov._steps.record_event

    async def slow_record(record: Any) -> None:
        if record.event.value == "ESTOP_REPEATED" and not release.is_set():
            entered.set()
            await release.wait()
        await record_event(record)

    monkeypatch.setattr(gov._steps, "record_event", slow_record)
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.wait_for(entered.wait(), 60)
    repeating = asyncio.ensure_future(gov.decide(command("estop"), ADMIN))
    await asyncio.sleep(0)  # begun at once (replied in order, after the clear)
    moved = await gov.decide(command("move", MOVE), ADMIN)
    assert moved.reason == Reason.ESTOP_ACTIVE.value, moved
    release.set()
    cleared, again = await clearing, await repeating
    assert again.reason == "already_latched", again
    assert (cleared.http_status, cleared.reason) == (409, Reason.ESTOP_ACTIVE.value), cleared
    await gov.stop()
    assert gov.latch.latched and _persisted(harness) and _published(harness) is True
    repeated = [(e["principal"], e["params"]["count"]) for e in harness.entries
                if e["event"] == "ESTOP_REPEATED"]
    assert repeated == [("planner", 1), ("root", 1)]
    _log_agrees(harness.entries)


async def test_an_estop_while_a_decided_clears_entry_fails_to_be_written(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    """Latched; a clear decided (its entry handed to the log, which then fails: audit
    unavailable); an e-stop comes meanwhile — begun at once, a new ESTOP (the clear had let go
    of the latch's entry). The clear answers audit_unavailable and unlatches nothing; the
    e-stop's entry holds the latch after it, so the next e-stop is a repeat of that one."""
    gov = await harness.governor()
    first = await gov.decide(command("estop"), VIEWER)
    entered, release = asyncio.Event(), asyncio.Event()
    write_ahead = gov._steps.write_ahead

    async def failing(entry: Any, *, urgent: bool = False) -> Any:
        if entry.action_type == "clear_estop":
            entered.set()
            await release.wait()
            return None  # the log could not write it
        return await write_ahead(entry, urgent=urgent)

    monkeypatch.setattr(gov._steps, "write_ahead", failing)
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.wait_for(entered.wait(), 60)
    estopping = asyncio.ensure_future(gov.decide(command("estop"), PLANNER))
    await asyncio.sleep(0)  # begun at once (replied in order, after the clear)
    release.set()
    cleared, estopped = await clearing, await estopping
    assert estopped.outcome is Outcome.EXECUTED and estopped.reason is None, estopped
    assert cleared.reason == "audit_unavailable", cleared
    again = await gov.decide(command("estop"), ADMIN)
    assert (again.reason, again.audit_id) == ("already_latched", estopped.audit_id)
    assert first.audit_id != estopped.audit_id
    await gov.stop()
    assert gov.latch.latched and _persisted(harness) and _published(harness) is True
    _log_agrees(harness.entries)


async def test_a_move_refused_behind_a_repeated_estop_is_listed_before_a_later_clear(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    """Unlatched. An e-stop whose latch file is slow to write; a second e-stop behind it
    (a repeat, waiting its turn); a move, refused for the latch; then a clear. Before, the
    move's refusal waited for the second e-stop to begin (`listed`: every latched e-stop's
    entry sealed), which let the clear, arriving after it, be sealed first: ESTOP,
    ESTOP_REPEATED, ESTOP_CLEARED, then the move refused for a latch the log says was
    cleared (the stateful model's crowd_on_a_slow_disk, 'estop, estop, move, clear'). Only
    an e-stop that latches can have a refusal listed before it, and it begins at once."""
    release, entered = threading.Event(), asyncio.Event()
    loop, write = asyncio.get_running_loop(), estop.atomic_write

    def held_write(path: Any, data: bytes, *args: Any) -> None:
        if b'"latched":true' in data and not release.is_set():
            loop.call_soon_threadsafe(entered.set)
            assert release.wait(60), "never released"
        write(path, data, *args)

    monkeypatch.setattr(estop, "atomic_write", held_write)
    gov = await harness.governor()
    first = asyncio.ensure_future(gov.decide(command("estop"), VIEWER))
    await asyncio.wait_for(entered.wait(), 60)
    second = asyncio.ensure_future(gov.decide(command("estop"), PLANNER))
    moving = asyncio.ensure_future(gov.decide(command("move", MOVE), ADMIN))
    for _ in range(20):  # the move decided (and, now, sealed) before the clear comes
        await asyncio.sleep(0)
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.sleep(0.05)
    release.set()
    await first, await second
    moved, cleared = await moving, await clearing
    await gov.stop()
    assert moved.reason == Reason.ESTOP_ACTIVE.value, moved
    assert cleared.outcome is Outcome.EXECUTED, cleared
    _log_agrees(harness.entries)
    assert _seq(harness, moved) < _seq(harness, cleared)
