"""`rcan-rtps run` reads its config, then lets PyYAML and the config loader go (issue 14)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = """
import argparse, sys
from rcan_rtps.cli import run_cmd
args = argparse.Namespace(config=sys.argv[1], sim=False)
config = run_cmd._read_config(args, {"T": "t" * 32})
assert config.bridge.ros2.namespace == "/released", config
left = sorted(n for n in sys.modules if n.split(".")[0] == "yaml" or n.startswith(
    ("rcan_rtps.config._load", "rcan_rtps.config._schema")))
assert not left, left
import rcan_rtps.config
again = rcan_rtps.config.load_config(sys.argv[1], env={"T": "t" * 32})  # a later read works
assert again == config
print("ok")
"""


def test_run_reads_its_config_then_releases_the_loader(tmp_path: Path) -> None:
    path = tmp_path / "c.rcan.yaml"
    path.write_text("robot: {ruri: rcan://registry.local/a/b/device-0001}\n"
                    "bridge:\n  ros2: {namespace: /released}\n"
                    "  api: {principals: [{name: p, role: USER, token_env: T}]}\n"
                    "  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}\n")
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(path)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
