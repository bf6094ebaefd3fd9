"""Shared whole-flight solves (issue 13, item 2, back end): one batch solve with the floor
camera's mount variable serves both the front camera's time-offset profile and the mount check
(fusion.pipeline.SharedWholeFlight), with the same estimates as the two separate solves."""

import math

import numpy as np
import pytest

from fusion.estimate import smoother as smoother_module
from fusion.estimate import variance
from fusion.estimate.common import FusionConfig
from fusion.estimate.extrinsics import (
    MountSource,
    check_mount,
    estimate_mount_and_trajectory,
    estimate_mount_rotation,
)
from fusion.estimate.smoother import smooth
from fusion.estimate.timeoffset import TimeOffsetConfig, fused_trajectory, resolve_time_offsets, shift_log
from fusion.geometry import so3_log
from fusion.pipeline import SharedWholeFlight
from fusion.types import Trajectory
from tests.test_estimate import FRONT_CAM, make_flight
from tests.test_extrinsics import FLOOR_CAM as MOUNT_FLOOR_CAM
from tests.test_extrinsics import _survey
from tests.test_realism import pose_chain
from tests.test_timeoffset import _flight, _log

MS = 1e-3
TRAJ_POS_TOL_M = 2e-5  # fixed-mount smoother vs the mount solve's nominal-mount trajectory
TRAJ_ROT_TOL_DEG = 1e-3  # (PnP sigmas 2 mm, 0.05 deg)
OFFSET_TOL_SIGMAS = 0.25  # an offset from the shared solve vs the separate one, in its sigma
MOUNT_TOL_SIGMAS = 0.2  # mount estimate, shared vs separate solve (midpoint-attitude IMU, floor shift)


def _pose_differences(a: Trajectory, b: Trajectory) -> tuple[float, float]:
    """Largest position (m) and attitude (deg) difference of two trajectories at the same stamps."""
    np.testing.assert_array_equal(a.timestamps_ns, b.timestamps_ns)
    dp = np.linalg.norm(a.T_world_body[:, :3, 3] - b.T_world_body[:, :3, 3], axis=1)
    dr = [np.linalg.norm(so3_log(x[:3, :3].T @ y[:3, :3])) for x, y in zip(a.T_world_body, b.T_world_body)]
    return float(dp.max()), math.degrees(float(np.max(dr)))


def test_mount_solve_returns_the_same_mount_and_a_smoother_trajectory():
    t, imu, raw = _survey(12.0, 3, (0.0, 0.0, 0.0))
    mount, traj = estimate_mount_and_trajectory(t, imu, raw, None, MOUNT_FLOOR_CAM)
    alone = estimate_mount_rotation(t, imu, raw, None, MOUNT_FLOOR_CAM)
    np.testing.assert_allclose(mount.rotvec_rad, alone.rotvec_rad, rtol=0, atol=1e-12)
    assert traj is not None and traj.covariances is None
    # without a mount error, the free-mount trajectory is the fixed-mount smoother's
    cfg = FusionConfig(compute_covariances=False, noise_scale_iterations=0, check_noise=False)
    ref = smooth(t, imu, raw, None, config=cfg, floor_camera=MOUNT_FLOOR_CAM).trajectory
    dp, dr = _pose_differences(traj, ref)
    assert dp < TRAJ_POS_TOL_M and dr < TRAJ_ROT_TOL_DEG, (dp, dr)


def test_mount_solve_trajectory_keeps_the_logged_mount_under_a_mount_error():
    """With a 2 deg mount error the shared solve still hands the front profile the fixed-mount
    smoother's trajectory (the estimate's meaning is kept), not the mount-corrected body."""
    t, imu, raw = _survey(20.0, 1, (0.0, 0.0, 2.0))
    mount, traj = estimate_mount_and_trajectory(t, imu, raw, None, MOUNT_FLOOR_CAM)
    assert mount.significant_axes == ["z"] and traj is not None
    cfg = FusionConfig(compute_covariances=False, noise_scale_iterations=0, check_noise=False)
    ref = smooth(t, imu, raw, None, config=cfg, floor_camera=MOUNT_FLOOR_CAM).trajectory
    dp, dr = _pose_differences(traj, ref)
    # second order in w = 2 deg (0.035 rad): still far below the 2 deg the mount solve removed
    assert dp < 10 * TRAJ_POS_TOL_M and dr < 0.05, (dp, dr)


@pytest.mark.parametrize("seed", [7, 8])
def test_shared_solve_gives_the_separate_solves_estimates(seed):
    """A flight longer than the floor profile's window: the front profile needs a whole-flight
    solve; shared with the mount check, the offsets and the mount match the separate solves."""
    fl = _flight(8.0, seed, -0.004, 0.011)
    cfg = TimeOffsetConfig(profile_window_s=4.0)
    log_ = _log(fl)
    separate = resolve_time_offsets(log_, fl["raw"], fl["obs"], config=cfg)
    shared = SharedWholeFlight()
    together = resolve_time_offsets(log_, fl["raw"], fl["obs"], config=cfg, whole_flight=shared)
    for cam in ("cam0", "cam1"):
        a, b = separate.cameras[cam], together.cameras[cam]
        assert a.sigma_s is not None and b.sigma_s == pytest.approx(a.sigma_s, rel=0.05)
        assert abs(a.offset_s - b.offset_s) < OFFSET_TOL_SIGMAS * a.sigma_s, (cam, a, b)
    assert abs(together.cameras["cam1"].offset_s - 0.011) < 1 * MS
    # the mount check the pipeline would otherwise make on the final stamps
    assert shared.mount is not None and shared.mount.source is MountSource.ESTIMATED
    final = shift_log(log_, together)
    raw_final = Trajectory(
        "pnp",
        fl["raw"].timestamps_ns + together.shift_ns("cam0"),
        fl["raw"].T_world_body,
        fl["raw"].covariances,
    )
    alone = check_mount(final, raw_final)
    assert alone.source is MountSource.ESTIMATED
    sig = alone.sigma_rad
    assert sig is not None and shared.mount.sigma_rad is not None
    assert np.all(np.abs(shared.mount.rotvec_rad - alone.rotvec_rad) < MOUNT_TOL_SIGMAS * sig)
    np.testing.assert_allclose(shared.mount.sigma_rad, sig, rtol=0.05)
    assert shared.mount.significant_axes == alone.significant_axes


def test_shared_solve_falls_back_without_pose_covariances():
    """PnP poses without covariances: no mount estimate, the plain whole-flight smoother."""
    fl = _flight(8.0, 7, 0.0, 0.0)
    raw = Trajectory("pnp", fl["raw"].timestamps_ns, fl["raw"].T_world_body, None)
    shared = SharedWholeFlight()
    cfg = TimeOffsetConfig()
    traj = shared(_log(fl), raw, 0, cfg, None)
    assert shared.mount is None
    ref = fused_trajectory(_log(fl), raw, 0, cfg, None)
    dp, dr = _pose_differences(traj, ref)
    assert dp == 0.0 and dr == 0.0


def test_noise_scale_iteration_computes_covariances_only_for_the_kept_solve(monkeypatch):
    """A flight whose pose covariances are 4x too small is solved twice (rescaled); only the
    second solve, the one returned, computes marginal covariances, and they equal those of a
    solve made directly at the final scales."""
    fl = make_flight(seed=5, duration_s=8.0, gaps=(), sigma_rot_rad=math.radians(0.1), sigma_pos_m=0.004)
    fl.raw.covariances = fl.raw.covariances / 4.0
    calls = []
    chain = smoother_module.chain_marginals

    def counted(*args, **kwargs):
        calls.append(1)
        return chain(*args, **kwargs)

    monkeypatch.setattr(smoother_module, "chain_marginals", counted)
    res = smooth(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM)
    rep = res.stats["noise_scales"]
    assert rep["solves"] >= 2 and len(calls) == 1
    assert res.trajectory.covariances is not None and res.stats["covariance_method"] == "chain"
    s2 = rep["groups"]["pose"]["applied_scale"]
    direct = smooth(
        fl.frame_t,
        fl.imu,
        variance.scale_trajectory(fl.raw, s2),
        fl.load_obs,
        FRONT_CAM,
        config=FusionConfig(noise_scale_iterations=0),
    )
    # the kept solve started from the previous one's solution: the same optimum within LM's
    # stopping tolerance, so the covariances' largest entries (~1e-6) agree to 1e-5 of their size
    np.testing.assert_allclose(
        res.trajectory.covariances, direct.trajectory.covariances, rtol=1e-6, atol=1e-11
    )


def test_hutchinson_probes_stop_once_the_redundancy_is_known(monkeypatch):
    """A long chain: each large group stops drawing probes before HUTCHINSON_PROBES, and its
    redundancy (rows - leverage) is within 4 standard errors (REDUNDANCY_REL_SD) of the
    dense hat matrix's."""
    graph, values, groups = pose_chain(np.random.default_rng(11), 200)
    lin = graph.linearize(values)
    A, _ = lin.jacobian()
    h = np.diag(A @ np.linalg.solve(A.T @ A, A.T))
    rows = np.repeat(groups, 6)
    exact = np.array([len(h[rows == g]) - h[rows == g].sum() for g in range(2)])
    blocks = []
    quadratic = variance._quadratic

    def counted(*args):
        blocks.append(1)
        return quadratic(*args)

    monkeypatch.setattr(variance, "_quadratic", counted)
    lev = variance.group_leverages(lin, values.dim(), groups, 2, [6] * len(groups))
    redundancy = np.bincount(rows) - lev
    assert len(blocks) < 2 * variance.HUTCHINSON_PROBES // variance.PROBE_BLOCK, len(blocks)
    assert np.all(np.abs(redundancy - exact) < 4 * variance.REDUNDANCY_REL_SD * exact), (redundancy, exact)
