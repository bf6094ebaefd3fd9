"""Rolling shutter: corners timed per row, moved to the image stamp; the readout time estimated.

A rolling-shutter camera (CameraModel.line_delay_s > 0) exposes row v at
t = t_stamp + dt(v), dt(v) = line_delay_s (v - v_stamp) (`CameraModel.row_time_offset_s`).
The body moves during the readout, so a frame's corners are not one pinhole view.  Here each
corner is moved to where a global-shutter camera at the stamp would have seen it, once, where the
corners are formed; PnP, the tight corner factors and the load observations then need no change:

1. body motion over the readout, to first order: constant body rate omega (the gyro at mid
   readout, or the PnP poses' rotation rate without IMU) and a local quadratic fit of the PnP
   positions around the stamp (velocity v_world, acceleration a_world):
   T_world_body(t + dt) = [R exp(omega dt),  p + v dt + a dt^2 / 2]   (geometry.so3_exp_stack);
2. each corner's point: its ray at its row's camera pose (`camera.T_world_cam`, mount-aware),
   at the depth of the floor code's known world corner (floor codes) or of the code's apparent
   size (load codes: f side / edge length);
3. that point projected with the stamp's camera pose: the corrected corner.  Its covariance is
   kept: an error dv, dw of the motion moves a corner at row time dt by the image of dt (dv, dw),
   the same for all codes of a frame, i.e. about a pose error of dt dv (0.15 mm for 15 ms and
   0.01 m/s) -- far below PnP's own (~1 mm at 1.5 m).  Adding it per code to the (8, 8) corner
   covariance would model it as independent between codes and cost PnP 2-3x its accuracy
   (measured), so it is left out.

`correct_flight` runs PnP on the raw corners, then CORRECTION_PASSES times: motion from the
last poses, corners corrected, PnP again (the poses' RS bias only enters the depths and the
velocity fit, so one pass leaves a second-order error).  The same approach as Kalibr's
(Oth et al., "Rolling Shutter Camera Calibration", CVPR 2013) uses a continuous-time spline;
a constant twist over one readout (<= 33 ms) is its first-order case.

`calibrate_readout`: the readout time minimising the whitened PnP reprojection cost of the
flight's moving frames (golden-section search, Kiefer 1953), its sigma from the profile's
curvature, sigma^2 = 2 / cost'' (cost = chi^2 = -2 log L), scaled by chi^2_min / dof when the
corners scatter more than their covariance says.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from fusion.camera import CameraModel
from fusion.errors import EstimationError
from fusion.geometry import inv_T, so3_exp_stack, so3_log
from fusion.qr.codes import classify
from fusion.qr.pnp import DEFAULT_CORNER_SIGMA_PX, corner_whitening, estimate_floor_poses, pnp_trajectory
from fusion.types import QRDetection, Trajectory
from fusion.world import World

log_ = logging.getLogger(__name__)

CORRECTION_PASSES = 2
"""PnP -> motion -> corrected corners rounds of `correct_flight` after the first PnP."""
FIT_HALF_WINDOW = 3
"""Poses each side of a stamp in the local quadratic fit of the position (velocity)."""
FIT_MAX_SPAN_S = 0.3
"""Poses further than this from the stamp are left out of the fit."""
MIN_FIT_POSES = 3
"""Fewer poses in the window: no velocity (the frame's corners are not corrected)."""
MIN_VELOCITY_SIGMA_M_S = 0.005
"""Floor under the velocity fit's own standard deviation."""
MAX_CALIBRATION_FRAMES = 300
"""`calibrate_readout` uses at most this many frames: those whose image moves most."""
GOLDEN_TOL_S = 5e-5
"""Golden-section search stops when the bracket is narrower than this (s)."""
CURVATURE_STEP_FRACTION = 0.1
"""Step of the profile's second difference, as a fraction of the readout upper bound."""
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass
class FrameMotion:
    """Body motion at frame stamps (for one camera's frames): approximate poses (N, 4, 4), body
    rate omega_body (N, 3) rad/s, world velocity and acceleration (N, 3) and the (N, 3, 3)
    covariance of the velocity; `valid` (N,) False where no motion is known."""

    timestamps_ns: np.ndarray
    T_world_body: np.ndarray
    omega_body: np.ndarray
    v_world: np.ndarray
    a_world: np.ndarray
    v_cov: np.ndarray
    valid: np.ndarray


@dataclass
class RollingShutterReport:
    """What `correct_flight` did: per camera, frames corrected / left as they were."""

    readout_s: dict[str, float] = field(default_factory=dict)
    frames_corrected: dict[str, int] = field(default_factory=dict)
    frames_uncorrected: dict[str, int] = field(default_factory=dict)
    motion_source: str = ""

    def notes(self) -> list[str]:
        return [
            f"rolling shutter {cam}: readout {1e3 * self.readout_s[cam]:.2f} ms, corners of "
            f"{self.frames_corrected[cam]} frame(s) moved to the stamp time ({self.motion_source}); "
            f"{self.frames_uncorrected[cam]} frame(s) without a motion estimate left as read"
            for cam in self.readout_s
        ]


@dataclass
class ReadoutCalibration:
    """`calibrate_readout`'s estimate: readout time and its sigma (s), frames used, the
    chi^2 / dof at the optimum, and the profile [(readout_s, cost)] evaluated."""

    readout_s: float
    sigma_s: float
    n_frames: int
    chi2_per_dof: float
    profile: list[tuple[float, float]] = field(default_factory=list)

    def note(self, camera: str) -> str:
        return (
            f"calibrated readout of {camera}: {1e3 * self.readout_s:.2f} +- {1e3 * self.sigma_s:.2f} ms "
            f"({self.n_frames} frames, chi2/dof {self.chi2_per_dof:.2f})"
        )


# ============================================================================ motion


def _gyro_at(imu, t_s: np.ndarray) -> np.ndarray:
    """(N, 3) body rate (body frame) interpolated from the IMU at times t_s."""
    ts = imu.timestamps_ns * 1e-9
    w_imu = np.column_stack([np.interp(t_s, ts, imu.gyro_rad_s[:, i]) for i in range(3)])
    return w_imu @ np.asarray(imu.T_body_imu, float)[:3, :3].T


def frame_motion(trajectory: Trajectory, stamps_ns: np.ndarray, camera: CameraModel, imu=None) -> FrameMotion:
    """Body motion at `stamps_ns` from the poses of `trajectory` (e.g. PnP) and the IMU's gyro.

    Velocity and acceleration: a quadratic fit (least squares) of the positions of the
    2 FIT_HALF_WINDOW nearest poses within FIT_MAX_SPAN_S of the stamp; its velocity covariance
    from the fit residuals.  Body rate: the gyro at mid readout, else the rotation between the
    nearest poses either side (geometry.so3_log).  The pose at the stamp: the nearest pose moved
    by the fitted motion."""
    ts = np.asarray(trajectory.timestamps_ns, dtype=np.int64)
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    n = len(stamps_ns)
    out = FrameMotion(
        stamps_ns,
        np.tile(np.eye(4), (n, 1, 1)),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        np.tile(np.eye(3), (n, 1, 1)),
        np.zeros(n, bool),
    )
    if len(ts) < MIN_FIT_POSES:
        return out
    T = trajectory.T_world_body
    t_mid = camera.row_time_offset_s(0.5 * (camera.height - 1))  # mid readout, from the stamp (s)
    if imu is not None and len(imu.timestamps_ns) > 1:
        out.omega_body = _gyro_at(imu, stamps_ns * 1e-9 + float(t_mid))
    for k, t in enumerate(stamps_ns.tolist()):
        i = int(np.searchsorted(ts, t))
        lo, hi = max(0, i - FIT_HALF_WINDOW), min(len(ts), i + FIT_HALF_WINDOW)
        idx = np.arange(lo, hi)
        dt = (ts[idx] - t) * 1e-9
        idx, dt = idx[np.abs(dt) <= FIT_MAX_SPAN_S], dt[np.abs(dt) <= FIT_MAX_SPAN_S]
        if len(idx) < MIN_FIT_POSES or dt.min() > 0 or dt.max() < 0:
            continue  # too few poses, or all on one side (extrapolation)
        A = np.column_stack([np.ones_like(dt), dt, 0.5 * dt**2])
        coef, *_ = np.linalg.lstsq(A, T[idx, :3, 3], rcond=None)
        resid = T[idx, :3, 3] - A @ coef
        dof = len(idx) - 3
        var = float(np.sum(resid**2) / (3 * dof)) if dof > 0 else 0.0
        AtA_inv = np.linalg.pinv(A.T @ A)
        sig2 = max(var * AtA_inv[1, 1], MIN_VELOCITY_SIGMA_M_S**2)
        near = idx[int(np.argmin(np.abs(dt)))]
        R = T[near, :3, :3]
        if imu is None:
            a, b = idx[dt <= 0][-1], idx[dt >= 0][0]
            if a == b:
                a, b = (a - 1, a) if a > 0 else (a, a + 1)
            span = (ts[b] - ts[a]) * 1e-9
            if span <= 0:
                continue
            out.omega_body[k] = so3_log(T[a, :3, :3].T @ T[b, :3, :3]) / span
        # the pose at the stamp: the nearest pose's rotation turned back by the body rate
        back = float((t - ts[near]) * 1e-9)
        out.T_world_body[k, :3, :3] = R @ so3_exp_stack(out.omega_body[k][None] * back)[0]
        out.T_world_body[k, :3, 3] = coef[0]
        out.v_world[k], out.a_world[k] = coef[1], coef[2]
        out.v_cov[k] = sig2 * np.eye(3)
        out.valid[k] = True
    return out


# ============================================================================ corners


def _body_poses_at(T_world_body: np.ndarray, omega: np.ndarray, v: np.ndarray, a: np.ndarray, dt: np.ndarray):
    """(M, 4, 4) body poses at offsets dt (M,) from the stamp's T_world_body: constant body
    rate and world acceleration, R exp(omega dt), p + v dt + a dt^2 / 2."""
    out = np.tile(np.eye(4), (len(dt), 1, 1))
    out[:, :3, :3] = T_world_body[:3, :3] @ so3_exp_stack(omega[None, :] * dt[:, None])
    out[:, :3, 3] = T_world_body[:3, 3] + v * dt[:, None] + 0.5 * a * (dt**2)[:, None]
    return out


def _moved_corners(
    camera: CameraModel,
    uv: np.ndarray,
    depth_point_world: np.ndarray | None,
    depth_fallback: np.ndarray,
    T_world_body: np.ndarray,
    omega: np.ndarray,
    v: np.ndarray,
    a: np.ndarray,
) -> np.ndarray:
    """(M, 2) corners `uv` (M, 2) moved to the stamp: each ray at its row's camera pose, at the
    depth of `depth_point_world` (M, 3) (or `depth_fallback` (M,) where None/NaN), projected with
    the stamp's camera pose."""
    dt = camera.row_time_offset_s(uv[:, 1])
    T_wc_rows = camera.T_world_cam(_body_poses_at(T_world_body, omega, v, a, dt))
    depth = np.asarray(depth_fallback, float).copy()
    if depth_point_world is not None:
        T_cw_rows = inv_T(T_wc_rows)
        z = np.einsum("mj,mj->m", T_cw_rows[:, 2, :3], depth_point_world) + T_cw_rows[:, 2, 3]
        depth = np.where(np.isfinite(z) & (z > 0), z, depth)
    xn = camera.undistort_normalized(uv)
    p_cam = np.column_stack([xn, np.ones(len(xn))]) * depth[:, None]
    p_world = np.einsum("mij,mj->mi", T_wc_rows[:, :3, :3], p_cam) + T_wc_rows[:, :3, 3]
    T_cw = inv_T(camera.T_world_cam(T_world_body))
    return camera.project(p_world @ T_cw[:3, :3].T + T_cw[:3, 3])


def correct_frame(
    detections: list[QRDetection],
    camera: CameraModel,
    world: World,
    motion: FrameMotion,
    k: int,
) -> list[QRDetection]:
    """The detections of one frame (motion index k) with their corners moved to the stamp time
    (module docstring); codes that are neither floor nor load codes are returned as they were."""
    if not camera.rolling_shutter or not motion.valid[k] or not detections:
        return list(detections)
    codes = classify(detections, world)
    points: dict[int, np.ndarray] = {id(s.detection): np.asarray(s.corners_world, float) for s in codes.floor}
    sides: dict[int, float] = {id(s.detection): world.floor_side_m for s in codes.floor}
    sides.update({id(s.detection): world.load_side_m for s in codes.loads})
    T_wb, omega, v, a = motion.T_world_body[k], motion.omega_body[k], motion.v_world[k], motion.a_world[k]
    f = 0.5 * (camera.fu + camera.fv)
    out = []
    for d in detections:
        if id(d) not in sides:
            out.append(d)
            continue
        uv = np.asarray(d.corners_px, float).reshape(4, 2)
        if not np.all(np.isfinite(uv)):
            out.append(d)
            continue
        edge = float(np.mean(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1)))
        fallback = np.full(4, f * sides[id(d)] / max(edge, 1.0))
        P = points.get(id(d))
        new = _moved_corners(camera, uv, P, fallback, T_wb, omega, v, a)
        if not np.all(np.isfinite(new)):
            out.append(d)
            continue
        out.append(replace(d, corners_px=new))
    return out


def correct_frames(
    frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    motion: FrameMotion,
) -> tuple[dict[int, list[QRDetection]], int]:
    """`correct_frame` of every frame {timestamp_ns: detections} (stamps as in `motion`);
    returns the corrected frames and how many had a motion estimate."""
    index = {int(t): k for k, t in enumerate(motion.timestamps_ns.tolist())}
    out, n = {}, 0
    for ts, dets in frames.items():
        k = index.get(int(ts))
        if k is None or not motion.valid[k]:
            out[ts] = list(dets)
            continue
        out[ts] = correct_frame(dets, camera, world, motion, k)
        n += 1
    return out, n


def correct_flight(
    det,
    cameras: dict[str, CameraModel],
    world: World,
    imu=None,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    passes: int = CORRECTION_PASSES,
):
    """(DetectionResult with every rolling-shutter camera's corners moved to their frame's stamp,
    RollingShutterReport).  The motion comes from the floor camera (`cameras["cam0"]`): PnP on
    the raw corners, then `passes` rounds of motion (`frame_motion`), correction, PnP.  Other
    cameras use the same poses and gyro at their own stamps.  Without a rolling-shutter camera
    the result is `det` itself."""
    report = RollingShutterReport(motion_source="IMU gyro + PnP velocity" if imu is not None else "PnP poses")
    rs = {name: cam for name, cam in cameras.items() if cam is not None and cam.rolling_shutter}
    floor_cam = cameras.get("cam0")
    if not rs or floor_cam is None:
        return det, report
    raw_floor = det.by_frame("cam0")
    traj, _ = pnp_trajectory(raw_floor, floor_cam, world, corner_sigma_px)
    stamps = np.array(sorted(raw_floor), dtype=np.int64)
    if floor_cam.rolling_shutter:
        for _ in range(passes):
            motion = frame_motion(traj, stamps, floor_cam, imu)
            fixed, _ = correct_frames(raw_floor, floor_cam, world, motion)
            traj, _ = pnp_trajectory(fixed, floor_cam, world, corner_sigma_px)
    corrected: list[QRDetection] = []
    for name in sorted({d.camera for d in det.detections}):
        frames = det.by_frame(name)
        cam = rs.get(name)
        if cam is None:
            corrected.extend(d for ds in frames.values() for d in ds)
            continue
        stamps = np.array(sorted(frames), dtype=np.int64)
        motion = frame_motion(traj, stamps, cam, imu)
        fixed, n = correct_frames(frames, cam, world, motion)
        corrected.extend(d for ts in sorted(fixed) for d in fixed[ts])
        report.readout_s[name] = cam.readout_s
        report.frames_corrected[name] = n
        report.frames_uncorrected[name] = len(frames) - n
    for note in report.notes():
        log_.info(note)
    return replace(det, detections=corrected), report


# ============================================================================ calibration


def _frames_cost(frames: list[list], camera: CameraModel, sigma: float) -> tuple[float, int]:
    """Whitened reprojection cost (chi^2) of the PnP poses of `frames` (each a list of floor
    sightings) and its degrees of freedom (8 per code - 6 per posed frame)."""
    results = estimate_floor_poses(frames, camera, sigma)
    cost, dof = 0.0, 0
    for sightings, res in zip(frames, results):
        if res is None:
            continue
        P = np.concatenate([np.asarray(s.corners_world, float) for s in sightings])
        T_cw = inv_T(res.T_world_cam)
        pred = camera.project(P @ T_cw[:3, :3].T + T_cw[:3, 3]).reshape(-1, 8)
        z = np.concatenate([np.asarray(s.detection.corners_px, float) for s in sightings]).reshape(-1, 8)
        W = corner_whitening([s.detection for s in sightings], sigma)
        r = np.einsum("cij,cj->ci", W, z - pred)
        if res.dropped_payloads or not np.all(np.isfinite(r)):
            continue
        cost += float(np.sum(r**2))
        dof += r.size - 6
    return cost, dof


def calibrate_readout(
    det,
    camera: CameraModel,
    world: World,
    imu=None,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    max_readout_s: float | None = None,
    max_frames: int = MAX_CALIBRATION_FRAMES,
) -> ReadoutCalibration:
    """Readout time (s, whole frame) of the floor camera `camera` from a flight's floor
    detections: the minimum over [0, max_readout_s] (default: one frame period) of the whitened
    PnP reprojection cost of the up to `max_frames` frames whose image moves most, after moving
    the corners to the stamp with that readout (`correct_frame`; motion from PnP on the raw
    corners and the IMU's gyro); golden-section search; sigma from the profile's curvature.
    Raises EstimationError when too few frames are posed or the camera does not move."""
    upper = float(max_readout_s) if max_readout_s is not None else 1.0 / max(camera.rate_hz, 1e-3)
    if not upper > 0:
        raise EstimationError(f"readout search bound must be positive, got {upper!r}")
    frames = det.by_frame("cam0")
    probe = replace(camera, line_delay_s=0.0)
    traj, _ = pnp_trajectory(frames, probe, world, corner_sigma_px)
    stamps = np.array(sorted(frames), dtype=np.int64)
    # the gyro sampled half way through a readout of upper / 2
    motion = frame_motion(traj, stamps, replace(camera, line_delay_s=0.5 * upper / camera.height), imu)
    # image speed of each frame: rate plus velocity over height (px per s, roughly)
    speed = np.full(len(stamps), -1.0)
    for k in np.flatnonzero(motion.valid):
        h = max(float(motion.T_world_body[k, 2, 3]), 0.3)
        speed[k] = np.linalg.norm(motion.omega_body[k]) + np.linalg.norm(motion.v_world[k]) / h
    order = [k for k in np.argsort(-speed) if speed[k] > 0][:max_frames]
    if len(order) < MIN_FIT_POSES:
        raise EstimationError(f"readout calibration: only {len(order)} frame(s) with a motion estimate")
    chosen = [(int(stamps[k]), k) for k in sorted(order)]

    cache: dict[float, tuple[float, int]] = {}

    def cost(readout_s: float) -> float:
        if readout_s not in cache:
            cam = replace(camera, line_delay_s=readout_s / camera.height)
            views = []
            for ts, k in chosen:
                fixed = correct_frame(frames[ts], cam, world, motion, k)
                floor = classify(fixed, world).floor
                if floor:
                    views.append(floor)
            cache[readout_s] = _frames_cost(views, cam, corner_sigma_px)
        return cache[readout_s][0]

    a, b = 0.0, upper
    c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)
    fc, fd = cost(c), cost(d)
    while b - a > GOLDEN_TOL_S:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - _GOLDEN * (b - a)
            fc = cost(c)
        else:
            a, c, fc = c, d, fd
            d = a + _GOLDEN * (b - a)
            fd = cost(d)
    best = 0.5 * (a + b)
    cost(best)
    chi2, dof = cache[best]
    h = CURVATURE_STEP_FRACTION * upper
    x0 = min(max(best, h), upper - h)  # keep the stencil inside [0, upper]
    curv = (cost(x0 + h) - 2.0 * cost(x0) + cost(x0 - h)) / h**2
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    sigma = math.sqrt(2.0 * scale / curv) if curv > 0 else math.inf
    if not math.isfinite(sigma):
        log_.warning("readout calibration: flat cost profile (does the camera move?)")
    profile = sorted((x, v[0]) for x, v in cache.items())
    return ReadoutCalibration(best, sigma, len(chosen), chi2 / dof if dof > 0 else math.nan, profile)
