"""PNG plots of trajectories, errors and load maps (matplotlib, Agg canvas, never interactive).

Figures are built with `matplotlib.figure.Figure` (no pyplot state), saved atomically.  Each
estimator keeps its colour in every plot (`estimator_colour`); raw per-frame estimators are drawn
as dots (they have gaps), fused ones as lines.  Units: m, cm and degrees as labelled.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import matplotlib

matplotlib.use("Agg")  # never open a window, whatever the environment says
import numpy as np  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402

from fusion.evaluate.metrics import associate  # noqa: E402
from fusion.fileio import atomic_open  # noqa: E402
from fusion.types import LoadMap, Trajectory  # noqa: E402

DEFAULT_DPI = 130
TRUTH_COLOUR = "#222222"
RAW_ESTIMATORS = ("paper", "pnp")
_COLOURS = {"paper": "#e69f00", "pnp": "#0072b2", "smoother": "#009e73",
            "incremental": "#56b4e9", "ekf": "#cc79a7"}
_EXTRA = ("#d55e00", "#8c564b", "#999999", "#f0e442", "#17becf")


def estimator_colour(name: str) -> str:
    """Fixed colour per estimator (Okabe-Ito palette, colour-blind safe)."""
    if name in _COLOURS:
        return _COLOURS[name]
    return _EXTRA[sum(map(ord, name)) % len(_EXTRA)]


def _save(fig: Figure, path: Path, dpi: int) -> Path:
    FigureCanvasAgg(fig)
    path = Path(path)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=dpi)
    return path


def _gt_xyz(gt) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(gt.timestamps_ns, dtype=np.int64), np.asarray(gt.p_world, dtype=float)


def _t0(gt, trajectories: dict[str, Trajectory]) -> int:
    starts = [int(t.timestamps_ns[0]) for t in trajectories.values() if len(t)]
    if gt is not None and len(gt.timestamps_ns):
        starts.append(int(gt.timestamps_ns[0]))
    return min(starts) if starts else 0


def _floor_grid(ax, xy_m: np.ndarray | None, extent: tuple[float, float, float, float] | None,
                unit_m: float | None) -> None:
    """Faint floor-code markers: the given centres, else grid points at multiples of `unit_m`."""
    if xy_m is None and unit_m and extent is not None:
        x0, x1, y0, y1 = extent
        gx = np.arange(np.floor(x0 / unit_m), np.ceil(x1 / unit_m) + 1) * unit_m
        gy = np.arange(np.floor(y0 / unit_m), np.ceil(y1 / unit_m) + 1) * unit_m
        if len(gx) * len(gy) <= 10000:
            X, Y = np.meshgrid(gx, gy)
            xy_m = np.column_stack([X.ravel(), Y.ravel()])
    if xy_m is not None and len(xy_m):
        ax.scatter(xy_m[:, 0], xy_m[:, 1], marker="s", s=14, facecolors="none",
                   edgecolors="#bbbbbb", linewidths=0.6, label="floor codes", zorder=0)


def _draw_path(ax, name: str, x: np.ndarray, y: np.ndarray, raw: bool) -> None:
    c = estimator_colour(name)
    if raw:
        ax.plot(x, y, ".", ms=2.0, color=c, label=name, alpha=0.8)
    else:
        ax.plot(x, y, "-", lw=1.1, color=c, label=name)


def plot_trajectories(path: Path, trajectories: dict[str, Trajectory], gt=None, *,
                      floor_codes_xy_m: np.ndarray | None = None,
                      payload_unit_m: float | None = 1.0,
                      raw_names: Iterable[str] = RAW_ESTIMATORS, dpi: int = DEFAULT_DPI) -> Path:
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
        ax_top.plot(p[:, 0], p[:, 1], "-", lw=2.2, color=TRUTH_COLOUR, alpha=0.45, label="truth")
        ax_side.plot(p[:, 0], p[:, 2], "-", lw=2.2, color=TRUTH_COLOUR, alpha=0.45, label="truth")
    for name, traj in trajectories.items():
        if not len(traj):
            continue
        p = traj.positions_xyz
        _draw_path(ax_top, name, p[:, 0], p[:, 1], name in raw_names)
        _draw_path(ax_side, name, p[:, 0], p[:, 2], name in raw_names)
    ax_side.axhline(0.0, color="#bbbbbb", lw=0.8, zorder=0)
    ax_top.set(title="Top view", xlabel="x [m]", ylabel="y [m]")
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_side.set(title="Side view", xlabel="x [m]", ylabel="z (height) [m]")
    for ax in (ax_top, ax_side):
        ax.grid(True, lw=0.3, alpha=0.5)
    handles, labels = ax_top.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right upper", markerscale=4, frameon=False)
    return _save(fig, path, dpi)


def _shade_blackouts(ax, blackouts, t0_ns: int, label: bool) -> None:
    for k, (a, b, _kind) in enumerate(blackouts or ()):
        ax.axvspan((a - t0_ns) * 1e-9, (b - t0_ns) * 1e-9, color="#888888", alpha=0.18, lw=0,
                   label="floor-code blackout" if (label and k == 0) else None)


def plot_position_errors(path: Path, trajectories: dict[str, Trajectory], gt,
                         blackouts: list[tuple[int, int, str]] | None = None, *,
                         raw_names: Iterable[str] = RAW_ESTIMATORS,
                         dpi: int = DEFAULT_DPI) -> Path:
    """Per-axis position error (est - truth, cm) and its norm over time, one colour per estimator,
    +-2 sigma bands from the covariances (world axes: R P_tt R^T), blackouts shaded."""
    raw_names = set(raw_names)
    t0 = _t0(gt, trajectories)
    fig = Figure(figsize=(11, 8), layout="constrained")
    axes = fig.subplots(4, 1, sharex=True)
    t_gt = np.asarray(gt.timestamps_ns, dtype=np.int64)
    T_gt = gt.T_world_body
    for name, traj in trajectories.items():
        a = associate(t_gt, T_gt, traj)
        if not len(a):
            continue
        ts = (a.timestamps_ns - t0) * 1e-9
        e_cm = 100.0 * a.position_errors_m
        c = estimator_colour(name)
        style = dict(ls="none", marker=".", ms=1.8) if name in raw_names else dict(lw=0.9)
        for k in range(3):
            axes[k].plot(ts, e_cm[:, k], color=c, label=name, **style)
        axes[3].plot(ts, np.linalg.norm(e_cm, axis=1), color=c, label=name, **style)
        if a.covariances is not None:
            R = a.T_world_body_est[:, :3, :3]
            P = R @ a.covariances[:, 3:, 3:] @ np.swapaxes(R, 1, 2)
            two_sigma_cm = 200.0 * np.sqrt(np.clip(np.diagonal(P, axis1=1, axis2=2), 0, None))
            for k in range(3):
                axes[k].fill_between(ts, -two_sigma_cm[:, k], two_sigma_cm[:, k], color=c,
                                     alpha=0.15, lw=0, label=f"{name} ±2σ" if k == 0 else None)
    for k, ax in enumerate(axes):
        _shade_blackouts(ax, blackouts, t0, label=(k == 0))
        ax.grid(True, lw=0.3, alpha=0.5)
        if k < 3:
            ax.axhline(0.0, color="#888888", lw=0.6)
            ax.set_ylabel(f"{'xyz'[k]} error [cm]")
    axes[3].set_ylabel("|error| [cm]")
    axes[3].set_xlabel("time since start [s]")
    axes[0].set_title("Position error (estimate − truth)")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right upper", markerscale=4, frameon=False)
    return _save(fig, path, dpi)


def plot_error_boxplots(path: Path, trajectories: dict[str, Trajectory], gt, *,
                        dpi: int = DEFAULT_DPI) -> Path:
    """Box plots of |error| per axis (cm) and of |yaw error| (deg) per estimator (the paper's
    Fig. 31)."""
    t_gt = np.asarray(gt.timestamps_ns, dtype=np.int64)
    T_gt = gt.T_world_body
    names, data = [], []
    for name, traj in trajectories.items():
        a = associate(t_gt, T_gt, traj)
        if len(a):
            names.append(name)
            data.append((100.0 * np.abs(a.position_errors_m), np.degrees(np.abs(a.yaw_errors_rad))))
    fig = Figure(figsize=(11, 3.8), layout="constrained")
    axes = fig.subplots(1, 4)
    titles = ("|x error| [cm]", "|y error| [cm]", "|z error| [cm]", "|yaw error| [deg]")
    for k, ax in enumerate(axes):
        vals = [d[0][:, k] if k < 3 else d[1] for d in data]
        if vals:
            bp = ax.boxplot(vals, patch_artist=True, widths=0.6,
                            medianprops=dict(color="black", lw=1.2),
                            flierprops=dict(marker=".", ms=2, alpha=0.4))
            for patch, name in zip(bp["boxes"], names):
                patch.set_facecolor(estimator_colour(name))
                patch.set_alpha(0.6)
            ax.set_xticks(range(1, len(names) + 1), names, rotation=30)
        ax.set_title(titles[k])
        ax.grid(True, axis="y", lw=0.3, alpha=0.5)
    axes[0].set_ylabel("absolute error")
    return _save(fig, path, dpi)


def _ellipse(ax, centre_xy, cov_xy, colour, n_sigma: float = 2.0) -> None:
    w, V = np.linalg.eigh(np.asarray(cov_xy, dtype=float))
    w = np.clip(w, 0, None)
    angle = np.degrees(np.arctan2(V[1, 1], V[0, 1]))
    ax.add_patch(Ellipse(centre_xy, 2 * n_sigma * np.sqrt(w[1]), 2 * n_sigma * np.sqrt(w[0]),
                         angle=angle, fill=False, ec=colour, lw=0.9))


def plot_load_map(path: Path, load_maps: dict[str, LoadMap],
                  loads_gt: dict[str, np.ndarray] | None = None, gt=None, *,
                  dpi: int = DEFAULT_DPI) -> Path:
    """Load map: top view (estimates with 2σ ellipses vs truth, flight path faint) and a height
    view per load id (estimate ± 2σ vs truth)."""
    fig = Figure(figsize=(11, 5.2), layout="constrained")
    ax_top, ax_h = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.0, 1.2]})
    if gt is not None:
        p = np.asarray(gt.p_world)
        ax_top.plot(p[:, 0], p[:, 1], "-", lw=0.8, color=TRUTH_COLOUR, alpha=0.2,
                    label="flight (truth)")
    ids = sorted(set(loads_gt or {}) | {l.load_id for lm in load_maps.values() for l in lm.loads})
    pos = {lid: i for i, lid in enumerate(ids)}
    if loads_gt:
        g = np.array([loads_gt[i] for i in sorted(loads_gt)]).reshape(-1, 3)
        ax_top.scatter(g[:, 0], g[:, 1], marker="x", s=40, color=TRUTH_COLOUR, label="truth",
                       zorder=3)
        ax_h.scatter([pos[i] for i in sorted(loads_gt)], g[:, 2], marker="x", s=40,
                     color=TRUTH_COLOUR, label="truth", zorder=3)
    n_maps = max(len(load_maps), 1)
    for m, (name, lm) in enumerate(load_maps.items()):
        c = estimator_colour(name)
        if not lm.loads:
            continue
        P = np.array([l.p_world for l in lm.loads]).reshape(-1, 3)
        ax_top.scatter(P[:, 0], P[:, 1], s=14, color=c, label=name, zorder=4)
        dx = (m - (n_maps - 1) / 2) * 0.12           # side by side per estimator
        xs = np.array([pos[l.load_id] for l in lm.loads]) + dx
        err = [2 * np.sqrt(max(l.cov_world[2, 2], 0)) if l.cov_world is not None else 0.0
               for l in lm.loads]
        ax_h.errorbar(xs, P[:, 2], yerr=err, fmt="o", ms=3.5, color=c, capsize=2, lw=0.9,
                      label=name)
        for l in lm.loads:
            if l.cov_world is not None:
                _ellipse(ax_top, l.p_world[:2], np.asarray(l.cov_world)[:2, :2], c)
    ax_top.set(title="Load map, top view (2σ ellipses)", xlabel="x [m]", ylabel="y [m]")
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_h.set(title="Load height (±2σ)", ylabel="z [m]")
    ax_h.set_xticks(range(len(ids)), ids, rotation=45 if len(ids) > 6 else 0, ha="right"
                    if len(ids) > 6 else "center")
    ax_h.set_xlabel("load id")
    for ax in (ax_top, ax_h):
        ax.grid(True, lw=0.3, alpha=0.5)
    handles, labels = ax_top.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right upper", frameon=False)
    return _save(fig, path, dpi)


def plot_all(out_dir: Path, trajectories: dict[str, Trajectory], load_maps: dict[str, LoadMap],
             gt=None, loads_gt: dict[str, np.ndarray] | None = None,
             blackouts: list[tuple[int, int, str]] | None = None, *,
             floor_codes_xy_m: np.ndarray | None = None, payload_unit_m: float | None = 1.0,
             dpi: int = DEFAULT_DPI) -> dict[str, Path]:
    """Every plot that the inputs allow; returns {plot name: PNG path}."""
    out_dir = Path(out_dir)
    paths = {"trajectories": plot_trajectories(
        out_dir / "trajectories.png", trajectories, gt, floor_codes_xy_m=floor_codes_xy_m,
        payload_unit_m=payload_unit_m, dpi=dpi)}
    if gt is not None and any(len(t) for t in trajectories.values()):
        paths["position_errors"] = plot_position_errors(out_dir / "position_errors.png",
                                                        trajectories, gt, blackouts, dpi=dpi)
        paths["error_boxplots"] = plot_error_boxplots(out_dir / "error_boxplots.png",
                                                      trajectories, gt, dpi=dpi)
    if any(lm.loads for lm in load_maps.values()) or loads_gt:
        paths["load_map"] = plot_load_map(out_dir / "load_map.png", load_maps, loads_gt, gt,
                                          dpi=dpi)
    return paths


__all__ = ["estimator_colour", "plot_trajectories", "plot_position_errors",
           "plot_error_boxplots", "plot_load_map", "plot_all"]
