"""sensor_msgs/Image pixels → PNG (RFC 2083), with the standard library only.

A camera frame is shown to a client (an MCP agent, a browser) as a PNG, losslessly: no image
library is needed for the encodings ROS cameras send most (`rgb8`, `bgr8`, `rgba8`, `bgra8`,
`mono8`, `mono16`, `8UC1`, `8UC3`, `16UC1`). Rows are written with PNG's "none" filter and
compressed at zlib level 1: fast on a small CPU, a frame or two a second is all a client asks.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

from .errors import BridgeError

SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class Layout:
    channels: int
    depth: int  # bits per channel
    color_type: int  # PNG's: 0 grey, 2 RGB, 6 RGBA
    swap_rb: bool = False  # stored BGR(A): PNG wants RGB(A)


LAYOUTS = {
    "rgb8": Layout(3, 8, 2), "bgr8": Layout(3, 8, 2, swap_rb=True), "8UC3": Layout(3, 8, 2),
    "rgba8": Layout(4, 8, 6), "bgra8": Layout(4, 8, 6, swap_rb=True),
    "mono8": Layout(1, 8, 0), "8UC1": Layout(1, 8, 0),
    "mono16": Layout(1, 16, 0), "16UC1": Layout(1, 16, 0),
}


class UnsupportedImage(BridgeError):
    """An Image this encoder cannot show (its encoding, or a size that does not add up)."""


def _chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


def _rows(data: bytes, height: int, step: int, row_bytes: int, layout: Layout,
          big_endian: bool) -> bytes:
    """The pixel rows as PNG wants them: each after a filter byte, RGB order, 16-bit values
    big-endian, the row padding (`step` beyond the pixels) dropped."""
    out = bytearray()
    for y in range(height):
        row = bytearray(data[y * step: y * step + row_bytes])
        if layout.swap_rb:
            row[0::layout.channels], row[2::layout.channels] = (
                row[2::layout.channels], row[0::layout.channels])
        if layout.depth == 16 and not big_endian:
            row[0::2], row[1::2] = row[1::2], row[0::2]
        out += b"\x00" + row
    return bytes(out)


def image_to_png(encoding: str, width: int, height: int, step: int, data: bytes,
                 is_bigendian: bool = False) -> bytes:
    layout = LAYOUTS.get(encoding)
    if layout is None:
        raise UnsupportedImage(f"encoding {encoding!r} (shown: {', '.join(sorted(LAYOUTS))})")
    row_bytes = width * layout.channels * layout.depth // 8
    if width <= 0 or height <= 0 or step < row_bytes or len(data) < step * (height - 1) + row_bytes:
        raise UnsupportedImage(f"{width}x{height} {encoding} with step {step} does not fit "
                               f"its {len(data)} bytes of data")
    header = struct.pack(">IIBBBBB", width, height, layout.depth, layout.color_type, 0, 0, 0)
    pixels = _rows(data, height, step, row_bytes, layout, is_bigendian)
    return (SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(pixels, 1))
            + _chunk(b"IEND", b""))
