"""The batched Levenberg–Marquardt engine shared by the floor and load solvers.

K independent pose problems (one per start) are iterated together: one vectorised evaluation of
the whitened normal equations per step for all of them.  A problem is any object with the
`PoseProblems` methods (fusion/qr/pnp/floor.py: body pose from floor codes; load.py: a load
code's pose in the camera).  Poses are (R (K, 3, 3), t (K, 3)) pairs, perturbed on the right as
each problem's `retract` says.

Written by hand rather than as one GTSAM graph per frame: one vectorised evaluation serves the
views of many frames at once, which is what makes batched PnP cheap per frame
(scripts/bench_pnp.py measures it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from fusion.qr.pnp.whitening import CORNER_COORDINATES

POSE_DOF = 6
"""Tangent dimension of a pose: [rx, ry, rz, tx, ty, tz] (GTSAM Pose3 order)."""
MAX_ITERATIONS = 20
"""Iteration cap of the LM; from the IPPE / SQPnP starts it converges in 2-4."""
CONVERGED_DECREMENT = 1e-6
"""Converged when the predicted decrease of the whitened cost, g^T H^-1 g, is below this fraction
of the cost (plus DECREMENT_FLOOR): the pose is then within about 1e-3 sqrt(cost / dof) standard
deviations of the optimum, and exact in a noise-free view."""
DECREMENT_FLOOR = 1e-15
"""Absolute part of the convergence test (a noise-free view has cost ~0)."""
LAMBDA_START = 1e-3
"""Damping lambda (H_ii <- (1 + lambda) H_ii) after the first step that raised the cost."""
LAMBDA_UP = 10.0
"""Factor on lambda after a step that raised the cost."""
LAMBDA_DOWN = 0.1
"""Factor on lambda after a step that lowered it (to zero once at or below LAMBDA_START)."""
LAMBDA_GIVE_UP = 1e6
"""A problem whose lambda exceeds this cannot descend: it stops, unconverged."""
START_MARGIN_CHI2 = 100.0
"""A start is refined only when its whitened cost is within 2x + this of the best start's of the
same view (refinement lowers a cost by about the 6 pose dof, rarely by tens: this keeps every
start that could end within AMBIGUITY_CHI2 of the best, and skips mirror solutions)."""
AMBIGUITY_CHI2 = 4.0
"""Two solutions whose summed squared residuals differ by less than this * sigma^2 are ambiguous;
the solver's prior then decides (floor: the more level; load: symbol up nearest world up)."""
MAX_REPROJECTION_RMS_PX = 2.0
"""A solution whose corner reprojection RMS exceeds this is treated as an outlier."""
MAX_CONDITION_NUMBER = 1e14
"""An information matrix more ill-conditioned than this gives no covariance (as
fusion.qr.reprojection.covariance_from_information)."""
SAME_MINIMUM_MAHALANOBIS2 = 0.01
"""Two refined poses closer than this (squared, in the information metric: a tenth of a standard
deviation) are one minimum; the LM stops within about 1e-3."""
SAME_MINIMUM_MIN_TRACE = 2.98
"""trace(R_a^T R_b) below this (rotations more than ~0.14 rad apart): certainly two minima."""


@dataclass
class NormalEquations:
    """Whitened Gauss-Newton normal equations of K problems at their current poses:
    H (K, 6, 6) = J^T W^T W J (the information; its inverse is the pose covariance),
    g (K, 6) = J^T W^T W r, cost (K,) = |W r|^2 (a chi-square value), J = d(px)/d(xi),
    r the px residuals, W the whitening (fusion/qr/pnp/whitening.py)."""

    H: np.ndarray
    g: np.ndarray
    cost: np.ndarray

    @classmethod
    def from_augmented(cls, Jr: np.ndarray, W: np.ndarray) -> NormalEquations:
        """Jr (K, N, 2, 7) = [J | r] of K problems (J d(px)/d(xi) of N = 4 n corners, r their px
        residuals), W (K, n, 8, 8) their whitening: H, g and cost all come from one product of
        the whitened [J | r] (K, 2N, 7), whose Gram matrix is [[H, g], [g^T, cost]]."""
        K, N = Jr.shape[:2]
        M = (W @ Jr.reshape(K, N // 4, CORNER_COORDINATES, POSE_DOF + 1)).reshape(K, 2 * N, POSE_DOF + 1)
        gram = M.transpose(0, 2, 1) @ M
        return cls(gram[:, :POSE_DOF, :POSE_DOF], gram[:, :POSE_DOF, POSE_DOF], gram[:, POSE_DOF, POSE_DOF])

    def __len__(self) -> int:
        return len(self.cost)

    def finite(self) -> np.ndarray:
        """(K,) mask of the problems whose equations are all finite."""
        return np.isfinite(self.H).all(axis=(1, 2)) & np.isfinite(self.g).all(axis=1) & np.isfinite(self.cost)

    def take(self, idx) -> NormalEquations:
        """The equations of problems `idx` (an index array or a mask), copied."""
        return NormalEquations(self.H[idx], self.g[idx], self.cost[idx])

    def put(self, idx, other: NormalEquations) -> None:
        """Overwrite the equations of problems `idx` with `other`'s, in place."""
        self.H[idx], self.g[idx], self.cost[idx] = other.H, other.g, other.cost

    def copy(self) -> NormalEquations:
        return NormalEquations(self.H.copy(), self.g.copy(), self.cost.copy())


class PoseProblems(Protocol):
    """K least-squares pose problems that the LM can iterate together."""

    def subset(self, idx: np.ndarray) -> PoseProblems:
        """The problems `idx` (an index array or a mask)."""

    def residual_px(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K, N, 2) reprojection errors (px) at poses R (K, 3, 3), t (K, 3)."""

    def normal_equations(self, R: np.ndarray, t: np.ndarray) -> NormalEquations:
        """The whitened normal equations at poses R (K, 3, 3), t (K, 3)."""

    def retract(self, R: np.ndarray, t: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The poses moved by the tangent steps delta (K, 6)."""


@dataclass
class Starts:
    """K starting poses: owner (K,) the view (frame or code) each belongs to, R (K, 3, 3),
    t (K, 3) in the frames of the problem they start."""

    owner: np.ndarray
    R: np.ndarray
    t: np.ndarray


@dataclass
class LMResult:
    """Poses R (K, 3, 3), t (K, 3) where the LM stopped, the normal equations there, and a (K,)
    mask of the problems that converged."""

    R: np.ndarray
    t: np.ndarray
    normal: NormalEquations
    converged: np.ndarray


@dataclass
class RefinedStarts:
    """Refined starts: owner (K,), R (K, 3, 3), t (K, 3), the normal equations at them and the
    px residuals (K, N, 2) (`refine_starts`)."""

    owner: np.ndarray
    R: np.ndarray
    t: np.ndarray
    normal: NormalEquations
    residual_px: np.ndarray

    @property
    def rms_px(self) -> np.ndarray:
        """(K,) reprojection RMS (px) over each problem's corner coordinates."""
        return np.sqrt(np.mean(self.residual_px**2, axis=(1, 2)))


def _steps(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(K, 6) solutions of H delta = -g; NaN for a singular H."""
    try:
        return np.linalg.solve(H, -g[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:  # one is singular: one at a time
        delta = np.full(g.shape, np.nan)
        for i in range(len(g)):
            try:
                delta[i] = np.linalg.solve(H[i], -g[i])
            except np.linalg.LinAlgError:
                pass
        return delta


def levenberg_marquardt(
    problems: PoseProblems,
    R: np.ndarray,
    t: np.ndarray,
    normal: NormalEquations,
    max_iter: int = MAX_ITERATIONS,
) -> LMResult:
    """Minimise each of K problems' whitened cost |W (h(x) - z)|^2 over its pose x = (R, t), from
    the starts R (K, 3, 3), t (K, 3) with their normal equations `normal`, all K in one
    evaluation per step; a start whose equations are not finite is left as it is, unconverged.
    Not converged: those that ran out of iterations or could not descend.

    Gauss-Newton steps, damped (Levenberg-Marquardt, H_ii <- (1 + lambda) H_ii; Nocedal & Wright,
    "Numerical Optimization", 2006, Sec. 10.3) only after a step that raised the cost; a problem
    stops when its predicted decrease g^T H^-1 g is below CONVERGED_DECREMENT cost: from IPPE /
    SQPnP starts that takes 2-4 evaluations."""
    R, t, normal = R.copy(), t.copy(), normal.copy()
    idx = np.flatnonzero(normal.finite())  # the problems still iterating
    if len(idx) < len(R):
        problems = problems.subset(idx)
    Ra, ta, eq = R[idx], t[idx], normal.take(idx)  # their current poses and equations
    lam = np.zeros(len(idx))
    converged = np.zeros(len(R), dtype=bool)
    diag = np.arange(POSE_DOF)

    def store() -> None:  # the active problems' state -> the outputs
        R[idx], t[idx] = Ra, ta
        normal.put(idx, eq)

    for _ in range(max_iter):
        if len(idx) == 0:
            break
        H = eq.H
        if lam.any():
            H = H.copy()
            H[:, diag, diag] *= (1.0 + lam)[:, None]
        delta = _steps(H, eq.g)
        decrease = -np.einsum("ki,ki->k", eq.g, delta)
        going = decrease > CONVERGED_DECREMENT * eq.cost + DECREMENT_FLOOR  # False for NaN
        if not going.all():  # converged ones leave the batch
            store()
            converged[idx[~going & np.isfinite(decrease)]] = True
            idx, Ra, ta, eq, lam, delta = (
                idx[going],
                Ra[going],
                ta[going],
                eq.take(going),
                lam[going],
                delta[going],
            )
            if len(idx) == 0:
                break
            problems = problems.subset(going)
        R_new, t_new = problems.retract(Ra, ta, delta)
        eq_new = problems.normal_equations(R_new, t_new)
        better = eq_new.cost <= eq.cost  # False for NaN
        if better.all():
            Ra, ta, eq = R_new, t_new, eq_new
            if lam.any():
                lam = np.where(lam <= LAMBDA_START, 0.0, LAMBDA_DOWN * lam)
            continue
        Ra[better], ta[better] = R_new[better], t_new[better]
        eq.put(better, eq_new.take(better))
        lam = np.where(
            better,
            np.where(lam <= LAMBDA_START, 0.0, LAMBDA_DOWN * lam),
            np.where(lam == 0.0, LAMBDA_START, LAMBDA_UP * lam),
        )
        alive = lam <= LAMBDA_GIVE_UP  # else give up: it cannot descend
        if not alive.all():
            store()
            idx, Ra, ta, eq, lam = idx[alive], Ra[alive], ta[alive], eq.take(alive), lam[alive]
            problems = problems.subset(alive)
    store()
    return LMResult(R, t, normal, converged)


def refine_starts(problems: PoseProblems, starts: Starts) -> RefinedStarts:
    """Refine `starts` of `problems` (one problem per start): all evaluated in one batch, those
    whose whitened cost is within 2x + START_MARGIN_CHI2 of their view's best refined by
    `levenberg_marquardt`.  Returns those that converged, and all refined starts of a view none
    of whose starts converged (an unconverged start is no minimum: its cost could pass for a
    second, ambiguous one)."""
    normal = problems.normal_equations(starts.R, starts.t)
    cost = np.where(normal.finite(), normal.cost, np.inf)
    owner = starts.owner
    best: dict[int, float] = {}
    for o, c in zip(owner.tolist(), cost.tolist()):
        best[o] = min(best.get(o, math.inf), c)
    keep = np.flatnonzero(cost <= 2.0 * np.array([best[o] for o in owner.tolist()]) + START_MARGIN_CHI2)
    sub = problems.subset(keep)
    res = levenberg_marquardt(sub, starts.R[keep], starts.t[keep], normal.take(keep))
    own, R, t, eq = owner[keep], res.R, res.t, res.normal
    if not res.converged.all():
        good = set(own[res.converged].tolist())
        use = np.array([c or o not in good for o, c in zip(own.tolist(), res.converged.tolist())])
        sub, own, R, t, eq = sub.subset(use), own[use], R[use], t[use], eq.take(use)
    return RefinedStarts(own, R, t, eq, sub.residual_px(R, t))


def covariances(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 6, 6) information matrices -> covariances H^-1 (K, 6, 6) through one batched
    eigen-decomposition, and a (K,) mask of the valid ones (finite, positive definite, condition
    number <= MAX_CONDITION_NUMBER)."""
    ok = np.isfinite(H).all(axis=(1, 2))
    Hs = np.where(ok[:, None, None], H, np.eye(POSE_DOF))
    lam, V = np.linalg.eigh(Hs)
    ok &= (lam[:, 0] > 0) & (lam[:, -1] <= MAX_CONDITION_NUMBER * lam[:, 0])
    lam = np.where(ok[:, None], lam, 1.0)
    C = (V / lam[:, None, :]) @ V.transpose(0, 2, 1)
    return 0.5 * (C + C.transpose(0, 2, 1)), ok


def same_pose(
    R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray, tol_rad: float, tol_m: float
) -> bool:
    """Whether poses (R_a, t_a), (R_b, t_b) differ by at most `tol_rad` in rotation and `tol_m`
    in position."""
    c = 0.5 * (float(np.vdot(R_a, R_b)) - 1.0)  # cos(angle): trace(R_a^T R_b) = <R_a, R_b>
    return c >= math.cos(tol_rad) and float(np.linalg.norm(t_a - t_b)) <= tol_m


def same_minimum(R_a: np.ndarray, t_a: np.ndarray, H_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> bool:
    """Whether refined poses a and b are the same minimum of a cost with information H_a at a:
    (R_b, t_b) = (R_a, t_a) Exp(xi) with xi^T H_a xi < SAME_MINIMUM_MAHALANOBIS2."""
    D = R_a.T @ R_b
    if np.trace(D) < SAME_MINIMUM_MIN_TRACE:
        return False
    xi = np.array(
        [
            0.5 * (D[2, 1] - D[1, 2]),
            0.5 * (D[0, 2] - D[2, 0]),
            0.5 * (D[1, 0] - D[0, 1]),
            *(R_a.T @ (t_b - t_a)),
        ]
    )
    return float(xi @ H_a @ xi) < SAME_MINIMUM_MAHALANOBIS2
