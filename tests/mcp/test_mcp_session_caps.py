"""MCP sessions at the bridge's `/mcp` (the 2025 protocol's handshake), capped per principal as
well as over all (`mcp_server.sessions`), driven by the official SDK's client against the API
in process. Before, one principal that opened sessions and abandoned them (no DELETE: a client
that dies sends none) filled the bridge's only cap, and every principal's new session was
refused 503 until they expired, half an hour later. Now a principal fills only its own cap;
at it, its session idle longest is closed for its new one (and answers 404, as an expired one
does); when none of its sessions is idle, the new one is refused with an error that names the
cap. A session stays its opener's: another principal's request for it is refused 404 and
touches nothing of it."""

from __future__ import annotations

import contextlib
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx2
import pytest
from mcp import Client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client
from mcp.shared.exceptions import MCPError
from mcp_types.jsonrpc import INVALID_REQUEST
from waiting import eventually

from rcan_rtps.mcp_server import http
from tests.api.apihelpers import TOKENS, Api
from tests.api.test_mcp_http import AGENT, CLIENT, _endpoint

# The caps shrunk (set before the first request to /mcp builds the server), so that a few
# sessions fill them: ALL is what one principal abandons, more than its CAP.
CAP, ALL = 3, 8
SHIPPED = (http.MAX_SESSIONS_PER_PRINCIPAL, http.MAX_SESSIONS)  # (read before any patch)
LISTED = {"jsonrpc": "2.0", "id": 7, "method": "tools/list"}


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    """The API in process (tests/mcp/test_mcp_sdk_oversize_stops.py's)."""
    harness = await Api(tmp_path).start()
    yield harness
    await harness.close()


@pytest.fixture(autouse=True)
def small_caps(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(http, "MAX_SESSIONS_PER_PRINCIPAL", CAP)
    monkeypatch.setattr(http, "MAX_SESSIONS", ALL)


@dataclass
class Opened:
    client: Client
    ids: list[str] = field(default_factory=list)  # the session ids the bridge gave it

    @property
    def session(self) -> str:
        assert len(self.ids) == 1, self.ids
        return self.ids[0]


@contextlib.asynccontextmanager
async def opened(api: Api, who: str, *, abandon: bool = False) -> AsyncIterator[Opened]:
    """The SDK's client of `who` in a session of its own (the 2025 protocol); `abandon`: it
    leaves without ending its session (no DELETE), as a client that died."""
    url = str(api.http.make_url("/mcp"))
    headers = {"Authorization": f"Bearer {TOKENS[who]}", **AGENT}
    async with create_mcp_http_client(headers=headers) as web:
        seen: list[str] = []

        async def note(response: httpx2.Response) -> None:
            sid = response.headers.get("mcp-session-id")
            if sid and sid not in seen:
                seen.append(sid)

        web.event_hooks = {"response": [note]}
        async with Client(streamable_http_client(url, http_client=web,
                                                 terminate_on_close=not abandon),
                          client_info=CLIENT, mode="legacy") as client:
            yield Opened(client, seen)


async def abandon(api: Api, who: str, count: int) -> list[str]:
    """`count` sessions of `who`'s, each used once (a tool call) then abandoned, and idle
    before the next opens (the bridge has seen its client's event stream close): their ids,
    in the order they were opened."""
    ids = []
    for _ in range(count):
        async with opened(api, who, abandon=True) as agent:
            assert not (await agent.client.call_tool("get_status", {})).is_error
            ids.append(agent.session)
        await eventually(lambda: idle(api, ids[-1:]), what="the abandoned session idle")
    return ids


def sessions(api: Api) -> dict[str, Any]:
    """The open sessions' transports by id, as the endpoint's SDK manager holds them."""
    server = _endpoint(api)._server
    assert server is not None
    return dict(server._manager._server_instances)


def idle(api: Api, ids: list[str]) -> bool:
    """Whether each of `ids` is open with no request in flight (its client's event stream
    closed: the bridge sees a client gone at its next look)."""
    held = sessions(api)
    return all(sid in held and held[sid].idle_scope.deadline != math.inf for sid in ids)


async def status_for(api: Api, who: str, sid: str, method: str = "POST") -> int:
    headers = {"Authorization": f"Bearer {TOKENS[who]}", "Mcp-Session-Id": sid,
               "Accept": "application/json, text/event-stream",
               "Mcp-Protocol-Version": "2025-06-18", **AGENT}
    async with api.http.request(method, "/mcp", json=LISTED if method == "POST" else None,
                                headers=headers) as resp:
        return resp.status


def mcp_error(raised: BaseException) -> MCPError:
    """The MCPError the SDK's client raised, out of the exception groups around it."""
    if isinstance(raised, MCPError):
        return raised
    inner = getattr(raised, "exceptions", None)
    assert inner, repr(raised)
    return mcp_error(inner[0])


def test_the_shipped_cap_of_a_principal_is_well_below_the_whole() -> None:
    per, whole = SHIPPED
    assert 0 < per * 8 <= whole, SHIPPED


def test_an_sdk_without_the_parts_the_cap_stands_on_is_said_at_start(
        caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """The per-principal cap overrides the SDK's private session admission: an SDK that
    renamed it would admit every session uncapped, silently. This SDK has them all (else
    this test fails first), and one without them is warned of at construction."""
    from mcp.server.lowlevel import Server
    from mcp.server.streamable_http_manager import StreamableHTTPSessionManager

    from rcan_rtps.mcp_server import sessions

    def made() -> sessions.CappedSessions:
        with caplog.at_level("WARNING", logger=sessions.__name__):
            return sessions.CappedSessions(Server("t"), session_idle_timeout=60.0,
                                           max_sessions=8, per_principal=2)

    assert all(hasattr(made(), n) for n in sessions._SDK_PARTS)
    assert "lacks" not in caplog.text
    real_init = StreamableHTTPSessionManager.__init__

    def init_without_owners(self: Any, *args: Any, **kwargs: Any) -> None:
        real_init(self, *args, **kwargs)
        del self._session_owners

    monkeypatch.setattr(StreamableHTTPSessionManager, "__init__", init_without_owners)
    made()
    assert "lacks _session_owners" in caplog.text


async def test_sessions_one_principal_abandons_never_shut_out_another(api: Api) -> None:
    """PLANNER abandons as many sessions as the bridge holds in all: it holds its cap, and
    VIEWER (a GUEST) still opens a session and calls a tool. Before, VIEWER was refused
    503 until PLANNER's sessions expired."""
    await abandon(api, "planner", ALL)
    async with opened(api, "viewer") as guest:
        done = await guest.client.call_tool("get_status", {})
        assert not done.is_error, done
        assert len(sessions(api)) == CAP + 1  # PLANNER's cap, and VIEWER's one


async def test_a_principal_at_its_cap_gets_its_idle_longest_session_closed(api: Api) -> None:
    """PLANNER's sessions all abandoned and idle, at its cap: its next opens, and its oldest
    is closed (404, as an expired session answers: the MCP spec's "start a new session")
    while the others still answer. Before (the whole cap its to fill), at the bridge's cap
    its own new session was refused too, and the oldest lived on."""
    ids = await abandon(api, "planner", CAP)
    async with opened(api, "planner") as agent:
        done = await agent.client.call_tool("get_status", {})
        assert not done.is_error, done
        assert set(sessions(api)) == {*ids[1:], agent.session}
    assert await status_for(api, "planner", ids[0]) == 404
    for sid in ids[1:]:
        assert await status_for(api, "planner", sid) == 200
    # On past the whole cap: never refused, never more than its cap.
    for _ in range(ALL):
        await abandon(api, "planner", 1)
        assert len(sessions(api)) == CAP


async def test_a_principal_whose_sessions_are_all_busy_is_told_its_cap(
        api: Api, caplog: pytest.LogCaptureFixture) -> None:
    """PLANNER's CAP sessions are live (each client's event stream open: a request in
    flight), so none is closed for a new one: that one is refused with an error naming
    the cap (429), the live ones go on, and another principal still opens one."""
    async with contextlib.AsyncExitStack() as stack:
        live = [await stack.enter_async_context(opened(api, "planner")) for _ in range(CAP)]
        ids = [agent.session for agent in live]
        await eventually(lambda: not any(idle(api, [sid]) for sid in ids),
                         what="each live client's event stream open")
        with pytest.raises(BaseException) as refused:  # (the SDK's client: in a group)
            async with opened(api, "planner"):
                pass
        error = mcp_error(refused.value)
        assert error.code == INVALID_REQUEST, error
        assert f"principal 'planner' has {CAP} open, its cap ({CAP} per principal)" in \
            error.message, error.message
        assert set(sessions(api)) == set(ids)
        for agent in live:
            assert (await agent.client.list_tools()).tools
        async with opened(api, "viewer") as guest:
            assert not (await guest.client.call_tool("get_status", {})).is_error
    said = [r.getMessage() for r in caplog.records if r.name.startswith(("mcp", "rcan"))]
    # (the SDK's own line would have said "8 sessions are already open": all principals')
    assert not [m for m in said if "Refusing to open" in m], said
    assert not [r for r in caplog.records if r.exc_info], said


async def test_a_session_used_by_another_principal_is_refused(api: Api) -> None:
    """OPS (an OWNER) sends PLANNER's session id — a call, and a DELETE: both answered as if
    the session did not exist (404); the session is still PLANNER's, and none of OPS's
    requests counted as or closed a session of PLANNER's."""
    async with opened(api, "planner") as agent:
        sid = agent.session
        assert await status_for(api, "ops", sid) == 404
        assert await status_for(api, "ops", sid, "DELETE") == 404
        assert set(sessions(api)) == {sid}
        done = await agent.client.call_tool("get_status", {})
        assert not done.is_error, done
        assert await status_for(api, "planner", sid) == 200


async def fill_the_whole(api: Api) -> dict[str, list[str]]:
    """The bridge's cap over all principals filled by abandoned, idle sessions: PLANNER and
    LESSEE at their caps, OPERATOR with the rest (fewer)."""
    held = {"planner": await abandon(api, "planner", CAP),
            "lessee": await abandon(api, "lessee", CAP),
            "operator": await abandon(api, "operator", ALL - 2 * CAP)}
    assert len(sessions(api)) == ALL
    return held


async def test_the_whole_cap_is_shared_fairly(api: Api) -> None:
    """At the cap over all principals, VIEWER (holding none) gets room in the sessions of the
    principal holding the most, its idle longest closed (404, as an expired one); again in the
    next's; once no principal holds two more than VIEWER, its new session is refused 503 with
    an error naming the cap over all, and nothing is closed for it. Before, VIEWER's first
    session was refused while PLANNER's and LESSEE's abandoned ones lived on."""
    held = await fill_the_whole(api)
    first = await abandon(api, "viewer", 1)
    assert set(sessions(api)) == {*held["planner"][1:], *held["lessee"],
                                  *held["operator"], *first}
    assert await status_for(api, "planner", held["planner"][0]) == 404
    second = await abandon(api, "viewer", 1)  # PLANNER now holds 2, LESSEE 3
    assert set(sessions(api)) == {*held["planner"][1:], *held["lessee"][1:],
                                  *held["operator"], *first, *second}
    before = set(sessions(api))  # 2 each: none holds VIEWER's 2 + 2
    with pytest.raises(BaseException) as refused:
        async with opened(api, "viewer"):
            pass
    error = mcp_error(refused.value)
    assert f"sessions are all taken ({ALL}, its cap over all principals)" in error.message, \
        error.message
    assert set(sessions(api)) == before


async def test_fair_room_is_made_only_in_idle_sessions(api: Api) -> None:
    """PLANNER holds the most but each of its sessions has a request in flight: none of them
    is closed for VIEWER; the idle longest of LESSEE (the next holding two more) is."""
    async with contextlib.AsyncExitStack() as stack:
        live = [await stack.enter_async_context(opened(api, "planner")) for _ in range(CAP)]
        ids = [agent.session for agent in live]
        await eventually(lambda: not any(idle(api, [sid]) for sid in ids),
                         what="each live client's event stream open")
        lessee = await abandon(api, "lessee", CAP)
        operator = await abandon(api, "operator", ALL - 2 * CAP)
        async with opened(api, "viewer") as guest:
            assert not (await guest.client.call_tool("get_status", {})).is_error
            assert set(sessions(api)) == {*ids, *lessee[1:], *operator, guest.session}
        for agent in live:
            assert (await agent.client.list_tools()).tools


async def sessionless(api: Api, who: str, method: str) -> int:
    """`who`'s request to `/mcp` without a session id that is no `initialize` (a call, an
    event stream, a DELETE): it opens no session (the SDK answers 400)."""
    headers = {"Authorization": f"Bearer {TOKENS[who]}",
               "Accept": "application/json, text/event-stream",
               "Mcp-Protocol-Version": "2025-06-18", **AGENT}
    async with api.http.request(method, "/mcp", json=LISTED if method == "POST" else None,
                                headers=headers) as resp:
        return resp.status


async def test_a_request_that_opens_no_session_closes_none(api: Api) -> None:
    """At the cap over all principals, VIEWER's requests without a session id that are no
    `initialize` open nothing, and close nothing: before, each closed the idle longest
    session of the principal holding the most (room made for nobody), so a principal holding
    none closed another's sessions at no cost, each time the cap was reached again. So did
    PLANNER's own at its cap. A stop sent so still stops (the door runs it), and an
    `initialize` still gets its room."""
    held = await fill_the_whole(api)
    before = set(sessions(api))
    for who in ("viewer", "planner"):
        for method in ("POST", "GET", "DELETE"):
            assert await sessionless(api, who, method) == 400, (who, method)
            assert set(sessions(api)) == before, (who, method)
    for sid in held["planner"]:
        assert await status_for(api, "planner", sid) == 200
    # A stop in such a request still stops (the door runs what the SDK refuses), closing none.
    stop = {"jsonrpc": "2.0", "id": 9, "method": "tools/call",
            "params": {"name": "stop", "arguments": {}}}
    headers = {"Authorization": f"Bearer {TOKENS['planner']}",
               "Accept": "application/json, text/event-stream", **AGENT}
    async with api.http.post("/mcp", json=stop, headers=headers) as resp:
        assert resp.status == 200, await resp.text()
    assert [action for action, _ in api.dispatcher.calls] == ["stop"]
    assert set(sessions(api)) == before
    first = await abandon(api, "viewer", 1)
    assert set(sessions(api)) == {*held["planner"][1:], *held["lessee"],
                                  *held["operator"], *first}
