"""The published RCAN conformance suite, vendored with its source, and what this bridge makes
of each case: run as written, run adapted (the suite's wording assumes another design), or out
of scope (the vendored metadata says why; the reasons are printed with every run).

The suite's cases are descriptions (inputs and expected results), not scripts: `probes.py`
turns each in-scope case into requests against a running bridge.
"""

from __future__ import annotations

import json
from importlib import resources
from typing import Any, Literal

import msgspec

Level = Literal["L1", "L2", "L3"]
LEVELS: tuple[Level, ...] = ("L1", "L2", "L3")


class Case(msgspec.Struct, frozen=True, kw_only=True):
    id: str
    name: str
    level: Level
    description: str = ""
    test_type: str = ""
    input: dict[str, Any] = msgspec.field(default_factory=dict)
    expect: dict[str, Any] = msgspec.field(default_factory=dict)
    out_of_scope: str | None = None  # why, if so
    adapted: str | None = None  # how, if the case is run other than as worded


class Source(msgspec.Struct, frozen=True):
    repository: str
    path: str
    snapshot_commit: str
    last_changed_in: str
    license: str


class Vendored(msgspec.Struct, frozen=True):
    suite: str
    source: Source
    out_of_scope: dict[str, str]
    adapted: dict[str, str]
    actions: dict[str, str]  # the suite's example actions → this bridge's registry actions


class Suite(msgspec.Struct, frozen=True):
    version: str
    cases: list[Case]
    vendored: Vendored

    def upto(self, level: Level) -> list[Case]:
        """The cases of `level` and those below it (a level includes the ones under it)."""
        wanted = LEVELS[: LEVELS.index(level) + 1]
        return [c for c in self.cases if c.level in wanted]


def load_suite() -> Suite:
    here = resources.files(__package__)
    vendored = msgspec.json.decode((here / "vendored.json").read_bytes(), type=Vendored)
    raw = json.loads((here / vendored.suite).read_bytes())
    cases = []
    for level in LEVELS:
        for case in raw["levels"].get(level, []):
            fields = {k: case[k] for k in ("id", "name", "description", "test_type", "input",
                                           "expect") if k in case}
            cases.append(Case(level=level, out_of_scope=vendored.out_of_scope.get(case["id"]),
                              adapted=vendored.adapted.get(case["id"]), **fields))
    return Suite(version=str(raw["version"]), cases=cases, vendored=vendored)
