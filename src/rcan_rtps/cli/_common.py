"""What every graph command shares: global options and a short-lived hidden node."""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from typing import Any, Protocol

import yaml

from ..ros.errors import GraphTimeout, WireError, seconds
from ..ros.graph import Direction, Endpoint, RosGraph
from ..ros.participant import RosNode, localhost_requested
from ..ros.typesys.store import TypeStore, env_idl_paths, normalize_name
from ._options import IDL_PATH_AFTER_VERB, add_global_options, merge_global_options

__all__ = ["IDL_PATH_AFTER_VERB", "add_global_options", "merge_global_options"]

TYPE_CHECK_PERIOD = 0.5  # s between looks at the graph for endpoints of another type
OTHER_TYPE_PATIENCE = 2.0  # s the graph has to name an endpoint DDS says is of another type
TOPIC_HELP = "topic name, e.g. /robot1/odom (relative names resolve from /)"
VALUES_HELP = "field values as YAML, e.g. \"{linear: {x: 0.2}}\" (default: all defaults)"


def make_store(args: argparse.Namespace) -> TypeStore:
    return TypeStore([*args.idl_path, *env_idl_paths()], args.distro)


def make_node(args: argparse.Namespace) -> RosNode:
    # Hidden (leading '_') like ros2cli's own nodes, so `node list` leaves it out.
    return RosNode(f"_rcan_rtps_cli_{os.getpid()}", "/", domain_id=args.domain_id,
                   localhost=args.localhost, store=make_store(args))


def parse_values(text: str) -> Any:
    """VALUES as ros2cli takes them: YAML (an empty string means all defaults)."""
    try:
        return yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as exc:
        raise WireError(f"VALUES is not valid YAML: {_yaml_problem(exc)}") from None


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """PyYAML's problem and where, in one line (its own text spans lines, with a caret)."""
    problem = getattr(exc, "problem", None)
    mark = getattr(exc, "problem_mark", None)
    if problem is None:
        return " ".join(str(exc).split())
    if mark is None:
        return str(problem)
    line = f"line {mark.line + 1}, " if mark.line else ""
    return f"{problem} (at {line}column {mark.column + 1})"


def dump(values: Any) -> str:
    return yaml.safe_dump(values, sort_keys=False, allow_unicode=True).rstrip()


def alone_hint(args: argparse.Namespace, node: RosNode, graph: RosGraph) -> str:
    """What to try next when the graph shows nobody but this tool; '' when others are there."""
    if any(name != node.name for _, name in graph.nodes()):
        return ""
    where = f"nothing found on ROS domain {node.domain_id}"
    if localhost_requested(args.localhost):
        return f"{where}: is anything running with this ROS_DOMAIN_ID (or --domain-id)?"
    return (f"{where}; the demo (`rcan-rtps run --sim`) keeps to loopback: add `--localhost` "
            "(or set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)")


def warn_if_alone(args: argparse.Namespace, node: RosNode, graph: RosGraph) -> None:
    hint = alone_hint(args, node, graph)
    if hint:
        print(f"rcan-rtps: {hint}", file=sys.stderr)


async def resolve_type(args: argparse.Namespace, node: RosNode, graph: RosGraph, topic: str,
                       given: str | None, timeout: float) -> tuple[str, list[Endpoint]]:
    """TYPE as given, else the one type the topic's publishers use; and those publishers."""
    timeout = timeout or 5.0
    deadline = time.monotonic() + timeout
    while True:
        graph.refresh()
        pubs = [e for e in graph.topic_endpoints(topic) if e.direction is Direction.PUBLISHER]
        if given or pubs or time.monotonic() > deadline:
            break
        await asyncio.sleep(0.1)
    if given:
        return given, pubs
    types = sorted({e.ros_type for e in pubs})
    if not types:
        hint = alone_hint(args, node, graph) or "is it published? or pass TYPE explicitly"
        raise GraphTimeout(f"could not determine the type of '{topic}': no publisher found "
                           f"within {seconds(timeout)}; {hint}")
    if len(types) > 1:
        raise GraphTimeout(f"'{topic}' has several types ({', '.join(types)}); pass TYPE")
    return types[0], pubs


def _short_hash(type_hash: str) -> str:
    if not type_hash:
        return "no type hash"
    kind, _, digest = type_hash.partition("_")
    return f"{kind} {digest[:12]}…" if digest else type_hash


def type_conflict(store: TypeStore, own_node: str, endpoints: list[Endpoint], topic: str,
                  type_name: str) -> str | None:
    """What is wrong when other endpoints of `topic` have another type than `type_name`: a
    different name, or the same name with a different RIHS01 hash (a changed definition;
    compared only where both sides have a hash)."""
    type_name = normalize_name(type_name)
    ours = store.hash_of(type_name) if store.distro != "humble" else ""
    theirs = {(e.ros_type, e.type_hash) for e in endpoints
              if e.node_name != own_node and (e.ros_type != type_name or (
                  ours and e.type_hash and e.type_hash != ours))}
    if not theirs:
        return None
    has = ", ".join(f"{name} ({_short_hash(h)})" for name, h in sorted(theirs))
    return (f"type mismatch: {topic} has {has}, you asked for {type_name} "
            f"({_short_hash(ours)})")


class OwnEndpoint(Protocol):
    """A publisher or subscription of the command, made with `warn_other_type=False`."""

    other_type_events: int


class TypeGuard:
    """Ends a command whose topic has endpoints of another type than its own, with one error
    that names both types and RIHS01 hashes (`type_conflict`), raised as a WireError: DDS
    never matches the two, so waiting cannot help.

    It hears of such an endpoint two ways: the graph, looked at every TYPE_CHECK_PERIOD,
    and the DDS status of the command's own endpoint (`other_type_events`; the participant's
    own warning about it is off, so that the user reads one line about one problem). The
    status can come a moment before the graph shows the other endpoint; the error then
    waits for the graph up to OTHER_TYPE_PATIENCE and, without it, still says what DDS saw.
    `topic echo` and `topic pub` share it."""

    def __init__(self, node: RosNode, graph: RosGraph, topic: str, type_name: str) -> None:
        self.node, self.graph, self.topic, self.type_name = node, graph, topic, type_name
        self.endpoint: OwnEndpoint | None = None
        self._next_look = 0.0
        self._status_since: float | None = None  # when DDS first said "another type"

    def watch(self, endpoint: OwnEndpoint) -> None:
        self.endpoint = endpoint

    def check(self) -> None:
        """Raises WireError when the topic has an endpoint of another type."""
        now = time.monotonic()
        self._next_look = now + TYPE_CHECK_PERIOD
        self.graph.refresh()
        problem = type_conflict(self.node.store, self.node.name,
                                self.graph.topic_endpoints(self.topic), self.topic,
                                self.type_name)
        if problem is not None:
            raise WireError(problem)
        if self._status_since is None:
            if self._dds_saw_other_type():
                self._status_since = now
        elif now - self._status_since >= OTHER_TYPE_PATIENCE:
            raise WireError(self._unnamed_conflict())

    def check_when_due(self) -> None:
        """`check` when its period is over, or at once when DDS just reported a conflict."""
        news = self._status_since is None and self._dds_saw_other_type()
        if news or time.monotonic() >= self._next_look:
            self.check()

    def _dds_saw_other_type(self) -> bool:
        return self.endpoint is not None and self.endpoint.other_type_events > 0

    def _unnamed_conflict(self) -> str:
        name = normalize_name(self.type_name)
        ours = self.node.store.hash_of(name) if self.node.store.distro != "humble" else ""
        return (f"type mismatch: {self.topic} has an endpoint of another type than the "
                f"{name} ({_short_hash(ours)}) you asked for, in name or definition (DDS "
                "reports it; the ROS graph cannot say which: no type hash to compare)")
