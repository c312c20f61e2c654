"""Every stop stops the arm on a busy robot computer: the simulator (`rcan-rtps sim`, a
process of its own: its arm follows the trajectory, its joint_states at 10 Hz) and the
bridge, with the CPU saturated by a load generator (cpu_load.py). Each round sends a long
elbow trajectory, stops it while the elbow moves (a stop, an e-stop, or the agent's MCP call
cancelled: its own stop), and reads the sim's joint_states: the elbow must come to rest near
where it was stopped and stay there.

Losses are counted over all rounds and printed: a stop that failed (an arm not held: its
joint_states older than MAX_AGE_S under load), an elbow still moving after the stop, or one
held far from where it was."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from waiting import eventually

from .bridge_rig import AGENT, OPS, Rig, bridge_config, close_rig, make_rig

ROUNDS = int(os.environ.get("ARM_LOAD_ROUNDS", "20"))
SPEED = 0.2  # rad/s: 4 rad in 20 s


@pytest.fixture
def sim_process(domain_id: int) -> Iterator[subprocess.Popen[str]]:
    proc = subprocess.Popen([sys.executable, "-m", "rcan_rtps", "sim", "--domain-id",
                             str(domain_id)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and "ready" in proc.stdout.readline()
        yield proc
    finally:
        proc.terminate()
        proc.wait(timeout=20)


@pytest.fixture
async def rig(tmp_path: Path, jazzy_python: Path, domain_id: int,
              sim_process: subprocess.Popen[str]) -> AsyncIterator[Rig]:
    r = await make_rig(bridge_config(tmp_path, domain_id), jazzy_python, domain_id)
    yield r
    await close_rig(r)


def elbow(rig: Rig) -> tuple[float, float] | None:
    joints = rig.telemetry.status(pending_auth=0).telemetry.joints
    if joints is None or not joints.velocities:
        return None
    named = dict(zip(joints.names, zip(joints.positions, joints.velocities, strict=True),
                     strict=True))
    return named.get("elbow")


async def _beat(rig: Rig) -> None:
    while True:
        rig.governor.heartbeat(AGENT)
        await asyncio.sleep(0.2)


@pytest.mark.slow
async def test_arm_stops_under_cpu_load(rig: Rig, cpu_load: None) -> None:
    beating = asyncio.create_task(_beat(rig))
    failed: list[str] = []
    moving_after: list[tuple[float, float]] = []
    far: list[tuple[float, float]] = []
    try:
        await eventually(lambda: elbow(rig) is not None, timeout=30, what="the sim's joints")
        for i in range(ROUNDS):
            action = ("stop", "estop", "cancelled")[i % 3]
            target = 4.0 if i % 4 < 2 else -4.0
            sent = await rig.command(AGENT, {"action": "arm_joint", "params": {
                "joints": ["elbow"], "positions": [target], "duration_s": 20.0}})
            assert sent.http_status == 200, sent
            await eventually(lambda: abs((elbow(rig) or (0.0, 0.0))[1]) > 0.1, timeout=20,
                             what="the elbow moving")
            await asyncio.sleep(0.3 + 0.1 * (i % 5))
            at = elbow(rig)
            assert at is not None
            if action == "cancelled":  # an MCP client cancelled a motion call of the agent's
                own = await rig.governor.command_cancelled(AGENT)
                held = (own.applied or {}).get("arms_held") if own else None
                if not held:
                    failed.append(f"{action}: {own}")
            else:
                stopped = await rig.command(AGENT, {"action": action})
                if stopped.http_status != 200:
                    failed.append(f"{action}: {stopped.reason}")
            try:
                await eventually(lambda: (elbow(rig) or (0.0, 1.0))[1] == 0.0, timeout=5,
                                 what="the elbow at rest")
            except AssertionError:
                moving_after.append(at)
                continue
            rest = elbow(rig)
            assert rest is not None
            await asyncio.sleep(1.0)
            later = elbow(rig)
            assert later is not None
            if later[0] != rest[0]:
                moving_after.append((rest[0], later[0]))
            elif abs(rest[0] - at[0]) > 0.5:  # 0.2 rad/s for up to the stop's latency
                far.append((at[0], rest[0]))
            if action == "estop":
                cleared = await rig.command(OPS, {"action": "clear_estop"})
                assert cleared.http_status == 200, cleared
            # back to the middle, unmeasured, so the next round has room
            home = await rig.command(AGENT, {"action": "arm_joint", "params": {
                "joints": ["elbow"], "positions": [0.0], "duration_s": 0.5}})
            assert home.http_status == 200, home
            await eventually(lambda: (elbow(rig) or (1.0, 1.0)) == (0.0, 0.0), timeout=10)
    finally:
        beating.cancel()
    print(f"\nARM LOAD rounds={ROUNDS} failed={len(failed)} {failed} "
          f"moving_after={moving_after} far={far}")
    assert not (failed or moving_after or far)
