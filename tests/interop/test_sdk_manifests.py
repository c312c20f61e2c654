"""Issue 24, items 7 and 8, against a real `rcan-rtps run --sim` (a subprocess, as the README's
tour runs it), with the official `rcan` SDK as the oracle of the RCAN side: it fetches and
parses the node manifest (no credential), its SAFETY messages move the safety manifest's
latch, its `canonical_json` recomputes every exported audit id, the manifest's key verifies
the export's issuer signature; STATUS carries §20's names; an AI command without a model is
refused and audited."""

from __future__ import annotations

import asyncio
import base64
import csv
import hashlib
import io
import json
import time
from collections.abc import AsyncIterator, Sequence
from typing import Any

import aiohttp
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
from rcan.address import RobotURI
from rcan.encoding import canonical_json
from rcan.message import RCANMessage
from rcan.node import NodeClient
from rcan.safety import make_estop_message, make_resume_message

from rcan_rtps.governance import load_public_key
from tests.interop.test_demo import Demo, call, wait_status


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as client:
        yield client


def _mth(leaves: Sequence[bytes]) -> bytes:
    """RFC 6962 §2.1 Merkle Tree Hash over the entries' lines, written out here (not the
    bridge's code): leaves 0x00-prefixed, nodes 0x01-prefixed, split at the largest power of
    two below n."""
    if not leaves:
        return hashlib.sha256(b"").digest()
    if len(leaves) == 1:
        return hashlib.sha256(b"\x00" + leaves[0]).digest()
    k = 1
    while k * 2 < len(leaves):
        k *= 2
    return hashlib.sha256(b"\x01" + _mth(leaves[:k]) + _mth(leaves[k:])).digest()


def _public_key(manifest: dict[str, Any]) -> Ed25519PublicKey:
    raw = base64.b64decode(manifest["public_key"].removeprefix("ed25519:"))
    return Ed25519PublicKey.from_public_bytes(raw)


async def test_the_sdk_reads_the_node_manifest(sim: Demo,
                                               http: aiohttp.ClientSession) -> None:
    status = await wait_status(http, sim, lambda s: s["ros"]["connected"])
    # the SDK's own client: no credential, its own parser
    manifest = await asyncio.to_thread(NodeClient(timeout=10).get_node_manifest, sim.url)
    assert RobotURI.parse(manifest["ruri"]) == RobotURI.parse(status["ruri"])
    assert manifest["rcan_versions"] == ["1.2", "3.2"]
    pub = load_public_key(sim.audit.with_name("audit.jsonl.pub")).public_bytes_raw()
    assert _public_key(manifest).public_bytes_raw() == pub
    assert manifest["api_base"] == sim.url + "/api"
    # every rule of the SDK's verify_node holds but one: over plain HTTP, api_base is not
    # https (tests/api/test_node_manifest.py serves it over TLS, where verify_node passes)
    assert not NodeClient().verify_node(manifest)
    https = manifest["api_base"].replace("http://", "https://", 1)
    assert NodeClient().verify_node({**manifest, "api_base": https})


async def test_the_safety_manifest_follows_config_and_latch(sim: Demo,
                                                            http: aiohttp.ClientSession) -> None:
    status = await wait_status(http, sim, lambda s: s["ros"]["connected"])
    code, manifest = await call(http, sim, sim.user, "GET", "/api/safety/manifest")
    assert code == 200 and manifest["protocol"] == 66 and all(manifest["invariants"].values())
    assert manifest["envelope"] == {"max_linear_speed_mps": 1.0, "max_angular_speed_radps": 1.5}
    assert manifest["limits"]["max_linear_accel"] == 2.0  # the demo's config
    assert manifest["workspace"]["polygon"] == [[-20, -20], [20, -20], [20, 20], [-20, 20]]
    assert manifest["estop"]["topic"] == "/robot1/emergency_stop"
    assert (manifest["estop"]["latched"], manifest["estop"]["clear_role"]) == (False, "OWNER")
    robot = str(RobotURI.parse(status["ruri"]))
    code, _ = await call(http, sim, sim.user, "POST", "/api/command",
                         make_estop_message(robot, "drill"))
    assert code == 200
    _, manifest = await call(http, sim, sim.user, "GET", "/api/safety/manifest")
    assert manifest["estop"]["latched"] is True
    code, _ = await call(http, sim, sim.owner, "POST", "/api/command",
                         make_resume_message(robot, "go"))
    assert code == 200
    _, manifest = await call(http, sim, sim.user, "GET", "/api/safety/manifest")
    assert manifest["estop"]["latched"] is False
    assert manifest["audit_count"] == len(sim.audit.read_bytes().splitlines())


async def test_the_export_verifies_with_the_sdk_and_the_manifests_key(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    status = await wait_status(http, sim, lambda s: s["ros"]["connected"])
    robot = RobotURI.parse(status["ruri"])
    # an AI's COMMAND naming its model executes; without one it is refused, and audited
    ai_move = RCANMessage(cmd="move", target=robot, params={"linear_x": 0.2, "duration_s": 0.5},
                          confidence=0.9).to_dict()
    code, body = await call(http, sim, sim.user, "POST", "/api/command",
                            ai_move | {"ai": {"provider": "acme", "model": "planner-7b"}})
    assert (code, body["status"]) == (200, "ok"), body
    bare = RCANMessage(cmd="move", target=robot, params={"linear_x": 0.2}, confidence=0.9)
    code, body = await call(http, sim, sim.user, "POST", "/api/command", bare.to_dict())
    assert (code, body["error_code"], body["status"]) == (
        400, "AUDIT_INCOMPLETE_AI_IDENTITY", "blocked"), body
    refused = [json.loads(line) for line in sim.audit.read_bytes().splitlines()]
    assert any(e["event"] == "COMMAND_REJECTED" and e["message_id"] == bare.msg_id
               and e["deny_reason"] == "AUDIT_INCOMPLETE_AI_IDENTITY:ai_model_required"
               for e in refused)

    manifest = await asyncio.to_thread(NodeClient(timeout=10).get_node_manifest, sim.url)
    since = int(time.time()) - 600
    async with http.get(f"{sim.url}/api/v1/audit?from={since}",
                        headers={"Authorization": f"Bearer {sim.owner}"}) as resp:
        assert resp.status == 200
        root_header = resp.headers["X-Audit-Chain-Root"]
        sig_header = resp.headers["X-Audit-Issuer-Sig"]
        body_bytes = await resp.read()
    header, *lines = body_bytes.splitlines()
    assert json.loads(header)["count"] == len(lines) >= 3
    on_disk = sim.audit.read_bytes().splitlines()
    assert lines == on_disk[: len(lines)]  # verbatim, in order (the run may have gone on)
    root = _mth(lines)
    assert root_header == "sha256:" + root.hex()
    _public_key(manifest).verify(base64.b64decode(sig_header.removeprefix("ed25519:")), root)
    for line in lines:  # the SDK recomputes every id
        entry = json.loads(line)
        unsigned = {k: v for k, v in entry.items() if k not in ("audit_id", "sig")}
        assert entry["audit_id"] == "sha256:" + hashlib.sha256(
            canonical_json(unsigned)).hexdigest(), entry["seq"]
        _public_key(manifest).verify(base64.b64decode(entry["sig"]),
                                     entry["audit_id"].encode())
    async with http.get(f"{sim.url}/api/v1/audit?format=csv&to={since + 1200}",
                        headers={"Authorization": f"Bearer {sim.owner}"}) as resp:
        rows = list(csv.DictReader(io.StringIO(await resp.text())))
    assert [r["entry"].encode() for r in rows][: len(lines)] == lines
    code, body = await call(http, sim, sim.owner, "GET", "/api/v1/audit?from=soon")
    assert (code, body["error_code"], body["path"]) == (400, "SCHEMA_VALIDATION_FAILED",
                                                        "$.query.from")


async def test_status_carries_the_section_20_names(sim: Demo,
                                                   http: aiohttp.ClientSession) -> None:
    status = await wait_status(http, sim, lambda s: s["ros"]["connected"]
                               and s["battery_percent"] is not None
                               and s["position"] is not None, timeout=60)
    assert status["battery_percent"] == status["battery_pct"]
    assert isinstance(status["battery_percent"], float) and 0 <= status["battery_percent"] <= 100
    assert status["cpu_percent"] is None or 0.0 <= status["cpu_percent"] <= 100.0
    assert status["position"]["heading_rad"] == status["telemetry"]["yaw"]
    assert status["timestamp_us"] // 1000 == status["timestamp_ms"]
    again = await wait_status(http, sim, lambda s: s["cpu_percent"] is not None, timeout=60)
    assert again["seq"] > status["seq"] and again["uptime_ms"] >= status["uptime_ms"]
