"""A fixed-lag smoother on iSAM2 whose Bayes tree is ordered by time: the incremental
smoother's engine (`smoother.smooth_incremental`).

GTSAM's `IncrementalFixedLagSmoother` puts every variable still in the window into one
constraint group and lets COLAMD order it, so the newest frame's variables land anywhere in the
Bayes tree: on the 60 s benchmark flight the path from them to the root grew by one frame per
update until iSAM2 re-eliminated the whole window (its batch step, at 65 % of the variables)
every ~10 frames, and the newest pose's marginal covariance, read every frame, needed the
separator marginals along that path.  Here every variable that iSAM2 orders is constrained by
its time stamp (older first; COLAMD orders only within one stamp), so

- the newest frame's variables form the root clique: an update re-eliminates the root clique
  and whatever the new factors, relinearisation and re-observed loads touch, and the newest
  pose's marginal is read from the root clique;
- no clique holds a variable newer than a variable of its separator, so the variables leaving
  the window (stamp before the newest stamp minus the lag) are leaves of the tree and are
  marginalised as they are (`ISAM2.marginalizeLeaves`; GTSAM's smoother first re-eliminates the
  cliques above them, `BayesTreeMarginalizationHelper`).

Why the second point holds: within one elimination a clique's frontal variables come before its
separator, so with time-ordered groups they are not newer; an orphaned subtree keeps its
cliques, and its separator's stamps can only have grown (a frame's stamp never changes, a load's
grows when it is observed again, and an observed variable is re-eliminated with every clique
above it).  So a child of a clique whose frontal variable leaves the window is no newer than
that variable and leaves too, and within a clique the leaving variables come first.

The constraint groups are the ranks of the stamps among the variables iSAM2 will order
(`ISAM2.predictUpdateInfo`: CCOLAMD refuses a group number above the number of variables it
orders).  Each update checks that iSAM2 re-eliminated as many variables as predicted; if not
(never seen), the whole window is re-eliminated in time order before anything is marginalised
(`stats['reorders']`).

Same factors, stamps, lag and marginalisations as GTSAM's smoother; the elimination order
differs, and with it iSAM2's partial back-substitution (wildfire) and so the relinearisation
steps taken: estimates move by rounding and by those steps (BENCHMARKS.md, "The incremental
smoother's time-ordered engine")."""

from __future__ import annotations

import gtsam
import numpy as np

BATCH_FRACTION = 0.65
"""iSAM2 re-eliminates every variable when the affected top of the tree (new variables not
counted) holds at least this share of its variables, new ones counted (ISAM2.cpp,
`kBatchThreshold`)."""


class TimeOrderedFixedLag:
    """The incremental smoother's fixed-lag engine (see the module docstring).

    `update(graph, values, stamps)`: `stamps` maps every key of `values` (the new variables)
    and every existing variable observed again to its time stamp in seconds; a variable keeps
    its latest stamp.  After the update, the variables whose stamp lies before the newest stamp
    minus `lag_s` are marginalised (as GTSAM's smoother: `findKeysBefore(now - lag)`).
    Estimates and marginals as `gtsam.IncrementalFixedLagSmoother`'s calls of the same names.
    `reorders`: updates after which the whole window was re-eliminated (a prediction missed)."""

    def __init__(self, lag_s: float, params: gtsam.ISAM2Params):
        self.isam = gtsam.ISAM2(params)
        self.lag_s = float(lag_s)
        self._relin_skip = int(params.relinearizeSkip) if params.enableRelinearization else 0
        self._stamp: dict[int, float] = {}  # every variable in the tree -> its stamp
        self._now = float("-inf")
        self._updates = 0
        self.reorders = 0

    def update(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float]
    ) -> None:
        isam, stamp = self.isam, self._stamp
        n_new = values.size()
        n_vars = len(stamp) + n_new  # iSAM2's variables once the new ones are added
        self._updates += 1
        if self._relin_skip and self._updates % self._relin_skip == 0:
            # iSAM2 brings its linear solution up to date before a relinearisation check;
            # predictUpdateInfo looks at the solution as it is, so bring it up to date here
            isam.getDelta()
        params = gtsam.ISAM2UpdateParams()
        affected = list(isam.predictUpdateInfo(graph, values, params)[0])
        stamp.update(stamps)
        self._now = max(self._now, max(stamps.values()))
        top = len(affected) - n_new  # the variables of the tree's top that iSAM2 removes
        batch = top >= BATCH_FRACTION * n_vars
        params.constrainedKeys = _time_groups(list(stamp) if batch else affected, stamp)
        result = isam.update(graph, values, params)
        # iSAM2's count: the removed top's variables and the new factors' (all, in a batch)
        if result.getVariablesReeliminated() != (n_vars if batch else top + graph.keys().size()):
            self._reorder_all()
        cutoff = self._now - self.lag_s
        leaving = [k for k, t in stamp.items() if t < cutoff]
        if leaving:
            leaves = gtsam.KeyList()
            for k in leaving:
                leaves.push_back(k)
                del stamp[k]
            isam.marginalizeLeaves(leaves)

    def _reorder_all(self) -> None:
        """Re-eliminate every variable in time order (an update without new factors)."""
        self.reorders += 1
        self._updates += 1
        params = gtsam.ISAM2UpdateParams()
        params.constrainedKeys = _time_groups(list(self._stamp), self._stamp)
        extra = gtsam.KeyList()
        for k in self._stamp:
            extra.push_back(k)
        params.extraReelimKeys = extra
        self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), params)

    def calculateEstimatePose3(self, key: int) -> gtsam.Pose3:
        return self.isam.calculateEstimatePose3(key)

    def calculateEstimateVector(self, key: int) -> np.ndarray:
        return self.isam.calculateEstimateVector(key)

    def calculateEstimateConstantBias(self, key: int) -> gtsam.imuBias.ConstantBias:
        return self.isam.calculateEstimateConstantBias(key)

    def calculateEstimatePoint3(self, key: int) -> np.ndarray:
        return self.isam.calculateEstimatePoint3(key)

    def marginalCovariance(self, key: int) -> np.ndarray:
        return self.isam.marginalCovariance(key)


class GtsamFixedLag:
    """`gtsam.IncrementalFixedLagSmoother` behind the same `update(graph, values, stamps)`:
    the engine the incremental smoother used before TimeOrderedFixedLag (kept to compare
    with, `smoother.FIXED_LAG_ENGINE`)."""

    def __init__(self, lag_s: float, params: gtsam.ISAM2Params):
        self.smoother = gtsam.IncrementalFixedLagSmoother(float(lag_s), params)
        self.reorders = 0

    def update(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float]
    ) -> None:
        self.smoother.update(graph, values, gtsam.FixedLagSmootherKeyTimestampMap(stamps))

    def calculateEstimatePose3(self, key: int) -> gtsam.Pose3:
        return self.smoother.calculateEstimatePose3(key)

    def calculateEstimateVector(self, key: int) -> np.ndarray:
        return self.smoother.calculateEstimateVector(key)

    def calculateEstimateConstantBias(self, key: int) -> gtsam.imuBias.ConstantBias:
        return self.smoother.calculateEstimateConstantBias(key)

    def calculateEstimatePoint3(self, key: int) -> np.ndarray:
        return self.smoother.calculateEstimatePoint3(key)

    def marginalCovariance(self, key: int) -> np.ndarray:
        return self.smoother.marginalCovariance(key)


def _time_groups(keys: list[int], stamp: dict[int, float]) -> gtsam.KeyGroupMap:
    """CCOLAMD constraint groups: each key's rank among the keys' distinct stamps (older
    first)."""
    rank = {t: i for i, t in enumerate(sorted({stamp[k] for k in keys}))}
    groups = gtsam.KeyGroupMap()
    for k in keys:
        groups.insert2(k, rank[stamp[k]])
    return groups
