"""GTSAM fusion of per-frame QR poses with IMU / velocity and load observations.

One state per floor-camera frame: X(k) Pose3 T_world_body, V(k) world velocity, B(k) IMU bias
(when there is an IMU).  Factors (see fusion.estimate.factors):

- CombinedImuFactor between consecutive frames whose interval the IMU covers (preintegration,
  Forster et al. 2017, GTSAM's PreintegratedCombinedMeasurements; the IMU signal at the
  midpoint of each sub-interval, split exactly at frame times);
- where the IMU does not cover an interval (IMU gap longer than `max_imu_gap_s`, IMU that starts
  late / stops early, or no IMU at all = velocity-only mode) a weak random-walk bridge
  (graph.bridge_factors: rotation and velocity random walks, position-velocity consistency, bias
  random walk), so the flight stays ONE graph; the intervals are counted in `stats`;
- a robust QR pose factor per frame with a raw pose: PriorFactorPose3 with the raw covariance
  (PnP), or position + yaw (the paper's estimator, no covariance: configured sigmas);
- body-frame velocity factors at frames with velocity data;
- one Point3 L(j) per load id and a camera-frame point factor per observation;
- priors: weak prior on the first bias, velocity prior at the first raw pose (least-squares line
  through the first raw positions).

`smooth` = batch Levenberg-Marquardt over the whole flight + marginal covariances;
`smooth_incremental` = iSAM2 (Cholesky; the whole flight re-run with QR on a singular system),
the estimate as known at each frame (causal).
"""

from __future__ import annotations

import ctypes
import functools
import logging
import math
import time
from collections.abc import Iterator, Mapping
from collections.abc import Set as AbstractSet
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import gtsam
import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import GRAVITY_M_S2
from fusion.errors import EstimationError, first_line
from fusion.estimate import asbuilt, factors, fixedlag
from fusion.estimate.common import (
    FusionConfig,
    FusionResult,
    RawPoseInput,
    RawPoses,
    SolveHealth,
    SolveMode,
    TightCoupling,
    first_velocity,
    fix_jumps,
    group_load_obs,
    initial_poses,
    initial_velocities,
    inlier_raw_mask,
    match_to_frames,
    prepare_inputs,
    retime_load_obs,
    velocity_at_frames,
)
from fusion.estimate.factors import B, L, V, X
from fusion.estimate.marginals import chain_marginals, chain_marginals_with_codes
from fusion.estimate.variance import (
    NoiseGroup,
    ResolvePredicate,
    factor_groups,
    first_solve_scales,
    problem_variance_components,
    solve_noise_scaled,
)
from fusion.geometry import make_T, rot_z, yaw_of
from fusion.log.euroc import ImuData, VelocityData
from fusion.qr.pnp import corner_whitening
from fusion.types import (
    Choice,
    Estimator,
    LoadEstimate,
    LoadMap,
    LoadObservation,
    Trajectory,
)

__all__ = [
    "FactorKind",
    "LMResult",
    "LMStop",
    "Problem",
    "SolveReuse",
    "build_problem",
    "imu_coverage",
    "imu_subintervals",
    "levenberg_marquardt",
    "smooth",
    "smooth_incremental",
    "warm_values",
]

if TYPE_CHECKING:  # ekf imports this module
    from fusion.estimate.ekf import LevelStart

log = logging.getLogger(__name__)
GRAVITY_W = np.array([0.0, 0.0, -GRAVITY_M_S2])
ZERO_BIAS_CACHE_SIZE = 2
"""Frame counts whose zero initial biases are kept (_zero_biases: a flight's whole-flight
solves, and the time-offset profile's windows)."""


# =========================================================================== IMU handling


def imu_coverage(frame_t: np.ndarray, imu: ImuData, max_gap_s: float) -> np.ndarray:
    """(N-1,) bool: interval [t_k, t_k+1] is covered by IMU samples, each held until the next
    sample when that comes within max_gap_s (the last sample holds for one nominal period)."""
    t = imu.timestamps_ns
    n = len(frame_t)
    if n < 2 or len(t) == 0:
        return np.zeros(max(n - 1, 0), bool)
    gap = int(max_gap_s * 1e9)
    d = np.diff(t)
    nominal = int(np.median(d)) if len(d) else gap
    end_last = t[-1] + min(nominal, gap)
    a, b = frame_t[:-1], frame_t[1:]
    ok = (a >= t[0]) & (b <= end_last)
    hole = np.flatnonzero(d > gap)  # hole (t[i] + nominal, t[i+1])
    if hole.size:
        h0 = t[hole] + min(nominal, gap)
        h1 = t[hole + 1]
        # interval overlaps a hole if a < h1 and b > h0
        j = np.searchsorted(h1, a, side="right")  # first hole ending after a
        jj = np.clip(j, 0, len(h1) - 1)
        overlaps = (j < len(h1)) & (b > h0[jj])
        ok &= ~overlaps
    return ok


SUBINTERVAL_BLOCK = 4096
"""Frame intervals split at once by imu_subintervals (its sorted unions and interpolation
temporaries: ~2.4 MB per flight minute at 30 fps and 200 Hz, whole)."""


def imu_subintervals(frame_t: np.ndarray, imu: ImuData, covered: np.ndarray):
    """Split the covered frame intervals at IMU sample times and at frame times.

    Returns (k (M,) frame interval, dt (M,) s, gyro (M, 3), accel (M, 3)) in time order: each
    sub-interval's measurement is the IMU signal linearly interpolated to its midpoint (samples
    are instantaneous; holding a sample over the following period instead would lag the
    attitude by half a sample period, which the NEES shows)."""
    t = imu.timestamps_ns
    ks = np.flatnonzero(covered)
    if ks.size > SUBINTERVAL_BLOCK:
        # blocks of consecutive covered intervals, concatenated: the same rows (an interval's
        # sub-intervals depend only on its own ends and the IMU samples between them), with
        # temporaries bounded by the block instead of the flight
        parts = []
        for i in range(0, ks.size, SUBINTERVAL_BLOCK):
            block = np.zeros_like(covered)
            block[ks[i : i + SUBINTERVAL_BLOCK]] = True
            parts.append(imu_subintervals(frame_t, imu, block))
        k_all, dt_all, gyr_all, acc_all = (np.concatenate(c) for c in zip(*parts))
        return k_all, dt_all, gyr_all, acc_all
    if ks.size == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    a, b = frame_t[ks], frame_t[ks + 1]
    inner = t[(t > a[0]) & (t < b[-1])]
    bounds = np.union1d(np.union1d(a, b), inner)
    s, e = bounds[:-1], bounds[1:]
    k_of = np.searchsorted(frame_t, s, side="right") - 1
    keep = (k_of < len(covered)) & covered[np.clip(k_of, 0, len(covered) - 1)]
    s, e, k_of = s[keep], e[keep], k_of[keep]
    mid = 0.5 * (s + e)
    i0 = np.clip(np.searchsorted(t, mid, side="right") - 1, 0, len(t) - 1)
    i1 = np.minimum(i0 + 1, len(t) - 1)
    span = (t[i1] - t[i0]).astype(float)
    w = np.where(span > 0, (mid - t[i0]) / np.where(span > 0, span, 1.0), 0.0)
    w = np.clip(w, 0.0, 1.0)[:, None]
    gyr = (1 - w) * imu.gyro_rad_s[i0] + w * imu.gyro_rad_s[i1]
    acc = (1 - w) * imu.accel_m_s2[i0] + w * imu.accel_m_s2[i1]
    return k_of, (e - s) * 1e-9, gyr, acc


MIDPOINT_BLOCK_ROWS = 65536
"""Sub-intervals turned at once by midpoint_specific_force (~1.6 MB per (rows, 3) temporary)."""


def midpoint_specific_force(gyr: np.ndarray, acc: np.ndarray, dts: np.ndarray) -> np.ndarray:
    """(M, 3) each sub-interval's specific force `acc` turned by Exp(gyr dt / 2): expressed in the
    body frame at the sub-interval's start, as seen at its midpoint.  GTSAM's preintegration
    rotates a sub-interval's specific force with the attitude at its start (TangentPreintegration
    update: a_nav = dR a dt), half a sub-interval behind the midpoint signal it is given: the
    velocity then lags the attitude, and a cost profile over a camera's time offset is least
    about 0.04 IMU periods late (0.22 ms at 200 Hz).  Turning a by half the sub-interval's
    rotation first makes that product R(t_mid) a, the midpoint rule (exact for a constant rate
    over the sub-interval); Rodrigues' formula, vectorised, in blocks of rows (each row is its
    own: the same to the bit; a 30-minute flight's ~0.4 M rows at once were ~80 MB of
    temporaries at the time-offset stage's memory peak, BENCHMARKS.md, mem14)."""
    if len(gyr) > MIDPOINT_BLOCK_ROWS:
        out = np.empty(np.broadcast_shapes(np.shape(gyr), np.shape(acc)))
        for lo in range(0, len(gyr), MIDPOINT_BLOCK_ROWS):
            hi = lo + MIDPOINT_BLOCK_ROWS
            out[lo:hi] = midpoint_specific_force(gyr[lo:hi], acc[lo:hi], dts[lo:hi])
        return out
    phi = 0.5 * gyr * dts[:, None]
    th = np.linalg.norm(phi, axis=1)[:, None]
    small = th < 1e-8
    safe = np.where(small, 1.0, th)
    s = np.where(small, 1.0 - th**2 / 6.0, np.sin(safe) / safe)
    c = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    cross = np.cross(phi, acc)
    return acc + s * cross + c * np.cross(phi, cross)


def preintegrate(
    frame_t: np.ndarray,
    imu: ImuData,
    covered: np.ndarray,
    params: gtsam.PreintegrationCombinedParams,
    midpoint_attitude: bool = False,
) -> dict[int, gtsam.PreintegratedCombinedMeasurements]:
    """Preintegrated measurements for each covered interval k (between frames k and k+1), with
    zero bias as the linearisation point (sub-intervals from imu_subintervals).
    `midpoint_attitude`: the specific force turned to each sub-interval's midpoint attitude
    (midpoint_specific_force).  Every interval at once: LazyPims integrates them when asked."""
    intervals = LazyPims(frame_t, imu, covered, params, midpoint_attitude)
    return {k: intervals.integrate(k) for k in intervals}


def imu_factor(k: int, pim: gtsam.PreintegratedCombinedMeasurements) -> gtsam.CombinedImuFactor:
    """The IMU factor of interval k (frames k and k + 1)."""
    return gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim)


class LazyPims(Mapping[int, gtsam.PreintegratedCombinedMeasurements]):
    """`preintegrate`'s result as a read-only mapping that integrates interval k when it is
    asked for (the same sub-intervals in the same order: bit-identical) and keeps only the last
    `keep` intervals: a causal estimator walking the flight holds the sub-interval arrays
    (~64 bytes per IMU sample) instead of every interval's preintegration.
    `midpoint_attitude`: as `preintegrate`'s."""

    def __init__(
        self,
        frame_t: np.ndarray,
        imu: ImuData,
        covered: np.ndarray,
        params: gtsam.PreintegrationCombinedParams,
        midpoint_attitude: bool = False,
        keep: int = 4,
    ):
        k_of, self._dts, self._gyr, self._acc = imu_subintervals(frame_t, imu, covered)
        if midpoint_attitude:
            self._acc = midpoint_specific_force(self._gyr, self._acc, self._dts)
        # rows of interval k: first[k]:first[k + 1] (k_of is in time order)
        self._first = np.searchsorted(k_of, np.arange(len(covered) + 1))
        self._params = params
        self._keep = keep
        self._cache: dict[int, gtsam.PreintegratedCombinedMeasurements] = {}

    def __contains__(self, k: object) -> bool:
        if not isinstance(k, (int, np.integer)):  # a Python or numpy integer
            return False
        i = int(k)
        return 0 <= i < len(self._first) - 1 and bool(self._first[i] < self._first[i + 1])

    def __getitem__(self, k: int) -> gtsam.PreintegratedCombinedMeasurements:
        pim = self._cache.get(k)
        if pim is not None:
            return pim
        if k not in self:
            raise KeyError(k)
        k = int(k)
        pim = self.integrate(k)
        if len(self._cache) >= self._keep:
            del self._cache[next(iter(self._cache))]
        self._cache[k] = pim
        return pim

    def integrate(self, k: int) -> gtsam.PreintegratedCombinedMeasurements:
        """Interval k's preintegration (zero bias), integrated now and not kept."""
        pim = gtsam.PreintegratedCombinedMeasurements(self._params, gtsam.imuBias.ConstantBias())
        for j in range(self._first[k], self._first[k + 1]):
            pim.integrateMeasurement(self._acc[j], self._gyr[j], self._dts[j])
        return pim

    def __iter__(self) -> Iterator[int]:
        return iter(np.flatnonzero(np.diff(self._first) > 0).tolist())

    def __len__(self) -> int:
        return int(np.count_nonzero(np.diff(self._first) > 0))


def gyro_fill_rotations(T_init: np.ndarray, known: np.ndarray, pims: Mapping) -> int:
    """Initial rotations inside raw-pose gaps from the gyro instead of slerp (in place).

    Between frames a < b with raw poses and no raw pose in between, when the IMU covers every
    interval: R_k = R_a dR_ak Exp(s_k r), dR_ak the preintegrated rotation (zero bias),
    r = Log((R_a dR_ab)^T R_b) the end mismatch spread linearly in frame count (s_k = (k-a)/(b-a)).
    A drone turns up to ~3 rad in a 5 s blackout, which slerp between the ends cannot follow;
    the closer start saves Gauss-Newton iterations.  Returns the number of frames filled."""
    filled = 0
    for a, b in zip(known[:-1].tolist(), known[1:].tolist()):
        if b - a < 2 or any(k not in pims for k in range(a, b)):
            continue
        R = [T_init[a, :3, :3]]
        for k in range(a, b):
            R.append(R[-1] @ pims[k].deltaRij().matrix())
        r = gtsam.Rot3.Logmap(gtsam.Rot3(R[-1].T @ T_init[b, :3, :3]))
        for k in range(a + 1, b):
            T_init[k, :3, :3] = R[k - a] @ gtsam.Rot3.Expmap((k - a) / (b - a) * r).matrix()
            filled += 1
    return filled


# =========================================================================== problem


class FactorKind(Choice):
    """Robust factors, by what they measure (gated and counted per kind)."""

    POSE = "pose"  # per-frame QR pose (6-dof, position + yaw, or level pose)
    LOAD = "load"  # load-code centre in the front camera
    CORNERS = "corners"  # floor-code corners of one frame (tight coupling)
    FLOOR_CODE = "floor_code"  # one floor code's pose in one frame (as-built floor codes)


@dataclass
class RobustFactor:
    kind: FactorKind
    threshold: float  # kernel threshold, Mahalanobis units


@dataclass
class LoadFactorArgs:
    """What a load factor was built from (the incremental smoother rebuilds it on a new key)."""

    k: int  # frame
    j: int  # load index
    p_cam: np.ndarray  # (3,) m, camera frame
    cov_cam: np.ndarray  # (3, 3) m^2


@dataclass
class LoadTrack:
    """One load id's sightings in the flight."""

    load_id: str
    init_world: np.ndarray  # (3,) initial position (median of sightings)
    sightings: list[tuple[int, np.ndarray]]  # (frame, p_cam (3,)) in time order

    @property
    def n_obs(self) -> int:
        return len(self.sightings)


@dataclass
class GraphCounts:
    """What build_problem put into the graph (FusionResult.stats, JSON-ready via as_dict)."""

    raw_pose_input: RawPoseInput = RawPoseInput.POSE6
    tight: TightCoupling = TightCoupling.OFF
    imu_intervals: int = 0
    bridged_intervals: int = 0
    imu_segments: int = 0
    frames_outside_imu: int | None = None
    pose_factors: int = 0
    corner_factors: int = 0
    velocity_factors: int = 0
    load_factors: int = 0
    load_observations_skipped: int = 0

    def as_dict(self) -> dict:
        d = asdict(self)
        if self.frames_outside_imu is None:
            del d["frames_outside_imu"]
        return d


@dataclass
class Problem:
    """The factor graph of one flight, with each factor tagged by the frame at which it becomes
    available (the newest frame among its keys), and the initial values."""

    frame_t: np.ndarray  # (N,) int64 ns
    front_camera: CameraModel | None
    raw_input: RawPoseInput
    has_imu: bool
    k_first: int  # first frame with an inlier raw pose
    fix_frames: np.ndarray  # frames with a raw pose (sorted, unique)
    fix_T: dict[int, np.ndarray]  # frame -> raw T_world_body (4, 4)
    pose_threshold: float
    load_threshold: float
    T_init: np.ndarray  # (N, 4, 4)
    v_init: np.ndarray  # (N, 3)
    factors: list = field(default_factory=list)  # gtsam factors
    factor_frame: list[int] = field(default_factory=list)  # frame index per factor
    robust: dict[int, RobustFactor] = field(default_factory=dict)  # by factor index
    velocity: list[int] = field(default_factory=list)  # the velocity factors' indices
    load_args: dict[int, LoadFactorArgs] = field(default_factory=dict)  # by factor index
    loads: list[LoadTrack] = field(default_factory=list)  # by load index j
    pims: Mapping[int, gtsam.PreintegratedCombinedMeasurements] = field(default_factory=dict)
    initial: gtsam.Values = field(default_factory=gtsam.Values)
    counts: GraphCounts = field(default_factory=GraphCounts)
    as_built: asbuilt.AsBuiltGraph | None = None  # the as-built floor codes' variables

    @property
    def load_ids(self) -> list[str]:
        return [t.load_id for t in self.loads]

    def add(self, factor, k: int, kind: FactorKind | None = None, threshold: float | None = None) -> None:
        if kind is not None:
            if threshold is None:
                threshold = self.load_threshold if kind is FactorKind.LOAD else self.pose_threshold
            self.robust[len(self.factors)] = RobustFactor(kind, threshold)
        self.factors.append(factor)
        self.factor_frame.append(int(k))

    def graph(self, skip: AbstractSet[int] = frozenset()) -> gtsam.NonlinearFactorGraph:
        g = gtsam.NonlinearFactorGraph()
        for i, f in enumerate(self.factors):
            if i not in skip:
                g.add(f)
        return g


def tight_corner_data(
    frame_t: np.ndarray, floor_frames: dict | None, floor_camera: CameraModel | None, config: FusionConfig
) -> tuple[dict, TightCoupling]:
    """({frame index: (corners_world (4c, 3), corners_px (4c, 2), whitening (c, 8, 8))},
    TightCoupling) for tight coupling; {} when it is off or impossible."""
    if not config.tight:
        return {}, TightCoupling.OFF
    if not floor_frames or floor_camera is None:
        return {}, TightCoupling.NO_SIGHTINGS
    t = np.array(sorted(floor_frames), dtype=np.int64)
    idx = match_to_frames(frame_t, t, config.max_sync_s)
    out = {}
    for ts, k in zip(t.tolist(), idx.tolist()):
        sightings = [
            s for s in floor_frames[ts] if np.all(np.isfinite(np.asarray(s.detection.corners_px, float)))
        ]
        if k < 0 or not sightings:
            continue
        P = np.concatenate([np.asarray(s.corners_world, float).reshape(4, 3) for s in sightings])
        uv = np.concatenate([np.asarray(s.detection.corners_px, float).reshape(4, 2) for s in sightings])
        W = corner_whitening([s.detection for s in sightings], config.corner_sigma_px)
        W = W / math.sqrt(config.corner_noise_scale)
        out[k] = (P, uv, W)
    return out, TightCoupling.ON


def raw_pose_input(rawp: RawPoses, floor_camera: CameraModel | None) -> RawPoseInput:
    """What the raw poses constrain: the paper's position + yaw (no covariance), a gimbaled floor
    camera's level pose (PnP: roll / pitch unobserved), else the full pose."""
    if not rawp.full_pose:
        return RawPoseInput.POSITION_YAW
    if floor_camera is not None and floor_camera.gimbaled:
        return RawPoseInput.LEVEL_POSE
    return RawPoseInput.POSE6


def dead_reckon(
    frame_t: np.ndarray, T: np.ndarray, v: np.ndarray, anchor: int, pims: Mapping, v_anchor: np.ndarray
) -> None:
    """Initial values by IMU dead reckoning from frame `anchor` (in place), forward and
    backward through the preintegrated intervals (zero bias); intervals without IMU hold the
    pose and velocity.  Forward (Forster et al. 2017, eq. 33): R1 = R0 dR, v1 = v0 + g dt +
    R0 dV, p1 = p0 + v0 dt + g dt^2 / 2 + R0 dP; backward the same solved for the start."""
    v[anchor] = v_anchor
    for k in range(anchor, len(frame_t) - 1):
        T[k + 1], v[k + 1] = T[k], v[k]
        if k in pims:
            nav = pims[k].predict(gtsam.NavState(gtsam.Pose3(T[k]), v[k]), gtsam.imuBias.ConstantBias())
            T[k + 1], v[k + 1] = nav.pose().matrix(), nav.velocity()
    for k in range(anchor - 1, -1, -1):
        T[k], v[k] = T[k + 1], v[k + 1]
        if k in pims:
            pim = pims[k]
            dt = pim.deltaTij()
            R0 = T[k + 1, :3, :3] @ pim.deltaRij().matrix().T
            v0 = v[k + 1] - GRAVITY_W * dt - R0 @ pim.deltaVij()
            p0 = T[k + 1, :3, 3] - v0 * dt - 0.5 * GRAVITY_W * dt**2 - R0 @ pim.deltaPij()
            T[k] = np.eye(4)
            T[k, :3, :3], T[k, :3, 3], v[k] = R0, p0, v0


@functools.lru_cache(maxsize=ZERO_BIAS_CACHE_SIZE)
def _zero_biases(n: int) -> gtsam.Values:
    """B(0..n-1) all zero ConstantBias (read-only: copied by Values.insert).  Inserting a
    ConstantBias from Python costs ~60 us (the wrapper tries Values.insert's other overloads
    first), ~1 s per build of a 10-minute flight; the whole-flight solves share the frame count."""
    out = gtsam.Values()
    zero = gtsam.imuBias.ConstantBias()
    for k in range(n):
        out.insert(B(k), zero)
    return out


@dataclass
class SolveReuse:
    """What consecutive batch solves of one flight can share (`smooth`'s noise-scale solves;
    the shared whole-flight solve's states for the main smoother, `warm_values`).

    `pims`: the preintegrated IMU of the frame intervals, reused when the IMU object, the frame
    times and the preintegration settings are the same (`key`); `values`: the previous solution,
    the next solve's initial values for every key both graphs have (warm start: the same
    optimum, reached in fewer Levenberg-Marquardt iterations)."""

    pims: dict[int, gtsam.PreintegratedCombinedMeasurements] | None = None
    key: tuple | None = None
    frame_t: np.ndarray | None = None
    values: gtsam.Values | None = None

    def pims_for(self, frame_t: np.ndarray, imu: ImuData | None, config: FusionConfig) -> dict | None:
        if self.pims is None or imu is None or self.frame_t is None:
            return None
        same = self.key == _pims_key(imu, config) and np.array_equal(self.frame_t, frame_t)
        return self.pims if same else None

    def keep_pims(self, pb: Problem, imu: ImuData | None, config: FusionConfig) -> None:
        if imu is not None and isinstance(pb.pims, dict) and pb.pims:  # not a LazyPims
            self.pims, self.key, self.frame_t = pb.pims, _pims_key(imu, config), pb.frame_t


def _pims_key(imu: ImuData, config: FusionConfig) -> tuple:
    return (
        id(imu),
        tuple(vars(imu.noise).values()),  # a noise-scaled copy (variance.scaled_imu) differs
        len(imu.timestamps_ns),
        config.max_imu_gap_s,
        config.integration_sigma,
        config.imu_midpoint_attitude,
    )


def warm_values(initial: gtsam.Values, warm: gtsam.Values | None) -> gtsam.Values:
    """`initial` with every key that `warm` also holds set to its value in `warm` (a copy; the
    keys only in `warm` are ignored)."""
    if warm is None or warm.size() == 0:
        return initial
    mine = np.asarray(initial.keys(), dtype=np.uint64)
    theirs = np.asarray(warm.keys(), dtype=np.uint64)
    extra = np.setdiff1d(theirs, mine)
    if not len(extra) and len(theirs) == len(mine):
        return gtsam.Values(warm)
    w = gtsam.Values(warm)
    for key in extra.tolist():
        w.erase(key)
    out = gtsam.Values(initial)
    out.update(w)
    return out


def build_problem(
    frame_times_ns,
    imu: ImuData | None,
    raw: Trajectory,
    load_obs: list[LoadObservation] | None,
    front_camera: CameraModel | None,
    velocity: VelocityData | None = None,
    config: FusionConfig | None = None,
    floor_frames: dict | None = None,
    floor_camera: CameraModel | None = None,
    require_motion: bool = True,
    as_built: asbuilt.AsBuiltInput | None = None,
    *,
    pims: dict[int, gtsam.PreintegratedCombinedMeasurements] | None = None,
    lazy_imu: bool = False,
) -> Problem:
    """Check the inputs and build the factor graph and initial values (no optimisation).

    front_camera: the load camera (CameraModel, mount-aware), None without one (load
    observations are then skipped and counted).  floor_camera: the floor camera; with a
    gimbaled one the PnP poses are level-frame poses (RawPoseInput.LEVEL_POSE), and with
    `config.tight` and `floor_frames` {frame timestamp_ns: [FloorSighting]} the known world
    corners are reprojection factors on X(k) (factors.floor_corner_factor) instead of the raw
    pose factor at frames with floor sightings; the raw poses still give the initial values
    and the factors elsewhere.  `as_built` (fusion.estimate.asbuilt): each floor code's pose is a
    variable F(c) and each sighting a relative-pose factor, instead of the frame's pose factor.
    `pims`: the preintegrated IMU of an earlier build with the same frames, IMU and settings
    (SolveReuse), used instead of integrating again.  `lazy_imu` (the incremental smoother, which
    adds a frame's factors as it reaches the frame): no IMU factors and no initial values in the
    problem, and `pb.pims` a LazyPims that integrates an interval when asked, so the flight's
    IMU factors (~7 KB per frame) are never all held at once.

    Raises EstimationError for: no raw pose at all ("no floor code was read in this flight"),
    non-increasing / duplicated timestamps or NaNs in any input (naming the sample index), raw
    poses at no frame time, neither IMU nor velocity, a front camera that is not a CameraModel."""
    config = config or FusionConfig()
    inp = prepare_inputs(frame_times_ns, imu, raw, velocity, front_camera, config, require_motion)
    frame_t, rawp, imu, velocity = inp.frame_t, inp.raw, inp.imu, inp.velocity
    n = len(frame_t)
    use = inlier_raw_mask(rawp, config, frame_t)
    raw_input = raw_pose_input(rawp, floor_camera)
    T_init = initial_poses(frame_t, rawp, config, use)
    pb = Problem(
        frame_t=frame_t,
        front_camera=inp.front_camera,
        raw_input=raw_input,
        has_imu=imu is not None,
        k_first=int(rawp.frame_idx[use].min()),
        fix_frames=np.unique(rawp.frame_idx),
        fix_T={int(k): T for k, T in zip(rawp.frame_idx.tolist(), rawp.T_world_body)},
        pose_threshold=config.threshold(6 if raw_input is RawPoseInput.POSE6 else 4),
        load_threshold=config.threshold(3),
        T_init=T_init,
        v_init=initial_velocities(frame_t, T_init),
    )
    pb.counts.raw_pose_input = raw_input

    # ---- motion model between consecutive frames
    covered = np.zeros(max(n - 1, 0), bool)
    if imu is not None:
        covered = imu_coverage(frame_t, imu, config.max_imu_gap_s)
        params = factors.imu_params(imu.noise, imu.T_body_imu, config.integration_sigma)
        if pims is not None:
            pb.pims = pims
        elif lazy_imu:
            pb.pims = LazyPims(frame_t, imu, covered, params, config.imu_midpoint_attitude)
        else:
            pb.pims = preintegrate(frame_t, imu, covered, params, config.imu_midpoint_attitude)
    v0 = first_velocity(
        frame_t, rawp, use, pb.k_first, config.first_velocity_fixes, config.first_velocity_window_s
    )
    inlier_frames = np.unique(rawp.frame_idx[use])
    if len(inlier_frames) <= config.dead_reckoning_max_fixes:
        dead_reckon(frame_t, pb.T_init, pb.v_init, pb.k_first, pb.pims, v0)
    elif imu is not None:
        gyro_fill_rotations(pb.T_init, inlier_frames, pb.pims)
    for k in range(n - 1):
        if covered[k]:
            if not lazy_imu:
                pb.add(imu_factor(k, pb.pims[k]), k + 1)
        else:
            dt = (frame_t[k + 1] - frame_t[k]) * 1e-9
            for f in factors.bridge_factors(
                k,
                k + 1,
                dt,
                config.bridge_accel_sigma_m_s2,
                config.bridge_rate_sigma_rad_s,
                imu is not None,
                imu.noise if imu is not None else None,
                config.bridge_free_sigma_m,
                config.bridge_min_dt_s,
                config.bridge_min_sigma,
            ):
                pb.add(f, k + 1)
    # segments = maximal runs of IMU-covered intervals
    edges = np.diff(np.r_[0, covered.astype(int), 0])
    pb.counts.imu_intervals = int(covered.sum())
    pb.counts.bridged_intervals = int((~covered).sum())
    pb.counts.imu_segments = int((edges == 1).sum())
    if imu is not None:
        t0, t1 = imu.timestamps_ns[0], imu.timestamps_ns[-1]
        pb.counts.frames_outside_imu = int(((frame_t < t0) | (frame_t > t1)).sum())

    # ---- priors
    # the first velocity comes from a line through the first fixes; with fewer than two of them
    # it is unknown (zero, with the sigma of a drone's speed)
    near = np.abs(frame_t[inlier_frames] - frame_t[pb.k_first]) <= config.first_velocity_window_s * 1e9
    v_sigma = config.velocity_prior_sigma_m_s if near.sum() >= 2 else config.unknown_velocity_sigma_m_s
    pb.add(
        gtsam.PriorFactorVector(V(pb.k_first), v0, gtsam.noiseModel.Isotropic.Sigma(3, v_sigma)), pb.k_first
    )
    if imu is not None:
        pb.add(
            gtsam.PriorFactorConstantBias(
                B(pb.k_first),
                gtsam.imuBias.ConstantBias(),
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.r_[
                        np.full(3, config.bias_prior_sigma_accel_m_s2),
                        np.full(3, config.bias_prior_sigma_gyro_rad_s),
                    ]
                ),
            ),
            pb.k_first,
        )

    # ---- QR pose factors (or, tightly coupled, corner reprojection factors)
    corner_frames, pb.counts.tight = tight_corner_data(frame_t, floor_frames, floor_camera, config)
    kernel = config.robust_kernel
    if as_built is not None and not corner_frames and raw_input is RawPoseInput.POSE6:
        pb.as_built = asbuilt.add_factors(pb, as_built, frame_t, pb.fix_frames, config, FactorKind.FLOOR_CODE)
    replaced = pb.as_built.frames if pb.as_built is not None else set()
    for m, k in enumerate(rawp.frame_idx.tolist()):
        if k in corner_frames or k in replaced:
            continue
        T = rawp.T_world_body[m]
        if raw_input is RawPoseInput.POSE6:
            assert rawp.covariances is not None  # full_pose
            f = factors.pose_prior_factor(k, T, rawp.covariances[m], kernel, pb.pose_threshold)
        elif raw_input is RawPoseInput.LEVEL_POSE:
            assert rawp.covariances is not None  # full_pose
            f = factors.level_pose_factor(k, T, rawp.covariances[m][2:, 2:], kernel, pb.pose_threshold)
        else:
            f = factors.position_yaw_factor(
                k,
                T[:3, 3],
                float(yaw_of(T[:3, :3])),
                config.paper_sigma_xyz_m,
                config.paper_sigma_yaw_rad,
                kernel,
                pb.pose_threshold,
            )
        pb.add(f, k, FactorKind.POSE)
        pb.counts.pose_factors += 1
    for k, (P, uv, W) in sorted(corner_frames.items()):
        assert floor_camera is not None  # corner_frames exist only with a floor camera
        thr = config.threshold(8 * len(W))
        pb.add(
            factors.floor_corner_factor(
                k, floor_camera, P, uv, W, kernel, thr, config.corner_behind_residual
            ),
            k,
            FactorKind.CORNERS,
            thr,
        )
    pb.counts.corner_factors = len(corner_frames)

    # ---- velocity factors
    # each sample once, at its nearest frame; the gravity term at the initial attitude
    vel = velocity_at_frames(frame_t, velocity, config, imu)
    for k in np.flatnonzero(vel.mask).tolist():
        v_k = vel.measured(k, pb.T_init[k, :3, :3])
        pb.velocity.append(len(pb.factors))
        pb.add(factors.body_velocity_factor(k, v_k, float(vel.sigma_m_s[k])), k)
    pb.counts.velocity_factors = int(vel.mask.sum())

    # ---- loads
    cam = pb.front_camera
    if cam is not None:  # each sighting from the body pose at its own stamp
        load_obs = retime_load_obs(frame_t, pb.T_init, load_obs or [], cam)
    groups, skipped = group_load_obs(frame_t, load_obs or [], config)
    if cam is None:
        skipped += sum(len(obs) for obs in groups.values())
        groups = {}
    for j, lid in enumerate(sorted(groups)):
        assert cam is not None  # groups is empty without a front camera
        obs = groups[lid]
        k_obs = np.array([k for k, _ in obs])
        p_cam = np.array([np.asarray(o.p_cam, float) for _, o in obs])
        for (k, o), pc in zip(obs, p_cam):
            cov_cam = np.asarray(o.cov_cam, float)
            pb.load_args[len(pb.factors)] = LoadFactorArgs(k, j, pc, cov_cam)
            pb.add(factors.load_factor(k, j, pc, cov_cam, cam, kernel, pb.load_threshold), k, FactorKind.LOAD)
        T_wc = cam.T_world_cam(pb.T_init[k_obs])
        pts = np.einsum("nij,nj->ni", T_wc[:, :3, :3], p_cam) + T_wc[:, :3, 3]
        order = np.argsort(k_obs, kind="stable")
        pb.loads.append(LoadTrack(lid, np.median(pts, axis=0), [(int(k_obs[i]), p_cam[i]) for i in order]))
    pb.counts.load_observations_skipped = skipped
    pb.counts.load_factors = sum(t.n_obs for t in pb.loads)

    # ---- initial values
    if lazy_imu:
        return pb
    for k in range(n):
        pb.initial.insert(X(k), gtsam.Pose3(pb.T_init[k]))
        pb.initial.insert(V(k), pb.v_init[k])
    if imu is not None:
        pb.initial.insert(_zero_biases(n))
    for j, track in enumerate(pb.loads):
        pb.initial.insert(L(j), track.init_world)
    return pb


def robust_distances(
    pb: Problem, values: gtsam.Values, skip: AbstractSet[int] = frozenset()
) -> dict[int, float]:
    """Mahalanobis distance (whitened residual norm before the kernel) of each robust factor."""
    return {i: mahalanobis(pb.factors[i], values) for i in pb.robust if i not in skip}


def mahalanobis(factor, values: gtsam.Values) -> float:
    e = factor.unwhitenedError(values)
    nm = factor.noiseModel()
    return (
        nm.noise().mahalanobisDistance(e)
        if isinstance(nm, gtsam.noiseModel.Robust)
        else nm.mahalanobisDistance(e)
    )


def count_rejections(pb: Problem, dist: dict[int, float]) -> dict[FactorKind, int]:
    """Robust factors whose Mahalanobis distance exceeds the kernel threshold, per kind."""
    out = dict.fromkeys(FactorKind, 0)
    for i, d in dist.items():
        if d > pb.robust[i].threshold:
            out[pb.robust[i].kind] += 1
    return out


def fix_health(pb: Problem, config: FusionConfig, health: SolveHealth) -> None:
    """Fixes, frames far from every fix, and the dead-reckoning label (in place)."""
    fix_t = pb.frame_t[pb.fix_frames]
    health.fixes = len(fix_t)
    j = np.clip(np.searchsorted(fix_t, pb.frame_t), 1, max(len(fix_t) - 1, 1))
    d = np.abs(pb.frame_t - fix_t[np.minimum(j, len(fix_t) - 1)])
    if len(fix_t) > 1:
        d = np.minimum(d, np.abs(pb.frame_t - fix_t[j - 1]))
    health.frames_far_from_fix = int((d > config.far_from_fix_s * 1e9).sum())
    if health.fixes <= config.dead_reckoning_max_fixes:
        health.mode = SolveMode.DEAD_RECKONED
        span = (pb.frame_t[-1] - pb.frame_t[0]) * 1e-9
        health.note(
            f"dead-reckoned: {health.fixes} fix(es) in {span:.1f} s; the estimate is "
            "IMU / velocity integration from it, sigma grows with the distance in time"
        )


# =========================================================================== batch


class LMStop(Choice):
    """Why levenberg_marquardt stopped."""

    CONVERGED = "converged"
    ITERATION_LIMIT = "iteration_limit"
    STALLED = "stalled"  # no damping up to lambda_max lowered the error


@dataclass
class LMResult:
    values: gtsam.Values
    iterations: int
    # the undamped linearisation of the last accepted step, reusable for marginal covariances;
    # None if that step was damped or the model-misfit test stopped (linearise at `values`)
    linear: gtsam.GaussianFactorGraph | None
    stop: LMStop


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    config: FusionConfig | None = None,
    ordering: gtsam.Ordering | None = None,
    errors: list | None = None,
    qr: bool = False,
) -> LMResult:
    """Levenberg-Marquardt (Nocedal & Wright 2006, Sec. 10.3; GTSAM's defaults: lambda0 1e-5,
    factor 10, identity damping) driven from Python around GTSAM's linearize / multifrontal
    elimination, with one COLAMD ordering computed up front and reused.  Each iteration first
    tries the undamped Gauss-Newton step and damps only if that does not lower the error (from
    a good initial guess the first steps succeed).  Stops when an accepted step lowers the error
    by less than lm_relative_tol (GTSAM's relativeErrorTol), or when an undamped step's actual
    decrease matches the linear model's predicted decrease to within lm_relative_tol of the
    error: the model misfit bounds what a further step could gain, so the usual last step that
    only confirms convergence (a full linearise + eliminate) is skipped.  A step that no
    damping up to lm_lambda_max makes descend is a stall, unless the error is already below
    lm_absolute_error_tol: there it meets rounding (an exactly determined solve sits at ~1e-20)
    and the solve has converged.

    Why not gtsam.LevenbergMarquardtOptimizer: with Python CustomFactors in the graph its
    linearisation is 8-110x slower than `graph.linearize` called from Python on the same graph
    (measured here, gtsam 4.3.0 wheel, same optimum; GTSAM issue #875: CustomFactor overhead).

    `qr`: eliminate by Householder QR on the whitened Jacobians instead of GTSAM's default
    (Cholesky on the normal equations, which squares the condition number: a long IMU-only
    stretch then looks indeterminate to it); slower, used by `solve` as the first fallback.
    Raises what GTSAM raises on a singular system (RuntimeError: IndeterminantLinearSystem;
    ValueError: a variable of the ordering in no factor); `solve` handles those.
    `errors`, if given, receives the graph error at the start and after each accepted step."""
    config = config or FusionConfig()
    if ordering is None:
        ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
    err = graph.error(values)
    if errors is not None:
        errors.append(err)
    lam = 0.0  # try the Gauss-Newton step first; damp only when it fails to descend
    dims = values.dims()  # each variable's tangent dimension, for the damping
    it = 0
    stop = LMStop.ITERATION_LIMIT
    lin = None
    undamped = False
    for it in range(1, config.lm_max_iterations + 1):
        lin = graph.linearize(values)
        stalled = False
        while True:
            system = lin
            if lam > 0:
                system = lin.clone()
                _add_damping(system, dims, lam)
            tree = (
                system.eliminateMultifrontal(ordering, gtsam.EliminateQR)
                if qr
                else system.eliminateMultifrontal(ordering)
            )
            delta = tree.optimize()
            trial = values.retract(delta)
            new_err = graph.error(trial)
            if new_err <= err:
                break
            lam = config.lm_lambda0 if lam == 0.0 else lam * config.lm_lambda_factor
            if lam > config.lm_lambda_max:
                stalled = True
                break
        if stalled:
            at_floor = err <= config.lm_absolute_error_tol  # nothing left to lower (FusionConfig)
            return LMResult(values, it, None, LMStop.CONVERGED if at_floor else LMStop.STALLED)
        undamped = lam == 0.0
        converged = (err - new_err) <= config.lm_relative_tol * max(err, 1e-300)
        if undamped and not converged:
            # the linear model's misfit on this step bounds what another step could still gain
            predicted = lin.error(gtsam.VectorValues.Zero(delta)) - lin.error(delta)
            if abs((err - new_err) - predicted) <= config.lm_relative_tol * max(new_err, 1e-300):
                converged = True
                lin = None  # the covariance pass linearises at the solution
        values, err = trial, new_err
        if errors is not None:
            errors.append(err)
        lam = lam / config.lm_lambda_factor if lam > config.lm_lambda0 else 0.0
        if converged:
            stop = LMStop.CONVERGED
            break
    return LMResult(values, it, lin if undamped and stop is LMStop.CONVERGED else None, stop)


def _add_damping(lin: gtsam.GaussianFactorGraph, dims: dict[int, int], lam: float) -> None:
    """Identity damping lam * I on every variable, sized by its own tangent dimension (a factor
    of the wrong size on a variable is undefined behaviour in GTSAM's elimination)."""
    s = math.sqrt(lam)
    for k, d in dims.items():
        lin.push_back(gtsam.JacobianFactor(k, s * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d)))


def weak_priors(values: gtsam.Values, config: FusionConfig) -> list:
    """A weak prior at its current value on every variable (FusionConfig.fallback_sigma_*):
    keeps a singular system solvable without moving a well-constrained estimate."""
    out: list = []
    rot, pos = config.fallback_sigma_rot_rad, config.fallback_sigma_pos_m
    pose_model = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, rot), np.full(3, pos)])
    for key in values.keys():
        c = gtsam.Symbol(key).chr()
        if c == ord("x"):
            out.append(gtsam.PriorFactorPose3(key, values.atPose3(key), pose_model))
        elif c == ord("v"):
            out.append(
                gtsam.PriorFactorVector(
                    key,
                    values.atVector(key),
                    gtsam.noiseModel.Isotropic.Sigma(3, config.fallback_sigma_vel_m_s),
                )
            )
        elif c == ord("b"):
            out.append(
                gtsam.PriorFactorConstantBias(
                    key,
                    values.atConstantBias(key),
                    gtsam.noiseModel.Isotropic.Sigma(6, config.fallback_sigma_bias),
                )
            )
        elif c == ord("l"):
            out.append(
                gtsam.PriorFactorPoint3(key, values.atPoint3(key), gtsam.noiseModel.Isotropic.Sigma(3, pos))
            )
    return out


def solve(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    config: FusionConfig,
    health: SolveHealth,
    ordering: gtsam.Ordering | None = None,
    errors: list | None = None,
) -> tuple[LMResult, gtsam.NonlinearFactorGraph, gtsam.Ordering]:
    """levenberg_marquardt with the failures recorded in `health`.  A singular linear system
    (IndeterminantLinearSystem, an ordering variable in no factor) is retried with QR
    elimination (nearly indeterminate for Cholesky only, e.g. seconds of IMU-only motion), then
    with QR and weak_priors on every state (a variable nothing constrains); each retry is
    counted in linear_fallbacks, and iteration-limit stops and stalls are counted.  Returns the
    result, the graph and the ordering actually solved (for the covariances).  A failure of
    the last retry raises EstimationError with GTSAM's reason."""
    ordering = ordering or gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
    try:
        res = levenberg_marquardt(graph, values, config, ordering, errors)
    except (RuntimeError, ValueError) as e:
        reason = _first_line(e)
        log.warning("singular linear system (%s): retrying with QR elimination", reason)
        health.linear_fallbacks += 1
        health.note(f"singular linear system for Cholesky ({reason}): solved by QR")
        try:
            res = levenberg_marquardt(graph, values, config, ordering, errors, qr=True)
        except (RuntimeError, ValueError) as e2:
            log.warning(
                "singular linear system (%s): retrying with weak priors on every state", _first_line(e2)
            )
            health.linear_fallbacks += 1
            health.note(
                f"singular linear system ({_first_line(e2)}): solved again with weak priors on every state"
            )
            priors = weak_priors(values, config)
            health.weak_prior_states += len(priors)
            graph = gtsam.NonlinearFactorGraph(graph)
            for f in priors:
                graph.add(f)
            ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
            try:
                res = levenberg_marquardt(graph, values, config, ordering, errors, qr=True)
            except (RuntimeError, ValueError) as e3:
                raise EstimationError(
                    f"the factor graph cannot be solved even with weak priors: {_first_line(e3)}"
                ) from None
    if res.stop is LMStop.ITERATION_LIMIT:
        health.iteration_limit_hits += 1
        health.note(
            f"Levenberg-Marquardt stopped at its iteration limit "
            f"({config.lm_max_iterations}) before converging"
        )
    elif res.stop is LMStop.STALLED:
        health.lm_stalls += 1
        health.note("Levenberg-Marquardt stalled: no damping lowered the error")
    return res, graph, ordering


def _first_line(e: Exception) -> str:
    """GTSAM's messages run over several lines; the first (plus the variable) names the cause."""
    lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
    if not lines:
        return type(e).__name__
    return " ".join(lines[:2]) if lines[0].endswith("variable") else lines[0]


def gate_outliers(
    pb: Problem, dist: dict[int, float], config: FusionConfig, health: SolveHealth
) -> tuple[set[int], list, dict[FactorKind, int]]:
    """Factors to remove after the robust solve (Mahalanobis distance beyond outlier_gate),
    weak priors that keep their variables constrained, and the counts per kind.

    Fixes (pose / corner factors) are gated only when at most max_gated_fraction of them are
    beyond the gate; otherwise the motion model, not the fixes, is suspect (IMU units, clock),
    and removing most fixes would leave the trajectory unanchored: none is removed and the
    skip is counted.  A load whose every sighting is gated is taken out of the map (its
    variable keeps a weak prior at its current value, so the graph stays solvable)."""
    gated = dict.fromkeys(FactorKind, 0)
    if config.outlier_gate is None:
        return set(), [], gated
    beyond = {i for i, d in dist.items() if d > config.outlier_gate}
    fixes = [i for i in dist if pb.robust[i].kind is not FactorKind.LOAD]
    bad_fixes = [i for i in fixes if i in beyond]
    if fixes and len(bad_fixes) > config.max_gated_fraction * len(fixes):
        health.gate_skipped += len(bad_fixes)
        health.note(
            f"{len(bad_fixes)} of {len(fixes)} fixes disagree with the motion model "
            "beyond the outlier gate: not removed (IMU units, scale or clock suspect)"
        )
        beyond -= set(bad_fixes)
    for i in beyond:
        gated[pb.robust[i].kind] += 1
    priors = []
    by_load: dict[int, list[int]] = {}
    for i, a in pb.load_args.items():
        by_load.setdefault(a.j, []).append(i)
    for j, idx in by_load.items():
        if all(i in beyond for i in idx):
            health.loads_dropped.append(pb.loads[j].load_id)
            priors.append(j)
    if health.loads_dropped:
        health.note(
            f"{len(health.loads_dropped)} load(s) with every sighting beyond the "
            f"outlier gate left out of the map: {', '.join(health.loads_dropped[:5])}"
        )
    return beyond, priors, gated


def jumped_fixes(pb: Problem, config: FusionConfig) -> set[int]:
    """Pose factors left out of the first batch solve: the fixes of short segments between
    physical impossibilities.  Consecutive fixes further apart than reinit_max_speed_m_s allows
    split the fixes into segments; one side of each split is wrong (a misprinted or misread
    code).  A segment shorter than reinit_lookback_s is suspect (a code read while crossing it:
    Huber's linear pull of a consistent run would otherwise bend the IMU chain towards it,
    worst at the flight's ends); `_smooth_once` takes suspects back when the solution without
    them agrees with them.  None when the suspects would exceed max_gated_fraction of the fixes."""
    pose_at = {pb.factor_frame[i]: i for i, r in pb.robust.items() if r.kind is FactorKind.POSE}
    ks = np.array(sorted(pose_at), dtype=np.int64)
    if len(ks) < 2:
        return set()
    t = pb.frame_t[ks] * 1e-9
    p = np.array([pb.fix_T[int(k)][:3, 3] for k in ks])
    jump = fix_jumps(t, p, config.reinit_max_speed_m_s)
    if not jump.any():
        return set()
    seg = np.r_[0, np.cumsum(jump)]
    suspects: list[int] = []
    for g in range(int(seg[-1]) + 1):
        members = np.flatnonzero(seg == g)
        if t[members[-1]] - t[members[0]] < config.reinit_lookback_s:
            suspects.extend(pose_at[int(ks[m])] for m in members)
    if len(suspects) > config.max_gated_fraction * len(ks):
        return set()
    return set(suspects)


def release_heap() -> None:
    """Hand the heap freed by GTSAM's eliminations back to the OS (glibc keeps it otherwise:
    ~250 MB after a 10-minute flight), so the covariance pass does not stack on top of it."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def poses_of(values: gtsam.Values, n: int) -> np.ndarray:
    """(n, 4, 4) T_world_body of X(0..n-1) (the only Pose3 keys besides the floor codes' F)."""
    rows = gtsam.utilities.extractPose3(values)  # per pose: R row-major (9), t (3), key order
    rows = rows[max(rows.shape[0] - n, 0) :]  # as-built floor codes F(c) sort before X(k)
    if rows.shape[0] != n:
        raise EstimationError(f"expected {n} poses in the solution, found {rows.shape[0]}")
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = rows[:, :9].reshape(n, 3, 3)
    T[:, :3, 3] = rows[:, 9:]
    return T


def smooth(
    frame_times_ns,
    imu: ImuData | None,
    raw: Trajectory,
    load_obs: list[LoadObservation] | None,
    front_camera: CameraModel | None = None,
    velocity: VelocityData | None = None,
    config: FusionConfig | None = None,
    floor_frames: dict | None = None,
    floor_camera: CameraModel | None = None,
    as_built: asbuilt.AsBuiltInput | None = None,
    warm_start: gtsam.Values | None = None,
    reuse: SolveReuse | None = None,
    resolves: ResolvePredicate | None = None,
) -> FusionResult:
    """Batch Levenberg-Marquardt smoothing of a whole flight (offline), with marginal covariances.

    frame_times_ns (N,) int64: floor-camera frame times (one state each); imu: ImuData or None
    (then velocity is required: velocity-only mode); raw: per-frame QR poses at a subset of the
    frame times (with (M,6,6) covariances, or None for the paper's position + yaw);
    load_obs: front-camera load observations with p_cam / cov_cam; front_camera: the load
    camera's CameraModel (mount-aware; None: no loads); floor_camera: the floor camera's
    CameraModel (a gimbaled one makes the PnP poses level-frame poses); floor_frames
    {frame timestamp_ns: [fusion.qr.codes.FloorSighting]}: used only with config.tight.
    Returns FusionResult with the trajectory at every frame time (covariances (N,6,6), Pose3
    order, body frame), the load map (3x3 world covariances), stats (iterations,
    initial/final error, rejected_* = robust factors beyond the kernel threshold at the robust
    solution, gated_* = those beyond `outlier_gate`, removed before the final solve, IMU
    segments / bridged intervals, times, `health` as a dict) and `health` (SolveHealth).
    Never raises a GTSAM exception: a singular system is retried by QR, then with weak priors,
    and only a third failure ends in EstimationError.  When most fixes disagree with the IMU
    beyond the outlier gate (config.reject_disagreeing_imu), the flight is solved again
    without the IMU (random-walk model and velocity): health.mode IMU_REJECTED.
    `as_built` (fusion.estimate.asbuilt.build_input): as-built floor codes, estimated in
    FusionResult.floor_codes.  `warm_start`: initial values for the keys it holds (e.g. the
    states X, V, B of an earlier whole-flight solve of these frames, SolveReuse); the noise-scale
    solves after the first start from the previous solution and reuse its preintegrated IMU.
    A warm start changes only where Levenberg-Marquardt starts: the optimum is the same within
    its stopping tolerance.  `reuse`: a SolveReuse carried over from an earlier call (e.g. the
    time-offset profile's solves of shifted frames), left holding this call's solution.
    `resolves` (variance.ResolvePredicate): whether the caller will solve again after the last
    solve (then its covariances are skipped: stats covariance_method "skipped")."""
    config = config or FusionConfig()
    if reuse is None:
        reuse = SolveReuse()
    if warm_start is not None:
        reuse.values = warm_start

    def once(imu_, raw_, load_obs_, config_, require_motion=True, resolves=None):
        return _smooth_once(
            frame_times_ns,
            imu_,
            raw_,
            load_obs_,
            front_camera,
            velocity,
            config_,
            floor_frames,
            floor_camera,
            require_motion,
            as_built=as_built,
            resolves=resolves,
            reuse=reuse if imu_ is imu else None,
        )

    res, scaled = solve_noise_scaled(once, imu, raw, load_obs, config, then=resolves)  # variance.py
    if not (res.health.gate_skipped and imu is not None and config.reject_disagreeing_imu):
        return res
    # most fixes disagree with the IMU: its units, the world's scale or a clock are wrong, and
    # the IMU's confident factors would drag the trajectory away from every fix
    log.warning("smoother: most fixes disagree with the IMU; solving again without it")
    alt = scaled(None, require_motion=False)
    h = alt.health
    h.mode = SolveMode.IMU_REJECTED
    h.reasons = list(
        dict.fromkeys(
            [
                f"{res.health.gate_skipped} of {res.health.fixes} fixes disagreed with the IMU beyond "
                "the outlier gate: solved again without the IMU (random-walk motion model"
                + (", velocity" if velocity is not None else "")
                + "); check the IMU's units and "
                "clock, and world.yaml's side_m / payload_unit_m"
            ]
            + h.reasons
        )
    )
    h.gate_skipped += res.health.gate_skipped
    h.iteration_limit_hits += res.health.iteration_limit_hits
    h.lm_stalls += res.health.lm_stalls
    h.linear_fallbacks += res.health.linear_fallbacks
    alt.stats["health"] = h.as_dict()
    alt.stats["imu_rejected"] = True
    return alt


def _smooth_once(
    frame_times_ns,
    imu,
    raw,
    load_obs,
    front_camera,
    velocity,
    config,
    floor_frames,
    floor_camera,
    require_motion: bool = True,
    as_built: asbuilt.AsBuiltInput | None = None,
    resolves: ResolvePredicate | None = None,
    reuse: SolveReuse | None = None,
) -> FusionResult:
    """One batch solve (smooth without the IMU-rejection retry).  `resolves(variance
    components, health)` True: the noise-scale iteration will solve again, so the marginal
    covariances are not computed (covariance_method "skipped").  `reuse`: the preintegrated IMU
    and initial values from the previous solve (updated with this one's)."""
    t0 = time.perf_counter()
    pb = build_problem(
        frame_times_ns,
        imu,
        raw,
        load_obs,
        front_camera,
        velocity,
        config,
        floor_frames,
        floor_camera,
        require_motion,
        as_built,
        pims=None if reuse is None else reuse.pims_for(np.asarray(frame_times_ns), imu, config),
    )
    initial = pb.initial
    if reuse is not None:
        reuse.keep_pims(pb, imu, config)
        initial = warm_values(pb.initial, reuse.values)
    health = SolveHealth()
    fix_health(pb, config, health)
    t_build = time.perf_counter() - t0
    suspects = jumped_fixes(pb, config)
    graph = pb.graph(suspects)
    errors: list[float] = []
    res, graph, ordering = solve(graph, initial, config, health, errors=errors)
    values, iterations, lin = res.values, res.iterations, res.linear
    err0 = errors[0]
    dist = robust_distances(pb, values)
    rej = count_rejections(pb, dist)
    drop, dropped_loads, gated = gate_outliers(pb, dist, config, health)
    if drop != suspects or dropped_loads:
        graph = pb.graph(drop)
        for j in dropped_loads:
            graph.add(
                gtsam.PriorFactorPoint3(
                    L(j),
                    values.atPoint3(L(j)),
                    gtsam.noiseModel.Isotropic.Sigma(3, config.fallback_sigma_pos_m),
                )
            )
        res, graph, ordering = solve(graph, values, config, health, ordering, errors)
        values, lin = res.values, res.linear
        iterations += res.iterations
    if reuse is not None:
        reuse.values = values
    t_opt = time.perf_counter() - t0 - t_build
    variance_components: dict | None = {}
    # each factor's variance group beyond the IMU's and "other" (variance.factor_groups)
    kinds = {i: str(r.kind) for i, r in pb.robust.items()}
    kinds.update(dict.fromkeys(pb.velocity, str(NoiseGroup.VELOCITY)))
    at_solution = None  # the graph linearised at `values` (the variance components')
    if config.check_noise:
        try:
            at_solution = graph.linearize(values)
        except (RuntimeError, ValueError) as e:
            log.debug("no linearisation at the solution: %s", e)
        variance_components = problem_variance_components(pb.factors, kinds, drop, graph, values, at_solution)
    if lin is not None:
        at_solution = None  # the covariances use the last step's linearisation
    release_heap()
    n = len(pb.frame_t)
    T = poses_of(values, n)
    cov = None
    lcov = {}
    n_codes = len(pb.as_built.code_of_var) if pb.as_built is not None else 0
    ccov = None  # (n_codes, 6, 6) as-built floor codes
    covariance_method = "none"
    skip_covariances = resolves is not None and resolves(variance_components, health)
    if skip_covariances:
        covariance_method = "skipped"
    covariance_scales = None  # config.covariances_at_first_scales: the scales they are at
    if config.compute_covariances and not skip_covariances:
        if lin is None:  # the last step was damped: linearise at the solution
            lin = at_solution if at_solution is not None else graph.linearize(values)
        weights = None
        approximate = n_codes > asbuilt.EXACT_MARGINALS_MAX_CODES and pb.as_built is not None
        if (
            config.covariances_at_first_scales
            and variance_components
            and lin.size() == graph.size()
            and not approximate  # (those marginals take no weights: at the solve's own scales)
        ):
            # the covariances of the graph at the scales s_g that these variance components
            # give (what the next solve applies), from this linearisation: each group's
            # whitened rows times 1 / sqrt(s_g) (its Hessian block over s_g; exact at this
            # point for the Gaussian and the inlier robust rows, whose kernel weight is 1 at
            # either scale; a row beyond the kernel keeps the weight of its residual here)
            scales = first_solve_scales(variance_components, config.pose_scale_floor)
            groups = factor_groups(pb.factors, kinds, drop, graph.size())
            weights = np.array([1.0 / math.sqrt(scales.of(g)) for g in groups])
            covariance_scales = {
                str(g): scales.of(g) for g in (NoiseGroup.POSE, NoiseGroup.CORNERS, NoiseGroup.LOAD)
            }
        bulk: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None
        try:
            if approximate and pb.as_built is not None:
                bulk = asbuilt.approximate_marginals(lin, values, n, pb.has_imu, len(pb.loads), pb.as_built)
                covariance_method = "chain_given_codes"
            elif n_codes:
                bulk = chain_marginals_with_codes(
                    lin, n, pb.has_imu, len(pb.loads), n_codes, row_weights=weights
                )
            else:
                two = chain_marginals(lin, n, pb.has_imu, len(pb.loads), row_weights=weights)
                bulk = None if two is None else (two[0], two[1], None)
        except np.linalg.LinAlgError:
            bulk = None
        if bulk is None:
            covariance_scales = None  # gtsam's Bayes tree below: at the solve's own scales
        if bulk is not None:
            cov, lc, ccov = bulk
            lcov = dict(enumerate(lc))
        else:  # not the chain structure: gtsam's Bayes tree, key by key
            try:
                tree = lin.eliminateMultifrontal(ordering, gtsam.EliminateQR)
                cov = np.empty((n, 6, 6))
                for k in range(n):
                    cov[k] = tree.marginalCovariance(X(k))
                for j in range(len(pb.loads)):
                    lcov[j] = tree.marginalCovariance(L(j))
                if n_codes:
                    ccov = np.array([tree.marginalCovariance(asbuilt.F(c)) for c in range(n_codes)])
            except (RuntimeError, ValueError) as e:
                cov, lcov = None, {}
                health.note(f"no covariances: the linearised system is singular ({e})")
        if bulk is None or covariance_method == "none":
            covariance_method = "chain" if bulk is not None else ("bayes_tree" if cov is not None else "none")
    t_cov = time.perf_counter() - t0 - t_build - t_opt
    dropped = set(health.loads_dropped)
    loads = LoadMap(
        str(Estimator.SMOOTHER),
        [
            LoadEstimate(t.load_id, values.atPoint3(L(j)).copy(), lcov.get(j), t.n_obs)
            for j, t in enumerate(pb.loads)
            if t.load_id not in dropped
        ],
    )
    stats = dict(
        pb.counts.as_dict(),
        iterations=iterations,
        initial_error=float(err0),
        final_error=float(errors[-1]),
        robust_kernel=config.robust_kernel,
        pose_threshold=pb.pose_threshold,
        n_factors=len(pb.factors),
        covariance_method=covariance_method,
        time_build_s=t_build,
        time_optimize_s=t_opt,
        time_covariance_s=t_cov,
        time_s=time.perf_counter() - t0,
    )
    for kind, word in ((FactorKind.POSE, "pose"), (FactorKind.LOAD, "load"), (FactorKind.CORNERS, "corner")):
        stats[f"gated_{word}_factors"] = gated[kind]
        stats[f"rejected_{word}_factors"] = rej[kind]
    stats["health"] = health.as_dict()
    stats["variance_components"] = variance_components
    if config.covariances_at_first_scales:
        stats["covariance_scales"] = covariance_scales
    traj = Trajectory(str(Estimator.SMOOTHER), pb.frame_t.copy(), T, cov)
    out = FusionResult(traj, loads, stats, health)
    if pb.as_built is not None and as_built is not None:
        out.floor_codes = asbuilt.floor_code_estimates(
            values, pb.as_built, as_built, ccov, str(Estimator.SMOOTHER)
        )
        stats.update(
            asbuilt.graph_stats(pb.as_built, gated[FactorKind.FLOOR_CODE], rej[FactorKind.FLOOR_CODE])
        )
    return out


# =========================================================================== incremental


LOAD_GENERATION_STRIDE = 10**9  # L(j + g * stride): generation g of load j's variable
_CHR_SHIFT, _IDX_MASK = 56, (1 << 56) - 1


def _frame_of(key: int) -> int:
    """Frame index of an X / V / B key, -1 for a load key."""
    return -1 if (key >> _CHR_SHIFT) == ord("l") else key & _IDX_MASK


@dataclass
class _Streak:
    """Consecutive fixes beyond the kernel threshold at the predicted state (incremental)."""

    frames: list[int] = field(default_factory=list)
    t_s: list[float] = field(default_factory=list)
    offsets_m: list[np.ndarray] = field(default_factory=list)  # fix - prediction, world
    offsets_yaw: list[float] = field(default_factory=list)
    # d(offset)/dt of the last agreeing streak (world, m/s): the estimate's velocity error
    velocity_offset_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def clear(self) -> None:
        self.frames.clear()
        self.t_s.clear()
        self.offsets_m.clear()
        self.offsets_yaw.clear()

    def agrees(self, config: FusionConfig) -> bool:
        """Enough fixes, and their offsets from the IMU prediction agree with each other up to a
        position and velocity error of the estimate (a line in time fits them: the fixes move
        as the IMU says, so the estimate, not the fixes, is off; an estimate left with a wrong
        velocity after a blackout drifts from the fixes linearly)."""
        m = config.reinit_rejected_fixes
        if len(self.frames) < m:
            return False
        t = np.array(self.t_s[-m:])
        t = t - t.mean()
        A = np.c_[np.ones(m), t]
        d = np.array(self.offsets_m[-m:])
        y = np.unwrap(np.array(self.offsets_yaw[-m:]))
        cd, *_ = np.linalg.lstsq(A, d, rcond=None)
        cy, *_ = np.linalg.lstsq(A, y, rcond=None)
        spread_m = np.linalg.norm(d - A @ cd, axis=1).max()
        spread_yaw = np.abs(y - A @ cy).max()
        self.velocity_offset_m_s = cd[1]
        return spread_m <= config.reinit_agreement_m and spread_yaw <= config.reinit_agreement_rad


def fixes_jumped(pb: Problem, k: int, config: FusionConfig) -> bool:
    """Whether two consecutive raw fixes within config.reinit_lookback_s before frame k (k
    included) are further apart than config.reinit_max_speed_m_s allows: the fixes jumped (a
    misprinted or misread code), so a streak of rejected fixes is no reason to restart."""
    t = pb.frame_t
    ks = pb.fix_frames[
        (t[pb.fix_frames] <= t[k]) & (t[pb.fix_frames] >= t[k] - config.reinit_lookback_s * 1e9)
    ]
    if len(ks) < 2:
        return False
    p = np.array([pb.fix_T[int(j)][:3, 3] for j in ks])
    return bool(np.any(fix_jumps(t[ks] * 1e-9, p, config.reinit_max_speed_m_s)))


def fix_position_cov_world(pb: Problem, k: int, i: int) -> np.ndarray:
    """3x3 world-frame covariance of the position of frame k's fix (its pose factor i's noise
    model: body frame for a 6-dof pose, the level frame for a gimbaled camera's level pose,
    world for the paper's position + yaw)."""
    nm = pb.factors[i].noiseModel()
    base: Any = nm.noise() if isinstance(nm, gtsam.noiseModel.Robust) else nm
    C = base.covariance()
    T = pb.fix_T[k]
    if pb.raw_input is RawPoseInput.POSE6:
        R = T[:3, :3]
        return R @ C[3:, 3:] @ R.T
    if pb.raw_input is RawPoseInput.LEVEL_POSE:
        R = rot_z(float(yaw_of(T[:3, :3])))
        return R @ C[1:, 1:] @ R.T
    return C[:3, :3]


def innovation_distance(
    pb: Problem, k: int, i: int, pose_pred: gtsam.Pose3, cov_prev: np.ndarray, R_prev: np.ndarray
) -> float:
    """Mahalanobis distance of frame k's fix position (pose factor i) from the IMU prediction pose_pred: the
    innovation covariance is the previous frame's marginal position covariance (body frame,
    R_prev its attitude) plus the preintegrated position covariance of the interval plus the
    fix's own (Bar-Shalom et al. 2001, Sec. 5.4: S = H P H^T + R, position rows only)."""
    C = cov_prev[3:, 3:]
    if (k - 1) in pb.pims:
        C = C + pb.pims[k - 1].preintMeasCov()[3:6, 3:6]
    S = R_prev @ C @ R_prev.T + fix_position_cov_world(pb, k, i)
    d = pb.fix_T[k][:3, 3] - pose_pred.translation()
    return math.sqrt(max(_inverse_quadratic_form3(S, d), 0.0))


def _inverse_quadratic_form3(S: np.ndarray, d: np.ndarray) -> float:
    """d^T S^-1 d for a symmetric 3x3 S (its upper triangle) and a 3-vector d, by the adjugate
    in Python floats: one call per fix in the incremental smoother's innovation gate, where
    np.linalg.solve's wrapper cost more than the arithmetic (equal to it within 1e-9 relative
    for condition numbers up to 1e4: tests/test_fixedlag.py)."""
    (a, b, c), (_, e, f), (_, _, i) = S.tolist()
    x, y, z = d.tolist()
    A, B, C = e * i - f * f, c * f - b * i, b * f - c * e  # first row of adj(S)
    D, E, F = a * i - c * c, b * c - a * f, a * e - b * b
    det = a * A + b * B + c * C
    return (A * x * x + D * y * y + F * z * z + 2.0 * (B * x * y + C * x * z + E * y * z)) / det


ISAM_FACTORIZATION = "CHOLESKY"
"""iSAM2's elimination in the incremental smoother.  Cholesky took ~30 % less CPU than QR (the
per-frame update and marginalCovariance are most of the smoother's time) for the same estimates
(poses within 1e-11 m, covariances within 1e-9 relative: BENCHMARKS.md).  QR is the fallback:
a Cholesky run that meets a singular update or covariance is run again from the start with QR,
so such flights get exactly the QR result (DESIGN.md pitfalls: Cholesky can throw
IndeterminantLinearSystemException where QR runs)."""
ISAM_FALLBACK_FACTORIZATION = "QR"


class _CholeskyFailed(Exception):
    """A Cholesky run of the incremental smoother met a singular system: run again with QR."""


FIXED_LAG_ENGINE = "time-ordered"
"""The incremental smoother's fixed-lag engine: "time-ordered" (fixedlag.TimeOrderedFixedLag:
iSAM2 ordered by time, ~2x less CPU: BENCHMARKS.md) or "gtsam" (GTSAM's
IncrementalFixedLagSmoother, the engine before it; the tests compare the two)."""


def _new_engine(config: FusionConfig, factorization: str = ISAM_FALLBACK_FACTORIZATION):
    params = gtsam.ISAM2Params()
    params.setFactorization(factorization)
    params.setRelinearizeThreshold(config.isam_relinearize_threshold)
    params.relinearizeSkip = config.isam_relinearize_skip
    params.findUnusedFactorSlots = True
    lag = config.incremental_lag_s
    if lag is None:
        return gtsam.ISAM2(params)
    if FIXED_LAG_ENGINE == "gtsam":
        return fixedlag.GtsamFixedLag(float(lag), params)
    return fixedlag.TimeOrderedFixedLag(float(lag), params)


def level_start(
    pb: Problem,
    frame_times_ns,
    imu: ImuData | None,
    raw: Trajectory,
    velocity: VelocityData | None,
    front_camera: CameraModel | None,
    config: FusionConfig,
    floor_camera: CameraModel | None,
    load_obs: list[LoadObservation] | None = None,
    failures: list[str] | None = None,
) -> LevelStart | None:
    """The incremental smoother's batch start (ekf.level_batch_start, the EKF's: a batch solve
    of the level fixes within `config.ekf_level_start_s` of the first inlier fix and the joint
    marginal of its last frame's pose, velocity and biases), or None: without level fixes
    (RawPoseInput.LEVEL_POSE: a gimbaled floor camera's PnP poses), without an IMU, with the
    start switched off (0 s) or when the window has too few fixes or its solve fails (its
    error then appended to `failures`: stats['batch_start_failed'], a run's warning).  The
    load sightings within the window are in its solve (their loads in the joint marginal).

    Why: the engine otherwise starts at the first fix with roll / pitch at the level fix's 0
    +- `initial_roll_pitch_sigma_rad` (the truth may roll 13 deg).  iSAM2 takes one Gauss-Newton
    step per update and relinearises every `isam_relinearize_skip` (10) updates, and with a lag
    of `incremental_lag_s` (0.5 s, 15 frames) the first states are marginalised while still
    linearised at tilts 0.1-0.4 rad off.  There PnP's tight level yaw (sigma ~0.06 mrad) reads as
    information on roll / pitch (the yaw's Jacobian turns with the tilt it is taken at), and the
    marginal factors keep it: a linear factor is fixed where it was taken, the inconsistency of
    a marginalised wrong linearisation point (Huang, Mourikis & Roumeliotis, IJRR 29(5), 2010).
    On `gimb27` (BENCHMARKS.md, inc15) the roll stayed -150 to -186 mrad off with sigma 2-3 mrad for
    the whole flight without the velocity sensor (-40 to -61 with it); with no lag, with
    relinearisation at every update, or with the fixes' yaw variance x200 it came back to
    within ~20 mrad: the marginalised linearisation is the cause.  The batch start iterates the
    window to convergence first, so the engine's first linearisation point is near the truth
    and its prior carries the window's tilt-bias correlation."""
    if not pb.has_imu or pb.raw_input is not RawPoseInput.LEVEL_POSE or config.ekf_level_start_s <= 0:
        return None
    if floor_camera is None:
        return None
    # a cycle otherwise: ekf builds its start with this module's build_problem / solve
    from fusion.estimate.ekf import level_batch_start

    inp = prepare_inputs(frame_times_ns, imu, raw, velocity, front_camera, config)
    if inp.imu is None:
        return None
    return level_batch_start(
        inp.frame_t,
        inp.imu,
        inp.raw,
        pb.k_first,
        inp.velocity,
        floor_camera,
        config,
        load_obs=load_obs,
        front_camera=inp.front_camera,
        failures=failures,
    )


def level_start_prior(
    k: int,
    joint: np.ndarray,
    pose: gtsam.Pose3,
    velocity: np.ndarray,
    bias: gtsam.imuBias.ConstantBias,
    loads: list[tuple[int, np.ndarray]] | None = None,
    joint_loads: np.ndarray | None = None,
) -> gtsam.LinearContainerFactor:
    """A Gaussian prior on [X(k), V(k), B(k)] jointly: mean (pose, velocity, bias), covariance
    `joint` (15, 15) in GTSAM's tangent order of those blocks (Pose3 [rot, trans], then the
    velocity, then ConstantBias [accel, gyro]: ekf.LevelStart.joint), as the linear factor
    I dx = 0 with that covariance held at the mean, whitened (W dx = 0, W = chol(joint)^-1: the
    wrapped JacobianFactor takes a diagonal model only) (gtsam.LinearContainerFactor: its error
    at other values through each variable's localCoordinates, the chart GTSAM's Marginals use).
    `loads` [(key, p_world (3,))] with `joint_loads` (15 + 3m, 15 + 3m), the joint covariance
    of [X, V, B, loads...]: the prior is on all of them, as the information matrix summed from
    one- and two-key HessianFactors (the wrapper builds a factor on at most three keys)."""
    lin = gtsam.Values()
    lin.insert(j=X(k), pose3=pose)
    lin.insert(V(k), np.asarray(velocity, float))
    lin.insert(j=B(k), constant_bias=bias)
    if loads:
        assert joint_loads is not None  # given with loads
        keys = [X(k), V(k), B(k)] + [key for key, _ in loads]
        for key, p in loads:
            lin.insert(key, np.asarray(p, float))
        info = np.linalg.inv(0.5 * (joint_loads + joint_loads.T))
        info = 0.5 * (info + info.T)
        offs = np.cumsum([0, 6, 3, 6] + [3] * len(loads))
        parts = gtsam.GaussianFactorGraph()
        for a, ka in enumerate(keys):
            sa = slice(offs[a], offs[a + 1])
            parts.add(gtsam.HessianFactor(ka, info[sa, sa], np.zeros(offs[a + 1] - offs[a]), 0.0))
            for b in range(a + 1, len(keys)):
                sb = slice(offs[b], offs[b + 1])
                da, db = offs[a + 1] - offs[a], offs[b + 1] - offs[b]
                parts.add(
                    gtsam.HessianFactor(
                        ka,
                        keys[b],
                        np.zeros((da, da)),
                        info[sa, sb],
                        np.zeros(da),
                        np.zeros((db, db)),
                        np.zeros(db),
                        0.0,
                    )
                )
        return gtsam.LinearContainerFactor(gtsam.HessianFactor(parts), lin)
    W = np.linalg.inv(np.linalg.cholesky(0.5 * (joint + joint.T)))
    jf = gtsam.JacobianFactor(
        X(k), W[:, :6], V(k), W[:, 6:9], B(k), W[:, 9:], np.zeros(15), gtsam.noiseModel.Unit.Create(15)
    )
    return gtsam.LinearContainerFactor(jf, lin)


def smooth_incremental(
    frame_times_ns,
    imu: ImuData | None,
    raw: Trajectory,
    load_obs: list[LoadObservation] | None,
    front_camera: CameraModel | None = None,
    velocity: VelocityData | None = None,
    config: FusionConfig | None = None,
    floor_frames: dict | None = None,
    floor_camera: CameraModel | None = None,
) -> FusionResult:
    """Causal incremental fusion: frame by frame, the factors available at that frame are added
    and the pose estimate and marginal covariance of X(k) *as known at frame k* are recorded (a
    filter-like output from a smoother).  Same inputs as `smooth`.

    Engine: iSAM2 (Cholesky factorization, ISAM_FACTORIZATION; the whole flight again with QR
    when Cholesky meets a singular system) inside gtsam's IncrementalFixedLagSmoother with lag
    `config.incremental_lag_s`: states older than the lag are marginalised, so the cost per frame
    stays bounded however long the flight.  A load's variable is marginalised too once it has not
    been seen for the lag; when the load is seen again a new variable (next generation,
    L(j + g * LOAD_GENERATION_STRIDE)) starts with no prior, as a sliding-window estimator's
    landmark does: marginalising the old variable put what its sightings told of the states
    into the window already, and its marginal is made of those states' information.  Given
    back as a prior (until 2026-12-05) it was counted twice, and more with every generation:
    6-dof NEES 11.3 on a 10-minute flight over an exactly laid floor and 20.5 on a 330 s one
    over misplaced codes, 2.1 and 7.9 without it, the ATE 10.1 -> 9.8 and 16.8 -> 16.8 mm
    (BENCHMARKS.md, twentieth session).  Loads seen again after the lag thus close no loop here;
    the batch smoother closes them.  `incremental_lag_s=None`: plain
    iSAM2 over the whole flight (exact, but loads re-seen after a long time make it re-solve
    much of the graph, so its cost grows with the flight).  Memory: the problem is built without
    its IMU factors (`build_problem(lazy_imu=True)`); each frame's IMU factor is made from a
    LazyPims when the frame is reached; what still grows with the flight is the other factors,
    the inputs and the outputs (peak ~9 MB per flight minute on the 10-minute benchmark flight,
    ~22 with every IMU factor built up front).

    Re-initialisation (health.resets): when config.reinit_rejected_fixes consecutive fixes lie
    beyond the kernel threshold of the IMU prediction but agree with each other (their offsets
    from the prediction match: they move as the IMU says) and no two consecutive fixes of the
    last reinit_lookback_s jumped faster than reinit_max_speed_m_s (fixes_jumped: a misprinted
    code read while crossing it), e.g. after a long blackout, the engine restarts at the latest
    fix: that fix's factor, priors on velocity and bias at their current estimates (a load
    seen again gets a new variable, as after leaving the window).  A singular update is
    handled the same way (health.linear_fallbacks).
    Innovation gate: a fix whose position lies beyond config.outlier_gate (Mahalanobis, against
    the IMU prediction, innovation_distance) is not added (stats['gated_pose_factors']); it
    still counts towards a re-initialisation streak.

    Output starts at the first raw-pose frame (`stats['frames_before_first_fix']` earlier
    frames have no estimate).  The velocity prior at the start uses the first 0.5 s of raw poses
    (a start-up look-ahead).  With level fixes (a gimbaled floor camera's PnP poses) and an IMU
    the engine starts instead at the last fix within `config.ekf_level_start_s` of the first,
    from the batch solve of that window (level_start: the EKF's start, ekf.level_batch_start),
    its joint marginal of pose, velocity and biases as the prior; the window's frames are that
    solve's (`stats['batch_start_frames']` of them, a start-up look-ahead as the EKF's).
    Loads: each load's variables' estimates and marginal covariances (the latest's at the end of
    the flight) combined as independent (`combine_generations`)."""
    config = config or FusionConfig()
    args = (frame_times_ns, imu, raw, load_obs, front_camera, velocity, config, floor_frames, floor_camera)
    try:
        res = _smooth_incremental(*args, factorization=ISAM_FACTORIZATION)
    except _CholeskyFailed as e:
        log.info("incremental: %s; solved again with %s", e, ISAM_FALLBACK_FACTORIZATION)
        res = _smooth_incremental(*args, factorization=ISAM_FALLBACK_FACTORIZATION)
        res.stats["cholesky_failure"] = str(e)
    return res


def combine_generations(estimates: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """One load's (estimate, covariance) from its incremental variables' (`estimates`), each
    generation's marginal taken as independent of the others: the information-weighted mean.
    Their pose errors are shared in part (the same floor codes), so the result is as
    optimistic as that share, as the prior chain before it was (each generation the last one's
    marginal as its prior)
    (load 3-dof NEES on the twentieth session's flights: 0.4-1.9)."""
    if len(estimates) == 1:
        p, c = estimates[0]
        return np.asarray(p, float).copy(), np.asarray(c, float).copy()
    info = np.zeros((3, 3))
    vec = np.zeros(3)
    for p, c in estimates:
        w = np.linalg.inv(0.5 * (c + c.T))
        info += w
        vec += w @ np.asarray(p, float)
    cov = np.linalg.inv(info)
    return cov @ vec, 0.5 * (cov + cov.T)


def _smooth_incremental(
    frame_times_ns,
    imu: ImuData | None,
    raw: Trajectory,
    load_obs: list[LoadObservation] | None,
    front_camera: CameraModel | None,
    velocity: VelocityData | None,
    config: FusionConfig,
    floor_frames: dict | None,
    floor_camera: CameraModel | None,
    *,
    factorization: str,
) -> FusionResult:
    """smooth_incremental with the given iSAM2 factorization; a run with any factorization but
    ISAM_FALLBACK_FACTORIZATION raises _CholeskyFailed at the first singular system."""
    fallback = factorization == ISAM_FALLBACK_FACTORIZATION
    try:
        return _smooth_incremental_run(
            frame_times_ns,
            imu,
            raw,
            load_obs,
            front_camera,
            velocity,
            config,
            floor_frames,
            floor_camera,
            factorization,
        )
    except (RuntimeError, ValueError, EstimationError) as e:
        if fallback:
            raise
        first = first_line(e)
        raise _CholeskyFailed(f"{factorization} failed ({first})") from None


def _smooth_incremental_run(
    frame_times_ns,
    imu,
    raw,
    load_obs,
    front_camera,
    velocity,
    config: FusionConfig,
    floor_frames,
    floor_camera,
    factorization: str,
) -> FusionResult:
    """The body of smooth_incremental (see there)."""
    fallback = factorization == ISAM_FALLBACK_FACTORIZATION
    config = config or FusionConfig()
    t0 = time.perf_counter()
    # the IMU factors are made frame by frame below (lazy_imu: memory flat in the flight's length)
    pb = build_problem(
        frame_times_ns,
        imu,
        raw,
        load_obs,
        front_camera,
        velocity,
        config,
        floor_frames,
        floor_camera,
        lazy_imu=True,
    )
    health = SolveHealth()
    fix_health(pb, config, health)
    t_build = time.perf_counter() - t0
    n, k0 = len(pb.frame_t), pb.k_first
    by_frame: list[list[int]] = [[] for _ in range(n)]
    for i, k in enumerate(pb.factor_frame):
        by_frame[k].append(i)
    # per factor: the oldest frame among its keys (-1: loads only) and the load it observes
    # (Python lists: the loop below reads them per factor, numpy scalars are slower)
    load_chr = ord("l")
    oldest = [
        min((key & _IDX_MASK for key in f.keys() if key >> _CHR_SHIFT != load_chr), default=-1)
        for f in pb.factors
    ]
    load_of = [-1] * len(pb.factors)
    for i, a in pb.load_args.items():
        load_of[i] = a.j
    # imu_into[k]: an IMU interval (k - 1, k) exists (one list look-up instead of LazyPims')
    imu_into = [False] + [(k - 1) in pb.pims for k in range(1, n)]
    cam = pb.front_camera
    lag = config.incremental_lag_s
    engine = _new_engine(config, factorization)
    t_rel = (pb.frame_t - pb.frame_t[0]) * 1e-9
    gen: dict[int, int] = {}  # load j -> generation of its current variable
    last_seen: dict[int, float] = {}  # load j -> time stamp of its current variable
    left: dict[int, tuple] = {}  # load j -> (estimate, covariance) when it left the window
    earlier: dict[int, list[tuple]] = {}  # load j -> its earlier variables' (estimate, covariance)
    n_generations = 0
    reorders = 0  # engine updates that re-eliminated the whole window (fixedlag), engines before
    start = k0  # factors on states before `start` are left out

    # the pose factor of each frame with a fix (for the re-initialisation test)
    pose_at = {pb.factor_frame[i]: i for i, r in pb.robust.items() if r.kind is FactorKind.POSE}
    streak = _Streak()
    gate = config.outlier_gate
    n_gated = 0
    # a fix counts towards a restart when the estimate is this far from it (Mahalanobis): the
    # outlier gate, else the kernel threshold
    reinit_distance = config.outlier_gate if config.outlier_gate is not None else pb.pose_threshold
    T_out = np.empty((n - k0, 4, 4))
    cov_out = np.empty((n - k0, 6, 6))
    pose_k = gtsam.Pose3(pb.T_init[k0])
    vel_k = pb.v_init[k0]
    bias_k = gtsam.imuBias.ConstantBias()
    start_failed: list[str] = []  # the batch start's solve error: the run names it
    level = level_start(
        pb, frame_times_ns, imu, raw, velocity, front_camera, config, floor_camera, load_obs, start_failed
    )
    k_begin = k0  # the engine's first frame: k0, or the batch start's last frame
    start_prior = None  # the batch start's joint prior on X, V, B (and loads) at k_begin
    start_loads: dict[int, np.ndarray] = {}  # load j -> its batch estimate (window loads)
    if level is not None:
        k_begin = start = level.k_end
        n_win = level.k_end - k0
        T_out[:n_win] = level.T_world_body[:-1]
        cov_out[:n_win] = level.cov_body[:-1]
        pose_k = gtsam.Pose3(level.T_world_body[-1])
        vel_k = level.v_world
        bias_k = gtsam.imuBias.ConstantBias(level.bias_accel, level.bias_gyro)
        # the window's loads: variables from the start (generation 0), in the joint prior
        start_loads = {pb.load_ids.index(lid): p for lid, p in zip(level.load_ids, level.p_loads)}
        start_prior = level_start_prior(
            k_begin,
            level.joint,
            pose_k,
            vel_k,
            bias_k,
            [(L(j), p) for j, p in start_loads.items()],
            level.joint_loads,
        )

    def lkey(j: int) -> int:
        return L(j + gen[j] * LOAD_GENERATION_STRIDE)

    def restart(k: int, reason: str) -> None:
        """A fresh engine whose first state will be frame k (a load seen again: a new variable)."""
        nonlocal engine, start, reorders
        for j in list(gen):
            if j not in left:
                try:
                    left[j] = (engine.calculateEstimatePoint3(lkey(j)), engine.marginalCovariance(lkey(j)))
                except (RuntimeError, ValueError, IndexError):
                    if not fallback:  # a Cholesky run: the QR run decides
                        raise
                    # never estimated (the failed update that brought it): start it afresh
                    left.pop(j, None)
                    gen.pop(j, None)
                    last_seen.pop(j, None)
        reorders += getattr(engine, "reorders", 0)
        engine = _new_engine(config, factorization)
        start = k
        streak.clear()
        health.resets += 1
        health.note(reason)

    def _incremental_step(k, tk, fresh, pose_guess, vel_guess, bias_guess, weak=False, skip=-1):
        nonlocal n_generations
        g = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        # keyword arguments: pybind11 then skips the ~60 overloads of Values.insert whose
        # parameter names differ instead of trying each conversion (a positional ConstantBias
        # insert ~180 us, keyword ~60 us; Pose3 ~30 / ~20 us)
        vals.insert(j=X(k), pose3=pose_guess)
        vals.insert(V(k), vel_guess)
        new_keys = [X(k), V(k)]
        if pb.has_imu:
            vals.insert(j=B(k), constant_bias=bias_guess)
            new_keys.append(B(k))
        if k == k_begin and start_prior is not None:
            # the batch start: its joint marginal of pose, velocity, biases (and the window's
            # loads) at k_begin is the prior, and the window's fixes, velocity and load sightings
            # (k_begin's too) are in it already
            g.add(start_prior)
            for j, p in start_loads.items():
                left.pop(j, None)
                gen[j] = 0
                last_seen[j] = tk
                vals.insert(L(j), np.asarray(p, float))
                new_keys.append(L(j))
        elif fresh and k > k0:
            # restart: the state carries over as priors (velocity, bias at their estimates;
            # attitude at the guess, loosely, as a position + yaw fix leaves roll / pitch
            # free); the position comes from this frame's fix (or, singular, a weak prior)
            g.add(
                gtsam.PriorFactorPose3(
                    X(k),
                    pose_guess,
                    gtsam.noiseModel.Diagonal.Sigmas(
                        np.r_[np.full(3, config.reinit_sigma_rot_rad), np.full(3, config.reinit_sigma_pos_m)]
                    ),
                )
            )
            g.add(
                gtsam.PriorFactorVector(
                    V(k), vel_guess, gtsam.noiseModel.Isotropic.Sigma(3, config.reinit_velocity_sigma_m_s)
                )
            )
            if pb.has_imu:
                g.add(
                    gtsam.PriorFactorConstantBias(
                        B(k),
                        bias_guess,
                        gtsam.noiseModel.Diagonal.Sigmas(
                            np.r_[
                                np.full(3, config.bias_prior_sigma_accel_m_s2),
                                np.full(3, config.bias_prior_sigma_gyro_rad_s),
                            ]
                        ),
                    )
                )
        if k == k0 and pb.raw_input is not RawPoseInput.POSE6:
            # position + yaw fixes leave the first roll / pitch to the IMU, which has not
            # spoken yet: a prior at the initial guess (sigma: the gimbal convention's)
            g.add(
                gtsam.PriorFactorPose3(
                    X(k),
                    pose_guess,
                    gtsam.noiseModel.Diagonal.Sigmas(
                        np.r_[
                            np.full(2, config.initial_roll_pitch_sigma_rad),
                            config.fallback_sigma_rot_rad,
                            np.full(3, config.fallback_sigma_pos_m),
                        ]
                    ),
                )
            )
        if weak or (fresh and k > k0 and k not in pose_at and not (k == k_begin and start_prior is not None)):
            for f in weak_priors(vals, config):
                if gtsam.Symbol(f.keys()[0]).chr() == ord("x"):
                    g.add(f)
        if lag is not None:
            # loads whose variable leaves the window in this update: keep their last marginal
            cutoff = tk - lag
            for j in [j for j, ts in last_seen.items() if ts < cutoff and j not in left]:
                left[j] = (engine.calculateEstimatePoint3(lkey(j)), engine.marginalCovariance(lkey(j)))
        if k - 1 >= start and imu_into[k]:  # the IMU factor into frame k (lazy_imu)
            g.add(imu_factor(k - 1, pb.pims[k - 1]))
        for i in by_frame[k]:
            if oldest[i] < start or i == skip:
                continue
            if k == k_begin and start_prior is not None:
                continue  # frame k_begin's fix, velocity and loads: in the batch start's window
            f = pb.factors[i]
            j = load_of[i]
            if j >= 0:
                if j not in gen or j in left:  # first sighting, or back after leaving
                    if j not in gen:
                        gen[j] = 0
                    else:
                        # a new variable with no prior: what the old one knew came from states
                        # whose information the window holds already (see the docstring)
                        gen[j] += 1
                        n_generations += 1
                        earlier.setdefault(j, []).append(left.pop(j))
                    a = pb.load_args[i]
                    T_wc = cam.T_world_cam(pose_guess.matrix())
                    vals.insert(lkey(j), T_wc[:3, :3] @ a.p_cam + T_wc[:3, 3])
                if gen[j] > 0:
                    a = pb.load_args[i]
                    f = factors.load_factor(
                        a.k,
                        j,
                        a.p_cam,
                        a.cov_cam,
                        cam,
                        config.robust_kernel,
                        pb.load_threshold,
                        load_key=lkey(j),
                        noise_model=f.noiseModel(),
                    )
                last_seen[j] = tk
                new_keys.append(lkey(j))
            g.add(f)
        if lag is None:
            engine.update(g, vals)
        else:
            engine.update(g, vals, dict.fromkeys(new_keys, tk))

    k = k_begin
    while k < n:
        tk = float(t_rel[k])
        # causal initial guess: IMU prediction, else the raw pose, else the previous state
        if k > start and imu_into[k]:
            nav = pb.pims[k - 1].predict(gtsam.NavState(pose_k, vel_k), bias_k)
            pose_guess, vel_guess = nav.pose(), nav.velocity()
        elif k in pose_at and pb.raw_input is RawPoseInput.POSE6:
            pose_guess, vel_guess = pb.factors[pose_at[k]].prior(), vel_k
        else:
            pose_guess, vel_guess = pose_k, vel_k
        if k == k0:
            pose_guess = gtsam.Pose3(pb.T_init[k0])
        elif k == k_begin:
            pose_guess = pose_k  # the batch start's
        fresh = k == start
        # innovation gate (as the EKF's): a fix beyond the outlier gate of the IMU prediction
        # is not added (a misprinted code pulls a fixed-lag window through any kernel); it
        # still counts towards a re-initialisation streak below
        skip = -1
        d_innov = (
            innovation_distance(
                pb, k, pose_at[k], pose_guess, cov_out[k - 1 - k0], pose_k.rotation().matrix()
            )
            if k in pose_at and not fresh and k > start and imu_into[k]
            else None
        )
        if gate is not None and d_innov is not None and d_innov > gate:
            skip = pose_at[k]
            n_gated += 1
        if (
            skip < 0
            and d_innov is not None
            and d_innov <= config.threshold(3)
            and pb.raw_input is RawPoseInput.POSE6
        ):
            # a fix within the kernel threshold of the prediction (against S = H P H^T + R, as
            # the EKF's kernel): X(k) linearised at the fix.  iSAM2 linearises a new factor at
            # its initial guess, and a robust model weighs it there (IRLS weight k / d, d the
            # fix's distance in its own R only); at the IMU prediction that distance is the
            # prediction's error (median 73 on a 5x-noise IMU: weight 0.09), and the
            # relinearisation threshold (0.01) seldom revisits it, so every fix kept a
            # fraction of its information in the marginal (NEES 2.4; BENCHMARKS.md, inc17)
            pose_guess = pb.factors[pose_at[k]].prior()
        try:
            _incremental_step(k, tk, fresh, pose_guess, vel_guess, bias_k, skip=skip)
        except (RuntimeError, ValueError) as e:
            if not fallback:
                raise
            reason = first_line(e)
            health.linear_fallbacks += 1
            log.warning("incremental: singular update at t=%.2f s (%s)", tk, reason)
            restart(k, f"singular update ({reason}): restarted with a weak pose prior")
            try:
                _incremental_step(k, tk, True, pose_guess, vel_guess, bias_k, weak=True)
            except (RuntimeError, ValueError) as e2:
                raise EstimationError(
                    f"incremental smoother: the update at frame {k} failed again after a restart: {e2}"
                ) from None
        # a fix the estimate rejects (beyond the kernel threshold after the update): part of a
        # streak that may call for a restart from the fixes
        pose_est = None  # X(k)'s estimate after this frame's update (reused below)
        if k in pose_at and not fresh:
            est = gtsam.Values()
            pose_est = engine.calculateEstimatePose3(X(k))
            est.insert(j=X(k), pose3=pose_est)
            f = pb.factors[pose_at[k]]
            if mahalanobis(f, est) > reinit_distance:
                T_fix = pb.fix_T[k]
                R_est = pose_est.rotation().matrix()
                streak.frames.append(k)
                streak.t_s.append(tk)
                streak.offsets_m.append(T_fix[:3, 3] - pose_est.translation())
                streak.offsets_yaw.append(float(yaw_of(T_fix[:3, :3]) - yaw_of(R_est)))
                if streak.agrees(config) and not fixes_jumped(pb, k, config):
                    # roll / pitch: the fix's when it has them, else the estimate's
                    R_new = (
                        T_fix[:3, :3]
                        if pb.raw_input is RawPoseInput.POSE6
                        else rot_z(float(yaw_of(T_fix[:3, :3]) - yaw_of(R_est))) @ R_est
                    )
                    log.info("incremental: re-initialised at t=%.2f s", tk)
                    restart(
                        k,
                        f"re-initialised from {config.reinit_rejected_fixes} agreeing "
                        "fixes that the estimate had rejected (count: resets)",
                    )
                    _incremental_step(
                        k,
                        tk,
                        True,
                        gtsam.Pose3(make_T(R_new, T_fix[:3, 3])),
                        vel_guess + streak.velocity_offset_m_s,
                        bias_k,
                    )
                    pose_est = None
            else:
                streak.clear()
        pose_k = pose_est if pose_est is not None else engine.calculateEstimatePose3(X(k))
        vel_k = engine.calculateEstimateVector(V(k))
        if pb.has_imu:
            bias_k = engine.calculateEstimateConstantBias(B(k))
        T_out[k - k0] = pose_k.matrix()
        cov_out[k - k0] = engine.marginalCovariance(X(k))
        k += 1

    loads = []
    for j, track in enumerate(pb.loads):
        gens = list(earlier.get(j, []))
        if j in left:
            gens.append(left[j])
        elif j in gen:
            gens.append((engine.calculateEstimatePoint3(lkey(j)), engine.marginalCovariance(lkey(j))))
        if gens:
            p, c = combine_generations(gens)
            loads.append(LoadEstimate(track.load_id, p, c, track.n_obs))
    elapsed = time.perf_counter() - t0
    duration = (pb.frame_t[-1] - pb.frame_t[k0]) * 1e-9
    stats = dict(
        pb.counts.as_dict(),
        frames_before_first_fix=k0,
        batch_start_frames=0 if level is None else level.k_end - k0 + 1,
        time_build_s=t_build,
        time_s=elapsed,
        incremental_lag_s=lag,
        load_generations=n_generations,
        gated_pose_factors=n_gated,
        engine_reorders=reorders + getattr(engine, "reorders", 0),
        realtime_factor=duration / max(elapsed - t_build, 1e-9),
        health=health.as_dict(),
    )
    if start_failed:  # batch_start_frames 0 alone would read as "not attempted"
        stats["batch_start_failed"] = start_failed[0]
    traj = Trajectory(str(Estimator.INCREMENTAL), pb.frame_t[k0:].copy(), T_out, cov_out)
    return FusionResult(traj, LoadMap(str(Estimator.INCREMENTAL), loads), stats, health)
