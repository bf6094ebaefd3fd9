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

Second stage (`finder_homography`, default on): the line fit leaves the bottom-right corner,
extrapolated from two short edges, the least accurate, and its 50 % crossings move outwards under
motion blur wider than a module (the finder's 1-module ring blurs grey with its neighbours, so
"halfway to the darkest sample" is no longer halfway to black: 0.2-1 px at 4-8 px blur).  Stage 2
locates the twelve straight finder edges (six on the symbol boundary, six facing the separators)
by fitting the finder's known module sequence across each edge (dark 1 | light 1 | dark 3, quiet
zone or separator + unknown data outside), blurred by a box per symbol axis (the motion blur's
projection, fitted) and a fixed 1.5 px box (PSF and sampling): `_model_edge_points`.  A symmetric
blur then moves no edge.  One homography H (module coordinates -> pixels) is fitted to all edge
points at once: each point p on the module line u = c (or v = c) gives the linear equation
g1.p - c g3.p = 0 (or g2.p - c g3.p = 0) in G = H^-1 (a DLT with Hartley normalisation, one round
of outlier rejection); STAGE2_PASSES passes.  The corners are H applied to the module square; their
1-sigma noise (`RefineResult.corner_sigma_px`) propagates the edge-point residuals through that
fit, plus a blur-per-module term calibrated on rendered codes.

Lens distortion bends the edges.  With a `CameraModel` the whole construction runs in
undistorted pixel coordinates: the raw corners are undistorted, the profiles are laid out in
undistorted space and each sample point is distorted to read the image, the lines are fitted and
intersected in undistorted space, and the corners are distorted back (camera.project of the
normalised ray).  Without a camera the image is taken as distortion-free.

Pixel convention: OpenCV's (pixel centres at integer coordinates).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from fusion.camera import CameraModel

FINDER_MODULES = 7
_SPAN_MARGIN = 0.6          # modules kept clear of a finder's ends (neighbouring edge, corner blur)
_MIN_CONTRAST = 20.0        # grey levels between quiet zone and finder ring for a usable profile
_PROFILES_PER_SPAN = 12     # intensity profiles across each finder edge
_COARSE_SAMPLES = 25        # samples per profile in the first pass (wide window, coarse step)
_FINE_STEP_PX = 0.25        # sample spacing of the final pass
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
    vals = cv2.remap(image, x.reshape(x.shape[0], -1), y.reshape(y.shape[0], -1),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return vals.reshape(x.shape).astype(np.float32), inside


class _Distortion:
    """Undistorted pixels <-> distorted pixels for one camera (identity without a camera)."""

    def __init__(self, camera: CameraModel | None):
        self.camera = camera if camera is not None and np.any(camera.distortion) else None

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) distorted -> undistorted pixels: OpenCV's iterative inverse run to 1e-14, the
        same as CameraModel.undistort_pixels (within 1e-12 px) at a fifteenth of its cost."""
        if self.camera is None:
            return uv
        c = self.camera
        uv = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        out = cv2.undistortPoints(uv, c.K, c.dist_cv, None, None, c.K, _UNDISTORT_CRITERIA)
        return out.reshape(-1, 2)

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
    spans = [(0, (m0, 0.0), (m1, 0.0), (0.0, -1.0)), (0, (n - m1, 0.0), (n - m0, 0.0), (0.0, -1.0)),
             (1, (n, m0), (n, m1), (1.0, 0.0)),
             (2, (m0, n), (m1, n), (0.0, 1.0)),
             (3, (0.0, m0), (0.0, m1), (-1.0, 0.0)), (3, (0.0, n - m1), (0.0, n - m0), (-1.0, 0.0))]
    a = np.array([sp[1] for sp in spans])
    b = np.array([sp[2] for sp in spans])
    out = np.array([sp[3] for sp in spans])
    span_of = np.repeat(np.arange(len(spans)), per_span)
    t = np.tile(np.linspace(0.0, 1.0, per_span), len(spans))
    uv = a[span_of] + t[:, None] * (b - a)[span_of]
    line_of = np.array([sp[0] for sp in spans])[span_of]
    return a, b, out, span_of, line_of, uv


def _edge_points(image, dist: _Distortion, H: np.ndarray, n: float, half_width_px: float,
                 n_offsets: int, per_span: int = _PROFILES_PER_SPAN) -> tuple[np.ndarray, np.ndarray]:
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
    base = _apply_h(H, uv)                                                    # (P, 2)
    nrm = normal[span_of]                                                     # (P, 2)
    offsets = np.linspace(half_width_px, -half_width_px, n_offsets)           # outside -> inside
    step = offsets[0] - offsets[1]
    pts = base[:, None, :] + offsets[None, :, None] * nrm[:, None, :]         # (P, K, 2)
    vals, inside = _sample(image, dist.distort(pts))
    light = vals[:, :3].mean(axis=1)
    dark = vals.min(axis=1)
    thr = 0.5 * (light + dark)
    below = vals < thr[:, None]
    first = np.argmax(below, axis=1)                                          # first dark sample
    ok = inside.all(axis=1) & ((light - dark) > _MIN_CONTRAST) & (first > 0)
    # a crossing in the last sample step belongs to a neighbouring feature, not this edge
    ok &= first < n_offsets - 1
    idx = np.nonzero(ok)[0]
    k = first[idx]
    v0 = vals[idx, k - 1]
    frac = (v0 - thr[idx]) / np.maximum(v0 - vals[idx, k], 1e-6)
    s = offsets[k - 1] - frac * step
    return base[idx] + s[:, None] * nrm[idx], line_of[idx]


def _fit_lines(points: np.ndarray, line_of: np.ndarray, n_lines: int = 4,
               min_points: int = 4) -> np.ndarray | None:
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
        mean = np.stack([np.bincount(lab, p[:, 0], n_lines), np.bincount(lab, p[:, 1], n_lines)],
                        axis=1) / count[:, None]
        q = p - mean[lab]
        sxx = np.bincount(lab, q[:, 0] * q[:, 0], n_lines)
        syy = np.bincount(lab, q[:, 1] * q[:, 1], n_lines)
        sxy = np.bincount(lab, q[:, 0] * q[:, 1], n_lines)
        # the normal is the eigenvector of the 2x2 scatter matrix with the smaller eigenvalue
        theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)          # direction of each line
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
_MODEL_ALONG = np.linspace(2.25, 4.75, 6)       # profile positions along the finder (modules)
_MODEL_WINDOW = {True: (-2.0, 3.0), False: (-1.0, 3.0)}   # sampled span (modules, + inwards)
_MODEL_DARK = np.array([0.0, 1.0, 2.0, 5.0])     # transitions dark/light/dark/light (modules)
_MODEL_SIGN = np.array([1.0, -1.0, 1.0, -1.0])
_MODEL_ITERATIONS = 6
STAGE2_PASSES = 2
_WIDTH_GRID_PX = np.array([1.2, 2.5, 4.0, 6.0, 8.5, 12.0])   # start of the width search
_MODEL_MIN_WIDTH_PX = 0.5    # floor of the fitted motion-blur box width (px)
_MODEL_PSF_PX = 1.5         # fixed second box (px): lens / pixel PSF and the bilinear sampling


@lru_cache(maxsize=64)
def _model_layout(n: float) -> tuple[np.ndarray, ...]:
    """Profiles of the 12 finder edges for a symbol of n modules: per profile the module position
    on the edge (P, 2), the inward module direction (P, 2), which coordinate is constant on its
    edge (0: u, 1: v), the constant (modules), and whether the edge is on the symbol boundary."""
    f = float(FINDER_MODULES)
    # (axis, const, finder start along the edge, outward sign, boundary?)
    edges = [(1, 0.0, 0.0, -1, True), (0, 0.0, 0.0, -1, True),               # TL: top, left
             (0, f, 0.0, +1, False), (1, f, 0.0, +1, False),                 # TL: right, bottom
             (1, 0.0, n - f, -1, True), (0, n, 0.0, +1, True),               # TR: top, right
             (0, n - f, 0.0, -1, False), (1, f, n - f, +1, False),           # TR: left, bottom
             (0, 0.0, n - f, -1, True), (1, n, 0.0, +1, True),               # BL: left, bottom
             (0, f, n - f, +1, False), (1, n - f, 0.0, -1, False)]           # BL: right, top
    k = len(_MODEL_ALONG)
    uv, inward, axis, const, boundary = [], [], [], [], []
    for ax, c, start, sign, bnd in edges:
        along = start + _MODEL_ALONG
        uv.append(np.column_stack([np.full(k, c), along]) if ax == 0
                  else np.column_stack([along, np.full(k, c)]))
        d = np.zeros(2)
        d[ax] = -sign
        inward.append(np.tile(d, (k, 1)))
        axis += [ax] * k
        const += [c] * k
        boundary += [bnd] * k
    return (np.concatenate(uv), np.concatenate(inward), np.array(axis), np.array(const),
            np.array(boundary))


def _ramp_integral(z, w):
    """Q(z) = integral of clip(z / w + 1/2, 0, 1) dz (0 below -w/2) and dQ/dw."""
    t = np.clip(z + 0.5 * w, 0.0, w)
    q = t * t / (2.0 * w) + np.maximum(z - 0.5 * w, 0.0)
    dq_dw = np.where((z > -0.5 * w) & (z < 0.5 * w), t / (2.0 * w) - t * t / (2.0 * w * w), 0.0)
    return q, dq_dw


def _edge_model(x: np.ndarray, width: np.ndarray, pixel: np.ndarray):
    """Blurred finder profile at x (P, K) modules inwards from the edge, for a box kernel of
    `width` (P, 1) modules convolved with a box of one pixel (`pixel` (P, 1) modules: the
    sampling's interpolation): the dark fraction D, the blurred data indicator Dd (x < -1), and
    their derivatives in x and in width.  A step at `pos` contributes H(x - pos), the kernel's
    cumulative distribution, (Q(z + p/2) - Q(z - p/2)) / p with Q the integral of the box's."""
    pos = np.concatenate([[-1.0], _MODEL_DARK])
    z = x[..., None] - pos                                  # (P, K, 5)
    w = width[..., None]
    p = pixel[..., None]
    qa, qa_w = _ramp_integral(z + 0.5 * p, w)
    qb, qb_w = _ramp_integral(z - 0.5 * p, w)
    H = (qa - qb) / p
    dHdz = (np.clip((z + 0.5 * p) / w + 0.5, 0.0, 1.0) - np.clip((z - 0.5 * p) / w + 0.5, 0.0, 1.0)) / p
    dHdw = (qa_w - qb_w) / p
    D = H[..., 1:] @ _MODEL_SIGN
    dD_dx = dHdz[..., 1:] @ _MODEL_SIGN
    dD_dw = dHdw[..., 1:] @ _MODEL_SIGN
    return D, 1.0 - H[..., 0], dD_dx, -dHdz[..., 0], dD_dw, -dHdw[..., 0]


@dataclass
class _ModelFit:
    """Stage-2 edge points and what the fit learnt: points (M, 2) undistorted px, their module
    line (axis (M,), const (M,)), edge-position sigma (M,) px, per-profile residual RMS (M,) DN,
    contrast (M,) DN, and the fitted kernel widths (px) across u-edges and v-edges."""
    points: np.ndarray
    axis: np.ndarray
    const: np.ndarray
    sigma_px: np.ndarray
    rms_dn: np.ndarray
    contrast_dn: np.ndarray
    width_px: np.ndarray


def _level_fit(D, Dd, y, wmask):
    """Per-profile least-squares levels (W, C, g) of y = W + C D + g Dd: (P, 3), residuals (P, K)."""
    A = np.stack([np.ones_like(D), D, Dd], axis=-1) * wmask[..., None]
    N = np.einsum("pki,pkj->pij", A, A) + np.diag([1e-9, 1e-9, 1e-6])
    lev = np.linalg.solve(N, np.einsum("pki,pk->pi", A, y * wmask)[..., None])[..., 0]
    r = (lev[:, 0:1] + lev[:, 1:2] * D + lev[:, 2:3] * Dd - y) * wmask
    return lev, r


def _model_edge_points(image, dist: _Distortion, H: np.ndarray, n: float,
                       width0_px: np.ndarray | None = None,
                       iterations: int = _MODEL_ITERATIONS) -> _ModelFit | None:
    """Fit the finder's known profile across each of the 12 finder edges (module docstring).

    Per profile i, image samples y(s) at s modules inwards from the edge H predicts (one remap
    for all profiles) are modelled as  y = W + C D(s - e_i; w) + g Dd(s - e_i; w)  with D the
    dark-module sequence blurred by a box of width w (modules) and Dd the data modules beyond the
    separator (edges facing the interior only).  W, C, g are solved linearly per profile
    (variable projection); the edge offsets e_i and one kernel width in pixels per edge
    direction (u-edges, v-edges: a motion blur's projections on the two symbol axes, plus the
    lens PSF) by Gauss-Newton, the widths eliminated by a Schur complement.  Symmetric blur then
    moves no edge, whatever its width relative to the module."""
    uv0, inward, axis, const, boundary = _model_layout(float(n))
    P = len(uv0)
    # local scale: |grad u| or |grad v| in modules per px at each profile (undistorted image)
    w3 = uv0 @ H[2, :2] + H[2, 2]
    xy0 = _apply_h(H, uv0)
    J = (H[:2, :2][None] - xy0[:, :, None] * H[2, :2][None, None, :]) / w3[:, None, None]
    try:
        Jinv = np.linalg.inv(J)                                # rows: grad u, grad v (mod / px)
    except np.linalg.LinAlgError:
        return None
    g = np.linalg.norm(Jinv[np.arange(P), axis], axis=1)      # modules per px across the edge
    if not np.all(np.isfinite(g)) or np.any(g <= 0):
        return None
    module_px = float(np.median(1.0 / g))
    # samples: dense (0.5 px) within 3 px of the predicted edge, 0.25 module over the window
    dense = np.arange(-3.0, 3.01, 0.5) / module_px
    lo, hi = _MODEL_WINDOW[True]
    s = np.unique(np.round(np.concatenate([dense, np.linspace(lo, hi, 21)]), 6))
    s_mod = np.broadcast_to(s, (P, len(s)))
    lo_inner = _MODEL_WINDOW[False][0]
    wmask = np.where(boundary[:, None], 1.0, (s_mod >= lo_inner).astype(float))
    pts = uv0[:, None, :] + s_mod[..., None] * inward[:, None, :]
    y, inside = _sample(image, dist.distort(_apply_h(H, pts)))
    y = y.astype(np.float64)
    ok = inside.all(axis=1)
    wmask = wmask * ok[:, None]
    data_on = (~boundary).astype(float)[:, None]
    # unknowns: e (P,) modules; kernel width per direction (2,) px
    e = np.zeros(P)
    max_w = 4.0 * module_px + 2.0
    if width0_px is None:
        # Gauss-Newton creeps when the width is far too small (samples outside the narrow ramps
        # carry no derivative): start each direction at the best of a few widths, e = 0
        grid = _WIDTH_GRID_PX[_WIDTH_GRID_PX <= max_w]
        sub = np.arange(P) % 3 == 0
        G = len(grid)
        x = np.tile(s_mod[sub], (G, 1))
        wg = np.repeat(grid, sub.sum())[:, None] * np.tile(g[sub], G)[:, None]
        D, Dd = _edge_model(x, wg, np.tile(g[sub], G)[:, None] * _MODEL_PSF_PX)[:2]
        wm = np.tile(wmask[sub], (G, 1))
        _, r = _level_fit(D, Dd * np.tile(data_on[sub], (G, 1)), np.tile(y[sub], (G, 1)), wm)
        cost = np.sum(r * r, axis=1).reshape(G, -1)
        ax_sub = axis[sub]
        per_axis = np.stack([cost[:, ax_sub == a].sum(axis=1) for a in (0, 1)], axis=1)
        width_px = grid[np.argmin(per_axis, axis=0)].astype(float)
    else:
        width_px = np.clip(np.asarray(width0_px, dtype=float), _MODEL_MIN_WIDTH_PX, max_w)
    for _ in range(iterations):
        wmod = (width_px[axis] * g)[:, None]
        D, Dd, dD_dx, dDd_dx, dD_dw, dDd_dw = _edge_model(s_mod - e[:, None], wmod, _MODEL_PSF_PX * g[:, None])
        Dd = Dd * data_on
        lev, r = _level_fit(D, Dd, y, wmask)
        C, gam = lev[:, 1:2], lev[:, 2:3]
        Je = -(C * dD_dx + gam * dDd_dx * data_on) * wmask               # d model / d e
        Jw = (C * dD_dw + gam * dDd_dw * data_on) * wmask * g[:, None]   # d model / d width_px
        a = np.sum(Je * Je, axis=1) + 1e-9
        b = np.sum(Je * Jw, axis=1)
        c = np.sum(Jw * Jw, axis=1)
        ge = np.sum(Je * r, axis=1)
        gw = np.sum(Jw * r, axis=1)
        S = np.bincount(axis, c - b * b / a, 2) + 1e-6
        rhs = np.bincount(axis, gw - b * ge / a, 2)
        dw = -rhs / S
        de = -(ge + b * dw[axis]) / a
        e = e + np.clip(de, -0.35, 0.35)
        width_px = np.clip(width_px + np.clip(dw, -1.5, 1.5), _MODEL_MIN_WIDTH_PX, max_w)
    dof = np.maximum(wmask.sum(axis=1) - 5.0, 1.0)
    rms = np.sqrt(np.sum(r * r, axis=1) / dof)
    contrast = -C[:, 0]
    sigma_e = rms / np.sqrt(a) / g                                     # px
    good = ok & (contrast > _MIN_CONTRAST) & (np.abs(e) < 1.0) & np.isfinite(sigma_e)
    if good.sum() < 24:
        return None
    med = float(np.median(rms[good]))
    good &= rms <= 3.0 * med + 1.0
    idx = np.nonzero(good)[0]
    p = _apply_h(H, uv0[idx] + e[idx, None] * inward[idx])
    return _ModelFit(p, axis[idx], const[idx], sigma_e[idx], rms[idx], contrast[idx], width_px)


def _fit_homography(p: np.ndarray, ax: np.ndarray, const: np.ndarray, n: float,
                    module_px: float) -> tuple[np.ndarray, np.ndarray] | None:
    """H (module coordinates -> undistorted px) from points p (M, 2) on module lines u = const
    (ax 0) or v = const (ax 1): linear least squares in G = H^-1 with Hartley normalisation, one
    round of outlier rejection.  Returns (H, mask of the points kept) or None."""
    c = const / n
    mean = p.mean(axis=0)
    scale = np.sqrt(2.0) / max(np.sqrt(np.mean(np.sum((p - mean) ** 2, axis=1))), 1e-9)
    T = np.array([[scale, 0.0, -scale * mean[0]], [0.0, scale, -scale * mean[1]], [0.0, 0.0, 1.0]])
    q = np.column_stack([(p - mean) * scale, np.ones(len(p))])
    keep = np.ones(len(q), dtype=bool)
    G = None
    for round_ in range(2):
        A = np.zeros((int(keep.sum()), 9))
        qk, axk, ck = q[keep], ax[keep], c[keep]
        A[axk == 0, 0:3] = qk[axk == 0]
        A[axk == 1, 3:6] = qk[axk == 1]
        A[:, 6:9] = -ck[:, None] * qk
        _, _, vt = np.linalg.svd(A, full_matrices=False)
        G = vt[-1].reshape(3, 3)
        if round_ == 1:
            break
        m = q @ G.T
        coord = np.where(ax == 0, m[:, 0], m[:, 1]) / m[:, 2]
        r = np.abs(coord - c) * n * module_px                                 # ~ px
        keep = r <= max(0.25, 3.0 * float(np.median(r)))
        if keep.all() or keep.sum() < 24:
            keep[:] = True if keep.sum() < 24 else keep
            break
    S = np.diag([1.0 / n, 1.0 / n, 1.0])            # module coords -> normalised module coords
    H_new = np.linalg.inv(T) @ np.linalg.inv(G) @ S
    if not np.all(np.isfinite(H_new)) or abs(H_new[2, 2]) < 1e-12:
        return None
    return H_new / H_new[2, 2], keep


@dataclass
class RefineResult:
    """Refined corners (4, 2) (TL, TR, BR, BL, distorted px), their 1-sigma noise per coordinate
    (px, calibrated on rendered codes: `corner_sigma`), the fitted blur+PSF box widths (px) across
    the symbol's u-edges and v-edges (NaN when stage 2 did not run), and which stage produced
    the corners (1: boundary lines, 2: finder-model homography)."""
    corners_px: np.ndarray
    corner_sigma_px: float
    width_px: np.ndarray
    stage: int


# corner sigma model, fitted by scripts/bench_detect.py's calibration on rendered codes (seeded,
# 0.7-1.8 m, blur 0-8 px, noise 0.5-4 DN):  sigma^2 = (K sigma_stat)^2 + A^2 + (B (w / m)^2)^2,
# with sigma_stat the corner noise the edge-point residuals imply, w the larger fitted blur width
# (px) and m the module size (px): the model's mismatch grows quickly once the blur spans modules.
_SIGMA_K = 0.85
_SIGMA_A_PX = 0.007
_SIGMA_B_PX = 0.025
STAGE1_SIGMA_PX = 0.6       # corners from the boundary lines only (stage 2 failed or disabled)


def _corner_sigma_stat(H: np.ndarray, fit: "_ModelFit", keep: np.ndarray, n: float) -> float:
    """RMS over the 8 corner coordinates of the first-order corner noise implied by independent
    edge points with sigma fit.sigma_px, through the weighted least-squares fit of H (8 params)."""
    p, ax, c, sig = fit.points[keep], fit.axis[keep], fit.const[keep], fit.sigma_px[keep]
    sq = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]])
    q = np.column_stack([p, np.ones(len(p))])

    def resid(h):
        Hh = np.append(h, 1.0).reshape(3, 3)
        m = q @ np.linalg.inv(Hh).T
        return (np.where(ax == 0, m[:, 0], m[:, 1]) / m[:, 2] - c)

    def corners(h):
        return _apply_h(np.append(h, 1.0).reshape(3, 3), sq).reshape(-1)

    h0 = (H / H[2, 2]).reshape(-1)[:8]
    step = 1e-6 * np.maximum(np.abs(h0), 1e-3)
    J = np.empty((len(p), 8))
    Jc = np.empty((8, 8))
    for k in range(8):
        d = np.zeros(8)
        d[k] = step[k]
        J[:, k] = (resid(h0 + d) - resid(h0 - d)) / (2 * step[k])
        Jc[:, k] = (corners(h0 + d) - corners(h0 - d)) / (2 * step[k])
    # residuals are in modules; sigma_px / module_px converts the point sigmas
    mod_px = np.linalg.norm(corners(h0).reshape(4, 2)[1] - corners(h0).reshape(4, 2)[0]) / n
    w = 1.0 / (sig / mod_px) ** 2
    try:
        cov_h = np.linalg.inv(J.T @ (J * w[:, None]))
    except np.linalg.LinAlgError:
        return float("nan")
    cov_c = Jc @ cov_h @ Jc.T
    return float(np.sqrt(max(np.trace(cov_c), 0.0) / 8.0))


def corner_sigma(sigma_stat_px: float, width_px: np.ndarray, module_px: float) -> float:
    """Calibrated 1-sigma corner noise per coordinate (px), see _SIGMA_K / _A / _B."""
    wm = float(np.max(width_px)) / module_px
    return float(np.sqrt((_SIGMA_K * sigma_stat_px) ** 2 + _SIGMA_A_PX ** 2
                         + (_SIGMA_B_PX * wm * wm) ** 2))


def refine_code(image: np.ndarray, corners_raw_px: np.ndarray, modules: int | None = None,
                camera: CameraModel | None = None, iterations: int = 1,
                finder_homography: bool = True) -> RefineResult | None:
    """Refined corners with their sigma and the fitted blur, or None (see
    `refine_corners_or_none`, which returns only the corners)."""
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
        new = [_intersect(top, left), _intersect(top, right), _intersect(right, bottom),
               _intersect(bottom, left)]
        if any(p is None for p in new):
            return None
        new = np.array(new)
        # a corner that moved by more than 1.5 modules (or 4 px) from the decoder's is a bad fit
        if np.max(np.linalg.norm(new - raw_u, axis=1)) > max(4.0, 1.5 * module_px):
            return None
        corners_u = new
    stage, width = 1, np.full(2, np.nan)
    sigma = STAGE1_SIGMA_PX
    if finder_homography:
        H = homography_from_corners(corners_u, n)
        module_px = np.mean(np.linalg.norm(corners_u - np.roll(corners_u, 1, axis=0), axis=1)) / n
        w0 = None
        for _ in range(STAGE2_PASSES):
            fit = _model_edge_points(image, dist, H, n, w0)
            if fit is None:
                break
            res = _fit_homography(fit.points, fit.axis, fit.const, n, module_px)
            if res is None:
                break
            new = _apply_h(res[0], np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]]))
            # stage 1's 50 % crossings move outwards by up to ~half the blur width
            tol = max(1.0, 0.3 * module_px) + 0.5 * float(np.max(fit.width_px))
            if np.max(np.linalg.norm(new - corners_u, axis=1)) >= tol:
                break
            corners_u, H, w0 = new, res[0], fit.width_px
            stage, width = 2, fit.width_px
            s_stat = _corner_sigma_stat(H, fit, res[1], n)
            if np.isfinite(s_stat):
                sigma = corner_sigma(s_stat, width, module_px)
    return RefineResult(dist.distort(corners_u), sigma, width, stage)


def refine_corners_or_none(image: np.ndarray, corners_raw_px: np.ndarray, modules: int | None = None,
                           camera: CameraModel | None = None, iterations: int = 1,
                           finder_homography: bool = True) -> np.ndarray | None:
    """Refined (4, 2) corners (TL, TR, BR, BL, distorted px, OpenCV convention) or None if the
    finder edges cannot be measured (too little contrast, symbol at the image border, ...).

    `iterations` passes of boundary-line fits (stage 1, module docstring), then with
    `finder_homography` STAGE2_PASSES homography fits to the twelve finder edges located by the
    blurred-profile model (stage 2), each kept when it agrees with the previous corners."""
    res = refine_code(image, corners_raw_px, modules, camera, iterations, finder_homography)
    return None if res is None else res.corners_px


def refine_corners(image: np.ndarray, corners_raw_px: np.ndarray, modules: int | None = None,
                   camera: CameraModel | None = None, iterations: int = 1,
                   finder_homography: bool = True) -> np.ndarray:
    """Sub-pixel (4, 2) corners of a QR symbol's outer edge, TL, TR, BR, BL in distorted pixels.

    `image`: (H, W) uint8 grey image; `corners_raw_px`: (4, 2) decoder corners in the same order;
    `modules`: modules per side (17 + 4 version), estimated from the finder patterns when None;
    `camera`: fit the lines in undistorted coordinates.  Returns a copy of the raw corners when
    the refinement fails (use `refine_corners_or_none` to tell)."""
    out = refine_corners_or_none(image, corners_raw_px, modules, camera, iterations,
                                 finder_homography)
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
