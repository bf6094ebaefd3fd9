"""ROS 1 and ROS 2 bags (sqlite3 or MCAP) as flight logs, through `rosbags` (no ROS install).

Reading (`read_bag`): one pass over the bag's index and messages finds every topic's stamps
(header stamps parsed from the first bytes of the raw message, no deserialisation), the IMU,
velocity, CameraInfo and our own `/fusion/*` topics; images are decoded lazily, frame by frame,
by `BagCameraStream.load_image` (a worker process opens its own reader).

Roles by type: sensor_msgs/Image or CompressedImage -> cameras (floor = Kalibr cam0 topic,
else the first in name order), sensor_msgs/Imu -> IMU, geometry_msgs/TwistStamped (else
nav_msgs/Odometry) -> body-frame velocity.  LogOptions topics override.

Calibration, first found: a Kalibr camchain (or an EuRoC folder's sensor.yaml) given in
LogOptions.calib; the bag's `/fusion/metadata` (written by `write_bag`); CameraInfo (intrinsics
only: then the camera-IMU extrinsics must come from a camchain, which is an error otherwise).

Writing (`write_bag`): images as sensor_msgs/Image mono8 (or CompressedImage png / jpeg),
CameraInfo, Imu, TwistStamped velocity, ground truth as nav_msgs/Odometry on
`/fusion/groundtruth`, and one std_msgs/String `/fusion/metadata` holding world.yaml, each
sensor.yaml, the load ground truth and the blackouts, so an exported bag reads back exactly.
"""

from __future__ import annotations

import hashlib
import heapq
import logging
import os
import shutil
import struct
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import yaml

from fusion.camera import CameraModel
from fusion.errors import CameraModelError, LogError
from fusion.geometry import R_from_quat_wxyz
from fusion.log.euroc import (
    CameraStream,
    FlightLog,
    Frame,
    GroundTruth,
    ImuData,
    ImuNoise,
    LogWarning,
    StreamSource,
    VelocityData,
    decode_image_bytes,
    gray16_to_8,
    truncated_image,
)
from fusion.log.options import LogOptions, StampSource
from fusion.types import CameraRole

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import Connection

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMU = "sensor_msgs/msg/Imu"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TWIST = "geometry_msgs/msg/TwistStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
STRING = "std_msgs/msg/String"
IMAGE_TYPES = (IMAGE, COMPRESSED)
VELOCITY_TYPES = (TWIST, ODOMETRY)  # preference order
NO_TOPIC = "none"  # --front-topic none / --velocity-topic none
MIXED_MSGTYPES = "(several message types)"  # a topic whose connections differ in type (rosbags: None)
METADATA_TOPIC = "/fusion/metadata"
GROUNDTRUTH_TOPIC = "/fusion/groundtruth"
METADATA_VERSION = 1
DEFAULT_VELOCITY_NOISE_M_S = 0.05
HEADER_STAMP_OFFSET = 4  # sec (4 bytes) + nsec (4 bytes) after the CDR encapsulation header
# (ROS 2) or after the uint32 seq (ROS 1)
MIN_MESSAGE_BYTES = 12
CDR_HEADER_BYTES = 4  # CDR alignment counts from the end of the encapsulation header
BAYER_TO_GRAY = {  # ROS names the first two pixels; OpenCV the 2nd row's 2nd/3rd
    "bayer_rggb8": cv2.COLOR_BayerBG2GRAY,  # (cv_bridge's mapping)
    "bayer_bggr8": cv2.COLOR_BayerRG2GRAY,
    "bayer_gbrg8": cv2.COLOR_BayerGR2GRAY,
    "bayer_grbg8": cv2.COLOR_BayerGB2GRAY,
}
COLOR_TO_GRAY = {
    "bgr8": cv2.COLOR_BGR2GRAY,
    "rgb8": cv2.COLOR_RGB2GRAY,
    "bgra8": cv2.COLOR_BGRA2GRAY,
    "rgba8": cv2.COLOR_RGBA2GRAY,
}
GRAY_ENCODINGS = ("mono8", "8UC1", "mono16", "16UC1")
SUPPORTED_ENCODINGS = GRAY_ENCODINGS + tuple(COLOR_TO_GRAY) + tuple(BAYER_TO_GRAY)
COMPRESSED_FORMATS = ("jpeg", "jpg", "png")
IMAGE_FORMATS = ("raw", "png", "jpeg")  # write_bag image_format
JPEG_QUALITY = 95


# ============================================================================ small helpers


def typestore_for(ros1: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def is_ros1(path: Path) -> bool:
    return Path(path).suffix == ".bag"


def header_stamp_ns(raw: bytes | memoryview, ros1: bool) -> int | None:
    """header.stamp of a raw message whose first field is a std_msgs/Header, or None if short."""
    if len(raw) < MIN_MESSAGE_BYTES:
        return None
    little = True if ros1 else raw[1] == 1  # CDR encapsulation: 0x0001 = little endian
    sec, nsec = struct.unpack_from("<iI" if little else ">iI", raw, HEADER_STAMP_OFFSET)
    return sec * 1_000_000_000 + nsec


def _after_string(raw, off: int, ros1: bool, little: bool) -> int:
    """Offset just past a serialised string starting at `off` (CDR: uint32 length aligned to 4
    from the start of the payload, after the 4-byte encapsulation header)."""
    if not ros1:
        off += -(off - CDR_HEADER_BYTES) % 4
    (n,) = struct.unpack_from("<I" if little else ">I", raw, off)
    return off + 4 + n


def raw_doubles(raw, ros1: bool, n_strings: int, count: int) -> np.ndarray:
    """`count` float64 right after the Header and `n_strings` more strings of a raw message.
    Imu, TwistStamped and Odometry are fixed-size after those, so this reads their numbers
    without deserialising (about 100x faster than rosbags' generic deserialiser)."""
    little = True if ros1 else raw[1] == 1
    off = HEADER_STAMP_OFFSET + 8  # past stamp sec, nsec
    for _ in range(1 + n_strings):  # header.frame_id, then the others
        off = _after_string(raw, off, ros1, little)
    if not ros1:
        off += -(off - CDR_HEADER_BYTES) % 8  # float64 alignment
    return np.frombuffer(raw, dtype="<f8" if little else ">f8", count=count, offset=off)


# (strings after the header, float64s to read, columns wanted) per type: the field order of
# sensor_msgs/Imu (orientation 4, its covariance 9, angular_velocity 3, covariance 9,
# linear_acceleration 3), geometry_msgs/TwistStamped (linear 3, angular 3) and nav_msgs/Odometry
# (child_frame_id; position 3, orientation xyzw 4, covariance 36, twist linear 3, ...).
RAW_LAYOUTS = {
    IMU: (0, 28, np.r_[13:16, 25:28]),  # gyro xyz, accel xyz
    TWIST: (0, 3, np.r_[0:3]),  # linear xyz
    ODOMETRY: (1, 46, np.r_[0:7, 43:46]),  # p xyz, q xyzw, twist linear xyz
}


def stamp_ns(t) -> int:
    """builtin_interfaces/Time (sec, nanosec) -> ns."""
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def _field(msg, *names):
    """The first attribute present (ROS 1 CameraInfo has K / D, ROS 2 k / d)."""
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


_BYTES_PER_PIXEL = {"mono16": 2, "16UC1": 2, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}
"""Raw Image encodings of more than one byte a pixel (mono8, 8UC1 and Bayer: one)."""


def decode_image(msg, msgtype: str) -> np.ndarray:
    """A sensor_msgs/Image or CompressedImage as uint8 grayscale (H, W).  Raises ValueError with
    the reason for an unsupported encoding or a malformed message."""
    if msgtype == COMPRESSED:
        fmt = str(msg.format).lower()
        if not any(f in fmt for f in COMPRESSED_FORMATS):
            raise ValueError(f"CompressedImage format {msg.format!r} is not supported (jpeg or png)")
        payload = bytes(msg.data)
        truncated = truncated_image(payload)
        if truncated:
            # said here: libpng would print its own error line on stderr for every frame
            raise ValueError(f"CompressedImage ({msg.format}) is truncated ({truncated})")
        img = decode_image_bytes(payload)
        if img is None or img.size == 0:
            raise ValueError(f"CompressedImage ({msg.format}) does not decode")
        return img
    enc, h, w, step = str(msg.encoding), int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if enc not in SUPPORTED_ENCODINGS:
        raise ValueError(f"image encoding {enc!r} is not supported (one of {', '.join(SUPPORTED_ENCODINGS)})")
    if h < 1 or w < 1 or step * h > data.size:
        raise ValueError(f"image {w}x{h} step {step} holds {data.size} bytes")
    bpp = _BYTES_PER_PIXEL.get(enc, 1)
    if data.size != step * h or step < w * bpp:
        # sensor_msgs/Image: data is step x height bytes, a row at least width x pixel size: more
        # is another format under this label (rgb8 published as mono8 read as grey stripes)
        raise ValueError(
            f"image {w}x{h} {enc} step {step} holds {data.size} bytes, not step x height = {step * h} "
            f"with a row of at least {w * bpp}: its encoding, width or step is not its data's"
        )
    rows = data[: step * h].reshape(h, step)
    if enc in ("mono16", "16UC1"):
        # full scale of a 16-bit container whatever the sensor's bit depth: stretch to 8 bits
        return gray16_to_8(rows[:, : 2 * w].copy().view(">u2" if msg.is_bigendian else "<u2"))
    if enc in ("mono8", "8UC1") or enc in BAYER_TO_GRAY:
        img = np.ascontiguousarray(rows[:, :w])
        return img if enc in ("mono8", "8UC1") else cv2.cvtColor(img, BAYER_TO_GRAY[enc])
    ch = 4 if enc in ("bgra8", "rgba8") else 3
    img = np.ascontiguousarray(rows[:, : w * ch]).reshape(h, w, ch)
    return cv2.cvtColor(img, COLOR_TO_GRAY[enc])


# ============================================================================ scanning


@dataclass
class TopicScan:
    """Every message of one topic, in the bag's (receive-time) order."""

    topic: str
    msgtype: str
    log_ns: list[int] = field(default_factory=list)
    header_ns: list[int | None] = field(default_factory=list)
    # first message, deserialised (images, CameraInfo, String); Any: rosbags makes its class at run time
    first: Any = None
    data: list = field(default_factory=list)  # deserialised messages (IMU, velocity, GT)


@dataclass
class BagScan:
    path: Path
    ros1: bool
    topics: dict[str, TopicScan]
    types: dict[str, str]  # every topic in the bag -> msgtype
    counts: dict[str, int]  # every topic -> message count (from the index)
    truncated: str | None = None  # where reading stopped early, if it did


def _open_reader(path: Path) -> AnyReader:
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([Path(path)], default_typestore=typestore_for(is_ros1(path)))
        reader.open()
    except FileNotFoundError:
        raise LogError(f"{path}: not found") from None
    except Exception as e:  # noqa: BLE001 - rosbags raises many types for a damaged bag
        fix = (
            "if it is truncated, `rosbag reindex` it"
            if is_ros1(path)
            else "if it is truncated, `mcap recover` it"
            if Path(path).suffix == ".mcap"
            else "is metadata.yaml intact?"
        )
        raise LogError(
            f"{path}: cannot open as a {'ROS 1' if is_ros1(path) else 'ROS 2'} bag "
            f"({e.__class__.__name__}: {str(e)[:160]}); {fix}"
        ) from None
    return reader


def readable_bag(path: Path) -> Path:
    """`path`, or for a bag cut short a readable copy of its complete messages
    (readable_bag_and_note)."""
    return readable_bag_and_note(path)[0]


def readable_bag_and_note(path: Path, warnings: list[LogWarning] | None = None) -> tuple[Path, str | None]:
    """(`path`, None), or for a ROS 1 bag that rosbags cannot open (cut short, so unindexed)
    an indexed copy of its complete messages (fusion.log.ros1recover), or for an MCAP file
    without its footer (a recording cut short) a copy of its complete records
    (fusion.log.mcaprecover), with a one-line note of what was read.  A copy of a sqlite3 bag
    leaves out messages of unknown types: `bag_unknown_types_left_out` in `warnings`."""
    path = Path(path)
    if path.is_dir() or path.suffix == ".db3":
        return _readable_ros2(path, warnings)
    if not path.is_file():
        return path, None
    if is_ros1(path):
        from rosbags.rosbag1 import Reader as Reader1

        try:
            with Reader1(path):
                return path, None
        except Exception:  # noqa: BLE001 - rosbags' ReaderError and struct errors of a cut header
            from fusion.log.ros1recover import recovered_copy

            copy = recovered_copy(path)
            return copy, f"{path}: truncated or unindexed ROS 1 bag; read the complete messages ({copy})"
    if path.suffix == ".mcap":
        from rosbags.rosbag2.storage_mcap import McapReader

        try:
            reader = McapReader(path)
            reader.open()
            reader.close()
            return path, None
        except Exception:  # noqa: BLE001 - rosbags raises many types for a damaged file
            from fusion.log.mcaprecover import recovered_mcap

            copy, note = recovered_mcap(path)
            log.warning(note)
            return copy, note
    return path, None


def _readable_ros2(path: Path, warnings: list[LogWarning] | None = None) -> tuple[Path, str | None]:
    """A ROS 2 bag folder (or .db3 file) as readable_bag_and_note: as it is when rosbags opens
    it; a folder without metadata.yaml holding one .mcap file: that file; else, with .db3
    files, a copy of their readable messages (fusion.log.sqliterecover)."""
    from rosbags.highlevel import AnyReader

    if path.is_dir() and not (path / "metadata.yaml").is_file():
        mcaps = sorted(path.glob("*.mcap"))
        if len(mcaps) == 1 and not any(path.glob("*.db3")):
            copy, note = readable_bag_and_note(mcaps[0])
            return copy, note or f"{path}: no metadata.yaml; read {mcaps[0].name} alone"
    elif path.is_dir():
        try:
            with AnyReader([path], default_typestore=typestore_for(False)):
                return path, None
        except Exception:  # noqa: BLE001 - rosbags raises many types for a damaged bag
            if not any(path.glob("*.db3")):
                return path, None  # _open_reader names the problem
    from fusion.log.sqliterecover import recovered_sqlite_bag

    copy, note = recovered_sqlite_bag(path, warnings)
    if note:
        log.warning(note)
    return copy, note


def scan_bag(
    path: Path,
    vectors: set[str] | None = None,
    first_of: set[str] | None = None,
    topics: set[str] | None = None,
) -> BagScan:
    """One pass over the bag: stamps of every message of `topics` (all when None), the numbers
    of `vectors` topics (Imu, TwistStamped, Odometry: RAW_LAYOUTS) in `TopicScan.data`, the
    first message of `first_of` topics deserialised.  A read error part-way stops the pass with
    a warning (`BagScan.truncated`)."""
    path = Path(path)
    vectors, first_of = vectors or set(), first_of or set()
    reader = _open_reader(path)
    ros1 = is_ros1(path)
    try:
        types = {t: info.msgtype or MIXED_MSGTYPES for t, info in reader.topics.items()}
        counts = {t: int(info.msgcount) for t, info in reader.topics.items()}
        want = [c for c in reader.connections if topics is None or c.topic in topics]
        scans = {t: TopicScan(t, types[t]) for t in types if topics is None or t in topics}
        truncated = None
        n = 0
        it = reader.messages(connections=want) if want else iter(())  # () would mean all
        while True:
            try:
                item = next(it)
            except StopIteration:
                break
            except Exception as e:  # noqa: BLE001
                truncated = (
                    f"{path}: read error after {n} messages "
                    f"({e.__class__.__name__}: {str(e)[:120]}); using what came before"
                )
                log.warning(truncated)
                break
            con, t_log, raw = item
            n += 1
            s = scans[con.topic]
            s.log_ns.append(int(t_log))
            s.header_ns.append(header_stamp_ns(raw, ros1))
            where = f"{path}: topic {con.topic} message {len(s.log_ns) - 1}"
            if s.first is None and (con.topic in first_of or con.topic in vectors):
                try:
                    s.first = reader.deserialize(raw, con.msgtype)
                except Exception as e:  # noqa: BLE001
                    raise LogError(f"{where}: cannot deserialise ({str(e)[:120]})") from None
            if con.topic in vectors:
                n_str, count, cols = RAW_LAYOUTS[con.msgtype]
                try:
                    s.data.append(raw_doubles(raw, ros1, n_str, count)[cols])
                except (struct.error, ValueError, IndexError):
                    raise LogError(f"{where}: malformed {con.msgtype}") from None
    finally:
        reader.close()
    return BagScan(path, ros1, scans, types, counts, truncated)


def choose_times(
    scan: TopicScan, stamps: StampSource, where: str, warnings: list[LogWarning] | None = None
) -> np.ndarray:
    """Per-message times (ns) of a topic: header stamps (falling back to receive time when the
    header is empty) or receive time.  The fallback is a named warning in `warnings`
    (`bag_receive_time`, count: the topic's messages): that topic is then on the recorder's
    clock, with its transport delay and jitter, while the others keep their sensors' stamps
    (a driver that leaves header.stamp empty is common), which the time-offset estimate and the
    stamp-jitter check must then absorb."""
    log_ns = np.asarray(scan.log_ns, dtype=np.int64)
    if stamps == StampSource.RECEIVE:
        return log_ns
    hdr = scan.header_ns
    # every stamp 0: none set (one message stamped 0 may be a clock's first instant: a topic of
    # a single message, such as a flight's camera_info at t = 0, said "no header stamps")
    if any(h is None for h in hdr) or (len(hdr) > 1 and all(h == 0 for h in hdr)):
        message = (
            f"{where}: topic {scan.topic} has no header stamps; using the bag's receive time "
            "(the recorder's clock, with its transport delay and jitter)"
        )
        log.warning(message)
        if warnings is not None:
            warnings.append(LogWarning("bag_receive_time", len(log_ns), message))
        return log_ns
    return np.asarray(hdr, dtype=np.int64)


UNSET_STAMP_CLOCK_NS = 86_400 * 10**9
"""A header stamp of 0 is unset (not the first instant of a clock starting at 0) when the
topic's other stamps are more than a day from it: an epoch-stamped driver that publishes 0
before its clock is synchronised."""


def times_in_order(
    scan: TopicScan,
    stamps: StampSource,
    where: str,
    path: Path,
    warnings: list[LogWarning] | None = None,
    shift_ns: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """A topic's times (choose_times, plus `shift_ns`) and the index of its messages in time
    order (sort_unique), without the messages whose header stamp is unset (0 among stamps a day
    or more away, UNSET_STAMP_CLOCK_NS): those are dropped and counted as `stamps_unset`.  They
    were kept at t = 0, 1.7e9 s before the rest of an epoch-stamped flight, and the smoother
    split that span into 11 million windows."""
    t = choose_times(scan, stamps, str(path), warnings)
    unset = np.zeros(len(t), bool)
    if stamps == StampSource.HEADER and len(t) and t.max() > UNSET_STAMP_CLOCK_NS:
        unset = t == 0
    n_unset = int(unset.sum())
    if n_unset:
        message = (
            f"{where}: {n_unset} message(s) with an unset header stamp (0, the others from "
            f"{t[~unset].min() * 1e-9:.10g} s), dropped"
        )
        log.warning(message)
        if warnings is not None:
            warnings.append(LogWarning("stamps_unset", n_unset, message))
    t = t + shift_ns
    kept = np.flatnonzero(~unset)
    order, _, _ = sort_unique(t[kept], where, warnings)
    return t, kept[order]


def sort_unique(
    t: np.ndarray, what: str, warnings: list[LogWarning] | None = None
) -> tuple[np.ndarray, int, int]:
    """Stable order by time with duplicates dropped (the first kept): (index, n_out_of_order,
    n_duplicates); both counts are logged as warnings, and appended to `warnings` as named,
    counted LogWarnings (`stamps_out_of_order`, `stamps_duplicate`)."""
    order = np.argsort(t, kind="stable")
    n_back = int(np.sum(np.diff(t) < 0)) if len(t) > 1 else 0
    ts = t[order]
    keep = np.r_[True, np.diff(ts) > 0] if len(ts) else np.zeros(0, bool)
    n_dup = int(np.sum(~keep))
    if n_back:
        log.warning("%s: %d out-of-order stamp(s), sorted", what, n_back)
        if warnings is not None:
            warnings.append(LogWarning("stamps_out_of_order", n_back, f"{what}: out-of-order stamps, sorted"))
    if n_dup:
        log.warning("%s: %d duplicate stamp(s), the later message(s) dropped", what, n_dup)
        if warnings is not None:
            warnings.append(
                LogWarning("stamps_duplicate", n_dup, f"{what}: duplicate stamps, later message(s) dropped")
            )
    return order[keep], n_back, n_dup


# ============================================================================ roles


@dataclass
class Roles:
    floor: str  # always found (assign_roles raises otherwise)
    front: str | None
    imu: str | None
    velocity: str | None
    unused_images: list[str] = field(default_factory=list)  # image topics given no role


def _topics_of(types: dict[str, str], wanted: tuple[str, ...], exclude=()) -> list[str]:
    return sorted(t for t, ty in types.items() if ty in wanted and t not in exclude)


def _listing(types: dict[str, str]) -> str:
    return ", ".join(f"{t} ({ty})" for t, ty in sorted(types.items())) or "nothing"


def assign_roles(
    path: Path,
    types: dict[str, str],
    opts: LogOptions,
    kalibr_topics: dict[str, str] | None = None,
    metadata: dict | None = None,
) -> Roles:
    """Which topic fills which role.  Overrides first, then our metadata / Kalibr's rostopic,
    then by type (cameras in name order: floor first).  Raises LogError listing the bag's
    topics when a needed role is empty or ambiguous."""

    def check(topic, wanted, what):
        if topic is None:
            return None
        if topic not in types:
            raise LogError(f"{path}: {what} topic {topic} is not in the bag; it holds {_listing(types)}")
        if types[topic] not in wanted:
            raise LogError(f"{path}: {what} topic {topic} is {types[topic]}, expected {' or '.join(wanted)}")
        return topic

    named = dict((metadata or {}).get("topics", {}) or {})
    for key, topic in (kalibr_topics or {}).items():
        named.setdefault(key, topic)
    images = _topics_of(types, IMAGE_TYPES)
    unused: list[str] = []
    floor = opts.floor_topic or named.get(CameraRole.FLOOR.value)
    no_front = opts.front_topic == NO_TOPIC
    front = None if no_front else opts.front_topic or named.get(CameraRole.FRONT.value)
    floor = check(floor if floor in types or opts.floor_topic else None, IMAGE_TYPES, "floor")
    front = check(
        front if front in types or (opts.front_topic and not no_front) else None, IMAGE_TYPES, "front"
    )
    if floor is not None and floor == front:
        raise LogError(
            f"{path}: topic {floor} given as both the floor and the front camera; one camera "
            "cannot be both (--floor-topic, --front-topic)"
        )
    rest = [t for t in images if t not in (floor, front)]
    if floor is None:
        if not rest:
            raise LogError(
                f"{path}: no camera topic (sensor_msgs/Image or CompressedImage); "
                f"the bag holds {_listing(types)}"
            )
        if len(rest) > 2 and front is None and not no_front:
            raise LogError(
                f"{path}: {len(rest)} image topics ({', '.join(rest)}); say which with "
                "--floor-topic and --front-topic"
            )
        floor = rest.pop(0)
    if no_front:
        pass
    elif front is None and len(rest) == 1:
        front = rest.pop(0)
    elif front is None and rest:
        log.warning(
            "%s: image topics %s not used; --front-topic picks the front camera", path, ", ".join(rest)
        )
        unused = rest
    imu = check(opts.imu_topic or named.get("imu0"), (IMU,), "IMU")
    if imu is None:
        imus = _topics_of(types, (IMU,))
        if len(imus) > 1:
            raise LogError(f"{path}: {len(imus)} IMU topics ({', '.join(imus)}); say which with --imu-topic")
        imu = imus[0] if imus else None
    no_vel = opts.velocity_topic == NO_TOPIC
    vel = None if no_vel else check(opts.velocity_topic or named.get("vel0"), VELOCITY_TYPES, "velocity")
    if vel is None and not no_vel:
        for ty in VELOCITY_TYPES:
            cands = _topics_of(types, (ty,), exclude=(GROUNDTRUTH_TOPIC,))
            if len(cands) > 1:
                raise LogError(
                    f"{path}: {len(cands)} {ty} topics ({', '.join(cands)}); say "
                    "which is the velocity with --velocity-topic"
                )
            if cands:
                vel = cands[0]
                break
    return Roles(floor, front, imu, vel, unused)


# ============================================================================ camera streams


class BagCameraStream(CameraStream):
    """A camera topic of a bag; images decoded on demand, in order by a continuing iterator,
    otherwise by seeking to the message's receive time.  Picklable (the reader is reopened in
    each process)."""

    def __init__(
        self,
        name: str,
        camera: CameraModel,
        timestamps_ns: np.ndarray,
        bag: Path,
        topic: str,
        msgtype: str,
        seq: np.ndarray,
        log_by_seq: np.ndarray,
        stamps: StampSource,
    ):
        super().__init__(name, camera, np.asarray(timestamps_ns, np.int64), [], [])
        self.bag, self.topic, self.msgtype = Path(bag), topic, msgtype
        self.seq = np.asarray(seq, np.int64)  # message number of frame i
        self.log_by_seq = np.asarray(log_by_seq, np.int64)  # receive time of message k
        self.stamps = stamps
        self._reader: AnyReader | None = None
        self._iter: Iterator[tuple[Connection, int, bytes]] | None = None
        self._next_seq = -1
        self._pid: int | None = None  # process that opened _reader

    def __getstate__(self):
        state = dict(self.__dict__)
        state.update(_reader=None, _iter=None, _next_seq=-1, _pid=None)
        return state

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
        self._reader, self._iter, self._next_seq = None, None, -1

    def fingerprint(self) -> bytes:
        """Identity of this stream for the detection cache: bag path, size and mtime, topic,
        stamps and camera model."""
        h = hashlib.sha256()
        st = self.bag.stat()
        h.update(f"{self.bag.resolve()}|{st.st_size}|{st.st_mtime_ns}|{self.topic}|{self.stamps}\n".encode())
        h.update(self.timestamps_ns.tobytes())
        h.update(yaml.safe_dump(self.camera.to_sensor_yaml(), sort_keys=True).encode())
        return h.digest()

    def _seek(self, k: int) -> Iterator[tuple[Connection, int, bytes]]:
        if self._reader is not None and self._pid != os.getpid():
            # a forked worker shares the parent's file offsets: never read through them
            self._reader, self._iter = None, None
        if self._reader is None:
            self._reader = _open_reader(self.bag)
            self._pid = os.getpid()
        cons = [c for c in self._reader.connections if c.topic == self.topic]
        start = int(self.log_by_seq[k])
        first = int(np.searchsorted(self.log_by_seq, start, side="left"))
        it = self._iter = self._reader.messages(connections=cons, start=start)
        self._next_seq = first
        while self._next_seq < k:
            next(it)
            self._next_seq += 1
        return it

    def _raw(self, k: int) -> tuple[Connection, bytes]:
        it = self._iter
        if it is None or self._next_seq != k or self._pid != os.getpid():
            it = self._seek(k)
        con, _, raw = next(it)
        self._next_seq += 1
        return con, raw

    def load_image(self, i: int) -> np.ndarray | None:
        k = int(self.seq[i])
        where = f"{self.bag}: topic {self.topic} message {k}"
        try:
            con, raw = self._raw(k)
            if self._reader is None:  # _raw opened it
                raise LogError(f"{where}: the bag reader is not open")
            img = decode_image(self._reader.deserialize(raw, con.msgtype), con.msgtype)
        except StopIteration:
            self.skipped.append(f"{where}: missing (bag ends early)")
            self._iter = None
            return None
        except ValueError as e:
            self.skipped.append(f"{where}: {e}")
            return None
        except Exception as e:  # noqa: BLE001 - a damaged message: skip it, say why
            self.skipped.append(f"{where}: unreadable ({e.__class__.__name__})")
            self._iter = None
            return None
        if img.shape != (self.camera.height, self.camera.width):
            self.skipped.append(
                f"{where}: image is {img.shape[1]}x{img.shape[0]}, the "
                f"calibration says {self.camera.width}x{self.camera.height}"
            )
            return None
        return img

    def frames(self) -> Iterator[Frame]:
        for i, t in enumerate(self.timestamps_ns):
            yield Frame(int(t), self.load_image(i), self.bag)
        self.close()


# ============================================================================ calibration


def camera_from_info(info, where: str) -> CameraModel:
    """Intrinsics and distortion from a CameraInfo (plumb_bob k1, k2, p1, p2, k3, or equidistant
    k1..k4); T_body_cam identity: callers must supply the extrinsics."""
    K = np.asarray(_field(info, "k", "K"), float).reshape(3, 3)
    D = np.asarray(_field(info, "d", "D"), float).reshape(-1)
    model = str(info.distortion_model)
    equi = model == "equidistant"
    # plumb_bob: OpenCV's k1, k2, p1, p2, k3; rational_polynomial adds k4..k6 (a denominator we
    # do not model: refused unless zero); equidistant: k1..k4
    n_used = 4 if equi else 5
    if (model not in ("plumb_bob", "rational_polynomial", "") and not equi) or (
        len(D) > n_used and np.any(np.abs(D[n_used:]) > 1e-12)
    ):
        raise LogError(
            f"{where}: distortion {model!r} with coefficients {D.tolist()} is not "
            "supported (plumb_bob k1, k2, p1, p2, k3, or equidistant k1..k4)"
        )
    dist = np.zeros(5)
    dist[: min(n_used, len(D))] = D[:n_used]
    if K[0, 0] <= 0 or K[1, 1] <= 0 or int(info.width) < 1 or int(info.height) < 1:
        raise LogError(f"{where}: CameraInfo has no calibration (zero K or size)")
    cam = CameraModel(
        int(info.width),
        int(info.height),
        K[0, 0],
        K[1, 1],
        K[0, 2],
        K[1, 2],
        distortion=dist[:4],
        k3=0.0 if equi else float(dist[4]),
        distortion_model="equidistant" if equi else "radtan",
    )
    try:
        cam.check_lens(f"{where}: CameraInfo")
    except CameraModelError as e:
        raise LogError(str(e)) from None
    return cam


def camera_info_msg(cam: CameraModel, stamp_ns: int, frame_id: str, ros1: bool, ts):
    Roi = ts.types["sensor_msgs/msg/RegionOfInterest"]
    Info = ts.types[CAMERA_INFO]
    K = cam.K.reshape(-1)
    P = np.c_[cam.K, np.zeros(3)].reshape(-1)
    d = cam.dist_cv
    arrays = {"d": d, "k": K, "r": np.eye(3).reshape(-1), "p": P}
    if ros1:
        arrays = {k.upper(): v for k, v in arrays.items()}
    return Info(
        header=_header(ts, stamp_ns, frame_id, ros1),
        height=cam.height,
        width=cam.width,
        distortion_model="equidistant" if cam.equidistant else "plumb_bob",
        binning_x=0,
        binning_y=0,
        roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        **{k: np.asarray(v, float) for k, v in arrays.items()},
    )


def _header(ts, stamp_ns: int, frame_id: str, ros1: bool):
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    t = Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))
    return Header(seq=0, stamp=t, frame_id=frame_id) if ros1 else Header(stamp=t, frame_id=frame_id)


def _metadata_cameras(meta: dict, where: str) -> dict[str, CameraModel]:
    out = {}
    for name, sensor in (meta.get("cameras") or {}).items():
        try:
            out[name] = CameraModel.from_sensor_yaml(sensor, f"{where} cameras.{name}")
        except CameraModelError as e:
            raise LogError(str(e)) from None
    return out


# ============================================================================ reading


@dataclass
class BagPass:
    """A bag as `fusion inspect` has already read it, for `read_bag` to build the run's log from
    without reading it again: its readable form (`readable_bag_and_note`: a recovered copy of a
    damaged bag), that call's note and warnings, and one `scan_bag` pass with the `vectors` and
    `first_of` topics it decoded."""

    bag: Path
    damage: str | None
    left_out: list[LogWarning]
    scan: BagScan
    vectors: set[str]
    first_of: set[str]

    def covers(self, topics: set[str], vectors: set[str], first_of: set[str]) -> bool:
        """Whether this pass read what a scan of `topics` with these `vectors` and `first_of`
        would have: every topic, their numbers and their first messages."""
        return topics <= set(self.scan.topics) and vectors <= self.vectors and first_of <= self.first_of


def read_bag(path: Path, opts: LogOptions | None = None, done: BagPass | None = None) -> FlightLog:
    """Open a ROS 1 (.bag) or ROS 2 (folder or .mcap) bag as a FlightLog; images stream.  `done`:
    the pass `fusion inspect` made over it (BagPass), reused where it covers the run's topics."""
    from fusion.log.sources import external_calibration, find_world  # cycle: sources -> rosbag

    opts = opts or LogOptions()
    path = Path(path)
    if done is None:
        left_out: list[LogWarning] = []  # a sqlite3 copy's messages of unknown types
        bag, damage = readable_bag_and_note(path, left_out)  # errors name `path`; reading goes through `bag`
    else:
        bag, damage, left_out = done.bag, done.damage, list(done.left_out)
    warnings = [LogWarning("bag_truncated", 1, damage)] if damage else []
    warnings += left_out
    first = scan_bag(bag, first_of={METADATA_TOPIC}, topics={METADATA_TOPIC})
    meta: dict = {}
    if first.topics.get(METADATA_TOPIC) and first.topics[METADATA_TOPIC].first is not None:
        try:
            meta = yaml.safe_load(first.topics[METADATA_TOPIC].first.data) or {}
        except yaml.YAMLError:
            raise LogError(f"{path}: topic {METADATA_TOPIC} message 0 is not YAML") from None
    types = first.types
    calib = external_calibration(opts)
    roles = assign_roles(path, types, opts, calib.topics if calib else None, meta)
    if roles.imu is None and roles.velocity is None:
        raise LogError(
            f"{path}: no IMU topic (sensor_msgs/Imu) and no velocity topic; the bag holds {_listing(types)}"
        )
    if roles.unused_images:
        # the front camera is then not chosen: no load map, and nothing else would say why
        warnings.append(
            LogWarning(
                "bag_image_topics_unused",
                len(roles.unused_images),
                f"{path}: image topics {', '.join(roles.unused_images)} not used, so no front camera "
                "(no load map); --front-topic picks it",
            )
        )
    cam_topics = {CameraRole.FLOOR.value: roles.floor}
    if roles.front:
        cam_topics[CameraRole.FRONT.value] = roles.front
    infos = {t: ty for t, ty in types.items() if ty == CAMERA_INFO}
    deser = {t for t in (roles.imu, roles.velocity) if t}
    gt_topic = GROUNDTRUTH_TOPIC if types.get(GROUNDTRUTH_TOPIC) == ODOMETRY else None
    if gt_topic:
        deser.add(gt_topic)
    want = set(cam_topics.values()) | deser | set(infos)
    first_of = set(cam_topics.values()) | set(infos)
    if done is not None and done.covers(want, deser, first_of):
        scan = done.scan
    else:
        scan = scan_bag(bag, vectors=deser, first_of=first_of, topics=want)
    if scan.truncated:
        warnings.append(LogWarning("bag_truncated", 1, scan.truncated))

    meta_cams = _metadata_cameras(meta, f"{path}: {METADATA_TOPIC}")
    cameras: dict[str, CameraStream] = {}
    shifts: dict[str, int] = {}  # Kalibr timeshift added to each camera's stamps
    for name, topic in cam_topics.items():
        ts_scan = scan.topics[topic]
        where = f"{path}: topic {topic}"
        if not ts_scan.log_ns:
            raise LogError(f"{where}: no messages")
        try:
            img = decode_image(ts_scan.first, ts_scan.msgtype)
        except ValueError as e:
            raise LogError(f"{where} message 0: {e}") from None
        cam, shift_ns = _camera_for(name, topic, calib, meta_cams, scan, infos, where)
        t, order = times_in_order(ts_scan, opts.stamps, where, path, warnings, shift_ns)
        shifts[name] = int(shift_ns)
        if len(order) > 1 and name not in meta_cams:
            cam.rate_hz = float(1e9 / np.median(np.diff(t[order])))
        if img.shape != (cam.height, cam.width):
            raise LogError(
                f"{where} message 0: image is {img.shape[1]}x{img.shape[0]}, the "
                f"calibration says {cam.width}x{cam.height}"
            )
        cameras[name] = BagCameraStream(
            name,
            cam,
            t[order],
            bag,
            topic,
            ts_scan.msgtype,
            order,
            np.asarray(ts_scan.log_ns, np.int64),
            opts.stamps,
        )

    imu = None
    if roles.imu:
        imu = _imu_from_scan(scan.topics[roles.imu], opts, calib, meta, path, warnings)
    vel = None
    if roles.velocity:
        vel = _velocity_from_scan(scan.topics[roles.velocity], opts, meta, path, warnings)
    gt = _groundtruth_from_scan(scan.topics[gt_topic], path, warnings) if gt_topic else None
    world = find_world(path, opts, meta.get("world"), f"{path}: {METADATA_TOPIC}")
    loads = {str(k): np.asarray(v, float) for k, v in (meta.get("loads_groundtruth") or {}).items()} or None
    blackouts = (
        [(int(a), int(b), str(k)) for a, b, k in meta["blackouts"]]
        if meta.get("blackouts") is not None
        else None
    )
    out = FlightLog(path, world, cameras, imu, vel, gt, loads, blackouts, warnings=warnings)
    out.timeshift_ns = shifts
    out.stream_sources = _stream_sources(path, cam_topics, roles, gt_topic, calib, meta)
    return out


def _stream_sources(path, cam_topics, roles, gt_topic, calib, meta) -> dict[str, StreamSource]:
    """Each stream's bag and topic as the reader's own warnings name them, the file stating its
    mount (the calibration given, else the bag's /fusion/metadata) and the IMU's rate a Kalibr
    imu.yaml states, for euroc.check_log: a bag has no mav0/<stream>/ to look in."""
    meta_where = f"{path}: {METADATA_TOPIC}"  # as _metadata_cameras names it
    out = {}
    for name, topic in cam_topics.items():
        given = calib is not None and name in calib.cameras
        mount = calib.where.get(name) if given else f"{meta_where} cameras.{name}"
        out[name] = StreamSource(f"{path}: topic {topic}", mount)
    if roles.imu:
        given = calib is not None and calib.imu_noise is not None  # its T_body_imu is used
        mount = calib.where.get("imu0") if given else f"{meta_where} imu" if meta.get("imu") else None
        # a bag's stamps are sec + nsec: a stated rate 1000x off is the yaml's mistake
        rate, said = (calib.imu_rate_hz, calib.imu_rate_said) if calib is not None else (None, None)
        out["imu0"] = StreamSource(f"{path}: topic {roles.imu}", mount, rate, said, stamps_ns=True)
    if roles.velocity:
        out["vel0"] = StreamSource(f"{path}: topic {roles.velocity}")
    if gt_topic:
        out["groundtruth"] = StreamSource(f"{path}: topic {gt_topic}")
    return out


def _camera_for(name, topic, calib, meta_cams, scan, infos, where) -> tuple[CameraModel, int]:
    """Camera model and the camera-to-IMU clock shift (ns) for one camera topic."""
    if calib is not None and name in calib.cameras:
        return calib.cameras[name], calib.timeshift_ns.get(name, 0)
    if name in meta_cams:
        return meta_cams[name], 0
    # CameraInfo in the camera's namespace (…/image_raw -> …/camera_info), else the only one
    ns = topic.rsplit("/", 1)[0]
    cands = [t for t in infos if t.rsplit("/", 1)[0] == ns] or (list(infos) if len(infos) == 1 else [])
    if cands and scan.topics[cands[0]].first is not None:
        cam = camera_from_info(scan.topics[cands[0]].first, f"{where}: CameraInfo {cands[0]}")
        raise LogError(
            f"{where}: CameraInfo {cands[0]} gives the intrinsics ({cam.width}x"
            f"{cam.height}, fu {cam.fu:g}) but not where the camera sits on the drone; "
            "give a Kalibr camchain-imucam.yaml (--calib)"
        )
    raise LogError(
        f"{where}: no calibration (no CameraInfo in the bag); give a Kalibr "
        "camchain-imucam.yaml or an EuRoC folder with --calib"
    )


def _imu_from_scan(s: TopicScan, opts, calib, meta, path, warnings=None) -> ImuData:
    where = f"{path}: topic {s.topic}"
    if not s.data:
        raise LogError(f"{where}: no messages")
    ga = np.array(s.data, dtype=float)
    g, a = ga[:, :3], ga[:, 3:]
    bad = np.flatnonzero(~np.isfinite(np.c_[g, a]).all(axis=1))
    if bad.size:
        raise LogError(f"{where} message {int(bad[0])}: NaN or infinite value")
    t, order = times_in_order(s, opts.stamps, where, path, warnings)
    t, g, a = t[order], g[order], a[order]
    noise, T_bi = ImuNoise(), np.eye(4)
    if calib is not None and calib.imu_noise is not None:
        noise = calib.imu_noise
        T_bi = calib.T_body_imu
    elif meta.get("imu"):
        sensor = meta["imu"]
        try:
            noise = ImuNoise(**{k: float(sensor[k]) for k in vars(ImuNoise())})
            T_bi = np.asarray(sensor["T_BS"]["data"], float).reshape(4, 4)
        except (KeyError, TypeError, ValueError):
            raise LogError(f"{path}: {METADATA_TOPIC} imu block is malformed") from None
    else:
        message = f"{where}: no IMU noise calibration (give a Kalibr imu.yaml with --calib); using defaults"
        log.warning(message)
        if warnings is not None:
            warnings.append(LogWarning("imu_noise_default", 1, message))
    rate = float(1e9 / np.median(np.diff(t))) if len(t) > 1 else 200.0
    return ImuData(t, g, a, noise, T_bi, rate)


def _velocity_from_scan(s: TopicScan, opts, meta, path, warnings=None) -> VelocityData:
    where = f"{path}: topic {s.topic}"
    if not s.data:
        raise LogError(f"{where}: no messages")
    v = np.array(s.data, dtype=float)
    if s.msgtype == ODOMETRY:
        v = v[:, 7:10]
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if bad.size:
        raise LogError(f"{where} message {int(bad[0])}: NaN or infinite value")
    t, order = times_in_order(s, opts.stamps, where, path, warnings)
    noise = float((meta.get("velocity") or {}).get("noise_m_s", 0) or 0)
    if not noise and s.msgtype == ODOMETRY:
        cov = np.asarray(s.first.twist.covariance, float).reshape(6, 6)
        noise = float(np.sqrt(np.mean(np.diag(cov)[:3]))) if np.all(np.diag(cov)[:3] > 0) else 0
    return VelocityData(t[order], v[order], noise or DEFAULT_VELOCITY_NOISE_M_S)


def _groundtruth_from_scan(s: TopicScan, path, warnings=None) -> GroundTruth | None:
    if not s.data:
        return None
    # its stamp problems are named like every topic's: the truth scores the flight
    x = np.array(s.data, dtype=float)
    p, q, v_body = x[:, 0:3], x[:, [6, 3, 4, 5]], x[:, 7:10]  # q: xyzw -> wxyz
    t, order = times_in_order(s, StampSource.HEADER, f"{path}: topic {s.topic}", path, warnings)
    v_world = np.einsum("nij,nj->ni", R_from_quat_wxyz(q), v_body)
    zeros = np.zeros_like(p)  # IMU biases are not carried by the bag
    return GroundTruth(t[order], p[order], q[order], v_world[order], zeros[order], zeros[order])


# ============================================================================ writing


def _image_msg(img: np.ndarray, stamp_ns: int, frame_id: str, ros1: bool, ts, image_format: str):
    header = _header(ts, stamp_ns, frame_id, ros1)
    if image_format == "raw":
        Image = ts.types[IMAGE]
        return IMAGE, Image(
            header=header,
            height=img.shape[0],
            width=img.shape[1],
            encoding="mono8",
            is_bigendian=0,
            step=img.shape[1],
            data=np.ascontiguousarray(img, np.uint8).reshape(-1),
        )
    ext, params = (
        (".png", [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if image_format == "png"
        else (".jpg", [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    )
    ok, buf = cv2.imencode(ext, img, params)
    if not ok:
        raise LogError(f"cannot encode a {image_format} frame at {stamp_ns}")
    Comp = ts.types[COMPRESSED]
    return COMPRESSED, Comp(header=header, format=image_format, data=np.frombuffer(buf.tobytes(), np.uint8))


def _vec3(ts, v):
    return ts.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def write_bag(flight: FlightLog, out: Path, image_format: str = "raw", overwrite: bool = False) -> Path:
    """Write `flight` as a ROS 1 bag (`out` ends in .bag) or a ROS 2 MCAP bag (`out` ends in
    .mcap: one file; otherwise a bag folder).  Streams the frames; returns `out`."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    out = Path(out)
    if image_format not in IMAGE_FORMATS:
        raise LogError(f"image format {image_format!r} is not one of {IMAGE_FORMATS}")
    if out.exists():
        if not overwrite:
            raise LogError(f"{out}: already exists")
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    ros1 = out.suffix == ".bag"
    ts = typestore_for(ros1)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    out.parent.mkdir(parents=True, exist_ok=True)
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    target = tmpdir / (out.name if ros1 else out.stem)
    try:
        writer = Writer1(target) if ros1 else Writer2(target, version=9, storage_plugin=StoragePlugin.MCAP)
        with writer:
            _write_messages(flight, writer, ts, ser, ros1, image_format)
        if ros1:
            target.replace(out)
        elif out.suffix == ".mcap":
            (target / f"{target.name}.mcap").replace(out)
        else:
            target.replace(out)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return out


def _write_messages(flight: FlightLog, writer, ts, ser, ros1: bool, image_format: str) -> None:
    def con(topic, msgtype):
        return writer.add_connection(topic, msgtype, typestore=ts)

    cam_topic = {name: f"/{name}/image_raw" for name in flight.cameras}
    imu_topic, vel_topic = "/imu0", "/vel0"
    meta = {
        "fusion_metadata": METADATA_VERSION,
        "world": flight.world.to_yaml(),
        "topics": {
            **cam_topic,
            **({"imu0": imu_topic} if flight.imu else {}),
            **({"vel0": vel_topic} if flight.velocity else {}),
        },
        "cameras": {n: s.camera.to_sensor_yaml() for n, s in flight.cameras.items()},
    }
    if flight.imu is not None:
        n = flight.imu.noise
        meta["imu"] = {
            **{k: float(getattr(n, k)) for k in vars(ImuNoise())},
            "T_BS": {
                "rows": 4,
                "cols": 4,
                "data": [float(v) for v in np.asarray(flight.imu.T_body_imu).reshape(-1)],
            },
        }
    if flight.velocity is not None:
        meta["velocity"] = {"noise_m_s": float(flight.velocity.noise_m_s), "frame": "body"}
    if flight.loads_groundtruth is not None:
        meta["loads_groundtruth"] = {k: [float(x) for x in v] for k, v in flight.loads_groundtruth.items()}
    if flight.blackouts is not None:
        meta["blackouts"] = [[int(a), int(b), str(k)] for a, b, k in flight.blackouts]

    t0 = min(int(s.timestamps_ns[0]) for s in flight.cameras.values())
    c_meta = con(METADATA_TOPIC, STRING)
    writer.write(c_meta, t0, ser(ts.types[STRING](data=yaml.safe_dump(meta, sort_keys=False)), STRING))
    cons = {}
    image_type = IMAGE if image_format == "raw" else COMPRESSED
    for name in flight.cameras:
        cons[name] = con(cam_topic[name], image_type)
        cons[name + "/info"] = con(f"/{name}/camera_info", CAMERA_INFO)

    def camera_items(name):
        stream = flight.cameras[name]
        for frame in stream.frames():
            if frame.image is not None:
                yield frame.timestamp_ns, 0, name, frame.image

    def imu_items():
        imu = flight.imu
        for t, w, a in zip(imu.timestamps_ns, imu.gyro_rad_s, imu.accel_m_s2):
            yield int(t), 1, "imu", (w, a)

    def vel_items():
        vel = flight.velocity
        for t, v in zip(vel.timestamps_ns, vel.v_body_m_s):
            yield int(t), 2, "vel", v

    def gt_items():
        gt = flight.groundtruth
        R = R_from_quat_wxyz(gt.q_world_body_wxyz)
        v_body = np.einsum("nji,nj->ni", R, gt.v_world)  # R^T v_world
        for k, t in enumerate(gt.timestamps_ns):
            yield int(t), 3, "gt", (gt.p_world[k], gt.q_world_body_wxyz[k], v_body[k])

    sources = [camera_items(n) for n in sorted(flight.cameras)]
    if flight.imu is not None:
        c_imu = con(imu_topic, IMU)
        sources.append(imu_items())
    if flight.velocity is not None:
        c_vel = con(vel_topic, TWIST)
        sources.append(vel_items())
    if flight.groundtruth is not None:
        c_gt = con(GROUNDTRUTH_TOPIC, ODOMETRY)
        sources.append(gt_items())
    T = ts.types
    Quat = T["geometry_msgs/msg/Quaternion"]
    info_sent = set()
    for t, _, kind, item in heapq.merge(*sources, key=lambda x: (x[0], x[1], x[2])):
        if kind in flight.cameras:
            if kind not in info_sent:
                info = camera_info_msg(flight.cameras[kind].camera, t, kind, ros1, ts)
                writer.write(cons[kind + "/info"], t, ser(info, CAMERA_INFO))
                info_sent.add(kind)
            msgtype, msg = _image_msg(item, t, kind, ros1, ts, image_format)
            writer.write(cons[kind], t, ser(msg, msgtype))
        elif kind == "imu":
            w, a = item
            msg = T[IMU](
                header=_header(ts, t, "imu0", ros1),
                orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.r_[-1.0, np.zeros(8)],  # -1: no orientation
                angular_velocity=_vec3(ts, w),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=_vec3(ts, a),
                linear_acceleration_covariance=np.zeros(9),
            )
            writer.write(c_imu, t, ser(msg, IMU))
        elif kind == "vel":
            msg = T[TWIST](
                header=_header(ts, t, "body", ros1),
                twist=T["geometry_msgs/msg/Twist"](linear=_vec3(ts, item), angular=_vec3(ts, np.zeros(3))),
            )
            writer.write(c_vel, t, ser(msg, TWIST))
        else:
            p, q, vb = item
            pose = T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
                    orientation=Quat(w=float(q[0]), x=float(q[1]), y=float(q[2]), z=float(q[3])),
                ),
                covariance=np.zeros(36),
            )
            twist = T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=_vec3(ts, vb), angular=_vec3(ts, np.zeros(3))),
                covariance=np.zeros(36),
            )
            msg = T[ODOMETRY](
                header=_header(ts, t, "world", ros1), child_frame_id="body", pose=pose, twist=twist
            )
            writer.write(c_gt, t, ser(msg, ODOMETRY))
