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
term, for a gimbaled floor camera whose mount sigma is not 0 (pipeline._fuse_into_result),
scaled by the share of the tilt-coupled error the conditioning keeps (`level_kept_fraction`):
the fused tilt is continuous in the stated sigma (lev16: the PnP poses at 1e-4 deg are those at
0 to 1e-7 m, but PnP's own tilt sigma is only 0.1-1 mrad, so 0.003-0.03 deg already matters).

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

import math

import numpy as np

from fusion.conventions import GRAVITY_M_S2
from fusion.geometry import level_frame
from fusion.types import Trajectory


def tilt_consider_sigma_rad(bias_prior_sigma_accel_m_s2: float, kept_fraction: float = 1.0) -> float:
    """sqrt(f) sigma_b / g (rad): the levelling limit sigma_b / g for an accelerometer bias known
    to sigma_b (m/s^2), scaled by the share f in [0, 1] of the fixes' tilt-coupled error that the
    level conditioning keeps (`level_kept_fraction`; 1: the free pose levelled)."""
    f = min(max(float(kept_fraction), 0.0), 1.0)
    return math.sqrt(f) * float(bias_prior_sigma_accel_m_s2) / GRAVITY_M_S2


def level_kept_fraction(free_tilt_covariances: np.ndarray | None, sigma_rad: float) -> float:
    """The share f in [0, 1] of the fixes' tilt-coupled position error variance that PnP's level
    conditioning at a stated level sigma `sigma_rad` keeps, over a flight's frames
    (`free_tilt_covariances` (N, 2, 2): each frame's free solve's [rx, ry] block C,
    PnPResult.free_tilt_covariance; None or empty: 1 at sigma > 0, nothing known to shrink it).

    Per frame (floor.condition_on_level; one axis for the derivation): the free pose's
    horizontal error carries h e_r of its tilt error e_r ~ N(0, C) (h = C_xr / C, the lever of
    the tilt-shift trade).  Conditioned at sigma, the shift its tilt error leaves is h F e_r,
    F = sigma^2 (C + sigma^2)^-1, and the gimbal's own level error adds sigma^2 K K^T,
    K = h C (C + sigma^2)^-1: h^2 C (F^2 + F (1 - F)) = F h^2 C in all, F times the
    free-levelled pose's tilt-coupled variance (Gaussian conditioning, Bishop 2006,
    eqs. 2.81-2.82).  Matrix form per frame: F_i = sigma^2 (C_i + sigma^2 I)^-1.  Over the
    flight the frames are weighted by their tilt information (F_bar = (sum C_i^-1)^-1
    sum C_i^-1 F_i, as the back ends weight the fixes by their information), and
    f = tr(F_bar) / 2, the mean over the two level axes.  f is 0 at sigma 0 and rises to 1 once
    sigma is well above the free tilt sigma (0.1-1 mrad on the simulated flights, BENCHMARKS.md
    lev16)."""
    s2 = float(sigma_rad) ** 2
    if s2 == 0.0:
        return 0.0
    if free_tilt_covariances is None or not len(free_tilt_covariances):
        return 1.0
    C = np.asarray(free_tilt_covariances, dtype=float).reshape(-1, 2, 2)
    C = C[np.all(np.isfinite(C), axis=(1, 2))]  # first: det of a NaN matrix warns
    C = C[(np.linalg.det(C) > 0.0) & (C[:, 0, 0] > 0.0)]
    if not len(C):
        return 1.0
    info = np.linalg.inv(C)
    F = s2 * np.linalg.inv(C + s2 * np.eye(2))
    F_bar = np.linalg.solve(info.sum(axis=0), (info @ F).sum(axis=0))
    return float(min(max(0.5 * np.trace(F_bar), 0.0), 1.0))


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
