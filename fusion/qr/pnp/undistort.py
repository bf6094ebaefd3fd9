"""Distorted pixels -> ideal normalised coordinates, fast: OpenCV's iterative undistortPoints
(cv2.fisheye's for an equidistant lens), verified once per camera against
CameraModel.undistort_normalized (and checked per call where it was not verified), with
CameraModel's Newton inversion as the fallback."""

from __future__ import annotations

import cv2
import numpy as np

from fusion.camera import CameraModel
from fusion.qr.reprojection import Projector

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-14)
"""Stopping rule of OpenCV's iterative undistortion (30 iterations, or a step below 1e-14)."""
ROUND_TRIP_TOL_PX = 1e-8
"""An undistorted point is trusted when distorting it back lands within this of the pixel."""
IMAGE_MARGIN = 0.1
"""Fraction of the image size beyond its edges where a verified OpenCV undistortion is trusted."""

_VERIFIED: dict[tuple, bool] = {}  # `opencv_undistorts`, per camera parameters


def cv_points(a: np.ndarray) -> np.ndarray:
    """(..., d) array -> contiguous float64 (N, 1, d), the point layout OpenCV expects."""
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 1, a.shape[-1]))


def opencv_undistorts(camera: CameraModel) -> bool:
    """Whether OpenCV's iterative undistortPoints reproduces CameraModel.undistort_normalized
    (to ROUND_TRIP_TOL_PX on distorting back) over a grid covering the image and an
    IMAGE_MARGIN margin; cached per camera parameters."""
    key = camera.projection_key
    ok = _VERIFIED.get(key)
    if ok is None:
        lo, hi = -IMAGE_MARGIN, 1.0 + IMAGE_MARGIN
        u, v = np.meshgrid(np.linspace(lo, hi, 25) * camera.width, np.linspace(lo, hi, 19) * camera.height)
        ok = undistort_checked(camera, np.column_stack([u.ravel(), v.ravel()])) is not None
        _VERIFIED[key] = ok
    return ok


def undistort_checked(camera: CameraModel, uv: np.ndarray) -> np.ndarray | None:
    """OpenCV's undistortPoints of (N, 2) pixels, or None where distorting back misses by more
    than ROUND_TRIP_TOL_PX."""
    xn = camera.cv_undistort_points(cv_points(uv), None, UNDISTORT_CRITERIA).reshape(-1, 2)
    back, _ = Projector(camera).project(np.column_stack([xn, np.ones(len(xn))]), jacobian=False)
    return xn if np.all(np.abs(back - uv) < ROUND_TRIP_TOL_PX) else None


def undistort(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """(N, 2) distorted pixels -> (N, 2) ideal normalised coordinates, = CameraModel's
    undistort_normalized: OpenCV's iterative undistortPoints (about 30x faster), trusted inside
    the image (+ IMAGE_MARGIN) when `opencv_undistorts` verified it for this camera, else checked
    by distorting back; where that fails (strong distortion), CameraModel's Newton inversion."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if len(uv) == 0 or not np.all(np.isfinite(uv)):
        return camera.undistort_normalized(uv)
    size = np.array([camera.width, camera.height])
    if (
        opencv_undistorts(camera)
        and np.all(uv >= -IMAGE_MARGIN * size)
        and np.all(uv <= (1.0 + IMAGE_MARGIN) * size)
    ):
        return camera.cv_undistort_points(cv_points(uv), None, UNDISTORT_CRITERIA).reshape(-1, 2)
    xn = undistort_checked(camera, uv)
    return camera.undistort_normalized(uv) if xn is None else xn
