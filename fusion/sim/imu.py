"""IMU and body-velocity synthesis from a trajectory with exact derivatives.

Specific force f_S = R_world_S^T (a_world - g_world), g_world = (0, 0, -9.81); gyro = omega_S.
Noise as Kalibr / GTSAM define it (https://github.com/ethz-asl/kalibr/wiki/IMU-Noise-Model):
white noise of continuous density sigma_c gives per-sample sigma_d = sigma_c * sqrt(rate); a bias
random walk of density sigma_bc gives per-step increments of sigma_bc * sqrt(dt).
"""

from __future__ import annotations

import numpy as np

from fusion.conventions import GRAVITY_M_S2
from fusion.errors import SimulationError
from fusion.log import ImuData, ImuNoise, VelocityData

G_WORLD = np.array([0.0, 0.0, -GRAVITY_M_S2])


def sample_times_ns(duration_s: float, rate_hz: float, t0_ns: int = 0) -> np.ndarray:
    """(N,) int64 timestamps k / rate_hz for k = 0 .. floor(duration * rate), offset by t0_ns."""
    if not (rate_hz > 0 and np.isfinite(rate_hz)) or not (duration_s >= 0):
        raise SimulationError(f"bad sampling: rate {rate_hz} Hz, duration {duration_s} s")
    n = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    return t0_ns + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)


def true_imu(traj, t_s: np.ndarray, T_body_imu: np.ndarray | None = None):
    """Noise-free (gyro_S (N,3) rad/s, accel_S (N,3) m/s^2) at times t_s.

    A lever arm p_body_imu adds omega_dot x r + omega x (omega x r) to the IMU's acceleration;
    omega_dot there comes from a central difference (h = 1e-5 s)."""
    st = traj.state(t_s)
    T_body_imu = np.eye(4) if T_body_imu is None else np.asarray(T_body_imu, dtype=float)
    R_bs, r = T_body_imu[:3, :3], T_body_imu[:3, 3]
    a = st.a_world
    if np.any(r != 0.0):
        h = 1e-5
        w_dot = (traj.state(t_s + h).omega_body - traj.state(t_s - h).omega_body) / (2 * h)
        w = st.omega_body
        a_body_extra = np.cross(w_dot, r) + np.cross(w, np.cross(w, r))
        a = a + np.einsum("nij,nj->ni", st.R_world_body, a_body_extra)
    f_body = np.einsum("nji,nj->ni", st.R_world_body, a - G_WORLD)
    return st.omega_body @ R_bs, f_body @ R_bs


def synthesize_imu(
    traj,
    rate_hz: float = 200.0,
    noise: ImuNoise | None = None,
    rng: np.random.Generator | None = None,
    T_body_imu: np.ndarray | None = None,
    t0_ns: int = 0,
    noise_free: bool = False,
    initial_bias_gyro_rad_s: float = 0.002,
    initial_bias_accel_m_s2: float = 0.03,
):
    """IMU samples over [0, traj.duration_s].

    Returns (ImuData, bias_gyro (N, 3), bias_accel (N, 3)): measurement = truth + bias + white
    noise; the biases start at N(0, initial_bias_*) per axis and random-walk.  `noise_free`
    gives exact samples and zero biases (the ImuData still carries `noise` for the estimators)."""
    noise = noise or ImuNoise()
    rng = rng if rng is not None else np.random.default_rng(0)
    T_body_imu = np.eye(4) if T_body_imu is None else np.asarray(T_body_imu, dtype=float)
    ts_ns = sample_times_ns(traj.duration_s, rate_hz, t0_ns)
    t_s = (ts_ns - t0_ns) * 1e-9
    gyro, accel = true_imu(traj, t_s, T_body_imu)
    n = len(ts_ns)
    if noise_free:
        zeros = np.zeros((n, 3))
        return ImuData(ts_ns, gyro, accel, noise, T_body_imu, rate_hz), zeros, zeros.copy()
    dt = 1.0 / rate_hz

    def walk(sigma0, rw):
        steps = rng.standard_normal((n, 3)) * (rw * np.sqrt(dt))
        steps[0] = rng.standard_normal(3) * sigma0
        return np.cumsum(steps, axis=0)

    bias_gyro = walk(initial_bias_gyro_rad_s, noise.gyroscope_random_walk)
    bias_accel = walk(initial_bias_accel_m_s2, noise.accelerometer_random_walk)
    gyro = gyro + bias_gyro + rng.standard_normal((n, 3)) * (noise.gyroscope_noise_density * np.sqrt(rate_hz))
    accel = (
        accel
        + bias_accel
        + rng.standard_normal((n, 3)) * (noise.accelerometer_noise_density * np.sqrt(rate_hz))
    )
    return ImuData(ts_ns, gyro, accel, noise, T_body_imu, rate_hz), bias_gyro, bias_accel


def synthesize_velocity(
    traj,
    rate_hz: float = 30.0,
    noise_m_s: float = 0.05,
    rng: np.random.Generator | None = None,
    t0_ns: int = 0,
) -> VelocityData:
    """Body-frame velocity v_B = R_world_body^T v_world plus white noise of `noise_m_s` per axis
    (what optical flow with a range sensor provides)."""
    rng = rng if rng is not None else np.random.default_rng(0)
    ts_ns = sample_times_ns(traj.duration_s, rate_hz, t0_ns)
    st = traj.state((ts_ns - t0_ns) * 1e-9)
    v_body = np.einsum("nji,nj->ni", st.R_world_body, st.v_world)
    v_body = v_body + rng.standard_normal(v_body.shape) * noise_m_s
    return VelocityData(ts_ns, v_body, noise_m_s)
