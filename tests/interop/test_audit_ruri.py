"""Every audit entry a real `rcan-rtps run` writes names the robot it governs (§6 `ruri`).

The runtime opened the log without the robot's RURI, so every entry said `"ruri": null`; the
unit tests opened it with one themselves and could not see that. This test goes through the
real process (run inside `scripts/netns`)."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
from pathlib import Path

from rcan_rtps.bridge.demo import DEMO_YAML

from .run_process import RunProcess, child_env, post, state_args

DEMO_RURI = DEMO_YAML.split("ruri: ", 1)[1].split("\n", 1)[0]


async def _commands(proc: RunProcess) -> list[int]:
    """A decision of each kind: executed, refused, e-stop, clear, a stream's end."""
    bodies = [
        (proc.user, {"action": "move", "params": {"linear_x": 0.2, "duration_s": 0.5}}),
        (proc.user, {"action": "move", "params": {"linear_x": 9.0}}),  # over the limit
        (proc.user, {"action": "clear_estop"}),  # a USER may not
        (proc.user, {"action": "estop"}),
        (proc.owner, {"action": "clear_estop"}),
        (proc.user, {"action": "stop"}),
    ]
    return [(await post(proc.url, token, body))[0] for token, body in bodies]


def test_every_entry_of_a_real_run_carries_the_robots_ruri(tmp_path: Path,
                                                           domain_id: int) -> None:
    assert DEMO_RURI.startswith("rcan://")
    proc = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                       *state_args(tmp_path, "state")], child_env(domain_id), demo=True)
    try:
        statuses = asyncio.run(_commands(proc))
        proc.signal(signal.SIGTERM)
        assert proc.wait(60) == 0, proc.output()
    finally:
        proc.kill()
    assert statuses == [200, 409, 403, 200, 200, 200], proc.output()
    log = tmp_path / "state" / "audit.jsonl"
    entries = [json.loads(line) for line in log.read_text().splitlines()]
    events = {e["event"] for e in entries}
    assert {"BRIDGE_STARTED", "COMMAND_DISPATCHED", "COMMAND_REJECTED", "ESTOP",
            "ESTOP_CLEARED", "STREAM_ENDED", "BRIDGE_STOPPED"} <= events, events
    assert [e["seq"] for e in entries if e.get("ruri") != DEMO_RURI] == []
    verified = subprocess.run([sys.executable, "-m", "rcan_rtps", "audit", "verify", str(log)],
                              capture_output=True, text=True, timeout=120)
    assert verified.returncode == 0, verified.stdout + verified.stderr
