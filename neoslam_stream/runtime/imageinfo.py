"""Image sizes from JPEG/PNG/BMP/PNM headers, read before decoding.

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


def _jpeg_dimensions(buf: memoryview) -> tuple[int, int] | None:
    """(width, height) of the JPEG's first start-of-frame segment, walking the marker segments
    over the whole buffer (each has a length, so this is a few steps whatever the file's size).

    Bytes between segments that are not a marker are skipped, as libjpeg skips them ("extraneous
    bytes before marker"): otherwise a few garbage bytes would hide a frame header that the
    decoder still finds. The walk ends at the first scan (SOS) or the end-of-image marker: a
    frame header comes before its scan.
    """
    n = len(buf)
    i = 2
    while i < n:
        if buf[i] != 0xFF:  # garbage between segments: resynchronise on the next 0xFF
            i += 1
            continue
        while i < n and buf[i] == 0xFF:  # fill bytes
            i += 1
        if i >= n:
            return None
        marker = buf[i]
        i += 1
        if marker == 0x00:  # a stuffed 0xFF00 is no marker
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before it
            return None
        if i + 2 > n:
            return None
        (length,) = struct.unpack_from(">H", buf, i)
        if marker in _SOF:
            if i + 7 > n:
                return None
            h, w = struct.unpack_from(">HH", buf, i + 3)
            return int(w), int(h)
        if length < 2:  # a malformed length would loop in place
            return None
        i += length
    return None


def _pnm_dimensions(buf: memoryview) -> tuple[int, int] | None:
    """(width, height) of a binary or ASCII PBM/PGM/PPM header (P1..P6), comments allowed."""
    head = bytes(buf[:4096])
    tokens: list[bytes] = []
    i = 2
    while len(tokens) < 2 and i < len(head):
        c = head[i:i + 1]
        if c == b"#":
            j = head.find(b"\n", i)
            i = len(head) if j < 0 else j + 1
        elif c.isspace():
            i += 1
        else:
            j = i
            while j < len(head) and not head[j:j + 1].isspace() and head[j:j + 1] != b"#":
                j += 1
            tokens.append(head[i:j])
            i = j
    if len(tokens) < 2 or not all(t.isdigit() for t in tokens):
        return None
    return int(tokens[0]), int(tokens[1])


def image_dimensions(data: bytes | memoryview) -> tuple[int, int] | None:
    """(width, height) from a PNG, JPEG, BMP or PNM header, or None when it cannot be read.

    The whole buffer is considered (a JPEG's frame header can sit after 64 KB of metadata
    segments); nothing is copied.
    """
    buf = memoryview(data).cast("B") if not isinstance(data, memoryview) else data.cast("B")
    if bytes(buf[:8]) == _PNG_SIGNATURE:
        if len(buf) < 24 or bytes(buf[12:16]) != b"IHDR":
            return None
        w, h = struct.unpack_from(">II", buf, 16)
        return int(w), int(h)
    if bytes(buf[:2]) == b"\xff\xd8":
        return _jpeg_dimensions(buf)
    if bytes(buf[:2]) == b"BM" and len(buf) >= 26:
        w, h = struct.unpack_from("<ii", buf, 18)  # height is negative for top-down rows
        return abs(int(w)), abs(int(h))
    if len(buf) >= 3 and buf[0] == ord("P") and ord("1") <= buf[1] <= ord("6"):
        return _pnm_dimensions(buf)
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
