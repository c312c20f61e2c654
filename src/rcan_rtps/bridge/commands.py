"""Governed commands → ROS 2 (spec §4): the bridge's `Dispatcher`.

Only parameters the governor approved (`applied`: clamped, checked) reach the wire, and only
after their audit entry is durable: `ready` does all the waiting (the governor calls it before
writing the entry), and `dispatch` publishes motion before its first await.

Robot liveness comes from the wire: a command topic whose robot-side reader is gone (it had
matched and no longer does), or a robot whose telemetry stopped for `telemetry_stale_s`, answers
ROBOT_UNAVAILABLE at once. A topic that never matched yet gets `match_timeout_s` to match
(start-up). `stop` is never held back by any of this.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Collection, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import msgspec

from ..config import Ros2Config
from ..events import Events
from ..governance import ArmsHeld, DispatchResult
from ..governance.clock import system_boot
from ..governance.left import SETTLING_S, LeftArm, LeftGoal, LeftRunning
from ..governance.steps import LeftHalted
from ..rcan import ActionParams, ActionSpec, Effect, NormalizedCommand
from ..rcan.actions import (
    EstopSignal,
    Halt,
    MoveParams,
    NoRoute,
    Publish,
    SendGoal,
    action_spec,
    specs,
    with_effect,
)
from ..ros import qos
from ..ros.errors import GraphTimeout, SampleTooLarge, seconds
from ..ros.participant import RosNode
from ..ros.rostime import now_msg
from .goals import CANCELING_NOTHING
from .joint_positions import JointPositions

if TYPE_CHECKING:
    from .arm_holds import ArmHolds

log = logging.getLogger(__name__)
# s the bridge, stopping, waits for the robot to acknowledge its last zero (within the bounded
# graceful stop)
LEAVING_ACK_S = 2.0

ESTOP_QOS = qos.DEFAULT.with_(depth=1, durability=qos.Durability.TRANSIENT_LOCAL)


class GoalServers(Protocol):
    """The goal action servers, one per goal route (`bridge.goals.GoalRoutes`)."""

    def action_name(self, action_key: str) -> str | None:
        """The action server a route's config key names, if the route is known."""
        ...

    async def send(self, action_key: str, goal: dict[str, Any], timeout: float, *,
                   message_id: str | None = None, command: str | None = None,
                   goal_id: str | None = None) -> str:
        """Sends a goal to its route's server (for the command `message_id` of action
        `command`, with the id `goal_id` its entry names, if chosen); returns its id once
        accepted. Raises on rejection/unavailability."""
        ...

    async def cancel_all(self) -> int:
        """Cancels every active goal on every server; returns how many were active."""
        ...

    def may_run(self, goal_id: str) -> bool:
        """Whether a goal whose send failed may run all the same: its send gave up after
        its request went out (its server may accept it late), or it was accepted and is
        being cancelled. Not one its server refused."""
        ...

    def unsettled(self) -> list[tuple[str, str, str | None, str | None]]:
        """(server, goal id, command, action) of each goal whose send gave up that its
        server may still accept or run (watched for, not seen ended or canceling)."""
        ...

    def not_seen_ended(self) -> list[tuple[str, str, str | None, str | None]]:
        """(server, goal id, command, action) of each goal of this run whose end was not
        seen that a stop's cancel may not have reached (its server lost from sight)."""
        ...

    async def settle(self, timeout: float) -> None:
        """Waits up to `timeout` for those goals to settle (the bridge is leaving)."""
        ...

    async def cancel(self, goal_id: str) -> bool:
        """Cancels one goal this bridge sent, on its own server; True if it is canceling."""
        ...

    async def cancel_left(self, server: str | None, goal_id: str | None,
                          timeout: float, *, message_id: str | None = None,
                          command: str | None = None) -> str | None:
        """Cancels a goal a crashed run sent (by id; with none, every goal of `server`);
        None once canceling, else why not (then one with an id is watched for its server
        accepting it late: the command `message_id` of `command` may have given up on it)."""
        ...


class _Kit:
    """The `MessageKit` of one publish route: the action modules build messages with it."""

    def __init__(self, node: RosNode, ros2: Ros2Config, message_type: str) -> None:
        self._node, self._ros2, self._type = node, ros2, message_type

    @property
    def message_type(self) -> str:
        return self._type

    def struct(self, type_name: str) -> Any:
        return self._node.types.struct(type_name)

    def now(self) -> dict[str, int]:
        return now_msg()

    def setting(self, key: str) -> Any:
        return getattr(self._ros2, key)


class Halted(NamedTuple):
    """What a halt reached: the velocity topic's reader, goals cancelled, arms held."""

    reached: bool
    cancelled: int
    arms: ArmsHeld

    def result(self, topic: str, *, told: bool = False) -> DispatchResult:
        """A stop's result on `topic` (`told`: an e-stop's signal reached the robot): failed
        if nothing was reached, or an arm that may be moving could not be held — unless the
        robot was told to e-stop: its own e-stop stops its arm, the hold is the bridge's
        second measure (logged when it could not be made)."""
        if self.arms.not_held and not told:
            return DispatchResult(ok=False, ros2_topic=topic,
                                  detail="; ".join(self.arms.not_held))
        if not (told or self.reached or self.cancelled or self.arms.held):
            return DispatchResult(ok=False, ros2_topic=topic, detail=f"no subscriber on {topic}")
        return DispatchResult(ok=True, ros2_topic=topic)


class CommandPublisher(Protocol):
    """What a route publishes through: a `RosPublisher`, or one made on first use."""

    @property
    def topic(self) -> str: ...

    def publish(self, message: Any) -> None: ...

    def matched_count(self) -> int: ...

    async def wait_for_subscribers(self, count: int = 1, timeout: float = 5.0) -> int: ...

    async def acknowledged(self, timeout: float) -> bool: ...


class _Route:
    """One declared `Publish`, bound to its publisher."""

    def __init__(self, spec: Publish[Any], publisher: CommandPublisher, kit: _Kit) -> None:
        self.spec, self.publisher, self.kit = spec, publisher, kit

    def message(self, params: ActionParams) -> Any:
        return self.spec.build(params, self.kit)


class RosDispatcher:
    """Carries out each action as its registry entry declares (`ActionSpec.ros`)."""

    def __init__(self, node: RosNode, ros2: Ros2Config, goals: GoalServers | None = None,
                 *, telemetry_age: Callable[[], float | None] = lambda: None,
                 events: Events | None = None,
                 joint_positions: JointPositions | None = None) -> None:
        self.node = node
        self.ros2 = ros2
        self.goals = goals  # None: no goal action is available (every goal is refused)
        self.events = events or Events()  # `command_sent`: e.g. leave `safe_stop` state
        self._telemetry_age = telemetry_age  # seconds since the robot last published, if ever
        # Where the joints are, followed from the start: a stop right after a first
        # trajectory must find them.
        self.positions = joint_positions or JointPositions()
        # Heard whatever a JointState's size: a configured arm's joints (`bridge.ros2.arms`).
        self.positions.watch("bridge.ros2.arms",
                             [j for arm in ros2.arms.values() for j in arm.joints])
        # The arms' trajectories that may still be running, for a stop to hold them: made
        # (its module loaded) at start when arms are configured, else by the first arm
        # command (`ready`, before its entry is written) — never by a stop: with none made,
        # no trajectory was sent, and a stop has no arm to hold (idle memory, issue 27).
        self._arms: ArmHolds | None = None
        if ros2.arms:
            self._holds()
        self._ever_matched: set[str] = set()
        # Arm topics a command waits on for joints never heard (`_takes_back`): one at a time.
        self._awaiting_joints: set[str] = set()
        self._publishers: dict[tuple[str, str, bool], CommandPublisher] = {}
        self._routes: dict[int, _Route] = {}
        self._grouped: dict[tuple[int, str], _Route] = {}  # (route, group) → its own topic
        self._goal_kits: dict[str, _Kit] = {}
        self._direct: dict[str, _Route] = {}
        # Every topic the bridge commands is written from the start, arm trajectories too,
        # though only a motion uses them: its writer is what marks the topic as governed
        # (`governed_by` in USER_DATA), and the project's own tools refuse to publish beside
        # it. Made on first use (issue 27's idle memory, ~0.1 MB), an idle bridge's arm topic
        # was unmarked and `topic pub` drove the arm past it (red team 24).
        self.cmd_vel = self._made_now(_halt_route().velocity)  # where halting sends zero
        # Latched (transient-local): a robot node that (re)joins still learns the e-stop state.
        self.estop = self._made_now(_estop_route().signal)
        streamed = [s for s in specs() if s.streamed]
        for spec in streamed:
            self._made_now(spec.ros.publishes()[0])
        for spec in specs():
            for publish in spec.ros.publishes():
                self._bind_all(publish)
        self._halt = self._bind(_halt_route().velocity)
        self._stream = self._route_of(streamed[0]) if streamed else self._halt
        # Each command looks its route up thrice (audit entry, readiness, send): those of
        # ungrouped actions are found once, here.
        self._direct = {spec.name: self._route_of(spec) for spec in specs()
                        if spec.ros.publishes() and not spec.ros.publishes()[0].group_key}
        self._command_topics = self._topics_by_motion()

    @property
    def arms(self) -> ArmHolds:
        """The arms' holds, made by the first use (`_holds`)."""
        return self._holds()

    def _holds(self) -> ArmHolds:
        """The arms' holds, made (loaded) by the first call (see `__init__`): never from a
        stop."""
        if self._arms is None:
            from .arm_holds import ArmHolds

            self._arms = ArmHolds(self.positions, self.ros2.telemetry_stale_s)
        return self._arms

    def _topics_by_motion(self) -> dict[str, bool]:
        topics: dict[str, bool] = {self.cmd_vel.topic: True, self.estop.topic: False}
        for spec in specs():
            for publish in spec.ros.publishes():
                routes = [r for (key, _), r in self._grouped.items() if key == id(publish)]
                if id(publish) in self._routes:
                    routes.append(self._routes[id(publish)])
                for route in routes:
                    topic = route.publisher.topic
                    topics[topic] = topics.get(topic, False) or spec.motion
        return topics

    def command_topics(self) -> dict[str, bool]:
        """Every topic the bridge commands the robot on (fully qualified) → whether what
        goes there moves the robot (velocity, trajectories) rather than signals (e-stop)."""
        return dict(self._command_topics)

    def _groups(self, publish: Publish[Any]) -> dict[str, Any]:
        return dict(getattr(self.ros2, publish.group_key)) if publish.group_key else {}

    def _bind_all(self, publish: Publish[Any]) -> None:
        groups = self._groups(publish)
        if not groups:
            self._bind(publish)
        for name, group in groups.items():
            self._grouped[(id(publish), name)] = self._bind(publish, group.topic)

    def _bind(self, publish: Publish[Any], group_topic: str | None = None) -> _Route:
        """The route of `publish` on its configured topic, or on one group's topic."""
        route = self._routes.get(id(publish)) if group_topic is None else None
        if route is not None:
            return route
        topic, type_name = self._topic_and_type(publish, group_topic)
        key = (topic, type_name, publish.latched)
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._publishers[key] = self.node.create_publisher(
                topic, type_name, ESTOP_QOS if publish.latched else qos.DEFAULT, governed=True)
        route = _Route(publish, publisher, _Kit(self.node, self.ros2, type_name))
        if group_topic is None:
            self._routes[id(publish)] = route
        return route

    def _topic_and_type(self, publish: Publish[Any],
                        group_topic: str | None = None) -> tuple[str, str]:
        topic = group_topic or getattr(self.ros2, publish.topic_key)
        return topic, publish.type_name or getattr(self.ros2, publish.type_key or "")

    def _made_now(self, publish: Publish[Any]) -> CommandPublisher:
        """The publisher of `publish`'s own topic (made by its route)."""
        return self._bind(publish).publisher

    def _route_of(self, spec: ActionSpec[Any], params: ActionParams | None = None) -> _Route:
        """The route of an action's own message; for a grouped one, the params' group's."""
        direct = self._direct.get(spec.name)
        if direct is not None:
            return direct
        publishes = spec.ros.publishes()
        if not publishes:
            raise TypeError(f"{spec.name} does not publish")
        publish = publishes[0]
        groups = self._groups(publish)
        if not groups:
            return self._routes[id(publish)]
        group = getattr(params, "group", None) or (next(iter(groups)) if len(groups) == 1
                                                   else None)
        route = self._grouped.get((id(publish), group or ""))
        if route is None:
            raise LookupError(f"{spec.name}: no {publish.group_key} group {group!r}")
        return route

    def route(self, command: NormalizedCommand) -> str | None:
        if isinstance(command.spec.ros, NoRoute):
            return None
        if isinstance(command.spec.ros, SendGoal):
            return self._goal_server(command.spec.ros)
        try:
            return self._route_of(command.spec, command.params).publisher.topic
        except LookupError:
            return None  # the group is unknown: the safety checks refuse it

    async def ready(self, command: NormalizedCommand) -> str | None:
        spec = command.spec
        if spec.stopping or isinstance(spec.ros, NoRoute):
            return None  # stopping is never held back; a lock needs no robot
        if spec.effect is not Effect.CLEAR_ESTOP:
            silent = self._silent()
            if silent is not None:
                return silent
        if isinstance(spec.ros, SendGoal):
            server = self._goal_server(spec.ros)
            return None if server is not None else f"{spec.ros.type_name} is not available"
        try:
            route = self._route_of(spec, command.params)
        except LookupError as exc:
            return str(exc)
        if not await self._matched(route.publisher):
            return f"no subscriber on {route.publisher.topic}"
        return await self._takes_back(route, command.params)

    async def _takes_back(self, route: _Route, params: ActionParams) -> str | None:
        """None if a stop could take back what `route` would start (an arm's trajectory: its
        joints heard lately), else why not: nothing is sent that no stop could stop. Joints
        never heard get `match_timeout_s` to be (start-up), as a topic gets to match — one
        command per arm's topic at a time: each waiter holds an admission slot, and commands
        naming joints no robot publishes would otherwise keep them all (everyone's commands
        but stops waited behind them); the others are refused at once."""
        hold = route.spec.hold
        if hold is None:
            return None
        joints, topic = hold.joints(params), route.publisher.topic
        why = self.arms.cannot_hold(joints)  # loads the holds: the first arm command
        if why is None:
            return None
        if self.positions.known(joints) or topic in self._awaiting_joints:
            return f"a stop could not hold the arm on {topic}: {why}"
        self._awaiting_joints.add(topic)
        try:
            return await self._joints_heard(joints, topic)
        finally:
            self._awaiting_joints.discard(topic)

    async def _joints_heard(self, joints: Sequence[str], topic: str) -> str | None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.ros2.match_timeout_s
        while (why := self.arms.cannot_hold(joints)) is not None:
            if self.positions.known(joints) or loop.time() >= deadline:
                return f"a stop could not hold the arm on {topic}: {why}"
            await asyncio.sleep(0.02)
        return None

    @property
    def awaiting_joints(self) -> frozenset[str]:
        """The arm topics a command waits on for joints never heard."""
        return frozenset(self._awaiting_joints)

    async def dispatch(self, command: NormalizedCommand,
                       applied: ActionParams) -> DispatchResult:
        self.events.command_sent.emit()
        ros = command.spec.ros
        if isinstance(ros, NoRoute):
            return DispatchResult(ok=True)
        if isinstance(ros, SendGoal):
            return await self._send_goal(ros, applied, command)
        if isinstance(ros, Halt):
            return await self._stop()
        if isinstance(ros, EstopSignal) and ros.engaged:
            return await self._estop(ros, applied)
        try:
            route = self._route_of(command.spec, applied)
        except LookupError as exc:
            return DispatchResult(ok=False, detail=str(exc))
        if command.spec.motion:
            return self._publish_motion(route, applied, command.message_id)
        return self._publish(route, applied)

    async def cancel_goal(self, goal_id: str) -> bool:
        """Cancel one goal the bridge sent, on its own server (the arbiter preempting it)."""
        if self.goals is None:
            return False
        return await self.goals.cancel(goal_id)

    def signal_estop(self) -> None:
        """`emergency_stop: true` now, on the latched topic (the e-stop's dispatch repeats it
        once matched, and halts)."""
        ros = _estop_route()
        route = self._routes[id(ros.signal)]
        route.publisher.publish(route.message(with_effect(Effect.ESTOP).params()))

    def send_velocity(self, velocity: MoveParams) -> str | None:
        """One sample of a velocity stream, now; why not, if the robot is gone."""
        route = self._stream
        if velocity.linear_x or velocity.linear_y or velocity.angular_z:
            pub = route.publisher
            why = self._silent() or (None if pub.matched_count()
                                     else f"no subscriber on {pub.topic}")
            if why is not None:
                return why
            self.events.command_sent.emit()
        route.publisher.publish(route.message(velocity))  # zero always goes out
        return None

    # -- helpers ---------------------------------------------------------------------
    def _silent(self) -> str | None:
        age = self._telemetry_age()
        if age is not None and age > self.ros2.telemetry_stale_s:
            return f"robot silent: no telemetry for {age:.1f} s"
        return None

    async def _matched(self, pub: CommandPublisher, timeout: float | None = None) -> bool:
        """Whether `pub` has its robot-side reader: waited for (`timeout`, default
        `match_timeout_s`) only if it never had one."""
        if pub.matched_count():
            self._ever_matched.add(pub.topic)
            return True
        if pub.topic in self._ever_matched:
            return False  # the robot's reader left: unavailable now, not after a timeout
        try:
            await pub.wait_for_subscribers(1, timeout=timeout or self.ros2.match_timeout_s)
        except GraphTimeout:
            return False
        self._ever_matched.add(pub.topic)
        return True

    @staticmethod
    def _publish(route: _Route, params: ActionParams) -> DispatchResult:
        # No await before the write: `ready` waited, the governor checked the latch last.
        try:
            route.publisher.publish(route.message(params))
        except SampleTooLarge as exc:  # (a trajectory past ros2.max_sample_bytes): not sent
            return DispatchResult(ok=False, ros2_topic=route.publisher.topic, detail=str(exc))
        return DispatchResult(ok=True, ros2_topic=route.publisher.topic)

    def _publish_motion(self, route: _Route, params: ActionParams,
                        message_id: str) -> DispatchResult:
        # `ready` passed before the write-ahead entry; the robot may have gone silent or its
        # reader left while that was written. Checked again with no await before the write.
        pub = route.publisher
        why = self._silent() or (None if pub.matched_count() else f"no subscriber on {pub.topic}")
        hold = route.spec.hold
        if why is None and hold is not None:  # its joints' news may have gone stale since
            held_by = self.arms.cannot_hold(hold.joints(params))
            why = None if held_by is None else f"a stop could not hold the arm: {held_by}"
        if why is not None:
            return DispatchResult(ok=False, ros2_topic=pub.topic, detail=why)
        result = self._publish(route, params)
        if hold is None or not result.ok:  # (not sent: nothing runs on to be taken back)
            return result
        kit = route.kit  # it runs on after this: a stop takes it back
        runs_for_s = hold.runs_for_s(params)
        self.arms.sent(pub, message_id, hold.joints(params), runs_for_s,
                       lambda joints, where: hold.build(joints, where, kit),
                       path=hold.path(params) if hold.path is not None else ())
        return DispatchResult(ok=True, ros2_topic=pub.topic, runs_for_s=runs_for_s)

    def goals_watched(self) -> list[LeftGoal]:
        """The goals their server may still accept or run that the stop's cancel may not have
        reached: those whose send gave up (watched for, not seen ended or canceling), and
        those whose end was not seen, their server lost from sight (it may come back with
        them). A clean stop leaves them to the next start, which cancels them by id."""
        if self.goals is None:
            return []
        found = {goal[1]: goal for goal in (*self.goals.unsettled(),
                                             *self.goals.not_seen_ended())}
        return [LeftGoal(message_id=message_id or "", action=action or "", principal=None,
                         server=server, goal_id=goal_id)
                for server, goal_id, message_id, action in found.values()]

    def hold_trajectories(self, message_ids: Collection[str]) -> ArmsHeld:
        """Holds the arms still running a trajectory of `message_ids` (a stop of one
        principal's motion alone); no await. No arm command yet: none to hold."""
        return self._arms.hold(message_ids) if self._arms is not None else ArmsHeld()

    def running_trajectories(self) -> list[str]:
        """The message ids of the trajectories that may still be running."""
        return self._arms.running() if self._arms is not None else []

    def _goal_server(self, ros: SendGoal[Any]) -> str | None:
        return self.goals.action_name(ros.action_key) if self.goals is not None else None

    async def _send_goal(self, ros: SendGoal[Any], params: ActionParams,
                         command: NormalizedCommand) -> DispatchResult:
        server = self._goal_server(ros)
        if self.goals is None or server is None:
            return DispatchResult(ok=False, detail=f"{ros.type_name} is not available")
        goal = ros.build(params, self._goal_kit(ros.type_name))
        try:  # to the route's own server: each goal action has its own
            goal_id = await self.goals.send(ros.action_key, goal,
                                            timeout=self.ros2.match_timeout_s,
                                            message_id=command.message_id,
                                            command=command.spec.name,
                                            goal_id=command.goal_id)
        except Exception as exc:  # rejected, no server, timeout: all mean "not executing"
            log.warning("%s goal not accepted: %s", ros.type_name, exc)
            # A send that gave up may still be accepted late: the failure names the goal,
            # so that a crash's restart cancels it (`governance.resume`).
            may_run = command.goal_id is not None and self.goals.may_run(command.goal_id)
            return DispatchResult(ok=False, ros2_topic=server, detail=str(exc),
                                  goal_id=command.goal_id if may_run else None)
        return DispatchResult(ok=True, ros2_topic=server, goal_id=goal_id)

    def _goal_kit(self, type_name: str) -> _Kit:
        kit = self._goal_kits.get(type_name)
        if kit is None:
            kit = self._goal_kits[type_name] = _Kit(self.node, self.ros2, type_name)
        return kit

    async def halt(self) -> Halted:
        """Zero velocity, hold the arms whose trajectories may still run, cancel every goal."""
        return await self._halt_rest(*self._halt_now())

    def _halt_now(self) -> tuple[Any, bool, ArmsHeld]:
        """What a halt sends at once, before any await: zero velocity (unconditionally: late
        joiners stop too), and each arm's hold. (zero, whether cmd_vel had matched, arms)."""
        zero = self._halt.message(with_effect(Effect.HALT).params())
        matched_before = self.cmd_vel.matched_count() > 0
        self.cmd_vel.publish(zero)
        # No import here: with no holds made yet, no trajectory was sent (`arms`).
        arms = self._arms.hold_all() if self._arms is not None else ArmsHeld()
        return zero, matched_before, arms

    async def _halt_rest(self, zero: Any, matched_before: bool, arms: ArmsHeld) -> Halted:
        # The goal cancels do not wait for cmd_vel to match: a robot may never read it.
        reached, cancelled = await asyncio.gather(self._zero_reached(zero, matched_before),
                                                  self._cancel_goals())
        for why in arms.not_held:
            log.warning("halting: %s", why)
        return Halted(reached, cancelled, arms)

    async def _zero_reached(self, zero: Any, matched_before: bool) -> bool:
        if matched_before:
            return True
        reached = await self._matched(self.cmd_vel)
        if reached:
            self.cmd_vel.publish(zero)  # the first preceded the match
        return reached

    async def _cancel_goals(self) -> int:
        if self.goals is None:
            return 0
        try:
            return await self.goals.cancel_all()  # on every goal server
        except Exception:
            log.exception("cancelling goals failed")
            return 0

    # -- a crashed run's motion, taken back at start ----------------------------------
    async def halt_left(self, left: LeftRunning) -> LeftHalted:
        """What a crashed run left, taken back (`Dispatcher.halt_left`): zero velocity now
        (again once matched), its goals cancelled by id, its arms still due held where
        joint_states says they are. Each waits up to `_crash_wait_s` for its peer: the
        bridge has just joined the domain."""
        zero = self._halt.message(with_effect(Effect.HALT).params())
        matched_before = self.cmd_vel.matched_count() > 0
        self.cmd_vel.publish(zero)  # the first word, before anything is waited for
        # Each part's outcome stands whatever another's: one that raised (a goal's cancel,
        # say) is reported for its own motion alone, never for the arms held beside it
        # (red team 16: a goal's ValueError had the arms held recorded as not held).
        reached, goals, held = await asyncio.gather(
            self._zero_reached(zero, matched_before), self._cancel_left(left.goals),
            self._hold_left(left.arms), return_exceptions=True)
        if isinstance(reached, BaseException):
            log.error("taking back a crashed run's motion: the zero's reach: %r", reached)
            reached = False
        if isinstance(goals, BaseException):
            log.error("taking back a crashed run's goals failed: %r", goals)
            goals = ((), tuple(f"{g.goal_id or g.server}: {goals!r}" for g in left.goals),
                     tuple(g.message_id for g in left.goals))
        if isinstance(held, BaseException):
            log.error("taking back a crashed run's arms failed: %r", held)
            held = (ArmsHeld(not_held=(repr(held),)), tuple(a.message_id for a in left.arms))
        (cancelled, not_cancelled, goals_left), (arms, arms_left) = goals, held
        return LeftHalted(reached, cancelled, not_cancelled, arms, (*arms_left, *goals_left))

    async def _cancel_left(self, goals: Sequence[LeftGoal]
                           ) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
        """(what is canceling, why each other goal is not, the message ids of those no
        server answered for: they may still run)."""
        if not goals:
            return (), (), ()
        timeout = self._crash_wait_s
        if self.goals is None:
            whys: list[str | None] = ["no goal server is configured"] * len(goals)
        else:
            whys = list(await asyncio.gather(*(
                self.goals.cancel_left(g.server, g.goal_id, timeout, message_id=g.message_id,
                                       command=g.action) for g in goals)))
        cancelled, not_cancelled, still = [], [], []
        for goal, why in zip(goals, whys, strict=True):
            named = goal.goal_id or f"every goal of {goal.server} (no goal id recorded)"
            if why is None:
                cancelled.append(named)
                continue
            not_cancelled.append(f"{named}, of command {goal.message_id}: {why}")
            if why != CANCELING_NOTHING:
                still.append(goal.message_id)
        return tuple(cancelled), tuple(not_cancelled), tuple(still)

    async def _hold_left(self, arms: Sequence[LeftArm]) -> tuple[ArmsHeld, tuple[str, ...]]:
        """(the arms held and why others were not, the message ids of those not held)."""
        if arms:  # at start, the zero already out: the holds are made (loaded) for them
            self._holds()
        outcomes = await asyncio.gather(*(self._hold_one_left(arm) for arm in arms))
        held = tuple(dict.fromkeys(topic for topic, why in outcomes if why is None))
        not_held = tuple(f"the arm on {topic} was not held: {why}"
                         for topic, why in outcomes if why is not None)
        still = tuple(arm.message_id for arm, (_, why) in zip(arms, outcomes, strict=True)
                      if why is not None)
        return ArmsHeld(held, not_held), still

    async def _hold_one_left(self, arm: LeftArm) -> tuple[str, str | None]:
        """(the arm's topic, why it was not held — None: held)."""
        topic = arm.topic or "(no topic recorded)"
        try:
            spec = action_spec(arm.action)
            route = self._route_of(spec, msgspec.convert(arm.params, spec.params))
        except (LookupError, TypeError, ValueError, msgspec.ValidationError) as exc:
            return topic, f"its route is not configured now ({exc})"
        hold = route.spec.hold
        if hold is None or route.publisher.topic != arm.topic:  # config changed since
            return topic, f"its trajectory went to {topic}, the arm's topic is now " \
                          f"{route.publisher.topic}"
        watcher = f"left by a crashed run: {arm.message_id}"
        self.positions.watch(watcher, arm.joints)  # kept whatever else is heard
        try:
            if not await self._matched(route.publisher, self._crash_wait_s):
                why: str | None = f"no subscriber on {topic}"
            else:
                where = await self._joints_now(arm.joints)
                why = where if isinstance(where, str) else None
                if not isinstance(where, str):
                    route.publisher.publish(hold.build(arm.joints, where, route.kit))
        finally:
            self.positions.watch(watcher, ())
        if why is not None:  # the next stop of this run tries again, as for one of its own
            kit = route.kit
            # Never longer than it runs: sent before now, whatever the clock says (one set
            # back across the restart puts its entry ahead of now). By the boot clock in
            # the boot it was sent in (the wall clock may have been set forward since).
            left_ms = arm.left_ms(int(time.time() * 1000), system_boot())
            left_s = min(arm.runs_for_s, left_ms / 1000 - SETTLING_S)
            self.arms.sent(route.publisher, arm.message_id, arm.joints, max(0.0, left_s),
                           lambda joints, where: hold.build(joints, where, kit))
        return topic, why

    @property
    def _crash_wait_s(self) -> float:
        """How long the take-back of a crashed run's motion waits for each peer."""
        return max(self.ros2.match_timeout_s, self.ros2.crash_halt_wait_s)

    async def _joints_now(self, joints: Sequence[str]) -> list[float] | str:
        """Where `joints` are, heard within `_crash_wait_s`; else why not known. Never a
        joint heard at rest long ago: the crashed run's trajectory may be moving it."""
        loop = asyncio.get_running_loop()
        wait = self._crash_wait_s
        deadline = loop.time() + wait
        while isinstance(where := self.positions.now(joints, self.ros2.telemetry_stale_s),
                         str):
            if loop.time() >= deadline:
                return f"{where} (waited {wait:g} s at start-up)"
            await asyncio.sleep(0.02)
        return where

    async def halt_before_leaving(self) -> None:
        """The bridge is stopping: halt, then wait (at most LEAVING_ACK_S) until the robot's
        subscriptions acknowledged the zero and each arm's hold. A sample dropped at a busy
        reader is sent again only while our writer lives, and the process exits right after:
        seen once in CI, a SIGINT during a move left an rclpy subscriber's last Twist the
        move's."""
        halted = await self.halt()
        sent: list[CommandPublisher] = [self.cmd_vel, *(
            p for p in self._publishers.values() if p.topic in halted.arms.held)]
        # Meanwhile, goals whose send gave up that their server has not yet accepted: the
        # halt's server-wide cancel reached none of them, and their watches end as the
        # bridge leaves. Those still unsettled then, BRIDGE_STOPPED names (`goals_watched`).
        acking = asyncio.gather(*(p.acknowledged(LEAVING_ACK_S) for p in sent))
        if self.goals is not None:
            await asyncio.gather(acking, self.goals.settle(LEAVING_ACK_S))
        acked = await acking
        for publisher, ok in zip(sent, acked, strict=True):
            if not ok:
                log.warning("leaving with the halt on %s not acknowledged by every subscriber "
                            "within %s", publisher.topic, seconds(LEAVING_ACK_S))

    async def _stop(self) -> DispatchResult:
        halted = await self.halt()
        return halted.result(self.cmd_vel.topic)

    async def _estop(self, ros: EstopSignal, params: ActionParams) -> DispatchResult:
        # The governor has already latched; here the robot is told, and motion halted too.
        route = self._routes[id(ros.signal)]
        signal = route.message(params)
        route.publisher.publish(signal)
        halting = self._halt_now()  # the halt never waits for the e-stop topic to match
        told, halted = await asyncio.gather(self._told(route, signal),
                                            self._halt_rest(*halting))
        return halted.result(route.publisher.topic, told=told)

    async def _told(self, route: _Route, signal: Any) -> bool:
        told = await self._matched(route.publisher)
        if told:
            route.publisher.publish(signal)  # the first write may have preceded the match
        return told


def _halt_route() -> Halt:
    ros = with_effect(Effect.HALT).ros
    assert isinstance(ros, Halt), "the HALT action must route as Halt"
    return ros


def _estop_route() -> EstopSignal:
    ros = with_effect(Effect.ESTOP).ros
    assert isinstance(ros, EstopSignal), "the ESTOP action must route as EstopSignal"
    return ros
