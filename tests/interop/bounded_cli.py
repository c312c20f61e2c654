"""A CLI command in a process whose DDS domain bounds samples at `bound` bytes: its first node
(a holder made before the command's own) sets the bound all its nodes share
(test_sample_size_writes.py, test_cli_bag.py)."""

from __future__ import annotations

import os
import subprocess
import sys

_BOUNDED = ("import sys; from rcan_rtps.ros.participant import RosNode; "
            "holder = RosNode('holder', domain_id=int(sys.argv[1]), "
            "max_sample_bytes=int(sys.argv[2])); from rcan_rtps.cli.main import main; "
            "sys.exit(main(sys.argv[3:]))")


def run_bounded(bound: int, domain_id: int, *args: str,
                timeout: float = 90) -> subprocess.CompletedProcess[str]:
    """`rcan-rtps <args>` in such a process; its output captured."""
    return subprocess.run([sys.executable, "-c", _BOUNDED, str(domain_id), str(bound), *args],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)})


def error_line(stderr: str) -> str:
    """The CLI's one `rcan-rtps: ...` line (Cyclone may have written its own beside it)."""
    [line] = [line for line in stderr.splitlines() if line.startswith("rcan-rtps:")]
    return line
