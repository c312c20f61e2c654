"""ReplayWindow (§8.3): the SDK's ReplayCache as the oracle of fresh/stale/replayed; bounds."""

from __future__ import annotations

import time
import uuid

import pytest
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
