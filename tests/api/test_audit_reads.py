"""Issue 9, costly reads: GET /api/audit/verify and GET /api/audit never hold up a command's
reply (they share no executor with the audit writer and verification runs in a process),
concurrent verifications coalesce honestly, and waiting pages are bounded."""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from waiting import eventually

from rcan_rtps.api import _reads
from rcan_rtps.api._bodies import VerifyReport
from rcan_rtps.api._keys import READS
from rcan_rtps.api._reads import AuditReads
from rcan_rtps.governance import AuditEvent, AuditRecord
from tests.api.apihelpers import Api

LARGE = 20_000


async def _grow(api: Api, n: int) -> None:
    """n more entries, quickly: concurrent appends share group commits."""
    assert api.log is not None
    log = api.log
    await asyncio.gather(*(log.append(AuditRecord(
        event=AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
        action_type="move", params={"linear_x": 0.1}, outcome="executed")) for _ in range(n)))


def _reads_of(api: Api) -> AuditReads:
    assert api.app is not None
    return api.app[READS].get()  # the readers the app makes on first use


@pytest.mark.slow
async def test_estop_is_answered_before_six_verifies_of_a_large_log(api: Api) -> None:
    await _grow(api, LARGE)
    head = api.gov.audit.head.last_seq
    finished: list[str] = []

    async def verify(n: int) -> dict[str, Any]:
        status, report = await api.call("GET", "/api/audit/verify", "lessee")
        finished.append(f"verify-{n}")
        assert status == 200
        return report

    verifies = [asyncio.create_task(verify(n)) for n in range(6)]
    # The expensive part is underway:
    await eventually(lambda: _reads_of(api).verifying, timeout=120)
    status, body = await api.command("viewer", {"action": "estop"})
    finished.append("estop")
    assert (status, body["outcome"]) == (200, "executed")
    reports = await asyncio.gather(*verifies)

    assert finished[0] == "estop", finished  # the order, not the time
    assert all(r["ok"] and r["last_seq"] >= head for r in reports), reports
    assert _reads_of(api).runs < 6  # coalesced (exactly: test_verify_coalescing)


@pytest.mark.slow
async def test_a_verify_covers_the_chain_as_it_was_when_asked(api: Api) -> None:
    await _grow(api, LARGE)
    first = asyncio.create_task(api.call("GET", "/api/audit/verify", "lessee"))
    await eventually(lambda: _reads_of(api).verifying, timeout=120)
    # Written while that run reads the file: a request from now on must see it.
    status, body = await api.command("planner", {"action": "move"})
    assert status == 200
    seq = api.entry(body["audit_id"])["seq"]
    later = await asyncio.gather(*(api.call("GET", "/api/audit/verify", "lessee")
                                   for _ in range(5)))
    assert all(s == 200 and r["ok"] and r["last_seq"] >= seq for s, r in later), later
    assert (await first)[1]["ok"]
    # The first, and runs shared by the five that came later (one, unless the first run ended
    # while they were still arriving).
    assert 2 <= _reads_of(api).runs <= 3


async def test_verify_coalescing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Deterministic: a fake verifier the test releases by hand."""
    api = Api(tmp_path)
    await api.build()
    reads = _reads_of(api)
    gate = asyncio.Event()
    served: list[int] = []

    async def fake() -> VerifyReport:
        served.append(len(served) + 1)
        run = len(served)
        await gate.wait()
        return VerifyReport(ok=True, count=run, last_seq=run)

    monkeypatch.setattr(reads, "_verify_once", fake)
    try:
        a = asyncio.create_task(reads.verify())
        b = asyncio.create_task(reads.verify())  # before run 1 reads anything: joins it
        await eventually(lambda: reads.verifying, timeout=120)
        later = [asyncio.create_task(reads.verify()) for _ in range(5)]  # run 1 is reading
        await asyncio.sleep(0.05)
        assert served == [1]  # one run at a time
        gate.set()
        got = [r.last_seq for r in await asyncio.gather(a, b, *later)]
        assert got == [1, 1, 2, 2, 2, 2, 2]
        assert reads.runs == 2 and not reads.verifying
    finally:
        gate.set()
        await api.close()


async def test_a_cancelled_caller_does_not_cancel_the_shared_run(tmp_path: Path,
                                                                 monkeypatch: Any) -> None:
    api = Api(tmp_path)
    await api.build()
    reads = _reads_of(api)
    gate = asyncio.Event()

    async def fake() -> VerifyReport:
        await gate.wait()
        return VerifyReport(ok=True, count=1, last_seq=1)

    monkeypatch.setattr(reads, "_verify_once", fake)
    try:
        gone = asyncio.create_task(reads.verify())
        stays = asyncio.create_task(reads.verify())
        await eventually(lambda: reads.verifying, timeout=120)
        gone.cancel()
        gate.set()
        assert (await stays).ok
    finally:
        gate.set()
        await api.close()


async def test_pages_are_bounded_and_never_hold_up_a_command(
        api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    release = threading.Event()
    real = _reads.entries_after

    def stuck(path: Path, since: int, limit: int, max_bytes: int) -> list[bytes]:
        release.wait(120)
        return real(path, since, limit, max_bytes)

    monkeypatch.setattr(_reads, "entries_after", stuck)
    backlog = 8  # ApiSettings.audit_read_backlog
    try:
        pages = [asyncio.create_task(api.call("GET", "/api/audit", "lessee"))
                 for _ in range(backlog + 1)]
        await eventually(lambda: _reads_of(api).pages_in_flight == backlog + 1, timeout=120)
        # One page being read (stuck), eight waiting: the next is refused, not queued.
        status, body = await api.call("GET", "/api/audit", "lessee")
        assert (status, body["error_code"], body["reason"]) == (429, "RATE_LIMITED",
                                                                "reads_busy")
        # The reader is stuck, yet commands (whose audit writes use the default executor)
        # are decided: reads have their own thread.
        for _ in range(8):
            assert (await api.command("planner", {"action": "move"}))[0] == 200
        assert (await api.command("viewer", {"action": "estop"}))[0] == 200
        assert not any(p.done() for p in pages)
    finally:
        release.set()
    results = await asyncio.gather(*pages)
    assert {status for status, _ in results} == {200}


async def test_closing_stops_a_verification_in_progress(tmp_path: Path) -> None:
    """A verification still running when the app closes must not hold the process's exit:
    Python joins a process pool's running task at exit (seen: a bridge that took over 30 s to
    exit after SIGINT while a 130k-entry verify ran at low priority)."""
    api = Api(tmp_path)
    await api.build()
    reads = _reads_of(api)
    try:
        pool = reads._verifier()
        if not isinstance(pool, concurrent.futures.ProcessPoolExecutor):
            pytest.skip("no process pool on this machine: verification runs in a thread")
        running = pool.submit(time.sleep, 600)  # stands in for a long verification
        await eventually(lambda: bool(getattr(pool, "_processes", {})), timeout=60)
        workers = list(pool._processes.values())
        await reads.close()
        for worker in workers:
            await asyncio.to_thread(worker.join, 30)
            # Polled, not read once: the pool's own thread reaps the same worker, and a poll
            # that loses that race reads "still running" although it is gone.
            await eventually(lambda w=worker: not w.is_alive(), timeout=30,
                             what=lambda w=worker: f"{w} still alive after close")
        with pytest.raises(Exception):  # noqa: B017 (BrokenProcessPool or CancelledError)
            await asyncio.wait_for(asyncio.wrap_future(running), 30)
    finally:
        await api.close()


_VERIFY_WITH_SIGNALS_BLOCKED = """
import asyncio, json, multiprocessing, re, signal, sys
from pathlib import Path
from rcan_rtps.api._reads import AuditReads
from rcan_rtps.governance import AuditLog


def masks(pid: str) -> list[dict[str, int]]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        status = (task / "status").read_text()
        found.append({key: int(re.search(rf"^{key}:\\s*([0-9a-f]+)", status, re.M)[1], 16)
                      for key in ("SigBlk", "SigIgn")})
    return found


async def main(tmp: Path) -> None:
    log = await AuditLog.open(tmp / "audit.jsonl", tmp / "audit.key")
    reads = AuditReads(log.path, log.public_key)
    try:
        for _ in range(2):  # the first starts the worker (and the resource tracker)
            assert (await reads.verify()).ok
        workers = [str(p.pid) for p in multiprocessing.active_children()]
        print(json.dumps({"bridge": masks("self"), "workers": [masks(w) for w in workers]}))
    finally:
        await reads.close()
        await log.close()


signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})  # as `run` does
asyncio.run(main(Path(sys.argv[1])))
"""


def test_verifying_leaves_sigint_and_sigterm_blocked(tmp_path: Path) -> None:
    """Issue 23: the verifier's process pool (multiprocessing's resource tracker) unblocked
    SIGINT and SIGTERM in the thread that started it, the event loop's: SIGTERM then killed
    `rcan-rtps run` on the spot. Run in a fresh interpreter: the tracker starts once per
    process. The worker takes SIGTERM (close() ends it so) and ignores SIGINT."""
    done = subprocess.run([sys.executable, "-c", _VERIFY_WITH_SIGNALS_BLOCKED, str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    both = (1 << (signal.SIGINT - 1)) | (1 << (signal.SIGTERM - 1))
    assert [m["SigBlk"] & both for m in found["bridge"]] == [both] * len(found["bridge"])
    assert len(found["workers"]) == 1, found
    worker = found["workers"][0][0]  # its main thread
    term, intr = 1 << (signal.SIGTERM - 1), 1 << (signal.SIGINT - 1)
    assert not worker["SigBlk"] & term and not worker["SigIgn"] & term, worker
    assert worker["SigIgn"] & intr, worker
