"""JSON Schema of the RCAN messages, ready for an OpenAPI `components.schemas` block."""

from __future__ import annotations

from typing import Any

import msgspec

from ._invoke import (
    AuthorizeMessage,
    InvokeCancelMessage,
    InvokeMessage,
    InvokeResult,
    SignedAuthorizeMessage,
)
from ._messages import (
    Authorize,
    DecisionBody,
    EnvelopeCommand,
    ErrorBody,
    PendingAuth,
    SafetyMessage,
    ShortCommand,
    Status,
)
from ._v3 import HeartbeatMessage, RcanCommand
from .actions import specs

_TYPES: tuple[type[msgspec.Struct], ...] = (
    ShortCommand,
    EnvelopeCommand,
    RcanCommand,  # the rcan SDK's COMMAND, and its SAFETY; HEARTBEAT (docs/rcan-profile.md)
    SafetyMessage,
    HeartbeatMessage,
    InvokeMessage,  # §19, and AUTHORIZE (§16.4): also command bodies
    InvokeCancelMessage,
    AuthorizeMessage,
    SignedAuthorizeMessage,  # AUTHORIZE in the SDK's envelope, which may be signed
    InvokeResult,
    *dict.fromkeys(spec.params for spec in specs()),  # each parameter type once
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
