"""Product-side handle on the rclpy oracle agent (a subprocess in the ROS environment)."""

from __future__ import annotations

import asyncio
import json
import os
import selectors
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

AGENT = Path(__file__).with_name("rclpy_agent.py")
RMWS = ("fastrtps", "cyclonedds")  # the RMW implementations an oracle can run on
# Runs a test against rclpy on each RMW (it overrides conftest's `oracle_rmw` fixture).
both_rmws = pytest.mark.parametrize("oracle_rmw", RMWS)


def fibonacci(order: int) -> list[int]:
    """The sequence the agent's Fibonacci action server ends with for `order`."""
    seq = [0, 1]
    for i in range(1, order):
        seq.append(seq[i] + seq[i - 1])
    return seq


@dataclass(frozen=True)
class OracleEnv:
    """A ROS prefix's interpreter and the RMW its processes run on ("fastrtps" or
    "cyclonedds"; the Cyclone one comes from tests/oracle/rmw-cyclonedds)."""

    python: Path
    rmw: str = "fastrtps"

    @property
    def prefix(self) -> Path:
        return self.python.parent.parent

    @property
    def env(self) -> dict[str, str]:
        # The recipe's README: ament index lookups need AMENT_PREFIX_PATH=PREFIX.
        return {"RMW_IMPLEMENTATION": f"rmw_{self.rmw}_cpp",
                "AMENT_PREFIX_PATH": str(self.prefix)}


class OracleError(RuntimeError):
    pass


class RclpyOracle:
    """One rclpy node in its own process; `call(op, **args)` runs an op and returns its result.

    `call` blocks on the pipe. Async tests use `await acall(...)`, which runs it in a worker
    thread so the event loop (and the bridge on it) keeps running meanwhile; a lock keeps
    requests one at a time, as the pipe protocol and the request ids assume.
    """

    def __init__(self, python: Path | OracleEnv, node_name: str = "oracle",
                 namespace: str = "/", *, domain_id: int | None = None,
                 env: dict[str, str] | None = None) -> None:
        oracle = python if isinstance(python, OracleEnv) else OracleEnv(python)
        self.rmw = oracle.rmw
        full_env = {**os.environ, **oracle.env, "PYTHONUNBUFFERED": "1"}
        if domain_id is not None:
            full_env["ROS_DOMAIN_ID"] = str(domain_id)
        full_env.update(env or {})
        self.proc = subprocess.Popen(
            [str(oracle.python), str(AGENT), node_name, namespace],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=full_env,
        )
        # Drained all along: rmw warnings must never block the node on a full pipe.
        self._stderr: list[str] = []
        self._stderr_done = threading.Thread(target=self._drain_stderr, daemon=True)
        self._stderr_done.start()
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
                self.proc.wait()
                self._stderr_done.join(timeout=5)
                raise OracleError(f"oracle exited: {self.stderr()[-2000:]}")
            answer = json.loads(line)
            if answer["id"] != rid:
                continue
            if not answer["ok"]:
                raise OracleError(answer["error"])
            return answer["result"]

    def _drain_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self._stderr.append(line)

    def stderr(self) -> str:
        """What the node wrote to stderr so far (rcl/rmw log lines); all of it after close."""
        return "".join(self._stderr)

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()
        self._stderr_done.join(timeout=5)
        self._selector.close()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        if self.proc.stderr is not None and not self._stderr_done.is_alive():
            self.proc.stderr.close()  # (its reader thread has seen the end of it)

    def __enter__(self) -> RclpyOracle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
