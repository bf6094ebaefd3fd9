"""Typed results passed between pipeline stages (DESIGN.md "Data flow").

Array layouts are in the names: `timestamps_ns` (N,), `T_world_body` (N, 4, 4), `corners_px`
(4, 2) in CORNER_NAMES order (symbol top-left, top-right, bottom-right, bottom-left), distorted
pixel coordinates as seen in the image.  Pose covariances are 6x6 in GTSAM's Pose3 tangent order
[rx, ry, rz, tx, ty, tz] (rad, m), expressed in the body frame (right perturbation
T = T_hat * Exp(xi)).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import TypeVar

import numpy as np

from fusion.geometry import quat_wxyz_from_R, yaw_of

_C = TypeVar("_C", bound="Choice")


class Choice(str, Enum):
    """An enum whose members are their own strings (file names, CLI choices, JSON keys)."""

    def __str__(self) -> str:
        return str(self.value)

    @classmethod
    def parse(cls: type[_C], value: str | Choice, what: str) -> _C:
        """The member named `value`; ValueError naming `what` and the choices otherwise."""
        try:
            return cls(value)
        except ValueError:
            raise ValueError(f"{what} {value!r} is not one of {', '.join(m.value for m in cls)}") from None


class Estimator(Choice):
    """Who produced a trajectory / load map: raw per-frame estimators, then fused back ends."""

    PAPER = "paper"  # Kang & Jung, Algorithms 1-6
    PNP = "pnp"  # our PnP with covariance
    SMOOTHER = "smoother"  # GTSAM batch
    INCREMENTAL = "incremental"  # GTSAM fixed-lag (causal)
    EKF = "ekf"  # filterpy error-state EKF (causal)

    @property
    def raw(self) -> bool:
        return self in RAW_ESTIMATORS


RAW_ESTIMATORS = (Estimator.PAPER, Estimator.PNP)
FUSED_ESTIMATORS = (Estimator.SMOOTHER, Estimator.INCREMENTAL, Estimator.EKF)


class Mount(Choice):
    """How a camera hangs on the airframe (CameraModel)."""

    BODY_FIXED = "body_fixed"
    GIMBALED = "gimbaled"  # keeps its attitude to the level, yaw-only body frame


class RobustKernel(Choice):
    """Robust kernel on QR pose and load factors (GTSAM's mEstimator names)."""

    NONE = "none"
    HUBER = "huber"
    CAUCHY = "cauchy"
    TUKEY = "tukey"


class CameraRole(Choice):
    """Which camera of a flight log: EuRoC folder names."""

    FLOOR = "cam0"  # down-looking, floor codes
    FRONT = "cam1"  # forward-looking, load codes


def role_name(camera: str) -> str:
    """ "floor" or "front": what a camera of the log (its EuRoC name, CameraRole) looks at."""
    return "front" if camera == CameraRole.FRONT.value else "floor"


@dataclass
class QRDetection:
    """One decoded QR code in one frame."""

    camera: str  # "cam0" (floor) or "cam1" (front)
    timestamp_ns: int
    payload: str  # raw decoded text (untrusted)
    corners_px: np.ndarray  # (4, 2) refined corners, symbol TL, TR, BR, BL
    corners_raw_px: np.ndarray  # (4, 2) corners as the decoder returned them
    corner_sigma_px: float | None = None  # 1-sigma noise per corner coordinate (px), if known
    # (8, 8) covariance of corners_px flattened TL u, TL v, TR u, TR v, BR u, ..., BL v (px^2):
    # the corners come from one fit, so their errors are correlated; None when unknown
    corner_cov_px2: np.ndarray | None = None
    # not decoded in this frame: found near where an earlier decode of the same code predicted it
    # (fusion.qr.track); corners_raw_px then holds the prediction
    tracked: bool = False

    @property
    def centre_px(self) -> np.ndarray:
        """Intersection of the diagonals of the corner quadrilateral (the paper's Sec. 3.2.3)."""
        return diagonal_intersection(self.corners_px)


def diagonal_intersection(corners_px: np.ndarray) -> np.ndarray:
    """Intersection of the diagonals TL-BR and TR-BL of a quadrilateral (4, 2) -> (2,)."""
    p0, p1, p2, p3 = np.asarray(corners_px, dtype=float)
    d1, d2 = p2 - p0, p3 - p1
    A = np.column_stack([d1, -d2])
    det = np.linalg.det(A)
    if abs(det) < 1e-12:
        return np.mean(corners_px, axis=0)
    s = np.linalg.solve(A, p1 - p0)[0]
    return p0 + s * d1


@dataclass
class Trajectory:
    """A pose per timestamp, optionally with a 6x6 covariance each."""

    name: str
    timestamps_ns: np.ndarray  # (N,) int64
    T_world_body: np.ndarray  # (N, 4, 4)
    covariances: np.ndarray | None = None  # (N, 6, 6), [rx, ry, rz, tx, ty, tz], body frame

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    @property
    def positions_xyz(self) -> np.ndarray:
        return self.T_world_body[:, :3, 3]

    @property
    def quat_wxyz(self) -> np.ndarray:
        return quat_wxyz_from_R(self.T_world_body[:, :3, :3]) if len(self) else np.zeros((0, 4))

    @property
    def yaw_rad(self) -> np.ndarray:
        return yaw_of(self.T_world_body[:, :3, :3])

    @property
    def timestamps_s(self) -> np.ndarray:
        return np.asarray(self.timestamps_ns, dtype=np.int64) * 1e-9

    @classmethod
    def empty(cls, name: str) -> Trajectory:
        return cls(name, np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)), np.zeros((0, 6, 6)))

    @classmethod
    def concatenate(cls, parts: list[Trajectory], name: str) -> Trajectory:
        """`parts` (consecutive, disjoint in time) end to end; covariances only when every
        non-empty part has them."""
        parts = [t for t in parts if len(t)]
        if not parts:
            return cls.empty(name)
        covs = [t.covariances for t in parts if t.covariances is not None]
        return cls(
            name,
            np.concatenate([t.timestamps_ns for t in parts]),
            np.concatenate([t.T_world_body for t in parts]),
            np.concatenate(covs) if len(covs) == len(parts) else None,
        )


@dataclass
class PositionTrack:
    """A position per timestamp, no orientation: what a view that draws positions only needs
    (report.html draws the ground truth from its positions as read, without building its
    (N, 4, 4) poses: ~0.1 GB of temporaries on a 30-minute flight, BENCHMARKS.md)."""

    name: str
    timestamps_ns: np.ndarray  # (N,) int64
    positions_xyz: np.ndarray  # (N, 3) p_world, m

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    @property
    def timestamps_s(self) -> np.ndarray:  # as Trajectory.timestamps_s
        return np.asarray(self.timestamps_ns, dtype=np.int64) * 1e-9


@dataclass
class LoadObservation:
    """One sighting of a load code by the front camera.

    `p_cam` / `cov_cam`: the code centre in the camera frame (m) and its 3x3 covariance, the
    measurement a landmark factor uses; `p_world` / `cov_world`: the same combined with the
    drone pose estimate at that frame (what the per-frame estimators report)."""

    timestamp_ns: int
    load_id: str
    p_world: np.ndarray  # (3,)
    cov_world: np.ndarray | None = None  # (3, 3)
    p_cam: np.ndarray | None = None  # (3,)
    cov_cam: np.ndarray | None = None  # (3, 3)
    corners_px: np.ndarray | None = None  # (4, 2)


@dataclass
class LoadEstimate:
    """One mapped load code."""

    load_id: str
    p_world: np.ndarray  # (3,)
    cov_world: np.ndarray | None  # (3, 3) or None when unknown
    n_obs: int
    # the part of cov_world every flight of this label and front camera shares (its print and
    # the mount's errors, estimate.loadconsider): merging flights does not average it down
    cov_shared: np.ndarray | None = None


@dataclass
class LoadMap:
    name: str
    loads: list[LoadEstimate] = field(default_factory=list)

    def by_id(self) -> dict[str, LoadEstimate]:
        return {l.load_id: l for l in self.loads}
