"""RCAN messages of the rcan-rtps profile: schemas, boundary validation, RURIs.

Public API (everything else is private)::

    validate_command(raw) -> NormalizedCommand     raises SchemaValidationError / InvalidRuriError
                                                   / VersionIncompatibleError
    validate_message(raw) -> a message            the same, HEARTBEAT, INVOKE, INVOKE_CANCEL and
                                                   AUTHORIZE included (`_invoke`)
    invoke_command(invoke, action, params) -> NormalizedCommand   what an INVOKE's skill runs
    reply_id(raw) -> str | None                    the msg_id a refusal of a 3.x body echoes
    decode_object(raw) -> dict                     a JSON object with unique keys, else
                                                   SchemaValidationError
    parse_ruri(text) -> Ruri                       raises InvalidRuriError
    openapi_schemas() -> dict                      JSON Schema for OpenAPI components
"""

from ._enums import (
    JWT_LEVELS,
    M2M_TRUSTED,
    M2M_TRUSTED_LEVEL,
    AnyRoleName,
    ErrorCode,
    Outcome,
    Reason,
    Role,
    RoleName,
)
from ._errors import (
    InvalidRuriError,
    RcanError,
    SchemaValidationError,
    VersionIncompatibleError,
)
from ._invoke import (
    Authorization,
    Invoke,
    InvokeCancel,
    InvokeResult,
    InvokeStatus,
    skill_error,
)
from ._messages import (
    AiInfo,
    Approval,
    Authorize,
    Capability,
    DecisionBody,
    EnvelopeCommand,
    ErrorBody,
    Fault,
    ForeignPublisher,
    Joints,
    Navigation,
    NormalizedCommand,
    PendingAuth,
    Position,
    RobotPosition,
    RosInfo,
    ShortCommand,
    Status,
    Telemetry,
    Velocity,
    invoke_caps,
)
from ._ruri import RobotId, Ruri, parse_ruri
from ._schema import openapi_schemas
from ._types import ActionParams, whole
from ._v3 import SPOKEN, STATUS_OF, Envelope, Heartbeat, RcanCommand, Signature
from ._validate import (
    convert_at,
    decode_object,
    invoke_command,
    reply_id,
    validate_command,
    validate_message,
    validation_path,
)
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
    "JWT_LEVELS",
    "M2M_TRUSTED",
    "M2M_TRUSTED_LEVEL",
    "SPOKEN",
    "STATUS_OF",
    "ActionName",
    "ActionParams",
    "ActionSpec",
    "AiInfo",
    "AnyRoleName",
    "Approval",
    "ArmJointParams",
    "Authorization",
    "Authorize",
    "Capability",
    "DecisionBody",
    "Effect",
    "Envelope",
    "EnvelopeCommand",
    "ErrorBody",
    "ErrorCode",
    "Fault",
    "ForeignPublisher",
    "GateableName",
    "Heartbeat",
    "InvalidRuriError",
    "Invariant",
    "Invoke",
    "InvokeCancel",
    "InvokeResult",
    "InvokeStatus",
    "Joints",
    "MoveParams",
    "NavigateParams",
    "Navigation",
    "NoParams",
    "NormalizedCommand",
    "Outcome",
    "PendingAuth",
    "Position",
    "RcanCommand",
    "RcanError",
    "Reason",
    "RobotId",
    "RobotPosition",
    "Role",
    "RoleName",
    "RosInfo",
    "Ruri",
    "SchemaValidationError",
    "ShortCommand",
    "Signature",
    "Status",
    "Telemetry",
    "Velocity",
    "VersionIncompatibleError",
    "action_spec",
    "convert_at",
    "decode_object",
    "invoke_caps",
    "invoke_command",
    "openapi_schemas",
    "parse_ruri",
    "reply_id",
    "skill_error",
    "validate_command",
    "validate_message",
    "validation_path",
    "whole",
]
