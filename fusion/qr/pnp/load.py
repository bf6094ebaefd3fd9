"""Front-camera PnP: each load code's centre in the camera and in the world, with covariances.

Each load code's pose in the camera from its four corners (IPPE, side world.load_side_m), refined
by the batched LM (fusion/qr/pnp/lm.py); its centre p_cam with covariance, and p_world with the
drone pose's covariance propagated to first order.  The paper's Alg. 4-6 assume a level camera
and a code facing it; this estimates the code's full pose.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import symbol_corners_S
from fusion.geometry import cross_rows, rot_z, skew, so3_exp_stack, yaw_of
from fusion.qr.codes import LoadSighting
from fusion.qr.pnp.ippe import ippe_or_none, opencv_starts
from fusion.qr.pnp.lm import (
    AMBIGUITY_CHI2,
    MAX_REPROJECTION_RMS_PX,
    NormalEquations,
    Starts,
    covariances,
    refine_starts,
)
from fusion.qr.pnp.undistort import undistort
from fusion.qr.pnp.whitening import DEFAULT_CORNER_SIGMA_PX, corner_whitening
from fusion.qr.reprojection import Projector
from fusion.types import LoadObservation, Mount
from fusion.world import World


class LoadFrame(NamedTuple):
    """One front-camera frame to solve: its load sightings, the drone pose T_world_body (4, 4)
    at the frame and that pose's (6, 6) body-frame covariance (None: exact)."""

    sightings: list[LoadSighting]
    T_world_body: np.ndarray
    cov_body: np.ndarray | None


class SymbolProblems:
    """K load-code problems: the code's corners P (4, 3) in its symbol frame, observed px
    z (K, 4, 2), whitening W (K, 1, 8, 8); unknown the pose (R, t) of T_cam_symbol, perturbed as
    R exp(w) (symbol frame), t + dt (camera frame) (fusion/qr/reprojection.symbol_reprojection)."""

    def __init__(self, projector: Projector, P: np.ndarray, z: np.ndarray, W: np.ndarray):
        self.projector, self.P, self.z, self.W = projector, P, z, W

    def subset(self, idx: np.ndarray) -> SymbolProblems:
        return SymbolProblems(self.projector, self.P, self.z[idx], self.W[idx])

    def residual_px(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        p_cam = self.P @ R.transpose(0, 2, 1) + t[:, None, :]
        uv, _ = self.projector.project(p_cam.reshape(-1, 3), jacobian=False)
        return uv.reshape(self.z.shape) - self.z

    def normal_equations(self, R: np.ndarray, t: np.ndarray) -> NormalEquations:
        """Whitened normal equations; d p_cam / d[w, dt] = [-R [p_S]x, I]."""
        K = len(R)
        uv, J_proj = self.projector.project((self.P @ R.transpose(0, 2, 1) + t[:, None, :]).reshape(-1, 3))
        B = (J_proj.reshape(K, 8, 3) @ R).reshape(-1, 2, 3)
        Jr = np.empty((4 * K, 2, 7))  # [J | r]
        Jr[:, :, :3] = cross_rows(B, np.broadcast_to(-self.P, (K, 4, 3)).reshape(-1, 3))
        Jr[:, :, 3:6] = J_proj
        Jr[:, :, 6] = uv - self.z.reshape(-1, 2)
        return NormalEquations.from_augmented(Jr.reshape(K, 4, 2, 7), self.W)

    @staticmethod
    def retract(R: np.ndarray, t: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return R @ so3_exp_stack(delta[:, :3]), t + delta[:, 3:]


def position_jacobian_wrt_body(
    T_world_body: np.ndarray, camera: CameraModel, p_cam: np.ndarray
) -> np.ndarray:
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
    if camera.mount == Mount.GIMBALED:
        Rz_q = rot_z(float(yaw_of(R))) @ q
        n = R[0, 0] ** 2 + R[1, 0] ** 2
        d_yaw = np.array(
            [0.0, (R[1, 0] * R[0, 2] - R[0, 0] * R[1, 2]) / n, (R[0, 0] * R[1, 1] - R[1, 0] * R[0, 1]) / n]
        )
        J[:, :3] = np.outer([-Rz_q[1], Rz_q[0], 0.0], d_yaw)
    else:
        J[:, :3] = -R @ skew(q)
    return J


def _symbol_starts(corners_S: np.ndarray, xn: np.ndarray, good: np.ndarray) -> Starts:
    """IPPE's two T_cam_symbol of each code `good` (normalised corners xn (c, 4, 2)), owner =
    code index: vectorised (`ippe`; one code at a time when the batch is degenerate), or
    OpenCV's IPPE_SQUARE for a code `ippe` cannot solve."""
    if len(good) > 1:
        poses = ippe_or_none(np.broadcast_to(corners_S[:, :2], (len(good), 4, 2)), xn[good])
        if poses is not None:
            return Starts(np.repeat(good, 2), poses[0].reshape(-1, 3, 3), poses[1].reshape(-1, 3))
    owner: list[int] = []
    R0: list[np.ndarray] = []
    t0: list[np.ndarray] = []
    for c in good.tolist():  # a degenerate code: one at a time
        poses = ippe_or_none(corners_S[None, :, :2], xn[c][None])
        starts = (
            opencv_starts(corners_S, xn[c], np.zeros(3), cv2.SOLVEPNP_IPPE_SQUARE)
            if poses is None
            else list(zip(poses[0][0], poses[1][0]))
        )
        for R, t in starts:
            owner.append(c)
            R0.append(R)
            t0.append(t)
    return Starts(np.asarray(owner, dtype=int), np.array(R0).reshape(-1, 3, 3), np.array(t0).reshape(-1, 3))


def estimate_load_observations_frames(
    frames: list[LoadFrame] | list[tuple[list[LoadSighting], np.ndarray, np.ndarray | None]],
    camera: CameraModel,
    world: World,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    *,
    max_rms_px: float = MAX_REPROJECTION_RMS_PX,
    ambiguity_chi2: float = AMBIGUITY_CHI2,
) -> list[list[LoadObservation]]:
    """`estimate_load_observations` of many front-camera frames, each a `LoadFrame` (or a tuple
    (sightings, T_world_body, cov_body or None)), computed together (all codes' LM steps in one
    vectorised evaluation); one list of observations per frame."""
    frames = [LoadFrame(*f) for f in frames]
    sigma = float(corner_sigma_px)
    items = [
        (f, s)
        for f, frame in enumerate(frames)
        for s in frame.sightings
        if np.asarray(s.detection.corners_px, dtype=float).shape == (4, 2)
    ]
    out: list[list[LoadObservation]] = [[] for _ in frames]
    if not items:
        return out
    uv = np.array([np.asarray(s.detection.corners_px, dtype=float) for _, s in items])
    xn = undistort(camera, uv.reshape(-1, 2)).reshape(-1, 4, 2)
    W = corner_whitening([s.detection for _, s in items], sigma)
    corners_S = symbol_corners_S(world.load_side_m)
    starts = _symbol_starts(corners_S, xn, np.flatnonzero(np.isfinite(xn).all(axis=(1, 2))))
    if len(starts.owner) == 0:
        return out
    problems = SymbolProblems(Projector(camera), corners_S, uv[starts.owner], W[starts.owner][:, None])
    ref = refine_starts(problems, starts)
    own, R, t, eq = ref.owner, ref.R, ref.t, ref.normal
    T_world_cam = np.array([camera.T_world_cam(np.asarray(f.T_world_body, dtype=float)) for f in frames])
    frame_of = np.array([f for f, _ in items])[own]
    up_z = np.einsum("kj,kj->k", T_world_cam[frame_of, 2, :3], R[:, :, 1])  # symbol up, world z
    rms = ref.rms_px
    cands: dict[int, list[int]] = {}
    for i in np.flatnonzero(eq.finite() & (t[:, 2] > 0)).tolist():
        cands.setdefault(int(own[i]), []).append(i)
    chosen = []
    for _, cs in sorted(cands.items()):
        if len(cs) > 1:
            best = min(eq.cost[i] for i in cs)
            close = [i for i in cs if eq.cost[i] <= best + ambiguity_chi2]  # whitened: chi^2
            cs = [max(close, key=lambda i: up_z[i])]  # symbol up nearest world +z
        if rms[cs[0]] <= max_rms_px:
            chosen.append(cs[0])
    if not chosen:
        return out
    covs, ok = covariances(eq.H[chosen])
    chosen = np.asarray(chosen)[ok]
    f = frame_of[chosen]
    p_cam, cov_cam = t[chosen], covs[ok, 3:, 3:]
    R_wc = T_world_cam[f, :3, :3]
    p_world = (R_wc @ p_cam[:, :, None])[:, :, 0] + T_world_cam[f, :3, 3]
    cov_world = R_wc @ cov_cam @ R_wc.transpose(0, 2, 1)
    for k, (i, fk) in enumerate(zip(chosen.tolist(), f.tolist())):
        c = int(own[i])
        frame = frames[fk]
        cw = cov_world[k]
        if frame.cov_body is not None:
            Jb = position_jacobian_wrt_body(np.asarray(frame.T_world_body, dtype=float), camera, p_cam[k])
            cw = cw + Jb @ np.asarray(frame.cov_body, dtype=float) @ Jb.T
        s = items[c][1]
        out[fk].append(
            LoadObservation(
                timestamp_ns=int(s.detection.timestamp_ns),
                load_id=s.load_id,
                p_world=p_world[k],
                cov_world=0.5 * (cw + cw.T),
                p_cam=p_cam[k],
                cov_cam=cov_cam[k],
                corners_px=uv[c].copy(),
            )
        )
    return out


def estimate_load_observations(
    sightings: list[LoadSighting],
    camera: CameraModel,
    world: World,
    T_world_body: np.ndarray,
    cov_body: np.ndarray | None = None,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    *,
    max_rms_px: float = MAX_REPROJECTION_RMS_PX,
    ambiguity_chi2: float = AMBIGUITY_CHI2,
) -> list[LoadObservation]:
    """One LoadObservation per load code of one front-camera frame whose corners fit a square of
    side world.load_side_m (reprojection RMS <= max_rms_px; others are skipped).

    p_cam (3,) = the code centre in the camera frame (m) from IPPE_SQUARE + LM in distorted pixels
    (both IPPE solutions unless one fits far worse: START_MARGIN_CHI2), cov_cam (3, 3) = the centre
    block of (J^T C^-1 J)^-1 (fusion/qr/reprojection.symbol_reprojection), C the detection's
    `corner_cov_px2`, else sigma^2 I with sigma its `corner_sigma_px`, else `corner_sigma_px` (the
    LM minimises the same weighted error);
    p_world = T_world_cam p_cam with T_world_cam = camera.T_world_cam(T_world_body), and
    cov_world = R_world_cam cov_cam R_world_cam^T + J_b cov_body J_b^T, J_b = d p_world / d xi
    (`position_jacobian_wrt_body`) for the body-frame right perturbation xi of T_world_body
    (cov_body None: drone pose exact).
    IPPE's two-fold ambiguity barely moves the centre; when both fit, the one whose symbol "up"
    is nearer world +z is taken (load codes hang on vertical faces, up = +z).

    Many frames: `estimate_load_observations_frames` (the same, computed together)."""
    return estimate_load_observations_frames(
        [LoadFrame(sightings, T_world_body, cov_body)],
        camera,
        world,
        corner_sigma_px,
        max_rms_px=max_rms_px,
        ambiguity_chi2=ambiguity_chi2,
    )[0]
