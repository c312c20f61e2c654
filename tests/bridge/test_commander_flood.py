"""A DDS peer that flaps its writer on a command topic, unauthenticated, made ~10 signed,
durable audit entries a second at poll_s 0.1, for ever: the audit (and the log) is told what
other publishers do within a budget (commanders.KEY_BURST/ALL_BURST, refilled slowly); the rest
is counted and summed up once per SUMMARY_S, and each participant whose events were left out
is then told as it is — the audit's last word on it is never false. STATUS and the e-stop's
fault are never held back. A real node's CommanderWatch, told the graph's publishers as the
graph would (test_expected_changes), on the test's clock."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from interop.bridge_rig import bridge_config
from test_expected_publishers import CMD_VEL, EXPECTED, writer

from rcan_rtps.bridge.commanders import (
    ALL_BURST,
    KEY_BURST,
    MAX_SETTLE,
    SUMMARY_S,
    CommanderWatch,
    Key,
    foreign_publishers,
)
from rcan_rtps.bridge.telemetry import ESTOP_NOT_HOLDING, TelemetryState
from rcan_rtps.rcan import ForeignPublisher
from rcan_rtps.ros.graph import Endpoint
from rcan_rtps.ros.participant import RosNode

POLL_S = 0.1  # the fastest poll_s the config takes


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Rig:
    def __init__(self, node: RosNode, show: Any = None) -> None:
        self.clock = Clock()
        self.audited: list[tuple[dict[str, Any], bool]] = []
        self.shown: list[list[ForeignPublisher]] = []
        self.own = node.participant.guid.bytes

        def shown(found: list[ForeignPublisher], motion: set[str]) -> None:
            self.shown.append(found)
            if show is not None:
                show(found, motion)

        self.watch = CommanderWatch(
            node, {CMD_VEL: True}, show=shown, expected=EXPECTED, monotonic=self.clock,
            audit=lambda facts, gone: self.audited.append((facts, gone)))

    def poll(self, *endpoints: Endpoint) -> None:
        """One poll at POLL_S after the last, the graph showing these publishers."""
        self.clock.now += POLL_S
        self.watch.update(foreign_publishers(list(endpoints), self.own, EXPECTED))
        self.watch.tick()

    def told(self, participant: str) -> list[tuple[bool, bool]]:
        """(gone, expected) of each entry about this participant, in order."""
        return [(gone, facts["expected"]) for facts, gone in self.audited
                if facts.get("participant") == participant]

    def summaries(self) -> list[dict[str, Any]]:
        return [facts for facts, _ in self.audited if "left_out" in facts]


@pytest.fixture
def node(domain_id: int) -> Iterator[RosNode]:
    with RosNode("commanders_flood", "/robot1", domain_id=domain_id) as n:
        yield n


def participant_of(endpoint: Endpoint) -> str:
    return ".".join(f"{b:02x}" for b in endpoint.participant_gid[:12])


@pytest.mark.parametrize("ends_present", [True, False])
def test_a_flapping_writer_is_audited_within_its_budget_and_its_last_word_is_true(
        node: RosNode, caplog: pytest.LogCaptureFixture, ends_present: bool) -> None:
    rig = Rig(node)
    teleop = writer(CMD_VEL, 1, "/teleop")
    who = participant_of(teleop)
    minutes = 10
    polls = int(minutes * 60 / POLL_S)
    with caplog.at_level(logging.INFO, logger="rcan_rtps.bridge.commanders"):
        for i in range(polls):  # there one poll, gone the next
            rig.poll(*([teleop] if i % 2 == 0 else []))
    # Was one entry per poll: 6000 in ten minutes. Now its first KEY_BURST, then per
    # summary at most the summary, its state then, and the one token refilled meanwhile.
    assert len(rig.audited) <= KEY_BURST + 3 * minutes, len(rig.audited)
    assert rig.told(who)[:int(KEY_BURST)] == [(False, False), (True, False)] * int(KEY_BURST // 2)
    summaries = rig.summaries()
    assert len(summaries) == minutes - 1 or len(summaries) == minutes
    assert sum(s["left_out"] for s in summaries) + len(rig.told(who)) <= polls
    assert all(s["of"][0]["participant"] == who and s["of"][0]["node"] == "/teleop" and
               s["topics"] == [CMD_VEL] for s in summaries)
    # The log is held back with the audit: a line per entry, not per poll.
    assert len(caplog.records) <= len(rig.audited)
    # STATUS was told every change: never held back.
    assert len(rig.shown) == polls
    # It stops flapping, present or gone: by the next summary the audit says so.
    for _ in range(int(SUMMARY_S / POLL_S) + 1):
        rig.poll(*([teleop] if ends_present else []))
    assert rig.told(who)[-1] == (not ends_present, False)
    # And, quiet, nothing more is told of it.
    before = len(rig.audited)
    for _ in range(int(3 * SUMMARY_S / POLL_S)):
        rig.poll(*([teleop] if ends_present else []))
    assert len(rig.audited) == before


def test_a_participant_within_its_budget_is_told_at_once(node: RosNode) -> None:
    """A node restarting now and then (nav2's controller on a relaunch) is audited as before:
    each appearance and disappearance, when it happens."""
    rig = Rig(node)
    controller = writer(CMD_VEL, 1, "/controller_server")
    who = participant_of(controller)
    for cycle in range(6):  # up for a minute, down for a minute
        for _ in range(int(60 / POLL_S)):
            rig.poll(controller)
        assert rig.told(who)[-1] == (False, True), cycle
        for _ in range(int(60 / POLL_S)):
            rig.poll()
        assert rig.told(who)[-1] == (True, True), cycle
    assert len(rig.told(who)) == 12 and rig.summaries() == []


def test_a_change_of_expected_left_out_is_told_as_it_is_at_the_summary(node: RosNode) -> None:
    """A participant whose writers flip between a declared node and another: the audit's
    last word is its `expected` as it is, not as it was when the budget ran out."""
    rig = Rig(node)
    controller = writer(CMD_VEL, 1, "/controller_server")
    who = participant_of(controller)
    teleop = writer(CMD_VEL, 1, "/teleop", 1)
    for i in range(int(2 * SUMMARY_S / POLL_S)):
        rig.poll(*([controller] if i % 2 else [controller, teleop]))
    for _ in range(int(SUMMARY_S / POLL_S) + 1):
        rig.poll(controller)
    assert rig.told(who)[-1] == (False, True)
    for _ in range(int(SUMMARY_S / POLL_S) + 1):
        rig.poll(controller, teleop)
    assert rig.told(who)[-1] == (False, False)


def test_churning_participants_share_one_budget(node: RosNode) -> None:
    """A peer making a new participant each poll (a budget per participant would never run
    out): the shared budget holds, the per-participant buckets do not pile up, and each left
    present is recorded present by a summary."""
    rig = Rig(node)
    polls = int(10 * 60 / POLL_S)
    for i in range(polls):
        rig.poll(writer(CMD_VEL, 1 + i % 250, None, i // 250))  # unnamed: told after 4 s
    assert len(rig.audited) <= ALL_BURST + (10 * 60 / 10) + 10 * (1 + MAX_SETTLE), \
        len(rig.audited)
    assert len(rig.watch._budget) <= ALL_BURST + 60
    last = writer(CMD_VEL, 7, None, 99)
    for _ in range(int(3 * SUMMARY_S / POLL_S)):  # one stays: told once named or 4 s on
        rig.poll(last)
    assert rig.told(participant_of(last))[-1] == (False, False)
    keys: set[Key] = set(rig.watch._said)
    assert keys == {(CMD_VEL, last.participant_gid)}  # the audit says only it is there


def test_the_estop_fault_and_status_are_never_held_back(tmp_path: Path, node: RosNode,
                                                        domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id)
    telemetry = TelemetryState(node, config, estop_latched=lambda: True, active_goals=list)
    try:
        rig = Rig(node, show=telemetry.foreign_publishers)
        teleop = writer(CMD_VEL, 1, "/teleop")
        for i in range(int(SUMMARY_S / POLL_S / 2)):  # its budget long spent
            rig.poll(*([teleop] if i % 2 else []))
            status = telemetry.status(pending_auth=0)
            assert [p.node for p in status.foreign_publishers] == (["/teleop"] if i % 2 else [])
            if i % 2:
                first = status.faults[0]
                assert (first.name, first.level) == (ESTOP_NOT_HOLDING, "ERROR")
            else:
                assert all(f.name != ESTOP_NOT_HOLDING for f in status.faults)
        assert len(rig.audited) == KEY_BURST
    finally:
        telemetry.close()
