"""A PNG reader for tests (filter type 0 rows, as ours writes them; any other filter fails)."""

from __future__ import annotations

import struct
import zlib

CHANNELS = {0: 1, 2: 3, 6: 4}


def read_png(data: bytes) -> tuple[int, int, int, int, bytes]:
    """(width, height, bit depth, PNG colour type, the rows' bytes without filter bytes);
    checks the signature and every chunk's CRC."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    pos, chunks = 8, []
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, f"bad CRC in {kind!r}"
        chunks.append((kind, body))
        pos += 12 + length
    assert chunks[0][0] == b"IHDR" and chunks[-1][0] == b"IEND"
    width, height, depth, color, _, _, _ = struct.unpack(">IIBBBBB", chunks[0][1])
    raw = zlib.decompress(b"".join(b for k, b in chunks if k == b"IDAT"))
    row = width * CHANNELS[color] * depth // 8
    rows = b""
    for y in range(height):
        line = raw[y * (row + 1):(y + 1) * (row + 1)]
        assert line[0] == 0, "a filter this reader does not know"
        rows += line[1:]
    return width, height, depth, color, rows
