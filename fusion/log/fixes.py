"""External position fixes (GNSS, UWB, a total station, motion capture): `fixes.csv`.

One fix a line, `t_ns, x, y, z, sigma_m`: the body origin's (IMU's) position in the world frame
of world.yaml (m) at time t_ns (the IMU's clock, int ns), with an isotropic 1-sigma `sigma_m`
(m) per axis.  A header line (first field not a number, or starting with '#') and blank lines are
skipped.  t_ns is read as the EuRoC readers read a timestamp (digits only: no sign, no
underscores, within int64).  Fixes out of time order are sorted and counted (a LogWarning); two
fixes at the same time are an error (which one holds?), and so are fixes faster than
MAX_FIX_RATE_HZ (median interval: t_ns in another unit).  Any other bad line is a LogError naming
file and line.

`fixes_in_flight` then checks the fixes against the flight's time span (its cameras' and IMU's):
none inside it is a LogError (another clock, e.g. UNIX epoch while the log starts at 0), the ones
outside it are dropped and counted (`fixes_outside_flight`).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.errors import LogError
from fusion.fileio import open_regular
from fusion.log.euroc import FlightLog, LogWarning, _timestamp

FIXES_COLUMNS = ("t_ns", "x", "y", "z", "sigma_m")
MAX_FIX_RATE_HZ = 2000.0
"""Fixes faster than this (median interval) are stamped in another unit than ns: GNSS gives
1-20 Hz, UWB up to ~100 Hz, motion capture up to ~1-2 kHz.  Fixes in ms or s are caught at any
rate, in us from 2 Hz up (slower us fixes are left to fixes_in_flight's span check)."""


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
                t_ns = _timestamp(row[0].strip(), path, lineno)
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
    if len(ts) > 1 and float(np.median(np.diff(ts))) < 1e9 / MAX_FIX_RATE_HZ:
        raise LogError(
            f"{path}: the fixes are {float(np.median(np.diff(ts))):.4g} ns apart (median), faster than "
            f"{MAX_FIX_RATE_HZ:g} Hz: t_ns is not in nanoseconds (seconds, milliseconds or "
            "microseconds?)"
        )
    return PositionFixes(ts, data[:, :3].copy(), data[:, 3].copy(), str(path), warnings)


def flight_span_ns(log: FlightLog) -> tuple[int, int, str]:
    """(first, last) timestamp of the flight's cameras and IMU (the streams that make the back
    ends' states and bridge them) and their names, in the IMU clock (ns)."""
    streams = {name: cam.timestamps_ns for name, cam in log.cameras.items()}
    if log.imu is not None:
        streams["imu0"] = log.imu.timestamps_ns
    streams = {n: t for n, t in streams.items() if len(t)}
    if not streams:
        raise LogError(f"{log.root}: no camera and no IMU samples to fuse the fixes with")
    t0 = min(int(t[0]) for t in streams.values())
    t1 = max(int(t[-1]) for t in streams.values())
    return t0, t1, ", ".join(streams)


def fixes_in_flight(fixes: PositionFixes, log: FlightLog) -> PositionFixes:
    """The fixes within the flight's time span (flight_span_ns): a LogError naming the file and
    both spans when none is (stamped in another clock: a fix there would add states days away
    from the flight, fused as if nothing were wrong); those outside it dropped and counted (the
    warning `fixes_outside_flight`)."""
    t0, t1, streams = flight_span_ns(log)
    ts = fixes.timestamps_ns
    inside = (ts >= t0) & (ts <= t1)
    spans = (
        f"fixes {ts[0] * 1e-9:.6g}-{ts[-1] * 1e-9:.6g} s, flight ({streams}) "
        f"{t0 * 1e-9:.6g}-{t1 * 1e-9:.6g} s"
    )
    if not inside.any():
        raise LogError(
            f"{fixes.source}: no fix lies within the flight's time span ({spans}): t_ns must be "
            "the IMU's clock (another clock, e.g. UNIX epoch, or an offset?)"
        )
    n_out = int((~inside).sum())
    if not n_out:
        return fixes
    warning = LogWarning(
        "fixes_outside_flight",
        n_out,
        f"{fixes.source}: {n_out} of {len(ts)} fix(es) lie outside the flight's time span ({spans}); dropped",
    )
    return PositionFixes(
        ts[inside],
        fixes.p_world[inside],
        fixes.sigma_m[inside],
        fixes.source,
        [*fixes.warnings, warning],
    )
