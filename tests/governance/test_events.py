"""The one events object: wired before start, frozen then; a failing listener breaks nothing.

The kernel's own reaction to the latch (zero, e-stop Bool, then STATUS) is one reflex in a
fixed order, not a list anyone can append to.
"""

from __future__ import annotations

import logging

import pytest
from govhelpers import OPS, PLANNER, Harness, command

from rcan_rtps.events import Channel, Events, EventsFrozenError
from rcan_rtps.rcan import Outcome


def test_a_channel_tells_its_subscribers_in_order_until_frozen() -> None:
    heard: list[tuple[str, int]] = []
    channel: Channel[[int]] = Channel("numbers")
    assert not channel.heard
    channel.subscribe(lambda n: heard.append(("first", n)))
    channel.subscribe(lambda n: heard.append(("second", n)))
    channel.freeze()
    channel.emit(7)
    assert heard == [("first", 7), ("second", 7)]
    with pytest.raises(EventsFrozenError, match="numbers"):
        channel.subscribe(lambda n: None)


@pytest.mark.logs_traceback  # (a fault injected on purpose)
def test_a_failing_listener_is_logged_and_the_rest_are_still_told(
        caplog: pytest.LogCaptureFixture) -> None:
    heard: list[str] = []

    def broken() -> None:
        raise RuntimeError("listener bug")

    events = Events()
    events.robot.subscribe(broken)
    events.robot.subscribe(lambda: heard.append("told"))
    with caplog.at_level(logging.ERROR, logger="rcan_rtps.events"):
        events.robot.emit()
    assert heard == ["told"]
    assert any("robot listener failed" in r.getMessage() for r in caplog.records)


def test_freezing_the_events_freezes_every_channel() -> None:
    events = Events()
    assert not events.frozen
    events.freeze()
    assert events.frozen
    for channel in (events.governance, events.safe_stop, events.session_lost, events.audited,
                    events.command_sent, events.robot, events.goal, events.goal_finished):
        with pytest.raises(EventsFrozenError):
            channel.subscribe(lambda *args: None)


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_the_latch_reflex_sends_the_bool_before_status_hears_and_survives_a_bad_listener(
        harness: Harness) -> None:
    gov = await harness.governor()
    await gov.start()
    signals_when_told: list[int] = []

    def status_listener() -> None:
        signals_when_told.append(len(harness.dispatcher.signals))
        raise RuntimeError("a STATUS listener bug must not touch the e-stop")

    gov.events.governance.subscribe(status_listener)
    decision = await gov.decide(command("estop"), PLANNER)
    assert decision.outcome is Outcome.EXECUTED
    assert harness.dispatcher.signals == [0]  # the Bool, before any dispatch
    assert signals_when_told == [1]  # STATUS heard after the Bool went out
    assert gov.latch.latched
    cleared = await gov.decide(command("clear_estop"), OPS)
    assert cleared.outcome is Outcome.EXECUTED
    assert signals_when_told == [1, 1]  # told of the clear too; no Bool for a clear
    await gov.stop()


async def test_the_latch_takes_one_reflex_only(harness: Harness) -> None:
    gov = await harness.governor()
    with pytest.raises(RuntimeError, match="reflex"):
        gov.latch.bind(lambda: None)  # nobody can slip in ahead of, or beside, the kernel
