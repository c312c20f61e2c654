"""GET /api/openapi.json: an OpenAPI 3.1 document built from the msgspec schemas."""

from __future__ import annotations

from typing import Any

import msgspec

from rcan_rtps import __version__
from rcan_rtps.governance.thoughts import Thought
from rcan_rtps.rcan import openapi_schemas

from ._bodies import (
    ApiError,
    AuditPage,
    CommandCancelAck,
    GoalList,
    HeartbeatAck,
    PendingList,
    PendingView,
    SkillList,
    VerifyReport,
    WsFrame,
)
from ._console_pages import WhoAmI
from ._protocol import HEAD_TOO_LARGE, MAX_FIELDS, MAX_LINE
from ._tickets import TicketReply
from .ports import GoalView

_REF = "#/components/schemas/{name}"

_API_TYPES: tuple[type[msgspec.Struct], ...] = (
    ApiError, GoalView, GoalList, PendingList, PendingView, HeartbeatAck, AuditPage, VerifyReport,
    WsFrame, SkillList, CommandCancelAck,
    Thought, WhoAmI, TicketReply,
)


def _ref(name: str) -> dict[str, str]:
    return {"$ref": _REF.format(name=name)}


def _json(name: str, description: str) -> dict[str, Any]:
    return {"description": description, "content": {"application/json": {"schema": _ref(name)}}}


_HEAD_TOO_LARGE = (f"request line or a header field over {MAX_LINE} bytes, or more than "
                   f"{MAX_FIELDS} header fields ({HEAD_TOO_LARGE}; not audited)")


def _errors(*codes: int) -> dict[str, Any]:
    text = {400: "body or query fails the schema (field path in `path`)",
            401: "no or invalid credentials", 403: "role too low",
            404: "not found", 409: "refused by a safety invariant or the e-stop",
            422: "cannot be shown",
            413: "body too large", 429: "rate limited", 431: _HEAD_TOO_LARGE,
            503: "robot or audit log unavailable"}
    return {str(c): _json("ApiError", text[c]) for c in (401, *codes, 431, 503)}


_COMMAND_BODY = {
    "required": True,
    "content": {"application/json": {"schema": {
        "oneOf": [_ref("ShortCommand"), _ref("EnvelopeCommand"), _ref("RcanCommand"),
                  _ref("SafetyMessage"), _ref("HeartbeatMessage"), _ref("InvokeMessage"),
                  _ref("InvokeCancelMessage"), _ref("AuthorizeMessage"),
                  _ref("SignedAuthorizeMessage")]}}},
}
_AUTHORIZE_BODY = {"required": True,
                   "content": {"application/json": {"schema": _ref("Authorize")}}}
_DECISION = {
    **{str(c): _json("DecisionBody", d) for c, d in (
        (200, "executed (possibly clamped; see `applied`)"), (202, "waiting for a human"),
        (403, "role too low (audited)"), (409, "refused by an invariant (audited)"),
        (413, "body too large (audited)"), (429, "rate limited (audited)"),
        (503, "robot unreachable, or audit unavailable"))},
    "400": _json("ApiError", "schema failure, with the field path (audited)"),
    "401": _json("ApiError", "no or invalid credentials (not audited); a refused JWT says why "
                 "in `reason`"),
    "431": _json("ApiError", _HEAD_TOO_LARGE),
}


def _op(op_id: str, summary: str, responses: dict[str, Any],
        body: dict[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
    op: dict[str, Any] = {"operationId": op_id, "summary": summary, "responses": responses}
    if body is not None:
        op["requestBody"] = body
    op.update(extra)
    return op


_MCP_DOC = ("MCP (streamable HTTP, JSON-RPC; see docs/mcp.md): the registry's actions as "
            "tools, as the authenticated principal; the agent's model in the RCAN-AI-Provider "
            "and RCAN-AI-Model headers. 501 without the `rcan-rtps[mcp]` extra")
_MCP_REPLY = {"200": {"description": "a JSON-RPC response (or an event stream for GET)",
                      "content": {"application/json": {}, "text/event-stream": {}}},
              "202": {"description": "a notification or response accepted"},
              "404": {"description": "an unknown session, or another principal's"},
              **_errors(400, 413)}
_MCP = {method: _op(f"{method}Mcp", _MCP_DOC, _MCP_REPLY) for method in ("post", "get", "delete")}


def _query(name: str, description: str) -> dict[str, Any]:
    return {"name": name, "in": "query", "required": False, "description": description,
            "schema": {"type": "integer", "minimum": 0}}


def _seconds(name: str, description: str) -> dict[str, Any]:
    return {"name": name, "in": "query", "required": False, "description": description,
            "schema": {"type": "string", "pattern": r"^[0-9]{1,11}(\.[0-9]{1,3})?$"}}


def _console_op(path: str, op_id: str, summary: str) -> dict[str, Any]:
    """The console's static routes: public (`security: []`), so no 401."""
    if "{" not in path:
        status = "200" if path.startswith("/console/") else "302"
        return _op(op_id, summary, {status: {"description": summary}}, security=[])
    return _op(op_id, summary, {"200": {"description": summary},
                                "404": _json("ApiError", "no such asset")}, security=[],
               parameters=[{"name": "name", "in": "path", "required": True,
                            "schema": {"type": "string"}}])


_HITL_DECISION = _DECISION | {"404": _json("DecisionBody", "unknown or expired pending_id")}
# An INVOKE (and INVOKE_CANCEL) is answered with an INVOKE_RESULT (§19.3), any other body with
# a decision.
_COMMAND_DECISION = _DECISION | {"200": {
    "description": "executed (possibly clamped; see `applied`); an INVOKE's INVOKE_RESULT",
    "content": {"application/json": {"schema": {
        "oneOf": [_ref("DecisionBody"), _ref("InvokeResult")]}}}}}

# docs/mcp.md, rcan_rtps._transport_warnings: what `rcan-rtps mcp` found wrong with a stop.
_TRANSPORT_WARNINGS = {
    "name": "RCAN-Transport-Warnings", "in": "header", "required": False,
    "description": "What the client's own transport found wrong with a stop (a JSON array of "
                   "strings): recorded in a stop's audit entry and reply `warnings`, each "
                   "marked `client: `, at most 8 of at most 500 characters, non-printable "
                   "characters escaped; dropped for any other command. One that cannot be "
                   "read so is one warning: the stop stops all the same.",
    "schema": {"type": "string"}}

PATHS: dict[str, dict[str, Any]] = {
    "/api/command": {"post": _op("postCommand", "Send a COMMAND (any form), SAFETY, HEARTBEAT, "
                                 "INVOKE, INVOKE_CANCEL or AUTHORIZE",
                                 _COMMAND_DECISION, _COMMAND_BODY,
                                 parameters=[_TRANSPORT_WARNINGS])},
    "/api/command/cancel": {"post": _op(
        "postCommandCancel", "A motion command of yours was cancelled by your client before "
        "its answer (`rcan-rtps mcp` sends this for its MCP client): your motion that has not "
        "started never does, and yours that runs stops — nobody else's; audited when anything "
        "was stopped. Your motion held for a human is withdrawn (never runs): `withdrawn` "
        "lists its pending ids. No body",
        {"200": _json("CommandCancelAck", "what was stopped, and what held was withdrawn"),
         **_errors()})},
    "/api/status": {"get": _op("getStatus", "The robot's STATUS (GUEST+)",
                               {"200": _json("Status", "STATUS"), **_errors()})},
    "/api/heartbeat": {"post": _op("postHeartbeat", "Keep a control session alive",
                                   {"200": _json("HeartbeatAck", "heard"), **_errors()})},
    "/api/goals": {"get": _op("getGoals", "Goals the bridge tracks, of every goal action (GUEST+)",
                              {"200": _json("GoalList", "goals"), **_errors()})},
    "/api/goals/{goal_id}": {"get": _op(
        "getGoal", "One goal: navigation, docking, ... (GUEST+)",
        {"200": _json("GoalView", "the goal"), **_errors(404)},
        parameters=[{"name": "goal_id", "in": "path", "required": True,
                     "schema": {"type": "string"}}])},
    "/api/skills": {"get": _op(
        "getSkills", "The skills an INVOKE may name (GUEST+): RCAN §18's Capability Object Map "
        "with the `invoke` capability (§19.7: `params.skills`), and each skill's action, the "
        "role it needs, its fixed and allowed parameters",
        {"200": _json("SkillList", "skills"), **_errors()})},
    "/api/thoughts/{thought_id}": {"get": _op(
        "getThought", "What an AI's thought led to (RCAN §16.5): model, confidence, its "
        "commands and their decisions (GUEST+); `reasoning` only for OWNER+. A thought id is "
        "its first sender's: another principal naming it gets a record of its own "
        "(`also_named_by` lists them; `?principal=` reads one)",
        {"200": _json("Thought", "the thought"), **_errors(404)},
        parameters=[{"name": "thought_id", "in": "path", "required": True,
                     "schema": {"type": "string"}},
                    {"name": "principal", "in": "query", "required": False,
                     "description": "whose commands naming the id (default: the first "
                                    "principal's)",
                     "schema": {"type": "string"}}])},
    "/api/hitl/pending": {"get": _op(
        "getPending", "Commands waiting for a human (approvers); with `mine=true`, the caller's "
        "own (any principal)",
        {"200": _json("PendingList", "pending"), **_errors(400, 403)},
        parameters=[{"name": "mine", "in": "query", "required": False,
                     "description": "true: only the caller's own held commands",
                     "schema": {"type": "boolean"}}])},
    "/api/hitl/pending/{pending_id}": {"get": _op(
        "getPendingOne", "One held command, for its issuer and its approvers: waiting (its "
        "PENDING_AUTH), being decided, or resolved with the decision that ended it (kept for "
        "the last 1024 resolved); unknown, or anyone else's: 404",
        {"200": _json("PendingView", "the held command"), **_errors(404)},
        parameters=[{"name": "pending_id", "in": "path", "required": True,
                     "schema": {"type": "string"}}])},
    "/api/hitl/authorize": {"post": _op(
        "postAuthorize", "Approve a pending command (`reason` is audited): 200 once it has "
        "as many distinct approvers as it needs and ran, 202 while it needs more (n-of-m); "
        "the issuer is never one of several approvers, an approver counts once (409); an "
        "approver whose signature policy is `required` is refused 403 SIGNATURE_REQUIRED "
        "(it sends a signed AUTHORIZE to /api/command)",
        _HITL_DECISION, _AUTHORIZE_BODY)},
    "/api/hitl/deny": {"post": _op(
        "postDeny", "Deny a pending command (any approver; ends it, whatever approvals it "
        "had; `reason` is audited)", _HITL_DECISION, _AUTHORIZE_BODY)},
    "/api/hitl/withdraw": {"post": _op(
        "postWithdraw", "Withdraw a pending command: its issuer, or an approver; audited "
        "HITL_WITHDRAWN (`reason` too); anyone else 403", _HITL_DECISION, _AUTHORIZE_BODY)},
    "/api/audit": {"get": _op(
        "getAudit", "Audit entries after `since`, verbatim (LEASEE+ by default)",
        {"200": _json("AuditPage", "entries"), **_errors(400, 403)},
        parameters=[_query("since", "return entries with seq > since (default 0)"),
                    _query("limit", "at most this many entries")])},
    "/api/audit/mine": {"get": _op(
        "getMyAudit", "The caller's own audit entries, verbatim (any role; never another "
        "principal's): after `since` (oldest first), or the newest `last`",
        {"200": _json("AuditPage", "entries"), **_errors(400, 429)},
        parameters=[_query("since", "return entries with seq > since (default 0)"),
                    _query("limit", "at most this many entries"),
                    _query("last", "the newest this many entries instead")])},
    "/mcp": _MCP,
    "/api/images": {"get": _op(
        "getImages", "The configured cameras (bridge.ros2.images), each with its path",
        {"200": {"description": "`{images: [{name, path}]}`",
                 "content": {"application/json": {}}}, **_errors()})},
    "/api/images/{name}": {"get": _op(
        "getImage", "A camera's newest frame: a PNG (a raw frame, lossless) or the JPEG/PNG "
        "the camera sent; X-Image-Size and X-Image-Age-S headers. 404 no such camera, 503 no "
        "frame yet, 422 an encoding that cannot be shown",
        {"200": {"description": "the frame", "content": {"image/png": {}, "image/jpeg": {}}},
         **_errors(404, 422)},
        parameters=[{"name": "name", "in": "path", "required": True,
                     "schema": {"type": "string"}}])},
    "/api/audit/verify": {"get": _op("getAuditVerify", "Verify the chain and signatures",
                                     {"200": _json("VerifyReport", "result"), **_errors(403)})},
    "/api/openapi.json": {"get": _op("getOpenApi", "This document",
                                     {"200": {"description": "OpenAPI 3.1 document",
                                              "content": {"application/json": {}}},
                                      **_errors()})},
    "/api/metrics": {"get": _op(
        "getMetrics", "Prometheus metrics: audit entries by event/action/outcome, command "
        "latency, pending approvals, e-stop, robot state, telemetry age",
        {"200": {"description": "Prometheus text exposition format",
                 "content": {"text/plain": {"schema": {"type": "string"}}}}, **_errors()})},
    "/.well-known/rcan-node.json": {"get": _op(
        "getNodeManifest", "RCAN §17 node manifest: the robot's RURI, the RCAN versions "
        "spoken, the bridge's public keys (public: no credential)",
        {"200": {"description": "node manifest",
                 "content": {"application/json": {"schema": {"type": "object"}}}}},
        security=[])},
    "/api/safety/manifest": {"get": _op(
        "getSafetyManifest", "Protocol 66 safety manifest: invariants, limits, workspace, "
        "e-stop, audit and clock facts, derived from the config and the action registry",
        {"200": {"description": "safety manifest",
                 "content": {"application/json": {"schema": {"type": "object"}}}},
         **_errors(429)})},
    "/api/v1/audit": {"get": _op(
        "getAuditExport", "RCAN §20 audit export (rbac.audit_read_role): entries with "
        "from <= time < to, verbatim, streamed; X-Audit-Chain-Root is the RFC 6962 root over "
        "the exported lines, X-Audit-Issuer-Sig Ed25519 over its 32 bytes",
        {"200": {"description": "JSON lines (a header line, then entries) or CSV",
                 "headers": {"X-Audit-Chain-Root": {"schema": {"type": "string"}},
                             "X-Audit-Issuer-Sig": {"schema": {"type": "string"}}},
                 "content": {"application/x-ndjson": {"schema": {"type": "string"}},
                             "text/csv": {"schema": {"type": "string"}}}},
         **_errors(400, 403)},
        parameters=[_seconds("from", "entries at or after this Unix time (s)"),
                    _seconds("to", "entries before this Unix time (s)"),
                    {"name": "format", "in": "query", "required": False,
                     "schema": {"enum": ["jsonl", "csv"], "default": "jsonl"}}])},
    "/api/ws": {"get": _op(
        "getWebSocket",
        "WebSocket: text frames in are COMMAND bodies; frames out are WsFrame (STATUS at "
        "telemetry_rate_hz, outcomes with the REST body, goal changes, and the held commands "
        "to approvers). Closing it while holding a control session stops the robot. A browser "
        "authenticates it with `?ticket=` (POST /api/ws-ticket) instead of the header.",
        {"101": {"description": "switching to WebSocket; frames are WsFrame",
                 "content": {"application/json": {"schema": _ref("WsFrame")}}},
         **_errors()},
        parameters=[{"name": "ticket", "in": "query", "required": False,
                     "description": "a single-use ticket from POST /api/ws-ticket (used only "
                                    "without an Authorization header)",
                     "schema": {"type": "string"}}])},
    "/api/ws-ticket": {"post": _op(
        "postWsTicket", "A single-use ticket (30 s) for the caller's own WebSocket, for a "
        "browser, which cannot set Authorization on one (any principal)",
        {"200": _json("TicketReply", "the ticket"), **_errors(429)})},
    "/api/whoami": {"get": _op(
        "getWhoAmI", "The caller's principal, role and what the console offers it (any "
        "principal; the API decides either way)",
        {"200": _json("WhoAmI", "who the credential is"), **_errors()})},
    **{path: {"get": _console_op(path, op_id, summary)} for path, op_id, summary in (
        ("/", "getRoot", "redirects to the operator console, /console/ (public)"),
        ("/console", "getConsoleBare", "redirects to /console/ (public)"),
        ("/console/", "getConsole", "the operator console's page (public: it holds no data)"),
        ("/console/{name}", "getConsoleAsset", "one of the console's static files (public)"))},
}


def openapi_document() -> dict[str, Any]:
    _, mine = msgspec.json.schema_components(_API_TYPES, ref_template=_REF)
    return {
        "openapi": "3.1.0",
        "jsonSchemaDialect": "https://json-schema.org/draft/2020-12/schema",
        "info": {"title": "rcan-rtps bridge API", "version": __version__,
                 "description": "RCAN governance (RCAN 1.2, bridge spec v1.0) in front of a "
                                "ROS 2 robot. Every /api route needs a Bearer token (or, for "
                                "/api/ws, a ticket) or a mapped mTLS client certificate (a "
                                "ticket or certificate: not from a page of another origin); "
                                "the node manifest and the console's static files need none."},
        "security": [{"bearer": []}],
        "paths": PATHS,
        "components": {
            "schemas": {**openapi_schemas(), **mine},
            "securitySchemes": {"bearer": {"type": "http", "scheme": "bearer"}},
        },
    }
