"""The velocity sensor's samples as measurements at the frames (common.velocity_at_frames):
each sample used once, carried to its frame's time by the IMU."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.conventions import GRAVITY_M_S2
from fusion.estimate.common import FusionConfig, velocity_at_frames
from fusion.log.euroc import ImuData, VelocityData

G = np.array([0.0, 0.0, -GRAVITY_M_S2])
W_BODY = np.array([0.3, -0.2, 1.5])  # rad/s, constant in the body
R0 = Rotation.from_euler("xyz", [0.1, -0.05, 0.4])


def _motion(t):
    """Attitude (Rotation), world velocity (n, 3) and world acceleration (n, 3) at times t (s)."""
    R = R0 * Rotation.from_rotvec(np.outer(t, W_BODY))
    v = np.stack([1.2 * np.cos(2.0 * t), 0.8 + 0.9 * t, 0.3 * np.sin(3.0 * t)], axis=1)
    a = np.stack([-2.4 * np.sin(2.0 * t), 0.9 + 0 * t, 0.9 * np.cos(3.0 * t)], axis=1)
    return R, v, a


def _imu(t0=0.0, t1=2.0, rate=200.0):
    t = np.arange(t0, t1, 1.0 / rate)
    R, _, a = _motion(t)
    f = R.inv().apply(a - G)
    return ImuData((t * 1e9).round().astype(np.int64), np.tile(W_BODY, (len(t), 1)), f, rate_hz=rate)


def _velocity(t, noise=0.05, rng=None):
    R, v, _ = _motion(t)
    m = R.inv().apply(v)
    if rng is not None:
        m = m + rng.standard_normal(m.shape) * noise
    return VelocityData((t * 1e9).round().astype(np.int64), m, noise)


def _frames(t0=0.1, t1=1.9, fps=30.0):
    return (np.arange(t0, t1, 1.0 / fps) * 1e9).round().astype(np.int64)


def test_each_sample_is_used_once_at_its_nearest_frame():
    """A 10 Hz sensor and 30 fps frames: one frame in three has a measurement, with the
    sensor's sigma (interpolating to every frame used each sample three times)."""
    frames = _frames()
    vel = _velocity(np.arange(0.0, 2.0, 0.1) + 0.004)
    fv = velocity_at_frames(frames, vel, FusionConfig())
    half = int(0.5 * FusionConfig().velocity_max_gap_s * 1e9)
    near = (vel.timestamps_ns >= frames[0] - half) & (vel.timestamps_ns <= frames[-1] + half)
    assert fv.mask.sum() == near.sum()
    assert np.all(fv.sigma_m_s[fv.mask] == pytest.approx(0.05))
    inner = fv.mask.copy()
    inner[[0, -1]] = False
    assert np.all(np.abs(fv.dt_s[inner]) <= 0.5 / 30.0 + 1e-9)


def test_faster_samples_are_averaged_per_frame():
    frames = _frames()
    vel = _velocity(np.arange(0.0, 2.0, 1.0 / 90.0))
    fv = velocity_at_frames(frames, vel, FusionConfig())
    inner = fv.mask.copy()
    inner[[0, -1]] = False
    assert np.all(fv.sigma_m_s[inner] == pytest.approx(0.05 / np.sqrt(3.0)))


def test_the_imu_carries_a_sample_to_its_frames_time():
    """Noise-free samples up to half a frame from their frame, on a turning, accelerating
    drone: the carried measurement (with the gravity term at the true attitude) is the body
    velocity at the frame to < 1 mm/s; the sample as it is, tens of mm/s off."""
    frames = _frames()
    t_s = frames * 1e-9 + np.random.default_rng(3).uniform(-0.016, 0.016, len(frames))
    vel = _velocity(t_s)
    fv = velocity_at_frames(frames, vel, FusionConfig(), _imu())
    R, v, _ = _motion(frames * 1e-9)
    truth = R.inv().apply(v)
    R_m = R.as_matrix()
    carried = np.array([fv.measured(k, R_m[k]) for k in range(len(frames))])
    assert fv.mask.all()
    assert np.abs(carried - truth).max() < 1e-3
    assert np.abs(vel.v_body_m_s - truth).max() > 0.02


def test_frames_moved_a_little_keep_the_same_samples():
    """The time-offset profile moves the frames by ms: each frame keeps its sample (no cusp of
    the cost at the stamps the frames and samples share, which interpolation had)."""
    frames = _frames()
    vel = _velocity(frames * 1e-9, rng=np.random.default_rng(0))
    imu = _imu()
    a = velocity_at_frames(frames, vel, FusionConfig(), imu)
    for d_ms in (-3.0, -0.5, 0.5, 3.0):
        b = velocity_at_frames(frames + int(d_ms * 1e6), vel, FusionConfig(), imu)
        assert np.array_equal(a.mask, b.mask)
        assert np.all(b.sigma_m_s == a.sigma_m_s)
        assert np.allclose(b.dt_s[b.mask], -d_ms * 1e-3)
        # the noise of each frame's measurement is its one sample's, not an average's
        assert np.abs(_noise(b, frames + int(d_ms * 1e6)) - _noise(a, frames)).max() < 1e-3


def _noise(fv, frames):
    """Each frame's carried measurement less the true body velocity there."""
    R, v, _ = _motion(frames * 1e-9)
    R_m = R.as_matrix()
    return np.array([fv.measured(k, R_m[k]) for k in range(len(frames))]) - R.inv().apply(v)


def test_samples_far_from_any_frame_or_without_velocity_are_not_used():
    frames = _frames(0.1, 0.5)
    vel = _velocity(np.array([0.2, 1.5]))
    fv = velocity_at_frames(frames, vel, FusionConfig())
    assert fv.mask.sum() == 1
    assert not velocity_at_frames(frames, None, FusionConfig()).mask.any()


def test_without_an_imu_a_sample_is_taken_at_its_frame_as_it_is():
    """No IMU to carry it: the sample itself, with no gravity term (dt_s 0)."""
    frames = _frames()
    vel = _velocity(frames * 1e-9 + 0.01)
    fv = velocity_at_frames(frames, vel, FusionConfig())
    assert np.all(fv.dt_s == 0.0)
    R = Rotation.from_euler("xyz", [0.3, 0.2, 1.0]).as_matrix()
    np.testing.assert_array_equal(fv.measured(5, R), vel.v_body_m_s[5])
