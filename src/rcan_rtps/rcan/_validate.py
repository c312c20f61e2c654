"""Validation at the boundary: raw bytes → NormalizedCommand, or SchemaValidationError."""

from __future__ import annotations

import os
import re
import threading
import uuid
from collections.abc import Callable
from typing import Any, TypeVar

import msgspec

from ._errors import InvalidRuriError, SchemaValidationError
from ._messages import AiInfo, EnvelopeCommand, NormalizedCommand, SafetyMessage, ShortCommand
from ._ruri import parse_ruri
from ._salvage import duplicate_key, salvage_stop, stop_intent
from ._types import ActionParams
from .actions import Effect, action_spec, with_effect

_AT = re.compile(r"^(?P<detail>.*?)(?: - at `(?P<path>[^`]*)`)?$", re.DOTALL)
_ROLE_CLAIMS = ("role", "role_level")
SAFETY_MESSAGE_TYPE = 6  # RCAN SAFETY: ESTOP, STOP, RESUME
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
    """Decode and validate a COMMAND body in any form; never trusts a number it did not check.

    A `role`/`role_level` in the body is kept as `claimed_role` for the governor to refuse
    (INSUFFICIENT_PRIVILEGES); the role itself always comes from authentication.

    Stops are the most forgiving input: a JSON object in which any `action` (or `cmd`) is
    `estop`/`stop`, or an RCAN SAFETY message whose `safety_event` is ESTOP/STOP, becomes that
    stop whatever else is wrong with it (duplicate keys, unknown fields, a malformed
    `message_id`, …); the problems travel with it as `warnings`. Any other body with a
    duplicate key is refused: which value counts would be the parser's guess.
    """
    obj = _decode(raw)
    duplicate = duplicate_key(raw, obj)
    stop = stop_intent(obj.items() if duplicate is None else duplicate.top)
    if duplicate is not None:
        if stop is None:
            raise SchemaValidationError(duplicate.path, f"duplicate key {duplicate.key!r}")
        return salvage_stop(stop, obj, [f"{duplicate.path}: duplicate key {duplicate.key!r}"],
                            new_id)
    try:
        return _strict(dict(obj), new_id)
    except (SchemaValidationError, InvalidRuriError) as exc:
        if stop is None:
            raise
        return salvage_stop(stop, obj, [_problem(exc)], new_id)


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
    return obj


def _strict(obj: dict[str, Any], new_id: Callable[[], str]) -> NormalizedCommand:
    claimed = {k: obj.pop(k) for k in _ROLE_CLAIMS if k in obj}
    claimed_role = claimed.get("role_level", claimed.get("role"))
    kind = obj.get("message_type")
    if kind == SAFETY_MESSAGE_TYPE:
        return _from_safety(convert_at(obj, SafetyMessage, "$"), claimed_role, new_id)
    if "message_type" in obj:
        return _from_envelope(convert_at(obj, EnvelopeCommand, "$"), claimed_role, new_id)
    return _from_short(convert_at(obj, ShortCommand, "$"), claimed_role, new_id)


def _problem(exc: SchemaValidationError | InvalidRuriError) -> str:
    if isinstance(exc, SchemaValidationError):
        return f"{exc.path}: {exc.detail}"
    return f"invalid RURI {exc.ruri!r}: {exc.rule}"


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
    ai_fields = (cmd.ai_provider, cmd.ai_model, cmd.confidence, cmd.thought_id)
    ai = None
    if any(f is not None for f in ai_fields):
        ai = AiInfo(
            provider=cmd.ai_provider,
            model=cmd.ai_model,
            confidence=cmd.confidence,
            thought_id=cmd.thought_id,
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
    cmd: EnvelopeCommand, claimed_role: Any, new_id: Callable[[], str]
) -> NormalizedCommand:
    parse_ruri(cmd.ruri)
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
    )


_SAFETY_EFFECTS = {"ESTOP": Effect.ESTOP, "STOP": Effect.HALT, "RESUME": Effect.CLEAR_ESTOP}


def _from_safety(
    msg: SafetyMessage, claimed_role: Any, new_id: Callable[[], str]
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
    )
