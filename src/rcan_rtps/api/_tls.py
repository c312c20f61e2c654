"""TLS for the API, and mTLS: a verified client certificate's subject CN names a principal."""

from __future__ import annotations

import ssl

from rcan_rtps.config import RcanConfig, TlsConfig
from rcan_rtps.governance import Principal
from rcan_rtps.governance.rbac import rate_limits
from rcan_rtps.rcan import Role


def server_ssl_context(tls: TlsConfig) -> ssl.SSLContext:
    """TLS 1.2+ with the configured certificate; with `client_ca`, client certificates are
    required (mTLS) and must chain to that CA."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_cert_chain(tls.cert, tls.key)
    if tls.client_ca is not None:
        context.load_verify_locations(cafile=tls.client_ca)
        context.verify_mode = ssl.CERT_REQUIRED
    return context


def cert_principals(config: RcanConfig) -> dict[str, Principal]:
    """With mTLS on, each configured principal is also reachable by a client certificate whose
    subject CN is the principal's name; its role is the configured one, never the certificate's.
    Without `tls.client_ca` no certificate names anyone."""
    api = config.bridge.api
    if api.tls is None or api.tls.client_ca is None:
        return {}
    limits = rate_limits(config.bridge.rbac)
    found: dict[str, Principal] = {}
    for p in api.principals:
        role = Role[p.role]
        found[p.name] = Principal(p.name, role, p.rate_limit_per_min or limits[role])
    return found
