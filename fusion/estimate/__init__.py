"""Fusion back end: GTSAM batch smoother, incremental (iSAM2) smoother and a filterpy EKF.

All three take the same inputs (floor-camera frame times, IMU, raw per-frame QR poses, load
observations, the front camera's CameraModel (mount-aware), optional velocity, FusionConfig;
the smoothers also the floor camera's CameraModel) and return a FusionResult whose `health`
(SolveHealth) says what happened inside: dead-reckoned, iteration-limit stops, singular solves
and their fallbacks, fixes the gate kept, loads dropped, re-initialisations."""

from fusion.estimate.common import (
    FusionConfig,
    FusionResult,
    RawPoseInput,
    SolveHealth,
    SolveMode,
    TightCoupling,
    write_sigmas_csv,
)
from fusion.estimate.ekf import EkfRecovery, run_ekf
from fusion.estimate.health import Health, HealthConfig, Status, assess, assess_result
from fusion.estimate.smoother import smooth, smooth_incremental

__all__ = [
    "EkfRecovery",
    "Health",
    "HealthConfig",
    "Status",
    "assess",
    "assess_result",
    "FusionConfig",
    "FusionResult",
    "RawPoseInput",
    "SolveHealth",
    "SolveMode",
    "TightCoupling",
    "run_ekf",
    "smooth",
    "smooth_incremental",
    "write_sigmas_csv",
]
