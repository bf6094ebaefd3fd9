"""fusion: drone 3D localization and load mapping from QR codes, fused with IMU in GTSAM.

Reproduces Kang & Jung, "A Drone's 3D Localization and Load Mapping Based on QR Codes for Load
Management", Drones 2024, 8(4):130, and extends it with PnP poses, factor-graph smoothing and an
EKF baseline.  See DESIGN.md for the data flow."""

from fusion.errors import FusionError

__version__ = "0.1.0"
__all__ = ["FusionError", "__version__"]
