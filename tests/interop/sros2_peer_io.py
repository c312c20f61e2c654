"""What the SROS2 peer scripts (sros2_peer.py, sros2_feedback_peer.py) share: one JSON object a
line on stdout, and a main that runs the script's `run(domain_id)` and reports an error as
{"error": "..."} with exit 1. Imported from the scripts' own directory (they run as files, in
the secure Cyclone interpreter)."""

from __future__ import annotations

import asyncio
import json
import sys
from collections.abc import Callable, Coroutine
from typing import Any


def say(**what: Any) -> None:
    print(json.dumps(what), flush=True)


def run_peer(run: Callable[[int], Coroutine[Any, Any, None]]) -> int:
    """Runs `run` with the domain id of the command line; the exit code."""
    try:
        asyncio.run(run(int(sys.argv[1])))
    except Exception as e:  # the test reads the reason
        say(error=f"{type(e).__name__}: {e}")
        return 1
    return 0
