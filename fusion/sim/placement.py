"""Floor codes stuck down off their nominal grid (issue #12, item 1), and synthetic per-code
sightings for benchmarks and tests that do not render.

`placement_offsets` draws each code's true pose error (dx, dy, dyaw) ~ N(0, diag(s_m, s_m, s_rad)^2)
from its own seeded generator, so a warehouse is the same for a seed whatever the flight.
`synthetic_sightings` gives, for each frame of a true trajectory, the codes under the floor camera
with the relative pose T_code_body a single-code PnP would measure (truth * Exp(n), n ~ N(0, cov)),
and the joint per-frame pose PnP would compute from the NOMINAL code poses.
"""

from __future__ import annotations

import numpy as np

from fusion.estimate.asbuilt import AsBuiltInput, CodePrior, CodeSightings, Placement, code_prior_cov
from fusion.geometry import adjoint, inv_T, make_T, rot_z, se3_exp, se3_log

__all__ = ["placement_offsets", "synthetic_sightings", "true_code_poses"]

STREAM_PLACEMENT = 4
"""Generator stream of the placement errors (fusion.sim.simulate's streams are 1-3)."""
SIGHTING_RADIUS_PER_HEIGHT = 0.45
"""A code is in the synthetic floor camera's view when its centre lies closer than this times
the body's height to the point below the body (60 deg field of view: tan 30 deg = 0.58, less
the code's own half side)."""


def placement_offsets(n: int, sigma_m: float, sigma_rad: float, seed: int) -> np.ndarray:
    """(n, 3) true offsets (dx m, dy m, dyaw rad) of n codes from their nominal poses."""
    rng = np.random.default_rng([int(seed), STREAM_PLACEMENT])
    z = rng.standard_normal((n, 3))
    return z * np.array([sigma_m, sigma_m, sigma_rad])


def true_code_poses(nominal_xy_m: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(n, 4, 4) T_world_code of codes at nominal (x, y) (n, 2) m moved by offsets (n, 3)."""
    nominal_xy_m = np.asarray(nominal_xy_m, float).reshape(-1, 2)
    out = np.empty((len(nominal_xy_m), 4, 4))
    for i, ((x, y), (dx, dy, dyaw)) in enumerate(zip(nominal_xy_m, np.asarray(offsets, float))):
        out[i] = make_T(rot_z(float(dyaw)), np.array([x + dx, y + dy, 0.0]))
    return out


def synthetic_sightings(
    frame_t_ns: np.ndarray,
    T_world_body: np.ndarray,
    ids: list[str],
    nominal_xy_m: np.ndarray,
    T_world_code_true: np.ndarray,
    cov: np.ndarray,
    placement: Placement,
    rng: np.random.Generator,
    radius_per_height: float = SIGHTING_RADIUS_PER_HEIGHT,
    placement_in_fixes: bool = False,
) -> tuple[AsBuiltInput, np.ndarray, np.ndarray, np.ndarray]:
    """Per-code sightings and the joint per-frame poses of a floor whose codes lie at
    T_world_code_true.  Returns (AsBuiltInput with payload priors, frame indices with a fix (M,),
    raw T_world_body (M, 4, 4) computed from the nominal poses (the mean of the codes' in
    tangent space), raw covariances (M, 6, 6) = cov / codes in view, plus, with
    `placement_in_fixes`, the placement's share as PnP states it (fusion.qr.pnp.whitening): the
    mean of the n codes' placement errors, each moving the body by Ad(T_code_body^-1) delta, so
    (1 / n^2) sum_c Ad P_prior Ad^T)."""
    nominal_xy_m = np.asarray(nominal_xy_m, float).reshape(-1, 2)
    L = np.linalg.cholesky(cov)
    T_nom = np.array([make_T(np.eye(3), np.array([x, y, 0.0])) for x, y in nominal_xy_m])
    inv_true = np.array([inv_T(T) for T in T_world_code_true])
    prior_cov = code_prior_cov(placement.sigma_m, placement.sigma_rad)
    t_s, c_s, T_s = [], [], []
    fix_k, fix_T, fix_cov = [], [], []
    for k, T in enumerate(T_world_body):
        d = np.linalg.norm(nominal_xy_m - T[:2, 3], axis=1)
        seen = np.flatnonzero(d < radius_per_height * T[2, 3])
        if not len(seen):
            continue
        poses = []
        placed = np.zeros((6, 6))
        for c in seen.tolist():
            T_cb = inv_true[c] @ T @ se3_exp(L @ rng.standard_normal(6))
            t_s.append(int(frame_t_ns[k]))
            c_s.append(c)
            T_s.append(T_cb)
            poses.append(T_nom[c] @ T_cb)
            if placement_in_fixes:
                Ad = adjoint(inv_T(T_cb))
                placed += Ad @ prior_cov @ Ad.T
        ref = poses[0]
        xi = se3_log(np.array([inv_T(ref) @ P for P in poses])).mean(axis=0)
        fix_k.append(k)
        fix_T.append(ref @ se3_exp(xi))
        fix_cov.append(cov / len(seen) + placed / len(seen) ** 2)
    codes = [CodePrior(cid, T_nom[i], T_nom[i], prior_cov) for i, cid in enumerate(ids)]
    S = len(t_s)
    sightings = CodeSightings(
        np.array(t_s, dtype=np.int64),
        np.array(c_s, dtype=np.int64),
        np.array(T_s).reshape(S, 4, 4),
        np.repeat(cov[None], S, axis=0),
    )
    return (
        AsBuiltInput(codes, sightings, placement),
        np.array(fix_k, dtype=np.int64),
        np.array(fix_T).reshape(-1, 4, 4),
        np.array(fix_cov).reshape(-1, 6, 6),
    )
