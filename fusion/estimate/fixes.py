"""External position fixes (fusion.log.fixes) as raw poses of the fusion back ends.

Every fix becomes a state of its own: the back ends' state times are the union of the floor
camera's frame times and the fix times, so a fix constrains the position at its own time (no
interpolation to the nearest frame, no lever in time).  Its raw pose is the fix's position with
an attitude that is an initial guess only: its 6x6 covariance (Pose3 order, body frame) is
diag(s_r^2 I3, sigma^2 I3) with s_r = FREE_ROTATION_SIGMA_RAD, so that the pose factor (the
smoothers' PriorFactorPose3, the EKF's pose update) constrains the position and leaves the
attitude to the IMU: a position-only factor (GTSAM's PoseTranslationPrior) by another name, which
keeps every back end's raw-pose machinery (initial values, robust gate, restarts, health) as it
is.  The translation block is sigma^2 I3 in the body frame as in the world frame (isotropic).

Attitude guess:
- with raw QR poses: their attitude, interpolated (slerp) to the fix time;
- without (no camera: IMU + fixes): the IMU's attitude aligned to the world from the fixes
  (`align_attitude`): velocity changes of the fixes against the gyro-rotated specific force
  (in-motion alignment, Wahba's problem).  The first fix then carries that attitude with sigmas
  ALIGN_SIGMA_* (the EKF and the incremental smoother start from it), the others none.

A fix at exactly a frame time that already has a raw pose is fused into it (information form in
the tangent space of the raw pose, first order): one raw pose per state.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from fusion.conventions import GRAVITY_M_S2
from fusion.errors import EstimationError
from fusion.geometry import integrate_gyro, interpolate_poses, rotation_aligning, se3_exp
from fusion.log.euroc import ImuData, LogWarning
from fusion.log.fixes import PositionFixes
from fusion.types import Trajectory

log = logging.getLogger(__name__)

FREE_ROTATION_SIGMA_RAD = 100.0
"""Attitude sigma of a fix's raw pose: no information (1e-4 rad^-2 against ~1e4 m^-2 for cm
fixes; a Pose3 residual's rotation is at most pi)."""
ALIGN_SIGMA_ROLL_PITCH_RAD = math.radians(3.0)
ALIGN_SIGMA_YAW_RAD = math.radians(15.0)
"""Sigmas of the aligned attitude on the first fix (camera-less flights)."""
ALIGN_FIT_HALF_WINDOW_S = 0.5
"""World velocity at an alignment anchor: least-squares line through the fixes within +- this."""
ALIGN_ANCHOR_STEP_S = 0.25
ALIGN_PAIR_SPAN_S = 1.0
"""Velocity changes are taken between anchors this far apart."""
ALIGN_MIN_FIXES_PER_FIT = 3
ALIGN_MIN_PAIRS = 3
ALIGN_MIN_SIDEWAYS_DV_M_S = 0.1
"""RMS of the velocity changes across the dominant (gravity) direction below this: the drone
never accelerated sideways enough to tell the heading (warned; the smoother may still find it)."""


@dataclass
class FixMerge:
    """The back ends' inputs with the fixes in them (merge_fixes)."""

    frame_t: np.ndarray  # (M,) int64 ns: union of frame times and fix times
    raw: Trajectory  # raw poses: QR poses and fixes, time-sorted, with (M', 6, 6) covariances
    n_fixes: int
    n_fused_into_qr: int  # fixes at a frame time that has a QR pose (fused into it)
    alignment: dict = field(default_factory=dict)  # camera-less: what align_attitude found

    def note(self) -> str:
        text = f"{self.n_fixes} external position fixes fused"
        if self.alignment:
            a = self.alignment
            text += (
                f" (no camera: attitude aligned from {a['pairs']} velocity changes, "
                f"sideways velocity change {a['sideways_dv_rms_m_s']:.2f} m/s RMS)"
            )
        return text


def _fit_velocities(t_s: np.ndarray, p: np.ndarray, anchors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World velocity at each anchor time: slope of a least-squares line through the fixes
    within +-ALIGN_FIT_HALF_WINDOW_S; (ok (A,), v (A, 3))."""
    v = np.zeros((len(anchors), 3))
    ok = np.zeros(len(anchors), bool)
    lo = np.searchsorted(t_s, anchors - ALIGN_FIT_HALF_WINDOW_S)
    hi = np.searchsorted(t_s, anchors + ALIGN_FIT_HALF_WINDOW_S, side="right")
    for i, (a, b) in enumerate(zip(lo.tolist(), hi.tolist())):
        if b - a < ALIGN_MIN_FIXES_PER_FIT:
            continue
        dt = t_s[a:b] - anchors[i]
        A = np.column_stack([np.ones(b - a), dt])
        coef, *_ = np.linalg.lstsq(A, p[a:b], rcond=None)
        v[i], ok[i] = coef[1], True
    return ok, v


def align_attitude(fixes: PositionFixes, imu: ImuData) -> tuple[np.ndarray, dict]:
    """(N, 3, 3) R_world_body at the fix times, and what the alignment found.

    In-motion alignment: between anchor times a < b, the world velocity change of the fixes
    minus gravity equals the specific force rotated into the world,
        v_b - v_a - g (t_b - t_a) = R_world_imu0 * sum_i R_imu0_imui f_i dt_i
    (strapdown, e.g. Groves, "Principles of GNSS, Inertial, and Multisensor Integrated Navigation
    Systems", 2nd ed., sec. 5.5 and 14.3), R_imu0_imui chained from the gyro (bias ignored: an
    initial guess).  R_world_imu0 solves Wahba's problem over all anchor pairs
    (geometry.rotation_aligning).  EstimationError when the fixes and the IMU overlap too little."""
    t_imu = imu.timestamps_ns
    t_fix = fixes.timestamps_ns
    inside = (t_imu >= t_fix[0]) & (t_imu <= t_fix[-1])
    i0 = max(int(np.flatnonzero(inside)[0]) - 1, 0) if inside.any() else -1
    if i0 < 0 or inside.sum() < 2:
        raise EstimationError(
            "external fixes: the IMU does not overlap the fixes' time span "
            f"({t_fix[0]}-{t_fix[-1]} ns): no attitude without a camera"
        )
    t_ref = int(t_imu[i0])
    ts = (t_imu[i0:] - t_ref) * 1e-9
    dt = np.diff(ts)
    R_0 = integrate_gyro(imu.gyro_rad_s[i0:-1], dt)  # (len(ts), 3, 3) R_imu0_imuk
    F = np.einsum("nij,nj->ni", R_0[:-1], imu.accel_m_s2[i0:-1]) * dt[:, None]
    C = np.vstack([np.zeros(3), np.cumsum(F, axis=0)])  # integral of R f dt from ts[0] to ts[k]
    tf = (t_fix - t_ref) * 1e-9
    anchors = np.arange(
        tf[0] + ALIGN_FIT_HALF_WINDOW_S, tf[-1] - ALIGN_FIT_HALF_WINDOW_S + 1e-9, ALIGN_ANCHOR_STEP_S
    )
    anchors = anchors[(anchors >= ts[0]) & (anchors <= ts[-1])]
    ok, v = _fit_velocities(tf, fixes.p_world, anchors)
    step = max(int(round(ALIGN_PAIR_SPAN_S / ALIGN_ANCHOR_STEP_S)), 1)
    a_idx = np.arange(len(anchors) - step)
    a_idx = a_idx[ok[a_idx] & ok[a_idx + step]]
    if len(a_idx) < ALIGN_MIN_PAIRS:
        raise EstimationError(
            f"external fixes: {len(a_idx)} velocity changes from the fixes (at least "
            f"{ALIGN_MIN_PAIRS} needed, {ALIGN_MIN_FIXES_PER_FIT} fixes within "
            f"{ALIGN_FIT_HALF_WINDOW_S} s of each): too few or too sparse fixes to align the IMU"
        )
    b_idx = a_idx + step

    def C_at(t):
        return np.column_stack([np.interp(t, ts, C[:, j]) for j in range(3)])

    u = C_at(anchors[b_idx]) - C_at(anchors[a_idx])
    g_w = np.array([0.0, 0.0, -GRAVITY_M_S2])
    w = v[b_idx] - v[a_idx] - np.outer(anchors[b_idx] - anchors[a_idx], g_w)
    R_w_i0, S = rotation_aligning(u, w)
    # the second singular value of sum u w^T ~ the sideways velocity changes' energy
    sideways = float(math.sqrt(max(S[1], 0.0) / len(a_idx)))
    if sideways < ALIGN_MIN_SIDEWAYS_DV_M_S:  # the run's named warning is heading_warning's
        log.info(
            "external fixes: the drone barely accelerated sideways (%.3f m/s RMS velocity "
            "change): the initial heading is a guess",
            sideways,
        )
    k = np.clip(np.searchsorted(ts, tf), 0, len(ts) - 1)
    R_bi = np.asarray(imu.T_body_imu, float)[:3, :3]
    R_wb = np.einsum("ij,njk,kl->nil", R_w_i0, R_0[k], R_bi.T)
    resid = w - u @ R_w_i0.T
    info = {
        "pairs": int(len(a_idx)),
        "sideways_dv_rms_m_s": sideways,
        "residual_rms_m_s": float(np.sqrt(np.mean(np.sum(resid**2, axis=1)))),
    }
    return R_wb, info


def heading_warning(alignment: dict) -> LogWarning | None:
    """A named warning (count 1: the alignment) when `align_attitude`'s sideways velocity change
    is below ALIGN_MIN_SIDEWAYS_DV_M_S: the heading it gives the first fix (sigma
    ALIGN_SIGMA_YAW_RAD) is then a guess that the IMU and the fixes may never correct.  It was a
    log line only."""
    sideways = alignment.get("sideways_dv_rms_m_s")
    if sideways is None or sideways >= ALIGN_MIN_SIDEWAYS_DV_M_S:
        return None
    return LogWarning(
        "fixes_heading_unobserved",
        1,
        f"external fixes without a camera: the drone barely accelerated sideways ({sideways:.3f} m/s "
        f"RMS velocity change, {ALIGN_MIN_SIDEWAYS_DV_M_S:g} needed), so the initial heading is a "
        "guess and the fused yaw may stay wrong",
    )


def _fuse_into(T_q: np.ndarray, C_q: np.ndarray, p_fix: np.ndarray, sigma: float):
    """A raw pose (T_q, C_q) and a position fix at the same time as one pose and covariance:
    the fix measures the tangent translation R_q^T (p_fix - t_q) with sigma^2 I (first order)."""
    H = np.hstack([np.zeros((3, 3)), np.eye(3)])
    z = T_q[:3, :3].T @ (p_fix - T_q[:3, 3])
    info = np.linalg.inv(C_q) + H.T @ H / sigma**2
    cov = np.linalg.inv(info)
    xi = cov @ (H.T @ z) / sigma**2
    return T_q @ se3_exp(xi), 0.5 * (cov + cov.T)


def merge_fixes(
    frame_times_ns: np.ndarray | None,
    raw: Trajectory | None,
    fixes: PositionFixes,
    imu: ImuData | None,
    name: str = "fixes",
) -> FixMerge:
    """The back ends' frame times and raw poses with the external fixes added (module
    docstring).  `frame_times_ns` / `raw`: the floor camera's frames and QR poses (None or
    empty: no camera).  The raw poses need covariances (PnP); without a raw pose at all the
    attitude comes from the IMU (required then).  EstimationError otherwise."""
    frame_t = np.zeros(0, np.int64) if frame_times_ns is None else np.asarray(frame_times_ns, np.int64)
    t_fix = np.asarray(fixes.timestamps_ns, np.int64)
    p_fix = np.asarray(fixes.p_world, float)
    sig = np.asarray(fixes.sigma_m, float)
    has_raw = raw is not None and len(raw) > 0
    free = np.diag(np.r_[np.full(3, FREE_ROTATION_SIGMA_RAD**2), np.zeros(3)])
    cov_fix = free[None] + np.einsum("n,ij->nij", sig**2, np.diag([0.0, 0, 0, 1, 1, 1]))
    alignment: dict = {}
    if has_raw:
        assert raw is not None
        if raw.covariances is None:
            raise EstimationError(
                f"external fixes: the raw poses {raw.name!r} have no covariances to weigh the fixes against"
            )
        tq = np.clip(t_fix, raw.timestamps_ns[0], raw.timestamps_ns[-1])
        R_fix = interpolate_poses(raw.timestamps_ns.astype(float), raw.T_world_body, tq.astype(float))[
            :, :3, :3
        ]
    else:
        if imu is None or len(imu.timestamps_ns) == 0:
            raise EstimationError("external fixes without a camera need an IMU: the fixes give no attitude")
        R_fix, alignment = align_attitude(fixes, imu)
        cov_fix[0, :3, :3] = np.diag(
            [ALIGN_SIGMA_ROLL_PITCH_RAD**2, ALIGN_SIGMA_ROLL_PITCH_RAD**2, ALIGN_SIGMA_YAW_RAD**2]
        )
    T_fix = np.tile(np.eye(4), (len(t_fix), 1, 1))
    T_fix[:, :3, :3] = R_fix
    T_fix[:, :3, 3] = p_fix
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    if has_raw:
        assert raw is not None and raw.covariances is not None
        for t, T, C in zip(raw.timestamps_ns.tolist(), raw.T_world_body, raw.covariances):
            poses[int(t)] = (T, C)
    n_fused = 0
    for i, t in enumerate(t_fix.tolist()):
        if t in poses:
            poses[t] = _fuse_into(*poses[t], p_fix[i], float(sig[i]))
            n_fused += 1
        else:
            poses[t] = (T_fix[i], cov_fix[i])
    ts = np.array(sorted(poses), dtype=np.int64)
    merged = Trajectory(
        raw.name if has_raw and raw is not None else name,
        ts,
        np.array([poses[int(t)][0] for t in ts]),
        np.array([poses[int(t)][1] for t in ts]),
    )
    return FixMerge(np.union1d(frame_t, t_fix), merged, len(t_fix), n_fused, alignment)
