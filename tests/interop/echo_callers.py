"""Processes calling one rclpy /echo server at the same moment (test_concurrent_clients.py,
test_rpc_identity.py): each caller script prints "ready" once matched, waits for "go" so that
all start together, makes its calls and prints a JSON tally as its last line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any


def run_callers(script: Path, processes: int, calls: int, domain_id: int, share: Path,
                timeout: float) -> list[dict[str, Any]]:
    """The tallies of `processes` copies of `script` (named p0, p1, ...), `calls` each."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    callers = [subprocess.Popen(
        [sys.executable, str(script), f"p{n}", str(calls), str(domain_id), str(share)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        for n in range(processes)]
    try:
        for caller in callers:  # all matched before anyone calls
            assert caller.stdout is not None and caller.stdout.readline().strip() == "ready"
        for caller in callers:
            assert caller.stdin is not None
            caller.stdin.write("go\n")
            caller.stdin.flush()
        return [json.loads(caller.communicate(timeout=timeout)[0].splitlines()[-1])
                for caller in callers]
    finally:
        for caller in callers:
            caller.kill()
