"""RCAN's AUTHORIZE (§16.4) and INVOKE / INVOKE_RESULT / INVOKE_CANCEL (§19) messages.

rcan-spec writes each of them more than one way (see tests/data/rcan-spec/SOURCE.md); every
form below is one the spec's text or its JSON schemas give, numbered by the canonical
MessageType table (§3, and the SDK's `rcan.message.MessageType`):

- INVOKE (11): §19.2 `{type: "INVOKE", skill, params?, timeout_ms?, msg_id}`; §3's payload
  table names the skill `skill_id`. A skill is what the config declares (`bridge.skills`),
  never a registry action directly: the API maps it (`api/_invoke.py`).
- INVOKE_CANCEL (13): §19.4 `{type: "INVOKE_CANCEL", payload: {msg_id, reason?,
  cancel_timeout_ms?}}`, or schemas/messages/invoke-cancel.json's flat form
  `{message_type, ruri, principal_id, session_token, cancel_msg_id, reason?, timestamp_ms,
  message_id}` (which numbers it 15; canonical is 13).
- AUTHORIZE (45): schemas/messages/authorize.json `{message_type, ruri, thought_id,
  principal_id, decision: APPROVE|REJECT, timestamp_ms, message_id}` (which numbers it 9),
  §16.4's `decision: approve|deny`; a held command is named by its `thought_id` (the schema's)
  or its `pending_id` (§3's PENDING_AUTH payload, and ours).
- AUTHORIZE signed as the SDK signs (`rcan.signing.sign_message`): the SDK has
  `MessageType.AUTHORIZE` (45) but no builder of it, and its `to_dict()` writes neither a
  message's `type` nor its `payload`, and signs neither: what it signs is a COMMAND's `rcan`,
  `msg_id`, `timestamp`, `cmd`, `target` and `params`. So a signed AUTHORIZE is the SDK's
  COMMAND envelope with `cmd: "AUTHORIZE"` (the type's name), `target` this robot's RURI and
  the review in `params` — `{decision, pending_id, command_message_id, reason?}`, where the
  signature covers them: the held command by its `pending_id` (made by the bridge, never
  reused) and by the `message_id` its PENDING_AUTH shows, so a signature names one held
  command and no other (`governance.review` checks the second).
- INVOKE_RESULT (12) is what the bridge answers an INVOKE with (`InvokeResult`).

Envelope fields (`rcan_version`, `ruri`, `timestamp_ms`, `message_id`) are accepted on each, and
§3.5 applies as to any message: with `rcan_version`, unknown fields are ignored and recorded.
The official SDK's envelope (`rcan.message.RCANMessage.to_dict()`, which has no builder of
these) times a message by `timestamp`, in Unix seconds: read as its sent time when
`timestamp_ms` is not given, as for the SDK's COMMAND. Its `msg_id` is an INVOKE_CANCEL's or
an AUTHORIZE's own id, as `message_id` is (§19.4's `msg_id` is in `payload`: the INVOKE's);
an INVOKE's `message_id` is its `msg_id`. Given twice, each must agree.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec

from ._errors import SchemaValidationError
from ._signatures import signed_bytes
from ._types import ShortText, Strict, TimestampMs, whole
from ._v3 import Envelope, MsgId, Signature, Text, VersionText

INVOKE_TYPE, INVOKE_RESULT_TYPE, INVOKE_CANCEL_TYPE, AUTHORIZE_TYPE = 11, 12, 13, 45
AUTHORIZE_CMD = "AUTHORIZE"  # the SDK COMMAND envelope's `cmd` of a signed AUTHORIZE
DEFAULT_TIMEOUT_MS = 30_000  # §19.2
DEFAULT_CANCEL_TIMEOUT_MS = 5_000  # §19.4

# §19.7: lowercase words joined by underscores, a reverse-DNS prefix for third parties.
SkillName = Annotated[str, msgspec.Meta(
    min_length=1, max_length=128, pattern=whole(r"[a-z][a-z0-9_]*(\.[a-z][a-z0-9_]*)*"))]
UnixSeconds = Annotated[float, msgspec.Meta(ge=0.0, le=1e11)]  # the SDK envelope's `timestamp`
Millis = Annotated[int, msgspec.Meta(ge=1, le=86_400_000)]


class InvokeMessage(Strict, frozen=True, kw_only=True):
    type: Literal["INVOKE"] | None = None
    message_type: Literal[11] | None = None
    skill: SkillName | None = None
    skill_id: SkillName | None = None  # §3's payload table
    params: dict[str, Any] = msgspec.field(default_factory=dict)
    timeout_ms: Millis = DEFAULT_TIMEOUT_MS
    msg_id: MsgId | None = None
    # The envelope's name of the same id (§3): read, never ignored — ignored, each copy of
    # an INVOKE got an id of its own and §8.3's replay window let a replay run it again.
    message_id: MsgId | None = None
    rcan_version: VersionText | None = None
    ruri: Text | None = None
    timestamp_ms: TimestampMs | None = None
    timestamp: UnixSeconds | None = None


class CancelPayload(Strict, frozen=True, kw_only=True):
    msg_id: MsgId
    reason: ShortText | None = None
    cancel_timeout_ms: Millis = DEFAULT_CANCEL_TIMEOUT_MS


class InvokeCancelMessage(Strict, frozen=True, kw_only=True):
    type: Literal["INVOKE_CANCEL"] | None = None
    message_type: Literal[13] | None = None
    payload: CancelPayload | None = None  # §19.4
    cancel_msg_id: MsgId | None = None  # schemas/messages/invoke-cancel.json
    reason: ShortText | None = None
    principal_id: Annotated[str, msgspec.Meta(min_length=1, max_length=128)] | None = None
    # The schema's JWT: authentication is the Authorization header's, so this is never read
    # (and never recorded: it is a credential).
    session_token: Annotated[str, msgspec.Meta(min_length=1, max_length=8192)] | None = None
    message_id: MsgId | None = None
    msg_id: MsgId | None = None  # the SDK envelope's: its own id (the INVOKE's is in payload)
    rcan_version: VersionText | None = None
    ruri: Text | None = None
    timestamp_ms: TimestampMs | None = None
    timestamp: UnixSeconds | None = None


class AuthorizeMessage(Strict, frozen=True, kw_only=True):
    type: Literal["AUTHORIZE"] | None = None
    message_type: Literal[45] | None = None
    decision: Literal["APPROVE", "REJECT", "approve", "deny"]
    thought_id: Annotated[str, msgspec.Meta(min_length=1, max_length=128)] | None = None
    pending_id: Annotated[str, msgspec.Meta(min_length=1, max_length=64)] | None = None
    principal_id: Annotated[str, msgspec.Meta(min_length=1, max_length=128)] | None = None
    reason: ShortText | None = None  # ours: recorded with the review
    message_id: MsgId | None = None
    msg_id: MsgId | None = None  # the SDK envelope's
    rcan_version: VersionText | None = None
    ruri: Text | None = None
    timestamp_ms: TimestampMs | None = None
    timestamp: UnixSeconds | None = None


PendingId = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
ReviewDecision = Literal["APPROVE", "REJECT", "approve", "deny"]


class AuthorizeParams(Strict, frozen=True, kw_only=True):
    """A signed AUTHORIZE's `params`: the review, all of it under the signature."""

    decision: ReviewDecision
    pending_id: PendingId
    command_message_id: MsgId  # the held command's (its PENDING_AUTH's original_command)
    reason: ShortText | None = None


class SignedAuthorizeMessage(Strict, frozen=True, kw_only=True):
    """AUTHORIZE in the SDK's COMMAND envelope, as `sign_message(RCANMessage(cmd="AUTHORIZE",
    target=ruri, params=...), key).to_dict()` writes it (fields acted on)."""

    rcan: VersionText | None = None
    rcan_version: VersionText | None = None
    msg_id: MsgId
    timestamp: UnixSeconds
    cmd: Literal["AUTHORIZE"]
    target: Text
    params: AuthorizeParams
    sig: Signature | None = None
    firmware_hash: Annotated[str, msgspec.Meta(max_length=256)] | None = None
    attestation_ref: Annotated[str, msgspec.Meta(max_length=2048)] | None = None


# -- what they become -----------------------------------------------------------------------


class Invoke(msgspec.Struct, frozen=True, kw_only=True):
    """A validated INVOKE: which skill, with what the invoker gave (checked against the
    skill's declaration and its action's parameters when it is mapped)."""

    skill: str
    params: dict[str, Any]
    timeout_ms: int
    msg_id: str  # the sender's, or one made for it (§19.2: INVOKE_RESULT's reply_to)
    client_msg_id: bool
    ruri: str | None
    timestamp_ms: int | None
    envelope: Envelope


class InvokeCancel(msgspec.Struct, frozen=True, kw_only=True):
    """A validated INVOKE_CANCEL of the INVOKE whose msg_id is `invoke_id`."""

    invoke_id: str
    reason: str | None
    cancel_timeout_ms: int
    principal_id: str | None
    message_id: str | None
    ruri: str | None
    envelope: Envelope


class Authorization(msgspec.Struct, frozen=True, kw_only=True):
    """A validated AUTHORIZE: a human's word on a held command (§16.4)."""

    verdict: Literal["approve", "deny"]
    pending_id: str | None
    thought_id: str | None
    principal_id: str | None
    reason: str | None
    message_id: str | None
    ruri: str | None
    envelope: Envelope
    # The held command's message_id the review names (a signed AUTHORIZE's, under its sig).
    command_message_id: str | None = None


Message3 = Invoke | InvokeCancel | Authorization


def is_kind(obj: dict[str, Any], name: str, number: int) -> bool:
    """`obj` says it is this message: by §19's `type` or the canonical `message_type`."""
    return obj.get("type") == name or obj.get("message_type") == number


def _sent_at(ms: int | None, seconds: float | None) -> float | None:
    """The message's sent time: `timestamp_ms`, or the SDK envelope's `timestamp`."""
    if ms is None:
        return seconds
    if seconds is not None and abs(seconds - ms / 1000.0) >= 0.001:
        raise SchemaValidationError("$.timestamp", "differs from timestamp_ms")
    return ms / 1000.0


def _own_id(message_id: str | None, msg_id: str | None) -> str | None:
    """The message's own id: `message_id`, or the SDK envelope's `msg_id`."""
    if message_id is not None and msg_id is not None and message_id != msg_id:
        raise SchemaValidationError("$.msg_id", "differs from message_id")
    return message_id or msg_id


def from_invoke(msg: InvokeMessage, ignored: tuple[str, ...], made_id: str) -> Invoke:
    skill = msg.skill or msg.skill_id
    if skill is None:
        raise SchemaValidationError("$.skill", "required: the skill to invoke")
    if msg.skill is not None and msg.skill_id is not None and msg.skill != msg.skill_id:
        raise SchemaValidationError("$.skill_id", "differs from skill")
    given = _own_id(msg.message_id, msg.msg_id)
    msg_id = given or made_id
    return Invoke(skill=skill, params=msg.params, timeout_ms=msg.timeout_ms, msg_id=msg_id,
                  client_msg_id=given is not None, ruri=msg.ruri,
                  timestamp_ms=msg.timestamp_ms,
                  envelope=Envelope(version=msg.rcan_version, msg_id=msg_id, ignored=ignored,
                                    sent_at_s=_sent_at(msg.timestamp_ms, msg.timestamp),
                                    skill=skill))


def from_cancel(msg: InvokeCancelMessage, ignored: tuple[str, ...]) -> InvokeCancel:
    if (msg.payload is None) == (msg.cancel_msg_id is None):
        raise SchemaValidationError("$.payload", "give the INVOKE to cancel once: payload.msg_id"
                                    " (§19.4) or cancel_msg_id")
    if msg.payload is not None:
        invoke_id, timeout = msg.payload.msg_id, msg.payload.cancel_timeout_ms
        reason = msg.payload.reason or msg.reason
    else:
        assert msg.cancel_msg_id is not None
        invoke_id, timeout, reason = msg.cancel_msg_id, DEFAULT_CANCEL_TIMEOUT_MS, msg.reason
    own_id = _own_id(msg.message_id, msg.msg_id)
    return InvokeCancel(invoke_id=invoke_id, reason=reason, cancel_timeout_ms=timeout,
                        principal_id=msg.principal_id, message_id=own_id, ruri=msg.ruri,
                        envelope=Envelope(version=msg.rcan_version, msg_id=own_id,
                                          ignored=ignored,
                                          sent_at_s=_sent_at(msg.timestamp_ms, msg.timestamp)))


def from_authorize(msg: AuthorizeMessage, ignored: tuple[str, ...]) -> Authorization:
    if (msg.pending_id is None) == (msg.thought_id is None):
        raise SchemaValidationError("$.thought_id", "name the held command once: thought_id "
                                    "or pending_id")
    own_id = _own_id(msg.message_id, msg.msg_id)
    return Authorization(verdict=_verdict(msg.decision), pending_id=msg.pending_id,
                         thought_id=msg.thought_id,
                         principal_id=msg.principal_id, reason=msg.reason,
                         message_id=own_id, ruri=msg.ruri,
                         envelope=Envelope(version=msg.rcan_version, msg_id=own_id,
                                           ignored=ignored,
                                           sent_at_s=_sent_at(msg.timestamp_ms, msg.timestamp)))


def from_signed_authorize(msg: SignedAuthorizeMessage, obj: dict[str, Any],
                          ignored: tuple[str, ...]) -> Authorization:
    """`obj`, decoded as `msg`: the signed bytes are made again from what arrived."""
    params = msg.params
    return Authorization(
        verdict=_verdict(params.decision), pending_id=params.pending_id, thought_id=None,
        principal_id=None, reason=params.reason, message_id=msg.msg_id, ruri=msg.target,
        command_message_id=params.command_message_id,
        envelope=Envelope(version=msg.rcan_version or msg.rcan, msg_id=msg.msg_id,
                          sent_at_s=msg.timestamp, ignored=ignored,
                          firmware_hash=msg.firmware_hash, attestation_ref=msg.attestation_ref,
                          sig=msg.sig, signed=signed_bytes(obj) if msg.sig is not None else None))


def _verdict(decision: ReviewDecision) -> Literal["approve", "deny"]:
    return "approve" if decision in ("APPROVE", "approve") else "deny"


# -- INVOKE_RESULT ----------------------------------------------------------------------------

InvokeStatus = Literal["success", "failure", "timeout", "not_found", "unauthorized",
                       "invalid_params", "cancelled"]
# §19.6: each status's error (success has none).
SKILL_ERRORS: dict[str, tuple[int, str]] = {
    "not_found": (7001, "SkillNotFound"),
    "timeout": (7002, "SkillTimeout"),
    "unauthorized": (7003, "SkillUnauthorized"),
    "invalid_params": (7004, "InvalidSkillParams"),
    "conflict": (7005, "SkillConflict"),  # status failure
    "failure": (7006, "SkillFailed"),
    "cancelled": (7007, "SkillCancelled"),
}


class SkillError(msgspec.Struct, frozen=True):
    code: int
    name: str
    message: str


def skill_error(kind: str, message: str) -> SkillError:
    code, name = SKILL_ERRORS[kind]
    return SkillError(code=code, name=name, message=message)


class InvokeResult(msgspec.Struct, omit_defaults=True, kw_only=True):
    """INVOKE_RESULT (§19.3) as this bridge answers an INVOKE (and an INVOKE_CANCEL), with
    the governor's decision fields beside the spec's.

    rcan-spec names the correlation and the output twice: §19.3 (and §3's payload table)
    `reply_to` and `result`; the conformance suite (v1.4, L1-INVOKE-003) `invoke_id` and
    `payload`. Both pairs are written: `invoke_id` is `reply_to`, and `payload` is `result`,
    or `{}` when the skill produced none (the suite requires the field)."""

    type: Literal["INVOKE_RESULT"]  # no default: omit_defaults would drop it
    status: InvokeStatus
    invoke_id: str  # = reply_to: the INVOKE's msg_id (or the one made for it)
    payload: dict[str, Any]  # = result, or {}
    skill: str | None = None
    reply_to: str | None = None
    duration_ms: int | None = None
    result: dict[str, Any] | None = None
    error: SkillError | None = None
    # The governor's decision on the command the skill ran (see DecisionBody).
    outcome: str | None = None
    audit_id: str | None = None
    message_id: str | None = None
    msg_id: str | None = None
    error_code: str | None = None
    reason: str | None = None
    path: str | None = None
    applied: dict[str, Any] | None = None
    goal_id: str | None = None
    ros2_topic: str | None = None
    warnings: list[str] | None = None

