"""EuRoC / ASL flight-log reader and writer (DESIGN.md "Flight-log layout").

    <flight>/world.yaml
    <flight>/mav0/cam0/{data.csv, data/<ns>.png, sensor.yaml}    floor camera
    <flight>/mav0/cam1/...                                        front camera (optional)
    <flight>/mav0/imu0/{data.csv, sensor.yaml}                    IMU (optional)
    <flight>/mav0/vel0/{data.csv, sensor.yaml}                    body-frame velocity (optional)
    <flight>/mav0/state_groundtruth_estimate0/data.csv            ground truth (optional)
    <flight>/loads_groundtruth.csv                                id,x_m,y_m,z_m (optional)
    <flight>/blackouts_groundtruth.csv                            start_ns,end_ns,kind (optional;
                                                                  simulator: intervals with no
                                                                  readable floor code by design)

The reader is defensive: every malformed row raises LogError naming the file and line; a frame
whose image is missing or unreadable (a symbolic link loop too) is skipped, counted and reported
(`CameraStream.skipped`); a stream folder (`mav0/cam1`, ...) or a camera's `data` folder that is
a file, a dangling link or a link loop is an error naming it, not an absent stream.
Images are streamed, never all held in memory; an image's size is read from its header and
checked against sensor.yaml before it is decoded.  Only regular files are opened (a named pipe
would hang the reader).  After reading, plausibility checks look for unit and clock mistakes
(`check_log`): certain ones raise LogError, the others become `FlightLog.warnings`.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import math
import os
import re
import shutil
import struct
from array import array
from collections.abc import Iterator
from dataclasses import astuple, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fusion.camera import SENSOR_YAML_KEYS, CameraModel, coefficient_count, read_T_BS, unknown_sensor_keys
from fusion.errors import CameraModelError, LogError, WorldError
from fusion.fileio import (
    FLIGHT_LOG_WRITERS,
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    atomic_open,
    csv_safe,
    csv_unsafe,
    dump_yaml,
    load_yaml,
    manifest_writer,
    open_regular,
    pid_alive,
    read_manifest,
    remove_listed,
    strict_float,
    strict_floats,
)
from fusion.geometry import R_from_quat_wxyz
from fusion.log.png import PNG_SIGNATURE, decode_gray8
from fusion.world import World

CAMERA_NAMES = ("cam0", "cam1")
IMU_HEADER = (
    "#timestamp [ns]",
    "w_RS_S_x [rad s^-1]",
    "w_RS_S_y [rad s^-1]",
    "w_RS_S_z [rad s^-1]",
    "a_RS_S_x [m s^-2]",
    "a_RS_S_y [m s^-2]",
    "a_RS_S_z [m s^-2]",
)
VEL_HEADER = ("#timestamp [ns]", "v_RS_S_x [m s^-1]", "v_RS_S_y [m s^-1]", "v_RS_S_z [m s^-1]")
GT_HEADER = (
    "#timestamp",
    " p_RS_R_x [m]",
    " p_RS_R_y [m]",
    " p_RS_R_z [m]",
    " q_RS_w []",
    " q_RS_x []",
    " q_RS_y []",
    " q_RS_z []",
    " v_RS_R_x [m s^-1]",
    " v_RS_R_y [m s^-1]",
    " v_RS_R_z [m s^-1]",
    " b_w_RS_S_x [rad s^-1]",
    " b_w_RS_S_y [rad s^-1]",
    " b_w_RS_S_z [rad s^-1]",
    " b_a_RS_S_x [m s^-2]",
    " b_a_RS_S_y [m s^-2]",
    " b_a_RS_S_z [m s^-2]",
)
LOADS_HEADER = ("id", "x_m", "y_m", "z_m")
BLACKOUTS_HEADER = ("#start_ns", "end_ns", "kind")
INT64_MAX = 2**63 - 1
_DIGITS = re.compile(r"[0-9]+")

# plausibility limits (check_log)
GRAVITY_M_S2 = 9.80665
ACCEL_NORM_RANGE_M_S2 = (7.0, 12.5)  # median |specific force| of a flying or resting drone
ACCEL_IN_G_RANGE = (0.7, 1.3)  # the same median when the accelerometer reports g
IMU_GAP_WARN_S = 0.05
"""IMU samples further apart than this are a gap (fusion.estimate.common.FusionConfig's
max_imu_gap_s default): the back ends bridge it with a weak random walk, so the fused poses there
rest on the cameras alone; a counted warning (`imu_gaps`)."""
GYRO_MAX_PLAUSIBLE_RAD_S = 8.7  # 500 deg/s: beyond any warehouse flight's 99th percentile
GYRO_NOISE_RATIO_SUSPECT = 30.0  # measured / stated white noise (deg/s: 57x; rotor vibration
# and conservative Kalibr densities stay well below)
GRAVITY_MAX_TILT_DEG = 60.0
"""The median specific force, turned into the body frame (FLU: z up) by imu0's T_BS, points up
within this angle on any multirotor flight (it hovers and cruises within ~30 deg of level); beyond
it the IMU's axes are not what T_BS says (`imu_gravity_axis`: an FRD / NED IMU read as FLU gave
the audit's EKF 2 cm off, 18 cm at worst, with health ok and no warning naming the axes)."""
SATURATION_MIN_SAMPLES = 10  # repeats of an axis' extreme value that mean clipping
SATURATION_MIN_FRACTION = 0.005
RATE_MISMATCH_FACTOR = 1.5  # measured vs sensor.yaml rate_hz (Kalibr imu.yaml: update_rate)
UNIT_MATCH_DECADES = 0.3  # |log10(ratio) - 3k| below this: a factor 1000^k (units)
MIN_PLAUSIBLE_DT_NS = 100_000  # faster than 10 kHz: timestamps are not nanoseconds
CLOCK_OFFSET_MAX_S = 0.5  # streams shifted by more than this: a clock offset
T_BS_MAX_TRANSLATION_M = 1.0  # a sensor farther than this from the IMU: millimetres?
QUAT_NORM_TOLERANCE = 1e-3  # ground-truth quaternions further from unit: renormalised
QUAT_NORM_MIN = 1e-6  # below this a quaternion is no rotation at all
IMAGE_HEADER_BYTES = 64 * 1024  # enough to reach a JPEG's frame header (after EXIF)
PARTIAL_MARKER = ".fusion-partial"  # inside `<log>.partial/`: written by FlightLogWriter
LOG_CONFLICT_NAMES = ("world.yaml", "loads_groundtruth.csv", "blackouts_groundtruth.csv", "mav0")


# ============================================================================ records


@dataclass
class LogWarning:
    """A named, counted problem of a flight log that does not stop the run (e.g. a suspected
    unit mistake); `count` is how many rows / streams / files it concerns."""

    name: str
    count: int
    message: str

    def to_dict(self) -> dict:
        return {"name": self.name, "count": int(self.count), "message": self.message}

    def __str__(self) -> str:
        return f"[{self.name}] x{self.count}: {self.message}"


@dataclass
class ImuNoise:
    """Continuous-time IMU noise as in Kalibr's imu.yaml (units per sqrt(Hz))."""

    gyroscope_noise_density: float = 1.7e-4  # rad / s / sqrt(Hz)
    gyroscope_random_walk: float = 1.9e-5  # rad / s^2 / sqrt(Hz)
    accelerometer_noise_density: float = 2.0e-3  # m / s^2 / sqrt(Hz)
    accelerometer_random_walk: float = 3.0e-3  # m / s^3 / sqrt(Hz)

    def scaled(self, k: float) -> ImuNoise:
        """Every density and random walk times k (sigmas: a variance factor's square root)."""
        return ImuNoise(*(k * v for v in astuple(self)))


@dataclass
class ImuData:
    """IMU samples in the IMU frame S; `T_body_imu` is its T_BS (identity when B is the IMU)."""

    timestamps_ns: np.ndarray  # (N,) int64
    gyro_rad_s: np.ndarray  # (N, 3) angular rate w_RS_S
    accel_m_s2: np.ndarray  # (N, 3) specific force a_RS_S (gravity included)
    noise: ImuNoise = field(default_factory=ImuNoise)
    T_body_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    rate_hz: float = 200.0


@dataclass
class VelocityData:
    """Body-frame velocity (e.g. optical flow + range), `noise_m_s` per axis (1 sigma)."""

    timestamps_ns: np.ndarray  # (N,)
    v_body_m_s: np.ndarray  # (N, 3)
    noise_m_s: float = 0.05


@dataclass
class GroundTruth:
    """EuRoC ground truth: body pose in W, world velocity, IMU biases."""

    timestamps_ns: np.ndarray  # (N,)
    p_world: np.ndarray  # (N, 3)
    q_world_body_wxyz: np.ndarray  # (N, 4)
    v_world: np.ndarray  # (N, 3)
    bias_gyro: np.ndarray  # (N, 3)
    bias_accel: np.ndarray  # (N, 3)

    @property
    def T_world_body(self) -> np.ndarray:
        """(N, 4, 4)."""
        return self.T_world_body_rows(slice(None))

    def T_world_body_rows(self, rows: slice | np.ndarray) -> np.ndarray:
        """(n, 4, 4) of the rows `rows` (a slice or indices) only, each the same as in
        T_world_body (the whole flight's are 128 bytes a row: ~46 MB for 30 minutes at 200 Hz)."""
        q = self.q_world_body_wxyz[rows]
        T = np.tile(np.eye(4), (len(q), 1, 1))
        T[:, :3, :3] = R_from_quat_wxyz(q)
        T[:, :3, 3] = self.p_world[rows]
        return T


@dataclass
class Frame:
    timestamp_ns: int
    image: np.ndarray | None  # uint8 grayscale (H, W); None when skipped
    path: Path


@dataclass
class CameraStream:
    """One camera's frames; iterate `frames()` to stream images."""

    name: str
    camera: CameraModel
    timestamps_ns: np.ndarray
    paths: list[Path]
    csv_lines: list[int]
    skipped: list[str] = field(default_factory=list)  # one message per skipped frame

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    def load_image(self, i: int) -> np.ndarray | None:
        """Image i as uint8 grayscale, or None (recorded in `skipped`) if missing, not a regular
        file, of another size than sensor.yaml's resolution (read from the header, before
        decoding: a header claiming 100000x100000 px is never decoded) or unreadable."""
        path = self.paths[i]
        if not os.path.lexists(path):
            self.skipped.append(f"{self._where(i)}: image {path.name} is missing")
            return None
        try:
            with open_regular(path, LogError, binary=True) as f:
                data = f.read(IMAGE_HEADER_BYTES)
                size = image_size_from_header(data)
                limit = (self.camera.width, self.camera.height)
                if size is not None and size != limit:
                    self.skipped.append(
                        f"{self._where(i)}: image {path.name} is {size[0]}x{size[1]} "
                        f"(header), sensor.yaml says {limit[0]}x{limit[1]}"
                    )
                    return None
                if size is None and data.startswith(PNG_SIGNATURE):
                    self.skipped.append(
                        f"{self._where(i)}: image {path.name} is unreadable "
                        "(PNG header truncated or malformed)"
                    )
                    return None
                if size is None and os.fstat(f.fileno()).st_size > _max_image_bytes(*limit):
                    self.skipped.append(
                        f"{self._where(i)}: image {path.name} is too large for {limit[0]}x{limit[1]} px"
                    )
                    return None
                data += f.read()
            truncated = truncated_image(data)
            if truncated:
                # said here: libpng / libjpeg would print their own errors on stderr, or decode
                # the missing rows as grey
                self.skipped.append(f"{self._where(i)}: image {path.name} is truncated ({truncated})")
                return None
        except LogError as e:
            self.skipped.append(f"{self._where(i)}: image {path.name}: {str(e).split(': ', 1)[-1]}")
            return None
        except OSError as e:
            self.skipped.append(f"{self._where(i)}: image {path.name} cannot be read ({e.strerror})")
            return None
        img = decode_image_bytes(data)
        if img is None or img.size == 0:
            self.skipped.append(f"{self._where(i)}: image {path.name} is unreadable")
            return None
        if img.shape != (self.camera.height, self.camera.width):
            self.skipped.append(
                f"{self._where(i)}: image {path.name} is {img.shape[1]}x{img.shape[0]}, "
                f"sensor.yaml says {self.camera.width}x{self.camera.height}"
            )
            return None
        return img

    def _where(self, i: int) -> str:
        """data.csv file and line of frame i (formatted only for a message: a frame's read is
        ~0.3 ms of CPU besides its decoding, a tenth of it this path arithmetic)."""
        return f"{self.paths[i].parent.parent / 'data.csv'}:{self.csv_lines[i]}"

    def frames(self) -> Iterator[Frame]:
        for i, t in enumerate(self.timestamps_ns):
            yield Frame(int(t), self.load_image(i), self.paths[i])


def decode_image_bytes(data: bytes) -> np.ndarray | None:
    """A PNG or JPEG file's bytes as a uint8 grey image, or None if they do not decode.  8-bit grey
    PNGs take the fast path of `fusion.log.png` (bit-identical, half the time); everything else
    is OpenCV's, 16-bit grey stretched by `gray16_to_8`."""
    img = decode_gray8(data)
    if img is not None:
        return img
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    except cv2.error:
        return None
    if img is not None and img.dtype == np.uint16:
        img = gray16_to_8(img)
    return img


def gray16_to_8(img16: np.ndarray) -> np.ndarray:
    """A 16-bit grey image (PNG, mono16) as uint8, stretched so its brightest pixel is 255:
    machine-vision cameras write 10- or 12-bit data in 16-bit containers (Mono12: 0-4095), which
    keeping the high byte (OpenCV's 8-bit read) turned near black; full-range 16-bit data reads
    as before.  An all-black image stays black."""
    top = float(img16.max()) if img16.size else 0.0
    if top <= 0:
        return np.zeros(img16.shape, np.uint8)
    return np.round(img16.astype(np.float64) * (255.0 / top)).astype(np.uint8)


def truncated_image(data: bytes) -> str | None:
    """What is missing at the end of a PNG (its IEND chunk) or JPEG (its EOI marker, anywhere:
    cameras may append trailers after it) file's bytes; None when complete or another format."""
    if data.startswith(PNG_SIGNATURE) and data.rfind(b"IEND") < 0:
        return "no IEND chunk"
    if data.startswith(b"\xff\xd8") and data.rfind(b"\xff\xd9") < 0:
        return "no JPEG end-of-image marker"
    return None


def image_size_from_header(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the first bytes of a PNG (IHDR) or JPEG (SOFn) file; None for other
    formats or a header too short to say."""
    if data.startswith(PNG_SIGNATURE):
        if len(data) >= 24 and data[12:16] == b"IHDR":
            w, h = struct.unpack(">II", data[16:24])
            return int(w), int(h)
        return None
    if data.startswith(b"\xff\xd8"):
        i = 2
        while i + 9 <= len(data):
            if data[i] != 0xFF:
                return (0, 0)
            marker = data[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                i += 2
                continue
            (length,) = struct.unpack(">H", data[i + 2 : i + 4])
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                h, w = struct.unpack(">HH", data[i + 5 : i + 9])
                return int(w), int(h)
            i += 2 + length
        return None
    return None


def _max_image_bytes(width: int, height: int) -> int:
    """Largest file we decode without a readable header: 4 bytes a pixel and 64 KiB of extras."""
    return 4 * width * height + 64 * 1024


@dataclass
class StreamSource:
    """Where a stream of a log that is not an EuRoC folder comes from, for check_log's messages
    (an EuRoC folder's name its `mav0/<stream>/data.csv` and `sensor.yaml`): `data` the file of
    its samples, or a bag and topic as the bag reader's own warnings name them (`<bag>: topic
    /imu0`); `mount` the file (and key) stating its T_BS (None: `data`); `rate_hz` a rate the
    calibration states (Kalibr imu.yaml's update_rate), `rate_said` who says it ("<imu.yaml>
    says update_rate"; None: the sensor.yaml beside an EuRoC data.csv).  `stamps_ns`: the
    format fixes the stamps' unit (a bag's sec + nsec header, a ULog's microseconds), so a
    stated rate 1000^k off is a `rate_mismatch`, not timestamps in another unit."""

    data: str
    mount: str | None = None
    rate_hz: float | None = None
    rate_said: str | None = None
    stamps_ns: bool = False


@dataclass
class FlightLog:
    root: Path
    world: World
    cameras: dict[str, CameraStream]
    imu: ImuData | None = None
    velocity: VelocityData | None = None
    groundtruth: GroundTruth | None = None
    loads_groundtruth: dict[str, np.ndarray] | None = None
    blackouts: list[tuple[int, int, str]] | None = None  # (start_ns, end_ns, kind)
    warnings: list[LogWarning] = field(default_factory=list)  # plausibility (check_log)
    # Kalibr's timeshift_cam_imu the reader already added to each camera's stamps (ns, t_imu =
    # t_cam + shift): the seed of the time-offset estimate (fusion.estimate.timeoffset)
    timeshift_ns: dict[str, int] = field(default_factory=dict)
    # a bag's or a video's StreamSource by stream name ("cam0", "imu0", "vel0", "groundtruth"),
    # for check_log's messages; empty for an EuRoC folder (its own files are named)
    stream_sources: dict[str, StreamSource] = field(default_factory=dict)

    @property
    def floor(self) -> CameraStream:
        return self.cameras["cam0"]

    @property
    def front(self) -> CameraStream | None:
        return self.cameras.get("cam1")

    @property
    def duration_s(self) -> float:
        if "cam0" not in self.cameras:  # camera-less (IMU + external fixes)
            t = self.imu.timestamps_ns if self.imu is not None else np.zeros(0, np.int64)
            return float(t[-1] - t[0]) * 1e-9 if len(t) > 1 else 0.0
        t = self.floor.timestamps_ns
        return float(t[-1] - t[0]) * 1e-9 if len(t) > 1 else 0.0


# ============================================================================ reading


def _rows(path: Path, ncols: int, header_prefix: str = "#") -> Iterator[tuple[int, list[str]]]:
    """Yield (line number, fields) of a CSV file, skipping comment/header lines and blank lines;
    a row with the wrong number of fields raises LogError naming file and line."""
    with open_regular(path, LogError) as f:
        try:
            for lineno, row in enumerate(csv.reader(f), start=1):
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue
                if row[0].lstrip().startswith(header_prefix):
                    continue
                if len(row) != ncols:
                    raise LogError(f"{path}:{lineno}: expected {ncols} fields, found {len(row)}")
                yield lineno, [c.strip() for c in row]
        except UnicodeDecodeError:
            raise LogError(f"{path}: not UTF-8 text") from None
        except csv.Error as e:
            raise LogError(f"{path}: malformed CSV ({e})") from None


def parse_timestamp_ns(text: str) -> int:
    """A non-negative integer number of nanoseconds that fits int64 (digits only: no sign, no
    underscores); ValueError saying why not."""
    if text.startswith("-") and _DIGITS.fullmatch(text[1:]):
        raise ValueError(f"negative timestamp {text[:30]}")
    if not _DIGITS.fullmatch(text):
        hint = " (seconds with a fraction?)" if re.fullmatch(r"[0-9]+\.[0-9]*", text) else ""
        raise ValueError(f"timestamp {text[:30]!r} is not an integer number of nanoseconds{hint}")
    if len(text) > 19 or int(text) > INT64_MAX:
        raise ValueError(
            f"timestamp {text[:30]}{'...' if len(text) > 30 else ''} "
            "is too large (beyond int64 nanoseconds, year 2262)"
        )
    return int(text)


def _timestamp(text: str, path: Path, lineno: int) -> int:
    """parse_timestamp_ns, a LogError naming the file and line."""
    try:
        return parse_timestamp_ns(text)
    except ValueError as e:
        raise LogError(f"{path}:{lineno}: {e}") from None


def _numbers(fields: list[str], path: Path, lineno: int) -> list[float]:
    try:
        vals = [float(v) for v in fields]
    except ValueError:
        raise LogError(f"{path}:{lineno}: a value is not a number") from None
    if not all(math.isfinite(v) for v in vals):
        raise LogError(f"{path}:{lineno}: NaN or infinite value")
    return vals


def _check_monotonic(t: int, prev: int | None, path: Path, lineno: int) -> None:
    if prev is not None and t <= prev:
        what = "duplicate" if t == prev else "non-monotonic"
        raise LogError(f"{path}:{lineno}: {what} timestamp {t} (previous {prev})")


_FAST_DATA_BYTES = np.zeros(256, bool)
_FAST_DATA_BYTES[list(b"0123456789.eE+-,\n")] = True
"""The bytes a data row of _numeric_csv_fast may hold: plain decimal numbers, commas, newlines
(no blanks, quotes, carriage returns, NaN / inf, underscores, '#' after a row's start)."""
_FAST_TIMESTAMP_DIGITS = 19
"""Longest timestamp _timestamp accepts (19 digits; the value then checked against INT64_MAX)."""
_FAST_BLOCK_BYTES = 1 << 22
"""_numeric_csv_fast reads and parses this many bytes at a time (whole lines): its temporaries
stay a few MB whatever the file's size (the whole 35 MB ground truth of the 10-minute flight
at once peaked 66 MB above the row parser)."""


def _numeric_csv_fast(path: Path, ncols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """_numeric_csv's (timestamps_ns (N,) int64, values (N, ncols - 1) float64, line numbers
    (N,) int64) of a well-formed file by numpy's C parser (np.loadtxt, whose floats are CPython's
    PyOS_string_to_double, as float() in _numbers: the same values to the bit), or None whenever
    the file is anything but plain: not ASCII (a BOM too), quotes, carriage returns, NUL, a
    blank or indented line, a '#' other than at a row's start, a character outside
    _FAST_DATA_BYTES in a data row, a row of another field count, a timestamp that is not 1-19
    digits or exceeds INT64_MAX, timestamps not strictly increasing, a value numpy cannot parse
    or that is not finite, no data row.  On None the row parser reads the file again and raises
    its one-line error naming the file and line (or accepts what only it accepts, e.g. CRLF
    line ends or blanks around a field): every error and every accepted value stay the row
    parser's.  Comment rows are lines starting with '#' (the row parser's header_prefix) and
    empty lines are skipped, as csv.reader and _rows do; line numbers count every line.  Read
    in blocks of whole lines (_FAST_BLOCK_BYTES)."""
    ts_parts, val_parts, line_parts = [], [], []
    lines_before = 0
    with open_regular(path, LogError, binary=True) as f:
        tail = b""
        while True:
            chunk = f.read(_FAST_BLOCK_BYTES)
            buf = tail + chunk
            cut = len(buf) if not chunk else buf.rfind(b"\n") + 1
            block, tail = buf[:cut], buf[cut:]
            del buf
            if block:
                parsed = _parse_block(block, ncols)
                if parsed is None:
                    return None
                ts, vals, lines_, n_lines = parsed
                ts_parts.append(ts)
                val_parts.append(vals)
                line_parts.append(lines_ + lines_before)
                lines_before += n_lines
            if not chunk:
                break
    ts = np.concatenate(ts_parts) if ts_parts else np.zeros(0, np.int64)
    if not len(ts) or (len(ts) > 1 and not (np.diff(ts) > 0).all()):
        return None
    return ts, np.concatenate(val_parts), np.concatenate(line_parts)


def _parse_block(raw: bytes, ncols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
    """_numeric_csv_fast on one block of whole lines: (timestamps (N,) int64, values
    (N, ncols - 1), line numbers (N,) 1-based within the block, the block's line count), or
    None when anything in it is unusual (_numeric_csv_fast's list; the timestamps' order is
    checked by the caller, across blocks)."""
    if not raw.isascii() or b'"' in raw or b"\r" in raw or b"\x00" in raw:
        return None
    text = np.frombuffer(raw, np.uint8)
    newlines = np.flatnonzero(text == ord("\n"))
    starts = np.r_[0, newlines + 1]
    ends = np.r_[newlines, len(text)]
    if starts[-1] == len(text):  # the last line ended by its newline
        starts, ends = starts[:-1], ends[:-1]
    empty = starts == ends
    comment = ~empty & (text[np.minimum(starts, len(text) - 1)] == ord("#"))
    rows = np.flatnonzero(~empty & ~comment)
    # every byte outside the data bytes lies in a comment row
    odd = np.flatnonzero(~_FAST_DATA_BYTES[text])
    if len(odd) and not comment[np.searchsorted(starts, odd, side="right") - 1].all():
        return None
    if not len(rows):
        return np.zeros(0, np.int64), np.zeros((0, ncols - 1)), np.zeros(0, np.int64), len(starts)
    # each data row has ncols - 1 commas
    commas = np.flatnonzero(text == ord(","))
    row_start = starts[rows]
    if ((np.searchsorted(commas, ends[rows]) - np.searchsorted(commas, row_start)) != ncols - 1).any():
        return None
    # the timestamp: 1-19 digits, then the row's first comma
    head = text[np.minimum(row_start[:, None] + np.arange(_FAST_TIMESTAMP_DIGITS + 1), len(text) - 1)]
    width = np.argmin((head >= ord("0")) & (head <= ord("9")), axis=1)  # first non-digit (0: none)
    if width.min() < 1 or not (head[np.arange(len(rows)), width] == ord(",")).all():
        return None
    dtype = np.dtype([("t", np.uint64), ("v", np.float64, (ncols - 1,))])
    try:
        table = np.loadtxt(
            io.BytesIO(raw),
            dtype=dtype,
            delimiter=",",
            comments="#",
            quotechar=None,
            ndmin=1,
            encoding="ascii",
        )
    except ValueError:
        return None
    if len(table) != len(rows) or not (table["t"] <= INT64_MAX).all():
        return None
    vals = np.ascontiguousarray(table["v"]).reshape(len(rows), ncols - 1)
    if not np.isfinite(vals).all():
        return None
    return table["t"].astype(np.int64), vals, (rows + 1).astype(np.int64), len(starts)


def _numeric_csv(path: Path, ncols: int, with_lines: bool = False):
    """Read a `timestamp, v1, ..., v{ncols-1}` CSV with strictly increasing timestamps:
    (timestamps_ns, values) and, with `with_lines`, each row's line number.  A well-formed file
    is read by numpy's C parser (_numeric_csv_fast, the same numbers to the bit); anything else
    by the row parser below, which names the first bad line.  The rows are gathered in typed
    buffers, 8 bytes a number, which the arrays then view (as lists of Python floats, ~0.6 kB a
    ground-truth row: reading a 2-minute flight peaked at 22.8 MB traced and left the process
    64 MB larger, against 8.7 and 8 MB now; BENCHMARKS.md)."""
    fast = _numeric_csv_fast(path, ncols)
    if fast is not None:
        return fast if with_lines else fast[:2]
    ts, vals, lines, prev = array("q"), array("d"), array("q"), None
    for lineno, row in _rows(path, ncols):
        t = _timestamp(row[0], path, lineno)
        _check_monotonic(t, prev, path, lineno)
        prev = t
        ts.append(t)
        vals.extend(_numbers(row[1:], path, lineno))
        lines.append(lineno)
    if not ts:
        raise LogError(f"{path}: no data rows")
    out = np.frombuffer(ts, dtype=np.int64), np.frombuffer(vals, dtype=float).reshape(len(ts), ncols - 1)
    return (*out, np.frombuffer(lines, dtype=np.int64)) if with_lines else out


def _check_sensor_numbers(cfg: dict, source: str, camera: bool) -> None:
    """Strict types for sensor.yaml's numbers (a bool or a string is not a number), before the
    camera model or IMU reader converts them; errors name the file and key."""
    if "rate_hz" in cfg:
        strict_float(cfg["rate_hz"], f"{source}: rate_hz", LogError, positive=True)
    if isinstance(cfg.get("T_BS"), dict) and "data" in cfg["T_BS"]:
        strict_floats(cfg["T_BS"]["data"], 16, f"{source}: T_BS.data", LogError)
    if not camera:
        return
    n_coeffs = coefficient_count(
        cfg.get("distortion_model", "radial-tangential"), cfg.get("distortion_coefficients")
    )
    for key, n in (("resolution", 2), ("intrinsics", 4), ("distortion_coefficients", n_coeffs)):
        if key in cfg:
            vals = strict_floats(cfg[key], n, f"{source}: {key}", LogError)
            if key == "resolution" and any(v != int(v) or v < 1 for v in vals):
                raise LogError(f"{source}: resolution must be two positive whole numbers")


_PLAIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
"""An image file name that is one path component and neither '.' nor '..' (it cannot start
with a dot): inside the data folder unless it names a symbolic link there."""


def _symlinked_names(data_dir: Path) -> set[str] | None:
    """The names of the symbolic links directly in `data_dir`, lower-cased (a case-insensitive
    file system finds 'a.png' for 'A.png': such a name is resolved too), from one listing (no
    stat per entry where the file system gives the entry's type); an empty set when it is no
    folder (every name then resolves to itself inside it); None when it cannot be listed (each
    name is then resolved)."""
    try:
        with os.scandir(data_dir) as entries:
            return {e.name.lower() for e in entries if e.is_symlink()}
    except (FileNotFoundError, NotADirectoryError):
        return set()
    except OSError:
        return None


def _resolve_failure(e: BaseException) -> str:
    """Why Path.resolve() failed: a symbolic link loop (RuntimeError on Python < 3.13, OSError
    ELOOP after) or the OSError's own reason."""
    if isinstance(e, RuntimeError) or getattr(e, "errno", None) == errno.ELOOP:
        return "a symbolic link loop"
    return getattr(e, "strerror", None) or str(e)


def _stream_folder(path: Path) -> bool:
    """Whether a stream folder (mav0/cam0, imu0, ...) is there: True for a folder, False when
    nothing is at `path`; LogError for anything else at its name (a file, a symbolic link loop, a
    dangling link), which had read as an absent stream, silently."""
    if path.is_dir():
        return True
    if not os.path.lexists(path):
        return False
    try:
        os.stat(path)
        why = "not a folder"
    except FileNotFoundError:
        why = "a symbolic link to nothing"
    except (RuntimeError, OSError) as e:
        why = _resolve_failure(e)
    raise LogError(f"{path}: is {why}; expected the stream's folder (or nothing, when the log has none)")


IMU_SENSOR_KEYS = (
    "sensor_type",
    "comment",
    "T_BS",
    "rate_hz",
    "gyroscope_noise_density",
    "gyroscope_random_walk",
    "accelerometer_noise_density",
    "accelerometer_random_walk",
)
"""An IMU sensor.yaml's keys (EuRoC's)."""


def _sensor_keys(cfg: dict, known: tuple[str, ...], path: Path, warnings: list[LogWarning]) -> None:
    """camera.unknown_sensor_keys on a sensor.yaml (a LogError for a key that would have meant
    something: Kalibr's name of one of ours, a typo); the other unknown keys, which other tools
    write and the reader ignores, are counted in `warnings` (`sensor_yaml_unknown_keys`)."""
    try:
        unknown = unknown_sensor_keys(cfg, known, str(path))
    except CameraModelError as e:
        raise LogError(str(e)) from None
    if unknown:
        warnings.append(
            LogWarning(
                "sensor_yaml_unknown_keys",
                len(unknown),
                f"{path}: key(s) {', '.join(k[:40] for k in unknown[:5])} not read "
                f"(known: {', '.join(known)})",
            )
        )


def _read_camera(cam_dir: Path, name: str, warnings: list[LogWarning] | None = None) -> CameraStream:
    """One camera's stream; unknown sensor.yaml keys are counted in `warnings`."""
    sensor_path = cam_dir / "sensor.yaml"
    cfg = load_yaml(sensor_path, LogError)
    _sensor_keys(cfg, SENSOR_YAML_KEYS, sensor_path, [] if warnings is None else warnings)
    _check_sensor_numbers(cfg, str(sensor_path), camera=True)
    try:
        camera = CameraModel.from_sensor_yaml(cfg, str(sensor_path))
    except CameraModelError as e:
        raise LogError(str(e)) from None
    try:
        data_dir = (cam_dir / "data").resolve()
    except (RuntimeError, OSError) as e:  # a symbolic link loop: RuntimeError before Python 3.13
        raise LogError(f"{cam_dir / 'data'}: cannot be opened ({_resolve_failure(e)})") from None
    links = _symlinked_names(data_dir)
    csv_path = cam_dir / "data.csv"
    ts, paths, lines, prev = [], [], [], None
    for lineno, row in _rows(csv_path, 2):
        t = _timestamp(row[0], csv_path, lineno)
        _check_monotonic(t, prev, csv_path, lineno)
        prev = t
        fname = row[1]
        if not fname:
            raise LogError(f"{csv_path}:{lineno}: empty file name")
        if links is not None and _PLAIN_NAME.fullmatch(fname) and fname.lower() not in links:
            # what resolve() returns for it (data_dir is resolved; the name is one component,
            # not '.' or '..', and no symbolic link), without its lstat of every component
            path = data_dir / fname
        else:
            try:
                path = (data_dir / fname).resolve()
            except (RuntimeError, OSError):
                # a symbolic link loop: it cannot be opened wherever it points, so the frame is
                # skipped and counted when its image is read, as any unreadable image
                path = data_dir / fname
            if data_dir not in path.parents:
                raise LogError(
                    f"{csv_path}:{lineno}: file name {fname[:60]!r} points outside {cam_dir / 'data'}"
                )
        ts.append(t)
        paths.append(path)
        lines.append(lineno)
    if not ts:
        raise LogError(f"{csv_path}: no frames")
    return CameraStream(name, camera, np.asarray(ts, dtype=np.int64), paths, lines)


def _read_imu(imu_dir: Path, warnings: list[LogWarning] | None = None) -> ImuData:
    """The IMU's samples and sensor.yaml; unknown sensor.yaml keys are counted in `warnings`."""
    sensor_path = imu_dir / "sensor.yaml"
    cfg = load_yaml(sensor_path, LogError)
    _sensor_keys(cfg, IMU_SENSOR_KEYS, sensor_path, [] if warnings is None else warnings)
    _check_sensor_numbers(cfg, str(sensor_path), camera=False)
    noise = {}
    for key in (
        "gyroscope_noise_density",
        "gyroscope_random_walk",
        "accelerometer_noise_density",
        "accelerometer_random_walk",
    ):
        if key not in cfg:
            raise LogError(f"{sensor_path}: missing key '{key}'")
        noise[key] = strict_float(cfg[key], f"{sensor_path}: {key}", LogError, positive=True)
    T = read_T_BS(cfg.get("T_BS", {"data": np.eye(4).reshape(-1).tolist()}), str(sensor_path), LogError)
    ts, vals = _numeric_csv(imu_dir / "data.csv", 7)
    if cfg.get("rate_hz") is not None:
        rate = float(cfg["rate_hz"])
    else:
        dt = float(np.median(np.diff(ts))) if len(ts) > 1 else 0.0
        rate = 1e9 / dt if dt > 0 else 200.0
    return ImuData(ts, vals[:, :3], vals[:, 3:], ImuNoise(**noise), T, rate)


def _read_velocity(vel_dir: Path) -> VelocityData:
    noise = 0.05
    sensor_path = vel_dir / "sensor.yaml"
    if sensor_path.exists():
        cfg = load_yaml(sensor_path, LogError)
        noise = strict_float(
            cfg.get("noise_m_s", noise), f"{sensor_path}: noise_m_s", LogError, positive=True
        )
        frame = cfg.get("frame", "body")
        if frame != "body":
            # it was never read: a world-frame velocity was fused as a body-frame one (third audit)
            raise LogError(
                f"{sensor_path}: frame {frame!r}: the velocity must be in the body frame (frame: "
                "body; rotate world-frame velocities by the attitude first)"
            )
    ts, vals = _numeric_csv(vel_dir / "data.csv", 4)
    return VelocityData(ts, vals, noise)


def _read_groundtruth(path: Path) -> tuple[GroundTruth, list[LogWarning]]:
    """Ground truth; a zero quaternion is an error naming the line, a non-unit one is
    renormalised and counted (warning `groundtruth_quaternion_not_unit`)."""
    ts, v, lines = _numeric_csv(path, 17, with_lines=True)
    q = v[:, 3:7]
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(norm < QUAT_NORM_MIN)
    if len(bad):
        raise LogError(
            f"{path}:{lines[bad[0]]}: quaternion q_RS_wxyz "
            f"({', '.join(f'{x:g}' for x in q[bad[0]])}) is not a rotation"
        )
    warnings = []
    off = np.abs(norm - 1.0) > QUAT_NORM_TOLERANCE
    if off.any():
        i = int(np.flatnonzero(off)[0])
        warnings.append(
            LogWarning(
                "groundtruth_quaternion_not_unit",
                int(off.sum()),
                f"{path}: {int(off.sum())} quaternion(s) not of unit norm (first: line {lines[i]}, "
                f"norm {norm[i]:.4g}); renormalised",
            )
        )
        q = q.copy()
        q[off] /= norm[off, None]  # unit ones stay bit-exact
    return GroundTruth(ts, v[:, 0:3], q, v[:, 7:10], v[:, 10:13], v[:, 13:16]), warnings


def _read_loads(path: Path) -> dict[str, np.ndarray]:
    loads: dict[str, np.ndarray] = {}
    for lineno, row in _rows(path, 4, header_prefix="id"):
        load_id = csv_unsafe(row[0])
        if load_id in loads:
            raise LogError(f"{path}:{lineno}: duplicate load id {load_id[:64]!r}")
        loads[load_id] = np.asarray(_numbers(row[1:], path, lineno))
    return loads


def _read_blackouts(path: Path) -> list[tuple[int, int, str]]:
    out = []
    for lineno, row in _rows(path, 3):
        t0, t1 = _timestamp(row[0], path, lineno), _timestamp(row[1], path, lineno)
        if t1 < t0:
            raise LogError(f"{path}:{lineno}: blackout ends before it starts")
        out.append((t0, t1, row[2]))
    return out


def read_flight(root: Path, cameras_optional: bool = False) -> FlightLog:
    """Open a flight log folder.  Reads every CSV and YAML now (validating them), images lazily.
    `cameras_optional`: a log without the floor camera is accepted (IMU + external fixes)."""
    root = Path(root)
    if not root.is_dir():
        raise LogError(f"{root}: not a folder")
    mav = root / "mav0"
    try:
        world = World.load(root / "world.yaml")
    except WorldError as e:
        raise LogError(str(e)) from None
    cameras = {}
    sensor_warnings: list[LogWarning] = []
    for name in CAMERA_NAMES:
        if _stream_folder(mav / name):
            cameras[name] = _read_camera(mav / name, name, sensor_warnings)
    if "cam0" not in cameras and not cameras_optional:
        raise LogError(f"{mav / 'cam0'}: the floor camera folder is missing")
    imu = _read_imu(mav / "imu0", sensor_warnings) if _stream_folder(mav / "imu0") else None
    vel = _read_velocity(mav / "vel0") if _stream_folder(mav / "vel0") else None
    gt_path = mav / "state_groundtruth_estimate0" / "data.csv"
    gt, warnings = _read_groundtruth(gt_path) if os.path.lexists(gt_path) else (None, [])
    loads_path = root / "loads_groundtruth.csv"
    loads = _read_loads(loads_path) if os.path.lexists(loads_path) else None
    bo_path = root / "blackouts_groundtruth.csv"
    blackouts = _read_blackouts(bo_path) if os.path.lexists(bo_path) else None
    log = FlightLog(root, world, cameras, imu, vel, gt, loads, blackouts, sensor_warnings + warnings)
    log.warnings += drop_short_groundtruth(log)
    log.warnings += check_log(log)
    return log


def drop_short_groundtruth(log: FlightLog) -> list[LogWarning]:
    """Ground truth of fewer than 2 samples cannot be interpolated to any estimate: it is dropped
    from `log` (the run is then evaluated against nothing, as a log without ground truth) with
    the warning `groundtruth_too_short` naming its file.  Ground truth is optional: a run that had
    finished its work then failed on it, with every output discarded."""
    gt = log.groundtruth
    if gt is None or len(gt.timestamps_ns) >= 2:
        return []
    log.groundtruth = None
    where = _stream_sources(log)["groundtruth"].data
    n = len(gt.timestamps_ns)
    return [
        LogWarning(
            "groundtruth_too_short",
            1,
            f"{where}: ground truth has {n} sample{'s' if n != 1 else ''} (2 or more needed): "
            "evaluation against ground truth skipped",
        )
    ]


# ============================================================================ plausibility


def stated_rate_hz(value: object) -> float | None:
    """A rate as a calibration states it (sensor.yaml's rate_hz, Kalibr imu.yaml's update_rate)
    when it is one check_log can compare with: a finite positive number; else None (it states
    nothing: absent, 0, negative, infinite, not a number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    v = float(value)
    return v if math.isfinite(v) and v > 0 else None


def _declared_rate(sensor_path: Path) -> float | None:
    """rate_hz as sensor.yaml states it (None when absent); the file was validated already."""
    try:
        return stated_rate_hz(load_yaml(sensor_path, LogError).get("rate_hz"))
    except LogError:
        return None


_UNIT_NAMES = {1: "microseconds", 2: "milliseconds", 3: "seconds"}


def _check_rate(name: str, src: StreamSource, ts: np.ndarray) -> list[LogWarning]:
    """Timestamp units from the sample interval against the stated rate (`src.rate_hz`: an EuRoC
    folder's sensor.yaml rate_hz, Kalibr imu.yaml's update_rate): a ratio of 1e-3 / 1e-6 / 1e-9
    is a unit mistake (LogError) unless the format fixes the unit; any other mismatch a warning.
    `src.data` names the samples in the messages."""
    if len(ts) < 2:
        return []
    where, rate_hz = src.data, stated_rate_hz(src.rate_hz)
    dt = float(np.median(np.diff(ts)))
    if rate_hz is None:
        if dt < MIN_PLAUSIBLE_DT_NS:
            return [
                LogWarning(
                    "timestamp_units",
                    1,
                    f"{where}: timestamps advance {dt:g} per sample, i.e. faster "
                    f"than {1e9 / MIN_PLAUSIBLE_DT_NS:g} Hz if they were nanoseconds: "
                    "are they in another unit?",
                )
            ]
        return []
    expected = 1e9 / rate_hz
    decades = math.log10(dt / expected)
    k = round(-decades / 3)
    if k in _UNIT_NAMES and abs(decades + 3 * k) < UNIT_MATCH_DECADES and not src.stamps_ns:
        said = src.rate_said or f"{Path(where).parent / 'sensor.yaml'} says rate_hz"
        raise LogError(
            f"{where}: timestamps advance {dt:g} per sample while {said} {rate_hz:g}: they look "
            f"like {_UNIT_NAMES[k]}; EuRoC timestamps are nanoseconds"
        )
    if abs(decades) > math.log10(RATE_MISMATCH_FACTOR):
        # an EuRoC folder's: named by its stream, "sensor.yaml" being the one in its folder
        who, said = (name, "sensor.yaml says rate_hz") if src.rate_said is None else (where, src.rate_said)
        return [
            LogWarning(
                "rate_mismatch",
                1,
                f"{who}: samples every {dt * 1e-6:.4g} ms ({1e9 / dt:.4g} Hz) but {said} {rate_hz:g}",
            )
        ]
    return []


def _check_imu(imu: ImuData, where: str) -> list[LogWarning]:
    """Accelerometer in g (median |specific force| ~ 1: LogError), other magnitudes, gaps, gyro in
    deg/s (rates beyond GYRO_MAX_PLAUSIBLE_RAD_S, or white noise far above sensor.yaml's density,
    estimated from first differences: std(diff)/sqrt(2) = sigma_d for white noise), clipping.
    `where` names the samples in the messages."""
    out = []
    n = len(imu.timestamps_ns)
    a_norm = float(np.median(np.linalg.norm(imu.accel_m_s2, axis=1)))
    if ACCEL_IN_G_RANGE[0] <= a_norm <= ACCEL_IN_G_RANGE[1]:
        raise LogError(
            f"{where}: the accelerometer's median magnitude is {a_norm:.3g}, gravity "
            f"is {GRAVITY_M_S2} m s^-2: the a_RS_S columns look like g; convert them "
            "to m s^-2"
        )
    if not ACCEL_NORM_RANGE_M_S2[0] <= a_norm <= ACCEL_NORM_RANGE_M_S2[1]:
        out.append(
            LogWarning(
                "accelerometer_magnitude",
                1,
                f"{where}: median |a_RS_S| is {a_norm:.3g} m s^-2, gravity is "
                f"{GRAVITY_M_S2}: wrong units, scale or a broken sensor?",
            )
        )
    up = _gravity_axis_warning(imu, where)
    if up is not None:
        out.append(up)
    w_norm = np.linalg.norm(imu.gyro_rad_s, axis=1)
    p99 = float(np.percentile(w_norm, 99))
    ratio = None
    if n > 2 and imu.rate_hz > 0:
        sigma_d = float(np.median(np.std(np.diff(imu.gyro_rad_s, axis=0), axis=0))) / math.sqrt(2)
        ratio = sigma_d / (imu.noise.gyroscope_noise_density * math.sqrt(imu.rate_hz))
    if p99 > GYRO_MAX_PLAUSIBLE_RAD_S or (ratio is not None and ratio > GYRO_NOISE_RATIO_SUSPECT):
        why = (
            f"99th percentile of |w| {p99:.3g} rad/s"
            if p99 > GYRO_MAX_PLAUSIBLE_RAD_S
            else f"white noise {ratio:.3g}x the stated gyroscope_noise_density"
        )
        out.append(
            LogWarning(
                "gyroscope_units",
                1,
                f"{where}: {why}: the gyro looks like deg/s (rad/s expected), or "
                "its stated noise is wrong (sensor.yaml, Kalibr imu.yaml, or the defaults)",
            )
        )
    dt = np.diff(imu.timestamps_ns)
    gaps = np.flatnonzero(dt > IMU_GAP_WARN_S * 1e9)
    if len(gaps):
        i = int(gaps[np.argmax(dt[gaps])])
        t0 = int(imu.timestamps_ns[0])
        out.append(
            LogWarning(
                "imu_gaps",
                len(gaps),
                f"{where}: {len(gaps)} gap(s) over {IMU_GAP_WARN_S * 1e3:g} ms between samples, "
                f"{dt[gaps].sum() * 1e-9:.3g} s in all; the longest {dt[i] * 1e-9:.3g} s after "
                f"timestamp {int(imu.timestamps_ns[i])} ({(int(imu.timestamps_ns[i]) - t0) * 1e-9:.2f} s "
                "into the IMU): bridged by a random walk, the fused poses there rest on the cameras",
            )
        )
    clipped = 0
    for col in np.hstack([imu.gyro_rad_s, imu.accel_m_s2]).T:
        m = float(np.max(np.abs(col)))
        hits = int(np.sum(np.abs(col) >= m)) if m > 0 else 0
        if hits >= max(SATURATION_MIN_SAMPLES, SATURATION_MIN_FRACTION * n):
            clipped += hits
    if clipped:
        out.append(
            LogWarning(
                "imu_saturated",
                clipped,
                f"{where}: {clipped} sample value(s) sit at an axis' extreme: the "
                "IMU saturates (clipped motion)",
            )
        )
    return out


def _gravity_axis_warning(imu: ImuData, where: str) -> LogWarning | None:
    """`imu_gravity_axis` when the median specific force in the body frame (imu0's T_BS applied)
    is more than GRAVITY_MAX_TILT_DEG off the body's up axis (+z, FLU); None otherwise."""
    f = np.median(np.asarray(imu.accel_m_s2, float), axis=0)
    f_body = np.asarray(imu.T_body_imu, float)[:3, :3] @ f
    norm = float(np.linalg.norm(f_body))
    if not norm > 0:
        return None
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, f_body[2] / norm))))
    if tilt <= GRAVITY_MAX_TILT_DEG:
        return None
    shown = ", ".join(f"{v:+.2f}" for v in f_body)
    return LogWarning(
        "imu_gravity_axis",
        1,
        f"{where}: the median specific force is ({shown}) m s^-2 in the body frame, {tilt:.0f} deg "
        "from its up axis (+z: the body frame is x forward, y left, z up): the IMU's axes are not "
        "what imu0's T_BS says (an FRD / NED IMU read as FLU, a T_BS missing the IMU's rotation?)",
    )


def _check_imu_coverage(imu_ns: np.ndarray, cameras: list[np.ndarray], where: str) -> list[LogWarning]:
    """The IMU (stamps `imu_ns`) starting after the cameras' first frame, or ending before their
    last, by more than IMU_GAP_WARN_S: the frames there have no IMU to bridge them, as in a gap
    between samples (`imu_gaps`, which only looks between samples; `clock_offset` only fires when
    both ends are shifted the same way).  One warning `imu_coverage`, counting the frames of the
    `cameras` (each one's stamps; those warned clock_offset left out) outside the IMU's span;
    `where` names the IMU's samples."""
    i0, i1 = _span(imu_ns)
    c0, c1 = min(int(t[0]) for t in cameras), max(int(t[-1]) for t in cameras)
    late, early = (i0 - c0) * 1e-9, (c1 - i1) * 1e-9
    ends = []
    if late > IMU_GAP_WARN_S:
        ends.append(f"starts {late:.3g} s after the cameras' first frame")
    if early > IMU_GAP_WARN_S:
        ends.append(f"ends {early:.3g} s before their last")
    if not ends:
        return []
    n = sum(int(((t < i0) | (t > i1)).sum()) for t in cameras)
    return [
        LogWarning(
            "imu_coverage",
            n,
            f"{where}: the IMU ({i0 * 1e-9:.6g}-{i1 * 1e-9:.6g} s) {' and '.join(ends)} "
            f"({c0 * 1e-9:.6g}-{c1 * 1e-9:.6g} s): {n} frame(s) outside it, where the fused poses "
            "rest on the cameras alone",
        )
    ]


def _span(ts: np.ndarray) -> tuple[int, int]:
    return int(ts[0]), int(ts[-1])


def _stream_sources(log: FlightLog) -> dict[str, StreamSource]:
    """check_log's StreamSource of each stream: the reader's (a bag's, a video's: their files and
    topics), else an EuRoC folder's `mav0/<stream>/data.csv` and `sensor.yaml` (its rate_hz, a
    camera's or the IMU's)."""
    names = [*log.cameras, "imu0", "vel0", "groundtruth"]
    if log.stream_sources:
        return {n: log.stream_sources.get(n) or StreamSource(f"{log.root}: {n}") for n in names}
    mav = Path(log.root) / "mav0"
    out = {}
    for n in names:
        d = mav / ("state_groundtruth_estimate0" if n == "groundtruth" else n)
        rate = _declared_rate(d / "sensor.yaml") if n in log.cameras or n == "imu0" else None
        out[n] = StreamSource(str(d / "data.csv"), str(d / "sensor.yaml"), rate)
    return out


def check_log(log: FlightLog) -> list[LogWarning]:
    """Plausibility checks of a read log: timestamp units and rates, IMU units, gaps, clipping and
    coverage of the cameras' span (`imu_coverage`), sensor clock offsets above
    CLOCK_OFFSET_MAX_S (streams shifted at both ends, or not overlapping) and T_BS translations
    above T_BS_MAX_TRANSLATION_M.  Certain mistakes raise LogError; the rest are returned as
    warnings, naming the files (a bag's: the bag and topic) as `log.stream_sources` says (an
    EuRoC folder's: mav0's)."""
    src = _stream_sources(log)
    out: list[LogWarning] = []
    streams: dict[str, np.ndarray] = {}
    for name, cam in log.cameras.items():
        out += _check_rate(name, src[name], cam.timestamps_ns)
        streams[name] = cam.timestamps_ns
    if log.imu is not None:
        out += _check_rate("imu0", src["imu0"], log.imu.timestamps_ns)
        out += _check_imu(log.imu, src["imu0"].data)
        streams["imu0"] = log.imu.timestamps_ns
    if log.velocity is not None:
        out += _check_rate("vel0", src["vel0"], log.velocity.timestamps_ns)
        streams["vel0"] = log.velocity.timestamps_ns
    if log.groundtruth is not None:
        out += _check_rate("groundtruth", src["groundtruth"], log.groundtruth.timestamps_ns)
        streams["groundtruth"] = log.groundtruth.timestamps_ns
    ref_name = "cam0" if "cam0" in streams else "imu0"
    ref0, ref1 = _span(streams[ref_name]) if ref_name in streams else (0, 0)
    offset: set[str] = set()  # streams warned clock_offset
    for name, ts in streams.items():
        if name == ref_name or ref_name not in streams:
            continue
        a0, a1 = _span(ts)
        d0, d1 = (a0 - ref0) * 1e-9, (a1 - ref1) * 1e-9
        if (a0 > ref1 or a1 < ref0) or (d0 * d1 > 0 and min(abs(d0), abs(d1)) > CLOCK_OFFSET_MAX_S):
            offset.add(name)
        if a0 > ref1 or a1 < ref0:
            out.append(
                LogWarning(
                    "clock_offset",
                    1,
                    f"{name} ({a0 * 1e-9:.6g}-{a1 * 1e-9:.6g} s) does not overlap "
                    f"{ref_name} ({ref0 * 1e-9:.6g}-{ref1 * 1e-9:.6g} s): its clock is "
                    "offset or in other units",
                )
            )
        elif d0 * d1 > 0 and min(abs(d0), abs(d1)) > CLOCK_OFFSET_MAX_S:
            off = d0 if abs(d0) < abs(d1) else d1
            out.append(
                LogWarning(
                    "clock_offset",
                    1,
                    f"{name} starts and ends {abs(off):.3g} s "
                    f"{'later' if off > 0 else 'earlier'} than {ref_name}: its clock "
                    f"seems offset (more than {CLOCK_OFFSET_MAX_S} s)",
                )
            )
    cameras = [c.timestamps_ns for n, c in log.cameras.items() if n not in offset and len(c.timestamps_ns)]
    if log.imu is not None and "imu0" not in offset and cameras:
        out += _check_imu_coverage(log.imu.timestamps_ns, cameras, src["imu0"].data)
    mounts = {name: cam.camera.T_body_cam for name, cam in log.cameras.items()}
    if log.imu is not None:
        mounts["imu0"] = log.imu.T_body_imu
    for name, T in mounts.items():
        path = src[name].mount or src[name].data
        d = float(np.linalg.norm(np.asarray(T)[:3, 3]))
        if d > T_BS_MAX_TRANSLATION_M:
            out.append(
                LogWarning(
                    "T_BS_translation",
                    1,
                    f"{path}: T_BS puts {name} {d:.4g} m from the body origin "
                    f"(more than {T_BS_MAX_TRANSLATION_M:g} m): millimetres "
                    "instead of metres?",
                )
            )
    return out


# ============================================================================ writing


def _write_csv(path: Path, header, rows) -> None:
    with atomic_open(path) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)


def _fmt(v: float) -> str:
    return repr(float(v))


class FlightLogWriter:
    """Write a flight log.  Everything goes to `<root>.partial/` first and is moved to `root`
    by `close()`, so an interrupted write never leaves a log that looks complete.

        with FlightLogWriter(out) as w:
            w.write_world(world)
            w.add_camera("cam0", camera)
            w.write_frame("cam0", t_ns, image)
            w.write_imu(imu)

    Nothing the writer did not create is deleted.  `root/manifest.json` lists the files it
    wrote and says who (`written_by`: `fusion simulate` or `fusion import`); with `overwrite`,
    only the files of the previous log's manifest are replaced and the user's other files in
    `root` are kept (a file of the log layout that the manifest does not list is refused, not
    overwritten, and so is a folder whose manifest another command wrote, e.g. a run's).  A
    pre-existing `<root>.partial/` is removed only if an earlier writer that has died made it
    (its PARTIAL_MARKER names a dead pid); otherwise the write is refused.  File-system errors
    (full disk, read-only folder) become one LogError."""

    def __init__(self, root: Path, overwrite: bool = False, written_by: str = "fusion simulate"):
        if written_by not in FLIGHT_LOG_WRITERS:
            raise ValueError(f"written_by must be one of {FLIGHT_LOG_WRITERS}, got {written_by!r}")
        self.root = Path(root)
        self.written_by = written_by
        if os.path.lexists(self.root) and not overwrite:
            raise LogError(f"{self.root}: already exists")
        self.previous: list[str] = []
        if os.path.lexists(self.root):
            self.previous = _previous_log_files(self.root)
        self.tmp = self.root.with_name(self.root.name + ".partial")
        try:
            self._claim_partial()
            (self.tmp / "mav0").mkdir()
        except OSError as e:
            self._discard()
            raise LogError(f"{self.tmp}: cannot write the flight log ({e.strerror})") from None
        self._frames: dict[str, list[tuple[int, str]]] = {}

    def _claim_partial(self) -> None:
        """Create `<root>.partial/` with our marker; take over only a dead writer's leftover."""
        self.root.parent.mkdir(parents=True, exist_ok=True)
        if os.path.lexists(self.tmp):
            marker = self.tmp / PARTIAL_MARKER
            try:
                pid = (
                    int(marker.read_text(encoding="utf-8").split()[0])
                    if self.tmp.is_dir() and not self.tmp.is_symlink()
                    else None
                )
            except (OSError, ValueError, IndexError):
                pid = None
            if pid is None:
                raise LogError(
                    f"{self.tmp}: exists and was not made by fusion; move or remove it "
                    f"to write {self.root.name}"
                )
            if pid_alive(pid):
                raise LogError(f"{self.tmp}: another fusion process (pid {pid}) is writing this flight log")
            shutil.rmtree(self.tmp)  # a dead writer's leftover: ours to remove
        self.tmp.mkdir()
        self._owns_tmp = True
        (self.tmp / PARTIAL_MARKER).write_text(f"{os.getpid()}\n", encoding="utf-8")

    def _discard(self) -> None:
        if getattr(self, "_owns_tmp", False):
            shutil.rmtree(self.tmp, ignore_errors=True)
            self._owns_tmp = False

    # context manager: commit on success, discard on error
    def __enter__(self) -> FlightLogWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            try:
                self.close()
            except OSError as e:
                self._discard()
                raise LogError(_os_message(self.root, e)) from None
            return
        self._discard()
        if issubclass(exc_type, OSError):
            raise LogError(_os_message(self.root, exc)) from None

    def write_world(self, world: World) -> None:
        world.save(self.tmp / "world.yaml")

    def add_camera(self, name: str, camera: CameraModel, comment: str = "") -> None:
        d = self.tmp / "mav0" / name
        (d / "data").mkdir(parents=True, exist_ok=True)
        camera.save(d / "sensor.yaml", comment)
        self._frames[name] = []

    def write_frame(self, name: str, timestamp_ns: int, image: np.ndarray) -> None:
        fname = f"{int(timestamp_ns)}.png"
        path = self.tmp / "mav0" / name / "data" / fname
        if not cv2.imwrite(str(path), image):
            raise LogError(f"{path}: could not write image")
        self._frames[name].append((int(timestamp_ns), fname))

    def write_frame_png(self, name: str, timestamp_ns: int, png: bytes) -> None:
        """Like `write_frame` for an image already PNG-encoded (e.g. by a worker process)."""
        fname = f"{int(timestamp_ns)}.png"
        path = self.tmp / "mav0" / name / "data" / fname
        try:
            path.write_bytes(png)
        except OSError as e:
            raise LogError(f"{path}: could not write image ({e})") from None
        self._frames[name].append((int(timestamp_ns), fname))

    def write_imu(self, imu: ImuData) -> None:
        d = self.tmp / "mav0" / "imu0"
        d.mkdir(parents=True, exist_ok=True)
        n = imu.noise
        dump_yaml(
            {
                "sensor_type": "imu",
                "comment": "fusion flight log",
                "T_BS": {
                    "cols": 4,
                    "rows": 4,
                    "data": [float(v) for v in np.asarray(imu.T_body_imu).reshape(-1)],
                },
                "rate_hz": float(imu.rate_hz),
                "gyroscope_noise_density": n.gyroscope_noise_density,
                "gyroscope_random_walk": n.gyroscope_random_walk,
                "accelerometer_noise_density": n.accelerometer_noise_density,
                "accelerometer_random_walk": n.accelerometer_random_walk,
            },
            d / "sensor.yaml",
        )
        rows = (
            [str(int(t))] + [_fmt(v) for v in np.r_[w, a]]
            for t, w, a in zip(imu.timestamps_ns, imu.gyro_rad_s, imu.accel_m_s2)
        )
        _write_csv(d / "data.csv", IMU_HEADER, rows)

    def write_velocity(self, vel: VelocityData) -> None:
        d = self.tmp / "mav0" / "vel0"
        d.mkdir(parents=True, exist_ok=True)
        dump_yaml(
            {"sensor_type": "velocity", "frame": "body", "noise_m_s": float(vel.noise_m_s)}, d / "sensor.yaml"
        )
        rows = ([str(int(t))] + [_fmt(x) for x in v] for t, v in zip(vel.timestamps_ns, vel.v_body_m_s))
        _write_csv(d / "data.csv", VEL_HEADER, rows)

    def write_groundtruth(self, gt: GroundTruth) -> None:
        d = self.tmp / "mav0" / "state_groundtruth_estimate0"
        d.mkdir(parents=True, exist_ok=True)
        rows = (
            [str(int(t))] + [_fmt(x) for x in np.r_[p, q, v, bw, ba]]
            for t, p, q, v, bw, ba in zip(
                gt.timestamps_ns, gt.p_world, gt.q_world_body_wxyz, gt.v_world, gt.bias_gyro, gt.bias_accel
            )
        )
        _write_csv(d / "data.csv", GT_HEADER, rows)

    def write_loads_groundtruth(self, loads: dict[str, np.ndarray]) -> None:
        rows = ([csv_safe(k)] + [_fmt(x) for x in p] for k, p in loads.items())
        _write_csv(self.tmp / "loads_groundtruth.csv", LOADS_HEADER, rows)

    def write_blackouts(self, blackouts: list[tuple[int, int, str]]) -> None:
        _write_csv(
            self.tmp / "blackouts_groundtruth.csv",
            BLACKOUTS_HEADER,
            ([str(int(a)), str(int(b)), k] for a, b, k in blackouts),
        )

    def close(self) -> Path:
        """Finish the log: frame lists and manifest, then move it to `root` (replacing only the
        previous log's own files)."""
        for name, frames in self._frames.items():
            _write_csv(
                self.tmp / "mav0" / name / "data.csv",
                ("#timestamp [ns]", "filename"),
                ([str(t), f] for t, f in frames),
            )
        os.unlink(self.tmp / PARTIAL_MARKER)
        files = sorted(str(p.relative_to(self.tmp).as_posix()) for p in self.tmp.rglob("*") if p.is_file())
        with atomic_open(self.tmp / MANIFEST_NAME) as f:
            json.dump(
                {
                    "format": MANIFEST_FORMAT,
                    "written_by": self.written_by,
                    "status": "complete",
                    "files": [{"path": r} for r in files],
                },
                f,
                indent=0,
            )
        if not os.path.lexists(self.root):
            self.tmp.rename(self.root)
        else:
            remove_listed(self.root, self.previous)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.root / MANIFEST_NAME)
            _merge_into(self.tmp, self.root)
            self.tmp.rmdir()
        self._owns_tmp = False
        return self.root


def _os_message(root: Path, e: OSError) -> str:
    where = f" ({e.filename})" if getattr(e, "filename", None) else ""
    return f"{root}: cannot write the flight log: {e.strerror or e}{where}; nothing was kept"


def _previous_log_files(root: Path) -> list[str]:
    """Files of the log in `root` that a FlightLogWriter wrote (its manifest).  Refuses (LogError)
    a root that is not a folder, that holds another command's outputs (a manifest not written by
    a FlightLogWriter, e.g. a run's: replacing "its files" would delete that run), or that holds
    files of the log layout the manifest does not list: they are the user's, and writing the log
    would overwrite them."""
    if not root.is_dir() or root.is_symlink():
        raise LogError(f"{root}: exists and is not a folder")
    manifest = read_manifest(root, LogError)
    if manifest is not None and manifest_writer(manifest) not in FLIGHT_LOG_WRITERS:
        raise LogError(
            f"{root}: holds the outputs of `{manifest_writer(manifest)}` (its {MANIFEST_NAME}), "
            "not a flight log; refusing to overwrite them: choose another folder"
        )
    ours = {e["path"] for e in manifest["files"]} if manifest else set()
    foreign = []
    for name in LOG_CONFLICT_NAMES:
        p = root / name
        if p.is_dir() and not p.is_symlink():
            foreign += [
                q.relative_to(root).as_posix()
                for q in p.rglob("*")
                if not q.is_dir() and q.relative_to(root).as_posix() not in ours
            ]
        elif os.path.lexists(p) and name not in ours:
            foreign.append(name)
    if foreign:
        raise LogError(
            f"{root}: holds {len(foreign)} file(s) that fusion did not write "
            f"(e.g. {', '.join(sorted(foreign)[:3])}); refusing to overwrite them: "
            "choose another folder or move them away"
        )
    return sorted(ours)


def _merge_into(src: Path, dst: Path) -> None:
    """Move every entry of `src` into `dst` (folders merged, files replaced)."""
    for entry in sorted(src.iterdir()):
        target = dst / entry.name
        if entry.is_dir() and target.is_dir() and not target.is_symlink():
            _merge_into(entry, target)
            entry.rmdir()
        else:
            os.replace(entry, target)
