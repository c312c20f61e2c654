"""Which cyclonedds Python binding is installed, and whether the wire layer can run on it.

rcan-rtps runs on the 11.x line of the binding. The 0.10.x line (PyPI's 0.10.5, Debian and
Ubuntu's `python3-cyclonedds`) imports but cannot run us; docs/compatibility.md has the
evidence and why it is refused rather than bridged. The checks look at what the binding
*does*, not at its version string: a patched 0.10 that has the calls passes, an 11 that lost
one fails. None of them opens a participant or sends anything.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .errors import UnsupportedBindingError

SUPPORTED_LINE = "11.x"
PIP_REQUIREMENT = "cyclonedds>=11,<12"
_PROBE_HANDLE = 424242  # any number: the probe below hands it back, nothing is looked up

_STATUS_GETTERS = (
    ("pub", "DataWriter", "get_publication_matched_status"),
    ("pub", "DataWriter", "get_offered_incompatible_qos_status"),
    ("sub", "DataReader", "get_subscription_matched_status"),
    ("sub", "DataReader", "get_requested_incompatible_qos_status"),
)
_MATCHED_CALLS = (
    ("pub", "DataWriter", "get_matched_subscriptions"),
    ("pub", "DataWriter", "get_matched_subscription_data"),
    ("sub", "DataReader", "get_matched_publications"),
    ("sub", "DataReader", "get_matched_publication_data"),
)


def binding_version() -> str:
    """The installed binding's distribution version ('unknown' without pip's metadata)."""
    # Here, not at import: importlib.metadata loads csv, zipfile and importlib.resources,
    # which a run never needs (~0.5 MB; tests/interop/test_run_imports.py).
    import importlib.metadata

    try:
        return importlib.metadata.version("cyclonedds")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def binding_location() -> str:
    import cyclonedds

    return str(Path(cyclonedds.__file__).parent)


def missing_features() -> list[str]:
    """What the installed binding lacks of what the wire layer calls (empty: it is usable)."""
    missing: list[str] = []
    for check in (_byte_type, _status_getters, _instance_handle, _take_with_mask,
                  _matched_calls):
        missing.extend(check())
    return missing


def require_supported_binding() -> None:
    """Raises UnsupportedBindingError naming the version, what is missing and the way to
    the supported line, when the wire layer cannot run on the installed binding."""
    missing = missing_features()
    if missing:
        raise UnsupportedBindingError(binding_version(), binding_location(), missing)


def _byte_type() -> list[str]:
    from cyclonedds.idl import types

    # octet must stay a type of its own: the XTypes information Cyclone sends for it is
    # TK_BYTE, for uint8 TK_UINT8 (0.10 announces both as TK_BYTE)
    return [] if hasattr(types, "byte") else ["cyclonedds.idl.types.byte (the octet type)"]


def _status_getters() -> list[str]:
    return [f"{cls}.{name}()" for cls, name in _absent(_STATUS_GETTERS)]


def _matched_calls() -> list[str]:
    return [f"{cls}.{name}()" for cls, name in _absent(_MATCHED_CALLS)]


def _absent(calls: tuple[tuple[str, str, str], ...]) -> list[tuple[str, str]]:
    import importlib

    found = []
    for module, cls, name in calls:
        owner = getattr(importlib.import_module(f"cyclonedds.{module}"), cls)
        if not callable(getattr(owner, name, None)):
            found.append((cls, name))
    return found


class _HandleProbe:
    """Stands in for an entity: `Entity.get_instance_handle` calls its C function through
    `self._get_instance_handle(self._ref, byref(handle))`, which this one answers."""

    _ref = 0

    def _get_instance_handle(self, _ref: int, pointer: Any) -> int:
        pointer._obj.value = _PROBE_HANDLE
        return 0


def _instance_handle() -> list[str]:
    """0.10's `get_instance_handle` returns `int(c_int64)`, which raises (or misreads the
    bytes); 11 returns the handle. The real method runs, on a stand-in entity."""
    from cyclonedds.core import Entity

    method: Callable[[Any], Any] = Entity.get_instance_handle
    try:
        ok = method(_HandleProbe()) == _PROBE_HANDLE
    except (TypeError, ValueError, AttributeError, ctypes.ArgumentError):
        ok = False
    return [] if ok else ["Entity.get_instance_handle() returning the handle"]


def _take_with_mask() -> list[str]:
    """ros/raw_cdr.py takes with a sample-state mask: `ddspy_take(reader, mask, n)`. Asked of
    entity 0, which is no entity, 11 answers an error code; 0.10's two-argument call raises
    TypeError. A binding without the private call at all is fine (raw_cdr falls back to the
    public API)."""
    try:
        from cyclonedds._clayer import ddspy_take
    except ImportError:
        return []
    try:
        answer = ddspy_take(0, 0, 1)
    except TypeError:
        return ["_clayer.ddspy_take(reader, mask, n) (a take with a sample-state mask)"]
    return [] if isinstance(answer, (int, list)) else [
        "_clayer.ddspy_take(reader, mask, n) answering samples or an error code"]
