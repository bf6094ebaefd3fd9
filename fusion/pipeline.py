"""The product's main job: `run(log_dir, out_dir)` takes a logged flight to trajectories, a load
map, metrics and a report (DESIGN.md "Data flow"):

    read log -> detect (cached) -> per-frame estimators (paper, pnp)
             -> fusion (smoother, incremental, ekf) -> evaluate (with ground truth) -> report

Each stage is a function with a typed result; the CLI only calls `run` / `demo` and prints
`RunResult.summary()`.  Outputs are written atomically, file by file, into an output folder that
the run locks, lists in `manifest.json` and rolls back on failure (`fusion.fileio.OutputFolder`).
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from fusion import __version__
from fusion.camera import DEFAULT_FOCAL_SIGMA_REL, DEFAULT_PRINCIPAL_POINT_SIGMA_PX
from fusion.errors import EstimationError, FusionError, LogError, first_line
from fusion.estimate import (
    FusionConfig,
    FusionResult,
    Health,
    Status,
    assess_result,
    cornerbias,
    correlation,
    run_ekf,
    smooth,
    smooth_incremental,
    variance,
    write_sigmas_csv,
)
from fusion.estimate.asbuilt import (
    FLOOR_CODES_CSV,
    AsBuiltInput,
    FloorCodeMap,
    Placement,
    common_shift,
    write_floor_codes_csv,
)
from fusion.estimate.common import LOAD_INTERP_MAX_GAP_S, interpolable_load_times, match_to_frames
from fusion.estimate.extrinsics import (
    MountRotation,
    MountSource,
    apply_mount,
    check_mount,
    estimate_front_mount,
    read_extrinsics_groundtruth,
)
from fusion.estimate.fixes import heading_warning, merge_fixes
from fusion.estimate.health import tilt_disagreement
from fusion.estimate.loadconsider import (
    add_departure,
    add_floor_shift,
    add_load_consider_covariance,
    add_places_spread,
    common_terms,
)
from fusion.estimate.mountconsider import add_mount_consider, mount_consider_covariance, mount_sigmas_rad
from fusion.estimate.tiltconsider import add_tilt_consider, level_kept_fraction, tilt_consider_sigma_rad
from fusion.estimate.timeoffset import (
    TimeOffsetConfig,
    TimeOffsets,
    add_stamp_covariance,
    check_stated_offsets,
    fused_trajectory,
    resolve_time_offsets,
    shift_detections,
    shift_log,
    whole_flight_input,
    widen_sightings,
)
from fusion.estimate.window import (
    AS_BUILT_WINDOW_S,
    WINDOW_S,
    WindowConfig,
    estimate_mount_windowed,
    smooth_windowed,
)
from fusion.evaluate.metrics import evaluate, export_groundtruth_tum, to_jsonable, write_metrics
from fusion.evaluate.report import write_report
from fusion.fileio import OutputFolder, atomic_open, csv_safe, load_yaml
from fusion.log import FlightLog, LogOptions, LogWarning, read_flight
from fusion.log.files import write_loads_csv, write_loads_json, write_tum
from fusion.log.fixes import PositionFixes, fixes_in_flight, read_fixes
from fusion.parallel import Outcome, call_each, chunk_bounds, parallel_map, start_workers_early, worker_count
from fusion.qr import paper, pnp
from fusion.qr.codes import FLOOR_CODE_ON_FRONT, LOAD_CODE_ON_FLOOR, classify, rejection_counts
from fusion.qr.detect import (
    CACHE_NAME,
    CACHE_REUSED,
    DetectionResult,
    detect_flight,
    flight_fingerprint,
    pack_frames,
    read_cache,
    unpack_frames,
    write_cache,
)
from fusion.qr.pnp import LoadFrame, estimate_load_observations_frames
from fusion.qr.predict import track_flight, tracked_fingerprint, with_tracked, without_tracked
from fusion.qr.refine import SMALL_MODULE_PX
from fusion.qr.rolling_shutter import (
    UNDECLARED_CHECK_CHI2_DOF,
    ReadoutCalibration,
    RollingShutterReport,
    add_pose_covariance,
    add_sighting_covariance,
    calibrate_readout,
    check_undeclared_readout,
    correct_flight,
)
from fusion.sim.simulate import simulate
from fusion.types import (
    RAW_ESTIMATORS,
    CameraRole,
    Estimator,
    LoadMap,
    LoadObservation,
    RobustKernel,
    Trajectory,
    role_name,
)
from fusion.warehouse import floorcodes
from fusion.warehouse.inventory import AMBIGUITY_SEPARATION_M, ambiguous_places
from fusion.warehouse.runs import WORLD_YAML
from fusion.warehouse.view3d import floor_codes_from_payloads
from fusion.world import FloorLayout, World

logger = logging.getLogger(__name__)

STAGES = ("detect", "localize", "smooth", "run")
WARM_START_MAX_SHIFT_S = 0.05
"""The batch smoother starts from the shared whole-flight solve's states only when each frame's
stamp moved by at most this (the time-offset search's half-width; a start, not a result)."""
GIMBALED_TILT_NOTE = (
    "gimbaled floor camera: its fixes give position and yaw only; the fused roll / pitch come from "
    "the IMU against the fixes' motion, and the health can only compare the back ends' tilts with "
    "each other.  PnP takes the camera as level to its sensor.yaml T_BS_sigma_deg (0.1 deg when "
    "not stated).  Stated exact, the tilt was consistent on simulated flights; otherwise it carries "
    "a consider term that grows with that sigma against PnP's own tilt sigma up to the "
    "accelerometer bias prior over g (~10 mrad per axis), because pitch was up to 20 mrad off "
    "with a claimed sigma of ~5 mrad at 0.1 deg and 15 at 0.01 deg (BENCHMARKS.md, gimb16 / lev16)"
)


@dataclass
class RunConfig:
    """Choices of a run; defaults are what `fusion run` uses."""

    backend: str = "zxing"  # QR detector: zxing | aruco
    workers: int | None = None  # detection processes (None: all cores)
    progress: bool = True  # tqdm bars
    force: bool = False  # allow an existing output folder
    robust: str = "huber"  # robust kernel on QR pose factors
    tight: bool = False  # corner reprojection factors instead of per-frame poses
    incremental: bool = True  # also run the incremental (causal) smoother
    th_px: float = 5.0  # the paper's Th (Algorithms 1 and 4), pixels
    corner_sigma_px: float = 0.15  # refined-corner noise, 1 sigma, pixels
    calibrate_readout: bool = False  # estimate the floor camera's rolling-shutter readout time
    # apply the floor camera's estimated mount rotation error when significant (the check and its
    # warning run regardless: fusion.estimate.extrinsics)
    calibrate_extrinsics: bool = False
    floor_map: Path | None = None  # `fusion run --map`: merged floor codes as the prior
    # camera-IMU time offsets fixed by hand {camera: s} (t_imu = t_cam + offset); the cameras
    # not given are estimated (fusion.estimate.timeoffset); None: estimate both
    time_offsets_s: dict[str, float] | None = None
    # external position fixes CSV (t_ns,x,y,z,sigma_m: GNSS, UWB, total station, mocap), fused
    # beside the QR poses, or instead of them in a log without cameras
    fixes: Path | None = None
    estimate_noise_scale: bool = True  # corner-noise scale from the residuals (variance.py)
    # with estimate_noise_scale: a floor-corner bias common to the flight, removed from the PnP
    # poses when significant and its uncertainty added to every pose covariance (cornerbias.py)
    correct_corner_bias: bool = True
    # with estimate_noise_scale: corner errors correlated from frame to frame (per corner class,
    # from the PnP residuals' autocorrelation) inflate the back ends' PnP input covariances by
    # their correlation time (correlation.py)
    inflate_correlated: bool = True
    # the track pass (--track): undecoded floor codes a predicted pose puts in view; off by default
    # (it made the clean demo's PnP ATE worse: BENCHMARKS.md)
    track: bool = False
    # the batch smoother solves flights longer than window.WINDOW_MIN_FLIGHT_S in overlapping
    # windows of this length (bounded memory: fusion.estimate.window); 0: always the whole
    # flight; None: WINDOW_S, or AS_BUILT_WINDOW_S when the floor codes are as built
    smoother_window_s: float | None = None


@dataclass
class RunResult:
    out_dir: Path
    log_summary: dict
    detection_stats: dict = field(default_factory=dict)
    trajectories: dict[str, Trajectory] = field(default_factory=dict)
    load_maps: dict[str, LoadMap] = field(default_factory=dict)
    metrics: dict | None = None
    notes: list[str] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)
    report_path: Path | None = None
    warnings: list[LogWarning] = field(default_factory=list)  # the log's (FlightLog.warnings)
    failures: dict[str, EstimatorFailure] = field(default_factory=dict)
    health: dict[str, Health] = field(default_factory=dict)  # fused estimators (health.py)
    readout_calibration: ReadoutCalibration | None = None  # --calibrate-readout's estimate
    rolling_shutter: RollingShutterReport | None = None  # what the corner correction did
    floor_codes: dict[str, FloorCodeMap] = field(default_factory=dict)  # as-built, by estimator
    time_offsets: TimeOffsets | None = None  # camera-IMU clock offsets, applied to every output
    extrinsics: MountRotation | None = None  # the floor camera's mount check / calibration
    front_extrinsics: MountRotation | None = None  # the front camera's (estimate_front_mount)
    noise_scales: dict = field(default_factory=dict)  # variance.noise_summary (metrics.json)

    fusion_expected: bool = False  # the run went as far as the fusion (until smooth / run)

    @property
    def trusted(self) -> bool:
        """True when every fused estimator ran and its health is ok (what --strict asks); a run
        that was to fuse and has no fused estimate at all (no floor pose, no IMU nor velocity)
        is not."""
        if self.fusion_expected and not self.health and not self.failures:
            return False
        return not self.failures and all(h.status == Status.OK for h in self.health.values())

    def summary(self) -> str:
        """A short table for the terminal."""
        lines = [
            f"flight: {self.log_summary.get('path')}  "
            f"({self.log_summary.get('duration_s', 0):.1f} s, "
            f"{self.log_summary.get('floor_frames', 0)} floor frames)"
        ]
        ds = self.detection_stats
        if ds:
            lines.append(
                f"floor frames with a code: {ds.get('floor_frames_with_code', 0)}"
                f"/{ds.get('floor_frames', 0)}; skipped frames: {ds.get('frames_skipped', 0)};"
                f" rejected payloads: {ds.get('rejected_total', 0)}"
            )
            for cam, r in ds.get("refinement", {}).items():
                why = ", ".join(
                    f"{k.removeprefix('refine_').replace('_', ' ')} {v}"
                    for k, v in r.items()
                    if k.startswith("refine_") and k != "refine_failed" and v
                )
                if r.get("refine_failed") or r.get("tracked"):
                    lines.append(
                        f"{cam}: {r.get('refine_failed', 0)} codes kept the decoder's corners"
                        + (f" ({why})" if why else "")
                        + f"; {r.get('tracked', 0)} tracked sightings"
                    )
                if r.get("small_module_codes"):
                    lines.append(
                        f"{cam}: {r['small_module_codes']} codes under {SMALL_MODULE_PX[1]} px per module "
                        "(far or small labels): their corner sigma widened"
                    )
        per = (self.metrics or {}).get("trajectories", {})
        header = (
            f"{'estimator':<12} {'poses':>6} {'x cm':>7} {'y cm':>7} {'z cm':>7} "
            f"{'yaw deg':>8} {'ATE cm':>8} {'ATE@pnp cm':>11} {'health':>9}"
        )
        lines += ["", header, "-" * len(header)]
        for name, traj in self.trajectories.items():
            m = per.get(name, {})
            mae = m.get("mae_xyz_m")

            def cm(i, mae=mae):
                return f"{100 * mae[i]:7.2f}" if mae else f"{'-':>7}"

            yaw = m.get("mae_yaw_deg")
            ate = m.get("ate_rmse_m")
            ate_ref = m.get("ate_rmse_on_reference_frames_m")
            lines.append(
                f"{name:<12} {len(traj):>6} {cm(0)} {cm(1)} {cm(2)} "
                f"{(f'{yaw:8.3f}' if yaw is not None else f'{chr(45):>8}')} "
                f"{(f'{100 * ate:8.2f}' if ate is not None else f'{chr(45):>8}')} "
                f"{(f'{100 * ate_ref:11.3f}' if ate_ref is not None else f'{chr(45):>11}')} "
                f"{str(self.health[name].status) if name in self.health else chr(45):>9}"
            )
        for name, lm in self.load_maps.items():
            m = (self.metrics or {}).get("load_maps", {}).get(name, {})
            mae = m.get("mae_xyz_m")
            err = f"; MAE x/y/z {100 * mae[0]:.2f}/{100 * mae[1]:.2f}/{100 * mae[2]:.2f} cm" if mae else ""
            lines.append(f"loads {name:<9} {len(lm.loads)} mapped{err}")
        for name, fmap in self.floor_codes.items():
            bad = fmap.misplaced
            lines.append(
                f"floor codes {name}: {len(fmap.codes)} as built, {len(bad)} misplaced"
                + (
                    ": "
                    + ", ".join(f"{c.code_id} {100 * np.linalg.norm(c.offset_xy_m):.1f} cm" for c in bad[:8])
                    if bad
                    else ""
                )
                + (" ..." if len(bad) > 8 else "")
            )
        for name, h in self.health.items():
            if h.status != Status.OK:
                lines.append(f"health: {name} {h.status}: {h.reason}")
        if self.time_offsets is not None:
            lines += self.time_offsets.lines()
        if self.extrinsics is not None:
            lines.append(self.extrinsics.describe())
        if self.front_extrinsics is not None:
            lines.append(self.front_extrinsics.describe())
        for w in self.warnings:
            lines.append(f"warning: {w}")
        for name, failure in self.failures.items():
            lines.append(f"{name:<12} FAILED: {failure.reason}")
        line = variance.summary_line(self.noise_scales)
        if line:
            lines.append(line)
        for note in self.notes:
            lines.append(f"note: {note}")
        if self.report_path is not None:
            lines.append(f"report: {self.report_path}")
        lines.append(f"outputs: {self.out_dir}")
        return "\n".join(lines)


def _require_readable_floor(log: FlightLog, det: DetectionResult) -> None:
    """LogError when not one of the floor camera's frames could be read (all missing, of another
    size than sensor.yaml's resolution, or unreadable): the run would have nothing to localise
    from, and its outputs would look like a flight without codes."""
    stats = det.stats.get(CameraRole.FLOOR.value)
    if stats is None or stats.frames_total == 0 or stats.frames_skipped < stats.frames_total:
        return
    floor_csv = f"{CameraRole.FLOOR.value}/data.csv"
    first = next((m for m in det.skipped if floor_csv in m), det.skipped[0] if det.skipped else "")
    raise LogError(f"{first} (and every other floor-camera frame: {stats.frames_total} unreadable)")


def unreadable_front_warning(det: DetectionResult) -> LogWarning | None:
    """The named warning `front_camera_unreadable` when not one of the front camera's frames
    could be read: the run goes on (the floor camera localises), but maps no load, which a note
    about skipped frames did not make plain (thirty-first session's audit; the floor camera's
    case is an error, `_require_readable_floor`)."""
    stats = det.stats.get(CameraRole.FRONT.value)
    if stats is None or stats.frames_total == 0 or stats.frames_skipped < stats.frames_total:
        return None
    front_csv = f"{CameraRole.FRONT.value}/data.csv"
    first = next((m for m in det.skipped if front_csv in m), "")
    return LogWarning(
        "front_camera_unreadable",
        stats.frames_total,
        f"not one of the front camera's {stats.frames_total} frames could be read (first: {first}): "
        "no load is mapped",
    )


def repeated_frames_warning(det: DetectionResult) -> LogWarning | None:
    """The named warning `repeated_frames` when a camera's frame repeats the codes of the frame
    before it to the last bit (every payload and every refined corner): a real image never does
    (sensor noise moves sub-pixel corners), a frozen camera or a driver re-sending its last image
    (a video made constant-rate by duplicating frames) does, and those frames' stamps are not
    their images'.  A frozen floor camera read as a mount 77 deg off before it was named
    (thirty-first session's audit)."""
    found = []
    for camera in sorted({d.camera for d in det.detections}):
        previous, stamps = None, []
        for t, frame in det.by_frame(camera).items():
            # refined corners only: the decoder's fall-back corners lie on a half-pixel grid, and
            # a code under slow motion keeps them from frame to frame
            key = sorted(
                (d.payload, np.asarray(d.corners_px, float).tobytes())
                for d in frame
                if not np.array_equal(d.corners_px, d.corners_raw_px)
            )
            if key and key == previous:
                stamps.append(t)
            previous = key
        if stamps:
            found.append((camera, len(stamps), stamps[0]))
    if not found:
        return None
    each = "; ".join(
        f"{camera} ({role_name(camera)}) {n} frame(s), the first at {t * 1e-9:.3f} s"
        for camera, n, t in found
    )
    return LogWarning(
        "repeated_frames",
        sum(n for _, n, _ in found),
        f"frames identical to the frame before them, to every corner's last bit: {each}. A frozen "
        "camera or a driver re-sending its last image (or a video made constant-rate by repeating "
        "frames): those frames' stamps are not their images', and the poses from them stand still "
        "whatever the drone does. Check the camera and its driver before calibrating anything",
    )


def log_summary(log: FlightLog) -> dict:
    return {
        "path": str(log.root),
        "duration_s": log.duration_s,
        "floor_frames": len(log.floor) if "cam0" in log.cameras else 0,
        "front_frames": len(log.front) if log.front else 0,
        "imu_samples": len(log.imu.timestamps_ns) if log.imu else 0,
        "has_velocity": log.velocity is not None,
        "has_groundtruth": log.groundtruth is not None,
        "has_loads_groundtruth": log.loads_groundtruth is not None,
    }


def prepare_out_dir(out_dir: Path, force: bool, log_dir: Path | None = None) -> OutputFolder:
    """The run's output folder, to use as a context manager: entering creates and locks it,
    refuses one that is, holds or lies inside `log_dir`, or holds a flight log or another
    command's outputs, refuses a non-empty one unless `force` (then deletes the previous run's
    outputs from its manifest, keeps the user's files and the self-checking detection cache);
    leaving writes `manifest.json`, or on failure removes what the run wrote."""

    meta = {"fusion_version": __version__, "log": str(log_dir) if log_dir is not None else None}
    inputs = (Path(log_dir),) if log_dir is not None else ()
    return OutputFolder(Path(out_dir), force, keep=(CACHE_NAME,), meta=meta, inputs=inputs)


# ============================================================================ stages


@dataclass
class LocalizeResult:
    """Per-frame (raw) estimates: trajectories, load observations and load maps by estimator."""

    trajectories: dict[str, Trajectory]
    load_observations: dict[str, list[LoadObservation]]
    load_maps: dict[str, LoadMap]
    stats: dict
    notes: list[str] = field(default_factory=list)
    # every front-camera load sighting as a camera-frame measurement (p_cam, cov_cam), also at
    # frames without a raw pose (their p_world is meaningless): what the fused back ends take
    camera_frame_observations: list[LoadObservation] = field(default_factory=list)
    # the removed common corner bias's uncertainty, for the fused covariances (cornerbias.py)
    bias_consider: cornerbias.BiasConsider | None = None
    # the back ends' extra input covariance for time-correlated corner errors (correlation.py)
    correlation: correlation.CorrelationInflation | None = None
    # a gimbaled floor camera's free PnP tilt covariances (N, 2, 2), before the level
    # conditioning (PnPStats.frame_free_tilt_covariance): the tilt consider's share
    free_tilt_covariances: np.ndarray | None = None
    # the floor camera's intrinsics error, for every output pose (cornerbias.intrinsics_consider)
    intrinsics_consider: cornerbias.BiasConsider | None = None


@dataclass
class Computed:
    """The detect and localize stages' results computed elsewhere (fusion batch's tasks),
    handed to `run`, which takes them out of this holder (`take`): it then holds the only
    references and lets them go before the fusion's peak, as it does its own (a caller's
    variable would keep them for the whole run: on a 30-minute flight the detections are
    ~130,000 objects)."""

    detections: DetectionResult | None = None
    localized: LocalizeResult | None = None

    def take(self) -> tuple[DetectionResult | None, LocalizeResult | None]:
        out = self.detections, self.localized
        self.detections = self.localized = None
        return out


_REFINE_COUNTERS = ("refine_", "tracked", "frames_with_tracked", "small_module")
"""detect.CameraStats counters reported under detection_statistics' "refinement"."""


def detection_statistics(log: FlightLog, det, world) -> dict:
    """Frames with a (valid) floor code, codes per frame, rejected payloads by reason."""

    # one frame classified at a time: the whole flight's classified sightings at once were a
    # ~80 MiB transient on a 30-minute flight, whose freed heap the later stages stacked on
    # (BENCHMARKS.md, mem14); the counts (and the reasons' order) are the same
    rejected: Counter = Counter()
    n_valid: list[int] = []
    # each camera's sightings of the other's codes: both at once say the cameras are swapped
    floor_with_load, front_with_floor = 0, 0
    for d in det.by_frame("cam0").values():
        c = classify(d, world)
        if c.floor:
            n_valid.append(len(c.floor))
        floor_with_load += any(reason == LOAD_CODE_ON_FLOOR for _, reason in c.rejected)
        rejected.update(rejection_counts([c]))
    front_with_load, load_sightings = 0, 0
    for d in (det.by_frame("cam1") if log.front is not None else {}).values():
        c = classify(d, world)
        front_with_load += bool(c.loads)
        front_with_floor += any(reason == FLOOR_CODE_ON_FRONT for _, reason in c.rejected)
        load_sightings += len(c.loads)
        rejected.update(rejection_counts([c]))
    return {
        "backend": det.backend,
        "from_cache": bool(det.from_cache),
        "cache": getattr(det, "cache_status", "none"),
        "floor_frames": len(log.floor),
        "floor_frames_with_code": len(n_valid),
        "floor_frames_with_code_fraction": len(n_valid) / max(1, len(log.floor)),
        "floor_codes_per_frame_with_code": float(np.mean(n_valid)) if n_valid else 0.0,
        "front_frames": len(log.front) if log.front is not None else 0,
        "front_frames_with_load_code": front_with_load,
        "floor_frames_with_load_code": floor_with_load,
        "front_frames_with_floor_code": front_with_floor,
        "load_sightings": load_sightings,
        "frames_skipped": len(det.skipped),
        "skipped_messages": det.skipped[:20],
        "rejected_total": int(sum(rejected.values())),
        "rejected_by_reason": dict(rejected),
        # per camera: codes whose refinement failed its self-check (kept the decoder's corners,
        # by reason) and codes tracked through frames where they did not decode (fusion.qr.track)
        "refinement": {
            name: {k: int(v) for k, v in vars(st).items() if k.startswith(_REFINE_COUNTERS)}
            for name, st in sorted(det.stats.items())
        },
    }


def localize_stage(log: FlightLog, det, cfg: RunConfig) -> LocalizeResult:
    """The two per-frame estimators on every floor frame, and load observations from cam1.

    Frames are independent, so both phases (floor poses, then load codes placed with those
    poses) run on `cfg.workers` processes over contiguous chunks of the flight.  The phases'
    chunk functions and their merges are public so a task graph (fusion.fleet) can run them."""
    floor_frames = det.by_frame("cam0")
    workers = _worker_count(cfg.workers, len(floor_frames))
    parts = list(
        parallel_map(
            *_localize_tasks(localize_floor_chunk, _chunks(floor_frames, workers), workers),
            workers,
            floor_context(log, cfg),
            preload=_LOCALIZE_PRELOAD,
        )
    )
    floor = merge_floor_parts(parts, cfg)
    if log.front is None:
        return merge_front_parts(log, floor, [])
    parts = list(
        parallel_map(
            *_localize_tasks(localize_front_chunk, _chunks(det.by_frame("cam1"), workers), workers),
            workers,
            front_context(log, floor, cfg),
            preload=_LOCALIZE_PRELOAD,
        )
    )
    return merge_front_parts(log, floor, parts)


def _localize_tasks(chunk_fn: Callable, chunks: list[dict], workers: int) -> tuple[Callable, list]:
    """(function, tasks) for parallel_map: on several workers the chunks' detections travel
    packed (fusion.qr.detect.pack_frames: ~1/30 of the pickling CPU of the objects)."""
    if workers <= 1 or len(chunks) <= 1:
        return chunk_fn, chunks
    packed_fn = _localize_floor_packed if chunk_fn is localize_floor_chunk else _localize_front_packed
    return packed_fn, [pack_frames(c) for c in chunks]


def _localize_floor_packed(context, packed) -> dict:
    return localize_floor_chunk(context, unpack_frames(packed))


def _localize_front_packed(context, packed) -> dict:
    return localize_front_chunk(context, unpack_frames(packed))


def floor_context(log: FlightLog, cfg: RunConfig) -> tuple:
    """What every `localize_floor_chunk` needs: (floor camera, world, cfg, floor layout)."""
    return (log.floor.camera, log.world, cfg, floor_layout(log, cfg))


def floor_layout(log: FlightLog, cfg: RunConfig) -> FloorLayout | None:
    """`fusion run --map`'s floor codes for PnP (world.FloorLayout: the map's pose and covariance
    of each code it holds, world.yaml's placement sigma for the others); None without --map or
    when world.yaml says the codes are laid exactly (the as-built codes' rule: the map unused)."""
    placement = Placement.from_world(log.world)
    if cfg.floor_map is None or not placement.enabled:
        return None
    prior = floorcodes.read_floor_map(cfg.floor_map, _world_yaml(log))
    return FloorLayout(placement, dict(prior.codes))


def front_context(log: FlightLog, floor: LocalizeResult, cfg: RunConfig) -> tuple:
    """What every `localize_front_chunk` needs: (front camera, world, paper and PnP trajectories,
    cfg); `floor` is `merge_floor_parts`' result."""
    assert log.front is not None
    return (log.front.camera, log.world, floor.trajectories.get("paper"), floor.trajectories["pnp"], cfg)


def merge_floor_parts(parts: list[dict], cfg: RunConfig) -> LocalizeResult:
    """The raw trajectories and PnP statistics of a flight from its `localize_floor_chunk`
    results, in time order (no load observations yet)."""
    notes: list[str] = []
    trajectories: dict[str, Trajectory] = {}
    paper_errors = [p["paper_error"] for p in parts if p["paper_error"]]
    if paper_errors:
        notes.append(f"paper estimator not run: {paper_errors[0]}")
    else:
        trajectories["paper"] = Trajectory.concatenate([p["paper"] for p in parts], "paper")
    traj_pnp = Trajectory.concatenate([p["pnp"] for p in parts], "pnp")
    stats = {"pnp": _merge_pnp_stats([p["pnp_stats"] for p in parts])}
    # honest sigma (issue 10): the flight's reprojection chi2/dof, per corner class, scales the
    # PnP covariances
    traj_pnp, stats["pnp"]["noise_scale"] = variance.scale_pnp_trajectory_by_class(
        traj_pnp, [p["pnp_stats"] for p in parts], cfg.estimate_noise_scale
    )
    # a corner class with too few degrees of freedom for its own factor whose residuals are
    # nonetheless far beyond its model (variance.thin_class_warnings): said in the summary
    notes += stats["pnp"]["noise_scale"].get("thin_class_warnings", [])
    # a corner bias common to the flight (issue 10.3): removed when significant, but not with
    # the floor codes' placement uncertain: a common dilation then trades with the codes'
    # spacing, and its estimate is off by several of its sigma (exact codes, 0.15 px noise:
    # +0.03-0.05 px against sigma 0.015; BENCHMARKS.md, eighteenth session)
    placement = next((p["pnp_stats"].placement for p in parts if p["pnp_stats"].placement is not None), None)
    traj_pnp, bias_report, consider = cornerbias.correct_pnp_trajectory(
        traj_pnp,
        [b for p in parts for b in p["pnp_stats"].frame_bias],
        float(stats["pnp"]["noise_scale"].get("scale", math.nan)),
        cfg.estimate_noise_scale and cfg.correct_corner_bias and placement is None,
    )
    if placement is not None and bias_report is not None and cfg.correct_corner_bias:
        notes.append(
            "floor-corner bias not removed: with the floor codes' placement uncertain (world.yaml's "
            "placement sigma, or --map's), a common corner dilation cannot be told from the codes' spacing"
        )
    if bias_report is not None:
        stats["pnp"]["corner_bias"] = bias_report
    # corner errors correlated in time (issue 10.3): the back ends' inputs count them as fewer
    # independent frames; the PnP trajectory keeps its per-frame covariances
    stats["pnp"]["correlation"], inflation = correlation.estimate_inflation(
        traj_pnp,
        [r for p in parts for r in p["pnp_stats"].frame_code_residuals],
        [g for p in parts for g in p["pnp_stats"].frame_class_covariance],
        variance.applied_class_scales(stats["pnp"]["noise_scale"]),
        cfg.estimate_noise_scale and cfg.inflate_correlated,
        # a removed corner bias (refined corners only, the bias model's class: fusion.qr.pnp.bias)
        # is in these residuals, correlated over every frame, and its consider term already
        # carries it: its share is taken off the correlation, the rest of the refined corners'
        # correlated error inflated (it was 1-5 % of their residuals on the sweep14 flights,
        # whose refined residuals kept rho ~0.1 to lag 19: BENCHMARKS.md, corr15)
        common_sum_sq={"refined": consider.residual_sum_sq} if consider is not None else None,
        # floor codes laid off their payloads (world.yaml's placement sigma): every frame seeing
        # the same code carries the same error
        placement_covariances=[g for p in parts for g in p["pnp_stats"].frame_placement_covariance],
    )
    trajectories["pnp"] = traj_pnp
    free_tilt = [c for p in parts for c in p["pnp_stats"].frame_free_tilt_covariance]
    sigmas = next((p["intrinsics_sigmas"] for p in parts if "intrinsics_sigmas" in p), None)
    return LocalizeResult(
        trajectories,
        {},
        {},
        stats,
        notes,
        bias_consider=consider,
        correlation=inflation,
        free_tilt_covariances=np.array(free_tilt).reshape(-1, 2, 2) if free_tilt else None,
        intrinsics_consider=None
        if sigmas is None
        else cornerbias.intrinsics_consider(
            traj_pnp, [b for p in parts for b in p["pnp_stats"].frame_bias], sigmas
        ),
    )


def merge_front_parts(log: FlightLog, floor: LocalizeResult, parts: list[dict]) -> LocalizeResult:
    """`floor` (merge_floor_parts) completed with the load observations and maps of the
    `localize_front_chunk` results, in time order."""
    notes = list(floor.notes)
    trajectories = dict(floor.trajectories)
    obs: dict[str, list[LoadObservation]] = {}
    maps: dict[str, LoadMap] = {}
    if log.front is None:
        # named by its stream (a bag's topic, a video's cam1 file, an EuRoC folder's mav0/cam1)
        notes.append("no front camera (stream cam1) in this log: no load map")
        return LocalizeResult(
            trajectories,
            obs,
            maps,
            floor.stats,
            notes,
            bias_consider=floor.bias_consider,
            correlation=floor.correlation,
            free_tilt_covariances=floor.free_tilt_covariances,
            intrinsics_consider=floor.intrinsics_consider,
        )
    if "paper" in trajectories:
        errors = [p["paper_error"] for p in parts if p["paper_error"]]
        if errors:
            notes.append(f"paper load mapping not run: {errors[0]}")
        else:
            obs["paper"] = [o for p in parts for o in p["paper"]]
            maps["paper"] = paper.aggregate_loads(obs["paper"], name="paper")
    obs["pnp"] = [o for p in parts for o in p["pnp"]]
    maps["pnp"] = pnp.aggregate_load_observations(obs["pnp"], name="pnp")
    # The landmark factors of the fusion back end need only the camera-frame measurement, so
    # they also take the sightings at frames without a raw pose (e.g. floor blackouts).
    camera_frame = obs["pnp"] + [o for p in parts for o in p["unposed"]]
    return LocalizeResult(
        trajectories,
        obs,
        maps,
        floor.stats,
        notes,
        camera_frame,
        floor.bias_consider,
        floor.correlation,
        floor.free_tilt_covariances,
        floor.intrinsics_consider,
    )


_LOCALIZE_PRELOAD = ("fusion.pipeline",)


def localize_floor_chunk(context, frames: dict) -> dict:
    """Paper and PnP poses of the floor frames {timestamp_ns: detections} of one chunk."""

    camera, world, cfg, layout = context
    out: dict[str, Any] = {"paper": None, "paper_error": None}
    # each frame classified once for both estimators (classify is ~1/8 of this stage's CPU; PnP
    # held every frame's FrameCodes to the end of the chunk before, for its rejection counts)
    codes = {t: classify(ds, world) for t, ds in frames.items()}
    # the paper's Algorithms read decoded codes only; tracked ones (fusion.qr.track) go to PnP
    decoded, decoded_codes = frames, codes  # every code decoded (no track pass): the same frames
    if any(d.tracked for ds in frames.values() for d in ds):
        decoded = {t: kept for t, ds in frames.items() if (kept := [d for d in ds if not d.tracked])}
        # a frame with a tracked code is classified again without it (its duplicates may differ)
        decoded_codes = {t: codes[t] for t, kept in decoded.items() if len(kept) == len(frames[t])}
    try:
        out["paper"] = paper.paper_trajectory(decoded, camera, world, cfg.th_px, codes=decoded_codes)
    except EstimationError as e:
        out["paper_error"] = str(e)
    del decoded, decoded_codes
    out["pnp"], out["pnp_stats"] = pnp.pnp_trajectory(
        frames, camera, world, cfg.corner_sigma_px, layout=layout, frame_codes=codes
    )
    out["intrinsics_sigmas"] = camera.intrinsics_sigmas
    return out


def localize_front_chunk(context, frames: dict) -> dict:
    """Paper and PnP load observations of the front frames {timestamp_ns: detections} of one
    chunk, placed with the raw trajectories."""

    camera, world, traj_paper, traj_pnp, cfg = context
    out: dict[str, Any] = {"paper": [], "paper_error": None}
    # each frame classified once for the three users below, which read only its load codes: the
    # frames that have any keep them (lists PnP's batch held for its posed frames before)
    loads = {t: c.loads for t, ds in frames.items() if (c := classify(ds, world)).loads}
    if traj_paper is not None:
        try:
            out["paper"] = paper.paper_load_observations(
                frames, camera, world, traj_paper, cfg.th_px, loads=loads
            )
        except EstimationError as e:
            out["paper_error"] = str(e)
    out["pnp"] = pnp.pnp_load_observations(
        frames, camera, world, traj_pnp, cfg.corner_sigma_px, frame_loads=loads
    )
    out["unposed"] = _unposed_load_observations(
        frames, {o.timestamp_ns for o in out["pnp"]}, camera, world, cfg.corner_sigma_px, loads
    )
    return out


MIN_FRAMES_PER_WORKER = 200
"""Below about this many frames a chunk, starting processes costs more than it saves."""


def _worker_count(requested: int | None, n_items: int) -> int:
    """`requested` processes as given; by default one per core, capped so that each has at least
    MIN_FRAMES_PER_WORKER frames."""
    if requested is not None:
        return max(1, min(int(requested), n_items))
    return max(1, min(worker_count(None), n_items // MIN_FRAMES_PER_WORKER))


def _chunks(frames: dict, n: int) -> list[dict]:
    """Split {timestamp: value} into n contiguous (time-ordered) dicts."""
    keys = sorted(frames)
    if not keys:
        return [{}]
    return [{k: frames[k] for k in keys[a:b]} for a, b in chunk_bounds(len(keys), n)]


def _merge_pnp_stats(parts: list) -> dict:
    """Sum the per-chunk PnPStats (counts and per-key counts; the mean RMS weighted by poses)."""
    from collections import Counter

    out: dict = {}
    for key in (
        "n_frames",
        "n_posed",
        "n_without_floor_code",
        "n_unsolved",
        "n_ambiguous",
        "n_codes_dropped",
    ):
        out[key] = int(sum(getattr(p, key) for p in parts))
    for key in ("codes_per_pose", "rejections"):
        c: Counter = Counter()
        for p in parts:
            c.update(getattr(p, key))
        out[key] = dict(sorted(c.items()))
    rms = [(p.mean_reprojection_rms_px, p.n_posed) for p in parts if p.n_posed]
    out["mean_reprojection_rms_px"] = (
        float(sum(r * n for r, n in rms) / sum(n for _, n in rms)) if rms else float("nan")
    )
    return out


def _unposed_load_observations(
    front_frames, posed_ns: set[int], camera, world, sigma_px, frame_loads: dict | None = None
) -> list[LoadObservation]:
    """Camera-frame load observations (p_cam, cov_cam) of the front frames not in `posed_ns`;
    their p_world is meaningless (identity drone pose) and must not be used.  frame_loads:
    {timestamp_ns: classify(front_frames[ts], world).loads} of every frame with a load code,
    when the caller has them (a frame not in it has none)."""

    batch: list[LoadFrame] = []
    for ts in sorted(set(front_frames) - posed_ns):
        loads = (
            frame_loads.get(ts, []) if frame_loads is not None else classify(front_frames[ts], world).loads
        )
        if loads:
            batch.append(LoadFrame(loads, np.eye(4), None))
    if not batch:
        return []
    per_frame = estimate_load_observations_frames(batch, camera, world, sigma_px)
    return [o for frame in per_frame for o in frame]


@dataclass
class EstimatorFailure:
    """A fused estimator that produced no result, and why (summary, metrics.json)."""

    estimator: Estimator
    reason: str  # one line
    error_type: str  # the exception's class name


@dataclass
class FuseStageResult:
    """The fused back ends' results, those that failed, and notes for the summary."""

    results: dict[Estimator, FusionResult] = field(default_factory=dict)
    failures: dict[Estimator, EstimatorFailure] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    warnings: list[LogWarning] = field(default_factory=list)  # the run's named warnings
    as_built: AsBuiltInput | None = None  # the smoother's as-built floor-code input
    raw: Trajectory | None = None  # the raw poses the back ends fused (PnP, with any fixes)


@dataclass
class FloorInputs:
    """What the fusion and the evaluation take from a flight's detections (floor_inputs), so
    that the detections themselves (objects per sighting, growing with the flight) can be let go
    before the fusion: its peak on a 30-minute flight 997 -> 884 MiB (BENCHMARKS.md)."""

    as_built: AsBuiltInput | None  # the smoother's as-built floor-code input (floorcodes.as_built_input)
    as_built_notes: list[str]  # as_built_input's notes
    tight_frames: dict  # {timestamp_ns: [FloorSighting]} for the corner factors: empty unless cfg.tight
    codes_xy: np.ndarray | None  # world (x, y) of the floor codes decoded (_floor_codes_seen)


class ClassifiedOnRead(Mapping):
    """{timestamp_ns: [FloorSighting]} of a camera's detections {timestamp_ns: [QRDetection]},
    each frame classified when it is read: the as-built input reads every frame once, and the
    whole flight's sightings held at once were 18 MB on the 10-minute flight (/proc RSS)."""

    def __init__(self, frames: dict[int, list], world: World) -> None:
        self._frames, self._world = frames, world

    def __getitem__(self, t: int) -> list:
        return classify(self._frames[t], self._world).floor

    def __iter__(self) -> Iterator[int]:
        return iter(self._frames)

    def __len__(self) -> int:
        return len(self._frames)


def floor_inputs(log: FlightLog, det: DetectionResult, cfg: RunConfig) -> FloorInputs:
    """FloorInputs of the detections `det` of `log` (final stamps and mount: take them just
    before the fusion).  Each frame's floor sightings are classified only when a graph uses
    them (tight corner factors, as-built floor codes): ~1 s of Python on a 10-minute flight."""
    if "cam0" not in log.cameras:
        return FloorInputs(None, [], {}, None)
    tight_frames: dict[int, list] = {}
    sightings: Mapping[int, list] = tight_frames
    if cfg.tight:
        sightings = tight_frames = {t: classify(d, log.world).floor for t, d in det.by_frame("cam0").items()}
    elif Placement.from_world(log.world).enabled:
        # the as-built input reads each frame once
        sightings = ClassifiedOnRead(det.by_frame("cam0"), log.world)
    as_built, notes = floorcodes.as_built_input(
        log.world,
        _world_yaml(log),
        sightings,
        log.floor.camera,
        cfg.corner_sigma_px,
        cfg.tight,
        cfg.floor_map,
    )
    return FloorInputs(as_built, notes, tight_frames, _floor_codes_seen(det, log))


def fuse_stage(
    log: FlightLog,
    loc: LocalizeResult,
    cfg: RunConfig,
    det: DetectionResult | FloorInputs | None = None,
    fixes: PositionFixes | None = None,
    shared: SharedWholeFlight | None = None,
) -> FuseStageResult:
    """Smoother, incremental smoother and EKF on the PnP poses (and the external `fixes`:
    estimate.fixes.merge_fixes; a log without cameras is fused from the IMU and the fixes).

    Each back end runs on its own: one that raises is recorded in `failures` with its reason
    and the others still run.  The smoothers take both cameras' CameraModels (mount-aware);
    with `cfg.tight` they use each floor code's corners as reprojection factors (the floor
    sightings of `det`) instead of the per-frame PnP pose; the EKF stays loosely coupled.
    `det`: the detections, or what the fusion takes of them (floor_inputs; the run passes
    these, having let the detections go).  `shared`: the run's whole-flight solve
    (SharedWholeFlight), whose states warm-start the batch smoother when they belong to the
    same frames."""
    out = FuseStageResult()
    raw = loc.trajectories.get(str(Estimator.PNP), Trajectory.empty(str(Estimator.PNP)))
    # time-correlated corner errors: the PnP poses are worth fewer independent frames
    # (correlation.py): each back end solved on them once, then again with their covariances
    # inflated for the average that solve took of the frames (solve_inflated)
    inflation = getattr(loc, "correlation", None)  # stand-ins of a LocalizeResult may lack it
    merged = None
    if fixes is not None:
        camera_t = log.floor.timestamps_ns if "cam0" in log.cameras else None
        merged = merge_fixes(camera_t, raw, fixes, log.imu)
        raw = merged.raw
        out.notes.append(merged.note())
        heading = heading_warning(merged.alignment) if merged.alignment else None
        if heading is not None:  # camera-less: an attitude aligned from barely any sideways motion
            out.warnings.append(heading)
    out.raw = raw
    if len(raw) == 0:
        out.notes.append("no floor code was read in this flight: nothing to fuse (no fused estimate)")
        return out
    if log.imu is None and log.velocity is None:
        out.notes.append("the log has neither IMU nor velocity: raw per-frame estimates only")
        return out
    if log.imu is None:
        out.notes.append("no IMU in this log: fused with velocity only (velocity-only mode)")
    kernel = _robust_kernel(cfg)
    fcfg = FusionConfig(
        robust_kernel=kernel,
        tight=cfg.tight,
        noise_scale_iterations=FusionConfig.noise_scale_iterations if cfg.estimate_noise_scale else 0,
        # the smoother's residuals understate time-correlated errors: never scale them down
        pose_scale_floor=1.0 if inflation is not None else 0.0,
    )
    # only a log read for external fixes may lack the floor camera (LogOptions.cameras_optional)
    has_floor = fixes is None or "cam0" in log.cameras
    frame_t = merged.frame_t if merged is not None else log.floor.timestamps_ns
    floor_camera = log.floor.camera if has_floor else None
    graph_kwargs: dict[str, Any] = {"floor_camera": floor_camera}
    floor = None
    if det is not None and has_floor:
        floor = det if isinstance(det, FloorInputs) else floor_inputs(log, det, cfg)
    if cfg.tight and det is not None:
        graph_kwargs["floor_frames"] = floor.tight_frames if floor is not None else {}
        out.notes.append(
            "tight coupling: floor-code corners as reprojection factors in the "
            "smoothers (the EKF stays loosely coupled)"
        )
    if floor_camera is not None and floor_camera.gimbaled and log.imu is not None:
        out.notes.append(GIMBALED_TILT_NOTE)
    load_obs = loc.camera_frame_observations if log.front is not None else []
    front = log.front.camera if log.front is not None else None
    smoother_kwargs = dict(graph_kwargs)
    if floor is not None:
        out.notes += floor.as_built_notes
        if floor.as_built is not None:
            smoother_kwargs["as_built"] = floor.as_built
            out.as_built = floor.as_built
    if shared is not None:
        smoother_kwargs["warm_start"] = shared.warm_start(frame_t)
        # the batch smoother is their only user: let the whole flight's states go with it
        shared.states = None
    smoother_kwargs["window"] = _window_config(cfg, as_built="as_built" in smoother_kwargs)
    smoother_kwargs["solver"] = smooth
    workers = backend_workers(cfg, len(frame_t))
    smoother_kwargs["workers"] = workers
    solvers: list[tuple[Estimator, Callable[..., FusionResult], dict[str, Any]]] = [
        (Estimator.SMOOTHER, smooth_windowed, smoother_kwargs)
    ]
    if cfg.incremental:
        solvers.append((Estimator.INCREMENTAL, smooth_incremental, graph_kwargs))
    solvers.append((Estimator.EKF, run_ekf, {"floor_camera": floor_camera}))
    # the back ends after the smoother take its noise scales and nothing from each other: they
    # run at once on `workers` processes (fusion.parallel.call_each), each outcome then taken
    # here in order, as if run here
    at_once: dict[Estimator, Outcome] = {}
    imu = log.imu  # with the noise scale the smoother estimates for it, if any, after the smoother
    for i, (name, fn, kwargs) in enumerate(solvers):
        if name != Estimator.SMOOTHER and not at_once:
            calls: list[tuple[Callable[..., Any], tuple, dict[str, Any]]] = []
            # the tight incremental smoother takes corners, not poses
            inflated = [n_ for n_, _, _ in solvers[i:] if not (cfg.tight and n_ == Estimator.INCREMENTAL)]
            causal = None
            if inflation is not None and len(inflated) > 1:
                # one causal pass (the EKF's) inflates the poses for both (correlation.causal_inflated)
                try:
                    # without the sightings: the EKF maps loads after filtering, from its poses,
                    # so they change nothing the inflation takes (its pose covariances)
                    causal = correlation.causal_inflated(
                        run_ekf,
                        frame_t,
                        imu,
                        raw,
                        None,
                        inflation=inflation,
                        front_camera=front,
                        velocity=log.velocity,
                        config=fcfg,
                        floor_camera=floor_camera,
                    )
                except Exception as e:  # each back end then takes its own first pass
                    logger.info(
                        "the EKF's pass on the raw poses failed (%s): each back end inflates its own", e
                    )
            for n_, f, kw in solvers[i:]:
                common = dict(front_camera=front, velocity=log.velocity, config=fcfg, **kw)
                if inflation is None or n_ not in inflated:
                    calls.append((f, (frame_t, imu, raw, load_obs), common))
                elif causal is not None:
                    calls.append(
                        (correlation.solve_on_inflated, (f, frame_t, imu, raw, causal, load_obs), common)
                    )
                else:
                    calls.append(
                        (
                            correlation.solve_inflated,
                            (f, frame_t, imu, raw, load_obs),
                            dict(common, inflation=inflation, two_sided=False),
                        )
                    )
            at_once = dict(zip((n for n, _, _ in solvers[i:]), call_each(calls, workers)))
        try:
            if name in at_once:
                res = at_once.pop(name).get()
            else:
                common = dict(front_camera=front, velocity=log.velocity, config=fcfg, **kwargs)
                if inflation is not None and not cfg.tight:  # the tight smoother takes corners
                    # each window solved twice in its own process, the second solve warm
                    common["solver"] = correlation.InflatedSmoother(inflation)
                res = fn(frame_t, imu, raw, load_obs, **common)
        except FusionError as e:
            out.failures[name] = EstimatorFailure(name, str(e), type(e).__name__)
            continue
        except Exception as e:  # a bug in one back end must not cost the others
            logger.exception("%s failed", name)
            out.failures[name] = EstimatorFailure(
                name, f"internal error: {type(e).__name__}: {first_line(e)}", type(e).__name__
            )
            continue
        finally:
            kwargs.pop("warm_start", None)  # the smoother's start: not needed after it
        res.trajectory.name = str(name)
        res.loads.name = str(name)
        if loc.bias_consider is not None and not cfg.tight:
            # the removed corner bias's uncertainty, common to every frame: no back end can
            # average it down (cornerbias.py)
            res.trajectory = loc.bias_consider.add_to(res.trajectory)
        out.results[name] = res
        if name == Estimator.SMOOTHER and cfg.estimate_noise_scale:
            # the smoother's noise scales, estimated on the whole flight, for the other back ends
            report = res.stats.get("noise_scales")
            raw, load_obs, corner_scale = variance.apply_smoother_scales(report, raw, load_obs)
            imu, fcfg = variance.apply_smoother_sensor_scales(report, imu, fcfg)
            if inflation is not None:  # its terms are shares of raw's covariance: scaled alike
                inflation = replace(inflation, class_terms=inflation.class_terms * corner_scale)
        for reason in res.health.reasons:
            out.notes.append(f"{name}: {reason}")
    for name, failure in out.failures.items():
        logger.warning("%s failed: %s", name, failure.reason)
    return out


BACKEND_MIN_FRAMES = 600
"""Fused frames below which the back ends and the report's figures stay in this process
(`backend_workers`): a guess (the crossover was not measured; a worker's start costs ~5 CPU ms
plus its inputs' unpickling, BENCHMARKS.md, seventh session); it keeps the tests' short flights in one
process."""


def backend_workers(cfg: RunConfig, n_frames: int) -> int:
    """Processes for the fusion back ends, the windowed solves and the report's figures:
    `cfg.workers` (None: one per core), 1 for a flight under BACKEND_MIN_FRAMES frames."""
    return worker_count(cfg.workers) if n_frames >= BACKEND_MIN_FRAMES else 1


def _world_yaml(log: FlightLog) -> dict:
    """The flight's world.yaml as written (what run.json records and map merge compares)."""
    path = Path(log.root) / WORLD_YAML
    return load_yaml(path, FusionError) if path.is_file() else log.world.to_yaml()


def write_load_observations_csv(path: Path, observations: list[LoadObservation]) -> None:
    """Raw per-frame load observations: `timestamp_ns,id,x_m,y_m,z_m,sigma_x_m,sigma_y_m,sigma_z_m`."""

    with atomic_open(path) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["timestamp_ns", "id", "x_m", "y_m", "z_m", "sigma_x_m", "sigma_y_m", "sigma_z_m"])
        for o in observations:
            sig = np.sqrt(np.diag(o.cov_world)) if o.cov_world is not None else None
            w.writerow(
                [
                    int(o.timestamp_ns),
                    csv_safe(o.load_id),
                    *(f"{v:.6f}" for v in o.p_world),
                    *(("", "", "") if sig is None else (f"{s:.6f}" for s in sig)),
                ]
            )


def run(
    log_dir: Path | FlightLog,
    out_dir: Path,
    cfg: RunConfig | None = None,
    until: str = "run",
    *,
    computed: Computed | None = None,
) -> RunResult:
    """Run the pipeline on a logged flight up to stage `until` (detect, localize, smooth, run).

    `computed`: the detect and localize stages' results when they were computed elsewhere
    (fusion.fleet runs them as tasks on a cluster), taken out of it; the outputs are the same files.
    The output folder is locked for the run; `manifest.json` lists what it wrote; on any failure
    the run's partial outputs are removed (a file-system error becomes one OutputError)."""
    cfg = cfg or RunConfig()
    if until not in STAGES:
        raise FusionError(f"unknown stage {until!r}; expected one of {STAGES}")
    timings: dict[str, float] = {}
    t = time.perf_counter()
    if worker_count(cfg.workers) > 1:
        start_workers_early()  # the workers' imports while the log is read (fusion.parallel)
    log = (
        log_dir
        if isinstance(log_dir, FlightLog)
        else read_flight(log_dir, LogOptions(cameras_optional=cfg.fixes is not None))
    )
    with prepare_out_dir(out_dir, cfg.force, log.root) as out:
        result = _run_into(log, out.path, cfg, until, timings, t, computed)
    return result


def _run_into(
    log: FlightLog,
    out_dir: Path,
    cfg: RunConfig,
    until: str,
    timings: dict,
    t: float,
    computed: Computed | None = None,
) -> RunResult:
    """`run`'s stages, writing into the prepared (locked) output folder."""
    detections, localized = computed.take() if computed is not None else (None, None)

    result = RunResult(out_dir, log_summary(log), warnings=list(log.warnings))
    check_stated_offsets(log, cfg.time_offsets_s)  # before any work: they are only applied later
    fixes = fixes_in_flight(read_fixes(cfg.fixes), log) if cfg.fixes is not None else None
    if fixes is not None:
        result.warnings += fixes.warnings
    timings["read_s"] = time.perf_counter() - t
    if "cam0" not in log.cameras:
        return _run_without_cameras(log, out_dir, cfg, until, timings, result, fixes)

    t = time.perf_counter()
    if detections is None:
        det = _tracked_cache(log, out_dir / CACHE_NAME, cfg) or detect_flight(
            log,
            cache_path=out_dir / CACHE_NAME,
            backend=cfg.backend,
            workers=cfg.workers,
            progress=cfg.progress,
        )
    else:
        det = detections
        write_cache(det, out_dir / CACHE_NAME, flight_fingerprint(log, det.backend))
    _require_readable_floor(log, det)
    for warning in (unreadable_front_warning(det), repeated_frames_warning(det)):
        if warning is not None:
            result.warnings.append(warning)
    result.detection_stats = detection_statistics(log, det, log.world)
    timings["detect_s"] = time.perf_counter() - t
    if det.skipped:
        result.notes.append(
            f"{len(det.skipped)} frame(s) skipped (missing or unreadable image); first: {det.skipped[0]}"
        )
    if det.from_cache:
        result.notes.append(f"detections reused from {out_dir / 'detections.csv'} (log and images unchanged)")
    if until == "detect":
        result.timings_s = timings
        return result

    t = time.perf_counter()
    detected = det
    det = _rolling_shutter(log, det, cfg, result)
    timings["rolling_shutter_s"] = time.perf_counter() - t

    t = time.perf_counter()
    _progress(cfg, "per-frame estimators (paper, pnp)")
    rs_active = cfg.calibrate_readout or any(s.camera.rolling_shutter for s in log.cameras.values())
    if localized is not None and not rs_active:
        loc, localized = localized, None
    else:
        # a rolling-shutter flight's corners were just moved to their stamps: a localisation
        # computed from the uncorrected detections (fusion batch's chunks) cannot be used
        loc = localize_stage(log, det, cfg)
    if not rs_active:
        undeclared = undeclared_rolling_shutter_warning(log, det, loc, cfg)
        if undeclared is not None:
            result.warnings.append(undeclared)
    wide = placement_too_wide_warning(log.world, floor_layout(log, cfg))
    if wide is not None:
        result.warnings.append(wide)
    timings["localize_s"] = time.perf_counter() - t
    t = time.perf_counter()
    det, loc = track_stage(log, detected, det, loc, cfg, result)
    timings["track_s"] = time.perf_counter() - t
    t = time.perf_counter()
    # the mount check runs on the final stamps; a calibration runs first, so that the time
    # offsets (the front camera's profile hangs the camera from the fused body) see the right mount
    mount_check = until in ("smooth", "run")
    if mount_check and cfg.calibrate_extrinsics:
        log, loc = _apply_extrinsics(log, det, loc, cfg, result)
    # the check alone shares its whole-flight solve with the front camera's time-offset profile
    shared = None
    if mount_check and not cfg.calibrate_extrinsics:
        shared = SharedWholeFlight(window=_window_config(cfg), workers=backend_workers(cfg, len(log.floor)))
    log, det, loc = _apply_time_offsets(log, det, loc, cfg, result, shared)
    if mount_check and not cfg.calibrate_extrinsics:
        log, loc = _apply_extrinsics(log, det, loc, cfg, result, None if shared is None else shared.mount)
    if mount_check:
        log, loc = _apply_front_extrinsics(log, det, loc, cfg, result)
    if result.rolling_shutter is not None:
        add_readout_covariances(loc, result.rolling_shutter, result.time_offsets)
        rs_sightings = rolling_shutter_sightings_warning(result.rolling_shutter)
        if rs_sightings is not None:
            result.warnings.append(rs_sightings)
    _add_stamp_jitter(log, loc, result)
    result.notes += loc.notes
    unstated = sorted(n for n, c in log.cameras.items() if c.camera.intrinsics_sigma_px is None)
    if unstated:
        result.notes.append(
            f"{', '.join(unstated)}: no intrinsics_sigma in sensor.yaml: every pose and load assumes "
            f"the focal lengths known to {100 * DEFAULT_FOCAL_SIGMA_REL:g} % and the principal point to "
            f"{DEFAULT_PRINCIPAL_POINT_SIGMA_PX:g} px (a calibration's usual error; state yours)"
        )
    if fixes is None:
        no_pose = no_floor_pose_warning(log, loc, result.detection_stats)
        if no_pose is not None:
            result.warnings.append(no_pose)
    too_large = corner_bias_too_large_warning(loc)
    if too_large is not None:
        result.warnings.append(too_large)
    result.trajectories.update(loc.trajectories)
    stamp_variance = _floor_stamp_variance(result)
    if str(Estimator.PNP) in result.trajectories:
        # the PnP poses as written: with the floor stamps' error and the mount's (loc's, the
        # back ends' input, without them: common errors no back end may average down;
        # timeoffset.py, mountconsider.py)
        result.trajectories[str(Estimator.PNP)] = add_mount_consider(
            add_stamp_covariance(result.trajectories[str(Estimator.PNP)], stamp_variance),
            _floor_mount_covariance(log, result),
        )
    result.load_maps.update(loc.load_maps)
    places = loads_at_two_places(loc.load_observations.get(str(Estimator.PNP), []))
    if places:
        result.warnings.append(loads_at_two_places_warning(places))
    for name, obs in loc.load_observations.items():
        if name in RAW_ESTIMATORS:
            write_load_observations_csv(out_dir / f"load_observations_{name}.csv", obs)
    timings["localize_s"] += time.perf_counter() - t

    fused_stats: dict = {}
    floor_xy = None
    if until in ("smooth", "run"):
        result.fusion_expected = True
        t = time.perf_counter()
        _progress(cfg, "fusion (smoother, incremental, ekf)")
        # what the fusion and the evaluation need of the detections, taken now so that they
        # (objects per sighting, growing with the flight) are let go before the fusion's peak
        floor = floor_inputs(log, det, cfg)
        floor_xy = floor.codes_xy
        del det, detected, detections, localized
        fused_stats = _fuse_into_result(log, loc, cfg, floor, fixes, result, shared)
        del floor
        unsynced = _unsynchronised_load_sightings(log, loc)
        if unsynced is not None:
            result.warnings.append(unsynced)
        timings["fuse_s"] = time.perf_counter() - t
    pnp_out = result.trajectories.get(str(Estimator.PNP))
    if loc.intrinsics_consider is not None and pnp_out is not None:
        # the PnP poses as written, with the floor camera's intrinsics error
        # (cornerbias.intrinsics_consider); now, not with the stamps' above: in place, once no
        # back end reads these covariances (a copy kept beside the back ends' input had raised
        # fusion batch's report worker on the 30-minute flight 949 -> 965 MiB)
        result.trajectories[str(Estimator.PNP)] = loc.intrinsics_consider.add_to(pnp_out, in_place=True)
    result.noise_scales = variance.noise_summary(loc.stats.get("pnp", {}), fused_stats)
    for misfit in misfit_warnings(result.noise_scales):
        result.warnings.append(misfit)
        if misfit.name != LOAD_MISFIT:
            # the poses rest on the misfit geometry: no fused estimate is trusted
            for health in result.health.values():
                health.degrade(misfit.message.split(":", 1)[0])
    imu_or_mount = _imu_scale_or_mount_note([result.extrinsics, result.front_extrinsics], fused_stats)
    if imu_or_mount is not None:
        result.notes.append(imu_or_mount)
    if log.front is not None:
        _add_load_consider(log, loc, result, places)

    _write_estimates(out_dir, result)
    if until == "run":
        t = time.perf_counter()
        _progress(cfg, "evaluation and report")
        # what the evaluation needs of the per-frame results, taken now so that they (objects
        # per sighting, growing with the flight) are let go before its peak
        raw_stats = loc.stats
        del loc, shared
        # the figures are drawn here, not on workers: sending them the trajectories and the
        # ground truth took a 30-minute flight's peak 909 -> 1,282 MiB for ~1.4 s on 10 minutes
        # (BENCHMARKS.md, seventh session; that code is in the history at 0246ea7)
        _evaluate_and_report(log, result, fused_stats, raw_stats, floor_xy)
        timings["report_s"] = time.perf_counter() - t
    result.timings_s = timings
    return result


def _tracked_cache(log: FlightLog, path: Path, cfg: RunConfig) -> DetectionResult | None:
    """A detection cache that the track pass completed (tracked_fingerprint), if it is this
    flight's: as it is with `cfg.track`, else without its tracked sightings (and rewritten so)."""
    if not path.is_file():
        return None
    fingerprint = flight_fingerprint(log, cfg.backend)
    det = read_cache(path, tracked_fingerprint(fingerprint))
    if det is None:
        return None
    det.backend, det.cache_status = cfg.backend, CACHE_REUSED
    if not cfg.track:
        det = without_tracked(det)
        write_cache(det, path, fingerprint)
    return det


def track_stage(
    log: FlightLog,
    detected: DetectionResult,
    det: DetectionResult,
    loc: LocalizeResult,
    cfg: RunConfig,
    result,
) -> tuple[DetectionResult, LocalizeResult]:
    """The track pass (fusion.qr.predict, issue 10 item 4) with `cfg.track`: floor codes that the
    pose predicted from the PnP poses puts in view, undecoded in a frame, tracked into it; then
    the per-frame stage again.  `detected`: the detections as detected (cached with the tracked
    ones in detections.csv), `det` as corrected (rolling shutter).  The counts go to
    `result.detection_stats` ("tracking") and a note."""
    if not cfg.track or CameraRole.FLOOR.value not in log.cameras:
        return det, loc
    if any(d.tracked for d in det.detections):
        result.notes.append("track pass: tracked sightings reused from the detection cache")
        return det, loc
    _progress(cfg, "track pass (undecoded floor codes in view of the predicted pose)")
    workers = _worker_count(cfg.workers, len(log.floor))
    tracked, rep = track_flight(
        log, det, loc.trajectories[str(Estimator.PNP)], cfg.corner_sigma_px, workers, cfg.backend
    )
    result.notes.append(rep.note())
    if tracked is not det:
        new = [d for d in tracked.detections if d.tracked]
        write_cache(
            with_tracked(detected, new, rep),
            result.out_dir / CACHE_NAME,
            tracked_fingerprint(flight_fingerprint(log, cfg.backend)),
        )
        det, loc = tracked, localize_stage(log, tracked, cfg)
    result.detection_stats = detection_statistics(log, det, log.world)
    result.detection_stats["tracking"] = rep.as_dict()
    return det, loc


def add_readout_covariances(
    loc: LocalizeResult, report: RollingShutterReport, time_offsets: TimeOffsets | None = None
) -> None:
    """`loc` (in place) with the readout correction's motion uncertainty added (`report`,
    fusion.qr.rolling_shutter.correct_flight): it moves the whole image, so it goes to the floor
    camera's PnP pose covariances and to the other cameras' camera-frame load sightings (the
    back ends' landmark measurements), keyed by stamps shifted like them when `time_offsets`
    were applied."""

    def moved(camera: str, stamps: list[int]) -> list[int]:
        """The stamps as the applied offsets moved them (the clock rate's correction included)."""
        if time_offsets is None:
            return stamps
        return time_offsets.stamps(camera, np.array(stamps, dtype=np.int64)).tolist()

    if report.pose_cov_added:
        floor = CameraRole.FLOOR.value
        pnp_key = str(Estimator.PNP)
        added = dict(zip(moved(floor, list(report.pose_cov_added)), report.pose_cov_added.values()))
        loc.trajectories[pnp_key] = add_pose_covariance(loc.trajectories[pnp_key], added)
    for camera, by_key in report.sighting_cov_added.items():
        if camera != CameraRole.FRONT.value or not by_key:
            continue  # load sightings come from the front camera only
        stamps = moved(camera, [t for t, _ in by_key])
        sightings = {(t, load_id): c for t, ((_, load_id), c) in zip(stamps, by_key.items())}
        loc.camera_frame_observations = add_sighting_covariance(loc.camera_frame_observations, sightings)


RS_SIGHTINGS_WARN_READOUT_S = 0.030
"""A front camera read out longer than this, the longest readout measured in band: its corrected
load sightings are fused with a warning (`rolling_shutter_sightings_warning`).  Realism bench
(scripts/bench_realism.py, 15 s, 10 fps), smoother NEES at 10 / 20 / 30 ms since the one-sided
readout motion fits of a floor blackout's edges were mended (BENCHMARKS.md, rs17): seed 0
5.8 / 7.6 / 6.7, 4 6.5 / 7.0 / 7.1, 6 5.7 / 6.8 / 6.8, held out 7 and 8 6.3-7.5 (band [3, 12]; the
`gate` session had set 25 ms with seed 0's 30 ms row at 12.1)."""


def rolling_shutter_sightings_warning(report: RollingShutterReport) -> LogWarning | None:
    """A named, counted warning when front-camera load sightings corrected for a readout longer
    than RS_SIGHTINGS_WARN_READOUT_S go to the fused back ends: beyond the readouts measured,
    what their covariance does not carry (at 30 ms, seed 0: moved corners 0.062 px centre RMS
    against the true stamp projection, 0.011 with the true motion) may leave the fused covariance
    optimistic."""
    front = CameraRole.FRONT.value
    readout_s = report.readout_s.get(front, 0.0)
    n = len(report.sighting_cov_added.get(front, {}))
    if readout_s <= RS_SIGHTINGS_WARN_READOUT_S or n == 0:
        return None
    return LogWarning(
        "rolling_shutter_load_sightings",
        n,
        f"{n} front-camera load sightings corrected for a {readout_s * 1e3:.0f} ms readout are fused: "
        f"above {RS_SIGHTINGS_WARN_READOUT_S * 1e3:.0f} ms the correction leaves errors their "
        "covariance does not carry, so the fused covariances may be optimistic",
    )


def rolling_shutter_unreadable_warning(report: RollingShutterReport) -> LogWarning | None:
    """A named warning (count: the frames) when images that gave detections did not read again
    at the rolling-shutter stamp refinement (RollingShutterReport.unreadable_at_stamp): their
    codes keep the corners moved to the stamp, less accurate than refined at it."""
    n = sum(report.unreadable_at_stamp.values())
    if n == 0:
        return None
    cams = ", ".join(f"{cam} {k}" for cam, k in sorted(report.unreadable_at_stamp.items()))
    return LogWarning(
        "rolling_shutter_images_unreadable",
        n,
        f"{n} image(s) that gave detections did not read again at the rolling-shutter refinement "
        f"({cams}): their codes were moved to the stamp, not refined at it (less accurate corners)",
    )


# what a back end's failed batch start costs it (batch_start_warnings)
_BATCH_START_FALLBACK = {
    Estimator.EKF: ("the EKF", "its first seconds' tilt may be inconsistent"),
    # its first states are marginalised at that tilt and keep it (smoother.level_start)
    Estimator.INCREMENTAL: ("the incremental smoother", "its tilt may stay off for the whole flight"),
}


def batch_start_warnings(fused_stats: dict) -> list[LogWarning]:
    """A named warning (count 1) per back end whose batch start from its first level fixes
    failed (ekf.level_batch_start, which the EKF and the incremental smoother share;
    stats['batch_start_failed'], the solve's error): `ekf_batch_start_failed`,
    `incremental_batch_start_failed`.  It then starts at the first fix with its tilt unsolved,
    the start that made its roll / pitch inconsistent.  It was a log line only."""
    out = []
    for estimator, (who, cost) in _BATCH_START_FALLBACK.items():
        reason = (fused_stats.get(estimator) or {}).get("batch_start_failed")
        if reason is not None:
            message = (
                f"{who}'s batch start from its first level fixes failed ({reason}): it started at "
                f"the first fix instead, its roll / pitch unsolved there, so {cost}"
            )
            out.append(LogWarning(f"{estimator}_batch_start_failed", 1, message))
    return out


MISFIT_SCALE = 10.0
"""A variance factor beyond this is geometry, not noise (misfit_warnings): on 78 correctly
configured simulated flights (the sweep's, the held-out ones, every camera effect, bags, video,
clocks, misplaced codes) PnP's corner factor was at most 3.5, the batch smoother's on the PnP
poses 1.2 and on the load sightings 2.3; the thirty-second session's audit of 61 calibration
errors found 396-25,000 for a floor code 3 % larger than world.yaml says, the payload unit 2 %
off, a principal point or distortion wrong; 32-1,390 on the loads for a load code's size 5-10 %
off, the front camera's distortion wrong, the floor camera's lever arm flipped or its T_BS
inverted; 25-250 on the poses for a camera-IMU offset fixed 30 ms wrong."""
FLOOR_CORNERS_MISFIT = "floor_corners_misfit"
FLOOR_POSES_MISFIT = "floor_poses_misfit"
LOAD_MISFIT = "load_sightings_misfit"


def misfit_warnings(noise_scales: dict) -> list[LogWarning]:
    """Named warnings (count 1) for the variance factors of `noise_scales` (metrics.json's,
    variance.noise_summary) beyond MISFIT_SCALE: PnP's on the floor corners, the batch
    smoother's on the PnP poses (cam0) and on the load sightings (cam1).  Each was applied to
    the covariances as if it were noise, and the run said nothing: a floor code 3 % larger than
    world.yaml says gave poses 4.7 cm off with every health ok (thirty-second session's audit).
    Each names the calibration that would make such a misfit."""
    cams = (noise_scales.get("smoother") or {}).get("cameras") or {}
    factors = (
        (
            FLOOR_CORNERS_MISFIT,
            (noise_scales.get("pnp") or {}).get("scale"),
            "the floor codes' corners misfit their PnP poses {:.0f}x beyond their noise (variance): "
            "the codes' geometry is not what the run assumes. Check world.yaml's floor_qr side_m and "
            "payload_unit_m (and the codes' placement), and the floor camera's intrinsics, "
            "distortion and line delay",
        ),
        (
            FLOOR_POSES_MISFIT,
            (cams.get("cam0") or {}).get("scale"),
            "the floor camera's poses misfit the IMU's motion {:.0f}x beyond their noise (variance): "
            "check the floor camera's T_BS (its lever arm too, and that it is body from camera), the "
            "camera-IMU time offset (a fixed --time-offset-ms), and the IMU's axes",
        ),
        (
            LOAD_MISFIT,
            (cams.get("cam1") or {}).get("scale"),
            "the load sightings misfit each other and the poses {:.0f}x beyond their noise "
            "(variance): the load map is off. Check world.yaml's load_qr side_m, the front camera's "
            "intrinsics, distortion and T_BS (its lever arm too), and the floor camera's lever arm",
        ),
    )
    out = []
    for name, factor, message in factors:
        scale = float(factor or 0.0)
        if scale > MISFIT_SCALE:
            out.append(LogWarning(name, 1, message.format(scale)))
    return out


def corner_bias_too_large_warning(loc: LocalizeResult) -> LogWarning | None:
    """A named warning (count 1: the flight) when the floor camera's flight-wide corner dilation
    is significant and confidently above cornerbias.MAX_BIAS_PX: the first-order correction does
    not model it, so it is reported, not removed, and every PnP and fused pose carries it.  It was
    a log line only: not in the summary's warnings, metrics.json or the report."""
    bias = ((loc.stats or {}).get(str(Estimator.PNP)) or {}).get("corner_bias") or {}
    if not (bias.get("significant") and bias.get("too_large")):
        return None
    worst = max(
        (abs(float(x)) for b in bias.get("bins", []) if b.get("determined") for x in b["bias_px"]),
        default=float("nan"),
    )
    return LogWarning(
        "corner_bias_too_large",
        1,
        f"the floor camera's refined corners share a dilation of up to {worst:.3f} px over the "
        f"flight (T = {float(bias['statistic']):.1f}), above the {cornerbias.MAX_BIAS_PX:g} px its "
        "correction models: not removed, so every pose carries it. Check the codes' printed size "
        "(world.yaml), the camera's focus and exposure (clipped whites thin the dark modules)",
    )


def no_floor_pose_warning(log: FlightLog, loc: LocalizeResult, detection_stats: dict) -> LogWarning | None:
    """A named, counted warning (count: the floor frames) when not one floor frame gave a PnP
    pose: the run has nothing to localise from and no fused estimate.  Before, it said so only in
    a note, so `--quiet` printed nothing, metrics.json listed no warning, the report no health
    line, and `--strict` exited 0 (1280x720 or a 1.5x focal length with the default scenario,
    BENCHMARKS.md, sweep14)."""
    pnp = loc.trajectories.get(str(Estimator.PNP))
    if pnp is not None and len(pnp) > 0:
        return None
    n = len(log.floor)
    with_code = int(detection_stats.get("floor_frames_with_code", 0))
    rejected = int(detection_stats.get("rejected_total", 0))
    w, h = log.floor.camera.width, log.floor.camera.height
    seen = (
        f"floor codes decoded in {with_code} of them but PnP posed none"
        if with_code
        else "no floor code decoded in any of them"
    )
    swapped = int(detection_stats.get("floor_frames_with_load_code", 0)) and int(
        detection_stats.get("front_frames_with_floor_code", 0)
    )
    check = (
        "The floor camera (cam0) read load codes and the front camera (cam1) floor codes: the two "
        "cameras look swapped (their streams, topics or files)"
        if swapped and not with_code
        else f"Check that whole codes fit the floor camera's view ({w}x{h}, fx "
        f"{log.floor.camera.fu:.0f} px) at the flight's height, its focus and exposure, and "
        "world.yaml's codes"
    )
    return LogWarning(
        "no_floor_pose",
        n,
        f"none of the {n} floor-camera frames gave a pose ({seen}; {rejected} payloads rejected): "
        f"nothing to localise from, no fused estimate. {check}",
    )


PLACE_CHECK_MAX_SIGHTINGS = 1000
"""One id's raw sightings are thinned to at most this many (every k-th) for the place check's
single-linkage clustering, whose memory is quadratic (a minute's hover in front of one label is
~1,800 sightings)."""


def loads_at_two_places(observations: list[LoadObservation]) -> dict[str, list[np.ndarray]]:
    """{load id: its places (3,)} for the ids whose raw PnP sightings form two or more places
    (`warehouse.inventory.ambiguous_places`: clusters more than AMBIGUITY_SEPARATION_M apart,
    each of at least MIN_CLUSTER_OBS sightings): a duplicated label, or a load moved while the
    drone flew.  Every back end maps such an id at one position, an average of the places or one
    of them, with a millimetre sigma (the sample flight with one label read as another's id:
    smoother 0.6 m from both places, sigma 4 mm)."""
    by_id: dict[str, list[np.ndarray]] = {}
    for o in observations:
        by_id.setdefault(o.load_id, []).append(np.asarray(o.p_world, dtype=float))
    found = {}
    for load_id, points in by_id.items():
        pts = np.array(points)
        pts = pts[np.isfinite(pts).all(axis=1)]
        stride = max(1, -(-len(pts) // PLACE_CHECK_MAX_SIGHTINGS))
        places = ambiguous_places(pts[::stride])
        if len(places) >= 2:
            found[load_id] = places
    return found


def loads_at_two_places_warning(found: dict[str, list[np.ndarray]]) -> LogWarning:
    """The named, counted warning (count: the ids) for `loads_at_two_places`' ids (the first
    five with their places)."""
    shown = sorted(found.items())[:5]
    at = {lid: ", ".join(f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})" for p in places) for lid, places in shown}
    listed = "; ".join(f"{lid} at {where}" for lid, where in at.items())
    more = f"; and {len(found) - len(shown)} more" if len(found) > len(shown) else ""
    return LogWarning(
        "load_seen_at_two_places",
        len(found),
        f"{len(found)} load id(s) read at places more than {AMBIGUITY_SEPARATION_M:.2f} m apart: "
        f"{listed}{more} (m). A duplicated label, or a load moved during the flight: their mapped "
        "positions are not to be trusted (their sigmas include the places' spread)",
    )


PLACEMENT_LINEAR_M = 0.05
PLACEMENT_LINEAR_DEG = 5.0
"""The largest floor-code placement sigma (world.yaml) at which PnP's first-order placement
whitening was measured honest (qr.pnp.whitening.floor_whitening; p20 stating 5 cm / 5 deg: PnP
NEES 5.8; 10 cm / 10 deg: 14.8, 20 cm / 20 deg: 57 with a 58 mm height bias; BENCHMARKS.md,
eighteenth session)."""


def placement_too_wide_warning(world, layout: FloorLayout | None = None) -> LogWarning | None:
    """A named warning when world.yaml states the floor codes' placement sigma beyond
    PLACEMENT_LINEAR_M / _DEG, or `layout` (`fusion run --map`) gives codes such a sigma: PnP's
    first-order model of it (and so the poses of the incremental smoother and the EKF) then
    fails; the batch smoother's as-built codes do not linearise it that way."""
    p = Placement.from_world(world)
    wide_world = p.sigma_m > PLACEMENT_LINEAR_M or math.degrees(p.sigma_rad) > PLACEMENT_LINEAR_DEG
    wide_map = []
    if layout is not None:
        for cid, (_, cov) in sorted(layout.codes.items()):
            sd = np.sqrt(np.maximum(np.diag(np.asarray(cov, dtype=float)), 0.0))
            if max(sd[0], sd[1]) > PLACEMENT_LINEAR_M or math.degrees(sd[2]) > PLACEMENT_LINEAR_DEG:
                wide_map.append(cid)
    if not wide_world and not wide_map:
        return None
    where = (
        f"world.yaml: floor codes laid to {100 * p.sigma_m:.3g} cm / {math.degrees(p.sigma_rad):.3g} deg"
        if wide_world
        else f"--map: {len(wide_map)} floor code(s) known only that loosely (first {wide_map[0]})"
    )
    return LogWarning(
        "placement_sigma_too_wide",
        1 if wide_world else len(wide_map),
        f"{where}, beyond the {100 * PLACEMENT_LINEAR_M:.0f} cm / {PLACEMENT_LINEAR_DEG:.0f} deg that PnP's "
        "placement model holds to: the PnP, incremental and EKF poses may be off by centimetres beyond "
        "their sigma (the batch smoother's as-built codes are not affected); survey the codes or state a "
        "tighter sigma",
    )


def undeclared_rolling_shutter_warning(
    log: FlightLog, det, loc: LocalizeResult, cfg: RunConfig
) -> LogWarning | None:
    """A named warning when the floor camera, declared global shutter, scatters its corners
    beyond their model (PnP chi^2 / dof above UNDECLARED_CHECK_CHI2_DOF) in a way a
    rolling-shutter readout explains (`check_undeclared_readout`).  Nothing is corrected: the
    readout is the user's to declare (sensor.yaml / Kalibr) or to calibrate (--calibrate-readout);
    fused as global shutter, the flight's time offset absorbs half the readout and its poses
    err by centimetres (2 m/s, 30 ms: PnP ATE 13 cm, the smoother's health "diverged")."""
    camera = log.floor.camera
    scale = float(loc.stats.get("pnp", {}).get("noise_scale", {}).get("scale", math.nan))
    if camera.rolling_shutter or not scale > UNDECLARED_CHECK_CHI2_DOF or "pnp" not in loc.trajectories:
        return None
    pnp = loc.trajectories["pnp"]
    calib = check_undeclared_readout(det, camera, log.world, log.imu, pnp, cfg.corner_sigma_px)
    if calib is None:
        return None
    return LogWarning(
        "rolling_shutter_undeclared",
        calib.n_better,
        f"cam0 is declared global shutter, but {calib.n_better} of {calib.n_frames} fast-moving frames "
        f"fit a rolling-shutter readout of about {calib.readout_s * 1e3:.0f} ms better (median PnP "
        f"chi2/dof {calib.chi2_per_dof_global:.1f} -> {calib.chi2_per_dof_rolling:.1f}): declare "
        "line_delay_s in cam0/sensor.yaml (Kalibr: line_delay) or run with --calibrate-readout",
    )


def _rolling_shutter(log: FlightLog, det, cfg: RunConfig, result: RunResult):
    """With `cfg.calibrate_readout`, the floor camera's readout time estimated from the flight
    (and used); then every rolling-shutter camera's corners moved to their frame's stamp
    (fusion.qr.rolling_shutter), so PnP, the tight corner factors and the load observations see
    global-shutter corners.  Returns the detections to use."""
    if cfg.calibrate_readout:
        calib = calibrate_readout(det, log.floor.camera, log.world, log.imu, cfg.corner_sigma_px)
        result.readout_calibration = calib
        result.notes.append(calib.note(CameraRole.FLOOR.value))
        if math.isfinite(calib.sigma_s):
            log.floor.camera.line_delay_s = calib.readout_s / log.floor.camera.height
        else:  # a flat cost profile: the readout is not determined, so none is made up
            result.warnings.append(
                LogWarning(
                    "readout_not_calibrated",
                    calib.n_frames,
                    f"--calibrate-readout: the floor camera's {calib.n_frames} frames do not determine "
                    "its readout (a flat cost profile: too little motion?); the declared line_delay_s "
                    f"({log.floor.camera.readout_s * 1e3:.2f} ms) is kept",
                )
            )
    cameras = {name: stream.camera for name, stream in log.cameras.items()}
    det, report = correct_flight(det, cameras, log.world, log.imu, cfg.corner_sigma_px, streams=log.cameras)
    result.notes += report.notes()
    unreadable = rolling_shutter_unreadable_warning(report)
    if unreadable is not None:
        result.warnings.append(unreadable)
    result.rolling_shutter = report
    return det


def _window_config(cfg: RunConfig, as_built: bool = False) -> WindowConfig:
    """The windows long flights are solved in (fusion.estimate.window; 0 s: never); `as_built`:
    the smoother estimates the floor codes (shorter windows by default: AS_BUILT_WINDOW_S)."""
    window_s = cfg.smoother_window_s
    if window_s is None:
        window_s = AS_BUILT_WINDOW_S if as_built else WINDOW_S
    if window_s > 0:
        return WindowConfig(window_s=window_s)
    return WindowConfig(min_flight_s=math.inf)


def _robust_kernel(cfg: RunConfig) -> RobustKernel:
    """`cfg.robust` as a RobustKernel (the fusion, the time offsets and the mount check share it);
    an unknown name is an EstimationError naming the choices."""
    try:
        return RobustKernel.parse(cfg.robust, "robust kernel")
    except ValueError as e:
        raise EstimationError(str(e)) from None


def placement_inflated(
    raw: Trajectory | None, inflation: correlation.CorrelationInflation | None
) -> Trajectory | None:
    """`raw` with the floor codes' placement share of each pose's covariance inflated by its
    correlation time (CorrelationInflation.add_to with placement_taus), as the batch smoother
    takes its poses: the mount check's flight-wide average of poses that share their codes'
    placement errors.  A 10 s flight over five codes laid 2 cm / 2 deg off read a 1.30 +- 0.27
    deg mount pitch and asked for a calibration (thirty-second session's held-out flight
    p_fps60_place2_exp).  Unchanged for a floor laid exactly."""
    if raw is None or inflation is None:
        return raw
    return inflation.add_to(raw, inflation.placement_taus())


@dataclass
class SharedWholeFlight:
    """One whole-flight batch solve serving both the front camera's time-offset profile and the
    floor camera's mount check (a resolve_time_offsets WholeFlightSolve).

    Order of operations in a run without --calibrate-extrinsics: (1) the floor profile (solves
    of its window) gives the floor offset r; (2) this solve: the whole flight with the floor
    stamps shifted by r (applied or not), the IMU as the front profile wants it, and the
    mount variable E0 (fusion.estimate.extrinsics.estimate_mount_and_states; a flight longer than
    the smoother's windows in those windows, fusion.estimate.window.estimate_mount_windowed); its body
    trajectory feeds the front profile and its E0 becomes the mount check (`mount`); (3) the
    pipeline's mount check takes `mount` instead of solving the whole flight again.  Before,
    (2) was two solves: one without E0 at shift r (front profile) and one with E0 at the applied
    shift with the IMU as logged (mount check).  The estimates keep their meaning and sigma:
    the mount check's stamps differ from the applied ones by at most the floor offset, which
    is below its significance when not applied (a 10 ms floor offset moves the mount estimate
    by ~0.02 deg, extrinsics' docstring); the front profile's trajectory is the fixed-mount one
    read through the estimated mount (equal within its sigma when the mount is right).  When
    the mount cannot be estimated (no IMU, gimbaled camera, poses without covariances or
    attitude) or most fixes disagree with the IMU, the trajectory is the plain
    `fused_trajectory` and `mount` stays None (the check then runs on its own, as before).

    `states` / `frame_t`: that solve's fixed-mount states X(k), V(k), B(k) and the (shifted)
    frame stamps they belong to; the batch smoother of fuse_stage starts from them
    (`warm_start`), so its first noise-scale solve begins next to its optimum instead of at the
    PnP poses (same optimum, fewer Levenberg-Marquardt iterations)."""

    mount: MountRotation | None = None
    states: gtsam.Values | None = None
    frame_t: np.ndarray | None = None
    window: WindowConfig | None = None  # a long flight solved in windows (estimate_mount_windowed)
    workers: int = 1  # processes for those windows
    # the PnP poses' time correlation (correlation.py): the mount solve takes their floor codes'
    # placement share inflated as the batch smoother does (placement_inflated)
    correlation: correlation.CorrelationInflation | None = None

    def warm_start(self, frame_t: np.ndarray) -> gtsam.Values | None:
        """The states for a smoother on the frames `frame_t`: None unless they are this solve's
        frames, each within WARM_START_MAX_SHIFT_S of its stamp here (an unapplied or applied
        floor offset moves them by its residual only)."""
        if self.states is None or self.frame_t is None or len(self.frame_t) != len(frame_t):
            return None
        shift = np.abs(np.asarray(frame_t, np.int64) - self.frame_t)
        return self.states if len(shift) and shift.max() <= WARM_START_MAX_SHIFT_S * 1e9 else None

    def __call__(
        self,
        log_: FlightLog,
        raw: Trajectory | None,
        shift_ns: int,
        config: TimeOffsetConfig,
        fusion_config: FusionConfig | None,
    ) -> Trajectory:
        inp = whole_flight_input(
            log_, placement_inflated(raw, self.correlation), shift_ns, config, fusion_config
        )
        trajectory = None
        if inp.raw.covariances is not None and CameraRole.FLOOR.value in log_.cameras:
            try:
                mount, trajectory, self.states = estimate_mount_windowed(
                    inp.frame_t,
                    inp.imu,
                    inp.raw,
                    inp.velocity,
                    log_.floor.camera,
                    inp.config,
                    self.window,
                    self.workers,
                )
                self.mount, self.frame_t = mount, np.asarray(inp.frame_t, np.int64)
            except EstimationError as e:
                logger.debug("shared whole-flight solve: no mount estimate (%s)", e)
        if trajectory is None:
            trajectory = fused_trajectory(log_, raw, shift_ns, config, fusion_config)
        return trajectory


def _apply_time_offsets(
    log: FlightLog,
    det,
    loc: LocalizeResult,
    cfg: RunConfig,
    result: RunResult,
    shared: SharedWholeFlight | None = None,
):
    """Each camera's time offset (fixed, else estimated: fusion.estimate.timeoffset) into
    `result.time_offsets`; when one is applied, the log and detections in the IMU clock and the
    per-frame estimates made again with them (so every output carries the corrected stamps).
    `shared`: the whole-flight solve for the front profile, shared with the mount check."""
    _progress(cfg, "camera-IMU time offsets")
    kernel = _robust_kernel(cfg)
    raw = loc.trajectories.get(str(Estimator.PNP))
    if raw is not None and result.rolling_shutter is not None and result.rolling_shutter.pose_cov_added:
        # the profile weighs each fix by its covariance: with the readout correction's share
        raw = add_pose_covariance(raw, result.rolling_shutter.pose_cov_added)
    # corner errors correlated in time (correlation.py): the floor profile averages the whole
    # flight's fixes, worth n / tau frames; its sigma says so (reweighting the fixes instead,
    # the inflated poses as its input, moved the x2.6 clipping offsets further off: BENCHMARKS.md)
    factor = 1.0
    if raw is not None and loc.correlation is not None:
        factor = loc.correlation.long_average_variance_factor(raw)
    if shared is not None:
        shared.correlation = loc.correlation
    offsets = resolve_time_offsets(
        log,
        raw,
        loc.camera_frame_observations,
        cfg.time_offsets_s,
        fusion_config=FusionConfig(robust_kernel=kernel),
        whole_flight=shared,
        floor_variance_factor=factor,
    )
    result.time_offsets = offsets
    drifting = {n: c.drift for n, c in offsets.cameras.items() if c.drift is not None and c.drift.applied}
    if drifting:
        each = "; ".join(
            f"{n} {d.rate * 1e6:+.1f} ppm ({d.rate * d.span_s * 1e3:+.2f} ms over the flight)"
            for n, d in drifting.items()
        )
        result.warnings.append(
            LogWarning(
                "camera_clock_drift",
                len(drifting),
                f"camera clocks running against the IMU's: {each}; corrected. A camera stamping with its "
                "own oscillator: stamp with the IMU's clock (or synchronise them) to avoid it",
            )
        )
    disagrees = fixed_offset_warning(offsets)
    if disagrees is not None:
        result.warnings.append(disagrees)
    bound = time_offset_bound_warning(offsets)
    if bound is not None:
        result.warnings.append(bound)
    if not offsets.any_applied:
        return log, det, loc
    log, det = shift_log(log, offsets), shift_detections(det, offsets)
    return log, det, localize_stage(log, det, cfg)


def fixed_offset_warning(offsets: TimeOffsets) -> LogWarning | None:
    """The named warning `time_offset_disagrees` for the cameras whose fixed offset
    (--time-offset-ms) the data put elsewhere (timeoffset.FixedCheck): a fixed offset was never
    checked, and one 60 ms off gave the audit's flight 3.6 cm with every health ok."""
    off = {n: c for n, c in offsets.cameras.items() if c.check is not None and c.check.disagrees()}
    if not off:
        return None
    parts = []
    for n, c in off.items():
        assert c.check is not None
        said = (
            "beyond the search"
            if c.check.at_bound or c.check.sigma_s is None
            else f"{(c.offset_s + c.check.residual_s) * 1e3:+.2f} +- {c.check.sigma_s * 1e3:.2f} ms"
        )
        parts.append(f"{n} ({role_name(n)}) fixed at {c.offset_s * 1e3:+.1f} ms, its data say {said}")
    return LogWarning(
        "time_offset_disagrees",
        len(off),
        f"fixed camera time offsets (--time-offset-ms) the data do not support: {'; '.join(parts)}. "
        "Every pose and load is stamped with the fixed value: check it (its sign: t_imu = t_cam + "
        "offset), or leave the offset to the run's estimate",
    )


def time_offset_bound_warning(offsets: TimeOffsets) -> LogWarning | None:
    """The named warning `time_offset_at_bound` for the cameras whose offset profile found its
    minimum at the search bound (timeoffset.CameraOffset.at_search_bound): the clock is further
    off than the search reaches, so no estimate of it, nor the poses stamped with it, holds."""
    bounded = {n: c for n, c in offsets.cameras.items() if c.at_search_bound}
    if not bounded:
        return None
    each = "; ".join(f"{n} ({role_name(n)}) {c.offset_s * 1e3:+.1f} ms" for n, c in bounded.items())
    return LogWarning(
        "time_offset_at_bound",
        len(bounded),
        f"camera time offsets at the edge of their search: {each} (+-"
        f"{TimeOffsetConfig().search_half_width_s * 1e3:.0f} ms around the seed): the camera "
        "clock is likely further off, and the estimates cannot be trusted. Measure the offset "
        "(a driver's latency, frames stamped on arrival) and fix it with --time-offset-ms, or "
        "seed the search with Kalibr's timeshift_cam_imu",
    )


def _apply_extrinsics(
    log: FlightLog,
    det,
    loc: LocalizeResult,
    cfg: RunConfig,
    result: RunResult,
    mount: MountRotation | None = None,
):
    """The floor camera's mount check (fusion.estimate.extrinsics) into `result.extrinsics`, its
    warning when significant; with `cfg.calibrate_extrinsics` a significant correction is applied
    to the floor camera and the per-frame estimates made again with it (so every output carries
    the corrected mount).  `mount`: the check already made by SharedWholeFlight (not solved again)."""
    _progress(cfg, "floor camera mount check")
    if mount is None:
        kernel = _robust_kernel(cfg)
        raw = placement_inflated(loc.trajectories.get(str(Estimator.PNP)), loc.correlation)
        mount = check_mount(log, raw, fusion_config=FusionConfig(robust_kernel=kernel))
    result.extrinsics = mount
    return _warn_or_apply_mount(log, det, loc, cfg, result, mount)


def _apply_front_extrinsics(log: FlightLog, det, loc: LocalizeResult, cfg: RunConfig, result: RunResult):
    """The front camera's mount check (extrinsics.estimate_front_mount: its load sightings hung
    from the PnP body poses, on the final stamps and the floor mount as the back ends take it)
    into `result.front_extrinsics`, its warning when significant; with `cfg.calibrate_extrinsics`
    a significant correction is applied to the front camera and the per-frame estimates made
    again with it.  Nothing without a front camera or its sightings."""
    pnp_traj = loc.trajectories.get(str(Estimator.PNP))
    if log.front is None or not loc.camera_frame_observations or pnp_traj is None or len(pnp_traj) < 2:
        return log, loc
    _progress(cfg, "front camera mount check")
    try:
        if "cam0" in log.cameras and log.floor.camera.gimbaled:
            raise EstimationError(
                "a gimbaled floor camera: its PnP poses are level, no body attitude to hang the "
                "front camera from"
            )
        mount = estimate_front_mount(
            pnp_traj,
            loc.camera_frame_observations,
            log.front.camera,
            fusion_config=FusionConfig(robust_kernel=_robust_kernel(cfg)),
        )
    except EstimationError as e:
        mount = MountRotation(CameraRole.FRONT.value, MountSource.NOT_ESTIMATED, note=str(e))
    result.front_extrinsics = mount
    return _warn_or_apply_mount(log, det, loc, cfg, result, mount)


def _warn_or_apply_mount(
    log: FlightLog, det, loc: LocalizeResult, cfg: RunConfig, result: RunResult, mount: MountRotation
):
    """A camera's mount check as the run takes it: nothing when not significant; its warning
    without `cfg.calibrate_extrinsics`; with it, the correction applied to that camera and the
    per-frame estimates made again (so every output carries the corrected mount)."""
    if not mount.significant:
        return log, loc
    if mount.implausible:
        result.warnings.append(mount.implausible_warning())
        return log, loc
    if not cfg.calibrate_extrinsics:
        warning = mount.warning()
        if warning is not None:
            result.warnings.append(warning)
        return log, loc
    log = apply_mount(log, mount)
    large = mount.large_correction_warning()
    if large is not None:
        result.warnings.append(large)
    return log, localize_stage(log, det, cfg)


def _fuse_into_result(
    log: FlightLog,
    loc: LocalizeResult,
    cfg: RunConfig,
    det,
    fixes: PositionFixes | None,
    result: RunResult,
    shared: SharedWholeFlight | None = None,
) -> dict:
    """fuse_stage, its results, failures and health into `result`; returns the fused stats.
    `shared`: the whole-flight solve of the time offsets / mount check (fuse_stage)."""
    fused_stage = fuse_stage(log, loc, cfg, det, fixes, shared)
    result.notes += fused_stage.notes
    result.warnings += fused_stage.warnings
    result.failures = {str(k): v for k, v in fused_stage.failures.items()}
    raw = fused_stage.raw if fused_stage.raw is not None else loc.trajectories[str(Estimator.PNP)]
    max_iterations = FusionConfig().lm_max_iterations
    gimbaled = "cam0" in log.cameras and log.floor.camera.gimbaled
    fused_stats = {}
    judged: dict[str, Trajectory] = {}
    stamp_variance = _floor_stamp_variance(result)
    # PnP conditions a gimbaled camera's pose on its level to the mount sigma
    # (floor.condition_on_level), which keeps the share f of the fixes' tilt-coupled error
    # (0 with the level stated exact, ~1 once the mount sigma is well above PnP's own tilt
    # sigma): the consider grows with it (tiltconsider.level_kept_fraction)
    kept = (
        level_kept_fraction(loc.free_tilt_covariances, log.floor.camera.mount_sigmas[0]) if gimbaled else 0.0
    )
    tilt_sigma = tilt_consider_sigma_rad(FusionConfig().bias_prior_sigma_accel_m_s2, kept)
    mount_covariance = _floor_mount_covariance(log, result)
    for name, res in fused_stage.results.items():
        # as built, the smoother's fixes are the sightings on the estimated codes, not PnP on
        # the nominal ones
        fixes_of = res.code_fixes if res.code_fixes is not None else raw
        result.health[str(name)] = assess_result(
            res, fixes_of, max_iterations=max_iterations, level_fixes=gimbaled
        )
        judged[str(name)] = res.trajectory
    if gimbaled:
        # level-frame fixes do not observe roll and pitch: the back ends' tilts against each
        # other (health.tilt_disagreement; the sweep's gimbaled flights, BENCHMARKS.md, sweep14)
        for fused_name, reason in tilt_disagreement(judged).items():
            result.health[fused_name].degrade(reason)
    del judged
    # after the health and the tilt comparison, the errors common to the fixes and every
    # estimate, which have no place in their innovations' covariances
    for name, res in fused_stage.results.items():
        res.trajectory = add_stamp_covariance(res.trajectory, stamp_variance)
        res.trajectory = add_mount_consider(res.trajectory, mount_covariance)
        if loc.intrinsics_consider is not None:
            # the floor camera's intrinsics error (cornerbias.intrinsics_consider), in place:
            # these covariances are this result's own, no longer read as they were
            window = cornerbias.FUSED_CONSIDER_WINDOW_S
            res.trajectory = loc.intrinsics_consider.add_to(res.trajectory, window, in_place=True)
        if tilt_sigma > 0.0 and log.imu is not None:  # 0 unless gimbaled
            # level fixes from a camera whose level is not known exactly: the tilt to the
            # levelling limit (tiltconsider.py); the back ends share the fixes whose error it covers
            res.trajectory = add_tilt_consider(res.trajectory, tilt_sigma)
            res.stats["tilt_consider_sigma_rad"] = tilt_sigma
            res.stats["level_kept_fraction"] = kept
        result.trajectories[name] = res.trajectory
        if log.front is not None:
            result.load_maps[name] = res.loads
        if res.floor_codes is not None:
            result.floor_codes[str(name)] = res.floor_codes
        fused_stats[name] = res.stats
    result.warnings += batch_start_warnings(fused_stats)  # (any run that fuses)
    return fused_stats


def _add_load_consider(
    log: FlightLog, loc: LocalizeResult, result: RunResult, places: dict[str, list[np.ndarray]]
) -> None:
    """Every load map's covariance plus the errors common to all sightings of a code
    (fusion.estimate.loadconsider): the body pose's, the label's print error, the front camera's
    stamps and mount.  The pose's from the batch smoother's covariances for every map (the part of the
    pose error the flight cannot average away, the same for every back end: they share the
    fixes), else from the map's own trajectory (a localize run: PnP's, conservative).  An id
    read at several `places` (loads_at_two_places) gains their spread about its estimate,
    mean_k (c_k - p)(c_k - p)^T: where that label is, the map cannot say.  Last, every other
    map gains its departure from the smoother's map (loadconsider.add_departure)."""
    assert log.front is not None
    offsets = result.time_offsets
    front = None if offsets is None else offsets.cameras.get(CameraRole.FRONT.value)
    stamp_variance = 0.0 if front is None else front.stamp_variance_s2
    smoother = result.trajectories.get(str(Estimator.SMOOTHER))
    terms: dict[int, dict] = {}  # common_terms per trajectory: every map's is the smoother's
    for name, load_map in result.load_maps.items():
        own = result.trajectories.get(name)
        traj = smoother if smoother is not None and smoother.covariances is not None else own
        if traj is not None and id(traj) not in terms:
            terms[id(traj)] = common_terms(loc.camera_frame_observations, traj, log.front.camera)
        result.load_maps[name] = add_load_consider_covariance(
            load_map,
            loc.camera_frame_observations,
            traj,
            log.front.camera,
            log.world.load_side_sigma_rel,
            stamp_variance,
            terms=None if traj is None else terms[id(traj)],
        )
        if places:
            result.load_maps[name] = add_places_spread(result.load_maps[name], places)
    # the floor's common shift, which every flight over these codes shares
    shift = _floor_common_shift(result)
    if shift is not None:
        for name in result.load_maps:
            result.load_maps[name] = add_floor_shift(result.load_maps[name], *shift)
    # every other map's departure from the batch smoother's (loadconsider.add_departure)
    reference = result.load_maps.get(str(Estimator.SMOOTHER))
    if reference is not None:
        for name in result.load_maps:
            if name != str(Estimator.SMOOTHER):
                result.load_maps[name] = add_departure(result.load_maps[name], reference)


def _floor_common_shift(result: RunResult) -> tuple[np.ndarray, np.ndarray] | None:
    """The floor's common shift (asbuilt.common_shift: centroid, Cov(delta)) over the codes of
    the batch smoother's as-built map, from their priors; None without one (a floor laid
    exactly: nothing shared).  One shift for the whole flight, though a long flight's windows
    each fix their own from fewer codes (a larger one)."""
    fmap = result.floor_codes.get(str(Estimator.SMOOTHER))
    codes = [] if fmap is None else [c for c in fmap.codes if c.prior_xy_yaw is not None]
    if not codes:
        return None
    xy = np.array([np.asarray(c.prior_xy_yaw)[:2] for c in codes])
    Q = np.array([c.prior_cov_xy_yaw for c in codes])
    return common_shift(xy, Q)


def _imu_scale_or_mount_note(mounts: list[MountRotation | None], fused_stats: dict) -> str | None:
    """A note when the batch smoother scaled the stated IMU noise up while a camera's mount check
    found a significant rotation it did not apply: a floor mount off by w tilts every fix against
    the gravity the IMU sees, a front mount off turns the load sightings against the fixes, and
    the smoother reads either as IMU noise (`held18`, to6_ext: an honest IMU scaled x2.89 by a
    0.5 deg floor mount error; a 0.5 deg roll of the front camera: x2.70).  None otherwise."""
    report = (fused_stats.get(str(Estimator.SMOOTHER)) or {}).get("noise_scales") or {}
    imu = report.get(str(variance.NoiseGroup.IMU))
    off = [m for m in mounts if m is not None and m.significant and not m.applied]
    if not off or not isinstance(imu, dict):
        return None
    which = "; ".join(
        f"the {m.role} camera's ({', '.join(m.significant_axes)}; {m.warning_name})" for m in off
    )
    return (
        f"the IMU's stated noise was scaled x{imu['sigma_factor']:.2f} for this flight, but a camera's "
        f"mount is off ({which}): the smoother reads it as IMU noise. Calibrate the mounts "
        "(--calibrate-extrinsics) before changing imu0/sensor.yaml"
    )


def _add_stamp_jitter(log: FlightLog, loc: LocalizeResult, result: RunResult) -> None:
    """`loc` (in place) with the cameras' significant stamp jitter (timeoffset.StampJitter):
    the floor camera's in the PnP fixes' covariances (s xi xi^T per fix), the front camera's in
    the load sightings' covariances (s u u^T, u the point's rate with the stamp) and PnP's load
    map made again from them: white per frame, so measurement noise for every back end; a named
    warning per camera.  The paper's load map (its own method) does not take it."""
    offsets = result.time_offsets
    if offsets is None:
        return
    key = str(Estimator.PNP)
    for role in (CameraRole.FLOOR, CameraRole.FRONT):
        c = offsets.cameras.get(role.value)
        jitter = None if c is None else c.jitter
        if jitter is None or not jitter.significant or key not in loc.trajectories:
            continue
        s2 = jitter.sigma_s**2
        fixes = loc.trajectories[key]
        if role == CameraRole.FLOOR:
            loc.trajectories[key] = add_stamp_covariance(fixes, s2)
            name, what = "floor", f"{jitter.n} fixes): every fix's covariance takes it along the motion"
        elif role.value in log.cameras:
            camera = log.cameras[role.value].camera
            loc.camera_frame_observations = widen_sightings(loc.camera_frame_observations, fixes, camera, s2)
            if loc.load_observations.get(key):
                # PnP's own load map, made from its sightings before the jitter was known
                loc.load_observations[key] = widen_sightings(loc.load_observations[key], fixes, camera, s2)
                loc.load_maps[key] = pnp.aggregate_load_observations(loc.load_observations[key], name=key)
            name, what = "front", f"{jitter.n} load sightings): the fused and PnP load maps take it"
        else:
            continue
        result.warnings.append(
            LogWarning(
                f"{name}_stamp_jitter",
                1,
                f"the {name} camera's ({role.value}) stamps jitter by {jitter.sigma_s * 1e3:.2f} ms "
                f"(1 sigma, {what}; or its images blur along the motion as much (a long "
                "exposure). Stamp frames at exposure (a hardware trigger, or the driver's sensor "
                "timestamp) rather than on arrival, or shorten the exposure" + _jitter_imu_caveat(log),
            )
        )


def _jitter_imu_caveat(log: FlightLog) -> str:
    """What else reads as stamp jitter in this log: no IMU, or an IMU with gaps, leaves the motion
    between frames uncertain, and its error looks like jitter (thirty-first session's audit: a
    log without its IMU was told to stamp its frames at exposure)."""
    if log.imu is None:
        return (
            ". This log has no IMU: the motion between frames comes from the velocity alone, and "
            "its error reads as jitter too"
        )
    gaps = [w.name for w in log.warnings if w.name in ("imu_gaps", "imu_coverage")]
    if gaps:
        return (
            f". The IMU's gaps ({', '.join(gaps)}) leave the motion between frames uncertain: that "
            "reads as jitter too"
        )
    return ""


def _floor_stamp_variance(result: RunResult) -> float:
    """E[stamp error^2] (s^2) of the floor frames as the outputs keep them: the floor camera's
    estimated time offset's (timeoffset.CameraOffset.stamp_variance_s2), 0 without one."""
    offsets = result.time_offsets
    floor = None if offsets is None else offsets.cameras.get(CameraRole.FLOOR.value)
    return 0.0 if floor is None else floor.stamp_variance_s2


def _floor_mount_covariance(log: FlightLog, result: RunResult) -> np.ndarray:
    """(6, 6) the body poses' covariance from the floor camera's mount rotation error
    (fusion.estimate.mountconsider): the stated sigma per axis, the estimate's on the axes
    --calibrate-extrinsics applied; zero without a floor camera, for a gimbaled one (its level
    carries the mount: tiltconsider) and for a mount stated exact or not stated."""
    if "cam0" not in log.cameras or log.floor.camera.gimbaled:
        return np.zeros((6, 6))
    mount = result.extrinsics
    applied = list(mount.significant_axes) if mount is not None and mount.applied else []
    sigma = mount_sigmas_rad(log.floor.camera, applied, None if mount is None else mount.sigma_rad)
    return mount_consider_covariance(log.floor.camera.T_body_cam, sigma)


def _run_without_cameras(
    log: FlightLog,
    out_dir: Path,
    cfg: RunConfig,
    until: str,
    timings: dict,
    result: RunResult,
    fixes: PositionFixes | None,
) -> RunResult:
    """A log without cameras (read with cameras_optional): IMU + external fixes only, the same
    outputs as a QR flight (no detections, no per-frame estimates, no load map)."""
    if fixes is None:
        raise FusionError(f"{log.root}: no floor camera and no --fixes: nothing to localise from")
    result.notes.append("no camera in this log: fused from the IMU and the external fixes only")
    loc = LocalizeResult({}, {}, {}, {})
    fused_stats: dict = {}
    if until in ("smooth", "run"):
        t = time.perf_counter()
        _progress(cfg, "fusion (smoother, incremental, ekf) on the external fixes")
        fused_stats = _fuse_into_result(log, loc, cfg, None, fixes, result)
        timings["fuse_s"] = time.perf_counter() - t
    _write_estimates(out_dir, result)
    if until == "run":
        t = time.perf_counter()
        _progress(cfg, "evaluation and report")
        _evaluate_and_report(log, result, fused_stats, {})
        timings["report_s"] = time.perf_counter() - t
    result.timings_s = timings
    return result


def _unsynchronised_load_sightings(log: FlightLog, loc: LocalizeResult) -> LogWarning | None:
    """A warning when front-camera load sightings can be placed neither by the body pose
    interpolated at their stamps (outside the floor frames' span, or in a gap between them:
    fusion.estimate.common.interpolable_load_times) nor at a floor frame within
    FusionConfig.max_sync_s: the back ends leave them out (no load factor)."""
    obs = loc.camera_frame_observations
    if log.front is None or not obs:
        return None
    max_sync_s = FusionConfig().max_sync_s
    t = np.array([o.timestamp_ns for o in obs], dtype=np.int64)
    frame_t = log.floor.timestamps_ns
    placed = (match_to_frames(frame_t, t, max_sync_s) >= 0) | interpolable_load_times(frame_t, t)
    unmatched = int((~placed).sum())
    if unmatched == 0:
        return None
    # only a frame's stamp beyond either end of the floor frames' span: the cameras started or
    # stopped a frame apart, or a stamp jittered past the end (a held-out flight with 1 ms jitter
    # lost 1 of 265 so, and the hint of a clock offset misled)
    period = int(np.median(np.diff(frame_t))) if len(frame_t) > 1 else 0
    edge = (t >= frame_t[0] - period) & (t <= frame_t[-1] + period) & ((t < frame_t[0]) | (t > frame_t[-1]))
    why = (
        "all within a frame of the floor camera's first or last frame: the cameras started or stopped apart"
        if np.all(edge[~placed])
        else "a clock offset on cam1?"
    )
    return LogWarning(
        "load_sightings_unsynchronised",
        unmatched,
        f"{unmatched} of {len(obs)} front-camera load sightings lie outside the floor-camera "
        f"frames' span or in a gap of over {LOAD_INTERP_MAX_GAP_S * 1e3:.0f} ms between them: "
        f"the fused load maps leave them out ({why})",
    )


def _progress(cfg: RunConfig, what: str) -> None:
    logger.info("%s ...", what)


def _write_estimates(out_dir: Path, result: RunResult) -> None:

    for name, traj in result.trajectories.items():
        write_tum(out_dir / f"trajectory_{name}.tum", traj)
        if traj.covariances is not None and len(traj):
            write_sigmas_csv(out_dir / f"sigmas_{name}.csv", traj)
    for name, lm in result.load_maps.items():
        write_loads_csv(out_dir / f"loads_{name}.csv", lm)
        write_loads_json(out_dir / f"loads_{name}.json", lm)
    for name, fmap in result.floor_codes.items():
        write_floor_codes_csv(out_dir / FLOOR_CODES_CSV.format(name), fmap)


def _evaluate_and_report(
    log: FlightLog,
    result: RunResult,
    fused_stats: dict,
    raw_stats: dict,
    floor_xy: np.ndarray | None = None,
) -> None:
    """metrics.json, the ground truth as TUM, report.md and its plots; `floor_xy`: the world
    (x, y) of the floor codes decoded in the flight (_floor_codes_seen), drawn as a faint grid."""

    out_dir = result.out_dir
    gt = log.groundtruth
    if gt is None:
        result.notes.append("no ground truth in this log: no metrics (report without errors)")
    # a gimbaled floor camera's PnP poses are its level frame: compared on position and yaw
    level_pnp = "cam0" in log.cameras and log.floor.camera.gimbaled
    metrics = evaluate(
        gt,
        result.trajectories,
        result.load_maps,
        log.loads_groundtruth,
        log.blackouts,
        result.detection_stats,
        # evo's `-a` beside the unaligned ATE: what is left once a rigid offset (an as-built
        # floor's common shift, a truth in another frame) is taken out
        align=True,
        position_yaw_only=("paper", str(Estimator.PNP)) if level_pnp else ("paper",),
    )
    metrics["estimator_stats"] = to_jsonable({**raw_stats, **fused_stats})
    metrics["estimator_failures"] = {
        name: {"reason": f.reason, "error_type": f.error_type} for name, f in result.failures.items()
    }
    metrics["notes"] = list(result.notes)
    mismatch = metrics.get("groundtruth_frame_mismatch")
    if mismatch is not None:
        result.warnings.append(
            LogWarning(
                "groundtruth_frame_mismatch",
                1,
                f"the ground truth is not in the floor codes' frame: {mismatch['estimator']} is "
                f"{mismatch['ate_rmse_m']:.2f} m off as given, "
                f"{100 * mismatch['ate_aligned_rmse_m']:.1f} cm after an SE(3) fit "
                f"({mismatch['translation_m']:.2f} m, {mismatch['rotation_deg']:.1f} deg): "
                "check the truth's origin and world.yaml's code positions; the errors below are as given",
            )
        )
    if result.floor_codes:
        unread = floorcodes.groundtruth_warning(log.root)
        if unread is not None:
            result.warnings.append(unread)
    metrics["warnings"] = [w.to_dict() for w in result.warnings]
    metrics["health"] = {name: h.to_dict() for name, h in result.health.items()}
    if result.floor_codes:
        metrics["floor_codes"] = to_jsonable(
            {name: floorcodes.floor_code_metrics(fmap, log.root) for name, fmap in result.floor_codes.items()}
        )
    if result.time_offsets is not None:
        metrics["time_offsets"] = result.time_offsets.as_dict()
    mounts = {"extrinsics": result.extrinsics, "front_extrinsics": result.front_extrinsics}
    truth = read_extrinsics_groundtruth(log.root) if any(m is not None for m in mounts.values()) else {}
    for key, mount in mounts.items():
        if mount is not None:
            metrics[key] = mount.as_dict(truth.get(mount.camera))
    metrics["noise_scales"] = to_jsonable(result.noise_scales)
    # written with or without ground truth: health, failures and warnings hold without it
    write_metrics(out_dir / "metrics.json", metrics)
    result.metrics = metrics
    if gt is not None:
        export_groundtruth_tum(gt, out_dir / "trajectory_groundtruth.tum")
    summary = dict(
        result.log_summary, payload_unit_m=log.world.payload_unit_m, detection=result.detection_stats
    )
    if result.warnings:
        summary["warnings"] = [str(w) for w in result.warnings]
    result.report_path = write_report(
        out_dir,
        metrics,
        result.trajectories,
        result.load_maps,
        gt,
        log.loads_groundtruth,
        log.blackouts,
        summary,
        floor_codes_xy_m=floor_xy,
        floor_codes=result.floor_codes.get(str(Estimator.SMOOTHER)),
    )


def _floor_codes_seen(det: DetectionResult, log: FlightLog) -> np.ndarray | None:
    """World (x, y) of every floor code decoded in the flight (for the plots' faint grid): the
    payloads of the floor camera's detections, those that detections.csv holds (its tracked
    sightings are codes decoded in other frames).  Taken from `det` rather than by reading
    detections.csv again (which held every detection of the flight as objects at the run's
    memory peak: ~65 MB a 2-minute flight, BENCHMARKS.md)."""
    return floor_codes_from_payloads((d.payload for d in det.for_camera("cam0")), log.world.payload_unit_m)


def demo(
    folder: Path = Path("demo-flight"), duration_s: float | None = None, seed: int = 0, progress: bool = True
) -> RunResult:
    """Simulate the default flight into `folder/log` (kept and reused if it is already there and
    complete) and run the whole pipeline into `folder/out` (the previous demo's outputs are
    replaced).  Nothing the demo did not create is deleted: other files in `folder/log` and
    `folder/out` stay, and files of a log layout it did not write are refused, not replaced."""

    folder = Path(folder)
    log_dir = folder / "log"
    if not (log_dir / "world.yaml").exists():
        _progress(RunConfig(progress=progress), f"simulating the default flight into {log_dir}")
        simulate(
            log_dir, scenario="default", duration_s=duration_s, seed=seed, overwrite=True, progress=progress
        )
    return run(log_dir, folder / "out", RunConfig(progress=progress, force=True))
