"""Decisions of the back ends pinned against closed forms, numerical derivatives or truth
(issue #9 item 6: the mutants scripts/mutation.py found surviving).

Each test names the decision it pins; each was checked by applying the surviving mutation by
hand and seeing the test fail.  Small and fast on purpose: mutmut runs them once per mutant.
"""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest

from fusion.estimate import FusionConfig, factors, run_ekf, smoother
from fusion.estimate.common import FusionResult
from fusion.estimate.ekf import EkfRecovery, _Ekf, load_point_world
from fusion.estimate.health import Health, assess_result
from fusion.geometry import make_T, skew, so3_exp
from fusion.log.euroc import ImuNoise, VelocityData
from fusion.qr.pnp.flight import pose_at
from fusion.qr.pnp.lm import same_pose
from fusion.sim.scenarios import make_cameras
from fusion.types import CameraRole, LoadMap, LoadObservation, RobustKernel, Trajectory

# --------------------------------------------------------------------------- factors.robust


@pytest.mark.parametrize(
    "kernel, weight",
    [
        # IRLS weights w(x) of the M-estimators on the whitened residual norm x, threshold k
        # (Zhang, "Parameter estimation techniques", IVC 15(1), 1997, table 1; gtsam mEstimator).
        (RobustKernel.HUBER, lambda x, k: 1.0 if x <= k else k / x),
        (RobustKernel.CAUCHY, lambda x, k: 1.0 / (1.0 + (x / k) ** 2)),
        (RobustKernel.TUKEY, lambda x, k: (1.0 - (x / k) ** 2) ** 2 if x <= k else 0.0),
    ],
)
def test_robust_wraps_the_named_kernel_with_its_threshold(kernel, weight):
    k = 2.0
    base = gtsam.noiseModel.Isotropic.Sigma(3, 0.5)
    model = factors.robust(base, kernel, k)
    for x in (0.5, 1.5, 3.0, 7.0):
        assert model.robust().weight(x) == pytest.approx(weight(x, k), rel=1e-12, abs=1e-15)
    np.testing.assert_allclose(model.noise().sigmas(), base.sigmas())


def test_robust_none_is_the_plain_model():
    base = gtsam.noiseModel.Isotropic.Sigma(2, 0.3)
    assert factors.robust(base, RobustKernel.NONE, 2.0) is base


# --------------------------------------------------------------------------- factors.bridge_factors


def test_bridge_sigmas_grow_with_sqrt_dt():
    """Random walks over dt: sigma = rate * sqrt(dt) (white noise integrated over dt)."""
    noise = ImuNoise()
    dt, accel, rate, free, min_sigma = 4.0, 0.5, 0.2, 100.0, 1e-6
    out = factors.bridge_factors(3, 4, dt, accel, rate, True, noise, free, 1e-3, min_sigma)
    rot_pose, vel, cv, bias = out
    np.testing.assert_allclose(rot_pose.noiseModel().sigmas(), np.r_[[rate * 2.0] * 3, [free] * 3])
    np.testing.assert_allclose(vel.noiseModel().sigmas(), [accel * 2.0] * 3)
    np.testing.assert_allclose(cv.noiseModel().sigmas(), [0.5 * accel * 8.0 + min_sigma] * 3)
    np.testing.assert_allclose(
        bias.noiseModel().sigmas(),
        np.r_[[noise.accelerometer_random_walk * 2.0] * 3, [noise.gyroscope_random_walk * 2.0] * 3],
    )
    assert len(factors.bridge_factors(3, 4, dt, accel, rate, False, None, free, 1e-3, min_sigma)) == 3


def test_bridge_dt_and_sigmas_are_floored():
    noise = ImuNoise()
    out = factors.bridge_factors(0, 1, 0.0, 0.5, 0.2, True, noise, 100.0, 0.01, 1.0)
    np.testing.assert_allclose(out[0].noiseModel().sigmas()[:3], 0.2 * math.sqrt(0.01))
    np.testing.assert_allclose(out[3].noiseModel().sigmas(), 1.0)  # bias random walk below the floor


# --------------------------------------------------------------------------- EKF robust weights


def _ekf(**cfg) -> _Ekf:
    return _Ekf(np.eye(4), FusionConfig(**cfg), EkfRecovery())


@pytest.mark.parametrize(
    "kernel, scale",
    [
        (RobustKernel.HUBER, lambda d, k: d / k),  # IRLS weight k/d
        (RobustKernel.CAUCHY, lambda d, k: 1.0 + (d / k) ** 2),
        (RobustKernel.TUKEY, lambda d, k: None),  # weight 0 beyond k: skipped
    ],
)
def test_ekf_robust_R_inflates_by_the_inverse_weight(kernel, scale):
    f = _ekf(robust_kernel=kernel, robust_threshold=2.0, outlier_gate=10.0)
    Rm = np.diag([1.0, 2.0, 3.0])
    # at or inside the threshold: unchanged, not counted
    assert f._robust_R(2.0, Rm, 3) is Rm and f._robust_R(0.5, Rm, 3) is Rm
    assert f.rejected == 0
    out = f._robust_R(5.0, Rm, 3)
    want = scale(5.0, 2.0)
    if want is None:
        assert out is None
    else:
        np.testing.assert_allclose(out, Rm * want)
    assert f.rejected == 1 and f.gated == 0
    # beyond the gate: skipped and counted for every kernel
    assert f._robust_R(10.5, Rm, 3) is None
    assert f.rejected == 2 and f.gated == 1
    assert f._robust_R(30.0, Rm, 3) is None
    assert f.rejected == 3 and f.gated == 2  # counts, not flags
    assert f._robust_R(10.0, Rm, 3) is not None or kernel is RobustKernel.TUKEY  # the gate is d > gate


def test_ekf_robust_R_none_kernel_never_inflates():
    f = _ekf(robust_kernel=RobustKernel.NONE, robust_threshold=2.0, outlier_gate=10.0)
    Rm = np.eye(2)
    assert f._robust_R(50.0, Rm, 2) is Rm
    assert f.rejected == 0 and f.gated == 0
    g = _ekf(robust_kernel=RobustKernel.HUBER, robust_threshold=2.0, outlier_gate=None)
    np.testing.assert_allclose(g._robust_R(50.0, Rm, 2), Rm * 25.0)  # no gate: inflated, not skipped
    assert g.gated == 0


# --------------------------------------------------------------------------- EKF covariance matching


def _spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def test_inflate_to_brings_the_innovation_to_the_target_distance():
    """Mehra's covariance matching: after scaling P by lam, y^T (H P H^T + R)^-1 y = d_target^2."""
    rng = np.random.default_rng(0)
    f = _ekf()
    f.kf.P = _spd(rng, 15, 1e-4)
    H = rng.normal(size=(4, 15))
    Rm = _spd(rng, 4, 1e-4)
    y = rng.normal(size=4)
    P0 = f.kf.P.copy()
    d0 = f._mahalanobis(y, H, Rm)
    target = 2.0
    assert d0 > 10 * target
    lam = f._inflate_to(y, H, Rm, target)
    assert lam > 1.0
    np.testing.assert_allclose(f.kf.P, lam * P0)
    assert f._mahalanobis(y, H, Rm) == pytest.approx(target, rel=1e-6)


def test_inflate_to_is_capped_at_max_inflation():
    rng = np.random.default_rng(1)
    f = _Ekf(np.eye(4), FusionConfig(), EkfRecovery(max_inflation=10.0))
    f.kf.P = _spd(rng, 15, 1e-8)
    H = rng.normal(size=(3, 15))
    Rm = 1e-6 * np.eye(3)
    y = np.ones(3)  # far beyond what a factor 10 can explain
    P0 = f.kf.P.copy()
    lam = f._inflate_to(y, H, Rm, 1.0)
    assert lam == pytest.approx(10.0)
    np.testing.assert_allclose(f.kf.P, 10.0 * P0)


# --------------------------------------------------------------------------- EKF load mapping


def test_load_point_jacobian_matches_the_closed_form():
    """p = R_wb q + t_wb with q = T_body_cam p_cam (body-fixed camera); right perturbation:
    dp/dtheta = -R_wb [q]x, dp/dt = R_wb."""
    cam = make_cameras(mount="body_fixed")[CameraRole.FRONT]
    rng = np.random.default_rng(3)
    T_wb = make_T(so3_exp(rng.normal(size=3)), rng.normal(size=3))
    p_cam = np.array([0.3, -0.2, 2.5])
    p, J = load_point_world(cam, T_wb, p_cam)
    T_bc = np.linalg.inv(T_wb) @ cam.T_world_cam(T_wb)
    q = T_bc[:3, :3] @ p_cam + T_bc[:3, 3]
    R = T_wb[:3, :3]
    np.testing.assert_allclose(p, R @ q + T_wb[:3, 3], atol=1e-12)
    np.testing.assert_allclose(J[:, :3], -R @ skew(q), atol=1e-7)
    np.testing.assert_allclose(J[:, 3:], R, atol=1e-7)


# --------------------------------------------------------------------------- run_ekf start


def _static_flight(n=20, first_fix=5, fps=10.0, full_pose=True):
    frame_t = np.round(np.arange(n) / fps * 1e9).astype(np.int64)
    T = make_T(so3_exp(np.array([0.02, -0.01, 0.7])), np.array([1.0, 2.0, 1.5]))
    m = n - first_fix
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-4, 4e-4, 9e-4])
    raw = Trajectory(
        "pnp",
        frame_t[first_fix:],
        np.repeat(T[None], m, 0),
        np.repeat(cov[None], m, 0) if full_pose else None,
    )
    return frame_t, raw, T, cov


def _still(frame_t, v=None):
    """Body velocity measurements (zero: the flight is static), one per frame."""
    return VelocityData(frame_t.copy(), np.zeros((len(frame_t), 3)) if v is None else v, 0.01)


def test_ekf_starts_with_the_first_fix_covariance():
    frame_t, raw, T, cov = _static_flight()
    res = run_ekf(frame_t, None, raw, velocity=_still(frame_t))
    assert res.stats["frames_before_first_fix"] == 5
    np.testing.assert_array_equal(res.trajectory.timestamps_ns, frame_t[5:])
    np.testing.assert_allclose(res.trajectory.T_world_body[0], T, atol=1e-12)
    np.testing.assert_allclose(res.trajectory.covariances[0], cov, rtol=1e-9, atol=1e-15)


def test_ekf_paper_input_starts_with_the_configured_sigmas():
    """Position + yaw input: start covariance diag(tilt^2, tilt^2, yaw^2, xyz^2) (variances)."""
    frame_t, raw, T, _ = _static_flight(full_pose=False)
    cfg = FusionConfig()
    res = run_ekf(frame_t, None, raw, velocity=_still(frame_t), config=cfg)
    tilt = 0.05  # ekf._TILT_SIGMA_RAD
    want = np.diag(
        np.r_[tilt**2, tilt**2, cfg.paper_sigma_yaw_rad**2, np.asarray(cfg.paper_sigma_xyz_m, float) ** 2]
    )
    np.testing.assert_allclose(res.trajectory.covariances[0], want, rtol=1e-9, atol=1e-15)


def test_ekf_ignores_velocity_before_the_first_fix():
    """The filter starts at the first fix: frames before it (and their velocity measurements)
    are not run, so wrong velocities there change nothing."""
    frame_t, raw, T, _ = _static_flight()
    v = np.zeros((len(frame_t), 3))
    good = _still(frame_t, v.copy())
    v[:5] = [3.0, -2.0, 1.0]  # before the first fix (frame 5)
    bad = _still(frame_t, v)
    a = run_ekf(frame_t, None, raw, velocity=good)
    b = run_ekf(frame_t, None, raw, velocity=bad)
    np.testing.assert_allclose(b.trajectory.T_world_body, a.trajectory.T_world_body, atol=1e-12)
    np.testing.assert_allclose(b.trajectory.covariances, a.trajectory.covariances, atol=1e-15)


# --------------------------------------------------------------------------- smoother covariances


def test_smoother_bayes_tree_fallback_agrees_with_the_chain(monkeypatch):
    """Where chain_marginals cannot run (LinAlgError), the smoother takes the marginals from
    gtsam's Bayes tree: same covariances as the chain, poses and loads alike."""
    frame_t, raw, _, _ = _static_flight(n=12, first_fix=0)
    cam = make_cameras(mount="body_fixed")[CameraRole.FRONT]
    obs = [
        LoadObservation(
            int(t), "L1", np.zeros(3), p_cam=np.array([0.2, -0.1, 2.0]), cov_cam=np.diag([1e-4, 2e-4, 4e-4])
        )
        for t in frame_t[::3]
    ]
    chain = smoother.smooth(frame_t, None, raw, obs, cam, velocity=_still(frame_t))
    assert chain.stats["covariance_method"] == "chain"

    def no_chain(*args, **kwargs):
        raise np.linalg.LinAlgError("not a chain")

    monkeypatch.setattr(smoother, "chain_marginals", no_chain)
    tree = smoother.smooth(frame_t, None, raw, obs, cam, velocity=_still(frame_t))
    assert tree.stats["covariance_method"] == "bayes_tree"
    np.testing.assert_allclose(tree.trajectory.T_world_body, chain.trajectory.T_world_body, atol=1e-9)
    c0, c1 = chain.trajectory.covariances, tree.trajectory.covariances
    np.testing.assert_allclose(c1, c0, rtol=1e-6, atol=1e-6 * np.abs(c0).max())
    (l0,), (l1,) = chain.loads.loads, tree.loads.loads
    np.testing.assert_allclose(l1.cov_world, l0.cov_world, rtol=1e-6, atol=1e-6 * np.abs(l0.cov_world).max())


# --------------------------------------------------------------------------- PnP helpers


def test_same_pose_needs_both_rotation_and_position_within_tolerance():
    """cos(angle) = (trace(R_a^T R_b) - 1) / 2; both tolerances must hold."""
    R = so3_exp(np.array([0.3, -0.2, 1.0]))
    t = np.array([1.0, 2.0, 3.0])
    tol = math.radians(2.0)
    axis = np.array([0.0, 0.6, 0.8])
    assert same_pose(R, t, R @ so3_exp(0.9 * tol * axis), t, tol, 0.01)
    assert not same_pose(R, t, R @ so3_exp(1.1 * tol * axis), t, tol, 0.01)
    assert not same_pose(R, t, R, t + [0.0, 0.011, 0.0], tol, 0.01)  # same rotation, too far
    assert not same_pose(R, t, R @ so3_exp(1.1 * tol * axis), t + 0.001, tol, 0.01)


def test_pose_at_interpolates_linearly_in_time():
    """Between two poses 0.1 s apart (stamped ~1.7e18 ns, as a real log): position at a of the way."""
    t0 = 1_700_000_000_000_000_000
    ts = np.array([t0, t0 + 100_000_000], np.int64)
    T = np.stack([make_T(np.eye(3), [0.0, 0.0, 1.0]), make_T(np.eye(3), [1.0, 2.0, 1.0])])
    traj = Trajectory("pnp", ts, T, None)
    got, cov = pose_at(traj, t0 + 25_000_000)
    assert cov is None
    np.testing.assert_allclose(got[:3, 3], [0.25, 0.5, 1.0], atol=1e-9)


# --------------------------------------------------------------------------- health summary


def test_health_summary_keys_are_the_field_names_and_fractions_are_per_fix():
    """metrics.json readers key on the Health field names; inflated / gated fractions are per
    raw fix (assess_result)."""
    frame_t, raw, _, _ = _static_flight(n=20, first_fix=0)
    res = FusionResult(raw, LoadMap("ekf"), {"inflated_updates": 5, "gated_updates": 2})
    h = assess_result(res, raw)
    assert h.inflated_fraction == pytest.approx(5 / 20)
    assert h.gated_fraction == pytest.approx(2 / 20)
    d = h.to_dict()
    fields = {f.name for f in dataclasses.fields(Health)} - {"reasons", "window_nis"}
    assert set(d) == fields | {"reason"}
    for k in fields - {"status"}:
        assert d[k] == getattr(h, k) or (d[k] != d[k] and getattr(h, k) != getattr(h, k))  # nan


def test_pnp_counts_every_frame_without_a_floor_code_and_merges_stats_by_sum():
    """Survivors of the mutation sample: the counter of frames without a floor code (`+= 1`
    -> `= 1`) and PnPStats.merged (never called by the subset)."""
    from fusion.qr.pnp.flight import PnPStats, pnp_trajectory
    from tests.test_pnp import FLOOR_CAM, WORLD

    traj, stats = pnp_trajectory({t: [] for t in (10, 20, 30)}, FLOOR_CAM, WORLD)
    assert len(traj) == 0 and stats.n_frames == 3 and stats.n_without_floor_code == 3
    a = PnPStats(n_frames=4, n_posed=2, mean_reprojection_rms_px=0.1, codes_per_pose={1: 2})
    b = PnPStats(n_frames=6, n_posed=6, mean_reprojection_rms_px=0.3, codes_per_pose={1: 1, 2: 5})
    m = PnPStats.merged([a, b, PnPStats()])
    assert (m.n_frames, m.n_posed) == (10, 8)
    assert m.codes_per_pose == {1: 3, 2: 5}
    assert m.mean_reprojection_rms_px == pytest.approx((2 * 0.1 + 6 * 0.3) / 8)
