"""The detect stage's plumbing outside the per-frame work (issue 13 item 2): the detections.csv
cache written and read a column block at a time gives the same bytes and the same doubles as
one value at a time; rows formatted while detection runs equal the rows written after; image
prefetching never fails; the forkserver preloads the package's imported modules."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
import pickle
import sys

import numpy as np
import pytest

from fusion.errors import DetectionError
from fusion.fileio import csv_safe
from fusion.log import read_flight
from fusion.parallel import _preload_modules, parallel_map
from fusion.qr import detect as detect_module
from fusion.qr.detect import (
    _MAGIC,
    CACHE_HEADER,
    FORMAT_VERSION,
    CameraStats,
    DetectionResult,
    PackedDetections,
    _cache_row,
    _prefetch,
    cache_rows_text,
    detect_flight,
    pack_detections,
    pack_frames,
    read_cache,
    unpack_detections,
    unpack_frames,
    write_cache,
)
from fusion.types import QRDetection
from tests.test_detect import _write_flight

_TRIU = np.triu_indices(8)


def _reference_write(result: DetectionResult, path, fingerprint: str) -> None:
    """detections.csv as write_cache wrote it before (one repr(float(v)) per value)."""
    meta = {
        "backend": result.backend,
        "stats": {k: vars(v) for k, v in sorted(result.stats.items())},
        "skipped": result.skipped,
    }
    with open(path, "w", encoding="utf-8", newline="") as f:
        f.write(f"{_MAGIC} v{FORMAT_VERSION} fingerprint={fingerprint}\n")
        f.write("# meta " + json.dumps(meta, ensure_ascii=True) + "\n")
        w = csv.writer(f, lineterminator="\n", quoting=csv.QUOTE_MINIMAL)
        w.writerow(CACHE_HEADER)
        for d in result.detections:
            cov = d.corner_cov_px2
            w.writerow(
                [d.camera, str(int(d.timestamp_ns)), csv_safe(d.payload)]
                + [repr(float(v)) for v in np.asarray(d.corners_px).reshape(-1)]
                + [repr(float(v)) for v in np.asarray(d.corners_raw_px).reshape(-1)]
                + [
                    str(int(not np.array_equal(d.corners_px, d.corners_raw_px))),
                    "" if d.corner_sigma_px is None else repr(float(d.corner_sigma_px)),
                    ""
                    if cov is None
                    else " ".join(repr(float(v)) for v in np.asarray(cov, dtype=float).reshape(8, 8)[_TRIU]),
                    str(int(d.tracked)),
                ]
            )


def _random_detections(seed: int, n: int) -> list[QRDetection]:
    """Detections with every kind of field: no covariance, no sigma, tracked, raw = refined,
    float32 corners, payloads a spreadsheet or the CSV quoting would touch, tiny and huge values."""
    rng = np.random.default_rng(seed)
    payloads = ["0/1/2", "1/box-7", "=cmd", "'quoted", 'has "quotes", and commas', "multi\nline", "ü-ß"]
    out = []
    for i in range(n):
        corners = rng.uniform(-5.0, 700.0, (4, 2)) * 10.0 ** rng.integers(-12, 12)
        raw = corners.copy() if i % 5 == 0 else np.round(corners + rng.normal(0.0, 1.0, (4, 2)))
        if i % 7 == 3:
            corners = corners.astype(np.float32)
        a = rng.normal(0.0, 1.0, (8, 8))
        cov = None if i % 4 == 1 else a @ a.T + 1e-3 * np.eye(8)
        sigma = None if i % 6 == 2 else float(rng.uniform(1e-4, 3.0))
        out.append(
            QRDetection(
                "cam0" if i % 3 else "cam1",
                int(rng.integers(0, 2**62)),
                payloads[i % len(payloads)],
                corners,
                raw,
                sigma,
                cov,
                bool(i % 8 == 5),
            )
        )
    return out


def _result(dets) -> DetectionResult:
    return DetectionResult(dets, {"cam0": CameraStats(frames_total=3)}, ["x.png: missing"])


@pytest.mark.parametrize("seed, n", [(0, 0), (1, 1), (2, 57)])
def test_cache_bytes_equal_the_value_by_value_writer(tmp_path, seed, n):
    result = _result(_random_detections(seed, n))
    write_cache(result, tmp_path / "new.csv", "f" * 64)
    _reference_write(result, tmp_path / "old.csv", "f" * 64)
    assert (tmp_path / "new.csv").read_bytes() == (tmp_path / "old.csv").read_bytes()
    # rows formatted part by part (as detect_flight does while the workers run) give the same file
    parts = [result.detections[a : a + 10] for a in range(0, n, 10)]
    write_cache(result, tmp_path / "parts.csv", "f" * 64, [cache_rows_text(p) for p in parts])
    assert (tmp_path / "parts.csv").read_bytes() == (tmp_path / "old.csv").read_bytes()


@pytest.mark.parametrize("block", [1, 7, 57, 58])
def test_cache_written_in_blocks_equals_the_value_by_value_writer(tmp_path, monkeypatch, block):
    result = _result(_random_detections(4, 57))
    _reference_write(result, tmp_path / "old.csv", "f" * 64)
    monkeypatch.setattr(detect_module, "CACHE_WRITE_ROWS", block)
    write_cache(result, tmp_path / "new.csv", "f" * 64)
    assert (tmp_path / "new.csv").read_bytes() == (tmp_path / "old.csv").read_bytes()


def test_cache_read_equals_the_row_by_row_reader_bit_for_bit(tmp_path):
    dets = _random_detections(3, 80)
    path = tmp_path / "detections.csv"
    write_cache(_result(dets), path, "f" * 64)
    back = read_cache(path, "f" * 64)
    assert back is not None and len(back.detections) == len(dets)
    rows = list(csv.reader(io.StringIO(path.read_text(encoding="utf-8"))))[3:]
    slow = [_cache_row(row, path, 0) for row in rows]
    for d, b, s in zip(dets, back.detections, slow):
        for x in (b, s):
            assert (x.camera, x.timestamp_ns, x.payload, x.tracked) == (
                d.camera,
                d.timestamp_ns,
                d.payload,
                d.tracked,
            )
            assert x.corners_px.shape == (4, 2) and x.corners_raw_px.shape == (4, 2)
            assert x.corners_px.tobytes() == np.asarray(d.corners_px, dtype=float).tobytes()
            assert x.corners_raw_px.tobytes() == d.corners_raw_px.tobytes()
            assert x.corner_sigma_px == d.corner_sigma_px
        assert b.corners_px.tobytes() == s.corners_px.tobytes()
        if d.corner_cov_px2 is None:
            assert b.corner_cov_px2 is None and s.corner_cov_px2 is None
        else:
            # the cache keeps the upper triangle: what comes back is its symmetric completion
            assert b.corner_cov_px2.tobytes() == s.corner_cov_px2.tobytes()
            np.testing.assert_array_equal(np.triu(b.corner_cov_px2), np.triu(d.corner_cov_px2))
            np.testing.assert_array_equal(b.corner_cov_px2, b.corner_cov_px2.T)


@pytest.mark.parametrize(
    "column, value, message",
    [
        (1, "-3", "negative timestamp"),
        (1, "12x", "not a number"),
        (5, "inf", "non-finite"),
        (0, "cam9", "unknown camera"),
        (20, "-0.1", "corner_sigma_px must be positive"),
        (22, "2", "tracked must be 0 or 1"),
        (21, "1 2 3", "corner_cov_px2 needs 36"),
    ],
)
def test_a_malformed_row_among_good_ones_is_named_by_its_line(tmp_path, column, value, message):
    dets = [d for d in _random_detections(4, 12) if d.corner_cov_px2 is not None and d.corner_sigma_px]
    path = tmp_path / "detections.csv"
    write_cache(_result(dets), path, "f" * 64)
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    rows = list(csv.reader(io.StringIO("".join(lines[3:]))))
    bad = 4  # 0-based among the rows: file line 3 (header) + 1 + 4 = 8 when no row spans lines
    assert all("\n" not in d.payload for d in dets[: bad + 1])
    rows[bad][column] = value
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    path.write_text("".join(lines[:3]) + buf.getvalue(), encoding="utf-8")
    with pytest.raises(DetectionError, match=rf"detections\.csv:8: .*{message}"):
        read_cache(path)


@pytest.mark.parametrize("block", [1, 7, 80, 81])
def test_cache_read_in_blocks_equals_the_cache_read_at_once(tmp_path, monkeypatch, block):
    dets = _random_detections(5, 80)
    path = tmp_path / "detections.csv"
    write_cache(_result(dets), path, "f" * 64)
    whole = read_cache(path)
    monkeypatch.setattr(detect_module, "CACHE_READ_ROWS", block)
    back = read_cache(path)
    assert whole is not None and back is not None and len(back.detections) == len(dets) == 80
    for a, b in zip(whole.detections, back.detections):
        assert (a.camera, a.timestamp_ns, a.payload, a.tracked, a.corner_sigma_px) == (
            b.camera,
            b.timestamp_ns,
            b.payload,
            b.tracked,
            b.corner_sigma_px,
        )
        assert a.corners_px.tobytes() == b.corners_px.tobytes()
        assert a.corners_raw_px.tobytes() == b.corners_raw_px.tobytes()
        assert (a.corner_cov_px2 is None) == (b.corner_cov_px2 is None)
        if a.corner_cov_px2 is not None:
            assert a.corner_cov_px2.tobytes() == b.corner_cov_px2.tobytes()
    assert (back.stats, back.skipped, back.backend) == (whole.stats, whole.skipped, whole.backend)


def test_a_malformed_row_in_a_later_block_is_named_by_its_line(tmp_path, monkeypatch):
    dets = [d for d in _random_detections(6, 40) if "\n" not in d.payload]
    path = tmp_path / "detections.csv"
    write_cache(_result(dets), path, "f" * 64)
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    bad = 13  # 0-based: file line 14, the 11th row (after 3 header lines), first of the third block of 5
    fields = next(csv.reader([lines[bad]]))
    fields[1] = "-3"
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(fields)
    lines[bad] = buf.getvalue()
    path.write_text("".join(lines), encoding="utf-8")
    monkeypatch.setattr(detect_module, "CACHE_READ_ROWS", 5)
    with pytest.raises(DetectionError, match=r"detections\.csv:14: negative timestamp"):
        read_cache(path)


def test_prefetch_ignores_missing_and_special_files(tmp_path):
    regular = tmp_path / "a.png"
    regular.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)

    class Stream:
        paths = [regular, tmp_path / "missing.png", fifo, tmp_path]

    _prefetch(Stream(), 0, 4)  # no exception, no blocking on the named pipe
    _prefetch(object(), 0, 4)  # a stream without files (bag, video): nothing


def test_detect_flight_cache_is_what_write_cache_writes(tmp_path):
    root = _write_flight(tmp_path / "log", n0=4)
    for workers in (1, 2):
        cache = tmp_path / f"out{workers}" / "detections.csv"
        res = detect_flight(read_flight(root), cache, workers=workers, progress=False, chunk_frames=1)
        _reference_write(res, tmp_path / "ref.csv", cache.read_text().split("fingerprint=")[1].split()[0])
        assert cache.read_bytes() == (tmp_path / "ref.csv").read_bytes()
    assert (tmp_path / "out1" / "detections.csv").read_bytes() == (
        tmp_path / "out2" / "detections.csv"
    ).read_bytes()


def test_forkserver_preload_lists_the_callers_modules_then_the_package():
    mods = _preload_modules(["fusion.qr.detect", "json"])
    assert mods[:2] == ["fusion.qr.detect", "json"]
    assert len(mods) == len(set(mods))
    imported = {m for m in sys.modules if m == "fusion" or m.startswith("fusion.")}
    assert imported <= set(mods)
    assert all(m.startswith("fusion") for m in mods[2:])


def _modules_in_worker(context, task):
    return "fusion.qr.detect" in sys.modules


def test_workers_start_with_the_preloaded_modules():
    assert (
        list(parallel_map(_modules_in_worker, [0, 1, 2], 2, None, preload=["fusion.qr.detect"])) == [True] * 3
    )


def _same_detection(a: QRDetection, b: QRDetection) -> bool:
    arrays_equal = all(
        type(x) is type(y) and (x is None or (x.dtype == y.dtype and x.tobytes() == y.tobytes()))
        for x, y in [
            (a.corners_px, b.corners_px),
            (a.corners_raw_px, b.corners_raw_px),
            (a.corner_cov_px2, b.corner_cov_px2),
        ]
    )
    fields = (a.camera, a.timestamp_ns, a.payload, a.corner_sigma_px, a.tracked)
    other = (b.camera, b.timestamp_ns, b.payload, b.corner_sigma_px, b.tracked)
    return arrays_equal and fields == other and [type(v) for v in fields] == [type(v) for v in other]


def test_packed_detections_round_trip_bit_for_bit_through_pickle():
    dets = [d for d in _random_detections(5, 60) if d.corners_px.dtype == np.float64]
    packed = pack_detections(dets)
    assert isinstance(packed, PackedDetections)
    back = unpack_detections(pickle.loads(pickle.dumps(packed, protocol=pickle.HIGHEST_PROTOCOL)))
    assert len(back) == len(dets) and all(_same_detection(a, b) for a, b in zip(dets, back))
    assert unpack_detections(pack_detections([])) == []


@pytest.mark.parametrize(
    "change",
    [
        {"corners_px": np.zeros((4, 2), np.float32)},
        {"corner_sigma_px": np.float64(0.2)},
        {"corner_sigma_px": float("nan")},
        {"timestamp_ns": np.int64(5)},
        {"corner_cov_px2": np.eye(4)},
    ],
)
def test_a_detection_the_arrays_cannot_hold_exactly_is_sent_as_it_is(change):
    dets = [d for d in _random_detections(6, 5) if d.corners_px.dtype == np.float64]
    dets[1] = dataclasses.replace(dets[1], **change)
    assert pack_detections(dets) is dets and unpack_detections(dets) is dets


def test_packed_frames_keep_keys_order_and_grouping():
    dets = [d for d in _random_detections(7, 40) if d.corners_px.dtype == np.float64]
    frames = {1000 + 7 * k: dets[a:b] for k, (a, b) in enumerate([(0, 3), (3, 4), (4, 20), (20, 40)])}
    frames = dict(reversed(list(frames.items())))  # any key order is kept
    back = unpack_frames(pickle.loads(pickle.dumps(pack_frames(frames))))
    assert list(back) == list(frames)
    assert all(len(back[k]) == len(v) and all(map(_same_detection, v, back[k])) for k, v in frames.items())
    assert unpack_frames(pack_frames({})) == {}
