"""Build cyclonedds `IdlStruct` classes from the neutral type model.

This is the one place that knows cyclonedds' Python type vocabulary; a faster codec can
replace it without touching the parser, the store or the hasher. Octet and uint8
sequences and arrays map to `bytes`, encoded in one copy: the struct is declared with
`sequence<uint8>` (so the type is described to XTypes peers as one, xtypes.py) and the
member's codec is then swapped for cyclonedds' own bytes codec, which writes the same
wire format (uint32 length, raw octets). A `wstring` is declared `sequence<uint32>`: that is
how rmw_fastrtps puts it on the wire (uint32 count of UTF-16 code units, then each unit as a
4-byte `wchar_t`, no terminator); values.py converts `str` to and from the units.
"""

from __future__ import annotations

import threading
import typing
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as t
from cyclonedds.idl._machinery import BytesMachine
from cyclonedds.topic import Topic

from ..errors import UnsupportedTypeError
from .model import Collection, FieldType, MessageType, Primitive
from .store import TypeStore

if TYPE_CHECKING:
    from .xtypes import Description

# A model changed before it is described (the Cyclone request header's `wrapper_model`).
Wrap = Callable[[MessageType], MessageType]
# cyclonedds' IDL classes take no larger sequence bound (`types.sequence`: it returns a
# TypeError in place of the type, which fails later with a traceback): refused clearly here.
MAX_SEQUENCE_BOUND = 65535

_PRIMITIVES: dict[Primitive, Any] = {
    Primitive.BOOLEAN: bool,
    Primitive.OCTET: t.byte,
    Primitive.CHAR: t.uint8,  # a ROS `char` is one unsigned byte on the wire
    Primitive.INT8: t.int8,
    Primitive.UINT8: t.uint8,
    Primitive.INT16: t.int16,
    Primitive.UINT16: t.uint16,
    Primitive.INT32: t.int32,
    Primitive.UINT32: t.uint32,
    Primitive.INT64: t.int64,
    Primitive.UINT64: t.uint64,
    Primitive.FLOAT: t.float32,
    Primitive.DOUBLE: t.float64,
    Primitive.STRING: str,
    Primitive.WSTRING: t.sequence[t.uint32],  # type: ignore[misc]
}
BYTE_LIKE = (Primitive.OCTET, Primitive.UINT8, Primitive.CHAR)


def is_byte_like(ftype: FieldType) -> bool:
    return ftype.primitive in BYTE_LIKE and ftype.is_collection


def use_bytes_codec(cls: type[IdlStruct], msg: MessageType) -> None:
    """Swaps in cyclonedds' one-copy bytes codec for `msg`'s octet/uint8 sequences."""
    byte_sequences = [f for f in msg.fields
                      if is_byte_like(f.type) and f.type.collection is not Collection.ARRAY]
    if not byte_sequences:
        return
    cls.__idl__.populate()
    for machine in (cls.__idl__.v1_machine, cls.__idl__.v2_machine):
        for f in byte_sequences:
            machine.members_machines[f.name] = BytesMachine(f.type.size or None)  # type: ignore[attr-defined]
    _ADJUSTED.add(cls)  # its machines are not cyclonedds' to rebuild (`make_topic`)


# Classes whose serializer machines `use_bytes_codec` changed: kept when a topic is made.
_ADJUSTED: weakref.WeakSet[type[IdlStruct]] = weakref.WeakSet()


# One topic made at a time: a class's `__idl__` holds our description only while its topic is
# made. It is held across `dds_create_topic`, which calls back into Python only on this thread
# (to drop its reference to a sertype's type when an equal one exists); no DDS thread runs our
# code, and a thread waiting for the lock releases the GIL, so it cannot close a deadlock.
_TOPIC_LOCK = threading.Lock()


def refuse_sequence_bound(ftype: FieldType, field_name: str) -> None:
    """Raises UnsupportedTypeError for a bounded sequence cyclonedds cannot declare."""
    if ftype.size > MAX_SEQUENCE_BOUND:
        raise UnsupportedTypeError(
            f"{field_name}: a sequence bound of {ftype.size} (over {MAX_SEQUENCE_BOUND}) is "
            "not supported on the wire yet")


class _Described:
    """Stands in `__idl__._xt_data` while a topic is made: cyclonedds' `fill_type_data` sees
    the type described and leaves the bytes we put in `_xt_bytedata`, which Cyclone copies."""


def make_topic(participant: DomainParticipant, dds_name: str, cls: type[IdlStruct],
               description: Description, *, keep_serializer: bool = False) -> Topic[Any]:
    """A Cyclone topic of `cls`, described by `description` (`xtypes.describe`), without the
    Python state cyclonedds builds to make one.

    Cyclone's C side reads a type's XTypes description (TypeInformation and TypeMapping,
    serialized) and a few flags when a topic is made, copies them, and never asks the Python
    side again; samples travel as raw CDR through our generated codecs (raw_cdr.py). So the
    description is ours, written from the type model, and cyclonedds' describer
    (`XTBuilder`) never runs: it would build its TypeInformation objects and, once per program
    and for good, the serializers of its own XTypes classes (~0.25 MB). The serializer
    cyclonedds builds for the type and every struct type in it (`__idl__`'s "machines", for
    the flags) is let go of once the topic is made: cyclonedds rebuilds it, the same, where
    its own codec is used (only the public-API fallbacks of raw_cdr.py and readers.py). The
    machines of a class `use_bytes_codec` changed are kept (a rebuild would lose the change),
    and all of them with `keep_serializer` (a topic read through cyclonedds' typed reader: no
    first sample should wait for a rebuild)."""
    with _TOPIC_LOCK:
        idl: Any = cls.__idl__
        idl._xt_data, idl._xt_bytedata = (_Described, _Described), description
        try:
            return Topic(participant, dds_name, cls)
        finally:
            idl._xt_data = idl._xt_bytedata = (None, None)  # as before fill_type_data
            for struct in [] if keep_serializer else _structs_in(cls):
                if struct not in _ADJUSTED:
                    _forget_machines(struct)


def _structs_in(cls: type[IdlStruct]) -> list[type[IdlStruct]]:
    """`cls` and every struct type its fields use, at any depth, each once."""
    found: dict[type[IdlStruct], None] = {}

    def visit(annotation: Any) -> None:
        if isinstance(annotation, type) and issubclass(annotation, IdlStruct):
            if annotation in found:
                return
            found[annotation] = None
            for field in vars(annotation).get("__annotations__", {}).values():
                visit(field)
            return
        for inner in typing.get_args(annotation):  # Annotated[Sequence[T], sequence[T]]…
            visit(inner)
        subtype = getattr(annotation, "subtype", None)  # cyclonedds' sequence / array
        if subtype is not None:
            visit(subtype)

    visit(cls)
    return list(found)


def _forget_machines(cls: type[IdlStruct]) -> None:
    """`cls.__idl__` back to unpopulated: what `populate()` and cyclonedds' field-type
    normalization built is rebuilt by them, the same, when next needed."""
    idl: Any = cls.__idl__
    with idl._lock:
        idl.v1_machine = idl.v2_machine = None
        idl.v1_keyresult = idl.v2_keyresult = None
        idl._populated = idl._populating = False
    if "__idl_type_annotations__" in vars(cls):  # made again by get_extended_type_hints
        delattr(cls, "__idl_type_annotations__")


class DdsTypes:
    """Caches one `IdlStruct` class per ROS struct type of a `TypeStore`."""

    def __init__(self, store: TypeStore) -> None:
        self.store = store
        self._classes: dict[str, type[IdlStruct]] = {}
        self._names: dict[type[IdlStruct], str] = {}  # the other way round
        self._by_asked: dict[str, type[IdlStruct]] = {}  # as asked for: "pkg/T", "pkg/msg/T"…
        self._kept: dict[tuple[str, Wrap | None], Description] = {}  # keep_description
        self._lock = threading.RLock()

    def struct(self, name: str) -> type[IdlStruct]:
        """The `IdlStruct` class of a ROS type, named `pkg::kind::dds_::T_` on the wire."""
        found = self._by_asked.get(name)  # the hot path (a message built per command): no lock
        if found is not None:
            return found
        msg = self.store.message(name)
        with self._lock:
            cls = self._classes.get(msg.name)
            if cls is None:
                cls = self._build(msg)
                self._classes[msg.name] = cls
                self._names[cls] = msg.name
            self._by_asked[name] = cls
            return cls

    def description(self, name: str, wrap: Wrap | None = None) -> Description:
        """The XTypes description of a ROS type's topics (`make_topic`); with `wrap`, of
        the type as `wrap` changes it. One kept (`keep_description`) is not made again."""
        kept = self._kept.get((name, wrap))
        if kept is not None:
            return kept
        # Imported by the first topic a process makes: a bridge lets the describer go once
        # started (`rcan_rtps._modules.START_ONLY`; idle memory, issue 27); a later first
        # use (a goal, an arm command) imports it again, a stop never (`keep_description`).
        from .xtypes import describe

        msg = self.store.message(name)
        return describe(msg if wrap is None else wrap(msg), self.store.message)

    def keep_description(self, name: str, wrap: Wrap | None = None) -> None:
        """Describes `name` (as `wrap` changes it) now, and keeps it: a topic made of it
        later — a service's, by a stop's first call — describes nothing."""
        self._kept[(name, wrap)] = self.description(name, wrap)

    def name_of(self, cls: type[Any]) -> str | None:
        """The ROS name of a struct class this registry made, else None."""
        return self._names.get(cls)

    def _build(self, msg: MessageType) -> type[IdlStruct]:
        fields = {f.name: self._annotation(msg, f.name, f.type) for f in msg.fields}
        class_name = msg.dds_name.rsplit("::", 1)[-1]
        cls = make_idl_struct(class_name, msg.dds_name, fields)
        use_bytes_codec(cls, msg)
        return cls

    def _annotation(self, msg: MessageType, fname: str, ftype: FieldType) -> Any:
        if is_byte_like(ftype) and ftype.collection is not Collection.ARRAY:
            ftype = FieldType(Primitive.UINT8, None, 0, ftype.collection, ftype.size)
        element = self._element(msg, fname, ftype)
        if ftype.collection is Collection.ARRAY:
            return t.array[element, ftype.size]  # type: ignore[misc]
        if ftype.collection is Collection.BOUNDED_SEQUENCE:
            refuse_sequence_bound(ftype, f"{msg.name}.{fname}")
            return t.sequence[element, ftype.size]  # type: ignore[misc]
        if ftype.collection is Collection.SEQUENCE:
            return t.sequence[element]  # type: ignore[misc]
        return element

    def _element(self, msg: MessageType, fname: str, ftype: FieldType) -> Any:
        if ftype.nested is not None:
            return self.struct(ftype.nested)
        assert ftype.primitive is not None
        # A bounded string is declared unbounded (`str`, the same bytes on the wire): Cyclone
        # checks a declared bound in UTF-8 bytes (writing 22 'é' to a string<22> fails), where
        # ROS bounds characters; values.py checks the bound the ROS way before anything is sent.
        found = _PRIMITIVES.get(ftype.primitive)
        if found is None:
            raise UnsupportedTypeError(
                f"{msg.name}.{fname}: {ftype.primitive.value} is not supported on the wire yet"
            )
        return found
