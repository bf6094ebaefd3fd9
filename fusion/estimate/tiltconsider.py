"""A consider term on the fused roll / pitch of a gimbaled floor camera (issue 10.3).

A gimbaled (levelled) floor camera's PnP poses fix the level frame only: position and yaw
(RawPoseInput.LEVEL_POSE).  The fused roll and pitch then come from the accelerometer against the
fixes' motion, and a tilt error delta (rad, about the level frame's x / y) and an accelerometer
bias b give the same specific-force residual, g delta ~ b, up to the rotation between the level
frame and the body.  This is the levelling limit of inertial alignment: without other
information the tilt is known to the accelerometer bias's uncertainty over g (Titterton and
Weston, "Strapdown Inertial Navigation Technology", 2nd ed., 2004, on initial alignment:
levelling accuracy ~ accelerometer bias / g).  The back ends separate the two only through the
airframe's attitude changes (the bias turns with the body, a tilt error does not), a weak signal
read through the second difference of the fixes, and that is what the fixes' time-correlated
errors move: on rendered gimbaled flights every back end's pitch was 14-22 mrad off with a
claimed sigma of ~5 mrad, while fixes made from the true level pose or a noise-free IMU with the
true biases left the tilt consistent (BENCHMARKS.md, gimb15 / gimb16).  The error is PnP's
tilt-shift trade (fusion.qr.pnp.floor.condition_on_level), which conditioning the pose on the
camera's level removes only when that level is stated exact: at a mount sigma of 0.01 deg the
pitch was still 15 mrad off on one flight, at the 0.1 deg default 20 (gimb16).  Its time
correlation is not visible in the flight's own residuals (against the fused trajectory, which
follows it: tau 1-2; the corner residuals: 2-2.6), so it cannot be inflated for.  Hence this
term, for a gimbaled floor camera whose mount sigma is not 0 (pipeline._fuse_into_result).

Consider term (an error source that is not estimated but whose uncertainty is added to the
estimate's: Bierman, "Factorization Methods for Discrete Sequential Estimation", 1977, consider
covariance analysis): the attitude-change information is not trusted, and the tilt is given the
levelling limit's variance, sigma_tilt = sigma_b / g per level axis, sigma_b the accelerometer
bias's prior sigma (FusionConfig.bias_prior_sigma_accel_m_s2: what is known of
the bias before the flight).  A level-frame tilt error delta_L = (dx, dy, 0) rotates the body as
R = Exp(R_L delta_L) R_hat = R_hat Exp(R_hat^T R_L delta_L) (R_L the level frame's rotation, yaw
only), so in the body-frame right perturbation of the poses' covariances (GTSAM's Pose3 [r, t])
the term is A diag(s^2, s^2, 0) A^T on the rotation block, A = R_hat^T R_L: at zero roll and
pitch it is the roll / pitch block alone; tilted, it reaches the body-frame yaw as well, as the
error does.  Positions are left as they are: the fixes pin them."""

from __future__ import annotations

import numpy as np

from fusion.conventions import GRAVITY_M_S2
from fusion.geometry import level_frame
from fusion.types import Trajectory


def tilt_consider_sigma_rad(bias_prior_sigma_accel_m_s2: float) -> float:
    """The levelling limit sigma_b / g (rad) for an accelerometer bias known to sigma_b (m/s^2)."""
    return float(bias_prior_sigma_accel_m_s2) / GRAVITY_M_S2


def tilt_consider_covariance(T_world_body: np.ndarray, sigma_rad: float) -> np.ndarray:
    """(N, 3, 3) the body-frame rotation covariance of a level-frame roll / pitch error of
    `sigma_rad` per axis at poses T_world_body (N, 4, 4): A diag(s^2, s^2, 0) A^T, A = R^T R_L."""
    T = np.asarray(T_world_body, dtype=float)
    R = T[:, :3, :3]
    R_L = level_frame(T)[:, :3, :3]
    A = np.einsum("nji,njk->nik", R, R_L)
    return float(sigma_rad) ** 2 * np.einsum("nia,nja->nij", A[:, :, :2], A[:, :, :2])


def add_tilt_consider(traj: Trajectory, sigma_rad: float) -> Trajectory:
    """`traj` with `tilt_consider_covariance` added to each pose's rotation block; unchanged
    without covariances or with sigma_rad <= 0."""
    if traj.covariances is None or not len(traj) or not sigma_rad > 0.0:
        return traj
    covs = np.array(traj.covariances, dtype=float, copy=True)
    covs[:, :3, :3] += tilt_consider_covariance(traj.T_world_body, sigma_rad)
    return Trajectory(traj.name, traj.timestamps_ns, traj.T_world_body, covs)
