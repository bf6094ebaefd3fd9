"""Our per-frame estimator (not the paper's): PnP on every QR code in view, with covariance.

Modules, one responsibility each (the public names are re-exported here):

    undistort.py   distorted px -> normalised coordinates (OpenCV, verified once per camera)
    whitening.py   corner covariances -> whitening matrices (DEFAULT_CORNER_SIGMA_PX)
    ippe.py        starting poses: vectorised IPPE, OpenCV's IPPE / IPPE_SQUARE / SQPnP
    lm.py          the batched Levenberg-Marquardt engine (NormalEquations, refine_starts)
    floor.py       floor camera (cam0): body pose from all floor codes of a frame (PnPResult)
    load.py        front camera (cam1): load-code centres in camera and world (LoadObservation)
    flight.py      whole flights: pnp_trajectory, pnp_load_observations, the load map, PnPStats
    readout_information.py  (diagnostic, not re-exported) the gyro's rolling-shutter readout noise
                   in one frame's PnP, and what image + gyro together could win back

Speed: each frame is solved on its own, but many frames are computed together
(`estimate_floor_poses`, `estimate_load_observations_frames`; `pnp_trajectory` and
`pnp_load_observations` use them): one vectorised IPPE and one vectorised LM evaluation per step
for all views with the same number of codes (scripts/bench_pnp.py measures it).

Pose covariances: 6x6, GTSAM Pose3 tangent order [rx, ry, rz, tx, ty, tz] (rad, m), BODY frame,
right perturbation T = T_hat * Exp(xi) (gtsam.Pose3.Expmap) -- ready for a PriorFactorPose3.

Where this departs from the paper (Alg. 1-3, 4-6): the paper uses the single code nearest the image
centre and assumes a level camera; we use all codes in view and estimate the full 6-DOF pose.
"""

from fusion.qr.pnp.flight import (
    FRAMES_PER_BATCH,
    PnPStats,
    aggregate_load_observations,
    pnp_load_observations,
    pnp_trajectory,
    pose_at,
)
from fusion.qr.pnp.floor import (
    GIMBAL_ROLL_PITCH_SIGMA_RAD,
    MAX_YAW_DEVIATION_RAD,
    PnPResult,
    edge_implied_yaw,
    estimate_floor_pose,
    estimate_floor_poses,
)
from fusion.qr.pnp.lm import AMBIGUITY_CHI2, MAX_REPROJECTION_RMS_PX
from fusion.qr.pnp.load import (
    LoadFrame,
    estimate_load_observations,
    estimate_load_observations_frames,
    position_jacobian_wrt_body,
)
from fusion.qr.pnp.undistort import undistort
from fusion.qr.pnp.whitening import DEFAULT_CORNER_SIGMA_PX, corner_sigmas, corner_whitening, floor_whitening

__all__ = [
    "AMBIGUITY_CHI2",
    "DEFAULT_CORNER_SIGMA_PX",
    "FRAMES_PER_BATCH",
    "GIMBAL_ROLL_PITCH_SIGMA_RAD",
    "LoadFrame",
    "MAX_REPROJECTION_RMS_PX",
    "MAX_YAW_DEVIATION_RAD",
    "PnPResult",
    "PnPStats",
    "aggregate_load_observations",
    "corner_sigmas",
    "corner_whitening",
    "edge_implied_yaw",
    "estimate_floor_pose",
    "estimate_floor_poses",
    "estimate_load_observations",
    "estimate_load_observations_frames",
    "floor_whitening",
    "pnp_load_observations",
    "pnp_trajectory",
    "pose_at",
    "position_jacobian_wrt_body",
    "undistort",
]
