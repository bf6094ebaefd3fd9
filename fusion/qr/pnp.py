"""Our per-frame estimator (not the paper's): PnP on every floor code in view, with covariance.

Floor camera (cam0): all floor codes of a frame are solved at once (4 known world corners each),
initialised by IPPE (one code: IPPE_SQUARE, both of its two-fold solutions; several codes: planar
IPPE and SQPnP), refined by Levenberg–Marquardt on the reprojection error in DISTORTED pixels
(fusion/qr/crb.py's model), and given the covariance sigma^2 (J^T J)^-1 of that model.

Front camera (cam1): each load code's pose in the camera from its four corners (IPPE_SQUARE, side
world.load_side_m), refined the same way; its centre p_cam with covariance, and p_world with the
drone pose's covariance propagated to first order.

Pose covariances: 6x6, GTSAM Pose3 tangent order [rx, ry, rz, tx, ty, tz] (rad, m), BODY frame,
right perturbation T = T_hat * Exp(xi) (gtsam.Pose3.Expmap) -- ready for a PriorFactorPose3.

Where this departs from the paper (Alg. 1-3, 4-6): the paper uses the single code nearest the image
centre and assumes a level camera; we use all codes in view and estimate the full 6-DOF pose.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fusion.camera import CameraModel
from fusion.conventions import (inv_T, make_T, rot_z, symbol_corners_S, transform_points,
                                wrap_angle, yaw_of)
from fusion.errors import EstimationError
from fusion.qr.codes import FloorSighting, LoadSighting, classify, rejection_counts
from fusion.qr.crb import (covariance_from_jacobian, floor_reprojection, se3_exp, so3_exp,
                           symbol_reprojection)
from fusion.types import LoadEstimate, LoadMap, LoadObservation, QRDetection, Trajectory
from fusion.world import World

DEFAULT_CORNER_SIGMA_PX = 0.15
"""Refined-corner error per pixel coordinate (DESIGN.md: about 0.13 px mean after refinement)."""
GIMBAL_ROLL_PITCH_SIGMA_RAD = math.radians(10.0)
"""Standard deviation given to the (unobserved) airframe roll and pitch with a gimbaled camera."""
MAX_REPROJECTION_RMS_PX = 2.0
"""A solution whose corner reprojection RMS exceeds this is treated as an outlier."""
AMBIGUITY_CHI2 = 4.0
"""Two solutions whose summed squared residuals differ by less than this * sigma^2 are ambiguous;
the more level one is taken (a multirotor rarely tilts more than 30 deg)."""
MAX_YAW_DEVIATION_RAD = math.pi / 2
"""A candidate whose yaw is further than this from the yaw implied by the codes' edges is wrong."""


@dataclass
class PnPResult:
    """Body pose of one floor-camera frame.

    `T_world_body` (4, 4); `covariance` (6, 6) [rx, ry, rz, tx, ty, tz], body frame, right
    perturbation; `T_world_cam` (4, 4); `reprojection_rms_px` over all corners used (distorted px).
    `ambiguous`: two solutions fitted the corners equally well and the more level one was taken.
    `dropped_payloads`: codes left out as outliers (their corners did not fit the others)."""
    T_world_body: np.ndarray
    covariance: np.ndarray
    T_world_cam: np.ndarray
    n_codes: int
    payloads: list[str]
    reprojection_rms_px: float
    ambiguous: bool = False
    dropped_payloads: list[str] = field(default_factory=list)


# ============================================================================ small helpers


def _tilt_rad(R_world_body: np.ndarray) -> float:
    """Angle between body z and world z (rad)."""
    return float(np.arccos(np.clip(R_world_body[2, 2], -1.0, 1.0)))


def level_frame(T_world_body: np.ndarray) -> np.ndarray:
    """The body frame with roll and pitch removed: same origin, z = world z, same yaw."""
    return make_T(rot_z(float(yaw_of(T_world_body[:3, :3]))), T_world_body[:3, 3])


def camera_pose(T_world_body: np.ndarray, camera: CameraModel) -> np.ndarray:
    """T_world_cam: T_world_body * T_body_cam, with the level frame for a "gimbaled" camera."""
    T = level_frame(T_world_body) if camera.mount == "gimbaled" else T_world_body
    return T @ camera.T_body_cam


def _same_pose(T_a: np.ndarray, T_b: np.ndarray, tol_rad: float, tol_m: float) -> bool:
    R = T_a[:3, :3].T @ T_b[:3, :3]
    angle = math.acos(max(-1.0, min(1.0, 0.5 * (np.trace(R) - 1.0))))
    return angle <= tol_rad and float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])) <= tol_m


def _cv_points(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 1, a.shape[-1]))


def _levenberg_marquardt(x0, residual_and_jacobian, retract, max_iter: int = 30):
    """Minimise |r(x)|^2 over a manifold; returns (x, r, J) at the optimum.

    `residual_and_jacobian(x) -> (r (m,), J (m, 6))`, `retract(x, delta) -> x'`."""
    x = x0
    r, J = residual_and_jacobian(x)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return x, r, J
    cost = float(r @ r)
    lam = 1e-4
    for _ in range(max_iter):
        H, g = J.T @ J, J.T @ r
        try:
            delta = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
        except np.linalg.LinAlgError:
            break
        x_new = retract(x, delta)
        r_new, J_new = residual_and_jacobian(x_new)
        cost_new = float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
        if cost_new <= cost:
            converged = cost - cost_new <= 1e-10 * cost or np.max(np.abs(delta)) < 1e-10
            x, r, J, cost = x_new, r_new, J_new, cost_new
            lam = max(lam * 0.1, 1e-10)
            if converged:
                break
        else:
            lam *= 10.0
            if lam > 1e6:
                break
    return x, r, J


def corner_whitening(detections, default_sigma_px: float) -> np.ndarray:
    """(n, 8, 8) whitening matrices W_i = L_i^-1 of each detection's corner covariance
    C_i = L_i L_i^T (Cholesky; order TL u, TL v, TR u, ..., BL v), so that W_i (z_i - h_i) has
    identity covariance: `corner_cov_px2` when set and positive definite (the corners come from
    one homography fit, so their errors are correlated), else diag(1 / sigma^2) with sigma the
    detection's `corner_sigma_px` or `default_sigma_px` (`corner_sigmas`)."""
    sig = corner_sigmas(detections, default_sigma_px).reshape(-1, 8)
    out = np.zeros((len(sig), 8, 8))
    for i, d in enumerate(detections):
        C = getattr(d, "corner_cov_px2", None)
        if C is not None:
            C = np.asarray(C, dtype=float)
            if C.shape == (8, 8) and np.all(np.isfinite(C)):
                try:
                    out[i] = np.linalg.inv(np.linalg.cholesky(0.5 * (C + C.T)))
                    continue
                except np.linalg.LinAlgError:
                    pass
        out[i] = np.diag(1.0 / sig[i])
    return out


def _whiten(W: np.ndarray, r: np.ndarray, J: np.ndarray | None = None):
    """Block-diagonal whitening: r (8n,) and J (8n, k) -> W_i r_i, W_i J_i per block of 8."""
    n = len(W)
    rw = (W @ r.reshape(n, 8, 1)).reshape(-1)
    if J is None:
        return rw
    return rw, (W @ J.reshape(n, 8, -1)).reshape(8 * n, -1)


def corner_sigmas(detections, default_sigma_px: float) -> np.ndarray:
    """Per-residual 1-sigma (8 per detection: x, y of its 4 corners), px: each detection's own
    `corner_sigma_px` when it has one (fusion.qr.refine's calibrated value), else the default."""
    out = []
    for d in detections:
        s = getattr(d, "corner_sigma_px", None)
        s = float(s) if s is not None and math.isfinite(s) and s > 0 else float(default_sigma_px)
        out.append(np.full(8, s))
    return np.concatenate(out) if out else np.zeros(0)


def _refine_body_pose(camera: CameraModel, T_world_body: np.ndarray, points_world: np.ndarray,
                      uv_obs: np.ndarray, whitening: np.ndarray | None = None):
    """LM on the distorted-pixel reprojection error over the body pose (right perturbation),
    whitened per code by `whitening` (n, 8, 8) when given (`corner_whitening`)."""
    z = uv_obs.reshape(-1)

    def rj(T):
        uv, J = floor_reprojection(camera, T, points_world)
        r = uv.reshape(-1) - z
        return (r, J) if whitening is None else _whiten(whitening, r, J)

    return _levenberg_marquardt(T_world_body, rj, lambda T, d: T @ se3_exp(d))


def _refine_symbol_pose(camera: CameraModel, T_cam_symbol: np.ndarray, points_symbol: np.ndarray,
                        uv_obs: np.ndarray, whitening: np.ndarray):
    """LM on the whitened (`whitening` (1, 8, 8)) distorted-pixel reprojection error over a code's
    pose in the camera."""
    z = uv_obs.reshape(-1)

    def rj(T):
        uv, J = symbol_reprojection(camera, T, points_symbol)
        return _whiten(whitening, uv.reshape(-1) - z, J)

    def retract(T, d):
        return make_T(T[:3, :3] @ so3_exp(d[:3]), T[:3, 3] + d[3:])

    return _levenberg_marquardt(T_cam_symbol, rj, retract)


# ============================================================================ floor camera


def edge_implied_yaw(sightings: list[FloorSighting], camera: CameraModel) -> float | None:
    """Body yaw (rad) implied by the floor codes' edge directions in the image, assuming a level body.

    Each code's corners are cast onto a floor below a level body at yaw 0; the symbol's "right"
    (TL->TR, BL->BR) and its "up" turned by -90 deg (BL->TL, BR->TR) give the direction of world +x
    in that frame, at angle a, so the yaw is -a.  A tilt of up to 30 deg moves this by far less
    than 90 deg, which is what rules out 180-deg yaw flips.  None if no code's rays meet the floor."""
    R_body_cam = camera.T_body_cam[:3, :3]
    e = np.zeros(2)
    for s in sightings:
        xn = camera.undistort_normalized(np.asarray(s.detection.corners_px, dtype=float))
        d = np.column_stack([xn, np.ones(4)]) @ R_body_cam.T
        if not np.all(np.isfinite(d)) or np.any(d[:, 2] > -1e-6):
            continue
        tl, tr, br, bl = d[:, :2] / (-d[:, 2:3])
        up = (tl - bl) + (tr - br)
        e += (tr - tl) + (br - bl) + np.array([up[1], -up[0]])
    if not np.any(e):
        return None
    return float(-math.atan2(e[1], e[0]))


def _initial_camera_poses(sightings: list[FloorSighting], camera: CameraModel) -> list[np.ndarray]:
    """Candidate T_cam_world from IPPE (both solutions) and, with >= 2 codes, SQPnP."""
    pts_w = np.vstack([s.corners_world for s in sightings])
    xn = camera.undistort_normalized(np.vstack([s.detection.corners_px for s in sightings]))
    if not np.all(np.isfinite(xn)):
        return []
    if len(sightings) == 1:
        origin = np.asarray(sightings[0].centre_world, dtype=float)
        obj = pts_w - origin        # floor symbol frame = world axes, so this is IPPE_SQUARE's order
        methods = [cv2.SOLVEPNP_IPPE_SQUARE]
    else:
        origin = pts_w.mean(axis=0)
        obj = pts_w - origin
        methods = [cv2.SOLVEPNP_IPPE, cv2.SOLVEPNP_SQPNP]
    out = []
    for method in methods:
        try:
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(_cv_points(obj), _cv_points(xn), np.eye(3),
                                                     None, flags=method)
        except cv2.error:
            continue
        for rv, tv in zip(rvecs[:n], tvecs[:n]):
            T_cam_obj = make_T(cv2.Rodrigues(np.asarray(rv, dtype=float))[0], np.ravel(tv))
            out.append(T_cam_obj @ make_T(np.eye(3), -origin))
    return out


def _solve_floor(sightings: list[FloorSighting], camera: CameraModel, sigma: float,
                 ambiguity_chi2: float):
    """Best refined body pose for these sightings: (T_world_body, r, J, ambiguous) or None.
    r and J are WHITENED per code (`corner_whitening`, default sigma `sigma`)."""
    wht = corner_whitening([s.detection for s in sightings], sigma)
    pts_w = np.vstack([s.corners_world for s in sightings])
    uv = np.vstack([np.asarray(s.detection.corners_px, dtype=float) for s in sightings])
    yaw_hint = edge_implied_yaw(sightings, camera)
    T_cam_body = inv_T(camera.T_body_cam)
    starts: list[np.ndarray] = []
    for T_cam_world in _initial_camera_poses(sightings, camera):
        T0 = inv_T(T_cam_world) @ inv_T(T_cam_body)
        if not any(_same_pose(T0, S, 1e-3, 1e-3) for S in starts):   # SQPnP often = one IPPE
            starts.append(T0)
    # A start that fits far worse than the best one is a rejected mirror solution: skip its refinement.
    rms0 = [float(np.sqrt(np.nanmean((floor_reprojection(camera, T0, pts_w)[0] - uv) ** 2)))
            for T0 in starts]
    best0 = min(rms0, default=np.inf)
    cands = []
    for T0, e0 in zip(starts, rms0):
        if not e0 <= 5.0 * best0 + 5.0 * sigma:
            continue
        T, r, J = _refine_body_pose(camera, T0, pts_w, uv, wht)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
            continue
        if (T @ camera.T_body_cam)[2, 3] <= 0.0:     # under the floor: a mirrored corner order
            continue
        if yaw_hint is not None and \
                abs(wrap_angle(yaw_of(T[:3, :3]) - yaw_hint)) > MAX_YAW_DEVIATION_RAD:
            continue
        if any(_same_pose(T, c[0], 1e-7, 1e-7) for c in cands):
            continue
        cands.append((T, r, J, float(r @ r)))
    if not cands:
        return None
    best_sse = min(c[3] for c in cands)
    close = [c for c in cands if c[3] <= best_sse + ambiguity_chi2]     # whitened: chi^2 units
    T, r, J, _ = min(close, key=lambda c: _tilt_rad(c[0][:3, :3]))
    return T, r, J, len(close) > 1


def estimate_floor_pose(sightings: list[FloorSighting], camera: CameraModel,
                        corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, *,
                        max_rms_px: float = MAX_REPROJECTION_RMS_PX,
                        ambiguity_chi2: float = AMBIGUITY_CHI2,
                        gimbal_roll_pitch_sigma_rad: float = GIMBAL_ROLL_PITCH_SIGMA_RAD
                        ) -> PnPResult | None:
    """Body pose from all floor codes of one floor-camera frame, or None (no code, no solution,
    or reprojection RMS above `max_rms_px` even after leaving out the worst-fitting codes).

    1. corners undistorted (CameraModel.undistort_normalized); IPPE / SQPnP candidates;
    2. each refined by LM on the reprojection error in distorted pixels over the body pose;
    3. candidates whose yaw is > 90 deg from `edge_implied_yaw` are dropped (no 180-deg flips);
       of those whose squared error is within `ambiguity_chi2` sigma^2 of the best, the most level;
    4. covariance (J^T W J)^-1, J = d(distorted px)/d(xi), xi the body-frame right
       perturbation [rx, ry, rz, tx, ty, tz] (GTSAM Pose3; fusion/qr/crb.py), W block-diagonal
       with one (8, 8) block C_i^-1 per code: C_i the detection's `corner_cov_px2` when set (its
       corners come from one homography fit, so their errors are correlated), else
       sigma_i^2 I with sigma_i its `corner_sigma_px`, else `corner_sigma_px`; the LM of step 2
       minimises the same weighted error.

    "gimbaled" camera: the camera is stabilised, so the airframe's roll and pitch are not observed.
    The returned T_world_body is then the LEVEL body frame (roll = pitch = 0, estimated yaw and
    position), and its covariance keeps the PnP marginal of [rz, tx, ty, tz] while rx and ry get
    variance gimbal_roll_pitch_sigma_rad^2 ((10 deg)^2 by default) and no correlation."""
    sightings = list(sightings)
    dropped: list[str] = []
    sigma = float(corner_sigma_px)
    if not sigma > 0:
        raise EstimationError(f"corner_sigma_px must be positive, got {corner_sigma_px!r}")
    while sightings:
        sol = _solve_floor(sightings, camera, sigma, ambiguity_chi2)
        if sol is None:
            return None
        T, _, J, ambiguous = sol
        pts_w = np.vstack([s.corners_world for s in sightings])
        uv = np.vstack([np.asarray(s.detection.corners_px, dtype=float) for s in sightings])
        r = (floor_reprojection(camera, T, pts_w)[0] - uv).reshape(-1)   # px, for the outlier test
        rms = float(np.sqrt(np.mean(r ** 2)))
        if rms <= max_rms_px:
            break
        if len(sightings) < 2:
            return None
        per_code = (r.reshape(len(sightings), 8) ** 2).sum(axis=1)
        worst = int(np.argmax(per_code))
        dropped.append(sightings[worst].detection.payload)
        del sightings[worst]
    else:
        return None
    try:
        cov = covariance_from_jacobian(J, 1.0)       # J whitened: (J^T W J)^-1
    except EstimationError:
        return None
    T_world_cam = T @ camera.T_body_cam
    if camera.mount == "gimbaled":
        T = level_frame(T)
        keep = np.diag([0.0, 0.0, 1.0, 1.0, 1.0, 1.0])
        cov = keep @ cov @ keep + np.diag([gimbal_roll_pitch_sigma_rad ** 2] * 2 + [0.0] * 4)
    return PnPResult(T_world_body=T, covariance=cov, T_world_cam=T_world_cam,
                     n_codes=len(sightings), payloads=[s.detection.payload for s in sightings],
                     reprojection_rms_px=rms, ambiguous=ambiguous, dropped_payloads=dropped)


# ============================================================================ front camera


def _numerical_jacobian(f, x_dim: int, h: float = 1e-6) -> np.ndarray:
    cols = []
    for k in range(x_dim):
        d = np.zeros(x_dim)
        d[k] = h
        cols.append((f(d) - f(-d)) / (2.0 * h))
    return np.column_stack(cols)


def estimate_load_observations(sightings: list[LoadSighting], camera: CameraModel, world: World,
                               T_world_body: np.ndarray, cov_body: np.ndarray | None = None,
                               corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, *,
                               max_rms_px: float = MAX_REPROJECTION_RMS_PX,
                               ambiguity_chi2: float = AMBIGUITY_CHI2) -> list[LoadObservation]:
    """One LoadObservation per load code of one front-camera frame whose corners fit a square of
    side world.load_side_m (reprojection RMS <= max_rms_px; others are skipped).

    p_cam (3,) = the code centre in the camera frame (m) from IPPE_SQUARE + LM in distorted pixels,
    cov_cam (3, 3) = the centre block of (J^T C^-1 J)^-1 (fusion/qr/crb.symbol_reprojection),
    C the detection's `corner_cov_px2`, else sigma^2 I with sigma its `corner_sigma_px`, else
    `corner_sigma_px` (the LM minimises the same weighted error);
    p_world = T_world_cam p_cam with T_world_cam = camera_pose(T_world_body, camera), and
    cov_world = R_world_cam cov_cam R_world_cam^T + J_b cov_body J_b^T, J_b = d p_world / d xi
    for the body-frame right perturbation xi of T_world_body (cov_body None: drone pose exact).
    IPPE's two-fold ambiguity barely moves the centre; when both fit, the one whose symbol "up"
    is nearer world +z is taken (load codes hang on vertical faces, up = +z)."""
    sigma = float(corner_sigma_px)
    T_world_body = np.asarray(T_world_body, dtype=float)
    T_world_cam = camera_pose(T_world_body, camera)
    R_wc = T_world_cam[:3, :3]
    corners_S = symbol_corners_S(world.load_side_m)
    out = []
    for s in sightings:
        wht = corner_whitening([s.detection], sigma)
        uv = np.asarray(s.detection.corners_px, dtype=float)
        xn = camera.undistort_normalized(uv)
        if uv.shape != (4, 2) or not np.all(np.isfinite(xn)):
            continue
        try:
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(_cv_points(corners_S), _cv_points(xn),
                                                     np.eye(3), None,
                                                     flags=cv2.SOLVEPNP_IPPE_SQUARE)
        except cv2.error:
            continue
        cands = []
        for rv, tv in zip(rvecs[:n], tvecs[:n]):
            T0 = make_T(cv2.Rodrigues(np.asarray(rv, dtype=float))[0], np.ravel(tv))
            T, r, J = _refine_symbol_pose(camera, T0, corners_S, uv, wht)
            if np.all(np.isfinite(r)) and np.all(np.isfinite(J)) and T[2, 3] > 0:
                cands.append((T, r, J, float(r @ r)))
        if not cands:
            continue
        best_sse = min(c[3] for c in cands)
        close = [c for c in cands if c[3] <= best_sse + ambiguity_chi2]      # whitened: chi^2
        T, r, J, _ = max(close, key=lambda c: (R_wc @ c[0][:3, 1])[2])
        r_px = symbol_reprojection(camera, T, corners_S)[0] - uv
        if float(np.sqrt(np.mean(r_px ** 2))) > max_rms_px:
            continue
        try:
            cov_cam = covariance_from_jacobian(J, 1.0)[3:, 3:]
        except EstimationError:
            continue
        p_cam = T[:3, 3].copy()
        p_world = transform_points(T_world_cam, p_cam[None])[0]
        cov_world = R_wc @ cov_cam @ R_wc.T
        if cov_body is not None:
            Jb = _numerical_jacobian(
                lambda xi: transform_points(camera_pose(T_world_body @ se3_exp(xi), camera),
                                            p_cam[None])[0], 6)
            cov_world = cov_world + Jb @ np.asarray(cov_body, dtype=float) @ Jb.T
        out.append(LoadObservation(timestamp_ns=int(s.detection.timestamp_ns), load_id=s.load_id,
                                   p_world=p_world, cov_world=0.5 * (cov_world + cov_world.T),
                                   p_cam=p_cam, cov_cam=cov_cam,
                                   corners_px=uv.copy()))
    return out


# ============================================================================ whole flights


@dataclass
class PnPStats:
    """What happened to a flight's floor-camera frames."""
    n_frames: int = 0
    n_posed: int = 0
    n_without_floor_code: int = 0
    n_unsolved: int = 0                  # floor codes in view but no acceptable pose
    n_ambiguous: int = 0                 # decided by the near-level rule
    n_codes_dropped: int = 0             # outlier codes left out of a pose
    codes_per_pose: dict[int, int] = field(default_factory=dict)   # n_codes -> n_frames
    rejections: dict[str, int] = field(default_factory=dict)       # classify() reasons
    mean_reprojection_rms_px: float = float("nan")


def pnp_trajectory(frames: dict[int, list[QRDetection]], camera: CameraModel, world: World,
                   corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, name: str = "pnp"
                   ) -> tuple[Trajectory, PnPStats]:
    """Per-frame PnP body poses of a floor-camera flight: {timestamp_ns: detections} ->
    (Trajectory with (N, 6, 6) covariances, PnPStats).  Frames with no usable floor code are
    left out (counted in the stats); rejected payloads (fusion.qr.codes.classify) are never used."""
    stats = PnPStats()
    ts_out, T_out, cov_out, rms = [], [], [], []
    codes_seen = []
    per_pose: Counter = Counter()
    for ts in sorted(frames):
        stats.n_frames += 1
        codes = classify(frames[ts], world)
        codes_seen.append(codes)
        if not codes.floor:
            stats.n_without_floor_code += 1
            continue
        res = estimate_floor_pose(codes.floor, camera, corner_sigma_px)
        if res is None:
            stats.n_unsolved += 1
            continue
        stats.n_posed += 1
        stats.n_ambiguous += int(res.ambiguous)
        stats.n_codes_dropped += len(res.dropped_payloads)
        per_pose[res.n_codes] += 1
        ts_out.append(int(ts))
        T_out.append(res.T_world_body)
        cov_out.append(res.covariance)
        rms.append(res.reprojection_rms_px)
    stats.codes_per_pose = dict(sorted(per_pose.items()))
    stats.rejections = rejection_counts(codes_seen)
    if rms:
        stats.mean_reprojection_rms_px = float(np.mean(rms))
    if not ts_out:
        return Trajectory.empty(name), stats
    return Trajectory(name, np.asarray(ts_out, dtype=np.int64), np.stack(T_out),
                      np.stack(cov_out)), stats


def pose_at(trajectory: Trajectory, timestamp_ns: int, max_gap_s: float = 0.1
            ) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(T_world_body, cov or None) at `timestamp_ns`: the pose stamped within 1 ms of it, or the
    interpolation (linear position, geodesic rotation; covariance of the nearer pose) between the
    poses on either side when they are at most `max_gap_s` apart; None otherwise."""
    ts = np.asarray(trajectory.timestamps_ns, dtype=np.int64)
    if len(ts) == 0:
        return None
    covs = trajectory.covariances
    i = int(np.searchsorted(ts, timestamp_ns))
    for j in (i - 1, i):
        if 0 <= j < len(ts) and abs(int(ts[j]) - int(timestamp_ns)) <= 1_000_000:
            return trajectory.T_world_body[j], (None if covs is None else covs[j])
    if i == 0 or i == len(ts) or (ts[i] - ts[i - 1]) * 1e-9 > max_gap_s:
        return None
    t0, t1 = int(ts[i - 1]), int(ts[i])
    a = (int(timestamp_ns) - t0) / (t1 - t0)
    T0, T1 = trajectory.T_world_body[i - 1], trajectory.T_world_body[i]
    dw = Rotation.from_matrix(T0[:3, :3].T @ T1[:3, :3]).as_rotvec()
    T = make_T(T0[:3, :3] @ so3_exp(a * dw), (1 - a) * T0[:3, 3] + a * T1[:3, 3])
    cov = None if covs is None else covs[i - 1 if a < 0.5 else i]
    return T, cov


def pnp_load_observations(front_frames: dict[int, list[QRDetection]], front_camera: CameraModel,
                          world: World, trajectory: Trajectory,
                          corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
                          max_gap_s: float = 0.1) -> list[LoadObservation]:
    """Load observations of a flight's front-camera frames ({timestamp_ns: detections}), placed
    with the drone pose of `trajectory` at each frame (`pose_at`); frames without a pose are
    skipped.  Rejected payloads (classify) are never used."""
    out: list[LoadObservation] = []
    for ts in sorted(front_frames):
        codes = classify(front_frames[ts], world)
        if not codes.loads:
            continue
        pose = pose_at(trajectory, ts, max_gap_s)
        if pose is None:
            continue
        T_world_body, cov = pose
        out.extend(estimate_load_observations(codes.loads, front_camera, world, T_world_body, cov,
                                              corner_sigma_px))
    return out


def aggregate_load_observations(observations: list[LoadObservation], name: str = "pnp") -> LoadMap:
    """Information-weighted mean of each load id's p_world: P = (sum C_i^-1)^-1,
    p = P sum C_i^-1 p_i (observations without cov_world get the plain mean, cov None).

    Caveat: observations taken from nearby drone poses share pose error, so P is optimistic when
    they are many; the factor-graph back end models that correlation properly."""
    by_id: dict[str, list[LoadObservation]] = {}
    for o in observations:
        by_id.setdefault(o.load_id, []).append(o)
    loads = []
    for load_id in sorted(by_id):
        obs = by_id[load_id]
        with_cov = [o for o in obs if o.cov_world is not None]
        if with_cov:
            info = np.zeros((3, 3))
            vec = np.zeros(3)
            for o in with_cov:
                W = np.linalg.inv(o.cov_world)
                info += W
                vec += W @ o.p_world
            P = np.linalg.inv(info)
            loads.append(LoadEstimate(load_id, P @ vec, 0.5 * (P + P.T), len(obs)))
        else:
            loads.append(LoadEstimate(load_id, np.mean([o.p_world for o in obs], axis=0), None,
                                      len(obs)))
    return LoadMap(name, loads)
