"""Time-correlated corner errors: how much less than n independent frames a flight's PnP poses
are worth to the fused back ends (issue 10.3, clipping x2.2).

The per-frame PnP covariance is right for one frame (fusion.estimate.variance scales it from
the frame's own residuals), but the smoother and the EKF take the frames as independent.
When the same code seen in consecutive frames carries nearly the same corner error (decoder
fallback corners under clipping: whole-pixel corners of a code that barely moves), averaging n
frames does not divide the error's variance by n but by n / tau, tau the integrated
autocorrelation time in frames (var(mean) ~ tau var / n, tau = 1 + 2 sum_l rho(l); e.g. Sokal,
"Monte Carlo Methods in Statistical Mechanics: Foundations and New Algorithms", 1996 lecture
notes, sec. 2).  GNSS processing handles time-correlated observation errors alike, with the
observations' covariance built from their correlation over the sampling interval
(El-Rabbany, "The effect of physical correlations on the ambiguity resolution and accuracy
estimation in GPS differential positioning", UNB technical report 170, 1994).

Estimate, per corner class (whitening.CORNER_CLASSES), from the flight's own PnP residuals
(fusion.qr.pnp.bias.FrameCodeResiduals: each code's whitened corner residuals at its frame's
pose): rho(l) = the mean product of a code's residuals l frames apart over their mean square,
pooled over codes and the 8 coordinates.  A residual r = (I - P) w keeps the part of the corner
error w that the pose did not absorb; with the geometry nearly the same between neighbouring
frames E[r_t r_(t+l)^T] = (I - P) E[w_t w_(t+l)^T] (I - P), so rho is w's correlation as far as
the residual space shows it.  tau is Geyer's initial monotone sequence estimator (Geyer,
"Practical Markov chain Monte Carlo", Statistical Science 7(4), 1992, sec. 3.3): the sums of
adjacent lags Gamma_k = rho(2k) + rho(2k + 1) (rho(0) = 1) are positive and decreasing for any
reversible stationary series, so the sum runs over k while Gamma_k > 0 (initial positive
sequence), each Gamma_k cut to the smallest before it (initial monotone), up to MAX_LAG frames;
tau = -1 + 2 sum_k Gamma_k.  The window thus does not end at a lag that happens to be small
(the 800x600 sweep flight: rho = 0.02 / 0.17 / 0.17 / 0.11 / ... at lags 1 / 2 / 3 / 4, tau 3.7;
the former rule, which stopped at the first lag below the significance gate, read tau = 1).
tau is 1 unless the window's sum of rho is significant,
sum rho > Z_GATE sqrt(sum_l 1 / pairs(l)) (each rho(l) of white noise has the standard error
1 / sqrt(pairs(l)), Bartlett 1946; pairs counted per code, not per coordinate, conservatively;
a false alarm on white residuals in 8 % of seeded trials, the window being chosen on the same
data, reading tau 1.3 (median, at most 1.9) when it does: covariances a little conservative).

Use: the back ends' input covariance of a PnP frame becomes cov + sum_c (tau_c - 1) s_c G_c
(G_c the class's share of the frame's covariance, s_c its applied variance factor: the frame's
covariance as if class c's corner variance were tau_c times larger; variance.py's sandwich).
The PnP trajectory itself keeps the per-frame covariance (it is honest for one frame).  Since
time-correlated errors leave the smoother's residuals smaller than their variance (the
trajectory follows the slow part of the error), the smoother's pose-group variance factor is
not let below 1 on such flights (FusionConfig.pose_scale_floor)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from fusion.estimate.common import nearest_frames
from fusion.qr.pnp.bias import FrameCodeResiduals
from fusion.qr.pnp.whitening import CORNER_CLASSES
from fusion.types import Trajectory

MAX_LAG = 20
"""Most frame lags summed into tau (2 s at 10 fps)."""
Z_GATE = 1.645
"""The summed autocorrelation counts when above this many standard errors of its white-noise
value (one-sided 5 %).  The costs are not symmetric: a white flight read as correlated gets
tau ~1.3 (covariances a little conservative), a correlated one read as white loses its whole
inflation and the smoother's pose-scale floor (pipeline.fuse_stage), so its NEES jumps.  At
3.09 (one-sided 10^-3, the corner-bias gate's level) 1 of the 27 sweep flights and 2 of 21
held-out ones read white with tau 1.9; at 1.645 their smoothers' NEES read 7.2 -> 5.1
(fps10_vel5_to5), 11.1 -> 9.3 (ob_ro20_real), 5.5 -> 4.3 (h_occ_defocus), and no pose NEES
left its band (BENCHMARKS.md, twenty-seventh session)."""
MIN_PAIRS = 20
"""Fewer code pairs than this at a lag: the lag (and all later ones) is not used."""
_TRIU = np.triu_indices(6)
"""The upper triangle of a 6 x 6 (rows, columns): CorrelationInflation's packed terms."""
PLACEMENT_MAX_LAG = 3000
"""Most frame lags of the floor codes' placement correlation (`placement_autocorrelation`):
100 s at 30 fps; the sum stops earlier, where no code is seen again."""
PLACEMENT_MIN_RHO = 1e-3
"""`placement_autocorrelation` stops at the first lag whose correlation is below this."""
PLACEMENT = len(CORNER_CLASSES)
"""Index of the floor codes' placement in CorrelationInflation's classes, after the corner classes."""
DIRECTIONAL_BLOCK_ROWS = 4096
"""Frames per block of `CorrelationInflation.directional` (each frame's inflation is its own:
the result is the same for any block size; a block's temporaries are ~17 MB)."""


@dataclass
class ClassCorrelation:
    """One corner class's residual autocorrelation: rho (MAX_LAG,) at lags 1..MAX_LAG (NaN
    without pairs), pairs (MAX_LAG,) code pairs per lag, `lags_used` the lags summed, `tau` the
    integrated correlation time (1 + 2 sum rho over the lags used), sightings and codes."""

    rho: np.ndarray
    pairs: np.ndarray
    lags_used: int
    tau: float
    sightings: int
    codes: int

    def as_dict(self) -> dict:
        n = max(self.lags_used, 3)
        return {
            "tau": self.tau,
            "lags_used": self.lags_used,
            "rho": [round(float(x), 4) if math.isfinite(x) else None for x in self.rho[:n]],
            "pairs": [int(x) for x in self.pairs[:n]],
            "sightings": self.sightings,
            "codes": self.codes,
        }


def frame_indices(timestamps_ns: np.ndarray) -> np.ndarray:
    """(n,) integer frame numbers of sorted stamps: (t - t_0) over the median stamp interval,
    rounded (posed frames are mostly consecutive; a gap of skipped frames keeps its length)."""
    t = np.asarray(timestamps_ns, dtype=np.int64)
    if len(t) < 2:
        return np.zeros(len(t), dtype=np.int64)
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        return np.arange(len(t), dtype=np.int64)
    return np.rint((t - t[0]) / dt).astype(np.int64)


def class_autocorrelation(
    frame_index: np.ndarray, frames: Sequence[FrameCodeResiduals | None], max_lag: int = MAX_LAG
) -> dict[str, tuple[np.ndarray, np.ndarray, int, int]]:
    """Per corner class: (rho (max_lag,), pairs (max_lag,), sightings, codes) of the whitened
    residuals of the same code `l` frames apart (frame_index (n,) of the n `frames`; a code
    seen twice in one frame keeps its last sighting).  Vectorised: each sighting keyed by
    (code, frame), the partner l frames later found by a sorted search."""
    kept = [(int(f), fr) for f, fr in zip(frame_index, frames) if fr is not None and len(fr.payloads)]
    names: dict[str, int] = {}
    code = np.array([names.setdefault(p, len(names)) for _, fr in kept for p in fr.payloads], dtype=np.int64)
    frame = np.repeat(np.array([f for f, _ in kept], dtype=np.int64), [len(fr.payloads) for _, fr in kept])
    cls = np.concatenate([fr.classes for _, fr in kept]).astype(np.int64) if kept else np.zeros(0, np.int64)
    r = np.concatenate([np.asarray(fr.whitened, dtype=float) for _, fr in kept]) if kept else np.zeros((0, 8))
    finite = np.isfinite(r).all(axis=1)
    span = int(frame.max() - frame.min()) + max_lag + 1 if len(frame) else 1
    out = {}
    for c, name in enumerate(CORNER_CLASSES):
        sel = finite & (cls == c)
        key = code[sel] * span + (frame[sel] - (frame.min() if len(frame) else 0))
        rho, pairs, n = keyed_autocorrelation(key, r[sel], max_lag)
        out[name] = (rho, pairs, n, len(np.unique(code[sel])))
    return out


def group_frame_keys(group: np.ndarray, stamps_ns: np.ndarray, max_lag: int = MAX_LAG) -> np.ndarray:
    """`keyed_autocorrelation`'s keys of residuals of groups (a load's sightings, a code's) at
    their stamps: group * span + frame, the frame numbered by `frame_indices` over the distinct
    stamps and span past the frames' range + max_lag (key + l: the same group l frames later)."""
    stamps, frame_of = np.unique(np.asarray(stamps_ns, dtype=np.int64), return_inverse=True)
    frame = frame_indices(stamps)[frame_of]
    span = int(frame.max()) + max_lag + 1 if len(frame) else 1
    return np.asarray(group, dtype=np.int64) * span + frame


def correlation_time(key: np.ndarray, r: np.ndarray, max_lag: int = MAX_LAG) -> float:
    """The integrated correlation time in frames of whitened residuals r (N, d) keyed as
    `keyed_autocorrelation` takes them (`group_frame_keys`): `integrated_time` of their
    autocorrelation, Geyer's initial monotone sequence with its gate (1 when white)."""
    rho, pairs, _ = keyed_autocorrelation(key, r, max_lag)
    return integrated_time(rho, pairs)[0]


def keyed_autocorrelation(
    key: np.ndarray, r: np.ndarray, max_lag: int = MAX_LAG
) -> tuple[np.ndarray, np.ndarray, int]:
    """(rho (max_lag,), pairs (max_lag,), n) of whitened residuals r (N, d) keyed code * span +
    frame (span > the frames' range + max_lag, so that key + l is the same code l frames later):
    rho(l) the mean product of the pairs l frames apart over the mean square, pooled over the d
    coordinates (NaN at a lag without pairs); one residual per key (a code seen twice in one
    frame keeps its last).  Vectorised: each partner found by a sorted search."""
    key, first = np.unique(np.asarray(key)[::-1], return_index=True)
    rc = np.asarray(r, dtype=float)[::-1][first]
    prod = np.zeros(max_lag)
    pairs = np.zeros(max_lag, dtype=np.int64)
    for lag in range(1, max_lag + 1):
        j = np.searchsorted(key, key + lag)
        j = np.minimum(j, len(key) - 1)
        hit = key[j] == key + lag if len(key) else np.zeros(0, bool)
        pairs[lag - 1] = int(hit.sum())
        prod[lag - 1] = float(np.sum(rc[hit] * rc[j[hit]]))
    n = len(key)
    var = float(np.sum(rc * rc)) / n if n else 0.0
    rho = prod / np.maximum(pairs, 1) / var if var > 0 else np.zeros(max_lag)
    return np.where(pairs > 0, rho, np.nan), pairs, n


def placement_autocorrelation(
    frame_index: np.ndarray, frames: Sequence[FrameCodeResiduals | None], max_lag: int = PLACEMENT_MAX_LAG
) -> np.ndarray:
    """rho_p (L,) at lags 1..L of the floor codes' placement error in the PnP poses (frame_index
    (n,) of the n `frames`, their codes' payloads): a code laid off its payload moves every pose
    that sees it by the same amount, so the share of a frame's placement error still present l
    frames later is the share of its codes seen again then (codes weighed equally), averaged
    over the frames with a posed frame l later.  Not estimated from residuals (a single code's
    frame absorbs its placement whole): from which codes each frame saw.  Stops at the first lag
    below PLACEMENT_MIN_RHO or at `max_lag`."""
    kept = [(int(f), fr) for f, fr in zip(frame_index, frames) if fr is not None and len(fr.payloads)]
    if not kept:
        return np.zeros(0)
    names: dict[str, int] = {}
    code = np.array([names.setdefault(p, len(names)) for _, fr in kept for p in fr.payloads], dtype=np.int64)
    frame = np.repeat(np.array([f for f, _ in kept], dtype=np.int64), [len(fr.payloads) for _, fr in kept])
    weight = np.repeat([1.0 / len(fr.payloads) for _, fr in kept], [len(fr.payloads) for _, fr in kept])
    span = int(frame.max() - frame.min()) + max_lag + 1
    key = code * span + (frame - frame.min())
    order = np.argsort(key, kind="stable")
    key, frame, weight = key[order], frame[order], weight[order]
    offset = frame - frame.min()
    posed = np.zeros(int(offset.max()) + max_lag + 2, dtype=bool)  # posed[f]: frame f was posed
    posed[offset] = True
    rho: list[float] = []
    for lag in range(1, max_lag + 1):
        later = posed[offset + lag]  # the sighting's frame has a posed frame lag later
        if not later.any():
            break
        j = np.minimum(np.searchsorted(key, key + lag), len(key) - 1)
        again = later & (key[j] == key + lag)
        r = float(np.sum(weight[again]) / np.sum(weight[later]))
        if r < PLACEMENT_MIN_RHO:
            break
        rho.append(r)
    return np.array(rho)


def monotone_sequence(rho: np.ndarray, pairs: np.ndarray, z: float = Z_GATE) -> np.ndarray:
    """The autocorrelation (m,) at lags 1..m that Geyer's initial monotone sequence estimator sums
    (Geyer 1992, sec. 3.3; the module's docstring): Gamma_0 = 1 + rho(1), Gamma_k = rho(2k) +
    rho(2k + 1) for k >= 1 while Gamma_k > 0 and both lags have >= MIN_PAIRS finite pairs, each
    pair of lags scaled so that its Gamma is min(Gamma_0..Gamma_k).  Empty (tau = 1) when lag 1
    has too few pairs or the window's sum is not significant: sum rho <= z sqrt(sum 1 / pairs)."""
    rho = np.asarray(rho, dtype=float)
    pairs = np.asarray(pairs)
    if not len(rho) or pairs[0] < MIN_PAIRS or not math.isfinite(rho[0]):
        return np.zeros(0)
    kept = [float(rho[0])]
    gamma_min = 1.0 + float(rho[0])
    for a in range(1, len(rho) - 1, 2):  # lags a + 1 = 2k and a + 2 = 2k + 1
        b = a + 1
        if min(pairs[a], pairs[b]) < MIN_PAIRS or not (math.isfinite(rho[a]) and math.isfinite(rho[b])):
            break
        gamma = float(rho[a] + rho[b])
        if gamma <= 0.0:
            break
        cut = min(gamma, gamma_min) / gamma
        gamma_min = min(gamma, gamma_min)
        kept += [float(rho[a]) * cut, float(rho[b]) * cut]
    out = np.array(kept)
    if not out.sum() > z * math.sqrt(float(np.sum(1.0 / pairs[: len(out)]))):
        return np.zeros(0)
    return out


def integrated_time(rho: np.ndarray, pairs: np.ndarray, z: float = Z_GATE) -> tuple[float, int]:
    """(tau, lags used): 1 + 2 sum of `monotone_sequence` (Geyer's initial monotone sequence
    estimator, -1 + 2 sum_k Gamma_k), and its length; (1, 0) when the sum is not significant."""
    kept = monotone_sequence(rho, pairs, z)
    return 1.0 + 2.0 * float(kept.sum()), len(kept)


@dataclass
class CorrelationInflation:
    """The back ends' extra input covariance of each PnP frame for time-correlated corner
    errors: stamps (n,), per class c the frame's class covariance at its applied scale
    `class_terms` s_c G_c of the m classes `classes` (indices into the k CORNER_CLASSES; None:
    all k in order), given as (n, m, 6, 6) and kept packed (`terms` unpacks rows), and per
    class the autocorrelation `rho` (k, MAX_LAG), the lags summed `lags_used` (k,) and `taus`
    (k,).  `add_to` adds sum_c (tau_c - 1) s_c G_c (a long average: the batch smoother);
    `filter_taus` the inflation of a filter's shorter, one-sided average (EKF, fixed-lag
    smoother: `solve_inflated`).

    Memory: the terms are alive through every back end's solves (a 30-minute flight's
    (n, k, 6, 6) float64 were 31 MB per class, and its first smoother solve the run's peak:
    +34 MiB, BENCHMARKS.md corr15), so `estimate_inflation` keeps the inflated classes only
    (the others' weight is exactly 0) and each 6 x 6 is kept as its upper triangle in float32
    (21 numbers, 4.5 MB per class on 30 minutes; an added inflation term, where float32's
    relative 6e-8 is far below anything the NEES can tell)."""

    timestamps_ns: np.ndarray
    class_terms: np.ndarray
    rho: np.ndarray
    lags_used: np.ndarray
    taus: np.ndarray
    tolerance_ns: int = 0
    classes: np.ndarray | None = None

    def __post_init__(self) -> None:
        terms = np.asarray(self.class_terms)
        if terms.ndim == 4:  # (n, m, 6, 6) given: packed
            self.class_terms = np.ascontiguousarray(terms[..., _TRIU[0], _TRIU[1]], dtype=np.float32)

    def terms(self, index) -> np.ndarray:
        """(len, m, 6, 6) float64 s_c G_c of the frames `index` (an index into the stamps)."""
        packed = np.asarray(self.class_terms[index], dtype=float)
        out = np.empty((*packed.shape[:-1], 6, 6))
        out[..., _TRIU[0], _TRIU[1]] = packed
        out[..., _TRIU[1], _TRIU[0]] = packed
        return out

    def _classes(self) -> np.ndarray:
        """(m,) the CORNER_CLASSES indices of class_terms' second axis."""
        return np.arange(len(self.taus)) if self.classes is None else np.asarray(self.classes, dtype=int)

    def _nearest(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(index of the nearest PnP stamp, whether within tolerance_ns) for stamps t."""
        nearest = nearest_frames(self.timestamps_ns, t)
        return nearest, np.abs(self.timestamps_ns[nearest] - t) <= self.tolerance_ns

    def add_to(self, traj: Trajectory, taus: np.ndarray | None = None) -> Trajectory:
        """`traj` with each pose's extra covariance sum_c (tau_c - 1) s_c G_c added (`taus`
        (k,), default the flight's): that of the PnP frame at the nearest stamp, when within
        `tolerance_ns` (half a frame; the time-offset stage may have moved the stamps by
        milliseconds), else none.  Unchanged without covariances."""
        if traj.covariances is None or not len(traj) or not len(self.timestamps_ns):
            return traj
        w = (np.asarray(self.taus if taus is None else taus, dtype=float) - 1.0)[self._classes()]
        t = np.asarray(traj.timestamps_ns, dtype=np.int64)
        nearest, close = self._nearest(t)
        covs = np.array(traj.covariances, dtype=float, copy=True)
        covs[close] += np.einsum("c,ncij->nij", w, self.terms(nearest[close]))
        return Trajectory(traj.name, traj.timestamps_ns, traj.T_world_body, covs)

    def placement_taus(self) -> np.ndarray:
        """The flight's taus with the corner classes' at 1: the floor codes' placement class
        alone (all 1 for a floor laid exactly)."""
        taus = np.ones(len(self.taus))
        if len(taus) > PLACEMENT:
            taus[PLACEMENT] = self.taus[PLACEMENT]
        return taus

    def long_average_variance_factor(self, traj: Trajectory) -> float:
        """By how much the variance of a flight-wide average of `traj`'s poses exceeds that of
        independent frames: the median over the frames of tr(C^-1 (C + E)) / 6, C a frame's
        covariance and E its extra of `add_to` (the flight's taus): the mean variance ratio over
        C's whitened directions, free of the units that a plain trace ratio would mix (rad^2,
        m^2).  1 without covariances."""
        if traj.covariances is None or not len(traj):
            return 1.0
        C = np.asarray(traj.covariances, dtype=float)
        E = np.asarray(self.add_to(traj).covariances, dtype=float) - C
        ok = np.isfinite(C).all(axis=(1, 2)) & np.isfinite(E).all(axis=(1, 2))
        ok[ok] &= np.linalg.eigvalsh(C[ok])[:, 0] > 0
        if not ok.any():
            return 1.0
        ratio = 1.0 + np.trace(np.linalg.solve(C[ok], E[ok]), axis1=1, axis2=2) / C.shape[-1]
        return float(np.median(ratio))

    def directional(self, raw: Trajectory, fused: Trajectory, two_sided: bool) -> Trajectory:
        """`raw` with the extra covariance of the average an estimator takes of it, direction by
        direction: per raw frame, in the eigenbasis u_i of R^-1/2 P R^-T/2 (R the frame's raw
        covariance, P the `fused` covariance at its stamp, solved on `raw` as it is), the fused
        pose holds n_i = 1 / eigenvalue frames' worth of raw information along u_i (1: that
        direction rests on the frame alone; many: averaged over many frames, or known from the
        IMU, where R hardly matters), and class c's share of R there,
        e_ci = u_i^T R^-1/2 s_c G_c R^-T/2 u_i, is inflated by `average_taus`(n_i) - 1.  Frames
        without a fused pose at their stamp (within tolerance_ns) are left as they are."""
        if raw.covariances is None or fused.covariances is None or not len(raw) or not len(fused):
            return raw
        t = np.asarray(raw.timestamps_ns, dtype=np.int64)
        nearest, close = self._nearest(t)
        t_f = np.asarray(fused.timestamps_ns, dtype=np.int64)
        j = nearest_frames(t_f, t)
        close &= np.abs(t_f[j] - t) <= self.tolerance_ns
        R = np.asarray(raw.covariances, dtype=float)
        P = np.asarray(fused.covariances, dtype=float)
        ok = close & np.isfinite(R).all(axis=(1, 2)) & np.isfinite(P).all(axis=(1, 2))[j]
        idx = np.flatnonzero(ok)
        if not len(idx):
            return raw
        covs = R.copy()
        # frames are independent: in blocks of rows, so that the (m, k, 6, 6) temporaries stay
        # small (all of a 30-minute flight's frames at once: ~0.2 GB at the fusion's peak)
        for lo in range(0, len(idx), DIRECTIONAL_BLOCK_ROWS):
            rows = idx[lo : lo + DIRECTIONAL_BLOCK_ROWS]
            try:
                L = np.linalg.cholesky(R[rows])
            except np.linalg.LinAlgError:
                return raw
            Li = np.linalg.inv(L)
            Pw = Li @ P[j[rows]] @ np.swapaxes(Li, 1, 2)
            mu, U = np.linalg.eigh(0.5 * (Pw + np.swapaxes(Pw, 1, 2)))  # (m, 6), (m, 6, 6)
            n_dir = 1.0 / np.maximum(mu, 1e-12)
            # (m, k, 6, 6)
            Ew = Li[:, None] @ self.terms(nearest[rows]) @ np.swapaxes(Li, 1, 2)[:, None]
            share = np.einsum("mai,mcab,mbi->mci", U, Ew, U)  # (m, k, 6): e_ci
            taus = self.average_taus(n_dir, two_sided)[:, self._classes()]  # (m, k', 6)
            d = np.sum((taus - 1.0) * share, axis=1)  # (m, 6)
            LU = L @ U
            covs[rows] += np.einsum("mai,mi,mbi->mab", LU, d, LU)
        return Trajectory(raw.name, raw.timestamps_ns, raw.T_world_body, covs)

    def average_taus(self, n_eff: np.ndarray, two_sided: bool) -> np.ndarray:
        """Per class, the variance of an exponentially weighted average of correlated samples
        over that of white ones, for averages over `n_eff` (m, d) frames (n_eff = (sum w)^2 /
        sum w^2: the white average's variance is 1 / n_eff of a sample's): 1 + 2 sum_l rho(l) c(l)
        over the lags used, c(l) = sum_i w_i w_(i+l) / sum_i w_i^2.  One-sided (a filter:
        w_i = a^i, i >= 0): c(l) = a^l, n_eff = (1 + a) / (1 - a).  Two-sided (a smoother:
        w_i = a^|i|): c(l) = a^l (2 + (l - 1)(1 - a^2)) / (1 + a^2), n_eff = (1 + a)^3 /
        ((1 - a)(1 + a^2)).  Tends to the flight's tau as n_eff grows; 1 at n_eff = 1.
        The floor codes' placement (class PLACEMENT) takes its tau_p at any n_eff: the error is
        the same in every frame of a code's run, and a back end's average does not decay over
        frames as the weights above assume (its IMU carries the run's earlier frames), so each
        run is counted as one placement error (place60, 60 s, codes 1 cm / 0.5 deg off:
        incremental / EKF NEES 13.7 / 9.5 with the weighted average, 6.2 / 5.1 so;
        BENCHMARKS.md, eighteenth session).  Returns (m, k, d)."""
        n = np.clip(np.nan_to_num(np.asarray(n_eff, dtype=float), nan=1.0), 1.0, 1e12)
        if two_sided:
            grid = np.linspace(0.0, 1.0 - 1e-6, 20001)
            n_grid = (1 + grid) ** 3 / ((1 - grid) * (1 + grid**2))
            a = np.interp(n, n_grid, grid)
        else:
            a = (n - 1.0) / (n + 1.0)
        out = np.ones((n.shape[0], len(self.taus), n.shape[1]))
        for c, used in enumerate(self.lags_used):
            if c == PLACEMENT:  # each code's placement counts once, whatever the average
                out[:, c, :] = self.taus[c]
                continue
            for lag in range(1, int(used) + 1):
                if two_sided:
                    w = a**lag * (2.0 + (lag - 1) * (1.0 - a**2)) / (1.0 + a**2)
                else:
                    w = a**lag
                out[:, c, :] += 2.0 * self.rho[c, lag - 1] * w
        return out


def solve_inflated(
    fn,
    frame_times_ns,
    imu,
    raw: Trajectory,
    load_obs,
    *,
    inflation: CorrelationInflation,
    two_sided: bool,
    keep_noise_scales: bool = False,
    reuse=None,
    **kwargs,
):
    """A back end `fn` (smooth / smooth_windowed: `two_sided`; run_ekf, smooth_incremental: not;
    the same call as theirs) on PnP poses `raw` whose corner errors are correlated in time:
    solved once on `raw` as it is, then again on `raw` with each frame's covariance inflated for
    the average that solve took of the frames, direction by direction
    (`CorrelationInflation.directional`).  `reuse` (smooth only: a smoother.SolveReuse): given to
    both solves, so that the second starts from the first's solution and reuses its
    preintegrated IMU (a `warm_start` in kwargs is the first solve's only).
    `keep_noise_scales` (the batch smoother, which estimates them: variance.solve_noise_scaled):
    the noise scales of the first solve (per camera, cam0 for the poses and tight corners, cam1
    for the loads) are applied to the second as they are and not estimated again (the inflated
    covariances would read as too large: the residuals of a correlated error understate it, so
    their chi2/dof is not measured at all: FusionConfig.check_noise off), and its report is the
    first solve's.  Its stats gain `correlation_inflation`: the median over the frames of the
    inflated covariance's trace over the raw one's."""
    from fusion.estimate import variance

    if reuse is not None:
        first = fn(frame_times_ns, imu, raw, load_obs, reuse=reuse, **kwargs)
        kwargs = {k: v for k, v in kwargs.items() if k != "warm_start"}
        kwargs["reuse"] = reuse
    else:
        first = fn(frame_times_ns, imu, raw, load_obs, **kwargs)
    inflated = inflation.directional(raw, first.trajectory, two_sided)
    report = first.stats.get("noise_scales") if keep_noise_scales else None
    # the first solve's result (a whole flight's poses and covariances, its stats) is not
    # needed past here: let it go before the second solve, not after it
    del first
    ratio = _trace_ratio(raw, inflated)
    if report is not None:
        again, load_again, _ = variance.apply_smoother_scales(report, inflated, load_obs)
        del inflated  # `again` is what the second solve takes
        config = kwargs.get("config")
        if config is not None:
            imu, config = variance.apply_smoother_sensor_scales(report, imu, config)
            # nor are its variance components measured (check_noise off): its report is the
            # first solve's, and they were the second solve's memory peak (the smoother windows'
            # leverages, with the inflated poses alive beside `raw`: a 30-minute flight's run
            # 870 -> 891 MiB; BENCHMARKS.md corr15)
            kwargs = dict(kwargs, config=replace(config, noise_scale_iterations=0, check_noise=False))
        res = fn(frame_times_ns, imu, again, load_again, **kwargs)
        res.stats["noise_scales"] = dict(report, inflated_solve=True)
    else:
        res = fn(frame_times_ns, imu, inflated, load_obs, **kwargs)
    res.stats["correlation_inflation"] = {
        "two_sided": bool(two_sided),
        "trace_ratio_median": ratio,
    }
    return res


def solve_inflated_twice(
    fn,
    frame_times_ns,
    imu,
    raw: Trajectory,
    load_obs,
    *,
    inflation: CorrelationInflation,
    reuse=None,
    **kwargs,
):
    """The batch smoother (`fn`: smooth; two-sided) on time-correlated PnP poses `raw`, one
    solve fewer than solve_inflated's noise-scale iteration (one to three solves) and its
    inflated solve:

    1. solved once at the nominal noise, its variance components giving each group its scale
       s_g (variance.first_solve_scales: the scales the iteration's report would apply after
       this solve), and its marginal covariances taken at those scales from its own
       linearisation (FusionConfig.covariances_at_first_scales: each group's whitened rows
       over sqrt(s_g));
    2. solved again, warm, at s_g on `raw` inflated direction by direction
       (`CorrelationInflation.directional`) from those covariances, its variance components
       measured: the noise-scale iteration goes on in these inflated solves (its stopping rule,
       variance.next_noise_scales, and its budget, config.noise_scale_iterations, counted from
       here) for every group but the poses, whose scale stays solve 1's (the inflated poses'
       residuals understate them: solve_inflated's report keeps the first solve's too).

    Why the covariances at s_g and not at the nominal noise: the inflation reads, per direction
    of a frame's pose, n = 1 / eigenvalue of R^-1/2 P R^-T/2, the frames' worth of raw
    information the fused pose holds; at the linearisation point P^-1 = sum_g H_g / s_g (H_g a
    group's Hessian), so a group's scale changes n through its share of the pose's information
    (the loads' scale, 0.1-0.7 on the sweep flights, moved the fused covariances by up to 2x in
    single directions).  Why the iteration goes on: the loads' first step stops 2-48 % short of
    where it ends on the sweep flights, and with the loads so weighted the smoother's pose NEES
    on a clipping flight (x2.6, seed 0) fell below 3 (BENCHMARKS.md, two17).  The inflation is
    not redone as the loads' scale moves (from solve 1's covariances at s_g).  The iteration is
    kept as it was (solve_inflated, warm from the first solve) when the first solve cannot say
    its scales: the fixes disagree with the IMU (its gate skipped, or the IMU-rejected retry),
    a stated sensor's (IMU, velocity) chi2/dof outside variance.IMU_WARN_BAND (the iteration
    then decides whether any scale applies, the sensor's included), or its covariances are not
    those at s_g (the approximate or Bayes-tree marginals).  Memory: the inflated solves
    measure variance components again (solve_inflated's second solve did not: corr15's b77f841,
    the 30-minute flight's peak)."""
    from fusion.estimate import variance
    from fusion.estimate.common import FusionConfig

    config = kwargs.get("config") or FusionConfig()
    rest = {k: v for k, v in kwargs.items() if k not in ("config", "warm_start")}
    one = replace(config, noise_scale_iterations=0, covariances_at_first_scales=True)
    first = fn(
        frame_times_ns,
        imu,
        raw,
        load_obs,
        reuse=reuse,
        config=one,
        **dict(rest, warm_start=kwargs.get("warm_start")),
    )
    report = first.stats.get("noise_scales") or {}
    lo, hi = variance.IMU_WARN_BAND
    outside = [
        name
        for g, (name, _) in variance.STATED_SENSORS.items()
        if (c := report.get(f"{g}_chi2_per_dof")) is not None and not lo <= c <= hi
    ]
    why = ""
    if first.stats.get("imu_rejected") or report.get("not_applied"):
        why = "the fixes disagree with the IMU"
    elif outside:
        # the iteration decides whether that sensor's stated noise is scaled (next_noise_scales)
        why = f"the {outside[0]}'s chi2/dof is outside its band"
    elif first.stats.get("covariance_scales") is None or first.trajectory.covariances is None:
        why = "no covariances at the first solve's scales"
    if why or config.noise_scale_iterations <= 0:
        del first
        res = solve_inflated(
            fn,
            frame_times_ns,
            imu,
            raw,
            load_obs,
            inflation=inflation,
            two_sided=True,
            keep_noise_scales=True,
            reuse=reuse,
            config=config,
            **rest,
        )
        if why:
            res.stats["noise_scales"] = dict(res.stats.get("noise_scales") or {}, two_solves_not_applied=why)
        return res
    inflated = inflation.directional(raw, first.trajectory, two_sided=True)
    scales = variance.NoiseScales(**first.stats["covariance_scales"])
    del first
    ratio = _trace_ratio(raw, inflated)
    # the noise-scale iteration goes on in the inflated solves, for every group but the poses
    # (held at the first solve's: the inflated poses' residuals understate them), with its
    # stopping rule and budget; the first step is solve 1's
    pose = variance.NoiseGroup.POSE

    def iterated(comps: dict) -> dict:
        # the poses held at solve 1's scale; the stated sensors, in band at solve 1, as stated
        return {g: c for g, c in comps.items() if g != pose and g not in variance.STATED_SENSORS}

    steps, last = 0, {}
    while True:
        cfg_k = replace(
            config,
            noise_scale_iterations=0,
            check_noise=True,
            corner_noise_scale=config.corner_noise_scale * scales.corners,
        )
        left = config.noise_scale_iterations - (steps + 1)  # solves the budget allows after this one

        def again(comps, health, scales_=scales, left_=left) -> bool:
            # this loop's own rule below, told to the solve: one it will discard skips its
            # covariances (a window's chain marginals, ~0.5 CPU s on the 10-minute flight)
            return left_ > 0 and variance.next_noise_scales(scales_, iterated(comps)) is not None

        res = fn(
            frame_times_ns,
            imu,
            variance.scale_trajectory(inflated, scales.pose),
            variance.scale_load_observations(load_obs, scales.load) if load_obs else load_obs,
            reuse=reuse,
            config=cfg_k,
            resolves=again,
            **rest,
        )
        steps += 1
        last = (res.stats.get("noise_scales") or {}).get("groups", {})
        comps = iterated(
            {
                variance.NoiseGroup(g): variance.VarianceComponent(
                    e["chi2"], e["dof"], e["n"], e.get("n_gated", 0)
                )
                for g, e in last.items()
            }
        )
        new = variance.next_noise_scales(scales, comps)
        if new is None or steps >= config.noise_scale_iterations:
            break
        scales = new
    if res.stats.get("covariance_method") == "skipped":  # `again` is the loop's own rule: a bug
        raise RuntimeError("solve_inflated_twice: the last inflated solve skipped its covariances")
    del inflated
    groups = {g: dict(e) for g, e in last.items()}
    if str(pose) in report.get("groups", {}):
        groups[str(pose)] = dict(report["groups"][str(pose)])
    cameras = {}
    for g, cam in variance.CAMERA_OF_GROUP.items():
        if str(g) in groups:
            groups[str(g)]["applied_scale"] = scales.of(g)
            cameras[cam] = {
                "scale": scales.of(g),
                "sigma_factor": math.sqrt(scales.of(g)),
                "dof": groups[str(g)]["dof"],
                "group": str(g),
            }
    out = {"solves": 1 + steps, "inflated_solves": steps, "groups": groups, "cameras": cameras}
    for g in variance.STATED_SENSORS:
        for key in (f"{g}_chi2_per_dof", f"{g}_warning"):
            if key in report:
                out[key] = report[key]
    res.stats["noise_scales"] = dict(out, inflated_solve=True, two_solves=True)
    res.stats["correlation_inflation"] = {"two_sided": True, "trace_ratio_median": ratio}
    return res


def causal_inflated(
    fn, frame_times_ns, imu, raw: Trajectory, load_obs, *, inflation: CorrelationInflation, **kwargs
):
    """`raw` inflated for the one-sided average a causal back end takes of the frames, from
    `fn`'s solve on `raw` as it is (the first of `solve_inflated`'s two, two_sided False).  The
    EKF's and the incremental smoother's outputs are both the marginal of frame k as known at
    frame k, from the same factors, so the run takes one such pass, the EKF's (the cheaper), for
    both (pipeline.fuse_stage).  An approximation for the incremental smoother, measured: from
    either's pass the inflated traces differ by 0.1 % (median), at most 0.7 %, on
    tests/test_backend_reuse.py's flight; on the 28 sweep flights its 6-dof NEES moved by -0.5 to
    +21 % (r800 6.90 -> 8.00, fps60 3.46 -> 4.19: its own, tighter covariance had inflated more),
    no flight's verdict changed; its own first pass cost ~9 CPU s on the 10-minute flight
    (BENCHMARKS.md, fifteenth session)."""
    first = fn(frame_times_ns, imu, raw, load_obs, **kwargs)
    return inflation.directional(raw, first.trajectory, two_sided=False)


def solve_on_inflated(fn, frame_times_ns, imu, raw: Trajectory, inflated: Trajectory, load_obs, **kwargs):
    """`fn` on the inflated poses of `causal_inflated` (`raw` as they were), its stats gaining
    `correlation_inflation` as solve_inflated's."""
    res = fn(frame_times_ns, imu, inflated, load_obs, **kwargs)
    res.stats["correlation_inflation"] = {
        "two_sided": False,
        "trace_ratio_median": _trace_ratio(raw, inflated),
    }
    return res


def _trace_ratio(raw: Trajectory, inflated: Trajectory) -> float:
    """The median over the frames of the inflated covariance's trace over the raw one's."""
    if raw.covariances is None or inflated.covariances is None or not len(raw):
        return 1.0
    ratio = np.trace(inflated.covariances, axis1=1, axis2=2) / np.trace(raw.covariances, axis1=1, axis2=2)
    return float(np.median(ratio))


@dataclass(frozen=True)
class InflatedSmoother:
    """The batch smoother of one window (smooth_windowed's `solver`; or of a whole short
    flight) solved as `solve_inflated_twice` does, both solves in the window's own process: the
    second starts from the first's solution and reuses its preintegrated IMU (smoother.
    SolveReuse), and applies the noise scales the window's first solve estimated.  Solved over
    the whole flight instead (first every window, then every window again with the flight's
    merged scales), the second pass started cold and rebuilt every IMU factor.  Before
    solve_inflated_twice, each window's noise-scale iteration took one to three solves before
    the inflated one; now the inflated solves carry the iteration on (BENCHMARKS.md, two17)."""

    inflation: CorrelationInflation

    def __call__(self, frame_times_ns, imu, raw: Trajectory, load_obs, **kwargs):
        from fusion.estimate.smoother import SolveReuse, smooth

        return solve_inflated_twice(
            smooth, frame_times_ns, imu, raw, load_obs, inflation=self.inflation, reuse=SolveReuse(), **kwargs
        )


def common_share(frames: Sequence[FrameCodeResiduals | None], cls: int, sum_sq: float) -> float:
    """`sum_sq` over the sum of squares of class `cls`'s whitened residuals in `frames`, at most 1
    (0 without residuals): a common error's share of every lag's rho (estimate_inflation)."""
    total = 0.0
    for fr in frames:
        if fr is None or not len(fr.payloads):
            continue
        r = np.asarray(fr.whitened, dtype=float)[np.asarray(fr.classes) == cls]
        total += float(np.sum(r[np.isfinite(r).all(axis=1)] ** 2))
    return min(sum_sq / total, 1.0) if total > 0 else 0.0


def estimate_inflation(
    traj: Trajectory,
    frames: Sequence[FrameCodeResiduals | None],
    class_covariances: Sequence[np.ndarray],
    class_scales: np.ndarray,
    apply: bool = True,
    exclude: dict[str, str] | None = None,
    common_sum_sq: dict[str, float] | None = None,
    placement_covariances: Sequence[np.ndarray] | None = None,
) -> tuple[dict, CorrelationInflation | None]:
    """Per corner class tau_c of the flight's PnP frames (`traj`, one pose per entry of `frames`
    and of `class_covariances` (k, 6, 6) G_c, in order), and the back ends' inflation when
    `apply` and some tau_c > 1 (None otherwise).  `class_scales` (k,): the variance factors
    applied to the classes (1 when none).  `exclude` {class: reason}: classes whose tau is
    reported but not applied (the reason in the report's `not_applied`).  `common_sum_sq`
    {class: sum of squares}: the part of the class's whitened residuals that a removed common
    error explains (the corner bias: cornerbias.BiasConsider.residual_sum_sq), whose consider
    term carries it.  A common error correlates the residuals at every lag by its share q of the
    class's sum of squares, so q is taken off every lag's rho before the sum (the inflation
    (tau - 1) s_c G_c is then 2 sum (rho - q) of the class's variance: that of the rest of the
    error, not counted twice); reported as `common_share`.
    `placement_covariances` (one (k, 6, 6) per frame, PnPResult.placement_covariance; None or
    empty when the floor codes are laid exactly): the part of each G_c that the codes' placement
    explains, common to the frames that see the same codes: it is taken out of the classes'
    terms and inflated on its own, as class PLACEMENT, by tau_p = 1 + 2 sum rho_p
    (`placement_autocorrelation`; reported as `placement`).  Returns the JSON-ready report (per
    class ClassCorrelation.as_dict, `applied`) and the inflation."""
    with_placement = placement_covariances is not None and len(placement_covariances) > 0
    if (
        len(frames) != len(traj)
        or len(class_covariances) != len(traj)
        or (with_placement and len(placement_covariances or ()) != len(traj))
    ):
        raise ValueError(
            f"correlation: {len(frames)} frames of residuals and {len(class_covariances)} of class "
            f"covariances for {len(traj)} PnP poses"
        )
    t = np.asarray(traj.timestamps_ns, dtype=np.int64)
    acf = class_autocorrelation(frame_indices(t), frames)
    report: dict = {"classes": {}, "applied": False, "max_lag": MAX_LAG, "z": Z_GATE}
    taus = np.ones(len(CORNER_CLASSES))
    for c, name in enumerate(CORNER_CLASSES):
        rho_c, pairs, n, codes = acf[name]
        share = 0.0
        if common_sum_sq and common_sum_sq.get(name, 0.0) > 0.0:
            share = common_share(frames, c, common_sum_sq[name])
            rho_c = rho_c - share
            acf[name] = (rho_c, pairs, n, codes)
        tau, n_used = integrated_time(rho_c, pairs)
        report["classes"][name] = ClassCorrelation(rho_c, pairs, n_used, tau, n, codes).as_dict()
        if share > 0.0:
            report["classes"][name]["common_share"] = round(share, 4)
        if exclude and name in exclude:
            report["classes"][name]["not_applied"] = exclude[name]
            continue
        taus[c] = tau
    rho_p = np.zeros(0)
    if with_placement:
        rho_p = placement_autocorrelation(frame_indices(t), frames)
        taus = np.append(taus, 1.0 + 2.0 * float(rho_p.sum()))
        report["placement"] = {"tau": round(float(taus[PLACEMENT]), 3), "lags_used": len(rho_p)}
    if not (apply and np.any(taus > 1.0)) or traj.covariances is None or not len(traj):
        return report, None
    # only the inflated classes' terms are kept (CorrelationInflation: the memory of long flights)
    active = np.flatnonzero(taus > 1.0)
    scales = np.asarray(class_scales, dtype=float)
    # in blocks of frames, packed as CorrelationInflation keeps them (no flight-long float64);
    # the placement's parts out of the classes, into a class of their own
    terms = np.empty((len(t), len(active), len(_TRIU[0])), dtype=np.float32)
    for lo in range(0, len(t), DIRECTIONAL_BLOCK_ROWS):
        hi = min(lo + DIRECTIONAL_BLOCK_ROWS, len(t))
        G = np.asarray(class_covariances[lo:hi], dtype=float) * scales[None, :, None, None]
        if with_placement:
            Gp = np.asarray((placement_covariances or [])[lo:hi], dtype=float) * scales[None, :, None, None]
            G = np.concatenate([G - Gp, Gp.sum(axis=1, keepdims=True)], axis=1)
        terms[lo:hi] = G[:, active][..., _TRIU[0], _TRIU[1]]
    # the lags as the estimator summed them (monotone-cut), so that a long average's factor
    # (CorrelationInflation.average_taus) tends to tau
    rho = np.zeros((len(taus), max(MAX_LAG, len(rho_p))))
    for c, name in enumerate(CORNER_CLASSES):
        kept = monotone_sequence(*acf[name][:2])
        rho[c, : len(kept)] = kept
    used = [
        report["classes"][name]["lags_used"] if taus[c] > 1.0 else 0 for c, name in enumerate(CORNER_CLASSES)
    ]
    if with_placement:
        rho[PLACEMENT, : len(rho_p)] = rho_p
        used.append(len(rho_p))
    dt = int(np.median(np.diff(t))) if len(t) > 1 else 0
    report["applied"] = True
    return report, CorrelationInflation(t, terms, rho, np.array(used), taus, dt // 2, classes=active)
