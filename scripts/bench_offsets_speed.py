"""CPU time of the camera-IMU time-offset stage alone (floor profile, the whole-flight solve shared
with the mount check, front profile) on a synthetic flight, with its estimates, for before/after
comparisons on a loaded machine (run it from each checkout; the smallest of --repeats runs is
the figure: other processes only ever add to a run's CPU time).

    PYTHONPATH=$PWD python3 scripts/bench_offsets_speed.py [--duration 60] [--seed 1] [--repeats 3]

The flight is tests/test_timeoffset.py's `_flight` (random aisle survey, 200 Hz IMU with noise
and random-walk biases, PnP-like floor poses at 30 Hz, front-camera load sightings), both
offsets 0; the stage is `resolve_time_offsets(..., whole_flight=pipeline.SharedWholeFlight())`
as `fusion run` calls it."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from fusion.estimate import timeoffset  # noqa: E402
from fusion.estimate.timeoffset import resolve_time_offsets  # noqa: E402
from fusion.pipeline import SharedWholeFlight  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="flight length, s")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    from test_timeoffset import _flight, _log

    fl = _flight(args.duration, args.seed, 0.0, 0.0)
    log_ = _log(fl)
    parts = {"floor profile": "estimate_floor_offset", "front profile": "estimate_front_offset"}
    rows = []
    for _ in range(args.repeats):
        spent = dict.fromkeys(parts, 0.0)

        def timed(label, fn, spent=spent):
            def inner(*a, **k):
                c = time.process_time()
                try:
                    return fn(*a, **k)
                finally:
                    spent[label] += time.process_time() - c

            return inner

        originals = {name: getattr(timeoffset, name) for name in parts.values()}
        for label, name in parts.items():
            setattr(timeoffset, name, timed(label, originals[name]))
        try:
            c = time.process_time()
            shared = SharedWholeFlight()
            off = resolve_time_offsets(log_, fl["raw"], fl["obs"], whole_flight=shared)
            total = time.process_time() - c
        finally:
            for name, fn in originals.items():
                setattr(timeoffset, name, fn)
        rows.append((total, spent, off, shared.mount))
    best = min(rows, key=lambda r: r[0])
    total, spent, off, mount = best
    load = os.getloadavg()[0]
    print(
        f"{time.strftime('%Y-%m-%d %H:%M')} UTC, load {load:.1f}; synthetic {args.duration:.0f} s flight, "
        f"seed {args.seed}; CPU s, least of {args.repeats} runs (all: "
        + ", ".join(f"{r[0]:.2f}" for r in rows)
        + ")"
    )
    print("\n| part | CPU s |\n|---|--:|")
    print(f"| time offsets (whole stage) | {total:.2f} |")
    for label in parts:
        print(f"| {label} | {spent[label]:.2f} |")
    print(f"| whole-flight solve + mount (rest) | {total - sum(spent.values()):.2f} |")
    for c in off.cameras.values():
        print(
            f"{c.camera}: {c.offset_s * 1e3:+.4f} ± {(c.sigma_s or float('nan')) * 1e3:.4f} ms, "
            f"{c.evaluations} evaluations"
        )
    if mount is not None and mount.rotvec_rad is not None:
        sig = mount.sigma_rad if mount.sigma_rad is not None else np.full(3, np.nan)
        print(
            "mount deg: "
            + " / ".join(f"{np.degrees(w):+.5f} ± {np.degrees(s):.5f}" for w, s in zip(mount.rotvec_rad, sig))
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
