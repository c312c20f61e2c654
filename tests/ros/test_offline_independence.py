"""The oracle-free tests stay oracle-free: no ROS import, no oracle fixture, no subprocess.

Run them exactly as a machine without ROS would (the oracle fixtures then skip, and an
offline test that skipped would fail, see tests/conftest.py):

    RCAN_RTPS_ORACLE_JAZZY=/nonexistent RCAN_RTPS_ORACLE_KILTED=/nonexistent \\
        .venv/bin/python -m pytest -q -m offline tests/ros
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import ORACLE_FIXTURES

pytestmark = pytest.mark.offline

HERE = Path(__file__).resolve().parent
OFFLINE_TESTS = [
    "test_idl_parser.py",
    "test_rihs01_vectors.py",
    "test_cdr_vectors.py",
    "test_cdr_roundtrip.py",
    "test_bundle_packages.py",
    "test_offline_independence.py",
]
HELPERS = ["offline_data.py", "cdr_reference.py", "strategies.py"]
FORBIDDEN_IMPORTS = {"oracle", "rclpy", "rosidl_parser", "subprocess"}


def _tree(name: str) -> ast.Module:
    return ast.parse((HERE / name).read_text(encoding="utf-8"), name)


@pytest.mark.parametrize("name", OFFLINE_TESTS + HELPERS)
def test_imports_nothing_from_ros_or_the_oracle(name: str) -> None:
    imported = set()
    for node in ast.walk(_tree(name)):
        if isinstance(node, ast.Import):
            imported |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            imported.add(node.module.split(".")[0])
    assert not imported & FORBIDDEN_IMPORTS


@pytest.mark.parametrize("name", OFFLINE_TESTS)
def test_marked_offline_and_never_asks_for_the_oracle(name: str) -> None:
    tree = _tree(name)
    marks = [
        node
        for node in tree.body
        if isinstance(node, ast.Assign)
        and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets)
    ]
    assert [ast.unparse(m.value) for m in marks] == ["pytest.mark.offline"]
    names = {n.arg for n in ast.walk(tree) if isinstance(n, ast.arg)}
    names |= {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    assert not names & ORACLE_FIXTURES


def test_collected_offline_items_use_no_oracle_fixture(request: pytest.FixtureRequest) -> None:
    offline = [
        item for item in request.session.items if item.get_closest_marker("offline") is not None
    ]
    assert offline
    for item in offline:
        assert not ORACLE_FIXTURES.intersection(getattr(item, "fixturenames", ())), item.nodeid
