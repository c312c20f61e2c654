"""Large blocks (more than `cdr_encode.BIG` bytes: images, point clouds, long numeric
sequences) leave the encoder's bytearray and are joined into the result in one copy; a few
placeholder bytes keep the alignment of what follows. Here, against cyclonedds' own codec:
blocks of odd sizes followed by fields that need alignment, at the top and inside a sequence
of structs (a nested function's blocks), typed and plain, and decoded back.
"""

from __future__ import annotations

from array import array
from typing import Any

import pytest

from rcan_rtps.ros.serialization import default_codec
from rcan_rtps.ros.typesys.cdr_encode import BIG

pytestmark = pytest.mark.offline

ODD = BIG + 5  # a block's size mod 8 is not 0: the placeholder must carry it


def sequences() -> dict[str, Any]:
    """Every numeric sequence of test_msgs/UnboundedSequences over BIG bytes, odd lengths,
    and an int32 after them (whose padding depends on where the last block ended)."""
    return {"bool_values": [i % 3 == 0 for i in range(ODD)],
            "byte_values": bytes(i % 251 for i in range(ODD)),
            "char_values": bytes(i % 127 for i in range(ODD + 1)),
            "float32_values": array("f", (i * 0.5 for i in range(ODD // 4 + 3))),
            "float64_values": [i * 0.25 for i in range(ODD // 8 + 1)],
            "int8_values": [i % 256 - 128 for i in range(ODD + 2)],
            "uint8_values": list(range(256)) * (ODD // 256 + 1),
            "int16_values": array("h", (i - 3000 for i in range(ODD // 2 + 1))),
            "uint32_values": [i * 7 for i in range(ODD // 4 + 1)],
            "int64_values": [-i for i in range(ODD // 8 + 3)],
            "string_values": ["after the blocks"],
            "alignment_check": 1234567}


def parameters() -> dict[str, Any]:
    """Big blocks inside a sequence of structs: each Parameter's value has them."""
    def value(i: int) -> dict[str, Any]:
        return {"type": 5, "byte_array_value": bytes([i]) * (ODD + i),
                "bool_array_value": [True, False, True],
                "integer_array_value": list(range(BIG // 8 + i)),
                "double_array_value": array("d", (0.5 * j for j in range(BIG // 8 + 1))),
                "string_array_value": ["x" * i]}
    return {"parameters": [{"name": f"p{i}", "value": value(i)} for i in range(3)]}


def image(size: int) -> dict[str, Any]:
    return {"height": 1, "width": size, "encoding": "mono8", "step": size,
            "data": bytes(i % 253 for i in range(size))}


# one block that ends the message (joined without memoryviews), with and without a
# placeholder to drop, and one that does not (a PointCloud2's data, then is_dense)
CASES = [("test_msgs/msg/UnboundedSequences", sequences()),
         ("rcl_interfaces/srv/SetParameters_Request", parameters()),
         ("sensor_msgs/msg/Image", {"height": 480, "width": 640, "encoding": "rgb8",
                                    "step": 1920, "data": bytes(range(256)) * 3600}),
         ("sensor_msgs/msg/Image", image(ODD)),
         ("sensor_msgs/msg/PointCloud2", {"height": 1, "width": ODD, "point_step": 1,
                                          "row_step": ODD, "data": image(ODD)["data"],
                                          "is_dense": True})]
IDS = ["UnboundedSequences", "SetParameters_Request", "Image 640x480", "Image odd size",
       "PointCloud2 odd size"]


@pytest.mark.parametrize(("type_name", "value"), CASES, ids=IDS)
def test_big_blocks_encode_as_cyclonedds_does(type_name: str, value: dict[str, Any]) -> None:
    codec = default_codec()
    message = codec.values.build(type_name, value)
    expected = bytes(message.serialize())
    generated = codec.of(type_name)
    fallbacks = generated.fallbacks
    plain = generated.encode_plain(value)
    assert generated.fallbacks == fallbacks, "valid values left the plain fast path"
    typed = generated.encode(message)
    assert type(plain) is bytes and type(typed) is bytes
    assert plain == expected
    assert typed == expected
    assert typed == generated.encode(generated.decode(expected))  # decoded blocks re-encode
    assert codec.deserialize(type_name, expected, plain=True) == codec.values.to_plain(
        type_name, message)
