"""GET /api/safety/manifest: the Protocol-66 safety manifest (rcan-spec docs/safety, P66 v1.6).

Read like STATUS (any authenticated principal). Every value is derived — from the config, the
action registry, the live e-stop latch and the audit log's files — never listed by hand, so
the manifest cannot say what the bridge does not do:

- `invariants`: P66's five, each computed from the registry's declarations (stopping actions
  are never gated and go in the e-stop lane; the e-stop signal is latched and only its clear
  action releases it; every motion action is guarded by the e-stop, AI commands included)
  and from the audit log's health; `checks`: the §8 checks each action goes through;
- `envelope` (P66's names) and `limits` (every `bridge.safety` value but paths and the
  workspace); `workspace`: the polygon and its frame, or null (no workspace check);
- `estop`: the action, the ROS topic its latched signal is published on, whether it is latched
  now, who may raise (any authenticated principal) and who may clear it;
- `audit_*` and `audit`: count, newest entry time, the chain head and the newest signed tree
  head, the signing key's id, the export route — no file path. A last line of the log (or of
  its tree heads) that is not one (edited or damaged on disk while the bridge runs) is shown,
  not raised: count and time null, `audit.problem` says so, and `audit_trail_complete` is
  false;
- clock fields (§8.4) from the kernel's clock discipline (`governance.timesync`).

Fields P66 has that the bridge cannot know are left out (`hardware_safety`: a bridge sees no
e-stop button nor watchdog MCU; `emergency_stop_distance`: it reads no proximity sensor).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import msgspec
from aiohttp import web

from rcan_rtps.config import RcanConfig
from rcan_rtps.governance import Governor
from rcan_rtps.governance.keyfacts import KeyFacts
from rcan_rtps.governance.rbac import RolePolicy
from rcan_rtps.governance.treehead import tree_head_path
from rcan_rtps.rcan import SPOKEN, ErrorCode
from rcan_rtps.rcan.actions import Effect, EstopSignal, Invariant, specs, with_effect

from ._bodies import ApiError, error_body, json_response
from ._errors import AuditUnreadable, ReadsBusy
from ._keys import GOVERNOR, READS
from ._node_manifest import AUDIT_EXPORT, newest_version
from ._reads import decoded, last_line

PATH = "/api/safety/manifest"
PROTOCOL = 66


class _Tail(msgspec.Struct):
    seq: int
    timestamp_ms: int


_TAIL = msgspec.json.Decoder(_Tail)
_TREE_HEAD = msgspec.json.Decoder(dict[str, Any])


class _Tails(msgspec.Struct, frozen=True):
    count: int | None  # the newest entry's seq; 0: an empty log; None: not readable
    last_event: float | None  # its time (Unix seconds)
    tree_head: dict[str, Any] | None
    problem: str | None  # what of the two files' last lines could not be read


def p66_invariants(audit_healthy: bool) -> dict[str, bool]:
    """P66's five invariants, each as the registry declares it (and the log's health)."""
    every = list(specs())
    estop = with_effect(Effect.ESTOP).ros
    clear = with_effect(Effect.CLEAR_ESTOP).ros
    return {
        # The bridge publishes commands and never disables a controller: its checks can only
        # add limits to what the robot's own safety allows, never lift one.
        "local_safety_wins": True,
        "safety_messages_bypass_queues": all(not s.hitl.gateable for s in every if s.stopping),
        "estop_requires_explicit_clear": (isinstance(estop, EstopSignal) and estop.engaged
                                          and estop.signal.latched
                                          and isinstance(clear, EstopSignal)
                                          and not clear.engaged),
        "ai_cannot_override_safety": all(Invariant.ESTOP_GUARD in s.invariants
                                         for s in every if s.motion),
        "audit_trail_complete": audit_healthy,
    }


def static_part(config: RcanConfig) -> dict[str, Any]:
    """What only the config and the registry decide (built once)."""
    bridge = config.bridge
    safety, ros2 = bridge.safety, bridge.ros2
    roles = RolePolicy.from_config(bridge.rbac)
    estop_spec, clear_spec = with_effect(Effect.ESTOP), with_effect(Effect.CLEAR_ESTOP)
    assert isinstance(estop_spec.ros, EstopSignal)
    limits = {k: v for k, v in msgspec.structs.asdict(safety).items()
              if k != "workspace" and not k.endswith("_path")}
    return {
        "protocol": PROTOCOL,
        "rcan_version": newest_version(SPOKEN),
        "ruri": config.robot.ruri,
        "checks": {s.name: [i.value for i in s.invariants] for s in specs()},
        "envelope": {"max_linear_speed_mps": safety.max_linear_vel,
                     "max_angular_speed_radps": safety.max_angular_vel},
        "limits": limits,
        "workspace": None if safety.workspace is None else {
            "frame_id": ros2.nav_frame_id, "polygon": [list(p) for p in safety.workspace]},
        "estop": {
            "action": estop_spec.name,
            "topic": ros2.resolve(getattr(ros2, estop_spec.ros.signal.topic_key)),
            "raise_role": roles.required(estop_spec.name).name,
            "clear_action": clear_spec.name,
            "clear_role": roles.required(clear_spec.name).name,
            "survives_restart": True,  # the latch file and the audit log (governance.estop)
        },
        "min_loa_for_control": 1,  # no LoA is asked of anyone (P66's default)
        "federation_enabled": False,
        "trusted_registries": [],
        "supported_transports": ["http"],
        "offline_mode": False,  # the bridge needs no registry to govern
        "offline_since_s": 0,
        "audit_enabled": True,
        "audit_retention_days": None,  # the bridge never prunes its log
    }


def _audit_tails(path: Path) -> _Tails:
    """The newest entry's seq and time, and the newest signed tree head (reader thread)."""
    entry, head = last_line(path), last_line(tree_head_path(path))
    problems: list[str] = []
    count: int | None = 0
    last_event: float | None = None
    tree_head: dict[str, Any] | None = None
    try:
        if entry is not None:
            tail = decoded(_TAIL, entry)
            count, last_event = tail.seq, tail.timestamp_ms / 1000.0
    except AuditUnreadable:
        count = None
        problems.append("the log's last line is not an audit entry")
    try:
        tree_head = None if head is None else decoded(_TREE_HEAD, head)
    except AuditUnreadable:
        problems.append("the last tree head is not one")
    problem = "; ".join(problems) + ": run `rcan-rtps audit verify`" if problems else None
    return _Tails(count, last_event, tree_head, problem)


async def live_part(app: web.Application, governor: Governor) -> dict[str, Any]:
    from rcan_rtps.governance.timesync import clock_status  # ctypes: only once asked

    audit = governor.audit
    tails: _Tails = await app[READS].get().read(_audit_tails, audit.path)
    clock, head = clock_status(), audit.head
    return {
        "invariants": p66_invariants(audit.healthy and tails.problem is None),
        "estop_latched": governor.latch.latched,
        "clock_synchronized": clock.synchronized,
        "clock_source": clock.source,
        "clock_drift_ms": clock.error_ms,
        "audit_count": tails.count,
        "audit_last_event": tails.last_event,
        "audit": {
            "format": "JSON lines, RCAN canonical JSON v1, SHA-256 hash chain, Ed25519 "
                      "signatures, RFC 6962 tree heads",
            "kid": KeyFacts(audit.public_key).kid,
            "healthy": audit.healthy,
            "chain_head": {"seq": head.last_seq, "audit_id": head.last_audit_id},
            "tree_head": tails.tree_head,
            "export": AUDIT_EXPORT,
            "problem": tails.problem,
        },
    }


async def manifest_reply(app: web.Application, fixed: dict[str, Any]
                         ) -> tuple[int, bytes | ApiError]:
    """The manifest now (`fixed`: its `static_part`), or 429 while the reader is busy."""
    try:
        live = await live_part(app, app[GOVERNOR])
    except ReadsBusy:
        return 429, error_body(ErrorCode.RATE_LIMITED, reason="reads_busy")
    estop = {**fixed["estop"], "latched": live.pop("estop_latched")}
    return 200, msgspec.json.encode({**fixed, **live, "estop": estop})


def handler(config: RcanConfig) -> Callable[[web.Request], Awaitable[web.Response]]:
    fixed = static_part(config)

    async def get_safety_manifest(request: web.Request) -> web.Response:
        status, body = await manifest_reply(request.app, fixed)
        if isinstance(body, bytes):
            return web.Response(body=body, content_type="application/json")
        return json_response(body, status, {"Retry-After": "1"})

    return get_safety_manifest
