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
from pathlib import Path
from typing import Any

from govhelpers import ADMIN, OPS, PLANNER, VIEWER, Harness, command
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

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


async def test_estop_and_clear_interleavings_agree_everywhere(harness: Harness) -> None:
    gov = await harness.governor()
    rng = random.Random(20261124)
    outcomes: dict[bool, int] = {True: 0, False: 0}
    for trial in range(TRIALS):
        acks: list[str] = []
        e, c = await _race(gov, rng, acks)
        assert e.outcome is Outcome.EXECUTED and c.outcome is Outcome.EXECUTED, trial
        estop_last = _seq(harness, e) > _seq(harness, c)
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


async def test_estop_arriving_during_a_clear_wins(harness: Harness) -> None:
    """The exact shape of the reported bug: clear in progress, e-stop acknowledged after it."""
    gov = await harness.governor()
    await gov.decide(command("estop"), VIEWER)
    write, entered, release = gov.latch.file.write, asyncio.Event(), asyncio.Event()

    async def slow_write(latched: bool, by: str, at_ms: int) -> None:
        if not latched:  # the clear is audited and now being persisted
            entered.set()
            await release.wait()
        await write(latched, by, at_ms)

    gov.latch.file.write = slow_write  # type: ignore[method-assign]
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), OPS))
    await asyncio.wait_for(entered.wait(), 10)
    estopping = asyncio.ensure_future(gov.decide(command("estop"), VIEWER))
    await asyncio.sleep(0.01)
    assert not estopping.done()  # ordered behind the clear
    release.set()
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
        self.latched = _seq(self.harness, e) > _seq(self.harness, c)

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
