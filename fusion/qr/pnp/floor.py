"""Floor-camera PnP: the body pose from all floor codes of a frame, with its covariance.

All floor codes of a frame are solved at once (4 known world corners each), started by IPPE (both
of its two-fold solutions; SQPnP too when neither refines to a plausible fit), refined by the
batched LM (fusion/qr/pnp/lm.py) on the whitened reprojection error in DISTORTED pixels
(fusion/qr/reprojection.py's model), and given the covariance (J^T W J)^-1 of that model.

Where this departs from the paper (Alg. 1-3): the paper uses the single code nearest the image
centre and assumes a level camera; we use all codes in view and estimate the full 6-DOF pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from fusion.camera import CameraModel
from fusion.errors import EstimationError
from fusion.geometry import cross_rows, level_frame, se3_exp, so3_exp_stack, so3_log, wrap_angle
from fusion.qr.codes import FloorSighting
from fusion.qr.pnp.ippe import ippe_or_none, opencv_starts
from fusion.qr.pnp.lm import (
    AMBIGUITY_CHI2,
    MAX_REPROJECTION_RMS_PX,
    NormalEquations,
    RefinedStarts,
    Starts,
    covariances,
    refine_starts,
    same_minimum,
    same_pose,
)
from fusion.qr.pnp.undistort import undistort
from fusion.qr.pnp.whitening import (
    CORNER_CLASSES,
    CORNER_COORDINATES,
    DEFAULT_CORNER_SIGMA_PX,
    corner_classes,
    corner_whitening,
    placement_factors,
    whitening_with,
)
from fusion.qr.reprojection import Projector
from fusion.types import Mount
from fusion.world import FloorLayout, Placement

GIMBAL_ROLL_PITCH_SIGMA_RAD = math.radians(10.0)
"""Standard deviation given to the (unobserved) airframe roll and pitch with a gimbaled camera."""
MAX_YAW_DEVIATION_RAD = math.pi / 2
"""A candidate whose yaw is further than this from the yaw implied by the codes' edges is wrong."""
DUPLICATE_START_RAD = 1e-3
DUPLICATE_START_M = 1e-3
"""Two starts of a view closer than these (rotation, position) are one start."""
MIN_RAY_DOWN = 1e-6
"""A corner's ray (body frame, unit z) must point down by at least this to meet the floor."""
PLACEMENT_GATE_SIGMAS = 3.0
"""With the codes' placement uncertain, a frame's reprojection RMS may exceed max_rms_px by this
many times the RMS by which its codes' placement sigma moves their corners (codes laid within
3 sigma of their payloads are not outliers; a wrong code is metres off)."""
CHI2_BOUND_SIGMAS = 5.0
"""`chi2_bound`: how many standard deviations above a chi-square's mean a plausible fit may be."""


@dataclass
class PnPResult:
    """Body pose of one floor-camera frame.

    `T_world_body` (4, 4); `covariance` (6, 6) [rx, ry, rz, tx, ty, tz], body frame, right
    perturbation; `T_world_cam` (4, 4); `reprojection_rms_px` over all corners used (distorted px).
    `ambiguous`: two solutions fitted the corners equally well and the more level one was taken.
    `dropped_payloads`: codes left out as outliers (their corners did not fit the others).
    `chi2`: the whitened reprojection error (chi-square with 8 n_codes - 6 dof when the corner
    covariances are right; fusion.estimate.variance).
    Per corner class c (whitening.CORNER_CLASSES: refined, decoder), for
    fusion.estimate.variance.pnp_class_components: `class_chi2` (k,) the class's share of chi2;
    `class_covariance` (k, 6, 6) G_c = H^-1 H_c H^-1, the class's share of `covariance` (H_c its
    codes' information, sum_c G_c = covariance less the gimbal prior); `class_redundancy` (k, k)
    T with E[chi2_c] = sum_c' T[c, c'] s_c' when class c' has variance factor s_c' (`class_parts`).
    `free_tilt_covariance` (2, 2): a gimbaled camera's free solve's [rx, ry] block before
    `condition_on_level` (None for a body-fixed camera), for the tilt consider's share
    (fusion.estimate.tiltconsider.level_kept_fraction).
    `placement_covariance` (k, 6, 6): with the codes' placement uncertain (`floor_whitening`),
    the part of each class's G_c that their placement explains, H^-1 A_c^T B_c B_c^T A_c H^-1
    (A the whitened pose Jacobian, B the whitened placement factors, of the class's codes;
    `class_parts`): the part of the error common to every frame that sees the
    same codes (fusion.estimate.correlation); None when the codes are laid exactly."""

    T_world_body: np.ndarray
    covariance: np.ndarray
    T_world_cam: np.ndarray
    n_codes: int
    payloads: list[str]
    reprojection_rms_px: float
    class_chi2: np.ndarray
    class_covariance: np.ndarray
    class_redundancy: np.ndarray
    ambiguous: bool = False
    dropped_payloads: list[str] = field(default_factory=list)
    chi2: float = math.nan
    free_tilt_covariance: np.ndarray | None = None
    placement_covariance: np.ndarray | None = None


@dataclass
class FloorCandidate:
    """A refined body pose of one view: R_world_body (3, 3), t_world_body (3,), the information
    H (6, 6) = J^T W^T W J there, the whitened cost (chi-square), the px residuals (4n, 2) and
    their RMS."""

    R_world_body: np.ndarray
    t_world_body: np.ndarray
    information: np.ndarray
    cost: float
    residual_px: np.ndarray
    rms_px: float


@dataclass
class FloorSolution:
    """The candidate chosen for a view; `ambiguous` when another fitted within the ambiguity
    margin and the near-level rule decided."""

    candidate: FloorCandidate
    ambiguous: bool


class FloorProblems:
    """K floor-camera problems with the same number n of codes: world corners P (K, 4n, 3),
    observed px z (K, 4n, 2), whitening W (K, n, 8, 8); unknown the body pose (R, t) of
    T_world_body, perturbed on the right by [w, v] (fusion/qr/reprojection.floor_reprojection),
    retracted as R exp(w), t + R v."""

    def __init__(
        self,
        projector: Projector,
        R_cb: np.ndarray,
        t_cb: np.ndarray,
        P: np.ndarray,
        z: np.ndarray,
        W: np.ndarray,
    ):
        self.projector, self.R_cb, self.t_cb = projector, R_cb, t_cb
        self.P, self.z, self.W = P, z, W

    @classmethod
    def for_camera(cls, camera: CameraModel, P: np.ndarray, z: np.ndarray, W: np.ndarray) -> FloorProblems:
        """Problems of `camera` (its T_body_cam inverted once)."""
        R_cb = np.ascontiguousarray(camera.T_body_cam[:3, :3].T)
        return cls(Projector(camera), R_cb, -R_cb @ camera.T_body_cam[:3, 3], P, z, W)

    def subset(self, idx: np.ndarray) -> FloorProblems:
        return FloorProblems(self.projector, self.R_cb, self.t_cb, self.P[idx], self.z[idx], self.W[idx])

    def residual_px(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K, 4n, 2) reprojection errors in pixels of poses R (K, 3, 3), t (K, 3)."""
        p_cam = ((self.P - t[:, None, :]) @ R) @ self.R_cb.T + self.t_cb
        uv, _ = self.projector.project(p_cam.reshape(-1, 3), jacobian=False)
        return uv.reshape(self.z.shape) - self.z

    def _augmented(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K, N, 2, 7) [J | r] at poses R, t: J = d px / d xi, d p_cam / d xi = R_cb [[p_body]x, -I]."""
        K, N = self.P.shape[:2]
        p_body = ((self.P - t[:, None, :]) @ R).reshape(-1, 3)  # (K N, 3)
        uv, J_proj = self.projector.project(p_body @ self.R_cb.T + self.t_cb)
        A = J_proj @ self.R_cb  # d px / d p_body
        Jr = np.empty((K * N, 2, 7))  # [J | r]
        Jr[:, :, :3] = cross_rows(A, p_body)  # A [p_body]x
        Jr[:, :, 3:6] = -A
        Jr[:, :, 6] = uv - self.z.reshape(-1, 2)
        return Jr.reshape(K, N, 2, 7)

    def normal_equations(self, R: np.ndarray, t: np.ndarray) -> NormalEquations:
        """Whitened normal equations at poses R, t."""
        return NormalEquations.from_augmented(self._augmented(R, t), self.W)

    def whitened_jacobian(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K, 8 n, 6) whitened pose Jacobian W d px / d xi at poses R, t."""
        K, N = self.P.shape[:2]
        J = self._augmented(R, t)[..., :6].reshape(K, N // 4, CORNER_COORDINATES, 6)
        return (self.W @ J).reshape(K, 2 * N, 6)

    @staticmethod
    def retract(R: np.ndarray, t: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return R @ so3_exp_stack(delta[:, :3]), t + (R @ delta[:, 3:, None])[:, :, 0]


# ============================================================================ yaw from the edges


def _edge_vectors(xn: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(n, 4, 2) undistorted corners of n floor codes -> (n, 2) each code's estimate of the
    direction of world +x in a level, yaw-0 body frame (`edge_implied_yaw`); zero for a code
    whose rays do not all meet the floor."""
    d = xn @ camera.T_body_cam[:3, :2].T + camera.T_body_cam[:3, 2]  # rays in the body frame
    ok = np.all(np.isfinite(d), axis=(1, 2)) & np.all(d[:, :, 2] < -MIN_RAY_DOWN, axis=1)
    f = d[:, :, :2] / np.where(ok[:, None, None], -d[:, :, 2:3], 1.0)  # floor points
    tl, tr, br, bl = f[:, 0], f[:, 1], f[:, 2], f[:, 3]
    up = (tl - bl) + (tr - br)
    e = (tr - tl) + (br - bl) + np.column_stack([up[:, 1], -up[:, 0]])
    return np.where(ok[:, None], e, 0.0)


def edge_implied_yaw(
    sightings: list[FloorSighting], camera: CameraModel, xn: np.ndarray | None = None
) -> float | None:
    """Body yaw (rad) implied by the floor codes' edge directions in the image, for a level body.

    Each code's corners are cast onto a floor below a level body at yaw 0; the symbol's "right"
    (TL->TR, BL->BR) and its "up" turned by -90 deg (BL->TL, BR->TR) give the direction of world +x
    in that frame, at angle a, so the yaw is -a.  A tilt of up to 30 deg moves this by far less
    than 90 deg, which is what rules out 180-deg yaw flips.  None if no code's rays meet the floor.
    `xn` (4n, 2): the corners already undistorted (`undistort`)."""
    if not sightings:
        return None
    if xn is None:
        xn = undistort(
            camera, np.vstack([np.asarray(s.detection.corners_px, dtype=float) for s in sightings])
        )
    e = _edge_vectors(np.asarray(xn).reshape(-1, 4, 2), camera).sum(axis=0)
    return float(-math.atan2(e[1], e[0])) if np.any(e) else None


# ============================================================================ starts and solving


def chi2_bound(dof: int) -> float:
    """A loose upper bound of a chi-square(dof) draw (Wilson-Hilferty, CHI2_BOUND_SIGMAS sigma):
    a whitened cost above it means the start does not fit."""
    return dof * (1.0 - 2.0 / (9.0 * dof) + CHI2_BOUND_SIGMAS * math.sqrt(2.0 / (9.0 * dof))) ** 3


class FloorCodes:
    """The floor codes of a batch of frames, stacked: world corners P (c, 4, 3), symbol centres
    (c, 3), observed px uv (c, 4, 2), undistorted xn (c, 4, 2), whitening W (c, 8, 8) (with the
    codes' `placement` when enabled: `floor_whitening`), each code's placement px (c,) (the
    RMS per corner coordinate by which its placement sigma moves its corners; 0 without), corner
    classes (c,) and edge vectors E (c, 2) (`_edge_vectors`)."""

    def __init__(
        self,
        sightings: list[FloorSighting],
        camera: CameraModel,
        sigma: float,
        placement: Placement | FloorLayout | None = None,
    ):
        self.P = np.array(
            [np.asarray(s.corners_world, dtype=float).reshape(4, 3) for s in sightings]
        ).reshape(-1, 4, 3)
        self.centres = np.array(
            [np.asarray(s.centre_world, dtype=float).reshape(3) for s in sightings]
        ).reshape(-1, 3)
        self.uv = np.array(
            [np.asarray(s.detection.corners_px, dtype=float).reshape(4, 2) for s in sightings]
        ).reshape(-1, 4, 2)
        self.xn = undistort(camera, self.uv.reshape(-1, 2)).reshape(-1, 4, 2)
        self.W = corner_whitening([s.detection for s in sightings], sigma)
        self.placement_px = np.zeros(len(sightings))
        self.placement_F: np.ndarray | None = None  # (c, 8, 4) the placement's factors
        if placement is not None and placement.enabled and len(sightings):
            self.placement_F = placement_factors(camera, sightings, placement)
            self.W = whitening_with(self.W, self.placement_F)
            self.placement_px = np.sqrt(np.sum(self.placement_F**2, axis=(1, 2)) / CORNER_COORDINATES)
        self.classes = corner_classes([s.detection for s in sightings])  # (c,) CORNER_CLASSES
        self.E = _edge_vectors(self.xn, camera)


def camera_starts(codes: FloorCodes, views: list[np.ndarray], which: list[int], sqpnp: bool) -> Starts:
    """Candidate T_cam_world (R_cam_world, t_cam_world) of views `which`, owner = view index.
    IPPE's two solutions per view (`ippe` on all views with the same number of codes, one view
    at a time when the batch is degenerate, and OpenCV's IPPE / IPPE_SQUARE for a view `ippe`
    cannot solve), or with `sqpnp` OpenCV's SQPnP."""
    owner: list[int] = []
    R_cw: list[np.ndarray] = []
    t_cw: list[np.ndarray] = []

    def opencv(k: int, method: int) -> None:
        v = views[k]
        # one code with IPPE_SQUARE: about its centre (the floor symbol frame has the world axes)
        origin = codes.centres[v[0]] if len(v) == 1 and method == cv2.SOLVEPNP_IPPE_SQUARE else None
        for R, t in opencv_starts(codes.P[v].reshape(-1, 3), codes.xn[v].reshape(-1, 2), origin, method):
            owner.append(k)
            R_cw.append(R)
            t_cw.append(t)

    def vectorised(ks: list[int], n: int) -> bool:
        idx = np.array([views[k] for k in ks])
        P = codes.P[idx].reshape(-1, 4 * n, 3)
        if np.any(P[:, :, 2] != 0.0):  # not on the floor z = 0
            return False
        poses = ippe_or_none(P[:, :, :2], codes.xn[idx].reshape(-1, 4 * n, 2))
        if poses is None:
            return False
        owner.extend(k for k in ks for _ in range(2))
        R_cw.extend(poses[0].reshape(-1, 3, 3))
        t_cw.extend(poses[1].reshape(-1, 3))
        return True

    if sqpnp:
        for k in which:
            opencv(k, cv2.SOLVEPNP_SQPNP)
    else:
        by_n: dict[int, list[int]] = {}
        for k in which:
            by_n.setdefault(len(views[k]), []).append(k)
        for n, ks in by_n.items():
            if len(ks) > 1 and vectorised(ks, n):
                continue
            for k in ks:  # a degenerate view: one at a time
                if not vectorised([k], n):
                    opencv(k, cv2.SOLVEPNP_IPPE_SQUARE if n == 1 else cv2.SOLVEPNP_IPPE)
    return Starts(
        np.asarray(owner, dtype=int), np.array(R_cw).reshape(-1, 3, 3), np.array(t_cw).reshape(-1, 3)
    )


def _choose(cands: list[FloorCandidate], ambiguity_chi2: float) -> FloorSolution | None:
    """Of a view's candidates, the most level (body z nearest world z) of those whose whitened
    cost is within `ambiguity_chi2` of the best (a multirotor rarely tilts more than 30 deg)."""
    if len(cands) < 2:
        return FloorSolution(cands[0], False) if cands else None
    best = min(c.cost for c in cands)
    close = [c for c in cands if c.cost <= best + ambiguity_chi2]  # whitened: chi^2
    return FloorSolution(max(close, key=lambda c: c.R_world_body[2, 2]), len(close) > 1)


def solve_floor_views(
    codes: FloorCodes,
    views: list[np.ndarray],
    camera: CameraModel,
    ambiguity_chi2: float,
    sqpnp_fallback: bool = True,
) -> list[FloorSolution | None]:
    """Best refined body pose of each view (an array of code indices into `codes`), or None.

    Starts: IPPE (`camera_starts`), and SQPnP when no IPPE start refined to a fit whose
    whitened error is plausible (`chi2_bound`; `sqpnp_fallback`); refined in batches of views
    with the same number of codes; candidates under the floor or > MAX_YAW_DEVIATION_RAD from
    the edge-implied yaw are dropped; of those within `ambiguity_chi2` of the best, the most
    level (`_choose`)."""
    projector = Projector(camera)
    R_bc, t_bc = camera.T_body_cam[:3, :3], camera.T_body_cam[:3, 3]
    R_cb = np.ascontiguousarray(R_bc.T)
    t_cb = -R_cb @ t_bc
    E = np.add.reduceat(
        codes.E[np.concatenate(views)],  # each view's sum of its codes'
        np.cumsum([0] + [len(v) for v in views[:-1]]),
    )  # edge vectors
    hints = np.where(np.any(E != 0.0, axis=1), -np.arctan2(E[:, 1], E[:, 0]), np.nan)
    finite = np.isfinite(codes.xn).all(axis=(1, 2))
    starts: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in views]  # (R_wb, t_wb)
    cands: list[list[FloorCandidate]] = [[] for _ in views]

    def add_starts(which: list[int], sqpnp: bool) -> None:
        """Starts of views `which`, refined in batches by number of codes, into `cands`."""
        cam = camera_starts(codes, views, [k for k in which if finite[views[k]].all()], sqpnp)
        if len(cam.owner) == 0:
            return
        R_wc = cam.R.transpose(0, 2, 1)
        R_wb = R_wc @ R_cb  # T_world_body = T_cam_world^-1 T_cam_body
        t_wb = -(R_wc @ cam.t[:, :, None])[:, :, 0] - R_wb @ t_bc
        owner = cam.owner
        new = np.ones(len(owner), dtype=bool)  # not a duplicate of another start
        if sqpnp:  # SQPnP's is usually one of IPPE's
            for i, k in enumerate(owner.tolist()):
                new[i] = not any(
                    same_pose(R_wb[i], t_wb[i], R, t, DUPLICATE_START_RAD, DUPLICATE_START_M)
                    for R, t in starts[k]
                )
        else:  # IPPE's two of a view (consecutive)
            pair = np.flatnonzero(owner[1:] == owner[:-1])
            cos = 0.5 * (np.einsum("kij,kij->k", R_wb[pair], R_wb[pair + 1]) - 1.0)
            new[pair + 1] = ~(
                (cos >= math.cos(DUPLICATE_START_RAD))
                & (np.linalg.norm(t_wb[pair] - t_wb[pair + 1], axis=1) <= DUPLICATE_START_M)
            )
        by_n: dict[int, list[int]] = {}
        for i in np.flatnonzero(new).tolist():
            k = int(owner[i])
            starts[k].append((R_wb[i], t_wb[i]))
            by_n.setdefault(len(views[k]), []).append(i)
        for n, group in by_n.items():
            idx = np.array([views[k] for k in owner[group]])  # (K, n)
            problems = FloorProblems(
                projector,
                R_cb,
                t_cb,
                codes.P[idx].reshape(-1, 4 * n, 3),
                codes.uv[idx].reshape(-1, 4 * n, 2),
                codes.W[idx],
            )
            _add_candidates(refine_starts(problems, Starts(owner[group], R_wb[group], t_wb[group])))

    def _add_candidates(ref: RefinedStarts) -> None:
        """Keep the refined poses above the floor and near the edge-implied yaw, once each."""
        R, t, hint = ref.R, ref.t, hints[ref.owner]
        ok = (
            ref.normal.finite()
            & (R[:, 2] @ t_bc + t[:, 2] > 0.0)
            & (
                np.isnan(hint)
                | (np.abs(wrap_angle(np.arctan2(R[:, 1, 0], R[:, 0, 0]) - hint)) <= MAX_YAW_DEVIATION_RAD)
            )
        )
        # (camera above the floor: else mirrored corners; yaw near the edges': no flip)
        rms = ref.rms_px
        for i in np.flatnonzero(ok).tolist():
            k = int(ref.owner[i])
            if any(same_minimum(c.R_world_body, c.t_world_body, c.information, R[i], t[i]) for c in cands[k]):
                continue
            cands[k].append(
                FloorCandidate(
                    R[i], t[i], ref.normal.H[i], float(ref.normal.cost[i]), ref.residual_px[i], float(rms[i])
                )
            )

    add_starts(list(range(len(views))), sqpnp=False)
    if sqpnp_fallback:  # SQPnP (a global solver) only where IPPE found no plausible fit
        retry = [
            k
            for k, v in enumerate(views)
            if len(v) > 1
            and min((c.cost for c in cands[k]), default=math.inf) > chi2_bound(CORNER_COORDINATES * len(v))
        ]
        if retry:
            add_starts(retry, sqpnp=True)
    return [_choose(cs, ambiguity_chi2) for cs in cands]


def estimate_floor_poses(
    frames: list[list[FloorSighting]],
    camera: CameraModel,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    *,
    max_rms_px: float = MAX_REPROJECTION_RMS_PX,
    ambiguity_chi2: float = AMBIGUITY_CHI2,
    gimbal_roll_pitch_sigma_rad: float = GIMBAL_ROLL_PITCH_SIGMA_RAD,
    sqpnp_fallback: bool = True,
    placement: Placement | FloorLayout | None = None,
) -> list[PnPResult | None]:
    """`estimate_floor_pose` of many frames (each a list of floor sightings), computed together:
    the corners undistorted and whitened at once, and the views refined in batches (one
    vectorised evaluation per LM step for all frames with the same number of codes).
    `placement`: how far the codes may lie off their payloads (world.yaml; `floor_whitening`),
    None or 0 / 0 for exactly laid codes; a frame's RMS gate then widens by
    PLACEMENT_GATE_SIGMAS times its codes' placement px."""
    sigma = float(corner_sigma_px)
    if not sigma > 0:
        raise EstimationError(f"corner_sigma_px must be positive, got {corner_sigma_px!r}")
    frames = [list(f) for f in frames]
    out: list[PnPResult | None] = [None] * len(frames)
    owner = [i for i, f in enumerate(frames) if f]
    if not owner:
        return out
    all_sightings = [s for i in owner for s in frames[i]]
    codes = FloorCodes(all_sightings, camera, sigma, placement)
    first = np.cumsum([0] + [len(frames[i]) for i in owner])
    views = [np.arange(a, b) for a, b in zip(first[:-1], first[1:])]
    dropped: list[list[str]] = [[] for _ in owner]
    done: dict[int, FloorSolution] = {}  # view -> accepted solution
    pending = list(range(len(owner)))
    while pending:
        sols = solve_floor_views(codes, [views[k] for k in pending], camera, ambiguity_chi2, sqpnp_fallback)
        retry = []
        for k, sol in zip(pending, sols):
            if sol is None:
                continue
            placed_px = math.sqrt(float(np.mean(codes.placement_px[views[k]] ** 2)))  # 0: laid exactly
            gate = max_rms_px + PLACEMENT_GATE_SIGMAS * placed_px
            if sol.candidate.rms_px <= gate:
                done[k] = sol
            elif len(views[k]) > 1:  # leave out the worst-fitting code and solve again
                r = sol.candidate.residual_px
                worst = int(np.argmax((r.reshape(-1, CORNER_COORDINATES) ** 2).sum(axis=1)))
                dropped[k].append(all_sightings[views[k][worst]].detection.payload)
                views[k] = np.delete(views[k], worst)
                retry.append(k)
        pending = retry
    if not done:
        return out
    ks = sorted(done)
    accepted = [done[k] for k in ks]
    covs, ok = covariances(np.array([s.candidate.information for s in accepted]))  # (J^T W J)^-1
    chi2_c, G_c, T_c, G_p = class_parts(codes, [views[k] for k in ks], accepted, covs, camera)
    gimbaled = camera.mount == Mount.GIMBALED
    Ts = np.zeros((len(accepted), 4, 4))
    Ts[:, :3, :3] = [s.candidate.R_world_body for s in accepted]
    Ts[:, :3, 3] = [s.candidate.t_world_body for s in accepted]
    Ts[:, 3, 3] = 1.0
    Ts_world_cam = Ts @ camera.T_body_cam
    for j, (k, sol, T, T_world_cam, cov, good) in enumerate(zip(ks, accepted, Ts, Ts_world_cam, covs, ok)):
        if not good:
            continue
        # the classes' shares, and their placement parts (transformed alike)
        G = G_c[j] if G_p is None else np.concatenate([G_c[j], G_p[j]])
        free_tilt = None
        if gimbaled:
            free_tilt = cov[:2, :2].copy()
            T, cov, G = condition_on_level(T, cov, G, camera.mount_sigmas[0])
            T = level_frame(T)
            keep = np.diag([0.0, 0.0, 1.0, 1.0, 1.0, 1.0])
            cov = keep @ cov @ keep + np.diag([gimbal_roll_pitch_sigma_rad**2] * 2 + [0.0] * 4)
            G = keep @ G @ keep
        G, G_place = (G, None) if G_p is None else (G[: len(CORNER_CLASSES)], G[len(CORNER_CLASSES) :])
        out[owner[k]] = PnPResult(
            T_world_body=T,
            covariance=cov,
            T_world_cam=T_world_cam,
            n_codes=len(views[k]),
            payloads=[all_sightings[c].detection.payload for c in views[k]],
            reprojection_rms_px=sol.candidate.rms_px,
            ambiguous=sol.ambiguous,
            dropped_payloads=dropped[k],
            chi2=float(sol.candidate.cost),
            class_chi2=chi2_c[j],
            class_covariance=G,
            class_redundancy=T_c[j],
            free_tilt_covariance=free_tilt,
            placement_covariance=G_place,
        )
    return out


def condition_on_level(
    T_world_parent: np.ndarray, cov: np.ndarray, class_covariance: np.ndarray, sigma_rad: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A gimbaled camera's free 6-dof PnP pose conditioned on what the gimbal tells: its parent
    frame (the level body frame) has roll = pitch = 0, to `sigma_rad` per axis.

    PnP solves the camera's parent pose with roll and pitch free; with one or two codes in view a
    small tilt and a horizontal shift nearly explain the same corners (the camera looks down),
    so the free solution's x / y error carries its roll / pitch error, frame after frame while
    the same codes are in view.  Levelling that pose (zeroing roll / pitch) keeps the shift.
    Here the known attitude enters as a linear-Gaussian measurement of the perturbation's
    [rx, ry] (Gaussian conditioning, e.g. Bishop, "Pattern Recognition and Machine Learning",
    2006, eqs. 2.81-2.82; one Gauss-Newton step of the constrained problem): with the pose
    T = L Exp(rho) (L its level frame, rho its roll / pitch) and the truth T Exp(xi),
    xi ~ N(0, C), the level truth says xi_r = -rho (first order), so
    xi | . ~ N(K (-rho), M C M^T + sigma^2 K K^T), K = C_:r (C_rr + sigma^2 I)^-1, M = I - K S
    (S picks [rx, ry]).  Returns the pose T Exp(-K rho), its covariance, and the corner classes'
    shares M G_c M^T (`class_covariance` (k, 6, 6): PnPResult.class_covariance, whose sum is
    the covariance without the gimbal term)."""
    T = np.asarray(T_world_parent, dtype=float)
    C = np.asarray(cov, dtype=float)
    rho = so3_log(level_frame(T)[:3, :3].T @ T[:3, :3])[:2]
    K = C[:, :2] @ np.linalg.inv(C[:2, :2] + sigma_rad**2 * np.eye(2))
    M = np.eye(6)
    M[:, :2] -= K
    cov_c = M @ C @ M.T + sigma_rad**2 * (K @ K.T)
    G = M @ np.asarray(class_covariance, dtype=float) @ M.T
    return T @ se3_exp(-K @ rho), 0.5 * (cov_c + cov_c.T), G


def class_parts(
    codes: FloorCodes,
    views: list[np.ndarray],
    solutions: list[FloorSolution],
    covs: np.ndarray,
    camera: CameraModel,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Per frame and corner class c (CORNER_CLASSES): chi2_c (F, k), G_c = C H_c C (F, k, 6, 6)
    and the redundancy matrix T (F, k, k), of frames solved on codes `views` at `solutions`
    with covariances C = H^-1 `covs` (F, 6, 6); H_c, chi2_c sum the whitened normal equations of
    the class's codes at the solution.  With the hat matrix P = A C A^T of the whitened Jacobian
    A and D_c the selector of class c's m_c rows, the residual r = (I - P) w of noise w whose
    class c' rows have variance s_c' gives E[r^T D_c r] = sum_c' s_c' tr(D_c (I - P) D_c' (I - P)),
    i.e. T[c, c'] = [c = c'] (m_c - 2 tr(C H_c)) + tr(C H_c C H_c') (Helmert's variance-component
    estimation, Helmert 1924; Koch 1999, sec. 3.6); each row sums to the class's redundancy
    m_c - tr(C H_c), and all of T to 8 n - 6.  With the codes' placement uncertain
    (`FloorCodes.placement_F`), also each class's placement share (F, k, 6, 6)
    (PnPResult.placement_covariance), else None."""
    k = len(CORNER_CLASSES)
    F = len(solutions)
    idx = np.concatenate(views) if F else np.zeros(0, dtype=np.int64)
    frame = np.repeat(np.arange(F), [len(v) for v in views])
    R = np.array([s.candidate.R_world_body for s in solutions]).reshape(-1, 3, 3)[frame]
    t = np.array([s.candidate.t_world_body for s in solutions]).reshape(-1, 3)[frame]
    one = FloorProblems.for_camera(camera, codes.P[idx], codes.uv[idx], codes.W[idx][:, None])
    ne = one.normal_equations(R, t)  # one problem per code
    cls = codes.classes[idx]
    H_c = np.zeros((F, k, 6, 6))
    chi2_c = np.zeros((F, k))
    m_c = np.zeros((F, k))
    np.add.at(H_c, (frame, cls), ne.H)
    np.add.at(chi2_c, (frame, cls), ne.cost)
    np.add.at(m_c, (frame, cls), float(CORNER_COORDINATES))
    CH = covs[:, None] @ H_c  # (F, k, 6, 6): C H_c
    G_c = CH @ covs[:, None]
    T = np.einsum("fcij,fdji->fcd", CH, CH)  # tr(C H_c C H_d)
    T += np.eye(k)[None] * (m_c - 2.0 * np.trace(CH, axis1=2, axis2=3))[:, :, None]
    G_p = None
    if codes.placement_F is not None:
        # the placement's share: each code's whitened placement factors B = W F
        # (whitening.placement_factors) meet the pose through A^T B (A its whitened pose Jacobian)
        # of x, y and yaw only: the turn's second order (the factors' last column, a bound that a
        # single code's pose absorbs whole) stays in the corner classes' share; counted once per
        # code run with the rest it took place60's incremental smoother / EKF NEES 3.4 / 3.1 to
        # 2.0 / 1.8 and p101's 10.1 / 5.8 to 2.9 / 3.2 (BENCHMARKS.md, eighteenth session)
        B = codes.W[idx] @ codes.placement_F[idx][:, :, :3]
        AtB = np.swapaxes(one.whitened_jacobian(R, t), 1, 2) @ B
        M_c = np.zeros((F, k, 6, 6))
        np.add.at(M_c, (frame, cls), AtB @ np.swapaxes(AtB, 1, 2))
        G_p = covs[:, None] @ M_c @ covs[:, None]
    return chi2_c, G_c, T, G_p


def estimate_floor_pose(
    sightings: list[FloorSighting],
    camera: CameraModel,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    *,
    max_rms_px: float = MAX_REPROJECTION_RMS_PX,
    ambiguity_chi2: float = AMBIGUITY_CHI2,
    gimbal_roll_pitch_sigma_rad: float = GIMBAL_ROLL_PITCH_SIGMA_RAD,
    sqpnp_fallback: bool = True,
    placement: Placement | FloorLayout | None = None,
) -> PnPResult | None:
    """Body pose from all floor codes of one floor-camera frame, or None (no code, no solution,
    or reprojection RMS above `max_rms_px` even after leaving out the worst-fitting codes).

    1. corners undistorted (`undistort`); candidates: one code: IPPE_SQUARE's two solutions;
       several: planar IPPE's two, and SQPnP's when no IPPE candidate refines to a plausible fit
       (`sqpnp_fallback`, on by default);
    2. the candidates whose whitened error is within 2x + START_MARGIN_CHI2 of the best one's
       are refined by Gauss-Newton / LM on the reprojection error in distorted pixels over the
       body pose (fusion/qr/pnp/lm.py; 2-4 evaluations);
    3. candidates whose yaw is > 90 deg from `edge_implied_yaw` are dropped (no 180-deg flips);
       of those whose squared error is within `ambiguity_chi2` sigma^2 of the best, the most level;
    4. covariance (J^T W J)^-1, J = d(distorted px)/d(xi) at the returned pose, xi the body-frame
       right perturbation [rx, ry, rz, tx, ty, tz] (GTSAM Pose3; fusion/qr/reprojection.py), W
       block-diagonal with one (8, 8) block C_i^-1 per code: C_i the detection's `corner_cov_px2`
       when set (its corners come from one homography fit, so their errors are correlated), else
       sigma_i^2 I with sigma_i its `corner_sigma_px`, else `corner_sigma_px`; the LM of step 2
       minimises the same weighted error.

    "gimbaled" camera: the camera is stabilised, so the airframe's roll and pitch are not observed.
    The returned T_world_body is then the LEVEL body frame (roll = pitch = 0, estimated yaw and
    position): the free pose conditioned on its level attitude, known to the camera's mount sigma
    (`condition_on_level`), and its covariance keeps the conditioned [rz, tx, ty, tz] block
    while rx and ry get variance gimbal_roll_pitch_sigma_rad^2 ((10 deg)^2 by default) and no
    correlation.

    `placement`: how far the codes may lie off their payloads (`estimate_floor_poses`).

    Many frames: `estimate_floor_poses` (the same, far cheaper per frame: scripts/bench_pnp.py)."""
    return estimate_floor_poses(
        [sightings],
        camera,
        corner_sigma_px,
        max_rms_px=max_rms_px,
        ambiguity_chi2=ambiguity_chi2,
        gimbal_roll_pitch_sigma_rad=gimbal_roll_pitch_sigma_rad,
        sqpnp_fallback=sqpnp_fallback,
        placement=placement,
    )[0]
