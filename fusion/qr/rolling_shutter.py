"""Rolling shutter: corners timed per row, moved to the image stamp; the readout time estimated.

A rolling-shutter camera (CameraModel.line_delay_s > 0) exposes row v at
t = t_stamp + dt(v), dt(v) = line_delay_s (v - v_stamp) (`CameraModel.row_time_offset_s`).
The body moves during the readout, so a frame's corners are not one pinhole view.  Here each
corner is moved to where a global-shutter camera at the stamp would have seen it, once, where the
corners are formed; PnP, the tight corner factors and the load observations then need no change:

1. body motion over the readout: at the stamp, body rate omega (the gyro's mean over the
   readout minus its bias, or the PnP poses' rotation rate without IMU) and a local quadratic fit
   of the PnP positions around the stamp (velocity v_world, acceleration a_world):
   T_world_body(t + dt) = [R exp(omega dt + dr),  p + v dt + a dt^2 / 2 + dp]
   (geometry.so3_exp_stack), dr and dp the IMU's rotation and displacement within the readout
   beyond the constant-rate and constant-acceleration parts (zero without IMU: a constant
   twist); a multirotor's rate changes within a 20-30 ms readout as it tilts (`_body_poses_at`);
2. each corner's point: its ray at its row's camera pose (`camera.T_world_cam`, mount-aware),
   at the depth of the floor code's known world corner (floor codes) or of the code's apparent
   size (load codes: f side / edge length);
3. that point projected with the stamp's camera pose: the corrected corner.  Its covariance is
   kept: an error dv, dw of the motion moves a corner at row time dt by the image of dt (dv, dw),
   the same for all codes of a frame, i.e. about a pose error of dt dv (0.15 mm for 15 ms and
   0.01 m/s) -- far below PnP's own (~1 mm at 1.5 m).  Adding it per code to the (8, 8) corner
   covariance would model it as independent between codes and cost PnP 2-3x its accuracy
   (measured), so it is left out.

`correct_flight` runs PnP on the raw corners, then CORRECTION_PASSES times: motion from the
last poses, corners corrected, PnP again (the poses' RS bias only enters the depths and the
velocity fit, so one pass leaves a second-order error).  Given the images, the floor camera's
floor codes are then refined again (`refine_at_stamp`): the finder edge points that
fusion.qr.refine finds in the image as read are moved to the stamp time (steps 1-3, exactly on
the code's plane) before its homography fit, so the fit is of a global-shutter view.  Moving
the refined corners afterwards is not enough: the readout bends a code's edges (the rate changes
over the rows), no homography fits the sheared code, and its extrapolated corner errs most
(2 m/s, 20 ms: refined corners 0.020 / 0.026 / 0.073 / 0.025 px TL / TR / BR / BL against the
true per-row projection, global shutter 0.010 / 0.010 / 0.031 / 0.010; refined at the stamp
0.018 / 0.017 / 0.035 / 0.019 px against the true stamp projection; BENCHMARKS.md).  The
motion is then taken again from the PnP poses of the codes refined at the stamp, and they are
refined at the stamp again with it (STAMP_MOTION_PASSES): where corrections reach 15-25 px (a
1.7 rad/s turn at 1 m/s, 30 ms) the refined-then-moved corners give poses 10-20 mm off, whose
velocity fit errs by up to 0.1 m/s, and that left the corrected corners up to 1.1 px off (exact
per-row poses: 0.03 px).  Kalibr
(Oth et al., "Rolling Shutter Camera Calibration", CVPR 2013) models the motion over the readout
with a continuous-time spline; the IMU's samples play its part here.

`calibrate_readout`: the readout time minimising the whitened PnP reprojection cost of the
flight's moving frames (golden-section search, Kiefer 1953), its sigma from the profile's
curvature, sigma^2 = 2 / cost'' (cost = chi^2 = -2 log L), scaled by chi^2_min / dof when the
corners scatter more than their covariance says.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import binomtest

from fusion.camera import CameraModel
from fusion.conventions import GRAVITY_M_S2
from fusion.errors import EstimationError, LogError
from fusion.geometry import interpolate_poses, inv_T, rot_z, se3_log, so3_exp_stack, so3_log, yaw_of
from fusion.qr.codes import classify
from fusion.qr.pnp import (
    DEFAULT_CORNER_SIGMA_PX,
    LoadFrame,
    estimate_floor_poses,
    estimate_load_observations_frames,
    floor_whitening,
    pnp_trajectory,
)
from fusion.qr.refine import POLISHED_CAMERAS, refine_frames
from fusion.types import LoadObservation, QRDetection, Trajectory
from fusion.world import FloorLayout, Placement, World

log_ = logging.getLogger(__name__)

CORRECTION_PASSES = 4
"""PnP -> motion -> corrected corners rounds of `correct_flight` after the first PnP."""
MAX_HOMOGRAPHY_CONDITION = 1e10
"""`code_corner_points` refuses a code whose 4-point homography system is worse conditioned
(three corners on a line, coincident corners; a 12 px code reads ~230)."""
LOAD_PLANE_PASSES = 2
"""Rounds of `correct_frames` that place a load code's corners from the homography of its
corners moved to the stamp (`CornerBatch.placed_by`; the first move at the depth of its size
as read, stretched by the readout)."""
FIT_HALF_WINDOW = 8
"""Poses each side of a stamp in the local quadratic fit of the position (velocity)."""
FIT_MAX_SPAN_S = 0.5
"""Poses further than this from the stamp are left out of the fit."""
MIN_FIT_POSES = 3
FIT_DEGREE = 2
"""Degree of the local polynomial fit of the positions (2: velocity and acceleration)."""
FIT_ROBUST_ROUNDS = 3
FIT_TRIM_MAD = 3.0
FIT_TRIM_MIN_M = 0.003
"""Trimmed fit: poses further than FIT_TRIM_MAD robust sigmas (at least FIT_TRIM_MIN_M) from the
fit are left out, up to FIT_ROBUST_ROUNDS times."""
"""Fewer poses in the window: no velocity (the frame's corners are not corrected)."""
MIN_VELOCITY_SIGMA_M_S = 0.003
"""Floor under the velocity fit's own standard deviation (its residuals are correlated, so the
fit's own sigma is optimistic: 0.85 mm/s predicted against 2.75 mm/s measured at 2 m/s)."""
MOTION_STEP = 1e-3
"""Central-difference step of `motion_pose_covariance` (rad/s, m/s)."""
DEFORMATION_SIGMA_FRACTION = 0.02
"""Corner sigma added per px of a code's readout deformation (`apply_corners`).  Measured on
scripts/bench_rolling_shutter.py's 2 m/s, 20 ms flight: the refined corners' chi^2 / 8 against
the true rolling-shutter corners 6.1 (mean) / 1.7 (median) without it, 0.81 / 0.62 with it
(global shutter: 0.68 / 0.58)."""
CORRECTION_SIGMA_PER_PX2 = 1.0 / 6600.0
"""Corner error (px) per px^2 of a frame's correction (its corners' mean displacement from where
they were read to the stamp): what the correction of a large readout motion leaves, modelled as
an error of the motion's scale (`correction_scale_sigma`, `motion_pose_covariance`).  Measured
on scripts/bench_rolling_shutter.py's 1 m/s, 30 ms flight against the true stamp projection, in
its last 0.5 s (a 1.3-1.8 rad/s yaw turn, corrections of 15-26 px): 0.065 px RMS beyond the
global-shutter corners' own error, about m^2 / 6600, with the motion taken again from the codes
refined at the stamp (STAMP_MOTION_PASSES).  Before that pass it was m^2 / 600 (0.04 / 0.17 /
0.49 / 1.12 px for corrections of 6.5 / 12.8 / 19.5 / 25.3 px), and without this term those
frames' PnP poses (3-9 mm off, NEES 100-36000) pulled the camera-IMU time offset profile to
-0.67 ms on a flight with no offset (fusion.estimate.timeoffset)."""
FIT_HALF_WINDOW_IMU = 15
FIT_MAX_SPAN_IMU_S = 0.6
"""With an IMU the fit window is wider: the IMU carries the motion's short-term part."""
BIAS_MAX_GAP_S = 0.1
"""Gyro bias: only consecutive poses at most this far apart give a rotation rate."""
ATTITUDE_GAP_FRAMES = 1.5
"""The IMU track's attitude between consecutive poses further apart than this many median pose
spacings (a frame or more without a pose) comes from the gyro (`_gyro_attitude_in_gaps`)."""
TILT_ACCEL_HALF_WINDOW_S = 0.15
"""`_body_tilt_from_imu`: the world acceleration at a level pose from a quadratic fit of the
positions within this of it, the accelerometer averaged over TILT_ACCEL_AVERAGE_S around it."""
TILT_ACCEL_AVERAGE_S = 0.05
TILT_SMOOTH_HALF_WINDOW_S = 0.5
"""`_body_tilt_from_imu`: each pose's body "up" the mean of the single-pose estimates within this
of it, carried to it by the gyro (the accelerometer's and the fit's noise averaged down)."""
OMEGA_BIAS_PRIOR_RAD_S = 0.005
"""Gyro bias sigma when it cannot be estimated (too few poses)."""
OMEGA_POSE_SIGMA_RAD_S = 0.02
"""Body-rate sigma when it comes from pose differences (no IMU)."""
MAX_CALIBRATION_FRAMES = 300
"""`calibrate_readout` uses at most this many frames: those whose image moves most."""
CALIBRATION_ROUNDS = 3
"""`calibrate_readout`: motion re-estimated with the previous estimate this many times.  The
first round's motion comes from uncorrected poses (its gyro bias and velocity carry the readout's
own error), and what is left of it biases the estimate low: scripts/bench_rolling_shutter.py,
2 m/s, 30 ms, 2 rounds 29.53 +- 0.03 ms (-1.6 %, seeds 1 and 2; -1.7 % seed 0), 3 rounds 30.04
(seed 1, chosen on it), 30.00 (seeds 0 and 2); 4 and 6 rounds 30.08 (seed 1); seed 0's other
flights with 3 rounds within +0.17 % (2 rounds: -0.3 % at 2 m/s, 20 ms).  With the true rotation
over the readout 2 rounds give 30.01 (scripts/diagnose_rolling_shutter.py --calibrate)."""
CALIBRATION_BLOCKS = 6
"""Contiguous blocks of frames whose minima's spread gives the readout's sigma (a lower bound)."""
GOLDEN_TOL_S = 5e-5
"""Golden-section search stops when the bracket is narrower than this (s)."""
CURVATURE_STEP_FRACTION = 0.1
"""Step of the profile's second difference, as a fraction of the readout upper bound."""
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
UNCORRECTED_RATE_RAD_S = 1.0
"""A rolling-shutter frame left uncorrected (no motion estimate: no floor pose near it) may have
moved this fast (a turning multirotor): its corners' covariance gains (rate x readout x f)^2 I
(11 px for 20 ms at f = 550 px), so that they no longer pass for refined corners (5 such front
camera frames took a fused flight's NEES from 20 to 570, scripts/bench_realism.py, BENCHMARKS.md)."""
STAMP_MOTION_PASSES = 2
"""`correct_flight` with the images: rounds of motion from the poses of the codes refined at the
stamp, refinement at the stamp again, before the final correction.  Measured on
scripts/bench_rolling_shutter.py's 1 m/s, 30 ms flight, corrected corners against the true stamp
projection where the correction is 15-20 / 20-30 px (3 + 3 codes, the final turn): 0.38 / 0.92 px
with 0 passes, 0.081 / 0.179 with 1, 0.037 / 0.080 with 2, 0.025 / 0.067 with 3 (exact per-row
poses: 0.012 / 0.033); each pass costs a refinement at the stamp (~4 CPU s per 600 frames)."""
REFINE_BATCH_FRAMES = 8
"""`refine_at_stamp`: frames refined together (as fusion.qr.detect does)."""


@dataclass
class FrameMotion:
    """Body motion at frame stamps (for one camera's frames): approximate poses (N, 4, 4), body
    rate omega_body (N, 3) rad/s, world velocity and acceleration (N, 3), the (N, 3, 3)
    covariances of the velocity and of the body rate; `valid` (N,) False where no motion is
    known."""

    timestamps_ns: np.ndarray
    T_world_body: np.ndarray
    omega_body: np.ndarray
    v_world: np.ndarray
    a_world: np.ndarray
    v_cov: np.ndarray
    valid: np.ndarray
    omega_cov: np.ndarray  # (N, 3, 3)
    # the IMU over the readout (None: constant twist): its rotation and displacement within the
    # readout beyond the constant-rate / constant-acceleration part (`_body_poses_at`);
    # imu_rate (N, 3) the gyro rate that omega_body was taken from (omega_body + bias)
    track: _ImuTrack | None = None
    imu_rate: np.ndarray | None = None


@dataclass
class RollingShutterReport:
    """What `correct_flight` did: per camera, frames corrected / left as they were."""

    readout_s: dict[str, float] = field(default_factory=dict)
    frames_corrected: dict[str, int] = field(default_factory=dict)
    frames_uncorrected: dict[str, int] = field(default_factory=dict)
    motion_source: str = ""
    refined_at_stamp: dict[str, int] = field(default_factory=dict)  # codes refined at the stamp
    # frames whose image did not read again at the stamp refinement (their codes corrected only)
    unreadable_at_stamp: dict[str, int] = field(default_factory=dict)
    pose_cov_added: dict[int, np.ndarray] = field(default_factory=dict)  # cam0 PnP, by stamp
    # the other rolling-shutter cameras' load sightings: {camera: {(stamp, load_id): (3, 3)}},
    # the camera-frame covariance the motion's uncertainty adds (`motion_sighting_covariance`)
    sighting_cov_added: dict[str, dict[tuple[int, str], np.ndarray]] = field(default_factory=dict)

    def notes(self) -> list[str]:
        return [
            f"rolling shutter {cam}: readout {1e3 * self.readout_s[cam]:.2f} ms, corners of "
            f"{self.frames_corrected[cam]} frame(s) moved to the stamp time ({self.motion_source}); "
            f"{self.frames_uncorrected[cam]} frame(s) without a motion estimate left as read "
            "(corner sigma inflated)"
            + (
                f"; {self.refined_at_stamp[cam]} code(s) refined with their edges at the stamp"
                if cam in self.refined_at_stamp
                else ""
            )
            + (
                f" ({self.unreadable_at_stamp[cam]} image(s) did not read again: their codes "
                "moved to the stamp, not refined)"
                if self.unreadable_at_stamp.get(cam)
                else ""
            )
            for cam in self.readout_s
        ]


@dataclass
class ReadoutCalibration:
    """`calibrate_readout`'s estimate: readout time and its sigma (s), frames used, the
    chi^2 / dof at the optimum, and the profile [(readout_s, cost)] evaluated."""

    readout_s: float
    sigma_s: float
    n_frames: int
    chi2_per_dof: float
    profile: list[tuple[float, float]] = field(default_factory=list)

    def note(self, camera: str) -> str:
        return (
            f"calibrated readout of {camera}: {1e3 * self.readout_s:.2f} +- {1e3 * self.sigma_s:.2f} ms "
            f"({self.n_frames} frames, chi2/dof {self.chi2_per_dof:.2f})"
        )


# ============================================================================ motion


class _ImuTrack:
    """The IMU's body rate and world acceleration integrated on its own time grid: cumulative
    gyro integral (body rate means over any window), and the world acceleration
    a = R f + g (R interpolated from the PnP poses, geometry.interpolate_poses, and inside a gap
    of the poses turned from the nearest one by the gyro, `_gyro_attitude_in_gaps`) integrated
    twice (trapezoid), so that positions can be fitted with the IMU's short-term motion removed;
    the gyro bias (`_gyro_bias`) as `gyro_bias`, `gyro_bias_sigma`."""

    def __init__(self, imu, trajectory: Trajectory):
        self.t = imu.timestamps_ns * 1e-9
        R_bs = np.asarray(imu.T_body_imu, float)[:3, :3]
        self.gyro = imu.gyro_rad_s @ R_bs.T
        dt = np.diff(self.t)[:, None]
        self.G = np.vstack([np.zeros(3), np.cumsum(0.5 * (self.gyro[1:] + self.gyro[:-1]) * dt, axis=0)])
        ts = trajectory.timestamps_ns * 1e-9
        R = interpolate_poses(ts, trajectory.T_world_body, np.clip(self.t, ts[0], ts[-1]))[:, :3, :3]
        self.gyro_bias, self.gyro_bias_sigma = _gyro_bias(self, trajectory)
        _gyro_attitude_in_gaps(R, self.t, self.G, self.gyro_bias, ts, trajectory.T_world_body[:, :3, :3])
        f_body = imu.accel_m_s2 @ R_bs.T
        self.a_world = np.einsum("nij,nj->ni", R, f_body) - np.array([0.0, 0.0, GRAVITY_M_S2])
        self.V = np.vstack(
            [np.zeros(3), np.cumsum(0.5 * (self.a_world[1:] + self.a_world[:-1]) * dt, axis=0)]
        )
        self.P = np.vstack([np.zeros(3), np.cumsum(0.5 * (self.V[1:] + self.V[:-1]) * dt, axis=0)])
        # column-major, so that `_at`'s np.interp reads each axis in place: a strided column was
        # copied on every call (a 10-minute flight's 120,000 samples: 0.3 ms a call, ~5 CPU s
        # of frame_motion's 8.7 at 900 frames); the values are the same
        self.gyro, self.G, self.a_world, self.V, self.P = (
            np.asfortranarray(x) for x in (self.gyro, self.G, self.a_world, self.V, self.P)
        )
        self.noise_density = imu.noise.gyroscope_noise_density

    def _at(self, X: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, self.t, X[:, i]) for i in range(3)])

    def mean_rate(self, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
        """(N, 3) mean body rate over [t0, t1] (the sample at t0 where t1 == t0)."""
        span = np.asarray(t1, float) - np.asarray(t0, float)
        point = self._at(self.gyro, t0)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (self._at(self.G, t1) - self._at(self.G, t0)) / span[:, None]
        return np.where((span > 0)[:, None], mean, point)

    def displacement(self, t0: float | np.ndarray, t: np.ndarray) -> np.ndarray:
        """(N, 3) position change from t0 (scalar or (N,)) to t of a body at rest at t0 with the
        IMU's world acceleration: P(t) - P(t0) - V(t0) (t - t0)."""
        t = np.asarray(t, float)
        t0 = np.broadcast_to(np.asarray(t0, float), t.shape)
        return self._at(self.P, t) - self._at(self.P, t0) - self._at(self.V, t0) * (t - t0)[:, None]

    def rotation(self, t0: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(N, 3) integral of the (bias-uncorrected) gyro from t0 to t (rad): the body's rotation
        vector over [t0, t] to first order (the rate's change of axis within a readout, a
        second-order term, is left out)."""
        return self._at(self.G, np.asarray(t, float)) - self._at(self.G, np.asarray(t0, float))


def _gyro_attitude_in_gaps(
    R: np.ndarray, t: np.ndarray, G: np.ndarray, bias: np.ndarray, ts: np.ndarray, R_poses: np.ndarray
) -> None:
    """`R` (N, 3, 3) world-from-body attitudes at the IMU times `t` (N,) s, in place: inside a
    gap of the poses (`ts` (M,) s, `R_poses` (M, 3, 3); consecutive poses more than
    ATTITUDE_GAP_FRAMES median spacings apart) from the nearest pose's attitude turned by the
    gyro (cumulative integral `G` (N, 3) rad, less `bias` (3,) rad/s), instead of the slerp between
    the poses either side.  The slerp knows nothing of the turn in between: across the realism
    bench's 1 s floor blackout it tilted the IMU's world acceleration by ~0.27 m/s^2, and the
    velocities extrapolated to the gap's frames were 45-87 mm/s off (BENCHMARKS.md, rs17)."""
    if len(ts) < 2:
        return
    spacing = np.diff(ts)
    gap = spacing > ATTITUDE_GAP_FRAMES * float(np.median(spacing))
    i = np.searchsorted(ts, t, side="right") - 1  # the poses either side of each sample: i, i + 1
    inside = (i >= 0) & (i < len(ts) - 1) & (t > ts[np.clip(i, 0, len(ts) - 1)])
    inside[inside] = gap[i[inside]]
    if not inside.any():
        return
    # from pose i forward and from pose i + 1 backward: R(t_k) = R(t_prev) Exp(∫ω - b) over
    # [t_prev, t_k] (negative going backward), the rate constant between samples (Forster et
    # al. 2017, eq. 24); one loop over the gaps' samples (per gap, 13,000 single-frame gaps of a
    # 30-minute flight cost 17 CPU s)
    k = np.flatnonzero(inside)
    gi = i[k]
    forward = t[k] <= 0.5 * (ts[gi] + ts[gi + 1])
    t_anchor = np.where(forward, ts[gi], ts[gi + 1])
    g_anchor = np.column_stack([np.interp(t_anchor, t, G[:, c]) for c in range(3)])
    prev = np.where(forward, k - 1, k + 1)  # the neighbour towards the anchor
    first = np.where(forward, ~np.isin(prev, k) | (i[np.clip(prev, 0, len(t) - 1)] != gi), False)
    last = np.where(~forward, ~np.isin(prev, k) | (i[np.clip(prev, 0, len(t) - 1)] != gi), False)
    start = first | last  # the sample next to its anchor pose
    prev = np.clip(prev, 0, len(t) - 1)
    g_prev = np.where(start[:, None], g_anchor, G[prev])
    t_prev = np.where(start, t_anchor, t[prev])
    steps = so3_exp_stack((G[k] - g_prev) - bias * (t[k] - t_prev)[:, None])
    R_anchor = np.where(forward, gi, gi + 1)
    for order in (np.flatnonzero(forward), np.flatnonzero(~forward)[::-1]):
        Rk = np.eye(3)
        for n in order:
            Rk = (R_poses[R_anchor[n]] if start[n] else Rk) @ steps[n]
            R[k[n]] = Rk


def _gyro_bias(track: _ImuTrack, trajectory: Trajectory) -> tuple[np.ndarray, float]:
    """Gyro bias (3,) and its 1-sigma (rad/s): the median over consecutive poses (at most
    BIAS_MAX_GAP_S apart) of the gyro's mean rate minus the poses' rotation rate (so3_log)."""
    ts = trajectory.timestamps_ns * 1e-9
    T = trajectory.T_world_body
    ok = np.flatnonzero((np.diff(ts) > 0) & (np.diff(ts) <= BIAS_MAX_GAP_S))
    if len(ok) < MIN_FIT_POSES:
        return np.zeros(3), OMEGA_BIAS_PRIOR_RAD_S
    rel = np.einsum("nji,njk->nik", T[ok, :3, :3], T[ok + 1, :3, :3])
    w_pose = so3_log(rel) / np.diff(ts)[ok, None]
    d = track.mean_rate(ts[ok], ts[ok + 1]) - w_pose
    bias = np.median(d, axis=0)
    mad = 1.4826 * np.median(np.abs(d - bias), axis=0)
    return bias, float(np.max(mad) / math.sqrt(len(ok)))


def frame_motion(
    trajectory: Trajectory, stamps_ns: np.ndarray, camera: CameraModel, imu=None, level_poses: bool = False
) -> FrameMotion:
    """Body motion at `stamps_ns` from the poses of `trajectory` (e.g. PnP) and the IMU.

    `level_poses`: the poses are level-frame poses (a gimbaled floor camera's PnP: roll = pitch =
    0), so with an IMU the body's roll and pitch are first restored from it
    (`_body_tilt_from_imu`): the gyro's body rate turned a level attitude, and the accelerometer's
    specific force rotated by it, are not the body's (gimbaled, 20 ms readout: PnP / smoother /
    EKF 6-dof NEES 24.6 / 33.2 / 32.7 with every health ok; 2.7 / 4.4 / 4.8 with the true
    attitude).

    With an IMU: body rate = the gyro's mean over the frame's readout minus the gyro bias
    (`_gyro_bias`); velocity = a trimmed quadratic fit of the positions of up to
    2 FIT_HALF_WINDOW_IMU poses within FIT_MAX_SPAN_IMU_S, after removing the IMU's
    double-integrated world acceleration (`_ImuTrack.displacement`; the quadratic term takes
    up the accelerometer bias), acceleration = the IMU's at the stamp plus that term; where the
    window is one-sided (a flight's end, a gap's edge) a line less the median quadratic term of
    the 2 FIT_HALF_WINDOW_IMU nearest two-sided fits, its spread (1.4826 MAD) times the window's
    mean distance from the stamp added to the velocity's sigma (`_fit_motion`).
    Without: a trimmed quadratic fit of the positions of 2 FIT_HALF_WINDOW poses within
    FIT_MAX_SPAN_S, and the rotation rate between the nearest poses either side.
    Velocity covariance from the fit residuals; body-rate covariance (`omega_cov`) from the gyro
    noise density over the readout and the bias's sigma (or OMEGA_POSE_SIGMA_RAD_S)."""
    ts = np.asarray(trajectory.timestamps_ns, dtype=np.int64)
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    n = len(stamps_ns)
    out = FrameMotion(
        stamps_ns,
        np.tile(np.eye(4), (n, 1, 1)),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        np.tile(np.eye(3), (n, 1, 1)),
        np.zeros(n, bool),
        np.tile(OMEGA_POSE_SIGMA_RAD_S**2 * np.eye(3), (n, 1, 1)),
    )
    if len(ts) < MIN_FIT_POSES:
        return out
    if level_poses and imu is not None and len(imu.timestamps_ns) > 1:
        trajectory = _body_tilt_from_imu(trajectory, imu)
    T = trajectory.T_world_body
    track = None
    bias = np.zeros(3)
    half, span_max = FIT_HALF_WINDOW, FIT_MAX_SPAN_S
    t_s = stamps_ns * 1e-9
    if imu is not None and len(imu.timestamps_ns) > 1:
        track = _ImuTrack(imu, trajectory)
        bias, bias_sigma = track.gyro_bias, track.gyro_bias_sigma
        t0 = t_s + float(camera.row_time_offset_s(0.0))
        t1 = t_s + float(camera.row_time_offset_s(camera.height - 1.0))
        # a readout beyond the IMU's samples (the flight's first or last frame): the rate over
        # the part it covers, and a constant twist (np.interp would hold the end values)
        covered = (t0 >= track.t[0]) & (t1 <= track.t[-1])
        rate = track.mean_rate(np.clip(t0, track.t[0], track.t[-1]), np.clip(t1, track.t[0], track.t[-1]))
        out.omega_body = rate - bias
        out.imu_rate = np.where(covered[:, None], rate, np.nan)
        out.track = track
        readout = max(camera.readout_s, 1.0 / imu.rate_hz)
        var = track.noise_density**2 / readout + bias_sigma**2
        out.omega_cov = np.tile(var * np.eye(3), (n, 1, 1))
        half, span_max = FIT_HALF_WINDOW_IMU, FIT_MAX_SPAN_IMU_S
    windows: list[tuple[np.ndarray, np.ndarray, bool] | None] = []
    for t in stamps_ns.tolist():
        i = int(np.searchsorted(ts, t))
        lo, hi = max(0, i - half), min(len(ts), i + half)
        idx = np.arange(lo, hi)
        dt = (ts[idx] - t) * 1e-9
        idx, dt = idx[np.abs(dt) <= span_max], dt[np.abs(dt) <= span_max]
        if len(idx) < MIN_FIT_POSES or (track is None and (dt.min() > 0 or dt.max() < 0)):
            windows.append(None)  # too few poses, or all on one side (extrapolation) without an IMU
            continue
        # at the flight's ends and a gap's edges (the window all on one side) a quadratic
        # extrapolates badly; with an IMU the positions less its motion are nearly linear in
        # time, so a line is fitted, less the acceleration the IMU leaves (below)
        windows.append((idx, dt, min(int(np.sum(dt < 0)), int(np.sum(dt > 0))) < MIN_FIT_POSES))
    # the quadratic term of the two-sided fits: the world acceleration the IMU track leaves (its
    # accelerometer bias, nearly constant: seed 0 of the realism bench 0.099 / -0.060 / 0.010
    # m/s^2, MAD 0.008-0.013); a one-sided window's line left it out, and its slope then erred by
    # it times the window's mean distance from the stamp (27-40 mm/s against a 3 mm/s sigma at
    # the edges of a 1 s floor blackout; BENCHMARKS.md, rs17)
    quad = np.full((n, 3), np.nan)
    deferred = []
    for k, window in enumerate(windows):
        if window is None:
            continue
        if track is not None and window[2]:
            deferred.append(k)
            continue
        quad[k] = _fit_motion(out, k, window, ts, T, track, bias, FIT_DEGREE, None)
    two_sided = np.flatnonzero(np.isfinite(quad[:, 0]))
    for k in deferred:
        known = None
        if len(two_sided) >= MIN_FIT_POSES:
            m = 2 * FIT_HALF_WINDOW_IMU  # the m two-sided frames nearest in time
            j = int(np.searchsorted(stamps_ns[two_sided], stamps_ns[k]))
            cand = two_sided[max(0, j - m) : j + m]
            near = cand[np.argsort(np.abs(stamps_ns[cand] - stamps_ns[k]), kind="stable")[:m]]
            q = quad[near]
            q_med = np.median(q, axis=0)
            known = (q_med, float(np.max(1.4826 * np.median(np.abs(q - q_med), axis=0))))
        _fit_motion(out, k, windows[k], ts, T, track, bias, 1, known)  # type: ignore[arg-type]
    return out


def _body_tilt_from_imu(trajectory: Trajectory, imu) -> Trajectory:
    """`trajectory` (level-frame poses: yaw and position) with each pose's attitude given the
    body's roll and pitch from the IMU, its yaw and position kept (level_frame of the result is
    the input).

    Per pose k: the world acceleration a_k from a quadratic fit of the positions within
    TILT_ACCEL_HALF_WINDOW_S, the accelerometer's mean f_k (body) over TILT_ACCEL_AVERAGE_S; the
    specific force f = R^T (a + g z) with R = Rz(yaw) R_tilt gives R_tilt as the smallest rotation
    taking f_k onto u_k = Rz(yaw)^T (a_k + g z), and the body's up u_b = R_tilt^T z.  The
    single-pose estimates (accelerometer noise, the fit's acceleration error) are averaged within
    TILT_SMOOTH_HALF_WINDOW_S, each carried to pose k by the gyro's rotation (integrated on the
    IMU's grid; Forster et al. 2017, eq. 24, bias left out: 2 mrad/s over 0.5 s is 1 mrad).
    Poses with too few neighbours for the fit keep their single-pose f_k against a = 0."""
    ts = trajectory.timestamps_ns * 1e-9
    T = np.array(trajectory.T_world_body, dtype=float)
    t_imu = imu.timestamps_ns * 1e-9
    R_bs = np.asarray(imu.T_body_imu, float)[:3, :3]
    gyro = imu.gyro_rad_s @ R_bs.T
    f_body = imu.accel_m_s2 @ R_bs.T
    # the gyro's attitude on the IMU grid (an arbitrary start), then at the poses
    steps = so3_exp_stack(0.5 * (gyro[1:] + gyro[:-1]) * np.diff(t_imu)[:, None])
    R_g = np.empty((len(t_imu), 3, 3))
    R_g[0] = np.eye(3)
    for i, step in enumerate(steps):
        R_g[i + 1] = R_g[i] @ step
    j = np.clip(np.searchsorted(t_imu, ts) - 1, 0, len(t_imu) - 2)
    frac = np.clip((ts - t_imu[j]) / np.maximum(t_imu[j + 1] - t_imu[j], 1e-12), 0.0, 1.0)
    R_gk = R_g[j] @ so3_exp_stack(gyro[j] * (frac * (t_imu[j + 1] - t_imu[j]))[:, None])
    # single-pose estimates of the body's up, expressed in the gyro's frame
    F = np.vstack(
        [np.zeros(3), np.cumsum(0.5 * (f_body[1:] + f_body[:-1]) * np.diff(t_imu)[:, None], axis=0)]
    )
    h = 0.5 * TILT_ACCEL_AVERAGE_S
    lo, hi = np.clip(ts - h, t_imu[0], t_imu[-1]), np.clip(ts + h, t_imu[0], t_imu[-1])
    f_mean = np.column_stack(
        [
            (np.interp(hi, t_imu, F[:, c]) - np.interp(lo, t_imu, F[:, c])) / np.maximum(hi - lo, 1e-9)
            for c in range(3)
        ]
    )
    near = hi - lo < 1e-6
    if near.any():
        f_mean[near] = np.column_stack([np.interp(ts[near], t_imu, f_body[:, c]) for c in range(3)])
    p = T[:, :3, 3]
    up_g = np.zeros((len(ts), 3))
    # each pose's window as an index range (the poses are in time order): O(N), not O(N^2)
    fit_lo = np.searchsorted(ts, ts - TILT_ACCEL_HALF_WINDOW_S, side="left")
    fit_hi = np.searchsorted(ts, ts + TILT_ACCEL_HALF_WINDOW_S, side="right")
    for k in range(len(ts)):
        sel = np.arange(fit_lo[k], fit_hi[k])
        a = np.zeros(3)
        if len(sel) >= MIN_FIT_POSES + 1 and ts[sel].min() < ts[k] < ts[sel].max():
            dt = ts[sel] - ts[k]
            A = np.column_stack([np.ones_like(dt), dt, 0.5 * dt**2])
            a = np.linalg.lstsq(A, p[sel], rcond=None)[0][2]
        u = T[k, :3, :3].T @ (a + np.array([0.0, 0.0, GRAVITY_M_S2]))  # level frame
        R_tilt = _smallest_rotation(f_mean[k], u)
        up_g[k] = R_gk[k] @ (R_tilt.T @ np.array([0.0, 0.0, 1.0]))
    # averaged over the window in the gyro's frame, back to each pose's body frame
    R_world = np.empty_like(T[:, :3, :3])
    win_lo = np.searchsorted(ts, ts - TILT_SMOOTH_HALF_WINDOW_S, side="left")
    win_hi = np.searchsorted(ts, ts + TILT_SMOOTH_HALF_WINDOW_S, side="right")
    cum = np.vstack([np.zeros(3), np.cumsum(up_g, axis=0)])
    mean_up = (cum[win_hi] - cum[win_lo]) / (win_hi - win_lo)[:, None]
    for k in range(len(ts)):
        up_b = R_gk[k].T @ mean_up[k]
        R_tilt = _smallest_rotation(up_b, np.array([0.0, 0.0, 1.0]))
        R0 = T[k, :3, :3] @ R_tilt
        R_world[k] = rot_z(float(yaw_of(T[k, :3, :3]) - yaw_of(R0))) @ R0  # keep the pose's yaw
    T[:, :3, :3] = R_world
    return replace(trajectory, T_world_body=T)


def _smallest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation R with R a / |a| = b / |b| (about a x b)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = float(np.linalg.norm(axis)), float(np.dot(a, b))
    if s < 1e-12:
        return np.eye(3)
    return so3_exp_stack((axis / s * math.atan2(s, c))[None])[0]


def _fit_motion(
    out: FrameMotion,
    k: int,
    window: tuple[np.ndarray, np.ndarray, bool],
    ts: np.ndarray,
    T: np.ndarray,
    track: _ImuTrack | None,
    bias: np.ndarray,
    degree: int,
    known_quad: tuple[np.ndarray, float] | None,
) -> np.ndarray:
    """Frame k of `out` (in place) from the poses (`ts` ns, `T`) of its fit `window` (pose
    indices, their times from the stamp (s), one-sided): a trimmed polynomial fit of `degree`
    through the positions less the IMU's motion (`track`); `known_quad` (q (3,) m/s^2, its
    sigma): a quadratic term taken as known (removed before a line fit; its sigma times the
    window's mean distance from the stamp added to the velocity's).  Returns the fitted
    quadratic term (3,) (NaN when not fitted or the frame is left invalid)."""
    idx, dt, one_sided = window
    t = int(out.timestamps_ns[k])
    y = T[idx, :3, 3]
    if track is not None:
        y = y - track.displacement(t * 1e-9, t * 1e-9 + dt)
    if known_quad is not None:
        y = y - 0.5 * known_quad[0] * (dt**2)[:, None]
    A = np.column_stack([dt**j / math.factorial(j) for j in range(degree + 1)])
    keep = np.ones(len(idx), bool)
    for _ in range(FIT_ROBUST_ROUNDS):  # trimmed least squares: PnP has outlier poses
        coef, *_ = np.linalg.lstsq(A[keep], y[keep], rcond=None)
        r = np.linalg.norm(y - A @ coef, axis=1)
        scale = max(FIT_TRIM_MAD * 1.4826 * float(np.median(r[keep])), FIT_TRIM_MIN_M)
        new_keep = r <= scale
        if new_keep.sum() < degree + 2 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    A, idx, dt, y = A[keep], idx[keep], dt[keep], y[keep]
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = y - A @ coef
    dof = len(idx) - degree - 1
    var_p = float(np.sum(resid**2) / (3 * dof)) if dof > 0 else 0.0
    sig2 = max(var_p * float(np.linalg.pinv(A.T @ A)[1, 1]), MIN_VELOCITY_SIGMA_M_S**2)
    if known_quad is not None:
        sig2 += (known_quad[1] * float(np.mean(dt))) ** 2
    near = idx[int(np.argmin(np.abs(dt)))]
    if track is None:
        a, b = idx[dt <= 0][-1], idx[dt >= 0][0]
        if a == b:
            a, b = (a - 1, a) if a > 0 else (a, a + 1)
        span = (ts[b] - ts[a]) * 1e-9
        if span <= 0:
            return np.full(3, np.nan)
        out.omega_body[k] = so3_log(T[a, :3, :3].T @ T[b, :3, :3]) / span
    # the pose at the stamp: the nearest pose's rotation turned back by the body rate
    back = float((t - ts[near]) * 1e-9)
    turn = out.omega_body[k] * back
    if track is not None:  # (the nearest pose may be a few frames away: the gyro's rotation)
        turn = track.rotation(np.array([ts[near] * 1e-9]), np.array([t * 1e-9]))[0] - bias * back
    out.T_world_body[k, :3, :3] = T[near, :3, :3] @ so3_exp_stack(turn[None])[0]
    out.T_world_body[k, :3, 3] = coef[0]
    out.v_world[k] = coef[1]
    quad = coef[2] if degree >= 2 else (known_quad[0] if known_quad is not None else np.zeros(3))
    out.a_world[k] = quad
    if track is not None:
        out.a_world[k] += track._at(track.a_world, np.array([t * 1e-9]))[0]
    out.v_cov[k] = sig2 * np.eye(3)
    out.valid[k] = True
    return np.asarray(coef[2], float).copy() if degree >= 2 else np.full(3, np.nan)


# ============================================================================ corners


def _body_poses_at(motion: FrameMotion, k: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """(M, 4, 4) body poses at offsets dt (M,) from the stamps of frames k (M,) of `motion`:
    R exp(omega dt + dr), p + v dt + a dt^2 / 2 + dp, where omega, v, a are the frame's body
    rate, velocity and acceleration at the stamp and dr, dp the IMU's rotation and displacement
    over [stamp, stamp + dt] beyond the constant-rate and constant-acceleration parts (zero
    without an IMU: constant twist).  A body's rate changes within a readout (a multirotor tilts
    with its acceleration's change): at 2 m/s and 30 ms the constant twist alone leaves 0.09 px
    of corner error with the TRUE mean rate, velocity and acceleration, the IMU's 200 Hz samples
    take most of it (BENCHMARKS.md)."""
    omega, v, a = motion.omega_body[k], motion.v_world[k], motion.a_world[k]
    rot = omega * dt[:, None]
    pos = v * dt[:, None] + 0.5 * a * (dt**2)[:, None]
    if motion.track is not None and motion.imu_rate is not None:
        t0 = motion.timestamps_ns[k] * 1e-9
        track = motion.track
        use = np.all(np.isfinite(motion.imu_rate[k]), axis=1)[:, None]  # readout within the IMU's
        d_rot = track.rotation(t0, t0 + dt) - motion.imu_rate[k] * dt[:, None]
        a_imu = track._at(track.a_world, t0)
        d_pos = track.displacement(t0, t0 + dt) - 0.5 * a_imu * (dt**2)[:, None]
        rot = rot + np.where(use, d_rot, 0.0)
        pos = pos + np.where(use, d_pos, 0.0)
    T_world_body = motion.T_world_body[k]
    out = np.tile(np.eye(4), (len(dt), 1, 1))
    out[:, :3, :3] = T_world_body[:, :3, :3] @ so3_exp_stack(rot)
    out[:, :3, 3] = T_world_body[:, :3, 3] + pos
    return out


@dataclass
class CornerBatch:
    """Corners of many detections, stacked (M = 4 per detection): observed px uv (M, 2), their
    normalised rays xn (M, 2), the known world point P (M, 3) (NaN for load codes), the
    size-implied depth (M,), the motion index of their frame (M,), the code's printed side (M,),
    whether P is a floor code's known point (M,); `where` [(timestamp_ns, position in the
    frame)] per detection."""

    uv: np.ndarray
    xn: np.ndarray
    P: np.ndarray
    depth_fallback: np.ndarray
    k: np.ndarray
    where: list[tuple[int, int]]
    side_m: np.ndarray
    known: np.ndarray

    def moved(self, camera: CameraModel, motion: FrameMotion) -> np.ndarray:
        """(M, 2) corners moved to their frame's stamp (module docstring, steps 1-3): each ray at
        its row's camera pose, at the depth of its world point (else the size-implied depth),
        projected with the stamp's camera pose."""
        k = self.k
        T_wb = motion.T_world_body[k]
        dt = camera.row_time_offset_s(self.uv[:, 1])
        T_wc_rows = camera.T_world_cam(_body_poses_at(motion, k, dt))
        T_cw_rows = inv_T(T_wc_rows)
        with np.errstate(invalid="ignore"):
            z = np.einsum("mj,mj->m", T_cw_rows[:, 2, :3], self.P) + T_cw_rows[:, 2, 3]
        depth = np.where(np.isfinite(z) & (z > 0), z, self.depth_fallback)
        p_cam = np.column_stack([self.xn, np.ones(len(self.xn))]) * depth[:, None]
        p_world = np.einsum("mij,mj->mi", T_wc_rows[:, :3, :3], p_cam) + T_wc_rows[:, :3, 3]
        T_cw = inv_T(camera.T_world_cam(T_wb))
        p_stamp = np.einsum("mij,mj->mi", T_cw[:, :3, :3], p_world) + T_cw[:, :3, 3]
        return camera.project(p_stamp)

    def placed_by(self, camera: CameraModel, motion: FrameMotion, corners_px: np.ndarray) -> CornerBatch:
        """This batch with each load code's corners given world points: the code's corners in
        the stamp's camera frame from the homography of `corners_px` (M, 2), its corners moved
        to the stamp (`code_corner_points`), through the stamp's camera pose.  `moved` then
        takes each corner's depth in its row's camera frame, as for a floor code's known
        corners.  A code whose homography is degenerate keeps its size-implied depth."""
        load = ~self.known
        points = code_corner_points(camera, corners_px[load], self.side_m[load])
        T_wc = camera.T_world_cam(motion.T_world_body[self.k[load]])
        world = np.einsum("mij,mj->mi", T_wc[:, :3, :3], points) + T_wc[:, :3, 3]
        P = self.P.copy()
        P[load] = world
        return replace(self, P=P)


def code_corner_points(camera: CameraModel, corners_px: np.ndarray, side_m: np.ndarray) -> np.ndarray:
    """(M, 3) each code's corners in the camera frame from its corners (M, 2) px, 4 per code in
    symbol order (TL, TR, BR, BL), the code a square of side `side_m` (M,: one per corner): the
    homography H from the unit square to the undistorted normalised corners (4 points: exact) is
    mu [side r1, side r2, t], so each corner's depth is H_3 . [U, V, 1] / mu, mu = (|h1| + |h2|)
    / (2 side) (Zhang 2000, "A flexible new technique for camera calibration", Sec. 2.3 / 3.1).
    Unlike the size-implied depth, it sees a code turned away from the camera (the depth across
    it and its centre's; 17 deg of yaw left the readout correction 0.2-0.5 px off at 30 ms).  NaN
    rows for a code whose homography is degenerate or puts it behind the camera."""
    c = np.asarray(corners_px, float).reshape(-1, 4, 2)
    side = np.asarray(side_m, float).reshape(-1, 4)[:, 0]
    n = len(c)
    out = np.full((n, 4, 3), np.nan)
    if n == 0:
        return out.reshape(-1, 3)
    xn = camera.undistort_normalized(c.reshape(-1, 2)).reshape(n, 4, 2)
    U = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    A = np.zeros((n, 8, 8))
    b = np.zeros((n, 8))
    for i, (u, v) in enumerate(U):
        x, y = xn[:, i, 0], xn[:, i, 1]
        A[:, 2 * i, :3] = [u, v, 1.0]
        A[:, 2 * i, 6:] = np.stack([-x * u, -x * v], axis=1)
        A[:, 2 * i + 1, 3:6] = [u, v, 1.0]
        A[:, 2 * i + 1, 6:] = np.stack([-y * u, -y * v], axis=1)
        b[:, 2 * i], b[:, 2 * i + 1] = x, y
    ok = np.all(np.isfinite(A), axis=(1, 2))
    ok[ok] = np.linalg.cond(A[ok]) < MAX_HOMOGRAPHY_CONDITION
    if not np.any(ok):
        return out.reshape(-1, 3)
    h = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    H = np.concatenate([h, np.ones((len(h), 1))], axis=1).reshape(-1, 3, 3)
    third = H[:, 2, :] @ np.column_stack([U, np.ones(4)]).T  # (k, 4): lambda_i mu
    mu = 0.5 * (np.linalg.norm(H[:, :, 0], axis=1) + np.linalg.norm(H[:, :, 1], axis=1)) / side[ok]
    mu = mu * np.sign(third.mean(axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = third / mu[:, None]
        points = np.concatenate([xn[ok], np.ones((len(h), 4, 1))], axis=2) * depth[:, :, None]
    good = np.all(depth > 0, axis=1) & np.all(np.isfinite(points), axis=(1, 2))
    rows = np.flatnonzero(ok)[good]
    out[rows] = points[good]
    return out.reshape(-1, 3)


def size_depths(camera: CameraModel, corners_px: np.ndarray, side_m: np.ndarray) -> np.ndarray:
    """(M,) depth (m) of each code of side `side_m` (M,: one per corner) facing the camera, from
    its corners (M, 2) px, 4 per code: side / its mean edge in undistorted normalised coordinates
    (in distorted px, f side / edge, a front camera's codes near the image border read up to
    3.5 % too far, which left their readout correction 0.2-0.3 px off at 30 ms; BENCHMARKS.md
    `gate` session); f side / edge px where the undistortion fails; NaN where a corner is not
    finite."""
    c = np.asarray(corners_px, float).reshape(-1, 4, 2)
    side = np.asarray(side_m, float).reshape(-1, 4)[:, 0]

    def mean_edge(x: np.ndarray) -> np.ndarray:
        return np.mean(np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2), axis=1)

    ok = np.all(np.isfinite(c), axis=(1, 2))
    edge_n = np.full(len(c), np.nan)
    if np.any(ok):
        edge_n[ok] = mean_edge(camera.undistort_normalized(c[ok].reshape(-1, 2)).reshape(-1, 4, 2))
    f = 0.5 * (camera.fu + camera.fv)
    with np.errstate(divide="ignore", invalid="ignore"):
        fallback = f * side / np.maximum(mean_edge(c), 1.0)
        depth = np.where(np.isfinite(edge_n) & (edge_n > 0), side / edge_n, fallback)
    return np.repeat(np.where(ok, depth, np.nan), 4)


def corner_batch(
    frames: dict[int, list[QRDetection]], camera: CameraModel, world: World, motion: FrameMotion
) -> CornerBatch:
    """The floor and load codes' corners of the frames that have a motion estimate, stacked."""
    index = {int(t): k for k, t in enumerate(motion.timestamps_ns.tolist())}
    uv, P, side, ks, where = [], [], [], [], []
    for ts, dets in frames.items():
        k = index.get(int(ts))
        if k is None or not motion.valid[k]:
            continue
        codes = classify(dets, world)
        known = {id(s.detection): np.asarray(s.corners_world, float) for s in codes.floor}
        sides = {id(s.detection): world.floor_side_m for s in codes.floor}
        sides.update({id(s.detection): world.load_side_m for s in codes.loads})
        for i, d in enumerate(dets):
            c = np.asarray(d.corners_px, float).reshape(4, 2)
            if id(d) not in sides or not np.all(np.isfinite(c)):
                continue
            uv.append(c)
            P.append(known.get(id(d), np.full((4, 3), np.nan)))
            side.append(np.full(4, sides[id(d)]))
            ks.append(np.full(4, k))
            where.append((int(ts), i))
    if not uv:
        e = np.zeros((0, 2))
        return CornerBatch(
            e, e, np.zeros((0, 3)), np.zeros(0), np.zeros(0, int), [], np.zeros(0), np.zeros(0, bool)
        )
    uv_all = np.concatenate(uv)
    side_all = np.concatenate(side)
    P_all = np.concatenate(P)
    return CornerBatch(
        uv_all,
        camera.undistort_normalized(uv_all),
        P_all,
        size_depths(camera, uv_all, side_all),
        np.concatenate(ks),
        where,
        side_all,
        np.all(np.isfinite(P_all), axis=1),
    )


def apply_corners(
    frames: dict[int, list[QRDetection]], batch: CornerBatch, corners_px: np.ndarray
) -> dict[int, list[QRDetection]]:
    """`frames` with the batch's detections given `corners_px` (M, 2) (non-finite ones kept).

    A code the readout deformed (its corners moved by different amounts: shear, stretch) is
    refined less well than a pinhole view of it (fusion.qr.refine fits one homography and
    extrapolates the fourth corner); its `corner_cov_px2` gains (DEFORMATION_SIGMA_FRACTION d)^2 I,
    d the largest corner displacement about the code's mean displacement (px)."""
    out = {ts: list(dets) for ts, dets in frames.items()}
    new = corners_px.reshape(-1, 4, 2)
    old = batch.uv.reshape(-1, 4, 2)
    for (ts, i), c, c0 in zip(batch.where, new, old):
        if np.all(np.isfinite(c)):
            d = out[ts][i]
            cov = d.corner_cov_px2
            if cov is not None:
                move = c - c0
                deform = float(np.max(np.linalg.norm(move - move.mean(axis=0), axis=1)))
                cov = np.asarray(cov, float) + (DEFORMATION_SIGMA_FRACTION * deform) ** 2 * np.eye(8)
            out[ts][i] = replace(d, corners_px=c, corner_cov_px2=cov)
    return out


def correction_scale_sigma(
    original: dict[int, list[QRDetection]], corrected: dict[int, list[QRDetection]]
) -> dict[int, float]:
    """{timestamp_ns: kappa}, the relative error of each frame's readout correction: kappa =
    CORRECTION_SIGMA_PER_PX2 m, m the mean displacement (px) of the frame's code corners from
        where the readout saw them (`original`) to the stamp (`corrected`), so that the corners'
    error is kappa m = CORRECTION_SIGMA_PER_PX2 m^2
    (the constant's measurement).  The error scales with the correction, i.e. with the motion
    over the readout, so it is an error of the motion's scale (`motion_pose_covariance`)."""
    out = {}
    for ts, dets in corrected.items():
        moves = []
        for d0, d in zip(original.get(ts, []), dets):
            move = np.asarray(d.corners_px, float).reshape(4, 2) - np.asarray(d0.corners_px, float).reshape(
                4, 2
            )
            m = np.linalg.norm(move, axis=1)
            if np.all(np.isfinite(m)):
                moves.append(float(m.mean()))
        if moves:
            out[int(ts)] = CORRECTION_SIGMA_PER_PX2 * float(np.mean(moves))
    return out


def correct_frames(
    frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    motion: FrameMotion,
) -> tuple[dict[int, list[QRDetection]], int]:
    """Every frame {timestamp_ns: detections} with its floor and load codes' corners moved to the
    stamp time (module docstring; stamps as in `motion`); other codes, and frames without a
    motion estimate, as they were.  Also returns how many frames had a motion estimate."""
    if not camera.rolling_shutter:
        return {ts: list(d) for ts, d in frames.items()}, 0
    batch = corner_batch(frames, camera, world, motion)
    # a load code's corners are first moved at the depth of its apparent size as read; then at
    # their points from the moved corners' homography (`CornerBatch.placed_by`): the readout
    # stretches a code that moves across the rows (1 m/s up at 1.1 m and 30 ms: ~3 % of its
    # height), and the stretched size put the correction ~1.5 % short (0.3 mm per m/s on the
    # sightings, which a front mount check read as a 0.08 deg pitch), and a code turned away
    # from the camera is not at one depth (BENCHMARKS.md, twenty-fifth session)
    if not np.all(batch.known):  # load codes (the floor camera's frames have none: no extra moves)
        for _ in range(LOAD_PLANE_PASSES):
            batch = batch.placed_by(camera, motion, batch.moved(camera, motion))
    index = {int(t): k for k, t in enumerate(motion.timestamps_ns.tolist())}
    n = sum(1 for ts in frames if index.get(int(ts)) is not None and motion.valid[index[int(ts)]])
    return apply_corners(frames, batch, batch.moved(camera, motion)), n


def corrected_trajectory(
    floor_frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    imu=None,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    passes: int = CORRECTION_PASSES,
) -> Trajectory:
    """PnP trajectory of the floor frames {timestamp_ns: detections} with their corners moved
    to the stamp: PnP on the raw corners, then `passes` rounds of motion (`frame_motion`),
    correction, PnP (the raw poses' rolling-shutter errors bias the first velocity fit; each
    round roughly halves what is left, measured)."""
    traj, _ = pnp_trajectory(floor_frames, camera, world, corner_sigma_px)
    if not camera.rolling_shutter:
        return traj
    stamps = np.array(sorted(floor_frames), dtype=np.int64)
    for _ in range(passes):
        motion = frame_motion(traj, stamps, camera, imu, level_poses=camera.gimbaled)
        fixed, _ = correct_frames(floor_frames, camera, world, motion)
        traj, _ = pnp_trajectory(fixed, camera, world, corner_sigma_px)
    return traj


def correct_flight(
    det,
    cameras: dict[str, CameraModel],
    world: World,
    imu=None,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    passes: int = CORRECTION_PASSES,
    streams=None,
):
    """(DetectionResult with every rolling-shutter camera's corners moved to their frame's stamp,
    RollingShutterReport).  The motion comes from the floor camera (`cameras["cam0"]`): PnP on
    the raw corners, then `passes` rounds of motion (`frame_motion`), correction, PnP.  Other
    cameras use the same poses and gyro at their own stamps.  With `streams` ({camera: stream
    with `timestamps_ns` and `load_image(i)`, e.g. FlightLog.cameras}) every rolling-shutter
    camera's floor and load codes are then refined again with their edge points at the stamp
    (`refine_at_stamp`); the codes it does not replace are corrected as above.  Before that the
    floor camera's motion is taken again STAMP_MOTION_PASSES times from the PnP poses of its
    codes refined at the stamp (module docstring).  Without a rolling-shutter camera the result
    is `det` itself."""
    report = RollingShutterReport(motion_source="IMU gyro + PnP velocity" if imu is not None else "PnP poses")
    rs = {name: cam for name, cam in cameras.items() if cam is not None and cam.rolling_shutter}
    floor_cam = cameras.get("cam0")
    if not rs or floor_cam is None:
        return det, report
    floor_frames = det.by_frame("cam0")
    traj = corrected_trajectory(floor_frames, floor_cam, world, imu, corner_sigma_px, passes)
    floor_reader = _image_reader(streams, "cam0")
    if "cam0" in rs and floor_reader is not None:
        # the motion again from the poses of the codes refined at the stamp: the corners moved
        # after refinement in the sheared image (`corrected_trajectory`) give poses 10-20 mm and
        # 10-15 mrad off where the correction exceeds ~15 px (a 1.7 rad/s turn at 1 m/s, 30 ms),
        # whose velocity fit and gravity then err by up to 0.1 m/s (~1 px at the last row)
        stamps = np.array(sorted(floor_frames), dtype=np.int64)
        for _ in range(STAMP_MOTION_PASSES):
            motion = frame_motion(traj, stamps, floor_cam, imu, level_poses=floor_cam.gimbaled)
            fixed, _, _ = _correct_camera(floor_frames, floor_cam, world, motion, floor_reader, "cam0")
            traj, _ = pnp_trajectory(fixed, floor_cam, world, corner_sigma_px)
    corrected: list[QRDetection] = []
    for name in sorted({d.camera for d in det.detections}):
        frames = det.by_frame(name)
        cam = rs.get(name)
        if cam is None:
            corrected.extend(d for ds in frames.values() for d in ds)
            continue
        stamps = np.array(sorted(frames), dtype=np.int64)
        motion = frame_motion(traj, stamps, cam, imu, level_poses=floor_cam.gimbaled)
        reader = _image_reader(streams, name)
        fixed, n, n_refined = _correct_camera(frames, cam, world, motion, reader, name)
        if reader is not None:
            report.refined_at_stamp[name] = n_refined
            if reader.unreadable:
                report.unreadable_at_stamp[name] = len(reader.unreadable)
        corrected.extend(d for ts in sorted(fixed) for d in fixed[ts])
        if name == "cam0" and not cam.gimbaled:
            kappa = correction_scale_sigma(frames, fixed)
            report.pose_cov_added = motion_pose_covariance(
                frames, cam, world, motion, corner_sigma_px, scale_sigma=kappa
            )
        elif name != "cam0":
            # the load codes' camera-frame measurements carry the motion's error as well: without
            # it the realism bench's 30 ms sightings read chi2/3 60 (mean; global shutter 0.36)
            # and pulled the smoother to NEES 23 (BENCHMARKS.md, `gate` session)
            report.sighting_cov_added[name] = motion_sighting_covariance(
                frames, cam, world, motion, corner_sigma_px, scale_sigma=correction_scale_sigma(frames, fixed)
            )
        report.readout_s[name] = cam.readout_s
        report.frames_corrected[name] = n
        report.frames_uncorrected[name] = len(frames) - n
    for note in report.notes():
        log_.info(note)
    return replace(det, detections=corrected), report


def _correct_camera(
    frames: dict[int, list[QRDetection]],
    cam: CameraModel,
    world: World,
    motion: FrameMotion,
    reader,
    name: str,
) -> tuple[dict[int, list[QRDetection]], int, int]:
    """One camera's frames moved to their stamps with `motion` (`correct_frames`), its codes
    refined again at the stamp where `reader` gives the images (`refine_at_stamp`), frames
    without a motion inflated; also the frames with a motion and the codes refined at the stamp."""
    fixed, n = correct_frames(frames, cam, world, motion)
    done: set[tuple[int, int]] = set()
    if reader is not None:
        # an image that read at detection and not now leaves its frame's codes as corrected
        # (the reader counts it: RollingShutterReport.unreadable_at_stamp)
        refined, done = refine_at_stamp(
            frames, reader, cam, world, motion, placed=fixed, polish=name in POLISHED_CAMERAS
        )
        for ts, i in done:
            fixed[ts][i] = refined[ts][i]
    return _inflate_uncorrected(fixed, cam, motion), n, len(done)


def _inflate_uncorrected(
    frames: dict[int, list[QRDetection]], camera: CameraModel, motion: FrameMotion
) -> dict[int, list[QRDetection]]:
    """`frames` with the corner covariance of those without a motion estimate inflated by
    (UNCORRECTED_RATE_RAD_S x readout x f)^2 I (their corners are as read)."""
    valid = {int(t): bool(v) for t, v in zip(motion.timestamps_ns.tolist(), motion.valid)}
    extra = (UNCORRECTED_RATE_RAD_S * camera.readout_s * 0.5 * (camera.fu + camera.fv)) ** 2
    out = {}
    for ts, dets in frames.items():
        if valid.get(int(ts), False):
            out[ts] = dets
            continue
        inflated = []
        for d in dets:
            sigma = d.corner_sigma_px if d.corner_sigma_px is not None else DEFAULT_CORNER_SIGMA_PX
            cov = d.corner_cov_px2 if d.corner_cov_px2 is not None else sigma**2 * np.eye(8)
            inflated.append(
                replace(
                    d, corner_cov_px2=cov + extra * np.eye(8), corner_sigma_px=math.sqrt(sigma**2 + extra)
                )
            )
        out[ts] = inflated
    return out


class _StampImages:
    """`load_image(timestamp_ns)` of a camera stream for `refine_at_stamp`: None for an image
    that does not read (the stream's None, or its LogError), whose stamp goes to `unreadable`.
    One such image had raised out of the refinement, which then refined none of the camera's
    codes with no reason given; one that gave None was left out unsaid."""

    def __init__(self, stream, name: str):
        self.stream, self.name = stream, name
        self.at = {int(t): i for i, t in enumerate(np.asarray(stream.timestamps_ns).tolist())}
        self.unreadable: set[int] = set()

    def __call__(self, timestamp_ns: int) -> np.ndarray | None:
        i = self.at.get(int(timestamp_ns))
        if i is None:
            return None
        try:
            image = self.stream.load_image(i)
        except LogError as e:
            log_.info(
                "rolling shutter %s: frame %d not refined at the stamp (%s)", self.name, timestamp_ns, e
            )
            image = None
        if image is None:
            self.unreadable.add(int(timestamp_ns))
        return image


def _image_reader(streams, name: str) -> _StampImages | None:
    """`load_image(timestamp_ns)` of camera `name`'s stream (_StampImages), or None (no streams
    given)."""
    stream = None if streams is None else streams.get(name)
    return None if stream is None else _StampImages(stream, name)


def motion_pose_covariance(
    frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    motion: FrameMotion,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    scale_sigma: dict[int, float] | None = None,
) -> dict[int, np.ndarray]:
    """{timestamp_ns: (6, 6)} the PnP pose covariance ([rx, ry, rz, tx, ty, tz], body frame,
    right perturbation) that the motion's uncertainty adds: G S G^T, G = d(pose) / d(omega, v)
    by central differences of the whole correct-then-PnP map (each motion component of every
    frame perturbed by MOTION_STEP at once: the frames are independent), S = the motion's
    covariance.  The motion's error moves all codes of a frame alike, i.e. the image shift
    PnP determines best (~0.003 px at 1.5 m), so it must enter the pose, not the corners.
    `scale_sigma` {timestamp_ns: kappa} (`correction_scale_sigma`): the correction's relative
    error, an error of the motion's scale, adds kappa^2 u u^T to S, u = (omega, v) (rank one,
    along the motion), so it enters the pose covariance and not PnP's weights (as corner sigma it
    cost PnP 10 % of its accuracy at 1 m/s, 20 ms: scripts/bench_rolling_shutter.py)."""
    base = _pnp_by_stamp(frames, camera, world, motion, corner_sigma_px)
    G = {ts: np.zeros((6, 6)) for ts in base}
    for j, plus, minus in _motion_steps(motion):
        poses = [_pnp_by_stamp(frames, camera, world, m, corner_sigma_px) for m in (plus, minus)]
        for ts in base:
            if ts in poses[0] and ts in poses[1]:
                d = se3_log(inv_T(poses[1][ts]) @ poses[0][ts])[0]
                G[ts][:, j] = d / (2.0 * MOTION_STEP)
    index = {int(t): k for k, t in enumerate(motion.timestamps_ns.tolist())}
    out = {}
    for ts, g in G.items():
        S = _motion_covariance(motion, index[int(ts)], (scale_sigma or {}).get(int(ts), 0.0))
        out[int(ts)] = g @ S @ g.T
    return out


def _motion_steps(motion: FrameMotion):
    """(j, motion + MOTION_STEP, motion - MOTION_STEP) in component j of (omega, v), j = 0..5,
    every frame at once (the frames are independent): the central differences of
    `motion_pose_covariance` and `motion_sighting_covariance`."""
    for j in range(6):
        pair = []
        for sign in (1.0, -1.0):
            m = replace(motion, omega_body=motion.omega_body.copy(), v_world=motion.v_world.copy())
            (m.omega_body if j < 3 else m.v_world)[:, j % 3] += sign * MOTION_STEP
            pair.append(m)
        yield j, pair[0], pair[1]


def _motion_covariance(motion: FrameMotion, k: int, kappa: float) -> np.ndarray:
    """(6, 6) covariance of frame k's (omega, v): the motion's own, plus kappa^2 u u^T, u = (omega,
    v), for the correction's relative scale error `kappa` (`correction_scale_sigma`)."""
    S = np.zeros((6, 6))
    S[:3, :3], S[3:, 3:] = motion.omega_cov[k], motion.v_cov[k]
    if kappa > 0.0:
        u = np.concatenate([motion.omega_body[k], motion.v_world[k]])
        S = S + kappa**2 * np.outer(u, u)
    return S


def motion_sighting_covariance(
    frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    motion: FrameMotion,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    scale_sigma: dict[int, float] | None = None,
) -> dict[tuple[int, str], np.ndarray]:
    """{(timestamp_ns, load_id): (3, 3)} the covariance of a load sighting's camera-frame code
    centre (LoadObservation.p_cam, m) that the motion's uncertainty adds, for a camera's `frames`
    {timestamp_ns: detections} (e.g. the front camera): G S G^T, G = d(p_cam) / d(omega, v) by
    central differences of the whole correct-then-solve map, S the motion's covariance with the
    correction's scale error (`scale_sigma`), as `motion_pose_covariance` does for the floor
    camera's PnP pose.  The floor camera's motion error moves a load code's corners alike, the
    image shift a code's solve determines best, so it is a camera-frame error of the sighting,
    common to the codes of a frame (kept per sighting: the back ends take sightings one by one)."""
    base = _sightings_by_key(frames, camera, world, motion, corner_sigma_px)
    G = {key: np.zeros((3, 6)) for key in base}
    for j, plus, minus in _motion_steps(motion):
        moved = [_sightings_by_key(frames, camera, world, m, corner_sigma_px) for m in (plus, minus)]
        for key in base:
            if key in moved[0] and key in moved[1]:
                G[key][:, j] = (moved[0][key] - moved[1][key]) / (2.0 * MOTION_STEP)
    index = {int(t): k for k, t in enumerate(motion.timestamps_ns.tolist())}
    out = {}
    for key, g in G.items():
        k = index.get(key[0])
        if k is None or not motion.valid[k]:
            continue  # not corrected: its corners' covariance was inflated instead
        S = _motion_covariance(motion, k, (scale_sigma or {}).get(key[0], 0.0))
        out[key] = g @ S @ g.T
    return out


def _sightings_by_key(frames, camera, world, motion, sigma) -> dict[tuple[int, str], np.ndarray]:
    """{(timestamp_ns, load_id): p_cam (3,)} of the load codes of the corrected frames."""
    fixed, _ = correct_frames(frames, camera, world, motion)
    stamps, batch = [], []
    for ts in sorted(fixed):
        loads = classify(fixed[ts], world).loads
        if loads:
            stamps.append(int(ts))
            batch.append(LoadFrame(loads, np.eye(4), None))
    if not batch:
        return {}
    per_frame = estimate_load_observations_frames(batch, camera, world, sigma)
    return {
        (ts, o.load_id): o.p_cam for ts, obs in zip(stamps, per_frame) for o in obs if o.p_cam is not None
    }


def add_sighting_covariance(
    observations: list[LoadObservation], added: dict[tuple[int, str], np.ndarray]
) -> list[LoadObservation]:
    """`observations` (LoadObservation) with `added[(timestamp_ns, load_id)]` added to each
    matching sighting's camera-frame covariance `cov_cam` (new objects; the others as they are)."""
    if not added:
        return observations
    out = []
    for o in observations:
        extra = added.get((int(o.timestamp_ns), o.load_id))
        out.append(o if extra is None or o.cov_cam is None else replace(o, cov_cam=o.cov_cam + extra))
    return out


def _pnp_by_stamp(frames, camera, world, motion, sigma) -> dict[int, np.ndarray]:
    """{timestamp_ns: T_world_body} of PnP on the corrected frames (posed ones only)."""
    fixed, _ = correct_frames(frames, camera, world, motion)
    traj, _ = pnp_trajectory(fixed, camera, world, sigma)
    return {int(t): T for t, T in zip(traj.timestamps_ns, traj.T_world_body)}


def add_pose_covariance(trajectory: Trajectory, added: dict[int, np.ndarray]) -> Trajectory:
    """`trajectory` with `added[timestamp_ns]` added to the covariance of each pose stamped so."""
    if not added or trajectory.covariances is None:
        return trajectory
    covs = trajectory.covariances.copy()
    for i, t in enumerate(trajectory.timestamps_ns.tolist()):
        extra = added.get(int(t))
        if extra is not None:
            covs[i] = covs[i] + extra
    return replace(trajectory, covariances=covs)


# ============================================================================ refinement at the stamp


class _StampMap:
    """Undistorted px of a rolling-shutter image -> undistorted px of a global-shutter image at
    the stamp, for points on known planes (floor codes): each point's ray at its row's camera
    pose (`_body_poses_at`), cut with its code's plane, projected with the stamp's camera pose.
    `frame_k` (I,) the motion index of each image; `plane_n` / `plane_d` (I, K_max, 3) / (I,
    K_max) each code's world plane n . p = d (code k of image i)."""

    def __init__(self, camera: CameraModel, motion: FrameMotion, frame_k, plane_n, plane_d):
        self.camera, self.motion = camera, motion
        self.frame_k, self.plane_n, self.plane_d = np.asarray(frame_k), plane_n, plane_d

    def __call__(self, image: np.ndarray, code: np.ndarray, points_u: np.ndarray) -> np.ndarray:
        cam = self.camera
        out = np.full(points_u.shape, np.nan)
        ok = np.all(np.isfinite(points_u), axis=1)
        if not np.any(ok):
            return out
        image, code, p = image[ok], code[ok], points_u[ok]
        k = self.frame_k[image]
        xn = np.column_stack([(p[:, 0] - cam.cu) / cam.fu, (p[:, 1] - cam.cv) / cam.fv, np.ones(len(p))])
        rows = cam.project(xn)[:, 1]  # the distorted row: its exposure time
        T_wc = cam.T_world_cam(_body_poses_at(self.motion, k, cam.row_time_offset_s(rows)))
        ray = np.einsum("mij,mj->mi", T_wc[:, :3, :3], xn)
        n, d = self.plane_n[image, code], self.plane_d[image, code]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = (d - np.einsum("mi,mi->m", n, T_wc[:, :3, 3])) / np.einsum("mi,mi->m", n, ray)
        p_world = T_wc[:, :3, 3] + depth[:, None] * ray
        T_cw = inv_T(cam.T_world_cam(self.motion.T_world_body[k]))
        p_cam = np.einsum("mij,mj->mi", T_cw[:, :3, :3], p_world) + T_cw[:, :3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = p_cam[:, :2] / p_cam[:, 2:3]
        out[ok] = np.column_stack([cam.fu * uv[:, 0] + cam.cu, cam.fv * uv[:, 1] + cam.cv])
        return out


def _load_code_plane(camera: CameraModel, T_wc: np.ndarray, at_stamp, as_read, side_m: float) -> np.ndarray:
    """A load code's world plane for `refine_at_stamp`, as (2, 3) [a point on it, its normal]:
    from the homography of its corners moved to the stamp `at_stamp` (`code_corner_points`; the
    corners as read are stretched by the readout), else facing the stamp's camera (pose T_wc) at
    the depth of its size as read (`as_read`)."""
    side = np.full(4, side_m)
    if at_stamp is not None:
        points = code_corner_points(camera, np.asarray(at_stamp, float).reshape(4, 2), side)
        normal = np.cross(points[1] - points[0], points[3] - points[0])
        if np.all(np.isfinite(points)) and np.linalg.norm(normal) > 0:
            R, t = T_wc[:3, :3], T_wc[:3, 3]
            return np.vstack([R @ points.mean(axis=0) + t, R @ (normal / np.linalg.norm(normal))])
    depth = size_depths(camera, np.asarray(as_read, float).reshape(4, 2), side)[0]
    return np.vstack([T_wc[:3, 3] + depth * T_wc[:3, 2], T_wc[:3, 2]])


def refine_at_stamp(
    frames: dict[int, list[QRDetection]],
    load_image,
    camera: CameraModel,
    world: World,
    motion: FrameMotion,
    placed: dict[int, list[QRDetection]] | None = None,
    polish: bool = False,
) -> tuple[dict[int, list[QRDetection]], set[tuple[int, int]]]:
    """The floor and load codes of `frames` {timestamp_ns: detections} refined again from their
    images (`load_image(timestamp_ns) -> (H, W) uint8 or None`), from the decoder's corners, with
    the finder edge points moved to the stamp time before the homography fit (on the floor
    code's known plane; a load code's plane taken facing the camera at its size-implied depth)
    (fusion.qr.refine.refine_frames `point_map`, `_StampMap`): the fit is then of a global-shutter
    view, not of the readout-sheared one, whose edges no homography describes (a changing body
    rate bends them).  Returns the frames (re-refined codes replaced) and the (timestamp_ns,
    position) of the codes replaced: those refined by stage 2 and passing its self-check, in
    frames with a motion estimate; the others are left for `correct_frames`.  `placed`: the
    same frames with their corners moved to the stamp (`correct_frames`), from which a load
    code's plane is taken (`_load_code_plane`).  `polish`: refine_frames' (the front camera's
    codes, POLISHED_CAMERAS)."""
    index = {int(t): k for k, t in enumerate(motion.timestamps_ns.tolist())}
    out = {ts: list(dets) for ts, dets in frames.items()}
    done: set[tuple[int, int]] = set()
    todo = [ts for ts in sorted(frames) if index.get(int(ts)) is not None and motion.valid[index[int(ts)]]]
    for start in range(0, len(todo), REFINE_BATCH_FRAMES):
        images: list[np.ndarray] = []
        codes: list[list[tuple[np.ndarray, int | None]]] = []
        where: list[list[tuple[int, int]]] = []
        ks: list[int] = []
        planes: list[list[tuple[np.ndarray, float]]] = []
        for ts in todo[start : start + REFINE_BATCH_FRAMES]:
            sorted_codes = classify(frames[ts], world)
            known = {id(s.detection): np.asarray(s.corners_world, float) for s in sorted_codes.floor}
            # a load code's plane is not known: from its corners moved to the stamp (`placed`)
            T_wc = camera.T_world_cam(motion.T_world_body[index[int(ts)]])
            position = {id(d): i for i, d in enumerate(frames[ts])}
            moved = placed.get(ts) if placed is not None else None
            for sighting in sorted_codes.loads:
                d = sighting.detection
                at_stamp = moved[position[id(d)]].corners_px if moved is not None else None
                known[id(d)] = _load_code_plane(camera, T_wc, at_stamp, d.corners_px, world.load_side_m)
            chosen = [(i, d) for i, d in enumerate(frames[ts]) if id(d) in known and not d.tracked]
            if not chosen:
                continue
            image = load_image(ts)
            if image is None:
                continue
            images.append(image)
            codes.append([(d.corners_raw_px, None) for _, d in chosen])
            where.append([(ts, i) for i, _ in chosen])
            ks.append(index[int(ts)])
            plane = []
            for _, d in chosen:
                P = known[id(d)]
                if len(P) == 2:  # load code: (a point, the normal)
                    plane.append((P[1], float(P[1] @ P[0])))
                    continue
                n = np.cross(P[1] - P[0], P[3] - P[0])
                n = n / np.linalg.norm(n)
                plane.append((n, float(n @ P.mean(axis=0))))
            planes.append(plane)
        if not images:
            continue
        width = max(len(c) for c in codes)
        plane_n = np.zeros((len(images), width, 3))
        plane_d = np.zeros((len(images), width))
        for i, plane in enumerate(planes):
            for j, (normal, offset) in enumerate(plane):
                plane_n[i, j], plane_d[i, j] = normal, offset
        results = refine_frames(
            images, codes, camera, point_map=_StampMap(camera, motion, ks, plane_n, plane_d), polish=polish
        )
        for frame_results, frame_where in zip(results, where):
            for res, (ts, i) in zip(frame_results, frame_where):
                if res is None or res.stage != 2 or not np.all(np.isfinite(res.corners_px)):
                    continue
                out[ts][i] = replace(
                    out[ts][i],
                    corners_px=res.corners_px,
                    corner_sigma_px=res.corner_sigma_px,
                    corner_cov_px2=res.corner_cov_px2,
                )
                done.add((ts, i))
    return out, done


# ============================================================================ calibration


def _frames_cost(
    frames: list[list], camera: CameraModel, sigma: float, placement: Placement | FloorLayout | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Whitened reprojection cost (chi^2) of the PnP pose of each of `frames` (each a list of
    floor sightings) and its degrees of freedom (8 per code - 6; 0, 0 for an unposed frame or
    one with a code left out)."""
    results = estimate_floor_poses(frames, camera, sigma, placement=placement)
    cost, dof = np.zeros(len(frames)), np.zeros(len(frames), dtype=int)
    for i, (sightings, res) in enumerate(zip(frames, results)):
        if res is None or res.dropped_payloads:
            continue
        P = np.concatenate([np.asarray(s.corners_world, float) for s in sightings])
        T_cw = inv_T(res.T_world_cam)
        pred = camera.project(P @ T_cw[:3, :3].T + T_cw[:3, 3]).reshape(-1, 8)
        z = np.concatenate([np.asarray(s.detection.corners_px, float) for s in sightings]).reshape(-1, 8)
        W = floor_whitening(sightings, sigma, placement, camera)
        r = np.einsum("cij,cj->ci", W, z - pred)
        if np.all(np.isfinite(r)):
            cost[i], dof[i] = float(np.sum(r**2)), r.size - 6
    return cost, dof


def calibrate_readout(
    det,
    camera: CameraModel,
    world: World,
    imu=None,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    max_readout_s: float | None = None,
    max_frames: int = MAX_CALIBRATION_FRAMES,
    rounds: int = CALIBRATION_ROUNDS,
) -> ReadoutCalibration:
    """Readout time (s, whole frame) of the floor camera `camera` from a flight's floor
    detections: the minimum over [0, max_readout_s] (default: one frame period) of the whitened
    PnP reprojection cost of the up to `max_frames` frames whose image moves most, after moving
    the corners to the stamp with that readout (`correct_frames`); golden-section search; sigma
    from the profile's curvature.  The motion comes from the poses corrected with the previous
    round's estimate (the first round: the camera's own readout, usually 0, i.e. raw PnP),
    `rounds` times.  Raises EstimationError when too few frames have a motion estimate."""
    upper = float(max_readout_s) if max_readout_s is not None else 1.0 / max(camera.rate_hz, 1e-3)
    if not upper > 0:
        raise EstimationError(f"readout search bound must be positive, got {upper!r}")
    frames = det.by_frame("cam0")
    stamps = np.array(sorted(frames), dtype=np.int64)
    readout = min(camera.readout_s, upper)
    result = None
    for _ in range(max(rounds, 1)):
        cam = replace(camera, line_delay_s=readout / camera.height)
        traj = corrected_trajectory(frames, cam, world, imu, corner_sigma_px)
        result = _golden_readout(
            frames,
            stamps,
            frame_motion(traj, stamps, cam, imu, level_poses=cam.gimbaled),
            camera,
            world,
            imu,
            corner_sigma_px,
            upper,
            max_frames,
        )
        readout = result.readout_s
    assert result is not None
    return result


def _fastest_frames(frames, stamps, motion: FrameMotion, max_frames: int) -> dict:
    """{timestamp_ns: detections} of the up to `max_frames` frames whose image moves most (body
    rate plus velocity over height, rad/s roughly), in time order."""
    speed = np.full(len(stamps), -1.0)
    for k in np.flatnonzero(motion.valid):
        h = max(float(motion.T_world_body[k, 2, 3]), 0.3)
        speed[k] = np.linalg.norm(motion.omega_body[k]) + np.linalg.norm(motion.v_world[k]) / h
    order = [k for k in np.argsort(-speed) if speed[k] > 0][:max_frames]
    if len(order) < MIN_FIT_POSES:
        raise EstimationError(f"readout calibration: only {len(order)} frame(s) with a motion estimate")
    return {int(stamps[k]): frames[int(stamps[k])] for k in sorted(order)}


def _readout_cost(chosen: dict, batch: CornerBatch, camera, world, motion, readout_s: float, sigma_px):
    """Per-frame whitened PnP cost and dof (`_frames_cost`) of the frames `chosen` with their
    corners moved to the stamp for a readout of `readout_s`."""
    cam = replace(camera, line_delay_s=readout_s / camera.height)
    fixed = apply_corners(chosen, batch, batch.moved(cam, motion))
    views = [classify(fixed[ts], world).floor for ts in chosen]
    return _frames_cost(views, cam, sigma_px, Placement.from_world(world))


def _golden_readout(frames, stamps, motion: FrameMotion, camera, world, imu, sigma_px, upper, max_frames):
    """One round of `calibrate_readout` with a fixed motion estimate."""
    chosen = _fastest_frames(frames, stamps, motion, max_frames)
    batch = corner_batch(chosen, camera, world, motion)
    cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def per_frame(readout_s: float) -> tuple[np.ndarray, np.ndarray]:
        if readout_s not in cache:
            cache[readout_s] = _readout_cost(chosen, batch, camera, world, motion, readout_s, sigma_px)
        return cache[readout_s]

    def cost(readout_s: float) -> float:
        return float(per_frame(readout_s)[0].sum())

    a, b = 0.0, upper
    c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)
    fc, fd = cost(c), cost(d)
    while b - a > GOLDEN_TOL_S:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - _GOLDEN * (b - a)
            fc = cost(c)
        else:
            a, c, fc = c, d, fd
            d = a + _GOLDEN * (b - a)
            fd = cost(d)
    best = 0.5 * (a + b)
    chi2, dof = float(per_frame(best)[0].sum()), int(per_frame(best)[1].sum())
    h = CURVATURE_STEP_FRACTION * upper
    x0 = min(max(best, h), upper - h)  # keep the stencil inside [0, upper]
    stencil = [per_frame(x)[0] for x in (x0 - h, x0, x0 + h)]
    curv = (stencil[2].sum() - 2.0 * stencil[1].sum() + stencil[0].sum()) / h**2
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    sigma = math.sqrt(2.0 * scale / curv) if curv > 0 else math.inf
    # the frames' errors are not independent (the motion estimate is shared by neighbours):
    # the spread of the minima of CALIBRATION_BLOCKS contiguous blocks (their parabolas through
    # the stencil) bounds sigma from below, sigma_blocks = std / sqrt(blocks)
    minima = []
    for block in np.array_split(np.arange(len(chosen)), CALIBRATION_BLOCKS):
        c0, c1, c2 = (float(st[block].sum()) for st in stencil)
        cb = (c2 - 2.0 * c1 + c0) / h**2
        if cb > 0:
            minima.append(x0 - (c2 - c0) / (2.0 * h) / cb)
    if len(minima) > 1:
        sigma = max(sigma, float(np.std(minima, ddof=1)) / math.sqrt(len(minima)))
    if not math.isfinite(sigma):
        log_.warning("readout calibration: flat cost profile (does the camera move?)")
    profile = sorted((x, float(v[0].sum())) for x, v in cache.items())
    return ReadoutCalibration(best, sigma, len(chosen), chi2 / dof if dof > 0 else math.nan, profile)


UNDECLARED_CHECK_CHI2_DOF = 1.5
"""`check_undeclared_readout` runs when the floor camera's PnP chi^2 / dof (the flight's corner
noise scale, variance.scale_pnp_trajectory_by_class) is above this: a readout the model ignores
shows as corners scattered beyond their covariance (simulated 20 s flights declared global
shutter: 5 ms readout, realistic effects 2.9; 10 ms at 1 m/s 59; 30 ms at 2 m/s 5,969)."""
UNDECLARED_FRAMES = 150
"""... on the frames that move most, at most this many (a sign test over 150 frames already
detects a 5 ms readout at p ~1e-6; the grid's PnP solves are the check's cost) ..."""
UNDECLARED_CANDIDATES = 3
"""... among at most this many times as many frames spread over the flight ..."""
UNDECLARED_GRID = 8
"""... on this many readouts in (0, one frame period] besides 0 ..."""
UNDECLARED_P_VALUE = 1e-6
"""... and reports one when more of the frames fit better with it than without than a coin
would give (sign test, one-sided p below this) ..."""
UNDECLARED_MIN_COST_DROP = 0.1
"""... and the frames' median chi^2 / dof falls by at least this share (a 5 ms readout under
the realistic effects: 1.95 -> 1.61, 212 of 299 frames better, p 2e-13; clipping x2.2 with
defocus 1 on a global shutter: 119 of 293 better, p 0.999)."""


@dataclass
class UndeclaredReadout:
    """`check_undeclared_readout`'s finding: the best readout of its grid (s, one round from the
    uncorrected poses: an indication, not a calibration), frames used and how many fit better
    with it, the frames' median chi^2 / dof without and with it, the sign test's p-value."""

    readout_s: float
    n_frames: int
    n_better: int
    chi2_per_dof_global: float
    chi2_per_dof_rolling: float
    p_value: float


def check_undeclared_readout(
    det,
    camera: CameraModel,
    world: World,
    imu,
    trajectory: Trajectory,
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX,
    max_frames: int = UNDECLARED_FRAMES,
) -> UndeclaredReadout | None:
    """A floor camera declared global shutter (`camera.readout_s` 0) whose corners fit a
    rolling-shutter readout.  The frames that move most (`calibrate_readout`'s choice), their
    corners moved to the stamp with the motion of the flight's uncorrected PnP `trajectory` for
    UNDECLARED_GRID readouts up to a frame period; per frame the whitened PnP cost.  Robust by
    construction: a frame whose motion estimate is off (the uncorrected poses' velocity at a
    flight's end) can dominate a summed cost -- it did, sending `calibrate_readout`'s first round
    to 18.4 ms on a 5 ms flight -- but it is one vote in the sign test and one value in a median.
    Returns the finding when significant (UNDECLARED_P_VALUE, UNDECLARED_MIN_COST_DROP), else None."""
    if camera.rolling_shutter:
        return None
    frames = det.by_frame("cam0")
    stamps = np.array(sorted(frames), dtype=np.int64)
    # the fastest frames among evenly spread candidates: a long flight's motion at every frame
    # would cost more than the check (10 minutes, 18,000 frames: ~45 CPU s)
    stamps = stamps[:: max(1, len(stamps) // (UNDECLARED_CANDIDATES * max_frames))]
    motion = frame_motion(trajectory, stamps, camera, imu, level_poses=camera.gimbaled)
    try:
        chosen = _fastest_frames(frames, stamps, motion, max_frames)
    except EstimationError:
        return None
    batch = corner_batch(chosen, camera, world, motion)
    grid = np.linspace(0.0, 1.0 / max(camera.rate_hz, 1e-3), UNDECLARED_GRID + 1)
    costs, dofs = zip(
        *(_readout_cost(chosen, batch, camera, world, motion, r, corner_sigma_px) for r in grid)
    )
    cost, dof = np.array(costs), np.array(dofs)
    ok = np.all(dof > 0, axis=0)  # frames posed at every readout
    if ok.sum() < MIN_FIT_POSES:
        return None
    per_dof = np.median(cost[:, ok] / dof[:, ok], axis=1)
    g = int(np.argmin(per_dof))
    if g == 0:
        return None
    better = int(np.sum(cost[g, ok] < cost[0, ok]))
    p = float(binomtest(better, int(ok.sum()), 0.5, alternative="greater").pvalue)
    if p >= UNDECLARED_P_VALUE or per_dof[g] > (1.0 - UNDECLARED_MIN_COST_DROP) * per_dof[0]:
        return None
    readout = float(grid[g])
    if g < UNDECLARED_GRID:  # the parabola through the grid minimum and its neighbours
        c0, c1, c2 = per_dof[g - 1 : g + 2]
        if c0 + c2 - 2.0 * c1 > 0:
            readout += 0.5 * (c0 - c2) / (c0 + c2 - 2.0 * c1) * float(grid[1] - grid[0])
    return UndeclaredReadout(readout, int(ok.sum()), better, float(per_dof[0]), float(per_dof[g]), p)
