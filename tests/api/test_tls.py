"""TLS and mTLS on 127.0.0.1, with certificates made here: a client certificate's subject CN
names a configured principal, whose role comes from the config, never from the certificate."""

from __future__ import annotations

import datetime as dt
import ipaddress
import ssl
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from rcan_rtps.api import ApiServer, cert_principals, server_ssl_context
from rcan_rtps.governance import ManualClock
from tests.api.apihelpers import Api, auth, make_config

_NOW = dt.datetime.now(dt.timezone.utc)
# The handshake judges a certificate by the real clock, the app by its own (a ManualClock's
# wall time, which may be ahead): a client certificate is good a day past the later of both.
APP_NOW = dt.datetime.fromtimestamp(ManualClock().time(), dt.timezone.utc)
_GOOD_UNTIL = max(_NOW, APP_NOW) + dt.timedelta(days=1)


class _Issued:
    def __init__(self, cert: x509.Certificate, key: ec.EllipticCurvePrivateKey) -> None:
        self.cert = cert
        self.key = key

    def write(self, directory: Path, stem: str) -> tuple[Path, Path]:
        cert_path, key_path = directory / f"{stem}.pem", directory / f"{stem}.key"
        cert_path.write_bytes(self.cert.public_bytes(serialization.Encoding.PEM))
        key_path.write_bytes(self.key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption()))
        key_path.chmod(0o600)  # the bridge refuses a TLS key others may read
        return cert_path, key_path


def _issue(cn: str, issuer: _Issued | None, *, ca: bool = False,
           server: bool = False, not_after: dt.datetime = _GOOD_UNTIL) -> _Issued:
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])
    builder = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(issuer.cert.subject if issuer else name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(_NOW - dt.timedelta(minutes=5))
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )
    if ca:
        builder = builder.add_extension(x509.KeyUsage(
            digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
            key_encipherment=False, data_encipherment=False, key_agreement=False,
            encipher_only=False, decipher_only=False), critical=True)
    else:
        usage = x509.ExtendedKeyUsageOID.SERVER_AUTH if server else \
            x509.ExtendedKeyUsageOID.CLIENT_AUTH
        builder = builder.add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
    if server:
        builder = builder.add_extension(x509.SubjectAlternativeName(
            [x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False)
    signer = issuer.key if issuer else key
    return _Issued(builder.sign(signer, hashes.SHA256()), key)


class Pki:
    def __init__(self, directory: Path) -> None:
        self.dir = directory
        self.ca = _issue("rcan test CA", None, ca=True)
        self.ca_path, _ = self.ca.write(directory, "ca")
        self.server_cert, self.server_key = _issue("127.0.0.1", self.ca, server=True).write(
            directory, "server")
        self.rogue_ca = _issue("rogue CA", None, ca=True)

    def client(self, cn: str, *, rogue: bool = False,
               not_after: dt.datetime = _GOOD_UNTIL) -> tuple[Path, Path]:
        issuer = self.rogue_ca if rogue else self.ca
        return _issue(cn, issuer, not_after=not_after).write(
            self.dir, f"client-{cn}-{int(rogue)}-{not_after.timestamp():.0f}")

    def context(self, client: tuple[Path, Path] | None = None) -> ssl.SSLContext:
        context = ssl.create_default_context(cafile=str(self.ca_path))
        if client is not None:
            context.load_cert_chain(*client)
        return context


@pytest.fixture
def pki(tmp_path: Path) -> Pki:
    (tmp_path / "pki").mkdir()
    return Pki(tmp_path / "pki")


async def _serve(tmp_path: Path, pki: Pki, *, mutual: bool) -> AsyncIterator[tuple[Api, str]]:
    client_ca = f", client_ca: {pki.ca_path}" if mutual else ""
    api = Api(tmp_path, api_extra=f"tls: {{cert: {pki.server_cert}, key: {pki.server_key}"
                                  f"{client_ca}}}")
    app = await api.build()
    tls = api.config.bridge.api.tls
    assert tls is not None
    async with ApiServer(app, host="127.0.0.1", port=0,
                         ssl_context=server_ssl_context(tls)) as server:
        assert server.url.startswith("https://127.0.0.1:")
        yield api, server.url
    await api.close()


@pytest.fixture
async def tls_api(tmp_path: Path, pki: Pki) -> AsyncIterator[tuple[Api, str]]:
    async for served in _serve(tmp_path, pki, mutual=False):
        yield served


@pytest.fixture
async def mtls_api(tmp_path: Path, pki: Pki) -> AsyncIterator[tuple[Api, str]]:
    async for served in _serve(tmp_path, pki, mutual=True):
        yield served


async def _call(url: str, context: ssl.SSLContext, method: str, path: str,
                headers: dict[str, str] | None = None, body: Any = None) -> tuple[int, Any]:
    async with aiohttp.ClientSession() as session, session.request(
            method, url + path, ssl=context, headers=headers, json=body) as resp:
        return resp.status, await resp.json()


async def test_tls_with_bearer(tls_api: tuple[Api, str], pki: Pki) -> None:
    api, url = tls_api
    status, body = await _call(url, pki.context(), "POST", "/api/heartbeat", auth("planner"))
    assert (status, body["principal"]) == (200, "planner")
    # Without client_ca, a certificate names no one.
    context = pki.context(pki.client("ops"))
    status, body = await _call(url, context, "GET", "/api/status")
    assert (status, body["error_code"]) == (401, "UNAUTHENTICATED")
    assert cert_principals(api.config) == {}


async def test_plain_http_to_the_tls_port_fails(tls_api: tuple[Api, str]) -> None:
    _, url = tls_api
    with pytest.raises(aiohttp.ClientError):
        async with aiohttp.ClientSession() as session, session.get(
                url.replace("https", "http") + "/api/status", headers=auth("ops")) as resp:
            await resp.read()


async def test_mtls_certificate_names_the_principal(mtls_api: tuple[Api, str],
                                                    pki: Pki) -> None:
    api, url = mtls_api
    ops = pki.context(pki.client("ops"))
    status, body = await _call(url, ops, "POST", "/api/heartbeat")
    assert (status, body["principal"]) == (200, "ops")
    status, body = await _call(url, ops, "POST", "/api/command", body={"action": "clear_estop"})
    assert status == 200
    entry = api.entry(body["audit_id"])
    assert (entry["principal"], entry["role"]) == ("ops", "OWNER")


async def test_mtls_role_comes_from_config(mtls_api: tuple[Api, str], pki: Pki) -> None:
    api, url = mtls_api
    viewer = pki.context(pki.client("viewer"))
    status, body = await _call(url, viewer, "POST", "/api/command",
                               body={"action": "move", "role": "GUEST"})
    assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES")
    assert api.entry(body["audit_id"])["role"] == "GUEST"
    assert api.dispatcher.calls == []


async def test_mtls_bearer_takes_precedence(mtls_api: tuple[Api, str], pki: Pki) -> None:
    _, url = mtls_api
    ops = pki.context(pki.client("ops"))
    status, body = await _call(url, ops, "POST", "/api/heartbeat", auth("planner"))
    assert (status, body["principal"]) == (200, "planner")
    bad = {"Authorization": "Bearer wrong-token-wrong-token"}
    status, body = await _call(url, ops, "POST", "/api/heartbeat", bad)
    assert (status, body["error_code"]) == (401, "UNAUTHENTICATED")


async def test_mtls_unknown_cn_needs_a_bearer(mtls_api: tuple[Api, str], pki: Pki) -> None:
    _, url = mtls_api
    stranger = pki.context(pki.client("stranger"))
    assert (await _call(url, stranger, "GET", "/api/status"))[0] == 401
    assert (await _call(url, stranger, "GET", "/api/status", auth("viewer")))[0] == 200


@pytest.mark.parametrize("client", ["none", "rogue"])
async def test_mtls_refuses_clients_without_a_trusted_certificate(
        mtls_api: tuple[Api, str], pki: Pki, client: str) -> None:
    api, url = mtls_api
    context = pki.context(None if client == "none" else pki.client("ops", rogue=True))
    with pytest.raises(aiohttp.ClientError):
        await _call(url, context, "POST", "/api/command", auth("ops"), {"action": "stop"})
    assert api.dispatcher.calls == []


def test_cert_principals_follow_the_configured_principals(tmp_path: Path) -> None:
    config = make_config(tmp_path, api_extra="tls: {cert: a.pem, key: a.key, client_ca: c.pem}")
    mapping = cert_principals(config)
    assert mapping["ops"].role.name == "OWNER"
    assert mapping["viewer"].role.name == "GUEST"
    assert mapping["slow"].rate_limit_per_min == 100  # the role's default limit
