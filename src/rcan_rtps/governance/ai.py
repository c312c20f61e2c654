"""§16.1 AI accountability: an AI command names its model, and agents keep to theirs.

An AI command is one that carries anything of an AI's (`confidence`, the `ai` object, the
short form's `ai_*` fields). Such a command without a model (`ai.model`, `ai_model`) is
refused — 400 AUDIT_INCOMPLETE_AI_IDENTITY `ai_model_required` — since its audit entry could
not say which model asked (rcan-spec conformance L3-AI-002). A principal bound to models in
`bridge.ai.agents` is an agent: each of its commands must be an AI command naming one of its
models (400 as above without one; 403 INSUFFICIENT_PRIVILEGES `ai_model_not_allowed` for
another). Both are audited (COMMAND_REJECTED, with the command's `ai`).

Stops are exempt: an authenticated request that says stop, stops; what would have refused it
comes back as a warning.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from rcan_rtps.rcan import NormalizedCommand

from . import outcomes
from .outcomes import Rejection
from .rbac import Principal


class AiPolicy:
    def __init__(self, agents: Mapping[str, Sequence[str]] | None = None) -> None:
        self._agents = {name: frozenset(models) for name, models in (agents or {}).items()}

    def check(self, command: NormalizedCommand, principal: Principal) -> Rejection | None:
        """Why this command may not go ahead as an AI's (or an agent's), or None."""
        allowed = self._agents.get(principal.name)
        ai = command.ai
        if ai is None and allowed is None:
            return None  # a human's command
        model = None if ai is None else ai.model
        if not model:
            return outcomes.AI_MODEL_REQUIRED
        if allowed is not None and model not in allowed:
            return outcomes.AI_MODEL_NOT_ALLOWED
        return None

    def warning(self, command: NormalizedCommand, principal: Principal) -> str | None:
        """For a stop, which is executed anyway: what `check` would have refused."""
        refused = self.check(command, principal)
        if refused is None:
            return None
        return f"{refused.reason}: executed anyway (a stop is never refused)"
