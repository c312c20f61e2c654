"""An AI agent's side of rcan-rtps: governed commands carrying the model's identity.

Every command names the provider, model, its confidence and the reasoning trace id, so
the audit log can say which model asked for what. Below-threshold confidence is held
for a human (HTTP 202) instead of executed.

    RCAN_URL=http://127.0.0.1:8765 RCAN_TOKEN=<USER token> python examples/agent_client.py
"""

from __future__ import annotations

import json
import os
import sys
import time
import urllib.error
import urllib.request
import uuid
from typing import Any

URL = os.environ.get("RCAN_URL", "http://127.0.0.1:8765")
TOKEN = os.environ.get("RCAN_TOKEN", "")
AI = {"ai_provider": "example-lab", "ai_model": "planner-7b"}


class Unusable(Exception):
    """The bridge cannot be used as configured: the message says why and what to do."""


def request(method: str, path: str, body: Any = None) -> tuple[int, Any]:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(URL + path, data=data, method=method, headers={
        "Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:  # 4xx/5xx still carry a JSON decision
        if err.code == 401:
            raise Unusable(f"{URL} refused the token (401): set RCAN_TOKEN to a USER token "
                           "(rcan-rtps run --sim prints one)") from None
        return err.code, json.loads(err.read())
    except (urllib.error.URLError, OSError) as err:
        reason = getattr(err, "reason", err)
        raise Unusable(f"cannot reach the bridge at {URL} ({reason}): is `rcan-rtps run` "
                       "running? (RCAN_URL sets the address)") from None


def command(action: str, params: dict[str, Any], confidence: float) -> tuple[int, Any]:
    body = {"action": action, "params": params, "message_id": str(uuid.uuid4()),
            "confidence": confidence, "thought_id": f"thought-{uuid.uuid4().hex[:12]}", **AI}
    status, decision = request("POST", "/api/command", body)
    print(f"{action:<9} {json.dumps(params):<44} → {status} {decision.get('outcome')}"
          f" {decision.get('reason') or ''}".rstrip())
    return status, decision


def main() -> int:
    if not TOKEN:
        print("set RCAN_TOKEN to a USER token (rcan-rtps run --sim prints one)", file=sys.stderr)
        return 2
    try:
        return run()
    except Unusable as exc:
        print(f"agent_client: {exc}", file=sys.stderr)
        return 1


def run() -> int:
    command("move", {"linear_x": 0.4, "angular_z": 0.2}, confidence=0.93)
    command("move", {"linear_x": 3.0}, confidence=0.97)  # over the limit: refused
    status, decision = command("navigate", {"x": 1.5, "y": 0.5, "yaw": 1.57}, confidence=0.88)
    if status == 200 and decision.get("goal_id"):
        goal_id = decision["goal_id"]
        for _ in range(200):
            # A controlling client must stay heard from, or the bridge halts the robot
            # (session loss, spec §10.8): heartbeat while waiting.
            request("POST", "/api/heartbeat", {})
            _, goal = request("GET", f"/api/goals/{goal_id}")
            if goal.get("state") in ("succeeded", "aborted", "canceled", "rejected", "lost"):
                break
            time.sleep(0.2)
        print(f"navigate goal {goal_id}: {goal.get('state')}")
    command("stop", {}, confidence=1.0)
    # Low confidence: a human decides. Sent after the stop: a stop withdraws the motion held
    # for a human before it.
    command("move", {"linear_x": 0.2}, confidence=0.3)
    _, status_body = request("GET", "/api/status")
    print(f"robot state: {status_body.get('state')}, pending approvals: "
          f"{status_body.get('pending_auth')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
