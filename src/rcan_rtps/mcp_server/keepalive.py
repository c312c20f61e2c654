"""Heartbeats for the motion this server started, while it runs.

The bridge stops the robot when the sender of a motion command goes quiet for
`safety.session_timeout_s` (§10.8): a timed move or a goal is no exception. An agent waits in
silence between tool calls, so this server holds the session for it — for as long as a move
it started lasts, or a goal it started has not ended — and for nothing else: once the agent's
motion is over (or stopped), the heartbeats stop, and if this server goes away, so do they,
and the bridge halts what is left. So they do once the principal's credential has run out
(a heartbeat refused 401: a JWT past its exp, with no fresher one of the principal's since):
what it left moving is then the bridge's to stop when its control session lapses.

One `Keepalive` per agent principal (heartbeats are a principal's); each hold remembers the
MCP session that started it, so a session that closes can stop what it left running
(`release_session`) without touching another session's.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass

from .ports import BridgeUnavailable, RobotApi

log = logging.getLogger(__name__)
INTERVAL_S = 1.0  # the demo's session timeout is 5 s; a config's is at least this, or close
MARGIN_S = 1.0  # past a move's end: its final zero is sent by the bridge, not by anyone here
UNAUTHENTICATED = 401  # a heartbeat without a valid credential
GOAL_ENDED = frozenset({"succeeded", "canceled", "aborted", "rejected", "unknown", "lost"})


@dataclass
class Hold:
    until: float | None = None  # monotonic end of a timed move
    goal_id: str | None = None  # a goal, until it ends
    session: str | None = None  # the MCP session that started it (None: stdio's only one)

    def running(self, now: float) -> bool:
        return self.until is None or self.until > now


class Keepalive:
    def __init__(self, bridge: RobotApi, *, interval_s: float = INTERVAL_S) -> None:
        self._bridge = bridge
        self._interval = interval_s
        self._holds: dict[str, Hold] = {}
        self._wake = asyncio.Event()
        self._calling: dict[str, int] = {}  # commands being decided, per MCP session
        # Sessions closed while a command of theirs was being decided (until it is): what
        # it starts is not held for them (`calling`).
        self._closed: set[str] = set()

    @property
    def holding(self) -> bool:
        """Whether motion this server started may still run (a move not yet over, a goal not
        known to have ended)."""
        now = time.monotonic()
        return any(h.running(now) for h in self._holds.values())

    def hold_for(self, key: str, seconds: float, session: str | None = None) -> None:
        self._hold(key, Hold(until=time.monotonic() + seconds + MARGIN_S, session=session))

    def hold_goal(self, key: str, goal_id: str, session: str | None = None) -> None:
        self._hold(key, Hold(goal_id=goal_id, session=session))

    def release(self, key: str) -> None:
        """One hold's motion was stopped: it is not held any more."""
        self._holds.pop(key, None)

    def release_all(self) -> None:
        """The robot was stopped: nothing this server started runs any more."""
        self._holds.clear()

    @contextlib.contextmanager
    def calling(self, session: str | None) -> Iterator[None]:
        """A command of `session`'s being decided: motion it may start counts as running for
        the session's close (`release_session`), from before it is decided."""
        if session is None:
            yield
            return
        self._calling[session] = self._calling.get(session, 0) + 1
        try:
            yield
        finally:
            left = self._calling.pop(session) - 1
            if left:
                self._calling[session] = left
            else:
                self._closed.discard(session)

    def release_session(self, session: str) -> bool:
        """Forget a closed session's holds: whether any of them may still be running, or a
        command of its is being decided (the stop that follows must stop it too: it would
        start after the session closed, and be held for nobody)."""
        now = time.monotonic()
        mine = [k for k, h in self._holds.items() if h.session == session]
        running = any(self._holds.pop(k).running(now) for k in mine)
        if session in self._calling:
            self._closed.add(session)
            return True
        return running

    def _hold(self, key: str, hold: Hold) -> None:
        if hold.session in self._closed:  # closed while it was decided: stopped, not held
            log.info("motion of MCP session %s, closed meanwhile: not held", hold.session)
            return
        self._holds[key] = hold
        self._wake.set()

    async def run(self) -> None:
        """Until cancelled: a heartbeat every interval while anything is held."""
        while True:
            if not self._holds:
                self._wake.clear()
                await self._wake.wait()
            await self._prune()
            if self._holds:
                await self._beat()
            await asyncio.sleep(self._interval)

    async def _prune(self) -> None:
        now = time.monotonic()
        for key, hold in list(self._holds.items()):
            if hold.until is not None and now >= hold.until:
                del self._holds[key]
            elif hold.goal_id is not None and await self._goal_over(hold.goal_id):
                self._holds.pop(key, None)

    async def _goal_over(self, goal_id: str) -> bool:
        try:
            reply = await self._bridge.goal(goal_id)
        except BridgeUnavailable as exc:
            log.warning("goal %s: %s", goal_id, exc)
            return False  # keep the session: the bridge decides when it is lost
        return reply.status == 404 or reply.body.get("state") in GOAL_ENDED

    async def _beat(self) -> None:
        try:
            reply = await self._bridge.heartbeat()
        except BridgeUnavailable as exc:
            log.warning("heartbeat: %s", exc)
            return
        if reply.status == UNAUTHENTICATED:  # its credential ran out: no heartbeat holds
            log.warning("heartbeat refused (%s): the principal's credential is no longer "
                        "valid; its motion is not held any more (the bridge stops it when "
                        "its control session lapses)", reply.body.get("reason"))
            self.release_all()
        elif not reply.ok:
            log.warning("heartbeat refused: %s %s", reply.status, reply.body.get("error_code"))
