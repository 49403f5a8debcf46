"""Image sizes from JPEG/PNG headers, read before decoding.

A decoder allocates the whole frame before it finds out that the data is short, so a few bytes
claiming 60000 x 60000 pixels would cost gigabytes. Readers check the header first.
"""

from __future__ import annotations

import struct

#: frames larger than this are refused (8192 x 8192: far beyond any camera here)
MAX_PIXELS = 8192 * 8192

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: JPEG start-of-frame markers (every SOFn except DHT 0xC4, JPG 0xC8 and DAC 0xCC)
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def image_dimensions(data: bytes | memoryview) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header, or None when the header cannot be read."""
    buf = bytes(data[:65536]) if len(data) > 65536 else bytes(data)
    if buf.startswith(_PNG_SIGNATURE):
        if len(buf) < 24 or buf[12:16] != b"IHDR":
            return None
        w, h = struct.unpack(">II", buf[16:24])
        return int(w), int(h)
    if buf.startswith(b"\xff\xd8"):
        i = 2
        while i + 4 <= len(buf):
            if buf[i] != 0xFF:
                return None
            marker = buf[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
                i += 2
                continue
            (length,) = struct.unpack(">H", buf[i + 2:i + 4])
            if marker in _SOF:
                if i + 9 > len(buf):
                    return None
                h, w = struct.unpack(">HH", buf[i + 5:i + 9])
                return int(w), int(h)
            i += 2 + length
        return None
    return None


def too_large(data: bytes | memoryview, max_pixels: int = MAX_PIXELS) -> tuple[int, int] | None:
    """The header's (width, height) when it exceeds ``max_pixels``, else None."""
    dims = image_dimensions(data)
    if dims is not None and dims[0] * dims[1] > max_pixels:
        return dims
    return None


def truncation(data: bytes | memoryview) -> str | None:
    """Why a JPEG/PNG is visibly truncated (its end marker is missing), else None.

    Decoders fill a JPEG cut inside its entropy-coded data with grey and return a frame, which
    would then be matched as if it were a real view; the end markers catch that before decoding.
    Up to 1 KB of padding after the marker is tolerated.
    """
    n = len(data)
    tail = bytes(data[max(0, n - 1024):])
    head = bytes(data[:8])
    if head.startswith(_PNG_SIGNATURE) and b"IEND" not in tail:
        return "PNG without its IEND chunk: truncated"
    if head.startswith(b"\xff\xd8") and b"\xff\xd9" not in tail:
        return "JPEG without its end-of-image marker: truncated"
    return None
