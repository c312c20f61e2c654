"""The bound on what a request puts in an audit entry (`governance.entry_bound`).

A request's content past the log's `request_bytes` is recorded as a marker; params that fit
are logged whole; a command whose params would not be is refused before it runs (never run
with its params left out). The API's side (stops, refusals, the body limit's number):
tests/api/test_audit_request_bound.py.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import msgspec
from govhelpers import OPS, RURI, Harness, command
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rcan.encoding import canonical_json

from rcan_rtps.governance import AuditEvent, AuditLog, AuditRecord, ManualClock
from rcan_rtps.governance.audit import canonical_v1
from rcan_rtps.governance.entry_bound import request_bytes_limit, size_within
from rcan_rtps.governance.governor import Governor
from rcan_rtps.rcan import ErrorCode, Outcome

LIMIT = 2048
OVERHEAD = 1024  # an entry's bytes besides its params (ids, signature, a marker, …)


async def test_a_command_whose_params_would_not_be_logged_whole_does_not_run(
        harness: Harness, tmp_path: Path) -> None:
    """The params of a body within the body limit always fit (`request_bytes_limit`); an
    INVOKE's skill's fixed params come from the config, which could make them larger. Such a
    command is refused (PAYLOAD_TOO_LARGE) rather than run with a marker for its params."""
    config = harness.config(gates="[]")
    log = await AuditLog.open(config.bridge.audit.path, config.bridge.audit.key_path, ruri=RURI,
                              clock=harness.clock, request_bytes=LIMIT)
    gov = Governor.from_config(config, audit=log, dispatcher=harness.dispatcher,
                               clock=harness.clock)
    points = [{"positions": [0.5, 1e-05], "time_from_start_s": t + 1.0} for t in range(100)]
    params = {"joints": ["j0", "j1"], "points": points}
    assert len(canonical_v1(params)) > LIMIT
    done = await gov.decide(command("arm_joint", params), OPS)
    assert (done.outcome, done.error_code, done.reason) == (
        Outcome.DENIED, ErrorCode.PAYLOAD_TOO_LARGE, "params_too_large_to_log")
    assert harness.dispatcher.calls == []  # nothing reached the robot
    small = {"joints": ["j0"], "points": points[:3]}
    small["points"] = [{**p, "positions": [0.5]} for p in small["points"]]
    assert (await gov.decide(command("arm_joint", small), OPS)).outcome is Outcome.EXECUTED
    await log.close()
    refused, executed = (json.loads(line) for line in
                         Path(config.bridge.audit.path).read_bytes().splitlines()[-2:])
    assert refused["params"]["omitted"] == "too_large_to_log"
    assert refused["deny_reason"] == "PAYLOAD_TOO_LARGE:params_too_large_to_log"
    assert executed["params"] == small


def test_the_bound_is_three_times_the_body_limit_and_at_least_64_kib() -> None:
    assert request_bytes_limit(256) == 64 * 1024
    assert request_bytes_limit(64 * 1024) == 3 * 64 * 1024
    assert request_bytes_limit(16 << 20) == 48 << 20


_KEY = st.text(st.characters(blacklist_categories=("Cs",)), max_size=8)
_NUMBER = (st.integers(-(2**70), 2**70) | st.floats(allow_nan=False, allow_infinity=False)
           | st.sampled_from([1e300, -1e300, 1e22, 1e9, 1e-07, -0.0, 50.0]))
_JSON = st.recursive(
    st.none() | st.booleans() | _NUMBER | _KEY,
    lambda inner: st.lists(inner, max_size=12) | st.dictionaries(_KEY, inner, max_size=6),
    max_leaves=40)


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(params=st.dictionaries(_KEY, _JSON, max_size=6))
async def test_entries_are_bounded_and_params_that_fit_are_whole(
        tmp_path_factory: Any, params: dict[str, Any]) -> None:
    tmp = tmp_path_factory.mktemp("bound")
    log = await AuditLog.open(tmp / "audit.jsonl", tmp / "audit.key", ruri=RURI,
                              clock=ManualClock(), request_bytes=LIMIT)
    await log.append(AuditRecord(event=AuditEvent.COMMAND_REJECTED, principal="viewer",
                                 role="GUEST", action_type="stop", params=params,
                                 outcome="denied"))
    await log.close()
    [line] = (tmp / "audit.jsonl").read_bytes().splitlines()
    entry = json.loads(line)
    assert len(line) <= LIMIT + OVERHEAD
    if len(canonical_v1(params)) <= LIMIT:
        assert entry["params"] == json.loads(canonical_v1(params))  # whole
    else:
        compact = msgspec.json.encode(params)
        assert entry["params"] == {"omitted": "too_large_to_log", "json_bytes": len(compact),
                                   "sha256": hashlib.sha256(compact).hexdigest(),
                                   "limit_bytes": LIMIT}
    body = {k: v for k, v in entry.items() if k not in ("audit_id", "sig")}
    assert entry["audit_id"] == "sha256:" + hashlib.sha256(canonical_json(body)).hexdigest()


async def test_the_bridge_s_own_facts_are_never_cut(tmp_path: Path) -> None:
    """A start's `left_running` (each arm's trajectory as sent) is what the next start takes
    back: bounded where it is made, never replaced by a marker."""
    log = await AuditLog.open(tmp_path / "audit.jsonl", tmp_path / "audit.key", ruri=RURI,
                              clock=ManualClock(), request_bytes=LIMIT)
    facts = {"left_running": {"arms": [{"params": {"positions": [1e9] * 400}}]}}
    await log.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED, params=facts))
    await log.close()
    [line] = (tmp_path / "audit.jsonl").read_bytes().splitlines()
    assert json.loads(line)["params"] == json.loads(canonical_v1(facts))


_ANY_NUMBER = st.integers(-(10**400), 10**400) | st.floats(allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(value=st.recursive(
    st.none() | st.booleans() | _ANY_NUMBER | _KEY,
    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(_KEY, inner, max_size=6),
    max_leaves=30), exponent=st.booleans())
def test_the_size_walk_is_the_canonical_size(value: Any, exponent: bool) -> None:
    """Red team 28: `size_within` is exact, infinities too (a stop's `1e400`, written null),
    with or without a float written with an exponent beside (which Python's json writes)."""
    value = [value, 1e-07] if exponent else [value]
    assert size_within(value, 10**9) == len(canonical_v1(value))
