"""Stops are the most forgiving input: a body that says stop is executed as that stop.

`validate_command` is strict for everything else; for a body in which any `action` (or `cmd`,
the RCAN 3.x COMMAND's name for it) is `estop`/`stop`, or any `safety_event` is ESTOP/STOP,
what is wrong with it (duplicate keys, unknown fields, a malformed `message_id`, a bad RURI,
ill-typed AI fields) becomes a warning on the stop instead of a refusal. What can be kept of
such a body (a valid id, RURI, reason, AI fields, role claim) is kept; the rest is dropped,
each with its warning.
"""

from __future__ import annotations

import json
import math
import re
import uuid
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple, TypeVar

import msgspec

from ._errors import InvalidRuriError, SchemaValidationError
from ._messages import AiInfo, NormalizedCommand
from ._ruri import parse_ruri
from ._types import TimestampMs
from ._v3 import Envelope, readable_id
from .actions import Effect, StopParams, with_effect

_ACTION_KEYS = ("action", "cmd")
_ACTION_EFFECTS = {with_effect(e).name: e for e in (Effect.ESTOP, Effect.HALT)}
_SAFETY_EFFECTS = {"ESTOP": Effect.ESTOP, "STOP": Effect.HALT}  # RCAN SAFETY safety_event
_ROLE_CLAIMS = ("role", "role_level")
_SURROGATE = re.compile("[\ud800-\udfff]")
# A body of the RCAN 3.x generation: its reply carries msg_id and status, salvaged or not.
_V3_MARKS = ("rcan", "rcan_version", "cmd", "msg_id")
_V3_TYPES = (4, 6, 11, 13, 45)  # HEARTBEAT, SAFETY, INVOKE, INVOKE_CANCEL, AUTHORIZE
_AI_FIELDS = {"ai_provider": "provider", "ai_model": "model", "confidence": "confidence",
              "thought_id": "thought_id", "ai_reasoning": "reasoning", "ai_client": "client"}


class Duplicate(NamedTuple):
    """The first key that occurs twice in one object, and the top-level object's pairs."""

    path: str
    key: str
    top: list[tuple[str, Any]]


def duplicate_key(raw: bytes, obj: dict[str, Any]) -> Duplicate | None:
    """The first repeated key of `raw` (already decoded as `obj`), or None.

    Every key in the text is followed by a colon, so when the text holds no more colons
    than `obj` has keys no key can repeat: the usual body costs a count, not a second parse.
    """
    if raw.count(b":") == count_keys(obj):
        return None
    try:
        top = json.loads(raw, object_pairs_hook=Pairs)
    except RecursionError as exc:  # deeper than this parser goes: nothing is taken on trust
        raise SchemaValidationError("$", "JSON nested too deeply") from exc
    return first_duplicate(top)


class Pairs(list[tuple[str, Any]]):
    """A JSON object as its key/value pairs, every occurrence kept."""


MAX_DEPTH = 32  # levels of objects and arrays a message may nest (the body itself is one)


def nested_deeper_than(obj: Any, limit: int) -> bool:
    """Whether `obj` (decoded JSON, objects as dicts or `Pairs`) nests more than `limit`
    levels of containers. Iterative: it is asked of what is too deep to recurse into."""
    todo: list[tuple[Any, int]] = [(obj, 1)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, Pairs):
            children: Iterable[Any] = (value for _, value in item)
        elif isinstance(item, dict):
            children = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        if depth > limit:
            return True
        todo.extend((child, depth + 1) for child in children)
    return False


def count_keys(obj: Any) -> int:
    count, todo = 0, [obj]
    while todo:
        item = todo.pop()
        if isinstance(item, dict):
            count += len(item)
            todo.extend(item.values())
        elif isinstance(item, list):
            todo.extend(item)
    return count


def first_duplicate(top: Pairs) -> Duplicate | None:
    todo: list[tuple[str, Any]] = [("$", top)]
    while todo:
        path, item = todo.pop(0)
        if isinstance(item, Pairs):
            seen: set[str] = set()
            for key, value in item:
                if key in seen:
                    return Duplicate(f"{path}.{key}", key, list(top))
                seen.add(key)
                todo.append((f"{path}.{key}", value))
        elif isinstance(item, list):
            todo.extend((f"{path}[{i}]", value) for i, value in enumerate(item))
    return None


class Lenient(NamedTuple):
    """JSON read as forgivingly as it can be, and what was read otherwise than written."""

    value: Any
    replaced: tuple[str, ...]

    def problem(self, problem: str) -> str:
        """`problem` (why the strict reader refused it), saying how it was read instead."""
        how = ", ".join(self.replaced) if self.replaced else "by Python's json"
        return f"{problem} (read leniently: {how})"


class _Reader:
    """json.loads's hooks for what a strict reader refuses, each noting what it replaced."""

    def __init__(self) -> None:
        self.replaced: dict[str, None] = {}  # in order, each once

    def constant(self, token: str) -> None:  # NaN, Infinity, -Infinity
        self.replaced[f"{token} as null"] = None

    def integer(self, digits: str) -> int | None:
        try:
            return int(digits)
        except ValueError:  # more digits than Python converts (sys.get_int_max_str_digits)
            self.replaced[f"an integer of {len(digits.lstrip('-'))} digits as null"] = None
            return None

    def real(self, text: str) -> float | None:
        value = float(text)
        if math.isfinite(value):
            return value
        self.replaced[f"{text[:24]}{'...' if len(text) > 24 else ''} (out of range) as "
                      "null"] = None
        return None


def read_leniently(raw: bytes, *, pairs: bool = False) -> Lenient | None:
    """`raw` as JSON, with what strict readers refuse read as something: NaN, Infinity and
    numbers out of range as null, an unpaired surrogate escape as U+FFFD, what is nested too
    deeply for Python's json as null (`pairs`: objects as `Pairs`, every occurrence of a key
    kept). None: not JSON even so."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return None
    reader = _Reader()
    if text.startswith("\ufeff"):  # RFC 8259 §8.1: a parser may ignore it; Python's refuses
        text = text[1:]
        reader.replaced["a byte order mark (U+FEFF) at the start as nothing"] = None
    try:
        try:
            value = json.loads(text, parse_constant=reader.constant, parse_int=reader.integer,
                               parse_float=reader.real, object_pairs_hook=Pairs if pairs else None)
            # Deeper than a message may be: what Python's json read, the audit log's encoders
            # (recursive) could not write, so the stop would go unrecorded (red team 20).
            deep = nested_deeper_than(value, MAX_DEPTH)
        except RecursionError:  # a stop says so near the top: what is deep need not be read
            deep = True
        if deep:
            value = _Shallow(text, reader, pairs).read()
        surrogates: list[bool] = []
        value = _clean(value, surrogates)
    except (ValueError, RecursionError):  # not JSON
        return None
    if surrogates:
        reader.replaced["an unpaired surrogate escape as U+FFFD"] = None
    return Lenient(value, tuple(reader.replaced))


T = TypeVar("T")
_BLANKS = re.compile(r"[ \t\n\r]*")
_CLOSERS = {"{": "}", "[": "]"}


class _Shallow:
    """JSON read down to `DEPTH` levels, anything deeper as null (with `reader`'s note): a
    stop says so at the top (`action`, `safety_event`) or a level below (an MCP call's
    `params.name`), so a field nested thousands of levels deep, which Python's json and
    msgspec give up on, must not keep it from being read. Iterative where it is deep."""

    DEPTH = MAX_DEPTH

    def __init__(self, text: str, reader: _Reader, pairs: bool) -> None:
        self._text = text
        self._reader = reader
        self._pairs = pairs
        self._scalars = json.JSONDecoder(parse_constant=reader.constant,
                                         parse_int=reader.integer, parse_float=reader.real)

    def read(self) -> Any:
        value, end = self._value(0, 0)
        if self._blank(end) != len(self._text):
            raise ValueError("extra data after the JSON value")
        return value

    def _blank(self, at: int) -> int:
        match = _BLANKS.match(self._text, at)
        assert match is not None  # it matches the empty string
        return match.end()

    def _value(self, at: int, depth: int) -> tuple[Any, int]:
        at = self._blank(at)
        opener = self._text[at:at + 1]
        if opener not in _CLOSERS:
            value, end = self._scalars.raw_decode(self._text, at)  # ValueError: not JSON
            if isinstance(value, (dict, list)):  # raw_decode reads containers too
                raise ValueError("unexpected container")
            return value, end
        if depth >= self.DEPTH:
            self._reader.replaced[f"what is nested more than {self.DEPTH} levels deep as "
                                  "null"] = None
            return None, self._past(at)
        return (self._object if opener == "{" else self._array)(at + 1, depth + 1)

    def _object(self, at: int, depth: int) -> tuple[Any, int]:
        items, end = self._members(at, "}", lambda at: self._member(at, depth))
        return (Pairs(items) if self._pairs else dict(items)), end

    def _array(self, at: int, depth: int) -> tuple[Any, int]:
        return self._members(at, "]", lambda at: self._value(at, depth))

    def _members(self, at: int, closer: str, member: Callable[[int], tuple[T, int]]
                 ) -> tuple[list[T], int]:
        """The comma-separated members of an object or array opened before `at`, each read by
        `member`, up to `closer`; and where the container ends."""
        items: list[T] = []
        at = self._blank(at)
        if self._text[at:at + 1] != closer:
            while True:
                item, at = member(at)
                items.append(item)
                at = self._blank(at)
                if self._text[at:at + 1] != ",":
                    break
                at += 1
            if self._text[at:at + 1] != closer:
                raise ValueError(f"expected ',' or '{closer}'")
        return items, at + 1

    def _member(self, at: int, depth: int) -> tuple[tuple[str, Any], int]:
        """An object's `"key": value`."""
        at = self._blank(at)
        if self._text[at:at + 1] != '"':
            raise ValueError("expected a key")
        key, at = self._scalars.raw_decode(self._text, at)
        at = self._blank(at)
        if self._text[at:at + 1] != ":":
            raise ValueError("expected ':'")
        value, at = self._value(at + 1, depth)
        return (key, value), at

    def _past(self, at: int) -> int:
        """Where the container opening at `at` ends: its brackets matched outside strings
        (its scalars are not checked: they are read as nothing)."""
        text, expected = self._text, [_CLOSERS[self._text[at]]]
        at += 1
        while expected:
            if at >= len(text):
                raise ValueError("unterminated")
            char = text[at]
            if char == '"':
                _, at = self._scalars.raw_decode(text, at)
                continue
            if char in _CLOSERS:
                expected.append(_CLOSERS[char])
            elif char in "]}" and char != expected.pop():
                raise ValueError("mismatched brackets")
            at += 1
        return at


def nonfinite_stop(raw: bytes, problem: str) -> tuple[str, dict[str, Any], list[str]] | None:
    """(stop, object, problems) of a body that is JSON but for what `read_leniently` forgives
    (NaN/Infinity tokens, which Python's `json.dumps` and so the `rcan` SDK's `to_json` writes;
    numbers out of range; unpaired surrogate escapes), when it says stop; else None. No
    non-finite number reaches the audit."""
    read, paired = read_leniently(raw), read_leniently(raw, pairs=True)
    if read is None or paired is None:
        return None
    obj, top = read.value, paired.value
    if not isinstance(obj, dict) or not isinstance(top, Pairs):
        return None
    stop = stop_intent(top)
    if stop is None:
        return None
    problems = [read.problem(problem)]
    duplicate = first_duplicate(top)
    if duplicate is not None:
        problems.append(f"{duplicate.path}: duplicate key {duplicate.key!r}")
    return stop, obj, problems


def _clean(value: Any, found: list[bool]) -> Any:
    """`value` with every unpaired surrogate (a `\\ud800` escape Python's json lets through,
    which no UTF-8 audit line can hold) replaced by U+FFFD, in keys and strings alike; each
    string changed is noted in `found`."""
    if isinstance(value, str):
        cleaned = _SURROGATE.sub("\ufffd", value)
        if cleaned != value:
            found.append(True)
        return cleaned
    if isinstance(value, Pairs):
        return Pairs((_clean(k, found), _clean(v, found)) for k, v in value)
    if isinstance(value, dict):
        return {_clean(k, found): _clean(v, found) for k, v in value.items()}
    if isinstance(value, list):
        return [_clean(v, found) for v in value]
    return value


def stop_intent(pairs: Iterable[tuple[str, Any]]) -> str | None:
    """`estop` if any value of the body says e-stop, else `stop` if any says stop, else None.

    Case and surrounding blanks are forgiven: what stops is never a matter of spelling."""
    said: set[Effect] = set()
    for key, value in pairs:
        if not isinstance(value, str):
            continue
        if key in _ACTION_KEYS:
            said.add(_ACTION_EFFECTS.get(value.strip().lower(), Effect.MOTION))
        elif key == "safety_event":
            said.add(_SAFETY_EFFECTS.get(value.strip().upper(), Effect.MOTION))
    for effect in (Effect.ESTOP, Effect.HALT):  # the stronger stop wins
        if effect in said:
            return with_effect(effect).name
    return None


def salvage_stop(action: str, obj: dict[str, Any], problems: list[str],
                 new_id: Callable[[], str]) -> NormalizedCommand:
    """The stop `action` from a body that failed validation for `problems`."""
    warnings: list[str] = []
    requested = _requested(obj)
    message_id, client_id = _message_id(obj.get("message_id", obj.get("msg_id")), new_id,
                                        warnings)
    if warnings:  # the id's own warning says more than the schema's
        problems = [p for p in problems if not p.startswith("$.message_id:")]
    warnings[:0] = problems
    return NormalizedCommand(
        action=action,
        params=_params(requested.get("reason", obj.get("reason")), warnings),
        requested=requested,
        message_id=message_id,
        client_message_id=client_id,
        ruri=_ruri(obj.get("ruri", obj.get("target")), warnings),
        timestamp_ms=_timestamp(obj.get("timestamp_ms")),
        ai=_ai(obj, warnings),
        claimed_role=next((obj[k] for k in reversed(_ROLE_CLAIMS) if k in obj), None),
        warnings=tuple(dict.fromkeys(warnings)),
        envelope=_envelope(obj),
    )


def _envelope(obj: dict[str, Any]) -> Envelope | None:
    """For a stop salvaged from an RCAN 3.x message: its id for the reply. The version is
    left out (it may be the very thing that was wrong), so no replay check is added to a
    stop that had none."""
    kind = obj.get("message_type")
    typed = isinstance(kind, int) and not isinstance(kind, bool) and kind in _V3_TYPES
    if not typed and not isinstance(obj.get("type"), str) and not any(
            key in obj for key in _V3_MARKS):
        return None
    return Envelope(version=None, msg_id=readable_id(obj), safety=kind == 6)


def _requested(obj: dict[str, Any]) -> dict[str, Any]:
    for key in ("params", "parameters"):
        if isinstance(obj.get(key), dict):
            return dict(obj[key])
    reason = obj.get("reason")  # a SAFETY message's
    return {"reason": reason} if reason is not None else {}


def _params(reason: Any, warnings: list[str]) -> StopParams:
    limit = 512
    if reason is None:
        return StopParams()
    if not isinstance(reason, str):
        warnings.append("reason dropped: not a string")
        return StopParams()
    if len(reason) > limit:
        warnings.append(f"reason cut to {limit} characters")
    return StopParams(reason=reason[:limit])


def _message_id(given: Any, new_id: Callable[[], str],
                warnings: list[str]) -> tuple[str, bool]:
    if given is not None:
        try:
            if isinstance(given, str) and len(given) <= 64:
                return str(uuid.UUID(given)), True
        except ValueError:
            pass
    made = new_id()
    if given is not None:
        shown = given[:64] if isinstance(given, str) else type(given).__name__
        warnings.append(f"message_id {shown!r} is not a UUID: recorded as {made}")
    return made, False


def _ruri(given: Any, warnings: list[str]) -> str | None:
    if given is None:
        return None
    try:
        if not isinstance(given, str):
            raise InvalidRuriError(type(given).__name__, "not a string")
        parse_ruri(given)
        return given
    except InvalidRuriError as exc:
        warnings.append(f"ruri ignored: {exc.rule}")
        return None


def _timestamp(given: Any) -> int | None:
    """The stop's `timestamp_ms` if it is one the schema takes (its problem is a warning)."""
    try:
        return msgspec.convert(given, TimestampMs)
    except msgspec.ValidationError:
        return None


def _ai(obj: dict[str, Any], warnings: list[str]) -> AiInfo | None:
    fields: Any = obj.get("ai")
    if fields is None:
        fields = {name: obj[key] for key, name in _AI_FIELDS.items() if key in obj} or None
    if fields is None:
        return None
    try:
        return msgspec.convert(fields, AiInfo)
    except msgspec.ValidationError as exc:
        warnings.append(f"ai fields dropped: {exc}")
        return None
