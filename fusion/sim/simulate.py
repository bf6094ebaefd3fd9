"""`simulate()`: render a scenario into a flight log (EuRoC layout, DESIGN.md) with ground truth.

Frames are rendered by `workers` processes in chunks, PNG-encoded there and streamed to disk in
order; the whole flight is never held in memory.  Every random draw comes from a generator seeded
by (seed, stream, index), so the log is the same for a seed whatever the number of workers.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from fusion.conventions import floor_payload
from fusion.errors import SimulationError
from fusion.estimate.asbuilt import FLOOR_CODES_GROUNDTRUTH_CSV, write_groundtruth_csv
from fusion.estimate.extrinsics import (
    EXTRINSICS_GROUNDTRUTH_CSV,
    corrected_camera,
    write_extrinsics_groundtruth,
)
from fusion.fileio import strict_float
from fusion.geometry import inv_T, quat_wxyz_from_R, yaw_of
from fusion.log import FlightLogWriter, GroundTruth
from fusion.parallel import parallel_map, worker_count
from fusion.sim.imu import sample_times_ns, synthesize_imu, synthesize_velocity
from fusion.sim.placement import placement_offsets
from fusion.sim.render import render_view, rolling_shutter_poses
from fusion.sim.scenarios import SCENARIOS, CameraOptions, Scenario, apply_camera_options, build_scenario

CAMERA_RATE_HZ = 30.0
_STREAM_IMU, _STREAM_VEL, _STREAM_FRAME, _STREAM_JITTER = 1, 2, 3, 4


@dataclass
class SimulationResult:
    """What `simulate()` wrote."""

    root: Path
    scenario: str
    duration_s: float
    n_frames: int  # per camera (synchronised)
    n_imu: int
    blackouts: list[tuple[int, int, str]]  # (start_ns, end_ns, kind)
    readable_floor_fraction: float | None  # frames of cam0 with a decodable floor code
    readable_floor_fraction_outside_blackouts: float | None
    wall_time_s: float
    cameras: list[str] = field(default_factory=list)
    render_cpu_s: float = 0.0  # CPU time of rendering + PNG encoding, all workers


# ---------------------------------------------------------------------------- worker side


def png_params(level: int) -> list[int]:
    """cv2.imencode parameters of the simulator's PNGs at zlib `level` (0-9).  Measured on a
    simulated 640x480 flight (scripts/bench_frontend_speed.py, BENCHMARKS.md): sensor
    noise defeats LZ matching, so Huffman-only coding is as small as deflate at level >= 3 and
    several times faster; libpng's adaptive filter choice (all five filters) saves ~6 % of the
    size but the Paeth rows it picks cost a reader ~40 % more decoding than the Up filter alone
    with OpenCV's decoder, ~3x with the reader's fast path (`fusion.log.png`: None / Sub / Up
    rows only); level 0 (stored, no filter: twice the size) decodes 5-7x faster than the level-1
    files with OpenCV (~4x with the fast path), for throughput benchmarks; level 9 with the
    default strategy and all filters for the smallest."""
    if level <= 0:
        return [cv2.IMWRITE_PNG_COMPRESSION, 0, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
    if level >= 9:
        return [cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_DEFAULT]
    return [
        cv2.IMWRITE_PNG_COMPRESSION,
        level,
        cv2.IMWRITE_PNG_STRATEGY,
        cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
        cv2.IMWRITE_PNG_FILTER,
        cv2.IMWRITE_PNG_FILTER_UP,
    ]


class _RenderJob:
    """What every rendering task needs (sent once to each worker process); the scene's code
    textures are built on first use, in the worker."""

    def __init__(self, scenario: Scenario, seed: int, png_level: int, check_readable: bool):
        self.scenario, self.seed, self.check_readable = scenario, seed, check_readable
        self.png_params = png_params(png_level)
        self._codes = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_codes": None}

    @property
    def codes(self):
        if self._codes is None:
            self._codes = self.scenario.codes()
        return self._codes


def _blur(camera, T_a: np.ndarray, T_b: np.ndarray, depth_hint_m: float) -> tuple[float, float]:
    """Image motion (px, direction) of the scene point on the optical axis between two poses."""
    R, c = T_a[:3, :3], T_a[:3, 3]
    axis = R[:, 2]
    depth = -c[2] / axis[2] if axis[2] < -0.2 else depth_hint_m  # floor, else a face ahead
    p_world = c + min(max(depth, 0.2), 20.0) * axis
    uv = []
    for T in (T_a, T_b):
        T_cw = inv_T(T)
        uv.append(camera.project((T_cw[:3, :3] @ p_world + T_cw[:3, 3])[None])[0])
    d = uv[1] - uv[0]
    if not np.all(np.isfinite(d)):
        return 0.0, 0.0
    return float(np.hypot(*d)), float(math.atan2(d[1], d[0]))


def _render_frame(job: _RenderJob, k: int, t_s: float) -> tuple[int, list[bytes], bool | None]:
    sc = job.scenario
    half = 0.5 * sc.exposure_s
    st = sc.trajectory.state(np.array([t_s - half, t_s, t_s + half]))
    T_wb = st.T_world_body
    pngs, readable = [], None
    for ci, (name, cam) in enumerate(sc.cameras.items()):
        poses = [cam.T_world_cam(T) for T in T_wb]
        blur_px, blur_dir = _blur(cam, poses[0], poses[2], 1.2)
        fx = sc.effects(name, t_s, blur_px, blur_dir)
        rng = np.random.default_rng([job.seed, _STREAM_FRAME, ci, k])
        view = poses[1]
        if cam.rolling_shutter:  # one true pose per row (the stamp is the camera's stamp_row)
            view = rolling_shutter_poses(cam, lambda t: sc.trajectory.state(t).T_world_body, t_s)
        img = render_view(cam, view, job.codes, rng, fx, sc.occluders)
        ok, buf = cv2.imencode(".png", img, job.png_params)
        if not ok:
            raise SimulationError(f"PNG encoding failed for {name} frame {k}")
        pngs.append(buf.tobytes())
        if name == "cam0" and job.check_readable:
            readable = floor_code_readable(img)
    return k, pngs, readable


def _render_chunk(job: _RenderJob, frames: list[tuple[int, float]]) -> tuple[list, float]:
    """Render frames [(index, t_s)]; also returns the CPU time this took (s)."""
    t0 = time.process_time()
    out = [_render_frame(job, k, t) for k, t in frames]
    return out, time.process_time() - t0


def frame_renderer(scenario: Scenario, seed: int = 0, png_compression: int = 1):
    """`render(k, t_s) -> [PNG bytes per camera]`: frame k of `scenario` at time t_s, exactly as
    `simulate` renders it (for benchmarks and experiments that time or inspect single frames)."""
    job = _RenderJob(scenario, seed, png_compression, check_readable=False)

    def render(k: int, t_s: float) -> list[bytes]:
        return _render_frame(job, k, t_s)[1]

    return render


def floor_code_readable(img: np.ndarray) -> bool:
    """True if zxing-cpp decodes at least one floor code (payload '0/...') in `img`."""
    import zxingcpp

    res = zxingcpp.read_barcodes(img, formats=zxingcpp.BarcodeFormats(zxingcpp.BarcodeFormat.QRCode))
    return any(r.text.startswith("0/") for r in res)


# ---------------------------------------------------------------------------- main side


def simulate(
    out_dir: Path,
    scenario: str | Scenario = "default",
    duration_s: float | None = None,
    seed: int = 0,
    overwrite: bool = False,
    progress: bool = True,
    workers: int | None = None,
    resolution=(640, 480),
    camera_rate_hz: float = CAMERA_RATE_HZ,
    noise_sigma_dn: float | None = None,
    png_compression: int = 1,
    check_readable: bool = False,
    start_s: float = 0.0,
    fmt: str = "euroc",
    readout_s: float | None = None,
    placement_error_m: float = 0.0,
    placement_error_deg: float = 0.0,
    placement_seed: int | None = None,
    time_offset_ms: dict[str, float] | float | None = None,
    clock_drift_ppm: dict[str, float] | float | None = None,
    stamp_jitter_ms: dict[str, float] | float | None = None,
    camera_options: CameraOptions | None = None,
    extrinsic_error_deg: dict[str, tuple[float, float, float]] | None = None,
    velocity_rate_hz: float | None = None,
    imu_noise_scale: float = 1.0,
    imu_noise_stated: float = 1.0,
) -> SimulationResult:
    """Simulate `scenario` for `duration_s` (None: the scenario's length) and write the flight
    log to `out_dir` (EuRoC layout: world.yaml, cam0 floor + cam1 front at `camera_rate_hz`,
    synchronised; imu0 200 Hz; vel0 30 Hz; ground truth at the IMU rate with the true biases;
    loads_groundtruth.csv; blackouts_groundtruth.csv).

    `start_s` skips the start of the flight (timestamps stay the trajectory's time in ns).
    Deterministic for a seed.  `workers` processes render (None: all cores); they start with
    multiprocessing's "forkserver" method, so a script calling this needs the usual
    `if __name__ == "__main__":` guard (or workers=1).  `check_readable`
    runs zxing-cpp on every floor frame and reports the fraction with a readable floor code.
    Raises SimulationError for an unknown scenario or a bad duration, LogError if `out_dir`
    exists and not `overwrite`.  With `overwrite`, only a previous simulation's files (its
    manifest.json) are replaced: the user's other files in `out_dir` are kept, and a folder
    holding a log fusion did not write, or a foreign `<out_dir>.partial/`, is refused.

    `fmt` (fusion.log.LogFormat): "euroc" (default), "rosbag1" (OUT.bag), "rosbag2" (OUT.mcap)
    or "video" (a folder of lossless FFV1 videos); the EuRoC folder is written first and
    converted once complete (fusion.log.convert.export_flight).

    `scenario` may also be a built `Scenario` (benchmarks flying their own trajectories; its
    cameras are then modified in place).  `readout_s` (None: the scenario's `readout_s`) makes
    both cameras rolling-shutter with that whole-frame readout time, stamped at the first row:
    each frame is rendered with one true pose per row (`render.rolling_shutter_poses`) and the
    line delay is written to the cameras' sensor.yaml (`line_delay_s`).
    `placement_error_m` / `placement_error_deg`: the floor codes are stuck down off their
    payload's pose by N(0, sigma) per axis and in yaw (drawn from `placement_seed`, None: from
    `seed`; one placement seed and several seeds: several flights over one floor); world.yaml then
    states these sigmas as floor_qr.placement_sigma_m / _deg (0 and 0, the default: exactly
    laid, today's model), and `floor_codes_groundtruth.csv` holds the true poses; it states
    the load labels' print error as load_qr.side_sigma_m 0 (they are rendered exactly).
    `time_offset_ms` ({"cam0": ms, "cam1": ms}, or one number for both): camera-IMU clock
    offsets, Kalibr's sign (t_imu = t_cam + offset): each frame is rendered at its true time t
    and logged with the stamp t - offset (ground truth, IMU and velocity stay in the true clock);
    frames whose stamp would fall before the flight's start are left out.
    `clock_drift_ppm` (likewise per camera): each camera's clock runs fast by that many ppm of
    the flight's time: the stamp is t - offset - ppm 1e-6 (t - start), the offset growing over
    the flight as a free-running camera oscillator's does (fusion.estimate.timeoffset.ClockDrift).
    `stamp_jitter_ms` (likewise per camera): each stamp off by white Gaussian noise of that
    sigma (a driver stamping frames on arrival); stamps stay increasing.
    `camera_options` (fusion.sim.scenarios.CameraOptions): camera effects (JPEG, noise, defocus,
    ...) and lens changes (focal length, distortion) on top of the scenario's.
    `extrinsic_error_deg` ({"cam0": (rx, ry, rz)}, degrees): each named camera's true mount is
    its nominal one turned by that rotation vector in the body frame about the camera's centre
    (fusion.estimate.extrinsics.corrected_mount); the images are rendered with the true mount
    while sensor.yaml keeps the nominal T_BS (a wrong calibration, as in real life) and states
    the error's RMS per axis as its T_BS_sigma_deg (0 for an exact mount, and T_BS_sigma_m 0;
    intrinsics_sigma 0: the images are rendered with the intrinsics it writes);
    `extrinsics_groundtruth.csv` holds the errors.  `velocity_rate_hz` (None: the scenario's
    30 Hz, stamped with the frames): the velocity sensor's own rate.
    `imu_noise_scale`: the IMU's white noise densities and bias random walks are this many times
    the scenario's (a worse IMU, or one on a vibrating frame); `imu_noise_stated`: imu0's
    sensor.yaml states this many times the true values (1: an honest calibration; below 1 an
    optimistic datasheet, e.g. one that leaves out the propellers' vibration)."""
    from fusion.log import LogFormat

    # every argument but the destination, for the conversion path (nothing left out by hand)
    forwarded = {k: v for k, v in locals().items() if k not in ("out_dir", "overwrite", "fmt", "LogFormat")}

    try:
        fmt = LogFormat(fmt)
    except ValueError:
        raise SimulationError(
            f"unknown format {fmt!r}; expected one of {', '.join(f.value for f in LogFormat)}"
        ) from None
    if fmt != LogFormat.EUROC:
        return _simulate_as(fmt, out_dir, overwrite, **forwarded)
    t_wall = time.perf_counter()
    if not isinstance(scenario, Scenario) and scenario not in SCENARIOS:
        raise SimulationError(f"unknown scenario {scenario!r}; expected one of {SCENARIOS}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SimulationError(f"seed must be a non-negative integer, got {seed!r}")
    want_s = None
    if isinstance(duration_s, (int, float)) and isinstance(start_s, (int, float)):
        want_s = float(start_s) + float(duration_s)
    if isinstance(scenario, Scenario):
        sc, scenario = scenario, scenario.name
    else:
        sc = build_scenario(scenario, resolution, min_duration_s=want_s)
    if readout_s is not None:
        sc.readout_s = float(readout_s)
    sc.apply_readout()
    if duration_s is None:
        duration_s = sc.duration_s
    try:
        duration_s = float(duration_s)
    except (TypeError, ValueError):
        raise SimulationError(f"duration {duration_s!r} is not a number") from None
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise SimulationError(f"duration must be a positive number of seconds, got {duration_s}")
    if not (isinstance(start_s, (int, float)) and math.isfinite(start_s) and start_s >= 0):
        raise SimulationError(f"start must be a non-negative number of seconds, got {start_s!r}")
    if start_s + duration_s > sc.trajectory.duration_s + 1e-9:
        raise SimulationError(
            f"scenario {scenario!r} flies {sc.trajectory.duration_s:.1f} s; "
            f"start {start_s} s + duration {duration_s} s is longer"
        )
    if not (camera_rate_hz > 0 and math.isfinite(camera_rate_hz)):
        raise SimulationError(f"camera rate must be positive, got {camera_rate_hz}")
    if velocity_rate_hz is not None:
        rate = velocity_rate_hz
        number = isinstance(rate, (int, float)) and not isinstance(rate, bool)
        if not (number and rate > 0 and math.isfinite(rate)):
            raise SimulationError(f"velocity rate must be positive, got {rate!r}")
        sc.velocity_rate_hz = float(rate)
    if camera_options is not None:
        apply_camera_options(sc, camera_options)
    if noise_sigma_dn is not None:
        sc.noise_sigma_dn = float(noise_sigma_dn)
    for name, v in (
        ("placement error (m)", placement_error_m),
        ("placement error (deg)", placement_error_deg),
    ):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
            raise SimulationError(f"{name} must be a number >= 0, got {v!r}")
    sc.layout.world.placement_sigma_m = float(placement_error_m)
    sc.layout.world.load_side_sigma_m = 0.0  # the rendered labels are exact
    sc.layout.world.placement_sigma_deg = float(placement_error_deg)
    if placement_error_m > 0 or placement_error_deg > 0:
        sc.layout.floor_offsets = placement_offsets(
            len(sc.layout.floor_codes_xy),
            placement_error_m,
            math.radians(placement_error_deg),
            seed if placement_seed is None else placement_seed,
        )
    workers = worker_count(workers)
    if workers > 1 and mp.current_process().name != "MainProcess":
        # most likely a worker re-importing an unguarded main script: stop before touching disk
        raise SimulationError(
            "simulate(workers > 1) called inside a child process; guard the "
            "calling script with `if __name__ == '__main__':` or use workers=1"
        )
    for cam in sc.cameras.values():
        cam.rate_hz = camera_rate_hz
    traj = sc.trajectory

    noise_scale = strict_float(imu_noise_scale, "IMU noise scale", SimulationError, positive=True)
    true_noise = sc.imu_noise.scaled(noise_scale)
    imu, bias_g, bias_a = synthesize_imu(
        traj, sc.imu_rate_hz, true_noise, np.random.default_rng([seed, _STREAM_IMU])
    )
    imu.noise = true_noise.scaled(
        strict_float(imu_noise_stated, "stated IMU noise", SimulationError, positive=True)
    )
    t0_ns, t1_ns = int(round(start_s * 1e9)), int(round((start_s + duration_s) * 1e9))
    keep = (imu.timestamps_ns >= t0_ns) & (imu.timestamps_ns <= t1_ns)
    imu.timestamps_ns, imu.gyro_rad_s, imu.accel_m_s2 = (
        imu.timestamps_ns[keep],
        imu.gyro_rad_s[keep],
        imu.accel_m_s2[keep],
    )
    bias_g, bias_a = bias_g[keep], bias_a[keep]
    vel = synthesize_velocity(
        traj, sc.velocity_rate_hz, sc.velocity_noise_m_s, np.random.default_rng([seed, _STREAM_VEL])
    )
    keep = (vel.timestamps_ns >= t0_ns) & (vel.timestamps_ns <= t1_ns)
    vel.timestamps_ns, vel.v_body_m_s = vel.timestamps_ns[keep], vel.v_body_m_s[keep]
    st = traj.state(imu.timestamps_ns * 1e-9)
    gt = GroundTruth(
        imu.timestamps_ns, st.p_world, quat_wxyz_from_R(st.R_world_body), st.v_world, bias_g, bias_a
    )
    blackouts = [
        (max(int(round(a * 1e9)), t0_ns), min(int(round(b * 1e9)), t1_ns), kind)
        for a, b, kind in sc.blackouts
        if a * 1e9 < t1_ns and b * 1e9 > t0_ns
    ]
    frame_ns = sample_times_ns(duration_s, camera_rate_hz, t0_ns)
    offset_ns = _camera_offsets_ns(time_offset_ms, list(sc.cameras))
    drift_ns = _camera_offsets_ns(clock_drift_ppm, list(sc.cameras), "clock drift")  # ppm x 1e6
    jitter_ns = _camera_offsets_ns(stamp_jitter_ms, list(sc.cameras), "stamp jitter")
    if any(v < 0 for v in jitter_ns.values()):
        raise SimulationError("stamp jitter must be >= 0 ms")
    period_ns, first_ns = 1e9 / camera_rate_hz, int(frame_ns[0]) if len(frame_ns) else t0_ns
    jitter = {  # per camera and frame index, drawn once; at most 0.45 period so stamps keep their order
        n: np.clip(
            np.random.default_rng([seed, _STREAM_JITTER, i]).normal(0.0, v, len(frame_ns) + 1),
            -0.45 * period_ns,
            0.45 * period_ns,
        )
        for i, (n, v) in enumerate(sorted(jitter_ns.items()))
    }

    def stamp_ns(name: str, t_ns):
        """The logged stamp of camera `name` for true time(s) t_ns."""
        t = np.asarray(t_ns, dtype=np.int64)
        drift = np.round(drift_ns.get(name, 0) * 1e-12 * (t - t0_ns)).astype(np.int64)
        out = t - offset_ns.get(name, 0) - drift
        if name in jitter:
            k = np.clip(np.round((t - first_ns) / period_ns).astype(np.int64), 0, len(jitter[name]) - 1)
            out = out + np.round(jitter[name][k]).astype(np.int64)
        return out

    mount_err = _mount_errors_rad(extrinsic_error_deg, list(sc.cameras))
    if offset_ns or drift_ns or jitter_ns:
        frame_ns = frame_ns[np.all([stamp_ns(n, frame_ns) >= t0_ns for n in sc.cameras], axis=0)]

    readable: list[bool] = []
    with FlightLogWriter(Path(out_dir), overwrite=overwrite) as writer:
        writer.write_world(sc.layout.world)
        for name, cam in sc.cameras.items():
            # the mount's sigma as it is: 0, or the RMS per axis of an extrinsic error given
            err = mount_err.get(name)
            sigma_deg = 0.0 if err is None else float(np.degrees(np.sqrt(np.mean(err**2))))
            writer.add_camera(
                name,
                # its intrinsics are exact: those it renders with
                replace(cam, mount_sigma_deg=sigma_deg, mount_sigma_m=0.0, intrinsics_sigma_px=(0.0,) * 4),
                comment=f"fusion simulator, scenario {scenario}, "
                f"{'floor' if name == 'cam0' else 'front'} camera",
            )
        writer.write_imu(imu)
        writer.write_velocity(vel)
        writer.write_groundtruth(gt)
        writer.write_loads_groundtruth({l.id: np.asarray(l.p_world) for l in sc.layout.loads})
        writer.write_blackouts(blackouts)
        if mount_err:
            write_extrinsics_groundtruth(writer.tmp / EXTRINSICS_GROUNDTRUTH_CSV, mount_err)
        if sc.layout.floor_offsets is not None:
            T_true = sc.floor_codes_true_T()
            write_groundtruth_csv(
                writer.tmp / FLOOR_CODES_GROUNDTRUTH_CSV,
                [floor_payload(x, y) for x, y in np.asarray(sc.layout.floor_codes_xy).reshape(-1, 2)],
                np.c_[T_true[:, :2, 3], yaw_of(T_true[:, :3, :3])],
            )

        tasks = [(k, t * 1e-9) for k, t in enumerate(frame_ns)]
        chunk = 8
        chunks = [tasks[i : i + chunk] for i in range(0, len(tasks), chunk)]
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(tasks), unit="frame", desc=f"simulate {scenario}")
        names = list(sc.cameras)

        cpu_s = [0.0]

        def consume(chunk_result):
            results, cpu = chunk_result
            cpu_s[0] += cpu
            for k, pngs, ok in results:
                for name, png in zip(names, pngs):
                    writer.write_frame_png(name, int(stamp_ns(name, frame_ns[k])), png)
                if ok is not None:
                    readable.append(ok)
                if bar is not None:
                    bar.update(1)

        # rendered with the true mounts; sensor.yaml above holds the nominal ones
        rendered = sc
        if mount_err:
            cams = {
                n: corrected_camera(c, mount_err[n]) if n in mount_err else c for n, c in sc.cameras.items()
            }
            rendered = replace(sc, cameras=cams)
        job = _RenderJob(rendered, seed, int(png_compression), check_readable)
        try:
            for res in parallel_map(_render_chunk, chunks, workers, job, preload=["fusion.sim.simulate"]):
                consume(res)
        finally:
            if bar is not None:
                bar.close()

    frac = frac_out = None
    if readable:
        r = np.array(readable)
        frac = float(r.mean())
        inside = np.zeros(len(frame_ns), bool)
        for a, b, _ in blackouts:
            inside |= (frame_ns >= a) & (frame_ns <= b)
        frac_out = float(r[~inside].mean()) if (~inside).any() else None
    return SimulationResult(
        Path(out_dir),
        scenario,
        duration_s,
        len(frame_ns),
        len(imu.timestamps_ns),
        blackouts,
        frac,
        frac_out,
        time.perf_counter() - t_wall,
        names,
        cpu_s[0],
    )


def _camera_offsets_ns(time_offset_ms, names: list[str], what: str = "time offset") -> dict[str, int]:
    """{camera: value x 1e6 as int} from `time_offset_ms` (a number for every camera, or a
    dict): ms -> ns for offsets, ppm -> 1e-6 ppm for clock drifts; SimulationError naming
    `what` for an unknown camera or a non-finite value."""
    if time_offset_ms is None:
        return {}
    given = time_offset_ms if isinstance(time_offset_ms, dict) else {n: time_offset_ms for n in names}
    out = {}
    for name, ms in given.items():
        if name not in names:
            raise SimulationError(f"{what} for unknown camera {name!r}; cameras: {', '.join(names)}")
        try:
            v = float(ms)
        except (TypeError, ValueError):
            raise SimulationError(f"{what} of {name}: {ms!r} is not a number") from None
        if not math.isfinite(v):
            raise SimulationError(f"{what} of {name} must be finite, got {ms!r}")
        out[name] = int(round(v * 1e6))
    return out


def _mount_errors_rad(extrinsic_error_deg, names: list[str]) -> dict[str, np.ndarray]:
    """{camera: rotation vector (3,) rad} from `extrinsic_error_deg`; SimulationError for an
    unknown camera or not three finite numbers."""
    out = {}
    for name, w in (extrinsic_error_deg or {}).items():
        if name not in names:
            raise SimulationError(f"extrinsic error for unknown camera {name!r}; cameras: {', '.join(names)}")
        try:
            v = np.asarray(w, dtype=float).reshape(3)
        except (TypeError, ValueError):
            raise SimulationError(
                f"extrinsic error of {name}: {w!r} is not three numbers (degrees)"
            ) from None
        if not np.all(np.isfinite(v)):
            raise SimulationError(f"extrinsic error of {name} must be finite, got {w!r}")
        if np.any(v):
            out[name] = np.radians(v)
    return out


_FORMAT_SUFFIX = {"rosbag1": ".bag", "rosbag2": ".mcap", "video": ""}


def _simulate_as(fmt, out: Path, overwrite: bool, **kwargs) -> SimulationResult:
    """simulate() into a temporary EuRoC folder beside `out`, then convert it to `fmt`."""
    import shutil

    from fusion.errors import LogError
    from fusion.log.convert import export_flight

    out = Path(out)
    suffix = _FORMAT_SUFFIX[fmt.value]
    if suffix and out.suffix != suffix:
        out = out.with_name(out.name + suffix)
    if out.exists() and not overwrite:
        raise LogError(f"{out}: already exists")
    tmp = out.with_name(out.name + ".euroc")
    t_wall = time.perf_counter()
    try:
        res = simulate(tmp, overwrite=True, **kwargs)
        export_flight(tmp, out, fmt=fmt, overwrite=overwrite)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res.root = out
    res.wall_time_s = time.perf_counter() - t_wall
    return res
