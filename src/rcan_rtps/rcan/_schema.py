"""JSON Schema of the RCAN messages, ready for an OpenAPI `components.schemas` block."""

from __future__ import annotations

from typing import Any

import msgspec

from ._messages import (
    ArmJointParams,
    Authorize,
    DecisionBody,
    EnvelopeCommand,
    ErrorBody,
    MoveParams,
    NavigateParams,
    NoParams,
    PendingAuth,
    ShortCommand,
    Status,
)

_TYPES: tuple[type[msgspec.Struct], ...] = (
    ShortCommand,
    EnvelopeCommand,
    MoveParams,
    ArmJointParams,
    NavigateParams,
    NoParams,
    Status,
    PendingAuth,
    Authorize,
    DecisionBody,
    ErrorBody,
)
_REF = "#/components/schemas/{name}"


def openapi_schemas() -> dict[str, Any]:
    """Every message schema, keyed by name, with `$ref`s pointing into components/schemas."""
    _, components = msgspec.json.schema_components(_TYPES, ref_template=_REF)
    return components
