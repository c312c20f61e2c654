"""Errors of the RCAN message layer.

    RcanError
    ├── SchemaValidationError   a body breaks the schema (error_code SCHEMA_VALIDATION_FAILED, path)
    └── InvalidRuriError        a RURI breaks the profile's grammar (error_code INVALID_RURI)
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
