"""The profile's outcome table in one place: each refusal with its HTTP status and outcome."""

from __future__ import annotations

import msgspec

from rcan_rtps.rcan import ErrorCode, Outcome, Reason


class Rejection(msgspec.Struct, frozen=True):
    http_status: int
    outcome: Outcome
    error_code: ErrorCode
    reason: str | None = None

    @property
    def deny_reason(self) -> str:
        """How the audit entry names it: the code, and the reason when there is one."""
        code = self.error_code.value
        return f"{code}:{self.reason}" if self.reason else code


def _rejected(reason: Reason, outcome: Outcome = Outcome.DENIED, status: int = 409) -> Rejection:
    return Rejection(status, outcome, ErrorCode.COMMAND_REJECTED, reason.value)


D, S = Outcome.DENIED, Outcome.SAFETY_VIOLATION

UNAUTHENTICATED = Rejection(401, D, ErrorCode.UNAUTHENTICATED)
SELF_APPROVAL = Rejection(403, D, ErrorCode.INSUFFICIENT_PRIVILEGES, Reason.SELF_APPROVAL.value)
RATE_LIMITED = Rejection(429, D, ErrorCode.RATE_LIMITED)


def privileges(reason: str) -> Rejection:
    """403 INSUFFICIENT_PRIVILEGES saying what was needed (the role, never a credential)."""
    return Rejection(403, D, ErrorCode.INSUFFICIENT_PRIVILEGES, reason)


PAYLOAD_TOO_LARGE = Rejection(413, D, ErrorCode.PAYLOAD_TOO_LARGE)
# A command whose params its audit entry could not hold whole (`entry_bound`): refused before
# it runs rather than run with its params left out of the record.
PARAMS_TOO_LARGE_TO_LOG = Rejection(413, D, ErrorCode.PAYLOAD_TOO_LARGE,
                                    "params_too_large_to_log")
NOT_THIS_ROBOT = Rejection(400, D, ErrorCode.INVALID_RURI, Reason.NOT_THIS_ROBOT.value)
ROBOT_UNAVAILABLE = Rejection(503, Outcome.FAILED, ErrorCode.ROBOT_UNAVAILABLE)
DISPATCH_ERROR = Rejection(
    503, Outcome.FAILED, ErrorCode.ROBOT_UNAVAILABLE, Reason.DISPATCH_ERROR.value
)
AUDIT_UNAVAILABLE = Rejection(
    503, Outcome.FAILED, ErrorCode.COMMAND_REJECTED, Reason.AUDIT_UNAVAILABLE.value
)
MESSAGE_ID_CONFLICT = Rejection(409, D, ErrorCode.MESSAGE_ID_CONFLICT)
DECIDED_BEFORE_RESTART = Rejection(409, D, ErrorCode.MESSAGE_ID_CONFLICT,
                                   Reason.DECIDED_BEFORE_RESTART.value)
# An arm is held by the message id of the command that sent it; ids are unique per principal.
ID_OF_ANOTHER_S_ARM = Rejection(409, D, ErrorCode.MESSAGE_ID_CONFLICT,
                                "message_id_of_another_principal_s_running_arm")
ESTOP_STATE_UNWRITABLE = Rejection(
    503, Outcome.FAILED, ErrorCode.COMMAND_REJECTED, Reason.ESTOP_STATE_UNWRITABLE.value
)
VELOCITY_LIMIT = _rejected(Reason.VELOCITY_LIMIT, S)
WORKSPACE_VIOLATION = _rejected(Reason.WORKSPACE_VIOLATION, S)
JOINT_GROUP_VIOLATION = _rejected(Reason.JOINT_GROUP_VIOLATION, S)
INVALID_VALUE = _rejected(Reason.INVALID_VALUE, S)
ESTOP_ACTIVE = _rejected(Reason.ESTOP_ACTIVE)
STOPPED = _rejected(Reason.STOPPED)
DURATION_LIMIT = _rejected(Reason.DURATION_LIMIT, S)
LOWER_PRIORITY = _rejected(Reason.LOWER_PRIORITY)
MOTION_LOCKED = _rejected(Reason.MOTION_LOCKED)
UNKNOWN_LOCK = _rejected(Reason.UNKNOWN_LOCK)
CONFIDENCE_BELOW_GATE = _rejected(Reason.CONFIDENCE_BELOW_GATE)
SAFETY_CHECK_ERROR = _rejected(Reason.SAFETY_CHECK_ERROR)
PARAMS_NOT_UNDERSTOOD = _rejected(Reason.PARAMS_NOT_UNDERSTOOD)
PENDING_NOT_FOUND = _rejected(Reason.PENDING_NOT_FOUND, status=404)
PENDING_EXPIRED = _rejected(Reason.PENDING_EXPIRED, status=404)
HITL_DENIED = _rejected(Reason.HITL_DENIED, status=200)
HITL_WITHDRAWN = _rejected(Reason.HITL_WITHDRAWN, status=200)
ALREADY_APPROVED = _rejected(Reason.ALREADY_APPROVED)
ISSUER_CREDENTIAL_EXPIRED = _rejected(Reason.ISSUER_CREDENTIAL_EXPIRED)
# A review whose `command_message_id` is not the held command's (governance.review): signed,
# its signature is for another command; unsigned, it names another.
SIGNED_FOR_ANOTHER_COMMAND = Rejection(403, D, ErrorCode.SIGNATURE_INVALID,
                                       "signed_for_another_command")
NOT_THE_HELD_COMMAND = _rejected(Reason.NOT_THE_HELD_COMMAND)


# §16.1 AI accountability (governance.ai).
AI_MODEL_REQUIRED = Rejection(400, D, ErrorCode.AUDIT_INCOMPLETE_AI_IDENTITY,
                              Reason.AI_MODEL_REQUIRED.value)
AI_MODEL_NOT_ALLOWED = Rejection(403, D, ErrorCode.INSUFFICIENT_PRIVILEGES,
                                 Reason.AI_MODEL_NOT_ALLOWED.value)


def robot_unavailable(detail: str | None) -> Rejection:
    return Rejection(503, Outcome.FAILED, ErrorCode.ROBOT_UNAVAILABLE, detail)


# RCAN 3.x: §3.5 versions, §8.3 replay window (the profile's "Two generations").
MESSAGE_STALE = Rejection(408, D, ErrorCode.MESSAGE_STALE)
REPLAY_DETECTED = Rejection(409, D, ErrorCode.REPLAY_DETECTED)


def version_incompatible(rule: str) -> Rejection:
    return Rejection(400, D, ErrorCode.VERSION_INCOMPATIBLE, rule)


def schema_failed(path: str) -> Rejection:
    return Rejection(400, D, ErrorCode.SCHEMA_VALIDATION_FAILED, path)


def invalid_ruri(rule: str) -> Rejection:
    return Rejection(400, D, ErrorCode.INVALID_RURI, rule)
