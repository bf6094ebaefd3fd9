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
from fusion.conventions import (inv_T, make_T, rot_z, symbol_corners_S,
                                wrap_angle, yaw_of)
from fusion.errors import EstimationError
from fusion.qr.codes import FloorSighting, LoadSighting, classify, rejection_counts
from fusion.qr.crb import (Projector, covariance_from_information, cross_rows, floor_reprojection_parts,
                           skew, so3_exp, symbol_reprojection_parts)
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


def level_frame(T_world_body: np.ndarray) -> np.ndarray:
    """The body frame with roll and pitch removed: same origin, z = world z, same yaw."""
    return make_T(rot_z(float(yaw_of(T_world_body[:3, :3]))), T_world_body[:3, 3])


def camera_pose(T_world_body: np.ndarray, camera: CameraModel) -> np.ndarray:
    """T_world_cam: T_world_body * T_body_cam, with the level frame for a "gimbaled" camera."""
    T = level_frame(T_world_body) if camera.mount == "gimbaled" else T_world_body
    return T @ camera.T_body_cam


def _same_pose(x_a, x_b, tol_rad: float, tol_m: float) -> bool:
    """Whether poses x = (R, t) differ by at most `tol_rad` in rotation and `tol_m` in position."""
    c = 0.5 * (float(np.vdot(x_a[0], x_b[0])) - 1.0)        # cos(angle): trace(R_a^T R_b) = <R_a, R_b>
    return c >= math.cos(tol_rad) and float(np.linalg.norm(x_a[1] - x_b[1])) <= tol_m


def _cv_points(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 1, a.shape[-1]))


_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-14)


def undistort(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """(N, 2) distorted pixels -> (N, 2) ideal normalised coordinates: OpenCV's iterative
    undistortPoints (about 30x faster than CameraModel.undistort_normalized), checked by
    distorting back; where that check fails (strong distortion), CameraModel's Newton inversion."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if not np.all(np.isfinite(uv)):
        return camera.undistort_normalized(uv)
    xn = cv2.undistortPoints(_cv_points(uv), camera.K, camera.dist_cv, None, None, None,
                             _UNDISTORT_CRITERIA).reshape(-1, 2)
    xd = camera.distort_normalized(xn)
    back = np.column_stack([camera.fu * xd[:, 0] + camera.cu, camera.fv * xd[:, 1] + camera.cv])
    if np.all(np.abs(back - uv) < 1e-8):
        return xn
    return camera.undistort_normalized(uv)


# ---------------------------------------------------------------------------- Gauss-Newton / LM

MAX_ITERATIONS = 20
"""Iteration cap of the LM; from the IPPE / SQPnP starts it converges in 2-4."""
CONVERGED_DECREMENT = 1e-10
"""Converged when the predicted decrease of the whitened cost, g^T H^-1 g (chi^2 units: the step
is sqrt of this many standard deviations long), is below this plus 1e-10 of the cost."""


def _whitened_normal_equations(J: np.ndarray, r: np.ndarray, W: np.ndarray) -> np.ndarray:
    """J (K, N, 2, 6) and r (K, N, 2) px of K poses, N = 4 n corners, W (n, 8, 8) whitening ->
    (K, 7, 7) matrices [[J^T W^T W J, J^T W^T W r], [., r^T W^T W r]]: H, g = G[:6, :6], G[:6, 6],
    cost = G[6, 6] (all of them from one product of the whitened [J | r])."""
    K, N = r.shape[:2]
    n = len(W)
    Jr = np.empty((K, N, 2, 7))
    Jr[..., :6] = J
    Jr[..., 6] = r
    M = (W @ Jr.reshape(K, n, 8, 7)).reshape(K, 8 * n, 7)
    return M.transpose(0, 2, 1) @ M


def _stack_poses(xs: list) -> tuple[np.ndarray, np.ndarray]:
    """[(R, t)] * K -> R (K, 3, 3), t (K, 3)."""
    if len(xs) == 1:
        return xs[0][0][None], xs[0][1][None]
    return np.stack([x[0] for x in xs]), np.stack([x[1] for x in xs])


class _FloorModel:
    """Whitened reprojection error of one frame's floor corners over the body pose (R, t) of
    T_world_body, right perturbation [w, v] (fusion/qr/crb.py); retraction R exp(w), t + R v.
    Evaluated for K poses at once (the starts are K = 2 or 3, the LM steps K = 1)."""

    def __init__(self, camera: CameraModel, points_world: np.ndarray, uv: np.ndarray,
                 whitening: np.ndarray):
        T_bc = camera.T_body_cam
        self.projector = Projector(camera)
        self.R_cb = np.ascontiguousarray(T_bc[:3, :3].T)
        self.t_cb = -self.R_cb @ T_bc[:3, 3]
        self.P, self.z, self.W = points_world, uv, whitening

    def residual_px(self, x) -> np.ndarray:
        """(4n, 2) reprojection error in pixels (NaN for a point behind the camera)."""
        uv, _ = floor_reprojection_parts(self.projector, self.R_cb, self.t_cb, x[0], x[1],
                                         self.P, jacobian=False)
        return uv - self.z

    def normal_equations(self, xs: list) -> np.ndarray:
        """(K, 7, 7) `_whitened_normal_equations` of K poses; d p_cam / d xi = R_cb [[p_body]x, -I]
        (fusion/qr/crb.floor_reprojection)."""
        R, t = _stack_poses(xs)
        N = len(self.P)
        p_body = ((self.P - t[:, None, :]) @ R).reshape(-1, 3)          # (K N, 3)
        uv, J_proj = self.projector.project(p_body @ self.R_cb.T + self.t_cb)
        A = J_proj @ self.R_cb                                           # d px / d p_body
        J = np.empty((len(p_body), 2, 6))
        J[:, :, :3] = cross_rows(A, p_body)                              # A [p_body]x
        J[:, :, 3:] = -A
        return _whitened_normal_equations(J.reshape(len(xs), N, 2, 6),
                                          uv.reshape(len(xs), N, 2) - self.z, self.W)

    @staticmethod
    def retract(x, delta):
        R, t = x
        return R @ so3_exp(delta[:3]), t + R @ delta[3:]


class _SymbolModel:
    """Whitened reprojection error of one load code's corners over its pose (R, t) in the camera:
    R exp(w) (symbol frame), t + dt (camera frame), as fusion/qr/crb.symbol_reprojection."""

    def __init__(self, projector: Projector, points_symbol: np.ndarray, uv: np.ndarray,
                 whitening: np.ndarray):
        self.projector, self.P, self.z, self.W = projector, points_symbol, uv, whitening

    def residual_px(self, x) -> np.ndarray:
        """(4, 2) reprojection error in pixels."""
        uv, _ = symbol_reprojection_parts(self.projector, x[0], x[1], self.P, jacobian=False)
        return uv - self.z

    def normal_equations(self, xs: list) -> np.ndarray:
        """(K, 7, 7) `_whitened_normal_equations` of K poses; d p_cam / d[w, dt] =
        [-R [p_S]x, I] (fusion/qr/crb.symbol_reprojection)."""
        R, t = _stack_poses(xs)
        K = len(xs)
        p_S = np.broadcast_to(self.P, (K, 4, 3)).reshape(-1, 3)
        uv, J_proj = self.projector.project((self.P @ R.transpose(0, 2, 1) + t[:, None, :])
                                            .reshape(-1, 3))
        J = np.empty((4 * K, 2, 6))
        J[:, :, :3] = -cross_rows((J_proj.reshape(K, 8, 3) @ R).reshape(-1, 2, 3), p_S)
        J[:, :, 3:] = J_proj
        return _whitened_normal_equations(J.reshape(K, 4, 2, 6), uv.reshape(K, 4, 2) - self.z,
                                          self.W)

    @staticmethod
    def retract(x, delta):
        return x[0] @ so3_exp(delta[:3]), x[1] + delta[3:]


def _levenberg_marquardt(model, x, G: np.ndarray | None = None, max_iter: int = MAX_ITERATIONS):
    """Minimise the model's whitened cost |W (h(x) - z)|^2 over a pose x = (R, t) from `x` (G: its
    normal equations when already evaluated); returns (x, G) at the optimum, G the 7x7
    `_whitened_normal_equations` there (H = J^T W^T W J for the covariance, cost = G[6, 6]), or
    None when the cost is not finite at the start.

    Gauss-Newton steps, damped (Levenberg-Marquardt, lambda diag(H)) only after a step that
    raised the cost; stops when the predicted decrease g^T H^-1 g is below
    CONVERGED_DECREMENT (1 + cost): from IPPE / SQPnP starts that takes 2-4 evaluations."""
    if G is None:
        G = model.normal_equations([x])[0]
    if not np.all(np.isfinite(G)):
        return None
    cost = G[6, 6]
    lam = 0.0
    for _ in range(max_iter):
        H, g = G[:6, :6], G[:6, 6]
        if lam > 0.0:
            H = H + lam * np.diag(H.diagonal())
        try:
            delta = np.linalg.solve(H, -g)
        except np.linalg.LinAlgError:
            break
        if -(g @ delta) <= CONVERGED_DECREMENT * (1.0 + cost):
            # converged: take this last, tiny step without re-linearising (G stays, H is then
            # that of a point < 1e-4 sigma away); in a noise-free view it is what makes the
            # solution exact to 1e-12
            x = model.retract(x, delta)
            break
        x_new = model.retract(x, delta)
        G_new = model.normal_equations([x_new])[0]
        cost_new = G_new[6, 6]
        if cost_new <= cost:                 # False for NaN
            x, G, cost = x_new, G_new, cost_new
            lam = 0.0 if lam <= 1e-3 else 0.1 * lam
        else:
            lam = 1e-3 if lam == 0.0 else 10.0 * lam
            if lam > 1e6:
                break
    return x, G


def corner_whitening(detections, default_sigma_px: float) -> np.ndarray:
    """(n, 8, 8) whitening matrices W_i = L_i^-1 of each detection's corner covariance
    C_i = L_i L_i^T (Cholesky; order TL u, TL v, TR u, ..., BL v), so that W_i (z_i - h_i) has
    identity covariance: `corner_cov_px2` when set and positive definite (the corners come from
    one homography fit, so their errors are correlated), else diag(1 / sigma^2) with sigma the
    detection's `corner_sigma_px` or `default_sigma_px` (`corner_sigmas`)."""
    sig = corner_sigmas(detections, default_sigma_px).reshape(-1, 8)
    out = np.zeros((len(sig), 8, 8))
    idx = np.arange(8)
    out[:, idx, idx] = 1.0 / sig
    with_cov, covs = [], []
    for i, d in enumerate(detections):
        C = getattr(d, "corner_cov_px2", None)
        if C is not None:
            C = np.asarray(C, dtype=float)
            if C.shape == (8, 8) and np.all(np.isfinite(C)):
                with_cov.append(i)
                covs.append(C)
    if with_cov:
        C = np.stack(covs)
        C = 0.5 * (C + np.swapaxes(C, 1, 2))
        try:
            out[with_cov] = np.linalg.inv(np.linalg.cholesky(C))
        except np.linalg.LinAlgError:          # one is not positive definite: one at a time
            for i, Ci in zip(with_cov, C):
                try:
                    out[i] = np.linalg.inv(np.linalg.cholesky(Ci))
                except np.linalg.LinAlgError:
                    pass                           # keeps diag(1 / sigma)
    return out


def corner_sigmas(detections, default_sigma_px: float) -> np.ndarray:
    """Per-residual 1-sigma (8 per detection: x, y of its 4 corners), px: each detection's own
    `corner_sigma_px` when it has one (fusion.qr.refine's calibrated value), else the default."""
    out = []
    for d in detections:
        s = getattr(d, "corner_sigma_px", None)
        s = float(s) if s is not None and math.isfinite(s) and s > 0 else float(default_sigma_px)
        out.append(s)
    return np.repeat(np.asarray(out, dtype=float), 8)


# ============================================================================ floor camera


def edge_implied_yaw(sightings: list[FloorSighting], camera: CameraModel,
                     xn: np.ndarray | None = None) -> float | None:
    """Body yaw (rad) implied by the floor codes' edge directions in the image, assuming a level body.

    Each code's corners are cast onto a floor below a level body at yaw 0; the symbol's "right"
    (TL->TR, BL->BR) and its "up" turned by -90 deg (BL->TL, BR->TR) give the direction of world +x
    in that frame, at angle a, so the yaw is -a.  A tilt of up to 30 deg moves this by far less
    than 90 deg, which is what rules out 180-deg yaw flips.  None if no code's rays meet the floor.
    `xn` (4n, 2): the corners already undistorted (`undistort`), to save doing it again."""
    if not sightings:
        return None
    if xn is None:
        xn = undistort(camera, np.vstack([np.asarray(s.detection.corners_px, dtype=float)
                                          for s in sightings]))
    d = xn @ camera.T_body_cam[:3, :2].T + camera.T_body_cam[:3, 2]     # rays in the body frame
    d = d.reshape(-1, 4, 3)
    ok = np.all(np.isfinite(d), axis=(1, 2)) & np.all(d[:, :, 2] < -1e-6, axis=1)
    if not np.any(ok):
        return None
    f = d[ok, :, :2] / (-d[ok, :, 2:3])
    tl, tr, br, bl = f[:, 0], f[:, 1], f[:, 2], f[:, 3]
    up = ((tl - bl) + (tr - br)).sum(axis=0)
    e = ((tr - tl) + (br - bl)).sum(axis=0) + np.array([up[1], -up[0]])
    if not np.any(e):
        return None
    return float(-math.atan2(e[1], e[0]))


def _initial_camera_poses(points_world: np.ndarray, xn: np.ndarray, centre_world: np.ndarray | None,
                          method: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate (R_cam_world, t_cam_world) from cv2.solvePnPGeneric with `method` (IPPE_SQUARE
    with one code, `centre_world` its centre; planar IPPE or SQPnP with several)."""
    origin = np.asarray(centre_world, dtype=float) if centre_world is not None \
        else points_world.mean(axis=0)      # floor symbol frame = world axes: IPPE_SQUARE's order
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(_cv_points(points_world - origin), _cv_points(xn),
                                                 _EYE3, None, flags=method)
    except cv2.error:
        return []
    out = []
    for rv, tv in zip(rvecs[:n], tvecs[:n]):
        R = cv2.Rodrigues(rv)[0]
        out.append((R, tv.reshape(3) - R @ origin))
    return out


_EYE3 = np.eye(3)
START_MARGIN_CHI2 = 100.0
"""A start is refined only when its whitened cost is within 2x + this of the best start's
(refinement lowers a cost by about the 6 pose dof, rarely by tens: this keeps every start that
could end within AMBIGUITY_CHI2 of the best, and skips mirror solutions)."""


def _solve_floor(sightings: list[FloorSighting], camera: CameraModel, points_world: np.ndarray,
                 uv: np.ndarray, xn: np.ndarray, whitening: np.ndarray, ambiguity_chi2: float):
    """Best refined body pose for these sightings (corners `points_world` (4n, 3), `uv` (4n, 2) px,
    `xn` undistorted, `whitening` (n, 8, 8)): (T_world_body, H, r_px, ambiguous) or None, with
    H = J^T W^T W J at the solution and r_px (4n, 2) its reprojection error in pixels.

    Starts: IPPE (IPPE_SQUARE for one code); SQPnP's too when no IPPE start refines to a fit
    whose whitened error is plausible (`_chi2_bound`)."""
    model = _FloorModel(camera, points_world, uv, whitening)
    yaw_hint = edge_implied_yaw(sightings, camera, xn)
    if len(sightings) == 1:
        centre, methods = sightings[0].centre_world, (cv2.SOLVEPNP_IPPE_SQUARE,)
    else:
        centre, methods = None, (cv2.SOLVEPNP_IPPE, cv2.SOLVEPNP_SQPNP)
    R_bc, t_bc = camera.T_body_cam[:3, :3], camera.T_body_cam[:3, 3]
    starts: list = []
    cands: list = []
    for method in methods:
        new = []
        for R_cw, t_cw in _initial_camera_poses(points_world, xn, centre, method):
            R_wb = R_cw.T @ R_bc.T                    # T_world_body = T_cam_world^-1 T_body_cam^-1
            x0 = (R_wb, -R_cw.T @ t_cw - R_wb @ t_bc)
            if not any(_same_pose(x0, x, 1e-3, 1e-3) for x in starts + new):
                new.append(x0)                        # SQPnP's is usually one of IPPE's
        if not new:
            continue
        starts += new
        G0 = model.normal_equations(new)
        costs = np.where(np.isfinite(G0).all(axis=(1, 2)), G0[:, 6, 6], np.inf)
        best0 = float(costs.min())
        for k in np.argsort(costs):
            if not costs[k] <= 2.0 * best0 + START_MARGIN_CHI2:
                continue
            sol = _levenberg_marquardt(model, new[k], G0[k])
            if sol is None:
                continue
            x, G = sol
            if not np.all(np.isfinite(G)):
                continue
            if x[0][2, :] @ t_bc + x[1][2] <= 0.0:     # camera under the floor: mirrored corners
                continue
            if yaw_hint is not None and \
                    abs(wrap_angle(math.atan2(x[0][1, 0], x[0][0, 0]) - yaw_hint)) \
                    > MAX_YAW_DEVIATION_RAD:
                continue
            if any(_same_pose(x, c[0], 1e-7, 1e-7) for c in cands):
                continue
            cands.append((x, G))
        if cands and min(c[1][6, 6] for c in cands) <= _chi2_bound(8 * len(sightings)):
            break                                     # SQPnP only when IPPE found no good fit
    if not cands:
        return None
    best_sse = min(c[1][6, 6] for c in cands)
    close = [c for c in cands if c[1][6, 6] <= best_sse + ambiguity_chi2]   # whitened: chi^2
    x, G = max(close, key=lambda c: c[0][0][2, 2])    # the most level: body z nearest world z
    return make_T(*x), G[:6, :6], model.residual_px(x), len(close) > 1


def _chi2_bound(dof: int) -> float:
    """A loose upper bound of a chi-square(dof) draw (Wilson-Hilferty, about 5 sigma): a whitened
    cost above it means the start does not fit."""
    return dof * (1.0 - 2.0 / (9.0 * dof) + 5.0 * math.sqrt(2.0 / (9.0 * dof))) ** 3


def estimate_floor_pose(sightings: list[FloorSighting], camera: CameraModel,
                        corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, *,
                        max_rms_px: float = MAX_REPROJECTION_RMS_PX,
                        ambiguity_chi2: float = AMBIGUITY_CHI2,
                        gimbal_roll_pitch_sigma_rad: float = GIMBAL_ROLL_PITCH_SIGMA_RAD
                        ) -> PnPResult | None:
    """Body pose from all floor codes of one floor-camera frame, or None (no code, no solution,
    or reprojection RMS above `max_rms_px` even after leaving out the worst-fitting codes).

    1. corners undistorted (`undistort`, once per frame); candidates: one code: IPPE_SQUARE's
       two solutions; several: planar IPPE's two, and SQPnP's when neither fits the corners;
    2. the candidates whose whitened error is within 2x + START_MARGIN_CHI2 of the best one's
       are refined by Gauss-Newton / LM on the reprojection error in distorted pixels over the
       body pose (`_levenberg_marquardt`; 2-4 evaluations);
    3. candidates whose yaw is > 90 deg from `edge_implied_yaw` are dropped (no 180-deg flips);
       of those whose squared error is within `ambiguity_chi2` sigma^2 of the best, the most level;
    4. covariance (J^T W J)^-1, J = d(distorted px)/d(xi), xi the body-frame right
       perturbation [rx, ry, rz, tx, ty, tz] (GTSAM Pose3; fusion/qr/crb.py), W block-diagonal
       with one (8, 8) block C_i^-1 per code: C_i the detection's `corner_cov_px2` when set (its
       corners come from one homography fit, so their errors are correlated), else
       sigma_i^2 I with sigma_i its `corner_sigma_px`, else `corner_sigma_px`; the LM of step 2
       minimises the same weighted error, and J is its last Jacobian.

    "gimbaled" camera: the camera is stabilised, so the airframe's roll and pitch are not observed.
    The returned T_world_body is then the LEVEL body frame (roll = pitch = 0, estimated yaw and
    position), and its covariance keeps the PnP marginal of [rz, tx, ty, tz] while rx and ry get
    variance gimbal_roll_pitch_sigma_rad^2 ((10 deg)^2 by default) and no correlation."""
    sightings = list(sightings)
    dropped: list[str] = []
    sigma = float(corner_sigma_px)
    if not sigma > 0:
        raise EstimationError(f"corner_sigma_px must be positive, got {corner_sigma_px!r}")
    if not sightings:
        return None
    pts_all = np.vstack([np.asarray(s.corners_world, dtype=float).reshape(4, 3) for s in sightings])
    uv_all = np.vstack([np.asarray(s.detection.corners_px, dtype=float).reshape(4, 2)
                        for s in sightings])
    xn_all = undistort(camera, uv_all)
    if not np.all(np.isfinite(xn_all)):
        return None
    wht_all = corner_whitening([s.detection for s in sightings], sigma)
    keep = list(range(len(sightings)))
    while True:
        rows = (4 * np.asarray(keep)[:, None] + np.arange(4)).reshape(-1)
        sub = [sightings[i] for i in keep]
        sol = _solve_floor(sub, camera, pts_all[rows], uv_all[rows], xn_all[rows], wht_all[keep],
                           ambiguity_chi2)
        if sol is None:
            return None
        T, H, r, ambiguous = sol
        r = r.reshape(-1)                              # px, for the outlier test
        rms = float(np.sqrt(np.mean(r ** 2)))
        if rms <= max_rms_px:
            break
        if len(keep) < 2:
            return None
        per_code = (r.reshape(len(keep), 8) ** 2).sum(axis=1)
        worst = int(np.argmax(per_code))
        dropped.append(sub[worst].detection.payload)
        del keep[worst]
    try:
        cov = covariance_from_information(H)       # H whitened: (J^T W J)^-1
    except EstimationError:
        return None
    T_world_cam = T @ camera.T_body_cam
    if camera.mount == "gimbaled":
        T = level_frame(T)
        keep6 = np.diag([0.0, 0.0, 1.0, 1.0, 1.0, 1.0])
        cov = keep6 @ cov @ keep6 + np.diag([gimbal_roll_pitch_sigma_rad ** 2] * 2 + [0.0] * 4)
    return PnPResult(T_world_body=T, covariance=cov, T_world_cam=T_world_cam,
                     n_codes=len(keep), payloads=[sightings[i].detection.payload for i in keep],
                     reprojection_rms_px=rms, ambiguous=ambiguous, dropped_payloads=dropped)


# ============================================================================ front camera


def position_jacobian_wrt_body(T_world_body: np.ndarray, camera: CameraModel,
                                p_cam: np.ndarray) -> np.ndarray:
    """(3, 6) d p_world / d xi of p_world = camera_pose(T_world_body Exp(xi), camera) p_cam, xi the
    body-frame right perturbation [rx, ry, rz, tx, ty, tz] (GTSAM Pose3).

    body_fixed: p_world = R (Exp(xi) q) + t with q = T_body_cam p_cam, so R [ -[q]x , I ].
    gimbaled: p_world = Rz(yaw) q + t' with yaw = yaw_of(R exp([w]x)) and t' = t + R v; only
    w_y, w_z move the yaw (d R[:, 0] = R (w x e_x) = R (0, w_z, -w_y)), by
    d yaw = (R00 dR10 - R10 dR00) / (R00^2 + R10^2), and d p_world / d yaw = e_z x (Rz q)."""
    R = T_world_body[:3, :3]
    q = camera.T_body_cam[:3, :3] @ p_cam + camera.T_body_cam[:3, 3]
    J = np.empty((3, 6))
    J[:, 3:] = R
    if camera.mount == "gimbaled":
        Rz_q = rot_z(float(yaw_of(R))) @ q
        n = R[0, 0] ** 2 + R[1, 0] ** 2
        d_yaw = np.array([0.0, (R[1, 0] * R[0, 2] - R[0, 0] * R[1, 2]) / n,
                          (R[0, 0] * R[1, 1] - R[1, 0] * R[0, 1]) / n])
        J[:, :3] = np.outer([-Rz_q[1], Rz_q[0], 0.0], d_yaw)
    else:
        J[:, :3] = -R @ skew(q)
    return J


def estimate_load_observations(sightings: list[LoadSighting], camera: CameraModel, world: World,
                               T_world_body: np.ndarray, cov_body: np.ndarray | None = None,
                               corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, *,
                               max_rms_px: float = MAX_REPROJECTION_RMS_PX,
                               ambiguity_chi2: float = AMBIGUITY_CHI2) -> list[LoadObservation]:
    """One LoadObservation per load code of one front-camera frame whose corners fit a square of
    side world.load_side_m (reprojection RMS <= max_rms_px; others are skipped).

    p_cam (3,) = the code centre in the camera frame (m) from IPPE_SQUARE + LM in distorted pixels
    (both IPPE solutions when their whitened errors are within 2x + START_MARGIN_CHI2 of each
    other, else the better one), cov_cam (3, 3) = the centre block of (J^T C^-1 J)^-1
    (fusion/qr/crb.symbol_reprojection), C the detection's `corner_cov_px2`, else sigma^2 I with
    sigma its `corner_sigma_px`, else `corner_sigma_px` (the LM minimises the same weighted error);
    p_world = T_world_cam p_cam with T_world_cam = camera_pose(T_world_body, camera), and
    cov_world = R_world_cam cov_cam R_world_cam^T + J_b cov_body J_b^T, J_b = d p_world / d xi
    (`position_jacobian_wrt_body`) for the body-frame right perturbation xi of T_world_body
    (cov_body None: drone pose exact).
    IPPE's two-fold ambiguity barely moves the centre; when both fit, the one whose symbol "up"
    is nearer world +z is taken (load codes hang on vertical faces, up = +z)."""
    sightings = [s for s in sightings
                 if np.asarray(s.detection.corners_px, dtype=float).shape == (4, 2)]
    if not sightings:
        return []
    sigma = float(corner_sigma_px)
    T_world_body = np.asarray(T_world_body, dtype=float)
    T_world_cam = camera_pose(T_world_body, camera)
    R_wc = T_world_cam[:3, :3]
    corners_S = symbol_corners_S(world.load_side_m)
    obj = _cv_points(corners_S)
    projector = Projector(camera)
    uv_all = np.vstack([np.asarray(s.detection.corners_px, dtype=float) for s in sightings])
    xn_all = undistort(camera, uv_all).reshape(-1, 4, 2)
    wht_all = corner_whitening([s.detection for s in sightings], sigma)
    out = []
    for k, s in enumerate(sightings):
        uv, xn = uv_all[4 * k:4 * k + 4], xn_all[k]
        if not np.all(np.isfinite(xn)):
            continue
        try:
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, _cv_points(xn), _EYE3, None,
                                                     flags=cv2.SOLVEPNP_IPPE_SQUARE)
        except cv2.error:
            continue
        model = _SymbolModel(projector, corners_S, uv, wht_all[k:k + 1])
        starts = [(cv2.Rodrigues(rv)[0], tv.reshape(3)) for rv, tv in zip(rvecs[:n], tvecs[:n])]
        if not starts:
            continue
        G0 = model.normal_equations(starts)
        costs = np.where(np.isfinite(G0).all(axis=(1, 2)), G0[:, 6, 6], np.inf)
        best0 = float(costs.min())
        cands = []
        for k, x0 in enumerate(starts):
            if not costs[k] <= 2.0 * best0 + START_MARGIN_CHI2:
                continue
            sol = _levenberg_marquardt(model, x0, G0[k])
            if sol is None:
                continue
            (R, t), G = sol
            if np.all(np.isfinite(G)) and t[2] > 0:
                cands.append((R, t, G, float(G[6, 6])))
        if not cands:
            continue
        best_sse = min(c[3] for c in cands)
        close = [c for c in cands if c[3] <= best_sse + ambiguity_chi2]      # whitened: chi^2
        R, t, G, _ = max(close, key=lambda c: (R_wc @ c[0][:, 1])[2])
        r_px = model.residual_px((R, t))
        if not float(np.sqrt(np.mean(r_px ** 2))) <= max_rms_px:
            continue
        try:
            cov_cam = covariance_from_information(G[:6, :6])[3:, 3:]
        except EstimationError:
            continue
        p_cam = t.copy()
        p_world = R_wc @ p_cam + T_world_cam[:3, 3]
        cov_world = R_wc @ cov_cam @ R_wc.T
        if cov_body is not None:
            Jb = position_jacobian_wrt_body(T_world_body, camera, p_cam)
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
