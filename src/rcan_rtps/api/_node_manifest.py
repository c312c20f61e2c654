"""GET /.well-known/rcan-node.json: the node manifest (rcan-spec §17.3), public, no credential.

§17 defines the manifest for registry nodes; a robot's bridge is none of its four node types.
It announces itself as a `resolver` — the one type that claims no namespace authority and
originates no records — so the SDK's parsers (`rcan.node.NodeClient.get_node_manifest`,
`verify_node`, `rcan.validate.validate_node`) take it, and adds what a client of this robot
needs: its RURI, the RCAN versions spoken and the bridge's public keys. Everything comes from
the config, the audit key and `SPOKEN`; nothing is secret (no path, no principal).

- `public_key` (`ed25519:<base64>`), `public_key_fingerprint`, `ed25519_public_key` (RCAN 2.3,
  base64url) and `kid`: the audit signing key (`governance.keyfacts`); `keys` lists every key
  with its use (today the one that signs audit entries, tree heads and audit exports).
- `api_base`: this API's base URL as the request reached it — the scheme of the connection and
  the local address and port of its socket (never the client's Host header: a public document
  a cache may keep must not echo what a client wrote). Behind a proxy it names the bridge's
  own socket.
- `operator`: `robot.operator`, else the RURI's manufacturer segment. `namespace_prefix` is
  `RRN` (the bridge holds no delegated prefix).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

import msgspec
from aiohttp import web
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from rcan_rtps.config import RcanConfig
from rcan_rtps.governance.keyfacts import KeyFacts
from rcan_rtps.rcan import SPOKEN, parse_ruri

PATH = "/.well-known/rcan-node.json"
NODE_VERSION = "1.0"  # rcan_node_version of rcan-spec's schemas/rcan-node.schema.json
SAFETY_MANIFEST = "/api/safety/manifest"
AUDIT_EXPORT = "/api/v1/audit"


def newest_version(versions: tuple[str, ...]) -> str:
    return max(versions, key=lambda v: tuple(int(p) for p in v.split(".")))


def manifest_body(config: RcanConfig, audit_key: Ed25519PublicKey) -> dict[str, Any]:
    """The manifest without `api_base` (which depends on the connection)."""
    ruri = parse_ruri(config.robot.ruri)
    key = KeyFacts(audit_key)
    return {
        "rcan_node_version": NODE_VERSION,
        "node_type": "resolver",
        "operator": config.robot.operator or ruri.manufacturer,
        "namespace_prefix": "RRN",
        "public_key": key.public_key,
        "public_key_fingerprint": key.fingerprint,
        "ed25519_public_key": key.raw_b64url,
        "kid": key.kid,
        "keys": [{"kid": key.kid, "alg": "Ed25519", "use": "audit",
                  "public_key": key.public_key}],
        "rcan_version": newest_version(SPOKEN),
        "spec_version": newest_version(SPOKEN),
        "rcan_versions": list(SPOKEN),
        "ruri": config.robot.ruri,
        **({"robot_name": config.robot.name} if config.robot.name else {}),
        "safety_manifest": SAFETY_MANIFEST,
        "audit_export": AUDIT_EXPORT,
    }


def api_base(request: web.Request) -> str | None:
    """`scheme://local-address:port/api` of the connection this request came on."""
    transport = request.transport
    sockname = None if transport is None else transport.get_extra_info("sockname")
    if not isinstance(sockname, tuple) or len(sockname) < 2:
        return None
    host, port = str(sockname[0]), int(sockname[1])
    if ":" in host:
        host = f"[{host}]"
    scheme = "https" if request.secure else "http"
    return f"{scheme}://{host}:{port}/api"


def handler(config: RcanConfig, audit_key: Ed25519PublicKey
            ) -> Callable[[web.Request], Awaitable[web.Response]]:
    body = manifest_body(config, audit_key)

    async def get_node_manifest(request: web.Request) -> web.Response:
        manifest = {**body, "api_base": api_base(request)}
        return web.Response(body=msgspec.json.encode(manifest), content_type="application/json",
                            headers={"Cache-Control": "no-cache"})

    return get_node_manifest
