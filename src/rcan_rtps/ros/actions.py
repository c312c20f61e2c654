"""ROS 2 actions over plain DDS: a client for Fast DDS and Cyclone servers, and a server.

Action `/x` is three services (`/x/_action/send_goal`, `get_result`, `cancel_goal`) and two
topics (`feedback`, `status`); see `services.py` for the two request-reply mappings.

An `ActionClient` is made in two halves. This module holds what a client needs before it
has sent a goal: the cancel service (a server-wide cancel: a bridge's stop) and the status
reader, made with the client and made ready at start. The goal-sending half — goals, their
feedback and results, the goal and result services (`action_goals.GoalSender`, with
`ClientGoal` and `GoalResult`, still importable from here) — is loaded by the client's first
goal or `wait_for_server`: a bridge that is never asked to `navigate` never loads it (issue
27: idle memory), and nothing a stop runs is in it.

`ActionServer` (in `action_server`, still importable from here) speaks the Cyclone mapping
(like `ServiceServer`); the simulated robot serves nav2 `NavigateToPose` with it.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any

from cyclonedds.core import DDSException
from cyclonedds.idl import IdlStruct

from . import qos as qos_mod
from .errors import ActionError, ServiceUnavailable
from .names import action_names
from .participant import RosNode
from .services import RequestMapping, ServiceClient

if TYPE_CHECKING:
    from .action_goals import ClientGoal, GoalSender, LateGoal
    from .typesys.model import ActionType

log = logging.getLogger(__name__)

STATUS_TYPE = "action_msgs/msg/GoalStatusArray"
CANCEL_TYPE = "action_msgs/srv/CancelGoal"
UUID_TYPE = "unique_identifier_msgs/msg/UUID"
# Samples our status reader keeps until the reader thread takes them. The topic is keyless:
# with action_status_default's depth of 1, a listing of another writer (a second server of
# the name, any node) arriving before the reader thread took the server's replaced it, and
# a goal's end, written once, was never seen (red team 31). History is no RxO policy: what
# matches is as with rcl's profile.
STATUS_READER_DEPTH = 32
# Ended goals a server keeps (for get_result and its status list) besides its result timeout:
# a burst of goals must not hold thousands for 15 minutes, each one listed in every status.
KEEP_FINISHED = 1000


class GoalState(enum.IntEnum):
    """action_msgs/msg/GoalStatus values, plus two outcomes only a client sees."""

    UNKNOWN = 0
    ACCEPTED = 1
    EXECUTING = 2
    CANCELING = 3
    SUCCEEDED = 4
    CANCELED = 5
    ABORTED = 6
    REJECTED = 100
    SERVER_LOST = 101

    @property
    def terminal(self) -> bool:
        return self in (GoalState.SUCCEEDED, GoalState.CANCELED, GoalState.ABORTED,
                        GoalState.REJECTED, GoalState.SERVER_LOST)


def _stamp(msg: Any) -> tuple[int, int]:
    return int(msg.sec), int(msg.nanosec)


class ActionClient:
    """Sends goals to one action and follows them (the goal side: `action_goals`), and
    cancels every goal of its server."""

    def __init__(self, node: RosNode, action: str, type_name: str, *,
                 mapping: RequestMapping = RequestMapping.AUTO,
                 governed: bool = False) -> None:
        self.node = node
        # Goals and cancels the robot obeys: their endpoints carry the node's `governed_by`.
        self.governed = governed
        self.name = node.resolve(action)
        # The action's own definition is parsed by its first use (`types`: the first goal);
        # canceling needs only CancelGoal and the status type. An unknown action still fails
        # here.
        self.type_name = node.store.require(type_name)
        self._types: ActionType | None = None
        self.mapping = mapping
        names = action_names(self.name)
        self._cancel_srv = ServiceClient(node, names["cancel_goal"], CANCEL_TYPE,
                                         mapping=mapping, governed=governed)
        self._cancel_srv.describe_ahead()  # a stop may be its first call: it describes nothing
        self._sending: GoalSender | None = None  # the goal side, made by the first goal
        # Told of a goal whose send gave up that the server accepted after all, which the
        # client has cancelled (`action_goals.GoalSender._give_up`); on the event loop.
        self.on_late_goal: Callable[[LateGoal], None] | None = None
        self._closed = False
        loop = asyncio.get_running_loop()

        def on_loop(handler: Callable[[Any], None]) -> Callable[[IdlStruct], None]:
            def hop(sample: IdlStruct) -> None:  # the node's reader thread → event loop
                with contextlib.suppress(RuntimeError):  # the loop has closed
                    loop.call_soon_threadsafe(handler, sample)
            return hop

        # Governed, it says so from the start: its goal and cancel writers come with their
        # first use, and a tool about to send a goal beside it must see it before that.
        self._status = node.create_subscription(
            names["status"], STATUS_TYPE, qos_mod.ACTION_STATUS.with_(depth=STATUS_READER_DEPTH),
            callback=on_loop(self._on_status), governed=governed)
        self._on_loop = on_loop

    @property
    def types(self) -> ActionType:
        """The action's types, its definition parsed by the first call."""
        if self._types is None:
            self._types = self.node.store.action(self.type_name)
        return self._types

    def _goal_side(self) -> GoalSender:
        """The goal-sending half (action_goals.py), made by the first goal or wait for the
        server: a client that only cancels — a bridge's until its first goal, and a stop in
        any case — never loads it."""
        if self._sending is None:
            self._check_open()
            from .action_goals import GoalSender

            self._sending = GoalSender(self)
        return self._sending

    # -- graph ----------------------------------------------------------------------
    async def wait_for_server(self, timeout: float = 5.0) -> None:
        """Waits like rcl's action server check: all three services matched both ways and
        the status and feedback writers matched with our readers; then until the server's
        replies and first feedback cannot be lost (see `handshake.py`)."""
        await self._goal_side().wait_for_server(timeout)

    def _gone(self) -> bool:
        """Closed, or its node closed: its endpoints are deleted, or about to be."""
        return self._closed or self.node.closed

    def _check_open(self) -> None:
        if self._closed:
            raise ActionError(f"the action client of {self.name} is closed")
        if self.node.closed:
            raise ActionError(f"the action client of {self.name} is closed: its node "
                              f"{self.node.fqn} was closed")

    @contextlib.contextmanager
    def _closed_said(self) -> Iterator[None]:
        """What a wait says when an endpoint of ours was deleted meanwhile (this client or
        its node closed): the binding's DDSException, or the ServiceUnavailable of one of
        the action's services, becomes ActionError, saying so."""
        try:
            yield
        except (DDSException, ServiceUnavailable):
            if not self._gone():
                raise
        else:
            return
        self._check_open()  # raises; out of the handler, so not chained to the binding's

    def feedback_in_sync(self) -> bool:
        """Whether a goal sent now gets its first feedback as soon as it arrives
        (`GoalSender.feedback_in_sync`); True before any goal."""
        return self._sending is None or self._sending.feedback_in_sync()

    def repair_time(self) -> float:
        """How long a reliable sample of this server's can take to be sent again."""
        return self._goal_side().repair_time()

    async def prepare_cancel(self, timeout: float = 5.0) -> None:
        """Makes the cancel service's endpoints and waits until they are matched with the
        server's and can be answered, as a first goal's `wait_for_server` does: so that a
        server-wide cancel (a stop, for goals others sent) neither makes endpoints nor waits
        for discovery."""
        self._check_open()
        with self._closed_said():
            await self._cancel_srv.wait_for_service(timeout)

    async def cancel_goal_id(self, goal_id: bytes, timeout: float = 10.0) -> bool:
        """Asks the server to cancel the goal `goal_id`, whoever sent it (a goal of a previous
        run of ours, which no handle here knows); True if the server is canceling it. Waits
        up to `timeout` for the server's cancel service first."""
        await self.prepare_cancel(timeout)
        request = {"goal_info": {"goal_id": {"uuid": goal_id}}}

        def names_it(reply: Any) -> bool:
            return any(bytes(info.goal_id.uuid) == goal_id for info in reply.goals_canceling)

        def ours(reply: Any) -> bool:  # Fast DDS: names our goal, or refuses naming none
            return names_it(reply) or (int(reply.return_code) != 0 and not reply.goals_canceling)

        with self._closed_said():
            reply: Any = await self._cancel_srv.call(request, timeout, accept=ours,
                                                     unidentified_ok=True)
        return names_it(reply)

    def status_matches(self) -> int:
        """How many times a status writer has matched our reader (a server appeared, or
        came back); 0 once closed."""
        if self._gone():
            return 0
        return int(self._status.reader.get_subscription_matched_status().total_count)

    def server_present(self) -> bool:
        """Whether an action server is on the graph now (its status writer is matched);
        False once this client is closed."""
        return not self._gone() and self._status.matched_count() > 0

    def check_server(self) -> bool:
        """False once the server has left the graph; its open goals then end as lost.
        Raises ActionError once this client (or its node) is closed (whoever waits on a goal
        is told). True before the first goal: no server was waited for yet."""
        if self._sending is None:
            self._check_open()
            return True
        return self._sending.check_server()

    # -- goals ----------------------------------------------------------------------
    async def send_goal(self, goal: IdlStruct | Mapping[str, Any] | None = None,
                        timeout: float = 10.0, *, goal_id: bytes | None = None) -> ClientGoal:
        """Sends a goal; the returned goal says `accepted` (or its state is REJECTED).
        `goal_id`: its id, when the caller chose it (a new random one by default). Should the
        send give up (no reply in time, cancelled), a server that accepts the goal late has
        it cancelled (`on_late_goal` is told: `action_goals.GoalSender._give_up`)."""
        return await self._goal_side().send_goal(goal, timeout, goal_id=goal_id)

    def watch_late(self, goal_id: bytes, timeout: float) -> None:
        """Watches for the server accepting `goal_id` late, as if its send had given up
        here (a goal of a previous run of ours: `action_goals.GoalSender.watch_left`)."""
        self._goal_side().watch_left(goal_id, timeout)

    def unsettled_late(self) -> list[bytes]:
        """The goals whose send gave up that are watched for and not yet seen ended or
        being canceled: their server may still accept (or run) them. Oldest first."""
        return [] if self._sending is None else self._sending.unsettled()

    def watching_late(self, goal_id: bytes) -> bool:
        """Whether the send of `goal_id` gave up after its request went out, and the server
        accepting it late is being watched for (`action_goals.GoalSender._give_up`)."""
        return self._sending is not None and self._sending.watching(goal_id)

    async def cancel_all(self, timeout: float = 10.0, *, server_wide: bool = False) -> int:
        """Cancels this client's open goals (or, `server_wide`, every goal of the server,
        whoever sent it: zero goal id and stamp). Returns how many goals are canceling."""
        if server_wide:
            with self._closed_said():
                # The request is what stops; a reply that may be another client's (its identity
                # unreadable) only miscounts, so it is taken rather than fail the stop.
                reply: Any = await self._cancel_srv.call({}, timeout, unidentified_ok=True)
            return len(reply.goals_canceling)
        if self._sending is None:
            return 0  # it sent no goal
        return await self._sending.cancel_open(timeout)

    def close(self) -> None:
        """Deletes the endpoints; calls still waiting fail. Idempotent."""
        self._closed = True
        self._cancel_srv.close()
        self._status.close()
        if self._sending is not None:
            self._sending.close()

    def _on_status(self, array: IdlStruct) -> None:
        if self._sending is not None:  # else no goal of ours is there to note
            self._sending.on_status(array)

    # The goal side's counts, 0 before the first goal.
    @property
    def goals_sent(self) -> int:
        return 0 if self._sending is None else self._sending.goals_sent

    @property
    def goals_tracked(self) -> int:
        """Goals the client still routes status and feedback to (sent or ended lately)."""
        return 0 if self._sending is None else self._sending.goals_tracked

    @property
    def foreign_listings(self) -> int:
        """Status samples that listed our goals from a writer not of their server's
        participant: ignored (`action_goals.GoalSender.on_status`)."""
        return 0 if self._sending is None else self._sending.foreign_listings

    @property
    def feedback_renewed(self) -> int:
        """Feedback readers made again (their announcement unheard)."""
        return 0 if self._sending is None else self._sending.feedback_renewed

    @property
    def feedback_unannounced(self) -> int:
        """1 when goals went out with the feedback writer's announcement unheard."""
        return 0 if self._sending is None else self._sending.feedback_unannounced

    @property
    def feedback_from_capture(self) -> int:
        """Feedback samples our reader never delivered, taken from the packet capture."""
        return 0 if self._sending is None else self._sending.feedback_from_capture

    @property
    def repairs_waited(self) -> int:
        """Goals whose feedback window stayed open past the repair time because the packet
        capture showed a repair still owed (`ClientGoal.waited_owed`)."""
        return 0 if self._sending is None else self._sending.repairs_waited


_SERVER_SIDE = ("ActionServer", "Execute", "ServerGoal")
_GOAL_SIDE = ("ClientGoal", "GoalResult", "GoalSender", "LateGoal")


def __getattr__(name: str) -> Any:
    """The server side (`action_server`) and the client's goal side (`action_goals`), from
    their own modules on first use: a bridge never serves a goal, and sends one only when
    asked to (issue 27, idle memory)."""
    if name in _SERVER_SIDE:
        from . import action_server

        return getattr(action_server, name)
    if name in _GOAL_SIDE:
        from . import action_goals

        return getattr(action_goals, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
