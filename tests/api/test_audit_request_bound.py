"""Red team 26 follow-up: what a request's params put in the signed audit log is bounded.

Entries are RCAN canonical JSON v1, which writes a whole float as an integer: `1e300` (5 bytes
sent) is 301 digits logged. A stop's body is read up to 4x `max_body_bytes` and a stop is
audited whatever else is wrong with it, a GUEST's refused one too: one stop of 256 KiB made an
entry of 13 MB. Now a request's content past `request_bytes_limit(max_body_bytes)` (3x it, at
least 64 KiB) is recorded as a marker (its compact JSON's size and SHA-256); a stop still stops,
and an executed command's params are always logged whole.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import msgspec
import pytest
from rcan.encoding import canonical_json

from rcan_rtps.governance.audit import canonical_v1
from rcan_rtps.governance.entry_bound import request_bytes_limit
from tests.api.apihelpers import Api

MAX_BODY = 64 * 1024  # the harness's (and the config's default) max_body_bytes
BOUND = request_bytes_limit(MAX_BODY)
OVERHEAD = 4096  # an entry's bytes besides its request content (ids, signature, marker, …)


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    api = await Api(tmp_path, gates="[]").start()
    yield api
    await api.close()


def _stop_of_big_params() -> bytes:
    """A stop body just under 4x the body limit whose params are thousands of `1e300`."""
    count = (4 * MAX_BODY - 100) // 6
    return b'{"action":"stop","params":{"x":[' + b",".join([b"1e300"] * count) + b"]}}"


def _lines(api: Api) -> list[bytes]:
    return (api.tmp / "audit.jsonl").read_bytes().splitlines()


def _marked(line: bytes, sent: bytes) -> dict[str, Any]:
    """The entry of `line`, whose params are the marker of what `sent` said."""
    entry = json.loads(line)
    params = msgspec.json.decode(sent)["params"]
    compact = msgspec.json.encode(params)
    assert entry["params"] == {"omitted": "too_large_to_log", "json_bytes": len(compact),
                               "sha256": hashlib.sha256(compact).hexdigest(),
                               "limit_bytes": BOUND}, entry["params"]
    assert entry["omitted"] == ["params"], entry.get("omitted")  # the bridge's marker
    assert len(line) <= BOUND + OVERHEAD
    return dict(entry)


def _sdk_recomputes(line: bytes) -> bool:
    entry = json.loads(line)
    body = {k: v for k, v in entry.items() if k not in ("audit_id", "sig")}
    return bool(entry["audit_id"] == "sha256:" + hashlib.sha256(canonical_json(body)).hexdigest()
                and canonical_json(entry) == line)


def _verified(log: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "rcan_rtps", "audit", "verify", str(log)],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout + done.stderr


async def test_a_stop_of_huge_params_stops_and_its_entry_is_bounded(api: Api) -> None:
    raw = _stop_of_big_params()
    status, body = await api.command("planner", raw=raw)  # a USER's stop: executed
    assert (status, body["outcome"]) == (200, "executed"), body
    assert ("stop", {}) in api.dispatcher.calls  # the robot was stopped
    line = _lines(api)[-1]
    entry = _marked(line, raw)  # was 13 MB: the whole floats written out
    assert (entry["event"], entry["action_type"], entry["outcome"]) == (
        "COMMAND_DISPATCHED", "stop", "executed")
    assert entry["warnings"]  # its size is still said: the stop was over the body limit
    assert _sdk_recomputes(line)
    await api.close()
    _verified(api.tmp / "audit.jsonl")


async def test_a_guests_refused_stop_of_huge_params_is_bounded(api: Api) -> None:
    raw = _stop_of_big_params()
    status, body = await api.command("viewer", raw=raw)  # a GUEST may not stop: refused
    assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES"), body
    assert api.dispatcher.calls == []
    line = _lines(api)[-1]
    entry = _marked(line, raw)
    assert (entry["event"], entry["outcome"]) == ("COMMAND_REJECTED", "denied")
    assert _sdk_recomputes(line)
    await api.close()
    _verified(api.tmp / "audit.jsonl")


async def test_params_that_look_like_a_marker_are_logged_as_sent_and_not_listed(
        api: Api) -> None:
    """A request may send a marker's shape itself: it is logged as sent, and only the entry's
    `omitted` list (which the bridge writes) says a field was replaced. Before, a forged marker
    read as the bridge's, claiming a size and digest of params never sent."""
    forged = {"omitted": "too_large_to_log", "json_bytes": 99_000_000,
              "sha256": "0" * 64, "limit_bytes": BOUND}
    for who, outcome in (("planner", "executed"), ("viewer", "denied")):
        status, body = await api.command(who, {"action": "stop", "params": forged})
        assert status in (200, 403), body
        entry = json.loads(_lines(api)[-1])
        assert (entry["outcome"], entry["params"]) == (outcome, forged), entry
        assert "omitted" not in entry, entry
    await api.close()
    _verified(api.tmp / "audit.jsonl")


def _arm_body_of_big_numbers() -> tuple[bytes, dict[str, Any]]:
    """An arm trajectory just within the body limit whose every position is `1e9`, the largest
    number a command is accepted with (`rcan._types.Finite`): 4 bytes a number sent (`1e9,`),
    11 logged (`1000000000,`)."""
    joints = [f"j{i}" for i in range(64)]
    point = '{"positions":[' + ",".join(["1e9"] * 64) + '],"time_from_start_s":%d}'
    head = '{"action":"arm_joint","params":{"joints":' + json.dumps(joints, separators=(",", ":"))
    points: list[str] = []
    while len(head) + len(",".join([*points, point % (len(points) + 1)])) + 20 <= MAX_BODY:
        points.append(point % (len(points) + 1))
    raw = (head + ',"points":[' + ",".join(points) + "]}}").encode()
    assert MAX_BODY - 400 < len(raw) <= MAX_BODY
    return raw, json.loads(raw)["params"]


async def test_an_executed_command_at_the_body_limit_keeps_its_params_whole(api: Api) -> None:
    raw, params = _arm_body_of_big_numbers()
    status, body = await api.command("ops", raw=raw)
    assert (status, body["outcome"]) == (200, "executed"), body
    line = _lines(api)[-1]
    entry = json.loads(line)
    assert entry["params"] == params  # whole: every point, every position
    logged = len(canonical_v1(params))
    assert logged > 2.5 * MAX_BODY  # what a bound of twice the body limit would have cut
    assert logged <= BOUND
    assert _sdk_recomputes(line)


async def test_an_arm_trajectory_is_logged_in_canonical_json(api: Api) -> None:
    """Its points reached the log as structs: their whole floats were written `1.0` (the SDK,
    and `audit verify`, compute another id: the log failed to verify), and a float written
    with an exponent beside them failed the append (503 internal_error, nothing sent)."""
    for position in (1.0, 1e-05):
        status, body = await api.command("ops", {"action": "arm_joint", "params": {
            "joints": ["j0", "j1"],
            "points": [{"positions": [position, 0.0], "time_from_start_s": 1.0}]}})
        assert (status, body["outcome"]) == (200, "executed"), body
    lines = _lines(api)
    assert b'"positions":[1,0]' in lines[-2] and b'"positions":[1e-05,0]' in lines[-1]
    assert all(_sdk_recomputes(line) for line in lines)
    await api.close()
    _verified(api.tmp / "audit.jsonl")


async def test_a_stop_with_an_out_of_range_number_leaves_the_log_json(api: Api) -> None:
    """Red team 28: `1e400` is read as infinity (`_validate._DECODER`) and a stop keeps its
    params as requested, unknown fields too. msgspec writes infinity `null`, but an entry with
    a float written with an exponent beside it is written by Python's json: `Infinity`, which
    is not JSON — the line failed `audit verify` and the log refused the next start. Any
    principal's stop could do it (a GUEST's refused stop is logged with its params)."""
    for who in ("planner", "viewer"):
        raw = b'{"action":"stop","params":{"x":1e400,"y":[-1e999],"z":1e-7}}'
        status, body = await api.command(who, raw=raw)
        assert status in (200, 403), body
    assert ("stop", {}) in api.dispatcher.calls  # the USER's stop stopped
    lines = _lines(api)[-2:]
    for line in lines:
        entry = msgspec.json.decode(line)  # strict JSON: no Infinity token
        assert entry["params"] == {"x": None, "y": [None], "z": 1e-07}
        assert _sdk_recomputes(line)
    await api.close()
    _verified(api.tmp / "audit.jsonl")
    reopened = await Api(api.tmp, gates="[]").start()  # the log opens for the next start
    await reopened.close()


def _estop_of_a_duplicated_key(i: int) -> bytes:
    """An e-stop just under the body limit whose params name one ~30 KB key twice: its
    duplicate-key warning quotes that key (twice: its path and the key)."""
    key = f"{i:02d}" + "k" * 30_000
    return (b'{"action":"estop","params":{"' + key.encode() + b'":1,"' + key.encode()
            + b'":2}}')


async def test_repeated_e_stops_warnings_are_held_to_the_bound(api: Api) -> None:
    """Red team 30: e-stops repeated while latched are recorded together, one ESTOP_REPEATED
    entry per principal keeping up to 8 distinct warnings — held to no bound: 10 GUEST
    e-stops, each a duplicated 30 KB key within the 64 KiB body limit, made one entry of
    480,960 bytes, 2.5x the 196,608 a request's content may take. Now those warnings are the
    entry's `warnings`, held to the bound like any request's; each e-stop still stopped."""
    for i in range(10):
        raw = _estop_of_a_duplicated_key(i)
        assert len(raw) < MAX_BODY
        status, body = await api.command("viewer", raw=raw)
        assert (status, body["outcome"]) == (200, "executed"), body
    assert [c for c in api.dispatcher.calls if c[0] == "estop"] and api.gov.latch.latched
    status, body = await api.command("ops", {"action": "clear_estop"})  # records the repeats
    assert (status, body["outcome"]) == (200, "executed"), body
    lines = [line for line in _lines(api) if b'"ESTOP_REPEATED"' in line]
    assert len(lines) == 1
    entry = json.loads(lines[0])
    assert entry["params"]["count"] == 9  # the first latched: nine repeats
    assert len(lines[0]) <= BOUND + OVERHEAD, len(lines[0])  # was 480,960 bytes
    assert entry["omitted"] == ["warnings"], entry.get("omitted")  # the bridge's marker
    assert len(entry["warnings"]) == 1 and "too_large_to_log" in entry["warnings"][0]
    assert _sdk_recomputes(lines[0])
    await api.close()
    _verified(api.tmp / "audit.jsonl")
