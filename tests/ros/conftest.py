"""Fixtures shared by the wire layer's tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from rcan_rtps.ros.security import keystore
from tests.ros.security_store import ENCLAVE


@pytest.fixture
def store(tmp_path: Path) -> Path:
    """A keystore with one enclave (domain 7), as the security tests start from."""
    root = tmp_path / "ks"
    keystore.create_keystore(root, domain_id=7)
    keystore.create_enclave(root, ENCLAVE, domain_id=7)
    return root
