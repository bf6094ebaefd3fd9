"""Variance-component estimation: how far each group of measurements' assumed noise is from what
a flight's residuals say, and the rescaling that makes the reported covariances honest on data
the noise model was not tuned for (issue 10, item 3).

Least squares with whitened residuals r = W (z - h(x)): when the assumed covariances are right,
each group g of measurements has E[chi2_g] = E[sum_{i in g} r_i^T r_i] = d_g, its redundancy

    d_g = sum_{i in g} (1 - h_ii),   h_ii = diag(A (A^T A)^-1 A^T)   (the hat matrix),

A the whitened Jacobian at the solution; the d_g add up to rows - unknowns.  The variance factor
s_g^2 = chi2_g / d_g estimates by how much group g's covariance is off; scaling that covariance by
s_g^2 and solving again, a few times, is Förstner's iterated variance-component estimator
(Förstner, "Ein Verfahren zur Schätzung von Varianz- und Kovarianzkomponenten", AVN 1979;
Koch, "Parameter Estimation and Hypothesis Testing in Linear Models", 1999, sec. 3.6.4).

Per-frame PnP has no other measurements: a frame with n codes has 8 n residuals and 6 unknowns,
so chi2_k has 8 n - 6 degrees of freedom and the flight's s^2 = sum chi2_k / sum (8 n_k - 6)
(the reference variance of the adjustment, Koch eq. 3.120), over every posed frame: PnP has
already left out the codes whose corners do not fit, and gating the heavy tail of blurred or
compressed corners (a quarter of the frames of a "realistic" flight beyond the 0.999 quantile)
would halve the scale that the pose errors show.

Scope of what a residual can tell: an error that the unknowns absorb (all four corners of a
single code shifted alike) leaves no residual, so the estimate is a lower bound of the
true error scale when such errors dominate; the smoother's groups see, in addition, the
disagreement of consecutive frames with the IMU.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.stats import chi2 as chi2_dist

from fusion.types import Choice, LoadObservation, Trajectory

log = logging.getLogger(__name__)

GATE_QUANTILE = 0.999
"""A sample whose chi2 / s^2 exceeds this quantile of its chi-square is an outlier, not noise."""
GATE_ITERATIONS = 10
"""Fixed-point iterations of the gated estimate (it settles in 3-4)."""
MIN_SCALE, MAX_SCALE = 1e-2, 1e4
"""Bounds of an applied variance factor (a wildly wrong model is reported, not trusted blindly)."""
MIN_DOF = 20.0
"""Fewer degrees of freedom than this: the estimate is too noisy to apply (it is still reported)."""
THIN_CLASS_ALPHA = 1e-3
"""A thin corner class (fewer than MIN_DOF) whose chi2 is beyond the 1 - this quantile of its
chi-square gets a warning (`thin_class_warnings`; the corner-bias gate's level, cornerbias.py)."""
SCALE_TOLERANCE = 0.1
"""The smoother stops re-solving once every applied group's chi2/dof is within 1 +- this."""
IMU_WARN_BAND = (0.5, 2.0)
"""A stated sensor's (STATED_SENSORS: IMU, velocity) chi2/dof outside this band: its stated noise is
probably wrong."""
HUTCHINSON_PROBES = 32
"""Most random probes of a group's leverage (group_leverages); groups with fewer rows are exact."""
HUTCHINSON_MIN_PROBES = 8
"""Fewest probes: a group stops drawing once its redundancy is known to REDUNDANCY_REL_SD."""
REDUNDANCY_REL_SD = 0.01
"""Target standard deviation of a group's Hutchinson redundancy, relative to it: 1 % of d_g,
below the chi-square's own relative noise sqrt(2 / d_g) for d_g < 20000 and a tenth of
SCALE_TOLERANCE."""
HUTCHINSON_SEED = 20240130
PROBE_BLOCK = 8
"""Probes per multi-right-hand-side solve in group_leverages (bounds its dense memory: 8 columns
of a 10-minute flight's 270 k unknowns are 17 MB)."""


class NoiseGroup(Choice):
    """Groups of measurements sharing one noise scale."""

    POSE = "pose"  # per-frame floor-camera poses (cam0, loosely coupled)
    CORNERS = "corners"  # floor-code corners (cam0, tightly coupled)
    LOAD = "load"  # load-code centres (cam1)
    FLOOR_CODE = "floor_code"  # as-built floor-code sightings (cam0): measured, not rescaled
    IMU = "imu"  # preintegrated IMU and bias random walk
    VELOCITY = "velocity"  # the velocity sensor's samples (vel0)
    OTHER = "other"  # priors, bridges


CAMERA_OF_GROUP = {NoiseGroup.POSE: "cam0", NoiseGroup.CORNERS: "cam0", NoiseGroup.LOAD: "cam1"}
"""The camera whose corner noise a group measures (CameraRole values)."""


@dataclass
class VarianceComponent:
    """One group's chi-square, its degrees of freedom (redundancy) and samples (frames or
    factors) used; `scale` = chi2 / dof, the variance factor (1 = the model is right)."""

    chi2: float
    dof: float
    n: int
    n_gated: int = 0

    @property
    def scale(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else math.nan

    @property
    def usable(self) -> bool:
        """Enough degrees of freedom to apply the scale."""
        return self.dof >= MIN_DOF and math.isfinite(self.scale) and self.scale > 0

    def as_dict(self) -> dict:
        return {
            "scale": self.scale,
            "sigma_factor": math.sqrt(self.scale) if self.scale >= 0 else math.nan,
            "chi2": self.chi2,
            "dof": self.dof,
            "n": self.n,
            "n_gated": self.n_gated,
        }


def clamp_scale(s2: float) -> float:
    return float(min(max(s2, MIN_SCALE), MAX_SCALE))


# =========================================================================== independent samples


def gated_variance_component(
    chi2_values: Sequence[float], dofs: Sequence[float], quantile: float | None = GATE_QUANTILE
) -> VarianceComponent:
    """s^2 = sum chi2_k / sum dof_k over the samples with chi2_k / s^2 within the `quantile` of
    their chi-square (fixed point from s^2 = the ungated estimate; `quantile` None: no gate);
    samples with dof <= 0 or a non-finite chi2 are left out.  The gate's truncation lowers the
    estimate by less than 1 - quantile relatively."""
    c = np.asarray(chi2_values, dtype=float).ravel()
    d = np.asarray(dofs, dtype=float).ravel()
    ok = np.isfinite(c) & (d > 0) & (c >= 0)
    c, d = c[ok], d[ok]
    if not len(c) or d.sum() <= 0:
        return VarianceComponent(0.0, 0.0, 0)
    keep = np.ones(len(c), bool)
    s2 = c.sum() / d.sum()
    if quantile is None:
        return VarianceComponent(float(c.sum()), float(d.sum()), len(c))
    bound = chi2_dist.ppf(quantile, d)
    for _ in range(GATE_ITERATIONS):
        new_keep = c <= bound * max(s2, 1e-300)
        if not new_keep.any():
            break
        s2_new = c[new_keep].sum() / d[new_keep].sum()
        converged = np.array_equal(new_keep, keep)
        keep, s2 = new_keep, s2_new
        if converged:
            break
    return VarianceComponent(float(c[keep].sum()), float(d[keep].sum()), int(keep.sum()), int((~keep).sum()))


def scale_trajectory(traj: Trajectory, s2: float) -> Trajectory:
    """A copy of `traj` with its covariances times `s2` (None stays None)."""
    if traj.covariances is None or s2 == 1.0:
        return traj
    return Trajectory(traj.name, traj.timestamps_ns, traj.T_world_body, traj.covariances * float(s2))


def scale_load_observations(observations: list[LoadObservation], s2: float) -> list[LoadObservation]:
    """Copies with the camera-frame covariance (the fused back ends' measurement) times `s2`."""
    if s2 == 1.0:
        return observations
    return [o if o.cov_cam is None else replace(o, cov_cam=o.cov_cam * float(s2)) for o in observations]


# =========================================================================== factor graphs


def factor_chi2(factor, values: gtsam.Values) -> float:
    """Squared Mahalanobis norm of a factor's residual under its base noise model (before any
    robust kernel)."""
    e = factor.unwhitenedError(values)
    nm = factor.noiseModel()
    if isinstance(nm, gtsam.noiseModel.Robust):
        nm = nm.noise()
    return float(nm.mahalanobisDistance(e)) ** 2


def group_leverages(
    lin: gtsam.GaussianFactorGraph,
    n_unknowns: int,
    factor_group: Sequence[int],
    n_groups: int,
    factor_rows: Sequence[int],
) -> np.ndarray:
    """(n_groups,) sum over each group's rows of the hat-matrix diagonal h_ii of the whitened
    Jacobian A of `lin` (factor i in group factor_group[i], with factor_rows[i] rows: its
    nonlinear factor's dim()), i.e. tr(A_g (A^T A)^-1 A_g^T).

    A^T A is factored once (sparse LU, symmetric mode, minimum-degree ordering); a group with at most
    HUTCHINSON_PROBES rows is summed exactly, row by row, a larger one by Hutchinson's estimator
    with Rademacher probes z (tr M = E[z^T M z]; Hutchinson, Commun. Stat. Simul.
    Comput. 18(3), 1989), M = A_g (A^T A)^-1 A_g^T, whose eigenvalues lie in [0, 1]: the
    estimate's standard deviation is below sqrt(2 tr M / probes), e.g. 2 % of a 600-dof group
    with 32 probes.  Probes are drawn PROBE_BLOCK at a time, from HUTCHINSON_MIN_PROBES up to
    HUTCHINSON_PROBES, until the mean's standard error (the probes' sample standard deviation
    / sqrt(probes)) is below REDUNDANCY_REL_SD of the group's redundancy rows - tr M (the
    large groups of a long flight stop at the minimum: their redundancy is thousands).  Seeded
    (HUTCHINSON_SEED), so a flight's result is reproducible.  Raises np.linalg.LinAlgError for a
    singular system."""
    A, _ = whitened_system(lin, n_unknowns, int(np.sum(factor_rows)))
    return _leverages(A, n_unknowns, factor_group, n_groups, factor_rows)


def whitened_system(
    lin: gtsam.GaussianFactorGraph, n_unknowns: int, m: int
) -> tuple[sp.csr_matrix, np.ndarray]:
    """The whitened Jacobian A (m x n_unknowns, CSR) and right-hand side b (m,) of `lin`, rows in
    factor order.  At the linearisation point b = -W e: a non-robust factor's rows of b hold its
    whitened residual, so their squared sum is its chi2 (factor_chi2)."""
    trip = lin.sparseJacobian_()  # 3 x nnz, 1-based (row, column, value); column n+1 is b
    # 3 x nnz doubles: ~0.4 GB on a 10-minute flight solved whole, ~0.1 GB a window; A's
    # entries are taken out as the int32 indices its CSR form keeps and the triplets let go
    # before it is built, so the temporaries are not stacked on each other at the smoother's
    # memory peak (the values and A itself are the same)
    keep = trip[1] <= n_unknowns  # 1-based: columns 1..n are A's, n + 1 is b
    b = np.zeros(m)
    rhs = ~keep
    b[trip[0][rhs].astype(np.int64) - 1] = trip[2][rhs]
    data = trip[2][keep]
    # scipy's own index type for A (int32 below 2^31 rows and columns): not converted again
    index = np.int32 if max(m, n_unknowns) < 2**31 - 1 else np.int64
    rows = trip[0][keep].astype(index) - 1
    cols = trip[1][keep].astype(index) - 1
    del trip, keep, rhs
    A = sp.csr_matrix((data, (rows, cols)), shape=(m, n_unknowns))
    return A, b


def _leverages(
    A: sp.csr_matrix,
    n_unknowns: int,
    factor_group: Sequence[int],
    n_groups: int,
    factor_rows: Sequence[int] | np.ndarray,
) -> np.ndarray:
    """group_leverages on the whitened Jacobian A."""
    sizes = np.asarray(factor_rows, dtype=int)
    try:
        # A^T A is symmetric positive definite: symmetric mode without pivoting keeps the
        # minimum-degree ordering's sparsity (SuperLU user guide, "symmetric mode"); on a
        # 60 s flight 1.3 M instead of 4.8 M nonzeros in L + U, factor and solves ~3x faster
        lu = spla.splu(
            (A.T @ A).tocsc(),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError as e:  # "Factor is exactly singular"
        raise np.linalg.LinAlgError(str(e)) from None
    row_group = np.repeat(np.asarray(factor_group, dtype=int), sizes)
    rng = np.random.default_rng(HUTCHINSON_SEED)
    out = np.zeros(n_groups)
    for g in range(n_groups):
        idx = np.flatnonzero(row_group == g)
        if not len(idx):
            continue
        AgT = A[idx].T.tocsc()
        if len(idx) <= HUTCHINSON_PROBES:  # every row of the group, exactly
            eye = np.eye(len(idx))
            blocks = range(0, len(idx), PROBE_BLOCK)
            out[g] = sum(float(np.sum(_quadratic(AgT, lu, eye[:, c : c + PROBE_BLOCK]))) for c in blocks)
            continue
        samples: list[float] = []
        while len(samples) < HUTCHINSON_PROBES:
            z = np.stack([rng.choice((-1.0, 1.0), len(idx)) for _ in range(PROBE_BLOCK)], axis=1)
            samples.extend(_quadratic(AgT, lu, z))
            trace = float(np.mean(samples))
            # the mean's standard error, from the probes themselves
            se = float(np.std(samples, ddof=1)) / math.sqrt(len(samples))
            if len(samples) >= HUTCHINSON_MIN_PROBES and se <= REDUNDANCY_REL_SD * (len(idx) - trace):
                break
        out[g] = float(np.mean(samples))
    if not np.all(np.isfinite(out)):
        raise np.linalg.LinAlgError("hat matrix: non-finite leverage")
    return out


def _quadratic(AgT, lu, z: np.ndarray) -> np.ndarray:
    """(columns,) z_j^T A_g (A^T A)^-1 A_g^T z_j for the columns z_j of z: b = A_g^T z in one
    multi-right-hand-side solve (one pass over the factors per block; dense memory
    n_unknowns x columns)."""
    b = np.asfortranarray(np.asarray(AgT @ z))
    return np.sum(b * lu.solve(b), axis=0)


def graph_variance_components(
    factors: Sequence,
    groups: Sequence[NoiseGroup],
    values: gtsam.Values,
    lin: gtsam.GaussianFactorGraph | None = None,
) -> dict[NoiseGroup, VarianceComponent]:
    """Each group's chi2 (factor_chi2 summed) and redundancy (rows minus leverage,
    group_leverages) at the solution `values` of the graph of `factors` (groups[i]: factor i's
    group).  `lin`: that graph linearised at `values`, if the caller has it.  A factor with a
    Gaussian noise model has its chi2 from the linearisation's right-hand side (whitened_system,
    the same number without a Python call per factor); a robust one from factor_chi2 (its
    linearisation is reweighted by the kernel)."""
    if lin is None:
        graph = gtsam.NonlinearFactorGraph()
        for f in factors:
            graph.add(f)
        lin = graph.linearize(values)
    if lin.size() != len(factors):
        raise np.linalg.LinAlgError("linearised graph does not match its factors")
    order = list(dict.fromkeys(groups))
    index = {g: i for i, g in enumerate(order)}
    rows = np.array([int(f.dim()) for f in factors], dtype=np.int64)
    n = values.dim()
    A, b = whitened_system(lin, n, int(rows.sum()))
    lev = _leverages(A, n, [index[g] for g in groups], len(order), rows)
    del A
    starts = np.r_[0, np.cumsum(rows)[:-1]]
    chi2 = np.add.reduceat(b**2, starts) if len(rows) else np.zeros(0)
    out = {g: VarianceComponent(0.0, -float(lev[index[g]]), 0) for g in order}
    for i, (f, g) in enumerate(zip(factors, groups)):
        comp = out[g]
        robust = isinstance(f.noiseModel(), gtsam.noiseModel.Robust)
        comp.chi2 += factor_chi2(f, values) if robust else float(chi2[i])
        comp.dof += int(rows[i])
        comp.n += 1
    return out


def imu_group(factor) -> bool:
    return isinstance(factor, (gtsam.CombinedImuFactor, gtsam.ImuFactor))


def factor_groups(factors: Sequence, robust_kinds: dict[int, str], skip, graph_size: int) -> list[NoiseGroup]:
    """The NoiseGroup of each factor of a smoother's final graph (graph_size factors): the
    problem's `factors` except those in `skip` (in order), then any priors the solver appended
    (OTHER).  A factor's group: its robust kind (`robust_kinds` by factor index), IMU for
    preintegrated IMU factors, else OTHER."""
    groups: list[NoiseGroup] = []
    for i, f in enumerate(factors):
        if i in skip:
            continue
        kind = robust_kinds.get(i)
        if kind is not None:
            groups.append(NoiseGroup(kind))
        else:
            groups.append(NoiseGroup.IMU if imu_group(f) else NoiseGroup.OTHER)
    return groups + [NoiseGroup.OTHER] * (graph_size - len(groups))


def problem_variance_components(
    factors: Sequence,
    robust_kinds: dict[int, str],
    skip,
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    lin: gtsam.GaussianFactorGraph | None = None,
) -> dict[NoiseGroup, VarianceComponent] | None:
    """Variance components of a smoother's final `graph` at its solution (`lin`: `graph`
    linearised there, when the caller has it): graph = the problem's
    `factors` except those in `skip` (in order), then any priors the solver appended (group
    OTHER).  A factor's group: its robust kind (pose, corners, load: `robust_kinds` by factor
    index, the NoiseGroup values), IMU for preintegrated IMU factors, else OTHER.  None when the
    linearised system is singular (then nothing is rescaled)."""
    groups = factor_groups(factors, robust_kinds, skip, graph.size())
    try:
        return graph_variance_components([graph.at(i) for i in range(graph.size())], groups, values, lin)
    except (np.linalg.LinAlgError, RuntimeError, ValueError) as e:
        log.debug("variance components not computed: %s", e)
        return None


# =========================================================================== iterated estimation


@dataclass
class NoiseScales:
    """Variance factors applied to each measurement group (1 = as modelled)."""

    pose: float = 1.0
    corners: float = 1.0
    load: float = 1.0
    imu: float = 1.0
    velocity: float = 1.0

    def of(self, group: NoiseGroup) -> float:
        return float(getattr(self, str(group), 1.0))


def scaled_imu(imu, scale: float):
    """`imu` (ImuData or None) with every noise density and random walk of its imu0 noise model
    times sqrt(`scale`) (a variance factor); the same object at scale 1.  The samples are shared,
    not copied."""
    if imu is None or scale == 1.0:
        return imu
    return replace(imu, noise=imu.noise.scaled(math.sqrt(scale)))


def imu_scale_of(report: dict | None) -> float:
    """The IMU noise scale the batch smoother applied (`solve_with_noise_scales`' report), 1 when
    none."""
    return float(((report or {}).get("imu") or {}).get("scale", 1.0))


def velocity_scale_of(report: dict | None) -> float:
    """The velocity sensor's noise scale the batch smoother applied, 1 when none."""
    return float(((report or {}).get("velocity") or {}).get("scale", 1.0))


STATED_SENSORS = {
    # where the user states it: an EuRoC folder's sensor.yaml, a Kalibr imu.yaml, a bag's metadata
    NoiseGroup.IMU: (
        "IMU",
        "the IMU's stated noise densities (imu0/sensor.yaml, Kalibr imu.yaml, a bag's metadata)",
    ),
    NoiseGroup.VELOCITY: (
        "velocity",
        "the velocity's stated noise_m_s (vel0/sensor.yaml, a video's velocity.yaml, a bag's metadata)",
    ),
}
"""The sensors whose noise the user states (a calibration, a datasheet) rather than the
project's own model: kept as stated inside IMU_WARN_BAND (next_noise_scales)."""


def next_noise_scales(scales: NoiseScales, comps: dict | None, pose_floor: float = 0.0) -> NoiseScales | None:
    """The iterated estimator's next scales: every applicable group (pose, corners, load) with
    enough degrees of freedom and chi2/dof off 1 by more than SCALE_TOLERANCE gets its scale
    multiplied by its chi2/dof (clamped; the pose group's at least `pose_floor`:
    FusionConfig.pose_scale_floor); None when none changes (converged).

    The sensors whose noise the user states (STATED_SENSORS: the IMU, the reference, and the
    velocity sensor) keep it while their chi2/dof is inside IMU_WARN_BAND; above it (the stated
    noise too small: an IMU datasheet's figures on a vibrating airframe, the common case; an
    optical-flow sensor over a poor floor) the scale is estimated like the cameras', never
    below 1 (a sensor quieter than stated is left as stated: conservative, and its chi2 below
    the band is only a warning)."""
    change = False
    # a sensor stated far too precise drags the estimate and so raises the others' residuals
    # too (an optical-flow sensor stated 10x too precise put the IMU's chi2/dof at 29): of the
    # stated sensors above the band and not yet scaled, only the worst is scaled in one step
    above = {
        g: c.scale
        for g in STATED_SENSORS
        if (c := (comps or {}).get(g)) is not None and c.usable and scales.of(g) == 1.0
        if c.scale > IMU_WARN_BAND[1]
    }
    worst = max(above, key=above.__getitem__) if above else None
    for g in STATED_SENSORS:
        c = (comps or {}).get(g)
        if c is None or not c.usable:
            continue
        now = scales.of(g)
        if now == 1.0:
            new = clamp_scale(c.scale) if g == worst else 1.0
        elif abs(c.scale - 1.0) > SCALE_TOLERANCE:
            new = max(1.0, clamp_scale(now * c.scale))
        else:
            new = now
        if new != now:
            scales = replace(scales, **{str(g): new})
            change = True
    for g in (NoiseGroup.POSE, NoiseGroup.CORNERS, NoiseGroup.LOAD):
        c = (comps or {}).get(g)
        if c is None or not c.usable or abs(c.scale - 1.0) <= SCALE_TOLERANCE:
            continue
        new = clamp_scale(scales.of(g) * c.scale)
        if g == NoiseGroup.POSE and new < pose_floor:
            if scales.of(g) == pose_floor:
                continue  # held at the floor already: nothing to solve again for
            new = pose_floor
        scales = replace(scales, **{str(g): new})
        change = True
    return scales if change else None


def first_solve_scales(comps: dict | None, pose_floor: float = 0.0) -> NoiseScales:
    """The scales that one solve at the nominal noise (all scales 1) reports for its groups
    (solve_with_noise_scales with no iteration: each camera's scale is its group's chi2/dof when
    usable, else 1; the pose group's at least `pose_floor`), clamped as apply_smoother_scales
    clamps them: what the batch smoother's inflated solve then applies to each group
    (correlation.solve_inflated_twice)."""
    out = NoiseScales()
    for g in (NoiseGroup.POSE, NoiseGroup.CORNERS, NoiseGroup.LOAD):
        c = (comps or {}).get(g)
        s2 = c.scale if c is not None and c.usable else 1.0
        if g == NoiseGroup.POSE:
            s2 = max(s2, pose_floor)
        out = replace(out, **{str(g): clamp_scale(s2)})
    return out


ResolvePredicate = Callable[[dict | None, Any], bool]
"""(variance components, SolveHealth) of a solve -> whether solve_with_noise_scales will solve
again after it: then that solve's covariances are never used and need not be computed."""


def solve_with_noise_scales(
    solve: Callable[..., Any],
    iterations: int,
    what: str = "smoother",
    pose_floor: float = 0.0,
    then: ResolvePredicate | None = None,
) -> tuple[Any, dict]:
    """Iterated variance-component estimation around `solve(scales, resolves=pred) ->
    FusionResult` (whose stats['variance_components'] maps NoiseGroup -> VarianceComponent at
    its solution): after each solve, every applicable group (pose, corners, load) with enough
    degrees of freedom has its scale multiplied by its chi2/dof and the flight is solved again
    (next_noise_scales), at most `iterations` times, stopping when all are within
    SCALE_TOLERANCE of 1.  `pred` (a ResolvePredicate) tells the solve, once it has its variance
    components, whether another solve follows (the same rule), so that it can skip the marginal
    covariances nobody will read.  Not applied (the first result, solved again with its
    covariances, report['not_applied'] says why) when the first solve skipped the outlier gate
    (the fixes disagree with the IMU: a fault) or when, rescaled, the IMU group's chi2/dof is
    outside IMU_WARN_BAND (the reference itself does not fit).  Returns the last result and a
    JSON-ready report: per group the applied scale, the final chi2/dof and dof; per camera the
    applied scale; per stated sensor (STATED_SENSORS: IMU, velocity) its final chi2/dof
    (`imu_chi2_per_dof`, `velocity_chi2_per_dof`; a warning outside IMU_WARN_BAND) and, when its
    stated noise was too small (next_noise_scales), the scale applied to it (`imu`, `velocity`;
    a warning too: the stated noise is a calibration the user should correct).  `then`: with
    no iteration left, the caller's own rule for whether it solves again after this
    (correlation.solve_inflated_twice's iteration), so that a solve it will discard skips its
    covariances too."""
    budget = max(int(iterations), 0)

    def resolves(scales_: NoiseScales, left: int) -> ResolvePredicate:
        if left <= 0 and then is not None:
            return then
        # Fixes that disagree with the IMU beyond the gate are a fault (units, world.yaml,
        # clock), not noise: the smoother's IMU-rejection path handles them, unscaled.
        return lambda comps, health: (
            left > 0 and not health.gate_skipped and next_noise_scales(scales_, comps, pose_floor) is not None
        )

    scales = NoiseScales()
    res = solve(scales, resolves=resolves(scales, budget))
    n_solves = 1
    first = res.stats.get("variance_components") or {}
    skip = "fixes disagree with the IMU" if res.health.gate_skipped else ""
    for i in range(0 if skip else budget):
        new = next_noise_scales(scales, res.stats.get("variance_components"), pose_floor)
        if new is None:
            break
        scales = new
        res = solve(scales, resolves=resolves(scales, budget - 1 - i))
        n_solves += 1
    comps = res.stats.get("variance_components") or {}
    imu = comps.get(NoiseGroup.IMU)
    lo, hi = IMU_WARN_BAND
    if n_solves > 1 and imu is not None and imu.usable and not lo <= imu.scale <= hi:
        # the IMU, the reference the camera scales are measured against, does not fit its own
        # noise model: the misfit cannot be attributed, so keep the model as configured
        skip = "the IMU does not fit its noise model"
        # the first solve was followed by another, so it skipped its covariances: again, whole
        res, scales = solve(NoiseScales()), NoiseScales()
        comps = res.stats.get("variance_components") or {}
    report: dict = {"solves": n_solves, "groups": {}, "cameras": {}}
    if skip:
        report["not_applied"] = skip
    for g, (name, where) in STATED_SENSORS.items():
        if scales.of(g) != 1.0:
            report[str(g)] = {"scale": scales.of(g), "sigma_factor": math.sqrt(scales.of(g))}
            report[f"{g}_warning"] = True
            log.warning(
                "%s: the %s factors' chi2/dof was %.2f at %s (ideal 1): too small; "
                "estimated and applied: x%.2f (sigma) for this flight",
                what,
                name,
                first[g].scale if g in first else math.nan,
                where,
                math.sqrt(scales.of(g)),
            )
    for g, c in comps.items():
        entry = c.as_dict()
        if g in CAMERA_OF_GROUP:
            entry["applied_scale"] = scales.of(g)
            cam = CAMERA_OF_GROUP[g]
            total = scales.of(g) * (c.scale if c.usable and not skip else 1.0)
            if g == NoiseGroup.POSE and not skip:
                total = max(total, pose_floor)
            report["cameras"][cam] = {
                "scale": total,
                "sigma_factor": math.sqrt(total),
                "dof": c.dof,
                "group": str(g),
            }
        report["groups"][str(g)] = entry
    for g, (name, where) in STATED_SENSORS.items():
        c = comps.get(g)
        if c is None or not c.usable:
            continue
        report[f"{g}_chi2_per_dof"] = c.scale
        lo, hi = IMU_WARN_BAND
        if not lo <= c.scale <= hi:
            log.warning(
                "%s: the %s factors' chi2/dof is %.2f (ideal 1, %.0f dof): %s seem %s",
                what,
                name,
                c.scale,
                c.dof,
                where,
                "too small" if c.scale > hi else "too large",
            )
            report[f"{g}_warning"] = True
    return res, report


def solve_noise_scaled(
    once: Callable, imu, raw: Trajectory, load_obs, config, then: ResolvePredicate | None = None
) -> tuple:
    """The batch smoother's hook: `once(imu, raw, load_obs, config, require_motion=True,
    resolves=None)` (`resolves`: solve_with_noise_scales' ResolvePredicate) solved with the noise
    scales of `solve_with_noise_scales` (raw pose covariances, tight corner
    covariances, load cov_cam) for config.noise_scale_iterations.  Returns the result (its
    stats['noise_scales'] the report, the raw components removed) and `scaled(imu, **kw)`, a
    solve at the final scales (the IMU-rejection retry)."""
    final = {"scales": NoiseScales()}

    def solve(scales: NoiseScales, imu_=imu, **kw):
        final["scales"] = scales
        return once(
            scaled_imu(imu_, scales.imu),
            scale_trajectory(raw, scales.pose),
            scale_load_observations(load_obs, scales.load) if load_obs else load_obs,
            replace(
                config,
                corner_noise_scale=config.corner_noise_scale * scales.corners,
                velocity_noise_scale=config.velocity_noise_scale * scales.velocity,
            ),
            **kw,
        )

    res, report = solve_with_noise_scales(
        solve, config.noise_scale_iterations, pose_floor=config.pose_scale_floor, then=then
    )
    res.stats.pop("variance_components", None)
    res.stats["noise_scales"] = report

    def scaled(imu_, **kw):
        alt = solve(final["scales"], imu_, **kw)
        comps = alt.stats.pop("variance_components", None) or {}
        alt.stats["noise_scales"] = dict(report, groups={str(g): c.as_dict() for g, c in comps.items()})
        return alt

    return res, scaled


def scale_pnp_trajectory(
    traj: Trajectory, stats_parts: Sequence, apply: bool = True
) -> tuple[Trajectory, dict]:
    """The per-frame PnP trajectory with its covariances times the flight's reprojection
    chi2/dof (`gated_variance_component` of the PnPStats parts' frame_chi2 / frame_dof), when
    `apply` and there are MIN_DOF degrees of freedom; and the JSON-ready report (camera cam0,
    scale, sigma_factor, chi2, dof, frames used and gated, applied)."""
    comp = gated_variance_component(
        [c for p in stats_parts for c in p.frame_chi2],
        [d for p in stats_parts for d in p.frame_dof],
        quantile=None,
    )
    applied = bool(apply and comp.usable)
    if applied:
        traj = scale_trajectory(traj, clamp_scale(comp.scale))
    if comp.usable:
        log.info(
            "PnP: corner noise %.2fx the model (chi2/dof %.2f over %.0f dof)",
            math.sqrt(comp.scale),
            comp.scale,
            comp.dof,
        )
    return traj, dict(comp.as_dict(), applied=applied, camera="cam0")


def pnp_class_components(stats_parts: Sequence) -> tuple[dict[str, VarianceComponent], np.ndarray | None]:
    """Per corner class (whitening.CORNER_CLASSES: refined, decoder) of a flight's PnP frames:
    its chi2, redundancy and frames, and the variance factors s (k,) that solve
    sum_frames T s = sum_frames chi2_c (Helmert's estimation, Helmert 1924; Koch 1999, sec. 3.6:
    PnPResult.class_redundancy T gives E[chi2_c] = sum_c' T[c, c'] s_c' at the poses solved with
    the modelled weights).  A class present with less than MIN_DOF redundancy ("thin") is not
    pooled with the others (their factor says nothing about its corners: clipping x2.6, 6
    refined sightings among 148 decoder ones, took the decoder's 0.28 and were then ~12x too
    optimistic, 86 % of the flight's PnP yaw information at NEES 108; BENCHMARKS.md, x26): its
    factor is its own chi2 / redundancy, never below 1 (too few degrees of freedom to trust a
    smaller one; `thin_class_factor`), and the others' are solved with it fixed.  None when no
    class has MIN_DOF, only one class is present, or the solve gives a non-positive or
    non-finite factor (then one pooled factor is the estimate)."""
    from fusion.qr.pnp.whitening import CORNER_CLASSES

    k = len(CORNER_CLASSES)
    chi2 = np.zeros(k)
    T = np.zeros((k, k))
    frames = np.zeros(k, dtype=int)
    for p in stats_parts:
        for c, t in zip(p.frame_class_chi2, p.frame_class_redundancy):
            chi2 += c
            T += t
            frames += np.asarray(t).sum(axis=1) > 0
    dof = T.sum(axis=1)
    comps = {
        name: VarianceComponent(float(chi2[i]), float(dof[i]), int(frames[i]))
        for i, name in enumerate(CORNER_CLASSES)
    }
    present = np.flatnonzero(dof > 0)
    usable = np.array([i for i in present if comps[CORNER_CLASSES[i]].usable], dtype=int)
    thin = np.array([i for i in present if not comps[CORNER_CLASSES[i]].usable], dtype=int)
    if len(present) < 2 or not len(usable):
        return comps, None
    scales = np.ones(k)
    for i in thin:
        scales[i] = thin_class_factor(comps[CORNER_CLASSES[i]])
    try:  # the usable classes' equations with the thin ones' factors moved to the right side
        s_usable = np.linalg.solve(
            T[np.ix_(usable, usable)], chi2[usable] - T[np.ix_(usable, thin)] @ scales[thin]
        )
    except np.linalg.LinAlgError:
        return comps, None
    if not (np.all(np.isfinite(s_usable)) and np.all(s_usable > 0)):
        return comps, None
    scales[usable] = [clamp_scale(float(x)) for x in s_usable]
    return comps, scales


def thin_class_factor(comp: VarianceComponent) -> float:
    """The variance factor of a corner class with too little redundancy to estimate its own
    (`pnp_class_components`): its chi2 / redundancy when above 1 (clamped), else 1.  A thin
    class is never scaled down: a small chi2 on few degrees of freedom is as likely luck, and
    its covariance scaled down would be trusted by every back end."""
    s = comp.scale
    return clamp_scale(s) if math.isfinite(s) and s > 1.0 else 1.0


def thin_class_warnings(report: dict) -> list[str]:
    """One line per corner class of a PnP noise report (`scale_pnp_trajectory_by_class`) whose
    factor could not be estimated (too few degrees of freedom) while its own chi2 is beyond the
    1 - THIN_CLASS_ALPHA quantile of its chi-square: its covariance (scaled by that chi2 / dof) is probably
    still too small, and the frames that rest on it may be overconfident."""
    out = []
    for name, c in (report.get("classes") or {}).items():
        if c.get("thin") and c.get("significant"):
            out.append(
                f"PnP: the {name} corners' noise is {math.sqrt(c['scale']):.1f}x the model on only "
                f"{c['dof']:.0f} degrees of freedom (fewer than {MIN_DOF:.0f}): a rough factor, "
                "their covariances may still be too small"
            )
    return out


def scale_pnp_trajectory_by_class(
    traj: Trajectory, stats_parts: Sequence, apply: bool = True
) -> tuple[Trajectory, dict]:
    """`scale_pnp_trajectory`, with one variance factor per corner class when the flight has
    both classes with enough redundancy (`pnp_class_components`): each pose's covariance
    becomes cov + sum_c (s_c - 1) G_c (G_c its class's share, PnPResult.class_covariance), the
    covariance of the pose solved with the modelled weights when class c's corner covariance is
    s_c times the model (the sandwich H^-1 (sum_c s_c H_c) H^-1); a gimbal's roll-pitch prior is
    not rescaled.  Otherwise the pooled factor, as `scale_pnp_trajectory`.  The report is
    `scale_pnp_trajectory`'s (the pooled factor) with `classes` (per class: scale, sigma_factor,
    chi2, dof, frames with the class; the factor applied) and `by_class` (whether applied)."""
    comps, scales = pnp_class_components(stats_parts)
    names = list(comps)
    if scales is None:
        out, report = scale_pnp_trajectory(traj, stats_parts, apply)
        report["by_class"] = False
    else:
        _, report = scale_pnp_trajectory(traj, stats_parts, apply=False)
        report["applied"] = bool(apply)
        report["by_class"] = bool(apply)
        out = traj
        G = [g for p in stats_parts for g in p.frame_class_covariance]
        if apply and traj.covariances is not None:
            if len(G) != len(traj):
                raise ValueError(f"PnP: {len(G)} frames of class covariances for {len(traj)} poses")
            covs = traj.covariances + np.einsum("c,ncij->nij", scales - 1.0, np.asarray(G))
            out = Trajectory(traj.name, traj.timestamps_ns, traj.T_world_body, covs)
        log.info(
            "PnP: corner noise by class %s",
            ", ".join(f"{n} {math.sqrt(s):.2f}x ({comps[n].dof:.0f} dof)" for n, s in zip(names, scales)),
        )
    report["classes"] = {
        n: dict(comps[n].as_dict(), applied_scale=float(scales[i]) if scales is not None else None)
        for i, n in enumerate(names)
    }
    for n, c in report["classes"].items():
        comp = comps[n]
        if comp.dof > 0 and not comp.usable and scales is not None:
            # a thin class (pnp_class_components): its own factor, and whether its chi2 alone
            # is significant
            c["thin"] = True
            c["significant"] = bool(comp.chi2 > chi2_dist.ppf(1.0 - THIN_CLASS_ALPHA, comp.dof))
    report["thin_class_warnings"] = thin_class_warnings(report)
    for line in report["thin_class_warnings"]:
        log.warning("%s", line)
    return out, report


def applied_class_scales(report: dict) -> np.ndarray:
    """(k,) the variance factor each corner class's covariance got from
    `scale_pnp_trajectory_by_class` (its report): the class factors when applied by class, the
    pooled factor for all when applied pooled, else ones."""
    from fusion.qr.pnp.whitening import CORNER_CLASSES

    out = np.ones(len(CORNER_CLASSES))
    if report.get("by_class"):
        for i, name in enumerate(CORNER_CLASSES):
            s = (report.get("classes") or {}).get(name, {}).get("applied_scale")
            if s is not None:
                out[i] = float(s)
    elif report.get("applied"):
        out[:] = clamp_scale(float(report["scale"]))
    return out


def apply_smoother_scales(report: dict | None, raw: Trajectory, load_obs):
    """(raw, load_obs, corner_scale) rescaled with the batch smoother's final per-camera scales
    (`solve_noise_scaled`'s report: cam0 for the poses and corners, cam1 for the loads), for the
    back ends that cannot estimate them themselves (incremental smoother, EKF)."""
    cams = (report or {}).get("cameras", {})
    s0 = clamp_scale(float(cams.get("cam0", {}).get("scale", 1.0)))
    s1 = clamp_scale(float(cams.get("cam1", {}).get("scale", 1.0)))
    return scale_trajectory(raw, s0), (scale_load_observations(load_obs, s1) if load_obs else load_obs), s0


def apply_smoother_sensor_scales(report: dict | None, imu, config):
    """(imu, config) with the batch smoother's final scales (`solve_noise_scaled`'s report) of
    what is not an input array: the IMU's noise (`scaled_imu`), the tight corner factors' (cam0's,
    `corner_noise_scale`) and the velocity sensor's (`velocity_noise_scale`); with
    `apply_smoother_scales`, for the back ends after the smoother and its own inflated solve."""
    s0 = clamp_scale(float((report or {}).get("cameras", {}).get("cam0", {}).get("scale", 1.0)))
    config = replace(
        config,
        corner_noise_scale=config.corner_noise_scale * s0,
        velocity_noise_scale=config.velocity_noise_scale * velocity_scale_of(report),
    )
    return scaled_imu(imu, imu_scale_of(report)), config


def nis_component(nis: Sequence[float], dims: Sequence[int]) -> VarianceComponent:
    """Normalised innovation squared of a filter's updates as a variance component: for a
    consistent filter each update's NIS is chi-square with its dimension (Bar-Shalom, Li &
    Kirubarajan, 2001, sec. 5.4.2), so sum NIS / sum dim ~ 1 (gated as above)."""
    return gated_variance_component(nis, dims)


def noise_summary(pnp_stats: dict, fused_stats: dict) -> dict:
    """metrics.json's `noise_scales`: the variance factors (1 = the noise model is right) per
    estimator and camera: PnP's (cam0, from its reprojection chi2/dof), the batch smoother's
    per camera (relative to the PnP-scaled input) and the IMU's chi2/dof, the EKF's pose NIS;
    and the floor corners' common bias (`pnp_corner_bias`, fusion.estimate.cornerbias)."""
    out: dict = {}
    if "noise_scale" in pnp_stats:
        out["pnp"] = pnp_stats["noise_scale"]
    if "corner_bias" in pnp_stats:
        out["pnp_corner_bias"] = pnp_stats["corner_bias"]
    if "correlation" in pnp_stats:
        out["pnp_correlation"] = pnp_stats["correlation"]
    smoother = fused_stats.get("smoother", {}).get("noise_scales")
    if smoother:
        out["smoother"] = smoother
    nis = fused_stats.get("ekf", {}).get("pose_nis")
    if nis:
        out["ekf_pose_nis"] = nis
    return out


def summary_line(summary: dict) -> str:
    """One line for the terminal summary, '' when there is nothing to say."""
    parts = []
    pnp = summary.get("pnp")
    if pnp and pnp.get("by_class"):
        parts.append(
            "PnP cam0 "
            + " ".join(
                f"{n} {c['applied_scale']:.2f} ({c['dof']:.0f} dof)"
                for n, c in pnp["classes"].items()
                if c["dof"]
            )
        )
    elif pnp and pnp.get("dof"):
        parts.append(f"PnP cam0 {pnp['scale']:.2f} ({pnp['dof']:.0f} dof)")
    sm = summary.get("smoother") or {}
    for cam, c in sorted((sm.get("cameras") or {}).items()):
        parts.append(f"smoother {cam} {c['scale']:.2f} ({c['dof']:.0f} dof)")
    for g, (name, _) in STATED_SENSORS.items():
        if f"{g}_chi2_per_dof" in sm:
            scale = float((sm.get(str(g)) or {}).get("scale", 1.0))
            parts.append(
                f"{name} {sm[f'{g}_chi2_per_dof']:.2f}"
                + (f" at its noise x{math.sqrt(scale):.2f} (sigma)" if scale != 1.0 else "")
                + (" (check its noise)" if sm.get(f"{g}_warning") else "")
            )
    nis = summary.get("ekf_pose_nis")
    if nis and nis.get("dof"):
        parts.append(f"EKF pose NIS/dim {nis['scale']:.2f}")
    bias = summary.get("pnp_corner_bias")
    if bias and bias.get("applied"):
        parts.append(
            "cam0 corner bias removed ("
            + ", ".join(
                f"{b['bias_px'][0]:+.4f} / {b['bias_px'][1]:+.4f} px at {b['side_px'][0]:.0f}"
                f"-{b['side_px'][1]:.0f} px"
                for b in bias["bins"]
            )
            + f"; T {bias['statistic']:.0f} > {bias['threshold']:.1f})"
        )
    corr = summary.get("pnp_correlation")
    if corr and corr.get("applied"):
        parts.append(
            "cam0 corner errors correlated over frames (back ends' input x "
            + ", ".join(
                [f"{n} {c['tau']:.1f}" for n, c in corr["classes"].items() if c["tau"] > 1.0]
                + ([f"placement {corr['placement']['tau']:.1f}"] if "placement" in corr else [])
            )
            + ")"
        )
    return ("noise chi2/dof (1 = as modelled; applied): " + ", ".join(parts)) if parts else ""
