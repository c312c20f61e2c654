"""`bridge.skills`: what an INVOKE (RCAN §19) may run, checked against the action registry.

A skill names one registry action, the parameters it always runs with (`params`, fixed) and
those the invoker may give (`allow`). When the config loads, every name must be a parameter of
that action, no name may be both fixed and allowed, every required parameter must be one or
the other, and each fixed value must have its parameter's type; what only a whole command can
show (a limit, arrays of equal length) is the governor's to check at each INVOKE.
"""

from __future__ import annotations

import typing
from typing import Any

import msgspec

from rcan_rtps.rcan.actions import action_spec


def skill_problem(action: str, params: dict[str, Any], allow: list[str]) -> str | None:
    """What is wrong with a skill's declaration, or None."""
    kind = action_spec(action).params
    fields = {f.name: f for f in msgspec.structs.fields(kind)}
    unknown = sorted(n for n in [*params, *allow] if n not in fields)
    if unknown:
        return (f"{', '.join(unknown)}: not a parameter of {action} "
                f"(its parameters: {', '.join(fields) or 'none'})")
    both = sorted(set(params) & set(allow))
    if both:
        return f"{', '.join(both)}: both fixed (params) and allowed (allow)"
    missing = sorted(n for n, f in fields.items() if f.required and n not in params
                     and n not in allow)
    if missing:
        return f"{', '.join(missing)}: required by {action}, neither fixed nor allowed"
    hints = typing.get_type_hints(kind, include_extras=True)
    for name, value in params.items():
        try:
            msgspec.convert(value, hints[name])
        except msgspec.ValidationError as exc:
            return f"params.{name}: {exc}"
    return None
