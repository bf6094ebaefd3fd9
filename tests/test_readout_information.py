"""fusion.qr.pnp.readout_information: the gyro's readout noise in one frame's PnP, predicted
covariances checked against a Monte Carlo of the random walk and the corner noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.camera import CameraModel, StampRow
from fusion.errors import EstimationError
from fusion.geometry import inv_T, so3_exp_stack
from fusion.qr.pnp.readout_information import frame_readout_information, random_walk_covariance

READOUT_S = 0.03
DENSITY = 1.7e-4  # rad/s/sqrt(Hz), the bench IMU's
# a large gyro density (x 20) so that the readout term stands out of the corner noise in the
# Monte Carlo
BIG_DENSITY = 20 * DENSITY
CORNER_SIGMA_PX = 0.015


def frame(stamp_row: StampRow = StampRow.FIRST, readout_s: float = READOUT_S):
    """A floor camera 1.5 m above two 0.2 m codes, looking down; stamp pose = row poses (the
    linearisation point need not move: the Jacobians are what is tested)."""
    cam = CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0, line_delay_s=readout_s / 480, stamp_row=stamp_row)
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # camera z down
    T[:3, 3] = [0.0, 0.0, 1.5]
    corners = np.array([[0, 0], [0.2, 0], [0.2, 0.2], [0, 0.2]], float)
    P = np.vstack([np.column_stack([corners + o, np.zeros(4)]) for o in ([-0.4, -0.35], [0.15, 0.1])])
    T_cw = inv_T(cam.T_world_cam(T))
    uv = cam.project(P @ T_cw[:3, :3].T + T_cw[:3, 3])
    assert np.ptp(uv[:, 1]) > 200  # the codes span many rows
    dt = cam.row_time_offset_s(uv[:, 1])
    rows = np.tile(T, (len(P), 1, 1))
    covs = np.tile(CORNER_SIGMA_PX**2 * np.eye(8), (2, 1, 1))
    return cam, rows, P, covs, dt, uv


def test_random_walk_covariance_same_side_only():
    K = random_walk_covariance(np.array([0.01, 0.02, -0.01, 0.0]), 2.0)
    expected = 4.0 * np.array(
        [[0.01, 0.01, 0, 0], [0.01, 0.02, 0, 0], [0, 0, 0.01, 0], [0, 0, 0, 0]], dtype=float
    )
    assert np.allclose(K, expected)


def test_global_shutter_adds_nothing():
    cam, rows, P, covs, dt, _ = frame(readout_s=0.0)
    assert np.all(dt == 0.0)
    info = frame_readout_information(cam, rows, P, covs, dt, DENSITY, 0.0, 1 / 30)
    assert info.pos_var_now == pytest.approx(info.pos_var_corners, rel=1e-9)
    assert info.pos_var_best == pytest.approx(info.pos_var_corners, rel=1e-9)
    assert np.all(info.rate_information_image < 1e-9 * info.rate_information_gyro + 1e-9)


def test_gyro_term_scales_with_the_density_squared_and_best_is_no_worse():
    cam, rows, P, covs, dt, _ = frame()
    a = frame_readout_information(cam, rows, P, covs, dt, DENSITY, READOUT_S, 1 / 30)
    b = frame_readout_information(cam, rows, P, covs, dt, 2 * DENSITY, READOUT_S, 1 / 30)
    assert a.pos_var_now > a.pos_var_corners
    excess_a, excess_b = a.pos_var_now - a.pos_var_corners, b.pos_var_now - b.pos_var_corners
    assert excess_b == pytest.approx(4 * excess_a, rel=1e-6)
    assert a.pos_var_corners <= a.pos_var_best <= a.pos_var_now
    assert a.rate_information_gyro == pytest.approx(READOUT_S / DENSITY**2)
    # without a prior the two rate informations agree; a prior on the pose can only add
    assert np.allclose(a.rate_information_image_with_prior, a.rate_information_image)
    prior = np.diag([5e-5] * 3 + [1.5e-4] * 3) ** 2
    c = frame_readout_information(cam, rows, P, covs, dt, DENSITY, READOUT_S, 1 / 30, prior)
    assert np.all(c.rate_information_image_with_prior >= a.rate_information_image - 1e-9)
    assert np.any(c.rate_information_image_with_prior > 1.5 * a.rate_information_image)


@pytest.mark.parametrize("stamp_row", [StampRow.FIRST, StampRow.MIDDLE])
def test_predicted_covariances_match_a_monte_carlo(stamp_row):
    """Corners perturbed by a random walk of the row rotations (independent increments, forward
    and backward from the stamp) and white corner noise; PnP as one Gauss-Newton step from the
    truth (its Jacobian by differences here, independently of the module), weighted by the
    corner covariance (as now) or by the sampled error covariance (the best linear estimator)."""
    cam, rows, P, covs, dt, uv = frame(stamp_row)
    info = frame_readout_information(cam, rows, P, covs, dt, BIG_DENSITY, READOUT_S, 1 / 30)
    rng = np.random.default_rng(3)
    n = 4000

    def project(T_rows):
        T_cw = inv_T(cam.T_world_cam(T_rows))
        return cam.project(np.einsum("mij,mj->mi", T_cw[:, :3, :3], P) + T_cw[:, :3, 3])

    # the random walk at the corners' times: sorted |t| on each side of the stamp
    walks = np.zeros((n, len(dt), 3))
    for side in (1.0, -1.0):
        idx = np.flatnonzero(np.sign(dt) == side)
        order = idx[np.argsort(np.abs(dt[idx]))]
        steps = np.diff(np.concatenate([[0.0], np.abs(dt[order])]))
        inc = rng.normal(0.0, 1.0, (n, len(order), 3)) * (BIG_DENSITY * np.sqrt(steps))[None, :, None]
        walks[:, order] = np.cumsum(inc, axis=1)
    errors = np.zeros((n, 2 * len(P)))
    for s in range(n):
        T = rows.copy()
        T[:, :3, :3] = rows[:, :3, :3] @ so3_exp_stack(walks[s])
        errors[s] = (project(T) - uv).ravel()
    errors += rng.normal(0.0, CORNER_SIGMA_PX, errors.shape)
    # the stamp pose's Jacobian: [rx, ry, rz] body (right), [tx, ty, tz] world
    h = 1e-6
    J = np.zeros((2 * len(P), 6))
    for j in range(6):
        for sign in (1.0, -1.0):
            T = rows.copy()
            e = np.zeros(3)
            e[j % 3] = sign * h
            if j < 3:
                T[:, :3, :3] = rows[:, :3, :3] @ so3_exp_stack(np.tile(e, (len(P), 1)))
            else:
                T[:, :3, 3] += e
            J[:, j] += sign * project(T).ravel() / (2 * h)
    W_now = np.eye(2 * len(P)) / CORNER_SIGMA_PX**2
    W_best = np.linalg.inv(np.cov(errors.T))
    for W, predicted in ((W_now, info.pos_var_now), (W_best, info.pos_var_best)):
        est = errors @ (np.linalg.solve(J.T @ W @ J, J.T @ W)).T
        assert np.trace(np.cov(est[:, 3:].T)) == pytest.approx(predicted, rel=0.1)
    assert info.pos_var_now > 1.5 * info.pos_var_corners  # the readout term is what is tested


def test_bad_shapes_are_named():
    cam, rows, P, covs, dt, _ = frame()
    with pytest.raises(EstimationError, match="need 4 per code"):
        frame_readout_information(cam, rows[:5], P[:5], covs, dt[:5], DENSITY, READOUT_S, 1 / 30)
    info = frame_readout_information(cam, rows, P, covs, dt, DENSITY, READOUT_S, 1 / 30)
    assert math.isfinite(info.pos_var_now)
