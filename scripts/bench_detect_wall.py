"""Where the wall time of the detect stage goes, outside the per-frame work (issue 13 item 2).

Runs `fusion.qr.detect.detect_flight`'s parts one by one on a flight log, timing each in the
main process and, chunk by chunk, in the workers (wall and CPU s, bytes, calls):

    open           open_flight (data.csv, sensor.yaml, IMU, ground truth)
    fingerprint    flight_fingerprint (one stat per image)
    pool start     first result's arrival less the first chunk's own work (process start-up,
                   imports, the context sent to each worker)
    chunks         per chunk in the worker: file read (open + read), PNG decode, detection
                   (zxing + refinement + records), CPU s of the chunk, pickled result bytes
    idle           main-process time waiting for a result in order (stragglers, the tail)
    cache write    write_cache (detections.csv); cache read: read_cache of the file written

The workers' read and decode times are split by timing `open`/`read` and `decode_image_bytes`
inside the image loader (fusion.log.euroc); PNG files never read since boot are read from disk (`--cold`
evicts this flight's files from the page cache first with posix_fadvise(DONTNEED), per file:
other files stay cached).

    PYTHONPATH=$PWD python3 scripts/bench_detect_wall.py FLIGHT [--workers 2] [--cold]
        [--out DIR] [--chunk-frames 32] [--json F]

Prints Markdown.  Load average before and after is printed: on a shared machine compare CPU
seconds and counts, not only wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import resource
import time
from pathlib import Path

import fusion.log.euroc as euroc_module
import fusion.qr.detect as detect_module
from fusion.log.sources import open_flight
from fusion.parallel import parallel_map, worker_count

_TIMES: dict[str, float] = {"decode": 0.0, "decode_cpu": 0.0}


_UNTIMED_DECODE = euroc_module.decode_image_bytes


def _timed_decode(data: bytes):
    """The loader's only decode call (`euroc.decode_image_bytes`), timed."""
    t, c = time.perf_counter(), time.process_time()
    try:
        return _UNTIMED_DECODE(data)
    finally:
        _TIMES["decode"] += time.perf_counter() - t
        _TIMES["decode_cpu"] += time.process_time() - c


def _install_timers() -> None:
    euroc_module.decode_image_bytes = _timed_decode  # type: ignore[assignment]


def _proc_counters() -> tuple[float, float, int]:
    """(CPU s, run-queue wait s, bytes read from storage) of this process (Linux /proc; zeros
    elsewhere): wall - CPU - run-queue wait = time blocked (disk, locks, pipes)."""
    try:
        with open("/proc/self/schedstat") as f:
            cpu_ns, wait_ns, _ = (int(v) for v in f.read().split())
        with open("/proc/self/io") as f:
            io = dict(line.split(": ") for line in f.read().splitlines())
        return cpu_ns / 1e9, wait_ns / 1e9, int(io["read_bytes"])
    except (OSError, ValueError, KeyError):
        return 0.0, 0.0, 0


def _timed_chunk(context, task):
    """detect.py's chunk function, with its time split (runs in the worker)."""
    _install_timers()
    for k in _TIMES:
        _TIMES[k] = 0.0
    p0 = _proc_counters()
    t0, c0 = time.time(), time.process_time()
    streams = context[0]
    stream = streams[task[0]]
    # the read alone: the loader reads and decodes; time a read of the same bytes first would
    # warm the cache, so the loader's whole time less its decode is the read
    load = type(stream).load_image
    spent = [0.0, 0.0]

    def timed_load(self, i, _load=load):
        t, c = time.perf_counter(), time.process_time()
        try:
            return _load(self, i)
        finally:
            spent[0] += time.perf_counter() - t
            spent[1] += time.process_time() - c

    type(stream).load_image = timed_load
    try:
        part = detect_module._detect_chunk(context, task)
    finally:
        type(stream).load_image = load
    part = (part[0], detect_module.pack_detections(part[1]), part[2], part[3])  # as detect_flight
    t1, c1 = time.time(), time.process_time()
    p1 = _proc_counters()
    tp = time.perf_counter()
    nbytes = len(pickle.dumps(part, protocol=pickle.HIGHEST_PROTOCOL))
    pickle_s = time.perf_counter() - tp
    info = {
        "pid": os.getpid(),
        "start": t0,
        "end": t1,
        "cpu_s": c1 - c0,
        "sched_cpu_s": p1[0] - p0[0],
        "runq_s": p1[1] - p0[1],
        "disk_bytes": p1[2] - p0[2],
        "load_s": spent[0],
        "load_cpu_s": spent[1],
        "decode_s": _TIMES["decode"],
        "decode_cpu_s": _TIMES["decode_cpu"],
        "bytes": nbytes,
        "pickle_s": pickle_s,
        "n_dets": len(detect_module.unpack_detections(part[1])),
        "frames": part[2].frames_total,
        "rusage_cpu_s": sum(resource.getrusage(resource.RUSAGE_SELF)[:2]),
        "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    return part, info


def _evict(log) -> int:
    n = 0
    for stream in log.cameras.values():
        for p in getattr(stream, "paths", []):
            try:
                fd = os.open(p, os.O_RDONLY)
            except OSError:
                continue
            try:
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
                n += 1
            finally:
                os.close(fd)
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight", type=Path)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--chunk-frames", type=int, default=32)
    ap.add_argument("--cold", action="store_true", help="evict the flight's images from the page cache first")
    ap.add_argument("--out", type=Path, default=None, help="write detections.csv here (default: a temp dir)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    load0 = os.getloadavg()
    rows: list[tuple[str, float, float]] = []  # (what, wall s, main CPU s)

    def clock():
        return time.perf_counter(), time.process_time()

    w0, c0 = clock()
    log = open_flight(args.flight)
    w1, c1 = clock()
    rows.append(("open_flight", w1 - w0, c1 - c0))
    if args.cold:
        print(f"evicted {_evict(log)} images from the page cache")
    w0, c0 = clock()
    fingerprint = detect_module.flight_fingerprint(log, "zxing")
    w1, c1 = clock()
    rows.append(("fingerprint", w1 - w0, c1 - c0))

    streams = {name: log.cameras[name] for name in sorted(log.cameras)}
    tasks = detect_module.detection_chunks(log, args.chunk_frames)
    workers = worker_count(args.workers)
    context = (streams, "zxing", False)
    ctx_bytes = len(pickle.dumps(context, protocol=pickle.HIGHEST_PROTOCOL))
    task_bytes = sum(len(pickle.dumps(t, protocol=pickle.HIGHEST_PROTOCOL)) for t in tasks)

    w0, c0 = clock()
    t_wall0 = time.time()
    infos, parts, arrivals, waits = [], [], [], []
    it = parallel_map(_timed_chunk, tasks, workers, context, preload=["fusion.qr.detect", __name__])
    while True:
        tw = time.perf_counter()
        try:
            part, info = next(it)
        except StopIteration:
            break
        waits.append(time.perf_counter() - tw)
        arrivals.append(time.time())
        parts.append((part[0], detect_module.unpack_detections(part[1]), part[2], part[3]))
        infos.append(info)
    w1, c1 = clock()
    rows.append(("parallel chunks (detect, main process view)", w1 - w0, c1 - c0))
    w0, c0 = clock()
    result = detect_module.assemble_detections(log, iter(parts), "zxing")
    w1, c1 = clock()
    rows.append(("assemble", w1 - w0, c1 - c0))

    import tempfile

    out_dir = args.out or Path(tempfile.mkdtemp(prefix="bench-detect-wall-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    cache = out_dir / detect_module.CACHE_NAME
    w0, c0 = clock()
    detect_module.write_cache(result, cache, fingerprint)
    w1, c1 = clock()
    rows.append(("write_cache", w1 - w0, c1 - c0))
    w0, c0 = clock()
    detect_module.read_cache(cache, fingerprint)
    w1, c1 = clock()
    rows.append(("read_cache (for comparison)", w1 - w0, c1 - c0))

    # worker-side breakdown
    n_frames = sum(i["frames"] for i in infos)
    by_pid: dict[int, list[dict]] = {}
    for i in infos:
        by_pid.setdefault(i["pid"], []).append(i)
    first_start = min(i["start"] for i in infos)
    last_end = max(i["end"] for i in infos)
    chunk_wall = sum(i["end"] - i["start"] for i in infos)
    cpu = sum(i["cpu_s"] for i in infos)
    load_s = sum(i["load_s"] for i in infos)
    decode_s = sum(i["decode_s"] for i in infos)
    load_cpu = sum(i["load_cpu_s"] for i in infos)
    decode_cpu = sum(i["decode_cpu_s"] for i in infos)
    pickled = sum(i["bytes"] for i in infos)
    pickle_s = sum(i["pickle_s"] for i in infos)
    load1 = os.getloadavg()

    print(
        f"\n{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, load average "
        f"{load0[0]:.1f} before, {load1[0]:.1f} after; {args.flight}, {n_frames} frames, "
        f"{len(tasks)} chunks of {args.chunk_frames}, {workers} workers{', cold' if args.cold else ''}"
    )
    print("\n| main process | wall [s] | CPU [s] |\n|---|--:|--:|")
    for what, w, c in rows:
        print(f"| {what} | {w:.2f} | {c:.2f} |")
    print("\n| workers | value |\n|---|--:|")
    print(f"| pool start: first chunk began after | {first_start - t_wall0:.2f} s |")
    print(
        f"| last chunk ended / last result arrived, after start | {last_end - t_wall0:.2f} / "
        f"{arrivals[-1] - t_wall0:.2f} s |"
    )
    print(f"| chunk wall, summed over chunks | {chunk_wall:.1f} s |")
    print(f"| chunk CPU, summed | {cpu:.1f} s ({1000 * cpu / n_frames:.2f} ms/frame) |")
    print(
        f"| of chunk wall: image load (read + decode) | {load_s:.1f} s, decode {decode_s:.1f} s, "
        f"read (load - decode) {load_s - decode_s:.1f} s |"
    )
    print(
        f"| of chunk CPU: image load | {load_cpu:.1f} s ({1000 * load_cpu / n_frames:.2f} ms/frame), decode "
        f"{decode_cpu:.1f} s, read and checks {load_cpu - decode_cpu:.1f} s |"
    )
    rest_cpu = cpu - load_cpu
    print(f"| of chunk CPU: detection (rest) | {rest_cpu:.1f} s ({1000 * rest_cpu / n_frames:.2f} ms/frame)|")
    print(f"| of chunk wall: detection (rest) | {chunk_wall - load_s:.1f} s |")
    runq = sum(i["runq_s"] for i in infos)
    sched_cpu = sum(i["sched_cpu_s"] for i in infos)
    disk = sum(i["disk_bytes"] for i in infos)
    print(
        f"| chunk wall - chunk CPU | {chunk_wall - cpu:.1f} s: waiting for a core {runq:.1f} s, "
        f"blocked (disk) {chunk_wall - sched_cpu - runq:.1f} s |"
    )
    print(f"| read from storage (not page cache) | {disk / 1e6:.0f} MB |")
    for pid, lst in sorted(by_pid.items()):
        busy = sum(i["end"] - i["start"] for i in lst)
        span = max(i["end"] for i in lst) - min(i["start"] for i in lst)
        print(
            f"| worker {pid}: chunks, busy / span, process CPU, peak RSS | {len(lst)}, {busy:.1f} / "
            f"{span:.1f} s, {max(i['rusage_cpu_s'] for i in lst):.1f} s, "
            f"{max(i['maxrss_mb'] for i in lst):.0f} MB |"
        )
    print(f"| context sent to each worker | {ctx_bytes / 1e6:.2f} MB |")
    print(f"| tasks sent, total | {task_bytes / 1e3:.1f} kB |")
    print(f"| results returned (pickled), total | {pickled / 1e6:.2f} MB ({pickle_s:.2f} s to pickle) |")
    print(f"| main process waiting for results, total | {sum(waits):.1f} s |")
    print(f"| detections | {len(result.detections)} |")
    print(f"| cache file | {cache.stat().st_size / 1e6:.1f} MB |")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "infos": infos, "t0": t_wall0}, indent=0))


if __name__ == "__main__":
    main()
