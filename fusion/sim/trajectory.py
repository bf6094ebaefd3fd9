"""Smooth multirotor trajectories with exact derivatives.

Position and yaw move between keyframes along the degree-7 "smootherstep"
s(tau) = 35 tau^4 - 84 tau^5 + 70 tau^6 - 20 tau^7, whose first three derivatives vanish at both
ends: velocity, acceleration and jerk are continuous everywhere (snap jumps at keyframes), so the
attitude and the angular rate, which depend on acceleration and jerk, are continuous too.

Attitude by differential flatness (Mellinger & Kumar, ICRA 2011, eq. 6-8): thrust axis
z_B = (a + g z_W) / |a + g z_W|, heading x_C = (cos yaw, sin yaw, 0), y_B = z_B x x_C normalised,
x_B = y_B x z_B.  The angular rate is the exact derivative of that construction (chain rule with
the jerk and the yaw rate), omega_body = vee(R^T dR/dt).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.conventions import GRAVITY_M_S2
from fusion.errors import SimulationError

# smootherstep and its derivatives as polynomials in tau (highest power first)
_S = [np.poly1d([-20.0, 70.0, -84.0, 35.0, 0.0, 0.0, 0.0, 0.0])]
for _ in range(3):
    _S.append(_S[-1].deriv())


@dataclass
class Keyframe:
    """The drone at rest at time t_s: position p_world (m) and yaw (rad, unwrapped)."""

    t_s: float
    p_world: tuple[float, float, float]
    yaw_rad: float


@dataclass
class TrueState:
    """Ground truth at N times.  Frames: W (z up), B (FLU body = IMU)."""

    t_s: np.ndarray  # (N,)
    p_world: np.ndarray  # (N, 3) m
    v_world: np.ndarray  # (N, 3) m/s
    a_world: np.ndarray  # (N, 3) m/s^2 (kinematic acceleration, no gravity)
    R_world_body: np.ndarray  # (N, 3, 3)
    omega_body: np.ndarray  # (N, 3) rad/s, angular rate in B

    @property
    def T_world_body(self) -> np.ndarray:
        """(N, 4, 4)."""
        T = np.tile(np.eye(4), (len(self.t_s), 1, 1))
        T[:, :3, :3] = self.R_world_body
        T[:, :3, 3] = self.p_world
        return T


class KeyframeTrajectory:
    """Rest-to-rest smootherstep motion through keyframes (hover = two keyframes, same pose).

    `state(t)` is vectorised; times outside [0, duration_s] are clamped to the end keyframes."""

    def __init__(self, keyframes: list[Keyframe]):
        if len(keyframes) < 2:
            raise SimulationError("a trajectory needs at least two keyframes")
        t = np.array([k.t_s for k in keyframes], dtype=float)
        if t[0] != 0.0 or np.any(np.diff(t) <= 0):
            raise SimulationError("keyframe times must start at 0 and increase strictly")
        self.keyframes = list(keyframes)
        self._t = t
        self._p = np.array([k.p_world for k in keyframes], dtype=float)
        self._yaw = np.array([k.yaw_rad for k in keyframes], dtype=float)

    @property
    def duration_s(self) -> float:
        return float(self._t[-1])

    def _flat(self, t: np.ndarray):
        """Flat outputs and derivatives: p, v, a, j (N, 3) and yaw, yaw_rate (N,)."""
        t = np.clip(np.asarray(t, dtype=float).reshape(-1), 0.0, self._t[-1])
        i = np.clip(np.searchsorted(self._t, t, side="right") - 1, 0, len(self._t) - 2)
        T = self._t[i + 1] - self._t[i]
        tau = (t - self._t[i]) / T
        dp = self._p[i + 1] - self._p[i]
        dyaw = self._yaw[i + 1] - self._yaw[i]
        s = [_S[k](tau) / T**k for k in range(4)]
        p = self._p[i] + s[0][:, None] * dp
        v, a, j = (s[k][:, None] * dp for k in (1, 2, 3))
        yaw = self._yaw[i] + s[0] * dyaw
        yaw_rate = s[1] * dyaw
        return t, p, v, a, j, yaw, yaw_rate

    def state(self, t: np.ndarray) -> TrueState:
        """Exact state at times t (s), shape (N,)."""
        t, p, v, a, j, yaw, yaw_rate = self._flat(t)
        thrust = a + np.array([0.0, 0.0, GRAVITY_M_S2])
        n_thrust = np.linalg.norm(thrust, axis=1, keepdims=True)
        z = thrust / n_thrust
        z_dot = (j - z * np.sum(z * j, axis=1, keepdims=True)) / n_thrust
        zeros = np.zeros_like(yaw)
        xc = np.column_stack([np.cos(yaw), np.sin(yaw), zeros])
        xc_dot = yaw_rate[:, None] * np.column_stack([-np.sin(yaw), np.cos(yaw), zeros])
        w = np.cross(z, xc)
        w_dot = np.cross(z_dot, xc) + np.cross(z, xc_dot)
        n_w = np.linalg.norm(w, axis=1, keepdims=True)
        y = w / n_w
        y_dot = (w_dot - y * np.sum(y * w_dot, axis=1, keepdims=True)) / n_w
        x = np.cross(y, z)
        x_dot = np.cross(y_dot, z) + np.cross(y, z_dot)
        R = np.stack([x, y, z], axis=-1)
        # omega = vee(R^T R_dot), (R^T R_dot)_ij = r_i . r_j_dot: (z . y_dot, x . z_dot, y . x_dot)
        omega = np.column_stack(
            [np.sum(z * y_dot, axis=1), np.sum(x * z_dot, axis=1), np.sum(y * x_dot, axis=1)]
        )
        return TrueState(t, p, v, a, R, omega)

    def jerk(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) jerk (m/s^3) at times t."""
        return self._flat(t)[4]


def random_aisle_survey(duration_s: float, rng: np.random.Generator) -> KeyframeTrajectory:
    """A random survey at least `duration_s` long: waypoints wandering in a 20 m x 10 m aisle
    area, 1-2.5 m high, at 0.6 m/s and 0.6 rad/s, hovering at random ones (the fusion
    benchmarks' flights; deterministic for the state of `rng`)."""
    wps = [(0.0, 0.0, 1.5, 0.0, 1.0)]
    while True:
        kf = survey_keyframes(wps, speed_m_s=0.6, yaw_rate_rad_s=0.6)
        if kf[-1].t_s >= duration_s:
            return KeyframeTrajectory(kf)
        prev = wps[-1]
        wps.append(
            (
                float(np.clip(prev[0] + rng.uniform(-4, 4), -10, 10)),
                float(np.clip(prev[1] + rng.uniform(-3, 3), -5, 5)),
                float(rng.uniform(1.0, 2.5)),
                prev[3] + float(rng.uniform(-1.5, 1.5)),
                float(rng.choice([0.0, 1.0])),
            )
        )


def survey_keyframes(
    waypoints, speed_m_s: float = 0.6, yaw_rate_rad_s: float = 0.6, min_segment_s: float = 0.8
) -> list[Keyframe]:
    """Keyframes through waypoints (x, y, z, yaw) or (x, y, z, yaw, hover_s): each segment is timed
    from its length so that its mean speed is `speed_m_s` (the peak on a smootherstep is 2.1875x
    the mean) and its mean yaw rate `yaw_rate_rad_s`; a hover_s > 0 holds that pose."""

    def hover(wp) -> float:
        return float(wp[4]) if len(wp) > 4 else 0.0

    def xyz(wp) -> tuple[float, float, float]:
        return (float(wp[0]), float(wp[1]), float(wp[2]))

    kfs = [Keyframe(0.0, xyz(waypoints[0]), float(waypoints[0][3]))]
    if hover(waypoints[0]) > 0:
        kfs.append(Keyframe(hover(waypoints[0]), kfs[0].p_world, kfs[0].yaw_rad))
    for wp in waypoints[1:]:
        prev = kfs[-1]
        dist = float(np.linalg.norm(np.subtract(wp[:3], prev.p_world)))
        dyaw = abs(float(wp[3]) - prev.yaw_rad)
        dt = max(dist / speed_m_s, dyaw / yaw_rate_rad_s, min_segment_s)
        kfs.append(Keyframe(prev.t_s + dt, xyz(wp), float(wp[3])))
        if hover(wp) > 0:
            kfs.append(Keyframe(kfs[-1].t_s + hover(wp), kfs[-1].p_world, kfs[-1].yaw_rad))
    return kfs
