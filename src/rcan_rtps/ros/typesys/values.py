"""Plain values (dicts from YAML/JSON) ⇄ typed messages, validated with field paths.

`build` is strict so that nothing malformed reaches the wire: unknown fields, wrong
types, integers out of range, oversize strings, arrays and sequences all raise
`ValueFitError` naming the path (`pose.pose.position.x`, `name[3]`). Floats may be
non-finite here because ROS allows them; the governance layer decides what it accepts.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Mapping, Sequence
from typing import Any

from cyclonedds.idl import IdlStruct

from ..errors import ValueFitError
from .ddstypes import DdsTypes, is_byte_like
from .model import INTEGER_RANGES, Collection, Field, FieldType, MessageType, Primitive

_FLOAT32_MAX = 3.4028234663852886e38
PLACEHOLDER = "structure_needs_at_least_one_member"  # rosidl's member of empty structs; hidden


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


class MessageValues:
    """Builds and reads messages of one `DdsTypes` registry."""

    def __init__(self, types: DdsTypes) -> None:
        self.types = types

    # -- plain → message ------------------------------------------------------
    def build(self, type_name: str, data: object = None, *, path: str = "") -> IdlStruct:
        """A message of `type_name` from a mapping; missing fields take their defaults."""
        msg = self.types.store.message(type_name)
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise ValueFitError(path, f"expected a mapping for {msg.name}, got {_kind(data)}")
        unknown = [k for k in data if not isinstance(k, str) or not _has_field(msg, k)]
        if unknown:
            names = ", ".join(f.name for f in msg.fields)
            raise ValueFitError(_join(path, str(unknown[0])),
                                f"{msg.name} has no such field (fields: {names})")
        kwargs = {
            f.name: self._field(f, data[f.name], _join(path, f.name)) if f.name in data
            else self._default(f)
            for f in msg.fields
        }
        return self.types.struct(msg.name)(**kwargs)

    def _field(self, field: Field, value: object, path: str) -> object:
        ftype = field.type
        if not ftype.is_collection:
            return self._element(ftype, value, path)
        if is_byte_like(ftype):
            return self._bytes(ftype, value, path)
        if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, Sequence):
            raise ValueFitError(
                path, f"expected a list ({ftype.ros_spelling()}), got {_kind(value)}")
        _check_length(ftype, len(value), path)
        element = ftype.element
        return [self._element(element, v, f"{path}[{i}]") for i, v in enumerate(value)]

    def _element(self, ftype: FieldType, value: object, path: str) -> object:
        if ftype.nested is not None:
            return self.build(ftype.nested, value, path=path)
        assert ftype.primitive is not None
        return _primitive(ftype, value, path)

    def _bytes(self, ftype: FieldType, value: object, path: str) -> bytes:
        if isinstance(value, (bytes, bytearray, memoryview)):
            data = bytes(value)
        elif isinstance(value, Sequence) and not isinstance(value, str):
            for i, v in enumerate(value):
                if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 255:
                    raise ValueFitError(f"{path}[{i}]", f"expected a byte 0..255, got {v!r}")
            data = bytes(value)
        else:
            raise ValueFitError(path, f"expected bytes or a list of bytes, got {_kind(value)}")
        _check_length(ftype, len(data), path)
        return data

    def _default(self, field: Field) -> object:
        ftype = field.type
        if ftype.element.primitive is Primitive.WSTRING and field.default is not None:
            return _wide_default(field.default)
        if field.default is not None:
            if is_byte_like(ftype):
                return bytes(field.default)  # type: ignore[call-overload]
            return list(field.default) if ftype.is_collection else field.default  # type: ignore[call-overload]
        if ftype.collection is Collection.ARRAY:
            if is_byte_like(ftype):
                return bytes(ftype.size)
            return [self._zero(ftype.element) for _ in range(ftype.size)]
        if ftype.is_collection:
            return b"" if is_byte_like(ftype) else []
        return self._zero(ftype)

    def _zero(self, ftype: FieldType) -> object:
        if ftype.nested is not None:
            return self.build(ftype.nested, {})
        prim = ftype.primitive
        if prim is Primitive.BOOLEAN:
            return False
        if prim is Primitive.WSTRING:
            return []
        if prim is not None and prim.is_string:
            return ""
        if prim is not None and prim.is_float:
            return 0.0
        return 0

    # -- message → plain ------------------------------------------------------
    def to_plain(self, type_name: str, message: IdlStruct, *,
                 no_arr: bool = False) -> dict[str, Any]:
        """A JSON-able dict; byte arrays become lists of ints. `no_arr` puts a placeholder
        naming type and length in place of every array and sequence (ros2's `--no-arr`)."""
        msg = self.types.store.message(type_name)
        return {f.name: self.field_to_plain(f.type, getattr(message, f.name), no_arr=no_arr)
                for f in msg.fields if f.name != PLACEHOLDER}

    def field_to_plain(self, ftype: FieldType, value: Any, *, no_arr: bool = False) -> Any:
        if ftype.is_collection and no_arr:
            return array_placeholder(ftype, len(value))
        if isinstance(value, (bytes, bytearray)):
            return list(value)
        if isinstance(value, memoryview):  # a decoded byte field (no copy was made)
            return list(value.tobytes())
        if isinstance(value, array):  # a decoded numeric sequence
            return value.tolist()
        if ftype.is_collection:
            element = ftype.element
            return [self.field_to_plain(element, v, no_arr=no_arr) for v in value]
        if ftype.nested is not None:
            return self.to_plain(ftype.nested, value, no_arr=no_arr)
        if ftype.primitive is Primitive.WSTRING:
            return wide_to_str(value)
        return value


def array_placeholder(ftype: FieldType, length: int) -> str:
    """What rosidl_runtime_py prints for an array left out: element type, bound, length."""
    element = ftype.nested or (ftype.primitive.value if ftype.primitive else "unknown")
    if ftype.collection is Collection.ARRAY:
        return f"<array type: {element}[{ftype.size}]>"
    if ftype.collection is Collection.BOUNDED_SEQUENCE:
        return f"<sequence type: {element}[{ftype.size}], length: {length}>"
    return f"<sequence type: {element}, length: {length}>"


def str_to_wide(text: str) -> list[int]:
    """A `wstring` as rmw puts it on the wire: its UTF-16 code units."""
    units = text.encode("utf-16-le", "surrogatepass")
    return list(memoryview(units).cast("H"))


def wide_to_str(units: Sequence[int]) -> str:
    """UTF-16 code units back to text; a unit no UTF-16 string holds becomes U+FFFD."""
    chars = "".join(chr(u) if u <= 0xFFFF else "\ufffd" for u in units)
    return chars.encode("utf-16-le", "surrogatepass").decode("utf-16-le", "replace")


def _wide_default(value: object) -> object:
    if isinstance(value, str):
        return str_to_wide(value)
    assert isinstance(value, (list, tuple)), value  # the parser checked it
    return [str_to_wide(str(v)) for v in value]


def _has_field(msg: MessageType, name: str) -> bool:
    return any(f.name == name for f in msg.fields)


def _kind(value: object) -> str:
    return "null" if value is None else type(value).__name__


def _check_length(ftype: FieldType, length: int, path: str) -> None:
    if ftype.collection is Collection.ARRAY and length != ftype.size:
        raise ValueFitError(path, f"expected exactly {ftype.size} items, got {length}")
    if ftype.collection is Collection.BOUNDED_SEQUENCE and length > ftype.size:
        raise ValueFitError(path, f"expected at most {ftype.size} items, got {length}")


def _primitive(ftype: FieldType, value: object, path: str) -> object:
    prim = ftype.primitive
    assert prim is not None
    if prim is Primitive.BOOLEAN:
        if not isinstance(value, bool):
            raise ValueFitError(path, f"expected true or false, got {_kind(value)}")
        return value
    if prim.is_string:
        if not isinstance(value, str):
            raise ValueFitError(path, f"expected a string, got {_kind(value)}")
        # rclpy's generated setters bound string<N> and wstring<N> in characters (len(str)),
        # not in UTF-8 bytes or UTF-16 units; nothing on the wire enforces bytes either.
        if ftype.string_bound and len(value) > ftype.string_bound:
            raise ValueFitError(path, f"string longer than its bound of {ftype.string_bound} "
                                "characters")
        return str_to_wide(value) if prim is Primitive.WSTRING else value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueFitError(path, f"expected a number ({prim.value}), got {_kind(value)}")
    if prim.is_float:
        try:
            number = float(value)
        except OverflowError:
            raise ValueFitError(path, f"{value!r} is out of range for {prim.value}") from None
        if prim is Primitive.FLOAT and math.isfinite(number) and abs(number) > _FLOAT32_MAX:
            raise ValueFitError(path, f"{value!r} is out of range for float32")
        return number
    if isinstance(value, float):
        if not value.is_integer():
            raise ValueFitError(path, f"expected an integer ({prim.value}), got {value!r}")
        value = int(value)
    low, high = INTEGER_RANGES[prim]
    if not low <= value <= high:
        raise ValueFitError(path, f"{value} is out of range for {prim.value} [{low}, {high}]")
    return int(value)
