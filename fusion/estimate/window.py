"""A long flight solved by the batch smoother in overlapping time windows (issue 13 item 2: peak
memory <= 1 GB per worker for a 30-minute flight).

The batch smoother's memory grows linearly with the frames (graph, Values, the linear systems of
Levenberg-Marquardt, the variance components' sparse factorisation: ~0.1 GB per flight minute of
a two-camera 30 fps flight, BENCHMARKS.md).  A flight longer than `WindowConfig.min_flight_s`
is cut into windows of at most `window_s` that overlap by `overlap_s`; each is solved by the
unchanged `smoother.smooth` (its own noise-scale iteration, outlier gate and marginal
covariances), one at a time, so the peak is that of one window.  Shorter flights are solved
whole: today's exact solution.

Stitching rule (fixed-interval smoothing by overlapping batches; the window's ends are the
only places it lacks information the whole-flight solve has):

- Windows: n = ceil((D - O) / (W - O)) windows of equal length L = (D + (n - 1) O) / n <= W
  over the flight's D seconds, window i starting at i (L - O); consecutive windows overlap by O.
- Trajectory: the cut between windows i - 1 and i is the middle of their overlap; each frame's
  pose and covariance come from the window whose cut range holds it, so every output frame is
  at least O / 2 from the end of the window it comes from (except at the flight's own ends,
  which the whole-flight solve does not see beyond either).  Each window starts from its own
  first fixes (the smoother's first-velocity and bias priors): at O / 2 = 15 s from a window's
  start, these are forgotten (the fixes every frame and the IMU pin the state).
- Loads: each load sighting is given to exactly one window, the one whose cut range holds its
  frame, so the windows' load estimates use disjoint sightings; a load seen in several windows
  is their information-weighted mean, P = (sum_i P_i^-1)^-1, x = P sum_i P_i^-1 x_i (the
  sightings' errors are independent; the windows' pose errors, which enter each sighting, are
  independent away from the cuts).  Without covariances: the sightings-weighted mean.
- Health, counts: summed over windows (iterations: the most of any window); the noise scales
  per camera: the windows' scales weighted by their degrees of freedom (each window estimates
  its own: Förstner's variance components per window).

- As-built floor codes (fusion.estimate.asbuilt): each window takes the sightings of all its
  frames (overlaps included, as it takes their fixes) and estimates the codes it sees from
  their priors; each code is taken from the window that saw it most (asbuilt.
  merge_window_maps: the windows' estimates share the prior and their floor's common shift, so
  they are not averaged as the loads are), and each output frame's as-built fixes (what the
  health monitor judges it against) are those on its own window's codes (FusionResult.
  code_fixes).  A code seen in several windows is thus less certain than in a whole-flight
  solve.  Giving the windows disjoint sightings instead left their overlaps on PnP fixes of
  the nominal codes, whose placement share is correlated from frame to frame: pose NEES 35
  against 5.5 on a synthetic flight (BENCHMARKS.md, nineteenth session).  Before, such a flight
  was solved whole, and took 4.2 GB at 30 minutes.
- Tight coupling's corner factors are windowed like the poses.

Windows are independent solves, so `workers` > 1 solves up to WINDOW_WORKERS of them at once on
worker processes (fusion.parallel); the result is the same as one at a time (each window is
the same solve of the same inputs; tests/test_parallel_backend.py), the peak memory that of
that many windows (one per process).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V
from scipy.spatial.transform import Rotation

from fusion.conventions import GRAVITY_M_S2
from fusion.errors import EstimationError
from fusion.estimate import variance
from fusion.estimate.asbuilt import AsBuiltInput, FloorCodeMap, as_built_fixes, merge_window_maps
from fusion.estimate.common import FusionConfig, FusionResult, SolveHealth, SolveMode, match_to_frames
from fusion.estimate.extrinsics import MountRotation, estimate_mount_and_states, merge_mount_rotations
from fusion.estimate.smoother import (
    imu_coverage,
    imu_subintervals,
    midpoint_specific_force,
    release_heap,
    smooth,
)
from fusion.geometry import PoseInterpolator, so3_exp_stack
from fusion.log.euroc import ImuData
from fusion.parallel import parallel_map, sendable
from fusion.types import Estimator, LoadEstimate, LoadMap, Trajectory

__all__ = [
    "AS_BUILT_WINDOW_S",
    "Window",
    "WindowConfig",
    "estimate_mount_windowed",
    "merge_loads",
    "plan_windows",
    "smooth_windowed",
]

log = logging.getLogger(__name__)

WINDOW_MIN_FLIGHT_S = 300.0
"""Flights up to this long are solved whole (today's exact solution); ~0.7 GB peak at 5 min."""
WINDOW_S = 180.0
"""Longest window: ~0.5 GB peak for a two-camera 30 fps window (BENCHMARKS.md)."""
AS_BUILT_WINDOW_S = 120.0
"""Longest window of a flight with as-built floor codes (the default whenever world.yaml does not
say the codes are exact): such a window holds a factor per code in view of each frame, not one
pose factor per frame, and the code variables' dense columns in its marginals.  On the
30-minute flight `fusion batch`'s worker peaked at 1,070 MiB with 180 s windows and 952 MiB with
120 s (ATE 0.966 / 0.961 mm; the smoother's CPU +12 %: more overlap; BENCHMARKS.md)."""
WINDOW_OVERLAP_S = 30.0
"""Overlap of consecutive windows; output frames are at least half of it from a window's end."""
WINDOW_WORKERS = 2
"""Windows solved at once with several workers: each holds ~0.5 GB at its peak (WINDOW_S), so
the processes' sum stays near 1 GB whatever the core count."""
IMU_PAD_S = 0.05
"""IMU / velocity samples kept beyond a window's first and last frame (a few samples at 200 Hz)."""
MOUNT_FRAME_RATE_HZ = 10.0
"""The windowed mount solve (estimate_mount_windowed: flights longer than min_flight_s only) keeps
the floor frames at about this rate (every k-th frame, k = round(frame rate / this), at least 1):
the IMU is preintegrated between the kept frames and the PnP fixes of the others are left out.
Its cost is ~linear in the frames (a 30 fps 10-minute flight: 13.6 -> ~4.6 CPU s); the mount's
sigma grows by at most ~sqrt(k) (measured on the 10-minute flight: 0.0022 -> 0.0023 deg, against
the 11.5 target's 0.05 deg), and the trajectory the front time-offset profile reads is filled in
at the other frames by the IMU from the kept frames' states (imu_fill)."""
_NS = 1e9


@dataclass(frozen=True)
class WindowConfig:
    """How a long flight is cut (module docstring).  min_flight_s = inf: never windowed."""

    window_s: float = WINDOW_S
    overlap_s: float = WINDOW_OVERLAP_S
    min_flight_s: float = WINDOW_MIN_FLIGHT_S

    def check(self) -> None:
        if not (self.overlap_s >= 0 and self.window_s > self.overlap_s):
            raise EstimationError(
                f"window: window_s ({self.window_s} s) must exceed overlap_s ({self.overlap_s} s) >= 0"
            )


@dataclass(frozen=True)
class Window:
    """Frames [first, stop) solved; frames [out_first, out_stop) taken from this window."""

    first: int
    stop: int
    out_first: int
    out_stop: int


def plan_windows(frame_t: np.ndarray, cfg: WindowConfig) -> list[Window]:
    """The windows of a flight with frame times `frame_t` (N,) int64 ns (module docstring);
    one window of every frame when the flight is at most cfg.min_flight_s long."""
    cfg.check()
    n = len(frame_t)
    if n == 0:
        return []
    t = (np.asarray(frame_t, np.int64) - int(frame_t[0])) / _NS
    duration = float(t[-1])
    if duration <= cfg.min_flight_s or duration <= cfg.window_s:
        return [Window(0, n, 0, n)]
    count = math.ceil((duration - cfg.overlap_s) / (cfg.window_s - cfg.overlap_s))
    length = (duration + (count - 1) * cfg.overlap_s) / count
    starts = np.arange(count) * (length - cfg.overlap_s)
    first = np.searchsorted(t, starts, "left")
    stop = np.searchsorted(t, starts + length, "right")
    stop[-1] = n
    cuts = np.r_[0, np.searchsorted(t, starts[1:] + cfg.overlap_s / 2, "left"), n]
    return [Window(int(first[i]), int(stop[i]), int(cuts[i]), int(cuts[i + 1])) for i in range(count)]


def _rows(record: Any, keep: np.ndarray) -> Any:
    """A copy of a dataclass record of per-sample arrays with only the samples in `keep`."""
    return replace(
        record,
        **{
            f.name: getattr(record, f.name)[keep]
            for f in fields(record)
            if isinstance(getattr(record, f.name), np.ndarray) and len(getattr(record, f.name)) == len(keep)
        },
    )


def _window_inputs(win: Window, frame_t: np.ndarray, imu, raw: Trajectory, load_obs, kwargs: dict) -> tuple:
    """The smoother's inputs restricted to the window's frames (load sightings: its cut range)."""
    t0, t1 = int(frame_t[win.first]), int(frame_t[win.stop - 1])
    pad = int(IMU_PAD_S * _NS)
    if imu is not None:
        ti = np.asarray(imu.timestamps_ns)
        imu = _rows(imu, (ti >= t0 - pad) & (ti <= t1 + pad))
    tr = np.asarray(raw.timestamps_ns)
    raw = _rows(raw, (tr >= t0) & (tr <= t1))
    o0 = int(frame_t[win.out_first]) if win.out_first > 0 else None
    o1 = int(frame_t[win.out_stop]) if win.out_stop < len(frame_t) else None
    kw = dict(kwargs)
    if kw.get("as_built") is not None:
        kw["as_built"] = _sightings_in(kw["as_built"], t0, t1 + 1)
    loads = [
        o
        for o in load_obs or []
        if (o0 is None or o.timestamp_ns >= o0) and (o1 is None or o.timestamp_ns < o1)
    ]
    if kw.get("velocity") is not None:
        tv = np.asarray(kw["velocity"].timestamps_ns)
        kw["velocity"] = _rows(kw["velocity"], (tv >= t0 - pad) & (tv <= t1 + pad))
    if kw.get("floor_frames"):
        kw["floor_frames"] = {t: s for t, s in kw["floor_frames"].items() if t0 <= t <= t1}
    return frame_t[win.first : win.stop], imu, raw, loads, kw


def _sightings_in(as_built: AsBuiltInput, t0: int, t1: int) -> AsBuiltInput:
    """`as_built` with only the sightings stamped in [t0, t1) ns."""
    t = np.asarray(as_built.sightings.timestamps_ns)
    return replace(as_built, sightings=_rows(as_built.sightings, (t >= t0) & (t < t1)))


def _judged_on_codes(res: FusionResult, as_built: AsBuiltInput | None) -> FusionResult:
    """`res` with its as-built fixes (FusionResult.code_fixes, asbuilt.as_built_fixes: what the
    health monitor judges it against) when it estimated the codes of `as_built`; computed once
    per result, not per solve (~0.6 CPU s for a 180 s window)."""
    if as_built is not None and res.floor_codes is not None:
        res.code_fixes = as_built_fixes(as_built, res.floor_codes)
    return res


def merge_loads(maps: list[LoadMap], name: str) -> LoadMap:
    """One load map from windows' maps of disjoint sightings: per load the information-weighted
    mean of its estimates (x = P sum P_i^-1 x_i, P = (sum P_i^-1)^-1), or, when any lacks a
    covariance, the mean weighted by sightings (covariance unknown)."""
    by_id: dict[str, list[LoadEstimate]] = {}
    for m in maps:
        for e in m.loads:
            by_id.setdefault(e.load_id, []).append(e)
    out = []
    for lid, ests in by_id.items():
        n_obs = sum(e.n_obs for e in ests)
        if len(ests) == 1:
            out.append(replace(ests[0]))
            continue
        if all(e.cov_world is not None for e in ests):
            info = [np.linalg.inv(np.asarray(e.cov_world, float)) for e in ests]
            cov = np.linalg.inv(sum(info))
            p = cov @ sum(i @ np.asarray(e.p_world, float) for i, e in zip(info, ests))
            out.append(LoadEstimate(lid, p, 0.5 * (cov + cov.T), n_obs))
        else:
            w = np.array([max(e.n_obs, 1) for e in ests], float)
            p = np.sum([wi * np.asarray(e.p_world, float) for wi, e in zip(w, ests)], axis=0) / w.sum()
            out.append(LoadEstimate(lid, p, None, n_obs))
    out.sort(key=lambda e: e.load_id)
    return LoadMap(name, out)


def _merge_health(parts: list[SolveHealth], mapped: set[str]) -> SolveHealth:
    h = SolveHealth()
    for p in parts:
        if h.mode is SolveMode.FUSED and p.mode is not SolveMode.FUSED:
            h.mode = p.mode
        for r in p.reasons:
            h.note(r)
        for name in ("fixes", "frames_far_from_fix", "iteration_limit_hits", "lm_stalls", "linear_fallbacks"):
            setattr(h, name, getattr(h, name) + getattr(p, name))
        h.weak_prior_states += p.weak_prior_states
        h.gate_skipped += p.gate_skipped
        h.resets += p.resets
    h.loads_dropped = sorted({lid for p in parts for lid in p.loads_dropped} - mapped)
    return h


def _merge_noise_scales(parts: list[dict | None]) -> dict | None:
    """The windows' noise-scale reports as one: per camera the dof-weighted scale, the IMU's
    chi2/dof likewise; `windows`: each window's per-camera scales."""
    reports = [r for r in parts if r]
    if not reports:
        return None
    out: dict = {
        "solves": max(int(r.get("solves", 1)) for r in reports),
        "groups": reports[0].get("groups", {}),
        "cameras": {},
    }
    for cam in sorted({c for r in reports for c in r.get("cameras", {})}):
        entries = [r["cameras"][cam] for r in reports if cam in r.get("cameras", {})]
        dof = sum(float(e["dof"]) for e in entries)
        scale = (
            sum(float(e["scale"]) * float(e["dof"]) for e in entries) / dof
            if dof > 0
            else float(np.mean([e["scale"] for e in entries]))
        )
        out["cameras"][cam] = dict(entries[0], scale=scale, sigma_factor=math.sqrt(scale), dof=dof)
    # a stated sensor's noise scale where a window estimated one (variance.next_noise_scales),
    # else 1: the windows' mean, for the back ends after the smoother
    for g in variance.STATED_SENSORS:
        scales = [float((r.get(str(g)) or {}).get("scale", 1.0)) for r in reports]
        if any(s != 1.0 for s in scales):
            scale = float(np.mean(scales))
            out[str(g)] = {"scale": scale, "sigma_factor": math.sqrt(scale), "windows": scales}
        chi2 = [r[f"{g}_chi2_per_dof"] for r in reports if f"{g}_chi2_per_dof" in r]
        if chi2:
            out[f"{g}_chi2_per_dof"] = float(np.mean(chi2))
        if any(r.get(f"{g}_warning") for r in reports):
            out[f"{g}_warning"] = True
    not_applied = sorted({r["not_applied"] for r in reports if "not_applied" in r})
    if not_applied:
        out["not_applied"] = "; ".join(not_applied)
    # correlation.solve_inflated_twice: whether every window took two solves, and why not
    for key in ("inflated_solve", "two_solves"):
        if any(key in r for r in reports):
            out[key] = all(r.get(key, False) for r in reports)
    kept = sorted({r["two_solves_not_applied"] for r in reports if "two_solves_not_applied" in r})
    if kept:
        out["two_solves_not_applied"] = "; ".join(kept)
    out["windows"] = [{cam: e["scale"] for cam, e in r.get("cameras", {}).items()} for r in reports]
    return out


_SUMMED = (
    "imu_intervals",
    "bridged_intervals",
    "imu_segments",
    "frames_outside_imu",
    "pose_factors",
    "corner_factors",
    "velocity_factors",
    "load_factors",
    "load_observations_skipped",
    "n_factors",
    "gated_pose_factors",
    "gated_load_factors",
    "gated_corner_factors",
    "rejected_pose_factors",
    "rejected_load_factors",
    "rejected_corner_factors",
    "time_build_s",
    "time_optimize_s",
    "time_covariance_s",
    "floor_code_factors",
    "floor_code_frames",
    "gated_floor_code_factors",
    "rejected_floor_code_factors",
    "time_s",
    "initial_error",
    "final_error",
)


def _merge_stats(parts: list[dict], plan: list[Window], frame_t: np.ndarray, health: SolveHealth) -> dict:
    stats = {k: v for k, v in parts[0].items() if k not in ("noise_scales", "health")}
    for k in _SUMMED:
        vals = [p[k] for p in parts if k in p]
        if vals:
            stats[k] = sum(vals)
    stats["iterations"] = max(int(p.get("iterations", 0)) for p in parts)
    methods = sorted({str(p.get("covariance_method")) for p in parts})
    stats["covariance_method"] = methods[0] if len(methods) == 1 else "+".join(methods)
    stats["health"] = health.as_dict()
    stats["noise_scales"] = _merge_noise_scales([p.get("noise_scales") for p in parts])
    if stats["noise_scales"] is None:
        del stats["noise_scales"]
    t0 = int(frame_t[0])
    stats["windows"] = [
        {
            "start_s": (int(frame_t[w.first]) - t0) / _NS,
            "end_s": (int(frame_t[w.stop - 1]) - t0) / _NS,
            "frames": w.stop - w.first,
            "output_frames": w.out_stop - w.out_first,
            "iterations": p.get("iterations"),
            "time_s": p.get("time_s"),
        }
        for w, p in zip(plan, parts)
    ]
    return stats


def smooth_windowed(
    frame_times_ns,
    imu,
    raw: Trajectory,
    load_obs,
    front_camera=None,
    velocity=None,
    config: FusionConfig | None = None,
    floor_frames: dict | None = None,
    floor_camera=None,
    as_built=None,
    window: WindowConfig | None = None,
    solver: Callable[..., FusionResult] | None = None,
    warm_start: gtsam.Values | None = None,
    workers: int = 1,
) -> FusionResult:
    """`smoother.smooth` (same arguments and result), a flight longer than
    window.min_flight_s solved in overlapping windows one at a time (module docstring: the
    stitching rule); stats['windows'] lists them.  A shorter flight is `smooth` itself; so is a
    flight with a window the smoother cannot solve on its own
    (EstimationError, e.g. no fix in it), with a health note saying so.  `solver`: the
    smoother of one window or of the whole flight (default `smoother.smooth`).  `warm_start`:
    the initial values of a whole-flight solve (`smooth`'s); the windows start cold (their keys
    are renumbered, and on the 10-minute flight the warm start saved no measurable time).
    `workers`: processes for the windows (at most WINDOW_WORKERS at once; module docstring)."""
    window = window or WindowConfig()
    solver = solver or smooth
    # the heap freed by earlier whole-flight solves (the time-offset profile's: ~0.4 GB at 10 min)
    # back to the system first, so that it does not stay under this solve's peak
    release_heap()
    kwargs = dict(
        front_camera=front_camera,
        velocity=velocity,
        config=config,
        floor_frames=floor_frames,
        floor_camera=floor_camera,
        as_built=as_built,
    )
    frame_t = np.asarray(frame_times_ns)
    plan = plan_windows(frame_t, window) if frame_t.ndim == 1 and len(frame_t) else []
    if len(plan) <= 1:
        return _judged_on_codes(
            solver(frame_times_ns, imu, raw, load_obs, warm_start=warm_start, **kwargs), as_built
        )
    log.info("smoother: %d frames in %d overlapping windows", len(frame_t), len(plan))
    poses: list[np.ndarray] = []
    covs: list[np.ndarray | None] = []
    maps: list[LoadMap] = []
    healths: list[SolveHealth] = []
    stats: list[dict] = []
    code_maps: list[FloorCodeMap] = []
    code_fixes: list[Trajectory] = []
    n_workers = min(workers, WINDOW_WORKERS) if sendable(solver) else 1
    tasks = (
        (
            solver,
            win.out_first - win.first,
            win.out_stop - win.first,
            *_window_inputs(win, frame_t, imu, raw, load_obs, kwargs),
        )
        for win in plan
    )
    parts = parallel_map(_solve_window, tasks, n_workers, preload=("fusion.estimate.window",))
    for i, win in enumerate(plan):
        try:
            T_part, cov_part, loads_part, codes_part, health_part, stats_part = next(parts)
        except EstimationError as e:
            # e.g. a window inside a long blackout (no fix): the whole flight bridges it
            t_s = (int(frame_t[win.first]) - int(frame_t[0])) / _NS
            reason = f"window {i + 1} of {len(plan)} (from {t_s:.1f} s) not solvable on its own ({e})"
            log.warning("smoother: %s: solving the whole flight instead", reason)
            del poses, covs, maps, code_maps, code_fixes, healths, stats, parts
            release_heap()
            whole = _judged_on_codes(
                solver(frame_times_ns, imu, raw, load_obs, warm_start=warm_start, **kwargs), as_built
            )
            whole.health.note(f"{reason}: solved as one window (memory not bounded)")
            whole.stats["health"] = whole.health.as_dict()
            return whole
        poses.append(T_part)
        covs.append(cov_part)
        maps.append(loads_part)
        if codes_part[0] is not None:
            code_maps.append(codes_part[0])
        if codes_part[1] is not None:
            code_fixes.append(codes_part[1])
        healths.append(health_part)
        stats.append(stats_part)
    name = str(Estimator.SMOOTHER)
    cov = None if any(c is None for c in covs) else np.concatenate([c for c in covs if c is not None])
    traj = Trajectory(name, frame_t.astype(np.int64), np.concatenate(poses), cov)
    loads = merge_loads(maps, name)
    health = _merge_health(healths, {e.load_id for e in loads.loads})
    merged_stats = _merge_stats(stats, plan, frame_t, health)
    out = FusionResult(traj, loads, merged_stats, health)
    if as_built is not None:
        out.floor_codes = merge_window_maps(code_maps, name, as_built.placement)
        merged_stats["floor_code_variables"] = len(out.floor_codes.codes)
        # each frame's fixes on the codes its own window estimated (their common shift is the
        # window's), not on the merged map's
        out.code_fixes = Trajectory.concatenate(code_fixes, "pnp") if code_fixes else None
    return out


def frame_stride(frame_t: np.ndarray, rate_hz: float) -> int:
    """k >= 1 such that every k-th of the frames `frame_t` (N,) int64 ns comes at about `rate_hz`
    (their median interval; 1 with fewer than two frames or a rate at or above theirs)."""
    if len(frame_t) < 2 or rate_hz <= 0:
        return 1
    dt_s = float(np.median(np.diff(np.asarray(frame_t, np.int64)))) / _NS
    return max(1, int(round(1.0 / (rate_hz * dt_s)))) if dt_s > 0 else 1


def decimate_frames(
    frame_t: np.ndarray, raw: Trajectory, rate_hz: float, max_sync_s: float = FusionConfig.max_sync_s
) -> tuple[np.ndarray, Trajectory]:
    """The indices (M,) of every k-th frame of `frame_t` (frame_stride; the last frame kept too,
    so the flight's span is unchanged) and the fixes of `raw` whose frame (the nearest within
    `max_sync_s`, as the smoother matches them: common.match_to_frames) is kept (rows of its
    arrays)."""
    k = frame_stride(frame_t, rate_hz)
    keep = np.zeros(len(frame_t), bool)
    keep[::k] = True
    if len(keep):
        keep[-1] = True
    if k == 1:
        return np.flatnonzero(keep), raw
    j = match_to_frames(np.asarray(frame_t, np.int64), np.asarray(raw.timestamps_ns, np.int64), max_sync_s)
    return np.flatnonzero(keep), _rows(raw, (j >= 0) & keep[np.maximum(j, 0)])


def imu_fill(
    frame_t: np.ndarray,
    kept: np.ndarray,
    T_kept: np.ndarray,
    v_kept: np.ndarray,
    bias_kept: np.ndarray,
    imu: ImuData,
    config: FusionConfig,
) -> np.ndarray:
    """(N, 4, 4) T_world_body at every frame of `frame_t` from the states solved at the frames
    `kept` (M,) indices: poses T_kept (M, 4, 4), world velocities v_kept (M, 3), IMU biases
    bias_kept (M, 6) [accelerometer, gyro].  Between consecutive kept frames a < b the state
    at a is carried forward frame by frame by the IMU, with a's bias: the smoother's own
    sub-intervals (smoother.imu_subintervals; the specific force at the midpoint attitude when
    config.imu_midpoint_attitude) integrated per frame interval into dR, dv, dp (Forster et al.,
    "On-Manifold Preintegration", TRO 2017, eq. 24: dR <- dR Exp(w dt), dv <- dv + dR a dt,
    dp <- dp + dv dt + dR a dt^2 / 2) and composed with the state (eq. 31: R' = R dR,
    v' = v + g dt + R dv, p' = p + v dt + g dt^2 / 2 + R dp), vectorised over the intervals;
    the mismatch with the solved pose at b, r = Log(R_pred(b)^T R_b), dp = p_b - p_pred(b), is
    then spread linearly in frame count, s = (k - a) / (b - a) (as smoother.gyro_fill_rotations
    does): continuous at the kept frames, the IMU's curvature in between.  Without the noise
    propagation of gtsam's preintegration this is ~30x cheaper than chaining NavState
    predictions (the same poses to ~1e-9 m: tests/test_window.py).  Between kept frames where
    the IMU misses an interval, or with an IMU not at the body origin (T_body_imu), the kept
    poses are interpolated instead (PoseInterpolator)."""
    frame_t = np.asarray(frame_t, np.int64)
    kept = np.asarray(kept, np.int64)
    n = len(frame_t)
    out = PoseInterpolator(frame_t[kept], T_kept)(frame_t) if len(kept) else np.tile(np.eye(4), (n, 1, 1))
    out[kept] = T_kept
    if len(kept) == n or len(kept) < 2 or not np.allclose(imu.T_body_imu, np.eye(4)):
        return out
    covered = imu_coverage(frame_t, imu, config.max_imu_gap_s)
    k_of, dts, gyr, acc = imu_subintervals(frame_t, imu, covered)
    if config.imu_midpoint_attitude:
        acc = midpoint_specific_force(gyr, acc, dts)
    owner = np.searchsorted(kept, np.arange(n - 1), side="right") - 1  # kept interval of frame interval k
    bias = np.asarray(bias_kept, float)[owner[k_of]]
    acc, gyr = acc - bias[:, :3], gyr - bias[:, 3:]
    # per frame interval: dR, dv, dp, dt (sub-intervals of one interval are consecutive rows)
    dR = np.tile(np.eye(3), (n - 1, 1, 1))
    dv, dp, dT = np.zeros((n - 1, 3)), np.zeros((n - 1, 3)), np.zeros(n - 1)
    first = np.searchsorted(k_of, np.arange(n))
    pos = np.arange(len(k_of)) - first[k_of]
    for j in range(int(pos.max()) + 1 if len(pos) else 0):
        rows = np.flatnonzero(pos == j)
        k, dt = k_of[rows], dts[rows]
        a_nav = np.einsum("kij,kj->ki", dR[k], acc[rows])
        dp[k] += dv[k] * dt[:, None] + 0.5 * a_nav * dt[:, None] ** 2
        dv[k] += a_nav * dt[:, None]
        dR[k] = dR[k] @ so3_exp_stack(gyr[rows] * dt[:, None])
        dT[k] += dt
    g = np.array([0.0, 0.0, -GRAVITY_M_S2])
    # every frame interval of a kept interval covered: carry the state forward
    ok = np.ones(len(kept) - 1, bool)
    np.logical_and.at(ok, owner[np.flatnonzero(~covered)], False)
    ok &= np.diff(kept) >= 2
    seg = np.flatnonzero(ok)
    if not len(seg):
        return out
    a, b = kept[seg], kept[seg + 1]
    R, v, p_ = T_kept[seg, :3, :3].copy(), np.asarray(v_kept, float)[seg].copy(), T_kept[seg, :3, 3].copy()
    pred = np.empty((len(seg), int((b - a).max()), 4, 4))
    for j in range(pred.shape[1]):
        live = a + j < b
        k, dt = a[live] + j, dT[a[live] + j][:, None]
        Rl = R[live]
        p_[live] = p_[live] + v[live] * dt + 0.5 * g * dt**2 + np.einsum("kij,kj->ki", Rl, dp[k])
        v[live] = v[live] + g * dt + np.einsum("kij,kj->ki", Rl, dv[k])
        R[live] = Rl @ dR[k]
        pred[live, j, :3, :3], pred[live, j, :3, 3] = R[live], p_[live]
    # pred[:, j] is frame a + j + 1; the mismatch at b spread linearly
    r = Rotation.from_matrix(np.einsum("kji,kjl->kil", R, T_kept[seg + 1, :3, :3])).as_rotvec()
    dpos = T_kept[seg + 1, :3, 3] - p_
    for j in range(pred.shape[1] - 1):
        sel = np.flatnonzero(a + j + 1 < b)
        frac = ((j + 1) / (b[sel] - a[sel]))[:, None]
        T = np.tile(np.eye(4), (len(sel), 1, 1))
        T[:, :3, :3] = pred[sel, j, :3, :3] @ so3_exp_stack(frac * r[sel])
        T[:, :3, 3] = pred[sel, j, :3, 3] + frac * dpos[sel]
        out[a[sel] + j + 1] = T
    return out


def _states_arrays(states: gtsam.Values, a: int, b: int) -> tuple[np.ndarray, np.ndarray] | None:
    """World velocities (b - a, 3) and IMU biases (b - a, 6) [accelerometer, gyro] of frames
    [a, b) in a solve's states; None when any frame lacks one (no IMU there)."""
    try:
        v = np.array([states.atVector(V(k)) for k in range(a, b)], float).reshape(-1, 3)
        bias = np.array([states.atConstantBias(B(k)).vector() for k in range(a, b)], float).reshape(-1, 6)
    except (RuntimeError, IndexError, ValueError):
        return None
    return v, bias


def _solve_window(context: None, task: tuple) -> tuple:
    """One window of smooth_windowed: its output frames' poses [a:b] and covariances, its load
    map, floor-code map (as-built; else None), health and stats (the rest of the result is let go
    here, not sent back)."""
    solver, a, b, frame_t, imu, raw, loads, kwargs = task
    res = solver(frame_t, imu, raw, loads, **kwargs)
    cov = None if res.trajectory.covariances is None else res.trajectory.covariances[a:b]
    fixes = None
    if kwargs.get("as_built") is not None and res.floor_codes is not None:
        # the output frames' fixes, on this window's codes
        hi = int(frame_t[b]) if b < len(frame_t) else int(frame_t[-1]) + 1
        fixes = as_built_fixes(_sightings_in(kwargs["as_built"], int(frame_t[a]), hi), res.floor_codes)
    out = (res.trajectory.T_world_body[a:b], cov, res.loads, (res.floor_codes, fixes), res.health, res.stats)
    del res
    release_heap()  # the window's GTSAM heap back to the system before the next one
    return out


def _mount_window(context: tuple, task: tuple) -> tuple[MountRotation, tuple | None]:
    """One window of estimate_mount_windowed: its mount estimate and its output frames' [a:b]
    body poses, world velocities and IMU biases (_states_arrays; None when the solve gave no
    trajectory of every frame or a frame has no IMU state)."""
    floor_camera, fusion_config = context
    a, b, f_t, w_imu, w_raw, _, kw = task
    mount, traj, states = estimate_mount_and_states(
        f_t, w_imu, w_raw, kw["velocity"], floor_camera, None, fusion_config
    )
    part = None
    if traj is not None and states is not None and len(traj) == len(f_t):
        vb = _states_arrays(states, a, b)
        part = None if vb is None else (traj.T_world_body[a:b], *vb)
    del traj, states
    release_heap()
    return mount, part


def estimate_mount_windowed(
    frame_t: np.ndarray,
    imu,
    raw: Trajectory,
    velocity,
    floor_camera,
    fusion_config: FusionConfig | None = None,
    window: WindowConfig | None = None,
    workers: int = 1,
    frame_rate_hz: float | None = MOUNT_FRAME_RATE_HZ,
) -> tuple[MountRotation, Trajectory | None, gtsam.Values | None]:
    """`extrinsics.estimate_mount_and_states` (the time-offset stage's whole-flight solve, shared
    with the mount check: pipeline.SharedWholeFlight) in the windows of `smooth_windowed`, so that
    its memory is one window's.  A flight of one window is that function itself.  Otherwise each
    window estimates the mount E0 on its own fixes (disjoint information but for the overlaps'
    30 s, which the windows share: the merged sigma is therefore optimistic by at most
    sqrt(window / (window - overlap)), ~1.1 with the defaults), the estimates are merged by
    `extrinsics.merge_mount_rotations`, and the body trajectory is stitched by the same cuts as
    the smoother's; no warm-start states (the main smoother is windowed too).  A window that
    cannot be solved on its own (no fix in it) makes the whole flight one solve, as in
    `smooth_windowed`.  `workers`: processes for the windows, as in `smooth_windowed`.  Such a
    long flight is solved on every k-th floor frame only (`frame_rate_hz`, default
    MOUNT_FRAME_RATE_HZ; None: every frame; decimate_frames): the trajectory returned is at
    every frame, the others carried from the kept frames' states by the IMU (imu_fill); its
    only reader is the front camera's time-offset profile."""
    window = window or WindowConfig()
    frame_t = np.asarray(frame_t)
    plan = plan_windows(frame_t, window) if frame_t.ndim == 1 and len(frame_t) else []
    release_heap()
    if len(plan) <= 1:
        return estimate_mount_and_states(frame_t, imu, raw, velocity, floor_camera, None, fusion_config)
    # a long flight: every k-th frame (MOUNT_FRAME_RATE_HZ), its fixes only; windows planned again
    all_t = frame_t
    kept, raw = decimate_frames(
        all_t, raw, frame_rate_hz or 0.0, (fusion_config or FusionConfig()).max_sync_s
    )
    frame_t = all_t[kept]
    plan = plan_windows(frame_t, window)
    mounts: list[MountRotation] = []
    poses: list[tuple] | None = []
    tasks = (
        (
            win.out_first - win.first,
            win.out_stop - win.first,
            *_window_inputs(win, frame_t, imu, raw, None, {"velocity": velocity}),
        )
        for win in plan
    )
    context = (floor_camera, fusion_config)
    parts = parallel_map(
        _mount_window, tasks, min(workers, WINDOW_WORKERS), context, preload=("fusion.estimate.window",)
    )
    for i, win in enumerate(plan):
        try:
            mount, part = next(parts)
        except EstimationError as e:
            t_s = (int(frame_t[win.first]) - int(frame_t[0])) / _NS
            log.warning(
                "mount solve: window %d of %d (from %.1f s) not solvable on its own (%s): "
                "solving the whole flight instead",
                i + 1,
                len(plan),
                t_s,
                e,
            )
            del mounts, poses, parts
            release_heap()
            whole, traj, states = estimate_mount_and_states(
                frame_t, imu, raw, velocity, floor_camera, None, fusion_config
            )
            vb = None if states is None or traj is None else _states_arrays(states, 0, len(frame_t))
            if vb is None or traj is None or imu is None:
                return whole, None, None
            T_all = imu_fill(all_t, kept, traj.T_world_body, *vb, imu, fusion_config or FusionConfig())
            return whole, Trajectory(str(Estimator.SMOOTHER), all_t.astype(np.int64), T_all, None), None
        mounts.append(mount)
        if poses is not None and part is not None:
            poses.append(part)
        else:
            poses = None
    merged = merge_mount_rotations(mounts)
    log.info("mount solve: %d of %d frames in %d overlapping windows", len(frame_t), len(all_t), len(plan))
    if poses is None or imu is None:
        return merged, None, None
    T_all = imu_fill(
        all_t,
        kept,
        np.concatenate([p[0] for p in poses]),
        np.concatenate([p[1] for p in poses]),
        np.concatenate([p[2] for p in poses]),
        imu,
        fusion_config or FusionConfig(),
    )
    trajectory = Trajectory(str(Estimator.SMOOTHER), all_t.astype(np.int64), T_all, None)
    return merged, trajectory, None
