"""Corner refinement of load codes seen at an angle (issue 10.2 / 10.3): the stage-2 corners and
edge points of the front camera's load codes along the first aisle (a view every 0.5 s) of the
`default` (square to the rack) and `oblique` (turned +-0.4 rad at the hovers) scenarios,
rendered noise-free with a global shutter, as flown ("far 1"), from 4x farther with a 4x
longer focal length ("far 4": the same turn, a quarter of the perspective, ~0.83x the module
size), or with the focal length scaled in place (`--zoom`: larger modules, the same
perspective).  Per case: the mean module size (px), mean corner error (px) against the true
projection, the signed error per corner (TL, TR, BR, BL), and the mean signed error of the last
pass's edge points per finder edge (module line u = c or v = c, px across the edge, against the
true homography).  `--supersample N` renders at N x N the resolution and averages each block:
pixels that integrate their area, as a sensor's do, instead of the renderer's point samples.

BENCHMARKS.md, twenty-fifth session: an oblique code's corners err ~4x a square one's.
Twenty-sixth session: not the perspective but the sharpness of the edges.  The renderer draws a
code from a mip level of 2^k texels per module, so its edges are a ramp one texel wide, 1-2 px;
codes from ~4 px per module get 1 px ramps, and the bilinear samples of the refinement read such
a sharp edge with an error that depends on where it falls between pixel centres (the square
codes at --zoom 1.15, 4.2 px per module, err like the oblique ones; "far 4" had smaller modules).

    PYTHONPATH=$PWD python3 scripts/bench_oblique_refine.py [--far 1 4] [--zoom 1 1.15]
        [--no-distortion] [--supersample N]
"""

from __future__ import annotations

import argparse
import datetime
import platform
from dataclasses import replace

import cv2
import numpy as np

import fusion.qr.refine as refine
from fusion.qr.detect import detect_frame
from fusion.sim.render import RenderEffects, project_code_corners, render_view
from fusion.sim.scenarios import build_scenario

AISLE = (4, 11)  # keyframes from the first to the last hover of aisle 1 (fusion.sim.scenarios._default)
STEP_S = 0.5  # a view every this many seconds along it
STANDOFF_M = 1.2  # the aisle's distance to the rack face


def _edge_errors(camera, fit, pr, ns, corners_px) -> list[tuple[int, float, float]]:
    """(axis, module line, signed error px) of each usable edge point of one code's last pass."""
    n = float(ns[0])
    xn = camera.undistort_normalized(corners_px)
    truth = np.column_stack([xn[:, 0] * camera.fu + camera.cu, xn[:, 1] * camera.fv + camera.cv])
    square = np.float32([[0, 0], [n, 0], [n, n], [0, n]])
    G = np.linalg.inv(cv2.getPerspectiveTransform(square, np.float32(truth)).astype(float))
    p = np.column_stack([fit.points, np.ones(len(fit.points))]) @ G.T
    uv = p[:, :2] / p[:, 2:3]
    err_px = (np.where(pr.axis == 0, uv[:, 0], uv[:, 1]) - pr.const) / fit.g
    return [(int(pr.axis[i]), float(pr.const[i]), float(err_px[i])) for i in np.flatnonzero(fit.good)]


def _render(cam, T_wc, codes, n: int) -> np.ndarray:
    """Noise-free view; with n > 1 rendered n x n larger (pixel centres kept: OpenCV's
    convention) and averaged over each n x n block."""
    if n == 1:
        return render_view(cam, T_wc, codes, None, RenderEffects(noise_sigma_dn=0.0))
    c = (n - 1) / 2.0
    big_cam = replace(cam, fu=cam.fu * n, fv=cam.fv * n, cu=cam.cu * n + c, cv=cam.cv * n + c)
    big_cam = replace(big_cam, width=cam.width * n, height=cam.height * n)
    big = render_view(big_cam, T_wc, codes, None, RenderEffects(noise_sigma_dn=0.0)).astype(np.float32)
    blocks = big.reshape(cam.height, n, cam.width, n).mean(axis=(1, 3))
    return np.clip(np.rint(blocks), 0, 255).astype(np.uint8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--far", type=float, nargs="+", default=[1.0, 4.0])
    ap.add_argument("--zoom", type=float, nargs="+", default=[1.0], help="focal length scales, in place")
    ap.add_argument("--no-distortion", action="store_true", help="the front camera without its lens")
    ap.add_argument("--supersample", type=int, default=1, help="render N x N larger, average blocks")
    args = ap.parse_args()
    captured = []
    fit_homographies = refine._fit_homographies

    def spy(fit, pr, ns, *a, **k):  # the last pass's edge points, for the per-edge errors
        captured.append((fit, pr, ns))
        return fit_homographies(fit, pr, ns, *a, **k)

    refine._fit_homographies = spy
    print(f"# bench_oblique_refine ({datetime.date.today()}, {platform.machine()})\n")
    print(
        "| scenario | far | zoom | module px | codes | corner error px | signed per corner (TL, TR, BR, BL) "
        "| edge points: mean signed px by line |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in ("default", "oblique"):
        sc = build_scenario(name)
        loads = [c for c in sc.codes() if not c.is_floor]
        by_payload = {c.payload: c for c in loads}
        for far, zoom in [(f, z) for f in args.far for z in args.zoom]:
            base = sc.cameras["cam1"]
            cam = replace(base, fu=base.fu * far * zoom, fv=base.fv * far * zoom)
            if args.no_distortion:
                cam = replace(cam, distortion=np.zeros(4))
            errors, signed, edges, module_px = [], [], [], []
            kf = sc.trajectory.keyframes
            for t in np.arange(kf[AISLE[0]].t_s, kf[AISLE[1]].t_s, STEP_S):
                T_wb = sc.trajectory.state(np.array([t])).T_world_body[0]
                T_wc = cam.T_world_cam(T_wb).copy()
                T_wc[:3, 3] -= (far - 1.0) * STANDOFF_M * T_wc[:3, 2]  # back along the optical axis
                image = _render(cam, T_wc, loads, args.supersample)
                for d in detect_frame(image, "cam1", 0, cam):
                    if d.payload not in by_payload:
                        continue
                    truth = project_code_corners(cam, T_wc, by_payload[d.payload])
                    captured.clear()
                    res = refine.refine_code(image, d.corners_raw_px, None, cam)
                    if res is None or res.stage != 2:
                        continue
                    errors.append(np.linalg.norm(res.corners_px - truth, axis=1))
                    module_px.append(res.quality.module_px)
                    signed.append(res.corners_px - truth)
                    edges += _edge_errors(cam, *captured[-1], truth)
            if not errors:
                print(f"| {name} | {far:g} | {zoom:g} | – | 0 | – | – | – |")
                continue
            e = np.array(edges)
            by_line = ", ".join(
                f"{'uv'[int(ax)]}={c:g} {e[(e[:, 0] == ax) & (e[:, 1] == c), 2].mean():+.3f}"
                for ax in (0, 1)
                for c in sorted(set(e[e[:, 0] == ax, 1]))
            )
            corners = np.mean(signed, axis=0).round(3).tolist()
            print(
                f"| {name} | {far:g} | {zoom:g} | {np.mean(module_px):.2f} | {len(errors)} "
                f"| {np.mean(errors):.4f} | {corners} | {by_line} |"
            )


if __name__ == "__main__":
    main()
