"""Simulator speed: frames rendered per second on one core (640x480 and 1280x720, floor and
front camera, PNG encoding included) and the wall time of a full two-camera 30 fps flight on all
cores, with the fraction of floor frames in which zxing-cpp decodes a floor code.

    /work/venv/bin/python scripts/bench_simulator.py [--duration 60] [--frames 60]

Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from fusion.sim.scenarios import build_scenario
from fusion.sim.simulate import frame_renderer, simulate


def frames_per_second(resolution, n_frames: int) -> float:
    """Camera frames (each camera counts) per second on one core, PNG encoding included."""
    sc = build_scenario("default", resolution)
    render = frame_renderer(sc, seed=0, png_compression=1)
    render(0, 5.0)  # warm the per-camera caches
    t0 = time.perf_counter()
    for k in range(n_frames):
        render(k, 5.0 + 50.0 * k / n_frames)
    return 2 * n_frames / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="flight length (s)")
    ap.add_argument("--frames", type=int, default=60, help="frame pairs per single-core timing")
    ap.add_argument("--scenario", default="default")
    args = ap.parse_args()
    rows = []
    for res in [(640, 480), (1280, 720)]:
        fps = frames_per_second(res, args.frames)
        rows.append((f"render + PNG, one core, {res[0]}x{res[1]}", f"{fps:.1f} frames/s"))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "flight"
        r = simulate(
            out, args.scenario, duration_s=args.duration, seed=0, progress=False, workers=os.cpu_count()
        )
        size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
        rows.append(
            (
                f"{args.duration:.0f} s flight, 2 cameras x 30 fps, 640x480, {os.cpu_count()} workers",
                f"{r.wall_time_s:.1f} s wall ({size / 1e6:.0f} MB)",
            )
        )
        rows.append(
            (
                "  of which rendering + PNG CPU time, all workers",
                f"{r.render_cpu_s:.1f} s ({1e3 * r.render_cpu_s / (2 * r.n_frames):.1f} ms per frame)",
            )
        )
    # readability is measured separately (zxing on every floor frame costs extra time)
    with tempfile.TemporaryDirectory() as tmp:
        r = simulate(
            Path(tmp) / "f",
            args.scenario,
            duration_s=args.duration,
            seed=0,
            progress=False,
            workers=os.cpu_count(),
            check_readable=True,
        )
        rows.append(
            (
                "floor frames with a readable floor code (all / outside blackouts)",
                f"{r.readable_floor_fraction:.3f} / {r.readable_floor_fraction_outside_blackouts:.3f}",
            )
        )
    print(f"| simulator ({args.scenario}) | measured |")
    print("|---|---|")
    for k, v in rows:
        print(f"| {k} | {v} |")


if __name__ == "__main__":
    main()
