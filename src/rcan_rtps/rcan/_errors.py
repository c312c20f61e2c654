"""Errors of the RCAN message layer.

    RcanError
    ├── SchemaValidationError   a body breaks the schema (error_code SCHEMA_VALIDATION_FAILED, path)
    ├── InvalidRuriError        a RURI breaks the profile's grammar (error_code INVALID_RURI)
    └── VersionIncompatibleError  `rcan_version` of a MAJOR this bridge does not speak (§3.5)
"""

from __future__ import annotations


class RcanError(Exception):
    """Base of every error raised by `rcan_rtps.rcan`."""

    error_code: str = "SCHEMA_VALIDATION_FAILED"


class SchemaValidationError(RcanError):
    error_code = "SCHEMA_VALIDATION_FAILED"

    def __init__(self, path: str, detail: str) -> None:
        super().__init__(f"{path}: {detail}")
        self.path = path
        self.detail = detail


class InvalidRuriError(RcanError):
    error_code = "INVALID_RURI"

    def __init__(self, ruri: str, rule: str) -> None:
        super().__init__(f"invalid RURI {ruri!r}: {rule}")
        self.ruri = ruri
        self.rule = rule


class VersionIncompatibleError(RcanError):
    error_code = "VERSION_INCOMPATIBLE"

    def __init__(self, version: str, rule: str, msg_id: str | None = None) -> None:
        super().__init__(f"rcan_version {version!r}: {rule}")
        self.version = version
        self.rule = rule
        self.msg_id = msg_id  # the refused message's, when it had a readable one
