"""Factors, noise models and keys of the fusion factor graph (GTSAM 4.3).

Keys: X(k) Pose3 T_world_body at frame k, V(k) world velocity (m/s), B(k) IMU bias
(gtsam.imuBias.ConstantBias, in the IMU frame), L(j) Point3 of load j in the world.

Hand-written factors (gtsam.CustomFactor, residual + analytic Jacobians, checked against numerical
derivatives in tests/test_estimate.py).  Jacobians are with respect to GTSAM's local coordinates
at the current value: for Pose3 a right perturbation [dr, dt] with R' = R Exp(dr), t' = t + R dt
(first order), for vectors / points plain addition.
"""

from __future__ import annotations

import math
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from fusion.camera import CameraModel
from fusion.conventions import GRAVITY_M_S2
from fusion.geometry import (
    level_frame,
    level_frame_jacobian,
    rot_z,
    skew,
    wrap_angle,
    yaw_gradient,
    yaw_of,
)
from fusion.log.euroc import ImuNoise
from fusion.qr.reprojection import floor_reprojection
from fusion.types import RobustKernel

__all__ = [
    "B",
    "L",
    "V",
    "X",
    "body_velocity_factor",
    "bridge_factors",
    "constant_velocity_factor",
    "floor_corner_factor",
    "imu_params",
    "level_pose_factor",
    "load_factor",
    "pose_prior_factor",
    "position_yaw_factor",
    "robust",
]


# =========================================================================== noise models


def imu_params(
    noise: ImuNoise, T_body_imu: np.ndarray, integration_sigma: float = 1e-4
) -> gtsam.PreintegrationCombinedParams:
    """CombinedImuFactor parameters from Kalibr continuous-time densities.

    GTSAM expects continuous-time covariances: sigma_density^2 * I for the measurement noise
    (it divides by dt per sample) and for the bias random walks (it multiplies by dt).
    Gravity (0, 0, -9.81) in the world (z up, `MakeSharedU`); `body_P_sensor` = T_body_imu, so
    the IMU may be offset / rotated from the body frame."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY_M_S2)
    I3 = np.eye(3)
    p.setGyroscopeCovariance(noise.gyroscope_noise_density**2 * I3)
    p.setAccelerometerCovariance(noise.accelerometer_noise_density**2 * I3)
    p.setBiasOmegaCovariance(noise.gyroscope_random_walk**2 * I3)
    p.setBiasAccCovariance(noise.accelerometer_random_walk**2 * I3)
    p.setIntegrationCovariance(integration_sigma**2 * I3)
    if not np.allclose(T_body_imu, np.eye(4)):
        p.setBodyPSensor(gtsam.Pose3(np.asarray(T_body_imu, float)))
    return p


def robust(
    base: gtsam.noiseModel.Base, kernel: RobustKernel | str, threshold: float
) -> gtsam.noiseModel.Base:
    """Wrap a Gaussian model in an M-estimator acting on the whitened residual norm."""
    est = gtsam.noiseModel.mEstimator
    kind = RobustKernel(kernel)
    if kind is RobustKernel.NONE:
        return base
    makers: dict[RobustKernel, Any] = {
        RobustKernel.HUBER: est.Huber,
        RobustKernel.CAUCHY: est.Cauchy,
        RobustKernel.TUKEY: est.Tukey,
    }
    make = makers[kind]
    return gtsam.noiseModel.Robust.Create(make.Create(threshold), base)


# =========================================================================== factors


def pose_prior_factor(
    k: int, T_world_body: np.ndarray, cov: np.ndarray, kernel: str, threshold: float
) -> gtsam.PriorFactorPose3:
    """Per-frame QR pose (6-dof, covariance in Pose3 order, body frame) as a robust prior on X(k)."""
    model = robust(gtsam.noiseModel.Gaussian.Covariance(cov), kernel, threshold)
    return gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T_world_body), model)


def position_yaw_error(p_meas: np.ndarray, yaw_meas: float, pose: gtsam.Pose3, want_jacobian: bool):
    """Residual [p - p_meas (world, m), wrap(yaw - yaw_meas) (rad)] (4,) and its 4x6 Jacobian."""
    R = pose.rotation().matrix()
    t = pose.translation()
    e = np.concatenate([t - p_meas, [float(wrap_angle(yaw_of(R) - yaw_meas))]])
    if not want_jacobian:
        return e, None
    H = np.zeros((4, 6))
    H[:3, 3:] = R
    H[3, :3] = yaw_gradient(R)
    return e, H


def position_yaw_factor(
    k: int, p_world: np.ndarray, yaw: float, sigma_xyz, sigma_yaw: float, kernel: str, threshold: float
) -> gtsam.CustomFactor:
    """The paper's per-frame output (position + yaw, no roll/pitch: those come from the IMU)."""
    p_meas = np.asarray(p_world, float).copy()
    yaw_meas = float(yaw)
    model = robust(
        gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.asarray(sigma_xyz, float), sigma_yaw]), kernel, threshold
    )

    def error(this, values, jacobians):
        e, H = position_yaw_error(p_meas, yaw_meas, values.atPose3(this.keys()[0]), jacobians is not None)
        if jacobians is not None:
            jacobians[0] = H
        return e

    return gtsam.CustomFactor(model, [X(k)], error)


def level_pose_error(T_meas_level: np.ndarray, pose: gtsam.Pose3, want_jacobian: bool):
    """Residual of a level-frame pose measurement (gimbaled floor camera: PnP observes the level
    frame's yaw and position, not the airframe's roll and pitch), in the measured level frame's
    right-perturbation coordinates [rz, tx, ty, tz]: [wrap(yaw - yaw_meas),
    Rz(yaw_meas)^T (t - t_meas)] (4,), and its 4x6 Jacobian w.r.t. the body pose."""
    R = pose.rotation().matrix()
    t = pose.translation()
    Rz_meas = T_meas_level[:3, :3]
    e = np.concatenate(
        [[float(wrap_angle(yaw_of(R) - yaw_of(Rz_meas)))], Rz_meas.T @ (t - T_meas_level[:3, 3])]
    )
    if not want_jacobian:
        return e, None
    H = np.zeros((4, 6))
    H[0, :3] = yaw_gradient(R)
    H[1:, 3:] = Rz_meas.T @ R
    return e, H


def level_pose_factor(
    k: int, T_world_level: np.ndarray, cov_level: np.ndarray, kernel: RobustKernel, threshold: float
) -> gtsam.CustomFactor:
    """A gimbaled floor camera's per-frame pose on X(k): yaw + position of the level frame with
    the PnP covariance's [rz, tx, ty, tz] block (cov_level 4x4; PnP's rx, ry are placeholders)."""
    T_meas = np.asarray(T_world_level, float).copy()
    T_meas[:3, :3] = rot_z(float(yaw_of(T_meas[:3, :3])))
    cov = np.asarray(cov_level, float)
    model = robust(gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T)), kernel, threshold)

    def error(this, values, jacobians):
        e, H = level_pose_error(T_meas, values.atPose3(this.keys()[0]), jacobians is not None)
        if jacobians is not None:
            jacobians[0] = H
        return e

    return gtsam.CustomFactor(model, [X(k)], error)


def body_velocity_error(v_meas_body: np.ndarray, pose: gtsam.Pose3, v_world: np.ndarray, want_jacobian: bool):
    """Residual R^T v - v_meas (body frame, m/s) (3,), Jacobians wrt pose (3x6) and v (3x3)."""
    R = pose.rotation().matrix()
    vb = R.T @ v_world
    e = vb - v_meas_body
    if not want_jacobian:
        return e, None, None
    Hx = np.zeros((3, 6))
    Hx[:, :3] = skew(vb)  # (R Exp(dr))^T v = (I - [dr]x) R^T v = vb + [vb]x dr
    return e, Hx, R.T


def body_velocity_factor(k: int, v_body: np.ndarray, sigma_m_s: float) -> gtsam.CustomFactor:
    """Body-frame velocity measurement at frame k on X(k), V(k): body_velocity_error, evaluated
    by one C++ call (Rot3.unrotate, R^T v with its Jacobians: [R^T v]x w.r.t. the rotation,
    R^T w.r.t. v), the pose's translation block zero.  One such factor per frame makes it the
    most frequent Python callback of a linearisation (~25 % less CPU than body_velocity_error;
    the same values and Jacobians, tests/test_estimate.py)."""
    v_meas = np.asarray(v_body, float).copy()
    model = gtsam.noiseModel.Isotropic.Sigma(3, sigma_m_s)
    kx, kv = X(k), V(k)

    def error(this, values, jacobians):
        R = values.atPose3(kx).rotation()
        if jacobians is None:
            return R.unrotate(values.atVector(kv)) - v_meas
        Hr, Hv = np.empty((3, 3), order="F"), np.empty((3, 3), order="F")
        vb = R.unrotate(values.atVector(kv), Hr, Hv)
        Hx = np.zeros((3, 6))
        Hx[:, :3] = Hr
        jacobians[0] = Hx
        jacobians[1] = Hv
        return vb - v_meas

    return gtsam.CustomFactor(model, [kx, kv], error)


def load_error(
    p_cam_meas: np.ndarray, camera: CameraModel, pose: gtsam.Pose3, l_world: np.ndarray, want_jacobian: bool
):
    """Residual T_world_cam^-1 l - p_cam (camera frame, m) (3,) with T_world_cam =
    camera.T_world_cam(T_world_body) (mount-aware), Jacobians wrt pose (3x6) and landmark (3x3).

    The camera hangs from a parent frame P: the body (body_fixed) or its level frame (gimbaled:
    p_world = level_frame(T_world_body) T_body_cam p_cam, which moves with the body's position
    and yaw only).  With q = R_wp^T (l - t_wp): d e / d xi_P = R_bc^T [[q]x, -I], and
    d xi_P / d xi_body = I or geometry.level_frame_jacobian."""
    T_wb = pose.matrix()
    T_wp = level_frame(T_wb) if camera.gimbaled else T_wb
    T_bc = camera.T_body_cam
    R_bc, t_bc = T_bc[:3, :3], T_bc[:3, 3]
    q = T_wp[:3, :3].T @ (l_world - T_wp[:3, 3])  # landmark in the parent frame
    e = R_bc.T @ (q - t_bc) - p_cam_meas
    if not want_jacobian:
        return e, None, None
    Hx = np.zeros((3, 6))
    Hx[:, :3] = R_bc.T @ skew(q)
    Hx[:, 3:] = -R_bc.T
    if camera.gimbaled:
        Hx = Hx @ level_frame_jacobian(T_wb)
    return e, Hx, R_bc.T @ T_wp[:3, :3].T


def load_factor(
    k: int,
    j: int,
    p_cam: np.ndarray,
    cov_cam: np.ndarray,
    camera: CameraModel,
    kernel: RobustKernel,
    threshold: float,
    load_key: int | None = None,
    noise_model: gtsam.noiseModel.Base | None = None,
) -> gtsam.CustomFactor:
    """A load-code centre measured in the front camera at frame k, on X(k) and L(j) (or on
    `load_key` instead of L(j)).

    Evaluated in the camera's parent frame P (the body, or its level frame for a gimbaled
    camera; see load_error): residual T_world_P^-1 l - T_body_cam p_cam with covariance
    R_bc cov_cam R_bc^T.  This is load_error rotated by the constant R_bc, so the whitened
    residual norm (hence the robust kernel and the normal equations) is exactly that of the
    camera-frame residual, while the value and Jacobians come from one C++ call
    (Pose3.transformTo) per evaluation; for a gimbaled camera the pose Jacobian is chained
    through geometry.level_frame_jacobian.  `noise_model`: the (robust) model of an earlier
    load_factor of the same sighting, reused (the incremental smoother re-keys a sighting)."""
    T_bc = np.asarray(camera.T_body_cam, float)
    R_bc = T_bc[:3, :3]
    p_parent = R_bc @ np.asarray(p_cam, float) + T_bc[:3, 3]
    model = noise_model
    if model is None:
        cov_parent = R_bc @ np.asarray(cov_cam, float) @ R_bc.T
        gaussian = gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov_parent + cov_parent.T))
        model = robust(gaussian, kernel, threshold)
    kx, kl = X(k), (L(j) if load_key is None else load_key)

    if not camera.gimbaled:

        def error(this, values, jacobians):
            pose, l_world = values.atPose3(kx), values.atPoint3(kl)
            if jacobians is None:
                return pose.transformTo(l_world) - p_parent
            Hx, Hl = np.empty((3, 6), order="F"), np.empty((3, 3), order="F")
            q = pose.transformTo(l_world, Hx, Hl)
            jacobians[0] = Hx
            jacobians[1] = Hl
            return q - p_parent
    else:

        def error(this, values, jacobians):
            T_wb = values.atPose3(kx).matrix()
            level = gtsam.Pose3(level_frame(T_wb))
            l_world = values.atPoint3(kl)
            if jacobians is None:
                return level.transformTo(l_world) - p_parent
            Hp, Hl = np.empty((3, 6), order="F"), np.empty((3, 3), order="F")
            q = level.transformTo(l_world, Hp, Hl)
            jacobians[0] = Hp @ level_frame_jacobian(T_wb)
            jacobians[1] = Hl
            return q - p_parent

    return gtsam.CustomFactor(model, [kx, kl], error)


def constant_velocity_error(
    dt: float, pose0: gtsam.Pose3, pose1: gtsam.Pose3, v0: np.ndarray, v1: np.ndarray, want_jacobian: bool
):
    """Residual p1 - p0 - (v0 + v1) dt / 2 (world, m) (3,) and Jacobians wrt X0, X1, V0, V1."""
    e = pose1.translation() - pose0.translation() - 0.5 * dt * (v0 + v1)
    if not want_jacobian:
        return e, None
    H0, H1 = np.zeros((3, 6)), np.zeros((3, 6))
    H0[:, 3:] = -pose0.rotation().matrix()
    H1[:, 3:] = pose1.rotation().matrix()
    Hv = -0.5 * dt * np.eye(3)
    return e, (H0, H1, Hv, Hv)


def constant_velocity_factor(k0: int, k1: int, dt: float, sigma_m: float) -> gtsam.CustomFactor:
    """Trapezoidal position-velocity consistency between frames k0 and k1 (where no IMU exists):
    part of the weak random-walk bridge (white acceleration)."""
    model = gtsam.noiseModel.Isotropic.Sigma(3, sigma_m)

    def error(this, values, jacobians):
        x0, x1, v0, v1 = this.keys()
        e, H = constant_velocity_error(
            dt,
            values.atPose3(x0),
            values.atPose3(x1),
            values.atVector(v0),
            values.atVector(v1),
            jacobians is not None,
        )
        if jacobians is not None:
            for i in range(4):
                jacobians[i] = H[i]
        return e

    return gtsam.CustomFactor(model, [X(k0), X(k1), V(k0), V(k1)], error)


def bridge_factors(
    k0: int,
    k1: int,
    dt: float,
    accel_sigma: float,
    rate_sigma: float,
    with_bias: bool,
    noise: ImuNoise | None,
    free_sigma_m: float,
    min_dt_s: float,
    min_sigma: float,
) -> list:
    """Weak random-walk link between frames k0 and k1 where no IMU data covers the interval:
    rotation random walk (white rate, sigma rate*sqrt(dt)), velocity random walk (white
    acceleration, sigma accel*sqrt(dt)), position-velocity consistency (sigma accel*dt^1.5/2;
    the pose link's translation is left free, sigma `free_sigma_m`), and the bias random walk
    of the IMU when bias states exist.  dt is floored at `min_dt_s`, sigmas at `min_sigma`."""
    dt = max(dt, min_dt_s)
    rot_sigma = rate_sigma * math.sqrt(dt)
    out = [
        gtsam.BetweenFactorPose3(
            X(k0),
            X(k1),
            gtsam.Pose3(),
            gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, rot_sigma), np.full(3, free_sigma_m)]),
        ),
        gtsam.BetweenFactorVector(
            V(k0), V(k1), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, accel_sigma * math.sqrt(dt))
        ),
        constant_velocity_factor(k0, k1, dt, 0.5 * accel_sigma * dt**1.5 + min_sigma),
    ]
    if with_bias:
        assert noise is not None  # bias states exist only with an IMU (and its noise)
        sg = max(noise.gyroscope_random_walk * math.sqrt(dt), min_sigma)
        sa = max(noise.accelerometer_random_walk * math.sqrt(dt), min_sigma)
        out.append(
            gtsam.BetweenFactorConstantBias(
                B(k0),
                B(k1),
                gtsam.imuBias.ConstantBias(),
                gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sa), np.full(3, sg)]),
            )
        )
    return out


def floor_corner_factor(
    k: int,
    camera: CameraModel,
    corners_world: np.ndarray,
    corners_px: np.ndarray,
    whitening: np.ndarray,
    kernel: RobustKernel,
    threshold: float,
    behind_residual: float,
) -> gtsam.CustomFactor:
    """Tight coupling: the floor codes' known world corners reprojected into the floor camera at
    frame k, one factor on X(k) for all codes of the frame.

    corners_world (4c, 3) m, corners_px (4c, 2) the refined detections (TL, TR, BR, BL per code),
    whitening (c, 8, 8) per code (fusion.qr.pnp.corner_whitening: the corners' 8x8 covariance
    C = L L^T -> L^-1).  Residual W (project(T_world_cam^-1 p) - uv) (8c,), unit-free after
    whitening, T_world_cam = camera.T_world_cam(T_world_body); the projection is the camera's
    full radial-tangential model (fusion.qr.reprojection.floor_reprojection, whose Jacobian is w.r.t. the
    same right perturbation as GTSAM's Pose3, of the camera's parent frame: for a gimbaled
    camera the level frame, chained to the body by geometry.level_frame_jacobian).  A corner
    behind the camera at the current estimate gives a residual of `behind_residual` with zero
    Jacobian (the robust kernel then caps its pull)."""
    P = np.asarray(corners_world, float).copy()
    z = np.asarray(corners_px, float).reshape(-1).copy()
    W = np.asarray(whitening, float).copy()
    c = len(W)
    model = robust(gtsam.noiseModel.Unit.Create(8 * c), kernel, threshold)
    kx = X(k)
    gimbaled = camera.gimbaled

    def error(this, values, jacobians):
        T_wb = values.atPose3(kx).matrix()
        uv, J = floor_reprojection(camera, level_frame(T_wb) if gimbaled else T_wb, P)
        if gimbaled:
            J = J @ level_frame_jacobian(T_wb)
        r = uv.reshape(-1) - z
        bad = ~np.isfinite(r)
        if bad.any():
            r[bad] = behind_residual
            J[bad] = 0.0
        rw = (W @ r.reshape(c, 8, 1)).reshape(-1)
        if jacobians is not None:
            jacobians[0] = (W @ J.reshape(c, 8, 6)).reshape(8 * c, 6)
        return rw

    return gtsam.CustomFactor(model, [kx], error)
