"""The robot's faults as STATUS lists them: bounded, and failing closed.

Any node on the graph may publish DiagnosticArrays, with as many component names as it likes:
the table keeps at most `MAX_FAULTS` components. Beyond that an ERROR is never dropped in
favour of a WARN or STALE (one of those makes room for it), and whatever is not listed is
counted in one synthetic ERROR fault (`UNLISTED`), so a STATUS that could not list everything
never reads as fine. A component that was not listed leaves the count when it reports OK, or
enters the table when it reports again and there is room. Names of components not listed are
themselves kept only up to `MAX_UNLISTED`; past that the bridge can no longer tell when they
clear, and the synthetic fault stays until the bridge restarts.

Names and messages are cut to `MAX_NAME` and `MAX_MESSAGE` characters (a cut name keeps a
digest of the whole, so two long names never merge into one component).
"""

from __future__ import annotations

import hashlib
from typing import Literal

from ..rcan import Fault

Level = Literal["WARN", "ERROR", "STALE"]

MAX_FAULTS = 256
MAX_UNLISTED = 4096
MAX_NAME = 256
MAX_MESSAGE = 512
UNLISTED = "rcan_rtps/faults_not_listed"


def cut_text(text: str, limit: int) -> str:
    """`text`, or its first characters and how many more there were."""
    if len(text) <= limit:
        return text
    more = f"… (+{len(text) - limit} chars)"
    return text[:limit - len(more)] + more


def component_name(name: str) -> str:
    """The name a component is kept under: itself, or, when too long, its start and a
    digest of all of it."""
    if len(name) <= MAX_NAME:
        return name
    digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:16]
    return f"{name[:MAX_NAME - 20]}…#{digest}"


class FaultTable:
    """The latest non-OK report of each diagnostic component. Not thread-safe: the caller
    holds its own lock."""

    def __init__(self, max_faults: int = MAX_FAULTS, max_unlisted: int = MAX_UNLISTED) -> None:
        self._max = max_faults
        self._max_unlisted = max_unlisted
        self._faults: dict[str, Fault] = {}
        self._unlisted: set[str] = set()
        self._unlisted_lost = 0  # reports of components past even `max_unlisted`

    def report(self, name: str, level: Level | None, message: str) -> None:
        """One component's report; `level` None is OK (it clears the component)."""
        name = component_name(name)
        if level is None:
            self._faults.pop(name, None)
            self._unlisted.discard(name)
            return
        fault = Fault(name, cut_text(message, MAX_MESSAGE), level)
        if name in self._faults or len(self._faults) < self._max or self._make_room(level):
            self._faults[name] = fault
            self._unlisted.discard(name)
        else:
            self._not_listed(name)

    def _make_room(self, level: Level) -> bool:
        """An ERROR takes the place of a listed WARN or STALE (which is then counted as not
        listed); nothing else makes room."""
        if level != "ERROR":
            return False
        lesser = next((n for n, f in self._faults.items() if f.level != "ERROR"), None)
        if lesser is None:
            return False
        del self._faults[lesser]
        self._not_listed(lesser)
        return True

    def _not_listed(self, name: str) -> None:
        if name in self._unlisted:
            return
        if len(self._unlisted) < self._max_unlisted:
            self._unlisted.add(name)
        else:
            self._unlisted_lost += 1

    def faults(self) -> list[Fault]:
        """The listed faults by name, then the synthetic one if anything is not listed."""
        listed = sorted(self._faults.values(), key=lambda f: f.name)
        if self._unlisted_lost:
            listed.append(Fault(UNLISTED, (
                f"more than {len(self._unlisted)} diagnostic components reported a fault that "
                f"is not listed (at most {self._max} are), too many to follow: this stays "
                f"until the bridge restarts"), "ERROR"))
        elif self._unlisted:
            listed.append(Fault(UNLISTED, (
                f"{len(self._unlisted)} more diagnostic component(s) reported a fault that is "
                f"not listed (at most {self._max} are)"), "ERROR"))
        return listed

    def __len__(self) -> int:
        return len(self._faults)
