"""Where the joints an arm hold needs are: the last position (and velocity) of each joint,
fed by every JointState the telemetry reader hears (`JointPositions`).

Apart from the holds themselves (`arm_holds`, which documents how a position heard is used):
joint_states is followed from the start, whether or not an arm is commanded, and a stop
right after a first trajectory must find where its joints are; the holds' code is loaded
only once an arm can move (configured arms, or the first arm command: idle memory, issue 27).
"""

from __future__ import annotations

import enum
import math
import threading
import time
from collections.abc import Callable, Collection, Sequence
from typing import NamedTuple

# joint_states comes at 10-1000 Hz: older than this, an arm moving at 1 rad/s has moved a
# visible way since, and holding it there would drive it back as far.
MAX_AGE_S = 0.5
MAX_LEAD = 0.1  # how far a hold may carry a joint past where it was heard
REST_SPEED = 0.01  # rad/s or m/s: a joint heard this slow (its velocity given) was at rest
MAX_KEPT = 256  # joints kept that no trajectory moves (yet)
MAX_JOINT_NAME = 128  # a longer name no command can give (rcan JointName)


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
                               _finite(given) and abs(given) <= REST_SPEED, _finite(given))
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
            resting_holds: bool = False) -> list[float] | Unknown:
        """Where `joints` are now (their last positions carried forward by their velocities),
        or why that is not known: heard more than MAX_AGE_S ago, a joint may have moved a
        visible way since — unless `resting_holds` (nothing of ours moves it) and it was
        heard at rest, its velocity given: then up to `max_age_s` (the robot's telemetry
        counting as silent). A busy computer delays joint_states that long (1.7 s measured
        under CPU load); an arm at rest is where it was. A reason other than age comes
        first: only a joint whose sole fault is its age is `Missing.STALE`."""
        now = self._monotonic()
        found: list[float] = []
        stale: Unknown | None = None
        with self._lock:
            for name in joints:
                heard = self._heard.get(name)
                why = self._unknown(name, heard, now, max_age_s, resting_holds)
                if why is not None and why.missing is not Missing.STALE:
                    return why
                stale = stale or why
                if heard is not None:
                    lead = max(-MAX_LEAD, min(MAX_LEAD, heard.velocity * (now - heard.at)))
                    found.append(heard.position + lead)
        return stale or found

    def _unknown(self, name: str, heard: _Heard | None, now: float, max_age_s: float,
                 resting_holds: bool) -> Unknown | None:
        """Why where `name` is now is not known from `heard` (its last sample), if it is
        not."""
        if heard is None:
            return Unknown(Missing.UNHEARD, f"no joint_states heard for {name!r}")
        if not _finite(heard.position):
            return Unknown(Missing.NOT_FINITE,
                           f"joint_states gave {name!r} the position {heard.position}")
        jumped = self._jumped.get(name)
        # Senders that disagreed within MAX_AGE_S before its last sample (so lately, if that
        # is recent): which is right is not known, then or since.
        if jumped is not None and heard.at - jumped[0] <= MAX_AGE_S:
            return Unknown(Missing.DISAGREE,
                           f"joint_states senders disagree on {name!r}: {jumped[1]:.3f} and "
                           f"{jumped[2]:.3f}, {now - jumped[0]:.2f} s ago")
        age = now - heard.at
        if age > max_age_s or (age > MAX_AGE_S and not (resting_holds and heard.resting)):
            return Unknown(Missing.STALE, f"joint_states for {name!r} last heard {age:.2f} s ago")
        return None

    def last(self, joints: Sequence[str]) -> list[tuple[float, float]] | None:
        """Each joint's last position heard and when (monotonic), however old; None if one
        was never heard."""
        with self._lock:
            heard = [self._heard.get(name) for name in joints]
        if any(h is None for h in heard):
            return None
        return [(h.position, h.at) for h in heard if h is not None]

    def velocities(self, joints: Sequence[str]) -> list[float] | None:
        """The velocities last heard with `joints`' positions; None unless each was given."""
        with self._lock:
            heard = [self._heard.get(name) for name in joints]
        if any(h is None or not h.given for h in heard):
            return None
        return [h.velocity for h in heard if h is not None]


class Missing(enum.Enum):
    """Why where a joint is is not known."""

    UNHEARD = "unheard"  # no joint_states ever named it
    STALE = "stale"  # heard, but too long ago (its only fault)
    NOT_FINITE = "not_finite"  # its position was NaN or infinite
    DISAGREE = "disagree"  # two senders of joint_states disagreed on it


class Unknown(str):
    """Why where joints are is not known: the text a stop reports, and what kind of reason
    (`missing`), so that only age can be worked around."""

    missing: Missing

    def __new__(cls, missing: Missing, text: str) -> Unknown:
        made = super().__new__(cls, text)
        made.missing = missing
        return made


def _finite(value: float) -> bool:
    return value - value == 0.0


class _Heard(NamedTuple):
    position: float
    velocity: float  # 0 when not given or not finite
    at: float  # monotonic
    sender: int | None  # the writer's handle, if known
    resting: bool = False  # its velocity was given, and at most REST_SPEED
    given: bool = False  # its velocity was given (and finite)


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
