"""Benchmark: time of evaluate(), write_report() (plots) and write_qr_sheet() on synthetic data.

A seeded 5-minute flight (ground truth 200 Hz), four estimators at 30 Hz (two raw with gaps in
four blackouts, two fused with covariances), 20 loads.  Prints a Markdown table.

    /work/venv/bin/python scripts/bench_evaluate.py [--minutes 5]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from fusion.evaluate.metrics import evaluate, inside_intervals, write_metrics
from fusion.evaluate.report import write_report
from fusion.geometry import R_from_euler, quat_wxyz_from_R
from fusion.log.euroc import GroundTruth
from fusion.qrsheet import write_qr_sheet
from fusion.types import LoadEstimate, LoadMap, Trajectory

NS = 1_000_000_000


def synthetic(minutes: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    n = int(minutes * 60 * 200) + 1
    t = (np.arange(n) * (NS // 200)).astype(np.int64)
    s = t * 1e-9
    p = np.column_stack([4 + 3 * np.cos(0.2 * s), 3 + 2 * np.sin(0.3 * s), 1.5 + 0.3 * np.sin(0.5 * s)])
    q = quat_wxyz_from_R(
        R_from_euler("xyz", np.column_stack([0.05 * np.sin(s), 0.04 * np.cos(0.7 * s), 0.2 * s]))
    )
    z = np.zeros((n, 3))
    gt = GroundTruth(t, p, q, z, z, z)
    T = gt.T_world_body
    blackouts = [
        (int(k * NS), int((k + d) * NS), "floor")
        for k, d in ((20, 0.5), (60, 1.0), (120, 2.0), (200, 5.0))
        if k + d < minutes * 60
    ]
    trajs = {}
    idx = np.arange(0, n, 7)  # ~28.6 Hz
    for name, sd, raw in (
        ("paper", 0.02, True),
        ("pnp", 0.01, True),
        ("smoother", 0.005, False),
        ("ekf", 0.008, False),
    ):
        i = idx[~inside_intervals(t[idx], blackouts)] if raw else idx
        Te = T[i].copy()
        Te[:, :3, 3] += rng.normal(scale=sd, size=(len(i), 3))
        cov = None if raw else np.tile(np.diag([1e-4] * 3 + [sd**2] * 3), (len(i), 1, 1))
        trajs[name] = Trajectory(name, t[i], Te, cov)
    loads_gt = {f"L{k:02d}": np.array([k * 0.5, 6.0, 0.5 + 0.3 * (k % 4)]) for k in range(20)}
    lms = {
        name: LoadMap(
            name,
            [
                LoadEstimate(k, v + rng.normal(scale=0.02, size=3), np.eye(3) * 4e-4, 5)
                for k, v in loads_gt.items()
            ],
        )
        for name in ("paper", "pnp", "smoother")
    }
    return gt, trajs, lms, loads_gt, blackouts


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=5.0)
    args = ap.parse_args()
    gt, trajs, lms, loads_gt, blackouts = synthetic(args.minutes)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        t0 = time.perf_counter()
        m = evaluate(gt, trajs, lms, loads_gt, blackouts, {"frames": 9000}, align=True)
        write_metrics(d / "metrics.json", m)
        rows.append(("evaluate + metrics.json", time.perf_counter() - t0))
        t0 = time.perf_counter()
        write_report(d, m, trajs, lms, gt, loads_gt, blackouts, {"minutes": args.minutes})
        rows.append(("write_report (4 PNG at 130 dpi + report.md)", time.perf_counter() - t0))
        t0 = time.perf_counter()
        pages = write_qr_sheet(
            d / "sheet.pdf", grid=(10, 6), side_m=0.20, page="A3", load_ids=list(loads_gt), load_side_m=0.10
        )
        rows.append(
            (f"write_qr_sheet 10x6 @ 20 cm + 20 loads @ 10 cm, A3 ({pages} pages)", time.perf_counter() - t0)
        )
    n_est = sum(len(t) for t in trajs.values())
    print(
        f"Synthetic flight: {args.minutes:g} min, ground truth {len(gt.timestamps_ns)} samples "
        f"at 200 Hz, {len(trajs)} estimators / {n_est} poses, {len(loads_gt)} loads.\n"
    )
    print("| step | time [s] |\n|---|--:|")
    for name, sec in rows:
        print(f"| {name} | {sec:.2f} |")
    sm = m["trajectories"]["smoother"]
    print(
        f"\n(sanity: smoother ATE RMSE {100 * sm['ate']['ate_rmse_m']:.2f} cm, "
        f"pose NEES mean {sm['nees_pose_6dof']['nees_mean']:.2f})"
    )


if __name__ == "__main__":
    main()
