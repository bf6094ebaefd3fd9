"""SO(3) / SE(3): the one place in `fusion` that writes rotation maths.

Conventions (DESIGN.md "Conventions"):
- `T_a_b` is a 4x4 homogeneous transform mapping b-coordinates into a-coordinates; stacks are
  (..., 4, 4).
- Tangent vectors follow GTSAM's Pose3: xi = [w (3), v (3)] = [rx, ry, rz, tx, ty, tz] (rad, m),
  right perturbation T = T_hat * Exp(xi), Exp = gtsam.Pose3.Expmap.
- Quaternions are (w, x, y, z) with w >= 0 inside the code; (x, y, z, w) only at file
  boundaries (TUM, scipy).
- Yaw is the heading of body x from world x, counter-clockwise (the paper's D_r-theta), rad.

Formulas: Rodrigues' exponential and the SE(3) V matrix and its inverse as in Barfoot, "State
Estimation for Robotics" (2017), eqs. 7.14, 7.86; the adjoint as GTSAM's `Pose3::AdjointMap`.
The hot paths (the PnP LM) use the hand-written `so3_exp` / `so3_exp_stack`; everything else
uses scipy's `Rotation`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

# --------------------------------------------------------------------------- matrices


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a 3-vector translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform (or a stack of them, shape (..., 4, 4))."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Map (N, 3) points from frame b into frame a."""
    p_b = np.asarray(p_b, dtype=float)
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two 3-vectors, the same products and differences as np.cross (whose general
    set-up costs more than the arithmetic on the EKF's per-update path)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def skew(w: np.ndarray) -> np.ndarray:
    """3x3 cross-product matrix [w]x (skew(w) @ p == cross(w, p))."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def skew_stack(p: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices of (..., 3) vectors."""
    p = np.asarray(p, dtype=float)
    S = np.zeros(p.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -p[..., 2], p[..., 1]
    S[..., 1, 0], S[..., 1, 2] = p[..., 2], -p[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -p[..., 1], p[..., 0]
    return S


def cross_rows(A: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, k, 3) rows a of A and (N, 3) points p -> (N, k, 3) rows a x p, i.e. A_n @ [p_n]x
    (a^T [p]x = (a x p)^T), without forming [p]x."""
    out = np.empty_like(A)
    a0, a1, a2 = A[..., 0], A[..., 1], A[..., 2]
    q0, q1, q2 = p[:, 0:1], p[:, 1:2], p[:, 2:3]
    out[..., 0] = a1 * q2 - a2 * q1
    out[..., 1] = a2 * q0 - a0 * q2
    out[..., 2] = a0 * q1 - a1 * q0
    return out


# --------------------------------------------------------------------------- SO(3)


def _so3_exp_entries(w0: float, w1: float, w2: float) -> tuple[float, ...]:
    """The 9 entries (row-major) of exp([w]x) = I + a [w]x + b [w]x^2, a = sin(th)/th,
    b = (1 - cos(th))/th^2 (Rodrigues, Barfoot eq. 7.14; Taylor series near th = 0), on Python
    floats: so3_exp and so3_exp_floats."""
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-8:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0  # error O(th^4) < 1e-16
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    b01, b02, b12 = b * w0 * w1, b * w0 * w2, b * w1 * w2
    return (
        1.0 - b * (w1 * w1 + w2 * w2),
        b01 - a * w2,
        b02 + a * w1,
        b01 + a * w2,
        1.0 - b * (w0 * w0 + w2 * w2),
        b12 - a * w0,
        b02 - a * w1,
        b12 + a * w0,
        1.0 - b * (w0 * w0 + w1 * w1),
    )


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix exp([w]x) (`_so3_exp_entries`), written out entry by entry: it runs in
    every PnP LM step."""
    w0, w1, w2 = w.tolist() if isinstance(w, np.ndarray) else (float(v) for v in w)
    return np.array(_so3_exp_entries(w0, w1, w2)).reshape(3, 3)


def so3_exp_floats(phi: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotations exp([phi_k]x) of (K, 3) rotation vectors with so3_exp's arithmetic
    (the same numbers) on Python floats, one array made at the end: for a handful of rotations
    (the IMU samples of one EKF frame interval) ~4x cheaper than so3_exp_stack's ~20 array
    operations, which cost per call, not per rotation."""
    rows = [_so3_exp_entries(w0, w1, w2) for w0, w1, w2 in np.asarray(phi, float).tolist()]
    return np.array(rows).reshape(-1, 3, 3)


def so3_exp_stack(w: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotation matrices exp([w_k]x) of (K, 3) rotation vectors (Rodrigues, as so3_exp)."""
    w = np.asarray(w, dtype=float)
    if len(w) == 1:
        return so3_exp(w[0])[None]
    th2 = np.einsum("ki,ki->k", w, w)
    small = th2 < 1e-8
    th = np.sqrt(th2)
    safe_th, safe_th2 = np.where(small, 1.0, th), np.where(small, 1.0, th2)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / safe_th)[:, None, None]
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / safe_th2)[:, None, None]
    W = skew_stack(w)
    return np.eye(3) + a * W + b * (W @ W)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector(s) (..., 3) of rotation matrices (..., 3, 3)."""
    return Rotation.from_matrix(R).as_rotvec()


def rot_z(yaw: float) -> np.ndarray:
    """Rotation about world z by `yaw` rad."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_z_stack(yaw: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about z by the angles `yaw` (N,) rad."""
    yaw = np.asarray(yaw, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros(yaw.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    R[..., 2, 2] = 1.0
    return R


def yaw_of(R_world_body: np.ndarray) -> np.ndarray:
    """Heading of body x from world x, counter-clockwise, in rad in (-pi, pi] (works for (...,3,3))."""
    R = np.asarray(R_world_body)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def wrap_angle(a):
    """Wrap an angle (or array of angles) to (-pi, pi]."""
    return -(np.mod(-np.asarray(a) + np.pi, 2.0 * np.pi) - np.pi)


def quat_wxyz_from_R(R: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (w, x, y, z), w >= 0, from rotation matrix (or stack (N,3,3))."""
    q_xyzw = Rotation.from_matrix(R).as_quat()
    q = np.roll(q_xyzw, 1, axis=-1)
    sign = np.where(q[..., :1] < 0.0, -1.0, 1.0)
    return q * sign


def R_from_quat_wxyz(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix (or stack) from quaternion(s) (w, x, y, z); normalises the input.
    Raises ValueError for a zero-norm quaternion."""
    q = np.asarray(q_wxyz, dtype=float)
    return Rotation.from_quat(np.roll(q, -1, axis=-1)).as_matrix()


def R_from_euler(seq: str, angles, degrees: bool = False) -> np.ndarray:
    """Rotation matrix (or stack) from Euler angles in scipy's `seq` convention (upper case:
    intrinsic, lower case: extrinsic)."""
    return Rotation.from_euler(seq, angles, degrees=degrees).as_matrix()


def R_from_rotvec(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (or stack) exp([w]x) for rotation vector(s) w (..., 3) (scipy)."""
    return Rotation.from_rotvec(w).as_matrix()


# --------------------------------------------------------------------------- SE(3)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 SE(3) exponential of xi = [w (3), v (3)], the same map as gtsam.Pose3.Expmap
    (Barfoot eq. 7.86 for V)."""
    xi = np.asarray(xi, dtype=float)
    w, v = xi[:3], xi[3:]
    th2 = float(w @ w)
    W = skew(w)
    if th2 < 1e-16:
        V = np.eye(3) + 0.5 * W
    else:
        th = np.sqrt(th2)
        V = np.eye(3) + (1.0 - np.cos(th)) / th2 * W + (th - np.sin(th)) / (th2 * th) * W @ W
    T = np.eye(4)
    T[:3, :3] = so3_exp(w)
    T[:3, 3] = V @ v
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """(N, 6) Log of (N, 4, 4) poses in GTSAM's Pose3 order [rx, ry, rz, tx, ty, tz]
    (same as gtsam.Pose3.Logmap: translation part u = V(w)^-1 t, Barfoot eq. 7.86)."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    w = so3_log(T[:, :3, :3])
    t = T[:, :3, 3]
    theta = np.linalg.norm(w, axis=1)
    W = skew_stack(w)
    W2 = W @ W
    # V^-1 = I - W/2 + (1/theta^2) (1 - (theta sin theta) / (2 (1 - cos theta))) W^2
    with np.errstate(invalid="ignore", divide="ignore"):
        c = (1.0 - theta * np.sin(theta) / (2.0 * (1.0 - np.cos(theta)))) / theta**2
    c = np.where(theta < 1e-4, 1.0 / 12.0 + theta**2 / 720.0, c)
    Vinv = np.eye(3) - 0.5 * W + c[:, None, None] * W2
    u = np.einsum("nij,nj->ni", Vinv, t)
    return np.hstack([w, u])


def is_rigid_transform(T: np.ndarray, atol: float = 1e-6) -> bool:
    """Whether a 4x4 matrix is a rigid transform: orthonormal rotation with det +1 and the last row
    [0, 0, 0, 1], within `atol` (files print a limited number of digits)."""
    R = T[:3, :3]
    return bool(
        np.allclose(R @ R.T, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1) <= atol
        and np.allclose(T[3], [0, 0, 0, 1])
    )


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a pose in GTSAM's [r, t] order: [[R, 0], [[t]x R, R]]
    (gtsam.Pose3.AdjointMap): xi_a = Ad(T_a_b) xi_b."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = skew(t) @ R
    return Ad


def level_frame(T_world_body: np.ndarray) -> np.ndarray:
    """The body frame with roll and pitch removed: same origin, z = world z, same yaw
    (works for stacks (..., 4, 4))."""
    T = np.asarray(T_world_body, dtype=float)
    out = np.zeros_like(T)
    out[..., :3, :3] = rot_z_stack(yaw_of(T[..., :3, :3]))
    out[..., :3, 3] = T[..., :3, 3]
    out[..., 3, 3] = 1.0
    return out


def yaw_gradient(R_world_body: np.ndarray) -> np.ndarray:
    """(3,) d yaw / d w of yaw_of(R Exp(w)) at w = 0 (right perturbation, GTSAM's Rot3 / Pose3).

    R' = R (I + [w]x) moves the first column by R (w x e_x) = R[:, 1] w_z - R[:, 2] w_y, and
    yaw = atan2(R10, R00) by (R00 dR10 - R10 dR00) / (R00^2 + R10^2); w_x (roll) does not move it."""
    R = np.asarray(R_world_body, dtype=float)
    n = R[0, 0] ** 2 + R[1, 0] ** 2
    return np.array(
        [0.0, (R[1, 0] * R[0, 2] - R[0, 0] * R[1, 2]) / n, (R[0, 0] * R[1, 1] - R[1, 0] * R[0, 1]) / n]
    )


def level_frame_jacobian(T_world_body: np.ndarray) -> np.ndarray:
    """(6, 6) d xi_level / d xi_body: how a right perturbation of the body pose,
    T_world_body Exp(xi_body), moves level_frame(T_world_body) in its own right-perturbation
    coordinates, level Exp(xi_level) (both in GTSAM's Pose3 order [r, t]).

    The level frame keeps only yaw and position: its rotation moves about its z by d yaw
    (yaw_gradient), its origin by R dt, i.e. by Rz(yaw)^T R dt in its own axes."""
    T = np.asarray(T_world_body, dtype=float)
    R = T[:3, :3]
    J = np.zeros((6, 6))
    J[2, :3] = yaw_gradient(R)
    J[3:, 3:] = rot_z(float(yaw_of(R))).T @ R
    return J


# --------------------------------------------------------------------------- interpolation


def interpolate_poses(ts: np.ndarray, T: np.ndarray, tq: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) sampled at increasing times `ts` (N,), interpolated at `tq` (M,) inside
    [ts[0], ts[-1]]: linear position, slerp (geodesic) rotation.  Returns (M, 4, 4)."""
    return PoseInterpolator(ts, T)(tq)


class PoseInterpolator:
    """interpolate_poses for many queries of one trajectory: the samples' rotations and the
    slerp's segment rotations (N of each) are prepared once, each call then costs only its
    queries (the same numbers as interpolate_poses)."""

    def __init__(self, ts: np.ndarray, T: np.ndarray) -> None:
        self.ts = np.asarray(ts, dtype=float)
        self.p = np.asarray(T[:, :3, 3], dtype=float)
        self.R0 = np.asarray(T[0, :3, :3], dtype=float)
        self.slerp = Slerp(self.ts, Rotation.from_matrix(T[:, :3, :3])) if len(self.ts) > 1 else None

    def __call__(self, tq: np.ndarray) -> np.ndarray:
        """(M, 4, 4) T_world_body at the times `tq` (M,)."""
        tq = np.asarray(tq, dtype=float)
        out = np.tile(np.eye(4), (len(tq), 1, 1))
        for a in range(3):
            out[:, a, 3] = np.interp(tq, self.ts, self.p[:, a])
        out[:, :3, :3] = self.R0 if self.slerp is None else self.slerp(tq).as_matrix()
        return out


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    """The pose a fraction `a` in [0, 1] of the way from T0 to T1: linear position, geodesic
    rotation R0 Exp(a Log(R0^T R1))."""
    dw = so3_log(T0[:3, :3].T @ T1[:3, :3])
    return make_T(T0[:3, :3] @ so3_exp(a * dw), (1 - a) * T0[:3, 3] + a * T1[:3, 3])


def rotation_aligning(u: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R minimising sum |w_i - R u_i|^2 over vectors u, w (N, 3) (Wahba's problem,
    solved by SVD: Kabsch 1976; Umeyama 1991, eqs. 38-39, with the det fix against a
    reflection).  Returns (R (3, 3), singular values (3,) of sum u_i w_i^T, descending: a small
    second value means the rotation about the dominant direction is not determined)."""
    H = np.asarray(u, float).T @ np.asarray(w, float)
    U, S, Vt = np.linalg.svd(H)
    d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T, S


def integrate_gyro(gyro_rad_s: np.ndarray, dt_s: np.ndarray) -> np.ndarray:
    """(N + 1, 3, 3) rotations R_0_k of the sensor frame at sample k relative to sample 0, by
    chaining R_k+1 = R_k Exp(w_k dt_k) over angular rates (N, 3) held for dt (N,) s."""
    dR = so3_exp_stack(np.asarray(gyro_rad_s, float) * np.asarray(dt_s, float)[:, None])
    out = np.empty((len(dR) + 1, 3, 3))
    out[0] = np.eye(3)
    for k in range(len(dR)):
        out[k + 1] = out[k] @ dR[k]
    return out


# --------------------------------------------------------------------------- world frames


def R_world_loadsymbol(normal_yaw: float) -> np.ndarray:
    """Rotation of a load code's symbol frame S on a vertical face whose outward normal points at
    heading `normal_yaw` (rad): z_S = normal, y_S = world +z, x_S = y_S x z_S (the viewer's right)."""
    n = np.array([math.cos(normal_yaw), math.sin(normal_yaw), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(up, n)
    return np.column_stack([x, up, n])
