"""CDR (XCDR1) layout facts shared by the generated encoders and decoders.

Offsets are counted from the start of the body, after the 4-byte encapsulation header, and a
primitive is aligned to its own size (8 at most). A code generator that knows the body
offset modulo 8 at some point packs a run of fixed-size fields with one precompiled
`struct.Struct` whose padding is spelled out; where the offset is only known at run time (after
a string or a sequence) it picks one of 8 precompiled variants by the offset's residue.
"""

from __future__ import annotations

import struct
import sys
from array import array

import msgspec

from .model import Primitive

HEADER_SIZE = 4
LITTLE_HEADER = b"\x00\x01\x00\x00"

FORMATS: dict[Primitive, str] = {
    Primitive.BOOLEAN: "?", Primitive.OCTET: "B", Primitive.CHAR: "B",
    Primitive.INT8: "b", Primitive.UINT8: "B", Primitive.INT16: "h", Primitive.UINT16: "H",
    Primitive.INT32: "i", Primitive.UINT32: "I", Primitive.INT64: "q", Primitive.UINT64: "Q",
    Primitive.FLOAT: "f", Primitive.DOUBLE: "d",
}


def _array_code(size: int, signed: bool) -> str:
    for code in ("bhilq" if signed else "BHILQ"):
        if array(code).itemsize == size:
            return code
    raise RuntimeError(f"no array typecode for {size}-byte integers")  # no such CPython


# `array.array` typecodes of the numeric primitives (C sizes are checked, not assumed).
ARRAY_CODES: dict[Primitive, str] = {
    Primitive.INT8: "b", Primitive.UINT8: "B",
    Primitive.INT16: _array_code(2, True), Primitive.UINT16: _array_code(2, False),
    Primitive.INT32: _array_code(4, True), Primitive.UINT32: _array_code(4, False),
    Primitive.INT64: _array_code(8, True), Primitive.UINT64: _array_code(8, False),
    Primitive.FLOAT: "f", Primitive.DOUBLE: "d",
}
NATIVE_LITTLE = sys.byteorder == "little"


def size_of(fmt: str) -> int:
    return struct.calcsize("<" + fmt)


class Item(msgspec.Struct, frozen=True):
    """One fixed-size piece of a run: a struct format (`d`, `36d`, `12s`) and its alignment."""

    fmt: str
    align: int


def layout(start: int, items: list[Item], order: str = "<") -> tuple[str, int]:
    """The struct format of `items` packed from body offset residue `start` (mod 8), padding
    spelled out as `x`, and the residue after them."""
    pos, parts = start, [order]
    for item in items:
        pad = -pos % item.align
        parts.append("x" * pad + item.fmt)
        pos += pad + size_of(item.fmt)
    return "".join(parts), pos % 8


_STRUCTS: dict[str, struct.Struct] = {}


def shared_struct(fmt: str) -> struct.Struct:
    """One Struct per format for every codec: the same runs recur across types and residues
    (a Vector3 in a Twist, an Odometry, an Imu ...), and each Struct keeps its compiled codes."""
    found = _STRUCTS.get(fmt)
    if found is None:
        found = _STRUCTS.setdefault(fmt, struct.Struct(fmt))
    return found


def by_residue(items: list[Item], order: str = "<") -> tuple[tuple[struct.Struct, ...], int | None]:
    """8 Structs indexed by `(HEADER_SIZE + body offset) & 7`, and the residue after the run
    when it does not depend on where the run starts (else None)."""
    structs, ends = [], set()
    for index in range(8):
        fmt, end = layout((index - HEADER_SIZE) % 8, items, order)
        structs.append(shared_struct(fmt))
        ends.add(end)
    return tuple(structs), (ends.pop() if len(ends) == 1 else None)


def pad_table(align: int) -> tuple[bytes, ...]:
    """Zero padding to reach `align`, indexed by `(HEADER_SIZE + body offset) & 7`."""
    return tuple(bytes(-(index - HEADER_SIZE) % align) for index in range(8))
