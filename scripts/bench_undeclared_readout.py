"""Does `fusion run` notice a rolling-shutter floor camera declared global shutter?  For each
flight (EuRoC folder, e.g. from `fusion simulate --readout-ms MS`), its floor camera is taken as
global shutter whatever sensor.yaml says, and `check_undeclared_readout` runs on the flight's
uncorrected PnP poses: the readout it suggests, the frames that fit better with it, the median
chi^2 / dof without and with it, the sign test's p-value, and its CPU time.  `--ungated` prints
the grid's best readout even where the check would stay silent (to see how far from its
thresholds a global-shutter flight is).

    PYTHONPATH=$PWD python3 scripts/bench_undeclared_readout.py FLIGHT... [--ungated]

Detections are cached in FLIGHT-det/detections.csv next to each flight."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import fusion.qr.rolling_shutter as rs
from fusion.log import LogOptions, read_flight
from fusion.qr.detect import detect_flight
from fusion.qr.pnp import pnp_trajectory


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+", type=Path)
    ap.add_argument(
        "--ungated", action="store_true", help="report the best readout even when not significant"
    )
    args = ap.parse_args()
    if args.ungated:
        rs.UNDECLARED_MIN_COST_DROP, rs.UNDECLARED_P_VALUE = -float("inf"), 2.0
    print(
        "| flight | true readout ms | suggested ms | frames better / used "
        "| median chi2/dof 0 -> it | p | CPU s |"
    )
    print("|---|--:|--:|--:|--:|--:|--:|")
    for flight in args.flights:
        log = read_flight(flight, LogOptions())
        cache = flight.parent / f"{flight.name}-det"
        cache.mkdir(exist_ok=True)
        det = detect_flight(log, cache_path=cache / "detections.csv", progress=False)
        truth_ms = log.floor.camera.readout_s * 1e3
        cam = replace(log.floor.camera, line_delay_s=0.0)
        t = time.process_time()
        raw = pnp_trajectory(det.by_frame("cam0"), cam, log.world)[0]
        found = rs.check_undeclared_readout(det, cam, log.world, log.imu, raw)
        cpu = time.process_time() - t
        if found is None:
            print(f"| {flight.name} | {truth_ms:.1f} | none | | | | {cpu:.1f} |", flush=True)
            continue
        print(
            f"| {flight.name} | {truth_ms:.1f} | {found.readout_s * 1e3:.1f} "
            f"| {found.n_better} / {found.n_frames} "
            f"| {found.chi2_per_dof_global:.2f} -> {found.chi2_per_dof_rolling:.2f} "
            f"| {found.p_value:.1e} | {cpu:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
