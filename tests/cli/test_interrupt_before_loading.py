"""A Ctrl-C while the interpreter loads the command line itself (before `cli.main` could
catch anything) is one line and exit code 130, both through `python -m rcan_rtps` and the
`rcan-rtps` script. The sweep of signals at random moments found it: a Ctrl-C 0.04 s after
the start of `bag play`, on a busy machine, printed a traceback ending in `_logging`'s
imports. Here the interrupt is raised by an import hook, deterministically."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
INTERRUPT_AT = "rcan_rtps.cli._logging"  # imported by cli.main at its top

HOOK = f"""
import importlib.abc, sys

class CtrlC(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == {INTERRUPT_AT!r}:
            raise KeyboardInterrupt
        return None

sys.meta_path.insert(0, CtrlC())
"""


def _script_entry() -> str:
    # pyproject's [project.scripts] line (no tomllib on Python 3.10)
    found = re.search(r'^rcan-rtps = "([\w.]+):(\w+)"$', (ROOT / "pyproject.toml").read_text(),
                      re.M)
    assert found, "pyproject.toml names no rcan-rtps script"
    module, function = found.groups()
    return f"import importlib; sys.exit(importlib.import_module({module!r}).{function}())"


@pytest.mark.parametrize("start", [
    "import runpy; runpy.run_module('rcan_rtps', run_name='__main__', alter_sys=True)",
    _script_entry(),
], ids=["python -m", "script"])
def test_ctrl_c_while_the_cli_loads_is_one_line(start: str) -> None:
    done = subprocess.run([sys.executable, "-c", HOOK + start, "bag", "info", "x"],
                          capture_output=True, text=True, timeout=120)
    assert done.stderr == "rcan-rtps: interrupted\n", done.stderr
    assert done.returncode == 130
