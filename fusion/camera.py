"""Pinhole camera with radial-tangential (plumb-bob) or equidistant (fisheye) distortion, and
its mount on the body.

Read from / written to EuRoC/Kalibr-style `sensor.yaml`.  Two distortion models, Kalibr's two for
a pinhole camera (`distortion_model`, four coefficients each):

- `radial-tangential` (`radtan`, ROS's `plumb_bob`): OpenCV's five-coefficient model, [k1, k2,
  p1, p2] and `k3` (Kalibr's radtan has no k3: 0; sensor.yaml, OpenCV and ROS may give a fifth
  coefficient):

      x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
      y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

- `equidistant` (Kalibr's `pinhole-equi`, OpenCV's `cv2.fisheye`, Kannala & Brandt 2006 with
  four terms), [k1, k2, k3, k4], for wide-angle lenses:

      theta = atan(r),  theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
      (x_d, y_d) = (theta_d / r) (x, y)

and then u = fu x_d + cu,   v = fv y_d + cv  (r^2 = x^2 + y^2, x = X / Z, y = Y / Z).

Rolling shutter (optional `sensor.yaml` keys, both absent for a global shutter):

    line_delay_s: 3.0e-5      # row readout time, s per row (0 = global shutter)
    stamp_row: first          # which row the image timestamp belongs to: first | middle

Row v (distorted pixel coordinate, OpenCV convention: row centres at integers) is exposed at
t_stamp + line_delay_s * (v - v_stamp), v_stamp = 0 (first) or (height - 1) / 2 (middle); the
whole readout lasts line_delay_s * height.  This is Kalibr's rolling-shutter model (aslam
`RollingShutter::temporalOffset` = lineDelay * v; Oth et al., "Rolling Shutter Camera
Calibration", CVPR 2013), whose stamp is the first row; `stamp_row: middle` is for drivers that
stamp mid-exposure of the frame.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import cv2
import numpy as np

from fusion.errors import CameraModelError, FusionError
from fusion.fileio import dump_yaml, load_yaml
from fusion.geometry import inv_T, is_rigid_transform, level_frame

MOUNTS = ("body_fixed", "gimbaled")
SENSOR_YAML_KEYS = (
    "sensor_type",
    "comment",
    "T_BS",
    "rate_hz",
    "resolution",
    "camera_model",
    "intrinsics",
    "distortion_model",
    "distortion_coefficients",
    "mount",
    "line_delay_s",
    "stamp_row",
    "T_BS_sigma_deg",
    "T_BS_sigma_m",
    "intrinsics_sigma",
)
"""A camera sensor.yaml's keys (EuRoC's and ours)."""
FOREIGN_SENSOR_KEYS = {
    "line_delay": "line_delay_s (s per row)",
    "distortion_coeffs": "distortion_coefficients",
    "T_cam_imu": "T_BS (the camera in the body frame: T_cam_imu's inverse)",
    "timeshift_cam_imu": "--time-offset-ms, or the Kalibr camchain given with --calib",
}
"""Kalibr camchain keys that mean something in a sensor.yaml under another name: ignored, each
had silently changed the model (a global shutter, no distortion, ...)."""

RADTAN = "radtan"
EQUIDISTANT = "equidistant"
DISTORTION_MODELS = {
    "radial-tangential": RADTAN,
    "radtan": RADTAN,
    "plumb_bob": RADTAN,
    "equidistant": EQUIDISTANT,
    "equi": EQUIDISTANT,
}
"""The distortion models' names as sensor.yaml, Kalibr and ROS write them -> ours."""
MAX_READOUT_S = 1.0
"""A whole-frame readout longer than this (s) is a unit mistake (line delay given in ms or us)."""
DEFAULT_MOUNT_SIGMA_DEG = 0.1
DEFAULT_MOUNT_SIGMA_M = 0.002
"""How well T_BS is known (1 sigma per axis: rotation, translation) when sensor.yaml does not say
(`T_BS_sigma_deg`, `T_BS_sigma_m`): a camera-IMU calibration's usual accuracy, a tenth of a
degree and two millimetres.  The front camera's carries into every mapped load
(fusion.estimate.loadconsider); the simulator states 0 (its mounts are what it writes)."""
MAX_MOUNT_SIGMA_DEG = 30.0
MAX_MOUNT_SIGMA_M = 1.0
"""A T_BS sigma beyond these is a unit mistake (radians for degrees, mm for m)."""
DEFAULT_FOCAL_SIGMA_REL = 0.002
DEFAULT_PRINCIPAL_POINT_SIGMA_PX = 1.0
"""How well the intrinsics are known (1 sigma: the focal lengths' relative error, the principal
point's in px) when sensor.yaml does not say (`intrinsics_sigma: [fu, fv, cu, cv]` px, as
Kalibr's results-cam.txt gives them after "+-"): a calibration's usual accuracy, a few tenths of
a percent and a pixel (the calibration's own sigma is smaller: it leaves out the lens's focus
and temperature drift between calibrating and flying).  A focal length 0.5 % off puts a floor
camera 0.5 % too high in every frame: 6.6 mm at 1.3 m, against PnP sigmas of ~0.1 mm (BENCHMARKS.md,
seventeenth session).  Every pose and load carries it as a consider term
(fusion.estimate.cornerbias.BiasConsider, fusion.estimate.loadconsider); the simulator states 0
(its intrinsics are what it renders with)."""
MAX_FOCAL_SIGMA_REL = 0.2
"""An intrinsics sigma beyond this share of the focal length is a unit or typing mistake."""


class StampRow(str, Enum):
    """Which image row the frame's timestamp belongs to (rolling shutter)."""

    FIRST = "first"
    MIDDLE = "middle"


@dataclass
class CameraModel:
    """Intrinsics, distortion and extrinsics of one camera.

    `T_body_cam` is the camera's pose in the body frame (EuRoC's T_BS).  With `mount ==
    "gimbaled"` the camera is stabilised: T_body_cam then holds for the *level* body frame
    (body with roll and pitch removed), i.e. the camera keeps its attitude to the floor whatever
    the airframe's tilt (the paper's assumption 3).
    """

    width: int
    height: int
    fu: float
    fv: float
    cu: float
    cv: float
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(4))  # radtan k1, k2, p1, p2; equi k1..k4
    T_body_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    rate_hz: float = 30.0
    mount: str = "body_fixed"
    line_delay_s: float = 0.0  # rolling shutter: row readout time (s per row); 0 = global
    stamp_row: StampRow = StampRow.FIRST  # the row the image timestamp belongs to
    # how well T_body_cam is known, 1 sigma per axis (deg, m); None: not stated in sensor.yaml
    mount_sigma_deg: float | None = None
    mount_sigma_m: float | None = None
    # how well [fu, fv, cu, cv] are known, 1 sigma (px); None: not stated in sensor.yaml
    intrinsics_sigma_px: tuple[float, ...] | None = None
    distortion_model: str = RADTAN  # RADTAN or EQUIDISTANT (module docstring)
    k3: float = 0.0  # radial-tangential only: OpenCV's fifth coefficient

    def __post_init__(self):
        self.distortion = np.asarray(self.distortion, dtype=float).reshape(4)
        if self.distortion_model not in DISTORTION_MODELS:
            raise CameraModelError(
                f"unknown distortion model {self.distortion_model!r}; "
                f"expected one of {sorted(DISTORTION_MODELS)}"
            )
        self.distortion_model = DISTORTION_MODELS[self.distortion_model]
        self.k3 = float(self.k3)
        if self.k3 and self.equidistant:
            raise CameraModelError("k3 is a radial-tangential coefficient; the equidistant model has k1..k4")
        self.T_body_cam = np.asarray(self.T_body_cam, dtype=float).reshape(4, 4)
        if self.mount not in MOUNTS:
            raise CameraModelError(f"unknown camera mount {self.mount!r}; expected one of {MOUNTS}")
        try:
            self.stamp_row = StampRow(self.stamp_row)
        except ValueError:
            raise CameraModelError(
                f"unknown stamp_row {self.stamp_row!r}; expected one of {[r.value for r in StampRow]}"
            ) from None
        self.line_delay_s = float(self.line_delay_s)
        if not (math.isfinite(self.line_delay_s) and 0.0 <= self.line_delay_s * self.height <= MAX_READOUT_S):
            raise CameraModelError(
                f"line_delay_s {self.line_delay_s!r} must be >= 0 with a readout of at most "
                f"{MAX_READOUT_S} s over {self.height} rows"
            )

    # ------------------------------------------------------------------ matrices
    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fu, 0.0, self.cu], [0.0, self.fv, self.cv], [0.0, 0.0, 1.0]])

    @property
    def projection_key(self) -> tuple:
        """Everything that decides where a ray lands in the image (size, intrinsics, distortion
        model and coefficients): the key of the caches built per camera."""
        return (
            self.width,
            self.height,
            self.fu,
            self.fv,
            self.cu,
            self.cv,
            self.distortion_model,
            *self.distortion.tolist(),
            self.k3,
        )

    @property
    def equidistant(self) -> bool:
        return self.distortion_model == EQUIDISTANT

    @property
    def distorted(self) -> bool:
        """Whether pixels differ from the ideal pinhole's: any coefficient, or the equidistant
        model at all (with k = 0 it is the f-theta lens, not a pinhole)."""
        return self.equidistant or bool(np.any(self.distortion)) or self.k3 != 0.0

    @property
    def dist_cv(self) -> np.ndarray:
        """Distortion vector as OpenCV takes it: (k1, k2, p1, p2, k3) for cv2's pinhole
        functions, (k1, k2, k3, k4) for cv2.fisheye's (equidistant)."""
        return self.distortion.copy() if self.equidistant else np.r_[self.distortion, self.k3]

    def cv_undistort_points(self, pts: np.ndarray, P: np.ndarray | None, criteria: tuple) -> np.ndarray:
        """OpenCV's iterative undistortion of distorted pixels `pts` (N, 1, 2) float64, for this
        camera's distortion model (cv2.undistortPoints, or cv2.fisheye.undistortPoints for the
        equidistant one): normalised coordinates, or pixels of camera matrix P when given."""
        if self.equidistant:
            return cv2.fisheye.undistortPoints(pts, self.K, self.dist_cv, P=P, criteria=criteria)
        return cv2.undistortPoints(pts, self.K, self.dist_cv, None, None, P, criteria)

    @property
    def image_centre_px(self) -> np.ndarray:
        """Geometric centre of the image (the paper's (FC_fx, FC_fy)), not the principal point."""
        return np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])

    # ------------------------------------------------------------------ mount
    def T_world_cam(self, T_world_body: np.ndarray) -> np.ndarray:
        """Camera pose(s) (..., 4, 4) for body pose(s) T_world_body (..., 4, 4): T_world_body *
        T_body_cam for a body-fixed mount; for a gimbaled one the camera hangs from the level
        (yaw-only) body frame (the paper's assumption 3): level_frame(T_world_body) * T_body_cam."""
        T_world_body = np.asarray(T_world_body, dtype=float)
        T_parent = level_frame(T_world_body) if self.mount == "gimbaled" else T_world_body
        return T_parent @ self.T_body_cam

    def T_body_cam_at(self, T_world_body: np.ndarray) -> np.ndarray:
        """The camera's pose in the (tilted) body frame at body pose(s) T_world_body: T_body_cam
        itself for a body-fixed mount; for a gimbaled one it follows the airframe's roll and pitch,
        T_body_level * T_body_cam."""
        T_world_body = np.asarray(T_world_body, dtype=float)
        if self.mount != "gimbaled":
            return np.broadcast_to(self.T_body_cam, T_world_body.shape).copy()
        return inv_T(T_world_body) @ self.T_world_cam(T_world_body)

    @property
    def mount_sigmas(self) -> tuple[float, float]:
        """(rad, m): how well T_body_cam is known, 1 sigma per axis (sensor.yaml's
        T_BS_sigma_deg / T_BS_sigma_m, else DEFAULT_MOUNT_SIGMA_DEG / _M)."""
        deg = DEFAULT_MOUNT_SIGMA_DEG if self.mount_sigma_deg is None else self.mount_sigma_deg
        m = DEFAULT_MOUNT_SIGMA_M if self.mount_sigma_m is None else self.mount_sigma_m
        return math.radians(deg), m

    @property
    def intrinsics_sigmas(self) -> np.ndarray:
        """(4,) px: how well [fu, fv, cu, cv] are known, 1 sigma (sensor.yaml's intrinsics_sigma,
        else DEFAULT_FOCAL_SIGMA_REL of the focal lengths and DEFAULT_PRINCIPAL_POINT_SIGMA_PX)."""
        if self.intrinsics_sigma_px is not None:
            return np.asarray(self.intrinsics_sigma_px, dtype=float)
        f, c = DEFAULT_FOCAL_SIGMA_REL, DEFAULT_PRINCIPAL_POINT_SIGMA_PX
        return np.array([f * self.fu, f * self.fv, c, c])

    @property
    def gimbaled(self) -> bool:
        return self.mount == "gimbaled"

    # ------------------------------------------------------------------ rolling shutter
    @property
    def rolling_shutter(self) -> bool:
        return self.line_delay_s > 0.0

    @property
    def readout_s(self) -> float:
        """Time to read the whole frame out (s): line_delay_s * height (0 for a global shutter)."""
        return self.line_delay_s * self.height

    @property
    def stamp_row_px(self) -> float:
        """Row coordinate (px) exposed at the image timestamp."""
        return 0.0 if self.stamp_row == StampRow.FIRST else (self.height - 1) / 2.0

    def row_time_offset_s(self, v_px) -> np.ndarray:
        """Exposure time of pixel row(s) `v_px` (distorted px, any shape) relative to the image
        stamp (s): line_delay_s * (v - stamp_row_px); zeros for a global shutter."""
        return self.line_delay_s * (np.asarray(v_px, dtype=float) - self.stamp_row_px)

    # ------------------------------------------------------------------ projection
    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) ideal normalised coordinates -> distorted normalised coordinates."""
        if self.equidistant:
            r = np.hypot(xy[..., 0], xy[..., 1])
            theta = np.arctan(r)
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(r > 1e-12, equidistant_theta_d(theta, self.distortion) / r, 1.0)
            return xy * scale[..., None]
        k1, k2, p1, p2 = self.distortion
        k3 = self.k3
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """(N, 3) points in the camera frame -> (N, 2) distorted pixel coordinates.

        Points at or behind the camera (z <= 1e-9) give NaN."""
        p_cam = np.asarray(p_cam, dtype=float)
        z = p_cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p_cam[..., :2] / np.where(z > 1e-9, z, np.nan)[..., None]
        xyd = self.distort_normalized(xy)
        return np.stack([self.fu * xyd[..., 0] + self.cu, self.fv * xyd[..., 1] + self.cv], axis=-1)

    def undistort_normalized(self, uv: np.ndarray, iterations: int = 30) -> np.ndarray:
        """(N, 2) distorted pixels -> (N, 2) ideal normalised coordinates (x/z, y/z).

        Inverts `distort_normalized` by Newton's method with the analytic 2x2 Jacobian; converges to
        1e-12 for the distortion of ordinary lenses inside the image."""
        uv = np.asarray(uv, dtype=float)
        xd = np.stack([(uv[..., 0] - self.cu) / self.fu, (uv[..., 1] - self.cv) / self.fv], axis=-1)
        if not self.distorted:
            return xd
        if self.equidistant:
            return _equidistant_undistort(xd, self.distortion, iterations)
        k1, k2, p1, p2 = self.distortion
        k3 = self.k3
        xy = xd.copy()
        for _ in range(iterations):
            x, y = xy[..., 0], xy[..., 1]
            r2 = x * x + y * y
            radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
            dradial = 2.0 * k1 + 4.0 * k2 * r2 + 6.0 * k3 * r2 * r2  # d(radial)/d(r2) * 2
            f = self.distort_normalized(xy) - xd
            j11 = radial + x * dradial * x + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = x * dradial * y + 2.0 * p1 * x + 2.0 * p2 * y
            j21 = y * dradial * x + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = radial + y * dradial * y + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j21
            dx = (j22 * f[..., 0] - j12 * f[..., 1]) / det
            dy = (-j21 * f[..., 0] + j11 * f[..., 1]) / det
            xy[..., 0] -= dx
            xy[..., 1] -= dy
            if np.nanmax(np.abs(dx) + np.abs(dy), initial=0.0) < 1e-14:
                break
        return xy

    def lens_fold(self) -> tuple[float, float] | None:
        """A pixel (u, v) of the image where the distortion model cannot be inverted (it folds:
        two rays land on one pixel, so the inverse is wrong or undefined there), or None.
        Checked on a 33 x 25 grid over the whole image: undistorted, then projected back within
        1e-6 px.  An equidistant lens's pixels beyond 90 degrees off the axis (a fisheye wider
        than a hemisphere) have no pinhole ray and are not folds: they are skipped when its
        theta_d(theta) rises monotonically to their radius."""
        if not self.distorted:
            return None
        u, v = np.meshgrid(np.linspace(0.0, self.width - 1.0, 33), np.linspace(0.0, self.height - 1.0, 25))
        uv = np.column_stack([u.ravel(), v.ravel()])
        xy = self.undistort_normalized(uv)
        ok = np.all(np.isfinite(xy), axis=1)
        if self.equidistant:
            rd = np.hypot((uv[:, 0] - self.cu) / self.fu, (uv[:, 1] - self.cv) / self.fv)
            theta = np.linspace(0.0, 0.5 * math.pi, 2001)
            td = equidistant_theta_d(theta, self.distortion)
            rising = np.all(np.diff(td) > 0.0)
            beyond = rd >= td[-1]  # past 90 degrees, reached while theta_d still rises
            ok |= ~ok & beyond & rising
        back = self.project(np.column_stack([np.where(np.isfinite(xy), xy, 0.0), np.ones(len(xy))]))
        good = np.isfinite(xy).all(axis=1)
        ok &= ~good | (np.abs(back - uv).max(axis=1) < 1e-6)
        if np.all(ok):
            return None
        i = int(np.flatnonzero(~ok)[0])
        return float(uv[i, 0]), float(uv[i, 1])

    def check_lens(self, source: str) -> None:
        """CameraModelError naming `source` when the distortion folds inside the image
        (`lens_fold`): a wrong calibration, or a lens this model cannot hold, would otherwise
        turn that region's corners into rays metres off, silently."""
        fold = self.lens_fold()
        if fold is not None:
            raise CameraModelError(
                f"{source}: the {self.distortion_model} distortion {self.dist_cv.tolist()} folds inside the "
                f"image (not invertible at pixel ({fold[0]:.0f}, {fold[1]:.0f})): a wrong calibration, or "
                "coefficients for another model or image size"
            )

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) distorted pixels -> (N, 2) pixels of the ideal (distortion-free) pinhole camera."""
        xy = self.undistort_normalized(uv)
        return np.stack([self.fu * xy[..., 0] + self.cu, self.fv * xy[..., 1] + self.cv], axis=-1)

    # ------------------------------------------------------------------ sensor.yaml
    def to_sensor_yaml(self, comment: str = "") -> dict:
        """EuRoC/Kalibr `sensor.yaml` content."""
        return {
            "sensor_type": "camera",
            "comment": comment,
            "T_BS": {"cols": 4, "rows": 4, "data": [float(v) for v in self.T_body_cam.reshape(-1)]},
            "rate_hz": float(self.rate_hz),
            "resolution": [int(self.width), int(self.height)],
            "camera_model": "pinhole",
            "intrinsics": [float(self.fu), float(self.fv), float(self.cu), float(self.cv)],
            "distortion_model": "equidistant" if self.equidistant else "radial-tangential",
            # OpenCV's k3 written only when set, so files without it stay as they were
            "distortion_coefficients": [float(v) for v in self.distortion] + ([self.k3] if self.k3 else []),
            "mount": self.mount,
            # written only for a rolling shutter, so global-shutter files stay as they were
            **(
                {"line_delay_s": float(self.line_delay_s), "stamp_row": self.stamp_row.value}
                if self.rolling_shutter
                else {}
            ),
            # written only when stated, likewise
            **({} if self.mount_sigma_deg is None else {"T_BS_sigma_deg": float(self.mount_sigma_deg)}),
            **({} if self.mount_sigma_m is None else {"T_BS_sigma_m": float(self.mount_sigma_m)}),
            **(
                {}
                if self.intrinsics_sigma_px is None
                else {"intrinsics_sigma": [float(v) for v in self.intrinsics_sigma_px]}
            ),
        }

    @classmethod
    def from_sensor_yaml(cls, data: dict, source: str = "sensor.yaml") -> CameraModel:
        """Build from parsed `sensor.yaml`; raises CameraModelError naming `source` and the key."""
        if not isinstance(data, dict):
            raise CameraModelError(f"{source}: expected a mapping at top level")

        def need(key):
            if key not in data:
                raise CameraModelError(f"{source}: missing key '{key}'")
            return data[key]

        unknown_sensor_keys(data, SENSOR_YAML_KEYS, source)
        model = need("camera_model")
        if model != "pinhole":
            raise CameraModelError(f"{source}: camera_model {model!r} is not supported (pinhole only)")
        dist_model = data.get("distortion_model", "radial-tangential")
        if dist_model not in DISTORTION_MODELS:
            raise CameraModelError(
                f"{source}: distortion_model {dist_model!r} is not supported "
                f"(one of {', '.join(sorted(DISTORTION_MODELS))})"
            )
        T = read_T_BS(need("T_BS"), source)
        res = _floats(need("resolution"), 2, "resolution", source)
        intr = _floats(need("intrinsics"), 4, "intrinsics", source)
        coeffs = data.get("distortion_coefficients", [0, 0, 0, 0])
        n_coeffs = coefficient_count(dist_model, coeffs)
        dist = _floats(coeffs, n_coeffs, "distortion_coefficients", source)
        check_intrinsics(res, intr, source, CameraModelError)
        rate = float(data.get("rate_hz", 30.0))
        mount = data.get("mount", "body_fixed")
        if mount not in MOUNTS:
            raise CameraModelError(f"{source}: mount {mount!r} is not one of {MOUNTS}")
        try:
            line_delay = float(data.get("line_delay_s", 0.0))
        except (TypeError, ValueError):
            raise CameraModelError(f"{source}: 'line_delay_s' must be a number") from None
        if not (math.isfinite(line_delay) and 0.0 <= line_delay * res[1] <= MAX_READOUT_S):
            raise CameraModelError(
                f"{source}: 'line_delay_s' {line_delay!r} must be >= 0 s per row with a readout of "
                f"at most {MAX_READOUT_S} s (is it in ms or us?)"
            )
        stamp_row = data.get("stamp_row", StampRow.FIRST.value)
        if stamp_row not in [r.value for r in StampRow]:
            raise CameraModelError(
                f"{source}: 'stamp_row' {stamp_row!r} is not one of {[r.value for r in StampRow]}"
            )
        sigmas = stated_mount_sigmas(data, source)
        fu, fv, cu, cv = intr
        intr_sigma = stated_intrinsics_sigma(data.get("intrinsics_sigma"), fu, fv, source)
        cam = cls(
            int(res[0]),
            int(res[1]),
            fu,
            fv,
            cu,
            cv,
            distortion=np.asarray(dist[:4]),
            k3=dist[4] if n_coeffs == 5 else 0.0,
            T_body_cam=T,
            rate_hz=rate,
            mount=mount,
            line_delay_s=line_delay,
            stamp_row=StampRow(stamp_row),
            mount_sigma_deg=sigmas.get("T_BS_sigma_deg"),
            mount_sigma_m=sigmas.get("T_BS_sigma_m"),
            intrinsics_sigma_px=intr_sigma,
            distortion_model=dist_model,
        )
        cam.check_lens(source)
        return cam

    @classmethod
    def load(cls, path: Path) -> CameraModel:
        return cls.from_sensor_yaml(load_yaml(path, CameraModelError), str(path))

    def save(self, path: Path, comment: str = "") -> None:
        dump_yaml(self.to_sensor_yaml(comment), path)


def equidistant_theta_d(theta: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The equidistant model's distorted angle theta (1 + k1 theta^2 + ... + k4 theta^8)."""
    t2 = theta * theta
    return theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))


def equidistant_dtheta_d(theta: np.ndarray, k: np.ndarray) -> np.ndarray:
    """d theta_d / d theta: 1 + 3 k1 theta^2 + 5 k2 theta^4 + 7 k3 theta^6 + 9 k4 theta^8."""
    t2 = theta * theta
    return 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])))


def _equidistant_undistort(xd: np.ndarray, k: np.ndarray, iterations: int) -> np.ndarray:
    """Distorted normalised coordinates -> ideal ones for the equidistant model: theta from
    theta_d(theta) = |x_d| by Newton's method (from theta = |x_d|), then r = tan(theta) along
    x_d's direction.  A radius the lens cannot reach (theta_d not monotonic up to it, or theta at
    or beyond 90 degrees) gives NaN."""
    rd = np.hypot(xd[..., 0], xd[..., 1])
    theta = rd.copy()
    for _ in range(iterations):
        step = (equidistant_theta_d(theta, k) - rd) / equidistant_dtheta_d(theta, k)
        theta = theta - step
        if np.nanmax(np.abs(step), initial=0.0) < 1e-15:
            break
    bad = ~((theta >= 0.0) & (theta < 0.5 * math.pi - 1e-9)) | (equidistant_dtheta_d(theta, k) <= 0.0)
    bad |= np.abs(equidistant_theta_d(theta, k) - rd) > 1e-9 * np.maximum(rd, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(rd > 1e-12, np.tan(theta) / rd, 1.0)
    scale = np.where(bad, np.nan, scale)
    return xd * scale[..., None]


def unknown_sensor_keys(data: dict, known: tuple[str, ...], source: str) -> list[str]:
    """The keys of a sensor.yaml `data` outside `known`, which the readers ignore (other tools'
    keys: Kalibr's `rostopic`, `cam_overlaps`, ...: the caller warns).  A CameraModelError naming
    `source`, the key and the known keys for one that would have meant something: a Kalibr key
    of FOREIGN_SENSOR_KEYS, or a near-miss of a known key (a typo: `intrinsic_sigma`), whose
    default had silently been used instead."""
    unknown = [str(k) for k in data if k not in known]
    for key in unknown:
        if key in FOREIGN_SENSOR_KEYS:
            raise CameraModelError(
                f"{source}: key {key!r} is Kalibr's; a sensor.yaml says {FOREIGN_SENSOR_KEYS[key]}"
            )
        close = near_miss(key, known)
        if close:
            raise CameraModelError(
                f"{source}: unknown key {key[:60]!r} (did you mean {close!r}? known: {', '.join(known)})"
            )
    return unknown


def near_miss(key: str, known: tuple[str, ...]) -> str | None:
    """The known key that `key` misspells (difflib ratio >= 0.8: `intrinsic_sigma`,
    `distortion_coefs`), or None: a typo of a key whose default would otherwise be used unsaid."""
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.8)
    return close[0] if close else None


def stated_mount_sigmas(data: dict, source: str) -> dict[str, float]:
    """{"T_BS_sigma_deg": deg, "T_BS_sigma_m": m}: the mount's stated 1-sigma per axis, the keys
    present in `data` (a sensor.yaml or a Kalibr camchain block); raises CameraModelError naming
    `source` and the key for a value that is not a number in [0, MAX_MOUNT_SIGMA_*]."""
    sigmas = {}
    for key, limit in (("T_BS_sigma_deg", MAX_MOUNT_SIGMA_DEG), ("T_BS_sigma_m", MAX_MOUNT_SIGMA_M)):
        v = data.get(key)
        if v is None:
            continue
        number = isinstance(v, (int, float)) and not isinstance(v, bool)
        if not (number and math.isfinite(v) and 0 <= v <= limit):
            raise CameraModelError(
                f"{source}: '{key}' must be a number from 0 to {limit:g}, got {v!r} (a unit mistake?)"
            )
        sigmas[key] = float(v)
    return sigmas


def check_intrinsics(
    resolution: Sequence[float], intrinsics: Sequence[float], source: str, error: type[FusionError]
) -> None:
    """`error` naming `source` unless the resolution and focal lengths are positive and the
    principal point lies inside the image ([0, width] x [0, height] px): one outside it is another
    resolution's calibration, or cu / cv swapped (the third audit's cx 642 for a 640 px width was
    taken)."""
    (w, h), (fu, fv, cu, cv) = resolution, intrinsics
    if w < 1 or h < 1 or fu <= 0 or fv <= 0:
        raise error(f"{source}: resolution and focal lengths must be positive")
    if not (0.0 <= cu <= w and 0.0 <= cv <= h):
        raise error(
            f"{source}: principal point ({cu:g}, {cv:g}) px lies outside the {w:g}x{h:g} image: "
            "intrinsics for another resolution, or cu and cv swapped?"
        )


def stated_intrinsics_sigma(
    value, fu: float, fv: float, source: str, key: str = "intrinsics_sigma"
) -> tuple[float, ...] | None:
    """The intrinsics' stated 1-sigma [fu, fv, cu, cv] px from `value` (a sensor.yaml's or Kalibr
    camchain block's `key`; None when absent); raises CameraModelError naming `source` and `key`
    unless it is 4 numbers from 0 to MAX_FOCAL_SIGMA_REL of the focal length."""
    if value is None:
        return None
    sigma = _floats(value, 4, key, source)
    limit = MAX_FOCAL_SIGMA_REL * min(fu, fv)
    if not all(0 <= v <= limit for v in sigma):
        raise CameraModelError(
            f"{source}: '{key}' must be 4 numbers from 0 to {limit:g} px "
            f"({MAX_FOCAL_SIGMA_REL:g} of the focal length), got {sigma} (a unit mistake?)"
        )
    return tuple(sigma)


def coefficient_count(model: str, coeffs) -> int:
    """How many distortion coefficients a file's list for `model` (any DISTORTION_MODELS name)
    should hold: five for a radial-tangential list of five (OpenCV's k3 last), else four."""
    try:
        five = len(coeffs) == 5
    except TypeError:
        five = False
    return 5 if five and DISTORTION_MODELS.get(model) == RADTAN else 4


def _floats(value, n: int, key: str, source: str, error=CameraModelError) -> list[float]:
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise error(f"{source}: '{key}' must be a list of {n} numbers") from None
    if len(out) != n or not np.all(np.isfinite(out)):
        raise error(f"{source}: '{key}' must be a list of {n} finite numbers")
    return out


def read_T_BS(value, source: str, error=CameraModelError) -> np.ndarray:
    """Parse a Kalibr matrix block {rows: 4, cols: 4, data: [16 numbers]} into a rigid transform;
    raises `error` naming `source` when it is malformed or not rigid."""
    if not isinstance(value, dict) or "data" not in value:
        raise error(f"{source}: 'T_BS' must have rows, cols and data")
    data = _floats(value["data"], 16, "T_BS.data", source, error)
    T = np.array(data).reshape(4, 4)
    if not is_rigid_transform(T, atol=1e-6):
        raise error(f"{source}: 'T_BS' is not a rigid transform")
    return T
