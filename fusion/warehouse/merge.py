"""Load maps of several flights of one warehouse fused into one map (issue #12, item 3, loads).

Runs are taken in the order given (flight order).  For each load id the merged state (p, P) is
the information-weighted fusion of its estimates since it last changed (covariance intersection
is not needed: the flights' load errors are independent given the floor, whose placement error
the as-built floor codes of item 1 will take over), except the part every flight shares
(`LoadEstimate.cov_shared`: the label's print error and the front camera's mount error,
fusion.estimate.loadconsider), which no number of flights averages down: with A_i = P_i - S_i,

    A = (sum_i A_i^-1)^-1,   p = A sum_i A_i^-1 p_i          (Bar-Shalom et al. 2001, eq. 8.4-5)
    P = A + S,  S the largest S_i (by trace; one label, one camera: the S_i are alike)

Between the state and a new flight's estimate (p_k, P_k) of the same id the change test of
`inventory.moved_test` runs with covariance P + P_k + MERGE_TOLERANCE_M^2 I:
- consistent: fused;
- moved (p < MOVED_ALPHA): the state restarts from the new estimate; listed with distance, sigma,
  chi2 and p-value;
- appeared: an id first read in a later flight (significance: its sightings);
- disappeared: an id of the state not read in a flight whose front camera had its place in view
  at readable range, and from inside the cone of directions the flights that read it read it
  from (inventory.view_cone: its face, and a line of sight past the racks), in at least
  MIN_FRAMES_IN_VIEW poses (significance: those poses); it leaves the merged map.  Not in
  view: kept, unchanged.  Without the cone (before 2026-12-05, and still for a load whose
  runs left no load_observations_pnp.csv, with a note), a flight down the next aisle, behind
  the rack the label faces away from, deleted it: a load of four rendered flights
  (scripts/bench_map_merge_rendered.py) was listed as disappeared, 24 poses "in view" through
  the rack.

Runs of different warehouses (their world.yaml differ) are refused, and so are two runs of one
flight (the same log, or the same raw sightings: a copy): their sightings would count twice.
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from fusion.errors import OutputError, WarehouseError
from fusion.fileio import atomic_open, dump_yaml, flight_log_mark
from fusion.log.files import LOADS_COLUMNS
from fusion.types import Estimator
from fusion.warehouse import escape
from fusion.warehouse.floorcodes import MergedFloorCode, merge_floor_codes, write_merged_floor_codes
from fusion.warehouse.inventory import (
    MIN_FRAMES_IN_VIEW,
    MOVED_ALPHA,
    moved_test,
    sighting_directions,
    view_cone,
    visibility,
)
from fusion.warehouse.runs import RunOutputs, load_run
from fusion.world import World, warehouse_differences

logger = logging.getLogger(__name__)

MERGE_TOLERANCE_M = 0.005
"""1-sigma per axis of what differs between two flights' maps of a load that stayed put beyond
their covariances (camera calibration, timing): half a centimetre."""


class ChangeKind(str, Enum):
    MOVED = "moved"
    APPEARED = "appeared"
    DISAPPEARED = "disappeared"

    def __str__(self) -> str:
        return str(self.value)


@dataclass
class MergedLoad:
    load_id: str
    p_world: np.ndarray  # (3,) m
    cov_world: np.ndarray  # (3, 3) m^2
    n_obs: int
    n_runs: int  # flights fused into this estimate (since its last change)
    last_run: int  # index of the last flight that read it
    cov_shared: np.ndarray | None = None  # (3, 3) m^2: the part of cov_world every flight shares
    view_dirs: np.ndarray | None = None  # (k, 3): directions from the load to the camera that read it


@dataclass
class Change:
    load_id: str
    kind: ChangeKind
    run_index: int  # the flight where the change shows
    p_before: np.ndarray | None = None
    p_after: np.ndarray | None = None
    distance_m: float | None = None
    sigma_m: float | None = None
    chi2: float | None = None
    p_value: float | None = None
    n_obs: int | None = None
    frames_in_view: int | None = None


@dataclass
class MergeResult:
    runs: list[str]
    estimator: str
    loads: list[MergedLoad]
    changes: list[Change]
    world_yaml: dict
    notes: list[str] = field(default_factory=list)
    floor_codes: list[MergedFloorCode] = field(default_factory=list)  # as-built, fused


def check_same_warehouse(runs: list[RunOutputs], notes: list[str] | None = None) -> dict:
    """The common world.yaml of `runs` (the first run's); WarehouseError if one is unknown or
    they describe different warehouses (world.warehouse_differences).  Runs that differ only in
    their stated print / placement sigmas are the same warehouse: each run's map already carries
    its own, and `notes` (when given) says which keys differ."""
    worlds = []
    for r in runs:
        if r.world_yaml is None:
            raise WarehouseError(
                f"{r.out_dir}: no run.json (world.yaml unknown): re-run `fusion run` on its log to record it"
            )
        worlds.append(r.world_yaml)
    ref = worlds[0]
    sigma_keys: set[str] = set()
    for r, w in zip(runs[1:], worlds[1:], strict=True):
        keys, sigmas = warehouse_differences(ref, w)
        if keys:
            raise WarehouseError(
                f"{r.out_dir}: a different warehouse than {runs[0].out_dir} "
                f"(world.yaml differs in {', '.join(keys)}); refusing to merge"
            )
        sigma_keys.update(sigmas)
    if sigma_keys and notes is not None:
        notes.append(
            f"the runs' world.yaml state different {', '.join(sorted(sigma_keys))} (each run's map "
            f"carries its own); the merged world.yaml is {runs[0].out_dir}'s"
        )
    return ref


def check_distinct_flights(runs: list[RunOutputs]) -> None:
    """WarehouseError when two of `runs` are of one flight: the same log (run.json), or the same
    raw load sightings (ids, stamps and positions: a copied log or run folder).  Fused, such a
    flight's sightings count twice: every sigma shrinks by sqrt(2) for nothing."""
    by_log: dict[str, RunOutputs] = {}
    by_sightings: dict[bytes, RunOutputs] = {}
    for r in runs:
        same = by_log.get(r.log_path) if r.log_path is not None else None
        if same is not None:
            raise WarehouseError(
                f"{r.out_dir}: a run of the same flight log as {same.out_dir} ({r.log_path}); "
                "merging them would count its sightings twice"
            )
        if r.log_path is not None:
            by_log[r.log_path] = r
        if not r.observations:
            continue
        key = b"".join(
            lid.encode()
            + b"\0"
            + np.asarray(r.observation_times_ns.get(lid, []), np.int64).tobytes()
            + np.round(np.asarray(p, float), 6).tobytes()
            for lid, p in sorted(r.observations.items())
        )
        same = by_sightings.get(key)
        if same is not None:
            raise WarehouseError(
                f"{r.out_dir}: the same load sightings as {same.out_dir} (a copy of one flight?); "
                "merging them would count them twice"
            )
        by_sightings[key] = r


def _fuse(p_a, P_a, S_a, p_b, P_b, S_b) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(p, P, S): information-weighted fusion of two estimates whose covariances P_a, P_b hold
    the shared parts S_a, S_b (None: nothing shared), which are not averaged down (module
    docstring).  A part P - S that is not positive definite is taken as P (S as 0)."""
    A_a, A_b = _independent(P_a, S_a), _independent(P_b, S_b)
    I_a, I_b = np.linalg.inv(A_a), np.linalg.inv(A_b)
    A = np.linalg.inv(I_a + I_b)
    shared = [S for S, A_, P in ((S_a, A_a, P_a), (S_b, A_b, P_b)) if S is not None and A_ is not P]
    S = max(shared, key=lambda m: float(np.trace(m))) if shared else None
    P = A if S is None else A + S
    return A @ (I_a @ p_a + I_b @ p_b), 0.5 * (P + P.T), S


def _independent(P: np.ndarray, S: np.ndarray | None) -> np.ndarray:
    """P - S when positive definite, else P."""
    if S is None:
        return P
    A = P - S
    return A if np.linalg.eigvalsh(0.5 * (A + A.T))[0] > 0 else P


def _view_dirs(run: RunOutputs, load_id: str, p_world: np.ndarray) -> np.ndarray | None:
    """Directions from the load to the front camera at the run's sightings of it
    (inventory.sighting_directions); None when the run has no stamped sightings of it or no
    front camera."""
    times = run.observation_times_ns.get(load_id)
    if times is None or run.front_camera is None:
        return None
    return sighting_directions(p_world, times, run.trajectory, run.front_camera)


def merge_runs(runs: list[RunOutputs]) -> MergeResult:
    """Fuse the load maps of `runs` (flight order) and list the changes between flights."""
    if len(runs) < 1:
        raise WarehouseError("map merge needs at least one run")
    notes: list[str] = []
    world_yaml = check_same_warehouse(runs, notes)
    check_distinct_flights(runs)
    state: dict[str, MergedLoad] = {}
    changes: list[Change] = []
    for k, run in enumerate(runs):
        for l in run.load_map.loads:
            if l.cov_world is None:
                raise WarehouseError(
                    f"{run.out_dir}: load map {run.estimator!r} has no "
                    "covariances; merge a fused estimator's map"
                )
        seen = run.load_map.by_id()
        for lid, l in sorted(seen.items()):
            cur = state.get(lid)
            p_new, P_new = np.asarray(l.p_world, float), np.asarray(l.cov_world, float)
            S_new = None if l.cov_shared is None else np.asarray(l.cov_shared, float)
            dirs = _view_dirs(run, lid, p_new)
            if cur is None:
                if k > 0:
                    changes.append(Change(lid, ChangeKind.APPEARED, k, None, p_new, n_obs=l.n_obs))
                state[lid] = MergedLoad(lid, p_new, P_new, l.n_obs, 1, k, S_new, dirs)
                continue
            dist, sigma, stat, pval = moved_test(p_new, cur.cov_world + P_new, cur.p_world, MERGE_TOLERANCE_M)
            if pval < MOVED_ALPHA:
                changes.append(
                    Change(lid, ChangeKind.MOVED, k, cur.p_world, p_new, dist, sigma, stat, pval, l.n_obs)
                )
                state[lid] = MergedLoad(lid, p_new, P_new, l.n_obs, 1, k, S_new, dirs)
            else:
                p, P, S = _fuse(cur.p_world, cur.cov_world, cur.cov_shared, p_new, P_new, S_new)
                known = [d for d in (cur.view_dirs, dirs) if d is not None]
                both = np.vstack(known) if known else None
                state[lid] = MergedLoad(lid, p, P, cur.n_obs + l.n_obs, cur.n_runs + 1, k, S, both)
        unseen = sorted(set(state) - set(seen))
        if k == 0 or not unseen:
            continue
        world = run.world
        if run.front_camera is None or world is None:
            notes.append(f"{run.out_dir}: front camera unknown: loads it did not read are kept")
            continue
        dirs_of = [state[lid].view_dirs for lid in unseen]
        cones = [None if d is None else view_cone(d) for d in dirs_of]
        if any(d is None for d in dirs_of):
            notes.append(
                f"{run.out_dir}: {sum(d is None for d in dirs_of)} loads it did not "
                "read were mapped without their sightings' stamps (no load_observations_pnp.csv): "
                "judged in view from any side, a rack between included"
            )
        frames, _ = visibility(
            np.array([state[lid].p_world for lid in unseen]),
            run.trajectory,
            run.front_camera,
            world.load_side_m,
            cones,
        )
        for lid, n in zip(unseen, frames, strict=False):
            if n >= MIN_FRAMES_IN_VIEW:
                changes.append(
                    Change(lid, ChangeKind.DISAPPEARED, k, state[lid].p_world, None, frames_in_view=int(n))
                )
                del state[lid]
    return MergeResult(
        [str(r.out_dir) for r in runs],
        runs[0].estimator,
        [state[k] for k in sorted(state)],
        changes,
        world_yaml,
        notes,
    )


def run_merge(
    run_outs: list[Path], out: Path, estimator: str = Estimator.SMOOTHER, force: bool = False
) -> MergeResult:
    """`fusion map merge`: read the runs, merge, write `out/` (map.json, loads_merged.csv,
    changes.csv, changes.md, world.yaml) and, when the runs estimated as-built floor codes,
    floor_codes_merged.csv (floorcodes.merge_floor_codes: inverse-covariance weighted; what
    `fusion run --map` reads)."""
    out = Path(out)
    mark = flight_log_mark(out) if out.is_dir() else None
    if mark is not None:  # its world.yaml would be replaced, even without --force
        raise OutputError(
            f"{out}: is a flight log ({mark}), not an output folder; choose another output folder"
        )
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not force)):
        raise OutputError(f"{out}: exists; use --force to write into it")
    runs = [load_run(p, estimator) for p in run_outs]
    result = merge_runs(runs)
    world = World.from_yaml(result.world_yaml, f"{runs[0].out_dir}/run.json")
    result.floor_codes, notes = merge_floor_codes([r.out_dir for r in runs], Estimator.SMOOTHER, world)
    if result.floor_codes:
        result.notes += notes
    out.mkdir(parents=True, exist_ok=True)
    write_merge(out, result)
    if result.floor_codes:
        write_merged_floor_codes(out, result.floor_codes, world.payload_unit_m)
    return result


def write_merge(out: Path, result: MergeResult) -> None:
    out = Path(out)
    dump_yaml(result.world_yaml, out / "world.yaml")
    data = {
        "estimator": result.estimator,
        "frame": "world",
        "unit": "m",
        "runs": result.runs,
        "loads": [
            {
                "id": l.load_id,
                "p_world_m": l.p_world.tolist(),
                "cov_world_m2": l.cov_world.tolist(),
                **({} if l.cov_shared is None else {"cov_shared_m2": l.cov_shared.tolist()}),
                "n_obs": int(l.n_obs),
                "n_runs": int(l.n_runs),
                "last_run": int(l.last_run),
            }
            for l in result.loads
        ],
    }
    with atomic_open(out / "map.json") as f:
        json.dump(data, f, indent=1)
    with atomic_open(out / "loads_merged.csv") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(LOADS_COLUMNS)
        for l in result.loads:
            w.writerow(
                [
                    escape.csv_cell(l.load_id),
                    *(f"{v:.6f}" for v in l.p_world),
                    *(f"{s:.6f}" for s in np.sqrt(np.diag(l.cov_world))),
                    l.n_obs,
                ]
            )

    def f6(v):
        return "" if v is None else f"{v:.6f}"

    with atomic_open(out / "changes.csv") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(
            [
                "id",
                "change",
                "run",
                "before_x_m",
                "before_y_m",
                "before_z_m",
                "after_x_m",
                "after_y_m",
                "after_z_m",
                "distance_m",
                "sigma_m",
                "chi2",
                "p_value",
                "n_obs",
                "frames_in_view",
            ]
        )
        for c in result.changes:
            w.writerow(
                [
                    escape.csv_cell(c.load_id),
                    str(c.kind),
                    escape.csv_cell(result.runs[c.run_index]),
                    *((f6(v) for v in c.p_before) if c.p_before is not None else ("",) * 3),
                    *((f6(v) for v in c.p_after) if c.p_after is not None else ("",) * 3),
                    f6(c.distance_m),
                    f6(c.sigma_m),
                    "" if c.chi2 is None else f"{c.chi2:.3f}",
                    "" if c.p_value is None else f"{c.p_value:.3g}",
                    "" if c.n_obs is None else c.n_obs,
                    "" if c.frames_in_view is None else c.frames_in_view,
                ]
            )
    lines = [
        "# Merged load map",
        "",
        f"{len(result.loads)} loads from {len(result.runs)} flights "
        f"(`{escape.markdown(result.estimator)}` maps, information-weighted).",
        "",
    ]
    lines += ["| # | run |", "|---:|---|"]
    lines += [f"| {i} | {escape.markdown(r)} |" for i, r in enumerate(result.runs)]
    lines += ["", "## Changes between flights", ""]
    if not result.changes:
        lines += ["None.", ""]
    else:
        lines += [
            "| id | change | run | distance [cm] | σ [cm] | χ² | p | sightings | frames in view |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for c in result.changes:
            lines.append(
                "| "
                + " | ".join(
                    [
                        escape.markdown(c.load_id),
                        str(c.kind),
                        str(c.run_index),
                        "" if c.distance_m is None else f"{100 * c.distance_m:.2f}",
                        "" if c.sigma_m is None else f"{100 * c.sigma_m:.2f}",
                        "" if c.chi2 is None else f"{c.chi2:.1f}",
                        "" if c.p_value is None else f"{c.p_value:.2g}",
                        "" if c.n_obs is None else str(c.n_obs),
                        "" if c.frames_in_view is None else str(c.frames_in_view),
                    ]
                )
                + " |"
            )
        lines.append("")
    for n in result.notes:
        lines += [f"> {escape.markdown(n)}", ""]
    with atomic_open(out / "changes.md") as f:
        f.write("\n".join(lines))
