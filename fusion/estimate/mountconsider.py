"""The floor camera's mount rotation error as a consider term on the body poses (issue 10.3).

PnP measures the floor camera's pose; the body pose is T_world_body = T_world_cam T_body_cam^-1
with the logged mount.  A mount off by a rotation w (body frame, about the camera's origin:
T_body_cam_true = [Exp(w) R_bc, t_bc], fusion.estimate.extrinsics.MountRotation) gives
T_world_body_est = T_world_body [Exp(w), (I - Exp(w)) t_bc], i.e. to first order the body-frame
right perturbation (GTSAM's Pose3 [r, t]) xi = [w, t_bc x w] = J w, J = [I; [t_bc]x], the same in
every frame.  sensor.yaml's `T_BS_sigma_deg` says how well the mount is known; until now it
reached a body-fixed floor camera's poses nowhere, so a flight whose mount is off within its
stated sigma read 6-dof NEES in the 10^4-10^6 (a held-out flight with the mount 0.5 / -0.3 /
0.2 deg off and 0.36 deg stated: PnP 1.2e6, EKF 6e4 with health ok; BENCHMARKS.md, held18).
The error is common to every frame, so like the stamps' (fusion.estimate.timeoffset
`add_stamp_covariance`) it is added to the outputs only, after the health, never to the back
ends' inputs (no back end may average it down): C += J diag(sigma^2) J^T (Bierman 1977, consider
covariance analysis).  The IMU's gravity observes part of a roll / pitch error in principle, but
a constant tilt and the accelerometer bias are the same residual while the body does not turn
(the mount check reports such axes as unexcited), so the whole stated sigma is kept.

Per axis the sigma is the stated one (sensor.yaml's `T_BS_sigma_deg`), and on the axes
--calibrate-extrinsics applied, the estimate's own sigma.  A mount whose sigma is not stated gets
no term on the other axes, as before: `CameraModel.mount_sigmas`' 0.1 deg default would widen
every such log's floor poses (the lead's sweep flights simulated before the simulator stated its
mounts: r800 PnP / smoother / EKF NEES 6.6 / 8.1 / 7.5 -> 3.5 / 4.1 / 4.2, its load maps 5.4-6.1
-> 0.0-0.1 of 3 through the load maps' pose term), a choice left to the project (BENCHMARKS.md,
held18).  A gimbaled floor camera
is left out: its level poses carry the mount's tilt through PnP's level conditioning and the
tilt consider (fusion.estimate.tiltconsider)."""

from __future__ import annotations

import math

import numpy as np

from fusion.camera import CameraModel
from fusion.geometry import skew
from fusion.types import Trajectory

AXES = ("x", "y", "z")

__all__ = ["add_mount_consider", "mount_consider_covariance", "mount_sigmas_rad"]


def mount_sigmas_rad(camera: CameraModel, applied_axes: list[str], applied_sigma_rad) -> np.ndarray:
    """(3,) rad: the mount rotation's 1-sigma per body axis that the outputs keep: the stated
    `camera.mount_sigma_deg` (0 when not stated: module docstring), or on `applied_axes` (those
    --calibrate-extrinsics corrected) the estimate's `applied_sigma_rad` (3,)."""
    stated = 0.0 if camera.mount_sigma_deg is None else math.radians(camera.mount_sigma_deg)
    out = np.full(3, stated)
    for i, axis in enumerate(AXES):
        if axis in applied_axes and applied_sigma_rad is not None:
            out[i] = float(applied_sigma_rad[i])
    return out


def mount_consider_covariance(T_body_cam: np.ndarray, sigma_rad: np.ndarray) -> np.ndarray:
    """(6, 6) body-frame [r, t] covariance of the body pose from a mount rotation error with
    1-sigma `sigma_rad` (3,) per body axis: J diag(sigma^2) J^T, J = [I; [t_bc]x] (module
    docstring)."""
    t_bc = np.asarray(T_body_cam, float)[:3, 3]
    J = np.vstack([np.eye(3), skew(t_bc)])
    return J @ np.diag(np.asarray(sigma_rad, float) ** 2) @ J.T


def add_mount_consider(trajectory: Trajectory, covariance: np.ndarray) -> Trajectory:
    """`trajectory` with `covariance` (6, 6) added to every pose's covariance (the same in every
    body frame); itself when it has no covariances or the term is zero."""
    if trajectory.covariances is None or not np.any(covariance):
        return trajectory
    return Trajectory(
        trajectory.name,
        trajectory.timestamps_ns,
        trajectory.T_world_body,
        np.asarray(trajectory.covariances) + covariance[None],
    )
