"""A finished run's output folder as the warehouse tools read it.

`fusion run` writes `run.json` (RUN_RECORD) next to report.md: the log's absolute path and copies of
its world.yaml and front-camera sensor.yaml, so `fusion inventory` and `fusion map merge` need
neither the log nor a --log option (both still accept one, which wins).  Without the record and
without --log, the front camera is unknown and places that were not read cannot be told
"missing" from "not surveyed".
"""

from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.camera import CameraModel
from fusion.errors import FusionError, WarehouseError
from fusion.fileio import atomic_open, csv_unsafe, load_yaml
from fusion.log.files import read_loads_csv, read_tum
from fusion.types import CameraRole, Estimator, LoadEstimate, LoadMap, Trajectory
from fusion.world import World

logger = logging.getLogger(__name__)

RUN_RECORD = "run.json"
WORLD_YAML = "world.yaml"
FRONT_SENSOR_YAML = Path("mav0") / str(CameraRole.FRONT.value) / "sensor.yaml"
OBSERVATIONS_CSV = "load_observations_pnp.csv"


@dataclass
class RunOutputs:
    """What the warehouse tools use of one run: its load map (full 3x3 covariances when
    loads_<estimator>.json is there), the fused trajectory, the raw PnP load observations
    {id: (n, 3) p_world}, and the warehouse (world.yaml as a dict) and front camera, if known."""

    out_dir: Path
    estimator: str
    load_map: LoadMap
    trajectory: Trajectory
    observations: dict[str, np.ndarray]
    world_yaml: dict | None
    front_camera: CameraModel | None
    log_path: str | None
    observation_times_ns: dict[str, np.ndarray] = field(default_factory=dict)  # {id: (n,)}, as observations

    @property
    def world(self) -> World | None:
        return (
            None
            if self.world_yaml is None
            else World.from_yaml(self.world_yaml, f"{self.out_dir}/{RUN_RECORD}")
        )


def write_run_record(out_dir: Path, log_path: str | Path) -> Path:
    """Write `out_dir/run.json`: the log path and copies of its world.yaml and front sensor.yaml."""
    log_path = Path(log_path).resolve()
    world = load_yaml(log_path / WORLD_YAML, WarehouseError)
    front = log_path / FRONT_SENSOR_YAML
    record = {
        "log": str(log_path),
        "world_yaml": world,
        "front_camera_sensor_yaml": load_yaml(front, WarehouseError) if front.exists() else None,
    }
    path = Path(out_dir) / RUN_RECORD
    with atomic_open(path) as f:
        json.dump(record, f, indent=1, default=_jsonable)
    return path


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v).__name__)


def load_run(out_dir: Path, estimator: str = Estimator.SMOOTHER, log: Path | None = None) -> RunOutputs:
    """Read a run folder; WarehouseError naming the file when an output is missing or bad.

    `log`: the flight log to take world.yaml and the front camera from (default: run.json)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise WarehouseError(f"{out_dir}: not a run output folder")
    estimator = str(estimator)
    load_map = read_load_map(out_dir, estimator)
    tum = out_dir / f"trajectory_{estimator}.tum"
    if not tum.exists():
        raise WarehouseError(
            f"{tum}: not found (was `fusion run` complete, and did the {estimator} estimator run?)"
        )
    try:
        traj = read_tum(tum, estimator)
    except FusionError as e:
        raise WarehouseError(str(e)) from None
    observation_times, observations = read_observation_rows(out_dir / OBSERVATIONS_CSV)
    world_yaml, camera, log_path = None, None, None
    if log is not None:
        log = Path(log)
        world_yaml = load_yaml(log / WORLD_YAML, WarehouseError)
        if (log / FRONT_SENSOR_YAML).exists():
            camera = _camera(CameraModel.load, log / FRONT_SENSOR_YAML)
        log_path = str(log.resolve())
    elif (out_dir / RUN_RECORD).exists():
        record = _read_record(out_dir / RUN_RECORD)
        world_yaml = record.get("world_yaml")
        cam = record.get("front_camera_sensor_yaml")
        if cam is not None:
            camera = _camera(lambda d: CameraModel.from_sensor_yaml(d, f"{out_dir}/{RUN_RECORD}"), cam)
        log_path = record.get("log")
    return RunOutputs(
        out_dir, estimator, load_map, traj, observations, world_yaml, camera, log_path, observation_times
    )


def _camera(loader, arg) -> CameraModel:
    try:
        return loader(arg)
    except FusionError as e:
        raise WarehouseError(str(e)) from None


def _read_record(path: Path) -> dict:
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as e:
        raise WarehouseError(f"{path}: not valid JSON ({e.__class__.__name__})") from None
    if not isinstance(record, dict) or not isinstance(record.get("world_yaml"), dict):
        raise WarehouseError(f"{path}: no world_yaml mapping")
    return record


def read_load_map(out_dir: Path, estimator: str) -> LoadMap:
    """loads_<estimator>.json (full covariances) or, without it, loads_<estimator>.csv
    (per-axis sigmas)."""
    js = Path(out_dir) / f"loads_{estimator}.json"
    if js.exists():
        try:
            data = json.loads(js.read_text(encoding="utf-8"))
            loads = []
            for i, l in enumerate(data["loads"]):
                p = np.asarray(l["p_world_m"], dtype=float).reshape(3)
                cov, shared = (l.get(k) for k in ("cov_world_m2", "cov_shared_m2"))
                cov = None if cov is None else np.asarray(cov, dtype=float).reshape(3, 3)
                shared = None if shared is None else np.asarray(shared, dtype=float).reshape(3, 3)
                if not all(x is None or np.all(np.isfinite(x)) for x in (p, cov, shared)):
                    raise ValueError(f"load {i}: non-finite value")
                loads.append(LoadEstimate(str(l["id"]), p, cov, int(l.get("n_obs", 0)), shared))
        except (ValueError, KeyError, TypeError, UnicodeDecodeError) as e:
            raise WarehouseError(f"{js}: malformed load map ({e.__class__.__name__}: {e})") from None
        return LoadMap(estimator, loads)
    csv_path = Path(out_dir) / f"loads_{estimator}.csv"
    if not csv_path.exists():
        raise WarehouseError(f"{csv_path}: not found (no load map of estimator {estimator!r})")
    try:
        return read_loads_csv(csv_path, estimator)
    except FusionError as e:
        raise WarehouseError(str(e)) from None


def read_observation_rows(path: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Raw per-frame load observations `timestamp_ns,id,x_m,y_m,z_m,...` as ({id: (n,)
    timestamp_ns}, {id: (n, 3) p_world}); ({}, {}) when the file is absent (a run without a
    front camera)."""
    path = Path(path)
    if not path.exists():
        return {}, {}
    out: dict[str, list] = {}
    stamps: dict[str, list] = {}
    with open(path, encoding="utf-8", newline="") as f:
        for lineno, row in enumerate(csv.reader(f), start=1):
            if lineno == 1 or not row:
                continue
            if len(row) < 5:
                raise WarehouseError(f"{path}:{lineno}: expected at least 5 fields, found {len(row)}")
            try:
                t = int(row[0])
            except ValueError:
                raise WarehouseError(f"{path}:{lineno}: timestamp_ns is not an integer") from None
            try:
                p = [float(v) for v in row[2:5]]
            except ValueError:
                raise WarehouseError(f"{path}:{lineno}: a position is not a number") from None
            if not all(math.isfinite(v) for v in p):
                raise WarehouseError(f"{path}:{lineno}: NaN or infinite position")
            load_id = csv_unsafe(row[1])  # written csv_safe (pipeline.write_load_observations_csv)
            out.setdefault(load_id, []).append(p)
            stamps.setdefault(load_id, []).append(t)
    return (
        {k: np.asarray(v, dtype=np.int64) for k, v in stamps.items()},
        {k: np.asarray(v) for k, v in out.items()},
    )
