"""The product's main job: `run(log_dir, out_dir)` takes a logged flight to trajectories, a load
map, metrics and a report (DESIGN.md "Data flow"):

    read log -> detect (cached) -> per-frame estimators (paper, pnp)
             -> fusion (smoother, incremental, ekf) -> evaluate (with ground truth) -> report

Each stage is a function with a typed result; the CLI only calls `run` / `demo` and prints
`RunResult.summary()`.  Outputs are written atomically, file by file.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.errors import EstimationError, FusionError, OutputError
from fusion.log import FlightLog, read_flight
from fusion.log.files import write_loads_csv, write_loads_json, write_tum
from fusion.types import LoadMap, LoadObservation, Trajectory

STAGES = ("detect", "localize", "smooth", "run")
RAW_ESTIMATORS = ("paper", "pnp")
FUSED_ESTIMATORS = ("smoother", "incremental", "ekf")


@dataclass
class RunConfig:
    """Choices of a run; defaults are what `fusion run` uses."""
    backend: str = "zxing"              # QR detector: zxing | aruco
    workers: int | None = None          # detection processes (None: all cores)
    progress: bool = True               # tqdm bars
    force: bool = False                 # allow an existing output folder
    robust: str = "huber"               # robust kernel on QR pose factors
    tight: bool = False                 # corner reprojection factors instead of per-frame poses
    incremental: bool = True            # also run the incremental (causal) smoother
    th_px: float = 5.0                  # the paper's Th (Algorithms 1 and 4), pixels
    corner_sigma_px: float = 0.15       # refined-corner noise, 1 sigma, pixels


@dataclass
class RunResult:
    out_dir: Path
    log_summary: dict
    detection_stats: dict = field(default_factory=dict)
    trajectories: dict[str, Trajectory] = field(default_factory=dict)
    load_maps: dict[str, LoadMap] = field(default_factory=dict)
    metrics: dict | None = None
    notes: list[str] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)
    report_path: Path | None = None

    def summary(self) -> str:
        """A short table for the terminal."""
        lines = [f"flight: {self.log_summary.get('path')}  "
                 f"({self.log_summary.get('duration_s', 0):.1f} s, "
                 f"{self.log_summary.get('floor_frames', 0)} floor frames)"]
        ds = self.detection_stats
        if ds:
            lines.append(f"floor frames with a code: {ds.get('floor_frames_with_code', 0)}"
                         f"/{ds.get('floor_frames', 0)}; skipped frames: {ds.get('frames_skipped', 0)};"
                         f" rejected payloads: {ds.get('rejected_total', 0)}")
        per = (self.metrics or {}).get("trajectories", {})
        header = f"{'estimator':<12} {'poses':>6} {'x cm':>7} {'y cm':>7} {'z cm':>7} {'yaw deg':>8} {'ATE cm':>8}"
        lines += ["", header, "-" * len(header)]
        for name, traj in self.trajectories.items():
            m = per.get(name, {})
            mae = m.get("mae_xyz_m")

            def cm(i):
                return f"{100 * mae[i]:7.2f}" if mae else f"{'-':>7}"
            yaw = m.get("mae_yaw_deg")
            ate = m.get("ate_rmse_m")
            lines.append(f"{name:<12} {len(traj):>6} {cm(0)} {cm(1)} {cm(2)} "
                         f"{(f'{yaw:8.3f}' if yaw is not None else f'{chr(45):>8}')} "
                         f"{(f'{100 * ate:8.2f}' if ate is not None else f'{chr(45):>8}')}")
        for name, lm in self.load_maps.items():
            m = (self.metrics or {}).get("loads", {}).get(name, {})
            mae = m.get("mae_xyz_m")
            err = (f"; MAE x/y/z {100 * mae[0]:.2f}/{100 * mae[1]:.2f}/{100 * mae[2]:.2f} cm"
                   if mae else "")
            lines.append(f"loads {name:<9} {len(lm.loads)} mapped{err}")
        for note in self.notes:
            lines.append(f"note: {note}")
        if self.report_path is not None:
            lines.append(f"report: {self.report_path}")
        lines.append(f"outputs: {self.out_dir}")
        return "\n".join(lines)


def log_summary(log: FlightLog) -> dict:
    return {"path": str(log.root), "duration_s": log.duration_s,
            "floor_frames": len(log.floor), "front_frames": len(log.front) if log.front else 0,
            "imu_samples": len(log.imu.timestamps_ns) if log.imu else 0,
            "has_velocity": log.velocity is not None, "has_groundtruth": log.groundtruth is not None,
            "has_loads_groundtruth": log.loads_groundtruth is not None}


def prepare_out_dir(out_dir: Path, force: bool) -> Path:
    """Create the output folder; refuse an existing non-empty one unless `force`."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir}: exists and is not a folder")
    if out_dir.exists() and any(out_dir.iterdir()) and not force:
        raise OutputError(f"{out_dir}: output folder exists; use --force to write into it")
    out_dir.mkdir(parents=True, exist_ok=True)
    return out_dir
