"""What `fusion run`'s report writer calls (fusion.evaluate.report.write_report): the 3D view
report.html, the run record run.json, and the lines report.md gets (a link to the view and the
markers the inventory section goes between)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from fusion.estimate.asbuilt import FloorCodeMap
from fusion.types import LoadMap, PositionTrack, Trajectory
from fusion.warehouse.inventory import REPORT_BEGIN, REPORT_END
from fusion.warehouse.runs import RUN_RECORD, WORLD_YAML, write_run_record
from fusion.warehouse.view3d import REPORT_HTML, write_report_html

logger = logging.getLogger(__name__)


def report_hook(
    out_dir: Path,
    trajectories: dict[str, Trajectory],
    load_maps: dict[str, LoadMap],
    floor_codes_xy_m: np.ndarray | None,
    log_summary: dict,
    gt=None,
    floor_codes: FloorCodeMap | None = None,
) -> list[str]:
    """Write `out_dir/report.html` (and `out_dir/run.json` when log_summary names the log);
    return the Markdown lines for report.md.  floor_codes: the as-built floor codes, whose
    misplaced ones report.html highlights."""
    out_dir = Path(out_dir)
    if "path" in log_summary and (Path(log_summary["path"]) / WORLD_YAML).exists():
        write_run_record(out_dir, log_summary["path"])
    else:
        logger.info(
            "%s: no flight log with a world.yaml named in the report facts: no %s "
            "(fusion inventory / map merge will need --log)",
            out_dir,
            RUN_RECORD,
        )
    gt_track = None if gt is None else groundtruth_track(gt)
    write_report_html(
        out_dir,
        trajectories,
        load_maps,
        floor_codes_xy_m,
        float(log_summary.get("payload_unit_m") or 1.0),
        gt_track,
        misplaced_codes=None
        if floor_codes is None
        else [
            (
                c.code_id,
                c.p_world,
                f"offset {100 * float(np.linalg.norm(c.offset_xy_m)):.1f} cm "
                f"({c.mahalanobis_offset():.1f} sigma), {c.n_obs} sightings",
            )
            for c in floor_codes.misplaced
        ],
    )
    return [
        f"Interactive 3D view (opens offline): [{REPORT_HTML}]({REPORT_HTML})",
        "",
        REPORT_BEGIN,
        REPORT_END,
        "",
    ]


def groundtruth_track(gt) -> PositionTrack:
    """The 3D view's ground truth (fusion.log.GroundTruth): its positions as read, as float64 like
    a pose's translation, without building the whole flight's (N, 4, 4) poses (~0.1 GB of
    temporaries at the evaluation's memory peak on a 30-minute flight, BENCHMARKS.md)."""
    return PositionTrack(
        "groundtruth", np.asarray(gt.timestamps_ns), np.asarray(gt.p_world, dtype=np.float64)
    )
