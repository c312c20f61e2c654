"""TLS for the API, and mTLS: a verified client certificate's subject CN names a principal."""

from __future__ import annotations

import ssl
from pathlib import Path

from rcan_rtps.config import RcanConfig, TlsConfig
from rcan_rtps.governance import Principal
from rcan_rtps.governance._durable import (
    WRITABLE_BY_OTHERS,
    foreign_owner_problem,
    regular_stat,
    writable_directory_problem,
)
from rcan_rtps.governance.rbac import rate_limits
from rcan_rtps.rcan import Role

# A TLS key others may read lets them pose as the bridge and collect bearer tokens; one they
# may write, swap it. 0640 stays allowed: a group such as Debian's ssl-cert is the convention.
_TLS_KEY_TOO_OPEN = 0o027


def server_ssl_context(tls: TlsConfig) -> ssl.SSLContext:
    """TLS 1.2+ with the configured certificate; with `client_ca`, client certificates are
    required (mTLS) and must chain to that CA. Raises ValueError for a file that is no regular
    file (a FIFO would hold the start for good) or a key open to others."""
    for key, path in (("cert", tls.cert), ("key", tls.key), ("client_ca", tls.client_ca)):
        if path is not None:
            _check_tls_file(key, path)
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_cert_chain(tls.cert, tls.key)
    if tls.client_ca is not None:
        context.load_verify_locations(cafile=tls.client_ca)
        context.verify_mode = ssl.CERT_REQUIRED
    return context


def _check_tls_file(key: str, path: str) -> None:
    """ValueError, naming the config key, unless `path` is a regular file (and, for the key,
    one that others can neither read nor write). Opened without blocking, as a FIFO's open
    waits for a writer; OSError (missing, unreadable) is left to the caller."""
    try:
        info = regular_stat(Path(path))
    except ValueError as exc:
        raise ValueError(f"bridge.api.tls.{key}: {exc}") from None
    mode = info.st_mode
    owner = foreign_owner_problem(Path(path), info) if key in ("key", "client_ca") else None
    if owner is not None:  # (the certificate is public; whoever swaps it has no key for it)
        raise ValueError(f"bridge.api.tls.{key}: {owner}")
    # (as for the keys the bridge trusts: governance's read_trusted)
    if key == "client_ca" and mode & WRITABLE_BY_OTHERS:
        raise ValueError(f"bridge.api.tls.client_ca: {path} may be written by others (mode "
                         f"{mode & 0o777:o}): whoever can write it can add their own CA, and "
                         "a certificate of theirs would name any principal (chmod go-w)")
    # Whoever may write the directory renames a pair of their own over the key and the
    # certificate: the bridge then serves as them (the certificate alone is public).
    directory = writable_directory_problem(Path(path)) if key != "cert" else None
    if directory is not None:
        raise ValueError(f"bridge.api.tls.{key}: {directory}")
    if key == "key" and mode & _TLS_KEY_TOO_OPEN:
        raise ValueError(f"bridge.api.tls.key: {path} is open to others (mode "
                         f"{mode & 0o777:o}): make it 0600 (or 0640 for a group such as "
                         "ssl-cert)")


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
