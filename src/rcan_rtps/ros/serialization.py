"""ROS 2 messages to and from CDR bytes, with no DDS: the counterpart of
`rclpy.serialization`.

    serialize("geometry_msgs/msg/Twist", {"linear": {"x": 0.5}}) -> bytes
    deserialize("geometry_msgs/msg/Twist", data)              -> a typed message
    deserialize("geometry_msgs/msg/Twist", data, plain=True)  -> plain values (dicts, lists)

Bytes are what rmw puts on the wire and rosbag2 stores: a 4-byte encapsulation header
(`00 01 00 00`, little-endian plain CDR) and the XCDR1 body. Values may be a typed message or
plain values, checked field by field (errors name the field). Types come from the IDL bundle
of the default distro unless a `TypeStore` is given.
"""

from __future__ import annotations

import threading
from typing import Any

from cyclonedds.idl import IdlStruct

from .errors import CdrDecodeError
from .typesys import TypeStore
from .typesys.ddstypes import DdsTypes
from .typesys.values import MessageValues

ENCAPSULATIONS = (b"\x00\x00", b"\x00\x01")  # plain CDR, big- and little-endian


class Codec:
    """Messages of one `TypeStore` to and from CDR."""

    def __init__(self, store: TypeStore | None = None) -> None:
        self.store = store or TypeStore()
        self.types = DdsTypes(self.store)
        self.values = MessageValues(self.types)

    def serialize(self, type_name: str, value: Any) -> bytes:
        message = value if isinstance(value, IdlStruct) else self.values.build(type_name, value)
        expected = self.types.struct(type_name)
        if not isinstance(message, expected):
            raise TypeError(f"a {type(message).__name__} is not a {type_name} message")
        return bytes(message.serialize())

    def deserialize(self, type_name: str, data: bytes | bytearray | memoryview, *,
                    plain: bool = False) -> Any:
        cls = self.types.struct(type_name)
        raw = bytes(data)
        if len(raw) < 4 or raw[:2] not in ENCAPSULATIONS:
            raise CdrDecodeError(f"{type_name}: not plain CDR (encapsulation "
                                 f"{raw[:4].hex(' ') or 'missing'})")
        try:
            message = cls.deserialize(raw)
        except Exception as exc:  # truncated or not this type: the codec's own words
            raise CdrDecodeError(f"{type_name}: {len(raw)} bytes do not decode ({exc})") from exc
        return self.values.to_plain(type_name, message) if plain else message


_default: Codec | None = None
_default_lock = threading.Lock()


def default_codec() -> Codec:
    """The codec of the bundle's default distro, made once."""
    global _default
    with _default_lock:
        if _default is None:
            _default = Codec()
        return _default


def serialize(type_name: str, value: Any) -> bytes:
    """CDR bytes (with the encapsulation header) of a message or of plain values."""
    return default_codec().serialize(type_name, value)


def deserialize(type_name: str, data: bytes | bytearray | memoryview, *,
                plain: bool = False) -> Any:
    """The message CDR bytes hold; with `plain`, as plain values."""
    return default_codec().deserialize(type_name, data, plain=plain)
