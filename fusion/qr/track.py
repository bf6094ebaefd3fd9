"""Codes tracked through blur, glare and occlusion: a code decoded in an earlier frame of the same
camera whose symbol is still visible but no longer decodes is found again near where its motion
predicts it, its corners refined (fusion.qr.refine, with its self-check), and its identity taken
from the prediction, gated by the innovation; never guessed.

Per camera, frames in time order (`CodeTracker.step`):

1. Predict each live track's corners at this frame: constant pixel velocity from its last two
   sightings (decoded or tracked), or its last corners when it has one.  The prediction's
   1-sigma per coordinate: TRACK_MIN_SIGMA_PX plus TRACK_VELOCITY_SIGMA of the motion since the
   last sighting.
2. Skip tracks decoded in this frame, tracks whose predicted symbol (with the quiet zone) leaves
   the image, and tracks whose prediction overlaps a code decoded in this frame (identity would
   be ambiguous).
3. Refine the finder edges from the predicted corners (refine_frames: stage 2 only, with its
   self-check, RefineChecks; the pipeline's pass without its 50 % crossings pass,
   TRACK_CROSSINGS_PASS; a matching dark square, match_square, is one more start, and its
   corners the sighting's when refinement fails from every start).  Accept when it passes, no
   corner moved more than TRACK_GATE_MODULES modules from the prediction (codes are separated
   by at least their quiet zones, 4 modules, so a code cannot take another's identity; several
   starts around the prediction, TRACK_START_OFFSETS_PX, the passing result nearest it kept),
   and the innovation e^T (S_pred + S_refined)^-1 e is below TRACK_GATE_CHI2 (chi^2, 8 dof, 99.9 %).
4. A track lives TRACK_MAX_MISSES frames without a sighting and at most TRACK_MAX_RUN tracked
   sightings in a row (then it needs a decode again).

Tracked detections carry `QRDetection.tracked = True`, the prediction as `corners_raw_px` and
refinement's covariance inflated by its disagreement with the prediction
(TRACK_AGREEMENT_SIGMA_PX).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fusion.camera import CameraModel
from fusion.qr.refine import DEFAULT_CHECKS, RefineChecks, refine_frames
from fusion.types import QRDetection

TRACK_MIN_SIGMA_PX = 1.5  # prediction 1-sigma floor per coordinate (px)
TRACK_VELOCITY_SIGMA = 0.5  # plus this share of the predicted motion since the last sighting
TRACK_GATE_MODULES = 2.0  # largest corner innovation (modules): half the quiet zone (4 modules)
TRACK_START_OFFSETS_PX = np.array(
    [[0.0, 0.0], [3.0, 0.0], [-3.0, 0.0], [0.0, 3.0], [0.0, -3.0]]
)  # refinement starts around a prediction, scaled by its sigma over TRACK_MIN_SIGMA_PX
TRACK_GATE_CHI2 = 26.12  # chi^2 with 8 degrees of freedom, 99.9 %
TRACK_MAX_MISSES = 2  # frames a track survives without a sighting
TRACK_MAX_RUN = 30  # tracked sightings in a row before a decode is needed again
TRACK_QUIET_MODULES = 2.0  # the predicted symbol and this much quiet zone must be in the image
# A tracked code's covariance: refinement's, plus the share of its disagreement with the
# prediction (mean square per coordinate) beyond this prediction sigma, per coordinate
# (innovation-based covariance matching: Mehra 1972, IEEE TAC 17(5); Mohamed & Schwarz 1999,
# J. Geodesy 73, eq. 23).  Under heavy blur refinement can move 2-5 px off a good prediction
# while claiming 0.3 px; with this, tracked codes' chi2/dof on a 50 ms-exposure flight fell from
# 8.3 to 1.6 (decoded codes: 1.3; BENCHMARKS.md).  0.5 px: the prediction's robust per-coordinate
# error there was 0.22 px.
TRACK_AGREEMENT_SIGMA_PX = 0.5
# Before refinement, the three finder patterns, their separators, a one-module quiet zone and the
# timing patterns (ISO/IEC 18004 sec. 6.3.3-6.3.5: the same in every symbol of a version) are
# matched (normalised cross-correlation) around the prediction, within the gate
# (TRACK_GATE_MODULES) and 3 prediction sigmas: refinement's capture range under 10 px blur is
# ~2 px, an IMU-bridged prediction across a 1.5 s gap was 4-15 px off (BENCHMARKS.md).  The
# innovation gate still measures from the prediction, so the identity argument is unchanged.
TRACK_LOCATE_PX_PER_MODULE = 4  # template resolution before it is warped into the image
TRACK_LOCATE_QUIET_MODULES = 1  # light modules around the symbol in the template
TRACK_LOCATE_MIN_NCC = 0.4  # a weaker best match is not used (the prediction is the start)
TRACK_LOCATE_SIGMAS = 3.0  # search radius in prediction sigmas (capped by the gate)
# Refinement from a tracked code's starts skips its first, 50 % crossings pass (refine_frames
# `crossings_pass`): under 10 px of motion blur the crossings lie outwards of the edges and move a
# start that is already within refinement's capture range away from it (BENCHMARKS.md, seventh session: from
# the true corners of blurred codes, 0.67 -> 0.42 px median)
TRACK_CROSSINGS_PASS = False
# Dark squares (fusion.qr.restamp.candidate_quads of a frame whose re-stamp decode failed: a
# symbol-sized dark quadrilateral in a bright quiet zone) near a prediction: an extra refinement
# start, and, when refinement fails from every start, the code's corners with
# TRACK_SQUARE_SIGMA_PX (the decoder-corner fallback's sigma) if, aligned to the prediction, each
# corner lies within TRACK_SQUARE_SHAPE_MODULES of it after removing the centres' offset (the
# same shape) and the centres within the gate; the identity is still the prediction's, behind the
# innovation gate (and the caller's pose gate)
TRACK_SQUARE_SHAPE_MODULES = 0.5
TRACK_SQUARE_SIGMA_PX = 1.5
FINDER_MODULES = 7
TIMING_INDEX = 6  # the timing patterns' row and column


def symbol_in_view(corners_px: np.ndarray, modules: int, shape: tuple[int, int]) -> bool:
    """True when a symbol's corners (4, 2) px and TRACK_QUIET_MODULES of its quiet zone lie in an
    image of `shape` (H, W): only then can its finder edges be refined."""
    corners = np.asarray(corners_px, dtype=float)
    if corners.shape != (4, 2) or not np.all(np.isfinite(corners)):
        return False
    side = float(np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)))
    margin = TRACK_QUIET_MODULES * side / modules
    h, w = shape[:2]
    return bool(
        np.all(corners[:, 0] >= margin)
        and np.all(corners[:, 1] >= margin)
        and np.all(corners[:, 0] <= w - 1 - margin)
        and np.all(corners[:, 1] <= h - 1 - margin)
    )


def function_pattern_template(modules: int) -> np.ndarray:
    """(M, M) module values of a symbol with TRACK_LOCATE_QUIET_MODULES of quiet zone (M = modules
    + 2 quiet): 0 dark, 1 light, NaN unknown (data).  Finder patterns (7 x 7: dark ring, light
    ring, dark 3 x 3), their light separators, the timing patterns (ISO/IEC 18004 sec. 6.3)."""
    n, q = int(modules), TRACK_LOCATE_QUIET_MODULES
    g = np.full((n + 2 * q, n + 2 * q), np.nan)
    g[:q, :] = g[-q:, :] = g[:, :q] = g[:, -q:] = 1.0
    sym = g[q : q + n, q : q + n]  # a view
    f = FINDER_MODULES
    finder = np.zeros((f, f))
    finder[1:-1, 1:-1] = 1.0
    finder[2:-2, 2:-2] = 0.0
    for r0, c0 in ((0, 0), (0, n - f), (n - f, 0)):
        r1, c1 = r0 + f, c0 + f
        sym[max(r0 - 1, 0) : min(r1 + 1, n), max(c0 - 1, 0) : min(c1 + 1, n)] = 1.0  # separator
        sym[r0:r1, c0:c1] = finder
    timing = (np.arange(f + 1, n - f - 1) % 2).astype(float)  # dark at even indices
    sym[TIMING_INDEX, f + 1 : n - f - 1] = timing
    sym[f + 1 : n - f - 1, TIMING_INDEX] = timing
    return g


def locate_symbol(image: np.ndarray, corners_px: np.ndarray, modules: int, max_shift_px: float):
    """(shift (2,) px, normalised cross-correlation) of the best match of the symbol's function
    patterns (function_pattern_template, warped by the homography of `corners_px` (4, 2) TL, TR,
    BR, BL) within +-max_shift_px of where the corners put it; None when the search window leaves
    the image or the template is degenerate."""
    n, q, k = int(modules), TRACK_LOCATE_QUIET_MODULES, TRACK_LOCATE_PX_PER_MODULE
    shift = int(np.floor(max_shift_px))
    if shift < 1:
        return None
    g = function_pattern_template(n)
    known = np.isfinite(g)
    size = g.shape[0] * k
    values = cv2.resize(
        np.where(known, g, 0.5).astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST
    )
    mask = cv2.resize(known.astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST)
    unit = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]]) + q  # corners in template modules
    H = cv2.getPerspectiveTransform((unit * k).astype(np.float32), np.asarray(corners_px, np.float32))
    outline = np.array([[0, 0], [size, 0], [size, size], [0, size]], np.float32)[None]
    box = cv2.perspectiveTransform(outline, H)[0]
    x0, y0 = np.floor(box.min(axis=0)).astype(int)
    x1, y1 = np.ceil(box.max(axis=0)).astype(int)
    h, w = image.shape[:2]
    if x0 - shift < 0 or y0 - shift < 0 or x1 + shift >= w or y1 + shift >= h:
        return None
    to_box = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ H
    dsize = (int(x1 - x0 + 1), int(y1 - y0 + 1))
    tmpl = cv2.warpPerspective(values, to_box, dsize, flags=cv2.INTER_LINEAR)
    tmask = cv2.warpPerspective(mask, to_box, dsize, flags=cv2.INTER_NEAREST)
    if tmask.sum() < 1 or float(np.std(tmpl[tmask > 0])) <= 0:
        return None
    region = image[y0 - shift : y1 + 1 + shift, x0 - shift : x1 + 1 + shift].astype(np.float32)
    score = cv2.matchTemplate(region, tmpl, cv2.TM_CCOEFF_NORMED, mask=tmask)
    score = np.where(np.isfinite(score), score, -1.0)
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    best = np.array([ix - shift, iy - shift], float)
    # sub-pixel: the vertex of the parabola through the peak and its two neighbours, per axis
    for axis, (a, b, c) in enumerate(
        (
            score[iy, ix - 1 : ix + 2] if 0 < ix < score.shape[1] - 1 else (0.0, 1.0, 0.0),
            score[iy - 1 : iy + 2, ix] if 0 < iy < score.shape[0] - 1 else (0.0, 1.0, 0.0),
        )
    ):
        curvature = a - 2.0 * b + c
        if curvature < 0:
            best[axis] += float(np.clip(0.5 * (a - c) / curvature, -0.5, 0.5))
    return best, float(score[iy, ix])


def _worst_px(corners: np.ndarray, pred: np.ndarray) -> float:
    return float(np.max(np.linalg.norm(corners - pred, axis=1)))


def match_square(squares: list[np.ndarray], pred: np.ndarray, modules: int) -> np.ndarray | None:
    """The dark square (4, 2) px of `squares` that matches the predicted corners `pred` (4, 2)
    TL, TR, BR, BL of a symbol of `modules` per side, its corners reordered to `pred`'s: its
    centre within TRACK_GATE_MODULES of the prediction's and, centres aligned, every corner
    within TRACK_SQUARE_SHAPE_MODULES; the nearest such one, else None."""
    pred = np.asarray(pred, float)
    module = float(np.mean(np.linalg.norm(pred - np.roll(pred, 1, axis=0), axis=1))) / modules
    centre = pred.mean(axis=0)
    best, best_d = None, np.inf
    for sq in squares:
        sq = np.asarray(sq, float)
        d = float(np.linalg.norm(sq.mean(axis=0) - centre))
        if d > TRACK_GATE_MODULES * module or d >= best_d:
            continue
        # the cyclic order (squares are image-clockwise, as a symbol's TL, TR, BR, BL) nearest
        shape = sq - sq.mean(axis=0)
        rolls = [np.roll(shape, -r, axis=0) for r in range(4)]
        r = int(np.argmin([np.sum((x - (pred - centre)) ** 2) for x in rolls]))
        if np.max(np.linalg.norm(rolls[r] - (pred - centre), axis=1)) > TRACK_SQUARE_SHAPE_MODULES * module:
            continue
        best, best_d = np.roll(sq, -r, axis=0), d
    return best


@dataclass
class _Track:
    modules: int
    times_ns: list[int]  # the last two sightings
    corners: list[np.ndarray]
    misses: int = 0
    run: int = 0  # tracked sightings since the last decode


@dataclass
class TrackStats:
    """Tracking counters: attempts (live tracks not decoded in a frame and in view), accepted
    sightings, and rejections by reason."""

    attempts: int = 0
    tracked: int = 0
    refine_failed: int = 0  # refinement found no finder edges or failed its self-check
    gated: int = 0  # innovation too large: not the predicted code
    gated_far: int = 0  # ... of them: a corner beyond TRACK_GATE_MODULES of the prediction
    ambiguous: int = 0  # a decoded code where the prediction lies
    pose_gated: int = 0  # accepted here, dropped by the caller (fusion.qr.predict's pose gate)
    square_starts: int = 0  # attempts with a dark square near the prediction (an extra start)
    square_corners: int = 0  # accepted sightings whose corners are the square's (refinement failed)


class CodeTracker:
    """Tracks one camera's codes through frames given in time order (module docstring)."""

    def __init__(
        self,
        camera: CameraModel | None = None,
        checks: RefineChecks = DEFAULT_CHECKS,
        crossings_pass: bool = True,
    ):
        """`crossings_pass`: refinement's first, 50 % crossings pass on the starts (refine_frames;
        the pipeline's track pass: TRACK_CROSSINGS_PASS)."""
        self.camera = camera
        self.checks = checks
        self.crossings_pass = crossings_pass
        self.tracks: dict[str, _Track] = {}
        self.stats = TrackStats()

    def _predict(self, tr: _Track, t_ns: int) -> tuple[np.ndarray, float]:
        c1 = tr.corners[-1]
        if len(tr.corners) < 2 or tr.times_ns[-1] == tr.times_ns[-2]:
            return c1, TRACK_MIN_SIGMA_PX
        v = (c1 - tr.corners[-2]) / (tr.times_ns[-1] - tr.times_ns[-2])
        step = v * (t_ns - tr.times_ns[-1])
        pred = c1 + step
        return pred, TRACK_MIN_SIGMA_PX + TRACK_VELOCITY_SIGMA * float(np.max(np.linalg.norm(step, axis=1)))

    def _in_view(self, corners: np.ndarray, modules: int, shape: tuple[int, int]) -> bool:
        return symbol_in_view(corners, modules, shape)

    def step(
        self,
        image: np.ndarray,
        camera_name: str,
        timestamp_ns: int,
        decoded: list[QRDetection],
        modules: list[int | None],
        predicted: dict[str, tuple[np.ndarray, float, int]] | None = None,
        own_motion: bool = True,
        squares: list[np.ndarray] | None = None,
        locate: bool = True,
    ) -> list[QRDetection]:
        """Tracked detections of this frame (codes not in `decoded`); then update the tracks with
        `decoded` (its codes' modules per side in `modules`, None when unknown) and them.

        `predicted`: payload -> (corners (4, 2) px, 1-sigma px, modules per side) of codes that a
        predicted camera pose puts in view (e.g. the floor grid projected with the pose
        extrapolated from the last PnP poses); preferred to a track's own pixel-motion
        prediction (a pose uses every code of the frame).  `own_motion=False`: only `predicted`
        codes are tried (the pipeline's track pass: a pose predicts every code in view, and the
        pixel-motion prediction once gave a tracked code 2-module-aliased corners).
        `squares`: dark quadrilaterals (4, 2) px found in the frame (module constants
        TRACK_SQUARE_*): starts, and fallback corners, for the predictions they match.
        `locate=False`: the first start is the prediction itself, not the symbol located by its
        function patterns (locate_symbol): for predictions nearer than the locator under heavy
        blur (fusion.qr.predict.TRACK_LOCATE_TWO_SIDED)."""
        t = int(timestamp_ns)
        seen = {d.payload for d in decoded}
        centres = [d.corners_px.mean(axis=0) for d in decoded]
        predicted = predicted or {}
        sources = [
            (p, tr, *self._predict(tr, t))
            for p, tr in self.tracks.items()
            if own_motion and tr.run < TRACK_MAX_RUN and p not in predicted
        ]
        for payload, (corners, sigma, n) in predicted.items():
            tr = self.tracks.get(payload) or _Track(int(n), [], [])
            sources.append((payload, tr, np.asarray(corners, float), float(sigma)))
        candidates = []
        for payload, tr, pred, sigma in sources:
            if payload in seen:
                continue
            if not (np.all(np.isfinite(pred)) and self._in_view(pred, tr.modules, image.shape)):
                continue
            self.stats.attempts += 1
            side = float(np.mean(np.linalg.norm(pred - np.roll(pred, 1, axis=0), axis=1)))
            if any(np.linalg.norm(c - pred.mean(axis=0)) < side for c in centres):
                self.stats.ambiguous += 1
                continue
            candidates.append((payload, tr, pred, sigma))
        out: list[tuple[QRDetection, _Track]] = []
        if candidates:
            # several starts per candidate: refinement's capture range under heavy blur (~2 px)
            # is below a prediction's error; the passing result nearest the prediction is kept
            starts: list[tuple[np.ndarray, int | None]] = []
            spans: list[tuple[int, int]] = []  # each candidate's starts in `starts`
            matched: list[np.ndarray | None] = []  # each candidate's matching dark square
            for _, tr, pred, sigma in candidates:
                side = float(np.mean(np.linalg.norm(pred - np.roll(pred, 1, axis=0), axis=1)))
                radius = min(TRACK_LOCATE_SIGMAS * sigma, TRACK_GATE_MODULES * side / tr.modules)
                found = locate_symbol(image, pred, tr.modules, radius) if locate else None
                at = pred + found[0] if found is not None and found[1] >= TRACK_LOCATE_MIN_NCC else pred
                begin = len(starts)
                starts.append((at, tr.modules))
                starts += [
                    (pred + off * (sigma / TRACK_MIN_SIGMA_PX), tr.modules)
                    for off in TRACK_START_OFFSETS_PX[1:]
                ]
                square = match_square(squares or [], pred, tr.modules)
                matched.append(square)
                if square is not None:
                    self.stats.square_starts += 1
                    starts.append((square, tr.modules))
                spans.append((begin, len(starts)))
            flat = refine_frames(
                [image], [starts], self.camera, checks=self.checks, crossings_pass=self.crossings_pass
            )[0]
            for i, (payload, tr, pred, sigma) in enumerate(candidates):
                begin, end = spans[i]
                passed = [
                    r
                    for r in flat[begin:end]
                    if r is not None
                    and r.stage == 2
                    and r.corner_cov_px2 is not None
                    and r.quality is not None
                ]
                square = matched[i]
                from_square = False
                if passed:
                    # the start at the located symbol (else the prediction) first (a shifted start
                    # can lock onto the finder's 2-module alias under heavy blur), else the
                    # result nearest the prediction
                    first = flat[begin]
                    res = (
                        first
                        if first is not None and first.stage == 2 and first.corner_cov_px2 is not None
                        else min(passed, key=lambda r: _worst_px(r.corners_px, pred))
                    )
                    res_corners, res_cov = res.corners_px, np.asarray(res.corner_cov_px2)
                elif square is not None:
                    res_corners = square
                    res_cov = TRACK_SQUARE_SIGMA_PX**2 * np.eye(8)
                    from_square = True
                else:
                    self.stats.refine_failed += 1
                    continue
                e = (res_corners - pred).reshape(8)
                side = float(np.mean(np.linalg.norm(pred - np.roll(pred, 1, axis=0), axis=1)))
                S = sigma * sigma * np.eye(8) + res_cov
                chi2 = float(e @ np.linalg.solve(S, e))
                worst = float(np.max(np.linalg.norm(e.reshape(4, 2), axis=1)))
                if worst > TRACK_GATE_MODULES * side / tr.modules or chi2 > TRACK_GATE_CHI2:
                    self.stats.gated += 1
                    self.stats.gated_far += worst > TRACK_GATE_MODULES * side / tr.modules
                    continue
                self.stats.tracked += 1
                self.stats.square_corners += from_square
                excess = max(0.0, float(e @ e) / 8 - TRACK_AGREEMENT_SIGMA_PX**2)
                cov = res_cov + excess * np.eye(8)
                det = QRDetection(
                    camera_name,
                    t,
                    payload,
                    res_corners,
                    pred,
                    float(np.sqrt(np.mean(np.diag(cov)))),
                    cov,
                    tracked=True,
                )
                out.append((det, tr))
        self._update(t, decoded, modules, out)
        return [d for d, _ in out]

    def _update(self, t: int, decoded, modules, tracked) -> None:
        sighted = set()
        for d, n in zip(decoded, modules):
            if n is None:
                n = self.tracks[d.payload].modules if d.payload in self.tracks else None
            if n is None:
                continue
            tr = self.tracks.get(d.payload)
            if tr is None:
                tr = self.tracks[d.payload] = _Track(int(n), [], [])
            tr.modules = int(n)
            self._sight(tr, t, d.corners_px)
            tr.run = 0
            sighted.add(d.payload)
        for d, tr_new in tracked:
            tr = self.tracks.setdefault(d.payload, tr_new)
            self._sight(tr, t, d.corners_px)
            tr.run += 1
            sighted.add(d.payload)
        for payload in list(self.tracks):
            if payload not in sighted:
                self.tracks[payload].misses += 1
                if self.tracks[payload].misses > TRACK_MAX_MISSES:
                    del self.tracks[payload]

    @staticmethod
    def _sight(tr: _Track, t: int, corners: np.ndarray) -> None:
        tr.times_ns = (tr.times_ns + [t])[-2:]
        tr.corners = (tr.corners + [np.asarray(corners, dtype=float).copy()])[-2:]
        tr.misses = 0
