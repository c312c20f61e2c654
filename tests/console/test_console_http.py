"""The console over HTTP (no browser): its pages need no principal while every /api route
still does, the page's headers and files keep it to its own origin with nothing inline,
`/api/whoami` follows the role, and WebSocket tickets (single-use, short-lived, the issuer's,
same-origin) with the approvals frame for approvers only."""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import AsyncIterator
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from aiohttp import WSServerHandshakeError

from rcan_rtps.api._tickets import TTL_S
from rcan_rtps.console import CSP, asset_names
from tests.api.apihelpers import Api, auth, next_frame

STATIC = Path(__file__).parents[2] / "src" / "rcan_rtps" / "console" / "static"
ARM = {"action": "arm_joint", "params": {"joints": ["elbow"], "positions": [0.5],
                                         "duration_s": 1.0}}


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path).start()
    yield harness
    await harness.close()


async def get(api: Api, path: str, **headers: str) -> aiohttp.ClientResponse:
    response = await api.http.get(path, headers=headers, allow_redirects=False)
    await response.read()
    return response


# -- the auth rule ------------------------------------------------------------------------


async def test_the_console_needs_no_principal_and_every_api_route_still_does(api: Api) -> None:
    home = await get(api, "/")
    assert (home.status, home.headers["Location"]) == (302, "/console/")
    assert (await get(api, "/console")).headers["Location"] == "/console/"
    page = await get(api, "/console/")
    assert page.status == 200 and page.content_type == "text/html"
    assert "<title>rcan-rtps console</title>" in await page.text()
    for name in ("app.js", "console.css"):
        assert (await get(api, f"/console/{name}")).status == 200
    # every /api route: 401 without a credential, whether the console asks or anything else
    for path in ("/api/status", "/api/whoami", "/api/hitl/pending", "/api/audit",
                 "/api/safety/manifest", "/api/openapi.json", "/api/ws"):
        response = await get(api, path)
        assert response.status == 401, path
        assert response.headers["WWW-Authenticate"].startswith("Bearer")
    for path in ("/api/ws-ticket", "/api/command", "/console/"):  # POSTs are never public
        assert (await api.http.post(path)).status == 401, path
    # a credential on a console request is never looked at: a bad one changes nothing
    assert (await get(api, "/console/", Authorization="Bearer nonsense")).status == 200


async def test_unknown_and_traversing_asset_names_are_404(api: Api) -> None:
    for path in ("/console/nope.js", "/console/..%2F__init__.py", "/console/__init__.py",
                 "/console/%2e%2e/__init__.py"):
        response = await get(api, path)
        assert response.status in (404, 401), path  # 401: it left /console/ (normalized)
        assert b"import" not in await response.read()


# -- what the page is served with ---------------------------------------------------------


async def test_console_responses_carry_a_strict_csp(api: Api) -> None:
    for path in ("/", "/console/", "/console/app.js", "/console/nope.js"):
        headers = (await get(api, path)).headers
        csp = headers["Content-Security-Policy"]
        assert csp == CSP, path
        assert headers["X-Content-Type-Options"] == "nosniff"
        assert headers["X-Frame-Options"] == "DENY"
    directives = dict(d.strip().split(" ", 1) for d in CSP.split(";"))
    assert directives["default-src"] == "'self'"
    assert directives["script-src"] == "'self'" and directives["style-src"] == "'self'"
    assert directives["frame-ancestors"] == "'none'" and directives["object-src"] == "'none'"
    assert "unsafe" not in CSP
    types = {name: (await get(api, f"/console/{name}")).headers["Content-Type"]
             for name in ("app.js", "console.css", "icon.svg")}
    assert types == {"app.js": "text/javascript; charset=utf-8",
                     "console.css": "text/css; charset=utf-8", "icon.svg": "image/svg+xml"}


class _Inline(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.problems: list[str] = []
        self.scripts: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        names = dict(attrs)
        if tag == "style" or "style" in names:
            self.problems.append(f"inline style on <{tag}>")
        if any(n.startswith("on") for n in names):
            self.problems.append(f"event attribute on <{tag}>")
        if tag == "script":
            if not names.get("src"):
                self.problems.append("inline script")
            else:
                self.scripts.append(str(names["src"]))
        for value in names.values():
            if value and re.match(r"\s*(https?:)?//", value):
                self.problems.append(f"another origin named: {value}")


def test_the_page_has_nothing_inline_and_no_markup_from_values() -> None:
    parser = _Inline()
    parser.feed((STATIC / "index.html").read_text())
    assert parser.problems == [] and parser.scripts == ["app.js"]
    names = asset_names()
    assert {"index.html", "app.js", "console.css"} <= names
    for name in sorted(n for n in names if n.endswith(".js")):
        code = re.sub(r"(^|\s)//.*$", "", (STATIC / name).read_text(), flags=re.M)  # comments
        for sink in ("innerHTML", "outerHTML", "insertAdjacentHTML", "document.write",
                     "eval(", "new Function", "localStorage", "document.cookie"):
            assert sink not in code, (name, sink)
        # modules import each other by relative path only: nothing from a CDN
        for spec in re.findall(r'from\s+"([^"]+)"', code):
            assert spec.startswith("./"), (name, spec)


# -- who am I -----------------------------------------------------------------------------


async def test_whoami_follows_the_role(api: Api) -> None:
    answers = {who: (await api.call("GET", "/api/whoami", who))[1]
               for who in ("viewer", "planner", "ops")}
    assert answers["viewer"] == {
        "principal": "viewer", "role": "GUEST", "covers": ["GUEST"],
        "may": {"command": False, "approve": False, "must_sign_approvals": False,
                "clear_estop": False, "read_audit": False}}
    assert answers["planner"]["may"] == {"command": True, "approve": False,
                                         "must_sign_approvals": False,
                                         "clear_estop": False, "read_audit": False}
    assert answers["ops"]["covers"] == ["GUEST", "USER", "LEASEE", "OWNER"]
    assert answers["ops"]["may"] == {"command": True, "approve": True,
                                     "must_sign_approvals": False, "clear_estop": True,
                                     "read_audit": True}


# -- WebSocket tickets --------------------------------------------------------------------


async def ticket(api: Api, who: str) -> str:
    status, body = await api.call("POST", "/api/ws-ticket", who)
    assert status == 200 and body["principal"] == who and body["ws_path"] == "/api/ws", body
    assert body["expires_in_s"] == TTL_S
    return str(body["ticket"])


async def refused(api: Api, path: str, **headers: str) -> int:
    with pytest.raises(WSServerHandshakeError) as caught:
        async with api.http.ws_connect(path, headers=headers):
            pass
    return caught.value.status


async def test_a_ticket_opens_one_socket_as_its_issuer(api: Api) -> None:
    first = await ticket(api, "planner")
    async with api.http.ws_connect(f"/api/ws?ticket={first}") as ws:
        assert (await next_frame(ws, "status"))["body"]["ruri"]
        await ws.send_str(json.dumps({"action": "move", "params": {"linear_x": 0.2}}))
        outcome = await next_frame(ws, "outcome")
        assert outcome["http_status"] == 200, outcome
        assert api.entry(outcome["body"]["audit_id"])["principal"] == "planner"
    assert await refused(api, f"/api/ws?ticket={first}") == 401  # spent


async def test_wrong_expired_and_cross_origin_tickets_are_refused(api: Api) -> None:
    assert await refused(api, "/api/ws?ticket=not-a-ticket") == 401
    assert await refused(api, "/api/ws?ticket=") == 401
    stale = await ticket(api, "ops")
    api.clock.advance(TTL_S + 0.5)
    assert await refused(api, f"/api/ws?ticket={stale}") == 401
    foreign = await ticket(api, "ops")
    assert await refused(api, f"/api/ws?ticket={foreign}", Origin="http://evil.example") == 401
    # spent by that attempt, even from the right origin now
    host = f"http://{api.http.host}:{api.http.port}"
    assert await refused(api, f"/api/ws?ticket={foreign}", Origin=host) == 401
    fresh = await ticket(api, "ops")
    async with api.http.ws_connect(f"/api/ws?ticket={fresh}", headers={"Origin": host}) as ws:
        assert (await next_frame(ws, "status"))["type"] == "status"
    # a ticket is for the socket only, never a bearer credential elsewhere
    other = await ticket(api, "ops")
    assert (await get(api, f"/api/status?ticket={other}")).status == 401
    status, _ = await api.call("GET", "/api/status", headers={"Authorization": f"Bearer {other}"})
    assert status == 401


async def test_tickets_are_bounded(api: Api) -> None:
    from rcan_rtps.api._keys import WS_TICKETS

    assert api.app is not None
    tickets = api.app[WS_TICKETS]
    tickets._max = 3  # the bound, made small
    for _ in range(3):
        await ticket(api, "viewer")
    status, body = await api.call("POST", "/api/ws-ticket", "viewer")
    assert (status, body["reason"]) == (429, "too_many_tickets")
    api.clock.advance(TTL_S + 0.5)  # expired ones make room
    await ticket(api, "viewer")
    assert tickets.outstanding == 1


# -- the approvals frame ------------------------------------------------------------------


async def test_approvers_get_the_held_commands_live_and_a_guest_never(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("ops")) as owner, \
            api.http.ws_connect(f"/api/ws?ticket={await ticket(api, 'viewer')}") as guest:
        assert (await next_frame(owner, "approvals"))["body"] == {"pending": []}
        status, held = await api.command("planner", {**ARM, "ai_model": "<script>x</script>",
                                                     "confidence": 0.9})
        assert status == 202, held
        listed = (await next_frame(owner, "approvals"))["body"]["pending"]
        assert [(p["pending_id"], p["ai_model"], p["issued_by"]) for p in listed] == [
            (held["pending_id"], "<script>x</script>", "planner")]
        status, body = await api.call("POST", "/api/hitl/deny", "ops",
                                      body={"pending_id": held["pending_id"]})
        assert status == 200, body
        assert (await next_frame(owner, "approvals"))["body"] == {"pending": []}
        # the guest saw both changes in STATUS, and never an approvals frame
        seen: list[dict[str, Any]] = []
        while True:
            msg = await asyncio.wait_for(guest.receive(), timeout=30)
            seen.append(json.loads(msg.data))
            if [f["body"]["pending_auth"] for f in seen if f["type"] == "status"][-2:] == [1, 0]:
                break
        assert "approvals" not in {f["type"] for f in seen}
