"""`topic echo --json` writes strict JSON, non-finite floats included."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from rcan_rtps.cli._echo import to_json

pytestmark = pytest.mark.offline


def strict_loads(text: str) -> Any:
    def refuse(constant: str) -> Any:
        raise ValueError(f"not JSON: {constant}")
    return json.loads(text, parse_constant=refuse)


def test_non_finite_floats_are_named_strings() -> None:
    plain = {"x": math.nan, "pose": {"y": math.inf, "z": -math.inf},
             "ranges": [1.5, math.inf, math.nan], "ok": 2.0}
    assert strict_loads(to_json(plain)) == {
        "x": "NaN", "pose": {"y": "Infinity", "z": "-Infinity"},
        "ranges": [1.5, "Infinity", "NaN"], "ok": 2.0}


def test_a_lone_field_and_plain_messages_stay_as_they_were() -> None:
    assert strict_loads(to_json(math.nan)) == "NaN"
    assert to_json({"data": "ok", "n": 3}) == '{"data": "ok", "n": 3}'


def test_named_strings_read_back_as_floats() -> None:
    back = strict_loads(to_json([math.inf, -math.inf, math.nan]))
    assert [float(v) for v in back[:2]] == [math.inf, -math.inf] and math.isnan(float(back[2]))
