"""Per-frame front-end budget of `fusion run`: CPU ms per frame and frames/s per core, by stage.

On a flight log (EuRoC folder, e.g. `fusion simulate DIR --duration 20`), one process, every
frame of cam0 and cam1 (or the first --frames of each):

    PNG decode      the loader's decode of the file's bytes (read from disk first, not timed):
                    fusion.log.png's fast path where it applies, else OpenCV; and OpenCV alone
    zxing           zxing-cpp decoding (fusion.qr.detect's options)
    refine          fusion.qr.refine.refine_frames, REFINE_BATCH_FRAMES frames per call
    detect overhead detect_frames with the two above replaced by look-ups (records, counts)
    paper           the paper's Algorithms (floor poses + load mapping: fusion.qr.paper)
    pnp             our PnP (floor poses, load observations, unposed sightings: fusion.qr.pnp)

All times are CPU times of this process (time.process_time, best of --repeats): per-core cost,
pessimistic on a loaded machine (shared caches) but not inflated by waiting for a core.
The estimators' cost is divided by all frames of both cameras, as a run spends it.  Target
(issue 13 item 2): detection, refinement and pose >= 300 frames/s per core at 640x480 (PNG
decoding excluded).  Then corner accuracy on rendered frames with ground truth (the frames of
scripts/bench_detect.py: mean / p95 / max px of refined corners), PNG decoding options (the
flight's own files re-encoded with other zlib levels / strategies: decode ms and size), and the
peak RSS of one detection worker over the flight (`--rss`, alone; runs `detect_chunk` chunk by chunk
and reports the RSS after every tenth of the flight, to see whether anything grows).

    PYTHONPATH=$PWD python3 scripts/bench_frontend_speed.py FLIGHT [--frames N] [--repeats 3] [--rss]

Prints Markdown.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path
from unittest import mock

import cv2
import numpy as np

import fusion.qr.detect as detect_module
from fusion.log.euroc import decode_image_bytes
from fusion.log.sources import open_flight
from fusion.parallel import keep_freed_memory
from fusion.pipeline import (
    RunConfig,
    _unposed_load_observations,
    floor_context,
    front_context,
    localize_floor_chunk,
    localize_front_chunk,
    merge_floor_parts,
)
from fusion.qr import paper, pnp
from fusion.qr.detect import (
    REFINE_BATCH_FRAMES,
    _detect_image,
    detect_chunk,
    detect_frames,
    detection_chunks,
)
from fusion.qr.refine import POLISHED_CAMERAS, refine_frames

sys.path.insert(0, str(Path(__file__).resolve().parent))

TARGET_FPS = 300.0
ACCURACY_FRAMES = 60  # scripts/bench_detect.py's default
ACCURACY_BASELINE_PX = 0.013  # BENCHMARKS.md, refined corners at 640x480 (issue 13: within 10 %)
_LEVEL, _STRATEGY, _FILTER = cv2.IMWRITE_PNG_COMPRESSION, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_FILTER
_HUFFMAN = cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY
_UP, _NONE = cv2.IMWRITE_PNG_FILTER_UP, cv2.IMWRITE_PNG_FILTER_NONE
PNG_VARIANTS = (
    ("as stored", None),
    ("level 1, Huffman only, all filters (simulator before)", [_LEVEL, 1, _STRATEGY, _HUFFMAN]),
    ("level 1, Huffman only, filter Up (simulator now)", [_LEVEL, 1, _STRATEGY, _HUFFMAN, _FILTER, _UP]),
    ("level 1, Huffman only, filter None", [_LEVEL, 1, _STRATEGY, _HUFFMAN, _FILTER, _NONE]),
    ("level 1, default strategy, all filters", [_LEVEL, 1]),
    ("level 3, all filters", [_LEVEL, 3]),
    ("level 9, all filters", [_LEVEL, 9]),
    ("level 0 (stored), all filters", [_LEVEL, 0]),
    ("level 0 (stored), filter Up", [_LEVEL, 0, _FILTER, _UP]),
    ("level 0 (stored), filter None (simulator: png_compression=0)", [_LEVEL, 0, _FILTER, _NONE]),
)


def best_of(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def read_bytes(stream, n: int) -> list[bytes]:
    return [Path(p).read_bytes() for p in stream.paths[:n]]


def decode(blobs: list[bytes], flag: int | None = None) -> list[np.ndarray]:
    """The flight loader's decode (`euroc.decode_image_bytes`), or with `flag` OpenCV's alone."""
    if flag is None:
        return [decode_image_bytes(b) for b in blobs]
    return [cv2.imdecode(np.frombuffer(b, np.uint8), flag) for b in blobs]


def batches(items, size=REFINE_BATCH_FRAMES):
    return [items[s : s + size] for s in range(0, len(items), size)]


def stage_budget(log, n: int, repeats: int) -> dict:
    """CPU seconds per stage over the first n frames of each camera (module docstring)."""
    t: dict[str, float] = {}
    frames: dict[str, list[np.ndarray]] = {}
    stamps: dict[str, list[int]] = {}
    blobs_all = {}
    for name in sorted(log.cameras):
        stream = log.cameras[name]
        k = min(n, len(stream))
        blobs_all[name] = read_bytes(stream, k)
        frames[name] = decode(blobs_all[name])
        stamps[name] = [int(s) for s in stream.timestamps_ns[:k]]
    n_frames = sum(len(f) for f in frames.values())
    t["png"] = best_of(lambda: [decode(b) for b in blobs_all.values()], repeats)
    t["png_cv2"] = best_of(lambda: [decode(b, cv2.IMREAD_GRAYSCALE) for b in blobs_all.values()], repeats)
    raws = {name: [_detect_image(im, "zxing")[0] for im in ims] for name, ims in frames.items()}
    t["zxing"] = best_of(
        lambda: [[_detect_image(im, "zxing") for im in ims] for ims in frames.values()], repeats
    )

    def refine_all():
        for name, ims in frames.items():
            cam = log.cameras[name].camera
            for b_im, b_raw in zip(batches(ims), batches(raws[name])):
                codes = [[(c.corners_px, c.modules) for c in rs] for rs in b_raw]
                refine_frames(b_im, codes, cam, polish=name in POLISHED_CAMERAS)

    t["refine"] = best_of(refine_all, repeats)
    dets: dict[str, dict[int, list]] = {}

    def detect_all():
        for name, ims in frames.items():
            cam = log.cameras[name].camera
            by_frame: dict[int, list] = {}
            for b_im, b_ts in zip(batches(ims), batches(stamps[name])):
                for ts, fd in zip(b_ts, detect_frames(b_im, name, b_ts, cam)):
                    if fd:
                        by_frame[ts] = fd
            dets[name] = by_frame

    detect_all()
    # detect_frames' own work (records, counts): the decoder and refinement replaced by look-ups
    # of their results, so it is timed alone rather than as a difference of noisy totals
    decoded = {id(im): _detect_image(im, "zxing") for ims in frames.values() for im in ims}
    refined = {}
    for name, ims in frames.items():
        cam = log.cameras[name].camera
        for b_im, b_raw in zip(batches(ims), batches(raws[name])):
            codes = [[(c.corners_px, c.modules) for c in rs] for rs in b_raw]
            refined[tuple(id(im) for im in b_im)] = refine_frames(
                b_im, codes, cam, polish=name in POLISHED_CAMERAS
            )
    with mock.patch.object(detect_module, "_detect_image", lambda im, backend: decoded[id(im)]):
        with mock.patch.object(
            detect_module,
            "refine_frames",
            lambda ims, codes, cam, stats, polish: refined[tuple(map(id, ims))],
        ):
            t["overhead"] = best_of(detect_all, repeats)
    cfg = RunConfig(workers=1, progress=False)
    floor_ctx = floor_context(log, cfg)  # the run's own (it grew the --map layout)
    paper_cost, pnp_cost = [], []
    for _ in range(repeats):
        # the paper's and PnP's halves of localize_*_chunk, timed apart
        t0 = time.process_time()
        traj_paper = paper.paper_trajectory(dets["cam0"], log.floor.camera, log.world, cfg.th_px)
        t1 = time.process_time()
        traj_pnp, _ = pnp.pnp_trajectory(dets["cam0"], log.floor.camera, log.world, cfg.corner_sigma_px)
        t2 = time.process_time()
        tp, tq = t1 - t0, t2 - t1
        if "cam1" in dets and log.front is not None:
            cam1 = log.front.camera
            t0 = time.process_time()
            paper.paper_load_observations(dets["cam1"], cam1, log.world, traj_paper, cfg.th_px)
            t1 = time.process_time()
            obs = pnp.pnp_load_observations(dets["cam1"], cam1, log.world, traj_pnp, cfg.corner_sigma_px)
            _unposed_load_observations(
                dets["cam1"], {o.timestamp_ns for o in obs}, cam1, log.world, cfg.corner_sigma_px
            )
            t2 = time.process_time()
            tp, tq = tp + t1 - t0, tq + t2 - t1
        paper_cost.append(tp)
        pnp_cost.append(tq)
    t["paper"], t["pnp"] = min(paper_cost), min(pnp_cost)
    # the pipeline's own chunk functions once, as a check that the split above covers them
    t0 = time.process_time()
    floor = merge_floor_parts([localize_floor_chunk(floor_ctx, dets["cam0"])], cfg)
    if "cam1" in dets and log.front is not None:
        localize_front_chunk(front_context(log, floor, cfg), dets["cam1"])
    t["localize_chunks"] = time.process_time() - t0
    codes = sum(len(d) for by in dets.values() for d in by.values())
    return {"t": t, "frames": n_frames, "codes": codes, "blobs": blobs_all, "frames_img": frames}


def png_options(blobs: dict[str, list[bytes]], frames: dict[str, list[np.ndarray]], repeats: int) -> list:
    rows = []
    ims = [im for name in sorted(frames) for im in frames[name]]
    for label, params in PNG_VARIANTS:
        if params is None:
            enc = [b for name in sorted(blobs) for b in blobs[name]]
        else:
            enc = [cv2.imencode(".png", im, params)[1].tobytes() for im in ims]
        dec = decode(enc)
        assert all(np.array_equal(a, b) for a, b in zip(dec, ims)), label  # lossless
        t_gray = best_of(lambda enc=enc: decode(enc), repeats) / len(enc)
        t_unch = best_of(lambda enc=enc: decode(enc, cv2.IMREAD_GRAYSCALE), repeats) / len(enc)
        rows.append((label, 1e3 * t_gray, 1e3 * t_unch, np.mean([len(b) for b in enc]) / 1024))
    return rows


def accuracy(seed: int = 0) -> dict:
    """Refined corner errors on scripts/bench_detect.py's rendered 640x480 frames."""
    from bench_detect import make_frames

    from fusion.qr.detect import detect_image

    camera, frames, truths = make_frames(640, 480, ACCURACY_FRAMES, seed)
    raws = [detect_image(im) for im in frames]
    errs, failed, found = [], 0, 0
    for b_im, b_raw, b_truth in zip(batches(frames), batches(raws), batches(truths)):
        res = refine_frames(b_im, [[(r.corners_px, r.modules) for r in rs] for rs in b_raw], camera)
        for rs, refs, truth in zip(b_raw, res, b_truth):
            for r, c in zip(rs, refs):
                if r.payload not in truth:
                    continue
                found += 1
                if c is None or c.stage != 2:
                    failed += 1
                    continue
                errs.append(np.linalg.norm(c.corners_px - truth[r.payload], axis=1))
    e = np.concatenate(errs)
    return {"mean": e.mean(), "p95": np.percentile(e, 95), "max": e.max(), "failed": failed, "codes": found}


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def worker_rss(log, chunk_frames: int = 32) -> list[tuple[int, float]]:
    """(frames done, RSS MB) after every tenth of the flight, running `detect_chunk` as a
    detection worker does (results dropped, as a worker sends them away)."""
    tasks = detection_chunks(log, chunk_frames)
    out, done = [(0, rss_mb())], 0
    step = max(1, len(tasks) // 10)
    for i, task in enumerate(tasks):
        part = detect_chunk(log, task)
        done += part[2].frames_total
        del part
        if (i + 1) % step == 0 or i == len(tasks) - 1:
            out.append((done, rss_mb()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight", type=Path)
    ap.add_argument("--frames", type=int, default=600, help="frames per camera (default 600)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rss", action="store_true", help="only the detection worker's RSS over the flight")
    ap.add_argument("--no-png", action="store_true", help="skip the PNG options table")
    ap.add_argument(
        "--default-malloc", action="store_true", help="leave glibc's malloc thresholds (workers raise them)"
    )
    args = ap.parse_args()
    cv2.setNumThreads(1)  # a worker's settings (fusion.parallel)
    tuned = keep_freed_memory() if not args.default_malloc else False
    log = open_flight(args.flight)
    if args.rss:
        # alone in this process: the budget below keeps its frames in memory
        print("| frames detected (one worker, chunk by chunk) | RSS MB |")
        print("|--:|--:|")
        for done, mb in worker_rss(log):
            print(f"| {done} | {mb:.0f} |")
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"\nPeak RSS of this process (ru_maxrss): {peak:.0f} MB")
        return
    r = stage_budget(log, args.frames, args.repeats)
    t, n = r["t"], r["frames"]
    res = {name: f"{s.camera.width}x{s.camera.height}" for name, s in log.cameras.items()}
    print(
        f"Flight {args.flight} ({', '.join(f'{k} {v}' for k, v in sorted(res.items()))}), {n} frames, "
        f"{r['codes']} detections ({r['codes'] / n:.2f} per frame); "
        f"CPU ms per frame, best of {args.repeats}; "
        f"malloc thresholds raised as in a worker: {tuned}."
    )
    print()
    print("| stage | ms / frame | frames/s per core |")
    print("|---|--:|--:|")
    order = [
        ("zxing decode", "zxing"),
        ("refinement", "refine"),
        ("detection overhead (records, counts)", "overhead"),
        ("paper (Algorithms 1-6)", "paper"),
        ("PnP (floor poses, load observations)", "pnp"),
    ]
    total = 0.0
    for label, key in order:
        ms = 1e3 * t[key] / n
        total += ms
        print(f"| {label} | {ms:.3f} | {1e3 / ms:.0f} |")
    print(
        f"| **total, PNG decoding excluded** | **{total:.3f}** | **{1e3 / total:.0f}** "
        f"(target {TARGET_FPS:.0f}) |"
    )
    png_ms = 1e3 * t["png"] / n
    print(f"| PNG decode (the loader: fusion.log.png, else OpenCV) | {png_ms:.3f} | {1e3 / png_ms:.0f} |")
    cv2_ms = 1e3 * t["png_cv2"] / n
    print(f"| (PNG decode by OpenCV alone: cv2.imdecode, grey) | {cv2_ms:.3f} | {1e3 / cv2_ms:.0f} |")
    print(f"| total with PNG decoding | {total + png_ms:.3f} | {1e3 / (total + png_ms):.0f} |")
    print()
    print(
        f"(check: the pipeline's localize_floor_chunk + localize_front_chunk once: "
        f"{1e3 * t['localize_chunks'] / n:.3f} ms / frame; paper + PnP above: "
        f"{1e3 * (t['paper'] + t['pnp']) / n:.3f})"
    )
    print()
    a = accuracy()
    print(
        f"Corner accuracy ({ACCURACY_FRAMES} rendered 640x480 frames of scripts/bench_detect.py, "
        f"{a['codes']} codes): mean {a['mean']:.4f} px (baseline {ACCURACY_BASELINE_PX} px, "
        f"{a['mean'] / ACCURACY_BASELINE_PX - 1:+.0%}), p95 {a['p95']:.3f} px, max {a['max']:.3f} px, "
        f"not refined {a['failed']}."
    )
    if not args.no_png:
        print()
        print(
            "| PNG encoding (the flight's frames re-encoded) | decode ms, the loader "
            "| OpenCV alone (IMREAD_GRAYSCALE) | KiB / frame |"
        )
        print("|---|--:|--:|--:|")
        for label, g, u, kib in png_options(r["blobs"], r["frames_img"], args.repeats):
            print(f"| {label} | {g:.3f} | {u:.3f} | {kib:.0f} |")


if __name__ == "__main__":
    main()
