"""Helpers of the governance tests: principals, commands, a recording dispatcher, a harness.

The dispatcher records what governance would hand to the bridge; governance has no DDS.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import tracemalloc
from collections.abc import Awaitable, Callable, Coroutine, Mapping
from pathlib import Path
from typing import Any, TypeVar

from recording import RecordingDispatcher

from rcan_rtps.config import RcanConfig, loads_config
from rcan_rtps.governance.audit import AuditLog, AuditRecord
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.governor import Decision, Governor
from rcan_rtps.governance.hitl import Notifier
from rcan_rtps.governance.rbac import DEFAULT_RATE_LIMITS, Principal
from rcan_rtps.rcan import NormalizedCommand, Role, validate_command
from rcan_rtps.rcan.actions import specs

RURI = "rcan://registry.local/clearpath/husky/a200-0001"
ARM_GATE = "[{action: arm_joint, require_auth: true, authorized_roles: [OWNER]}]"
CONFIG = """\
robot: {ruri: "%(ruri)s"}
bridge:
  ros2: {namespace: /robot1}
  api: {auth_token_env: RCAN_BRIDGE_TOKEN}
  hitl:
    timeout_seconds: %(hitl_timeout)s
    gates: %(gates)s
    %(hitl_extra)s
  safety:
    max_linear_vel: 1.0
    max_angular_vel: 0.5
    workspace: [[-10, -10], [10, -10], [10, 10], [-10, 10]]
    %(safety_extra)s
  audit: {path: "%(dir)s/audit.jsonl", key_path: "%(dir)s/audit.key"}
"""


def principal(name: str, role: Role) -> Principal:
    return Principal(name, role, DEFAULT_RATE_LIMITS[role])


OPS = principal("ops", Role.OWNER)
ADMIN = principal("root", Role.CREATOR)
PLANNER = principal("planner", Role.USER)
VIEWER = principal("viewer", Role.GUEST)


def command(
    action: str, params: Mapping[str, Any] | None = None, **extra: Any
) -> NormalizedCommand:
    body = {"action": action, "params": dict(params or {}), **extra}
    return validate_command(json.dumps(body).encode())


def audit_entries(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


class Harness:
    def __init__(self, tmp: Path, clock: ManualClock) -> None:
        self.tmp = tmp
        self.clock = clock
        self.dispatcher = RecordingDispatcher()
        self.logs: list[AuditLog] = []
        self.governors: list[Governor] = []

    def config(self, hitl_extra: str = "", gates: str = ARM_GATE,
               safety_extra: str = "", hitl_timeout: float = 300) -> RcanConfig:
        text = CONFIG % {"ruri": RURI, "dir": self.tmp, "hitl_extra": hitl_extra,
                         "gates": gates, "safety_extra": safety_extra,
                         "hitl_timeout": hitl_timeout}
        return loads_config(text, env={})

    async def governor(self, hitl_extra: str = "", notifier: Notifier | None = None,
                       group_commit: bool = True, gates: str = ARM_GATE,
                       safety_extra: str = "", hitl_timeout: float = 300) -> Governor:
        config = self.config(hitl_extra, gates, safety_extra, hitl_timeout)
        log = await AuditLog.open(config.bridge.audit.path, config.bridge.audit.key_path,
                                  ruri=RURI, clock=self.clock, group_commit=group_commit)
        self.logs.append(log)
        governor = Governor.from_config(config, audit=log, dispatcher=self.dispatcher,
                                        clock=self.clock, notifier=notifier)
        self.governors.append(governor)
        return governor

    async def restart(self) -> None:
        """The process ends without a clean stop (no BRIDGE_STOPPED): its audit logs are
        closed, and its governors' e-stop machines end with it — one dropped running would
        leave its worker task pending for the garbage collector ("Task was destroyed but it
        is pending!" in the log, at whatever test the collector runs in)."""
        for governor in self.governors:
            await governor.latch.close()
        self.governors.clear()
        for log in self.logs:
            await log.close()
        self.logs.clear()

    @property
    def entries(self) -> list[dict[str, Any]]:
        return audit_entries(self.tmp / "audit.jsonl")


def withdrawals_missed(gov: Governor) -> None:
    """No stop withdraws held motion any more, as if that step had failed (`HitlDesk.
    withdrawing` picks nothing): what the checks of an approval (`Governor._run_approved`)
    do on their own, the backstop."""
    gov._desk.withdrawing = lambda issuer, which: []  # type: ignore[method-assign]


class LossTrial:
    """One trial of a principal's loss racing its motion, as the dispatcher saw it from the
    trial's start: what of the lost principal's motion outlived the loss."""

    def __init__(self, dispatcher: RecordingDispatcher) -> None:
        self.dispatcher = dispatcher
        self.goals_before, self.calls_before = dispatcher._goals, len(dispatcher.calls)

    def outliving(self, gov: Governor, lost: Principal) -> list[str]:
        """"stream" while `lost`'s stream drives; "goal" for a goal sent in the trial that was
        neither cancelled by its id nor by a robot-wide halt after it (a goal that took the
        base was cancelled by the halt the loss then was)."""
        found: list[str] = []
        active = gov.streams.active
        if active is not None and active.owner == lost.name:
            found.append("stream")
        goals = {f"goal-{k}" for k in range(self.goals_before + 1, self.dispatcher._goals + 1)}
        calls = [a for a, _ in self.dispatcher.calls[self.calls_before:]]
        halted = "navigate" in calls and "stop" in calls[calls.index("navigate"):]
        if goals - set(self.dispatcher.cancelled) and not halted:
            found.append("goal")
        return found


MOTION_ACTIONS = frozenset(spec.name for spec in specs() if spec.motion)


def motion_held_at(gov: Governor, harness: Harness, where: str
                   ) -> tuple[asyncio.Event, asyncio.Event]:
    """Motion waits at `where` (`ready`: for the robot; `write_ahead`: for its entry) until
    the first event is set; the second is set once it waits there."""
    release = asyncio.Event()
    if where == "ready":
        harness.dispatcher.hold_ready = release
        return release, harness.dispatcher.ready_entered
    entered = asyncio.Event()
    write_ahead = gov._steps.write_ahead

    async def held_write(entry: AuditRecord, *, urgent: bool = False) -> Any:
        if entry.action_type in MOTION_ACTIONS:
            entered.set()
            await release.wait()
        return await write_ahead(entry, urgent=urgent)

    gov._steps.write_ahead = held_write  # type: ignore[method-assign]
    return release, entered


async def held_motion_stopped(gov: Governor, harness: Harness, where: str,
                              motion: Coroutine[Any, Any, Decision],
                              stop: Callable[[], Awaitable[Decision | None]]) -> Decision | None:
    """`motion` waits at `where` (`motion_held_at`) when `stop` comes; then it goes on and is
    refused `stopped`, and the governor's tasks end. The stop's decision."""
    release, entered = motion_held_at(gov, harness, where)
    moving = asyncio.ensure_future(motion)
    await asyncio.wait_for(entered.wait(), timeout=10)
    stopped = await stop()
    release.set()
    moved = await moving
    assert (moved.http_status, moved.reason) == (409, "stopped"), moved
    await asyncio.gather(*gov._tasks)
    return stopped


T = TypeVar("T")


def fresh_copy(written: Path, tmp: Path) -> Path:
    """A fresh copy of the files of a log written once for a module (a start appends to
    them); the log's path."""
    for file in written.iterdir():
        shutil.copy2(file, tmp / file.name)
    return tmp / "audit.jsonl"


def peak_of(call: Callable[[], T]) -> tuple[T, int]:
    """What `call` returns, and the most memory it held at once (every thread's)."""
    tracemalloc.start()
    try:
        return call(), tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
