"""Validation at the boundary: raw bytes → NormalizedCommand, or SchemaValidationError."""

from __future__ import annotations

import os
import re
import threading
import uuid
from collections.abc import Callable
from typing import Any, TypeVar

import msgspec

from ._errors import InvalidRuriError, SchemaValidationError, VersionIncompatibleError
from ._invoke import (
    AUTHORIZE_CMD,
    AUTHORIZE_TYPE,
    INVOKE_CANCEL_TYPE,
    INVOKE_TYPE,
    AuthorizeMessage,
    Invoke,
    InvokeCancelMessage,
    InvokeMessage,
    Message3,
    SignedAuthorizeMessage,
    from_authorize,
    from_cancel,
    from_invoke,
    from_signed_authorize,
    is_kind,
)
from ._messages import AiInfo, EnvelopeCommand, NormalizedCommand, SafetyMessage, ShortCommand
from ._ruri import parse_ruri
from ._salvage import (
    MAX_DEPTH,
    duplicate_key,
    nested_deeper_than,
    nonfinite_stop,
    salvage_stop,
    stop_intent,
)
from ._signatures import signed_bytes
from ._types import ActionParams, Confidence, Strict
from ._v3 import (
    Envelope,
    Heartbeat,
    HeartbeatMessage,
    RcanCommand,
    message_version,
    normal_id,
    readable_id,
    split_known,
)
from .actions import Effect, action_spec, names, with_effect

_AT = re.compile(r"^(?P<detail>.*?)(?: - at `(?P<path>[^`]*)`)?$", re.DOTALL)
_ROLE_CLAIMS = ("role", "role_level")
SAFETY_MESSAGE_TYPE = 6  # RCAN SAFETY: ESTOP, STOP, RESUME
HEARTBEAT_MESSAGE_TYPE = 4
_V3_KEYS = ("rcan", "rcan_version", "cmd")  # the SDK's COMMAND (no message_type)
_MESSAGE_ERRORS = (SchemaValidationError, InvalidRuriError, VersionIncompatibleError)
# Overflowing literals (1e400) become ±inf here so the typed pass rejects them *with* their path.
_DECODER = msgspec.json.Decoder(float_hook=float)

T = TypeVar("T")


def validation_path(exc: msgspec.ValidationError, prefix: str = "$") -> tuple[str, str]:
    """Split a msgspec error into (JSON path under `prefix`, detail)."""
    match = _AT.match(str(exc))
    assert match is not None  # the pattern matches every string
    inner = match["path"] or "$"
    return prefix + inner[1:], match["detail"]


def convert_at(obj: Any, kind: type[T], prefix: str) -> T:
    try:
        return msgspec.convert(obj, kind)
    except msgspec.ValidationError as exc:
        path, detail = validation_path(exc, prefix)
        raise SchemaValidationError(path, detail) from exc


class _Uuid4s:
    """Random (version 4) UUIDs as `uuid.uuid4` makes them, their randomness drawn from the OS
    256 at a time: a command without a message_id costs no getrandom call of its own."""

    BATCH = 256

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pool: list[bytes] = []
        os.register_at_fork(after_in_child=self._forget)

    def _forget(self) -> None:
        """In a forked child: draw afresh, or parent and child would hand out the same ids."""
        self._lock = threading.Lock()
        self._pool = []

    def __call__(self) -> str:
        with self._lock:
            if not self._pool:
                block = os.urandom(16 * self.BATCH)
                self._pool = [block[i:i + 16] for i in range(0, len(block), 16)]
            raw = self._pool.pop()
        return str(uuid.UUID(bytes=raw, version=4))


new_message_id = _Uuid4s()


def decode_object(raw: bytes) -> dict[str, Any]:
    """A JSON object with unique keys; anything else raises SchemaValidationError."""
    obj = _decode(raw)
    duplicate = duplicate_key(raw, obj)
    if duplicate is not None:
        raise SchemaValidationError(duplicate.path, f"duplicate key {duplicate.key!r}")
    return obj


def validate_command(
    raw: bytes, *, new_id: Callable[[], str] = new_message_id
) -> NormalizedCommand:
    """`validate_message` for a body that must be a command (a HEARTBEAT, INVOKE, … is a
    schema error)."""
    message = validate_message(raw, new_id=new_id)
    if not isinstance(message, NormalizedCommand):
        raise SchemaValidationError("$", f"{_said(message)} is not a command")
    return message


Message = NormalizedCommand | Heartbeat | Message3


def validate_message(
    raw: bytes, *, new_id: Callable[[], str] = new_message_id
) -> Message:
    """Decode and validate a COMMAND, SAFETY, HEARTBEAT, INVOKE, INVOKE_CANCEL or AUTHORIZE
    body in any form of either generation; never trusts a number it did not check.

    A `role`/`role_level` in the body is kept as `claimed_role` for the governor to refuse
    (INSUFFICIENT_PRIVILEGES); the role itself always comes from authentication.

    Stops are the most forgiving input: a JSON object in which any `action` (or `cmd`) is
    `estop`/`stop`, or an RCAN SAFETY message whose `safety_event` is ESTOP/STOP, becomes that
    stop whatever else is wrong with it (duplicate keys, unknown fields, a malformed
    `message_id`, an incompatible `rcan_version`, …); the problems travel with it as
    `warnings`. A body that is valid as something else but also says stop somewhere (an
    ignored field of a newer MINOR, say) is that stop too. Any other body with a duplicate key
    is refused: which value counts would be the parser's guess.
    """
    try:
        obj = _decode(raw)
    except SchemaValidationError as exc:
        salvaged = nonfinite_stop(raw, _problem(exc))  # Python's json.dumps writes NaN
        if salvaged is None:
            raise
        return salvage_stop(*salvaged, new_id)
    duplicate = duplicate_key(raw, obj)
    stop = stop_intent(obj.items() if duplicate is None else duplicate.top)
    if duplicate is not None:
        if stop is None:
            raise SchemaValidationError(duplicate.path, f"duplicate key {duplicate.key!r}")
        return salvage_stop(stop, obj, [f"{duplicate.path}: duplicate key {duplicate.key!r}"],
                            new_id)
    try:
        message = _strict(dict(obj), new_id)
    except _MESSAGE_ERRORS as exc:
        if stop is None:
            raise
        return salvage_stop(stop, obj, [_problem(exc)], new_id)
    said = _said(message)
    if stop is not None and said != stop:
        return salvage_stop(stop, obj, [f"$: says {stop} beside {said}: {stop} it is"], new_id)
    return message


def _said(message: Message) -> str:
    if isinstance(message, NormalizedCommand):
        return message.action
    return f"a {type(message).__name__.upper()}"


def _decode(raw: bytes) -> dict[str, Any]:
    try:
        obj = _DECODER.decode(raw)
    except msgspec.DecodeError as exc:  # also NaN / Infinity tokens: not JSON
        raise SchemaValidationError("$", str(exc)) from exc
    except UnicodeDecodeError as exc:  # msgspec raises this, not DecodeError, inside a string
        raise SchemaValidationError("$", f"JSON is not valid UTF-8 (byte {exc.start})") from exc
    except RecursionError as exc:  # msgspec's answer to absurdly deep nesting
        raise SchemaValidationError("$", "JSON nested too deeply") from exc
    if not isinstance(obj, dict):
        raise SchemaValidationError("$", "expected a JSON object")
    # (the count first: a body with fewer brackets than levels allowed cannot nest deeper)
    if raw.count(b"[") + raw.count(b"{") > MAX_DEPTH and nested_deeper_than(obj, MAX_DEPTH):
        # msgspec reads ~1000 levels; the audit log's encoders are recursive and give up
        # hundreds of levels earlier, so such a message could not be recorded (a stop among
        # them: it stopped, unrecorded, and was answered "failed"). A stop is still read,
        # what is deeper than this as null (`_salvage.read_leniently`).
        raise SchemaValidationError("$", f"JSON nested more than {MAX_DEPTH} levels deep")
    return obj


def _strict(obj: dict[str, Any], new_id: Callable[[], str]) -> Message:
    claimed = {k: obj.pop(k) for k in _ROLE_CLAIMS if k in obj}
    claimed_role = claimed.get("role_level", claimed.get("role"))
    version = message_version(obj)  # §3.5: first, before anything else is looked at
    spoken = _message3(obj, version, new_id)
    if spoken is not None:
        return spoken
    kind = obj.get("message_type")
    if kind == SAFETY_MESSAGE_TYPE:
        safety, ignored = _known(obj, SafetyMessage, version)
        return _from_safety(safety, claimed_role, new_id, ignored)
    if kind == HEARTBEAT_MESSAGE_TYPE:
        beat, ignored = _known(obj, HeartbeatMessage, version)
        return _heartbeat(beat, ignored)
    if "message_type" in obj:
        envelope, ignored = _known(obj, EnvelopeCommand, version)
        return _from_envelope(envelope, claimed_role, new_id, ignored)
    if any(key in obj for key in _V3_KEYS):
        if version is None:
            raise SchemaValidationError("$.rcan", "required: the RCAN version this COMMAND "
                                        "speaks (the SDK writes rcan and rcan_version)")
        command, ignored = _known(obj, RcanCommand, version)
        return _from_v3(command, obj, claimed_role, ignored)
    return _from_short(convert_at(obj, ShortCommand, "$"), claimed_role, new_id)


def _message3(obj: dict[str, Any], version: str | None,
              new_id: Callable[[], str]) -> Message3 | None:
    """INVOKE, INVOKE_CANCEL or AUTHORIZE (see `_invoke`), or None for any other message."""
    if is_kind(obj, "INVOKE", INVOKE_TYPE):
        invoke, ignored = _known(obj, InvokeMessage, version)
        message: Message3 = from_invoke(invoke, ignored, new_id())
    elif is_kind(obj, "INVOKE_CANCEL", INVOKE_CANCEL_TYPE):
        cancel, ignored = _known(obj, InvokeCancelMessage, version)
        message = from_cancel(cancel, ignored)
    elif is_kind(obj, "AUTHORIZE", AUTHORIZE_TYPE):
        authorize, ignored = _known(obj, AuthorizeMessage, version)
        message = from_authorize(authorize, ignored)
    elif obj.get("cmd") == AUTHORIZE_CMD:  # the SDK's COMMAND envelope, signed or not
        if version is None:
            raise SchemaValidationError("$.rcan", "required: the RCAN version this AUTHORIZE "
                                        "speaks (the SDK writes rcan and rcan_version)")
        signed, ignored = _known(obj, SignedAuthorizeMessage, version)
        message = from_signed_authorize(signed, obj, ignored)
    else:
        return None
    if message.ruri is not None:
        parse_ruri(message.ruri)
    return message


def _known(obj: dict[str, Any], kind: type[T], version: str | None) -> tuple[T, tuple[str, ...]]:
    """`obj` as `kind`: with an rcan_version, unknown envelope fields are ignored (§3.5) and
    named; without one, they are errors (the 1.2 forms and the SDK's SAFETY stay strict)."""
    ignored: tuple[str, ...] = ()
    if version is not None:
        obj, ignored = split_known(obj, kind)
    return convert_at(obj, kind, "$"), ignored


def _problem(exc: Exception) -> str:
    if isinstance(exc, SchemaValidationError):
        return f"{exc.path}: {exc.detail}"
    if isinstance(exc, InvalidRuriError):
        return f"invalid RURI {exc.ruri!r}: {exc.rule}"
    return str(exc)


def _params(action: str, raw: dict[str, Any], prefix: str) -> ActionParams:
    params: ActionParams = convert_at(raw, action_spec(action).params, prefix)
    return params


def _message_id(given: str | None, new_id: Callable[[], str]) -> str:
    if given is None:
        return new_id()
    try:
        return str(uuid.UUID(given))
    except ValueError as exc:
        raise SchemaValidationError("$.message_id", "expected a UUID") from exc


def _from_short(
    cmd: ShortCommand, claimed_role: Any, new_id: Callable[[], str]
) -> NormalizedCommand:
    ai_fields = (cmd.ai_provider, cmd.ai_model, cmd.confidence, cmd.thought_id,
                 cmd.ai_reasoning, cmd.ai_client)
    ai = None
    if any(f is not None for f in ai_fields):
        ai = AiInfo(
            provider=cmd.ai_provider,
            model=cmd.ai_model,
            confidence=cmd.confidence,
            thought_id=cmd.thought_id,
            reasoning=cmd.ai_reasoning,
            client=cmd.ai_client,
        )
    return NormalizedCommand(
        action=cmd.action,
        params=_params(cmd.action, cmd.params, "$.params"),
        requested=cmd.params,
        message_id=_message_id(cmd.message_id, new_id),
        client_message_id=cmd.message_id is not None,
        ai=ai,
        claimed_role=claimed_role,
    )


def _from_envelope(
    cmd: EnvelopeCommand, claimed_role: Any, new_id: Callable[[], str],
    ignored: tuple[str, ...] = (),
) -> NormalizedCommand:
    parse_ruri(cmd.ruri)
    envelope = None
    if cmd.rcan_version is not None:
        envelope = Envelope(version=cmd.rcan_version, msg_id=cmd.message_id, ignored=ignored,
                            sent_at_s=_seconds(cmd.timestamp_ms))
    return NormalizedCommand(
        action=cmd.action,
        params=_params(cmd.action, cmd.parameters, "$.parameters"),
        requested=cmd.parameters,
        message_id=_message_id(cmd.message_id, new_id),
        client_message_id=cmd.message_id is not None,
        ruri=cmd.ruri,
        timestamp_ms=cmd.timestamp_ms,
        priority=cmd.priority,
        ai=cmd.ai,
        claimed_role=claimed_role,
        envelope=envelope,
    )


_SAFETY_EFFECTS = {"ESTOP": Effect.ESTOP, "STOP": Effect.HALT, "RESUME": Effect.CLEAR_ESTOP}


def _from_safety(
    msg: SafetyMessage, claimed_role: Any, new_id: Callable[[], str],
    ignored: tuple[str, ...] = (),
) -> NormalizedCommand:
    parse_ruri(msg.ruri)
    action = with_effect(_SAFETY_EFFECTS[msg.safety_event]).name
    requested = {} if msg.reason is None else {"reason": msg.reason}
    takes_reason = "reason" in action_spec(action).params.__struct_fields__
    return NormalizedCommand(
        action=action,
        params=_params(action, requested if takes_reason else {}, "$"),
        requested=requested,
        message_id=_message_id(msg.message_id, new_id),
        client_message_id=msg.message_id is not None,
        ruri=msg.ruri,
        timestamp_ms=msg.timestamp_ms,
        claimed_role=claimed_role,
        envelope=Envelope(version=msg.rcan_version, msg_id=msg.message_id, safety=True,
                          ignored=ignored, sent_at_s=_seconds(msg.timestamp_ms)),
    )


def _seconds(ms: int | None) -> float | None:
    return None if ms is None else ms / 1000.0


def _heartbeat(beat: HeartbeatMessage, ignored: tuple[str, ...]) -> Heartbeat:
    if beat.ruri is not None:
        parse_ruri(beat.ruri)
    return Heartbeat(message_id=beat.message_id, envelope=Envelope(
        version=beat.rcan_version, msg_id=beat.message_id, ignored=ignored,
        sent_at_s=_seconds(beat.timestamp_ms)))


def _from_v3(cmd: RcanCommand, obj: dict[str, Any], claimed_role: Any,
             ignored: tuple[str, ...]) -> NormalizedCommand:
    """The SDK's COMMAND: `cmd` names a registry action, `params` are its parameters."""
    if cmd.cmd not in names():
        raise SchemaValidationError("$.cmd", f"unknown action {cmd.cmd!r} (this robot's: "
                                    f"{', '.join(names())})")
    parse_ruri(cmd.target)
    unsigned = tuple(f for f in _GOVERNANCE_FIELDS if getattr(cmd, f) is not None)
    cmd = _lift_governance(cmd)
    ai = _v3_ai(cmd)
    version = cmd.rcan_version or cmd.rcan
    return NormalizedCommand(
        action=cmd.cmd,
        params=_params(cmd.cmd, cmd.params, "$.params"),
        requested=cmd.params,
        message_id=normal_id(cmd.msg_id),
        client_message_id=True,
        ruri=cmd.target,
        timestamp_ms=int(cmd.timestamp * 1000),
        ai=ai,
        claimed_role=claimed_role,
        envelope=Envelope(
            version=version, msg_id=cmd.msg_id, sent_at_s=cmd.timestamp, ignored=ignored,
            firmware_hash=cmd.firmware_hash, attestation_ref=cmd.attestation_ref, sig=cmd.sig,
            signed=signed_bytes(obj) if cmd.sig is not None else None,
            unsigned_fields=unsigned),
    )


# A COMMAND's governance fields: beside `params` (the SDK's `confidence`) or inside them, where
# a signature covers them; never action parameters.
_GOVERNANCE_FIELDS = ("confidence", "ai")


class _SignedGovernance(Strict, frozen=True):
    confidence: Confidence | None = None
    ai: dict[str, Any] | None = None


def _lift_governance(cmd: RcanCommand) -> RcanCommand:
    """`cmd` with `confidence`/`ai` taken out of its params (once only: not in both places)."""
    inside = {k: v for k, v in cmd.params.items() if k in _GOVERNANCE_FIELDS}
    if not inside:
        return cmd
    for name in inside:
        if getattr(cmd, name) is not None:
            raise SchemaValidationError(f"$.params.{name}", f"given twice: inside params "
                                        f"(signed) and beside them ({name})")
    lifted = convert_at(inside, _SignedGovernance, "$.params")
    params = {k: v for k, v in cmd.params.items() if k not in _GOVERNANCE_FIELDS}
    return msgspec.structs.replace(cmd, params=params, confidence=lifted.confidence,
                                   ai=lifted.ai)


def _v3_ai(cmd: RcanCommand) -> AiInfo | None:
    """The SDK's top-level `confidence`, with our `ai` block's provider/model/thought_id."""
    ai = None if cmd.ai is None else convert_at(cmd.ai, AiInfo, "$.ai")
    if cmd.confidence is None:
        return ai
    if ai is None:
        return AiInfo(confidence=cmd.confidence)
    if ai.confidence is not None and ai.confidence != cmd.confidence:
        raise SchemaValidationError("$.ai.confidence", "differs from confidence")
    return msgspec.structs.replace(ai, confidence=cmd.confidence)


def invoke_command(invoke: Invoke, action: str, params: dict[str, Any]) -> NormalizedCommand:
    """The command an INVOKE runs: `action` with `params` (the skill's fixed ones and what the
    invoker may set, already merged by the caller); SchemaValidationError at `$.params`."""
    return NormalizedCommand(
        action=action,
        params=_params(action, params, "$.params"),
        requested=params,
        message_id=normal_id(invoke.msg_id),
        client_message_id=invoke.client_msg_id,
        ruri=invoke.ruri,
        timestamp_ms=invoke.timestamp_ms,
        envelope=invoke.envelope,
    )


def reply_id(raw: bytes) -> str | None:
    """The id a refusal of `raw` echoes as `msg_id`: its `msg_id` (or `message_id`) when it
    is a message of the RCAN 3.x generation (it carries `rcan_version` or `rcan`), else None.
    Best effort on a body already refused: anything unreadable gives None."""
    try:
        obj = _DECODER.decode(raw)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError):
        return None
    if not isinstance(obj, dict) or not any(k in obj for k in ("rcan_version", "rcan")):
        return None
    return readable_id(obj)
