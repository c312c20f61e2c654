"""Signed RCAN 3.x COMMANDs: the bytes a signature covers, public keys, and verification.

The official SDK (`rcan.signing.sign_message`) signs, with ML-DSA-65 (FIPS 204, the
algorithm the 3.2 freeze names), the JSON of six fields of the COMMAND — `rcan` (the
version), `msg_id`, `timestamp`, `cmd`, `target` and `params` — with sorted keys, no
whitespace, and Python `json`'s spelling (ASCII escapes, floats by repr), and writes
`sig: {alg: "ml-dsa-65", kid, value}` with the signature in URL-safe base64. The bridge makes
those bytes again from what arrived and verifies them with `cryptography`; Ed25519 over the same
bytes (`alg` "ed25519") is this bridge's extension, for signers without ML-DSA.

Everything outside the six fields (`confidence`, `ai`, `firmware_hash`, …) is not covered:
`governance.signatures` decides what a policy makes of that.
"""

from __future__ import annotations

import base64
import binascii
import json
import re
from typing import TYPE_CHECKING, Any, Final, Literal, TypeAlias

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from ._errors import RcanError

if TYPE_CHECKING:
    # Imported where an ML-DSA key is loaded: a run whose principals have none never pays
    # for the module (idle memory, issue 27).
    from cryptography.hazmat.primitives.asymmetric.mldsa import MLDSA65PublicKey

Algorithm = Literal["ml-dsa-65", "ed25519"]
ALGORITHMS: Final[tuple[Algorithm, ...]] = ("ml-dsa-65", "ed25519")
PublicKey: TypeAlias = "MLDSA65PublicKey | Ed25519PublicKey"
# Raw sizes (FIPS 204 table 2; RFC 8032): a key or signature of another length is not one.
KEY_BYTES: Final[dict[Algorithm, int]] = {"ml-dsa-65": 1952, "ed25519": 32}
SIGNATURE_BYTES: Final[dict[Algorithm, int]] = {"ml-dsa-65": 3309, "ed25519": 64}
_B64URL = re.compile(r"^[A-Za-z0-9_-]*={0,2}$")
_B64 = re.compile(r"^[A-Za-z0-9+/_-]*={0,2}$")


class KeyLoadError(RcanError, ValueError):
    """A configured public key that is not a key of its algorithm."""


def signed_bytes(obj: dict[str, Any]) -> bytes:
    """The bytes `rcan.signing` signs for a COMMAND, made again from the decoded body: the JSON
    of rcan (else rcan_version, which the SDK keeps equal to it), msg_id, timestamp, cmd,
    target and params, sorted keys, separators without blanks, ASCII escapes."""
    payload = {
        "rcan": obj.get("rcan", obj.get("rcan_version")),
        "msg_id": obj.get("msg_id"),
        "timestamp": obj.get("timestamp"),
        "cmd": obj.get("cmd"),
        "target": obj.get("target"),
        "params": obj.get("params", {}),
    }
    return json.dumps(payload, sort_keys=True, separators=(",", ":")).encode("ascii")


def signature_value(text: str) -> bytes | None:
    """A `sig.value`: URL-safe base64 as the SDK writes it, padded or not; None unless it is
    the one canonical spelling of its bytes (no stray characters, no unused bits set), so
    that no two values name one signature."""
    if not _B64URL.fullmatch(text):
        return None
    bare = text.rstrip("=")
    if len(bare) % 4 == 1 or (text != bare and len(text) % 4 != 0):
        return None
    try:
        raw = base64.urlsafe_b64decode(bare + "=" * (-len(bare) % 4))
    except (binascii.Error, ValueError):
        return None
    if base64.urlsafe_b64encode(raw).decode("ascii").rstrip("=") != bare:
        return None
    return raw


def verifies(key: PublicKey, message: bytes, signature: bytes) -> bool:
    """Whether `signature` is `key`'s over exactly `message` (ML-DSA: the empty context, as
    the SDK signs)."""
    try:
        key.verify(signature, message)
    except InvalidSignature:
        return False
    return True


def algorithm_of(key: PublicKey) -> Algorithm:
    return "ed25519" if isinstance(key, Ed25519PublicKey) else "ml-dsa-65"


def load_public_key(alg: Algorithm, data: bytes) -> PublicKey:
    """A public key of `alg` from its raw bytes (what `MLDSAKeyPair.save_public` writes) or a
    PEM/DER SubjectPublicKeyInfo. Raises KeyLoadError."""
    if len(data) == KEY_BYTES[alg]:
        return _from_raw(alg, data)
    from cryptography.hazmat.primitives import serialization  # key files only: not for a run
    from cryptography.hazmat.primitives.asymmetric.mldsa import MLDSA65PublicKey

    try:
        if data.lstrip().startswith(b"-----BEGIN"):
            key = serialization.load_pem_public_key(data)
        else:
            key = serialization.load_der_public_key(data)
    except (ValueError, UnsupportedAlgorithm):
        raise KeyLoadError(f"is neither the {KEY_BYTES[alg]} raw bytes of an {alg} public "
                           f"key nor a PEM/DER SubjectPublicKeyInfo ({len(data)} bytes)"
                           ) from None
    if not isinstance(key, (MLDSA65PublicKey, Ed25519PublicKey)) or algorithm_of(key) != alg:
        raise KeyLoadError(f"holds a {type(key).__name__}, not an {alg} public key")
    return key


def load_inline_key(alg: Algorithm, text: str) -> PublicKey:
    """A public key written in config as base64 (standard or URL-safe) of its raw bytes."""
    compact = "".join(text.split())
    if not _B64.fullmatch(compact):
        raise KeyLoadError("is not base64")
    try:
        raw = base64.urlsafe_b64decode(compact.replace("+", "-").replace("/", "_")
                                       + "=" * (-len(compact) % 4))
    except (binascii.Error, ValueError) as exc:
        raise KeyLoadError(f"is not base64 ({exc})") from None
    if len(raw) != KEY_BYTES[alg]:
        raise KeyLoadError(f"is {len(raw)} bytes; an {alg} public key is {KEY_BYTES[alg]}")
    return _from_raw(alg, raw)


def _from_raw(alg: Algorithm, raw: bytes) -> PublicKey:
    try:
        if alg == "ml-dsa-65":
            from cryptography.hazmat.primitives.asymmetric.mldsa import MLDSA65PublicKey

            return MLDSA65PublicKey.from_public_bytes(raw)
        return Ed25519PublicKey.from_public_bytes(raw)
    except UnsupportedAlgorithm as exc:  # an OpenSSL before 3.5 under cryptography
        raise KeyLoadError(f"{alg} is not available here: {exc}") from None
    except ValueError as exc:
        raise KeyLoadError(f"is not an {alg} public key ({exc})") from None
