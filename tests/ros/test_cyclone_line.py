"""The Cyclone DDS lines: 11.x runs the wire layer, 0.10.x is refused at import with a message
saying how to get 11.x (docs/compatibility.md, 'Cyclone DDS lines').

The refusal is shown against the real cyclonedds 0.10.5 from PyPI, in a venv of its own under
.cache/cyclonedds-0.10 that scripts/test.sh makes during set-up (scripts/cyclonedds_010_venv.py:
Python 3.10, as PyPI's 0.10.5 wheels stop there); under CI=true a venv not made fails.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

from rcan_rtps.ros import UnsupportedBindingError, WireError, _binding

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import cyclonedds_010_venv as old_venv

ROOT = Path(__file__).resolve().parents[2]
ON_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
# One phrase per gap the issue found on 0.10.5 (the message names each).
GAPS = ("cyclonedds.idl.types.byte", "DataWriter.get_publication_matched_status()",
        "DataReader.get_requested_incompatible_qos_status()",
        "Entity.get_instance_handle() returning the handle",
        "_clayer.ddspy_take(reader, mask, n)", "DataReader.get_matched_publication_data()",
        "DataWriter.get_matched_subscription_data()")


def test_the_installed_binding_is_the_supported_line() -> None:
    assert _binding.missing_features() == []
    assert _binding.binding_version().startswith("11.")


def test_the_pin_admits_the_11_line_only() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pins = [d for d in project["dependencies"] if d.startswith("cyclonedds")]
    assert pins == ["cyclonedds>=11,<12"]


def _unavailable(why: str) -> None:
    if ON_CI:
        pytest.fail(f"the cyclonedds 0.10.5 venv is needed under CI: {why}")
    pytest.skip(why)


@pytest.fixture(scope="module")
def old_line_python() -> Path:
    """The venv scripts/test.sh makes (scripts/cyclonedds_010_venv.py, with the network the
    tests run without)."""
    python = old_venv.ready()
    if python is None:
        _unavailable(f"{old_venv.VENV} is not made for this tree: run "
                     "`.venv/bin/python scripts/cyclonedds_010_venv.py` (scripts/test.sh does)")
    assert python is not None
    return python


def _run(python: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    env.pop("PYTHONHOME", None)
    return subprocess.run([str(python), *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=120)


PROBE = """
import json
try:
    import rcan_rtps.ros
except Exception as exc:
    print(json.dumps({"classes": [c.__name__ for c in type(exc).__mro__],
                      "name": exc.name, "version": exc.version, "missing": exc.missing,
                      "message": str(exc)}))
else:
    print("null")
"""


def test_cyclonedds_0_10_is_refused_at_import_naming_each_gap(old_line_python: Path) -> None:
    import json

    assert _run(old_line_python, "-c", "import cyclonedds.idl.types as t; "
                "print(hasattr(t, 'byte'))").stdout.strip() == "False"  # it is 0.10's binding
    done = _run(old_line_python, "-c", PROBE)
    assert done.returncode == 0, done.stderr
    refusal = json.loads(done.stdout)
    assert refusal is not None, "the wire layer imported on cyclonedds 0.10.5"
    assert refusal["classes"][:3] == ["UnsupportedBindingError", "WireError", "ImportError"]
    assert (refusal["name"], refusal["version"]) == ("cyclonedds", "0.10.5")
    message = refusal["message"]
    assert message.startswith("the cyclonedds Python binding 0.10.5 (at ")
    for gap in GAPS:
        assert gap in message
    assert len(refusal["missing"]) == 11
    assert "pip install 'cyclonedds>=11,<12'" in message
    assert "CYCLONEDDS_HOME=<its install prefix>" in message and "ldconfig" in message


def test_the_cli_on_cyclonedds_0_10_says_so_in_one_error(old_line_python: Path) -> None:
    done = _run(old_line_python, "-m", "rcan_rtps", "--help")
    assert done.returncode == 1
    assert done.stdout == ""
    assert done.stderr.startswith("rcan-rtps: error: the cyclonedds Python binding 0.10.5")
    assert "Traceback" not in done.stderr
    assert "pip install 'cyclonedds>=11,<12'" in done.stderr


def test_the_refusal_is_a_wire_error_and_an_import_error() -> None:
    error = UnsupportedBindingError("0.10.5", "/somewhere", ["x()"])
    assert isinstance(error, WireError) and isinstance(error, ImportError)
    assert error.name == "cyclonedds"
    assert "  - x()" in str(error).splitlines()

