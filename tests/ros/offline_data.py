"""Where the oracle-free test data lives (tests/data/, see its README)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

DATA = Path(__file__).resolve().parents[1] / "data"
TEST_IDL = DATA / "idl"  # test_msgs types written from their field facts, for the vectors


def load(name: str) -> Any:
    return json.loads((DATA / name).read_text(encoding="utf-8"))
