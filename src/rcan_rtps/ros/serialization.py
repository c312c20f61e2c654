"""ROS 2 messages to and from CDR bytes, with no DDS: the counterpart of
`rclpy.serialization`.

    serialize("geometry_msgs/msg/Twist", {"linear": {"x": 0.5}}) -> bytes
    deserialize("geometry_msgs/msg/Twist", data)              -> a typed message
    deserialize("geometry_msgs/msg/Twist", data, plain=True)  -> plain values (dicts, lists)

Bytes are what rmw puts on the wire and rosbag2 stores: a 4-byte encapsulation header
(`00 01 00 00`, little-endian plain CDR) and the XCDR1 body. Values may be a typed message or
plain values, checked field by field (errors name the field). Numeric sequences may be given as
`array.array`s of the field's width; typed messages decode them to arrays, and byte fields to
read-only memoryviews over `data` (no copy). Types come from the IDL bundle of the default
distro unless a `TypeStore` is given. The codecs are generated per type (typesys/cdr.py).
"""

from __future__ import annotations

import threading
from typing import Any

from .typesys import TypeStore
from .typesys.cdr import CdrCodecs, MessageCodec
from .typesys.ddstypes import DdsTypes
from .typesys.values import MessageValues


class Codec:
    """Messages of one `TypeStore` to and from CDR."""

    def __init__(self, store: TypeStore | None = None) -> None:
        self.store = store or TypeStore()
        self.types = DdsTypes(self.store)
        self.values = MessageValues(self.types)
        self.codecs = CdrCodecs(self.types, self.values)
        self._known = self.codecs.known  # the per-call lookup, without a method call

    def of(self, type_name: str) -> MessageCodec:
        """The generated codec of one type, for callers that encode many messages."""
        return self.codecs.of(type_name)

    def serialize(self, type_name: str, value: Any) -> bytes:
        codec = self._known.get(type_name) or self.codecs.of(type_name)
        return codec.encode_value(value)

    def deserialize(self, type_name: str, data: bytes | bytearray | memoryview, *,
                    plain: bool = False) -> Any:
        codec = self._known.get(type_name) or self.codecs.of(type_name)
        return codec.read_plain(data) if plain else codec.read(data)  # decode(_plain) itself


_default: Codec | None = None
_default_lock = threading.Lock()


def default_codec() -> Codec:
    """The codec of the bundle's default distro, made once."""
    global _default
    if _default is not None:  # made: no lock per message
        return _default
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
