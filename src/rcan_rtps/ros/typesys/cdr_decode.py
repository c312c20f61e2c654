"""Python source of a CDR decoder per ROS type and byte order, generated from the type model.

*Typed* decoders build the type's `IdlStruct` (numeric sequences and arrays as `array.array`,
byte fields as read-only memoryviews over the sample, no copy); *plain* decoders build the
dicts and lists that `MessageValues.to_plain` gives (JSON-able). Lengths are checked
against the buffer before anything is sliced, so truncated data raises instead of decoding short.
"""

from __future__ import annotations

from array import array

from .cdr_layout import (
    ARRAY_CODES,
    FORMATS,
    HEADER_SIZE,
    NATIVE_LITTLE,
    Item,
    by_residue,
    layout,
    shared_struct,
    size_of,
)
from .cdr_source import FunctionWriter, Source
from .ddstypes import DdsTypes, is_byte_like
from .hashing import referenced_types
from .model import Collection, FieldType, MessageType, Primitive
from .values import PLACEHOLDER

STRING_BLOCKS_KEPT = 8  # per field of a decoder: counts of strings whose last block is kept
STRING_BLOCK_MAX = 4096  # bytes: a longer block of strings is read every time, never kept


class DecoderSource(FunctionWriter):
    """Emits `dec_<n>(b, mv, p)` functions returning `(value, next offset)`; `p` counts from
    the start of the buffer, encapsulation header included. `b` is the sample as bytes (or a
    bytearray: strings are sliced and decoded from it), `mv` the same sample as a memoryview
    where blocks are sliced out of it (`views`), else `b` again.

    Lengths are not checked one by one: a slice past the end is short, and every read of a
    fixed-size field past the end fails, so the top function checks once, at its end, that
    it did not run past the data (unless a fixed-size read came last).

    The top function, `dec_<n>(b, mv=None, p=4)`, is also the entry point: given bytes that
    start like little-endian plain CDR and no `mv`, it makes `mv` itself; anything else goes
    to `slow(b, p)` (which checks the header, casts memoryviews and picks the byte order,
    then calls it again with `mv`). It returns the value alone, and turns the errors of bad
    data (struct.error, ValueError: truncated, over a bound, bad UTF-8) into
    `CdrDecodeError`s; the others return `(value, next offset)`."""

    prefix = "dec_"

    def __init__(self, types: DdsTypes, source: Source, *, plain: bool, order: str,
                 lenient: bool = False) -> None:
        super().__init__(types.store, source)
        self.types = types
        self.plain = plain
        self.order = order
        self.lenient = lenient
        self.swap = (order == "<") != NATIVE_LITTLE
        self._run: list[tuple[Item, str]] = []
        self._known: int | None = None
        self._builds: list[str] = []  # typed structs to build once the run is unpacked
        self.views = False  # whether the code slices blocks out of `mv` (needs a memoryview)
        self._sliced = False  # a slice may have run past the end since the last fixed read
        self._view_line: int | None = None  # where the entry point makes `mv`

    def function(self, type_name: str, *, top: bool = False) -> str:
        name = super().function(type_name, top=top)
        if top and self.views and self._view_line is not None:  # all bodies written now
            self.src.lines[self._view_line] = self._view_line_text("memoryview(b)")
        return name

    @property
    def _utf8(self) -> str:
        """The call that makes text of a string's bytes. Strict first (a bad byte raises, and
        the entry point hands the sample to its `lenient` twin): bytes that are not UTF-8 are
        read as U+FFFD, as rclpy reads them, and the sample is not lost; no string of a good
        sample pays for the error handler's argument parsing."""
        return "decode('utf-8', 'replace')" if self.lenient else "decode()"

    def _has_text(self, msg: MessageType) -> bool:
        """Whether `msg` holds a (UTF-8) string at any depth: its decoder may meet bad
        bytes. Nested types' functions are written after the top one, so this asks the
        type model rather than the code written so far."""
        return any(f.type.element.primitive is Primitive.STRING
                   for m in (msg, *referenced_types(msg, self.store.message)) for f in m.fields)

    @staticmethod
    def _view_line_text(value: str) -> str:
        return f"        mv = {value}"

    def body(self, name: str, msg: MessageType, top: bool) -> None:
        self._sliced = False
        if not top:
            self.src.emit(0, f"def {name}(b, mv, p):")
            self._known = None
            result = self._struct(msg, 1)
            self._flush(1)
            self.src.emit(1, f"return {result}, p")
            self.src.emit(0, "")
            return
        self.src.emit(0, f"def {name}(b, mv=None, p={HEADER_SIZE}):")
        self.src.emit(1, "if mv is None:  # a call from outside")
        self.src.emit(2, "if b.__class__ is not bytes or b[:2] != LITTLE_START: "
                         "return slow(b, p)")
        self._view_line = len(self.src.lines)
        self.src.lines.append(self._view_line_text("b"))  # a memoryview if blocks are sliced
        start_line = len(self.src.lines)
        self.src.emit(1, "try:")
        self._known = 0
        result = self._struct(msg, 2)
        self._flush(2)
        if self._sliced:
            self.src.emit(2, "if p > len(b): raise truncated(p, len(b))")
        self.src.emit(2, f"return {result}")
        type_name = self.src.const(msg.name, "TYPE")
        if not self.lenient and self._has_text(msg):  # `p` moves on: kept for the twin
            self.src.lines.insert(start_line, "    start = p")
            self.src.emit(1, "except UnicodeDecodeError:")
            self.src.emit(2, "return lenient(b, mv, start)")
        self.src.emit(1, "except (STRUCT_ERROR, ValueError) as exc:")
        self.src.emit(2, f"raise undecodable({type_name}, len(b), exc) from exc")
        self.src.emit(0, "")

    # -- fields ------------------------------------------------------------------------
    def _struct(self, msg: MessageType, ind: int) -> str:
        """Emits the reads of `msg`'s fields; returns the expression that builds it."""
        parts = [(f.name, self._field(f.type, ind)) for f in msg.fields]
        if self.plain:
            return "{" + ", ".join(f"{n!r}: {v}" for n, v in parts if n != PLACEHOLDER) + "}"
        # `object.__new__` and attribute stores in line: what the struct's generated
        # `__init__` does, without the call through the class (a third of a Twist's decode)
        cls, obj = self.src.const(self.types.struct(msg.name), "C"), self.src.name("m")
        build = "; ".join([f"{obj} = new({cls})", *(f"{obj}.{n} = {v}" for n, v in parts)])
        if self._run:
            self._builds.append(build)  # its fields are read by the run's unpack
        else:
            self.src.emit(ind, build)
        return obj

    def _field(self, ftype: FieldType, ind: int) -> str:
        if ftype.collection is Collection.SINGLE:
            return self._single(ftype, ind)
        if ftype.collection is Collection.ARRAY:
            return self._elements(ftype, str(ftype.size), ind)
        count = self._read("I", ind)  # read with the fixed fields before it, in one unpack
        self._flush(ind)
        if ftype.collection is Collection.BOUNDED_SEQUENCE:
            self.src.emit(ind, f"if {count} > {ftype.size}: raise over_bound({count}, "
                               f"{ftype.size})")
        value = self._elements(ftype, count, ind, after_count=True)
        self._known = None
        return value

    def _single(self, ftype: FieldType, ind: int) -> str:
        if ftype.nested is not None:
            return self._struct(self.types.store.message(ftype.nested), ind)
        prim = ftype.primitive
        assert prim is not None
        if prim is Primitive.STRING:
            return self._string(ind)
        if prim is Primitive.WSTRING:
            self._flush(ind)
            value = self.src.name("w")
            self.src.emit(ind, f"{value}, p = get_wide(mv, p, {self.order!r})")
            self._known = None
            return f"wide_to_str({value})" if self.plain else value
        return self._read(FORMATS[prim], ind)

    def _read(self, fmt: str, ind: int, align: int = 0) -> str:
        local = self.src.name("v")
        self._run.append((Item(fmt, align or size_of(fmt)), local))
        return local

    def _string(self, ind: int) -> str:
        count = self._read("I", ind)
        self._flush(ind)
        value, end = self.src.name("s"), self.src.name("q")
        self.src.emit(ind, f"{end} = p + {count}")
        # a length of 0 (no NUL: not what rmw writes) slices to b'' as well; bytes that are
        # not UTF-8 read as U+FFFD, as rclpy reads them (the sample is not lost)
        self.src.emit(ind, f"{value} = b[p:{end} - 1].{self._utf8}")
        self._sliced = True
        self.src.emit(ind, f"p = {end}")
        self._known = None
        return value

    def _elements(self, ftype: FieldType, count: str, ind: int, *,
                  after_count: bool = False) -> str:
        """`count` elements; a fixed array keeps the known residue where it can. Right
        after a sequence's count, p is a multiple of 4 in the body: no padding below 8."""
        element = ftype.element
        if element.nested is not None:
            self._flush(ind)
            inner = self.function(element.nested)
            value, item = self.src.name("l"), self.src.name("o")
            self.src.emit(ind, f"{value} = []")
            self.src.emit(ind, f"for _ in range({count}):")
            self.src.emit(ind + 1, f"{item}, p = {inner}(b, mv, p)")
            self.src.emit(ind + 1, f"{value}.append({item})")
            self._known = None
            self._sliced = True  # the element's function may end with a slice
            return value
        prim = element.primitive
        assert prim is not None
        if prim.is_string:
            return self._strings(element, count, ind)
        if ftype.collection is Collection.ARRAY and is_byte_like(ftype):
            octets = self._read(f"{ftype.size}s", ind, align=1)
            return f"list({octets})" if self.plain else octets
        return self._block(prim, is_byte_like(ftype), count, ind, after_count)

    def _strings(self, element: FieldType, count: str, ind: int) -> str:
        self._flush(ind)
        value = self.src.name("l")
        if element.primitive is Primitive.STRING:
            self._string_block(value, count, ind)
            self._known = None
            self._sliced = True
            return value
        self.src.emit(ind, f"{value} = []")
        self.src.emit(ind, f"for _ in range({count}):")
        self._known = None
        item = self._single(element, ind + 1)
        self._flush(ind + 1)
        self.src.emit(ind + 1, f"{value}.append({item})")
        self._known = None
        return value

    def _string_block(self, value: str, count: str, ind: int) -> None:
        """A sequence of strings, found among the last blocks this field held (one per
        count) when its bytes are the same: a robot's joint names are in every JointState,
        and reading 12 of them one by one was over half of its decode (2.5 µs of 4.2,
        measured). The block starts right after its 4-aligned count, so its strings depend
        on its bytes alone; the list is new each time (the strings, immutable, are shared).
        A miss reads the strings one by one and keeps the block unless it ran past the data
        or is long: by count, so two publishers' lists (an arm's, a gripper's) both stay."""
        kept, entry, start = self.src.const({}, "N"), self.src.name("k"), self.src.name("s")
        self.src.emit(ind, f"{entry} = {kept}.get({count})")
        self.src.emit(ind, f"if {entry} is not None and b.startswith({entry}[0], p):")
        self.src.emit(ind + 1, f"{value} = list({entry}[1]); p += {entry}[2]")
        self.src.emit(ind, "else:")
        inner = ind + 1
        length = self.src.const(shared_struct(self.order + "I").unpack_from, "U")
        end = self.src.name("q")
        self.src.emit(inner, f"{start} = p; {value} = []")
        self.src.emit(inner, f"for _ in range({count}):")  # its body as short as it goes
        self.src.emit(inner + 1, "p += -p & 3")  # -p & 3: the header's 4 keep p's residue
        self.src.emit(inner + 1, f"{end} = p + 4 + {length}(mv, p)[0]")
        self.src.emit(inner + 1, f"{value}.append(b[p + 4:{end} - 1].{self._utf8})")
        self.src.emit(inner + 1, f"p = {end}")
        self.src.emit(inner, f"if p <= len(b) and p - {start} <= {STRING_BLOCK_MAX}:")
        self.src.emit(inner + 1, f"if len({kept}) >= {STRING_BLOCKS_KEPT}: {kept}.clear()")
        # b[...] copies, from a bytearray too: a later change to the sample changes no entry
        self.src.emit(inner + 1, f"{kept}[{count}] = (b[{start}:p], tuple({value}), "
                                 f"p - {start})")

    def _block(self, prim: Primitive, byte_like: bool, count: str, ind: int,
               after_count: bool) -> str:
        """`count` primitives read in one slice; a fixed array keeps the known residue."""
        self._flush(ind)
        size = size_of(FORMATS[prim])
        value, end = self.src.name("a"), self.src.name("q")
        static = count.isdigit()
        inner = ind if static else ind + 1
        if not static:
            self.src.emit(ind, f"if {count}:")
        if size > 4 or (size > 1 and not after_count):
            self._align(size, inner)
        self.src.emit(inner, f"{end} = p + {count} * {size}")
        if byte_like or prim is Primitive.BOOLEAN or self.plain:
            self.src.emit(inner, f"{value} = {self._slice(prim, byte_like, end)}")
        else:  # one copy, in line (a function call costs as much as a short copy)
            self.views = self._sliced = True
            empty = self._empty_array(prim)  # copying an empty array beats making one
            self.src.emit(inner, f"{value} = {empty}[:]; {value}.frombytes(mv[p:{end}])")
            if self.swap:
                self.src.emit(inner, f"{value}.byteswap()")
        self.src.emit(inner, f"p = {end}")
        if static:
            if self._known is not None:
                self._known = (self._known + int(count) * size) % 8
            return value
        self.src.emit(ind, "else:")
        empty = "[]" if self.plain or prim is Primitive.BOOLEAN else (
            "EMPTY_OCTETS" if byte_like else f"{self._empty_array(prim)}[:]")
        self.src.emit(ind + 1, f"{value} = {empty}")
        self._known = None
        return value

    def _slice(self, prim: Primitive, byte_like: bool, end: str) -> str:
        self.views = self._sliced = True
        raw = f"mv[p:{end}]"
        # Lists are built from a bytes slice of `b` (bytes or a bytearray): iterating bytes
        # is twice as fast as iterating a memoryview (921,600 octets: 2.0 ms against 3.9)
        if byte_like:
            return f"list(b[p:{end}])" if self.plain else f"{raw}.toreadonly()"
        if prim is Primitive.BOOLEAN:
            return f"list(map(bool, b[p:{end}]))"
        code = ARRAY_CODES[prim]
        if self.plain and not self.swap:  # from `b`, bytes or bytearray: read as by frombytes
            return f"ARRAY({code!r}, b[p:{end}]).tolist()"
        call = f"to_array({code!r}, {raw}, {self.swap})"
        return f"{call}.tolist()" if self.plain else call

    def _align(self, size: int, ind: int) -> None:
        if self._known is not None:
            pad = -self._known % size
            if pad:
                self.src.emit(ind, f"p += {pad}")
            self._known = (self._known + pad) % 8
        else:
            self.src.emit(ind, f"p += (4 - p) & {size - 1}")

    # -- runs ---------------------------------------------------------------------------
    def _flush(self, ind: int) -> None:
        if not self._run:
            return
        items = [item for item, _ in self._run]
        targets = ", ".join(name for _, name in self._run) + ","
        self._run = []
        if self._known is not None:
            fmt, end = layout(self._known, items, self.order)
            reader = shared_struct(fmt)
            name = self.src.const(reader.unpack_from, "S")  # bound once, not per call
            self.src.emit(ind, f"{targets} = {name}(mv, p)")
            self.src.emit(ind, f"p += {reader.size}")
            self._known = end
            self._sliced = False
            self._emit_builds(ind)
            return
        table, after = by_residue(items, self.order)
        name = self.src.const(tuple((s.unpack_from, s.size) for s in table), "T")
        chosen, size = self.src.name("r"), self.src.name("z")
        self.src.emit(ind, f"{chosen}, {size} = {name}[p & 7]")
        self.src.emit(ind, f"{targets} = {chosen}(mv, p)")
        self.src.emit(ind, f"p += {size}")
        self._known = after
        self._sliced = False
        self._emit_builds(ind)

    def _empty_array(self, prim: Primitive) -> str:
        return self.src.const(array(ARRAY_CODES[prim]), "E")

    def _emit_builds(self, ind: int) -> None:
        for build in self._builds:
            self.src.emit(ind, build)
        self._builds = []
