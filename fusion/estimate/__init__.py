"""Fusion back end: GTSAM batch smoother, incremental (iSAM2) smoother and a filterpy EKF.

All three take the same inputs (floor-camera frame times, IMU, raw per-frame QR poses, load
observations, T_body_frontcam, optional velocity, FusionConfig) and return a FusionResult."""
from fusion.estimate.common import FusionConfig, FusionResult, write_sigmas_csv
from fusion.estimate.ekf import run_ekf
from fusion.estimate.smoother import smooth, smooth_incremental

__all__ = ["FusionConfig", "FusionResult", "smooth", "smooth_incremental", "run_ekf",
           "write_sigmas_csv"]
