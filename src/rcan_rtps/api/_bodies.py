"""Response bodies the API adds to the RCAN messages, and JSON response helpers."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

import msgspec
from aiohttp import web

from rcan_rtps.governance import AuditError
from rcan_rtps.rcan import Capability, DecisionBody, ErrorCode, PendingAuth, Reason

from .ports import GoalView

JSON = "application/json"


class ApiError(msgspec.Struct, kw_only=True, omit_defaults=True):
    """A request refused before (or outside) a decision: 400, 401, 403, 404, 413, 503.

    Like `rcan.ErrorBody`, but `outcome` is always present (the profile: every body has one;
    ErrorBody's default would be omitted when encoded).
    """

    outcome: Literal["denied", "failed"]
    error_code: str
    reason: str | None = None
    path: str | None = None
    audit_id: str | None = None
    message_id: str | None = None  # when the refused body had one (matches WebSocket replies)
    # A refused message of the RCAN 3.x generation: its id, and `outcome` as its status.
    msg_id: str | None = None
    status: Literal["ok", "pending", "blocked", "error"] | None = None


class GoalList(msgspec.Struct, kw_only=True):
    goals: list[GoalView]


class SkillView(msgspec.Struct, kw_only=True):
    """One skill of `bridge.skills`, as an INVOKE runs it."""

    action: str  # the registry action it runs
    role: str  # the lowest role that may invoke it: its action's (rbac)
    params: dict[str, Any]  # always run with these
    allow: list[str]  # the parameters an INVOKE may set
    description: str = ""


class SkillList(msgspec.Struct, kw_only=True):
    """GET /api/skills: §18's Capability Object Map with the `invoke` capability (§19.7: its
    `params.skills` lists every skill an INVOKE may name), and each skill's declaration."""

    caps: dict[str, Capability]
    skills: dict[str, SkillView]


class PendingList(msgspec.Struct, kw_only=True):
    pending: list[PendingAuth]


class PendingView(msgspec.Struct, kw_only=True, omit_defaults=True):
    """GET /api/hitl/pending/{pending_id}, for its issuer and its approvers: its PENDING_AUTH
    (`pending`, with the approvals it had) and its `state` — `pending` while it waits,
    `resolving` while the last approval runs it, `resolved` with the `decision` that ended it
    (executed, denied: `hitl_denied`, `hitl_withdrawn`, `pending_expired`, or refused)."""

    pending_id: str
    state: Literal["pending", "resolving", "resolved"]
    pending: PendingAuth
    decision: DecisionBody | None = None



class HeartbeatAck(msgspec.Struct, kw_only=True):
    ok: bool = True
    principal: str
    timestamp_ms: int


class CommandCancelAck(msgspec.Struct, kw_only=True, omit_defaults=True):
    """POST /api/command/cancel: whether any of the principal's motion was stopped (it was on
    its way or running), and then that stop's decision (its audit entry's id); and the
    pending ids of its motion held for a human that was withdrawn (HITL_WITHDRAWN: it never
    runs), when there was any — `stopped` stays false for those alone: nothing moved."""

    principal: str
    stopped: bool
    decision: DecisionBody | None = None
    withdrawn: list[str] = msgspec.field(default_factory=list)


class HeartbeatReply(msgspec.Struct, kw_only=True, omit_defaults=True):
    """A HEARTBEAT message's reply (POST /api/command, the WebSocket): HeartbeatAck's fields
    with the message's id and an RCAN 3.x status."""

    ok: bool
    principal: str
    timestamp_ms: int
    status: Literal["ok"]
    msg_id: str | None = None


class AuditPage(msgspec.Struct, kw_only=True):
    """Entries with seq > `since`, verbatim (canonical JSON, so each can be re-verified): up
    to `limit` and `_reads.PAGE_BYTES` of them (one larger entry is a page alone); the next
    page is `since=next_since`."""

    entries: list[dict[str, Any]]
    next_since: int
    head_seq: int


class VerifyReport(msgspec.Struct, kw_only=True, omit_defaults=True):
    ok: bool
    count: int | None = None
    last_seq: int | None = None
    last_audit_id: str | None = None
    bad_seq: int | None = None
    detail: str | None = None
    # The signed tree heads beside the log (RFC 6962 style) that match its entries, and the
    # largest tree they cover; a head that does not match is a problem like a broken chain.
    tree_heads: int | None = None
    tree_size: int | None = None
    problems: list[str] | None = None


class WsFrame(msgspec.Struct, kw_only=True, omit_defaults=True):
    """One WebSocket text frame from the bridge: a STATUS, a command's outcome, a goal's change,
    the held commands (approvers only)."""

    type: Literal["status", "outcome", "goal", "approvals"]
    body: Any
    http_status: int | None = None


def json_response(body: Any, status: int = 200,
                  headers: Mapping[str, str] | None = None) -> web.Response:
    return web.Response(body=msgspec.json.encode(body), status=status, content_type=JSON,
                        headers=headers)


def error_body(code: ErrorCode | str, *, reason: str | None = None, path: str | None = None,
               audit_id: str | None = None, outcome: Literal["denied", "failed"] = "denied",
               message_id: str | None = None) -> ApiError:
    value = code.value if isinstance(code, ErrorCode) else code
    return ApiError(outcome=outcome, error_code=value, reason=reason, path=path,
                    audit_id=audit_id, message_id=message_id)


def failure_reply(exc: Exception) -> tuple[int, ApiError]:
    """What an unexpected exception is answered with: 503, never 500.

    Without an audit log nothing may run unrecorded, so the bridge is unavailable
    (COMMAND_REJECTED `audit_unavailable`); anything else is ROBOT_UNAVAILABLE `internal_error`.
    """
    if isinstance(exc, AuditError):
        return 503, error_body(ErrorCode.COMMAND_REJECTED, outcome="failed",
                               reason=Reason.AUDIT_UNAVAILABLE.value)
    return 503, error_body(ErrorCode.ROBOT_UNAVAILABLE, outcome="failed",
                           reason="internal_error")


def error_response(status: int, code: ErrorCode | str, *, reason: str | None = None,
                   path: str | None = None, audit_id: str | None = None,
                   outcome: Literal["denied", "failed"] = "denied",
                   headers: Mapping[str, str] | None = None) -> web.Response:
    body = error_body(code, reason=reason, path=path, audit_id=audit_id, outcome=outcome)
    return json_response(body, status, headers)
