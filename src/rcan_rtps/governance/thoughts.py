"""The Thought log (RCAN §16.5): what an AI's thought (its `thought_id`) led to, queryable.

A command carrying `ai.thought_id` adds to its thought's record: the model that produced it,
its confidence, the command (action and parameters as asked), and the governor's decision with
the audit entry that holds it. The model's reasoning, if the command carried one, is kept here
and only here: the audit entry records its SHA-256 (so what is shown can be checked against
the signed chain), because the audit is readable below the scope the reasoning needs — §16.5:
`reasoning` is omitted unless the reader holds the config scope, OWNER or higher, so a
principal with operational access cannot extract the prompt.

A thought id is its first sender's: the record shown is the one of the principal whose command
named it first, and another principal's command naming the same id (a GUEST's refused one, a
replayed id) never rewrites that record's model, confidence or reasoning. Such commands go into
a record of their own sender's for the same id (`?principal=`), and the first record lists who
else named it (`also_named_by`), so a reader sees the collision instead of a forged thought.

The log is in memory, bounded (`KEPT` thought ids, the oldest let go first; `NAMERS` senders
per id): since the bridge started. The audit log keeps every command's AI identity for good.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import msgspec

from rcan_rtps.rcan import NormalizedCommand, Role

from .rbac import Principal

KEPT = 1024
NAMERS = 8  # senders' records per thought id: the first one's, and 7 more who named it
REASONING_ROLE = Role.OWNER  # §16.5: "config scope (OWNER or higher)"


class ThoughtCommand(msgspec.Struct, frozen=True, kw_only=True):
    """One command of a thought, and what the governor decided."""

    type: str  # the action
    params: dict[str, Any]
    message_id: str
    principal: str
    outcome: str
    audit_id: str | None = None
    error_code: str | None = None
    reason: str | None = None


class Thought(msgspec.Struct, kw_only=True, omit_defaults=True):
    """GET /api/thoughts/{thought_id} (§16.5's record, with every command of the thought)."""

    id: str
    principal: str  # whose record this is (the first to name the id, unless asked otherwise)
    timestamp_ms: int
    provider: str | None = None
    model: str | None = None
    confidence: float | None = None
    action: ThoughtCommand  # the latest command of the thought
    commands: list[ThoughtCommand]
    reasoning: str | None = None
    reasoning_sha256: str | None = None
    also_named_by: list[str] | None = None  # other principals whose commands named the id


class ThoughtLog:
    def __init__(self, kept: int = KEPT) -> None:
        self._kept = kept
        # thought id → each sender's record, the first sender's first
        self._thoughts: OrderedDict[str, dict[str, Thought]] = OrderedDict()

    def remember(self, command: NormalizedCommand, principal: Principal, at_ms: int, *,
                 outcome: str, audit_id: str | None, error_code: str | None = None,
                 reason: str | None = None, reasoning_sha256: str | None = None) -> None:
        ai = command.ai
        if ai is None or not ai.thought_id:
            return
        done = ThoughtCommand(type=command.action, params=dict(command.requested),
                              message_id=command.message_id, principal=principal.name,
                              outcome=outcome, audit_id=audit_id, error_code=error_code,
                              reason=reason)
        named = self._thoughts.pop(ai.thought_id, {})
        self._thoughts[ai.thought_id] = named
        while len(self._thoughts) > self._kept:
            self._thoughts.popitem(last=False)
        thought = named.get(principal.name)
        if thought is None:
            if len(named) >= NAMERS:
                return  # the id named by too many: the audit log has them all
            thought = named[principal.name] = Thought(
                id=ai.thought_id, principal=principal.name, timestamp_ms=at_ms, action=done,
                commands=[])
        thought.provider, thought.model = ai.provider or thought.provider, (
            ai.model or thought.model)
        if ai.confidence is not None:
            thought.confidence = ai.confidence
        if ai.reasoning is not None:
            thought.reasoning, thought.reasoning_sha256 = ai.reasoning, reasoning_sha256
        thought.action = done
        thought.commands = [*thought.commands[-63:], done]  # bounded, like the log

    def read(self, thought_id: str, reader: Principal, principal: str | None = None
             ) -> Thought | None:
        """The thought as `reader` may see it: the record of `principal`'s commands naming
        it (None: of the first to name it), without its reasoning below the config scope."""
        named = self._thoughts.get(thought_id)
        if not named:
            return None
        first = next(iter(named))
        thought = named.get(first if principal is None else principal)
        if thought is None:
            return None
        others = [name for name in named if name != thought.principal]
        shown = msgspec.structs.replace(thought, also_named_by=others or None)
        if reader.role < REASONING_ROLE:
            shown.reasoning = None  # its digest stays: that there was one is no secret
        return shown
