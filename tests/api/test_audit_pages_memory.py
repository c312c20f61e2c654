"""A page of GET /api/audit (and /api/audit/mine) reads the log a chunk at a time, from a line
found by halving the file: it holds the page, not the log. Before, every page read the whole
log and split it into lines (a 700 MB log: 1.4 GB a page, on a robot computer with 4-8 GB).
The answers are the whole read's: checked against a reference that reads everything."""

from __future__ import annotations

import collections
import json
import tracemalloc
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rcan_rtps.api._reads import PAGE_BYTES, entries_after, entries_of

PRINCIPALS = ("ops", "planner", None)


def _line(seq: int, padding: int = 0) -> bytes:
    entry = {"seq": seq, "principal": PRINCIPALS[seq % 3], "event": "COMMAND_DISPATCHED",
             "params": {"note": "x" * padding}}
    return json.dumps(entry, sort_keys=True, separators=(",", ":")).encode() + b"\n"


def _reference(data: bytes, since: int, limit: int, principal: str | None = None,
               last: bool = False, max_bytes: int = PAGE_BYTES) -> list[bytes]:
    """What a page is: the complete lines read whole, filtered in order, then as many as fit
    `max_bytes` from the page's start (with `last`, its end) — one at least."""
    lines = data[: data.rfind(b"\n") + 1].splitlines()
    found: collections.deque[bytes] = collections.deque(maxlen=limit if last else None)
    for line in lines:
        entry = json.loads(line)
        if entry["seq"] > since and (principal is None or entry["principal"] == principal):
            found.append(line)
            if not last and len(found) == limit:
                break
    page = list(reversed(found)) if last else list(found)
    kept = 1
    while kept < len(page) and sum(map(len, page[:kept + 1])) <= max_bytes:
        kept += 1
    page = page[:kept]
    return list(reversed(page)) if last else page


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(paddings=st.lists(st.sampled_from([0, 10, 3000, 70_000, 300_000]), min_size=0,
                         max_size=40),
       since=st.integers(-1, 45), limit=st.integers(1, 12), torn=st.binary(max_size=40),
       last=st.booleans(), max_bytes=st.sampled_from([1, 5000, 400_000, PAGE_BYTES]))
def test_a_page_is_what_a_whole_read_finds(tmp_path: Path, paddings: list[int], since: int,
                                           limit: int, torn: bytes, last: bool,
                                           max_bytes: int) -> None:
    """Lines short and longer than a read (64 KiB) and than where the halving stops (256 KiB),
    an unterminated last line (being appended) that is never part of a page; pages held to a
    byte budget (red team 26), one line at least."""
    path = tmp_path / "audit.jsonl"
    data = b"".join(_line(seq, pad) for seq, pad in enumerate(paddings, 1))
    data += torn.replace(b"\n", b"")
    path.write_bytes(data)
    assert entries_after(path, since, limit, max_bytes) == _reference(
        data, since, limit, max_bytes=max_bytes)
    assert entries_of(path, "ops", since, limit, last, max_bytes) == _reference(
        data, since, limit, "ops", last, max_bytes)


def test_a_page_deep_in_a_long_log_holds_the_page_not_the_log(tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    count = 120_000
    with path.open("wb") as log:
        for seq in range(1, count + 1):
            log.write(_line(seq, 200))
    size = path.stat().st_size
    tracemalloc.start()
    try:
        page = entries_after(path, count - 100, 50)
        mine = entries_of(path, "planner", 0, 20, True)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert [json.loads(line)["seq"] for line in page] == list(range(count - 99, count - 49))
    assert [json.loads(line)["seq"] for line in mine] == [
        s for s in range(count - 59, count + 1) if s % 3 == 1][-20:]
    assert peak < size / 20, (peak, size)


def test_a_damaged_line_past_the_page_does_not_refuse_it(tmp_path: Path) -> None:
    """Reads never verify, and a page never fails on a line it does not reach: a line that is
    no entry (planted on disk) past the page, where the halving looks first, is read over
    from the last good probe on — not answered 503 (the whole read never got there)."""
    path = tmp_path / "audit.jsonl"
    lines = [_line(seq, 1000) for seq in range(1, 2001)]
    middle = len(lines) // 2
    lines[middle - 20: middle + 20] = [b"not an entry " + b"x" * 1000 + b"\n"] * 40
    data = b"".join(lines)
    path.write_bytes(data)
    assert len(data) // 2 > 256 * 1024  # the halving probes the middle first
    entries = [line.rstrip(b"\n") for line in lines]
    assert entries_after(path, 0, 5) == entries[:5]
    assert entries_of(path, "ops", 0, 3, False) == [entries[2], entries[5], entries[8]]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(paddings=st.lists(st.sampled_from([0, 3000, 70_000, 300_000]), max_size=30),
       limit=st.integers(1, 12), max_bytes=st.sampled_from([1, 5000, 400_000, 1_000_000]))
def test_paging_on_by_since_gives_every_entry_once_within_the_budget(
        tmp_path: Path, paddings: list[int], limit: int, max_bytes: int) -> None:
    """Red team 26: a page is held to `max_bytes` (one entry larger than that is a page
    alone), and a client paging on from each page's last seq gets every entry, once."""
    path = tmp_path / "audit.jsonl"
    lines = [_line(seq, pad) for seq, pad in enumerate(paddings, 1)]
    path.write_bytes(b"".join(lines))
    got: list[bytes] = []
    since = 0
    while page := entries_after(path, since, limit, max_bytes):
        assert len(page) <= limit
        assert len(page) == 1 or sum(map(len, page)) <= max_bytes
        got += page
        since = json.loads(page[-1])["seq"]
    assert got == [line.rstrip(b"\n") for line in lines]
