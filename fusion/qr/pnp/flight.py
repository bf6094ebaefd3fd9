"""Whole flights: per-frame PnP over a flight's detections, batched; load observations placed
with the drone trajectory; the information-weighted load map; and what happened (PnPStats)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from fusion.camera import CameraModel
from fusion.geometry import interpolate_pose
from fusion.qr.codes import FrameCodes, LoadSighting, classify, rejection_counts
from fusion.qr.pnp.bias import FrameBiasTerms, FrameCodeResiduals, frames_bias_and_residuals
from fusion.qr.pnp.floor import estimate_floor_poses
from fusion.qr.pnp.load import LoadFrame, estimate_load_observations_frames
from fusion.qr.pnp.whitening import CORNER_COORDINATES, DEFAULT_CORNER_SIGMA_PX
from fusion.types import LoadEstimate, LoadMap, LoadObservation, QRDetection, Trajectory
from fusion.world import FloorLayout, Placement, World

FRAMES_PER_BATCH = 512
"""Frames solved together by `pnp_trajectory` / `pnp_load_observations` (bounded memory)."""
SAME_STAMP_NS = 1_000_000
"""`pose_at`: a pose stamped within this of the query is taken as it is (1 ms)."""
MAX_POSE_GAP_S = 0.1
"""`pose_at`: the longest gap between two poses across which a pose is interpolated."""
S_PER_NS = 1e-9
POSE_DOF = 6
"""Unknowns of a floor-camera PnP frame (a frame's chi2 has 8 n_codes - POSE_DOF dof)."""


@dataclass
class PnPStats:
    """What happened to a flight's floor-camera frames."""

    n_frames: int = 0
    n_posed: int = 0
    n_without_floor_code: int = 0
    n_unsolved: int = 0  # floor codes in view but no acceptable pose
    n_ambiguous: int = 0  # decided by the near-level rule
    n_codes_dropped: int = 0  # outlier codes left out of a pose
    codes_per_pose: dict[int, int] = field(default_factory=dict)  # n_codes -> n_frames
    rejections: dict[str, int] = field(default_factory=dict)  # classify() reason -> count
    mean_reprojection_rms_px: float = float("nan")  # over the posed frames
    # per posed frame: whitened reprojection chi2 and its dof (fusion.estimate.variance)
    frame_chi2: list[float] = field(default_factory=list)
    frame_dof: list[int] = field(default_factory=list)
    # per posed frame and corner class (PnPResult.class_chi2, class_redundancy, class_covariance):
    # the per-class noise scales (fusion.estimate.variance.pnp_class_components)
    frame_class_chi2: list[np.ndarray] = field(default_factory=list)
    frame_class_redundancy: list[np.ndarray] = field(default_factory=list)
    frame_class_covariance: list[np.ndarray] = field(default_factory=list)
    # per posed frame: its share of the flight's common corner bias (fusion.qr.pnp.bias; None
    # when the pose's information is singular), for fusion.estimate.cornerbias
    frame_bias: list[FrameBiasTerms | None] = field(default_factory=list)
    # per posed frame: each code's whitened corner residuals (fusion.qr.pnp.bias), for the time
    # correlation of the corner errors (fusion.estimate.correlation)
    frame_code_residuals: list[FrameCodeResiduals] = field(default_factory=list)
    # per posed frame of a gimbaled camera: the free solve's [rx, ry] covariance before the
    # level conditioning (PnPResult.free_tilt_covariance), for fusion.estimate.tiltconsider
    frame_free_tilt_covariance: list[np.ndarray] = field(default_factory=list)
    # per posed frame, with the floor codes' placement uncertain: each class's placement share
    # (PnPResult.placement_covariance, float32), for fusion.estimate.correlation; else empty
    frame_placement_covariance: list[np.ndarray] = field(default_factory=list)
    # how the codes' placement was weighed (world.Placement, or --map's FloorLayout; None: exact)
    placement: Placement | FloorLayout | None = None

    @classmethod
    def merged(cls, parts: list[PnPStats]) -> PnPStats:
        """The stats of a flight solved in parts: counts summed, the mean RMS weighted by the
        parts' posed frames."""
        codes: Counter = Counter()
        rejections: Counter = Counter()
        for p in parts:
            codes.update(p.codes_per_pose)
            rejections.update(p.rejections)
        posed = [p for p in parts if p.n_posed]
        n_posed = sum(p.n_posed for p in parts)
        return cls(
            n_frames=sum(p.n_frames for p in parts),
            n_posed=n_posed,
            n_without_floor_code=sum(p.n_without_floor_code for p in parts),
            n_unsolved=sum(p.n_unsolved for p in parts),
            n_ambiguous=sum(p.n_ambiguous for p in parts),
            n_codes_dropped=sum(p.n_codes_dropped for p in parts),
            codes_per_pose=dict(sorted(codes.items())),
            rejections=dict(sorted(rejections.items())),
            mean_reprojection_rms_px=(
                float(sum(p.mean_reprojection_rms_px * p.n_posed for p in posed) / n_posed)
                if n_posed
                else float("nan")
            ),
            frame_chi2=[c for p in parts for c in p.frame_chi2],
            frame_dof=[d for p in parts for d in p.frame_dof],
            frame_class_chi2=[c for p in parts for c in p.frame_class_chi2],
            frame_class_redundancy=[c for p in parts for c in p.frame_class_redundancy],
            frame_class_covariance=[c for p in parts for c in p.frame_class_covariance],
            frame_bias=[b for p in parts for b in p.frame_bias],
            frame_code_residuals=[r for p in parts for r in p.frame_code_residuals],
            frame_free_tilt_covariance=[c for p in parts for c in p.frame_free_tilt_covariance],
            frame_placement_covariance=[c for p in parts for c in p.frame_placement_covariance],
            placement=next((p.placement for p in parts if p.placement is not None), None),
        )


def pnp_trajectory(
    frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    name: str = "pnp",
    layout: FloorLayout | None = None,
    frame_codes: dict[int, FrameCodes] | None = None,
) -> tuple[Trajectory, PnPStats]:
    """Per-frame PnP body poses of a floor-camera flight: {timestamp_ns: detections} ->
    (Trajectory with (N, 6, 6) covariances, PnPStats).  Frames with no usable floor code are
    left out (counted in the stats); rejected payloads (fusion.qr.codes.classify) are never used.
    Each frame is solved on its own (`estimate_floor_pose`), FRAMES_PER_BATCH frames at a time
    (`estimate_floor_poses`), weighing its codes by world.yaml's placement sigma
    (`world.Placement.from_world`: absent, the defaults; 0 / 0, exactly laid), or by `layout`
    (`fusion run --map`: the codes a merged map holds where it puts them, to its covariance).
    frame_codes: {timestamp_ns: classify(frames[ts], world)} the caller has already; others
    classified here."""
    placement: Placement | FloorLayout = layout if layout is not None else Placement.from_world(world)
    stats = PnPStats(placement=placement if placement.enabled else None)
    ts_out, T_out, cov_out, rms = [], [], [], []
    codes_seen = []
    per_pose: Counter = Counter()
    with_floor = []
    for ts in sorted(frames):
        stats.n_frames += 1
        codes = (
            frame_codes[ts] if frame_codes is not None and ts in frame_codes else classify(frames[ts], world)
        )
        codes_seen.append(codes)
        if codes.floor:
            with_floor.append((ts, [layout.place(s) for s in codes.floor] if layout else codes.floor))
        else:
            stats.n_without_floor_code += 1
    for b in range(0, len(with_floor), FRAMES_PER_BATCH):
        batch = with_floor[b : b + FRAMES_PER_BATCH]
        used: list = []  # per posed frame: the sightings its pose used, and the pose
        used_T: list = []
        for (ts, floor), res in zip(
            batch, estimate_floor_poses([f for _, f in batch], camera, corner_sigma_px, placement=placement)
        ):
            if res is None:
                stats.n_unsolved += 1
                continue
            stats.n_posed += 1
            stats.n_ambiguous += int(res.ambiguous)
            stats.n_codes_dropped += len(res.dropped_payloads)
            per_pose[res.n_codes] += 1
            ts_out.append(int(ts))
            T_out.append(res.T_world_body)
            cov_out.append(res.covariance)
            rms.append(res.reprojection_rms_px)
            stats.frame_chi2.append(res.chi2)
            stats.frame_dof.append(CORNER_COORDINATES * res.n_codes - POSE_DOF)
            stats.frame_class_chi2.append(res.class_chi2)
            stats.frame_class_redundancy.append(res.class_redundancy)
            stats.frame_class_covariance.append(res.class_covariance)
            if res.free_tilt_covariance is not None:
                stats.frame_free_tilt_covariance.append(res.free_tilt_covariance)
            if res.placement_covariance is not None:
                stats.frame_placement_covariance.append(res.placement_covariance.astype(np.float32))
            used.append([s for s in floor if s.detection.payload in res.payloads])
            used_T.append(res.T_world_body)
        bias, residuals = frames_bias_and_residuals(
            camera, used, np.array(used_T).reshape(-1, 4, 4), corner_sigma_px, placement
        )
        stats.frame_bias += bias
        stats.frame_code_residuals += residuals
    stats.codes_per_pose = dict(sorted(per_pose.items()))
    stats.rejections = rejection_counts(codes_seen)
    if rms:
        stats.mean_reprojection_rms_px = float(np.mean(rms))
    if not ts_out:
        return Trajectory.empty(name), stats
    return Trajectory(name, np.asarray(ts_out, dtype=np.int64), np.stack(T_out), np.stack(cov_out)), stats


def pose_at(
    trajectory: Trajectory, timestamp_ns: int, max_gap_s: float = MAX_POSE_GAP_S
) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(T_world_body, cov or None) at `timestamp_ns`: the pose stamped within SAME_STAMP_NS of
    it, or the interpolation (linear position, geodesic rotation; covariance of the nearer pose)
    between the poses on either side when they are at most `max_gap_s` apart; None otherwise."""
    ts = np.asarray(trajectory.timestamps_ns, dtype=np.int64)
    if len(ts) == 0:
        return None
    covs = trajectory.covariances
    i = int(np.searchsorted(ts, timestamp_ns))
    for j in (i - 1, i):
        if 0 <= j < len(ts) and abs(int(ts[j]) - int(timestamp_ns)) <= SAME_STAMP_NS:
            return trajectory.T_world_body[j], (None if covs is None else covs[j])
    if i == 0 or i == len(ts) or (ts[i] - ts[i - 1]) * S_PER_NS > max_gap_s:
        return None
    t0, t1 = int(ts[i - 1]), int(ts[i])
    a = (int(timestamp_ns) - t0) / (t1 - t0)
    T = interpolate_pose(trajectory.T_world_body[i - 1], trajectory.T_world_body[i], a)
    cov = None if covs is None else covs[i - 1 if a < 0.5 else i]
    return T, cov


def pnp_load_observations(
    front_frames: dict[int, list[QRDetection]],
    front_camera: CameraModel,
    world: World,
    trajectory: Trajectory,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    max_gap_s: float = MAX_POSE_GAP_S,
    frame_loads: dict[int, list[LoadSighting]] | None = None,
) -> list[LoadObservation]:
    """Load observations of a flight's front-camera frames ({timestamp_ns: detections}), placed
    with the drone pose of `trajectory` at each frame (`pose_at`); frames without a pose are
    skipped.  Rejected payloads (classify) are never used.  Solved FRAMES_PER_BATCH frames at a
    time (`estimate_load_observations_frames`).  frame_loads: {timestamp_ns: classify(...).loads}
    of every frame with a load code, classified by the caller (a frame not in it has none)."""
    todo = []
    for ts in sorted(front_frames):
        loads = (
            frame_loads.get(ts, []) if frame_loads is not None else classify(front_frames[ts], world).loads
        )
        if not loads:
            continue
        pose = pose_at(trajectory, ts, max_gap_s)
        if pose is None:
            continue
        todo.append(LoadFrame(loads, pose[0], pose[1]))
    out: list[LoadObservation] = []
    for b in range(0, len(todo), FRAMES_PER_BATCH):
        for obs in estimate_load_observations_frames(
            todo[b : b + FRAMES_PER_BATCH], front_camera, world, corner_sigma_px
        ):
            out.extend(obs)
    return out


def aggregate_load_observations(observations: list[LoadObservation], name: str = "pnp") -> LoadMap:
    """Information-weighted mean of each load id's p_world: P = (sum C_i^-1)^-1,
    p = P sum C_i^-1 p_i (observations without cov_world get the plain mean, cov None).

    Caveat: observations taken from nearby drone poses share pose error, so P is optimistic when
    they are many (load-map NEES 10-36 of 3 on the sweep's flights); the run adds that shared
    error, with the label's print error and the front stamps', as consider terms
    (fusion.estimate.loadconsider)."""
    by_id: dict[str, list[LoadObservation]] = {}
    for o in observations:
        by_id.setdefault(o.load_id, []).append(o)
    loads = []
    for load_id in sorted(by_id):
        obs = by_id[load_id]
        covs = [(o.cov_world, o.p_world) for o in obs if o.cov_world is not None]
        if covs:
            info = np.zeros((3, 3))
            vec = np.zeros(3)
            for cov, p_world in covs:
                W = np.linalg.inv(cov)
                info += W
                vec += W @ p_world
            P = np.linalg.inv(info)
            loads.append(LoadEstimate(load_id, P @ vec, 0.5 * (P + P.T), len(obs)))
        else:
            loads.append(LoadEstimate(load_id, np.mean([o.p_world for o in obs], axis=0), None, len(obs)))
    return LoadMap(name, loads)
