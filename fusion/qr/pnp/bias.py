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
from fusion.geometry import cross_rows
from fusion.qr.codes import FloorSighting
from fusion.qr.pnp.whitening import CORNER_CLASSES, CORNER_COORDINATES, corner_classes, floor_whitening
from fusion.qr.reprojection import Projector
from fusion.world import FloorLayout, Placement

SIZE_BIN_EDGES_PX: tuple[float, ...] = tuple(32.0 * 2.0 ** (k / 2) for k in range(1, 7))
"""Edges (px) of the code-size bins, a factor sqrt(2) apart from 45 to 256 px (the code's mean
side length in the image): each bin has its own dilation, since the edge model's error depends
on the blur against the module size (defocus r 1, 60 s seed 2: b_v +0.012 px with the codes at
~85 px, -0.002 px at ~55 px; BENCHMARKS.md, eighth session).  A 12 s flight at one height uses one or two."""
N_BINS = len(SIZE_BIN_EDGES_PX) + 1
BIN_PARAMS = ("dilation_u_px", "dilation_v_px")
"""Per size bin: the outward edge moves of the left / right and the top / bottom edges (px)."""
N_PARAMS = len(BIN_PARAMS) * N_BINS
"""Length of the bias vector b: BIN_PARAMS of bin 0, then of bin 1, ..."""


def bin_range_px(j: int) -> tuple[float, float]:
    """(low, high) code side in px of size bin j."""
    edges = (0.0, *SIZE_BIN_EDGES_PX, float("inf"))
    return edges[j], edges[j + 1]


def size_bins(corners_px: np.ndarray) -> np.ndarray:
    """(n,) size bins (SIZE_BIN_EDGES_PX) of codes whose corners are `corners_px` (n, 4, 2): by
    the mean side length of the corner quadrilateral."""
    c = np.asarray(corners_px, dtype=float).reshape(-1, 4, 2)
    side = np.linalg.norm(np.roll(c, -1, axis=1) - c, axis=2).mean(axis=1)
    return np.searchsorted(SIZE_BIN_EDGES_PX, side, side="right")


def size_bin(corners_px: np.ndarray) -> int:
    """`size_bins` of one code, corners (4, 2)."""
    return int(size_bins(corners_px)[0])


_DECODER = CORNER_CLASSES.index("decoder")


def dilation_patterns(corners_px: np.ndarray) -> np.ndarray:
    """(n, 8, 2) corner offsets [TL u, TL v, ..., BL v] (px) per unit (b_u, b_v) of outward edge
    move, for codes whose corners are `corners_px` (n, 4, 2): edge j (corner j to j + 1) moves by
    b_u n_u^2 + b_v n_v^2 along its outward unit normal n, and corner i (edges a = i - 1 and
    b = i) solves n_a . d = move_a, n_b . d = move_b (Cramer's rule)."""
    c = np.asarray(corners_px, dtype=float).reshape(-1, 4, 2)
    e = np.roll(c, -1, axis=1) - c  # edge j: corner j -> j + 1
    nrm = np.stack([e[..., 1], -e[..., 0]], axis=-1) / np.linalg.norm(e, axis=-1, keepdims=True)
    mid = 0.5 * (c + np.roll(c, -1, axis=1))
    outward = np.einsum("nji,nji->nj", nrm, mid - c.mean(axis=1, keepdims=True))
    nrm = np.where(outward[..., None] < 0, -nrm, nrm)
    na, nb = np.roll(nrm, 1, axis=1), nrm  # (n, 4, 2): the edges before and after corner i
    det = na[..., 0] * nb[..., 1] - na[..., 1] * nb[..., 0]  # (n, 4)
    out = np.empty((len(c), 4, 2, 2))  # [code, corner, u / v of d, b_u / b_v]
    for k in range(2):  # rhs (na_k^2, nb_k^2)
        ra, rb = na[..., k] ** 2, nb[..., k] ** 2
        out[:, :, 0, k] = (nb[..., 1] * ra - na[..., 1] * rb) / det
        out[:, :, 1, k] = (na[..., 0] * rb - nb[..., 0] * ra) / det
    return out.reshape(len(c), CORNER_COORDINATES, 2)


def dilation_pattern(corners_px: np.ndarray) -> np.ndarray:
    """`dilation_patterns` of one code: (8, 2) for corners (4, 2)."""
    return dilation_patterns(corners_px)[0]


@dataclass
class FrameBiasTerms:
    """One posed frame's share of the flight's bias estimate (p = N_PARAMS), kept compact: only
    the parameters of the size bins its codes fall in (`params`, q of them; the other rows and
    columns are exactly zero), so that a long flight's terms stay small (a dense frame took
    ~2.9 kB: 30 minutes of floor frames raised `fusion run`'s peak by ~90 MiB).

    `normal` (p, p) A^T M A and `rhs` (p,) A^T M r, with A the whitened bias columns, r the
    whitened residual (observed - predicted) at the PnP pose and M = I - J (J^T J)^-1 J^T (J the
    whitened pose Jacobian): the bias normal equations with the pose eliminated.
    `sensitivity` (6, p) S = (J^T J)^-1 J^T A: the PnP pose's error, body-frame right
    perturbation [rx, ry, rz, tx, ty, tz], per unit of bias (first order: xi_est = xi_true + S b).
    Stored: `params` (q,), `normal_q` (q, q), `rhs_q` (q,), `sensitivity_q` (6, q).
    `intrinsics_sensitivity` (6, 4) float32: the PnP pose's error per px of error in the stated
    [fu, fv, cu, cv] (xi_est = xi_true + S_K (stated - true)); None when the camera states its
    intrinsics exact."""

    params: np.ndarray
    normal_q: np.ndarray
    rhs_q: np.ndarray
    sensitivity_q: np.ndarray
    intrinsics_sensitivity: np.ndarray | None = None

    @property
    def normal(self) -> np.ndarray:
        out = np.zeros((N_PARAMS, N_PARAMS))
        out[np.ix_(self.params, self.params)] = self.normal_q
        return out

    @property
    def rhs(self) -> np.ndarray:
        out = np.zeros(N_PARAMS)
        out[self.params] = self.rhs_q
        return out

    @property
    def sensitivity(self) -> np.ndarray:
        out = np.zeros((6, N_PARAMS))
        out[:, self.params] = self.sensitivity_q
        return out


@dataclass
class FrameCodeResiduals:
    """One posed frame's corner residuals per code, whitened as PnP whitens them (observed -
    predicted at the frame's PnP pose, W (z - h), identity covariance when the corner model is
    right): `payloads` (n,), `classes` (n,) index into whitening.CORNER_CLASSES, `whitened`
    (n, 8) [TL u, TL v, ..., BL v].  For the time correlation of each class's corner errors
    (fusion.estimate.correlation): the same code's residuals in consecutive frames."""

    payloads: tuple[str, ...]
    classes: np.ndarray
    whitened: np.ndarray


INTRINSICS = ("fu", "fv", "cu", "cv")


def intrinsics_patterns(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """(n, 8, 4) d corner px / d [fu, fv, cu, cv] at the projected corners `uv` (n, 4, 2): u = fu
    x_d + cu, v = fv y_d + cv with x_d, y_d the distorted normalised coordinates."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 4, 2)
    out = np.zeros((len(uv), 4, 2, len(INTRINSICS)))
    out[:, :, 0, 0] = (uv[..., 0] - camera.cu) / camera.fu
    out[:, :, 1, 1] = (uv[..., 1] - camera.cv) / camera.fv
    out[:, :, 0, 2] = 1.0
    out[:, :, 1, 3] = 1.0
    return out.reshape(len(uv), CORNER_COORDINATES, len(INTRINSICS))


def frame_bias_terms(
    camera: CameraModel, sightings: list[FloorSighting], T_world_body: np.ndarray, corner_sigma_px: float
) -> FrameBiasTerms | None:
    """`FrameBiasTerms` of the floor codes `sightings` used by a PnP pose `T_world_body`
    (whitened as PnP whitens them: corner_whitening); None when the pose's information is singular."""
    return frames_bias_terms(camera, [sightings], np.asarray(T_world_body)[None], corner_sigma_px)[0]


def frames_bias_terms(
    camera: CameraModel, frames: list[list[FloorSighting]], T_world_body: np.ndarray, corner_sigma_px: float
) -> list[FrameBiasTerms | None]:
    """`frame_bias_terms` of many frames at once (frames (F,) lists of sightings, T_world_body
    (F, 4, 4)): `frames_bias_and_residuals`' first list."""
    return frames_bias_and_residuals(camera, frames, T_world_body, corner_sigma_px)[0]


def frames_bias_and_residuals(
    camera: CameraModel,
    frames: list[list[FloorSighting]],
    T_world_body: np.ndarray,
    corner_sigma_px: float,
    placement: Placement | FloorLayout | None = None,
) -> tuple[list[FrameBiasTerms | None], list[FrameCodeResiduals]]:
    """Per posed frame (frames (F,) lists of the sightings each pose used, T_world_body
    (F, 4, 4)): its `FrameBiasTerms` (None when the pose's information is singular) and its
    `FrameCodeResiduals`, from one reprojection of all codes.  The codes' whitening, patterns and
    Jacobians are computed together (the reprojection is
    fusion.qr.reprojection.floor_reprojection's, per code's own pose), the per-frame sums by
    code, and the 6 x 6 solves batched.  `placement`: the codes' placement sigma, whitened as
    PnP whitens it (`floor_whitening`)."""
    F, k, p = len(frames), len(BIN_PARAMS), N_PARAMS
    if not F:
        return [], []
    sightings = [s for f in frames for s in f]
    frame_of = np.repeat(np.arange(F), [len(f) for f in frames])  # (n,) each code's frame
    dets = [s.detection for s in sightings]
    W = floor_whitening(sightings, corner_sigma_px, placement, camera)  # (n, 8, 8)
    corners = np.stack([np.asarray(d.corners_px, dtype=float) for d in dets])  # (n, 4, 2)
    # floor_reprojection, each code at its frame's pose: p_body = R^T (P - t)
    T = np.asarray(T_world_body, dtype=float)[frame_of]  # (n, 4, 4)
    P = np.stack([s.corners_world for s in sightings])  # (n, 4, 3)
    p_body = np.einsum("nqi,nij->nqj", P - T[:, None, :3, 3], T[:, :3, :3]).reshape(-1, 3)
    T_bc = np.asarray(camera.T_body_cam, dtype=float)
    uv, J_proj = Projector(camera).project((p_body - T_bc[:3, 3]) @ T_bc[:3, :3])
    A = J_proj @ T_bc[:3, :3].T  # d px / d p_body
    J = np.concatenate([cross_rows(A, p_body), -A], axis=2).reshape(-1, CORNER_COORDINATES, 6)
    Jw = W @ J  # (n, 8, 6)
    rw = np.einsum("nij,nj->ni", W, (corners - uv.reshape(-1, 4, 2)).reshape(-1, CORNER_COORDINATES))
    classes = np.asarray(corner_classes(dets), dtype=np.int8)
    starts = np.r_[0, np.cumsum([len(f) for f in frames])]
    residuals = [
        FrameCodeResiduals(
            tuple(d.payload for d in dets[a:b]), classes[a:b].copy(), rw[a:b].astype(np.float32)
        )
        for a, b in zip(starts[:-1], starts[1:])
    ]
    refined = classes != _DECODER
    Pw = (W @ dilation_patterns(corners)) * refined[:, None, None]  # (n, 8, k)
    bins = size_bins(corners)
    H = np.zeros((F, 6, 6))
    np.add.at(H, frame_of, np.swapaxes(Jw, 1, 2) @ Jw)
    Jtr = np.zeros((F, 6))
    np.add.at(Jtr, frame_of, np.einsum("nij,ni->nj", Jw, rw))
    JtA_bins = np.zeros((F, N_BINS, 6, k))
    np.add.at(JtA_bins, (frame_of, bins), np.swapaxes(Jw, 1, 2) @ Pw)
    AtA = np.zeros((F, N_BINS, k, k))
    np.add.at(AtA, (frame_of, bins), np.swapaxes(Pw, 1, 2) @ Pw)
    Atr = np.zeros((F, N_BINS, k))
    np.add.at(Atr, (frame_of, bins), np.einsum("nij,ni->nj", Pw, rw))
    JtA = np.moveaxis(JtA_bins, 2, 1).reshape(F, 6, p)  # columns: bin 0's k, bin 1's k, ...
    # the intrinsics (every corner's, decoder fallbacks too): a stated value off by d moves the
    # predicted corners by D d, so the pose by -(J^T J)^-1 J^T D d; not for intrinsics stated
    # exact, whose consider term is none (cornerbias.intrinsics_consider)
    with_intrinsics = bool(np.any(camera.intrinsics_sigmas > 0.0))
    JtD = np.zeros((F, 6, len(INTRINSICS)))
    if with_intrinsics:
        np.add.at(JtD, frame_of, np.swapaxes(Jw, 1, 2) @ (W @ intrinsics_patterns(camera, uv)))
    if camera.gimbaled:
        # the pose is the level frame, conditioned on its roll = pitch = 0 (floor.condition_on_level):
        # the gimbal's attitude as information on [rx, ry], or, known exactly, those two fixed
        sigma = camera.mount_sigmas[0]
        if sigma > 0.0:
            H[:, :2, :2] += np.eye(2) / sigma**2
        else:
            H[:, :2, :] = 0.0
            H[:, :, :2] = 0.0
            H[:, 0, 0] = H[:, 1, 1] = 1.0
            JtA[:, :2, :] = 0.0
            JtD[:, :2, :] = 0.0
            Jtr[:, :2] = 0.0
    AtA_full = np.zeros((F, p, p))
    for j in range(N_BINS):  # block diagonal: a code's columns are its own bin's
        AtA_full[:, k * j : k * j + k, k * j : k * j + k] = AtA[:, j]
    out: list[FrameBiasTerms | None] = [None] * F
    ok = np.linalg.matrix_rank(H) == 6
    if not ok.any():
        return out, residuals
    S = np.linalg.solve(H[ok], JtA[ok])  # (m, 6, p) = H^-1 J^T A
    S_K = (
        -np.linalg.solve(H[ok], JtD[ok]).astype(np.float32)  # (m, 6, 4)
        if with_intrinsics
        else [None] * int(ok.sum())
    )
    N = AtA_full[ok] - np.swapaxes(JtA[ok], 1, 2) @ S  # A^T M A
    y = Atr.reshape(F, p)[ok] - np.einsum("mip,mi->mp", S, Jtr[ok])  # A^T M r
    has_bin = np.zeros((F, N_BINS), dtype=bool)
    has_bin[frame_of, bins] = True
    for f, S_f, N_f, y_f, K_f in zip(np.flatnonzero(ok), S, N, y, S_K):
        if np.all(np.isfinite(S_f)) and (K_f is None or np.all(np.isfinite(K_f))):
            # the bins without codes have zero columns in A, hence in S, N and y: left out
            q = (k * np.flatnonzero(has_bin[f])[:, None] + np.arange(k)).ravel()
            out[f] = FrameBiasTerms(q, N_f[np.ix_(q, q)], y_f[q], S_f[:, q], K_f)
    return out, residuals
