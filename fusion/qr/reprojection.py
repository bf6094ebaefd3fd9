"""Reprojection model of QR corners in distorted pixels, its Jacobians, and the Cramér–Rao bound.

`Projector` (CameraModel.project with its Jacobian d(px)/d(p_cam)); `floor_reprojection` /
`symbol_reprojection` (corner pixels and their Jacobians w.r.t. a body pose / a code's pose in
the camera); `floor_pose_crb` / `load_position_crb` and the information -> covariance helpers.

Not from the paper: this is the model our PnP estimator (fusion/qr/pnp/) minimises and the bound
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

from typing import Literal, overload

import numpy as np

from fusion.camera import CameraModel, equidistant_dtheta_d, equidistant_theta_d
from fusion.errors import EstimationError
from fusion.geometry import cross_rows

# ============================================================================ projection Jacobians


class Projector:
    """CameraModel.project with its Jacobian, the camera's constants read once: the PnP
    estimator's LM evaluates it a few times per frame, so it is written out entry by entry."""

    __slots__ = ("k1", "k2", "k3", "f", "c", "p12", "p21", "M_tangential", "equi")

    def __init__(self, camera: CameraModel):
        # the equidistant model's four coefficients, or None for radial-tangential
        self.equi = camera.distortion.copy() if camera.equidistant else None
        self.k1, self.k2, p1, p2 = (float(v) for v in camera.distortion)
        self.k3 = float(camera.k3)
        self.f = np.array([float(camera.fu), float(camera.fv)])
        self.c = np.array([float(camera.cu), float(camera.cv)])
        self.p12 = np.array([p1, p2])
        self.p21 = np.array([p2, p1])
        # [2 p1 y + 6 p2 x, 6 p1 y + 2 p2 x] = [x, y] @ M_tangential: the tangential part of
        # d(x_d)/dx and d(y_d)/dy
        self.M_tangential = np.array([[6.0 * p2, 2.0 * p2], [2.0 * p1, 6.0 * p1]])

    @overload
    def project(self, p_cam: np.ndarray, jacobian: Literal[True] = ...) -> tuple[np.ndarray, np.ndarray]: ...

    @overload
    def project(self, p_cam: np.ndarray, jacobian: Literal[False]) -> tuple[np.ndarray, None]: ...

    def project(self, p_cam: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, 3) camera-frame points -> distorted pixels (N, 2) and d(pixels)/d(p_cam) (N, 2, 3)
        (None when not `jacobian`).  Points at or behind the camera (z <= 1e-9) give NaN.

        Model (fusion/camera.py): x = X/Z, y = Y/Z, r^2 = x^2 + y^2, radial = 1 + k1 r^2 + k2 r^4 + k3 r^6,
        x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2), y_d = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y,
        u = fu x_d + cu, v = fv y_d + cv; the Jacobian is F D P with F = diag(fu, fv),
        D = d(x_d, y_d)/d(x, y), P = d(x, y)/d(X, Y, Z) = [[1, 0, -x], [0, 1, -y]] / Z.  Written
        on (N, 2) arrays: the LM evaluates it a few times per frame."""
        Z = p_cam[:, 2:3]
        iz = 1.0 / np.where(Z > 1e-9, Z, np.nan)  # (N, 1)
        xy = p_cam[:, :2] * iz  # (N, 2) x, y
        if self.equi is not None:
            return self._project_equidistant(xy, iz, jacobian)
        sq = xy * xy
        r2 = sq[:, 0:1] + sq[:, 1:2]
        radial = 1.0 + r2 * (self.k1 + self.k2 * r2 + self.k3 * r2 * r2)
        cross = xy[:, 0:1] * xy[:, 1:2]  # x y
        xy_d = xy * radial + (2.0 * cross) * self.p12 + (r2 + 2.0 * sq) * self.p21
        uv = xy_d * self.f + self.c
        if not jacobian:
            return uv, None
        dr = 2.0 * (self.k1 + 2.0 * self.k2 * r2 + 3.0 * self.k3 * r2 * r2)  # d(radial)/dx = dr x
        D = np.empty((len(p_cam), 2, 2))
        diag = radial + dr * sq + xy @ self.M_tangential
        D[:, 0, 0] = diag[:, 0]
        D[:, 1, 1] = diag[:, 1]
        d01 = dr * cross + 2.0 * (xy @ self.p12)[:, None]  # = D[1, 0]
        D[:, 0, 1:] = d01
        D[:, 1, :1] = d01
        FD = D * (self.f * iz)[:, :, None]  # rows fu / Z D[0], fv / Z D[1]
        return uv, _chain_pinhole(FD, xy)

    def _project_equidistant(
        self, xy: np.ndarray, iz: np.ndarray, jacobian: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """`project` for the equidistant model (fusion/camera.py): x_d = s(r) (x, y), s = theta_d
        / r, theta = atan(r); D = s I + (s'(r) / r) (x, y)^T (x, y), s'(r) = (theta_d'(theta) r /
        (1 + r^2) - theta_d) / r^2, whose ratio to r tends to 2 (k1 - 1/3) at the centre."""
        k = self.equi
        assert k is not None
        r2 = xy[:, 0] ** 2 + xy[:, 1] ** 2
        r = np.sqrt(r2)
        theta = np.arctan(r)
        centre = r < 1e-8
        rs = np.where(centre, 1.0, r)
        td = equidistant_theta_d(theta, k)
        scale = np.where(centre, 1.0, td / rs)
        uv = xy * scale[:, None] * self.f + self.c
        if not jacobian:
            return uv, None
        ds_over_r = np.where(
            centre,
            2.0 * (k[0] - 1.0 / 3.0),
            (equidistant_dtheta_d(theta, k) * rs / (1.0 + r2) - td) / (rs**3),
        )
        D = ds_over_r[:, None, None] * (xy[:, :, None] * xy[:, None, :])
        D[:, 0, 0] += scale
        D[:, 1, 1] += scale
        FD = D * (self.f * iz)[:, :, None]
        return uv, _chain_pinhole(FD, xy)


def _chain_pinhole(FD: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """d(pixels)/d(p_cam) (N, 2, 3) from FD = F D / Z (N, 2, 2): F D P with P = [[1, 0, -x],
    [0, 1, -y]] / Z."""
    J = np.empty((len(FD), 2, 3))
    J[:, :, :2] = FD
    J[:, :, 2] = -(FD @ xy[:, :, None])[:, :, 0]
    return J


def floor_reprojection(
    camera: CameraModel, T_world_body: np.ndarray, points_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2) of world points (N, 3) seen from body pose T_world_body, and the
    Jacobian (2N, 6) of the stacked [u0, v0, u1, v1, ...] w.r.t. the body-frame right perturbation
    xi = [rx, ry, rz, tx, ty, tz] (T_world_body * Exp(xi)).

    For a "gimbaled" camera T_world_body is the level body frame (CameraModel docstring).
    Derivation: p_body(xi) = Exp(xi)^-1 p_body ~ p_body + [p_body]x w - v,
    p_cam = T_cam_body p_body, so d p_cam / d xi = R_cam_body [ [p_body]x , -I ]."""
    T_body_cam = np.asarray(camera.T_body_cam, dtype=float)
    T_world_body = np.asarray(T_world_body, dtype=float)
    R_cb = T_body_cam[:3, :3].T
    p_body = (np.asarray(points_world, dtype=float).reshape(-1, 3) - T_world_body[:3, 3]) @ T_world_body[
        :3, :3
    ]
    uv, J_proj = Projector(camera).project((p_body - T_body_cam[:3, 3]) @ T_body_cam[:3, :3])
    A = J_proj @ R_cb  # d(pixels)/d(p_body)
    J = np.empty((len(p_body), 2, 6))
    J[:, :, :3] = cross_rows(A, p_body)  # A [p_body]x
    J[:, :, 3:] = -A
    return uv, J.reshape(-1, 6)


def symbol_reprojection(
    camera: CameraModel, T_cam_symbol: np.ndarray, points_symbol: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2) of points given in a code's symbol frame, and the Jacobian (2N, 6)
    w.r.t. [w (3), dt (3)] where R_cam_symbol <- R_cam_symbol exp([w]x) (symbol frame) and
    t_cam_symbol <- t_cam_symbol + dt (camera frame, m): the last three are the code centre p_cam.
    d p_cam / d[w, dt] = [ -R_cam_symbol [p_S]x , I ]."""
    T_cam_symbol = np.asarray(T_cam_symbol, dtype=float)
    R = T_cam_symbol[:3, :3]
    p_S = np.asarray(points_symbol, dtype=float).reshape(-1, 3)
    uv, J_proj = Projector(camera).project(p_S @ R.T + T_cam_symbol[:3, 3])
    J = np.empty((len(p_S), 2, 6))
    J[:, :, :3] = -cross_rows(J_proj @ R, p_S)  # -J_proj R [p_S]x
    J[:, :, 3:] = J_proj
    return uv, J.reshape(-1, 6)


# ============================================================================ Cramér–Rao bounds


def covariance_from_information(H: np.ndarray, sigma_px: float = 1.0) -> np.ndarray:
    """sigma^2 H^-1 of a symmetric information matrix H (e.g. J^T J), symmetrised, through its
    eigen-decomposition; raises EstimationError when H is singular or its condition number is
    above 1e14."""
    H = np.asarray(H, dtype=float)
    if not np.all(np.isfinite(H)):
        raise EstimationError("non-finite Jacobian (a point at or behind the camera)")
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    if not lam[0] > 0:
        raise EstimationError("singular information matrix (degenerate view)")
    if lam[-1] > 1e14 * lam[0]:
        raise EstimationError("ill-conditioned information matrix (degenerate view)")
    C = (sigma_px**2) * ((V / lam) @ V.T)
    return 0.5 * (C + C.T)


def covariance_from_jacobian(J: np.ndarray, sigma_px: float) -> np.ndarray:
    """sigma^2 (J^T J)^-1, symmetrised; raises EstimationError when J^T J is singular."""
    return covariance_from_information(J.T @ J, sigma_px)


def floor_pose_crb(
    camera: CameraModel,
    T_world_body: np.ndarray,
    corners_world_list: list[np.ndarray],
    corner_sigma_px: float = 0.15,
) -> np.ndarray:
    """6x6 Cramér–Rao bound of the body pose, [rx, ry, rz, tx, ty, tz] in the body frame (rad, m),
    from the floor codes' world corners (each (4, 3)) seen at the TRUE pose with i.i.d. corner noise
    of `corner_sigma_px` per pixel coordinate: sigma^2 (J^T J)^-1."""
    pts = np.vstack([np.asarray(c, dtype=float).reshape(-1, 3) for c in corners_world_list])
    _, J = floor_reprojection(camera, T_world_body, pts)
    return covariance_from_jacobian(J, corner_sigma_px)


def load_position_crb(
    camera: CameraModel, T_cam_symbol: np.ndarray, corners_symbol: np.ndarray, corner_sigma_px: float = 0.15
) -> np.ndarray:
    """3x3 Cramér–Rao bound of a load code's centre in the camera frame (m), from its four corners
    (symbol frame, (4, 3)) at the true symbol pose T_cam_symbol."""
    _, J = symbol_reprojection(camera, T_cam_symbol, corners_symbol)
    return covariance_from_jacobian(J, corner_sigma_px)[3:, 3:]
