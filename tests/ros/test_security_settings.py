"""ROS_SECURITY_* read as rcl reads it, the enclave's files found as rmw_dds_common finds
them and checked before DDS is asked (ros/security/settings.py): one clear error per way a
keystore can be unusable. No DDS here: the secured graph is tests/interop/test_sros2.py."""

from __future__ import annotations

import datetime
import logging
import shutil
from pathlib import Path

import pytest

from rcan_rtps.ros.security import (
    CertificateError,
    KeystoreError,
    SecurityUnavailable,
    SignatureError,
    keystore,
    settings,
)
from rcan_rtps.ros.security.settings import EnclaveFiles, check, participant_security
from tests.ros.security_store import ENCLAVE

pytestmark = pytest.mark.offline
UTC = datetime.timezone.utc


def env(store: Path, **more: str) -> dict[str, str]:
    return {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce",
            "ROS_SECURITY_KEYSTORE": str(store), **more}


def files(store: Path, enclave: str = ENCLAVE) -> EnclaveFiles:
    return EnclaveFiles.of(keystore.Keystore(store).enclave_dir(enclave))


# -- the environment, as rcl reads it ---------------------------------------------------


@pytest.mark.parametrize(("values", "enabled", "enforce"), [
    ({}, False, False),
    ({"ROS_SECURITY_ENABLE": "true"}, True, False),
    ({"ROS_SECURITY_ENABLE": "True"}, False, False),  # exactly "true", as rcl compares
    ({"ROS_SECURITY_ENABLE": "1"}, False, False),
    ({"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"}, True, True),
    ({"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "enforce"}, True, False),
])
def test_enable_and_strategy(values: dict[str, str], enabled: bool, enforce: bool) -> None:
    request = settings.request_from_env("/", values)
    assert (request.enabled, request.enforce) == (enabled, enforce)


def test_the_enclave_is_the_override_else_the_contexts() -> None:
    assert settings.request_from_env("/robot1/x", {}).enclave == "/robot1/x"
    assert settings.request_from_env(
        "/robot1/x", {"ROS_SECURITY_ENCLAVE_OVERRIDE": "/other"}).enclave == "/other"
    assert settings.request_from_env(  # empty counts as unset (rcl's dupenv)
        "/robot1/x", {"ROS_SECURITY_ENCLAVE_OVERRIDE": ""}).enclave == "/robot1/x"


def test_lookup_is_exact_under_enclaves(store: Path) -> None:
    request = settings.request_from_env(ENCLAVE, env(store))
    assert settings.locate(request) == store / "enclaves/robot1/rcan_bridge"
    keystore.create_enclave(store, "/", domain_id=7)
    assert settings.locate(settings.request_from_env("/", env(store))) == store / "enclaves"


def test_disabled_means_no_properties(store: Path) -> None:
    assert participant_security(ENCLAVE, 7, {"ROS_SECURITY_KEYSTORE": str(store)}) == []


# -- a keystore or enclave that is not there ---------------------------------------------


def test_enforce_without_a_keystore_variable() -> None:
    with pytest.raises(KeystoreError, match=r"ROS_SECURITY_KEYSTORE is not set.*Enforce"):
        participant_security(ENCLAVE, 7, {"ROS_SECURITY_ENABLE": "true",
                                          "ROS_SECURITY_STRATEGY": "Enforce"})


def test_enforce_with_a_missing_keystore(tmp_path: Path) -> None:
    with pytest.raises(KeystoreError, match=r"no such directory.*create-keystore"):
        participant_security(ENCLAVE, 7, env(tmp_path / "nowhere"))


def test_enforce_with_a_missing_enclave(store: Path) -> None:
    with pytest.raises(KeystoreError, match=r"no enclave '/robot2/x'.*create-enclave .* /robot2/x"):
        participant_security("/robot2/x", 7, env(store))


def test_permissive_with_a_missing_enclave_runs_unsecured_and_says_so(
        store: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        found = participant_security("/robot2/x", 7,
                                     env(store, ROS_SECURITY_STRATEGY="Permissive"))
    assert found == []
    assert "no enclave '/robot2/x'" in caplog.text
    assert "running WITHOUT security" in caplog.text


def test_an_enclave_missing_a_file(store: Path) -> None:
    (store / "enclaves/robot1/rcan_bridge/permissions.p7s").unlink()
    with pytest.raises(KeystoreError, match=r"lacks permissions.p7s"):
        participant_security(ENCLAVE, 7, env(store))


def test_a_dangling_link_is_missing(store: Path) -> None:
    (store / "enclaves/governance.p7s").unlink()
    with pytest.raises(KeystoreError, match=r"lacks governance.p7s"):
        files(store)


# -- a Cyclone DDS without DDS-Security --------------------------------------------------


@pytest.fixture
def wheel_cyclone() -> None:
    if settings.cyclone_has_security():
        pytest.skip("this interpreter's Cyclone DDS has security (PyPI's wheel has not)")


@pytest.mark.usefixtures("wheel_cyclone")
def test_enforce_on_a_cyclone_without_security_refuses_and_says_how(store: Path) -> None:
    with pytest.raises(SecurityUnavailable) as refused:
        participant_security(ENCLAVE, 7, env(store))
    message = str(refused.value)
    assert "has no DDS-Security" in message
    assert "ENABLE_SECURITY=ON" in message
    assert "--no-binary cyclonedds" in message
    assert "Enforce" in message


@pytest.mark.usefixtures("wheel_cyclone")
def test_permissive_on_a_cyclone_without_security_warns_and_runs_unsecured(
        store: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        found = participant_security(ENCLAVE, 7, env(store, ROS_SECURITY_STRATEGY="Permissive"))
    assert found == []
    assert "has no DDS-Security" in caplog.text
    assert "running WITHOUT security" in caplog.text


# -- files that are there but wrong: refused whatever the strategy ----------------------------


def test_a_good_enclave_passes(store: Path) -> None:
    check(files(store), 7)


def test_an_expired_certificate(store: Path) -> None:
    keystore.create_enclave(store, "/old", 7, now=datetime.datetime(2020, 1, 1, tzinfo=UTC),
                            validity=datetime.timedelta(days=30))
    with pytest.raises(CertificateError, match=r"expired on 2020-01-31.*create-enclave"):
        check(files(store, "/old"), 7)


def test_a_certificate_not_yet_valid(store: Path) -> None:
    later = datetime.datetime.now(UTC) + datetime.timedelta(days=30)
    keystore.create_enclave(store, "/later", 7, now=later)
    with pytest.raises(CertificateError, match=r"is not valid before .*clock"):
        check(files(store, "/later"), 7)


def test_a_key_of_another_certificate(store: Path) -> None:
    keystore.create_enclave(store, "/other", 7)
    shutil.copy(store / "enclaves/other/key.pem", store / "enclaves/robot1/rcan_bridge/key.pem")
    with pytest.raises(CertificateError, match=r"key.pem is not the key of .*cert.pem"):
        check(files(store), 7)


def test_an_identity_from_another_keystore(store: Path, tmp_path: Path) -> None:
    other = tmp_path / "other"
    keystore.create_keystore(other, 7)
    keystore.create_enclave(other, ENCLAVE, 7)
    for name in ("cert.pem", "key.pem"):
        shutil.copy(other / "enclaves/robot1/rcan_bridge" / name,
                    store / "enclaves/robot1/rcan_bridge" / name)
    with pytest.raises(CertificateError, match=r"was not issued by identity_ca.cert.pem"):
        check(files(store), 7)


def test_permissions_changed_after_signing(store: Path) -> None:
    signed = store / "enclaves/robot1/rcan_bridge/permissions.p7s"
    signed.write_bytes(signed.read_bytes().replace(b"<topic>rt/*</topic>",
                                                   b"<topic>rt/**</topic>", 1))
    with pytest.raises(SignatureError, match=r"permissions.p7s: the signed permissions is refused: "
                       r"the signed text was changed after signing"):
        check(files(store), 7)


def test_permissions_signed_by_another_ca(store: Path, tmp_path: Path) -> None:
    other = keystore.create_keystore(tmp_path / "other", 7)
    keystore.create_enclave(other.root, ENCLAVE, 7)
    shutil.copy(other.root / "enclaves/robot1/rcan_bridge/permissions.p7s",
                store / "enclaves/robot1/rcan_bridge/permissions.p7s")
    with pytest.raises(SignatureError, match=r"not signed by this CA but by another one"):
        check(files(store), 7)


def test_permissions_of_another_enclave(store: Path) -> None:
    keystore.create_enclave(store, "/other", 7)
    shutil.copy(store / "enclaves/other/permissions.p7s",
                store / "enclaves/robot1/rcan_bridge/permissions.p7s")
    with pytest.raises(KeystoreError, match=r"has no grant for CN=/robot1/rcan_bridge .*"
                       r"it grants 'CN=/other'"):
        check(files(store), 7)


def test_a_governance_for_another_domain(store: Path) -> None:
    with pytest.raises(KeystoreError, match=r"covers domain 7, not domain 8.*ROS_DOMAIN_ID=8"):
        check(files(store), 8)


# -- what Cyclone is given ----------------------------------------------------------------


def test_the_properties_are_rmw_cyclonedds(store: Path, tmp_path: Path) -> None:
    enclave = files(store)
    props = dict(enclave.properties())
    directory = (store / "enclaves/robot1/rcan_bridge").absolute()
    assert props["dds.sec.auth.identity_ca"] == f"file:{directory}/identity_ca.cert.pem"
    assert props["dds.sec.auth.identity_certificate"] == f"file:{directory}/cert.pem"
    assert props["dds.sec.auth.private_key"] == f"file:{directory}/key.pem"
    assert props["dds.sec.access.permissions_ca"] == f"file:{directory}/permissions_ca.cert.pem"
    assert props["dds.sec.access.governance"] == f"file:{directory}/governance.p7s"
    assert props["dds.sec.access.permissions"] == f"file:{directory}/permissions.p7s"
    assert props["dds.sec.auth.library.path"] == "dds_security_auth"
    assert props["dds.sec.access.library.init"] == "init_access_control"
    assert props["dds.sec.crypto.library.finalize"] == "finalize_crypto"
    assert "org.eclipse.cyclonedds.sec.auth.crl" not in props
    (tmp_path / "libdds_security_auth.so").touch()
    beside = dict(enclave.properties(tmp_path))
    assert beside["dds.sec.auth.library.path"] == str(tmp_path / "libdds_security_auth.so")
    assert beside["dds.sec.crypto.library.path"] == "dds_security_crypto"  # not there


def test_a_crl_is_passed_when_present(store: Path) -> None:
    (store / "enclaves/robot1/rcan_bridge/crl.pem").write_bytes(b"")
    props = dict(files(store).properties())
    assert props["org.eclipse.cyclonedds.sec.auth.crl"].endswith("/crl.pem")


def test_the_check_command(store: Path, capsys: pytest.CaptureFixture[str],
                           monkeypatch: pytest.MonkeyPatch) -> None:
    from rcan_rtps.cli.main import main as cli

    code = cli(["--domain-id", "7", "security", "check", str(store), ENCLAVE])
    out = capsys.readouterr().out
    assert f"enclave {ENCLAVE} in {store}/enclaves/robot1/rcan_bridge: usable on domain 7" in out
    assert code == (0 if settings.cyclone_has_security() else 1)
    monkeypatch.setenv("ROS_SECURITY_KEYSTORE", str(store))
    monkeypatch.setenv("ROS_SECURITY_ENCLAVE_OVERRIDE", ENCLAVE)
    assert cli(["--domain-id", "8", "security", "check"]) == 1
    assert "not domain 8" in capsys.readouterr().err
