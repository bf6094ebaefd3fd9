"""`fusion map merge` end to end on rendered flights over one floor: are the merged floor codes'
and loads' sigma honest however many flights saw them?

Renders N flights of the default scenario over one misplaced floor (`fusion simulate` with a
common `--placement-seed`, each flight its own `--seed` and a later `--start`), runs
`fusion run` on each, merges them with `fusion map merge`, and prints the 3-dof NEES (ideal 3)
against the simulator's ground truth, by the number of flights behind each estimate:

- floor codes (x, y, yaw; codes seen in at least --min-obs frames by every run that saw them):
  each run's own floor_codes_smoother.csv; the merge (`merge_floor_codes` on the runs, with its
  full covariances, and floor_codes_merged.csv: what `fusion run --map` reads, its sigma and,
  since 2026-12-05, their correlations); and the independent per-code information fusion that
  `fusion map merge` used before 2026-12-05 (for comparison);
- loads (x, y, z): each run's loads_smoother.json, the merged map.json, and the independent
  fusion of the runs' covariances;
- the changes the merge lists between flights: the simulator moves no load, so every "moved" and
  "disappeared" is false.

Existing flights and runs in WORKDIR are reused (delete them to redo); the merge is redone.

    PYTHONPATH=$PWD python3 scripts/bench_map_merge_rendered.py WORKDIR [--flights 4]
        [--duration 45] [--stagger 15] [--seed 201] [--placement-seed 77]
        [--placement-error-m 0.01] [--placement-error-deg 1] [--workers 1]
        [--simulate-args "--camera-effects realistic ..."]
"""

from __future__ import annotations

import argparse
import collections
import csv
import datetime
import json
import math
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

from fusion.estimate.asbuilt import read_floor_code_rows
from fusion.warehouse.floorcodes import merge_floor_codes
from fusion.world import World

FUSION = [sys.executable, "-m", "fusion.cli"]


def sh(args: list[str]) -> None:
    print("$", " ".join(args[2:] if args[:2] == FUSION[:2] else args), flush=True)
    subprocess.run(args, check=True)


def code_truth(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as f:
        return {
            r["id"]: np.array([float(r["x_m"]), float(r["y_m"]), math.radians(float(r["yaw_deg"]))])
            for r in csv.DictReader(f)
        }


def load_truth(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as f:
        return {r["id"]: np.array([float(r[k]) for k in ("x_m", "y_m", "z_m")]) for r in csv.DictReader(f)}


def z2(x: np.ndarray, P: np.ndarray, truth: np.ndarray, angle: int | None = None) -> float:
    e = np.asarray(x, float) - truth
    if angle is not None:
        e[angle] = math.remainder(e[angle], 2 * math.pi)
    return float(e @ np.linalg.solve(P, e))


def fused(
    estimates: list[tuple[np.ndarray, np.ndarray]], angle: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Information-weighted fusion of (x, P) as if independent (angles unwrapped to the first)."""
    x0 = estimates[0][0]
    info = sum(np.linalg.inv(P) for _, P in estimates)
    P = np.linalg.inv(info)
    xs = []
    for x, _ in estimates:
        x = np.array(x, float)
        if angle is not None:
            x[angle] = x0[angle] + math.remainder(x[angle] - x0[angle], 2 * math.pi)
        xs.append(x)
    return P @ sum(np.linalg.solve(Pi, xi) for xi, (_, Pi) in zip(xs, estimates)), P


def table(title: str, columns: dict[str, dict[int, list[float]]]) -> None:
    print(f"\n{title}\n")
    print("| flights behind the estimate | count | " + " | ".join(f"NEES, {k}" for k in columns) + " |")
    print("|--:|--:|" + "--:|" * len(columns))
    first = next(iter(columns.values()))
    for n in sorted(first):
        cells = " | ".join(f"{np.mean(v[n]):.2f}" for v in columns.values())
        print(f"| {n} | {len(first[n])} | {cells} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--flights", type=int, default=4)
    ap.add_argument("--duration", type=float, default=45.0)
    ap.add_argument("--stagger", type=float, default=15.0, help="each flight starts this much later (s)")
    ap.add_argument("--seed", type=int, default=201, help="flight i gets seed + i")
    ap.add_argument("--placement-seed", type=int, default=77)
    ap.add_argument("--placement-error-m", type=float, default=0.01)
    ap.add_argument("--placement-error-deg", type=float, default=1.0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--min-obs", type=int, default=10)
    ap.add_argument(
        "--simulate-args",
        default="",
        help="more `fusion simulate` options, e.g. '--camera-effects realistic'",
    )
    args = ap.parse_args()
    wd = args.workdir
    wd.mkdir(parents=True, exist_ok=True)
    outs = []
    for i in range(args.flights):
        log, out = wd / f"f{i + 1}", wd / f"o{i + 1}"
        if not (log / "manifest.json").is_file():
            sh([*FUSION, "simulate", str(log), "--duration", f"{args.duration:g}",
                "--start", f"{i * args.stagger:g}", "--seed", str(args.seed + i),
                "--placement-seed", str(args.placement_seed),
                "--placement-error-m", f"{args.placement_error_m:g}",
                "--placement-error-deg", f"{args.placement_error_deg:g}",
                "--workers", str(args.workers), "-q", "--force",
                *shlex.split(args.simulate_args)])  # fmt: skip
        if not (out / "run.json").is_file():
            sh([*FUSION, "run", str(log), "--out", str(out), "--workers", str(args.workers), "-q", "--force"])
        outs.append(out)
    merged_dir = wd / "merged"
    sh([*FUSION, "map", "merge", *map(str, outs), "--out", str(merged_dir), "--force", "-q"])

    codes = code_truth(wd / "f1" / "floor_codes_groundtruth.csv")
    for i in range(1, args.flights):
        other = code_truth(wd / f"f{i + 1}" / "floor_codes_groundtruth.csv")
        if other.keys() != codes.keys() or any(not np.array_equal(other[k], codes[k]) for k in codes):
            sys.exit(f"{wd}/f{i + 1}: another floor than f1's (placement seed?)")
    loads = load_truth(wd / "f1" / "loads_groundtruth.csv")

    # floor codes
    rows: dict[str, list] = collections.defaultdict(list)
    own = []
    for out in outs:
        for cid, r in read_floor_code_rows(out / "floor_codes_smoother.csv").items():
            if r.n_obs >= args.min_obs:
                rows[cid].append(r)
                own.append(z2(r.xy_yaw, r.cov, codes[cid], angle=2))
    # the merge's full covariances, and floor_codes_merged.csv's (its sigma and correlations)
    merged_codes, _ = merge_floor_codes(outs, "smoother", World.load(wd / "f1" / "world.yaml"))
    merged_rows = read_floor_code_rows(merged_dir / "floor_codes_merged.csv")
    m_codes: dict[int, list[float]] = collections.defaultdict(list)
    d_codes: dict[int, list[float]] = collections.defaultdict(list)
    i_codes: dict[int, list[float]] = collections.defaultdict(list)
    for c in merged_codes:
        cid = c.code_id
        if len(rows[cid]) < 2 or len(rows[cid]) != c.n_runs:
            continue  # seen by one run, or by a run in fewer than --min-obs frames
        m_codes[c.n_runs].append(z2(c.xy_yaw, c.cov, codes[cid], angle=2))
        d_codes[c.n_runs].append(z2(merged_rows[cid].xy_yaw, merged_rows[cid].cov, codes[cid], angle=2))
        x, P = fused([(q.xy_yaw, q.cov) for q in rows[cid]], angle=2)
        i_codes[c.n_runs].append(z2(x, P, codes[cid], angle=2))

    # loads
    run_loads: dict[str, list] = collections.defaultdict(list)
    own_loads = []
    for out in outs:
        for l in json.loads((out / "loads_smoother.json").read_text())["loads"]:
            if l["cov_world_m2"] is None or l["id"] not in loads:
                continue
            x, P = np.array(l["p_world_m"]), np.array(l["cov_world_m2"])
            run_loads[l["id"]].append((x, P))
            own_loads.append(z2(x, P, loads[l["id"]]))
    m_loads: dict[int, list[float]] = collections.defaultdict(list)
    i_loads: dict[int, list[float]] = collections.defaultdict(list)
    for l in json.loads((merged_dir / "map.json").read_text())["loads"]:
        if l["n_runs"] < 2 or l["id"] not in loads:
            continue
        m_loads[l["n_runs"]].append(z2(np.array(l["p_world_m"]), np.array(l["cov_world_m2"]), loads[l["id"]]))
        x, P = fused(run_loads[l["id"]])
        i_loads[l["n_runs"]].append(z2(x, P, loads[l["id"]]))

    print(
        f"\n# bench_map_merge_rendered {datetime.date.today()}: {args.flights} flights of "
        f"{args.duration:g} s, placement {100 * args.placement_error_m:g} cm / "
        f"{args.placement_error_deg:g} deg (seed {args.placement_seed}) {args.simulate_args}, {wd}"
    )
    with open(merged_dir / "changes.csv", newline="") as f:
        kinds = collections.Counter(r["change"] for r in csv.DictReader(f))
    print(
        f"changes between flights (the simulator moves no load: every 'moved' and 'disappeared' is "
        f"false): {dict(sorted(kinds.items()))}"
    )
    print(f"runs' own floor codes: 3-dof NEES {np.mean(own):.2f} over {len(own)} (code, run)")
    print(f"runs' own load maps: 3-dof NEES {np.mean(own_loads):.2f} over {len(own_loads)} (load, run)")
    table(
        "Floor codes (x, y, yaw), 3-dof NEES (ideal 3)",
        {"merged": m_codes, "merged, the CSV's sigma": d_codes, "independent fusion": i_codes},
    )
    table("Loads (x, y, z), 3-dof NEES (ideal 3)", {"merged": m_loads, "independent fusion": i_loads})


if __name__ == "__main__":
    main()
