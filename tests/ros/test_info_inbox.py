"""InfoInbox: what the reader thread keeps of ros_discovery_info until a refresh reads it
(no DDS here: the inbox is fed (CDR bytes, SampleInfo) pairs as the reader thread feeds it)."""

from __future__ import annotations

import threading
import uuid
from types import SimpleNamespace

from cyclonedds.core import InstanceState
from hypothesis import given, settings
from hypothesis import strategies as st

from rcan_rtps.ros.info_inbox import (
    MAX_INFO_BYTES,
    WAITING_INFO_BYTES,
    WAITING_INFOS,
    InfoInbox,
)

ALIVE = SimpleNamespace(valid_data=True, instance_state=InstanceState.Alive,
                        publication_handle=1)
NO_WRITERS = SimpleNamespace(valid_data=True, instance_state=InstanceState.NotAliveNoWriters,
                             publication_handle=1)
INVALID = SimpleNamespace(valid_data=False, instance_state=InstanceState.NotAliveNoWriters,
                          publication_handle=1)


def written_by(handle: int) -> SimpleNamespace:
    """The SampleInfo of an alive sample of the writer with this instance handle."""
    return SimpleNamespace(valid_data=True, instance_state=InstanceState.Alive,
                           publication_handle=handle)


def sample(gid: bytes, size: int = 64) -> bytes:
    """CDR-shaped bytes: a 4-byte header, the 16-byte gid, then padding to `size`."""
    return b"\x00\x01\x00\x00" + gid + bytes(max(0, size - 20))


def gid(n: int) -> bytes:
    return n.to_bytes(16, "big")


def test_the_newest_info_of_a_participant_replaces_the_one_waiting() -> None:
    inbox = InfoInbox()
    old, new = sample(gid(1), 100), sample(gid(1), 200)
    inbox.arrived([(old, ALIVE)])
    inbox.arrived([(sample(gid(2)), ALIVE)])
    inbox.arrived([(new, ALIVE)])
    taken, drained = inbox.take(1 << 30)
    assert drained and [(g, a.data) for g, a in taken] == [(gid(2), sample(gid(2))),
                                                          (gid(1), new)]


def test_an_info_past_the_size_bound_waits_as_a_mark_without_its_bytes() -> None:
    inbox = InfoInbox()
    inbox.arrived([(sample(gid(1), MAX_INFO_BYTES + 1), ALIVE)])
    inbox.arrived([(sample(gid(2), MAX_INFO_BYTES), NO_WRITERS)])
    taken, _ = inbox.take(1 << 30)
    assert [(g, a.data is None, a.alive) for g, a in taken] == [(gid(1), True, True),
                                                               (gid(2), False, False)]
    assert inbox.large == 1 and inbox.dropped == 0


def test_invalid_samples_name_no_participant() -> None:
    inbox = InfoInbox()
    inbox.arrived([(b"", INVALID)])
    assert inbox.waiting() == 0


def test_a_take_stops_once_its_budget_is_crossed() -> None:
    inbox = InfoInbox()
    for n in range(5):
        inbox.arrived([(sample(gid(n), 1000), ALIVE)])
    taken, drained = inbox.take(1500)
    assert [g for g, _ in taken] == [gid(0), gid(1)] and not drained
    taken, drained = inbox.take(1 << 30)
    assert [g for g, _ in taken] == [gid(2), gid(3), gid(4)] and drained


def test_past_the_count_bound_the_oldest_go() -> None:
    inbox = InfoInbox()
    for n in range(WAITING_INFOS + 10):
        inbox.arrived([(sample(gid(n)), ALIVE)])
    taken, _ = inbox.take(1 << 30)
    assert len(taken) == WAITING_INFOS and taken[0][0] == gid(10)
    assert inbox.dropped == 10


def test_past_the_count_bound_the_writer_with_the_most_waiting_loses_its_oldest() -> None:
    """A writer flooding made-up gids faster than refreshes run pushes out its own infos,
    not the one each other writer wrote before (the oldest overall went: theirs)."""
    inbox = InfoInbox()
    for honest in range(5):
        inbox.arrived([(sample(gid(10**6 + honest)), written_by(100 + honest))])
    for n in range(3 * WAITING_INFOS):
        inbox.arrived([(sample(gid(n)), written_by(7))])
    taken, _ = inbox.take(1 << 30)
    assert [g for g, _ in taken[:5]] == [gid(10**6 + h) for h in range(5)]
    assert [g for g, _ in taken[5:]] == [gid(n) for n in range(2 * WAITING_INFOS + 5,
                                                                3 * WAITING_INFOS)]
    assert inbox.dropped == 2 * WAITING_INFOS + 5 and inbox.waiting() == 0


def test_a_flood_from_many_writers_of_one_participant_is_one_source() -> None:
    """A peer spreading its flood over one writer per made-up gid tied every writer at one
    info waiting, and the honest writers, counted first, went first (all five here). Counted
    by their writers' participant, its writers are one source, and push out their own."""
    participants = {100 + h: bytes([h]) for h in range(5)}  # five honest participants
    inbox = InfoInbox(lambda handle: participants.get(handle, b"hostile"))
    for honest in range(5):
        inbox.arrived([(sample(gid(10**6 + honest)), written_by(100 + honest))])
    for n in range(2 * WAITING_INFOS):
        inbox.arrived([(sample(gid(n)), written_by(1000 + n))])  # a writer each
    taken, _ = inbox.take(1 << 30)
    assert [g for g, _ in taken[:5]] == [gid(10**6 + h) for h in range(5)]
    assert len(taken) == WAITING_INFOS and inbox.dropped == WAITING_INFOS + 5


def test_past_the_byte_bound_the_largest_become_marks_and_small_infos_stay() -> None:
    """A flood of large infos of made-up participants cannot push out a small, honest one
    that came before it."""
    inbox = InfoInbox()
    inbox.arrived([(sample(gid(0), 300), ALIVE)])
    for _ in range(39):
        inbox.arrived([(sample(uuid.uuid4().bytes, MAX_INFO_BYTES), ALIVE)])
    taken, _ = inbox.take(1 << 40)
    assert taken[0] == (gid(0), taken[0][1]) and taken[0][1].data == sample(gid(0), 300)
    assert sum(len(a.data) for _, a in taken if a.data is not None) <= WAITING_INFO_BYTES
    assert inbox.dropped == len([a for _, a in taken if a.data is None]) > 0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 40), st.integers(0, 3 * MAX_INFO_BYTES // 2),
                          st.booleans()), max_size=120),
       st.integers(1, 8 * MAX_INFO_BYTES))
def test_what_waits_stays_within_its_bounds_and_takes_return_the_newest(
        arrivals: list[tuple[int, int, bool]], budget: int) -> None:
    inbox = InfoInbox()
    newest: dict[bytes, int] = {}
    for n, size, alive in arrivals:
        inbox.arrived([(sample(gid(n), size), ALIVE if alive else NO_WRITERS)])
        newest[gid(n)] = size
        assert inbox._bytes <= WAITING_INFO_BYTES and inbox.waiting() <= WAITING_INFOS
        assert inbox._bytes == sum(len(a.data) for a in inbox._waiting.values()
                                   if a.data is not None)
    seen: list[bytes] = []
    while True:
        taken, drained = inbox.take(budget)
        for g, a in taken:
            if a.data is not None:  # (else: past the bound, or dropped waiting)
                assert len(a.data) == max(20, newest[g]) <= MAX_INFO_BYTES
            seen.append(g)
        if drained:
            break
    assert len(seen) == len(set(seen)) == len(newest)  # (under both bounds here)
    assert inbox._bytes == 0


def test_a_reader_thread_and_a_refresh_at_once_lose_nothing() -> None:
    """The reader thread adds while the loop takes: every participant's info is taken once."""
    inbox = InfoInbox()
    count = 20_000
    def feed() -> None:
        for n in range(count):
            inbox.arrived([(sample(gid(n % 500), 40 + n % 7), ALIVE)])

    thread = threading.Thread(target=feed)
    thread.start()
    taken: list[bytes] = []
    while thread.is_alive():
        taken += [g for g, _ in inbox.take(10_000)[0]]
    thread.join()
    taken += [g for g, _ in inbox.take(1 << 30)[0]]
    assert set(taken) == {gid(n) for n in range(500)} and inbox._bytes == 0
    assert inbox.dropped == 0
