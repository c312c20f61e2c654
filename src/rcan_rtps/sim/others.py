"""Another robot on the simulated robot's topics: warned of once, at its start.

Two robots publishing one odometry topic (a second `rcan-rtps sim` or `run --sim` on the same
domain and namespace, or a real robot there) both obey the same `cmd_vel`, and whoever reads
`odom` sees it jump between them. The sim does not refuse to start (a user may mean it, e.g.
to test a bridge against two bases); it says so, once, naming the other participant.

The look is a task of its own on the sim's node: the graph is read once discovery has had its
moment (`RosGraph.settle`), then let go of. It holds nothing the robot's loop, its e-stop or a
command waits for, and a stop cancels it wherever it is.
"""

from __future__ import annotations

import logging

from .._printable import shown
from ..ros.graph import Endpoint, RosGraph, node_fqn, short_gid
from ..ros.participant import RosNode

log = logging.getLogger(__name__)

SETTLE_S = 1.5  # discovery's moment before the graph is read (as the CLI's --spin-time)
_UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"


async def warn_of_other_robots(node: RosNode, odom_topic: str = "odom") -> list[str]:
    """After discovery settled: one warning naming each other participant that publishes
    this robot's odometry (`odom_topic`, resolved on `node`); else an INFO line that none
    does. What it named (for tests). A look that fails is logged, never raised: the robot
    runs on without it."""
    topic = node.resolve(odom_topic)
    try:
        graph = RosGraph(node)
        try:
            await graph.settle(SETTLE_S)
            others = describe_other_publishers(graph.publishers_on({topic}),
                                               node.participant.guid.bytes)
        finally:
            # Its readers go now: nobody reads them after this look, and left to the
            # collector they outlived it (frozen by `run`'s gc.freeze()), keeping every
            # peer that came and went since.
            graph.close()
    except Exception as exc:  # DDS refused a builtin reader, the node closed meanwhile, …
        log.warning("could not look for another robot publishing %s: %s", topic, exc)
        return []
    if not others:
        log.info("no other robot publishes %s on ROS domain %d", topic, node.domain_id)
        return []
    log.warning("another robot on ROS domain %d already publishes %s: %s. Both take the "
                "same velocity commands and whoever reads %s sees odometry jump between "
                "them; stop one, or run this one on another domain (--domain-id) or "
                "namespace", node.domain_id, topic, "; ".join(others), topic)
    return others


def describe_other_publishers(endpoints: list[Endpoint], own: bytes) -> list[str]:
    """Each participant but `own` among these publishers, once: its node(s) and its GUID
    prefix and vendor (a node may be unnamed: ros_discovery_info not read, or none sent)."""
    nodes: dict[bytes, list[str]] = {}
    vendors: dict[bytes, str] = {}
    for e in endpoints:
        if e.participant_gid == own:
            continue
        named = nodes.setdefault(e.participant_gid, [])
        vendors[e.participant_gid] = e.vendor
        if e.node_name != _UNKNOWN_NODE:
            fqn = shown(node_fqn(e.node_namespace, e.node_name))  # a peer's words
            if fqn not in named:
                named.append(fqn)
    return [f"node {', '.join(named) or 'unnamed'} (participant "
            f"{short_gid(participant[:12])}, {vendors[participant]})"
            for participant, named in nodes.items()]
