"""PX4 ULog (.ulg) through pyulog: the IMU from `sensor_combined`, frame times from
`camera_capture` (else `camera_trigger`) when the log has them.

PX4's body frame is FRD (x forward, y right, z down); ours is FLU, so the samples stay in the
IMU frame S = FRD and `ImuData.T_body_imu` = T_FLU_FRD (a 180 degree turn about x).  ULog
timestamps are microseconds since boot.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from fusion.errors import LogError
from fusion.log.euroc import ImuData, ImuNoise, LogWarning
from fusion.log.rosbag import sort_unique

log = logging.getLogger(__name__)

IMU_TOPIC = "sensor_combined"
CAPTURE_TOPICS = ("camera_capture", "camera_trigger")  # preference order
NS_PER_US = 1000
T_FLU_FRD = np.diag([1.0, -1.0, -1.0, 1.0])
"""Pose of PX4's FRD body/IMU frame in our FLU body frame (rotation by pi about x)."""


def _open(path: Path, topics: list[str] | None):
    """The ULog at `path`, reading only `topics` (every topic when None)."""
    from pyulog import ULog

    try:
        return ULog(str(path), topics)
    except FileNotFoundError:
        raise LogError(f"{path}: not found") from None
    except Exception as e:  # noqa: BLE001 - pyulog raises several types for a damaged file
        raise LogError(f"{path}: not a readable PX4 ULog ({e.__class__.__name__}: {str(e)[:120]})") from None


def _dataset(ulog, name: str):
    sets = [d for d in ulog.data_list if d.name == name]
    return min(sets, key=lambda d: d.multi_id) if sets else None


def read_ulog_imu(
    path: Path, noise: ImuNoise | None = None, warnings: list[LogWarning] | None = None
) -> ImuData:
    """IMU samples of `sensor_combined` (gyro and accel in FRD; T_body_imu = T_FLU_FRD), sorted,
    duplicates dropped; those are named, counted LogWarnings in `warnings`
    (`stamps_out_of_order`, `stamps_duplicate`, as a bag's topics give them)."""
    path = Path(path)
    ulog = _open(path, [IMU_TOPIC])
    ds = _dataset(ulog, IMU_TOPIC)
    if ds is None:
        names = sorted({d.name for d in _open(path, None).data_list})
        raise LogError(f"{path}: no '{IMU_TOPIC}' topic; the ULog holds {', '.join(names) or 'no data'}")
    d = ds.data
    try:
        t = np.asarray(d["timestamp"], np.int64) * NS_PER_US
        gyro = np.c_[[np.asarray(d[f"gyro_rad[{i}]"], float) for i in range(3)]].T
        acc = np.c_[[np.asarray(d[f"accelerometer_m_s2[{i}]"], float) for i in range(3)]].T
    except KeyError as e:
        raise LogError(f"{path}: '{IMU_TOPIC}' has no field {e.args[0]}") from None
    bad = np.flatnonzero(~np.isfinite(np.c_[gyro, acc]).all(axis=1))
    if bad.size:
        raise LogError(f"{path}: {IMU_TOPIC} sample {int(bad[0])}: NaN or infinite value")
    idx, _, _ = sort_unique(t, f"{path}: {IMU_TOPIC}", warnings)
    if not len(idx):
        raise LogError(f"{path}: '{IMU_TOPIC}' has no samples")
    rate = float(1e9 / np.median(np.diff(t[idx]))) if len(idx) > 1 else 200.0
    return ImuData(t[idx], gyro[idx], acc[idx], noise or ImuNoise(), T_FLU_FRD.copy(), rate)


def read_ulog_frame_times(path: Path, warnings: list[LogWarning] | None = None) -> np.ndarray | None:
    """Camera capture (or trigger) times in ns, sorted, duplicates dropped (a re-sent capture
    message had failed every back end with "sample 50 is duplicated", naming no file: second
    audit); those are counted LogWarnings in `warnings`, as read_ulog_imu's.  None when the ULog
    has neither topic."""
    ulog = _open(Path(path), list(CAPTURE_TOPICS))
    for name in CAPTURE_TOPICS:
        ds = _dataset(ulog, name)
        if ds is not None and len(ds.data["timestamp"]):
            t = np.asarray(ds.data["timestamp"], np.int64) * NS_PER_US
            idx, _, _ = sort_unique(t, f"{path}: {name}", warnings)
            return t[idx]
    return None
