"""8-bit grey PNG frames decoded without libpng: ISA-L's inflate and a numpy row filter.

Why by hand (measured in BENCHMARKS.md, "Thirty-third session"): decoding the frames is the
largest single cost of `fusion run` on a PNG log.  A 640x480 frame of the benchmark flight takes
1.5-1.9 ms in OpenCV's libpng (zlib's inflate alone 1.27 ms) and 1.2-1.8 ms in pyspng.  The
`isal` package (Intel's ISA-L, the compiled inflate behind python-isal / xopen) inflates it in
0.66 ms, and undoing the rows' filters is 0.3-0.45 ms of numpy.

Only the common case takes this path (PNG specification, sections 11.2.2 and 9.2): 8-bit
greyscale, not interlaced, every row filtered with None, Sub or Up, which is what OpenCV's
encoder writes and so what most robotics tools write, and no chunk that could change the pixels
(besides IHDR, IDAT and IEND only text, time, physical-size and the colour-space chunks that
OpenCV does not apply). Anything else (colour, 16 bits, a palette, Average or Paeth rows, a
transparency or ICC-profile chunk, a CRC or zlib error, a length that does not match) returns
None, and the caller decodes with OpenCV as before, which also names the errors. The result is
bit-identical to OpenCV's (`tests/test_png.py`).
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
from isal import isal_zlib

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

_PIXEL_NEUTRAL = frozenset({b"tEXt", b"zTXt", b"iTXt", b"tIME", b"pHYs", b"gAMA", b"sRGB", b"cHRM"})
"""Ancillary chunks that do not change a grey pixel as OpenCV decodes it: text, time, pixel size,
and gamma / sRGB intent / chromaticities, which OpenCV's reader does not apply (a gamma of 0.1 or
10 decodes to the stored values: `tests/test_png.py`; three of zxing-cpp's sample images carry
them)."""

PEEK_ROWS = 8
"""Rows inflated first, to see their filters (libpng's adaptive choice has Paeth from row 1)."""

_MAX_SIDE = 1 << 15
"""Wider or taller frames are left to OpenCV (its own limits and messages apply)."""


def decode_gray8(data: bytes) -> np.ndarray | None:
    """The (height, width) uint8 image of an 8-bit grey PNG file's bytes, or None when the file
    is anything this fast path does not take (the caller then decodes with OpenCV)."""
    view = memoryview(data)
    if len(view) < 33 or view[:8] != PNG_SIGNATURE:
        return None
    idat: list[memoryview] = []
    idat_closed = False  # a chunk after the IDATs: another IDAT is an error to libpng
    width = height = 0
    pos = 8
    while True:
        if pos + 12 > len(view):
            return None
        (length,) = struct.unpack_from(">I", view, pos)
        end = pos + 8 + length
        if end + 4 > len(view):
            return None
        kind = bytes(view[pos + 4 : pos + 8])
        (crc,) = struct.unpack_from(">I", view, end)
        if isal_zlib.crc32(view[pos + 4 : end]) != crc:
            return None
        body = view[pos + 8 : end]
        if pos == 8:
            if kind != b"IHDR" or length != 13:
                return None
            width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", body)
            if (depth, colour, compression, filtering, interlace) != (8, 0, 0, 0, 0):
                return None
            if not (0 < width <= _MAX_SIDE and 0 < height <= _MAX_SIDE):
                return None
        elif kind == b"IDAT":
            if idat_closed:
                return None
            idat.append(body)
        elif kind == b"IEND":
            break
        elif kind not in _PIXEL_NEUTRAL:
            return None
        else:
            idat_closed = bool(idat)
        pos = end + 4
    row = width + 1
    size = height * row
    stream = b"".join(idat)
    try:
        # the first rows' filters first, by zlib (0.02 ms; ISA-L's first call costs 0.1 ms
        # whatever it inflates): a file with Average / Paeth rows (libpng's adaptive filter
        # choice) is told by them before the whole image is inflated for nothing
        head = zlib.decompressobj().decompress(stream, min(height, PEEK_ROWS) * row)
    except zlib.error:
        return None
    if len(head) % row or max(head[::row], default=3) > 2:
        return None
    inflater = isal_zlib.decompressobj()
    try:
        raw = inflater.decompress(stream, size + 1)
    except isal_zlib.error:  # type: ignore[misc]  # (isal's stub declares `error` an instance)
        return None
    if not inflater.eof or len(raw) != size or inflater.unconsumed_tail or inflater.unused_data:
        return None
    return _unfilter(np.frombuffer(raw, np.uint8).reshape(height, row))


def _unfilter(rows: np.ndarray) -> np.ndarray | None:
    """The pixels of filtered rows (each row's first byte its filter type), one byte a pixel;
    None if a row uses a filter other than None (0), Sub (1) or Up (2).  One filter on every
    row (what encoders told a filter write) is undone in whole-image numpy operations, mixed
    rows one row at a time."""
    filters, filtered = rows[:, 0], rows[:, 1:]
    if not filters.any():
        return np.ascontiguousarray(filtered)
    if np.all(filters == 1):
        # Sub on every row (OpenCV's encoder by default): each row's running sum mod 256
        return np.cumsum(filtered, axis=1, dtype=np.uint8)
    if np.all(filters == 2):
        # Up on every row (the simulator's `png_params`): each pixel is its column's running sum,
        # a prefix sum over rows in log2(height) vector additions (0.31 ms against 0.45 ms for
        # the row loop below at 640x480)
        x = np.ascontiguousarray(filtered)
        y = np.empty_like(x)
        step = 1
        while step < len(x):
            np.add(x[step:], x[:-step], out=y[step:])
            y[:step] = x[:step]
            x, y = y, x
            step *= 2
        return x
    if filters.max() > 2:
        return None
    out = np.empty_like(filtered)
    above = np.zeros(filtered.shape[1], np.uint8)
    for i, kind in enumerate(filters):
        if kind == 0:
            out[i] = filtered[i]
        elif kind == 1:
            np.cumsum(filtered[i], dtype=np.uint8, out=out[i])
        else:
            np.add(filtered[i], above, out=out[i])
        above = out[i]
    return out
