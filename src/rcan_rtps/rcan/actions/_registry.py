"""The registry: every public module of this package declares one action as `SPEC`.

Adding an action is adding a module; every surface (validation, OpenAPI, RBAC defaults, HiTL,
the e-stop lane, mDNS `caps`, metrics, docs) is derived from what is found here.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Iterator, Mapping
from types import MappingProxyType
from typing import Any

from ._invariants import READS
from ._spec import ActionSpec, Effect


def _discover() -> dict[str, ActionSpec[Any]]:
    found: dict[str, ActionSpec[Any]] = {}
    package = __name__.rsplit(".", 1)[0]
    for info in sorted(pkgutil.iter_modules(importlib.import_module(package).__path__),
                       key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        spec = getattr(importlib.import_module(f"{package}.{info.name}"), "SPEC", None)
        if not isinstance(spec, ActionSpec):
            raise TypeError(f"{package}.{info.name} declares no ActionSpec named SPEC")
        if spec.name in found or spec.name != info.name:
            raise ValueError(f"action {spec.name!r} must be declared once, by a module of "
                             "that name")
        found[spec.name] = spec
    found = dict(sorted(found.items(), key=lambda item: (item[1].order, item[0])))
    for effect in (Effect.HALT, Effect.ESTOP, Effect.CLEAR_ESTOP):
        if sum(s.effect is effect for s in found.values()) != 1:
            raise ValueError(f"exactly one action must have effect {effect.name}")
    return found


ACTIONS: Mapping[str, ActionSpec[Any]] = MappingProxyType(_discover())


def action_spec(name: str) -> ActionSpec[Any]:
    """The spec of a (validated) action name; KeyError for names not in the registry."""
    return ACTIONS[name]


def names() -> tuple[str, ...]:
    return tuple(ACTIONS)


def with_effect(effect: Effect) -> ActionSpec[Any]:
    """The one action of a singular effect (HALT, ESTOP, CLEAR_ESTOP)."""
    return next(s for s in ACTIONS.values() if s.effect is effect)


def stopping_names() -> frozenset[str]:
    return frozenset(n for n, s in ACTIONS.items() if s.stopping)


def specs() -> Iterator[ActionSpec[Any]]:
    return iter(ACTIONS.values())


def markdown_table() -> str:
    """The tables of docs/actions.md: the actions, then what each §8 check reads."""
    rows = ["| action | what it does | default role | human approval | §8 invariants |",
            "|---|---|---|---|---|"]
    for spec in ACTIONS.values():
        facts = spec.describe()
        rows.append(f"| `{spec.name}` | {spec.summary} | {facts['default_role']} | "
                    f"{facts['hitl']} | {', '.join(facts['invariants'])} |")
    rows += ["", "| §8 check | reads from the parameters (an action declaring it must have them) |",
             "|---|---|"]
    rows += [f"| {invariant.value} | {reads.describe()} |" for invariant, reads in READS.items()]
    return "\n".join(rows) + "\n"
