"""`report.md`: a headline table (raw vs fused, blackouts, loads) on the first screen, then the
details (the paper's per-axis MAE beside its published figures, ATE / RPE, each blackout, NEES,
the load map), each section with its plots, and the log and detection facts last.

With ground truth the tables come from `metrics.evaluate`'s dict; without it the report shows
the trajectories, the load map and the detection statistics only, and says so.  Every column
header states its unit; numbers carry three significant digits (errors span 0.001-50 cm).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fusion.estimate.asbuilt import FloorCodeMap
from fusion.evaluate.metrics import (
    PAPER_SIM_LOADMAP_MAE_CM,
    PAPER_SIM_LOCALIZATION_MAE_CM,
    PAPER_SIM_YAW_MAE_DEG,
    coverage_fraction,
    inside_intervals,
)
from fusion.evaluate.plots import DEFAULT_DPI, plot_all, time_origin_ns
from fusion.fileio import atomic_open
from fusion.types import RAW_ESTIMATORS, LoadMap, Trajectory
from fusion.warehouse.floorcodes import floor_code_section
from fusion.warehouse.hook import report_hook

DASH = "–"
BLACKOUT_COVERAGE_TOLERANCE_S = 0.05  # a blackout instant counts as covered by a pose this close
PLOT_CAPTIONS = {
    "trajectories": "Trajectories: top view and side view (truth grey, raw estimators as dots, "
    "fused as lines; floor codes as faint squares; cf. the paper's Fig. 32)",
    "position_errors": "Raw vs fused: |position error| and |yaw error| over time, log scale, "
    "floor-code blackouts shaded with their durations",
    "position_errors_zoom": "Position error per axis (estimate − truth, cm) of PnP and the "
    "fused estimators with their ±2σ bands, blackouts shaded; the y-range"
    " comes from these estimators' errors (the paper's are in the "
    "overview)",
    "error_boxplots": "Absolute errors per estimator on log axes: drone per axis and yaw (cf. the "
    "paper's Fig. 31) and loads per axis (cf. Fig. 34); boxes are quartiles, "
    "whiskers 5th–95th percentiles, × the maximum, dashed the paper's "
    "simulator MAE",
    "position_sigma": "Position uncertainty the estimators report (3D 1σ, cm, log scale) and "
    "the times at which the raw estimators have a pose",
    "load_map": "Load map, for orientation: top view with 2σ ellipses and rack columns labelled, "
    "height per load id; hollow grey: true loads that no estimator saw "
    "(cf. the paper's Fig. 33)",
    "load_errors": "Load error per load id and axis (estimate − truth, cm) with ±2σ bars; the "
    "paper's estimator and the others each on their own scale; grey rows: not seen",
}
_PLOT_SECTION = {
    "position_errors": "summary",
    "position_errors_zoom": "summary",
    "position_sigma": "localization",
    "error_boxplots": "localization",
    "trajectories": "localization",
    "load_map": "loads",
    "load_errors": "loads",
}


# ============================================================================ formatting


def fmt(v, scale: float = 1.0, sig: int = 3, max_decimals: int = 5) -> str:
    """`v * scale` with `sig` significant digits and no exponent (15.3, 0.318, 0.00512);
    a dash for None / NaN; whole numbers above 10**sig."""
    if v is None:
        return DASH
    try:
        x = float(v) * scale
    except (TypeError, ValueError):
        return str(v)
    if not math.isfinite(x):
        return DASH
    if x == 0:
        return "0"
    decimals = min(max(sig - 1 - math.floor(math.log10(abs(x))), 0), max_decimals)
    return f"{x:.{decimals}f}"


_MD_SPECIAL = set("\\`*_[]<>|~&")  # inline-significant in a table cell (cells hold no blocks)


def _md_plain(text) -> str:
    """Control characters and line breaks as spaces (a line break would end the table row)."""
    return "".join(" " if ch in "\r\n\t" or ord(ch) < 0x20 or ord(ch) == 0x7F else ch for ch in str(text))


def md_text(text) -> str:
    """Untrusted text (a path, a payload) as literal Markdown table-cell text: the characters
    that format, link or split a cell (`|`) are backslash-escaped (CommonMark escapes)."""
    return "".join("\\" + ch if ch in _MD_SPECIAL else ch for ch in _md_plain(text))


def md_code(text) -> str:
    """Untrusted text (a load id from a QR payload) as a code span in a table cell: a fence
    longer than any backtick run inside, `|` escaped (GFM splits cells before inline parsing and
    shows `\\|` as `|`, also in code spans)."""
    t = _md_plain(text).replace("|", "\\|")
    longest = max((len(m) for m in re.findall("`+", t)), default=0)
    fence = "`" * (longest + 1)
    pad = " " if longest or t.startswith(" ") or t.endswith(" ") else ""
    return f"{fence}{pad}{t}{pad}{fence}" if t else DASH


def _pct(v) -> str:
    return DASH if v is None else f"{100.0 * float(v):.1f}"


def _get(d: dict | None, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _table(header: list[str], rows: Sequence[Sequence[object]]) -> list[str]:
    """Markdown table; each cell is written with str()."""
    out = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" if i == 0 else "--:" for i in range(len(header))) + "|",
    ]
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
        rows.append([f"`{k}`", md_text(v)])
    return rows


def _plots(plots: dict[str, Path], section: str) -> list[str]:
    lines = []
    for key, path in plots.items():
        if _PLOT_SECTION.get(key, "other") == section:
            lines += [f"![{key}]({path.name})", "", f"*{PLOT_CAPTIONS.get(key, key)}.*", ""]
    return lines


# ============================================================================ summary


def _longest_gap_s(traj: Trajectory) -> float | None:
    """Longest time between consecutive poses (s); the time before the first pose and after the
    last one is in the coverage, not here."""
    t = np.asarray(traj.timestamps_ns, dtype=np.int64)
    return float(np.max(np.diff(t))) * 1e-9 if len(t) >= 2 else None


def _blackout_coverage(traj: Trajectory, gt, blackouts) -> float | None:
    """Share of the blackouts' time with a pose within BLACKOUT_COVERAGE_TOLERANCE_S."""
    if gt is None or not blackouts:
        return None
    t_gt = np.asarray(gt.timestamps_ns, dtype=np.int64)
    t_in = t_gt[inside_intervals(t_gt, blackouts)]
    if not len(t_in):
        return None
    return coverage_fraction(t_in, traj.timestamps_ns, BLACKOUT_COVERAGE_TOLERANCE_S)


def _health_lines(m: dict) -> list[str]:
    """The headline's first line: can each fused estimate be trusted (estimate/health.py),
    which back ends failed, and the log's warnings."""
    health = m.get("health") or {}
    failures = m.get("estimator_failures") or {}
    warnings = m.get("warnings") or []
    if not (health or failures or warnings):
        return []
    parts = [
        f"{md_code(name)} **{md_text(h.get('status', DASH))}**"
        + (f" ({md_text(h.get('reason', ''))})" if h.get("status") != "ok" else "")
        for name, h in health.items()
    ]
    parts += [f"{md_code(name)} **failed** ({md_text(f.get('reason', ''))})" for name, f in failures.items()]
    lines = ["**Health:** " + "; ".join(parts) + "." if parts else "**Health:** no fused estimate."]
    if warnings:
        lines += [
            "",
            "**Log warnings:** "
            + "; ".join(
                f"{md_code(w.get('name', ''))} ×{w.get('count', 1)}: {md_text(w.get('message', ''))}"
                for w in warnings
            )
            + ".",
        ]
    return lines + [""]


def _time_offset_lines(m: dict) -> list[str]:
    """Each camera's camera-IMU time offset (fusion.estimate.timeoffset): value, sigma, where it
    comes from and whether the outputs carry it."""
    offsets = m.get("time_offsets") or {}
    if not offsets:
        return []
    parts = []
    for name, o in offsets.items():
        sig = f" ± {fmt(o.get('sigma_ms'))}" if o.get("sigma_ms") is not None else ""
        parts.append(
            f"{md_code(name)} {o.get('offset_ms', 0.0):+.2f}{sig} ms ({md_text(o.get('source', DASH))}; "
            f"outputs stamped with {o.get('effective_ms', 0.0):+.2f} ms)"
            + (f" ({md_text(o['note'])})" if o.get("note") else "")
        )
    return ["**Camera-IMU time offsets** (t_imu = t_cam + offset): " + "; ".join(parts) + ".", ""]


def _mount_lines(m: dict) -> list[str]:
    """The cameras' mount rotation checks / calibrations (fusion.estimate.extrinsics)."""
    out = []
    for key, title in (("extrinsics", "Floor"), ("front_extrinsics", "Front")):
        e = m.get(key) or {}
        if not e:
            continue
        head = f"**{title} camera mount rotation** ({md_code(e.get('camera', DASH))})"
        if e.get("rotvec_deg") is None:
            out += [f"{head}: not estimated ({md_text(e.get('note', DASH))}).", ""]
            continue
        axes = ", ".join(
            f"{a} {v:+.3f} ± {d:.3f}"
            for a, v, d in zip("xyz", e["rotvec_deg"], e.get("sigma_deg") or [0.0] * 3)
        )
        sig_axes = e.get("significant_axes") or []
        corr = ", ".join(
            f"{a} {v:+.3f}" for a, v in zip("xyz", e.get("correction_deg") or []) if a in sig_axes
        )
        if e.get("applied"):
            used = f"applied to every output ({corr} deg)"
        else:
            used = "significant: run with --calibrate-extrinsics" if sig_axes else "not significant"
        truth = (
            f"; error against the simulator's truth {'/'.join(f'{v:+.3f}' for v in e['error_deg'])} deg"
            if e.get("error_deg")
            else ""
        )
        out += [f"{head} (body frame, deg): {axes}; {used}{truth}.", ""]
    return out


def _summary_section(m: dict, trajectories: dict[str, Trajectory], gt, blackouts) -> list[str]:
    trajs = m.get("trajectories", {})
    maps = m.get("load_maps", {})
    has_loads = any("axis" in r for r in maps.values())
    rows, facts = [], {}
    for name, t in trajs.items():
        traj = trajectories.get(name)
        b = t.get("blackouts") or {}
        cov_b = _blackout_coverage(traj, gt, blackouts) if traj is not None else None
        gap = _longest_gap_s(traj) if traj is not None else None
        facts[name] = dict(
            ate=_get(t, "ate", "ate_rmse_m"),
            max_in=_get(b, "inside", "max_m"),
            cov_b=cov_b,
            gap=gap,
            coverage=t.get("coverage_fraction"),
        )
        row = [
            name,
            _kind(name),
            _pct(t.get("coverage_fraction")),
            fmt(gap),
            fmt(_get(t, "ate", "ate_rmse_m"), 100),
            fmt(t.get("ate_rmse_on_reference_frames_m"), 100),
            fmt(_get(t, "yaw", "yaw_mae_deg")),
        ]
        if blackouts:
            row += [_pct(cov_b), fmt(_get(b, "inside", "max_m"), 100)]
        if has_loads:
            r = maps.get(name, {})
            row += [
                f"{r.get('n_mapped', 0)}/{r.get('n_loads_gt', 0)}" if r else DASH,
                fmt(_get(r, "error_norm", "rmse_m"), 100),
            ]
        rows.append(row)
    ref = m.get("common_reference", "pnp")
    header = [
        "estimator",
        "kind",
        "coverage [%]",
        "longest gap [s]",
        "ATE RMSE [cm]",
        f"ATE RMSE on {ref} frames [cm]",
        "yaw MAE [deg]",
    ]
    if blackouts:
        header += ["blackout time with a pose [%]", "max error in blackouts [cm]"]
    if has_loads:
        header += ["loads mapped/true", "load 3D RMSE [cm]"]
    lines = ["## Summary", ""] + _table(header, rows)
    lines += _headline_sentences(m, facts, blackouts)
    tol_s = _get(next(iter(trajs.values()), {}), "coverage_tolerance_s") or 0.1
    lines += [
        f"Coverage: share of the ground-truth time with a pose within {tol_s * 1e3:.0f} ms "
        f"(blackouts: within {BLACKOUT_COVERAGE_TOLERANCE_S * 1e3:.0f} ms); longest gap: "
        "between consecutive poses. ATE: |p_est − p_true| "
        "in the floor codes' world frame, no alignment; over all of an estimator's poses, "
        f"and like-for-like over the frames where {ref} has a pose (a fused trajectory "
        "also covers blackouts and the time before the first floor code). Loads: 3D distance to the true "
        "code centre over the loads both mapped and known.",
        "",
    ]
    return lines


def _headline_sentences(m: dict, facts: dict, blackouts) -> list[str]:
    def best(kind):
        c = [(f["ate"], n) for n, f in facts.items() if _kind(n) == kind and f["ate"] is not None]
        return min(c)[1] if c else None

    raw, fused = best("raw"), best("fused")
    if raw is None or fused is None:
        return []
    fr, ff = facts[raw], facts[fused]
    out = [
        f"**Best raw: {raw}**, ATE RMSE {fmt(fr['ate'], 100)} cm, a pose for "
        f"{_pct(fr['coverage'])} % of the flight. **Best fused: {fused}**, ATE RMSE "
        f"{fmt(ff['ate'], 100)} cm, {_pct(ff['coverage'])} % of the flight."
    ]
    info = m.get("blackouts")
    if blackouts and info:
        longest = max(info.get("durations_s") or [0.0])
        out.append(
            f"Floor-code blackouts: {info['n']}, {fmt(info.get('total_s'))} s in total, "
            f"the longest {fmt(longest)} s; {raw} has a pose in "
            f"{_pct(fr['cov_b'])} % of that time, {fused} in {_pct(ff['cov_b'])} % with a "
            f"maximum error of {fmt(ff['max_in'], 100)} cm."
        )
    return [" ".join(out), ""]


# ============================================================================ details


def _localization_section(m: dict) -> list[str]:
    trajs = m.get("trajectories", {})
    rows = []
    for name, t in trajs.items():
        rows.append(
            [
                name,
                _kind(name),
                t.get("n_matched", 0),
                fmt(_get(t, "axis", "mae_x_cm")),
                fmt(_get(t, "axis", "mae_y_cm")),
                fmt(_get(t, "axis", "mae_z_cm")),
                fmt(_get(t, "yaw", "yaw_mae_deg")),
            ]
        )
    p = PAPER_SIM_LOCALIZATION_MAE_CM
    rows.append(
        [
            "*paper, simulator (Sec. 4.1)*",
            "",
            "50",
            f"{p['x']:g}",
            f"{p['y']:g}",
            f"{p['z']:g}",
            f"{PAPER_SIM_YAW_MAE_DEG:g}",
        ]
    )  # as published
    lines = ["## Localization", "", "### Per-axis mean absolute error (the paper's metric)", ""]
    lines += _table(
        ["estimator", "kind", "poses", "MAE x [cm]", "MAE y [cm]", "MAE z [cm]", "MAE yaw [deg]"], rows
    )
    lines += ["The paper's estimator gives position and yaw only; its roll and pitch are not compared.", ""]

    rows = []
    for name, t in trajs.items():
        rows.append(
            [
                name,
                fmt(_get(t, "ate", "ate_rmse_m"), 100),
                fmt(_get(t, "ate", "ate_mean_m"), 100),
                fmt(_get(t, "ate", "ate_max_m"), 100),
                fmt(_get(t, "ate_aligned", "ate_rmse_m"), 100),
                fmt(_get(t, "rotation", "rot_rmse_deg")),
                fmt(_get(t, "rpe_1m", "rpe_trans_rmse_m"), 100),
                fmt(_get(t, "rpe_1m", "rpe_yaw_rmse_deg")),
                fmt(_get(t, "rpe_1s", "rpe_trans_rmse_m"), 100),
                fmt(_get(t, "rpe_1s", "rpe_rot_rmse_deg")),
            ]
        )
    lines += ["### Absolute and relative errors", ""]
    lines += _table(
        [
            "estimator",
            "ATE RMSE [cm]",
            "ATE mean [cm]",
            "ATE max [cm]",
            "ATE RMSE, SE(3)-aligned [cm]",
            "rotation RMSE [deg]",
            "RPE 1 m trans. RMSE [cm]",
            "RPE 1 m yaw RMSE [deg]",
            "RPE 1 s trans. RMSE [cm]",
            "RPE 1 s rot. RMSE [deg]",
        ],
        rows,
    )
    lines += [
        "ATE: |p_est − p_true| in the floor codes' world frame, no alignment (the aligned "
        "column, when present, is evo's `-a`). RPE: drift of the displacement over 1 m of "
        "travelled distance / over 1 s, in the world frame. Rotation: full attitude "
        "(not for the paper's estimator).",
        "",
    ]
    return lines


def _blackout_section(m: dict, t0_ns: int) -> list[str]:
    info = m.get("blackouts")
    if not info:
        return []
    trajs = {n: t for n, t in m.get("trajectories", {}).items() if t.get("blackouts")}
    lines = [
        "## Floor-code blackouts",
        "",
        f"{info['n']} blackouts in the log, {fmt(info.get('total_s'))} s in total "
        "(intervals in which the simulator made the floor codes unreadable on purpose). "
        "Maximum |position error| inside each, in cm, with the number of poses inside in "
        "brackets; \"no pose\": the estimator has nothing there (the gap the fusion "
        "fills).",
        "",
    ]
    per = {n: t["blackouts"].get("per_blackout") or [] for n, t in trajs.items()}
    n_b = max((len(v) for v in per.values()), default=0)
    rows = []
    for i in range(n_b):
        ref = next(v[i] for v in per.values() if len(v) > i)
        row = [
            str(i + 1),
            fmt((ref["start_ns"] - t0_ns) * 1e-9),
            fmt(ref["duration_s"]),
            str(ref.get("kind", "")),
        ]
        for name in trajs:
            b = per[name][i] if len(per[name]) > i else None
            if b is None:
                row.append(DASH)
            elif not b.get("n_estimates"):
                row.append("no pose")
            else:
                row.append(f"{fmt(b.get('max_error_m'), 100)} ({b['n_estimates']})")
        rows.append(row)
    if rows:
        lines += _table(
            ["#", "start [s]", "duration [s]", "kind"] + [f"{n} max [cm] (poses)" for n in trajs], rows
        )
    rows = []
    for name, t in trajs.items():
        b = t["blackouts"]
        rows.append(
            [
                name,
                b["n_inside"],
                fmt(_get(b, "inside", "rmse_m"), 100),
                fmt(_get(b, "inside", "max_m"), 100),
                fmt(_get(b, "outside", "rmse_m"), 100),
                fmt(_get(b, "outside", "max_m"), 100),
            ]
        )
    lines += ["Inside vs outside the blackouts:", ""]
    lines += _table(
        [
            "estimator",
            "poses inside",
            "RMSE inside [cm]",
            "max inside [cm]",
            "RMSE outside [cm]",
            "max outside [cm]",
        ],
        rows,
    )
    lines += [
        "Start times count from the plots' time origin. Raw estimators may show a pose at a blackout's edge.",
        "",
    ]
    return lines


def _nees_section(m: dict) -> list[str]:
    rows = []
    for name, t in m.get("trajectories", {}).items():
        n3, n6 = t.get("nees_position_3dof"), t.get("nees_pose_6dof")
        if not n3 and not n6:
            continue
        rows.append(
            [
                name,
                (n3 or n6 or {}).get("n", 0),
                fmt(_get(n3, "nees_mean")),
                _pct(_get(n3, "fraction_inside_95")),
                fmt(_get(n6, "nees_mean")),
                _pct(_get(n6, "fraction_inside_95")),
            ]
        )
    if not rows:
        return []
    lines = ["## Consistency (NEES)", ""]
    lines += _table(
        [
            "estimator",
            "poses",
            "position NEES mean (ideal 3)",
            "inside χ²(3) 95% [%]",
            "pose NEES mean (ideal 6)",
            "inside χ²(6) 95% [%]",
        ],
        rows,
    )
    lines += [
        "Pose error ξ = Log(T_true⁻¹ T_est) in the body frame, GTSAM order "
        "[rx, ry, rz, tx, ty, tz], against the reported 6×6 covariance (NEES is "
        "dimensionless). A mean far above the dimension means overconfident covariances; "
        "far below, overcautious.",
        "",
    ]
    return lines


def _loadmap_section(m: dict, plot_lines: list[str]) -> list[str]:
    maps = m.get("load_maps", {})
    if not maps or not any("axis" in v for v in maps.values()):
        return []
    rows = []
    for name, r in maps.items():
        rows.append(
            [
                name,
                _kind(name),
                f"{r.get('n_mapped', 0)}/{r.get('n_loads_gt', 0)}",
                fmt(_get(r, "axis", "mae_x_cm")),
                fmt(_get(r, "axis", "mae_y_cm")),
                fmt(_get(r, "axis", "mae_z_cm")),
                fmt(_get(r, "error_norm", "rmse_m"), 100),
                fmt(_get(r, "error_norm", "max_m"), 100),
                fmt(_get(r, "nees_3dof", "nees_mean")),
                ", ".join(md_code(i) for i in r.get("extra_ids", [])[:8]) or DASH,
            ]
        )
    p = PAPER_SIM_LOADMAP_MAE_CM
    rows.append(
        [
            "*paper, simulator (Sec. 4.2)*",
            "",
            DASH,
            f"{p['x']:g}",
            f"{p['y']:g}",
            f"{p['z']:g}",
            DASH,
            DASH,
            DASH,
            DASH,
        ]
    )  # as published
    lines = ["## Load map", ""]
    lines += _table(
        [
            "estimator",
            "kind",
            "mapped/true",
            "MAE x [cm]",
            "MAE y [cm]",
            "MAE z [cm]",
            "3D RMSE [cm]",
            "3D max [cm]",
            "NEES mean (ideal 3)",
            "ids not in the truth",
        ],
        rows,
    )
    missing = sorted(set.intersection(*[set(r.get("missing_ids", [])) for r in maps.values()]))
    if missing:
        lines += [
            f"Not seen by any estimator ({len(missing)}): "
            + ", ".join(md_code(i) for i in missing[:40])
            + (" …" if len(missing) > 40 else "")
            + ".",
            "",
        ]
    lines += plot_lines
    ids = sorted({i for r in maps.values() for i in (r.get("per_load") or {})})
    if ids:
        names = list(maps)
        per = [
            [md_code(i)] + [fmt(_get(maps[n], "per_load", i, "error_norm_m"), 100) for n in names]
            for i in ids
        ]
        lines += ["3D error per load [cm] (a dash: not mapped by that estimator):", ""]
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
            rows.append(
                [
                    name,
                    _kind(name),
                    len(t),
                    f"{span:.1f}",
                    f"{rate:.1f}",
                    fmt(_longest_gap_s(t)),
                    f"{length:.2f}",
                    f"{p[:, 2].mean():.2f}",
                    "yes" if t.covariances is not None else "no",
                ]
            )
        else:
            rows.append([name, _kind(name), 0, DASH, DASH, DASH, DASH, DASH, DASH])
    return _table(
        [
            "estimator",
            "kind",
            "poses",
            "time span [s]",
            "mean rate [Hz]",
            "longest gap [s]",
            "path length [m]",
            "mean height [m]",
            "covariance",
        ],
        rows,
    )


def _load_table(load_maps: dict[str, LoadMap]) -> list[str]:
    rows = []
    for name, lm in load_maps.items():
        for l in sorted(lm.loads, key=lambda l: l.load_id):
            sig = (
                np.sqrt(np.clip(np.diag(l.cov_world), 0, None)) * 100
                if l.cov_world is not None
                else [None] * 3
            )
            rows.append(
                [name, md_code(l.load_id), *(f"{v:.4f}" for v in l.p_world), *(fmt(s) for s in sig), l.n_obs]
            )
    if not rows:
        return []
    return ["## Load map estimates", ""] + _table(
        ["estimator", "load id", "x [m]", "y [m]", "z [m]", "σx [cm]", "σy [cm]", "σz [cm]", "observations"],
        rows,
    )


def _load_counts(load_maps: dict[str, LoadMap]) -> list[str]:
    if not load_maps:
        return []
    rows = [
        [
            name,
            _kind(name),
            len(lm.loads),
            fmt(
                np.median(
                    [np.sqrt(max(np.trace(l.cov_world), 0)) for l in lm.loads if l.cov_world is not None]
                )
                if any(l.cov_world is not None for l in lm.loads)
                else None,
                100,
            ),
        ]
        for name, lm in load_maps.items()
    ]
    return _table(["estimator", "kind", "loads mapped", "median 3D σ [cm]"], rows)


# ============================================================================ report


def write_report(
    out_dir: Path,
    metrics: dict | None,
    trajectories: dict[str, Trajectory],
    load_maps: dict[str, LoadMap],
    gt=None,
    loads_gt: dict[str, np.ndarray] | None = None,
    blackouts: list[tuple[int, int, str]] | None = None,
    log_summary: dict | None = None,
    *,
    dpi: int = DEFAULT_DPI,
    floor_codes_xy_m: np.ndarray | None = None,
    floor_codes: FloorCodeMap | None = None,
) -> Path:
    """Write `out_dir/report.md` and its PNG plots; returns the report's path.

    metrics: `evaluate(...)`'s dict (None, or has_groundtruth False: a report without errors).
    gt: `fusion.log.GroundTruth` or None.  log_summary: free key/value facts about the log
    (e.g. log path, duration_s, frames, payload_unit_m); a `detection` entry there is used when
    `metrics` has none.  floor_codes: the as-built floor codes (a section with their offsets
    plot; misplaced ones highlighted in report.html)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    log_summary = dict(log_summary or {})
    has_truth = bool(metrics and metrics.get("has_groundtruth") and gt is not None)
    unit = log_summary.get("payload_unit_m", 1.0)
    blackouts = blackouts if has_truth else None
    plots = plot_all(
        out_dir,
        trajectories,
        load_maps,
        gt if has_truth else None,
        loads_gt if has_truth else None,
        blackouts,
        floor_codes_xy_m=floor_codes_xy_m,
        payload_unit_m=float(unit) if unit else None,
        dpi=dpi,
    )

    lines = ["# fusion report", ""]
    facts = [
        md_code(log_summary["path"]) if "path" in log_summary else None,
        f"{fmt(log_summary['duration_s'])} s" if "duration_s" in log_summary else None,
        f"{log_summary['floor_frames']} floor frames" if "floor_frames" in log_summary else None,
    ]
    if any(facts):
        lines += ["Flight " + ", ".join(f for f in facts if f) + ".", ""]
    warehouse_lines = report_hook(
        out_dir,
        trajectories,
        load_maps,
        floor_codes_xy_m,
        log_summary,
        gt if has_truth else None,
        floor_codes,
    )
    lines += warehouse_lines[:2]  # link to report.html
    lines += _health_lines(metrics or {})
    lines += _time_offset_lines(metrics or {})
    lines += _mount_lines(metrics or {})
    if has_truth and metrics is not None:  # has_truth implies metrics; the check narrows it
        lines += _summary_section(metrics, trajectories, gt, blackouts)
        lines += _plots(plots, "summary")
        gtm = metrics.get("groundtruth", {})
        lines += _localization_section(metrics)
        lines += [
            "Trajectories (ground truth: "
            f"{gtm.get('n_samples', DASH)} samples over {fmt(gtm.get('duration_s'))} s, "
            f"path length {fmt(gtm.get('path_length_m'))} m):",
            "",
        ]
        lines += _trajectory_summary(trajectories)
        lines += _plots(plots, "localization")
        lines += _blackout_section(metrics, time_origin_ns(gt, trajectories))
        lines += _nees_section(metrics)
        load_plots = _plots(plots, "loads")
        section = _loadmap_section(metrics, load_plots)
        lines += section
        if section:
            plots = {k: v for k, v in plots.items() if _PLOT_SECTION.get(k) != "loads"}
    else:
        lines += [
            "## Summary",
            "",
            "> **No ground truth in this log:** errors, NEES and the comparison with the "
            "paper's figures are not computed. Shown: trajectories, load map and detection "
            "statistics only.",
            "",
        ]
        lines += _trajectory_summary(trajectories)
        lines += _load_counts(load_maps)
        lines += ["## Localization", ""] + _plots(plots, "localization")
        if load_maps:
            lines += ["## Load map", ""]
    lines += _plots(plots, "loads")
    lines += _plots(plots, "other")
    lines += _load_table(load_maps)
    if log_summary:
        lines += ["## Flight log", ""]
        lines += _table(
            ["item", "value"], _kv_rows({k: v for k, v in log_summary.items() if k != "detection"})
        )
    detection = (metrics or {}).get("detection") or log_summary.get("detection")
    lines += ["## Detection statistics", ""]
    if detection:
        lines += _table(["item", "value"], _kv_rows(detection))
    else:
        lines += ["No detection statistics were given.", ""]
    if floor_codes is not None:
        lines += floor_code_section(out_dir, floor_codes, log_summary.get("path"), dpi)
    lines += warehouse_lines[2:]  # where `fusion inventory` puts its section
    report = out_dir / "report.md"
    with atomic_open(report) as f:
        f.write("\n".join(lines).rstrip() + "\n")
    return report
