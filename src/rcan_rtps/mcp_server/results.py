"""Tool results as the JSON an MCP client reads (`CallToolResult`'s wire form), with no SDK
import: the bridge's `/mcp` door answers a stop with one even when the SDK is not installed
or not running, and the SDK's tools build theirs from the same functions.
"""

from __future__ import annotations

import json
import uuid
from typing import Any

from .ports import Reply
from .seat import Agent

Result = dict[str, Any]  # a CallToolResult as JSON (its camelCase wire names)


def result_json(data: dict[str, Any], note: str, *, error: bool) -> Result:
    """`data` as structured content, and as text under a first line that says what it is:
    `note`, or for an error the RCAN `error_code` and `reason`."""
    head = note
    if error:
        code = data.get("error_code") or data.get("outcome") or "REFUSED"
        head = f"refused: {code}: {data.get('reason') or 'no reason given'}"
    return {"content": [{"type": "text", "text": f"{head}\n{json.dumps(data)}"}],
            "structuredContent": data, "isError": error}


def reply_json(reply: Reply, note: str, **extra: Any) -> Result:
    """The bridge's reply as a tool result: an error when it refused (4xx, 5xx)."""
    return result_json({"http_status": reply.status, **reply.body, **extra}, note,
                       error=not reply.ok)


def failure_json(message: str, error_code: str) -> Result:
    data = {"error_code": error_code, "reason": message}
    return {"content": [{"type": "text", "text": f"{error_code}: {message}"}],
            "structuredContent": data, "isError": True}


def warned_json(done: Result, warnings: tuple[str, ...]) -> Result:
    """`done` with `warnings` before those its data has (the bridge's)."""
    data = dict(done.get("structuredContent") or {})
    data["warnings"] = [*warnings, *(data.get("warnings") or ())]
    text = next((c.get("text", "") for c in done["content"] if c.get("type") == "text"), "")
    return result_json(data, text.split("\n", 1)[0], error=bool(done.get("isError")))


def outcome_note(body: dict[str, Any]) -> str:
    outcome = body.get("outcome", "")
    if outcome == "pending_auth":
        return (f"pending_auth: held for a human; call wait_for_approval with pending_id "
                f"{body.get('pending_id')}")
    return str(outcome)


def ai_fields(agent: Agent) -> dict[str, str]:
    """The short form's AI identity fields the agent has (none it has not)."""
    fields = {"ai_provider": agent.provider, "ai_model": agent.model}
    return {k: v for k, v in fields.items() if v is not None}


def command_body(agent: Agent, client: str, action: str, args: dict[str, Any]
                 ) -> dict[str, Any]:
    """A tool's call as the short-form COMMAND the bridge takes: the agent's identity, a
    `thought_id` of its own, `confidence` and `reasoning` as the AI fields, the rest as
    `params`."""
    params = dict(args)
    body: dict[str, Any] = {"action": action, **ai_fields(agent), "ai_client": client,
                            "thought_id": uuid.uuid4().hex}
    if "confidence" in params:
        body["confidence"] = params.pop("confidence")
    if "reasoning" in params:
        body["ai_reasoning"] = params.pop("reasoning")
    body["params"] = params
    return body
