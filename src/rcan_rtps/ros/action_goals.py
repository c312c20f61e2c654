"""The goal-sending half of an `ActionClient` (actions.py): goals, their status, feedback
and results, made by a client's first goal (or `wait_for_server`).

A client that has sent no goal only cancels (a server-wide cancel: a stop) and hears the
status topic; that half, in actions.py, is all a bridge loads until its first `navigate`
(issue 27: idle memory). The cancel client, the status reader and what a stop runs stay
there, made ready at start: nothing here is on the path of a stop.

With a Fast DDS server a reply is tied to its request only where the packet capture reads
its related sample identity (services.py, `Answer.tied`; replies to every client reach every
client). A send_goal reply so tied (or any in the Cyclone mapping) is taken as it is;
otherwise the client cross-checks against the status topic, which names goals by id:
- "accepted" counts only once the status topic lists our goal id; "rejected" only if our
  id has not appeared there within a short grace period;
- the result is requested once the status topic shows our goal terminal, and a reply
  not tied to our request is ours only if its status is that terminal status (a tied one
  is ours whatever it names: any peer may list our goal ended on the status topic); a
  goal accepted by a tied reply asks earlier when the topic is late (`_status_late`) and
  takes only a tied reply naming an end (`_tied_result`);
- a cancel reply is ours only if it lists our goal id (or refuses, naming no goal).
Any participant may write the status topic (a second server of the name, a broken or
hostile node: DDS without security authenticates nobody), and the topic is keyless: a goal's
status is taken only from its server's participant (`GoalSender.on_status`, `_Lister`) —
the one whose reply writer answered its send_goal with a reply tied to our request (that
writer's GUID prefix: `Answer.writer`), or, before that is known or when no reply could be
tied (and for a goal whose send gave up), any participant serving the action (a send_goal
request reader in the graph). Other writers' listings of our goals are ignored, counted
(`foreign_listings`) and logged once per writer: they neither end a goal, nor keep it from
a stop's cancel, nor count it accepted. Rclpy's servers, ours and rmw_cyclonedds' share one
participant for a node's endpoints, so the status writer has the reply writer's prefix. The
get_result request reaches every server of the name: only the goal's server's reply is
taken, once it is known (`ServiceClient.call`'s `from_participant`).
A server that leaves the graph ends its open goals with `GoalState.SERVER_LOST`; so does
one whose participant has had no status writer matched for LOST_GRACE while another's is
(a restart: a new participant, which does not have its goals).
A goal whose send gave up after its request went out is cancelled should the server accept
it late: at once, and whenever the status topic lists it running within a bounded watch
(`GoalSender._give_up`, LATE_WATCH_S); `ActionClient.on_late_goal` is told of it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import uuid
from collections.abc import AsyncIterator, Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cyclonedds.core import DDSException
from cyclonedds.idl import IdlStruct

from . import qos as qos_mod
from .actions import CANCEL_TYPE, UUID_TYPE, GoalState, _stamp
from .captured_replies import CapturedSample
from .errors import (
    ActionError,
    AmbiguousReply,
    ServiceTimeout,
    ServiceUnavailable,
    WireError,
    seconds,
)
from .graph import Direction, shared_graph
from .handshake import (
    CYCLONE_VENDOR,
    FASTDDS_VENDOR,
    WriterGuids,
    acquire_by,
    hear_announcements,
    matched_writers,
    may_withhold_before_heartbeat,
    participant_prefix,
    writer_handle,
    writers_ready,
)
from .names import action_names, mangle_topic
from .participant import RosSubscription
from .rtps_capture import IdentityCapture
from .services import (
    CAPTURE_SETTLE,
    PAIR_READER_DEPTH,
    RequestMapping,
    ServiceClient,
)

if TYPE_CHECKING:
    from .actions import ActionClient

log = logging.getLogger(__name__)

REJECT_GRACE = 0.5  # s: a "rejected" reply is ours only if our goal does not show up by then
LOST_GRACE = 0.5  # s without a status writer before open goals count as lost
POLL = 0.02
SETTLE_S = 5.0  # s: how long a finished goal's feedback waits for its result (see `feedback`)
# s: how long a dropped feedback datagram can take to come again, by the server's request
# mapping (its RMW): Cyclone's writers send a HEARTBEAT every 100 ms while a reader owes an
# ACK, Fast DDS's every 3 s; our reader asks again every 100 ms once a HEARTBEAT showed it a
# sample missing (participant.py). So with Fast DDS the repair comes with the first HEARTBEAT
# our socket did not drop: measured 0.2-3.4 s after the end, and 5.8-5.9 s where the first
# was dropped (docs/design/zero-loss.md, "Repairs dropped again"). Two HEARTBEATs, with
# margin for a busy host.
REPAIR_S = {RequestMapping.CYCLONE: 2.0, RequestMapping.FASTDDS: 7.0}
# s past REPAIR_S a window stays open while the packet capture shows the repair still owed
# (`IdentityCapture.repair_owed`: no HEARTBEAT of the feedback writer has reached our socket
# since the goal's end, or our reader's answer to the last one asks for samples again). Under
# a 3 kHz stream to a 1 kB buffer a Fast DDS writer's 3 s HEARTBEATs were all dropped at our
# socket for 10.9 s after a goal's end (docs/design/zero-loss.md, "Heartbeats dropped for the
# whole window"), and, with ~60 % of datagrams dropped, for the 15 s this was before in 5 of
# 900 goals ("A repair taken but not handed over"): 30 s is ten HEARTBEATs. Cyclone's writers
# send one every 100 ms while a reader owes an ACK: none.
OWED_REPAIR_S = {RequestMapping.CYCLONE: 0.0, RequestMapping.FASTDDS: 30.0}
OWED_POLL = 0.25  # s between looks at the capture while a repair is owed
RESULT_ASK_S = 5.0  # s: a get_result request unanswered this long is sent again (`_ask_result`)
# A goal accepted by a reply tied to our request has its result asked for before the status
# topic shows its end (`fetch_result`; rclpy asks at once) when the topic has not listed it
# UNLISTED_S after, or when only LAST_ASK_S of the wait for its end is left: its status
# samples and their HEARTBEATs were seen dropped at our socket for over 10 s.
UNLISTED_S = 1.0
LAST_ASK_S = 5.0
# A goal whose send gave up after its request went out (no reply in time, the send cancelled)
# may still be accepted by a server that was only slow (`GoalSender._give_up`): its status is
# watched for max(LATE_WATCH_S, the send's timeout) and it is cancelled as soon as it shows.
# A server that answered later than the send's timeout was busy about that long: it is given
# as long again. And no less than 10 s: the status sample listing it may have been dropped at
# our socket, and a Fast DDS writer sends it again only with a HEARTBEAT (REPAIR_S, up to 7 s
# with one dropped); a running goal's status may not be written again. A goal accepted later
# than that is cancelled when the status topic lists it running (MAX_UNSEEN); a stop (a
# server-wide cancel) cancels it too.
LATE_WATCH_S = 10.0
MAX_GIVEN_UP = 64  # goals whose send gave up, watched at once (no goal is sent while as many)
# Goals whose watch ended without the status topic listing them, kept by id (the newest this
# many: 16 bytes and a float each) so that the server accepting one later still has it
# cancelled as soon as it is listed, not run on until a stop.
MAX_UNSEEN = 1024
TAKE_BACK_CANCEL_S = 2.0  # s a cancel of such a goal waits for its reply (as a stop's does)
TAKE_BACK_RETRY_S = 1.0  # s between cancels of one listed running whose cancel went unanswered
# Status writers of other participants than our goals' servers whose listing of one of our
# goals was ignored and logged (once each): any peer may make writers by the thousand.
MAX_FOREIGN_LOGGED = 64


def forget_after() -> float:
    """s after its end a goal nobody follows the feedback of is let go of: by then a
    `feedback()` begun at its end has waited for its result (SETTLE_S) and for the longest
    repair (REPAIR_S), so nothing sent for it before its end can still come."""
    return SETTLE_S + max(REPAIR_S.values()) + max(OWED_REPAIR_S.values())


# the values a GoalStatus may carry on the wire (REJECTED and SERVER_LOST are ours alone)
_WIRE_STATES = frozenset(int(s) for s in GoalState if s < GoalState.REJECTED)
_RUNNING_STATES = frozenset({int(GoalState.ACCEPTED), int(GoalState.EXECUTING)})


@dataclass(frozen=True)
class GoalResult:
    state: GoalState
    result: IdlStruct | None
    detail: str = ""


@dataclass(frozen=True)
class LateGoal:
    """A goal whose send gave up that the server accepted after all (`GoalSender._give_up`).
    `state`: the last state the status topic listed (CANCELING: the server said it was
    canceling it, and no end was listed within the watch); `canceled`: the server took our
    cancel of it."""

    goal_id: bytes
    state: GoalState
    canceled: bool


class _GivenUp:
    """A goal whose send gave up, watched for on the status topic until `deadline` (loop
    time); `span`: how long its watch is (also how long its end is waited for). Only the
    listings of participants serving the action count (there was no send_goal reply to
    name its server: `GoalSender.on_status`)."""

    def __init__(self, goal_id: bytes, span: float) -> None:
        self.goal_id = goal_id
        self.span = span
        self.deadline = asyncio.get_running_loop().time() + span
        self.state: GoalState | None = None  # as the status topic last listed it
        self.canceled = False  # the server answered our cancel of it: canceling
        # Listed running since our last cancel of it went out: any writer may list it ended
        # (or canceling) in between, so `state` alone may never show it running.
        self.listed_running = False
        self._changed = asyncio.Event()
        self.task: asyncio.Task[None] | None = None

    def listed(self, state: GoalState) -> None:
        self.state = state
        if int(state) in _RUNNING_STATES:
            self.listed_running = True
        self._changed.set()

    @property
    def to_cancel(self) -> bool:
        """Listed running, and our cancel not answered canceling: cancelled (again)."""
        return not self.canceled and (self.listed_running or (
            self.state is not None and not self.settled))

    @property
    def settled(self) -> bool:
        """Listed ended, or being canceled: nothing more to cancel."""
        return self.state is not None and (self.state.terminal or
                                           self.state is GoalState.CANCELING)

    @property
    def ended(self) -> bool:
        return self.state is not None and self.state.terminal

    async def change(self, until: float) -> None:
        """Until the status topic lists it again, or `until` (loop time)."""
        self._changed.clear()
        left = until - asyncio.get_running_loop().time()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._changed.wait(), max(0.0, left))


# -- client -------------------------------------------------------------------------
class ClientGoal:
    """One goal sent by an `ActionClient`."""

    def __init__(self, sender: GoalSender, goal_id: bytes) -> None:
        self.client = sender.client
        self._sender = sender
        self.goal_id = goal_id
        self.accepted = False
        # Accepted by a reply known to answer our request (`Answer.tied`): then its result's
        # reply is too, and tells its end without the status topic (`fetch_result`).
        self.tied = False
        self._accepted_at: float | None = None  # loop time
        self.stamp: tuple[int, int] = (0, 0)
        self._state = GoalState.UNKNOWN
        self._ended_at: float | None = None  # monotonic time it was first seen terminal
        # Its state and stamp as its server last listed them on the status topic (None: not
        # yet), and the GUID prefix of the participant whose status writer listed them.
        self._listed: tuple[GoalState, tuple[int, int]] | None = None
        self._listed_by: bytes | None = None
        # The GUID prefix of the participant whose reply writer answered its send_goal with
        # a reply tied to our request: the server that has it, the only one whose listing
        # of it counts (`GoalSender.on_status`). None until then, or when no reply could be
        # tied: then any participant serving the action that our client matched.
        self.server: bytes | None = None
        self._sending = True  # until `send_goal` has returned it (or failed)
        # A `feedback()` waited out its end: nothing sent before the end can come any more.
        self._window_closed = False
        self._feedback: asyncio.Queue[IdlStruct] = asyncio.Queue(maxsize=1000)
        self._result: GoalResult | None = None
        self._drops = sender.node.udp_drops()  # dropped at our sockets before it was sent
        # Sent before our feedback reader was known to be in sync with a Cyclone feedback
        # writer (or one whose vendor cannot be told, as under DDS-Security): its first
        # feedback may come only with the writer's next HEARTBEAT. Once a
        # feedback of this goal was taken, its first one was too (or is lost for good): the
        # reader takes a writer's samples in order.
        self._unsynced = not sender.feedback_in_sync()
        self._fed = False
        # Looking in the packet capture for feedback of it that reached our socket but not our
        # reader (`GoalSender._expect_feedback`), until its first feedback is settled.
        self._capture: IdentityCapture | None = None
        # (writer GUID, source timestamp) of the feedback delivered from the capture: the
        # reader's copy of one, should it come after all, is not yielded again
        self._from_capture: set[tuple[bytes, int | None]] = set()
        # The look for what came before the first feedback our reader delivered, and what the
        # reader delivered meanwhile (yielded after what the look finds).
        self._looking: asyncio.Task[None] | None = None
        self._held_back: list[tuple[IdlStruct, tuple[bytes, int] | None]] = []
        # Set by `feedback()` once the goal has ended, its result is in (or was given up on)
        # and every feedback that had reached us by then was yielded: what it yields after is
        # feedback whose dropped datagram came again, in the repair window.
        self.end_settled = asyncio.Event()
        # The packet capture's mark once the goal was seen ended (`_settle`), and until when
        # (loop time) the window may stay open while it shows a repair still owed.
        self._end_mark: int | None = None
        self._owed_until: float | None = None
        self.waited_owed = False  # its window stayed open past REPAIR_S for an owed repair

    def __repr__(self) -> str:
        return f"<ClientGoal {uuid.UUID(bytes=self.goal_id)} {self.state.name}>"

    @property
    def state(self) -> GoalState:
        return self._state

    @state.setter
    def state(self, state: GoalState) -> None:
        if state.terminal and self._ended_at is None:
            self._ended_at = time.monotonic()
        self._state = state

    def _served_by(self, server: bytes) -> None:
        """Its send_goal was answered by `server`'s participant (a reply tied to our
        request): from now on only that participant's listing of it counts. A listing of
        another server of the name (which got our request too) taken before is forgotten;
        nobody has this goal yet (`send_goal` has not returned it)."""
        self.server = server
        if self._listed is not None and self._listed_by != server:
            self._listed = self._listed_by = None
            self._state, self._ended_at = GoalState.UNKNOWN, None

    def forgettable(self, now: float) -> bool:
        """Whether its client may let go of it: it has ended, `send_goal` is done with it,
        and nothing that anyone waits on can still come for it (a rejected goal has no
        feedback; otherwise a `feedback()` waited out its end, or `forget_after()` has
        passed since). Its result needs nothing of the client's tables."""
        if self._sending or self._ended_at is None:
            return False
        return self.state is GoalState.REJECTED or self._window_closed or \
            now - self._ended_at >= forget_after()

    async def feedback(self, timeout: float | None = None) -> AsyncIterator[IdlStruct]:
        """Feedback messages (the `feedback` part) until the goal has ended and no feedback
        sent before its end can still be on its way (`end_settled` is set in between)."""
        loop = asyncio.get_running_loop()
        deadline = None if timeout is None else loop.time() + timeout
        until: float | None = None  # once the end has settled: how long feedback may still come
        while True:
            if not self._feedback.empty():
                yield self._feedback.get_nowait()
                continue
            present = self._sender.check_server()
            if self.state.terminal and until is None:
                until = await self._settle(deadline)
                continue
            if until is not None:
                self.end_settled.set()
                if not present:
                    self._close_window()
                    return  # the server has left: no datagram of its can be sent again
            now = loop.time()
            if until is not None and now >= until:
                if await self._repair_owed(now):
                    until = now + OWED_POLL
                    continue
                if await self._handed_over_late():
                    continue
                self._close_window()
                return
            if deadline is not None and now >= deadline:
                return
            ends = [t for t in (until, deadline) if t is not None]
            try:
                yield await asyncio.wait_for(self._feedback.get(),
                                             min([0.1, *(t - now for t in ends)]))
            except asyncio.TimeoutError:
                continue

    async def _handed_over_late(self) -> bool:
        """As the window closes: whether feedback came meanwhile, after one more pass of the
        node's reader thread (and the capture's look, if one is under way). The capture shows
        a repair taken (our reader's ACKNACK after it) as soon as Cyclone has it, before the
        reader thread has handed the sample to us: on a busy host, closing then lost it
        (docs/design/zero-loss.md, "A repair taken but not handed over")."""
        await self._sender.node.delivered()
        if self._looking is not None:
            await asyncio.shield(self._looking)
        return not self._feedback.empty()

    def _close_window(self) -> None:
        """Nothing sent before the end can come any more: the client lets go of it."""
        self._window_closed = True
        self._sender.forget(self)

    async def ended(self) -> GoalState:
        """Waits until the goal has ended (or its server has left the graph)."""
        while not self.state.terminal:
            self._sender.check_server()
            await asyncio.sleep(POLL)
        return self.state

    async def _settle(self, deadline: float | None) -> float:
        """Once the goal is terminal: until when feedback sent before its end may still come.

        The terminal status comes on another reader than the feedback sent before it: both
        can arrive in one wake-up of the node's reader thread, which hands the status over
        first, and on a busy machine Cyclone may hand the feedback to a delivery queue of its
        own, later still. The result is asked for only now, and its reply leaves the server
        after that feedback: wait for it (bounded; whoever asks `result()` gets it cached, or
        asks again), then for one more pass of the reader thread. A feedback whose datagram
        the kernel dropped at our socket comes only once the writer's next HEARTBEAT asks for
        it to be sent again: if our DDS sockets dropped anything since the goal was
        sent (or that cannot be known), or if the goal went out before our feedback reader
        was known to be in sync with the writer (handshake.py, 4.) and none of its feedback
        has come, wait as long as the server's repair can take. docs/design/zero-loss.md
        has the evidence for each step."""
        loop = asyncio.get_running_loop()
        capture = self._sender.node.identities
        # (after the terminal status came: a HEARTBEAT heard after this was sent after the
        # goal's feedback was written, so it names it)
        self._end_mark = capture.mark() if capture is not None and capture.reading else None
        with contextlib.suppress(WireError):
            await self.result(timeout=SETTLE_S if deadline is None
                              else max(0.1, min(SETTLE_S, deadline - loop.time())))
        await self._sender.node.delivered()
        await self._feedback_from_capture()
        drops = self._sender.node.udp_drops()
        if self.state in (GoalState.REJECTED, GoalState.SERVER_LOST) or \
                (drops is not None and drops == self._drops and
                 not (self._unsynced and not self._fed)):
            return loop.time()
        owed = self._sender.owed_repair_time()
        if self._end_mark is not None and owed > 0:
            self._owed_until = loop.time() + self._sender.repair_time() + owed
        return loop.time() + self._sender.repair_time()

    async def _repair_owed(self, now: float) -> bool:
        """At the end of the repair window: whether the packet capture shows our feedback
        reader still owed a sample the feedback writer sent before the goal's end (its
        HEARTBEATs dropped at our socket since, or our reader's answer asking for samples
        again), so that the window stays open (at most OWED_REPAIR_S more). The look reads
        the capture to its end: in a worker thread."""
        capture, mark = self._sender.node.identities, self._end_mark
        if capture is None or mark is None or self._owed_until is None or \
                now >= self._owed_until or not capture.reading:
            return False
        sources = self._sender.repair_sources()
        if sources is None:
            return False
        reader, writers = sources
        owed = await asyncio.to_thread(
            lambda: any(capture.repair_owed(w, reader, mark) for w in writers))
        if owed and not self.waited_owed:
            self.waited_owed = True
            self._sender.repairs_waited += 1
            log.debug("action %s: goal %s: a feedback repair is still owed after the repair "
                      "window; waiting for it", self._sender.name, uuid.UUID(bytes=self.goal_id))
        return owed

    async def result(self, timeout: float = 60.0) -> GoalResult:
        """Waits for the goal to end and fetches its result (once)."""
        if self._result is None:
            self._result = await self._sender.fetch_result(self, timeout)
        return self._result

    async def cancel(self, timeout: float = 10.0) -> bool:
        """Asks the server to cancel this goal; True if the server is canceling it."""
        return await self._sender.cancel(self, timeout)

    def _on_feedback(self, feedback: IdlStruct, key: tuple[bytes, int] | None) -> None:
        """A feedback sample of this goal our reader delivered (`key`: its writer GUID and
        source timestamp, when known and looked for)."""
        if key is not None and key in self._from_capture:
            return  # delivered from the capture already: this is its late copy
        if self._looking is None and self._capture is not None:  # its first: look before it
            self._looking = asyncio.get_running_loop().create_task(self._captured_before(key))
        if self._looking is not None:  # after what the look finds
            self._held_back.append((feedback, key))
            return
        self._put(feedback)

    def _put(self, feedback: IdlStruct) -> None:
        self._fed = True
        if self._feedback.full():  # keep the newest
            self._feedback.get_nowait()
        self._feedback.put_nowait(feedback)

    async def _captured_before(self, key: tuple[bytes, int] | None) -> None:
        """Before the first feedback our reader delivered: the goal's feedback that reached
        our socket ahead of it (same writer, lower sequence numbers), which the reader never
        delivered. Cyclone drops as history only what came before the reader's start, so
        nothing after this one is looked for. The look may read the capture to its end (up
        to MISS_BUDGET bytes): in a worker thread, not on the loop a stop needs; what the
        reader delivers meanwhile is held back, and follows what it finds."""
        capture, earlier = self._capture, None
        try:
            if capture is not None and key is not None:
                earlier = await asyncio.to_thread(capture.feedback_before, self.goal_id, *key)
        except Exception as exc:  # (the capture closed meanwhile, say): nothing put before
            log.warning("action %s: looking in the packet capture for feedback of goal %s: "
                        "%s", self._sender.name, uuid.UUID(bytes=self.goal_id), exc)
        finally:  # no await from here on: nothing comes in between
            self._release_capture()  # (after the look: what it kept goes with it)
            for sample in sorted(earlier or (), key=lambda s: s.seq):
                self._deliver_captured(sample)
            held, self._held_back, self._looking = self._held_back, [], None
            for feedback, its_key in held:
                if its_key is None or its_key not in self._from_capture:
                    self._put(feedback)

    async def _feedback_from_capture(self) -> None:
        """Once the goal has ended and nothing of it came from our reader: its feedback that
        reached our socket all the same (Cyclone dropped it as history: a Fast DDS writer's
        HEARTBEAT ahead of it taken as our reader's start, docs/design/zero-loss.md), in the
        order the writer sent it. The reader gets its turn first (CAPTURE_SETTLE, then the
        reader thread's barrier); a sample it delivers meanwhile takes the other path
        (`_captured_before`). Each look reads the capture to its end: in a worker thread."""
        capture = self._capture
        if capture is None:
            return
        kept = await self._look_at_end(capture)
        if kept:
            await asyncio.sleep(CAPTURE_SETTLE)  # it may just have come: reader first
            await self._sender.node.delivered()
            kept = await self._look_at_end(capture)
        if kept is None:
            return  # the reader delivered one meanwhile, and what came before it was taken
        self._release_capture()
        for sample in sorted(kept, key=lambda s: (s.writer_guid, s.seq)):
            self._deliver_captured(sample)

    async def _look_at_end(self, capture: IdentityCapture) -> list[CapturedSample] | None:
        """The goal's feedback kept in the capture, read to its end in a worker thread; None
        if our reader delivered one meanwhile (the look before that one, waited for here,
        took what came first and let go of the capture)."""
        kept = await asyncio.to_thread(capture.captured_feedback, self.goal_id)
        if self._looking is not None:
            await asyncio.shield(self._looking)
        return kept if self._capture is capture else None

    def _deliver_captured(self, sample: CapturedSample) -> None:
        sender = self._sender
        try:
            message: Any = sender.node.codecs.of(sender.feedback_type).prepare_decoder() \
                .decode(sample.payload)
            ours = bytes(message.goal_id.uuid) == self.goal_id
        except Exception as exc:  # bad input from the wire: said, not raised
            log.warning("action %s: a feedback of goal %s, found in the packet capture, does "
                        "not decode: %s", sender.name, uuid.UUID(bytes=self.goal_id), exc)
            return
        if not ours:  # (the capture matched its goal id already)
            return
        self._from_capture.add((sample.writer_guid, sample.source_timestamp))
        sender.feedback_from_capture += 1
        log.info("action %s: a feedback of goal %s reached our socket but not our reader "
                 "(dropped as history); taken from the packet capture", sender.name,
                 uuid.UUID(bytes=self.goal_id))
        self._put(message.feedback)

    def _release_capture(self) -> None:
        """Stops looking in the capture for this goal's feedback (what it kept goes)."""
        capture, self._capture = self._capture, None
        if capture is not None:
            capture.forget_feedback(self.goal_id)

    @property
    def watching_capture(self) -> bool:
        return self._capture is not None or bool(self._from_capture)


class GoalSender:
    """The goal-sending half of `client`: its goal and result services, its feedback reader
    and the goals it sent, and the action's definition (parsed when this is made). It shares
    the client's cancel service, status reader and closed state (`ActionClient._goal_side`
    makes it)."""

    def __init__(self, client: ActionClient) -> None:
        self.client = client
        self.node, self.name = client.node, client.name
        self.types, self.type_name = client.types, client.type_name  # parses the action
        names = action_names(self.name)
        self._send = ServiceClient(self.node, names["send_goal"], self.type_name + "_SendGoal",
                                   mapping=client.mapping, governed=client.governed)
        self._get = ServiceClient(self.node, names["get_result"], self.type_name + "_GetResult",
                                  mapping=client.mapping)
        # Our goals the status and feedback topics may still speak of: those ended are let go
        # of once nothing more can come for them (`ClientGoal.forgettable`), so a client
        # that lives for weeks keeps only the goals of the last moments.
        self._goals: dict[bytes, ClientGoal] = {}
        # Goals whose send gave up, watched for on the status topic (`_give_up`), oldest first;
        # cancelled on a cancel client of their own, made by the first (`_take_back_client`).
        self._given_up: dict[bytes, _GivenUp] = {}
        # Those whose watch ended unlisted: goal id → its watch's span (`_note_given_up`).
        self._unseen: dict[bytes, float] = {}
        self._take_back_srv: ServiceClient | None = None
        self.goals_sent = 0
        self._unknown_status_logged = False
        # The status writers' GUIDs by handle: a listing counts only from a goal's server.
        self._status_writers = WriterGuids(self.node, client._status.reader)
        self.foreign_listings = 0  # status samples listing our goals from another writer
        self._foreign_logged: set[bytes | None] = set()
        self._server_seen = False
        self._lost_since: float | None = None
        # The participants of the status writers matched with our reader (GUID prefixes),
        # looked at again when the reader's matches change (`_servers_gone`); and since when
        # (monotonic) a goal's server has had none there.
        self._lister_matches: tuple[int, int] | None = None
        self._listers: set[bytes] = set()
        self._gone_since: dict[bytes, float] = {}
        self._feedback_ready: set[int] = set()  # feedback writers made ready (handshake.py)
        self._feedback_announced = False  # see `_await_feedback_announced`
        self._feedback_since = 0  # the capture's mark once the feedback reader was made
        self._feedback_reader_no = 0  # feedback readers made so far (renewals make more)
        # Feedback writers (handles) the current reader is known to be in sync with: one of
        # their HEARTBEATs was heard, or it took a sample of theirs (`feedback_in_sync`).
        self._feedback_synced: set[int] = set()
        self._announce_lock = asyncio.Lock()  # one such wait for goals sent at once
        self.feedback_renewed = 0  # feedback readers made again (their announcement unheard)
        self.feedback_unannounced = 0  # 1 when goals went out with the announcement unheard
        self.feedback_from_capture = 0  # feedback samples our reader never delivered, captured
        self.repairs_waited = 0  # goals whose window stayed open for a repair still owed
        self.feedback_type = self.type_name + "_FeedbackMessage"
        self._feedback_writers: WriterGuids | None = None  # of the current feedback reader
        # Made once the server's feedback writer is known (wait_for_server, handshake.py).
        self._feedback: RosSubscription | None = None
        self._feedback_topic = names["feedback"]

    async def wait_for_server(self, timeout: float = 5.0) -> None:
        """Waits like rcl's action server check: all three services matched both ways and
        the status and feedback writers matched with our readers; then until the server's
        replies and first feedback cannot be lost (see `handshake.py`)."""
        with self.client._closed_said():
            await self._wait_for_server(timeout)

    async def _wait_for_server(self, timeout: float) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout

        def left() -> float:
            return max(0.0, deadline - loop.time())

        # The capture reads from before a new feedback reader is made until it was heard.
        capture = self.node.identities
        if capture is not None and (self._feedback_announced or self.goals_sent):
            capture = None
        if capture is not None:
            capture.use()
        try:
            await self._wait_for_server_endpoints(left, deadline)
        finally:
            if capture is not None:
                capture.unuse()
        self._server_seen = True

    async def _wait_for_server_endpoints(self, left: Callable[[], float],
                                         deadline: float) -> None:
        pairs = [await client.wait_matched(left())
                 for client in (self._send, self._get, self.client._cancel_srv)]
        await self.client._status.wait_for_publishers(1, left())
        feedback = await self._feedback_subscription(left())
        await feedback.wait_for_publishers(1, left())
        writers = {h: g for h, g in matched_writers(feedback.reader).items()
                   if h not in self._feedback_ready}
        for pair in pairs:
            writers |= pair.unready_writers()
        if writers:  # one handshake for all: it proves every reader made before it
            await writers_ready(self.node, writers, left())
            for pair in pairs:
                pair.ready |= writers.keys()
            self._feedback_ready |= writers.keys()
        await self._await_feedback_announced(deadline)

    async def _await_feedback_announced(self, deadline: float) -> None:
        """As `ServiceClient._await_announced`, for the feedback reader: a Fast DDS feedback
        writer announces itself to a new reader once, and when that HEARTBEAT was dropped at
        our socket, Cyclone takes the next one, sent ahead of the first feedback, as the
        reader's start: that feedback is dropped as history (handshake.py, 3.); and our
        reader takes nothing from a Cyclone feedback writer before one of its HEARTBEATs
        (4.). So, once, before the first goal: hear one in the packet capture, or make the
        reader again (at most ANNOUNCE_TRIES readers within the deadline:
        `hear_announcements`). Needs the capture; goals sent without it wait for feedback
        longer after their end (`feedback_in_sync`). Goals sent at once share the one wait:
        another's would renew the reader with the first goal's feedback on its way
        (bounded by that goal's deadline, not ours)."""
        capture = self.node.identities
        if self._feedback_announced or capture is None or not capture.reading or \
                self.goals_sent:
            return
        if not await acquire_by(self._announce_lock, deadline):
            raise ServiceTimeout(f"action {self.name}: timed out waiting behind another goal "
                                 "for the server's feedback writer to announce itself")
        try:
            if self._feedback_announced or self.goals_sent or self._feedback is None:
                return
            await self._hear_feedback_announced(capture, deadline)
        finally:
            self._announce_lock.release()

    async def _hear_feedback_announced(self, capture: IdentityCapture, deadline: float) -> None:
        def reader() -> Any:  # the current one: a renewal makes a new one or raises
            assert self._feedback is not None
            return self._feedback.reader

        heard, unheard = await hear_announcements(
            capture, reader, lambda: self._feedback_since,
            lambda: self._renew_feedback_reader(deadline), deadline,
            vendors=(FASTDDS_VENDOR, CYCLONE_VENDOR), skip=self._in_process_feedback_writers,
            may_renew=lambda: not self.goals_sent, closed=self.client._gone)
        if self.client._gone():
            return  # wait_for_server says so
        if unheard:
            log.debug("action %s: no first HEARTBEAT from the feedback writer to our reader "
                      "after %d readers; goals go out without it", self.name,
                      self.feedback_renewed + 1)
            self.feedback_unannounced += 1
        self._feedback_synced |= heard
        self._feedback_announced = True  # heard, or given up on (best effort: once)

    def feedback_in_sync(self) -> bool:
        """Whether a goal sent now gets its first feedback as soon as it arrives: our
        feedback reader has heard a HEARTBEAT of each Cyclone feedback writer matched with it
        (in the capture) or has taken a sample of it (handshake.py, 4.). Per writer: a server
        that restarts has a new writer, out of sync with the reader made for the old one. A
        writer whose vendor cannot be told (DDS-Security) counts as a Cyclone one, unless it
        is in this process (`may_withhold_before_heartbeat`)."""
        if self._feedback is None or self.client._gone():  # (its reader deleted: the
            return True                                    # goal's call says it is closed)
        return not any(may_withhold_before_heartbeat(g) and h not in self._feedback_synced
                       and not self.node.in_process(g)  # (one DDS query per goal)
                       for h, g in matched_writers(self._feedback.reader).items())

    def _in_process_feedback_writers(self) -> set[int]:
        """Feedback writers of this process's participants: no HEARTBEAT comes from them, and
        none is needed (Cyclone delivers their samples directly)."""
        if self._feedback is None:
            return set()
        return {h for h, g in matched_writers(self._feedback.reader).items()
                if self.node.in_process(g)}

    async def _renew_feedback_reader(self, deadline: float) -> None:
        """A new feedback reader (before any goal: none can miss its feedback), matched and
        handshaken like the first."""
        loop = asyncio.get_running_loop()
        self._close_feedback()
        self.feedback_renewed += 1
        feedback = await self._feedback_subscription(max(0.0, deadline - loop.time()))
        await feedback.wait_for_publishers(1, max(0.0, deadline - loop.time()))
        writers = matched_writers(feedback.reader)
        if writers:
            await writers_ready(self.node, writers, max(0.0, deadline - loop.time()))

    async def _feedback_subscription(self, timeout: float) -> RosSubscription:
        """The feedback subscription, made once discovery shows the server's feedback
        writer (or at the timeout, for `wait_for_publishers` to report)."""
        if self._feedback is None:
            self.client._check_open()
            graph, topic = shared_graph(self.node), mangle_topic(self._feedback_topic)
            loop = asyncio.get_running_loop()
            deadline = loop.time() + timeout
            while loop.time() < deadline:
                graph.refresh()
                if any(e.dds_topic == topic and e.direction is Direction.PUBLISHER
                       for e in graph.endpoints()):
                    break
                await asyncio.sleep(POLL)
            self.client._check_open()  # closed while it waited: no reader for a closed client
            made = self._current_feedback()  # another wait made it meanwhile: one reader
            if made is not None:
                return made
            self._feedback_reader_no += 1
            self._feedback_synced = set()
            self._feedback = self.node.create_subscription(
                self._feedback_topic, self.feedback_type,
                qos_mod.DEFAULT.keeping(PAIR_READER_DEPTH),  # every goal's feedback comes
                callback=self.client._on_loop(self._feedback_taker(self._feedback_reader_no)))
            self._feedback_writers = WriterGuids(self.node, self._feedback.reader)
            # Once the reader is there: a HEARTBEAT captured after this was applied to it.
            capture = self.node.identities
            self._feedback_since = 0 if capture is None else capture.mark()
        return self._feedback

    def _current_feedback(self) -> RosSubscription | None:
        return self._feedback

    def _feedback_taker(self, number: int) -> Callable[[IdlStruct], None]:
        def on_feedback(message: IdlStruct) -> None:  # on the loop
            info = getattr(message, "sample_info", None)
            # (not the last sample of a reader made again since)
            if number == self._feedback_reader_no and info is not None:
                self._feedback_synced.add(writer_handle(info.publication_handle))
            self._on_feedback(message)
        return on_feedback

    def repair_time(self) -> float:
        """How long a reliable sample of this server's can take to be sent again (REPAIR_S);
        the longest while its RMW is not known."""
        try:
            mapping = self._get.resolve_mapping()
        except (WireError, DDSException):  # both mappings; or its node closed meanwhile
            mapping = None
        return REPAIR_S[mapping] if mapping in REPAIR_S else max(REPAIR_S.values())

    def owed_repair_time(self) -> float:
        """How long past `repair_time` a repair the capture shows owed is waited for."""
        try:
            mapping = self._get.resolve_mapping()
        except (WireError, DDSException):
            return 0.0
        return OWED_REPAIR_S.get(mapping, 0.0) if mapping is not None else 0.0

    def repair_sources(self) -> tuple[bytes, list[bytes]] | None:
        """Our feedback reader's GUID and the feedback writers matched with it that send
        over the wire (not this process's); None without a reader."""
        if self._feedback is None:
            return None
        try:
            reader = self._feedback.reader
            writers = [g for g in matched_writers(reader).values()
                       if not self.node.in_process(g)]
            return bytes(reader.guid.bytes), writers
        except DDSException:  # (deleted meanwhile: the goal's feedback says it is closed)
            return None

    def check_server(self) -> bool:
        """False once the server has left the graph; its open goals then end as lost.
        Raises ActionError once this client (or its node) is closed (whoever waits on a goal
        is told)."""
        self.client._check_open()
        matched = self.client._status.reader.get_subscription_matched_status()
        if matched.current_count > 0:
            self._server_seen, self._lost_since = True, None
            self._servers_gone(matched)
            return True
        if not self._server_seen:
            return True  # never there: that is wait_for_server's error to report
        now = time.monotonic()
        self._lost_since = self._lost_since or now
        if now - self._lost_since < LOST_GRACE:
            return True
        for goal in self._goals.values():
            if not goal.state.terminal:
                goal.state = GoalState.SERVER_LOST
        return False

    def _servers_gone(self, matched: Any) -> None:
        """Ends as lost the open goals whose server (`ClientGoal.server`) has had no status
        writer matched with our reader for LOST_GRACE, while another has: it restarted (a
        new participant, which does not have its goals) or left with a second server of the
        name still there, and only its listing of them counts. `matched`: the status
        reader's subscription-matched status, as `check_server` read it; the matched writers
        are looked up again only when it changed."""
        seen = (int(matched.total_count), int(matched.current_count))
        if seen != self._lister_matches:
            self._lister_matches = seen
            self._listers = {participant_prefix(g)
                             for g in matched_writers(self.client._status.reader).values()}
        servers = {g.server for g in self._goals.values()
                   if g.server is not None and not g.state.terminal}
        now = time.monotonic()
        for server in list(self._gone_since):
            if server in self._listers or server not in servers:
                del self._gone_since[server]
        for server in servers - self._listers:
            since = self._gone_since.setdefault(server, now)
            if now - since < LOST_GRACE:
                continue
            for goal in self._goals.values():
                if goal.server == server and not goal.state.terminal:
                    log.info("action %s: goal %s: its server left the graph (another server "
                             "of the name is there, which does not have it): lost", self.name,
                             uuid.UUID(bytes=goal.goal_id))
                    goal.state = GoalState.SERVER_LOST

    async def send_goal(self, goal: IdlStruct | Mapping[str, Any] | None = None,
                        timeout: float = 10.0, *, goal_id: bytes | None = None) -> ClientGoal:
        """Sends a goal; the returned goal says `accepted` (or its state is REJECTED).
        `goal_id`: its 16-byte id, when the caller chose it (default: a new random one)."""
        values = self.node.values
        message = goal if isinstance(goal, IdlStruct) else \
            values.build(self.types.goal.name, goal)
        with self.client._closed_said():
            return await self._send_goal(message, timeout, goal_id or uuid.uuid4().bytes)

    async def _send_goal(self, message: IdlStruct, timeout: float,
                         goal_id: bytes) -> ClientGoal:
        values = self.node.values
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        await self._wait_for_server(timeout)
        self._forget_ended()
        # A server would take it for the one it has; one given up on is cancelled if seen.
        if goal_id in self._goals or goal_id in self._given_up or goal_id in self._unseen:
            raise ActionError(f"{self.name}: goal {uuid.UUID(bytes=goal_id)} was sent already")
        self._check_watch_room()
        handle = ClientGoal(self, goal_id)
        self._goals[handle.goal_id] = handle  # before sending: feedback may come quickly
        self.goals_sent += 1
        self._expect_feedback(handle)
        request_cls: Any = self.node.types.struct(self.types.send_goal.request.name)
        request = request_cls(goal_id=values.build(UUID_TYPE, {"uuid": handle.goal_id}),
                              goal=message)
        try:
            return await self._sent(handle, request, deadline)
        except BaseException:
            # Nobody has it: the caller is told it failed. (A stop cancels every goal of the
            # server, whoever sent it: GoalTracker.cancel_all.) A slow server may still
            # accept it: it is cancelled should it show up (no await before the watch starts:
            # the status topic's news of it is not missed).
            self._goals.pop(handle.goal_id, None)
            handle._release_capture()
            self._give_up(handle.goal_id, timeout)
            raise
        finally:
            handle._sending = False

    def _check_watch_room(self) -> None:
        """Refuses a goal while MAX_GIVEN_UP sends that gave up are watched for, or could be:
        each send on its way may give up too, so it holds a place. A server that left so
        many unanswered is not answering, and making room would let go of a goal it may
        still accept (to run with nobody to cancel it but a stop). Nothing is sent; the
        watches end within max(LATE_WATCH_S, their send's timeout)."""
        on_way = sum(1 for goal in self._goals.values() if goal._sending)
        if len(self._given_up) + on_way < MAX_GIVEN_UP:
            return
        log.warning("action %s: a goal refused: %d goals whose send gave up are watched "
                    "for, %d sends on their way", self.name, len(self._given_up), on_way)
        raise ActionError(
            f"{self.name}: {len(self._given_up)} goals whose send gave up are watched for "
            f"their server accepting them late and {on_way} sends are on their way (at most "
            f"{MAX_GIVEN_UP} together): no goal is sent until it answers")

    def _give_up(self, goal_id: bytes, timeout: float) -> None:
        """The send of `goal_id` gave up after its request went out (no reply within
        `timeout`, the send cancelled, an answer the status topic never confirmed): a server
        that was only slow may accept it yet, and it would run with nobody following it.
        Cancelled at once, and again should the status topic list it running within
        max(LATE_WATCH_S, `timeout`); whoever listens (`ActionClient.on_late_goal`) is told
        of one that showed up. MAX_GIVEN_UP are watched, and no goal is sent while as many
        could be (`_check_watch_room`: a send on its way holds a place)."""
        if self.client._gone():
            return  # closed: its endpoints are gone (a bridge halts the robot as it stops)
        watch = self._given_up[goal_id] = _GivenUp(goal_id, max(LATE_WATCH_S, timeout))
        watch.task = asyncio.get_running_loop().create_task(self._take_back(watch))

    async def _take_back(self, watch: _GivenUp) -> None:
        """Cancels a goal whose send gave up: at once (the server may have it already), and
        whenever the status topic lists it running until its watch ends; then waits (as
        long again) for its end and tells `on_late_goal` of it, if the server had it."""
        loop = asyncio.get_running_loop()
        try:
            canceled = await self._cancel_given_up(watch)
            while not canceled and not watch.settled and loop.time() < watch.deadline:
                if self.client._gone():
                    return
                # Listed running and the cancel unanswered: asked again, every RETRY_S.
                until = watch.deadline if watch.state is None else \
                    min(watch.deadline, loop.time() + TAKE_BACK_RETRY_S)
                await watch.change(until)
                if watch.to_cancel:
                    canceled = await self._cancel_given_up(watch)
            if watch.state is None and not canceled:
                log.debug("action %s: goal %s, whose send gave up, was not accepted within "
                          "%s; cancelled should it be listed later", self.name,
                          uuid.UUID(bytes=watch.goal_id), seconds(watch.span))
                self._keep_unseen(watch)
                return
            # Listed ended or canceling: by its server, or by another writer (a second
            # server of the name, a broken or hostile node): listed running meanwhile, it is
            # cancelled still, and once the watch is over kept as unseen (red team 31).
            ends_by = loop.time() + watch.span
            while not watch.ended and loop.time() < ends_by:
                if self.client._gone():
                    return
                await watch.change(ends_by if not watch.to_cancel else
                                   min(ends_by, loop.time() + TAKE_BACK_RETRY_S))
                if watch.to_cancel:
                    canceled = await self._cancel_given_up(watch)
            if watch.to_cancel:  # listed running, then ended, between two looks
                canceled = await self._cancel_given_up(watch)
            state = watch.state if watch.ended or not canceled else GoalState.CANCELING
            assert state is not None
            if not canceled:
                self._keep_unseen(watch)
            self._tell_late(LateGoal(watch.goal_id, state, canceled))
        finally:
            if self._given_up.get(watch.goal_id) is watch:
                del self._given_up[watch.goal_id]

    def _tell_late(self, late: LateGoal) -> None:
        """Tells the client's callback of a late goal (on the loop, never a Cyclone thread);
        with none, the log (a warning)."""
        tell = self.client.on_late_goal
        if tell is None:
            log.warning("action %s: goal %s, whose send had given up, was accepted by the "
                        "server after all; %s, now %s", self.name,
                        uuid.UUID(bytes=late.goal_id),
                        "cancelled" if late.canceled else "not cancelled", late.state.name)
            return
        try:
            tell(late)
        except Exception:  # a callback's bug: the late goal is still said
            log.exception("action %s: telling of late goal %s (%s) failed", self.name,
                          uuid.UUID(bytes=late.goal_id), late.state.name)

    async def _cancel_given_up(self, watch: _GivenUp) -> bool:
        """Asks the server to cancel a goal whose send gave up; True if it is canceling it.
        On a cancel client of its own: with a Fast DDS server a client has one request out
        at a time (services.py), and a stop's server-wide cancel must not queue behind this
        one, which a busy server may leave unanswered."""
        loop = asyncio.get_running_loop()
        request = {"goal_info": {"goal_id": {"uuid": watch.goal_id}}}

        def ours(reply: Any) -> bool:  # Fast DDS: names our goal, or refuses naming none
            return _names_goal(reply, watch.goal_id) or (
                int(reply.return_code) != 0 and not reply.goals_canceling)

        watch.listed_running = False  # (listed running again after this: cancelled again)
        try:
            with self.client._closed_said():
                client = self._take_back_client()
                # (its first use matches it with the server: up to the watch's end)
                await client.wait_for_service(max(TAKE_BACK_CANCEL_S,
                                                  watch.deadline - loop.time()))
                reply: Any = await client.call(request, TAKE_BACK_CANCEL_S, accept=ours,
                                               unidentified_ok=True)
        except (WireError, DDSException) as exc:
            if self.client._gone():
                return False  # closed: the watch ends (`_take_back`)
            log.info("action %s: cancelling goal %s, whose send gave up: %s", self.name,
                     uuid.UUID(bytes=watch.goal_id), exc)
            return False
        watch.canceled = _names_goal(reply, watch.goal_id)
        return watch.canceled

    def watch_left(self, goal_id: bytes, timeout: float) -> None:
        """A goal a previous run of ours sent, which the server is not running now: its
        send may have given up on a server still holding the request. Watched as one whose
        send gave up here (`_give_up`), unless it is ours already or there is no room (then
        only a stop cancels it, logged)."""
        if goal_id in self._goals or goal_id in self._given_up:
            return
        if len(self._given_up) >= MAX_GIVEN_UP:
            log.warning("action %s: goal %s, left by a previous run, is not watched for (%d "
                        "goals whose send gave up are): should its server accept it late, "
                        "only a stop cancels it", self.name, uuid.UUID(bytes=goal_id),
                        len(self._given_up))
            return
        self._give_up(goal_id, timeout)

    def unsettled(self) -> list[bytes]:
        """The goals whose send gave up that are watched for and not yet seen ended or
        being canceled (listed so, or our cancel answered so): their server may run them
        yet. Oldest first."""
        return [w.goal_id for w in self._given_up.values() if not (w.settled or w.canceled)]

    def watching(self, goal_id: bytes) -> bool:
        """Whether `goal_id`'s send gave up after its request went out and its late
        acceptance is being watched for (`_give_up`): its server may run it yet."""
        return goal_id in self._given_up

    def _take_back_client(self) -> ServiceClient:
        if self._take_back_srv is None:
            self.client._check_open()
            self._take_back_srv = ServiceClient(self.node, action_names(self.name)["cancel_goal"],
                                                CANCEL_TYPE, mapping=self.client.mapping,
                                                governed=self.client.governed)
        return self._take_back_srv

    async def _sent(self, handle: ClientGoal, request: Any, deadline: float) -> ClientGoal:
        loop = asyncio.get_running_loop()
        tied, writer = False, None
        try:
            # Cross-checked: a Fast DDS reply not tied to our request counts only once the
            # status topic lists the goal (`_confirm`), so one whose identity cannot be read
            # is still taken.
            answer = await self._send.answer(request, max(0.0, deadline - loop.time()),
                                             unidentified_ok=True)
            reply: Any = answer.reply
            tied, writer = answer.tied, answer.writer
        except ServiceTimeout:
            # The reply can be lost for good when datagrams are dropped at our socket (see
            # `_ask_result`); the status topic names the goals the server accepted (a listing
            # of a participant serving the action, never another writer's: `on_status`).
            if handle._listed is None:
                raise
            log.info("action %s: no reply to goal %s, which the status topic lists: accepted",
                     self.name, uuid.UUID(bytes=handle.goal_id))
            reply = None
        if reply is None:
            accepted = True
        elif tied:
            # It answers our request (the Cyclone mapping's header, or the related sample
            # identity the capture read): it is ours, whenever the status topic lists the
            # goal. Its status sample and that writer's HEARTBEATs were seen dropped at our
            # socket for longer than `_confirm` waits (docs/design/zero-loss.md, "The goal's
            # status late"). Its writer's participant is the goal's server: only its listing
            # of the goal counts from now on.
            accepted = bool(reply.accepted)
            if writer is not None:
                handle._served_by(participant_prefix(writer))
        else:
            accepted = await self._confirm(handle, bool(reply.accepted), deadline)
        handle.accepted, handle.tied = accepted, tied and accepted
        handle._accepted_at = loop.time()
        if accepted:
            stamp = (0, 0) if reply is None else _stamp(reply.stamp)
            handle.stamp = stamp if handle._listed is None else handle._listed[1]
            handle.state = max(handle.state, GoalState.ACCEPTED)
        else:
            handle.state = GoalState.REJECTED
        return handle

    async def _confirm(self, goal: ClientGoal, accepted: bool, deadline: float) -> bool:
        """Fast DDS, a reply not tied to our request: it may be another client's; the status
        topic decides."""
        loop = asyncio.get_running_loop()
        until = deadline if accepted else min(deadline, loop.time() + REJECT_GRACE)
        while goal._listed is None:
            if loop.time() >= until:
                if accepted:
                    raise ActionError(
                        f"action {self.name}: the server answered 'accepted' but goal "
                        f"{uuid.UUID(bytes=goal.goal_id)} never appeared on its status topic "
                        "(the reply was probably another client's)")
                return False
            await asyncio.sleep(POLL)
        return True

    async def fetch_result(self, goal: ClientGoal, timeout: float) -> GoalResult:
        if not goal.accepted:
            return GoalResult(GoalState.REJECTED, None, "the server rejected the goal")
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        early: asyncio.Task[GoalResult | None] | None = None
        try:
            while not goal.state.terminal:  # the result is asked for once the goal ended ...
                if not self.check_server():
                    break
                if loop.time() >= deadline:
                    raise ActionError(f"action {self.name}: goal still {goal.state.name} "
                                      f"after {seconds(timeout)}")
                if early is None and self._status_late(goal, deadline):  # ... or earlier
                    early = asyncio.create_task(self._tied_result(goal, deadline))
                told = early.result() if early is not None and early.done() else None
                if told is not None:
                    return told
                await asyncio.sleep(POLL)
        finally:
            if early is not None and not early.done():
                early.cancel()  # (the status topic showed the end: asked for the usual way)
        if goal.state is GoalState.SERVER_LOST:
            return GoalResult(GoalState.SERVER_LOST, None,
                              f"action server {self.name} left the graph before the goal ended")
        final = goal.state

        # Fast DDS, a reply not tied to our request: another goal's result has another
        # status. (A tied reply is taken whatever it names, services.py: `final` may be
        # another writer's listing.)
        def ours(reply: Any) -> bool:
            return int(reply.status) == int(final)

        try:
            reply = await self._ask_result(goal, ours, deadline)
        except AmbiguousReply as exc:  # another client's result may have come: none taken
            return GoalResult(final, None, f"the end is the status topic's; no result: {exc}")
        if reply is None:
            return GoalResult(final, None, f"action server {self.name} left the graph before "
                              f"the result was fetched; the end is its status topic's")
        value = int(reply.status)
        if value not in _WIRE_STATES or not GoalState(value).terminal:
            # A result is asked for once the goal ended: a reply naming no end (or a value
            # action_msgs does not define) keeps the end the status topic showed.
            return GoalResult(final, reply.result,
                              f"the server's result named status {value}; kept {final.name}")
        return GoalResult(GoalState(value), reply.result)

    @staticmethod
    def _status_late(goal: ClientGoal, deadline: float) -> bool:
        """Whether a goal accepted by a reply tied to our request, whose end the status topic
        has not shown, asks for its result now: the topic has not listed it UNLISTED_S
        after, or LAST_ASK_S is all that is left before `deadline` (rather than fail on the
        topic's silence: its samples may have been dropped at our socket). Not at once: on a
        Fast DDS server the client has one request out at a time, and a goal may run long."""
        if not goal.tied or goal._accepted_at is None:
            return False
        now = asyncio.get_running_loop().time()
        return deadline - now <= LAST_ASK_S or \
            (goal._listed is None and now - goal._accepted_at >= UNLISTED_S)

    async def _tied_result(self, goal: ClientGoal, deadline: float) -> GoalResult | None:
        """The goal's result asked for before the status topic showed its end (the server
        answers once the goal has ended), taken only from a reply tied to our request that
        names an end: it tells the goal's end, and ends it here (the status topic, once its
        samples come, only repeats it). None otherwise: the status topic is waited for."""
        loop = asyncio.get_running_loop()
        request = {"goal_id": {"uuid": goal.goal_id}}
        try:
            answer = await self._get.answer(request, max(0.1, deadline - loop.time()),
                                            accept=lambda reply: _ended(reply) is not None,
                                            from_participant=goal.server)
        except (WireError, DDSException):  # timed out, ambiguous, its node closed: the usual way
            return None
        except Exception as exc:  # (a fault of ours: this ask is only a shortcut, never a need)
            log.warning("action %s: goal %s: the early ask for its result failed (%r); its end "
                        "is waited for on the status topic", self.name,
                        uuid.UUID(bytes=goal.goal_id), exc)
            return None
        reply: Any = answer.reply
        state = _ended(reply)
        if not answer.tied or state is None:
            return None
        log.info("action %s: goal %s not shown ended on the status topic; its result, tied "
                 "to our request, says %s", self.name, uuid.UUID(bytes=goal.goal_id), state.name)
        if not goal.state.terminal:
            goal.state = state
        return GoalResult(state, reply.result)

    async def _ask_result(self, goal: ClientGoal, ours: Callable[[Any], bool],
                          deadline: float) -> Any:
        """The get_result reply, asked for again every RESULT_ASK_S until `deadline`: asking
        is idempotent, and a reply can be lost for good when datagrams are dropped at our
        socket (seen with Fast DDS servers, docs/design/zero-loss.md). None once the server
        has left the graph: nobody can answer any more."""
        loop = asyncio.get_running_loop()
        request = {"goal_id": {"uuid": goal.goal_id}}
        while True:
            left = max(0.1, deadline - loop.time())
            try:
                # (every server gets the request: only the goal's server's reply is taken,
                # when known — a second server of the name may have run it too)
                return await self._get.call(request, min(RESULT_ASK_S, left), accept=ours,
                                            from_participant=goal.server)
            except (ServiceTimeout, ServiceUnavailable):
                if not self.check_server():
                    return None
                if left <= RESULT_ASK_S:
                    raise
                log.info("action %s: no result for goal %s yet; asking again", self.name,
                         uuid.UUID(bytes=goal.goal_id))

    async def cancel(self, goal: ClientGoal, timeout: float) -> bool:
        request = {"goal_info": {"goal_id": {"uuid": goal.goal_id}}}

        def ours(reply: Any) -> bool:  # Fast DDS: names our goal, or refuses naming none
            return _names_goal(reply, goal.goal_id) or (
                int(reply.return_code) != 0 and not reply.goals_canceling)

        with self.client._closed_said():
            reply: Any = await self.client._cancel_srv.call(request, timeout, accept=ours,
                                                            unidentified_ok=True)
        canceling = _names_goal(reply, goal.goal_id)
        if canceling and not goal.state.terminal:
            goal.state = GoalState.CANCELING
        return canceling

    def on_status(self, array: IdlStruct) -> None:
        # Any peer may write to the status topic: only our goals are noted (another's
        # thousands of goal ids would be kept for good), each only as its server lists it
        # (`_Lister`: another writer's listing is ignored, counted), and a status value
        # action_msgs does not define leaves the goal as it was (it tells us nothing, and
        # must not end it).
        lister = _Lister(self, array)
        for status in array.status_list:  # type: ignore[attr-defined]
            goal_id = bytes(status.goal_info.goal_id.uuid)
            goal = self._goals.get(goal_id)
            if goal is None:  # another client's, one of ours let go of, or given up on
                if goal_id in self._given_up or goal_id in self._unseen:
                    if lister.has(None):  # (no send_goal reply: its server's participant)
                        self._note_given_up(goal_id, int(status.status))
                    else:
                        lister.foreign = True
                continue
            if not lister.has(goal.server):
                lister.foreign = True
                continue
            value = int(status.status)
            if value not in _WIRE_STATES:
                if not self._unknown_status_logged:
                    self._unknown_status_logged = True
                    log.warning("action %s: goal %s has status %d, which action_msgs does not "
                                "define; ignored (logged once)", self.name,
                                uuid.UUID(bytes=goal_id), value)
                continue
            state = GoalState(value)
            goal._listed = (state, _stamp(status.goal_info.stamp))
            goal._listed_by = lister.prefix
            if not goal.state.terminal:
                goal.state = state
        if lister.foreign:
            self._foreign_listing(lister)

    def _server_participants(self) -> set[bytes]:
        """The GUID prefixes of the participants serving the action (their send_goal request
        readers, in the graph): a goal's listing counts from them until its server is known
        by its send_goal reply, or if it never is (a goal whose send gave up). Empty once the
        node's graph is gone (a status sample handed to the loop as the node closed: a
        clean-clone CI logged the DDSException out of the status callback)."""
        try:
            guids = self._send.server_guids()
        except DDSException:  # (the graph's readers deleted meanwhile)
            return set()
        return {participant_prefix(guid) for guid in guids}

    def _foreign_listing(self, lister: _Lister) -> None:
        """A status sample listed our goals from a writer that is not their server's (a
        second server of the name, a broken or hostile node: DDS without security tells
        nobody who writes): ignored, counted, logged once per writer."""
        self.foreign_listings += 1
        if lister.guid in self._foreign_logged or \
                len(self._foreign_logged) >= MAX_FOREIGN_LOGGED:
            return
        self._foreign_logged.add(lister.guid)
        log.debug("action %s: status writer %s, not of our goals' server, listed our goals: "
                  "ignored (logged once per writer)", self.name,
                  lister.guid.hex() if lister.guid is not None else "(unknown)")

    def _note_given_up(self, goal_id: bytes, value: int) -> None:
        watch = self._given_up.get(goal_id)
        if watch is not None and value in _WIRE_STATES:
            watch.listed(GoalState(value))
        elif goal_id in self._unseen and value in _RUNNING_STATES:
            # Accepted after its watch ended: taken back as when it was first given up on
            # (even past MAX_GIVEN_UP: that bound refuses sends, never a take-back).
            log.warning("action %s: goal %s, whose send gave up, is listed running after "
                        "its watch ended: cancelling it", self.name, uuid.UUID(bytes=goal_id))
            self._give_up(goal_id, self._unseen.pop(goal_id))
            watch = self._given_up.get(goal_id)  # (None: this client is closed)
            if watch is not None:
                watch.listed(GoalState(value))

    def _keep_unseen(self, watch: _GivenUp) -> None:
        self._unseen[watch.goal_id] = watch.span
        while len(self._unseen) > MAX_UNSEEN:
            del self._unseen[next(iter(self._unseen))]

    def _on_feedback(self, message: IdlStruct) -> None:
        # (None: another client's goal, or one of ours let go of, whose feedback nobody waits
        # for any more)
        goal = self._goals.get(bytes(message.goal_id.uuid))  # type: ignore[attr-defined]
        if goal is not None:
            key = self._sample_key(message) if goal.watching_capture else None
            goal._on_feedback(message.feedback, key)  # type: ignore[attr-defined]

    def _expect_feedback(self, goal: ClientGoal) -> None:
        """Before the goal goes out: has the packet capture keep its feedback from the
        feedback writers matched with our reader, so that a feedback that reaches our socket
        and is dropped as history still reaches the goal (`ClientGoal._feedback_from_capture`;
        docs/design/zero-loss.md). Only while the capture reads anyway (a Fast DDS server's
        services use it), and never under DDS-Security (fails closed): the capture sees only
        what travels in clear, so all it could take is a plaintext DATA Cyclone refuses from
        a protected writer — a forged feedback."""
        capture = None if self.node.secured else self.node.identities
        if capture is None or not capture.reading or self._feedback is None:
            return
        writers = [g for g in matched_writers(self._feedback.reader).values()
                   if not self.node.in_process(g)]  # (their samples travel in no datagram)
        if capture.expect_feedback(goal.goal_id, writers):
            goal._capture = capture

    def _sample_key(self, message: IdlStruct) -> tuple[bytes, int] | None:
        """A feedback sample's writer GUID and source timestamp (how the capture knows it)."""
        info = getattr(message, "sample_info", None)
        if info is None or self._feedback_writers is None:
            return None
        guid = None
        with contextlib.suppress(DDSException):  # (its reader deleted meanwhile)
            guid = self._feedback_writers.of(info.publication_handle)
        return None if guid is None else (guid, int(info.source_timestamp))

    @property
    def goals_tracked(self) -> int:
        """Goals the client still routes status and feedback to (sent or ended lately)."""
        return len(self._goals)

    def forget(self, goal: ClientGoal) -> None:
        if goal.forgettable(time.monotonic()) and self._goals.get(goal.goal_id) is goal:
            del self._goals[goal.goal_id]
            goal._release_capture()

    def _forget_ended(self) -> None:
        """Lets go of the goals nothing more can come for (`ClientGoal.forgettable`); one
        look at each tracked goal per goal sent. A goal not yet ended is always kept: a stop
        (`cancel_all`) cancels every one."""
        now = time.monotonic()
        for goal in [g for g in self._goals.values() if g.forgettable(now)]:
            del self._goals[goal.goal_id]
            goal._release_capture()

    def close(self) -> None:
        """Deletes the goal and result services' endpoints and the feedback reader."""
        self._status_writers.close()
        for goal in self._goals.values():
            goal._release_capture()
        for watch in self._given_up.values():
            if watch.task is not None:
                watch.task.cancel()
        for client in (self._send, self._get, self._take_back_srv):
            if client is not None:
                client.close()
        self._close_feedback()

    def _close_feedback(self) -> None:
        if self._feedback is not None:
            self._feedback.close()
            self._feedback = None
        if self._feedback_writers is not None:
            self._feedback_writers.close()
            self._feedback_writers = None

    async def cancel_open(self, timeout: float) -> int:
        """Cancels the goals this client sent that have not ended; how many are canceling."""
        open_goals = [g for g in self._goals.values() if g.accepted and not g.state.terminal]
        results = await asyncio.gather(*(g.cancel(timeout) for g in open_goals))
        return sum(results)


class _Lister:
    """The writer of one status sample, as our goals' listings go: its participant's GUID
    prefix, and (asked once a sample, only if a goal whose server is not known is listed)
    whether that participant serves the action."""

    def __init__(self, sender: GoalSender, array: IdlStruct) -> None:
        self._sender, self._array = sender, array
        self._guid: bytes | None = None
        self._looked = False
        self._serving: bool | None = None
        self.foreign = False  # it listed a goal of ours that is not its participant's

    @property
    def guid(self) -> bytes | None:
        if not self._looked:  # (only for a sample naming a goal of ours)
            # (one DDS query per writer: the reader's handles are mapped once)
            self._guid = self._sender._status_writers.of_sample(self._array)
            self._looked = True
        return self._guid

    @property
    def prefix(self) -> bytes | None:
        return None if self.guid is None else participant_prefix(self.guid)

    def has(self, server: bytes | None) -> bool:
        """Whether its listing of a goal counts: its participant is the goal's `server`
        (the send_goal reply's), or, with none known, serves the action. An unknown writer
        never counts (its goals' server, if it was, has left: SERVER_LOST)."""
        prefix = self.prefix
        if prefix is None:
            return False
        if server is not None:
            return prefix == server
        if self._serving is None:
            self._serving = prefix in self._sender._server_participants()
        return self._serving


def _ended(reply: Any) -> GoalState | None:
    """The end a get_result reply names (None: a value that is no end, or unknown)."""
    value = int(reply.status)
    return GoalState(value) if value in _WIRE_STATES and GoalState(value).terminal else None


def _names_goal(reply: Any, goal_id: bytes) -> bool:
    return any(bytes(info.goal_id.uuid) == goal_id for info in reply.goals_canceling)
