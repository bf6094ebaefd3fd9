"""The track pass (issue 10 item 4): floor codes that a predicted body pose puts in view, in floor
frames where they did not decode, found and refined by fusion.qr.track.CodeTracker and named
from the prediction (gated by the innovation), never guessed.

Detection runs before any pose exists, so this pass runs after the first per-frame
localisation (pipeline.track_stage):

1. The catalogue: every floor code decoded somewhere in the flight (its world corners from its
   payload, fusion.qr.codes.classify; its modules per side from one re-decoded image).  Only
   these codes can be tracked: a code never decoded has no identity to give.
2. Per floor frame, in time order, the body pose predicted offline from the PnP poses on both
   sides (`PosePredictor`): the frame's own first-pass pose; with an IMU (`ImuBridge`), the
   IMU's motion between the last pose before (first pass, or found earlier in this pass) and
   the next first-pass pose when they are at most MAX_IMU_BRIDGE_S apart (rotation from the
   gyro, position double-integrated and pinned at both poses, a constant accelerometer bias
   fitted from the poses around the gap), else extrapolated with the IMU at most
   MAX_EXTRAPOLATION_S; without one (or where it does not apply), linear / geodesic
   interpolation between poses at most MAX_INTERPOLATION_GAP_S apart, else constant velocity
   extrapolated from the last poses (over at least VELOCITY_BASELINE_S) at most
   MAX_EXTRAPOLATION_S ahead, forward or backward.  The first pass's poses (and the
   re-stamped ones) come first: where the IMU bridges two of them, that is the prediction.
   Else, with an IMU, an IMU trajectory fitted to every pose within FIT_WINDOW_S of the
   nearest one (ImuFit: attitude, velocity and body-frame gyro and accelerometer biases; the
   pass's own poses too, and those too uncertain to predict from alone weighted by their
   sigma), up to FIT_MAX_EXTRAPOLATION_S from the nearest pose.  Else the poses found by the
   pass itself (step 3) are used where that is nearer in time (PosePredictor.predict).
3. The catalogue's codes the predicted camera pose (camera.T_world_cam: mounts) puts in view
   with their quiet zone (track.symbol_in_view) and that did not decode in the frame are given
   to CodeTracker.step(predicted=..., own_motion=False), when their modules are at least
   TRACK_MIN_MODULE_PX, with a prediction sigma of
   PREDICTION_SIGMA_PX + PREDICTION_SIGMA_PX_PER_S x (time to the nearest pose used).  A frame
   with tracked codes gets a PnP pose from all its codes (its decoded and tracked ones); its
   tracked codes are kept only when that pose lies within POSE_GATE_M (+ POSE_GATE_M_PER_S x
   the time to the nearest pose used) of the predicted one, POSE_GATE_BRIDGE_M (+
   POSE_GATE_BRIDGE_M_PER_S x ...) where the prediction is the frame's own first-pass pose or a
   first-pass IMU bridge (with several tracked codes, the one
   furthest from its prediction is left out and the pose solved again, until it does or one is
   left); dark squares left by failed re-stamp decodes (fusion.qr.restamp.restamp_candidates)
   are the tracker's extra starts and fallback corners (fusion.qr.track.match_square); that
   pose predicts
   later frames when its position sigma is at most
   MAX_FEEDBACK_POSITION_SIGMA_M, so a code is followed through a long stretch of blur.
4. A backward sweep: the floor frames still without a pose or a tracked sighting, each chunk
   latest first, the forward sweep's poses added to the predictor (so a code is followed back
   from the next decode where the forward chain broke, e.g. before the first decode).
5. The flight is cut into chunks of about TRACK_CHUNK_FRAMES frames at frames with two
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
from dataclasses import dataclass, field, fields, replace

import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import GRAVITY_M_S2
from fusion.geometry import (
    integrate_gyro,
    interpolate_pose,
    inv_T,
    make_T,
    so3_exp,
    so3_log,
    transform_points,
)
from fusion.parallel import parallel_map
from fusion.qr.codes import classify
from fusion.qr.detect import RAW_CORNER_SIGMA_PX, CameraStats, DetectionResult, detect_image
from fusion.qr.pnp import estimate_floor_pose
from fusion.qr.refine import refine_frames
from fusion.qr.restamp import restamp_candidates
from fusion.qr.track import (
    TRACK_AGREEMENT_SIGMA_PX,
    TRACK_CROSSINGS_PASS,
    CodeTracker,
    TrackStats,
    symbol_in_view,
)
from fusion.types import CameraRole, QRDetection, Trajectory
from fusion.world import World

logger = logging.getLogger(__name__)

# in the tracked cache's fingerprint: change with the method
TRACK_METHOD = (
    "pose-track/5+restamp+squares+backward+no-crossings+bridge-gate+imu-fit+bridge-fit+no-locate-across"
)
PREDICTION_SIGMA_PX = 3.0  # 1-sigma per corner coordinate of a code projected with a PnP pose
PREDICTION_SIGMA_PX_PER_S = 10.0  # ... plus this per second to the nearest pose used
MAX_INTERPOLATION_GAP_S = 1.0  # interpolate between poses at most this far apart
MAX_EXTRAPOLATION_S = 0.5  # extrapolate at most this far from the last pose
VELOCITY_BASELINE_S = 0.05  # velocity over at least this (consecutive poses: their noise, amplified)
# With an IMU, poses up to this far apart are bridged by the IMU's motion pinned at both ends
# (ImuBridge): on a 20 ms-exposure flight the cruise between two hovers left 0.5-1.8 s without a
# decoded pose, and the geodesic interpolation / constant-velocity extrapolation put the codes
# 14-80 px off (the body pitches as it accelerates), beyond refinement's capture (BENCHMARKS.md).
# An accelerometer bias b leaves at most b T^2 / 8 with both ends pinned (T = 2 s, 0.05 m/s^2:
# 2.5 cm)
MAX_IMU_BRIDGE_S = 2.0
# The bridge's accelerometer-bias fit from the poses around a gap (ImuBridge.bridge `extra`):
# poses this far outside the gap, PnP's position noise, the bias prior (a MEMS accelerometer's
# turn-on bias, tens of mg; the simulator's default flight drifted 0.13 m/s^2: BENCHMARKS.md)
BIAS_WINDOW_S = 0.5
POSE_NOISE_M = 0.002
ACCEL_BIAS_PRIOR_M_S2 = 0.3
GRAVITY_WORLD_M_S2 = np.array([0.0, 0.0, -GRAVITY_M_S2])  # world z up
TRACK_CHUNK_FRAMES = 300  # nominal frames per chunk of the pass (10 s at 30 Hz)
# Smaller predicted modules are not tried.  2.5 px before the pose gate (POSE_GATE_M): on the
# clean demo flight, codes tracked at under 2.5 px per module (2.6 m up, turning) were up to
# 3.6 px off and gave PnP poses 8-25 cm off (BENCHMARKS.md).  With the pose gate and predictions
# from the first pass's IMU bridges, 2.0 px: on the 20 ms-exposure flight (seed 0) the 2.0-2.5 px
# codes tracked were 0.70 px off (median; 3.9 px at most), and 63 floor frames that had only
# such codes in view got a pose (BENCHMARKS.md, seventh session)
TRACK_MIN_MODULE_PX = 2.0
# A pose found by the pass predicts later frames only when PnP's position sigma (its covariance,
# Pose3 order [r, t]) is at most this: single blurred codes gave poses 10-55 cm off with sigma
# 3-50 cm on a 20 ms-exposure flight (good ones: 0.04 cm), and fed back, the next predictions
# followed them
MAX_FEEDBACK_POSITION_SIGMA_M = 0.01
# A frame's tracked sightings are kept only when PnP on the frame's codes (decoded and tracked)
# puts the body within POSE_GATE_M + POSE_GATE_M_PER_S x horizon of the predicted pose (a
# pose-level innovation gate): on a 20 ms-exposure flight single tracked codes 1-9 px off gave
# PnP poses 13-63 cm off, the IMU-bridged prediction there was within 1 cm (BENCHMARKS.md)
POSE_GATE_M = 0.05
POSE_GATE_M_PER_S = 0.1
# ... and tighter where the prediction is the IMU bridge between two first-pass poses: within
# 0.14-0.38 cm (median; p90 0.3-0.9 cm) up to 1 s on a 20 ms-exposure flight (BENCHMARKS.md, seventh session)
POSE_GATE_BRIDGE_M = 0.03
POSE_GATE_BRIDGE_M_PER_S = 0.05
# Where neither the frame's own pose nor a first-pass IMU bridge applies, the pose is predicted
# from an IMU trajectory fitted to every pose (first pass, re-stamped, the pass's own) within
# FIT_WINDOW_S of the nearest one (ImuFit: a start attitude, position and velocity, body-frame
# gyro and accelerometer biases), on the nearer side of the frame, or on both when their nearest
# poses are at most MAX_IMU_BRIDGE_S apart; at most FIT_MAX_EXTRAPOLATION_S from the nearest
# pose.  On the strip-occluded ECC L flight (seed 0) single-code re-stamped poses at 2.6 m put
# the codes up to 7 px off, and the IMU extrapolated from the last two 3-6 px off at 0.3-0.6 s:
# beyond the 2-module gate (~4 px there), so the chain broke; a prototype of the fit over the
# poses of the last second was 0.65 cm / 0.12 deg off 0.5 s later, 2.5 cm 1 s later; with it
# the pass posed 84-88 % of the floor frames instead of 74-76 % (BENCHMARKS.md, eighth session)
FIT_WINDOW_S = 1.0
USE_FIT = True  # (a switch for the benches: the old prediction where False)
# Between two first-pass poses that ImuBridge spans, ImuFit over the first pass's poses within
# FIT_WINDOW_S outside both ends instead (PosePredictor._predict_bridge_fit): the bridge pins
# both ends, and where an end is a single small code 2 cm off its velocity fit put the middle
# of a 2 s gap 6 cm off (20 ms-exposure flight, seed 3, 36.9-38.8 s: the codes 7-11 px off at
# 2 px per module, beyond the 2-module gate); against the truth at every bridged floor frame of
# the 20 ms-exposure seeds 0-3 the fit was nearer in median and p90 in every gap-length class
# (e.g. seed 3, 1.5-2 s gaps: 0.23 / 0.58 cm against 0.48 / 5.54 cm; BENCHMARKS.md, ninth session).  The
# bridge where the fit has too few poses
USE_BRIDGE_FIT = True
# Where the prediction is that two-sided fit, the tracker starts refinement at the prediction,
# not at the symbol located by its function patterns (track.locate_symbol, a sharp template):
# under 10-20 px of blur at 3.4-3.8 px per module (3-5 modules) the located start put single
# codes' refined corners 3-6 px off where the fitted prediction was 0.2-2 px off, their PnP poses
# 10-35 cm off (pose-gated); with both changes the 20 ms-exposure seeds 0 / 1 / 2 / 3 posed
# 936 / 951 / 946 / 953 floor frames instead of 914 / 907 / 910 / 893 (change 1 alone: seed 0
# 905, seed 3 914; BENCHMARKS.md, ninth session).  The locator stays for one-sided predictions (horizons up
# to 1 s), whose errors it was made for
TRACK_LOCATE_TWO_SIDED = False
FIT_MIN_POSES = 6
FIT_MIN_SPAN_S = 0.3
FIT_MAX_EXTRAPOLATION_S = 1.0
FIT_GYRO_BIAS_PRIOR_RAD_S = 0.01  # a MEMS gyro's turn-on bias is ~1e-3 rad/s (the simulator: 2e-3)
FIT_ROTATION_NOISE_RAD = 0.002  # a re-stamped single-code pose's rotation, ~0.1 deg
FIT_MAX_POSITION_SIGMA_M = 0.05  # the pass's poses up to this sigma join the fit, weighted by it
FIT_OUTLIER_SIGMAS = 3.0  # poses this many residual RMS off are left out and the fit redone once
POSE_DOF = 6  # Pose3 tangent: rotation (3) then translation (3)
FLOOR = CameraRole.FLOOR.value
# What the pass did at a floor frame (TrackReport.frame_outcomes), most advanced step reached:
OUTCOMES = (
    "no_prediction",  # no pose within MAX_INTERPOLATION_GAP_S / MAX_EXTRAPOLATION_S
    "none_in_view",  # no undecoded catalogue code predicted in view with its quiet zone
    "too_small",  # ... only ones under TRACK_MIN_MODULE_PX per module
    "no_image",  # the image could not be read
    "ambiguous",  # every try was next to a decoded code
    "refine_failed",  # ... tried; refinement failed on every one (none gated)
    "gated",  # ... tried; at least one refused by the innovation gate, none accepted
    "pose_gated",  # codes tracked, but PnP with them put the body beyond POSE_GATE_M (+ per s)
    # of the predicted pose: the tracked sightings are dropped
    "pnp_failed",  # codes tracked, but PnP on the frame's codes found no pose
    "posed",  # codes tracked and a PnP pose found
    "restamped",  # no code tracked, but codes decoded with re-stamped finders posed the frame
)


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
    restamped: int = 0  # floor-code sightings decoded with re-stamped function patterns (restamp)
    frames_restamp_tried: int = 0  # frames without a first-pass pose searched for them
    frames_with_restamped: int = 0  # ... with at least one such code (outcome counts: frames_<outcome>)
    restamp_poses: int = 0  # ... whose codes gave a PnP pose precise enough to predict from
    restamp_seconds: float = 0.0  # wall time of the re-stamp decoding (within `seconds`)
    squares: int = 0  # dark squares left by failed re-stamp decodes (tracker starts, TrackStats)
    frames_backward: int = 0  # unposed frames the backward sweep looked at
    poses_backward: int = 0  # ... and posed (also in frames_tracked / poses_added)
    chunks: int = 0
    seconds: float = 0.0  # wall time of the pass (catalogue and tracking)
    skipped_reason: str = ""  # why the pass did not run ("" when it ran)
    frame_outcomes: dict[int, str] = field(default_factory=dict)  # floor stamp -> one of OUTCOMES
    restamped_keys: set[tuple[int, str]] = field(default_factory=set)  # (stamp, payload) re-stamped
    poses: dict[int, np.ndarray] = field(default_factory=dict)  # stamp -> T_world_body fed back
    # stamp -> (T_world_body, position sigma m, rotation sigma rad) fed back to ImuFit only
    weak_poses: dict[int, tuple[np.ndarray, float, float]] = field(default_factory=dict)
    fits: int = 0  # predictions from ImuFit (PosePredictor.fits)
    bridge_fits: int = 0  # ... between two first-pass poses, instead of ImuBridge (bridge_fits)

    def outcome_counts(self) -> dict[str, int]:
        """{outcome: floor frames} over OUTCOMES (frames the pass looked at)."""
        values = list(self.frame_outcomes.values())
        return {k: values.count(k) for k in OUTCOMES}

    def as_dict(self) -> dict:
        skip = ("stats", "frame_outcomes", "restamped_keys", "poses", "weak_poses")
        out: dict = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in skip}
        out.update({f"tracker_{k}": int(v) for k, v in vars(self.stats).items()})
        out.update({f"frames_{k}": n for k, n in self.outcome_counts().items()})
        out["seconds_per_frame_tried"] = self.seconds / self.frames_tried if self.frames_tried else 0.0
        return out

    def note(self) -> str:
        if self.skipped_reason:
            return f"track pass not run: {self.skipped_reason}"
        s = self.stats
        restamp = (
            f"; {self.restamped} floor-code sightings decoded with re-stamped finders in "
            f"{self.frames_with_restamped} of {self.frames_restamp_tried} unposed frames"
        )
        return (
            f"track pass: {s.tracked} floor-code sightings tracked in {self.frames_tracked} frames "
            f"({self.frames_tracked_only} with tracked codes only, {self.poses_added} new PnP poses); "
            f"{s.attempts} tried in {self.frames_tried} frames, {s.gated} refused by the innovation "
            f"gate, {s.refine_failed} not refined, {s.ambiguous} next to a decoded code"
            f"{restamp}; {self.poses_backward} of {self.frames_backward} frames posed by the backward "
            f"sweep; {s.square_corners} with a dark square's corners; {self.fits} predictions from "
            f"the IMU fit (and {self.bridge_fits} across first-pass gaps); {self.seconds:.1f} s"
        )


class ImuBridge:
    """Body poses between and beyond PnP poses from the IMU's samples (body frame B; the IMU's
    lever arm is ignored).

    Between two poses (t0, T0), (t1, T1): rotation R(t) = R0 dR(t0, t) Exp(s d), dR the gyro's
    integral (geometry.integrate_gyro), d = Log((R0 dR(t0, t1))^T R1) the end mismatch (gyro bias,
    noise) spread linearly, s = (t - t0) / (t1 - t0); position p(t) = p0 + v0 (t - t0) + D(t),
    D the double integral of the world acceleration R f + g from t0 with zero initial velocity
    (f: specific force), v0 = (p1 - p0 - D(t1)) / (t1 - t0), so both ends are met (the
    two-point boundary form of strapdown integration: Titterton & Weston, Strapdown Inertial
    Navigation Technology, 2nd ed., sec. 3.6)."""

    def __init__(self, imu):
        R_bs = np.asarray(imu.T_body_imu, float)[:3, :3]
        self.t_ns = np.asarray(imu.timestamps_ns, dtype=np.int64)
        self.gyro = np.asarray(imu.gyro_rad_s, float) @ R_bs.T
        self.force = np.asarray(imu.accel_m_s2, float) @ R_bs.T

    def covers(self, t0_ns: int, t1_ns: int) -> bool:
        return len(self.t_ns) > 1 and self.t_ns[0] <= min(t0_ns, t1_ns) and max(t0_ns, t1_ns) <= self.t_ns[-1]

    def _motion(self, t_from: int, t_to: int, R_from: np.ndarray):
        """IMU motion from t_from to t_to (either order) starting at rotation R_from:
        (grid times s relative to t_from (M,), rotations (M, 3, 3), velocity (M, 3) and
        displacement (M, 3) from zero velocity at t_from)."""
        lo, hi = min(t_from, t_to), max(t_from, t_to)
        inner = self.t_ns[(self.t_ns > lo) & (self.t_ns < hi)]
        grid = np.concatenate([[lo], inner, [hi]]).astype(np.int64)
        if t_to < t_from:
            grid = grid[::-1]
        tt = (grid - t_from) * 1e-9
        ts = (self.t_ns - t_from) * 1e-9
        rate = np.column_stack([np.interp(tt, ts, self.gyro[:, a]) for a in range(3)])
        force = np.column_stack([np.interp(tt, ts, self.force[:, a]) for a in range(3)])
        dt = np.diff(tt)
        R = R_from @ integrate_gyro(0.5 * (rate[:-1] + rate[1:]), dt)
        acc = np.einsum("nij,nj->ni", R, force) + GRAVITY_WORLD_M_S2
        vel = np.vstack([np.zeros(3), np.cumsum(0.5 * (acc[:-1] + acc[1:]) * dt[:, None], axis=0)])
        disp = np.vstack([np.zeros(3), np.cumsum(0.5 * (vel[:-1] + vel[1:]) * dt[:, None], axis=0)])
        return tt, R, vel, disp

    def bridge(
        self, t0: int, T0: np.ndarray, t1: int, T1: np.ndarray, t: int, extra=()
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(T_world_body (4, 4) at t in [t0, t1], world velocity (3,) at t0 and at t1) between
        the poses (class docstring).  `extra`: more poses [(t_ns, p_world (3,))] near the ends:
        with them a constant world-frame acceleration bias b is fitted too (p(t) gains
        -b (t - t0)^2 / 2; least squares with a zero-mean prior of ACCEL_BIAS_PRIOR_M_S2)."""
        R0 = T0[:3, :3]
        tt, R, vel, disp = self._motion(t0, t1, R0)
        span = tt[-1]
        d = so3_log(R[-1].T @ T1[:3, :3])
        s_t, R_t, _, disp_t = self._motion(t0, t, R0)
        s = s_t[-1]
        v0, b = (T1[:3, 3] - T0[:3, 3] - disp[-1]) / span, np.zeros(3)
        extra = [(int(te), np.asarray(pe, float)) for te, pe in extra if te != t0 and te != t1]
        if extra:
            rows_s, rows_y = [span], [T1[:3, 3] - T0[:3, 3] - disp[-1]]
            for side in (-1, 1):
                ends = [te for te, _ in extra if (te > t0) == (side > 0)]
                if not ends:
                    continue
                t_end = max(max(ends), t1) if side > 0 else min(ends)
                mt, _, _, md = self._motion(t0, t_end, R0)
                if side < 0:
                    mt, md = mt[::-1], md[::-1]
                for te, pe in extra:
                    if (te > t0) == (side > 0):
                        se = (te - t0) * 1e-9
                        rows_s.append(se)
                        rows_y.append(
                            pe - T0[:3, 3] - np.array([np.interp(se, mt, md[:, a]) for a in range(3)])
                        )
            sk = np.asarray(rows_s)
            # per axis: y_k = v0 s_k - b s_k^2 / 2 (noise POSE_NOISE_M), prior b ~ N(0, prior^2)
            A = np.vstack(
                [np.column_stack([sk, -0.5 * sk**2]) / POSE_NOISE_M, [[0.0, 1.0 / ACCEL_BIAS_PRIOR_M_S2]]]
            )
            Y = np.vstack([np.asarray(rows_y) / POSE_NOISE_M, np.zeros((1, 3))])
            v0, b = np.linalg.lstsq(A, Y, rcond=None)[0]
        p_t = T0[:3, 3] + v0 * s + disp_t[-1] - 0.5 * b * s * s
        T = make_T(R_t[-1] @ so3_exp((s / span) * d), p_t)
        return T, v0, v0 + vel[-1] - b * span

    def extrapolate(self, t1: int, T1: np.ndarray, v1: np.ndarray, t: int) -> np.ndarray:
        """T_world_body (4, 4) at t (before or after t1) from the pose and world velocity at t1."""
        tt, R, _, disp = self._motion(t1, t, T1[:3, :3])
        return make_T(R[-1], T1[:3, 3] + v1 * tt[-1] + disp[-1])


class ImuFit:
    """A body trajectory through the IMU's samples fitted to several poses [(t_ns, T_world_body,
    position sigma m, rotation sigma rad)] (a small batch smoother, without GTSAM):
    R(t) = Exp(d) R_a dR(t) with dR the gyro's integral from the first pose's time t_a after
    removing a constant body-frame bias b_g; p(t) = p_a +
    v_a s + D(s) - C(s) b_a, D the double integral of R f + g, C that of R (a constant
    body-frame accelerometer bias b_a), s = t - t_a.  The rotation unknowns (d, b_g) by
    Gauss-Newton on the poses' body-frame rotation residuals, with the first-order effect of the
    bias on the integral, J_k = dR_k^T sum_j dR_j dt_j (Forster et al., "On-Manifold
    Preintegration for Real-Time Visual-Inertial Odometry", IEEE T-RO 2017, eq. 44); then
    (p_a, v_a, b_a) by linear least squares with zero-mean priors on the biases; poses more than
    FIT_OUTLIER_SIGMAS residual RMS off are left out once.  `until_ns`: the trajectory is also
    integrated to this time (extrapolation)."""

    def __init__(self, imu: ImuBridge, poses: list[tuple[int, np.ndarray, float, float]], until_ns: int):
        stamps = np.array([p[0] for p in poses], dtype=np.int64)
        self.t_a = int(stamps.min())
        lo, hi = self.t_a, max(int(stamps.max()), int(until_ns))
        lo = min(lo, int(until_ns))
        inner = imu.t_ns[(imu.t_ns > lo) & (imu.t_ns < hi)]
        self.grid = np.unique(np.concatenate([[lo, hi], inner, stamps]))
        tt = (self.grid - self.t_a) * 1e-9
        ts = (imu.t_ns - self.t_a) * 1e-9
        rate = np.column_stack([np.interp(tt, ts, imu.gyro[:, a]) for a in range(3)])
        self.force = np.column_stack([np.interp(tt, ts, imu.force[:, a]) for a in range(3)])
        self.tt, self.dt = tt, np.diff(tt)
        self.w_mid = 0.5 * (rate[:-1] + rate[1:])
        self.k_anchor = int(np.searchsorted(self.grid, self.t_a))
        self._solve(poses)
        keep = self._inliers(poses)
        if not np.all(keep) and np.sum(keep) >= FIT_MIN_POSES:
            self._solve([p for p, k in zip(poses, keep) if k])
        else:
            keep[:] = True
        self.poses_used = int(keep.sum())

    def _inliers(self, poses) -> np.ndarray:
        """(K,) bool: the poses within FIT_OUTLIER_SIGMAS of the fit (whitened residual norm
        against its RMS over all, at least 1)."""
        idx = np.searchsorted(self.grid, [p[0] for p in poses])
        R_fit, p_fit = self.R[idx], self._positions(idx)
        R_k = np.stack([p[1][:3, :3] for p in poses])
        rot = np.linalg.norm(so3_log(np.einsum("nji,njk->nik", R_fit, R_k)), axis=1)
        pos = np.linalg.norm(p_fit - np.stack([p[1][:3, 3] for p in poses]), axis=1)
        r = np.hypot(rot / np.array([p[3] for p in poses]), pos / np.array([p[2] for p in poses]))
        return r <= FIT_OUTLIER_SIGMAS * max(float(np.sqrt(np.mean(r**2))), 1.0)

    def _rotations(self, b_g: np.ndarray) -> np.ndarray:
        """(M, 3, 3) gyro integral from grid[0] with the bias b_g removed, relative to t_a."""
        dR = integrate_gyro(self.w_mid - b_g, self.dt)
        return np.einsum("ij,njk->nik", dR[self.k_anchor].T, dR)

    def _solve(self, poses) -> None:
        """The fit (class docstring) to `poses`: sets b_g, R (M, 3, 3) on the grid, D, C and
        x = (p_a, v_a, b_a)."""
        idx = np.searchsorted(self.grid, [p[0] for p in poses])
        Rk = np.stack([p[1][:3, :3] for p in poses])
        sig_p = np.array([p[2] for p in poses])
        sig_r = np.array([p[3] for p in poses])
        b_g, R_a = np.zeros(3), np.asarray(poses[int(np.argmin([p[0] for p in poses]))][1][:3, :3], float)
        for _ in range(2):
            dR = self._rotations(b_g)
            # J_k: d(log residual at pose k) / d(b_g), to first order
            S = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(dR[:-1] * self.dt[:, None, None], axis=0)])
            S -= S[self.k_anchor]
            Rp = np.einsum("ij,njk->nik", R_a, dR[idx])  # (K, 3, 3) predicted at the poses
            e = so3_log(np.einsum("nji,njk->nik", Rp, Rk))  # (K, 3) body-frame residuals
            J = np.einsum("nji,njk->nik", dR[idx], S[idx])  # (K, 3, 3)
            rows = np.concatenate([-np.transpose(Rp, (0, 2, 1)), J], axis=2) / sig_r[:, None, None]
            A = np.vstack(
                [rows.reshape(-1, 6), np.hstack([np.zeros((3, 3)), np.eye(3) / FIT_GYRO_BIAS_PRIOR_RAD_S])]
            )
            y = np.concatenate([(-e / sig_r[:, None]).reshape(-1), -b_g / FIT_GYRO_BIAS_PRIOR_RAD_S])
            x = np.linalg.lstsq(A, y, rcond=None)[0]
            R_a = so3_exp(x[:3]) @ R_a
            b_g = b_g + x[3:]
        self.b_g = b_g
        self.R = np.einsum("ij,njk->nik", R_a, self._rotations(b_g))
        acc = np.einsum("nij,nj->ni", self.R, self.force) + GRAVITY_WORLD_M_S2
        self.D = self._double_integral(acc)
        self.C = self._double_integral(self.R)
        s = self.tt[idx]
        pk = np.stack([p[1][:3, 3] for p in poses])
        A = np.zeros((3 * len(poses) + 3, 9))
        y = np.zeros(3 * len(poses) + 3)
        for j, k in enumerate(idx):
            A[3 * j : 3 * j + 3, 0:3] = np.eye(3)
            A[3 * j : 3 * j + 3, 3:6] = s[j] * np.eye(3)
            A[3 * j : 3 * j + 3, 6:9] = -self.C[k]
            y[3 * j : 3 * j + 3] = pk[j] - self.D[k]
        w = np.repeat(1.0 / sig_p, 3)
        A[: 3 * len(poses)] *= w[:, None]
        y[: 3 * len(poses)] *= w
        A[3 * len(poses) :, 6:9] = np.eye(3) / ACCEL_BIAS_PRIOR_M_S2
        self.x = np.linalg.lstsq(A, y, rcond=None)[0]

    def _double_integral(self, a: np.ndarray) -> np.ndarray:
        """Trapezoidal double integral over the grid of samples a (M, ...), zero at t_a."""
        dt = self.dt.reshape((-1,) + (1,) * (a.ndim - 1))
        v = np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(0.5 * (a[:-1] + a[1:]) * dt, axis=0)])
        v -= v[self.k_anchor]
        d = np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(0.5 * (v[:-1] + v[1:]) * dt, axis=0)])
        return d - d[self.k_anchor]

    def _positions(self, k: np.ndarray) -> np.ndarray:
        """(K, 3) fitted positions at grid indices k (K,)."""
        return self.x[:3] + np.outer(self.tt[k], self.x[3:6]) + self.D[k] - self.C[k] @ self.x[6:]

    def at(self, t_ns: int) -> np.ndarray:
        """T_world_body (4, 4) at t_ns (a grid time: a pose's stamp or `until_ns`)."""
        k = int(np.clip(np.searchsorted(self.grid, int(t_ns)), 0, len(self.grid) - 1))
        return make_T(self.R[k], self._positions(np.array([k]))[0])


class PosePredictor:
    """Body poses predicted at floor-frame stamps from PnP poses (module docstring, step 2).

    `timestamps_ns` (N,) increasing and `T_world_body` (N, 4, 4): the first pass's poses;
    `add` records a pose found by the pass (stamps increasing, after every earlier `add`).
    `imu`: an ImuBridge: poses up to MAX_IMU_BRIDGE_S apart bridged by the IMU's motion, and
    extrapolation with its rotation and acceleration (None: geodesic / constant velocity)."""

    def __init__(self, timestamps_ns: np.ndarray, T_world_body: np.ndarray, imu: ImuBridge | None = None):
        self.imu = imu
        self.first_t = [int(t) for t in timestamps_ns]
        self.first_T = list(np.asarray(T_world_body, dtype=float).reshape(-1, 4, 4))
        self.added_t: list[int] = []
        self.added_T: list[np.ndarray] = []
        # poses of the pass too uncertain to predict from alone (position sigma above
        # MAX_FEEDBACK_POSITION_SIGMA_M, at most FIT_MAX_POSITION_SIGMA_M): ImuFit weighs them
        # by their sigma (position m, rotation rad)
        self.weak: dict[int, tuple[np.ndarray, float, float]] = {}
        # what the last predict() used: "own", "bridge" (first pass), "bridge_fit" (ImuFit across
        # a first-pass gap), "fit", "other"
        self.last_kind = ""
        self.fits = 0  # predictions from ImuFit
        self.bridge_fits = 0  # ... of them, between two first-pass poses (instead of ImuBridge)

    def add(self, t_ns: int, T_world_body: np.ndarray) -> None:
        k = bisect.bisect_left(self.added_t, int(t_ns))
        self.added_t.insert(k, int(t_ns))
        self.added_T.insert(k, np.asarray(T_world_body, dtype=float))

    def _before(self, t: int, k: int, added: bool = True) -> list[tuple[int, np.ndarray]]:
        """Up to k poses strictly before t, latest first (first-pass, and added ones if `added`)."""
        i = bisect.bisect_left(self.first_t, t)
        merged = [(self.first_t[m], self.first_T[m]) for m in range(max(0, i - k), i)]
        if added:
            j = bisect.bisect_left(self.added_t, t)
            merged += [(self.added_t[m], self.added_T[m]) for m in range(max(0, j - k), j)]
        merged.sort(key=lambda p: p[0], reverse=True)
        out: list[tuple[int, np.ndarray]] = []
        for p in merged:  # one pose per stamp: the first pass's (listed first; the sort is stable)
            if not out or out[-1][0] != p[0]:
                out.append(p)
        return out[:k]

    def _after(self, t: int, k: int, added: bool = True) -> list[tuple[int, np.ndarray]]:
        """Up to k poses strictly after t, earliest first (first-pass, and added ones if `added`:
        the backward sweep adds poses after the frames it has still to predict)."""
        i = bisect.bisect_right(self.first_t, t)
        merged = [(self.first_t[m], self.first_T[m]) for m in range(i, min(len(self.first_t), i + k))]
        if added:
            j = bisect.bisect_right(self.added_t, t)
            merged += [(self.added_t[m], self.added_T[m]) for m in range(j, min(len(self.added_t), j + k))]
        merged.sort(key=lambda p: p[0])  # stable: the first pass's pose first at a shared stamp
        out: list[tuple[int, np.ndarray]] = []
        for p in merged:  # one pose per stamp, as in _before
            if not out or out[-1][0] != p[0]:
                out.append(p)
        return out[:k]

    def has_first_pose(self, t_ns: int) -> bool:
        i = bisect.bisect_left(self.first_t, int(t_ns))
        return i < len(self.first_t) and self.first_t[i] == int(t_ns)

    def predict(self, t_ns: int) -> tuple[np.ndarray, float] | None:
        """(T_world_body (4, 4), seconds to the nearest pose used) at t_ns, or None.

        The first pass's poses first: where the IMU bridges two of them, that bridge.  Else the
        nearer (in time) of that prediction and the one that also uses the poses added by the
        pass: those come from tracked codes and can be a few cm off within the pose gate, and
        as bridge ends they put the codes of the next frames 5-14 px off where the first
        pass's bridge was within ~1 px (20 ms-exposure flight, seed 0: BENCHMARKS.md, seventh session)."""
        t = int(t_ns)
        i = bisect.bisect_left(self.first_t, t)
        if i < len(self.first_t) and self.first_t[i] == t:
            self.last_kind = "own"
            return self.first_T[i], 0.0
        first = self._predict(t, self._before(t, 8, False), self._after(t, 8, False))
        if first is not None and first[2] == "bridge":
            self.last_kind = "bridge"
            if self.imu is not None and USE_FIT and USE_BRIDGE_FIT:
                fitted = self._predict_bridge_fit(t)
                if fitted is not None:
                    self.last_kind = "bridge_fit"
                    self.bridge_fits += 1
                    return fitted
            return first[0], first[1]
        if self.imu is not None and USE_FIT:
            fitted = self._predict_fit(t)
            if fitted is not None:
                self.last_kind = "fit"
                self.fits += 1
                return fitted
        self.last_kind = "other"
        cands = [first] if first is not None else []
        if self.added_t:
            with_added = self._predict(t, self._before(t, 8), self._after(t, 8))
            if with_added is not None:
                cands.append(with_added)
        if not cands:
            return None
        best = min(cands, key=lambda p: p[1])
        return best[0], best[1]

    def add_weak(self, t_ns: int, T_world_body: np.ndarray, sigma_m: float, sigma_rad: float) -> None:
        """A pose of the pass for ImuFit only (`weak`), its position and rotation sigmas."""
        self.weak[int(t_ns)] = (np.asarray(T_world_body, float), float(sigma_m), float(sigma_rad))

    def _window(
        self, lo: int, hi: int, first_only: bool = False
    ) -> list[tuple[int, np.ndarray, float, float]]:
        """Every pose with lo <= t <= hi, one per stamp (first pass, else added, else weak; only
        the first pass's with `first_only`), in time order, with its sigmas (position m,
        rotation rad: POSE_NOISE_M and FIT_ROTATION_NOISE_RAD but for the weak ones' own, when
        larger)."""
        out: dict[int, tuple[np.ndarray, float, float]] = {
            t: (T, max(sp, POSE_NOISE_M), max(sr, FIT_ROTATION_NOISE_RAD))
            for t, (T, sp, sr) in self.weak.items()
            if lo <= t <= hi and not first_only
        }
        sources = [(self.first_t, self.first_T)]  # listed last: the first pass's pose wins
        if not first_only:
            sources.insert(0, (self.added_t, self.added_T))
        for ts, Ts in sources:
            for m in range(bisect.bisect_left(ts, lo), bisect.bisect_right(ts, hi)):
                out[ts[m]] = (Ts[m], POSE_NOISE_M, FIT_ROTATION_NOISE_RAD)  # the first pass's last
        return [(t, *out[t]) for t in sorted(out)]

    def _predict_fit(self, t: int) -> tuple[np.ndarray, float] | None:
        """(T_world_body, seconds to the nearest pose) at t from ImuFit (FIT_* constants) over
        the poses within FIT_WINDOW_S of the nearest pose before t and of the nearest after it
        (both sides when those two are at most MAX_IMU_BRIDGE_S apart, else the nearer side),
        or None."""
        before, after = self._nearest_any(t, -1), self._nearest_any(t, 1)
        sides = []
        if before and (t - before[0][0]) * 1e-9 <= FIT_MAX_EXTRAPOLATION_S:
            sides.append(("before", before[0][0]))
        if after and (after[0][0] - t) * 1e-9 <= FIT_MAX_EXTRAPOLATION_S:
            sides.append(("after", after[0][0]))
        if not sides:
            return None
        window = int(FIT_WINDOW_S * 1e9)
        if len(sides) == 2 and before and after and (after[0][0] - before[0][0]) * 1e-9 <= MAX_IMU_BRIDGE_S:
            poses = self._window(before[0][0] - window, before[0][0]) + self._window(
                after[0][0], after[0][0] + window
            )
        else:
            side, t_near = min(sides, key=lambda p: abs(p[1] - t))
            if side == "before":
                poses = self._window(t_near - window, t_near)
            else:
                poses = self._window(t_near, t_near + window)
        T = self._fit_at(poses, t, FIT_MIN_SPAN_S)
        return None if T is None else (T, min(abs(t - p[0]) for p in poses) * 1e-9)

    def _predict_bridge_fit(self, t: int) -> tuple[np.ndarray, float] | None:
        """(T_world_body, seconds to the nearer end) at t between the first pass's poses that
        the IMU bridges (ImuBridge), from ImuFit over the first pass's poses within FIT_WINDOW_S
        outside both ends of the gap (the pass's own poses left out, as in the bridge), or None
        (too few poses: the bridge is used)."""
        (t0, _), (t1, _) = self._before(t, 1, False)[0], self._after(t, 1, False)[0]
        window = int(FIT_WINDOW_S * 1e9)
        poses = self._window(t0 - window, t0, True) + self._window(t1, t1 + window, True)
        T = self._fit_at(poses, t)  # (t lies between t0 and t1, inside the poses' span)
        return None if T is None else (T, min(t - t0, t1 - t) * 1e-9)

    def _fit_at(
        self, poses: list[tuple[int, np.ndarray, float, float]], t: int, min_span_s: float = 0.0
    ) -> np.ndarray | None:
        """T_world_body at t of an ImuFit over `poses` (time order), or None: fewer than
        FIT_MIN_POSES poses given or kept by the fit, a span under `min_span_s`, or the IMU not
        covering the poses and t."""
        imu = self.imu
        assert imu is not None
        if len(poses) < FIT_MIN_POSES or (poses[-1][0] - poses[0][0]) * 1e-9 < min_span_s:
            return None
        if not imu.covers(min(poses[0][0], t), max(poses[-1][0], t)):
            return None
        fit = ImuFit(imu, poses, t)
        return fit.at(t) if fit.poses_used >= FIT_MIN_POSES else None

    def _nearest_any(self, t: int, side: int) -> list[tuple[int, np.ndarray]]:
        """[(stamp, T)] of the nearest pose (first pass, added or weak) strictly before (side -1)
        or after (side 1) t, or []."""
        near = self._before(t, 1) if side < 0 else self._after(t, 1)
        weak = [w for w in self.weak if (w < t if side < 0 else w > t)]
        if weak:
            w = max(weak) if side < 0 else min(weak)
            if not near or abs(w - t) < abs(near[0][0] - t):
                near = [(w, self.weak[w][0])]
        return near

    def _predict(self, t: int, before, after) -> tuple[np.ndarray, float, str] | None:
        """(T_world_body, horizon s, "bridge" / "other") from the poses `before` (latest first)
        and `after` (earliest first) t (module docstring, step 2)."""
        if self.imu is not None:
            pred = self._predict_imu(t, before, after)
            if pred is not None:
                return pred
        if before and after and (after[0][0] - before[0][0]) * 1e-9 <= MAX_INTERPOLATION_GAP_S:
            (t0, T0), (t1, T1) = before[0], after[0]
            a = (t - t0) / (t1 - t0)
            return interpolate_pose(T0, T1, a), min(t - t0, t1 - t) * 1e-9, "other"
        ahead = _extrapolate(before, t)  # forward from the past
        behind = _extrapolate(after, t)  # backward from the future
        cands = [p for p in (ahead, behind) if p is not None]
        if not cands:
            return None
        best = min(cands, key=lambda p: p[1])
        return best[0], best[1], "other"

    def _predict_imu(self, t: int, before, after) -> tuple[np.ndarray, float, str] | None:
        """_predict with the IMU (class docstring), None where it does not apply."""
        imu = self.imu
        assert imu is not None
        if before and after:
            (t0, T0), (t1, T1) = before[0], after[0]
            if (t1 - t0) * 1e-9 <= MAX_IMU_BRIDGE_S and imu.covers(t0, t1):
                extra = [
                    (te, Te[:3, 3])
                    for te, Te in before[1:] + after[1:]
                    if min(abs(te - t0), abs(te - t1)) * 1e-9 <= BIAS_WINDOW_S
                    and imu.covers(min(te, t0), max(te, t1))
                ]
                T = imu.bridge(t0, T0, t1, T1, t, extra)[0]
                return T, min(t - t0, t1 - t) * 1e-9, "bridge"
        cands = []
        for near, far in ((before, True), (after, False)):
            if not near or abs(t - near[0][0]) * 1e-9 > MAX_EXTRAPOLATION_S:
                continue
            t1, T1 = near[0]
            older = [p for p in near[1:] if VELOCITY_BASELINE_S <= abs(t1 - p[0]) * 1e-9 <= MAX_IMU_BRIDGE_S]
            if not older or not imu.covers(older[0][0], t):
                continue
            t0, T0 = older[0]
            if far:  # the velocity at t1 from the bridge (t0, t1), t0 < t1 < t
                v1 = imu.bridge(t0, T0, t1, T1, t1)[2]
            else:  # t < t1 < t0: the velocity at t1 from the bridge (t1, t0)
                v1 = imu.bridge(t1, T1, t0, T0, t1)[1]
            cands.append((imu.extrapolate(t1, T1, v1, t), abs(t - t1) * 1e-9, "other"))
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


def _track_chunk(context, task: list[int]):
    """The pass over the floor frames `task` (indices, in the order given: increasing for the
    forward sweep, decreasing for the backward one): (tracked detections, TrackReport)."""
    stream, camera, world, catalogue, first_t, first_T, decoded, corner_sigma_px, imu, squares, seed = context
    predictor = PosePredictor(first_t, first_T, imu)
    strong, weak = seed
    for t_seed in sorted(strong):  # the forward sweep's poses, for the backward one
        predictor.add(t_seed, strong[t_seed])
    for t_seed, (T_seed, sp, sr) in weak.items():
        predictor.add_weak(t_seed, T_seed, sp, sr)
    tracker = CodeTracker(camera, crossings_pass=TRACK_CROSSINGS_PASS)
    rep = TrackReport()
    out: list[QRDetection] = []
    h, w = camera.height, camera.width
    for i in task:
        t = int(stream.timestamps_ns[i])
        pred = predictor.predict(t)
        if pred is None:
            rep.frame_outcomes[t] = "no_prediction"
            continue
        rep.frames_predicted += 1
        T_body, horizon_s = pred
        T_cam_world = inv_T(camera.T_world_cam(T_body))
        frame_dets = decoded.get(t, [])
        seen = {d.payload for d in frame_dets}
        sigma = PREDICTION_SIGMA_PX + PREDICTION_SIGMA_PX_PER_S * horizon_s
        predicted = {}
        small = False
        for payload, code in catalogue.items():
            if payload in seen:
                continue
            p_cam = transform_points(T_cam_world, code.corners_world)
            if np.any(p_cam[:, 2] <= 0):
                continue
            uv = camera.project(p_cam)
            side_px = float(np.mean(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1)))
            if not symbol_in_view(uv, code.modules, (h, w)):
                continue
            if side_px >= TRACK_MIN_MODULE_PX * code.modules:
                predicted[payload] = (uv, sigma, code.modules)
            else:
                small = True
        if not predicted:
            rep.frame_outcomes[t] = "too_small" if small else "none_in_view"
            continue
        image = stream.load_image(i)
        if image is None:
            rep.frame_outcomes[t] = "no_image"
            continue
        rep.frames_tried += 1
        before = TrackStats(**vars(tracker.stats))
        tracked = tracker.step(
            image,
            FLOOR,
            t,
            frame_dets,
            [None] * len(frame_dets),
            predicted,
            own_motion=False,
            squares=squares.get(t),
            locate=TRACK_LOCATE_TWO_SIDED or predictor.last_kind != "bridge_fit",
        )
        if not tracked:
            if tracker.stats.gated > before.gated:
                rep.frame_outcomes[t] = "gated"
            elif tracker.stats.refine_failed > before.refine_failed:
                rep.frame_outcomes[t] = "refine_failed"
            else:
                rep.frame_outcomes[t] = "ambiguous"
            continue
        if predictor.last_kind == "other":
            gate_m = POSE_GATE_M + POSE_GATE_M_PER_S * horizon_s
        else:  # the frame's own first-pass pose, a first-pass IMU bridge or an IMU fit
            gate_m = POSE_GATE_BRIDGE_M + POSE_GATE_BRIDGE_M_PER_S * horizon_s
        kept = list(tracked)
        while True:
            floor = classify(frame_dets + kept, world).floor
            res = estimate_floor_pose(floor, camera, corner_sigma_px) if floor else None
            outside = res is not None and np.linalg.norm(res.T_world_body[:3, 3] - T_body[:3, 3]) > gate_m
            if not outside or len(kept) <= 1:
                break
            # several tracked codes: the one furthest from its prediction left out, solved again
            kept.remove(max(kept, key=_innovation_px))
        if outside:
            kept = []
        tracker.stats.tracked -= len(tracked) - len(kept)
        tracker.stats.pose_gated += len(tracked) - len(kept)
        if outside:
            rep.frame_outcomes[t] = "pose_gated"  # the tracked codes disagree with the prediction
            continue
        tracked = kept
        out.extend(tracked)
        rep.frames_tracked += 1
        rep.frames_tracked_only += not frame_dets
        if res is None:
            rep.frame_outcomes[t] = "pnp_failed"
            continue
        rep.frame_outcomes[t] = "posed"
        rep.poses_added += not predictor.has_first_pose(t)
        position_var = np.diag(np.asarray(res.covariance).reshape(POSE_DOF, POSE_DOF))[3:]
        sigma_p = float(np.sqrt(np.max(position_var)))
        if sigma_p <= MAX_FEEDBACK_POSITION_SIGMA_M:
            predictor.add(t, res.T_world_body)
            rep.poses[t] = res.T_world_body
        else:
            # for ImuFit: the pose with the tracked corners' own (refinement) covariance, not
            # inflated by their disagreement with a prediction that ImuFit replaces
            floor = classify(frame_dets + [_refinement_only(d) for d in tracked], world).floor
            weak = estimate_floor_pose(floor, camera, corner_sigma_px)
            if weak is not None:
                cov = np.diag(np.asarray(weak.covariance).reshape(POSE_DOF, POSE_DOF))
                sigma_p, sigma_r = float(np.sqrt(np.max(cov[3:]))), float(np.sqrt(np.max(cov[:3])))
                if sigma_p <= FIT_MAX_POSITION_SIGMA_M:
                    predictor.add_weak(t, weak.T_world_body, sigma_p, sigma_r)
                    rep.weak_poses[t] = (weak.T_world_body, sigma_p, sigma_r)
    rep.fits += predictor.fits
    rep.bridge_fits += predictor.bridge_fits
    rep.stats = tracker.stats
    return out, rep


def _refinement_only(d: QRDetection) -> QRDetection:
    """A tracked sighting with the covariance refinement gave it: CodeTracker.step added
    max(0, |e|^2 / 8 - TRACK_AGREEMENT_SIGMA_PX^2) I, e = corners_px - corners_raw_px (the
    prediction), to it; that part is taken off again."""
    if d.corner_cov_px2 is None:
        return d
    e = (np.asarray(d.corners_px, float) - np.asarray(d.corners_raw_px, float)).reshape(8)
    excess = max(0.0, float(e @ e) / 8 - TRACK_AGREEMENT_SIGMA_PX**2)
    cov = np.asarray(d.corner_cov_px2, float) - excess * np.eye(8)
    return replace(d, corner_cov_px2=cov, corner_sigma_px=float(np.sqrt(np.mean(np.diag(cov)))))


def _innovation_px(d: QRDetection) -> float:
    """A tracked sighting's largest corner distance from its prediction (corners_raw_px), px."""
    return float(np.max(np.linalg.norm(d.corners_px - d.corners_raw_px, axis=1)))


RESTAMP_CHUNK_FRAMES = 64  # frames per task of the re-stamp decoding


def _restamp_chunk(
    context, task: list[int]
) -> tuple[list[QRDetection], dict[str, int], dict[int, list[np.ndarray]]]:
    """Codes decoded with re-stamped function patterns (fusion.qr.restamp) in the floor frames
    `task` (indices), away from the frame's decoded codes: (their QRDetections, tracked=True,
    corners refined from the fitted quadrilateral with refinement's self-check, else the
    quadrilateral with RAW_CORNER_SIGMA_PX; {payload: modules per side}; {stamp: the dark
    squares that did not decode (4, 2) px}, for the tracker)."""
    stream, camera, decoded = context
    out: list[QRDetection] = []
    modules: dict[str, int] = {}
    squares: dict[int, list[np.ndarray]] = {}
    for i in task:
        t = int(stream.timestamps_ns[i])
        image = stream.load_image(i)
        if image is None:
            continue
        frame = decoded.get(t, [])
        seen = {d.payload for d in frame}
        found = []
        got, failed = restamp_candidates(image, [d.corners_px for d in frame])
        if failed:
            squares[t] = failed
        for f in got:
            if f.payload not in seen:
                seen.add(f.payload)
                found.append(f)
        if not found:
            continue
        refined = refine_frames([image], [[(f.corners_px, f.modules) for f in found]], camera)[0]
        for f, res in zip(found, refined):
            if res is None:
                corners, sigma = f.corners_px, RAW_CORNER_SIGMA_PX
                cov = RAW_CORNER_SIGMA_PX**2 * np.eye(8)
            else:
                corners, sigma = res.corners_px, res.corner_sigma_px
                cov = res.corner_cov_px2 if res.corner_cov_px2 is not None else sigma**2 * np.eye(8)
            det = QRDetection(FLOOR, t, f.payload, corners, f.corners_px, float(sigma), cov, tracked=True)
            out.append(det)
            modules[f.payload] = f.modules
    return out, modules, squares


def restamp_flight(
    stream, camera: CameraModel, world: World, decoded: dict, first_t, corner_sigma_px: float, workers: int
) -> tuple[list[QRDetection], dict[str, CatalogueCode], dict[int, np.ndarray], int, dict]:
    """Floor codes decoded with re-stamped function patterns in the floor frames without a
    first-pass pose (fusion.qr.restamp: finders hidden by an occluder; the identity is decoded,
    never predicted): (their detections, the floor codes among them for the catalogue, {stamp:
    T_world_body} of the frames they give a PnP pose with position sigma at most
    MAX_FEEDBACK_POSITION_SIGMA_M, frames searched, {stamp: dark squares (4, 2) px that did not
    decode}).  `decoded`: stamp -> decoded detections."""
    posed = set(int(t) for t in first_t)
    todo = [i for i in range(len(stream)) if int(stream.timestamps_ns[i]) not in posed]
    tasks = [todo[k : k + RESTAMP_CHUNK_FRAMES] for k in range(0, len(todo), RESTAMP_CHUNK_FRAMES)]
    found: list[QRDetection] = []
    modules: dict[str, int] = {}
    squares: dict[int, list[np.ndarray]] = {}
    for dets, mods, sq in parallel_map(
        _restamp_chunk,
        tasks,
        max(1, min(workers, len(tasks))),
        (stream, camera, decoded),
        preload=["fusion.qr.predict"],
    ):
        found.extend(dets)
        modules.update(mods)
        squares.update(sq)
    by_t: dict[int, list[QRDetection]] = {}
    for d in found:
        by_t.setdefault(d.timestamp_ns, []).append(d)
    kept: list[QRDetection] = []
    catalogue: dict[str, CatalogueCode] = {}
    poses: dict[int, np.ndarray] = {}
    for t, dets in sorted(by_t.items()):
        floor = classify(decoded.get(t, []) + dets, world).floor
        new = [s for s in floor if s.detection.tracked]
        if not new:
            continue
        kept += [s.detection for s in new]
        for s in new:
            p = s.detection.payload
            catalogue.setdefault(p, CatalogueCode(s.corners_world, modules[p]))
        res = estimate_floor_pose(floor, camera, corner_sigma_px)
        if res is None:
            continue
        position_var = np.diag(np.asarray(res.covariance).reshape(POSE_DOF, POSE_DOF))[3:]
        if float(np.sqrt(np.max(position_var))) <= MAX_FEEDBACK_POSITION_SIGMA_M:
            poses[t] = res.T_world_body
    return kept, catalogue, poses, len(todo), squares


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
    frames_with_code and detections counted), and what the pass did.  First, in the floor frames
    without a PnP pose, codes whose finder patterns are hidden are decoded by re-stamping them
    (restamp_flight): they join the catalogue and their poses the first pass's."""
    t0 = time.perf_counter()
    rep = TrackReport()
    stream = log.floor
    camera: CameraModel = stream.camera
    if camera.rolling_shutter:
        rep.skipped_reason = "rolling-shutter floor camera (predictions are global-shutter projections)"
        return det, rep
    catalogue, rep.no_modules = floor_catalogue(det, log.world, stream, backend)
    decoded = {t: [d for d in ds if not d.tracked] for t, ds in det.by_frame(FLOOR).items()}
    first_t = np.asarray(traj_pnp.timestamps_ns, dtype=np.int64)
    first_T = np.asarray(traj_pnp.T_world_body, dtype=float).reshape(-1, 4, 4)
    restamped, extra, poses, rep.frames_restamp_tried, squares = restamp_flight(
        stream, camera, log.world, decoded, first_t, corner_sigma_px, workers
    )
    rep.squares = sum(len(v) for v in squares.values())
    rep.restamp_seconds = time.perf_counter() - t0
    rep.restamped = len(restamped)
    rep.restamped_keys = {(d.timestamp_ns, d.payload) for d in restamped}
    rep.restamp_poses = len(poses)
    for d in restamped:
        decoded.setdefault(d.timestamp_ns, []).append(d)
    rep.frames_with_restamped = len({d.timestamp_ns for d in restamped})
    for p, code in extra.items():
        catalogue.setdefault(p, code)
    if poses:
        first_t = np.concatenate([first_t, np.fromiter(poses, dtype=np.int64)])
        first_T = np.concatenate([first_T, np.stack(list(poses.values()))])
        order = np.argsort(first_t, kind="stable")
        first_t, first_T = first_t[order], first_T[order]
    rep.catalogue = len(catalogue)
    if not catalogue or len(first_t) == 0:
        rep.skipped_reason = "no floor code decoded and posed in this flight"
        return with_tracked(det, restamped, rep), rep
    chunks = track_chunks(first_t, stream.timestamps_ns, len(stream))
    imu = getattr(log, "imu", None)
    bridge = ImuBridge(imu) if imu is not None and len(imu.timestamps_ns) > 1 else None
    context: tuple = (
        stream,
        camera,
        log.world,
        catalogue,
        first_t,
        first_T,
        decoded,
        corner_sigma_px,
        bridge,
        squares,
        ({}, {}),
    )
    forward = [list(range(a, b)) for a, b in chunks]
    tracked = _run_sweep(forward, context, workers, rep)
    # the backward sweep: the frames the forward one left without a tracked sighting, latest
    # first, predicted from the first pass's poses and the forward sweep's (a code followed back
    # from the next decode, where the forward chain broke or a gap exceeds the IMU bridge)
    done = set(int(t) for t in first_t) | set(rep.poses)
    kept_outcomes = ("posed", "pnp_failed")  # frames with tracked sightings already
    stamps = stream.timestamps_ns
    backward = [
        [i for i in reversed(range(a, b)) if _needs_backward(int(stamps[i]), done, rep, kept_outcomes)]
        for a, b in chunks
    ]
    backward = [task for task in backward if task]
    before = dict(rep.frame_outcomes)
    back = TrackReport()
    tracked += _run_sweep(backward, context[:-1] + ((dict(rep.poses), dict(rep.weak_poses)),), workers, back)
    rep.frames_backward = sum(len(task) for task in backward)
    for t, outcome in back.frame_outcomes.items():
        if outcome in kept_outcomes or t not in before:
            rep.frame_outcomes[t] = outcome
    rep.poses_backward = sum(o == "posed" for o in back.frame_outcomes.values())
    for k, v in vars(back.stats).items():
        setattr(rep.stats, k, getattr(rep.stats, k) + v)
    summed = ("frames_tried", "frames_tracked", "frames_tracked_only", "poses_added", "fits", "bridge_fits")
    for name in summed:
        setattr(rep, name, getattr(rep, name) + getattr(back, name))
    for t in poses:
        if rep.frame_outcomes.get(t) != "posed":
            rep.frame_outcomes[t] = "restamped"
    rep.chunks = len(chunks)
    rep.seconds = time.perf_counter() - t0
    logger.info(rep.note())
    return with_tracked(det, tracked + restamped, rep), rep


def _needs_backward(t: int, posed: set[int], rep: TrackReport, kept_outcomes: tuple[str, ...]) -> bool:
    """A floor frame the backward sweep looks at: no pose (first pass, re-stamped or forward
    sweep) and no tracked sighting from the forward sweep."""
    return t not in posed and rep.frame_outcomes.get(t) not in kept_outcomes


def _run_sweep(tasks: list[list[int]], context, workers: int, rep: TrackReport) -> list[QRDetection]:
    """_track_chunk over `tasks` (frame index lists), its counters and outcomes summed into `rep`
    (poses fed back too): the tracked detections."""
    tracked: list[QRDetection] = []
    for chunk_dets, chunk_rep in parallel_map(
        _track_chunk, tasks, max(1, min(workers, len(tasks))), context, preload=["fusion.qr.predict"]
    ):
        tracked.extend(chunk_dets)
        rep.frame_outcomes.update(chunk_rep.frame_outcomes)
        rep.poses.update(chunk_rep.poses)
        rep.weak_poses.update(chunk_rep.weak_poses)
        rep.fits += chunk_rep.fits
        rep.bridge_fits += chunk_rep.bridge_fits
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
    return tracked


def with_tracked(det: DetectionResult, tracked: list[QRDetection], rep: TrackReport) -> DetectionResult:
    """`det` with the floor camera's `tracked` detections (tracked and re-stamped) merged in time
    order and counted."""
    if not tracked:
        return det
    stats = {k: CameraStats(**vars(v)) for k, v in det.stats.items()}
    st = stats.setdefault(FLOOR, CameraStats())
    with_decoded = {d.timestamp_ns for d in det.detections if d.camera == FLOOR and not d.tracked}
    only = len({d.timestamp_ns for d in tracked} - with_decoded)
    st.tracked += len(tracked)
    st.detections += len(tracked)
    st.frames_with_tracked_only += only
    st.frames_with_code += only
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
