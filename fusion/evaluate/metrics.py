"""Trajectory and load-map error metrics against ground truth (pure maths, no I/O but `write_metrics`).

Conventions (DESIGN.md): poses are T_world_body, both estimate and truth are in the world frame of
the floor codes, so errors are computed without alignment unless asked (`align=True` is evo's
`-a`: an SE(3) Umeyama fit of the positions).  Pose covariances are 6x6 in GTSAM Pose3 tangent
order [rx, ry, rz, tx, ty, tz], body frame.  Every record's keys carry their unit
(`ate_rmse_m`, `yaw_mae_deg`), so `metrics.json` carries its units.

Estimators named in `position_yaw_only` (default: the paper's, Alg. 1-3, which gives position and
yaw D_r-theta only; the run adds a gimbaled floor camera's PnP, whose poses are the level frame)
are compared on position and yaw; their roll/pitch are treated as unknown, and with covariances
their NEES is the 4-dof one of [yaw, world position] (`position_yaw_nees`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2

from fusion.errors import EvaluationError
from fusion.fileio import atomic_open
from fusion.geometry import interpolate_poses as _interpolate_sampled
from fusion.geometry import inv_T, se3_log, so3_log, wrap_angle, yaw_of
from fusion.types import LoadMap, Trajectory

SCHEMA = "fusion.metrics/1"

# The paper's simulator results (Sec. 4.1: per-axis mean absolute error; Sec. 4.2: load map).
PAPER_SIM_LOCALIZATION_MAE_CM = {"x": 0.83, "y": 0.32, "z": 2.95}
PAPER_SIM_YAW_MAE_DEG = 1.08
PAPER_SIM_LOADMAP_MAE_CM = {"x": 0.87, "y": 1.64, "z": 2.11}

BLACKOUT_NOMINAL_DURATIONS_S = (0.5, 1.0, 2.0, 5.0)
AXES = ("x", "y", "z")


# ============================================================================ association


@dataclass
class Association:
    """An estimate matched to ground truth interpolated at the estimate's timestamps.

    Only estimate samples inside the ground-truth time span are kept (`index_est` says which)."""

    name: str
    timestamps_ns: np.ndarray  # (M,)
    T_world_body_est: np.ndarray  # (M, 4, 4)
    T_world_body_gt: np.ndarray  # (M, 4, 4)
    covariances: np.ndarray | None  # (M, 6, 6) or None
    index_est: np.ndarray  # (M,) indices into the estimate
    n_outside_gt: int  # estimate samples outside the ground-truth span

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    @property
    def position_errors_m(self) -> np.ndarray:
        """(M, 3) p_est - p_gt in the world frame."""
        return self.T_world_body_est[:, :3, 3] - self.T_world_body_gt[:, :3, 3]

    @property
    def yaw_errors_rad(self) -> np.ndarray:
        """(M,) yaw_est - yaw_gt wrapped to (-pi, pi]."""
        return wrap_angle(yaw_of(self.T_world_body_est[:, :3, :3]) - yaw_of(self.T_world_body_gt[:, :3, :3]))


class TruthPoses:
    """A ground truth's (N, 4, 4) T_world_body made only for the rows asked for, each the same to
    the bit as in GroundTruth.T_world_body: interpolation reads only the rows around the
    estimates' stamps (bracketing_samples), and the whole array of a 200 Hz 30-minute flight is
    46 MB plus its rotation temporaries, at the evaluation's memory peak (BENCHMARKS.md)."""

    def __init__(self, gt) -> None:
        self.gt = gt  # fusion.log.GroundTruth

    def __len__(self) -> int:
        return len(self.gt.timestamps_ns)

    def rows(self, idx: np.ndarray) -> np.ndarray:
        """(len(idx), 4, 4)."""
        return self.gt.T_world_body_rows(idx)

    @property
    def p_world(self) -> np.ndarray:
        """(N, 3) float64, as the poses' translations."""
        return np.asarray(self.gt.p_world, dtype=float)


def _truth_rows(T_world_body: np.ndarray | TruthPoses, idx: np.ndarray) -> np.ndarray:
    return T_world_body.rows(idx) if isinstance(T_world_body, TruthPoses) else np.asarray(T_world_body)[idx]


def _truth_positions(T_world_body: np.ndarray | TruthPoses) -> np.ndarray:
    return T_world_body.p_world if isinstance(T_world_body, TruthPoses) else T_world_body[:, :3, 3]


def interpolate_poses(
    timestamps_ns: np.ndarray, T_world_body: np.ndarray | TruthPoses, query_ns: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at `query_ns` (M,): linear in position, slerp in rotation.

    Returns (T (K, 4, 4), mask (M,) of queries inside [t_0, t_end]); K = mask.sum()."""
    t = np.asarray(timestamps_ns, dtype=np.int64)
    q = np.asarray(query_ns, dtype=np.int64)
    if len(t) == 0:
        return np.zeros((0, 4, 4)), np.zeros(len(q), dtype=bool)
    mask = _inside_span(t, q)
    qk = q[mask]
    # Interpolate in float seconds relative to t0: exact at the samples, no int64 -> float loss.
    ts = (t - t[0]) * 1e-9
    qs = (qk - t[0]) * 1e-9
    keep = bracketing_samples(ts, qs)
    return _interpolate_sampled(ts[keep], _truth_rows(T_world_body, keep), qs), mask


def _inside_span(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(M,) queries q inside [t[0], t[-1]] (int64 ns; t non-empty)."""
    return (q >= t[0]) & (q <= t[-1])


def bracketing_samples(ts: np.ndarray, qs: np.ndarray) -> np.ndarray:
    """Sorted indices of the samples `ts` (N,) that interpolation at the queries `qs` (K,) inside
    [ts[0], ts[-1]] can touch: for each query the two samples around it and the one before
    (scipy's Slerp picks the interval ending at a query equal to a sample), so that on this
    subset every query falls in the same interval as on all samples and the interpolated poses
    are the same to the bit.  A 200 Hz truth queried at 30 Hz: ~3x fewer rotations to convert
    (geometry.interpolate_poses converts every sample; this was most of the metrics' time)."""
    n = len(ts)
    if n <= 2 or len(qs) == 0:
        return np.arange(n)
    j = np.searchsorted(ts, qs, side="right")
    return np.unique(np.clip(np.concatenate([j - 2, j - 1, j]), 0, n - 1))


def associate(
    gt_timestamps_ns: np.ndarray,
    gt_T_world_body: np.ndarray | TruthPoses,
    traj: Trajectory,
    truth_at: tuple[np.ndarray, np.ndarray] | None = None,
) -> Association:
    """Interpolate the ground truth (200 Hz) at the estimate's timestamps.  Estimate samples with
    a non-finite pose are dropped (counted in `n_outside_gt`); unsorted timestamps raise.
    truth_at: (stamps (K,) sorted, truth there (K, 4, 4)) covering every stamp of `traj` inside
    the truth's span (associate_many), used instead of interpolating again."""
    t_est = np.asarray(traj.timestamps_ns, dtype=np.int64)
    if np.any(np.diff(t_est) < 0):
        raise EvaluationError(f"trajectory '{traj.name}': timestamps are not sorted")
    if truth_at is None:
        T_gt, mask = interpolate_poses(gt_timestamps_ns, gt_T_world_body, t_est)
    elif len(gt_timestamps_ns) == 0:
        T_gt, mask = np.zeros((0, 4, 4)), np.zeros(len(t_est), dtype=bool)
    else:
        mask = _inside_span(np.asarray(gt_timestamps_ns, dtype=np.int64), t_est)
        T_gt = _rows_of(truth_at[1], np.searchsorted(truth_at[0], t_est[mask]))
    finite = np.isfinite(np.asarray(traj.T_world_body, dtype=float).reshape(len(t_est), 16)).all(axis=1)
    idx = np.flatnonzero(mask & finite)
    finite_inside = finite[mask]
    if not finite_inside.all():
        T_gt = T_gt[finite_inside]
    cov = None
    if traj.covariances is not None and len(traj.covariances) == len(traj):
        cov = _rows_of(np.asarray(traj.covariances), idx)
    return Association(
        traj.name,
        _rows_of(np.asarray(traj.timestamps_ns, dtype=np.int64), idx),
        _rows_of(np.asarray(traj.T_world_body), idx),
        T_gt,
        cov,
        idx,
        int(len(traj) - len(idx)),
    )


def _rows_of(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """a[idx] for sorted row indices `idx`: a read-only view of `a` when they are consecutive
    (every sample of a fused trajectory, the truth table's rows at the frame stamps), else a
    copy.  The same values either way; the views spare the evaluation's and the plots'
    associations a copy of each trajectory's poses and covariances (30-minute flight: ~23 MB
    each, held for every estimator at the report's memory peak, BENCHMARKS.md)."""
    if len(idx) and bool(np.all(np.diff(idx) == 1)):
        view = a[int(idx[0]) : int(idx[-1]) + 1]
        view.flags.writeable = False
        return view
    return a[idx]


def associate_many(
    gt_timestamps_ns: np.ndarray,
    gt_T_world_body: np.ndarray | TruthPoses,
    trajectories: dict[str, Trajectory],
) -> dict[str, Association]:
    """`associate` of every trajectory, the truth interpolated once at the union of their stamps
    (the fused estimators share the frame stamps; interpolation is per query, so each
    association is the same to the bit as associating alone)."""
    stamps = [np.asarray(t.timestamps_ns, dtype=np.int64) for t in trajectories.values()]
    t_all = np.unique(np.concatenate(stamps)) if stamps else np.zeros(0, dtype=np.int64)
    T_all, mask = interpolate_poses(gt_timestamps_ns, gt_T_world_body, t_all)
    table = (t_all[mask], T_all)
    return {
        name: associate(gt_timestamps_ns, gt_T_world_body, traj, truth_at=table)
        for name, traj in trajectories.items()
    }


# ============================================================================ SE(3) helpers


def umeyama_alignment(p_est: np.ndarray, p_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising sum |p_gt - (R p_est + t)|^2, no scale
    (Umeyama 1991, eqs. 34-35 with c = 1; what evo's `-a` does).  (N, 3), (N, 3) -> (3,3), (3,)."""
    if len(p_est) < 3:
        raise EvaluationError(f"alignment needs at least 3 poses, got {len(p_est)}")
    mu_e, mu_g = p_est.mean(axis=0), p_gt.mean(axis=0)
    cov = (p_gt - mu_g).T @ (p_est - mu_e) / len(p_est)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    return R, mu_g - R @ mu_e


def align_association(a: Association) -> tuple[Association, np.ndarray]:
    """Apply the SE(3) Umeyama fit to the estimate; returns (aligned copy, T_gtworld_estworld)."""
    R, t = umeyama_alignment(a.T_world_body_est[:, :3, 3], a.T_world_body_gt[:, :3, 3])
    T_align = np.eye(4)
    T_align[:3, :3], T_align[:3, 3] = R, t
    aligned = Association(
        a.name,
        a.timestamps_ns,
        T_align @ a.T_world_body_est,
        a.T_world_body_gt,
        a.covariances,
        a.index_est,
        a.n_outside_gt,
    )
    return aligned, T_align


# ============================================================================ records


def _stats(x: np.ndarray) -> dict[str, float | None]:
    """rmse / mean / median / std / max of non-negative errors (None when empty)."""
    x = np.asarray(x, dtype=float)
    if len(x) == 0:
        return {"rmse": None, "mean": None, "median": None, "std": None, "max": None}
    return {
        "rmse": float(np.sqrt(np.mean(x**2))),
        "mean": float(np.mean(x)),
        "median": float(np.median(x)),
        "std": float(np.std(x)),
        "max": float(np.max(x)),
    }


@dataclass
class AxisErrors:
    """Per-axis error of p_est - p_gt (world frame): the paper's metric is the mean absolute error."""

    n: int
    mae_x_m: float | None
    mae_y_m: float | None
    mae_z_m: float | None
    mae_x_cm: float | None
    mae_y_cm: float | None
    mae_z_cm: float | None
    rmse_x_m: float | None
    rmse_y_m: float | None
    rmse_z_m: float | None
    bias_x_m: float | None
    bias_y_m: float | None
    bias_z_m: float | None


def axis_errors(err_xyz_m: np.ndarray) -> AxisErrors:
    """Per-axis MAE (m and cm), RMSE and mean (bias) of (N, 3) errors."""
    e = np.asarray(err_xyz_m, dtype=float).reshape(-1, 3)
    if len(e) == 0:
        return AxisErrors(0, *([None] * 12))
    mae = np.mean(np.abs(e), axis=0)
    rmse = np.sqrt(np.mean(e**2, axis=0))
    bias = np.mean(e, axis=0)
    return AxisErrors(
        len(e), *map(float, mae), *map(float, 100.0 * mae), *map(float, rmse), *map(float, bias)
    )


@dataclass
class ATE:
    """Absolute trajectory error: |p_est - p_gt| (evo APE, translation part)."""

    n: int
    alignment: str  # "none" or "se3"
    ate_rmse_m: float | None
    ate_mean_m: float | None
    ate_median_m: float | None
    ate_std_m: float | None
    ate_max_m: float | None


def ate(a: Association, align: bool = False) -> ATE:
    if align:
        a, _ = align_association(a)
    s = _stats(np.linalg.norm(a.position_errors_m, axis=1))
    return ATE(len(a), "se3" if align else "none", s["rmse"], s["mean"], s["median"], s["std"], s["max"])


@dataclass
class Yaw:
    """Heading error yaw_est - yaw_gt, wrapped (degrees)."""

    n: int
    yaw_mae_deg: float | None
    yaw_rmse_deg: float | None
    yaw_max_deg: float | None
    yaw_bias_deg: float | None


def yaw_errors(a: Association) -> Yaw:
    e = np.degrees(a.yaw_errors_rad)
    if len(e) == 0:
        return Yaw(0, None, None, None, None)
    return Yaw(
        len(e),
        float(np.mean(np.abs(e))),
        float(np.sqrt(np.mean(e**2))),
        float(np.max(np.abs(e))),
        float(np.mean(e)),
    )


def rotation_errors_deg(a: Association) -> np.ndarray:
    """(M,) angle of R_gt^T R_est in degrees (full attitude)."""
    R = np.swapaxes(a.T_world_body_gt[:, :3, :3], 1, 2) @ a.T_world_body_est[:, :3, :3]
    return np.degrees(np.linalg.norm(so3_log(R), axis=1)) if len(R) else np.zeros(0)


@dataclass
class RPE:
    """Relative error over a fixed travelled distance or time.

    Translation: |(p_est_j - p_est_i) - (p_gt_j - p_gt_i)| in the world frame (orientation-free, so
    the yaw-only paper estimator is comparable; equals evo's RPE translation when the rotation
    error at i is zero).  Rotation: angle of (R_gt_i^T R_gt_j)^T (R_est_i^T R_est_j) (None for
    yaw-only estimators); yaw: drift of the heading change.  Pairs: each i with the first j whose
    distance (or time) from i reaches `delta`, kept if it overshoots by at most `tolerance`."""

    delta: float
    delta_unit: str  # "m" (travelled, along the truth) or "s"
    n_pairs: int
    rpe_trans_rmse_m: float | None
    rpe_trans_mean_m: float | None
    rpe_trans_max_m: float | None
    rpe_rot_rmse_deg: float | None
    rpe_rot_max_deg: float | None
    rpe_yaw_rmse_deg: float | None
    rpe_yaw_max_deg: float | None


def travelled_distance_m(
    gt_timestamps_ns: np.ndarray, gt_p_world: np.ndarray, query_ns: np.ndarray
) -> np.ndarray:
    """Path length of the truth from its start to each query time (m), (M,)."""
    step = np.linalg.norm(np.diff(gt_p_world, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(step)])
    t = np.asarray(gt_timestamps_ns, dtype=np.int64)
    return np.interp((np.asarray(query_ns, dtype=np.int64) - t[0]) * 1e-9, (t - t[0]) * 1e-9, cum)


def rpe(
    a: Association, along: np.ndarray, delta: float, unit: str, full_attitude: bool, tolerance: float = 0.2
) -> RPE:
    """RPE with pairs chosen along a monotonic coordinate `along` (M,) (distance m or time s)."""
    along = np.asarray(along, dtype=float)
    j = np.searchsorted(along, along + delta, side="left")
    ok = j < len(along)
    i = np.flatnonzero(ok)
    j = j[ok]
    keep = (along[j] - along[i]) <= delta * (1.0 + tolerance)
    i, j = i[keep], j[keep]
    if len(i) == 0:
        return RPE(delta, unit, 0, *([None] * 7))
    p_e, p_g = a.T_world_body_est[:, :3, 3], a.T_world_body_gt[:, :3, 3]
    d = np.linalg.norm((p_e[j] - p_e[i]) - (p_g[j] - p_g[i]), axis=1)
    ye, yg = yaw_of(a.T_world_body_est[:, :3, :3]), yaw_of(a.T_world_body_gt[:, :3, :3])
    dyaw = np.degrees(np.abs(wrap_angle((ye[j] - ye[i]) - (yg[j] - yg[i]))))
    rot_rmse = rot_max = None
    if full_attitude:
        Re, Rg = a.T_world_body_est[:, :3, :3], a.T_world_body_gt[:, :3, :3]
        rel_e = np.swapaxes(Re[i], 1, 2) @ Re[j]
        rel_g = np.swapaxes(Rg[i], 1, 2) @ Rg[j]
        ang = np.degrees(np.linalg.norm(so3_log(np.swapaxes(rel_g, 1, 2) @ rel_e), axis=1))
        rot_rmse, rot_max = float(np.sqrt(np.mean(ang**2))), float(np.max(ang))
    return RPE(
        delta,
        unit,
        len(i),
        float(np.sqrt(np.mean(d**2))),
        float(np.mean(d)),
        float(np.max(d)),
        rot_rmse,
        rot_max,
        float(np.sqrt(np.mean(dyaw**2))),
        float(np.max(dyaw)),
    )


@dataclass
class NEES:
    """Normalised estimation error squared e^T P^-1 e: its mean should be `dof` for a consistent
    estimator; `fraction_inside_95` of samples should lie below the chi2(dof) 95% quantile
    (filterpy.stats.NEES; Bar-Shalom, Li & Kirubarajan, Sec. 5.4)."""

    dof: int
    n: int
    nees_mean: float | None
    nees_median: float | None
    chi2_95_bound: float
    fraction_inside_95: float | None
    # two-sided 95% interval of the mean if the samples were independent (they are not: a
    # smoother's errors are correlated in time, so read it as a rough guide)
    mean_interval_95_independent: tuple[float, float] | None


def nees_from_errors(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,) e_k^T P_k^-1 e_k for (N, d) errors and (N, d, d) covariances (singular -> NaN)."""
    err = np.asarray(err, dtype=float)
    cov = np.asarray(cov, dtype=float)
    if len(err) == 0:
        return np.zeros(0)
    try:  # batched; one singular matrix makes it fall back
        x = np.linalg.solve(cov, err[..., None])[..., 0]
        return np.einsum("ni,ni->n", err, x)
    except np.linalg.LinAlgError:
        pass
    out = np.full(len(err), np.nan)
    for k, (e, P) in enumerate(zip(err, cov)):
        try:
            out[k] = float(e @ np.linalg.solve(P, e))
        except np.linalg.LinAlgError:
            pass
    return out


def nees_record(values: np.ndarray, dof: int) -> NEES:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    bound = float(chi2.ppf(0.95, dof))
    if len(v) == 0:
        return NEES(dof, 0, None, None, bound, None, None)
    n = len(v)
    lo, hi = chi2.ppf([0.025, 0.975], n * dof) / n
    return NEES(
        dof,
        n,
        float(np.mean(v)),
        float(np.median(v)),
        bound,
        float(np.mean(v <= bound)),
        (float(lo), float(hi)),
    )


def pose_nees(a: Association) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample NEES (position 3-dof, pose 6-dof) of an association with covariances.

    6-dof: xi = Log(T_gt^-1 T_est) in the body frame, Pose3 order, against the full 6x6.
    3-dof: the world position error against R_est P_tt R_est^T (to first order
    p = p_hat + R_hat t for T = T_hat Exp(xi))."""
    if a.covariances is None or len(a) == 0:
        return np.zeros(0), np.zeros(0)
    P = a.covariances
    T_err = np.einsum("nij,njk->nik", inv_T(a.T_world_body_gt), a.T_world_body_est)
    xi = se3_log(T_err)
    nees6 = nees_from_errors(xi, P)
    R = a.T_world_body_est[:, :3, :3]
    P_pos_world = R @ P[:, 3:, 3:] @ np.swapaxes(R, 1, 2)
    nees3 = nees_from_errors(a.position_errors_m, P_pos_world)
    return nees3, nees6


def position_yaw_nees(a: Association) -> np.ndarray:
    """Per-sample 4-dof NEES of [yaw, world position] for an estimate whose attitude is its level
    frame (roll = pitch = 0: a gimbaled floor camera's PnP): the error [wrap(yaw_est - yaw_gt),
    p_est - p_gt] against J P J^T, J taking the body-frame [rz, t] of the Pose3 covariance to
    world yaw and position (rz is the world yaw for a level estimate; t turns by R_est).  The
    6-dof NEES of such a pose against the truth's full attitude reads the truth's tilt as a yaw
    error at second order (roll x pitch / 2: ~10 mrad at 13 and 6 deg against yaw sigmas of
    0.01-0.03 mrad; BENCHMARKS.md, held18's Defect 6)."""
    if a.covariances is None or len(a) == 0:
        return np.zeros(0)
    P = a.covariances
    R = a.T_world_body_est[:, :3, :3]
    J = np.zeros((len(a), 4, 6))
    J[:, 0, 2] = 1.0
    J[:, 1:, 3:] = R
    C = J @ P @ np.swapaxes(J, 1, 2)
    e = np.column_stack([a.yaw_errors_rad, a.position_errors_m])
    return nees_from_errors(e, C)


# ============================================================================ blackouts, coverage


def inside_intervals(t_ns: np.ndarray, intervals: Iterable[tuple[int, int, str]]) -> np.ndarray:
    """(N,) True where start <= t <= end for some interval."""
    t = np.asarray(t_ns, dtype=np.int64)
    mask = np.zeros(len(t), dtype=bool)
    for start, end, *_ in intervals or ():
        mask |= (t >= int(start)) & (t <= int(end))
    return mask


def nominal_duration_s(duration_s: float) -> float:
    """Nearest of BLACKOUT_NOMINAL_DURATIONS_S in log scale (0.5 / 1 / 2 / 5 s)."""
    d = max(duration_s, 1e-6)
    return min(BLACKOUT_NOMINAL_DURATIONS_S, key=lambda n: abs(math.log(d / n)))


def blackout_errors(a: Association, blackouts: list[tuple[int, int, str]]) -> dict:
    """Position errors inside vs outside the blackouts, and the max error inside each blackout
    (grouped by nominal duration 0.5 / 1 / 2 / 5 s)."""
    err = np.linalg.norm(a.position_errors_m, axis=1)
    inside = inside_intervals(a.timestamps_ns, blackouts)
    s_in, s_out = _stats(err[inside]), _stats(err[~inside])
    per: list[dict[str, Any]] = []
    for start, end, kind in blackouts:
        m = (a.timestamps_ns >= start) & (a.timestamps_ns <= end)
        per.append(
            {
                "start_ns": int(start),
                "end_ns": int(end),
                "kind": str(kind),
                "duration_s": (end - start) * 1e-9,
                "n_estimates": int(m.sum()),
                "max_error_m": float(err[m].max()) if m.any() else None,
            }
        )
    groups: dict[str, dict] = {}
    for b in per:
        key = f"{nominal_duration_s(b['duration_s']):g}"
        g = groups.setdefault(
            key, {"nominal_duration_s": float(key), "n_blackouts": 0, "n_with_estimates": 0, "_max": []}
        )
        g["n_blackouts"] += 1
        if b["max_error_m"] is not None:
            g["n_with_estimates"] += 1
            g["_max"].append(b["max_error_m"])
    for g in groups.values():
        m = g.pop("_max")
        g["max_error_max_m"] = float(np.max(m)) if m else None
        g["max_error_mean_m"] = float(np.mean(m)) if m else None
    return {
        "n_inside": int(inside.sum()),
        "n_outside": int((~inside).sum()),
        "inside": {f"{k}_m": v for k, v in s_in.items()},
        "outside": {f"{k}_m": v for k, v in s_out.items()},
        "per_blackout": per,
        "by_duration": dict(sorted(groups.items(), key=lambda kv: float(kv[0]))),
    }


def coverage_fraction(
    gt_timestamps_ns: np.ndarray, est_timestamps_ns: np.ndarray, tolerance_s: float = 0.1
) -> float:
    """Fraction of ground-truth samples (uniform in time) with an estimate within `tolerance_s`."""
    g = np.asarray(gt_timestamps_ns, dtype=np.int64)
    e = np.sort(np.asarray(est_timestamps_ns, dtype=np.int64))
    if len(g) == 0:
        return 0.0
    if len(e) == 0:
        return 0.0
    k = np.clip(np.searchsorted(e, g), 1, len(e)) if len(e) > 1 else np.zeros(len(g), dtype=int)
    if len(e) > 1:
        d = np.minimum(np.abs(e[k - 1] - g), np.abs(e[np.minimum(k, len(e) - 1)] - g))
    else:
        d = np.abs(e[0] - g)
    return float(np.mean(d <= tolerance_s * 1e9))


# ============================================================================ load maps


def load_map_errors(load_map: LoadMap, loads_gt: dict[str, np.ndarray]) -> dict:
    """Per-load and per-axis errors of a load map; ids missing from either side are listed."""
    est = load_map.by_id()
    common = sorted(set(est) & set(loads_gt))
    per_load = {}
    errs, nees = [], []
    for lid in common:
        e = np.asarray(est[lid].p_world, dtype=float) - np.asarray(loads_gt[lid], dtype=float)
        errs.append(e)
        rec = {
            "error_x_m": float(e[0]),
            "error_y_m": float(e[1]),
            "error_z_m": float(e[2]),
            "error_norm_m": float(np.linalg.norm(e)),
            "n_obs": int(est[lid].n_obs),
            "nees": None,
        }
        cov = est[lid].cov_world
        if cov is not None:
            v = nees_from_errors(e[None], np.asarray(cov, dtype=float)[None])[0]
            rec["nees"] = None if not np.isfinite(v) else float(v)
            if np.isfinite(v):
                nees.append(v)
        per_load[lid] = rec
    E = np.asarray(errs).reshape(-1, 3)
    norm = _stats(np.linalg.norm(E, axis=1))
    return {
        "n_loads_gt": len(loads_gt),
        "n_mapped": len(common),
        "missing_ids": sorted(set(loads_gt) - set(est)),
        "extra_ids": sorted(set(est) - set(loads_gt)),
        "axis": asdict(axis_errors(E)),
        "mae_xyz_m": [float(v) for v in np.mean(np.abs(E), axis=0)] if len(E) else None,
        "error_norm": {f"{k}_m": v for k, v in norm.items()},
        "nees_3dof": asdict(nees_record(np.asarray(nees), 3)),
        "per_load": per_load,
    }


# ============================================================================ evaluate


GT_FRAME_MIN_M = 0.5
"""`groundtruth_frame_mismatch` speaks when the reference estimate's ATE as given is above this ...
"""
GT_FRAME_RATIO = 10.0
"""... and this many times its ATE after an SE(3) fit: the shapes agree, the frames do not."""


def groundtruth_frame_mismatch(a: Association) -> dict | None:
    """Is the ground truth in another frame than the estimate (the floor codes', world.yaml)?
    An estimate whose errors vanish under an SE(3) fit (evo's -a) but are large as given
    (GT_FRAME_MIN_M, GT_FRAME_RATIO) was compared with a truth whose origin or axes differ: its
    ATE measures the frames' offset, not the estimate.  Returns the two RMSEs and the fit's
    translation (m) and rotation (deg), or None."""
    if len(a) < 3:
        return None
    as_given = ate(a).ate_rmse_m
    if as_given is None or not as_given > GT_FRAME_MIN_M:
        return None
    aligned, T = align_association(a)
    fitted = ate(aligned).ate_rmse_m
    if fitted is None or as_given < GT_FRAME_RATIO * fitted:
        return None
    angle = float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
    return {
        "estimator": a.name,
        "ate_rmse_m": as_given,
        "ate_aligned_rmse_m": fitted,
        "translation_m": float(np.linalg.norm(T[:3, 3])),
        "rotation_deg": angle,
    }


def trajectory_metrics(
    gt_timestamps_ns: np.ndarray,
    gt_T_world_body: np.ndarray | TruthPoses,
    traj: Trajectory,
    blackouts: list[tuple[int, int, str]] | None = None,
    full_attitude: bool = True,
    align: bool = False,
    coverage_tolerance_s: float = 0.1,
    association: Association | None = None,
) -> dict:
    """All metrics of one estimated trajectory against the truth, as a JSON-ready dict.
    association: `associate(gt_timestamps_ns, gt_T_world_body, traj)` when the caller has it."""
    a = association if association is not None else associate(gt_timestamps_ns, gt_T_world_body, traj)
    out: dict = {
        "n_poses": len(traj),
        "n_matched": len(a),
        "n_outside_groundtruth": a.n_outside_gt,
        "compared": "position+yaw" if not full_attitude else "pose",
        "coverage_fraction": coverage_fraction(gt_timestamps_ns, traj.timestamps_ns, coverage_tolerance_s),
        "coverage_tolerance_s": coverage_tolerance_s,
    }
    if len(a) == 0:
        return out
    out["axis"] = asdict(axis_errors(a.position_errors_m))
    out["ate"] = asdict(ate(a))
    # headline figures, flat, for terminal summaries
    out["mae_xyz_m"] = [out["axis"][f"mae_{k}_m"] for k in AXES]
    out["mae_yaw_deg"] = yaw_errors(a).yaw_mae_deg
    out["ate_rmse_m"] = out["ate"]["ate_rmse_m"]
    if align and len(a) >= 3:
        out["ate_aligned"] = asdict(ate(a, align=True))
    out["yaw"] = asdict(yaw_errors(a))
    if full_attitude:
        r = rotation_errors_deg(a)
        out["rotation"] = {
            "rot_rmse_deg": float(np.sqrt(np.mean(r**2))),
            "rot_mean_deg": float(np.mean(r)),
            "rot_max_deg": float(np.max(r)),
        }
    dist = travelled_distance_m(gt_timestamps_ns, _truth_positions(gt_T_world_body), a.timestamps_ns)
    out["rpe_1m"] = asdict(rpe(a, dist, 1.0, "m", full_attitude))
    out["rpe_1s"] = asdict(rpe(a, (a.timestamps_ns - a.timestamps_ns[0]) * 1e-9, 1.0, "s", full_attitude))
    if blackouts:
        out["blackouts"] = blackout_errors(a, blackouts)
    if a.covariances is not None:
        n3, n6 = pose_nees(a)
        out["nees_position_3dof"] = asdict(nees_record(n3, 3))
        if full_attitude:
            out["nees_pose_6dof"] = asdict(nees_record(n6, 6))
        else:
            out["nees_position_yaw_4dof"] = asdict(nees_record(position_yaw_nees(a), 4))
    return out


def evaluate(
    gt,
    trajectories: dict[str, Trajectory],
    load_maps: dict[str, LoadMap],
    loads_gt: dict[str, np.ndarray] | None,
    blackouts: list[tuple[int, int, str]] | None,
    detection_stats: dict | None = None,
    *,
    align: bool = False,
    position_yaw_only: Iterable[str] = ("paper",),
    coverage_tolerance_s: float = 0.1,
    common_reference: str = "pnp",
) -> dict:
    """Compare every trajectory and load map with the truth; returns a JSON-ready dict.

    gt: `fusion.log.GroundTruth` (or None: only detection statistics and counts are returned).
    trajectories / load_maps: by estimator name.  loads_gt: {id: (3,) world position, m}.
    blackouts: [(start_ns, end_ns, kind)].  align: also report SE(3)-aligned ATE (evo's -a).
    position_yaw_only: estimators whose roll/pitch are unknown (compared on position and yaw)."""
    yaw_only = set(position_yaw_only)
    blackouts = list(blackouts or [])
    out: dict = {
        "schema": SCHEMA,
        "paper_simulator_reference": {
            "localization_mae_cm": PAPER_SIM_LOCALIZATION_MAE_CM,
            "yaw_mae_deg": PAPER_SIM_YAW_MAE_DEG,
            "loadmap_mae_cm": PAPER_SIM_LOADMAP_MAE_CM,
        },
        "has_groundtruth": gt is not None,
        "trajectories": {},
        "load_maps": {},
        "detection": detection_stats,
    }
    if blackouts:
        d = [(b - a) * 1e-9 for a, b, _ in blackouts]
        out["blackouts"] = {
            "n": len(blackouts),
            "total_s": float(np.sum(d)),
            "durations_s": [float(x) for x in d],
        }
    if gt is not None:
        t_gt = np.asarray(gt.timestamps_ns, dtype=np.int64)
        T_gt = TruthPoses(gt)
        if len(t_gt) < 2:
            raise EvaluationError(f"ground truth has {len(t_gt)} samples; need at least 2")
        if np.any(np.diff(t_gt) <= 0):
            raise EvaluationError("ground-truth timestamps are not strictly increasing")
        out["groundtruth"] = {
            "n_samples": int(len(t_gt)),
            "duration_s": float((t_gt[-1] - t_gt[0]) * 1e-9),
            "path_length_m": float(np.sum(np.linalg.norm(np.diff(_truth_positions(T_gt), axis=0), axis=1))),
        }
        # one association per trajectory, shared by its metrics and the like-for-like ATE below
        assoc = associate_many(t_gt, T_gt, trajectories)
        for name, traj in trajectories.items():
            out["trajectories"][name] = trajectory_metrics(
                t_gt,
                T_gt,
                traj,
                blackouts,
                full_attitude=name not in yaw_only,
                align=align,
                coverage_tolerance_s=coverage_tolerance_s,
                association=assoc[name],
            )
        # Like-for-like: every estimator on the frames where the reference raw estimator has a
        # pose (a fused trajectory also covers blackouts and the time before the first fix,
        # where errors are larger by nature).
        ref = trajectories.get(common_reference)
        if ref is not None:
            mismatch = groundtruth_frame_mismatch(assoc[common_reference])
            if mismatch is not None:
                out["groundtruth_frame_mismatch"] = mismatch
        if ref is not None and len(ref):
            for name in trajectories:
                # the association's rows at the reference's stamps = associating the poses at
                # those stamps (interpolation and the finiteness test are per sample)
                a = _subset(assoc[name], np.isin(assoc[name].timestamps_ns, ref.timestamps_ns))
                if len(a):
                    out["trajectories"][name]["ate_rmse_on_reference_frames_m"] = ate(a).ate_rmse_m
            out["common_reference"] = common_reference
    else:
        for name, traj in trajectories.items():
            out["trajectories"][name] = {"n_poses": len(traj)}
    for name, lm in load_maps.items():
        if loads_gt:
            out["load_maps"][name] = load_map_errors(lm, loads_gt)
        else:
            out["load_maps"][name] = {"n_mapped": len(lm.loads)}
    return to_jsonable(out)


def _subset(a: Association, keep: np.ndarray) -> Association:
    """The rows `keep` (M,) bool of an association (n_outside_gt unchanged)."""
    return Association(
        a.name,
        a.timestamps_ns[keep],
        a.T_world_body_est[keep],
        a.T_world_body_gt[keep],
        a.covariances[keep] if a.covariances is not None else None,
        a.index_est[keep],
        a.n_outside_gt,
    )


def to_jsonable(obj):
    """Numpy scalars/arrays -> Python; NaN/inf -> None (strict JSON has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj


def write_metrics(path: Path, metrics: dict) -> Path:
    """Write `metrics.json` atomically (strict JSON, indented)."""
    path = Path(path)
    with atomic_open(path) as f:
        json.dump(to_jsonable(metrics), f, indent=1, allow_nan=False)
        f.write("\n")
    return path


GROUNDTRUTH_TUM_PIECE_ROWS = 65_536  # rows converted at a time (8 MB of poses), not the whole flight


def export_groundtruth_tum(gt, path: Path) -> Path:
    """Write the ground truth (`fusion.log.GroundTruth`) as a TUM file for evo, converted to
    poses GROUNDTRUTH_TUM_PIECE_ROWS rows at a time (the same text as converting them all)."""
    from fusion.log.files import write_tum_pieces

    t = np.asarray(gt.timestamps_ns, dtype=np.int64)
    rows = (slice(a, a + GROUNDTRUTH_TUM_PIECE_ROWS) for a in range(0, len(t), GROUNDTRUTH_TUM_PIECE_ROWS))
    write_tum_pieces(path, (Trajectory("groundtruth", t[r], gt.T_world_body_rows(r)) for r in rows))
    return Path(path)
