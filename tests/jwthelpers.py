"""EdDSA JWTs and JWKS files for the tests: what an identity provider would hand out."""

from __future__ import annotations

import base64
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey


def b64(raw: bytes) -> str:
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


def sign_jwt(key: Ed25519PrivateKey, claims: Mapping[str, Any],
             header: Mapping[str, Any] | None = None) -> str:
    head = b64(json.dumps(header or {"alg": "EdDSA", "typ": "JWT"}).encode())
    body = b64(json.dumps(claims).encode())
    sig = key.sign(f"{head}.{body}".encode())
    return f"{head}.{body}.{b64(sig)}"


def public_jwk(key: Ed25519PrivateKey, kid: str, **extra: Any) -> dict[str, Any]:
    raw = key.public_key().public_bytes(serialization.Encoding.Raw,
                                        serialization.PublicFormat.Raw)
    return {"kty": "OKP", "crv": "Ed25519", "x": b64(raw), "kid": kid, **extra}


def write_jwks(path: Path, keys: Mapping[str, Ed25519PrivateKey]) -> Path:
    """A JWKS file of the public halves of `keys`, by kid."""
    path.write_text(json.dumps({"keys": [public_jwk(k, kid) for kid, k in keys.items()]}))
    return path


LEEWAY_S = 30  # api.jwt.leeway_s's default: a token is taken this long after its exp
AUDIENCE = "rcan-bridge"


def jwt_issuer(folder: Path) -> tuple[Ed25519PrivateKey, str]:
    """A fresh signing key, its public half written in `folder`, and the `api:` config text
    (`jwt: {...}`) that trusts it for AUDIENCE."""
    key = Ed25519PrivateKey.generate()
    pem = key.public_key().public_bytes(serialization.Encoding.PEM,
                                        serialization.PublicFormat.SubjectPublicKeyInfo)
    (folder / "jwt.pem").write_bytes(pem)
    return key, f"jwt: {{public_key: '{folder / 'jwt.pem'}', audience: {AUDIENCE}}}"


def expiring_jwt(key: Ed25519PrivateKey, now_s: float, left_s: float, *, sub: str,
                 role: str) -> str:
    """A JWT for `sub` in `role` that the bridge takes for `left_s` more seconds from `now_s`
    (its exp, plus the leeway)."""
    claims = {"sub": sub, "role": role, "aud": AUDIENCE, "exp": now_s + left_s - LEEWAY_S}
    return sign_jwt(key, claims, {"alg": "EdDSA"})
