"""Red team 22: key files. `config check` and `run` judge every key file alike (the audit
signing key was checked by `run` only), none of them can hold a start for good (a FIFO at a
key's path did), and a TLS private key others may read or write is refused."""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from rcan_rtps.bridge.runtime import Bridge, BridgeOptions
from rcan_rtps.config import load_config
from tests.config.test_config_check import TLS, TOKEN, check, config_text, write_tls


@pytest.fixture(autouse=True)
def token(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RCAN_CHECK_TOKEN", TOKEN)


def _bridge_refuses(tmp_path: Path) -> str:
    """What `run` says, before anything joins the domain, of the config `check` wrote."""
    config = load_config(tmp_path / "robot.rcan.yaml", env={})
    bridge = Bridge(config, BridgeOptions(port=0, mdns=False, env={"RCAN_CHECK_TOKEN": TOKEN}))
    with pytest.raises(Exception) as info:  # each file has its own error type
        bridge.prepare()
    return str(info.value)


def _write_audit_key(path: Path, mode: int) -> None:
    path.write_bytes(Ed25519PrivateKey.generate().private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption()))
    path.chmod(mode)


# -- the audit signing key: `config check` and `run` agree -----------------------------------


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o602])
def test_an_audit_key_open_to_others_fails_the_check_as_it_fails_run(
        mode: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Before: `config check` said ok, and `run` then refused the same file."""
    text = config_text("127.0.0.1")
    _write_audit_key(tmp_path / "audit.key", mode)
    assert check(tmp_path, text) == 1
    err = capsys.readouterr().err
    assert f"bridge.audit.key_path: audit key {tmp_path / 'audit.key'} is open to others" in err
    assert f"(mode {mode:o})" in err and "Traceback" not in err
    assert "is open to others" in _bridge_refuses(tmp_path)
    assert check(tmp_path, text, "--file-only") == 0  # this machine's file, not the config's


@pytest.mark.parametrize("content", [b"", b"-----BEGIN PRIVATE KEY-----\nMC4CAQ",
                                     b"not a key\n"])
def test_an_audit_key_that_does_not_load_fails_the_check_as_it_fails_run(
        content: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "audit.key").write_bytes(content)
    (tmp_path / "audit.key").chmod(0o600)
    assert check(tmp_path, config_text("127.0.0.1")) == 1
    assert "bridge.audit.key_path: cannot load audit key" in capsys.readouterr().err
    assert "cannot load audit key" in _bridge_refuses(tmp_path)


def test_an_audit_key_of_the_right_mode_or_none_at_all_passes(tmp_path: Path) -> None:
    assert check(tmp_path, config_text("127.0.0.1")) == 0  # none: `run` makes one
    assert not (tmp_path / "audit.key").exists()  # and the check did not
    _write_audit_key(tmp_path / "audit.key", 0o600)
    assert check(tmp_path, config_text("127.0.0.1")) == 0


def test_a_dangling_link_at_the_audit_key_fails_the_check(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`run` cannot make a key there (the link's name is taken) nor read one."""
    (tmp_path / "audit.key").symlink_to(tmp_path / "nowhere.key")
    assert check(tmp_path, config_text("127.0.0.1")) == 1
    assert "bridge.audit.key_path: cannot read audit key" in capsys.readouterr().err
    assert "cannot read audit key" in _bridge_refuses(tmp_path)


# -- a FIFO where a key file should be: refused, never waited on ------------------------------


def _unblocked(fifo: Path, call: Callable[[], object]) -> tuple[bool, list[object]]:
    """`call`'s result, and whether it was stuck on the FIFO (then let go: a writer end opened
    and closed gives its reader end-of-file, so that a failing test ends)."""
    results: list[object] = []
    thread = threading.Thread(target=lambda: results.append(call()), daemon=True)
    thread.start()
    thread.join(30)  # a guard against hanging the suite, not a measurement
    stuck = thread.is_alive()
    while thread.is_alive():
        with contextlib.suppress(OSError):  # no reader yet
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(1)
    return stuck, results


JWKS = "jwt: {jwks: keys.json, audience: rcan-bridge}"
JWT_PEM = "jwt: {public_key: key.pem, audience: rcan-bridge}"
SIGNER = ("principals: [{name: ops, role: OWNER, token_env: RCAN_CHECK_TOKEN, "
          "signatures: {keys: [{kid: k1, alg: ed25519, public_key_file: ops.pub}]}}]")


@pytest.mark.parametrize(("fifo_name", "api_extra", "said"), [
    ("audit.key", "", "bridge.audit.key_path: cannot read audit key"),
    ("keys.json", JWKS, "bridge.api.jwt: cannot load JWKS"),
    ("key.pem", JWT_PEM, "bridge.api.jwt: cannot load"),
    ("ops.pub", SIGNER, "kid 'k1': cannot read"),
    ("tls/server.key", TLS, "bridge.api.tls.key:"),
    ("tls/server.pem", TLS, "bridge.api.tls.cert:"),
    ("tls/clients.pem", TLS, "bridge.api.tls.client_ca:"),
])
def test_a_fifo_at_a_key_files_path_is_refused_not_waited_on(
        fifo_name: str, api_extra: str, said: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Before: `config check` (and `run`, before its API was up) waited on the FIFO for a
    writer that never came: no error, no exit."""
    (tmp_path / "tls").mkdir()
    write_tls(tmp_path / "tls")
    fifo = tmp_path / fifo_name
    fifo.unlink(missing_ok=True)
    os.mkfifo(fifo, 0o600)
    text = config_text("127.0.0.1", api_extra)
    stuck, results = _unblocked(fifo, lambda: check(tmp_path, text))
    assert not stuck
    assert results == [1]
    err = capsys.readouterr().err
    assert said in err and "not a regular file" in err, err
    stuck, results = _unblocked(fifo, lambda: _bridge_refuses(tmp_path))
    assert not stuck
    assert "not a regular file" in str(results[0])


# -- the TLS private key ----------------------------------------------------------------------


@pytest.mark.parametrize("mode", [0o644, 0o604, 0o660, 0o666])
def test_a_tls_key_others_may_read_or_write_is_refused(
        mode: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Who reads it may pose as the bridge and collect every bearer token sent to it; who
    writes it, swap it. Before: served with it."""
    (tmp_path / "tls").mkdir()
    paths = write_tls(tmp_path / "tls")
    paths["key"].chmod(mode)
    assert check(tmp_path, config_text("0.0.0.0", TLS)) == 1
    err = capsys.readouterr().err
    assert f"bridge.api.tls.key: {paths['key']} is open to others (mode {mode:o})" in err
    assert "is open to others" in _bridge_refuses(tmp_path)


@pytest.mark.parametrize("mode", [0o600, 0o640, 0o400])
def test_a_tls_key_of_its_owner_or_its_group_passes(mode: int, tmp_path: Path) -> None:
    """0640: a group such as Debian's ssl-cert reading it is the convention."""
    (tmp_path / "tls").mkdir()
    write_tls(tmp_path / "tls")["key"].chmod(mode)
    assert check(tmp_path, config_text("0.0.0.0", TLS)) == 0


# -- keys the bridge trusts credentials by, in files others may write ---------------------------


@pytest.mark.parametrize(("name", "api_extra", "said"), [
    ("keys.json", JWKS, "bridge.api.jwt: cannot load JWKS"),
    ("key.pem", JWT_PEM, "bridge.api.jwt: cannot load"),
    ("ops.pub", SIGNER, "kid 'k1': cannot read"),
    ("tls/clients.pem", TLS, "bridge.api.tls.client_ca:"),
])
@pytest.mark.parametrize("mode", [0o666, 0o646, 0o664])
def test_a_trusted_key_file_others_may_write_is_refused(
        name: str, api_extra: str, said: str, mode: int, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Whoever writes a JWT issuer's key set puts their own key in and mints OWNER tokens;
    a principal's signing key, signs as it; a client CA, names any principal by certificate.
    Before: loaded whatever the mode (ssh refuses such an authorized_keys)."""
    _trusted_files(tmp_path)
    (tmp_path / name).chmod(mode)
    text = config_text("127.0.0.1", api_extra)
    assert check(tmp_path, text) == 1
    err = capsys.readouterr().err
    assert said in err and f"may be written by others (mode {mode:o})" in err, err
    assert "may be written by others" in _bridge_refuses(tmp_path)
    (tmp_path / name).chmod(0o644)
    assert check(tmp_path, text) == 0


def _trusted_files(directory: Path) -> None:
    """A JWKS, a JWT PEM, a signer's key and TLS files, each 0644 (the TLS key 0600)."""
    from jwthelpers import write_jwks

    issuer = Ed25519PrivateKey.generate()
    write_jwks(directory / "keys.json", {"k1": issuer})
    pem = issuer.public_key().public_bytes(serialization.Encoding.PEM,
                                           serialization.PublicFormat.SubjectPublicKeyInfo)
    (directory / "key.pem").write_bytes(pem)
    (directory / "ops.pub").write_bytes(pem)
    (directory / "tls").mkdir()
    write_tls(directory / "tls")
    for name in ("keys.json", "key.pem", "ops.pub", "tls/clients.pem", "tls/server.pem"):
        (directory / name).chmod(0o644)
