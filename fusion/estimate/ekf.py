"""Causal EKF baseline (filterpy ExtendedKalmanFilter), same inputs and outputs as the smoother.

Error-state EKF (Sola, "Quaternion kinematics for the error-state Kalman filter", 2017, Sec. 5
and 6) with filterpy holding the 15-d error state and its covariance:

    x = [dtheta (IMU-frame rotation, right perturbation), dp (world), dv (world), dbg, dba]

The nominal state is the IMU frame's pose T_world_imu, world velocity and the biases; it is
propagated by strapdown at the IMU rate (the signal at each sub-interval's midpoint, as in the
smoother), so an IMU mounted off the body frame needs no lever-arm approximation; outputs and
measurements are mapped to the body with T_body_imu (Pose3 adjoint).  After each update the
error is injected into the nominal state and reset to zero (reset Jacobian taken as identity).

Start: at the first fix, or, with level fixes (a gimbaled floor camera) and an IMU, from a
batch solve of the first `FusionConfig.ekf_level_start_s` of fixes and its joint marginal
(`level_batch_start`: level fixes leave roll / pitch to the accelerometer, where they trade with
its bias, and a start at tilt 0 +- 10 deg made the filter inconsistent there).

Updates: QR pose (6-dof, residual Log(T_hat^-1 T_meas) in the body frame), or position + yaw
(yaw wrap-around handled by filterpy's `residual` hook) for the paper's output and for the
level-frame pose of a gimbaled floor camera (pnp.py gives roll/pitch no information there: its
world position and yaw, with their covariance, are what the fix measures), and body velocity.
The update is filterpy's, in Joseph form (P = (I-KH) P (I-KH)^T + K R K^T, filterpy/kalman/EKF.py),
its arithmetic reproduced without the per-call copies and checks (`_kf_update`, the same numbers).
A frame's fix and body velocity are one stacked filterpy update when both are within their
robust thresholds (`_Ekf.update_fix_and_velocity`; the two in turn otherwise), and the gates'
Mahalanobis distances come from filterpy's own innovation and S^-1 (`_Ekf._trial`).
Outliers: the measurement covariance is inflated by the robust kernel's IRLS weight at the
innovation's Mahalanobis distance d (huber: d/k, cauchy: 1+(d/k)^2, tukey: skipped beyond k);
updates with d > k are counted as rejected (`rejected_pose_factors`, all updates), those with
d > FusionConfig.outlier_gate are skipped (`gated_updates`).

Recovery, not lock-out (issue 8).  A fixed gate locks a filter out for good once it has drifted
(a faulty IMU: gyro dead band, saturation, accelerometer in g): every later fix is "an outlier".
The filter therefore keeps the fixes of the last `EkfRecovery.window_s` and asks whether they
agree with each other (a cubic in time fits their positions and yaw within 3 sigma plus a motion
tolerance; a misread or a misprinted code makes a jump that a cubic does not fit):
- most fixes of the window beyond the robust threshold and the window consistent: the filter, not
  the fixes, is wrong; its covariance is inflated (all of P, biases included, by the scalar that
  brings the squared Mahalanobis distance of the innovation to its expected value, the
  dimension: innovation-based covariance matching, Mehra, IEEE TAC 17(5), 1972; cf. the
  fading-memory filter of Simon, "Optimal State Estimation", 2006, sec. 7.4) and the fix is used
  at full weight (`inflated_updates`);
- every fix of the window gated and the window consistent: the filter re-initialises from the
  fixes (pose and covariance from the last fix, velocity from the cubic's slope, bias covariance
  back to its fault level) (`resets`).
So no run of consistent fixes is gated for ever, and the covariance grows when the filter is
wrong instead of claiming an accuracy it lost.

Where no IMU data covers an interval (gap, IMU that stops early) the prediction is a random walk
(constant velocity, constant rotation; process noise from FusionConfig.bridge_*), counted.
An update that turns the attitude by more than ITERATE_MIN_ROTATION_RAD (the first fix after
such a gap) is iterated to convergence (`_Ekf._iterate`), counted (`iterated_updates`).

Loads: not filter states.  Each observation is mapped to the world with the filtered pose at its
frame through the front camera's mount, p = T_world_cam(T_world_body) p_cam (CameraModel, so a
gimbaled camera hangs from the level frame), covariance R_wc cov_cam R_wc^T + J P_pose J^T (J by
central differences on the body pose, mount-agnostic), and the observations of one load are
fused by information weighting (this ignores the correlation of pose errors between frames, so
the load covariance is optimistic by itself: the run adds the error the sightings share as
consider terms, fusion.estimate.loadconsider).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
import scipy.linalg
from filterpy.kalman import ExtendedKalmanFilter

from fusion.camera import CameraModel
from fusion.conventions import GRAVITY_M_S2
from fusion.errors import EstimationError
from fusion.estimate import factors
from fusion.estimate.common import (
    FusionConfig,
    FusionResult,
    RawPoses,
    SolveHealth,
    first_velocity,
    fix_jumps,
    group_load_obs,
    inlier_raw_mask,
    prepare_inputs,
    retime_load_obs,
    velocity_at_frames,
)
from fusion.estimate.factors import B, L, V, X
from fusion.estimate.smoother import build_problem, imu_coverage, imu_subintervals, solve
from fusion.estimate.variance import nis_component
from fusion.geometry import (
    adjoint,
    cross3,
    inv_T,
    rot_z,
    se3_exp,
    skew,
    skew_stack,
    so3_exp,
    so3_exp_floats,
    so3_log,
    wrap_angle,
    yaw_of,
)
from fusion.log.euroc import ImuData, VelocityData
from fusion.types import LoadEstimate, LoadMap, LoadObservation, Trajectory

__all__ = ["EkfRecovery", "LevelStart", "level_batch_start", "run_ekf"]

log = logging.getLogger(__name__)

GRAVITY_W = np.array([0.0, 0.0, -GRAVITY_M_S2])
_TH, _P, _V, _BG, _BA = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)
_EYE3 = np.eye(3)  # read-only identities (np.eye per call was ~3 % of the EKF's time)
_EYE15 = np.eye(15)
_LOAD_JACOBIAN_STEP = 1e-6  # body-pose perturbation (rad, m) for the load-point Jacobian
_TILT_SIGMA_RAD = 0.05  # roll / pitch 1-sigma of a start or reset from position + yaw
LEVEL_START_MIN_FIXES = 5
"""Fewest level fixes in the start window: a window of FusionConfig.ekf_level_start_s with fewer
(sparse fixes at the start) is extended to this many fixes; a flight with fewer fixes in all
starts at the first fix as before."""
ITERATE_MIN_ROTATION_RAD = 0.01
"""An update whose attitude correction exceeds this is iterated (`_Ekf._iterate`): the
measurement relinearised at the corrected state until the correction settles."""
ITERATE_MAX = 8
ITERATE_TOL = 1e-10
"""Largest change of the error state (rad, m, m/s) between two iterations that ends them."""


def _inv_kernel():
    """scipy.linalg.inv's LAPACK kernel (a private name of scipy 1.17: `_inv(a, structure,
    overwrite_a, lower)` -> (inverse, errors)), or None where it is missing or does not answer
    as that on a test matrix (another scipy): _inv then takes scipy.linalg.inv itself."""
    try:
        from scipy.linalg._batched_linalg import _inv as kernel

        probe = np.array([[4.0, 1.0], [2.0, 3.0]])
        out, errors = kernel(probe, -1, False, False)
        if errors or not np.array_equal(out, scipy.linalg.inv(probe)):
            return None
        return kernel
    except Exception:  # noqa: BLE001 - any failure: the public function
        return None


_scipy_inv_kernel = _inv_kernel()


def _inv(S: np.ndarray) -> np.ndarray:
    """scipy.linalg.inv(S) (filterpy's S^-1), the same numbers: for a finite float64 matrix its
    LAPACK kernel is called directly (the checks around it were ~2/3 of its ~35 us per update);
    anything else, or a kernel that reports an error (singular S), through scipy.linalg.inv
    itself, so its errors and warnings are filterpy's."""
    if _scipy_inv_kernel is not None and S.dtype == np.float64 and S.ndim == 2 and np.isfinite(S).all():
        out, errors = _scipy_inv_kernel(S, -1, False, False)
        if not errors:
            return out
    return scipy.linalg.inv(S)


def _kf_update(kf: ExtendedKalmanFilter, z: np.ndarray, H: np.ndarray, hx, R: np.ndarray, residual) -> None:
    """filterpy's ExtendedKalmanFilter.update(z, lambda x: H, hx, R=R, residual=residual) for an
    array R and z, the same arithmetic in the same order (the Joseph form, filterpy/kalman/EKF.py):
    S, S^-1, K, y, x and P are set as it sets them and bound to new arrays (`_trial`'s `before`
    keeps the old ones).  Left out: its copies of z, x and P into z / x_post / P_post (a
    deepcopy of z per update; nothing here reads them) and its argument checks, ~1/3 of the
    update's time (BENCHMARKS.md, speed18).  hx: h(x) at kf.x (a callable, as filterpy's)."""
    P = kf.P
    PHT = np.dot(P, H.T)
    kf.S = np.dot(H, PHT) + R
    kf.SI = _inv(kf.S)
    kf.K = PHT.dot(kf.SI)
    kf.y = residual(z, hx(kf.x))
    kf.x = kf.x + np.dot(kf.K, kf.y)
    I_KH = kf._I - np.dot(kf.K, H)
    kf.P = np.dot(I_KH, P).dot(I_KH.T) + np.dot(kf.K, R).dot(kf.K.T)
    kf._log_likelihood = kf._likelihood = kf._mahalanobis = None


_EYE15_STACKS: dict[int, np.ndarray] = {}


def _eye15_stack(K: int) -> np.ndarray:
    """A fresh (K, 15, 15) stack of identities (the template kept per K)."""
    t = _EYE15_STACKS.get(K)
    if t is None:
        t = _EYE15_STACKS[K] = np.broadcast_to(_EYE15, (K, 15, 15)).copy()
    return t.copy()


@dataclass
class EkfRecovery:
    """When and how the EKF recovers instead of locking out (module docstring).

    window_s / min_fixes: the fixes looked at (at least min_fixes within the last window_s);
    lookback_s / max_speed_m_s: no step between consecutive fixes of the last lookback_s may be
    faster than max_speed_m_s (a warehouse drone's top speed, with margin; see _FixWindow);
    fault_share: share of the window's fixes beyond the robust threshold that makes the filter,
    not the fixes, the suspect; consistency_m / consistency_rad: motion tolerance of the cubic
    fit (unmodelled jerk over the window plus margin) on top of 3 sigma of each fix;
    max_inflation: cap of the covariance scale factor per fix; reset_sigma_gyro_rad_s /
    reset_sigma_accel_m_s2: bias 1-sigma after a reset (a faulty IMU: dead band, saturation, wrong
    unit, so large biases must be learnable); reset_velocity_sigma_m_s: floor of the velocity
    1-sigma after a reset.  enabled=False gives the plain gated filter (it can lock out)."""

    enabled: bool = True
    window_s: float = 1.5
    lookback_s: float = 3.0
    max_speed_m_s: float = 5.0
    min_fixes: int = 6
    fault_share: float = 0.5
    consistency_m: float = 0.1
    consistency_rad: float = math.radians(3.0)
    max_inflation: float = 1e8
    reset_sigma_gyro_rad_s: float = 0.1
    reset_sigma_accel_m_s2: float = 2.0
    reset_velocity_sigma_m_s: float = 0.3


@dataclass
class _Fix:
    """One raw fix as the recovery logic sees it: time (s), world position (3,), yaw (rad),
    their 1-sigma (position per axis (3,), yaw), the fix itself (for a reset) and its outcome."""

    t_s: float
    p_world: np.ndarray
    yaw: float
    sigma_p: np.ndarray
    sigma_yaw: float
    T_meas: np.ndarray
    cov: np.ndarray  # 6x6 body-frame (full pose) or level-frame covariance
    over: bool = False  # beyond the robust threshold
    gated: bool = False  # beyond the gate


class _FixWindow:
    """The recent fixes and whether they agree with each other: a cubic in time fits those of
    the last `window_s`, and no step between consecutive fixes of the last `lookback_s` is
    faster than `max_speed_m_s` (so a jump into a run of self-consistent but wrong fixes, a
    misprinted code, stays visible for lookback_s after it)."""

    def __init__(self, rec: EkfRecovery):
        self.rec = rec
        self.fixes: deque[_Fix] = deque()

    def add(self, fix: _Fix) -> None:
        self.fixes.append(fix)
        while self.fixes and fix.t_s - self.fixes[0].t_s > max(self.rec.lookback_s, self.rec.window_s):
            self.fixes.popleft()

    def clear(self) -> None:
        self.fixes.clear()

    def recent(self) -> list[_Fix]:
        t_new = self.fixes[-1].t_s
        return [f for f in self.fixes if t_new - f.t_s <= self.rec.window_s]

    def jump_free(self) -> bool:
        """No step between consecutive fixes of the look-back beyond max_speed_m_s * dt plus
        3 sigma of both fixes and the motion tolerance."""
        f = list(self.fixes)
        if len(f) < 2:
            return True
        t = np.array([x.t_s for x in f])
        P = np.array([x.p_world for x in f])
        sp = np.array([np.linalg.norm(x.sigma_p) for x in f])
        slack = 3.0 * (sp[1:] + sp[:-1]) + self.rec.consistency_m
        return not bool(np.any(fix_jumps(t, P, self.rec.max_speed_m_s, slack)))

    def consistent(self) -> bool:
        return self.fit(self.recent())[0] and self.jump_free()

    def fit(self, fixes):
        """(consistent: bool, velocity at the last fix (3,)): least-squares cubic per position
        axis and for the unwrapped yaw over `fixes`; consistent when every residual is within
        3 sigma of the fix plus the motion tolerance."""
        t = np.array([f.t_s for f in fixes])
        t = t - t[-1]
        P = np.array([f.p_world for f in fixes])
        yaw = np.unwrap([f.yaw for f in fixes])
        deg = min(3, len(t) - 2)
        A = np.vander(t, deg + 1)
        Y = np.column_stack([P, yaw])
        coef, *_ = np.linalg.lstsq(A, Y, rcond=None)
        res = np.abs(Y - A @ coef)
        sp = np.array([f.sigma_p for f in fixes])
        sy = np.array([f.sigma_yaw for f in fixes])
        ok = bool(
            np.all(res[:, :3] <= 3.0 * sp + self.rec.consistency_m)
            and np.all(res[:, 3] <= 3.0 * sy + self.rec.consistency_rad)
        )
        velocity = coef[-2, :3] if deg >= 1 else np.zeros(3)
        return ok, velocity

    def filter_at_fault(self) -> bool:
        recent = self.recent()
        if len(recent) < self.rec.min_fixes:
            return False
        share = np.mean([f.over for f in recent])
        return bool(share >= self.rec.fault_share) and self.consistent()

    def all_gated(self) -> bool:
        recent = self.recent()
        return len(recent) >= self.rec.min_fixes and all(f.gated for f in recent) and self.consistent()


@dataclass
class _Measurement:
    """One EKF measurement: z, its Jacobian H (m, 15) in the error state, the prediction hx at
    zero error, covariance R (m, m), the residual hook (z, hx) -> y, and the fix it is (None for
    a velocity)."""

    z: np.ndarray
    H: np.ndarray
    hx: np.ndarray
    R: np.ndarray
    residual: Any
    fix: _Fix | None
    # (z, H, hx) again at the filter's current nominal state, for the iterated update
    relinearize: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]


def _yaw_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[p (3), yaw] residual with the yaw wrapped to (-pi, pi]."""
    r = np.subtract(a, b)
    r[3] = wrap_angle(r[3])
    return r


class _Ekf:
    def __init__(self, T_body_imu: np.ndarray, config: FusionConfig, recovery: EkfRecovery):
        self.kf = ExtendedKalmanFilter(dim_x=15, dim_z=6)
        self.T_bi = T_body_imu
        self.T_ib = inv_T(T_body_imu)
        self.Ad_bi = adjoint(T_body_imu)
        self.config = config
        self.recovery = recovery
        self.R = np.eye(3)  # R_world_imu
        self.p = np.zeros(3)  # p_world_imu
        self.v = np.zeros(3)  # v_world_imu
        self.bg = np.zeros(3)
        self.ba = np.zeros(3)
        self.omega = np.zeros(3)  # last bias-corrected rate (IMU frame), for velocity updates
        self.rejected = 0
        self.gated = 0
        self.inflated = 0
        self.resets = 0
        self.iterated = 0  # updates iterated (_iterate)
        self.window = _FixWindow(recovery)
        self.nis: list[tuple[float, int]] = []  # (squared Mahalanobis innovation, dim) per fix
        self._q_cache: tuple[Any, np.ndarray] | None = None  # (noise record, _q_density of it)

    # ------------------------------------------------------------------ state <-> body pose
    def T_world_body(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.p
        return T @ self.T_ib

    def J_body(self) -> np.ndarray:
        """d xi_body / d [dtheta, dp] (6x6): xi_imu = [dtheta, R^T dp], xi_body = Ad_bi xi_imu."""
        J = np.zeros((6, 6))
        J[:3, :3] = _EYE3
        J[3:, 3:] = self.R.T
        return self.Ad_bi @ J

    def body_cov(self) -> np.ndarray:
        J = self.J_body()
        return J @ self.kf.P[:6, :6] @ J.T

    def set_pose(self, T_world_body: np.ndarray, cov_body: np.ndarray) -> None:
        """Nominal pose from a body pose and its 6x6 body-frame covariance (Pose3 order)."""
        T_wi = T_world_body @ self.T_bi
        self.R, self.p = T_wi[:3, :3].copy(), T_wi[:3, 3].copy()
        Jinv = np.linalg.inv(self.J_body())
        self.kf.P[:6, :6] = Jinv @ cov_body @ Jinv.T
        self.kf.P[:6, 6:] = 0.0
        self.kf.P[6:, :6] = 0.0

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
        q[_TH] = noise.gyroscope_noise_density**2 * dt
        q[_P] = (self.config.integration_sigma**2) * dt
        q[_V] = noise.accelerometer_noise_density**2 * dt
        q[_BG] = noise.gyroscope_random_walk**2 * dt
        q[_BA] = noise.accelerometer_random_walk**2 * dt
        self.kf.F = F
        self.kf.Q = np.diag(q)
        self.kf.predict()

    def predict_imu_block(self, acc: np.ndarray, gyr: np.ndarray, dts: np.ndarray, noise) -> None:
        """predict_imu over the K IMU sub-intervals between two frames at once (acc, gyr (K, 3),
        dts (K,) s): the same strapdown, F and Q per sample (Sola 2017, eq. 260 and 269), and the
        same products P = F P F^T + Q as filterpy's predict, but the biases are fixed between
        updates, so the rate exponentials are taken together and P is handed to filterpy once
        (its error state x is zero between updates, so F x stays zero).  The per-sample filterpy
        call and its matrix set-up were most of the EKF's time (BENCHMARKS.md, back-end speed)."""
        K = len(dts)
        if K == 0:
            return
        dts = np.asarray(dts, float)
        W = gyr - self.bg
        Fb = acc - self.ba
        dRs = so3_exp_floats(W * dts[:, None])
        # F per sub-interval (Sola eq. 269); the attitude R0[i] at the start of sub-interval i is
        # filled in below, as the chain of rate exponentials reaches it
        F = _eye15_stack(K)
        R0 = np.empty((K, 3, 3))
        R = self.R
        for i in range(K):
            R0[i] = R
            R = R @ dRs[i]
        a_w = np.einsum("kij,kj->ki", R0, Fb) + GRAVITY_W  # world acceleration per sub-interval
        dv = a_w * dts[:, None]
        v_start = np.empty((K + 1, 3))  # velocity at the start of each sub-interval, and the end
        v_start[0] = self.v
        np.add.accumulate(dv, axis=0, out=v_start[1:])  # cumsum without its wrapper
        v_start[1:] += self.v
        dp = v_start[:-1] * dts[:, None] + 0.5 * a_w * (dts * dts)[:, None]
        dt3 = dts[:, None, None]
        F[:, _TH, _TH] = dRs.transpose(0, 2, 1)
        eye_dt = _EYE3 * dt3
        F[:, _TH, _BG] = -eye_dt
        F[:, _P, _V] = eye_dt
        F[:, _V, _TH] = -(R0 @ skew_stack(Fb)) * dt3
        F[:, _V, _BA] = -R0 * dt3
        Ft = F.transpose(0, 2, 1)
        Q = self._q_density(noise)[None, :] * dts[:, None]  # (K, 15) diagonal of Q
        P = self.kf.P
        dot = np.dot
        for F_i, Ft_i, Q_i in zip(F, Ft, Q):  # filterpy's predict: P = F P F^T + Q
            P = dot(F_i, P).dot(Ft_i)
            diagonal = P.reshape(225)[::16]  # a view (P is a new contiguous array)
            diagonal += Q_i  # Q is diagonal: adding its zeros would leave P's entries exact
        self.R = R
        self.p = self.p + np.add.reduce(dp, axis=0)
        self.v = v_start[-1]
        self.omega = W[-1]
        self.kf.F = F[-1]
        self.kf.P = P
        self.kf.x_prior = self.kf.x.copy()
        self.kf.P_prior = P.copy()

    def _q_density(self, noise) -> np.ndarray:
        """(15,) continuous process noise of predict_imu per second (Q = diag(q) dt), computed
        once per noise record (it is the same for the whole flight)."""
        if self._q_cache is not None and self._q_cache[0] is noise:
            return self._q_cache[1]
        q = np.empty(15)
        q[_TH] = noise.gyroscope_noise_density**2
        q[_P] = self.config.integration_sigma**2
        q[_V] = noise.accelerometer_noise_density**2
        q[_BG] = noise.gyroscope_random_walk**2
        q[_BA] = noise.accelerometer_random_walk**2
        self._q_cache = (noise, q)
        return q

    def predict_random_walk(self, dt: float, noise) -> None:
        """No IMU: constant velocity and rotation, white acceleration / rate (FusionConfig.bridge_*)."""
        self.p = self.p + self.v * dt
        F = np.eye(15)
        F[_P, _V] = np.eye(3) * dt
        qa = self.config.bridge_accel_sigma_m_s2**2
        q = np.zeros(15)
        q[_TH] = self.config.bridge_rate_sigma_rad_s**2 * dt
        q[_V] = qa * dt
        q[_P] = qa * dt**3 / 3.0
        if noise is not None:
            q[_BG] = noise.gyroscope_random_walk**2 * dt
            q[_BA] = noise.accelerometer_random_walk**2 * dt
        self.kf.F = F
        self.kf.Q = np.diag(q)
        self.kf.predict()

    # ------------------------------------------------------------------ updates
    def _mahalanobis(self, y: np.ndarray, H: np.ndarray, Rm: np.ndarray) -> float:
        """Mahalanobis distance of the innovation y under the current P (the updates take it
        from filterpy's own S^-1, `_trial`)."""
        S = H @ self.kf.P @ H.T + Rm
        return math.sqrt(max(float(y @ np.linalg.solve(S, y)), 0.0))

    def _robust_R(self, d: float, Rm: np.ndarray, dim: int):
        """Measurement covariance inflated by the kernel's IRLS weight at Mahalanobis distance d;
        None = skip (gated, or tukey beyond its threshold)."""
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
        return None  # tukey: weight 0

    def _apply(self, m: _Measurement, Rm: np.ndarray) -> None:
        """filterpy's update of m with covariance Rm (m.R, or inflated), injected."""
        P0 = self.kf.P
        _kf_update(self.kf, m.z, m.H, lambda x: m.hx + m.H @ x, Rm, m.residual)
        self._inject(m, Rm, P0)

    def _trial(self, m: _Measurement) -> tuple[float, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """filterpy's update with the unweighted m.R, not yet injected: (Mahalanobis distance d of
        the innovation y, y, (x, P) before the update, for `_settle`).  d from filterpy's own
        innovation and S^-1 (d^2 = y^T S^-1 y), so S is formed and inverted once per
        measurement; most updates keep this result (d within the robust threshold)."""
        before = (self.kf.x, self.kf.P)  # filterpy's update binds new arrays: these stay as they were
        _kf_update(self.kf, m.z, m.H, lambda x: m.hx + m.H @ x, m.R, m.residual)
        y = np.asarray(self.kf.y, float).ravel()
        return math.sqrt(max(float(y @ self.kf.SI @ y), 0.0)), y, before

    def _undo(self, before: tuple[np.ndarray, np.ndarray]) -> None:
        self.kf.x, self.kf.P = before

    def _settle(self, Rr, m: _Measurement, before) -> None:
        """Keep the trial update when the kernel left m.R as it was; otherwise undo it and update
        with the inflated Rr (or not at all: Rr None)."""
        if Rr is m.R:
            self._inject(m, m.R, before[1])
            return
        self._undo(before)
        if Rr is not None:
            self._apply(m, Rr)

    def _update(self, m: _Measurement) -> None:
        """A velocity update: robust kernel and gate, no recovery logic."""
        d, _, before = self._trial(m)
        self._settle(self._robust_R(d, m.R, len(m.hx)), m, before)

    def _inflate_to(self, y: np.ndarray, H: np.ndarray, Rm: np.ndarray, d_target: float) -> float:
        """Scale P by lam >= 1 so that y^T (lam H P H^T + R)^-1 y = d_target^2 (bisection on
        log lam; the left side decreases with lam); returns lam."""
        HPH = H @ self.kf.P @ H.T
        lo, hi = 0.0, math.log(self.recovery.max_inflation)

        def d2(log_lam):
            return float(y @ np.linalg.solve(math.exp(log_lam) * HPH + Rm, y))

        if d2(hi) > d_target**2:
            lo = hi
        else:
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                if d2(mid) > d_target**2:
                    lo = mid
                else:
                    hi = mid
        lam = math.exp(hi)
        self.kf.P = self.kf.P * lam
        return lam

    def _fix_update(self, m: _Measurement) -> None:
        """A pose fix: robust kernel and gate, with recovery (module docstring)."""
        fix, H, Rm = m.fix, m.H, m.R
        assert fix is not None
        d, y, before = self._trial(m)
        self.nis.append((d * d, len(y)))  # consistency check (variance.nis_component)
        k = self.config.threshold(len(y))
        gate = self.config.outlier_gate
        fix.over = d > k
        fix.gated = gate is not None and d > gate
        rec = self.recovery
        self.window.add(fix)
        if not rec.enabled or not fix.over:
            self._settle(self._robust_R(d, Rm, len(y)), m, before)
            return
        if fix.gated and self.window.all_gated():
            self._undo(before)
            self.rejected += 1
            self.reset(fix)
            return
        if self.window.filter_at_fault():
            self._undo(before)
            self.rejected += 1
            self.inflated += 1
            self._inflate_to(y, H, Rm, math.sqrt(len(y)))
            self._apply(m, Rm)
            return
        self._settle(self._robust_R(d, Rm, len(y)), m, before)

    def reset(self, fix: _Fix) -> None:
        """Re-initialise from the window's fixes: pose and covariance of the last fix, velocity
        from the cubic fit, biases kept with their covariance back to the fault level."""
        _, v = self.window.fit(self.window.recent())
        P = np.zeros((15, 15))
        self.kf.P = P
        if fix.cov.shape == (6, 6):
            self.set_pose(fix.T_meas, fix.cov)
        else:  # position + yaw fix: keep the filter's roll/pitch
            R_b = self.T_world_body()[:3, :3]
            T = np.eye(4)
            T[:3, :3] = rot_z(fix.yaw - float(yaw_of(R_b))) @ R_b
            T[:3, 3] = fix.p_world
            cov = np.diag(np.r_[[_TILT_SIGMA_RAD**2] * 2, fix.sigma_yaw**2, fix.sigma_p**2])
            self.set_pose(T, cov)
        self.v = v - self.R @ cross3(self.omega, self.T_ib[:3, 3])
        rec = self.recovery
        sigma_v = max(rec.reset_velocity_sigma_m_s, self.config.velocity_prior_sigma_m_s)
        self.kf.P[_V, _V] = np.eye(3) * sigma_v**2
        self.kf.P[_BG, _BG] = np.eye(3) * rec.reset_sigma_gyro_rad_s**2
        self.kf.P[_BA, _BA] = np.eye(3) * rec.reset_sigma_accel_m_s2**2
        self.kf.x = np.zeros(15)
        self.resets += 1
        self.window.clear()

    def _nominal(self) -> tuple[np.ndarray, ...]:
        return self.R, self.p, self.v, self.bg, self.ba

    def _retract(self, X0: tuple[np.ndarray, ...], dx: np.ndarray) -> None:
        """Nominal state = X0 [+] dx (rotation on the right, the rest added)."""
        R0, p0, v0, bg0, ba0 = X0
        self.R = R0 @ so3_exp(dx[_TH])
        self.p = p0 + dx[_P]
        self.v = v0 + dx[_V]
        self.bg = bg0 + dx[_BG]
        self.ba = ba0 + dx[_BA]

    def _local(self, X0: tuple[np.ndarray, ...]) -> np.ndarray:
        """The nominal state's error state relative to X0 (the inverse of _retract)."""
        R0, p0, v0, bg0, ba0 = X0
        dv = [self.p - p0, self.v - v0, self.bg - bg0, self.ba - ba0]
        return np.concatenate([so3_log(R0.T @ self.R), *dv])

    def _inject(
        self, m: _Measurement | None = None, Rm: np.ndarray | None = None, P0: np.ndarray | None = None
    ) -> None:
        """The filter's error state into the nominal state; then, when m's update (covariance
        Rm, prior P0) turned the attitude by more than ITERATE_MIN_ROTATION_RAD, `_iterate`."""
        dx = self.kf.x.ravel()
        X0 = self._nominal()
        self._retract(X0, dx)
        self.kf.x = np.zeros(15)
        if m is not None and float(np.linalg.norm(dx[_TH])) > ITERATE_MIN_ROTATION_RAD:
            assert Rm is not None and P0 is not None
            self._iterate(m, Rm, P0, X0)

    def _iterate(self, m: _Measurement, Rm: np.ndarray, P0: np.ndarray, X0: tuple[np.ndarray, ...]) -> None:
        """Iterated EKF update: Gauss-Newton on the update's MAP cost (Bell and Cathey, "The
        iterated Kalman filter update as a Gauss-Newton method", IEEE TAC 38(2), 1993), in the
        error state of the prior X0 (covariance P0).  At iterate X_i = X0 [+] d_i the
        measurement is relinearised (m.relinearize: z_i, H_i, h_i, H_i in X_i's right
        perturbation e); e = Jr(d_i) (d - d_i) (SO(3)'s right Jacobian, gtsam
        Rot3.ExpmapDerivative), so in d: Hd = H_i Jr and y = z_i - (h_i - Hd d_i); d_(i+1) =
        K y.  The posterior covariance is moved to the last iterate's tangent space by Jr(d).
        Why: one linear update is exact to first order in the correction; after a gap without
        an IMU the attitude prior is ~10-20 deg wide, the first fix turns it by as much, and the
        second-order terms left the state off the fix along its thin (correlated) directions
        by 10^2-10^4 sigma^2 (a velocity-only flight's EKF NEES 35,000 on that frame)."""
        self.iterated += 1
        d = self._local(X0)
        for _ in range(ITERATE_MAX):
            z, H, hx = m.relinearize()
            J = _EYE15.copy()
            J[_TH, _TH] = gtsam.Rot3.ExpmapDerivative(d[_TH])
            Hd = H @ J
            h0 = hx - Hd @ d
            self.kf.x = np.zeros(15)
            self.kf.P = P0
            _kf_update(self.kf, z, Hd, lambda x, Hd=Hd, h0=h0: h0 + Hd @ x, Rm, m.residual)
            d_new = self.kf.x.ravel()
            self._retract(X0, d_new)
            step = float(np.max(np.abs(d_new - d)))
            d = d_new
            if step < ITERATE_TOL:
                break
        self.kf.x = np.zeros(15)
        J = _EYE15.copy()
        J[_TH, _TH] = gtsam.Rot3.ExpmapDerivative(d[_TH])
        self.kf.P = J @ self.kf.P @ J.T

    def pose_fix(self, t_s: float, T_meas: np.ndarray, cov: np.ndarray) -> _Measurement:
        """z = Log(T_hat_body^-1 T_meas) (6,), h(dx) = J_body dx (right perturbation)."""

        def linearize():
            T_hat = gtsam.Pose3(self.T_world_body())
            H = np.zeros((6, 15))
            H[:, :6] = self.J_body()
            return gtsam.Pose3.Logmap(T_hat.between(gtsam.Pose3(T_meas))), H, np.zeros(6)

        z, H, hx = linearize()
        R_m = T_meas[:3, :3]
        sigma_p = np.sqrt(np.maximum(np.diag(R_m @ cov[3:, 3:] @ R_m.T), 0.0))
        fix = _Fix(
            t_s,
            T_meas[:3, 3].copy(),
            float(yaw_of(R_m)),
            sigma_p,
            math.sqrt(max(cov[2, 2], 0.0)),
            T_meas,
            cov,
        )
        return _Measurement(z, H, hx, cov, np.subtract, fix, linearize)

    def update_pose(self, t_s: float, T_meas: np.ndarray, cov: np.ndarray) -> None:
        """A 6-dof pose fix (pose_fix)."""
        self._fix_update(self.pose_fix(t_s, T_meas, cov))

    def position_yaw_fix(
        self, t_s: float, T_meas: np.ndarray, Rm: np.ndarray, cov6: np.ndarray | None = None
    ) -> _Measurement:
        """z = [p_world_body (3), yaw (1)] with 4x4 covariance Rm; the residual hook wraps yaw
        to (-pi, pi].  cov6: the level-frame 6x6 covariance it came from (kept for a reset)."""
        z = np.r_[T_meas[:3, 3], yaw_of(T_meas[:3, :3])]

        def linearize():
            T_hat = gtsam.Pose3(self.T_world_body())
            e, Hb = factors.position_yaw_error(np.zeros(3), 0.0, T_hat, True)  # e = h(T_hat)
            H = np.zeros((4, 15))
            H[:, :6] = Hb @ self.J_body()
            return z, H, e

        _, H, e = linearize()
        sd = np.sqrt(np.maximum(np.diag(Rm), 0.0))
        fix = _Fix(
            t_s, z[:3].copy(), float(z[3]), sd[:3], float(sd[3]), T_meas, cov6 if cov6 is not None else Rm
        )
        return _Measurement(z, H, e, Rm, _yaw_residual, fix, linearize)

    def update_position_yaw(
        self, t_s: float, T_meas: np.ndarray, Rm: np.ndarray, cov6: np.ndarray | None = None
    ) -> None:
        """A position + yaw fix (position_yaw_fix)."""
        self._fix_update(self.position_yaw_fix(t_s, T_meas, Rm, cov6))

    def body_velocity(self, v_meas: np.ndarray, sigma: float) -> _Measurement:
        """z = R_world_body^T v_world_body, with v_world_body = v + R (omega x t_imu_body), i.e.
        h = R_imu_body^T (R^T v + omega x t_imu_body).  With R' = R Exp(dtheta),
        R'^T v = R^T v + [R^T v]x dtheta: only the IMU velocity term depends on dtheta (the lever
        arm term is in the IMU frame already)."""
        z = np.asarray(v_meas, float)
        R_ib = self.T_ib[:3, :3]

        def linearize():
            v_b_world = self.v + self.R @ cross3(self.omega, self.T_ib[:3, 3])
            R_bw = R_ib.T @ self.R.T  # R_body_world
            H = np.zeros((3, 15))
            H[:, _TH] = R_ib.T @ skew(self.R.T @ self.v)
            H[:, _V] = R_bw
            return z, H, R_bw @ v_b_world

        _, H, hx = linearize()
        return _Measurement(z, H, hx, _EYE3 * sigma**2, np.subtract, None, linearize)

    def update_body_velocity(self, v_meas: np.ndarray, sigma: float) -> None:
        """A body-velocity update (body_velocity)."""
        self._update(self.body_velocity(v_meas, sigma))

    def update_fix_and_velocity(self, fix: _Measurement, v_meas: np.ndarray, sigma: float) -> None:
        """A fix and a body velocity of the same frame in one filterpy update (z, H, R stacked),
        when neither is beyond its robust threshold; otherwise undone and made one after the
        other (update_pose / update_position_yaw, then update_body_velocity), the order this
        replaces.  The two are independent and linear in the error state, so the stacked update
        is the sequential one (Kalman; e.g. Simon, "Optimal State Estimation", 2006, sec. 7.1)
        but for the velocity's H and h taken before the fix's correction is injected rather than
        after (a second-order difference, ~|dx|^2).  The fix's gate distance is its marginal
        d_f^2 = y_f^T S_ff^-1 y_f (as alone) and the velocity's the conditional one the
        sequential update sees, d_v^2 = y^T S^-1 y - d_f^2 (chain rule of the Gaussian)."""
        vel = self.body_velocity(v_meas, sigma)
        nf = len(fix.hx)
        Rm = np.zeros((nf + 3, nf + 3))
        Rm[:nf, :nf] = fix.R
        Rm[nf:, nf:] = vel.R
        fix_residual = fix.residual

        def residual(a, b):
            r = np.subtract(a, b)
            r[:nf] = fix_residual(a[:nf], b[:nf])
            return r

        def linearize():
            (zf, Hf, hf), (zv, Hv, hv) = fix.relinearize(), vel.relinearize()
            return np.concatenate([zf, zv]), np.concatenate([Hf, Hv]), np.concatenate([hf, hv])

        both = _Measurement(
            np.concatenate([fix.z, vel.z]),
            np.concatenate([fix.H, vel.H]),
            np.concatenate([fix.hx, vel.hx]),
            Rm,
            residual,
            None,
            linearize,
        )
        d, y, before = self._trial(both)
        yf = y[:nf]
        d2_fix = max(float(yf @ np.linalg.solve(self.kf.S[:nf, :nf], yf)), 0.0)
        d_fix, d_vel = math.sqrt(d2_fix), math.sqrt(max(d * d - d2_fix, 0.0))
        if d_fix <= self.config.threshold(nf) and d_vel <= self.config.threshold(3):
            self.nis.append((d2_fix, nf))
            assert fix.fix is not None
            fix.fix.over = fix.fix.gated = False  # d_fix within the threshold, so within the gate
            self.window.add(fix.fix)
            self._inject(both, Rm, before[1])
            return
        self._undo(before)
        self._fix_update(fix)
        self.update_body_velocity(v_meas, sigma)


def _imu_to_body(f: _Ekf, T_out: np.ndarray, cov_out: np.ndarray, block: int = 4096) -> None:
    """In place, for a whole flight at once (in blocks of `block` frames, bounded temporaries):
    T_out (N, 4, 4) holding T_world_imu's rotation and translation becomes T_world_body =
    T_world_imu T_imu_body (_Ekf.T_world_body), and cov_out (N, 6, 6) holding the error state's
    [dtheta, dp] covariance becomes the body frame's, symmetrised (_Ekf.J_body, body_cov)."""
    for a in range(0, len(T_out), block):
        T = T_out[a : a + block]
        C = cov_out[a : a + block]
        J = np.zeros((len(T), 6, 6))
        J[:, :3, :3] = _EYE3
        J[:, 3:, 3:] = T[:, :3, :3].transpose(0, 2, 1)
        J = f.Ad_bi @ J
        C[:] = J @ C @ J.transpose(0, 2, 1)
        C[:] = 0.5 * (C + C.transpose(0, 2, 1))
        T[:, 3, :3] = 0.0
        T[:, 3, 3] = 1.0
        T[:] = T @ f.T_ib


@dataclass
class LevelStart:
    """The EKF's start from a batch solve of its first level fixes (level_batch_start).

    k_end: the window's last frame (a fix), where the filter takes over; T_world_body
    (k_end - k0 + 1, 4, 4) and cov_body (same, 6, 6; Pose3 order, body frame): the batch
    solution and its marginal covariances at frames k0..k_end (the EKF's output there);
    v_world (3,): body velocity at k_end; bias_accel / bias_gyro (3,) IMU frame; joint (15, 15):
    the joint marginal covariance of [X(k_end) (Pose3 tangent), V(k_end), B(k_end) (accel,
    gyro)] in GTSAM's order of those blocks.  With load observations (the incremental
    smoother's start): load_ids (m,) the loads seen in the window, p_loads (m, 3) world, and
    joint_loads (15 + 3m, 15 + 3m) the joint marginal of [X, V, B, L_0 .. L_m-1] (None
    without)."""

    k_end: int
    T_world_body: np.ndarray
    cov_body: np.ndarray
    v_world: np.ndarray
    bias_accel: np.ndarray
    bias_gyro: np.ndarray
    joint: np.ndarray
    load_ids: tuple[str, ...] = ()
    p_loads: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    joint_loads: np.ndarray | None = None


def level_batch_start(
    frame_t: np.ndarray,
    imu: ImuData,
    rawp: RawPoses,
    k0: int,
    velocity: VelocityData | None,
    floor_camera: CameraModel,
    config: FusionConfig,
    *,
    load_obs: list[LoadObservation] | None = None,
    front_camera: CameraModel | None = None,
    failures: list[str] | None = None,
) -> LevelStart | None:
    """Batch-smooth the first `config.ekf_level_start_s` seconds of level fixes (from frame k0,
    the first inlier fix, to the last fix within the window, or to the LEVEL_START_MIN_FIXES-th
    fix if that is later) and return the solution with the joint marginal of the last frame's
    pose, velocity and biases; None when the flight has fewer fixes or the solve fails (its
    error then appended to `failures`: run_ekf's stats['batch_start_failed'], a run's warning).

    Why: level fixes (position + yaw) leave roll / pitch to the accelerometer against the
    fixes' second difference, where they trade with the accelerometer bias.  Started from the
    first fix with tilt 0 +- 10 deg (the truth may roll 13 deg) and a tilt uncorrelated with the
    bias, the filter linearises its first updates far from the truth and gains bias information
    it does not have (b_x sigma 0.1 -> 0.011 m/s^2 in 1.3 s, estimate 26 sigma off: BENCHMARKS.md,
    thirteenth session), the EKF inconsistency of Huang, Mourikis & Roumeliotis (IJRR 29(5),
    2010) on a weakly observable direction.  A batch solve iterates to the nonlinear optimum and
    its marginal keeps the tilt-bias correlation, so the filter starts near the truth with an
    honest joint prior (a filter initialised from the least-squares estimate of its first
    measurements, as tracking filters are; here the nonlinear least-squares solve of the window,
    `smoother.build_problem` / `solve`, and its covariance from GTSAM's Marginals, the inverse of
    the information at the solution).  The window's outputs are smoothed, a start-up look-ahead of
    `ekf_level_start_s` like `first_velocity`'s 0.5 s; from k_end on the filter is causal.
    Velocity samples are given to the window only up to half-way to the next frame, so each is
    used once, at the frame it is used at in the filter (common.velocity_at_frames).
    `load_obs` / `front_camera` (the incremental smoother, whose load variables live in its
    graph): the load sightings before the same cut are in the window's graph too, and the
    joint marginal takes in their loads (LevelStart.load_ids); the EKF maps its loads from its
    output poses afterwards and passes none."""
    window_ns = config.ekf_level_start_s * 1e9
    if rawp.covariances is None:  # the paper's position + yaw: not level-frame PnP poses
        return None
    fix_k = rawp.frame_idx
    after = np.unique(fix_k[fix_k >= k0])  # the fixes' frames from k0 on, in time order
    if len(after) < LEVEL_START_MIN_FIXES:
        return None
    in_time = after[frame_t[after] - frame_t[k0] <= window_ns]
    k_end = int(max(in_time[-1], after[LEVEL_START_MIN_FIXES - 1]))
    in_win = (fix_k >= k0) & (fix_k <= k_end)
    if k_end + 1 >= len(frame_t):
        return None
    t_win = frame_t[k0 : k_end + 1]
    raw = Trajectory("raw", frame_t[fix_k[in_win]], rawp.T_world_body[in_win], rawp.covariances[in_win])
    vel_win = None
    t_cut = (frame_t[k_end] + frame_t[k_end + 1]) / 2
    obs_win = [o for o in load_obs or [] if o.timestamp_ns < t_cut] if front_camera is not None else []
    if velocity is not None:
        keep = velocity.timestamps_ns < t_cut
        if keep.any():
            vel_win = VelocityData(
                velocity.timestamps_ns[keep], velocity.v_body_m_s[keep], velocity.noise_m_s
            )
    try:
        pb = build_problem(
            t_win,
            imu,
            raw,
            obs_win or None,
            front_camera if obs_win else None,
            vel_win,
            config,
            floor_camera=floor_camera,
        )
        graph = pb.graph()
        res, graph, _ = solve(graph, pb.initial, config, SolveHealth())
        values = res.values
        marg = gtsam.Marginals(graph, values)
        n = len(t_win)
        keys = [X(n - 1), V(n - 1), B(n - 1)]
        kv = gtsam.KeyVector()
        for key in keys:
            kv.append(key)
        jm = marg.jointMarginalCovariance(kv)
        dims = (6, 3, 6)
        offs = np.cumsum((0,) + dims)
        joint = np.zeros((15, 15))
        for a, ka in enumerate(keys):
            for b, kb in enumerate(keys):
                joint[offs[a] : offs[a + 1], offs[b] : offs[b + 1]] = jm.at(ka, kb)
        T = np.array([values.atPose3(X(k)).matrix() for k in range(n)])
        cov = np.array([marg.marginalCovariance(X(k)) for k in range(n)])
        joint_loads = None
        if pb.loads:
            all_keys = keys + [L(j) for j in range(len(pb.loads))]
            kv = gtsam.KeyVector()
            for key in all_keys:
                kv.append(key)
            jl = marg.jointMarginalCovariance(kv)
            offs_l = np.cumsum((0,) + dims + (3,) * len(pb.loads))
            joint_loads = np.zeros((offs_l[-1], offs_l[-1]))
            for a, ka in enumerate(all_keys):
                for b, kb in enumerate(all_keys):
                    joint_loads[offs_l[a] : offs_l[a + 1], offs_l[b] : offs_l[b + 1]] = jl.at(ka, kb)
            joint_loads = 0.5 * (joint_loads + joint_loads.T)
        p_loads = np.array([values.atPoint3(L(j)) for j in range(len(pb.loads))]).reshape(-1, 3)
    except (RuntimeError, ValueError, EstimationError) as e:
        log.warning("no batch start from the first level fixes (%s); starting at the first fix", e)
        if failures is not None:
            failures.append(str(e))
        return None
    bias = values.atConstantBias(B(n - 1))
    return LevelStart(
        k_end=k_end,
        T_world_body=T,
        cov_body=0.5 * (cov + cov.transpose(0, 2, 1)),
        v_world=np.asarray(values.atVector(V(n - 1)), float),
        bias_accel=np.asarray(bias.accelerometer(), float),
        bias_gyro=np.asarray(bias.gyroscope(), float),
        joint=0.5 * (joint + joint.T),
        load_ids=tuple(pb.load_ids),
        p_loads=p_loads,
        joint_loads=joint_loads,
    )


def _start_from_batch(f: _Ekf, start: LevelStart, imu: ImuData, t_ns: int) -> None:
    """The filter's nominal state and covariance at frame start.k_end from the batch start.

    Error state from GTSAM's: [dtheta, dp] = J_body^-1 xi_body (_Ekf.J_body: xi_imu = [dtheta,
    R^T dp], xi_body = Ad_bi xi_imu), dv = the body velocity's error (the lever arm's
    omega x t_imu_body term taken at the nominal rate, without its uncertainty: zero when the IMU
    is at the body origin), dbg / dba = the ConstantBias blocks (accelerometer first in GTSAM)."""
    T_wb = start.T_world_body[-1]
    T_wi = T_wb @ f.T_bi
    f.R, f.p = T_wi[:3, :3].copy(), T_wi[:3, 3].copy()
    f.bg, f.ba = start.bias_gyro.copy(), start.bias_accel.copy()
    i = int(np.clip(np.searchsorted(imu.timestamps_ns, t_ns), 0, len(imu.timestamps_ns) - 1))
    f.omega = np.asarray(imu.gyro_rad_s[i], float) - f.bg
    # body_velocity's h inverted: v_world_body = v + R (omega x t_imu_body)
    f.v = start.v_world - f.R @ cross3(f.omega, f.T_ib[:3, 3])
    J = np.zeros((15, 15))
    J[:6, :6] = np.linalg.inv(f.J_body())
    J[_V, 6:9] = _EYE3
    J[_BG, 12:15] = _EYE3
    J[_BA, 9:12] = _EYE3
    P = J @ start.joint @ J.T
    f.kf.x = np.zeros(15)
    f.kf.P = 0.5 * (P + P.T)


def level_fix_covariance(T_level: np.ndarray, cov_level: np.ndarray) -> np.ndarray:
    """4x4 covariance of [p_world (3), yaw] of a level-frame pose T_level = [Rz(yaw), p] whose
    6x6 covariance (Pose3 order, right perturbation T = T_level Exp(xi)) is cov_level: to first
    order yaw = yaw_hat + xi_rz and p = p_hat + Rz xi_t (the level frame's z is world z)."""
    J = np.zeros((4, 6))
    J[:3, 3:] = T_level[:3, :3]
    J[3, 2] = 1.0
    return J @ cov_level @ J.T


def run_ekf(
    frame_times_ns,
    imu: ImuData | None,
    raw: Trajectory,
    load_obs: list[LoadObservation] | None = None,
    *,
    front_camera: CameraModel | None = None,
    floor_camera: CameraModel | None = None,
    velocity: VelocityData | None = None,
    config: FusionConfig | None = None,
    recovery: EkfRecovery | None = None,
) -> FusionResult:
    """Causal error-state EKF over a flight; same inputs and result as `smooth`.

    front_camera: maps load observations to the world (its mount: camera.T_world_cam); None:
    no load map (a warning when there are load observations).  floor_camera: only its mount is
    used; a gimbaled floor camera's raw poses are level-frame poses (pnp.py), fused as position + yaw.
    The filter starts at the first (inlier) raw pose (`stats['frames_before_first_fix']` earlier
    frames have no estimate), with the velocity from a line through the first 0.5 s of raw
    positions (start-up look-ahead, as smooth_incremental).  With level fixes (a gimbaled floor
    camera's PnP poses) and an IMU it starts instead from a batch solve of the fixes within
    `config.ekf_level_start_s` of the first (level_batch_start: the window's frames are that
    solve's, `stats['batch_start_frames']` of them; the filter runs from the window's last fix
    on, its prior the solve's joint marginal of pose, velocity and biases there).  Trajectory at
    the remaining frame times, with the filtered (causal) covariance mapped to the body frame
    (Pose3 order).
    stats: pose_updates, rejected_pose_factors, gated_updates, inflated_updates, resets, ..."""
    config = config or FusionConfig()
    recovery = recovery or EkfRecovery()
    t_start = time.perf_counter()
    inp = prepare_inputs(frame_times_ns, imu, raw, velocity, front_camera, config)
    frame_t, rawp, imu, velocity = inp.frame_t, inp.raw, inp.imu, inp.velocity
    raw_cov = rawp.covariances  # None: paper input (position + yaw), i.e. not rawp.full_pose
    if load_obs and front_camera is None:
        log.warning("%d load observations but no front camera: the EKF maps no loads", len(load_obs))
    level_fixes = floor_camera is not None and floor_camera.gimbaled
    n = len(frame_t)
    use = inlier_raw_mask(rawp, config, frame_t)
    k0 = int(rawp.frame_idx[use].min())
    m0 = int(np.flatnonzero(use & (rawp.frame_idx == k0))[0])
    raw_at = {int(k): m for m, k in enumerate(rawp.frame_idx.tolist())}
    vel = velocity_at_frames(frame_t, velocity, config, imu)
    vmask = vel.mask

    T_bi = np.asarray(imu.T_body_imu, float) if imu is not None else np.eye(4)
    f = _Ekf(T_bi, config, recovery)
    f.kf.x = np.zeros(15)
    f.kf.P = np.zeros((15, 15))
    if raw_cov is not None:
        f.set_pose(rawp.T_world_body[m0], raw_cov[m0])
    else:
        f.set_pose(
            rawp.T_world_body[m0],
            np.diag(
                np.r_[
                    _TILT_SIGMA_RAD**2,
                    _TILT_SIGMA_RAD**2,
                    config.paper_sigma_yaw_rad**2,
                    np.asarray(config.paper_sigma_xyz_m, float) ** 2,
                ]
            ),
        )
    f.v = first_velocity(frame_t, rawp, use, k0)
    f.kf.P[_V, _V] = np.eye(3) * config.velocity_prior_sigma_m_s**2
    f.kf.P[_BG, _BG] = np.eye(3) * config.bias_prior_sigma_gyro_rad_s**2
    f.kf.P[_BA, _BA] = np.eye(3) * config.bias_prior_sigma_accel_m_s2**2
    start = None
    start_failed: list[str] = []  # the batch start's solve error: the run names it
    if level_fixes and imu is not None and config.ekf_level_start_s > 0:
        assert floor_camera is not None  # level_fixes
        start = level_batch_start(
            frame_t, imu, rawp, k0, velocity, floor_camera, config, failures=start_failed
        )
    if start is not None:
        assert imu is not None  # a batch start is made only with an IMU
        _start_from_batch(f, start, imu, frame_t[start.k_end])
    paper_Rm = np.diag(np.r_[np.asarray(config.paper_sigma_xyz_m, float), config.paper_sigma_yaw_rad] ** 2)

    covered = np.zeros(max(n - 1, 0), bool)
    if imu is not None:
        covered = imu_coverage(frame_t, imu, config.max_imu_gap_s)
        k_of, dts, gyr, acc = imu_subintervals(frame_t, imu, covered)
        # sub-intervals of frame interval k: rows first[k]:first[k + 1] (k_of in time order);
        # sliced when reached, not split up front (~3 arrays per frame held for the flight)
        first = np.searchsorted(k_of, np.arange(n))
    noise = imu.noise if imu is not None else None

    T_out = np.empty((n - k0, 4, 4))
    cov_out = np.empty((n - k0, 6, 6))
    n_pose_updates = 0
    k_from = k0 if start is None else start.k_end  # the batch start used the fixes up to k_end
    for k in range(k_from, n):
        if k > k_from:
            if covered[k - 1]:
                rows = slice(first[k - 1], first[k])
                f.predict_imu_block(acc[rows], gyr[rows], dts[rows], noise)
            else:
                f.predict_random_walk((frame_t[k] - frame_t[k - 1]) * 1e-9, noise)
        # frame k_end's fix and velocity are in the batch start already
        has_vel = bool(vmask[k]) and not (start is not None and k == k_from)
        if has_vel:
            # the gravity term of the samples' time shift at the predicted attitude (body)
            v_meas = vel.measured(k, f.R @ f.T_ib[:3, :3])
            sigma_v = float(vel.sigma_m_s[k])
        m = raw_at.get(k) if k > k_from else None
        if m is not None:
            t_s = frame_t[k] * 1e-9
            T_m = rawp.T_world_body[m]
            if raw_cov is not None and not level_fixes:
                fix = f.pose_fix(t_s, T_m, raw_cov[m])
            elif raw_cov is not None:
                fix = f.position_yaw_fix(t_s, T_m, level_fix_covariance(T_m, raw_cov[m]), raw_cov[m])
            else:
                fix = f.position_yaw_fix(t_s, T_m, paper_Rm)
            if has_vel:
                f.update_fix_and_velocity(fix, v_meas, sigma_v)
            else:
                f._fix_update(fix)
            n_pose_updates += 1
        elif has_vel:
            f.update_body_velocity(v_meas, sigma_v)
        # the IMU pose and its error covariance now; mapped to the body after the loop, in one go
        T_out[k - k0, :3, :3] = f.R
        T_out[k - k0, :3, 3] = f.p
        cov_out[k - k0] = f.kf.P[:6, :6]
    # the filter's frames (from k_from) to the body; the window's before them are the batch
    # solution's, in the body frame already (k_end's is the filter's start)
    _imu_to_body(f, T_out[k_from - k0 :], cov_out[k_from - k0 :])
    if start is not None:
        T_out[: start.k_end - k0] = start.T_world_body[:-1]
        cov_out[: start.k_end - k0] = start.cov_body[:-1]

    loads = _map_loads(
        frame_t, load_obs if front_camera is not None else None, front_camera, T_out, cov_out, k0, config
    )
    stats: dict[str, Any] = {
        "frames_before_first_fix": k0,
        "batch_start_frames": 0 if start is None else start.k_end - k0 + 1,
        "pose_updates": n_pose_updates,
        "rejected_pose_factors": f.rejected,
        "gated_updates": f.gated,
        "inflated_updates": f.inflated,
        "resets": f.resets,
        "iterated_updates": f.iterated,
        "pose_nis": nis_component([a for a, _ in f.nis], [b for _, b in f.nis]).as_dict(),
        "robust_kernel": config.robust_kernel,
        "imu_intervals": int(covered.sum()),
        "bridged_intervals": int((~covered).sum()),
        "time_s": time.perf_counter() - t_start,
    }
    if start_failed:
        stats["batch_start_failed"] = start_failed[0]
    if imu is not None:
        t0, t1 = imu.timestamps_ns[0], imu.timestamps_ns[-1]
        stats["frames_outside_imu"] = int(((frame_t < t0) | (frame_t > t1)).sum())
    duration = (frame_t[-1] - frame_t[k0]) * 1e-9
    stats["realtime_factor"] = duration / max(stats["time_s"], 1e-9)
    return FusionResult(Trajectory("ekf", frame_t[k0:].copy(), T_out, cov_out), loads, stats)


def load_point_world(camera: CameraModel, T_world_body: np.ndarray, p_cam: np.ndarray):
    """World point of a camera-frame point through the camera's mount, and its 3x6 Jacobian
    with respect to the body pose (right perturbation, Pose3 order): load_points_world of one."""
    pts, J, _ = load_points_world(
        camera, np.asarray(T_world_body, float)[None], np.asarray(p_cam, float)[None]
    )
    return pts[0], J[0]


def load_points_world(camera: CameraModel, T_world_body: np.ndarray, p_cam: np.ndarray):
    """World points (M, 3) of camera-frame points p_cam (M, 3) seen from body poses
    T_world_body (M, 4, 4) through the camera's mount, their (M, 3, 6) Jacobians with respect to
    the body pose (right perturbation, Pose3 order) by central differences (step
    _LOAD_JACOBIAN_STEP), so body-fixed and gimbaled mounts take the same path, and the camera
    rotations R_world_cam (M, 3, 3).  The 12 perturbed poses T Exp(+-h e_i) of each
    (Pose3.retract, whose chart is Expmap) go through the mount with it as one stack."""
    m = len(T_world_body)
    poses = np.concatenate([T_world_body[:, None], T_world_body[:, None] @ _LOAD_PERTURBATIONS[None]], axis=1)
    T_wc = camera.T_world_cam(poses.reshape(-1, 4, 4)).reshape(m, 13, 4, 4)
    pts = np.einsum("mkij,mj->mki", T_wc[:, :, :3, :3], p_cam) + T_wc[:, :, :3, 3]
    J = (pts[:, 1:7] - pts[:, 7:]).transpose(0, 2, 1) / (2 * _LOAD_JACOBIAN_STEP)
    return pts[:, 0], J, T_wc[:, 0, :3, :3]


def _perturbations(h: float) -> np.ndarray:
    """(12, 4, 4): Exp(+h e_i) for i = 0..5, then Exp(-h e_i) (Pose3 tangent order)."""
    return np.array([se3_exp(s * h * e) for s in (1.0, -1.0) for e in _EYE6])


_EYE6 = np.eye(6)
_LOAD_PERTURBATIONS = _perturbations(_LOAD_JACOBIAN_STEP)


def _map_loads(frame_t, load_obs, camera, T_out, cov_out, k0, config, block: int = 512) -> LoadMap:
    """Information-weighted fusion of per-observation world points (see module docstring).
    Every sighting's point, Jacobian (load_point_world) and covariance is made for the flight's
    sightings at once, in blocks of `block` (the 13 poses of each through the mount)."""
    # each sighting from the body pose at its own stamp (frames from k0 on have poses)
    load_obs = retime_load_obs(frame_t[k0 : k0 + len(T_out)], T_out, load_obs or [], camera)
    groups, _ = group_load_obs(frame_t, load_obs, config)
    ids = sorted(groups)
    rows = [(i, k - k0, o) for i, lid in enumerate(ids) for k, o in groups[lid] if k >= k0]
    info = np.zeros((len(ids), 3, 3))
    vec = np.zeros((len(ids), 3))
    nobs = np.zeros(len(ids), int)
    for a in range(0, len(rows), block):
        part = rows[a : a + block]
        which = np.array([r[0] for r in part])
        ks = np.array([r[1] for r in part])
        p_cam = np.array([r[2].p_cam for r in part], float)
        cov_cam = np.array([r[2].cov_cam for r in part], float)
        pts, J, R_wc = load_points_world(camera, T_out[ks], p_cam)
        C = R_wc @ cov_cam @ R_wc.transpose(0, 2, 1) + J @ cov_out[ks] @ J.transpose(0, 2, 1)
        W = np.linalg.inv(C)
        np.add.at(info, which, W)
        np.add.at(vec, which, (W @ pts[:, :, None])[:, :, 0])
        np.add.at(nobs, which, 1)
    out = []
    for i, lid in enumerate(ids):
        if nobs[i]:
            cov = np.linalg.inv(info[i])
            out.append(LoadEstimate(lid, cov @ vec[i], cov, int(nobs[i])))
    return LoadMap("ekf", out)
