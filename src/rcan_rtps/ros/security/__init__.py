"""SROS2 for rcan-rtps: keystores made without ROS, and DDS-Security for our participants.

`keystore` makes and reads the keystore layout of `ros2 security`; `documents` the
governance and permissions XML; `smime` signs and checks them; `settings` turns the
ROS_SECURITY_* environment into a secured participant's settings, as rcl and
rmw_cyclonedds do. `RosNode` applies it (ros/participant.py): nothing to call by hand.
"""

from .errors import (
    CertificateError,
    KeystoreError,
    PolicyError,
    SecurityError,
    SecurityUnavailable,
    SignatureError,
)
from .keystore import Keystore, create_enclave, create_keystore, create_permission, list_enclaves
from .settings import (
    EnclaveFiles,
    SecurityRequest,
    check,
    cyclone_has_security,
    participant_security,
    request_from_env,
)

__all__ = [
    "CertificateError",
    "EnclaveFiles",
    "Keystore",
    "KeystoreError",
    "PolicyError",
    "SecurityError",
    "SecurityRequest",
    "SecurityUnavailable",
    "SignatureError",
    "check",
    "create_enclave",
    "create_keystore",
    "create_permission",
    "cyclone_has_security",
    "list_enclaves",
    "participant_security",
    "request_from_env",
]
