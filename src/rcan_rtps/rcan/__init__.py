"""RCAN messages of the rcan-rtps profile: schemas, boundary validation, RURIs.

Public API (everything else is private)::

    validate_command(raw) -> NormalizedCommand     raises SchemaValidationError / InvalidRuriError
    parse_ruri(text) -> Ruri                       raises InvalidRuriError
    openapi_schemas() -> dict                      JSON Schema for OpenAPI components
"""

from ._enums import (
    MOTION_ACTIONS,
    Action,
    ActionName,
    ErrorCode,
    Outcome,
    Reason,
    Role,
    RoleName,
)
from ._errors import InvalidRuriError, RcanError, SchemaValidationError
from ._messages import (
    ActionParams,
    AiInfo,
    ArmJointParams,
    Authorize,
    DecisionBody,
    EnvelopeCommand,
    ErrorBody,
    Fault,
    Joints,
    MoveParams,
    NavigateParams,
    NoParams,
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
from ._validate import convert_at, validate_command, validation_path

__all__ = [
    "MOTION_ACTIONS",
    "Action",
    "ActionName",
    "ActionParams",
    "AiInfo",
    "ArmJointParams",
    "Authorize",
    "DecisionBody",
    "EnvelopeCommand",
    "ErrorBody",
    "ErrorCode",
    "Fault",
    "InvalidRuriError",
    "Joints",
    "MoveParams",
    "NavigateParams",
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
    "convert_at",
    "openapi_schemas",
    "parse_ruri",
    "validate_command",
    "validation_path",
]
