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
velocity is the robot's word, and a wrong one must not turn a hold into a long move. Older than
`MAX_AGE_S` (a joint heard at rest that nothing of ours moves: until the robot's telemetry
counts as silent), never heard, or two senders of joint_states disagreeing on it within
MAX_AGE_S, the arm is not held: a hold at a guess could move it anywhere. That arm is
reported (the stop fails, saying which and why), and the next stop tries again; and no
trajectory is sent for joints a hold could not be made for (`RosDispatcher.ready`).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Collection, Sequence
from typing import Any, NamedTuple, Protocol

from ..governance import ArmsHeld

# A controller may still be settling onto the last point just after its time.
SETTLING_S = 1.0
# joint_states comes at 10-1000 Hz: older than this, an arm moving at 1 rad/s has moved a
# visible way since, and holding it there would drive it back as far.
MAX_AGE_S = 0.5
MAX_LEAD = 0.1  # how far a hold may carry a joint past where it was heard
REST_SPEED = 0.01  # rad/s or m/s: a joint heard this slow (its velocity given) was at rest
MAX_KEPT = 256  # joints kept that no trajectory moves (yet)
MAX_JOINT_NAME = 128  # a longer name no command can give (rcan JointName)
MAX_SETS = 8  # distinct joint sets remembered per trajectory topic


class JointPositions:
    """The last measured position (and velocity) of each joint the bridge may have to hold,
    whichever JointState carried it: written on the telemetry reader's thread, read on the
    loop. Every joint is kept from when it is heard, not from its first trajectory on: a
    stop right after that trajectory (before the next JointState) must find where it is.
    A JointState's size is its sender's choice: at most MAX_KEPT joints are kept besides the
    watched ones (those of the trajectories that may be running), and no name longer than
    a command may give."""

    def __init__(self, monotonic: Callable[[], float] = time.monotonic) -> None:
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self._watching: dict[str, frozenset[str]] = {}  # who watches → its joints
        self._watched: frozenset[str] = frozenset()
        self._heard: dict[str, _Heard] = {}
        # → (at, from, to): the last time two senders disagreed on where a joint is
        self._jumped: dict[str, tuple[float, float, float]] = {}

    def watch(self, who: str, joints: Collection[str]) -> None:
        """`who` (a trajectory topic) needs `joints` now, instead of what it needed before:
        they are kept whatever else was heard."""
        with self._lock:
            self._watching[who] = frozenset(joints)
            self._watched = frozenset().union(*self._watching.values())

    def heard(self, names: Sequence[str], positions: Sequence[float],
              velocities: Sequence[float], sender: int | None = None) -> None:
        """One JointState (its parallel lists; `velocities` may be empty) from `sender` (its
        writer, if known)."""
        at = self._monotonic()
        with self._lock:
            for i, name in enumerate(names[:len(positions)]):
                if name not in self._heard and not self._keeps(name):
                    continue
                given = float(velocities[i]) if i < len(velocities) else math.nan
                velocity = given if _finite(given) else 0.0
                heard = _Heard(float(positions[i]), velocity, at, sender,
                               _finite(given) and abs(given) <= REST_SPEED)
                before = self._heard.get(name)
                if before is not None and _disagree(before, heard):
                    self._jumped[name] = (at, before.position, heard.position)
                self._heard[name] = heard

    def _keeps(self, name: str) -> bool:
        """Whether a joint not kept yet is kept from now on."""
        return name in self._watched or (len(self._heard) < MAX_KEPT
                                         and len(name) <= MAX_JOINT_NAME)

    def known(self, joints: Sequence[str]) -> bool:
        """Whether each of `joints` was ever heard (lately or not)."""
        with self._lock:
            return all(name in self._heard for name in joints)

    def now(self, joints: Sequence[str], max_age_s: float, *,
            resting_holds: bool = False) -> list[float] | str:
        """Where `joints` are now (their last positions carried forward by their velocities),
        or why that is not known: heard more than MAX_AGE_S ago, a joint may have moved a
        visible way since — unless `resting_holds` (nothing of ours moves it) and it was
        heard at rest, its velocity given: then up to `max_age_s` (the robot's telemetry
        counting as silent). A busy computer delays joint_states that long (1.7 s measured
        under CPU load); an arm at rest is where it was."""
        now = self._monotonic()
        found = []
        with self._lock:
            for name in joints:
                heard = self._heard.get(name)
                if heard is None:
                    return f"no joint_states heard for {name!r}"
                position, velocity, at, _, resting = heard
                age = now - at
                if age > max_age_s or (age > MAX_AGE_S and not (resting_holds and resting)):
                    return f"joint_states for {name!r} last heard {age:.2f} s ago"
                if not _finite(position):
                    return f"joint_states gave {name!r} the position {position}"
                jumped = self._jumped.get(name)
                if jumped is not None and now - jumped[0] <= MAX_AGE_S:
                    return (f"joint_states senders disagree on {name!r}: {jumped[1]:.3f} "
                            f"and {jumped[2]:.3f}, {now - jumped[0]:.2f} s ago")
                lead = max(-MAX_LEAD, min(MAX_LEAD, velocity * (now - at)))
                found.append(position + lead)
        return found


def _finite(value: float) -> bool:
    return value - value == 0.0


class _Heard(NamedTuple):
    position: float
    velocity: float  # 0 when not given or not finite
    at: float  # monotonic
    sender: int | None  # the writer's handle, if known
    resting: bool = False  # its velocity was given, and at most REST_SPEED


def _disagree(before: _Heard, after: _Heard) -> bool:
    """Two senders of one joint's position (a joint_state_publisher left running beside the
    robot's broadcaster) disagree on where it is: `after`, from another sender than
    `before` (at most MAX_AGE_S earlier), is farther from it than either's speed carries
    the joint in between, plus MAX_LEAD. A hold at whichever came last may be a step across
    the arm's reach. One sender's own samples never disagree, however fast the joint moves
    (a sender may give no velocities); a wrap of a continuous joint by whole turns is no
    disagreement."""
    if before.sender == after.sender or after.at - before.at > MAX_AGE_S:
        return False
    moved = after.position - before.position
    moved -= 2 * math.pi * round(moved / (2 * math.pi)) if _finite(moved) else 0.0
    speed = max(abs(before.velocity), abs(after.velocity))
    return abs(moved) > MAX_LEAD + speed * (after.at - before.at)


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
             runs_for_s: float, hold: Callable[[Sequence[str], Sequence[float]], Any]) -> None:
        """A trajectory went out on `publisher`, running `runs_for_s` from now."""
        now = self._monotonic()
        topic = publisher.topic
        new = _Running(message_id, tuple(joints), now + runs_for_s + SETTLING_S, publisher,
                       hold)
        runs = [r for r in self._running.get(topic, ())
                if now <= r.due and set(r.joints) != set(new.joints)]
        self._running[topic] = [*runs, new][-MAX_SETS:]
        self._watch(topic)

    def cannot_hold(self, joints: Sequence[str]) -> str | None:
        """Why a hold of `joints` could not be made now (None: it could); while none of our
        trajectories moves them, a joint heard at rest holds where it was heard."""
        now, moving = self._monotonic(), set(joints)
        still = not any(moving.intersection(r.joints) for runs in self._running.values()
                        for r in runs if now <= r.due)
        where = self.positions.now(joints, self._max_age_s, resting_holds=still)
        return where if isinstance(where, str) else None

    def hold_all(self) -> ArmsHeld:
        """Every arm whose trajectory may still be running is held (a stop of the robot)."""
        return self._hold(lambda run: True)

    def hold(self, message_ids: Collection[str]) -> ArmsHeld:
        """The arms still running one of `message_ids`' trajectories are held (a stop of one
        principal's motion alone); others' trajectories run on."""
        return self._hold(lambda run: run.message_id in message_ids)

    def _hold(self, chosen: Callable[[_Running], bool]) -> ArmsHeld:
        now = self._monotonic()
        held, not_held = [], []
        for topic in list(self._running):
            # ended: holding it now would only fight whoever moves it next
            runs = [r for r in self._running[topic] if now <= r.due]
            kept = [r for r in runs if not chosen(r)]
            reached = False
            for run in (r for r in runs if chosen(r)):  # oldest first
                why = self._hold_one(run)
                if why is None:
                    reached = True
                else:
                    kept.append(run)  # the next stop tries again
                    not_held.append(f"the arm on {topic} was not held: {why}")
            if reached:
                held.append(topic)
            self._running[topic] = [r for r in runs if r in kept]
            self._watch(topic)
        return ArmsHeld(tuple(held), tuple(not_held))

    def _hold_one(self, run: _Running) -> str | None:
        """Publishes the hold of one trajectory's joints; why not, if it could not."""
        where = self.positions.now(run.joints, self._max_age_s)
        if isinstance(where, str):
            return where
        try:
            run.publisher.publish(run.hold(run.joints, where))
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
