"""Errors of SROS2 keystores and secured participants.

    WireError
    └── SecurityError               SROS2 cannot be set up as asked (always says what to do)
        ├── KeystoreError           a keystore or enclave missing, incomplete or not usable
        ├── CertificateError        expired / not yet valid / wrong CA / key not matching
        ├── SignatureError          a signed document (governance, permissions) fails its check
        ├── PolicyError             a policy file that cannot be turned into permissions
        └── SecurityUnavailable     the loaded Cyclone DDS has no DDS-Security
"""

from __future__ import annotations

from ..errors import WireError


class SecurityError(WireError):
    """Base of every SROS2 error."""


class KeystoreError(SecurityError):
    pass


class CertificateError(SecurityError):
    pass


class SignatureError(SecurityError):
    pass


class PolicyError(SecurityError):
    pass


class SecurityUnavailable(SecurityError):
    pass
