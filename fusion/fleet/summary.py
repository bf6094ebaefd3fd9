"""The fleet summary: `OUT/fleet.csv` (one row per flight) and `OUT/fleet.md` (the table, the
totals and two plots), from fleet.json's records and each flight's `metrics.json`.

Per flight: status and failure reason; health (the worst fused estimator's, RunResult.health);
coverage (share of floor frames with a raw QR fix, PnP); ATE RMSE of the smoother when the
log has ground truth; loads mapped (smoother, else PnP); the flight's length, its task seconds
and its wall time, and their ratio to the flight's length.
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # never open a window
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from fusion.errors import FleetError, first_line  # noqa: E402
from fusion.estimate.health import Status  # noqa: E402
from fusion.fileio import atomic_open, csv_safe, open_regular  # noqa: E402
from fusion.fleet.flights import FlightRecord, FlightStatus  # noqa: E402
from fusion.types import Estimator  # noqa: E402

logger = logging.getLogger(__name__)

CSV_NAME = "fleet.csv"
MD_NAME = "fleet.md"
TIME_PLOT = "fleet_time.png"
ERROR_PLOT = "fleet_ate.png"
HEADLINE = Estimator.SMOOTHER  # whose ATE and load map the summary shows
FALLBACK = Estimator.PNP
HEALTH_ORDER = (Status.OK, Status.DEGRADED, Status.DIVERGED)  # worst last
NO_HEALTH = "none"  # no fused estimator ran (no IMU and no velocity, no floor code)
UNREAD_HEALTH = "unknown"  # the flight finished but its metrics.json could not be read
DPI = 110
_HEALTH_COLOURS = {"ok": "#009e73", "degraded": "#e69f00", "diverged": "#d55e00", NO_HEALTH: "#999999"}
COLUMNS = (
    "flight",
    "status",
    "health",
    "coverage",
    "ate_rmse_m",
    "loads_mapped",
    "duration_s",
    "frames",
    "compute_s",
    "wall_s",
    "attempts",
    "failure",
    "health_detail",
    "path",
    "warnings",
)


@dataclass
class FlightRow:
    """One line of fleet.csv."""

    flight: str
    status: str
    health: str = ""
    coverage: float | None = None
    ate_rmse_m: float | None = None
    loads_mapped: int | None = None
    duration_s: float | None = None
    frames: int | None = None
    compute_s: float | None = None
    wall_s: float | None = None
    attempts: int = 0
    failure: str = ""
    health_detail: str = ""
    path: str = ""
    warnings: str = ""  # the run's named warnings, "name xcount; ..." (clock, lens, mount, ...)


def flight_row(out: Path, rec: FlightRecord) -> FlightRow:
    """The summary of one flight: its record, and OUT/<name>/metrics.json when it finished."""
    row = FlightRow(
        rec.name,
        rec.status or "not run",
        duration_s=rec.duration_s,
        frames=rec.n_frames,
        compute_s=rec.compute_s,
        wall_s=rec.wall_s,
        attempts=rec.attempts,
        failure=rec.reason,
        path=rec.path,
    )
    if rec.status != FlightStatus.OK:
        return row
    metrics, problem = _read_metrics(Path(out) / rec.name / "metrics.json")
    if metrics is None:  # finished, but its health and warnings cannot be told: not "ok" for them
        row.health = UNREAD_HEALTH
        row.health_detail = f"metrics.json not read ({problem}): health, coverage and warnings unknown"
        return row
    health = metrics.get("health") or {}
    statuses = [str(h.get("status")) for h in health.values()]
    known = [s for s in statuses if s in HEALTH_ORDER]
    row.health = max(known, key=lambda s: HEALTH_ORDER.index(Status(s))) if known else NO_HEALTH
    details = [
        f"{n} {h.get('status')}" + ("" if h.get("status") == Status.OK else f": {h.get('reason')}")
        for n, h in health.items()
    ]
    details += [
        f"{n} failed: {f.get('reason')}" for n, f in (metrics.get("estimator_failures") or {}).items()
    ]
    row.warnings = "; ".join(
        f"{w.get('name')} x{w.get('count')}"
        for w in metrics.get("warnings") or []
        if isinstance(w, dict) and w.get("name")
    )
    if not known and row.warnings:  # no fused estimate: the log's warnings say why (e.g. no_floor_pose)
        details.append(row.warnings)
    row.health_detail = "; ".join(details)
    pnp = (metrics.get("estimator_stats") or {}).get(str(FALLBACK)) or {}
    # every floor frame of the log, not PnP's n_frames (the frames with a detection only: a
    # flight whose codes were read in half its frames read 100 % until 2026-12-05)
    n_floor = (metrics.get("detection") or {}).get("floor_frames") or pnp.get("n_frames")
    if n_floor:
        row.coverage = pnp.get("n_posed", 0) / n_floor
    traj = (metrics.get("trajectories") or {}).get(str(HEADLINE)) or {}
    row.ate_rmse_m = traj.get("ate_rmse_m")
    maps = metrics.get("load_maps") or {}
    lm = maps.get(str(HEADLINE)) or maps.get(str(FALLBACK))
    if lm is not None:
        row.loads_mapped = lm.get("n_mapped")
    return row


def _read_metrics(path: Path) -> tuple[dict | None, str]:
    """(metrics.json's contents, "") or (None, why it could not be read)."""
    try:
        with open_regular(path, FleetError, newline=None) as f:
            data = json.load(f)
    except (FleetError, ValueError, UnicodeDecodeError) as e:
        logger.warning("%s: cannot read (%s); the flight's summary row says so", path, e)
        return None, first_line(e)
    if not isinstance(data, dict):
        return None, "not a JSON object"
    return data, ""


def write_summary(out: Path, records: list[FlightRecord]) -> list[Path]:
    """Write OUT/fleet.csv, OUT/fleet.md and its plots; returns their paths."""
    out = Path(out)
    rows = [flight_row(out, r) for r in sorted(records, key=lambda r: r.name)]
    paths = [_write_csv(out / CSV_NAME, rows)]
    plots = [_time_plot(out / TIME_PLOT, rows), _error_plot(out / ERROR_PLOT, rows)]
    paths.append(_write_md(out / MD_NAME, rows, [p for p in plots if p is not None]))
    return paths + [p for p in plots if p is not None]


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return csv_safe(str(v))


def _write_csv(path: Path, rows: list[FlightRow]) -> Path:
    with atomic_open(path) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow([_cell(getattr(r, c)) for c in COLUMNS])
    return path


def _md(text: str) -> str:
    """A table cell: no pipes or line breaks from untrusted text (paths, reasons)."""
    return str(text).replace("|", "\\|").replace("\n", " ").replace("`", "'")


def _write_md(path: Path, rows: list[FlightRow], plots: list[Path]) -> Path:
    ok = [r for r in rows if r.status == FlightStatus.OK]
    failed = [r for r in rows if r.status == FlightStatus.FAILED]
    flown = sum(r.duration_s or 0.0 for r in ok)
    compute = sum(r.compute_s or 0.0 for r in ok if r.compute_s is not None)
    lines = [
        "# Fleet summary",
        "",
        f"{len(rows)} flights: {len(ok)} ok, {len(failed)} failed, "
        f"{len(rows) - len(ok) - len(failed)} not run.",
        f"Flight time processed: {flown / 60:.1f} min; task time: {compute / 60:.1f} min "
        f"({compute / flown:.2f} s per flight second)."
        if flown > 0 and compute > 0
        else "",
        "",
        "Health is the worst fused estimator's; coverage is the share of floor frames with a raw "
        f"QR fix (PnP); ATE is the {HEADLINE}'s RMSE against ground truth (when the log has it); "
        "task time sums every task of the flight, wall time runs from its first task to its report.",
        "",
        "| flight | status | health | coverage | ATE cm | loads | flight s | task s | wall s | tries "
        "| failure |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            "| "
            + " | ".join(
                [
                    f"[{_md(r.flight)}]({_md(r.flight)}/report.md)"
                    if r.status == FlightStatus.OK
                    else _md(r.flight),
                    r.status,
                    r.health or "",
                    f"{100 * r.coverage:.1f} %" if r.coverage is not None else "",
                    f"{100 * r.ate_rmse_m:.2f}" if r.ate_rmse_m is not None else "",
                    str(r.loads_mapped) if r.loads_mapped is not None else "",
                    f"{r.duration_s:.1f}" if r.duration_s is not None else "",
                    f"{r.compute_s:.1f}" if r.compute_s is not None else "",
                    f"{r.wall_s:.1f}" if r.wall_s is not None else "",
                    str(r.attempts),
                    _md(r.failure),
                ]
            )
            + " |"
        )
    not_ok = [r for r in ok if r.health not in (Status.OK, "")]
    if not_ok:
        lines += ["", "## Health below ok", ""]
        lines += [f"- {_md(r.flight)}: {_md(r.health_detail)}" for r in not_ok]
    warned = [r for r in ok if r.warnings]
    if warned:
        # what each run warned of (a camera's clock or stamps, its mount, the log): a drone
        # whose flights all warn alike needs its setup fixed, not its flights re-run
        lines += ["", "## Warnings", ""]
        lines += [f"- {_md(r.flight)}: {_md(r.warnings)}" for r in warned]
    if plots:
        lines += [""] + [f"![{p.stem}]({p.name})" for p in plots]
    with atomic_open(path) as f:
        f.write("\n".join(lines) + "\n")
    return path


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=DPI)
    return path


def _time_plot(path: Path, rows: list[FlightRow]) -> Path | None:
    """Task seconds per flight second, per finished flight."""
    rs = [r for r in rows if r.status == FlightStatus.OK and r.compute_s and r.duration_s]
    if not rs:
        return None
    fig = Figure(figsize=(max(4.0, 0.5 * len(rs) + 2), 3.2), layout="constrained")
    ax = fig.add_subplot()
    ax.bar(
        range(len(rs)),
        [(r.compute_s or 0.0) / (r.duration_s or 1.0) for r in rs],
        color="#0072b2",
        label="task s",
    )
    wall = [(r.wall_s or 0.0) / (r.duration_s or 1.0) for r in rs]
    ax.plot(range(len(rs)), wall, "o", color="#d55e00", label="wall s")
    ax.set_xticks(range(len(rs)), [r.flight for r in rs], rotation=45, ha="right", fontsize=7)
    ax.set_ylabel("seconds per flight second")
    ax.set_title("processing cost per flight")
    ax.legend(fontsize=7)
    return _save(fig, path)


def _error_plot(path: Path, rows: list[FlightRow]) -> Path | None:
    """Smoother ATE per flight with ground truth, coloured by health."""
    rs = [r for r in rows if r.status == FlightStatus.OK and r.ate_rmse_m is not None]
    if not rs:
        return None
    fig = Figure(figsize=(max(4.0, 0.5 * len(rs) + 2), 3.2), layout="constrained")
    ax = fig.add_subplot()
    colours = [_HEALTH_COLOURS.get(r.health, _HEALTH_COLOURS[NO_HEALTH]) for r in rs]
    ax.bar(range(len(rs)), [100 * (r.ate_rmse_m or 0.0) for r in rs], color=colours)
    ax.set_xticks(range(len(rs)), [r.flight for r in rs], rotation=45, ha="right", fontsize=7)
    ax.set_ylabel(f"{HEADLINE} ATE RMSE (cm)")
    ax.set_title("trajectory error per flight (colour: health)")
    return _save(fig, path)
