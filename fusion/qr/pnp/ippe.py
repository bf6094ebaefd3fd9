"""Starting poses of planar targets: IPPE (Collins & Bartoli 2014) vectorised over many views,
and OpenCV's solvePnPGeneric (IPPE, IPPE_SQUARE, SQPnP) one view at a time.

The IPPE starts come from `ippe` even for a single view, although OpenCV's is faster there:
OpenCV returns rotation vectors, and near a rotation of pi -- a level body over a down-looking
camera, as in simulated hovers -- its IPPE poses are wrong (opencv-contrib 5.0: [13.6, -13.6, 0]
or [0, 0, 0] for [2.22, -2.22, 0]; both poses tilted by +-12 deg for a code at the image centre),
and the LM cannot reach the level pose from them (tests/test_pnp.py
`test_level_body_single_frame_is_recovered_exactly`).  OpenCV stays the fallback for a view
`ippe` finds degenerate, and the source of SQPnP starts."""

from __future__ import annotations

import cv2
import numpy as np

from fusion.qr.pnp.undistort import cv_points

_EYE3 = np.eye(3)


def opencv_starts(
    points: np.ndarray, xn: np.ndarray, origin: np.ndarray | None, method: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate poses (R, t) with p_cam = R p + t of points p (N, 3) seen at normalised image
    points xn (N, 2), from cv2.solvePnPGeneric with `method` (IPPE_SQUARE: one square code,
    `origin` its centre, the points in a frame with the symbol's axes; planar IPPE or SQPnP:
    any points, `origin` None = their mean).  Empty when OpenCV fails."""
    origin = np.asarray(origin, dtype=float) if origin is not None else points.mean(axis=0)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            cv_points(points - origin), cv_points(xn), _EYE3, None, flags=method
        )
    except cv2.error:
        return []
    out = []
    for rv, tv in zip(rvecs[:n], tvecs[:n]):
        R = cv2.Rodrigues(rv)[0]
        out.append((R, tv.reshape(3) - R @ origin))
    return out


def ippe(X: np.ndarray, xn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """IPPE (Collins & Bartoli, "Infinitesimal Plane-Based Pose Estimation", IJCV 2014, Sec. 4 and
    Algorithm 1) for K views at once: plane points X (K, N, 2) (z = 0, N >= 4) and their
    normalised image points xn (K, N, 2) -> the two candidate poses of each view, R (K, 2, 3, 3),
    t (K, 2, 3) with p_cam = R [x, y, 0] + t (as cv2.solvePnPGeneric(SOLVEPNP_IPPE), whose
    homography estimate differs slightly for N > 4).  Raises np.linalg.LinAlgError when a view
    is degenerate.

    Homography H (plane -> image, h22 = 1) by the normalised DLT (Hartley & Zisserman 2004,
    Alg. 4.2); J its Jacobian at the plane origin, v = H(0); R_v rotates z onto the ray of v
    (IPPE eq. 29); A = B^-1 J with B = [I2, -v] R_v[:, :2]; gamma = the largest singular value of A
    and R~ = A / gamma the top-left 2x2 of R_v^T R, completed to a rotation in the two ways b, -b
    (eq. 30-32); each t by linear least squares on the projection equations (eq. 37).
    A degenerate view (e.g. all points at one pixel) gives NaN poses or LinAlgError."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return _ippe_unchecked(X, xn)


def ippe_or_none(X: np.ndarray, xn: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """`ippe`, or None when a view of the batch is degenerate (np.linalg.LinAlgError)."""
    try:
        return ippe(X, xn)
    except np.linalg.LinAlgError:
        return None


def _ippe_unchecked(X: np.ndarray, xn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K, N = X.shape[:2]
    mx = X.mean(axis=1, keepdims=True)
    Xc = X - mx  # plane points about their mean
    sx = np.sqrt(2.0 / (Xc**2).sum(axis=2).mean(axis=1))  # Hartley scaling (K,)
    my = xn.mean(axis=1, keepdims=True)
    sy = np.sqrt(2.0 / ((xn - my) ** 2).sum(axis=2).mean(axis=1))
    a = Xc * sx[:, None, None]
    b = (xn - my) * sy[:, None, None]
    A = np.zeros((K, N, 2, 9))  # DLT rows, h = H row-major
    A[:, :, 0, 0:2] = a
    A[:, :, 0, 2] = 1.0
    A[:, :, 1, 3:5] = a
    A[:, :, 1, 5] = 1.0
    A[:, :, 0, 6:8] = -b[:, :, 0:1] * a
    A[:, :, 0, 8] = -b[:, :, 0]
    A[:, :, 1, 6:8] = -b[:, :, 1:2] * a
    A[:, :, 1, 8] = -b[:, :, 1]
    rows = A.reshape(K, 2 * N, 9)
    M = rows.transpose(0, 2, 1) @ rows
    h = np.linalg.solve(M[:, :8, :8], -M[:, :8, 8:])[:, :, 0]
    Hn = np.concatenate([h, np.ones((K, 1))], axis=1).reshape(K, 3, 3)
    T_inv = np.zeros((K, 3, 3))  # undo the image normalisation
    T_inv[:, 0, 0] = T_inv[:, 1, 1] = 1.0 / sy
    T_inv[:, :2, 2] = my[:, 0]
    T_inv[:, 2, 2] = 1.0
    H = (T_inv @ Hn) * np.stack([sx, sx, np.ones(K)], axis=1)[:, None, :]
    H = H / H[:, 2:3, 2:3]  # centred plane -> image
    v = H[:, :2, 2]
    J = H[:, :2, :2] - H[:, 2:3, :2] * H[:, :2, 2:3]  # d(image) / d(plane) at the origin
    ray = np.concatenate([v, np.ones((K, 1))], axis=1) / np.sqrt(1.0 + (v**2).sum(axis=1))[:, None]
    ax, ay, az = ray[:, 0], ray[:, 1], ray[:, 2]
    d = 1.0 / (1.0 + az)
    Rv = np.empty((K, 3, 3))  # R_v e_z = ray
    Rv[:, 0, 0], Rv[:, 0, 1], Rv[:, 0, 2] = 1.0 - ax * ax * d, -ax * ay * d, ax
    Rv[:, 1, 0], Rv[:, 1, 1], Rv[:, 1, 2] = -ax * ay * d, 1.0 - ay * ay * d, ay
    Rv[:, 2, 0], Rv[:, 2, 1], Rv[:, 2, 2] = -ax, -ay, 1.0 - (ax * ax + ay * ay) * d
    B = Rv[:, :2, :2] - v[:, :, None] * Rv[:, 2:3, :2]
    Am = np.linalg.solve(B, J)
    ata = Am.transpose(0, 2, 1) @ Am
    tr = ata[:, 0, 0] + ata[:, 1, 1]
    det = ata[:, 0, 0] * ata[:, 1, 1] - ata[:, 0, 1] ** 2
    gamma = np.sqrt(0.5 * (tr + np.sqrt(np.maximum(tr * tr - 4.0 * det, 0.0))))
    Rt = Am / gamma[:, None, None]
    b0 = np.sqrt(np.maximum(1.0 - Rt[:, 0, 0] ** 2 - Rt[:, 1, 0] ** 2, 0.0))
    b1 = np.sqrt(np.maximum(1.0 - Rt[:, 0, 1] ** 2 - Rt[:, 1, 1] ** 2, 0.0))
    b1 = np.where(Rt[:, 0, 0] * Rt[:, 0, 1] + Rt[:, 1, 0] * Rt[:, 1, 1] > 0.0, -b1, b1)
    # R_v^T R = [c1, c2, c1 x c2], c1 = (Rt00, Rt10, +-b0), c2 = (Rt01, Rt11, +-b1)
    M = np.empty((K, 2, 3, 3))
    M[:, :, :2, :2] = Rt[:, None]
    M[:, 0, 2, 0], M[:, 1, 2, 0] = b0, -b0
    M[:, 0, 2, 1], M[:, 1, 2, 1] = b1, -b1
    e0 = Rt[:, 1, 0] * b1 - Rt[:, 1, 1] * b0
    e1 = Rt[:, 0, 1] * b0 - Rt[:, 0, 0] * b1
    M[:, 0, 0, 2], M[:, 1, 0, 2] = e0, -e0
    M[:, 0, 1, 2], M[:, 1, 1, 2] = e1, -e1
    M[:, :, 2, 2] = (Rt[:, 0, 0] * Rt[:, 1, 1] - Rt[:, 0, 1] * Rt[:, 1, 0])[:, None]
    R = Rv[:, None] @ M
    # t: least squares of [1, 0, -u; 0, 1, -v] t = [u r_z - r_x, v r_z - r_y], r = R [x, y, 0]
    r = Xc[:, None] @ R[:, :, :, :2].transpose(0, 1, 3, 2)  # (K, 2, N, 3)
    u, w = xn[:, None, :, 0], xn[:, None, :, 1]
    ATA = np.zeros((K, 1, 3, 3))
    ATA[:, 0, 0, 0] = ATA[:, 0, 1, 1] = N
    ATA[:, 0, 0, 2] = ATA[:, 0, 2, 0] = -xn[:, :, 0].sum(axis=1)
    ATA[:, 0, 1, 2] = ATA[:, 0, 2, 1] = -xn[:, :, 1].sum(axis=1)
    ATA[:, 0, 2, 2] = (xn**2).sum(axis=(1, 2))
    bx, by = u * r[..., 2] - r[..., 0], w * r[..., 2] - r[..., 1]
    ATb = np.stack([bx.sum(-1), by.sum(-1), -(u * bx + w * by).sum(-1)], axis=-1)
    t = np.linalg.solve(np.broadcast_to(ATA, (K, 2, 3, 3)), ATb[..., None])[..., 0]
    return R, t - (R[..., :2] @ mx[:, :, :, None])[..., 0]  # p_cam = R ([x, y] - mx) + t
