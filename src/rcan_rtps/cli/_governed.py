"""Publishing where a governor commands the robot: refused unless asked for.

A bridge (`rcan-rtps run`) marks each writer the robot obeys — velocity and trajectory
topics, the e-stop's, its action clients' goal and cancel requests — with its robot's id
(`ros.graph.Endpoint.governed_by`). A message published beside one reaches the robot without
passing that governance: no role, no limits, no HiTL, no audit entry, and through a latched
e-stop. So the commands that send (`topic pub`, `bag play`, `service call`, `action
send_goal`) refuse a topic a governed writer is on, unless `--ungoverned` says that is meant
(the bridge then lists the sender among the robot's other commanders).

A tool only sees what it has discovered: each command looks for GOVERNOR_LOOK_S before it
sends and again while it sends (a governor found later ends it). This guards against a
mistake; it is no security boundary — any DDS peer can publish, and what keeps one out is
DDS-Security's permissions (SROS2).
"""

from __future__ import annotations

import asyncio
import sys
import time

from .._printable import shown
from ..ros.errors import WireError
from ..ros.graph import RosGraph
from ..ros.names import action_names, action_of, mangle_service, mangle_topic

GOVERNOR_LOOK_S = 1.0  # s a command looks at the graph for a governor before it first sends
LOOK_PERIOD = 0.5  # s between looks while it sends
# Characters of a governor's name shown: a RURI is far shorter, but the mark is a peer's own
# words, of any length (a 60 KB one filled the terminal with the error's one line).
SHOWN_GOVERNOR = 200
UNGOVERNED = ("--ungoverned", "send even where a governor (an rcan-rtps bridge) commands the "
              "robot: past its roles, limits, approvals, audit and e-stop")


class GovernorGuard:
    """Looks for governed endpoints on the DDS topics a command sends on (`topics`: DDS name
    → what to call it), as `TypeGuard` looks for other types."""

    def __init__(self, graph: RosGraph, topics: dict[str, str], *, allowed: bool) -> None:
        self.graph, self.topics, self.allowed = graph, topics, allowed
        self._next_look = 0.0
        self._warned: set[tuple[str, str]] = set()

    async def look_before_sending(self) -> None:
        """Looks for GOVERNOR_LOOK_S (discovery takes a moment), raising at the first seen,
        and on until the graph has read all discovery waiting: a refresh takes so much at a
        time (`ros.graph.REFRESH_TAKE`), and behind a large graph or a flood of discovery the
        governor may be among what is not read yet (fails closed: nothing sent meanwhile)."""
        deadline = time.monotonic() + GOVERNOR_LOOK_S
        while True:
            caught_up = self.check()
            if caught_up and time.monotonic() >= deadline:
                return
            await asyncio.sleep(0.05 if caught_up else 0)

    def check_when_due(self) -> None:
        if time.monotonic() >= self._next_look:
            self.check()

    def check(self) -> bool:
        """Raises WireError (one line, exit 1) for a governed endpoint on one of the topics
        (or, allowed, says once on stderr that the governor is passed by). False when the
        graph has more discovery waiting than one refresh takes."""
        self._next_look = time.monotonic() + LOOK_PERIOD
        caught_up = self.graph.refresh()
        governed = {(e.dds_topic, e.governed_by) for e in self.graph.endpoints()
                    if e.governed_by and e.dds_topic in self.topics}  # one look at the graph
        for dds_topic, name in self.topics.items():
            for governor in sorted(g for t, g in governed if t == dds_topic):
                self._found(name, governor)
        return caught_up

    def _found(self, name: str, governor: str) -> None:
        said = _shown_governor(governor)
        if not self.allowed:
            raise WireError(
                f"{name} is governed: the rcan-rtps bridge of {said} commands the robot "
                "there, and what is sent beside it passes its roles, limits, approvals, "
                "audit and e-stop by. Command the robot through the bridge's API, or add "
                "--ungoverned to send anyway")
        if (name, governor) not in self._warned:
            self._warned.add((name, governor))
            print(f"warning: {name} is governed by {said}: sending ungoverned "
                  "(--ungoverned)", file=sys.stderr, flush=True)


def _shown_governor(governor: str) -> str:
    """A peer's words: what does not print escaped, and no more than SHOWN_GOVERNOR of them."""
    if len(governor) <= SHOWN_GOVERNOR:
        return shown(governor)
    return f"{shown(governor[:SHOWN_GOVERNOR])}… ({len(governor)} characters)"


def action_topics(action: str) -> dict[str, str]:
    """The DDS topics a governed action client is seen on: its status reader from the
    start, its goal and cancel request writers from their first use."""
    names = action_names(action)
    return {mangle_topic(names["status"]): action,
            mangle_service(names["send_goal"])[0]: action,
            mangle_service(names["cancel_goal"])[0]: action}


def service_topics(service: str) -> dict[str, str]:
    """A service's request topic; for one of an action's services, the action's too."""
    part_of = action_of(service)
    return {mangle_service(service)[0]: service,
            **(action_topics(part_of[0]) if part_of is not None else {})}
