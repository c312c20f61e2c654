"""Signed messages: each principal's trusted keys and policy, applied to what it sends.

A configured principal may list the public keys it signs RCAN 3.x COMMANDs with
(`api.principals[].signatures.keys`, each with its `kid`) and a policy:

- `off` (a principal without `signatures`; JWT principals and single-token mode's `default`
  too): a `sig` is recorded in the audit entry as unverified, never checked;
- `verify` (the default once `signatures` is given): a message that carries a `sig` must
  verify with one of the principal's keys; an unsigned one passes as it would under `off`;
- `required`: every command must carry a `sig` that verifies, and its governance fields
  (`confidence`, `ai`) must be inside the signed `params`, not beside them.

A signature that fails is refused whatever the policy says beyond `off`: a bad value, an
algorithm not spoken, a kid nobody holds, a kid bound to another principal (a key is its
principal's alone). Stops are not refused for any of this: the intake turns every refusal into
a warning on a stop (a request that says stop, stops).

A review of a held command (§9, `check_review`) is held to the same policy when it approves:
an approval releases motion, so under `required` it must come signed (an AUTHORIZE in the SDK's
signed envelope, `rcan._invoke`) — a bearer token alone, stolen or not, releases nothing. A
denial or a withdrawal only keeps the robot from moving: it passes unsigned under every
policy, and is refused only for a signature that is given and fails.

Checked when the message arrives, before the replay window records its id: a message refused
for its signature does not use up its `msg_id`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import msgspec

from rcan_rtps.config import ApiConfig, SignaturePolicy, SignerKey
from rcan_rtps.rcan import Envelope, ErrorCode, Outcome
from rcan_rtps.rcan._signatures import (
    ALGORITHMS,
    SIGNATURE_BYTES,
    Algorithm,
    KeyLoadError,
    PublicKey,
    load_inline_key,
    load_public_key,
    signature_value,
    verifies,
)

from ._durable import read_trusted
from .errors import AuthConfigError
from .outcomes import Rejection

SIGNATURE_STATUS = 403
# An ML-DSA-65 public key is 1952 bytes (PEM: ~2.7 KB): a file far larger holds no key.
MAX_KEY_FILE_BYTES = 64 * 1024


class TrustedKey(msgspec.Struct, frozen=True):
    kid: str
    alg: Algorithm
    key: PublicKey


class Signer(msgspec.Struct, frozen=True):
    """One principal's policy and the keys it signs with, by kid."""

    policy: SignaturePolicy
    keys: Mapping[str, TrustedKey]


OFF = Signer("off", {})


def _invalid(reason: str) -> Rejection:
    return Rejection(SIGNATURE_STATUS, Outcome.DENIED, ErrorCode.SIGNATURE_INVALID, reason)


def _required(reason: str) -> Rejection:
    return Rejection(SIGNATURE_STATUS, Outcome.DENIED, ErrorCode.SIGNATURE_REQUIRED, reason)


UNSIGNED = _required("unsigned")


class Signatures:
    """Every principal's `Signer`; a principal not named here is `off`."""

    def __init__(self, signers: Mapping[str, Signer]) -> None:
        self._signers = dict(signers)
        self._owners: dict[str, str] = {}
        for name, signer in self._signers.items():
            for kid in signer.keys:
                other = self._owners.setdefault(kid, name)
                if other != name:
                    raise AuthConfigError(f"kid {kid!r} is bound to two principals "
                                          f"({other}, {name})")

    @classmethod
    def from_config(cls, api: ApiConfig) -> Signatures:
        """The configured principals' keys, loaded; raises AuthConfigError naming the key."""
        signers = {}
        for principal in api.principals:
            config = principal.signatures
            if config is not None:
                keys = {k.kid: _trusted(principal.name, k) for k in config.keys}
                signers[principal.name] = Signer(config.policy, keys)
        return cls(signers)

    def policy(self, principal: str) -> SignaturePolicy:
        return self._signers.get(principal, OFF).policy

    def check(self, principal: str, envelope: Envelope | None
              ) -> tuple[Rejection | None, Envelope | None]:
        """Why `principal`'s message with `envelope` (None: a 1.2 form) is refused, or None;
        and the envelope, marked verified when its signature was checked and holds."""
        signer = self._signers.get(principal, OFF)
        sig = None if envelope is None else envelope.sig
        if envelope is None or sig is None:
            return (UNSIGNED if signer.policy == "required" else None), envelope
        if signer.policy == "off":
            return None, envelope
        refusal = self._refusal(principal, signer, envelope)
        if refusal is not None:
            return refusal, envelope
        verified = msgspec.structs.replace(envelope, verified=True)
        if signer.policy == "required" and envelope.unsigned_fields:
            loose = "_".join(envelope.unsigned_fields)
            return _required(f"{loose}_outside_signed_params"), verified
        return None, verified

    def check_review(self, principal: str, approving: bool, envelope: Envelope | None
                     ) -> tuple[Rejection | None, Envelope | None]:
        """`check` for a review of a held command: `envelope` is its AUTHORIZE's (None: a
        review without a message, POST /api/hitl/*). An approval is held to the policy; a
        denial or withdrawal (the fail-safe direction) needs no signature, but one it gives
        must hold."""
        if not approving and (envelope is None or envelope.sig is None):
            return None, envelope
        return self.check(principal, envelope)

    def _refusal(self, principal: str, signer: Signer, envelope: Envelope) -> Rejection | None:
        sig = envelope.sig
        assert sig is not None
        if sig.alg not in ALGORITHMS:
            return _invalid("unsupported_alg")
        trusted = signer.keys.get(sig.kid)
        if trusted is None:
            owner = self._owners.get(sig.kid)
            return _invalid("unknown_kid" if owner is None else "kid_of_another_principal")
        if trusted.alg != sig.alg:
            return _invalid("alg_mismatch")
        raw = signature_value(sig.value)
        if raw is None or len(raw) != SIGNATURE_BYTES[trusted.alg] or envelope.signed is None:
            return _invalid("malformed_signature")
        if not verifies(trusted.key, envelope.signed, raw):
            return _invalid("bad_signature")
        return None


def _trusted(principal: str, key: SignerKey) -> TrustedKey:
    where = f"api.principals[{principal}].signatures kid {key.kid!r}"
    try:
        if key.public_key is not None:
            loaded = load_inline_key(key.alg, key.public_key)
        else:
            path = key.public_key_file or ""
            try:
                # (read_small: a FIFO there held the start for a writer that never came)
                data = read_trusted(Path(path), MAX_KEY_FILE_BYTES)
            except OSError as exc:
                raise AuthConfigError(f"{where}: cannot read {path}: {exc.strerror}") from None
            except ValueError as exc:
                raise AuthConfigError(f"{where}: cannot read {path}: {exc}") from None
            loaded = load_public_key(key.alg, data)
    except KeyLoadError as exc:
        raise AuthConfigError(f"{where}: the public key {exc}") from None
    return TrustedKey(key.kid, key.alg, loaded)
