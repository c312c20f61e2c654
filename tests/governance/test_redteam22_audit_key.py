"""Red team 22: the audit signing key replaced, and a JWK not meant for verifying. A start
with another key is refused (key rotation is not supported), and now says so, instead of
blaming a torn tail or an edit; a key replaced on disk while the log is open changes nothing
until the next start."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import public_jwk

from rcan_rtps.governance import AuthConfigError
from rcan_rtps.governance.audit import (
    AuditLog,
    checkpoint_path,
    load_private_key,
    public_key_pem_of,
    verify,
)
from rcan_rtps.governance.errors import AuditIntegrityError
from rcan_rtps.governance.jwt import load_jwks
from rcan_rtps.governance.treehead import public_key_path
from tests.governance.test_audit import record

REPLACED = "the signing key is not the one a.jsonl.pub holds: a replaced key_path?"


async def _a_log_of(path: Path, key: Path, entries: int) -> None:
    log = await AuditLog.open(path, key)
    for i in range(entries):
        await log.append(record(i))
    await log.close()


async def test_a_start_with_another_key_says_the_key_was_replaced(tmp_path: Path) -> None:
    log, key = tmp_path / "a.jsonl", tmp_path / "a.key"
    await _a_log_of(log, key, 3)
    os.replace(key, tmp_path / "old.key")  # key_path now names no key: a new one is made
    with pytest.raises(AuditIntegrityError) as info:
        await AuditLog.open(log, key)
    assert REPLACED in str(info.value)
    assert "key rotation is not supported" in str(info.value)
    assert str(info.value).endswith("; refusing to start")
    os.replace(tmp_path / "old.key", key)  # the log's key back: it starts
    await (await AuditLog.open(log, key)).close()


async def test_a_damaged_log_with_its_own_key_is_not_blamed_on_the_key(tmp_path: Path) -> None:
    log, key = tmp_path / "a.jsonl", tmp_path / "a.key"
    await _a_log_of(log, key, 3)
    lines = log.read_bytes().splitlines(keepends=True)
    log.write_bytes(b"".join([lines[0], lines[1].replace(b"m1", b"m9"), *lines[2:]]))
    checkpoint_path(log).unlink()  # (else the start verifies only what follows it)
    with pytest.raises(AuditIntegrityError) as info:
        await AuditLog.open(log, key)
    assert "signing key" not in str(info.value)


async def test_a_key_replaced_while_the_log_is_open_signs_nothing_until_a_restart(
        tmp_path: Path) -> None:
    """Held as designed: the key is read once, at open. Entries written after the file was
    replaced are still signed by the key the log was opened with, and verify with its `.pub`."""
    path, key = tmp_path / "a.jsonl", tmp_path / "a.key"
    log = await AuditLog.open(path, key)
    await log.append(record(0))
    original = load_private_key(key).public_key()
    key.unlink()
    await (await AuditLog.open(tmp_path / "other.jsonl", key)).close()  # a new key there
    assert load_private_key(key).public_key() != original
    await log.append(record(1))
    await log.close()
    assert public_key_path(path).read_bytes() == public_key_pem_of(original)
    assert verify(path, original).last_seq == 2


# -- a JWK meant for something else than verifying tokens ------------------------------------


@pytest.mark.parametrize("key_ops", ['["encrypt"]', '["sign"]', '[]', '"verify"'])
def test_a_jwk_whose_key_ops_leave_out_verify_is_refused(key_ops: str, tmp_path: Path) -> None:
    """RFC 7517 §4.3: `key_ops` lists what a key is for. Before: a key marked for encrypting
    only (or an empty list) checked tokens all the same; `use: enc` was already refused."""
    x = public_jwk(Ed25519PrivateKey.generate(), "a")["x"]
    path = tmp_path / "jwks.json"
    jwk = f'{{"kty": "OKP", "crv": "Ed25519", "x": "{x}", "kid": "a", "key_ops": {key_ops}}}'
    path.write_text(f'{{"keys": [{jwk}]}}')
    with pytest.raises(AuthConfigError, match=r"not a key for verifying \(`key_ops`"):
        load_jwks(str(path))


@pytest.mark.parametrize("extra", ['"key_ops": ["verify"]', '"key_ops": ["verify", "sign"]',
                                   '"x5t": "whatever"', '"alg": "EdDSA", "use": "sig"'])
def test_a_jwk_for_verifying_with_other_members_loads(extra: str, tmp_path: Path) -> None:
    x = public_jwk(Ed25519PrivateKey.generate(), "a")["x"]
    path = tmp_path / "jwks.json"
    jwk = f'{{"kty": "OKP", "crv": "Ed25519", "x": "{x}", "kid": "a", {extra}}}'
    path.write_text(f'{{"keys": [{jwk}]}}')
    assert list(load_jwks(str(path))) == ["a"]
