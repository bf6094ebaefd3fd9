"""Corner noise of QR detections as whitening matrices: W_i (z_i - h_i) has identity covariance,
so every solver minimises (and every covariance uses) the same weighted reprojection error."""

from __future__ import annotations

import math

import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import floor_payload
from fusion.qr.pnp.undistort import undistort
from fusion.qr.refine import FALLBACK_SIGMA_PX
from fusion.qr.reprojection import Projector
from fusion.world import FloorLayout, Placement

DEFAULT_CORNER_SIGMA_PX = 0.15
"""Refined-corner error per pixel coordinate (DESIGN.md: about 0.13 px mean after refinement)."""
CORNER_COORDINATES = 8
"""Residuals per code: u, v of its four corners (TL, TR, BR, BL)."""
CORNER_CLASSES = ("refined", "decoder")
"""Corner classes with their own noise scale (fusion.estimate.variance.pnp_class_components):
corners refined with their own calibrated sigma, and the decoder's corners kept with
FALLBACK_SIGMA_PX (refinement failed its self-check or could not measure the code)."""


def corner_whitening(detections, default_sigma_px: float) -> np.ndarray:
    """(n, 8, 8) whitening matrices W_i = L_i^-1 of each detection's corner covariance
    C_i = L_i L_i^T (Cholesky; order TL u, TL v, TR u, ..., BL v), so that W_i (z_i - h_i) has
    identity covariance: `corner_cov_px2` when set and positive definite (the corners come from
    one homography fit, so their errors are correlated), else diag(1 / sigma) with sigma the
    detection's `corner_sigma_px` or `default_sigma_px` (`corner_sigmas`)."""
    n = CORNER_COORDINATES
    sig = corner_sigmas(detections, default_sigma_px).reshape(-1, n)
    out = np.zeros((len(sig), n, n))
    idx = np.arange(n)
    out[:, idx, idx] = 1.0 / sig
    with_cov: list[int] = []
    covs: list[np.ndarray] = []
    for i, d in enumerate(detections):
        cov = getattr(d, "corner_cov_px2", None)
        if cov is not None:
            cov = np.asarray(cov, dtype=float)
            if cov.shape == (n, n):
                with_cov.append(i)
                covs.append(cov)
    if covs:
        C = np.stack(covs)
        finite = np.isfinite(C).all(axis=(1, 2))
        with_cov, C = [i for i, f in zip(with_cov, finite) if f], C[finite]
        if with_cov:
            C = 0.5 * (C + np.swapaxes(C, 1, 2))
            try:
                out[with_cov] = np.linalg.inv(np.linalg.cholesky(C))
            except np.linalg.LinAlgError:  # one is not positive definite: one at a time
                for i, Ci in zip(with_cov, C):
                    try:
                        out[i] = np.linalg.inv(np.linalg.cholesky(Ci))
                    except np.linalg.LinAlgError:
                        pass  # keeps diag(1 / sigma)
    return out


def corner_sigmas(detections, default_sigma_px: float) -> np.ndarray:
    """Per-residual 1-sigma (8 per detection: u, v of its 4 corners), px: each detection's own
    `corner_sigma_px` when it has one (fusion.qr.refine's calibrated value), else the default."""
    out = []
    for d in detections:
        s = getattr(d, "corner_sigma_px", None)
        out.append(float(s) if s is not None and math.isfinite(s) and s > 0 else float(default_sigma_px))
    return np.repeat(np.asarray(out, dtype=float), CORNER_COORDINATES)


def corner_classes(detections) -> np.ndarray:
    """(n,) index into CORNER_CLASSES of each detection: "decoder" when its corner_sigma_px is
    FALLBACK_SIGMA_PX (fusion.qr.refine's fallback and detect's unrefined corners), else
    "refined" (a detection without a sigma gets the refined default, DEFAULT_CORNER_SIGMA_PX)."""
    out = np.zeros(len(detections), dtype=np.int64)
    for i, d in enumerate(detections):
        s = getattr(d, "corner_sigma_px", None)
        if s is not None and math.isclose(float(s), FALLBACK_SIGMA_PX):
            out[i] = CORNER_CLASSES.index("decoder")
    return out


def floor_whitening(
    sightings,
    default_sigma_px: float,
    placement: Placement | FloorLayout | None,
    camera: CameraModel | None = None,
) -> np.ndarray:
    """(n, 8, 8) whitening of floor sightings' corners (fusion.qr.codes.FloorSighting) against
    their codes' world corners as given (the payloads', or a merged map's: world.FloorLayout):
    `corner_whitening`'s, or, when where the codes lie is uncertain (`placement` enabled:
    world.yaml's floor_qr.placement_sigma_m / _deg, or a map's covariances), that of
    C_i + F_i F_i^T (`placement_factors`; `camera` required then).  A code laid 1 cm off its
    payload moves its corners by ~4 px at 1.3 m against a corner sigma of 0.03-0.15 px: PnP on
    the nominal corners then has to weigh its codes by that, and its covariance carries it (a
    single code's pose by the whole placement error; codes that disagree by centimetres are
    fitted within their placement, not by tilting the pose).  The error's tilt and height are
    not modelled (a flat floor)."""
    W0 = corner_whitening([s.detection for s in sightings], default_sigma_px)
    if placement is None or not placement.enabled or not len(W0):
        return W0
    if camera is None:
        raise ValueError("floor_whitening: a placement sigma needs the camera")
    return whitening_with(W0, placement_factors(camera, sightings, placement))


def whitening_with(W0: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n, 8, 8) whitening of the corner covariances W0^-1 W0^-T + F F^T (F (n, 8, m)): inverse
    Cholesky factors; a code whose sum is not positive definite keeps W0."""
    L0 = np.linalg.inv(W0)  # the corner covariance's Cholesky factor (W0 = L0^-1)
    C = L0 @ np.swapaxes(L0, 1, 2) + F @ np.swapaxes(F, 1, 2)
    out = W0.copy()
    idx = np.flatnonzero(np.isfinite(C).all(axis=(1, 2)))
    try:
        out[idx] = np.linalg.inv(np.linalg.cholesky(C[idx]))
    except np.linalg.LinAlgError:  # one is not positive definite: one at a time
        for i in idx.tolist():
            try:
                out[i] = np.linalg.inv(np.linalg.cholesky(C[i]))
            except np.linalg.LinAlgError:
                pass  # keeps the corners' own whitening
    return out


def placement_factors(camera: CameraModel, sightings, placement: Placement | FloorLayout) -> np.ndarray:
    """(n, 8, 4) F with F F^T the pixel covariance that the codes' placement adds to each floor
    sighting's corners: J_p S (`placement_pixel_jacobians`, the code's x, y and yaw about its
    centre; S S^T the code's (x, y, yaw) covariance: world.yaml's sigmas, or a merged map's for
    the codes it holds) and the turn's second order g: a code turned by d has its corners
    (P - c) d^2 / 2 nearer its centre than the tangent J_yaw d puts them (a shrink the tangent
    cannot take), E[(d^2 / 2)^2] = 3 s_yaw^4 / 4, so g = sqrt(3 / 4) s_yaw^2 d(px)/d(floor point)
    (P - c).  At clean renders' 0.026 px corners a 2 deg sigma without g read NEES 27.5 of 6
    (tests/test_placement.py)."""
    uv = np.array([np.asarray(s.detection.corners_px, dtype=float).reshape(4, 2) for s in sightings])
    P = np.array([np.asarray(s.corners_world, dtype=float).reshape(4, 3)[:, :2] for s in sightings])
    c = np.array([np.asarray(s.centre_world, dtype=float).reshape(3)[:2] for s in sightings])
    J = placement_pixel_jacobians(camera, uv, P, c)  # (n, 8, 3)
    r = (P - c[:, None, :])[..., None]  # (n, 4, 2, 1)
    g = (J[:, :, :2].reshape(-1, 4, 2, 2) @ r).reshape(-1, CORNER_COORDINATES, 1)
    if isinstance(placement, Placement):  # one sigma for every code
        sigmas = np.array([placement.sigma_m, placement.sigma_m, placement.sigma_rad])
        return np.concatenate([J * sigmas, math.sqrt(0.75) * placement.sigma_rad**2 * g], axis=2)
    cov = np.array([placement.covariance(floor_payload(s.payload.x, s.payload.y)) for s in sightings])
    w, V = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    S = V * np.sqrt(np.maximum(w, 0.0))[:, None, :]  # S S^T = cov
    return np.concatenate([J @ S, math.sqrt(0.75) * cov[:, 2, 2, None, None] * g], axis=2)


def placement_pixel_jacobians(
    camera: CameraModel, uv: np.ndarray, P_xy: np.ndarray, centre_xy: np.ndarray
) -> np.ndarray:
    """(n, 8, 3) d(corner px)/d(code x, y, yaw) of n floor codes observed at uv (n, 4, 2) (distorted
    px): `placement_jacobians` of the undistorted corners (exact for the ideal camera), through
    the lens's Jacobian d(px)/d(normalised point) at each corner.  Taken in pixels directly, the
    homography would carry the lens's curvature across the code (a fraction of a percent of a
    4 px move: at the 0.03 px corner sigma of clean renders, enough to tilt the pose)."""
    n = len(uv)
    xn = undistort(camera, uv.reshape(-1, 2))  # (4 n, 2)
    _, D = Projector(camera).project(np.column_stack([xn, np.ones(len(xn))]))  # (4 n, 2, 3)
    J = placement_jacobians(xn.reshape(n, 4, 2), P_xy, centre_xy).reshape(n, 4, 2, 3)
    out = D[:, :, :2].reshape(n, 4, 2, 2) @ J
    return out.reshape(n, CORNER_COORDINATES, 3)


def placement_jacobians(uv: np.ndarray, P_xy: np.ndarray, centre_xy: np.ndarray) -> np.ndarray:
    """(n, 8, 3) d(corner image point)/d(code x, y, yaw) of n floor codes: uv (n, 4, 2) their
    observed corners (ideal pinhole points: `placement_pixel_jacobians` takes distorted pixels
    there), P_xy (n, 4, 2) their nominal world corners on the floor, centre_xy (n, 2) the
    centres they turn about.  Each code's homography H (floor -> px) from its 4 correspondences
    (direct linear transform with h_33 = 1, about the code's centre and mean pixel for
    conditioning; Hartley & Zisserman 2004, sec. 4.1); d(u, v)/d(X, Y) = [[h00 - u h20, h01 - u h21],
    [h10 - v h20, h11 - v h21]] / w at each corner; a yaw dpsi moves corner X by
    dpsi (-(Y - cy), X - cx).  A code whose 4 points are degenerate gets zeros (no inflation).
    Batched by hand: 20,000 codes 0.05 CPU s, against 0.17 s for OpenCV's getPerspectiveTransform
    one code at a time (the homographies alone, before their Jacobians)."""
    n = len(uv)
    X = P_xy - centre_xy[:, None, :]  # (n, 4, 2)
    m = uv.mean(axis=1, keepdims=True)
    u = uv - m
    A = np.zeros((n, 8, 8))
    b = u.reshape(n, 8)
    A[:, 0::2, 0:2] = X
    A[:, 0::2, 2] = 1.0
    A[:, 1::2, 3:5] = X
    A[:, 1::2, 5] = 1.0
    A[:, 0::2, 6:8] = -u[:, :, 0:1] * X
    A[:, 1::2, 6:8] = -u[:, :, 1:2] * X
    h = np.zeros((n, 8))
    good = np.isfinite(A).all(axis=(1, 2)) & np.isfinite(b).all(axis=1)
    good[good] = np.abs(np.linalg.det(A[good])) > 0.0
    if good.any():
        try:
            h[good] = np.linalg.solve(A[good], b[good][:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # one singular among them: one at a time
            for i in np.flatnonzero(good).tolist():
                try:
                    h[i] = np.linalg.solve(A[i], b[i])
                except np.linalg.LinAlgError:
                    good[i] = False
    H = np.concatenate([h, np.ones((n, 1))], axis=1).reshape(n, 3, 3)
    w = X @ H[:, 2, :2, None] + 1.0  # (n, 4, 1) the homography's scale at each corner
    J_xy = np.empty((n, 4, 2, 2))
    J_xy[:, :, 0, :] = (H[:, None, 0, :2] - u[:, :, 0:1] * H[:, None, 2, :2]) / w
    J_xy[:, :, 1, :] = (H[:, None, 1, :2] - u[:, :, 1:2] * H[:, None, 2, :2]) / w
    turn = np.stack([-X[:, :, 1], X[:, :, 0]], axis=2)  # (n, 4, 2) d(corner)/d(yaw)
    J = np.concatenate([J_xy, (J_xy @ turn[:, :, :, None])], axis=3)  # (n, 4, 2, 3)
    J = J.reshape(n, 8, 3)
    J[~(good & np.isfinite(J).all(axis=(1, 2)))] = 0.0
    return J
