"""Inventory: a run's load map against the warehouse system's manifest (issue #12, item 2).

Each load gets one status (`Status`):

- present: read, and the 3D difference d = p_map - p_expected passes the chi-square test
  d^T (Sigma_map + tol^2 I)^-1 d <= chi2_3(1 - MOVED_ALPHA), Sigma_map the map's 3x3 covariance
  and tol the manifest's 1-sigma placement tolerance per axis (Bar-Shalom, Li & Kirubarajan,
  "Estimation with Applications to Tracking and Navigation", 2001, sec. 5.4: normalised
  innovation squared of a 3-vector is chi-square with 3 degrees of freedom);
- moved: read, test failed; reported with |d| and its sigma sqrt(u^T Sigma_map u), u = d/|d|;
- missing: expected, not read, and its place was in the front camera's field of view at readable
  range (see `visibility`), and in front of its label when the manifest gives its face
  (`face_yaw_deg`, up to MAX_READ_OBLIQUITY_DEG off its normal), in at least MIN_FRAMES_IN_VIEW
  poses of the fused trajectory;
- not_surveyed: expected, not read, never (or too briefly) in view at readable range;
- unexpected: read, not in the manifest;
- ambiguous: the run's raw load observations of one id form two or more separate clusters
  (AMBIGUITY_SEPARATION_M apart, each of at least MIN_CLUSTER_OBS sightings): the same id at two
  places, whatever the manifest says.

Limits: the run knows no rack geometry, so without the manifest's `face_yaw_deg` a place hidden
behind a rack or seen from behind its face counts as in view when it is in the image at readable
range (one of four rendered 45 s flights called a load "missing" through its rack).  With it,
a rack between the camera and a label it faces away from is left out; a rack or pallet in front
of the label is not.  `fusion map merge` knows the faces from the flights themselves: the
directions earlier flights read a load from (`view_cone`).
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.stats import chi2

from fusion.camera import CameraModel
from fusion.errors import WarehouseError
from fusion.fileio import atomic_open
from fusion.geometry import inv_T
from fusion.types import Estimator, LoadMap, Trajectory
from fusion.warehouse import escape
from fusion.warehouse.manifest import ExpectedLoad, read_manifest
from fusion.warehouse.runs import RunOutputs, load_run
from fusion.world import World

logger = logging.getLogger(__name__)

MOVED_ALPHA = 1e-3
"""False-alarm probability of the 'moved' test per load (chi-square, 3 dof: gate 16.3).  With a
few hundred loads per flight and a consistent covariance this gives well under one false 'moved'
per flight."""

READABLE_MODULE_PX = 2.1
"""Smallest module size zxing-cpp decodes on our renders, px (measured; fusion/sim/scenarios.py)."""
READABLE_MODULES = 25
"""Modules across a version-2 QR symbol, which holds `1/<id>` for the ids we print (version 1,
21 modules, holds the shorter ones; taking 25 errs towards 'not surveyed')."""
MIN_READABLE_SIDE_PX = READABLE_MODULE_PX * READABLE_MODULES
"""A load code is at readable range when its side spans at least this many pixels (52.5 px):
f * side / depth >= 52.5, i.e. a 0.15 m code from up to 1.57 m with f = 550 px, the simulator's
read range of load codes."""
MIN_FRAMES_IN_VIEW = 3
"""Poses in view at readable range needed to call an unread load 'missing' rather than 'not
surveyed': one frame may be blurred (a tenth of a second at 30 fps covers that)."""
AMBIGUITY_SEPARATION_M = 0.30
"""Raw sightings of one id farther apart than this (single linkage) are different places: a
raw PnP load observation is off by a few centimetres at most, pallets stand a rack slot apart."""
MAX_READ_OBLIQUITY_DEG = 60.0
"""A label seen more than this off its normal (the manifest's face_yaw_deg) is not counted as
seen: QR codes read to about 60-70 degrees off their normal, so a miss beyond is no evidence."""
MAX_CONE_HALF_ANGLE_DEG = 80.0
"""view_cone: sightings of one id spread wider than this around their mean direction are not
one face's (a QR code reads to about 60-70 degrees off its normal)."""
MIN_CLUSTER_OBS = 3
"""Sightings a place needs to count for 'ambiguous' (a single outlier does not make one)."""


class Status(str, Enum):
    PRESENT = "present"
    MOVED = "moved"
    MISSING = "missing"
    NOT_SURVEYED = "not_surveyed"
    UNEXPECTED = "unexpected"
    AMBIGUOUS = "ambiguous"

    def __str__(self) -> str:
        return str(self.value)


INVENTORY_COLUMNS = (
    "id",
    "status",
    "location",
    "expected_x_m",
    "expected_y_m",
    "expected_z_m",
    "mapped_x_m",
    "mapped_y_m",
    "mapped_z_m",
    "distance_m",
    "sigma_m",
    "chi2",
    "p_value",
    "tolerance_m",
    "n_obs",
    "frames_in_view",
    "max_side_px",
    "places",
)


@dataclass
class InventoryRow:
    load_id: str
    status: Status
    expected: ExpectedLoad | None = None
    p_map: np.ndarray | None = None  # (3,) m
    distance_m: float | None = None
    sigma_m: float | None = None
    chi2: float | None = None
    p_value: float | None = None
    n_obs: int = 0
    frames_in_view: int | None = None  # None: visibility unknown (no camera)
    max_side_px: float | None = None
    places: list[np.ndarray] = field(default_factory=list)  # ambiguous: cluster centres


@dataclass
class InventoryResult:
    rows: list[InventoryRow]
    estimator: str
    notes: list[str] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        return {str(s): sum(1 for r in self.rows if r.status == s) for s in Status}

    def statuses(self) -> dict[str, Status]:
        return {r.load_id: r.status for r in self.rows}


# ============================================================================ the tests


def moved_test(
    p_map: np.ndarray, cov_map: np.ndarray | None, p_expected: np.ndarray, tolerance_m: float
) -> tuple[float, float, float, float]:
    """(distance_m, sigma_m, chi2, p_value) of d = p_map - p_expected with covariance
    Sigma_map + tolerance^2 I (module docstring); sigma_m is the map's sigma along d."""
    d = np.asarray(p_map, dtype=float) - np.asarray(p_expected, dtype=float)
    cov_map = np.zeros((3, 3)) if cov_map is None else np.asarray(cov_map, dtype=float)
    S = cov_map + tolerance_m**2 * np.eye(3)
    dist = float(np.linalg.norm(d))
    u = d / dist if dist > 0 else np.array([1.0, 0.0, 0.0])
    sigma = float(np.sqrt(max(u @ cov_map @ u, 0.0)))
    if dist == 0.0:
        return 0.0, sigma, 0.0, 1.0
    if np.linalg.matrix_rank(S) < 3:  # zero tolerance and no covariance: any offset moved
        return dist, sigma, float("inf"), 0.0
    stat = float(d @ np.linalg.solve(S, d))
    return dist, sigma, stat, float(chi2.sf(stat, 3))


def face_cone(face_yaw_rad: float | None) -> tuple[np.ndarray, float] | None:
    """The directions a label facing `face_yaw_rad` (its outward normal's yaw; None: unknown)
    reads from, as a view_cone: up to MAX_READ_OBLIQUITY_DEG off its normal."""
    if face_yaw_rad is None:
        return None
    axis = np.array([np.cos(face_yaw_rad), np.sin(face_yaw_rad), 0.0])
    return axis, float(np.cos(np.radians(MAX_READ_OBLIQUITY_DEG)))


def view_cone(directions: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The cone of directions a code was read from: (k, 3) unit vectors from the code to the
    camera at its sightings -> (axis, cos of the half angle), the axis their normalised mean and
    the half angle the widest of them from it.  None without directions, or when they spread
    over more than MAX_CONE_HALF_ANGLE_DEG around their mean (one id read from both sides of
    a rack: no one face to judge by)."""
    d = np.asarray(directions, dtype=float).reshape(-1, 3)
    if len(d) == 0:
        return None
    axis = d.sum(axis=0)
    norm = float(np.linalg.norm(axis))
    if norm <= 0:
        return None
    axis /= norm
    cos_min = float(np.min(d @ axis))
    if cos_min < np.cos(np.radians(MAX_CONE_HALF_ANGLE_DEG)):
        return None
    return axis, cos_min


def sighting_directions(
    point_world: np.ndarray, times_ns: np.ndarray, trajectory: Trajectory, camera: CameraModel
) -> np.ndarray:
    """(k, 3) unit vectors from a code at `point_world` to the front camera at the sightings'
    stamps (the trajectory's nearest pose; none without a trajectory)."""
    times = np.asarray(times_ns, dtype=np.int64)
    if len(trajectory) == 0 or len(times) == 0:
        return np.zeros((0, 3))
    t = trajectory.timestamps_ns
    if len(t) == 1:
        i = np.zeros(len(times), dtype=np.int64)
    else:
        i = np.clip(np.searchsorted(t, times), 1, len(t) - 1)
        i -= (times - t[i - 1]) < (t[i] - times)  # the nearer of the two neighbours
    centres = camera.T_world_cam(trajectory.T_world_body[i])[:, :3, 3]
    d = centres - np.asarray(point_world, dtype=float)
    n = np.linalg.norm(d, axis=1)
    return d[n > 0] / n[n > 0, None]


def visibility(
    points_world: np.ndarray,
    trajectory: Trajectory,
    camera: CameraModel,
    side_m: float,
    cones: list[tuple[np.ndarray, float] | None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """For each of (M, 3) code centres: the number of trajectory poses at which the front camera
    sees it inside the image (the whole symbol, approximated by its projected half side as the
    margin), in front of the camera, at readable range (projected side >= MIN_READABLE_SIDE_PX)
    and, where `cones` gives the code's (view_cone: the directions it was read from before), from
    inside that cone; and the largest projected side in px (0 if never in front).
    Returns ((M,) int, (M,) float)."""
    pts = np.asarray(points_world, dtype=float).reshape(-1, 3)
    counts = np.zeros(len(pts), dtype=int)
    best = np.zeros(len(pts))
    if len(trajectory) == 0 or len(pts) == 0:
        return counts, best
    T_world_cam = camera.T_world_cam(trajectory.T_world_body)  # (N, 4, 4)
    T_cam_world = inv_T(T_world_cam)
    f = min(camera.fu, camera.fv)
    for j, p in enumerate(pts):
        p_cam = np.einsum("nij,j->ni", T_cam_world[:, :3, :3], p) + T_cam_world[:, :3, 3]
        z = p_cam[:, 2]
        ahead = z > 1e-6
        side_px = np.where(ahead, f * side_m / np.where(ahead, z, 1.0), 0.0)
        uv = camera.project(np.where(ahead[:, None], p_cam, np.nan))
        margin = 0.5 * side_px
        inside = (
            ahead
            & (uv[:, 0] >= margin)
            & (uv[:, 0] <= camera.width - 1 - margin)
            & (uv[:, 1] >= margin)
            & (uv[:, 1] <= camera.height - 1 - margin)
        )
        readable = inside & (side_px >= MIN_READABLE_SIDE_PX)
        cone = None if cones is None else cones[j]
        if cone is not None:
            d = T_world_cam[:, :3, 3] - p
            readable &= d @ cone[0] >= cone[1] * np.linalg.norm(d, axis=1)
        counts[j] = int(np.count_nonzero(readable))
        best[j] = float(np.max(np.where(inside, side_px, 0.0), initial=0.0))
    return counts, best


def ambiguous_places(points_world: np.ndarray) -> list[np.ndarray]:
    """Centres of the separate places among one id's raw sightings (n, 3); two or more means the
    id is ambiguous.  Single-linkage clusters cut at AMBIGUITY_SEPARATION_M, keeping those with
    at least MIN_CLUSTER_OBS sightings."""
    pts = np.asarray(points_world, dtype=float).reshape(-1, 3)
    if len(pts) < 2 * MIN_CLUSTER_OBS:
        return [np.median(pts, axis=0)] if len(pts) else []
    labels = fcluster(linkage(pts, method="single"), t=AMBIGUITY_SEPARATION_M, criterion="distance")
    places = [
        np.median(pts[labels == k], axis=0)
        for k in np.unique(labels)
        if np.count_nonzero(labels == k) >= MIN_CLUSTER_OBS
    ]
    return sorted(places, key=lambda p: tuple(p))


# ============================================================================ inventory


def inventory(run: RunOutputs, expected: list[ExpectedLoad]) -> InventoryResult:
    """Statuses of every expected and every mapped load of `run` (module docstring)."""
    notes: list[str] = []
    mapped = run.load_map.by_id()
    places = {lid: ambiguous_places(obs) for lid, obs in run.observations.items()}
    ambiguous = {lid for lid, p in places.items() if len(p) >= 2}
    not_read = [e for e in expected if e.load_id not in mapped and e.load_id not in ambiguous]
    view: dict[str, tuple[int | None, float | None]] = {e.load_id: (None, None) for e in not_read}
    world = run.world
    if not_read:
        if run.front_camera is None or world is None:
            notes.append(
                "front camera unknown (no run.json and no --log): expected loads that "
                "were not read are all reported as not surveyed"
            )
        else:
            faceless = sum(e.face_yaw_rad is None for e in not_read)
            if faceless:
                notes.append(
                    f"{faceless} loads not read have no face_yaw_deg in the manifest: a pose behind "
                    "their rack counts as seeing them (a 'missing' there may be hidden)"
                )
            frames, best = visibility(
                np.array([e.p_world for e in not_read]),
                run.trajectory,
                run.front_camera,
                world.load_side_m,
                [face_cone(e.face_yaw_rad) for e in not_read],
            )
            view = {e.load_id: (int(n), float(b)) for e, n, b in zip(not_read, frames, best, strict=True)}
    rows: list[InventoryRow] = []
    for e in expected:
        est = mapped.get(e.load_id)
        if e.load_id in ambiguous:
            rows.append(
                InventoryRow(
                    e.load_id,
                    Status.AMBIGUOUS,
                    e,
                    est.p_world if est else None,
                    n_obs=est.n_obs if est else 0,
                    places=places[e.load_id],
                )
            )
        elif est is not None:
            dist, sigma, stat, pval = moved_test(est.p_world, est.cov_world, e.p_world, e.tolerance_m)
            status = Status.MOVED if pval < MOVED_ALPHA else Status.PRESENT
            rows.append(InventoryRow(e.load_id, status, e, est.p_world, dist, sigma, stat, pval, est.n_obs))
        else:
            n_view, side = view[e.load_id]
            status = Status.MISSING if (n_view or 0) >= MIN_FRAMES_IN_VIEW else Status.NOT_SURVEYED
            rows.append(InventoryRow(e.load_id, status, e, frames_in_view=n_view, max_side_px=side))
    expected_ids = {e.load_id for e in expected}
    for lid in sorted(set(mapped) - expected_ids):
        est = mapped[lid]
        status = Status.AMBIGUOUS if lid in ambiguous else Status.UNEXPECTED
        rows.append(
            InventoryRow(
                lid,
                status,
                None,
                est.p_world,
                n_obs=est.n_obs,
                places=places.get(lid, []) if lid in ambiguous else [],
            )
        )
    return InventoryResult(rows, run.estimator, notes)


MANIFEST_BOUNDS_MARGIN_M = 1.0
"""How far outside world.yaml's bounds_m an expected position may lie (a label on the outer face
of a rack at the wall) before the manifest is refused."""


def check_inside_warehouse(expected: list[ExpectedLoad], world: World | None, manifest: Path) -> None:
    """WarehouseError naming the manifest's line of the first expected position outside the
    warehouse's bounds (world.yaml bounds_m, MANIFEST_BOUNDS_MARGIN_M beyond): a plain manifest
    is in metres, and one filled in mm or cm would otherwise report every load "moved" by
    kilometres.  Nothing is checked when the bounds are unknown."""
    if world is None:
        return
    for e in expected:
        if not world.contains(e.p_world, MANIFEST_BOUNDS_MARGIN_M):
            x, y = (float(v) for v in e.p_world[:2])
            raise WarehouseError(
                f"{manifest}:{e.line}: {e.load_id!r} expected at x {x:g}, y {y:g} m, outside the "
                f"warehouse (world.yaml bounds_m x {list(world.bounds_x_m or ())}, y "
                f"{list(world.bounds_y_m or ())}); a plain manifest is in metres (mm or cm? use the "
                "WMS layout's unit column)"
            )


def run_inventory(
    run_out: Path,
    manifest: Path,
    estimator: str = Estimator.SMOOTHER,
    log: Path | None = None,
    write: bool = True,
) -> InventoryResult:
    """`fusion inventory`: read the run and the manifest, classify, and (with `write`) write
    `inventory.csv` and `inventory.md` into the run folder, put the section into report.md and
    re-draw report.html with the inventory colours."""
    expected = read_manifest(manifest)
    run = load_run(run_out, estimator, log)
    check_inside_warehouse(expected, run.world, manifest)
    result = inventory(run, expected)
    if write:
        out = Path(run_out)
        write_inventory_csv(out / "inventory.csv", result)
        section = inventory_markdown(result)
        with atomic_open(out / "inventory.md") as f:
            f.write("\n".join(section) + "\n")
        attach_to_report(out / "report.md", section)
        from fusion.warehouse.view3d import write_run_html

        write_run_html(out, result, log=log)
    return result


# ============================================================================ outputs


def _f(v, fmt="{:.6f}") -> str:
    return "" if v is None else fmt.format(v)


def write_inventory_csv(path: Path, result: InventoryResult) -> None:
    """One row per load (INVENTORY_COLUMNS); ids and location codes neutralised against CSV
    injection; `places` lists the ambiguous places as `x y z` triples separated by `;`."""
    with atomic_open(path) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(INVENTORY_COLUMNS)
        for r in result.rows:
            e = r.expected
            w.writerow(
                [
                    escape.csv_cell(r.load_id),
                    str(r.status),
                    escape.csv_cell(e.location) if e is not None and e.location else "",
                    *((_f(v) for v in e.p_world) if e is not None else ("",) * 3),
                    *((_f(v) for v in r.p_map) if r.p_map is not None else ("",) * 3),
                    _f(r.distance_m),
                    _f(r.sigma_m),
                    _f(r.chi2, "{:.3f}"),
                    _f(r.p_value, "{:.3g}"),
                    _f(e.tolerance_m if e else None),
                    r.n_obs,
                    "" if r.frames_in_view is None else r.frames_in_view,
                    _f(r.max_side_px, "{:.1f}"),
                    ";".join(" ".join(f"{v:.3f}" for v in p) for p in r.places),
                ]
            )


def inventory_markdown(result: InventoryResult) -> list[str]:
    """The report section: counts per status, then a table of every load (ids escaped)."""
    counts = result.counts()
    lines = [
        "## Inventory",
        "",
        f"Load map `{escape.markdown(result.estimator)}` against the manifest: "
        + ", ".join(f"{n} {s.replace('_', ' ')}" for s, n in counts.items())
        + ".",
        "",
        f"Moved: chi-square test (3 dof, alpha {MOVED_ALPHA:g}) of the difference with "
        "the map covariance plus the placement tolerance. Missing: not read although in the "
        f"front camera's view with the code spanning at least {MIN_READABLE_SIDE_PX:.0f} px "
        f"in at least {MIN_FRAMES_IN_VIEW} poses (from in front of the label, within "
        f"{MAX_READ_OBLIQUITY_DEG:.0f} deg of its normal, where the manifest gives its "
        "face_yaw_deg); not surveyed otherwise.",
        "",
    ]
    for note in result.notes:
        lines += [f"> {escape.markdown(note)}", ""]
    lines += [
        "| id | location | status | distance [cm] | σ [cm] | χ² | n obs | frames in view |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    order = {
        s: i
        for i, s in enumerate(
            [
                Status.MOVED,
                Status.MISSING,
                Status.AMBIGUOUS,
                Status.UNEXPECTED,
                Status.NOT_SURVEYED,
                Status.PRESENT,
            ]
        )
    }
    for r in sorted(result.rows, key=lambda r: (order[r.status], r.load_id)):
        loc = r.expected.location if r.expected is not None and r.expected.location else ""
        lines.append(
            "| "
            + " | ".join(
                [
                    escape.markdown(r.load_id),
                    escape.markdown(loc),
                    str(r.status).replace("_", " "),
                    _f(None if r.distance_m is None else 100 * r.distance_m, "{:.2f}"),
                    _f(None if r.sigma_m is None else 100 * r.sigma_m, "{:.2f}"),
                    _f(r.chi2, "{:.1f}"),
                    str(r.n_obs) if r.n_obs else "",
                    "" if r.frames_in_view is None else str(r.frames_in_view),
                ]
            )
            + " |"
        )
    lines.append("")
    return lines


REPORT_BEGIN = "<!-- inventory:begin -->"
REPORT_END = "<!-- inventory:end -->"


def attach_to_report(report_md: Path, section: list[str]) -> None:
    """Put `section` between the REPORT_BEGIN / REPORT_END markers of report.md (written there by
    the report's inventory hook), or append it with the markers; nothing if there is no report."""
    report_md = Path(report_md)
    if not report_md.exists():
        return
    text = report_md.read_text(encoding="utf-8")
    block = "\n".join([REPORT_BEGIN, *section, REPORT_END])
    a, b = text.find(REPORT_BEGIN), text.find(REPORT_END)
    if a >= 0 and b > a:
        text = text[:a] + block + text[b + len(REPORT_END) :]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    with atomic_open(report_md) as f:
        f.write(text)


def status_colours() -> dict[Status, str]:
    """Colours of the statuses in report.html."""
    return {
        Status.PRESENT: "#2ca02c",
        Status.MOVED: "#ff7f0e",
        Status.MISSING: "#d62728",
        Status.NOT_SURVEYED: "#7f7f7f",
        Status.UNEXPECTED: "#9467bd",
        Status.AMBIGUOUS: "#e377c2",
    }


__all__ = [
    "Status",
    "InventoryRow",
    "InventoryResult",
    "inventory",
    "run_inventory",
    "moved_test",
    "visibility",
    "ambiguous_places",
    "write_inventory_csv",
    "inventory_markdown",
    "attach_to_report",
    "LoadMap",
]
