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
whose image is missing or unreadable is skipped, counted and reported (`CameraStream.skipped`).
Images are streamed, never all held in memory.
"""
from __future__ import annotations

import csv
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from fusion.camera import CameraModel, read_T_BS
from fusion.errors import CameraModelError, LogError, WorldError
from fusion.fileio import atomic_open, dump_yaml, load_yaml
from fusion.geometry import R_from_quat_wxyz
from fusion.world import World

CAMERA_NAMES = ("cam0", "cam1")
IMU_HEADER = ("#timestamp [ns]", "w_RS_S_x [rad s^-1]", "w_RS_S_y [rad s^-1]",
              "w_RS_S_z [rad s^-1]", "a_RS_S_x [m s^-2]", "a_RS_S_y [m s^-2]",
              "a_RS_S_z [m s^-2]")
VEL_HEADER = ("#timestamp [ns]", "v_RS_S_x [m s^-1]", "v_RS_S_y [m s^-1]", "v_RS_S_z [m s^-1]")
GT_HEADER = ("#timestamp", " p_RS_R_x [m]", " p_RS_R_y [m]", " p_RS_R_z [m]", " q_RS_w []",
             " q_RS_x []", " q_RS_y []", " q_RS_z []", " v_RS_R_x [m s^-1]", " v_RS_R_y [m s^-1]",
             " v_RS_R_z [m s^-1]", " b_w_RS_S_x [rad s^-1]", " b_w_RS_S_y [rad s^-1]",
             " b_w_RS_S_z [rad s^-1]", " b_a_RS_S_x [m s^-2]", " b_a_RS_S_y [m s^-2]",
             " b_a_RS_S_z [m s^-2]")
LOADS_HEADER = ("id", "x_m", "y_m", "z_m")
BLACKOUTS_HEADER = ("#start_ns", "end_ns", "kind")


# ============================================================================ records


@dataclass
class ImuNoise:
    """Continuous-time IMU noise as in Kalibr's imu.yaml (units per sqrt(Hz))."""
    gyroscope_noise_density: float = 1.7e-4       # rad / s / sqrt(Hz)
    gyroscope_random_walk: float = 1.9e-5         # rad / s^2 / sqrt(Hz)
    accelerometer_noise_density: float = 2.0e-3   # m / s^2 / sqrt(Hz)
    accelerometer_random_walk: float = 3.0e-3     # m / s^3 / sqrt(Hz)


@dataclass
class ImuData:
    """IMU samples in the IMU frame S; `T_body_imu` is its T_BS (identity when B is the IMU)."""
    timestamps_ns: np.ndarray     # (N,) int64
    gyro_rad_s: np.ndarray        # (N, 3) angular rate w_RS_S
    accel_m_s2: np.ndarray        # (N, 3) specific force a_RS_S (gravity included)
    noise: ImuNoise = field(default_factory=ImuNoise)
    T_body_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    rate_hz: float = 200.0


@dataclass
class VelocityData:
    """Body-frame velocity (e.g. optical flow + range), `noise_m_s` per axis (1 sigma)."""
    timestamps_ns: np.ndarray     # (N,)
    v_body_m_s: np.ndarray        # (N, 3)
    noise_m_s: float = 0.05


@dataclass
class GroundTruth:
    """EuRoC ground truth: body pose in W, world velocity, IMU biases."""
    timestamps_ns: np.ndarray     # (N,)
    p_world: np.ndarray           # (N, 3)
    q_world_body_wxyz: np.ndarray  # (N, 4)
    v_world: np.ndarray           # (N, 3)
    bias_gyro: np.ndarray         # (N, 3)
    bias_accel: np.ndarray        # (N, 3)

    @property
    def T_world_body(self) -> np.ndarray:
        """(N, 4, 4)."""
        T = np.tile(np.eye(4), (len(self.timestamps_ns), 1, 1))
        T[:, :3, :3] = R_from_quat_wxyz(self.q_world_body_wxyz)
        T[:, :3, 3] = self.p_world
        return T


@dataclass
class Frame:
    timestamp_ns: int
    image: np.ndarray | None      # uint8 grayscale (H, W); None when skipped
    path: Path


@dataclass
class CameraStream:
    """One camera's frames; iterate `frames()` to stream images."""
    name: str
    camera: CameraModel
    timestamps_ns: np.ndarray
    paths: list[Path]
    csv_lines: list[int]
    skipped: list[str] = field(default_factory=list)   # one message per skipped frame

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    def load_image(self, i: int) -> np.ndarray | None:
        """Image i as uint8 grayscale, or None (recorded in `skipped`) if missing or unreadable."""
        path = self.paths[i]
        where = f"{path.parent.parent / 'data.csv'}:{self.csv_lines[i]}"
        if not path.is_file():
            self.skipped.append(f"{where}: image {path.name} is missing")
            return None
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None or img.size == 0:
            self.skipped.append(f"{where}: image {path.name} is unreadable")
            return None
        if img.shape != (self.camera.height, self.camera.width):
            self.skipped.append(f"{where}: image {path.name} is {img.shape[1]}x{img.shape[0]}, "
                                f"sensor.yaml says {self.camera.width}x{self.camera.height}")
            return None
        return img

    def frames(self) -> Iterator[Frame]:
        for i, t in enumerate(self.timestamps_ns):
            yield Frame(int(t), self.load_image(i), self.paths[i])


@dataclass
class FlightLog:
    root: Path
    world: World
    cameras: dict[str, CameraStream]
    imu: ImuData | None = None
    velocity: VelocityData | None = None
    groundtruth: GroundTruth | None = None
    loads_groundtruth: dict[str, np.ndarray] | None = None
    blackouts: list[tuple[int, int, str]] | None = None   # (start_ns, end_ns, kind)

    @property
    def floor(self) -> CameraStream:
        return self.cameras["cam0"]

    @property
    def front(self) -> CameraStream | None:
        return self.cameras.get("cam1")

    @property
    def duration_s(self) -> float:
        t = self.floor.timestamps_ns
        return float(t[-1] - t[0]) * 1e-9 if len(t) > 1 else 0.0


# ============================================================================ reading


def _rows(path: Path, ncols: int, header_prefix: str = "#") -> Iterator[tuple[int, list[str]]]:
    """Yield (line number, fields) of a CSV file, skipping comment/header lines and blank lines;
    a row with the wrong number of fields raises LogError naming file and line."""
    try:
        f = open(path, encoding="utf-8", newline="")
    except FileNotFoundError:
        raise LogError(f"{path}: file not found") from None
    with f:
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


def _timestamp(text: str, path: Path, lineno: int) -> int:
    try:
        t = int(text)
    except ValueError:
        raise LogError(f"{path}:{lineno}: timestamp {text[:30]!r} is not an integer "
                       "number of nanoseconds") from None
    if t < 0:
        raise LogError(f"{path}:{lineno}: negative timestamp {t}")
    return t


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


def _numeric_csv(path: Path, ncols: int) -> tuple[np.ndarray, np.ndarray]:
    """Read a `timestamp, v1, ..., v{ncols-1}` CSV with strictly increasing timestamps."""
    ts, vals, prev = [], [], None
    for lineno, row in _rows(path, ncols):
        t = _timestamp(row[0], path, lineno)
        _check_monotonic(t, prev, path, lineno)
        prev = t
        ts.append(t)
        vals.append(_numbers(row[1:], path, lineno))
    if not ts:
        raise LogError(f"{path}: no data rows")
    return np.asarray(ts, dtype=np.int64), np.asarray(vals, dtype=float)


def _read_camera(cam_dir: Path, name: str) -> CameraStream:
    try:
        camera = CameraModel.load(cam_dir / "sensor.yaml")
    except CameraModelError as e:
        raise LogError(str(e)) from None
    data_dir = (cam_dir / "data").resolve()
    csv_path = cam_dir / "data.csv"
    ts, paths, lines, prev = [], [], [], None
    for lineno, row in _rows(csv_path, 2):
        t = _timestamp(row[0], csv_path, lineno)
        _check_monotonic(t, prev, csv_path, lineno)
        prev = t
        fname = row[1]
        if not fname:
            raise LogError(f"{csv_path}:{lineno}: empty file name")
        path = (data_dir / fname).resolve()
        if data_dir not in path.parents:
            raise LogError(f"{csv_path}:{lineno}: file name {fname[:60]!r} points outside "
                           f"{cam_dir / 'data'}")
        ts.append(t)
        paths.append(path)
        lines.append(lineno)
    if not ts:
        raise LogError(f"{csv_path}: no frames")
    return CameraStream(name, camera, np.asarray(ts, dtype=np.int64), paths, lines)


def _read_imu(imu_dir: Path) -> ImuData:
    sensor_path = imu_dir / "sensor.yaml"
    cfg = load_yaml(sensor_path, LogError)
    noise = {}
    for key in ("gyroscope_noise_density", "gyroscope_random_walk",
                "accelerometer_noise_density", "accelerometer_random_walk"):
        if key not in cfg:
            raise LogError(f"{sensor_path}: missing key '{key}'")
        try:
            noise[key] = float(cfg[key])
        except (TypeError, ValueError):
            raise LogError(f"{sensor_path}: '{key}' is not a number") from None
        if not (math.isfinite(noise[key]) and noise[key] > 0):
            raise LogError(f"{sensor_path}: '{key}' must be positive")
    T = read_T_BS(cfg.get("T_BS", {"data": np.eye(4).reshape(-1).tolist()}), str(sensor_path),
                  LogError)
    ts, vals = _numeric_csv(imu_dir / "data.csv", 7)
    rate = float(cfg.get("rate_hz", 0) or 0) or float(1e9 / np.median(np.diff(ts)) if len(ts) > 1 else 200)
    return ImuData(ts, vals[:, :3], vals[:, 3:], ImuNoise(**noise), T, rate)


def _read_velocity(vel_dir: Path) -> VelocityData:
    noise = 0.05
    sensor_path = vel_dir / "sensor.yaml"
    if sensor_path.exists():
        cfg = load_yaml(sensor_path, LogError)
        try:
            noise = float(cfg.get("noise_m_s", noise))
        except (TypeError, ValueError):
            raise LogError(f"{sensor_path}: 'noise_m_s' is not a number") from None
    ts, vals = _numeric_csv(vel_dir / "data.csv", 4)
    return VelocityData(ts, vals, noise)


def _read_groundtruth(path: Path) -> GroundTruth:
    ts, v = _numeric_csv(path, 17)
    return GroundTruth(ts, v[:, 0:3], v[:, 3:7], v[:, 7:10], v[:, 10:13], v[:, 13:16])


def _read_loads(path: Path) -> dict[str, np.ndarray]:
    loads: dict[str, np.ndarray] = {}
    for lineno, row in _rows(path, 4, header_prefix="id"):
        if row[0] in loads:
            raise LogError(f"{path}:{lineno}: duplicate load id {row[0]!r}")
        loads[row[0]] = np.asarray(_numbers(row[1:], path, lineno))
    return loads


def _read_blackouts(path: Path) -> list[tuple[int, int, str]]:
    out = []
    for lineno, row in _rows(path, 3):
        t0, t1 = _timestamp(row[0], path, lineno), _timestamp(row[1], path, lineno)
        if t1 < t0:
            raise LogError(f"{path}:{lineno}: blackout ends before it starts")
        out.append((t0, t1, row[2]))
    return out


def read_flight(root: Path) -> FlightLog:
    """Open a flight log folder.  Reads every CSV and YAML now (validating them), images lazily."""
    root = Path(root)
    if not root.is_dir():
        raise LogError(f"{root}: not a folder")
    mav = root / "mav0"
    try:
        world = World.load(root / "world.yaml")
    except WorldError as e:
        raise LogError(str(e)) from None
    cameras = {}
    for name in CAMERA_NAMES:
        if (mav / name).is_dir():
            cameras[name] = _read_camera(mav / name, name)
    if "cam0" not in cameras:
        raise LogError(f"{mav / 'cam0'}: the floor camera folder is missing")
    imu = _read_imu(mav / "imu0") if (mav / "imu0").is_dir() else None
    vel = _read_velocity(mav / "vel0") if (mav / "vel0").is_dir() else None
    gt_path = mav / "state_groundtruth_estimate0" / "data.csv"
    gt = _read_groundtruth(gt_path) if gt_path.exists() else None
    loads_path = root / "loads_groundtruth.csv"
    loads = _read_loads(loads_path) if loads_path.exists() else None
    bo_path = root / "blackouts_groundtruth.csv"
    blackouts = _read_blackouts(bo_path) if bo_path.exists() else None
    return FlightLog(root, world, cameras, imu, vel, gt, loads, blackouts)


# ============================================================================ writing


def _write_csv(path: Path, header, rows) -> None:
    with atomic_open(path) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)


def _fmt(v: float) -> str:
    return repr(float(v))


class FlightLogWriter:
    """Write a flight log.  Everything goes to `<root>.partial/` first and is renamed to `root`
    by `close()`, so an interrupted write never leaves a log that looks complete.

        with FlightLogWriter(out) as w:
            w.write_world(world)
            w.add_camera("cam0", camera)
            w.write_frame("cam0", t_ns, image)
            w.write_imu(imu)
    """

    def __init__(self, root: Path, overwrite: bool = False):
        self.root = Path(root)
        if self.root.exists() and not overwrite:
            raise LogError(f"{self.root}: already exists")
        self.tmp = self.root.with_name(self.root.name + ".partial")
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        (self.tmp / "mav0").mkdir(parents=True)
        self._frames: dict[str, list[tuple[int, str]]] = {}

    # context manager: commit on success, discard on error
    def __enter__(self) -> "FlightLogWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            shutil.rmtree(self.tmp, ignore_errors=True)

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
        dump_yaml({"sensor_type": "imu", "comment": "fusion flight log",
                   "T_BS": {"cols": 4, "rows": 4,
                            "data": [float(v) for v in np.asarray(imu.T_body_imu).reshape(-1)]},
                   "rate_hz": float(imu.rate_hz),
                   "gyroscope_noise_density": n.gyroscope_noise_density,
                   "gyroscope_random_walk": n.gyroscope_random_walk,
                   "accelerometer_noise_density": n.accelerometer_noise_density,
                   "accelerometer_random_walk": n.accelerometer_random_walk},
                  d / "sensor.yaml")
        rows = ([str(int(t))] + [_fmt(v) for v in np.r_[w, a]]
                for t, w, a in zip(imu.timestamps_ns, imu.gyro_rad_s, imu.accel_m_s2))
        _write_csv(d / "data.csv", IMU_HEADER, rows)

    def write_velocity(self, vel: VelocityData) -> None:
        d = self.tmp / "mav0" / "vel0"
        d.mkdir(parents=True, exist_ok=True)
        dump_yaml({"sensor_type": "velocity", "frame": "body", "noise_m_s": float(vel.noise_m_s)},
                  d / "sensor.yaml")
        rows = ([str(int(t))] + [_fmt(x) for x in v] for t, v in zip(vel.timestamps_ns, vel.v_body_m_s))
        _write_csv(d / "data.csv", VEL_HEADER, rows)

    def write_groundtruth(self, gt: GroundTruth) -> None:
        d = self.tmp / "mav0" / "state_groundtruth_estimate0"
        d.mkdir(parents=True, exist_ok=True)
        rows = ([str(int(t))] + [_fmt(x) for x in np.r_[p, q, v, bw, ba]]
                for t, p, q, v, bw, ba in zip(gt.timestamps_ns, gt.p_world, gt.q_world_body_wxyz,
                                              gt.v_world, gt.bias_gyro, gt.bias_accel))
        _write_csv(d / "data.csv", GT_HEADER, rows)

    def write_loads_groundtruth(self, loads: dict[str, np.ndarray]) -> None:
        rows = ([k] + [_fmt(x) for x in p] for k, p in loads.items())
        _write_csv(self.tmp / "loads_groundtruth.csv", LOADS_HEADER, rows)

    def write_blackouts(self, blackouts: list[tuple[int, int, str]]) -> None:
        _write_csv(self.tmp / "blackouts_groundtruth.csv", BLACKOUTS_HEADER,
                   ([str(int(a)), str(int(b)), k] for a, b, k in blackouts))

    def close(self) -> Path:
        for name, frames in self._frames.items():
            _write_csv(self.tmp / "mav0" / name / "data.csv", ("#timestamp [ns]", "filename"),
                       ([str(t), f] for t, f in frames))
        if self.root.exists():
            shutil.rmtree(self.root)
        self.tmp.rename(self.root)
        return self.root
