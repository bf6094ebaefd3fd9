"""As-built floor codes (issue #12, item 1): each floor code's pose is a variable of the batch
smoother, so codes stuck down centimetres off their nominal grid are estimated, not trusted.

Model.  Floor code c has a Pose3 variable F(c) = T_world_code (symbol frame, DESIGN.md: flat,
axes along the world's).  Its prior is the payload's nominal pose (or a merged map's estimate,
`fusion run --map`) with sigmas [tilt, tilt, yaw, x, y, z] (GTSAM's Pose3 order, code frame):
x, y from world.yaml's `placement_sigma_m`, yaw from `placement_sigma_deg`, tilt and height
nearly fixed (FLOOR_TILT_SIGMA_RAD, FLOOR_Z_SIGMA_M: a code glued to a flat floor).

Each sighting (code c in floor frame k) is a relative-pose factor: PnP on that code's four
corners alone, with the code at its nominal pose, gives T_world_body' and its covariance
(J^T W J)^-1 (body frame, right perturbation; fusion/qr/pnp/floor.py); the camera-to-code
measurement is then T_code_body = T_world_nominal^-1 T_world_body' (the camera mount is inside
PnP's model), with the same covariance, and

    BetweenFactorPose3(F(c), X(k), T_code_body, Sigma_pnp)
    error = Log(T_code_body^-1 F(c)^-1 X(k))     (GTSAM BetweenFactor, body-frame tangent)

replaces the frame's joint PnP pose factor (to first order the joint PnP's information is the
sum of its codes', so a perfectly laid floor gives the same solution).  A placement sigma of 0
(both m and deg) switches the model off: the smoother is today's, factor for factor.

Misplaced: a code whose estimated offset from nominal (x, y) is beyond MISPLACED_SIGMAS in
Mahalanobis distance (its posterior covariance) and longer than MISPLACED_MIN_OFFSET_M.

Gauge: the grid's common shift and rotation are seen only through the priors (the drone sees
codes relative to each other), so a floor whose codes are all off the same way is not flagged.
Not in the incremental smoother or the EKF (they keep the nominal codes), nor with a gimbaled
floor camera (its PnP gives a level pose) or `--tight` (corner factors).
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import D, F

from fusion.camera import CameraModel
from fusion.conventions import FloorPayload, floor_payload, parse_payload
from fusion.errors import EstimationError, FusionError
from fusion.estimate.common import match_to_frames
from fusion.estimate.factors import X, robust
from fusion.estimate.marginals import chain_marginals
from fusion.evaluate.metrics import umeyama_alignment
from fusion.fileio import atomic_open, csv_safe, csv_unsafe
from fusion.geometry import adjoint, inv_T, make_T, rot_z, se3_exp, se3_log, wrap_angle, yaw_of
from fusion.qr.codes import FloorSighting
from fusion.qr.pnp import estimate_floor_poses
from fusion.types import Trajectory
from fusion.world import DEFAULT_PLACEMENT_SIGMA_DEG, DEFAULT_PLACEMENT_SIGMA_M, Placement, World

__all__ = [
    "DEFAULT_PLACEMENT_SIGMA_DEG",
    "DEFAULT_PLACEMENT_SIGMA_M",
    "AsBuiltInput",
    "CodePrior",
    "CodeSightings",
    "FloorCodeEstimate",
    "FloorCodeMap",
    "Placement",
    "add_factors",
    "build_input",
    "code_prior_cov",
    "common_shift",
    "common_shift_covs",
    "correlation_cells",
    "floor_code_estimates",
    "merge_window_maps",
    "shared_cells",
    "read_floor_code_rows",
    "read_floor_codes_csv",
    "read_groundtruth_csv",
    "shift_jacobians",
    "sightings_from_frames",
    "write_floor_codes_csv",
    "write_groundtruth_csv",
    "xy_yaw_cov_to_pose_cov",
]

log = logging.getLogger(__name__)

FLOOR_Z_SIGMA_M = 1e-4
"""Prior sigma of a floor code's height (it lies on the floor, z = 0)."""
FLOOR_TILT_SIGMA_RAD = 1e-4
"""Prior sigma of a floor code's roll and pitch (flat floor)."""
OWN_PART_MIN = 0.01
"""A map code's own part of its prior covariance is at least this share of it (own_part)."""
SHIFT_HELD_SIGMA = 1e-5
"""Sigma (rad, m) of the map shift's tilt and height: a floor shift is planar."""
SHIFT_KEY = D(0)
"""The variable of a merged map's common shift (AsBuiltInput.shift_cov), a Pose3."""
ZERO_SIGMA_FLOOR = 1e-6
"""A placement sigma of 0 next to a non-zero one (m or rad): the 0 axis is held this tightly."""
MISPLACED_SIGMAS = 3.0
"""A code is misplaced when its offset is beyond this many sigma (2-D Mahalanobis distance) ..."""
MISPLACED_MIN_OFFSET_M = 0.02
"""... and longer than this."""
SIGHTINGS_PER_PNP_CALL = 4096
"""Single-code PnP of the sightings (sightings_from_frames) this many at a time: one call of the
whole flight's took +327 MB at its peak on a 10-minute flight (34,865 sightings)."""
FLOOR_CODES_CSV = "floor_codes_{}.csv"
FLOOR_CODES_GROUNDTRUTH_CSV = "floor_codes_groundtruth.csv"
SHARED_COLUMNS = [
    "prior_x_m",
    "prior_y_m",
    "prior_yaw_deg",
    "prior_sigma_x_m",
    "prior_sigma_y_m",
    "prior_sigma_yaw_deg",
    "shared_sigma_x_m",
    "shared_sigma_y_m",
    "shared_sigma_yaw_deg",
]
"""What a code's estimate shares with every other flight's: the prior it started from (its
payload with world.yaml's placement sigma, or `--map`'s) and the floor's common shift, which only
the priors fix (module docstring, "Gauge"); `fusion map merge` counts both once
(fusion.warehouse.floorcodes.merge_floor_codes).  Empty in files written before them."""
CORRELATION_COLUMNS = ["corr_x_y", "corr_x_yaw", "corr_y_yaw"]
"""The x-y, x-yaw and y-yaw correlation coefficients of a code's estimate: the floor's common
rotation moves x and y with yaw by the code's lever arm, which per-axis sigma alone drop."""
FLOOR_CODE_COLUMNS = [
    "id",
    "nominal_x_m",
    "nominal_y_m",
    "x_m",
    "y_m",
    "z_m",
    "yaw_deg",
    "offset_x_m",
    "offset_y_m",
    "offset_m",
    "offset_yaw_deg",
    "sigma_x_m",
    "sigma_y_m",
    "sigma_yaw_deg",
    "n_obs",
    "misplaced",
    *SHARED_COLUMNS,
    "shift_group",
    *CORRELATION_COLUMNS,
]
"""`shift_group`: the codes of one file with the same number carry the same common shift (one
solve's: a long flight's window, merge_window_maps); empty or absent: 0, one solve.
CORRELATION_COLUMNS: the correlation coefficients of x, y, yaw (with the sigma columns, the full
3 x 3 covariance; empty or absent: 0)."""
GROUNDTRUTH_COLUMNS = ["id", "x_m", "y_m", "yaw_deg"]


class AsBuiltError(FusionError):
    """A floor-code map or ground-truth file that cannot be read."""


# =========================================================================== inputs


def code_prior_cov(sigma_m: float, sigma_rad: float) -> np.ndarray:
    """(6, 6) prior covariance of F(c), Pose3 order [rx, ry, rz, tx, ty, tz], code frame."""
    s_m, s_r = max(sigma_m, ZERO_SIGMA_FLOOR), max(sigma_rad, ZERO_SIGMA_FLOOR)
    return np.diag(np.square([FLOOR_TILT_SIGMA_RAD, FLOOR_TILT_SIGMA_RAD, s_r, s_m, s_m, FLOOR_Z_SIGMA_M]))


def xy_yaw_cov_to_pose_cov(T_world_code: np.ndarray, cov_xyyaw: np.ndarray) -> np.ndarray:
    """(6, 6) Pose3 covariance (code frame) from a world (x, y, yaw) covariance; tilt and height
    get the flat-floor sigmas."""
    R2 = rot_z(float(yaw_of(T_world_code[:3, :3])))[:2, :2]
    C = np.diag(np.square([FLOOR_TILT_SIGMA_RAD, FLOOR_TILT_SIGMA_RAD, 0.0, 0.0, 0.0, FLOOR_Z_SIGMA_M]))
    C[3:5, 3:5] = R2.T @ cov_xyyaw[:2, :2] @ R2
    C[2, 2] = cov_xyyaw[2, 2]
    C[2, 3:5] = C[3:5, 2] = R2.T @ cov_xyyaw[:2, 2]
    return C


def pose_cov_to_xy_yaw_cov(T_world_code: np.ndarray, cov6: np.ndarray) -> np.ndarray:
    """(3, 3) world (x, y, yaw) covariance of a code from its Pose3 covariance (code frame)."""
    R = T_world_code[:3, :3]
    J = np.zeros((3, 6))
    J[:2, 3:] = R[:2, :]  # world translation = R dt
    J[2, 2] = 1.0  # yaw of a flat code: its z rotation
    return J @ cov6 @ J.T


@dataclass
class CodePrior:
    """One floor code: id (canonical payload), nominal pose from the payload, prior mean and
    covariance (Pose3 order, code frame)."""

    code_id: str
    T_world_nominal: np.ndarray  # (4, 4)
    T_world_prior: np.ndarray  # (4, 4)
    cov_prior: np.ndarray  # (6, 6)
    from_map: bool = False
    # (6, 6): the prior's own part when the code's map shares a common shift (AsBuiltInput.
    # shift_cov): its prior then hangs from that shift's variable (add_factors)
    cov_own: np.ndarray | None = None


@dataclass
class CodeSightings:
    """Single-code PnP of every floor sighting: timestamps_ns (S,), code (S,) index into the
    codes, T_code_body (S, 4, 4), cov (S, 6, 6) body-frame right perturbation (Pose3 order)."""

    timestamps_ns: np.ndarray
    code: np.ndarray
    T_code_body: np.ndarray
    cov: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps_ns)


@dataclass
class AsBuiltInput:
    """What the batch smoother needs for the as-built floor codes."""

    codes: list[CodePrior]
    sightings: CodeSightings
    placement: Placement
    notes: list[str] = field(default_factory=list)
    # (6, 6) Pose3 covariance (world frame, at the identity) of the map's common shift D, which
    # every code with a cov_own shares (map_shift_cov); None: the priors are independent
    shift_cov: np.ndarray | None = None


@dataclass
class PriorMap:
    """A merged floor-code map used as the prior: id -> ((3,) x, y, yaw; (3, 3) covariance)."""

    codes: dict[str, tuple[np.ndarray, np.ndarray]]
    source: str = ""
    # each code's share of the map's common shift (3, 3), and the shift itself (centroid (2,),
    # Cov(delta) (3, 3), common_shift): a merged map's codes are not independent; empty / None
    # for a map written without the prior and shared columns
    shared: dict[str, np.ndarray] = field(default_factory=dict)
    shift: tuple[np.ndarray, np.ndarray] | None = None


def code_id(payload: FloorPayload) -> str:
    """The canonical text of a floor payload (one id per code however it was printed)."""
    return floor_payload(payload.x, payload.y)


def sightings_from_frames(
    floor_frames: Mapping[int, list[FloorSighting]], camera: CameraModel, corner_sigma_px: float
) -> tuple[np.ndarray, list[FloorPayload], np.ndarray, np.ndarray]:
    """(timestamps_ns (S,), payloads [S], T_code_body (S, 4, 4), cov (S, 6, 6)) from single-code
    PnP of every floor sighting (codes that fail PnP are left out), frame by frame in time order,
    SIGHTINGS_PER_PNP_CALL at a time (each sighting is its own view: the same poses as one call);
    `floor_frames` is read one frame at a time (it may classify each frame when read)."""
    t_parts: list[np.ndarray] = []
    T_parts: list[np.ndarray] = []
    cov_parts: list[np.ndarray] = []
    payloads: list[FloorPayload] = []
    chunk: list[tuple[int, FloorSighting]] = []

    def flush() -> None:
        res = estimate_floor_poses([[s] for _, s in chunk], camera, corner_sigma_px)
        kept = [(t, s, r) for (t, s), r in zip(chunk, res) if r is not None]
        chunk.clear()
        if not kept:
            return
        t_parts.append(np.array([t for t, _, _ in kept], dtype=np.int64))
        payloads.extend(s.payload for _, s, _ in kept)
        # T_world_nominal^-1 T_world_body, the nominal pose a translation: t - centre
        T = np.array([r.T_world_body for _, _, r in kept])
        T[:, :3, 3] -= np.array([np.asarray(s.centre_world, float) for _, s, _ in kept])
        T_parts.append(T)
        cov_parts.append(np.array([r.covariance for _, _, r in kept]))

    for t in sorted(floor_frames):
        for s in floor_frames[t]:
            chunk.append((int(t), s))
            if len(chunk) == SIGHTINGS_PER_PNP_CALL:
                flush()
    if chunk:
        flush()
    if not t_parts:
        return np.zeros(0, np.int64), [], np.zeros((0, 4, 4)), np.zeros((0, 6, 6))
    return np.concatenate(t_parts), payloads, np.concatenate(T_parts), np.concatenate(cov_parts)


def build_input(
    floor_frames: Mapping[int, list[FloorSighting]],
    camera: CameraModel,
    world: World,
    placement: Placement,
    corner_sigma_px: float,
    prior_map: PriorMap | None = None,
) -> AsBuiltInput:
    """The as-built input of a flight: one CodePrior per floor code seen, the single-code PnP of
    every sighting.  Raises EstimationError for a gimbaled floor camera (its single-code PnP is a
    level pose, not a relative pose)."""
    if camera.gimbaled:
        raise EstimationError("as-built floor codes need a body-fixed floor camera")
    t_s, payloads, T_code_body, cov_s = sightings_from_frames(floor_frames, camera, corner_sigma_px)
    index: dict[str, int] = {}
    codes: list[CodePrior] = []
    base_cov = code_prior_cov(placement.sigma_m, placement.sigma_rad)
    for payload in payloads:
        cid = code_id(payload)
        if cid in index:
            continue
        index[cid] = len(codes)
        T_nom = make_T(np.eye(3), world.floor_code_position(payload))
        codes.append(CodePrior(cid, T_nom, T_nom, base_cov))
    notes: list[str] = []
    shift_cov = None
    if prior_map is not None:
        codes, shift_cov, n_map = apply_prior_map(codes, prior_map)
        notes.append(
            f"floor-code prior: {n_map} of {len(codes)} codes seen from the map {prior_map.source}, "
            "the others from their payloads"
        )
        if n_map and prior_map.shift is None:
            notes.append(
                f"the map {prior_map.source} states no prior / shared columns (written before "
                "2026-12-05): its codes are taken as independent priors, so its common shift counts "
                "once per code and the floor's sigma is too small; run `fusion map merge` again"
            )
    code = np.array([index[code_id(p)] for p in payloads], dtype=np.int64)
    sightings = CodeSightings(t_s, code, T_code_body, cov_s)
    return AsBuiltInput(codes, sightings, placement, notes, shift_cov)


def apply_prior_map(
    codes: list[CodePrior], prior_map: PriorMap
) -> tuple[list[CodePrior], np.ndarray | None, int]:
    """The codes' priors with a merged map's where it has them: (codes, shift_cov, how many from
    the map).  A map that states each code's share of its common shift (PriorMap.shift) gives
    its codes the rest as their own part (cov_own) and the shift once (shift_cov, map_shift_cov),
    so that the flight takes the map's common shift once, not once per code: with a four-flight
    map of 34 codes taken as independent priors, a fifth flight's smoother read pose NEES 62
    (BENCHMARKS.md, twenty-first session)."""
    out: list[CodePrior] = []
    n_map = 0
    for c in codes:
        if c.code_id not in prior_map.codes:
            out.append(c)
            continue
        xyyaw, c3 = prior_map.codes[c.code_id]
        T_prior = make_T(rot_z(float(xyyaw[2])), np.array([xyyaw[0], xyyaw[1], c.T_world_nominal[2, 3]]))
        cov_own = None
        if prior_map.shift is not None and c.code_id in prior_map.shared:
            cov_own = xy_yaw_cov_to_pose_cov(T_prior, own_part(c3, prior_map.shared[c.code_id]))
        out.append(
            CodePrior(
                c.code_id, c.T_world_nominal, T_prior, xy_yaw_cov_to_pose_cov(T_prior, c3), True, cov_own
            )
        )
        n_map += 1
    shift = prior_map.shift
    shift_cov = (
        map_shift_cov(*shift) if shift is not None and any(c.cov_own is not None for c in out) else None
    )
    return out, shift_cov, n_map


def own_part(cov: np.ndarray, shared: np.ndarray) -> np.ndarray:
    """cov - shared, kept at least OWN_PART_MIN of cov along cov's whitened eigenvectors (the
    share of the shift that world.yaml's priors give can exceed what the map's rounded
    covariance holds along some direction)."""
    L = np.linalg.cholesky(cov)
    Li = np.linalg.inv(L)
    lam, V = np.linalg.eigh(Li @ (cov - shared) @ Li.T)
    M = L @ V
    out = (M * np.maximum(lam, OWN_PART_MIN)) @ M.T
    return 0.5 * (out + out.T)


def map_shift_cov(centroid: np.ndarray, cov_delta: np.ndarray) -> np.ndarray:
    """(6, 6) Pose3 covariance (rotation first; world frame at the identity) of a rigid motion D
    of the floor that turns by theta about `centroid` and shifts by (t_x, t_y), delta = (t_x,
    t_y, theta) ~ N(0, cov_delta) (common_shift): D = Exp(M delta), its translation t +
    (I - R) c ~ (t_x + theta c_y, t_y - theta c_x) to first order; tilt and height held
    (SHIFT_HELD_SIGMA)."""
    cx, cy = float(centroid[0]), float(centroid[1])
    M = np.zeros((6, 3))
    M[2, 2] = 1.0
    M[3, 0], M[3, 2] = 1.0, cy
    M[4, 1], M[4, 2] = 1.0, -cx
    C = M @ np.asarray(cov_delta, float) @ M.T
    C[[0, 1, 5], [0, 1, 5]] += SHIFT_HELD_SIGMA**2
    return 0.5 * (C + C.T)


# =========================================================================== smoother hook


@dataclass
class AsBuiltGraph:
    """What add_factors put into a problem: the codes with a variable (index c of F(c) ->
    index into AsBuiltInput.codes), sightings per code, the frames whose pose factor the
    sightings replace, and the factor indices of the sightings."""

    code_of_var: list[int]
    n_obs: list[int]
    frames: set[int]
    sighting_factors: list[int] = field(default_factory=list)


def add_factors(pb, as_built: AsBuiltInput, frame_t: np.ndarray, fix_frames, config, kind) -> AsBuiltGraph:
    """Add F(c) priors, initial values and one robust BetweenFactorPose3 per sighting to `pb`
    (fusion.estimate.smoother.Problem), at frames with a raw fix only (the fixes the flight's
    PnP accepted).  Returns the AsBuiltGraph; the caller leaves out those frames' pose factors."""
    s = as_built.sightings
    k_of = match_to_frames(frame_t, s.timestamps_ns, config.max_sync_s)
    fixes = set(int(k) for k in fix_frames)
    use = np.array([k >= 0 and int(k) in fixes for k in k_of], dtype=bool)
    var_of: dict[int, int] = {}
    out = AsBuiltGraph([], [], set())
    thr = config.threshold(6)
    for i in np.flatnonzero(use).tolist():
        c, k = int(s.code[i]), int(k_of[i])
        if c not in var_of:
            var_of[c] = len(out.code_of_var)
            out.code_of_var.append(c)
            out.n_obs.append(0)
            prior = as_built.codes[c]
            v = var_of[c]
            if prior.cov_own is not None and as_built.shift_cov is not None:
                # a merged map's code: its own part about the map's common shift D, which all of
                # them share (one prior on D), not the whole map sigma each as if independent
                if not pb.initial.exists(SHIFT_KEY):
                    pb.add(
                        gtsam.PriorFactorPose3(
                            SHIFT_KEY, gtsam.Pose3(), gtsam.noiseModel.Gaussian.Covariance(as_built.shift_cov)
                        ),
                        k,
                    )
                    pb.initial.insert(SHIFT_KEY, gtsam.Pose3())
                pb.add(
                    gtsam.BetweenFactorPose3(
                        SHIFT_KEY,
                        F(v),
                        gtsam.Pose3(prior.T_world_prior),
                        gtsam.noiseModel.Gaussian.Covariance(prior.cov_own),
                    ),
                    k,
                )
            else:
                pb.add(
                    gtsam.PriorFactorPose3(
                        F(v),
                        gtsam.Pose3(prior.T_world_prior),
                        gtsam.noiseModel.Gaussian.Covariance(prior.cov_prior),
                    ),
                    k,
                )
            pb.initial.insert(F(v), gtsam.Pose3(prior.T_world_prior))
        v = var_of[c]
        out.n_obs[v] += 1
        out.frames.add(k)
        out.sighting_factors.append(len(pb.factors))
        model = robust(gtsam.noiseModel.Gaussian.Covariance(s.cov[i]), config.robust_kernel, thr)
        pb.add(gtsam.BetweenFactorPose3(F(v), X(k), gtsam.Pose3(s.T_code_body[i]), model), k, kind, thr)
    return out


def graph_stats(graph_info: AsBuiltGraph, gated: int, rejected: int) -> dict:
    """FusionResult.stats entries of the as-built floor codes."""
    return {
        "floor_code_variables": len(graph_info.code_of_var),
        "floor_code_factors": len(graph_info.sighting_factors),
        "floor_code_frames": len(graph_info.frames),
        "gated_floor_code_factors": gated,
        "rejected_floor_code_factors": rejected,
    }


# =========================================================================== covariances

EXACT_MARGINALS_MAX_CODES = 48
"""Up to this many floor-code variables the covariances are exact (the codes as border
variables of the chain recursion, fusion.estimate.marginals.chain_marginals_with_codes: its
cost grows with frames x codes^2); beyond, `approximate_marginals`."""


def approximate_marginals(
    lin: gtsam.GaussianFactorGraph,
    values: gtsam.Values,
    n_frames: int,
    has_bias: bool,
    n_loads: int,
    graph_info: AsBuiltGraph,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Pose (N, 6, 6), load (n_loads, 3, 3) and code (C, 6, 6) covariances without the cost of
    the exact border recursion (EXACT_MARGINALS_MAX_CODES), in three approximations:

    - poses and loads given the codes: the exact chain marginals of the graph with the codes
      held at their estimates (every F column dropped from the linearised factors);
    - code c: inv(Lambda_prior + sum_s A_F^T (I + A_X S_k A_X^T)^-1 A_F) over its sightings s
      (whitened Jacobians A_F, A_X; S_k the pose covariance given the codes), plus the
      code's share of the floor's common shift, which only the priors fix (module docstring,
      "Gauge"; `common_shift_covs`: a planar rigid motion, so a code's share grows with its
      distance from the codes' centroid; the codes' summed 6 x 6 prior information, used
      until 2026-12-05, ignored that lever arm: x / y sigma 0.50-0.97 of the exact marginals'
      and yaw 3.2-4.5 times on six synthetic 30 s flights, now BENCHMARKS.md, twentieth
      session);
    - pose k: S_k + Ad(M^-1) Cov(F_c) Ad(M^-1)^T, c the code seen at frame k that the flight saw
      most, M = F_c^-1 X_k (the pose moves rigidly with the code it sees); frames without a
      sighting take the term of the nearest frame with one.

    Loads keep their covariance given the codes (an underestimate by the codes' share).
    None when the conditional graph is not a chain (the caller falls back to gtsam)."""
    n_codes = len(graph_info.code_of_var)
    f_chr = ord("f")
    cond = gtsam.GaussianFactorGraph()
    prior_info = np.zeros((n_codes, 6, 6))
    shift_info = np.zeros((6, 6))  # a merged map's common shift D (add_factors)
    on_shift: set[int] = set()  # the codes whose prior hangs from D
    sight: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # (code, frame, A_F, A_X)
    for i in range(lin.size()):
        f = lin.at(i)
        if f is None:
            continue
        keys = list(f.keys())
        is_f = [gtsam.Symbol(k).chr() == f_chr for k in keys]
        if SHIFT_KEY in keys:  # a merged map's shift: its prior, or a code's own part about it
            A, b = f.jacobian()
            if any(is_f):
                jf = is_f.index(True)
                A_F = A[:, 6 * jf : 6 * jf + 6]
                prior_info[gtsam.Symbol(keys[jf]).index()] += A_F.T @ A_F
                on_shift.add(gtsam.Symbol(keys[jf]).index())
            else:
                shift_info += A.T @ A
            continue
        if not any(is_f):
            cond.push_back(f)
            continue
        A, b = f.jacobian()
        if all(is_f):  # a code's prior
            prior_info[gtsam.Symbol(keys[0]).index()] += A.T @ A
            continue
        # a sighting: keys (F(c), X(k)), both 6 columns
        c, k = gtsam.Symbol(keys[0]).index(), gtsam.Symbol(keys[1]).index()
        A_F, A_X = A[:, :6], A[:, 6:12]
        cond.push_back(gtsam.JacobianFactor(keys[1], A_X, b, gtsam.noiseModel.Unit.Create(len(b))))
        sight.append((c, k, A_F, A_X))
    bulk = chain_marginals(cond, n_frames, has_bias, n_loads)
    if bulk is None:
        return None
    S, lcov = bulk
    info = prior_info.copy()
    if sight:
        cs = np.array([t[0] for t in sight])
        ks = np.array([t[1] for t in sight])
        AF = np.stack([t[2] for t in sight])
        AX = np.stack([t[3] for t in sight])
        eff = np.eye(AX.shape[1])[None] + AX @ S[ks] @ AX.transpose(0, 2, 1)
        np.add.at(info, cs, AF.transpose(0, 2, 1) @ np.linalg.solve(eff, AF))
    gauge = _gauge_terms(values, prior_info)
    if on_shift:  # the map's codes share its shift D: F = D T_prior, so Ad(F^-1) Cov(D) Ad(F^-1)^T
        shift_cov = np.linalg.inv(shift_info)
        for c in on_shift:
            Ad = adjoint(inv_T(values.atPose3(F(c)).matrix()))
            gauge[c] = Ad @ shift_cov @ Ad.T
    ccov = np.linalg.inv(info) + gauge
    cov = S.copy()
    if sight:
        best: dict[int, int] = {}
        for c, k in zip(cs.tolist(), ks.tolist()):
            if k not in best or graph_info.n_obs[c] > graph_info.n_obs[best[k]]:
                best[k] = c
        seen = np.array(sorted(best), dtype=np.int64)
        add = np.empty((len(seen), 6, 6))
        for m, k in enumerate(seen.tolist()):
            c = best[k]
            T_fx = inv_T(values.atPose3(F(c)).matrix()) @ values.atPose3(X(k)).matrix()
            Ad = adjoint(inv_T(T_fx))
            add[m] = Ad @ ccov[c] @ Ad.T
        # frames without a sighting (gaps): the term of the nearest frame with one
        j = np.clip(np.searchsorted(seen, np.arange(n_frames)), 1, max(len(seen) - 1, 1))
        j0 = np.minimum(j, len(seen) - 1)
        jm = np.maximum(j - 1, 0)
        near = np.where(
            np.abs(seen[j0] - np.arange(n_frames)) < np.abs(seen[jm] - np.arange(n_frames)), j0, jm
        )
        cov += add[near]
    return 0.5 * (cov + cov.transpose(0, 2, 1)), lcov, 0.5 * (ccov + ccov.transpose(0, 2, 1))


def _gauge_terms(values: gtsam.Values, prior_info: np.ndarray) -> np.ndarray:
    """(C, 6, 6) code frame: each code's share of the floor's common shift (`common_shift_covs`
    for x, y, yaw, from the codes' estimated places and their priors' information `prior_info`
    (C, 6, 6)); tilt and height as the summed priors fix them (their flat-floor sigmas)."""
    T = np.array([values.atPose3(F(c)).matrix() for c in range(len(prior_info))])
    summed = np.linalg.inv(prior_info.sum(axis=0))
    Q = np.array([pose_cov_to_xy_yaw_cov(T[c], np.linalg.inv(prior_info[c])) for c in range(len(T))])
    shift = common_shift_covs(T[:, :2, 3], Q)
    out = np.repeat(summed[None], len(T), axis=0)
    planar = [2, 3, 4]  # rz, tx, ty
    for c in range(len(T)):
        C = xy_yaw_cov_to_pose_cov(T[c], shift[c])
        out[c][np.ix_(planar, range(6))] = 0.0
        out[c][np.ix_(range(6), planar)] = 0.0
        out[c][np.ix_(planar, planar)] = C[np.ix_(planar, planar)]
    return out


# =========================================================================== results


@dataclass
class FloorCodeEstimate:
    """One floor code as built: pose T_world_code (4, 4), covariance (6, 6) (Pose3 order, code
    frame; None without covariances), sightings, and the nominal centre (3,)."""

    code_id: str
    nominal_world: np.ndarray
    T_world_code: np.ndarray
    cov: np.ndarray | None
    n_obs: int
    misplaced: bool = False
    prior_xy_yaw: np.ndarray | None = None  # (3,) x, y (m), yaw (rad): the prior's mean
    prior_cov_xy_yaw: np.ndarray | None = None  # (3, 3): the prior's covariance
    shared_cov_xy_yaw: np.ndarray | None = None  # (3, 3): the floor's common shift, part of cov
    shift_group: int = 0  # the solve (window) whose common shift it carries

    @property
    def p_world(self) -> np.ndarray:
        return self.T_world_code[:3, 3]

    @property
    def yaw_rad(self) -> float:
        return float(yaw_of(self.T_world_code[:3, :3]))

    @property
    def offset_xy_m(self) -> np.ndarray:
        return self.p_world[:2] - self.nominal_world[:2]

    @property
    def cov_xy_yaw(self) -> np.ndarray | None:
        return None if self.cov is None else pose_cov_to_xy_yaw_cov(self.T_world_code, self.cov)

    def mahalanobis_offset(self) -> float:
        c = self.cov_xy_yaw
        if c is None:
            return float("nan")
        d = self.offset_xy_m
        return float(math.sqrt(max(float(d @ np.linalg.solve(c[:2, :2], d)), 0.0)))


def is_misplaced(est: FloorCodeEstimate) -> bool:
    """Offset beyond MISPLACED_SIGMAS (Mahalanobis) and longer than MISPLACED_MIN_OFFSET_M."""
    d = float(np.linalg.norm(est.offset_xy_m))
    m = est.mahalanobis_offset()
    return bool(d > MISPLACED_MIN_OFFSET_M and math.isfinite(m) and m > MISPLACED_SIGMAS)


@dataclass
class FloorCodeMap:
    """The as-built floor codes of one estimator."""

    estimator: str
    codes: list[FloorCodeEstimate]
    placement: Placement = field(default_factory=Placement)

    @property
    def misplaced(self) -> list[FloorCodeEstimate]:
        return [c for c in self.codes if c.misplaced]

    def by_id(self) -> dict[str, FloorCodeEstimate]:
        return {c.code_id: c for c in self.codes}

    def summary(self) -> dict:
        """JSON-ready: counts, misplaced ids with offsets (m) and sigma distances."""
        off = np.array([np.linalg.norm(c.offset_xy_m) for c in self.codes]) if self.codes else np.zeros(0)
        return {
            "n_codes": len(self.codes),
            "placement_sigma_m": self.placement.sigma_m,
            "placement_sigma_deg": math.degrees(self.placement.sigma_rad),
            "offset_rms_m": float(np.sqrt(np.mean(off**2))) if len(off) else None,
            "offset_max_m": float(off.max()) if len(off) else None,
            "misplaced": [
                {
                    "id": c.code_id,
                    "offset_m": float(np.linalg.norm(c.offset_xy_m)),
                    "offset_xy_m": c.offset_xy_m.tolist(),
                    "sigmas": c.mahalanobis_offset(),
                    "n_obs": c.n_obs,
                }
                for c in self.misplaced
            ],
        }


def floor_code_estimates(
    values: gtsam.Values,
    graph_info: AsBuiltGraph,
    as_built: AsBuiltInput,
    covs: np.ndarray | None,
    estimator: str,
) -> FloorCodeMap:
    """FloorCodeMap from a solution: F(v) estimates, covs (V, 6, 6) or None, flags set, each
    code's prior and its share of the floor's common shift (`common_shift_covs`) kept for
    `fusion map merge`."""
    out = []
    priors = [as_built.codes[c] for c in graph_info.code_of_var]
    shift = None
    if covs is not None and priors:
        xy = np.array([p.T_world_prior[:2, 3] for p in priors])
        Q = np.array([pose_cov_to_xy_yaw_cov(p.T_world_prior, p.cov_prior) for p in priors])
        shift = common_shift_covs(xy, Q)
    for v, prior in enumerate(priors):
        T = values.atPose3(F(v)).matrix()
        est = FloorCodeEstimate(
            prior.code_id,
            prior.T_world_nominal[:3, 3].copy(),
            T,
            None if covs is None else np.asarray(covs[v]),
            graph_info.n_obs[v],
            prior_xy_yaw=np.array([*prior.T_world_prior[:2, 3], yaw_of(prior.T_world_prior[:3, :3])]),
            prior_cov_xy_yaw=pose_cov_to_xy_yaw_cov(prior.T_world_prior, prior.cov_prior),
            shared_cov_xy_yaw=None if shift is None else shift[v],
        )
        est.misplaced = is_misplaced(est)
        out.append(est)
    out.sort(key=lambda e: e.code_id)
    return FloorCodeMap(estimator, out, as_built.placement)


def shift_jacobians(xy: np.ndarray) -> np.ndarray:
    """(C, 3, 3): how a planar rigid motion delta = (t_x, t_y, theta) of the codes at `xy` (C, 2)
    about their centroid moves each code's x, y, yaw: [[1, 0, -(y - y_0)], [0, 1, x - x_0],
    [0, 0, 1]]."""
    d = np.asarray(xy, float) - np.mean(xy, axis=0)
    J = np.zeros((len(d), 3, 3))
    J[:, 0, 0] = J[:, 1, 1] = J[:, 2, 2] = 1.0
    J[:, 0, 2] = -d[:, 1]
    J[:, 1, 2] = d[:, 0]
    return J


def common_shift_covs(xy: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(C, 3, 3) x, y, yaw: each code's share of the floor's common shift in a solve over codes
    at `xy` (C, 2) with prior covariances `Q` (C, 3, 3), which only those priors fix (module
    docstring, "Gauge").  The shift is a planar rigid motion delta (shift_jacobians: code c
    moves by J_c delta), so the priors give it the information sum_c J_c^T Q_c^-1 J_c and code c
    the covariance J_c Cov(delta) J_c^T: its position's share grows with its distance from the
    centroid, and the rotation is fixed mostly by the spread of the priors' positions, not by
    their yaw (nine codes over 3 m at 1 cm and 1 deg: 0.33 deg from the yaw priors alone, 0.09
    with the positions).  Every flight over these codes shares it: the codes are where they
    were laid, whoever looks."""
    J = shift_jacobians(xy)
    return J @ common_shift(xy, Q)[1] @ J.transpose(0, 2, 1)


def common_shift(xy: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The floor's common shift over codes at `xy` (C, 2) with prior covariances `Q` (C, 3, 3)
    (x, y, yaw): the centroid (2,) it turns about and Cov(delta) (3, 3), delta = (t_x, t_y,
    theta) (common_shift_covs)."""
    J = shift_jacobians(xy)
    info = np.einsum("nji,njk,nkl->il", J, np.linalg.inv(Q), J)
    return np.mean(np.asarray(xy, float), axis=0), np.linalg.inv(info)


def merge_window_maps(maps: list[FloorCodeMap], estimator: str, placement: Placement) -> FloorCodeMap:
    """One floor-code map from the maps of a flight's windows (fusion.estimate.window): per
    code, the estimate of the window that saw it most (the first of a tie).  Not
    their information-weighted mean: every window's estimate rests on the same prior, and its
    covariance holds that window's common shift of the floor, fixed by the priors of all the
    codes it saw (module docstring, "Gauge"), so neighbouring windows share most of their
    information about where a code is; a mean would count it once per window."""
    best: dict[str, FloorCodeEstimate] = {}
    for i, m in enumerate(maps):
        for c in m.codes:
            if c.code_id not in best or c.n_obs > best[c.code_id].n_obs:
                best[c.code_id] = replace(c, shift_group=i)
    return FloorCodeMap(estimator, [best[k] for k in sorted(best)], placement)


def as_built_fixes(as_built: AsBuiltInput, fmap: FloorCodeMap) -> Trajectory:
    """The per-frame fixes as the as-built codes give them (what the health monitor compares the
    smoother with, instead of PnP on the nominal codes): per frame, each sighting's
    T_world_code (estimated) T_code_body, information-weighted in the tangent space of the
    first (se3_log / se3_exp; the sightings' covariances share the body frame to first order),
    covariance (sum_i Sigma_i^-1)^-1."""
    est = fmap.by_id()
    s = as_built.sightings
    by_t: dict[int, list[int]] = {}
    for i, (t, c) in enumerate(zip(s.timestamps_ns.tolist(), s.code.tolist())):
        if as_built.codes[c].code_id in est:
            by_t.setdefault(t, []).append(i)
    ts = sorted(by_t)
    T_out = np.empty((len(ts), 4, 4))
    cov_out = np.empty((len(ts), 6, 6))
    for m, t in enumerate(ts):
        idx = by_t[t]
        poses = np.array(
            [est[as_built.codes[s.code[i]].code_id].T_world_code @ s.T_code_body[i] for i in idx]
        )
        ref = poses[0]
        xi = se3_log(np.einsum("ij,njk->nik", inv_T(ref), poses))
        info = np.linalg.inv(s.cov[idx])
        cov_out[m] = np.linalg.inv(info.sum(axis=0))
        T_out[m] = ref @ se3_exp(cov_out[m] @ np.einsum("nij,nj->i", info, xi))
    return Trajectory("pnp", np.array(ts, dtype=np.int64), T_out, cov_out)


# =========================================================================== files


def _f(v: float, fmt: str = "{:.6f}") -> str:
    return "" if v is None or not math.isfinite(v) else fmt.format(v)


def write_floor_codes_csv(path: Path, fmap: FloorCodeMap) -> None:
    """`floor_codes_<estimator>.csv` (FLOOR_CODE_COLUMNS); ids through csv_safe (payloads are
    untrusted)."""
    with atomic_open(Path(path)) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(FLOOR_CODE_COLUMNS)
        for c in fmap.codes:
            C = c.cov_xy_yaw
            sig = [math.nan] * 3 if C is None else np.sqrt(np.maximum(np.diag(C), 0.0)).tolist()
            off = c.offset_xy_m
            w.writerow(
                [
                    csv_safe(c.code_id),
                    _f(c.nominal_world[0]),
                    _f(c.nominal_world[1]),
                    *(_f(v) for v in c.p_world),
                    _f(math.degrees(c.yaw_rad)),
                    _f(off[0]),
                    _f(off[1]),
                    _f(float(np.linalg.norm(off))),
                    _f(math.degrees(c.yaw_rad)),
                    _f(sig[0]),
                    _f(sig[1]),
                    _f(math.degrees(sig[2]) if math.isfinite(sig[2]) else math.nan),
                    c.n_obs,
                    int(c.misplaced),
                    *shared_cells(c.prior_xy_yaw, c.prior_cov_xy_yaw, c.shared_cov_xy_yaw),
                    c.shift_group,
                    *correlation_cells(C),
                ]
            )


def _sigmas_cells(cov: np.ndarray | None) -> list[str]:
    """x, y sigma (m) and yaw sigma (deg) of an (x, y, yaw) covariance; empty cells for None."""
    if cov is None:
        return ["", "", ""]
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return [_f(sig[0]), _f(sig[1]), _f(math.degrees(sig[2]))]


def correlation_cells(cov: np.ndarray | None) -> list[str]:
    """The CORRELATION_COLUMNS cells of an (x, y, yaw) covariance; empty for None."""
    if cov is None:
        return ["", "", ""]
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    if not np.all(sig > 0):
        return ["", "", ""]
    r = cov / np.outer(sig, sig)
    return [_f(float(np.clip(r[i, j], -1.0, 1.0))) for i, j in ((0, 1), (0, 2), (1, 2))]


def shared_cells(
    prior: np.ndarray | None, prior_cov: np.ndarray | None, shared: np.ndarray | None
) -> list[str]:
    """The SHARED_COLUMNS cells of one code."""
    mean = ["", "", ""] if prior is None else [_f(prior[0]), _f(prior[1]), _f(math.degrees(prior[2]))]
    return [*mean, *_sigmas_cells(prior_cov), *_sigmas_cells(shared)]


def _num(row: dict, col: str, path: Path, line: int) -> float:
    try:
        v = float(row[col])
    except (KeyError, TypeError, ValueError):
        raise AsBuiltError(f"{path}:{line}: {col} is not a number: {row.get(col)!r}") from None
    if not math.isfinite(v):
        raise AsBuiltError(f"{path}:{line}: {col} is not finite")
    return v


@dataclass
class FloorCodeRow:
    """One row of a floor_codes CSV: x, y, yaw (rad) and its diagonal covariance, sightings, and
    what it shares with other flights (SHARED_COLUMNS; None when the file has them empty)."""

    xy_yaw: np.ndarray  # (3,)
    cov: np.ndarray  # (3, 3)
    n_obs: int
    prior_xy_yaw: np.ndarray | None = None
    prior_cov: np.ndarray | None = None
    shared_cov: np.ndarray | None = None
    shift_group: int = 0


def _xy_yaw(row: dict, cols: tuple[str, str, str], path: Path, line: int) -> np.ndarray:
    """x, y (as written) and yaw (degrees in the file, radians out) from three columns."""
    x, y, yaw = (_num(row, c, path, line) for c in cols)
    return np.array([x, y, math.radians(yaw)])


def _sigmas_cov(
    row: dict, cols: tuple[str, str, str], path: Path, line: int, zero: bool = False
) -> np.ndarray:
    """The diagonal covariance of three sigma columns, each positive (or, `zero`, not negative)."""
    sig = _xy_yaw(row, cols, path, line)
    if np.any(sig < 0) or (not zero and np.any(sig == 0)):
        raise AsBuiltError(f"{path}:{line}: sigmas must be {'non-negative' if zero else 'positive'}")
    return np.diag(sig**2)


def _with_correlations(cov: np.ndarray, row: dict, path: Path, line: int) -> np.ndarray:
    """A diagonal (x, y, yaw) covariance with the row's CORRELATION_COLUMNS (those empty or absent:
    0); AsBuiltError naming the file and line for a coefficient outside [-1, 1] or a matrix that
    is not a covariance."""
    if not any(row.get(c) for c in CORRELATION_COLUMNS):
        return cov
    r = np.eye(3)
    for (i, j), col in zip(((0, 1), (0, 2), (1, 2)), CORRELATION_COLUMNS):
        if row.get(col):
            v = _num(row, col, path, line)
            if not -1.0 <= v <= 1.0:
                raise AsBuiltError(f"{path}:{line}: {col} is not a correlation in [-1, 1]: {v:g}")
            r[i, j] = r[j, i] = v
    sig = np.sqrt(np.diag(cov))
    out = r * np.outer(sig, sig)
    if np.linalg.eigvalsh(r)[0] < -1e-9:
        raise AsBuiltError(f"{path}:{line}: the correlations do not make a covariance")
    return out


def _numbered_rows(text: str) -> list[tuple[int, dict[str, str]]]:
    """The CSV `text`'s records as (line, row): the line each ends on, as an editor counts
    them (csv.DictReader skips blank lines, so counting its rows from 2 named a later row's
    error a line too early for every blank line above it)."""
    reader = csv.DictReader(text.splitlines())
    return [(reader.line_num, row) for row in reader]


def read_floor_code_rows(path: Path) -> dict[str, FloorCodeRow]:
    """{id: FloorCodeRow} from a floor_codes CSV (ours or a merged map's).  AsBuiltError naming
    the file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise AsBuiltError(f"{path}: cannot read ({e.__class__.__name__})") from None
    rows = _numbered_rows(text)
    need = {"id", "x_m", "y_m", "yaw_deg", "sigma_x_m", "sigma_y_m", "sigma_yaw_deg", "n_obs"}
    if rows and not need <= set(rows[0][1]):
        raise AsBuiltError(f"{path}:1: missing columns {sorted(need - set(rows[0][1]))}")
    out: dict[str, FloorCodeRow] = {}
    for line, row in rows:
        cid = csv_unsafe(row["id"])
        if cid in out:
            raise AsBuiltError(f"{path}:{line}: floor code {cid!r} listed twice")
        r = FloorCodeRow(
            _xy_yaw(row, ("x_m", "y_m", "yaw_deg"), path, line),
            _with_correlations(
                _sigmas_cov(row, ("sigma_x_m", "sigma_y_m", "sigma_yaw_deg"), path, line), row, path, line
            ),
            int(_num(row, "n_obs", path, line)),
        )
        if row.get("prior_x_m"):
            r.prior_xy_yaw = _xy_yaw(row, ("prior_x_m", "prior_y_m", "prior_yaw_deg"), path, line)
            r.prior_cov = _sigmas_cov(
                row, ("prior_sigma_x_m", "prior_sigma_y_m", "prior_sigma_yaw_deg"), path, line
            )
        if row.get("shift_group"):
            g = row["shift_group"]
            if not g.isdigit():
                raise AsBuiltError(f"{path}:{line}: shift_group is not a whole number: {g!r}")
            r.shift_group = int(g)
        if row.get("shared_sigma_x_m"):
            r.shared_cov = _sigmas_cov(
                row, ("shared_sigma_x_m", "shared_sigma_y_m", "shared_sigma_yaw_deg"), path, line, zero=True
            )
        out[cid] = r
    return out


def read_floor_codes_csv(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, int]]:
    """{id: ((3,) x, y, yaw rad; (3, 3) diagonal covariance; n_obs)} from a floor_codes CSV
    (read_floor_code_rows without what the rows share)."""
    return {cid: (r.xy_yaw, r.cov, r.n_obs) for cid, r in read_floor_code_rows(path).items()}


def write_groundtruth_csv(path: Path, ids: list[str], xy_yaw: np.ndarray) -> None:
    """The simulator's true floor-code poses: `id,x_m,y_m,yaw_deg` (world frame)."""
    with atomic_open(Path(path)) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(GROUNDTRUTH_COLUMNS)
        for cid, (x, y, yaw) in zip(ids, np.asarray(xy_yaw, float).reshape(-1, 3)):
            w.writerow([csv_safe(cid), f"{x:.6f}", f"{y:.6f}", f"{math.degrees(yaw):.6f}"])


def read_groundtruth_csv(path: Path) -> dict[str, np.ndarray]:
    """{canonical id: (3,) x, y, yaw rad} from floor_codes_groundtruth.csv; AsBuiltError naming
    the file (and line) when it cannot be read, or naming both lines of a code listed twice."""
    path = Path(path)
    try:
        rows = _numbered_rows(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise AsBuiltError(f"{path}: not UTF-8 text (byte {e.start})") from None
    except (OSError, csv.Error) as e:
        raise AsBuiltError(f"{path}: {e}") from None
    out = {}
    first_line: dict[str, int] = {}  # canonical id -> its line
    for line, row in rows:
        raw = csv_unsafe(row.get("id") or "")
        try:
            p = parse_payload(raw)
        except FusionError:
            raise AsBuiltError(f"{path}:{line}: {raw!r} is not a floor code") from None
        if not isinstance(p, FloorPayload):
            raise AsBuiltError(f"{path}:{line}: {raw!r} is not a floor code")
        cid = code_id(p)
        if cid in first_line:
            # two true poses for one code: the later silently replaced the earlier
            raise AsBuiltError(
                f"{path}:{line}: floor code {cid!r} listed twice (first on line {first_line[cid]})"
            )
        first_line[cid] = line
        out[cid] = np.array(
            [
                _num(row, "x_m", path, line),
                _num(row, "y_m", path, line),
                math.radians(_num(row, "yaw_deg", path, line)),
            ]
        )
    return out


def gauge_transform(fmap: FloorCodeMap, truth: dict[str, np.ndarray]) -> np.ndarray | None:
    """(4, 4) T_true_est: the rigid motion that best maps the estimated code centres onto the
    true ones (Umeyama; all codes in both), i.e. the common shift and rotation of the floor
    that no flight can observe (module docstring, "Gauge").  None with fewer than 3 codes."""
    pairs = [(c.p_world, truth[c.code_id]) for c in fmap.codes if c.code_id in truth]
    if len(pairs) < 3:
        return None
    p_est = np.array([p for p, _ in pairs])
    p_gt = np.array([[t[0], t[1], 0.0] for _, t in pairs])
    R, t = umeyama_alignment(p_est, p_gt)
    return make_T(R, t)


def groundtruth_errors(fmap: FloorCodeMap, truth: dict[str, np.ndarray], min_obs: int = 0) -> dict:
    """Errors of the estimated codes against the true ones (codes with >= min_obs sightings):
    RMS of the (x, y) error (m) and of the yaw error (deg), raw and after the gauge transform
    (gauge_transform: the floor's unobservable common shift and rotation), and the RMS of the
    true offsets from nominal."""
    T_g = gauge_transform(fmap, truth)
    est, est_g, tru, nom, yaw_err = [], [], [], [], []
    for c in fmap.codes:
        if c.code_id not in truth or c.n_obs < min_obs:
            continue
        t = truth[c.code_id]
        est.append(c.p_world[:2])
        est_g.append((T_g[:3, :3] @ c.p_world + T_g[:3, 3])[:2] if T_g is not None else c.p_world[:2])
        tru.append(t[:2])
        nom.append(c.nominal_world[:2])
        yaw_err.append(float(wrap_angle(c.yaw_rad - t[2])))
    if not est:
        return {"n_codes": 0}
    e, t, n = np.array(est), np.array(tru), np.array(nom)
    err, err_g = e - t, np.array(est_g) - t
    return {
        "n_codes": len(est),
        "min_obs": min_obs,
        "offset_error_rms_m": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        "offset_error_rms_gauge_removed_m": float(np.sqrt(np.mean(np.sum(err_g**2, axis=1)))),
        "gauge_shift_m": None if T_g is None else T_g[:2, 3].tolist(),
        "gauge_yaw_deg": None if T_g is None else math.degrees(float(yaw_of(T_g[:3, :3]))),
        "yaw_error_rms_deg": float(math.degrees(math.sqrt(np.mean(np.square(yaw_err))))),
        "true_offset_rms_m": float(np.sqrt(np.mean(np.sum((t - n) ** 2, axis=1)))),
    }
