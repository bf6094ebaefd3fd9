"""The incremental smoother's time-ordered fixed-lag engine (fusion.estimate.fixedlag) against
GTSAM's IncrementalFixedLagSmoother.

On a linear problem (vector variables, prior and between factors: linearisation is exact) both
engines marginalise the same variables at the same updates, so every estimate and marginal
agrees to rounding whatever the elimination order; that is checked on a chain of frames with
landmarks that leave the window and come back (a new variable with a prior from the old
marginal, as the incremental smoother does with loads).  The smoother itself is compared on the
synthetic flight of tests/test_estimate.py, where the engines differ by the relinearisation
steps taken.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fusion.estimate import fixedlag
from fusion.estimate import smoother as sm
from fusion.estimate.fixedlag import GtsamFixedLag, TimeOrderedFixedLag
from tests.test_estimate import FRONT_CAM, make_flight

FPS = 10.0
LAG_S = 0.5


def _params() -> gtsam.ISAM2Params:
    """iSAM2 with a full back-substitution at every update (wildfire threshold 0): its partial
    one skips changes below the threshold (1e-3 by default), which depends on the tree."""
    p = gtsam.ISAM2Params()
    p.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))
    p.setFactorization("CHOLESKY")
    p.relinearizeSkip = 3
    p.findUnusedFactorSlots = True
    return p


def _x(k: int) -> int:
    return gtsam.symbol("x", k)


def _l(j: int, g: int) -> int:
    return gtsam.symbol("l", 1000 * g + j)


def run_chain(engine, n_frames: int = 120, n_landmarks: int = 4, seed: int = 0) -> dict:
    """Drive `engine` through a linear random-walk chain with intermittently seen landmarks;
    return every frame's estimate and marginal covariance, and the final landmark marginals."""
    rng = np.random.default_rng(seed)
    walk = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    fix = gtsam.noiseModel.Isotropic.Sigma(3, 0.3)
    sight = gtsam.noiseModel.Diagonal.Sigmas([0.05, 0.08, 0.2])
    truth = np.cumsum(rng.normal(0, 0.1, (n_frames, 3)), axis=0)
    land = rng.normal(0, 3, (n_landmarks, 3))
    # each landmark is seen in bursts separated by gaps longer than the lag
    seen = rng.random((n_frames, n_landmarks)) < 0.5
    seen &= (np.arange(n_frames)[:, None] // 9 + np.arange(n_landmarks)) % 3 != 0
    gen = [-1] * n_landmarks
    last = [-np.inf] * n_landmarks
    kept: dict[int, tuple] = {}
    est, cov = [], []
    for k in range(n_frames):
        t = k / FPS
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        v.insert(_x(k), truth[k] + rng.normal(0, 0.05, 3))
        stamps = {_x(k): t}
        if k == 0:
            g.add(gtsam.PriorFactorVector(_x(0), truth[0], fix))
        else:
            g.add(gtsam.BetweenFactorVector(_x(k - 1), _x(k), truth[k] - truth[k - 1], walk))
        if k % 4 == 0:
            g.add(gtsam.PriorFactorVector(_x(k), truth[k] + rng.normal(0, 0.3, 3), fix))
        for j in range(n_landmarks):
            if gen[j] >= 0 and last[j] < t - LAG_S and j not in kept:
                kept[j] = (
                    engine.calculateEstimateVector(_l(j, gen[j])),
                    engine.marginalCovariance(_l(j, gen[j])),
                )
        for j in np.flatnonzero(seen[k]).tolist():
            if gen[j] < 0 or j in kept:
                gen[j] += 1
                key = _l(j, gen[j])
                if j in kept:
                    p, c = kept.pop(j)
                    g.add(gtsam.PriorFactorVector(key, p, gtsam.noiseModel.Gaussian.Covariance(c)))
                    v.insert(key, p)
                else:
                    v.insert(key, truth[k] + land[j] + rng.normal(0, 0.5, 3))
            key = _l(j, gen[j])
            g.add(gtsam.BetweenFactorVector(_x(k), key, land[j] - truth[k] + rng.normal(0, 0.05, 3), sight))
            stamps[key] = t
            last[j] = t
        engine.update(g, v, stamps)
        est.append(engine.calculateEstimateVector(_x(k)))
        cov.append(engine.marginalCovariance(_x(k)))
    loads = {
        j: kept.get(j)
        or (engine.calculateEstimateVector(_l(j, gen[j])), engine.marginalCovariance(_l(j, gen[j])))
        for j in range(n_landmarks)
        if gen[j] >= 0
    }
    return {
        "est": np.array(est),
        "cov": np.array(cov),
        "loads": loads,
        "generations": sum(g + 1 for g in gen),
    }


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_time_ordered_engine_equals_gtsam_smoother_on_a_linear_chain(seed):
    engine = TimeOrderedFixedLag(LAG_S, _params())
    a = run_chain(engine, seed=seed)
    b = run_chain(GtsamFixedLag(LAG_S, _params()), seed=seed)
    assert a["generations"] > 4  # landmarks did leave the window and come back
    np.testing.assert_allclose(a["est"], b["est"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a["cov"], b["cov"], rtol=1e-9, atol=1e-12)
    for j in b["loads"]:
        np.testing.assert_allclose(a["loads"][j][0], b["loads"][j][0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(a["loads"][j][1], b["loads"][j][1], rtol=1e-9, atol=1e-12)
    assert engine.reorders == 0
    # the window holds the last LAG_S of frames (and the landmarks seen in it), nothing older
    assert max(engine._stamp.values()) - min(engine._stamp.values()) <= LAG_S + 1e-9


def test_missed_prediction_reorders_the_window_and_keeps_the_solution():
    """If iSAM2 re-eliminates other variables than predicted (here: the prediction is made to
    miss a variable), the whole window is re-eliminated in time order before anything leaves it,
    and the solution is unchanged."""

    class Missing:
        """An ISAM2 whose predicted affected set lacks its largest key every 7th update."""

        def __init__(self, isam):
            self.isam, self.n = isam, 0

        def __getattr__(self, name):
            return getattr(self.isam, name)

        def predictUpdateInfo(self, *args):
            self.n += 1
            keys, batch = self.isam.predictUpdateInfo(*args)
            if self.n % 7 == 0:
                keys = gtsam.KeySet(sorted(keys)[:-1]) if len(keys) > 1 else keys
            return keys, batch

    engine = TimeOrderedFixedLag(LAG_S, _params())
    engine.isam = Missing(engine.isam)
    a = run_chain(engine, seed=3)
    b = run_chain(GtsamFixedLag(LAG_S, _params()), seed=3)
    assert engine.reorders > 0
    np.testing.assert_allclose(a["est"], b["est"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a["cov"], b["cov"], rtol=1e-9, atol=1e-12)


def test_time_groups_are_stamp_ranks():
    stamp = {10: 0.5, 11: 0.2, 12: 0.5, 13: 0.9}
    groups = fixedlag._time_groups([10, 11, 12, 13], stamp)
    assert [groups.at(k) for k in (10, 11, 12, 13)] == [1, 0, 1, 2]


@pytest.fixture(scope="module")
def flight():
    # 20 s at 30 fps with a 2 s blackout and loads (re-observed after leaving the window)
    return make_flight(seed=5, duration_s=20.0, gaps=((8.0, 10.0),))


def test_incremental_smoother_engines_agree(flight, monkeypatch):
    """The incremental smoother on the time-ordered engine and on GTSAM's smoother: the same
    problem, so poses, per-frame covariances and loads agree up to the relinearisation steps
    each took (here 1e-9 of them), with no missed prediction."""
    # loads out of sight for a while (longer than the lag): a new variable when seen again
    t0 = flight.frame_t[0]
    hidden = {"B7": (4.0, 6.0), "C3": (11.0, 16.0)}
    obs = [
        o
        for o in flight.load_obs
        if not (
            hidden.get(o.load_id, (0, 0))[0]
            <= (o.timestamp_ns - t0) * 1e-9
            < hidden.get(o.load_id, (0, 0))[1]
        )
    ]
    args = (flight.frame_t, flight.imu, flight.raw, obs, FRONT_CAM)
    fast = sm.smooth_incremental(*args)
    monkeypatch.setattr(sm, "FIXED_LAG_ENGINE", "gtsam")
    ref = sm.smooth_incremental(*args)
    a, b = fast.trajectory, ref.trajectory
    np.testing.assert_array_equal(a.timestamps_ns, b.timestamps_ns)
    sigma_pos = np.sqrt(np.einsum("nii->ni", b.covariances[:, 3:, 3:]))
    dp = np.linalg.norm(a.T_world_body[:, :3, 3] - b.T_world_body[:, :3, 3], axis=1)
    assert (dp / sigma_pos.min(axis=1)).max() < 1e-6
    sa, sb = np.sqrt(np.einsum("nii->ni", a.covariances)), np.sqrt(np.einsum("nii->ni", b.covariances))
    assert np.abs(sa / sb - 1).max() < 1e-6
    assert fast.stats["load_generations"] == ref.stats["load_generations"] > 0
    for la, lb in zip(fast.loads.loads, ref.loads.loads):
        assert la.load_id == lb.load_id
        assert np.linalg.norm(la.p_world - lb.p_world) < 1e-2 * np.sqrt(np.trace(lb.cov_world))
    assert fast.stats["engine_reorders"] == 0


# ----------------------------------------------------------- the smoother's per-frame helpers


def test_inverse_quadratic_form3_equals_solve():
    """The innovation gate's d^T S^-1 d by the adjugate equals np.linalg.solve's to rounding,
    over covariances of 1e-10 to 1 m^2 and condition numbers up to 1e4 (a fix's position
    sigmas 0.1 to 10 mm; the adjugate loses more digits than LU as the condition grows: at 1e6
    they differ by ~1e-7 relative)."""
    rng = np.random.default_rng(4)
    for _ in range(500):
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        scale = 10.0 ** rng.uniform(-10, 0)
        S = scale * (Q * 10.0 ** rng.uniform(0, 4, 3)) @ Q.T
        S = 0.5 * (S + S.T)
        d = rng.normal(size=3) * np.sqrt(scale) * 10.0 ** rng.uniform(-1, 3)
        want = float(d @ np.linalg.solve(S, d))
        assert sm._inverse_quadratic_form3(S, d) == pytest.approx(want, rel=1e-9)


def test_load_factor_with_a_reused_noise_model_is_the_same_factor():
    """A re-keyed load sighting (factors.load_factor(noise_model=) of the first build's model)
    gives the same whitened error and Jacobians as a fresh build."""
    from fusion.estimate import factors
    from fusion.estimate.common import FusionConfig

    rng = np.random.default_rng(6)
    cfg = FusionConfig()
    p_cam, cov = rng.normal(size=3), np.diag([0.01, 0.02, 0.03]) ** 2
    key = gtsam.symbol("l", 7)
    first = factors.load_factor(3, 0, p_cam, cov, FRONT_CAM, cfg.robust_kernel, 2.0)
    fresh = factors.load_factor(3, 0, p_cam, cov, FRONT_CAM, cfg.robust_kernel, 2.0, load_key=key)
    reused = factors.load_factor(
        3, 0, p_cam, cov, FRONT_CAM, cfg.robust_kernel, 2.0, load_key=key, noise_model=first.noiseModel()
    )
    values = gtsam.Values()
    values.insert(
        gtsam.symbol("x", 3), gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    )
    values.insert(key, rng.normal(size=3) * 3)
    assert reused.error(values) == fresh.error(values) > 0
    la, lb = reused.linearize(values), fresh.linearize(values)
    np.testing.assert_array_equal(la.jacobian()[0], lb.jacobian()[0])
    np.testing.assert_array_equal(la.jacobian()[1], lb.jacobian()[1])
