"""ReplayWindow (§8.3): the SDK's ReplayCache as the oracle of fresh/stale/replayed; bounds."""

from __future__ import annotations

import time
import uuid

import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule
from rcan.replay import ReplayCache

from rcan_rtps.governance import ManualClock, SystemClock
from rcan_rtps.governance.replay import ReplayWindow


@pytest.mark.parametrize("safety", [False, True])
@pytest.mark.parametrize("age_s", [-30.0, -6.0, -4.0, 0.0, 2.0, 9.0, 11.0, 29.0, 31.0, 600.0])
def test_fresh_and_stale_as_the_sdk_decides(age_s: float, safety: bool) -> None:
    ours, sdk = ReplayWindow(SystemClock()), ReplayCache()
    msg_id, sent = str(uuid.uuid4()), time.time() - age_s
    verdict = ours.check(msg_id, sent, safety=safety) is None
    assert verdict == sdk.check_and_record(msg_id, sent, is_safety=safety)[0]
    again_ours = ours.check(msg_id, sent, safety=safety) is None
    again_sdk = sdk.check_and_record(msg_id, sent, is_safety=safety)[0]
    assert again_ours is again_sdk is False  # a replay for both (or stale for both)


def test_ids_are_forgotten_once_their_message_is_stale() -> None:
    clock = ManualClock()
    window = ReplayWindow(clock, window_s=30)
    for _ in range(100):
        assert window.check(str(uuid.uuid4()), clock.time()) is None
    assert len(window) == 100
    clock.advance(31)
    assert window.check("late", clock.time()) is None
    assert len(window) == 1  # memory never grows with the messages served


def test_a_full_window_refuses_rather_than_forgets() -> None:
    clock = ManualClock()
    window = ReplayWindow(clock, max_entries=3)
    sent = clock.time()
    for n in range(3):
        assert window.check(f"m{n}", sent) is None
    full = window.check("m3", sent)
    assert full is not None and (full.http_status, full.reason) == (429, "replay_window_full")
    replay = window.check("m0", sent)  # still caught: nothing was forgotten to make room
    assert replay is not None and replay.error_code.value == "REPLAY_DETECTED"
    clock.advance(31)
    assert window.check("m4", clock.time()) is None


def test_no_timestamp_is_stale() -> None:
    rejection = ReplayWindow(ManualClock()).check("m", None)
    assert rejection is not None and (rejection.http_status, rejection.reason) == (
        408, "no_timestamp")


def test_the_bound_is_per_sender_and_a_replay_is_a_replay_from_anyone() -> None:
    clock = ManualClock()
    window = ReplayWindow(clock, max_entries=3)
    sent = clock.time()
    for n in range(3):
        assert window.check(f"g{n}", sent, sender="guest") is None
    full = window.check("g3", sent, sender="guest")
    assert full is not None and full.reason == "replay_window_full"
    assert window.check("p0", sent, sender="planner") is None  # the guest's flood is its own
    replay = window.check("g0", sent, sender="planner")
    assert replay is not None and replay.error_code.value == "REPLAY_DETECTED"
    clock.advance(31)
    assert window.check("g4", clock.time(), sender="guest") is None
    assert len(window) == 1


def test_an_id_given_back_by_its_sender_passes_again_and_is_then_kept_its_full_window() -> None:
    """A message refused before anything was done with it (a full WebSocket queue's 429)
    gives its id back: the client's retry is the same message, not a replay. Only its own
    sender gives it back; the first admission's expiry does not cut the second's short."""
    clock = ManualClock()
    window = ReplayWindow(clock, window_s=30, max_entries=1)
    assert window.check("m", clock.time(), sender="a") is None
    window.release("m", sender="b")  # not b's to give back
    refused = window.check("m", clock.time(), sender="a")
    assert refused is not None and refused.error_code.value == "REPLAY_DETECTED"
    window.release("m", sender="a")
    window.release("unknown", sender="a")
    window.release(None, sender="a")
    assert len(window) == 0
    clock.advance(20)
    assert window.check("m", clock.time(), sender="a") is None  # its retry, 20 s later
    assert window.check("other", clock.time(), sender="a") is not None  # a's bound: 1 held
    clock.advance(15)  # past the first admission's expiry, within the retry's
    replay = window.check("m", clock.time(), sender="a")
    assert replay is not None and replay.error_code.value == "REPLAY_DETECTED"


IDS = st.sampled_from(["a", "b", "c"])  # few: the same id comes back often


class ReplayModel(RuleBasedStateMachine):
    """The window against a plain model of §8.3 as this module states it: an id seen (and
    not given back) while its message is fresh is a replay from anyone; a sender holds at
    most `MAX` fresh ids; a given-back id is free again; time only moves forward."""

    MAX = 3
    WINDOW = 30.0

    def __init__(self) -> None:
        super().__init__()
        self.clock = ManualClock()
        self.window = ReplayWindow(self.clock, window_s=self.WINDOW, max_entries=self.MAX)
        self.kept: dict[str, tuple[str, float]] = {}  # id → (sender, stale after)

    def _forget_stale(self) -> None:
        now = self.clock.time()
        self.kept = {i: (s, at) for i, (s, at) in self.kept.items() if at >= now}

    @rule(msg_id=IDS,
          sender=st.sampled_from(["p", "q"]), age_s=st.sampled_from([0.0, 29.0, 31.0]))
    def check(self, msg_id: str, sender: str, age_s: float) -> None:
        sent = self.clock.time() - age_s
        verdict = self.window.check(msg_id, sent, sender=sender)
        self._forget_stale()
        if age_s > self.WINDOW:
            expected = "MESSAGE_STALE"
        elif msg_id in self.kept:
            expected = "REPLAY_DETECTED"
        elif sum(1 for s, _ in self.kept.values() if s == sender) >= self.MAX:
            expected = "RATE_LIMITED"
        else:
            expected = None
            self.kept[msg_id] = (sender, sent + self.WINDOW)
        assert (None if verdict is None else verdict.error_code.value) == expected

    @rule(msg_id=IDS, sender=st.sampled_from(["p", "q"]))
    def give_back(self, msg_id: str, sender: str) -> None:
        self.window.release(msg_id, sender)
        if self.kept.get(msg_id, ("", 0.0))[0] == sender:
            del self.kept[msg_id]

    @rule(seconds=st.sampled_from([5.0, 20.0]))
    def advance(self, seconds: float) -> None:
        self.clock.advance(seconds)

    @invariant()
    def holds_no_more_than_the_model(self) -> None:
        self._forget_stale()
        assert len(self.window) >= len(self.kept)  # (stale ids go at the next check)


TestReplayModel = ReplayModel.TestCase
# (a give-back, a later admission, then the first one's expiry: a few steps deep)
TestReplayModel.settings = settings(max_examples=400, stateful_step_count=20, deadline=None)
