"""One probe per in-scope case: the suite's description turned into requests to the bridge.

A probe returns a `Verdict`: pass, fail (saying what it saw), or n/a (the case presumes a
configuration this bridge does not have, e.g. a confidence gate that blocks when this one
escalates — the other case of the pair then runs). The suite's example actions are mapped to
registry actions (`vendored.json`, `actions`); motion probes send zero velocity. The INVOKE
probes invoke the skill `BridgeUnderTest.skill` picks (one that moves nothing, unless the run
names another), never the suite's example skills.
"""

from __future__ import annotations

import asyncio
import base64
import ipaddress
import time
import uuid
from collections.abc import Awaitable, Callable
from typing import Any, Literal, TypeGuard
from urllib.parse import urlsplit

import msgspec

from .bridge import Body, BridgeUnderTest, ProbeError, Reply, message_id
from .suite import Case

Outcome = Literal["pass", "fail", "n/a"]


class Verdict(msgspec.Struct, frozen=True):
    outcome: Outcome
    detail: str = ""


def passed(detail: str = "") -> Verdict:
    return Verdict("pass", detail)


def failed(detail: str) -> Verdict:
    return Verdict("fail", detail)


Probe = Callable[[BridgeUnderTest, Case], Awaitable[Verdict]]
PROBES: dict[str, Probe] = {}


def probe(*case_ids: str) -> Callable[[Probe], Probe]:
    def register(fn: Probe) -> Probe:
        for case_id in case_ids:
            PROBES[case_id] = fn
        return fn
    return register


ZERO_MOVE: Body = {"linear_x": 0.0, "angular_z": 0.0, "duration_s": 0.2}


def _refused(reply: Reply) -> bool:
    return reply.status >= 400 and reply.get("outcome") != "executed"


# -- L1 -------------------------------------------------------------------------------------

@probe("L1-RURI-001", "L1-RURI-002", "L1-RURI-003")
async def ruri_format(bridge: BridgeUnderTest, case: Case) -> Verdict:
    """The suite's RURI on a command: a valid one names another robot (refused as such), an
    invalid one is refused for its grammar."""
    body = {"message_type": 1, "ruri": case.input["ruri"], "action": "unlock",
            "parameters": {"name": "conformance-probe"}, "message_id": message_id()}
    reply = await bridge.command("OWNER", body)
    if reply.get("error_code") != "INVALID_RURI":
        return failed(f"expected INVALID_RURI, got {reply.describe()}")
    parsed = reply.get("reason") == "not_this_robot"
    if parsed != case.expect["valid"]:
        return failed(f"{case.input['ruri']} taken as {'valid' if parsed else 'invalid'}: "
                      f"{reply.describe()}")
    return passed(reply.get("reason") or "")


@probe("L1-MDNS-001")
async def mdns_advert(bridge: BridgeUnderTest, case: Case) -> Verdict:
    from rcan_rtps.bridge.mdns import SERVICE_TYPE, RcanBrowser

    wanted = case.input["service_type"]
    if SERVICE_TYPE.removesuffix(".local.") != wanted:
        return failed(f"advertised as {SERVICE_TYPE}, not {wanted}")
    host = urlsplit(bridge.url).hostname or ""
    try:
        interfaces = [str(ipaddress.ip_address(host))]
    except ValueError:
        interfaces = None  # a name: browse everywhere
    async with RcanBrowser(interfaces=interfaces) as browser:
        try:
            robots = await browser.wait_for(
                lambda found: any(r.txt.get("api") == bridge.url for r in found), 8.0)
        except TimeoutError:
            return failed(f"no {wanted} advert with api={bridge.url} within 8 s")
    [robot] = [r for r in robots if r.txt.get("api") == bridge.url]
    missing = [k for k in case.expect["required_txt_keys"] if not robot.txt.get(k)]
    if missing:
        return failed(f"TXT lacks {missing}")
    return passed(", ".join(f"{k}={robot.txt[k]}" for k in case.expect["required_txt_keys"]))


@probe("L1-RBAC-001")
async def guest_cannot_command(bridge: BridgeUnderTest, case: Case) -> Verdict:
    body = {"action": "move", "params": ZERO_MOVE, "message_id": message_id()}
    reply = await bridge.command("GUEST", body)
    expected = (case.expect["http_status"], case.expect["error_code"])
    if (reply.status, reply.get("error_code")) != expected:
        return failed(f"expected {expected}, got {reply.describe()}")
    return passed()


@probe("L1-AUDIT-001")
async def audit_entry_fields(bridge: BridgeUnderTest, case: Case) -> Verdict:
    since = await bridge.head_seq()
    mid = message_id()
    reply = await bridge.command("USER", {"action": "move", "params": ZERO_MOVE,
                                          "message_id": mid})
    if reply.get("outcome") != "executed":
        return failed(f"the USER's command was not dispatched: {reply.describe()}")
    entry = await bridge.wait_for_entry(since, lambda e: e.get("message_id") == mid)
    if entry is None:
        return failed(f"no audit entry with message_id {mid}")
    missing = [f for f in case.expect["audit_entry_contains"] if entry.get(f) in (None, "")]
    if missing:
        return failed(f"entry {entry.get('seq')} lacks {missing}")
    return passed(f"entry {entry['seq']} ({entry['event']})")


@probe("L1-SCHEMA-001")
async def malformed_rejected(bridge: BridgeUnderTest, case: Case) -> Verdict:
    reply = await bridge.command("USER", case.input["message"])
    if (reply.status, reply.get("error_code")) != (400, case.expect["error_code"]):
        return failed(f"expected 400 {case.expect['error_code']}, got {reply.describe()}")
    return passed(str(reply.get("reason") or ""))


# -- L2 -------------------------------------------------------------------------------------

@probe("L2-SAFE-001")
async def estop_blocks_commands(bridge: BridgeUnderTest, case: Case) -> Verdict:
    raised = await _raise_estop(bridge)
    if raised is not None:
        return raised
    try:
        since = await bridge.head_seq()
        mid = message_id()
        reply = await bridge.command("USER", {"action": "move", "params": ZERO_MOVE,
                                              "message_id": mid})
    finally:
        await bridge.clear_estop()
    return _refusal(reply, case, await _entry(bridge, since, mid))


@probe("L2-INJECT-001")
async def injected_text_blocked(bridge: BridgeUnderTest, case: Case) -> Verdict:
    since = await bridge.head_seq()
    params = {**ZERO_MOVE, **case.input["payload"]}
    reply = await bridge.command("USER", {"action": "move", "params": params,
                                          "message_id": message_id()})
    if not _refused(reply):
        return failed(f"dispatched: {reply.describe()}")
    entry = await bridge.wait_for_entry(since, lambda e: e.get("event") == "COMMAND_REJECTED")
    if entry is None:
        return failed("refused, but no COMMAND_REJECTED entry")
    return passed(f"{reply.describe()}; audited as entry {entry['seq']}")


@probe("L2-CONF-001", "L2-CONF-002")
async def confidence_gate(bridge: BridgeUnderTest, case: Case) -> Verdict:
    ai = case.input["ai_command"]
    mid = message_id()
    reply = await bridge.command("USER", {
        "action": "move", "params": ZERO_MOVE, "message_id": mid, "ai_provider": "conformance",
        "ai_model": "probe", "confidence": ai["confidence"]})
    escalates = case.input["confidence_gate"]["on_fail"] == "escalate"
    if reply.get("outcome") == "pending_auth":
        await bridge.call("USER", "POST", "/api/hitl/withdraw",
                          {"pending_id": reply.get("pending_id")})
        return passed("held for approval (then withdrawn)") if escalates else Verdict(
            "n/a", "this bridge's confidence gate escalates (see the case that escalates)")
    if reply.get("reason") == "confidence_below_gate":
        return Verdict("n/a", "this bridge's confidence gate blocks (see the case that "
                              "blocks)") if escalates else passed(reply.describe())
    return failed(f"confidence {ai['confidence']} neither blocked nor held: {reply.describe()}")


@probe("L2-SAFE-002")
async def silence_safe_stops(bridge: BridgeUnderTest, case: Case) -> Verdict:
    since = await bridge.head_seq()
    mid = message_id()
    held = {"linear_x": 0.0, "angular_z": 0.0}  # a held stream: it needs its sender
    reply = await bridge.command("USER", {"action": "move", "params": held, "message_id": mid})
    if reply.get("outcome") != "executed":
        return failed(f"the USER's move was not dispatched: {reply.describe()}")
    started = time.monotonic()
    move = await _entry(bridge, since, mid)
    if move is None:
        return failed("no entry for the move")
    # Silence from here: no command and no heartbeat as the USER.
    stop = await bridge.wait_for_entry(
        since, lambda e: e.get("event") == case.expect["audit_event"]
        and e.get("principal") == move.get("principal"), timeout_s=SESSION_WAIT_S)
    if stop is None:
        return failed(f"no {case.expect['audit_event']} within {SESSION_WAIT_S:g} s of silence")
    # STATUS is told once the halt is sent and its entry durable: a read racing the entry may
    # see the state before it.
    state = await _status_state(bridge, case.expect["robot_state"], within_s=3.0)
    if state != case.expect["robot_state"]:
        return failed(f"STATUS says {state!r} 3 s after the safe stop")
    return passed(f"after {time.monotonic() - started:.1f} s of silence: entry {stop['seq']}, "
                  f"state {state}")


SESSION_WAIT_S = 30.0


@probe("L2-HMAC-001")
async def tampered_entry_breaks_chain(bridge: BridgeUnderTest, case: Case) -> Verdict:
    from rcan_rtps.governance import AuditIntegrityError, verify_bytes

    key = await _audit_key(bridge)
    lines = await _audit_lines(bridge)
    if len(lines) < 2:
        return failed("the log has fewer than 2 entries to tamper with")
    verify_bytes(b"".join(lines), key)  # untampered: raises if the bridge's chain is broken
    victim = len(lines) // 2
    tampered = list(lines)
    tampered[victim] = lines[victim].replace(b'"outcome":"', b'"outcome":"X', 1)
    if tampered[victim] == lines[victim]:
        tampered[victim] = lines[victim].replace(b'"event":"', b'"event":"X', 1)
    try:
        verify_bytes(b"".join(tampered), key)
    except AuditIntegrityError as exc:
        if exc.seq != victim + 1:
            return failed(f"tampered entry {victim + 1}, but verification blamed {exc.seq}")
        return passed(f"{len(lines)} entries verify; entry {victim + 1} changed: refused")
    return failed(f"entry {victim + 1} changed, and the chain still verified")


# -- L3 -------------------------------------------------------------------------------------

@probe("L3-AI-001")
async def ai_identity_audited(bridge: BridgeUnderTest, case: Case) -> Verdict:
    ai = case.input["ai_metadata"]
    since, mid = await bridge.head_seq(), message_id()
    reply = await bridge.command("USER", {
        "action": "move", "params": ZERO_MOVE, "message_id": mid,
        "ai_provider": ai["provider"], "ai_model": ai["model"], "confidence": ai["confidence"]})
    if reply.get("outcome") != "executed":
        return failed(f"not dispatched: {reply.describe()}")
    entry = await _entry(bridge, since, mid)
    if entry is None:
        return failed(f"no entry for {mid}")
    recorded = entry.get("ai") or {}
    missing = [f for f in case.expect.get("audit_ai_fields", ("provider", "model", "confidence"))
               if recorded.get(f.removeprefix("ai.")) is None]
    if missing:
        return failed(f"entry {entry['seq']}'s ai lacks {missing}: {recorded}")
    return passed(f"entry {entry['seq']}: ai {recorded}")


@probe("L3-HITL-001", "L3-HITL-002")
async def hitl_gate(bridge: BridgeUnderTest, case: Case) -> Verdict:
    """A gated action waits for approval; a GUEST's approval is refused, an OWNER's runs it."""
    since, mid = await bridge.head_seq(), message_id()
    reply = await bridge.command("USER", {"action": "arm_joint", "message_id": mid,
                                          "params": await _still_arm(bridge)})
    if reply.get("outcome") != "pending_auth":
        return failed(f"arm_joint (the suite's arm_extend) was not held: {reply.describe()}")
    pending = {"pending_id": reply.get("pending_id")}
    dispatched = await bridge.wait_for_entry(
        since, lambda e: e.get("message_id") == mid and e.get("event") == "COMMAND_DISPATCHED",
        timeout_s=0.5)
    if dispatched is not None:
        return failed(f"held, yet dispatched (entry {dispatched['seq']})")
    if case.id == "L3-HITL-001":
        await bridge.call("USER", "POST", "/api/hitl/withdraw", pending)
        return passed(f"held as {pending['pending_id']} (then withdrawn)")
    guest = await bridge.call("GUEST", "POST", "/api/hitl/authorize", pending)
    if (guest.status, guest.get("error_code")) != (403, "INSUFFICIENT_PRIVILEGES"):
        await bridge.call("USER", "POST", "/api/hitl/withdraw", pending)
        return failed(f"a GUEST's approval: {guest.describe()}")
    owner = await bridge.call("OWNER", "POST", "/api/hitl/authorize", pending)
    if owner.get("outcome") != "executed":
        return failed(f"an OWNER's approval: {owner.describe()}")
    return passed("GUEST refused (403 INSUFFICIENT_PRIVILEGES); OWNER's approval executed it")


@probe("L3-THOUGHT-001")
async def thought_log_scope(bridge: BridgeUnderTest, case: Case) -> Verdict:
    """A thought made here (an AI's zero move with its reasoning), read as the case's USER
    (operational scopes: no reasoning) and as the OWNER (config scope: the reasoning)."""
    thought = f"conformance-{message_id()}"
    reply = await bridge.command("USER", {
        "action": "move", "params": ZERO_MOVE, "message_id": message_id(),
        "ai_provider": "conformance", "ai_model": "probe", "confidence": 0.9,
        "thought_id": thought, "ai_reasoning": "conformance probe: hold still"})
    if reply.get("outcome") is None:
        return failed(f"the AI command was not decided: {reply.describe()}")
    path = f"/api/thoughts/{thought}"
    seen = await bridge.call("USER", "GET", path)
    if seen.status != case.expect.get("http_status", 200):
        return failed(f"GET {path} as USER: {seen.describe()}")
    absent = [f for f in case.expect["response_contains"] if seen.get(f) is None]
    leaked = [f for f in case.expect["response_excludes"] if seen.get(f) is not None]
    if absent or leaked:
        return failed(f"as USER: missing {absent}, shown {leaked}")
    owner = await bridge.call("OWNER", "GET", path)
    if owner.get("reasoning") is None:
        return failed(f"the OWNER (config scope) was not shown the reasoning: {owner.describe()}")
    return passed("USER: confidence, no reasoning; OWNER: the reasoning")


@probe("L3-AI-002")
async def ai_without_model_refused(bridge: BridgeUnderTest, case: Case) -> Verdict:
    ai = case.input["ai_metadata"]
    since, mid = await bridge.head_seq(), message_id()
    reply = await bridge.command("USER", {
        "action": "move", "params": ZERO_MOVE, "message_id": mid,
        "ai_provider": ai["provider"], "confidence": ai["confidence"]})
    if not _refused(reply):
        return failed(f"an AI command without ai.model was dispatched: {reply.describe()}")
    if reply.get("error_code") != case.expect["error_code"]:
        return failed(f"expected {case.expect['error_code']}, got {reply.describe()}")
    entry = await _entry(bridge, since, mid)
    if not _audited_as_refused(entry):
        return failed(f"refused, but audited as {entry and entry.get('event')}")
    return passed(f"{reply.describe()}; entry {entry['seq']}")


@probe("L3-CHAIN-001")
async def offline_export_verifies(bridge: BridgeUnderTest, case: Case) -> Verdict:
    """The §20 JSONL export, checked here with nothing but the node manifest's public key: every
    entry's signature and link, and the issuer's signature over the RFC 6962 root of the
    exported lines; one byte changed, both checks refuse."""
    from cryptography.exceptions import InvalidSignature

    from rcan_rtps.governance import AuditIntegrityError, verify_bytes
    from rcan_rtps.governance.merkle import leaf_hash, root_of

    key = await _audit_key(bridge)
    path = f"/api/v1/audit?format={case.input['export_format']}"
    export = await bridge.call("OWNER", "GET", path)
    raw = export.body if isinstance(export.body, str) else None
    if export.status != 200 or raw is None:
        return failed(f"GET {path}: HTTP {export.status}")
    header, *entries = raw.encode().splitlines()
    if msgspec.json.decode(header).get("count") != len(entries):
        return failed(f"the export's header says {header!r}, and {len(entries)} entries follow")
    root_text, sig_text = export.headers.get("X-Audit-Chain-Root", ""), export.headers.get(
        "X-Audit-Issuer-Sig", "")
    root = root_of([leaf_hash(line) for line in entries])
    if root_text != "sha256:" + root.hex():
        return failed(f"X-Audit-Chain-Root {root_text} is not the root of the exported lines")
    try:
        key.verify(base64.b64decode(sig_text.removeprefix("ed25519:")), root)
    except (InvalidSignature, ValueError):
        return failed("X-Audit-Issuer-Sig does not verify with the node manifest's key")
    data = b"".join(line + b"\n" for line in entries)
    try:
        verify_bytes(data, key)
    except AuditIntegrityError as exc:
        return failed(f"the untampered export does not verify: {exc}")
    victim = len(entries) // 2
    tampered = list(entries)
    tampered[victim] = entries[victim].replace(b'"outcome":"', b'"outcome":"X', 1)
    try:
        verify_bytes(b"".join(line + b"\n" for line in tampered), key)
    except AuditIntegrityError:
        if root_of([leaf_hash(line) for line in tampered]) == root:
            return failed("a tampered export kept its root")
        return passed(f"{len(entries)} exported entries verify offline; entry {victim + 1} "
                      "changed: refused")
    return failed(f"entry {victim + 1} changed, and the export still verified")


# -- INVOKE (§19) ---------------------------------------------------------------------------

@probe("L1-INVOKE-001")
async def invoke_routed_to_skill(bridge: BridgeUnderTest, case: Case) -> Verdict:
    """A USER's INVOKE of a listed skill runs it: its action is dispatched as that skill."""
    skill = await bridge.skill()
    since, mid = await bridge.head_seq(), invoke_id()
    reply = await bridge.invoke("USER", skill, mid,
                                timeout_ms=case.input.get("payload", {}).get("timeout_ms"))
    if (reply.status, reply.get("type"), reply.get("status")) != (200, "INVOKE_RESULT",
                                                                  "success"):
        return failed(f"{skill.name}: {_invoke_reply(reply)}")
    entry = await bridge.wait_for_entry(
        since, lambda e: e.get("message_id") == mid and e.get("event") == "COMMAND_DISPATCHED")
    if entry is None:
        return failed(f"{skill.name} answered success, but no COMMAND_DISPATCHED entry")
    ran_as = (entry.get("rcan") or {}).get("skill")
    if ran_as != skill.name or entry.get("action_type") != skill.action:
        return failed(f"entry {entry['seq']}: {entry.get('action_type')} as skill {ran_as!r}")
    return passed(f"{skill.name} ran as {skill.action} (entry {entry['seq']})")


@probe("L1-INVOKE-002")
async def guest_cannot_invoke(bridge: BridgeUnderTest, case: Case) -> Verdict:
    skill = await bridge.skill()
    if skill.role == "GUEST":
        return failed(f"{skill.name} is open to GUEST here: the case needs a skill that "
                      "requires control scope (name one with --skill)")
    since, mid = await bridge.head_seq(), invoke_id()
    reply = await bridge.invoke("GUEST", skill, mid)
    expected = (case.expect["http_status"], case.expect["error_code"])
    if (reply.status, reply.get("error_code")) != expected:
        return failed(f"expected {expected}, got {_invoke_reply(reply)}")
    entry = await _entry(bridge, since, mid)
    if not _audited_as_refused(entry):
        return failed(f"refused, but audited as {entry and entry.get('event')}")
    return passed(f"{skill.name} (needs {skill.role}): {reply.status} "
                  f"{reply.get('error_code')}, status {reply.get('status')}")


@probe("L1-INVOKE-003")
async def invoke_result_fields(bridge: BridgeUnderTest, case: Case) -> Verdict:
    skill = await bridge.skill()
    mid = invoke_id()
    reply = await bridge.invoke("USER", skill, mid)
    if reply.get("type") != "INVOKE_RESULT":
        return failed(f"not an INVOKE_RESULT: {_invoke_reply(reply)}")
    missing = [f for f in case.expect["required_fields"] if reply.get(f) is None]
    if missing:
        return failed(f"INVOKE_RESULT lacks {missing}: {reply.body!r}")
    if reply.get("invoke_id") != mid:
        return failed(f"invoke_id {reply.get('invoke_id')!r} does not echo the INVOKE's {mid}")
    if reply.get("status") not in ("success", "failure") or not isinstance(
            reply.get("payload"), dict):
        return failed(f"status {reply.get('status')!r}, payload {reply.get('payload')!r}")
    return passed(f"invoke_id {mid}, status {reply.get('status')}, "
                  f"payload {reply.get('payload')}")


@probe("L2-INVOKE-001")
async def estop_blocks_invoke(bridge: BridgeUnderTest, case: Case) -> Verdict:
    skill = await bridge.skill()
    raised = await _raise_estop(bridge)
    if raised is not None:
        return raised
    try:
        since, mid = await bridge.head_seq(), invoke_id()
        reply = await bridge.invoke("USER", skill, mid)
    finally:
        await bridge.clear_estop()
    if reply.get("status") == "success":
        return failed(f"{skill.name} ran under the e-stop: {_invoke_reply(reply)}")
    return _refusal(reply, case, await _entry(bridge, since, mid))


@probe("L3-INVOKE-001")
async def invoke_result_audited(bridge: BridgeUnderTest, case: Case) -> Verdict:
    """The INVOKE's INVOKE_RESULT is in the log with its invoke_id, after the entries of what
    the skill did: the lifecycle reads back from the audit alone."""
    skill = await bridge.skill()
    since, mid = await bridge.head_seq(), invoke_id(case.input.get("invoke_id", "inv"))
    reply = await bridge.invoke("USER", skill, mid)
    if reply.get("type") != "INVOKE_RESULT":
        return failed(f"not an INVOKE_RESULT: {_invoke_reply(reply)}")
    result = await bridge.wait_for_entry(
        since, lambda e: e.get("event") == "INVOKE_RESULT" and e.get("invoke_id") == mid)
    if result is None:
        return failed(f"no INVOKE_RESULT entry with invoke_id {mid}")
    missing = [f for f in case.expect["audit_entry_contains"] if result.get(f) in (None, "")]
    if missing:
        return failed(f"entry {result['seq']} lacks {missing}")
    if result.get("status") != reply.get("status"):
        return failed(f"entry {result['seq']} says {result.get('status')!r}, the INVOKE_RESULT "
                      f"{reply.get('status')!r}")
    before = [e for e in await bridge.entries_since(since)
              if e.get("message_id") == mid and e["seq"] < result["seq"]]
    if not before:
        return failed(f"entry {result['seq']}: no entry of the INVOKE's command before it")
    lifecycle = " → ".join(f"{e['event']} {e['seq']}" for e in [*before, result])
    return passed(f"{mid}: {lifecycle} (status {result['status']}, outcome "
                  f"{result['outcome']})")


def invoke_id(prefix: str = "inv") -> str:
    """A fresh INVOKE msg_id (a repeated one would be answered from its first decision)."""
    return f"{prefix}-{uuid.uuid4().hex[:16]}"


def _invoke_reply(reply: Reply) -> str:
    error = reply.get("error")
    fields = {k: reply.get(k) for k in ("status", "outcome", "error_code", "reason")
              if reply.get(k) is not None}
    if isinstance(error, dict):
        fields["error"] = f"{error.get('code')} {error.get('name')}: {error.get('message')}"
    return f"HTTP {reply.status} {fields or reply.body!r}"


# -- helpers --------------------------------------------------------------------------------

async def _status_state(bridge: BridgeUnderTest, wanted: str, within_s: float) -> Any:
    deadline = time.monotonic() + within_s
    while True:
        state = (await bridge.status()).get("state")
        if state == wanted or time.monotonic() > deadline:
            return state
        await asyncio.sleep(0.1)


async def _entry(bridge: BridgeUnderTest, since: int, mid: str) -> Body | None:
    return await bridge.wait_for_entry(since, lambda e: e.get("message_id") == mid)


def _refusal(reply: Reply, case: Case, entry: Body | None) -> Verdict:
    reason = case.expect.get("reason")
    if not _refused(reply):
        return failed(f"dispatched: {reply.describe()}")
    if reply.get("error_code") != case.expect["error_code"] or reply.get("reason") != reason:
        return failed(f"expected {case.expect['error_code']}/{reason}, got {reply.describe()}")
    if not _audited_as_refused(entry):
        return failed(f"refused, but audited as {entry and entry.get('event')}")
    return passed(f"{reply.describe()}; entry {entry['seq']}")


async def _raise_estop(bridge: BridgeUnderTest) -> Verdict | None:
    """Latch the e-stop (a GUEST's, if given: anyone may); a failed verdict if it did not."""
    raised = await bridge.command("GUEST" if bridge.has("GUEST") else "OWNER",
                                  {"action": "estop", "params": {"reason": "conformance"}})
    if raised.get("outcome") != "executed":
        return failed(f"the e-stop did not latch: {raised.describe()}")
    return None


def _audited_as_refused(entry: Body | None) -> TypeGuard[Body]:
    return entry is not None and entry.get("event") == "COMMAND_REJECTED"


async def _still_arm(bridge: BridgeUnderTest) -> dict[str, Any]:
    """A trajectory to where the arm already is (it does not move), from STATUS."""
    joints = ((await bridge.status()).get("telemetry") or {}).get("joints") or {}
    # STATUS lists every joint the robot reports; wheels are not the arm's (a heuristic: a
    # robot whose arm joints say "wheel" needs its own probe).
    names, positions = joints.get("names") or [], joints.get("positions") or []
    if len(names) != len(positions):
        raise ProbeError(f"STATUS joints: {len(names)} names, {len(positions)} positions")
    held = [(n, p) for n, p in zip(names, positions, strict=True) if "wheel" not in n]
    if not held:
        raise ProbeError("STATUS shows no arm joints to hold still")
    return {"joints": [n for n, _ in held], "positions": [p for _, p in held],
            "duration_s": 1.0}


async def _audit_lines(bridge: BridgeUnderTest) -> list[bytes]:
    return [line + b"\n" for line in await bridge.lines_since(0)]


async def _audit_key(bridge: BridgeUnderTest) -> Any:
    """The bridge's audit key, from its public node manifest (`ed25519_public_key`)."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    reply = await bridge.call("OWNER", "GET", "/.well-known/rcan-node.json", public=True)
    raw = reply.get("ed25519_public_key") if reply.status == 200 else None
    if not isinstance(raw, str):
        raise ProbeError(f"no Ed25519 audit key in the node manifest: {reply.describe()}")
    try:
        padded = raw + "=" * (-len(raw) % 4)
        return Ed25519PublicKey.from_public_bytes(base64.urlsafe_b64decode(padded))
    except ValueError as exc:
        raise ProbeError(f"the node manifest's key does not load: {exc}") from None
