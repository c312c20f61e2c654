"""docs/compatibility.md points every cell at a test: each named test must exist."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.offline

ROOT = Path(__file__).resolve().parents[1]
DOC = (ROOT / "docs" / "compatibility.md").read_text(encoding="utf-8")
# `dir/test_x.py::test_name[variant]` or `::test_name` continuing the previous file
REFERENCE = re.compile(r"`(?:((?:interop|ros)/test_\w+\.py))?(?:::(\w+|\*)(?:\[\w+\])?)?`")


def _references() -> list[tuple[str, str]]:
    found, current = [], None
    for match in REFERENCE.finditer(DOC):
        path, name = match.groups()
        if path:
            current = path
        if current and (path or name):
            found.append((current, name or "*"))
    return found


def test_the_matrix_names_tests_that_exist() -> None:
    references = _references()
    assert len(references) > 25
    missing = []
    for path, name in references:
        source = ROOT / "tests" / path
        if not source.exists():
            missing.append(path)
        elif name != "*" and not re.search(rf"def {name}\(", source.read_text()):
            missing.append(f"{path}::{name}")
    assert missing == []
