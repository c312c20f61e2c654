"""A bridge run imports what serving needs, not the rest of the CLI (issue 14: idle memory).

The set comes from the running process itself (`PYTHONPROFILEIMPORTTIME`: one stderr line per
module imported), up to and after its ready line and a governed command; no timing or memory
figure is asserted, only which modules were loaded.
"""

from __future__ import annotations

import json
import re
import signal
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from rcan_rtps.cli.main import COMMANDS
from rcan_rtps.governance.audit import load_or_create_key

from .run_process import RunProcess, child_env, state_args

EXIT_TIMEOUT = 60.0
# Loaded only by the commands, options or requests that use them.
NOT_FOR_A_RUN = {
    *(f"rcan_rtps.cli.{module}" for module in COMMANDS.values() if module != "run_cmd"),
    "rcan_rtps.cli._common", "rcan_rtps.cli._echo", "rcan_rtps.cli._measure",
    "rcan_rtps.ros.bag", "mcap",  # bags
    "rcan_rtps.bridge.mdns", "zeroconf",  # --no-mdns
    "prometheus_client",  # until /api/metrics is scraped
    "concurrent.futures.process", "multiprocessing",  # until an audit verification
    # a key is written (first start) and parsed (later ones) without it
    "cryptography.hazmat.primitives.serialization",
    "rcan_rtps.api._openapi",  # until /api/openapi.json is asked for
    "difflib",  # "did you mean" hints of config and type errors
    "rcan_rtps.mcp_server", "mcp", "mcp_types",  # `rcan-rtps mcp` (the `mcp` extra)
    # issue 27 (idle footprint): loaded by the first request that needs them
    "rcan_rtps.api._asgi", "rcan_rtps.api._local",  # /mcp
    "rcan_rtps.api._safety_manifest",  # /api/safety/manifest, /mcp
    "rcan_rtps.api._audit_export", "csv",  # /api/v1/audit
    "importlib.resources", "zipfile",  # the console's files (/console/)
    "cryptography.hazmat.primitives.asymmetric.mldsa",  # a principal's ML-DSA key
    "pkgutil",  # the action registry lists its folder itself
    "encodings.idna", "stringprep",  # the API's address is resolved as bytes
    "rcan_rtps.governance.logcheck",  # GET /api/audit/verify's worker process
    "rcan_rtps.api._ws",  # GET /api/ws
    "rcan_rtps.api._mcp",  # /mcp (McpDoor)
    "rcan_rtps.api._console_pages", "rcan_rtps.console",  # the console and its API calls
    "rcan_rtps.api._invoke",  # INVOKE, INVOKE_CANCEL, AUTHORIZE, GET /api/skills
    "rcan_rtps.governance.thoughts",  # an AI command, GET /api/thoughts/{id}
    "rcan_rtps.governance.jwt",  # bridge.api.jwt
    "rcan_rtps.api._reads",  # GET /api/audit, /api/audit/mine, /api/audit/verify
}


# Each lazily loaded door, the request that opens it and the modules that request loads.
FIRST_USE = {
    "/console/": {"rcan_rtps.api._console_pages", "rcan_rtps.console"},
    "/api/whoami": {"rcan_rtps.api._console_pages"},
    "/api/skills": {"rcan_rtps.api._invoke"},
    "/api/thoughts/no-such-thought": {"rcan_rtps.governance.thoughts"},
    "/api/audit/mine?last=5": {"rcan_rtps.api._reads"},
}


def imported(stderr: list[str]) -> set[str]:
    found = (re.match(r"import time:\s+\d+ \|\s+\d+ \|\s*(\S+)", line) for line in stderr)
    return {m.group(1) for m in found if m}


def get(url: str, token: str) -> tuple[int, bytes]:
    request = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(request, timeout=30) as reply:
            return int(reply.status), reply.read()
    except urllib.error.HTTPError as error:
        return error.code, error.read()


def command(url: str, token: str) -> int:
    body = json.dumps({"action": "move", "params": {"linear_x": 0.1, "duration_s": 0.2}})
    request = urllib.request.Request(
        f"{url}/api/command", data=body.encode(), method="POST",
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as reply:
        return int(reply.status)


@pytest.mark.parametrize("start", ["first", "later"])
def test_a_bridge_run_leaves_cli_only_modules_unimported(tmp_path: Path, domain_id: int,
                                                          start: str) -> None:
    # A first start writes the audit key; a later one reads it.
    (tmp_path / "state").mkdir(mode=0o700)
    if start == "later":
        load_or_create_key(tmp_path / "state" / "audit-ed25519.key")
    env = child_env(domain_id, PYTHONPROFILEIMPORTTIME="1")
    proc = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                       *state_args(tmp_path, "state")], env, demo=True)
    try:
        assert command(proc.url, proc.user) == 200, proc.output()
        proc.signal(signal.SIGINT)
        assert proc.wait(EXIT_TIMEOUT) == 0, proc.output()
        modules = imported(proc.stderr)
        assert "rcan_rtps.bridge.runtime" in modules  # the import log is complete
        assert (tmp_path / "state" / "audit-ed25519.key").exists()  # made or read
        loaded = {m for m in NOT_FOR_A_RUN
                  if m in modules or any(n.startswith(m + ".") for n in modules)}
        assert not loaded, f"a bridge run imported {sorted(loaded)}"
    finally:
        proc.kill()


def test_the_lazy_doors_answer_their_first_request(tmp_path: Path, domain_id: int) -> None:
    """What a run leaves unimported is loaded by the first request that needs it, and that
    request is answered as it would have been (issue 27)."""
    env = child_env(domain_id, PYTHONPROFILEIMPORTTIME="1")
    proc = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                       *state_args(tmp_path, "state")], env, demo=True)
    try:
        answers = {path: get(proc.url + path, proc.user) for path in FIRST_USE}
        proc.signal(signal.SIGINT)
        assert proc.wait(EXIT_TIMEOUT) == 0, proc.output()
    finally:
        proc.kill()
    status, page = answers["/console/"]
    assert status == 200 and b"<html" in page.lower(), answers
    status, who = answers["/api/whoami"]
    assert status == 200 and json.loads(who)["principal"] == "operator", answers
    status, skills = answers["/api/skills"]
    assert status == 200 and "invoke" in json.loads(skills)["caps"], answers
    status, mine = answers["/api/audit/mine?last=5"]
    assert status == 200 and json.loads(mine)["entries"] == [], answers  # commanded nothing
    status, thought = answers["/api/thoughts/no-such-thought"]
    assert status == 404 and json.loads(thought)["reason"] == "thought_not_found", answers
    modules = imported(proc.stderr)
    missing = {m for needed in FIRST_USE.values() for m in needed} - modules
    assert not missing, f"first requests answered without loading {sorted(missing)}"
