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

Second stage (`finder_homography`, default on; `refine_frames` runs it for all codes of its frames in
one set of array operations): the line fit leaves the bottom-right corner, extrapolated from two
short edges, the least accurate, and 50 % crossings move outwards under motion blur wider than a
module (the finder's 1-module ring blurs grey with its neighbours).  Stage 2 locates the twelve
straight finder edges (six on the symbol boundary, six facing the separators) by fitting the
finder's known module sequence across each edge (dark 1 | light 1 | dark 3, quiet zone or
separator + unknown data outside), blurred by a box per code and symbol axis (the motion blur's
projection, fitted) and a second box (lens PSF and sampling; 1.5 px, or fitted from there with
`FIT_PSF`), in closed form (a box convolved with a box is a trapezoid; its integral is piecewise
quadratic): `_model_edge_points`.  A symmetric blur then moves no edge when its shape is in the
model's family: with the second box fixed at 1.5 px, a defocus disc of 1 px radius moves every
edge outwards by ~0.01 px (every code looks larger, in every frame: a bias PnP cannot see and
the smoother averaged into NEES 54); the fitted width leaves a third to a half of it
(BENCHMARKS.md).  Passes (`_MODEL_ITERATIONS`): from the decoder's corners, the
profiles' 50 % crossings (local, so free of the decoder's scale error); then the model fit
(3 Gauss-Newton iterations), then once more around the refined edges (1 iteration, widths warm).
After each pass one homography H (module coordinates -> pixels) is fitted to all edge points of a
code: each point p on the module line u = c (or v = c) gives the linear equation
g1.p - c g3.p = 0 (or g2.p - c g3.p = 0) in G = H^-1 (a DLT with Hartley normalisation, one round
of outlier rejection), then one weighted Gauss-Newton step on the geometric residuals.  The corners
are H applied to the module square; their (8, 8) covariance (`RefineResult.corner_cov_px2`)
propagates each edge point's noise (its profile's residual RMS over its information) through that
fit, Jc (J^T W J)^-1 Jc^T, and the lens distortion, calibrated on rendered codes (`CornerCovarianceModel`).

Third (versions >= 2): the alignment patterns' centres join the homography fit, and where they do
not fit one homography (a curled print, an imperfect lens model), each corner comes from its own
distance-weighted fit (`_add_alignment`).  Then the self-check: every stage-2 result carries a
`RefineQuality` (edge contrast over noise, misfit of the edge points, share of edges used,
distance to the decoder's corners); one that fails `RefineChecks` keeps the decoder's corners
with FALLBACK_SIGMA_PX (stage 0), counted in `RefineStats`.  Profiles are used by contrast
relative to the code's own (no fixed grey-level cutoff) and clipped samples stay out of the fit.

Lens distortion bends the edges.  With a `CameraModel` the whole construction runs in
undistorted pixel coordinates: the raw corners are undistorted, the profiles are laid out in
undistorted space and each sample point is distorted to read the image, the lines are fitted and
intersected in undistorted space, and the corners are distorted back (camera.project of the
normalised ray).  Without a camera the image is taken as distortion-free.

Pixel convention: OpenCV's (pixel centres at integer coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from fusion.camera import CameraModel
from fusion.types import CameraRole

FINDER_MODULES = 7
_SPAN_MARGIN = 0.6  # modules kept clear of a finder's ends (neighbouring edge, corner blur)
# A profile is usable when its edge contrast is a fair share of the code's typical contrast
# (glare, shadow or occlusion over part of a code lowers it there) and above the quantisation
# floor of 8-bit images: adapts to exposure and print contrast (no fixed grey-level cutoff).
_MIN_CONTRAST_FRACTION = 0.35  # of the median contrast of the code's profiles
_CONTRAST_FLOOR_DN = 3.0  # a few quantisation steps of an 8-bit image
_MIN_EDGE_SNR = 4.0  # stage 2: edge contrast over the profile's residual RMS
# Clipped (saturated) samples carry no edge position: a clipped light level pulls the 50 %
# crossing and the model's level fit.  Samples within _CLIP_MARGIN_DN of the image's top value
# (or whose bilinear footprint touches such a pixel) are left out of the model fit, unless too
# few samples would remain (a sharp, noise-free synthetic edge: clipping moves no crossing there).
_CLIP_MARGIN_DN = 1
_MIN_UNCLIPPED_SAMPLES = 10
_PROFILES_PER_SPAN = 12  # intensity profiles across each finder edge
_COARSE_SAMPLES = 25  # samples per profile in the first pass (wide window, coarse step)
_FINE_STEP_PX = 0.25  # sample spacing of the final pass
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)


def modules_for_version(version: int) -> int:
    """Modules per side of a QR symbol of `version` (1..40): 17 + 4 version."""
    return 17 + 4 * int(version)


def homography_from_corners(corners_px: np.ndarray, modules: float) -> np.ndarray:
    """3x3 H mapping module coordinates (u, v, 1) to pixels, from the 4 corners TL, TR, BR, BL."""
    n = float(modules)
    src = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]], dtype=np.float32)
    # float32 (OpenCV 5 accepts nothing else): 1e-4 px, ample for laying out profiles
    return cv2.getPerspectiveTransform(src, np.asarray(corners_px, dtype=np.float32))


def _apply_h(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = uv @ H[:, :2].T + H[:, 2]
    return p[..., :2] / p[..., 2:3]


def _sample(image: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear image values at (..., 2) pixel positions and a mask of positions inside the image."""
    h, w = image.shape
    x = xy[..., 0].astype(np.float32)
    y = xy[..., 1].astype(np.float32)
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    vals = cv2.remap(
        image,
        x.reshape(x.shape[0], -1),
        y.reshape(y.shape[0], -1),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return vals.reshape(x.shape).astype(np.float32), inside


class _Distortion:
    """Undistorted pixels <-> distorted pixels for one camera (identity without a camera)."""

    def __init__(self, camera: CameraModel | None):
        self.camera = camera if camera is not None and camera.distorted else None

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) distorted -> undistorted pixels: OpenCV's iterative inverse run to 1e-14, the
        same as CameraModel.undistort_pixels (within 1e-12 px) at a fifteenth of its cost."""
        if self.camera is None:
            return uv
        c = self.camera
        uv = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        return c.cv_undistort_points(uv, c.K, _UNDISTORT_CRITERIA).reshape(-1, 2)

    def distort_xy(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted -> distorted pixels, x and y as separate arrays (keeps their dtype)."""
        if self.camera is None:
            return x, y
        c = self.camera
        if c.equidistant:  # not a hot path for any camera we simulate: the model's own, in float64
            uv = self.distort(np.stack([x, y], axis=-1).astype(np.float64))
            return uv[..., 0].astype(x.dtype), uv[..., 1].astype(y.dtype)
        k1, k2, p1, p2 = (x.dtype.type(v) for v in c.distortion)
        k3 = x.dtype.type(c.k3)
        xn = (x - x.dtype.type(c.cu)) * x.dtype.type(1.0 / c.fu)
        yn = (y - y.dtype.type(c.cv)) * y.dtype.type(1.0 / c.fv)
        xy2 = xn * yn
        x2, y2 = xn * xn, yn * yn
        r2 = x2 + y2
        radial = 1 + r2 * (k1 + k2 * r2 + k3 * r2 * r2)
        xd = xn * radial + (2 * p1) * xy2 + p2 * (r2 + 2 * x2)
        yd = yn * radial + p1 * (r2 + 2 * y2) + (2 * p2) * xy2
        return xd * x.dtype.type(c.fu) + x.dtype.type(c.cu), yd * y.dtype.type(c.fv) + y.dtype.type(c.cv)

    def jacobian(self, xy: np.ndarray, step: float) -> np.ndarray:
        """(..., 2, 2) d distorted / d undistorted at the undistorted pixels xy (..., 2), columns
        d / dx, d / dy, by central differences of `step` px (a camera is given)."""
        cols = []
        for j in range(2):
            d = np.zeros(2)
            d[j] = step
            cols.append((self.distort(xy + d) - self.distort(xy - d)) / (2 * step))
        return np.stack(cols, axis=-1)

    def gradient_to_distorted(self, xy: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradients (N, 2) of a function of the undistorted pixel at xy (N, 2) -> the same
        gradients w.r.t. the distorted pixel: grad D^-1, D = d distorted / d undistorted there
        (central differences of 0.5 px)."""
        if self.camera is None:
            return grad
        D = self.jacobian(xy, 0.5)
        return np.linalg.solve(D.transpose(0, 2, 1), grad[..., None])[..., 0]

    def distort(self, uv: np.ndarray) -> np.ndarray:
        if self.camera is None:
            return uv
        c = self.camera
        xy = np.stack([(uv[..., 0] - c.cu) / c.fu, (uv[..., 1] - c.cv) / c.fv], axis=-1)
        xyd = c.distort_normalized(xy)
        return np.stack([c.fu * xyd[..., 0] + c.cu, c.fv * xyd[..., 1] + c.cv], axis=-1)


@lru_cache(maxsize=64)
def _layout(n: float, per_span: int) -> tuple[np.ndarray, ...]:
    """Fixed sampling layout for a symbol of n modules: span ends a, b and outward directions
    (6, 2) in module coordinates, and per profile its span, line (0 top, 1 right, 2 bottom,
    3 left) and module position (P, 2).  The six finder edges on the symbol's boundary:
    top (TL and TR finders), right (TR), bottom (BL), left (TL and BL)."""
    m0, m1 = _SPAN_MARGIN, FINDER_MODULES - _SPAN_MARGIN
    spans = [
        (0, (m0, 0.0), (m1, 0.0), (0.0, -1.0)),
        (0, (n - m1, 0.0), (n - m0, 0.0), (0.0, -1.0)),
        (1, (n, m0), (n, m1), (1.0, 0.0)),
        (2, (m0, n), (m1, n), (0.0, 1.0)),
        (3, (0.0, m0), (0.0, m1), (-1.0, 0.0)),
        (3, (0.0, n - m1), (0.0, n - m0), (-1.0, 0.0)),
    ]
    a = np.array([sp[1] for sp in spans])
    b = np.array([sp[2] for sp in spans])
    out = np.array([sp[3] for sp in spans])
    span_of = np.repeat(np.arange(len(spans)), per_span)
    t = np.tile(np.linspace(0.0, 1.0, per_span), len(spans))
    uv = a[span_of] + t[:, None] * (b - a)[span_of]
    line_of = np.array([sp[0] for sp in spans])[span_of]
    return a, b, out, span_of, line_of, uv


def _edge_points(
    image,
    dist: _Distortion,
    H: np.ndarray,
    n: float,
    half_width_px: float,
    n_offsets: int,
    per_span: int = _PROFILES_PER_SPAN,
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel points on the symbol's finder edges (undistorted px) and their line index
    (0 top, 1 right, 2 bottom, 3 left): ((M, 2), (M,)).  Each profile runs from `half_width_px`
    outside the expected edge to as far inside in `n_offsets` samples; the edge point is its first
    crossing, from outside, of the level halfway between the quiet zone (outermost samples) and
    the darkest sample, interpolated linearly.  All profiles are read in one remap."""
    a, b, out, span_of, line_of, uv = _layout(float(n), per_span)
    ends = _apply_h(H, np.concatenate([a, b, 0.5 * (a + b) + out]))
    pa, pb, po = ends[:6], ends[6:12], ends[12:]
    d = pb - pa
    length = np.hypot(d[:, 0], d[:, 1])
    if not np.all(np.isfinite(length)) or np.any(length < 1.0):
        return np.zeros((0, 2)), np.zeros(0, dtype=int)
    normal = np.stack([d[:, 1], -d[:, 0]], axis=1) / length[:, None]
    flip = np.sum(normal * (po - 0.5 * (pa + pb)), axis=1) < 0
    normal[flip] *= -1.0
    base = _apply_h(H, uv)  # (P, 2)
    nrm = normal[span_of]  # (P, 2)
    offsets = np.linspace(half_width_px, -half_width_px, n_offsets)  # outside -> inside
    step = offsets[0] - offsets[1]
    pts = base[:, None, :] + offsets[None, :, None] * nrm[:, None, :]  # (P, K, 2)
    vals, inside = _sample(image, dist.distort(pts))
    light = vals[:, :3].mean(axis=1)
    dark = vals.min(axis=1)
    thr = 0.5 * (light + dark)
    below = vals < thr[:, None]
    first = np.argmax(below, axis=1)  # first dark sample
    contrast = light - dark
    ok = inside.all(axis=1) & _contrast_ok(contrast[None])[0] & (first > 0)
    # a crossing in the last sample step belongs to a neighbouring feature, not this edge
    ok &= first < n_offsets - 1
    idx = np.nonzero(ok)[0]
    k = first[idx]
    v0 = vals[idx, k - 1]
    frac = (v0 - thr[idx]) / np.maximum(v0 - vals[idx, k], 1e-6)
    s = offsets[k - 1] - frac * step
    return base[idx] + s[:, None] * nrm[idx], line_of[idx]


def _contrast_ok(contrast: np.ndarray) -> np.ndarray:
    """Usable profiles of codes (C, M) by contrast (module comment above _MIN_CONTRAST_FRACTION):
    at least that fraction of the code's median contrast and above the quantisation floor."""
    contrast = np.where(np.isfinite(contrast), contrast, 0.0)
    pos = contrast > _CONTRAST_FLOOR_DN
    med = _masked_median(contrast, pos)
    return pos & (contrast >= _MIN_CONTRAST_FRACTION * med[:, None])


def _fit_lines(
    points: np.ndarray, line_of: np.ndarray, n_lines: int = 4, min_points: int = 4
) -> np.ndarray | None:
    """Total-least-squares lines (n_lines, 3), rows (a, b, c) with a x + b y + c = 0 and (a, b)
    unit, for the points (M, 2) labelled by `line_of` (M,); None if a line has too few points.

    One round of outlier rejection: points farther than max(0.25 px, 3 x the median residual of
    all lines) are dropped and the lines refitted (all lines at once, no Python loop per line)."""
    keep = np.ones(len(points), dtype=bool)
    lines = None
    for round_ in range(2):
        lab, p = line_of[keep], points[keep]
        count = np.bincount(lab, minlength=n_lines)
        if np.any(count < min_points):
            return None
        mean = (
            np.stack([np.bincount(lab, p[:, 0], n_lines), np.bincount(lab, p[:, 1], n_lines)], axis=1)
            / count[:, None]
        )
        q = p - mean[lab]
        sxx = np.bincount(lab, q[:, 0] * q[:, 0], n_lines)
        syy = np.bincount(lab, q[:, 1] * q[:, 1], n_lines)
        sxy = np.bincount(lab, q[:, 0] * q[:, 1], n_lines)
        # the normal is the eigenvector of the 2x2 scatter matrix with the smaller eigenvalue
        theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of each line
        normal = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
        lines = np.column_stack([normal, -np.sum(normal * mean, axis=1)])
        if round_ == 1:
            break
        r = np.abs(np.sum(points * normal[line_of], axis=1) + lines[line_of, 2])
        keep = r <= max(0.25, 3.0 * float(np.median(r)))
        if keep.all():
            break
    return lines


def _intersect(l1: np.ndarray, l2: np.ndarray) -> np.ndarray | None:
    x = l1[1] * l2[2] - l1[2] * l2[1]
    y = l1[2] * l2[0] - l1[0] * l2[2]
    w = l1[0] * l2[1] - l1[1] * l2[0]
    if abs(w) < 1e-12:
        return None
    return np.array([x / w, y / w])


# ---------------------------------------------------------------------------- stage 2: model fit

# Across any outer edge of a finder pattern, going inwards, the modules read dark 1 | light 1 |
# dark 3 | light 1 | dark 1 (the pattern is symmetric).  Outside lies the quiet zone (light, >= 4
# modules) for the six edges on the symbol boundary, or the 1-module light separator and then data
# modules (unknown) for the six edges facing the symbol's interior.  Profiles are taken in the
# central band of each edge (2.25..4.75 modules along it), where this 1-D sequence holds for every
# point a blur of up to ~1 module along the edge can reach.
_MODEL_ALONG = np.linspace(2.75, 4.25, 6)  # profile positions along the finder (modules)
_MODEL_GROUP = 3  # consecutive profiles averaged into one before the fit
_MODEL_WINDOW = (-2.0, 3.0)  # sampled span (modules, + inwards)
_MODEL_INNER_LO = -1.0  # interior edges: data modules beyond this
_MODEL_UNIFORM = 11  # samples spread evenly over the window ...
_MODEL_DENSE_PX = np.arange(-1.75, 1.8, 0.5)  # ... and 8 within 2 px of the edge
_MODEL_STEPS = np.array([-1.0, 0.0, 1.0, 2.0])  # data | dark | light | dark transitions (modules)
# how each transition moves when the dark modules grow by d on every side (ink spread, clipped
# white, a threshold-like sensor response): rises into dark at 0 and 2 move out by d, the fall at
# 1 and the data's edge at -1 move in (z_j = x - step_j + sign_j d)
_DILATION_SIGN = np.array([-1.0, 1.0, -1.0, 1.0])
_MAX_DILATION = 0.3  # modules: the fitted growth of the dark modules is clipped to +- this
# The growth's corners are used only where it is significant (|d| >= GROWTH_MIN_Z sigma_d, sigma_d
# from the fit's normal matrix and residual variance): on real photographs of white paper (59 % of
# the edge samples at 254-255) an insignificant growth moved corners by noise, median 0.2527 ->
# 0.2575 px over 97 codes, 0.2506 px with the test (scripts/bench_refine_real.py, BENCHMARKS.md);
# clipped renders give |d| / sigma_d of 36-78
GROWTH_MIN_Z = 3.0
_MODEL_ITERATIONS = (0, 3, 1)  # Gauss-Newton iterations per pass (0: 50 % crossings only)
_MODEL_STEP_CLIP = (0.35, 0.1)  # largest edge step per iteration (modules): first / later passes
STAGE2_PASSES = len(_MODEL_ITERATIONS)
_POLISH_ITERATIONS = 2  # Gauss-Newton iterations of the whole-pixel polish (_polish); 0: none
_POLISH_MAX_MOVE_PX = 0.2  # a polish that moves a corner farther is not taken (_polish)
_POLISH_MAX_WIDTH_PX = 2.0  # codes whose fitted blur box is wider are not polished (_polish)
POLISHED_CAMERAS = frozenset({CameraRole.FRONT.value})
"""The cameras (CameraRole values) whose codes get the whole-pixel polish (_polish): the front
camera's load codes, not the floor camera's (see _polish)."""
_WIDTH_GRID_PX = np.array([2.0, 4.5, 8.0])  # start of the width search (first model pass)
_MODEL_MIN_WIDTH_PX = 0.5  # floor of the fitted motion-blur box width (px)
_MODEL_PSF_PX = 1.5  # second box (px), its start: lens / pixel PSF and the bilinear sampling
_PIXEL_PSF_PX = 0.5  # the same for whole-pixel samples (no interpolation's own blur)
_MIN_GOOD_PROFILES = 10  # of 24 (averaged) per code
# fit the second box's width too (True), or keep it at _MODEL_PSF_PX (False, the default): fitted,
# it halves the defocus disc's bias (defocus r 1 flight: smoother NEES 54 -> 26, EKF 14 -> 10) and
# brings the floor PnP NEES on rendered frames to ~6, but the load-centre NEES of
# tests/test_pnp.py's rendered frames rises from 4.0 to 5.2-5.6 (ideal 3, heavy-tailed; the
# shared widths' uncertainty, added to each edge sigma, does not explain it).  Opt-in until the
# cause is found (BENCHMARKS.md).
FIT_PSF = False
_PSF_PRIOR_PX = 1.0  # 1-sigma prior of the fitted second box's width about _MODEL_PSF_PX (0: none)
_GROUP_DAMPING = 1e-3  # relative Levenberg damping of the per-code (width, PSF, growth) step


@lru_cache(maxsize=64)
def _model_layout(n: float) -> tuple[np.ndarray, ...]:
    """Profiles of the 12 finder edges for a symbol of n modules (72 = 12 x 6, consecutive
    _MODEL_GROUP of them on one edge): per profile the module position on the edge (72, 2), the
    inward module direction (72, 2), which coordinate is constant on its edge (0: u, 1: v), the
    constant (modules), and whether the edge is on the symbol boundary."""
    f = float(FINDER_MODULES)
    # (axis, const, finder start along the edge, outward sign, boundary?)
    edges = [
        (1, 0.0, 0.0, -1, True),
        (0, 0.0, 0.0, -1, True),  # TL: top, left
        (0, f, 0.0, +1, False),
        (1, f, 0.0, +1, False),  # TL: right, bottom
        (1, 0.0, n - f, -1, True),
        (0, n, 0.0, +1, True),  # TR: top, right
        (0, n - f, 0.0, -1, False),
        (1, f, n - f, +1, False),  # TR: left, bottom
        (0, 0.0, n - f, -1, True),
        (1, n, 0.0, +1, True),  # BL: left, bottom
        (0, f, n - f, +1, False),
        (1, n - f, 0.0, -1, False),
    ]  # BL: right, top
    k = len(_MODEL_ALONG)
    uv, inward, axis, const, boundary = [], [], [], [], []
    for ax, c, start, sign, bnd in edges:
        along = start + _MODEL_ALONG
        uv.append(
            np.column_stack([np.full(k, c), along]) if ax == 0 else np.column_stack([along, np.full(k, c)])
        )
        d = np.zeros(2)
        d[ax] = -sign
        inward.append(np.tile(d, (k, 1)))
        axis += [ax] * k
        const += [c] * k
        boundary += [bnd] * k
    return (np.concatenate(uv), np.concatenate(inward), np.array(axis), np.array(const), np.array(boundary))


def _blurred_steps(
    x: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    derivatives: bool = True,
    dilation: np.ndarray | None = None,
    psf_derivative: bool = False,
):
    """Unit steps at _MODEL_STEPS (each moved by _DILATION_SIGN x `dilation` (P, 1) modules when
    given: dark modules grown by that much on every side, dF_j / d dilation = sign_j dF_j / dx)
    seen through a box of width a convolved with a box of width b
    (all in modules; x (P, K) inwards from the edge, a and b (P, 1)): the kernel's cumulative
    distribution F (4, P, K) (step j in F[j]), and dF/dx, dF/da (and dF/db with
    `psf_derivative`: a 4-tuple).  Closed form: with
    s1 = (a + b) / 2, s2 = |a - b| / 2 and z clipped to [-s1, s1] (F is 0 / 1 beyond),
    F = ((z + s1)^2 - max(z + s2, 0)^2 - max(z - s2, 0)^2) / (2 a b)  (a trapezoid's integral).
    In-place arithmetic: this is the inner loop of the model fit.  Steps first and the per-profile
    terms spread over (P, K): every operation then runs over whole contiguous planes (with the
    steps as a trailing axis of 4, numpy looped 4 elements at a time, ~4x slower)."""
    shape = x.shape
    z = np.empty((len(_MODEL_STEPS),) + shape, x.dtype)
    for j, step in enumerate(_MODEL_STEPS.astype(x.dtype)):
        np.subtract(x, step, out=z[j])
        if dilation is not None:
            z[j] += _DILATION_SIGN[j].astype(x.dtype) * dilation
    a2 = np.broadcast_to(a, shape)
    b2 = np.broadcast_to(b, shape)
    s1 = 0.5 * (a2 + b2)
    s2 = 0.5 * np.abs(a2 - b2)
    np.maximum(z, -s1, out=z)
    np.minimum(z, s1, out=z)
    m1 = z + s2
    np.maximum(m1, 0.0, out=m1)
    m2 = z - s2
    np.maximum(m2, 0.0, out=m2)
    p = z
    p += s1
    half_inv = 0.5 / (a2 * b2)
    F = p * p
    F -= m1 * m1
    F -= m2 * m2
    F *= half_inv
    if not derivatives:
        return F, None, None
    dF_dx = p - m1
    dF_dx -= m2
    dF_dx *= 2.0 * half_inv
    m1 -= m2
    m1 *= np.sign(a2 - b2)
    dF_db = None
    if psf_derivative:  # F is symmetric in (a, b): ds2/db = -ds2/da
        dF_db = p + m1
        dF_db *= half_inv
        dF_db -= F / b2
    dF_da = p
    dF_da -= m1
    dF_da *= half_inv
    dF_da -= F / a2
    if psf_derivative:
        return F, dF_dx, dF_da, dF_db
    return F, dF_dx, dF_da


def _dark(F: np.ndarray) -> np.ndarray:
    """D = F(0) - F(1) + F(2): the finder's dark modules, from _blurred_steps' (4, P, K)."""
    return F[1] - F[2] + F[3]


def _levels(D, Dd, y, m):
    """Per-profile least-squares levels (W, C, g) of y = W + C D + g Dd over the samples with
    mask m (all (P, K)): levels (P, 3), residuals (P, K), the basis as three (P, K) planes
    (m, D m, Dd m) and its inverse normal matrix as a `_Sym3` of (P,) entries.  Sums over K
    plane by plane (`_dots`): stacked (P, K, 3) matrix products loop 3 elements at a time."""
    A = (m, D * m, Dd * m)
    ym = y * m
    n = [_dots(A[i], A[j]).astype(np.float64) for i, j in _SYM3_INDEX]
    reg = np.diag(_LEVEL_REG)
    Ninv = _Sym3.inverse(n[0] + reg[0], n[1], n[2], n[3] + reg[1], n[4], n[5] + reg[2], m.dtype)
    lev = Ninv.matvec(np.stack([_dots(a, ym) for a in A], axis=1))
    r = A[0] * lev[:, 0:1]
    r += A[1] * lev[:, 1:2]
    r += A[2] * lev[:, 2:3]
    r -= ym
    return lev, r, A, Ninv


def _dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of two (P, K) arrays: (P,)."""
    return np.einsum("pk,pk->p", a, b)


_LEVEL_REG = np.diag([1e-9, 1e-9, 1e-6])  # the data level g: absent on boundary edges
_SYM3_INDEX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@dataclass
class _Sym3:
    """A stack of symmetric 3x3 matrices as their six (P,) upper-triangle entries (row by row):
    the per-profile arithmetic on them runs over (P,) arrays, not (P, 3, 3) stacks."""

    a00: np.ndarray
    a01: np.ndarray
    a02: np.ndarray
    a11: np.ndarray
    a12: np.ndarray
    a22: np.ndarray

    @classmethod
    def inverse(cls, a00, a01, a02, a11, a12, a22, dtype) -> _Sym3:
        """The inverses of the matrices with these entries by cofactors (np.linalg.inv is ~10x
        slower on small stacks); NaN where singular (determinant <= 0)."""
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        det = a00 * c00 + a01 * c01 + a02 * c02
        with np.errstate(all="ignore"):
            inv_det = np.where(det > 0, 1.0 / det, np.nan)
        return cls(*((c * inv_det).astype(dtype) for c in (c00, c01, c02, c11, c12, c22)))

    def matvec(self, v: np.ndarray) -> np.ndarray:
        """(P, 3) products of the matrices with the vectors v (P, 3)."""
        x, y, z = v[:, 0], v[:, 1], v[:, 2]
        return np.stack(
            [
                self.a00 * x + self.a01 * y + self.a02 * z,
                self.a01 * x + self.a11 * y + self.a12 * z,
                self.a02 * x + self.a12 * y + self.a22 * z,
            ],
            axis=1,
        )


def _inv(M: np.ndarray) -> np.ndarray:
    """Inverses of a stack of square matrices (..., k, k); NaN where one is singular."""
    try:
        return np.linalg.inv(M)
    except np.linalg.LinAlgError:
        out = np.full(M.shape, np.nan)
        for i in np.ndindex(M.shape[:-2]):
            try:
                out[i] = np.linalg.inv(M[i])
            except np.linalg.LinAlgError:
                pass
        return out


@dataclass
class _Profiles:
    """The stage-2 profiles of a batch of codes, each the average of _MODEL_GROUP sampled ones
    (24 per code, see _model_layout); per averaged profile the middle one's position."""

    code: np.ndarray  # (P,) index of the code
    uv0: np.ndarray  # (P, 2) module position on the edge
    inward: np.ndarray  # (P, 2) inward module direction
    axis: np.ndarray  # (P,) 0: edge on u = const, 1: on v = const
    const: np.ndarray  # (P,) the constant (modules)
    boundary: np.ndarray  # (P,) bool: edge on the symbol boundary (quiet zone outside)
    uv_sampled: np.ndarray  # (P * _MODEL_GROUP, 2) the sampled profiles' positions


def _profiles(ns: list[float]) -> _Profiles:
    parts = [_model_layout(float(n)) for n in ns]
    cat = [np.concatenate([p[i] for p in parts]) for i in range(5)]
    mid = slice(_MODEL_GROUP // 2, None, _MODEL_GROUP)
    code = np.repeat(np.arange(len(ns)), [len(p[0]) // _MODEL_GROUP for p in parts])
    uv0, inward, axis, const, boundary = (a[mid] for a in cat)
    return _Profiles(code, uv0, inward, axis, const, boundary, cat[0])


def _apply_hs(Hp: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Per-row homographies Hp (P, 3, 3) applied to uv (P, ..., 2)."""
    ex = (slice(None),) + (None,) * (uv.ndim - 2)
    w = Hp[:, 2, 0][ex] * uv[..., 0] + Hp[:, 2, 1][ex] * uv[..., 1] + Hp[:, 2, 2][ex]
    x = Hp[:, 0, 0][ex] * uv[..., 0] + Hp[:, 0, 1][ex] * uv[..., 1] + Hp[:, 0, 2][ex]
    y = Hp[:, 1, 0][ex] * uv[..., 0] + Hp[:, 1, 1][ex] * uv[..., 1] + Hp[:, 1, 2][ex]
    return np.stack([x / w, y / w], axis=-1)


@dataclass
class _ModelFit:
    """Stage-2 edge points of a batch: points (P, 2) undistorted px, `good` (P,) usable, the
    edge-position sigma (P,) px, modules per px across each edge g (P,), the fitted box widths
    (C, 2) px across u-edges and v-edges."""

    points: np.ndarray
    good: np.ndarray
    sigma_px: np.ndarray
    g: np.ndarray
    width_px: np.ndarray
    contrast: np.ndarray  # (P,) fitted edge contrast (grey levels)
    rms: np.ndarray  # (P,) the profile's residual RMS (grey levels; NaN in the crossings pass)
    dilation: np.ndarray | None = None  # (C, 2) growth of the dark modules (modules), per edge direction
    clipped: np.ndarray | None = None  # (C,) the code's profiles had clipped samples
    psf_px: np.ndarray | None = None  # (C, 2) the fitted second box (px), per edge direction
    dilation_sigma: np.ndarray | None = None  # (C, 2) the growth's 1-sigma (modules; NaN: not fitted)


def _sample_profiles(
    images: list[np.ndarray],
    image_rows: np.ndarray,
    dist: _Distortion,
    H: np.ndarray,
    uv: np.ndarray,
    step: np.ndarray,
    s: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image values along profiles: row i samples images[image_rows[i]] at the module
    coordinates uv[i] + s[i, k] step[i] mapped by H[i] (module -> undistorted px) and distorted.
    Returns (y (R, K) float32, inside (R, K), clipped (R, K): the sample's bilinear footprint
    touches a pixel within _CLIP_MARGIN_DN of the image's top value).  float32 and separate
    x / y arrays: this runs for every sample of every pass."""
    H = H.astype(np.float32)
    s = s.astype(np.float32)
    u = uv[:, 0:1].astype(np.float32) + s * step[:, 0:1].astype(np.float32)
    v = uv[:, 1:2].astype(np.float32) + s * step[:, 1:2].astype(np.float32)
    w = H[:, 2, 0:1] * u + H[:, 2, 1:2] * v + H[:, 2, 2:3]
    x = (H[:, 0, 0:1] * u + H[:, 0, 1:2] * v + H[:, 0, 2:3]) / w
    y = (H[:, 1, 0:1] * u + H[:, 1, 1:2] * v + H[:, 1, 2:3]) / w
    x, y = dist.distort_xy(x, y)
    vals = np.empty(x.shape, np.float32)
    inside = np.empty(x.shape, bool)
    clipped = np.zeros(x.shape, bool)
    top = np.iinfo(np.uint8).max - _CLIP_MARGIN_DN
    for i, rows in _rows_by_image(image_rows, len(images)):
        img = images[i]
        xi, yi = x[rows], y[rows]
        v = cv2.remap(img, xi, yi, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        vals[rows] = v
        inside[rows] = (xi >= 0) & (yi >= 0) & (xi <= img.shape[1] - 1) & (yi <= img.shape[0] - 1)
        if v.max() >= top - 2 * _CLIP_MARGIN_DN:  # (cheap pre-check on the samples)
            mask = np.where(img >= top, np.uint8(255), np.uint8(0))  # 255 where clipped
            clipped[rows] = cv2.remap(mask, xi, yi, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) > 0
    return vals, inside, clipped


def _sample_pixels(
    images: list[np.ndarray],
    image_rows: np.ndarray,
    dist: _Distortion,
    H: np.ndarray,
    uv: np.ndarray,
    grad: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel values along profiles without interpolation: row i reads, for each point uv[i, k]
    (module coordinates, mapped by H[i] (module -> undistorted px) and distorted), the pixel
    whose centre is nearest, in images[image_rows[i]].  Returns (y (R, K) float32, inside (R, K),
    clipped (R, K): the pixel is within _CLIP_MARGIN_DN of the image's top value, ds (R, K)
    float32: how far that centre lies from the point along the profile, in modules, from
    `grad` (R, 2), the gradient of the module offset along the profile in distorted pixels,
    pixel (R, K): the pixel's index in its image)."""
    H = H.astype(np.float32)
    u = uv[..., 0].astype(np.float32)
    v = uv[..., 1].astype(np.float32)
    w = H[:, 2, 0:1] * u + H[:, 2, 1:2] * v + H[:, 2, 2:3]
    x = (H[:, 0, 0:1] * u + H[:, 0, 1:2] * v + H[:, 0, 2:3]) / w
    y = (H[:, 1, 0:1] * u + H[:, 1, 1:2] * v + H[:, 1, 2:3]) / w
    x, y = dist.distort_xy(x, y)
    xr, yr = np.rint(x), np.rint(y)
    gr = grad.astype(np.float32)
    ds = gr[:, 0:1] * (xr - x) + gr[:, 1:2] * (yr - y)
    vals = np.empty(x.shape, np.float32)
    inside = np.empty(x.shape, bool)
    pixel = np.empty(x.shape, np.int64)
    top = np.iinfo(np.uint8).max - _CLIP_MARGIN_DN
    for i, rows in _rows_by_image(image_rows, len(images)):
        img = images[i]
        h, wd = img.shape
        xi, yi = xr[rows], yr[rows]
        inside[rows] = (xi >= 0) & (yi >= 0) & (xi <= wd - 1) & (yi <= h - 1)
        col = np.clip(xi, 0, wd - 1).astype(np.intp)
        row = np.clip(yi, 0, h - 1).astype(np.intp)
        vals[rows] = img[row, col]
        pixel[rows] = row * wd + col
    return vals, inside, vals >= top, ds, pixel


def _rows_by_image(image_rows: np.ndarray, n_images: int) -> list[tuple[int, slice | np.ndarray]]:
    """(image index, its rows) for the rows of a sampling array labelled by image (R,): slices
    when the labels are sorted (as refine_frames lays codes out, image by image: a slice is a
    view, where a boolean mask copies), masks otherwise."""
    if n_images == 1:
        return [(0, slice(None))]
    if len(image_rows) == 0 or np.all(image_rows[1:] >= image_rows[:-1]):
        images = np.arange(n_images)
        lo = np.searchsorted(image_rows, images, side="left")
        hi = np.searchsorted(image_rows, images, side="right")
        return [(int(i), slice(int(a), int(b))) for i, a, b in zip(images, lo, hi) if b > a]
    return [(int(i), image_rows == i) for i in np.unique(image_rows)]


def _model_edge_points(
    images: list[np.ndarray],
    image_of: np.ndarray,
    dist: _Distortion,
    Hs: np.ndarray,
    module_px: np.ndarray,
    pr: _Profiles,
    width0_px: np.ndarray | None,
    iterations: int,
    step_clip: float = _MODEL_STEP_CLIP[0],
    dilation0: np.ndarray | None = None,
    fit_dilation: bool = True,
    psf0_px: np.ndarray | None = None,
    fit_psf: bool = True,
    whole_pixels: bool = False,
) -> _ModelFit:
    """Fit the finder's known profile across each of the 12 finder edges of every code of a
    batch (module docstring), all codes' profiles in one array; code c is in images[image_of[c]].

    Per profile i, image samples y(s) at s modules inwards from the edge H predicts (one remap
    for all profiles of all codes) are modelled as  y = W + C D(s - e_i; w) + g Dd(s - e_i; w)
    with D the dark-module sequence blurred by a box of width w and a box of width b (PSF), Dd the
    data modules beyond the separator (edges facing the interior only).  W, C, g are solved
    linearly per profile and projected out (variable projection); the edge offsets e_i (modules)
    and per code and edge direction (u-edges, v-edges: a motion blur's projections on the two
    symbol axes) the box widths w and b in pixels (b from `psf0_px`, else _MODEL_PSF_PX; fixed
    unless `fit_psf`) by Gauss-Newton, the offsets eliminated by a Schur complement (a damped
    k x k system per code and direction: w and b are exchangeable, so their difference is
    unobservable where w ~ b and the damping leaves it unchanged).  A symmetric blur then moves no
    edge, whatever its width relative to the module, as far as its shape is a trapezoid's.
    Without `width0_px` (first pass) e starts at each profile's 50 % crossing and the widths at
    the best of _WIDTH_GRID_PX; otherwise at 0 and `width0_px`.  With the widths, one growth d of
    the dark modules per code and edge direction (_DILATION_SIGN; from `dilation0`, else 0), so
    e is the module grid's edge, not the dark ring's apparent edge: with clipped white the dark
    modules look thinner, and fitting one offset to the ring's three transitions moved the
    symbol's edges inwards by ~0.15 px at 1.6x over-exposure (a bias common to every frame)."""
    C = len(Hs)
    P = len(pr.code)
    Hp = Hs[pr.code]
    xy0 = _apply_hs(Hp, pr.uv0)
    w3 = Hp[:, 2, 0] * pr.uv0[:, 0] + Hp[:, 2, 1] * pr.uv0[:, 1] + Hp[:, 2, 2]
    J = (Hp[:, :2, :2] - xy0[:, :, None] * Hp[:, 2, None, :2]) / w3[:, None, None]
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    # rows of J^-1 are grad u = (J11, -J01) / det and grad v = (-J10, J00) / det (modules / px)
    g = np.where(pr.axis == 0, np.hypot(J[:, 1, 1], J[:, 0, 1]), np.hypot(J[:, 1, 0], J[:, 0, 0])) / np.abs(
        det
    )
    bad_geom = ~(np.isfinite(g) & (g > 0))
    g = np.where(bad_geom, 1.0, g)
    if whole_pixels:
        # Each sample is the pixel nearest its point, at that pixel centre's own offset (module
        # coordinates, to first order: the offset's gradient along `inward`).  Interpolating the
        # image instead (bilinear) reads a sharp edge through a reconstruction that depends on
        # where the edge falls between pixel centres, not a blur: edge errors of 0.02-0.045 px,
        # systematic per edge (a code at ~4 px per module, 1 px ramps, or area-sampled), that no
        # blur width in the model removes (BENCHMARKS.md, twenty-sixth session).  Per group,
        # each profile's _MODEL_UNIFORM samples over the window and its dense ones near the edge
        # (where the edge's position is read), side by side, sorted by offset.
        G = _MODEL_GROUP
        lo, hi = _MODEL_WINDOW
        dense = (_MODEL_DENSE_PX[None] / module_px[:, None])[pr.code]  # (P, D)
        uniform = np.broadcast_to(np.linspace(lo, hi, _MODEL_UNIFORM), (P, _MODEL_UNIFORM))
        blocks = [(j, b) for j in range(G) for b in (uniform, dense)]
        s = np.concatenate([b for _, b in blocks], axis=1)  # (P, K)
        K = s.shape[1]
        at = pr.uv_sampled.reshape(P, G, 2)
        at = np.concatenate([np.repeat(at[:, j : j + 1], b.shape[1], axis=1) for j, b in blocks], axis=1)
        grad_u = np.stack([J[:, 1, 1], -J[:, 0, 1]], axis=1) / det[:, None]
        grad_v = np.stack([-J[:, 1, 0], J[:, 0, 0]], axis=1) / det[:, None]
        grad_in = np.where((pr.axis == 0)[:, None], grad_u, grad_v) * np.sum(pr.inward, axis=1)[:, None]
        y, inside, clipped, ds, pixel = _sample_pixels(
            images,
            image_of[pr.code],
            dist,
            Hp,
            at + s[..., None] * pr.inward[:, None, :],
            dist.gradient_to_distorted(xy0, grad_in),
        )
        s = s + np.nan_to_num(ds)  # (NaN: bad_geom)
        # a pixel read twice in a group (dense samples 0.5 px apart, profiles less than a pixel
        # apart along the edge) is one sample, at one offset: its repeats are left out
        by_pixel = np.argsort(pixel, axis=1, kind="stable")
        repeat = np.zeros((P, K), bool)
        sorted_pixel = np.take_along_axis(pixel, by_pixel, axis=1)
        np.put_along_axis(repeat, by_pixel[:, 1:], sorted_pixel[:, 1:] == sorted_pixel[:, :-1], axis=1)
        # sorted by offset, the repeats last and cut where no row has more unique pixels (the
        # model's cost is per sample: about half of them are repeats)
        order = np.argsort(np.where(repeat, np.inf, s), axis=1)
        K = int(np.max(np.sum(~repeat, axis=1))) if P else 0
        order = order[:, :K]
        s, y, inside, clipped_any, repeat = (
            np.take_along_axis(a, order, axis=1) for a in (s, y, inside, clipped, repeat)
        )
        s = s.astype(np.float32)
        ok = inside.reshape(P, -1).all(axis=1) & ~bad_geom
        used = np.where(pr.boundary[:, None], True, s >= _MODEL_INNER_LO) & ok[:, None] & ~repeat
        # clipped samples out of the fit where enough remain (module comment at _CLIP_MARGIN_DN)
        unclipped = used & ~clipped_any
        # (as a share of the samples: a binary image's light pixels are all at the top value, and
        # its dark ones alone cannot place an edge; the interpolated profiles' 10 of 19)
        # and only where some light samples remain unclipped (the edges' partly covered pixels): a
        # profile's dark samples alone fix no contrast
        with np.errstate(invalid="ignore"):  # (a row without used samples: NaN, no light ones)
            mid = 0.5 * (
                np.max(np.where(used, y, -np.inf), axis=1) + np.min(np.where(used, y, np.inf), axis=1)
            )
        light = np.sum(unclipped & (y > mid[:, None]), axis=1)
        drop_clipped = (
            np.sum(unclipped, axis=1) >= (_MIN_UNCLIPPED_SAMPLES / 19.0) * np.sum(used, axis=1)
        ) & (light >= 3)
        m = np.where(drop_clipped[:, None], unclipped, used).astype(np.float32)
    else:
        # samples: 11 over the window, 8 dense within 2 px of the predicted edge (per code)
        lo, hi = _MODEL_WINDOW
        s_code = np.sort(
            np.concatenate(
                [
                    np.broadcast_to(np.linspace(lo, hi, _MODEL_UNIFORM), (C, _MODEL_UNIFORM)),
                    _MODEL_DENSE_PX[None] / module_px[:, None],
                ],
                axis=1,
            ),
            axis=1,
        )
        s = s_code[pr.code]  # (P, K)
        K = s.shape[1]
        # (the crossings pass too: one profile per group was measurably worse on a flight)
        y, inside, clipped = _sample_profiles(
            images,
            np.repeat(image_of[pr.code], _MODEL_GROUP),
            dist,
            np.repeat(Hp, _MODEL_GROUP, axis=0),
            pr.uv_sampled,
            np.repeat(pr.inward, _MODEL_GROUP, axis=0),
            np.repeat(s, _MODEL_GROUP, axis=0),
        )
        # the model fit runs in float32 (samples are 8-bit, edges wanted to ~1e-3 px)
        y = y.reshape(P, _MODEL_GROUP, K).mean(axis=1)
        clipped_any = np.any(clipped.reshape(P, _MODEL_GROUP, K), axis=1)
        s = s.astype(np.float32)
        ok = inside.reshape(P, -1).all(axis=1) & ~bad_geom
        used = np.where(pr.boundary[:, None], True, s >= _MODEL_INNER_LO) & ok[:, None]
        # clipped samples out of the fit where enough remain (module comment at _CLIP_MARGIN_DN)
        unclipped = used & ~clipped_any
        drop_clipped = np.sum(unclipped, axis=1) >= _MIN_UNCLIPPED_SAMPLES
        m = np.where(drop_clipped[:, None], unclipped, used).astype(np.float32)
    inner = (~pr.boundary).astype(np.float32)[:, None]
    lbl = 2 * pr.code + pr.axis  # width groups
    max_w = 4.0 * module_px + 2.0  # (C,)
    g32 = g.astype(np.float32)[:, None]
    psf_box = _PIXEL_PSF_PX if whole_pixels else _MODEL_PSF_PX
    per_profile = float(_MODEL_GROUP) if whole_pixels else 1.0
    psf = np.float32(psf_box) * g32
    if width0_px is None:
        # e: the first crossing, from outside, of the level halfway between outside and darkest
        out_lvl = np.where(pr.boundary, y[:, 0], y[np.arange(P), np.argmin(np.abs(s + 0.5), axis=1)])
        dark = np.min(np.where((s > -0.8) & (s < 1.6), y, np.inf), axis=1)
        thr = 0.5 * (out_lvl + dark)
        below = (y < thr[:, None]) & (s > np.where(pr.boundary, lo, -0.5)[:, None])
        k = np.maximum(np.argmax(below, axis=1), 1)
        y0, y1 = y[np.arange(P), k - 1], y[np.arange(P), k]
        frac = np.clip((y0 - thr) / np.maximum(y0 - y1, 1e-6), 0.0, 1.0)
        e = s[np.arange(P), k - 1] + frac * (s[np.arange(P), k] - s[np.arange(P), k - 1])
        e = np.where(below.any(axis=1), np.clip(e, -0.7, 0.7), 0.0).astype(np.float32)
        if iterations == 0:
            # a first look: the crossings alone (biased outwards by blur, but local, so free of
            # the decoder corners' scale errors that the model's later transitions would feel)
            contrast0 = (out_lvl - dark).astype(float)
            good = (
                ok
                & _contrast_ok(contrast0.reshape(C, -1)).reshape(-1)
                & below.any(axis=1)
                & (np.abs(e) < 0.7)
            )
            points = _apply_hs(Hp, pr.uv0 + e[:, None].astype(np.float64) * pr.inward)
            return _ModelFit(
                points, good, np.full(P, 0.3), g, np.full((C, 2), np.nan), contrast0, np.full(P, np.nan)
            )
        # widths: the best of a few, on every third profile
        sub = np.arange(P) % 3 == 0
        G = len(_WIDTH_GRID_PX)
        xs = np.tile((s - e[:, None])[sub], (G, 1))
        gs = np.tile(g32[sub], (G, 1))
        F = _blurred_steps(
            xs,
            np.repeat(_WIDTH_GRID_PX.astype(np.float32), sub.sum())[:, None] * gs,
            np.tile(psf[sub], (G, 1)),
            derivatives=False,
        )[0]
        _, r, _, _ = _levels(
            _dark(F),
            (1.0 - F[0]) * np.tile(inner[sub], (G, 1)),
            np.tile(y[sub], (G, 1)),
            np.tile(m[sub], (G, 1)),
        )
        cost = np.bincount(
            np.tile(lbl[sub], G) + 2 * C * np.repeat(np.arange(G), sub.sum()),
            np.sum(r * r, axis=1),
            2 * C * G,
        ).reshape(G, 2 * C)
        width_px = _WIDTH_GRID_PX[np.argmin(cost, axis=0)].astype(float)
        width_px = np.minimum(width_px, np.repeat(max_w, 2))
    else:
        e = np.zeros(P, np.float32)
        width_px = np.clip(
            np.asarray(width0_px, dtype=float).reshape(-1), _MODEL_MIN_WIDTH_PX, np.repeat(max_w, 2)
        )
    dil = np.zeros(2 * C) if dilation0 is None else np.nan_to_num(np.asarray(dilation0, float).reshape(-1))
    # the growth is a free parameter only for codes with clipped samples in their profiles:
    # elsewhere an extra parameter would only soak up misfit that the self-check must see
    clipped_code = np.bincount(pr.code, np.any(used & clipped_any, axis=1), C) > 0
    free_dil = np.repeat(clipped_code & bool(fit_dilation), 2)
    dil = np.where(free_dil, dil, 0.0)
    any_free = bool(free_dil.any())  # (else the growth's terms are skipped: every clean frame)
    dil_sigma = np.full(2 * C, np.nan)
    psf_px = (
        np.full(2 * C, psf_box)
        if psf0_px is None
        else np.nan_to_num(np.asarray(psf0_px, float).reshape(-1), nan=psf_box)
    )
    # the PSF's width is fitted on codes without clipped samples: where the growth d is free it
    # takes the clipped profiles' misfit, and a second shape parameter there was confounded with
    # it (b free on every code: clipping x2.2 smoother NEES 13 -> 30, and 4 real photographs
    # worse than the decoder by > 0.5 px instead of 1, two of them clipped; BENCHMARKS.md)
    free_psf = np.repeat(~clipped_code & bool(fit_psf), 2)
    psf_px = np.where(free_psf, psf_px, psf_box)
    free = np.stack([np.ones(2 * C, bool), free_psf, free_dil], axis=1)  # w, b, d
    for _ in range(iterations):
        wmod = width_px[lbl].astype(np.float32)[:, None] * g32
        bmod = psf_px[lbl].astype(np.float32)[:, None] * g32
        shift = dil[lbl].astype(np.float32)[:, None] if any_free else None
        F, F_x, F_a, F_b = _blurred_steps(s - e[:, None], wmod, bmod, dilation=shift, psf_derivative=True)
        # D: the dark modules, Dd = 1 - F(-1): the data beyond the separator (interior edges)
        D, Dd = _dark(F), (1.0 - F[0]) * inner
        lev, r, A, Ninv = _levels(D, Dd, y, m)
        Cl, gam = lev[:, 1:2], lev[:, 2:3] * inner
        Je = -(Cl * _dark(F_x) - gam * F_x[0]) * m  # d model / d e
        # d model / d (width_px, psf_px, dilation): the group parameters
        Jg = [
            (Cl * _dark(F_a) - gam * F_a[0]) * (m * g32),
            (Cl * _dark(F_b) - gam * F_b[0]) * (m * g32),
        ]
        if any_free:
            Jg.append((Cl * (F_x[1] + F_x[2] + F_x[3]) + gam * F_x[0]) * m)
        # project out the levels (variable projection): J <- (I - A N^-1 A^T) J, so the
        # normal matrix of (e, group parameters) is J^T J - q^T N^-1 q with q = A^T J (P, 3)
        qe = np.stack([_dots(ai, Je) for ai in A], axis=1)
        Nqe = Ninv.matvec(qe)
        qg = [np.stack([_dots(ai, J) for ai in A], axis=1) for J in Jg]
        Nqg = [Ninv.matvec(q) for q in qg]
        a = _dots(Je, Je) - _dots(qe, Nqe) + 1e-9
        ge = _dots(Je, r)
        k = len(Jg)
        bg = [_dots(Je, Jg[i]) - _dots(qg[i], Nqe) for i in range(k)]
        # the per-profile offsets e eliminated (Schur complement): a k x k system per width group
        S = np.zeros((2 * C, 3, 3))
        rhs = np.zeros((2 * C, 3))
        for i in range(k):
            rhs[:, i] = np.bincount(lbl, _dots(Jg[i], r) - bg[i] * ge / a, 2 * C)
            for j in range(i, k):
                cij = _dots(Jg[i], Jg[j]) - _dots(qg[i], Nqg[j]) - bg[i] * bg[j] / a
                S[:, i, j] = S[:, j, i] = np.bincount(lbl, cij, 2 * C)
        fixed = ~free
        fixed[:, k:] = True
        if _PSF_PRIOR_PX > 0:
            # the PSF width's prior N(_MODEL_PSF_PX, _PSF_PRIOR_PX^2), in the cost's units: times
            # the group's residual variance per sample (cost = sum r^2 = 2 sigma_r^2 (-log L))
            var_r = np.bincount(lbl, np.sum(r * r, axis=1), 2 * C) / np.maximum(
                np.bincount(lbl, np.maximum(m.sum(axis=1) - 5.0, 1.0), 2 * C), 1.0
            )
            w_prior = var_r / _PSF_PRIOR_PX**2
            S[:, 1, 1] += w_prior
            rhs[:, 1] += w_prior * (psf_px - psf_box)
        S[fixed[:, :, None] | fixed[:, None, :]] = 0.0  # a fixed parameter's row and column
        rhs[fixed] = 0.0
        if any_free:
            # the growth's sigma: (S^-1)_dd times the group's residual variance per sample (the
            # profiles' offsets and the levels eliminated; fixed parameters out)
            S_cov = S + np.einsum("gi,ij->gij", fixed.astype(float), np.eye(3))
            var_g = np.bincount(lbl, np.sum(r * r, axis=1), 2 * C) / np.maximum(
                np.bincount(lbl, np.maximum(m.sum(axis=1) - 5.0, 1.0), 2 * C), 1.0
            )
            # (a group without usable samples has a zero row: its growth is unmeasured, NaN;
            # whole pixels: the group's profiles side by side count as one profile, as sigma_e)
            with np.errstate(invalid="ignore", divide="ignore"):
                invertible = np.all(np.isfinite(S_cov), axis=(1, 2))
                invertible[invertible] = np.linalg.cond(S_cov[invertible]) < 1e12
                S_inv = np.full_like(S_cov, np.nan)
                S_inv[invertible] = np.linalg.inv(S_cov[invertible])
                dil_sigma = np.sqrt(per_profile * var_g * S_inv[:, 2, 2])
        diag = np.einsum("gii->gi", S)
        # Levenberg damping: (w, b) are exchangeable in the model, so their difference is
        # unobservable where w ~ b; the damped step leaves it where it is
        diag += _GROUP_DAMPING * diag + 1e-6 + fixed
        step = -np.linalg.solve(S, rhs[..., None])[..., 0]
        step = np.nan_to_num(step)
        dw, db, dd = step[:, 0], step[:, 1], step[:, 2]
        de = -(ge + sum(bg[i] * step[lbl, i] for i in range(k))) / a
        e = e + np.clip(de, -step_clip, step_clip).astype(np.float32)
        width_px = np.clip(width_px + np.clip(dw, -1.5, 1.5), _MODEL_MIN_WIDTH_PX, np.repeat(max_w, 2))
        psf_px = np.clip(psf_px + np.clip(db, -1.5, 1.5), _MODEL_MIN_WIDTH_PX, np.repeat(max_w, 2))
        dil = np.clip(dil + np.clip(dd, -step_clip, step_clip), -_MAX_DILATION, _MAX_DILATION)
    dof = np.maximum(m.sum(axis=1) - 5.0, 1.0)
    rms = np.sqrt(np.sum(r * r, axis=1) / dof)
    contrast = -lev[:, 1]
    e = e.astype(np.float64)
    # Whole pixels: the _MODEL_GROUP profiles of a group cross the same edge a fraction of a
    # module apart, and what the model misses of the edge's shape (compression, sharpening, a
    # blur that is not two boxes) they miss alike, so their samples count as one profile's (on
    # real photographs, counted as independent, the edge points' chi2/dof about the homography
    # rose from a median of 2.4 to 5.5 and 3 in 10 codes fell back; BENCHMARKS.md)
    sigma_e = (rms / np.sqrt(np.maximum(a, 1e-12) / per_profile)).astype(np.float64) / g  # px
    good = (
        ok
        & _contrast_ok(np.where(ok, contrast, 0.0).reshape(C, -1)).reshape(-1)
        & (contrast > _MIN_EDGE_SNR * rms)
        & (np.abs(e) < 1.0)
        & np.isfinite(sigma_e)
        & (sigma_e > 0)
    )
    # per code: drop profiles whose residual is far above the code's median (occlusion, glare)
    med = _masked_median(rms.reshape(C, -1), good.reshape(C, -1))
    good &= rms <= 3.0 * med[pr.code] + 1.0
    points = _apply_hs(Hp, pr.uv0 + e[:, None] * pr.inward)
    return _ModelFit(
        points,
        good,
        np.where(good, sigma_e, 1.0),
        g,
        width_px.reshape(C, 2),
        contrast.astype(float),
        rms.astype(float),
        dil.reshape(C, 2),
        clipped_code,
        psf_px.reshape(C, 2),
        dil_sigma.reshape(C, 2),
    )


# The alignment pattern (versions >= 2; ISO/IEC 18004 6.3.6, Annex E: the one nearest the
# bottom-right corner is centred on module (N - 7, N - 7), i.e. at (N - 6.5, N - 6.5) in corner
# coordinates) puts a measurable point near the bottom-right corner, which the finders leave to
# extrapolation: on real photographs (lens distortion, paper that is not flat) that corner was
# the one refinement got wrong (scripts/bench_refine_real.py).  Its 5x5 module pattern (dark
# ring, light ring, dark centre) is point-symmetric, so the centre is found without bias under
# any symmetric blur by Gauss-Newton on the shift d that best matches a + b T(x) to the image
# sampled at H(c + x + d), x over the pattern's own 5x5 modules (data modules outside excluded).
_ALIGN_SAMPLES_PER_MODULE = 5
_ALIGN_HALF = 2.4  # modules: sampled square (the pattern's 2.5, less a margin for blur)
_ALIGN_ITERATIONS = 4
_ALIGN_MAX_SHIFT = 0.6  # modules from where the finders' homography predicts it
_ALIGN_MIN_CORR = 0.6  # correlation of the matched template
_LOCAL_FIT_SCALE = 0.5  # per-corner fits: weight exp(-d^2 / 2 L^2), d in symbol sides
_ALIGN_MISFIT_SIGMA = 3.0  # an alignment centre this many sigmas ...
_ALIGN_MISFIT_MODULES = 0.05  # ... and this many modules off the finder edges' homography: not flat


@lru_cache(maxsize=1)
def _align_template() -> tuple[np.ndarray, np.ndarray]:
    """Sample offsets (S, 2) in modules around the pattern centre and the pattern there (S,):
    1 dark, 0 light."""
    k = int(round(2 * _ALIGN_HALF * _ALIGN_SAMPLES_PER_MODULE))
    t = np.linspace(-_ALIGN_HALF, _ALIGN_HALF, k)
    x = np.stack(np.meshgrid(t, t), axis=-1).reshape(-1, 2)
    r = np.max(np.abs(x), axis=1)
    return x, ((r < 0.5) | (r >= 1.5)).astype(float)


def alignment_centres(n: int) -> np.ndarray:
    """(A, 2) module coordinates (u, v) of the centres of the alignment patterns of a symbol of
    n modules (ISO/IEC 18004 Annex E, Table E.1, by its construction rule: row / column centres
    6, then evenly spaced from n - 7 down, step rounded up to even; none where a finder is)."""
    version = (int(n) - 17) // 4
    if version < 2:
        return np.zeros((0, 2))
    count = version // 7 + 2
    step = 26 if version == 32 else (version * 4 + count * 2 + 1) // (count * 2 - 2) * 2
    pos = sorted([int(n) - 7 - i * step for i in range(count - 1)] + [6])
    last = pos[-1]
    centres = [
        (u, v)
        for v in pos
        for u in pos
        if not ((u == 6 and v == 6) or (u == 6 and v == last) or (u == last and v == 6))
    ]
    return np.array(centres, dtype=float) + 0.5


def _alignment_points(
    images: list[np.ndarray], image_of: np.ndarray, dist: _Distortion, Hs: np.ndarray, ns: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The alignment patterns of each code: centres (C, A) in modules (padded), their measured
    centres (C, A, 2) undistorted px, 1-sigma (C, A) px, and found (C, A) (the pattern exists,
    correlation >= _ALIGN_MIN_CORR, within _ALIGN_MAX_SHIFT modules of where Hs, module ->
    undistorted px, puts it)."""
    C = len(ns)
    lists = [alignment_centres(int(n)) for n in ns]
    A = max(len(c) for c in lists)
    centre = np.zeros((C, A, 2))
    found = np.zeros((C, A), bool)
    for i, c in enumerate(lists):
        centre[i, : len(c)] = c
        found[i, : len(c)] = True
    x, T = _align_template()
    S = len(x)
    d = np.zeros((C, A, 2))
    h = 0.25  # modules: central differences for the image gradient
    offs = np.array([[0.0, 0.0], [h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    Tc = T - T.mean()
    corr = np.zeros((C, A))
    sigma_mod = np.full((C, A), np.inf)
    for _ in range(_ALIGN_ITERATIONS):
        uv = (centre + d)[:, :, None, None, :] + offs[None, None, :, None, :] + x[None, None, None]
        y, inside = _sample_points(images, image_of, dist, Hs, uv.reshape(C, A * 5, S, 2))
        y = y.reshape(C, A, 5, S).astype(float)
        found &= inside.reshape(C, A, -1).all(axis=2)
        y0 = y[:, :, 0]
        grad = np.stack([y[:, :, 1] - y[:, :, 2], y[:, :, 3] - y[:, :, 4]], axis=-1) / (2 * h)
        # levels a + b T by least squares, then a Gauss-Newton step in d on r = a + b T - y(d)
        yc = y0 - y0.mean(axis=2, keepdims=True)
        b = (yc @ Tc) / (Tc @ Tc)
        r = b[..., None] * Tc - yc
        J = grad - grad.mean(axis=2, keepdims=True)  # d(-r)/dd, the offset a projected out
        JtJ = np.swapaxes(J, -1, -2) @ J + 1e-9 * np.eye(2)
        JtJ_inv = _inv(JtJ)
        step = (JtJ_inv @ (np.swapaxes(J, -1, -2) @ r[..., None]))[..., 0]
        d = d + np.clip(np.nan_to_num(step), -0.3, 0.3)
        with np.errstate(all="ignore"):
            corr = -b * np.linalg.norm(Tc) / np.linalg.norm(yc, axis=2)
        cov = JtJ_inv * (np.sum(r * r, axis=2) / max(S - 4, 1))[..., None, None]  # modules^2
        sigma_mod = np.sqrt(np.maximum(0.5 * (cov[..., 0, 0] + cov[..., 1, 1]), 0.0))
    found &= (
        (corr >= _ALIGN_MIN_CORR) & np.all(np.abs(d) <= _ALIGN_MAX_SHIFT, axis=2) & np.isfinite(sigma_mod)
    )
    pts = _apply_hs(Hs, centre + d)
    half = np.array([0.5, 0.0])
    scale = np.linalg.norm(_apply_hs(Hs, centre + d + half) - _apply_hs(Hs, centre + d - half), axis=2)
    return centre, pts, np.where(found, sigma_mod * scale, np.inf), found


def _sample_points(
    images: list[np.ndarray], image_of: np.ndarray, dist: _Distortion, Hs: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Image values at module coordinates uv (C, R, K, 2) of each code (H: module -> undistorted
    px), (C, R, K) float32, and whether inside the image."""
    C, R, K, _ = uv.shape
    xy = _apply_hs(Hs, uv)
    xd, yd = dist.distort_xy(xy[..., 0].astype(np.float32), xy[..., 1].astype(np.float32))
    out = np.empty((C, R, K), np.float32)
    ins = np.empty((C, R, K), bool)
    for i, rows in _rows_by_image(image_of, len(images)):
        img = images[i]
        xi, yi = xd[rows], yd[rows]
        xr, yr = xi.reshape(-1, K), yi.reshape(-1, K)
        out[rows] = cv2.remap(img, xr, yr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(
            -1, R, K
        )
        ins[rows] = (xi >= 0) & (yi >= 0) & (xi <= img.shape[1] - 1) & (yi <= img.shape[0] - 1)
    return out, ins


def _masked_median(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Row medians (lower middle) of x (C, M) over the entries where mask; 0 for empty rows."""
    srt = np.sort(np.where(mask, x, np.inf), axis=1)
    k = np.maximum(mask.sum(axis=1) - 1, 0) // 2
    out = srt[np.arange(len(x)), k]
    return np.where(np.isfinite(out), out, 0.0)


_SQUARE01 = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def _fit_homographies(fit: _ModelFit, pr: _Profiles, ns: np.ndarray, protected: np.ndarray | None = None):
    """Per code, H (module coordinates -> undistorted px) from the edge points on module lines
    u = const (axis 0) or v = const (axis 1), and the (8, 8) covariance of the corners
    H (0,0), H (n,0), H (n,n), H (0,n) that the edge-point sigmas imply.

    Each point p on u = c gives the linear equation g1.p - c g3.p = 0 in G = H^-1 (v: g2):
    a DLT per code in Hartley-normalised coordinates, one round of outlier rejection (points
    farther than max(0.25 px, 3 x the median) dropped), then one weighted Gauss-Newton step on
    the geometric residuals (module coordinate of G p minus c, weights 1 / (sigma_i g_i)^2).
    The corner covariance is Jc (J^T W J)^-1 Jc^T with J = d residual / d h and Jc = d corners / d h
    (h: the 8 entries of the normalised H, H33 = 1).  All codes at once: arrays (C, 60, ...).
    Returns (H (C, 3, 3), corners (C, 4, 2), cov (C, 8, 8), ok (C,), (chi2 per degree of
    freedom of the weighted geometric residuals, their RMS in px, edge points used) each (C,));
    rows with ok False are junk.  `protected` (C, M): points exempt from the outlier round."""
    C = len(ns)
    p = fit.points.reshape(C, -1, 2)
    good = fit.good.reshape(C, -1) & np.all(np.isfinite(p), axis=2)
    p = np.where(good[..., None], p, 0.0)  # (unused points: finite, weight 0)
    ax = pr.axis.reshape(C, -1)
    cn = pr.const.reshape(C, -1) / ns[:, None]  # normalised module coordinates
    gm = ns[:, None] / fit.g.reshape(C, -1)  # px per normalised module
    sig = fit.sigma_px.reshape(C, -1) / gm  # sigma in normalised modules
    wgood = good.astype(float)
    cnt = np.maximum(wgood.sum(axis=1), 1.0)
    mean = (wgood[:, None, :] @ p)[:, 0] / cnt[:, None]
    d2 = np.sum(wgood * np.sum((p - mean[:, None]) ** 2, axis=2), axis=1) / cnt
    scale = np.sqrt(2.0) / np.maximum(np.sqrt(d2), 1e-9)
    q = np.concatenate(
        [(p - mean[:, None]) * scale[:, None, None], np.ones(p.shape[:2] + (1,))], axis=2
    )  # (C, M, 3)
    on_u = (ax == 0)[..., None]
    A = np.concatenate([q * on_u, q * ~on_u, -cn[..., None] * q], axis=2)  # (C, M, 9)
    keep = good
    for round_ in range(2):  # (a degenerate code gives NaN here and fails `ok` below)
        Wk = keep.astype(float)
        M = (A * Wk[..., None]).transpose(0, 2, 1) @ A
        Gv = np.linalg.eigh(M)[1][:, :, 0].reshape(C, 3, 3)
        mG = q @ Gv.transpose(0, 2, 1)
        with np.errstate(all="ignore"):
            coord = np.where(ax == 0, mG[..., 0], mG[..., 1]) / mG[..., 2]
        if round_ == 1:
            break
        res_px = np.abs(coord - cn) * gm
        med = _masked_median(res_px, good)
        keep = good & (res_px <= np.maximum(0.25, 3.0 * med)[:, None])
        keep = np.where((keep.sum(axis=1) >= _MIN_GOOD_PROFILES)[:, None], keep, good)
        if protected is not None:  # points of another kind (alignment pattern): no outlier test
            keep |= good & protected
    with np.errstate(all="ignore"):
        Hn = _inv(Gv)
        Hn = Hn / Hn[:, 2:3, 2:3]
        # one Gauss-Newton step on the geometric residuals, h = Hn.flat[:8]
        G = _inv(Hn)
        mG = q @ G.transpose(0, 2, 1)
        coord = np.where(ax == 0, mG[..., 0], mG[..., 1]) / mG[..., 2]
        r = coord - cn
        Ga = np.where(on_u, G[:, None, 0, :], G[:, None, 1, :])  # (C, M, 3)
        v = Ga - coord[..., None] * G[:, None, 2, :]
        Jh = -(v[..., :, None] * mG[..., None, :]).reshape(C, -1, 9)[..., :8] / mG[..., 2:3]
        w = keep / sig**2
        n_used = keep.sum(axis=1)
        chi2_dof = np.sum(w * r * r, axis=1) / np.maximum(n_used - 8, 1)
        resid_px = np.sqrt(np.sum(keep * (r * gm) ** 2, axis=1) / np.maximum(n_used, 1))
        info = (Jh * w[..., None]).transpose(0, 2, 1) @ Jh
        cov_h = _inv(info)
        dh = -(cov_h @ (Jh.transpose(0, 2, 1) @ (w * r)[..., None]))[..., 0]
        Hn = Hn + np.concatenate([dh, np.zeros((C, 1))], axis=1).reshape(C, 3, 3)
        # corners in normalised coordinates and their Jacobian in h
        sq = np.column_stack([_SQUARE01, np.ones(4)])  # (4, 3)
        hq = sq @ Hn.transpose(0, 2, 1)  # (C, 4, 3)
        xy = hq[..., :2] / hq[..., 2:3]
        Jc = np.zeros((C, 4, 2, 9))
        Jc[:, :, 0, 0:3] = sq[None] / hq[..., 2:3]
        Jc[:, :, 1, 3:6] = sq[None] / hq[..., 2:3]
        Jc[:, :, :, 6:9] = -xy[..., None] * sq[None, :, None, :] / hq[..., 2:3, None]
        Jc = Jc.reshape(C, 8, 9)[..., :8]
        cov = Jc @ cov_h @ Jc.transpose(0, 2, 1) / (scale**2)[:, None, None]
        corners = xy / scale[:, None, None] + mean[:, None, :]
        T_inv = np.zeros((C, 3, 3))
        T_inv[:, 0, 0] = T_inv[:, 1, 1] = 1.0 / scale
        T_inv[:, :2, 2] = mean
        T_inv[:, 2, 2] = 1.0
        S = np.diag([1.0, 1.0, 1.0])[None] * np.ones((C, 1, 1))
        S[:, 0, 0] = S[:, 1, 1] = 1.0 / ns
        H = T_inv @ Hn @ S
        H = H / H[:, 2:3, 2:3]
    ok = (
        (keep.sum(axis=1) >= _MIN_GOOD_PROFILES)
        & np.all(np.isfinite(H).reshape(C, -1), axis=1)
        & np.all(np.isfinite(cov).reshape(C, -1), axis=1)
        & np.all(np.isfinite(corners).reshape(C, -1), axis=1)
    )
    return H, corners, cov, ok, (chi2_dof, resid_px, n_used)


@dataclass(frozen=True)
class RefineQuality:
    """How well stage 2 fitted one code (undistorted px): the median edge contrast over the
    profile residual RMS of the edge profiles used, the chi^2 per degree of freedom and RMS (px)
    of the edge points about the fitted homography, the share of the 24 edge profiles used, and
    the largest distance of a refined corner from the decoder's (px), the module size (px)."""

    edge_snr: float
    chi2_dof: float
    residual_px: float
    used_fraction: float
    decoder_move_px: float
    module_px: float

    def failure(self, checks: RefineChecks) -> str | None:
        """The first check (a RefineStats counter name) this fit fails, or None."""
        if not (self.edge_snr >= checks.min_edge_snr):
            return "low_contrast"
        if not (self.used_fraction >= checks.min_used_fraction):
            return "few_edges"
        misfit = self.chi2_dof > checks.max_chi2_dof and self.residual_px > checks.negligible_residual_px
        if misfit or not (self.residual_px <= checks.max_residual_px):
            return "high_residual"
        limit = max(checks.max_decoder_move_px, checks.max_decoder_move_modules * self.module_px)
        if not (self.decoder_move_px <= limit):
            return "far_from_decoder"
        return None


@dataclass(frozen=True)
class RefineChecks:
    """Thresholds of refinement's self-check (RefineQuality.failure): a fit that fails one keeps
    the decoder's corners with FALLBACK_SIGMA_PX (measured on real photographs,
    scripts/bench_refine_real.py, and renders, scripts/bench_detect.py; BENCHMARKS.md)."""

    # clean renders (scripts/bench_detect.py frames): edge SNR >= 30, chi2/dof <= 6.4, residual
    # <= 0.035 px, >= 92 % of the edges used, decoder within 0.9 module; real photographs that
    # refinement got wrong: chi2/dof 18, residual 0.40 px, 58 % of the edges (BENCHMARKS.md)
    min_edge_snr: float = 7.0
    min_used_fraction: float = 0.6
    max_chi2_dof: float = 9.0
    max_residual_px: float = 0.35
    # a misfit this small is negligible whatever its chi2: on a nearly noise-free image (a clean
    # render) chi2/dof grows with the image's tiny noise, not with the fit's error; a rolling
    # shutter's shear of a code leaves ~0.015 px of misfit with chi2/dof ~9 there
    negligible_residual_px: float = 0.05
    max_decoder_move_px: float = 4.0
    max_decoder_move_modules: float = 1.5


DEFAULT_CHECKS = RefineChecks()
FALLBACK_SIGMA_PX = 1.5  # decoder corners: whole pixels; 1.4 px median error on real photographs


@dataclass
class RefineStats:
    """What refinement did with each code (named counters; detect.CameraStats adds them up):
    refined by stage 2 and passing its checks, by stage 1 (boundary lines), kept at the decoder's
    corners because a check failed (by the failed check), or not measurable at all."""

    refined: int = 0
    stage1: int = 0
    low_contrast: int = 0
    few_edges: int = 0
    high_residual: int = 0
    far_from_decoder: int = 0
    unmeasurable: int = 0
    small_modules: int = 0  # refined, with the small-module sigma added (not a fallback)

    @property
    def fell_back(self) -> int:
        return self.low_contrast + self.few_edges + self.high_residual + self.far_from_decoder

    def add(self, other: RefineStats) -> None:
        for k in self.__dataclass_fields__:
            setattr(self, k, getattr(self, k) + getattr(other, k))


@dataclass
class RefineResult:
    """Refined corners (4, 2) (TL, TR, BR, BL, distorted px), their (8, 8) covariance (px^2,
    order TL u, TL v, TR u, ..., BL v; calibrated on rendered codes, see `CornerCovarianceModel`), the
    1-sigma noise per coordinate (sqrt of its mean diagonal), the fitted blur+PSF box widths (px)
    across the symbol's u-edges and v-edges (NaN when stage 2 did not run), and which stage
    produced the corners (0: the decoder's, kept because stage 2 failed its self-check,
    RefineChecks; 1: boundary lines; 2: finder-model homography)."""

    corners_px: np.ndarray
    corner_sigma_px: float
    width_px: np.ndarray
    stage: int
    corner_cov_px2: np.ndarray | None = None
    quality: RefineQuality | None = None  # stage 2's fit quality (None: stages 0 and 1)


# corner covariance model:  Sigma = K^2 Sigma_stat + A^2 I_8,  Sigma_stat the edge-point noise
# (each profile's residual RMS over the square root of its Gauss-Newton information) propagated
# through the homography fit.  Maximum likelihood on rendered codes gives K ~ 1.0-1.15 and A < 0.004
# px, and no blur-dependent term (the blurred-model fit leaves no blur bias to cover).  The errors
# are heavier-tailed than Gaussian: the simulator renders by point-sampling a bilinearly
# interpolated texture, which is not the model's box PSF, and leaves orientation-dependent edge
# errors of 0.02-0.09 px (worst for edges a few degrees off the pixel axes or diagonal) that the
# per-profile residuals do not reveal.  A is therefore chosen for the MEAN pose NEES of PnP on
# rendered frames (tests/test_pnp.py `rendered_nees`; `scripts/bench_detect.py --calibrate`
# prints the mean-matching A on single-code renders): 8-D corner NEES out of sample ~7.3.
STAGE1_SIGMA_PX = 0.6  # corners from the boundary lines only (stage 2 failed or disabled)

# Codes whose modules are about a pixel wide: the finder's one-module ring is then no wider
# than the model's PSF box and the fit's propagated covariance no longer bounds its error.  On
# renders of a load code (21 modules, 0.15 m, tilted up to 0.5 rad, noise 2 DN; 100-120 codes
# per size) the calibrated model's mean 8-D corner NEES (ideal 8) is 6-15 from 1.4 to 3 px per
# module, then 13-21 at 1.2-1.3, 26 / 53 / 71 at 1.15 / 1.1 / 1.05, 125 at 1.0 and 159 at 0.9;
# the isotropic sigma that brings the mean to 8 is 0.017-0.03 px at 1.2-1.4, 0.10-0.16 px at
# 1.05-1.15, 0.33 px at 1.0 and 0.39 px at 0.9 (BENCHMARKS.md, twenty-fourth session).  Such a
# code (a load label 3.9 m away at f = 550 px) took a load 26 mm off at 4.3 sigma on a held-out
# flight.  So below SMALL_MODULE_PX[1] px per module an isotropic SMALL_MODULE_SIGMA_PX x
# (SMALL_MODULE_PX[1] - m) / (SMALL_MODULE_PX[1] - SMALL_MODULE_PX[0]) (capped at the full
# value) is added to each corner coordinate's sigma (in quadrature): the refined corners are
# still far better than the decoder's (0.2-0.4 px RMS against ~1.4 px), so they are kept with
# an honest sigma rather than dropped.  Counted per camera (RefineStats.small_modules).
SMALL_MODULE_PX = (1.0, 1.25)
SMALL_MODULE_SIGMA_PX = 0.35


def small_module_sigma_px(module_px: np.ndarray) -> np.ndarray:
    """The isotropic corner sigma (px) added for codes of `module_px` px per module (above)."""
    lo, hi = SMALL_MODULE_PX
    return SMALL_MODULE_SIGMA_PX * np.clip((hi - np.asarray(module_px, float)) / (hi - lo), 0.0, 1.0)


@dataclass(frozen=True)
class CornerCovarianceModel:
    """Sigma = k^2 Sigma_stat + a_px^2 I_8 (the model above); the defaults are the calibrated
    values.  `CornerCovarianceModel(1.0, 0.0)` leaves Sigma_stat as it is (what
    `scripts/bench_detect.py --calibrate` fits k and a_px to)."""

    k: float = 1.05
    a_px: float = 0.005

    def apply(self, cov_stat_px2: np.ndarray) -> np.ndarray:
        """(..., 8, 8) corner covariance (px^2) from the propagated one, symmetrised."""
        cov = self.k * self.k * np.asarray(cov_stat_px2) + self.a_px * self.a_px * np.eye(8)
        return 0.5 * (cov + np.swapaxes(cov, -1, -2))


CALIBRATED_COV_MODEL = CornerCovarianceModel()


def _distort_cov(dist: _Distortion, corners_u: np.ndarray, cov_u: np.ndarray) -> np.ndarray:
    """(C, 8, 8) covariances of undistorted corners (C, 4, 2) -> of the distorted corners."""
    if dist.camera is None:
        return cov_u
    Jd = dist.jacobian(corners_u, 1e-3)
    C = len(corners_u)
    Jb = np.zeros((C, 8, 8))
    for k in range(4):
        Jb[:, 2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = Jd[:, k]
    return Jb @ cov_u @ Jb.transpose(0, 2, 1)


def _stage1(
    image, dist: _Distortion, raw_u: np.ndarray, n: float, iterations: int, finder_homography: bool
) -> np.ndarray | None:
    """Boundary-line corners (4, 2) undistorted px from the decoder's (module docstring), or None."""
    corners_u = raw_u
    for it in range(iterations):
        H = homography_from_corners(corners_u, n)
        side_px = np.mean(np.linalg.norm(corners_u - np.roll(corners_u, 1, axis=0), axis=1))
        module_px = side_px / n
        wide = min(max(2.5, 0.9 * module_px), max(1.5, 1.4 * module_px))
        if it == 0 and iterations > 1:
            # coarse pass: room for the decoder's error (up to about a module), short of the
            # finder ring's inner edge one module in
            half, n_offsets = wide, _COARSE_SAMPLES
        else:
            # fine pass around edges already known to a fraction of a pixel
            half = wide if it == 0 else float(np.clip(0.4 * module_px, 2.0, 4.0))
            step = _FINE_STEP_PX if it > 0 else float(np.clip(half / 16.0, _FINE_STEP_PX, 0.5))
            n_offsets = int(round(2.0 * half / step)) + 1
        # with stage 2 to follow, stage 1 only has to land within a fraction of a module
        per_span = 8 if finder_homography else _PROFILES_PER_SPAN
        pts, line_of = _edge_points(image, dist, H, n, half, n_offsets, per_span)
        lines = _fit_lines(pts, line_of)
        if lines is None:
            return None
        top, right, bottom, left = lines
        new = [
            _intersect(top, left),
            _intersect(top, right),
            _intersect(right, bottom),
            _intersect(bottom, left),
        ]
        if any(p is None for p in new):
            return None
        corners_new = np.array(new)
        # a corner that moved by more than 1.5 modules (or 4 px) from the decoder's is a bad fit
        if np.max(np.linalg.norm(corners_new - raw_u, axis=1)) > max(4.0, 1.5 * module_px):
            return None
        corners_u = corners_new
    return corners_u


def _stage2(
    images: list[np.ndarray],
    image_of: np.ndarray,
    dist: _Distortion,
    starts_u: list[np.ndarray],
    ns: list[float],
    point_map=None,
    fit_dilation: bool = False,
    crossings_pass: bool = True,
    polish: bool = False,
) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray, RefineQuality] | None], np.ndarray]:
    """Stage 2 for a batch of codes (code c in images[image_of[c]]) from their (4, 2)
    undistorted starting corners: per code (corners_u (4, 2), cov_stat (8, 8) undistorted px^2,
    width_px (2,), RefineQuality) or None.  `point_map(code (P,), points (P, 2)) -> (P, 2)`
    (undistorted px; refine_frames' `point_map`): the corners from one more homography fit to
    the last accepted pass's edge points so moved (alignment patterns then left out).
    `fit_dilation`: fit the dark modules' growth where a code's profiles have clipped samples
    (_model_edge_points); a code whose growth is not significant (GROWTH_MIN_Z) then gets None.
    `crossings_pass=False`: the model passes start from the given corners (no 50 % crossings
    pass to lay them out: under motion blur the crossings move outwards and pull a start that is
    already close away from it; fusion.qr.track's starts are predictions and located symbols).
    `polish`: the sharp codes' corners placed again from whole pixels (_polish).
    Also returns (C,) bool: the code's profiles had clipped samples."""
    C = len(ns)
    clipped = np.zeros(C, bool)
    pr = _profiles(ns)
    nsa = np.asarray(ns, dtype=float)
    Hs = np.stack([homography_from_corners(c, n) for c, n in zip(starts_u, ns)]).astype(float)
    prev = np.stack(starts_u)
    module_px = np.mean(np.linalg.norm(prev - np.roll(prev, 1, axis=1), axis=2), axis=1) / nsa
    raw = prev
    out: list = [None] * C
    width = dilation = dilation_sigma = psf = None
    alive = np.ones(C, dtype=bool)
    model_passes = 0
    kept_fit: _ModelFit | None = None  # per code, the profiles of its last accepted pass
    for _pass, iterations in enumerate(_MODEL_ITERATIONS):
        if iterations == 0 and not crossings_pass:
            continue
        fit = _model_edge_points(
            images,
            image_of,
            dist,
            Hs,
            module_px,
            pr,
            width,
            iterations,
            _MODEL_STEP_CLIP[min(model_passes, 1)],
            dilation,
            fit_dilation=fit_dilation,
            psf0_px=psf,
            fit_psf=FIT_PSF,
        )
        H, corners, cov, ok, fit_stats = _fit_homographies(fit, pr, nsa)
        if fit.clipped is not None:
            clipped |= fit.clipped
        wmax = np.nan_to_num(np.max(fit.width_px, axis=1))
        if iterations == 0 or model_passes == 0:
            # against the decoder's corners: no corner moves by more than 1.5 modules (or 4 px),
            # plus half the blur (50 % crossings move outwards by up to that)
            move = np.max(np.linalg.norm(corners - raw, axis=2), axis=1)
            ok &= move < np.maximum(4.0, 1.5 * module_px) + 0.5 * wmax
        else:
            move = np.max(np.linalg.norm(corners - prev, axis=2), axis=1)
            ok &= move < np.maximum(1.0, 0.3 * module_px) + 0.5 * wmax
        if iterations == 0:
            # the crossings only lay out the next pass: where they fail (heavy blur), the
            # decoder's corners do
            Hs = np.where(ok[:, None, None], H, Hs)
            continue
        # a code that fails a model pass keeps the previous model pass's result
        alive &= ok
        model_passes += 1
        snr = fit.contrast / np.maximum(fit.rms, 1e-6)
        good = fit.good.reshape(C, -1)
        edge_snr = _masked_median(snr.reshape(C, -1), good)
        used = fit_stats[2] / good.shape[1]
        to_raw = np.max(np.linalg.norm(corners - raw, axis=2), axis=1)
        for ci in np.nonzero(alive)[0]:
            quality = RefineQuality(
                float(edge_snr[ci]),
                float(fit_stats[0][ci]),
                float(fit_stats[1][ci]),
                float(used[ci]),
                float(to_raw[ci]),
                float(module_px[ci]),
            )
            out[ci] = (corners[ci], cov[ci], fit.width_px[ci], quality)
        width = fit.width_px if width is None else np.where(alive[:, None], fit.width_px, width)
        if fit.dilation is not None:
            dilation = fit.dilation if dilation is None else np.where(alive[:, None], fit.dilation, dilation)
        if fit.dilation_sigma is not None:
            dilation_sigma = (
                fit.dilation_sigma
                if dilation_sigma is None
                else np.where(alive[:, None], fit.dilation_sigma, dilation_sigma)
            )
        if fit.psf_px is not None:
            psf = fit.psf_px if psf is None else np.where(alive[:, None], fit.psf_px, psf)
        Hs = np.where(alive[:, None, None], H, Hs)
        prev = np.where(alive[:, None, None], corners, prev)
        module_px = np.where(
            alive,
            np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1) / nsa,
            module_px,
        )
        kept_fit = fit if kept_fit is None else _merge_fit(kept_fit, fit, alive)
    if polish and kept_fit is not None and _POLISH_ITERATIONS > 0 and np.any(alive):
        Hs, kept_fit = _polish(
            images,
            image_of,
            dist,
            Hs,
            module_px,
            pr,
            nsa,
            width,
            dilation,
            fit_dilation,
            psf,
            kept_fit,
            alive,
            out,
        )
    if fit_dilation and dilation is not None and dilation_sigma is not None:
        # the growth only where the data support it: |d| >= GROWTH_MIN_Z sigma in an edge
        # direction; elsewhere this run gives no result and the first run's corners stand
        with np.errstate(invalid="ignore"):
            supported = np.any(np.abs(dilation) >= GROWTH_MIN_Z * dilation_sigma, axis=1)
        out = [o if supported[ci] else None for ci, o in enumerate(out)]
    if point_map is not None and kept_fit is not None:
        moved = replace(kept_fit, points=point_map(pr.code, kept_fit.points))
        _, corners, cov, ok, _ = _fit_homographies(moved, pr, nsa)
        return [
            o if o is None or not ok[ci] else (corners[ci], cov[ci], o[2], o[3]) for ci, o in enumerate(out)
        ], clipped
    has = np.array([o is not None for o in out], bool)
    if kept_fit is not None and np.any(has & (nsa >= modules_for_version(2))):
        _add_alignment(images, image_of, dist, Hs, nsa, pr, kept_fit, has, raw, module_px, out)
    return out, clipped


def _polish(
    images,
    image_of,
    dist,
    Hs,
    module_px,
    pr,
    nsa,
    width,
    dilation,
    fit_dilation,
    psf,
    kept: _ModelFit,
    alive,
    out,
) -> tuple[np.ndarray, _ModelFit]:
    """The last model pass's edges placed again from whole pixels (_model_edge_points'
    `whole_pixels`) on the codes whose edges are sharp (fitted blur box at most
    _POLISH_MAX_WIDTH_PX), their corners moved to them; everything else of the bilinear passes
    kept: which codes are refined, their RefineQuality (the self-check) and their edge sigmas
    (so the corner covariance, calibrated on them, is unchanged).

    Why: bilinear samples of an edge about a pixel wide are a piecewise-linear reconstruction
    whose shape depends on where the edge falls between pixel centres, and the model (a blurred
    step) cannot follow it: 0.02-0.045 px of error per edge even from the true homography,
    the same in every frame that sees the code alike (a hover), so no back end averages it;
    codes at ~4 px per module or seen obliquely were refined 3-4x worse than others.  Whole
    pixels read at their own offsets have no such reconstruction.  Only sharp codes: from 1.5
    px of motion blur the polish no longer helped, and from 2 px it was worse (0.016 -> 0.021
    px), where a wide ramp is what bilinear samples reconstruct well.  Not every pass: as the
    fit's start and its self-check, whole pixels accepted and placed codes of real photographs
    worse than the decoder by > 0.5 px (2 to 5 of 97, against 1), and cost 2.5x the samples.
    A polish corrects hundredths of a pixel: one that moves a corner more than
    _POLISH_MAX_MOVE_PX fits something else (compression, sharpening) and is not taken
    (BENCHMARKS.md, twenty-seventh session).

    Only the front camera's codes (POLISHED_CAMERAS).  On the trust sweep's and the held-out
    flights the polished load codes made the load maps more accurate and more of them consistent
    (93 of 108 and 60 of 80 inside their interval, against 89 and 54), with every floor pose
    unchanged.  Polishing the floor codes too made the floor poses more accurate but their
    sigma less honest: PnP's residuals and the corners' correlation time had been reading the
    phase error, and what remains (errors common to a frame's corners: timing, readout) they do
    not see, so smoother pose NEES reached 12-21 on timing-heavy flights (BENCHMARKS.md,
    twenty-seventh and twenty-eighth sessions).  Updates `out` (per code) in place; returns the
    homographies and the kept fit."""
    C = len(nsa)
    sharp = alive & (np.nan_to_num(np.max(width, axis=1), nan=np.inf) <= _POLISH_MAX_WIDTH_PX)
    sharp &= np.array([o is not None for o in out], bool)
    idx = np.flatnonzero(sharp)
    if not len(idx):
        return Hs, kept
    per = len(pr.code) // C  # profiles per code, the same for every code (_model_layout)
    rows = (idx[:, None] * per + np.arange(per)).ravel()
    pr_s = _profiles([float(n) for n in nsa[idx]])
    kept_s = _fit_rows(kept, idx, rows)
    fit = _model_edge_points(
        images,
        image_of[idx],
        dist,
        Hs[idx],
        module_px[idx],
        pr_s,
        width[idx],
        _POLISH_ITERATIONS,
        _MODEL_STEP_CLIP[1],
        None if dilation is None else dilation[idx],
        fit_dilation=fit_dilation,
        psf0_px=None if psf is None else psf[idx],
        fit_psf=FIT_PSF,
        whole_pixels=True,
    )
    take_point = fit.good & kept_s.good
    moved = replace(kept_s, points=np.where(take_point[:, None], fit.points, kept_s.points))
    H, corners, cov, ok, _ = _fit_homographies(moved, pr_s, nsa[idx])
    before = np.stack([out[ci][0] for ci in idx])
    with np.errstate(invalid="ignore"):
        move = np.max(np.linalg.norm(corners - before, axis=2), axis=1)
    take = ok & (move <= _POLISH_MAX_MOVE_PX)
    for k in np.nonzero(take)[0]:
        o = out[idx[k]]
        out[idx[k]] = (corners[k], cov[k], o[2], o[3])
    Hs = Hs.copy()
    Hs[idx[take]] = H[take]
    points = kept.points.copy()
    taken_rows = (idx[take][:, None] * per + np.arange(per)).ravel()
    points[taken_rows] = moved.points.reshape(len(idx), per, 2)[take].reshape(-1, 2)
    return Hs, replace(kept, points=points)


def _fit_rows(fit: _ModelFit, idx: np.ndarray, rows: np.ndarray) -> _ModelFit:
    """The codes `idx` of a batch's fit (their profiles: `rows`)."""

    def per_code(a):
        return None if a is None else a[idx]

    return _ModelFit(
        fit.points[rows],
        fit.good[rows],
        fit.sigma_px[rows],
        fit.g[rows],
        fit.width_px[idx],
        fit.contrast[rows],
        fit.rms[rows],
        per_code(fit.dilation),
        per_code(fit.clipped),
        per_code(fit.psf_px),
        per_code(fit.dilation_sigma),
    )


def _merge_fit(old: _ModelFit, new: _ModelFit, take: np.ndarray) -> _ModelFit:
    """Per code, `new`'s profiles where take (C,), else `old`'s."""
    C = len(take)

    def pick(a, b):
        return np.where(
            take.reshape((C,) + (1,) * (b.ndim)),
            b.reshape(C, -1, *b.shape[1:]),
            a.reshape(C, -1, *a.shape[1:]),
        ).reshape(b.shape)

    return _ModelFit(
        pick(old.points, new.points),
        pick(old.good, new.good),
        pick(old.sigma_px, new.sigma_px),
        pick(old.g, new.g),
        np.where(take[:, None], new.width_px, old.width_px),
        pick(old.contrast, new.contrast),
        pick(old.rms, new.rms),
    )


def _add_alignment(images, image_of, dist, Hs, nsa, pr, fit, alive, raw, module_px, out) -> None:
    """Refit the homography of codes of version >= 2 with their alignment patterns' centres as
    more points (each two equations: u = const, v = const), where found (see
    _ALIGN_SAMPLES_PER_MODULE); updates `out` in place (corners, covariance, widths, quality)."""
    C = len(nsa)
    centre, pts, sig, found = _alignment_points(images, image_of, dist, Hs, nsa)
    found &= alive[:, None]
    if not np.any(found):
        return
    M = len(pr.code) // C
    A = centre.shape[1]

    def cat(a, extra):
        """Per-code arrays (C * M, ...) with (C, 2A, ...) appended per code -> (C * (M + 2A), ...)."""
        return np.concatenate([a.reshape(C, M, *a.shape[1:]), extra], axis=1).reshape(
            C * (M + 2 * A), *a.shape[1:]
        )

    def twice(a):  # each alignment point enters as two equations, u = const and v = const
        return np.repeat(a, 2, axis=1)

    local_g = 1.0 / np.maximum(module_px, 1e-9)  # modules per px at the pattern
    fit2 = _ModelFit(
        cat(fit.points, twice(pts)),
        cat(fit.good, twice(found)),
        cat(fit.sigma_px, twice(np.where(found, sig, 1.0))),
        cat(fit.g, np.repeat(local_g[:, None], 2 * A, axis=1)),
        fit.width_px,
        cat(fit.contrast, np.full((C, 2 * A), np.nan)),
        cat(fit.rms, np.full((C, 2 * A), np.nan)),
    )
    pr2 = _Profiles(
        np.repeat(np.arange(C), M + 2 * A),
        cat(pr.uv0, twice(centre)),
        cat(pr.inward, np.zeros((C, 2 * A, 2))),
        cat(pr.axis, np.tile([0, 1], (C, A))),
        cat(pr.const, twice(centre).reshape(C, 2 * A, 2)[:, np.arange(2 * A), np.tile([0, 1], A)]),
        cat(pr.boundary, np.zeros((C, 2 * A), bool)),
        pr.uv_sampled,
    )
    protected = np.zeros((C, M + 2 * A), bool)
    protected[:, M:] = True
    # one homography through the finder edges and the alignment centres; where the centres do
    # not fit it (misfit beyond _ALIGN_MISFIT_SIGMA sigmas and _ALIGN_MISFIT_MODULES), one fit
    # per corner instead, each point's weight falling with its distance (modules) from that
    # corner: a printed symbol is not always flat, nor the lens model perfect, and a single
    # homography then errs most at the corner farthest from the finders (module comment above).
    # The misfit is a held-out prediction: each centre against the finder edges' homography Hs,
    # which did not see it.  Against the joint fit (as before) a centre pulls that homography
    # towards itself and hides its own misfit: on a curled real print (zxing-cpp's
    # qrcode-1/1.webp) the joint misfit passed, the single homography was kept, and a finder
    # corner came out 1.19 px off against the decoder's 0.58 (BENCHMARKS.md, real photographs)
    H, corners, cov, ok, _ = _fit_homographies(fit2, pr2, nsa, protected)
    misfit = np.linalg.norm(_apply_hs(Hs, centre) - pts, axis=2)  # (C, A) px
    with np.errstate(all="ignore"):
        bad_fit = (misfit > _ALIGN_MISFIT_SIGMA * sig) & (misfit > _ALIGN_MISFIT_MODULES * module_px[:, None])
    local = np.any(found & bad_fit, axis=1)
    uv = pr2.uv0.reshape(C, M + 2 * A, 2)
    for k in range(4) if np.any(local) else ():
        d = np.linalg.norm(uv - (_SQUARE01[k] * nsa[:, None])[:, None, :], axis=2) / nsa[:, None]
        weight = np.exp(-0.5 * (d / _LOCAL_FIT_SCALE) ** 2)
        fit_k = _ModelFit(
            fit2.points,
            fit2.good,
            fit2.sigma_px / np.sqrt(np.maximum(weight.reshape(-1), 1e-12)),
            fit2.g,
            fit2.width_px,
            fit2.contrast,
            fit2.rms,
        )
        corners_k, cov_k, ok_k = _fit_homographies(fit_k, pr2, nsa, protected)[1:4]
        corners[local, k] = corners_k[local, k]
        block = slice(2 * k, 2 * k + 2)
        if k == 0:
            cov[local] = 0.0  # the per-corner fits' errors: taken as independent
        cov[local, block, block] = cov_k[local, block, block]
        ok &= ~local | ok_k
    move = np.max(np.linalg.norm(corners - raw, axis=2), axis=1)
    ok &= found.any(axis=1) & (move < np.maximum(4.0, 1.5 * module_px))
    for ci in np.nonzero(ok)[0]:
        c_old, _, width, q = out[ci]
        # (chi^2 and residual stay those of the finder edges' single homography)
        quality = RefineQuality(
            q.edge_snr, q.chi2_dof, q.residual_px, q.used_fraction, float(move[ci]), q.module_px
        )
        out[ci] = (corners[ci], cov[ci], width, quality)


def refine_frames(
    images: list[np.ndarray],
    codes: list[list[tuple[np.ndarray, int | None]]],
    camera: CameraModel | None = None,
    iterations: int = 1,
    finder_homography: bool = True,
    cov_model: CornerCovarianceModel = CALIBRATED_COV_MODEL,
    checks: RefineChecks | None = DEFAULT_CHECKS,
    stats: RefineStats | None = None,
    point_map=None,
    crossings_pass: bool = True,
    polish: bool = False,
) -> list[list[RefineResult | None]]:
    """Refined corners of every code of several images of one camera: codes[i] lists image i's
    (decoder corners (4, 2) TL, TR, BR, BL, modules per side or None); returns, per image, a
    RefineResult or None (finder edges not measurable) per code.  Stage 2
    (`finder_homography`) runs for all codes of all images at once, from the decoder's corners
    (the array work is shared, only the sampling is per image: batching frames is what makes it
    fast); a code it fails on, or every code without it, gets `iterations` passes of stage 1.
    `camera`: fit in undistorted coordinates (None: no distortion); `cov_model`: the corner
    covariance model applied to stage 2's propagated covariance.  `checks`: stage 2's
    self-check (RefineQuality.failure); a code that fails it keeps its decoder corners with
    FALLBACK_SIGMA_PX (stage 0), counted by reason in `stats` (None: no checks).
    `point_map(image (P,), code (P,), points (P, 2)) -> (P, 2)`, undistorted px, optional: stage
    2's corners are those of a homography fitted to its edge points so moved (a rolling-shutter
    image's points moved to the stamp time: fusion.qr.rolling_shutter.refine_at_stamp); the
    self-check judges the fit in the image as read.  `crossings_pass=False`: stage 2 without
    its first, 50 % crossings pass (_stage2; for starts already near the code, e.g. tracked ones).
    `polish`: sharp codes' corners placed again from whole pixels (_polish; the cameras in
    POLISHED_CAMERAS).

    One code: `refine_code`."""
    if len(images) != len(codes):
        raise ValueError("refine_frames: one list of codes per image")
    for image in images:
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError("refine_frames expects (H, W) uint8 images")
    dist = _Distortion(camera)
    results: list[list[RefineResult | None]] = [[None] * len(c) for c in codes]
    todo, raws, ns = [], [], []  # todo: (image, code) of each code refined
    for i, (image, image_codes) in enumerate(zip(images, codes)):
        for k, (corners_raw_px, modules) in enumerate(image_codes):
            corners = np.asarray(corners_raw_px, dtype=np.float64).reshape(4, 2)
            if not np.all(np.isfinite(corners)):
                continue
            if modules is None:
                modules = estimate_modules(image, corners, camera)
                if modules is None:
                    continue
            todo.append((i, k))
            raws.append(corners)
            ns.append(float(modules))
    if not todo:
        return results
    raw_u = dist.undistort(np.concatenate(raws)).reshape(-1, 4, 2)
    image_of = np.array([i for i, _ in todo])
    code_map = None
    if point_map is not None:
        k_of = np.array([k for _, k in todo])
        code_map = lambda c, p: point_map(image_of[c], k_of[c], p)  # noqa: E731
    stage2: list = [None] * len(todo)
    if finder_homography:
        stage2, clipped = _stage2(
            images, image_of, dist, list(raw_u), ns, code_map, crossings_pass=crossings_pass, polish=polish
        )
        redo = np.nonzero(clipped & np.array([s is not None for s in stage2], bool))[0]
        if len(redo):
            # codes with clipped samples: their corners from a second run that fits the dark
            # modules' growth (_model_edge_points); the self-check keeps judging the first run,
            # whose misfit its thresholds were set on (the growth fits such profiles better and
            # would loosen it: on real photographs 3 more codes then passed it, 2 of them worse
            # than the decoder; BENCHMARKS.md)
            sub_map = None if code_map is None else (lambda c, p: code_map(redo[c], p))
            again, _ = _stage2(
                images,
                image_of[redo],
                dist,
                [raw_u[j] for j in redo],
                [ns[j] for j in redo],
                sub_map,
                True,
                crossings_pass,
                polish,
            )
            for r, s in zip(redo.tolist(), again):
                first = stage2[r]
                if s is not None and first is not None:
                    stage2[r] = (s[0], s[1], s[2], first[3])
    done = [(j, s) for j, s in enumerate(stage2) if s is not None]
    if done:
        cu = np.stack([s[0] for _, s in done])
        cov_u = np.stack([s[1] for _, s in done])
        cd = dist.distort(cu)
        cov_d = cov_model.apply(_distort_cov(dist, cu, cov_u))
        small = small_module_sigma_px(np.array([s[3].module_px for _, s in done]))
        cov_d = cov_d + (small * small)[:, None, None] * np.eye(8)
        sig = np.sqrt(np.mean(np.diagonal(cov_d, axis1=1, axis2=2), axis=1))
        for k, (j, s) in enumerate(done):
            i, c = todo[j]
            reason = None if checks is None else s[3].failure(checks)
            if reason is None:
                results[i][c] = RefineResult(cd[k], float(sig[k]), s[2], 2, cov_d[k], s[3])
                _count(stats, "refined")
                if small[k] > 0:
                    _count(stats, "small_modules")
            else:
                results[i][c] = RefineResult(
                    raws[j].copy(), FALLBACK_SIGMA_PX, s[2], 0, FALLBACK_SIGMA_PX**2 * np.eye(8), s[3]
                )
                _count(stats, reason)
    for j, (i, c) in enumerate(todo):
        if stage2[j] is not None:
            continue
        if checks is not None and finder_homography:
            # stage 1 has no self-check: with checks on, a code stage 2 cannot measure keeps the
            # decoder's corners (on real photographs stage 1 was worse than them)
            _count(stats, "unmeasurable")
            continue
        corners_u = _stage1(images[i], dist, raw_u[j], ns[j], iterations, finder_homography)
        _count(stats, "unmeasurable" if corners_u is None else "stage1")
        if corners_u is not None:
            results[i][c] = RefineResult(
                dist.distort(corners_u),
                STAGE1_SIGMA_PX,
                np.full(2, np.nan),
                1,
                STAGE1_SIGMA_PX**2 * np.eye(8),
            )
    return results


def _count(stats: RefineStats | None, name: str) -> None:
    if stats is not None:
        setattr(stats, name, getattr(stats, name) + 1)


def refine_code(
    image: np.ndarray,
    corners_raw_px: np.ndarray,
    modules: int | None = None,
    camera: CameraModel | None = None,
    iterations: int = 1,
    finder_homography: bool = True,
    cov_model: CornerCovarianceModel = CALIBRATED_COV_MODEL,
    checks: RefineChecks | None = DEFAULT_CHECKS,
) -> RefineResult | None:
    """Sub-pixel corners of one QR symbol's outer edge with their covariance and the fitted
    blur, or None when the finder edges cannot be measured (too little contrast, symbol at the
    image border, ...): `refine_frames` of one image with one code.

    `image`: (H, W) uint8 grey image; `corners_raw_px`: (4, 2) decoder corners, TL, TR, BR, BL
    (distorted px, OpenCV convention); `modules`: modules per side (17 + 4 version), estimated
    from the finder patterns when None; `iterations` passes of boundary-line fits (stage 1,
    module docstring), and with `finder_homography` the homography fits to the twelve finder
    edges located by the blurred-profile model (stage 2)."""
    return refine_frames(
        [image], [[(corners_raw_px, modules)]], camera, iterations, finder_homography, cov_model, checks
    )[0][0]


def estimate_modules(
    image: np.ndarray, corners_px: np.ndarray, camera: CameraModel | None = None
) -> int | None:
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
        end_t = t[changes[4]]  # dark, light, dark, light, dark -> 5th change ends the finder
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
