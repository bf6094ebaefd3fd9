"""As-built floor codes in a run and across runs (issue #12, items 1 and 3): the pipeline's glue
around fusion.estimate.asbuilt.

- `as_built_input`: the batch smoother's as-built input of a flight (or None, with the reason),
  from world.yaml's placement sigmas and, with `fusion run --map MAP`, a merged floor-code map as
  the prior (refused when MAP's world.yaml is not the flight's);
- `floor_code_metrics`: metrics.json's entry (misplaced codes; errors against the simulator's
  floor_codes_groundtruth.csv when the log has one);
- `markdown_lines`: report.md's section; `merge_floor_codes` / `write_merged_floor_codes`: the
  inverse-covariance fusion of several runs' floor codes for `fusion map merge`.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import FloorPayload, parse_payload
from fusion.errors import WarehouseError
from fusion.estimate.asbuilt import (
    FLOOR_CODE_COLUMNS,
    FLOOR_CODES_CSV,
    FLOOR_CODES_GROUNDTRUTH_CSV,
    MISPLACED_MIN_OFFSET_M,
    MISPLACED_SIGMAS,
    AsBuiltError,
    AsBuiltInput,
    FloorCodeMap,
    FloorCodeRow,
    Placement,
    PriorMap,
    build_input,
    code_prior_cov,
    common_shift,
    common_shift_covs,
    correlation_cells,
    groundtruth_errors,
    pose_cov_to_xy_yaw_cov,
    read_floor_code_rows,
    read_groundtruth_csv,
    shared_cells,
    shift_jacobians,
)
from fusion.evaluate.plots import plot_floor_code_offsets
from fusion.fileio import atomic_open, csv_safe, load_yaml
from fusion.geometry import make_T
from fusion.log.euroc import LogWarning
from fusion.warehouse import escape
from fusion.world import World, warehouse_differences

__all__ = [
    "MERGED_FLOOR_CODES_CSV",
    "MergedFloorCode",
    "as_built_input",
    "floor_code_metrics",
    "groundtruth_warning",
    "markdown_lines",
    "merge_floor_codes",
    "read_floor_map",
    "write_merged_floor_codes",
]

logger = logging.getLogger(__name__)

MERGED_FLOOR_CODES_CSV = "floor_codes_merged.csv"
FLOOR_OFFSETS_PNG = "floor_code_offsets.png"
WORLD_YAML = "world.yaml"
MIN_OBS_FOR_ERRORS = 20
"""metrics.json's ground-truth errors are also given over the codes seen in this many frames."""


def read_floor_map(map_dir: Path, world_yaml: dict) -> PriorMap:
    """The merged floor codes of `fusion map merge --out MAP` as a prior; WarehouseError when
    MAP is not a merged map or is of another warehouse (its world.yaml differs from the flight's)."""
    map_dir = Path(map_dir)
    csv_path = map_dir / MERGED_FLOOR_CODES_CSV
    if not csv_path.is_file():
        raise WarehouseError(f"{csv_path}: not found (is {map_dir} the --out of `fusion map merge`?)")
    theirs = load_yaml(map_dir / WORLD_YAML, WarehouseError)
    keys, _ = warehouse_differences(theirs, world_yaml)
    if keys:
        raise WarehouseError(
            f"{map_dir}: a map of a different warehouse (world.yaml differs in {', '.join(keys)}); "
            "refusing to use it as this flight's floor-code prior"
        )
    try:
        rows = read_floor_code_rows(csv_path)
    except AsBuiltError as e:
        raise WarehouseError(str(e)) from None
    prior = PriorMap({cid: (r.xy_yaw, r.cov) for cid, r in rows.items()}, str(map_dir))
    # the codes' common shift (merge_floor_codes: the merged floor's, fixed by world.yaml's
    # priors of all its codes), so that a flight takes it once, not once per code
    if rows and all(
        r.prior_xy_yaw is not None and r.prior_cov is not None and r.shared_cov is not None
        for r in rows.values()
    ):
        xy = np.array([r.prior_xy_yaw[:2] for r in rows.values() if r.prior_xy_yaw is not None])
        Q = np.array([r.prior_cov for r in rows.values() if r.prior_cov is not None])
        prior.shift = common_shift(xy, Q)
        # each code's share, J_c Cov(delta) J_c^T in full (the file states its diagonal)
        prior.shared = dict(zip(rows, common_shift_covs(xy, Q)))
    return prior


def as_built_input(
    world: World,
    world_yaml: dict,
    floor_frames: Mapping,
    floor_camera: CameraModel,
    corner_sigma_px: float,
    tight: bool = False,
    map_dir: Path | None = None,
) -> tuple[AsBuiltInput | None, list[str]]:
    """(AsBuiltInput or None, notes) of a flight for the batch smoother (module docstring).
    floor_frames {timestamp_ns: [FloorSighting]}; world_yaml: the flight's world.yaml as read."""
    notes: list[str] = []
    placement = Placement.from_world(world)
    prior_map = None
    if map_dir is not None:
        prior_map = read_floor_map(map_dir, world_yaml)
    if not placement.enabled:
        if prior_map is not None:
            notes.append("--map given but world.yaml says the floor codes are laid exactly: map not used")
        return None, notes
    if tight:
        notes.append("as-built floor codes are not estimated with --tight (corner factors use nominal codes)")
        return None, notes
    if floor_camera.gimbaled:
        notes.append("as-built floor codes need a body-fixed floor camera: nominal codes used")
        return None, notes
    ab = build_input(floor_frames, floor_camera, world, placement, corner_sigma_px, prior_map)
    notes += ab.notes
    notes.append(
        f"as-built floor codes (smoother): {len(ab.codes)} codes, placement sigma "
        f"{100 * placement.sigma_m:.1f} cm / {math.degrees(placement.sigma_rad):.1f} deg"
    )
    return ab, notes


def floor_code_metrics(fmap: FloorCodeMap, log_root: Path | None) -> dict:
    """metrics.json's entry: FloorCodeMap.summary() plus, when the log has the simulator's
    floor_codes_groundtruth.csv, errors against it (all codes, and those seen in
    MIN_OBS_FOR_ERRORS frames or more)."""
    out = fmap.summary()
    gt_path = None if log_root is None else Path(log_root) / FLOOR_CODES_GROUNDTRUTH_CSV
    if gt_path is not None and gt_path.is_file():
        try:
            truth = read_groundtruth_csv(gt_path)
        except AsBuiltError as e:  # the run's named warning is groundtruth_warning's
            logger.info("%s", e)
            return out
        out["groundtruth"] = groundtruth_errors(fmap, truth)
        out["groundtruth_min_obs"] = groundtruth_errors(fmap, truth, MIN_OBS_FOR_ERRORS)
        true_bad = {
            cid
            for cid, t in truth.items()
            if cid in fmap.by_id()
            and np.linalg.norm(t[:2] - fmap.by_id()[cid].nominal_world[:2]) > MISPLACED_MIN_OFFSET_M
        }
        flagged = {c.code_id for c in fmap.misplaced}
        out["flags_vs_truth"] = {
            "truly_off_more_than_min_offset": len(true_bad),
            "flagged": len(flagged),
            "flagged_and_truly_off": len(flagged & true_bad),
        }
    return out


def groundtruth_warning(log_root: Path | None) -> LogWarning | None:
    """A named warning (count 1: the file) when the log's floor_codes_groundtruth.csv cannot be
    read (read_groundtruth_csv's one line, naming the file and line): the floor codes are then
    not scored against it.  It was a log line only: metrics.json lacked the errors, unexplained."""
    gt_path = None if log_root is None else Path(log_root) / FLOOR_CODES_GROUNDTRUTH_CSV
    if gt_path is None or not gt_path.is_file():
        return None
    try:
        read_groundtruth_csv(gt_path)
    except AsBuiltError as e:
        return LogWarning(
            "floor_codes_groundtruth_unreadable", 1, f"{e}: the floor codes are not scored against it"
        )
    return None


def markdown_lines(fmap: FloorCodeMap, plot_file: str | None) -> list[str]:
    """report.md's section on the as-built floor codes."""
    s = fmap.summary()
    lines = [
        "## As-built floor codes",
        "",
        f"{s['n_codes']} floor codes estimated by the `{escape.markdown(fmap.estimator)}` "
        f"(placement prior {100 * fmap.placement.sigma_m:.1f} cm, "
        f"{math.degrees(fmap.placement.sigma_rad):.1f}°); offsets from nominal: RMS "
        f"{100 * (s['offset_rms_m'] or 0):.2f} cm, max {100 * (s['offset_max_m'] or 0):.2f} cm. "
        f"Misplaced (beyond {MISPLACED_SIGMAS:g} σ and {100 * MISPLACED_MIN_OFFSET_M:g} cm): "
        f"**{len(s['misplaced'])}**.",
        "",
    ]
    if plot_file:
        lines += [f"![Floor-code offsets, top view]({plot_file})", ""]
    if s["misplaced"]:
        lines += [
            "| code | offset x [cm] | offset y [cm] | offset [cm] | σ distance | sightings |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for m in s["misplaced"]:
            dx, dy = (100 * v for v in m["offset_xy_m"])
            lines.append(
                f"| {escape.markdown(m['id'])} | {dx:.2f} | {dy:.2f} "
                f"| {100 * m['offset_m']:.2f} | {m['sigmas']:.1f} | {m['n_obs']} |"
            )
        lines.append("")
    lines += [
        f"Every code: [{FLOOR_CODES_CSV.format(fmap.estimator)}]({FLOOR_CODES_CSV.format(fmap.estimator)}).",
        "",
    ]
    return lines


def floor_code_section(out_dir: Path, fmap: FloorCodeMap, log_root: str | Path | None, dpi: int) -> list[str]:
    """Draw FLOOR_OFFSETS_PNG into out_dir (true offsets too when the log has the simulator's
    floor_codes_groundtruth.csv) and return report.md's section."""
    truth = None
    gt_path = None if log_root is None else Path(log_root) / FLOOR_CODES_GROUNDTRUTH_CSV
    if gt_path is not None and gt_path.is_file():
        try:
            truth = read_groundtruth_csv(gt_path)
        except AsBuiltError as e:  # the run's named warning is groundtruth_warning's
            logger.info("%s", e)
    plot_file = None
    if fmap.codes:
        nominal = np.array([c.nominal_world[:2] for c in fmap.codes])
        true_off = (
            None
            if truth is None
            else np.array(
                [
                    truth[c.code_id][:2] - c.nominal_world[:2] if c.code_id in truth else (0.0, 0.0)
                    for c in fmap.codes
                ]
            )
        )
        plot_floor_code_offsets(
            Path(out_dir) / FLOOR_OFFSETS_PNG,
            nominal,
            np.array([c.offset_xy_m for c in fmap.codes]),
            np.array([c.misplaced for c in fmap.codes]),
            true_off,
            dpi=dpi,
        )
        plot_file = FLOOR_OFFSETS_PNG
    return markdown_lines(fmap, plot_file)


# =========================================================================== merge


@dataclass
class MergedFloorCode:
    code_id: str
    xy_yaw: np.ndarray  # (3,) world x, y (m), yaw (rad)
    cov: np.ndarray  # (3, 3), the shared part included
    n_obs: int
    n_runs: int
    prior_xy_yaw: np.ndarray | None = None  # (3,) the prior counted once (world.yaml's)
    prior_cov: np.ndarray | None = None  # (3, 3)
    shared_cov: np.ndarray | None = None  # (3, 3): the largest common shift of the runs


def merge_floor_codes(
    run_dirs: list[Path], estimator: str, world: World
) -> tuple[list[MergedFloorCode], list[str]]:
    """The runs' floor_codes_<estimator>.csv merged into one map of the floor.

    Every run's estimate of a code holds what every other run's holds too
    (asbuilt.SHARED_COLUMNS): the prior it started from, and the floor's common shift g, a
    planar rigid motion of all the codes it saw that only those priors fix
    (asbuilt.common_shift_covs).  Fused per code as independent (Bar-Shalom et al. 2001,
    eq. 8.4-5, until 2026-12-05), a code seen in n runs had both counted n times: on 20
    synthetic floors of 8 flights each the merged codes' 3-dof NEES rose with the runs behind
    them (2 runs 4.6, 4 runs 5.9, 8 runs 7.1; BENCHMARKS.md, twentieth session).  Here each
    run r gives the codes' places up to a rigid motion delta_r of its own, and the payload
    priors of world.yaml fix the floor once.  Per run and code, per axis, with p its variance,
    g its share of the run's common shift and q the run's prior,

        d = 1 / (p - g) - 1 / q    (0 when not positive)

    is what the run's own sightings say of the code relative to the run's other codes, and the
    merged map is the least-squares solution of

        x_rc = x_c + J_c delta_r + n_rc,  n_rc ~ N(0, 1 / d)     every run r, code c
        x_c ~ N(m_c, q_c)                                         every code, once (world.yaml)

    with x_c the codes and delta_r free (J_c as in common_shift_covs, about the run's centroid
    of the codes' priors); each code's covariance is its marginal, the merged floor's common
    shift included (the delta_r are eliminated first: a Schur complement of 3 x runs).  A long
    flight's codes come from its windows, each of which fixed its own shift (the file's
    shift_group, asbuilt.merge_window_maps): one delta per run and shift group.  One delta for
    the whole run took the windows' shifts as one: 3-dof NEES 4.4 against 3.2 on linear-Gaussian
    two-window flights (tests/test_asbuilt.py); 2.77 against 2.67 on two rendered 400 s flights
    of five windows each, whose windows see mostly the same codes (BENCHMARKS.md).  One run
    gives back its own estimate and sigma to first order.  A CSV without the shared columns
    (written before them): its prior is taken as world.yaml's and g as 0.  A run made with
    `--map` started from the map: d is what it added, and the map's information counts through
    the runs it was merged from (merge those too).  Runs without the file are noted and
    skipped; a code id that is not a floor payload is a WarehouseError naming the file."""
    runs: list[tuple[Path, dict[str, FloorCodeRow]]] = []
    notes = []
    for d in run_dirs:
        path = Path(d) / FLOOR_CODES_CSV.format(estimator)
        if not path.is_file():
            notes.append(f"{d}: no {path.name} (floor codes laid exactly, or not estimated): not merged")
            continue
        try:
            rows = read_floor_code_rows(path)
        except AsBuiltError as e:
            raise WarehouseError(str(e)) from None
        for cid in rows:
            if not isinstance(parse_payload(cid), FloorPayload):
                raise WarehouseError(f"{path}: {cid!r} is not a floor-code payload")
        runs.append((path, rows))
    ids = sorted({cid for _, rows in runs for cid in rows})
    if not ids:
        return [], notes
    index = {cid: i for i, cid in enumerate(ids)}
    priors = [_world_prior(cid, world) for cid in ids]
    m = np.array([mp for mp, _ in priors])
    q = np.array([qp for _, qp in priors])
    n_c = len(ids)
    # one shift per run and shift group (a long flight's windows each fix their own)
    groups = [
        {cid: row for cid, row in rows.items() if row.shift_group == k}
        for _, rows in runs
        for k in sorted({row.shift_group for row in rows.values()})
    ]
    n_r = len(groups)
    # normal equations: codes' blocks diagonal per axis (Hc: (C, 3)), the shifts dense
    Hc = 1.0 / q
    bc = m / q
    Hcd = np.zeros((n_c, 3, 3 * n_r))  # code c x all shifts
    Hd = np.zeros((3 * n_r, 3 * n_r))
    bd = np.zeros(3 * n_r)
    n_obs = np.zeros(n_c, dtype=np.int64)
    n_runs = np.zeros(n_c, dtype=np.int64)
    for r, rows in enumerate(groups):
        cs = np.array([index[cid] for cid in rows])
        x = np.array([row.xy_yaw for row in rows.values()])
        x[:, 2] = m[cs, 2] + np.remainder(x[:, 2] - m[cs, 2] + math.pi, 2 * math.pi) - math.pi
        p = np.array([np.diag(row.cov) for row in rows.values()])
        g = np.array(
            [np.zeros(3) if row.shared_cov is None else np.diag(row.shared_cov) for row in rows.values()]
        )
        qr = np.array(
            [q[c] if row.prior_cov is None else np.diag(row.prior_cov) for c, row in zip(cs, rows.values())]
        )
        a = p - np.minimum(g, p)
        with np.errstate(divide="ignore"):
            w = np.where(a > 0, 1.0 / np.where(a > 0, a, 1.0) - 1.0 / qr, 0.0)
        w = np.maximum(w, 0.0)  # (k, 3): each axis's weight 1 / var(n)
        J = shift_jacobians(m[cs, :2])
        sl = slice(3 * r, 3 * r + 3)
        # a code appears once in a run: plain fancy-indexed sums
        Hc[cs] += w
        bc[cs] += w * x
        WJ = w[:, :, None] * J  # W J per code
        Hcd[cs, :, sl] += WJ
        Hd[sl, sl] += np.einsum("kji,kjl->il", J, WJ)
        bd[sl] += np.einsum("kji,kj->i", J, w * x)
        n_obs[cs] += [row.n_obs for row in rows.values()]
        n_runs[cs] += 1
    # eliminate the codes (diagonal) into the shifts, solve, back-substitute
    Hc_inv = 1.0 / Hc
    S = Hd - np.einsum("cik,ci,cil->kl", Hcd, Hc_inv, Hcd)
    S_inv = np.linalg.pinv(S, hermitian=True)
    delta = S_inv @ (bd - np.einsum("cik,ci->k", Hcd, Hc_inv * bc))
    xc = Hc_inv * (bc - np.einsum("cik,k->ci", Hcd, delta))
    B = Hc_inv[:, :, None] * Hcd  # Hc^-1 Hcd
    cov = np.einsum("ci,ij->cij", Hc_inv, np.eye(3)) + np.einsum("cik,kl,cjl->cij", B, S_inv, B)
    shared = common_shift_covs(m[:, :2], np.einsum("ci,ij->cij", q, np.eye(3)))
    out = [
        MergedFloorCode(
            cid,
            xc[i],
            0.5 * (cov[i] + cov[i].T),
            int(n_obs[i]),
            int(n_runs[i]),
            m[i],
            np.diag(q[i]),
            np.minimum(np.diag(np.diag(shared[i])), np.diag(np.diag(cov[i]))),
        )
        for i, cid in enumerate(ids)
    ]
    return out, notes


def _diag_or_zero(cov: np.ndarray | None) -> np.ndarray:
    return np.zeros(3) if cov is None else np.diag(cov)


def _world_prior(cid: str, world: World) -> tuple[np.ndarray, np.ndarray]:
    """(x, y, yaw), (x, y, yaw) variances: world.yaml's prior of a floor code (its payload's
    place, the placement sigma)."""
    payload = parse_payload(cid)
    assert isinstance(payload, FloorPayload)
    placement = Placement.from_world(world)
    T_nom = make_T(np.eye(3), world.floor_code_position(payload))
    cov = pose_cov_to_xy_yaw_cov(T_nom, code_prior_cov(placement.sigma_m, placement.sigma_rad))
    return np.array([T_nom[0, 3], T_nom[1, 3], 0.0]), np.diag(cov).copy()


def write_merged_floor_codes(out_dir: Path, codes: list[MergedFloorCode], payload_unit_m: float) -> Path:
    """MAP/floor_codes_merged.csv in the columns of floor_codes_<estimator>.csv (what
    `fusion run --map` reads) plus n_runs; nominal and offset columns from the payload."""
    path = Path(out_dir) / MERGED_FLOOR_CODES_CSV
    with atomic_open(path) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow([*FLOOR_CODE_COLUMNS, "n_runs"])
        for c in codes:
            p = parse_payload(c.code_id)
            nominal = (
                (p.x * payload_unit_m, p.y * payload_unit_m)
                if isinstance(p, FloorPayload)
                else (math.nan, math.nan)
            )
            sig = np.sqrt(np.diag(c.cov))
            off = c.xy_yaw[:2] - np.asarray(nominal)
            w.writerow(
                [
                    csv_safe(c.code_id),
                    *(f"{v:.6f}" for v in nominal),
                    f"{c.xy_yaw[0]:.6f}",
                    f"{c.xy_yaw[1]:.6f}",
                    "0.000000",
                    f"{math.degrees(c.xy_yaw[2]):.6f}",
                    f"{off[0]:.6f}",
                    f"{off[1]:.6f}",
                    f"{float(np.linalg.norm(off)):.6f}",
                    f"{math.degrees(c.xy_yaw[2]):.6f}",
                    f"{sig[0]:.6f}",
                    f"{sig[1]:.6f}",
                    f"{math.degrees(sig[2]):.6f}",
                    c.n_obs,
                    0,
                    *shared_cells(c.prior_xy_yaw, c.prior_cov, c.shared_cov),
                    0,
                    *correlation_cells(c.cov),
                    c.n_runs,
                ]
            )
    return path
