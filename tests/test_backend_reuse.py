"""What consecutive batch solves of one flight share (issue 13, item 2, back end): the noise-scale
solves reuse the preintegrated IMU and start from the previous solution, the main smoother
starts from the shared whole-flight solve's states (smooth(warm_start=)), and the variance
components take the Gaussian factors' chi2 from the linearisation.  Each is checked against
the computation it replaces."""

import math
from dataclasses import replace

import gtsam
import numpy as np
import pytest

from fusion.estimate import correlation, variance
from fusion.estimate import smoother as smoother_module
from fusion.estimate.common import FusionConfig
from fusion.estimate.ekf import run_ekf
from fusion.estimate.extrinsics import estimate_mount_and_states, estimate_mount_and_trajectory
from fusion.estimate.factors import B, V, X
from fusion.estimate.smoother import SolveReuse, smooth, smooth_incremental, warm_values
from fusion.pipeline import SharedWholeFlight
from tests.test_estimate import FRONT_CAM, make_flight
from tests.test_extrinsics import FLOOR_CAM
from tests.test_realism import pose_chain

TIGHT_TOL = 1e-12  # lm_relative_tol: both solves run to the optimum itself
SAME_OPTIMUM_M = 1e-9  # positions, warm vs cold start, both at TIGHT_TOL
DEFAULT_TOL_M = 2e-5  # positions, warm vs cold start at the default stopping tolerance (PnP 2 mm)


@pytest.fixture(scope="module")
def flight():
    return make_flight(seed=11, duration_s=6.0, gaps=((3.0, 3.5),))


def _positions(res) -> np.ndarray:
    return res.trajectory.T_world_body[:, :3, 3]


def _cold(monkeypatch) -> None:
    """The solves as before: no reuse of the preintegration, no warm start."""
    monkeypatch.setattr(SolveReuse, "pims_for", lambda self, *a: None)
    monkeypatch.setattr(smoother_module, "warm_values", lambda initial, warm: initial)


def test_bulk_chi2_equals_factor_chi2():
    """Gaussian factors' chi2 from the linearisation's right-hand side = factor_chi2; robust ones
    (reweighted in the linearisation) keep factor_chi2."""
    rng = np.random.default_rng(4)
    graph, values, groups = pose_chain(rng, 15)
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.02)
    for k in (0, 7):  # robust priors far off: the kernel's weight is well below 1
        off = values.atPose3(k).compose(gtsam.Pose3.Expmap(rng.normal(size=6) * 0.3))
        graph.add(
            gtsam.PriorFactorPose3(
                k, off, gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), noise)
            )
        )
        groups.append(2)
    factors = [graph.at(i) for i in range(graph.size())]
    names = [variance.NoiseGroup.POSE, variance.NoiseGroup.IMU, variance.NoiseGroup.LOAD]
    comps = variance.graph_variance_components(factors, [names[g] for g in groups], values)
    for g, name in enumerate(names):
        want = sum(variance.factor_chi2(f, values) for f, gi in zip(factors, groups) if gi == g)
        assert comps[name].chi2 == pytest.approx(want, rel=1e-10), name
    assert comps[variance.NoiseGroup.LOAD].chi2 > 100  # the robust priors did count in full


def test_warm_values_takes_the_shared_keys_only():
    initial, warm = gtsam.Values(), gtsam.Values()
    for k in range(3):
        initial.insert(X(k), gtsam.Pose3())
        initial.insert(V(k), np.zeros(3))
        warm.insert(X(k), gtsam.Pose3(gtsam.Rot3(), np.array([k, 0.0, 0.0])))
    warm.insert(B(0), gtsam.imuBias.ConstantBias())  # not in `initial`: ignored
    out = warm_values(initial, warm)
    assert out.size() == initial.size() and not out.exists(B(0))
    assert out.atPose3(X(2)).translation()[0] == 2.0
    np.testing.assert_array_equal(out.atVector(V(1)), np.zeros(3))
    assert initial.atPose3(X(2)).translation()[0] == 0.0  # a copy
    assert warm_values(initial, None) is initial


@pytest.mark.parametrize("tol, limit_m", [(TIGHT_TOL, SAME_OPTIMUM_M), (None, DEFAULT_TOL_M)])
def test_noise_scale_solves_with_reuse_reach_the_same_optimum(flight, monkeypatch, tol, limit_m):
    """The second noise-scale solve starts from the first's solution with its preintegrated IMU:
    the same trajectory, scales and covariances as solving it from the PnP poses."""
    cfg = FusionConfig() if tol is None else FusionConfig(lm_relative_tol=tol)
    raw = variance.scale_trajectory(flight.raw, 3.0)  # PnP sigmas overstated: a second solve
    args = (flight.frame_t, flight.imu, raw, flight.load_obs, FRONT_CAM, flight.velocity, cfg)
    warm = smooth(*args)
    assert warm.stats["noise_scales"]["solves"] == 2
    with monkeypatch.context() as m:
        _cold(m)
        cold = smooth(*args)
    assert np.abs(_positions(warm) - _positions(cold)).max() < limit_m
    assert warm.stats["initial_error"] < 0.1 * cold.stats["initial_error"]  # it did start warm
    for g, c in cold.stats["noise_scales"]["groups"].items():
        assert warm.stats["noise_scales"]["groups"][g]["scale"] == pytest.approx(c["scale"], rel=1e-3), g
    np.testing.assert_allclose(
        warm.trajectory.covariances, cold.trajectory.covariances, rtol=1e-3, atol=1e-12
    )


def test_warm_start_from_the_shared_solve_reaches_the_same_optimum(flight):
    """The main smoother started from the mount solve's fixed-mount states: the optimum of the
    cold start, in fewer iterations."""
    mount, traj, states = estimate_mount_and_states(
        flight.frame_t, flight.imu, flight.raw, flight.velocity, FLOOR_CAM
    )
    assert states is not None and traj is not None and not states.exists(smoother_module.gtsam.symbol("e", 0))
    same_mount, same_traj = estimate_mount_and_trajectory(
        flight.frame_t, flight.imu, flight.raw, flight.velocity, FLOOR_CAM
    )
    np.testing.assert_array_equal(same_mount.rotvec_rad, mount.rotvec_rad)
    assert same_traj is not None
    np.testing.assert_array_equal(same_traj.T_world_body, traj.T_world_body)
    cfg = FusionConfig(lm_relative_tol=TIGHT_TOL)
    args = (flight.frame_t, flight.imu, flight.raw, flight.load_obs, FRONT_CAM, flight.velocity, cfg)
    cold = smooth(*args)
    warm = smooth(*args, warm_start=states)
    assert np.abs(_positions(warm) - _positions(cold)).max() < SAME_OPTIMUM_M
    assert warm.stats["initial_error"] < cold.stats["initial_error"]


def test_shared_whole_flight_warm_start_needs_the_same_frames():
    shared = SharedWholeFlight()
    t = np.arange(10, dtype=np.int64) * 33_000_000
    assert shared.warm_start(t) is None  # nothing solved
    shared.states, shared.frame_t = gtsam.Values(), t + 70_000  # a 0.07 ms floor residual
    assert shared.warm_start(t) is shared.states
    assert shared.warm_start(t[:-1]) is None  # other frames (fixes merged in)
    assert shared.warm_start(t + int(0.2e9)) is None  # beyond WARM_START_MAX_SHIFT_S
    assert math.isclose(float(np.abs(shared.frame_t - t).max()), 70_000.0)


def _flight_inflation(raw, share=0.5, rho=(0.5, 0.3)):
    """A CorrelationInflation over `raw`'s frames: one class holding `share` of each frame's
    covariance, correlated over len(rho) lags (tau = 1 + 2 sum rho)."""
    lags = len(rho)
    rho_all = np.zeros((1, correlation.MAX_LAG))
    rho_all[0, :lags] = rho
    terms = share * np.asarray(raw.covariances)[:, None]
    return correlation.CorrelationInflation(
        np.asarray(raw.timestamps_ns, np.int64),
        terms,
        rho_all,
        np.array([lags]),
        np.array([1 + 2 * sum(rho)]),
        tolerance_ns=16_000_000,
    )


TWO_SOLVE_POS_SIGMA = 0.01  # positions, two solves vs the iteration + inflated solve, in sigmas
TWO_SOLVE_COV_REL = 0.015  # the fused covariances' whitened eigenvalues (measured <= 0.71 %)
TWO_SOLVE_SCALE_REL = 0.015  # the applied camera scales (measured <= 0.69 %: s vs s * chi2/dof)


@pytest.mark.parametrize("pose_scale, load_scale, floor", [(3.0, 3.0, 0.0), (1.0, 3.0, 1.0), (0.5, 1.0, 1.0)])
def test_two_solves_agree_with_the_iteration_and_the_inflated_solve(
    flight, monkeypatch, pose_scale, load_scale, floor
):
    """correlation.InflatedSmoother (solve_inflated_twice: one solve at the nominal noise, its
    covariances at the scales it estimates, then the inflated solves warm from those scales,
    the iteration going on in them for all but the poses) against solve_inflated (the
    noise-scale iteration, two solves here, then the inflated solve): one solve fewer, the same
    trajectory within 1 % of a sigma, covariances and scales within 1.5 %.
    Stated noise off by 3x (poses and loads overstated; poses understated 2x, held at the
    floor 1 as on time-correlated flights) so that the iteration takes a second solve."""
    cfg = FusionConfig(lm_relative_tol=TIGHT_TOL, pose_scale_floor=floor)
    raw = variance.scale_trajectory(flight.raw, pose_scale)
    load_obs = variance.scale_load_observations(flight.load_obs, load_scale)
    inf = _flight_inflation(raw)
    args = (flight.frame_t, flight.imu, raw, load_obs)
    kw = dict(front_camera=FRONT_CAM, velocity=flight.velocity, config=cfg)
    initial_errors: list[float] = []
    methods: list[str] = []
    real_smooth = smoother_module.smooth

    def recording(*a, **k):
        res = real_smooth(*a, **k)
        initial_errors.append(res.stats["initial_error"])
        methods.append(res.stats["covariance_method"])
        return res

    monkeypatch.setattr(smoother_module, "smooth", recording)
    two = correlation.InflatedSmoother(inf)(*args, **kw)
    three = correlation.solve_inflated(
        real_smooth, *args, inflation=inf, two_sided=True, keep_noise_scales=True, reuse=SolveReuse(), **kw
    )
    assert three.stats["noise_scales"]["solves"] == 2  # the iteration did solve again
    ns = two.stats["noise_scales"]
    assert ns["two_solves"] and "two_solves_not_applied" not in ns
    # one solve fewer than the iteration and its inflated solve, each after the first warm
    assert (
        ns["solves"]
        == 1 + ns["inflated_solves"]
        == len(initial_errors)
        <= three.stats["noise_scales"]["solves"]
    )
    first, *later = initial_errors
    assert all(e < 1e-3 * first for e in later)
    # the first solve's covariances feed the inflation, the last one's are the result; an
    # inflated solve followed by another skips its own (nobody reads them)
    assert methods[0] != "skipped" and methods[-1] != "skipped"
    assert methods[1:-1] == ["skipped"] * (len(methods) - 2)
    sigma = np.sqrt(np.einsum("nii->ni", three.trajectory.covariances)[:, 3:])
    assert np.max(np.abs(_positions(two) - _positions(three)) / sigma) < TWO_SOLVE_POS_SIGMA
    Li = np.linalg.inv(np.linalg.cholesky(three.trajectory.covariances))
    ev = np.linalg.eigvalsh(Li @ two.trajectory.covariances @ np.swapaxes(Li, 1, 2))
    assert np.abs(ev - 1).max() < TWO_SOLVE_COV_REL
    for cam, c in three.stats["noise_scales"]["cameras"].items():
        assert ns["cameras"][cam]["scale"] == pytest.approx(c["scale"], rel=TWO_SOLVE_SCALE_REL), cam
    ratio = two.stats["correlation_inflation"]["trace_ratio_median"]
    assert ratio == pytest.approx(three.stats["correlation_inflation"]["trace_ratio_median"], rel=1e-3)
    assert ratio > 1.2  # the inflation is material


def test_an_inflated_solve_followed_by_another_skips_its_covariances(flight, monkeypatch):
    """solve_inflated_twice tells each inflated solve its own rule for solving again: one it
    will discard skips its marginal covariances (covariance_method "skipped"), the last one
    keeps them.  The noise-scale rule is made to ask for exactly one more round here (this
    flight's converges after one)."""
    cfg = FusionConfig(lm_relative_tol=TIGHT_TOL)
    inf = _flight_inflation(flight.raw)
    methods: list[str] = []
    real_smooth = smoother_module.smooth

    def recording(*a, **k):
        res = real_smooth(*a, **k)
        methods.append(res.stats["covariance_method"])
        return res

    first_round: list = []

    def once_more(scales, comps, *rest):
        if not first_round:
            first_round.append(scales)
        # a new, equal NoiseScales after the first inflated solve (one more round), then done
        return replace(scales) if scales is first_round[0] else None

    monkeypatch.setattr(smoother_module, "smooth", recording)
    monkeypatch.setattr(variance, "next_noise_scales", once_more)
    res = correlation.InflatedSmoother(inf)(
        flight.frame_t,
        flight.imu,
        flight.raw,
        flight.load_obs,
        front_camera=FRONT_CAM,
        velocity=flight.velocity,
        config=cfg,
    )
    assert res.stats["noise_scales"]["inflated_solves"] == 2
    assert len(methods) == 3 and methods[1] == "skipped"
    assert methods[0] != "skipped" and methods[2] != "skipped"
    assert res.trajectory.covariances is not None


def test_covariances_at_first_scales_are_those_of_the_rescaled_problem(flight):
    """FusionConfig.covariances_at_first_scales: the marginals of one solve's linearisation with
    each group's whitened rows over sqrt(s_g) = those of the problem solved at the scales s_g
    (the inputs rescaled; it moves the optimum a little: 1e-3 relative), and unlike the
    solve's own covariances (poses 3x, loads 3x overstated here)."""
    raw = variance.scale_trajectory(flight.raw, 3.0)
    load_obs = variance.scale_load_observations(flight.load_obs, 3.0)
    base = dict(front_camera=FRONT_CAM, velocity=flight.velocity)
    cfg = FusionConfig(lm_relative_tol=TIGHT_TOL, noise_scale_iterations=0)
    args = (flight.frame_t, flight.imu)
    at_first = smooth(*args, raw, load_obs, config=replace(cfg, covariances_at_first_scales=True), **base)
    own = smooth(*args, raw, load_obs, config=cfg, **base)
    s = at_first.stats["covariance_scales"]
    assert s["pose"] == pytest.approx(1 / 3, rel=0.2) and s["load"] == pytest.approx(1 / 3, rel=0.2)
    assert "covariance_scales" not in own.stats
    np.testing.assert_array_equal(_positions(at_first), _positions(own))  # the same solve
    rescaled = smooth(
        *args,
        variance.scale_trajectory(raw, s["pose"]),
        variance.scale_load_observations(load_obs, s["load"]),
        config=replace(cfg, check_noise=False),
        **base,
    )

    def whitened_ev(a, b):
        Li = np.linalg.inv(np.linalg.cholesky(b))
        return np.linalg.eigvalsh(Li @ a @ np.swapaxes(Li, 1, 2))

    ev = whitened_ev(at_first.trajectory.covariances, rescaled.trajectory.covariances)
    assert np.abs(ev - 1).max() < 1e-3
    assert whitened_ev(own.trajectory.covariances, rescaled.trajectory.covariances).max() > 2.0
    assert len(at_first.loads.loads) == len(rescaled.loads.loads) > 0
    for a, b in zip(at_first.loads.loads, rescaled.loads.loads):
        np.testing.assert_allclose(a.cov_world, b.cov_world, rtol=1e-3, atol=1e-3 * np.abs(b.cov_world).max())


def test_two_solves_keep_the_iteration_without_covariances_at_the_first_scales(flight, monkeypatch):
    """When the first solve's covariances cannot be had at its scales (here: the chain
    marginals unavailable, gtsam's Bayes tree instead), solve_inflated_twice keeps the
    noise-scale iteration and its inflated solve, and says why."""
    monkeypatch.setattr(smoother_module, "chain_marginals", lambda *a, **k: None)
    cfg = FusionConfig(lm_relative_tol=TIGHT_TOL)
    raw = variance.scale_trajectory(flight.raw, 3.0)
    inf = _flight_inflation(raw)
    args = (flight.frame_t, flight.imu, raw, flight.load_obs)
    kw = dict(front_camera=FRONT_CAM, velocity=flight.velocity, config=cfg)
    two = correlation.InflatedSmoother(inf)(*args, **kw)
    three = correlation.solve_inflated(
        smooth, *args, inflation=inf, two_sided=True, keep_noise_scales=True, reuse=SolveReuse(), **kw
    )
    ns = two.stats["noise_scales"]
    assert ns["two_solves_not_applied"] == "no covariances at the first solve's scales"
    assert ns["solves"] == three.stats["noise_scales"]["solves"] == 2 and "two_solves" not in ns
    assert np.abs(_positions(two) - _positions(three)).max() < SAME_OPTIMUM_M


def test_two_solves_keep_the_iteration_when_a_stated_sensor_is_outside_its_band(flight):
    """An IMU stated 10x noisier than it is: its chi2/dof at the first solve is below
    variance.IMU_WARN_BAND, and the iteration (solve_inflated) decides what to do with it, as
    for any flight whose stated sensor does not fit; solve_inflated_twice says why."""
    imu = replace(flight.imu, noise=flight.imu.noise.scaled(10.0))
    args = (flight.frame_t, imu, flight.raw, flight.load_obs)
    kw = dict(front_camera=FRONT_CAM, velocity=flight.velocity, config=FusionConfig(lm_relative_tol=TIGHT_TOL))
    two = correlation.InflatedSmoother(_flight_inflation(flight.raw))(*args, **kw)
    ns = two.stats["noise_scales"]
    assert ns["imu_chi2_per_dof"] < variance.IMU_WARN_BAND[0]
    assert ns["two_solves_not_applied"] == "the IMU's chi2/dof is outside its band"
    assert "two_solves" not in ns


def test_one_causal_pass_inflates_the_ekf_and_the_incremental_smoother_alike(flight):
    """The EKF's and the incremental smoother's outputs are both the marginal of frame k as known
    at frame k: inflated from either's pass, the poses' covariances agree (the run takes the
    EKF's for both, correlation.causal_inflated)."""
    inf = _flight_inflation(flight.raw)
    args = (flight.frame_t, flight.imu, flight.raw, flight.load_obs)
    kw = dict(front_camera=FRONT_CAM, velocity=flight.velocity, config=FusionConfig())
    by_ekf = correlation.causal_inflated(run_ekf, *args, inflation=inf, **kw)
    by_inc = correlation.causal_inflated(smooth_incremental, *args, inflation=inf, **kw)
    raw_tr = np.trace(flight.raw.covariances, axis1=1, axis2=2)
    grown_ekf = np.trace(by_ekf.covariances, axis1=1, axis2=2) / raw_tr
    grown_inc = np.trace(by_inc.covariances, axis1=1, axis2=2) / raw_tr
    assert np.median(grown_ekf) > 1.2  # the inflation is material
    assert np.median(np.abs(grown_ekf / grown_inc - 1)) < 0.02
    res = correlation.solve_on_inflated(smooth_incremental, *args[:3], by_ekf, args[3], **kw)
    assert res.stats["correlation_inflation"] == {
        "two_sided": False,
        "trace_ratio_median": pytest.approx(np.median(grown_ekf)),
    }


def test_the_ekfs_causal_pass_without_the_sightings_inflates_to_the_bit(flight):
    """The run's causal pass leaves the load sightings out (pipeline.fuse_stage): the EKF maps
    loads after filtering, from its poses, so the inflated poses are those with them, bit for
    bit, and the pass maps nothing."""
    assert flight.load_obs  # the sightings are there to leave out
    inf = _flight_inflation(flight.raw)
    kw = dict(front_camera=FRONT_CAM, velocity=flight.velocity, config=FusionConfig())
    with_loads = correlation.causal_inflated(
        run_ekf, flight.frame_t, flight.imu, flight.raw, flight.load_obs, inflation=inf, **kw
    )
    without = correlation.causal_inflated(
        run_ekf, flight.frame_t, flight.imu, flight.raw, None, inflation=inf, **kw
    )
    assert np.array_equal(without.timestamps_ns, with_loads.timestamps_ns)
    assert np.array_equal(without.T_world_body, with_loads.T_world_body)
    assert np.array_equal(without.covariances, with_loads.covariances)
    assert not np.array_equal(without.covariances, flight.raw.covariances)  # inflated
    bare = run_ekf(flight.frame_t, flight.imu, flight.raw, None, **kw)
    assert not bare.loads.loads


def test_merged_window_reports_say_whether_every_window_took_two_solves():
    from fusion.estimate.window import _merge_noise_scales

    cams = {"cam0": {"scale": 1.0, "dof": 100.0, "group": "pose"}}
    two = {"solves": 1, "cameras": cams, "inflated_solve": True, "two_solves": True}
    kept = {"solves": 2, "cameras": cams, "inflated_solve": True, "two_solves_not_applied": "why"}
    merged = _merge_noise_scales([two, kept])
    assert merged["inflated_solve"] and not merged["two_solves"] and merged["two_solves_not_applied"] == "why"
    assert _merge_noise_scales([two, two])["two_solves"]
    assert "two_solves" not in _merge_noise_scales([{"solves": 1, "cameras": cams}])
