"""Codes whose finder patterns are hidden, decoded by re-stamping them (issue 10 item 4).

zxing-cpp needs all three finder patterns to locate a QR symbol; a strap, a hand or a pallet edge
over one side of a floor code (the simulator's strip occluder, fusion.sim.render
.occlusion_polygon) cuts one or two of them, and the code is lost in every frame although most of
its modules are still visible.  The function patterns are the same in every symbol of a version
(ISO/IEC 18004:2015 sec. 6.3.3-6.3.5: finders, separators, timing patterns, the dark module), so:

1. `candidate_quads`: dark quadrilaterals of a symbol's size.  The image is binarised (Otsu),
   closed with a kernel of about a module so that a symbol's dark modules merge into one blob
   (the 4-module quiet zone keeps neighbours apart), and each blob's convex hull is reduced to
   four vertices; each side is then a line fitted to the blob's outline points near it (finder
   edges and dark edge modules lie on the symbol's edge; light edge modules lie inside and are
   left out), the corners the lines' intersections.
2. `restamp_decode`: the quadrilateral rectified to the module grid (the homography of its
   corners, ISO 18004 sec. 12 step "sampling grid"), each module read at its centre and
   thresholded (Otsu over the module values), the function patterns written over them, and the
   clean module image decoded by zxing-cpp (pure-symbol mode).  The hidden data modules are
   left to the Reed-Solomon code (level H corrects 30 % of the codewords, L 7 %: ISO 18004
   Table 13).  Each of the four corners is tried as the one without a finder; a wrong guess
   leaves the format information and the codewords inconsistent and zxing returns nothing
   (a random word lies within a version-1-H symbol's correction radius with probability ~1e-15,
   version-1-L ~1e-6, and the payload must still parse as a floor code).

So the identity always comes from a decode, never from a prediction or a guess.  The corners are
the fitted quadrilateral's, refined by the caller (fusion.qr.refine with its self-check).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import zxingcpp

from fusion.qr.detect import ZXING_FORMATS, modules_for_version
from fusion.qr.track import FINDER_MODULES, TIMING_INDEX

RESTAMP_MODULES = (21, 25)  # symbol sizes tried (versions 1, 2: floor payloads fit version 1 at H)
RESTAMP_MIN_SIDE_PX = 40.0  # smaller quadrilaterals are not tried (2 px per module at version 1)
RESTAMP_MAX_SIDE_FRACTION = 0.9  # ... nor ones larger than this share of the image's height
RESTAMP_MAX_ASPECT = 1.6  # longest / shortest side: a floor code seen from above is near square
# closing kernels (px): a symbol's dark modules merge into one blob when the kernel is about 1.5-3
# modules (light runs reaching the edge leave dents the convex hull removes); two sizes cover
# modules of ~3-8 px, and stay below the 8 modules of quiet zone between two codes
RESTAMP_CLOSE_PX = (7, 13)
RESTAMP_REGION_ERODE_PX = 2  # px of a bright region's edge left out (the floor beside it)
RESTAMP_SIDE_BAND_PX = 2.0  # outline points this close to a side's line are fitted to it
RESTAMP_FIT_ITERATIONS = 4
RESTAMP_PX_PER_MODULE = 6  # rectified sampling resolution
RESTAMP_SAMPLE_FRACTION = 0.5  # a module's value: the mean of its central share (per axis)
RESTAMP_QUIET_MODULES = 4  # quiet zone of the decoded synthetic image (ISO 18004 sec. 6.3.8)
RESTAMP_RENDER_PX = 4  # pixels per module of the synthetic image


@dataclass
class Restamped:
    """A symbol decoded after its function patterns were re-stamped: payload, corners (4, 2) px
    TL, TR, BR, BL of the symbol (the fitted quadrilateral), modules per side."""

    payload: str
    corners_px: np.ndarray
    modules: int


def _order_clockwise(quad: np.ndarray) -> np.ndarray:
    """(4, 2) corners in image-clockwise order (y down), starting at the top-left-most."""
    c = quad.mean(axis=0)
    ang = np.arctan2(quad[:, 1] - c[1], quad[:, 0] - c[0])
    q = quad[np.argsort(ang)]  # increasing angle = clockwise on screen (y down)
    start = int(np.argmin(q.sum(axis=1)))
    return np.roll(q, -start, axis=0)


def _fit_sides(outline: np.ndarray, quad: np.ndarray) -> np.ndarray | None:
    """Corners (4, 2) as the intersections of lines fitted to the outline points (K, 2) near each
    side of `quad` (4, 2), RESTAMP_FIT_ITERATIONS times from the new corners (a hull vertex cut
    short by a light corner module tilts its two sides; the finder edges pull them back); None
    when a side has too few points, two lines are parallel or a corner runs away."""
    corners = np.asarray(quad, float)
    for _ in range(RESTAMP_FIT_ITERATIONS):
        lines = []
        for k in range(4):
            a, b = corners[k], corners[(k + 1) % 4]
            d = b - a
            length = float(np.linalg.norm(d))
            if length < 1e-6:
                return None
            d = d / length
            n = np.array([-d[1], d[0]])
            rel = outline - a
            along = rel @ d
            inside = (along > 0.05 * length) & (along < 0.95 * length)
            near = (np.abs(rel @ n) <= RESTAMP_SIDE_BAND_PX) & inside
            pts = outline[near]
            if len(pts) < 5:
                return None
            vx, vy, x0, y0 = cv2.fitLine(pts.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
            lines.append(np.cross([x0, y0, 1.0], [x0 + vx, y0 + vy, 1.0]))
        new = []
        for k in range(4):
            p = np.cross(lines[k - 1], lines[k])  # side k-1 meets side k at corner k
            if abs(p[2]) < 1e-9:
                return None
            new.append(p[:2] / p[2])
        corners = np.asarray(new)
    side = float(np.linalg.norm(quad[1] - quad[0]))
    if np.max(np.linalg.norm(corners - quad, axis=1)) > 0.25 * side:
        return None
    return corners


def _quiet_regions(image: np.ndarray) -> list[tuple[int, int, np.ndarray]]:
    """(x0, y0, mask) of each bright region large enough to hold a symbol: the light quiet zone
    around every symbol (ISO/IEC 18004 sec. 6.3.8, 4 modules) is brighter than a floor, so the
    image's Otsu threshold keeps it; its outline filled holds the symbol.  The mask (h, w) bool,
    eroded by RESTAMP_REGION_ERODE_PX so the floor at its edge is left out."""
    _, bright = cv2.threshold(image, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(bright, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    kernel = np.ones((3, 3), np.uint8)
    for cnt in contours:
        x, y, w, h = cv2.boundingRect(cnt)
        if min(w, h) < RESTAMP_MIN_SIDE_PX:
            continue
        filled = np.zeros((h, w), np.uint8)
        cv2.drawContours(filled, [cnt], -1, 255, cv2.FILLED, offset=(-x, -y))
        eroded = cv2.erode(filled, kernel, iterations=RESTAMP_REGION_ERODE_PX)
        out.append((x, y, np.asarray(eroded) > 0))
    return out


def candidate_quads(image: np.ndarray, exclude_px: Sequence[np.ndarray] = ()) -> list[np.ndarray]:
    """Dark quadrilaterals (4, 2) px, image-clockwise from the top-left-most, the size of a floor
    code (module docstring, step 1), none whose centre lies inside a quadrilateral of
    `exclude_px` (codes already decoded).  Searched inside bright regions (_quiet_regions), each
    binarised by its own Otsu threshold."""
    h, w = image.shape[:2]
    out: list[np.ndarray] = []
    max_side = RESTAMP_MAX_SIDE_FRACTION * min(h, w)
    for x0, y0, region in _quiet_regions(image):
        rh, rw = region.shape
        roi = image[y0 : y0 + rh, x0 : x0 + rw]
        values = roi[region]
        if values.size < 16 or int(values.max()) - int(values.min()) < 2:
            continue
        t, _ = cv2.threshold(values.reshape(1, -1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        dark = ((roi <= t) & region).astype(np.uint8) * 255
        inside = region.astype(np.uint8) * 255
        contours: list[np.ndarray] = []
        for k in RESTAMP_CLOSE_PX:
            kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
            closed = cv2.bitwise_and(cv2.morphologyEx(dark, cv2.MORPH_CLOSE, kernel), inside)
            contours += list(cv2.findContours(closed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0])
        for cnt in contours:
            quad = _blob_quad(cnt.reshape(-1, 2).astype(float) + [x0, y0], max_side, (h, w))
            if quad is None:
                continue
            centre = quad.mean(axis=0)
            side = float(np.mean(np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)))
            if any(np.linalg.norm(q.mean(axis=0) - centre) < 0.25 * side for q in out):
                continue  # the same blob at another closing size
            if any(
                cv2.pointPolygonTest(np.asarray(q, np.float32), (float(centre[0]), float(centre[1])), False)
                >= 0
                for q in exclude_px
            ):
                continue
            out.append(quad)
    return out


def _blob_quad(outline: np.ndarray, max_side: float, shape: tuple[int, int]) -> np.ndarray | None:
    """The fitted quadrilateral (4, 2) of a dark blob's outline (K, 2) px, or None when it is not
    a symbol-sized near-square away from the image border."""
    h, w = shape
    pts = outline.astype(np.float32)
    if cv2.contourArea(pts) < RESTAMP_MIN_SIDE_PX**2 * 0.5:
        return None
    hull = cv2.convexHull(pts)
    approx = cv2.approxPolyDP(hull, 0.04 * cv2.arcLength(hull, True), True).reshape(-1, 2)
    if len(approx) != 4:
        return None
    quad = _order_clockwise(approx.astype(float))
    sides = np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)
    if (
        sides.min() < RESTAMP_MIN_SIDE_PX
        or sides.max() > max_side
        or sides.max() > RESTAMP_MAX_ASPECT * sides.min()
    ):
        return None
    if np.any(quad < 1) or np.any(quad[:, 0] > w - 2) or np.any(quad[:, 1] > h - 2):
        return None  # touches the image border: part of it may be outside
    return _fit_sides(outline, quad)


def function_patterns(modules: int) -> tuple[np.ndarray, np.ndarray]:
    """(known (N, N) bool, dark (N, N) bool) of a version's fixed modules: finder patterns, their
    separators, timing patterns and the dark module (ISO/IEC 18004 sec. 6.3.3-6.3.5, 7.9.1);
    alignment patterns from version 2 on (one, at N-7)."""
    n, f = int(modules), FINDER_MODULES
    known = np.zeros((n, n), bool)
    dark = np.zeros((n, n), bool)
    finder = np.ones((f, f), bool)
    finder[1:-1, 1:-1] = False
    finder[2:-2, 2:-2] = True
    for r0, c0 in ((0, 0), (0, n - f), (n - f, 0)):
        rs = slice(max(r0 - 1, 0), min(r0 + f + 1, n))
        cs = slice(max(c0 - 1, 0), min(c0 + f + 1, n))
        known[rs, cs] = True
        dark[rs, cs] = False
        dark[r0 : r0 + f, c0 : c0 + f] = finder
    idx = np.arange(f + 1, n - f - 1)
    known[TIMING_INDEX, idx] = known[idx, TIMING_INDEX] = True
    dark[TIMING_INDEX, idx] = dark[idx, TIMING_INDEX] = idx % 2 == 0
    known[n - f - 1, f + 1] = dark[n - f - 1, f + 1] = True  # the dark module (4V + 9, 8)
    if n >= 25:  # version 2-6: one alignment pattern centred at (n-7, n-7)
        c = n - 7
        ring = np.ones((5, 5), bool)
        ring[1:-1, 1:-1] = False
        ring[2, 2] = True
        known[c - 2 : c + 3, c - 2 : c + 3] = True
        dark[c - 2 : c + 3, c - 2 : c + 3] = ring
    return known, dark


def sample_modules(image: np.ndarray, corners_px: np.ndarray, modules: int) -> np.ndarray | None:
    """(N, N) bool, True = dark: each module's mean grey over its central RESTAMP_SAMPLE_FRACTION,
    sampled through the homography of the symbol's corners (4, 2) TL, TR, BR, BL, thresholded by
    Otsu over the module means; None when they do not split in two."""
    n, k = int(modules), RESTAMP_PX_PER_MODULE
    grid = np.array([[0, 0], [n * k, 0], [n * k, n * k], [0, n * k]], np.float32)
    H = cv2.getPerspectiveTransform(grid, np.asarray(corners_px, np.float32))
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    rect = cv2.warpPerspective(image, H, (n * k, n * k), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    rect = rect.astype(np.float32)
    m = max(1, int(round(k * RESTAMP_SAMPLE_FRACTION)))
    lo = (k - m) // 2
    cells = rect.reshape(n, k, n, k)[:, lo : lo + m, :, lo : lo + m].mean(axis=(1, 3))
    values = np.clip(np.round(cells), 0, 255).astype(np.uint8)
    if int(values.max()) - int(values.min()) < 2:
        return None
    threshold, _ = cv2.threshold(values.reshape(1, -1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return cells <= threshold


def _render(modules_dark: np.ndarray) -> np.ndarray:
    """uint8 image of a module matrix, RESTAMP_RENDER_PX per module, with its quiet zone."""
    q = RESTAMP_QUIET_MODULES
    padded = np.pad(np.where(modules_dark, 0, 255).astype(np.uint8), q, constant_values=255)
    return np.kron(padded, np.ones((RESTAMP_RENDER_PX, RESTAMP_RENDER_PX), np.uint8))


def restamp_decode(image: np.ndarray, quad_px: np.ndarray, sizes=RESTAMP_MODULES) -> Restamped | None:
    """The symbol in the quadrilateral `quad_px` (4, 2), image-clockwise, decoded with its
    function patterns re-stamped (module docstring, step 2), or None."""
    quad = np.asarray(quad_px, float)
    for n in sizes:
        known, dark = function_patterns(n)
        for r in range(4):
            corners = np.roll(quad, -r, axis=0)  # this corner taken as the symbol's top-left
            sampled = sample_modules(image, corners, n)
            if sampled is None:
                return None
            stamped = np.where(known, dark, sampled)
            for b in zxingcpp.read_barcodes(
                _render(stamped),
                formats=ZXING_FORMATS,
                try_rotate=False,
                try_downscale=False,
                try_invert=False,
                is_pure=True,
            ):
                if not b.valid:
                    continue
                try:
                    text = bytes(b.bytes).decode("utf-8")
                except UnicodeDecodeError:
                    continue
                version = b.extra.get("Version", "") if isinstance(b.extra, dict) else ""
                if str(version).isdigit() and modules_for_version(int(version)) != n:
                    continue
                return Restamped(text, corners, n)
    return None


def restamp_image(image: np.ndarray, exclude_px: Sequence[np.ndarray] = ()) -> list[Restamped]:
    """Every symbol of a grey image (H, W) uint8 decoded by re-stamping (candidate_quads, then
    restamp_decode), none where `exclude_px` quadrilaterals (decoded codes) lie."""
    return restamp_candidates(image, exclude_px)[0]


def restamp_candidates(
    image: np.ndarray, exclude_px: Sequence[np.ndarray] = ()
) -> tuple[list[Restamped], list[np.ndarray]]:
    """restamp_image's decoded symbols, and the candidate quadrilaterals (4, 2) px that did not
    decode (dark squares: a blurred or damaged symbol, or something else symbol-sized; with no
    identity of their own, fusion.qr.track uses them only next to a prediction)."""
    out, failed = [], []
    for quad in candidate_quads(image, exclude_px):
        got = restamp_decode(image, quad)
        if got is not None:
            out.append(got)
        else:
            failed.append(quad)
    return out, failed
