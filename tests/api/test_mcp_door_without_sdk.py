"""A stop at `/mcp` stops whether or not the SDK is there to serve it (non-negotiable 4).

Before: without the `mcp` extra, `/mcp` answered every request 501, an e-stop's `tools/call`
too (a sessionless 2026-07-28 client sends one without any handshake), and the robot was not
stopped; a stop whose call the SDK failed (its session manager gone: a 503 "internal error")
was not run either; and the SDK's server task, had it ended, was never restarted and its
exception never retrieved. Now the door runs such a stop itself, as its tool runs it, with why
as its warning; anything else is refused as before (501) or served by a new server.
"""

from __future__ import annotations

import asyncio
import logging
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from rcan_rtps.api._app import McpDoor
from rcan_rtps.api._mcp import EXTRA_HINT, McpEndpoint
from tests.api.apihelpers import TOKENS, Api
from tests.api.test_mcp_stop_intake import (
    LEGACY,
    MODERN,
    call,
    headers,
    no_traceback,
    post,
    stopped,
    tool_call,
    warned,
)
from tests.waiting import eventually

PROTOCOLS = [LEGACY, MODERN]


@pytest.fixture
def log(caplog: pytest.LogCaptureFixture) -> pytest.LogCaptureFixture:
    caplog.set_level(logging.DEBUG)
    return caplog


@pytest.fixture
def no_sdk(monkeypatch: pytest.MonkeyPatch) -> None:
    """As if the `mcp` extra were not installed (what serves MCP is imported anew). Its
    modules already imported by another test of this process are hidden too: an import of one
    that is in `sys.modules` would not look at its package."""
    for name in [*sys.modules, "mcp", "mcp_types"]:
        if name.split(".")[0] in ("mcp", "mcp_types"):
            monkeypatch.setitem(sys.modules, name, None)  # type: ignore[arg-type]
    monkeypatch.delitem(sys.modules, "rcan_rtps.mcp_server.http", raising=False)


def bare_headers(who: str, protocol: str, tool: str = "estop") -> dict[str, str]:
    """A tools/call's headers with no session (nothing can open one without the SDK)."""
    sent = {"Authorization": f"Bearer {TOKENS[who]}", "Content-Type": "application/json",
            "Accept": "application/json, text/event-stream", "RCAN-AI-Model": "m-1"}
    if protocol == MODERN:
        sent |= {"Mcp-Protocol-Version": MODERN, "Mcp-Method": "tools/call", "Mcp-Name": tool}
    return sent


def endpoint(api: Api) -> McpEndpoint:
    assert api.app is not None
    route = next(r for r in api.app.router.routes()
                 if r.resource is not None and r.resource.canonical == "/mcp")
    door = getattr(route.handler, "__self__", None)
    assert isinstance(door, McpDoor) and door.endpoint is not None
    return door.endpoint


def audited_stop(api: Api, data: dict[str, Any], event: str, who: str) -> None:
    entry = api.entry(data["audit_id"])
    assert (entry["event"], entry["principal"]) == (event, who), entry
    assert entry["warnings"] == data["warnings"], (entry, data)


# -- the SDK not installed ----------------------------------------------------------------------

@pytest.mark.parametrize("protocol", PROTOCOLS)
async def test_an_estop_stops_without_the_sdk(api: Api, no_sdk: None,
                                              log: pytest.LogCaptureFixture,
                                              protocol: str) -> None:
    status, reply = await post(api, call("estop", b'"reason": "x"', protocol),
                               bare_headers("viewer", protocol))
    assert status == 200, reply
    data = stopped(reply)
    assert api.gov.latch.latched and [a for a, _ in api.dispatcher.calls] == ["estop"]
    assert EXTRA_HINT in warned(data, "the bridge ran the stop"), data
    assert reply["result"]["resultType"] == "complete", reply
    audited_stop(api, data, "ESTOP", "viewer")
    no_traceback(log)


async def test_a_halt_a_notification_and_a_batch_stop_without_the_sdk(
        api: Api, no_sdk: None, log: pytest.LogCaptureFixture) -> None:
    status, reply = await post(api, call("stop", b'"reason": "x"', LEGACY),
                               bare_headers("planner", LEGACY, "stop"))
    assert status == 200, reply
    audited_stop(api, stopped(reply), "COMMAND_DISPATCHED", "planner")
    async with api.http.post("/mcp", data=tool_call("stop", b"{}", LEGACY, None),
                             headers=bare_headers("planner", LEGACY, "stop")) as resp:
        assert resp.status == 202, await resp.text()
    move = call("move", b'"linear_x": 0.2, "duration_s": 5, "confidence": 0.9', LEGACY, 3)
    status, replies = await post(api, b"[" + call("estop", b"", LEGACY) + b", " + move + b"]",
                                 bare_headers("planner", LEGACY))
    assert status == 200 and len(replies) == 2, replies
    stopped(replies[0])
    assert replies[1]["error"]["code"] == -32600, replies
    assert [a for a, _ in api.dispatcher.calls] == ["stop", "stop", "estop"]
    assert api.gov.latch.latched
    no_traceback(log)


async def test_anything_else_is_still_refused_without_the_sdk(api: Api, no_sdk: None) -> None:
    move = call("move", b'"linear_x": 0.2, "duration_s": 5, "confidence": 0.9', MODERN)
    async with api.http.post("/mcp", data=move,
                             headers=bare_headers("planner", MODERN, "move")) as resp:
        body = await resp.json()
        assert (resp.status, body["error_code"]) == (501, "NOT_IMPLEMENTED"), body
        assert body["reason"] == EXTRA_HINT
    assert api.dispatcher.calls == []


# -- the SDK failing, or its server gone --------------------------------------------------------

@pytest.mark.parametrize("protocol", PROTOCOLS)
async def test_a_stop_the_sdk_fails_is_run_by_the_door(api: Api, log: pytest.LogCaptureFixture,
                                                       monkeypatch: pytest.MonkeyPatch,
                                                       protocol: str) -> None:
    from rcan_rtps.mcp_server.http import HttpMcp

    await headers(api, "viewer", LEGACY)  # the SDK's server started (a session opened)
    sent = await headers(api, "viewer", protocol)

    async def failing(*args: Any, **kwargs: Any) -> None:
        raise RuntimeError("the session manager broke\nsecond line")

    monkeypatch.setattr(HttpMcp, "handle", failing)
    status, reply = await post(api, call("estop", b'"reason": "x"', protocol), sent)
    assert status == 200, reply
    data = stopped(reply)
    said = warned(data, "the MCP server failed", "the bridge ran the stop")
    assert "RuntimeError: the session manager broke" in said and "second line" not in said
    assert api.gov.latch.latched
    audited_stop(api, data, "ESTOP", "viewer")
    assert any("failed a stop's call" in r.getMessage() for r in log.records)
    no_traceback(log)


async def test_a_server_gone_is_started_again_and_stops_meanwhile_run(
        api: Api, log: pytest.LogCaptureFixture) -> None:
    sent = await headers(api, "viewer", LEGACY)  # a session of the first server
    door = endpoint(api)
    serving = door._serving
    assert serving is not None
    serving.cancel()
    await eventually(lambda: any("the MCP server stopped" in r.getMessage()
                                 for r in log.records), timeout=30.0,
                     what="the door noticing its server ended")
    # The session died with its server: the door runs the stop at once (it does not wait
    # for a new server), with nothing to warn of: the robot is stopped as the tool stops it.
    status, reply = await post(api, call("estop", b'"reason": "x"', LEGACY), sent)
    assert status == 200, reply
    data = stopped(reply)
    assert not data.get("warnings") and api.gov.latch.latched, data
    # Anything else is served again, by a new server: a new session opens, lists the tools.
    fresh = await headers(api, "viewer", LEGACY)
    listing = b'{"jsonrpc": "2.0", "id": 5, "method": "tools/list", "params": {}}'
    status, reply = await post(api, listing, fresh)
    assert status == 200 and any(t["name"] == "estop" for t in reply["result"]["tools"]), reply
    assert door._serving is not None and door._serving is not serving
    # The old session's requests are the new server's to refuse (it does not know it: 404).
    async with api.http.post("/mcp", data=listing, headers=sent) as resp:
        assert resp.status == 404, await resp.text()
    no_traceback(log)


async def test_a_server_that_fails_is_said_once_and_retrieved(
        api: Api, log: pytest.LogCaptureFixture) -> None:
    """Its exception is read (no "Task exception was never retrieved" when it is collected:
    the suite's asyncio guard fails the run on one) and named in one warning line."""
    await headers(api, "viewer", LEGACY)
    door = endpoint(api)
    serving = door._serving
    assert serving is not None

    async def fail() -> None:
        raise OSError("out of descriptors")

    failed = asyncio.ensure_future(fail())
    await asyncio.wait([failed])
    door._serving = failed  # stands for the SDK's task, ended by a failure of its own
    door._ended(failed)
    said = [r.getMessage() for r in log.records if "the MCP server stopped" in r.getMessage()]
    assert said == ["the MCP server stopped (OSError: out of descriptors): the next request "
                    "to /mcp starts it again"], said
    serving.cancel()  # the real one (already forgotten by the door: no second line)
    await asyncio.wait([serving])
    await asyncio.sleep(0)
    assert len([r for r in log.records if "the MCP server stopped" in r.getMessage()]) == 1
    no_traceback(log)


# -- the SDK's import does not hold the bridge up ---------------------------------------------

IMPORT_SCRIPT = """
import asyncio, sys
from pathlib import Path
from tests.api.apihelpers import Api
from tests.api.test_mcp_stop_intake import LEGACY, call, headers

def importing():
    http = sys.modules.get("rcan_rtps.mcp_server.http")
    return http is None or bool(getattr(http.__spec__, "_initializing", False))

async def main(first):
    api = await Api(Path(sys.argv[1])).start()
    if first == "stop":  # the run's first MCP request is an e-stop: answered at once
        sent = {"Authorization": "Bearer " + sys.argv[3], "Content-Type": "application/json",
                "Accept": "application/json, text/event-stream"}
        async with api.http.post("/mcp", data=call("estop", b"", LEGACY), headers=sent) as r:
            print("mcp estop", r.status, (await r.json())["result"]["isError"],
                  "during" if importing() else "after")
    opening = asyncio.ensure_future(headers(api, "viewer", LEGACY))
    while "mcp" not in sys.modules and not opening.done():  # the SDK's import has begun
        await asyncio.sleep(0.001)
    status, body = await api.command("viewer", {"action": "estop"})
    print("rest estop", status, body["outcome"], "during" if importing() else "after")
    await opening
    await api.close()

asyncio.run(main(sys.argv[2]))
"""


@pytest.mark.parametrize("first", ["session", "stop"])
def test_the_sdk_is_imported_while_the_bridge_answers(tmp_path: Path, first: str) -> None:
    """The SDK takes ~1 s of CPU to import, on the first request to `/mcp`: imported on the
    loop, it held every other request up — an e-stop over REST sent then was answered only
    once it was done. Now it is imported on a thread: that e-stop is answered while the
    import still runs, and a first MCP request that is a stop does not wait for it at all."""
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(root / "src"), str(root), str(root / "tests")])}
    run = subprocess.run([sys.executable, "-c", IMPORT_SCRIPT, str(tmp_path), first,
                          TOKENS["viewer"]], capture_output=True, text=True, timeout=120,
                         check=False, cwd=root, env=env)
    assert run.returncode == 0, run.stderr
    assert "rest estop 200 executed during" in run.stdout, run.stdout
    if first == "stop":
        assert "mcp estop 200 False during" in run.stdout, run.stdout
