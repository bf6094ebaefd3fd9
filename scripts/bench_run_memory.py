"""Peak memory of a whole `fusion run`, per stage, measured from outside the process.

    python scripts/bench_run_memory.py [--interval S] [--batch] [--trace CSV] LOG OUT [-- RUN ARGS]

Runs `python -m fusion.cli run LOG --out OUT --force` (with `--batch`: `fusion batch LOG --out OUT`,
whose Dask workers are the descendants below; OUT must be new) as a child and samples its resident set
(/proc/PID/status VmRSS, which counts GTSAM's C++ heap and numpy alike) every `--interval`
seconds, crediting each sample to the stage the run last announced on stderr (its progress and
log lines).  Prints one row per announced line, in order: the largest RSS seen while it was the
last line, and when it appeared.  Put a copy of the flight's detections.csv in OUT to time the
run with detections cached.  Linux only (/proc).  Also printed: the main process's exact peak and
CPU seconds (the kernel's, from wait4: the samples can miss a short peak), and the largest peak
(VmHWM) and summed CPU seconds of its descendant processes (the pool workers and their
forkserver: sampled, so a worker's CPU after its last sample is missed)."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

PROGRESS_MARKS = ("frame/s", "it/s")  # tqdm's redrawn bars: not a stage


def status_mb(pid: int, key: str = "VmRSS") -> float | None:
    """/proc/PID/status's `key` (VmRSS: resident now; VmHWM: the process's peak) in MiB."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def rss_mb(pid: int) -> float | None:
    return status_mb(pid, "VmRSS")


def _stat_fields(pid: int) -> list[str] | None:
    """/proc/PID/stat's fields after the command name (which may hold spaces and parentheses):
    [0] state, [1] ppid, ..., [11] utime, [12] stime (clock ticks)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return None


def descendants(pid: int) -> list[int]:
    """Every live process below `pid` (its children, their children, ...)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            f = _stat_fields(int(d.name))
            if f is not None:
                children.setdefault(int(f[1]), []).append(int(d.name))
    out, todo = [], list(children.get(pid, []))
    while todo:
        c = todo.pop()
        out.append(c)
        todo += children.get(c, [])
    return out


class DescendantSampler(threading.Thread):
    """Samples `pid`'s descendant processes every `interval` s until stopped: each one's peak
    resident set (VmHWM, its own high-water mark: one sample before it ends is enough) and CPU
    seconds (utime + stime: the CPU after a process's last sample is missed).  RUSAGE_CHILDREN
    cannot give these: the pool workers are the forkserver's children, not this process's."""

    def __init__(self, pid: int, interval: float = 0.5, trace: Path | None = None) -> None:
        super().__init__(daemon=True)
        self.pid, self.interval = pid, interval
        self.hwm_mb: dict[int, float] = {}
        self.cpu_s: dict[int, float] = {}
        self.trace = trace  # a CSV of every sample: seconds, pid, VmRSS MiB, VmHWM MiB
        self._stopped = threading.Event()

    def run(self) -> None:
        tick = os.sysconf("SC_CLK_TCK")
        t0 = time.perf_counter()
        trace = open(self.trace, "w") if self.trace is not None else None  # noqa: SIM115 (closed below)
        if trace is not None:
            trace.write("t_s,pid,rss_mb,hwm_mb\n")
        while not self._stopped.is_set():
            for c in descendants(self.pid):
                hwm = status_mb(c, "VmHWM")
                if hwm is not None:
                    self.hwm_mb[c] = max(hwm, self.hwm_mb.get(c, 0.0))
                    if trace is not None:
                        rss = status_mb(c, "VmRSS")
                        trace.write(f"{time.perf_counter() - t0:.1f},{c},{rss or 0:.0f},{hwm:.0f}\n")
                f = _stat_fields(c)
                if f is not None:
                    self.cpu_s[c] = (int(f[11]) + int(f[12])) / tick
            self._stopped.wait(self.interval)
        if trace is not None:
            trace.close()

    def stop(self) -> None:
        self._stopped.set()
        self.join()

    def largest_mb(self) -> float | None:
        return max(self.hwm_mb.values()) if self.hwm_mb else None

    def summary(self) -> str:
        if not self.hwm_mb:
            return "descendant processes: none seen"
        return (
            f"descendant processes (pool workers, forkserver): {len(self.hwm_mb)}, largest peak "
            f"(VmHWM) {self.largest_mb():.0f} MB, CPU {sum(self.cpu_s.values()):.1f} s summed"
        )

    def table(self) -> str:
        """One row per descendant process: its peak (VmHWM) and CPU seconds, largest first."""
        rows = sorted(self.hwm_mb, key=lambda c: -self.hwm_mb[c])
        lines = ["| pid | peak MB (VmHWM) | CPU s |", "|--:|--:|--:|"]
        lines += [f"| {c} | {self.hwm_mb[c]:.0f} | {self.cpu_s.get(c, 0.0):.1f} |" for c in rows]
        return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--interval", type=float, default=0.2, help="seconds between samples (default 0.2)")
    ap.add_argument("--batch", action="store_true", help="run `fusion batch` (Dask) instead of `fusion run`")
    ap.add_argument(
        "--trace", type=Path, help="write every descendant sample (s, pid, VmRSS, VmHWM) to this CSV"
    )
    ap.add_argument("extra", nargs=argparse.REMAINDER, help="more `fusion run` arguments, after --")
    args = ap.parse_args()
    extra = [a for a in args.extra if a != "--"]
    command = "batch" if args.batch else "run"
    cmd = [sys.executable, "-m", "fusion.cli", command, str(args.log), "--out", str(args.out)]
    cmd += extra if args.batch else ["--force", *extra]
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
    workers = DescendantSampler(child.pid, trace=args.trace)
    workers.start()
    t0 = time.perf_counter()
    rows: dict[str, tuple[float, float]] = {}  # stage -> (peak MB, first seen s); insertion order
    usage = None
    while True:
        # reaped here, not by poll(), so that the kernel's accounting of it comes back too
        pid, status, ru = os.wait4(child.pid, os.WNOHANG)
        if pid == child.pid:
            child.returncode, usage = os.waitstatus_to_exitcode(status), ru
            break
        mb = rss_mb(child.pid)
        if mb is not None:  # None: exiting (a zombie has no VmRSS)
            name = stage[0]
            peak, first = rows.get(name, (0.0, time.perf_counter() - t0))
            rows[name] = (max(peak, mb), first)
        time.sleep(args.interval)
    wall = time.perf_counter() - t0
    workers.stop()
    when = time.strftime("%Y-%m-%d %H:%M")
    print(f"{when} UTC, `fusion {command} {args.log}`: exit {child.returncode}, {wall:.1f} s")
    print("\n| from s | peak RSS MB | stage (the run's last line) |\n|--:|--:|---|")
    for name, (peak, first) in rows.items():
        print(f"| {first:.1f} | {peak:.0f} | {name.replace('|', '/')} |")
    if rows:
        print(f"\npeak RSS of the run's main process: {max(p for p, _ in rows.values()):.0f} MB (sampled)")
    if usage is not None:
        # ru_maxrss, KiB on Linux: the main process's peak (or a reaped child's, if larger)
        print(
            f"main process, from the kernel (wait4): peak {usage.ru_maxrss / 1024:.0f} MB = "
            f"{usage.ru_maxrss * 1024:,} bytes; CPU {usage.ru_utime + usage.ru_stime:.1f} s "
            f"(user {usage.ru_utime:.1f}, system {usage.ru_stime:.1f})"
        )
    print(workers.summary())
    if args.batch:
        print("\nthe batch's processes (Dask's workers and their helpers):\n" + workers.table())
    print("(MB are MiB, kB / 1024: 10^9 bytes = 954 MiB, 1 GiB = 1,024 MiB)")
    return child.returncode


if __name__ == "__main__":
    sys.exit(main())
