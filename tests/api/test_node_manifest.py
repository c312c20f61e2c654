"""GET /.well-known/rcan-node.json (issue 24, item 7): rcan-spec §17.3's node manifest, public,
with the robot's RURI, the versions spoken and the bridge's public key; the official SDK's
own client parses it (`rcan.node.NodeClient`) and, over TLS, its `verify_node` accepts it."""

from __future__ import annotations

import asyncio
import base64
import hashlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from rcan.node import NodeClient

from rcan_rtps.api import ApiServer, server_ssl_context
from rcan_rtps.api._node_manifest import manifest_body
from rcan_rtps.config import loads_config
from rcan_rtps.governance import load_public_key
from rcan_rtps.rcan import SPOKEN
from tests.api.apihelpers import RURI, Api
from tests.api.test_tls import Pki

PATH = "/.well-known/rcan-node.json"


def _key_of(manifest: dict[str, object]) -> Ed25519PublicKey:
    text = str(manifest["public_key"])
    assert text.startswith("ed25519:")
    return Ed25519PublicKey.from_public_bytes(base64.b64decode(text.removeprefix("ed25519:")))


async def test_the_manifest_names_the_robot_and_the_audit_key(api: Api, tmp_path: Path) -> None:
    status, manifest = await api.call("GET", PATH)
    assert status == 200
    assert (manifest["ruri"], manifest["robot_name"]) == (RURI, "Husky A200")
    assert manifest["rcan_versions"] == list(SPOKEN) and manifest["rcan_version"] == "3.2"
    assert (manifest["node_type"], manifest["namespace_prefix"]) == ("resolver", "RRN")
    assert manifest["operator"] == "clearpath"  # the RURI's manufacturer, by default
    # the audit key: what `audit verify` reads beside the log, in each of the spec's spellings
    pub = load_public_key(tmp_path / "audit.jsonl.pub").public_bytes_raw()
    assert _key_of(manifest).public_bytes_raw() == pub
    assert manifest["ed25519_public_key"] == base64.urlsafe_b64encode(pub).rstrip(b"=").decode()
    assert manifest["public_key_fingerprint"] == "sha256:" + hashlib.sha256(pub).hexdigest()
    assert manifest["kid"] == hashlib.sha256(pub).hexdigest()[:8]  # the SDK's key_id rule
    assert manifest["keys"] == [{"kid": manifest["kid"], "alg": "Ed25519", "use": "audit",
                                 "public_key": manifest["public_key"]}]
    # it verifies what the log signs
    status, decision = await api.command("planner", {"action": "stop"})
    entry = api.entry(decision["audit_id"])
    _key_of(manifest).verify(base64.b64decode(entry["sig"]), entry["audit_id"].encode())
    host, port = api.http.server.host, api.http.server.port
    assert manifest["api_base"] == f"http://{host}:{port}/api"
    assert (manifest["safety_manifest"], manifest["audit_export"]) == (
        "/api/safety/manifest", "/api/v1/audit")


def test_the_operator_comes_from_the_config() -> None:
    text = (f'robot: {{ruri: "{RURI}", operator: Acme Fleet}}\n'
            "bridge: {api: {auth_token_env: T}, safety: {max_linear_vel: 1, max_angular_vel: 1}}")
    config = loads_config(text, env={"T": "x" * 32})
    key = Ed25519PrivateKey.generate().public_key()
    assert manifest_body(config, key)["operator"] == "Acme Fleet"


@pytest.fixture
async def tls_url(tmp_path: Path) -> AsyncIterator[tuple[str, Pki]]:
    (tmp_path / "pki").mkdir()
    pki = Pki(tmp_path / "pki")
    api = Api(tmp_path, api_extra=f"tls: {{cert: {pki.server_cert}, key: {pki.server_key}}}")
    app = await api.build()
    tls = api.config.bridge.api.tls
    assert tls is not None
    async with ApiServer(app, host="127.0.0.1", port=0,
                         ssl_context=server_ssl_context(tls)) as server:
        yield server.url, pki
    await api.close()


async def test_the_sdk_parses_and_verifies_it_over_tls(
        tls_url: tuple[str, Pki], monkeypatch: pytest.MonkeyPatch) -> None:
    url, pki = tls_url
    monkeypatch.setenv("SSL_CERT_FILE", str(pki.ca_path))  # urllib's default context trusts it
    manifest = await asyncio.to_thread(NodeClient(timeout=10).get_node_manifest, url)
    assert manifest["api_base"] == url + "/api"
    assert NodeClient().verify_node(manifest)  # the SDK's own well-formedness rules
    assert manifest["ruri"] == RURI


async def test_api_base_is_the_connections_never_the_host_header(api: Api) -> None:
    """A client that pins the manifest's `api_base` must not be sent where a Host (or a
    forwarded host) header of someone else's request said."""
    spoofed = {"Host": "evil.example:443", "X-Forwarded-Host": "evil.example",
               "X-Forwarded-Proto": "https", "Forwarded": "host=evil.example;proto=https"}
    status, manifest = await api.call("GET", PATH, headers=spoofed)
    assert status == 200
    host, port = api.http.server.host, api.http.server.port
    assert manifest["api_base"] == f"http://{host}:{port}/api"

