"""Red team 23: a key file the bridge trusts, or a private key it holds, owned by another
user. The mode checks (red team 22) judged only what the mode lets group and others do;
a file's owner may rewrite it (or chmod it first) and read it whatever its mode says, so
`mallory`'s 0644 JWKS let mallory put her own key in later and mint OWNER tokens, and her
0600 audit key was hers to read (and forge entries with). ssh's StrictModes asks the
same: owned by the user or root. Root is needed to make a file someone else's."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.config.test_config_check import TLS, TOKEN, check, config_text
from tests.config.test_redteam22_keys import (
    JWKS,
    JWT_PEM,
    SIGNER,
    _bridge_refuses,
    _trusted_files,
    _write_audit_key,
)

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="only root can give a file away")

NOBODY = 65534


@pytest.fixture(autouse=True)
def token(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RCAN_CHECK_TOKEN", TOKEN)


@pytest.mark.parametrize(("name", "api_extra", "said"), [
    ("keys.json", JWKS, "bridge.api.jwt: cannot load JWKS"),
    ("key.pem", JWT_PEM, "bridge.api.jwt: cannot load"),
    ("ops.pub", SIGNER, "kid 'k1': cannot read"),
    ("tls/clients.pem", TLS, "bridge.api.tls.client_ca:"),
    ("tls/server.key", TLS, "bridge.api.tls.key:"),
    ("audit.key", "", "bridge.audit.key_path:"),
])
def test_a_key_file_owned_by_another_user_is_refused(
        name: str, api_extra: str, said: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Before: config check ok and `run` served with it (each mode as red team 22 asks)."""
    _trusted_files(tmp_path)
    _write_audit_key(tmp_path / "audit.key", 0o600)
    text = config_text("127.0.0.1", api_extra)
    assert check(tmp_path, text) == 0  # the modes are right
    os.chown(tmp_path / name, NOBODY, NOBODY)
    assert check(tmp_path, text) == 1
    err = capsys.readouterr().err
    assert said in err and f"is owned by uid {NOBODY}" in err, err
    assert f"is owned by uid {NOBODY}" in _bridge_refuses(tmp_path)
    os.chown(tmp_path / name, 0, 0)  # root's own is fine (the bridge's user's, too)
    assert check(tmp_path, text) == 0


# -- the directory a key file is in ----------------------------------------------------------


@pytest.mark.parametrize(("name", "api_extra", "said"), [
    ("keys/keys.json", JWKS.replace("keys.json", "keys/keys.json"), "bridge.api.jwt:"),
    ("keys/ops.pub", SIGNER.replace("ops.pub", "keys/ops.pub"), "kid 'k1':"),
    ("keys/clients.pem", TLS.replace("tls/clients.pem", "keys/clients.pem"),
     "bridge.api.tls.client_ca:"),
    ("keys/server.key", TLS.replace("tls/server.key", "keys/server.key"),
     "bridge.api.tls.key:"),
])
@pytest.mark.parametrize("directory_mode", [0o775, 0o777])
def test_a_key_file_in_a_directory_others_may_write_is_refused(
        name: str, api_extra: str, said: str, directory_mode: int, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Red team 22 refused a trusted key file its group may write; one in a directory its
    group may write passed, and whoever may write the directory replaces the file (a new
    file, their key in it, renamed over the old): /etc/rcan 0775 root:robots let any member
    of robots mint OWNER tokens. ssh's StrictModes judges the directories too."""
    _trusted_files(tmp_path)
    (tmp_path / "keys").mkdir()
    tls_file = "clients" in name or "server" in name
    os.replace(tmp_path / "tls" / Path(name).name if tls_file
               else tmp_path / Path(name).name, tmp_path / name)
    text = config_text("127.0.0.1", api_extra)
    assert check(tmp_path, text) == 0
    (tmp_path / "keys").chmod(directory_mode)
    assert check(tmp_path, text) == 1
    err = capsys.readouterr().err
    assert said in err and f"{tmp_path / 'keys'} may be written by others" in err, err
    assert "may be written by others" in _bridge_refuses(tmp_path)
    (tmp_path / "keys").chmod(directory_mode | 0o1000)  # sticky: others cannot replace it
    assert check(tmp_path, text) == 0
