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

import re
from dataclasses import dataclass

import numpy as np

from fusion.errors import PayloadError

GRAVITY_M_S2 = 9.81
"""Magnitude of gravity used by the simulator and the estimators (world -z)."""

# Default camera mounts (rotation part of T_body_cam).
# Floor camera: optical axis = body -z, image "up" (12 o'clock) = body +x, as the paper's Fig. 15d.
R_BODY_FLOORCAM = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# Front camera: optical axis = body +x, image right = body -y, image down = body -z.
R_BODY_FRONTCAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

# QR corner order used everywhere: symbol top-left, top-right, bottom-right, bottom-left.
CORNER_NAMES = ("top_left", "top_right", "bottom_right", "bottom_left")


def symbol_corners_S(side_m: float) -> np.ndarray:
    """(4, 3) corners of a symbol of edge `side_m` in its own frame S, in CORNER_NAMES order."""
    h = 0.5 * side_m
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


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
