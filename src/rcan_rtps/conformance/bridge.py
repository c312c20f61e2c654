"""The bridge under test, seen only through its API (REST): what the probes need of it.

A probe speaks as a role: the principal whose token was given for it. The OWNER's token is
the run's own (`--token`): it reads the audit, approves, and clears the e-stops the safety
cases raise. Other roles' tokens are optional; a case that needs one it was not given fails,
saying which.

The INVOKE cases (§19) invoke one skill of those the bridge lists (`GET /api/skills`; §19.7:
a client never invokes an unlisted one): the one the run names (`--skill`), else the first,
by name, that cannot move the robot (`still_skill`).
"""

from __future__ import annotations

import asyncio
import time
import uuid
from collections.abc import Callable, Mapping
from typing import Any

import aiohttp
import msgspec

from rcan_rtps.rcan.actions import MoveParams, specs

Body = dict[str, Any]


class ConformanceError(Exception):
    """Base of the errors a conformance run reports as a case's failure."""


class MissingToken(ConformanceError):
    def __init__(self, role: str) -> None:
        super().__init__(f"needs a {role} principal's token (--token-for {role}=TOKEN)")


class Reply(msgspec.Struct, frozen=True):
    status: int
    body: Any
    headers: dict[str, str] = msgspec.field(default_factory=dict)

    def get(self, key: str) -> Any:
        return self.body.get(key) if isinstance(self.body, dict) else None

    def describe(self) -> str:
        fields = {k: self.get(k) for k in ("outcome", "error_code", "reason")
                  if self.get(k) is not None}
        return f"HTTP {self.status} {fields or self.body!r}"


class Skill(msgspec.Struct, frozen=True):
    """A skill the bridge lists, as GET /api/skills declares it."""

    name: str
    action: str
    role: str
    params: dict[str, Any] = msgspec.field(default_factory=dict)
    allow: list[str] = msgspec.field(default_factory=list)


# The registry's velocity action (its parameters are MoveParams) and its velocities, each 0 by
# default: a bridge of this version names them so.
_VELOCITY_ACTION = next(s.name for s in specs() if s.params is MoveParams)
_VELOCITIES = tuple(f.name for f in msgspec.structs.fields(MoveParams) if f.name != "duration_s")


def still_skill(skills: Mapping[str, Skill]) -> Skill | None:
    """The first skill, by name, that cannot move the robot: a `move` whose velocities are
    fixed at zero (or left at their zero default) for a fixed duration, the invoker setting
    nothing (a held zero stream would outlive the case)."""
    for name in sorted(skills):
        skill = skills[name]
        if (skill.action == _VELOCITY_ACTION and not skill.allow and "duration_s" in skill.params
                and all(skill.params.get(v, 0) == 0 for v in _VELOCITIES)):
            return skill
    return None


class BridgeUnderTest:
    def __init__(self, session: aiohttp.ClientSession, url: str,
                 tokens: Mapping[str, str], *, skill: str | None = None) -> None:
        self.session = session
        self.url = url.rstrip("/")
        self._tokens = dict(tokens)
        self._skill_name = skill  # the run's --skill
        self._skill: Skill | None = None

    def has(self, role: str) -> bool:
        return role in self._tokens

    async def call(self, role: str, method: str, path: str, body: Any = None,
                   *, public: bool = False) -> Reply:
        headers = {} if public else {"Authorization": f"Bearer {self._token(role)}"}
        async with self.session.request(method, self.url + path, json=body,
                                        headers=headers) as response:
            data = await response.read()
            headers = dict(response.headers)
            try:
                body = msgspec.json.decode(data) if data else None
            except msgspec.DecodeError:  # not one JSON document: JSON lines, CSV, text
                body = data.decode("utf-8", "replace")
            return Reply(response.status, body, headers)

    async def command(self, role: str, body: Body) -> Reply:
        return await self.call(role, "POST", "/api/command", body)

    async def skill(self) -> Skill:
        """The skill the INVOKE cases invoke (see the module's docstring), looked up once."""
        if self._skill is None:
            reply = await self.call("OWNER", "GET", "/api/skills")
            if reply.status != 200:
                raise ProbeError(f"GET /api/skills: {reply.describe()}")
            try:
                listed = msgspec.convert(reply.get("skills"), dict[str, _Declared])
            except msgspec.ValidationError as exc:
                raise ProbeError(f"GET /api/skills: {exc}") from None
            skills = {n: Skill(name=n, action=d.action, role=d.role, params=d.params,
                               allow=d.allow) for n, d in listed.items()}
            self._skill = self._choose(skills)
        return self._skill

    def _choose(self, skills: Mapping[str, Skill]) -> Skill:
        if self._skill_name is not None:
            if self._skill_name not in skills:
                raise ProbeError(f"--skill {self._skill_name}: not listed by GET /api/skills "
                                 f"(listed: {', '.join(sorted(skills)) or 'none'})")
            return skills[self._skill_name]
        found = still_skill(skills)
        if found is None:
            raise ProbeError("no listed skill is sure to move nothing (a move fixed at zero "
                             "velocity for a fixed duration): name a harmless one with --skill "
                             f"(listed: {', '.join(sorted(skills)) or 'none'})")
        return found

    async def invoke(self, role: str, skill: Skill, msg_id: str, *,
                     timeout_ms: int | None = None) -> Reply:
        """An INVOKE of `skill` with nothing set by the invoker, in §3's form (MessageType
        11, `skill_id`); the reply is its INVOKE_RESULT."""
        body: Body = {"message_type": 11, "skill_id": skill.name, "params": {},
                      "msg_id": msg_id}
        if timeout_ms is not None:
            body["timeout_ms"] = timeout_ms
        return await self.command(role, body)

    async def status(self) -> Body:
        reply = await self.call("OWNER", "GET", "/api/status")
        if reply.status != 200 or not isinstance(reply.body, dict):
            raise ProbeError(f"GET /api/status: {reply.describe()}")
        return reply.body

    async def head_seq(self) -> int:
        reply = await self.call("OWNER", "GET", "/api/audit?since=0&limit=1")
        if reply.status != 200:
            raise ProbeError(f"GET /api/audit: {reply.describe()}")
        return int(reply.get("head_seq"))

    async def entries_since(self, seq: int) -> list[Body]:
        return [msgspec.json.decode(line) for line in await self.lines_since(seq)]

    async def lines_since(self, seq: int) -> list[bytes]:
        """The entries after `seq`, each byte for byte as the log holds it (so a signature
        can be checked), page after page."""
        found: list[bytes] = []
        while True:
            async with self.session.get(
                    f"{self.url}/api/audit?since={seq}",
                    headers={"Authorization": f"Bearer {self._token('OWNER')}"}) as response:
                data = await response.read()
            if response.status == 429:  # the reader is busy: a bound, not a fault
                await asyncio.sleep(0.2)
                continue
            if response.status != 200:
                raise ProbeError(f"GET /api/audit: HTTP {response.status} {data[:200]!r}")
            page = msgspec.json.decode(data, type=_RawPage)
            found += [bytes(line) for line in page.entries]
            if page.next_since in (seq, page.head_seq):
                return found
            seq = page.next_since

    async def wait_for_entry(self, since: int, match: Callable[[Body], bool],
                             timeout_s: float = 5.0) -> Body | None:
        """The first entry after `since` that `match`es, once it is in the log."""
        deadline = time.monotonic() + timeout_s
        while True:
            for entry in await self.entries_since(since):
                if match(entry):
                    return entry
            if time.monotonic() > deadline:
                return None
            await asyncio.sleep(0.1)

    async def clear_estop(self) -> None:
        """Leave the robot as the case found it: unlatched (an OWNER's clear)."""
        reply = await self.command("OWNER", {"action": "clear_estop"})
        if reply.get("outcome") != "executed":
            raise ProbeError(f"could not clear the e-stop it raised: {reply.describe()}")

    def _token(self, role: str) -> str:
        token = self._tokens.get(role)
        if token is None:
            raise MissingToken(role)
        return token


class _Declared(msgspec.Struct):
    action: str
    role: str
    params: dict[str, Any] = msgspec.field(default_factory=dict)
    allow: list[str] = msgspec.field(default_factory=list)


class _RawPage(msgspec.Struct):
    entries: list[msgspec.Raw]
    next_since: int
    head_seq: int


class ProbeError(ConformanceError):
    """The bridge answered something a probe cannot go on from."""


def message_id() -> str:
    return str(uuid.uuid4())  # the 1.2 forms want a UUID
