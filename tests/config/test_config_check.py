"""`rcan-rtps config check` (and the loader under it) refuse what `run` must not serve: a
non-loopback API in plain HTTP unless `api.allow_plaintext`, and TLS or JWT key files that are
missing or do not load (those are this machine's: `--file-only` skips them, as it skips tokens)."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from cryptography.x509.oid import NameOID
from jwthelpers import write_jwks

from rcan_rtps.bridge.runtime import Bridge, BridgeOptions
from rcan_rtps.cli.main import main
from rcan_rtps.config import ConfigError, loads_config

TOKEN = "t" * 32
CONFIG = """\
robot: {ruri: rcan://registry.local/clearpath/husky/a200-0001}
bridge:
  api:
    host: "%(host)s"
    auth_token_env: RCAN_CHECK_TOKEN
    %(api_extra)s
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
  audit: {path: audit.jsonl, key_path: audit.key}
"""


def config_text(host: str, api_extra: str = "") -> str:
    return CONFIG % {"host": host, "api_extra": api_extra}


def check(tmp_path: Path, text: str, *flags: str) -> int:
    path = tmp_path / "robot.rcan.yaml"
    path.write_text(text)
    return main(["config", "check", *flags, str(path)])


@pytest.fixture(autouse=True)
def token(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RCAN_CHECK_TOKEN", TOKEN)


# -- plain HTTP beyond loopback -------------------------------------------------------------

NETWORK_HOSTS = ["0.0.0.0", "", "::", "192.168.1.20", "10.0.0.7", "fe80::1", "robot.local",
                 "localhost.example.com"]
LOOPBACK_HOSTS = ["127.0.0.1", "127.0.0.53", "::1", "[::1]", "localhost", "LOCALHOST"]


@pytest.mark.parametrize("host", NETWORK_HOSTS)
def test_a_network_api_without_tls_is_refused(host: str, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ConfigError) as info:
        loads_config(config_text(host), env={})
    [issue] = info.value.issues
    assert issue.path == "$.bridge.api" and "not loopback and there is no `tls`" in issue.message
    assert "allow_plaintext" in issue.message
    for flags in ((), ("--file-only",)):  # a file problem: whatever the machine
        assert check(tmp_path, config_text(host), *flags) == 1
        assert "bearer tokens would cross the network in clear" in capsys.readouterr().err


@pytest.mark.parametrize("host", LOOPBACK_HOSTS)
def test_a_loopback_api_needs_no_tls(host: str, tmp_path: Path) -> None:
    assert loads_config(config_text(host), env={}).bridge.api.host == host
    assert check(tmp_path, config_text(host)) == 0


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.20"])
def test_plaintext_on_a_network_when_explicitly_allowed(host: str, tmp_path: Path) -> None:
    config = loads_config(config_text(host, "allow_plaintext: true"), env={})
    assert config.bridge.api.allow_plaintext
    assert check(tmp_path, config_text(host, "allow_plaintext: true")) == 0


def test_run_host_cannot_point_a_loopback_config_at_the_network(tmp_path: Path) -> None:
    """`run --host 0.0.0.0` over a loopback config: refused before any port is bound."""
    config = loads_config(config_text("127.0.0.1").replace("audit.", f"{tmp_path}/audit."),
                          env={})
    bridge = Bridge(config, BridgeOptions(host="0.0.0.0", port=0, mdns=False,
                                          env={"RCAN_CHECK_TOKEN": TOKEN}))
    with pytest.raises(ValueError, match=r"'0\.0\.0\.0' is not loopback"):
        bridge.prepare()


# -- TLS files ------------------------------------------------------------------------------


def write_tls(directory: Path) -> dict[str, Path]:
    """A self-signed server certificate, its key, and a CA file (the same certificate)."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "robot")])
    now = dt.datetime.now(dt.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .sign(key, hashes.SHA256()))
    paths = {"cert": directory / "server.pem", "key": directory / "server.key",
             "client_ca": directory / "clients.pem"}
    paths["cert"].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    paths["client_ca"].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    paths["key"].write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                               serialization.PrivateFormat.PKCS8,
                                               serialization.NoEncryption()))
    paths["key"].chmod(0o600)  # the bridge refuses a TLS key others may read
    return paths


# Relative paths: relative to the config file, as the loader resolves them.
TLS = "tls: {cert: tls/server.pem, key: tls/server.key, client_ca: tls/clients.pem}"


def test_tls_files_present_pass(tmp_path: Path) -> None:
    (tmp_path / "tls").mkdir()
    write_tls(tmp_path / "tls")
    assert check(tmp_path, config_text("0.0.0.0", TLS)) == 0


@pytest.mark.parametrize("missing", ["cert", "key", "client_ca"])
def test_a_missing_tls_file_fails_the_check(missing: str, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "tls").mkdir()
    paths = write_tls(tmp_path / "tls")
    paths[missing].unlink()
    assert check(tmp_path, config_text("0.0.0.0", TLS)) == 1
    err = capsys.readouterr().err
    assert "`rcan-rtps run` would fail here" in err
    assert f"bridge.api.tls.{missing}: cannot read {paths[missing]}" in err
    assert check(tmp_path, config_text("0.0.0.0", TLS), "--file-only") == 0  # not this machine


def test_tls_files_that_do_not_load_fail_the_check(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "tls").mkdir()
    paths = write_tls(tmp_path / "tls")
    paths["key"].write_text("not a key\n")
    assert check(tmp_path, config_text("0.0.0.0", TLS)) == 1
    assert "bridge.api.tls: the certificate, key or client CA does not load" in (
        capsys.readouterr().err)


def test_no_tls_directory_at_all(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert check(tmp_path, config_text("127.0.0.1", TLS)) == 1
    err = capsys.readouterr().err
    assert all(f"bridge.api.tls.{key}: cannot read" in err for key in ("cert", "key", "client_ca"))
    assert "Traceback" not in err


# -- JWT key files --------------------------------------------------------------------------


@pytest.mark.parametrize("keys", ["jwks: keys.json", "public_key: key.pem"])
def test_a_missing_or_bad_jwt_key_file_fails_the_check(keys: str, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    text = config_text("127.0.0.1", f"jwt: {{{keys}, audience: rcan-bridge}}")
    assert check(tmp_path, text) == 1
    assert "bridge.api.jwt: cannot load" in capsys.readouterr().err
    (tmp_path / keys.split(": ")[1]).write_text(json.dumps({"keys": []}))
    assert check(tmp_path, text) == 1
    assert "bridge.api.jwt:" in capsys.readouterr().err
    assert check(tmp_path, text, "--file-only") == 0


def test_a_good_jwks_passes(tmp_path: Path) -> None:
    write_jwks(tmp_path / "keys.json", {"k1": Ed25519PrivateKey.generate()})
    text = config_text("127.0.0.1", "jwt: {jwks: keys.json, audience: rcan-bridge}")
    assert check(tmp_path, text) == 0


# -- n-of-m approvals that nobody configured could give ------------------------------------

PRINCIPALS = """principals:
      - {name: ops, role: OWNER, token_env: RCAN_CHECK_TOKEN}
      - {name: admin, role: ADMIN, token_sha256: "%(admin)s"}
      - {name: planner, role: USER, token_sha256: "%(planner)s"}
"""


def _gated(approvals: int, roles: str = "[OWNER]") -> str:
    api = CONFIG.replace("    auth_token_env: RCAN_CHECK_TOKEN\n", "")
    # (each its own token: one token of two principals is refused)
    principals = PRINCIPALS % {"admin": "a" * 64, "planner": "b" * 64}
    return (api % {"host": "127.0.0.1", "api_extra": principals}
            + f"  hitl:\n    gates: [{{action: arm_joint, require_auth: true, "
            f"authorized_roles: {roles}, approvals: {approvals}}}]\n")


@pytest.mark.parametrize("approvals", [1, 2])
def test_approvals_the_configured_principals_can_give_pass(
        approvals: int, tmp_path: Path) -> None:
    assert check(tmp_path, _gated(approvals)) == 0  # ops and admin (ADMIN = OWNER)


def test_more_approvals_than_principals_able_to_give_them_fail_the_check(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert check(tmp_path, _gated(3)) == 1
    err = capsys.readouterr().err
    assert "hitl.gates[arm_joint]: needs 3 distinct approvers of role OWNER" in err
    assert "only 2 configured principal(s)" in err


def test_a_creator_only_gate_with_no_creator_fails_even_the_file_only_check(
        tmp_path: Path) -> None:
    assert check(tmp_path, _gated(1, "[CREATOR]"), "--file-only") == 1  # the file's own fault
    assert check(tmp_path, _gated(1, "[OWNER]"), "--file-only") == 0


# -- signing keys of principals (issue 24 item 5) -------------------------------------------

SIGNER = ("principals: [{name: ops, role: OWNER, token_env: RCAN_CHECK_TOKEN, "
          "signatures: {policy: required, keys: [{kid: k1, alg: ed25519, "
          "public_key_file: keys/ops.pub}]}}]")


def test_a_signing_key_file_is_checked_relative_to_the_config(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = config_text("127.0.0.1", SIGNER)
    assert check(tmp_path, text) == 1
    assert f"cannot read {tmp_path / 'keys' / 'ops.pub'}" in capsys.readouterr().err
    assert check(tmp_path, text, "--file-only") == 0
    (tmp_path / "keys").mkdir()
    (tmp_path / "keys" / "ops.pub").write_bytes(b"\0" * 31)
    assert check(tmp_path, text) == 1
    assert "is neither the 32 raw bytes of an ed25519" in capsys.readouterr().err
    key = Ed25519PrivateKey.generate().public_key()
    (tmp_path / "keys" / "ops.pub").write_bytes(key.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
    assert check(tmp_path, text) == 0
