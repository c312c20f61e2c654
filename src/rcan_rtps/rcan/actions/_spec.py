"""What an action declares: parameters, governance defaults, invariants, ROS translation."""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, NamedTuple, Protocol, TypeVar

from .._enums import Role
from .._types import ActionParams
from ._invariants import Invariant as Invariant  # action modules import it from here
from ._invariants import unreadable

P = TypeVar("P", bound=ActionParams)


class Effect(enum.Enum):
    """What an action does to the robot; the governor's rules key on this, never on names."""

    MOTION = "motion"  # moves the robot: refused while the e-stop is latched
    HALT = "halt"  # zero velocity, cancel goals: the e-stop lane, never rate-limited or gated
    ESTOP = "estop"  # latch, tell the robot, halt: any authenticated principal
    CLEAR_ESTOP = "clear_estop"  # unlatch, once its audit entry is durable
    LOCK = "lock"  # block lower-priority velocity streams (twist_mux-like); no robot I/O
    UNLOCK = "unlock"  # release such a lock


class MessageKit(Protocol):
    """What a ROS translation may use; the bridge provides it (no DDS in action modules)."""

    @property
    def message_type(self) -> str:
        """The ROS type the route's topic is configured with (e.g. Twist or TwistStamped)."""
        ...

    def struct(self, type_name: str) -> Any:
        """The message class of a ROS type: for hot paths that build messages directly."""
        ...

    def now(self) -> dict[str, int]:
        """`builtin_interfaces/Time` of the wall clock now."""
        ...

    def setting(self, key: str) -> Any:
        """A `bridge.ros2` setting (e.g. `nav_frame_id`)."""
        ...


Builder = Callable[[P, MessageKit], Any]  # a message object, or its plain data (a mapping)


class PathPoint(NamedTuple):
    """One point of a joint trajectory, as its controller reads it: where each joint is due
    (`positions`, the route's joints' order), how fast (`velocities`: None if not given), and
    when (`time_s` after the trajectory starts)."""

    positions: tuple[float, ...]
    velocities: tuple[float, ...] | None
    time_s: float


@dataclass(frozen=True)
class Hold(Generic[P]):
    """How a stop takes back what a route's message started and what runs on after it was
    sent (an arm's trajectory): which joints it moves (`joints`), for how long at most
    (`runs_for_s`), and the message that holds those joints where they were measured
    (`build`: the joints and their positions, in that order). `path`: the points the message
    sends them through, if the bridge may work out where the controller drives them at a
    given time (a stop while their measurements are late holds them there); None: it may
    not, and such a stop fails."""

    joints: Callable[[P], Sequence[str]]
    runs_for_s: Callable[[P], float]
    build: Callable[[Sequence[str], Sequence[float], MessageKit], Any]
    path: Callable[[P], Sequence[PathPoint]] | None = None


@dataclass(frozen=True)
class Publish(Generic[P]):
    """Publish one message on a topic named by a `bridge.ros2` config key."""

    topic_key: str
    build: Builder[P]
    type_name: str | None = None  # None: the type named by `type_key`
    type_key: str | None = None
    latched: bool = False  # transient-local: late joiners still get the last value
    # Named groups (a `bridge.ros2` mapping name → {topic}): the params' `group` picks the
    # topic; with no group configured, `topic_key`'s.
    group_key: str | None = None
    # What runs on after the message was sent, and how a stop holds it (None: nothing runs on).
    hold: Hold[P] | None = None

    def publishes(self) -> tuple[Publish[Any], ...]:
        """What this route publishes, its own message first."""
        return (self,)


@dataclass(frozen=True)
class SendGoal(Generic[P]):
    """Send an action goal to the server named by a `bridge.ros2` config key.

    Every (config key, action type) the registry declares is a goal route of its own: the
    bridge follows each with its own action client (bridge.goals), and a config naming one
    server for two types is refused when loaded."""

    action_key: str
    type_name: str
    build: Builder[P]

    def publishes(self) -> tuple[Publish[Any], ...]:
        return ()


@dataclass(frozen=True)
class Halt:
    """Publish zero velocity (`velocity`), and cancel every goal."""

    velocity: Publish[Any]

    def publishes(self) -> tuple[Publish[Any], ...]:
        return (self.velocity,)


@dataclass(frozen=True)
class EstopSignal:
    """Publish the e-stop state (`signal`, latched); engaging it also halts (`halt`)."""

    engaged: bool
    signal: Publish[Any]
    halt: Halt | None = None

    def publishes(self) -> tuple[Publish[Any], ...]:
        return (self.signal, *(self.halt.publishes() if self.halt else ()))


@dataclass(frozen=True)
class NoRoute:
    """Governance only (locks): nothing is sent to the robot."""

    def publishes(self) -> tuple[Publish[Any], ...]:
        return ()


RosRoute = Publish[Any] | SendGoal[Any] | Halt | EstopSignal | NoRoute


@dataclass(frozen=True)
class HitlDefault:
    """Whether a human may be asked (`gateable`) and must be, unless configured otherwise."""

    gateable: bool = True
    required: bool = False


@dataclass(frozen=True)
class ActionSpec(Generic[P]):
    """One action, everything about it in one place; surfaces are derived from these."""

    name: str
    summary: str
    params: type[P]
    effect: Effect
    default_role: Role
    ros: RosRoute
    invariants: tuple[Invariant, ...]
    scope: str = "control"
    hitl: HitlDefault = field(default_factory=HitlDefault)
    starts_goal: bool = False  # its work outlives the command (a SendGoal: nav, docking)
    # Held on the wire: republished at `cmd_rate_hz` until its duration ends or it is replaced,
    # stopped, e-stopped, its session or the robot is lost (see governance.streams).
    streamed: bool = False
    order: int = 100  # where it is listed (docs, OpenAPI, mDNS caps); ties go by name
    example: Mapping[str, Any] | None = None  # valid params, where the required ones are not

    def __post_init__(self) -> None:
        if not self.invariants:
            raise ValueError(f"action {self.name!r} declares no invariants: fail closed")
        if self.effect in (Effect.HALT, Effect.ESTOP) and self.hitl.gateable:
            raise ValueError(f"action {self.name!r} stops the robot: it can never be gated")
        if self.effect is Effect.MOTION and Invariant.ESTOP_GUARD not in self.invariants:
            raise ValueError(f"motion action {self.name!r} must be guarded by the e-stop")
        if self.streamed and not (self.motion and isinstance(self.ros, Publish)):
            raise ValueError(f"streamed action {self.name!r} must be motion that publishes")
        for invariant in self.invariants:  # a check must never meet what it cannot read
            problem = unreadable(self.params, invariant)
            if problem:
                raise ValueError(f"action {self.name!r} declares the {invariant.value} check, "
                                 f"but {problem}")
        if self.starts_goal != isinstance(self.ros, SendGoal):
            # The governor arbitrates goals by `starts_goal`; the bridge tracks them by route.
            raise ValueError(f"action {self.name!r}: a goal is started exactly by a SendGoal "
                             "route")

    @property
    def stopping(self) -> bool:
        """Stops the robot: decided at once on every transport, never queued or limited."""
        return self.effect in (Effect.HALT, Effect.ESTOP)

    @property
    def motion(self) -> bool:
        return self.effect is Effect.MOTION

    def describe(self) -> Mapping[str, Any]:
        """Plain facts for docs and discovery."""
        return {"action": self.name, "summary": self.summary, "effect": self.effect.value,
                "default_role": self.default_role.name, "scope": self.scope,
                "hitl": "never" if not self.hitl.gateable else (
                    "required" if self.hitl.required else "optional"),
                "invariants": [i.value for i in self.invariants]}
