"""Peak memory of a whole `fusion run`, per stage, measured from outside the process.

    python scripts/bench_run_memory.py LOG OUT [--interval S] [-- EXTRA fusion run ARGS]

Runs `python -m fusion.cli run LOG --out OUT --force` as a child and samples its resident set
(/proc/PID/status VmRSS, which counts GTSAM's C++ heap and numpy alike) every `--interval`
seconds, crediting each sample to the stage the run last announced on stderr (its progress and
log lines).  Prints one row per announced line, in order: the largest RSS seen while it was the
last line, and when it appeared.  Put a copy of the flight's detections.csv in OUT to time the
run with detections cached.  Linux only (/proc).  The pool workers are separate processes and
not counted (`bench_pipeline.py` reports the largest)."""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time
from pathlib import Path

PROGRESS_MARKS = ("frame/s", "it/s")  # tqdm's redrawn bars: not a stage


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--interval", type=float, default=0.2, help="seconds between samples (default 0.2)")
    ap.add_argument("extra", nargs=argparse.REMAINDER, help="more `fusion run` arguments, after --")
    args = ap.parse_args()
    extra = [a for a in args.extra if a != "--"]
    cmd = [sys.executable, "-m", "fusion.cli", "run", str(args.log), "--out", str(args.out), "--force"]
    cmd += extra
    child = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, bufsize=1)
    assert child.stderr is not None
    stderr = child.stderr
    stage = ["start (reading the log)"]

    def follow() -> None:
        for line in stderr:
            for part in line.replace("\r", "\n").split("\n"):
                part = part.strip()
                if part and not any(m in part for m in PROGRESS_MARKS):
                    stage[0] = part[:90]

    threading.Thread(target=follow, daemon=True).start()
    t0 = time.perf_counter()
    rows: dict[str, tuple[float, float]] = {}  # stage -> (peak MB, first seen s); insertion order
    while child.poll() is None:
        mb = rss_mb(child.pid)
        if mb is None:
            break
        name = stage[0]
        peak, first = rows.get(name, (0.0, time.perf_counter() - t0))
        rows[name] = (max(peak, mb), first)
        time.sleep(args.interval)
    child.wait()
    wall = time.perf_counter() - t0
    when = time.strftime("%Y-%m-%d %H:%M")
    print(f"{when} UTC, `fusion run {args.log}`: exit {child.returncode}, {wall:.1f} s")
    print("\n| from s | peak RSS MB | stage (the run's last line) |\n|--:|--:|---|")
    for name, (peak, first) in rows.items():
        print(f"| {first:.1f} | {peak:.0f} | {name.replace('|', '/')} |")
    if rows:
        print(f"\npeak RSS of the run's main process: {max(p for p, _ in rows.values()):.0f} MB")
    return child.returncode


if __name__ == "__main__":
    sys.exit(main())
