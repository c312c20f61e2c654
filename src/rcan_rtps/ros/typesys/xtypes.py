"""XTypes descriptions of our struct types, the bytes Cyclone takes when a topic is made.

Making a topic, Cyclone's C side copies two serialized XTypes objects of its type — the
TypeInformation (its type identifiers and those it depends on) and the TypeMapping (every
type object involved) — and announces them to peers. cyclonedds builds them in Python from
the `IdlStruct` class (`XTBuilder.process_type`), and to serialize them it builds, once per
program and for good, the serializers of some eighty of its own XTypes classes (~0.25 MB of
a bridge's idle memory). This module writes the same bytes straight from the type model,
in XCDR2 as the XTypes 1.3 specification lays those objects out, following cyclonedds'
choices where the specification leaves one (member flags, equivalence kinds, the order of
the dependencies). The tests hold it to cyclonedds' own output for every type the bundled
IDL defines.

Only what ROS types use is described: final structs of primitives, strings, nested structs,
and arrays or sequences of those (ROS has no unions, enums, keys, optionals or recursion). The
field types are those `ddstypes.DdsTypes` declares to cyclonedds: octet and uint8 sequences
as `sequence<uint8>`, `char` as `uint8`, bounded strings unbounded, `wstring` as
`sequence<uint32>`.
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Callable, Sequence
from hashlib import md5

from ..errors import UnsupportedTypeError
from .ddstypes import refuse_sequence_bound
from .model import Collection, Field, FieldType, MessageType, Primitive

# Type kinds and type identifier kinds (XTypes 1.3, 7.3.4.9).
TK_NONE = 0x00
_KINDS = {
    Primitive.BOOLEAN: 0x01, Primitive.OCTET: 0x02, Primitive.INT16: 0x03,
    Primitive.INT32: 0x04, Primitive.INT64: 0x05, Primitive.UINT16: 0x06,
    Primitive.UINT32: 0x07, Primitive.UINT64: 0x08, Primitive.FLOAT: 0x09,
    Primitive.DOUBLE: 0x0A, Primitive.INT8: 0x0C, Primitive.UINT8: 0x0D,
    Primitive.CHAR: 0x0D,  # declared uint8 (ddstypes)
}
_TK_UINT32 = 0x07
_TK_STRUCTURE = 0x51
_TI_STRING8_SMALL, _TI_STRING8_LARGE = 0x70, 0x71
_TI_SEQUENCE_SMALL, _TI_SEQUENCE_LARGE = 0x80, 0x81
_TI_ARRAY_SMALL, _TI_ARRAY_LARGE = 0x90, 0x91
EK_MINIMAL, EK_COMPLETE, EK_BOTH = 0xF1, 0xF2, 0xF3
_TRY_CONSTRUCT_DISCARD = 0x0001  # MemberFlag TRY_CONSTRUCT1: every member, every element
_IS_FINAL = 0x0001  # TypeFlag: ROS structs are final
_SMALL = 256  # bounds below this have the "small" identifiers
# TypeInformation is mutable: each member has an EMHEADER1 whose length is the next int.
_EMHEADER_NEXTINT = 4 << 28
_MINIMAL_ID, _COMPLETE_ID = 0x1001, 0x1002
_ABSENT_ANNOTATIONS = b"\0\0"  # two optional members (builtin, custom annotations) not present


class _Out:
    """XCDR2, little-endian: nothing is aligned beyond 4 bytes."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def align(self, size: int) -> None:
        self.buf += bytes(-len(self.buf) % min(size, 4))

    def put(self, fmt: str, *values: int) -> None:
        self.align(struct.calcsize(fmt))
        self.buf += struct.pack("<" + fmt, *values)

    def string(self, text: str) -> None:
        data = text.encode()
        self.put("I", len(data) + 1)
        self.buf += data + b"\0"

    def delimited(self, body: Callable[[], None]) -> None:
        """A DHEADER (the byte size of what follows) before `body`: appendable types and
        sequences of non-primitive elements."""
        self.put("I", 0)
        start = len(self.buf)
        body()
        self.buf[start - 4:start] = struct.pack("<I", len(self.buf) - start)

    def sequence(self, items: Sequence[Callable[[], None]]) -> None:
        """A sequence of non-primitive elements: DHEADER, count, elements."""
        def body() -> None:
            self.put("I", len(items))
            for item in items:
                item()
        self.delimited(body)


# A type identifier, written where it stands (its alignment is that of the whole): a
# struct's is its hash and differs between the minimal and the complete description, a plain
# one (primitive, string, collection of those) is the same in both.
TypeId = Callable[[_Out], None]


def _raw(data: bytes) -> TypeId:
    def write(out: _Out) -> None:
        out.buf += data
    return write


class _Hashed:
    """One struct type's two type objects, serialized, and the identifiers they hash to."""

    def __init__(self, minimal: bytes, complete: bytes) -> None:
        self.minimal_object = minimal
        self.complete_object = complete
        self.minimal_id = bytes([EK_MINIMAL]) + md5(minimal).digest()[:14]
        self.complete_id = bytes([EK_COMPLETE]) + md5(complete).digest()[:14]


StructLookup = Callable[[str], MessageType]


Description = tuple[bytes, bytes]


def describe(msg: MessageType, lookup: StructLookup) -> Description:
    """The serialized TypeInformation and TypeMapping of `msg` (its nested types found by
    `lookup`), as cyclonedds' `IDL._xt_bytedata` holds them: without encapsulation header.
    Nothing is kept: a topic's description is made when the topic is, and Cyclone copies it.
    """
    return _Describer(lookup).describe(msg)


class _Describer:
    """One description: each struct in it described once (the hashes of a type's
    dependencies are used by every type that contains it)."""

    def __init__(self, lookup: StructLookup) -> None:
        self._lookup = lookup
        self._hashed: dict[str, _Hashed] = {}
        self._types: dict[str, MessageType] = {}

    def describe(self, msg: MessageType) -> Description:
        names, edges, leaves = self._gather(msg)
        root = self._hash(msg)
        if not edges:
            return self._information(root, []), self._mapping([root])
        depends = [self._hash(self._struct_named(name)) for name in leaves]
        depends += [h for h in self._components(names, edges, msg) if h is not root]
        mapped = [root if i == 0 else self._hash(self._struct_named(name))
                  for i, name in enumerate(names)]
        mapped += [self._hash(self._struct_named(name)) for name in leaves]
        return self._information(root, depends), self._mapping(mapped)

    # -- the dependency graph, as cyclonedds' `XTBuilder.gather_types` walks it ----------
    def _gather(self, msg: MessageType) -> tuple[list[str], list[list[int]], list[str]]:
        """The struct types `msg` reaches that contain structs (`msg` first) with the edges
        between them, and those that contain none (the order decides the bytes)."""
        top = msg.dds_name
        graph: dict[str, set[str]] = {top: set()}
        types: dict[str, MessageType] = {top: msg}
        to_scan: deque[MessageType] = deque([msg])
        while to_scan:
            current = to_scan.pop()
            node = current.dds_name
            for field in current.fields:
                if field.type.nested is None:
                    continue
                nested = self._lookup(field.type.nested)
                name = nested.dds_name
                if name not in graph:
                    graph[name] = set()
                    types[name] = nested
                    to_scan.append(nested)
                graph[node].add(name)
        leaves = [name for name, out in graph.items() if not out]
        for name in leaves:
            del graph[name]
        names = list(graph)
        index = {name: i for i, name in enumerate(names)}
        edges = [[index[n] for n in graph[name] if n in index] for name in names]
        self._types = types
        return names, edges, leaves

    def _struct_named(self, dds_name: str) -> MessageType:
        return self._types[dds_name]

    def _components(self, names: list[str], edges: list[list[int]],
                    msg: MessageType) -> list[_Hashed]:
        """The non-leaf types in the order cyclonedds lists them as dependencies: depth
        first from `msg`, each type after those it contains (repeated where reached twice).
        ROS types cannot contain themselves, so each is a component of its own."""
        successors: list[set[int]] = [set() for _ in names]
        for i, out in enumerate(edges):
            for j in out:
                if j != i:
                    successors[i].add(j)

        def visit(i: int) -> list[_Hashed]:
            found = [h for j in successors[i] for h in visit(j)]
            found.append(msg_hash if i == 0 else self._hash(self._struct_named(names[i])))
            return found

        msg_hash = self._hash(msg)
        return visit(0)

    # -- type objects -------------------------------------------------------------------
    def _hash(self, msg: MessageType) -> _Hashed:
        key = msg.dds_name + "|" + ",".join(f.name for f in msg.fields)  # a wrapper: its own
        found = self._hashed.get(key)
        if found is None:
            found = self._hashed[key] = _Hashed(self._type_object(msg, minimal=True),
                                                self._type_object(msg, minimal=False))
        return found

    def _type_object(self, msg: MessageType, *, minimal: bool) -> bytes:
        """`TypeObject` (appendable union) → Minimal/CompleteTypeObject → StructType."""
        out = _Out()

        def struct_type() -> None:
            out.put("B", EK_MINIMAL if minimal else EK_COMPLETE)
            out.put("B", _TK_STRUCTURE)
            out.put("H", _IS_FINAL)
            out.delimited(lambda: self._struct_header(out, msg, minimal))
            out.sequence([self._member(out, msg, i, f, minimal)
                          for i, f in enumerate(msg.fields)])

        out.delimited(struct_type)
        return bytes(out.buf)

    def _struct_header(self, out: _Out, msg: MessageType, minimal: bool) -> None:
        out.put("B", TK_NONE)  # no base type
        if not minimal:  # CompleteTypeDetail: no builtin or custom annotations, the name
            out.buf += _ABSENT_ANNOTATIONS
            out.string(msg.dds_name)

    def _member(self, out: _Out, msg: MessageType, member_id: int, field: Field,
                minimal: bool) -> Callable[[], None]:
        def member() -> None:
            out.put("I", member_id)
            out.put("H", _TRY_CONSTRUCT_DISCARD)
            self._identifier(field.type, minimal, f"{msg.name}.{field.name}")(out)
            if minimal:
                out.buf += md5(field.name.encode()).digest()[:4]
            else:
                out.string(field.name)
                out.buf += _ABSENT_ANNOTATIONS

        return lambda: out.delimited(member)

    # -- type identifiers ---------------------------------------------------------------
    def _identifier(self, ftype: FieldType, minimal: bool, field_name: str) -> TypeId:
        """The identifier of a field's type as ddstypes declares it to cyclonedds."""
        if _byte_sequence(ftype):
            ftype = FieldType(Primitive.UINT8, None, 0, ftype.collection, ftype.size)
        element = self._element(ftype, minimal, field_name)
        descriptive = ftype.nested is None
        if ftype.collection is Collection.ARRAY:
            return _array(element, [ftype.size], descriptive, minimal)
        if ftype.collection is Collection.BOUNDED_SEQUENCE:
            refuse_sequence_bound(ftype, field_name)
            return _sequence(element, ftype.size, descriptive, minimal)
        if ftype.collection is Collection.SEQUENCE:
            return _sequence(element, 0, descriptive, minimal)
        return element

    def _element(self, ftype: FieldType, minimal: bool, field_name: str) -> TypeId:
        if ftype.nested is not None:
            hashed = self._hash(self._lookup(ftype.nested))
            return _raw(hashed.minimal_id if minimal else hashed.complete_id)
        primitive = ftype.primitive
        assert primitive is not None
        if primitive is Primitive.STRING:  # declared unbounded: see ddstypes
            return _raw(bytes([_TI_STRING8_SMALL, 0]))
        if primitive is Primitive.WSTRING:  # declared sequence<uint32>: see ddstypes
            return _sequence(_raw(bytes([_TK_UINT32])), 0, True, minimal)
        kind = _KINDS.get(primitive)
        if kind is None:
            raise UnsupportedTypeError(
                f"{field_name}: {primitive.value} is not supported on the wire yet")
        return _raw(bytes([kind]))

    # -- TypeInformation and TypeMapping -----------------------------------------------
    @staticmethod
    def _information(root: _Hashed, depends: list[_Hashed]) -> bytes:
        out = _Out()
        # The minimal list names each type once, the complete one as reached (cyclonedds').
        once: dict[bytes, _Hashed] = {}
        for h in depends:
            once.setdefault(h.minimal_id, h)
        minimal = list(once.values())

        def with_size(type_id: bytes, size: int) -> Callable[[], None]:
            def body() -> None:
                out.buf += type_id
                out.put("I", size)
            return lambda: out.delimited(body)

        def with_dependencies(root_id: bytes, size: int,
                              listed: list[tuple[bytes, int]]) -> None:
            with_size(root_id, size)()
            out.put("i", len(listed))
            out.sequence([with_size(type_id, n) for type_id, n in listed])

        def member(member_id: int, body: Callable[[], None]) -> None:
            out.put("I", _EMHEADER_NEXTINT | member_id)
            out.put("I", 0)
            start = len(out.buf)
            out.delimited(body)
            out.buf[start - 4:start] = struct.pack("<I", len(out.buf) - start)

        def information() -> None:
            member(_MINIMAL_ID, lambda: with_dependencies(
                root.minimal_id, len(root.minimal_object),
                [(h.minimal_id, len(h.minimal_object)) for h in minimal]))
            member(_COMPLETE_ID, lambda: with_dependencies(
                root.complete_id, len(root.complete_object),
                [(h.complete_id, len(h.complete_object)) for h in depends]))

        out.delimited(information)
        return bytes(out.buf)

    @staticmethod
    def _mapping(types: list[_Hashed]) -> bytes:
        out = _Out()

        def pair(type_id: bytes, second: bytes) -> Callable[[], None]:
            def write() -> None:
                out.buf += type_id
                if len(second) != len(type_id):  # a type object: it starts with a DHEADER
                    out.align(4)
                out.buf += second
            return write

        out.sequence([pair(h.minimal_id, h.minimal_object) for h in types])
        out.sequence([pair(h.complete_id, h.complete_object) for h in types])
        out.sequence([pair(h.complete_id, h.minimal_id) for h in types])
        return bytes(out.buf)


def _byte_sequence(ftype: FieldType) -> bool:
    return (ftype.primitive in (Primitive.OCTET, Primitive.UINT8, Primitive.CHAR)
            and ftype.collection in (Collection.SEQUENCE, Collection.BOUNDED_SEQUENCE))


def _header(out: _Out, descriptive: bool, minimal: bool) -> None:
    """PlainCollectionHeader: equivalence kind, element flags."""
    out.put("B", EK_BOTH if descriptive else (EK_MINIMAL if minimal else EK_COMPLETE))
    out.put("H", _TRY_CONSTRUCT_DISCARD)


def _sequence(element: TypeId, bound: int, descriptive: bool, minimal: bool) -> TypeId:
    def write(out: _Out) -> None:
        out.put("B", _TI_SEQUENCE_SMALL if bound < _SMALL else _TI_SEQUENCE_LARGE)
        _header(out, descriptive, minimal)
        out.put("B" if bound < _SMALL else "I", bound)
        element(out)
    return write


def _array(element: TypeId, bounds: list[int], descriptive: bool, minimal: bool) -> TypeId:
    small = all(b < _SMALL for b in bounds)

    def write(out: _Out) -> None:
        out.put("B", _TI_ARRAY_SMALL if small else _TI_ARRAY_LARGE)
        _header(out, descriptive, minimal)
        out.put("I", len(bounds))
        for bound in bounds:
            out.put("B" if small else "I", bound)
        element(out)
    return write
