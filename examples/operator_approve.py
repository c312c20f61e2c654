"""A human operator's console: review commands held for approval and approve or deny them.

    RCAN_URL=http://127.0.0.1:8765 RCAN_TOKEN=<OWNER token> python examples/operator_approve.py
    ... --yes      approve everything pending without asking (for demos and tests)

An approver whose signature policy is `required` must sign its approvals: set RCAN_SIGNING_KEY
to its key file (the official SDK's `MLDSAKeyPair.save`; `pip install rcan[pq]`) and each
approval goes as an SDK-signed AUTHORIZE to /api/command. Denials need no signature.
"""

from __future__ import annotations

import json
import os
import sys
import urllib.error
import urllib.request
from typing import Any

URL = os.environ.get("RCAN_URL", "http://127.0.0.1:8765")
TOKEN = os.environ.get("RCAN_TOKEN", "")
SIGNING_KEY = os.environ.get("RCAN_SIGNING_KEY", "")


def request(method: str, path: str, body: Any = None) -> tuple[int, Any]:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(URL + path, data=data, method=method, headers={
        "Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read())
    except (urllib.error.URLError, OSError) as err:
        reason = getattr(err, "reason", err)
        raise SystemExit(f"operator_approve: cannot reach the bridge at {URL} ({reason}): is "
                         "`rcan-rtps run` running? (RCAN_URL sets the address)") from None


def main() -> int:
    if not TOKEN:
        print("set RCAN_TOKEN to an OWNER token (rcan-rtps run --sim prints one)",
              file=sys.stderr)
        return 2
    approve_all = "--yes" in sys.argv[1:]
    status, body = request("GET", "/api/hitl/pending")
    if status == 401:
        print(f"{URL} refused the token (401): set RCAN_TOKEN to an OWNER token "
              "(rcan-rtps run --sim prints one)", file=sys.stderr)
        return 1
    if status != 200:
        print(f"cannot list pending commands: {status} {body}", file=sys.stderr)
        return 1
    pending = body["pending"]
    if not pending:
        print("nothing waits for approval")
    for item in pending:
        cmd = item["original_command"]
        print(f"{item['pending_id']}: {cmd.get('action')} {json.dumps(cmd.get('params', {}))}"
              f" from {item['issued_by']} (model {item.get('ai_model')}, confidence "
              f"{item.get('confidence')})")
        answer = "y" if approve_all else input("  approve? [y/N] ").strip().lower()
        verb = "authorize" if answer == "y" else "deny"
        if verb == "authorize" and SIGNING_KEY:
            code, decision = request("POST", "/api/command", signed_approval(item))
        else:
            code, decision = request("POST", f"/api/hitl/{verb}",
                                     {"pending_id": item["pending_id"]})
        print(f"  {verb}: {code} {decision.get('outcome')} {decision.get('reason') or ''}")
        if decision.get("error_code") == "SIGNATURE_REQUIRED":
            print("  this approver's approvals must be signed: set RCAN_SIGNING_KEY to its "
                  "key file", file=sys.stderr)
    return 0


def signed_approval(item: dict[str, Any]) -> dict[str, Any]:
    """An AUTHORIZE signed as the SDK signs a COMMAND: the review is in `params`, naming the
    held command by its pending_id and its message_id (the signature covers both)."""
    from rcan.message import RCANMessage
    from rcan.signing import MLDSAKeyPair, sign_message

    _, status = request("GET", "/api/status")
    params = {"decision": "approve", "pending_id": item["pending_id"],
              "command_message_id": item["original_command"]["message_id"]}
    message = RCANMessage(cmd="AUTHORIZE", target=status["ruri"], params=params)
    body: dict[str, Any] = sign_message(message, MLDSAKeyPair.load(SIGNING_KEY)).to_dict()
    return body


if __name__ == "__main__":
    sys.exit(main())
