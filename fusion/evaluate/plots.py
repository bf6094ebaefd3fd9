"""PNG plots of trajectories, errors and load maps (matplotlib, Agg canvas, never interactive).

Figures are built with `matplotlib.figure.Figure` (no pyplot state), saved atomically.  Each
estimator keeps its colour in every plot (`estimator_colour`); raw per-frame estimators are drawn
as dots (they have gaps), fused ones as lines.  Units: m, cm and degrees as labelled.

Scale: the paper's estimator (Alg. 1-3) errs by tens of cm, PnP and the fused estimators by
fractions of a cm.  Overviews that show both use log axes; the zoomed plots leave out the
estimators in `ZOOM_EXCLUDE` and take their y-range from a robust percentile of the others.
Long flights are decimated for drawing (per-bin min/max, so spikes survive); statistics such
as box plots always use every sample.
"""

from __future__ import annotations

import gc
import os
from collections.abc import Iterable
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

import matplotlib

matplotlib.use("Agg")  # never open a window, whatever the environment says
import numpy as np  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402
from matplotlib.ticker import NullFormatter, NullLocator  # noqa: E402

from fusion.evaluate.metrics import (  # noqa: E402
    PAPER_SIM_LOADMAP_MAE_CM,
    PAPER_SIM_LOCALIZATION_MAE_CM,
    PAPER_SIM_YAW_MAE_DEG,
    Association,
    TruthPoses,
    associate_many,
)
from fusion.fileio import atomic_open  # noqa: E402
from fusion.types import RAW_ESTIMATORS, LoadMap, Trajectory  # noqa: E402

DEFAULT_DPI = 130
TRUTH_COLOUR = "#222222"
UNSEEN_COLOUR = "#aaaaaa"
ZOOM_EXCLUDE = ("paper",)  # left out of the zoomed (cm-scale) plots: its errors set the scale
MAX_DRAWN_POINTS = 4000  # per series; longer series are min/max-decimated for drawing
PNG_COMPRESS_LEVEL = 1
"""zlib level of the PNGs: 1 encodes ~2x faster than PIL's default 6 for ~5 % larger files
(measured on error_boxplots.png: 0.052 s / 156 KB against 0.094 s / 149 KB); same pixels."""
LOG_FLOOR = 1e-4  # smallest value drawn on log axes (cm or deg)
_COLOURS = {
    "paper": "#e69f00",
    "pnp": "#0072b2",
    "smoother": "#009e73",
    "incremental": "#56b4e9",
    "ekf": "#cc79a7",
}
_EXTRA = ("#d55e00", "#8c564b", "#999999", "#f0e442", "#17becf")


def estimator_colour(name: str) -> str:
    """Fixed colour per estimator (Okabe-Ito palette, colour-blind safe)."""
    if name in _COLOURS:
        return _COLOURS[name]
    return _EXTRA[sum(map(ord, name)) % len(_EXTRA)]


_P = TypeVar("_P", Path, "Path | None")


def _freed(path: _P) -> _P:
    """`path`, after a full garbage collection: a Figure and its canvas are a reference cycle,
    so a drawn figure (its artists, the Agg renderer's buffer) outlives its plot function
    until the cyclic collector's oldest generation runs, which the next plots do not
    trigger: plot_all's figures piled up at the evaluation's memory peak (BENCHMARKS.md).
    Inside `_heap_frozen` the collection looks only at what was made since (the figures)."""
    gc.collect()
    return path


@contextmanager
def _heap_frozen():
    """The objects that exist now left out of the garbage collector's passes until the end
    (gc.freeze): plot_all's full collection after each figure then walks the figure's objects
    only, not the flight's (trajectories, sightings, detections: a full pass over them was ~10 %
    of the report's CPU on the 10-minute flight).  Nothing is frozen when a caller froze first
    (gc.unfreeze would release its objects too)."""
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _save(fig: Figure, path: Path, dpi: int) -> Path:
    """`fig` as a PNG at `dpi`.  A figure with a layout engine (constrained) is laid out once,
    here, at the saving dpi, and then saved without it: savefig would otherwise draw the whole
    figure once with drawing disabled only to run the layout, then again to render it (the
    layout is the same: it runs on the same figure at the same dpi before any artist is drawn)."""
    FigureCanvasAgg(fig)
    path = Path(path)
    engine = fig.get_layout_engine()
    if engine is not None:
        fig.set_dpi(dpi)
        engine.execute(fig)
        # None, not "none" (a placeholder engine, which savefig would still pre-draw for)
        with matplotlib.rc_context({"figure.autolayout": False, "figure.constrained_layout.use": False}):
            fig.set_layout_engine(None)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=dpi, pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
    return path


# ============================================================================ helpers


def decimate_minmax(y: np.ndarray, max_points: int = MAX_DRAWN_POINTS) -> np.ndarray:
    """Indices (sorted) of at most ~`max_points` samples of the 1-D series `y` that keep each
    bin's minimum and maximum, so that spikes stay visible; all indices when `y` is short."""
    y = np.asarray(y, dtype=float)
    n = len(y)
    if n <= max_points:
        return np.arange(n)
    n_bins = max(max_points // 2, 1)
    k = -(-n // n_bins)  # samples per bin (ceil)
    n_bins = -(-n // k)
    padded = np.full(n_bins * k, np.nan)
    padded[:n] = np.where(np.isfinite(y), y, np.nan)
    rows = padded.reshape(n_bins, k)
    ok = ~np.all(np.isnan(rows), axis=1)
    base = np.arange(n_bins)[ok] * k
    lo = base + np.nanargmin(rows[ok], axis=1)
    hi = base + np.nanargmax(rows[ok], axis=1)
    return np.unique(np.concatenate([lo, hi]))


def _stride(n: int, max_points: int = MAX_DRAWN_POINTS) -> slice:
    return slice(None, None, max(1, -(-n // max_points)))


def _gt_xyz(gt) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(gt.timestamps_ns, dtype=np.int64), np.asarray(gt.p_world, dtype=float)


def time_origin_ns(gt, trajectories: dict[str, Trajectory]) -> int:
    """Timestamp (ns) that the plots' time axes count from: the earliest of truth and estimates."""
    starts = [int(t.timestamps_ns[0]) for t in trajectories.values() if len(t)]
    if gt is not None and len(gt.timestamps_ns):
        starts.append(int(gt.timestamps_ns[0]))
    return min(starts) if starts else 0


def associate_all(trajectories: dict[str, Trajectory], gt) -> dict[str, Association]:
    """{name: Association with the truth} for every trajectory that overlaps it (shared by the
    error plots so that a long flight is associated once)."""
    t_gt = np.asarray(gt.timestamps_ns, dtype=np.int64)
    assoc = associate_many(t_gt, TruthPoses(gt), {n: t for n, t in trajectories.items() if len(t)})
    return {name: a for name, a in assoc.items() if len(a)}


def _world_sigma_cm(a: Association) -> np.ndarray | None:
    """(M, 3) 1-sigma position in world axes, cm (R P_tt R^T of the body-frame covariance)."""
    if a.covariances is None:
        return None
    R = a.T_world_body_est[:, :3, :3]
    P = R @ a.covariances[:, 3:, 3:] @ np.swapaxes(R, 1, 2)
    return 100.0 * np.sqrt(np.clip(np.diagonal(P, axis1=1, axis2=2), 0, None))


def _floor_grid(
    ax, xy_m: np.ndarray | None, extent: tuple[float, float, float, float] | None, unit_m: float | None
) -> None:
    """Faint floor-code markers: the given centres, else grid points at multiples of `unit_m`."""
    if xy_m is None and unit_m and extent is not None:
        x0, x1, y0, y1 = extent
        gx = np.arange(np.floor(x0 / unit_m), np.ceil(x1 / unit_m) + 1) * unit_m
        gy = np.arange(np.floor(y0 / unit_m), np.ceil(y1 / unit_m) + 1) * unit_m
        if len(gx) * len(gy) <= 10000:
            X, Y = np.meshgrid(gx, gy)
            xy_m = np.column_stack([X.ravel(), Y.ravel()])
    if xy_m is not None and len(xy_m):
        ax.scatter(
            xy_m[:, 0],
            xy_m[:, 1],
            marker="s",
            s=14,
            facecolors="none",
            edgecolors="#bbbbbb",
            linewidths=0.6,
            label="floor codes",
            zorder=0,
        )


def _draw_series(
    ax, name: str, x: np.ndarray, y: np.ndarray, raw: bool, label=True, decimate: bool = True
) -> None:
    """Raw estimators as dots, fused as lines; long series min/max-decimated on `y`."""
    if decimate:
        i = decimate_minmax(y)
        x, y = x[i], y[i]
    c = estimator_colour(name)
    lab = name if label else None
    if raw:
        ax.plot(x, y, ".", ms=2.0, color=c, label=lab, alpha=0.8)
    else:
        ax.plot(x, y, "-", lw=1.0, color=c, label=lab)


def _draw_band(ax, name: str, t: np.ndarray, half_width: np.ndarray, label: str | None) -> None:
    """±half_width band around zero; on long series the per-bin maximum (conservative)."""
    n = len(t)
    if n > MAX_DRAWN_POINTS:
        k = -(-n // (MAX_DRAWN_POINTS // 2))
        n_bins = -(-n // k)
        padded = np.full(n_bins * k, np.nan)
        padded[:n] = half_width
        half_width = np.nanmax(padded.reshape(n_bins, k), axis=1)
        t = t[::k]
    ax.fill_between(t, -half_width, half_width, color=estimator_colour(name), alpha=0.15, lw=0, label=label)


def _shade_blackouts(ax, blackouts, t0_ns: int, label: bool, annotate: bool = False) -> None:
    for k, (a, b, _kind) in enumerate(blackouts or ()):
        x0, x1 = (a - t0_ns) * 1e-9, (b - t0_ns) * 1e-9
        ax.axvspan(
            x0,
            x1,
            color="#888888",
            alpha=0.18,
            lw=0,
            label="floor-code blackout" if (label and k == 0) else None,
        )
        if annotate:
            ax.annotate(
                f"{x1 - x0:g} s",
                ((x0 + x1) / 2, 1.0),
                xycoords=("data", "axes fraction"),
                xytext=(0, 2),
                textcoords="offset points",
                ha="center",
                va="bottom",
                fontsize=7,
                color="#555555",
            )


def _log_y(ax, minor: bool = True) -> None:
    """Log y-axis with unlabelled minor ticks (labelling them costs most of a figure's time;
    `minor=False`: none, for many small panels)."""
    ax.set_yscale("log")
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.grid(True, which="major", lw=0.4, alpha=0.6)
    if minor:
        ax.grid(True, which="minor", lw=0.2, alpha=0.3)
    else:
        ax.yaxis.set_minor_locator(NullLocator())


def _legend(fig, ax_or_axes, **kw) -> None:
    axes = ax_or_axes if isinstance(ax_or_axes, (list, tuple, np.ndarray)) else [ax_or_axes]
    seen, handles, labels = set(), [], []
    for ax in np.ravel(axes):
        for h, l in zip(*ax.get_legend_handles_labels()):
            if l not in seen:
                seen.add(l)
                handles.append(h)
                labels.append(l)
    if handles:
        fig.legend(handles, labels, loc="outside right upper", frameon=False, **kw)


# ============================================================================ trajectories


def plot_trajectories(
    path: Path,
    trajectories: dict[str, Trajectory],
    gt=None,
    *,
    floor_codes_xy_m: np.ndarray | None = None,
    payload_unit_m: float | None = 1.0,
    raw_names: Iterable[str] = RAW_ESTIMATORS,
    dpi: int = DEFAULT_DPI,
) -> Path:
    """Top view (x-y) and side view (x-z) of truth, raw and fused trajectories (the paper's
    Fig. 32), floor codes shown faintly."""
    raw_names = set(raw_names)
    fig = Figure(figsize=(11, 5.2), layout="constrained")
    ax_top, ax_side = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.0, 1.2]})
    pts = [t.positions_xyz for t in trajectories.values() if len(t)]
    if gt is not None:
        pts.append(np.asarray(gt.p_world))
    allp = np.vstack(pts) if pts else np.zeros((1, 3))
    extent = (allp[:, 0].min(), allp[:, 0].max(), allp[:, 1].min(), allp[:, 1].max())
    _floor_grid(ax_top, floor_codes_xy_m, extent, payload_unit_m)
    if gt is not None:
        _, p = _gt_xyz(gt)
        p = p[_stride(len(p), 4 * MAX_DRAWN_POINTS)]
        ax_top.plot(p[:, 0], p[:, 1], "-", lw=2.2, color=TRUTH_COLOUR, alpha=0.45, label="truth")
        ax_side.plot(p[:, 0], p[:, 2], "-", lw=2.2, color=TRUTH_COLOUR, alpha=0.45, label="truth")
    for name, traj in trajectories.items():
        if not len(traj):
            continue
        p = traj.positions_xyz
        p = p[_stride(len(p), 4 * MAX_DRAWN_POINTS)]
        raw = name in raw_names
        _draw_series(ax_top, name, p[:, 0], p[:, 1], raw, decimate=False)
        _draw_series(ax_side, name, p[:, 0], p[:, 2], raw, decimate=False)
    ax_side.axhline(0.0, color="#bbbbbb", lw=0.8, zorder=0)
    ax_top.set(title="Top view", xlabel="x [m]", ylabel="y [m]")
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_side.set(title="Side view", xlabel="x [m]", ylabel="z (height) [m]")
    for ax in (ax_top, ax_side):
        ax.grid(True, lw=0.3, alpha=0.5)
    _legend(fig, ax_top, markerscale=4)
    return _save(fig, path, dpi)


# ============================================================================ errors over time


def plot_error_overview(
    path: Path,
    trajectories: dict[str, Trajectory],
    gt,
    blackouts: list[tuple[int, int, str]] | None = None,
    *,
    raw_names: Iterable[str] = RAW_ESTIMATORS,
    associations: dict[str, Association] | None = None,
    dpi: int = DEFAULT_DPI,
) -> Path:
    """Raw vs fused at a glance: |position error| (cm) and |yaw error| (deg) over time on log
    axes, every estimator, floor-code blackouts shaded and labelled with their durations."""
    raw_names = set(raw_names)
    assoc = associations if associations is not None else associate_all(trajectories, gt)
    t0 = time_origin_ns(gt, trajectories)
    fig = Figure(figsize=(11, 5.6), layout="constrained")
    ax_p, ax_y = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [1.6, 1.0]})
    drawn: list[list[np.ndarray]] = [[], []]
    for name, a in assoc.items():
        ts = (a.timestamps_ns - t0) * 1e-9
        e_cm = np.maximum(100.0 * np.linalg.norm(a.position_errors_m, axis=1), LOG_FLOOR)
        e_deg = np.maximum(np.degrees(np.abs(a.yaw_errors_rad)), LOG_FLOOR)
        _draw_series(ax_p, name, ts, e_cm, name in raw_names)
        _draw_series(ax_y, name, ts, e_deg, name in raw_names, label=False)
        drawn[0].append(e_cm)
        drawn[1].append(e_deg)
    for k, ax in enumerate((ax_p, ax_y)):
        if drawn[k]:  # the lowest 1 % is numerical noise: not worth the decades
            v = np.concatenate(drawn[k])
            ax.set_ylim(bottom=max(LOG_FLOOR, 0.5 * float(np.percentile(v, 1.0))))
        _shade_blackouts(ax, blackouts, t0, label=(k == 0), annotate=(k == 0))
        _log_y(ax)
    ax_p.set_ylabel("|position error| [cm]")
    ax_y.set_ylabel("|yaw error| [deg]")
    ax_y.set_xlabel("time since start [s]")
    ax_p.set_title("Raw vs fused: error norm over time (log scale)", pad=12)
    _legend(fig, ax_p, markerscale=4)
    return _save(fig, path, dpi)


def _robust_limit(values: list[np.ndarray], percentile: float, floor: float) -> float:
    v = np.concatenate([np.abs(x[np.isfinite(x)]) for x in values]) if values else np.zeros(0)
    return max(float(np.percentile(v, percentile)) if len(v) else floor, floor)


def zoom_limits_cm(
    errors_cm: list[np.ndarray],
    two_sigmas_cm: list[np.ndarray],
    percentile: float = 99.5,
    sigma_percentile: float = 95.0,
    margin: float = 1.3,
    floor_cm: float = 1e-3,
) -> np.ndarray:
    """(3,) symmetric y-limits (cm) per axis for the zoomed error plot: `margin` x the larger of
    the `percentile` of |error| and the `sigma_percentile` of 2σ over the given (N_i, 3) arrays."""
    return np.array(
        [
            margin
            * max(
                _robust_limit([e[:, k] for e in errors_cm], percentile, floor_cm),
                _robust_limit([s[:, k] for s in two_sigmas_cm], sigma_percentile, floor_cm),
            )
            for k in range(3)
        ]
    )


def plot_position_errors_zoom(
    path: Path,
    trajectories: dict[str, Trajectory],
    gt,
    blackouts: list[tuple[int, int, str]] | None = None,
    *,
    exclude: Iterable[str] = ZOOM_EXCLUDE,
    raw_names: Iterable[str] = RAW_ESTIMATORS,
    associations: dict[str, Association] | None = None,
    percentile: float = 99.5,
    sigma_percentile: float = 95.0,
    dpi: int = DEFAULT_DPI,
) -> Path | None:
    """Per-axis position error (est - truth, cm) of the estimators not in `exclude` (PnP and the
    fused ones) with their ±2σ bands (world axes), blackouts shaded.  Each axis' y-range is
    `zoom_limits_cm`: 1.3 x the larger of the `percentile` of |error| and the `sigma_percentile`
    of 2σ over those estimators, so a few spikes or a briefly huge σ do not flatten the rest;
    samples beyond it are counted in the panel.
    Returns None when no estimator is left to draw."""
    raw_names, exclude = set(raw_names), set(exclude)
    assoc = associations if associations is not None else associate_all(trajectories, gt)
    assoc = {n: a for n, a in assoc.items() if n not in exclude}
    if not assoc:
        return None
    t0 = time_origin_ns(gt, trajectories)
    fig = Figure(figsize=(11, 7.2), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    errs = {n: 100.0 * a.position_errors_m for n, a in assoc.items()}
    sigmas = {n: _world_sigma_cm(a) for n, a in assoc.items()}
    for name, a in assoc.items():
        ts = (a.timestamps_ns - t0) * 1e-9
        s = sigmas[name]
        for k in range(3):
            if s is not None:
                _draw_band(axes[k], name, ts, 2.0 * s[:, k], f"{name} ±2σ" if k == 0 else None)
            _draw_series(axes[k], name, ts, errs[name][:, k], name in raw_names, label=(k == 0))
    lims = zoom_limits_cm(
        list(errs.values()), [2 * s for s in sigmas.values() if s is not None], percentile, sigma_percentile
    )
    for k, ax in enumerate(axes):
        lim = lims[k]
        n_out = sum(int(np.sum(np.abs(e[:, k]) > lim)) for e in errs.values())
        ax.set_ylim(-lim, lim)
        if n_out:
            ax.text(
                0.995,
                0.03,
                f"{n_out} sample(s) beyond ±{lim:.2g} cm",
                transform=ax.transAxes,
                ha="right",
                va="bottom",
                fontsize=7,
                color="#555555",
                bbox=dict(fc="white", ec="none", alpha=0.8, pad=1.0),
            )
        _shade_blackouts(ax, blackouts, t0, label=(k == 0), annotate=(k == 0))
        ax.axhline(0.0, color="#888888", lw=0.6)
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.set_ylabel(f"{'xyz'[k]} error [cm]")
    axes[-1].set_xlabel("time since start [s]")
    left_out = ", ".join(sorted(exclude & set(trajectories)))
    axes[0].set_title(
        "Position error (estimate − truth) with ±2σ"
        + (f"; {left_out} left out (see the overview)" if left_out else ""),
        pad=12,
    )
    _legend(fig, axes[0], markerscale=4)
    return _save(fig, path, dpi)


def plot_position_sigma(
    path: Path,
    trajectories: dict[str, Trajectory],
    *,
    raw_names: Iterable[str] = RAW_ESTIMATORS,
    dpi: int = DEFAULT_DPI,
) -> Path | None:
    """Without ground truth, what the estimators claim: 3D position 1σ (cm, sqrt of the trace
    of the translation covariance) over time on a log axis, one colour per estimator, and a
    rug of the raw estimators' poses (their gaps are where the floor codes were unreadable).
    Returns None when no trajectory has covariances."""
    raw_names = set(raw_names)
    with_cov = {n: t for n, t in trajectories.items() if len(t) and t.covariances is not None}
    if not with_cov:
        return None
    t0 = time_origin_ns(None, trajectories)
    fig = Figure(figsize=(11, 4.6), layout="constrained")
    ax, ax_rug = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [4.0, 1.0]})
    for name, traj in with_cov.items():
        ts = (np.asarray(traj.timestamps_ns, dtype=np.int64) - t0) * 1e-9
        tr = np.trace(np.asarray(traj.covariances)[:, 3:, 3:], axis1=1, axis2=2)
        sig_cm = np.maximum(100.0 * np.sqrt(np.clip(tr, 0, None)), LOG_FLOOR)
        _draw_series(ax, name, ts, sig_cm, name in raw_names)
    raw = [n for n in trajectories if n in raw_names and len(trajectories[n])]
    for i, name in enumerate(raw):
        ts = (np.asarray(trajectories[name].timestamps_ns, dtype=np.int64) - t0) * 1e-9
        ts = ts[_stride(len(ts), 4 * MAX_DRAWN_POINTS)]
        ax_rug.plot(ts, np.full(len(ts), i), "|", ms=6, color=estimator_colour(name))
    ax_rug.set_yticks(range(len(raw)), raw, fontsize=8)
    ax_rug.set_ylim(-0.7, len(raw) - 0.3)
    ax_rug.set_xlabel("time since start [s]")
    ax_rug.set_title("raw poses (gaps: no floor code read)", fontsize=8, loc="left")
    _log_y(ax)
    ax.set_ylabel("position 1σ (3D) [cm]")
    ax.set_title("Claimed position uncertainty over time (no ground truth: no errors)")
    _legend(fig, ax, markerscale=4)
    return _save(fig, path, dpi)


# ============================================================================ box plots


def _boxes(ax, names: list[str], vals: list[np.ndarray], title: str, reference: float | None) -> None:
    if vals:
        vals = [np.maximum(v, LOG_FLOOR) for v in vals]
        bp = ax.boxplot(
            vals,
            patch_artist=True,
            widths=0.6,
            whis=(5, 95),
            showfliers=False,
            medianprops=dict(color="black", lw=1.2),
        )
        for i, (patch, name) in enumerate(zip(bp["boxes"], names)):
            patch.set_facecolor(estimator_colour(name))
            patch.set_alpha(0.6)
            ax.plot(
                i + 1,
                vals[i].max(),
                ls="none",
                marker="x",
                ms=4,
                color="#333333",
                label="maximum" if i == 0 else None,
            )
        ax.set_xticks(range(1, len(names) + 1), names, rotation=40, ha="right", fontsize=8)
    if reference is not None:
        ax.axhline(reference, color="#d55e00", ls="--", lw=0.9, label="paper's simulator MAE")
    _log_y(ax, minor=False)
    ax.grid(False, axis="x", which="both")
    ax.set_title(title, fontsize=10)


def plot_error_boxplots(
    path: Path,
    trajectories: dict[str, Trajectory],
    gt,
    *,
    load_maps: dict[str, LoadMap] | None = None,
    loads_gt: dict[str, np.ndarray] | None = None,
    associations: dict[str, Association] | None = None,
    dpi: int = DEFAULT_DPI,
) -> Path:
    """Box plots of |error| per axis (cm) and |yaw error| (deg) per estimator (the paper's
    Fig. 31), and when a load truth is given |load error| per axis over the loads (Fig. 34).
    Log axes (raw and fused differ by orders of magnitude); boxes are the quartiles, whiskers
    the 5th-95th percentiles, x the maximum; the paper's reported simulator MAE is dashed."""
    assoc = associations if associations is not None else associate_all(trajectories, gt)
    names = list(assoc)
    data = [
        (100.0 * np.abs(a.position_errors_m), np.degrees(np.abs(a.yaw_errors_rad))) for a in assoc.values()
    ]
    load_names, load_errs = [], []
    for name, lm in (load_maps or {}).items():
        e = [
            100.0 * np.abs(np.asarray(l.p_world, float) - np.asarray(loads_gt[l.load_id], float))
            for l in lm.loads
            if loads_gt and l.load_id in loads_gt
        ]
        if e:
            load_names.append(name)
            load_errs.append(np.array(e))
    rows = 2 if load_names else 1
    fig = Figure(figsize=(11, 3.9 * rows), layout="constrained")
    axes = np.atleast_2d(fig.subplots(rows, 4))
    ref = [PAPER_SIM_LOCALIZATION_MAE_CM[a] for a in "xyz"] + [PAPER_SIM_YAW_MAE_DEG]
    titles = ("|x error| [cm]", "|y error| [cm]", "|z error| [cm]", "|yaw error| [deg]")
    for k, ax in enumerate(axes[0]):
        vals = [d[0][:, k] if k < 3 else d[1] for d in data]
        _boxes(ax, names, vals, "Drone " + titles[k], ref[k])
    axes[0, 0].set_ylabel("absolute error (log scale)")
    if load_names:
        for k in range(3):
            _boxes(
                axes[1, k],
                load_names,
                [e[:, k] for e in load_errs],
                "Load " + titles[k] + " over loads",
                PAPER_SIM_LOADMAP_MAE_CM["xyz"[k]],
            )
        axes[1, 0].set_ylabel("absolute error (log scale)")
        n = {name: len(e) for name, e in zip(load_names, load_errs)}
        axes[1, 3].axis("off")
        axes[1, 3].text(
            0.0,
            0.9,
            "loads mapped (with truth):\n" + "\n".join(f"  {k}: {v}" for k, v in n.items()),
            va="top",
            fontsize=9,
            transform=axes[1, 3].transAxes,
        )
    _legend(fig, axes[0, 0])
    return _save(fig, path, dpi)


# ============================================================================ load map


def _ellipse(ax, centre_xy, cov_xy, colour, n_sigma: float = 2.0) -> None:
    w, V = np.linalg.eigh(np.asarray(cov_xy, dtype=float))
    w = np.clip(w, 0, None)
    angle = np.degrees(np.arctan2(V[1, 1], V[0, 1]))
    ax.add_patch(
        Ellipse(
            centre_xy,
            2 * n_sigma * np.sqrt(w[1]),
            2 * n_sigma * np.sqrt(w[0]),
            angle=angle,
            fill=False,
            ec=colour,
            lw=0.9,
        )
    )


def _seen_ids(load_maps: dict[str, LoadMap]) -> set[str]:
    return {l.load_id for lm in load_maps.values() for l in lm.loads}


def _stack_labels(ids: list[str], xy: np.ndarray, tol_m: float = 0.05) -> list[tuple[str, np.ndarray]]:
    """One label per group of loads at the same (x, y) (a rack column): the ids' common prefix
    followed by '*' when they differ."""
    out, used = [], np.zeros(len(ids), dtype=bool)
    for i in range(len(ids)):
        if used[i]:
            continue
        grp = np.flatnonzero(~used & (np.linalg.norm(xy - xy[i], axis=1) < tol_m))
        used[grp] = True
        names = [ids[j] for j in grp]
        pre = os.path.commonprefix(names)
        label = (
            names[0]
            if len(names) == 1
            else (pre.rstrip("-_ ") + "-*" if len(pre) >= 2 else f"{names[0]} (+{len(names) - 1})")
        )
        out.append((label, xy[i]))
    return out


def plot_load_map(
    path: Path,
    load_maps: dict[str, LoadMap],
    loads_gt: dict[str, np.ndarray] | None = None,
    gt=None,
    *,
    dpi: int = DEFAULT_DPI,
) -> Path:
    """Where the loads are (orientation; accuracy is `plot_load_errors`): top view (estimates
    with 2σ ellipses, truth, flight path faint, rack columns labelled) and the height of every
    load id.  True loads that no estimator mapped are drawn hollow and grey ("not seen")."""
    fig = Figure(figsize=(11, 5.2), layout="constrained")
    ax_top, ax_h = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.0, 1.2]})
    if gt is not None:
        p = np.asarray(gt.p_world)
        p = p[_stride(len(p), 4 * MAX_DRAWN_POINTS)]
        ax_top.plot(p[:, 0], p[:, 1], "-", lw=0.8, color=TRUTH_COLOUR, alpha=0.2, label="flight (truth)")
    seen = _seen_ids(load_maps)
    ids = sorted(set(loads_gt or {}) | seen)
    pos = {lid: i for i, lid in enumerate(ids)}
    if loads_gt:
        gids = sorted(loads_gt)
        g = np.array([loads_gt[i] for i in gids], dtype=float).reshape(-1, 3)
        is_seen = np.array([i in seen for i in gids])
        for mask, kw in (
            (is_seen, dict(marker="x", color=TRUTH_COLOUR, label="truth")),
            (
                ~is_seen,
                dict(
                    marker="o",
                    facecolors="none",
                    edgecolors=UNSEEN_COLOUR,
                    label="truth, not seen by any estimator",
                ),
            ),
        ):
            if mask.any():
                ax_top.scatter(g[mask, 0], g[mask, 1], s=40, zorder=3, **kw)
                ax_h.scatter([pos[i] for i in np.array(gids)[mask]], g[mask, 2], s=40, zorder=3, **kw)
        for label, xy in _stack_labels(gids, g[:, :2]):
            ax_top.annotate(label, xy, xytext=(4, 4), textcoords="offset points", fontsize=7, color="#444444")
    n_maps = max(len(load_maps), 1)
    for m, (name, lm) in enumerate(load_maps.items()):
        c = estimator_colour(name)
        if not lm.loads:
            continue
        P = np.array([l.p_world for l in lm.loads], dtype=float).reshape(-1, 3)
        ax_top.scatter(P[:, 0], P[:, 1], s=14, color=c, label=name, zorder=4)
        dx = (m - (n_maps - 1) / 2) * 0.12  # side by side per estimator
        xs = np.array([pos[l.load_id] for l in lm.loads]) + dx
        err = [2 * np.sqrt(max(l.cov_world[2, 2], 0)) if l.cov_world is not None else 0.0 for l in lm.loads]
        ax_h.errorbar(xs, P[:, 2], yerr=err, fmt="o", ms=3.5, color=c, capsize=2, lw=0.9, label=name)
        for l in lm.loads:
            if l.cov_world is not None:
                _ellipse(ax_top, l.p_world[:2], np.asarray(l.cov_world)[:2, :2], c)
    ax_top.set(title="Load map, top view (2σ ellipses)", xlabel="x [m]", ylabel="y [m]")
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_h.set(title="Load height per id (±2σ)", ylabel="z [m]")
    ax_h.set_xticks(
        range(len(ids)),
        ids,
        rotation=60 if len(ids) > 6 else 0,
        ha="right" if len(ids) > 6 else "center",
        fontsize=7 if len(ids) > 12 else 9,
    )
    for tick, lid in zip(ax_h.get_xticklabels(), ids):
        if loads_gt and lid not in seen:
            tick.set_color(UNSEEN_COLOUR)
    ax_h.set_xlabel("load id (grey: not seen)")
    for ax in (ax_top, ax_h):
        ax.grid(True, lw=0.3, alpha=0.5)
    _legend(fig, [ax_top, ax_h])
    return _save(fig, path, dpi)


def load_rows(
    load_maps: dict[str, LoadMap], loads_gt: dict[str, np.ndarray], max_unseen_rows: int = 40
) -> tuple[list[str], int]:
    """Row labels of the per-load error plot and how many of them (the first) were mapped by
    some estimator; the true loads nobody mapped follow, or one "<n> loads not seen" row when
    there are more than `max_unseen_rows`.  Mapped ids that are not in the truth are left out."""
    seen = sorted(_seen_ids(load_maps) & set(loads_gt))
    unseen = sorted(set(loads_gt) - set(seen))
    rows = seen + (unseen if len(unseen) <= max_unseen_rows else [f"{len(unseen)} loads not seen"])
    return rows, len(seen)


def plot_load_errors(
    path: Path,
    load_maps: dict[str, LoadMap],
    loads_gt: dict[str, np.ndarray],
    *,
    exclude: Iterable[str] = ZOOM_EXCLUDE,
    max_unseen_rows: int = 40,
    dpi: int = DEFAULT_DPI,
) -> Path | None:
    """Per-load error (estimate − truth, cm) per axis and estimator, ±2σ bars where the map has
    a covariance (a forest plot: one row per load id).  Two groups of columns x / y / z: the
    estimators in `exclude` (the paper's, cm to tens of cm) and the others (PnP and fused,
    sub-mm to mm), each group on its own scale.  True loads seen by no estimator are listed last
    on grey rows marked "not seen" (more than `max_unseen_rows` of them: one row with their
    count).  Returns None without a load truth."""
    if not loads_gt:
        return None
    rows, n_seen = load_rows(load_maps, loads_gt, max_unseen_rows)
    seen = rows[:n_seen]
    y_of = {lid: i for i, lid in enumerate(rows)}
    exclude = set(exclude)
    groups = [
        g for g in ([n for n in load_maps if n in exclude], [n for n in load_maps if n not in exclude]) if g
    ] or [[]]
    n_rows = len(rows)
    fig = Figure(figsize=(11, min(2.0 + 0.26 * n_rows, 40.0)), layout="constrained")
    axes = fig.subplots(1, 3 * len(groups), sharey=True, squeeze=False)[0]
    for g, names in enumerate(groups):
        offsets = (np.arange(len(names)) - (len(names) - 1) / 2) * min(0.6 / max(len(names), 1), 0.18)
        for m, name in enumerate(names):
            ls = [l for l in load_maps[name].loads if l.load_id in loads_gt]
            if not ls:
                continue
            E = 100.0 * np.array([np.asarray(l.p_world, float) - loads_gt[l.load_id] for l in ls])
            S = np.array(
                [
                    2 * 100.0 * np.sqrt(np.clip(np.diag(l.cov_world), 0, None))
                    if l.cov_world is not None
                    else np.full(3, np.nan)
                    for l in ls
                ]
            )
            ys = np.array([y_of[l.load_id] for l in ls]) + offsets[m]
            for k in range(3):
                ax = axes[3 * g + k]
                has = np.isfinite(S[:, k])
                c = estimator_colour(name)
                if has.any():
                    ax.errorbar(
                        E[has, k],
                        ys[has],
                        xerr=S[has, k],
                        fmt="o",
                        ms=3.2,
                        color=c,
                        capsize=1.5,
                        lw=0.8,
                        label=f"{name} ±2σ",
                    )
                if (~has).any():
                    ax.plot(E[~has, k], ys[~has], "o", ms=3.2, color=c, label=f"{name} (no σ)")
        for k in range(3):
            ax = axes[3 * g + k]
            ax.axvline(0.0, color="#888888", lw=0.6)
            ax.grid(True, axis="x", lw=0.3, alpha=0.5)
            ax.set_xlabel(f"{'xyz'[k]} error [cm]")
            ax.set_title((" + ".join(names) if k == 1 else ""), fontsize=9)
            for i in range(len(seen), n_rows):
                ax.axhspan(i - 0.45, i + 0.45, color=UNSEEN_COLOUR, alpha=0.25, lw=0)
                if k == 1:
                    ax.annotate(
                        "not seen",
                        (0.5, i),
                        xycoords=("axes fraction", "data"),
                        ha="center",
                        va="center",
                        fontsize=7,
                        color="#666666",
                    )
            ax.tick_params(axis="x", labelsize=8)
    axes[0].set_yticks(range(n_rows), rows, fontsize=8)
    for tick, lid in zip(axes[0].get_yticklabels(), rows):
        if lid not in seen:
            tick.set_color("#888888")
    axes[0].set_ylim(n_rows - 0.5, -0.5)  # first id on top
    axes[0].set_ylabel("load id")
    fig.suptitle(
        "Load map error per load (estimate − truth); each group of columns on its own scale", fontsize=10
    )
    _legend(fig, axes)
    return _save(fig, path, dpi)


# ============================================================================ all


def plot_all(
    out_dir: Path,
    trajectories: dict[str, Trajectory],
    load_maps: dict[str, LoadMap],
    gt=None,
    loads_gt: dict[str, np.ndarray] | None = None,
    blackouts: list[tuple[int, int, str]] | None = None,
    *,
    floor_codes_xy_m: np.ndarray | None = None,
    payload_unit_m: float | None = 1.0,
    dpi: int = DEFAULT_DPI,
) -> dict[str, Path]:
    """Every plot that the inputs allow; returns {plot name: PNG path}, names as in the files:
    trajectories, position_errors (raw vs fused overview, log), position_errors_zoom (PnP and
    fused per axis ±2σ), error_boxplots, load_map, load_errors; without ground truth
    position_sigma instead of the error plots."""
    with _heap_frozen():
        out_dir = Path(out_dir)
        paths = {
            "trajectories": _freed(
                plot_trajectories(
                    out_dir / "trajectories.png",
                    trajectories,
                    gt,
                    floor_codes_xy_m=floor_codes_xy_m,
                    payload_unit_m=payload_unit_m,
                    dpi=dpi,
                )
            )
        }
        assoc = associate_all(trajectories, gt) if gt is not None else {}
        if not assoc:
            sig = _freed(plot_position_sigma(out_dir / "position_sigma.png", trajectories, dpi=dpi))
            if sig is not None:
                paths["position_sigma"] = sig
        if assoc:
            paths["position_errors"] = _freed(
                plot_error_overview(
                    out_dir / "position_errors.png", trajectories, gt, blackouts, associations=assoc, dpi=dpi
                )
            )
            zoom = _freed(
                plot_position_errors_zoom(
                    out_dir / "position_errors_zoom.png",
                    trajectories,
                    gt,
                    blackouts,
                    associations=assoc,
                    dpi=dpi,
                )
            )
            if zoom is not None:
                paths["position_errors_zoom"] = zoom
            paths["error_boxplots"] = _freed(
                plot_error_boxplots(
                    out_dir / "error_boxplots.png",
                    trajectories,
                    gt,
                    load_maps=load_maps,
                    loads_gt=loads_gt,
                    associations=assoc,
                    dpi=dpi,
                )
            )
        if any(lm.loads for lm in load_maps.values()) or loads_gt:
            paths["load_map"] = _freed(
                plot_load_map(out_dir / "load_map.png", load_maps, loads_gt, gt, dpi=dpi)
            )
            if loads_gt:
                p = plot_load_errors(out_dir / "load_errors.png", load_maps, loads_gt, dpi=dpi)
                if p is not None:
                    paths["load_errors"] = p
        return paths


__all__ = [
    "estimator_colour",
    "decimate_minmax",
    "associate_all",
    "time_origin_ns",
    "plot_trajectories",
    "plot_error_overview",
    "plot_position_errors_zoom",
    "plot_position_sigma",
    "plot_error_boxplots",
    "plot_load_map",
    "plot_load_errors",
    "plot_all",
    "zoom_limits_cm",
    "load_rows",
    "ZOOM_EXCLUDE",
]


# ============================================================================ as-built floor codes

FLOOR_OFFSET_ARROW_SCALE = 20.0
"""Offset arrows of plot_floor_code_offsets are drawn this many times their length."""
MISPLACED_COLOUR = "#d62728"


def plot_floor_code_offsets(
    path: Path,
    nominal_xy_m: np.ndarray,
    offsets_xy_m: np.ndarray,
    misplaced: np.ndarray,
    true_offsets_xy_m: np.ndarray | None = None,
    *,
    dpi: int = DEFAULT_DPI,
) -> Path:
    """Top view of the as-built floor codes (fusion.estimate.asbuilt): an arrow from each code's
    nominal centre along its estimated offset, FLOOR_OFFSET_ARROW_SCALE times longer; misplaced
    codes red; the true offsets (simulated floors) as grey arrows.  (N, 2) m arrays, misplaced
    (N,) bool."""
    xy = np.asarray(nominal_xy_m, float).reshape(-1, 2)
    off = np.asarray(offsets_xy_m, float).reshape(-1, 2)
    bad = np.asarray(misplaced, bool).reshape(-1)
    k = FLOOR_OFFSET_ARROW_SCALE
    fig = Figure(figsize=(9, 6), layout="constrained")
    ax = fig.subplots()
    ax.scatter(xy[:, 0], xy[:, 1], marker="s", s=14, color="#bbbbbb", label="nominal (payload)", zorder=1)
    if true_offsets_xy_m is not None:
        t = np.asarray(true_offsets_xy_m, float).reshape(-1, 2)
        ax.quiver(
            xy[:, 0],
            xy[:, 1],
            k * t[:, 0],
            k * t[:, 1],
            angles="xy",
            scale_units="xy",
            scale=1,
            color=TRUTH_COLOUR,
            alpha=0.35,
            width=0.004,
            label="true offset",
            zorder=2,
        )
    for mask, colour, label in ((~bad, "#1f77b4", "estimated offset"), (bad, MISPLACED_COLOUR, "misplaced")):
        if mask.any():
            ax.quiver(
                xy[mask, 0],
                xy[mask, 1],
                k * off[mask, 0],
                k * off[mask, 1],
                angles="xy",
                scale_units="xy",
                scale=1,
                color=colour,
                width=0.004,
                label=label,
                zorder=3,
            )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"As-built floor codes: offsets from nominal (arrows ×{k:g}; 1 cm = {k / 100:g} m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return _save(fig, path, dpi)
