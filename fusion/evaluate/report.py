"""`report.md`: Markdown tables (raw vs fused, beside the paper's figures) and the PNG plots.

With ground truth the tables come from `metrics.evaluate`'s dict; without it the report shows
the trajectories, the load map and the detection statistics only, and says so.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fusion.evaluate.metrics import (PAPER_SIM_LOADMAP_MAE_CM, PAPER_SIM_LOCALIZATION_MAE_CM,
                                     PAPER_SIM_YAW_MAE_DEG)
from fusion.evaluate.plots import DEFAULT_DPI, RAW_ESTIMATORS, plot_all
from fusion.fileio import atomic_open
from fusion.types import LoadMap, Trajectory

DASH = "–"
PLOT_CAPTIONS = {
    "trajectories": "Trajectories: top view and side view (truth grey, raw estimators as dots, "
                    "fused as lines; floor codes as faint squares)",
    "position_errors": "Position error over time per axis and its norm, ±2σ from the "
                       "covariances, floor-code blackouts shaded",
    "error_boxplots": "Absolute error per axis and yaw per estimator (cf. the paper's Fig. 31)",
    "load_map": "Load map: estimated vs true positions (top view, 2σ ellipses) and heights "
                "(cf. the paper's Figs. 33-34)",
}


def _f(v, scale: float = 1.0, digits: int = 2) -> str:
    if v is None:
        return DASH
    try:
        x = float(v) * scale
    except (TypeError, ValueError):
        return str(v)
    if not np.isfinite(x):
        return DASH
    return f"{x:.{digits}f}"


def _get(d: dict | None, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |",
           "|" + "|".join("---" if i == 0 else "--:" for i in range(len(header))) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out + [""]


def _kind(name: str) -> str:
    return "raw" if name in RAW_ESTIMATORS else "fused"


def _flatten(d: dict, prefix: str = "") -> list[tuple[str, object]]:
    out = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out += _flatten(v, key + ".")
        else:
            out.append((key, v))
    return out


def _kv_rows(d: dict) -> list[list[str]]:
    rows = []
    for k, v in _flatten(d):
        if isinstance(v, float):
            v = f"{v:.4g}"
        elif isinstance(v, (list, tuple)):
            v = ", ".join(str(x) for x in v[:12]) + (" …" if len(v) > 12 else "")
        rows.append([f"`{k}`", str(v).replace("|", "\\|").replace("\n", " ")])
    return rows


# ============================================================================ sections


def _localization_section(m: dict) -> list[str]:
    trajs = m.get("trajectories", {})
    rows = []
    for name, t in trajs.items():
        rows.append([name, _kind(name), t.get("n_matched", 0), _f(t.get("coverage_fraction"), 100, 1),
                     _f(_get(t, "axis", "mae_x_cm")), _f(_get(t, "axis", "mae_y_cm")),
                     _f(_get(t, "axis", "mae_z_cm")), _f(_get(t, "yaw", "yaw_mae_deg"))])
    p = PAPER_SIM_LOCALIZATION_MAE_CM
    rows.append(["*paper, simulator (Sec. 4.1)*", "", "50", DASH, _f(p["x"]), _f(p["y"]),
                 _f(p["z"]), _f(PAPER_SIM_YAW_MAE_DEG)])
    lines = ["## Localization: per-axis mean absolute error (the paper's metric)", ""]
    lines += _table(["estimator", "kind", "poses", "coverage [%]", "MAE x [cm]", "MAE y [cm]",
                     "MAE z [cm]", "MAE yaw [deg]"], rows)
    lines += ["Coverage: share of ground-truth time with an estimate within "
              f"{_f(_get(next(iter(trajs.values()), {}), 'coverage_tolerance_s'), 1000, 0)} ms. "
              "The paper's estimator gives position and yaw only; its roll and pitch are not "
              "compared.", ""]

    rows = []
    for name, t in trajs.items():
        rows.append([name, _f(_get(t, "ate", "ate_rmse_m"), 100), _f(_get(t, "ate", "ate_mean_m"), 100),
                     _f(_get(t, "ate", "ate_max_m"), 100),
                     _f(_get(t, "ate_aligned", "ate_rmse_m"), 100),
                     _f(_get(t, "rotation", "rot_rmse_deg")),
                     _f(_get(t, "rpe_1m", "rpe_trans_rmse_m"), 100),
                     _f(_get(t, "rpe_1m", "rpe_yaw_rmse_deg")),
                     _f(_get(t, "rpe_1s", "rpe_trans_rmse_m"), 100),
                     _f(_get(t, "rpe_1s", "rpe_rot_rmse_deg"))])
    lines += ["## Absolute and relative errors", ""]
    lines += _table(["estimator", "ATE RMSE [cm]", "ATE mean [cm]", "ATE max [cm]",
                     "ATE RMSE, SE(3)-aligned [cm]", "rotation RMSE [deg]",
                     "RPE 1 m trans. RMSE [cm]", "RPE 1 m yaw RMSE [deg]",
                     "RPE 1 s trans. RMSE [cm]", "RPE 1 s rot. RMSE [deg]"], rows)
    lines += ["ATE: |p_est − p_true| in the floor codes' world frame, no alignment (the aligned "
              "column, when present, is evo's `-a`). RPE: drift of the displacement over 1 m of "
              "travelled distance / over 1 s, in the world frame.", ""]
    return lines


def _blackout_section(m: dict) -> list[str]:
    info = m.get("blackouts")
    if not info:
        return []
    trajs = m.get("trajectories", {})
    groups = sorted({g for t in trajs.values() for g in (_get(t, "blackouts", "by_duration") or {})},
                    key=float)
    rows = []
    for name, t in trajs.items():
        b = t.get("blackouts")
        if not b:
            continue
        row = [name, b["n_inside"], _f(_get(b, "inside", "rmse_m"), 100),
               _f(_get(b, "inside", "max_m"), 100), _f(_get(b, "outside", "rmse_m"), 100),
               _f(_get(b, "outside", "max_m"), 100)]
        for g in groups:
            rec = _get(b, "by_duration", g) or {}
            row.append(_f(rec.get("max_error_max_m"), 100) +
                       (f" ({rec.get('n_with_estimates', 0)}/{rec.get('n_blackouts', 0)})"
                        if rec else ""))
        rows.append(row)
    lines = ["## Floor-code blackouts", "",
             f"{info['n']} blackouts in the log, {_f(info.get('total_s'), 1, 1)} s in total "
             "(intervals in which the simulator made the floor codes unreadable on purpose).", ""]
    lines += _table(["estimator", "poses inside", "RMSE inside [cm]", "max inside [cm]",
                     "RMSE outside [cm]", "max outside [cm]"]
                    + [f"max in {g} s blackouts [cm] (with estimates/all)" for g in groups], rows)
    lines += ["A raw estimator has no pose inside a blackout (a dash): that is the gap the fusion "
              "fills.", ""]
    return lines


def _nees_section(m: dict) -> list[str]:
    rows = []
    for name, t in m.get("trajectories", {}).items():
        n3, n6 = t.get("nees_position_3dof"), t.get("nees_pose_6dof")
        if not n3 and not n6:
            continue
        rows.append([name, (n3 or n6 or {}).get("n", 0), _f(_get(n3, "nees_mean")),
                     _f(_get(n3, "fraction_inside_95"), 100, 1), _f(_get(n6, "nees_mean")),
                     _f(_get(n6, "fraction_inside_95"), 100, 1)])
    if not rows:
        return []
    lines = ["## Consistency (NEES)", ""]
    lines += _table(["estimator", "poses", "position NEES mean (ideal 3)",
                     "inside χ²(3) 95% [%]", "pose NEES mean (ideal 6)", "inside χ²(6) 95% [%]"],
                    rows)
    lines += ["Pose error ξ = Log(T_true⁻¹ T_est) in the body frame, GTSAM order "
              "[rx, ry, rz, tx, ty, tz], against the reported 6×6 covariance. A mean far above "
              "the dimension means overconfident covariances; far below, overcautious.", ""]
    return lines


def _loadmap_section(m: dict) -> list[str]:
    maps = m.get("load_maps", {})
    if not maps or not any("axis" in v for v in maps.values()):
        return []
    rows = []
    for name, r in maps.items():
        rows.append([name, f"{r.get('n_mapped', 0)}/{r.get('n_loads_gt', 0)}",
                     _f(_get(r, "axis", "mae_x_cm")), _f(_get(r, "axis", "mae_y_cm")),
                     _f(_get(r, "axis", "mae_z_cm")), _f(_get(r, "error_norm", "rmse_m"), 100),
                     _f(_get(r, "error_norm", "max_m"), 100), _f(_get(r, "nees_3dof", "nees_mean")),
                     ", ".join(r.get("missing_ids", [])[:8]) or DASH,
                     ", ".join(r.get("extra_ids", [])[:8]) or DASH])
    p = PAPER_SIM_LOADMAP_MAE_CM
    rows.append(["*paper, simulator (Sec. 4.2)*", DASH, _f(p["x"]), _f(p["y"]), _f(p["z"]), DASH,
                 DASH, DASH, DASH, DASH])
    lines = ["## Load map", ""]
    lines += _table(["estimator", "mapped/true", "MAE x [cm]", "MAE y [cm]", "MAE z [cm]",
                     "3D RMSE [cm]", "3D max [cm]", "NEES mean (ideal 3)", "missing", "unknown ids"],
                    rows)
    ids = sorted({i for r in maps.values() for i in (r.get("per_load") or {})})
    if ids:
        names = list(maps)
        per = [[f"`{i}`"] + [_f(_get(maps[n], "per_load", i, "error_norm_m"), 100) for n in names]
               for i in ids]
        lines += ["3D error per load [cm]:", ""]
        lines += _table(["load id"] + names, per)
    return lines


def _trajectory_summary(trajectories: dict[str, Trajectory]) -> list[str]:
    rows = []
    for name, t in trajectories.items():
        if len(t):
            p = t.positions_xyz
            span = (int(t.timestamps_ns[-1]) - int(t.timestamps_ns[0])) * 1e-9
            length = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
            rate = (len(t) - 1) / span if span > 0 else 0.0
            rows.append([name, _kind(name), len(t), _f(span, 1, 1), _f(rate, 1, 1), _f(length),
                         _f(p[:, 2].mean()), "yes" if t.covariances is not None else "no"])
        else:
            rows.append([name, _kind(name), 0, DASH, DASH, DASH, DASH, DASH])
    lines = ["## Trajectories", ""]
    lines += _table(["estimator", "kind", "poses", "time span [s]", "mean rate [Hz]",
                     "path length [m]", "mean height [m]", "covariance"], rows)
    return lines


def _load_table(load_maps: dict[str, LoadMap]) -> list[str]:
    rows = []
    for name, lm in load_maps.items():
        for l in sorted(lm.loads, key=lambda l: l.load_id):
            sig = np.sqrt(np.clip(np.diag(l.cov_world), 0, None)) * 100 if l.cov_world is not None \
                else [None] * 3
            rows.append([name, f"`{l.load_id}`", *(_f(v, 1, 3) for v in l.p_world),
                         *(_f(s) for s in sig), l.n_obs])
    if not rows:
        return []
    return ["## Load map (estimates)", ""] + _table(
        ["estimator", "load id", "x [m]", "y [m]", "z [m]", "σx [cm]", "σy [cm]", "σz [cm]",
         "observations"], rows)


# ============================================================================ report


def write_report(out_dir: Path, metrics: dict | None, trajectories: dict[str, Trajectory],
                 load_maps: dict[str, LoadMap], gt=None,
                 loads_gt: dict[str, np.ndarray] | None = None,
                 blackouts: list[tuple[int, int, str]] | None = None,
                 log_summary: dict | None = None, *, dpi: int = DEFAULT_DPI,
                 floor_codes_xy_m: np.ndarray | None = None) -> Path:
    """Write `out_dir/report.md` and its PNG plots; returns the report's path.

    metrics: `evaluate(...)`'s dict (None, or has_groundtruth False: a report without errors).
    gt: `fusion.log.GroundTruth` or None.  log_summary: free key/value facts about the log
    (e.g. log path, duration_s, frames, payload_unit_m); a `detection` entry there is used when
    `metrics` has none."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    log_summary = dict(log_summary or {})
    has_truth = bool(metrics and metrics.get("has_groundtruth") and gt is not None)
    unit = log_summary.get("payload_unit_m", 1.0)
    plots = plot_all(out_dir, trajectories, load_maps, gt if has_truth else None,
                     loads_gt if has_truth else None, blackouts if has_truth else None,
                     floor_codes_xy_m=floor_codes_xy_m,
                     payload_unit_m=float(unit) if unit else None, dpi=dpi)

    lines = ["# fusion report", ""]
    if log_summary:
        lines += ["## Flight log", ""]
        lines += _table(["item", "value"], _kv_rows({k: v for k, v in log_summary.items()
                                                      if k != "detection"}))
    if not has_truth:
        lines += ["> **No ground truth in this log:** errors, NEES and the comparison with the "
                  "paper's figures are not computed. Shown: trajectories, load map and detection "
                  "statistics only.", ""]
    lines += _trajectory_summary(trajectories)
    if has_truth:
        gtm = metrics.get("groundtruth", {})
        lines += [f"Ground truth: {gtm.get('n_samples', DASH)} samples over "
                  f"{_f(gtm.get('duration_s'), 1, 1)} s, path length "
                  f"{_f(gtm.get('path_length_m'))} m.", ""]
        lines += _localization_section(metrics)
        lines += _blackout_section(metrics)
        lines += _nees_section(metrics)
        lines += _loadmap_section(metrics)
    lines += _load_table(load_maps)
    detection = (metrics or {}).get("detection") or log_summary.get("detection")
    lines += ["## Detection statistics", ""]
    if detection:
        lines += _table(["item", "value"], _kv_rows(detection))
    else:
        lines += ["No detection statistics were given.", ""]
    lines += ["## Plots", ""]
    for key, path in plots.items():
        lines += [f"![{key}]({path.name})", "",
                  f"*{PLOT_CAPTIONS.get(key, key)}.*", ""]
    report = out_dir / "report.md"
    with atomic_open(report) as f:
        f.write("\n".join(lines).rstrip() + "\n")
    return report
