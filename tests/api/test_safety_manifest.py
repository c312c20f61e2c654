"""GET /api/safety/manifest (issue 24, item 7): the Protocol-66 safety manifest, derived from
the config, the action registry, the e-stop latch and the audit log — change the config and
the manifest follows; latch the e-stop and it says so."""

from __future__ import annotations

import json
from pathlib import Path

from rcan_rtps.governance.timesync import clock_status
from rcan_rtps.rcan.actions import specs
from tests.api.apihelpers import Api

PATH = "/api/safety/manifest"
P66 = {"local_safety_wins", "safety_messages_bypass_queues", "estop_requires_explicit_clear",
       "ai_cannot_override_safety", "audit_trail_complete"}


async def test_a_read_for_any_authenticated_principal(api: Api) -> None:
    assert (await api.call("GET", PATH))[0] == 401
    status, manifest = await api.call("GET", PATH, "viewer")
    assert status == 200
    assert (manifest["protocol"], manifest["rcan_version"]) == (66, "3.2")
    assert set(manifest["invariants"]) == P66 and all(manifest["invariants"].values())


async def test_limits_workspace_and_checks_come_from_config_and_registry(api: Api) -> None:
    _, manifest = await api.call("GET", PATH, "viewer")
    safety = api.config.bridge.safety
    assert manifest["envelope"] == {"max_linear_speed_mps": 1.0, "max_angular_speed_radps": 0.5}
    assert manifest["limits"]["max_linear_vel"] == safety.max_linear_vel
    assert manifest["limits"]["session_timeout_s"] == 60
    assert manifest["limits"]["max_move_duration_s"] == safety.max_move_duration_s
    assert "estop_state_path" not in manifest["limits"]  # no path goes out
    assert "workspace" not in manifest["limits"]
    assert manifest["workspace"] == {"frame_id": "map", "polygon": [
        [-10, -10], [10, -10], [10, 10], [-10, 10]]}
    assert manifest["checks"] == {s.name: [i.value for i in s.invariants] for s in specs()}
    assert "/" not in json.dumps(manifest["audit"]).replace("/api/v1/audit", "")


async def test_the_config_changes_the_manifest(tmp_path: Path) -> None:
    api = await Api(tmp_path, bridge_extra="rbac: {action_roles: {clear_estop: CREATOR}}",
                    hitl_extra="").start()
    try:
        _, manifest = await api.call("GET", PATH, "viewer")
        assert manifest["estop"]["clear_role"] == "CREATOR"
    finally:
        await api.close()


async def test_estop_facts_follow_the_latch(api: Api) -> None:
    _, manifest = await api.call("GET", PATH, "viewer")
    assert manifest["estop"] == {"action": "estop", "topic": "/robot1/emergency_stop",
                                 "raise_role": "GUEST", "clear_action": "clear_estop",
                                 "clear_role": "OWNER", "survives_restart": True,
                                 "latched": False}
    assert (await api.command("viewer", {"action": "estop"}))[0] == 200
    _, manifest = await api.call("GET", PATH, "viewer")
    assert manifest["estop"]["latched"] is True


async def test_audit_facts_name_the_log_head_and_tree_head(api: Api, tmp_path: Path) -> None:
    await api.gov.start()
    api.clock.advance(5)
    assert (await api.command("planner", {"action": "stop"}))[0] == 200
    _, manifest = await api.call("GET", PATH, "viewer")
    last = api.entries[-1]
    assert manifest["audit_count"] == last["seq"] == len(api.entries)
    assert manifest["audit_last_event"] == last["timestamp_ms"] / 1000
    assert manifest["audit"]["chain_head"] == {"seq": last["seq"], "audit_id": last["audit_id"]}
    heads = (tmp_path / "audit.jsonl.sth").read_text().splitlines()
    assert manifest["audit"]["tree_head"] == json.loads(heads[-1])
    assert manifest["audit"]["tree_head"]["tree_size"] == last["seq"]
    assert manifest["audit_enabled"] is True and manifest["audit"]["healthy"] is True
    assert manifest["audit_retention_days"] is None  # the bridge never prunes its log


async def test_clock_fields_are_the_kernels(api: Api) -> None:
    _, manifest = await api.call("GET", PATH, "viewer")
    clock = clock_status()
    assert manifest["clock_synchronized"] == clock.synchronized
    assert manifest["clock_source"] == clock.source
    assert set(manifest) >= {"clock_drift_ms", "offline_mode", "min_loa_for_control",
                             "supported_transports", "federation_enabled"}
