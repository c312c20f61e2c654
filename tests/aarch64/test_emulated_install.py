"""The aarch64 install path, run for real under emulation (issue 28, Deliver 2).

An arm64 Debian bookworm root, whose programs run under qemu-user through binfmt_misc:
scripts/install-aarch64.sh installs scripts/test.sh's wheel there (Cyclone DDS C 11 with
DDS-Security cross-built for the root, the binding built in it), then `rcan-rtps run --sim`
reaches its ready line, answers /api/status and executes a move, loopback only
(scripts/aarch64-emulated.sh).

The root is prepared, with network, by scripts/test.sh before the tests (built cold once, then
kept as an archive outside the clone); this test runs offline from that archive, about half a
minute, with qemu on both cores: with pytest-xdist it belongs to the serial phase.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
HARNESS = ROOT / "scripts" / "aarch64-emulated.sh"
ON_CI_AS_ROOT = os.environ.get("CI") == "true" and sys.platform == "linux" and os.geteuid() == 0

# serial: alone, after the parallel phase (scripts/pytest_phases.sh): qemu takes both cores
pytestmark = [pytest.mark.slow, pytest.mark.serial]

UNAVAILABLE = 3  # the harness's exit status when arm64 programs cannot run here
NOT_PREPARED = 4


def _not_here(reason: str) -> None:
    """Skip, except under CI=true as root, where the emulated check must run."""
    if ON_CI_AS_ROOT:
        pytest.fail(f"the emulated aarch64 check must run under CI=true as root: {reason}")
    pytest.skip(reason)


@pytest.fixture(scope="module")
def wheel() -> Path:
    wheel_dir = Path(os.environ.get("RCAN_RTPS_WHEEL_DIR", ROOT / ".cache" / "dist"))
    wheels = sorted(wheel_dir.glob("rcan_rtps-*.whl"))
    if not wheels:
        _not_here("no wheel built; scripts/test.sh builds it into .cache/dist")
    return wheels[-1]


def _prepare_log() -> str:
    """The end of scripts/test.sh's prepare step, which says why the root is not there."""
    log = Path(os.environ.get("RCAN_RTPS_AARCH64_LOG", ROOT / ".cache" / "aarch64-prepare.log"))
    if not log.is_file():
        return "\n(no prepare log: scripts/test.sh prepares the root before the tests)"
    return f"\n{log}, last lines:\n" + "\n".join(log.read_text().splitlines()[-15:])


def _harness(*args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["bash", str(HARNESS), *args], capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)


def test_the_wheel_installs_and_runs_on_emulated_aarch64(wheel: Path) -> None:
    if sys.platform != "linux" or os.geteuid() != 0:
        _not_here("needs root on Linux (binfmt_misc, chroot)")
    host = _harness("host", timeout=600)
    if host.returncode == UNAVAILABLE:
        _not_here(host.stderr.strip())
    assert host.returncode == 0, host.stdout + host.stderr

    done = _harness("smoke", str(wheel), timeout=1800)
    output = done.stdout + done.stderr
    if done.returncode == NOT_PREPARED:
        _not_here(done.stderr.strip() + _prepare_log())
    failed = [line for line in output.splitlines() if "step failed" in line]
    assert done.returncode == 0, (failed or ["(no step named)"])[0] + "\n" + output[-6000:]
    # each part of it, as the harness and release.sh's tour report them
    assert "install-aarch64.sh done" in output
    assert "== 5/5 rcan-rtps" in output and "rcan-rtps loads /opt/cyclonedds-11.0.1/lib/" in output
    assert "smoke: ready, /api/status answered, a move executed, stopped cleanly" in output
