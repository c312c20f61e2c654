"""SROS2 keystores without ROS: what `ros2 security create_keystore / create_enclave /
create_permission / list_enclaves` make, laid out the same way, so rclpy (any RMW) and
rcan-rtps use one keystore:

    KEYSTORE/
      public/   ca.cert.pem  identity_ca.cert.pem → ca.cert.pem  permissions_ca.cert.pem → …
      private/  ca.key.pem   identity_ca.key.pem → ca.key.pem    permissions_ca.key.pem → …
      enclaves/ governance.xml  governance.p7s (signed by the permissions CA)
        <enclave path>/  cert.pem key.pem (EC P-256, CN=<enclave>, issued by the identity CA)
                         permissions.xml permissions.p7s (signed by the permissions CA)
                         identity_ca.cert.pem permissions_ca.cert.pem governance.p7s (links)

As in SROS2 one CA plays both roles by default (the two names are links to it); giving
separate identity and permissions CAs is a matter of replacing the links' targets.
DDS reads only the .p7s documents: editing an .xml changes nothing until it is signed again
(`create-permission`).
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from ..errors import InvalidNameError
from ..names import validate_namespace
from . import documents, smime
from .errors import KeystoreError

CA_NAME = "sros2CA"  # the CA's CN, as SROS2 names it
VALIDITY = datetime.timedelta(days=3650)
# Backdated a day, as SROS2 does: a peer whose clock is a little behind must not find the
# certificate (or the permissions' validity, which follows it) in the future.
BACKDATE = datetime.timedelta(days=1)

PUBLIC, PRIVATE, ENCLAVES = "public", "private", "enclaves"
IDENTITY_CA_CERT, PERMISSIONS_CA_CERT = "identity_ca.cert.pem", "permissions_ca.cert.pem"
IDENTITY_CA_KEY, PERMISSIONS_CA_KEY = "identity_ca.key.pem", "permissions_ca.key.pem"
GOVERNANCE_XML, GOVERNANCE = "governance.xml", "governance.p7s"
CERT, KEY = "cert.pem", "key.pem"
PERMISSIONS_XML, PERMISSIONS = "permissions.xml", "permissions.p7s"


@dataclass(frozen=True)
class Keystore:
    root: Path

    @property
    def public(self) -> Path:
        return self.root / PUBLIC

    @property
    def private(self) -> Path:
        return self.root / PRIVATE

    @property
    def enclaves(self) -> Path:
        return self.root / ENCLAVES

    def enclave_dir(self, enclave: str) -> Path:
        """Where an enclave's files are (rcl's lookup: `/` is enclaves/ itself)."""
        check_enclave_name(enclave)
        return self.enclaves.joinpath(*[p for p in enclave.split("/") if p])

    def missing(self) -> list[str]:
        """What a keystore needs to make enclaves and lacks (relative paths)."""
        needed = [f"{PUBLIC}/{IDENTITY_CA_CERT}", f"{PUBLIC}/{PERMISSIONS_CA_CERT}",
                  f"{PRIVATE}/{IDENTITY_CA_KEY}", f"{PRIVATE}/{PERMISSIONS_CA_KEY}",
                  f"{ENCLAVES}/{GOVERNANCE}"]
        return [name for name in needed if not (self.root / name).is_file()]

    def require(self) -> None:
        missing = self.missing()
        if missing:
            raise KeystoreError(f"{self.root} is not a keystore (missing {', '.join(missing)}); "
                                f"create it with `rcan-rtps security create-keystore {self.root}`")


def check_enclave_name(enclave: str) -> None:
    """Enclave names follow the rules of an absolute namespace (as rcl checks them)."""
    try:
        if not enclave.startswith("/"):
            raise InvalidNameError(enclave, "an enclave name must start with '/'")
        validate_namespace(enclave)
    except InvalidNameError as e:
        raise KeystoreError(f"invalid enclave name {enclave!r}: {e.rule}") from e


def _new_key() -> ec.EllipticCurvePrivateKey:
    # DDS-Security's builtin authentication (9.3.1) uses ECDSA on prime256v1 (= SECP256R1).
    return ec.generate_private_key(ec.SECP256R1())


def _certificate(subject: str, key: ec.EllipticCurvePrivateKey, *,
                 issuer: x509.Certificate | None = None,
                 issuer_key: ec.EllipticCurvePrivateKey | None = None,
                 now: datetime.datetime | None = None,
                 validity: datetime.timedelta = VALIDITY) -> x509.Certificate:
    """A CA certificate (no issuer: self-signed) or one issued by `issuer`."""
    now = now or datetime.datetime.now(datetime.timezone.utc)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)])
    is_ca = issuer is None
    builder = (x509.CertificateBuilder()
               .subject_name(name)
               .issuer_name(name if issuer is None else issuer.subject)
               .public_key(key.public_key())
               .serial_number(x509.random_serial_number())
               .not_valid_before(now - BACKDATE)
               .not_valid_after(now + validity)
               .add_extension(x509.BasicConstraints(ca=is_ca, path_length=1 if is_ca else None),
                              critical=is_ca))
    return builder.sign(key if issuer_key is None else issuer_key, hashes.SHA256())


def _write(path: Path, data: bytes, *, private: bool = False) -> None:
    """Writes through a temporary file (no half-written file is ever read); keys 0600."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _pem_cert(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _link(target: Path, link: Path) -> None:
    """A relative symlink `link` → `target` (replacing what is there)."""
    if link.absolute() == target.absolute():
        return  # the enclave `/` is enclaves/ itself, where governance.p7s already is
    relative = os.path.relpath(target, link.parent)
    if link.is_symlink() or link.exists():
        if link.is_symlink() and os.readlink(link) == relative:
            return
        link.unlink()
    link.symlink_to(relative)


def load_cert(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except OSError as e:
        raise KeystoreError(f"cannot read {path}: {e.strerror}") from e
    except ValueError as e:
        raise KeystoreError(f"{path} is not a PEM certificate ({e})") from e


def load_key(path: Path) -> ec.EllipticCurvePrivateKey:
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except OSError as e:
        raise KeystoreError(f"cannot read {path}: {e.strerror}") from e
    except (ValueError, TypeError) as e:  # TypeError: an encrypted key, no password
        raise KeystoreError(f"{path} is not an unencrypted PEM private key ({e})") from e
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise KeystoreError(f"{path} is not an EC key (DDS-Security wants ECDSA P-256)")
    return key


def _sign_file(keystore: Keystore, document: Path, signed: Path) -> None:
    ca = load_cert(keystore.public / PERMISSIONS_CA_CERT)
    key = load_key(keystore.private / PERMISSIONS_CA_KEY)
    _write(signed, smime.sign(document.read_bytes(), ca, key))


def create_keystore(root: Path, domain_id: int = 0) -> Keystore:
    """A new keystore at `root` (a CA, governance signed for `domain_id`); what exists is
    kept, so running it again completes a partial keystore and changes nothing else."""
    keystore = Keystore(root)
    for path in (keystore.public, keystore.private, keystore.enclaves):
        path.mkdir(parents=True, exist_ok=True)
    names = [keystore.public / IDENTITY_CA_CERT, keystore.public / PERMISSIONS_CA_CERT,
             keystore.private / IDENTITY_CA_KEY, keystore.private / PERMISSIONS_CA_KEY]
    if not all(p.is_file() for p in names):
        key = _new_key()
        _write(keystore.private / "ca.key.pem", _pem_key(key), private=True)
        _write(keystore.public / "ca.cert.pem", _pem_cert(_certificate(CA_NAME, key)))
        for role in ("identity_ca", "permissions_ca"):
            _link(keystore.public / "ca.cert.pem", keystore.public / f"{role}.cert.pem")
            _link(keystore.private / "ca.key.pem", keystore.private / f"{role}.key.pem")
    governance = keystore.enclaves / GOVERNANCE_XML
    if not governance.is_file():
        _write(governance, documents.governance_xml(domain_id))
    if not (keystore.enclaves / GOVERNANCE).is_file():
        _sign_file(keystore, governance, keystore.enclaves / GOVERNANCE)
    return keystore


def create_enclave(root: Path, enclave: str, domain_id: int = 0, *,
                   validity: datetime.timedelta = VALIDITY,
                   now: datetime.datetime | None = None) -> Path:
    """An enclave's identity (key and certificate, kept if both exist) and its default
    permissions (everything allowed, as SROS2 grants by default); returns its directory."""
    keystore = Keystore(root)
    keystore.require()
    directory = keystore.enclave_dir(enclave)
    directory.mkdir(parents=True, exist_ok=True)
    for name in (IDENTITY_CA_CERT, PERMISSIONS_CA_CERT):
        _link(keystore.public / name, directory / name)
    _link(keystore.enclaves / GOVERNANCE, directory / GOVERNANCE)
    if not ((directory / CERT).is_file() and (directory / KEY).is_file()):
        ca = load_cert(keystore.public / IDENTITY_CA_CERT)
        ca_key = load_key(keystore.private / IDENTITY_CA_KEY)
        key = _new_key()
        cert = _certificate(enclave, key, issuer=ca, issuer_key=ca_key, now=now,
                            validity=validity)
        _write(directory / KEY, _pem_key(key), private=True)
        _write(directory / CERT, _pem_cert(cert))
    write_permissions(keystore, enclave, documents.read_policy(
        documents.default_policy(enclave), enclave), domain_id)
    return directory


def write_permissions(keystore: Keystore, enclave: str, grant: documents.Grant,
                      domain_id: int) -> None:
    """permissions.xml from `grant`, valid as long as the enclave's certificate, and its
    signed permissions.p7s."""
    directory = keystore.enclave_dir(enclave)
    cert = load_cert(directory / CERT)
    xml = documents.permissions_xml(grant, domain_id, cert.not_valid_before_utc,
                                    cert.not_valid_after_utc)
    _write(directory / PERMISSIONS_XML, xml)
    _sign_file(keystore, directory / PERMISSIONS_XML, directory / PERMISSIONS)


def create_permission(root: Path, enclave: str, policy: Path, domain_id: int = 0) -> Path:
    """The enclave's permissions replaced by what an SROS2 policy file grants it."""
    keystore = Keystore(root)
    keystore.require()
    directory = keystore.enclave_dir(enclave)
    if not (directory / CERT).is_file():
        raise KeystoreError(f"no enclave {enclave!r} in {root} (no {directory / CERT}); "
                            f"create it with `rcan-rtps security create-enclave {root} "
                            f"{enclave}`")
    write_permissions(keystore, enclave, documents.read_policy_file(policy, enclave),
                      domain_id)
    return directory


def list_enclaves(root: Path) -> list[str]:
    """The enclaves of a keystore (every directory under enclaves/ with a key), sorted."""
    keystore = Keystore(root)
    keystore.require()
    found = []
    for key in keystore.enclaves.rglob(KEY):
        relative = key.parent.relative_to(keystore.enclaves).as_posix()
        found.append("/" if relative == "." else f"/{relative}")
    return sorted(found)
