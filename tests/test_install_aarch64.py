"""scripts/install-aarch64.sh says what is missing, by name and package, before building.

Offline and quick: each case stops at step 1. The whole install runs under emulation in
tests/aarch64/test_emulated_install.py.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "install-aarch64.sh"

pytestmark = pytest.mark.offline

# what the script itself uses besides the tools it checks for
BASE_TOOLS = ("bash", "sed", "grep", "sort", "tr", "cut", "uname", "id", "dirname", "cat",
              "env", "printf", "head", "sha256sum", "tar", "mktemp", "od", "pwd")


def _bin(tmp_path: Path, **scripts: str) -> Path:
    """A PATH directory with the base tools, this interpreter as python3, and fake tools."""
    path = tmp_path / "bin"
    path.mkdir()
    for tool in BASE_TOOLS:
        found = shutil.which(tool)
        if found:
            (path / tool).symlink_to(found)
    (path / "python3").symlink_to(sys.executable)
    for name, body in scripts.items():
        (path / name).write_text(f"#!/bin/sh\n{body}\n")
        (path / name).chmod(0o755)
    return path


def _install(path: Path, tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {"PATH": str(path), "HOME": str(tmp_path)}
    return subprocess.run(["bash", str(SCRIPT), "--prefix", str(tmp_path / "c"),
                           "--venv", str(tmp_path / "venv"), *args],
                          env=env, capture_output=True, text=True, timeout=60)


def test_each_missing_build_tool_is_named_with_its_package(tmp_path: Path) -> None:
    done = _install(_bin(tmp_path), tmp_path)
    assert done.returncode == 1
    assert "missing prerequisites:" in done.stderr
    for line in ("  - cmake: no cmake (3.16 or newer)", "  - make: no make",
                 "  - gcc: no C compiler (cc)", "  - g++: no C++ compiler (c++)"):
        assert line in done.stderr, done.stderr
    assert "apt-get install build-essential cmake" in done.stderr
    assert "== 2/5" not in done.stdout  # nothing was built


def test_an_old_cmake_and_missing_openssl_headers_are_named(tmp_path: Path) -> None:
    path = _bin(tmp_path, cmake='echo "cmake version 3.10.2"', make="exit 0",
                cc="exit 1",  # a compiler that finds no openssl/ssl.h
                **{"c++": "exit 0"})
    done = _install(path, tmp_path)
    assert done.returncode == 1
    assert "  - cmake: cmake 3.10 is older than the 3.16 Cyclone DDS needs" in done.stderr
    assert "  - libssl-dev: no OpenSSL headers (openssl/ssl.h)" in done.stderr
    assert "  - make:" not in done.stderr and "  - g++:" not in done.stderr
    apt = next(line for line in done.stderr.splitlines() if "apt-get install" in line)
    assert {"cmake", "libssl-dev"} <= set(apt.split()) and "build-essential" not in apt


def test_a_cross_build_names_what_the_host_and_the_root_lack(tmp_path: Path) -> None:
    root = tmp_path / "arm64-root"
    (root / "bin").mkdir(parents=True)
    (root / "bin" / "sh").write_text("")
    (root / "bin" / "sh").chmod(0o755)
    done = _install(_bin(tmp_path), tmp_path, "--sysroot", str(root))
    assert done.returncode == 1
    for line in ("  - gcc-aarch64-linux-gnu: no aarch64 cross compiler",
                 "  - g++-aarch64-linux-gnu:",
                 f"  - libssl-dev: no OpenSSL headers in {root}",
                 f"  - libc6-dev: no C library to link against in {root}"):
        assert line in done.stderr, done.stderr
    assert f"go into the arm64 root {root}" in done.stderr


def test_a_sysroot_that_is_no_root_file_system_is_refused(tmp_path: Path) -> None:
    done = _install(_bin(tmp_path), tmp_path, "--sysroot", str(tmp_path))
    assert done.returncode == 1
    assert f"--sysroot {tmp_path} is not a root file system" in done.stderr
