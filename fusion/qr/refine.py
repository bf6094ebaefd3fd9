"""Sub-pixel QR corners from straight-line fits to the finder patterns' outer edges.

A decoder's corners are whole pixels and 1-2 px off.  The symbol's outer boundary is reliable
only where a finder pattern lies on it (elsewhere the border modules are data):

    top line    v = 0   TL finder and TR finder top edges     (u in [0, 7] and [N-7, N])
    left line   u = 0   TL finder and BL finder left edges    (v in [0, 7] and [N-7, N])
    right line  u = N   TR finder right edge                  (v in [0, 7])
    bottom line v = N   BL finder bottom edge                 (u in [0, 7])

(u, v) are module coordinates of the symbol (u right, v down, origin at the outer top-left
corner, N modules per side).  Edge points are the 50 % crossings of intensity profiles taken
across each edge (light quiet zone -> dark finder ring), interpolated linearly between samples;
each line is a total-least-squares fit with one round of outlier rejection; the corners are the
intersections TL = top x left, TR = top x right, BR = right x bottom, BL = left x bottom (the
bottom-right corner has no finder: it is where the TR finder's right edge and the BL finder's
bottom edge, extended, meet).

Lens distortion bends the edges.  With a `CameraModel` the whole construction runs in
undistorted pixel coordinates: the raw corners are undistorted, the profiles are laid out in
undistorted space and each sample point is distorted to read the image, the lines are fitted and
intersected in undistorted space, and the corners are distorted back (camera.project of the
normalised ray).  Without a camera the image is taken as distortion-free.

Pixel convention: OpenCV's (pixel centres at integer coordinates).
"""
from __future__ import annotations

import cv2
import numpy as np

from fusion.camera import CameraModel

FINDER_MODULES = 7
_SPAN_MARGIN = 0.6          # modules kept clear of a finder's ends (neighbouring edge, corner blur)
_MIN_CONTRAST = 20.0        # grey levels between quiet zone and finder ring for a usable profile
_STEP_PX = 0.25             # profile sample spacing along the normal (final pass)
_COARSE_STEP_PX = 0.5       # ... in the first pass, whose window is wider
_MAX_SAMPLES_PER_SPAN = 16  # profiles per finder edge


def modules_for_version(version: int) -> int:
    """Modules per side of a QR symbol of `version` (1..40): 17 + 4 version."""
    return 17 + 4 * int(version)


def homography_from_corners(corners_px: np.ndarray, modules: float) -> np.ndarray:
    """3x3 H mapping module coordinates (u, v, 1) to pixels, from the 4 corners TL, TR, BR, BL."""
    n = float(modules)
    src = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]], dtype=np.float64)
    return homography_4pt(src, corners_px)


def homography_4pt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """3x3 H (H[2, 2] = 1) with dst ~ H src for 4 point pairs (4, 2), in float64
    (OpenCV 5's getPerspectiveTransform takes float32 only)."""
    src = np.asarray(src, dtype=np.float64).reshape(4, 2)
    dst = np.asarray(dst, dtype=np.float64).reshape(4, 2)
    A = np.zeros((8, 8))
    b = dst.reshape(8)
    for i, ((x, y), (u, v)) in enumerate(zip(src, dst)):
        A[2 * i] = [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y]
        A[2 * i + 1] = [0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y]
    h = np.linalg.solve(A, b)
    return np.append(h, 1.0).reshape(3, 3)


def _apply_h(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = uv @ H[:, :2].T + H[:, 2]
    return p[..., :2] / p[..., 2:3]


def _sample(image: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear image values at (..., 2) pixel positions and a mask of positions inside the image."""
    h, w = image.shape
    x = xy[..., 0].astype(np.float32)
    y = xy[..., 1].astype(np.float32)
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    vals = cv2.remap(image, x.reshape(x.shape[0], -1), y.reshape(y.shape[0], -1),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return vals.reshape(x.shape).astype(np.float32), inside


class _Distortion:
    """Undistorted pixels <-> distorted pixels for one camera (identity without a camera)."""

    def __init__(self, camera: CameraModel | None):
        self.camera = camera if camera is not None and np.any(camera.distortion) else None

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        return uv if self.camera is None else self.camera.undistort_pixels(uv)

    def distort(self, uv: np.ndarray) -> np.ndarray:
        if self.camera is None:
            return uv
        c = self.camera
        xy = np.stack([(uv[..., 0] - c.cu) / c.fu, (uv[..., 1] - c.cv) / c.fv], axis=-1)
        xyd = c.distort_normalized(xy)
        return np.stack([c.fu * xyd[..., 0] + c.cu, c.fv * xyd[..., 1] + c.cv], axis=-1)


# The six finder edges on the symbol boundary: (line index, start (u, v), end (u, v), outward (u, v))
# with line index 0 top, 1 right, 2 bottom, 3 left; coordinates in units of (modules, N).
def _spans(n: float) -> list[tuple[int, tuple, tuple, tuple]]:
    m0, m1 = _SPAN_MARGIN, FINDER_MODULES - _SPAN_MARGIN
    return [(0, (m0, 0.0), (m1, 0.0), (0.0, -1.0)), (0, (n - m1, 0.0), (n - m0, 0.0), (0.0, -1.0)),
            (1, (n, m0), (n, m1), (1.0, 0.0)),
            (2, (m0, n), (m1, n), (0.0, 1.0)),
            (3, (0.0, m0), (0.0, m1), (-1.0, 0.0)), (3, (0.0, n - m1), (0.0, n - m0), (-1.0, 0.0))]


def _edge_points(image, dist: _Distortion, H: np.ndarray, n: float, half_width_px: float,
                 step_px: float = _STEP_PX, max_samples: int = _MAX_SAMPLES_PER_SPAN
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel points on the symbol's finder edges (undistorted px) and their line index
    (0 top, 1 right, 2 bottom, 3 left): ((M, 2), (M,)).  All profiles are read in one remap."""
    spans = _spans(n)
    a = np.array([sp[1] for sp in spans])
    b = np.array([sp[2] for sp in spans])
    out = np.array([sp[3] for sp in spans])
    pa, pb, po = _apply_h(H, a), _apply_h(H, b), _apply_h(H, 0.5 * (a + b) + out)
    d = pb - pa
    length = np.linalg.norm(d, axis=1)
    if not np.all(np.isfinite(length)) or np.any(length < 1.0):
        return np.zeros((0, 2)), np.zeros(0, dtype=int)
    d /= length[:, None]
    normal = np.stack([d[:, 1], -d[:, 0]], axis=1)
    flip = np.einsum("ij,ij->i", normal, po - 0.5 * (pa + pb)) < 0
    normal[flip] *= -1.0
    n_samples = np.clip((length / 2.0).astype(int), 4, max_samples)
    span_of = np.repeat(np.arange(len(spans)), n_samples)
    t = np.concatenate([np.linspace(0.0, 1.0, k) for k in n_samples])
    uv = a[span_of] + t[:, None] * (b - a)[span_of]
    base = _apply_h(H, uv)                                                    # (S, 2)
    nrm = normal[span_of]                                                     # (S, 2)
    offsets = np.arange(half_width_px, -half_width_px - 1e-9, -step_px)       # outside -> inside
    pts = base[:, None, :] + offsets[None, :, None] * nrm[:, None, :]         # (S, K, 2)
    vals, inside = _sample(image, dist.distort(pts))
    light = vals[:, :3].mean(axis=1)
    dark = vals.min(axis=1)
    thr = 0.5 * (light + dark)
    below = vals < thr[:, None]
    first = np.argmax(below, axis=1)                                          # first dark sample
    ok = inside.all(axis=1) & ((light - dark) > _MIN_CONTRAST) & (first > 0)
    idx = np.nonzero(ok)[0]
    k = first[idx]
    v0 = vals[idx, k - 1]
    v1 = vals[idx, k]
    frac = (v0 - thr[idx]) / np.maximum(v0 - v1, 1e-6)
    s = offsets[k - 1] - frac * step_px
    # a crossing at the very end of the window belongs to a neighbouring feature
    keep = np.abs(s) < half_width_px - step_px
    idx, s = idx[keep], s[keep]
    line_of = np.array([sp[0] for sp in spans])[span_of[idx]]
    return base[idx] + s[:, None] * nrm[idx], line_of


def _fit_line(points: np.ndarray, min_points: int = 4) -> np.ndarray | None:
    """Total-least-squares line (a, b, c), a x + b y + c = 0 with (a, b) unit, or None.

    One round of outlier rejection (residual > max(3 * 1.4826 MAD, 0.15 px))."""
    if len(points) < min_points:
        return None
    line = None
    for _ in range(2):
        c = points.mean(axis=0)
        q = points - c
        sxx, syy, sxy = q[:, 0] @ q[:, 0], q[:, 1] @ q[:, 1], q[:, 0] @ q[:, 1]
        # normal = eigenvector of the 2x2 scatter matrix with the smaller eigenvalue
        theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)          # direction of the line
        normal = np.array([-np.sin(theta), np.cos(theta)])
        line = np.array([normal[0], normal[1], -normal @ c])
        r = np.abs(q @ normal)
        keep = r <= max(3.0 * 1.4826 * np.median(r), 0.15)
        if keep.all() or keep.sum() < min_points:
            break
        points = points[keep]
    return line


def _intersect(l1: np.ndarray, l2: np.ndarray) -> np.ndarray | None:
    x = l1[1] * l2[2] - l1[2] * l2[1]
    y = l1[2] * l2[0] - l1[0] * l2[2]
    w = l1[0] * l2[1] - l1[1] * l2[0]
    if abs(w) < 1e-12:
        return None
    return np.array([x / w, y / w])


def refine_corners_or_none(image: np.ndarray, corners_raw_px: np.ndarray, modules: int | None = None,
                           camera: CameraModel | None = None, iterations: int = 2) -> np.ndarray | None:
    """Refined (4, 2) corners (TL, TR, BR, BL, distorted px, OpenCV convention) or None if the
    finder edges cannot be measured (too little contrast, symbol at the image border, ...)."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError("refine_corners expects a (H, W) uint8 image")
    corners = np.asarray(corners_raw_px, dtype=np.float64).reshape(4, 2)
    if not np.all(np.isfinite(corners)):
        return None
    dist = _Distortion(camera)
    if modules is None:
        modules = estimate_modules(image, corners, camera)
        if modules is None:
            return None
    n = float(modules)
    raw_u = dist.undistort(corners)
    corners_u = raw_u
    for it in range(iterations):
        H = homography_from_corners(corners_u, n)
        side_px = np.mean(np.linalg.norm(corners_u - np.roll(corners_u, 1, axis=0), axis=1))
        module_px = side_px / n
        # first pass: room for the decoder's 1-2 px error, but short of the finder ring's inner
        # edge one module in; later passes: well inside one module
        if it == 0:
            half = min(max(2.5, 0.9 * module_px), max(1.5, 1.4 * module_px))
        else:
            half = min(max(1.5, 0.6 * module_px), 0.9 * module_px + 0.5)
        step = _COARSE_STEP_PX if it == 0 and iterations > 1 else _STEP_PX
        pts, line_of = _edge_points(image, dist, H, n, half, step)
        lines = []
        for j in range(4):
            line = _fit_line(pts[line_of == j])
            if line is None:
                return None
            lines.append(line)
        top, right, bottom, left = lines
        new = [_intersect(top, left), _intersect(top, right), _intersect(right, bottom),
               _intersect(bottom, left)]
        if any(p is None for p in new):
            return None
        new = np.array(new)
        # a corner that moved by more than 1.5 modules (or 4 px) from the decoder's is a bad fit
        if np.max(np.linalg.norm(new - raw_u, axis=1)) > max(4.0, 1.5 * module_px):
            return None
        corners_u = new
    return dist.distort(corners_u)


def refine_corners(image: np.ndarray, corners_raw_px: np.ndarray, modules: int | None = None,
                   camera: CameraModel | None = None, iterations: int = 2) -> np.ndarray:
    """Sub-pixel (4, 2) corners of a QR symbol's outer edge, TL, TR, BR, BL in distorted pixels.

    `image`: (H, W) uint8 grey image; `corners_raw_px`: (4, 2) decoder corners in the same order;
    `modules`: modules per side (17 + 4 version), estimated from the finder patterns when None;
    `camera`: fit the lines in undistorted coordinates.  Returns a copy of the raw corners when
    the refinement fails (use `refine_corners_or_none` to tell)."""
    out = refine_corners_or_none(image, corners_raw_px, modules, camera, iterations)
    return np.array(corners_raw_px, dtype=np.float64).reshape(4, 2) if out is None else out


def estimate_modules(image: np.ndarray, corners_px: np.ndarray,
                     camera: CameraModel | None = None) -> int | None:
    """Modules per side (17 + 4 v) from the three finder patterns, or None.

    Along the diagonal from a finder's outer corner towards the symbol centre the modules (k, k),
    k = 0..7, read dark, light, dark, dark, dark, light, dark, light (separator): the end of the
    third dark run is 7 modules in.  Its fraction of the diagonal gives 7 / N."""
    dist = _Distortion(camera)
    corners_u = dist.undistort(np.asarray(corners_px, dtype=np.float64).reshape(4, 2))
    H = homography_from_corners(corners_u, 1.0)
    t = np.linspace(0.0, 0.5, 400)
    estimates = []
    for origin, direction in (((0, 0), (1, 1)), ((1, 0), (-1, 1)), ((0, 1), (1, -1))):
        uv = np.asarray(origin, float) + t[:, None] * np.asarray(direction, float)
        vals, inside = _sample(image, dist.distort(_apply_h(H, uv))[None])
        vals, inside = vals[0], inside[0]
        if not inside.all():
            continue
        thr = 0.5 * (float(vals.max()) + float(vals.min()))
        dark = vals < thr
        # runs of the binarised profile, starting at the first dark sample
        start = int(np.argmax(dark)) if dark.any() else -1
        if start < 0 or start > 40:
            continue
        changes = np.nonzero(np.diff(dark[start:].astype(np.int8)))[0] + start + 1
        if len(changes) < 5:
            continue
        end_t = t[changes[4]]        # dark, light, dark, light, dark -> 5th change ends the finder
        if end_t <= 0.0:
            continue
        estimates.append(FINDER_MODULES / end_t)
    if not estimates:
        return None
    n = float(np.median(estimates))
    version = int(round((n - 17.0) / 4.0))
    if not 1 <= version <= 40:
        return None
    return modules_for_version(version)
