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
