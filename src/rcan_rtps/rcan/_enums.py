"""Roles, actions, outcomes and error codes of the rcan-rtps profile."""

from __future__ import annotations

import enum
from typing import Literal


class Role(enum.IntEnum):
    """§12 roles; a higher role can do everything a lower one can.

    RCAN v2's names (`rcan.identity.Role`) are aliases of the role each stands for here — one
    mapping for tokens, JWTs, config and bodies' role claims (docs/rcan-profile.md):
    OPERATOR = USER, ADMIN = OWNER, CONTRIBUTOR = GUEST (its scope is fleet contribution, not
    control), M2M_PEER = USER. `Role["ADMIN"] is Role.OWNER`; names in output are always the
    profile's. LEASEE has no v2 name; M2M_TRUSTED (RRF-issued fleet orchestration) has no
    role here unless `api.jwt.m2m_trusted_role` gives it one.
    """

    GUEST = 1
    USER = 2
    LEASEE = 3
    OWNER = 4
    CREATOR = 5
    OPERATOR = 2
    ADMIN = 4
    CONTRIBUTOR = 1
    M2M_PEER = 2


RoleName = Literal["GUEST", "USER", "LEASEE", "OWNER", "CREATOR"]
# What config and JWT `role` claims may name: the profile's roles and RCAN v2's aliases.
AnyRoleName = Literal["GUEST", "USER", "LEASEE", "OWNER", "CREATOR",
                      "OPERATOR", "ADMIN", "CONTRIBUTOR", "M2M_PEER"]
M2M_TRUSTED = "M2M_TRUSTED"

# JWT `rcan_role` levels (rcan.identity.ROLE_TO_JWT_LEVEL) → the role they stand for; 6.0 is
# M2M_TRUSTED (see Role).
JWT_LEVELS: dict[float, Role] = {1.0: Role.GUEST, 2.0: Role.USER, 2.5: Role.GUEST,
                                 3.0: Role.OWNER, 4.0: Role.USER, 5.0: Role.CREATOR}
M2M_TRUSTED_LEVEL = 6.0


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
    # RCAN 3.x (see docs/rcan-profile.md, "Two generations")
    VERSION_INCOMPATIBLE = "VERSION_INCOMPATIBLE"  # §3.5: rcan_version of another MAJOR
    MESSAGE_STALE = "MESSAGE_STALE"  # §8.3: timestamp outside the replay window
    REPLAY_DETECTED = "REPLAY_DETECTED"  # §8.3: msg_id already seen within the window
    # §16.1: an AI command that does not say which model made it (rcan-spec conformance
    # L3-AI-002's code).
    AUDIT_INCOMPLETE_AI_IDENTITY = "AUDIT_INCOMPLETE_AI_IDENTITY"
    # Signed messages (docs/rcan-profile.md, "Signed messages")
    SIGNATURE_INVALID = "SIGNATURE_INVALID"  # a sig that does not verify with a key of yours
    SIGNATURE_REQUIRED = "SIGNATURE_REQUIRED"  # your policy is `required`: unsigned, or loose


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
    # A review of a held command whose issuer's credential (a JWT's exp, a client
    # certificate's notAfter) ran out while it was held: it is withdrawn, never run.
    ISSUER_CREDENTIAL_EXPIRED = "issuer_credential_expired"
    # An AUTHORIZE whose command_message_id is not the held command's (unsigned; a signed
    # one is SIGNATURE_INVALID `signed_for_another_command`).
    NOT_THE_HELD_COMMAND = "not_the_held_command"
    DISPATCH_ERROR = "dispatch_error"
    AUDIT_UNAVAILABLE = "audit_unavailable"
    NOT_THIS_ROBOT = "not_this_robot"
    ROBOT_SILENT = "robot_silent"
    ESTOP_STATE_UNWRITABLE = "estop_state_unwritable"
    DURATION_LIMIT = "duration_limit"  # duration_s over safety.max_move_duration_s
    # A stop came after the command was decided and before its motion reached the robot.
    STOPPED = "stopped"
    LOWER_PRIORITY = "lower_priority"  # a higher-priority velocity stream is running
    MOTION_LOCKED = "motion_locked"  # a motion lock of a higher priority is engaged
    UNKNOWN_LOCK = "unknown_lock"  # not in bridge.motion.locks
    # A check was handed parameters it cannot read (another type, a field missing): refused.
    PARAMS_NOT_UNDERSTOOD = "params_not_understood"
    # A retried id the audit log shows an earlier run of the bridge decided: its outcome is
    # the log's (that run's memory is gone), and it is not run a second time.
    DECIDED_BEFORE_RESTART = "decided_before_restart"
    AI_MODEL_REQUIRED = "ai_model_required"  # an AI command without `ai.model` (§16.1)
    AI_MODEL_NOT_ALLOWED = "ai_model_not_allowed"  # not one of its agent's `ai.agents` models
