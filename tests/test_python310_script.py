"""scripts/python310.sh: which Python 3.10 the test command's 3.10 stage uses, and what it does
when there is none (a skip, but a failure under CI=true)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "python310.sh"
NO_PYTHON310 = 3


def _script(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """The script with a bare environment: no PYTHON310, PYENV_ROOT or CI unless given."""
    return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True,
                          timeout=120, env={"PATH": "/usr/bin:/bin", **env})


@pytest.fixture(scope="module")
def python310() -> str:
    """A real 3.10 interpreter, found as the stage finds it."""
    found = subprocess.run(["bash", str(SCRIPT), "find"], capture_output=True, text=True,
                           timeout=120)
    if found.returncode != 0:
        pytest.skip(f"no Python 3.10 here: {found.stderr.strip()}")
    return found.stdout.strip()


def _fake_pyenv(root: Path, versions: dict[str, str]) -> Path:
    """A pyenv folder whose versions/V/bin/python3.10 are the given programs."""
    for version, target in versions.items():
        bin_dir = root / "versions" / version / "bin"
        bin_dir.mkdir(parents=True)
        (bin_dir / "python3.10").symlink_to(target)
    return root


def test_without_an_interpreter_it_says_where_it_looked_and_skips(tmp_path: Path) -> None:
    done = _script("test", HOME=str(tmp_path))
    assert done.returncode == NO_PYTHON310, done.stdout + done.stderr
    assert f"python3.10 on PATH or {tmp_path}/.pyenv/versions/3.10.*" in done.stderr
    assert "SKIPPED: the Python 3.10 tests do not run here" in done.stdout


@pytest.mark.parametrize("command", ["prepare", "test"])
def test_without_an_interpreter_ci_fails(tmp_path: Path, command: str) -> None:
    wheel = tmp_path / "rcan_rtps-0-py3-none-any.whl"
    wheel.write_bytes(b"")
    args = [command, str(wheel)] if command == "prepare" else [command]
    done = _script(*args, HOME=str(tmp_path), CI="true")
    assert done.returncode == 1, done.stdout + done.stderr
    assert "under CI=true the Python 3.10 tests must run" in done.stderr


def test_a_named_interpreter_that_is_not_3_10_is_refused_not_passed_over(
        tmp_path: Path, python310: str) -> None:
    # a 3.10 is there to fall back on (pyenv's folder): PYTHON310 still wins, and fails
    pyenv = _fake_pyenv(tmp_path / "pyenv", {"3.10.13": python310})
    done = _script("find", PYTHON310="/bin/sh", PYENV_ROOT=str(pyenv))
    assert done.returncode == NO_PYTHON310
    assert "PYTHON310=/bin/sh is not a Python 3.10 with venv" in done.stderr


def test_pyenvs_newest_3_10_is_taken_past_a_shim_that_does_not_run(
        tmp_path: Path, python310: str) -> None:
    shim = tmp_path / "shims" / "python3.10"  # as pyenv's, when 3.10 is not selected
    shim.parent.mkdir()
    shim.write_text("#!/bin/sh\necho 'pyenv: python3.10: command not found' >&2\nexit 127\n")
    shim.chmod(0o755)
    # 3.10.9 sorts after 3.10.13 as text: the newest is by version, not by name
    pyenv = _fake_pyenv(tmp_path / "pyenv", {"3.10.9": python310, "3.10.13": python310,
                                             "3.10.2": "/bin/false"})
    done = _script("find", PYENV_ROOT=str(pyenv), PATH=f"{shim.parent}:/usr/bin:/bin")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(pyenv / "versions" / "3.10.13" / "bin" / "python3.10")


def test_the_stage_refuses_to_test_the_source_tree() -> None:
    """RCAN_RTPS_TEST_INSTALLED (the stage sets it): pytest stops at once when rcan_rtps would
    come from src/ rather than the interpreter's site-packages."""
    env = {**os.environ, "RCAN_RTPS_TEST_INSTALLED": "1", "PYTHONPATH": str(ROOT / "src")}
    done = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q",
                           "--collect-only", str(ROOT / "tests" / "test_public_api.py")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == pytest.ExitCode.USAGE_ERROR, done.stdout + done.stderr
    assert (f"rcan_rtps comes from {ROOT / 'src' / 'rcan_rtps' / '__init__.py'}, not from "
            f"{sys.executable}'s site-packages") in done.stderr
