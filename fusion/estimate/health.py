"""Consistency monitor: a status per fused estimate, ok | degraded | diverged, with its reasons.

Works on any back end's output without ground truth (issue 8, "Health per estimator"), from:

1. The normalised innovation of each raw fix against the fused estimate at its frame,
   e_i = Log(T_fused^-1 T_raw) (6-dof, body frame, Pose3 order), NIS_i = e_i^T S_i^-1 e_i with
   S_i = P_fused + C_raw (the correlation of a fused estimate with the fix it used is ignored,
   which makes S too large and the test conservative).  Without raw covariances (the paper's
   estimator) the fix is position + yaw with HealthConfig.raw_sigma_*.
   In windows of `window_s`:
   - a fix is inconsistent when NIS_i > chi2(q, dim) (q = fix_quantile);
   - a window is *lost* when most of its fixes are inconsistent: the estimate, not the fixes, is
     wrong (a misread code moves one fix, a drifting estimate moves them all);
   - a window is *overconfident* when the mean NIS of its consistent fixes exceeds the
     chi-square bound chi2(q, n dim) / (n dim) of an n-fix window (Bar-Shalom, Li, Kirubarajan,
     "Estimation with Applications to Tracking and Navigation", 2001, sec. 5.4.2: the
     time-average NIS test).
2. The share of fixes the back end gated / rejected / removed, and (EKF) the share of updates at
   which it had to inflate its covariance.
3. Hits of the solver's iteration limit; re-initialisations (resets).
4. Covariance growth: the largest position 1-sigma of the fused estimate.
5. Coverage: the share of raw fixes whose frame has a fused estimate.

Status: DIVERGED when lost windows hold at least `diverged_share` of the fixes and at least
`diverged_run` of them come in a row (an estimate that lost the fixes for good, not one that
rightly ignored a short run of wrong ones, e.g. a misprinted code), the gated share reaches
`gated_diverged`, or a position sigma exceeds `sigma_diverged_m`; otherwise DEGRADED when any
test above fails its (lower) threshold; otherwise OK.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from scipy.stats import chi2

from fusion.errors import EstimationError
from fusion.geometry import inv_T, se3_log, so3_log, wrap_angle, yaw_of
from fusion.types import Trajectory

# stats keys of the back ends (smoother.py, ekf.py) that count gated / removed fixes
_GATED_KEYS = ("gated_updates", "gated_pose_factors", "removed_pose_factors")

__all__ = [
    "Health",
    "HealthConfig",
    "Status",
    "assess",
    "assess_result",
    "fix_nis",
    "tilt_disagreement",
    "tilt_nis",
]


class Status(str, Enum):
    """Health of one estimate (str-valued: `Status.OK == "ok"`)."""

    OK = "ok"
    DEGRADED = "degraded"
    DIVERGED = "diverged"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class HealthConfig:
    """Thresholds of `assess` (shares are fractions of the raw fixes)."""

    window_s: float = 2.0
    min_window_fixes: int = 5
    fix_quantile: float = 0.999  # per-fix and per-window chi-square quantile
    lost_share: float = 0.5  # inconsistent fixes that make a window lost
    inconsistent_degraded: float = 0.1  # inconsistent fixes over the flight -> degraded
    overconfident_share: float = 0.1  # overconfident windows (share of windows) -> degraded
    diverged_share: float = 0.1  # fixes in lost windows -> diverged, if also
    diverged_run: int = 2  # ... this many consecutive windows were lost
    gated_degraded: float = 0.1
    gated_diverged: float = 0.5
    inflated_degraded: float = 0.05
    sigma_degraded_m: float = 0.5
    sigma_diverged_m: float = 10.0
    coverage_degraded: float = 0.9
    max_sync_s: float = 0.002  # raw fix <-> fused frame matching
    raw_sigma_xyz_m: float = 0.02  # fixes without covariance (the paper's estimator)
    raw_sigma_yaw_rad: float = math.radians(1.0)


@dataclass
class Health:
    """Result of `assess`.  `reasons`: one short sentence per failed test (empty when OK)."""

    status: Status
    reasons: list[str] = field(default_factory=list)
    n_fixes: int = 0  # raw fixes with a fused estimate at their frame
    coverage: float = 1.0  # n_fixes / raw fixes
    inconsistent_share: float = 0.0  # fixes beyond the per-fix chi-square bound
    lost_share: float = 0.0  # fixes in lost windows
    lost_run: int = 0  # longest run of consecutive lost windows
    overconfident_windows: int = 0
    windows: int = 0
    window_nis: np.ndarray = field(default_factory=lambda: np.zeros(0))  # mean NIS / dim
    gated_fraction: float = 0.0
    inflated_fraction: float = 0.0
    iteration_limit_hits: int = 0
    resets: int = 0
    max_sigma_m: float = float("nan")

    @property
    def reason(self) -> str:
        return "; ".join(self.reasons) if self.reasons else "consistent with the raw fixes"

    def degrade(self, reason: str) -> None:
        """Add `reason`; an OK estimate becomes DEGRADED (a worse status stays)."""
        self.reasons.append(reason)
        if self.status == Status.OK:
            self.status = Status.DEGRADED

    def to_dict(self) -> dict:
        """JSON-ready summary (for metrics.json)."""
        return {
            "status": str(self.status),
            "reason": self.reason,
            "n_fixes": self.n_fixes,
            "coverage": self.coverage,
            "inconsistent_share": self.inconsistent_share,
            "lost_share": self.lost_share,
            "lost_run": self.lost_run,
            "overconfident_windows": self.overconfident_windows,
            "windows": self.windows,
            "gated_fraction": self.gated_fraction,
            "inflated_fraction": self.inflated_fraction,
            "iteration_limit_hits": self.iteration_limit_hits,
            "resets": self.resets,
            "max_sigma_m": self.max_sigma_m,
        }


def _match(t_fused: np.ndarray, t_raw: np.ndarray, max_sync_ns: int) -> np.ndarray:
    """Index of the fused sample at each raw time, -1 where none lies within max_sync_ns."""
    if len(t_fused) == 0:
        return np.full(len(t_raw), -1)
    j = np.clip(np.searchsorted(t_fused, t_raw), 0, len(t_fused) - 1)
    jl = np.clip(j - 1, 0, len(t_fused) - 1)
    j = np.where(np.abs(t_fused[jl] - t_raw) < np.abs(t_fused[j] - t_raw), jl, j)
    return np.where(np.abs(t_fused[j] - t_raw) <= max_sync_ns, j, -1)


def _position_yaw_jacobian(T: np.ndarray) -> np.ndarray:
    """(N, 4, 6): body-frame Pose3 perturbation [rx, ry, rz, tx, ty, tz] -> world position and
    yaw (first order; yaw ~ rz of a near-level frame)."""
    J = np.zeros((len(T), 4, 6))
    J[:, :3, 3:] = T[:, :3, :3]
    J[:, 3, 2] = 1.0
    return J


def fix_nis(
    fused: Trajectory, raw: Trajectory, config: HealthConfig | None = None, level_fixes: bool = False
):
    """Normalised innovation squared of each raw fix against the fused estimate at its frame.
    Returns (raw indices (M,), NIS (M,), dim): 6 with raw covariances, else 4 (position + yaw).
    `level_fixes`: the raw poses are level-frame poses (a gimbaled floor camera: PnP knows
    nothing of the airframe's roll and pitch), so only position and yaw are compared (dim 4)."""
    config = config or HealthConfig()
    t_f = np.asarray(fused.timestamps_ns, dtype=np.int64)
    t_r = np.asarray(raw.timestamps_ns, dtype=np.int64)
    j = _match(t_f, t_r, int(config.max_sync_s * 1e9))
    idx = np.flatnonzero(j >= 0)
    jf = j[idx]
    Tf, Tr = np.asarray(fused.T_world_body)[jf], np.asarray(raw.T_world_body)[idx]
    Pf = None if fused.covariances is None else np.asarray(fused.covariances)[jf]
    if level_fixes and raw.covariances is not None:
        e = np.column_stack(
            [Tr[:, :3, 3] - Tf[:, :3, 3], wrap_angle(yaw_of(Tr[:, :3, :3]) - yaw_of(Tf[:, :3, :3]))]
        )
        Jr = _position_yaw_jacobian(Tr)
        S = Jr @ np.asarray(raw.covariances)[idx] @ np.swapaxes(Jr, 1, 2)
        if Pf is not None:
            Jf = _position_yaw_jacobian(Tf)
            S = S + Jf @ Pf @ np.swapaxes(Jf, 1, 2)
        dim = 4
    elif raw.covariances is not None:
        e = se3_log(inv_T(Tf) @ Tr)
        S = np.asarray(raw.covariances)[idx] + (Pf if Pf is not None else 0.0)
        dim = 6
    else:
        e = np.column_stack(
            [Tr[:, :3, 3] - Tf[:, :3, 3], wrap_angle(yaw_of(Tr[:, :3, :3]) - yaw_of(Tf[:, :3, :3]))]
        )
        S = np.tile(
            np.diag([config.raw_sigma_xyz_m**2] * 3 + [config.raw_sigma_yaw_rad**2]), (len(idx), 1, 1)
        )
        if Pf is not None:
            Jf = _position_yaw_jacobian(Tf)
            S = S + Jf @ Pf @ np.swapaxes(Jf, 1, 2)
        dim = 4
    if len(idx) == 0:
        return idx, np.zeros(0), dim
    nis = np.einsum("ni,ni->n", e, np.linalg.solve(S, e[..., None])[..., 0])
    return idx, nis, dim


def assess(
    fused: Trajectory,
    raw: Trajectory,
    *,
    gated_fraction: float = 0.0,
    inflated_fraction: float = 0.0,
    iteration_limit_hits: int = 0,
    resets: int = 0,
    config: HealthConfig | None = None,
    level_fixes: bool = False,
) -> Health:
    """Health of `fused` judged against the raw fixes `raw` it was computed from (module
    docstring); `level_fixes`: as in fix_nis.  gated_fraction: share of raw fixes the back end
    gated / rejected / removed; inflated_fraction: share at which it inflated its own covariance
    (EKF); iteration_limit_hits: solves that stopped at their iteration limit; resets:
    re-initialisations."""
    config = config or HealthConfig()
    if len(raw) == 0:
        raise EstimationError("health: no raw fix to judge the fused estimate against")
    if len(fused) == 0:
        return Health(
            Status.DIVERGED,
            ["no fused estimate at all"],
            coverage=0.0,
            gated_fraction=gated_fraction,
            iteration_limit_hits=iteration_limit_hits,
            resets=resets,
        )
    idx, nis, dim = fix_nis(fused, raw, config, level_fixes)
    h = Health(
        Status.OK,
        n_fixes=len(idx),
        coverage=len(idx) / len(raw),
        gated_fraction=float(gated_fraction),
        inflated_fraction=float(inflated_fraction),
        iteration_limit_hits=int(iteration_limit_hits),
        resets=int(resets),
    )
    bound_fix = chi2.ppf(config.fix_quantile, dim)
    bad = nis > bound_fix
    h.inconsistent_share = float(bad.mean()) if len(bad) else 0.0

    # windows of window_s over the matched fixes
    t = np.asarray(raw.timestamps_ns, dtype=np.int64)[idx] * 1e-9
    lost_fixes = 0
    means = []
    run, last_lost = 0, None
    if len(t):
        edges = np.arange(t[0], t[-1] + config.window_s, config.window_s)
        w_of = np.searchsorted(edges, t, side="right") - 1
        for w in np.unique(w_of):
            sel = w_of == w
            n = int(sel.sum())
            if n < config.min_window_fixes:
                continue
            h.windows += 1
            if bad[sel].mean() > config.lost_share:
                lost_fixes += n
                run = run + 1 if last_lost == w - 1 else 1
                last_lost = w
                h.lost_run = max(h.lost_run, run)
                means.append(float(np.mean(nis[sel])) / dim)
                continue
            good = nis[sel & ~bad]
            means.append(float(np.mean(good)) / dim)
            if means[-1] > chi2.ppf(config.fix_quantile, len(good) * dim) / (len(good) * dim):
                h.overconfident_windows += 1
    h.window_nis = np.array(means)
    h.lost_share = lost_fixes / max(len(idx), 1)
    if fused.covariances is not None:
        sig = np.sqrt(
            np.maximum(np.diagonal(np.asarray(fused.covariances)[:, 3:, 3:], axis1=1, axis2=2), 0.0)
        )
        h.max_sigma_m = float(sig.max())

    diverged, degraded = [], []
    if h.lost_share >= config.diverged_share and h.lost_run >= config.diverged_run:
        diverged.append(
            f"lost the raw fixes in {100 * h.lost_share:.0f} % of them "
            f"(windowed innovation beyond chi-square {config.fix_quantile}, "
            f"{h.lost_run} windows in a row)"
        )
    elif h.lost_share > 0:
        degraded.append(
            f"lost the raw fixes in {100 * h.lost_share:.1f} % of them, for at most "
            f"{h.lost_run * config.window_s:.0f} s (wrong fixes, or a transient)"
        )
    if h.inconsistent_share >= config.inconsistent_degraded:
        degraded.append(
            f"{100 * h.inconsistent_share:.0f} % of the fixes disagree with the estimate "
            f"(beyond chi-square {config.fix_quantile})"
        )
    if h.windows and h.overconfident_windows / h.windows >= config.overconfident_share:
        degraded.append(
            f"overconfident: windowed NIS beyond its chi-square bound in "
            f"{h.overconfident_windows} of {h.windows} windows"
        )
    if h.gated_fraction >= config.gated_diverged:
        diverged.append(f"{100 * h.gated_fraction:.0f} % of the fixes gated or rejected")
    elif h.gated_fraction >= config.gated_degraded:
        degraded.append(f"{100 * h.gated_fraction:.0f} % of the fixes gated or rejected")
    if h.inflated_fraction >= config.inflated_degraded:
        degraded.append(
            f"covariance inflated at {100 * h.inflated_fraction:.0f} % of the fixes "
            "(the motion model disagrees with the fixes: faulty IMU?)"
        )
    if h.iteration_limit_hits:
        degraded.append(f"iteration limit hit {h.iteration_limit_hits} time(s)")
    if h.resets:
        degraded.append(f"re-initialised from the fixes {h.resets} time(s)")
    if np.isfinite(h.max_sigma_m):
        if h.max_sigma_m > config.sigma_diverged_m:
            diverged.append(f"position sigma grew to {h.max_sigma_m:.3g} m")
        elif h.max_sigma_m > config.sigma_degraded_m:
            degraded.append(f"position sigma grew to {h.max_sigma_m:.2f} m (dead reckoning)")
    if h.coverage < config.coverage_degraded:
        degraded.append(f"estimate at only {100 * h.coverage:.0f} % of the fixes' frames")
    h.reasons = diverged + degraded
    h.status = Status.DIVERGED if diverged else Status.DEGRADED if degraded else Status.OK
    return h


def assess_result(
    result,
    raw: Trajectory,
    *,
    max_iterations: int | None = None,
    config: HealthConfig | None = None,
    level_fixes: bool = False,
) -> Health:
    """`assess` of a back end's FusionResult, its inputs read from `result.stats`: gated fixes
    (gated_updates / gated_pose_factors), inflated updates, resets, and an iteration-limit hit
    when stats['iterations'] reached `max_iterations` (FusionConfig.lm_max_iterations) or
    stats['iteration_limit_hits'] says so."""
    st = result.stats or {}
    n = max(len(raw), 1)
    gated = next((st[k] for k in _GATED_KEYS if k in st), 0)
    hits = int(st.get("iteration_limit_hits", 0))
    if max_iterations is not None and "iterations" in st:
        hits += int(st["iterations"] >= max_iterations)
    resets = int(st.get("resets", 0))
    solve = getattr(result, "health", None)  # the smoothers' SolveHealth
    if solve is not None:
        hits += int(solve.iteration_limit_hits)
        resets += int(solve.resets)
    health = assess(
        result.trajectory,
        raw,
        gated_fraction=gated / n,
        inflated_fraction=st.get("inflated_updates", 0) / n,
        iteration_limit_hits=hits,
        resets=resets,
        config=config,
        level_fixes=level_fixes,
    )
    mode = str(getattr(solve, "mode", "fused"))
    if mode != "fused":
        # dead-reckoned from at most a few fixes, or fused without the IMU: usable, not ok
        health.degrade(f"solved in {mode.replace('_', ' ')} mode")
    return health


def tilt_nis(a: Trajectory, b: Trajectory, config: HealthConfig | None = None) -> np.ndarray:
    """(M,) roll / pitch disagreement of two fused estimates at their common frames:
    e = the first two components of Log(R_a^T R_b) (body frame of a), e^T (P_a + P_b)^-1 e over
    their [rx, ry] blocks.  Estimates of one flight from the same data are positively
    correlated, so Cov(a - b) <= P_a + P_b and the statistic is conservative."""
    config = config or HealthConfig()
    if a.covariances is None or b.covariances is None or not len(a) or not len(b):
        return np.zeros(0)
    j = _match(
        np.asarray(a.timestamps_ns, np.int64),
        np.asarray(b.timestamps_ns, np.int64),
        int(config.max_sync_s * 1e9),
    )
    ib = np.flatnonzero(j >= 0)
    ia = j[ib]
    Ra = np.asarray(a.T_world_body)[ia, :3, :3]
    Rb = np.asarray(b.T_world_body)[ib, :3, :3]
    e = so3_log(np.einsum("nji,njk->nik", Ra, Rb))[:, :2]
    S = np.asarray(a.covariances)[ia][:, :2, :2] + np.asarray(b.covariances)[ib][:, :2, :2]
    return np.einsum("ni,ni->n", e, np.linalg.solve(S, e[..., None])[..., 0])


def tilt_disagreement(
    trajectories: dict[str, Trajectory], config: HealthConfig | None = None
) -> dict[str, str]:
    """The fused estimates whose roll / pitch disagree with the others', with a reason each.

    For fixes that do not measure roll and pitch (a gimbaled floor camera's level-frame poses)
    the fix innovation (`assess`) cannot see a wrong tilt; the back ends, which infer it from the
    IMU against the fixes in different ways, can be compared.  Two disagree when `tilt_nis`
    exceeds chi2(fix_quantile, 2) at `inconsistent_degraded` of their common frames or more.
    With three or more estimates, one is named when it disagrees with every other (a majority
    says which); when every pair disagrees, or with two, all are named.  Measured on the
    sweep14 flights (BENCHMARKS.md, sweep14): the incremental smoother at 6-dof NEES 480 / 462 on
    two gimbaled flights disagreed at 91-99 % of the frames, every pair on the body-fixed demo
    and 800x600 flights at 0 %."""
    config = config or HealthConfig()
    names = [n for n, t in trajectories.items() if t.covariances is not None and len(t)]
    bound = chi2.ppf(config.fix_quantile, 2)
    share: dict[tuple[str, str], float] = {}
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            nis = tilt_nis(trajectories[a], trajectories[b], config)
            if len(nis):
                share[(a, b)] = share[(b, a)] = float(np.mean(nis > bound))
    out: dict[str, str] = {}
    for a in names:
        others = [b for b in names if b != a and (a, b) in share]
        bad = [b for b in others if share[(a, b)] >= config.inconsistent_degraded]
        if not others or not bad:
            continue
        everyone = all(
            share[(x, y)] >= config.inconsistent_degraded
            for x in names
            for y in names
            if x < y and (x, y) in share
        )
        if len(bad) == len(others) or everyone:
            worst = max(bad, key=lambda b: share[(a, b)])
            out[a] = (
                f"roll / pitch disagree with {', '.join(bad)} beyond their covariances at "
                f"{100 * share[(a, worst)]:.0f} % of the frames (the fixes do not observe them)"
            )
    return out
