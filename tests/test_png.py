"""The 8-bit grey PNG fast path (fusion.log.png): bit-identical to OpenCV where it decodes, and
None (OpenCV decodes instead) for everything it does not take."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion.log.euroc import decode_image_bytes
from fusion.log.png import PEEK_ROWS, PNG_SIGNATURE, decode_gray8
from fusion.sim.simulate import png_params


def chunk(kind: bytes, body: bytes, crc: int | None = None) -> bytes:
    crc = zlib.crc32(kind + body) if crc is None else crc
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)


def paeth(a: int, b: int, c: int) -> int:
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else b if pb <= pc else c


def filtered_rows(img: np.ndarray, filters: list[int]) -> bytes:
    """The PNG specification's filters (section 9.2), one byte a pixel, written out plainly."""
    out = bytearray()
    above = [0] * img.shape[1]
    for row, kind in zip(img.tolist(), filters):
        out.append(kind)
        for x, value in enumerate(row):
            left = row[x - 1] if x else 0
            corner = above[x - 1] if x else 0
            predictor = [0, left, above[x], (left + above[x]) // 2, paeth(left, above[x], corner)][kind]
            out.append((value - predictor) % 256)
        above = row
    return bytes(out)


def png(
    img: np.ndarray,
    filters: list[int] | None = None,
    *,
    header: tuple[int, int, int, int, int] = (8, 0, 0, 0, 0),
    extra: bytes = b"",
    idat_parts: int = 1,
    stream: bytes | None = None,
) -> bytes:
    h, w = img.shape
    filters = [2] * h if filters is None else filters
    data = zlib.compress(filtered_rows(img, filters)) if stream is None else stream
    cut = np.linspace(0, len(data), idat_parts + 1).astype(int)
    idat = b"".join(chunk(b"IDAT", data[a:b]) for a, b in zip(cut[:-1], cut[1:]))
    ihdr = chunk(b"IHDR", struct.pack(">II", w, h) + bytes(header))
    return PNG_SIGNATURE + ihdr + extra + idat + chunk(b"IEND", b"")


def split_idat(encoded: bytes) -> bytes:
    """A text chunk put between the first and second IDAT chunks."""
    (first,) = struct.unpack_from(">I", encoded, 33)
    cut = 33 + 12 + first
    return encoded[:cut] + chunk(b"tEXt", b"a\x00b") + encoded[cut:]


def opencv(data: bytes) -> np.ndarray | None:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)


@pytest.mark.parametrize("shape", [(480, 640), (1, 1), (1, 7), (9, 1), (37, 53), (720, 1280)])
def test_opencv_written_frames_take_the_fast_path_bit_identical(shape):
    img = np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8)
    img[: shape[0] // 2] //= 7  # smooth and noisy parts: both kinds of zlib block
    ok, buf = cv2.imencode(".png", img)
    assert ok
    fast = decode_gray8(buf.tobytes())
    assert fast is not None
    assert fast.dtype == np.uint8 and fast.shape == shape
    np.testing.assert_array_equal(fast, img)
    np.testing.assert_array_equal(fast, opencv(buf.tobytes()))


@pytest.mark.parametrize("level", [0, 1, 5, 8])
def test_the_simulators_frames_take_the_fast_path(level):
    """`fusion simulate --png-compression 0-8` writes None / Up rows (9: libpng's adaptive
    filters, OpenCV's); the committed sample flight, written before, has Paeth rows: both paths
    run end to end in the suite."""
    img = np.random.default_rng(level).integers(0, 256, (48, 64), dtype=np.uint8)
    ok, buf = cv2.imencode(".png", img, png_params(level))
    assert ok
    fast = decode_gray8(buf.tobytes())
    assert fast is not None
    np.testing.assert_array_equal(fast, img)


@settings(max_examples=60, deadline=None)
@given(
    h=st.integers(1, 12),
    w=st.integers(1, 12),
    seed=st.integers(0, 2**31),
    parts=st.integers(1, 3),
    data=st.data(),
)
def test_none_sub_and_up_rows_in_any_order_decode_exactly(h, w, seed, parts, data):
    img = np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)
    filters = data.draw(st.lists(st.integers(0, 2), min_size=h, max_size=h))
    text = chunk(b"tEXt", b"Software\x00test")
    encoded = png(img, filters, idat_parts=parts, extra=text)
    fast = decode_gray8(encoded)
    assert fast is not None
    np.testing.assert_array_equal(fast, img)
    np.testing.assert_array_equal(fast, opencv(encoded))


@pytest.mark.parametrize("pattern", ["none", "sub", "up", "mixed"])
def test_one_filter_on_every_row_and_mixed_rows_decode_exactly(pattern):
    img = np.random.default_rng(3).integers(0, 256, (40, 23), dtype=np.uint8)
    filters = {"none": [0] * 40, "sub": [1] * 40, "up": [2] * 40, "mixed": [0, 1, 2, 2, 1] * 8}[pattern]
    fast = decode_gray8(png(img, filters))
    assert fast is not None
    np.testing.assert_array_equal(fast, img)


@pytest.mark.parametrize("row", [0, PEEK_ROWS - 1, PEEK_ROWS, 39])
@pytest.mark.parametrize("kind", [3, 4])
def test_an_average_or_paeth_row_anywhere_is_left_to_opencv(kind, row):
    """Before and after the rows inflated first (`PEEK_ROWS`)."""
    img = np.random.default_rng(row).integers(0, 256, (40, 9), dtype=np.uint8)
    filters = [2] * 40
    filters[row] = kind
    encoded = png(img, filters)
    assert decode_gray8(encoded) is None
    np.testing.assert_array_equal(decode_image_bytes(encoded), img)


@pytest.mark.parametrize("kind", [3, 4])
def test_average_and_paeth_rows_are_left_to_opencv(kind):
    img = np.random.default_rng(kind).integers(0, 256, (6, 5), dtype=np.uint8)
    encoded = png(img, [2, kind, 2, 1, 0, 2])
    assert decode_gray8(encoded) is None
    np.testing.assert_array_equal(decode_image_bytes(encoded), img)


IMG = np.arange(48, dtype=np.uint8).reshape(6, 8) * 5
ROWS = filtered_rows(IMG, [2] * 6)


@pytest.mark.parametrize(
    "encoded",
    [
        pytest.param(png(IMG, header=(16, 0, 0, 0, 0)), id="16-bit"),
        pytest.param(png(IMG, header=(8, 2, 0, 0, 0)), id="colour"),
        pytest.param(png(IMG, header=(8, 0, 0, 0, 1)), id="interlaced"),
        pytest.param(png(IMG, extra=chunk(b"tRNS", b"\x00\x05")), id="transparency chunk"),
        pytest.param(png(IMG, extra=chunk(b"tEXt", b"a\x00b", crc=7)), id="bad CRC"),
        pytest.param(png(IMG, stream=zlib.compress(ROWS)[:-9]), id="cut stream"),
        pytest.param(png(IMG, stream=zlib.compress(ROWS) + b"xx"), id="trailing bytes"),
        pytest.param(png(IMG, stream=zlib.compress(ROWS[:-8])), id="rows short"),
        pytest.param(png(IMG, stream=zlib.compress(ROWS + b"\0")), id="rows long"),
        pytest.param(png(IMG, stream=b"not a zlib stream"), id="not zlib"),
        pytest.param(
            png(IMG, stream=zlib.compress(ROWS.replace(b"\x02", b"\x07", 1))),
            id="unknown filter",
        ),
        pytest.param(png(IMG)[:-12], id="no IEND"),
        pytest.param(split_idat(png(IMG, idat_parts=2)), id="IDATs not consecutive"),
        pytest.param(png(IMG)[:40], id="truncated"),
        pytest.param(b"\xff\xd8\xff\xe0 a JPEG", id="not PNG"),
    ],
)
def test_anything_else_is_left_to_opencv(encoded):
    assert decode_gray8(encoded) is None


@pytest.mark.parametrize(
    "extra",
    [
        pytest.param(chunk(b"gAMA", struct.pack(">I", 10_000)), id="gamma 0.1"),
        pytest.param(chunk(b"gAMA", struct.pack(">I", 1_000_000)), id="gamma 10"),
        pytest.param(chunk(b"sRGB", b"\x00"), id="sRGB"),
        pytest.param(
            chunk(b"cHRM", struct.pack(">8I", *[31270, 32900, 64000, 33000, 30000, 60000, 15000, 6000])),
            id="cHRM",
        ),
    ],
)
def test_colour_space_chunks_are_read_past_as_opencv_does(extra):
    """OpenCV does not apply gamma, sRGB intent or chromaticities: the stored values come out."""
    img = np.arange(256, dtype=np.uint8).reshape(16, 16)
    encoded = png(img, extra=extra)
    np.testing.assert_array_equal(opencv(encoded), img)
    fast = decode_gray8(encoded)
    assert fast is not None
    np.testing.assert_array_equal(fast, img)


def test_opencv_still_decodes_what_the_fast_path_leaves():
    """A 16-bit frame: stretched to 8 bits as before; a corrupt one: None, as before."""
    img16 = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 80).astype(np.uint16)
    ok, buf = cv2.imencode(".png", img16)
    assert ok and decode_gray8(buf.tobytes()) is None
    out = decode_image_bytes(buf.tobytes())
    assert out is not None and out.dtype == np.uint8 and out.max() == 255
    assert decode_image_bytes(png(IMG, stream=b"not a zlib stream")) is None
