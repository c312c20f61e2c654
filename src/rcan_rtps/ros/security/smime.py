"""S/MIME signing and checking of DDS-Security documents (governance, permissions).

DDS-Security reads governance.p7s and permissions.p7s as S/MIME "multipart/signed" messages:
the XML as a text/plain part and a detached PKCS#7 signature made by the permissions CA,
exactly what `openssl smime -sign -text` writes (and sros2 through `cryptography`).

`cryptography` signs but has no PKCS#7 verification, so `verify` reads the few DER fields
it needs itself (RFC 5652 SignedData → SignerInfo: digest algorithm, signed attributes,
signature) and checks them with `cryptography`'s primitives. It exists for clear errors
before DDS is asked (Cyclone itself refuses a bad file, saying little): it checks what the
DDS plugins check — the signed text's digest and a signature by the CA or a certificate the
CA issued — and is no general S/MIME implementation.
"""

from __future__ import annotations

import base64
import re
from dataclasses import dataclass

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, padding, rsa
from cryptography.hazmat.primitives.serialization import pkcs7

from .errors import SignatureError

_DIGESTS: dict[str, type[hashes.HashAlgorithm]] = {
    "1.3.14.3.2.26": hashes.SHA1,
    "2.16.840.1.101.3.4.2.1": hashes.SHA256,
    "2.16.840.1.101.3.4.2.2": hashes.SHA384,
    "2.16.840.1.101.3.4.2.3": hashes.SHA512,
}
_SIGNED_DATA = "1.2.840.113549.1.7.2"
_MESSAGE_DIGEST = "1.2.840.113549.1.9.4"


def sign(content: bytes, cert: x509.Certificate,
         key: pkcs7.PKCS7PrivateKeyTypes) -> bytes:
    """`content` as an S/MIME message signed by `cert`/`key` (text/plain, detached, SHA-256)."""
    builder = pkcs7.PKCS7SignatureBuilder().set_data(content).add_signer(
        cert, key, hashes.SHA256())
    return builder.sign(serialization.Encoding.SMIME,
                        [pkcs7.PKCS7Options.Text, pkcs7.PKCS7Options.DetachedSignature])


@dataclass(frozen=True)
class _Tlv:
    tag: int
    start: int  # of the whole element (tag byte)
    body: int  # of its contents
    end: int


def _tlv(data: bytes, at: int) -> _Tlv:
    """The DER element at `at` (definite lengths only: DER has no other)."""
    if at + 2 > len(data):
        raise SignatureError("the signature is cut short")
    tag, first = data[at], data[at + 1]
    body = at + 2
    if first < 0x80:
        length = first
    else:
        count = first & 0x7F
        if count == 0 or count > 4:
            raise SignatureError("the signature is not DER (indefinite or huge length)")
        length = int.from_bytes(data[body:body + count], "big")
        body += count
    if body + length > len(data):
        raise SignatureError("the signature is cut short")
    return _Tlv(tag, at, body, body + length)


def _children(data: bytes, parent: _Tlv) -> list[_Tlv]:
    found, at = [], parent.body
    while at < parent.end:
        child = _tlv(data, at)
        found.append(child)
        at = child.end
    return found


def _oid(data: bytes, element: _Tlv) -> str:
    if element.tag != 0x06:
        raise SignatureError("the signature is not PKCS#7 (an object identifier expected)")
    raw = data[element.body:element.end]
    parts, value = [], 0
    for byte in raw:
        value = (value << 7) | (byte & 0x7F)
        if not byte & 0x80:
            parts.append(value)
            value = 0
    if not parts:
        raise SignatureError("the signature holds an empty object identifier")
    first = min(parts[0] // 40, 2)
    return ".".join(str(p) for p in [first, parts[0] - 40 * first, *parts[1:]])


@dataclass(frozen=True)
class _Signer:
    digest: type[hashes.HashAlgorithm]
    signed_attributes: bytes  # DER, re-tagged as the SET OF that was signed
    message_digest: bytes
    signature: bytes
    certificates: list[x509.Certificate]
    issuer_serial: tuple[bytes, int]


def _signer(der: bytes) -> _Signer:
    content_info = _tlv(der, 0)
    oid, explicit = _children(der, content_info)[:2]
    if _oid(der, oid) != _SIGNED_DATA:
        raise SignatureError("the signature is not PKCS#7 signed data")
    signed_data = _children(der, _children(der, explicit)[0])
    certificates = [x509.load_der_x509_certificate(der[c.start:c.end])
                    for part in signed_data if part.tag == 0xA0
                    for c in _children(der, part)]
    signer_infos = signed_data[-1]
    infos = _children(der, signer_infos)
    if signer_infos.tag != 0x31 or len(infos) != 1:
        raise SignatureError("the signature must have exactly one signer")
    fields = _children(der, infos[0])
    sid, digest_algorithm = fields[1], fields[2]
    issuer, serial = _children(der, sid)[:2]
    digest = _DIGESTS.get(_oid(der, _children(der, digest_algorithm)[0]))
    if digest is None:
        raise SignatureError("the signature uses an unknown digest algorithm")
    attributes = fields[3]
    if attributes.tag != 0xA0:
        raise SignatureError("the signature has no signed attributes")
    message_digest = b""
    for attribute in _children(der, attributes):
        kind, values = _children(der, attribute)[:2]
        if _oid(der, kind) == _MESSAGE_DIGEST:
            value = _children(der, values)[0]
            message_digest = der[value.body:value.end]
    signature = fields[5]
    return _Signer(
        digest=digest,
        signed_attributes=b"\x31" + der[attributes.start + 1:attributes.end],
        message_digest=message_digest,
        signature=der[signature.body:signature.end],
        certificates=certificates,
        issuer_serial=(der[issuer.start:issuer.end],
                       int.from_bytes(der[serial.body:serial.end], "big", signed=True)))


_BOUNDARY = re.compile(rb'boundary="?([^";\r\n]+)"?', re.IGNORECASE)


def split(message: bytes) -> tuple[bytes, bytes]:
    """(the signed MIME part as signed: CRLF line ends, its headers included; the DER
    signature) of an S/MIME multipart/signed message."""
    header_end = re.search(rb"\r?\n\r?\n", message)
    boundary = _BOUNDARY.search(message[:header_end.start()] if header_end else b"")
    if header_end is None or boundary is None:
        raise SignatureError("not an S/MIME signed message (no multipart/signed boundary)")
    delimiter = b"--" + boundary.group(1)
    parts = re.split(rb"(?:\r?\n)?" + re.escape(delimiter) + rb"(?:--)?[ \t]*\r?\n?",
                     message[header_end.end():])
    if len(parts) < 3:
        raise SignatureError("not an S/MIME signed message (fewer than two parts)")
    signed, signature_part = parts[1], parts[2]
    body = re.search(rb"\r?\n\r?\n", signature_part)
    if body is None:
        raise SignatureError("the signature part has no body")
    try:
        der = base64.b64decode(re.sub(rb"\s+", b"", signature_part[body.end():]),
                               validate=True)
    except ValueError as e:
        raise SignatureError("the signature part is not base64") from e
    return re.sub(rb"\r?\n", b"\r\n", signed), der


def signed_text(message: bytes) -> bytes:
    """The document an S/MIME message carries, without its MIME headers (LF line ends)."""
    part, _ = split(message)
    header_end = part.find(b"\r\n\r\n")
    body = part[header_end + 4:] if header_end >= 0 else part
    return body.replace(b"\r\n", b"\n")


def verify(message: bytes, ca: x509.Certificate) -> bytes:
    """Checks that `message` (S/MIME) is signed by `ca` or by a certificate `ca` issued, and
    returns the signed document. Raises SignatureError saying what does not hold."""
    part, der = split(message)
    try:
        signer = _signer(der)
    except (IndexError, ValueError) as e:
        raise SignatureError(f"the signature does not parse as PKCS#7 ({e})") from e
    digest = hashes.Hash(signer.digest())
    digest.update(part)
    if digest.finalize() != signer.message_digest:
        raise SignatureError("the signed text was changed after signing (digest mismatch)")
    cert = _signing_certificate(signer, ca)
    key = cert.public_key()
    try:
        if isinstance(key, ec.EllipticCurvePublicKey):
            key.verify(signer.signature, signer.signed_attributes, ec.ECDSA(signer.digest()))
        elif isinstance(key, rsa.RSAPublicKey):
            key.verify(signer.signature, signer.signed_attributes, padding.PKCS1v15(),
                       signer.digest())
        else:
            raise SignatureError("the signer's key is neither EC nor RSA")
    except InvalidSignature as e:
        raise SignatureError("the signature does not verify with the signer's key") from e
    return signed_text(message)


def _signing_certificate(signer: _Signer, ca: x509.Certificate) -> x509.Certificate:
    """The certificate that signed: `ca` itself, or one it issued that the message carries."""
    ca_id = (ca.issuer.public_bytes(), ca.serial_number)
    if signer.issuer_serial == ca_id:
        return ca
    for cert in signer.certificates:
        if (cert.issuer.public_bytes(), cert.serial_number) == signer.issuer_serial:
            if cert.issuer == cert.subject:  # self-signed: a CA of its own
                raise SignatureError("not signed by this CA but by another one "
                                     f"({cert.subject.rfc4514_string()}, serial "
                                     f"{cert.serial_number:x}): from another keystore?")
            try:
                cert.verify_directly_issued_by(ca)
            except (ValueError, TypeError, InvalidSignature) as e:
                raise SignatureError("signed by a certificate the CA did not issue "
                                     f"({cert.subject.rfc4514_string()})") from e
            return cert
    raise SignatureError("not signed by this CA (the signer is another certificate)")
