"""Measurement model of QR corners in distorted pixels, its Jacobians, and the Cramér–Rao bound.

Not from the paper: this is the model our PnP estimator (fusion/qr/pnp.py) minimises and the bound
its benchmark compares against.  Corner pixels z = pi(T_cam_world p_world) + e, e ~ N(0, sigma^2 I)
per coordinate; pi = CameraModel.project (pinhole + radial-tangential distortion).

Pose perturbations follow GTSAM's Pose3 (so covariances feed a PriorFactorPose3 unchanged):
tangent xi = [rx, ry, rz, tx, ty, tz] (rad, m) in the BODY frame, right perturbation
T = T_hat * Exp(xi), with Exp the SE(3) exponential of gtsam.Pose3.Expmap.
For Gaussian corner noise the Fisher information is J^T J / sigma^2 with J = d(pixels)/d(xi), so
the CRB of any unbiased pose estimator is sigma^2 (J^T J)^-1 (Barfoot, "State Estimation for
Robotics", 2017, Sec. 7.3 for the perturbation; Kay, "Fundamentals of Statistical Signal
Processing I", 1993, eq. 3.31 for the Gaussian Fisher information).
"""
from __future__ import annotations

import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import inv_T, transform_points
from fusion.errors import EstimationError

# ============================================================================ SE(3) in GTSAM's order


def skew(w: np.ndarray) -> np.ndarray:
    """3x3 cross-product matrix [w]x (skew(w) @ p == cross(w, p))."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def skew_stack(p: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    p = np.asarray(p, dtype=float)
    S = np.zeros(p.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -p[..., 2], p[..., 1]
    S[..., 1, 0], S[..., 1, 2] = p[..., 2], -p[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -p[..., 1], p[..., 0]
    return S


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix exp([w]x) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    th2 = float(w @ w)
    W = skew(w)
    if th2 < 1e-16:
        return np.eye(3) + W + 0.5 * W @ W
    th = np.sqrt(th2)
    return np.eye(3) + np.sin(th) / th * W + (1.0 - np.cos(th)) / th2 * W @ W


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 SE(3) exponential of xi = [w (3), v (3)], the same map as gtsam.Pose3.Expmap."""
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


# ============================================================================ projection Jacobians


def project_with_jacobian(camera: CameraModel, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) camera-frame points -> distorted pixels (N, 2) and d(pixels)/d(p_cam) (N, 2, 3).

    Points at or behind the camera give NaN (as CameraModel.project)."""
    p_cam = np.asarray(p_cam, dtype=float).reshape(-1, 3)
    X, Y, Z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    Zs = np.where(Z > 1e-9, Z, np.nan)
    x, y = X / Zs, Y / Zs
    k1, k2, p1, p2 = camera.distortion
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    dr = 2.0 * (k1 + 2.0 * k2 * r2)                    # d(radial)/dx = dr * x
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    D = np.empty((len(p_cam), 2, 2))                   # d(xd, yd)/d(x, y)
    D[:, 0, 0] = radial + dr * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    D[:, 0, 1] = dr * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    D[:, 1, 0] = dr * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    D[:, 1, 1] = radial + dr * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    P = np.zeros((len(p_cam), 2, 3))                   # d(x, y)/d(X, Y, Z)
    P[:, 0, 0] = 1.0 / Zs
    P[:, 1, 1] = 1.0 / Zs
    P[:, 0, 2] = -x / Zs
    P[:, 1, 2] = -y / Zs
    F = np.diag([camera.fu, camera.fv])
    uv = np.stack([camera.fu * xd + camera.cu, camera.fv * yd + camera.cv], axis=-1)
    return uv, F @ D @ P


def floor_reprojection(camera: CameraModel, T_world_body: np.ndarray, points_world: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2) of world points (N, 3) seen from body pose T_world_body, and the
    Jacobian (2N, 6) of the stacked [u0, v0, u1, v1, ...] w.r.t. the body-frame right perturbation
    xi = [rx, ry, rz, tx, ty, tz] (T_world_body * Exp(xi)).

    For a "gimbaled" camera T_world_body is the level body frame (CameraModel docstring).
    Derivation: p_body(xi) = Exp(xi)^-1 p_body ~ p_body + [p_body]x w - v, p_cam = T_cam_body p_body,
    so d p_cam / d xi = R_cam_body [ [p_body]x , -I ]."""
    T_cam_body = inv_T(camera.T_body_cam)
    p_body = transform_points(inv_T(T_world_body), points_world)
    p_cam = transform_points(T_cam_body, p_body)
    uv, J_proj = project_with_jacobian(camera, p_cam)
    R_cb = T_cam_body[:3, :3]
    n = len(p_body)
    J_pt = np.empty((n, 3, 6))
    J_pt[:, :, :3] = R_cb @ skew_stack(p_body)
    J_pt[:, :, 3:] = -R_cb
    return uv, np.einsum("nij,njk->nik", J_proj, J_pt).reshape(2 * n, 6)


def symbol_reprojection(camera: CameraModel, T_cam_symbol: np.ndarray, points_symbol: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2) of points given in a code's symbol frame, and the Jacobian (2N, 6)
    w.r.t. [w (3), dt (3)] where R_cam_symbol <- R_cam_symbol exp([w]x) (symbol frame) and
    t_cam_symbol <- t_cam_symbol + dt (camera frame, m): the last three are the code centre p_cam.
    d p_cam / d[w, dt] = [ -R_cam_symbol [p_S]x , I ]."""
    R, t = T_cam_symbol[:3, :3], T_cam_symbol[:3, 3]
    p_S = np.asarray(points_symbol, dtype=float)
    uv, J_proj = project_with_jacobian(camera, p_S @ R.T + t)
    n = len(p_S)
    J_pt = np.empty((n, 3, 6))
    J_pt[:, :, :3] = -R @ skew_stack(p_S)
    J_pt[:, :, 3:] = np.eye(3)
    return uv, np.einsum("nij,njk->nik", J_proj, J_pt).reshape(2 * n, 6)


# ============================================================================ Cramér–Rao bounds


def covariance_from_jacobian(J: np.ndarray, sigma_px: float) -> np.ndarray:
    """sigma^2 (J^T J)^-1, symmetrised; raises EstimationError when J^T J is singular."""
    H = J.T @ J
    if not np.all(np.isfinite(H)):
        raise EstimationError("non-finite Jacobian (a point at or behind the camera)")
    try:
        C = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        raise EstimationError("singular information matrix (degenerate view)") from None
    if np.linalg.cond(H) > 1e14:
        raise EstimationError("ill-conditioned information matrix (degenerate view)")
    C = sigma_px ** 2 * C
    return 0.5 * (C + C.T)


def floor_pose_crb(camera: CameraModel, T_world_body: np.ndarray,
                   corners_world_list: list[np.ndarray], corner_sigma_px: float = 0.15
                   ) -> np.ndarray:
    """6x6 Cramér–Rao bound of the body pose, [rx, ry, rz, tx, ty, tz] in the body frame (rad, m),
    from the floor codes' world corners (each (4, 3)) seen at the TRUE pose with i.i.d. corner noise
    of `corner_sigma_px` per pixel coordinate: sigma^2 (J^T J)^-1."""
    pts = np.vstack([np.asarray(c, dtype=float).reshape(-1, 3) for c in corners_world_list])
    _, J = floor_reprojection(camera, T_world_body, pts)
    return covariance_from_jacobian(J, corner_sigma_px)


def load_position_crb(camera: CameraModel, T_cam_symbol: np.ndarray, corners_symbol: np.ndarray,
                      corner_sigma_px: float = 0.15) -> np.ndarray:
    """3x3 Cramér–Rao bound of a load code's centre in the camera frame (m), from its four corners
    (symbol frame, (4, 3)) at the true symbol pose T_cam_symbol."""
    _, J = symbol_reprojection(camera, T_cam_symbol, corners_symbol)
    return covariance_from_jacobian(J, corner_sigma_px)[3:, 3:]
