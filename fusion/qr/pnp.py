"""Our per-frame estimator (not the paper's): PnP on every floor code in view, with covariance.

Floor camera (cam0): all floor codes of a frame are solved at once (4 known world corners each),
initialised by IPPE (both of its two-fold solutions; SQPnP too when neither refines to a plausible
fit), refined by Gauss-Newton / Levenberg–Marquardt on the whitened reprojection error in
DISTORTED pixels (fusion/qr/crb.py's model), and given the covariance (J^T W J)^-1 of that model.

Front camera (cam1): each load code's pose in the camera from its four corners (IPPE, side
world.load_side_m), refined the same way; its centre p_cam with covariance, and p_world with the
drone pose's covariance propagated to first order.

Speed: each frame is solved on its own, but many frames are computed together
(`estimate_floor_poses`, `estimate_load_observations_frames`; `pnp_trajectory` and
`pnp_load_observations` use them): one vectorised IPPE and one vectorised LM evaluation per step
for all views with the same number of codes.  About 0.1 ms per floor frame and 0.05 ms per front
frame in batches, 0.7-1 ms for a single call (2 shared cores, scripts/bench_pnp.py).

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

from fusion.camera import CameraModel
from fusion.conventions import symbol_corners_S
from fusion.errors import EstimationError
from fusion.geometry import (
    cross_rows,
    interpolate_pose,
    level_frame,
    rot_z,
    skew,
    so3_exp_stack,
    wrap_angle,
    yaw_of,
)
from fusion.qr.codes import FloorSighting, LoadSighting, classify, rejection_counts
from fusion.qr.crb import Projector
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


def _same_pose(x_a, x_b, tol_rad: float, tol_m: float) -> bool:
    """Whether poses x = (R, t) differ by at most `tol_rad` in rotation and `tol_m` in position."""
    c = 0.5 * (float(np.vdot(x_a[0], x_b[0])) - 1.0)     # cos(angle): trace(R_a^T R_b) = <R_a, R_b>
    return c >= math.cos(tol_rad) and float(np.linalg.norm(x_a[1] - x_b[1])) <= tol_m


def _same_minimum(x_a, H_a: np.ndarray, x_b) -> bool:
    """Whether refined poses x = (R, t) are the same minimum of a cost with information H_a at
    x_a: x_b = x_a Exp(xi) with xi^T H_a xi < 0.01 (a tenth of a standard deviation apart; the LM
    stops within about 1e-3)."""
    D = x_a[0].T @ x_b[0]
    if np.trace(D) < 2.98:                      # more than ~0.14 rad apart
        return False
    xi = np.array([0.5 * (D[2, 1] - D[1, 2]), 0.5 * (D[0, 2] - D[2, 0]), 0.5 * (D[1, 0] - D[0, 1]),
                   *(x_a[0].T @ (x_b[1] - x_a[1]))])
    return float(xi @ H_a @ xi) < 0.01


def _cv_points(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 1, a.shape[-1]))


_EYE3 = np.eye(3)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-14)
_OPENCV_UNDISTORTS: dict[tuple, bool] = {}          # `_opencv_undistorts`, per camera


def _opencv_undistorts(camera: CameraModel) -> bool:
    """Whether OpenCV's iterative undistortPoints reproduces CameraModel.undistort_normalized
    (to 1e-8 px on distorting back) over a grid covering the image and a 10 % margin; cached per
    camera parameters."""
    key = (camera.width, camera.height, camera.fu, camera.fv, camera.cu, camera.cv,
           *camera.distortion.tolist())
    ok = _OPENCV_UNDISTORTS.get(key)
    if ok is None:
        u, v = np.meshgrid(np.linspace(-0.1, 1.1, 25) * camera.width,
                           np.linspace(-0.1, 1.1, 19) * camera.height)
        ok = _undistort_checked(camera, np.column_stack([u.ravel(), v.ravel()])) is not None
        _OPENCV_UNDISTORTS[key] = ok
    return ok


def _undistort_checked(camera: CameraModel, uv: np.ndarray) -> np.ndarray | None:
    """OpenCV's undistortPoints of (N, 2) pixels, or None where distorting back misses by 1e-8 px."""
    xn = cv2.undistortPoints(_cv_points(uv), camera.K, camera.dist_cv, None, None, None,
                             _UNDISTORT_CRITERIA).reshape(-1, 2)
    back, _ = Projector(camera).project(np.column_stack([xn, np.ones(len(xn))]), jacobian=False)
    return xn if np.all(np.abs(back - uv) < 1e-8) else None


def undistort(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """(N, 2) distorted pixels -> (N, 2) ideal normalised coordinates, = CameraModel's
    undistort_normalized: OpenCV's iterative undistortPoints (about 30x faster), trusted inside
    the image (+10 %) when `_opencv_undistorts` verified it for this camera, else checked by
    distorting back; where that fails (strong distortion), CameraModel's Newton inversion."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if len(uv) == 0 or not np.all(np.isfinite(uv)):
        return camera.undistort_normalized(uv)
    lo = -0.1 * np.array([camera.width, camera.height])
    if _opencv_undistorts(camera) and np.all(uv >= lo) and np.all(uv <= -11.0 * lo):
        return cv2.undistortPoints(_cv_points(uv), camera.K, camera.dist_cv, None, None, None,
                                   _UNDISTORT_CRITERIA).reshape(-1, 2)
    xn = _undistort_checked(camera, uv)
    return camera.undistort_normalized(uv) if xn is None else xn


def corner_whitening(detections, default_sigma_px: float) -> np.ndarray:
    """(n, 8, 8) whitening matrices W_i = L_i^-1 of each detection's corner covariance
    C_i = L_i L_i^T (Cholesky; order TL u, TL v, TR u, ..., BL v), so that W_i (z_i - h_i) has
    identity covariance: `corner_cov_px2` when set and positive definite (the corners come from
    one homography fit, so their errors are correlated), else diag(1 / sigma) with sigma the
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
            if C.shape == (8, 8):
                with_cov.append(i)
                covs.append(C)
    if covs:
        C = np.stack(covs)
        finite = np.isfinite(C).all(axis=(1, 2))
        with_cov, C = [i for i, f in zip(with_cov, finite) if f], C[finite]
    if with_cov:
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
        out.append(float(s) if s is not None and math.isfinite(s) and s > 0
                   else float(default_sigma_px))
    return np.repeat(np.asarray(out, dtype=float), 8)


def _covariances(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 6, 6) information matrices -> covariances H^-1 (K, 6, 6) through one batched
    eigen-decomposition, and a (K,) mask of the valid ones (finite, positive definite, condition
    number <= 1e14, as crb.covariance_from_information)."""
    ok = np.isfinite(H).all(axis=(1, 2))
    Hs = np.where(ok[:, None, None], H, np.eye(6))
    lam, V = np.linalg.eigh(Hs)
    ok &= (lam[:, 0] > 0) & (lam[:, -1] <= 1e14 * lam[:, 0])
    lam = np.where(ok[:, None], lam, 1.0)
    C = (V / lam[:, None, :]) @ V.transpose(0, 2, 1)
    return 0.5 * (C + C.transpose(0, 2, 1)), ok


# ============================================================================ batched Gauss-Newton

MAX_ITERATIONS = 20
"""Iteration cap of the LM; from the IPPE / SQPnP starts it converges in 2-4."""
CONVERGED_DECREMENT = 1e-6
"""Converged when the predicted decrease of the whitened cost, g^T H^-1 g, is below this fraction
of the cost (plus 1e-15): the pose is then within about 1e-3 sqrt(cost / dof) standard deviations
of the optimum, and exact in a noise-free view."""
START_MARGIN_CHI2 = 100.0
"""A start is refined only when its whitened cost is within 2x + this of the best start's of the
same view (refinement lowers a cost by about the 6 pose dof, rarely by tens: this keeps every
start that could end within AMBIGUITY_CHI2 of the best, and skips mirror solutions)."""


def _whitened_normal_equations(Jr: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Jr (K, N, 2, 7) = [J | r] of K problems (J d(px)/d(pose) of N = 4 n corners, r their
    px residuals), W (K, n, 8, 8) their whitening -> (K, 7, 7) matrices
    [[J^T W^T W J, J^T W^T W r], [., r^T W^T W r]]: H, g = G[:6, :6], G[:6, 6], cost = G[6, 6]
    (all of them from one product of the whitened [J | r])."""
    K, N = Jr.shape[:2]
    M = (W @ Jr.reshape(K, N // 4, 8, 7)).reshape(K, 2 * N, 7)
    return M.transpose(0, 2, 1) @ M


class _FloorProblems:
    """K floor-camera problems with the same number n of codes: world corners P (K, 4n, 3),
    observed px z (K, 4n, 2), whitening W (K, n, 8, 8); unknown the body pose (R, t) of
    T_world_body, perturbed on the right by [w, v] (fusion/qr/crb.floor_reprojection), retracted
    as R exp(w), t + R v."""

    def __init__(self, projector: Projector, R_cb: np.ndarray, t_cb: np.ndarray, P: np.ndarray,
                 z: np.ndarray, W: np.ndarray):
        self.projector, self.R_cb, self.t_cb, self.P, self.z, self.W = projector, R_cb, t_cb, P, z, W

    def subset(self, idx: np.ndarray) -> "_FloorProblems":
        return _FloorProblems(self.projector, self.R_cb, self.t_cb, self.P[idx], self.z[idx],
                              self.W[idx])

    def residual_px(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K, 4n, 2) reprojection errors in pixels of poses R (K, 3, 3), t (K, 3)."""
        p_cam = ((self.P - t[:, None, :]) @ R) @ self.R_cb.T + self.t_cb
        uv, _ = self.projector.project(p_cam.reshape(-1, 3), jacobian=False)
        return uv.reshape(self.z.shape) - self.z

    def normal_equations(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K, 7, 7) `_whitened_normal_equations`; d p_cam / d xi = R_cb [[p_body]x, -I]."""
        K, N = self.P.shape[:2]
        p_body = ((self.P - t[:, None, :]) @ R).reshape(-1, 3)          # (K N, 3)
        uv, J_proj = self.projector.project(p_body @ self.R_cb.T + self.t_cb)
        A = J_proj @ self.R_cb                                           # d px / d p_body
        Jr = np.empty((K * N, 2, 7))
        Jr[:, :, :3] = cross_rows(A, p_body)                             # A [p_body]x
        Jr[:, :, 3:6] = -A
        Jr[:, :, 6] = uv - self.z.reshape(-1, 2)
        return _whitened_normal_equations(Jr.reshape(K, N, 2, 7), self.W)

    @staticmethod
    def retract(R: np.ndarray, t: np.ndarray, delta: np.ndarray):
        return R @ so3_exp_stack(delta[:, :3]), t + (R @ delta[:, 3:, None])[:, :, 0]


class _SymbolProblems:
    """K load-code problems: the code's corners P (4, 3) in its symbol frame, observed px
    z (K, 4, 2), whitening W (K, 1, 8, 8); unknown the pose (R, t) of T_cam_symbol, perturbed as
    R exp(w) (symbol frame), t + dt (camera frame) (fusion/qr/crb.symbol_reprojection)."""

    def __init__(self, projector: Projector, P: np.ndarray, z: np.ndarray, W: np.ndarray):
        self.projector, self.P, self.z, self.W = projector, P, z, W

    def subset(self, idx: np.ndarray) -> "_SymbolProblems":
        return _SymbolProblems(self.projector, self.P, self.z[idx], self.W[idx])

    def residual_px(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        p_cam = self.P @ R.transpose(0, 2, 1) + t[:, None, :]
        uv, _ = self.projector.project(p_cam.reshape(-1, 3), jacobian=False)
        return uv.reshape(self.z.shape) - self.z

    def normal_equations(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K, 7, 7) `_whitened_normal_equations`; d p_cam / d[w, dt] = [-R [p_S]x, I]."""
        K = len(R)
        uv, J_proj = self.projector.project(
            (self.P @ R.transpose(0, 2, 1) + t[:, None, :]).reshape(-1, 3))
        B = (J_proj.reshape(K, 8, 3) @ R).reshape(-1, 2, 3)
        Jr = np.empty((4 * K, 2, 7))
        Jr[:, :, :3] = cross_rows(B, np.broadcast_to(-self.P, (K, 4, 3)).reshape(-1, 3))
        Jr[:, :, 3:6] = J_proj
        Jr[:, :, 6] = uv - self.z.reshape(-1, 2)
        return _whitened_normal_equations(Jr.reshape(K, 4, 2, 7), self.W)

    @staticmethod
    def retract(R: np.ndarray, t: np.ndarray, delta: np.ndarray):
        return R @ so3_exp_stack(delta[:, :3]), t + delta[:, 3:]


def _levenberg_marquardt(problems, R: np.ndarray, t: np.ndarray, G: np.ndarray,
                         max_iter: int = MAX_ITERATIONS):
    """Minimise each of K problems' whitened cost |W (h(x) - z)|^2 over its pose x = (R, t), from
    the starts R (K, 3, 3), t (K, 3) with normal equations G (K, 7, 7) (`normal_equations`), all
    K in one evaluation per step; returns R, t, G at the optima (H = G[:, :6, :6] = J^T W^T W J
    for the covariance, cost = G[:, 6, 6]) and a (K,) mask of the converged ones (not those that
    ran out of iterations or could not descend; a start whose G is not finite is left as it is).

    Gauss-Newton steps, damped (Levenberg-Marquardt, lambda diag(H)) only after a step that
    raised the cost; a problem stops when its predicted decrease g^T H^-1 g is below
    CONVERGED_DECREMENT cost: from IPPE / SQPnP starts that takes 2-4 evaluations."""
    R, t, G = R.copy(), t.copy(), G.copy()
    idx = np.flatnonzero(np.isfinite(G).all(axis=(1, 2)))      # the problems still iterating
    if len(idx) < len(R):
        problems = problems.subset(idx)
    Ra, ta, Ga = R[idx], t[idx], G[idx]                         # their current poses
    lam = np.zeros(len(idx))
    converged = np.zeros(len(R), dtype=bool)
    diag = np.arange(6)
    for _ in range(max_iter):
        if len(idx) == 0:
            break
        H, g = Ga[:, :6, :6], Ga[:, :6, 6]
        if lam.any():
            H = H.copy()
            H[:, diag, diag] *= (1.0 + lam)[:, None]
        try:
            delta = np.linalg.solve(H, -g[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:                  # one is singular: one at a time
            delta = np.full(g.shape, np.nan)
            for i in range(len(idx)):
                try:
                    delta[i] = np.linalg.solve(H[i], -g[i])
                except np.linalg.LinAlgError:
                    pass
        decrease = -np.einsum("ki,ki->k", g, delta)
        going = decrease > CONVERGED_DECREMENT * Ga[:, 6, 6] + 1e-15     # False for NaN
        if not going.all():                            # converged ones leave the batch
            R[idx], t[idx], G[idx] = Ra, ta, Ga
            converged[idx[~going & np.isfinite(decrease)]] = True
            idx, Ra, ta, Ga, lam, delta = (idx[going], Ra[going], ta[going], Ga[going],
                                           lam[going], delta[going])
            if len(idx) == 0:
                break
            problems = problems.subset(going)
        R_new, t_new = problems.retract(Ra, ta, delta)
        G_new = problems.normal_equations(R_new, t_new)
        better = G_new[:, 6, 6] <= Ga[:, 6, 6]                           # False for NaN
        if better.all():
            Ra, ta, Ga = R_new, t_new, G_new
            if lam.any():
                lam = np.where(lam <= 1e-3, 0.0, 0.1 * lam)
            continue
        Ra[better], ta[better], Ga[better] = R_new[better], t_new[better], G_new[better]
        lam = np.where(better, np.where(lam <= 1e-3, 0.0, 0.1 * lam),
                       np.where(lam == 0.0, 1e-3, 10.0 * lam))
        alive = lam <= 1e6                             # else give up: it cannot descend
        if not alive.all():
            R[idx], t[idx], G[idx] = Ra, ta, Ga
            idx, Ra, ta, Ga, lam = idx[alive], Ra[alive], ta[alive], Ga[alive], lam[alive]
            problems = problems.subset(alive)
    R[idx], t[idx], G[idx] = Ra, ta, Ga
    return R, t, G, converged


def _refine(problems, R: np.ndarray, t: np.ndarray, owner: np.ndarray):
    """Refine starts R (K, 3, 3), t (K, 3) of `problems` (one per start; `owner[k]` the view it
    belongs to): all evaluated in one batch, those whose whitened cost is within
    2x + START_MARGIN_CHI2 of their view's best refined by `_levenberg_marquardt`.
    Returns owner (K',), R (K', 3, 3), t (K', 3), G (K', 7, 7), r_px (K', N, 2) of those that
    converged, or of all refined starts of a view none of whose starts converged."""
    G0 = problems.normal_equations(R, t)
    cost = np.where(np.isfinite(G0).all(axis=(1, 2)), G0[:, 6, 6], np.inf)
    best: dict[int, float] = {}
    for o, c in zip(owner.tolist(), cost.tolist()):
        best[o] = min(best.get(o, math.inf), c)
    keep = np.flatnonzero(cost <= 2.0 * np.array([best[o] for o in owner.tolist()])
                          + START_MARGIN_CHI2)
    sub = problems.subset(keep)
    R, t, G, converged = _levenberg_marquardt(sub, R[keep], t[keep], G0[keep])
    own = owner[keep]
    if not converged.all():         # an unconverged start is no minimum: no candidate (unless
        good = set(own[converged].tolist())           # its view has nothing better)
        use = np.array([c or o not in good for o, c in zip(own.tolist(), converged.tolist())])
        sub, own, R, t, G = sub.subset(use), own[use], R[use], t[use], G[use]
    return own, R, t, G, sub.residual_px(R, t)


# ============================================================================ floor camera


def _edge_vectors(xn: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(n, 4, 2) undistorted corners of n floor codes -> (n, 2) each code's estimate of the
    direction of world +x in a level, yaw-0 body frame (`edge_implied_yaw`); zero for a code
    whose rays do not all meet the floor."""
    d = xn @ camera.T_body_cam[:3, :2].T + camera.T_body_cam[:3, 2]   # rays in the body frame
    ok = np.all(np.isfinite(d), axis=(1, 2)) & np.all(d[:, :, 2] < -1e-6, axis=1)
    f = d[:, :, :2] / np.where(ok[:, None, None], -d[:, :, 2:3], 1.0)  # floor points
    tl, tr, br, bl = f[:, 0], f[:, 1], f[:, 2], f[:, 3]
    up = (tl - bl) + (tr - br)
    e = (tr - tl) + (br - bl) + np.column_stack([up[:, 1], -up[:, 0]])
    return np.where(ok[:, None], e, 0.0)


def edge_implied_yaw(sightings: list[FloorSighting], camera: CameraModel,
                     xn: np.ndarray | None = None) -> float | None:
    """Body yaw (rad) implied by the floor codes' edge directions in the image, assuming a level body.

    Each code's corners are cast onto a floor below a level body at yaw 0; the symbol's "right"
    (TL->TR, BL->BR) and its "up" turned by -90 deg (BL->TL, BR->TR) give the direction of world +x
    in that frame, at angle a, so the yaw is -a.  A tilt of up to 30 deg moves this by far less
    than 90 deg, which is what rules out 180-deg yaw flips.  None if no code's rays meet the floor.
    `xn` (4n, 2): the corners already undistorted (`undistort`)."""
    if not sightings:
        return None
    if xn is None:
        xn = undistort(camera, np.vstack([np.asarray(s.detection.corners_px, dtype=float)
                                          for s in sightings]))
    return _yaw_of_edges(_edge_vectors(np.asarray(xn).reshape(-1, 4, 2), camera).sum(axis=0))


def _yaw_of_edges(e: np.ndarray) -> float | None:
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


IPPE_BATCH_MIN = 4
"""Fewer views than this are initialised by OpenCV's IPPE one at a time (faster than `_ippe`'s
vectorised form for a handful)."""


def _ippe(X: np.ndarray, xn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """IPPE (Collins & Bartoli, "Infinitesimal Plane-Based Pose Estimation", IJCV 2014, Sec. 4 and
    Algorithm 1) for K views at once: plane points X (K, N, 2) (z = 0, N >= 4) and their
    normalised image points xn (K, N, 2) -> the two candidate poses of each view, R (K, 2, 3, 3),
    t (K, 2, 3) with p_cam = R [x, y, 0] + t (as cv2.solvePnPGeneric(SOLVEPNP_IPPE), whose
    homography estimate differs slightly for N > 4).  Raises np.linalg.LinAlgError when a view
    is degenerate.

    Homography H (plane -> image, h22 = 1) by the normalised DLT (Hartley & Zisserman 2004,
    Alg. 4.2); J its Jacobian at the plane origin, v = H(0); R_v rotates z onto the ray of v
    (IPPE eq. 29); A = B^-1 J with B = [I2, -v] R_v[:, :2]; gamma = the largest singular value of A
    and R~ = A / gamma the top-left 2x2 of R_v^T R, completed to a rotation in the two ways b, -b
    (eq. 30-32); each t by linear least squares on the projection equations (eq. 37).
    A degenerate view (e.g. all points at one pixel) gives NaN poses or LinAlgError."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return _ippe_unchecked(X, xn)


def _ippe_unchecked(X: np.ndarray, xn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K, N = X.shape[:2]
    mx = X.mean(axis=1, keepdims=True)
    Xc = X - mx                                               # plane points about their mean
    sx = np.sqrt(2.0 / (Xc ** 2).sum(axis=2).mean(axis=1))    # Hartley scaling (K,)
    my = xn.mean(axis=1, keepdims=True)
    sy = np.sqrt(2.0 / ((xn - my) ** 2).sum(axis=2).mean(axis=1))
    a = Xc * sx[:, None, None]
    b = (xn - my) * sy[:, None, None]
    A = np.zeros((K, N, 2, 9))                                # DLT rows, h = H row-major
    A[:, :, 0, 0:2] = a
    A[:, :, 0, 2] = 1.0
    A[:, :, 1, 3:5] = a
    A[:, :, 1, 5] = 1.0
    A[:, :, 0, 6:8] = -b[:, :, 0:1] * a
    A[:, :, 0, 8] = -b[:, :, 0]
    A[:, :, 1, 6:8] = -b[:, :, 1:2] * a
    A[:, :, 1, 8] = -b[:, :, 1]
    A = A.reshape(K, 2 * N, 9)
    M = A.transpose(0, 2, 1) @ A
    h = np.linalg.solve(M[:, :8, :8], -M[:, :8, 8:])[:, :, 0]
    Hn = np.concatenate([h, np.ones((K, 1))], axis=1).reshape(K, 3, 3)
    T_inv = np.zeros((K, 3, 3))                               # undo the image normalisation
    T_inv[:, 0, 0] = T_inv[:, 1, 1] = 1.0 / sy
    T_inv[:, :2, 2] = my[:, 0]
    T_inv[:, 2, 2] = 1.0
    H = (T_inv @ Hn) * np.stack([sx, sx, np.ones(K)], axis=1)[:, None, :]
    H = H / H[:, 2:3, 2:3]                                    # centred plane -> image
    v = H[:, :2, 2]
    J = H[:, :2, :2] - H[:, 2:3, :2] * H[:, :2, 2:3]          # d(image) / d(plane) at the origin
    ray = np.concatenate([v, np.ones((K, 1))], axis=1) / np.sqrt(1.0 + (v ** 2).sum(axis=1))[:, None]
    ax, ay, az = ray[:, 0], ray[:, 1], ray[:, 2]
    d = 1.0 / (1.0 + az)
    Rv = np.empty((K, 3, 3))                                  # R_v e_z = ray
    Rv[:, 0, 0], Rv[:, 0, 1], Rv[:, 0, 2] = 1.0 - ax * ax * d, -ax * ay * d, ax
    Rv[:, 1, 0], Rv[:, 1, 1], Rv[:, 1, 2] = -ax * ay * d, 1.0 - ay * ay * d, ay
    Rv[:, 2, 0], Rv[:, 2, 1], Rv[:, 2, 2] = -ax, -ay, 1.0 - (ax * ax + ay * ay) * d
    B = Rv[:, :2, :2] - v[:, :, None] * Rv[:, 2:3, :2]
    Am = np.linalg.solve(B, J)
    ata = Am.transpose(0, 2, 1) @ Am
    tr = ata[:, 0, 0] + ata[:, 1, 1]
    det = ata[:, 0, 0] * ata[:, 1, 1] - ata[:, 0, 1] ** 2
    gamma = np.sqrt(0.5 * (tr + np.sqrt(np.maximum(tr * tr - 4.0 * det, 0.0))))
    Rt = Am / gamma[:, None, None]
    b0 = np.sqrt(np.maximum(1.0 - Rt[:, 0, 0] ** 2 - Rt[:, 1, 0] ** 2, 0.0))
    b1 = np.sqrt(np.maximum(1.0 - Rt[:, 0, 1] ** 2 - Rt[:, 1, 1] ** 2, 0.0))
    b1 = np.where(Rt[:, 0, 0] * Rt[:, 0, 1] + Rt[:, 1, 0] * Rt[:, 1, 1] > 0.0, -b1, b1)
    R = np.empty((K, 2, 3, 3))
    for i, sign in enumerate((1.0, -1.0)):
        c1 = np.stack([Rt[:, 0, 0], Rt[:, 1, 0], sign * b0], axis=1)
        c2 = np.stack([Rt[:, 0, 1], Rt[:, 1, 1], sign * b1], axis=1)
        R[:, i] = Rv @ np.stack([c1, c2, np.cross(c1, c2)], axis=2)
    # t: least squares of [1, 0, -u; 0, 1, -v] t = [u r_z - r_x, v r_z - r_y], r = R [x, y, 0]
    r = Xc[:, None] @ R[:, :, :, :2].transpose(0, 1, 3, 2)    # (K, 2, N, 3)
    u, w = xn[:, None, :, 0], xn[:, None, :, 1]
    ATA = np.zeros((K, 1, 3, 3))
    ATA[:, 0, 0, 0] = ATA[:, 0, 1, 1] = N
    ATA[:, 0, 0, 2] = ATA[:, 0, 2, 0] = -xn[:, :, 0].sum(axis=1)
    ATA[:, 0, 1, 2] = ATA[:, 0, 2, 1] = -xn[:, :, 1].sum(axis=1)
    ATA[:, 0, 2, 2] = (xn ** 2).sum(axis=(1, 2))
    bx, by = u * r[..., 2] - r[..., 0], w * r[..., 2] - r[..., 1]
    ATb = np.stack([bx.sum(-1), by.sum(-1), -(u * bx + w * by).sum(-1)], axis=-1)
    t = np.linalg.solve(np.broadcast_to(ATA, (K, 2, 3, 3)), ATb[..., None])[..., 0]
    return R, t - (R[..., :2] @ mx[:, :, :, None])[..., 0]      # p_cam = R ([x, y] - mx) + t


def _chi2_bound(dof: int) -> float:
    """A loose upper bound of a chi-square(dof) draw (Wilson-Hilferty, about 5 sigma): a whitened
    cost above it means the start does not fit."""
    return dof * (1.0 - 2.0 / (9.0 * dof) + 5.0 * math.sqrt(2.0 / (9.0 * dof))) ** 3


class _FloorCodes:
    """The floor codes of a batch of frames, stacked: world corners P (c, 4, 3), symbol centres
    (c, 3), observed px uv (c, 4, 2), undistorted xn (c, 4, 2), whitening W (c, 8, 8) and edge
    vectors E (c, 2) (`_edge_vectors`)."""

    def __init__(self, sightings: list[FloorSighting], camera: CameraModel, sigma: float):
        self.P = np.array([np.asarray(s.corners_world, dtype=float).reshape(4, 3)
                           for s in sightings]).reshape(-1, 4, 3)
        self.centres = np.array([np.asarray(s.centre_world, dtype=float).reshape(3)
                                 for s in sightings]).reshape(-1, 3)
        self.uv = np.array([np.asarray(s.detection.corners_px, dtype=float).reshape(4, 2)
                            for s in sightings]).reshape(-1, 4, 2)
        self.xn = undistort(camera, self.uv.reshape(-1, 2)).reshape(-1, 4, 2)
        self.W = corner_whitening([s.detection for s in sightings], sigma)
        self.E = _edge_vectors(self.xn, camera)


def _camera_starts(codes: _FloorCodes, views: list[np.ndarray], which: list[int], sqpnp: bool
                   ) -> tuple[list[int], list[np.ndarray], list[np.ndarray]]:
    """Candidate T_cam_world of views `which`: (view index, R_cam_world, t_cam_world) lists.
    IPPE's two solutions per view (`_ippe` on all views with the same number of codes; OpenCV's
    IPPE / IPPE_SQUARE one view at a time for fewer than IPPE_BATCH_MIN views, or when the
    batch is degenerate), or with `sqpnp` OpenCV's SQPnP."""
    owner, R_cw, t_cw = [], [], []

    def opencv(k: int, method: int) -> None:
        v = views[k]
        for R, t in _initial_camera_poses(codes.P[v].reshape(-1, 3), codes.xn[v].reshape(-1, 2),
                                          codes.centres[v[0]] if len(v) == 1 and
                                          method == cv2.SOLVEPNP_IPPE_SQUARE else None, method):
            owner.append(k)
            R_cw.append(R)
            t_cw.append(t)

    if sqpnp:
        for k in which:
            opencv(k, cv2.SOLVEPNP_SQPNP)
        return owner, R_cw, t_cw
    by_n: dict[int, list[int]] = {}
    for k in which:
        by_n.setdefault(len(views[k]), []).append(k)
    for n, ks in by_n.items():
        idx = np.array([views[k] for k in ks])
        P = codes.P[idx].reshape(-1, 4 * n, 3)
        try:
            if len(ks) < IPPE_BATCH_MIN or np.any(P[:, :, 2] != 0.0):
                raise np.linalg.LinAlgError("few views, or not on the floor z = 0")
            R, t = _ippe(P[:, :, :2], codes.xn[idx].reshape(-1, 4 * n, 2))
        except np.linalg.LinAlgError:
            for k in ks:
                opencv(k, cv2.SOLVEPNP_IPPE_SQUARE if n == 1 else cv2.SOLVEPNP_IPPE)
            continue
        owner += [k for k in ks for _ in range(2)]
        R_cw += list(R.reshape(-1, 3, 3))
        t_cw += list(t.reshape(-1, 3))
    return owner, R_cw, t_cw


def _solve_floor_views(codes: _FloorCodes, views: list[np.ndarray], camera: CameraModel,
                       ambiguity_chi2: float) -> list[tuple | None]:
    """Best refined body pose of each view (an array of code indices into `codes`):
    (R_world_body, t_world_body, G (7, 7), r_px (4n, 2), rms_px, ambiguous) or None, G the
    `_whitened_normal_equations` there (H = G[:6, :6] = J^T W^T W J).

    Starts: IPPE (`_camera_starts`), and SQPnP when no IPPE start refined to a fit whose
    whitened error is plausible (`_chi2_bound`); refined in batches of views with the same number
    of codes; candidates under the floor or > MAX_YAW_DEVIATION_RAD from the edge-implied yaw are
    dropped; of those within `ambiguity_chi2` of the best, the most level."""
    projector = Projector(camera)
    R_bc, t_bc = camera.T_body_cam[:3, :3], camera.T_body_cam[:3, 3]
    R_cb = np.ascontiguousarray(R_bc.T)
    t_cb = -R_cb @ t_bc
    E = np.add.reduceat(codes.E[np.concatenate(views)],           # each view's sum of its codes'
                        np.cumsum([0] + [len(v) for v in views[:-1]]))   # edge vectors
    hints = np.where(np.any(E != 0.0, axis=1), -np.arctan2(E[:, 1], E[:, 0]), np.nan)
    finite = np.isfinite(codes.xn).all(axis=(1, 2))
    starts: list[list] = [[] for _ in views]
    cands: list[list] = [[] for _ in views]

    def add_starts(which: list[int], sqpnp: bool) -> None:
        """Starts of views `which`, refined in batches by number of codes, into `cands`."""
        owner, R_cw, t_cw = _camera_starts(codes, views, [k for k in which
                                                          if finite[views[k]].all()], sqpnp)
        if not owner:
            return
        R_wc = np.array(R_cw).transpose(0, 2, 1)
        R_wb = R_wc @ R_cb                          # T_world_body = T_cam_world^-1 T_cam_body
        t_wb = -(R_wc @ np.array(t_cw)[:, :, None])[:, :, 0] - R_wb @ t_bc
        owner = np.asarray(owner)
        new = np.ones(len(owner), dtype=bool)     # not a duplicate (1e-3 rad, 1e-3 m) of another
        if sqpnp:                                   # SQPnP's is usually one of IPPE's
            for i, k in enumerate(owner.tolist()):
                new[i] = not any(_same_pose((R_wb[i], t_wb[i]), x, 1e-3, 1e-3)
                                 for x in starts[k])
        else:                                       # IPPE's two of a view (consecutive)
            pair = np.flatnonzero(owner[1:] == owner[:-1])
            cos = 0.5 * (np.einsum("kij,kij->k", R_wb[pair], R_wb[pair + 1]) - 1.0)
            new[pair + 1] = ~((cos >= math.cos(1e-3)) &
                              (np.linalg.norm(t_wb[pair] - t_wb[pair + 1], axis=1) <= 1e-3))
        by_n: dict[int, list[int]] = {}
        for i in np.flatnonzero(new).tolist():
            k = int(owner[i])
            starts[k].append((R_wb[i], t_wb[i]))
            by_n.setdefault(len(views[k]), []).append(i)
        for n, group in by_n.items():
            own = owner[group]
            idx = np.array([views[k] for k in own])                              # (K, n)
            problems = _FloorProblems(projector, R_cb, t_cb, codes.P[idx].reshape(-1, 4 * n, 3),
                                      codes.uv[idx].reshape(-1, 4 * n, 2), codes.W[idx])
            own, R, t, G, r = _refine(problems, R_wb[group], t_wb[group], own)
            hint = hints[own]
            ok = np.isfinite(G).all(axis=(1, 2)) \
                & (R[:, 2] @ t_bc + t[:, 2] > 0.0) \
                & (np.isnan(hint) | (np.abs(wrap_angle(np.arctan2(R[:, 1, 0], R[:, 0, 0]) - hint))
                                     <= MAX_YAW_DEVIATION_RAD))
            # (camera above the floor: else mirrored corners; yaw near the edges': no flip)
            rms = np.sqrt(np.mean(r ** 2, axis=(1, 2)))
            for i in np.flatnonzero(ok).tolist():
                k = int(own[i])
                if any(_same_minimum((c[0], c[1]), c[2][:6, :6], (R[i], t[i])) for c in cands[k]):
                    continue
                cands[k].append((R[i], t[i], G[i], r[i], float(rms[i])))

    add_starts(list(range(len(views))), sqpnp=False)
    # SQPnP (a global solver) only where IPPE found no plausible fit
    retry = [k for k, v in enumerate(views) if len(v) > 1 and
             min((c[2][6, 6] for c in cands[k]), default=math.inf) > _chi2_bound(8 * len(v))]
    if retry:
        add_starts(retry, sqpnp=True)
    out: list[tuple | None] = []
    for cs in cands:
        if len(cs) < 2:
            out.append((*cs[0], False) if cs else None)
            continue
        best = min(c[2][6, 6] for c in cs)
        close = [c for c in cs if c[2][6, 6] <= best + ambiguity_chi2]      # whitened: chi^2
        c = max(close, key=lambda c: c[0][2, 2])      # most level: body z nearest world z
        out.append((*c, len(close) > 1))
    return out


def estimate_floor_poses(frames: list[list[FloorSighting]], camera: CameraModel,
                         corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, *,
                         max_rms_px: float = MAX_REPROJECTION_RMS_PX,
                         ambiguity_chi2: float = AMBIGUITY_CHI2,
                         gimbal_roll_pitch_sigma_rad: float = GIMBAL_ROLL_PITCH_SIGMA_RAD
                         ) -> list[PnPResult | None]:
    """`estimate_floor_pose` of many frames (each a list of floor sightings), computed together:
    the corners undistorted and whitened at once, and the views refined in batches (one
    vectorised evaluation per LM step for all frames with the same number of codes)."""
    sigma = float(corner_sigma_px)
    if not sigma > 0:
        raise EstimationError(f"corner_sigma_px must be positive, got {corner_sigma_px!r}")
    frames = [list(f) for f in frames]
    out: list[PnPResult | None] = [None] * len(frames)
    owner = [i for i, f in enumerate(frames) if f]
    if not owner:
        return out
    all_sightings = [s for i in owner for s in frames[i]]
    codes = _FloorCodes(all_sightings, camera, sigma)
    first = np.cumsum([0] + [len(frames[i]) for i in owner])
    views = [np.arange(a, b) for a, b in zip(first[:-1], first[1:])]
    dropped: list[list[str]] = [[] for _ in owner]
    done: list[tuple] = []                  # (k, R, t, H, rms, ambiguous)
    pending = list(range(len(owner)))
    while pending:
        sols = _solve_floor_views(codes, [views[k] for k in pending], camera, ambiguity_chi2)
        retry = []
        for k, sol in zip(pending, sols):
            if sol is None:
                continue
            R, t, G, r, rms, ambiguous = sol
            if rms <= max_rms_px:
                done.append((k, R, t, G[:6, :6], rms, ambiguous))
            elif len(views[k]) > 1:          # leave out the worst-fitting code and solve again
                worst = int(np.argmax((r.reshape(-1, 8) ** 2).sum(axis=1)))
                dropped[k].append(all_sightings[views[k][worst]].detection.payload)
                views[k] = np.delete(views[k], worst)
                retry.append(k)
        pending = retry
    if not done:
        return out
    covs, ok = _covariances(np.array([d[3] for d in done]))   # H whitened: (J^T W J)^-1
    gimbaled = camera.mount == "gimbaled"
    Ts = np.zeros((len(done), 4, 4))
    Ts[:, :3, :3] = [d[1] for d in done]
    Ts[:, :3, 3] = [d[2] for d in done]
    Ts[:, 3, 3] = 1.0
    Ts_world_cam = Ts @ camera.T_body_cam
    for (k, _, _, _, rms, ambiguous), T, T_world_cam, cov, good in zip(done, Ts, Ts_world_cam,
                                                                        covs, ok):
        if not good:
            continue
        if gimbaled:
            T = level_frame(T)
            keep = np.diag([0.0, 0.0, 1.0, 1.0, 1.0, 1.0])
            cov = keep @ cov @ keep + np.diag([gimbal_roll_pitch_sigma_rad ** 2] * 2 + [0.0] * 4)
        out[owner[k]] = PnPResult(
            T_world_body=T, covariance=cov, T_world_cam=T_world_cam, n_codes=len(views[k]),
            payloads=[all_sightings[c].detection.payload for c in views[k]],
            reprojection_rms_px=rms, ambiguous=ambiguous, dropped_payloads=dropped[k])
    return out


def estimate_floor_pose(sightings: list[FloorSighting], camera: CameraModel,
                        corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, *,
                        max_rms_px: float = MAX_REPROJECTION_RMS_PX,
                        ambiguity_chi2: float = AMBIGUITY_CHI2,
                        gimbal_roll_pitch_sigma_rad: float = GIMBAL_ROLL_PITCH_SIGMA_RAD
                        ) -> PnPResult | None:
    """Body pose from all floor codes of one floor-camera frame, or None (no code, no solution,
    or reprojection RMS above `max_rms_px` even after leaving out the worst-fitting codes).

    1. corners undistorted (`undistort`); candidates: one code: IPPE_SQUARE's two solutions;
       several: planar IPPE's two, and SQPnP's when no IPPE candidate refines to a plausible fit;
    2. the candidates whose whitened error is within 2x + START_MARGIN_CHI2 of the best one's
       are refined by Gauss-Newton / LM on the reprojection error in distorted pixels over the
       body pose (`_levenberg_marquardt`; 2-4 evaluations);
    3. candidates whose yaw is > 90 deg from `edge_implied_yaw` are dropped (no 180-deg flips);
       of those whose squared error is within `ambiguity_chi2` sigma^2 of the best, the most level;
    4. covariance (J^T W J)^-1, J = d(distorted px)/d(xi) at the returned pose, xi the body-frame
       right perturbation [rx, ry, rz, tx, ty, tz] (GTSAM Pose3; fusion/qr/crb.py), W
       block-diagonal with one (8, 8) block C_i^-1 per code: C_i the detection's `corner_cov_px2`
       when set (its corners come from one homography fit, so their errors are correlated), else
       sigma_i^2 I with sigma_i its `corner_sigma_px`, else `corner_sigma_px`; the LM of step 2
       minimises the same weighted error.

    "gimbaled" camera: the camera is stabilised, so the airframe's roll and pitch are not observed.
    The returned T_world_body is then the LEVEL body frame (roll = pitch = 0, estimated yaw and
    position), and its covariance keeps the PnP marginal of [rz, tx, ty, tz] while rx and ry get
    variance gimbal_roll_pitch_sigma_rad^2 ((10 deg)^2 by default) and no correlation.

    Many frames: `estimate_floor_poses` (the same, about 10x faster per frame)."""
    return estimate_floor_poses([sightings], camera, corner_sigma_px, max_rms_px=max_rms_px,
                                ambiguity_chi2=ambiguity_chi2,
                                gimbal_roll_pitch_sigma_rad=gimbal_roll_pitch_sigma_rad)[0]


# ============================================================================ front camera


def position_jacobian_wrt_body(T_world_body: np.ndarray, camera: CameraModel,
                                p_cam: np.ndarray) -> np.ndarray:
    """(3, 6) d p_world / d xi of p_world = camera.T_world_cam(T_world_body Exp(xi)) p_cam, xi the
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


def estimate_load_observations_frames(
        frames: list[tuple[list[LoadSighting], np.ndarray, np.ndarray | None]],
        camera: CameraModel, world: World, corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, *,
        max_rms_px: float = MAX_REPROJECTION_RMS_PX, ambiguity_chi2: float = AMBIGUITY_CHI2
        ) -> list[list[LoadObservation]]:
    """`estimate_load_observations` of many front-camera frames, each given as (sightings,
    T_world_body, cov_body or None), computed together (all codes' LM steps in one vectorised
    evaluation); one list of observations per frame."""
    sigma = float(corner_sigma_px)
    items = [(f, s) for f, (sightings, _, _) in enumerate(frames) for s in sightings
             if np.asarray(s.detection.corners_px, dtype=float).shape == (4, 2)]
    out: list[list[LoadObservation]] = [[] for _ in frames]
    if not items:
        return out
    uv = np.array([np.asarray(s.detection.corners_px, dtype=float) for _, s in items])
    xn = undistort(camera, uv.reshape(-1, 2)).reshape(-1, 4, 2)
    W = corner_whitening([s.detection for _, s in items], sigma)
    corners_S = symbol_corners_S(world.load_side_m)
    good = np.flatnonzero(np.isfinite(xn).all(axis=(1, 2)))
    owner, R0, t0 = [], [], []
    try:                                     # IPPE (IPPE_SQUARE's), both solutions of each code
        if len(good) < IPPE_BATCH_MIN:
            raise np.linalg.LinAlgError("few codes")
        R, t = _ippe(np.broadcast_to(corners_S[:, :2], (len(good), 4, 2)), xn[good])
        owner, R0, t0 = np.repeat(good, 2), R.reshape(-1, 3, 3), t.reshape(-1, 3)
    except np.linalg.LinAlgError:            # OpenCV's, one code at a time
        for c in good.tolist():
            for R, t in _initial_camera_poses(corners_S, xn[c], np.zeros(3),
                                              cv2.SOLVEPNP_IPPE_SQUARE):
                owner.append(c)
                R0.append(R)
                t0.append(t)
    if len(owner) == 0:
        return out
    owner = np.asarray(owner)
    problems = _SymbolProblems(Projector(camera), corners_S, uv[owner], W[owner][:, None])
    own, R, t, G, r = _refine(problems, np.array(R0), np.array(t0), owner)
    T_world_cam = np.array([camera.T_world_cam(np.asarray(T, dtype=float)) for _, T, _ in frames])
    frame_of = np.array([f for f, _ in items])[own]
    up_z = np.einsum("kj,kj->k", T_world_cam[frame_of, 2, :3], R[:, :, 1])  # symbol up, world z
    rms = np.sqrt(np.mean(r ** 2, axis=(1, 2)))
    cands: dict[int, list[int]] = {}
    for i in np.flatnonzero(np.isfinite(G).all(axis=(1, 2)) & (t[:, 2] > 0)).tolist():
        cands.setdefault(int(own[i]), []).append(i)
    chosen = []
    for c, cs in sorted(cands.items()):
        if len(cs) > 1:
            best = min(G[i, 6, 6] for i in cs)
            close = [i for i in cs if G[i, 6, 6] <= best + ambiguity_chi2]  # whitened: chi^2
            cs = [max(close, key=lambda i: up_z[i])]          # symbol up nearest world +z
        if rms[cs[0]] <= max_rms_px:
            chosen.append(cs[0])
    if not chosen:
        return out
    covs, ok = _covariances(G[chosen, :6, :6])
    chosen = np.asarray(chosen)[ok]
    f = frame_of[chosen]
    p_cam, cov_cam = t[chosen], covs[ok, 3:, 3:]
    R_wc = T_world_cam[f, :3, :3]
    p_world = (R_wc @ p_cam[:, :, None])[:, :, 0] + T_world_cam[f, :3, 3]
    cov_world = R_wc @ cov_cam @ R_wc.transpose(0, 2, 1)
    for k, (i, fk) in enumerate(zip(chosen.tolist(), f.tolist())):
        c = int(own[i])
        _, T_world_body, cov_body = frames[fk]
        cw = cov_world[k]
        if cov_body is not None:
            Jb = position_jacobian_wrt_body(np.asarray(T_world_body, dtype=float), camera,
                                            p_cam[k])
            cw = cw + Jb @ np.asarray(cov_body, dtype=float) @ Jb.T
        s = items[c][1]
        out[fk].append(LoadObservation(timestamp_ns=int(s.detection.timestamp_ns),
                                       load_id=s.load_id, p_world=p_world[k],
                                       cov_world=0.5 * (cw + cw.T), p_cam=p_cam[k],
                                       cov_cam=cov_cam[k], corners_px=uv[c].copy()))
    return out
    covs, ok = _covariances(np.array([x[2] for x in chosen]))
    for (c, t, _), cov, good in zip(chosen, covs, ok):
        if not good:
            continue
        f, s = items[c]
        _, T_world_body, cov_body = frames[f]
        R_wc, t_wc = T_world_cam[f][:3, :3], T_world_cam[f][:3, 3]
        cov_cam = cov[3:, 3:].copy()
        p_cam = t.copy()
        cov_world = R_wc @ cov_cam @ R_wc.T
        if cov_body is not None:
            Jb = position_jacobian_wrt_body(np.asarray(T_world_body, dtype=float), camera, p_cam)
            cov_world = cov_world + Jb @ np.asarray(cov_body, dtype=float) @ Jb.T
        out[f].append(LoadObservation(timestamp_ns=int(s.detection.timestamp_ns),
                                      load_id=s.load_id, p_world=R_wc @ p_cam + t_wc,
                                      cov_world=0.5 * (cov_world + cov_world.T), p_cam=p_cam,
                                      cov_cam=cov_cam, corners_px=uv[c].copy()))
    return out


def estimate_load_observations(sightings: list[LoadSighting], camera: CameraModel, world: World,
                               T_world_body: np.ndarray, cov_body: np.ndarray | None = None,
                               corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, *,
                               max_rms_px: float = MAX_REPROJECTION_RMS_PX,
                               ambiguity_chi2: float = AMBIGUITY_CHI2) -> list[LoadObservation]:
    """One LoadObservation per load code of one front-camera frame whose corners fit a square of
    side world.load_side_m (reprojection RMS <= max_rms_px; others are skipped).

    p_cam (3,) = the code centre in the camera frame (m) from IPPE_SQUARE + LM in distorted pixels
    (both IPPE solutions unless one fits far worse: START_MARGIN_CHI2), cov_cam (3, 3) = the centre
    block of (J^T C^-1 J)^-1 (fusion/qr/crb.symbol_reprojection), C the detection's
    `corner_cov_px2`, else sigma^2 I with sigma its `corner_sigma_px`, else `corner_sigma_px` (the
    LM minimises the same weighted error);
    p_world = T_world_cam p_cam with T_world_cam = camera.T_world_cam(T_world_body), and
    cov_world = R_world_cam cov_cam R_world_cam^T + J_b cov_body J_b^T, J_b = d p_world / d xi
    (`position_jacobian_wrt_body`) for the body-frame right perturbation xi of T_world_body
    (cov_body None: drone pose exact).
    IPPE's two-fold ambiguity barely moves the centre; when both fit, the one whose symbol "up"
    is nearer world +z is taken (load codes hang on vertical faces, up = +z).

    Many frames: `estimate_load_observations_frames` (the same, computed together)."""
    return estimate_load_observations_frames([(sightings, T_world_body, cov_body)], camera, world,
                                             corner_sigma_px, max_rms_px=max_rms_px,
                                             ambiguity_chi2=ambiguity_chi2)[0]


# ============================================================================ whole flights


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


FRAMES_PER_BATCH = 512
"""Frames solved together by `pnp_trajectory` / `pnp_load_observations` (bounded memory)."""


def pnp_trajectory(frames: dict[int, list[QRDetection]], camera: CameraModel, world: World,
                   corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX, name: str = "pnp"
                   ) -> tuple[Trajectory, PnPStats]:
    """Per-frame PnP body poses of a floor-camera flight: {timestamp_ns: detections} ->
    (Trajectory with (N, 6, 6) covariances, PnPStats).  Frames with no usable floor code are
    left out (counted in the stats); rejected payloads (fusion.qr.codes.classify) are never used.
    Each frame is solved on its own (`estimate_floor_pose`), FRAMES_PER_BATCH frames at a time
    (`estimate_floor_poses`)."""
    stats = PnPStats()
    ts_out, T_out, cov_out, rms = [], [], [], []
    codes_seen = []
    per_pose: Counter = Counter()
    with_floor = []
    for ts in sorted(frames):
        stats.n_frames += 1
        codes = classify(frames[ts], world)
        codes_seen.append(codes)
        if codes.floor:
            with_floor.append((ts, codes.floor))
        else:
            stats.n_without_floor_code += 1
    for b in range(0, len(with_floor), FRAMES_PER_BATCH):
        batch = with_floor[b:b + FRAMES_PER_BATCH]
        for (ts, _), res in zip(batch, estimate_floor_poses([f for _, f in batch], camera,
                                                            corner_sigma_px)):
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
    T = interpolate_pose(trajectory.T_world_body[i - 1], trajectory.T_world_body[i], a)
    cov = None if covs is None else covs[i - 1 if a < 0.5 else i]
    return T, cov


def pnp_load_observations(front_frames: dict[int, list[QRDetection]], front_camera: CameraModel,
                          world: World, trajectory: Trajectory,
                          corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
                          max_gap_s: float = 0.1) -> list[LoadObservation]:
    """Load observations of a flight's front-camera frames ({timestamp_ns: detections}), placed
    with the drone pose of `trajectory` at each frame (`pose_at`); frames without a pose are
    skipped.  Rejected payloads (classify) are never used.  Solved FRAMES_PER_BATCH frames at a
    time (`estimate_load_observations_frames`)."""
    todo = []
    for ts in sorted(front_frames):
        codes = classify(front_frames[ts], world)
        if not codes.loads:
            continue
        pose = pose_at(trajectory, ts, max_gap_s)
        if pose is None:
            continue
        todo.append((codes.loads, pose[0], pose[1]))
    out: list[LoadObservation] = []
    for b in range(0, len(todo), FRAMES_PER_BATCH):
        for obs in estimate_load_observations_frames(todo[b:b + FRAMES_PER_BATCH], front_camera,
                                                     world, corner_sigma_px):
            out.extend(obs)
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
