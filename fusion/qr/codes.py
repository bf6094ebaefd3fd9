"""Sort one frame's decoded QR codes into floor codes, load codes and rejections.

Payloads are untrusted (fusion.conventions.parse_payload).  What is rejected here is reported,
counted and never used for estimation (issue: "Bad input"):
- a payload that is not ours ("not_ours"),
- a floor code on the front camera or a load code on the floor camera ("wrong_camera"),
- a floor code whose position lies outside the world's bounds ("outside_world"),
- the same floor code read at two places in one frame ("duplicate_floor"): both are dropped, since
  at most one of them can be right and we cannot tell which,
- a load id that is not printable ("bad_load_id", via the payload grammar).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from fusion.conventions import FloorPayload, LoadPayload, parse_payload
from fusion.errors import PayloadError
from fusion.types import QRDetection
from fusion.world import World

FLOOR_CAMERA = "cam0"
FRONT_CAMERA = "cam1"


@dataclass
class FloorSighting:
    """A floor code in a floor-camera frame, with its known world position."""

    detection: QRDetection
    payload: FloorPayload
    centre_world: np.ndarray  # (3,) symbol centre, z = 0
    corners_world: np.ndarray  # (4, 3) TL, TR, BR, BL


@dataclass
class LoadSighting:
    detection: QRDetection
    load_id: str


FLOOR_CODE_ON_FRONT = "wrong_camera: floor code on the front camera"
LOAD_CODE_ON_FLOOR = "wrong_camera: load code on the floor camera"


@dataclass
class FrameCodes:
    """One frame's codes, sorted."""

    floor: list[FloorSighting] = field(default_factory=list)
    loads: list[LoadSighting] = field(default_factory=list)
    rejected: list[tuple[QRDetection, str]] = field(default_factory=list)  # (detection, reason)


def classify(detections: list[QRDetection], world: World) -> FrameCodes:
    """Sort the detections of ONE frame of one camera (see the module docstring for the rules)."""
    out = FrameCodes()
    floor: list[FloorSighting] = []
    for det in detections:
        try:
            payload = parse_payload(det.payload)
        except PayloadError as e:
            reason = "bad_load_id" if str(det.payload).startswith("1/") else "not_ours"
            out.rejected.append((det, f"{reason}: {e}"))
            continue
        if isinstance(payload, FloorPayload):
            if det.camera != FLOOR_CAMERA:
                out.rejected.append((det, FLOOR_CODE_ON_FRONT))
                continue
            centre = world.floor_code_position(payload)
            if not world.contains(centre):
                out.rejected.append((det, f"outside_world: floor code at {centre[:2].tolist()}"))
                continue
            floor.append(FloorSighting(det, payload, centre, world.floor_corners_world(centre)))
        elif isinstance(payload, LoadPayload):
            if det.camera != FRONT_CAMERA:
                out.rejected.append((det, LOAD_CODE_ON_FLOOR))
                continue
            out.loads.append(LoadSighting(det, payload.id))
    counts = Counter(s.payload for s in floor)
    for s in floor:
        if counts[s.payload] > 1:
            out.rejected.append((s.detection, "duplicate_floor: same floor code twice in one frame"))
        else:
            out.floor.append(s)
    return out


def rejection_counts(frames: list[FrameCodes]) -> dict[str, int]:
    """Number of rejected detections per reason over many frames."""
    c: Counter = Counter()
    for f in frames:
        for _, reason in f.rejected:
            c[reason.split(":", 1)[0]] += 1
    return dict(c)
