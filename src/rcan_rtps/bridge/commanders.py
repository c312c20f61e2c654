"""Other commanders: participants that publish on the topics the bridge commands the robot on.

A second node publishing on the bridge's velocity or trajectory topic makes the robot obey it
between the bridge's samples, and an e-stop cannot hold the robot against it. The bridge
cannot stop such a peer; it makes it seen. `CommanderWatch` reads the graph (the builtin
publication topic, `ros.graph.RosGraph`) every `interval` seconds and, for each participant
other than the bridge's own publishing on a command topic:

- STATUS lists it (`foreign_publishers`; telemetry.py turns it into faults),
- a WARNING is logged when it appears and when it goes (once each),
- the audit records each appearance and disappearance (FOREIGN_PUBLISHER, _GONE).

The operator may declare the nodes meant to publish there too (nav2's controller_server or
velocity_smoother on cmd_vel: `bridge.ros2.foreign_publishers.expected`). A participant is
`expected` on a topic when every one of its writers there belongs to a node named on that
topic's list; one writer of an unnamed node (no ros_discovery_info) or of another node makes
it unexpected. An expected one is listed, audited and logged (at INFO) all the same; what it
changes is telemetry.py's faults. One reported that turns unexpected (or expected) is logged and
audited again, as an appearance with its new facts: the audit never ends on "expected" for a
participant whose writers are no longer all declared.

A participant counts once per topic, however many writers it has there. Its appearance is
logged and audited once its node is named (ros_discovery_info may come after the endpoint:
Fast DDS sends it to a new reader on its next heartbeat), or after `NAME_GRACE_S` unnamed;
STATUS lists it at once.

Any participant may appear and leave as often as it likes, unauthenticated, and each told is a
signed, durable audit entry: what the log and the audit are told has a budget (`ReportBudget`,
a token bucket per participant on a topic and one for all). An event past it is counted, and
its participant held: its later events are counted too. Once per `SUMMARY_S`, one entry (and
one log line) says how many were left out and of whom, and each held participant whose last
audited state is no longer true is told as it is now (an appearance, with its facts, or its
going): the audit keeps each participant's first events and its last word, and never ends on
"present" for one that left, or the reverse. STATUS, and so the e-stop's fault, is told every
change, never held back.

Cost: a poll takes what discovery changed since the last one (nothing, on a quiet graph) and
only then looks at the publishers of the command topics: a set lookup per endpoint of the
graph. No lock of the bridge is held while DDS is called. Behind a flood of discovery (a peer
making and deleting endpoints faster than they are read) a refresh takes so much at a time
(`ros.graph.REFRESH_TAKE`) and the watch polls again at once, giving the loop a turn between
two: a stop is answered while the flood lasts.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

from ..rcan import ForeignPublisher
from ..ros.graph import MAX_NODE_FQN, Endpoint, node_fqn, shared_graph, short_gid
from ..ros.participant import RosNode
from .report_budget import ReportBudget

log = logging.getLogger(__name__)

POLL_S = 1.0
NAME_GRACE_S = 4.0
# What the audit is told of other publishers, whatever they do (`report_budget`): a
# participant's first KEY_BURST events on a topic, then one each KEY_REFILL_S; all together,
# ALL_BURST, then one each ALL_REFILL_S. What is left out is summed up once each SUMMARY_S,
# with at most MAX_SETTLE participants told as they are then. Sustained, a domain of
# flapping peers makes at most ~1 + 6 + 8 entries a minute (was ~600 at poll_s 0.1).
KEY_BURST, KEY_REFILL_S = 4.0, 60.0
ALL_BURST, ALL_REFILL_S = 32.0, 10.0
SUMMARY_S = 60.0
MAX_SETTLE = 8
MAX_NAMED = 8  # participants a summary names, with their counts
_UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"
# A node's fully qualified name as ros_discovery_info bounds it (namespace and name 256
# characters each): the graph cuts what a peer writes past that where it reads it, and a cut
# name never matches a declared one (ros.graph.bound_node_name).
MAX_NODE_NAME = MAX_NODE_FQN

Key = tuple[str, bytes]  # (topic, participant GUID)
_Event = tuple[Key, ForeignPublisher, bool]  # who, as it is, gone
Audit = Callable[..., None]  # Governor.foreign_publisher(facts, gone=...)


Expected = dict[str, frozenset[str]]  # topic → the nodes declared to publish there


def _facts(publisher: ForeignPublisher) -> dict[str, Any]:
    return {"topic": publisher.topic, "type": publisher.type,
            "participant": publisher.participant, "node": publisher.node,
            "writers": publisher.writers, "expected": publisher.expected}


def _describe(publisher: ForeignPublisher) -> str:
    who = publisher.node or "an unnamed node"
    return (f"{who}{' (expected)' if publisher.expected else ''} (participant "
            f"{publisher.participant}, {publisher.writers} writer(s), {publisher.type})")


def foreign_publishers(endpoints: list[Endpoint], own: bytes,
                       expected: Expected | None = None) -> dict[Key, ForeignPublisher]:
    """Each participant other than `own` publishing on these endpoints' topics, once per
    topic (its writers counted), marked `expected` when each of its writers there is of a
    node `expected` lists for the topic. It is named by the node of its first named writer
    that is not expected, else of its first named writer."""
    expected = expected or {}
    found: dict[Key, ForeignPublisher] = {}
    nodes: dict[Key, list[str | None]] = {}
    for e in endpoints:
        if e.participant_gid == own:
            continue
        key = (e.ros_name, e.participant_gid)
        node = None if e.node_name == _UNKNOWN_NODE else node_fqn(e.node_namespace, e.node_name)
        if key not in found:
            found[key] = ForeignPublisher(topic=e.ros_name, type=e.ros_type,
                                          participant=short_gid(e.participant_gid[:12]))
        else:
            found[key].writers += 1
        nodes.setdefault(key, []).append(node)
    for key, publisher in found.items():
        declared = expected.get(publisher.topic, frozenset())
        named = [n for n in nodes[key] if n is not None]
        publisher.expected = len(named) == len(nodes[key]) and all(n in declared for n in named)
        shown = [n for n in named if n not in declared] or named
        publisher.node = shown[0] if shown else None
    return found


class _LeftOut:
    """What the budget left out since the last summary: how many events, and of whom (the
    first `MAX_NAMED` participants counted one by one, the rest in all)."""

    def __init__(self) -> None:
        self.events = 0
        self.topics: set[str] = set()
        self.named: dict[Key, tuple[ForeignPublisher, int]] = {}
        self.others = 0  # events of participants past the first MAX_NAMED

    def add(self, key: Key, publisher: ForeignPublisher) -> None:
        self.events += 1
        self.topics.add(publisher.topic)
        if key in self.named or len(self.named) < MAX_NAMED:
            self.named[key] = (publisher, self.named.get(key, (publisher, 0))[1] + 1)
        else:
            self.others += 1

    def facts(self, window_s: float, unsettled: int) -> dict[str, Any]:
        topics = sorted(self.topics)
        who = sorted(self.named.values(), key=lambda pn: -pn[1])
        return {"topic": topics[0] if topics else None, "topics": topics,
                "left_out": self.events, "window_s": round(window_s, 3),
                "of": [{"topic": p.topic, "participant": p.participant, "node": p.node,
                        "left_out": n} for p, n in who],
                "others_left_out": self.others, "unsettled": unsettled}


class CommanderWatch:
    """Polls the graph for other publishers on the command topics; tells STATUS, the log and
    the audit. `start()` on the loop; `close()` stops it."""

    def __init__(self, node: RosNode, topics: dict[str, bool], *,
                 show: Callable[[list[ForeignPublisher], set[str]], None], audit: Audit,
                 interval: float = POLL_S, expected: Expected | None = None,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        # The node's one view, the one its service and action clients refresh before each
        # call: polled here, it is read at least every `interval` even when no call is made
        # (its builtin readers keep every endpoint that came and went until a refresh takes
        # it: an idle bridge beside peers that come and go grew ~2 kB per endpoint).
        self._graph = shared_graph(node)
        self._own = node.participant.guid.bytes
        self._topics = set(topics)
        self._expected = dict(expected or {})
        self._motion = {t for t, moves in topics.items() if moves}
        self._show, self._audit, self.interval = show, audit, interval
        self._known: dict[Key, ForeignPublisher] = {}
        self._unreported: dict[Key, float] = {}  # seen, not yet logged: since when
        self._monotonic = monotonic
        self._generation = -1
        self._task: asyncio.Task[None] | None = None
        self._failed = False
        now = monotonic()
        self._budget: ReportBudget[Key] = ReportBudget(
            key_burst=KEY_BURST, key_refill_s=KEY_REFILL_S, all_burst=ALL_BURST,
            all_refill_s=ALL_REFILL_S, now=now)
        # What the audit last said of each participant on a topic (absent: not there), and
        # those whose events were left out since: each is told as it is at the next summary.
        self._said: dict[Key, ForeignPublisher] = {}
        self._held: set[Key] = set()
        self._left_out = _LeftOut()
        self._window_start = now

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="commander-watch")

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    async def _run(self) -> None:
        while True:
            caught_up = True
            try:
                caught_up = self.poll()
                self._failed = False
            except Exception as exc:  # the watch fails alone, logged once until it works
                if not self._failed:
                    log.warning("watching the command topics for other publishers failed "
                                "(%s: %s); retrying", type(exc).__name__, exc)
                self._failed = True
            # Behind a flood of discovery (a refresh takes so much at a time, ros.graph):
            # again at once, after the loop's other work, until caught up.
            await asyncio.sleep(self.interval if caught_up else 0)

    def poll(self) -> bool:
        """One look at the graph: what appeared and what went since the last. False when
        the graph has more discovery waiting than one refresh takes."""
        caught_up = self._graph.refresh()
        if self._graph.generation != self._generation:  # else nothing came or went
            self._generation = self._graph.generation
            self.update(foreign_publishers(self._graph.publishers_on(self._topics), self._own,
                                           self._expected))
        self.tick()
        return caught_up

    def tick(self) -> None:
        """What each poll does after reading the graph: appearances now due are told, and
        once per `SUMMARY_S` what the budget left out is summed up."""
        self._tell(self._due())
        if self._monotonic() - self._window_start >= SUMMARY_S:
            self._summarize()

    def update(self, now: dict[Key, ForeignPublisher]) -> None:
        """The publishers on the command topics are now these: STATUS shows them at once;
        what came, changed and went is told (within the budget)."""
        clock = self._monotonic()
        for key in now.keys() - self._known.keys():
            self._unreported[key] = clock
        events: list[_Event] = []
        # One that came and went between two reports: its appearance is recorded too.
        events += [(k, self._known[k], False) for k in self._unreported if k not in now]
        # One reported that is now expected where it was not, or the reverse (a writer of
        # another node joined it, or left): told again, as it is now.
        events += [(k, p, False) for k, p in now.items() if k in self._known and k not in
                   self._unreported and p.expected != self._known[k].expected]
        events += [(k, p, True) for k, p in self._known.items() if k not in now]
        self._unreported = {k: t for k, t in self._unreported.items() if k in now}
        self._known = now
        self._show(list(now.values()), self._motion)
        self._tell(events)

    def _due(self) -> list[_Event]:
        """Appearances to report now: named, or unnamed for `NAME_GRACE_S`."""
        clock = self._monotonic()
        due = [k for k, since in self._unreported.items()
               if self._known[k].node is not None or clock - since >= NAME_GRACE_S]
        for key in due:
            del self._unreported[key]
        return [(k, self._known[k], False) for k in due]

    def _tell(self, events: list[_Event]) -> None:
        """Logs and audits each event the budget allows; counts the others. A participant
        with one left out is held: its later events are counted too until the summary,
        which tells how it is then — so the audit's last word on each is never one that
        the left-out events made false."""
        clock = self._monotonic()
        for key, publisher, gone in events:
            if key not in self._held and self._budget.take(key, clock):
                self._tell_one(key, publisher, gone=gone)
            else:
                self._held.add(key)
                self._left_out.add(key, publisher)

    def _tell_one(self, key: Key, p: ForeignPublisher, *, gone: bool) -> None:
        # A declared one is the robot's design, not news: told at INFO.
        level = logging.INFO if p.expected else logging.WARNING
        if gone:
            log.log(level, "%s no longer publishes on %s", _describe(p), p.topic)
            self._said.pop(key, None)
        else:
            log.log(level, "%s publishes on %s, a topic the bridge commands the robot on: "
                    "the robot obeys it too%s", _describe(p), p.topic,
                    ", and an e-stop cannot hold it" if p.topic in self._motion else "")
            self._said[key] = p
        self._audit(_facts(p), gone=gone)

    def _unsettled(self) -> list[Key]:
        """The held participants the audit's last word on is not true of now (the present
        ones first, the unexpected first among them). One still waiting for its name is
        told when it is named, as any."""
        def wrong(key: Key) -> bool:
            said, now = self._said.get(key), self._known.get(key)
            return (said is None) != (now is None) or (
                said is not None and now is not None and said.expected != now.expected)
        keys = [k for k in self._held if k not in self._unreported and wrong(k)]
        return sorted(keys, key=lambda k: (k not in self._known, self._known[k].expected
                                           if k in self._known else True, k))

    def _summarize(self) -> None:
        """Once per `SUMMARY_S`, when any event was left out: one entry (and one log line)
        saying how many and of whom, then each held participant as it is now (at most
        `MAX_SETTLE`; the others at the next summary, counted as `unsettled`)."""
        clock = self._monotonic()
        window, self._window_start = clock - self._window_start, clock
        self._budget.prune(clock)
        if not self._held and not self._left_out.events:
            return
        unsettled = self._unsettled()
        settle, later = unsettled[:MAX_SETTLE], unsettled[MAX_SETTLE:]
        left_out, self._left_out = self._left_out, _LeftOut()
        if left_out.events:
            facts = left_out.facts(window, len(later))
            log.warning("%d appearance(s) and disappearance(s) of %d participant(s) on %s in "
                        "the last %.0f s were not logged or audited one by one (too many); "
                        "each is recorded as it is now, and STATUS lists those present",
                        left_out.events, len(left_out.named) + (left_out.others > 0),
                        ", ".join(facts["topics"]), window)
            self._audit(facts, gone=False)
        for key in settle:
            now = self._known.get(key)
            self._tell_one(key, now or self._said[key], gone=now is None)
        self._held = set(later) | {k for k in self._held if k in self._unreported}

    @property
    def known(self) -> list[ForeignPublisher]:
        return list(self._known.values())
