"""Speed of `fusion run` on the same two-camera flight as an EuRoC folder (PNG frames) and as a
ROS 2 bag (MCAP) with JPEG sensor_msgs/CompressedImage (issue 11, item 8: the bag must run at
least as fast as the folder), with the time per stage, the per-frame decode time of each
format, and how close the results are (JPEG is lossy).

    python scripts/bench_logs.py [--minutes 10] [--workdir /tmp/fusion-bench-logs] [--order euroc,bag]

The flight is simulated once into WORKDIR/log-<minutes>min (EuRoC) and exported once to
WORKDIR/log-<minutes>min.mcap; both are reused on later runs.  Each format runs into a fresh
output folder (no detection cache).  Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import time
from pathlib import Path

import numpy as np

from fusion.log import open_flight
from fusion.log.convert import export_flight
from fusion.pipeline import RunConfig, run
from fusion.sim.simulate import simulate

DECODE_SAMPLE_FRAMES = 200


def decode_ms_per_frame(log_path: Path, n: int) -> float:
    """Mean wall time (ms) to read and decode one floor frame, sequentially, over the first n."""
    flight = open_flight(log_path)
    cam = flight.floor
    n = min(n, len(cam))
    t = time.perf_counter()
    for i, _frame in enumerate(cam.frames()):
        if i + 1 >= n:
            break
    return (time.perf_counter() - t) / n * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/fusion-bench-logs"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--order", default="euroc,bag", help="which format runs first")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    euroc = args.workdir / f"log-{args.minutes:g}min"
    bag = args.workdir / f"log-{args.minutes:g}min.mcap"
    times: dict[str, float] = {}
    if not (euroc / "world.yaml").exists():
        t = time.perf_counter()
        simulate(euroc, scenario="default", duration_s=60 * args.minutes, seed=args.seed, overwrite=True)
        times["simulate_s"] = time.perf_counter() - t
    if not bag.exists():
        t = time.perf_counter()
        export_flight(euroc, bag, image_format="jpeg")
        times["export_jpeg_mcap_s"] = time.perf_counter() - t
    sizes = {
        "euroc_mb": sum(p.stat().st_size for p in euroc.rglob("*") if p.is_file()) / 1e6,
        "bag_mb": bag.stat().st_size / 1e6,
    }
    decode = {
        "euroc_png_ms": decode_ms_per_frame(euroc, DECODE_SAMPLE_FRAMES),
        "bag_jpeg_ms": decode_ms_per_frame(bag, DECODE_SAMPLE_FRAMES),
    }
    results = {}
    for name in args.order.split(","):
        src = euroc if name == "euroc" else bag
        out = args.workdir / f"out-{name}-{args.minutes:g}min"
        shutil.rmtree(out, ignore_errors=True)
        t = time.perf_counter()
        res = run(src, out, RunConfig(progress=False, force=True, workers=args.workers))
        wall = time.perf_counter() - t
        per = (res.metrics or {}).get("trajectories", {})
        results[name] = {
            "wall_s": wall,
            "stages_s": res.timings_s,
            "floor_frames_with_code": res.detection_stats.get("floor_frames_with_code"),
            "ate_rmse_cm": {k: 100 * v["ate_rmse_m"] for k, v in per.items() if "ate_rmse_m" in v},
        }
    flight_s = 60 * args.minutes
    print(
        f"\n{time.strftime('%Y-%m-%d %H:%M')} UTC, {platform.machine()}, {os.cpu_count()} cores "
        f"(loaded by parallel sessions: load average {os.getloadavg()[0]:.1f}), "
        f"python {platform.python_version()}; flight {flight_s:g} s, 2 cameras x 30 fps, 640x480"
    )
    print(f"\nsizes: EuRoC folder {sizes['euroc_mb']:.0f} MB, JPEG MCAP bag {sizes['bag_mb']:.0f} MB")
    print(
        f"decode one floor frame (sequential, first {DECODE_SAMPLE_FRAMES}): PNG "
        f"{decode['euroc_png_ms']:.2f} ms, bag JPEG {decode['bag_jpeg_ms']:.2f} ms"
    )
    stages = sorted({k for r in results.values() for k in r["stages_s"]})
    print("\n| format | wall s | " + " | ".join(stages) + " | frames with code | ATE smoother cm |")
    print("|---" * (len(stages) + 4) + "|")
    for name, r in results.items():
        cells = " | ".join(f"{r['stages_s'].get(s, float('nan')):.1f}" for s in stages)
        print(
            f"| {name} | {r['wall_s']:.1f} | {cells} | {r['floor_frames_with_code']} | "
            f"{r['ate_rmse_cm'].get('smoother', float('nan')):.3f} |"
        )
    if "euroc" in results and "bag" in results:
        ratio = results["bag"]["wall_s"] / results["euroc"]["wall_s"]
        print(f"\nbag / EuRoC wall time: {ratio:.2f} ({'met' if ratio <= 1.0 else 'NOT met'}: <= 1)")
    report = {"times": times, "sizes": sizes, "decode": decode, "results": results, "minutes": args.minutes}
    (args.workdir / f"bench_logs-{args.minutes:g}min.json").write_text(
        json.dumps(report, indent=1, default=lambda o: float(o) if isinstance(o, np.floating) else str(o))
    )


if __name__ == "__main__":
    main()
