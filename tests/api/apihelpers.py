"""Helpers of the API tests: principals and tokens, a config, an in-memory robot, a harness.

The API has no DDS: the robot side is a `RobotView` kept in memory and a `Dispatcher` that
records what the governor hands to the bridge.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import aiohttp
from aiohttp import web
from aiohttp.test_utils import TestClient, TestServer
from local_http import serve_post
from recording import RecordingDispatcher

from rcan_rtps.api import GoalView, build_app
from rcan_rtps.api.ports import ImageSource
from rcan_rtps.config import RcanConfig, loads_config
from rcan_rtps.governance import (
    AuditLog,
    Governor,
    ManualClock,
    Notifier,
    TokenAuthenticator,
)
from rcan_rtps.governance.entry_bound import request_bytes_limit
from rcan_rtps.rcan import MoveParams, NormalizedCommand, Status
from rcan_rtps.rcan._messages import Position, RosInfo, Telemetry

RURI = "rcan://registry.local/clearpath/husky/a200-0001"
ARM_GATE = "[{action: arm_joint, require_auth: true, authorized_roles: [OWNER]}]"
ROLES = {"viewer": "GUEST", "planner": "USER", "lessee": "LEASEE", "ops": "OWNER",
         "root": "CREATOR", "ops2": "OWNER", "slow": "USER",
         # RCAN v2's names for roles (issue 24): OPERATOR = USER, ADMIN = OWNER, …
         "operator": "OPERATOR", "admin": "ADMIN", "contributor": "CONTRIBUTOR",
         "peer": "M2M_PEER"}
TOKENS = {name: f"{name}-token-0123456789abcdef" for name in ROLES}
ENV = {f"TOK_{name.upper()}": token for name, token in TOKENS.items()}
CONFIG = """\
robot: {ruri: "%(ruri)s", name: Husky A200}
bridge:
  ros2: {namespace: /robot1, distro: jazzy, telemetry_rate_hz: %(rate)s}
  api:
    max_body_bytes: %(max_body)d
    principals:
%(principals)s
    %(api_extra)s
  hitl:
    timeout_seconds: 300
    gates: %(gates)s
    confidence_gate: {min_confidence: 0.5, on_fail: escalate}
    %(hitl_extra)s
  safety:
    max_linear_vel: 1.0
    max_angular_vel: 0.5
    session_timeout_s: 60
    workspace: [[-10, -10], [10, -10], [10, 10], [-10, 10]]
  audit: {path: "%(dir)s/audit.jsonl", key_path: "%(dir)s/audit.key"}
  %(bridge_extra)s
"""


def _principals(extra: Mapping[str, str]) -> str:
    lines = []
    for name, role in ROLES.items():
        limit = "" if name == "slow" else ", rate_limit_per_min: 1000000"
        more = f", {extra[name]}" if name in extra else ""
        lines.append(f"      - {{name: {name}, role: {role}, token_env: TOK_{name.upper()}"
                     f"{limit}{more}}}")
    return "\n".join(lines)


ZERO = MoveParams(linear_x=0.0, linear_y=0.0, angular_z=0.0)  # the sample that stops


def own_stops(entries: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The entries of a stop of one principal's motion alone (not of the robot's)."""
    return [e for e in entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]


def make_config(tmp: Path, *, hitl_extra: str = "", api_extra: str = "",
                bridge_extra: str = "", max_body: int = 64 * 1024,
                rate: float = 20.0, gates: str = ARM_GATE,
                principal_extra: Mapping[str, str] | None = None) -> RcanConfig:
    """The harness's config; `principal_extra` adds flow-mapping keys to named principals."""
    text = CONFIG % {"ruri": RURI, "dir": tmp, "hitl_extra": hitl_extra, "rate": rate,
                     "gates": gates,
                     "bridge_extra": bridge_extra,
                     "api_extra": api_extra, "max_body": max_body,
                     "principals": _principals(principal_extra or {})}
    return loads_config(text, env=ENV)


def auth(name: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKENS[name]}"}


class MemoryRobot:
    """A RobotView whose STATUS and goals the test sets directly."""

    def __init__(self) -> None:
        self.state: Any = "idle"
        self.goal_views: dict[str, GoalView] = {}
        self.x = 0.0
        self.watchers: list[Callable[[], None]] = []
        self.goal_watchers: list[Callable[[GoalView], None]] = []
        self.estop_latched: Callable[[], bool] = lambda: False  # the governor's, once built

    def status(self, *, pending_auth: int) -> Status:
        return Status(
            ruri=RURI, state=self.state, estop=self.estop_latched(), battery_pct=87.5,
            telemetry=Telemetry(position=Position(x=self.x, y=0.0, z=0.0), yaw=0.0),
            faults=[], active_goals=sorted(self.goal_views), pending_auth=pending_auth,
            ros=RosInfo(domain_id=0, distro="jazzy", connected=True, last_telemetry_age_s=0.1),
            timestamp_ms=1,
        )

    def watch(self, changed: Callable[[], None]) -> None:
        self.watchers.append(changed)

    def changed(self) -> None:
        """What a test calls after setting `state`, `x` or goals: STATUS is pushed at once."""
        for watcher in self.watchers:
            watcher()

    def watch_goals(self, changed: Callable[[GoalView], None]) -> None:
        self.goal_watchers.append(changed)

    def goal_changed(self, view: GoalView) -> None:
        """What a test calls to play a goal's change (the tracker's event)."""
        self.goal_views[view.goal_id] = view
        for watcher in self.goal_watchers:
            watcher(view)

    def goal(self, goal_id: str) -> GoalView | None:
        return self.goal_views.get(goal_id)

    def goals(self) -> list[GoalView]:
        return list(self.goal_views.values())


class Api:
    """The real Governor + AuditLog in tmp, the app on 127.0.0.1, and a client for it."""

    def __init__(self, tmp: Path, *, hitl_extra: str = "", api_extra: str = "",
                 bridge_extra: str = "", max_body: int = 64 * 1024,
                 notifier: Notifier | None = None, rate: float = 20.0,
                 gates: str = ARM_GATE,
                 principal_extra: Mapping[str, str] | None = None,
                 images: ImageSource | None = None) -> None:
        self.tmp = tmp
        self.images = images
        self.clock = ManualClock()
        self.config = make_config(tmp, hitl_extra=hitl_extra, api_extra=api_extra,
                                  bridge_extra=bridge_extra, max_body=max_body, rate=rate,
                                  gates=gates, principal_extra=principal_extra)
        self.dispatcher = RecordingDispatcher()
        self.robot = MemoryRobot()
        self.notifier = notifier
        self.log: AuditLog | None = None
        self.governor: Governor | None = None
        self.app: web.Application | None = None
        self.client: TestClient[web.Request, web.Application] | None = None

    async def start(self) -> Api:
        """Build, and serve on 127.0.0.1 through aiohttp's test server."""
        await self.build()
        assert self.app is not None
        self.client = TestClient(TestServer(self.app, host="127.0.0.1"))
        await self.client.start_server()
        return self

    async def build(self) -> web.Application:
        bridge = self.config.bridge
        self.log = await AuditLog.open(bridge.audit.path, bridge.audit.key_path, ruri=RURI,
                                       clock=self.clock,
                                       request_bytes=request_bytes_limit(bridge.api.max_body_bytes))
        self.governor = Governor.from_config(self.config, audit=self.log,
                                             dispatcher=self.dispatcher, clock=self.clock,
                                             notifier=self.notifier)
        authenticator = TokenAuthenticator.from_config(bridge.api, bridge.rbac, ENV,
                                                       clock=self.clock)
        governor = self.governor
        self.robot.estop_latched = lambda: governor.latch.latched
        self.app = build_app(governor=self.governor, authenticator=authenticator,
                             robot=self.robot, config=self.config, clock=self.clock,
                             images=self.images)
        return self.app

    async def close(self) -> None:
        if self.client is not None:
            await self.client.close()
        if self.log is not None:
            await self.log.close()

    def hold_decisions(self, held: Callable[[NormalizedCommand], bool], *, decided: bool
                       ) -> tuple[asyncio.Event, asyncio.Event]:
        """The commands `held` picks wait — before the governor has them or, `decided`, once
        it has decided them (motion started) — until the first event is set; the second is
        set once one waits. As a busy bridge still taking a request, or answering it."""
        release, entered = asyncio.Event(), asyncio.Event()
        decide = self.gov.decide

        async def held_decide(command: NormalizedCommand, principal: Any) -> Any:
            if not held(command):
                return await decide(command, principal)
            done = await decide(command, principal) if decided else None
            entered.set()
            await release.wait()
            return done if done is not None else await decide(command, principal)

        decide_soon = self.gov.decide_soon

        def held_soon(command: NormalizedCommand, principal: Any) -> Any:  # an INVOKE's
            if not held(command):
                return decide_soon(command, principal)
            return asyncio.shield(asyncio.ensure_future(held_decide(command, principal)))

        self.gov.decide = held_decide  # type: ignore[method-assign]
        self.gov.decide_soon = held_soon  # type: ignore[method-assign]
        return release, entered

    @property
    def gov(self) -> Governor:
        assert self.governor is not None
        return self.governor

    @property
    def http(self) -> TestClient[web.Request, web.Application]:
        assert self.client is not None
        return self.client

    async def call(self, method: str, path: str, who: str | None = None, *,
                   body: Any = None, raw: bytes | None = None,
                   headers: Mapping[str, str] | None = None) -> tuple[int, Any]:
        """(status, decoded JSON body); asserts the body *is* JSON, whatever the status."""
        hdrs = {**(auth(who) if who else {}), **(headers or {})}
        data = raw if raw is not None else (None if body is None else json.dumps(body))
        if data is not None:
            hdrs.setdefault("Content-Type", "application/json")
        async with self.http.request(method, path, data=data, headers=hdrs) as resp:
            text = await resp.text()
            assert resp.content_type == "application/json", (resp.status, text)
            return resp.status, json.loads(text)

    async def command(self, who: str | None, body: Any = None, *,
                      raw: bytes | None = None) -> tuple[int, Any]:
        return await self.call("POST", "/api/command", who, body=body, raw=raw)

    @property
    def entries(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in (self.tmp / "audit.jsonl").read_text().splitlines()]

    def entry(self, audit_id: str) -> dict[str, Any]:
        found = [e for e in self.entries if e["audit_id"] == audit_id]
        assert len(found) == 1, audit_id
        return found[0]


async def webhook_receiver() -> tuple[web.AppRunner, str, list[dict[str, Any]]]:
    """A local HiTL webhook on 127.0.0.1: returns (runner, url, received messages)."""
    received: list[dict[str, Any]] = []

    async def hook(request: web.Request) -> web.Response:
        received.append(await request.json())
        return web.Response(status=204)

    runner, url = await serve_post("/hitl", hook)
    return runner, url, received


async def next_frame(ws: aiohttp.ClientWebSocketResponse, kind: str) -> dict[str, Any]:
    """The next WebSocket frame of `kind` ("status", "outcome", "approvals", ...), skipping
    the others."""
    async def wait() -> dict[str, Any]:
        while True:
            msg = await ws.receive()
            assert msg.type is aiohttp.WSMsgType.TEXT, msg
            frame: dict[str, Any] = json.loads(msg.data)
            if frame["type"] == kind:
                return frame

    return await asyncio.wait_for(wait(), timeout=30)
