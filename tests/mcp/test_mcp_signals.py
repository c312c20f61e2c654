"""`rcan-rtps mcp` ends on SIGINT, SIGTERM and SIGHUP while its client keeps stdin open: at
once, with the shell's code for the signal (128 + its number) and nothing on stderr. Before,
the SDK's stdin reader (a worker thread blocked in readline, which no cancel interrupts and
the interpreter waits for) kept a Ctrl-C'd server alive until the client closed stdin, and
SIGTERM/SIGHUP killed it without stopping what its agent had started (that part:
tests/interop/test_mcp_sim.py). No bridge is needed: nothing here calls it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from tests.mcp.test_mcp_tools import closed_port

EXIT_TIMEOUT = 60.0  # s; generous for a busy machine: the server ends at once
INITIALIZE = {"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
    "protocolVersion": "2025-06-18", "capabilities": {},
    "clientInfo": {"name": "signal-test", "version": "1"}}}


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=lambda s: signal.Signals(s).name)
def test_a_signal_ends_the_stdio_server_while_stdin_is_open(sig: int) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "rcan_rtps", "mcp", "--url", f"http://127.0.0.1:{closed_port()}",
         "--token-env", "AGENT_TOKEN", "--ai-provider", "acme", "--ai-model", "m1"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "AGENT_TOKEN": "a" * 32})
    assert proc.stdin is not None and proc.stdout is not None
    try:
        proc.stdin.write(json.dumps(INITIALIZE) + "\n")
        proc.stdin.flush()
        reply = json.loads(proc.stdout.readline())  # serving: its stdin reader is waiting
        assert reply["id"] == 1 and "result" in reply, reply
        proc.send_signal(sig)
        try:
            code = proc.wait(EXIT_TIMEOUT)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{signal.Signals(sig).name} did not end the server")
        assert code == 128 + sig
        assert proc.stderr is not None and proc.stderr.read() == ""
    finally:
        proc.kill()
        proc.wait()
        proc.stdin.close()


def test_a_client_that_closed_its_end_of_stdout_is_a_disconnect() -> None:
    """The reply to a client that closed its reader (it went away) hits a broken pipe: the
    server ends as when stdin closes, exit 0 and no traceback. The error came out of the
    SDK's task groups wrapped in exception groups, which the command line's handler of a
    broken pipe does not see: a traceback, exit 1."""
    reader, writer = os.pipe()
    proc = subprocess.Popen(
        [sys.executable, "-m", "rcan_rtps", "mcp", "--url", f"http://127.0.0.1:{closed_port()}",
         "--token-env", "AGENT_TOKEN", "--ai-provider", "acme", "--ai-model", "m1"],
        stdin=subprocess.PIPE, stdout=writer, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "AGENT_TOKEN": "a" * 32})
    os.close(writer)
    os.close(reader)  # the client's reader gone before the reply
    assert proc.stdin is not None
    try:
        proc.stdin.write(json.dumps(INITIALIZE) + "\n")
        proc.stdin.flush()
        proc.wait(EXIT_TIMEOUT)  # stdin still open: the broken pipe alone ends it
    finally:
        proc.kill()
        proc.wait()
        proc.stdin.close()
    assert proc.stderr is not None
    err = proc.stderr.read()
    assert "Traceback" not in err, err
    assert proc.returncode == 0, err
