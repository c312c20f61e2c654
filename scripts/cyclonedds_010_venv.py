"""Make .cache/cyclonedds-0.10: a venv with PyPI's cyclonedds 0.10.5 and our other
dependencies, where tests/ros/test_cyclone_line.py shows that line refused at import.

Run by scripts/test.sh during set-up (it needs the package index; the tests run without
network). PyPI has 0.10.5 wheels up to CPython 3.10 only, so the venv runs Python 3.10 (the
machines' pyenv has it, or RCAN_RTPS_PYTHON310 names one). Stamped: made once per interpreter
and dependency list. Exit status 1 with the reason on stderr when it cannot be made.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
OLD_LINE = "cyclonedds==0.10.5"
VENV = ROOT / ".cache" / "cyclonedds-0.10"


def python310() -> str | None:
    candidates = [os.environ.get("RCAN_RTPS_PYTHON310", ""), shutil.which("python3.10") or ""]
    pyenv_root = os.environ.get("PYENV_ROOT", str(Path.home() / ".pyenv"))
    candidates += sorted(glob.glob(f"{pyenv_root}/versions/3.10.*/bin/python3.10"), reverse=True)
    candidates.append("/usr/bin/python3.10")
    for candidate in filter(None, candidates):
        done = subprocess.run([candidate, "-c", "import sys, venv; print(sys.version_info[:2])"],
                              capture_output=True, text=True, check=False)
        if done.returncode == 0 and done.stdout.strip() == "(3, 10)":
            return candidate
    return None


def requirements() -> list[str]:
    """0.10.5 and every other dependency of ours, so the CLI gets as far as it would."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return [OLD_LINE, *(d for d in project["dependencies"] if not d.startswith("cyclonedds"))]


def stamp(python: str) -> str:
    return "\n".join([python, *requirements()])


def ready() -> Path | None:
    """The venv's python when it is made for this tree's dependencies, else None."""
    python = python310()
    if python is None or not (VENV / ".stamp").is_file():
        return None
    if (VENV / ".stamp").read_text() != stamp(python):
        return None
    return VENV / "bin" / "python"


def make() -> str | None:
    """Make the venv unless it is ready; the reason it cannot be made, or None."""
    if ready() is not None:
        return None
    python = python310()
    if python is None:
        return ("no Python 3.10 (PyPI's cyclonedds 0.10.5 wheels stop at CPython 3.10); "
                "set RCAN_RTPS_PYTHON310")
    shutil.rmtree(VENV, ignore_errors=True)  # no stamp: made anew (a failed try leaves none)
    made = subprocess.run([python, "-m", "venv", str(VENV)], capture_output=True, text=True,
                          check=False)
    installed = made.returncode == 0 and subprocess.run(
        [str(VENV / "bin" / "pip"), "install", "-q", *requirements()],
        capture_output=True, text=True, timeout=600, check=False)
    if not installed or installed.returncode != 0:
        shutil.rmtree(VENV, ignore_errors=True)
        return (f"could not install {OLD_LINE}: "
                f"{(installed.stderr if installed else made.stderr)[-800:]}")
    (VENV / ".stamp").write_text(stamp(python))
    return None


if __name__ == "__main__":
    problem = make()
    if problem is not None:
        print(problem, file=sys.stderr)
        sys.exit(1)
    print(f"{VENV}: {OLD_LINE} ready")
