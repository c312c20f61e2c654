"""SROS2 for one participant: the ROS_SECURITY_* environment read as rcl reads it, the
enclave's files found as rmw_dds_common finds them, checked before DDS is asked, and given
to Cyclone DDS as the participant QoS properties rmw_cyclonedds sets.

rcl's rules (rcl/security.c, Jazzy):
- security is on only when ROS_SECURITY_ENABLE is exactly `true`;
- ROS_SECURITY_STRATEGY exactly `Enforce` enforces; anything else is Permissive;
- the enclave is ROS_SECURITY_ENCLAVE_OVERRIDE if set and not empty, else the context's
  enclave (`--ros-args --enclave`, default `/`; since Foxy no longer the node's name);
- its directory is ROS_SECURITY_KEYSTORE/enclaves/<enclave> (`/` is enclaves/ itself).
With Enforce, a keystore or enclave that cannot be found is an error; with Permissive the
participant runs without security, with a warning (rmw_cyclonedds does the same when its
Cyclone has no security). Files that are there but wrong (expired, tampered, another CA) are
an error under either strategy: DDS refuses them, and so do we, first, saying which and why.
"""

from __future__ import annotations

import datetime
import logging
import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization

from . import keystore as ks
from . import smime
from .errors import CertificateError, KeystoreError, SecurityError, SecurityUnavailable

log = logging.getLogger(__name__)

ENABLE, STRATEGY = "ROS_SECURITY_ENABLE", "ROS_SECURITY_STRATEGY"
KEYSTORE, ENCLAVE_OVERRIDE = "ROS_SECURITY_KEYSTORE", "ROS_SECURITY_ENCLAVE_OVERRIDE"
HOW_TO_GET_SECURITY = (
    "PyPI's cyclonedds wheel is built without DDS-Security: install Cyclone DDS C 11 built "
    "with -DENABLE_SECURITY=ON and the binding against it (CYCLONEDDS_HOME=<install> pip "
    "install --no-binary cyclonedds cyclonedds==11.0.1; from a source tree: bash "
    "scripts/cyclonedds-secure/build.sh PREFIX), then run with CYCLONEDDS_HOME=<install>; "
    "see docs/security.md")
# The plugins rmw_cyclonedds names (library, init and finalize symbols).
_PLUGINS = {
    "auth": ("dds_security_auth", "init_authentication", "finalize_authentication"),
    "crypto": ("dds_security_crypto", "init_crypto", "finalize_crypto"),
    "access": ("dds_security_ac", "init_access_control", "finalize_access_control"),
}


@dataclass(frozen=True)
class SecurityRequest:
    """What the environment asks of one participant."""

    enabled: bool
    enforce: bool
    keystore: Path | None
    enclave: str

    @property
    def strategy(self) -> str:
        return "Enforce" if self.enforce else "Permissive"


def request_from_env(enclave: str = "/", env: Mapping[str, str] | None = None
                     ) -> SecurityRequest:
    env = os.environ if env is None else env
    keystore = env.get(KEYSTORE, "")
    return SecurityRequest(
        enabled=env.get(ENABLE, "") == "true",
        enforce=env.get(STRATEGY, "") == "Enforce",
        keystore=Path(keystore) if keystore else None,
        enclave=env.get(ENCLAVE_OVERRIDE, "") or enclave)


def locate(request: SecurityRequest) -> Path:
    """The enclave's directory in the keystore (KeystoreError saying what is missing)."""
    if request.keystore is None:
        raise KeystoreError(f"{ENABLE}=true but {KEYSTORE} is not set: point it at an SROS2 "
                            "keystore (`rcan-rtps security create-keystore DIR`)")
    if not request.keystore.is_dir():
        raise KeystoreError(f"{KEYSTORE}={request.keystore}: no such directory (create one "
                            f"with `rcan-rtps security create-keystore {request.keystore}`)")
    directory = ks.Keystore(request.keystore).enclave_dir(request.enclave)
    if not directory.is_dir():
        raise KeystoreError(
            f"keystore {request.keystore} has no enclave {request.enclave!r} (no directory "
            f"{directory}); create it with `rcan-rtps security create-enclave "
            f"{request.keystore} {request.enclave}`, or choose another with "
            f"{ENCLAVE_OVERRIDE}")
    return directory


@dataclass(frozen=True)
class EnclaveFiles:
    """The files DDS-Security reads for one enclave (rmw_dds_common's list)."""

    directory: Path
    identity_ca: Path
    cert: Path
    key: Path
    permissions_ca: Path
    governance: Path
    permissions: Path
    crl: Path | None

    @classmethod
    def of(cls, directory: Path) -> EnclaveFiles:
        names = {"identity_ca": ks.IDENTITY_CA_CERT, "cert": ks.CERT, "key": ks.KEY,
                 "permissions_ca": ks.PERMISSIONS_CA_CERT, "governance": ks.GOVERNANCE,
                 "permissions": ks.PERMISSIONS}
        missing = [n for n in names.values() if not (directory / n).is_file()]
        if missing:
            raise KeystoreError(f"enclave directory {directory} lacks {', '.join(missing)} "
                                "(a dangling link counts as missing)")
        crl = directory / "crl.pem"
        return cls(directory=directory, crl=crl if crl.is_file() else None,
                   **{field: directory / name for field, name in names.items()})

    def properties(self, plugin_dir: Path | None = None) -> list[tuple[str, str]]:
        """The participant QoS properties of rmw_cyclonedds, plugins from `plugin_dir` when
        given (else found by name on the library path)."""
        props = [
            ("dds.sec.auth.identity_ca", _uri(self.identity_ca)),
            ("dds.sec.auth.identity_certificate", _uri(self.cert)),
            ("dds.sec.auth.private_key", _uri(self.key)),
            ("dds.sec.access.permissions_ca", _uri(self.permissions_ca)),
            ("dds.sec.access.governance", _uri(self.governance)),
            ("dds.sec.access.permissions", _uri(self.permissions)),
        ]
        for kind, (library, init, finalize) in _PLUGINS.items():
            path = plugin_dir / f"lib{library}.so" if plugin_dir else None
            props += [(f"dds.sec.{kind}.library.path",
                       str(path) if path and path.is_file() else library),
                      (f"dds.sec.{kind}.library.init", init),
                      (f"dds.sec.{kind}.library.finalize", finalize)]
        if self.crl is not None:
            props.append(("org.eclipse.cyclonedds.sec.auth.crl", _uri(self.crl)))
        return props


def _uri(path: Path) -> str:
    return f"file:{path.absolute()}"


def _utc(moment: datetime.datetime) -> str:
    return moment.astimezone(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def _check_window(cert: x509.Certificate, what: str, now: datetime.datetime) -> None:
    if now < cert.not_valid_before_utc:
        raise CertificateError(f"{what} is not valid before {_utc(cert.not_valid_before_utc)} "
                               f"(now {_utc(now)}): is this machine's clock right?")
    if now > cert.not_valid_after_utc:
        raise CertificateError(f"{what} expired on {_utc(cert.not_valid_after_utc)}: make a "
                               "new one (remove cert.pem and key.pem, then `rcan-rtps "
                               "security create-enclave KEYSTORE ENCLAVE`)")


def _check_issued(cert: x509.Certificate, ca: x509.Certificate, what: str) -> None:
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature) as e:
        raise CertificateError(f"{what} was not issued by identity_ca.cert.pem "
                               f"({ca.subject.rfc4514_string()}): it belongs to another "
                               "keystore") from e


def _domains(rule: ET.Element) -> list[tuple[int, int]]:
    ranges = []
    for element in rule.iterfind("domains/*"):
        if element.tag == "id":
            value = int((element.text or "").strip())
            ranges.append((value, value))
        elif element.tag == "id_range":
            low = element.findtext("min")
            high = element.findtext("max")
            ranges.append((int(low) if low else 0, int(high) if high else 232))
    return ranges


def _check_governance_domain(text: bytes, domain_id: int, files: EnclaveFiles) -> None:
    try:
        rules = ET.fromstring(text).iterfind("domain_access_rules/domain_rule")
        covered = [r for rule in rules for r in _domains(rule)]
    except (ET.ParseError, ValueError) as e:
        raise KeystoreError(f"{files.governance}: the signed governance is not valid XML "
                            f"({e})") from e
    if not any(low <= domain_id <= high for low, high in covered):
        listed = ", ".join(str(lo) if lo == hi else f"{lo}-{hi}" for lo, hi in covered)
        raise KeystoreError(f"{files.governance} covers domain {listed or 'none'}, not domain "
                            f"{domain_id}: make the keystore for this domain "
                            f"(ROS_DOMAIN_ID={domain_id} `rcan-rtps security create-keystore`"
                            " in a new directory)")


def _subject(text: str) -> dict[str, str]:
    """`CN=/a, O=b` as {"CN": "/a", "O": "b"} (DDS compares subject names by attribute)."""
    pairs = (part.split("=", 1) for part in text.replace(";", ",").split(",") if "=" in part)
    return {key.strip().upper(): value.strip() for key, value in pairs}


def _check_grant(text: bytes, cert: x509.Certificate, files: EnclaveFiles) -> None:
    """The permissions must hold a grant for this certificate's subject (Cyclone's access
    control looks it up by subject name; without one it refuses the participant)."""
    try:
        grants = list(ET.fromstring(text).iterfind("permissions/grant"))
    except ET.ParseError as e:
        raise KeystoreError(f"{files.permissions}: the signed permissions are not valid XML "
                            f"({e})") from e
    subject = cert.subject.rfc4514_string()
    wanted = _subject(subject)
    if not any(_subject(g.findtext("subject_name") or "") == wanted for g in grants):
        names = ", ".join(repr(g.findtext("subject_name")) for g in grants) or "none"
        raise KeystoreError(f"{files.permissions} has no grant for {subject} (the subject of "
                            f"{files.cert}; it grants {names}): the permissions belong to "
                            "another enclave — `rcan-rtps security create-permission`")


def _public_der(key: Any) -> bytes:
    der: bytes = key.public_bytes(serialization.Encoding.DER,
                                  serialization.PublicFormat.SubjectPublicKeyInfo)
    return der


def check(files: EnclaveFiles, domain_id: int, now: datetime.datetime | None = None) -> None:
    """What Cyclone's plugins would refuse, refused first with the reason and the remedy:
    certificates in their validity window and issued by the identity CA, the key that of
    the certificate, governance and permissions signed by the permissions CA (untouched
    since), and a governance that covers `domain_id`."""
    now = now or datetime.datetime.now(datetime.timezone.utc)
    identity_ca = ks.load_cert(files.identity_ca)
    permissions_ca = ks.load_cert(files.permissions_ca)
    cert = ks.load_cert(files.cert)
    key = ks.load_key(files.key)
    _check_window(identity_ca, f"the identity CA {files.identity_ca}", now)
    _check_window(permissions_ca, f"the permissions CA {files.permissions_ca}", now)
    _check_window(cert, f"the certificate {files.cert}", now)
    _check_issued(cert, identity_ca, f"the certificate {files.cert}")
    if _public_der(cert.public_key()) != _public_der(key.public_key()):
        raise CertificateError(f"{files.key} is not the key of {files.cert} (the two come "
                               "from different enclaves or runs): restore the pair, or "
                               "remove both and create the enclave again")
    for document, what in ((files.governance, "governance"),
                           (files.permissions, "permissions")):
        try:
            text = smime.verify(document.read_bytes(), permissions_ca)
        except SecurityError as e:
            raise type(e)(f"{document}: the signed {what} is refused: {e} (checked against "
                          f"{files.permissions_ca}); sign it again with `rcan-rtps security "
                          f"{'create-keystore' if what == 'governance' else 'create-permission'}"
                          "`") from e
        if what == "governance":
            _check_governance_domain(text, domain_id, files)
        else:
            _check_grant(text, cert, files)


def cyclone_library() -> object:
    """The Cyclone DDS C library the binding loaded (a ctypes handle)."""
    from cyclonedds.internal import DDS

    return DDS._dll_handle


def cyclone_has_security(library: object | None = None) -> bool:
    """Whether Cyclone DDS was built with DDS-Security: its security core (the DDS_Security_*
    functions the plugins link against) is part of libddsc only then."""
    library = cyclone_library() if library is None else library
    return hasattr(library, "DDS_Security_BinaryProperty_alloc")


def plugin_dir(library: object | None = None) -> Path | None:
    """The directory of the loaded libddsc, where a Cyclone install keeps its plugins."""
    library = cyclone_library() if library is None else library
    name = getattr(library, "_name", None)
    if not name or "/" not in str(name):
        return None
    return Path(os.path.realpath(name)).parent


def _library_path(library: object) -> str:
    name = str(getattr(library, "_name", "?"))
    return os.path.realpath(name) if "/" in name else name


def participant_security(enclave: str, domain_id: int,
                         env: Mapping[str, str] | None = None,
                         library: object | None = None) -> list[tuple[str, str]]:
    """The DDS-Security properties for a participant of `enclave` on `domain_id`, or [] to
    run unsecured (security off, or Permissive without a usable enclave). SecurityError
    when it may not run."""
    request = request_from_env(enclave, env)
    if not request.enabled:
        return []
    library = cyclone_library() if library is None else library
    try:
        files = EnclaveFiles.of(locate(request))
        if not cyclone_has_security(library):
            raise SecurityUnavailable(
                f"{ENABLE}=true, but the Cyclone DDS library loaded "
                f"({_library_path(library)}) has no DDS-Security. "
                f"{HOW_TO_GET_SECURITY}")
    except (KeystoreError, SecurityUnavailable) as e:
        if request.enforce:
            raise type(e)(f"{e} [{STRATEGY}=Enforce: not starting without security]") from e
        log.warning("%s; running WITHOUT security (%s is not Enforce)", e, STRATEGY)
        return []
    check(files, domain_id)
    log.info("SROS2: enclave %s from %s (%s)", request.enclave, files.directory,
             request.strategy)
    return files.properties(plugin_dir(library))
