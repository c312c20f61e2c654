"""A stop takes back the arms' trajectories: what runs on after it was sent.

Zero velocity and goal cancels do not reach an arm: a JointTrajectory runs on in its
controller up to its last point's time (`arm_joint` allows an hour), and
joint_trajectory_controller's topic has no cancel (an empty trajectory is refused). So the
dispatcher remembers, per trajectory topic, the trajectories it sent there and until when they
may run (the controller may have refused the last, `ArmHolds`); a stop sends each arm still
due the message its route declares to hold it (`Publish.hold`): one point at the joints'
measured positions, at rest, due at once — what the controller does itself when its action
goal is cancelled.

Where the joints are comes from `joint_states` (`JointPositions`, fed by the telemetry reader).
A position heard `age` seconds ago is carried forward by the velocity heard with it (a hold at
where the arm was, not where it is, drives it back), by at most `MAX_LEAD` (rad or m): the
velocity is the robot's word, and a wrong one must not turn a hold into a long move. Never
heard, not finite, or two senders of joint_states disagreeing on it within MAX_AGE_S (of now,
or of its last sample), the arm is not held: a hold at a guess could move it anywhere.

Older than `MAX_AGE_S` (a joint heard at rest that nothing of ours moves: until the robot's
telemetry counts as silent) and that its only fault, the measurement is late — on a busy
robot computer exactly when a moving arm must stop (0.76 s and 1.7 s measured under CPU
load). Then the better estimate is the controller's own: the trajectory we sent, evaluated
now from where the joints were measured as it went out (`DesiredPath`: straight lines, or
cubics where velocities are given, as joint_trajectory_controller interpolates; clamped to
its span, so on the approved path by construction). It is used only if the trajectory is
known to be what drives the arm: the last positions heard, late as they are, were where it
had them when they were heard (within MAX_LEAD plus its speed × TRACKING_SLACK_S), and an
arm left standing where it was would not have been (the trajectory had moved a joint farther
than that and MAX_LEAD by then; else the hold is no farther than MAX_LEAD from them), they
are no older than the robot's telemetry may be (`telemetry_stale_s`), no other trajectory of ours
still due names those joints or went to that topic (the controller may run either), and none
it replaced for the same joints, still due, is followed by those samples as well while it has
them elsewhere now (the controller refused this one, and runs that one on).
Otherwise the controller refused or aborted it, or something else drives the arm, and a hold
there could be a step across its reach. A hold made so is reported (`ArmsHeld.at_desired`, logged).

An arm not held is reported (the stop fails, saying which and why), and the next stop tries
again; and no trajectory is sent for joints a hold could not be made for where measured
(`RosDispatcher.ready`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection, Sequence
from typing import Any, NamedTuple, Protocol

from ..governance import ArmsHeld
from ..rcan.actions import PathPoint
from .desired_path import DesiredPath
from .joint_positions import MAX_AGE_S, MAX_LEAD, JointPositions, Missing, Unknown, _finite

log = logging.getLogger(__name__)

# A controller may still be settling onto the last point just after its time.
SETTLING_S = 1.0
# How far behind (s) a late joint_states sample may describe the arm when it is checked against
# our trajectory at the time it was heard: MAX_AGE_S, the age a measured hold accepts. A
# sample is heard after it was taken (delivery; under load the backlog that made it late),
# and the controller starts a trajectory a cycle or a delivery after we sent it: a tracking
# arm is then up to its speed × that behind the trajectory. Farther off than a measurement
# the bridge would hold at (plus MAX_LEAD, the controller's following error) is not tracking.
TRACKING_SLACK_S = MAX_AGE_S
MAX_SETS = 8  # distinct joint sets remembered per trajectory topic


class HoldPublisher(Protocol):
    @property
    def topic(self) -> str: ...

    def publish(self, message: Any) -> None: ...


class _Running(NamedTuple):
    message_id: str
    joints: tuple[str, ...]
    due: float  # monotonic: after this, it has ended (settled included)
    publisher: HoldPublisher
    hold: Callable[[Sequence[str], Sequence[float]], Any]  # joints, positions → message
    sent_at: float = 0.0  # monotonic: when it went out (its controller starts it then)
    path: DesiredPath | None = None  # where its controller drives the joints, from sent_at
    # Ours on its topic, of the same joints, still due when it went out (newest last, at
    # most MAX_SETS + 1 kept): forgotten for it, but the controller runs one on if it
    # refused this one.
    replaced: tuple[_Running, ...] = ()


class _Where(NamedTuple):
    """Where a hold puts a trajectory's joints: measured, or (`desired`) where the
    controller drives them now, their measurements late."""

    positions: list[float]
    desired: bool = False
    late: str = ""  # why not where measured (desired)


class ArmHolds:
    """The trajectories that may still be running, per topic, and holding them.

    A new trajectory on a topic does not make the bridge forget the ones before it: it
    replaces them in the controller only if the controller takes it, and the topic answers
    nothing. joint_trajectory_controller refuses one naming only some of its joints (unless
    `allow_partial_joints_goal`) or a joint it lacks, and the one before runs on. So a stop
    holds each joint set still due on the topic, oldest first: a hold of a set the
    controller refuses is refused too, and the hold of the set it ran is taken. One entry per
    distinct joint set (the later replaces the earlier), at most MAX_SETS per topic."""

    def __init__(self, positions: JointPositions, max_age_s: float,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self.positions = positions
        self._max_age_s = max_age_s  # the robot's telemetry counts as silent after this
        self._monotonic = monotonic
        self._running: dict[str, list[_Running]] = {}  # topic → oldest first

    def sent(self, publisher: HoldPublisher, message_id: str, joints: Sequence[str],
             runs_for_s: float, hold: Callable[[Sequence[str], Sequence[float]], Any],
             *, path: Sequence[PathPoint] = ()) -> None:
        """A trajectory went out on `publisher`, running `runs_for_s` from now through
        `path`'s points (none given: a stop holds it only where it is measured). Where the
        joints were measured as it went out is its start (a hold had to be possible then)."""
        now = self._monotonic()
        topic = publisher.topic
        before = [r for r in self._running.get(topic, ()) if now <= r.due]
        replaced = [old for r in before if set(r.joints) == set(joints)
                    for old in (*r.replaced, r._replace(replaced=())) if now <= old.due]
        new = _Running(message_id, tuple(joints), now + runs_for_s + SETTLING_S, publisher,
                       hold, now, self._desired_path(joints, path),
                       tuple(replaced[-(MAX_SETS + 1):]))
        runs = [r for r in before if set(r.joints) != set(new.joints)]
        self._running[topic] = [*runs, new][-MAX_SETS:]
        self._watch(topic)

    def _desired_path(self, joints: Sequence[str], path: Sequence[PathPoint]
                      ) -> DesiredPath | None:
        start = self._measured(joints)
        if not path or isinstance(start, Unknown):  # no start known: never estimated
            return None
        return DesiredPath(start, self.positions.velocities(joints), path)

    def cannot_hold(self, joints: Sequence[str]) -> str | None:
        """Why a hold of `joints` could not be made now (None: it could); while none of our
        trajectories moves them, a joint heard at rest holds where it was heard."""
        where = self._measured(joints)
        return where if isinstance(where, Unknown) else None

    def _measured(self, joints: Sequence[str]) -> list[float] | Unknown:
        now, moving = self._monotonic(), set(joints)
        still = not any(moving.intersection(r.joints) for runs in self._running.values()
                        for r in runs if now <= r.due)
        return self.positions.now(joints, self._max_age_s, resting_holds=still)

    def hold_all(self) -> ArmsHeld:
        """Every arm whose trajectory may still be running is held (a stop of the robot)."""
        return self._hold(lambda run: True)

    def hold(self, message_ids: Collection[str]) -> ArmsHeld:
        """The arms still running one of `message_ids`' trajectories are held (a stop of one
        principal's motion alone); others' trajectories run on."""
        return self._hold(lambda run: run.message_id in message_ids)

    def _hold(self, chosen: Callable[[_Running], bool]) -> ArmsHeld:
        now = self._monotonic()
        due = [r for runs in self._running.values() for r in runs if now <= r.due]
        held, at_desired, not_held = [], [], []
        for topic in list(self._running):
            # ended: holding it now would only fight whoever moves it next
            runs = [r for r in self._running[topic] if now <= r.due]
            kept = [r for r in runs if not chosen(r)]
            reached = desired = False
            for run in (r for r in runs if chosen(r)):  # oldest first
                where = self._where_or_why(run, due, now)
                why = where if isinstance(where, str) else self._publish(run, where.positions)
                if why is None and isinstance(where, _Where) and where.desired:
                    log.warning("holding the arm on %s where its trajectory has it now, not "
                                "where it was measured: %s", topic, where.late)
                    desired = True
                if why is None:
                    reached = True
                else:
                    kept.append(run)  # the next stop tries again
                    not_held.append(f"the arm on {topic} was not held: {why}")
            if reached:
                held.append(topic)
            if desired:
                at_desired.append(topic)
            self._running[topic] = [r for r in runs if r in kept]
            self._watch(topic)
        return ArmsHeld(tuple(held), tuple(not_held), tuple(at_desired))

    def _where_or_why(self, run: _Running, due: Sequence[_Running], now: float
                      ) -> _Where | str:
        try:
            return self._where(run, due, now)
        except Exception as exc:  # one arm's fault must not keep the others moving
            log.exception("working out where to hold the arm on %s failed", run.publisher.topic)
            return f"where to hold it could not be worked out: {exc!r}"

    def _where(self, run: _Running, due: Sequence[_Running], now: float) -> _Where | str:
        """Where a hold puts `run`'s joints, or why it cannot be made: measured; with only
        late measurements, where its controller drives them now if they were following it."""
        measured = self.positions.now(run.joints, self._max_age_s)
        if not isinstance(measured, Unknown):
            return _Where(measured)
        if measured.missing is not Missing.STALE:
            return str(measured)
        desired = self._desired(run, due, now)
        if isinstance(desired, str):
            return f"{measured}, and {desired}"
        return _Where(desired, desired=True, late=str(measured))

    def _desired(self, run: _Running, due: Sequence[_Running], now: float) -> list[float] | str:
        """Where `run`'s controller drives its joints now (its trajectory at now), or why
        that is not trusted: no trajectory kept, another of ours that the controller may run
        instead (`_rival`), a measurement older than the robot's
        telemetry may be, or the last measurements off the trajectory where it had them then
        (the controller refused or aborted it, or something else drives the arm)."""
        if run.path is None:
            return "no trajectory is known to tell where its controller drives it"
        rival = self._rival(run, due)
        if rival is not None:
            return f"{rival}: which one its controller runs is not known"
        last = self.positions.last(run.joints)
        if last is None:
            return "a joint was never heard"
        speeds, start = run.path.peak_speeds, run.path.at(0.0)
        if not all(map(_finite, speeds)):  # (a segment too short for its cubic to bound)
            return ("its trajectory's peak speed is not finite: where it has the arm cannot be "
                    "checked")
        shown = False  # a sample an arm left standing where it was would not match
        for i, (name, (position, at)) in enumerate(zip(run.joints, last, strict=True)):
            if now - at > self._max_age_s:
                return (f"{name!r} unheard for longer than the robot's telemetry may be "
                        f"({self._max_age_s:g} s)")
            then = run.path.at(at - run.sent_at)[i]
            off = abs(position - then)
            tolerance = MAX_LEAD + speeds[i] * TRACKING_SLACK_S
            if not off <= tolerance:
                return (f"{name!r} was last heard {off:.3f} from where its trajectory had it "
                        f"then (more than {tolerance:.3f}): the arm was not following it")
            # The start was carried forward by up to MAX_LEAD: an arm left standing may be
            # that far short of it.
            shown = shown or abs(start[i] - then) > tolerance + MAX_LEAD
        desired = run.path.at(now - run.sent_at)
        if not all(map(_finite, desired)):  # a cubic overflowing (a velocity heard absurd)
            return f"its trajectory has the arm at {desired} now: not finite"
        # Samples heard before the trajectory had moved the arm farther than the tolerance
        # match an arm that never moved (the controller refused it: jazzy's refuses a last
        # point still moving) as well: then a hold there may move no farther than MAX_LEAD.
        if not shown and any(abs(d - p) > MAX_LEAD
                             for d, (p, _) in zip(desired, last, strict=True)):
            return ("its last samples cannot tell it following its trajectory from standing "
                    "where it was when the trajectory went out")
        return self._replaced_may_drive(run, last, desired, now) or desired

    @staticmethod
    def _replaced_may_drive(run: _Running, last: Sequence[tuple[float, float]],
                            desired: Sequence[float], now: float) -> str | None:
        """Why a trajectory of ours that `run` replaced may be what drives its joints (the
        controller refused `run`, and runs that one on): the last samples follow it too, and
        it has them elsewhere now; None if none may."""
        if len(run.replaced) > MAX_SETS:
            return "more trajectories of ours it replaced are still due than are kept"
        for before in (r for r in run.replaced if now <= r.due):
            if before.path is None:
                return "it replaced a trajectory of ours not known to be elsewhere"
            order = [before.joints.index(name) for name in run.joints]
            speeds = before.path.peak_speeds
            there = before.path.at(now - before.sent_at)
            follows = all(
                abs(position - before.path.at(at - before.sent_at)[j])
                <= MAX_LEAD + speeds[j] * TRACKING_SLACK_S
                for (position, at), j in zip(last, order, strict=True))
            elsewhere = any(abs(d - there[j]) > MAX_LEAD
                            for d, j in zip(desired, order, strict=True))
            if follows and elsewhere:
                return ("its last samples cannot tell it from a trajectory of ours it replaced, "
                        "which its controller runs on if it refused this one")
        return None

    @staticmethod
    def _rival(run: _Running, due: Sequence[_Running]) -> str | None:
        """Another trajectory of ours still due that the controller may run instead of `run`
        on its joints: one naming some of them, or any other on its topic (a controller
        that takes partial goals holds the joints one leaves out, and stops `run` there)."""
        others = [r for r in due if r is not run]
        shared = sorted({j for r in others for j in set(r.joints) & set(run.joints)})
        if shared:
            return f"another trajectory of ours names {', '.join(map(repr, shared))}"
        topic = run.publisher.topic
        if any(r.publisher.topic == topic for r in others):
            return f"another trajectory of ours went to {topic}"
        return None

    @staticmethod
    def _publish(run: _Running, positions: Sequence[float]) -> str | None:
        """Publishes the hold of one trajectory's joints; why not, if it could not."""
        try:
            run.publisher.publish(run.hold(run.joints, positions))
        except Exception as exc:  # one arm's fault must not keep the others moving
            return repr(exc)
        return None

    def _watch(self, topic: str) -> None:
        runs = self._running.get(topic, [])
        if not runs:
            self._running.pop(topic, None)
        self.positions.watch(topic, {j for r in runs for j in r.joints})

    def running(self) -> list[str]:
        """The message ids of the trajectories that may still be running."""
        now = self._monotonic()
        return [r.message_id for runs in self._running.values() for r in runs if now <= r.due]
