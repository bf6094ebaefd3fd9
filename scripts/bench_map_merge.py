"""Benchmark of `fusion map merge`'s floor codes (fusion.warehouse.floorcodes.merge_floor_codes):
is a merged map's sigma honest however many flights saw a code?

Synthetic floors (no rendering): floor codes on a 1 m grid (13 x 11), each stuck down off its
payload's place by N(0, sigma_m) per axis and N(0, sigma_deg) in yaw, the same errors for every
flight over that floor; each flight is a 20 s random aisle survey with a 200 Hz IMU, every frame
seeing the codes under the floor camera with single-code-PnP-like noise (3 mm, 0.1 deg), solved
by the batch smoother with the as-built codes (world.yaml stating the placement sigma), its
floor_codes_smoother.csv written as `fusion run` writes it.  Then the floor's flights are merged
two ways: the merge (prior and common shift counted once) and the independent per-code fusion
that it replaced.  Printed: the 3-dof NEES (x, y, yaw; ideal 3) of the merged codes against the
true placement, by the number of flights that saw the code (codes seen in at least 10 frames).

    PYTHONPATH=$PWD python3 scripts/bench_map_merge.py [--floors 20] [--flights 8]
        [--sigma-m 0.01] [--sigma-deg 1]
"""

from __future__ import annotations

import argparse
import collections
import datetime
import math
import tempfile
from pathlib import Path

import numpy as np

from fusion.conventions import floor_payload
from fusion.estimate import FusionConfig, smooth
from fusion.estimate.asbuilt import Placement, read_floor_code_rows, write_floor_codes_csv
from fusion.log.euroc import ImuNoise
from fusion.sim.imu import synthesize_imu
from fusion.sim.placement import synthetic_sightings, true_code_poses
from fusion.sim.trajectory import random_aisle_survey
from fusion.types import Trajectory
from fusion.warehouse.floorcodes import merge_floor_codes
from fusion.world import World

SIGHTING_COV = np.diag([math.radians(0.1)] * 3 + [0.003] * 3) ** 2
DURATION_S = 20.0
MIN_OBS = 10


def flight_csv(
    path: Path, seed: int, offsets: np.ndarray, placement: Placement
) -> tuple[list[str], np.ndarray]:
    """One flight over the floor: its floor_codes_smoother.csv at `path`; returns ids, xy."""
    rng = np.random.default_rng(seed)
    traj = random_aisle_survey(DURATION_S, rng)
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), rng)
    frame_t = np.round(np.arange(0.0, DURATION_S, 1 / 30.0) * 1e9).astype(np.int64)
    T_true = traj.state(frame_t * 1e-9).T_world_body
    xs, ys = np.meshgrid(np.arange(-6, 7), np.arange(-5, 6))
    xy = np.c_[xs.ravel(), ys.ravel()].astype(float)
    ids = [floor_payload(x, y) for x, y in xy]
    ab, fk, fT, fcov = synthetic_sightings(
        frame_t,
        T_true,
        ids,
        xy,
        true_code_poses(xy, offsets),
        SIGHTING_COV,
        placement,
        rng,
        placement_in_fixes=True,
    )
    res = smooth(
        frame_t, imu, Trajectory("pnp", frame_t[fk], fT, fcov), [], config=FusionConfig(), as_built=ab
    )
    write_floor_codes_csv(path, res.floor_codes)
    return ids, xy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--floors", type=int, default=20)
    ap.add_argument("--flights", type=int, default=8)
    ap.add_argument("--sigma-m", type=float, default=0.01)
    ap.add_argument("--sigma-deg", type=float, default=1.0)
    args = ap.parse_args()
    placement = Placement(args.sigma_m, math.radians(args.sigma_deg))
    world = World(placement_sigma_m=args.sigma_m, placement_sigma_deg=args.sigma_deg)
    merged: dict[int, list[float]] = collections.defaultdict(list)
    independent: dict[int, list[float]] = collections.defaultdict(list)
    single: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        for floor in range(args.floors):
            rng = np.random.default_rng([floor, 7])
            n_codes = 13 * 11
            offsets = np.c_[
                rng.normal(0, args.sigma_m, (n_codes, 2)), rng.normal(0, placement.sigma_rad, n_codes)
            ]
            dirs = []
            for flight in range(args.flights):
                d = Path(tmp) / f"{floor}-{flight}"
                d.mkdir()
                ids, xy = flight_csv(
                    d / "floor_codes_smoother.csv", 1000 * floor + flight, offsets, placement
                )
                dirs.append(d)
            truth = {cid: np.r_[p + o[:2], o[2]] for cid, p, o in zip(ids, xy, offsets)}

            def z2(cid: str, x: np.ndarray, P: np.ndarray, truth: dict = truth) -> float:
                e = np.asarray(x, float) - truth[cid]
                e[2] = math.remainder(e[2], 2 * math.pi)
                return float(e @ np.linalg.solve(P, e))

            rows: dict[str, list] = collections.defaultdict(list)
            for d in dirs:
                for cid, r in read_floor_code_rows(d / "floor_codes_smoother.csv").items():
                    rows[cid].append(r)
                    if r.n_obs >= MIN_OBS:
                        single.append(z2(cid, r.xy_yaw, r.cov))
            for c in merge_floor_codes(dirs, "smoother", world)[0]:
                if c.n_obs < MIN_OBS:
                    continue
                merged[c.n_runs].append(z2(c.code_id, c.xy_yaw, c.cov))
                info = sum(np.linalg.inv(r.cov) for r in rows[c.code_id])
                P = np.linalg.inv(info)
                x = P @ sum(np.linalg.inv(r.cov) @ r.xy_yaw for r in rows[c.code_id])
                independent[c.n_runs].append(z2(c.code_id, x, P))
    print(
        f"# bench_map_merge {datetime.date.today()}: {args.floors} floors x {args.flights} flights, "
        f"placement {100 * args.sigma_m:g} cm / {args.sigma_deg:g} deg"
    )
    print(f"single flights: 3-dof NEES {np.mean(single):.2f} over {len(single)} codes")
    print("| flights seeing the code | codes | NEES, merged | NEES, independent fusion |")
    print("|--:|--:|--:|--:|")
    for n in sorted(merged):
        print(f"| {n} | {len(merged[n])} | {np.mean(merged[n]):.2f} | {np.mean(independent[n]):.2f} |")


if __name__ == "__main__":
    main()
