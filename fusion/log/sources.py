"""`open_flight(path)`: any supported log as a FlightLog, by what the path is.

    folder with mav0/                      EuRoC / ASL (fusion.log.euroc)
    file *.bag                             ROS 1 bag
    folder with metadata.yaml, or *.mcap   ROS 2 bag (sqlite3 or MCAP storage)
    *.mp4 / *.mkv / *.avi, or a folder
      holding cam0.<ext>                   video (+ frame times, IMU CSV or PX4 ULog, Kalibr yaml)

Also here: the calibration given next to a log (Kalibr camchain / imu.yaml, or an EuRoC
folder's sensor.yaml files) and the world.yaml lookup shared by every non-EuRoC reader.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.camera import CameraModel, read_T_BS
from fusion.errors import CameraModelError, LogError, WorldError
from fusion.fileio import load_yaml
from fusion.log import euroc
from fusion.log.euroc import FlightLog, ImuNoise
from fusion.log.kalibr import read_camchain, read_imu_yaml, role_of_kalibr_key
from fusion.log.options import LogFormat, LogOptions
from fusion.world import World

VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov")
WORLD_FILE = "world.yaml"


def detect_format(path: Path) -> LogFormat:
    """What kind of log `path` is; LogError when it is none of them."""
    path = Path(path)
    if not path.exists():
        raise LogError(f"{path}: not found")
    if path.is_dir():
        if (path / "mav0").is_dir():
            return LogFormat.EUROC
        if (path / "metadata.yaml").is_file():
            return LogFormat.ROSBAG2
        if any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return LogFormat.ROSBAG2  # a recording that never wrote its metadata.yaml
        if any((path / f"cam0{s}").is_file() for s in VIDEO_SUFFIXES):
            return LogFormat.VIDEO
        raise LogError(f"{path}: not a flight log (no mav0/ folder, no ROS 2 metadata.yaml, no cam0 video)")
    suffix = path.suffix.lower()
    if suffix == ".bag":
        return LogFormat.ROSBAG1
    if suffix in (".mcap", ".db3"):
        return LogFormat.ROSBAG2
    if suffix in VIDEO_SUFFIXES:
        return LogFormat.VIDEO
    raise LogError(
        f"{path}: unknown log type (expected an EuRoC folder, .bag, a ROS 2 bag "
        f"folder or .mcap, or a {'/'.join(VIDEO_SUFFIXES)} video)"
    )


def open_flight(path: Path, opts: LogOptions | None = None) -> FlightLog:
    """Open any supported flight log; frames stream lazily whatever the format."""
    opts = opts or LogOptions()
    fmt = detect_format(path)
    if fmt == LogFormat.EUROC:
        return euroc.read_flight(path, cameras_optional=opts.cameras_optional)
    if fmt in (LogFormat.ROSBAG1, LogFormat.ROSBAG2):
        from fusion.log.rosbag import read_bag

        log = read_bag(path, opts)
    else:
        from fusion.log.video import read_video_flight

        log = read_video_flight(path, opts)
    # the same unit, rate and clock plausibility checks as an EuRoC folder gets
    log.warnings += euroc.drop_short_groundtruth(log)
    log.warnings += euroc.check_log(log)
    return log


# ============================================================================ calibration


@dataclass
class ExternalCalibration:
    """Calibration given beside a log: cameras by role name ("cam0" floor, "cam1" front)."""

    cameras: dict[str, CameraModel] = field(default_factory=dict)
    timeshift_ns: dict[str, int] = field(default_factory=dict)  # t_imu = t_cam + shift
    topics: dict[str, str] = field(default_factory=dict)  # role name -> rostopic
    imu_noise: ImuNoise | None = None
    T_body_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    # role name / "imu0" -> the file (and key) stating its mount, for messages (check_log's)
    where: dict[str, str] = field(default_factory=dict)
    imu_rate_hz: float | None = None  # Kalibr imu.yaml's update_rate, when it states one
    imu_rate_said: str | None = None  # "<imu.yaml> says update_rate" (check_log's rate_mismatch)


def external_calibration(
    opts: LogOptions, T_body_imu: np.ndarray | None = None
) -> ExternalCalibration | None:
    """Read LogOptions.calib (Kalibr camchain yaml, or an EuRoC folder's mav0/*/sensor.yaml) and
    LogOptions.imu_calib (Kalibr imu.yaml); None when neither is given."""
    if opts.calib is None and opts.imu_calib is None:
        return None
    out = ExternalCalibration(T_body_imu=np.eye(4) if T_body_imu is None else T_body_imu)
    if opts.calib is not None:
        calib = Path(opts.calib)
        if calib.is_dir():
            _euroc_calibration(calib, out)
        else:
            for key, kc in read_camchain(calib, out.T_body_imu).items():
                role = role_of_kalibr_key(key)
                if role is None:
                    continue
                out.cameras[role.value] = kc.camera
                out.timeshift_ns[role.value] = kc.timeshift_ns
                out.where[role.value] = f"{calib}: {key}"  # as read_camchain's errors name it
                if kc.rostopic:
                    out.topics[role.value] = kc.rostopic
    if opts.imu_calib is not None:
        ki = read_imu_yaml(opts.imu_calib)
        out.imu_noise = ki.noise
        if ki.rate_hz is not None:
            out.imu_rate_hz, out.imu_rate_said = ki.rate_hz, f"{opts.imu_calib} says update_rate"
        if ki.rostopic:
            out.topics["imu0"] = ki.rostopic
    return out


def _euroc_calibration(root: Path, out: ExternalCalibration) -> None:
    mav = root / "mav0"
    if not mav.is_dir():
        raise LogError(f"{root}: a calibration folder needs mav0/cam0/sensor.yaml (EuRoC layout)")
    for name in euroc.CAMERA_NAMES:
        sensor = mav / name / "sensor.yaml"
        if sensor.is_file():
            try:
                out.cameras[name] = CameraModel.load(sensor)
            except CameraModelError as e:
                raise LogError(str(e)) from None
            out.where[name] = str(sensor)
    imu_yaml = mav / "imu0" / "sensor.yaml"
    if imu_yaml.is_file():
        cfg = load_yaml(imu_yaml, LogError)
        try:
            out.imu_noise = ImuNoise(**{k: float(cfg[k]) for k in vars(ImuNoise())})
        except (KeyError, TypeError, ValueError):
            raise LogError(f"{imu_yaml}: needs the four IMU noise numbers") from None
        if "T_BS" in cfg:
            out.T_body_imu = read_T_BS(cfg["T_BS"], str(imu_yaml), LogError)
            out.where["imu0"] = str(imu_yaml)
        rate = euroc.stated_rate_hz(cfg.get("rate_hz"))  # checked against a bag's IMU stamps (check_log)
        if rate is not None:
            out.imu_rate_hz, out.imu_rate_said = rate, f"{imu_yaml} says rate_hz"
    if not out.cameras:
        raise LogError(f"{mav}: no cam0/sensor.yaml or cam1/sensor.yaml")


# ============================================================================ world


def find_world(path: Path, opts: LogOptions, embedded: dict | None, embedded_where: str) -> World:
    """world.yaml: LogOptions.world, else the one the log carries, else world.yaml in the log's
    folder (or beside it)."""
    try:
        if opts.world is not None:
            return World.load(Path(opts.world))
        if embedded:
            return World.from_yaml(embedded, embedded_where)
        path = Path(path)
        tried = ([path / WORLD_FILE] if path.is_dir() else []) + [path.parent / WORLD_FILE]
        for cand in tried:
            if cand.is_file():
                return World.load(cand)
    except WorldError as e:
        raise LogError(str(e)) from None
    raise LogError(
        f"{path}: no world.yaml (looked for {', '.join(str(c) for c in tried)}); give one with --world"
    )
