"""Python source of a CDR encoder per ROS type, generated from the type model.

Two flavours share one emitter: *typed* reads attributes of a message object and trusts their
types; *plain* reads dicts (JSON/YAML values) and checks every value inline, raising `Slow`
at the first doubt. The caller then runs the strict, path-naming validator of values.py:
it either raises the precise `ValueFitError` or builds a typed message (coercing, e.g., an
integral float into an int field), which the typed encoder then writes. So the fast path
never accepts what the validator rejects, and errors read the same as before.

Nested structs are inlined, so a Twist is one `Struct.pack` (header included: a message of
fixed size is that one call); sequences of structs call the element's own function in a loop.
A large block (an image's bytes, a point cloud, a long numeric sequence) is not appended: it
is noted in `big` with its offset, a few placeholder bytes keep the buffer's length at the
right residue mod 8 for the alignment that follows, and `join_big` copies it once, straight
into the result, with the small pieces around it.
"""

from __future__ import annotations

import re
from typing import Any

from ..errors import WireError
from .cdr_layout import (
    ARRAY_CODES,
    FORMATS,
    NATIVE_LITTLE,
    Item,
    by_residue,
    layout,
    pad_table,
    shared_struct,
    size_of,
)
from .cdr_source import FunctionWriter, Source
from .ddstypes import is_byte_like
from .model import Collection, Field, FieldType, MessageType, Primitive
from .store import TypeStore


class Slow(WireError):
    """The plain encoder's signal: leave this value to the strict validator (never escapes)."""


NUMBERS = frozenset({int, float})
FLOAT64_MARK = b"\xcb"  # MessagePack's float 64: the mark, then 8 bytes (see cdr.all_floats)
INTS = frozenset({int})


_WRITES = re.compile(r"(?<![.\w])buf\b")  # generated code touching the buffer (not m.buf)
BIG = 16 * 1024  # bytes of a block that goes into `big` rather than into the bytearray


class EncoderSource(FunctionWriter):
    """Emits `enc_<n>(m, buf, big)` functions that append a struct's CDR body to a bytearray
    (blocks of more than BIG bytes to `big`), and the top function `enc_<n>(m)` that returns
    the message's CDR, encapsulation header included."""

    prefix = "enc_"

    def __init__(self, store: TypeStore, source: Source, *, plain: bool) -> None:
        super().__init__(store, source)
        self.plain = plain
        self._run: list[tuple[Item, str]] = []
        self._known: int | None = None

    def body(self, name: str, msg: MessageType, top: bool) -> None:
        if not top:
            self.src.emit(0, f"def {name}(m, buf, big):")
            self._known = None
            self._struct(msg, "m", 1)
            self._flush(1)
            self.src.emit(1, "return")
            self.src.emit(0, "")
            return
        self.src.emit(0, f"def {name}(m):")
        self.src.emit(1, "buf = bytearray(HEADER); big = []")
        start = len(self.src.lines)
        self._known = 0
        self._struct(msg, "m", 1)
        if not any(_WRITES.search(line) for line in self.src.lines[start:]):  # fixed size
            del self.src.lines[start - 1]
            self._flush(1, result=True)
        else:
            self._flush(1)
            self.src.emit(1, "return join_big(buf, big)")
        self.src.emit(0, "")

    # -- fields ------------------------------------------------------------------------
    def _struct(self, msg: MessageType, ref: str, ind: int) -> None:
        if self.plain:
            names = self.src.const(frozenset(f.name for f in msg.fields), "NAMES")
            self.src.emit(ind, f"if {ref}.__class__ is not dict or not {names}.issuperset({ref}):")
            self.src.emit(ind + 1, "raise Slow")
        for f in msg.fields:
            self._field(f, ref, ind)

    def _value(self, f: Field, ref: str, ind: int) -> str:
        """An expression (typed) or a local holding the field's value (plain)."""
        if not self.plain:
            return f"{ref}.{f.name}"  # names are identifiers: cyclonedds structs need it too
        local = self.src.name("v")
        default = self.src.const(_plain_default(f))
        self.src.emit(ind, f"{local} = {ref}.get({f.name!r}, {default})")
        return local

    def _field(self, f: Field, ref: str, ind: int) -> None:
        ftype = f.type
        value = self._value(f, ref, ind)
        if ftype.collection is Collection.SINGLE:
            self._single(ftype, value, ind)
        elif ftype.collection is Collection.ARRAY and _fixed_element(ftype):
            self._fixed_array(ftype, value, ind)
        else:
            if not self.plain:  # read several times below: one attribute lookup
                local = self.src.name("v")
                self.src.emit(ind, f"{local} = {value}")
                value = local
            self._repeated(ftype, value, ind)

    def _single(self, ftype: FieldType, value: str, ind: int) -> None:
        if ftype.nested is not None:
            self._struct(self.store.message(ftype.nested), value, ind)
            return
        prim = ftype.primitive
        assert prim is not None
        if prim is Primitive.STRING:
            self._string(ftype, value, ind)
        elif prim is Primitive.WSTRING:
            self._flush(ind)
            self.src.emit(ind, f"put_wide(buf, {self._wide(ftype, value)})")
            self._known = None
        else:
            self._check_scalar(prim, value, ind)
            self._run.append((Item(FORMATS[prim], size_of(FORMATS[prim])), value))

    def _check_scalar(self, prim: Primitive, value: str, ind: int) -> None:
        if not self.plain:
            return
        if prim is Primitive.BOOLEAN:
            self.src.emit(ind, f"if {value}.__class__ is not bool: raise Slow")
        elif prim.is_float:
            self.src.emit(ind, f"if {value}.__class__ is not float and {value}.__class__ is "
                               "not int: raise Slow")  # two identity tests beat a set's
        else:
            self.src.emit(ind, f"if {value}.__class__ is not int: raise Slow")

    def _string(self, ftype: FieldType, value: str, ind: int) -> None:
        if self.plain:
            bound = f" or len({value}) > {ftype.string_bound}" if ftype.string_bound else ""
            self.src.emit(ind, f"if {value}.__class__ is not str{bound}: raise Slow")
        encoded = self.src.name("s")
        self.src.emit(ind, f"{encoded} = {value}.encode()")
        self._run.append((Item("I", 4), f"len({encoded}) + 1"))
        self._flush(ind)
        self.src.emit(ind, f"buf += {encoded}")
        self.src.emit(ind, "buf.append(0)")
        self._known = None

    def _wide(self, ftype: FieldType, value: str) -> str:
        return f"plain_wide({value}, {ftype.string_bound})" if self.plain else value

    def _fixed_array(self, ftype: FieldType, value: str, ind: int) -> None:
        """Arrays of fixed-size primitives join the current run."""
        prim = ftype.primitive
        assert prim is not None
        n = ftype.size
        if is_byte_like(ftype):
            octets = f"plain_octets({value})" if self.plain else f"bytes({value})"
            self._run.append((Item(f"{n}s", 1), octets))
            if self.plain:  # `s` pads or truncates silently: the length is checked here
                self.src.emit(ind, f"if len({value}) != {n}: raise Slow")
            return
        if self.plain:
            self.src.emit(ind, f"if {value}.__class__ is not list or "
                               f"not {self._fixed_all_of(prim, value, n)}: raise Slow")
        fmt = FORMATS[prim]
        self._run.append((Item(f"{n}{fmt}", size_of(fmt)), f"*{value}"))

    def _fixed_all_of(self, prim: Primitive, value: str, size: int) -> str:
        """`_all_of` for an array of `size` items: for floats, `all_floats` written out with
        its constants (a list of another length fails the pack that follows)."""
        if not prim.is_float:
            return _all_of(prim, value)
        head = 1 if size < 16 else 3 if size < 65536 else 5
        marks = self.src.const(FLOAT64_MARK * size, "MARKS")
        return (f"(to_msgpack({value})[{head}::9] == {marks} or "
                f"NUMBERS.issuperset(map(type, {value})))")

    def _repeated(self, ftype: FieldType, value: str, ind: int) -> None:
        self._flush(ind)
        count = self.src.name("n")
        if is_byte_like(ftype):  # counted in bytes, whatever the buffer's item format
            octets = self.src.name("o")
            self.src.emit(ind, f"{octets} = {'plain_' if self.plain else ''}octets({value})")
            value = octets
        elif self.plain:
            self.src.emit(ind, f"if {value}.__class__ is not list and {value}.__class__ is "
                               "not ARRAY: raise Slow")
        self.src.emit(ind, f"{count} = len({value})")
        if ftype.collection is Collection.ARRAY:
            self.src.emit(ind, f"if {count} != {ftype.size}: raise Slow" if self.plain else
                          f"if {count} != {ftype.size}: raise length_error({count}, "
                          f"{ftype.size}, True)")
        else:
            if ftype.collection is Collection.BOUNDED_SEQUENCE:
                self.src.emit(ind, f"if {count} > {ftype.size}: raise Slow" if self.plain else
                              f"if {count} > {ftype.size}: raise length_error({count}, "
                              f"{ftype.size}, False)")
            self._run.append((Item("I", 4), count))
            self._flush(ind)
        element = ftype.element
        if element.nested is not None:
            inner = self.function(element.nested)
            item = self.src.name("e")
            self.src.emit(ind, f"for {item} in {value}:")
            self.src.emit(ind + 1, f"{inner}({item}, buf, big)")
        elif is_byte_like(ftype):
            self._append_block(value, count, ind)
        else:
            assert element.primitive is not None
            if element.primitive is Primitive.STRING and not element.string_bound and \
                    ftype.collection is not Collection.ARRAY:  # right after a count
                self.src.emit(ind, f"buf += string_block({value}, {self.plain})")
            else:
                self._repeated_primitive(element, value, count, ind)
        self._known = None

    def _repeated_primitive(self, element: FieldType, value: str, count: str, ind: int) -> None:
        prim = element.primitive
        assert prim is not None
        if prim is Primitive.STRING or prim is Primitive.WSTRING:
            item = self.src.name("e")
            self.src.emit(ind, f"for {item} in {value}:")
            if prim is Primitive.WSTRING:
                self.src.emit(ind + 1, f"put_wide(buf, {self._wide(element, item)})")
                return
            self._known = None
            self._string(element, item, ind + 1)
            return
        fmt = FORMATS[prim]
        align = size_of(fmt)
        self.src.emit(ind, f"if {count}:")
        if align > 1:
            pads = self.src.const(pad_table(align), "PAD")
            self.src.emit(ind + 1, f"buf += {pads}[len(buf) & 7]")
        if prim is Primitive.BOOLEAN:
            if self.plain:
                self.src.emit(ind + 1, f"if not {_all_of(prim, value)}: raise Slow")
            self.src.emit(ind + 1, f"buf += bytes({value})")
            return
        code = ARRAY_CODES[prim]
        if self.plain:
            self.src.emit(ind + 1, f"if {value}.__class__ is ARRAY:")
            self.src.emit(ind + 2, f"if {value}.typecode != {code!r}: raise Slow")
            self.src.emit(ind + 1, f"elif not {_all_of(prim, value)}: raise Slow")
        block = self.src.name("b")
        packed = f"packer({fmt!r}, {count})(*{value})"
        if NATIVE_LITTLE:  # an array of the field's type is its wire bytes already
            self.src.emit(ind + 1, f"{block} = {value} if {value}.__class__ is ARRAY and "
                                   f"{value}.typecode == {code!r} else {packed}")
        else:
            self.src.emit(ind + 1, f"{block} = {packed}")
        self._append_block(block, f"{count} * {align}", ind + 1)

    def _append_block(self, block: str, size: str, ind: int) -> None:
        """Appends a bytes-like block of `size` bytes, or notes it in `big` if large."""
        self.src.emit(ind, f"if {size} > BIG: big.append((len(buf), {block}, {size})); "
                           f"buf += ZEROS[{size} & 7]")
        self.src.emit(ind, f"else: buf += {block}")

    # -- runs ---------------------------------------------------------------------------
    def _flush(self, ind: int, *, result: bool = False) -> None:
        """Writes the pending run; with `result`, returns it as the whole message (the run
        starts the body and nothing follows it)."""
        if result:
            fmt, _ = layout(0, [item for item, _ in self._run])
            packer = self.src.const(shared_struct("<4s" + fmt[1:]).pack, "S")
            args = "".join(f", {arg}" for _, arg in self._run)
            self._run = []
            self.src.emit(ind, f"return {packer}(HEADER{args})")
            return
        if not self._run:
            return
        items = [item for item, _ in self._run]
        args = ", ".join(arg for _, arg in self._run)
        self._run = []
        if self._known is not None:
            fmt, end = layout(self._known, items)
            packer = self.src.const(shared_struct(fmt).pack, "S")  # bound once, not per call
            self.src.emit(ind, f"buf += {packer}({args})")
            self._known = end
            return
        table, after = by_residue(items)
        packers = self.src.const(tuple(s.pack for s in table), "T")
        self.src.emit(ind, f"buf += {packers}[len(buf) & 7]({args})")
        self._known = after


def _all_of(prim: Primitive, value: str) -> str:
    """Source of a check that every item of the list `value` fits `prim` by type (ranges
    are struct's to check). One exact type is the fast case: floats in a float list (checked
    in C, `all_floats`); ints there too, and bools nowhere else, send it to the exact
    (slower) test."""
    if prim.is_float:
        return f"(all_floats({value}) or NUMBERS.issuperset(map(type, {value})))"
    exact = "bool" if prim is Primitive.BOOLEAN else "int"
    return f"list(map(type, {value})).count({exact}) == len({value})"


def _fixed_element(ftype: FieldType) -> bool:
    prim = ftype.primitive
    return ftype.nested is None and prim is not None and not prim.is_string


def _plain_default(f: Field) -> Any:
    """What a missing plain field means: its @default, else zeros (as values.py builds)."""
    ftype = f.type
    if f.default is not None:
        if ftype.element.primitive is Primitive.WSTRING:
            return f.default  # plain values hold text, converted like any other
        if is_byte_like(ftype):
            return bytes(f.default)  # type: ignore[call-overload]
        return list(f.default) if ftype.is_collection else f.default  # type: ignore[call-overload]
    if ftype.collection is Collection.ARRAY:
        if is_byte_like(ftype):
            return bytes(ftype.size)
        return [{} if ftype.nested else _zero(ftype.element)] * ftype.size
    if ftype.is_collection:
        return b"" if is_byte_like(ftype) else []
    if ftype.nested is not None:
        return {}
    return _zero(ftype)


def _zero(ftype: FieldType) -> Any:
    prim = ftype.primitive
    if prim is Primitive.BOOLEAN:
        return False
    if prim is not None and prim.is_string:
        return ""
    if prim is not None and prim.is_float:
        return 0.0
    return 0
