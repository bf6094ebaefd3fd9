"""Output files: TUM trajectories (evo-readable) and load maps (CSV and JSON).

TUM line: `t_s tx ty tz qx qy qz qw` of T_world_body.  The quaternion order is rolled
(wxyz <-> xyzw) here, at the file boundary, and nowhere else.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from fusion.errors import LogError
from fusion.fileio import atomic_open, csv_safe, csv_unsafe, open_regular
from fusion.geometry import R_from_quat_wxyz
from fusion.types import LoadEstimate, LoadMap, Trajectory

LOADS_COLUMNS = ("id", "x_m", "y_m", "z_m", "sigma_x_m", "sigma_y_m", "sigma_z_m", "n_obs")


def write_tum(path: Path, traj: Trajectory) -> None:
    """Write a trajectory as TUM text (nanosecond timestamps printed exactly as seconds)."""
    write_tum_pieces(path, [traj])


def write_tum_pieces(path: Path, pieces: Iterable[Trajectory]) -> None:
    """Write the consecutive pieces of one trajectory as one TUM file, the text write_tum writes
    of the whole (every row is converted on its own): a long trajectory made piece by piece."""
    with atomic_open(path) as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for traj in pieces:
            f.write("".join(_tum_rows(traj)))


_TUM_ROW = "%d.%09d %.9f %.9f %.9f %.12f %.12f %.12f %.12f\n"
"""A TUM row: seconds and nanoseconds of the integer timestamp, position (m), quaternion xyzw."""


def _tum_rows(traj: Trajectory) -> Iterable[str]:
    """The TUM rows of `traj`, each converted on its own (the columns as Python numbers, so
    that %-formatting is the whole per-row cost: the same text as formatting numpy scalars)."""
    if not len(traj):
        return []
    s, ns = np.divmod(np.asarray(traj.timestamps_ns, dtype=np.int64), 1_000_000_000)  # floor, as // and %
    p = np.asarray(traj.positions_xyz, dtype=float)
    q = np.asarray(traj.quat_wxyz, dtype=float)
    columns = (s, ns, p[:, 0], p[:, 1], p[:, 2], q[:, 1], q[:, 2], q[:, 3], q[:, 0])
    return map(_TUM_ROW.__mod__, zip(*(c.tolist() for c in columns)))


def read_tum(path: Path, name: str | None = None) -> Trajectory:
    """Read a TUM trajectory file; malformed lines raise LogError naming file and line."""
    path = Path(path)
    ts, T = [], []
    try:
        with open_regular(path, LogError, newline=None) as f:
            lines = f.read().splitlines()
    except UnicodeDecodeError as e:
        raise LogError(f"{path}: cannot read ({e.__class__.__name__})") from None
    for lineno, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != 8:
            raise LogError(f"{path}:{lineno}: expected 8 fields, found {len(parts)}")
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise LogError(f"{path}:{lineno}: a value is not a number") from None
        if not all(math.isfinite(v) for v in vals):
            raise LogError(f"{path}:{lineno}: NaN or infinite value")
        sec, _, frac = parts[0].partition(".")
        t_ns = (
            int(sec) * 1_000_000_000 + int((frac + "000000000")[:9])
            if sec.lstrip("-").isdigit()
            else int(round(vals[0] * 1e9))
        )
        M = np.eye(4)
        M[:3, :3] = R_from_quat_wxyz(np.array([vals[7], vals[4], vals[5], vals[6]]))
        M[:3, 3] = vals[1:4]
        ts.append(t_ns)
        T.append(M)
    return Trajectory(name or path.stem, np.asarray(ts, dtype=np.int64), np.asarray(T).reshape(-1, 4, 4))


def write_loads_csv(path: Path, load_map: LoadMap) -> None:
    """`id,x_m,y_m,z_m,sigma_x_m,sigma_y_m,sigma_z_m,n_obs` (sigma empty when unknown).  Ids come
    from QR payloads (untrusted): `csv_safe` keeps a spreadsheet from reading one as a formula."""
    with atomic_open(path) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(LOADS_COLUMNS)
        for l in sorted(load_map.loads, key=lambda l: l.load_id):
            sig = np.sqrt(np.diag(l.cov_world)) if l.cov_world is not None else [None] * 3
            w.writerow(
                [
                    csv_safe(l.load_id),
                    *(f"{v:.6f}" for v in l.p_world),
                    *("" if s is None else f"{s:.6f}" for s in sig),
                    l.n_obs,
                ]
            )


def read_loads_csv(path: Path, name: str | None = None) -> LoadMap:
    path = Path(path)
    loads = []
    with open_regular(path, LogError) as f:
        for lineno, row in enumerate(csv.reader(f), start=1):
            if lineno == 1 or not row:
                continue
            if len(row) != len(LOADS_COLUMNS):
                raise LogError(f"{path}:{lineno}: expected {len(LOADS_COLUMNS)} fields")
            try:
                p = np.array([float(v) for v in row[1:4]])
                sig = [float(v) for v in row[4:7]] if all(row[4:7]) else None
                n = int(row[7])
            except ValueError:
                raise LogError(f"{path}:{lineno}: a value is not a number") from None
            cov = np.diag(np.square(sig)) if sig is not None else None
            loads.append(LoadEstimate(csv_unsafe(row[0]), p, cov, n))
    return LoadMap(name or path.stem, loads)


def write_loads_json(path: Path, load_map: LoadMap) -> None:
    data = {
        "estimator": load_map.name,
        "frame": "world",
        "unit": "m",
        "loads": [
            {
                "id": l.load_id,
                "p_world_m": [float(v) for v in l.p_world],
                "cov_world_m2": None if l.cov_world is None else np.asarray(l.cov_world).tolist(),
                "n_obs": int(l.n_obs),
                # the part every flight of this label and camera shares (LoadEstimate.cov_shared)
                **({} if l.cov_shared is None else {"cov_shared_m2": np.asarray(l.cov_shared).tolist()}),
            }
            for l in sorted(load_map.loads, key=lambda l: l.load_id)
        ],
    }
    with atomic_open(path) as f:
        json.dump(data, f, indent=1)
