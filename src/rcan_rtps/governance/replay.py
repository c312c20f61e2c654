"""§8.3 replay window for messages carrying rcan_version >= 1.5: fresh, and never seen before.

A message is stale when its sender's timestamp is more than `window_s` old (`safety_window_s`
for SAFETY messages), or more than `ahead_s` in the future (the sender's clock may run a little
ahead of ours; more than that is not drift). A fresh message whose `msg_id` was seen while that
id could still be fresh is a replay. Ids are kept until the message they came with goes stale,
at most `max_entries` of one sender's: when that many of its fresh ids are held, that sender's
new messages are refused (`replay_window_full`) rather than an id forgotten while a replay of it
would still pass — stops are never refused (their callers turn any refusal into a warning).
The bound is per sender because one window shared by all let any principal, a GUEST whose
messages are all refused later, fill it and so have every other principal's refused. An id
seen from any sender is a replay from every sender.

The window is kept in memory, so a start reads back the ids the audit log's last entries
name (`remember_logged`): a message the previous run took, sent again while it could still be
fresh, is a replay after a restart too. The start keeps the same bound: the newest
`max_entries` of each sender's ids (a flood's refusals are logged with their ids too: 200 000
of them, 65 MB at start, were all kept). It fails closed on the ids it does not keep: every
message of that sender sent no later than the newest of them could have been (its log time +
`ahead_s`) is refused as stale (`older_than_the_ids_kept_at_start`) until the window has passed
it; a message it sends after the restart is newer. (While the kept ids are held the sender's
window is full anyway, but they are the log's last lines, not always its latest times: after a
step back of the last run's clock they may go stale first.) Per sender, as the bound is: one
refusing every sender's would again let a flooding GUEST have other principals' messages
refused. (A forgotten id sent by another principal runs with that principal's rights.)

The wall clock may be stepped under the bridge. Ids are forgotten, and messages judged stale,
by the latest wall time this run has read (`LatestWall`) as well as by the wall time now: a
step back cannot make a message fresh again whose id was forgotten — it is refused as stale
(`..._before_the_clock_went_back`) until the clock has passed the time it was stepped back
from. A step forward makes what was fresh stale at once.

The 1.2 forms and unversioned messages keep the idempotent retry instead (the governor's).
"""

from __future__ import annotations

import heapq
import math
from collections import Counter
from pathlib import Path

from rcan_rtps._counts import count_down
from rcan_rtps.rcan import ErrorCode, Outcome
from rcan_rtps.rcan._v3 import normal_id

from . import outcomes
from .clock import Clock, latest_wall
from .log_tail import logged_ids
from .outcomes import Rejection

DEFAULT_WINDOW_S = 30.0
SAFETY_WINDOW_S = 10.0  # §8.3: a SAFETY message's window is never longer
DEFAULT_AHEAD_S = 5.0  # §8.4's clock-drift tolerance
DEFAULT_MAX_ENTRIES = 10_000
WINDOW_FULL = Rejection(429, Outcome.DENIED, ErrorCode.RATE_LIMITED, "replay_window_full")
FORGOTTEN_AT_START = "older_than_the_ids_kept_at_start"


class ReplayWindow:
    def __init__(self, clock: Clock, *, window_s: float = DEFAULT_WINDOW_S,
                 ahead_s: float = DEFAULT_AHEAD_S,
                 max_entries: int = DEFAULT_MAX_ENTRIES) -> None:
        self._clock = clock
        self._latest = latest_wall(clock)
        self.window_s = window_s
        self.safety_window_s = min(window_s, SAFETY_WINDOW_S)
        self.ahead_s = ahead_s
        self._max = max_entries  # per sender
        self._seen: dict[str, tuple[str, float]] = {}  # msg_id → (its sender, stale at)
        self._held: Counter[str] = Counter()  # sender → how many of its ids are kept
        self._expiry: list[tuple[float, str]] = []  # (when it goes stale, msg_id), soonest first
        # sender → sent at or before this, its message may bear an id the start did not keep
        self._forgotten_until: dict[str, float] = {}

    def __len__(self) -> int:
        return len(self._seen)

    def check(self, msg_id: str | None, sent_at_s: float | None, *,
              safety: bool = False, sender: str = "") -> Rejection | None:
        """None if the message may go on (its id is then remembered), else why not.
        `sender`: the authenticated principal, whose own ids count against its bound."""
        now, latest = self._clock.time(), self._latest.time()
        window = self.safety_window_s if safety else self.window_s
        if sent_at_s is None:
            return _stale("no_timestamp")
        if now - sent_at_s > window:
            return _stale(f"older_than_{window:g}_s")
        if sent_at_s - now > self.ahead_s:
            return _stale(f"more_than_{self.ahead_s:g}_s_ahead")
        if latest - sent_at_s > window:  # its id may have been forgotten before the step
            return _stale(f"older_than_{window:g}_s_before_the_clock_went_back")
        if msg_id is None:  # nothing to remember it by: fresh is all that can be said
            return None
        # One UUID is one id however it is spelled: the audit log (and so `remember_logged`)
        # names it in its canonical spelling.
        msg_id = normal_id(msg_id)
        self._forget_stale(latest)
        if msg_id in self._seen:
            return outcomes.REPLAY_DETECTED
        if sent_at_s <= self._forgotten_until.get(sender, -math.inf):
            return _stale(FORGOTTEN_AT_START)
        if self._held[sender] >= self._max:
            return WINDOW_FULL
        self._seen[msg_id] = (sender, sent_at_s + window)
        self._held[sender] += 1
        heapq.heappush(self._expiry, (sent_at_s + window, msg_id))
        return None

    def remember_logged(self, path: Path) -> int:
        """At start: remember the ids the audit log at `path` names (of messages decided,
        refused or held) in entries logged while those messages could still be fresh, each
        until it could no longer be. Returns how many.

        A message taken at time t was sent at most `ahead_s` after t, so it is stale by
        t + ahead_s + window_s at the latest; every entry naming an id counts (a message
        refused after the window took its id — an e-stop was latched, say — must not pass
        when sent again once the new run has cleared it).

        At most `max_entries` of one sender's, the newest (as a run holds them): when an id
        of a sender is not kept, its messages sent up to that id's log time + `ahead_s` are
        refused as stale until the window has passed that time (`check`).

        Entries logged ahead of the clock now (it was stepped back, or this start came before
        NTP set it) are kept too, until the clock passes them: their messages become fresh
        again when it does. Only the last run's last `window_s + ahead_s` are read."""
        now = self._clock.time()
        keep_s = self.window_s + self.ahead_s
        remembered, newest = 0, now
        for msg_id, sender, logged_s in logged_ids(path, since_s=now - keep_s):
            newest = max(newest, logged_s)
            if logged_s < newest - keep_s:
                break  # stale by the log's own last entries, whatever the clock says now
            if msg_id in self._seen:
                continue
            if self._held[sender] >= self._max:  # (read from the newest: this one is older)
                self._forget_logged(sender, logged_s)
                continue
            stale_at = logged_s + keep_s
            self._seen[msg_id] = (sender, stale_at)
            self._held[sender] += 1
            heapq.heappush(self._expiry, (stale_at, msg_id))
            remembered += 1
        return remembered

    def _forget_logged(self, sender: str, logged_s: float) -> None:
        """An id of `sender` logged at `logged_s` is not kept: refuse what may bear it (its
        message was sent `ahead_s` after it was taken at the latest)."""
        sent_by = logged_s + self.ahead_s
        if sent_by > self._forgotten_until.get(sender, -math.inf):
            self._forgotten_until[sender] = sent_by

    def release(self, msg_id: str | None, sender: str = "") -> None:
        """Forgets an id `check` let through whose message was then refused before anything
        was done with it (a full queue's 429): its retry is the same message, not a replay.
        Only the sender that brought the id releases it."""
        if msg_id is None:
            return
        msg_id = normal_id(msg_id)
        kept = self._seen.get(msg_id)
        if kept is not None and kept[0] == sender:
            self._drop(msg_id)

    def _forget_stale(self, now: float) -> None:
        if self._forgotten_until:  # (rare: after a start that left some ids out)
            for sender, sent_by in list(self._forgotten_until.items()):
                if now - sent_by > self.window_s:  # all it covers is stale
                    del self._forgotten_until[sender]
        while self._expiry and self._expiry[0][0] < now:
            stale_at, msg_id = heapq.heappop(self._expiry)
            kept = self._seen.get(msg_id)
            if kept is not None and kept[1] == stale_at:  # (not released and seen again)
                self._drop(msg_id)

    def _drop(self, msg_id: str) -> None:
        sender, _ = self._seen.pop(msg_id)
        count_down(self._held, sender)


def _stale(reason: str) -> Rejection:
    return Rejection(outcomes.MESSAGE_STALE.http_status, Outcome.DENIED, ErrorCode.MESSAGE_STALE,
                     reason)
