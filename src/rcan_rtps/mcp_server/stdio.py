"""What `rcan-rtps mcp` needs around the SDK's stdio transport to end on a signal.

The SDK reads stdin in one of anyio's worker threads, blocked in `readline`: no cancellation
interrupts it, and it is not a daemon, so the interpreter waits for it at exit. A Ctrl-C, a
SIGTERM or SIGHUP left the server hanging for as long as its client kept stdin open (and,
had it ended, it would have skipped stopping the motion its agent had started).

- `StdinLines`: stdin's lines, read by a daemon thread that hands each over and waits until
  it is taken (the SDK's own pace); a cancelled reader leaves the thread blocked, harmlessly.
  Each line is screened first (`stdio_door.StdioDoor.screen`: a stop is found, and run, in
  any line the SDK would refuse or misread), as the bridge's `/mcp` screens a body.

SIGINT, SIGTERM and SIGHUP cancel the serving scope (`serve_stdio`, through the command
line's one way of taking them: `rcan_rtps._stop_signals`), so the server then stops what it
started, as when the client goes.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import os
import threading
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator

READ_SIZE = 65536
Screen = Callable[[bytes], Awaitable[bytes | None]]  # a line for the SDK; None: none


class StdinLines:
    """An async iterable of the text lines read from file descriptor `fd` (UTF-8;
    undecodable bytes replaced, as the SDK does). Iterate it once.

    The thread reads with os.read, holding no lock: a buffered reader's lock, held by a
    daemon thread blocked in a read, aborts the interpreter at exit (sys.stdin's is closed
    there). `screen` sees each line as read (bytes: a stop is read from what was sent, not
    from its lossy decoding) and says what of it the SDK gets."""

    def __init__(self, fd: int, screen: Screen | None = None) -> None:
        self._fd = fd
        self._screen = screen

    async def __aiter__(self) -> AsyncIterator[str]:
        loop = asyncio.get_running_loop()
        lines: asyncio.Queue[bytes] = asyncio.Queue(maxsize=1)
        thread = threading.Thread(target=self._read, args=(loop, lines), name="mcp-stdin",
                                  daemon=True)
        thread.start()
        while raw := await lines.get():
            line = raw if self._screen is None else await self._screen(raw)
            if line is not None:
                yield line.decode("utf-8", errors="replace")

    def _read(self, loop: asyncio.AbstractEventLoop, lines: asyncio.Queue[bytes]) -> None:
        for raw in _raw_lines(self._fd):
            if not _hand_over(loop, lines, raw):
                return
        _hand_over(loop, lines, b"")  # the end


def _raw_lines(fd: int) -> Iterator[bytes]:
    """The lines (each with its b"\\n", the last maybe without) until end of file, or an
    error reading (stdin closed under us: as an end)."""
    pending = bytearray()
    while True:
        try:
            chunk = os.read(fd, READ_SIZE)
        except OSError:
            chunk = b""
        if not chunk:
            if pending:
                yield bytes(pending)
            return
        pending += chunk
        if b"\n" in chunk:  # only the new bytes looked at: a long line costs no more
            *complete, rest = bytes(pending).split(b"\n")
            yield from (line + b"\n" for line in complete)
            pending[:] = rest


def _hand_over(loop: asyncio.AbstractEventLoop, lines: asyncio.Queue[bytes],
               line: bytes) -> bool:
    """Whether `line` was taken; False once nobody reads any more (the loop is closed)."""
    try:
        asyncio.run_coroutine_threadsafe(lines.put(line), loop).result()
    except (RuntimeError, concurrent.futures.CancelledError):
        return False
    return True
