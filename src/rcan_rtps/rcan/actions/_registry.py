"""The registry: every public module of this package declares one action as `SPEC`.

Adding an action is adding a module; every surface (validation, OpenAPI, RBAC defaults, HiTL,
the e-stop lane, mDNS `caps`, metrics, docs) is derived from what is found here.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import os
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from ._invariants import READS
from ._spec import ActionSpec, Effect, SendGoal


@dataclass(frozen=True)
class GoalRoute:
    """One goal action server: the `bridge.ros2` key that names it, its type, and the
    registry actions that send goals to it."""

    action_key: str
    type_name: str
    actions: tuple[str, ...]


def collect_goal_routes(found: Iterable[ActionSpec[Any]]) -> tuple[GoalRoute, ...]:
    """The distinct (config key, type) of every SendGoal; a key declared with two types is
    refused (one key names one server, and a server serves one type)."""
    routes: dict[str, GoalRoute] = {}
    for spec in found:
        ros = spec.ros
        if not isinstance(ros, SendGoal):
            continue
        seen = routes.get(ros.action_key)
        if seen is not None and seen.type_name != ros.type_name:
            raise ValueError(
                f"goal route `{ros.action_key}` declared with two action types: "
                f"{seen.type_name} ({', '.join(seen.actions)}) and {ros.type_name} "
                f"({spec.name})")
        actions = (*seen.actions, spec.name) if seen else (spec.name,)
        routes[ros.action_key] = GoalRoute(ros.action_key, ros.type_name, actions)
    return tuple(routes.values())


def module_names(folders: Iterable[str]) -> list[str]:
    """The modules and sub-packages in a package's folders, sorted: what
    `pkgutil.iter_modules` names, without importing pkgutil, which a bridge run would keep
    for good (idle memory, issue 27)."""
    suffixes = importlib.machinery.all_suffixes()  # .py first, then .pyc, extensions
    names: set[str] = set()
    for folder in folders:
        with os.scandir(folder) as entries:
            for entry in entries:
                if entry.is_dir():
                    if os.path.isfile(os.path.join(entry.path, "__init__.py")):
                        names.add(entry.name)
                    continue
                suffix = next((s for s in suffixes if entry.name.endswith(s)), None)
                if suffix is not None:
                    names.add(entry.name[:-len(suffix)])
    return sorted(n for n in names if n.isidentifier() and n != "__init__")


def _discover() -> dict[str, ActionSpec[Any]]:
    found: dict[str, ActionSpec[Any]] = {}
    package = __name__.rsplit(".", 1)[0]
    for name in module_names(importlib.import_module(package).__path__):
        if name.startswith("_"):
            continue
        spec = getattr(importlib.import_module(f"{package}.{name}"), "SPEC", None)
        if not isinstance(spec, ActionSpec):
            raise TypeError(f"{package}.{name} declares no ActionSpec named SPEC")
        if spec.name in found or spec.name != name:
            raise ValueError(f"action {spec.name!r} must be declared once, by a module of "
                             "that name")
        found[spec.name] = spec
    found = dict(sorted(found.items(), key=lambda item: (item[1].order, item[0])))
    for effect in (Effect.HALT, Effect.ESTOP, Effect.CLEAR_ESTOP):
        if sum(s.effect is effect for s in found.values()) != 1:
            raise ValueError(f"exactly one action must have effect {effect.name}")
    collect_goal_routes(found.values())  # refused here, before anything uses the registry
    return found


ACTIONS: Mapping[str, ActionSpec[Any]] = MappingProxyType(_discover())
_GOAL_ROUTES = collect_goal_routes(ACTIONS.values())


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


def goal_routes() -> tuple[GoalRoute, ...]:
    """Every goal action server the registry sends to, one per (config key, type)."""
    return _GOAL_ROUTES


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
