"""Video flight logs through PyAV: a floor (and optionally a front) camera video, per-frame
times, the IMU from a CSV or a PX4 ULog, the calibration from Kalibr.

A video folder (what `write_video_flight` / `fusion simulate --format video` writes, and what
`open_flight` recognises by its cam0.<ext>):

    cam0.mkv  cam0.csv           floor video + its frame times (`#timestamp [ns]`, one per frame)
    cam1.mkv  cam1.csv           front video (optional)
    imu.csv | *.ulg              IMU: EuRoC imu0 columns, or a PX4 ULog (sensor_combined)
    camchain-imucam.yaml         Kalibr: intrinsics, T_cam_imu, timeshift_cam_imu (cam0 floor)
    imu.yaml                     Kalibr IMU noise (optional: defaults with a warning)
    world.yaml                   the codes
    velocity.csv velocity.yaml   body-frame velocity, EuRoC vel0 columns (optional)
    groundtruth.csv loads_groundtruth.csv blackouts_groundtruth.csv   (optional, simulator)

A single video file opens the same way with its side files looked up in its folder; LogOptions
name any of them explicitly.  Frame times, first found: the CSV; the ULog's camera_capture /
camera_trigger times; a constant rate (LogOptions.video_fps or the container's) from
LogOptions.video_start_ns.  A variable-frame-rate video without frame times is refused.
Frames decode lazily: sequentially when read in order, by seeking to the previous key frame
otherwise.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import shutil
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from fusion.camera import CameraModel
from fusion.errors import LogError
from fusion.fileio import dump_yaml, load_yaml, strict_float
from fusion.geometry import inv_T
from fusion.log import euroc
from fusion.log.euroc import (
    CameraStream,
    FlightLog,
    Frame,
    ImuData,
    ImuNoise,
    LogWarning,
    StreamSource,
    VelocityData,
    _numeric_csv,
    _timestamp,
    _write_csv,
)
from fusion.log.kalibr import read_camchain, read_imu_yaml, write_camchain, write_imu_yaml
from fusion.log.options import LogOptions
from fusion.log.sources import VIDEO_SUFFIXES, find_world
from fusion.types import CameraRole

if TYPE_CHECKING:
    from av.container import InputContainer
    from av.video.frame import VideoFrame

log = logging.getLogger(__name__)

CAMCHAIN_FILE = "camchain-imucam.yaml"
IMU_YAML_FILE = "imu.yaml"
IMU_CSV_FILE = "imu.csv"
VELOCITY_CSV_FILE = "velocity.csv"
VELOCITY_YAML_FILE = "velocity.yaml"
GROUNDTRUTH_FILE = "groundtruth.csv"
LOADS_FILE = "loads_groundtruth.csv"
BLACKOUTS_FILE = "blackouts_groundtruth.csv"
FRAME_TIMES_HEADER = ("#timestamp [ns]",)
TRUNCATION_TOLERANCE_FRAMES = 1.5
"""Frames ending more than this many frame steps before the container's declared duration: the
file was cut (a warning; the frames there are are used)."""
VFR_TOLERANCE_TICKS = 1  # pts steps may differ by one tick of rounding and stay CFR
CODECS = {  # codec -> (container suffix, pixel format, encoder options)
    "ffv1": (".mkv", "gray", {}),  # lossless
    "h264": (".mp4", "yuv420p", {"crf": "18", "preset": "veryfast"}),  # lossy, everywhere
}
DEFAULT_VIDEO_RATE_HZ = 30.0


# ============================================================================ frame stream


class VideoCameraStream(CameraStream):
    """Frames of one video file, decoded on demand.  `frame_index[i]` is the decoded frame
    number of timestamp i.  Picklable (the container is reopened in each process)."""

    def __init__(
        self,
        name: str,
        camera: CameraModel,
        timestamps_ns: np.ndarray,
        video: Path,
        pts: np.ndarray,
        frame_index: np.ndarray,
    ):
        super().__init__(name, camera, np.asarray(timestamps_ns, np.int64), [], [])
        self.video = Path(video)
        self.pts = np.asarray(pts, np.int64)  # presentation order
        self.frame_index = np.asarray(frame_index, np.int64)
        self._container: InputContainer | None = None
        self._frames: Iterator[VideoFrame] | None = None
        self._next: int | None = -1  # None: unknown (just seeked)
        self._pid: int | None = None  # process that opened _container

    def __getstate__(self):
        state = dict(self.__dict__)
        state.update(_container=None, _frames=None, _next=-1, _pid=None)
        return state

    def close(self) -> None:
        if self._container is not None:
            self._container.close()
        self._container, self._frames, self._next = None, None, -1

    def fingerprint(self) -> bytes:
        h = hashlib.sha256()
        st = self.video.stat()
        h.update(f"{self.video.resolve()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
        h.update(self.timestamps_ns.tobytes())
        h.update(yaml.safe_dump(self.camera.to_sensor_yaml(), sort_keys=True).encode())
        return h.digest()

    def _seek(self, k: int) -> Iterator[VideoFrame]:
        import av

        if self._container is not None and self._pid != os.getpid():
            # a forked worker shares the parent's file offsets: never read through them
            self._container, self._frames = None, None
        if self._container is None:
            self._container = av.open(str(self.video))
            self._pid = os.getpid()
        vs = self._container.streams.video[0]
        target = int(self.pts[k])
        if k == 0:
            self._container.seek(0)
        else:
            self._container.seek(target, stream=vs, backward=True, any_frame=False)
        frames = self._frames = self._container.decode(vs)
        self._next = None  # unknown until the first frame at or after the target
        return frames

    def _decode(self, k: int) -> VideoFrame:
        frames = self._frames
        if frames is None or self._next != k or self._pid != os.getpid():
            frames = self._seek(k)
            target = int(self.pts[k])
            for frame in frames:
                if frame.pts is not None and frame.pts >= target:
                    if frame.pts != target:
                        raise ValueError(f"seek landed on pts {frame.pts}, wanted {target}")
                    self._next = k + 1
                    return frame
            raise StopIteration
        frame = next(frames)
        self._next = k + 1
        return frame

    def load_image(self, i: int) -> np.ndarray | None:
        k = int(self.frame_index[i])
        where = f"{self.video}: frame {k}"
        try:
            img = self._decode(k).to_ndarray(format="gray")
        except StopIteration:
            self.skipped.append(f"{where}: missing (video ends early)")
            self._frames = None
            return None
        except Exception as e:  # noqa: BLE001 - a damaged frame: skip it, say why
            self.skipped.append(f"{where}: unreadable ({e.__class__.__name__}: {str(e)[:80]})")
            self._frames = None
            return None
        if img.shape != (self.camera.height, self.camera.width):
            self.skipped.append(
                f"{where}: image is {img.shape[1]}x{img.shape[0]}, the "
                f"calibration says {self.camera.width}x{self.camera.height}"
            )
            return None
        return np.ascontiguousarray(img)

    def frames(self):
        for i, t in enumerate(self.timestamps_ns):
            yield Frame(int(t), self.load_image(i), self.video)
        self.close()


# ============================================================================ probing


def probe_video(path: Path) -> tuple[np.ndarray, Fraction, float | None, str | None]:
    """(pts of every frame in presentation order, time base, the container's average rate in Hz
    or None, a warning if demuxing stopped at damage)."""
    import av

    try:
        container = av.open(str(path))
    except FileNotFoundError:
        raise LogError(f"{path}: not found") from None
    except Exception as e:  # noqa: BLE001 - PyAV raises its own error per FFmpeg error code
        hint = (
            "; an MP4 / MOV cut short loses its index (moov atom) with it: record to MKV, "
            "or repair it (e.g. untrunc) first"
            if Path(path).suffix.lower() in (".mp4", ".mov")
            else ""
        )
        raise LogError(f"{path}: not a readable video ({e.__class__.__name__}){hint}") from None
    with container:
        if not container.streams.video:
            raise LogError(f"{path}: has no video stream")
        vs = container.streams.video[0]
        pts, warning = [], None
        try:
            for pkt in container.demux(vs):
                t = pkt.pts if pkt.pts is not None else pkt.dts
                if t is not None and pkt.size > 0:
                    pts.append(int(t))
        except Exception as e:  # noqa: BLE001
            warning = (
                f"{path}: damaged after {len(pts)} frames ({e.__class__.__name__}); using the frames before"
            )
            log.warning(warning)
        rate = float(vs.average_rate) if vs.average_rate else None
        tb = vs.time_base
        declared_s = container.duration / av.time_base if container.duration else None
    if not pts:
        raise LogError(f"{path}: no video frames")
    if warning is None and declared_s is not None and tb is not None and len(pts) > 1:
        # a file cut at a frame boundary demuxes without error: compare with the header's duration
        p = np.sort(np.asarray(pts, np.int64))
        step_s = float(np.median(np.diff(p)) * tb)
        end_s = float((p[-1] - p[0]) * tb) + step_s
        if end_s < declared_s - TRUNCATION_TOLERANCE_FRAMES * step_s:
            warning = (
                f"{path}: its frames end at {end_s:.3f} s of the {declared_s:.3f} s its header "
                f"declares (truncated?); using the {len(pts)} frames there are"
            )
            log.warning(warning)
    if tb is None:
        raise LogError(f"{path}: the video stream has no time base")
    return np.sort(np.asarray(pts, np.int64)), tb, rate, warning


def read_frame_times(path: Path) -> np.ndarray:
    """Frame times CSV: first column ns, one row per frame in order (more columns ignored)."""
    ts, prev = [], None
    path = Path(path)
    try:
        f = open(path, encoding="utf-8")
    except FileNotFoundError:
        raise LogError(f"{path}: file not found") from None
    with f:
        for lineno, line in enumerate(f, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            t = _timestamp(text.split(",")[0].strip(), path, lineno)
            if prev is not None and t <= prev:
                raise LogError(
                    f"{path}:{lineno}: {'duplicate' if t == prev else 'non-monotonic'}"
                    f" timestamp {t} (previous {prev})"
                )
            ts.append(t)
            prev = t
    if not ts:
        raise LogError(f"{path}: no frame times")
    return np.asarray(ts, np.int64)


def _frame_times(
    video: Path,
    pts: np.ndarray,
    tb: Fraction,
    rate: float | None,
    times_csv: Path | None,
    ulog_times: np.ndarray | None,
    opts: LogOptions,
    warnings: list[LogWarning] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps_ns, frame index) for the decodable frames of `video`; a frame count that
    differs from the frame times is a `frame_times_mismatch` LogWarning in `warnings`."""
    n = len(pts)
    if times_csv is not None:
        t, source = read_frame_times(times_csv), str(times_csv)
    elif ulog_times is not None:
        t, source = ulog_times, "the ULog's camera capture times"
    else:
        steps = np.diff(pts)
        if len(steps) and steps.max() - steps.min() > VFR_TOLERANCE_TICKS:
            raise LogError(
                f"{video}: variable frame rate (frame steps {steps.min()}..{steps.max()}"
                f" x {tb} s) and no frame times file; give one with --frame-times"
            )
        if opts.video_start_ns is None:
            raise LogError(
                f"{video}: no frame times file ({video.with_suffix('.csv').name}) and "
                "no camera capture topic; give --frame-times, or --video-start-ns "
                "(the first frame's time in the IMU clock) for a constant-rate video"
            )
        if opts.video_fps is not None and not (math.isfinite(opts.video_fps) and opts.video_fps > 0):
            raise LogError(f"{video}: video_fps {opts.video_fps} is not a frame rate (finite, > 0 Hz)")
        if opts.video_start_ns < 0:
            raise LogError(f"{video}: video_start_ns {opts.video_start_ns} is negative")
        fps = opts.video_fps or (float(1 / (steps[0] * tb)) if len(steps) else rate)
        if not fps:
            raise LogError(f"{video}: frame rate unknown; give --video-fps")
        t = int(opts.video_start_ns) + np.round(np.arange(n) * 1e9 / fps).astype(np.int64)
        return t, np.arange(n)
    if len(t) != n:
        log.warning(
            "%s: %d frames but %d times in %s; using the first %d", video, n, len(t), source, min(n, len(t))
        )
        if warnings is not None:
            warnings.append(
                LogWarning(
                    "frame_times_mismatch",
                    abs(n - len(t)),
                    f"{video}: {n} frames but {len(t)} times in {source}; using the first {min(n, len(t))}",
                )
            )
    m = min(n, len(t))
    return t[:m], np.arange(m)


# ============================================================================ reading


def _find(folder: Path, given: Path | None, name: str | None, pattern: str | None = None) -> Path | None:
    if given is not None:
        return Path(given)
    if name and (folder / name).is_file():
        return folder / name
    if pattern:
        found = sorted(folder.glob(pattern))
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise LogError(f"{folder}: {len(found)} files match {pattern}; name one explicitly")
    return None


def _video_of(folder: Path, stem: str) -> Path | None:
    for s in VIDEO_SUFFIXES:
        if (folder / f"{stem}{s}").is_file():
            return folder / f"{stem}{s}"
    return None


def read_video_flight(path: Path, opts: LogOptions | None = None) -> FlightLog:
    """Open a video folder or a video file (see the module docstring) as a FlightLog."""
    opts = opts or LogOptions()
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    videos = {CameraRole.FLOOR.value: _video_of(folder, "cam0") if path.is_dir() else path}
    front = (
        Path(opts.front_video) if opts.front_video else (_video_of(folder, "cam1") if path.is_dir() else None)
    )
    if front is not None:
        videos[CameraRole.FRONT.value] = front

    imu_path = _find(folder, opts.imu, IMU_CSV_FILE, "*.ulg")
    imu, ulog_times = None, None
    sources: dict[str, StreamSource] = {}  # for euroc.check_log's messages: the files read
    ulog_warnings: list[LogWarning] = []  # the ULog's unordered / duplicate IMU samples and captures
    imu_yaml = _find(folder, opts.imu_calib, IMU_YAML_FILE)
    kimu = read_imu_yaml(imu_yaml) if imu_yaml else None
    if imu_path is not None and imu_path.suffix.lower() == ".ulg":
        from fusion.log.ulog import IMU_TOPIC, read_ulog_frame_times, read_ulog_imu

        imu = read_ulog_imu(imu_path, kimu.noise if kimu else None, ulog_warnings)
        ulog_times = read_ulog_frame_times(imu_path, ulog_warnings)
        # as read_ulog_imu names it; its stamps are microseconds by the format
        sources["imu0"] = StreamSource(f"{imu_path}: {IMU_TOPIC}", stamps_ns=True)
    elif imu_path is not None:
        imu = _read_imu_csv(imu_path, kimu, folder)
        stated_T = kimu is not None and (folder / IMU_YAML_FILE).is_file()  # T_i_b, if any
        sources["imu0"] = StreamSource(str(imu_path), str(folder / IMU_YAML_FILE) if stated_T else None)
    if "imu0" in sources and kimu is not None and kimu.rate_hz is not None:
        # checked against the stamps as an EuRoC folder's sensor.yaml rate_hz (check_log)
        sources["imu0"].rate_hz, sources["imu0"].rate_said = kimu.rate_hz, f"{imu_yaml} says update_rate"
    noise_default = None
    if imu is not None and kimu is None:
        noise_default = f"{imu_path}: no IMU noise calibration (Kalibr imu.yaml); using defaults"
        log.warning(noise_default)

    calib_path = _find(folder, opts.calib, CAMCHAIN_FILE, "*camchain*.yaml")
    if calib_path is None:
        raise LogError(
            f"{path}: no camera calibration ({CAMCHAIN_FILE}); give a Kalibr "
            "camchain-imucam.yaml with --calib"
        )
    if Path(calib_path).is_dir():
        from fusion.log.sources import external_calibration

        ext = external_calibration(LogOptions(calib=calib_path))
        if ext is None:  # only when no calibration is given, and calib_path is one
            raise LogError(f"{calib_path}: no camera calibration read")
        kal = {k: (cam, ext.timeshift_ns.get(k, 0)) for k, cam in ext.cameras.items()}
        mounts = dict(ext.where)
    else:
        T_bi = imu.T_body_imu if imu is not None else None
        kal = {k: (kc.camera, kc.timeshift_ns) for k, kc in read_camchain(calib_path, T_bi).items()}
        mounts = {k: f"{calib_path}: {k}" for k in kal}  # as read_camchain's errors name it

    cameras: dict[str, CameraStream] = {}
    warnings: list[LogWarning] = ulog_warnings + (
        [] if noise_default is None else [LogWarning("imu_noise_default", 1, noise_default)]
    )
    for name, video in videos.items():
        if video is None or not Path(video).is_file():
            raise LogError(f"{video or folder / 'cam0.mkv'}: video not found")
        if name not in kal:
            raise LogError(f"{calib_path}: no '{name}' block for {video}")
        cam, shift_ns = kal[name]
        pts, tb, rate, damage = probe_video(video)
        if damage:
            warnings.append(LogWarning("video_truncated", 1, damage))
        times = opts.frame_times if name == CameraRole.FLOOR.value else opts.front_frame_times
        times = (
            Path(times)
            if times
            else (video.with_suffix(".csv") if video.with_suffix(".csv").is_file() else None)
        )
        capture_times = ulog_times if name == CameraRole.FLOOR.value else None
        t, idx = _frame_times(video, pts, tb, rate, times, capture_times, opts, warnings)
        stamped_by = str(video)  # where its times came from, as _frame_times picks it
        if times is not None:
            stamped_by = str(times)
        elif capture_times is not None:
            stamped_by = f"{imu_path}: camera capture times"
        sources[name] = StreamSource(stamped_by, mounts.get(name))
        t = t + shift_ns
        if "rate_hz" not in _camchain_keys(calib_path, name) and len(t) > 1:
            cam.rate_hz = float(1e9 / np.median(np.diff(t)))
        cameras[name] = VideoCameraStream(name, cam, t, video, pts, idx)

    vel = None
    vel_csv = folder / VELOCITY_CSV_FILE
    if vel_csv.is_file():
        ts, v = _numeric_csv(vel_csv, 4)
        sources["vel0"] = StreamSource(str(vel_csv))
        noise = 0.05
        if (folder / VELOCITY_YAML_FILE).is_file():
            stated = load_yaml(folder / VELOCITY_YAML_FILE, LogError).get("noise_m_s", noise)
            noise = strict_float(stated, f"{folder / VELOCITY_YAML_FILE}: noise_m_s", LogError, positive=True)
        vel = VelocityData(ts, v, noise)
    gt, gt_warnings = (
        euroc._read_groundtruth(folder / GROUNDTRUTH_FILE)
        if (folder / GROUNDTRUTH_FILE).is_file()
        else (None, [])
    )
    loads = euroc._read_loads(folder / LOADS_FILE) if (folder / LOADS_FILE).is_file() else None
    blackouts = (
        euroc._read_blackouts(folder / BLACKOUTS_FILE) if (folder / BLACKOUTS_FILE).is_file() else None
    )
    world = find_world(path, opts, None, "")
    if imu is None and vel is None:
        log.warning("%s: no IMU (imu.csv or a .ulg) and no velocity.csv", path)
    out = FlightLog(path, world, cameras, imu, vel, gt, loads, blackouts, warnings + list(gt_warnings))
    out.timeshift_ns = {name: int(kal[name][1]) for name in cameras}  # added to the stamps above
    if gt is not None:
        sources["groundtruth"] = StreamSource(str(folder / GROUNDTRUTH_FILE))
    out.stream_sources = sources
    return out


def _camchain_keys(calib_path: Path, name: str) -> set:
    if Path(calib_path).is_dir():
        return {"rate_hz"}
    block = load_yaml(calib_path, LogError).get(name) or {}
    return set(block) if isinstance(block, dict) else set()


def _read_imu_csv(path: Path, kimu, folder: Path) -> ImuData:
    """IMU CSV with EuRoC imu0 columns (ns, gyro rad/s xyz, accel m/s^2 xyz); T_body_imu from
    imu.yaml's Kalibr `T_i_b` when present."""
    t, vals = _numeric_csv(path, 7)
    T_bi = np.eye(4)
    imu_yaml = folder / IMU_YAML_FILE
    if kimu is not None and imu_yaml.is_file():
        data = load_yaml(imu_yaml, LogError)
        block = data.get("imu0", data) if isinstance(data.get("imu0"), dict) else data
        if "T_i_b" in block:
            from fusion.log.kalibr import _matrix

            T_bi = inv_T(_matrix(block["T_i_b"], f"{imu_yaml}: T_i_b"))
    rate = (
        kimu.rate_hz
        if kimu is not None and kimu.rate_hz
        else (float(1e9 / np.median(np.diff(t))) if len(t) > 1 else 200.0)
    )
    return ImuData(t, vals[:, :3], vals[:, 3:], kimu.noise if kimu else ImuNoise(), T_bi, rate)


# ============================================================================ writing


def write_video_flight(flight: FlightLog, out: Path, codec: str = "ffv1", overwrite: bool = False) -> Path:
    """Write `flight` as a video folder (module docstring).  `codec` "ffv1" is lossless (gray
    MKV), "h264" lossy (MP4, yuv420p, CRF 18).  Written to OUT.partial, renamed when complete."""
    import av

    out = Path(out)
    if codec not in CODECS:
        raise LogError(f"video codec {codec!r} is not one of {', '.join(CODECS)}")
    if out.exists() and not overwrite:
        raise LogError(f"{out}: already exists")
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    suffix, pix_fmt, options = CODECS[codec]
    try:
        for name, stream in sorted(flight.cameras.items()):
            cam = stream.camera
            rate = (
                Fraction(cam.rate_hz).limit_denominator(1001)
                if cam.rate_hz > 0
                else Fraction(int(DEFAULT_VIDEO_RATE_HZ))
            )
            times: list[int] = []
            with av.open(str(tmp / f"{name}{suffix}"), mode="w") as container:
                vs = container.add_stream(
                    "libx264" if codec == "h264" else codec, rate=rate, options=dict(options)
                )
                vs.width, vs.height, vs.pix_fmt = cam.width, cam.height, pix_fmt
                for frame in stream.frames():
                    if frame.image is None:
                        continue
                    vf = av.VideoFrame.from_ndarray(frame.image, format="gray")
                    if pix_fmt != "gray":
                        vf = vf.reformat(format=pix_fmt)
                    vf.pts = len(times)
                    times.append(frame.timestamp_ns)
                    for pkt in vs.encode(vf):
                        container.mux(pkt)
                for pkt in vs.encode():
                    container.mux(pkt)
            _write_csv(tmp / f"{name}.csv", FRAME_TIMES_HEADER, ([str(t)] for t in times))
        write_camchain(
            tmp / CAMCHAIN_FILE,
            {n: s.camera for n, s in flight.cameras.items()},
            {n: f"/{n}/image_raw" for n in flight.cameras},
            flight.imu.T_body_imu if flight.imu is not None else None,
        )
        flight.world.save(tmp / "world.yaml")
        if flight.imu is not None:
            imu = flight.imu
            write_imu_yaml(tmp / IMU_YAML_FILE, imu.noise, imu.rate_hz)
            if not np.allclose(imu.T_body_imu, np.eye(4)):
                data = load_yaml(tmp / IMU_YAML_FILE, LogError)
                data["T_i_b"] = [[float(v) for v in r] for r in inv_T(imu.T_body_imu)]
                dump_yaml(data, tmp / IMU_YAML_FILE)
            _write_csv(
                tmp / IMU_CSV_FILE,
                euroc.IMU_HEADER,
                (
                    [str(int(t))] + [repr(float(v)) for v in np.r_[w, a]]
                    for t, w, a in zip(imu.timestamps_ns, imu.gyro_rad_s, imu.accel_m_s2)
                ),
            )
        if flight.velocity is not None:
            v = flight.velocity
            _write_csv(
                tmp / VELOCITY_CSV_FILE,
                euroc.VEL_HEADER,
                (
                    [str(int(t))] + [repr(float(x)) for x in row]
                    for t, row in zip(v.timestamps_ns, v.v_body_m_s)
                ),
            )
            dump_yaml({"noise_m_s": float(v.noise_m_s), "frame": "body"}, tmp / VELOCITY_YAML_FILE)
        gt = flight.groundtruth
        if gt is not None:
            _write_csv(
                tmp / GROUNDTRUTH_FILE,
                euroc.GT_HEADER,
                (
                    [str(int(t))] + [repr(float(x)) for x in np.r_[p, q, vw, bw, ba]]
                    for t, p, q, vw, bw, ba in zip(
                        gt.timestamps_ns,
                        gt.p_world,
                        gt.q_world_body_wxyz,
                        gt.v_world,
                        gt.bias_gyro,
                        gt.bias_accel,
                    )
                ),
            )
        if flight.loads_groundtruth is not None:
            _write_csv(
                tmp / LOADS_FILE,
                euroc.LOADS_HEADER,
                ([k] + [repr(float(x)) for x in p] for k, p in flight.loads_groundtruth.items()),
            )
        if flight.blackouts is not None:
            _write_csv(
                tmp / BLACKOUTS_FILE,
                euroc.BLACKOUTS_HEADER,
                ([str(a), str(b), k] for a, b, k in flight.blackouts),
            )
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    tmp.rename(out)
    return out
