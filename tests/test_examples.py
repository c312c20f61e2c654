"""The shipped example configs are valid (as `rcan-rtps config check` sees them), and none of
them holds a credential anyone knows or serves one in clear."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from rcan_rtps.config import load_config
from rcan_rtps.config._model import is_loopback

ROOT = Path(__file__).resolve().parents[1]
TOKENS = {name: "x" * 32 for name in ("RCAN_BRIDGE_TOKEN", "RCAN_OPS_TOKEN", "RCAN_AGENT_TOKEN",
                                      "RCAN_DASHBOARD_TOKEN", "RCAN_VIEWER_TOKEN")}
SHIPPED = sorted([*ROOT.glob("examples/*.rcan.yaml"), *ROOT.glob("config/*.rcan.yaml")])


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_example_config_loads(path: Path) -> None:
    config = load_config(path, env=TOKENS)
    assert config.bridge.safety.max_linear_vel > 0


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_no_shipped_config_holds_a_token(path: Path) -> None:
    """A token_sha256 in a shipped file is a credential every copy of it shares (and whoever
    can invert it, e.g. sha256("test"), holds): tokens come from each robot's environment."""
    text = path.read_text()
    assert not re.search(r"\b[0-9a-fA-F]{64}\b", text), "a SHA-256 digest in a shipped config"
    api = yaml.safe_load(text)["bridge"]["api"]
    for principal in api.get("principals", []):
        assert set(principal) & {"token_env", "token_sha256"} == {"token_env"}, principal


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_no_shipped_config_serves_plain_http_on_a_network(path: Path) -> None:
    api = load_config(path, env=TOKENS).bridge.api
    assert not api.allow_plaintext
    assert is_loopback(api.host) or api.tls is not None, api.host
