"""Camera-IMU time offsets: estimated per camera, or fixed by hand, and applied to every output.

Convention (Kalibr's `timeshift_cam_imu`): t_imu = t_cam + offset, t_cam being the stamp the
log file holds.  The log readers already add Kalibr's shift (the seed, FlightLog.timeshift_ns)
to the camera stamps, so what is estimated here is the residual r around the seed; the
reported offset is seed + r.

Floor camera (cam0): profile of the batch smoother's cost over the offset.  Shifting the floor
frames (states and PnP poses) by delta against the IMU, the smoother's final error E(delta) =
0.5 * sum of squared whitened residuals (GTSAM's error: the negative log-likelihood up to a
constant, minimised over every state) is minimised by Newton steps on E from the seed: the
vertex of the parabola through E(r - h), E(r), E(r + h), until it moves less than `xatol_s`
(E is nearly quadratic in the offset, so from the seed this takes 1-3 steps, each solve close
to the optimum, where the smoother needs few iterations; bounded Brent, scipy's
minimize_scalar, over the whole search interval when the steps do not settle, or the parabola
opens downwards); sigma = 1 / sqrt(E''(r)) (the curvature of the negative log-likelihood: the
Cramér-Rao / Laplace approximation of the profile likelihood).  An offset
delta makes every PnP pose T(t + delta) disagree with the IMU's angular rate and specific force
(attitude against gravity), which is what E measures.  Long flights are profiled on the
`profile_window_s` window with the most rotation while fixes are seen.  The profile's solves
(and the whole-flight solve for the front camera) turn each IMU sub-interval's specific force to
its midpoint attitude (FusionConfig.imu_midpoint_attitude): GTSAM rotates it with the attitude at
the sub-interval's start, which put E's minimum ~0.22 ms late at 200 Hz (noise-free); the IMU
interpolated 4x had left 0.05 ms of it, at 4x the preintegration's cost.

Front camera (cam1): profile of the load-landmark factors' cost with the fused trajectory held
fixed.  A load sighting's camera-frame point p_cam (covariance C_cam) at time t + delta gives
p_world = T_world_cam(T(t + delta)) p_cam with covariance R C_cam R^T; with each landmark at its
information-weighted (Huber-IRLS) mean, the cost is sum rho(Mahalanobis distance): the landmark
factors' error minimised over the landmarks.  The drone's motion while a load is in view
(velocity and, through the lever arm, rotation) makes the sightings of one load disagree unless
delta is right.  Grid search, Brent, the same parabola refinement and curvature sigma.

An estimated residual is applied only when it is significant (|r| > `apply_sigmas` sigma and
> `min_apply_s`): a flight with no offset keeps its results unchanged.

The stamps the outputs keep are off the truth by the offset's error: an applied estimate by its
own error (variance sigma^2), a significant residual r left unapplied (|r| below min_apply_s)
by all of it (r^2 + sigma^2); a residual within apply_sigmas sigma is taken as no offset (0:
the unbiased max(r^2 - sigma^2, 0) was tried: it widened 6 of 23 sweep flights with no offset
by their estimate's noise, BENCHMARKS.md, sweep14).  A pose stamped delta off is T(t + delta) =
T(t) Exp(delta xi), xi the body twist, so every floor pose (PnP and fused) gains the consider
covariance E[delta^2] xi xi^T (`add_stamp_covariance`), after the health (the error is common
to the fixes and the estimate): common to every frame, so no back end may average it down
(like the removed corner bias, cornerbias.py).  Without it a
-12 ms offset recovered as -12.08 +- 0.11 ms left PnP / smoother 6-dof NEES 11.8 / 24.9 (the
truth read 0.05 ms later: 5.2 / 13.9): PnP's rotation sigmas are 0.02-0.3 mrad.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import minimize_scalar

from fusion.camera import CameraModel
from fusion.errors import EstimationError
from fusion.estimate.common import FusionConfig
from fusion.estimate.correlation import correlation_time, frame_indices, group_frame_keys
from fusion.estimate.smoother import SolveReuse, smooth
from fusion.geometry import PoseInterpolator, inv_T, se3_log
from fusion.log.euroc import FlightLog, ImuData, VelocityData
from fusion.types import CameraRole, Choice, LoadObservation, Trajectory, role_name

log = logging.getLogger(__name__)

NS_PER_S = 1e9
MS_PER_S = 1e3


class OffsetSource(Choice):
    """Where a camera's time offset comes from."""

    ESTIMATED = "estimated"  # profiled here (around the seed)
    FIXED = "fixed"  # --time-offset-ms
    SEED = "seed"  # the log's own (Kalibr timeshift_cam_imu, else 0): could not be estimated


@dataclass
class TimeOffsetConfig:
    """Every tuning number of the time-offset estimation.

    Search: residual offsets within +-`search_half_width_s` of the seed; Brent stops at
    `xatol_s`; the curvature (sigma) and parabola refinement use steps of `curvature_step_s`
    (floor) and `front_curvature_step_s` (front); the front cost is first scanned on a grid of
    `front_grid_step_s`.  Flights longer than `profile_window_s` are profiled (floor) on the
    window of that length with the most rotation at the fixes.  The front profile needs at least
    `min_load_sightings` sightings of loads seen at least twice; its Huber threshold is FusionConfig's
    for a 3-d point, `irls_iterations` reweightings.  An estimate is applied when |r| exceeds
    both `apply_sigmas` sigma and `min_apply_s`."""

    search_half_width_s: float = 0.05
    xatol_s: float = 5e-5
    curvature_step_s: float = 2e-3
    front_curvature_step_s: float = 1e-3
    front_grid_step_s: float = 2e-3
    profile_window_s: float = 30.0
    min_load_sightings: int = 10
    irls_iterations: int = 3
    apply_sigmas: float = 3.0
    min_apply_s: float = 5e-4
    # Newton steps of the floor profile before it falls back to Brent (_newton_minimum)
    newton_steps: int = 6
    # the smoother's relative tolerance while profiling: tight enough that E's solve noise is
    # far below its change over xatol_s
    profile_lm_relative_tol: float = 1e-9
    # the cameras' clock rates (ClockDrift): checked on flights spanning at least this long,
    # each third profiled on its best profile_window_s window, or whole when shorter (three
    # profile windows, 90 s, had left 40 ppm unchecked on a 45 s flight: its ends 0.9 ms off)
    check_drift: bool = True
    drift_min_span_s: float = 30.0
    # profiles made again on the corrected stamps after a rate is applied: a window's estimate
    # belongs to where its fixes see motion, not to its centre, which the first line misreads
    # while the offset still drifts across the window (100 ppm over 100 s: 108 +- 2 ppm, the
    # offset at the middle 0.7 ms off; BENCHMARKS.md, twenty-second session)
    drift_refinements: int = 1
    # per-frame stamp noise of the floor camera (StampJitter): a likelihood-ratio statistic
    # beyond this (chi2_1 at 0.001) and a sigma beyond jitter_min_s make it significant
    jitter_lr_threshold: float = 10.83
    jitter_min_s: float = 2e-4
    jitter_iterations: int = 4

    @property
    def profile_margin_s(self) -> float:
        """How far inside the IMU's span the floor profile's window keeps (no shifted frame
        may leave it): the search width, a curvature step and the tolerance."""
        return self.search_half_width_s + self.curvature_step_s + self.xatol_s


@dataclass
class StampJitter:
    """White noise on a camera's stamps, sigma_s per frame (a driver that stamps a
    frame on arrival, after a variable transfer latency).  A stamp off by d puts the PnP pose at
    T(t + d) = T(t) Exp(d xi), xi the body twist, so each fix's error gains d xi along the
    motion: PnP poses of 0.1 mm sigma read 3 mm off at 1 m/s and 3 ms.  Estimated by maximum
    likelihood from the floor profile's fixes against its smoothed trajectory (residual e_k,
    covariance C_k, twist xi_k): e_k ~ N(0, C_k + s xi_k xi_k^T), s = sigma^2; `lr` the
    likelihood-ratio statistic against s = 0, judged as lr / `correlation_time` (`_jitter_ml`).
    Significant (TimeOffsetConfig.jitter_*): the
    fixes' covariances take s xi xi^T before any back end (white per frame, it is measurement
    noise, not a common error).  The front camera's likewise from its load sightings against
    their landmarks (`estimate_front_offset`), widening the sightings (`widen_sightings`)."""

    sigma_s: float
    lr: float
    n: int
    significant: bool = False
    correlation_time: float = 1.0  # the residuals' integrated correlation time (frames)

    def as_dict(self) -> dict:
        return {
            "sigma_ms": self.sigma_s * MS_PER_S,
            "lr": self.lr,
            "fixes": self.n,
            "significant": self.significant,
            "correlation_time": self.correlation_time,
        }

    def describe(self) -> str:
        used = "widening the fixes / sightings" if self.significant else "not significant"
        return f"stamp jitter {self.sigma_s * MS_PER_S:.2f} ms ({used})"


def estimate_stamp_jitter(
    raw: Trajectory, smoothed: Trajectory, config: TimeOffsetConfig | None = None
) -> StampJitter | None:
    """StampJitter of the fixes `raw` (their covariances) against `smoothed` (the same clock):
    None without covariances or with fewer than 10 fixes inside the smoothed span."""
    config = config or TimeOffsetConfig()
    if raw.covariances is None or len(smoothed) < 2:
        return None
    ts = smoothed.timestamps_ns
    inside = (raw.timestamps_ns >= ts[0]) & (raw.timestamps_ns <= ts[-1])
    if inside.sum() < 10:
        return None
    t = raw.timestamps_ns[inside]
    T_s = PoseInterpolator(ts, smoothed.T_world_body)(t)
    e = se3_log(inv_T(T_s) @ raw.T_world_body[inside])
    twist_all = body_twists(smoothed)
    xi = np.stack([np.interp(t, ts, twist_all[:, a]) for a in range(6)], axis=1)
    return _jitter_ml(e, np.asarray(raw.covariances)[inside], xi, config, slice(3, 6), frame_indices(t))


JITTER_GATE_M = 0.3
"""A residual farther than this (m) is no stamp jitter's (a stamp error within the offsets'
+-50 ms search moves a point at 3 m/s by 0.15 m): a wrong fix or a duplicated label, left out of
the jitter's estimate (a duplicated label 2 m away read 46 s of jitter)."""


def _jitter_ml(
    e: np.ndarray,
    C: np.ndarray,
    u: np.ndarray,
    config: TimeOffsetConfig,
    position: slice = slice(None),
    keys: np.ndarray | None = None,
) -> StampJitter:
    """Maximum likelihood of s = sigma^2 in e_k ~ N(0, k C_k + s u_k u_k^T) (residuals e (n, d),
    covariances C (n, d, d), the residual's rate of change with the stamp u (n, d)), k a free
    scale of the stated covariances: only an excess along u reads as jitter, not covariances
    stated too small in every direction (the sample flight's front sightings, exact stamps, read
    2.1 ms with k held at 1).  With g = s / k, by the determinant lemma
    -2 log L = sum d log k + log(1 + g q) + (b - g a^2 / (1 + g q)) / k, q = u^T C^-1 u,
    a = u^T C^-1 e, b = e^T C^-1 e, and k's optimum in closed form for each g; the likelihood
    ratio against g = 0 (k free) for its significance, which also needs sigma inside the offsets'
    search width.  Residuals whose `position` part is beyond JITTER_GATE_M are left out.

    The ratio is judged as lr / tau, tau the whitened residuals' integrated correlation time
    over frames (`keys`: correlation.group_frame_keys, a residual l frames after another of the
    same load or code at key + l; correlation.correlation_time, Geyer's estimator with its gate,
    as for the front mount; tau = 1 when they are white or without keys): the statistic adds n
    independent terms' worth of evidence, and residuals that persist over frames are worth
    n / tau of them.  Without it the load sightings' errors, correlated over ~20 frames
    (tau ~5, BENCHMARKS.md, twenty-ninth session), read as jitter on flights whose stamps are
    exact: the 10-minute benchmark flight's front camera 2.05 ms at lr 158."""
    keep = np.linalg.norm(e[:, position], axis=1) <= JITTER_GATE_M
    e, C, u = e[keep], C[keep], u[keep]
    if len(e) < 10:
        return StampJitter(0.0, 0.0, len(e), False)
    Ci = np.linalg.inv(C)
    q = np.einsum("ni,nij,nj->n", u, Ci, u)
    a = np.einsum("ni,nij,nj->n", u, Ci, e)
    b = np.einsum("ni,nij,nj->n", e, Ci, e)
    nd = e.size

    def scale(g: float) -> float:
        return max(float(np.sum(b - g * a**2 / (1.0 + g * q))) / nd, 1e-300)

    def minus2loglik(g: float) -> float:  # k at its optimum, up to the terms without g
        return nd * math.log(scale(g)) + float(np.sum(np.log1p(g * q)))

    hi = config.search_half_width_s
    res = minimize_scalar(
        lambda x: minus2loglik(x * x), bounds=(0.0, hi), method="bounded", options={"xatol": 1e-6}
    )
    g = float(res.x) ** 2
    lr = max(0.0, minus2loglik(0.0) - minus2loglik(g))
    sigma = math.sqrt(g * scale(g))
    tau = 1.0
    if keys is not None:
        try:
            white = np.linalg.solve(np.linalg.cholesky(C), e[..., None])[..., 0]  # C = L L^T: L^-1 e
        except np.linalg.LinAlgError:  # a covariance not positive definite: its diagonal's scale
            white = e / np.sqrt(np.maximum(np.einsum("nii->ni", C), 1e-300))
        tau = correlation_time(np.asarray(keys)[keep], white)
    significant = (
        lr / tau > config.jitter_lr_threshold and config.jitter_min_s < sigma < config.search_half_width_s
    )
    return StampJitter(sigma, lr, len(e), bool(significant), tau)


@dataclass
class ClockDrift:
    """A camera's clock rate against the IMU's: the offset grows as r(t) = r(t_ref) +
    rate (t - t_ref), t the log's stamp.  A camera stamping with its own oscillator drifts by
    its frequency error (tens of ppm: 20 ppm is 12 ms over a 10-minute flight, 2.4 cm at
    2 m/s), which one offset per flight cannot hold.  Estimated from the camera's offset in
    parts of the flight (`points`: time ns, residual s, sigma s; estimate_floor_drift,
    estimate_front_drift); applied, like an offset, when significant (|rate| beyond
    apply_sigmas sigma and the drift over the flight beyond min_apply_s): the camera's stamps
    are then corrected by rate (t - t_ref) before its offset is taken."""

    rate: float  # s of offset per s of camera time
    sigma: float | None
    t_ref_ns: int  # the flight's middle: the correction is 0 there
    span_s: float  # the flight's floor stamps' span
    points: list[tuple[int, float, float | None]] = field(default_factory=list)
    applied: bool = False
    offset_s: float = 0.0  # the fitted line's residual offset at t_ref
    offset_sigma_s: float | None = None

    def correction_ns(self, t_ns: np.ndarray) -> np.ndarray:
        """ns to add to stamps `t_ns` (log clock) for the rate: 0 unless applied."""
        t = np.asarray(t_ns, dtype=np.int64)
        if not self.applied:
            return np.zeros_like(t)
        return np.round(self.rate * (t - self.t_ref_ns).astype(float)).astype(np.int64)

    @property
    def stamp_variance_s2(self) -> float:
        """E[stamp error^2] over the flight that the rate leaves: E[rate error^2] span^2 / 12 (the
        mean of (t - t_ref)^2 over a flight centred on t_ref).  The rate's error is sigma^2 when
        applied; when left unapplied (below 3 sigma) it is the whole rate, whose square has the
        unbiased estimate max(rate^2 - sigma^2, 0): 40 ppm read 33 +- 19 on a 32 s flight and,
        without the term, put every pose NEES at 17-19; rate^2 + sigma^2 instead also widened
        the flights with no drift (BENCHMARKS.md, twenty-eighth session)."""
        s2 = (self.sigma or 0.0) ** 2
        rate_s2 = s2 if self.applied else max(self.rate**2 - s2, 0.0)
        return rate_s2 * self.span_s**2 / 12.0

    def as_dict(self) -> dict:
        return {
            "rate_ppm": self.rate * 1e6,
            "sigma_ppm": None if self.sigma is None else self.sigma * 1e6,
            "applied": self.applied,
            "over_flight_ms": self.rate * self.span_s * MS_PER_S,
            "windows": [
                {
                    "t_s": t / NS_PER_S,
                    "residual_ms": r * MS_PER_S,
                    "sigma_ms": None if sg is None else sg * MS_PER_S,
                }
                for t, r, sg in self.points
            ],
        }

    def describe(self) -> str:
        sig = "" if self.sigma is None else f" ± {self.sigma * 1e6:.1f}"
        used = "applied" if self.applied else "not applied (not significant)"
        return (
            f"clock rate {self.rate * 1e6:+.1f}{sig} ppm ({self.rate * self.span_s * MS_PER_S:+.2f} ms over "
            f"the flight); {used}"
        )


@dataclass
class FixedCheck:
    """A fixed offset (--time-offset-ms) against the data: the camera's profile on its stamps
    shifted by the fixed offset finds the residual `residual_s` +- `sigma_s` (0 when the fixed
    value is right); `at_bound`: beyond the profile's search.  A fixed offset was never checked:
    one 60 ms off gave the audit's flight 3.6 cm, every health ok and no warning (thirty-second
    session)."""

    residual_s: float
    sigma_s: float | None
    at_bound: bool = False

    def disagrees(self, config: TimeOffsetConfig | None = None) -> bool:
        """The data put the offset elsewhere: beyond the search, or a residual beyond
        apply_sigmas sigma and min_apply_s (the rule an estimate is applied by)."""
        return self.at_bound or _significant(self.residual_s, self.sigma_s, config or TimeOffsetConfig())

    def as_dict(self) -> dict:
        return {
            "residual_ms": self.residual_s * MS_PER_S,
            "sigma_ms": None if self.sigma_s is None else self.sigma_s * MS_PER_S,
            "at_search_bound": self.at_bound,
            "disagrees": self.disagrees(),
        }


@dataclass
class CameraOffset:
    """One camera's offset (s): t_imu = t_cam + offset_s, t_cam the log file's stamp."""

    camera: str  # CameraRole value
    offset_s: float  # estimated / fixed / seed value, seed included
    sigma_s: float | None  # 1-sigma of an estimate (None: fixed or seed)
    source: OffsetSource
    seed_s: float = 0.0  # Kalibr's timeshift_cam_imu the log reader already added
    applied_s: float = 0.0  # shift added to the reader's stamps in this run
    note: str = ""
    evaluations: int = 0  # cost evaluations of the profile
    # the significance rule the estimate was judged by (TimeOffsetConfig.apply_sigmas; None:
    # the default's), for stamp_variance_s2
    apply_sigmas: float | None = None
    drift: ClockDrift | None = None  # the camera's clock rate, when checked
    jitter: StampJitter | None = None  # the camera's stamp noise, when estimated
    at_search_bound: bool = False  # the profile's minimum at its bound: the offset may be larger
    # a fixed offset checked against the data (FixedCheck), None when not fixed or not checkable
    check: FixedCheck | None = None

    @property
    def effective_s(self) -> float:
        """The offset the outputs are stamped with: seed + applied."""
        return self.seed_s + self.applied_s

    @property
    def stamp_variance_s2(self) -> float:
        """E[(true - effective offset)^2], s^2: sigma^2 for an applied estimate; r^2 + sigma^2
        for a residual r beyond TimeOffsetConfig.apply_sigmas sigma left unapplied (below
        min_apply_s: the stamps keep all of it); 0 for one within it (taken as no offset, so
        such a flight keeps its results bit for bit), for a fixed or a seed offset."""
        rate = 0.0 if self.drift is None else self.drift.stamp_variance_s2
        if self.source != OffsetSource.ESTIMATED or self.sigma_s is None:
            return rate
        left = self.offset_s - self.effective_s
        k = TimeOffsetConfig().apply_sigmas if self.apply_sigmas is None else self.apply_sigmas
        if self.applied_s or abs(left) > k * self.sigma_s:
            return self.sigma_s**2 + left**2 + rate
        return rate

    def as_dict(self) -> dict:
        return {
            "camera": self.camera,
            "offset_ms": self.offset_s * MS_PER_S,
            "sigma_ms": None if self.sigma_s is None else self.sigma_s * MS_PER_S,
            "source": str(self.source),
            "seed_ms": self.seed_s * MS_PER_S,
            "applied_ms": self.applied_s * MS_PER_S,
            "effective_ms": self.effective_s * MS_PER_S,
            "evaluations": self.evaluations,
            "note": self.note,
            "stamp_sigma_ms": math.sqrt(self.stamp_variance_s2) * MS_PER_S,
            "clock_drift": None if self.drift is None else self.drift.as_dict(),
            "stamp_jitter": None if self.jitter is None else self.jitter.as_dict(),
            "at_search_bound": self.at_search_bound,
            "fixed_check": None if self.check is None else self.check.as_dict(),
        }

    def describe(self) -> str:
        """One line: `cam1 (front): +15.02 ± 0.31 ms, estimated (seed 0.00 ms); applied`."""
        role = role_name(self.camera)
        sig = f" ± {self.sigma_s * MS_PER_S:.2f}" if self.sigma_s is not None else ""
        seed = f" (seed {self.seed_s * MS_PER_S:+.2f} ms)" if self.seed_s else ""
        if self.source == OffsetSource.ESTIMATED:
            used = "applied" if self.applied_s else "not applied (not significant)"
            if self.at_search_bound:  # not a measurement: the cost still falls beyond the bound
                used = "applied up to the bound" if self.applied_s else "not applied"
        elif self.source == OffsetSource.FIXED:
            used = "applied"
        else:
            used = "log stamps used"
        note = f"; {self.note}" if self.note else ""
        clock = "" if self.drift is None else f"; {self.drift.describe()}"
        if self.jitter is not None and self.jitter.significant:
            clock += f"; {self.jitter.describe()}"
        return (
            f"time offset {self.camera} ({role}): {self.offset_s * MS_PER_S:+.2f}{sig} ms, "
            f"{self.source}{seed}; {used}{clock}{note}"
        )


@dataclass
class TimeOffsets:
    """The offsets of a run's cameras (RunResult.time_offsets, metrics.json `time_offsets`)."""

    cameras: dict[str, CameraOffset] = field(default_factory=dict)

    def shift_ns(self, camera: str) -> int:
        """ns to add to the reader's stamps of `camera` (0 for an unknown camera), the clock
        rate's correction aside (`stamps`)."""
        c = self.cameras.get(camera)
        return 0 if c is None else int(round(c.applied_s * NS_PER_S))

    def stamps(self, camera: str, t_ns) -> np.ndarray:
        """The reader's stamps `t_ns` of `camera` in the IMU clock: the applied shift, and the
        applied clock rate's correction (ClockDrift) at each stamp."""
        t = np.asarray(t_ns, dtype=np.int64)
        c = self.cameras.get(camera)
        drift = None if c is None else c.drift
        return t + self.shift_ns(camera) + (0 if drift is None else drift.correction_ns(t))

    def drift_applied(self, camera: str) -> bool:
        c = self.cameras.get(camera)
        return c is not None and c.drift is not None and c.drift.applied

    @property
    def any_applied(self) -> bool:
        return any(self.shift_ns(name) != 0 or self.drift_applied(name) for name in self.cameras)

    def as_dict(self) -> dict:
        return {name: c.as_dict() for name, c in self.cameras.items()}

    def lines(self) -> list[str]:
        return [c.describe() for c in self.cameras.values()]


STAMP_TWIST_MAX_GAP_S = 0.2
"""Neighbouring poses farther apart than this do not give a pose's twist (`body_twists`)."""


def body_twists(traj: Trajectory, max_gap_s: float = STAMP_TWIST_MAX_GAP_S) -> np.ndarray:
    """(N, 6) body twist [omega (rad/s), v (m/s)] in Pose3 order at each pose of `traj`:
    Log(T_a^-1 T_b) / (t_b - t_a) over its neighbours a, b (central, else one-sided, within
    `max_gap_s`); zero for a pose with neither neighbour."""
    n = len(traj)
    out = np.zeros((n, 6))
    if n < 2:
        return out
    t = np.asarray(traj.timestamps_ns, dtype=np.int64) * 1e-9
    T = np.asarray(traj.T_world_body, dtype=float)
    dt = np.diff(t)
    near = dt <= max_gap_s  # (n - 1,) pose k and k + 1 are neighbours
    prev = np.r_[False, near]
    nxt = np.r_[near, False]
    a = np.where(prev, np.arange(n) - 1, np.arange(n))
    b = np.where(nxt, np.arange(n) + 1, np.arange(n))
    ok = a != b
    xi = se3_log(np.einsum("nij,njk->nik", inv_T(T[a[ok]]), T[b[ok]]))
    out[ok] = xi / (t[b[ok]] - t[a[ok]])[:, None]
    return out


def add_stamp_covariance(traj: Trajectory, variance_s2: float) -> Trajectory:
    """`traj` with each pose's covariance plus variance_s2 xi xi^T, xi its body twist
    (`body_twists`): the pose's error from a stamp error of that variance (module docstring).
    Unchanged without covariances or with a zero variance."""
    if traj.covariances is None or not len(traj) or not variance_s2 > 0.0:
        return traj
    xi = body_twists(traj)
    covs = np.asarray(traj.covariances) + variance_s2 * np.einsum("ni,nj->nij", xi, xi)
    return Trajectory(traj.name, traj.timestamps_ns, traj.T_world_body, covs)


# =========================================================================== options


def parse_time_offsets_ms(text: str) -> dict[str, float]:
    """`--time-offset-ms`: "5" (both cameras) or "cam0=5,cam1=-3" (either may be left out: it
    is then estimated) -> {camera: offset in s}.  ValueError with the reason otherwise."""
    names = [r.value for r in CameraRole]
    text = text.strip()
    if not text:
        raise ValueError("empty value; expected MS or cam0=MS,cam1=MS")
    if "=" not in text:
        v = _ms(text)
        return {n: v for n in names}
    out: dict[str, float] = {}
    for part in text.split(","):
        key, sep, val = part.partition("=")
        key = key.strip()
        if not sep or key not in names:
            raise ValueError(f"{part.strip()!r}: expected cam0=MS or cam1=MS")
        if key in out:
            raise ValueError(f"{key} given twice")
        out[key] = _ms(val)
    return out


def _ms(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{text.strip()!r} is not a number of milliseconds") from None
    if not math.isfinite(v):
        raise ValueError(f"{text.strip()!r} is not a finite number of milliseconds")
    return v / MS_PER_S


# =========================================================================== floor camera


def _profile_minimum(
    cost: Callable[[float], float], lo: float, hi: float, xatol: float, step: float
) -> tuple[float, float | None, float]:
    """Minimum of a 1-d cost on [lo, hi] (bounded Brent), refined by the vertex of the parabola
    through cost(r - step), cost(r), cost(r + step); sigma = 1 / sqrt(curvature) (None when
    the cost is not convex there).  Returns (r, sigma, cost at r)."""
    res = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
    r = float(res.x)
    e0, ep, em = cost(r), cost(r + step), cost(r - step)
    curv = (ep - 2.0 * e0 + em) / step**2
    if not (curv > 0 and math.isfinite(curv)):
        return r, None, e0
    vertex = r - step * (ep - em) / (2.0 * (ep - 2.0 * e0 + em))
    if abs(vertex - r) < step:
        r = float(vertex)
    return r, 1.0 / math.sqrt(curv), e0


def _newton_minimum(
    cost: Callable[[float], float], lo: float, hi: float, xatol: float, step: float, max_steps: int
) -> tuple[float, float | None, float] | None:
    """Minimum of a 1-d cost on [lo, hi] by Newton steps from 0 (the seed): r <- the vertex of
    the parabola through cost(r - step), cost(r), cost(r + step) (clipped to [lo, hi]) until
    it moves less than `xatol`; sigma = 1 / sqrt(curvature) there.  Returns (r, sigma, cost at
    the last centre), as _profile_minimum, or None when the parabola opens downwards, is not
    finite, or `max_steps` steps do not settle (the caller falls back to Brent)."""
    r = min(max(0.0, lo), hi)
    for _ in range(max_steps):
        e0, ep, em = cost(r), cost(r + step), cost(r - step)
        denom = ep - 2.0 * e0 + em
        curv = denom / step**2
        if not (curv > 0 and math.isfinite(curv)):
            return None
        vertex = min(max(r - step * (ep - em) / (2.0 * denom), lo), hi)
        if abs(vertex - r) < xatol:
            return float(vertex), 1.0 / math.sqrt(curv), e0
        r = float(vertex)
    return None


def _inflate(sigma: float | None, e_min: float, dof: int) -> float | None:
    """sigma scaled by sqrt(reduced chi-square) when the fit is worse than its noise model
    says (2 E_min / dof > 1): the usual correction of a curvature sigma for an underestimated
    measurement noise (e.g. Press et al., Numerical Recipes, 15.1)."""
    if sigma is None or dof <= 0:
        return sigma
    return sigma * math.sqrt(max(1.0, 2.0 * e_min / dof))


def _shift_traj(traj: Trajectory, d_ns: int) -> Trajectory:
    return Trajectory(traj.name, traj.timestamps_ns + d_ns, traj.T_world_body, traj.covariances)


def profile_window(
    frame_t: np.ndarray, raw: Trajectory, imu: ImuData | None, window_s: float, margin_s: float
) -> tuple[int, int]:
    """[t0, t1] ns of the floor profile: the whole flight inside the IMU's span (less
    `margin_s`, so that no shifted frame leaves it), or, when longer than `window_s`, the
    window of that length whose fixes see the most rotation (sum of |gyro|^2 at the fixes)."""
    t0, t1 = int(frame_t[0]), int(frame_t[-1])
    if imu is not None and len(imu.timestamps_ns):
        margin = int(margin_s * NS_PER_S)
        t0 = max(t0, int(imu.timestamps_ns[0]) + margin)
        t1 = min(t1, int(imu.timestamps_ns[-1]) - margin)
    w = int(window_s * NS_PER_S)
    if t1 - t0 <= w:
        return t0, t1
    tr = raw.timestamps_ns[(raw.timestamps_ns >= t0) & (raw.timestamps_ns <= t1)]
    if imu is None or len(tr) == 0:
        return t0, t0 + w
    gyro = np.stack([np.interp(tr, imu.timestamps_ns, imu.gyro_rad_s[:, a]) for a in range(3)], axis=1)
    score = np.r_[0.0, np.cumsum(np.sum(gyro**2, axis=1))]
    starts = np.clip(tr, t0, t1 - w)
    i0 = np.searchsorted(tr, starts)
    i1 = np.searchsorted(tr, starts + w, side="right")
    best = int(np.argmax(score[i1] - score[i0]))
    return int(starts[best]), int(starts[best]) + w


@dataclass
class FloorProfile:
    """Result of the floor-camera profile (residual around the seed)."""

    residual_s: float
    sigma_s: float | None
    trajectory: Trajectory | None  # smoothed at the estimate, IMU clock (the front profile's)
    evaluations: int
    note: str = ""
    whole_flight: bool = True  # False: profiled on a window of the flight (profile_window_s)
    window_ns: tuple[int, int] = (0, 0)  # the stamps profiled (log clock)
    jitter: StampJitter | None = None  # the fixes' stamp noise at the estimate
    at_bound: bool = False  # the minimum is at the search bound: the offset may be larger


def estimate_floor_offset(
    frame_t: np.ndarray,
    imu: ImuData | None,
    raw: Trajectory,
    velocity: VelocityData | None = None,
    floor_camera: CameraModel | None = None,
    config: TimeOffsetConfig | None = None,
    fusion_config: FusionConfig | None = None,
    jitter: bool = True,
) -> FloorProfile:
    """Residual offset of the floor camera: frames `frame_t` and PnP poses `raw` (the log's
    stamps) against the IMU / velocity, by the smoother's cost profile (module docstring), and
    with `jitter` the fixes' stamp jitter at the estimate (`_profile_jitter`: more smoother
    solves when it is significant; the clock-rate profiles of a flight's parts skip it).
    EstimationError when neither IMU nor velocity or no raw pose lies in the profile window."""
    config = config or TimeOffsetConfig()
    fusion_config = fusion_config or FusionConfig()
    if imu is None and velocity is None:
        raise EstimationError("neither IMU nor velocity: the floor camera's offset cannot be estimated")
    S = config.search_half_width_s
    t0, t1 = profile_window(frame_t, raw, imu, config.profile_window_s, config.profile_margin_s)
    fsel = (frame_t >= t0) & (frame_t <= t1)
    rsel = (raw.timestamps_ns >= t0) & (raw.timestamps_ns <= t1)
    if rsel.sum() < 2:
        raise EstimationError("fewer than two floor-code fixes in the profile window")
    frames = frame_t[fsel]
    sub = Trajectory(
        raw.name,
        raw.timestamps_ns[rsel],
        raw.T_world_body[rsel],
        None if raw.covariances is None else raw.covariances[rsel],
    )
    pcfg = replace(
        fusion_config,
        compute_covariances=False,
        outlier_gate=None,
        reject_disagreeing_imu=False,
        lm_relative_tol=config.profile_lm_relative_tol,
        tight=False,
        noise_scale_iterations=0,
        check_noise=False,
        imu_midpoint_attitude=True,
    )
    cache: dict[int, float] = {}
    trajs: dict[int, Trajectory] = {}
    n_fixes: dict[int, int] = {}
    # each solve starts from the previous one's solution (frames shifted by a few ms: the poses
    # move by ~speed x shift), not from the PnP poses: fewer iterations to the same optimum
    reuse = SolveReuse()

    def cost_ms(r_ms: float) -> float:
        d = int(round(r_ms * 1e6))
        if d not in cache:
            res = smooth(
                frames + d,
                imu,
                _shift_traj(sub, d),
                None,
                velocity=velocity,
                config=pcfg,
                floor_camera=floor_camera,
                reuse=reuse,
            )
            cache[d] = float(res.stats["final_error"])
            trajs[d] = res.trajectory
            n_fixes[d] = int(res.stats.get("pose_factors", 0))
        return cache[d]

    S_ms = S * MS_PER_S
    args = (cost_ms, -S_ms, S_ms, config.xatol_s * MS_PER_S, config.curvature_step_s * MS_PER_S)
    found = _newton_minimum(*args, config.newton_steps)
    if found is None:
        log.info("floor camera time offset: Newton steps did not settle; bounded Brent instead")
        found = _profile_minimum(*args)
    r_ms, sig_ms, e_min = found
    at_bound = abs(r_ms) > S_ms - 2 * config.curvature_step_s * MS_PER_S
    note = _at_bound_note(S_ms) if at_bound else ""
    d_best = min(trajs, key=lambda d: abs(d - r_ms * 1e6))
    # residual degrees of freedom: the fixes' dimensions (the IMU's are taken up by the states)
    dim = 6 if sub.covariances is not None else 4
    sig_ms = _inflate(sig_ms, e_min, dim * n_fixes[d_best] - 1)
    log.info("floor camera time offset: residual %+.3f ms (%d smoother solves)", r_ms, len(cache))
    return FloorProfile(
        r_ms / MS_PER_S,
        None if sig_ms is None else sig_ms / MS_PER_S,
        trajs[d_best],
        len(cache),
        note,
        whole_flight=(t1 - t0) < int(config.profile_window_s * NS_PER_S),
        window_ns=(int(t0), int(t1)),
        at_bound=at_bound,
        jitter=_profile_jitter(
            frames, imu, _shift_traj(sub, d_best), trajs[d_best], d_best, velocity, floor_camera, pcfg, config
        )
        if jitter
        else None,
    )


def _at_bound_note(search_ms: float) -> str:
    return f"at the search bound (+-{search_ms:.0f} ms around the seed): the offset may be larger"


def _profile_jitter(
    frames: np.ndarray,
    imu: ImuData | None,
    fixes: Trajectory,
    smoothed: Trajectory,
    d_ns: int,
    velocity: VelocityData | None,
    floor_camera: CameraModel | None,
    pcfg: FusionConfig,
    config: TimeOffsetConfig,
) -> StampJitter | None:
    """estimate_stamp_jitter of the profile's fixes (shifted by the estimate d_ns) against its
    smoothed trajectory; when significant, solved again with the fixes widened by the jitter
    found and estimated again, `jitter_iterations` times: the smoother follows fixes it takes
    as exact, which hid about half of the jitter (4 ms read 1.9 ms on the sample flight)."""
    jitter = estimate_stamp_jitter(fixes, smoothed, config)
    for _ in range(config.jitter_iterations):
        if jitter is None or not jitter.significant:
            break
        res = smooth(
            frames + d_ns,
            imu,
            add_stamp_covariance(fixes, jitter.sigma_s**2),
            None,
            velocity=velocity,
            config=pcfg,
            floor_camera=floor_camera,
        )
        again = estimate_stamp_jitter(fixes, res.trajectory, config)
        if again is None:
            break
        done = abs(again.sigma_s - jitter.sigma_s) < 0.05 * jitter.sigma_s
        jitter = again
        if done:
            break
    return jitter


def estimate_floor_drift(
    frame_t: np.ndarray,
    imu: ImuData | None,
    raw: Trajectory,
    main: FloorProfile,
    velocity: VelocityData | None = None,
    floor_camera: CameraModel | None = None,
    config: TimeOffsetConfig | None = None,
    fusion_config: FusionConfig | None = None,
    variance_factor: float = 1.0,
) -> ClockDrift | None:
    """The floor camera's clock rate (ClockDrift): the floor profile (estimate_floor_offset) of
    the flight's first third and of its last third, each on its best window, with the flight's
    own profile `main` (unless its window overlaps one of theirs: the same fixes), and the
    weighted least-squares line through their residuals; `ClockDrift.offset_s` is the line at
    the flight's middle.  None when not checked: TimeOffsetConfig.check_drift off, a flight
    shorter than drift_min_span_s, or a profile without curvature (sigma).
    `variance_factor` widens each window's sigma as resolve_time_offsets widens the flight's
    (time-correlated fixes).  EstimationError when a third cannot be profiled."""
    config = config or TimeOffsetConfig()
    frame_t = np.asarray(frame_t, dtype=np.int64)
    if not config.check_drift or len(frame_t) < 2 or main.sigma_s is None:
        return None
    t0, t1 = int(frame_t[0]), int(frame_t[-1])
    span_s = (t1 - t0) / NS_PER_S
    if span_s < config.drift_min_span_s:
        return None
    widen = math.sqrt(max(variance_factor, 1.0))
    third = (t1 - t0) // 3
    profiles = []
    for a, b in ((t0, t0 + third), (t1 - third, t1)):
        rsel = (raw.timestamps_ns >= a) & (raw.timestamps_ns <= b)
        part = Trajectory(
            raw.name,
            raw.timestamps_ns[rsel],
            raw.T_world_body[rsel],
            None if raw.covariances is None else raw.covariances[rsel],
        )
        fsel = (frame_t >= a) & (frame_t <= b)
        window = (
            profile_window(frame_t[fsel], part, imu, config.profile_window_s, config.profile_margin_s)
            if len(part)
            else None
        )
        if window == main.window_ns:
            profiles.append(main)  # the flight's own window is this third's best: the same solves
            continue
        profiles.append(
            estimate_floor_offset(
                frame_t[fsel], imu, part, velocity, floor_camera, config, fusion_config, jitter=False
            )
        )
    if not any(_overlap(main.window_ns, fp.window_ns) for fp in profiles):
        profiles.append(main)
    if any(fp.sigma_s is None for fp in profiles):
        return None
    centres = [(fp.window_ns[0] + fp.window_ns[1]) // 2 for fp in profiles]
    points = [(tc, fp.residual_s, float(fp.sigma_s or 0.0) * widen) for tc, fp in zip(centres, profiles)]
    return _drift_line(points, (t0 + t1) // 2, span_s, config, CameraRole.FLOOR.value)


def _rate_corrected(log_: FlightLog, raw: Trajectory, drift: ClockDrift) -> tuple[FlightLog, Trajectory]:
    """The log's floor stamps and the PnP poses' stamps corrected for the clock rate."""
    floor = CameraRole.FLOOR.value
    stream = copy.copy(log_.floor)
    stream.timestamps_ns = stream.timestamps_ns + drift.correction_ns(stream.timestamps_ns)
    moved = replace(raw, timestamps_ns=raw.timestamps_ns + drift.correction_ns(raw.timestamps_ns))
    return replace(log_, cameras={**log_.cameras, floor: stream}), moved


def _overlap(a: tuple[int, int], b: tuple[int, int]) -> bool:
    return a[0] < b[1] and b[0] < a[1]


# =========================================================================== front camera


def usable_sightings(obs: list[LoadObservation]) -> list[LoadObservation]:
    """The sightings with a finite camera-frame point (3,) and a finite positive-definite
    covariance (3, 3); the eigenvalue check batched over all of them (one call, not one per
    sighting: ~9 000 on the 10-minute flight)."""
    shaped = []
    for o in obs:
        if o.p_cam is None or o.cov_cam is None:
            continue
        p, C = np.asarray(o.p_cam, float), np.asarray(o.cov_cam, float)
        if p.shape == (3,) and C.shape == (3, 3):
            shaped.append((o, p, C))
    if not shaped:
        return []
    P = np.array([p for _, p, _ in shaped])
    C = np.array([c for _, _, c in shaped])
    ok = np.isfinite(P).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    sym = 0.5 * (C + np.swapaxes(C, 1, 2))
    sym[~ok] = np.eye(3)  # a non-finite one is dropped anyway; eigvalsh would raise on it
    ok &= np.linalg.eigvalsh(sym)[:, 0] > 0
    return [o for (o, _, _), keep in zip(shaped, ok) if keep]


def seen_twice(obs: list[LoadObservation]) -> tuple[list[LoadObservation], np.ndarray]:
    """The sightings of loads seen twice or more (a landmark needs two to say anything of the
    camera), and their load ids (M,)."""
    ids = np.array([o.load_id for o in obs])
    if not len(obs):
        return obs, ids
    _, inverse, counts = np.unique(ids, return_inverse=True, return_counts=True)
    keep = counts[inverse] >= 2
    return [o for o, k in zip(obs, keep) if k], ids[keep]


def landmark_fit(
    trajectory: PoseInterpolator,
    t_ns: np.ndarray,
    group: np.ndarray,
    p_cam: np.ndarray,
    info_cam: np.ndarray,
    front_camera: CameraModel,
    threshold: float,
    iterations: int,
) -> tuple[float, np.ndarray, np.ndarray]:
    """The load-landmark factors' robust cost with the drone on `trajectory` (T_world_body
    interpolated at `t_ns` (M,)) and each landmark at its Huber-IRLS weighted mean: sum rho(d_i),
    d_i the Mahalanobis distance of sighting i (p_cam (M, 3), information info_cam (M, 3, 3),
    load index `group` (M,)) from its landmark, rho Huber's with `threshold`; with each
    sighting's world residual from its landmark (M, 3) and its world information (M, 3, 3)."""
    T = trajectory(t_ns)
    T_wc = front_camera.T_world_cam(T)
    R = T_wc[:, :3, :3]
    p_w = np.einsum("nij,nj->ni", R, p_cam) + T_wc[:, :3, 3]
    W = R @ info_cam @ np.swapaxes(R, 1, 2)
    n_g = int(group.max()) + 1
    w = np.ones(len(t_ns))
    d = np.zeros(len(t_ns))
    r = np.zeros_like(p_w)
    Wp = np.einsum("nij,nj->ni", W, p_w)
    for _ in range(iterations + 1):
        # per-landmark sums by bincount (the same additions in the same order as np.add.at,
        # which was most of an evaluation's cost)
        wW = (w[:, None, None] * W).reshape(-1, 9)
        wWp = w[:, None] * Wp
        info = np.stack([np.bincount(group, wW[:, c], n_g) for c in range(9)], axis=1).reshape(n_g, 3, 3)
        vec = np.stack([np.bincount(group, wWp[:, c], n_g) for c in range(3)], axis=1)
        L = np.linalg.solve(info, vec[:, :, None])[:, :, 0]
        r = p_w - L[group]
        d = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, W, r), 0.0))
        w = np.where(d <= threshold, 1.0, threshold / np.maximum(d, 1e-12))
    rho = np.where(d <= threshold, 0.5 * d**2, threshold * (d - 0.5 * threshold))
    return float(rho.sum()), r, W


def sighting_rates(
    trajectory: PoseInterpolator,
    t_ns: np.ndarray,
    p_cam: np.ndarray,
    front_camera: CameraModel,
    h_s: float = 0.005,
) -> np.ndarray:
    """(M, 3) how fast each sighting's world point moves with its stamp (m/s): d/dt of
    T_world_cam(T(t)) p_cam, by central differences of the interpolated trajectory (a gimbaled
    camera's level frame included)."""
    t = np.asarray(t_ns, dtype=float)
    lo, hi = float(trajectory.ts[0]), float(trajectory.ts[-1])
    ta = np.clip(t - h_s * NS_PER_S, lo, hi)
    tb = np.clip(t + h_s * NS_PER_S, lo, hi)

    def world(tq: np.ndarray) -> np.ndarray:
        T_wc = front_camera.T_world_cam(trajectory(tq))
        return np.einsum("nij,nj->ni", T_wc[:, :3, :3], p_cam) + T_wc[:, :3, 3]

    dt = (tb - ta) / NS_PER_S
    rate = (world(tb) - world(ta)) / np.where(dt > 0, dt, 1.0)[:, None]
    return np.where((dt > 0)[:, None], rate, 0.0)


def widen_sightings(
    sightings: list[LoadObservation], trajectory: Trajectory, front_camera: CameraModel, variance_s2: float
) -> list[LoadObservation]:
    """The front camera's sightings with their camera-frame covariance plus variance_s2 u u^T,
    u their point's rate of change with the stamp in the camera frame (sighting_rates along
    `trajectory`, the drone in the sightings' clock), and their world covariance (when they
    have one) likewise in the world frame: white stamp noise of that variance."""
    if not sightings or variance_s2 <= 0.0 or len(trajectory) < 2:
        return sightings
    poses = PoseInterpolator(trajectory.timestamps_ns, trajectory.T_world_body)
    # all at once (one interpolation of the trajectory; one at a time it was ~0.8 ms a
    # sighting, 12.7 s of a 10-minute flight's 16 k sightings): those with a camera-frame point
    # and covariance inside the trajectory; the others (outside: their rate is not known, the
    # back ends drop them) as they are
    t = np.array([float(o.timestamp_ns) for o in sightings])
    has_point = np.array([o.p_cam is not None and o.cov_cam is not None for o in sightings])
    idx = np.flatnonzero(has_point & (t >= poses.ts[0]) & (t <= poses.ts[-1]))
    out = list(sightings)
    if not len(idx):
        return out
    p_cam = np.array([np.asarray(sightings[i].p_cam, float) for i in idx])
    u_w = sighting_rates(poses, t[idx], p_cam, front_camera)
    R_wc = front_camera.T_world_cam(poses(t[idx]))[:, :3, :3]
    u_c = np.einsum("nji,nj->ni", R_wc, u_w)  # R_wc^T u_w
    for k, i in enumerate(idx):
        o = sightings[i]
        cov_world = o.cov_world
        if cov_world is not None:
            cov_world = np.asarray(cov_world, float) + variance_s2 * np.outer(u_w[k], u_w[k])
        out[i] = replace(
            o,
            cov_cam=np.asarray(o.cov_cam, float) + variance_s2 * np.outer(u_c[k], u_c[k]),
            cov_world=cov_world,
        )
    return out


@dataclass
class FrontProfile:
    residual_s: float
    sigma_s: float | None
    sightings: int
    note: str = ""
    evaluations: int = 0
    jitter: StampJitter | None = None  # the sightings' stamp noise at the estimate
    at_bound: bool = False  # the minimum is at the search bound: the offset may be larger


def estimate_front_offset(
    trajectory: Trajectory,
    sightings: list[LoadObservation],
    front_camera: CameraModel,
    config: TimeOffsetConfig | None = None,
    fusion_config: FusionConfig | None = None,
    jitter: bool = True,
) -> FrontProfile:
    """Residual offset of the front camera: its load sightings (camera-frame p_cam / cov_cam,
    the log's stamps) against `trajectory` (the fused drone poses in the IMU clock), by the
    load-landmark cost profile (module docstring).  EstimationError with too few sightings."""
    config = config or TimeOffsetConfig()
    fusion_config = fusion_config or FusionConfig()
    S = config.search_half_width_s
    S_ns = int((S + config.front_curvature_step_s) * NS_PER_S)
    ts = trajectory.timestamps_ns
    obs, ids = seen_twice(
        [o for o in usable_sightings(sightings) if ts[0] + S_ns <= o.timestamp_ns <= ts[-1] - S_ns]
    )
    if len(obs) < config.min_load_sightings:
        raise EstimationError(
            f"{len(obs)} load sightings of loads seen twice or more (at least "
            f"{config.min_load_sightings} needed): the front camera's offset cannot be estimated"
        )
    _, group = np.unique(ids, return_inverse=True)
    t = np.array([o.timestamp_ns for o in obs], dtype=np.int64)
    p_cam = np.array([o.p_cam for o in obs], dtype=float)
    C = np.array([o.cov_cam for o in obs], dtype=float)
    info_cam = np.linalg.inv(0.5 * (C + np.swapaxes(C, 1, 2)))
    thr = fusion_config.threshold(3)
    n_eval = [0]
    # the trajectory's slerp prepared once for every offset tried (most of an evaluation's cost)
    poses = PoseInterpolator(trajectory.timestamps_ns, trajectory.T_world_body)

    def cost_ms(r_ms: float) -> float:
        n_eval[0] += 1
        tq = t.astype(float) + r_ms * 1e6
        return landmark_fit(poses, tq, group, p_cam, info_cam, front_camera, thr, config.irls_iterations)[0]

    S_ms, step_ms = S * MS_PER_S, config.front_grid_step_s * MS_PER_S
    grid = np.arange(-S_ms, S_ms + 0.5 * step_ms, step_ms)
    costs = [cost_ms(float(g)) for g in grid]
    i = int(np.argmin(costs))
    lo, hi = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
    r_ms, sig_ms, e_min = _profile_minimum(
        cost_ms, lo, hi, config.xatol_s * MS_PER_S, config.front_curvature_step_s * MS_PER_S
    )
    sig_ms = _inflate(sig_ms, e_min, 3 * (len(obs) - int(group.max()) - 1) - 1)
    at_bound = abs(r_ms) > S_ms - step_ms
    note = _at_bound_note(S_ms) if at_bound else ""
    found = None
    if jitter:
        # the sightings' stamp jitter at the estimate: residuals from their landmarks against
        # the rate their points move with the stamp
        tq = t.astype(float) + r_ms * 1e6
        _, resid, W = landmark_fit(
            poses, tq, group, p_cam, info_cam, front_camera, thr, config.irls_iterations
        )
        rates = sighting_rates(poses, tq, p_cam, front_camera)
        found = _jitter_ml(resid, np.linalg.inv(W), rates, config, keys=group_frame_keys(group, t))
    return FrontProfile(
        r_ms / MS_PER_S,
        None if sig_ms is None else sig_ms / MS_PER_S,
        len(obs),
        note,
        n_eval[0],
        found,
        at_bound,
    )


def estimate_front_drift(
    trajectory: Trajectory,
    sightings: list[LoadObservation],
    front_camera: CameraModel,
    config: TimeOffsetConfig | None = None,
    fusion_config: FusionConfig | None = None,
) -> ClockDrift | None:
    """The front camera's clock rate (ClockDrift): the front profile (estimate_front_offset) of
    the sightings of each third of their span, each at its sightings' mean stamp, and the
    weighted line through the three (independent: no sighting is in two).  None when not
    checked (check_drift off, a span shorter than drift_min_span_s, a profile
    without curvature); EstimationError when a third has too few sightings."""
    config = config or TimeOffsetConfig()
    obs = usable_sightings(sightings)
    if not config.check_drift or len(obs) < 2:
        return None
    t = np.array([o.timestamp_ns for o in obs], dtype=np.int64)
    t0, t1 = int(t.min()), int(t.max())
    span_s = (t1 - t0) / NS_PER_S
    if span_s < config.drift_min_span_s:
        return None
    edges = [t0 + (t1 - t0) * k // 3 for k in range(4)]
    points: list[tuple[int, float, float]] = []
    for k in range(3):
        sel = (t >= edges[k]) & ((t < edges[k + 1]) if k < 2 else (t <= edges[k + 1]))
        part = [o for o, keep in zip(obs, sel) if keep]
        fr = estimate_front_offset(trajectory, part, front_camera, config, fusion_config, jitter=False)
        if fr.sigma_s is None:
            return None
        points.append((int(np.mean(t[sel])), fr.residual_s, fr.sigma_s))
    return _drift_line(points, (t0 + t1) // 2, span_s, config, CameraRole.FRONT.value)


def _drift_line(
    points: list[tuple[int, float, float]], t_ref: int, span_s: float, config: TimeOffsetConfig, camera: str
) -> ClockDrift:
    """The weighted least-squares line r(t) = offset + rate (t - t_ref) through (t ns, r s,
    sigma s) `points`, applied when significant (ClockDrift); logged with the `camera`'s name."""
    x = np.array([(ti - t_ref) / NS_PER_S for ti, _, _ in points])
    r = np.array([ri for _, ri, _ in points])
    w = np.array([1.0 / sg**2 for _, _, sg in points])
    A = np.column_stack([np.ones_like(x), x])
    cov = np.linalg.inv(A.T @ (w[:, None] * A))
    offset, rate = cov @ (A.T @ (w * r))
    if len(points) > 2:
        # the points' scatter about the line beyond their sigmas widens it (Birge ratio): three
        # steady front-camera thirds 0.65 +- 0.27, 0.10 +- 0.16, 0.23 +- 0.10 ms read -59 +- 15 ppm
        chi2 = float(np.sum(w * (r - A @ np.array([offset, rate])) ** 2))
        cov = cov * max(1.0, chi2 / (len(points) - 2))
    sigma = math.sqrt(cov[1, 1])
    applied = abs(rate) > config.apply_sigmas * sigma and abs(rate) * span_s > config.min_apply_s
    drift = ClockDrift(
        float(rate), sigma, t_ref, span_s, list(points), bool(applied), float(offset), math.sqrt(cov[0, 0])
    )
    log.info("%s (%s): %s", camera, role_name(camera), drift.describe())
    return drift


def _sightings_corrected(sightings: list[LoadObservation], drift: ClockDrift) -> list[LoadObservation]:
    t = drift.correction_ns(np.array([o.timestamp_ns for o in sightings], dtype=np.int64))
    return [replace(o, timestamp_ns=int(o.timestamp_ns + d)) for o, d in zip(sightings, t.tolist())]


# =========================================================================== a run's offsets


def _too_short_for_drift(stamps_ns, config: TimeOffsetConfig) -> str:
    """The note of a camera whose clock rate was not checked for the flight's span: such a drift
    is in no sigma (h_ro15_clock's 40 ppm over 20 s left its smoother at NEES 12; DESIGN.md), so
    the run says so; '' when the span was long enough (or the check is off)."""
    t = np.asarray(stamps_ns, dtype=np.int64)
    span_s = float(t.max() - t.min()) / NS_PER_S if len(t) else 0.0
    if not config.check_drift or span_s >= config.drift_min_span_s:
        return ""
    return f"clock rate not checked (a {span_s:.1f} s span, under {config.drift_min_span_s:.0f} s)"


def _significant(r: float, sigma: float | None, config: TimeOffsetConfig) -> bool:
    return sigma is not None and abs(r) > config.apply_sigmas * sigma and abs(r) > config.min_apply_s


def check_stated_offsets(log_: FlightLog, fixed_s: dict[str, float] | None) -> None:
    """EstimationError (one line) when a stated offset (`fixed_s` {camera: s}, --time-offset-ms)
    moves a camera's frames wholly off the IMU's span: then no frame has an IMU sample to fuse
    with, and the run had finished with exit 0, health ok and no ATE (a value in us or ns typed
    as ms: 1e9 'ms' is 11.6 days).  Overlap is the test rather than a size bound: a camera
    stamped in another clock than the IMU's (the reader's `clock_offset`) needs an offset far
    larger than the flight to be corrected, and any offset larger than the flight while both
    clocks agree already fails it.  The shift is the stated offset minus the reader's seed (Kalibr's
    timeshift_cam_imu, already in the stamps), as resolve_time_offsets applies it.  Only an
    offset that moves frames overlapping the IMU off it is refused: a camera off the IMU before
    any offset is the reader's warning (`clock_offset`), and its loads' (`load_sightings_
    unsynchronised`).  A log without IMU is not checked (no clock to line up with)."""
    if not fixed_s or log_.imu is None or not len(log_.imu.timestamps_ns):
        return
    i0, i1 = int(log_.imu.timestamps_ns[0]), int(log_.imu.timestamps_ns[-1])
    for name, offset_s in fixed_s.items():
        stream = log_.cameras.get(name)
        if stream is None or not len(stream.timestamps_ns):
            continue
        shift_s = offset_s - log_.timeshift_ns.get(name, 0) / NS_PER_S
        c0, c1 = float(stream.timestamps_ns[0]) / NS_PER_S, float(stream.timestamps_ns[-1]) / NS_PER_S
        overlaps_before = c1 >= i0 / NS_PER_S and c0 <= i1 / NS_PER_S
        if overlaps_before and (c1 + shift_s < i0 / NS_PER_S or c0 + shift_s > i1 / NS_PER_S):
            raise EstimationError(
                f"the stated time offset {name}={offset_s * 1e3:.6g} ms moves {name}'s frames "
                f"({c0:.6g}-{c1:.6g} s) to {c0 + shift_s:.6g}-{c1 + shift_s:.6g} s, wholly outside the "
                f"IMU's {i0 / NS_PER_S:.6g}-{i1 / NS_PER_S:.6g} s: give it in milliseconds (not us "
                "or ns), or leave it out to estimate it"
            )


def resolve_time_offsets(
    log_: FlightLog,
    raw: Trajectory | None,
    sightings: list[LoadObservation],
    fixed_s: dict[str, float] | None = None,
    config: TimeOffsetConfig | None = None,
    fusion_config: FusionConfig | None = None,
    whole_flight: WholeFlightSolve | None = None,
    floor_variance_factor: float = 1.0,
) -> TimeOffsets:
    """Each camera's offset for a run: fixed (`fixed_s` {camera: s}, --time-offset-ms), else
    estimated around the log's seed (FlightLog.timeshift_ns) from the floor PnP poses `raw`
    (log stamps) and the front camera's camera-frame load `sightings`; when it cannot be
    estimated, the seed, with the reason in `note`.

    Order: the floor profile (its window's solves); then, for the front profile, the whole
    flight in the IMU clock: the floor profile's own trajectory when it covered the whole
    flight, else one whole-flight solve at the floor estimate (`whole_flight`, default
    `fused_trajectory`; the pipeline passes a solve shared with the mount check).

    `floor_variance_factor`: the floor profile's variance times this (>= 1) when the PnP poses'
    errors are correlated in time (correlation.py: the profile is a flight-wide average of them,
    worth n / tau independent frames, while its curvature counts n); the front offset's sigma
    takes the floor's as before."""
    config = config or TimeOffsetConfig()
    fixed_s = dict(fixed_s or {})
    seeds = {name: log_.timeshift_ns.get(name, 0) / NS_PER_S for name in log_.cameras}
    out = TimeOffsets()
    floor, front = CameraRole.FLOOR.value, CameraRole.FRONT.value
    fused: Trajectory | None = None  # the drone in the IMU clock, for the front profile
    fused_shift_ns = 0  # ... else solved with the floor stamps shifted by this

    seed = seeds.get(floor, 0.0)
    if floor in fixed_s:
        delta_ns = int(round((fixed_s[floor] - seed) * NS_PER_S))
        check = None
        if raw is not None and len(raw):
            try:
                fp = estimate_floor_offset(
                    log_.floor.timestamps_ns + delta_ns,
                    log_.imu,
                    _shift_traj(raw, delta_ns),
                    log_.velocity,
                    log_.floor.camera,
                    config,
                    fusion_config,
                )
                sigma_fp = fp.sigma_s
                if sigma_fp is not None:
                    sigma_fp *= math.sqrt(max(floor_variance_factor, 1.0))
                check = FixedCheck(fp.residual_s, sigma_fp, fp.at_bound)
            except EstimationError as e:
                log.info("the fixed floor offset not checked: %s", e)
        out.cameras[floor] = CameraOffset(
            floor, fixed_s[floor], None, OffsetSource.FIXED, seed, fixed_s[floor] - seed, check=check
        )
    else:
        drift: ClockDrift | None = None
        drift_note = ""
        try:
            if raw is None or len(raw) == 0:
                raise EstimationError("no floor-code fix: the floor camera's offset cannot be estimated")
            fp = estimate_floor_offset(
                log_.floor.timestamps_ns,
                log_.imu,
                raw,
                log_.velocity,
                log_.floor.camera,
                config,
                fusion_config,
            )
            try:
                drift = estimate_floor_drift(
                    log_.floor.timestamps_ns,
                    log_.imu,
                    raw,
                    fp,
                    log_.velocity,
                    log_.floor.camera,
                    config,
                    fusion_config,
                    floor_variance_factor,
                )
            except EstimationError as e:
                drift_note = f"clock rate not checked ({e})"
            else:
                drift_note = _too_short_for_drift(log_.floor.timestamps_ns, config) if drift is None else ""
            residual, sigma_fp = fp.residual_s, fp.sigma_s
            if sigma_fp is not None:
                sigma_fp *= math.sqrt(max(floor_variance_factor, 1.0))
            if drift is not None and drift.applied:
                # the offset is the rate's line at the flight's middle (where the correction is
                # 0); the front profile and the whole-flight solve read the corrected floor stamps
                for _ in range(config.drift_refinements):
                    lg, rw = _rate_corrected(log_, raw, drift)
                    fp = estimate_floor_offset(
                        lg.floor.timestamps_ns,
                        lg.imu,
                        rw,
                        lg.velocity,
                        lg.floor.camera,
                        config,
                        fusion_config,
                    )
                    again = estimate_floor_drift(
                        lg.floor.timestamps_ns,
                        lg.imu,
                        rw,
                        fp,
                        lg.velocity,
                        lg.floor.camera,
                        config,
                        fusion_config,
                        floor_variance_factor,
                    )
                    if again is None:
                        break
                    drift = replace(
                        again, rate=drift.rate + again.rate, t_ref_ns=drift.t_ref_ns, applied=True
                    )
                residual, sigma_fp = drift.offset_s, drift.offset_sigma_s
                log_, raw = _rate_corrected(log_, raw, drift)
                fused_shift_ns = int(round(residual * NS_PER_S))
            # the profile's trajectory, unless it covers only a window of the flight; a profile
            # without curvature (sigma None) leaves the offset undetermined: the front profile
            # then reads the trajectory at the log's floor stamps, not at that arbitrary minimum
            elif fp.sigma_s is None:
                pass
            elif fp.whole_flight:
                fused = fp.trajectory
            else:
                fused_shift_ns = int(round(fp.residual_s * NS_PER_S))
            applied = residual if _significant(residual, sigma_fp, config) else 0.0
            out.cameras[floor] = CameraOffset(
                floor,
                seed + residual,
                sigma_fp,
                OffsetSource.ESTIMATED,
                seed,
                applied,
                "; ".join(n for n in (fp.note, drift_note) if n),
                fp.evaluations,
                config.apply_sigmas,
                drift,
                fp.jitter,
                fp.at_bound,
            )
        except EstimationError as e:
            out.cameras[floor] = CameraOffset(floor, seed, None, OffsetSource.SEED, seed, 0.0, str(e))

    if front not in log_.cameras:
        return out
    seed = seeds.get(front, 0.0)
    if front in fixed_s:
        delta_ns = int(round((fixed_s[front] - seed) * NS_PER_S))
        check = None
        try:
            if raw is None or len(raw) == 0:
                raise EstimationError("no floor-code fix")
            shift_ns = fused_shift_ns or out.shift_ns(floor)
            floor_check = out.cameras[floor].check if floor in out.cameras else None
            if floor_check is not None and floor_check.disagrees():
                # the front camera is checked in the IMU's clock: the floor's as its data say
                if floor_check.at_bound:
                    raise EstimationError("the floor camera's fixed offset is beyond its search")
                shift_ns += int(round(floor_check.residual_s * NS_PER_S))
                fused = None
            if fused is None:
                # its own solve, not `whole_flight`: the run's other outputs stay what they were
                # without the check (the shared solve would warm-start the smoother, and give
                # the mount check its estimate)
                fused = fused_trajectory(log_, raw, shift_ns, config, fusion_config)
            shifted = [replace(o, timestamp_ns=int(o.timestamp_ns) + delta_ns) for o in sightings]
            fr = estimate_front_offset(fused, shifted, log_.cameras[front].camera, config, fusion_config)
            # the trajectory's clock carries the floor's error one to one, as for an estimate
            floor_sigma = out.cameras[floor].sigma_s if floor in out.cameras else None
            if floor_sigma is None and floor_check is not None:
                floor_sigma = floor_check.sigma_s
            sigma = fr.sigma_s
            if sigma is not None and floor_sigma is not None:
                sigma = math.hypot(sigma, floor_sigma)
            check = FixedCheck(fr.residual_s, sigma, fr.at_bound)
        except EstimationError as e:
            log.info("the fixed front offset not checked: %s", e)
        out.cameras[front] = CameraOffset(
            front, fixed_s[front], None, OffsetSource.FIXED, seed, fixed_s[front] - seed, check=check
        )
        return out
    try:
        if fused is None:
            fused_shift_ns = fused_shift_ns or out.shift_ns(floor)
            fused = (whole_flight or fused_trajectory)(log_, raw, fused_shift_ns, config, fusion_config)
        front_camera = log_.cameras[front].camera
        fr = estimate_front_offset(fused, sightings, front_camera, config, fusion_config)
        residual, sigma = fr.residual_s, fr.sigma_s
        drift_note = ""
        front_drift: ClockDrift | None = None
        try:
            front_drift = estimate_front_drift(fused, sightings, front_camera, config, fusion_config)
            for _ in range(
                config.drift_refinements if front_drift is not None and front_drift.applied else 0
            ):
                assert front_drift is not None
                again = estimate_front_drift(
                    fused, _sightings_corrected(sightings, front_drift), front_camera, config, fusion_config
                )
                if again is None:
                    break
                front_drift = replace(
                    again, rate=front_drift.rate + again.rate, t_ref_ns=front_drift.t_ref_ns, applied=True
                )
        except EstimationError as e:
            drift_note = f"clock rate not checked ({e})"
        else:
            if front_drift is None:
                drift_note = _too_short_for_drift(
                    [o.timestamp_ns for o in usable_sightings(sightings)], config
                )
        jitter = fr.jitter
        if front_drift is not None and front_drift.applied:
            residual, sigma = front_drift.offset_s, front_drift.offset_sigma_s
            corrected = _sightings_corrected(sightings, front_drift)
            jitter = estimate_front_offset(fused, corrected, front_camera, config, fusion_config).jitter
        # the trajectory's clock carries the floor estimate's error one to one
        floor_sigma = out.cameras[floor].sigma_s if floor in out.cameras else None
        if sigma is not None and floor_sigma is not None:
            sigma = math.hypot(sigma, floor_sigma)
        applied = residual if _significant(residual, sigma, config) else 0.0
        out.cameras[front] = CameraOffset(
            front,
            seed + residual,
            sigma,
            OffsetSource.ESTIMATED,
            seed,
            applied,
            "; ".join(n for n in (fr.note, drift_note) if n),
            fr.evaluations,
            config.apply_sigmas,
            front_drift,
            jitter,
            fr.at_bound,
        )
    except EstimationError as e:
        out.cameras[front] = CameraOffset(front, seed, None, OffsetSource.SEED, seed, 0.0, str(e))
    return out


@dataclass
class WholeFlightInput:
    """The front profile's whole-flight solve's inputs: floor frame stamps (ns) and PnP poses
    shifted into the IMU clock, the IMU, and the smoother's config (no loads, no covariances, no
    noise scaling; the specific force at each sub-interval's midpoint attitude, as for the floor
    profile: FusionConfig.imu_midpoint_attitude)."""

    frame_t: np.ndarray
    imu: ImuData | None
    raw: Trajectory
    velocity: VelocityData | None
    config: FusionConfig


def whole_flight_input(
    log_: FlightLog,
    raw: Trajectory | None,
    shift_ns: int,
    config: TimeOffsetConfig,
    fusion_config: FusionConfig | None,
) -> WholeFlightInput:
    """WholeFlightInput with the floor stamps shifted by `shift_ns`; EstimationError when the
    front camera's offset cannot be estimated (no fix, neither IMU nor velocity)."""
    if raw is None or len(raw) == 0:
        raise EstimationError("no floor-code fix: the front camera's offset cannot be estimated")
    if log_.imu is None and log_.velocity is None:
        raise EstimationError("neither IMU nor velocity: the front camera's offset cannot be estimated")
    pcfg = replace(
        fusion_config or FusionConfig(),
        compute_covariances=False,
        tight=False,
        noise_scale_iterations=0,
        check_noise=False,
        imu_midpoint_attitude=True,
    )
    return WholeFlightInput(
        log_.floor.timestamps_ns + shift_ns, log_.imu, _shift_traj(raw, shift_ns), log_.velocity, pcfg
    )


def fused_trajectory(
    log_: FlightLog,
    raw: Trajectory | None,
    shift_ns: int,
    config: TimeOffsetConfig,
    fusion_config: FusionConfig | None,
) -> Trajectory:
    """One smoother solve (no loads, no covariances) with the floor stamps shifted by
    `shift_ns`: the drone in the IMU clock over the whole flight (the floor profile covered only a
    window, or none was made).  The default WholeFlightSolve of resolve_time_offsets."""
    inp = whole_flight_input(log_, raw, shift_ns, config, fusion_config)
    res = smooth(
        inp.frame_t,
        inp.imu,
        inp.raw,
        None,
        velocity=inp.velocity,
        config=inp.config,
        floor_camera=log_.floor.camera,
    )
    return res.trajectory


WholeFlightSolve = Callable[
    [FlightLog, Trajectory | None, int, TimeOffsetConfig, FusionConfig | None], Trajectory
]
"""(log, floor PnP poses, floor shift ns, config, fusion config) -> the whole flight smoothed in
the IMU clock: `fused_trajectory`, or the pipeline's solve shared with the mount check."""


# =========================================================================== applying


def shift_log(log_: FlightLog, offsets: TimeOffsets) -> FlightLog:
    """A copy of the log whose camera stamps are in the IMU clock (each camera's applied shift
    added); frames still stream from the same files."""
    cams = {}
    for name, stream in log_.cameras.items():
        if offsets.shift_ns(name) or offsets.drift_applied(name):
            stream = copy.copy(stream)
            stream.timestamps_ns = offsets.stamps(name, stream.timestamps_ns)
        cams[name] = stream
    return replace(log_, cameras=cams)


def shift_detections(det, offsets: TimeOffsets):
    """A copy of a DetectionResult with each detection's stamp shifted like its camera's."""
    moved = {name for name in offsets.cameras if offsets.shift_ns(name) or offsets.drift_applied(name)}
    return replace(
        det,
        detections=[
            replace(d, timestamp_ns=int(offsets.stamps(d.camera, d.timestamp_ns))) if d.camera in moved else d
            for d in det.detections
        ],
    )
