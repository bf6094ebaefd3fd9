"""A corner bias common to every frame of a flight, seen through the per-frame PnP residuals
(issue 10.3, BENCHMARKS.md "Defocus σ"): per posed frame, the normal equations of the bias
reduced by the pose (a Schur complement) and the pose's first-order sensitivity to the bias.
The flight-level estimate, its significance and its use are fusion.estimate.cornerbias.

Bias model, b (N_PARAMS,) in px: every refined code's four edges move outward along their
image normal n by b_u n_u^2 + b_v n_v^2 (a code that looks wider / taller: an edge-spread model
that does not match the lens's blur, e.g. the refinement's box PSF against a disc), each corner
where its two moved edges meet (`dilation_pattern`), with one (b_u, b_v) per code-size bin
(SIZE_BIN_EDGES_PX); decoder-fallback corners (whole-pixel decoder output,
whitening.CORNER_CLASSES "decoder") carry no dilation.  A common image shift is
left out: a pose rotation absorbs it almost wholly, and its estimate only adds noise."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.camera import CameraModel
from fusion.qr.codes import FloorSighting
from fusion.qr.pnp.whitening import CORNER_CLASSES, CORNER_COORDINATES, corner_classes, corner_whitening
from fusion.qr.reprojection import floor_reprojection

SIZE_BIN_EDGES_PX: tuple[float, ...] = tuple(32.0 * 2.0 ** (k / 2) for k in range(1, 7))
"""Edges (px) of the code-size bins, a factor sqrt(2) apart from 45 to 256 px (the code's mean
side length in the image): each bin has its own dilation, since the edge model's error depends
on the blur against the module size (defocus r 1, 60 s seed 2: b_v +0.012 px with the codes at
~85 px, -0.002 px at ~55 px; NOTES-bias.md).  A 12 s flight at one height uses one or two."""
N_BINS = len(SIZE_BIN_EDGES_PX) + 1
BIN_PARAMS = ("dilation_u_px", "dilation_v_px")
"""Per size bin: the outward edge moves of the left / right and the top / bottom edges (px)."""
N_PARAMS = len(BIN_PARAMS) * N_BINS
"""Length of the bias vector b: BIN_PARAMS of bin 0, then of bin 1, ..."""


def bin_range_px(j: int) -> tuple[float, float]:
    """(low, high) code side in px of size bin j."""
    edges = (0.0, *SIZE_BIN_EDGES_PX, float("inf"))
    return edges[j], edges[j + 1]


def size_bin(corners_px: np.ndarray) -> int:
    """The size bin (SIZE_BIN_EDGES_PX) of a code whose corners are `corners_px` (4, 2)."""
    c = np.asarray(corners_px, dtype=float).reshape(4, 2)
    side = float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))
    return int(np.searchsorted(SIZE_BIN_EDGES_PX, side, side="right"))


_DECODER = CORNER_CLASSES.index("decoder")


def dilation_pattern(corners_px: np.ndarray) -> np.ndarray:
    """(8, 2) corner offsets [TL u, TL v, ..., BL v] (px) per unit (b_u, b_v) of outward edge
    move, for a code whose corners are `corners_px` (4, 2): edge j (corner j to j + 1) moves by
    b_u n_u^2 + b_v n_v^2 along its outward unit normal n, and corner i (edges i - 1 and i)
    solves n_a . d = move_a, n_b . d = move_b."""
    c = np.asarray(corners_px, dtype=float).reshape(4, 2)
    centre = c.mean(axis=0)
    normals = []
    for j in range(4):
        e = c[(j + 1) % 4] - c[j]
        n = np.array([e[1], -e[0]]) / np.linalg.norm(e)
        if n @ (0.5 * (c[j] + c[(j + 1) % 4]) - centre) < 0:
            n = -n
        normals.append(n)
    out = np.zeros((CORNER_COORDINATES, len(BIN_PARAMS)))
    for i in range(4):
        na, nb = normals[(i - 1) % 4], normals[i]
        out[2 * i : 2 * i + 2] = np.linalg.solve(np.array([na, nb]), np.array([na**2, nb**2]))
    return out


@dataclass
class FrameBiasTerms:
    """One posed frame's share of the flight's bias estimate (p = N_PARAMS).

    `normal` (p, p) A^T M A and `rhs` (p,) A^T M r, with A the whitened bias columns, r the
    whitened residual (observed - predicted) at the PnP pose and M = I - J (J^T J)^-1 J^T (J the
    whitened pose Jacobian): the bias normal equations with the pose eliminated.
    `sensitivity` (6, p) S = (J^T J)^-1 J^T A: the PnP pose's error, body-frame right
    perturbation [rx, ry, rz, tx, ty, tz], per unit of bias (first order: xi_est = xi_true + S b)."""

    normal: np.ndarray
    rhs: np.ndarray
    sensitivity: np.ndarray


def frame_bias_terms(
    camera: CameraModel, sightings: list[FloorSighting], T_world_body: np.ndarray, corner_sigma_px: float
) -> FrameBiasTerms | None:
    """`FrameBiasTerms` of the floor codes `sightings` used by a PnP pose `T_world_body`
    (whitened as PnP whitens them: corner_whitening); None when the pose's information is singular."""
    p = N_PARAMS
    dets = [s.detection for s in sightings]
    W = corner_whitening(dets, corner_sigma_px)
    uv, J = floor_reprojection(camera, T_world_body, np.vstack([s.corners_world for s in sightings]))
    n = len(sightings)
    Jw = np.empty((CORNER_COORDINATES * n, 6))
    Aw = np.zeros((CORNER_COORDINATES * n, p))
    r = np.empty(CORNER_COORDINATES * n)
    classes = corner_classes(dets)
    for i, (d, cls) in enumerate(zip(dets, classes)):
        rows = slice(CORNER_COORDINATES * i, CORNER_COORDINATES * (i + 1))
        z = np.asarray(d.corners_px, dtype=float).reshape(-1)
        Jw[rows] = W[i] @ J[rows]
        r[rows] = W[i] @ (z - uv[4 * i : 4 * i + 4].reshape(-1))
        if cls != _DECODER:
            j = len(BIN_PARAMS) * size_bin(d.corners_px)
            Aw[rows, j : j + len(BIN_PARAMS)] = W[i] @ dilation_pattern(d.corners_px)
    H = Jw.T @ Jw
    try:
        S = np.linalg.solve(H, Jw.T @ Aw)  # (6, p)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(S)):
        return None
    A_red = Aw - Jw @ S  # M A
    return FrameBiasTerms(A_red.T @ Aw, A_red.T @ r, S)
