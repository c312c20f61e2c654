"""Hypothesis strategies that generate plain values for any type of a TypeStore."""

from __future__ import annotations

import math
from typing import Any

from hypothesis import strategies as st

from rcan_rtps.ros.typesys.model import INTEGER_RANGES, Collection, FieldType, Primitive
from rcan_rtps.ros.typesys.store import TypeStore

# The message types the issue names for byte-exact and interop checks.
LISTED_TYPES = [
    "geometry_msgs/msg/Twist",
    "geometry_msgs/msg/TwistStamped",
    "sensor_msgs/msg/JointState",
    "nav_msgs/msg/Odometry",
    "diagnostic_msgs/msg/DiagnosticArray",
    "trajectory_msgs/msg/JointTrajectory",
    "sensor_msgs/msg/BatteryState",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/LaserScan",
]

_TEXT = st.text(st.characters(min_codepoint=32, max_codepoint=0x2FF), max_size=12)


def _primitive(ftype: FieldType) -> st.SearchStrategy[Any]:
    prim = ftype.primitive
    assert prim is not None
    if prim is Primitive.BOOLEAN:
        return st.booleans()
    if prim is Primitive.FLOAT:
        return st.floats(width=32, allow_nan=False)
    if prim.is_float:
        return st.floats(allow_nan=False)
    if prim is Primitive.WSTRING:
        # any code point but surrogates: astral ones take two UTF-16 units on the wire
        wide = st.text(st.characters(min_codepoint=32, blacklist_categories=("Cs",)),
                       max_size=6)
        return wide.filter(lambda s: len(s) <= ftype.string_bound) if ftype.string_bound \
            else wide
    if prim.is_string:
        # ROS bounds strings in characters (rclpy's setters), not UTF-8 bytes
        if ftype.string_bound:
            return _TEXT.filter(lambda s: len(s) <= ftype.string_bound)
        return _TEXT
    low, high = INTEGER_RANGES[prim]
    return st.integers(low, high)


def values_for(store: TypeStore, type_name: str, max_items: int = 4) -> st.SearchStrategy[Any]:
    msg = store.message(type_name)
    fields = {
        # rclpy hides the empty-struct placeholder and always sends 0
        f.name: st.just(0) if f.name == "structure_needs_at_least_one_member"
        else _field(store, f.type, max_items)
        for f in msg.fields
    }
    return st.fixed_dictionaries(fields)


def _field(store: TypeStore, ftype: FieldType, max_items: int) -> st.SearchStrategy[Any]:
    element = (values_for(store, ftype.nested, max_items) if ftype.nested is not None
               else _primitive(ftype.element))
    if ftype.collection is Collection.ARRAY:
        return st.lists(element, min_size=ftype.size, max_size=ftype.size)
    if ftype.collection is Collection.BOUNDED_SEQUENCE:
        return st.lists(element, max_size=min(ftype.size, max_items))
    if ftype.collection is Collection.SEQUENCE:
        return st.lists(element, max_size=max_items)
    return element


UNBOUNDED_EXTREME_ITEMS = 8  # an unbounded sequence or string at "max" has this many items
_FLOAT32_MAX = 3.4028234663852886e38
_DOUBLE_MAX = 1.7976931348623157e308


def extreme_values(store: TypeStore, type_name: str, end: str) -> dict[str, Any]:
    """Every field at one end of its range: `max` (largest numbers, strings and sequences at
    their bounds, non-ASCII text, astral characters where unbounded) or `min` (smallest
    numbers, -inf, empty strings and sequences)."""
    assert end in ("max", "min")
    msg = store.message(type_name)
    return {f.name: 0 if f.name == "structure_needs_at_least_one_member"
            else _extreme_field(store, f.type, end) for f in msg.fields}


def _extreme_field(store: TypeStore, ftype: FieldType, end: str) -> Any:
    def element() -> Any:
        if ftype.nested is not None:
            return extreme_values(store, ftype.nested, end)
        return _extreme_primitive(ftype.element, end)

    if ftype.collection is Collection.ARRAY:
        return [element() for _ in range(ftype.size)]
    if ftype.collection is Collection.BOUNDED_SEQUENCE:
        return [element() for _ in range(ftype.size if end == "max" else 0)]
    if ftype.collection is Collection.SEQUENCE:
        return [element() for _ in range(UNBOUNDED_EXTREME_ITEMS if end == "max" else 0)]
    return element()


def _extreme_primitive(ftype: FieldType, end: str) -> Any:
    prim = ftype.primitive
    assert prim is not None
    top = end == "max"
    if prim is Primitive.BOOLEAN:
        return top
    if prim is Primitive.FLOAT:
        return _FLOAT32_MAX if top else -math.inf
    if prim.is_float:
        return _DOUBLE_MAX if top else -math.inf
    if prim.is_string:
        if not top:
            return ""
        if ftype.string_bound:  # bounds count characters
            return "é" * ftype.string_bound
        return "Grüße 😀 " * UNBOUNDED_EXTREME_ITEMS
    low, high = INTEGER_RANGES[prim]
    return high if top else low
