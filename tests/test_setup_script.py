"""The test command's set-up: a failed install fails the command and is never cached as good."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _bash(script: str, cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["bash", "-c", f"set -euo pipefail; . {ROOT}/scripts/setup_lib.sh; "
                           + script], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env={"PATH": "/usr/bin:/bin", "PYTHON": sys.executable, **env})


def test_a_failed_install_fails_and_leaves_no_stamp(tmp_path: Path) -> None:
    done = _bash("ensure_venv venv stamp-1 --no-index no-such-package-rcan-rtps-xyz", tmp_path)
    assert done.returncode != 0
    assert "pip install into venv failed" in done.stderr
    assert not (tmp_path / "venv").exists()  # nothing half-made is left to be trusted later


def test_inside_a_condition_the_failure_still_counts(tmp_path: Path) -> None:
    # `set -e` does not apply inside `if`: the function must return the failure itself.
    done = _bash("if ensure_venv venv s --no-index no-such-package-rcan-rtps-xyz; "
                 "then echo installed; else echo refused; fi", tmp_path)
    assert done.stdout.strip().splitlines()[-1] == "refused"
    assert not (tmp_path / "venv").exists()


def test_a_good_install_is_stamped_and_reused(tmp_path: Path) -> None:
    # No packages to fetch (pip is asked only to check itself), so no network is needed.
    assert _bash("ensure_venv venv s1 --no-index pip", tmp_path).returncode == 0
    assert (tmp_path / "venv" / ".stamp").read_text().strip() == "s1"
    marker = tmp_path / "venv" / "marker"
    marker.write_text("x")
    assert _bash("ensure_venv venv s1 --no-index pip", tmp_path).returncode == 0
    assert marker.exists()  # the stamp matched: not rebuilt


def test_quiet_pip_passes_the_exit_status_through(tmp_path: Path) -> None:
    assert _bash("quiet_pip false", tmp_path).returncode != 0
    assert _bash("quiet_pip true", tmp_path).returncode == 0


def test_copy_source_copies_tracked_files_from_a_checkout(tmp_path: Path) -> None:
    done = _bash(f"copy_source {ROOT} {tmp_path}/copy", tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "copy" / "pyproject.toml").is_file()
    assert not (tmp_path / "copy" / ".venv").exists()
    assert not (tmp_path / "copy" / ".git").exists()


def test_copy_source_works_without_git(tmp_path: Path) -> None:
    # An sdist has no .git: everything but environments and caches is copied.
    src = tmp_path / "sdist"
    (src / "src").mkdir(parents=True)
    (src / "pyproject.toml").write_text("[project]\n")
    (src / "src" / "m.py").write_text("x = 1\n")
    (src / ".venv").mkdir()
    (src / ".venv" / "big").write_text("not copied")
    done = _bash(f"copy_source {src} {tmp_path}/copy", tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "copy" / "src" / "m.py").read_text() == "x = 1\n"
    assert not (tmp_path / "copy" / ".venv").exists()


def test_port_free_refuses_a_port_in_use(tmp_path: Path) -> None:
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        done = _bash(f"port_free {port}", tmp_path)
    assert done.returncode == 1 and f"port {port} is already in use" in done.stderr


# -- the Cyclone oracle build (scripts/cyclone_oracle.sh), with a stand-in recipe ---------------
FAKE_BUILD = """set -e
echo built >> "$(dirname "$0")/runs"
[ -z "${FAIL_BUILD:-}" ] || { echo "no compiler here" >&2; exit 3; }
mkdir -p "$1/bin" && ln -sf "$(command -v true)" "$1/bin/python"
"""


def _recipe(tmp_path: Path) -> Path:
    recipe = tmp_path / "recipe"
    recipe.mkdir()
    (recipe / "build_rmw_cyclonedds.sh").write_text(FAKE_BUILD)
    (recipe / "rmw_cyclonedds-src.tar.gz").write_bytes(b"sources")
    return recipe


def _cyclone(script: str, cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    return _bash(f". {ROOT}/scripts/cyclone_oracle.sh; " + script, cwd, **env)


ENSURE = ("ensure_cyclone_oracle prefix recipe; "
          "echo \"oracle=${RCAN_RTPS_ORACLE_JAZZY_CYCLONE:-}\"; "
          "echo \"error=${RCAN_RTPS_ORACLE_JAZZY_CYCLONE_ERROR:-}\"")


def test_cyclone_oracle_is_built_once_and_reused_while_the_recipe_is_unchanged(
        tmp_path: Path) -> None:
    recipe = _recipe(tmp_path)
    first = _cyclone(ENSURE, tmp_path)
    assert first.returncode == 0, first.stderr
    assert f"oracle={tmp_path}/prefix/bin/python" in first.stdout.splitlines()
    assert _cyclone(ENSURE, tmp_path).returncode == 0
    assert (recipe / "runs").read_text() == "built\n"  # the stamp matched: no second build
    (recipe / "build_rmw_cyclonedds.sh").write_text(FAKE_BUILD + "# changed\n")
    assert _cyclone(ENSURE, tmp_path).returncode == 0
    assert (recipe / "runs").read_text() == "built\nbuilt\n"


def test_a_failed_cyclone_build_is_reported_not_fatal_and_not_stamped(tmp_path: Path) -> None:
    _recipe(tmp_path)
    done = _cyclone(ENSURE, tmp_path, FAIL_BUILD="1")
    assert done.returncode == 0  # the Cyclone tests report it (skip, or fail under CI=true)
    assert "oracle=" in done.stdout.splitlines()
    assert "error=its build failed (log: prefix.log)" in done.stdout.splitlines()
    assert "no compiler here" in done.stderr
    assert not (tmp_path / "prefix").exists()


def test_a_given_cyclone_prefix_is_used_as_it_is(tmp_path: Path) -> None:
    recipe = _recipe(tmp_path)
    done = _cyclone(ENSURE, tmp_path, RCAN_RTPS_ORACLE_JAZZY_CYCLONE="/opt/ros/bin/python")
    assert "oracle=/opt/ros/bin/python" in done.stdout.splitlines()
    assert not (recipe / "runs").exists()
