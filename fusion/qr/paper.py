"""The paper's per-frame method, faithfully: Kang & Jung, Drones 2024, 8(4):130, Sections 3.2-3.3.

- Algorithm 1 (Drone 3D Localization): the floor code whose centre is nearest the image centre;
  Algorithm 2 (MatchedLocalization, Eqs. 1-2) when it is within `Th` pixels of the centre,
  Algorithm 3 (NotMatchedLocalization, Eqs. 3-11) otherwise; the yaw D_r-theta from the finder
  patterns (Sec. 3.2.5, Figs. 14-15).
- Algorithm 4 (LoadMapping), 5 (MatchedMapping), 6 (NotMatchedMapping) for the front camera.

What the paper leaves open, and what we chose (each choice is repeated where it is used):

- Image coordinates are OpenCV pixels (u right, v *down*); the world is right-handed with z up and
  yaw counter-clockwise (fusion.conventions).  The paper writes its image formulas as if image y
  and world y pointed the same way and never fixes a handedness; we derive every sign from our
  camera mounts (conventions.R_BODY_FLOORCAM / R_BODY_FRONTCAM: image 12 o'clock = body forward,
  image right = body right, for both cameras), and list each place where that flips a sign of the
  paper's pseudo-code.
- FL, the "focal length", is in pixels: `camera.fu` (the paper uses one focal length; fu = fv
  for our cameras).  All image lengths (QR_Lf, VC_f, distances) are in pixels, world ones in m.
- (FC_fx, FC_fy), "the centre point of the frame", is the geometric image centre
  ((W-1)/2, (H-1)/2), not the principal point (option `centre="principal"` uses (cu, cv)).
- The QR centre (QR_fx, QR_fy) is the intersection of the corner quadrilateral's diagonals
  (Sec. 3.2.3, Fig. 12b): `QRDetection.centre_px`.
- The paper ignores lens distortion (Sec. 4.2.3 blames it for the real-drone errors): by default
  we use the distorted pixel corners as given; `undistort=True` undistorts them first.
- The drone's position is the camera's position (no lever arm), as in the paper.
- D_r-theta: the paper gives degrees in [0, 360); this module's API returns radians in
  (-pi, pi] (conventions.wrap_angle); the branch tests of Algorithm 6 use degrees in [0, 360).
- Which of the paper's formulas are approximations?  For a distortion-free pinhole camera looking
  exactly perpendicular at the code plane, with (FC_fx, FC_fy) the principal point, the image is a
  similarity of the plane, so Eqs. 2, 5, 7, the yaw, Algorithm 3 and Algorithm 6 are exact.
  Algorithms 2 and 5 are approximations: they drop the image offset of up to Th pixels, i.e. up
  to Th * depth / FL metres in x/y (Alg. 2) or in the lateral position and height (Alg. 5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import R_BODY_FLOORCAM, R_BODY_FRONTCAM
from fusion.errors import EstimationError
from fusion.geometry import make_T, rot_z, wrap_angle
from fusion.qr.codes import FLOOR_CAMERA, FRONT_CAMERA, FrameCodes, LoadSighting, classify
from fusion.types import (
    LoadEstimate,
    LoadMap,
    LoadObservation,
    QRDetection,
    Trajectory,
    diagonal_intersection,
)
from fusion.world import World

MATCHED = "matched"
NOT_MATCHED = "not_matched"

AXIS_TOL_DEG = 0.5
"""Algorithm 6 lines 11, 17, 23, 29 compare the float D_r-theta with 0, 90, 180, 270.  We take
"equal" as "within AXIS_TOL_DEG degrees" (the paper's Table A1 reports D_r-theta to 0.01 deg and
its walls are axis-aligned, Assumption 8).  Within the tolerance the axis branch is used, which
snaps the heading to the axis; outside, the general branch (lines 35-44).  The two agree exactly
at the axis angles, so the tolerance only decides whether a small yaw error is snapped away."""

MOUNT_TOL_DEG = 10.0
"""A camera mount further than this from the paper's (image 12 o'clock = body forward, optical
axis down / forward) is refused: the paper's yaw rule cannot know about it."""


@dataclass
class PaperPose:
    """Output of Algorithm 1: the drone (= floor camera) position in the world (m) and yaw (rad,
    counter-clockwise from world x, in (-pi, pi]); which branch ran and which floor code it used."""

    x: float
    y: float
    z: float
    yaw_rad: float
    case: str  # MATCHED (Alg. 2) or NOT_MATCHED (Alg. 3)
    floor_payload: str  # raw payload of MinQR
    min_dist_px: float  # MinDist of Algorithm 1

    @property
    def xyz(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])

    @property
    def T_world_body(self) -> np.ndarray:
        """4x4 pose with roll = pitch = 0 (the paper estimates no tilt)."""
        return make_T(rot_z(self.yaw_rad), self.xyz)


# --------------------------------------------------------------------------- image geometry


def frame_centre_px(camera: CameraModel, centre: str = "geometric") -> np.ndarray:
    """(FC_fx, FC_fy) of Algorithm 1 line 3 / Algorithm 4 line 2: the geometric image centre
    ((W-1)/2, (H-1)/2) by default (the paper's "centre point of the frame"); "principal" gives
    (cu, cv), where the optical axis actually meets the image."""
    if centre == "geometric":
        return camera.image_centre_px
    if centre == "principal":
        return np.array([camera.cu, camera.cv])
    raise EstimationError(f"unknown image centre {centre!r}; expected 'geometric' or 'principal'")


def side_length_px(corners_px: np.ndarray) -> float:
    """QR_Lf: average of the four side lengths of the corner quadrilateral (Alg. 2 line 2), px."""
    c = np.asarray(corners_px, dtype=float)
    return float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))


def vertex_centre_px(corners_px: np.ndarray, centre_px: np.ndarray) -> float:
    """VC_f: average distance from the code centre to its four vertices (Alg. 3 line 1,
    Alg. 6 line 3), px."""
    return float(np.mean(np.linalg.norm(np.asarray(corners_px, float) - centre_px, axis=1)))


def yaw_from_floor_corners(corners_px: np.ndarray) -> float:
    """D_r-theta (Alg. 2 line 1, Alg. 3 line 2; Sec. 3.2.5, Figs. 14-15) in rad, (-pi, pi].

    The paper takes the centroids of the three finder patterns (at the symbol's top-left,
    top-right and bottom-left corners) and reads the drone's heading as the image's 12 o'clock
    relative to the code, which is attached in a fixed direction (Assumption 5; ours: symbol right
    = world +x, symbol up = world +y).  Under Assumption 3 (camera perpendicular to the floor) the
    image is a similarity of the floor, so the finder-centroid lines TL->TR and BL->TL are parallel
    to the corner edges TL->TR and BL->TL; we use those edges of the (sub-pixel) corners, as the
    detector gives no finder centroids.  Both directions are combined (symbol up rotated by -90 deg
    onto symbol right) and averaged.

    Image (u right, v down) -> "y up" image coordinates (u, -v): the image is the floor seen from
    above, not mirrored (R_BODY_FLOORCAM).  If world +x appears at angle beta (counter-clockwise
    from image right) and the heading (body x) is the image's 12 o'clock (90 deg), then
    yaw = 90 deg - beta.
    """
    tl, tr, _, bl = np.asarray(corners_px, dtype=float)
    right = tr - tl  # world +x in the image
    up = tl - bl  # world +y in the image
    right_up = np.array([right[0], -right[1]])
    up_up = np.array([up[0], -up[1]])
    combined = right_up / np.linalg.norm(right_up) + np.array([up_up[1], -up_up[0]]) / np.linalg.norm(up_up)
    beta = math.atan2(combined[1], combined[0])
    return float(wrap_angle(math.pi / 2 - beta))


# --------------------------------------------------------------------------- Algorithms 1-3


def matched_localization(
    qr_world_xy: np.ndarray, side_m: float, corners_px: np.ndarray, fl_px: float
) -> tuple[float, float, float, float]:
    """Algorithm 2 (MatchedLocalization) -> (D_rx, D_ry, D_rz, D_r-theta rad).

    line 1: D_r-theta from the code's shape (`yaw_from_floor_corners`);
    line 2: QR_Lf = mean side length in px;
    line 3: D_rz = QR_Lr * FL / QR_Lf (Eqs. 1-2);
    lines 4-5: (D_rx, D_ry) = (QR_rx, QR_ry).  Typo fixed: the paper's line 4 assigns D_ry from
    QR_rx (then line 5 overwrites it); the evident intent is D_rx <- QR_rx.
    Approximation of the paper: the up-to-Th-pixel offset of the code from the image centre is
    dropped (an x/y error of up to Th * D_rz / FL metres).
    """
    yaw = yaw_from_floor_corners(corners_px)
    qr_lf = side_length_px(corners_px)
    d_rz = side_m * fl_px / qr_lf
    return float(qr_world_xy[0]), float(qr_world_xy[1]), float(d_rz), yaw


def not_matched_localization(
    qr_world_xy: np.ndarray,
    side_m: float,
    corners_px: np.ndarray,
    centre_px: np.ndarray,
    fc_px: np.ndarray,
    fl_px: float,
) -> tuple[float, float, float, float]:
    """Algorithm 3 (NotMatchedLocalization) -> (D_rx, D_ry, D_rz, D_r-theta rad).

    line 1: VC_f = mean distance from (MQR_fx, MQR_fy) to the four vertices (px);
    line 2: D_r-theta from the code's shape;
    line 3: D_rz = VC_r * FL / VC_f (Eqs. 3-5), VC_r = QR_Lr / sqrt(2) (centre-to-vertex, m);
    line 4: DQ_rxy = QR_Lr * Dist(FC, MQR_f) / QR_Lf (Eqs. 6-7);
    line 5: QR_r-theta, the world direction from the drone to the code (Eqs. 8-9, Fig. 21);
    lines 6-7: D_rx = QR_rx - DQ_rxy cos(QR_r-theta), D_ry = QR_ry - DQ_rxy sin(QR_r-theta)
    (Eqs. 10-11).

    Departures:
    - line 7 uses QR_rx for y; Eq. 11 has QR_ry, which we use.
    - line 5 / Eqs. 8-9: the paper intersects a line of slope tan(D_r-theta) with the line through
      the image centre and the code centre, whose slope it writes (QR_fx-FC_fx)/(QR_fy-FC_fy)
      (inverted: dy/dx is meant), and takes the "angle between two lines", which loses the
      quadrant (a line has no direction).  We compute the same angle with its quadrant: the image
      offset d = MQR_f - FC (u right, v down) is, in the body frame, forward = -d_v and
      left = -d_u (image 12 o'clock = forward, image right = body right), so
      QR_r-theta = D_r-theta + atan2(-d_u, -d_v).
    """
    yaw = yaw_from_floor_corners(corners_px)
    vc_f = vertex_centre_px(corners_px, centre_px)
    vc_r = side_m / math.sqrt(2.0)
    d_rz = vc_r * fl_px / vc_f
    qr_lf = side_length_px(corners_px)
    d = np.asarray(centre_px, float) - np.asarray(fc_px, float)
    dq_rxy = side_m * float(np.hypot(d[0], d[1])) / qr_lf
    qr_rtheta = yaw + math.atan2(-d[0], -d[1])
    d_rx = float(qr_world_xy[0]) - dq_rxy * math.cos(qr_rtheta)
    d_ry = float(qr_world_xy[1]) - dq_rxy * math.sin(qr_rtheta)
    return d_rx, d_ry, float(d_rz), yaw


def _check_mount(camera: CameraModel, R_nominal: np.ndarray, what: str) -> None:
    R = camera.T_body_cam[:3, :3]
    cos_angle = (np.trace(R_nominal.T @ R) - 1.0) / 2.0
    angle = math.degrees(math.acos(max(-1.0, min(1.0, cos_angle))))
    if angle > MOUNT_TOL_DEG:
        raise EstimationError(
            f"paper method: the {what} camera mount is {angle:.1f} deg from the paper's "
            f"(image 12 o'clock = body forward); its yaw rule cannot be applied"
        )


def _pixels(camera: CameraModel, corners_px: np.ndarray, undistort: bool) -> np.ndarray:
    c = np.asarray(corners_px, dtype=float).reshape(4, 2)
    return camera.undistort_pixels(c) if undistort else c


def localize_frame(
    detections: list[QRDetection],
    camera: CameraModel,
    world: World,
    th_px: float = 5.0,
    *,
    undistort: bool = False,
    centre: str = "geometric",
    codes: FrameCodes | None = None,
) -> PaperPose | None:
    """Algorithm 1 (Drone 3D Localization) on one floor-camera frame.

    detections: the frame's decoded codes (camera "cam0"); only valid floor codes are used
    (fusion.qr.codes.classify: payloads not ours, duplicates, codes outside the world are
    dropped).  camera: the floor camera (FL = camera.fu, px).  th_px: Th (px).
    codes: `classify(detections, world)` when the caller has it already (its `floor` is the
    same with or without other cameras' detections); None: classified here.
    Returns None when no valid floor code is in view.

    lines 1-9: MinQR = the code whose centre (diagonal intersection, Sec. 3.2.3) is nearest
    (FC_fx, FC_fy); lines 10-13: Algorithm 2 if MinDist <= Th, else Algorithm 3.  Ties keep the
    first code (line 6 uses a strict '>').
    """
    _check_mount(camera, R_BODY_FLOORCAM, "floor")
    frame = (
        codes if codes is not None else classify([d for d in detections if d.camera == FLOOR_CAMERA], world)
    )
    if not frame.floor:
        return None
    fc = frame_centre_px(camera, centre)
    min_dist, min_qr, min_corners, min_centre = math.inf, None, None, None
    for s in frame.floor:
        corners = _pixels(camera, s.detection.corners_px, undistort)
        if not np.all(np.isfinite(corners)):
            continue
        centre_px = diagonal_intersection(corners)
        dist = float(np.hypot(*(centre_px - fc)))
        if min_dist > dist:
            min_dist, min_qr, min_corners, min_centre = dist, s, corners, centre_px
    if min_qr is None or min_corners is None or min_centre is None:  # set together: no usable code
        return None
    qr_xy = min_qr.centre_world[:2]
    if min_dist <= th_px:
        x, y, z, yaw = matched_localization(qr_xy, world.floor_side_m, min_corners, camera.fu)
        case = MATCHED
    else:
        x, y, z, yaw = not_matched_localization(
            qr_xy, world.floor_side_m, min_corners, min_centre, fc, camera.fu
        )
        case = NOT_MATCHED
    return PaperPose(x, y, z, yaw, case, min_qr.detection.payload, min_dist)


def paper_trajectory(
    frames: dict[int, list[QRDetection]],
    camera: CameraModel,
    world: World,
    th_px: float = 5.0,
    *,
    undistort: bool = False,
    centre: str = "geometric",
    name: str = "paper",
    codes: dict[int, FrameCodes] | None = None,
) -> Trajectory:
    """Algorithm 1 on every floor frame {timestamp_ns: detections}; frames without a valid floor
    code are left out.  T_world_body has roll = pitch = 0; covariances None (the paper gives none).
    codes: {timestamp_ns: classify(frames[t], world)} for the frames the caller classified
    already (shared with PnP: one classification a frame); the others are classified here.
    """
    ts, Ts = [], []
    for t in sorted(frames):
        frame_codes = codes.get(t) if codes is not None else None
        pose = localize_frame(
            frames[t], camera, world, th_px, undistort=undistort, centre=centre, codes=frame_codes
        )
        if pose is not None:
            ts.append(int(t))
            Ts.append(pose.T_world_body)
    return Trajectory(name, np.asarray(ts, dtype=np.int64), np.asarray(Ts).reshape(-1, 4, 4), None)


# --------------------------------------------------------------------------- Algorithms 4-6


def _axis_branch(yaw_deg: float, tol_deg: float) -> int | None:
    """0, 90, 180 or 270 when D_r-theta (deg, [0, 360)) is within tol_deg of it, else None."""
    for axis in (0, 90, 180, 270):
        if abs((yaw_deg - axis + 180.0) % 360.0 - 180.0) <= tol_deg:
            return axis
    return None


def matched_mapping(
    drone_xyz: np.ndarray, yaw_rad: float, side_m: float, corners_px: np.ndarray, fl_px: float
) -> np.ndarray:
    """Algorithm 5 (MatchedMapping) -> (QR_rx, QR_ry, QR_rz) in m.

    line 1: DQ_rxy = FL * QR_Lr / QR_Lf (Fig. 24; QR_Lf = mean side, px; the paper names the
    result DQW_rxy in its inputs and DQ_rxy in line 1 -- the same distance to the wall);
    lines 2-3: QR_r{x,y} = D_r{x,y} + DQ_rxy (cos, sin)(D_r-theta); line 4: QR_rz = D_rz.
    Approximation of the paper: the up-to-Th-pixel image offset is dropped.
    """
    dq = fl_px * side_m / side_length_px(corners_px)
    return np.array(
        [drone_xyz[0] + dq * math.cos(yaw_rad), drone_xyz[1] + dq * math.sin(yaw_rad), float(drone_xyz[2])]
    )


def not_matched_mapping(
    drone_xyz: np.ndarray,
    yaw_rad: float,
    side_m: float,
    corners_px: np.ndarray,
    centre_px: np.ndarray,
    fc_px: np.ndarray,
    fl_px: float,
    axis_tol_deg: float = AXIS_TOL_DEG,
) -> np.ndarray:
    """Algorithm 6 (NotMatchedMapping) -> (QR_rx, QR_ry, QR_rz) in m.

    line 1: (QRFC_fx, QRFC_fy) = (|FC_fx - QR_fx|, |FC_fy - QR_fy|) px;
    line 2: (QRFC_rx, QRFC_ry) = (QRFC_fx, QRFC_fy) * QR_Lr / QR_Lf (QR_Lf = mean side, px);
    line 3: VC_f = mean distance from the code's centre to its vertices.  Typo fixed: the paper
    writes (MQR_fx, MQR_fy) (Algorithm 1's floor code); the load code's centre (QR_fx, QR_fy) is
    meant;
    line 4: DQW_rxy = VC_r * FL / VC_f (VC_r = QR_Lr / sqrt(2));
    line 5: Inter = D_r{x,y} + DQW_rxy (cos, sin)(D_r-theta);
    line 6: QRW_r-theta, the wall's direction in which the image's right side lies;
    lines 7-10: QR_rz = D_rz + QRFC_ry if the code is above the centre (FC_fy > QR_fy: image v
    points down), else D_rz - QRFC_ry;
    lines 11-34: the axis cases D_r-theta = 0, 90, 180, 270 (within `axis_tol_deg`, see
    AXIS_TOL_DEG; the heading is then snapped to the axis); lines 35-44: the general case
    QR_r{x,y} = Inter + QRFC_rx (cos, sin)(QRW_r-theta), or + 180 deg when the code is left of
    the centre, or Inter when QR_fx = FC_fx.

    Departure (sign of the lateral term): the paper's line 6 sets QRW_r-theta = D_r-theta + 90,
    i.e. the image's right side lies 90 deg counter-clockwise of the heading, and its branches
    0, 90, 180 (lines 11-28) agree with that; its 270 branch (lines 29-34: right -> D_rx -
    QRFC_rx) contradicts it (it would need D_rx + QRFC_rx).  In our right-handed world with
    counter-clockwise yaw (world z up), a camera looking along the heading has its image right at
    heading - 90 deg (conventions.R_BODY_FRONTCAM: image right = body -y).  So here
    QRW_r-theta = (D_r-theta - 90) mod 360 (= 270 + D_r-theta), and every axis branch is the
    general formula evaluated at the exact axis angle:
        0:   QR_rx = D_rx + DQW; right -> QR_ry = D_ry - QRFC_rx   (paper line 14: +)
        90:  QR_ry = D_ry + DQW; right -> QR_rx = D_rx + QRFC_rx   (paper line 20: -)
        180: QR_rx = D_rx - DQW; right -> QR_ry = D_ry + QRFC_rx   (paper line 26: -)
        270: QR_ry = D_ry - DQW; right -> QR_rx = D_rx - QRFC_rx   (paper line 32: -, agrees)
    i.e. the paper's branches describe a mirrored (clockwise-yaw / left-handed) world, except its
    270 branch, which matches ours.
    """
    fc = np.asarray(fc_px, float)
    qr_f = np.asarray(centre_px, float)
    qrfc_f = np.abs(fc - qr_f)  # line 1
    scale = side_m / side_length_px(corners_px)
    qrfc_rx, qrfc_ry = qrfc_f * scale  # line 2
    vc_f = vertex_centre_px(corners_px, qr_f)  # line 3
    dqw = (side_m / math.sqrt(2.0)) * fl_px / vc_f  # line 4
    yaw_deg = math.degrees(yaw_rad) % 360.0
    d_rx, d_ry, d_rz = (float(v) for v in drone_xyz)
    inter = (d_rx + dqw * math.cos(yaw_rad), d_ry + dqw * math.sin(yaw_rad))  # line 5
    qrw_deg = (yaw_deg - 90.0) % 360.0  # line 6 (sign: see above)
    qr_rz = d_rz + qrfc_ry if fc[1] > qr_f[1] else d_rz - qrfc_ry  # lines 7-10
    right = qr_f[0] > fc[0]
    axis = _axis_branch(yaw_deg, axis_tol_deg)
    if axis == 0:  # lines 11-16
        qr_rx = d_rx + dqw
        qr_ry = d_ry - qrfc_rx if right else d_ry + qrfc_rx
    elif axis == 90:  # lines 17-22
        qr_ry = d_ry + dqw
        qr_rx = d_rx + qrfc_rx if right else d_rx - qrfc_rx
    elif axis == 180:  # lines 23-28
        qr_rx = d_rx - dqw
        qr_ry = d_ry + qrfc_rx if right else d_ry - qrfc_rx
    elif axis == 270:  # lines 29-34
        qr_ry = d_ry - dqw
        qr_rx = d_rx - qrfc_rx if right else d_rx + qrfc_rx
    else:  # lines 35-44
        if right:
            a = math.radians(qrw_deg)
        elif qr_f[0] == fc[0]:
            a, qrfc_rx = 0.0, 0.0
        else:
            a = math.radians((qrw_deg + 180.0) % 360.0)
        qr_rx = inter[0] + qrfc_rx * math.cos(a)
        qr_ry = inter[1] + qrfc_rx * math.sin(a)
    return np.array([qr_rx, qr_ry, qr_rz])


def map_loads_frame(
    detections: list[QRDetection],
    camera: CameraModel,
    world: World,
    drone_xyz: np.ndarray,
    drone_yaw_rad: float,
    th_px: float = 5.0,
    *,
    undistort: bool = False,
    centre: str = "geometric",
    axis_tol_deg: float = AXIS_TOL_DEG,
    loads: list[LoadSighting] | None = None,
) -> list[LoadObservation]:
    """Algorithm 4 (LoadMapping) on one front-camera frame: every valid load code (camera "cam1";
    fusion.qr.codes.classify) -> a LoadObservation with p_world only (m).

    drone_xyz (3,) m and drone_yaw_rad: the drone pose at this frame (Algorithm 1's output or any
    other estimate); the front camera is taken to sit at the drone position (no lever arm), level,
    looking along the heading, perpendicular to the code's face (Assumption 8).
    lines 1-4: each code's centre (diagonal intersection); line 5: Dist <= Th -> Algorithm 5
    (line 6), else Algorithm 6 (line 8); line 9: collect.
    loads: `classify(detections, world).loads` when the caller has it already (the same with or
    without other cameras' detections); None: classified here.
    """
    _check_mount(camera, R_BODY_FRONTCAM, "front")
    if loads is None:
        loads = classify([d for d in detections if d.camera == FRONT_CAMERA], world).loads
    fc = frame_centre_px(camera, centre)
    drone_xyz = np.asarray(drone_xyz, dtype=float).reshape(3)
    out = []
    for s in loads:
        corners = _pixels(camera, s.detection.corners_px, undistort)
        if not np.all(np.isfinite(corners)):
            continue
        qr_f = diagonal_intersection(corners)
        if float(np.hypot(*(qr_f - fc))) <= th_px:
            p = matched_mapping(drone_xyz, drone_yaw_rad, world.load_side_m, corners, camera.fu)
        else:
            p = not_matched_mapping(
                drone_xyz, drone_yaw_rad, world.load_side_m, corners, qr_f, fc, camera.fu, axis_tol_deg
            )
        out.append(
            LoadObservation(
                int(s.detection.timestamp_ns),
                s.load_id,
                p,
                corners_px=np.asarray(s.detection.corners_px, float),
            )
        )
    return out


def aggregate_loads(observations: list[LoadObservation], name: str = "paper") -> LoadMap:
    """The paper's "average result" (Table A5): the mean p_world per load id; cov_world = sample
    covariance / n (the covariance of the mean; None with a single observation); n_obs = n."""
    groups: dict[str, list[np.ndarray]] = {}
    for o in observations:
        groups.setdefault(o.load_id, []).append(np.asarray(o.p_world, dtype=float))
    loads = []
    for load_id in sorted(groups):
        P = np.array(groups[load_id])
        n = len(P)
        cov = np.cov(P, rowvar=False) / n if n > 1 else None
        loads.append(LoadEstimate(load_id, P.mean(axis=0), cov, n))
    return LoadMap(name, loads)


def paper_load_observations(
    front_frames: dict[int, list[QRDetection]],
    front_camera: CameraModel,
    world: World,
    trajectory: Trajectory,
    th_px: float = 5.0,
    *,
    max_gap_s: float = 0.05,
    undistort: bool = False,
    centre: str = "geometric",
    loads: dict[int, list[LoadSighting]] | None = None,
) -> list[LoadObservation]:
    """Algorithm 4 on every front frame {timestamp_ns: detections}, with the drone pose of the
    `trajectory` frame nearest in time (the paper records both cameras together, Sec. 4.1.1);
    frames with no pose within `max_gap_s` are skipped.  Position and yaw come from the pose;
    its roll / pitch are ignored (the paper's front camera is level, Assumption 8).
    loads: {timestamp_ns: classify(front_frames[t], world).loads} of every frame with a load
    code, when the caller has classified them already (shared with PnP); a frame not in it has
    none.  None: each frame classified here."""
    ts = np.asarray(trajectory.timestamps_ns, dtype=np.int64)
    out: list[LoadObservation] = []
    if len(ts) == 0:
        return out
    for t in sorted(front_frames):
        i = int(np.searchsorted(ts, t))
        near = [j for j in (i - 1, i) if 0 <= j < len(ts)]
        j = min(near, key=lambda k: abs(int(ts[k]) - int(t)))
        if abs(int(ts[j]) - int(t)) * 1e-9 > max_gap_s:
            continue
        T = trajectory.T_world_body[j]
        yaw = math.atan2(T[1, 0], T[0, 0])
        out.extend(
            map_loads_frame(
                front_frames[t],
                front_camera,
                world,
                T[:3, 3],
                yaw,
                th_px,
                undistort=undistort,
                centre=centre,
                loads=loads.get(t, []) if loads is not None else None,
            )
        )
    return out
