"""The built-in demo: a config for `rcan-rtps run --sim`, with tokens made per run."""

from __future__ import annotations

import os
import secrets
from collections.abc import Mapping
from pathlib import Path

from ..config import RcanConfig, loads_config

USER_TOKEN_ENV = "RCAN_DEMO_USER_TOKEN"
OWNER_TOKEN_ENV = "RCAN_BRIDGE_TOKEN"
VIEWER_TOKEN_ENV = "RCAN_DEMO_VIEWER_TOKEN"

DEMO_YAML = """\
robot:
  ruri: rcan://registry.local/rcan-rtps/simbot/v1/sim-0001
  name: rcan-rtps simulated robot
bridge:
  type: ros2
  ros2:
    namespace: {namespace}
    node_name: rcan_bridge
    domain_id: {domain_id}
    distro: jazzy
    telemetry_rate_hz: 10
    cmd_rate_hz: 20
    nav_frame_id: map
    images: {{overhead: {{topic: camera/image_raw}}}}  # the sim's top-down camera
  hitl:
    timeout_seconds: 300
    confidence_gate: {{min_confidence: 0.5, on_fail: escalate}}
    gates:
      - {{action: arm_joint, require_auth: true, authorized_roles: [OWNER, CREATOR]}}
  api:
    host: 127.0.0.1
    port: {port}
    principals:
      - {{name: viewer, role: GUEST, token_env: {viewer}}}
      - {{name: operator, role: USER, token_env: {user}}}
      - {{name: owner, role: OWNER, token_env: {owner}}}
  safety:
    max_linear_vel: 1.0
    max_angular_vel: 1.5
    velocity_exceed_deny: true
    session_timeout_s: 5.0
    max_move_duration_s: 30
    max_linear_accel: 2.0
    max_angular_accel: 3.0
    workspace: [[-20, -20], [20, -20], [20, 20], [-20, 20]]
  audit:
    path: {state}/audit.jsonl
    key_path: {state}/audit-ed25519.key
  skills:  # what an RCAN INVOKE (§19) may run: a registry action, fixed and allowed params
    go_home: {{action: navigate, params: {{x: 0, y: 0, yaw: 0}}, description: back to the origin}}
    go_to: {{action: navigate, allow: [x, y, yaw], description: drive to a point}}
    nudge: {{action: move, params: {{linear_x: 0.3}}, allow: [duration_s]}}
    hold_still:  # moves nothing (it ends a running move): what `rcan-rtps conformance` invokes
      action: move
      params: {{linear_x: 0, angular_z: 0, duration_s: 0.5}}
      description: a zero velocity (it ends a running move)
    raise_elbow:  # held for an owner, as every arm_joint is here
      action: arm_joint
      params: {{joints: [elbow], positions: [0.8], duration_s: 1}}
"""


def default_state_dir() -> Path:
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "rcan-rtps" / "sim"


def demo_tokens(env: Mapping[str, str]) -> dict[str, str]:
    """Fresh tokens for the demo principals; RCAN_BRIDGE_TOKEN, when set, is the owner's."""
    return {name: env.get(name) or fresh_demo_token()
            for name in (VIEWER_TOKEN_ENV, USER_TOKEN_ENV, OWNER_TOKEN_ENV)}


def fresh_demo_token() -> str:
    """A random token to print for pasting: the prefix keeps it from beginning with `-`
    (1 in 64 url-safe tokens do, and `--token -x…` then reads as an option) and names it
    for secret scanners."""
    return "rcan_" + secrets.token_urlsafe(24)


def demo_yaml(*, state_dir: Path, port: int, domain_id: int, namespace: str) -> str:
    """The demo's config, as text: its principals' tokens read from the `*_TOKEN_ENV`
    variables."""
    return DEMO_YAML.format(namespace=namespace, domain_id=domain_id, port=port,
                            state=state_dir, viewer=VIEWER_TOKEN_ENV, user=USER_TOKEN_ENV,
                            owner=OWNER_TOKEN_ENV)


def demo_config(*, state_dir: Path, port: int, domain_id: int, namespace: str,
                env: Mapping[str, str]) -> RcanConfig:
    state_dir.mkdir(parents=True, exist_ok=True)
    text = demo_yaml(state_dir=state_dir, port=port, domain_id=domain_id, namespace=namespace)
    return loads_config(text, source="<built-in demo config>", env=env)
