"""How the bridge names its public keys to others (node manifest, audit export, P66).

- `kid`: the first 8 hex digits of SHA-256 over the raw public key, the rule the rcan SDK
  uses for its own key ids (`rcan.signing`, `key_id`), so a client keeps one convention;
- `public_key`: `ed25519:<base64>` (rcan-spec §17.3, node_pubkey / public_key);
- `fingerprint`: `sha256:<hex>` of the raw key (§17's `public_key_fingerprint`);
- `raw_b64url`: unpadded base64url of the raw key (RCAN 2.3's `ed25519_public_key`, RFC 8037's
  `x` of a JWK).
"""

from __future__ import annotations

import base64
import hashlib
import os
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from ._durable import read_small, read_trusted

MAX_PEM_BYTES = 64 * 1024  # a public key's PEM is a few hundred bytes


class KeyFacts:
    """The public names of one Ed25519 public key."""

    __slots__ = ("fingerprint", "kid", "public_key", "raw_b64url")

    def __init__(self, key: Ed25519PublicKey) -> None:
        raw = key.public_bytes_raw()
        digest = hashlib.sha256(raw).hexdigest()
        self.kid = digest[:8]
        self.fingerprint = "sha256:" + digest
        self.public_key = "ed25519:" + base64.b64encode(raw).decode()
        self.raw_b64url = base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


def signature_text(signature: bytes) -> str:
    """`ed25519:<base64>`, as rcan-spec writes Ed25519 signatures (§17, §20 headers)."""
    return "ed25519:" + base64.b64encode(signature).decode()


def read_public_pem(path: str | os.PathLike[str], *, trusted: bool = False) -> Ed25519PublicKey:
    """The Ed25519 public key in a PEM file; a ValueError says what is wrong with it (callers
    raise it as their own configuration error, naming what the key is for). `trusted`: a key
    the bridge accepts credentials by (a JWT issuer's), refused if others may write the file;
    a key a verifier was handed (`audit verify --pubkey`) is the reader's business."""
    from cryptography.hazmat.primitives import serialization  # verifiers only, not a run

    read = read_trusted if trusted else read_small
    try:
        # (read_small: a FIFO there would hold the reader for ever)
        key = serialization.load_pem_public_key(read(Path(path), MAX_PEM_BYTES))
    except (OSError, ValueError) as exc:
        raise ValueError(f"cannot load {path}: {exc}") from exc
    if not isinstance(key, Ed25519PublicKey):
        raise ValueError(f"{path} is not an Ed25519 public key")
    return key
