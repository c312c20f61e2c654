"""What a start takes up from the audit log: the e-stop latch and the motion locks held.

The latch file says whether the e-stop is latched, but a file can be rewritten (`latched:
false`) or lost; the audit chain is signed. A start therefore latches if *either* says so: the
log's last word on the latch is read from its tail, back to the last BRIDGE_STARTED or
BRIDGE_STOPPED (each records the latch, and the locks, as they were then).

Locks are taken up the same way: the locks of the last start or stop, plus the `lock`s and
less the `unlock`s executed after it. A start re-engages them (fail closed: a lock keeps lower
priorities off the base) and records them in its BRIDGE_STARTED entry; one the config no longer
declares is recorded there as released.

A run that did not end with BRIDGE_STOPPED (killed, out of memory, the board's power cut) left
its motion to nobody: every session of it was lost, and a lost session's motion halts
(docs/governance.md). So the same replay lists the motion that run started and no later entry
shows ended (`LeftRunning`): arm trajectories still due (running `Hold.runs_for_s` of the
`applied` parameters, as the dispatcher counted them, from their entry: by the boot clock it
records when this start is in the same boot, else from its `timestamp_ms` by the wall clock:
`LeftArm.left_ms`), goals (their `goal_id`, written ahead since goals were sent with an id chosen
before their entry; older entries have none) and velocity streams. A start halts them
(`Governor.start`). Ended: GOAL_FINISHED of an end its server listed (not `unknown`, not
`lost`), STREAM_ENDED, a COMMAND_FAILED of the command
(its principal's and action's: a failed hold or cancel under its id ended nothing;
one naming a goal did not end it: its send gave up, the server may accept it late), a
later trajectory of the same joints on the same topic (it replaced it, unless its own
COMMAND_FAILED follows: refused once written ahead, it was never sent; the newest such
replacement may not have been sent either — the crash came between its entry and its
publish — so what it replaced stays listed while due), a move whose entry says it replaced
a stream (`applied.replaces`: that stream's end has no entry of its own; given back, and
listed, on the same terms as a replaced trajectory), a stop of everyone's
motion (a `stop`, an e-stop, a safe stop of the whole robot) unless that stop's own
COMMAND_FAILED follows, and a stop of one principal's motion for what it says it stopped.

A clean stop may leave goals as well: those whose send gave up that their server had not yet
accepted, which its BRIDGE_STOPPED names (`params.left_running`, `Governor.stop`); they are
listed (`Resumed.left`, not `crashed`) for the start to cancel.

A run may be months long; its replay would grow with it (0.57 s per 100 000 entries), and the
e-stop waits for the start. So the running bridge writes the replay's state beside the log at
each audit checkpoint (`<log>.resume`, a start point: `write_point`, from the previous point on),
signed with the log's key and naming the last entry it covers (its seq, audit_id and byte span).
A start replays from the later of the last boundary and that entry: the same result
(`tests/governance/test_resume_points.py` checks both ways agree) at a cost bounded by the
entries between checkpoints. A point that is missing, not signed by the key, or does not name
an entry of this log as it stands is not used: the replay goes back to the boundary.
"""

from __future__ import annotations

import base64
import json
import logging
import os
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from rcan_rtps.rcan import Effect
from rcan_rtps.rcan.actions import ActionSpec, Hold, Publish, action_spec, with_effect

from ._durable import atomic_write, read_small
from ._json import decode, decode_as
from .audit import RESUME_POINT_TAG, Checkpoint, carries_its_id
from .clock import BootInstant, system_boot
from .left import LeftArm, LeftGoal, LeftRunning, LeftStream
from .log_tail import lines_backwards

log = logging.getLogger(__name__)

_CHUNK = 64 * 1024
_ENGAGED = ("ESTOP", "ESTOP_REPEATED")
_BOUNDARIES = ("BRIDGE_STARTED", "BRIDGE_STOPPED")
# A start point's file is read whole before its signature can be checked: a larger one is not
# read (the replay goes back to the boundary). The replay's state is far smaller than this.
MAX_POINT_BYTES = 64 * 1024 * 1024
MAX_LEFT = 64  # of each kind: the newest are kept (a run's log may hold any number)
_EXECUTED = ("COMMAND_DISPATCHED", "HITL_AUTHORIZED")  # the entries motion is sent after
_HALTS = ("ESTOP", "NETWORK_LOSS_SAFE_STOP")  # besides an executed `stop`
# A GOAL_FINISHED's outcomes that are an end its server listed. Not `unknown` (a goal accepted
# after its send gave up whose end was not seen: `SentGoals._late_goal`) nor `lost` (its server
# vanished from sight, and may run it still).
_GOAL_ENDS = ("succeeded", "canceled", "aborted", "rejected")


class Resumed(msgspec.Struct):
    """The log's last word: `latched` None when it never spoke of the e-stop; `crashed` when
    the previous run did not end with BRIDGE_STOPPED, and then what it `left` running."""

    latched: bool | None = None
    latched_by: str | None = None
    locks: dict[str, str] = msgspec.field(default_factory=dict)  # name → who engaged it
    crashed: bool = False
    left: LeftRunning = msgspec.field(default_factory=LeftRunning)


def resume(path: Path | str, *, now_ms: int | None = None, boot: BootInstant | None = None,
           pubkey: Ed25519PublicKey | None = None) -> Resumed:
    """Replay the log from its last start or stop on (or from its start point, `pubkey`'s:
    without one, none is used); a missing log is a first start.

    Entries are trusted as they stand: the log was verified when it was opened. `now_ms`:
    the wall time arm trajectories are due against, `boot` the boot clock then (default,
    both: now; `now_ms` given without `boot`: the wall clock alone). The run since the
    boundary may be long (weeks up): its entries are replayed one at a time, never held.
    """
    replay = _Replay()
    if now_ms is None:
        now_ms, boot = int(time.time() * 1000), system_boot()
    try:
        replay.run(Path(path), pubkey)
        # (inside: working out when an arm is due may overflow, as an entry may be misshapen)
        return replay.result(now_ms, boot)
    # It verified at open: this is no time to trust it. An entry of a shape this version
    # does not expect (another version's) fails closed as well, never a traceback — an arm
    # run for a time out of range included (OverflowError working out when it is due).
    # (RecursionError: a line nested thousands of levels deep, which Python's json refuses so)
    except (OSError, ValueError, TypeError, AttributeError, ArithmeticError,
            RecursionError) as exc:
        return Resumed(latched=True, latched_by=f"an unreadable audit tail ({exc!r})")


class _Replay:
    """The replay's state: the log's last word so far and the motion still running."""

    def __init__(self) -> None:
        self.found = Resumed()
        self.motion = _Motion()
        self.last_event: str | None = None  # of the last entry replayed (None: none yet)

    def run(self, path: Path, pubkey: Ed25519PublicKey | None, *,
            until: int | None = None) -> None:
        """Replay the entries from the boundary or the start point, to `until` (a line's
        end; default the file's)."""
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            return
        try:
            size = os.fstat(fd).st_size
            if until is not None:
                if until > size:  # the file was cut below the checkpoint (by someone else)
                    raise ValueError(f"the log ends at {size}, before {until}")
                size = until
            torn_at = None if _ends_line(fd, size) else size  # a crash mid-append
            point = _usable_point(fd, path, size, pubkey)
            boundary = _boundary_at(fd, size, torn_at, floor=0 if point is None else point.end)
            if point is not None and boundary is None:
                self._restore(point)
            for entry in _forwards(fd, _start_at(point, boundary), size, torn_at):
                self.apply(entry)
        finally:
            os.close(fd)

    def apply(self, entry: dict[str, Any]) -> None:
        event = entry.get("event")
        self.last_event = event if isinstance(event, str) else ""
        _apply(self.found, entry)
        self.motion.apply(entry)

    def result(self, now_ms: int, boot: BootInstant | None) -> Resumed:
        found = msgspec.structs.replace(self.found, locks=dict(self.found.locks))
        # No boundary at all in a log with entries is no clean stop either: fail closed.
        found.crashed = self.last_event is not None and self.last_event != "BRIDGE_STOPPED"
        # (after a clean stop: only the goals its BRIDGE_STOPPED named, `Governor.stop`)
        found.left = self.motion.left(now_ms, boot)
        return found

    def point(self, cp: Checkpoint) -> StartPoint:
        motion = self.motion
        return StartPoint(
            seq=cp.seq, audit_id=cp.audit_id, start=cp.start, end=cp.end,
            last_event=self.last_event, latched=self.found.latched,
            latched_by=self.found.latched_by, locks=dict(self.found.locks),
            motion=_MotionState.of(motion.running(), motion._halted))

    def _restore(self, point: StartPoint) -> None:
        self.last_event = point.last_event
        self.found = Resumed(latched=point.latched, latched_by=point.latched_by,
                             locks=dict(point.locks))
        state, motion = point.motion, self.motion
        motion.set_running(state.running())
        motion._halted = {_frozen(k): h.running() for k, h in state.halted}


V = TypeVar("V")


def _by_key(pairs: list[tuple[tuple[Any, str, Any], V]]) -> dict[_Key, V]:
    """A point's (key, value) pairs as `_Motion`'s dictionary, each key as it was made."""
    return {_frozen(key): value for key, value in pairs}


def _frozen(key: tuple[Any, str, Any]) -> _Key:
    """A key read back from a point: JSON holds a tuple inside it (a goal taken up by its id,
    `_taken_up_key`) as a list, which no dict can hold as a key."""
    principal, message_id, action = key
    return principal, message_id, tuple(action) if isinstance(action, list) else action


def _start_at(point: StartPoint | None, boundary: int | None) -> int:
    if boundary is not None:
        return boundary
    return 0 if point is None else point.end


# A command, as its entries name it: message ids are unique per principal only, and a
# hold or cancel of a command's motion (an INVOKE's timeout, its client gone) bears the
# command's id under an action of its own (`hold_trajectory`, `cancel_goal`): its
# COMMAND_FAILED says that motion runs on, not that the command failed.
_Key = tuple[Any, str, Any]  # (principal, message id, action)


def _key(entry: dict[str, Any]) -> _Key:
    return entry.get("principal"), str(entry.get("message_id")), entry.get("action_type")


def _key_of(left: LeftArm | LeftGoal | LeftStream) -> _Key:
    return left.principal, left.message_id, left.action


class _Running(NamedTuple):
    """`_Motion`'s running motion and what it replaced, as a stop found it."""

    arms: dict[_Key, LeftArm]
    goals: dict[_Key, LeftGoal]
    streams: dict[_Key, LeftStream]
    replaced: dict[_Key, list[LeftArm]]
    replaced_streams: dict[_Key, list[LeftStream]]


class _Motion:
    """The motion sent since the boundary, less what ended, replayed oldest first."""

    def __init__(self) -> None:
        self.arms: dict[_Key, LeftArm] = {}  # (insertion order: oldest first)
        self.goals: dict[_Key, LeftGoal] = {}
        self.streams: dict[_Key, LeftStream] = {}
        # A trajectory → the arms it replaced, given back if its own COMMAND_FAILED follows
        # (written ahead, then refused: it was never sent).
        self._replaced: dict[_Key, list[LeftArm]] = {}
        # A move → the stream its entry says it replaced, the same way. (Kept in `streams`,
        # every replaced move of a long run piled up there and in each start point.)
        self._replaced_streams: dict[_Key, list[LeftStream]] = {}
        # A stop → what it ended, given back if its own COMMAND_FAILED follows.
        self._halted: dict[_Key, _Running] = {}

    def running(self) -> _Running:
        return _Running(self.arms, self.goals, self.streams, self._replaced,
                        self._replaced_streams)

    def set_running(self, running: _Running) -> None:
        (self.arms, self.goals, self.streams, self._replaced,
         self._replaced_streams) = running

    def left(self, now_ms: int, boot: BootInstant | None) -> LeftRunning:
        # Fail closed: the bridge may have died between a trajectory's write-ahead entry and
        # its publish (nothing in the log tells), and then the one it replaced runs on. Both
        # are listed while due; a hold of an arm the later one did stop holds it at rest.
        replaced = [run for by, runs in self._replaced.items() if by in self.arms
                    for run in runs]
        streams = {_key_of(s): s for by, ended in self._replaced_streams.items()
                   if by in self.streams for s in ended}
        return LeftRunning(
            arms=_arms_left([a for a in (*replaced, *self.arms.values())
                             if a.left_ms(now_ms, boot) > 0], now_ms, boot),
            goals=_goals_left(list(self.goals.values())),
            streams=list({**streams, **self.streams}.values())[-MAX_LEFT:])

    def apply(self, entry: dict[str, Any]) -> None:
        event, message_id = entry.get("event"), entry.get("message_id")
        if event in _BOUNDARIES:  # what a start set out to take back, or a stop left, runs on
            given = entry.get("params")
            self._taken_up((given if isinstance(given, dict) else {}).get("left_running"))
        elif event in _EXECUTED and entry.get("outcome") == "executed":
            self._executed(entry)
        elif event in _HALTS:
            self._halt(entry)
        elif event == "COMMAND_FAILED" and isinstance(message_id, str):
            sent = self.goals.get(_key(entry))
            self._failed(_key(entry))
            self._may_run(entry, sent)
        elif event == "GOAL_FINISHED":
            self._goal_finished(entry)
        elif event == "STREAM_ENDED" and isinstance(message_id, str):
            self._stream_ended(message_id)

    def _executed(self, entry: dict[str, Any]) -> None:
        try:
            spec = action_spec(str(entry.get("action_type")))
        except KeyError:  # not an action of the registry (cancel_goal): nothing it started
            return
        message_id, topic = str(entry.get("message_id")), entry.get("ros2_topic")
        principal = entry.get("principal")
        if spec.effect is Effect.HALT:
            self._halted_all(_key(entry))
        elif spec.starts_goal:
            self.goals[_key(entry)] = LeftGoal(
                message_id=message_id, action=spec.name, principal=principal, server=topic,
                goal_id=_goal_id(entry.get("goal_id")))
        elif spec.streamed:
            self._stream(entry, LeftStream(message_id=message_id, action=spec.name,
                                           principal=principal, topic=topic))
        elif isinstance(spec.ros, Publish) and spec.ros.hold is not None:
            self._trajectory(entry, spec, spec.ros.hold, message_id)

    def _trajectory(self, entry: dict[str, Any], spec: ActionSpec[Any], hold: Hold[Any],
                    message_id: str) -> None:
        applied = entry.get("applied")
        try:
            params = msgspec.convert(applied, spec.params)
            joints, runs_for_s = list(hold.joints(params)), float(hold.runs_for_s(params))
        except (msgspec.ValidationError, TypeError, ValueError):
            return  # not what an executed command's entry holds: nothing was sent for it
        boot_id, boot_ms = _boot_stamp(entry)
        arm = LeftArm(message_id=message_id, action=spec.name, principal=entry.get("principal"),
                      topic=entry.get("ros2_topic"), params=dict(applied or {}),
                      joints=joints, sent_at_ms=int(entry.get("timestamp_ms") or 0),
                      runs_for_s=runs_for_s, sent_boot_id=boot_id, sent_boot_ms=boot_ms)
        replaced = {k: run for k, run in self.arms.items()  # the controller replaced them
                    if run.topic == arm.topic and set(run.joints) == set(arm.joints)}
        for k in replaced:
            del self.arms[k]
        if replaced:
            self._replaced[_key(entry)] = list(replaced.values())
            _keep_newest(self._replaced)
        self.arms[_key(entry)] = arm

    def _stream(self, entry: dict[str, Any], stream: LeftStream) -> None:
        """A move's stream; the one its entry says it replaced ends, set aside (no
        STREAM_ENDED of it follows: `StreamEnded.recorded`)."""
        key, ended = _key(entry), _replaced_id(entry.get("applied"))
        if ended is not None:
            replaced = [s for k, s in self.streams.items() if k[1] == ended and k != key]
            if replaced:
                self.streams = {k: s for k, s in self.streams.items()
                                if k[1] != ended or k == key}
                self._replaced_streams[key] = replaced
                _keep_newest(self._replaced_streams)
        self.streams[key] = stream

    def _stream_ended(self, message_id: str) -> None:
        """Its owner's, where the command's entry may name its approver: by id alone. Set
        aside, it ends there too; as a replacer, what it replaced is let go (it ran)."""
        self.streams = {k: s for k, s in self.streams.items() if k[1] != message_id}
        self._replaced_streams = {
            by: running for by, ended in self._replaced_streams.items() if by[1] != message_id
            if (running := [s for s in ended if s.message_id != message_id])}

    def _halt(self, entry: dict[str, Any]) -> None:
        applied = entry.get("applied")
        facts: dict[str, Any] = applied if isinstance(applied, dict) else {}
        if facts.get("scope") == "own":
            self._own_stop(str(entry.get("principal")), facts)
            return
        # An e-stop, a safe stop of the whole robot, a start's halt of a crash.
        self._halted_all(_key(entry))
        if facts.get("scope") in ("crash", "stopped"):
            self._still_left(facts)

    def _still_left(self, facts: dict[str, Any]) -> None:
        """What a start's halt of a crashed run could not take back (an arm not held, a
        goal no server answered for) runs on: listed again, for the next start to try."""
        still = set(facts.get("still_left") or ())
        self._taken_up(facts.get("left"), lambda message_id: message_id in still)

    def _taken_up(self, facts: Any, chosen: Callable[[str], bool] = lambda _: True) -> None:
        """The motion an entry lists as left by a crashed run (`LeftRunning.facts`), those
        `chosen`, as running still."""
        try:
            left = msgspec.convert(facts or {}, LeftRunning)
        except msgspec.ValidationError as exc:
            # Motion the entry says runs on, unreadable: never dropped in silence (its goals
            # would run with nobody to cancel them). The start fails closed: latched.
            raise ValueError(f"motion left running, unreadable: {exc}") from exc
        self.arms.update((_key_of(a), a) for a in left.arms if chosen(a.message_id))
        goals = (msgspec.structs.replace(g, goal_id=_goal_id(g.goal_id)) for g in left.goals
                 if chosen(g.message_id))
        self.goals.update((_taken_up_key(g), g) for g in goals)
        self.streams.update((_key_of(s), s) for s in left.streams if chosen(s.message_id))

    def _halted_all(self, stop: _Key) -> None:
        self._halted[stop] = self.running()
        self.set_running(_Running({}, {}, {}, {}, {}))
        _keep_newest(self._halted)

    def _own_stop(self, principal: str, facts: dict[str, Any]) -> None:
        """A stop of `principal`'s motion alone: its goals it cancelled and its arms on the
        topics it held end; the arms it could not hold run on."""
        cancelled = set(facts.get("goals_cancelled") or ())
        held = set(facts.get("arms_held") or ())
        self.goals = {m: g for m, g in self.goals.items()
                      if not (g.principal == principal and g.goal_id in cancelled)}
        self.arms = {m: a for m, a in self.arms.items()
                     if not (a.principal == principal and a.topic in held)}
        self._replaced = {m: kept for m, arms in self._replaced.items()
                          if (kept := [a for a in arms
                                       if not (a.principal == principal and a.topic in held)])}
        self.streams = {m: s for m, s in self.streams.items() if s.principal != principal}
        self._replaced_streams = {
            m: others for m, ended in self._replaced_streams.items()
            if (others := [s for s in ended if s.principal != principal])}

    def _failed(self, command: _Key) -> None:
        """The send of `command` failed: it started nothing — or, a stop's, ended nothing."""
        for running in (self.arms, self.goals, self.streams):
            running.pop(command, None)
        # A trajectory or move refused after its entry replaced nothing: that runs on.
        self.arms = {**{_key_of(a): a for a in self._replaced.pop(command, ())}, **self.arms}
        self.streams = {**{_key_of(s): s for s in self._replaced_streams.pop(command, ())},
                        **self.streams}
        given_back = self._halted.pop(command, None)
        if given_back is not None:
            self.set_running(_merged(given_back, self.running()))

    def _may_run(self, failed: dict[str, Any], sent: LeftGoal | None) -> None:
        """A COMMAND_FAILED naming a goal: its send gave up after the request went out (the
        server may accept it late), or it was accepted and was being cancelled. Failed, it
        is not ended: listed until its GOAL_FINISHED (fails closed; a cancel by id of a goal
        the server never had cancels nothing)."""
        if not isinstance(failed.get("goal_id"), str):
            return
        self.goals[_key(failed)] = LeftGoal(
            message_id=str(failed.get("message_id")), action=str(failed.get("action_type")),
            principal=failed.get("principal"),
            server=sent.server if sent is not None else None,  # (None: asked of every one)
            goal_id=_goal_id(failed.get("goal_id")))

    def _goal_finished(self, entry: dict[str, Any]) -> None:
        if entry.get("outcome") not in _GOAL_ENDS:
            return  # no end seen (`unknown`, `lost`): it may run still (fails closed)
        given = entry.get("params")
        goal_id = _goal_id(given.get("goal_id")) if isinstance(given, dict) else None
        message_id = entry.get("message_id")
        self.goals = {m: g for m, g in self.goals.items()
                      if not (g.goal_id is not None and g.goal_id == goal_id)
                      and not (g.goal_id is None and m[1] == message_id)}


def _goals_left(goals: list[LeftGoal]) -> list[LeftGoal]:
    """The goals left (oldest first), at most MAX_LEFT listed: the newest by their own ids,
    and none of the older dropped (they would run on with nobody to cancel them): each server
    of theirs is listed once with no goal id, so that every goal of it is cancelled (as for
    an entry that predates goal ids); servers too many for that, every goal of every one."""
    first, every = 0, dict[Any, LeftGoal]()  # server → the goal naming all of its
    while len(goals) - first + len(every) > MAX_LEFT:
        older = goals[first]
        first += 1
        every[older.server] = msgspec.structs.replace(older, principal=None, goal_id=None)
        if len(every) > MAX_LEFT // 2:  # (servers are the config's: not in a real run)
            anywhere = msgspec.structs.replace(older, principal=None, server=None, goal_id=None)
            return [anywhere, *goals[-(MAX_LEFT - 1):]]
    return [*every.values(), *goals[first:]]


def _boot_stamp(entry: dict[str, Any]) -> tuple[str | None, int | None]:
    """The boot clock an arm's entry was stamped with (`AuditRecord.boot`); (None, None)
    when it has none or none this version reads (then the wall clock dates the arm)."""
    boot = entry.get("boot")
    if not isinstance(boot, dict):
        return None, None
    boot_id, ms = boot.get("boot_id"), boot.get("ms")
    if not isinstance(boot_id, str) or not isinstance(ms, int) or isinstance(ms, bool):
        return None, None
    return boot_id, ms


def _arms_left(arms: list[LeftArm], now_ms: int, boot: BootInstant | None) -> list[LeftArm]:
    """The arm trajectories left (oldest first), at most MAX_LEFT listed, none dropped (it
    would run on with nobody to hold it): past MAX_LEFT, those of one route (topic, action,
    group) are listed as one — every joint any of them moves, until the last of them is due
    — so a hold stops them all. Routes are the configuration's: a handful."""
    if len(arms) <= MAX_LEFT:
        return arms
    by_route: dict[tuple[Any, ...], LeftArm] = {}
    for arm in arms:
        route = (arm.topic, arm.action, arm.params.get("group"))
        kept = by_route.pop(route, None)  # (re-inserted: the routes in order of last use)
        if kept is not None:
            last = max(kept, arm, key=lambda a: a.left_ms(now_ms, boot))
            arm = msgspec.structs.replace(last, message_id=arm.message_id,
                                          joints=list(dict.fromkeys([*kept.joints,
                                                                     *arm.joints])))
        by_route[route] = arm
    return list(by_route.values())[-MAX_LEFT:]


def _taken_up_key(goal: LeftGoal) -> _Key:
    """A goal an entry lists as left running, by its id when it has one: a clean stop names
    its goals by id alone (no principal: `Dispatcher.goals_watched`), and message ids are
    unique per principal only — two such goals of one message id (or of no command known)
    are two goals, not one listed in place of the other (red team 16: the next start left
    the other to run). A COMMAND_FAILED of this run ends no goal of an earlier run's."""
    if goal.goal_id is None:  # every goal of its server: one per server, whatever its command
        return goal.principal, goal.message_id, (goal.action, goal.server)
    return goal.principal, goal.message_id, (goal.action, goal.goal_id)


def _goal_id(given: Any) -> str | None:
    """A goal id an entry gives, as the take-back names it (`str(uuid.UUID(...))`); None
    when it is no goal id: the goal cannot be named, so every goal of its server is
    cancelled (fail closed), as for an entry that predates goal ids. Never raised into the
    start: the take-back turns an id into its 16 bytes (red team 16: a goal id not a UUID
    failed the whole take-back, arms included, with a traceback, at every start)."""
    if not isinstance(given, str):
        return None
    try:
        return str(uuid.UUID(given))
    except ValueError:
        return None


def _merged(older: _Running, newer: _Running) -> _Running:
    """Both, each collection in order: the older first."""
    return _Running({**older.arms, **newer.arms}, {**older.goals, **newer.goals},
                    {**older.streams, **newer.streams}, {**older.replaced, **newer.replaced},
                    {**older.replaced_streams, **newer.replaced_streams})


def _replaced_id(applied: Any) -> str | None:
    """The message id of the stream a move's `applied` says it replaced (`Replaces.entry`)."""
    replaces = applied.get("replaces") if isinstance(applied, dict) else None
    given = replaces.get("message_id") if isinstance(replaces, dict) else None
    return given if isinstance(given, str) else None


def _keep_newest(given_back: dict[_Key, Any]) -> None:
    """What a command's COMMAND_FAILED may give back, for the newest MAX_LEFT commands: it
    follows its command closely (a run's log may hold any number)."""
    while len(given_back) > MAX_LEFT:
        del given_back[next(iter(given_back))]


def _apply(state: Resumed, entry: dict[str, Any]) -> None:
    event, action = entry.get("event"), entry.get("action_type")
    given = entry.get("params")
    params: dict[str, Any] = given if isinstance(given, dict) else {}
    if event in _BOUNDARIES:
        latched = params.get("estop_latched")
        if isinstance(latched, bool):
            state.latched = latched
            state.latched_by = "a latched start" if latched else None
        locks = params.get("locks")
        state.locks = dict(locks) if isinstance(locks, dict) else {}
    elif event in _ENGAGED:
        state.latched, state.latched_by = True, entry.get("principal")
    elif event == "ESTOP_CLEARED":
        state.latched, state.latched_by = False, None
    elif event == "COMMAND_FAILED" and action == with_effect(Effect.CLEAR_ESTOP).name:
        # The clear was audited but not persisted (the governor stayed latched).
        state.latched, state.latched_by = True, "a clear that failed"
    elif entry.get("outcome") == "executed":
        _lock_entry(state, entry, action)


def _lock_entry(state: Resumed, entry: dict[str, Any], action: Any) -> None:
    applied = entry.get("applied")
    name = applied.get("name") if isinstance(applied, dict) else None
    if not isinstance(name, str):
        return
    if action == with_effect(Effect.LOCK).name:
        state.locks[name] = str(entry.get("principal"))
    elif action == with_effect(Effect.UNLOCK).name:
        state.locks.pop(name, None)


def _boundary_at(fd: int, size: int, torn_at: int | None, *, floor: int) -> int | None:
    """The offset of the last BRIDGE_STARTED or BRIDGE_STOPPED line at or after `floor` (a
    line's start), read back from the end in chunks; None if there is none (with `floor` 0:
    0, the log's start). Only a line naming one is parsed here."""
    for offset, line in lines_backwards(fd, size, floor):
        if b"BRIDGE_ST" not in line:  # the event's name, in whatever field: checked below
            continue
        entry = _parsed(line, last=offset + len(line) == torn_at)
        if entry is not None and entry.get("event") in _BOUNDARIES:
            return offset
    return 0 if floor == 0 else None


def _forwards(fd: int, offset: int, size: int, torn_at: int | None
              ) -> Iterator[dict[str, Any]]:
    """Parsed entries from `offset` to the end, a chunk at a time."""
    rest = b""
    while offset < size:
        read = os.pread(fd, min(_CHUNK, size - offset), offset)
        if not read:  # the file is shorter than it was: never loop on it
            raise ValueError(f"the audit log ends at {offset}, before {size}")
        block = rest + read
        offset += len(block) - len(rest)
        lines = block.split(b"\n")
        rest = lines.pop() if offset < size else b""
        for n, line in enumerate(lines):
            if line.strip():
                entry = _parsed(line, last=torn_at is not None and offset >= size
                                and n == len(lines) - 1)
                if entry is not None:
                    yield entry


def _ends_line(fd: int, size: int) -> bool:
    return size == 0 or os.pread(fd, 1, size - 1) == b"\n"


def _parsed(line: bytes, *, last: bool) -> dict[str, Any] | None:
    """One entry; None for a torn last line (unterminated: its append never finished, and
    the log cuts it when it opens), which is no entry. Anything else unreadable raises."""
    try:
        entry = json.loads(line)
    except (ValueError, RecursionError) as exc:  # (json recurses: a line thousands deep)
        if last:
            return None
        what = "nested too deeply" if isinstance(exc, RecursionError) else f"not JSON ({exc})"
        raise ValueError(f"an audit line {what}: {line[:40]!r}") from exc
    if not isinstance(entry, dict):
        raise ValueError(f"an audit line that is no entry: {line[:40]!r}")
    return entry


# -- start points ---------------------------------------------------------------------------

class _MotionState(msgspec.Struct, kw_only=True):
    """`_Motion`'s dictionaries as (key, value) pairs, in their order."""

    arms: list[tuple[tuple[Any, str, Any], LeftArm]]
    goals: list[tuple[tuple[Any, str, Any], LeftGoal]]
    streams: list[tuple[tuple[Any, str, Any], LeftStream]]
    replaced: list[tuple[tuple[Any, str, Any], list[LeftArm]]]
    halted: list[tuple[tuple[Any, str, Any], _MotionState]] = msgspec.field(
        default_factory=list)
    # (a point written before replaced streams were set aside has none)
    replaced_streams: list[tuple[tuple[Any, str, Any], list[LeftStream]]] = msgspec.field(
        default_factory=list)

    @classmethod
    def of(cls, running: _Running, halted: dict[_Key, _Running] | None = None,
           ) -> _MotionState:
        return cls(arms=list(running.arms.items()), goals=list(running.goals.items()),
                   streams=list(running.streams.items()),
                   replaced=list(running.replaced.items()),
                   replaced_streams=list(running.replaced_streams.items()),
                   halted=[(k, cls.of(h)) for k, h in (halted or {}).items()])

    def running(self) -> _Running:
        return _Running(_by_key(self.arms), _by_key(self.goals), _by_key(self.streams),
                        _by_key(self.replaced), _by_key(self.replaced_streams))


class StartPoint(msgspec.Struct, kw_only=True):
    """The replay's state after the entry `seq` (its audit_id and the byte span of its line):
    where a start may replay from instead of the boundary."""

    seq: int
    audit_id: str
    start: int
    end: int
    last_event: str | None
    latched: bool | None
    latched_by: str | None
    locks: dict[str, Any]
    motion: _MotionState


class _PointFile(msgspec.Struct):
    body: msgspec.Raw  # a StartPoint, as signed
    sig: str  # base64 Ed25519 over RESUME_POINT_TAG + body


def point_path(log_path: Path) -> Path:
    return log_path.with_name(log_path.name + ".resume")


def write_point(log_path: Path, cp: Checkpoint, pubkey: Ed25519PublicKey,
                sign: Callable[[bytes], bytes]) -> None:
    """The start point after checkpoint `cp`'s entry, replayed from the previous point (or the
    boundary): run on the audit log's checkpoint-hook thread (`AuditLog.on_checkpoint`)."""
    _at_its_place(log_path, cp)
    replay = _Replay()
    replay.run(log_path, pubkey, until=cp.end)
    body = msgspec.json.encode(replay.point(cp))
    sig = base64.b64encode(sign(body)).decode()
    atomic_write(point_path(log_path), msgspec.json.encode(_PointFile(msgspec.Raw(body), sig)))


def _at_its_place(log_path: Path, cp: Checkpoint) -> None:
    """Raises ValueError unless the checkpoint's entry is where the log's writer put it: a
    line written into the file by anyone else shifts every later entry (a cut removes it),
    and a point naming the writer's offsets would be refused at the next start anyway."""
    fd = os.open(log_path, os.O_RDONLY)
    try:
        _names_its_line(fd, cp, os.fstat(fd).st_size)
    except ValueError as exc:
        raise ValueError(f"checkpoint {cp.seq} is not where the log's writer put it ({exc}): "
                         f"the file was changed by another") from exc
    finally:
        os.close(fd)


def _usable_point(fd: int, log_path: Path, size: int,
                  pubkey: Ed25519PublicKey | None) -> StartPoint | None:
    """The start point, if `pubkey` signed it and it names a line of this log before `size`
    as it stands; else None (logged: the replay goes back to the boundary)."""
    if pubkey is None:
        return None
    path = point_path(log_path)
    try:
        point = _signed_point(read_small(path, MAX_POINT_BYTES), pubkey)
        _names_its_line(fd, point, size)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("audit start point %s not used (%s): replaying from the last start", path,
                    exc)
        return None
    return point


def _signed_point(data: bytes, pubkey: Ed25519PublicKey) -> StartPoint:
    """Raises ValueError unless `data` is a point file signed by `pubkey`."""
    try:
        file = decode_as(data, _PointFile)
        body = bytes(file.body)
        pubkey.verify(base64.b64decode(file.sig, validate=True), RESUME_POINT_TAG + body)
        return decode_as(body, StartPoint)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise ValueError(f"malformed: {exc}") from exc
    except (ValueError, InvalidSignature) as exc:  # (a bad base64 is a ValueError)
        raise ValueError("not signed by the audit log's key") from exc


def _names_its_line(fd: int, point: StartPoint | Checkpoint, size: int) -> None:
    """Raises ValueError unless the line at the point's span is its entry, whole."""
    if not 0 <= point.start < point.end <= size:
        raise ValueError(f"its entry's span {point.start}..{point.end} is not in the log")
    line = os.pread(fd, point.end - point.start, point.start)
    if not line.endswith(b"\n") or (point.start > 0 and os.pread(fd, 1, point.start - 1)
                                     != b"\n"):
        raise ValueError("its span is not a line of the log")
    try:
        entry = decode(line[:-1])
    except msgspec.DecodeError as exc:
        raise ValueError("its span is not an entry") from exc
    its_entry = (isinstance(entry, dict) and entry.get("seq") == point.seq
                 and entry.get("audit_id") == point.audit_id
                 and carries_its_id(entry, point.audit_id))
    if not its_entry:
        raise ValueError(f"the log's line there is not its entry (seq {point.seq})")
