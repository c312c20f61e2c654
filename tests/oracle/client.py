"""Product-side handle on the rclpy oracle agent (a subprocess in the ROS environment)."""

from __future__ import annotations

import asyncio
import json
import os
import selectors
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

AGENT = Path(__file__).with_name("rclpy_agent.py")


class OracleError(RuntimeError):
    pass


class RclpyOracle:
    """One rclpy node in its own process; `call(op, **args)` runs an op and returns its result.

    `call` blocks on the pipe. Async tests use `await acall(...)`, which runs it in a worker
    thread so the event loop (and the bridge on it) keeps running meanwhile; a lock keeps
    requests one at a time, as the pipe protocol and the request ids assume.
    """

    def __init__(self, python: Path, node_name: str = "oracle", namespace: str = "/",
                 *, domain_id: int | None = None, env: dict[str, str] | None = None) -> None:
        full_env = dict(os.environ)
        full_env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
        full_env["PYTHONUNBUFFERED"] = "1"
        if domain_id is not None:
            full_env["ROS_DOMAIN_ID"] = str(domain_id)
        full_env.update(env or {})
        self.proc = subprocess.Popen(
            [str(python), str(AGENT), node_name, namespace],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=full_env,
        )
        self._next_id = 1
        self._lock = threading.Lock()
        self._selector = selectors.DefaultSelector()
        assert self.proc.stdout is not None
        self._selector.register(self.proc.stdout, selectors.EVENT_READ)
        self._read(0, timeout=60.0)

    def call(self, op: str, timeout: float = 30.0, **args: Any) -> Any:
        with self._lock:
            rid = self._next_id
            self._next_id += 1
            assert self.proc.stdin is not None
            self.proc.stdin.write(json.dumps({"id": rid, "op": op, **args}) + "\n")
            self.proc.stdin.flush()
            return self._read(rid, timeout)

    async def acall(self, op: str, timeout: float = 30.0, **args: Any) -> Any:
        """`call` off the event loop."""
        return await asyncio.to_thread(self.call, op, timeout, **args)

    def _read(self, rid: int, timeout: float) -> Any:
        assert self.proc.stdout is not None
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not self._selector.select(left):
                raise OracleError(f"oracle did not answer request {rid} in {timeout} s")
            line = self.proc.stdout.readline()
            if not line:
                err = self.proc.stderr.read() if self.proc.stderr else ""
                raise OracleError(f"oracle exited: {err[-2000:]}")
            answer = json.loads(line)
            if answer["id"] != rid:
                continue
            if not answer["ok"]:
                raise OracleError(answer["error"])
            return answer["result"]

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()
        self._selector.close()

    def __enter__(self) -> RclpyOracle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
