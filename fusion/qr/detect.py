"""QR detection: decode every frame of a flight, refine the corners, cache the table.

    detect_image(image, backend)            one frame -> list[RawCode] (decoder corners + payload)
    detect_frame(image, camera, ...)        one frame -> list[QRDetection] with refined corners
    detect_frames(images, camera, ...)      several frames of one camera, refined together
    detect_flight(log, cache_path, ...)     every frame of cam0 / cam1 -> DetectionResult

Backends: "zxing" (zxing-cpp, default: fast, corners at the symbol's outer corners in whole
pixels) and "aruco" (OpenCV's QRCodeDetectorAruco).  Both give corners in CORNER_NAMES order
(symbol TL, TR, BR, BL, fixed by the finder patterns, so a code's rotation in the image is kept)
in OpenCV's pixel convention (pixel centres at integer coordinates).

Payloads are untrusted.  A payload that is not valid UTF-8 is dropped and counted
(`CameraStats.payloads_dropped`); any other text is returned as-is (classification into floor /
load / rejected is fusion.qr.codes' job).

Cache `detections.csv`: first line `# fusion-detections v<FORMAT_VERSION> fingerprint=<sha256>`,
second line `# meta <json>` (per-camera counts and skip messages), then a header row and one
CSV row per detection; its last field `corner_cov_px2` holds the 36 upper-triangle entries (row
by row) of the (8, 8) corner covariance, space-separated, or nothing when unknown.  The
fingerprint hashes the format version, the backend and refinement settings, each camera's
data.csv and sensor.yaml bytes, and the size and modification time (ns) of every image, so a
cache is recomputed when any image changes.  Payloads (untrusted) are stored spreadsheet-safe
(`fusion.fileio.csv_safe`, undone on reading).  `DetectionResult.cache_status` and a log
message say whether a run reused the cache.
"""

from __future__ import annotations

import copy
import csv
import hashlib
import io
import json
import logging
import math
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict

import cv2
import numpy as np
import zxingcpp

from fusion.camera import CameraModel
from fusion.errors import DetectionError
from fusion.fileio import atomic_open, csv_safe, csv_unsafe, open_regular
from fusion.parallel import keep_freed_memory, parallel_map, worker_count
from fusion.qr.refine import (
    FALLBACK_SIGMA_PX,
    POLISHED_CAMERAS,
    RefineStats,
    modules_for_version,
    refine_frames,
)
from fusion.qr.track import CodeTracker
from fusion.types import QRDetection

BACKENDS = ("zxing", "aruco")
FORMAT_VERSION = 5  # 5: `tracked` column; 4: payloads spreadsheet-safe; image sizes and mtimes in the key
CACHE_NAME = "detections.csv"
REFINE_METHOD = (
    # change when refine.py's output changes
    "finder-crossings+finder-model-homography+alignment+checks+dilation-3sigma+damped-widths+small-modules+front-pixel-polish/13"
)
CACHE_HEADER = (
    "camera",
    "timestamp_ns",
    "payload",
    "tl_x",
    "tl_y",
    "tr_x",
    "tr_y",
    "br_x",
    "br_y",
    "bl_x",
    "bl_y",
    "raw_tl_x",
    "raw_tl_y",
    "raw_tr_x",
    "raw_tr_y",
    "raw_br_x",
    "raw_br_y",
    "raw_bl_x",
    "raw_bl_y",
    "refined",
    "corner_sigma_px",
    "corner_cov_px2",
    "tracked",
)
_MAGIC = "# fusion-detections"
RAW_CORNER_SIGMA_PX = FALLBACK_SIGMA_PX  # decoder corners (refinement failed or self-check failed)
CACHE_REUSED, CACHE_WRITTEN, CACHE_STALE, CACHE_NONE = "reused", "written", "recomputed", "none"

logger = logging.getLogger(__name__)


class _ZxingOptions(TypedDict):
    """Keyword arguments of zxingcpp.read_barcodes that we set."""

    try_rotate: bool
    try_downscale: bool
    try_invert: bool
    binarizer: zxingcpp.Binarizer


# zxing-cpp options, measured on rendered 640x480 / 1280x720 frames (scripts/bench_detect.py):
# try_invert=False and try_downscale=False cost no decodes on our codes (dark on light, >= 3 px
# per module) and save ~40 % of the time; try_rotate only concerns 1-D symbologies; the
# GlobalHistogram binarizer is ~2x faster but lost 7-23 % of the codes, so LocalAverage stays.
ZXING_OPTIONS = _ZxingOptions(
    try_rotate=False, try_downscale=False, try_invert=False, binarizer=zxingcpp.Binarizer.LocalAverage
)
ZXING_FORMATS = zxingcpp.BarcodeFormats(zxingcpp.BarcodeFormat.QRCode)  # QR only (typed: BarcodeFormats)


@dataclass
class RawCode:
    """One decoded symbol as the decoder gave it."""

    payload: str
    corners_px: np.ndarray  # (4, 2) TL, TR, BR, BL (OpenCV pixel convention)
    modules: int | None  # modules per side when the decoder reports the version


@dataclass
class CameraStats:
    frames_total: int = 0
    frames_skipped: int = 0  # missing / unreadable images
    frames_with_code: int = 0  # frames with at least one kept detection
    detections: int = 0
    payloads_dropped: int = 0  # non-UTF-8 payloads (aruco: frames where OpenCV's decoder threw)
    refine_failed: int = 0  # detections whose corners stayed the decoder's (sum of the next five)
    # why (fusion.qr.refine.RefineStats): refinement's self-check failed on ...
    refine_low_contrast: int = 0  # ... edge contrast over noise
    refine_few_edges: int = 0  # ... share of finder edges usable
    refine_high_residual: int = 0  # ... edge-point misfit of the homography
    refine_far_from_decoder: int = 0  # ... corners far from the decoder's
    refine_unmeasurable: int = 0  # finder edges not measurable at all
    small_module_codes: int = 0  # refined codes under 1.25 px per module: corner sigma widened
    tracked: int = 0  # detections not decoded but tracked from earlier frames (fusion.qr.track)
    frames_with_tracked_only: int = 0  # frames whose only codes were tracked ones

    def add(self, other: CameraStats) -> None:
        for k in self.__dataclass_fields__:
            setattr(self, k, getattr(self, k) + getattr(other, k))


@dataclass
class DetectionResult:
    """Every detection of a flight; `stats[camera]` counts frames; `skipped` says why frames were
    skipped (file and line of data.csv)."""

    detections: list[QRDetection]
    stats: dict[str, CameraStats]
    skipped: list[str] = field(default_factory=list)
    backend: str = "zxing"
    from_cache: bool = False
    cache_status: str = CACHE_NONE  # reused | written (no cache) | recomputed (stale) | none

    def for_camera(self, camera: str) -> list[QRDetection]:
        return [d for d in self.detections if d.camera == camera]

    def by_frame(self, camera: str) -> dict[int, list[QRDetection]]:
        """timestamp_ns -> detections of that frame, in time order (frames without codes absent)."""
        out: dict[int, list[QRDetection]] = {}
        for d in self.detections:
            if d.camera == camera:
                out.setdefault(d.timestamp_ns, []).append(d)
        return dict(sorted(out.items()))


# ============================================================================ one image


def _payload_text(raw: bytes, fallback: str | None) -> str | None:
    try:
        return bytes(raw).decode("utf-8")
    except UnicodeDecodeError:
        return fallback


def _zxing(image: np.ndarray) -> tuple[list[RawCode], int]:
    codes, dropped = [], 0
    for b in zxingcpp.read_barcodes(image, formats=ZXING_FORMATS, **ZXING_OPTIONS):
        text = _payload_text(b.bytes, b.text if b.content_type == zxingcpp.ContentType.Text else None)
        if text is None:
            dropped += 1
            continue
        p = b.position
        # zxing's pixel corners are at integer coordinates: shift by half a pixel to OpenCV's
        corners = (
            np.array(
                [
                    [p.top_left.x, p.top_left.y],
                    [p.top_right.x, p.top_right.y],
                    [p.bottom_right.x, p.bottom_right.y],
                    [p.bottom_left.x, p.bottom_left.y],
                ],
                dtype=np.float64,
            )
            - 0.5
        )
        modules = None
        extra = b.extra  # a dict of symbology-specific facts (the stub says object)
        if isinstance(extra, dict):
            try:
                version = int(extra.get("Version", ""))
                if 1 <= version <= 40:
                    modules = modules_for_version(version)
            except (TypeError, ValueError):
                pass
        codes.append(RawCode(text, corners, modules))
    return codes, dropped


_ARUCO = None


def _aruco(image: np.ndarray) -> tuple[list[RawCode], int]:
    global _ARUCO
    if _ARUCO is None:
        _ARUCO = cv2.QRCodeDetectorAruco()
    try:
        ok, texts, points, _ = _ARUCO.detectAndDecodeMulti(image)
    except cv2.error:
        # OpenCV 5.0's decoder asserts on some malformed symbols ("idx < data.size()"):
        # the frame's codes are lost, counted as one dropped payload
        return [], 1
    if not ok or points is None:
        return [], 0
    codes = []
    for text, pts in zip(texts, points):
        if not text:  # located but not decoded
            continue
        # OpenCV's corners are the centres of the outermost module pixels, not the symbol's outer
        # edge; refinement moves them onto the edge.
        codes.append(RawCode(str(text), np.asarray(pts, dtype=np.float64).reshape(4, 2), None))
    # OpenCV decodes bytes to str itself; undecodable payloads come back empty and are not counted
    return codes, 0


_RECTIFY: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def _rectify_maps(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps from a fisheye (equidistant) image to the pinhole image of the same size and
    intrinsics; cached per camera."""
    key = camera.projection_key
    maps = _RECTIFY.get(key)
    if maps is None:
        u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
        xy = np.stack([(u - camera.cu) / camera.fu, (v - camera.cv) / camera.fv], axis=-1).reshape(-1, 2)
        uv = camera.project(np.column_stack([xy, np.ones(len(xy))])).reshape(camera.height, camera.width, 2)
        maps = cv2.convertMaps(uv[..., 0].astype(np.float32), uv[..., 1].astype(np.float32), cv2.CV_16SC2)
        _RECTIFY[key] = maps
    return maps


def _detect_rectified(image: np.ndarray, backend: str, camera: CameraModel) -> tuple[list[RawCode], int]:
    """`_detect_image` for a fisheye (equidistant) lens: decoders sample a code's modules through
    a homography, which a fisheye's curvature breaks (a rendered 0.2 m floor grid through Kalibr-like
    k1..k4 at 0.6 m: zxing read 1 code of 20 in view, 7 on the pinhole image of the same scene).
    The codes are decoded on the pinhole image of the same size and intrinsics, their corners
    mapped back into the fisheye image (where the refinement fits them through the lens model),
    and on the fisheye image itself for the periphery that pinhole image leaves out (a code read
    on both is taken once, from the pinhole image): on TUM VI's lens at 1280x960, 371 codes on
    the pinhole images, 360 on the fisheye ones, 424 together (BENCHMARKS.md)."""
    if image.shape[:2] != (camera.height, camera.width):
        return _detect_image(image, backend)
    m1, m2 = _rectify_maps(camera)
    pinhole = cv2.remap(image, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    codes, dropped = _detect_image(pinhole, backend)
    out = []
    for c in codes:
        xy = (c.corners_px - [camera.cu, camera.cv]) / [camera.fu, camera.fv]
        out.append(RawCode(c.payload, camera.project(np.column_stack([xy, np.ones(4)])), c.modules))
    seen = {c.payload for c in out}
    direct, dropped_direct = _detect_image(image, backend)
    out += [c for c in direct if c.payload not in seen]
    return out, max(dropped, dropped_direct)  # a foreign code read in both is one


def detect_image(image: np.ndarray, backend: str = "zxing") -> list[RawCode]:
    """Decode the QR codes of one (H, W) uint8 grey image; corners as the decoder gives them."""
    return _detect_image(image, backend)[0]


def _detect_image(image: np.ndarray, backend: str) -> tuple[list[RawCode], int]:
    if backend == "zxing":
        return _zxing(image)
    if backend == "aruco":
        return _aruco(image)
    raise DetectionError(f"unknown detection backend {backend!r}; expected one of {BACKENDS}")


def detect_frame(
    image: np.ndarray,
    camera_name: str = "",
    timestamp_ns: int = 0,
    camera: CameraModel | None = None,
    backend: str = "zxing",
    stats: CameraStats | None = None,
) -> list[QRDetection]:
    """Decode and refine one frame: QRDetections with `corners_px` refined (sub-pixel, see
    fusion.qr.refine), `corners_raw_px` as decoded, `corner_cov_px2` the refinement's calibrated
    (8, 8) corner covariance and `corner_sigma_px` the square root of its mean diagonal
    (RAW_CORNER_SIGMA_PX and no covariance when refinement failed).  `camera` (optional) makes
    the fits run in undistorted coordinates.  Counts go to `stats` when given."""
    return detect_frames([image], camera_name, [timestamp_ns], camera, backend, stats)[0]


def detect_frames(
    images: list[np.ndarray],
    camera_name: str = "",
    timestamps_ns=None,
    camera: CameraModel | None = None,
    backend: str = "zxing",
    stats: CameraStats | None = None,
    tracker: CodeTracker | None = None,
) -> list[list[QRDetection]]:
    """`detect_frame` for several frames of one camera: each decoded on its own, all their codes
    refined together (fusion.qr.refine.refine_frames: the array work is shared, ~2x cheaper per
    frame than one frame at a time).  Returns one list of detections per image.

    A code whose refinement fails its self-check keeps the decoder's corners with
    RAW_CORNER_SIGMA_PX (and that sigma squared times I_8 as covariance), counted by reason in
    `stats`.  With `tracker` (fusion.qr.track.CodeTracker, fed the frames in time order) codes
    decoded in earlier frames and not decoded in a frame are tracked into it (`tracked=True`).
    A camera named in POLISHED_CAMERAS (the front camera) has its sharp codes polished
    (fusion.qr.refine._polish)."""
    timestamps_ns = [0] * len(images) if timestamps_ns is None else list(timestamps_ns)
    if camera is not None and camera.equidistant:
        decoded = [_detect_rectified(image, backend, camera) for image in images]
    else:
        decoded = [_detect_image(image, backend) for image in images]
    rstats = RefineStats()
    refined_all = refine_frames(
        list(images),
        [[(c.corners_px, c.modules) for c in codes] for codes, _ in decoded],
        camera,
        stats=rstats,
        polish=camera_name in POLISHED_CAMERAS,
    )
    out = []
    for image, (codes, dropped), refined_frame, ts in zip(images, decoded, refined_all, timestamps_ns):
        dets = []
        for code, res in zip(codes, refined_frame):
            cov: np.ndarray | None
            if res is None:
                refined, sigma = code.corners_px.copy(), RAW_CORNER_SIGMA_PX
                cov = RAW_CORNER_SIGMA_PX**2 * np.eye(8)
            else:
                refined, sigma, cov = res.corners_px, res.corner_sigma_px, res.corner_cov_px2
            dets.append(
                QRDetection(camera_name, int(ts), code.payload, refined, code.corners_px, float(sigma), cov)
            )
        tracked = (
            []
            if tracker is None
            else tracker.step(image, camera_name, int(ts), dets, [c.modules for c in codes])
        )
        if stats is not None:
            stats.payloads_dropped += dropped
            stats.detections += len(dets) + len(tracked)
            stats.tracked += len(tracked)
            stats.frames_with_code += bool(dets or tracked)
            stats.frames_with_tracked_only += bool(tracked and not dets)
        out.append(dets + tracked)
    if stats is not None:
        stats.refine_low_contrast += rstats.low_contrast
        stats.refine_few_edges += rstats.few_edges
        stats.refine_high_residual += rstats.high_residual
        stats.refine_far_from_decoder += rstats.far_from_decoder
        stats.refine_unmeasurable += rstats.unmeasurable
        stats.small_module_codes += rstats.small_modules
        stats.refine_failed += rstats.fell_back + rstats.unmeasurable
    return out


REFINE_BATCH_FRAMES = 32
"""Frames refined together in a flight (a detection chunk's worth, `detect_flight`'s
chunk_frames): refinement's array work is shared by all codes of the batch, so its cost per
code falls with the batch's size; re-measured after refine.py's loops were reshaped
(scripts/bench_frontend_speed.py, BENCHMARKS.md): 32 frames cost 15-30 % less per frame
than 8 on a simulated flight (0.8 codes per frame) and ~30 % less on 4-code frames."""
TRACK_SEED_FRAMES = 8
"""Frames before a chunk that its tracker sees first (fusion.qr.track: a track lives through
TRACK_MAX_MISSES missed frames, so a few frames carry every live track across)."""


# ============================================================================ a whole flight


def _detect_chunk(
    context: tuple[dict, str, bool], task: tuple[str, int, int]
) -> tuple[str, list[QRDetection], CameraStats, list[str]]:
    """Frames [start, stop) of one camera, read from their paths in the calling process;
    `context` = ({camera name: CameraStream}, backend, track).  With `track`, the tracker is
    first run over the TRACK_SEED_FRAMES frames before `start` (their detections discarded), so
    chunks do not cut tracks."""
    streams, backend, track = context
    camera_name, start, stop = task
    keep_freed_memory()  # (fusion.parallel: refinement's temporaries ~35 % cheaper; pool and dask workers)
    stream = streams[camera_name]
    stats = CameraStats()
    skipped_before = len(stream.skipped)
    dets: list[QRDetection] = []
    tracker = CodeTracker(stream.camera) if track else None
    if tracker is not None and start > 0:
        seed = [(i, stream.load_image(i)) for i in range(max(0, start - TRACK_SEED_FRAMES), start)]
        seed = [(i, im) for i, im in seed if im is not None]
        if seed:
            detect_frames(
                [im for _, im in seed],
                camera_name,
                [int(stream.timestamps_ns[i]) for i, _ in seed],
                stream.camera,
                backend,
                None,
                tracker,
            )
        del stream.skipped[skipped_before:]  # (the seed frames' own chunk reports them)
    _prefetch(stream, start, stop)
    images, stamps = [], []
    for i in range(start, stop):
        stats.frames_total += 1
        image = stream.load_image(i)
        if image is None:
            stats.frames_skipped += 1
        else:
            images.append(image)
            stamps.append(int(stream.timestamps_ns[i]))
        if len(images) == REFINE_BATCH_FRAMES or (i == stop - 1 and images):
            for frame_dets in detect_frames(
                images, camera_name, stamps, stream.camera, backend, stats, tracker
            ):
                dets.extend(frame_dets)
            images, stamps = [], []
    skipped = stream.skipped[skipped_before:]
    del stream.skipped[skipped_before:]
    return camera_name, dets, stats, skipped


def _prefetch(stream, start: int, stop: int) -> None:
    """Ask the kernel to read the image files of frames [start, stop) ahead (posix_fadvise
    WILLNEED: asynchronous, the pages land in the page cache), so that a chunk's disk reads
    overlap its decoding instead of blocking before each frame (a flight's PNGs not read since
    they were written or copied: ~4.8 GB for the 10-minute flight).  Streams without files
    (bags, videos) and systems without posix_fadvise: nothing.  Never raises: the frame's own
    read reports any problem."""
    paths = getattr(stream, "paths", None)
    if paths is None or not hasattr(os, "posix_fadvise"):
        return
    for path in paths[start:stop]:
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # (non-blocking: a named pipe is not waited on)
        except OSError:
            continue
        try:
            if stat.S_ISREG(os.fstat(fd).st_mode):
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_WILLNEED)
        except OSError:
            pass
        finally:
            os.close(fd)


def flight_fingerprint(log, backend: str, track: bool = False) -> str:
    """sha256 over the cache format, backend, refinement, each camera's data.csv + sensor.yaml
    and the (size, mtime_ns) of each of its images (a stat per image: no image is read)."""
    h = hashlib.sha256()
    h.update(f"fusion-detections/{FORMAT_VERSION}/{backend}/{REFINE_METHOD}/track={int(track)}\n".encode())
    for name in sorted(log.cameras):
        cam_dir = Path(log.root) / "mav0" / name
        h.update(f"{name}\n".encode())
        if hasattr(log.cameras[name], "fingerprint"):  # bag / video streams (fusion.log)
            h.update(log.cameras[name].fingerprint())
            continue
        for fname in ("data.csv", "sensor.yaml"):
            try:
                with open_regular(cam_dir / fname, DetectionError, binary=True) as f:
                    h.update(hashlib.sha256(f.read()).digest())
            except (DetectionError, OSError):
                h.update(b"missing")
        for path in log.cameras[name].paths:
            try:
                st = os.stat(path)
                h.update(f"{st.st_size} {st.st_mtime_ns}\n".encode())
            except OSError:
                h.update(b"missing\n")
    return h.hexdigest()


def detect_flight(
    log,
    cache_path: Path | None = None,
    backend: str = "zxing",
    workers: int | None = None,
    progress: bool = True,
    chunk_frames: int = 32,
    track: bool = False,
) -> DetectionResult:
    """Detections of every frame of every camera of `log` (fusion.log.FlightLog).

    Frames are processed in parallel by `workers` processes (default: all cores; 1 = in this
    process), each reading its own images.  With `cache_path` (a `detections.csv`), a cache whose
    fingerprint matches is reused; a stale one (other data.csv / sensor.yaml / backend / format)
    is recomputed and overwritten; a malformed one raises DetectionError naming file and line.
    `track`: codes tracked through frames where they do not decode (fusion.qr.track; off by
    default; the pipeline's track pass, fusion.qr.predict, feeds it pose predictions instead).
    """
    if backend not in BACKENDS:
        raise DetectionError(f"unknown detection backend {backend!r}; expected one of {BACKENDS}")
    fingerprint = flight_fingerprint(log, backend, track)
    status = CACHE_NONE if cache_path is None else CACHE_WRITTEN
    if cache_path is not None and os.path.lexists(cache_path):
        cached = read_cache(cache_path, expected_fingerprint=fingerprint)
        if cached is not None:
            cached.backend = backend
            cached.cache_status = CACHE_REUSED
            logger.info(
                "detections reused from %s (same data.csv, sensor.yaml, image sizes and times, backend %s)",
                cache_path,
                backend,
            )
            return cached
        status = CACHE_STALE
        logger.info(
            "detection cache %s is stale (the log, its images or the settings changed): detecting again",
            cache_path,
        )
    streams = {name: log.cameras[name] for name in sorted(log.cameras)}
    tasks = detection_chunks(log, chunk_frames)
    n_frames = sum(len(s) for s in streams.values())
    workers = worker_count(workers)
    bar = _progress_bar(n_frames, progress)
    rows_text: list[str] | None = None if cache_path is None else []
    try:
        results = parallel_map(
            _detect_chunk_packed, tasks, workers, (streams, backend, track), preload=["fusion.qr.detect"]
        )
        parts = ((name, unpack_detections(dets), st, sk) for name, dets, st, sk in results)
        result = assemble_detections(log, _counted(parts, bar, rows_text), backend, status)
    finally:
        if bar is not None:
            bar.close()
    if cache_path is not None:
        write_cache(result, cache_path, fingerprint, rows_text)
    return result


def _detect_chunk_packed(context: tuple[dict, str, bool], task: tuple[str, int, int]):
    """`_detect_chunk` with its detections packed (`pack_detections`) for the trip back."""
    name, dets, stats, skipped = _detect_chunk(context, task)
    return name, pack_detections(dets), stats, skipped


# ============================================================================ transfer


@dataclass
class PackedDetections:
    """QRDetections as a few arrays, for sending between processes: pickling and unpickling a
    chunk's detections this way costs ~1/30 of the CPU of the objects (9,224 detections: 0.51
    vs 0.015 s, BENCHMARKS.md).  `unpack_detections` gives back equal detections, every
    array and number bit for bit (detections that do not fit the arrays exactly are sent as
    they are: `pack_detections`)."""

    cameras: list[str]
    timestamps_ns: np.ndarray  # (n,) int64
    payloads: list[str]
    corners_px: np.ndarray  # (n, 2, 4, 2) float64: refined corners, then the decoder's
    sigma_px: np.ndarray  # (n,) float64, NaN: None
    cov_index: np.ndarray  # (m,) int64: the detections with a covariance
    cov_px2: np.ndarray  # (m, 8, 8) float64
    tracked: np.ndarray  # (n,) bool


_INT64 = np.iinfo(np.int64)


def _packable(d: QRDetection) -> bool:
    """True when `d`'s fields survive the arrays exactly: float64 (4, 2) corners, a float64
    (8, 8) covariance or None, a finite Python float sigma or None, an int64 timestamp."""
    arrays = [d.corners_px, d.corners_raw_px] + ([] if d.corner_cov_px2 is None else [d.corner_cov_px2])
    sigma = d.corner_sigma_px
    shapes = [(4, 2), (4, 2), (8, 8)]
    return (
        all(
            isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == shape
            for a, shape in zip(arrays, shapes)
        )
        and (sigma is None or (type(sigma) is float and math.isfinite(sigma)))
        and type(d.timestamp_ns) is int
        and _INT64.min <= d.timestamp_ns <= _INT64.max
        and type(d.tracked) is bool
    )


def pack_detections(dets: list[QRDetection]) -> PackedDetections | list[QRDetection]:
    """`dets` as a PackedDetections, or the list itself when one of them does not fit exactly."""
    if not all(_packable(d) for d in dets):
        return dets
    n = len(dets)
    corners = np.empty((n, 2, 4, 2))
    for i, d in enumerate(dets):
        corners[i, 0] = d.corners_px
        corners[i, 1] = d.corners_raw_px
    cov_index = [i for i, d in enumerate(dets) if d.corner_cov_px2 is not None]
    return PackedDetections(
        [d.camera for d in dets],
        np.array([d.timestamp_ns for d in dets], dtype=np.int64),
        [d.payload for d in dets],
        corners,
        np.array([np.nan if d.corner_sigma_px is None else d.corner_sigma_px for d in dets], dtype=float),
        np.array(cov_index, dtype=np.int64),
        np.array([dets[i].corner_cov_px2 for i in cov_index], dtype=float).reshape(-1, 8, 8),
        np.array([d.tracked for d in dets], dtype=bool),
    )


def unpack_detections(packed: PackedDetections | list[QRDetection]) -> list[QRDetection]:
    """The detections of `pack_detections` (each array its own (4, 2) / (8, 8) slice)."""
    if not isinstance(packed, PackedDetections):
        return packed
    covs: list[np.ndarray | None] = [None] * len(packed.cameras)
    for i, cov in zip(packed.cov_index.tolist(), packed.cov_px2):
        covs[i] = cov
    sigmas = [None if math.isnan(s) else s for s in packed.sigma_px.tolist()]
    return [
        QRDetection(camera, t, payload, corners[0], corners[1], sigma, cov, tracked)
        for camera, t, payload, corners, sigma, cov, tracked in zip(
            packed.cameras,
            packed.timestamps_ns.tolist(),
            packed.payloads,
            packed.corners_px,
            sigmas,
            covs,
            packed.tracked.tolist(),
        )
    ]


PackedFrames = tuple[list[int], list[int], PackedDetections | list[QRDetection]]
"""{timestamp_ns: detections} as (keys, detections per key, packed detections)."""


def pack_frames(frames: dict[int, list[QRDetection]]) -> PackedFrames:
    """{timestamp_ns: detections} as (keys, detections per key, packed detections)."""
    keys = list(frames)
    return keys, [len(frames[k]) for k in keys], pack_detections([d for k in keys for d in frames[k]])


def unpack_frames(
    packed: tuple[list[int], list[int], PackedDetections | list],
) -> dict[int, list[QRDetection]]:
    """The {timestamp_ns: detections} of `pack_frames`, in the same order."""
    keys, sizes, dets = packed
    flat = unpack_detections(dets)
    bounds = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)]).tolist()
    return {k: flat[a:b] for k, a, b in zip(keys, bounds[:-1], bounds[1:])}


DetectionPart = tuple[str, list[QRDetection], CameraStats, list[str]]
"""One chunk's (camera, detections, counts, skip messages)."""


def detection_chunks(log, chunk_frames: int) -> list[tuple[str, int, int]]:
    """The flight's detection work as (camera, start, stop) frame ranges of at most
    `chunk_frames` frames, cameras in name order: `detect_chunk`'s tasks."""
    return [
        (name, s, min(s + chunk_frames, len(log.cameras[name])))
        for name in sorted(log.cameras)
        for s in range(0, len(log.cameras[name]), chunk_frames)
    ]


def detect_chunk(
    log, task: tuple[str, int, int], backend: str = "zxing", track: bool = False
) -> DetectionPart:
    """Detections of frames [start, stop) of one camera of `log` (task from `detection_chunks`),
    read here; a copy of the stream takes the skip messages, so tasks sharing `log` may run
    on threads."""
    name = task[0]
    stream = copy.copy(log.cameras[name])
    stream.skipped = []
    return _detect_chunk(({name: stream}, backend, track), task)


def assemble_detections(log, parts, backend: str, status: str = CACHE_WRITTEN) -> DetectionResult:
    """A flight's DetectionResult from its chunks' results (`detect_chunk`), given in
    `detection_chunks` order; each stream of `log` keeps its skip messages, as if it had been
    read here."""
    stats = {name: CameraStats() for name in sorted(log.cameras)}
    dets: list[QRDetection] = []
    skipped: list[tuple[str, str]] = []  # (camera, message)
    for name, chunk_dets, chunk_stats, chunk_skipped in parts:
        dets.extend(chunk_dets)
        stats[name].add(chunk_stats)
        skipped.extend((name, m) for m in chunk_skipped)
    for msg_cam, msg in skipped:
        log.cameras[msg_cam].skipped.append(msg)
    return DetectionResult(dets, stats, [m for _, m in skipped], backend, False, status)


def _counted(results, bar, rows_text: list[str] | None = None):
    """The parts, counted on the progress bar; with `rows_text`, each part's cache rows are
    formatted as it arrives (while the workers detect the next chunks, instead of all after)."""
    for part in results:
        if bar is not None:
            bar.update(part[2].frames_total)
        if rows_text is not None:
            rows_text.append(cache_rows_text(part[1]))
        yield part


def _progress_bar(total: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="detect", leave=False)


# ============================================================================ cache


CACHE_WRITE_ROWS = 4096
"""Detections formatted per block when `write_cache` formats them (rows are independent, so
the file is the same bytes for any block size)."""


def write_cache(
    result: DetectionResult, path: Path, fingerprint: str, rows_text: list[str] | None = None
) -> None:
    """Write `detections.csv` atomically (see the module docstring for the layout).  The numbers
    are formatted a column block at a time (`_cache_rows`), byte for byte as one at a time.
    `rows_text`: the detections' rows already formatted (`cache_rows_text` of each part of
    `result.detections`, in order), e.g. while detection ran."""
    meta = {
        "backend": result.backend,
        "stats": {k: vars(v) for k, v in sorted(result.stats.items())},
        "skipped": result.skipped,
    }
    with atomic_open(Path(path)) as f:
        f.write(f"{_MAGIC} v{FORMAT_VERSION} fingerprint={fingerprint}\n")
        f.write("# meta " + json.dumps(meta, ensure_ascii=True) + "\n")
        w = csv.writer(f, lineterminator="\n", quoting=csv.QUOTE_MINIMAL)
        w.writerow(CACHE_HEADER)
        if rows_text is None:
            # a block of rows at a time: the rows of a 30-minute flight's ~130,000 detections,
            # formatted at once, are ~0.3 GB of str objects (fusion batch's report task)
            dets = result.detections
            for start in range(0, len(dets), CACHE_WRITE_ROWS):
                w.writerows(_cache_rows(dets[start : start + CACHE_WRITE_ROWS]))
        else:
            f.writelines(rows_text)


def cache_rows_text(dets: list[QRDetection]) -> str:
    """The `detections.csv` rows of `dets` as text (what `write_cache` writes for them)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n", quoting=csv.QUOTE_MINIMAL).writerows(_cache_rows(dets))
    return buf.getvalue()


_TRIU = np.triu_indices(8)
_N_CORNER_VALUES = 8  # (4, 2) corners flattened


def _cache_rows(dets: list[QRDetection]) -> list[list[str]]:
    """The CSV rows of `dets`: every float as `repr` of the Python float (shortest text that
    reads back to the same double), converted for all detections at once (`tolist` + `map`:
    ~10x less CPU than a `repr(float(v))` per value on a 10-minute flight's 44k detections)."""
    if not dets:
        return []
    n = len(dets)
    corners = np.empty((n, _N_CORNER_VALUES))
    raw = np.empty((n, _N_CORNER_VALUES))
    for i, d in enumerate(dets):
        corners[i] = np.asarray(d.corners_px, dtype=float).reshape(-1)
        raw[i] = np.asarray(d.corners_raw_px, dtype=float).reshape(-1)
    # np.array_equal per detection: False when any value differs (or is NaN)
    refined = (corners != raw).any(axis=1).tolist()
    with_cov = [i for i, d in enumerate(dets) if d.corner_cov_px2 is not None]
    cov_text = [""] * n
    if with_cov:
        covs = np.stack([np.asarray(dets[i].corner_cov_px2, dtype=float).reshape(8, 8) for i in with_cov])
        for i, vals in zip(with_cov, covs[:, _TRIU[0], _TRIU[1]].tolist()):
            cov_text[i] = " ".join(map(repr, vals))
    rows = []
    for d, c, r, ref, cov in zip(dets, corners.tolist(), raw.tolist(), refined, cov_text):
        rows.append(
            [d.camera, str(int(d.timestamp_ns)), csv_safe(d.payload), *map(repr, c), *map(repr, r)]
            + [
                str(int(ref)),
                "" if d.corner_sigma_px is None else repr(float(d.corner_sigma_px)),
                cov,
                str(int(d.tracked)),
            ]
        )
    return rows


def _cov_parse(text: str, path: Path, lineno: int) -> np.ndarray | None:
    if not text:
        return None
    try:
        vals = np.array([float(v) for v in text.split()])
    except ValueError:
        raise DetectionError(f"{path}:{lineno}: corner_cov_px2 is not numbers") from None
    if vals.shape != (36,) or not np.all(np.isfinite(vals)):
        raise DetectionError(f"{path}:{lineno}: corner_cov_px2 needs 36 finite numbers")
    cov = np.zeros((8, 8))
    cov[_TRIU] = vals
    cov = cov + np.triu(cov, 1).T
    if np.any(np.diag(cov) <= 0):
        raise DetectionError(f"{path}:{lineno}: corner_cov_px2 has a non-positive variance")
    return cov


def read_cache(path: Path, expected_fingerprint: str | None = None) -> DetectionResult | None:
    """Read `detections.csv`.  Returns None when its fingerprint differs from
    `expected_fingerprint` (stale: recompute); raises DetectionError naming the file and line when
    it is malformed."""
    path = Path(path)
    with open_regular(path, DetectionError) as f:
        try:
            first = f.readline()
            if not first.startswith(_MAGIC + " "):
                raise DetectionError(f"{path}:1: not a fusion detection cache")
            fields = {
                key: value for key, _, value in (tok.partition("=") for tok in first[len(_MAGIC) :].split())
            }
            if f"v{FORMAT_VERSION}" not in fields:
                return None  # another format version: recompute
            if expected_fingerprint is not None and fields.get("fingerprint") != expected_fingerprint:
                return None
            second = f.readline()
            if not second.startswith("# meta "):
                raise DetectionError(f"{path}:2: missing '# meta' line")
            try:
                meta = json.loads(second[len("# meta ") :])
                stats = {
                    str(k): CameraStats(**{kk: int(vv) for kk, vv in v.items()})
                    for k, v in meta["stats"].items()
                }
                skipped = [str(m) for m in meta["skipped"]]
                backend = str(meta["backend"])
            except (ValueError, TypeError, KeyError, AttributeError):
                raise DetectionError(f"{path}:2: malformed '# meta' line") from None
            reader = csv.reader(f)
            dets: list[QRDetection] = []
            rows, lines = [], []
            for lineno, row in enumerate(reader, start=3):
                if lineno == 3:
                    if tuple(row) != CACHE_HEADER:
                        raise DetectionError(f"{path}:3: unexpected header")
                    continue
                rows.append(row)
                lines.append(reader.line_num + 2)
                if len(rows) == CACHE_READ_ROWS:
                    dets += _cache_block(rows, lines, path)
                    rows, lines = [], []
            dets += _cache_block(rows, lines, path)
        except UnicodeDecodeError:
            raise DetectionError(f"{path}: not UTF-8 text") from None
        except csv.Error as e:
            raise DetectionError(f"{path}: malformed CSV ({e})") from None
    return DetectionResult(dets, stats, skipped, backend, True, CACHE_REUSED)


CACHE_READ_ROWS = 1024
"""detections.csv is converted this many rows at a time: its rows as lists of text took ~7 kB a
detection while they were converted, the detections ~1.3 kB (a 2-minute flight's 9,224 read at
once: 64.6 MB traced peak, 11.8 MB kept; 1,024 at a time: 17.8 MB peak; BENCHMARKS.md)."""


def _cache_block(rows: list[list[str]], lines: list[int], path: Path) -> list[QRDetection]:
    """The detections of consecutive cache rows (their line numbers `lines`)."""
    dets = _cache_dets(rows)
    if dets is None:  # something is malformed: the row-by-row reader names its line
        dets = [_cache_row(row, path, lineno) for row, lineno in zip(rows, lines)]
    return dets


_CACHE_CAMERAS = ("cam0", "cam1")
_COV_TEXT_COLUMN, _SIGMA_COLUMN, _TRACKED_COLUMN = 21, 20, 22


def _cache_dets(rows: list[list[str]]) -> list[QRDetection] | None:
    """The detections of well-formed cache rows, converted a column block at a time (the same
    `float` / `int` parsing as `_cache_row`, so the same doubles); None when any row breaks a
    rule of `_cache_row` (which then names the line)."""
    n = len(rows)
    if n == 0:
        return []
    n_fields = len(CACHE_HEADER)
    if any(len(row) != n_fields for row in rows):
        return None
    try:
        stamps = list(map(int, (row[1] for row in rows)))
        corner_vals = np.array(list(map(float, (v for row in rows for v in row[3:19]))), dtype=float).reshape(
            n, 2, 4, 2
        )
        sigma_text = [row[_SIGMA_COLUMN] for row in rows]
        sigmas = [float(t) if t else None for t in sigma_text]
        cov_rows = [i for i, row in enumerate(rows) if row[_COV_TEXT_COLUMN]]
        cov_tokens = [rows[i][_COV_TEXT_COLUMN].split() for i in cov_rows]
        if any(len(tok) != len(_TRIU[0]) for tok in cov_tokens):
            return None
        cov_vals = np.array(list(map(float, (v for tok in cov_tokens for v in tok))), dtype=float)
    except ValueError:
        return None
    if min(stamps) < 0 or not np.all(np.isfinite(corner_vals)):
        return None
    if any(row[0] not in _CACHE_CAMERAS or row[_TRACKED_COLUMN] not in ("0", "1") for row in rows):
        return None
    if any(s is not None and not (math.isfinite(s) and s > 0) for s in sigmas):
        return None
    covs: list[np.ndarray | None] = [None] * n
    if cov_rows:
        upper = cov_vals.reshape(len(cov_rows), len(_TRIU[0]))
        if not np.all(np.isfinite(upper)):
            return None
        full = np.zeros((len(cov_rows), 8, 8))
        full[:, _TRIU[0], _TRIU[1]] = upper
        full = full + np.triu(full, 1).transpose(0, 2, 1)  # (as _cov_parse: cov + triu(cov, 1).T)
        if np.any(np.diagonal(full, axis1=1, axis2=2) <= 0):
            return None
        for i, cov in zip(cov_rows, full):
            covs[i] = cov
    return [
        QRDetection(
            row[0],
            t,
            csv_unsafe(row[2]),
            corner_vals[i, 0],
            corner_vals[i, 1],
            sigma,
            covs[i],
            row[_TRACKED_COLUMN] == "1",
        )
        for i, (row, t, sigma) in enumerate(zip(rows, stamps, sigmas))
    ]


def _cache_row(row: list[str], path: Path, lineno: int) -> QRDetection:
    if len(row) != len(CACHE_HEADER):
        raise DetectionError(f"{path}:{lineno}: expected {len(CACHE_HEADER)} fields, found {len(row)}")
    camera, ts, payload = row[0], row[1], csv_unsafe(row[2])
    try:
        t = int(ts)
        vals = [float(v) for v in row[3:19]]
    except ValueError:
        raise DetectionError(f"{path}:{lineno}: a timestamp or corner is not a number") from None
    if t < 0 or not all(math.isfinite(v) for v in vals):
        raise DetectionError(f"{path}:{lineno}: negative timestamp or non-finite corner")
    if camera not in ("cam0", "cam1"):
        raise DetectionError(f"{path}:{lineno}: unknown camera {camera[:20]!r}")
    corners = np.array(vals[:8]).reshape(4, 2)
    raw = np.array(vals[8:]).reshape(4, 2)
    sigma = None
    if row[20]:
        try:
            sigma = float(row[20])
        except ValueError:
            raise DetectionError(f"{path}:{lineno}: corner_sigma_px is not a number") from None
        if not (math.isfinite(sigma) and sigma > 0):
            raise DetectionError(f"{path}:{lineno}: corner_sigma_px must be positive and finite")
    if row[22] not in ("0", "1"):
        raise DetectionError(f"{path}:{lineno}: tracked must be 0 or 1")
    return QRDetection(
        camera, t, payload, corners, raw, sigma, _cov_parse(row[21], path, lineno), row[22] == "1"
    )
