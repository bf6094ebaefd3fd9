"""`report.html`: a self-contained interactive 3D view of a run (issue #12, item 4).

plotly with its JavaScript embedded (`include_plotlyjs=True`), so the page opens offline.  It
shows the floor codes decoded in the flight, the raw (dots) and fused (lines) trajectories with a
time slider that moves a marker per estimator, the load map with ELLIPSOID_SIGMAS-sigma
covariance ellipsoids, coloured by inventory status once `fusion inventory` has run (it redraws
the page), the expected places of loads that were not read, and hover text naming each code and
load (ids HTML-escaped: plotly renders hover text as HTML).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import plotly.graph_objects as go

from fusion.conventions import FloorPayload, floor_payload, parse_payload
from fusion.errors import PayloadError
from fusion.fileio import atomic_open
from fusion.log.files import read_tum
from fusion.types import Estimator, LoadMap, PositionTrack, Trajectory
from fusion.warehouse import escape

logger = logging.getLogger(__name__)

REPORT_HTML = "report.html"
ELLIPSOID_SIGMAS = 3.0
"""Ellipsoids are drawn at 3 sigma (a 3D Gaussian puts 97 % of its mass inside)."""
ELLIPSOID_LAT, ELLIPSOID_LON = 8, 12  # mesh resolution of an ellipsoid
SLIDER_STEPS = 60  # positions of the time slider
MAX_DISPLAY_POSES = 2000  # trajectories are decimated to this many points
MAP_PREFERENCE = (Estimator.SMOOTHER, Estimator.INCREMENTAL, Estimator.EKF, Estimator.PNP, Estimator.PAPER)
TRAJECTORY_COLOURS = {
    Estimator.PAPER: "#8c564b",
    Estimator.PNP: "#1f77b4",
    Estimator.SMOOTHER: "#d62728",
    Estimator.INCREMENTAL: "#ff7f0e",
    Estimator.EKF: "#2ca02c",
    "groundtruth": "#555555",
}
LOAD_COLOUR = "#17becf"  # loads without an inventory
FLOOR_COLOUR = "#bbbbbb"
MISPLACED_COLOUR = "#d62728"  # as-built floor codes flagged misplaced


def _decimate(n: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(n, MAX_DISPLAY_POSES)).round().astype(int))


def _ellipsoid_mesh(p: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (F, 3) of the ELLIPSOID_SIGMAS-sigma ellipsoid of (p, cov)."""
    lat = np.linspace(0.0, np.pi, ELLIPSOID_LAT + 1)
    lon = np.linspace(0.0, 2 * np.pi, ELLIPSOID_LON, endpoint=False)
    sphere = np.array([[np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)] for a in lat for b in lon])
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    A = V @ np.diag(ELLIPSOID_SIGMAS * np.sqrt(np.clip(w, 0.0, None)))
    verts = p + sphere @ A.T
    tris = []
    for i in range(ELLIPSOID_LAT):
        for j in range(ELLIPSOID_LON):
            a, b = i * ELLIPSOID_LON + j, i * ELLIPSOID_LON + (j + 1) % ELLIPSOID_LON
            c, d = a + ELLIPSOID_LON, b + ELLIPSOID_LON
            tris += [(a, b, c), (b, d, c)]
    return verts, np.array(tris)


def _load_hover(load_id: str, p: np.ndarray, cov: np.ndarray | None, n_obs: int, status: str | None) -> str:
    sig = (
        ""
        if cov is None
        else "<br>σ " + " / ".join(f"{100 * s:.2f}" for s in np.sqrt(np.clip(np.diag(cov), 0, None))) + " cm"
    )
    st = "" if status is None else f"<br>{escape.html_text(status).replace('_', ' ')}"
    return (
        f"load {escape.html_text(load_id)}{st}<br>x {p[0]:.3f} y {p[1]:.3f} z {p[2]:.3f} m"
        f"{sig}<br>{n_obs} sightings"
    )


def build_figure(
    trajectories: dict[str, Trajectory],
    load_map: LoadMap | None,
    floor_codes_xy_m: np.ndarray | None = None,
    payload_unit_m: float = 1.0,
    statuses: dict | None = None,
    expected: list | None = None,
    groundtruth: Trajectory | PositionTrack | None = None,
    title: str = "fusion: 3D view",
    misplaced_codes: list[tuple[str, np.ndarray, str]] | None = None,
) -> go.Figure:
    """The figure: floor codes, trajectories (raw: dots, fused: lines, truth: grey), a marker per
    trajectory driven by the time slider, the loads of `load_map` with their ellipsoids, coloured
    by `statuses` {id: Status} when given, and `expected` (ExpectedLoad list) places not read.
    `misplaced_codes` [(id, (3,) estimated world centre, hover detail)]: as-built floor codes
    flagged misplaced (fusion.estimate.asbuilt), drawn large and red."""
    from fusion.warehouse.inventory import Status, status_colours

    colours = status_colours()
    fig = go.Figure()
    if floor_codes_xy_m is not None and len(floor_codes_xy_m):
        xy = np.asarray(floor_codes_xy_m, dtype=float).reshape(-1, 2)
        hover = [
            f"floor code {escape.html_text(floor_payload(x / payload_unit_m, y / payload_unit_m))}"
            f"<br>x {x:.3f} y {y:.3f} m"
            for x, y in xy
        ]
        fig.add_trace(
            go.Scatter3d(
                x=xy[:, 0],
                y=xy[:, 1],
                z=np.zeros(len(xy)),
                mode="markers",
                marker={"symbol": "square", "size": 5, "color": FLOOR_COLOUR},
                name="floor codes",
                hovertext=hover,
                hoverinfo="text",
            )
        )
    if misplaced_codes:
        p = np.array([c[1] for c in misplaced_codes], dtype=float).reshape(-1, 3)
        fig.add_trace(
            go.Scatter3d(
                x=p[:, 0],
                y=p[:, 1],
                z=p[:, 2],
                mode="markers",
                marker={"symbol": "square", "size": 9, "color": MISPLACED_COLOUR},
                name="misplaced floor codes",
                hovertext=[
                    f"MISPLACED floor code {escape.html_text(cid)}<br>{escape.html_text(detail)}"
                    for cid, _, detail in misplaced_codes
                ],
                hoverinfo="text",
            )
        )
    trajs: dict[str, Trajectory | PositionTrack] = dict(trajectories)
    if groundtruth is not None and len(groundtruth):
        trajs = {"groundtruth": groundtruth, **trajs}
    shown = [(name, t) for name, t in trajs.items() if len(t)]
    for name, traj in shown:
        idx = _decimate(len(traj))
        p = traj.positions_xyz[idx]
        t_s = traj.timestamps_s[idx]
        raw = name in (Estimator.PAPER, Estimator.PNP)
        fig.add_trace(
            go.Scatter3d(
                x=p[:, 0],
                y=p[:, 1],
                z=p[:, 2],
                mode="markers" if raw else "lines",
                name=f"{escape.html_text(name)} trajectory",
                marker={"size": 1.5, "color": TRAJECTORY_COLOURS.get(name, "#000000")},
                line={
                    "width": 3 if name != "groundtruth" else 2,
                    "color": TRAJECTORY_COLOURS.get(name, "#000000"),
                },
                hovertext=[f"{escape.html_text(name)} t {v:.2f} s" for v in t_s],
                hoverinfo="text",
            )
        )
    # time slider: a marker per trajectory at the pose nearest (at or before) each step's time
    marker_traces = []
    if shown:
        t0 = min(float(t.timestamps_s[0]) for _, t in shown)
        t1 = max(float(t.timestamps_s[-1]) for _, t in shown)
        times = np.linspace(t0, t1, SLIDER_STEPS)
        positions = []
        for name, traj in shown:
            k = np.clip(np.searchsorted(traj.timestamps_s, times, side="right") - 1, 0, len(traj) - 1)
            positions.append(traj.positions_xyz[k])
            marker_traces.append(len(fig.data))
            fig.add_trace(
                go.Scatter3d(
                    x=[positions[-1][0, 0]],
                    y=[positions[-1][0, 1]],
                    z=[positions[-1][0, 2]],
                    mode="markers",
                    showlegend=False,
                    name=f"{escape.html_text(name)} at t",
                    marker={"size": 6, "color": TRAJECTORY_COLOURS.get(name, "#000000"), "symbol": "diamond"},
                    hoverinfo="name",
                )
            )
        steps = [
            {
                "method": "restyle",
                "label": f"{times[i] - t0:.1f}",
                "args": [
                    {
                        "x": [[p[i, 0]] for p in positions],
                        "y": [[p[i, 1]] for p in positions],
                        "z": [[p[i, 2]] for p in positions],
                    },
                    marker_traces,
                ],
            }
            for i in range(SLIDER_STEPS)
        ]
        fig.update_layout(
            sliders=[
                {
                    "active": 0,
                    "steps": steps,
                    "currentvalue": {"prefix": "time since start [s]: "},
                    "pad": {"t": 20},
                }
            ]
        )
    # loads
    if load_map is not None and load_map.loads:
        loads = sorted(load_map.loads, key=lambda l: l.load_id)
        p = np.array([l.p_world for l in loads])
        st = [statuses.get(l.load_id) if statuses else None for l in loads]
        cols = [colours.get(s, LOAD_COLOUR) if s is not None else LOAD_COLOUR for s in st]
        fig.add_trace(
            go.Scatter3d(
                x=p[:, 0],
                y=p[:, 1],
                z=p[:, 2],
                mode="markers",
                name=f"loads ({escape.html_text(load_map.name)})",
                marker={"size": 5, "color": cols, "line": {"width": 1, "color": "#000000"}},
                hovertext=[
                    _load_hover(l.load_id, l.p_world, l.cov_world, l.n_obs, None if s is None else str(s))
                    for l, s in zip(loads, st, strict=False)
                ],
                hoverinfo="text",
            )
        )
        first = True
        for l, c in zip(loads, cols, strict=False):
            if l.cov_world is None:
                continue
            v, f = _ellipsoid_mesh(np.asarray(l.p_world, dtype=float), np.asarray(l.cov_world))
            fig.add_trace(
                go.Mesh3d(
                    x=v[:, 0],
                    y=v[:, 1],
                    z=v[:, 2],
                    i=f[:, 0],
                    j=f[:, 1],
                    k=f[:, 2],
                    color=c,
                    opacity=0.35,
                    legendgroup="ellipsoids",
                    name=f"{ELLIPSOID_SIGMAS:g}σ ellipsoids",
                    showlegend=first,
                    hovertext=escape.html_text(l.load_id),
                    hoverinfo="text",
                )
            )
            first = False
    if expected and statuses:
        mapped = set(load_map.by_id()) if load_map is not None else set()
        for status in (Status.MISSING, Status.NOT_SURVEYED, Status.MOVED):
            es = [
                e
                for e in expected
                if statuses.get(e.load_id) == status and (status != Status.MOVED or e.load_id in mapped)
            ]
            if not es:
                continue
            q = np.array([e.p_world for e in es])
            fig.add_trace(
                go.Scatter3d(
                    x=q[:, 0],
                    y=q[:, 1],
                    z=q[:, 2],
                    mode="markers",
                    name=(
                        "expected place of moved loads"
                        if status == Status.MOVED
                        else f"expected, {str(status).replace('_', ' ')}"
                    ),
                    marker={"size": 6, "symbol": "circle-open", "color": colours[status]},
                    hovertext=[
                        f"expected {escape.html_text(e.load_id)}"
                        + (f" at {escape.html_text(e.location)}" if e.location else "")
                        + f"<br>{str(status).replace('_', ' ')}"
                        f"<br>x {e.p_world[0]:.3f} y {e.p_world[1]:.3f} z {e.p_world[2]:.3f} m"
                        for e in es
                    ],
                    hoverinfo="text",
                )
            )
    fig.update_layout(
        title=escape.html_text(title),
        scene={"aspectmode": "data", "xaxis_title": "x [m]", "yaxis_title": "y [m]", "zaxis_title": "z [m]"},
        legend={"itemsizing": "constant"},
        margin={"l": 0, "r": 0, "t": 40, "b": 0},
    )
    return fig


def write_html(path: Path, fig: go.Figure) -> Path:
    """Write `fig` as one self-contained HTML file (plotly.js embedded, no network needed)."""
    html = fig.to_html(include_plotlyjs=True, full_html=True, config={"responsive": True})
    with atomic_open(path) as f:
        f.write(html)
    return Path(path)


def pick_load_map(load_maps: dict[str, LoadMap]) -> LoadMap | None:
    """The map the view shows: the first of MAP_PREFERENCE the run has."""
    for name in MAP_PREFERENCE:
        if name in load_maps:
            return load_maps[name]
    return next(iter(load_maps.values()), None)


def write_report_html(
    out_dir: Path,
    trajectories: dict[str, Trajectory],
    load_maps: dict[str, LoadMap],
    floor_codes_xy_m: np.ndarray | None = None,
    payload_unit_m: float = 1.0,
    groundtruth: Trajectory | PositionTrack | None = None,
    misplaced_codes: list[tuple[str, np.ndarray, str]] | None = None,
) -> Path:
    """`out_dir/report.html` of a run (no inventory yet); misplaced_codes as build_figure's."""
    fig = build_figure(
        trajectories,
        pick_load_map(load_maps),
        floor_codes_xy_m,
        payload_unit_m,
        groundtruth=groundtruth,
        title=f"fusion: {Path(out_dir).name}",
        misplaced_codes=misplaced_codes,
    )
    return write_html(Path(out_dir) / REPORT_HTML, fig)


def floor_codes_from_detections(out_dir: Path, payload_unit_m: float) -> np.ndarray | None:
    """World (x, y) of every floor code in the run's detections.csv (None without it)."""
    from fusion.qr.detect import read_cache

    cached = read_cache(Path(out_dir) / "detections.csv")
    if cached is None:
        return None
    return floor_codes_from_payloads((d.payload for d in cached.for_camera("cam0")), payload_unit_m)


def floor_codes_from_payloads(payloads: Iterable[str], payload_unit_m: float) -> np.ndarray | None:
    """World (x, y) of every floor code among the floor camera's decoded `payloads` (sorted,
    each once), None when there is none; other payloads are ignored."""
    xy = set()
    for payload in set(payloads):  # a code is read in hundreds of frames: parse it once
        try:
            p = parse_payload(payload)
        except PayloadError:
            continue
        if isinstance(p, FloorPayload):
            xy.add((p.x * payload_unit_m, p.y * payload_unit_m))
    return np.array(sorted(xy)) if xy else None


def write_run_html(
    out_dir: Path, inventory_result=None, expected: list | None = None, log: Path | None = None
) -> Path:
    """Redraw `out_dir/report.html` from the run's files (trajectory_*.tum, loads_*.json,
    detections.csv, run.json or `log`), with the inventory's colours when given."""
    from fusion.warehouse.runs import load_run

    out_dir = Path(out_dir)
    trajectories = {}
    for name in Estimator:
        path = out_dir / f"trajectory_{name}.tum"
        if path.exists():
            trajectories[str(name)] = read_tum(path, str(name))
    gt_path = out_dir / "trajectory_groundtruth.tum"
    gt = read_tum(gt_path, "groundtruth") if gt_path.exists() else None
    estimator = inventory_result.estimator if inventory_result is not None else Estimator.SMOOTHER
    run = load_run(out_dir, estimator, log)
    world = run.world
    unit = world.payload_unit_m if world is not None else 1.0
    statuses = inventory_result.statuses() if inventory_result is not None else None
    if expected is None and inventory_result is not None:
        expected = [r.expected for r in inventory_result.rows if r.expected is not None]
    fig = build_figure(
        trajectories,
        run.load_map,
        floor_codes_from_detections(out_dir, unit),
        unit,
        statuses,
        expected,
        gt,
        title=f"fusion: {out_dir.name}",
    )
    return write_html(out_dir / REPORT_HTML, fig)
