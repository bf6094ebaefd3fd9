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

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from fusion.conventions import GRAVITY_M_S2
from fusion.geometry import skew, wrap_angle
from fusion.log.euroc import ImuNoise

__all__ = ["X", "V", "B", "L", "imu_params", "robust", "pose_prior_factor",
           "position_yaw_factor", "body_velocity_factor", "load_factor",
           "constant_velocity_factor", "skew"]


# =========================================================================== noise models


def imu_params(noise: ImuNoise, T_body_imu: np.ndarray,
               integration_sigma: float = 1e-4) -> gtsam.PreintegrationCombinedParams:
    """CombinedImuFactor parameters from Kalibr continuous-time densities.

    GTSAM expects continuous-time covariances: sigma_density^2 * I for the measurement noise
    (it divides by dt per sample) and for the bias random walks (it multiplies by dt).
    Gravity (0, 0, -9.81) in the world (z up, `MakeSharedU`); `body_P_sensor` = T_body_imu, so
    the IMU may be offset / rotated from the body frame."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY_M_S2)
    I3 = np.eye(3)
    p.setGyroscopeCovariance(noise.gyroscope_noise_density ** 2 * I3)
    p.setAccelerometerCovariance(noise.accelerometer_noise_density ** 2 * I3)
    p.setBiasOmegaCovariance(noise.gyroscope_random_walk ** 2 * I3)
    p.setBiasAccCovariance(noise.accelerometer_random_walk ** 2 * I3)
    p.setIntegrationCovariance(integration_sigma ** 2 * I3)
    if not np.allclose(T_body_imu, np.eye(4)):
        p.setBodyPSensor(gtsam.Pose3(np.asarray(T_body_imu, float)))
    return p


def robust(base: gtsam.noiseModel.Base, kernel: str, threshold: float) -> gtsam.noiseModel.Base:
    """Wrap a Gaussian model in an M-estimator acting on the whitened residual norm."""
    est = gtsam.noiseModel.mEstimator
    if kernel == "none":
        return base
    make = {"huber": est.Huber, "cauchy": est.Cauchy, "tukey": est.Tukey}[kernel]
    return gtsam.noiseModel.Robust.Create(make.Create(threshold), base)


# =========================================================================== factors


def pose_prior_factor(k: int, T_world_body: np.ndarray, cov: np.ndarray, kernel: str,
                      threshold: float) -> gtsam.PriorFactorPose3:
    """Per-frame QR pose (6-dof, covariance in Pose3 order, body frame) as a robust prior on X(k)."""
    model = robust(gtsam.noiseModel.Gaussian.Covariance(cov), kernel, threshold)
    return gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T_world_body), model)


def position_yaw_error(p_meas: np.ndarray, yaw_meas: float, pose: gtsam.Pose3,
                       want_jacobian: bool):
    """Residual [p - p_meas (world, m), wrap(yaw - yaw_meas) (rad)] (4,) and its 4x6 Jacobian."""
    R = pose.rotation().matrix()
    t = pose.translation()
    yaw = math.atan2(R[1, 0], R[0, 0])
    e = np.concatenate([t - p_meas, [float(wrap_angle(yaw - yaw_meas))]])
    if not want_jacobian:
        return e, None
    H = np.zeros((4, 6))
    H[:3, 3:] = R
    # R' = R (I + [dr]x): dR[i,0] = R[i,1] dr_z - R[i,2] dr_y
    n = R[0, 0] ** 2 + R[1, 0] ** 2
    H[3, 1] = -(R[0, 0] * R[1, 2] - R[1, 0] * R[0, 2]) / n
    H[3, 2] = (R[0, 0] * R[1, 1] - R[1, 0] * R[0, 1]) / n
    return e, H


def position_yaw_factor(k: int, p_world: np.ndarray, yaw: float, sigma_xyz, sigma_yaw: float,
                        kernel: str, threshold: float) -> gtsam.CustomFactor:
    """The paper's per-frame output (position + yaw, no roll/pitch: those come from the IMU)."""
    p_meas = np.asarray(p_world, float).copy()
    yaw_meas = float(yaw)
    model = robust(gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.asarray(sigma_xyz, float), sigma_yaw]),
                   kernel, threshold)

    def error(this, values, jacobians):
        e, H = position_yaw_error(p_meas, yaw_meas, values.atPose3(this.keys()[0]),
                                  jacobians is not None)
        if jacobians is not None:
            jacobians[0] = H
        return e

    return gtsam.CustomFactor(model, [X(k)], error)


def body_velocity_error(v_meas_body: np.ndarray, pose: gtsam.Pose3, v_world: np.ndarray,
                        want_jacobian: bool):
    """Residual R^T v - v_meas (body frame, m/s) (3,), Jacobians wrt pose (3x6) and v (3x3)."""
    R = pose.rotation().matrix()
    vb = R.T @ v_world
    e = vb - v_meas_body
    if not want_jacobian:
        return e, None, None
    Hx = np.zeros((3, 6))
    Hx[:, :3] = skew(vb)           # (R Exp(dr))^T v = (I - [dr]x) R^T v = vb + [vb]x dr
    return e, Hx, R.T


def body_velocity_factor(k: int, v_body: np.ndarray, sigma_m_s: float) -> gtsam.CustomFactor:
    """Body-frame velocity measurement at frame k on X(k), V(k)."""
    v_meas = np.asarray(v_body, float).copy()
    model = gtsam.noiseModel.Isotropic.Sigma(3, sigma_m_s)

    def error(this, values, jacobians):
        kx, kv = this.keys()
        e, Hx, Hv = body_velocity_error(v_meas, values.atPose3(kx), values.atVector(kv),
                                        jacobians is not None)
        if jacobians is not None:
            jacobians[0] = Hx
            jacobians[1] = Hv
        return e

    return gtsam.CustomFactor(model, [X(k), V(k)], error)


def load_error(p_cam_meas: np.ndarray, T_body_cam: np.ndarray, pose: gtsam.Pose3,
               l_world: np.ndarray, want_jacobian: bool):
    """Residual (T_world_body T_body_cam)^-1 l - p_cam (camera frame, m) (3,), Jacobians wrt pose
    (3x6) and landmark (3x3)."""
    R = pose.rotation().matrix()
    t = pose.translation()
    R_bc, t_bc = T_body_cam[:3, :3], T_body_cam[:3, 3]
    q = R.T @ (l_world - t)                       # landmark in the body frame
    e = R_bc.T @ (q - t_bc) - p_cam_meas
    if not want_jacobian:
        return e, None, None
    Hx = np.zeros((3, 6))
    Hx[:, :3] = R_bc.T @ skew(q)
    Hx[:, 3:] = -R_bc.T
    return e, Hx, R_bc.T @ R.T


def load_factor(k: int, j: int, p_cam: np.ndarray, cov_cam: np.ndarray, T_body_cam: np.ndarray,
                kernel: str, threshold: float, load_key: int | None = None) -> gtsam.CustomFactor:
    """A load-code centre measured in the front camera at frame k, on X(k) and L(j) (or on
    `load_key` instead of L(j)).

    Evaluated in the body frame: residual T_world_body^-1 l - T_body_cam p_cam with covariance
    R_bc cov_cam R_bc^T.  This is load_error rotated by the constant R_bc, so the whitened
    residual norm (hence the robust kernel and the normal equations) is exactly that of the
    camera-frame residual, while the value and Jacobians come from one C++ call
    (Pose3.transformTo) per evaluation."""
    T_bc = np.asarray(T_body_cam, float)
    R_bc = T_bc[:3, :3]
    p_body = R_bc @ np.asarray(p_cam, float) + T_bc[:3, 3]
    cov_body = R_bc @ np.asarray(cov_cam, float) @ R_bc.T
    model = robust(gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov_body + cov_body.T)), kernel,
                   threshold)
    kx, kl = X(k), (L(j) if load_key is None else load_key)

    def error(this, values, jacobians):
        pose, l_world = values.atPose3(kx), values.atPoint3(kl)
        if jacobians is None:
            return pose.transformTo(l_world) - p_body
        Hx, Hl = np.empty((3, 6), order="F"), np.empty((3, 3), order="F")
        q = pose.transformTo(l_world, Hx, Hl)
        jacobians[0] = Hx
        jacobians[1] = Hl
        return q - p_body

    return gtsam.CustomFactor(model, [kx, kl], error)


def constant_velocity_error(dt: float, pose0: gtsam.Pose3, pose1: gtsam.Pose3, v0: np.ndarray,
                            v1: np.ndarray, want_jacobian: bool):
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
        e, H = constant_velocity_error(dt, values.atPose3(x0), values.atPose3(x1),
                                       values.atVector(v0), values.atVector(v1),
                                       jacobians is not None)
        if jacobians is not None:
            for i in range(4):
                jacobians[i] = H[i]
        return e

    return gtsam.CustomFactor(model, [X(k0), X(k1), V(k0), V(k1)], error)


def bridge_factors(k0: int, k1: int, dt: float, accel_sigma: float, rate_sigma: float,
                   with_bias: bool, noise: ImuNoise | None) -> list:
    """Weak random-walk link between frames k0 and k1 where no IMU data covers the interval:
    rotation random walk (white rate, sigma rate*sqrt(dt)), velocity random walk (white
    acceleration, sigma accel*sqrt(dt)), position-velocity consistency (sigma accel*dt^1.5/2),
    and the bias random walk of the IMU when bias states exist."""
    dt = max(dt, 1e-6)
    rot_sigma = rate_sigma * math.sqrt(dt)
    out = [
        gtsam.BetweenFactorPose3(X(k0), X(k1), gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(
            np.r_[np.full(3, rot_sigma), np.full(3, 1e3)])),
        gtsam.BetweenFactorVector(V(k0), V(k1), np.zeros(3),
                                  gtsam.noiseModel.Isotropic.Sigma(3, accel_sigma * math.sqrt(dt))),
        constant_velocity_factor(k0, k1, dt, 0.5 * accel_sigma * dt ** 1.5 + 1e-6),
    ]
    if with_bias:
        sg = max(noise.gyroscope_random_walk * math.sqrt(dt), 1e-9)
        sa = max(noise.accelerometer_random_walk * math.sqrt(dt), 1e-9)
        out.append(gtsam.BetweenFactorConstantBias(
            B(k0), B(k1), gtsam.imuBias.ConstantBias(),
            gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sa), np.full(3, sg)])))
    return out


def floor_corner_factor(k: int, camera, corners_world: np.ndarray, corners_px: np.ndarray,
                        whitening: np.ndarray, kernel: str, threshold: float) -> gtsam.CustomFactor:
    """Tight coupling: the floor codes' known world corners reprojected into the floor camera at
    frame k, one factor on X(k) for all codes of the frame.

    corners_world (4c, 3) m, corners_px (4c, 2) the refined detections (TL, TR, BR, BL per code),
    whitening (c, 8, 8) per code (fusion.qr.pnp.corner_whitening: the corners' 8x8 covariance
    C = L L^T -> L^-1).  Residual W (project(T_body_cam^-1 T_world_body^-1 p) - uv) (8c,),
    unit-free after whitening; the projection is the camera's full radial-tangential model
    (fusion.qr.reprojection.floor_reprojection; its Jacobian is w.r.t. the right perturbation of
    GTSAM's Pose3).  A corner behind the camera at the current estimate gives a residual of
    1e3 with zero Jacobian (the robust kernel then caps its pull)."""
    from fusion.qr.reprojection import floor_reprojection
    P = np.asarray(corners_world, float).copy()
    z = np.asarray(corners_px, float).reshape(-1).copy()
    W = np.asarray(whitening, float).copy()
    c = len(W)
    model = robust(gtsam.noiseModel.Unit.Create(8 * c), kernel, threshold)
    kx = X(k)

    def error(this, values, jacobians):
        uv, J = floor_reprojection(camera, values.atPose3(kx).matrix(), P)
        r = uv.reshape(-1) - z
        bad = ~np.isfinite(r)
        if bad.any():
            r[bad] = 1e3
            J[bad] = 0.0
        rw = (W @ r.reshape(c, 8, 1)).reshape(-1)
        if jacobians is not None:
            jacobians[0] = (W @ J.reshape(c, 8, 6)).reshape(8 * c, 6)
        return rw

    return gtsam.CustomFactor(model, [kx], error)
