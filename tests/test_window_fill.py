"""The windowed mount solve's frame decimation and IMU fill (fusion.estimate.window)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fusion.estimate import FusionConfig
from fusion.estimate.factors import imu_params
from fusion.estimate.smoother import LazyPims, imu_coverage
from fusion.estimate.window import decimate_frames, frame_stride, imu_fill
from fusion.log.euroc import ImuNoise
from fusion.sim.imu import synthesize_imu
from fusion.sim.trajectory import random_aisle_survey
from fusion.types import Trajectory


def _flight(seed: int, duration_s: float = 12.0):
    rng = np.random.default_rng(seed)
    traj = random_aisle_survey(duration_s, rng)
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), rng)
    t = np.round(np.arange(0.5, duration_s - 0.5, 1 / 30.0) * 1e9).astype(np.int64)
    return traj, imu, t


def test_frame_stride_and_decimation_keep_the_ends_and_their_fixes():
    t = np.round(np.arange(0, 100) * 1e9 / 30.0).astype(np.int64)
    assert frame_stride(t, 10.0) == 3 and frame_stride(t, 5.0) == 6
    assert frame_stride(t, 30.0) == 1 and frame_stride(t, 60.0) == 1 and frame_stride(t[:1], 10.0) == 1
    has_fix = np.arange(100) % 2 == 0  # fixes on every other frame
    raw = Trajectory("pnp", t[has_fix], np.tile(np.eye(4), (50, 1, 1)), np.tile(np.eye(6), (50, 1, 1)))
    kept, raw_kept = decimate_frames(t, raw, 10.0)
    assert kept[0] == 0 and kept[-1] == 99 and np.all(np.diff(kept)[:-1] == 3)
    np.testing.assert_array_equal(raw_kept.timestamps_ns, np.intersect1d(t[kept], t[has_fix]))
    assert len(raw_kept.covariances) == len(raw_kept)
    # fixes stamped up to max_sync_s off their frame are matched as the smoother matches them
    jitter = raw.timestamps_ns + np.where(np.arange(50) % 2 == 0, 1_000_000, -1_000_000)
    raw_j = Trajectory("pnp", jitter, raw.T_world_body, raw.covariances)
    _, raw_jk = decimate_frames(t, raw_j, 10.0, max_sync_s=0.002)
    np.testing.assert_array_equal(raw_jk.timestamps_ns, jitter[np.isin(raw.timestamps_ns, t[kept])])
    _, none = decimate_frames(t, raw_j, 10.0, max_sync_s=0.0005)
    assert len(none) == 0
    every, same = decimate_frames(t, raw, 0.0)
    np.testing.assert_array_equal(every, np.arange(100))
    assert same is raw


@pytest.mark.parametrize("seed,midpoint", [(0, False), (1, True)])
def test_imu_fill_is_gtsams_navstate_prediction_with_the_end_mismatch_spread(seed, midpoint):
    """imu_fill against a reference built from gtsam itself: the kept state carried frame by
    frame by PreintegratedCombinedMeasurements.predict (the smoother's LazyPims), the end
    mismatch spread linearly; kept frames exact, the others equal to 1e-7 m / 1e-8 rad."""
    traj, imu, t = _flight(seed)
    cfg = FusionConfig(imu_midpoint_attitude=midpoint)
    kept = np.r_[np.arange(0, len(t) - 1, 3), len(t) - 1]
    st = traj.state(t * 1e-9)
    rng = np.random.default_rng(seed)
    T_kept = st.T_world_body[kept].copy()
    T_kept[:, :3, 3] += 1e-3 * rng.standard_normal((len(kept), 3))  # a solve's noise
    v_kept = st.v_world[kept] + 1e-3 * rng.standard_normal((len(kept), 3))
    bias = np.tile([0.01, -0.02, 0.03, 1e-3, -2e-3, 5e-4], (len(kept), 1))
    out = imu_fill(t, kept, T_kept, v_kept, bias, imu, cfg)
    np.testing.assert_array_equal(out[kept], T_kept)
    covered = imu_coverage(t, imu, cfg.max_imu_gap_s)
    pims = LazyPims(t, imu, covered, imu_params(imu.noise, imu.T_body_imu, cfg.integration_sigma), midpoint)
    for i in range(len(kept) - 1):
        a, b = int(kept[i]), int(kept[i + 1])
        b_i = gtsam.imuBias.ConstantBias(bias[i, :3], bias[i, 3:])
        state = gtsam.NavState(gtsam.Pose3(T_kept[i]), v_kept[i])
        pred = []
        for k in range(a, b):
            state = pims[k].predict(state, b_i)
            pred.append(state.pose().matrix())
        r = gtsam.Rot3.Logmap(gtsam.Rot3(pred[-1][:3, :3].T @ T_kept[i + 1, :3, :3]))
        dp = T_kept[i + 1, :3, 3] - pred[-1][:3, 3]
        for j, k in enumerate(range(a + 1, b)):
            s = (k - a) / (b - a)
            np.testing.assert_allclose(out[k, :3, 3], pred[j][:3, 3] + s * dp, atol=1e-7)
            R = pred[j][:3, :3] @ gtsam.Rot3.Expmap(s * r).matrix()
            np.testing.assert_allclose(out[k, :3, :3], R, atol=1e-8)


def test_imu_fill_follows_the_truth_between_kept_frames():
    """With the true states at every third frame and a noise-free IMU, the filled frames are
    within 0.1 mm of the truth, where interpolating the kept poses is >= 10x off."""
    rng = np.random.default_rng(2)
    traj = random_aisle_survey(12.0, rng)
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(0.0, 0.0, 0.0, 0.0), rng)
    t = np.round(np.arange(0.5, 11.5, 1 / 30.0) * 1e9).astype(np.int64)
    st = traj.state(t * 1e-9)
    kept = np.r_[np.arange(0, len(t) - 1, 3), len(t) - 1]
    out = imu_fill(
        t, kept, st.T_world_body[kept], st.v_world[kept], np.zeros((len(kept), 6)), imu, FusionConfig()
    )
    between = np.setdiff1d(np.arange(len(t)), kept)
    err = np.linalg.norm(out[between, :3, 3] - st.T_world_body[between, :3, 3], axis=1)
    assert err.max() < 1e-4
    from fusion.geometry import PoseInterpolator

    lin = PoseInterpolator(t[kept], st.T_world_body[kept])(t[between])
    err_lin = np.linalg.norm(lin[:, :3, 3] - st.T_world_body[between, :3, 3], axis=1)
    assert err_lin.max() > 10 * err.max()
