"""Causal EKF baseline (filterpy ExtendedKalmanFilter), same inputs and outputs as the smoother.

Error-state EKF (Sola, "Quaternion kinematics for the error-state Kalman filter", 2017, Sec. 5
and 6) with filterpy holding the 15-d error state and its covariance:

    x = [dtheta (IMU-frame rotation, right perturbation), dp (world), dv (world), dbg, dba]

The nominal state is the IMU frame's pose T_world_imu, world velocity and the biases; it is
propagated by strapdown at the IMU rate (the signal at each sub-interval's midpoint, as in the
smoother), so an IMU mounted off the body frame needs no lever-arm approximation; outputs and
measurements are mapped to the body with T_body_imu (Pose3 adjoint).  After each update the
error is injected into the nominal state and reset to zero (reset Jacobian taken as identity).

Updates: QR pose (6-dof, residual Log(T_hat^-1 T_meas) in the body frame), or the paper's
position + yaw (yaw wrap-around handled by filterpy's `residual` hook), and body velocity.  The
update is filterpy's, in Joseph form (P = (I-KH) P (I-KH)^T + K R K^T, filterpy/kalman/EKF.py).
Outliers: the measurement covariance is inflated by the robust kernel's IRLS weight at the
innovation's Mahalanobis distance d (huber: d/k, cauchy: 1+(d/k)^2, tukey: skipped beyond k);
updates with d > k are counted as rejected (`rejected_pose_factors`, all updates), those with
d > FusionConfig.outlier_gate are skipped (`gated_updates`).

Where no IMU data covers an interval (gap, IMU that stops early) the prediction is a random walk
(constant velocity, constant rotation; process noise from FusionConfig.bridge_*), counted.

Loads: not filter states.  Each observation is mapped to the world with the filtered pose at its
frame, p = T_world_body T_body_cam p_cam, covariance R_wc cov_cam R_wc^T + J P_pose J^T, and the
observations of one load are fused by information weighting (this ignores the correlation of pose
errors between frames, so the load covariance is optimistic).
"""
from __future__ import annotations

import math
import time

import gtsam
import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from fusion.conventions import GRAVITY_M_S2
from fusion.estimate import graph as G
from fusion.estimate.common import (
    FusionConfig,
    FusionResult,
    check_inputs,
    first_velocity,
    group_load_obs,
    inlier_raw_mask,
    velocity_at_frames,
)
from fusion.estimate.smoother import imu_coverage, imu_subintervals
from fusion.geometry import adjoint, inv_T, skew, so3_exp, wrap_angle, yaw_of
from fusion.log.euroc import ImuData, VelocityData
from fusion.types import LoadEstimate, LoadMap, LoadObservation, Trajectory

__all__ = ["run_ekf"]

GRAVITY_W = np.array([0.0, 0.0, -GRAVITY_M_S2])
_TH, _P, _V, _BG, _BA = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)


class _Ekf:
    def __init__(self, T_body_imu: np.ndarray, config: FusionConfig):
        self.kf = ExtendedKalmanFilter(dim_x=15, dim_z=6)
        self.T_bi = T_body_imu
        self.T_ib = inv_T(T_body_imu)
        self.Ad_bi = adjoint(T_body_imu)
        self.config = config
        self.R = np.eye(3)          # R_world_imu
        self.p = np.zeros(3)        # p_world_imu
        self.v = np.zeros(3)        # v_world_imu
        self.bg = np.zeros(3)
        self.ba = np.zeros(3)
        self.omega = np.zeros(3)    # last bias-corrected rate (IMU frame), for velocity updates
        self.rejected = 0
        self.gated = 0

    # ------------------------------------------------------------------ state <-> body pose
    def T_world_body(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.p
        return T @ self.T_ib

    def J_body(self) -> np.ndarray:
        """d xi_body / d [dtheta, dp] (6x6): xi_imu = [dtheta, R^T dp], xi_body = Ad_bi xi_imu."""
        J = np.zeros((6, 6))
        J[:3, :3] = np.eye(3)
        J[3:, 3:] = self.R.T
        return self.Ad_bi @ J

    def body_cov(self) -> np.ndarray:
        J = self.J_body()
        return J @ self.kf.P[:6, :6] @ J.T

    # ------------------------------------------------------------------ prediction
    def predict_imu(self, acc: np.ndarray, gyr: np.ndarray, dt: float, noise) -> None:
        """Strapdown step over dt with one IMU sample (Sola 2017, eq. 260 and 269)."""
        w = gyr - self.bg
        f = acc - self.ba
        self.omega = w
        R = self.R
        a_w = R @ f + GRAVITY_W
        self.p = self.p + self.v * dt + 0.5 * a_w * dt * dt
        self.v = self.v + a_w * dt
        dR = so3_exp(w * dt)
        self.R = R @ dR
        F = np.eye(15)
        F[_TH, _TH] = dR.T
        F[_TH, _BG] = -np.eye(3) * dt
        F[_P, _V] = np.eye(3) * dt
        F[_V, _TH] = -R @ skew(f) * dt
        F[_V, _BA] = -R * dt
        q = np.empty(15)
        q[_TH] = noise.gyroscope_noise_density ** 2 * dt
        q[_P] = (self.config.integration_sigma ** 2) * dt
        q[_V] = noise.accelerometer_noise_density ** 2 * dt
        q[_BG] = noise.gyroscope_random_walk ** 2 * dt
        q[_BA] = noise.accelerometer_random_walk ** 2 * dt
        self.kf.F = F
        self.kf.Q = np.diag(q)
        self.kf.predict()

    def predict_random_walk(self, dt: float, noise) -> None:
        """No IMU: constant velocity and rotation, white acceleration / rate (FusionConfig.bridge_*)."""
        self.p = self.p + self.v * dt
        F = np.eye(15)
        F[_P, _V] = np.eye(3) * dt
        qa = self.config.bridge_accel_sigma_m_s2 ** 2
        q = np.zeros(15)
        q[_TH] = self.config.bridge_rate_sigma_rad_s ** 2 * dt
        q[_V] = qa * dt
        q[_P] = qa * dt ** 3 / 3.0
        if noise is not None:
            q[_BG] = noise.gyroscope_random_walk ** 2 * dt
            q[_BA] = noise.accelerometer_random_walk ** 2 * dt
        self.kf.F = F
        self.kf.Q = np.diag(q)
        self.kf.predict()

    # ------------------------------------------------------------------ updates
    def _robust_R(self, y: np.ndarray, H: np.ndarray, Rm: np.ndarray, dim: int):
        """Measurement covariance inflated by the kernel's IRLS weight; None = reject."""
        S = H @ self.kf.P @ H.T + Rm
        d = math.sqrt(max(float(y @ np.linalg.solve(S, y)), 0.0))
        k = self.config.threshold(dim)
        kernel = self.config.robust_kernel
        if d <= k or kernel == "none":
            return Rm
        self.rejected += 1
        if self.config.outlier_gate is not None and d > self.config.outlier_gate:
            self.gated += 1
            return None
        if kernel == "huber":
            return Rm * (d / k)
        if kernel == "cauchy":
            return Rm * (1.0 + (d / k) ** 2)
        return None    # tukey: weight 0

    def _update(self, z, H, hx, Rm, residual=np.subtract):
        y = residual(z, hx)
        Rr = self._robust_R(np.asarray(y).ravel(), H, Rm, len(y))
        if Rr is None:
            return
        self.kf.update(z, lambda x: H, lambda x: hx + H @ x, R=Rr, residual=residual)
        self._inject()

    def _inject(self) -> None:
        dx = self.kf.x.ravel()
        self.R = self.R @ so3_exp(dx[_TH])
        self.p = self.p + dx[_P]
        self.v = self.v + dx[_V]
        self.bg = self.bg + dx[_BG]
        self.ba = self.ba + dx[_BA]
        self.kf.x = np.zeros(15)

    def update_pose(self, T_meas: np.ndarray, cov: np.ndarray) -> None:
        """z = Log(T_hat_body^-1 T_meas) (6,), h(dx) = J_body dx (right perturbation)."""
        T_hat = gtsam.Pose3(self.T_world_body())
        z = gtsam.Pose3.Logmap(T_hat.between(gtsam.Pose3(T_meas)))
        H = np.zeros((6, 15))
        H[:, :6] = self.J_body()
        self._update(z, H, np.zeros(6), cov)

    def update_position_yaw(self, T_meas: np.ndarray, sigma_xyz, sigma_yaw: float) -> None:
        """z = [p_world_body (3), yaw (1)]; the residual hook wraps yaw to (-pi, pi]."""
        T_hat = gtsam.Pose3(self.T_world_body())
        z = np.r_[T_meas[:3, 3], yaw_of(T_meas[:3, :3])]
        e, Hb = G.position_yaw_error(np.zeros(3), 0.0, T_hat, True)   # e = h(T_hat)
        H = np.zeros((4, 15))
        H[:, :6] = Hb @ self.J_body()
        Rm = np.diag(np.r_[np.asarray(sigma_xyz, float), sigma_yaw] ** 2)

        def residual(a, b):
            r = np.subtract(a, b)
            r[3] = wrap_angle(r[3])
            return r

        self._update(z, H, e, Rm, residual)

    def update_body_velocity(self, v_meas: np.ndarray, sigma: float) -> None:
        """z = R_world_body^T v_world_body, with v_world_body = v + R (omega x t_imu_body)."""
        R_ib = self.T_ib[:3, :3]
        v_b_world = self.v + self.R @ np.cross(self.omega, self.T_ib[:3, 3])
        hx = R_ib.T @ self.R.T @ v_b_world
        H = np.zeros((3, 15))
        H[:, _TH] = R_ib.T @ skew(self.R.T @ v_b_world)
        H[:, _V] = R_ib.T @ self.R.T
        self._update(v_meas, H, hx, np.eye(3) * sigma ** 2)


def run_ekf(frame_times_ns, imu: ImuData | None, raw: Trajectory,
            load_obs: list[LoadObservation] | None, T_body_frontcam: np.ndarray,
            velocity: VelocityData | None = None,
            config: FusionConfig | None = None) -> FusionResult:
    """Causal error-state EKF over a flight; same inputs and result as `smooth`.

    The filter starts at the first (inlier) raw pose (`stats['frames_before_first_fix']` earlier
    frames have no estimate), with the velocity from a line through the first 0.5 s of raw
    positions (start-up look-ahead, as smooth_incremental).  Trajectory at the remaining frame
    times, with the filtered (causal) covariance mapped to the body frame (Pose3 order)."""
    config = config or FusionConfig()
    t_start = time.perf_counter()
    frame_t, rawp, imu, velocity, T_bc = check_inputs(frame_times_ns, imu, raw, velocity,
                                                      T_body_frontcam, config)
    n = len(frame_t)
    use = inlier_raw_mask(rawp, config)
    k0 = int(rawp.frame_idx[use].min())
    m0 = int(np.flatnonzero(use & (rawp.frame_idx == k0))[0])
    raw_at = {int(k): m for m, k in enumerate(rawp.frame_idx.tolist())}
    vmask, v_body = velocity_at_frames(frame_t, velocity, config)

    T_bi = np.asarray(imu.T_body_imu, float) if imu is not None else np.eye(4)
    f = _Ekf(T_bi, config)
    T_wi = rawp.T_world_body[m0] @ T_bi
    f.R, f.p = T_wi[:3, :3].copy(), T_wi[:3, 3].copy()
    f.v = first_velocity(frame_t, rawp, use, k0)
    P0 = np.zeros((15, 15))
    if rawp.full_pose:
        Jinv = np.linalg.inv(f.J_body())
        P0[:6, :6] = Jinv @ rawp.covariances[m0] @ Jinv.T
    else:
        P0[_TH, _TH] = np.diag([0.05 ** 2, 0.05 ** 2, config.paper_sigma_yaw_rad ** 2])
        P0[_P, _P] = np.diag(np.asarray(config.paper_sigma_xyz_m, float) ** 2)
    P0[_V, _V] = np.eye(3) * config.velocity_prior_sigma_m_s ** 2
    P0[_BG, _BG] = np.eye(3) * config.bias_prior_sigma_gyro_rad_s ** 2
    P0[_BA, _BA] = np.eye(3) * config.bias_prior_sigma_accel_m_s2 ** 2
    f.kf.x = np.zeros(15)
    f.kf.P = P0

    covered = np.zeros(max(n - 1, 0), bool)
    sub: dict[int, list] = {}
    if imu is not None:
        covered = imu_coverage(frame_t, imu, config.max_imu_gap_s)
        k_of, dts, gyr, acc = imu_subintervals(frame_t, imu, covered)
        cut = np.flatnonzero(np.diff(k_of)) + 1
        for ks, ds, gs, as_ in zip(np.split(k_of, cut), np.split(dts, cut), np.split(gyr, cut),
                                   np.split(acc, cut)):
            if len(ks):
                sub[int(ks[0])] = list(zip(as_, gs, ds.tolist()))
    noise = imu.noise if imu is not None else None

    T_out = np.empty((n - k0, 4, 4))
    cov_out = np.empty((n - k0, 6, 6))
    n_pose_updates = 0
    for k in range(k0, n):
        if k > k0:
            if covered[k - 1]:
                for acc_s, gyr_s, dt in sub[k - 1]:
                    f.predict_imu(acc_s, gyr_s, dt, noise)
            else:
                f.predict_random_walk((frame_t[k] - frame_t[k - 1]) * 1e-9, noise)
        m = raw_at.get(k)
        if m is not None and k > k0:
            if rawp.full_pose:
                f.update_pose(rawp.T_world_body[m], rawp.covariances[m])
            else:
                f.update_position_yaw(rawp.T_world_body[m], config.paper_sigma_xyz_m,
                                      config.paper_sigma_yaw_rad)
            n_pose_updates += 1
        if vmask[k]:
            f.update_body_velocity(v_body[k], velocity.noise_m_s)
        T_out[k - k0] = f.T_world_body()
        cov_out[k - k0] = f.body_cov()
        cov_out[k - k0] = 0.5 * (cov_out[k - k0] + cov_out[k - k0].T)

    loads = _map_loads(frame_t, load_obs, T_bc, T_out, cov_out, k0, config)
    stats = {"frames_before_first_fix": k0, "pose_updates": n_pose_updates,
             "rejected_pose_factors": f.rejected, "gated_updates": f.gated, "robust_kernel": config.robust_kernel,
             "imu_intervals": int(covered.sum()), "bridged_intervals": int((~covered).sum()),
             "time_s": time.perf_counter() - t_start}
    if imu is not None:
        t0, t1 = imu.timestamps_ns[0], imu.timestamps_ns[-1]
        stats["frames_outside_imu"] = int(((frame_t < t0) | (frame_t > t1)).sum())
    duration = (frame_t[-1] - frame_t[k0]) * 1e-9
    stats["realtime_factor"] = duration / max(stats["time_s"], 1e-9)
    return FusionResult(Trajectory("ekf", frame_t[k0:].copy(), T_out, cov_out), loads, stats)


def _map_loads(frame_t, load_obs, T_bc, T_out, cov_out, k0, config) -> LoadMap:
    """Information-weighted fusion of per-observation world points (see module docstring)."""
    groups, _ = group_load_obs(frame_t, load_obs or [], config)
    out = []
    for lid in sorted(groups):
        info, vec, nobs = np.zeros((3, 3)), np.zeros(3), 0
        for k, o in groups[lid]:
            if k < k0:
                continue
            T_wb = T_out[k - k0]
            q = T_bc[:3, :3] @ np.asarray(o.p_cam, float) + T_bc[:3, 3]   # body frame
            R_wb = T_wb[:3, :3]
            p = R_wb @ q + T_wb[:3, 3]
            J = np.hstack([-R_wb @ skew(q), R_wb])
            R_wc = R_wb @ T_bc[:3, :3]
            C = R_wc @ o.cov_cam @ R_wc.T + J @ cov_out[k - k0] @ J.T
            W = np.linalg.inv(C)
            info += W
            vec += W @ p
            nobs += 1
        if nobs:
            cov = np.linalg.inv(info)
            out.append(LoadEstimate(lid, cov @ vec, cov, nobs))
    return LoadMap("ekf", out)
