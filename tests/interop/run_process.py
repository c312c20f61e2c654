"""`rcan-rtps run` as a real subprocess, and an HTTP client that keeps commanding it.

The process's stdout and stderr are drained by threads (a stall report with every
thread's stack must never block the process on a full pipe), so a test can print them
when something goes wrong.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp

REQUEST_TIMEOUT = 10.0  # s: generous; a request that takes longer counts as a hang


class RunProcess:
    """`python -m rcan_rtps <args>` (or `program <args>`); waits for its ready line (and the
    demo's tokens). `ready`: the ready line of another command than `run` (its group 1 is
    kept as `url`)."""

    def __init__(self, args: Sequence[str], env: dict[str, str], *, demo: bool,
                 ready_timeout: float = 90.0,
                 program: Sequence[str] = (sys.executable, "-m", "rcan_rtps"),
                 ready: str = r"^rcan-rtps ready api=(\S+)$") -> None:
        self.proc = subprocess.Popen(
            [*program, *args], stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self._drained: list[list[str]] = []  # the sinks whose stream reached its end
        self._cond = threading.Condition()
        for stream, sink in ((self.proc.stdout, self.stdout), (self.proc.stderr, self.stderr)):
            threading.Thread(target=self._drain, args=(stream, sink), daemon=True).start()
        self.url = self.wait_for(ready, ready_timeout).group(1)
        self.user = self.owner = ""
        if demo:
            self.user = self.wait_for(r"USER \(operator\) (\S+)", 10).group(1)
            self.owner = self.wait_for(r"OWNER \(owner\)\s+(\S+)", 10).group(1)

    def _drain(self, stream: Any, sink: list[str]) -> None:
        for line in stream:
            with self._cond:
                sink.append(line)
                self._cond.notify_all()
        with self._cond:
            self._drained.append(sink)
            self._cond.notify_all()

    def wait_for(self, pattern: str, timeout: float, *, stderr: bool = False) -> re.Match[str]:
        """The first line of stdout (or stderr) matching `pattern`, waiting for it."""
        lines = self.stderr if stderr else self.stdout
        deadline = time.monotonic() + timeout
        seen = 0
        with self._cond:
            while True:
                for line in lines[seen:]:
                    found = re.search(pattern, line)
                    if found:
                        return found
                seen = len(lines)
                left = deadline - time.monotonic()
                # An exited process may still have lines in the pipe, not yet read by the
                # drain thread (a busy machine): all of them are in only at the stream's end.
                ended = self.proc.poll() is not None and any(d is lines for d in self._drained)
                if left <= 0 or ended:
                    raise AssertionError(f"no line matching {pattern!r}:\n{self.output()}")
                self._cond.wait(min(left, 0.5))

    def output(self) -> str:
        with self._cond:
            return ("--- stdout ---\n" + "".join(self.stdout[-200:]) +
                    "--- stderr ---\n" + "".join(self.stderr[-400:]))

    def signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)

    def wait(self, timeout: float) -> int | None:
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, timeout: float = 30.0) -> int | None:
        """SIGTERM, then SIGKILL (whole session) if it has not ended within `timeout`."""
        self.signal(signal.SIGTERM)
        code = self.wait(timeout)
        if code is None:
            self.kill()
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()


@dataclass
class HammerReport:
    replies: dict[int, int] = field(default_factory=dict)  # HTTP status → count
    errors: list[str] = field(default_factory=list)  # the first few 5xx bodies, to say why
    hang: str | None = None  # the first request that got no reply in time
    seconds: float = 0.0

    @property
    def total(self) -> int:
        return sum(self.replies.values())


async def hammer(url: str, token: str, body: Callable[[int], dict[str, Any] | None],
                 seconds: float, *, rate_hz: float = 10.0,
                 report: HammerReport | None = None) -> HammerReport:
    """Sends `body(i)` to /api/command (or GETs /api/status when it is None) at about
    `rate_hz` for `seconds`; stops at the first request without a reply within
    REQUEST_TIMEOUT, which it records as a hang."""
    report = report or HammerReport()
    loop = asyncio.get_running_loop()
    start = loop.time()
    headers = {"Authorization": f"Bearer {token}"}
    timeout = aiohttp.ClientTimeout(total=REQUEST_TIMEOUT)
    async with aiohttp.ClientSession(headers=headers, timeout=timeout) as http:
        i = 0
        while loop.time() - start < seconds:
            payload = body(i)
            try:
                if payload is None:
                    async with http.get(url + "/api/status") as resp:
                        await resp.read()
                else:
                    async with http.post(url + "/api/command", json=payload) as resp:
                        text = await resp.text()
                        if resp.status >= 500 and len(report.errors) < 5:
                            report.errors.append(f"#{i} {payload}: {resp.status} {text}")
                report.replies[resp.status] = report.replies.get(resp.status, 0) + 1
            except (asyncio.TimeoutError, aiohttp.ClientError) as exc:
                report.hang = (f"request #{i} ({payload}) after {loop.time() - start:.1f} s: "
                               f"{type(exc).__name__} {exc}")
                break
            i += 1
            await asyncio.sleep(1.0 / rate_hz)
    report.seconds = loop.time() - start
    return report


async def post(url: str, token: str, body: dict[str, Any]) -> tuple[int, Any]:
    timeout = aiohttp.ClientTimeout(total=REQUEST_TIMEOUT)
    async with aiohttp.ClientSession(timeout=timeout) as http, http.post(
            url + "/api/command", json=body,
            headers={"Authorization": f"Bearer {token}"}) as resp:
        return resp.status, await resp.json()


def child_env(domain_id: int, **extra: str) -> dict[str, str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id), "PYTHONUNBUFFERED": "1",
           "PYTHONFAULTHANDLER": "1"}
    for key in ("RCAN_BRIDGE_TOKEN", "RCAN_DEMO_USER_TOKEN", "RCAN_DEMO_VIEWER_TOKEN"):
        env.pop(key, None)
    env.update(extra)
    return env


def state_args(tmp_path: Path, name: str) -> list[str]:
    return ["--state-dir", str(tmp_path / name)]
