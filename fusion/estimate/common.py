"""Shared pieces of the fusion back end: configuration, result type, input checks, initial values.

Frames and layouts as in fusion.types: poses are T_world_body (4x4), pose covariances are 6x6 in
GTSAM's Pose3 tangent order [rx, ry, rz, tx, ty, tz] in the body frame (right perturbation
T = T_hat * Exp(xi)); positions in m, angles in rad, timestamps in int64 ns.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from fusion.camera import CameraModel
from fusion.conventions import GRAVITY_M_S2
from fusion.errors import EstimationError
from fusion.fileio import atomic_open
from fusion.geometry import interpolate_poses, inv_T
from fusion.log.euroc import ImuData, VelocityData
from fusion.types import Choice, LoadMap, LoadObservation, RobustKernel, Trajectory


class RawPoseInput(Choice):
    """What the raw per-frame poses constrain (chosen once per flight in build_problem)."""

    POSE6 = "pose6"  # full 6-dof pose with covariance (PnP, body-fixed camera)
    POSITION_YAW = "position_yaw"  # the paper's output: position + yaw, configured sigmas
    LEVEL_POSE = "level_pose"  # gimbaled floor camera: yaw + position, PnP covariance


class TightCoupling(Choice):
    """Whether floor-code corners entered the graph as reprojection factors (config.tight)."""

    OFF = "off"  # not asked for
    ON = "on"
    NO_SIGHTINGS = "no_sightings"  # asked for, but no floor sightings / floor camera given


class SolveMode(Choice):
    """How much the fixes constrain the estimate, and by what."""

    FUSED = "fused"  # fixes and motion model
    DEAD_RECKONED = "dead_reckoned"  # at most config.dead_reckoning_max_fixes fixes: IMU /
    #                                  velocity integration from them, sigma grows accordingly
    IMU_REJECTED = "imu_rejected"  # most fixes disagreed with the IMU beyond the gate: fused
    #                                  without it (random-walk model, velocity if any)


@dataclass
class SolveHealth:
    """What happened inside a back end, beyond its numbers (FusionResult.health).

    `iteration_limit_hits`: solves that stopped at config.lm_max_iterations (or, incremental,
    never); `lm_stalls`: LM could not lower the error with any damping; `linear_fallbacks`: a
    linear solve that failed (IndeterminantLinearSystem, an empty elimination) and was retried
    with weak priors on every state (`weak_prior_states` of them); `gate_skipped`: the outlier
    gate would have removed more than config.max_gated_fraction of the fixes, so it was not
    applied (the motion model, not the fixes, is suspect); `loads_dropped`: load ids whose every
    sighting was gated; `resets`: incremental re-initialisations from agreeing fixes."""

    mode: SolveMode = SolveMode.FUSED
    reasons: list[str] = field(default_factory=list)
    fixes: int = 0
    frames_far_from_fix: int = 0
    iteration_limit_hits: int = 0
    lm_stalls: int = 0
    linear_fallbacks: int = 0
    weak_prior_states: int = 0
    gate_skipped: int = 0
    loads_dropped: list[str] = field(default_factory=list)
    resets: int = 0

    def note(self, reason: str) -> None:
        if reason not in self.reasons:
            self.reasons.append(reason)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["mode"] = str(self.mode)
        return d


@functools.lru_cache(maxsize=256)
def chi2_threshold(quantile: float, dim: int) -> float:
    """sqrt of the chi-square `quantile` with `dim` dof (Mahalanobis units), cached: the EKF and
    the smoothers ask for it per fix, and scipy's ppf costs ~0.7 ms a call."""
    return float(math.sqrt(chi2.ppf(quantile, dim)))


@dataclass
class FusionConfig:
    """Settings shared by the smoother, the incremental smoother and the EKF: every tuning number
    of the back end lives here.

    Robust kernel (QR pose factors and load factors): `robust_kernel` (RobustKernel; a plain
    string is parsed), applied to the Mahalanobis norm of the whole residual (GTSAM's Robust
    noise model); `robust_threshold` in those units (None: sqrt of the chi-square
    `robust_quantile` quantile for the factor's dimension, 4.79 for a 6-dof pose, 4.30 for
    position + yaw, 3.72 for a 3-d point), also the threshold at which a factor is counted as
    rejected in `stats`.
    `outlier_gate`: after the robust solve, QR pose / load factors whose Mahalanobis distance
    still exceeds this are removed and the graph solved again (the EKF skips such updates);
    Huber's bounded but non-zero pull of a misread code 1-3 m away otherwise still bends the
    trajectory by ~0.1 mm per outlier.  None disables it.
    """

    robust_kernel: RobustKernel = RobustKernel.HUBER
    robust_threshold: float | None = None
    robust_quantile: float = 0.999
    outlier_gate: float | None = 25.0
    # The gate is not applied when it would remove more than this share of the fixes: then the
    # motion model (IMU units, clock) rather than the fixes is wrong, and removing the fixes
    # would leave the trajectory unanchored.
    max_gated_fraction: float = 0.5
    # ... and then the batch smoother solves again without the IMU (SolveMode.IMU_REJECTED)
    reject_disagreeing_imu: bool = True
    # Raw trajectories without covariance (the paper's estimator: position + yaw only).
    paper_sigma_xyz_m: tuple[float, float, float] = (0.02, 0.02, 0.02)
    paper_sigma_yaw_rad: float = math.radians(1.0)
    # Priors on the first state.
    bias_prior_sigma_gyro_rad_s: float = 1e-2
    bias_prior_sigma_accel_m_s2: float = 0.1
    velocity_prior_sigma_m_s: float = 0.1
    # ... and when fewer than two fixes give the first velocity: a drone's speed
    unknown_velocity_sigma_m_s: float = 2.0
    # Incremental start from position + yaw fixes: roll / pitch prior (the IMU pins them next)
    initial_roll_pitch_sigma_rad: float = math.radians(10.0)
    # EKF and incremental smoother with level fixes (a gimbaled floor camera) and an IMU: started
    # from a batch solve of the fixes within this many seconds of the first one, its joint
    # marginal of pose, velocity and biases as the prior (ekf.level_batch_start,
    # smoother.level_start); 0 starts both at the first fix
    ekf_level_start_s: float = 1.5
    # First velocity: least-squares line through up to `first_velocity_fixes` inlier raw
    # positions within `first_velocity_window_s` of the first fix.
    first_velocity_fixes: int = 10
    first_velocity_window_s: float = 0.5
    # IMU coverage: a sample holds until the next one if that comes within `max_imu_gap_s`.
    max_imu_gap_s: float = 0.05
    integration_sigma: float = 1e-4  # GTSAM integration covariance (sigma^2 * I)
    # Each sub-interval's specific force turned by half its own rotation before GTSAM integrates
    # it (smoother.midpoint_specific_force); off: as logged.  On in every back end: with noise-
    # free 200 Hz samples between 30 fps frames the plain rule's velocity error is 38-127 um/s a
    # frame, systematic with the rotation, the midpoint rule's 0.1-0.9 (BENCHMARKS.md, thirtieth
    # session: pose NEES of the sweep and held-out flights nearer the band's centre)
    imu_midpoint_attitude: bool = True
    # Weak random-walk model used where there is no IMU (gaps, no-IMU flights): white
    # acceleration `bridge_accel_sigma_m_s2` (m/s^2/sqrt(Hz)), white angular rate
    # `bridge_rate_sigma_rad_s` (rad/s/sqrt(Hz)); the bridge's pose link leaves the
    # translation free (`bridge_free_sigma_m`: the position-velocity factor constrains it), and
    # its sigmas are floored at `bridge_min_sigma` (a zero-length interval).
    bridge_accel_sigma_m_s2: float = 2.0
    bridge_rate_sigma_rad_s: float = 0.5
    bridge_free_sigma_m: float = 1e3
    bridge_min_dt_s: float = 1e-6
    bridge_min_sigma: float = 1e-9
    # A velocity sample is a measurement at its nearest frame when within half this distance
    # of it (velocity_at_frames).
    velocity_max_gap_s: float = 0.1
    # Frame-time matching of raw poses and load observations.
    max_sync_s: float = 0.002
    # Initial values: a raw position farther than this from the median of its neighbours
    # (+- `init_window` raw poses) is not used for the initial guess (it still gets a factor).
    init_outlier_m: float = 0.3
    init_window: int = 15
    # Batch Levenberg-Marquardt (GTSAM's defaults: lambda0 1e-5, factor 10, relativeErrorTol
    # 1e-5); a step is given up (an LM stall) once lambda exceeds `lm_lambda_max`, unless the
    # error is already below `lm_absolute_error_tol` (GTSAM's absoluteErrorTol, 1e-5): there a
    # step that does not lower it meets rounding, not a misfit (an exactly determined solve, e.g.
    # one fix dead-reckoned, reaches ~1e-20), and the solve has converged.
    lm_max_iterations: int = 100
    lm_relative_tol: float = 1e-5
    lm_absolute_error_tol: float = 1e-5
    lm_lambda0: float = 1e-5
    lm_lambda_factor: float = 10.0
    lm_lambda_max: float = 1e10
    compute_covariances: bool = True
    # A failed linear solve (unconstrained variable) is retried with weak priors on every
    # state at its current value: rotation, position, velocity, bias sigmas.
    fallback_sigma_rot_rad: float = math.pi
    fallback_sigma_pos_m: float = 1e3
    fallback_sigma_vel_m_s: float = 1e2
    fallback_sigma_bias: float = 1e2
    # Dead reckoning: with at most `dead_reckoning_max_fixes` fixes the result is labelled
    # dead-reckoned (SolveMode); frames more than `far_from_fix_s` from every fix are counted.
    dead_reckoning_max_fixes: int = 1
    far_from_fix_s: float = 1.0
    # Tight coupling (smooth / smooth_incremental with floor_frames + floor_camera): floor-code
    # corners as reprojection factors instead of the per-frame QR pose; a detection without its
    # own corner_sigma_px / corner_cov_px2 uses `corner_sigma_px` (px, per coordinate).  A
    # corner behind the camera at the current estimate gives `corner_behind_residual`
    # (whitened) with zero Jacobian.
    tight: bool = False
    corner_sigma_px: float = 0.15
    # Noise scales estimated from the residuals (fusion.estimate.variance): the batch smoother
    # re-solves up to `noise_scale_iterations` times with each measurement group's covariance
    # times its chi2/dof (0: report only); `corner_noise_scale` multiplies the tight corner
    # factors' covariance (set by that estimation).
    noise_scale_iterations: int = 2
    corner_noise_scale: float = 1.0
    # multiplies the velocity sensor's stated variance (noise_m_s^2; set by that estimation when
    # the velocity factors' chi2/dof is above variance.IMU_WARN_BAND)
    velocity_noise_scale: float = 1.0
    # the least variance factor the estimation may give the per-frame pose group (0: none): 1
    # when the poses' errors are correlated in time (fusion.estimate.correlation), which makes
    # the smoother's residuals smaller than the errors' variance (it follows their slow part)
    pose_scale_floor: float = 0.0
    # measure each group's chi2/dof at all (False: neither scaled nor checked; the time-offset
    # profile's many solves, whose shifted frames misfit on purpose)
    check_noise: bool = True
    # the marginal covariances at the scales this solve's chi2/dof give its groups
    # (variance.first_solve_scales), from this solve's linearisation with each group's rows
    # reweighted, instead of at the scales it was solved with (the batch smoother's first of two
    # solves on time-correlated poses: correlation.solve_inflated_twice)
    covariances_at_first_scales: bool = False
    corner_behind_residual: float = 1e3
    # Incremental mode: iSAM2 inside gtsam's IncrementalFixedLagSmoother; states older than
    # `incremental_lag_s` are marginalised (loads too, re-created when seen again); None = plain
    # iSAM2 over the whole flight (its cost grows with the flight).
    isam_relinearize_threshold: float = 0.01
    isam_relinearize_skip: int = 10
    incremental_lag_s: float | None = 0.5
    # Incremental re-initialisation: after `reinit_rejected_fixes` consecutive fixes beyond the
    # kernel threshold whose offsets from the estimate agree (spread <= `reinit_agreement_m`,
    # `reinit_agreement_rad`), the smoother restarts from the latest fix, its velocity and bias
    # estimates carried over as priors (velocity sigma `reinit_velocity_sigma_m_s`).
    # Consecutive fixes beyond the outlier gate (the kernel threshold without a gate) count.
    # The restart's priors: attitude `reinit_sigma_rot_rad` and position `reinit_sigma_pos_m`
    # at the re-initialised pose, velocity `reinit_velocity_sigma_m_s`.
    reinit_rejected_fixes: int = 10
    reinit_velocity_sigma_m_s: float = 0.5
    reinit_sigma_rot_rad: float = 0.05
    reinit_sigma_pos_m: float = 1.0
    reinit_agreement_m: float = 0.05
    reinit_agreement_rad: float = math.radians(2.0)
    # ... unless two consecutive fixes of the last `reinit_lookback_s` are further apart than
    # `reinit_max_speed_m_s` allows (a warehouse drone's top speed with margin; as the EKF's
    # EkfRecovery): the fixes jumped, not the estimate (a misprinted code read while crossing
    # it), so the streak is theirs to explain.  A lock-out after a blackout has no such jump.
    reinit_lookback_s: float = 3.0
    reinit_max_speed_m_s: float = 5.0

    def __post_init__(self):
        try:
            self.robust_kernel = RobustKernel.parse(self.robust_kernel, "robust kernel")
        except ValueError:
            raise EstimationError(
                f"unknown robust kernel {self.robust_kernel!r}; "
                f"choose one of {', '.join(k.value for k in RobustKernel)}"
            ) from None
        if self.outlier_gate is not None and not self.outlier_gate > 0:
            raise EstimationError(f"outlier_gate must be > 0, got {self.outlier_gate}")
        if self.robust_threshold is not None and not self.robust_threshold > 0:
            raise EstimationError(f"robust_threshold must be > 0, got {self.robust_threshold}")
        if not 0 < self.max_gated_fraction <= 1:
            raise EstimationError(f"max_gated_fraction must be in (0, 1], got {self.max_gated_fraction}")

    def threshold(self, dim: int) -> float:
        """Robust-kernel threshold (Mahalanobis units) for a factor of dimension `dim`."""
        if self.robust_threshold is not None:
            return float(self.robust_threshold)
        return chi2_threshold(self.robust_quantile, dim)


@dataclass
class FusionResult:
    """Output of every fusion back end: trajectory at frame times with (N, 6, 6) covariances,
    load map with 3x3 covariances, statistics (counts and times, JSON-ready) and what happened
    inside (`health`)."""

    trajectory: Trajectory
    loads: LoadMap
    stats: dict = field(default_factory=dict)
    health: SolveHealth = field(default_factory=SolveHealth)
    floor_codes: Any = None  # fusion.estimate.asbuilt.FloorCodeMap (batch smoother, as-built)
    # as built, the per-frame fixes on the estimated codes (asbuilt.as_built_fixes): what the
    # health monitor judges the smoother against, instead of PnP on the nominal codes
    code_fixes: Trajectory | None = None


# =========================================================================== input checks


def check_timestamps(t_ns: np.ndarray, what: str) -> np.ndarray:
    """int64 copy of strictly increasing timestamps; EstimationError naming the first bad index."""
    t = np.asarray(t_ns)
    if t.ndim != 1:
        raise EstimationError(f"{what}: timestamps must be 1-D, got shape {t.shape}")
    if t.dtype.kind == "f":
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise EstimationError(f"{what}: timestamp {bad[0]} is NaN or infinite")
    t = t.astype(np.int64)
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "duplicated" if d[bad[0]] == 0 else "out of order"
        raise EstimationError(f"{what}: sample {i} is {kind} (t={t[i]} ns after {t[i - 1]} ns)")
    return t


def check_finite(a: np.ndarray, what: str) -> None:
    """EstimationError naming the first sample (row) index holding a NaN or infinity."""
    a = np.asarray(a, dtype=float)
    bad = ~np.isfinite(a.reshape(len(a), -1)).all(axis=1) if len(a) else np.zeros(0, bool)
    idx = np.flatnonzero(bad)
    if idx.size:
        raise EstimationError(f"{what}: sample {int(idx[0])} contains NaN or infinity")


def check_imu(imu: ImuData) -> ImuData:
    t = check_timestamps(imu.timestamps_ns, "IMU")
    g, a = np.asarray(imu.gyro_rad_s, float), np.asarray(imu.accel_m_s2, float)
    if g.shape != (len(t), 3) or a.shape != (len(t), 3):
        raise EstimationError(f"IMU: gyro {g.shape} / accel {a.shape} do not match {len(t)} timestamps")
    check_finite(g, "IMU gyro")
    check_finite(a, "IMU accel")
    T = np.asarray(imu.T_body_imu, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise EstimationError("IMU: T_body_imu must be a finite 4x4 transform")
    return ImuData(t, g, a, imu.noise, T, imu.rate_hz)


def check_velocity(vel: VelocityData) -> VelocityData:
    t = check_timestamps(vel.timestamps_ns, "velocity")
    v = np.asarray(vel.v_body_m_s, float)
    if v.shape != (len(t), 3):
        raise EstimationError(f"velocity: shape {v.shape} does not match {len(t)} timestamps")
    check_finite(v, "velocity")
    if not vel.noise_m_s > 0:
        raise EstimationError(f"velocity: noise_m_s must be > 0, got {vel.noise_m_s}")
    return VelocityData(t, v, float(vel.noise_m_s))


def nearest_frames(frame_t: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Index of the nearest of the sorted stamps `frame_t` (non-empty) for each timestamp `t`
    (the earlier one on a tie)."""
    t = np.asarray(t, dtype=np.int64)
    if len(frame_t) == 1:
        return np.zeros(len(t), dtype=np.int64)
    j = np.clip(np.searchsorted(frame_t, t), 1, len(frame_t) - 1)
    left = j - 1
    return np.where(np.abs(t - frame_t[left]) <= np.abs(frame_t[j] - t), left, j)


def match_to_frames(frame_t: np.ndarray, t: np.ndarray, max_sync_s: float) -> np.ndarray:
    """Index of the nearest frame for each timestamp, -1 where none lies within max_sync_s."""
    t = np.asarray(t, dtype=np.int64)
    if len(frame_t) == 0 or len(t) == 0:
        return np.full(len(t), -1, dtype=np.int64)
    j = nearest_frames(frame_t, t)
    ok = np.abs(frame_t[j] - t) <= int(max_sync_s * 1e9)
    return np.where(ok, j, -1)


@dataclass
class RawPoses:
    """Raw per-frame poses matched to frame indices."""

    frame_idx: np.ndarray  # (M,) index into frame times
    T_world_body: np.ndarray  # (M, 4, 4)
    covariances: np.ndarray | None  # (M, 6, 6) or None (paper input: position + yaw)

    @property
    def full_pose(self) -> bool:
        return self.covariances is not None


def prepare_raw(frame_t: np.ndarray, raw: Trajectory, config: FusionConfig) -> RawPoses:
    """Check the raw trajectory and match it to frames.  No pose at all -> EstimationError."""
    if raw is None or len(raw) == 0:
        raise EstimationError("no floor code was read in this flight")
    t = check_timestamps(raw.timestamps_ns, f"raw trajectory {raw.name!r}")
    T = np.asarray(raw.T_world_body, float)
    if T.shape != (len(t), 4, 4):
        raise EstimationError(f"raw trajectory {raw.name!r}: T_world_body has shape {T.shape}")
    check_finite(T, f"raw trajectory {raw.name!r}")
    cov = None
    if raw.covariances is not None:
        cov = np.asarray(raw.covariances, float)
        if cov.shape != (len(t), 6, 6):
            raise EstimationError(f"raw trajectory {raw.name!r}: covariances have shape {cov.shape}")
        check_finite(cov, f"raw trajectory {raw.name!r} covariances")
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
        ev_min = np.linalg.eigvalsh(cov)[:, 0]
        bad = np.flatnonzero(ev_min <= 0)
        if bad.size:
            raise EstimationError(
                f"raw trajectory {raw.name!r}: covariance {int(bad[0])} is not positive definite"
            )
    idx = match_to_frames(frame_t, t, config.max_sync_s)
    bad = np.flatnonzero(idx < 0)
    if bad.size:
        raise EstimationError(
            f"raw trajectory {raw.name!r}: pose {int(bad[0])} (t={t[bad[0]]} ns) "
            "is at no floor-camera frame time"
        )
    return RawPoses(idx, T, cov)


@dataclass
class FrameVelocities:
    """The velocity sensor's samples as one measurement per frame (velocity_at_frames): `mask`
    (N,) frames with one, `v_body` (N, 3) the mean of the frame's samples carried to the frame's
    time by the IMU but for gravity's part, `dt_s` (N,) the mean time from the frame to those
    samples (0 for a sample taken as it is, without an IMU over the interval), `sigma_m_s`
    (N,) the mean's noise per axis (the sensor's / sqrt(samples))."""

    mask: np.ndarray
    v_body: np.ndarray
    dt_s: np.ndarray
    sigma_m_s: np.ndarray

    def measured(self, k: int, R_world_body: np.ndarray) -> np.ndarray:
        """Frame k's body velocity measurement: v_body[k] less R^T g dt (the velocity gravity
        adds between the frame and its samples, g = (0, 0, -GRAVITY_M_S2); R the body attitude,
        the current estimate's: a 1 mrad error moves it by dt x 9.8 mm/s, ~0.2 mm/s at 30 fps)."""
        g_dt = np.array([0.0, 0.0, -GRAVITY_M_S2 * float(self.dt_s[k])])
        return self.v_body[k] - np.asarray(R_world_body, float).T @ g_dt


def velocity_at_frames(
    frame_t: np.ndarray, vel: VelocityData | None, config: FusionConfig, imu: ImuData | None = None
) -> FrameVelocities:
    """The velocity samples as measurements at the frames, each sample used once: at its
    nearest frame k when within half `config.velocity_max_gap_s` of it, the samples of one frame
    averaged.  A sample m = R_j^T v_j at t_j is carried to the frame's time t_k by the IMU
    between the two (Delta t = t_j - t_k, at most half a frame interval when the rates match):
    R_j = R_k dR and v_j = v_k + R_k dv + g Delta t, so R_k^T v_k = dR m - dv - R_k^T g Delta t,
    with dR = Exp(w Delta t) and dv = Exp(w Delta t / 2) f Delta t from the IMU's rate w and
    specific force f at the interval's midpoint (the midpoint rule; the lever arm's share of f
    and the biases over < 20 ms are left out: ~3 mm/s at 2 rad/s and a 5 cm arm).  The gravity
    term needs the attitude: FrameVelocities.measured adds it with the estimator's.  Without
    an IMU over the interval the sample is taken at the frame's time as it is.

    Why not the samples interpolated to every frame: the interpolated value's noise falls from
    the sensor's to half its variance between two samples while the factor keeps the sensor's
    sigma, and one sample is used by up to two frames (three or more from a slower sensor);
    the smoother's cost then has a cusp wherever frames and samples share stamps, which pulled
    the floor camera's time-offset profile ~1-5 ms off (BENCHMARKS.md, twelfth session)."""
    n = len(frame_t)
    none = FrameVelocities(np.zeros(n, bool), np.zeros((n, 3)), np.zeros(n), np.zeros(n))
    if vel is None or len(vel.timestamps_ns) == 0 or n == 0:
        return none
    tv = np.asarray(vel.timestamps_ns, np.int64)
    k = nearest_frames(np.asarray(frame_t, np.int64), tv)
    dt_ns = tv - np.asarray(frame_t, np.int64)[k]
    use = np.abs(dt_ns) <= int(0.5 * config.velocity_max_gap_s * 1e9)
    if not use.any():
        return none
    k, dt_ns, m = k[use], dt_ns[use], np.asarray(vel.v_body_m_s, float)[use]
    dt = dt_ns * 1e-9
    v = m.copy()
    carried = np.zeros(len(k), bool)  # moved by the IMU: their gravity term is measured()'s
    if imu is not None and len(imu.timestamps_ns) >= 2:
        t_imu = np.asarray(imu.timestamps_ns, np.int64)
        t_a = np.minimum(tv[use], tv[use] - dt_ns)
        t_b = np.maximum(tv[use], tv[use] - dt_ns)
        inside = (dt_ns != 0) & (t_a >= t_imu[0]) & (t_b <= t_imu[-1])
        if inside.any():
            mid = (0.5 * (t_a[inside] + t_b[inside]) - t_imu[0]).astype(float)
            rel = (t_imu - t_imu[0]).astype(float)
            R_bi = np.asarray(imu.T_body_imu, float)[:3, :3]
            w = np.stack([np.interp(mid, rel, imu.gyro_rad_s[:, a]) for a in range(3)], axis=1) @ R_bi.T
            f = np.stack([np.interp(mid, rel, imu.accel_m_s2[:, a]) for a in range(3)], axis=1) @ R_bi.T
            d = dt[inside][:, None]
            dR = Rotation.from_rotvec(w * d)
            dv = Rotation.from_rotvec(0.5 * w * d).apply(f) * d
            v[inside] = dR.apply(m[inside]) - dv
            carried = inside
    counts = np.bincount(k, minlength=n).astype(float)
    mask = counts > 0
    safe = np.maximum(counts, 1.0)
    sums = np.stack([np.bincount(k, weights=v[:, a], minlength=n) for a in range(3)], axis=1)
    v_body = sums / safe[:, None]
    dt_mean = np.bincount(k, weights=np.where(carried, dt, 0.0), minlength=n) / safe
    sigma = np.where(mask, float(vel.noise_m_s) * math.sqrt(config.velocity_noise_scale) / np.sqrt(safe), 0.0)
    return FrameVelocities(mask, v_body, dt_mean, sigma)


# =========================================================================== initial values


INLIER_WINDOW_S = 0.25
"""Half-width (s) of the time window of inlier_raw_mask: short enough that the median of a
one-sided window (at the edge of a gap) lags a 1.3 m/s drone by 0.16 m < init_outlier_m."""
INLIER_BLOCK = 1024
"""Raw poses judged at once by inlier_raw_mask: its (block, 2 init_window + 1, 3) neighbour
arrays and nanmedian's copies stay ~4 MB instead of growing with the flight (~7 MB per flight
minute at 30 fps, judged whole)."""


def inlier_raw_mask(raw: RawPoses, config: FusionConfig, frame_t: np.ndarray | None = None) -> np.ndarray:
    """Raw poses whose position lies within init_outlier_m of the median position of its
    neighbours in time: the raw poses within +-INLIER_WINDOW_S of it (at most init_window on
    each side, nearest first), itself included.  Without frame_t (frame times, ns) the window is
    +-init_window frames (regular frames assumed).  Neighbours are taken in time, not by index,
    so the valid poses on either side of a blackout are not compared with each other.  A pose
    with fewer than two neighbours in its window cannot be judged and is kept."""
    p = raw.T_world_body[:, :3, 3]
    m = len(p)
    w = int(config.init_window)
    if m == 0:
        return np.zeros(0, bool)
    if frame_t is not None:
        t = np.asarray(frame_t, dtype=np.int64)[raw.frame_idx]
        half = int(round(INLIER_WINDOW_S * 1e9))
    else:
        t = np.asarray(raw.frame_idx, dtype=np.int64)
        half = w
    offs = np.arange(-w, w + 1)
    ok = np.empty(m, bool)
    for a in range(0, m, INLIER_BLOCK):  # rows are independent: blocks bound the memory
        rows = np.arange(a, min(a + INLIER_BLOCK, m))
        nb = rows[:, None] + offs[None, :]  # (b, 2w+1) neighbour indices
        valid = (nb >= 0) & (nb < m)
        nbc = np.clip(nb, 0, m - 1)
        valid &= np.abs(t[nbc] - t[rows, None]) <= half
        P = np.where(valid[:, :, None], p[nbc], np.nan)  # (b, 2w+1, 3)
        med = np.nanmedian(P, axis=1)
        judged = valid.sum(axis=1) >= 3  # itself and two neighbours
        ok[rows] = ~judged | (np.linalg.norm(p[rows] - med, axis=1) <= config.init_outlier_m)
    if not ok.any():
        ok[:] = True
    return ok


def initial_poses(
    frame_t: np.ndarray, raw: RawPoses, config: FusionConfig, use: np.ndarray | None = None
) -> np.ndarray:
    """(N, 4, 4) initial T_world_body at every frame: raw poses, interpolated (linear position,
    slerp rotation) through gaps and held at the ends.  `use` masks out outliers."""
    use = inlier_raw_mask(raw, config, frame_t) if use is None else use
    idx = raw.frame_idx[use]
    T = raw.T_world_body[use]
    # several raw poses at one frame (not expected): keep the first
    idx, first = np.unique(idx, return_index=True)
    T = T[first]
    ts = frame_t[idx].astype(float)
    tq = np.clip(frame_t.astype(float), ts[0], ts[-1])
    return interpolate_poses(ts, T, tq)


def initial_velocities(frame_t: np.ndarray, T_init: np.ndarray) -> np.ndarray:
    """(N, 3) world velocities by central finite differences of the initial positions."""
    p = T_init[:, :3, 3]
    if len(p) < 2:
        return np.zeros_like(p)
    return np.gradient(p, frame_t * 1e-9, axis=0)


def first_velocity(
    frame_t: np.ndarray,
    raw: RawPoses,
    use: np.ndarray,
    k0: int,
    n_fit: int = FusionConfig.first_velocity_fixes,
    window_s: float = FusionConfig.first_velocity_window_s,
) -> np.ndarray:
    """World velocity at frame k0 from a least-squares line through the first inlier raw
    positions (up to `n_fit`, within `window_s` of k0); zeros when there are fewer than two."""
    idx = raw.frame_idx[use]
    p = raw.T_world_body[use, :3, 3]
    t = frame_t[idx] * 1e-9
    sel = np.flatnonzero(np.abs(t - frame_t[k0] * 1e-9) <= window_s)[:n_fit]
    if len(sel) < 2:
        return np.zeros(3)
    A = np.column_stack([np.ones(len(sel)), t[sel] - frame_t[k0] * 1e-9])
    coef, *_ = np.linalg.lstsq(A, p[sel], rcond=None)
    return coef[1]


# =========================================================================== outputs


def write_sigmas_csv(path, traj: Trajectory) -> None:
    """Per-axis 1-sigma over time: `t_ns,sigma_rx_rad,...,sigma_tz_m` (body frame, Pose3 order)."""
    if traj.covariances is None:
        raise EstimationError(f"trajectory {traj.name!r} has no covariances to write")
    sig = np.sqrt(np.maximum(np.diagonal(traj.covariances, axis1=1, axis2=2), 0.0))
    with atomic_open(path) as f:
        f.write("t_ns,sigma_rx_rad,sigma_ry_rad,sigma_rz_rad,sigma_tx_m,sigma_ty_m,sigma_tz_m\n")
        # one %-format per row on Python numbers: the text of f"{v:.6e}" on numpy scalars
        rows = zip(np.asarray(traj.timestamps_ns, dtype=np.int64).tolist(), *sig.T.tolist())
        f.write("".join(map(("%d" + ",%.6e" * sig.shape[1] + "\n").__mod__, rows)))


def fix_jumps(t_s: np.ndarray, p_world: np.ndarray, max_speed_m_s: float, slack_m=0.0) -> np.ndarray:
    """(N-1,) whether each step between consecutive fixes (times `t_s` (N,), positions
    `p_world` (N, 3)) is longer than a drone at `max_speed_m_s` can fly in that time, plus
    `slack_m` (a scalar or (N-1,) tolerance for the fixes' own noise): the fixes jumped."""
    step = np.linalg.norm(np.diff(p_world, axis=0), axis=1)
    return step > max_speed_m_s * np.diff(t_s) + slack_m


LOAD_INTERP_MAX_GAP_S = 0.2
"""A load sighting between two floor frames further apart than this (a camera blackout) is not
placed by interpolation (`retime_load_obs`): the body's motion across the gap is not known."""


def interpolable_load_times(
    frame_t: np.ndarray, t: np.ndarray, max_gap_s: float = LOAD_INTERP_MAX_GAP_S
) -> np.ndarray:
    """(M,) whether each load-sighting time `t` (M,) ns lies between two floor frames of `frame_t`
    (N,) at most `max_gap_s` apart (or on a frame): where `retime_load_obs` can place it from the
    interpolated body pose."""
    frame_t = np.asarray(frame_t, dtype=np.int64)
    t = np.asarray(t, dtype=np.int64)
    if len(frame_t) == 0 or len(t) == 0:
        return np.zeros(len(t), bool)
    inside = (t >= frame_t[0]) & (t <= frame_t[-1])
    b = np.clip(np.searchsorted(frame_t, t), 0, len(frame_t) - 1)
    a = np.maximum(b - 1, 0)
    on_frame = frame_t[b] == t
    gap_ok = (frame_t[b] - frame_t[a]) <= int(max_gap_s * 1e9)
    return inside & (on_frame | gap_ok)


def retime_load_obs(
    frame_t: np.ndarray,
    T_world_body: np.ndarray,
    load_obs: list[LoadObservation],
    camera: CameraModel,
) -> list[LoadObservation]:
    """Each load sighting placed by the body pose at its own (front camera's, offset-corrected)
    stamp t, as the paper's Algorithms 4-6 place a load from the drone pose at that image's time:
    its camera-frame point p_cam and covariance cov_cam re-expressed in the camera at the nearest
    floor frame k, through T_cam_k^-1 T_cam(t), T_cam = camera.T_world_cam of the body poses
    `T_world_body` (N, 4, 4) at `frame_t` (N,) interpolated at t (geometry.interpolate_poses),
    and stamped frame_t[k]; a load factor on X(k) then measures the load from the pose at t (to
    the interpolation's accuracy: the relative motion over at most half a frame interval).
    Sightings that cannot be interpolated (`interpolable_load_times`) or that already lie on a
    frame are returned as they are (group_load_obs matches those within max_sync_s)."""
    if not load_obs or len(frame_t) == 0:
        return list(load_obs)
    frame_t = np.asarray(frame_t, dtype=np.int64)
    t = np.array([o.timestamp_ns for o in load_obs], dtype=np.int64)
    # the nearest frame (any distance: `move` limits which are used)
    b = np.clip(np.searchsorted(frame_t, t), 1, max(len(frame_t) - 1, 1)) if len(frame_t) > 1 else 0 * t
    a = np.maximum(b - 1, 0)
    k = np.where(np.abs(t - frame_t[a]) <= np.abs(frame_t[b] - t), a, b)
    move = interpolable_load_times(frame_t, t) & (frame_t[k] != t)
    move &= np.array([o.p_cam is not None and o.cov_cam is not None for o in load_obs])
    if not move.any():
        return list(load_obs)
    i = np.flatnonzero(move)
    T_wc_t = camera.T_world_cam(interpolate_poses(frame_t, T_world_body, t[i]))
    T_ck_ct = inv_T(camera.T_world_cam(T_world_body[k[i]])) @ T_wc_t
    out = list(load_obs)
    for m, j in enumerate(i.tolist()):
        o = load_obs[j]
        R, p = T_ck_ct[m, :3, :3], T_ck_ct[m, :3, 3]
        out[j] = replace(
            o,
            timestamp_ns=int(frame_t[k[j]]),
            p_cam=R @ np.asarray(o.p_cam, float) + p,
            cov_cam=R @ np.asarray(o.cov_cam, float) @ R.T,
        )
    return out


def group_load_obs(
    frame_t: np.ndarray, load_obs: list[LoadObservation], config: FusionConfig
) -> tuple[dict[str, list[tuple[int, LoadObservation]]], int]:
    """Load observations with a camera-frame measurement, grouped by id, matched to frames.
    Returns ({id: [(frame index, obs)]}, number skipped: no p_cam / non-finite / no frame)."""
    groups: dict[str, list] = {}
    skipped = 0
    if not load_obs:
        return groups, 0
    idx = match_to_frames(
        frame_t, np.array([o.timestamp_ns for o in load_obs], dtype=np.int64), config.max_sync_s
    )
    usable = [
        k >= 0
        and o.p_cam is not None
        and o.cov_cam is not None
        and np.shape(o.p_cam) == (3,)
        and np.shape(o.cov_cam) == (3, 3)
        for k, o in zip(idx.tolist(), load_obs)
    ]
    sel = [i for i, u in enumerate(usable) if u]
    skipped = len(load_obs) - len(sel)
    if not sel:
        return groups, skipped
    P = np.array([load_obs[i].p_cam for i in sel], dtype=float)
    C = np.array([load_obs[i].cov_cam for i in sel], dtype=float)
    finite = np.isfinite(P).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    C_ok = np.where(finite[:, None, None], C, np.eye(3))
    pd = np.linalg.eigvalsh(0.5 * (C_ok + np.swapaxes(C_ok, 1, 2)))[:, 0] > 0
    good = finite & pd
    skipped += int((~good).sum())
    for i, g in zip(sel, good.tolist()):
        if g:
            o = load_obs[i]
            groups.setdefault(o.load_id, []).append((int(idx[i]), o))
    return groups, skipped


@dataclass
class FusionInputs:
    """Checked inputs of a back end (prepare_inputs)."""

    frame_t: np.ndarray  # (N,) int64 ns, strictly increasing
    raw: RawPoses
    imu: ImuData | None
    velocity: VelocityData | None
    front_camera: CameraModel | None


def check_front_camera(front_camera) -> CameraModel | None:
    """The front camera as a CameraModel (None: no front camera).  A bare 4x4 T_body_cam is
    refused: without the mount a gimbaled camera would be fused as a rigid one."""
    if front_camera is None or isinstance(front_camera, CameraModel):
        if front_camera is not None and not np.all(np.isfinite(front_camera.T_body_cam)):
            raise EstimationError("front camera: T_body_cam must be finite")
        return front_camera
    raise EstimationError(
        f"front_camera must be a CameraModel (its mount matters), got {type(front_camera).__name__}"
    )


def prepare_inputs(
    frame_times_ns,
    imu: ImuData | None,
    raw: Trajectory,
    velocity: VelocityData | None,
    front_camera: CameraModel | None,
    config: FusionConfig,
    require_motion: bool = True,
) -> FusionInputs:
    """The checks every back end starts with, or EstimationError naming the bad input.
    `require_motion=False` accepts neither IMU nor velocity (the random-walk model alone)."""
    frame_t = check_timestamps(frame_times_ns, "floor-camera frames")
    if len(frame_t) == 0:
        raise EstimationError("no floor-camera frames")
    rawp = prepare_raw(frame_t, raw, config)
    imu = check_imu(imu) if imu is not None and len(imu.timestamps_ns) else None
    velocity = check_velocity(velocity) if velocity is not None else None
    if imu is None and velocity is None and require_motion:
        raise EstimationError("neither IMU nor velocity data: nothing to fuse the QR poses with")
    return FusionInputs(frame_t, rawp, imu, velocity, check_front_camera(front_camera))
