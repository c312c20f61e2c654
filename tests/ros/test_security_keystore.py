"""SROS2 keystores made without ROS (ros/security/keystore.py, documents.py, smime.py):
`ros2 security`'s layout, documents Debian's openssl verifies against the permissions CA,
policies turned into DDS topic names, and our S/MIME check against openssl's signatures.
Whether rclpy accepts such a keystore: tests/interop/test_sros2.py."""

from __future__ import annotations

import os
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from rcan_rtps.cli.main import main as cli
from rcan_rtps.ros.security import KeystoreError, PolicyError, SignatureError, keystore, smime
from rcan_rtps.ros.security.documents import read_policy
from tests.ros.security_store import ENCLAVE

pytestmark = pytest.mark.offline
OPENSSL = shutil.which("openssl")
needs_openssl = pytest.mark.skipif(OPENSSL is None and os.environ.get("CI") is None,
                                   reason="the openssl command line (Debian: openssl)")


def links(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): os.readlink(p) for p in root.rglob("*") if p.is_symlink()}


def test_layout_is_sros2s(store: Path) -> None:
    files = {str(p.relative_to(store)) for p in store.rglob("*") if p.is_file()
             and not p.is_symlink()}
    assert files == {
        "public/ca.cert.pem", "private/ca.key.pem",
        "enclaves/governance.xml", "enclaves/governance.p7s",
        *(f"enclaves/robot1/rcan_bridge/{n}" for n in (
            "cert.pem", "key.pem", "permissions.xml", "permissions.p7s")),
    }
    assert links(store) == {
        "public/identity_ca.cert.pem": "ca.cert.pem",
        "public/permissions_ca.cert.pem": "ca.cert.pem",
        "private/identity_ca.key.pem": "ca.key.pem",
        "private/permissions_ca.key.pem": "ca.key.pem",
        "enclaves/robot1/rcan_bridge/identity_ca.cert.pem": "../../../public/identity_ca.cert.pem",
        "enclaves/robot1/rcan_bridge/permissions_ca.cert.pem":
            "../../../public/permissions_ca.cert.pem",
        "enclaves/robot1/rcan_bridge/governance.p7s": "../../governance.p7s",
    }
    assert (store / "private/ca.key.pem").stat().st_mode & 0o077 == 0
    assert (store / "enclaves/robot1/rcan_bridge/key.pem").stat().st_mode & 0o077 == 0


def test_certificates(store: Path) -> None:
    ca = keystore.load_cert(store / "public/identity_ca.cert.pem")
    cert = keystore.load_cert(store / "enclaves/robot1/rcan_bridge/cert.pem")
    assert ca.subject.rfc4514_string() == "CN=sros2CA"
    assert cert.subject.rfc4514_string() == f"CN={ENCLAVE}"
    cert.verify_directly_issued_by(ca)
    assert cert.not_valid_after_utc - cert.not_valid_before_utc > keystore.VALIDITY


def test_the_root_enclave_is_enclaves_itself(store: Path) -> None:
    keystore.create_enclave(store, "/", domain_id=7)
    assert (store / "enclaves/cert.pem").is_file()
    assert not (store / "enclaves/governance.p7s").is_symlink()  # not a link to itself
    assert keystore.list_enclaves(store) == ["/", ENCLAVE]


def test_run_again_keeps_what_exists(store: Path) -> None:
    before = {p: p.read_bytes() for p in [store / "public/ca.cert.pem",
                                          store / "enclaves/robot1/rcan_bridge/cert.pem"]}
    keystore.create_keystore(store, domain_id=7)
    keystore.create_enclave(store, ENCLAVE, domain_id=7)
    assert {p: p.read_bytes() for p in before} == before


@needs_openssl
@pytest.mark.parametrize("document", ["enclaves/governance.p7s",
                                      "enclaves/robot1/rcan_bridge/permissions.p7s"])
def test_openssl_verifies_against_the_permissions_ca(store: Path, document: str) -> None:
    done = subprocess.run(
        ["openssl", "smime", "-verify", "-in", str(store / document),
         "-CAfile", str(store / "public/permissions_ca.cert.pem"), "-text"],
        capture_output=True, check=False)
    assert done.returncode == 0, done.stderr
    assert b"Verification successful" in done.stderr
    unsigned = (store / document).with_suffix(".xml").read_bytes()
    assert done.stdout.replace(b"\r\n", b"\n") == unsigned


@needs_openssl
def test_openssl_refuses_a_document_changed_after_signing(store: Path) -> None:
    signed = store / "enclaves/robot1/rcan_bridge/permissions.p7s"
    signed.write_bytes(signed.read_bytes().replace(b"rt/*", b"rt/**", 1))
    done = subprocess.run(
        ["openssl", "smime", "-verify", "-in", str(signed),
         "-CAfile", str(store / "public/permissions_ca.cert.pem")],
        capture_output=True, check=False)
    assert done.returncode != 0


def test_our_check_reads_what_we_signed(store: Path) -> None:
    ca = keystore.load_cert(store / "public/permissions_ca.cert.pem")
    text = smime.verify((store / "enclaves/governance.p7s").read_bytes(), ca)
    assert text == (store / "enclaves/governance.xml").read_bytes()


@needs_openssl
def test_our_check_accepts_openssls_signature_and_refuses_its_tampering(
        store: Path, tmp_path: Path) -> None:
    document = tmp_path / "doc.xml"
    document.write_bytes(b"<dds>\n  <x>1</x>\n</dds>\n")
    signed = tmp_path / "doc.p7s"
    subprocess.run(["openssl", "smime", "-sign", "-text", "-in", str(document),
                    "-out", str(signed), "-signer", str(store / "public/ca.cert.pem"),
                    "-inkey", str(store / "private/ca.key.pem")], check=True)
    ca = keystore.load_cert(store / "public/permissions_ca.cert.pem")
    assert smime.verify(signed.read_bytes(), ca) == document.read_bytes()
    signed.write_bytes(signed.read_bytes().replace(b"<x>1</x>", b"<x>2</x>"))
    with pytest.raises(SignatureError, match=r"changed after signing"):
        smime.verify(signed.read_bytes(), ca)


def test_our_check_refuses_another_ca(store: Path, tmp_path: Path) -> None:
    other = keystore.create_keystore(tmp_path / "other")
    other_ca = keystore.load_cert(other.public / "permissions_ca.cert.pem")
    with pytest.raises(SignatureError, match=r"not signed by this CA"):
        smime.verify((store / "enclaves/governance.p7s").read_bytes(), other_ca)


def test_our_check_refuses_what_is_not_smime(store: Path) -> None:
    ca = keystore.load_cert(store / "public/permissions_ca.cert.pem")
    with pytest.raises(SignatureError, match=r"not an S/MIME signed message"):
        smime.verify(b"<dds/>", ca)


def test_governance_is_sros2s_default_for_the_domain(store: Path) -> None:
    rule = ET.parse(store / "enclaves/governance.xml").getroot().find(
        "domain_access_rules/domain_rule")
    assert rule is not None
    assert rule.findtext("domains/id") == "7"
    assert rule.findtext("allow_unauthenticated_participants") == "false"
    assert rule.findtext("enable_join_access_control") == "true"
    assert rule.findtext("rtps_protection_kind") == "SIGN"
    assert rule.findtext("topic_access_rules/topic_rule/data_protection_kind") == "ENCRYPT"


def test_default_permissions_grant_everything_to_the_enclave(store: Path) -> None:
    grant = ET.parse(store / "enclaves/robot1/rcan_bridge/permissions.xml").getroot().find(
        "permissions/grant")
    assert grant is not None
    assert grant.get("name") == ENCLAVE
    assert grant.findtext("subject_name") == f"CN={ENCLAVE}"
    assert grant.findtext("default") == "DENY"
    published = [t.text for t in grant.iterfind("allow_rule/publish/topics/topic")]
    assert {"rt/*", "rq/*Request", "rr/*Reply", "ros_discovery_info"} <= set(published)
    assert {d.text for d in grant.iterfind("allow_rule/domains/id")} == {"7"}


POLICY = b"""<policy version="0.2.0"><enclaves>
<enclave path="/robot1/rcan_bridge"><profiles>
  <profile ns="/robot1" node="rcan_bridge">
    <topics publish="ALLOW"><topic>cmd_vel</topic><topic>~/status</topic></topics>
    <topics subscribe="ALLOW"><topic>/tf</topic></topics>
    <topics publish="DENY"><topic>/secret</topic></topics>
    <services request="ALLOW"><service>reset</service></services>
    <actions call="ALLOW"><action>navigate_to_pose</action></actions>
  </profile>
</profiles></enclave>
<enclave path="/other"><profiles/></enclave>
</enclaves></policy>"""


def test_a_policy_becomes_dds_topic_names() -> None:
    grant = read_policy(POLICY, ENCLAVE)
    assert grant.allow.publish == {
        "rt/robot1/cmd_vel", "rt/robot1/rcan_bridge/status", "rq/robot1/resetRequest",
        *(f"rq/robot1/navigate_to_pose/_action/{s}Request"
          for s in ("send_goal", "cancel_goal", "get_result"))}
    assert grant.allow.subscribe == {
        "rt/tf", "rr/robot1/resetReply",
        *(f"rr/robot1/navigate_to_pose/_action/{s}Reply"
          for s in ("send_goal", "cancel_goal", "get_result")),
        "rt/robot1/navigate_to_pose/_action/feedback",
        "rt/robot1/navigate_to_pose/_action/status"}
    assert grant.deny.publish == {"rt/secret"}


@pytest.mark.parametrize(("policy", "message"), [
    (b"<nope/>", "not an SROS2 policy"),
    (b"<policy", "not XML"),
    (POLICY.replace(b'path="/robot1/rcan_bridge"', b'path="/x"'), "no enclave"),
    (POLICY.replace(b'publish="DENY"', b'publish="MAYBE"'), "ALLOW or DENY"),
    (POLICY.replace(b"<topic>/tf</topic>", b"<service>/tf</service>"), "non-empty <topic>"),
])
def test_a_bad_policy_says_why(policy: bytes, message: str) -> None:
    with pytest.raises(PolicyError, match=message):
        read_policy(policy, ENCLAVE)


def test_create_permission_from_a_policy(store: Path, tmp_path: Path) -> None:
    policy = tmp_path / "policy.xml"
    policy.write_bytes(POLICY)
    keystore.create_permission(store, ENCLAVE, policy, domain_id=7)
    ca = keystore.load_cert(store / "public/permissions_ca.cert.pem")
    text = smime.verify((store / "enclaves/robot1/rcan_bridge/permissions.p7s").read_bytes(), ca)
    assert b"<topic>rt/robot1/cmd_vel</topic>" in text
    assert b"<deny_rule>" in text


@pytest.mark.parametrize("name", ["robot1", "/robot 1", "/1robot", "//x", "/x/"])
def test_invalid_enclave_names(store: Path, name: str) -> None:
    with pytest.raises(KeystoreError, match=r"invalid enclave name"):
        keystore.create_enclave(store, name)


def test_an_enclave_needs_a_keystore(tmp_path: Path) -> None:
    with pytest.raises(KeystoreError, match=r"is not a keystore.*create-keystore"):
        keystore.create_enclave(tmp_path, ENCLAVE)


def test_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "ks"
    assert cli(["--domain-id", "3", "security", "create-keystore", str(root)]) == 0
    assert cli(["security", "create-enclave", str(root), ENCLAVE, "--domain-id", "3"]) == 0
    policy = tmp_path / "policy.xml"
    policy.write_bytes(POLICY)
    assert cli(["security", "create-permission", str(root), ENCLAVE, str(policy),
                "--domain-id", "3"]) == 0
    assert cli(["security", "list-enclaves", str(root)]) == 0
    out = capsys.readouterr().out
    assert "governance for domain 3" in out
    assert out.rstrip().endswith(ENCLAVE)
    assert cli(["security", "create-permission", str(root), "/nobody", str(policy)]) == 1
    assert "no enclave '/nobody'" in capsys.readouterr().err
