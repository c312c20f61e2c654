"""Helpers of the velocity-stream tests: a manual loop timer, a wire recorder, a governor.

`Wire` records every velocity the bridge would put on cmd_vel, in order: the first sample of
a move (its dispatch), each stream sample (`send_velocity`), and the zero of every halt
(`stop`, `estop`, a safe stop). `ManualTimer` fires the streams' timers only when advanced.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from pathlib import Path

from govhelpers import RURI
from recording import RecordingDispatcher

from rcan_rtps.config import loads_config
from rcan_rtps.governance import DispatchResult
from rcan_rtps.governance.audit import AuditLog
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.governor import Governor
from rcan_rtps.governance.streams import Velocity
from rcan_rtps.rcan import ActionParams, MoveParams, NormalizedCommand

MAX_LINEAR, MAX_ANGULAR = 1.0, 0.5
LINEAR_ACCEL, ANGULAR_ACCEL = 2.0, 1.0
RATE_HZ = 20.0
CONFIG = """\
robot: {ruri: "%(ruri)s"}
bridge:
  ros2: {namespace: /robot1, cmd_rate_hz: %(rate)s}
  api: {principals: [{name: low-agent, role: USER, token_env: RCAN_LOW_AGENT_TOKEN}]}
  safety:
    max_linear_vel: %(lin)s
    max_angular_vel: %(ang)s
    max_linear_accel: %(lacc)s
    max_angular_accel: %(aacc)s
    max_move_duration_s: 10
  motion:
    role_priorities: {USER: 10, OWNER: 50, CREATOR: 50}
    principal_priorities: {low-agent: 1}
    locks: [{name: teleop, priority: 50}, {name: top, priority: 1000}]
  audit: {path: "%(dir)s/audit.jsonl", key_path: "%(dir)s/audit.key"}
"""


class Handle:
    def __init__(self) -> None:
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class ManualTimer:
    """A loop's `time`/`call_at`, moved only by `advance`."""

    def __init__(self) -> None:
        self.now = 0.0
        self._due: list[tuple[float, int, Callable[[], object], Handle]] = []
        self._order = itertools.count()

    def time(self) -> float:
        return self.now

    def call_at(self, when: float, callback: Callable[[], object]) -> Handle:
        handle = Handle()
        heapq.heappush(self._due, (when, next(self._order), callback, handle))
        return handle

    def advance(self, seconds: float) -> None:
        until = self.now + seconds
        while self._due and self._due[0][0] <= until:
            when, _, callback, handle = heapq.heappop(self._due)
            self.now = max(self.now, when)
            if not handle.cancelled:
                callback()
        self.now = until


class Wire(RecordingDispatcher):
    """Every velocity sent, in order."""

    def __init__(self) -> None:
        super().__init__()
        self.wire: list[Velocity] = []

    async def dispatch(self, command: NormalizedCommand,
                       applied: ActionParams) -> DispatchResult:
        result = await super().dispatch(command, applied)
        if result.ok and isinstance(applied, MoveParams):
            self.wire.append(Velocity.of(applied))
        elif result.ok and command.spec.stopping:
            self.wire.append(Velocity())
        return result

    def send_velocity(self, velocity: MoveParams) -> str | None:
        why = super().send_velocity(velocity)
        if why is None:
            self.wire.append(Velocity.of(velocity))
        return why


async def stream_governor(tmp: Path, *, rate_hz: float = RATE_HZ,
                          linear_accel: float = LINEAR_ACCEL
                          ) -> tuple[Governor, Wire, ManualTimer, AuditLog]:
    config = loads_config(CONFIG % {
        "ruri": RURI, "dir": tmp, "rate": rate_hz, "lin": MAX_LINEAR, "ang": MAX_ANGULAR,
        "lacc": linear_accel, "aacc": ANGULAR_ACCEL}, env={})
    log = await AuditLog.open(config.bridge.audit.path, config.bridge.audit.key_path,
                              ruri=RURI, clock=ManualClock())
    wire, timer = Wire(), ManualTimer()
    gov = Governor.from_config(config, audit=log, dispatcher=wire, clock=ManualClock())
    gov.streams._timer = timer  # type: ignore[assignment]
    return gov, wire, timer, log
