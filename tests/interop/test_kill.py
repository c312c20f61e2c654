"""Write-ahead audit and wire liveness under attack, against real rclpy Jazzy nodes.

1. The bridge (`rcan-rtps run --config`, a real subprocess) is SIGKILLed at a random moment
   while concurrent REST clients send `move`s: every Twist rclpy received has its
   COMMAND_DISPATCHED entry, every decision a client got is in the file, and the chain verifies
   once the next start has cut a torn tail.
2. The robot is SIGKILLed (audit disk fast, or slow): once STATUS says `offline`, no `move`
   is answered "executed" and no Twist is published, not even for a move decided before whose
   write-ahead entry was still being written; a robot whose cmd_vel reader leaves cleanly gets
   503 at once, not after the staleness timeout.
3. An audit log that cannot be written: a `move` sends nothing (503 audit_unavailable), an
   e-stop still reaches the robot.

Only orderings and counts are asserted; every wait has a generous timeout (CI is slow).
`RCAN_KILL_SEED` replays the kill moments of test 1; `RCAN_KILL_ROUNDS` changes their number.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import itertools
import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
import msgspec
import pytest
from oracle.client import RclpyOracle
from waiting import eventually, take

from rcan_rtps.config import RcanConfig
from rcan_rtps.governance import AuditLog, Decision, verify
from rcan_rtps.governance import audit as audit_module
from rcan_rtps.governance.audit import load_private_key, public_key_pem
from rcan_rtps.governance.errors import AuditError

from .bridge_rig import AGENT, Rig, bridge_config, close_rig, make_rig

TOKEN = "k" * 32
TWIST = "geometry_msgs/msg/Twist"
ODOM = "nav_msgs/msg/Odometry"
CMD_VEL = "/robot1/cmd_vel"
SCALE = 100_000  # move n asks for linear_x = n / SCALE: unique, below every limit, exact
ROUNDS = int(os.environ.get("RCAN_KILL_ROUNDS", "20"))
CLIENTS = 12
ODOM_MSG = {"header": {"frame_id": "odom"}, "child_frame_id": "base_link",
            "pose": {"pose": {"orientation": {"w": 1.0}}}}


def _x(n: int) -> float:
    return n / SCALE


def _n(x: float) -> int | None:
    """The move number a received linear.x belongs to, or None if it is no move's value."""
    n = round(x * SCALE)
    return n if n > 0 and _x(n) == x else None


# -- 1. SIGKILL the bridge under load ------------------------------------------------------


def _config_text(state: Path, domain_id: int) -> str:
    return textwrap.dedent(f"""\
        robot:
          ruri: rcan://registry.local/acme/rover/unit-0001
          name: Kill Rover
        bridge:
          ros2:
            namespace: /robot1
            node_name: rcan_bridge
            domain_id: {domain_id}
            match_timeout_s: 30.0
          api:
            auth_token_env: RCAN_BRIDGE_TOKEN
          safety:
            max_linear_vel: 1.5
            max_angular_vel: 1.0
            session_timeout_s: 3600
          audit:
            path: {state / "audit.jsonl"}
            key_path: {state / "audit.key"}
          rbac:
            rate_limits_per_min: {{OWNER: null}}
        """)


@dataclass
class Round:
    index: int
    sent: int = 0
    replies: dict[int, tuple[int, dict[str, Any]]] = field(default_factory=dict)
    cut: int = 0  # requests the kill cut off (no reply)
    torn: bytes = b""  # what followed the last newline right after the kill
    snapshot_end: int = 0  # bytes of complete lines in the file right after the kill
    snapshot: str = ""  # their SHA-256


async def _start_bridge(config: Path, stderr: Any) -> tuple[asyncio.subprocess.Process, str]:
    env = {**os.environ, "RCAN_BRIDGE_TOKEN": TOKEN}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "rcan_rtps", "run", "--config", str(config), "--port", "0",
        "--no-mdns", stdout=asyncio.subprocess.PIPE, stderr=stderr, env=env)
    assert proc.stdout is not None
    try:
        while True:
            line = (await asyncio.wait_for(proc.stdout.readline(), 120)).decode()
            if not line:
                raise AssertionError(f"bridge exited before it was ready ({await proc.wait()})")
            if line.startswith("rcan-rtps ready api="):
                return proc, line.split("=", 1)[1].strip()
    except BaseException:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        await proc.wait()
        raise


async def _drain(oracle: RclpyOracle, into: list[Any], quiet: float) -> None:
    """Takes what rclpy received until nothing new came for `quiet` seconds.

    A quiet period, not a sentinel: the writer was SIGKILLed, nothing can follow its samples.
    """
    loop = asyncio.get_running_loop()
    last = loop.time()
    while loop.time() - last < quiet:
        got = await oracle.acall("take", topic=CMD_VEL)
        if got:
            into += got
            last = loop.time()
        await asyncio.sleep(0.1)


async def _load_and_kill(url: str, proc: asyncio.subprocess.Process, rnd: Round,
                         counter: itertools.count[int], rng: random.Random) -> None:
    """CLIENTS concurrent clients send moves; SIGKILL after a random number of replies."""
    kill_after = rng.randint(1, 150)
    enough = asyncio.Event()
    headers = {"Authorization": f"Bearer {TOKEN}"}
    connector = aiohttp.TCPConnector(limit=CLIENTS)
    timeout = aiohttp.ClientTimeout(total=120)
    async with aiohttp.ClientSession(headers=headers, connector=connector,
                                     timeout=timeout) as http:

        async def client() -> None:
            while True:
                n = next(counter)
                rnd.sent += 1
                body = {"action": "move", "params": {"linear_x": _x(n)}}
                try:
                    async with http.post(url + "/api/command", json=body) as resp:
                        rnd.replies[n] = (resp.status, await resp.json())
                except (aiohttp.ClientError, asyncio.TimeoutError):
                    rnd.cut += 1
                    return  # the bridge is gone
                if len(rnd.replies) >= kill_after:
                    enough.set()

        clients = [asyncio.create_task(client()) for _ in range(CLIENTS)]
        try:
            await asyncio.wait_for(enough.wait(), 120)
            await asyncio.sleep(rng.uniform(0.0, 0.3))  # a random moment in the load
            proc.send_signal(signal.SIGKILL)
            await proc.wait()
            await asyncio.wait_for(asyncio.gather(*clients), 120)
        finally:
            for task in clients:
                task.cancel()
            with contextlib.suppress(ProcessLookupError):
                proc.kill()


@pytest.mark.slow
async def test_sigkill_under_load_loses_nothing_acknowledged(
        tmp_path: Path, jazzy_python: Path, domain_id: int,
        record_property: Callable[[str, object], None]) -> None:
    seed = int(os.environ.get("RCAN_KILL_SEED", random.SystemRandom().randrange(2**32)))
    rng = random.Random(seed)
    state = tmp_path / "state"
    config = tmp_path / "robot.rcan.yaml"
    config.write_text(_config_text(state, domain_id))
    audit = state / "audit.jsonl"
    counter = itertools.count(1)
    rounds: list[Round] = []
    twists: list[Any] = []
    # One round has a torn tail for sure: a kill mid-write leaves a line's first bytes.
    forced_torn = rng.randrange(ROUNDS - 1) if ROUNDS > 1 else -1
    with RclpyOracle(jazzy_python, "robot", "/robot1", domain_id=domain_id) as oracle, \
            (tmp_path / "bridge.log").open("w") as log:
        await oracle.acall("subscribe", topic=CMD_VEL, type=TWIST, qos="deep")
        for i in range(ROUNDS):
            rnd = Round(i)
            rounds.append(rnd)
            proc, url = await _start_bridge(config, log)
            await _load_and_kill(url, proc, rnd, counter, rng)
            data = audit.read_bytes()
            rnd.snapshot_end = data.rfind(b"\n") + 1
            rnd.torn = data[rnd.snapshot_end:]
            rnd.snapshot = hashlib.sha256(data[:rnd.snapshot_end]).hexdigest()
            if i == forced_torn and not rnd.torn:
                rnd.torn = b'{"action_type":"move","ai'  # as a kill inside write() leaves it
                with audit.open("ab") as f:
                    f.write(rnd.torn)
            await _drain(oracle, twists, quiet=0.3)  # the next start drains too
        await _drain(oracle, twists, quiet=3.0)

    # The last kill's torn tail: cut and audited on open, as the next start would.
    log_ = await AuditLog.open(audit, state / "audit.key")
    await log_.close()
    pubkey = load_private_key(state / "audit.key").public_key()
    head = verify(audit, pubkey)
    pem = tmp_path / "audit.pub"
    pem.write_bytes(public_key_pem(load_private_key(state / "audit.key")))
    cli = await asyncio.to_thread(subprocess.run, [
        sys.executable, "-m", "rcan_rtps", "audit", "verify", str(audit), "--pubkey", str(pem)],
        capture_output=True, text=True, timeout=120)
    assert cli.returncode == 0, cli.stdout + cli.stderr

    final = audit.read_bytes()
    entries = [json.loads(line) for line in final.splitlines()]
    assert head.count == len(entries)
    # Nothing complete at a kill was lost or rewritten later.
    for rnd in rounds:
        assert hashlib.sha256(final[:rnd.snapshot_end]).hexdigest() == rnd.snapshot, (
            f"round {rnd.index}: entries complete at the kill changed later")
    events = Counter(e["event"] for e in entries)
    assert events["BRIDGE_STARTED"] == ROUNDS and events["BRIDGE_STOPPED"] == 0
    recovered = [e["params"] for e in entries if e["event"] == "AUDIT_TAIL_RECOVERED"]
    torn = [r for r in rounds if r.torn]
    assert [p["cut_bytes"] for p in recovered] == [len(r.torn) for r in torn]

    dispatched: dict[int, dict[str, Any]] = {}
    for e in entries:
        # (a robot-unavailable refusal is COMMAND_DISPATCHED too, with outcome failed)
        if e["event"] == "COMMAND_DISPATCHED" and e["outcome"] == "executed":
            n = _n(e["applied"]["linear_x"])
            assert n is not None and n not in dispatched, e
            dispatched[n] = e
    ids = {e["audit_id"] for e in entries}

    # (a) every Twist rclpy received was audited: a move's (COMMAND_DISPATCHED, same applied
    # value), or the zero a restart sends first when the run before was killed (its halt of
    # the motion left: NETWORK_LOSS_SAFE_STOP, scope "crash"; once, and again once matched)
    halts = [e for e in entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"
             and e["applied"].get("scope") == "crash"]
    zeros = [t for t in twists if not any(t["linear"].values()) and not any(
        t["angular"].values())]
    assert len(zeros) <= 2 * len(halts), (zeros, halts)
    received = Counter(_n(t["linear"]["x"]) for t in twists if t not in zeros)
    assert None not in received, f"a Twist that is no move's: {twists}"
    # (a move is a velocity stream: rclpy gets each value many times, all from one entry)
    unaudited = sorted(n for n in received if n not in dispatched)
    # (b) every decision a client received is in the file
    replies = {n: r for rnd in rounds for n, r in rnd.replies.items()}
    unrecorded = sorted(n for n, (_, body) in replies.items()
                        if body.get("audit_id") and body["audit_id"] not in ids)
    for n, (status, body) in replies.items():
        if status == 200:
            assert body["outcome"] == "executed" and dispatched[n]["audit_id"] == body["audit_id"]
    codes = Counter(status for status, _ in replies.values())
    report = (f"seed={seed} rounds={ROUNDS} sent={sum(r.sent for r in rounds)} "
              f"replied={len(replies)} {dict(codes)} cut_by_kill={sum(r.cut for r in rounds)} "
              f"dispatched_entries={len(dispatched)} twists_received={len(twists)} "
              f"audited_not_received={len(set(dispatched) - set(received))} "
              f"received_unanswered={len(set(received) - set(replies))} "
              f"torn_tails={len(torn)} (one forced, in round {forced_torn}) "
              f"entries={len(entries)} "
              f"LOSSES: unaudited_twists={len(unaudited)} unrecorded_replies={len(unrecorded)}")
    print("\n" + report)
    record_property("kill_report", report)
    assert not unaudited, f"Twists rclpy received without an audit entry: {unaudited}; {report}"
    assert not unrecorded, f"acknowledged decisions missing from the log: {unrecorded}; {report}"
    assert codes[200] >= ROUNDS, report  # every round was under load when it was killed
    assert received, report


# -- 2. SIGKILL the robot -------------------------------------------------------------------


def _rig_config(tmp_path: Path, domain_id: int, *, stale: float = 1.0) -> RcanConfig:
    """bridge_rig's config; sessions never time out here (a safe stop would publish zero
    Twists of its own), a first command may wait long for its match on a loaded machine."""
    config = bridge_config(tmp_path, domain_id, extra_ros2="match_timeout_s: 10.0")
    bridge = config.bridge
    return msgspec.structs.replace(config, bridge=msgspec.structs.replace(
        bridge, ros2=msgspec.structs.replace(bridge.ros2, telemetry_stale_s=stale),
        safety=msgspec.structs.replace(bridge.safety, session_timeout_s=3600.0)))


@dataclass
class Move:
    started: int  # ticks of one counter shared with the status monitor: the event order
    finished: int
    n: int
    decision: Decision


class Probe:
    """Movers and a status monitor on one event loop; `tick()` orders what they observe."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self._ticks = itertools.count()
        self.moves: list[Move] = []
        self.states: list[tuple[int, str]] = []
        self.numbers = itertools.count(1)
        self.stop = asyncio.Event()

    def tick(self) -> int:
        return next(self._ticks)

    async def move(self) -> Move:
        n = next(self.numbers)
        started = self.tick()
        decision = await self.rig.command(AGENT, {"action": "move",
                                                  "params": {"linear_x": _x(n)}})
        move = Move(started, self.tick(), n, decision)
        self.moves.append(move)
        return move

    async def mover(self) -> None:
        while not self.stop.is_set():
            await self.move()
            await asyncio.sleep(0.01)

    async def monitor(self) -> None:
        while not self.stop.is_set():
            self.states.append((self.tick(), self.rig.telemetry.status(pending_auth=0).state))
            await asyncio.sleep(0.01)

    def first(self, state: str, after: int = -1) -> int | None:
        return next((t for t, s in self.states if s == state and t > after), None)


async def _robot_online(rig: Rig, oracle: RclpyOracle) -> None:
    """Odometry at 20 Hz, a cmd_vel reader, and a first move that reached it."""
    await oracle.acall("publisher", topic="/robot1/odom", type=ODOM)
    await oracle.acall("publish_periodic", topic="/robot1/odom", type=ODOM, value=ODOM_MSG,
                       rate=20.0)
    await oracle.acall("subscribe", topic=CMD_VEL, type=TWIST)
    await eventually(lambda: rig.telemetry.status(pending_auth=0).state != "offline",
                     timeout=30)
    for _ in range(10):  # the first moves may wait for the match (match_timeout_s)
        d = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.5}})
        if d.http_status == 200:
            break
    assert d.http_status == 200, d
    await take(oracle, CMD_VEL, until=lambda got: any(t["linear"]["x"] == 0.5 for t in got),
               timeout=30)


@pytest.mark.parametrize("disk", ["fast", "slow"])
async def test_robot_sigkill_no_move_executed_once_offline(
        tmp_path: Path, jazzy_python: Path, domain_id: int, disk: str,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """`slow`: each audit write takes 0.1 s longer (an SD card): the robot may go silent while
    a move waits for its write-ahead entry."""
    config = _rig_config(tmp_path, domain_id)
    stale = config.bridge.ros2.telemetry_stale_s
    rig = await make_rig(config, jazzy_python, domain_id)
    probe = Probe(rig)
    if disk == "slow":
        write = audit_module._write_durable

        def slow_write(fd: int, data: bytes) -> float:
            started = time.perf_counter()
            time.sleep(0.1)
            write(fd, data)
            return time.perf_counter() - started  # the log sees a slow disk

        monkeypatch.setattr(audit_module, "_write_durable", slow_write)
    # When each Twist really went out, on the probe's clock.
    published: list[tuple[int, float]] = []
    cmd_vel = rig.dispatcher.cmd_vel
    publish = cmd_vel.publish

    def recorded(message: Any) -> None:
        published.append((probe.tick(), float(message.linear.x)))
        publish(message)

    cmd_vel.publish = recorded  # type: ignore[method-assign]
    try:
        await _robot_online(rig, rig.oracle)
        tasks = [asyncio.create_task(probe.mover()) for _ in range(3)]
        tasks.append(asyncio.create_task(probe.monitor()))
        try:
            await eventually(
                lambda: sum(m.decision.http_status == 200 for m in probe.moves) >= 20, timeout=60)
            killed = probe.tick()
            rig.oracle.proc.send_signal(signal.SIGKILL)
            await asyncio.to_thread(rig.oracle.proc.wait)
            # Offline after telemetry_stale_s (+ a generous margin for a loaded machine) ...
            await eventually(lambda: probe.first("offline", killed) is not None,
                             timeout=stale + 30,
                             what=lambda: f"offline after the kill: {probe.states[-5:]}")
            offline = probe.first("offline", killed)
            assert offline is not None
            # ... then at least 30 more moves, all started after STATUS said offline.
            await eventually(lambda: sum(m.started > offline for m in probe.moves) >= 30,
                             timeout=60)
        finally:
            probe.stop.set()
            await asyncio.gather(*tasks)
    finally:
        await close_rig(rig)

    after_offline = [m for m in probe.moves if m.started > offline]
    blind = [m for m in probe.moves if m.started > killed and m.decision.http_status == 200]
    straddling = [m for m in blind if m.finished > offline]
    late = [x for t, x in published if t > offline and x != 0.0]
    print(f"\nrobot SIGKILL ({disk} disk): moves={len(probe.moves)} executed after the kill "
          f"(sent to a dead robot)={len(blind)}, of which answered after STATUS said offline="
          f"{len(straddling)}; moves started once offline={len(after_offline)}; Twists "
          f"published once offline={len(late)}")
    assert all(s == "offline" for t, s in probe.states if t > offline), "the robot came back?"
    # Nothing moves the robot once the bridge itself says it is offline: not even a move
    # decided before, whose write-ahead entry was still being written.
    assert not late, f"Twists published after STATUS said offline: {late}"
    executed = [m.n for m in after_offline if m.decision.outcome.value == "executed"]
    assert not executed, f"moves answered executed after STATUS said offline: {executed}"
    assert {(m.decision.http_status, m.decision.error_code.value if m.decision.error_code
             else None) for m in after_offline} == {(503, "ROBOT_UNAVAILABLE")}
    # Each is audited once, as refused at the dispatch stage: nothing was sent.
    entries = rig.entries()
    # A move decided in time whose robot went silent during its write-ahead: COMMAND_FAILED.
    print(f"moves failed after their write-ahead entry: "
          f"{sum(e['event'] == 'COMMAND_FAILED' for e in entries)}")
    for m in after_offline:
        mine = [(e["event"], e["outcome"], e["deny_reason"].split(":")[0]) for e in entries
                if e.get("message_id") == m.decision.message_id]
        assert mine == [("COMMAND_DISPATCHED", "failed", "ROBOT_UNAVAILABLE")], (m, mine)


async def test_reader_leaving_is_unavailable_at_once(tmp_path: Path, jazzy_python: Path,
                                                     domain_id: int) -> None:
    """Telemetry stays fresh (stale only after an hour): a 503 can come only from the wire."""
    config = _rig_config(tmp_path, domain_id, stale=3600.0)
    rig = await make_rig(config, jazzy_python, domain_id)
    cmd_vel = rig.dispatcher.cmd_vel
    try:
        await _robot_online(rig, rig.oracle)

        async def next_move_refused(how: str) -> None:
            await eventually(lambda: cmd_vel.matched_count() == 0, timeout=60,
                             what=f"{how}: the cmd_vel reader is gone")
            d = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.25}})
            assert d.http_status == 503, (how, d)
            assert d.error_code is not None and d.error_code.value == "ROBOT_UNAVAILABLE"
            assert d.reason is not None and "no subscriber" in d.reason, (how, d)
            assert rig.telemetry.status(pending_auth=0).state != "offline"

        # (a) the robot destroys its cmd_vel subscription; its odometry goes on
        assert await rig.oracle.acall("unsubscribe", topic=CMD_VEL)
        await next_move_refused("unsubscribe")

        # (b) another robot process subscribes (moves run again), then exits normally
        with RclpyOracle(jazzy_python, "driver", "/robot1", domain_id=domain_id) as driver:
            await driver.acall("subscribe", topic=CMD_VEL, type=TWIST)
            assert await driver.acall("wait_matched", topic=CMD_VEL, timeout=30) >= 1
            # Once a reader has left, a command never waits for one: both sides must match.
            await eventually(lambda: cmd_vel.matched_count() >= 1, timeout=60)
            d = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.125}})
            assert d.http_status == 200, d
            got = await take(driver, CMD_VEL, timeout=30)
            # a held move streams: one velocity, sent once or more by the time we look
            assert {t["linear"]["x"] for t in got} == {0.125}
        await next_move_refused("clean exit")
    finally:
        await close_rig(rig)


# -- 3. The audit log cannot be written ------------------------------------------------------


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_unwritable_audit_blocks_motion_but_not_estop(
        tmp_path: Path, jazzy_python: Path, domain_id: int,
        monkeypatch: pytest.MonkeyPatch) -> None:
    config = _rig_config(tmp_path, domain_id)
    rig = await make_rig(config, jazzy_python, domain_id)
    try:
        await rig.oracle.acall("subscribe", topic="/robot1/emergency_stop",
                               type="std_msgs/msg/Bool", qos="transient_local")
        await rig.oracle.acall("subscribe", topic=CMD_VEL, type=TWIST)
        d = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.5}})
        assert d.http_status == 200, d
        streamed = await take(rig.oracle, CMD_VEL, timeout=30)
        assert {t["linear"]["x"] for t in streamed} == {0.5}  # a held move: 0.5, repeated

        def broken_disk(fd: int, data: bytes) -> float:
            raise OSError(5, "Input/output error (injected)")

        monkeypatch.setattr(audit_module, "_write_durable", broken_disk)
        d = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.75}})
        assert (d.http_status, d.outcome.value, d.reason) == (503, "failed", "audit_unavailable")
        assert d.audit_id is None
        # Cut back to its durable end, the log stays open: the next append tries the disk again.
        assert rig.governor.audit.healthy

        d = await rig.command(AGENT, {"action": "estop"})
        assert rig.governor.latch.latched
        # The e-stop was not audited (it says so), but the robot was told.
        assert (d.http_status, d.reason) == (503, "audit_unavailable"), d
        await take(rig.oracle, "/robot1/emergency_stop", until=lambda got: {"data": True} in got,
                   timeout=30)
        # The e-stop's halt is a zero Twist from the same writer, in order: had the refused
        # move been published, it would have arrived before it.
        twists = await take(rig.oracle, CMD_VEL, timeout=30,
                            until=lambda got: any(t["linear"]["x"] == 0.0 for t in got))
        xs = [t["linear"]["x"] for t in twists]
        assert 0.0 in xs and 0.75 not in xs, xs
    finally:
        monkeypatch.undo()
        with contextlib.suppress(AuditError):
            await rig.governor.stop()  # BRIDGE_STOPPED cannot be written either
        await rig.governor.audit.close()
        rig.oracle.close()
        rig.node.close()
    # What was written before the failure still verifies.
    verify(rig.audit_path)
