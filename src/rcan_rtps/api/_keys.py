"""Typed application and request state of the API (aiohttp `AppKey` / `RequestKey`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Protocol

import msgspec
from aiohttp import web

from rcan_rtps.governance import Governor, Principal
from rcan_rtps.rcan import Role

from .ports import RobotView


class Authenticator(Protocol):
    """Bearer credential → principal; raises `AuthenticationError` (TokenAuthenticator does)."""

    def authenticate(self, bearer: str | None) -> Principal: ...


class ApiSettings(msgspec.Struct, frozen=True, kw_only=True):
    """What the handlers need from the config, resolved once when the app is built."""

    max_body_bytes: int
    telemetry_rate_hz: float
    audit_read_role: Role
    hitl_list_role: Role
    ws_max_in_flight: int = 32
    audit_page_max: int = 1000


GOVERNOR = web.AppKey("governor", Governor)
ROBOT = web.AppKey("robot", RobotView)
AUTHENTICATOR = web.AppKey("authenticator", Authenticator)
CERT_PRINCIPALS = web.AppKey("cert_principals", Mapping[str, Principal])
SETTINGS = web.AppKey("settings", ApiSettings)
SOCKETS = web.AppKey("sockets", set[web.WebSocketResponse])
# Seconds per decided command, reported to the metrics (a no-op where there are none).
OBSERVE: web.AppKey[Callable[[float], None]] = web.AppKey("observe_command_seconds")

PRINCIPAL = web.RequestKey("principal", Principal)
