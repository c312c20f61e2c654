"""A human operator's console: review commands held for approval and approve or deny them.

    RCAN_URL=http://127.0.0.1:8765 RCAN_TOKEN=<OWNER token> python examples/operator_approve.py
    ... --yes      approve everything pending without asking (for demos and tests)
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
        code, decision = request("POST", f"/api/hitl/{verb}", {"pending_id": item["pending_id"]})
        print(f"  {verb}: {code} {decision.get('outcome')} {decision.get('reason') or ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
