"""The shipped example configs are valid (as `rcan-rtps config check` sees them)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rcan_rtps.config import load_config

ROOT = Path(__file__).resolve().parents[1]
TOKENS = {name: "x" * 32 for name in ("RCAN_BRIDGE_TOKEN", "RCAN_OPS_TOKEN", "RCAN_AGENT_TOKEN",
                                      "RCAN_DASHBOARD_TOKEN", "RCAN_VIEWER_TOKEN")}


@pytest.mark.parametrize("path", sorted([*ROOT.glob("examples/*.rcan.yaml"),
                                         *ROOT.glob("config/*.rcan.yaml")]),
                         ids=lambda p: p.name)
def test_example_config_loads(path: Path) -> None:
    config = load_config(path, env=TOKENS)
    assert config.bridge.safety.max_linear_vel > 0
