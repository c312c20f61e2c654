"""A peer flooding discovery: participants with thousands of writers each, made and deleted
round after round, faster than the graph reads their discovery samples (red team 32).

A refresh took every waiting sample, and went on taking while they kept coming: on the
caller's event loop, for as long as the flood lasted (11 s for two such peers), so the bridge
(whose commander watch refreshes the graph every poll) answered nothing meanwhile, an e-stop
included. A refresh now takes so much at a time (`REFRESH_TAKE`) and says it is behind.
The flood is two processes of plain cyclonedds (discovery_flood.py), each bounded in rounds
so that a refresh that chases it ends with it: "returned while the flood ran" is the outcome
checked, never a time.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from oracle.client import OracleEnv
from waiting import take

from rcan_rtps.ros.graph import RosGraph
from rcan_rtps.ros.participant import RosNode

from .bridge_rig import VIEWER, Rig, bridge_config, close_rig, make_rig

FLOODER = Path(__file__).with_name("discovery_flood.py")
FLOODERS = 2
ROUNDS, WRITERS = 20, 2000  # per flooder thread: a round is ~4,000 discovery samples
TWIST = "geometry_msgs/msg/Twist"


@contextlib.contextmanager
def flooding(domain_id: int) -> Iterator[list[subprocess.Popen[str]]]:
    """The flooders, each past its first round; stopped (stdin closed) on the way out."""
    flooders = [subprocess.Popen([sys.executable, str(FLOODER), str(domain_id), str(ROUNDS),
                                  str(WRITERS)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                 text=True) for _ in range(FLOODERS)]
    try:
        for flooder in flooders:
            assert flooder.stdout is not None and flooder.stdout.readline() == "flooding\n"
        yield flooders
    finally:
        for flooder in flooders:
            assert flooder.stdin is not None
            flooder.stdin.close()
            flooder.wait(60)


def still_flooding(flooders: list[subprocess.Popen[str]]) -> bool:
    return all(flooder.poll() is None for flooder in flooders)


@pytest.fixture
async def victim(domain_id: int) -> AsyncIterator[RosNode]:
    with RosNode("victim", "/", domain_id=domain_id) as node:
        yield node


async def test_a_refresh_returns_while_a_discovery_flood_lasts(
        victim: RosNode, domain_id: int) -> None:
    graph = RosGraph(victim)
    graph.refresh()
    with flooding(domain_id) as flooders:
        caught_up = [graph.refresh() for _ in range(5)]
        assert still_flooding(flooders), "a refresh chased the flood until it ended"
    assert not all(caught_up)  # the flood outran the refreshes: it was behind, and said so
    graph.close()


@pytest.fixture
async def rig(tmp_path: Path, jazzy_oracle: OracleEnv, domain_id: int) -> AsyncIterator[Rig]:
    r = await make_rig(bridge_config(tmp_path, domain_id), jazzy_oracle, domain_id,
                       watch_s=0.2)
    yield r
    await close_rig(r)


async def test_an_estop_is_answered_and_stops_while_a_discovery_flood_lasts(rig: Rig) -> None:
    """The commander watch refreshes the bridge's graph on its event loop: behind the flood it
    held the loop until the flood ended, and the e-stop waited for it."""
    await rig.oracle.acall("subscribe", topic="/robot1/cmd_vel", type=TWIST)
    assert await rig.oracle.acall("wait_matched", topic="/robot1/cmd_vel") >= 1
    with flooding(rig.node.domain_id) as flooders:
        assert rig.commanders is not None
        rig.commanders.poll()  # the watch is behind the flood from here on
        estop = await rig.command(VIEWER, {"action": "estop"})
        assert estop.http_status == 200 and rig.governor.latch.latched
        await take(rig.oracle, "/robot1/cmd_vel",
                   until=lambda got: any(t["linear"]["x"] == 0.0 for t in got))
        assert still_flooding(flooders), "the e-stop waited for the flood to end"
