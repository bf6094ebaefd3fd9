"""A floor-camera corner bias common to a whole flight: estimated from the PnP residuals,
removed from the PnP poses when significant, and its estimate's own uncertainty carried into
every pose covariance as a "consider" term (issue 10.3; BENCHMARKS.md "Defocus σ").

Why: a bias shared by every frame (defocus r 1: each floor code looks ~0.01 px taller) moves
every PnP pose the same way by ~0.9σ.  Each frame's χ² cannot see it (the pose absorbs most of
it) and the fused back ends, which treat the frames as independent, average the noise down
~1/sqrt(n) but not the bias: smoother NEES 54.  Over a flight, though, the part of the bias the
pose cannot absorb (the Schur-reduced normal equations of fusion.qr.pnp.bias) is seen at 10σ.

The bias is a dilation of every refined code (fusion.qr.pnp.bias), one per code-size bin.
Estimate (generalised least squares with the pose as nuisance; Koch 1999, sec. 3.2.5 on reduced
normal equations): b = N^-1 y with N = sum_k A_k^T M_k A_k, y = sum_k A_k^T M_k r_k, and
Cov(b) = s^2 N^-1, s^2 the flight's PnP variance factor (fusion.estimate.variance).
Which bins are judged (issue 10.1/10.3 `gate` session): a bin is *determined* when
GATE_SIGMAS σ_b <= MAX_BIAS_PX for each of its parameters (σ_b from Cov(b)): only then can the
flight tell a dilation of the model's size (<= MAX_BIAS_PX) from one beyond it.  A bin that is
not determined (e.g. the 90-128 px bin of the 30 ms rolling-shutter bench flights, a few frames
whose pose absorbs the dilation: σ ≈ 0.25 px against 0.006 px on the same flights' global-shutter
renders) is not judged; it stays in the joint estimate (its dilation is a nuisance of the
others': b is solved jointly, so the determined bins' estimate and covariance are the marginal
ones).  A flight with such a bin keeps its poses (`all_determined`, reported, no warning):
removing the determined bins only, with the undetermined one's size and σ in the consider term,
was measured and not kept (scripts/bench_rolling_shutter.py 2 m/s / 30 ms, seeds 0 / 1 / 2:
smoother 0.01659 / 0.01430 / 0.01603 → 0.01701 / 0.01452 / 0.01611 cm, PnP within ±0.6 %;
with the shift alone, no consider term, seed 0 0.01683: on those flights the dilation the
residuals show is not a pose bias the shift removes, while on the global-shutter flights the
same shift takes the smoother 0.01356 → 0.01290 cm; BENCHMARKS.md `gate` session).
Significance: over the determined bins' parameters d, T = b_d^T Cov(b)_dd^-1 b_d ~ χ²(|d|)
when there is no bias; the correction is made only when T exceeds its (1 - GATE_ALPHA)
quantile, so a flight without a bias keeps its poses and covariances bit for bit (the earlier
ungated correction, ~0.002 px off on the clean flight, took its smoother NEES 5.9 → 9.8;
BENCHMARKS.md fifth session).  Size: the flight's bias is `too_large` (reported, not removed)
only when some determined parameter is confidently beyond MAX_BIAS_PX, |b| - GATE_SIGMAS σ_b >
MAX_BIAS_PX (before: max |b| over every bin, however poorly determined, switched the removal off
on every 30 ms bench flight).
Correction: each PnP pose is moved by -S_k b (S_k its first-order sensitivity to the bias).
Consider term (Schmidt's consider covariance; Bierman 1977, ch. VI; Tapley, Schutz & Born 2004,
sec. 6.2): the corrected pose still carries S_k (b_true - b), an error common to all frames.
Its covariance is not Cov(b) alone: the two-number dilation model is itself an approximation
(on the defocus r 2 flight the estimate matched the true dilation to 0.002 px, yet removing it
took the PnP bias from 0.47 to 0.64σ and the smoother's NEES from 7.1 to 12.3: another error
the dilation had partly cancelled; BENCHMARKS.md, eighth session), so the model's error is
taken as large as the correction itself: C = Cov(b) + b b^T.  S_k C S_k^T is added to the
covariance of the PnP pose and, after
the fusion, to the fused pose's (that sum is what no per-frame covariance can say: the back
ends would average it down as if independent).  Adding it to the fused output rather than to a
state in the graph is first order and takes the fused pose's sensitivity to be the nearest PnP
frame's (the fused estimate near a frame is a local average of PnP poses whose S_k change
slowly with the codes in view); tight coupling (corners in the smoother) is left alone."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2 as chi2_dist

from fusion.estimate.common import nearest_frames
from fusion.geometry import se3_exp
from fusion.qr.pnp.bias import BIN_PARAMS, N_PARAMS, FrameBiasTerms, bin_range_px
from fusion.types import Trajectory

log = logging.getLogger(__name__)

GATE_ALPHA = 1e-3
"""False-alarm probability of the significance gate on a flight without a bias."""
MIN_FRAMES = 20
"""Fewer posed frames with bias terms than this: no estimate (too few to tell bias from noise)."""
MAX_BIAS_PX = 0.1
"""A significant dilation larger than this (px) is reported and not removed (a counted warning,
`too_large`): the model is a small bias, the correction first order, and the refined corners'
own mean error is 0.013-0.04 px on the renders (BENCHMARKS.md); on the few-frame flights the
estimate was 1-5 px with T < 10 (ill-conditioned: single codes, whose pose absorbs a dilation)."""
GATE_SIGMAS = 3.0
"""k of the size gate (module docstring): a bin is determined when k σ_b <= MAX_BIAS_PX (its
σ_b <= 0.033 px), and too large when |b| - k σ_b > MAX_BIAS_PX (a normal tail of 0.0013 per
parameter: a bin at the limit is not called too large by its noise)."""


@dataclass
class CornerBias:
    """A flight's common corner bias: `bias_px` (p,) (fusion.qr.pnp.bias.N_PARAMS: BIN_PARAMS per
    code-size bin; 0 in the bins without codes), `covariance_px2` (p, p) Cov(b) (its noise only),
    `statistic` T = b_d^T Cov(b)_dd^-1 b_d over the determined bins' parameters d (`determined`;
    χ²(|d|) without a bias), `threshold` the gate (0 / 0 when no bin is determined), `frames` the
    frames used; `significant` when T > threshold."""

    bias_px: np.ndarray
    covariance_px2: np.ndarray
    statistic: float
    threshold: float
    frames: int

    @property
    def significant(self) -> bool:
        return bool(self.statistic > self.threshold)

    @property
    def consider_px2(self) -> np.ndarray:
        """(p, p) what is left of the bias after the correction: Cov(b) + b b^T (the estimate's
        noise, and the bias model's own error taken as large as the correction itself)."""
        return self.covariance_px2 + np.outer(self.bias_px, self.bias_px)

    def bins(self) -> list[int]:
        """The size bins with codes (a non-zero variance)."""
        k = len(BIN_PARAMS)
        var = np.diag(self.covariance_px2).reshape(-1, k)
        return [int(j) for j in np.flatnonzero(np.any(var > 0, axis=1))]

    @property
    def sigma_px(self) -> np.ndarray:
        """(p,) σ_b of each parameter (0 in the bins without codes)."""
        return np.sqrt(np.maximum(np.diag(self.covariance_px2), 0.0))

    @property
    def determined(self) -> np.ndarray:
        """(p,) bool: the parameters of the bins with codes whose every parameter has
        GATE_SIGMAS σ_b <= MAX_BIAS_PX (the only ones judged)."""
        return _determined(self.covariance_px2)

    @property
    def too_large(self) -> bool:
        """Some determined parameter confidently beyond MAX_BIAS_PX: |b| - GATE_SIGMAS σ_b."""
        excess = np.abs(self.bias_px) - GATE_SIGMAS * self.sigma_px
        return bool(np.any(excess[self.determined] > MAX_BIAS_PX))

    @property
    def all_determined(self) -> bool:
        """Every size bin with codes is determined (the removal's condition)."""
        return bool(np.all(self.determined[np.diag(self.covariance_px2) > 0]))

    def as_dict(self, applied: bool) -> dict:
        """JSON-ready: per size bin with codes its side range (px), bias and σ ([u, v] px) and
        whether it is determined (judged; the flight is corrected only when all are)."""
        k = len(BIN_PARAMS)
        sd, det = self.sigma_px, self.determined
        return {
            "params": list(BIN_PARAMS),
            "bins": [
                {
                    "side_px": list(bin_range_px(j)),
                    "bias_px": [float(x) for x in self.bias_px[k * j : k * j + k]],
                    "sigma_px": [float(x) for x in sd[k * j : k * j + k]],
                    "determined": bool(det[k * j]),
                }
                for j in self.bins()
            ],
            "statistic": float(self.statistic),
            "threshold": float(self.threshold),
            "frames": int(self.frames),
            "significant": self.significant,
            "too_large": self.too_large,
            "all_determined": self.all_determined,
            "applied": bool(applied),
        }


def estimate_corner_bias(terms: Sequence[FrameBiasTerms | None], variance_factor: float) -> CornerBias | None:
    """The flight's `CornerBias` from the posed frames' `terms` (PnPStats.frame_bias) and the
    flight's PnP variance factor s^2 (chi2/dof); None with fewer than MIN_FRAMES frames, a
    non-finite factor or singular normal equations (e.g. no refined code)."""
    used = [t for t in terms if t is not None]
    if len(used) < MIN_FRAMES or not (math.isfinite(variance_factor) and variance_factor > 0):
        return None
    N = np.zeros((N_PARAMS, N_PARAMS))
    y = np.zeros(N_PARAMS)
    for t in used:  # frame order, whatever the chunks: the same sums on any number of workers
        N[np.ix_(t.params, t.params)] += t.normal_q
        y[t.params] += t.rhs_q
    N = 0.5 * (N + N.T)
    active = np.flatnonzero(np.diag(N) > 0)  # the size bins with codes
    if not len(active):
        return None
    Na = N[np.ix_(active, active)]
    try:
        Ninv = np.linalg.inv(Na)
    except np.linalg.LinAlgError:
        return None
    if not (np.all(np.isfinite(Ninv)) and np.all(np.linalg.eigvalsh(Na) > 0)):
        return None
    b = np.zeros(len(y))
    b[active] = Ninv @ y[active]
    cov = np.zeros((len(y), len(y)))
    cov[np.ix_(active, active)] = variance_factor * Ninv
    d = np.flatnonzero(_determined(cov))
    if len(d):  # the marginal test of the determined bins (the others a nuisance of the joint fit)
        statistic = float(b[d] @ np.linalg.solve(cov[np.ix_(d, d)], b[d]))
        threshold = float(chi2_dist.ppf(1.0 - GATE_ALPHA, len(d)))
    else:
        statistic = threshold = 0.0
    return CornerBias(
        bias_px=b, covariance_px2=cov, statistic=statistic, threshold=threshold, frames=len(used)
    )


def _determined(covariance_px2: np.ndarray) -> np.ndarray:
    """(p,) bool: parameters of the size bins with codes whose every parameter has GATE_SIGMAS
    σ_b <= MAX_BIAS_PX (CornerBias.determined)."""
    var = np.diag(covariance_px2).reshape(-1, len(BIN_PARAMS))
    ok = np.all(var > 0, axis=1) & np.all(GATE_SIGMAS * np.sqrt(np.maximum(var, 0.0)) <= MAX_BIAS_PX, axis=1)
    return np.repeat(ok, len(BIN_PARAMS))


@dataclass
class BiasConsider:
    """An error common to every PnP frame, as a consider term of the poses: the PnP frames'
    stamps (n,) and sensitivities (n, 6, p), and the error's covariance (p, p).  Made for a
    corrected flight's bias uncertainty (Cov(b), `correct_pnp_trajectory`) and for the stated
    intrinsics' error (`intrinsics_consider`).  `residual_sum_sq`:
    the removed bias's share of the frames' whitened PnP residuals, sum_f b^T N_f b (N_f = A^T M A,
    FrameBiasTerms.normal: |M A b|^2, the bias as the residuals see it once each pose absorbed
    its part), for the time-correlation estimate (fusion.estimate.correlation: a common error
    correlates the residuals at every lag, and this term already carries it)."""

    timestamps_ns: np.ndarray
    sensitivities: np.ndarray
    covariance_px2: np.ndarray
    residual_sum_sq: float = 0.0

    def covariances(self, timestamps_ns: np.ndarray, window_s: float = 0.0) -> np.ndarray:
        """(m, 6, 6) consider covariances S Cov(b) S^T at `timestamps_ns`, S the nearest PnP
        frame's sensitivity; with `window_s` > 0, the mean of S Cov(b) S^T over the PnP frames
        within window_s of each stamp (the nearest one where there is none): a fused pose is a
        weighted mean of the fixes around it, so its share of the common error spans their
        sensitivities, not one frame's (whose S Cov(b) S^T has rank p < 6)."""
        out = np.zeros((len(timestamps_ns), 6, 6))
        self._add_windowed(out, np.asarray(timestamps_ns, dtype=np.int64), window_s)
        return out

    def add_to(self, traj: Trajectory, window_s: float = 0.0, in_place: bool = False) -> Trajectory:
        """`traj` with the consider covariances added (unchanged without covariances).
        `in_place`: into traj's own covariance array, which the caller owns: a 30-minute flight's
        fused covariances are 15 MB, whose copy beside the original had raised `fusion batch`'s
        report worker by as much (949 -> 964 MiB)."""
        if traj.covariances is None or not len(traj):
            return traj
        own = (
            in_place
            and isinstance(traj.covariances, np.ndarray)
            and traj.covariances.dtype == float
            and traj.covariances.flags.writeable
        )
        covs = traj.covariances if own else np.array(traj.covariances, dtype=float)
        self._add_windowed(covs, np.asarray(traj.timestamps_ns, dtype=np.int64), window_s)
        return traj if own else Trajectory(traj.name, traj.timestamps_ns, traj.T_world_body, covs)

    def _add_windowed(self, out: np.ndarray, t: np.ndarray, window_s: float, block: int = 4096) -> None:
        """`covariances(t, window_s)` added into `out` (m, 6, 6) (window_s 0: the nearest frame's),
        `block` stamps at a time, so
        that a 30-minute flight's terms (54,000 frames) need a few MB, not five arrays of
        (n, 6, 6) (they had raised `fusion batch`'s report worker by 37 MiB)."""
        near = nearest_frames(self.timestamps_ns, t)
        if window_s <= 0.0:  # the nearest frame's
            for a in range(0, len(t), block):
                S = self.sensitivities[near[a : a + block]]
                out[a : a + block] += np.einsum("nip,pq,njq->nij", S, self.covariance_px2, S)
            return
        w = int(round(window_s * 1e9))
        lo = np.searchsorted(self.timestamps_ns, t - w, side="left")
        hi = np.searchsorted(self.timestamps_ns, t + w, side="right")
        for a in range(0, len(t), block):
            sl = slice(a, a + block)
            f0 = int(min(lo[sl].min(), near[sl].min()))
            f1 = int(max(hi[sl].max(), near[sl].max() + 1))
            S = np.asarray(self.sensitivities[f0:f1], dtype=float)
            per_frame = np.einsum("nip,pq,njq->nij", S, self.covariance_px2, S)
            cum = np.concatenate([np.zeros((1, 6, 6)), np.cumsum(per_frame, axis=0)])
            n = hi[sl] - lo[sl]
            mean = (cum[hi[sl] - f0] - cum[lo[sl] - f0]) / np.maximum(n, 1)[:, None, None]
            empty = n == 0
            mean[empty] = per_frame[near[sl][empty] - f0]
            out[sl] += mean


def correct_pnp_trajectory(
    traj: Trajectory, terms: Sequence[FrameBiasTerms | None], variance_factor: float, apply: bool = True
) -> tuple[Trajectory, dict | None, BiasConsider | None]:
    """The flight's PnP trajectory (one pose per entry of `terms`, in order) with the common
    corner bias removed and its consider covariance added, when `apply` and the bias is
    significant; the JSON-ready report (None when there is no estimate); and the BiasConsider
    for the fused back ends (None when nothing was applied)."""
    if len(terms) != len(traj):
        raise ValueError(f"corner bias: {len(terms)} frames of bias terms for {len(traj)} PnP poses")
    est = estimate_corner_bias(terms, variance_factor)
    if est is None:
        return traj, None, None
    # a flight with a bin not determined keeps its poses (module docstring: removing the
    # determined bins alone made the 30 ms rolling-shutter bench flights' smoother worse)
    applied = bool(apply and est.significant and not est.too_large and est.all_determined)
    if apply and est.significant and est.too_large:
        # (the run's named warning is pipeline.corner_bias_too_large_warning's)
        log.info(
            "corner_bias_too_large: a common floor-corner dilation of up to %.3f px (T = %.1f), "
            "above %.2f px by more than %g sigma: reported, not removed",
            float(np.max(np.abs(est.bias_px[est.determined]))),
            est.statistic,
            MAX_BIAS_PX,
            GATE_SIGMAS,
        )
    k = len(BIN_PARAMS)
    log.info(
        "PnP: common corner bias %s px (T = %.1f, gate %.1f)%s",
        ", ".join(
            f"{est.bias_px[k * j]:+.4f} / {est.bias_px[k * j + 1]:+.4f} at {lo:.0f}-{hi:.0f} px"
            + ("" if est.determined[k * j] else f" (not determined: sigma {est.sigma_px[k * j]:.3f})")
            for j in est.bins()
            for lo, hi in [bin_range_px(j)]
        ),
        est.statistic,
        est.threshold,
        ": removed" if applied else ("" if est.all_determined else ": kept (a size bin not determined)"),
    )
    if not applied:
        return traj, est.as_dict(False), None
    p = len(est.bias_px)
    S = np.zeros((len(terms), 6, p))
    for i, t in enumerate(terms):
        if t is not None:
            S[i][:, t.params] = t.sensitivity_q
    dxi = -S @ est.bias_px  # (n, 6): xi_true ≈ xi_est - S b
    T = np.stack([T_wb @ se3_exp(d) for T_wb, d in zip(traj.T_world_body, dxi)])
    residual_sum_sq = sum(
        float(est.bias_px[t.params] @ t.normal_q @ est.bias_px[t.params]) for t in terms if t is not None
    )
    stamps = np.asarray(traj.timestamps_ns, dtype=np.int64)
    consider = BiasConsider(stamps, S, est.consider_px2, residual_sum_sq)
    out = Trajectory(traj.name, traj.timestamps_ns, T, traj.covariances)
    return consider.add_to(out), est.as_dict(True), consider


FUSED_CONSIDER_WINDOW_S = 1.0
"""The span (s, either side) of PnP frames whose intrinsics sensitivities a fused pose's consider
term averages (BiasConsider.covariances): a back end's pose is a weighted mean of the fixes
around it (and trades tilt with the accelerometer bias over seconds), so its share of the common
error spans their sensitivities, not the nearest frame's alone.  Chosen on the demo flight with
its focal length 0.5 % or its principal point 1.5 / 1.0 px off (0, 0.5, 1 and 2 s: the smoother's
NEES 111, 15.0, 11.3 and 3.7 / 43, 11.8, 6.6 and 3.7 with the focal lengths' errors then taken
independent); measured on flights it was not chosen on in BENCHMARKS.md, seventeenth session."""


def intrinsics_consider(
    traj: Trajectory, terms: Sequence[FrameBiasTerms | None], sigmas_px: np.ndarray
) -> BiasConsider | None:
    """The floor camera's intrinsics error as a consider term of every pose: the PnP frames'
    (one per entry of `terms`, in order) sensitivities to [fu, fv, cu, cv]
    (FrameBiasTerms.intrinsics_sensitivity; zero where a frame has none) with covariance
    diag(`sigmas_px`^2) (CameraModel.intrinsics_sigmas).  A focal length off by e in relative
    terms puts every frame's camera e farther from the floor: no number of frames, and no back
    end, averages it down (the IMU would see it only through vertical accelerations), so the
    pipeline adds it to every output pose's covariance after the fusion and the health checks,
    not to the back ends' inputs.  None when every sigma is 0 or no frame has a sensitivity."""
    sig = np.asarray(sigmas_px, dtype=float)
    if len(terms) != len(traj):
        raise ValueError(f"intrinsics consider: {len(terms)} frames of terms for {len(traj)} PnP poses")
    if not np.any(sig > 0.0) or all(t is None or t.intrinsics_sensitivity is None for t in terms):
        return None
    S = np.zeros((len(terms), 6, len(sig)), dtype=np.float32)
    for i, t in enumerate(terms):
        if t is not None and t.intrinsics_sensitivity is not None:
            S[i] = t.intrinsics_sensitivity
    stamps = np.asarray(traj.timestamps_ns, dtype=np.int64)
    return BiasConsider(stamps, S, intrinsics_covariance(sig))


def intrinsics_covariance(sigmas_px: np.ndarray) -> np.ndarray:
    """(4, 4) covariance of the error in [fu, fv, cu, cv] from its 1-sigma `sigmas_px`: the two
    focal lengths' errors fully correlated (a lens's focal length is off, or drifts with focus
    and temperature, by one factor in both directions; their ratio is the sensor's pixel aspect,
    known far better), the principal point's independent.  Taken independent, fu against fv
    reads as a stretched image, which PnP explains by tilting the camera: 5 mrad of tilt and 6
    mm of lateral shift per frame on the demo flight from a 0.2 % sigma, an error calibrations do
    not make (BENCHMARKS.md, seventeenth session)."""
    s = np.asarray(sigmas_px, dtype=float)
    C = np.diag(s**2)
    C[0, 1] = C[1, 0] = s[0] * s[1]
    return C
