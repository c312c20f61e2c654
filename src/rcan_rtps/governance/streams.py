"""Velocity streams (§8, issue 11): a governed `move` held on the wire until it ends.

A robot's velocity controller stops when no command arrives for a while (ros2_control's diff
drive: 0.5 s), so one Twist per `move` drives a fraction of a metre. `VelocityStreams` is the
one owner of what the robot is being told to do: the active stream, the velocity last sent,
the engaged motion locks. Everything about it runs on the event loop, without awaits:

- `start` (after the move's write-ahead entry, see Governor) replaces the active stream
  atomically; the first sample was sent by the dispatcher just before, with no await between.
- a loop timer sends the next sample every 1/`rate_hz` s, each a step of the ramp from the
  velocity last sent toward the target (acceleration limits), until the duration is over;
- `end` (stop, e-stop, session loss, robot loss, completion) sends zero at once: a stop is
  never ramped or delayed. The e-stop ends the stream from the latch's listener, synchronously
  when the latch flips, before the e-stop's first await; and every sample checks the latch
  right before it is written: no non-zero sample follows a latched e-stop.

Every end is reported (`on_end`) so the governor audits it (STREAM_ENDED) and tells whoever
waits for it (an INVOKE of a `move` skill is answered then). Priorities and
locks work like twist_mux's: a higher priority preempts, a lower one is refused while a higher
stream runs or a higher lock is engaged.

Goals drive the base too (a Nav2 goal, a docking): the goals the bridge sent are held here
beside the stream, with their owner's priority, so one arbiter decides for both. A move or a
goal is refused while a higher stream, goal or lock holds the base; once it starts, the lower
and equal goals it replaces are returned to the governor to cancel (`goal_started`,
`goals_at_or_below`), and a lock returns the goals below it (`lock`).
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import math
from collections.abc import Callable, Iterator
from typing import NamedTuple, Protocol

import msgspec

from rcan_rtps.rcan.actions import MoveParams

from . import outcomes
from .outcomes import Rejection

log = logging.getLogger(__name__)


class Velocity(NamedTuple):
    linear_x: float = 0.0
    linear_y: float = 0.0
    angular_z: float = 0.0

    @classmethod
    def of(cls, params: MoveParams) -> Velocity:
        return cls(params.linear_x, params.linear_y, params.angular_z)

    def params(self) -> MoveParams:
        return MoveParams(linear_x=self.linear_x, linear_y=self.linear_y,
                          angular_z=self.angular_z)


ZERO = Velocity()


class AccelLimits(msgspec.Struct, frozen=True):
    """m/s² and rad/s²; None: unlimited (a step goes straight to the target)."""

    linear: float | None = None
    angular: float | None = None

    def step(self, current: Velocity, target: Velocity, dt: float) -> Velocity:
        """One sample `dt` after `current`, toward `target`, within the limits."""
        lin = math.inf if self.linear is None else self.linear * dt
        ang = math.inf if self.angular is None else self.angular * dt
        return Velocity(_toward(current.linear_x, target.linear_x, lin),
                        _toward(current.linear_y, target.linear_y, lin),
                        _toward(current.angular_z, target.angular_z, ang))

    def ramp_s(self, current: Velocity, target: Velocity) -> float:
        """How long the limits take from `current` to `target`."""
        lin = max(abs(t - c) for c, t in zip(current[:2], target[:2], strict=True))
        ang = abs(target.angular_z - current.angular_z)
        return max(0.0 if self.linear is None else lin / self.linear,
                   0.0 if self.angular is None else ang / self.angular)


def _toward(current: float, target: float, max_step: float) -> float:
    return max(current - max_step, min(current + max_step, target))


class EndReason(str, enum.Enum):
    COMPLETED = "completed"  # its duration is over
    REPLACED = "replaced"  # a newer move of the same or a lower-or-equal priority sender
    PREEMPTED = "preempted"  # a higher-priority move, or a lock above its priority
    STOPPED = "stopped"
    ESTOPPED = "estopped"
    SESSION_LOST = "session_lost"
    CANCELLED = "cancelled"  # its sender's client cancelled a motion command (an own stop)
    ROBOT_LOST = "robot_lost"
    BRIDGE_STOPPED = "bridge_stopped"


class StopMark(NamedTuple):
    """The stops that apply to `owner`'s motion, counted when it was decided (`mark`): a stop
    of everyone's (`halt`, an e-stop) or of `owner`'s alone (`own_stop`) changes it."""

    owner: str
    stops: int


class Stream(msgspec.Struct):
    action: str
    owner: str  # the principal whose command it is
    priority: int
    target: Velocity
    message_id: str
    duration_s: float | None  # None: held until something ends it
    started_at: float = 0.0  # loop time
    ends_at: float | None = None
    samples: int = 0
    stops: StopMark | None = None  # `VelocityStreams.mark` when the move was decided


class StreamEnded(msgspec.Struct, frozen=True):
    stream: Stream
    reason: EndReason
    by: str | None  # who ended it, when someone did
    last: Velocity  # the last sample it sent
    at: float
    zeroed: bool  # zero was sent (False: the next stream took over the wire)
    recorded: bool = False  # the replacing move's own entry records it (`applied.replaces`)
    why: str | None = None  # what made `by` end it, when more than `reason` says (`end_command`)


class Replaces(NamedTuple):
    """The stream a move's audit entry says it ends (`applied.replaces`)."""

    owner: str
    message_id: str
    reason: EndReason

    def entry(self) -> dict[str, str]:
        return {"message_id": self.message_id, "reason": self.reason.value}


class HeldGoal(msgspec.Struct, frozen=True):
    """A goal the bridge sent, holding the base until it ends."""

    goal_id: str
    owner: str
    priority: int
    message_id: str


class _Claim(NamedTuple):
    """A move whose entry is being written; it starts its stream once that is durable."""

    owner: str
    message_id: str
    priority: int


class VelocitySink(Protocol):
    def send_velocity(self, velocity: MoveParams) -> str | None:
        """Publish one velocity sample now; None if sent, else why not (robot lost)."""
        ...


class Latch(Protocol):
    @property
    def latched(self) -> bool: ...


class Cancellable(Protocol):
    def cancel(self) -> None: ...


class Timer(Protocol):
    """What the streams need of the event loop (tests drive a manual one)."""

    def time(self) -> float: ...

    def call_at(self, when: float, callback: Callable[[], object]) -> Cancellable: ...


class VelocityStreams:
    """The one owner of the active velocity stream; see the module docs."""

    def __init__(self, sink: VelocitySink, latch: Latch, *, rate_hz: float = 20.0,
                 accel: AccelLimits | None = None, timer: Timer | None = None) -> None:
        self._sink = sink
        self._latch = latch
        self.period = 1.0 / rate_hz
        self.accel = accel or AccelLimits()
        self._timer = timer
        self.active: Stream | None = None
        self.commanded = ZERO  # the velocity last sent
        self.locks: dict[str, int] = {}  # engaged lock → its priority
        self.goals: dict[str, HeldGoal] = {}  # goals in progress, by id
        # Stops so far (`halt`, an e-stop latching): motion decided before one must not
        # start after it.
        self.stops = 0
        # The bridge is stopping (`close`): no motion starts from then on, whenever decided
        # (a robot halted last must stay so: nothing of ours may follow its halt).
        self.closed = False
        # Motion decided and not yet started or refused, per owner (`deciding`): it drives
        # the base as much as a running stream does, for a session loss of someone else.
        self._deciding: dict[str, int] = {}
        # Stops of one owner's motion alone (`own_stop`), kept while it has motion being
        # decided (no mark of its is in use otherwise): bounded by `_deciding`.
        self._own_stops: dict[str, int] = {}
        self.on_end: Callable[[StreamEnded], None] = lambda ended: None
        self._handle: Cancellable | None = None
        self._last = ZERO
        self._claim: _Claim | None = None  # the move that starts next, once audited

    # -- admission -----------------------------------------------------------------------
    def admits(self, priority: int, *, since: StopMark | None = None) -> Rejection | None:
        """None if a move or goal of `priority` may start now (no higher stream, goal or
        lock; with `since`, its `mark` taken when it was decided: no stop of it since)."""
        if self._latch.latched:  # first: an e-stop counts as a stop too, and says more
            return outcomes.ESTOP_ACTIVE
        if since is not None and self.stopped_since(since):
            return outcomes.STOPPED
        if any(p > priority for p in self.locks.values()):
            return outcomes.MOTION_LOCKED
        if self.active is not None and self.active.priority > priority:
            return outcomes.LOWER_PRIORITY
        if any(g.priority > priority for g in self.goals.values()):
            return outcomes.LOWER_PRIORITY
        return None

    # -- goals -----------------------------------------------------------------------------
    def goal_started(self, goal: HeldGoal) -> list[HeldGoal]:
        """`goal` holds the base now: the other goals it replaces (forgotten; to cancel)."""
        replaced = self.take_goals(below=goal.priority + 1)
        self.goals[goal.goal_id] = goal
        return replaced

    def goal_ended(self, goal_id: str) -> None:
        self.goals.pop(goal_id, None)

    def take_goals(self, *, owner: str | None = None,
                   below: float = math.inf) -> list[HeldGoal]:
        """Forget (and return) the goals of `owner` (or anyone's) of a priority below
        `below`: they are being cancelled."""
        taken = [g for g in self.goals.values()
                 if (owner is None or g.owner == owner) and g.priority < below]
        for goal in taken:
            del self.goals[goal.goal_id]
        return taken

    def driven_by_other_than(self, owner: str) -> bool:
        """Someone else's stream or goal holds the base, or motion of theirs decided before
        now is still on its way (a goal being sent): a halt of the whole robot now would
        stop it for `owner`'s sake."""
        if self.active is not None and self.active.owner != owner:
            return True
        if any(name != owner for name in self._deciding):
            return True
        return any(g.owner != owner for g in self.goals.values())

    @contextlib.contextmanager
    def deciding(self, owner: str) -> Iterator[StopMark]:
        """Motion of `owner`'s, from its decision until it started or was refused; yields its
        mark, for `stopped_since`, to be used only inside this block."""
        mark = self.arrived(owner)
        try:
            yield mark
        finally:
            self.decided(owner)

    def arrived(self, owner: str) -> StopMark:
        """`deciding`'s start, for motion whose decision is handed on (to a task of its own):
        its mark, in use until the matching `decided`, which must follow, whatever happens."""
        self._deciding[owner] = self._deciding.get(owner, 0) + 1
        return self.mark(owner)

    def decided(self, owner: str) -> None:
        """`deciding`'s end: motion of `owner`'s started or was refused."""
        left = self._deciding.pop(owner) - 1
        if left:
            self._deciding[owner] = left
        else:  # none of its marks is in use any more
            self._own_stops.pop(owner, None)

    def first_sample(self, target: Velocity) -> Velocity:
        return self.accel.step(self.commanded, target, self.period)

    # -- the stream ------------------------------------------------------------------------
    def claim(self, owner: str, message_id: str, priority: int) -> Replaces | None:
        """A move of `priority` is about to write its entry: what it will replace, for that
        entry. Entries are written, and their streams started, in claim order, so the stream
        it replaces is the one claimed just before it (still being audited) or, with none
        pending, the active one; under load each end is then recorded by its successor's
        entry instead of an entry of its own. A move that cannot replace that (lower
        priority) claims nothing. `release` undoes a claim whose move does not start."""
        last = self._claim
        if last is None and self.active is not None:
            last = _Claim(self.active.owner, self.active.message_id, self.active.priority)
        if last is not None and last.priority > priority:
            return None
        self._claim = _Claim(owner, message_id, priority)
        if last is None:
            return None
        reason = EndReason.PREEMPTED if priority > last.priority else EndReason.REPLACED
        return Replaces(last.owner, last.message_id, reason)

    def release(self, owner: str, message_id: str) -> None:
        if self._claim is not None and self._claim[:2] == (owner, message_id):
            self._claim = None

    def start(self, stream: Stream, first: Velocity, *, by: str,
              recorded: Replaces | None = None) -> Rejection | None:
        """`first` has just been sent; from now on `stream` owns the wire (sync, atomic).

        `recorded`: the stream the new move's audit entry says it replaces; its end needs no
        entry of its own (any other stream it replaces, after a race, gets one)."""
        self.release(stream.owner, stream.message_id)
        refused = self.admits(stream.priority, since=stream.stops)
        if refused is not None:  # changed since the first sample went: undo it at once
            self._send(self._last if self.active is not None else ZERO)
            return refused
        old = self.active
        if old is not None:
            higher = stream.priority > old.priority
            said = recorded is not None and recorded[:2] == (old.owner, old.message_id)
            self._finish(EndReason.PREEMPTED if higher else EndReason.REPLACED, by, zero=False,
                         recorded=said, keep_timer=True)
        timer = self._clock()
        stream.started_at = timer.time()
        if stream.duration_s is not None:
            stream.ends_at = stream.started_at + stream.duration_s
        stream.samples = 1
        self.active, self.commanded, self._last = stream, first, first
        if first == ZERO and stream.target == ZERO:
            self._finish(EndReason.COMPLETED, None, zero=False)  # nothing to hold
            return None
        # A replaced stream's timer is due within a period: kept, not re-armed per move (its
        # tick waits for this stream's first period when it comes early).
        if self._handle is None:
            self._schedule(timer, stream.started_at + self.period)
        return None

    def halt(self, by: str | None, reason: EndReason = EndReason.STOPPED) -> bool:
        """A stop (a `stop`, a session-loss halt of the whole robot, the bridge stopping):
        the active stream ends (as `end`), and motion decided before this and not yet started
        never starts (`stopped_since`)."""
        self.stops += 1
        return self.end(reason, by)

    def own_stop(self, owner: str) -> bool:
        """A stop of `owner`'s motion alone (its control session lost while another principal
        drives, its connection closed): what of its motion was decided before this and has
        not started (a goal being sent, a move waiting for the robot or its entry) never
        starts, or is cancelled once its server accepted it. Nobody else's motion is touched.
        Whether any such motion was on its way."""
        if owner not in self._deciding:
            return False
        self._own_stops[owner] = self._own_stops.get(owner, 0) + 1
        return True

    def mark(self, owner: str) -> StopMark:
        """The stops of `owner`'s motion so far: every robot-wide stop, and its own. Both
        only grow while a mark is in use (inside `deciding`), so the sum changes with each."""
        return StopMark(owner, self.stops + self._own_stops.get(owner, 0))

    def stopped_since(self, mark: StopMark) -> bool:
        """Whether a stop of `mark.owner`'s motion came after `mark` was taken."""
        return self.mark(mark.owner) != mark

    def halted_since(self, stops: StopMark) -> Rejection | None:
        """After a motion command's write-ahead entry, just before its first publish: why it
        must not reach the robot — the e-stop latched, or a stop came since it was decided
        (`stops`) — or None."""
        if self._latch.latched:
            return outcomes.ESTOP_ACTIVE
        return outcomes.STOPPED if self.closed or self.stopped_since(stops) else None

    def close(self, reason: EndReason) -> None:
        """The bridge is stopping: a halt (`halt`), and no motion starts after it, whenever
        it was decided (an approval or a command in a task of its own, past the API)."""
        self.closed = True
        self.halt(None, reason)

    def end(self, reason: EndReason, by: str | None = None) -> bool:
        """End the active stream, if any, sending zero at once (True). Without one (False),
        nothing is sent here: the caller halts the robot itself."""
        if self.active is None:
            self.commanded = ZERO  # the caller halts; nothing of ours to end
            return False
        self._finish(reason, by, zero=True)
        return True

    def end_command(self, owner: str, message_id: str, reason: EndReason, *,
                    why: str | None = None) -> bool:
        """End the active stream if it is the one `owner`'s command `message_id` started
        (True), sending zero at once; any other stream — a later move of `owner`'s that
        replaced it, someone else's — is left alone."""
        active = self.active
        if active is None or (active.owner, active.message_id) != (owner, message_id):
            return False
        self._finish(reason, owner, zero=True, why=why)
        return True

    def end_of(self, owner: str, reason: EndReason) -> bool:
        """End the active stream if it is `owner`'s (True), sending zero at once."""
        if self.active is None or self.active.owner != owner:
            return False
        self._finish(reason, owner, zero=True)
        return True

    def on_latch(self) -> None:
        """The latch's listener: an e-stop ends the stream before anything else happens, and
        is a stop for motion decided before it (cleared before that motion started, it still
        does not start)."""
        if self._latch.latched:
            self.halt(None, EndReason.ESTOPPED)

    # -- locks -----------------------------------------------------------------------------
    def lock(self, name: str, priority: int, by: str) -> list[HeldGoal]:
        """Engage a lock: a lower stream ends at once; the lower goals are returned (and
        forgotten) for the caller to cancel."""
        self.locks[name] = priority
        if self.active is not None and self.active.priority < priority:
            self._finish(EndReason.PREEMPTED, by, zero=True)
        return self.take_goals(below=priority)

    def unlock(self, name: str) -> bool:
        return self.locks.pop(name, None) is not None

    # -- internals -------------------------------------------------------------------------
    def _clock(self) -> Timer:
        if self._timer is None:
            self._timer = asyncio.get_running_loop()
        return self._timer

    def _schedule(self, timer: Timer, when: float) -> None:
        self._handle = timer.call_at(when, lambda: self._tick(when))

    def _tick(self, due: float) -> None:
        self._handle = None
        stream, timer = self.active, self._clock()
        if stream is None:
            return
        now = timer.time()
        first_due = stream.started_at + self.period
        if now < first_due and stream.samples == 1:  # armed for the stream it replaced
            self._schedule(timer, first_due)
            return
        if stream.ends_at is not None and now >= stream.ends_at - self.period / 2:
            self._finish(EndReason.COMPLETED, None, zero=True)
            return
        if self._latch.latched:  # the listener ended it already; never send on a latch
            self._finish(EndReason.ESTOPPED, None, zero=True)
            return
        if self.commanded == ZERO and stream.target == ZERO:  # ramped down to a standstill
            self._finish(EndReason.COMPLETED, None, zero=False)
            return
        sample = self.accel.step(self.commanded, stream.target, self.period)
        why = self._send(sample)
        if why is not None:
            log.warning("velocity stream of '%s' ended: %s", stream.owner, why)
            self._finish(EndReason.ROBOT_LOST, None, zero=True)
            return
        stream.samples += 1
        self._last = sample
        # A late tick (a busy loop) does not bunch up the next ones behind it.
        self._schedule(timer, max(due + self.period, now + self.period / 2))

    def _send(self, velocity: Velocity) -> str | None:
        try:
            why = self._sink.send_velocity(velocity.params())
        except Exception as exc:  # a bridge fault ends the stream, never the loop
            log.exception("sending a velocity sample failed")
            why = repr(exc)
        self.commanded = velocity if why is None else ZERO
        return why

    def _finish(self, reason: EndReason, by: str | None, *, zero: bool,
                recorded: bool = False, keep_timer: bool = False,
                why: str | None = None) -> None:
        stream, self.active = self.active, None
        if self._handle is not None and not keep_timer:
            self._handle.cancel()
            self._handle = None
        if zero:
            self._send(ZERO)
        if stream is None:
            return
        ended = StreamEnded(stream, reason, by, self._last, self._clock().time(), zero, recorded,
                            why)
        try:
            self.on_end(ended)
        except Exception:  # reporting must never keep a stream alive
            log.exception("reporting the end of a velocity stream failed")
