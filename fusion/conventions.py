"""Frames, units and the QR payload grammar (DESIGN.md, "Conventions").

- World W: z up, floor z = 0.  Body B = IMU frame, FLU (x forward, y left, z up).
- Camera C: OpenCV (x right, y down, z along the optical axis).
- `T_a_b` is a 4x4 homogeneous transform mapping b-coordinates into a-coordinates.
- Symbol frame S of a QR code: origin at the symbol centre, x_S = symbol "right" (top-left finder
  to top-right finder), y_S = symbol "up" (bottom-left finder to top-left finder), z_S = out of
  the printed face.  Floor codes: S aligned with W.  Load codes: y_S = world +z, z_S = the face's
  outward normal.
- Yaw (the paper's D_r-theta) is the heading of body x from world x, counter-clockwise, in rad.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from fusion.errors import PayloadError

GRAVITY_M_S2 = 9.81
"""Magnitude of gravity used by the simulator and the estimators (world -z)."""

# Default camera mounts (rotation part of T_body_cam).
# Floor camera: optical axis = body -z, image "up" (12 o'clock) = body +x, as the paper's Fig. 15d.
R_BODY_FLOORCAM = np.array([[0.0, -1.0, 0.0],
                            [-1.0, 0.0, 0.0],
                            [0.0, 0.0, -1.0]])
# Front camera: optical axis = body +x, image right = body -y, image down = body -z.
R_BODY_FRONTCAM = np.array([[0.0, 0.0, 1.0],
                            [-1.0, 0.0, 0.0],
                            [0.0, -1.0, 0.0]])

# QR corner order used everywhere: symbol top-left, top-right, bottom-right, bottom-left.
CORNER_NAMES = ("top_left", "top_right", "bottom_right", "bottom_left")


def symbol_corners_S(side_m: float) -> np.ndarray:
    """(4, 3) corners of a symbol of edge `side_m` in its own frame S, in CORNER_NAMES order."""
    h = 0.5 * side_m
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


# --------------------------------------------------------------------------- SE(3) helpers


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a 3-vector translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def skew(w: np.ndarray) -> np.ndarray:
    """3x3 cross-product matrix [w]x (skew(w) @ p == cross(w, p))."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def skew_stack(p: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices of (..., 3) vectors."""
    p = np.asarray(p, dtype=float)
    S = np.zeros(p.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -p[..., 2], p[..., 1]
    S[..., 1, 0], S[..., 1, 2] = p[..., 2], -p[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -p[..., 1], p[..., 0]
    return S


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform (or a stack of them, shape (..., 4, 4))."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Map (N, 3) points from frame b into frame a."""
    p_b = np.asarray(p_b, dtype=float)
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def yaw_of(R_world_body: np.ndarray) -> float:
    """Heading of body x from world x, counter-clockwise, in rad in (-pi, pi] (works for (...,3,3))."""
    R = np.asarray(R_world_body)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def wrap_angle(a):
    """Wrap an angle (or array of angles) to (-pi, pi]."""
    return -(np.mod(-np.asarray(a) + np.pi, 2.0 * np.pi) - np.pi)


def interpolate_poses(ts: np.ndarray, T: np.ndarray, tq: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) sampled at increasing times `ts` (N,), interpolated at `tq` (M,) inside
    [ts[0], ts[-1]]: linear position, slerp rotation.  Returns (M, 4, 4)."""
    from scipy.spatial.transform import Slerp
    out = np.tile(np.eye(4), (len(tq), 1, 1))
    for a in range(3):
        out[:, a, 3] = np.interp(tq, ts, T[:, a, 3])
    if len(ts) == 1:
        out[:, :3, :3] = T[0, :3, :3]
    else:
        out[:, :3, :3] = Slerp(ts, Rotation.from_matrix(T[:, :3, :3]))(tq).as_matrix()
    return out


def quat_wxyz_from_R(R: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (w, x, y, z), w >= 0, from rotation matrix (or stack (N,3,3))."""
    q_xyzw = Rotation.from_matrix(R).as_quat()
    q = np.roll(q_xyzw, 1, axis=-1)
    sign = np.where(q[..., :1] < 0.0, -1.0, 1.0)
    return q * sign


def R_from_quat_wxyz(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix (or stack) from quaternion(s) (w, x, y, z); normalises the input."""
    q = np.asarray(q_wxyz, dtype=float)
    return Rotation.from_quat(np.roll(q, -1, axis=-1)).as_matrix()


def rot_z(yaw: float) -> np.ndarray:
    """Rotation about world z by `yaw` rad."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def R_world_loadsymbol(normal_yaw: float) -> np.ndarray:
    """Rotation of a load code's symbol frame S on a vertical face whose outward normal points at
    heading `normal_yaw` (rad): z_S = normal, y_S = world +z, x_S = y_S x z_S (the viewer's right)."""
    n = np.array([math.cos(normal_yaw), math.sin(normal_yaw), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(up, n)
    return np.column_stack([x, up, n])


# --------------------------------------------------------------------------- payload grammar

MAX_PAYLOAD_CHARS = 128
MAX_LOAD_ID_CHARS = 64
_NUMBER = r"[+-]?(?:\d{1,9}(?:\.\d{1,9})?|\.\d{1,9})"
_FLOOR_RE = re.compile(rf"0/({_NUMBER})/({_NUMBER})")
_LOAD_RE = re.compile(r"1/(.+)", re.DOTALL)


@dataclass(frozen=True)
class FloorPayload:
    """A floor code `0/<x>/<y>`: the symbol centre is (x, y) * payload_unit_m in the world."""
    x: float
    y: float

    def position_m(self, payload_unit_m: float) -> np.ndarray:
        return np.array([self.x * payload_unit_m, self.y * payload_unit_m, 0.0])


@dataclass(frozen=True)
class LoadPayload:
    """A load code `1/<id>`; `id` is printable text of at most MAX_LOAD_ID_CHARS characters."""
    id: str


def parse_payload(raw) -> FloorPayload | LoadPayload:
    """Parse an untrusted QR payload (str or bytes).  Raises PayloadError, never anything else.

    Grammar: ``0/<x>/<y>`` with decimal numbers, or ``1/<id>`` with a printable id (no control
    characters, no surrounding whitespace, at most 64 characters).
    """
    if isinstance(raw, (bytes, bytearray)):
        try:
            raw = bytes(raw).decode("utf-8")
        except UnicodeDecodeError:
            raise PayloadError("payload is not UTF-8 text") from None
    if not isinstance(raw, str):
        raise PayloadError(f"payload is not text ({type(raw).__name__})")
    if len(raw) > MAX_PAYLOAD_CHARS:
        raise PayloadError(f"payload too long ({len(raw)} > {MAX_PAYLOAD_CHARS} characters)")
    m = _FLOOR_RE.fullmatch(raw)
    if m:
        x, y = float(m.group(1)), float(m.group(2))
        return FloorPayload(x, y)
    m = _LOAD_RE.fullmatch(raw)
    if m:
        load_id = m.group(1)
        if len(load_id) > MAX_LOAD_ID_CHARS:
            raise PayloadError(f"load id too long ({len(load_id)} > {MAX_LOAD_ID_CHARS})")
        if not load_id.isprintable() or load_id != load_id.strip():
            raise PayloadError(f"load id is not printable text: {load_id!r}")
        return LoadPayload(load_id)
    raise PayloadError(f"not a fusion payload: {raw[:40]!r}")


def floor_payload(x: float, y: float) -> str:
    """Payload text for a floor code at (x, y) in payload units (integers printed without '.0')."""
    def fmt(v: float) -> str:
        return str(int(v)) if float(v).is_integer() else f"{v:.6f}".rstrip("0")
    return f"0/{fmt(x)}/{fmt(y)}"


def load_payload(load_id: str) -> str:
    """Payload text for a load code."""
    return f"1/{load_id}"
