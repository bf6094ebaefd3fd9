"""What the gyro's white noise over a rolling-shutter readout costs one frame's PnP, and how much
of it any estimator that also uses the image could win back (issue 10.1, BENCHMARKS.md `rsjoint`).

The correction (fusion.qr.rolling_shutter) takes each row's rotation from the stamp's by the
gyro's integral.  The gyro's white noise (density sigma_g, rad/s/sqrt(Hz)) makes that integral a
random walk W(t) from the stamp: Cov(W(t_i), W(t_j)) = sigma_g^2 min(|t_i|, |t_j|) I3 for row
times t_i, t_j on the same side of the stamp, 0 across it (a Wiener process; Maybeck,
"Stochastic Models, Estimation and Control" vol. 1, sec. 4.5).  A corner at row time t_i then
errs by J_i W(t_i) px (J_i: its pixel's derivative by a rotation of its row's body pose), so the
frame's corners get a correlated error of covariance S_W[i, j] = J_i J_j^T sigma_g^2 min(...).

Linearised at the true per-row poses, with J_p the corners' derivative by the stamp pose and S_c
the corners' own covariance (the refinement's (8, 8) blocks):

- corners only (a global shutter):   C_0 = (J_p^T S_c^-1 J_p)^-1;
- PnP as now (weights from the corners, the gyro's error not modelled):
  C_now = C_0 + A S_W A^T, A = C_0 J_p^T S_c^-1 (the estimator's gain);
- the best linear unbiased estimator from the image and the gyro together (Aitken's generalised
  least squares, Kariya & Kurata, "Generalized Least Squares" 2004, thm. 2.1):
  C_best = (J_p^T (S_c + S_W)^-1 J_p)^-1.  Any joint estimate of the pose and the motion over the
  readout with the gyro as a prior (a rolling-shutter PnP: Albl et al. "R6P", Magerand et al.,
  Saurer et al., linearised) is such an estimator, so C_now - C_best bounds what it can win.

Also the image's own information on a constant body-rate error over the readout (the pose free),
against the gyro's, sigma_g^2 / T per axis, and PnP's rotation sigma against the gyro's rotation
over a frame period (what the smoother's images could add to the gyro between two stamps).

Jacobians: central differences of `CameraModel.project` (step JACOBIAN_STEP), not analytic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fusion.camera import CameraModel
from fusion.errors import EstimationError
from fusion.geometry import inv_T, so3_exp_stack

JACOBIAN_STEP = 1e-6
"""Central-difference step (rad, m) of the pixel Jacobians."""


@dataclass
class ReadoutInformation:
    """One frame's numbers.  Position covariance traces (m^2, world frame): `pos_var_corners` C_0
    (corners only), `pos_var_now` C_now (PnP as now), `pos_var_best` C_best (best linear use of
    image and gyro), `pos_var_now_xy` C_now with the random walk about the body x and y axes only;
    `rate_information_image` (3,) (rad/s)^-2 the image's information on a constant body-rate error
    over the readout, per body axis (x, y, z) with the pose free and the other two axes known (an
    upper bound; 0 for a global shutter), `rate_information_gyro` the gyro's, readout / sigma_g^2
    per axis; `rotation_sigma_pnp` (3,) rad PnP's rotation sigma (body axes) and
    `rotation_sigma_gyro` rad the gyro's over one frame period; `rate_information_image_with_prior`
    (3,) as `rate_information_image` with the stamp pose's prior (e.g. a fused estimate) added."""

    pos_var_corners: float
    pos_var_now: float
    pos_var_best: float
    pos_var_now_xy: float
    rate_information_image: np.ndarray
    rate_information_gyro: float
    rotation_sigma_pnp: np.ndarray
    rotation_sigma_gyro: float
    rate_information_image_with_prior: np.ndarray


def random_walk_covariance(dt_s: np.ndarray, density: float) -> np.ndarray:
    """(M, M) covariance of a scalar Wiener process of `density` (unit/sqrt(Hz)) started at the
    stamp, at offsets dt_s (M,) s: density^2 min(|t_i|, |t_j|) on the same side, 0 across."""
    t = np.asarray(dt_s, float)
    same_side = np.outer(np.sign(t), np.sign(t)) > 0
    return np.where(same_side, density**2 * np.minimum.outer(np.abs(t), np.abs(t)), 0.0)


def frame_readout_information(
    camera: CameraModel,
    T_world_body_rows: np.ndarray,
    p_world: np.ndarray,
    corner_cov_px2: np.ndarray,
    dt_s: np.ndarray,
    gyro_density: float,
    readout_s: float,
    frame_period_s: float,
    pose_prior_cov: np.ndarray | None = None,
) -> ReadoutInformation:
    """One frame's `ReadoutInformation` (module docstring).  M corners of C = M / 4 codes:
    `T_world_body_rows` (M, 4, 4) the body pose at each corner's row time (the linearisation
    point, e.g. the truth), `p_world` (M, 3) the corners' world points, `corner_cov_px2` (C, 8, 8)
    each code's corner covariance (px^2, TL u, TL v, TR u, ...), `dt_s` (M,) each corner's row
    time from the stamp, `gyro_density` rad/s/sqrt(Hz), `readout_s` the whole frame's readout
    (s; 0 for a global shutter), `frame_period_s` s between stamps, `pose_prior_cov` (6, 6) optional
    covariance of a prior on the stamp pose ([rx, ry, rz] body rad, [tx, ty, tz] world m) for
    `rate_information_image_with_prior`.  Raises EstimationError when
    the corners do not fix the pose (fewer than one code)."""
    T_rows = np.asarray(T_world_body_rows, float)
    P = np.asarray(p_world, float)
    dt = np.asarray(dt_s, float)
    covs = np.asarray(corner_cov_px2, float)
    M = len(P)
    if M < 4 or M % 4 or covs.shape != (M // 4, 8, 8) or T_rows.shape != (M, 4, 4) or dt.shape != (M,):
        raise EstimationError(
            f"readout information: {M} corner(s), covariances {covs.shape}, poses {T_rows.shape}, "
            f"times {dt.shape}: need 4 per code"
        )

    def project(rot: np.ndarray, shift: np.ndarray) -> np.ndarray:
        """(M, 2) px with each row pose turned by rot (M, 3) (body, right) and moved by shift (3,)."""
        T = T_rows.copy()
        T[:, :3, :3] = T_rows[:, :3, :3] @ so3_exp_stack(rot)
        T[:, :3, 3] = T_rows[:, :3, 3] + shift
        T_cw = inv_T(camera.T_world_cam(T))
        return camera.project(np.einsum("mij,mj->mi", T_cw[:, :3, :3], P) + T_cw[:, :3, 3])

    h = JACOBIAN_STEP
    zero_rot, zero_shift = np.zeros((M, 3)), np.zeros(3)
    J_pose = np.zeros((2 * M, 6))  # [rx, ry, rz] body, [tx, ty, tz] world
    J_row = np.zeros((M, 2, 3))  # each corner's px by a rotation of its own row's pose
    J_rate = np.zeros((2 * M, 3))  # by a constant body-rate error: rotation rate * dt
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        d_rot = (project(np.tile(e, (M, 1)), zero_shift) - project(np.tile(-e, (M, 1)), zero_shift)) / (2 * h)
        J_row[:, :, j] = d_rot
        J_pose[:, j] = d_rot.ravel()
        J_pose[:, 3 + j] = ((project(zero_rot, e) - project(zero_rot, -e)) / (2 * h)).ravel()
        J_rate[:, j] = (d_rot * dt[:, None]).ravel()
    if not np.all(np.isfinite(J_pose)):
        raise EstimationError("readout information: a corner behind the camera")
    S_c = np.zeros((2 * M, 2 * M))
    for c, C in enumerate(covs):
        S_c[8 * c : 8 * c + 8, 8 * c : 8 * c + 8] = C
    W_c = np.linalg.inv(S_c)
    C_0 = np.linalg.inv(J_pose.T @ W_c @ J_pose)
    K = random_walk_covariance(dt, gyro_density)
    S_w = np.einsum("iak,jbk,ij->iajb", J_row, J_row, K).reshape(2 * M, 2 * M)
    J_xy = J_row.copy()
    J_xy[:, :, 2] = 0.0
    S_w_xy = np.einsum("iak,jbk,ij->iajb", J_xy, J_xy, K).reshape(2 * M, 2 * M)
    gain = C_0 @ J_pose.T @ W_c
    C_now = C_0 + gain @ S_w @ gain.T
    C_now_xy = C_0 + gain @ S_w_xy @ gain.T
    C_best = np.linalg.inv(J_pose.T @ np.linalg.solve(S_c + S_w, J_pose))
    # the image's information on a constant body-rate error, the pose marginalised (Schur
    # complement); its diagonal is each axis's information with the other two axes known, an
    # upper bound (a one-code frame leaves the 3 x 3 block singular)
    I_pp, I_pr, I_rr = J_pose.T @ W_c @ J_pose, J_pose.T @ W_c @ J_rate, J_rate.T @ W_c @ J_rate
    rate_info = I_rr - I_pr.T @ np.linalg.solve(I_pp, I_pr)
    rate_info_prior = rate_info
    if pose_prior_cov is not None:
        I_pp_prior = I_pp + np.linalg.inv(np.asarray(pose_prior_cov, float))
        rate_info_prior = I_rr - I_pr.T @ np.linalg.solve(I_pp_prior, I_pr)
    return ReadoutInformation(
        pos_var_corners=float(np.trace(C_0[3:, 3:])),
        pos_var_now=float(np.trace(C_now[3:, 3:])),
        pos_var_best=float(np.trace(C_best[3:, 3:])),
        pos_var_now_xy=float(np.trace(C_now_xy[3:, 3:])),
        rate_information_image=np.clip(np.diag(rate_info), 0.0, None),
        rate_information_gyro=readout_s / gyro_density**2 if gyro_density > 0 else math.inf,
        rotation_sigma_pnp=np.sqrt(np.diag(C_0)[:3]),
        rotation_sigma_gyro=gyro_density * math.sqrt(frame_period_s),
        rate_information_image_with_prior=np.clip(np.diag(rate_info_prior), 0.0, None),
    )
