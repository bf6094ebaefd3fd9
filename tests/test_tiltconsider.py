"""The gimbaled floor camera's tilt consider term (fusion.estimate.tiltconsider)."""

import numpy as np

from fusion.conventions import GRAVITY_M_S2
from fusion.estimate.tiltconsider import add_tilt_consider, tilt_consider_covariance, tilt_consider_sigma_rad
from fusion.geometry import R_from_euler, level_frame, so3_exp, so3_log
from fusion.types import Trajectory


def _poses(rng, n, max_tilt_rad):
    """(n, 4, 4) poses with random yaw, roll / pitch up to max_tilt_rad, positions in a box."""
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        roll, pitch = rng.uniform(-max_tilt_rad, max_tilt_rad, 2)
        T[k, :3, :3] = R_from_euler("ZYX", [rng.uniform(-np.pi, np.pi), pitch, roll])
        T[k, :3, 3] = rng.uniform(-5.0, 5.0, 3)
    return T


def test_the_levelling_limit_is_the_accelerometer_bias_over_g():
    assert tilt_consider_sigma_rad(0.1) == 0.1 / GRAVITY_M_S2


def test_the_consider_is_a_level_frame_tilt_error_in_body_coordinates():
    """Monte Carlo: a level-frame roll / pitch error of sigma s per axis, R' = Exp(R_L d) R,
    seen as the body-frame right perturbation Log(R^T R') has the covariance the module gives,
    on tilted poses (where it reaches the body yaw too)."""
    rng = np.random.default_rng(3)
    s = 0.01
    T = _poses(rng, 4, np.radians(20.0))
    Q = tilt_consider_covariance(T, s)
    for k in range(len(T)):
        R, R_L = T[k, :3, :3], level_frame(T[k])[:3, :3]
        d = np.zeros((20000, 3))
        d[:, :2] = rng.standard_normal((20000, 2)) * s
        xi = np.array([so3_log(R.T @ so3_exp(R_L @ di) @ R) for di in d])
        emp = np.cov(xi.T)
        np.testing.assert_allclose(emp, Q[k], atol=0.04 * s**2)
        assert np.linalg.matrix_rank(Q[k], tol=1e-12) == 2  # no error about the world vertical


def test_level_poses_get_the_roll_pitch_block_only():
    T = np.tile(np.eye(4), (3, 1, 1))
    for k, yaw in enumerate((0.0, 1.0, -2.5)):
        T[k, :3, :3] = R_from_euler("ZYX", [yaw, 0.0, 0.0])
    np.testing.assert_allclose(
        tilt_consider_covariance(T, 0.02), np.tile(np.diag([4e-4, 4e-4, 0.0]), (3, 1, 1)), atol=1e-15
    )


def test_add_tilt_consider_changes_the_rotation_block_only():
    rng = np.random.default_rng(5)
    T = _poses(rng, 6, np.radians(15.0))
    A = rng.standard_normal((6, 6, 6))
    C = A @ np.swapaxes(A, 1, 2) * 1e-6
    traj = Trajectory("smoother", np.arange(6, dtype=np.int64) * 33_333_333, T, C)
    out = add_tilt_consider(traj, 0.01)
    np.testing.assert_array_equal(out.covariances[:, 3:, :], C[:, 3:, :])
    np.testing.assert_array_equal(out.covariances[:, :, 3:], C[:, :, 3:])
    np.testing.assert_allclose(out.covariances[:, :3, :3] - C[:, :3, :3], tilt_consider_covariance(T, 0.01))
    np.testing.assert_array_equal(out.T_world_body, T)
    assert add_tilt_consider(traj, 0.0) is traj
    bare = Trajectory("smoother", traj.timestamps_ns, T, None)
    assert add_tilt_consider(bare, 0.01) is bare
