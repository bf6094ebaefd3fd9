"""Wall time and CPU of whole `fusion run`s, two code trees alternating (issue 13.2: >= 10x real
time), so that both see the same machine, hour and page cache.

    python3 scripts/bench_run_ab.py LOG --tree before=/path/to/old/checkout --tree after=$PWD
        [--reps 2] [--out-dir /tmp/fusion-ab] [--duration-s 600]

Each run is `python3 -m fusion.cli run LOG --out OUT -q` with PYTHONPATH at its tree and a fresh
OUT (no detection cache).  CPU is the machine's busy time over the run (/proc/stat: all but idle
and iowait): `fusion run`'s detection workers are children of a forkserver that is never waited
for, so the run's own rusage misses them; run it on an otherwise idle machine.  `--duration-s`
is the flight's length for the real-time factor (the 10-minute benchmark flight: 600).  Prints
one Markdown row per run; the last OUT of each tree is kept, to compare their outputs.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path


def busy_cpu_s() -> float:
    """Busy CPU seconds of the whole machine since boot (/proc/stat: all but idle and iowait)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return (sum(v) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--tree", action="append", required=True, help="NAME=PATH of a checkout")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--out-dir", type=Path, default=Path("/tmp/fusion-ab"))
    ap.add_argument("--duration-s", type=float, default=600.0)
    args = ap.parse_args()
    trees = dict(t.split("=", 1) for t in args.tree)
    print(
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.machine()}, "
        f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; {args.log}\n"
    )
    print("| run | tree | exit | wall [s] | real time | machine busy CPU [s] |")
    print("|---|---|--:|--:|--:|--:|")
    for rep in range(args.reps):
        for name, tree in trees.items():
            out = args.out_dir / name
            shutil.rmtree(out, ignore_errors=True)
            out.parent.mkdir(parents=True, exist_ok=True)
            env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
            cpu0, t0 = busy_cpu_s(), time.perf_counter()
            p = subprocess.run(
                [sys.executable, "-m", "fusion.cli", "run", str(args.log), "--out", str(out), "-q"],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            )
            wall, cpu = time.perf_counter() - t0, busy_cpu_s() - cpu0
            print(
                f"| {rep + 1} | {name} | {p.returncode} | {wall:.1f} | {args.duration_s / wall:.2f}x "
                f"| {cpu:.1f} |",
                flush=True,
            )
            if p.returncode:
                print(p.stderr.strip().splitlines()[-1] if p.stderr.strip() else "(no message)")


if __name__ == "__main__":
    main()
