"""Camera frames as PNG: each encoding ROS cameras send most, read back pixel for pixel."""

from __future__ import annotations

import pytest
from pngcheck import read_png

from rcan_rtps.bridge.images import compressed_mime, encode
from rcan_rtps.bridge.png import LAYOUTS, UnsupportedImage, image_to_png
from rcan_rtps.ros.serialization import serialize

RGB = bytes([255, 0, 0, 0, 255, 0, 0, 0, 255, 10, 20, 30])  # 2x2: red, green, blue, grey


def test_rgb8_is_kept_as_it_is() -> None:
    assert read_png(image_to_png("rgb8", 2, 2, 6, RGB)) == (2, 2, 8, 2, RGB)


def test_bgr8_and_bgra8_come_out_in_rgb_order() -> None:
    bgr = bytes(b for i in range(0, 12, 3) for b in (RGB[i + 2], RGB[i + 1], RGB[i]))
    assert read_png(image_to_png("bgr8", 2, 2, 6, bgr))[4] == RGB
    bgra = bytes([30, 20, 10, 128])
    assert read_png(image_to_png("bgra8", 1, 1, 4, bgra))[2:] == (8, 6, bytes([10, 20, 30, 128]))


def test_mono16_is_big_endian_in_the_png_whatever_the_frame() -> None:
    little = bytes([0x34, 0x12, 0xFF, 0x00])  # 0x1234, 0x00FF
    assert read_png(image_to_png("mono16", 2, 1, 4, little))[4] == bytes([0x12, 0x34, 0, 0xFF])
    big = bytes([0x12, 0x34, 0x00, 0xFF])
    assert read_png(image_to_png("16UC1", 2, 1, 4, big, is_bigendian=True))[4] == big


def test_row_padding_is_dropped() -> None:
    padded = bytes([1, 2, 9, 9, 3, 4, 9, 9])  # mono8 2x2, step 4
    assert read_png(image_to_png("mono8", 2, 2, 4, padded)) == (2, 2, 8, 0, bytes([1, 2, 3, 4]))


@pytest.mark.parametrize(("encoding", "width", "height", "step", "size"), [
    ("yuv422", 2, 2, 4, 8), ("bayer_rggb8", 2, 2, 2, 4), ("", 1, 1, 3, 3),
    ("rgb8", 2, 2, 6, 11), ("rgb8", 2, 2, 5, 12), ("rgb8", 0, 2, 0, 0), ("mono8", 2, -1, 2, 4),
])
def test_what_cannot_be_shown_is_refused_by_name(encoding: str, width: int, height: int,
                                                 step: int, size: int) -> None:
    with pytest.raises(UnsupportedImage):
        image_to_png(encoding, width, height, step, bytes(size))


def test_every_layout_round_trips() -> None:
    for encoding, layout in LAYOUTS.items():
        row = 3 * layout.channels * layout.depth // 8
        data = bytes(range(row * 2))
        width, height, depth, _, _ = read_png(image_to_png(encoding, 3, 2, row, data))
        assert (width, height, depth) == (3, 2, layout.depth), encoding


def test_a_sample_is_encoded_from_its_cdr() -> None:
    cdr = serialize("sensor_msgs/msg/Image", {"height": 2, "width": 2, "encoding": "rgb8",
                                              "step": 6, "data": RGB})
    mime, png, width, height = encode("sensor_msgs/msg/Image", cdr)
    assert (mime, width, height, read_png(png)[4]) == ("image/png", 2, 2, RGB)
    jpeg = serialize("sensor_msgs/msg/CompressedImage", {"format": "rgb8; jpeg compressed bgr8",
                                                         "data": b"\xff\xd8jpeg"})
    assert encode("sensor_msgs/msg/CompressedImage", jpeg) == (
        "image/jpeg", b"\xff\xd8jpeg", None, None)
    with pytest.raises(UnsupportedImage, match="does not decode"):
        encode("sensor_msgs/msg/Image", b"\x00\x01\x00\x00\x05")
    tiff = serialize("sensor_msgs/msg/CompressedImage", {"format": "tiff", "data": b"II*"})
    with pytest.raises(UnsupportedImage, match="tiff"):
        encode("sensor_msgs/msg/CompressedImage", tiff)


@pytest.mark.parametrize(("fmt", "mime"), [
    ("jpeg", "image/jpeg"), ("png", "image/png"), ("bgr8; png compressed bgr8", "image/png"),
    ("JPG", "image/jpeg"), ("theora", None), ("", None)])
def test_compressed_formats(fmt: str, mime: str | None) -> None:
    assert compressed_mime(fmt) == mime
