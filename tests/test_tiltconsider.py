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


def test_the_consider_shrinks_with_the_share_the_level_conditioning_keeps():
    """sqrt(f) sigma_b / g: the full levelling limit at f = 1 (and by default), none at f = 0."""
    full = tilt_consider_sigma_rad(0.1)
    assert tilt_consider_sigma_rad(0.1, 1.0) == full
    assert tilt_consider_sigma_rad(0.1, 0.0) == 0.0
    assert np.isclose(tilt_consider_sigma_rad(0.1, 0.25), 0.5 * full)


def test_level_kept_fraction_is_continuous_from_an_exact_level_to_none():
    """0 at a level stated exact, 1 with nothing to shrink it (no covariances) or a level far
    looser than PnP's tilt, sigma^2 / (c + sigma^2) for frames of one tilt variance c, and
    monotone in sigma in between (no switch at sigma > 0)."""
    from fusion.estimate.tiltconsider import level_kept_fraction

    rng = np.random.default_rng(11)
    A = rng.standard_normal((50, 2, 2)) * 3e-4
    C = A @ np.swapaxes(A, 1, 2) + 1e-9 * np.eye(2)
    assert level_kept_fraction(C, 0.0) == 0.0
    assert level_kept_fraction(None, 0.0) == 0.0
    assert level_kept_fraction(None, 1e-3) == 1.0
    assert level_kept_fraction(np.zeros((0, 2, 2)), 1e-3) == 1.0
    assert level_kept_fraction(C, 1.0) > 0.999
    sigmas = np.radians([1e-6, 1e-4, 1e-3, 3e-3, 0.01, 0.03, 0.1, 1.0])
    f = [level_kept_fraction(C, s) for s in sigmas]
    assert f[0] < 1e-6 and np.all(np.diff(f) > 0.0), f
    c = 2e-7
    one = np.tile(np.eye(2) * c, (7, 1, 1))
    for s in (1e-5, 4e-4, 3e-3):
        assert np.isclose(level_kept_fraction(one, s), s**2 / (c + s**2), rtol=1e-12)


def test_level_kept_fraction_is_the_conditioned_share_of_the_tilt_coupled_variance():
    """One frame whose horizontal error is a lever h times its tilt error plus independent noise
    v (tx = -h ry + n, ty = h rx + n): PnP's level conditioning (floor.condition_on_level) at
    sigma leaves tx / ty the variance v + f h^2 c, f the share this module gives (f h^2 c the
    tilt error kept plus the gimbal's own level error)."""
    from fusion.estimate.tiltconsider import level_kept_fraction
    from fusion.qr.pnp.floor import condition_on_level

    c, h, v = (2e-4) ** 2, 1.3, (2e-5) ** 2
    L = np.zeros((6, 6))  # the pose error as a linear map of independent unit draws
    L[0, 0] = L[1, 1] = np.sqrt(c)
    L[2, 2] = 1e-4
    L[3, 1], L[4, 0] = -h * np.sqrt(c), h * np.sqrt(c)
    L[3, 3] = L[4, 4] = L[5, 5] = np.sqrt(v)
    C = L @ L.T
    T = np.eye(4)
    for s in np.radians([1e-4, 3e-3, 0.01, 0.1]):
        _, C_c, _ = condition_on_level(T, C, C[None], s)
        f = level_kept_fraction(C[None, :2, :2], s)
        np.testing.assert_allclose(np.diag(C_c)[3:5], v + f * h**2 * c, rtol=1e-9)


def test_a_share_above_one_is_the_full_levelling_limit():
    assert tilt_consider_sigma_rad(0.1, 5.0) == tilt_consider_sigma_rad(0.1)
    assert tilt_consider_sigma_rad(0.1, -1.0) == 0.0


def test_frames_without_a_usable_free_tilt_covariance_are_left_out():
    """A frame whose free tilt covariance is singular (det 0) or not finite says nothing of the
    tilt: the share is that of the other frames, not 1 and not an error."""
    from fusion.estimate.tiltconsider import level_kept_fraction

    rng = np.random.default_rng(5)
    A = rng.standard_normal((20, 2, 2)) * 3e-4
    C = A @ np.swapaxes(A, 1, 2) + 1e-9 * np.eye(2)
    s = np.radians(0.01)
    good = level_kept_fraction(C, s)
    assert 0.0 < good < 1.0
    singular = np.array([[[4e-8, 2e-8], [2e-8, 1e-8]]])  # det 0
    nan = np.full((1, 2, 2), np.nan)
    for bad in (singular, nan, np.concatenate([singular, nan])):
        assert level_kept_fraction(np.concatenate([C, bad]), s) == good


def test_add_tilt_consider_keeps_the_stamps():
    rng = np.random.default_rng(6)
    T = _poses(rng, 3, 0.2)
    stamps = np.array([5, 6, 9], dtype=np.int64)
    out = add_tilt_consider(Trajectory("ekf", stamps, T, np.tile(np.eye(6) * 1e-6, (3, 1, 1))), 0.01)
    np.testing.assert_array_equal(out.timestamps_ns, stamps)
    assert out.name == "ekf"
