"""Where joint_trajectory_controller drives an arm at a given time of a trajectory we sent.

A trajectory with a zero stamp starts when the controller takes it: from the state the arm
was in then to the first point, then point to point. Each segment is interpolated as the
controller's default `spline` does (ros2_controllers jazzy, `Trajectory::sample` and
`interpolate_between_points`): a cubic through both ends' positions and velocities when both
ends give velocities (the start state's: the arm's measured velocities, when its joint_states
give them), a straight line between the positions otherwise; before the start the start
state, after the last point the last point. Accelerations (a quintic) are never sent by
`arm_joint`, so never read here. A continuous joint's wrap-around is not modelled.

Written from that behaviour, not from its code: `tests/bridge/test_arm_holds.py` checks it.
"""

from __future__ import annotations

import bisect
import functools
import itertools
import math
from array import array
from collections.abc import Sequence
from typing import NamedTuple

from ..rcan.actions import PathPoint


class _Knot(NamedTuple):
    time_s: float
    # Packed doubles: a trajectory is kept while it may run (several per arm, up to 1000
    # points of 64 joints each): 8 bytes a value, not a float object's 24 and its pointer.
    positions: array[float]
    velocities: array[float] | None


def _packed(values: Sequence[float] | None) -> array[float] | None:
    return None if values is None else array("d", values)


class DesiredPath:
    """A trajectory as its controller runs it: `start` (and `start_velocities`, if known) at
    time 0, then its `points`."""

    def __init__(self, start: Sequence[float], start_velocities: Sequence[float] | None,
                 points: Sequence[PathPoint]) -> None:
        if not points:
            raise ValueError("a trajectory has at least one point")
        self._knots = [_Knot(0.0, array("d", start), _packed(start_velocities)),
                       *(_Knot(p.time_s, array("d", p.positions), _packed(p.velocities))
                         for p in points)]
        self._times = [k.time_s for k in self._knots]

    @property
    def end_s(self) -> float:
        """When its last point is due."""
        return self._times[-1]

    def at(self, time_s: float) -> list[float]:
        """Where the controller drives each joint `time_s` after the start (clamped to the
        trajectory's span: the start state before it, the last point after it)."""
        if not time_s > 0.0:  # NaN too: the start, not a guess
            return list(self._knots[0].positions)
        if time_s >= self.end_s:
            return list(self._knots[-1].positions)
        i = bisect.bisect_right(self._times, time_s) - 1
        a, b = self._knots[i], self._knots[i + 1]
        return _between(a, b, time_s - a.time_s)

    @functools.cached_property
    def peak_speeds(self) -> list[float]:
        """Each joint's highest speed along the whole trajectory (rad/s or m/s); worked out
        when first asked (a stop with late measurements), not as the trajectory goes out."""
        peaks = [0.0] * len(self._knots[0].positions)
        for a, b in itertools.pairwise(self._knots):
            for j, speed in enumerate(_segment_peaks(a, b)):
                peaks[j] = max(peaks[j], speed)
        return peaks


def _between(a: _Knot, b: _Knot, elapsed: float) -> list[float]:
    span = b.time_s - a.time_s
    s = elapsed / span
    if a.velocities is None or b.velocities is None:  # no velocities at both ends: a line
        return [pa + (pb - pa) * s for pa, pb in zip(a.positions, b.positions, strict=True)]
    # The cubic Hermite basis: the unique cubic with both ends' positions and velocities.
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    return [h00 * pa + h10 * span * va + h01 * pb + h11 * span * vb
            for pa, va, pb, vb in zip(a.positions, a.velocities, b.positions, b.velocities,
                                      strict=True)]


def _segment_peaks(a: _Knot, b: _Knot) -> list[float]:
    span = b.time_s - a.time_s
    if a.velocities is None or b.velocities is None:
        return [abs(pb - pa) / span for pa, pb in zip(a.positions, b.positions, strict=True)]
    return [_cubic_peak(pa, va, pb, vb, span)
            for pa, va, pb, vb in zip(a.positions, a.velocities, b.positions, b.velocities,
                                      strict=True)]


def _cubic_peak(pa: float, va: float, pb: float, vb: float, span: float) -> float:
    """The highest |velocity| of the Hermite cubic on [0, span]: its velocity is a parabola,
    highest at an end or at its vertex."""
    square = span * span
    if square == 0.0:  # a segment so short (5e-324 s in) its square is 0.0: no bound
        return math.inf
    slope = (pb - pa) / span
    # velocity(τ) = va + c2·τ + c3·τ² (the cubic's derivative)
    c2 = (6 * slope - 4 * va - 2 * vb) / span
    c3 = (3 * va + 3 * vb - 6 * slope) / square
    if not (math.isfinite(c2) and math.isfinite(c3)):  # overflowed: no bound either
        return math.inf
    candidates = [abs(va), abs(vb)]
    if c3 != 0.0:
        vertex = -c2 / (2 * c3)
        if 0.0 < vertex < span:
            candidates.append(abs(va + c2 * vertex + c3 * vertex**2))
    return max(candidates)
