"""§8 safety invariants as composable checks; every check fails closed.

A check takes the command and the parameters as they stand so far, and returns the parameters
to apply (possibly clamped) or raises `Violation`. `AllOf` runs checks in order; any other
exception inside a check becomes a denial (SAFETY_CHECK_ERROR), never a pass. A combinator
with nothing in it (`AllOf()`, `PerAction({})`) is refused when built (`EmptyPolicyError`).
`safety_policy` gives every registry action its declared checks (each declares one or more),
and the config cannot leave the velocity limits out (`SafetyConfig` has no defaults for them).

Each check is one `Invariant` and reads what that invariant declares (`rcan.actions.READS`):
the registry refuses an action whose parameters lack it, and a check handed parameters it
cannot read (of another type, a missing field, a value of the wrong kind) refuses them
(PARAMS_NOT_UNDERSTOOD) — it never passes them as "not mine".
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Protocol, cast

import msgspec

from rcan_rtps.config import ArmConfig, SafetyConfig, polygon_edges, polygon_problem
from rcan_rtps.rcan import ActionParams, Invariant, NormalizedCommand
from rcan_rtps.rcan.actions import RampedMove, not_understood, numbers, specs

from . import outcomes
from .errors import EmptyPolicyError, GovernanceError
from .outcomes import Rejection
from .streams import AccelLimits, Velocity

log = logging.getLogger(__name__)
EXCEED_DENY_FACTOR = 1.10  # the bridge spec: more than 10 % over the limit is denied, not clamped


class Violation(GovernanceError):
    def __init__(self, rejection: Rejection, detail: str = "") -> None:
        super().__init__(detail or rejection.deny_reason)
        self.rejection = rejection


class Check(Protocol):
    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams: ...


class AllOf:
    """Every check must pass; parameters flow from one to the next."""

    def __init__(self, *checks: Check) -> None:
        if not checks:  # fail closed: a policy of nothing would pass a 1e6 m/s move
            raise EmptyPolicyError("AllOf needs at least one check")
        self.checks = checks

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        for check in self.checks:
            try:
                params = check(command, params)
            except Violation:
                raise
            except Exception as exc:  # a broken check must never let a command through
                log.exception("safety check %r failed", check)
                raise Violation(outcomes.SAFETY_CHECK_ERROR, f"{check!r}: {exc}") from exc
        return params


class Declared(Protocol):
    """A check that is one invariant, and reads what that invariant declares."""

    @property
    def invariant(self) -> Invariant: ...

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams: ...


def _refuse_unreadable(checker: str, problem: str) -> Violation:
    # The registry vets every action's parameters, so this is a wiring fault: fail closed, loudly.
    log.error("the %s refused parameters it cannot read: %s", checker, problem)
    return Violation(outcomes.PARAMS_NOT_UNDERSTOOD, f"{checker}: {problem}")


def understood(params: ActionParams, invariant: Invariant) -> None:
    """Raises `Violation` (PARAMS_NOT_UNDERSTOOD) unless `params` hold what `invariant` reads."""
    problem = not_understood(params, invariant)
    if problem is not None:
        raise _refuse_unreadable(f"{invariant.value} check", problem)


class FiniteNumbers:
    """Defence in depth behind the schema: every number finite, no bools posing as numbers."""

    invariant = Invariant.FINITE

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        if not isinstance(params, msgspec.Struct):
            raise _refuse_unreadable("finite check", f"{type(params).__name__} is no struct")
        try:
            for n in numbers(params):  # one walk; TypeError at anything it cannot walk
                if isinstance(n, bool) or not math.isfinite(n):
                    raise Violation(outcomes.INVALID_VALUE,
                                    f"non-finite or non-numeric value {n!r}")
        except TypeError as exc:
            raise _refuse_unreadable("finite check", str(exc)) from exc
        return params


finite_numbers = FiniteNumbers()


class _Planar(Protocol):
    """What the velocity checks read (`READS`), once `understood` has checked it."""

    @property
    def linear_x(self) -> float: ...
    @property
    def linear_y(self) -> float: ...
    @property
    def angular_z(self) -> float: ...
    @property
    def duration_s(self) -> float | None: ...


class _Goal(Protocol):
    @property
    def x(self) -> float: ...
    @property
    def y(self) -> float: ...
    @property
    def frame_id(self) -> str | None: ...


class _Joints(Protocol):
    @property
    def joints(self) -> Sequence[str]: ...
    @property
    def group(self) -> str | None: ...


class VelocityLimit:
    """Clamp `move` to the limits; deny when a request exceeds a limit by more than 10 %."""

    invariant = Invariant.VELOCITY

    def __init__(self, max_linear: float, max_angular: float, deny_on_exceed: bool) -> None:
        self.max_linear = max_linear
        self.max_angular = max_angular
        self.deny_on_exceed = deny_on_exceed

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        understood(params, self.invariant)
        velocity = cast(_Planar, params)
        return msgspec.structs.replace(
            params,
            linear_x=self._limit(velocity.linear_x, self.max_linear, "linear_x"),
            linear_y=self._limit(velocity.linear_y, self.max_linear, "linear_y"),
            angular_z=self._limit(velocity.angular_z, self.max_angular, "angular_z"),
        )

    def _limit(self, value: float, limit: float, name: str) -> float:
        if not math.isfinite(value):
            raise Violation(outcomes.INVALID_VALUE, f"{name} is not finite")
        if self.deny_on_exceed and abs(value) > limit * EXCEED_DENY_FACTOR:
            raise Violation(outcomes.VELOCITY_LIMIT, f"{name}={value} exceeds {limit} by >10%")
        return max(-limit, min(limit, value))


class DurationLimit:
    """A timed move lasts at most `max_s`; a longer one is denied, not shortened."""

    invariant = Invariant.DURATION

    def __init__(self, max_s: float) -> None:
        self.max_s = max_s

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        understood(params, self.invariant)
        duration = cast(_Planar, params).duration_s
        if duration is not None and not duration <= self.max_s:  # NaN is not within either
            raise Violation(outcomes.DURATION_LIMIT, f"duration_s={duration} exceeds {self.max_s}")
        return params


class Commanded(Protocol):
    @property
    def commanded(self) -> Velocity: ...


class AccelerationLimit:
    """A move ramps from the velocity commanded now; the ramp is part of what is applied
    (and audited). The stream enforces it sample by sample (governance.streams).

    The ramped move is made of what the check reads: a stream sends nothing else."""

    invariant = Invariant.ACCELERATION

    def __init__(self, limits: AccelLimits, motion: Commanded) -> None:
        self.limits = limits
        self.motion = motion

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        understood(params, self.invariant)
        move = cast(_Planar, params)
        now = self.motion.commanded
        target = Velocity(move.linear_x, move.linear_y, move.angular_z)
        return RampedMove(linear_x=move.linear_x, linear_y=move.linear_y,
                          angular_z=move.angular_z, duration_s=move.duration_s,
                          ramp_from=[now.linear_x, now.linear_y, now.angular_z],
                          ramp_s=round(self.limits.ramp_s(now, target), 6))


class Workspace:
    """Navigation goals must lie strictly inside the polygon (in the navigation frame)."""

    invariant = Invariant.WORKSPACE

    def __init__(self, polygon: Sequence[tuple[float, float]] | None, frame_id: str) -> None:
        self.polygon = list(polygon) if polygon is not None else None
        self.frame_id = frame_id

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        understood(params, self.invariant)  # even with no fence: a goal it cannot read is none
        if self.polygon is None:
            return params
        goal = cast(_Goal, params)
        problem = polygon_problem(self.polygon)
        if problem:  # a polygon that bounds nothing must not allow everything
            raise Violation(outcomes.WORKSPACE_VIOLATION, f"workspace {problem}")
        if (goal.frame_id or self.frame_id) != self.frame_id:
            # The workspace is defined in one frame; a goal in another cannot be checked.
            raise Violation(outcomes.WORKSPACE_VIOLATION, f"goal not in frame {self.frame_id}")
        if not strictly_inside((goal.x, goal.y), self.polygon):
            raise Violation(outcomes.WORKSPACE_VIOLATION, "goal outside the workspace")
        return params


def strictly_inside(point: tuple[float, float], polygon: list[tuple[float, float]]) -> bool:
    """Ray casting; a point on an edge counts as outside (the boundary is the limit)."""
    x, y = point
    inside = False
    for (x1, y1), (x2, y2) in polygon_edges(polygon):
        if _on_segment(point, (x1, y1), (x2, y2)):
            return False
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def _on_segment(p: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> bool:
    cross = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
    if abs(cross) > 1e-12 * max(1.0, abs(b[0] - a[0]) + abs(b[1] - a[1])):
        return False
    return min(a[0], b[0]) <= p[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= p[1] <= max(a[1], b[1])


class JointGroups:
    """`arm_joint` names an arm that exists, and only joints it owns (`bridge.ros2.arms`).

    The arm is resolved here (the only one, when `group` is left out), so `applied` and the
    audit entry say which arm moved."""

    invariant = Invariant.JOINT_GROUP

    def __init__(self, arms: Mapping[str, ArmConfig]) -> None:
        self.arms = {name: frozenset(arm.joints) for name, arm in arms.items()}

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        understood(params, self.invariant)
        arm = cast(_Joints, params)
        if not self.arms:
            if arm.group is not None:
                raise Violation(outcomes.JOINT_GROUP_VIOLATION,
                                "this robot has no arm groups: leave out `group`")
            return params
        group = arm.group or self._only_arm()
        owned = self.arms.get(group)
        if owned is None:
            raise Violation(outcomes.JOINT_GROUP_VIOLATION,
                            f"no arm {group!r} (arms: {', '.join(sorted(self.arms))})")
        foreign = [j for j in arm.joints if owned and j not in owned]
        if foreign:
            raise Violation(outcomes.JOINT_GROUP_VIOLATION,
                            f"arm {group!r} has no joint {', '.join(foreign)}")
        return msgspec.structs.replace(params, group=group)

    def _only_arm(self) -> str:
        if len(self.arms) > 1:
            raise Violation(outcomes.JOINT_GROUP_VIOLATION,
                            f"name the arm in `group`: one of {', '.join(sorted(self.arms))}")
        return next(iter(self.arms))


class Latch(Protocol):
    @property
    def latched(self) -> bool: ...


class EstopGuard:
    """While the e-stop is latched, no motion command passes."""

    invariant = Invariant.ESTOP_GUARD

    def __init__(self, latch: Latch) -> None:
        self.latch = latch

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        if self.latch.latched and command.spec.motion:
            raise Violation(outcomes.ESTOP_ACTIVE)
        return params


class PerAction:
    """Each action through the invariants its registry entry declares; an action without an
    entry is refused (fail closed), and so are parameters not of the action's own type (the
    type the registry checked against what its invariants read)."""

    def __init__(self, policies: Mapping[str, Check]) -> None:
        if not policies:  # would refuse everything: a wiring mistake, reported where it is made
            raise EmptyPolicyError("PerAction needs at least one action")
        self.policies = dict(policies)

    def __call__(self, command: NormalizedCommand, params: ActionParams) -> ActionParams:
        policy = self.policies.get(command.action)
        if policy is None:
            raise Violation(outcomes.SAFETY_CHECK_ERROR, f"no invariants for {command.action!r}")
        if not isinstance(params, command.spec.params):
            raise _refuse_unreadable("safety policy", f"{command.action} takes "
                                     f"{command.spec.params.__name__}, not {type(params).__name__}")
        return policy(command, params)


class _Standstill:
    commanded = Velocity()


def safety_policy(safety: SafetyConfig, latch: Latch, nav_frame_id: str,
                  motion: Commanded | None = None, *,
                  arms: Mapping[str, ArmConfig] | None = None) -> PerAction:
    """`motion`: what the robot is being told now (the velocity streams); `arms`: the joint
    groups of `bridge.ros2.arms`."""
    accel = AccelLimits(safety.max_linear_accel, safety.max_angular_accel)
    checks: dict[Invariant, Declared] = {
        Invariant.ESTOP_GUARD: EstopGuard(latch),
        Invariant.FINITE: finite_numbers,
        Invariant.VELOCITY: VelocityLimit(safety.max_linear_vel, safety.max_angular_vel,
                                          safety.velocity_exceed_deny),
        Invariant.WORKSPACE: Workspace(safety.workspace, nav_frame_id),
        Invariant.JOINT_GROUP: JointGroups(arms or {}),
        Invariant.DURATION: DurationLimit(safety.max_move_duration_s),
        Invariant.ACCELERATION: AccelerationLimit(accel, motion or _Standstill()),
    }
    for invariant, check in checks.items():  # each check is the invariant it stands for
        if check.invariant is not invariant:
            raise ValueError(f"{check!r} is the {check.invariant.value} check, "
                             f"not {invariant.value}")
    return PerAction({spec.name: AllOf(*(checks[i] for i in spec.invariants))
                      for spec in specs()})
