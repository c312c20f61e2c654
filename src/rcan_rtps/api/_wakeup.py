"""One coalesced wake-up of the event loop, callable from any thread.

STATUS and the approvals list are told "something changed" from DDS reader threads and from
the loop, sometimes hundreds of times a second; what they send is computed afresh each time.
So however many times `changed()` is called before the loop gets to it, `refresh` runs once.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable


class Wakeup:
    def __init__(self, refresh: Callable[[], None]) -> None:
        self._refresh = refresh
        self._loop: asyncio.AbstractEventLoop | None = None
        self._scheduled = False

    def start(self) -> None:
        """From the loop that is to run `refresh`."""
        self._loop = asyncio.get_running_loop()

    def close(self) -> None:
        self._loop = None

    def changed(self) -> None:
        """Safe from any thread; a no-op before `start` and after `close`."""
        loop = self._loop
        if loop is None or self._scheduled:
            return
        self._scheduled = True
        with contextlib.suppress(RuntimeError):  # the loop is closing: nobody to tell
            loop.call_soon_threadsafe(self._run)

    def _run(self) -> None:
        self._scheduled = False
        self._refresh()
