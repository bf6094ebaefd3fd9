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

CORRECTION_PASSES = 4
"""PnP -> motion -> corrected corners rounds of `correct_flight` after the first PnP."""
FIT_HALF_WINDOW = 8
"""Poses each side of a stamp in the local quadratic fit of the position (velocity)."""
FIT_MAX_SPAN_S = 0.5
"""Poses further than this from the stamp are left out of the fit."""
MIN_FIT_POSES = 3
FIT_DEGREE = 2
"""Degree of the local polynomial fit of the positions (2: velocity and acceleration)."""
FIT_ROBUST_ROUNDS = 3
FIT_TRIM_MAD = 3.0
FIT_TRIM_MIN_M = 0.003
"""Trimmed fit: poses further than FIT_TRIM_MAD robust sigmas (at least FIT_TRIM_MIN_M) from the
fit are left out, up to FIT_ROBUST_ROUNDS times."""
"""Fewer poses in the window: no velocity (the frame's corners are not corrected)."""
MIN_VELOCITY_SIGMA_M_S = 0.005
"""Floor under the velocity fit's own standard deviation."""
MAX_CALIBRATION_FRAMES = 300
"""`calibrate_readout` uses at most this many frames: those whose image moves most."""
CALIBRATION_ROUNDS = 2
"""`calibrate_readout`: motion re-estimated with the previous estimate this many times."""
CALIBRATION_BLOCKS = 6
"""Contiguous blocks of frames whose minima's spread gives the readout's sigma (a lower bound)."""
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
        A = np.column_stack([dt**j / math.factorial(j) for j in range(FIT_DEGREE + 1)])
        keep = np.ones(len(idx), bool)
        for _ in range(FIT_ROBUST_ROUNDS):  # trimmed least squares: PnP has outlier poses
            coef, *_ = np.linalg.lstsq(A[keep], T[idx[keep], :3, 3], rcond=None)
            r = np.linalg.norm(T[idx, :3, 3] - A @ coef, axis=1)
            scale = max(FIT_TRIM_MAD * 1.4826 * float(np.median(r[keep])), FIT_TRIM_MIN_M)
            new_keep = r <= scale
            if new_keep.sum() < FIT_DEGREE + 2 or np.array_equal(new_keep, keep):
                break
            keep = new_keep
        A, idx, dt = A[keep], idx[keep], dt[keep]
        coef, *_ = np.linalg.lstsq(A, T[idx, :3, 3], rcond=None)
        resid = T[idx, :3, 3] - A @ coef
        dof = len(idx) - FIT_DEGREE - 1
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
        out.v_world[k], out.a_world[k] = coef[1], coef[2] if FIT_DEGREE >= 2 else 0.0
        out.v_cov[k] = sig2 * np.eye(3)
        out.valid[k] = True
    return out


# ============================================================================ corners


def _body_poses_at(T_world_body: np.ndarray, omega: np.ndarray, v: np.ndarray, a: np.ndarray, dt: np.ndarray):
    """(M, 4, 4) body poses at offsets dt (M,) from the stamp poses T_world_body (M, 4, 4):
    constant body rate omega (M, 3) and world acceleration, R exp(omega dt), p + v dt + a dt^2/2."""
    out = np.tile(np.eye(4), (len(dt), 1, 1))
    out[:, :3, :3] = T_world_body[:, :3, :3] @ so3_exp_stack(omega * dt[:, None])
    out[:, :3, 3] = T_world_body[:, :3, 3] + v * dt[:, None] + 0.5 * a * (dt**2)[:, None]
    return out


@dataclass
class CornerBatch:
    """Corners of many detections, stacked (M = 4 per detection): observed px uv (M, 2), their
    normalised rays xn (M, 2), the known world point P (M, 3) (NaN for load codes), the
    size-implied depth (M,), the motion index of their frame (M,); `where` [(timestamp_ns,
    position in the frame)] per detection."""

    uv: np.ndarray
    xn: np.ndarray
    P: np.ndarray
    depth_fallback: np.ndarray
    k: np.ndarray
    where: list[tuple[int, int]]

    def moved(self, camera: CameraModel, motion: FrameMotion) -> np.ndarray:
        """(M, 2) corners moved to their frame's stamp (module docstring, steps 1-3): each ray at
        its row's camera pose, at the depth of its world point (else the size-implied depth),
        projected with the stamp's camera pose."""
        k = self.k
        T_wb = motion.T_world_body[k]
        dt = camera.row_time_offset_s(self.uv[:, 1])
        T_wc_rows = camera.T_world_cam(
            _body_poses_at(T_wb, motion.omega_body[k], motion.v_world[k], motion.a_world[k], dt)
        )
        T_cw_rows = inv_T(T_wc_rows)
        with np.errstate(invalid="ignore"):
            z = np.einsum("mj,mj->m", T_cw_rows[:, 2, :3], self.P) + T_cw_rows[:, 2, 3]
        depth = np.where(np.isfinite(z) & (z > 0), z, self.depth_fallback)
        p_cam = np.column_stack([self.xn, np.ones(len(self.xn))]) * depth[:, None]
        p_world = np.einsum("mij,mj->mi", T_wc_rows[:, :3, :3], p_cam) + T_wc_rows[:, :3, 3]
        T_cw = inv_T(camera.T_world_cam(T_wb))
        p_stamp = np.einsum("mij,mj->mi", T_cw[:, :3, :3], p_world) + T_cw[:, :3, 3]
        return camera.project(p_stamp)


def corner_batch(
    frames: dict[int, list[QRDetection]], camera: CameraModel, world: World, motion: FrameMotion
) -> CornerBatch:
    """The floor and load codes' corners of the frames that have a motion estimate, stacked."""
    index = {int(t): k for k, t in enumerate(motion.timestamps_ns.tolist())}
    f = 0.5 * (camera.fu + camera.fv)
    uv, P, fallback, ks, where = [], [], [], [], []
    for ts, dets in frames.items():
        k = index.get(int(ts))
        if k is None or not motion.valid[k]:
            continue
        codes = classify(dets, world)
        known = {id(s.detection): np.asarray(s.corners_world, float) for s in codes.floor}
        sides = {id(s.detection): world.floor_side_m for s in codes.floor}
        sides.update({id(s.detection): world.load_side_m for s in codes.loads})
        for i, d in enumerate(dets):
            c = np.asarray(d.corners_px, float).reshape(4, 2)
            if id(d) not in sides or not np.all(np.isfinite(c)):
                continue
            edge = float(np.mean(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)))
            uv.append(c)
            P.append(known.get(id(d), np.full((4, 3), np.nan)))
            fallback.append(np.full(4, f * sides[id(d)] / max(edge, 1.0)))
            ks.append(np.full(4, k))
            where.append((int(ts), i))
    if not uv:
        e = np.zeros((0, 2))
        return CornerBatch(e, e, np.zeros((0, 3)), np.zeros(0), np.zeros(0, int), [])
    uv_all = np.concatenate(uv)
    return CornerBatch(
        uv_all,
        camera.undistort_normalized(uv_all),
        np.concatenate(P),
        np.concatenate(fallback),
        np.concatenate(ks),
        where,
    )


def apply_corners(
    frames: dict[int, list[QRDetection]], batch: CornerBatch, corners_px: np.ndarray
) -> dict[int, list[QRDetection]]:
    """`frames` with the batch's detections given `corners_px` (M, 2) (non-finite ones kept)."""
    out = {ts: list(dets) for ts, dets in frames.items()}
    new = corners_px.reshape(-1, 4, 2)
    for (ts, i), c in zip(batch.where, new):
        if np.all(np.isfinite(c)):
            out[ts][i] = replace(out[ts][i], corners_px=c)
    return out


def correct_frames(
    frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    motion: FrameMotion,
) -> tuple[dict[int, list[QRDetection]], int]:
    """Every frame {timestamp_ns: detections} with its floor and load codes' corners moved to the
    stamp time (module docstring; stamps as in `motion`); other codes, and frames without a
    motion estimate, as they were.  Also returns how many frames had a motion estimate."""
    if not camera.rolling_shutter:
        return {ts: list(d) for ts, d in frames.items()}, 0
    batch = corner_batch(frames, camera, world, motion)
    index = {int(t): k for k, t in enumerate(motion.timestamps_ns.tolist())}
    n = sum(1 for ts in frames if index.get(int(ts)) is not None and motion.valid[index[int(ts)]])
    return apply_corners(frames, batch, batch.moved(camera, motion)), n


def corrected_trajectory(
    floor_frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    imu=None,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    passes: int = CORRECTION_PASSES,
) -> Trajectory:
    """PnP trajectory of the floor frames {timestamp_ns: detections} with their corners moved
    to the stamp: PnP on the raw corners, then `passes` rounds of motion (`frame_motion`),
    correction, PnP (the raw poses' rolling-shutter errors bias the first velocity fit; each
    round roughly halves what is left, measured)."""
    traj, _ = pnp_trajectory(floor_frames, camera, world, corner_sigma_px)
    if not camera.rolling_shutter:
        return traj
    stamps = np.array(sorted(floor_frames), dtype=np.int64)
    for _ in range(passes):
        motion = frame_motion(traj, stamps, camera, imu)
        fixed, _ = correct_frames(floor_frames, camera, world, motion)
        traj, _ = pnp_trajectory(fixed, camera, world, corner_sigma_px)
    return traj


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
    traj = corrected_trajectory(det.by_frame("cam0"), floor_cam, world, imu, corner_sigma_px, passes)
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


def _frames_cost(frames: list[list], camera: CameraModel, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Whitened reprojection cost (chi^2) of the PnP pose of each of `frames` (each a list of
    floor sightings) and its degrees of freedom (8 per code - 6; 0, 0 for an unposed frame or
    one with a code left out)."""
    results = estimate_floor_poses(frames, camera, sigma)
    cost, dof = np.zeros(len(frames)), np.zeros(len(frames), dtype=int)
    for i, (sightings, res) in enumerate(zip(frames, results)):
        if res is None or res.dropped_payloads:
            continue
        P = np.concatenate([np.asarray(s.corners_world, float) for s in sightings])
        T_cw = inv_T(res.T_world_cam)
        pred = camera.project(P @ T_cw[:3, :3].T + T_cw[:3, 3]).reshape(-1, 8)
        z = np.concatenate([np.asarray(s.detection.corners_px, float) for s in sightings]).reshape(-1, 8)
        W = corner_whitening([s.detection for s in sightings], sigma)
        r = np.einsum("cij,cj->ci", W, z - pred)
        if np.all(np.isfinite(r)):
            cost[i], dof[i] = float(np.sum(r**2)), r.size - 6
    return cost, dof


def calibrate_readout(
    det,
    camera: CameraModel,
    world: World,
    imu=None,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    max_readout_s: float | None = None,
    max_frames: int = MAX_CALIBRATION_FRAMES,
    rounds: int = CALIBRATION_ROUNDS,
) -> ReadoutCalibration:
    """Readout time (s, whole frame) of the floor camera `camera` from a flight's floor
    detections: the minimum over [0, max_readout_s] (default: one frame period) of the whitened
    PnP reprojection cost of the up to `max_frames` frames whose image moves most, after moving
    the corners to the stamp with that readout (`correct_frames`); golden-section search; sigma
    from the profile's curvature.  The motion comes from the poses corrected with the previous
    round's estimate (the first round: the camera's own readout, usually 0, i.e. raw PnP),
    `rounds` times.  Raises EstimationError when too few frames have a motion estimate."""
    upper = float(max_readout_s) if max_readout_s is not None else 1.0 / max(camera.rate_hz, 1e-3)
    if not upper > 0:
        raise EstimationError(f"readout search bound must be positive, got {upper!r}")
    frames = det.by_frame("cam0")
    stamps = np.array(sorted(frames), dtype=np.int64)
    readout = min(camera.readout_s, upper)
    result = None
    for _ in range(max(rounds, 1)):
        cam = replace(camera, line_delay_s=readout / camera.height)
        traj = corrected_trajectory(frames, cam, world, imu, corner_sigma_px)
        result = _golden_readout(
            frames,
            stamps,
            frame_motion(traj, stamps, cam, imu),
            camera,
            world,
            imu,
            corner_sigma_px,
            upper,
            max_frames,
        )
        readout = result.readout_s
    assert result is not None
    return result


def _golden_readout(frames, stamps, motion: FrameMotion, camera, world, imu, sigma_px, upper, max_frames):
    """One round of `calibrate_readout` with a fixed motion estimate."""
    # image speed of each frame: rate plus velocity over height (rad/s, roughly)
    speed = np.full(len(stamps), -1.0)
    for k in np.flatnonzero(motion.valid):
        h = max(float(motion.T_world_body[k, 2, 3]), 0.3)
        speed[k] = np.linalg.norm(motion.omega_body[k]) + np.linalg.norm(motion.v_world[k]) / h
    order = [k for k in np.argsort(-speed) if speed[k] > 0][:max_frames]
    if len(order) < MIN_FIT_POSES:
        raise EstimationError(f"readout calibration: only {len(order)} frame(s) with a motion estimate")
    chosen = {int(stamps[k]): frames[int(stamps[k])] for k in sorted(order)}
    batch = corner_batch(chosen, camera, world, motion)
    cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def per_frame(readout_s: float) -> tuple[np.ndarray, np.ndarray]:
        if readout_s not in cache:
            cam = replace(camera, line_delay_s=readout_s / camera.height)
            fixed = apply_corners(chosen, batch, batch.moved(cam, motion))
            views = [classify(fixed[ts], world).floor for ts in chosen]
            cache[readout_s] = _frames_cost(views, cam, sigma_px)
        return cache[readout_s]

    def cost(readout_s: float) -> float:
        return float(per_frame(readout_s)[0].sum())

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
    chi2, dof = float(per_frame(best)[0].sum()), int(per_frame(best)[1].sum())
    h = CURVATURE_STEP_FRACTION * upper
    x0 = min(max(best, h), upper - h)  # keep the stencil inside [0, upper]
    stencil = [per_frame(x)[0] for x in (x0 - h, x0, x0 + h)]
    curv = (stencil[2].sum() - 2.0 * stencil[1].sum() + stencil[0].sum()) / h**2
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    sigma = math.sqrt(2.0 * scale / curv) if curv > 0 else math.inf
    # the frames' errors are not independent (the motion estimate is shared by neighbours):
    # the spread of the minima of CALIBRATION_BLOCKS contiguous blocks (their parabolas through
    # the stencil) bounds sigma from below, sigma_blocks = std / sqrt(blocks)
    minima = []
    for block in np.array_split(np.arange(len(chosen)), CALIBRATION_BLOCKS):
        c0, c1, c2 = (float(st[block].sum()) for st in stencil)
        cb = (c2 - 2.0 * c1 + c0) / h**2
        if cb > 0:
            minima.append(x0 - (c2 - c0) / (2.0 * h) / cb)
    if len(minima) > 1:
        sigma = max(sigma, float(np.std(minima, ddof=1)) / math.sqrt(len(minima)))
    if not math.isfinite(sigma):
        log_.warning("readout calibration: flat cost profile (does the camera move?)")
    profile = sorted((x, float(v[0].sum())) for x, v in cache.items())
    return ReadoutCalibration(best, sigma, len(chosen), chi2 / dof if dof > 0 else math.nan, profile)
