"""The track pass (issue 10 item 4): floor codes that a predicted body pose puts in view, in floor
frames where they did not decode, found and refined by fusion.qr.track.CodeTracker and named
from the prediction (gated by the innovation), never guessed.

Detection runs before any pose exists, so this pass runs after the first per-frame
localisation (pipeline.track_stage):

1. The catalogue: every floor code decoded somewhere in the flight (its world corners from its
   payload, fusion.qr.codes.classify; its modules per side from one re-decoded image).  Only
   these codes can be tracked: a code never decoded has no identity to give.
2. Per floor frame, in time order, the body pose predicted offline from the PnP poses on both
   sides (`PosePredictor`): the frame's own first-pass pose; else linear / geodesic
   interpolation between the last pose before (first pass, or found earlier in this pass) and
   the next first-pass pose, when they are at most MAX_INTERPOLATION_GAP_S apart; else constant
   velocity extrapolated from the last poses (over at least VELOCITY_BASELINE_S) at most
   MAX_EXTRAPOLATION_S ahead, forward or backward.  Offline both sides are known, so no IMU
   model is needed (IMU propagation and a first fused pass were not compared: BENCHMARKS.md).
3. The catalogue's codes the predicted camera pose (camera.T_world_cam: mounts) puts in view
   with their quiet zone (track.symbol_in_view) and that did not decode in the frame are given
   to CodeTracker.step(predicted=..., own_motion=False), when their modules are at least
   TRACK_MIN_MODULE_PX, with a prediction sigma of
   PREDICTION_SIGMA_PX + PREDICTION_SIGMA_PX_PER_S x (time to the nearest pose used).  A frame
   with tracked codes gets a PnP pose from all its codes (its decoded and tracked ones), which
   later frames' predictions use when its position sigma is at most
   MAX_FEEDBACK_POSITION_SIGMA_M, so a code is followed through a long stretch of blur.
4. The flight is cut into chunks of about TRACK_CHUNK_FRAMES frames at frames with two
   first-pass poses within MAX_EXTRAPOLATION_S (a fresh start loses little there); the cut
   does not depend on the number of workers, so any number of processes gives the same result.

Not done: load codes on the front camera; rolling-shutter floor cameras (the prediction is a
global-shutter projection at the stamp; the pipeline skips the pass there and says so).
"""

from __future__ import annotations

import bisect
import hashlib
import logging
import time
from dataclasses import dataclass, field, fields

import numpy as np

from fusion.camera import CameraModel
from fusion.geometry import interpolate_pose, inv_T, transform_points
from fusion.parallel import parallel_map
from fusion.qr.codes import classify
from fusion.qr.detect import CameraStats, DetectionResult, detect_image
from fusion.qr.pnp import estimate_floor_pose
from fusion.qr.track import CodeTracker, TrackStats, symbol_in_view
from fusion.types import CameraRole, QRDetection, Trajectory
from fusion.world import World

logger = logging.getLogger(__name__)

TRACK_METHOD = "pose-track/1"  # in the tracked cache's fingerprint: change with the method
PREDICTION_SIGMA_PX = 3.0  # 1-sigma per corner coordinate of a code projected with a PnP pose
PREDICTION_SIGMA_PX_PER_S = 10.0  # ... plus this per second to the nearest pose used
MAX_INTERPOLATION_GAP_S = 1.0  # interpolate between poses at most this far apart
MAX_EXTRAPOLATION_S = 0.5  # extrapolate at most this far from the last pose
VELOCITY_BASELINE_S = 0.05  # velocity over at least this (consecutive poses: their noise, amplified)
TRACK_CHUNK_FRAMES = 300  # nominal frames per chunk of the pass (10 s at 30 Hz)
# Smaller predicted modules are not tried: on the clean demo flight, codes tracked at under 2.5 px
# per module (2.6 m up, turning) were up to 3.6 px off and gave PnP poses 8-25 cm off; at 2.5 px
# and more, at most 0.5 px (BENCHMARKS.md)
TRACK_MIN_MODULE_PX = 2.5
# A pose found by the pass predicts later frames only when PnP's position sigma (its covariance,
# Pose3 order [r, t]) is at most this: single blurred codes gave poses 10-55 cm off with sigma
# 3-50 cm on a 20 ms-exposure flight (good ones: 0.04 cm), and fed back, the next predictions
# followed them
MAX_FEEDBACK_POSITION_SIGMA_M = 0.01
POSE_DOF = 6  # Pose3 tangent: rotation (3) then translation (3)
FLOOR = CameraRole.FLOOR.value


@dataclass
class CatalogueCode:
    """A floor code decoded somewhere in the flight: its world corners (4, 3) TL, TR, BR, BL and
    its modules per side."""

    corners_world: np.ndarray
    modules: int


@dataclass
class TrackReport:
    """What the track pass did: tracker counters summed over chunks, frames and time."""

    stats: TrackStats = field(default_factory=TrackStats)
    catalogue: int = 0  # floor codes that can be tracked (decoded somewhere in the flight)
    no_modules: int = 0  # decoded codes left out: their version could not be read again
    frames_predicted: int = 0  # floor frames with a predicted pose
    frames_tried: int = 0  # ... with an undecoded code in view: image read, tracker run
    frames_tracked: int = 0  # ... with at least one tracked code
    frames_tracked_only: int = 0  # ... whose codes are all tracked ones
    poses_added: int = 0  # frames of the pass with a PnP pose that had none before
    chunks: int = 0
    seconds: float = 0.0  # wall time of the pass (catalogue and tracking)
    skipped_reason: str = ""  # why the pass did not run ("" when it ran)

    def as_dict(self) -> dict:
        out: dict = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "stats"}
        out.update({f"tracker_{k}": int(v) for k, v in vars(self.stats).items()})
        out["seconds_per_frame_tried"] = self.seconds / self.frames_tried if self.frames_tried else 0.0
        return out

    def note(self) -> str:
        if self.skipped_reason:
            return f"track pass not run: {self.skipped_reason}"
        s = self.stats
        return (
            f"track pass: {s.tracked} floor-code sightings tracked in {self.frames_tracked} frames "
            f"({self.frames_tracked_only} with tracked codes only, {self.poses_added} new PnP poses); "
            f"{s.attempts} tried in {self.frames_tried} frames, {s.gated} refused by the innovation "
            f"gate, {s.refine_failed} not refined, {s.ambiguous} next to a decoded code; "
            f"{self.seconds:.1f} s"
        )


class PosePredictor:
    """Body poses predicted at floor-frame stamps from PnP poses (module docstring, step 2).

    `timestamps_ns` (N,) increasing and `T_world_body` (N, 4, 4): the first pass's poses;
    `add` records a pose found by the pass (stamps increasing, after every earlier `add`)."""

    def __init__(self, timestamps_ns: np.ndarray, T_world_body: np.ndarray):
        self.first_t = [int(t) for t in timestamps_ns]
        self.first_T = list(np.asarray(T_world_body, dtype=float).reshape(-1, 4, 4))
        self.added_t: list[int] = []
        self.added_T: list[np.ndarray] = []

    def add(self, t_ns: int, T_world_body: np.ndarray) -> None:
        self.added_t.append(int(t_ns))
        self.added_T.append(np.asarray(T_world_body, dtype=float))

    def _before(self, t: int, k: int) -> list[tuple[int, np.ndarray]]:
        """Up to k poses strictly before t, latest first (first-pass and added)."""
        i = bisect.bisect_left(self.first_t, t)
        j = bisect.bisect_left(self.added_t, t)
        merged = [(self.first_t[m], self.first_T[m]) for m in range(max(0, i - k), i)]
        merged += [(self.added_t[m], self.added_T[m]) for m in range(max(0, j - k), j)]
        merged.sort(key=lambda p: p[0], reverse=True)
        out: list[tuple[int, np.ndarray]] = []
        for p in merged:  # an added pose replaces the first pass's at the same stamp
            if not out or out[-1][0] != p[0]:
                out.append(p)
        return out[:k]

    def _after(self, t: int, k: int) -> list[tuple[int, np.ndarray]]:
        """Up to k first-pass poses strictly after t, earliest first."""
        i = bisect.bisect_right(self.first_t, t)
        return [(self.first_t[m], self.first_T[m]) for m in range(i, min(len(self.first_t), i + k))]

    def has_first_pose(self, t_ns: int) -> bool:
        i = bisect.bisect_left(self.first_t, int(t_ns))
        return i < len(self.first_t) and self.first_t[i] == int(t_ns)

    def predict(self, t_ns: int) -> tuple[np.ndarray, float] | None:
        """(T_world_body (4, 4), seconds to the nearest pose used) at t_ns, or None."""
        t = int(t_ns)
        i = bisect.bisect_left(self.first_t, t)
        if i < len(self.first_t) and self.first_t[i] == t:
            return self.first_T[i], 0.0
        before = self._before(t, 8)
        after = self._after(t, 8)
        if before and after and (after[0][0] - before[0][0]) * 1e-9 <= MAX_INTERPOLATION_GAP_S:
            (t0, T0), (t1, T1) = before[0], after[0]
            a = (t - t0) / (t1 - t0)
            return interpolate_pose(T0, T1, a), min(t - t0, t1 - t) * 1e-9
        ahead = _extrapolate(before, t)  # forward from the past
        behind = _extrapolate(after, t)  # backward from the future
        cands = [p for p in (ahead, behind) if p is not None]
        return min(cands, key=lambda p: p[1]) if cands else None


def _extrapolate(poses: list[tuple[int, np.ndarray]], t: int) -> tuple[np.ndarray, float] | None:
    """Constant velocity (linear position, geodesic rotation) from poses[0] through the nearest
    pose of `poses` at least VELOCITY_BASELINE_S from it (and within MAX_EXTRAPOLATION_S),
    to t; `poses` ordered by distance in time from t."""
    if not poses:
        return None
    t1, T1 = poses[0]
    horizon = abs(t - t1) * 1e-9
    if horizon > MAX_EXTRAPOLATION_S:
        return None
    older = [
        p
        for p in poses[1:]
        if VELOCITY_BASELINE_S <= abs(t1 - p[0]) * 1e-9 <= MAX_EXTRAPOLATION_S + VELOCITY_BASELINE_S
    ]
    if not older:
        return None
    t0, T0 = older[0]
    return interpolate_pose(T0, T1, (t - t0) / (t1 - t0)), horizon


# ============================================================================ catalogue


def floor_catalogue(det: DetectionResult, world: World, stream, backend: str) -> tuple[dict, int]:
    """({payload: CatalogueCode} of the floor codes decoded (not tracked) in the flight, number
    left out because no image gave their version again).  The modules per side come from
    re-decoding the frames where most still-unknown codes were decoded (fewest images read)."""
    where: dict[str, list[int]] = {}  # payload -> stamps where decoded
    corners: dict[str, np.ndarray] = {}
    for ts, dets in det.by_frame(FLOOR).items():
        for s in classify([d for d in dets if not d.tracked], world).floor:
            where.setdefault(s.detection.payload, []).append(ts)
            corners[s.detection.payload] = s.corners_world
    index = {int(t): i for i, t in enumerate(stream.timestamps_ns)}
    modules: dict[str, int] = {}
    unknown = set(where)
    tried: set[int] = set()
    by_frame: dict[int, set[str]] = {}
    for p, stamps in where.items():
        for t in stamps:
            by_frame.setdefault(t, set()).add(p)
    while unknown:
        best = max(
            (t for t in by_frame if t not in tried and by_frame[t] & unknown),
            key=lambda t: (len(by_frame[t] & unknown), -t),
            default=None,
        )
        if best is None:
            break
        tried.add(best)
        image = stream.load_image(index[best]) if best in index else None
        if image is None:
            continue
        for code in detect_image(image, backend):
            if code.payload in unknown and code.modules is not None:
                modules[code.payload] = int(code.modules)
                unknown.discard(code.payload)
    cat = {p: CatalogueCode(corners[p], modules[p]) for p in sorted(modules)}
    return cat, len(unknown)


# ============================================================================ the pass


def track_chunks(first_t: np.ndarray, stamps_ns: np.ndarray, n_frames: int) -> list[tuple[int, int]]:
    """[start, stop) frame ranges of the pass: about TRACK_CHUNK_FRAMES frames each, each start
    at a frame with a first-pass pose and another within MAX_EXTRAPOLATION_S before it."""
    posed = set(int(t) for t in first_t)
    first = np.asarray(first_t, dtype=np.int64)
    starts = [0]
    nominal = TRACK_CHUNK_FRAMES
    i = nominal
    while i < n_frames:
        t = int(stamps_ns[i])
        k = int(np.searchsorted(first, t))
        if t in posed and k > 0 and (t - first[k - 1]) * 1e-9 <= MAX_EXTRAPOLATION_S:
            starts.append(i)
            nominal = i + TRACK_CHUNK_FRAMES
            i = nominal
        else:
            i += 1
    return [(a, b) for a, b in zip(starts, starts[1:] + [n_frames])]


def _track_chunk(context, task: tuple[int, int]):
    """The pass over floor frames [start, stop): (tracked detections, TrackReport)."""
    stream, camera, world, catalogue, first_t, first_T, decoded, corner_sigma_px = context
    start, stop = task
    predictor = PosePredictor(first_t, first_T)
    tracker = CodeTracker(camera)
    rep = TrackReport()
    out: list[QRDetection] = []
    h, w = camera.height, camera.width
    for i in range(start, stop):
        t = int(stream.timestamps_ns[i])
        pred = predictor.predict(t)
        if pred is None:
            continue
        rep.frames_predicted += 1
        T_body, horizon_s = pred
        T_cam_world = inv_T(camera.T_world_cam(T_body))
        frame_dets = decoded.get(t, [])
        seen = {d.payload for d in frame_dets}
        sigma = PREDICTION_SIGMA_PX + PREDICTION_SIGMA_PX_PER_S * horizon_s
        predicted = {}
        for payload, code in catalogue.items():
            if payload in seen:
                continue
            p_cam = transform_points(T_cam_world, code.corners_world)
            if np.any(p_cam[:, 2] <= 0):
                continue
            uv = camera.project(p_cam)
            side_px = float(np.mean(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1)))
            if side_px >= TRACK_MIN_MODULE_PX * code.modules and symbol_in_view(uv, code.modules, (h, w)):
                predicted[payload] = (uv, sigma, code.modules)
        if not predicted:
            continue
        image = stream.load_image(i)
        if image is None:
            continue
        rep.frames_tried += 1
        tracked = tracker.step(
            image, FLOOR, t, frame_dets, [None] * len(frame_dets), predicted, own_motion=False
        )
        if not tracked:
            continue
        out.extend(tracked)
        rep.frames_tracked += 1
        rep.frames_tracked_only += not frame_dets
        floor = classify(frame_dets + tracked, world).floor
        res = estimate_floor_pose(floor, camera, corner_sigma_px) if floor else None
        if res is None:
            continue
        rep.poses_added += not predictor.has_first_pose(t)
        position_var = np.diag(np.asarray(res.covariance).reshape(POSE_DOF, POSE_DOF))[3:]
        if float(np.sqrt(np.max(position_var))) <= MAX_FEEDBACK_POSITION_SIGMA_M:
            predictor.add(t, res.T_world_body)
    rep.stats = tracker.stats
    return out, rep


def track_flight(
    log,
    det: DetectionResult,
    traj_pnp: Trajectory,
    corner_sigma_px: float,
    workers: int = 1,
    backend: str = "zxing",
) -> tuple[DetectionResult, TrackReport]:
    """The track pass over the floor camera of `log` (module docstring): `det` with the tracked
    detections added (tracked=True; CameraStats tracked, frames_with_tracked_only,
    frames_with_code and detections counted), and what the pass did."""
    t0 = time.perf_counter()
    rep = TrackReport()
    stream = log.floor
    camera: CameraModel = stream.camera
    if camera.rolling_shutter:
        rep.skipped_reason = "rolling-shutter floor camera (predictions are global-shutter projections)"
        return det, rep
    catalogue, rep.no_modules = floor_catalogue(det, log.world, stream, backend)
    rep.catalogue = len(catalogue)
    decoded = {t: [d for d in ds if not d.tracked] for t, ds in det.by_frame(FLOOR).items()}
    if not catalogue or len(traj_pnp) == 0:
        rep.skipped_reason = "no floor code decoded and posed in this flight"
        return det, rep
    first_t = np.asarray(traj_pnp.timestamps_ns, dtype=np.int64)
    first_T = np.asarray(traj_pnp.T_world_body, dtype=float)
    chunks = track_chunks(first_t, stream.timestamps_ns, len(stream))
    context = (stream, camera, log.world, catalogue, first_t, first_T, decoded, corner_sigma_px)
    tracked: list[QRDetection] = []
    for chunk_dets, chunk_rep in parallel_map(
        _track_chunk, chunks, max(1, min(workers, len(chunks))), context, preload=["fusion.qr.predict"]
    ):
        tracked.extend(chunk_dets)
        for k, v in vars(chunk_rep.stats).items():
            setattr(rep.stats, k, getattr(rep.stats, k) + v)
        for name in (
            "frames_predicted",
            "frames_tried",
            "frames_tracked",
            "frames_tracked_only",
            "poses_added",
        ):
            setattr(rep, name, getattr(rep, name) + getattr(chunk_rep, name))
    rep.chunks = len(chunks)
    rep.seconds = time.perf_counter() - t0
    logger.info(rep.note())
    return with_tracked(det, tracked, rep), rep


def with_tracked(det: DetectionResult, tracked: list[QRDetection], rep: TrackReport) -> DetectionResult:
    """`det` with the floor camera's `tracked` detections merged in time order and counted."""
    if not tracked:
        return det
    stats = {k: CameraStats(**vars(v)) for k, v in det.stats.items()}
    st = stats.setdefault(FLOOR, CameraStats())
    st.tracked += len(tracked)
    st.detections += len(tracked)
    st.frames_with_tracked_only += rep.frames_tracked_only
    st.frames_with_code += rep.frames_tracked_only
    dets = sorted(
        det.detections + tracked, key=lambda d: (d.camera, d.timestamp_ns, d.tracked)
    )  # stable: a frame's decoded codes keep their order, tracked ones after them
    return DetectionResult(dets, stats, list(det.skipped), det.backend, det.from_cache, det.cache_status)


def without_tracked(det: DetectionResult) -> DetectionResult:
    """`det` with every tracked detection and its counts removed (what detection alone gave)."""
    if not any(d.tracked for d in det.detections):
        return det
    stats = {k: CameraStats(**vars(v)) for k, v in det.stats.items()}
    for st in stats.values():
        st.detections -= st.tracked
        st.frames_with_code -= st.frames_with_tracked_only
        st.tracked = st.frames_with_tracked_only = 0
    dets = [d for d in det.detections if not d.tracked]
    return DetectionResult(dets, stats, list(det.skipped), det.backend, det.from_cache, det.cache_status)


def tracked_fingerprint(fingerprint: str) -> str:
    """The detection cache's fingerprint once the track pass added its sightings: the flight's
    (detect.flight_fingerprint) and TRACK_METHOD."""
    return hashlib.sha256(f"{fingerprint}/{TRACK_METHOD}".encode()).hexdigest()
