"""The RCAN 3.x generation: the official SDK's COMMAND, SAFETY and HEARTBEAT, §3.5 versions.

Beside the bridge spec's 1.2 forms (short form, `message_type` 1 envelope) this bridge speaks
RCAN 3.2 as the `rcan` SDK writes it (see docs/rcan-profile.md, "Two generations"):

- COMMAND, `RCANMessage.to_dict()`: `{rcan, rcan_version, msg_id, timestamp (s), cmd, target,
  params, confidence?, sig?, firmware_hash?, attestation_ref?, ...}`; `cmd` is a registry action.
- SAFETY (`message_type` 6, `rcan.safety`): ESTOP, STOP, RESUME (= `clear_estop`).
- HEARTBEAT (`message_type` 4): keeps the sender's control session alive.

§3.5: `rcan_version`, when a message carries it, is checked before anything else: a MAJOR this
bridge does not speak is VERSION_INCOMPATIBLE. Such a message's unknown envelope fields are
ignored (a newer MINOR may add some) and recorded in its audit entry; without `rcan_version`
the 1.2 forms, the SDK's SAFETY message and HEARTBEAT stay strict. Unknown *action parameters*
are always refused: a typo must not become a zero.
"""

from __future__ import annotations

import re
import uuid
from typing import Annotated, Any, Literal

import msgspec

from ._errors import SchemaValidationError, VersionIncompatibleError
from ._types import Confidence, Strict, TimestampMs, whole

SPOKEN = ("1.2", "3.2")  # what mDNS and the node manifest announce
_MAJORS = {1: 2, 3: 2}  # MAJOR → the highest MINOR of it this bridge knows
REPLAY_CHECKED_FROM = (1, 5)  # §8.3 applies to messages carrying rcan_version >= 1.5
_VERSION = re.compile(r"([0-9]{1,4})(?:\.([0-9]{1,4}))?(?:\.[0-9]{1,4})?")

VersionText = Annotated[str, msgspec.Meta(min_length=1, max_length=16)]
# The SDK's ids are UUIDs; other senders' may be any short token (never free text: they end up
# in replies and audit entries).
MsgId = Annotated[str, msgspec.Meta(min_length=1, max_length=64,
                                    pattern=whole(r"[A-Za-z0-9._:-]+"))]
Text = Annotated[str, msgspec.Meta(max_length=512)]


class Signature(Strict, frozen=True):
    """A message's `sig` block, as `rcan.signing.sign_message` writes it."""

    alg: Annotated[str, msgspec.Meta(min_length=1, max_length=32)]
    kid: Annotated[str, msgspec.Meta(min_length=1, max_length=128)]
    value: Annotated[str, msgspec.Meta(min_length=1, max_length=8192)]


class RcanCommand(Strict, frozen=True, kw_only=True):
    """COMMAND as `rcan.message.RCANMessage.to_dict()` writes it (fields acted on)."""

    rcan: VersionText | None = None
    rcan_version: VersionText | None = None
    msg_id: MsgId
    timestamp: Annotated[float, msgspec.Meta(ge=0.0, le=1e11)]  # Unix seconds
    cmd: Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
    target: Text
    params: dict[str, Any] = msgspec.field(default_factory=dict)
    confidence: Confidence | None = None
    # Ours beside the SDK's `confidence`: which AI asked (provider, model, thought_id).
    ai: dict[str, Any] | None = None
    sig: Signature | None = None
    firmware_hash: Annotated[str, msgspec.Meta(max_length=256)] | None = None
    attestation_ref: Annotated[str, msgspec.Meta(max_length=2048)] | None = None


class HeartbeatMessage(Strict, frozen=True, kw_only=True):
    """HEARTBEAT (`message_type` 4 in the canonical table, rcan-spec §3); fields of
    rcan-spec's schemas/messages/heartbeat.json and §3's payload table, all optional (§3:
    "No payload required"). See tests/data/rcan-spec/SOURCE.md."""

    message_type: Literal[4]
    rcan_version: VersionText | None = None
    ruri: Text | None = None
    message_id: MsgId | None = None
    timestamp_ms: TimestampMs | None = None
    latency_budget_ms: Annotated[int, msgspec.Meta(ge=1)] | None = None
    uptime_ms: Annotated[int, msgspec.Meta(ge=0)] | None = None
    sequence: Annotated[int, msgspec.Meta(ge=0)] | None = None


class Heartbeat(msgspec.Struct, frozen=True, kw_only=True):
    """A validated HEARTBEAT: keeps its sender's control session alive."""

    message_id: str | None
    envelope: Envelope | None = None


class Envelope(msgspec.Struct, frozen=True, kw_only=True):
    """What a message of the RCAN 3.x generation carried beside the command itself."""

    version: str | None  # rcan_version as sent; None: a SAFETY or HEARTBEAT without one
    msg_id: str | None  # echoed in the reply
    sent_at_s: float | None = None  # the sender's timestamp (the replay window's clock)
    safety: bool = False  # a SAFETY message: the shorter replay window
    ignored: tuple[str, ...] = ()  # unknown envelope fields (§3.5), recorded
    firmware_hash: str | None = None
    attestation_ref: str | None = None
    sig: Signature | None = None
    signed: bytes | None = None  # the bytes `sig` covers
    verified: bool = False  # `sig` checked against a trusted key of the sender (signatures)
    # Governance fields of the message outside what a signature covers (`confidence`, `ai`
    # given beside `params` rather than inside them).
    unsigned_fields: tuple[str, ...] = ()
    skill: str | None = None  # an INVOKE's skill (§19), recorded beside its action

    @property
    def replay_checked(self) -> bool:
        """§8.3 applies: the message carries rcan_version >= 1.5."""
        return self.version is not None and version_tuple(self.version) >= REPLAY_CHECKED_FROM

    def audit_facts(self) -> dict[str, Any] | None:
        """What the audit entry's `rcan` object records (never the signature's value); None
        for a message of the 3.x forms that carries nothing beyond a 1.2 one would."""
        facts: dict[str, Any] = {} if self.version is None else {"version": self.version}
        if self.skill is not None:
            facts["skill"] = self.skill
        if self.ignored:
            facts["ignored"] = list(self.ignored)
        if self.firmware_hash is not None:
            facts["firmware_hash"] = self.firmware_hash
        if self.attestation_ref is not None:
            facts["attestation_ref"] = self.attestation_ref
        if self.sig is not None:
            facts["sig"] = {"alg": self.sig.alg, "kid": self.sig.kid, "verified": self.verified}
        return facts or None


def version_tuple(text: str) -> tuple[int, int]:
    """(MAJOR, MINOR) of a version string; ValueError if it is not one."""
    match = _VERSION.fullmatch(text)
    if match is None:
        raise ValueError(text)
    return int(match[1]), int(match[2] or 0)


def message_version(obj: dict[str, Any]) -> str | None:
    """The message's `rcan_version` (or, in the SDK's COMMAND, `rcan`), checked per §3.5 before
    anything else; None when it carries neither. Raises VersionIncompatibleError."""
    given, alias = obj.get("rcan_version"), obj.get("rcan")
    if given is None:
        given = alias
    elif alias is not None and alias != given:
        raise SchemaValidationError("$.rcan", f"{alias!r} differs from rcan_version {given!r}")
    if given is None:
        return None
    msg_id = readable_id(obj)
    if not isinstance(given, str):
        raise VersionIncompatibleError(repr(given), "not a version string", msg_id)
    try:
        major, _ = version_tuple(given)
    except ValueError:
        raise VersionIncompatibleError(given[:16], "not MAJOR.MINOR", msg_id) from None
    if major not in _MAJORS:
        raise VersionIncompatibleError(
            given, f"MAJOR {major} is not spoken here (this bridge speaks RCAN "
            f"{' and '.join(SPOKEN)})", msg_id)
    return given


def readable_id(obj: dict[str, Any]) -> str | None:
    """The message's id as a reply may echo it: printable, at most 64 characters."""
    for key in ("msg_id", "message_id"):
        value = obj.get(key)
        if isinstance(value, str) and 0 < len(value) <= 64 and value.isprintable():
            return value
    return None


def split_known(obj: dict[str, Any], kind: type[Any]) -> tuple[dict[str, Any], tuple[str, ...]]:
    """`obj` without the fields `kind` does not know, and their names (sorted)."""
    known = kind.__struct_fields__
    ignored = tuple(sorted(k for k in obj if k not in known))
    return {k: v for k, v in obj.items() if k in known}, ignored


def normal_id(text: str) -> str:
    """A UUID in its canonical spelling; any other (already checked) id as it is."""
    try:
        return str(uuid.UUID(text))
    except ValueError:
        return text


Status3 = Literal["ok", "pending", "blocked", "error"]
STATUS_OF: dict[str, Status3] = {"executed": "ok", "pending_auth": "pending",
                                 "denied": "blocked", "safety_violation": "blocked",
                                 "failed": "error"}
