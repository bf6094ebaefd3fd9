"""Camera-body rotations: a small rotation error of the floor camera's T_body_cam, estimated in
the batch smoother, and of the front camera's, against the floor camera's poses
(`estimate_front_mount`, its own docstring).

Model.  The log's mount T_body_cam = [R_bc, t_bc] (sensor.yaml T_BS) is off by a small rotation
of the camera about its own centre, expressed in the body frame:

    T_body_cam_true = [exp(w^) R_bc, t_bc],    w = the mount's rotation error (rad, body x/y/z).

PnP measures the camera's true pose T_world_cam; the per-frame estimators turn it into a body
pose with the nominal mount, so a PnP pose is

    Z_k = T_world_cam T_body_cam^-1 = X_k T_body_cam_true T_body_cam^-1 = X_k E(w),
    E(w) = A [exp(w^), 0] A^-1 = [exp(w^), t_bc - exp(w^) t_bc],    A = [I, t_bc],

a constant body-frame error (rotation, plus the lever arm swung by it).  Here the batch smoother's
graph (`smoother.build_problem`: IMU preintegration, biases, velocity, robust PnP factors) gets
one Rot3 variable E0 = exp(w^) with a weak zero-mean prior (`prior_sigma_deg`), and each PnP
pose factor Local(Z_k, X_k) is replaced by Local(Z_k, X_k E(w)) with the same (robust) noise model
(`mount_pose_factor`: analytic Jacobians chained from GTSAM's Pose3 compose / localCoordinates).
The estimate is the solution's w, its covariance the marginal of E0 (E0 ordered last, so it is
the root of the Bayes tree), inflated by sqrt(chi^2 / dof) when the fit is worse than its noise
model says (as timeoffset._inflate).

Observability (what separates w from the other states).  PnP alone cannot: the camera's pose is
right whatever w is; only the IMU sees the body's attitude.
- roll / pitch of the mount (tilt about body x / y): the accelerometer's gravity direction says
  the body's true tilt, PnP's says the true tilt plus w.  At hover the difference is a constant
  body-frame specific force g x w, exactly what an accelerometer bias of |g w| looks like (2 deg ~
  0.34 m/s^2; the prior on the bias is 0.1 m/s^2, the simulated IMU's 0.03 m/s^2), so a hovering
  flight pins the tilt only through the bias prior.  Under acceleration a (or body tilt) the
  mount error rotates the measured a too (error w x a, changing with the motion) while a bias
  stays constant: horizontal accelerations make roll / pitch separable.
- yaw of the mount (about body z): gravity says nothing about yaw; a yaw error d makes the IMU's
  horizontal accelerations, rotated into the world with PnP's yaw, point d off the direction in
  which PnP's positions accelerate.  Horizontal accelerations against positions observe it; a
  flight at constant velocity (or hovering) does not.
- the lever arm (I - exp(w^)) t_bc adds a little through positions (t_bc = 8 cm: 2.7 mm at 2 deg).
An axis the flight does not excite keeps a sigma near the prior's (reported, with a note), and the
check below then cannot call it significant: a large sigma, not a confident wrong number.

The check (always on, one smoother solve without covariances of the states): an estimate is
significant on an axis when |w_i| > `significant_sigmas` sigma_i and |w_i| > `min_significant_deg`;
then a named, counted warning (`extrinsic_rotation_bias`) says to run --calibrate-extrinsics, which
applies the correction on the significant axes (`MountRotation.correction_rad`: their estimate
given the other axes held at zero) to the floor camera (`corrected_camera`) and re-runs the
per-frame estimators and the fusion.  The pipeline calibrates before estimating the time offsets
(the front camera's offset profile hangs the camera from the fused body: a 2 deg yaw error of the
floor mount read as a 2.8 ms front offset in a 20 s simulated flight); the check alone runs after
them, on the final stamps (a 10 ms floor offset moves the estimate by ~0.02 deg, synthetic).
Not supported: a gimbaled floor camera (its PnP poses are level-frame poses) and the paper's
position + yaw poses (no attitude measured).
"""

from __future__ import annotations

import copy
import csv
import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import gtsam
import numpy as np

from fusion.camera import CameraModel
from fusion.errors import EstimationError, first_line
from fusion.estimate.common import (
    LOAD_INTERP_MAX_GAP_S,
    FusionConfig,
    RawPoseInput,
    SolveHealth,
    interpolable_load_times,
)
from fusion.estimate.correlation import correlation_time, group_frame_keys
from fusion.estimate.factors import X
from fusion.estimate.smoother import (
    FactorKind,
    build_problem,
    gate_outliers,
    jumped_fixes,
    poses_of,
    robust_distances,
    solve,
)
from fusion.estimate.timeoffset import seen_twice, usable_sightings
from fusion.fileio import atomic_open
from fusion.geometry import PoseInterpolator, make_T, skew_stack, so3_exp, so3_log
from fusion.log.euroc import FlightLog, ImuData, LogWarning, VelocityData
from fusion.types import CameraRole, Choice, Estimator, LoadObservation, Trajectory, role_name

log = logging.getLogger(__name__)

E = gtsam.symbol_shorthand.E  # E(0): the floor camera's mount rotation error (Rot3)
WARNING_NAME = "extrinsic_rotation_bias"
FRONT_WARNING_NAME = "front_extrinsic_rotation_bias"
IMPLAUSIBLE_WARNING_NAME = "mount_check_implausible"
MAX_CORRECTION_DEG = 10.0
"""A mount check reading a rotation larger than this is not a calibration error to correct: a
T_BS in another axis convention, a camera in the other camera's role, or images that do not
follow the motion (a frozen camera read as a 77 deg mount, thirty-first session's audit).
--calibrate-extrinsics does not apply it; the warning IMPLAUSIBLE_WARNING_NAME says so."""
LARGE_CORRECTION_DEG = 3.0
"""An applied mount correction above this is named (`mount_correction_large`): a camera bolted to
its frame is rarely this far off, and a misfit the correction can absorb, such as a load code 10 %
larger than world.yaml says, read as a 4.5 deg front pitch and was applied with no warning (the
thirty-second session's audit).  The benchmarks' mount errors are 0.05-2 deg."""
LARGE_WARNING_NAME = "mount_correction_large"
AXES = ("x", "y", "z")
EXTRINSICS_GROUNDTRUTH_CSV = "extrinsics_groundtruth.csv"  # the simulator's true mount errors
GROUNDTRUTH_COLUMNS = ["camera", "rx_deg", "ry_deg", "rz_deg"]
NOMINAL_MOUNT_SIGMA_RAD = 1e-8
"""The prior holding E0 at the nominal mount in nominal_mount_trajectory (a constraint in effect:
the PnP attitudes' sigma is ~1e-3 rad)."""
FRONT_MOUNT_MIN_SIGHTINGS = 20  # of loads seen twice or more (estimate_front_mount)
FRONT_MOUNT_MAX_ITERATIONS = 30
FRONT_MOUNT_STEP_TOL_RAD = 1e-9
FRONT_MOUNT_MAX_HALVINGS = 20
FRONT_MOUNT_MAX_GAP_FRAMES = 2.5
"""estimate_front_mount interpolates the PnP body pose over at most this many of their median
frame intervals (one missing frame; and at most LOAD_INTERP_MAX_GAP_S): the sweep's pincushion
flight (30 fps) read a false front pitch of 0.151 +- 0.043 deg from 20 of 153 sightings placed
across 200 ms gaps, 0.032 +- 0.043 without them (BENCHMARKS.md, twenty-fourth session)."""
FRONT_MOUNT_MAX_LAG = 20
"""Frames of lag over which estimate_front_mount measures its residuals' correlation time (as
fusion.estimate.correlation.MAX_LAG for the PnP residuals)."""
FRONT_MOUNT_MIN_SIGNIFICANT_DEG = 0.03
"""estimate_front_mount's floor on a significant axis (with its 3 sigma), below the floor
camera's 0.1 deg: the load sightings see far less than the IMU does (a 0.15 deg roll of the front
camera made the batch smoother's pose NEES 149), and a flight without a mount error reads at
most 0.014 deg (BENCHMARKS.md, twenty-third session)."""
FRONT_MOUNT_TRAJECTORY_SIGMA_DEG = 0.01
"""Added in quadrature to each axis' sigma of estimate_front_mount: the PnP body poses it takes
as exact carry their attitude's error (~0.01 deg), common to the sightings near each pose.
Without it, flights with no mount error read up to 0.014 deg against a fit's sigma of
0.001-0.007 (6.5 sigma on the 10-minute flight: BENCHMARKS.md, twenty-third session)."""


class MountSource(Choice):
    """What became of a camera's mount check."""

    ESTIMATED = "estimated"
    NOT_ESTIMATED = "not_estimated"  # with the reason in `note`


@dataclass
class ExtrinsicsConfig:
    """Every tuning number of the mount-rotation estimate.

    `prior_sigma_deg`: zero-mean prior on each axis of w; weak against any excited axis (the
    PnP attitude alone is ~0.05 deg per frame), and the sigma an unexcited axis reports.
    `unexcited_fraction`: an axis whose posterior sigma exceeds this fraction of the prior's is
    named as not excited by the flight.  `significant_sigmas` / `min_significant_deg`: the check's
    test, per axis.  The floor 0.1 deg is twice the calibration's accuracy target (0.05 deg, the
    benchmark's): a correction smaller than what the calibration itself can deliver is not worth
    a recalibration, and 0.1 deg of tilt leaks 0.017 m/s^2 of gravity into the horizontal, below
    the simulated IMU's accelerometer bias (0.03 m/s^2) that the smoother estimates anyway."""

    prior_sigma_deg: float = 5.0
    unexcited_fraction: float = 0.5
    significant_sigmas: float = 3.0
    min_significant_deg: float = 0.1


# =========================================================================== the factor


def mount_transform(A: gtsam.Pose3, R_err: gtsam.Rot3) -> tuple[gtsam.Pose3, np.ndarray]:
    """The mount error E = A [R_err, 0] A^-1 (A = [I, t_bc], module docstring) and its Jacobian
    (6x3) with respect to R_err, chained from GTSAM's Pose3 compose."""
    H_a, H_q, H_e1, H_ai = (np.zeros((6, 6), order="F") for _ in range(4))
    E1 = A.compose(gtsam.Pose3(R_err, np.zeros(3)), H_a, H_q)
    Ek = E1.compose(A.inverse(), H_e1, H_ai)
    # Pose3([R exp(w), 0]) = Pose3([R, 0]) Pose3([exp(w), 0]): the tangent [w, 0]
    return Ek, (H_e1 @ H_q)[:, :3]


def mount_pose_error(
    Z: gtsam.Pose3, A: gtsam.Pose3, X_k: gtsam.Pose3, R_err: gtsam.Rot3, want_jacobians: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Residual Local(Z, X_k E) (6,) of a PnP body pose Z against the state X_k seen through the
    mount error E = A [R_err, 0] A^-1 (A = [I, t_bc], module docstring), and its Jacobians
    (6x6 on X_k, 6x3 on R_err), chained from GTSAM's Pose3 compose / localCoordinates."""
    return _mount_pose_error(Z, X_k, *mount_transform(A, R_err), want_jacobians)


def _mount_pose_error(
    Z: gtsam.Pose3, X_k: gtsam.Pose3, Ek: gtsam.Pose3, H_ew: np.ndarray, want_jacobians: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """mount_pose_error given E and its Jacobian H_ew (mount_transform)."""
    if not want_jacobians:
        return Z.localCoordinates(X_k.compose(Ek)), None, None
    H_x, H_e, H_z, H_p = (np.zeros((6, 6), order="F") for _ in range(4))
    P = X_k.compose(Ek, H_x, H_e)
    e = Z.localCoordinates(P, H_z, H_p)
    return e, H_p @ H_x, H_p @ H_e @ H_ew


class MountTransformCache:
    """mount_transform for one mount translation t_bc, computed once per value of the mount
    variable: every PnP factor of a linearisation sees the same E(0), so its factors share E
    and dE/dw instead of composing them again each (two Pose3 compositions with Jacobians of
    the four per factor evaluation)."""

    def __init__(self, t_body_cam: np.ndarray) -> None:
        self.A = gtsam.Pose3(gtsam.Rot3(), np.asarray(t_body_cam, float))
        self._key: bytes | None = None
        self._value: tuple[gtsam.Pose3, np.ndarray] | None = None

    def __call__(self, R_err: gtsam.Rot3) -> tuple[gtsam.Pose3, np.ndarray]:
        key = R_err.matrix().tobytes()
        if key != self._key or self._value is None:
            self._key, self._value = key, mount_transform(self.A, R_err)
        return self._value


def mount_pose_factor(
    k: int,
    Z_world_body: np.ndarray,
    t_body_cam: np.ndarray,
    model: gtsam.noiseModel.Base,
    cache: MountTransformCache | None = None,
) -> gtsam.CustomFactor:
    """PnP pose factor on X(k) and the mount error E(0): Local(Z, X(k) E(w)) with `model` (the
    PriorFactorPose3's, robust kernel included).  `cache`: E(w) shared with the other factors
    of the same mount (MountTransformCache for `t_body_cam`)."""
    Z = gtsam.Pose3(np.asarray(Z_world_body, float))
    transform = cache if cache is not None else MountTransformCache(t_body_cam)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None):
        keys = this.keys()
        e, Hx, Hr = _mount_pose_error(
            Z, values.atPose3(keys[0]), *transform(values.atRot3(keys[1])), H is not None
        )
        if H is not None:
            H[0], H[1] = Hx, Hr
        return e

    return gtsam.CustomFactor(model, [X(k), E(0)], error)


def corrected_mount(T_body_cam: np.ndarray, rotvec_rad: np.ndarray) -> np.ndarray:
    """T_body_cam with its rotation turned by exp(rotvec^) in the body frame about the camera's
    centre: [exp(w^) R_bc, t_bc] (module docstring)."""
    T = np.asarray(T_body_cam, float)
    return make_T(so3_exp(np.asarray(rotvec_rad, float)) @ T[:3, :3], T[:3, 3])


def corrected_camera(camera: CameraModel, rotvec_rad: np.ndarray) -> CameraModel:
    """A copy of `camera` with the mount corrected by `rotvec_rad` (corrected_mount)."""
    return replace(camera, T_body_cam=corrected_mount(camera.T_body_cam, rotvec_rad))


# =========================================================================== estimate


@dataclass
class MountRotation:
    """A camera's mount rotation error: T_body_cam_true = [exp(w^) R_bc, t_bc], w in the body
    frame (rad); RunResult.extrinsics, metrics.json `extrinsics`."""

    camera: str  # CameraRole value
    source: MountSource
    rotvec_rad: np.ndarray | None = None  # (3,) w, body x / y / z
    cov_rad2: np.ndarray | None = None  # (3, 3)
    significant_axes: list[str] = field(default_factory=list)
    applied: bool = False  # the correction was applied to every output (--calibrate-extrinsics)
    unexcited_axes: list[str] = field(default_factory=list)
    note: str = ""
    fixes: int = 0
    iterations: int = 0
    time_s: float = 0.0
    # the fit's residuals' integrated correlation time in frames, its covariance's factor (the
    # front check; 1: white, or not measured)
    correlation_time: float = 1.0

    @property
    def sigma_rad(self) -> np.ndarray | None:
        return None if self.cov_rad2 is None else np.sqrt(np.maximum(np.diag(self.cov_rad2), 0.0))

    @property
    def significant(self) -> bool:
        return bool(self.significant_axes)

    @property
    def correction_rad(self) -> np.ndarray | None:
        """The rotation --calibrate-extrinsics applies (3,): the significant axes S at their
        estimate given the other axes O held at 0, w_S - C_SO C_OO^-1 w_O (the Gaussian
        conditional mean), zero on O: an axis the flight did not pin down keeps the logged mount
        rather than taking a poorly determined value.  None when nothing is significant."""
        if self.rotvec_rad is None or self.cov_rad2 is None or not self.significant:
            return None
        S = [i for i, a in enumerate(AXES) if a in self.significant_axes]
        O = [i for i in range(3) if i not in S]
        out = np.zeros(3)
        out[S] = self.rotvec_rad[S]
        if O:
            C = self.cov_rad2
            out[S] -= C[np.ix_(S, O)] @ np.linalg.solve(C[np.ix_(O, O)], self.rotvec_rad[O])
        return out

    def as_dict(self, truth_rad: np.ndarray | None = None) -> dict:
        """JSON-ready; with the simulator's `truth_rad` (3,), the estimate's error too."""
        sig = self.sigma_rad
        out = {
            "camera": self.camera,
            "source": str(self.source),
            "rotvec_deg": None if self.rotvec_rad is None else np.degrees(self.rotvec_rad).tolist(),
            "sigma_deg": None if sig is None else np.degrees(sig).tolist(),
            "angle_deg": None
            if self.rotvec_rad is None
            else math.degrees(float(np.linalg.norm(self.rotvec_rad))),
            "significant_axes": list(self.significant_axes),
            "correction_deg": None
            if self.correction_rad is None
            else np.degrees(self.correction_rad).tolist(),
            "unexcited_axes": list(self.unexcited_axes),
            "applied": self.applied,
            "fixes": self.fixes,
            "iterations": self.iterations,
            "time_s": self.time_s,
            "correlation_time": self.correlation_time,
            "note": self.note,
        }
        if truth_rad is not None:
            out["truth_deg"] = np.degrees(np.asarray(truth_rad, float)).tolist()
            if self.rotvec_rad is not None:
                # the rotation between truth and estimate (exact, not a difference of vectors)
                err = so3_log(so3_exp(self.rotvec_rad) @ so3_exp(np.asarray(truth_rad, float)).T)
                out["error_deg"] = np.degrees(err).tolist()
            if self.correction_rad is not None:
                err = so3_log(so3_exp(self.correction_rad) @ so3_exp(np.asarray(truth_rad, float)).T)
                out["correction_error_deg"] = np.degrees(err).tolist()
        return out

    @property
    def role(self) -> str:
        return role_name(self.camera)

    @property
    def warning_name(self) -> str:
        return FRONT_WARNING_NAME if self.camera == CameraRole.FRONT.value else WARNING_NAME

    def describe(self) -> str:
        """One line: `mount rotation cam0 (floor): x +2.01 ± 0.02, y ... deg; applied`."""
        head = f"mount rotation {self.camera} ({self.role})"
        if self.rotvec_rad is None or self.sigma_rad is None:
            return f"{head}: not estimated ({self.note})"
        w, s = np.degrees(self.rotvec_rad), np.degrees(self.sigma_rad)
        axes = ", ".join(f"{a} {v:+.3f} ± {d:.3f}" for a, v, d in zip(AXES, w, s))
        if self.applied and self.correction_rad is not None:
            used = "applied: " + ", ".join(
                f"{a} {v:+.3f}"
                for a, v in zip(AXES, np.degrees(self.correction_rad))
                if a in self.significant_axes
            )
        elif self.implausible:
            used = f"beyond a calibration error (> {MAX_CORRECTION_DEG:g} deg), not applied"
        elif self.significant:
            used = "significant, not applied (run with --calibrate-extrinsics)"
        else:
            used = "not significant"
        extra = (
            f"; not excited by the flight: {', '.join(self.unexcited_axes)}" if self.unexcited_axes else ""
        )
        note = f"; {self.note}" if self.note else ""
        return f"{head}: {axes} deg; {used}{extra}{note}"

    @property
    def angle_deg(self) -> float:
        """The estimated rotation's angle (0 when not estimated)."""
        return 0.0 if self.rotvec_rad is None else math.degrees(float(np.linalg.norm(self.rotvec_rad)))

    @property
    def implausible(self) -> bool:
        """Significant and larger than MAX_CORRECTION_DEG: not a mount error to correct."""
        return self.significant and self.angle_deg > MAX_CORRECTION_DEG

    def implausible_warning(self) -> LogWarning:
        """The named warning for an `implausible` reading (never applied)."""
        front = self.camera == CameraRole.FRONT.value
        what = (
            "load sightings disagree with the floor camera and the IMU"
            if front
            else "poses disagree with the IMU"
        )
        return LogWarning(
            IMPLAUSIBLE_WARNING_NAME,
            1,
            f"the {self.role} camera's ({self.camera}) {what} by a {self.angle_deg:.1f} deg "
            f"rotation, beyond any mount calibration error (> {MAX_CORRECTION_DEG:g} deg): not applied. "
            "Check that T_BS is in the EuRoC convention (body from camera), that the cameras are not "
            "swapped, that the images follow the motion (a frozen camera, repeated frames), and the "
            "camera's intrinsics (another resolution's, cu / cv swapped) and the IMU's axes",
        )

    def large_correction_warning(self) -> LogWarning | None:
        """`mount_correction_large` when the correction applied is above LARGE_CORRECTION_DEG,
        else None."""
        c = self.correction_rad
        if not self.applied or c is None:
            return None
        angle = math.degrees(float(np.linalg.norm(c)))
        if angle <= LARGE_CORRECTION_DEG:
            return None
        front = self.camera == CameraRole.FRONT.value
        others = (
            "world.yaml's load_qr side_m, the front camera's intrinsics or distortion"
            if front
            else "world.yaml's floor_qr side_m or payload_unit_m, the floor camera's intrinsics, "
            "the IMU's axes"
        )
        return LogWarning(
            LARGE_WARNING_NAME,
            1,
            f"the {self.role} camera's ({self.camera}) mount was corrected by {angle:.1f} deg "
            f"(--calibrate-extrinsics), more than a mount is usually off (> {LARGE_CORRECTION_DEG:g} "
            f"deg): if the camera sits as T_BS says, the correction hides another error: {others}",
        )

    def warning(self) -> LogWarning | None:
        """The check's named, counted warning (count: significant axes), or None."""
        if not self.significant or self.applied or self.rotvec_rad is None:
            return None
        w = np.degrees(self.rotvec_rad)
        s = np.degrees(self.sigma_rad) if self.sigma_rad is not None else np.zeros(3)
        parts = ", ".join(
            f"{a} {w[i]:+.2f} ± {s[i]:.2f} deg" for i, a in enumerate(AXES) if a in self.significant_axes
        )
        if self.camera == CameraRole.FRONT.value:
            what = (
                f"the front camera's load sightings disagree with the floor camera and the IMU by a "
                f"constant rotation of its mount ({parts}): one camera's T_BS, or its intrinsics, "
                "looks off"
            )
        else:
            what = (
                f"the floor camera's PnP attitudes disagree with the IMU by a constant rotation ({parts}): "
                "sensor.yaml's T_BS looks off"
            )
        return LogWarning(
            self.warning_name,
            len(self.significant_axes),
            f"{what}; run with --calibrate-extrinsics to estimate and apply it",
        )


def estimate_mount_rotation(
    frame_t: np.ndarray,
    imu: ImuData | None,
    raw: Trajectory,
    velocity: VelocityData | None,
    floor_camera: CameraModel,
    config: ExtrinsicsConfig | None = None,
    fusion_config: FusionConfig | None = None,
) -> MountRotation:
    """The floor camera's mount rotation error from its PnP poses `raw` (with covariances) and
    the IMU / velocity, by the batch smoother with a Rot3 variable (module docstring).
    EstimationError when it cannot be estimated (no IMU, a gimbaled camera, poses without
    attitude, a singular graph)."""
    return estimate_mount_and_trajectory(frame_t, imu, raw, velocity, floor_camera, config, fusion_config)[0]


def _classify(out: MountRotation, config: ExtrinsicsConfig) -> MountRotation:
    """`out` with its significant axes (|w| > significant_sigmas sigma and > min_significant_deg)
    and its unexcited ones (sigma > unexcited_fraction of the prior's) named."""
    w, sig = out.rotvec_rad, out.sigma_rad
    assert w is not None and sig is not None
    prior_rad = math.radians(config.prior_sigma_deg)
    floor_rad = math.radians(config.min_significant_deg)
    out.significant_axes = [
        a
        for a, wi, si in zip(AXES, w, sig)
        if abs(wi) > config.significant_sigmas * si and abs(wi) > floor_rad
    ]
    out.unexcited_axes = [a for a, si in zip(AXES, sig) if si > config.unexcited_fraction * prior_rad]
    return out


def merge_mount_rotations(
    parts: list[MountRotation], config: ExtrinsicsConfig | None = None
) -> MountRotation:
    """One mount estimate from estimates on disjoint stretches of a flight (fusion.estimate.window:
    a long flight solved in windows).  Each part is Gaussian, w_i ~ N(w, C_i), and each carries
    the same zero-mean prior P = prior_sigma^2 I once; the combined information counts it once:
    C^-1 = P^-1 + sum (C_i^-1 - P^-1)_+ (each part's own information, negative eigenvalues
    clipped), w = C sum C_i^-1 w_i (the prior's mean is 0).  Fixes and
    iterations add up; the axes are classified again from the combined sigma."""
    config = config or ExtrinsicsConfig()
    if not parts:
        raise EstimationError("no mount estimate to merge")
    if len(parts) == 1:
        return parts[0]
    infos = [np.linalg.inv(np.asarray(p.cov_rad2, float)) for p in parts]
    prior_info = np.eye(3) / math.radians(config.prior_sigma_deg) ** 2
    info = prior_info.copy()
    for i in infos:
        # the part's own information: an unexcited axis, its sigma inflated by the fit's
        # chi2/dof, can sit below the prior's; that part then adds nothing on it, not less
        lam, vec = np.linalg.eigh(0.5 * (i + i.T) - prior_info)
        info += (vec * np.maximum(lam, 0.0)) @ vec.T
    cov = np.linalg.inv(info)
    cov = 0.5 * (cov + cov.T)
    w = cov @ sum(i @ np.asarray(p.rotvec_rad, float) for i, p in zip(infos, parts))
    notes = [p.note for p in parts if p.note]
    out = MountRotation(
        parts[0].camera,
        MountSource.ESTIMATED,
        w,
        cov,
        fixes=sum(p.fixes for p in parts),
        iterations=sum(p.iterations for p in parts),
        note="; ".join(notes),
        time_s=sum(p.time_s for p in parts),
    )
    return _classify(out, config)


def estimate_mount_and_states(
    frame_t: np.ndarray,
    imu: ImuData | None,
    raw: Trajectory,
    velocity: VelocityData | None,
    floor_camera: CameraModel,
    config: ExtrinsicsConfig | None = None,
    fusion_config: FusionConfig | None = None,
) -> tuple[MountRotation, Trajectory | None, gtsam.Values | None]:
    """estimate_mount_and_trajectory, plus the fixed-mount solution's states X(k), V(k), B(k)
    (gtsam.Values, the mount variable removed; None with the trajectory): the batch smoother's
    warm start on these frames (smoother.smooth(warm_start=), fusion.pipeline.SharedWholeFlight)."""
    config = config or ExtrinsicsConfig()
    fusion_config = fusion_config or FusionConfig()
    t0 = time.perf_counter()
    floor = CameraRole.FLOOR.value
    if imu is None:
        raise EstimationError("no IMU: the floor camera's mount rotation cannot be estimated")
    if floor_camera.gimbaled:
        raise EstimationError("a gimbaled floor camera: its mount rotation is not estimated")
    if raw is None or len(raw) < 2:
        raise EstimationError("fewer than two floor-code fixes: the mount rotation cannot be estimated")
    pcfg = replace(
        fusion_config,
        compute_covariances=False,
        tight=False,
        noise_scale_iterations=0,
        check_noise=False,
    )
    pb = build_problem(frame_t, imu, raw, None, None, velocity, pcfg, floor_camera=floor_camera)
    if pb.raw_input is not RawPoseInput.POSE6:
        raise EstimationError("the fixes carry no attitude: the mount rotation cannot be estimated")
    t_bc = floor_camera.T_body_cam[:3, 3]
    transform = MountTransformCache(t_bc)
    n_fixes = 0
    for i, r in pb.robust.items():
        if r.kind is FactorKind.POSE:
            old = pb.factors[i]
            k = pb.factor_frame[i]
            pb.factors[i] = mount_pose_factor(k, old.prior().matrix(), t_bc, old.noiseModel(), transform)
            n_fixes += 1
    if n_fixes < 2:
        raise EstimationError("fewer than two PnP pose factors: the mount rotation cannot be estimated")
    prior = gtsam.PriorFactorRot3(
        E(0), gtsam.Rot3(), gtsam.noiseModel.Isotropic.Sigma(3, math.radians(config.prior_sigma_deg))
    )
    pb.add(prior, 0)
    pb.initial.insert(E(0), gtsam.Rot3())

    health = SolveHealth()
    suspects = jumped_fixes(pb, pcfg)
    graph = pb.graph(suspects)
    ordering = gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, [E(0)])
    errors: list[float] = []
    res, graph, ordering = solve(graph, pb.initial, pcfg, health, ordering, errors)
    values, iterations = res.values, res.iterations
    drop, dropped_loads, _ = gate_outliers(pb, robust_distances(pb, values), pcfg, health)
    if drop != suspects:
        graph = pb.graph(drop)
        ordering = gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, [E(0)])
        res, graph, ordering = solve(graph, values, pcfg, health, ordering, errors)
        values = res.values
        iterations += res.iterations
    w = so3_log(values.atRot3(E(0)).matrix())
    try:
        lin = graph.linearize(values)
        cov = np.asarray(lin.eliminateMultifrontal(ordering).marginalCovariance(E(0)), float)
    except (RuntimeError, ValueError) as e:
        raise EstimationError(
            f"no covariance of the mount rotation: the system is singular ({first_line(e)})"
        ) from None
    # residual degrees of freedom: the fixes' 6 dimensions (the IMU's are taken up by the states)
    used = n_fixes - len([i for i in drop if pb.robust[i].kind is FactorKind.POSE])
    dof = 6 * used - 3
    if dof > 0:
        cov = cov * max(1.0, 2.0 * errors[-1] / dof)
    out = _classify(
        MountRotation(floor, MountSource.ESTIMATED, w, cov, fixes=used, iterations=iterations), config
    )
    sig = out.sigma_rad
    assert sig is not None
    if health.reasons:
        out.note = "; ".join(health.reasons)
    out.time_s = time.perf_counter() - t0
    log.info(
        "floor camera mount rotation: %s deg (sigma %s deg), %d fixes, %.2f s",
        np.round(np.degrees(w), 3),
        np.round(np.degrees(sig), 3),
        used,
        out.time_s,
    )
    states = None
    if not health.gate_skipped:
        try:
            states = nominal_mount_values(lin, values, ordering)
        except (RuntimeError, ValueError) as e:
            log.debug("no fixed-mount trajectory from the mount solve: %s", e)
    if states is None:
        return out, None, None
    n = len(pb.frame_t)
    trajectory = Trajectory(str(Estimator.SMOOTHER), pb.frame_t.copy(), poses_of(states, n), None)
    states.erase(E(0))
    return out, trajectory, states


def estimate_mount_and_trajectory(
    frame_t: np.ndarray,
    imu: ImuData | None,
    raw: Trajectory,
    velocity: VelocityData | None,
    floor_camera: CameraModel,
    config: ExtrinsicsConfig | None = None,
    fusion_config: FusionConfig | None = None,
) -> tuple[MountRotation, Trajectory | None]:
    """estimate_mount_rotation, plus the whole flight's body trajectory T_world_body at the frame
    times `frame_t` with the logged mount (no covariances; Estimator.SMOOTHER): the batch
    smoother's fixed-mount trajectory recovered from this solve by one Gauss-Newton step
    (nominal_mount_trajectory), so that one whole-flight solve serves both the mount check and
    the front camera's time-offset profile (fusion.pipeline.SharedWholeFlight).  The trajectory
    is None when most fixes disagreed with the IMU (health.gate_skipped: the plain smoother
    would solve again without the IMU, which this solve does not) or that step failed."""
    mount, trajectory, _ = estimate_mount_and_states(
        frame_t, imu, raw, velocity, floor_camera, config, fusion_config
    )
    return mount, trajectory


def nominal_mount_values(
    lin: gtsam.GaussianFactorGraph, values: gtsam.Values, ordering: gtsam.Ordering
) -> gtsam.Values:
    """The batch smoother's states with the logged (nominal) mount, from the mount solve's
    solution `values` (E0 = exp(w^) free) and its linearisation `lin` there: one Gauss-Newton
    step with E0 held at the identity by a tight prior (NOMINAL_MOUNT_SIGMA_RAD; the step to it in
    E0's local coordinates is -w).  At the free optimum the gradient is zero, so the step moves the
    states only by what fixing E0 implies: the fixed-mount optimum up to second order in w
    (|w| ~ its sigma, hundredths of a degree, when the mount is right).  Every key of `values`."""
    w = so3_log(values.atRot3(E(0)).matrix())
    system = lin.clone()
    hold = gtsam.noiseModel.Isotropic.Sigma(3, NOMINAL_MOUNT_SIGMA_RAD)
    system.push_back(gtsam.JacobianFactor(E(0), np.eye(3), -w, hold))
    return values.retract(system.eliminateMultifrontal(ordering).optimize())


def nominal_mount_trajectory(
    lin: gtsam.GaussianFactorGraph, values: gtsam.Values, ordering: gtsam.Ordering, frame_t: np.ndarray
) -> Trajectory:
    """nominal_mount_values' poses: (N, 4, 4) T_world_body at `frame_t`, no covariances."""
    fixed = nominal_mount_values(lin, values, ordering)
    return Trajectory(str(Estimator.SMOOTHER), frame_t.copy(), poses_of(fixed, len(frame_t)), None)


def check_mount(
    log_: FlightLog,
    raw: Trajectory | None,
    config: ExtrinsicsConfig | None = None,
    fusion_config: FusionConfig | None = None,
) -> MountRotation:
    """The floor camera's mount check for a run: the estimate, or NOT_ESTIMATED with the reason."""
    floor = CameraRole.FLOOR.value
    try:
        if raw is None or len(raw) == 0 or raw.covariances is None:
            raise EstimationError("no PnP pose with a covariance: the mount rotation cannot be estimated")
        return estimate_mount_rotation(
            log_.floor.timestamps_ns,
            log_.imu,
            raw,
            log_.velocity,
            log_.floor.camera,
            config,
            fusion_config,
        )
    except EstimationError as e:
        return MountRotation(floor, MountSource.NOT_ESTIMATED, note=str(e))


def apply_mount(log_: FlightLog, mount: MountRotation) -> FlightLog:
    """A copy of the log whose floor camera carries the corrected mount (`mount.correction_rad`;
    frames still stream from the same files); marks `mount` applied."""
    correction = mount.correction_rad
    if correction is None:
        return log_
    cams = dict(log_.cameras)
    stream = copy.copy(cams[mount.camera])
    stream.camera = corrected_camera(stream.camera, correction)
    cams[mount.camera] = stream
    mount.applied = True
    return replace(log_, cameras=cams)


# =========================================================================== the front camera


def estimate_front_mount(
    trajectory: Trajectory,
    sightings: list[LoadObservation],
    front_camera: CameraModel,
    config: ExtrinsicsConfig | None = None,
    fusion_config: FusionConfig | None = None,
) -> MountRotation:
    """The front camera's mount rotation error f (T_body_cam_true = [exp(f^) R_bc, t_bc], body
    frame, as the floor's) in the body frame that `trajectory` defines (the floor camera's fixes
    and the IMU, fused: its attitude is the floor camera's to ~0.01 deg): each load sighting
    p_cam (camera frame, its stamp on the trajectory's clock) hung from the interpolated body
    pose, its covariance plus the nearest pose's (when the trajectory has covariances; times the
    number of sightings sharing that pose, whose common error they would otherwise count that
    many times), the loads' world positions free.  Gauss-Newton on f with the landmarks eliminated
    (Schur complement; at each step every landmark at its weighted mean, Huber-IRLS weights at
    the robust threshold as the smoother's load factors), the floor's weak prior on f
    (`prior_sigma_deg`); the covariance the reduced Hessian's inverse, inflated by sqrt(chi^2 /
    dof) when the fit is worse than its noise model (as the floor's), and by the whitened
    residuals' integrated correlation time tau over frames (a load's sightings l frames apart,
    pooled; Geyer's initial monotone sequence with its significance gate, as fusion.estimate.
    correlation does for the PnP residuals: tau = 1 when they are white): errors that persist
    over frames (a rolling shutter's motion error in the PnP poses, a corner bias of one code)
    make n sightings worth ~n / tau independent ones.  Without it a 15 ms readout with the
    cameras' clocks 4 ms off read a front pitch of 0.050 +- 0.013 deg on a flight with no mount
    error (tau 3.4 there; BENCHMARKS.md, twenty-fourth session; the error that persisted, the
    readout correction at a load code's stretched size, was then mended: tau 1.0, twenty-fifth).
    The trajectory is taken as exact (its attitude's error, ~0.01 deg, is well below any mount
    error worth correcting): FRONT_MOUNT_TRAJECTORY_SIGMA_DEG is added to each axis' sigma for
    it.

    Why: the floor camera's check (the IMU against its fixes) is blind to what the IMU cannot
    see, and a front mount error is not in it at all: a 0.5 deg roll of either camera turned the
    load sightings against the floor fixes (smoothers `diverged`, the IMU's noise scaled x2.7 and
    blamed).  This estimate sees any rotation between the two cameras.  It cannot say which of
    them is off where the IMU does not (the floor's roll at near-constant heading): with the
    floor camera off, correcting the front one instead makes the cameras agree and leaves the
    body's attitude off by the floor's error, which the floor mount's stated sigma covers.
    EstimationError with too few sightings of loads seen twice, or a gimbaled front camera."""
    config = config or ExtrinsicsConfig(min_significant_deg=FRONT_MOUNT_MIN_SIGNIFICANT_DEG)
    fusion_config = fusion_config or FusionConfig()
    front = CameraRole.FRONT.value
    t0 = time.perf_counter()
    if front_camera.gimbaled:
        raise EstimationError("a gimbaled front camera: its mount rotation is not estimated")
    ts = trajectory.timestamps_ns
    obs = usable_sightings(sightings) if len(ts) >= 2 else []
    # the body pose on a sample, or interpolated between samples at most FRONT_MOUNT_MAX_GAP_FRAMES
    # frame intervals (and LOAD_INTERP_MAX_GAP_S) apart: the PnP poses have no IMU between them,
    # and a straight line over a longer gap of a turning, accelerating drone is mm off
    dt_s = float(np.median(np.diff(ts))) * 1e-9 if len(ts) >= 2 else 0.0
    max_gap_s = min(LOAD_INTERP_MAX_GAP_S, FRONT_MOUNT_MAX_GAP_FRAMES * dt_s)
    near = interpolable_load_times(ts, np.array([o.timestamp_ns for o in obs], dtype=np.int64), max_gap_s)
    obs, ids = seen_twice([o for o, k in zip(obs, near) if k])
    if len(obs) < FRONT_MOUNT_MIN_SIGHTINGS:
        raise EstimationError(
            f"{len(obs)} sightings of loads seen twice or more (at least {FRONT_MOUNT_MIN_SIGHTINGS} "
            "needed): the front camera's mount rotation cannot be estimated"
        )
    _, group = np.unique(ids, return_inverse=True)
    n_g = int(group.max()) + 1
    t = np.array([o.timestamp_ns for o in obs], dtype=float)
    p_cam = np.array([o.p_cam for o in obs], dtype=float)
    C = np.array([o.cov_cam for o in obs], dtype=float)
    C = 0.5 * (C + np.swapaxes(C, 1, 2))
    T = PoseInterpolator(ts, trajectory.T_world_body)(t)
    R_wb = T[:, :3, :3]
    T_bc = np.asarray(front_camera.T_body_cam, float)
    v = p_cam @ T_bc[:3, :3].T  # the sighting's direction in the body frame, nominal mount
    c_w = np.einsum("nij,j->ni", R_wb, T_bc[:3, 3]) + T[:, :3, 3]  # the camera's centre
    # the body pose's own error at each sighting (its nearest sample's covariance, [r, t] body
    # frame): X -> X exp([dr, dt]) moves the sighting's world point by R_wb (-[q]x dr + dt)
    pose_cov = np.zeros((len(obs), 3, 3))
    if trajectory.covariances is not None:
        near = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)
        near -= (t - ts[near - 1]) < (ts[near] - t)
        q = v + T_bc[:3, 3]
        J = np.concatenate([-skew_stack(q), np.broadcast_to(np.eye(3), (len(obs), 3, 3))], axis=2)
        J = R_wb @ J
        Sigma = np.asarray(trajectory.covariances, float)[near]
        Sigma[~np.isfinite(Sigma).all(axis=(1, 2))] = 0.0  # a pose without a usable covariance
        # the sightings of one frame share its pose's error: each takes it n_frame times, so
        # that taken as independent they still say no more of it than one sighting would
        _, frame_of, per_frame = np.unique(near, return_inverse=True, return_counts=True)
        pose_cov = per_frame[frame_of][:, None, None] * (J @ Sigma @ np.swapaxes(J, 1, 2))
    thr = fusion_config.threshold(3)
    prior_info = np.eye(3) / math.radians(config.prior_sigma_deg) ** 2

    def bysum(x: np.ndarray) -> np.ndarray:  # per-landmark sums of (M, ...) rows
        flat = x.reshape(len(x), -1)
        out = np.stack([np.bincount(group, flat[:, c], n_g) for c in range(flat.shape[1])], axis=1)
        return out.reshape((n_g, *x.shape[1:]))

    def fit(f: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """At mount error f, each landmark at its mean weighted by w: the robust cost, the new
        Huber weights, the reduced Hessian and gradient of f (landmarks eliminated), and the
        residuals whitened by their covariance (N, 3)."""
        R_f = so3_exp(f)
        u = v @ R_f.T
        p_w = np.einsum("nij,nj->ni", R_wb, u) + c_w
        R_wc = R_wb @ (R_f @ T_bc[:3, :3])
        W = np.linalg.inv(R_wc @ C @ np.swapaxes(R_wc, 1, 2) + pose_cov)
        wW = w[:, None, None] * W
        H_LL = bysum(wW)
        landmarks = np.linalg.solve(H_LL, bysum(np.einsum("nij,nj->ni", wW, p_w))[:, :, None])[:, :, 0]
        r = p_w - landmarks[group]
        d = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, W, r), 0.0))
        cost = float(np.where(d <= thr, 0.5 * d**2, thr * (d - 0.5 * thr)).sum())
        cost += 0.5 * float(f @ prior_info @ f)
        # residual r_i = p_w(f) - L_g: d r / d delta = -R_wb [u]x (f -> log(exp(delta^) exp(f^)))
        J = -R_wb @ skew_stack(u)
        JtW = np.swapaxes(J, 1, 2) @ wW
        H_fL = bysum(-JtW)  # (G, 3, 3)
        S = (JtW @ J).sum(axis=0) + prior_info
        S -= np.einsum("gij,gjk,gkl->il", H_fL, np.linalg.inv(H_LL), np.swapaxes(H_fL, 1, 2))
        b = np.einsum("nij,nj->i", JtW, r) + prior_info @ f
        white = np.einsum("nji,nj->ni", np.linalg.cholesky(W), r)  # L^T r, W = L L^T
        return cost, np.where(d <= thr, 1.0, thr / np.maximum(d, 1e-12)), S, b, white

    try:
        f, cov, cost, iterations, white = _front_mount_irls(fit, len(obs))
    except np.linalg.LinAlgError as e:
        raise EstimationError(f"the front camera's mount rotation: a singular system ({e})") from None
    dof = 3 * (len(obs) - n_g) - 3
    if dof > 0:
        cov = cov * max(1.0, 2.0 * cost / dof)
    # sightings of one load whose errors persist over frames say less than as many independent
    # ones: the covariance times the residuals' integrated correlation time (1 when white)
    keys = group_frame_keys(group, t, FRONT_MOUNT_MAX_LAG)
    tau = correlation_time(keys, white, FRONT_MOUNT_MAX_LAG)
    cov = cov * tau
    cov = cov + np.eye(3) * math.radians(FRONT_MOUNT_TRAJECTORY_SIGMA_DEG) ** 2
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(cov))):
        raise EstimationError("the front camera's mount rotation: the fit did not converge (not finite)")
    out = _classify(
        MountRotation(
            front,
            MountSource.ESTIMATED,
            f,
            0.5 * (cov + cov.T),
            fixes=len(obs),
            iterations=iterations,
            correlation_time=tau,
        ),
        config,
    )
    out.time_s = time.perf_counter() - t0
    log.info(
        "front camera mount rotation: %s deg (sigma %s deg, residuals' correlation time %.2f "
        "frames), %d sightings of %d loads, %.2f s",
        np.round(np.degrees(f), 3),
        np.round(np.degrees(np.sqrt(np.diag(cov))), 3),
        tau,
        len(obs),
        n_g,
        out.time_s,
    )
    return out


def _front_mount_irls(fit, n: int) -> tuple[np.ndarray, np.ndarray, float, int, np.ndarray]:
    """estimate_front_mount's IRLS from f = 0: Gauss-Newton steps at fixed Huber weights, each
    halved until the cost falls; the solution, the reduced Hessian's inverse there, its robust
    cost, the iterations and the whitened residuals.  `fit(f, w)` -> (cost, next weights,
    reduced Hessian, gradient, whitened residuals) for the `n` sightings' weights w."""
    f = np.zeros(3)
    cost, w_next, S, b, _ = fit(f, np.ones(n))
    iterations = 0
    for iterations in range(1, FRONT_MOUNT_MAX_ITERATIONS + 1):
        w = w_next
        cost, _, S, b, _ = fit(f, w)
        step = -np.linalg.solve(S, b)
        for _ in range(FRONT_MOUNT_MAX_HALVINGS):
            f_new = so3_log(so3_exp(step) @ so3_exp(f))
            cost_new, w_next, S_new, b_new, _ = fit(f_new, w)
            if cost_new <= cost:
                break
            step = 0.5 * step
        else:
            break
        f, cost, S, b = f_new, cost_new, S_new, b_new
        log.debug(
            "front mount iteration %d: cost %.6g, step %.3g deg",
            iterations,
            cost,
            math.degrees(float(np.linalg.norm(step))),
        )
        if np.linalg.norm(step) < FRONT_MOUNT_STEP_TOL_RAD:
            break
    cost, _, S, _, white = fit(f, w_next)
    return f, np.linalg.inv(S), cost, iterations, white


# =========================================================================== ground truth


def write_extrinsics_groundtruth(path: Path, errors_rad: dict[str, np.ndarray]) -> None:
    """The simulator's true mount errors: `camera,rx_deg,ry_deg,rz_deg` (rotation vector w of
    T_body_cam_true = [exp(w^) R_bc, t_bc], body frame)."""
    with atomic_open(Path(path)) as f:
        out = csv.writer(f, lineterminator="\n")
        out.writerow(GROUNDTRUTH_COLUMNS)
        for cam, w in errors_rad.items():
            out.writerow([cam, *(f"{v:.9f}" for v in np.degrees(np.asarray(w, float)))])


def read_extrinsics_groundtruth(root: Path) -> dict[str, np.ndarray]:
    """{camera: w (3,) rad} from a simulated log's extrinsics_groundtruth.csv ({} without one);
    EstimationError naming file and line for a malformed row."""
    path = Path(root) / EXTRINSICS_GROUNDTRUTH_CSV
    if not path.is_file():
        return {}
    out = {}
    rows = csv.DictReader(path.read_text(encoding="utf-8").splitlines())
    for line, row in enumerate(rows, start=2):
        try:
            w = np.radians([float(row[c]) for c in GROUNDTRUTH_COLUMNS[1:]])
        except (KeyError, TypeError, ValueError):
            raise EstimationError(f"{path}:{line}: expected {','.join(GROUNDTRUTH_COLUMNS)}") from None
        if not np.all(np.isfinite(w)):
            raise EstimationError(f"{path}:{line}: not finite")
        out[str(row["camera"])] = w
    return out
