"""Roles, actions, outcomes and error codes of the rcan-rtps profile."""

from __future__ import annotations

import enum
from typing import Literal


class Role(enum.IntEnum):
    """§12 roles; a higher role can do everything a lower one can."""

    GUEST = 1
    USER = 2
    LEASEE = 3
    OWNER = 4
    CREATOR = 5


RoleName = Literal["GUEST", "USER", "LEASEE", "OWNER", "CREATOR"]


class Outcome(str, enum.Enum):
    EXECUTED = "executed"
    PENDING_AUTH = "pending_auth"
    DENIED = "denied"
    SAFETY_VIOLATION = "safety_violation"
    FAILED = "failed"


class ErrorCode(str, enum.Enum):
    SCHEMA_VALIDATION_FAILED = "SCHEMA_VALIDATION_FAILED"
    UNAUTHENTICATED = "UNAUTHENTICATED"
    INSUFFICIENT_PRIVILEGES = "INSUFFICIENT_PRIVILEGES"
    COMMAND_REJECTED = "COMMAND_REJECTED"
    RATE_LIMITED = "RATE_LIMITED"
    ROBOT_UNAVAILABLE = "ROBOT_UNAVAILABLE"
    PAYLOAD_TOO_LARGE = "PAYLOAD_TOO_LARGE"
    INVALID_RURI = "INVALID_RURI"
    MESSAGE_ID_CONFLICT = "MESSAGE_ID_CONFLICT"


class Reason(str, enum.Enum):
    """COMMAND_REJECTED reasons of the profile, plus the ones docs/governance.md adds."""

    VELOCITY_LIMIT = "velocity_limit"
    ESTOP_ACTIVE = "estop_active"
    WORKSPACE_VIOLATION = "workspace_violation"
    JOINT_GROUP_VIOLATION = "joint_group_violation"
    CONFIDENCE_BELOW_GATE = "confidence_below_gate"
    INVALID_VALUE = "invalid_value"
    SAFETY_CHECK_ERROR = "safety_check_error"
    PENDING_NOT_FOUND = "pending_not_found"
    PENDING_EXPIRED = "pending_expired"
    SELF_APPROVAL = "self_approval"
    HITL_DENIED = "hitl_denied"
    HITL_WITHDRAWN = "hitl_withdrawn"  # the issuer (or an approver) took it back
    ALREADY_APPROVED = "already_approved"  # an approver's second approval counts once
    DISPATCH_ERROR = "dispatch_error"
    AUDIT_UNAVAILABLE = "audit_unavailable"
    NOT_THIS_ROBOT = "not_this_robot"
    ROBOT_SILENT = "robot_silent"
    ESTOP_STATE_UNWRITABLE = "estop_state_unwritable"
    DURATION_LIMIT = "duration_limit"  # duration_s over safety.max_move_duration_s
    LOWER_PRIORITY = "lower_priority"  # a higher-priority velocity stream is running
    MOTION_LOCKED = "motion_locked"  # a motion lock of a higher priority is engaged
    UNKNOWN_LOCK = "unknown_lock"  # not in bridge.motion.locks
    # A check was handed parameters it cannot read (another type, a field missing): refused.
    PARAMS_NOT_UNDERSTOOD = "params_not_understood"
