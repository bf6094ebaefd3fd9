"""External position fixes (GNSS, UWB, a total station, motion capture): `fixes.csv`.

One fix a line, `t_ns, x, y, z, sigma_m`: the body origin's (IMU's) position in the world frame
of world.yaml (m) at time t_ns (the IMU's clock, int ns), with an isotropic 1-sigma `sigma_m`
(m) per axis.  A header line (first field not a number, or starting with '#') and blank lines are
skipped.  Fixes out of time order are sorted and counted (a LogWarning); two fixes at the same
time are an error (which one holds?).  Any other bad line is a LogError naming file and line.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.errors import LogError
from fusion.fileio import open_regular
from fusion.log.euroc import LogWarning

FIXES_COLUMNS = ("t_ns", "x", "y", "z", "sigma_m")


@dataclass
class PositionFixes:
    """External position fixes of the body origin, time-sorted.

    timestamps_ns (N,) int64 strictly increasing; p_world (N, 3) m; sigma_m (N,) m, > 0."""

    timestamps_ns: np.ndarray
    p_world: np.ndarray
    sigma_m: np.ndarray
    source: str = ""
    warnings: list[LogWarning] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.timestamps_ns)


def _is_header(row: list[str]) -> bool:
    head = row[0].strip()
    if head.startswith("#"):
        return True
    try:
        int(head)
    except ValueError:
        try:
            float(head)
        except ValueError:
            return True
    return False


def read_fixes(path: Path) -> PositionFixes:
    """Read a fixes CSV (module docstring); LogError naming file and line for a bad line."""
    path = Path(path)
    t: list[int] = []
    rows: list[tuple[float, float, float, float]] = []
    with open_regular(path, LogError) as f:
        try:
            for lineno, row in enumerate(csv.reader(f), start=1):
                if not row or all(not c.strip() for c in row):
                    continue
                if not t and _is_header(row):
                    continue
                if len(row) != len(FIXES_COLUMNS):
                    raise LogError(
                        f"{path}:{lineno}: expected {len(FIXES_COLUMNS)} fields "
                        f"({', '.join(FIXES_COLUMNS)}), found {len(row)}"
                    )
                try:
                    t_ns = int(row[0].strip())
                except ValueError:
                    raise LogError(
                        f"{path}:{lineno}: t_ns {row[0].strip()!r} is not an integer (ns)"
                    ) from None
                vals = []
                for name, cell in zip(FIXES_COLUMNS[1:], row[1:]):
                    try:
                        v = float(cell.strip())
                    except ValueError:
                        raise LogError(f"{path}:{lineno}: {name} {cell.strip()!r} is not a number") from None
                    if not math.isfinite(v):
                        raise LogError(f"{path}:{lineno}: {name} is {cell.strip()}, not a finite number")
                    vals.append(v)
                if not vals[3] > 0:
                    raise LogError(f"{path}:{lineno}: sigma_m must be > 0, got {row[4].strip()}")
                t.append(t_ns)
                rows.append((vals[0], vals[1], vals[2], vals[3]))
        except UnicodeDecodeError:
            raise LogError(f"{path}: not a text file") from None
        except csv.Error as e:
            raise LogError(f"{path}: not valid CSV ({e})") from None
    if not t:
        raise LogError(f"{path}: no fixes (expected lines of {', '.join(FIXES_COLUMNS)})")
    ts = np.array(t, dtype=np.int64)
    data = np.array(rows, dtype=float)
    warnings: list[LogWarning] = []
    order = np.argsort(ts, kind="stable")
    n_back = int((np.diff(ts) < 0).sum())
    if n_back:
        warnings.append(
            LogWarning(
                "fixes_out_of_order",
                n_back,
                f"{path}: {n_back} fix(es) earlier than the line before them; sorted by time",
            )
        )
    ts, data = ts[order], data[order]
    dup = np.flatnonzero(np.diff(ts) == 0)
    if dup.size:
        raise LogError(
            f"{path}: {dup.size} fix(es) share a timestamp with another, first t_ns={ts[dup[0]]} "
            "(which one holds? remove the duplicates)"
        )
    return PositionFixes(ts, data[:, :3].copy(), data[:, 3].copy(), str(path), warnings)
