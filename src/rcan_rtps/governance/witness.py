"""The audit witness: each signed tree head sent off the box, so a truncated log is detectable
by someone other than the machine that holds it (`rcan-rtps audit verify --witness FILE`).

`audit.witness` in the config names where:

- `file:///abs/path`: each head appended (one JSON line, the `<log>.sth` format) and fsynced;
  meant for another disk, a mount of another machine, a pipe to a shipper.
- `http://...` or `https://...`: each head POSTed as its JSON object (Content-Type
  application/json; the receiver keeps the bodies as JSON lines, the `--witness` file format).

Sending never blocks the command path: the log hands each head to a bounded queue (WITNESS_QUEUE
heads) that one daemon thread drains. When the witness falls that far behind, the oldest unsent
heads are dropped (a newer head covers every entry an older one does); a failed send is logged
(once until one succeeds again), never raised, and that head is not retried.
"""

from __future__ import annotations

import collections
import logging
import os
import stat
import threading
import urllib.parse
from pathlib import Path

from ._durable import full_fsync, not_regular_problem, write_all

log = logging.getLogger(__name__)
WITNESS_QUEUE = 256
POST_TIMEOUT_S = 5.0


def witness_problem(url: str) -> str | None:
    """What is wrong with an `audit.witness` value, or None."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme == "file":
        if parts.netloc not in ("", "localhost") or not parts.path.startswith("/"):
            return f"a file witness must be file:///absolute/path, not {url!r}"
        return None
    if parts.scheme in ("http", "https"):
        return None if parts.netloc else f"no host in {url!r}"
    return f"must be a file://, http:// or https:// URL, not {url!r}"


def witness_file(url: str) -> Path | None:
    """The file a `file:` witness appends to (None for a URL witness)."""
    if not url.startswith("file:"):
        return None
    return Path(urllib.parse.unquote(urllib.parse.urlsplit(url).path))


def check_witness_file(url: str) -> None:
    """Raises ValueError if a `file:` witness names something that is no regular file: at
    /dev/null the tree heads go nowhere, at a FIFO its thread waits for a reader for good.
    What `run` and `config check` refuse before the start."""
    path = witness_file(url)
    problem = None if path is None else not_regular_problem(path)
    if problem is not None:
        raise ValueError(f"audit witness {problem}")


class Witness:
    """Sends tree-head lines to `url` from its own thread; `submit` never blocks."""

    def __init__(self, url: str, *, queue_size: int = WITNESS_QUEUE) -> None:
        problem = witness_problem(url)
        if problem:
            raise ValueError(problem)
        self.url = url
        self._queue: collections.deque[bytes] = collections.deque()
        self._queue_size = queue_size
        self._cond = threading.Condition()
        self._closing = False
        self._busy = False
        self._failing = False
        self._dropped = 0
        self.sent = 0  # heads delivered (for tests and the log)
        self._thread = threading.Thread(target=self._run, name="rcan-audit-witness", daemon=True)
        self._thread.start()

    def submit(self, line: bytes) -> None:
        with self._cond:
            if self._closing:
                return
            if len(self._queue) >= self._queue_size:
                self._queue.popleft()
                self._dropped += 1
            self._queue.append(line)
            self._cond.notify()

    def close(self, timeout: float = 2.0) -> bool:
        """Sends what is queued (for at most `timeout` seconds), then stops; True if all went."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout)
        with self._cond:
            left = len(self._queue) + (1 if self._busy else 0)
        if left:
            log.warning("audit witness %s: %d tree heads not sent at close", self.url, left)
        return not left and not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue:
                    return
                batch = list(self._queue)
                self._queue.clear()
                dropped, self._dropped = self._dropped, 0
                self._busy = True
            if dropped:
                log.warning("audit witness %s fell behind: %d older tree heads dropped",
                            self.url, dropped)
            try:
                self._send(batch)
            finally:
                with self._cond:
                    self._busy = False

    def _send(self, batch: list[bytes]) -> None:
        try:
            path = witness_file(self.url)
            if path is not None:
                _append(path, b"".join(batch))
            else:
                for line in batch:
                    _post(self.url, line.rstrip(b"\n"))
        except (OSError, ValueError) as exc:  # URLError and HTTPError are OSErrors
            if not self._failing:
                log.warning("audit witness %s: tree head not sent: %s", self.url, exc)
            self._failing = True
            return
        if self._failing:
            log.warning("audit witness %s reachable again", self.url)
        self._failing = False
        self.sent += len(batch)


def _append(path: Path, data: bytes) -> None:
    # Without blocking: a FIFO put there since the start fails the open (no reader) or the
    # check below, instead of holding this thread, and every head after, for a reader.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NONBLOCK, 0o600)
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{path} is not a regular file")
        size = info.st_size
        try:
            write_all(fd, data)
            full_fsync(fd)
        except OSError:
            os.ftruncate(fd, size)  # no torn line for the next heads to follow
            raise
    finally:
        os.close(fd)


def _post(url: str, body: bytes) -> None:
    import urllib.request  # only where a URL witness is configured (http.client is not small)

    request = urllib.request.Request(url, data=body, method="POST",
                                     headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=POST_TIMEOUT_S) as reply:
        reply.read()
