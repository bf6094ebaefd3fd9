"""Tests of the fusion back end (fusion.estimate) on a small analytic flight.

The flight: smooth sinusoidal position, yaw swinging +-60 deg and a few degrees of roll/pitch,
with analytic acceleration; body rate by a central difference of the analytic rotation (error
~1e-10 rad/s); specific force f = R^T (a - g).  Raw poses = truth * Exp(n), n ~ N(0, cov) with
a stated (correlated) covariance; blackouts = intervals with no raw pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import (
    numericalDerivative11,
    numericalDerivative21,
    numericalDerivative22,
)
from scipy.spatial.transform import Rotation

from fusion.camera import CameraModel
from fusion.conventions import GRAVITY_M_S2, R_BODY_FRONTCAM
from fusion.errors import EstimationError
from fusion.estimate import (
    FusionConfig,
    run_ekf,
    smooth,
    smooth_incremental,
    write_sigmas_csv,
)
from fusion.estimate import factors
from fusion.estimate.common import RawPoseInput, TightCoupling
from fusion.geometry import inv_T, make_T, wrap_angle, yaw_of
from fusion.log.euroc import ImuData, ImuNoise, VelocityData
from fusion.types import LoadObservation, Mount, RobustKernel, Trajectory

T_BODY_FRONTCAM = make_T(R_BODY_FRONTCAM, [0.1, 0.0, 0.05])
FRONT_CAM = CameraModel(640, 480, 400.0, 400.0, 320.0, 240.0, T_body_cam=T_BODY_FRONTCAM)


def front_camera(T_body_cam: np.ndarray, mount: Mount = Mount.BODY_FIXED) -> CameraModel:
    return CameraModel(640, 480, 400.0, 400.0, 320.0, 240.0, T_body_cam=T_body_cam, mount=str(mount))


# =========================================================================== synthetic flight


def truth_state(t: np.ndarray):
    """Analytic T_world_body (N,4,4), world velocity (N,3), world acceleration (N,3)."""
    t = np.asarray(t, float)
    A = np.array([1.5, 1.0, 0.3])
    w = np.array([0.5, 0.7, 0.9])
    ph = np.array([0.0, 0.5, 1.0])
    p = A * np.sin(w * t[:, None] + ph) + np.array([2.0, 3.0, 1.5])
    v = A * w * np.cos(w * t[:, None] + ph)
    a = -A * w**2 * np.sin(w * t[:, None] + ph)
    R = rot(t)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    return T, v, a


def rot(t: np.ndarray) -> np.ndarray:
    yaw = 0.3 + 1.0 * np.sin(0.4 * t)
    pitch = 0.05 * np.sin(1.1 * t)
    roll = 0.06 * np.sin(1.3 * t + 0.2)
    return Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_matrix()


def body_rate(t: np.ndarray, h: float = 1e-5) -> np.ndarray:
    R0, R1 = rot(t - h), rot(t + h)
    return Rotation.from_matrix(np.einsum("nji,njk->nik", R0, R1)).as_rotvec() / (2 * h)


@dataclass
class Flight:
    frame_t: np.ndarray
    imu: ImuData
    velocity: VelocityData
    raw: Trajectory
    T_true: np.ndarray
    v_true: np.ndarray
    loads_true: dict
    load_obs: list
    gap_mask: np.ndarray  # frames inside a blackout


def make_flight(
    seed=0,
    duration_s=20.0,
    frame_hz=30.0,
    imu_hz=200.0,
    gaps=((8.0, 10.0),),
    sigma_rot_rad=math.radians(0.05),
    sigma_pos_m=0.002,
    imu_noise=ImuNoise(),
    bias_acc=(0.05, -0.03, 0.02),
    bias_gyr=(0.002, -0.001, 0.0015),
) -> Flight:
    rng = np.random.default_rng(seed)
    frame_t = np.round(np.arange(0.0, duration_s, 1.0 / frame_hz) * 1e9).astype(np.int64) + 10**9
    imu_t = np.round(np.arange(-0.1, duration_s + 0.1, 1.0 / imu_hz) * 1e9).astype(np.int64) + 10**9
    ts = imu_t * 1e-9 - 1.0
    T, v, a = truth_state(ts)
    R = T[:, :3, :3]
    g = np.array([0.0, 0.0, -GRAVITY_M_S2])
    f = np.einsum("nji,nj->ni", R, a - g)
    w = body_rate(ts)
    dt = 1.0 / imu_hz
    n = len(ts)
    acc = (
        f
        + np.asarray(bias_acc)
        + rng.normal(size=(n, 3)) * imu_noise.accelerometer_noise_density / math.sqrt(dt)
    )
    gyr = (
        w + np.asarray(bias_gyr) + rng.normal(size=(n, 3)) * imu_noise.gyroscope_noise_density / math.sqrt(dt)
    )
    imu = ImuData(imu_t, gyr, acc, imu_noise, np.eye(4), imu_hz)

    fs = frame_t * 1e-9 - 1.0
    T_true, v_true, _ = truth_state(fs)
    vb = np.einsum("nji,nj->ni", T_true[:, :3, :3], v_true)
    vel = VelocityData(frame_t.copy(), vb + rng.normal(size=vb.shape) * 0.05, 0.05)

    gap_mask = np.zeros(len(fs), bool)
    for g0, g1 in gaps:
        gap_mask |= (fs >= g0) & (fs < g1)
    keep = ~gap_mask
    # correlated PnP-like covariance: roll <-> y shift, pitch <-> x shift
    cov = np.diag([sigma_rot_rad**2] * 3 + [sigma_pos_m**2] * 3)
    c = 0.8 * sigma_rot_rad * sigma_pos_m
    cov[0, 4] = cov[4, 0] = -c
    cov[1, 3] = cov[3, 1] = c
    Lc = np.linalg.cholesky(cov)
    raw_T = []
    for k in np.flatnonzero(keep):
        xi = Lc @ rng.normal(size=6)
        raw_T.append(T_true[k] @ gtsam.Pose3.Expmap(xi).matrix())
    raw = Trajectory("pnp", frame_t[keep], np.array(raw_T), np.repeat(cov[None], keep.sum(), 0))

    loads_true = {
        "A1": np.array([4.0, 3.0, 1.2]),
        "B7": np.array([3.0, 5.0, 2.0]),
        "C3": np.array([0.0, 2.0, 1.0]),
    }
    cov_cam = np.diag([0.01, 0.01, 0.02]) ** 2
    Lcam = np.linalg.cholesky(cov_cam)
    obs = []
    for k in range(0, len(fs), 6):
        T_wc = T_true[k] @ T_BODY_FRONTCAM
        for lid, l in loads_true.items():
            p_cam = (inv_T(T_wc) @ np.r_[l, 1.0])[:3] + Lcam @ rng.normal(size=3)
            obs.append(LoadObservation(int(frame_t[k]), lid, np.zeros(3), None, p_cam, cov_cam))
    return Flight(frame_t, imu, vel, raw, T_true, v_true, loads_true, obs, gap_mask)


def pos_err(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    return np.linalg.norm(T_est[:, :3, 3] - T_true[:, :3, 3], axis=1)


def nees(traj: Trajectory, T_true: np.ndarray) -> np.ndarray:
    """Per-frame 6-dof NEES with xi = Log(T_est^-1 T_true) (body frame, Pose3 order)."""
    out = []
    for Te, Tt, P in zip(traj.T_world_body, T_true, traj.covariances):
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(Te).between(gtsam.Pose3(Tt)))
        out.append(xi @ np.linalg.solve(P, xi))
    return np.array(out)


@pytest.fixture(scope="module")
def flight():
    return make_flight(seed=1)


@pytest.fixture(scope="module")
def smoothed(flight):
    return smooth(flight.frame_t, flight.imu, flight.raw, flight.load_obs, FRONT_CAM)


# =========================================================================== Jacobians


def _rand_pose(rng):
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))


def test_position_yaw_jacobian_matches_numerical():
    rng = np.random.default_rng(2)
    for _ in range(5):
        pose = _rand_pose(rng)
        p_meas, yaw_meas = rng.normal(size=3), rng.uniform(-3, 3)
        _, H = factors.position_yaw_error(p_meas, yaw_meas, pose, True)
        Hn = numericalDerivative11(lambda x: factors.position_yaw_error(p_meas, yaw_meas, x, False)[0], pose)
        np.testing.assert_allclose(H, Hn, atol=1e-6)


def test_yaw_residual_wraps_around():
    pose = gtsam.Pose3(gtsam.Rot3.Yaw(math.pi - 0.01), np.zeros(3))
    e, _ = factors.position_yaw_error(np.zeros(3), -math.pi + 0.01, pose, False)
    assert abs(e[3] + 0.02) < 1e-9


def test_body_velocity_jacobians_match_numerical():
    rng = np.random.default_rng(3)
    for _ in range(5):
        pose, v, vm = _rand_pose(rng), rng.normal(size=3), rng.normal(size=3)
        _, Hx, Hv = factors.body_velocity_error(vm, pose, v, True)
        f = lambda x, vv: factors.body_velocity_error(vm, x, vv, False)[0]
        np.testing.assert_allclose(Hx, numericalDerivative21(f, pose, v), atol=1e-6)
        np.testing.assert_allclose(Hv, numericalDerivative22(f, pose, v), atol=1e-6)


def test_load_jacobians_match_numerical():
    rng = np.random.default_rng(4)
    for _ in range(5):
        pose, l, pm = _rand_pose(rng), rng.normal(size=3) * 3, rng.normal(size=3)
        cam = front_camera(_rand_pose(rng).matrix())
        _, Hx, Hl = factors.load_error(pm, cam, pose, l, True)
        f = lambda x, ll: factors.load_error(pm, cam, x, ll, False)[0]
        np.testing.assert_allclose(Hx, numericalDerivative21(f, pose, l), atol=1e-6)
        np.testing.assert_allclose(Hl, numericalDerivative22(f, pose, l), atol=1e-6)


def test_load_error_zero_at_truth():
    rng = np.random.default_rng(5)
    pose, T_bc, l = _rand_pose(rng), _rand_pose(rng).matrix(), rng.normal(size=3)
    p_cam = (inv_T(pose.matrix() @ T_bc) @ np.r_[l, 1])[:3]
    e, _, _ = factors.load_error(p_cam, front_camera(T_bc), pose, l, False)
    np.testing.assert_allclose(e, 0, atol=1e-12)


def test_constant_velocity_jacobians_match_numerical():
    rng = np.random.default_rng(6)
    p0, p1, v0, v1 = _rand_pose(rng), _rand_pose(rng), rng.normal(size=3), rng.normal(size=3)
    _, H = factors.constant_velocity_error(0.1, p0, p1, v0, v1, True)
    from gtsam.utils.numerical_derivative import (
        numericalDerivative41,
        numericalDerivative42,
        numericalDerivative43,
        numericalDerivative44,
    )

    f = lambda a, b, c, d: factors.constant_velocity_error(0.1, a, b, c, d, False)[0]
    for Hi, nd in zip(
        H, (numericalDerivative41, numericalDerivative42, numericalDerivative43, numericalDerivative44)
    ):
        np.testing.assert_allclose(Hi, nd(f, p0, p1, v0, v1), atol=1e-6)


def test_custom_factor_linearizes_with_our_jacobian():
    """The CustomFactor wrapper passes the Jacobian through (compare with the function)."""
    rng = np.random.default_rng(7)
    for _ in range(5):  # the factor (Rot3.unrotate) against body_velocity_error (numpy)
        pose, v, vm = _rand_pose(rng), rng.normal(size=3), rng.normal(size=3)
        f = factors.body_velocity_factor(0, vm, 1.0)
        vals = gtsam.Values()
        vals.insert(factors.X(0), pose)
        vals.insert(factors.V(0), v)
        A, b = f.linearize(vals).jacobian()
        e, Hx, Hv = factors.body_velocity_error(vm, pose, v, True)
        np.testing.assert_allclose(A, np.hstack([Hx, Hv]), atol=1e-12)
        np.testing.assert_allclose(b, -e, atol=1e-12)
        np.testing.assert_allclose(f.unwhitenedError(vals), e, atol=1e-12)


# =========================================================================== batch smoother


def test_smoother_beats_raw(flight, smoothed):
    k_raw = np.searchsorted(flight.frame_t, flight.raw.timestamps_ns)
    raw_rmse = np.sqrt(np.mean(pos_err(flight.raw.T_world_body, flight.T_true[k_raw]) ** 2))
    fused = pos_err(smoothed.trajectory.T_world_body, flight.T_true)
    fused_rmse = np.sqrt(np.mean(fused[k_raw] ** 2))
    assert fused_rmse < 0.6 * raw_rmse, (fused_rmse, raw_rmse)
    yaw_err = wrap_angle(smoothed.trajectory.yaw_rad - yaw_of(flight.T_true[:, :3, :3]))
    assert np.degrees(np.sqrt(np.mean(yaw_err**2))) < 0.1


def test_smoother_bridges_2s_gap(flight, smoothed):
    err = pos_err(smoothed.trajectory.T_world_body, flight.T_true)
    assert flight.gap_mask.sum() > 50
    assert err[flight.gap_mask].max() < 0.02, err[flight.gap_mask].max()


def test_smoother_nees_near_dimension(flight, smoothed):
    e = nees(smoothed.trajectory, flight.T_true)
    assert 0.5 * 6 < e.mean() < 2.0 * 6, e.mean()


def test_smoother_maps_loads(flight, smoothed):
    est = smoothed.loads.by_id()
    assert set(est) == set(flight.loads_true)
    for lid, l in flight.loads_true.items():
        d = est[lid].p_world - l
        assert np.linalg.norm(d) < 0.01
        assert est[lid].cov_world.shape == (3, 3)
        assert d @ np.linalg.solve(est[lid].cov_world, d) < 20.0  # chi2(3) 99.98 %


def test_smoother_stats(smoothed):
    s = smoothed.stats
    assert s["iterations"] >= 1 and s["final_error"] < s["initial_error"]
    assert s["rejected_pose_factors"] <= 2
    assert s["bridged_intervals"] == 0 and s["imu_segments"] == 1


def test_outliers_rejected_by_robust_kernel():
    fl = make_flight(seed=3, duration_s=12.0, gaps=())
    rng = np.random.default_rng(30)
    raw = fl.raw
    T = raw.T_world_body.copy()
    bad = rng.choice(len(T), size=len(T) // 20, replace=False)
    shift = rng.uniform(1.0, 3.0, size=(len(bad), 1)) * rng.choice([-1, 1], size=(len(bad), 2))
    T[bad, :2, 3] += shift
    bad_raw = Trajectory("pnp", raw.timestamps_ns, T, raw.covariances)
    clean = smooth(fl.frame_t, fl.imu, raw, [], FRONT_CAM)
    dirty = smooth(fl.frame_t, fl.imu, bad_raw, [], FRONT_CAM)
    rmse = lambda r: np.sqrt(np.mean(pos_err(r.trajectory.T_world_body, fl.T_true) ** 2))
    assert rmse(dirty) < 1.2 * rmse(clean), (rmse(dirty), rmse(clean))
    assert dirty.stats["rejected_pose_factors"] >= len(bad)
    assert dirty.stats["rejected_pose_factors"] <= len(bad) + 3
    assert dirty.stats["gated_pose_factors"] == len(bad)
    assert clean.stats["gated_pose_factors"] == 0
    ekf = run_ekf(fl.frame_t, fl.imu, bad_raw, [])
    assert ekf.stats["gated_updates"] >= len(bad) - 1


def test_paper_input_position_yaw_only():
    fl = make_flight(seed=4, duration_s=10.0, gaps=((4.0, 5.0),))
    T = fl.raw.T_world_body.copy()
    rng = np.random.default_rng(40)
    # the paper's output: position + yaw, roll = pitch = 0, no covariance
    for i in range(len(T)):
        yaw = yaw_of(T[i, :3, :3])
        T[i, :3, :3] = Rotation.from_euler("z", yaw).as_matrix()
        T[i, :3, 3] += rng.normal(size=3) * 0.01
    raw = Trajectory("paper", fl.raw.timestamps_ns, T, None)
    cfg = FusionConfig(paper_sigma_xyz_m=(0.01, 0.01, 0.01))
    res = smooth(fl.frame_t, fl.imu, raw, [], FRONT_CAM, config=cfg)
    assert res.stats["raw_pose_input"] is RawPoseInput.POSITION_YAW
    err = pos_err(res.trajectory.T_world_body, fl.T_true)
    assert np.sqrt(np.mean(err**2)) < 0.01
    # roll / pitch recovered from gravity although the raw poses say 0
    R_err = np.einsum("nji,njk->nik", res.trajectory.T_world_body[:, :3, :3], fl.T_true[:, :3, :3])
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(R_err).as_rotvec(), axis=1))
    assert ang.max() < 0.5, ang.max()


def test_velocity_only_mode():
    fl = make_flight(seed=5, duration_s=10.0, gaps=((4.0, 5.0),))
    res = smooth(fl.frame_t, None, fl.raw, [], FRONT_CAM, velocity=fl.velocity)
    assert res.stats["imu_intervals"] == 0
    err = pos_err(res.trajectory.T_world_body, fl.T_true)
    assert np.sqrt(np.mean(err[~fl.gap_mask] ** 2)) < 0.004
    assert err[fl.gap_mask].max() < 0.1


def test_imu_with_velocity_factors(flight):
    res = smooth(flight.frame_t, flight.imu, flight.raw, [], FRONT_CAM, velocity=flight.velocity)
    assert res.stats["velocity_factors"] == len(flight.frame_t)
    err = pos_err(res.trajectory.T_world_body, flight.T_true)
    assert err[flight.gap_mask].max() < 0.02


def test_imu_offset_body_P_sensor_is_honoured():
    """The same motion measured by an IMU rotated and offset from the body frame."""
    fl = make_flight(
        seed=6,
        duration_s=8.0,
        gaps=((3.0, 5.0),),
        imu_noise=ImuNoise(),
        bias_acc=(0, 0, 0),
        bias_gyr=(0, 0, 0),
    )
    R_bi = Rotation.from_euler("xyz", [0.1, -0.2, 1.2]).as_matrix()
    t_bi = np.array([0.05, -0.03, 0.02])
    T_bi = make_T(R_bi, t_bi)
    # IMU at offset: omega_s = R_bi^T omega_b; f_s = R_bi^T (f_b + alpha x r + w x (w x r))
    ts = fl.imu.timestamps_ns * 1e-9 - 1.0
    w_b = body_rate(ts)
    h = 1e-4
    alpha = (body_rate(ts + h) - body_rate(ts - h)) / (2 * h)
    T, v, a = truth_state(ts)
    g = np.array([0.0, 0.0, -GRAVITY_M_S2])
    f_b = np.einsum("nji,nj->ni", T[:, :3, :3], a - g)
    f_s = (f_b + np.cross(alpha, t_bi) + np.cross(w_b, np.cross(w_b, t_bi))) @ R_bi
    imu = ImuData(fl.imu.timestamps_ns, w_b @ R_bi, f_s, ImuNoise(), T_bi, 200.0)
    res = smooth(fl.frame_t, imu, fl.raw, [], FRONT_CAM)
    err = pos_err(res.trajectory.T_world_body, fl.T_true)
    assert err[fl.gap_mask].max() < 0.02, err[fl.gap_mask].max()


# =========================================================================== incremental


def test_incremental_is_causal_and_tracks(flight):
    res = smooth_incremental(flight.frame_t, flight.imu, flight.raw, flight.load_obs, FRONT_CAM)
    tr = res.trajectory
    k0 = res.stats["frames_before_first_fix"]
    np.testing.assert_array_equal(tr.timestamps_ns, flight.frame_t[k0:])
    err = pos_err(tr.T_world_body, flight.T_true[k0:])
    assert np.sqrt(np.mean(err[30:] ** 2)) < 0.005
    assert err[flight.gap_mask[k0:]].max() < 0.05
    # causal: sigma grows inside the blackout (nothing from the future)
    sig = np.sqrt(tr.covariances[:, 3, 3])
    gap_idx = np.flatnonzero(flight.gap_mask[k0:])
    assert sig[gap_idx[-1]] > 3 * sig[gap_idx[0] - 1]
    assert set(res.loads.by_id()) == set(flight.loads_true)


def test_incremental_cholesky_equals_qr(flight, monkeypatch):
    """The incremental smoother eliminates with Cholesky (faster); its poses and per-frame
    marginal covariances equal the QR engine's on a flight with a blackout and loads."""
    from fusion.estimate import smoother as sm

    fast = smooth_incremental(flight.frame_t, flight.imu, flight.raw, flight.load_obs, FRONT_CAM)
    monkeypatch.setattr(sm, "ISAM_FACTORIZATION", sm.ISAM_FALLBACK_FACTORIZATION)
    qr = smooth_incremental(flight.frame_t, flight.imu, flight.raw, flight.load_obs, FRONT_CAM)
    a, b = fast.trajectory, qr.trajectory
    np.testing.assert_array_equal(a.timestamps_ns, b.timestamps_ns)
    np.testing.assert_allclose(a.T_world_body, b.T_world_body, rtol=0, atol=1e-9)
    scale = np.abs(b.covariances).max(axis=(1, 2))[:, None, None]
    assert (np.abs(a.covariances - b.covariances) / scale).max() < 1e-6
    for la, lb in zip(fast.loads.loads, qr.loads.loads):
        np.testing.assert_allclose(la.p_world, lb.p_world, rtol=0, atol=1e-9)
    assert "cholesky_failure" not in fast.stats


def test_incremental_cholesky_failure_reruns_with_qr(flight, monkeypatch):
    """A singular system met by the Cholesky run: the whole flight is solved again with QR,
    giving exactly the QR result, and the stats say so."""
    from fusion.estimate import smoother as sm

    monkeypatch.setattr(sm, "ISAM_FACTORIZATION", sm.ISAM_FALLBACK_FACTORIZATION)
    qr = smooth_incremental(flight.frame_t, flight.imu, flight.raw, [], FRONT_CAM)
    monkeypatch.setattr(sm, "ISAM_FACTORIZATION", "CHOLESKY")
    real_engine = sm._new_engine

    class Singular:
        def __init__(self, engine):
            self.engine, self.n = engine, 0

        def __getattr__(self, name):
            return getattr(self.engine, name)

        def update(self, *args):
            self.n += 1
            if self.n == 40:
                raise RuntimeError("Indeterminant linear system detected (test)")
            return self.engine.update(*args)

    def engine(config, factorization=sm.ISAM_FALLBACK_FACTORIZATION):
        e = real_engine(config, factorization)
        return Singular(e) if factorization == "CHOLESKY" else e

    monkeypatch.setattr(sm, "_new_engine", engine)
    res = smooth_incremental(flight.frame_t, flight.imu, flight.raw, [], FRONT_CAM)
    assert "Indeterminant" in res.stats["cholesky_failure"]
    np.testing.assert_array_equal(res.trajectory.T_world_body, qr.trajectory.T_world_body)
    np.testing.assert_array_equal(res.trajectory.covariances, qr.trajectory.covariances)
    assert res.health.linear_fallbacks == 0


# =========================================================================== EKF


def test_ekf_tracks(flight):
    res = run_ekf(flight.frame_t, flight.imu, flight.raw, flight.load_obs, front_camera=FRONT_CAM)
    tr = res.trajectory
    k0 = res.stats["frames_before_first_fix"]
    err = pos_err(tr.T_world_body, flight.T_true[k0:])
    assert np.sqrt(np.mean(err[30:] ** 2)) < 0.006
    assert err[flight.gap_mask[k0:]].max() < 0.05
    e = nees(tr, flight.T_true[k0:])[30:]
    assert 0.3 * 6 < e.mean() < 3 * 6, e.mean()
    for lid, l in flight.loads_true.items():
        assert np.linalg.norm(res.loads.by_id()[lid].p_world - l) < 0.02


def test_ekf_paper_input_wraps_yaw():
    """Yaw near +-pi: the residual hook must wrap, or the filter diverges."""
    fl = make_flight(seed=8, duration_s=6.0, gaps=())
    flip = make_T(Rotation.from_euler("z", math.pi - 0.3).as_matrix(), [0, 0, 0])
    T = np.einsum("ij,njk->nik", flip, fl.raw.T_world_body)
    T_true = np.einsum("ij,njk->nik", flip, fl.T_true)
    R_flip = flip[:3, :3]
    for i in range(len(T)):
        T[i, :3, :3] = Rotation.from_euler("z", yaw_of(T[i, :3, :3])).as_matrix()
    raw = Trajectory("paper", fl.raw.timestamps_ns, T, None)
    # world rotated by the flip: gravity unchanged (rotation about z); IMU unchanged (body frame)
    res = run_ekf(fl.frame_t, fl.imu, raw, [], config=FusionConfig(paper_sigma_xyz_m=(0.003,) * 3))
    k0 = res.stats["frames_before_first_fix"]
    yaw_err = wrap_angle(res.trajectory.yaw_rad - yaw_of(T_true[k0:, :3, :3]))
    assert np.degrees(np.abs(yaw_err[30:])).max() < 1.0
    assert np.any(np.abs(yaw_of(T_true[:, :3, :3])) > math.pi - 0.05)
    del R_flip


# =========================================================================== bad input


def test_no_floor_code_raises(flight):
    with pytest.raises(EstimationError, match="no floor code was read in this flight"):
        smooth(flight.frame_t, flight.imu, Trajectory.empty("pnp"), [], FRONT_CAM)
    with pytest.raises(EstimationError, match="no floor code was read in this flight"):
        run_ekf(flight.frame_t, flight.imu, Trajectory.empty("pnp"), [])


def test_nan_in_imu_names_the_sample(flight):
    imu = flight.imu
    acc = imu.accel_m_s2.copy()
    acc[123, 1] = np.nan
    bad = ImuData(imu.timestamps_ns, imu.gyro_rad_s, acc, imu.noise)
    with pytest.raises(EstimationError, match="sample 123"):
        smooth(flight.frame_t, bad, flight.raw, [], FRONT_CAM)
    with pytest.raises(EstimationError, match="sample 123"):
        run_ekf(flight.frame_t, bad, flight.raw, [])


@pytest.mark.parametrize("kind", ["duplicated", "out of order"])
def test_bad_imu_timestamps_raise(flight, kind):
    t = flight.imu.timestamps_ns.copy()
    if kind == "duplicated":
        t[50] = t[49]
    else:
        t[50], t[51] = t[51], t[50]
    bad = ImuData(t, flight.imu.gyro_rad_s, flight.imu.accel_m_s2)
    with pytest.raises(EstimationError, match=f"sample 5[01] is {kind}"):
        smooth(flight.frame_t, bad, flight.raw, [], FRONT_CAM)


def test_imu_gap_is_bridged_and_counted():
    fl = make_flight(seed=9, duration_s=10.0, gaps=())
    imu = fl.imu
    t = imu.timestamps_ns * 1e-9 - 1.0
    keep = ~((t > 4.0) & (t < 4.5))
    gapped = ImuData(imu.timestamps_ns[keep], imu.gyro_rad_s[keep], imu.accel_m_s2[keep], imu.noise)
    res = smooth(fl.frame_t, gapped, fl.raw, [], FRONT_CAM)
    assert res.stats["imu_segments"] == 2
    assert 14 <= res.stats["bridged_intervals"] <= 17
    err = pos_err(res.trajectory.T_world_body, fl.T_true)
    assert np.sqrt(np.mean(err**2)) < 0.004


def test_imu_stops_early():
    fl = make_flight(seed=10, duration_s=10.0, gaps=())
    imu = fl.imu
    keep = imu.timestamps_ns < fl.frame_t[200]
    short = ImuData(imu.timestamps_ns[keep], imu.gyro_rad_s[keep], imu.accel_m_s2[keep], imu.noise)
    res = smooth(fl.frame_t, short, fl.raw, [], FRONT_CAM, velocity=fl.velocity)
    assert res.stats["frames_outside_imu"] >= len(fl.frame_t) - 201
    assert res.stats["imu_segments"] == 1
    err = pos_err(res.trajectory.T_world_body, fl.T_true)
    assert np.sqrt(np.mean(err**2)) < 0.005
    ekf = run_ekf(fl.frame_t, short, fl.raw, [], velocity=fl.velocity)
    assert len(ekf.trajectory) == len(fl.frame_t)
    assert ekf.stats["frames_outside_imu"] >= len(fl.frame_t) - 201


def test_raw_pose_off_frame_time_raises(flight):
    raw = flight.raw
    t = raw.timestamps_ns.copy()
    t[3] += 7_000_000
    with pytest.raises(EstimationError, match="pose 3"):
        smooth(
            flight.frame_t, flight.imu, Trajectory("pnp", t, raw.T_world_body, raw.covariances), [], FRONT_CAM
        )


def test_no_imu_no_velocity_raises(flight):
    with pytest.raises(EstimationError, match="neither IMU nor velocity"):
        smooth(flight.frame_t, None, flight.raw, [], FRONT_CAM)


def test_unknown_kernel_raises():
    with pytest.raises(EstimationError, match="unknown robust kernel"):
        FusionConfig(robust_kernel="l1")


# =========================================================================== outputs


def test_write_sigmas_csv(tmp_path, smoothed):
    path = tmp_path / "sigmas_smoother.csv"
    write_sigmas_csv(path, smoothed.trajectory)
    lines = path.read_text().splitlines()
    assert lines[0].startswith("t_ns,sigma_rx_rad")
    assert len(lines) == len(smoothed.trajectory) + 1
    vals = np.array([float(v) for v in lines[1].split(",")[1:]])
    np.testing.assert_allclose(vals, np.sqrt(np.diag(smoothed.trajectory.covariances[0])), rtol=1e-5)


# =========================================================================== speed-path equivalences


def test_load_factor_body_frame_equals_camera_frame_residual():
    """The body-frame load factor has the camera-frame residual's Mahalanobis norm and normal
    equations (it is that residual rotated by the constant R_bc)."""
    rng = np.random.default_rng(11)
    for _ in range(3):
        pose, l = _rand_pose(rng), rng.normal(size=3) * 3
        cam = front_camera(_rand_pose(rng).matrix())
        p_cam = rng.normal(size=3)
        Lc = rng.normal(size=(3, 3)) * 0.01
        cov = Lc @ Lc.T + 1e-5 * np.eye(3)
        f = factors.load_factor(0, 0, p_cam, cov, cam, RobustKernel.NONE, 1.0)
        vals = gtsam.Values()
        vals.insert(factors.X(0), pose)
        vals.insert(factors.L(0), l)
        e, Hx, Hl = factors.load_error(p_cam, cam, pose, l, True)
        info = np.linalg.inv(cov)
        np.testing.assert_allclose(f.error(vals), 0.5 * e @ info @ e, rtol=1e-9)
        A, b = f.linearize(vals).jacobian()
        J = np.hstack([Hx, Hl])
        np.testing.assert_allclose(A.T @ A, J.T @ info @ J, rtol=1e-7, atol=1e-6)
        np.testing.assert_allclose(A.T @ b, -J.T @ info @ e, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("mode", ["imu_loads", "velocity_only"])
def test_bulk_marginals_equal_gtsam(mode):
    from fusion.estimate.marginals import chain_marginals
    from fusion.estimate.smoother import build_problem, levenberg_marquardt

    fl = make_flight(seed=12, duration_s=6.0, gaps=((2.0, 3.0),))
    imu = None if mode == "velocity_only" else fl.imu
    pb = build_problem(fl.frame_t, imu, fl.raw, fl.load_obs, FRONT_CAM, fl.velocity)
    graph = pb.graph()
    values = levenberg_marquardt(graph, pb.initial).values
    lin = graph.linearize(values)
    cov, lcov = chain_marginals(
        lin, len(fl.frame_t), imu is not None, len(pb.load_ids), work_mb=0.01, group=7
    )  # load chunks; 180 frames: 26 blocks, 2 pad
    marg = gtsam.Marginals(graph, values)
    for k in range(0, len(fl.frame_t), 7):
        ref = marg.marginalCovariance(factors.X(k))
        np.testing.assert_allclose(cov[k], ref, rtol=1e-7, atol=1e-7 * np.abs(ref).max())
    for j in range(len(pb.load_ids)):
        ref = marg.marginalCovariance(factors.L(j))
        np.testing.assert_allclose(lcov[j], ref, rtol=1e-7, atol=1e-7 * np.abs(ref).max())


def test_blackout_initial_rotation_follows_gyro(flight):
    from fusion.estimate.smoother import build_problem

    pb = build_problem(flight.frame_t, flight.imu, flight.raw, [], FRONT_CAM)
    gap = np.flatnonzero(flight.gap_mask)
    R_err = np.einsum("nji,njk->nik", pb.T_init[gap, :3, :3], flight.T_true[gap, :3, :3])
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(R_err).as_rotvec(), axis=1))
    assert ang.max() < 0.2, ang.max()


def test_incremental_short_lag_recreates_loads(flight):
    """With a lag shorter than the time between sightings every load leaves the window and comes
    back as a new variable; the map, its generations combined, stays accurate."""
    res = smooth_incremental(
        flight.frame_t,
        flight.imu,
        flight.raw,
        flight.load_obs,
        FRONT_CAM,
        config=FusionConfig(incremental_lag_s=0.1),
    )
    assert res.stats["load_generations"] > 10
    est = res.loads.by_id()
    assert set(est) == set(flight.loads_true)
    for lid, l in flight.loads_true.items():
        assert np.linalg.norm(est[lid].p_world - l) < 0.02
    k0 = res.stats["frames_before_first_fix"]
    err = pos_err(res.trajectory.T_world_body, flight.T_true[k0:])
    assert np.sqrt(np.mean(err[30:] ** 2)) < 0.005


def test_incremental_reseen_loads_add_no_information_twice(flight):
    """A load seen again after leaving the window must not make the fixed-lag smoother surer
    than plain iSAM2 over the whole flight (lag None, which keeps every variable): what the
    old variable knew is in the window already.  Each generation given its predecessor's
    marginal as a prior counted it twice (here y down to 0.91 of the exact sigma; on a
    10-minute flight 6-dof NEES 11.3, 2.1 without)."""
    runs = {
        lag: smooth_incremental(
            flight.frame_t,
            flight.imu,
            flight.raw,
            flight.load_obs,
            FRONT_CAM,
            config=FusionConfig(incremental_lag_s=lag),
        )
        for lag in (0.1, None)
    }
    assert runs[0.1].stats["load_generations"] > 100
    lagged, exact = (np.sqrt(np.einsum("nii->ni", runs[lag].trajectory.covariances)) for lag in (0.1, None))
    assert (lagged / exact).min() > 0.99, (lagged / exact).min(axis=0)


# =========================================================================== tight coupling


def floor_sightings(
    fl: Flight, camera, seed: int, sigma_px: float = 0.15, spacing_m: float = 0.6, side_m: float = 0.12
) -> dict:
    """{frame timestamp_ns: [FloorSighting]}: floor codes on a grid, corners projected through
    the truth with N(0, sigma_px) pixel noise, at frames outside the blackouts."""
    from fusion.qr.codes import FloorSighting
    from fusion.types import QRDetection

    rng = np.random.default_rng(seed)
    half = side_m / 2
    offs = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]])
    out = {}
    for k in np.flatnonzero(~fl.gap_mask):
        T_cw = inv_T(fl.T_true[k] @ camera.T_body_cam)
        c = fl.T_true[k, :2, 3]
        gx = np.arange(np.floor(c[0] / spacing_m) - 3, np.floor(c[0] / spacing_m) + 4) * spacing_m
        gy = np.arange(np.floor(c[1] / spacing_m) - 3, np.floor(c[1] / spacing_m) + 4) * spacing_m
        found = []
        for x in gx:
            for y in gy:
                P = offs + [x, y, 0.0]
                pc = P @ T_cw[:3, :3].T + T_cw[:3, 3]
                if np.any(pc[:, 2] < 0.3):
                    continue
                uv = camera.project(pc)
                if np.all(np.isfinite(uv)) and np.all(
                    (uv > 5) & (uv < [camera.width - 5, camera.height - 5])
                ):
                    uv = uv + rng.normal(size=uv.shape) * sigma_px
                    det = QRDetection("cam0", int(fl.frame_t[k]), f"0/{x:g}/{y:g}", uv, uv.round(), sigma_px)
                    found.append(FloorSighting(det, None, np.array([x, y, 0.0]), P))
        if found:
            out[int(fl.frame_t[k])] = found
    return out


def test_tight_coupling_uses_corners_and_is_consistent():
    from fusion.sim.scenarios import make_cameras

    cam = make_cameras()["cam0"]
    fl = make_flight(seed=13, duration_s=6.0, gaps=((2.5, 3.5),))
    floor = floor_sightings(fl, cam, seed=14)
    loose = smooth(fl.frame_t, fl.imu, fl.raw, [], FRONT_CAM)
    tight = smooth(
        fl.frame_t,
        fl.imu,
        fl.raw,
        [],
        FRONT_CAM,
        config=FusionConfig(tight=True),
        floor_frames=floor,
        floor_camera=cam,
    )
    assert tight.stats["tight"] is TightCoupling.ON and loose.stats["tight"] is TightCoupling.OFF
    assert tight.stats["corner_factors"] == len(floor) > 100
    assert tight.stats["pose_factors"] == len(fl.raw) - len(floor)
    assert tight.stats["covariance_method"] == "chain"
    seen = ~fl.gap_mask
    rmse = lambda r: np.sqrt(np.mean(pos_err(r.trajectory.T_world_body, fl.T_true)[seen] ** 2))
    # ~4.5 codes x 4 corners at 0.15 px per frame carry more than one 2 mm raw pose
    assert rmse(tight) < 0.85 * rmse(loose), (rmse(tight), rmse(loose))
    e = nees(tight.trajectory, fl.T_true)
    assert 0.5 * 6 < e.mean() < 2.0 * 6, e.mean()
    # the causal mode takes the same factors
    inc = smooth_incremental(
        fl.frame_t,
        fl.imu,
        fl.raw,
        [],
        FRONT_CAM,
        config=FusionConfig(tight=True),
        floor_frames=floor,
        floor_camera=cam,
    )
    k0 = inc.stats["frames_before_first_fix"]
    err = pos_err(inc.trajectory.T_world_body, fl.T_true[k0:])
    assert np.sqrt(np.mean(err[30:][~fl.gap_mask[k0:][30:]] ** 2)) < 0.002


def test_tight_without_sightings_falls_back(flight):
    res = smooth(
        flight.frame_t[:90],
        flight.imu,
        Trajectory(
            "pnp", flight.raw.timestamps_ns[:90], flight.raw.T_world_body[:90], flight.raw.covariances[:90]
        ),
        [],
        FRONT_CAM,
        config=FusionConfig(tight=True),
    )
    assert res.stats["tight"] is TightCoupling.NO_SIGHTINGS
    assert res.stats["pose_factors"] == 90
