"""What the warehouse system says should be where: the expected-loads manifest.

Two CSV layouts are read (the header decides which; column names are case-insensitive, cells are
stripped, `,` or `;` separated, UTF-8 with or without a byte-order mark):

1. **Plain manifest** (ours): `id,x_m,y_m,z_m[,tolerance_m][,face_yaw_deg]` in metres, world
   frame W of world.yaml (z up, floor z = 0), the load code's symbol centre.

2. **WMS location export**: one row per pallet as warehouse-management systems export their
   bin/handling-unit list with coordinates (SAP EWM "storage bin" + "handling unit", Manhattan
   "location" + "LPN" and similar):

       location,pallet_id,x,y,z,unit[,tolerance][,face_yaw_deg]
       A-01-01,PAL-000123,1500,2700,700,mm,10,-90

   `location` is the WMS bin code (kept and reported), `pallet_id` the id printed in the load's
   QR code (`1/<pallet_id>`), `x,y,z` the label's centre in the warehouse frame (the same frame
   as the floor-code grid), `unit` one of mm, cm, m per row (converted to metres here; any other
   unit is refused, never guessed), `tolerance` in the same unit.

`tolerance_m` is the 1-sigma placement spread of the expected position per axis (how precisely
the system knows where a pallet stands); DEFAULT_TOLERANCE_M when absent.

`face_yaw_deg` (optional, either layout; a cell may be empty) is the direction the label faces,
the yaw of its outward normal in the world frame in degrees (-90: it faces -y, the aisle on the
rack's -y side).  The inventory then counts a pose as seeing the place only from in front of
the label (inventory.MAX_READ_OBLIQUITY_DEG): without it, a flight down the next aisle, behind
the rack, would call a load it could not have read "missing".

Bad input (duplicate ids, missing columns, short rows, non-numeric or non-finite cells, foreign
units, empty or unprintable ids) raises WarehouseError with one line naming file and line; so
does, in `fusion inventory`, an expected position outside world.yaml's bounds_m (a plain
manifest filled in mm: inventory.check_inside_warehouse).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.conventions import MAX_LOAD_ID_CHARS
from fusion.errors import WarehouseError

DEFAULT_TOLERANCE_M = 0.01
"""1-sigma placement tolerance per axis when the manifest gives none: a label stuck by hand and a
pallet set down by a forklift are known to about a centimetre.  With the chi-square gate of
`inventory` (alpha = MOVED_ALPHA) a load then counts as moved beyond about 4 cm when the map
itself is precise (simulated flights: load sigma below 1 mm)."""

UNIT_TO_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
"""Units accepted in the WMS export's `unit` column (anything else is refused)."""

PLAIN_COLUMNS = ("id", "x_m", "y_m", "z_m")
PLAIN_OPTIONAL = ("tolerance_m", "face_yaw_deg")
WMS_COLUMNS = ("location", "pallet_id", "x", "y", "z", "unit")
WMS_OPTIONAL = ("tolerance", "face_yaw_deg")


@dataclass(frozen=True)
class ExpectedLoad:
    """One manifest entry: `p_world` (3,) in m, `tolerance_m` 1-sigma per axis, the WMS location
    code (None for a plain manifest), the 1-based line it came from, and the yaw (rad) of the
    label's outward normal when the manifest gives it."""

    load_id: str
    p_world: np.ndarray
    tolerance_m: float
    location: str | None
    line: int
    face_yaw_rad: float | None = None


def read_manifest(path: Path) -> list[ExpectedLoad]:
    """Read a plain manifest or a WMS export (see the module docstring); WarehouseError on bad
    input, naming the file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise WarehouseError(f"{path}: file not found") from None
    except (UnicodeDecodeError, IsADirectoryError) as e:
        raise WarehouseError(f"{path}: cannot read ({e.__class__.__name__})") from None
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise WarehouseError(f"{path}:1: empty file or empty header line")
    delimiter = ";" if lines[0].count(";") > lines[0].count(",") else ","
    rows = csv.reader(lines, delimiter=delimiter)
    header = [h.strip().lower() for h in next(rows)]
    required: tuple[str, ...]
    optional: tuple[str, ...]
    if "pallet_id" in header or "location" in header:
        layout, required, optional = "wms", WMS_COLUMNS, WMS_OPTIONAL
    else:
        layout, required, optional = "plain", PLAIN_COLUMNS, PLAIN_OPTIONAL
    missing = [c for c in required if c not in header]
    if missing:
        raise WarehouseError(
            f"{path}:1: missing column(s) {', '.join(missing)} ({layout} manifest needs {','.join(required)})"
        )
    dup = sorted({h for h in header if header.count(h) > 1 and h})
    if dup:
        raise WarehouseError(f"{path}:1: column(s) {', '.join(dup)} appear twice")
    col = {name: header.index(name) for name in (*required, *optional) if name in header}
    out: list[ExpectedLoad] = []
    first_line: dict[str, int] = {}
    for lineno, row in enumerate(rows, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) < len(header):
            raise WarehouseError(f"{path}:{lineno}: expected {len(header)} fields, found {len(row)}")
        if any(c.strip() for c in row[len(header) :]):  # a spreadsheet's empty trailing cells pass
            raise WarehouseError(
                f"{path}:{lineno}: {len(row)} fields, the header names {len(header)} (a column "
                "without its header: which is it?)"
            )
        cells = {name: row[i].strip() for name, i in col.items()}
        entry = (_plain_row if layout == "plain" else _wms_row)(cells, path, lineno)
        if entry.load_id in first_line:
            raise WarehouseError(
                f"{path}:{lineno}: duplicate id {entry.load_id!r} (first on line {first_line[entry.load_id]})"
            )
        first_line[entry.load_id] = lineno
        out.append(entry)
    return out


def _plain_row(cells: dict, path: Path, lineno: int) -> ExpectedLoad:
    load_id = _load_id(cells["id"], "id", path, lineno)
    p = np.array([_number(cells[c], c, path, lineno) for c in ("x_m", "y_m", "z_m")])
    tol = _tolerance(cells.get("tolerance_m", ""), "tolerance_m", 1.0, path, lineno)
    return ExpectedLoad(load_id, p, tol, None, lineno, _face(cells, path, lineno))


def _wms_row(cells: dict, path: Path, lineno: int) -> ExpectedLoad:
    load_id = _load_id(cells["pallet_id"], "pallet_id", path, lineno)
    unit = cells["unit"].lower()
    if unit not in UNIT_TO_M:
        raise WarehouseError(
            f"{path}:{lineno}: column unit: {cells['unit'][:20]!r} is not one of {', '.join(UNIT_TO_M)}"
        )
    scale = UNIT_TO_M[unit]
    p = np.array([_number(cells[c], c, path, lineno) * scale for c in ("x", "y", "z")])
    tol = _tolerance(cells.get("tolerance", ""), "tolerance", scale, path, lineno)
    return ExpectedLoad(load_id, p, tol, cells["location"], lineno, _face(cells, path, lineno))


def _face(cells: dict, path: Path, lineno: int) -> float | None:
    text = cells.get("face_yaw_deg", "")
    return math.radians(_number(text, "face_yaw_deg", path, lineno)) if text else None


def _load_id(text: str, column: str, path: Path, lineno: int) -> str:
    if not text:
        raise WarehouseError(f"{path}:{lineno}: column {column}: empty id")
    if len(text) > MAX_LOAD_ID_CHARS or not text.isprintable():
        raise WarehouseError(
            f"{path}:{lineno}: column {column}: not a load id (printable, at most "
            f"{MAX_LOAD_ID_CHARS} characters): {text[:20]!r}"
        )
    return text


def _number(text: str, column: str, path: Path, lineno: int) -> float:
    try:
        v = float(text)
    except ValueError:
        raise WarehouseError(f"{path}:{lineno}: column {column}: {text[:20]!r} is not a number") from None
    if not math.isfinite(v):
        raise WarehouseError(f"{path}:{lineno}: column {column}: {text[:20]!r} is not finite")
    return v


def _tolerance(text: str, column: str, scale: float, path: Path, lineno: int) -> float:
    if not text:
        return DEFAULT_TOLERANCE_M
    v = _number(text, column, path, lineno) * scale
    if v < 0:
        raise WarehouseError(f"{path}:{lineno}: column {column}: negative tolerance")
    return v
