"""RCAN messages of the rcan-rtps profile: schemas, boundary validation, RURIs.

Public API (everything else is private)::

    validate_command(raw) -> NormalizedCommand     raises SchemaValidationError / InvalidRuriError
    decode_object(raw) -> dict                     a JSON object with unique keys, else
                                                   SchemaValidationError
    parse_ruri(text) -> Ruri                       raises InvalidRuriError
    openapi_schemas() -> dict                      JSON Schema for OpenAPI components
"""

from ._enums import (
    ErrorCode,
    Outcome,
    Reason,
    Role,
    RoleName,
)
from ._errors import InvalidRuriError, RcanError, SchemaValidationError
from ._messages import (
    AiInfo,
    Approval,
    Authorize,
    DecisionBody,
    EnvelopeCommand,
    ErrorBody,
    Fault,
    Joints,
    Navigation,
    NormalizedCommand,
    PendingAuth,
    Position,
    RosInfo,
    ShortCommand,
    Status,
    Telemetry,
    Velocity,
)
from ._ruri import Ruri, parse_ruri
from ._schema import openapi_schemas
from ._types import ActionParams
from ._validate import convert_at, decode_object, validate_command, validation_path
from .actions import (
    ACTIONS,
    ActionName,
    ActionSpec,
    ArmJointParams,
    Effect,
    GateableName,
    Invariant,
    MoveParams,
    NavigateParams,
    NoParams,
    action_spec,
)

__all__ = [
    "ACTIONS",
    "ActionName",
    "ActionParams",
    "ActionSpec",
    "AiInfo",
    "Approval",
    "ArmJointParams",
    "Authorize",
    "DecisionBody",
    "Effect",
    "EnvelopeCommand",
    "ErrorBody",
    "ErrorCode",
    "Fault",
    "GateableName",
    "InvalidRuriError",
    "Invariant",
    "Joints",
    "MoveParams",
    "NavigateParams",
    "Navigation",
    "NoParams",
    "NormalizedCommand",
    "Outcome",
    "PendingAuth",
    "Position",
    "RcanError",
    "Reason",
    "Role",
    "RoleName",
    "RosInfo",
    "Ruri",
    "SchemaValidationError",
    "ShortCommand",
    "Status",
    "Telemetry",
    "Velocity",
    "action_spec",
    "convert_at",
    "decode_object",
    "openapi_schemas",
    "parse_ruri",
    "validate_command",
    "validation_path",
]
