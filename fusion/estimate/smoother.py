"""GTSAM fusion of per-frame QR poses with IMU / velocity and load observations.

One state per floor-camera frame: X(k) Pose3 T_world_body, V(k) world velocity, B(k) IMU bias
(when there is an IMU).  Factors (see fusion.estimate.graph):

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
`smooth_incremental` = iSAM2 (QR factorization), the estimate as known at each frame (causal).
"""
from __future__ import annotations

import ctypes
import math
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from fusion.errors import EstimationError
from fusion.estimate import graph as G
from fusion.estimate.common import (
    FusionConfig,
    FusionResult,
    check_inputs,
    first_velocity,
    group_load_obs,
    initial_poses,
    initial_velocities,
    inlier_raw_mask,
    match_to_frames,
    velocity_at_frames,
)
from fusion.estimate.graph import B, L, V, X
from fusion.estimate.marginals import chain_marginals
from fusion.geometry import yaw_of
from fusion.log.euroc import ImuData, VelocityData
from fusion.types import LoadEstimate, LoadMap, LoadObservation, Trajectory

__all__ = ["smooth", "smooth_incremental", "build_problem", "Problem", "imu_coverage",
           "imu_subintervals"]


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
    hole = np.flatnonzero(d > gap)                      # hole (t[i] + nominal, t[i+1])
    if hole.size:
        h0 = t[hole] + min(nominal, gap)
        h1 = t[hole + 1]
        # interval overlaps a hole if a < h1 and b > h0
        j = np.searchsorted(h1, a, side="right")        # first hole ending after a
        jj = np.clip(j, 0, len(h1) - 1)
        overlaps = (j < len(h1)) & (b > h0[jj])
        ok &= ~overlaps
    return ok


def imu_subintervals(frame_t: np.ndarray, imu: ImuData, covered: np.ndarray):
    """Split the covered frame intervals at IMU sample times and at frame times.

    Returns (k (M,) frame interval, dt (M,) s, gyro (M, 3), accel (M, 3)) in time order: each
    sub-interval's measurement is the IMU signal linearly interpolated to its midpoint (samples
    are instantaneous; holding a sample over the following period instead would lag the
    attitude by half a sample period, which the NEES shows)."""
    t = imu.timestamps_ns
    ks = np.flatnonzero(covered)
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


def preintegrate(frame_t: np.ndarray, imu: ImuData, covered: np.ndarray,
                 params: gtsam.PreintegrationCombinedParams) -> dict[int, gtsam.PreintegratedCombinedMeasurements]:
    """Preintegrated measurements for each covered interval k (between frames k and k+1), with
    zero bias as the linearisation point (sub-intervals from imu_subintervals)."""
    k_of, dts, gyr, acc = imu_subintervals(frame_t, imu, covered)
    out: dict[int, gtsam.PreintegratedCombinedMeasurements] = {}
    bias0 = gtsam.imuBias.ConstantBias()
    pim, cur = None, -1
    for j, (k, dt) in enumerate(zip(k_of.tolist(), dts.tolist())):
        if k != cur:
            pim = gtsam.PreintegratedCombinedMeasurements(params, bias0)
            out[k] = pim
            cur = k
        pim.integrateMeasurement(acc[j], gyr[j], dt)
    return out


def gyro_fill_rotations(T_init: np.ndarray, known: np.ndarray, pims: dict) -> int:
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


@dataclass
class Problem:
    """The factor graph of one flight, with each factor tagged by the frame at which it becomes
    available (the newest frame among its keys), and the initial values."""
    frame_t: np.ndarray
    factors: list = field(default_factory=list)        # gtsam factors
    factor_frame: list = field(default_factory=list)   # frame index per factor
    robust_kind: dict = field(default_factory=dict)    # factor index -> "pose" / "load" / "corners"
    robust_threshold: dict = field(default_factory=dict)   # factor index -> kernel threshold
    initial: gtsam.Values = field(default_factory=gtsam.Values)
    T_init: np.ndarray | None = None
    v_init: np.ndarray | None = None
    has_imu: bool = False
    k_first: int = 0                                    # first frame with an (inlier) raw pose
    load_ids: list = field(default_factory=list)
    load_first_frame: dict = field(default_factory=dict)   # j -> first frame observing it
    load_init: dict = field(default_factory=dict)           # j -> (3,) initial position
    load_nobs: dict = field(default_factory=dict)
    load_first_pcam: dict = field(default_factory=dict)     # j -> p_cam of the first sighting
    load_sightings: dict = field(default_factory=dict)      # j -> [(frame, p_cam)] in time order
    load_args: dict = field(default_factory=dict)   # factor index -> (k, j, p_cam, cov_cam)
    T_body_cam: np.ndarray | None = None
    thresholds: dict = field(default_factory=dict)      # "pose" / "load" -> Mahalanobis threshold
    pims: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)

    def add(self, factor, k: int, kind: str | None = None, threshold: float | None = None) -> None:
        if kind is not None:
            self.robust_kind[len(self.factors)] = kind
            self.robust_threshold[len(self.factors)] = threshold if threshold is not None \
                else self.thresholds[kind]
        self.factors.append(factor)
        self.factor_frame.append(int(k))

    def graph(self) -> gtsam.NonlinearFactorGraph:
        g = gtsam.NonlinearFactorGraph()
        for f in self.factors:
            g.add(f)
        return g


def tight_corner_data(frame_t: np.ndarray, floor_frames: dict | None, floor_camera,
                      config: FusionConfig, stats: dict) -> dict:
    """{frame index: (corners_world (4c, 3), corners_px (4c, 2), whitening (c, 8, 8))} for tight
    coupling; {} when it is off or impossible (the reason goes to stats['tight'])."""
    if not config.tight:
        stats["tight"] = "off"
        return {}
    if not floor_frames or floor_camera is None:
        stats["tight"] = "no floor sightings / floor camera given: loosely coupled"
        return {}
    if getattr(floor_camera, "mount", "body_fixed") != "body_fixed":
        stats["tight"] = f"{floor_camera.mount} floor camera not supported: loosely coupled"
        return {}
    from fusion.qr.pnp import corner_whitening
    t = np.array(sorted(floor_frames), dtype=np.int64)
    idx = match_to_frames(frame_t, t, config.max_sync_s)
    out = {}
    for ts, k in zip(t.tolist(), idx.tolist()):
        sightings = [s for s in floor_frames[ts]
                     if np.all(np.isfinite(np.asarray(s.detection.corners_px, float)))]
        if k < 0 or not sightings:
            continue
        P = np.concatenate([np.asarray(s.corners_world, float).reshape(4, 3) for s in sightings])
        uv = np.concatenate([np.asarray(s.detection.corners_px, float).reshape(4, 2)
                             for s in sightings])
        W = corner_whitening([s.detection for s in sightings], config.corner_sigma_px)
        out[k] = (P, uv, W)
    stats["tight"] = "on"
    return out


def build_problem(frame_times_ns, imu: ImuData | None, raw: Trajectory,
                  load_obs: list[LoadObservation] | None, T_body_frontcam: np.ndarray,
                  velocity: VelocityData | None = None,
                  config: FusionConfig | None = None, floor_frames: dict | None = None,
                  floor_camera=None) -> Problem:
    """Check the inputs and build the factor graph and initial values (no optimisation).

    Tight coupling (`config.tight` with `floor_frames` {frame timestamp_ns: [FloorSighting]} and
    the floor `floor_camera` CameraModel): at frames with floor sightings the known world
    corners are reprojection factors on X(k) (graph.floor_corner_factor) instead of the raw
    pose factor; the raw poses still give the initial values and the factors elsewhere.

    Raises EstimationError for: no raw pose at all ("no floor code was read in this flight"),
    non-increasing / duplicated timestamps or NaNs in any input (naming the sample index), raw
    poses at no frame time, neither IMU nor velocity."""
    config = config or FusionConfig()
    frame_t, rawp, imu, velocity, T_bc = check_inputs(frame_times_ns, imu, raw, velocity,
                                                      T_body_frontcam, config)

    n = len(frame_t)
    pb = Problem(frame_t=frame_t, has_imu=imu is not None, T_body_cam=T_bc)
    use = inlier_raw_mask(rawp, config)
    pb.T_init = initial_poses(frame_t, rawp, config, use)
    pb.v_init = initial_velocities(frame_t, pb.T_init)
    pb.k_first = int(rawp.frame_idx[use].min())
    thr_pose = config.threshold(6 if rawp.full_pose else 4)
    thr_load = config.threshold(3)
    pb.thresholds = {"pose": thr_pose, "load": thr_load}

    # ---- motion model between consecutive frames
    covered = np.zeros(max(n - 1, 0), bool)
    if imu is not None:
        covered = imu_coverage(frame_t, imu, config.max_imu_gap_s)
        params = G.imu_params(imu.noise, imu.T_body_imu, config.integration_sigma)
        pb.pims = preintegrate(frame_t, imu, covered, params)
        gyro_fill_rotations(pb.T_init, np.unique(rawp.frame_idx[use]), pb.pims)
    for k in range(n - 1):
        if covered[k]:
            pb.add(gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1),
                                           pb.pims[k]), k + 1)
        else:
            dt = (frame_t[k + 1] - frame_t[k]) * 1e-9
            for f in G.bridge_factors(k, k + 1, dt, config.bridge_accel_sigma_m_s2,
                                      config.bridge_rate_sigma_rad_s, imu is not None,
                                      imu.noise if imu is not None else None):
                pb.add(f, k + 1)
    # segments = maximal runs of IMU-covered intervals
    edges = np.diff(np.r_[0, covered.astype(int), 0])
    pb.stats.update(imu_intervals=int(covered.sum()), bridged_intervals=int((~covered).sum()),
                    imu_segments=int((edges == 1).sum()))
    if imu is not None:
        t0, t1 = imu.timestamps_ns[0], imu.timestamps_ns[-1]
        pb.stats["frames_outside_imu"] = int(((frame_t < t0) | (frame_t > t1)).sum())

    # ---- priors
    v0 = first_velocity(frame_t, rawp, use, pb.k_first)
    pb.add(gtsam.PriorFactorVector(V(pb.k_first), v0, gtsam.noiseModel.Isotropic.Sigma(
        3, config.velocity_prior_sigma_m_s)), pb.k_first)
    if imu is not None:
        pb.add(gtsam.PriorFactorConstantBias(B(pb.k_first), gtsam.imuBias.ConstantBias(),
                                             gtsam.noiseModel.Diagonal.Sigmas(np.r_[
                                                 np.full(3, config.bias_prior_sigma_accel_m_s2),
                                                 np.full(3, config.bias_prior_sigma_gyro_rad_s)])),
               pb.k_first)

    # ---- QR pose factors (or, tightly coupled, corner reprojection factors)
    corner_frames = tight_corner_data(frame_t, floor_frames, floor_camera, config, pb.stats)
    n_pose = 0
    for m, k in enumerate(rawp.frame_idx.tolist()):
        if k in corner_frames:
            continue
        T = rawp.T_world_body[m]
        if rawp.full_pose:
            f = G.pose_prior_factor(k, T, rawp.covariances[m], config.robust_kernel, thr_pose)
        else:
            f = G.position_yaw_factor(k, T[:3, 3], float(yaw_of(T[:3, :3])),
                                      config.paper_sigma_xyz_m, config.paper_sigma_yaw_rad,
                                      config.robust_kernel, thr_pose)
        pb.add(f, k, "pose")
        n_pose += 1
    for k, (P, uv, W) in sorted(corner_frames.items()):
        thr = config.threshold(8 * len(W))
        pb.add(G.floor_corner_factor(k, floor_camera, P, uv, W, config.robust_kernel, thr), k,
               "corners", thr)
    pb.stats["pose_factors"] = n_pose
    pb.stats["corner_factors"] = len(corner_frames)
    pb.stats["raw_pose_input"] = "pose6" if rawp.full_pose else "position_yaw"

    # ---- velocity factors
    vmask, v_body = velocity_at_frames(frame_t, velocity, config)
    for k in np.flatnonzero(vmask).tolist():
        pb.add(G.body_velocity_factor(k, v_body[k], velocity.noise_m_s), k)
    pb.stats["velocity_factors"] = int(vmask.sum())

    # ---- loads
    groups, skipped = group_load_obs(frame_t, load_obs or [], config)
    pb.load_ids = sorted(groups)
    for j, lid in enumerate(pb.load_ids):
        obs = groups[lid]
        pts = []
        for k, o in obs:
            pb.load_args[len(pb.factors)] = (k, j, o.p_cam, o.cov_cam)
            pb.add(G.load_factor(k, j, o.p_cam, o.cov_cam, T_bc, config.robust_kernel, thr_load),
                   k, "load")
            T_wc = pb.T_init[k] @ T_bc
            pts.append(T_wc[:3, :3] @ np.asarray(o.p_cam, float) + T_wc[:3, 3])
        pb.load_init[j] = np.median(np.array(pts), axis=0)
        k_min, o_min = min(obs, key=lambda ko: ko[0])
        pb.load_first_frame[j] = k_min
        pb.load_first_pcam[j] = np.asarray(o_min.p_cam, float)
        pb.load_sightings[j] = sorted(((k, np.asarray(o.p_cam, float)) for k, o in obs),
                                      key=lambda kp: kp[0])
        pb.load_nobs[j] = len(obs)
    pb.stats["load_observations_skipped"] = skipped
    pb.stats["load_factors"] = sum(pb.load_nobs.values())

    # ---- initial values
    for k in range(n):
        pb.initial.insert(X(k), gtsam.Pose3(pb.T_init[k]))
        pb.initial.insert(V(k), pb.v_init[k])
        if imu is not None:
            pb.initial.insert(B(k), gtsam.imuBias.ConstantBias())
    for j, p in pb.load_init.items():
        pb.initial.insert(L(j), p)
    return pb


def robust_distances(pb: Problem, values: gtsam.Values) -> dict[int, float]:
    """Mahalanobis distance (whitened residual norm before the kernel) of each robust factor."""
    out = {}
    for i in pb.robust_kind:
        f = pb.factors[i]
        e = f.unwhitenedError(values)
        nm = f.noiseModel()
        out[i] = nm.noise().mahalanobisDistance(e) if isinstance(nm, gtsam.noiseModel.Robust) \
            else nm.mahalanobisDistance(e)
    return out


def count_rejections(pb: Problem, dist: dict[int, float]) -> dict:
    """Robust factors whose Mahalanobis distance exceeds the kernel threshold, per kind."""
    out = {"pose": 0, "load": 0, "corners": 0}
    for i, d in dist.items():
        if d > pb.robust_threshold[i]:
            out[pb.robust_kind[i]] += 1
    return out


# =========================================================================== batch


def levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                        max_iterations: int = 100, relative_tol: float = 1e-5,
                        lambda0: float = 1e-5, ordering: gtsam.Ordering | None = None,
                        errors: list | None = None):
    """Levenberg-Marquardt (Nocedal & Wright 2006, Sec. 10.3; GTSAM's defaults: lambda0 1e-5,
    factor 10, identity damping) driven from Python around GTSAM's linearize / multifrontal
    elimination, with one COLAMD ordering computed up front and reused.  Each iteration first
    tries the undamped Gauss-Newton step and damps only if that does not lower the error (from
    a good initial guess the first steps succeed).  Stops when an accepted step lowers the error
    by less than relative_tol (GTSAM's relativeErrorTol), or when an undamped step's actual
    decrease matches the linear model's predicted decrease to within relative_tol of the error:
    the model misfit bounds what a further step could gain, so the usual last step that only
    confirms convergence (a full linearise + eliminate) is skipped.

    Why not gtsam.LevenbergMarquardtOptimizer: with Python CustomFactors in the graph its
    linearisation took ~5 s per iteration on a 2-minute flight here (gtsam 4.3.0 wheel), 100x
    more than `graph.linearize` called from Python on the same graph; the maths is the same.

    Returns (values, iterations, linear_graph): linear_graph is the undamped linearisation of
    the last accepted step (at the iterate before the returned one, whose step changed the error
    by < relative_tol), reusable for marginal covariances; None if that step was damped or the
    model-misfit test stopped (then linearise at the returned values).
    `errors`, if given, receives the graph error at the start and after each accepted step."""
    if ordering is None:
        ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
    err = graph.error(values)
    if errors is not None:
        errors.append(err)
    lam = 0.0      # try the Gauss-Newton step first; damp only when it fails to descend
    keys = [int(k) for k in values.keys()]
    it = 0
    for it in range(1, max_iterations + 1):
        lin = graph.linearize(values)
        while True:
            if lam > 0:
                damped = lin.clone()
                _add_damping(damped, keys, lam)
                tree = damped.eliminateMultifrontal(ordering)
            else:
                tree = lin.eliminateMultifrontal(ordering)
            delta = tree.optimize()
            trial = values.retract(delta)
            new_err = graph.error(trial)
            if new_err <= err:
                break
            lam = lambda0 if lam == 0.0 else lam * 10.0
            if lam > 1e10:
                return values, it, None
        undamped = lam == 0.0
        converged = (err - new_err) <= relative_tol * max(err, 1e-300)
        if undamped and not converged:
            # the linear model's misfit on this step bounds what another step could still gain
            predicted = lin.error(gtsam.VectorValues.Zero(delta)) - lin.error(delta)
            if abs((err - new_err) - predicted) <= relative_tol * max(new_err, 1e-300):
                converged = True
                lin = None              # the covariance pass linearises at the solution
        values, err = trial, new_err
        if errors is not None:
            errors.append(err)
        lam = lam / 10.0 if lam > lambda0 else 0.0
        if converged:
            break
    return values, it, lin if undamped else None


def _add_damping(lin: gtsam.GaussianFactorGraph, keys, lam: float) -> None:
    s = math.sqrt(lam)
    for k in keys:
        d = _dim_of(k)
        lin.push_back(gtsam.JacobianFactor(k, s * np.eye(d), np.zeros(d),
                                           gtsam.noiseModel.Unit.Create(d)))


def _dim_of(key: int) -> int:
    return {ord("x"): 6, ord("v"): 3, ord("b"): 6, ord("l"): 3}[gtsam.Symbol(key).chr()]


def release_heap() -> None:
    """Hand the heap freed by GTSAM's eliminations back to the OS (glibc keeps it otherwise:
    ~250 MB after a 10-minute flight), so the covariance pass does not stack on top of it."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def poses_of(values: gtsam.Values, n: int) -> np.ndarray:
    """(n, 4, 4) T_world_body of X(0..n-1) (the only Pose3 keys in the graph)."""
    rows = gtsam.utilities.extractPose3(values)      # per pose: R row-major (9), t (3)
    if rows.shape[0] != n:
        raise EstimationError(f"expected {n} poses in the solution, found {rows.shape[0]}")
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = rows[:, :9].reshape(n, 3, 3)
    T[:, :3, 3] = rows[:, 9:]
    return T


def smooth(frame_times_ns, imu: ImuData | None, raw: Trajectory,
           load_obs: list[LoadObservation] | None, T_body_frontcam: np.ndarray,
           velocity: VelocityData | None = None,
           config: FusionConfig | None = None, floor_frames: dict | None = None,
           floor_camera=None) -> FusionResult:
    """Batch Levenberg-Marquardt smoothing of a whole flight (offline), with marginal covariances.

    frame_times_ns (N,) int64: floor-camera frame times (one state each); imu: ImuData or None
    (then velocity is required: velocity-only mode); raw: per-frame QR poses at a subset of the
    frame times (with (M,6,6) covariances, or None for the paper's position + yaw);
    load_obs: front-camera load observations with p_cam / cov_cam; T_body_frontcam (4,4);
    floor_frames {frame timestamp_ns: [fusion.qr.codes.FloorSighting]} and floor_camera
    (CameraModel of cam0): used only with config.tight (see build_problem).
    Returns FusionResult with the trajectory at every frame time (covariances (N,6,6), Pose3
    order, body frame), the load map (3x3 world covariances) and stats (iterations,
    initial/final error, rejected_* = robust factors beyond the kernel threshold at the robust
    solution, gated_* = those beyond `outlier_gate`, removed before the final solve, IMU
    segments / bridged intervals, times)."""
    config = config or FusionConfig()
    t0 = time.perf_counter()
    pb = build_problem(frame_times_ns, imu, raw, load_obs, T_body_frontcam, velocity, config,
                       floor_frames, floor_camera)
    t_build = time.perf_counter() - t0
    graph = pb.graph()
    ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
    errors: list[float] = []
    values, iterations, lin = levenberg_marquardt(graph, pb.initial, config.lm_max_iterations,
                                                   config.lm_relative_tol, ordering=ordering,
                                                   errors=errors)
    err0 = errors[0]
    dist = robust_distances(pb, values)
    rej = count_rejections(pb, dist)
    gated = {"pose": 0, "load": 0, "corners": 0}
    if config.outlier_gate is not None and any(d > config.outlier_gate for d in dist.values()):
        drop = {i for i, d in dist.items() if d > config.outlier_gate}
        for i in drop:
            gated[pb.robust_kind[i]] += 1
        graph = gtsam.NonlinearFactorGraph()
        for i, f in enumerate(pb.factors):
            if i not in drop:
                graph.add(f)
        values, it2, lin = levenberg_marquardt(graph, values, config.lm_max_iterations,
                                                config.lm_relative_tol, ordering=ordering,
                                                errors=errors)
        iterations += it2
    t_opt = time.perf_counter() - t0 - t_build
    release_heap()
    n = len(pb.frame_t)
    T = poses_of(values, n)
    cov = None
    lcov = {}
    covariance_method = "none"
    if config.compute_covariances:
        if lin is None:         # the last step was damped: linearise at the solution
            lin = graph.linearize(values)
        try:
            bulk = chain_marginals(lin, n, pb.has_imu, len(pb.load_ids))
        except np.linalg.LinAlgError:
            bulk = None
        if bulk is not None:
            cov, lc = bulk
            lcov = dict(enumerate(lc))
        else:                   # not the chain structure: gtsam's Bayes tree, key by key
            tree = lin.eliminateMultifrontal(ordering)
            cov = np.empty((n, 6, 6))
            for k in range(n):
                cov[k] = tree.marginalCovariance(X(k))
            for j in range(len(pb.load_ids)):
                lcov[j] = tree.marginalCovariance(L(j))
        covariance_method = "chain" if bulk is not None else "bayes_tree"
    t_cov = time.perf_counter() - t0 - t_build - t_opt
    loads = LoadMap("smoother", [LoadEstimate(lid, values.atPoint3(L(j)).copy(), lcov.get(j),
                                              pb.load_nobs[j])
                                 for j, lid in enumerate(pb.load_ids)])
    stats = dict(pb.stats, iterations=iterations, gated_pose_factors=gated["pose"],
                 gated_load_factors=gated["load"], gated_corner_factors=gated["corners"],
                 rejected_corner_factors=rej["corners"], initial_error=float(err0),
                 final_error=float(errors[-1]), rejected_pose_factors=rej["pose"],
                 rejected_load_factors=rej["load"], robust_kernel=config.robust_kernel,
                 pose_threshold=pb.thresholds["pose"], n_factors=len(pb.factors),
                 covariance_method=covariance_method,
                 time_build_s=t_build, time_optimize_s=t_opt, time_covariance_s=t_cov,
                 time_s=time.perf_counter() - t0)
    traj = Trajectory("smoother", pb.frame_t.copy(), T, cov)
    return FusionResult(traj, loads, stats)


# =========================================================================== incremental


LOAD_GENERATION_STRIDE = 10 ** 9       # L(j + g * stride): generation g of load j's variable


def smooth_incremental(frame_times_ns, imu: ImuData | None, raw: Trajectory,
                       load_obs: list[LoadObservation] | None, T_body_frontcam: np.ndarray,
                       velocity: VelocityData | None = None,
                       config: FusionConfig | None = None, floor_frames: dict | None = None,
                       floor_camera=None) -> FusionResult:
    """Causal incremental fusion: frame by frame, the factors available at that frame are added
    and the pose estimate and marginal covariance of X(k) *as known at frame k* are recorded (a
    filter-like output from a smoother).

    Engine: iSAM2 (QR factorization) inside gtsam's IncrementalFixedLagSmoother with lag
    `config.incremental_lag_s`: states older than the lag are marginalised, so the cost per frame
    stays bounded however long the flight.  A load's variable is marginalised too once it has not
    been seen for the lag; when the load is seen again a new variable (next generation,
    L(j + g * LOAD_GENERATION_STRIDE)) starts from a Gaussian prior = the old variable's
    estimate and marginal covariance just before it left (its correlation with the states still
    in the window is dropped: slightly optimistic, causal).  `incremental_lag_s=None`: plain
    iSAM2 over the whole flight (exact, but loads re-seen after a long time make it re-solve
    much of the graph, so its cost grows with the flight).

    Output starts at the first raw-pose frame (`stats['frames_before_first_fix']` earlier
    frames have no estimate).  The velocity prior at the start uses the first 0.5 s of raw poses
    (a start-up look-ahead).  Loads: the estimate and marginal covariance of each load's latest
    variable at the end of the flight."""
    config = config or FusionConfig()
    t0 = time.perf_counter()
    pb = build_problem(frame_times_ns, imu, raw, load_obs, T_body_frontcam, velocity, config,
                       floor_frames, floor_camera)
    t_build = time.perf_counter() - t0
    n, k0 = len(pb.frame_t), pb.k_first
    by_frame: list[list[int]] = [[] for _ in range(n)]
    for i, k in enumerate(pb.factor_frame):
        by_frame[k].append(i)
    pcam_at = {(k, j): p for j, sightings in pb.load_sightings.items() for k, p in sightings}
    # per factor: the load it observes (-1: none); factors on states before k0 are left out
    chr_l, mask = ord("l"), (1 << 56) - 1
    load_of, usable = {}, {}
    for i, f in enumerate(pb.factors):
        keys = f.keys()
        usable[i] = all((key >> 56) == chr_l or (key & mask) >= k0 for key in keys)
        load_of[i] = next(((key & mask) for key in keys if (key >> 56) == chr_l), -1)

    params = gtsam.ISAM2Params()
    params.setFactorization("QR")
    params.setRelinearizeThreshold(config.isam_relinearize_threshold)
    params.relinearizeSkip = config.isam_relinearize_skip
    lag = config.incremental_lag_s
    engine = gtsam.ISAM2(params) if lag is None else \
        gtsam.IncrementalFixedLagSmoother(float(lag), params)
    t_rel = (pb.frame_t - pb.frame_t[0]) * 1e-9
    gen: dict[int, int] = {}            # load j -> generation of its current variable
    last_seen: dict[int, float] = {}    # load j -> time stamp of its current variable
    left: dict[int, tuple] = {}         # load j -> (estimate, covariance) when it left the window
    n_generations = 0

    # raw pose factors index by frame, for the causal initial guess
    pose_at = {pb.factor_frame[i]: i for i, kind in pb.robust_kind.items()
               if kind == "pose" and isinstance(pb.factors[i], gtsam.PriorFactorPose3)}
    T_out = np.empty((n - k0, 4, 4))
    cov_out = np.empty((n - k0, 6, 6))
    pose_k = gtsam.Pose3(pb.T_init[k0])
    vel_k = pb.v_init[k0]
    bias_k = gtsam.imuBias.ConstantBias()
    for k in range(k0, n):
        tk = float(t_rel[k])
        g = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        # causal initial guess: IMU prediction, else the raw pose, else the previous state
        if k > k0 and pb.has_imu and (k - 1) in pb.pims:
            nav = pb.pims[k - 1].predict(gtsam.NavState(pose_k, vel_k), bias_k)
            pose_guess, vel_guess = nav.pose(), nav.velocity()
        elif k in pose_at and pb.stats["raw_pose_input"] == "pose6":
            pose_guess, vel_guess = pb.factors[pose_at[k]].prior(), vel_k
        else:
            pose_guess, vel_guess = pose_k, vel_k
        if k == k0:
            pose_guess = gtsam.Pose3(pb.T_init[k0])
        vals.insert(X(k), pose_guess)
        vals.insert(V(k), vel_guess)
        new_keys = [X(k), V(k)]
        if pb.has_imu:
            vals.insert(B(k), bias_k)
            new_keys.append(B(k))
        if lag is not None:
            # loads whose variable leaves the window in this update: keep their last marginal
            cutoff = tk - lag
            for j in [j for j, ts in last_seen.items() if ts < cutoff and j not in left]:
                key = L(j + gen[j] * LOAD_GENERATION_STRIDE)
                left[j] = (engine.calculateEstimatePoint3(key), engine.marginalCovariance(key))
        for i in by_frame[k]:
            if not usable[i]:
                continue
            f = pb.factors[i]
            j = load_of[i]
            if j >= 0:
                if j not in gen or j in left:        # first sighting, or back after leaving
                    T_wc = pose_guess.matrix() @ pb.T_body_cam
                    if j not in gen:
                        gen[j] = 0
                        guess = T_wc[:3, :3] @ pcam_at[(k, j)] + T_wc[:3, 3]
                    else:
                        gen[j] += 1
                        n_generations += 1
                        guess, cov = left.pop(j)
                        g.add(gtsam.PriorFactorPoint3(
                            L(j + gen[j] * LOAD_GENERATION_STRIDE), guess,
                            gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))))
                    vals.insert(L(j + gen[j] * LOAD_GENERATION_STRIDE), guess)
                if gen[j] > 0:
                    kk, _, p_cam, cov_cam = pb.load_args[i]
                    f = G.load_factor(kk, j, p_cam, cov_cam, pb.T_body_cam, config.robust_kernel,
                                      pb.thresholds["load"],
                                      load_key=L(j + gen[j] * LOAD_GENERATION_STRIDE))
                last_seen[j] = tk
                new_keys.append(L(j + gen[j] * LOAD_GENERATION_STRIDE))
            g.add(f)
        if lag is None:
            engine.update(g, vals)
        else:
            for key in new_keys:
                stamps.insert((key, tk))
            engine.update(g, vals, stamps)
        pose_k = engine.calculateEstimatePose3(X(k))
        vel_k = engine.calculateEstimateVector(V(k))
        if pb.has_imu:
            bias_k = engine.calculateEstimateConstantBias(B(k))
        T_out[k - k0] = pose_k.matrix()
        cov_out[k - k0] = engine.marginalCovariance(X(k))
    loads = []
    for j, lid in enumerate(pb.load_ids):
        if j not in gen:
            continue
        if j in left:
            p, c = left[j]
        else:
            key = L(j + gen[j] * LOAD_GENERATION_STRIDE)
            p, c = engine.calculateEstimatePoint3(key), engine.marginalCovariance(key)
        loads.append(LoadEstimate(lid, np.asarray(p, float).copy(), c, pb.load_nobs[j]))
    elapsed = time.perf_counter() - t0
    duration = (pb.frame_t[-1] - pb.frame_t[k0]) * 1e-9
    stats = dict(pb.stats, frames_before_first_fix=k0, time_build_s=t_build, time_s=elapsed,
                 incremental_lag_s=lag, load_generations=n_generations,
                 realtime_factor=duration / max(elapsed - t_build, 1e-9))
    traj = Trajectory("incremental", pb.frame_t[k0:].copy(), T_out, cov_out)
    return FusionResult(traj, LoadMap("incremental", loads), stats)
