"""How honest a merged floor map's covariances are, as a flight's prior (`fusion run --map`).

Per synthetic floor (the tests' 13 x 11 grid of codes, 1 cm / 1 deg placement errors, the same
for every flight over that floor): four 20 s surveys solved by the batch smoother with as-built
codes, merged (`fusion map merge`), and a fifth flight solved with the merged map as its codes'
prior (asbuilt.apply_prior_map: each code's own part about one variable D, the map's common
shift).  Prints, over the floors:

- the merged map against the true placement: each code's 3-dof marginal chi2 per dof; the map's
  joint chi2 per dof under the model that `--map` uses (own parts independent across codes plus
  the common shift delta, `PriorMap.shift`); delta's chi2 per dof (its GLS estimate from the errors
  against Cov(delta) + its estimation covariance); the own-part residual's per-code chi2 per dof;
- the fifth flight's codes (seen 10 times or more) with and without the map: mean z^2 per axis
  (x, y, yaw), the floor's mean taken as one sample (the codes of a floor share its draws), with
  its standard error over floors.

Usage: PYTHONPATH=. python3 scripts/bench_map_prior_nees.py [--floors 30] [--start 100]
"""

from __future__ import annotations

import argparse
import math
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from fusion.estimate import FusionConfig, smooth
from fusion.estimate.asbuilt import Placement, apply_prior_map, own_part
from fusion.warehouse import floorcodes
from fusion.world import World
from tests.test_asbuilt import _flight, _floor_offsets, _surveys


def map_against_truth(prior, truth: dict[str, np.ndarray]) -> dict[str, float]:
    """The merged map's errors: marginal, joint (own parts independent + common shift), shift,
    and own-part residual chi2 (sums) and their degrees of freedom."""
    centroid, cov_delta = prior.shift
    ids = [c for c in prior.codes if c in prior.shared and c in truth]
    n = len(ids)
    err = np.zeros(3 * n)
    own = np.zeros((3 * n, 3 * n))
    marginal = 0.0
    J = np.zeros((3 * n, 3))
    for i, cid in enumerate(ids):
        m, cov = prior.codes[cid]
        e = m - truth[cid]
        err[3 * i : 3 * i + 3] = e
        own[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = own_part(cov, prior.shared[cid])
        marginal += float(e @ np.linalg.solve(cov, e))
        J[3 * i : 3 * i + 3] = [[1, 0, -(m[1] - centroid[1])], [0, 1, m[0] - centroid[0]], [0, 0, 1]]
    joint = float(err @ np.linalg.solve(own + J @ cov_delta @ J.T, err))
    W = np.linalg.inv(own)
    H = J.T @ W @ J
    delta = np.linalg.solve(H, J.T @ W @ err)
    shift = float(delta @ np.linalg.solve(np.linalg.inv(H) + cov_delta, delta))
    r = err - J @ delta
    residual = sum(
        float(
            r[3 * i : 3 * i + 3]
            @ np.linalg.solve(own[3 * i : 3 * i + 3, 3 * i : 3 * i + 3], r[3 * i : 3 * i + 3])
        )
        for i in range(n)
    )
    return {
        "marginal": marginal,
        "joint": joint,
        "shift": shift,
        "residual": residual,
        "dof": 3 * n,
        "dof_resid": 3 * n - 3,
    }


def flight_codes_z(res, prior, truth) -> np.ndarray:
    """(k, 3) per-axis normalised errors of a flight's codes seen 10 times or more that the map has."""
    out = []
    for c in res.floor_codes.codes:
        if c.n_obs >= 10 and c.code_id in prior.codes:
            e = np.r_[c.p_world[:2], c.yaw_rad] - truth[c.code_id]
            out.append(e / np.sqrt(np.diag(c.cov_xy_yaw)))
    return np.array(out).reshape(-1, 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--floors", type=int, default=30)
    ap.add_argument("--start", type=int, default=100, help="the first floor's seed")
    args = ap.parse_args()
    placement = Placement(0.01, math.radians(1.0))
    world = World(placement_sigma_m=0.01, placement_sigma_deg=1.0)
    tmp = Path(tempfile.mkdtemp(prefix="bench_map_prior_"))
    sums: dict[str, float] = {}
    with_map, alone = [], []
    print("floor codes  marginal joint shift residual (chi2/dof)  flight --map z2 x/y/yaw")
    for floor in range(args.start, args.start + args.floors):
        offsets = _floor_offsets([floor, 11], placement)
        dirs, ids, true = _surveys(
            tmp / str(floor), [1000 + 10 * floor + f for f in range(4)], offsets, placement
        )
        truth = {cid: np.array([*map(float, cid.split("/")[1:]), 0.0]) + o for cid, o in zip(ids, true)}
        map_dir = tmp / f"map{floor}"
        map_dir.mkdir()
        floorcodes.write_merged_floor_codes(
            map_dir, floorcodes.merge_floor_codes(dirs, "smoother", world)[0], 1.0
        )
        world.save(map_dir / "world.yaml")
        prior = floorcodes.read_floor_map(map_dir, world.to_yaml())
        m = map_against_truth(prior, truth)
        for k, v in m.items():
            sums[k] = sums.get(k, 0.0) + v
        frame_t, imu, raw, ab, _, _ = _flight(1000 + 10 * floor + 9, 20.0, offsets, placement, True)
        codes, shift_cov, _ = apply_prior_map(ab.codes, prior)
        cfg = FusionConfig()
        z_map = flight_codes_z(
            smooth(frame_t, imu, raw, [], config=cfg, as_built=replace(ab, codes=codes, shift_cov=shift_cov)),
            prior,
            truth,
        )
        z_alone = flight_codes_z(smooth(frame_t, imu, raw, [], config=cfg, as_built=ab), prior, truth)
        with_map.append((z_map**2).mean(0))
        alone.append((z_alone**2).mean(0))
        print(
            f"{floor:5d} {m['dof'] // 3:5d}  {m['marginal'] / m['dof']:8.2f} {m['joint'] / m['dof']:5.2f}"
            f" {m['shift'] / 3:5.2f} {m['residual'] / m['dof_resid']:8.2f}   {np.round(with_map[-1], 2)}",
            flush=True,
        )
    n = args.floors
    print(f"\nmerged map over {n} floors, chi2 per dof (1 if honest):")
    dof = sums["dof"]
    print(
        f"  marginal {sums['marginal'] / dof:.3f}   joint (own independent + shift) {sums['joint'] / dof:.3f}"
    )
    resid = sums["residual"] / sums["dof_resid"]
    print(f"  shift {sums['shift'] / (3 * n):.3f}   own-part residual per code {resid:.3f}")
    for name, z in (("flight with --map", np.array(with_map)), ("flight alone", np.array(alone))):
        se = z.std(0, ddof=1) / math.sqrt(n)
        nees = z.sum(1)
        print(
            f"{name}: code z^2 x / y / yaw {z.mean(0).round(2)} (se {se.round(2)}); "
            f"3-dof NEES {nees.mean():.2f} (se {nees.std(ddof=1) / math.sqrt(n):.2f})"
        )


if __name__ == "__main__":
    main()
