"""A slow, obviously-correct CDR (XCDR1, little endian) encoder used only by tests.

Besides the bytes it returns a mask of which bytes are alignment padding: rclpy's Fast
CDR leaves padding bytes uninitialised, so byte comparisons with it must skip them.
"""

from __future__ import annotations

import struct
from typing import Any

from rcan_rtps.ros.typesys.model import Collection, FieldType, Primitive
from rcan_rtps.ros.typesys.store import TypeStore

_FORMATS = {
    Primitive.BOOLEAN: "?", Primitive.OCTET: "B", Primitive.CHAR: "B", Primitive.INT8: "b",
    Primitive.UINT8: "B", Primitive.INT16: "h", Primitive.UINT16: "H", Primitive.INT32: "i",
    Primitive.UINT32: "I", Primitive.INT64: "q", Primitive.UINT64: "Q", Primitive.FLOAT: "f",
    Primitive.DOUBLE: "d",
}


class _Writer:
    def __init__(self) -> None:
        self.data = bytearray()
        self.padding = bytearray()  # 1 where the byte is alignment padding

    def align(self, n: int) -> None:
        while len(self.data) % n:
            self.data.append(0)
            self.padding.append(1)

    def put(self, fmt: str, value: Any) -> None:
        size = struct.calcsize(fmt)
        self.align(size)
        self.raw(struct.pack("<" + fmt, value))

    def raw(self, chunk: bytes) -> None:
        self.data += chunk
        self.padding += bytes(len(chunk))


def encode(store: TypeStore, type_name: str, value: dict[str, Any]) -> tuple[bytes, bytes]:
    """Payload bytes (no encapsulation header) and their padding mask."""
    w = _Writer()
    _struct(store, w, type_name, value)
    return bytes(w.data), bytes(w.padding)


def _struct(store: TypeStore, w: _Writer, type_name: str, value: dict[str, Any]) -> None:
    for f in store.message(type_name).fields:
        _field(store, w, f.type, value.get(f.name, 0))  # 0: the empty-struct placeholder


def _field(store: TypeStore, w: _Writer, ftype: FieldType, value: Any) -> None:
    if ftype.collection is Collection.SINGLE:
        _element(store, w, ftype, value)
        return
    if ftype.collection is not Collection.ARRAY:
        w.put("I", len(value))
    for item in value:
        _element(store, w, ftype.element, item)


def _element(store: TypeStore, w: _Writer, ftype: FieldType, value: Any) -> None:
    if ftype.nested is not None:
        _struct(store, w, ftype.nested, value)
    elif ftype.primitive is Primitive.STRING:
        encoded = value.encode("utf-8") + b"\0"
        w.put("I", len(encoded))
        w.raw(encoded)
    elif ftype.primitive is Primitive.WSTRING:
        # rmw_fastrtps: UTF-16 code units, counted, each a 4-byte wchar_t; no terminator
        units = value.encode("utf-16-le")
        w.put("I", len(units) // 2)
        for (unit,) in struct.iter_unpack("<H", units):
            w.put("I", unit)
    else:
        assert ftype.primitive is not None
        w.put(_FORMATS[ftype.primitive], value)


def equal_ignoring_padding(a: bytes, b: bytes, padding: bytes) -> bool:
    if not len(a) == len(b) == len(padding):
        return False
    return all(x == y or pad for x, y, pad in zip(a, b, padding, strict=False))
