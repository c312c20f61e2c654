"""rmw_cyclonedds' in-band request header, as a wrapper struct under the plain type's name.

rmw_cyclonedds puts `uint64 client_guid; int64 seq` between the 4-byte CDR encapsulation
and the fields of every request and reply, in the sample's byte order. A struct
`{uint64 client_guid; int64 seq; <the fields of T>}` serializes to exactly those bytes:
16 is a multiple of 8, so every later field keeps its alignment and its bytes. The
wrapper keeps T's DDS type name so that rmw_cyclonedds endpoints match it. (The fields
are copied rather than nested: a member type named like its parent breaks XTypes.)

The topic keeps that wrapper type (for discovery and matching), but samples travel as raw
CDR (raw_cdr.py): `wrap_cdr` puts the header in front of the generated codec's body, and
`decoder` reads it back and decodes the body in place.
"""

from __future__ import annotations

import struct
import threading
import typing
import weakref
from collections.abc import Callable
from typing import Any

import msgspec
from cyclonedds.core import Policy
from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as t
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from .errors import WireError
from .participant import RosNode
from .qos import QosProfile
from .typesys.cdr import byte_order
from .typesys.ddstypes import make_topic, use_bytes_codec
from .typesys.model import Field, FieldType, MessageType, Primitive

ENCAPSULATION_SIZE = 4
HEADER_SIZE = 16  # uint64 client_guid at offset 4, int64 seq at offset 12 (after encapsulation)
GUID_FIELD, SEQ_FIELD = "rmw_request_client_guid", "rmw_request_seq"


_HEADER = struct.Struct("<Qq")  # after the encapsulation, in the sample's byte order
_HEADER_BIG = struct.Struct(">Qq")


class RequestHeader(msgspec.Struct, frozen=True):
    client_guid: int  # rmw_cyclonedds uses the request writer's instance handle
    seq: int  # per-client sequence number, echoed in the reply


class Wrapped:
    """A request or reply as read: its in-band header and the plain message."""

    __slots__ = ("header", "payload", "sample_info")

    def __init__(self, header: RequestHeader, payload: IdlStruct) -> None:
        self.header = header
        self.payload = payload
        self.sample_info: Any = None


def wrap_cdr(header: RequestHeader, data: bytes) -> bytes:
    """The wire bytes of a wrapped sample, from the plain message's little-endian CDR."""
    guid = header.client_guid & 0xFFFF_FFFF_FFFF_FFFF
    return data[:ENCAPSULATION_SIZE] + _HEADER.pack(guid, header.seq) + data[ENCAPSULATION_SIZE:]


def decoder(node: RosNode, type_name: str) -> Callable[[bytes], Wrapped]:
    """Reads wrapped samples of `type_name`: the header, then the plain body decoded in place
    (16 header bytes keep every later field's alignment, so the body decodes as it stands)."""
    codec = node.codecs.of(type_name).prepare_decoder()

    def decode(data: bytes) -> Wrapped:
        mv = memoryview(data)
        header = _HEADER if byte_order(mv, codec.type_name) == "<" else _HEADER_BIG
        guid, seq = header.unpack_from(mv, ENCAPSULATION_SIZE)
        payload = codec.decode(mv, offset=ENCAPSULATION_SIZE + HEADER_SIZE)
        return Wrapped(RequestHeader(guid, seq), payload)

    return decode


_wrappers: dict[tuple[int, str], type[IdlStruct]] = {}
_topics: weakref.WeakKeyDictionary[RosNode, dict[str, Topic[Any]]] = weakref.WeakKeyDictionary()
_lock = threading.Lock()


def wrapper_struct(node: RosNode, type_name: str) -> type[IdlStruct]:
    """`{uint64 client_guid; int64 seq; <fields of T>}` named like T on the wire."""
    plain = node.types.struct(type_name)
    msg = node.store.message(type_name)
    key = (id(plain), msg.dds_name)
    with _lock:
        found = _wrappers.get(key)
        if found is None:
            found = _build_wrapper(plain, msg)
            _wrappers[key] = found
        return found


def _build_wrapper(plain: type[IdlStruct], msg: Any) -> type[IdlStruct]:
    hints = typing.get_type_hints(plain, include_extras=True)
    if GUID_FIELD in hints or SEQ_FIELD in hints:
        raise WireError(f"{msg.name} has a field named like the request header")
    short = msg.dds_name.rsplit("::", 1)[-1]
    cls = make_idl_struct(f"{short}CycloneWrapper", msg.dds_name,
                          {GUID_FIELD: t.uint64, SEQ_FIELD: t.int64, **hints})
    use_bytes_codec(cls, msg)  # byte sequences as in DdsTypes
    return cls


def wrapper_model(msg: MessageType) -> MessageType:
    """`msg` with the request header's fields first, as `wrapper_struct` declares it."""
    header = (Field(GUID_FIELD, FieldType(Primitive.UINT64)),
              Field(SEQ_FIELD, FieldType(Primitive.INT64)))
    return MessageType(msg.name, header + msg.fields, msg.constants, msg.source)


def wrapper_topic(node: RosNode, dds_topic: str, type_name: str) -> Topic[Any]:
    with _lock:
        topics = _topics.setdefault(node, {})
        found = topics.get(dds_topic)
    if found is None:
        try:
            found = make_topic(node.participant, dds_topic, wrapper_struct(node, type_name),
                               node.types.description(type_name, wrapper_model))
        except Exception as exc:  # cyclonedds raises a bare DDSException
            raise WireError(f"cannot create {dds_topic} with the Cyclone request header in "
                            f"this participant (a plain one exists?): {exc}") from exc
        with _lock:
            found = _topics[node].setdefault(dds_topic, found)
    return found


def _user_data(node: RosNode, type_name: str, extra: str) -> bytes | None:
    data = (node.endpoint_user_data(type_name) or b"") + extra.encode()
    return data or None


def create_writer(node: RosNode, dds_topic: str, type_name: str, qos: QosProfile,
                  extra_user_data: str) -> DataWriter[Any]:
    """A writer of wrapped samples; USER_DATA carries the plain type's hash, like rmw."""
    writer: DataWriter[Any] = DataWriter(
        node.publisher, wrapper_topic(node, dds_topic, type_name),
        qos=qos.to_dds(_user_data(node, type_name, extra_user_data)))
    node.track_writer(writer)
    return writer


def create_reader(node: RosNode, dds_topic: str, type_name: str, qos: QosProfile,
                  extra_user_data: str) -> DataReader[Any]:
    """A reader of wrapped samples, without delivery (`node.watch` it)."""
    # Header member names are not part of the wire: match peers that name them differently.
    tolerant = Qos(Policy.TypeConsistency.AllowTypeCoercion(ignore_member_names=True))
    reader: DataReader[Any] = DataReader(
        node.subscriber, wrapper_topic(node, dds_topic, type_name),
        qos=qos.to_dds(_user_data(node, type_name, extra_user_data)) + tolerant)
    node.track_reader(reader)
    return reader
