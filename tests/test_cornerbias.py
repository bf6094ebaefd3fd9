"""The common floor-corner bias (fusion.qr.pnp.bias, fusion.estimate.cornerbias; issue 10.3):
its dilation pattern, the pose's first-order sensitivity, the flight estimate and its gate, the
correction and the consider covariance, and the pipeline's use of them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_pnp import FLOOR_CAM, FOUR, SIGMA, WORLD, aim, body_pose, floor_dets, floor_of, local

from fusion import pipeline
from fusion.estimate.cornerbias import (
    GATE_SIGMAS,
    MAX_BIAS_PX,
    BiasConsider,
    CornerBias,
    correct_pnp_trajectory,
    estimate_corner_bias,
)
from fusion.geometry import inv_T, se3_log
from fusion.qr.pnp import estimate_floor_pose, pnp_trajectory
from fusion.qr.pnp.bias import N_BINS, dilation_pattern, dilation_patterns, frame_bias_terms, size_bin
from fusion.types import Trajectory

B_TRUE = np.array([0.004, 0.012])  # px: about the defocus r 1 flight's (BENCHMARKS.md)


def every_bin(b):
    """A (b_u, b_v) dilation as the bias vector b of every code-size bin."""
    return np.tile(np.asarray(b, dtype=float), N_BINS)


NOISE = 0.02  # px, corner noise of the flights: about the refined corners' on the renders


def biased(dets, b):
    """The detections with each code's edges moved outward by its size bin's dilation in b
    ((2 N_BINS,) px, or one (2,) for every bin)."""
    b = np.asarray(b, dtype=float)
    b = every_bin(b) if len(b) == 2 else b
    out = []
    for d in dets:
        c = np.asarray(d.corners_px, dtype=float)
        j = 2 * size_bin(c)
        out.append(dataclasses.replace(d, corners_px=c + (dilation_pattern(c) @ b[j : j + 2]).reshape(4, 2)))
    return out


def flight_frames(
    n: int, seed: int, b: np.ndarray, heights=(2.3, 2.8), centres=FOUR, first: int = 0
) -> tuple[dict, dict]:
    """{timestamp_ns: floor detections} of n frames over the four codes (corner noise NOISE,
    every code dilated by b) and {timestamp_ns: T_world_body} truth."""
    rng = np.random.default_rng(seed)
    frames, truth = {}, {}
    while len(frames) < n:
        T = aim(
            body_pose(0, 0, rng.uniform(*heights), rng.uniform(-180, 180), *rng.normal(0.0, 2.0, 2)),
            np.mean(centres, axis=0) + rng.normal(0, 0.03, 2),
        )
        ts = (first + len(frames) + 1) * 100_000_000
        try:
            frames[ts] = biased(floor_dets(T, centres, rng=rng, sigma=NOISE, ts=ts), b)
        except AssertionError:  # a code out of view: another pose
            continue
        truth[ts] = T
    return frames, truth


def test_dilation_pattern_moves_each_edge_outward():
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])  # TL TR BR BL, v down
    P = dilation_pattern(square)
    np.testing.assert_allclose((P @ [1.0, 0.0]).reshape(4, 2), [[-1, 0], [1, 0], [1, 0], [-1, 0]], atol=1e-12)
    np.testing.assert_allclose((P @ [0.0, 1.0]).reshape(4, 2), [[0, -1], [0, -1], [0, 1], [0, 1]], atol=1e-12)
    # a rotated code: the moves are along its own edges' normals, weighted by n_u^2 / n_v^2
    c, s = np.cos(0.5), np.sin(0.5)
    rot = (square - 5.0) @ np.array([[c, s], [-s, c]]) + 50.0
    moved = rot + (dilation_pattern(rot) @ [0.3, 0.3]).reshape(4, 2)
    # b_u = b_v: every edge moves out by 0.3 (n_u^2 + n_v^2 = 1): the side grows by 0.6
    np.testing.assert_allclose(np.linalg.norm(moved[1] - moved[0]), 10.6, atol=1e-9)


def test_dilation_patterns_of_many_codes_match_moved_edge_lines():
    """Batch = per code, and each corner is where the two moved edge lines meet (a reference
    built from the lines' intersection, not from the normals' 2x2 solve)."""
    rng = np.random.default_rng(11)
    quads = np.array([[0, 0], [40, 0], [40, 40], [0, 40]], float) + rng.normal(0, 4, (20, 4, 2))
    b = np.array([0.3, -0.2])
    P = dilation_patterns(quads)
    for q, Pq in zip(quads, P):
        np.testing.assert_allclose(Pq, dilation_pattern(q), atol=1e-12)
        centre = q.mean(axis=0)
        lines = []  # (point, direction) of each edge moved outward
        for j in range(4):
            a, e = q[j], q[(j + 1) % 4] - q[j]
            n = np.array([e[1], -e[0]]) / np.linalg.norm(e)
            n = n if n @ (a + 0.5 * e - centre) > 0 else -n
            lines.append((a + (b @ n**2) * n, e))
        for i in range(4):
            (pa, da), (pb, db) = lines[(i - 1) % 4], lines[i]
            s = np.linalg.solve(np.array([da, -db]).T, pb - pa)
            np.testing.assert_allclose(q[i] + Pq[2 * i : 2 * i + 2] @ b, pa + s[0] * da, atol=1e-9)


def test_sensitivity_predicts_the_pose_error_of_a_dilated_frame():
    T = aim(body_pose(0, 0, 2.6, 35.0, roll_deg=4.0, pitch_deg=-3.0), (0.45, 0.6))
    b = np.array([0.05, 0.10])
    res = estimate_floor_pose(floor_of(biased(floor_dets(T, FOUR), b)), FLOOR_CAM, SIGMA)
    terms = frame_bias_terms(FLOOR_CAM, floor_of(floor_dets(T, FOUR)), T, SIGMA)
    xi = local(T, res.T_world_body)
    np.testing.assert_allclose(xi, terms.sensitivity @ every_bin(b), rtol=0.05, atol=1e-7)
    assert np.linalg.norm(xi) > 1e-4  # the dilation does move the pose
    # the pose absorbs part of a dilation, not all: the reduced normal equations see the rest
    seen = np.flatnonzero(np.diag(terms.normal) > 0)  # the size bins of this frame's codes
    assert len(seen) >= 2 and np.all(np.linalg.eigvalsh(terms.normal[np.ix_(seen, seen)]) > 0)


@pytest.mark.parametrize("b, significant", [(B_TRUE, True), (np.zeros(2), False)])
def test_flight_estimate_recovers_the_bias_and_gates_its_absence(b, significant):
    frames, _ = flight_frames(120, seed=3, b=b)
    _, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD, NOISE)
    est = estimate_corner_bias(stats.frame_bias, float(np.mean(stats.frame_chi2) / np.mean(stats.frame_dof)))
    sd = np.sqrt(np.diag(est.covariance_px2))
    seen = sd > 0  # the size bins with codes
    assert 0 < seen.sum() < len(sd)
    assert np.all(np.abs(est.bias_px - every_bin(b))[seen] < 4 * sd[seen]), (est.bias_px, sd)
    assert np.all(est.bias_px[~seen] == 0)
    assert est.significant == significant, est.statistic
    assert est.frames == 120


def test_too_few_frames_give_no_estimate():
    frames, _ = flight_frames(5, seed=1, b=B_TRUE)
    _, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD, NOISE)
    assert estimate_corner_bias(stats.frame_bias, 1.0) is None


def _mean_error_over_sigma(traj: Trajectory, truth: dict) -> np.ndarray:
    T_gt = np.stack([truth[int(t)] for t in traj.timestamps_ns])
    xi = se3_log(np.einsum("nij,njk->nik", inv_T(T_gt), traj.T_world_body))
    return np.mean(xi / np.sqrt(np.einsum("nii->ni", traj.covariances)), axis=0)


def test_correction_removes_the_pose_bias_and_adds_the_consider_covariance():
    frames, truth = flight_frames(120, seed=5, b=B_TRUE)
    traj, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD, NOISE)
    out, report, consider = correct_pnp_trajectory(traj, stats.frame_bias, 1.0)
    assert report["applied"] and consider is not None
    before, after = _mean_error_over_sigma(traj, truth), _mean_error_over_sigma(out, truth)
    assert np.abs(before).max() > 0.3  # the bias is there, common to the frames
    assert np.abs(after).max() < 0.5 * np.abs(before).max(), (before, after)
    S = np.stack([t.sensitivity for t in stats.frame_bias])
    est = estimate_corner_bias(stats.frame_bias, 1.0)
    C = consider.covariance_px2
    # the estimate's noise plus the model's error, taken as large as the correction
    np.testing.assert_allclose(C, est.covariance_px2 + np.outer(est.bias_px, est.bias_px), rtol=1e-12)
    assert [b["bias_px"] for b in report["bins"]] == [
        list(est.bias_px[2 * j : 2 * j + 2]) for j in est.bins()
    ]
    np.testing.assert_allclose(out.covariances - traj.covariances, S @ C @ np.swapaxes(S, 1, 2), atol=1e-18)


def test_consider_knows_the_removed_bias_share_of_the_residuals():
    """BiasConsider.residual_sum_sq = sum_f b^T N_f b = sum_f |M A b|^2: on a noise-free dilated
    flight the residuals are the bias as the poses left it, so it is their whole sum of squares
    (what fusion.estimate.correlation takes off the refined corners' correlation)."""
    rng = np.random.default_rng(9)
    frames = {}
    while len(frames) < 40:
        T = aim(
            body_pose(0, 0, rng.uniform(2.3, 2.8), rng.uniform(-180, 180), 0.0, 0.0), np.mean(FOUR, axis=0)
        )
        ts = (len(frames) + 1) * 100_000_000
        try:
            frames[ts] = biased(floor_dets(T, FOUR, ts=ts), B_TRUE)
        except AssertionError:
            continue
    traj, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD, NOISE)
    _, report, consider = correct_pnp_trajectory(traj, stats.frame_bias, 1.0)
    assert report["applied"] and consider is not None
    est = estimate_corner_bias(stats.frame_bias, 1.0)
    expected = sum(float(est.bias_px @ t.normal @ est.bias_px) for t in stats.frame_bias)
    assert consider.residual_sum_sq == pytest.approx(expected, rel=1e-9)
    seen = sum(float(np.sum(r.whitened.astype(float) ** 2)) for r in stats.frame_code_residuals)
    assert consider.residual_sum_sq == pytest.approx(seen, rel=0.02)


def test_no_significant_bias_leaves_the_trajectory_as_it_is():
    frames, _ = flight_frames(60, seed=2, b=np.zeros(2))
    traj, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD, NOISE)
    out, report, consider = correct_pnp_trajectory(traj, stats.frame_bias, 1.0)
    assert out is traj and consider is None and report["applied"] is False
    off, report, consider = correct_pnp_trajectory(traj, stats.frame_bias, 1.0, apply=False)
    assert off is traj and consider is None
    with pytest.raises(ValueError, match="2 frames of bias terms for 60 PnP poses"):
        correct_pnp_trajectory(traj, stats.frame_bias[:2], 1.0)


def test_consider_covariances_take_the_nearest_frame():
    S = np.zeros((3, 6, 2))
    for k in range(3):
        S[k, k, 0] = k + 1.0
    c = BiasConsider(np.array([100, 200, 300], dtype=np.int64), S, np.diag([1.0, 0.0]))
    out = c.covariances(np.array([0, 140, 160, 251, 999], dtype=np.int64))
    assert [int(np.argmax(np.diag(o))) for o in out] == [0, 0, 1, 2, 2]
    assert out[3][2, 2] == 9.0
    traj = Trajectory("x", np.array([150], dtype=np.int64), np.eye(4)[None], np.eye(6)[None])
    assert c.add_to(traj).covariances[0][0, 0] == 2.0
    assert c.add_to(Trajectory("x", traj.timestamps_ns, traj.T_world_body, None)).covariances is None


@pytest.mark.parametrize("on", [True, False])
def test_the_pipeline_corrects_only_on_the_honest_path(on):
    frames, truth = flight_frames(60, seed=4, b=B_TRUE)
    cfg = pipeline.RunConfig(workers=1, progress=False, correct_corner_bias=on, corner_sigma_px=NOISE)
    part = pipeline.localize_floor_chunk((FLOOR_CAM, WORLD, cfg, None), frames)
    loc = pipeline.merge_floor_parts([part], cfg)
    report = loc.stats["pnp"]["corner_bias"]
    assert report["significant"] and report["applied"] == on
    assert (loc.bias_consider is not None) == on
    raw = part["pnp"]
    changed = not np.allclose(loc.trajectories["pnp"].T_world_body, raw.T_world_body, atol=1e-12)
    assert changed == on


def test_each_code_size_bin_has_its_own_dilation():
    """Low frames (codes ~80 px) dilated by +b, high ones (~53 px) by -b: one dilation for the
    flight would average them away; the size bins recover both."""
    b = np.array([0.0, 0.02])
    low, _ = flight_frames(60, seed=8, b=every_bin(b), heights=(1.45, 1.55), centres=FOUR[:2])
    high, _ = flight_frames(60, seed=9, b=every_bin(-b), heights=(2.2, 2.3), first=100)
    bins = (
        {size_bin(d.corners_px) for f in low.values() for d in f},
        {size_bin(d.corners_px) for f in high.values() for d in f},
    )
    assert len(bins[0]) == len(bins[1]) == 1 and bins[0] != bins[1]  # one bin per height
    _, stats = pnp_trajectory({**low, **high}, FLOOR_CAM, WORLD, NOISE)
    est = estimate_corner_bias(stats.frame_bias, 1.0)
    assert est.bins() == sorted(bins[1] | bins[0])
    sd = np.sqrt(np.diag(est.covariance_px2))
    for (j,), truth in ((bins[0], b), (bins[1], -b)):
        k = slice(2 * j, 2 * j + 2)
        assert np.all(np.abs(est.bias_px[k] - truth) < 4 * sd[k]), (j, est.bias_px[k], sd[k])


def test_an_implausibly_large_dilation_is_reported_not_removed(caplog):
    frames, _ = flight_frames(60, seed=6, b=np.array([0.0, 0.3]))
    traj, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD, NOISE)
    with caplog.at_level("INFO", logger="fusion.estimate.cornerbias"):
        out, report, consider = correct_pnp_trajectory(traj, stats.frame_bias, 1.0)
    assert report["significant"] and report["too_large"] and not report["applied"]
    assert out is traj and consider is None
    assert "corner_bias_too_large" in caplog.text
    # and the run says so by name (it was a log line only: not in the summary, metrics.json or
    # the report)
    from fusion.pipeline import LocalizeResult, corner_bias_too_large_warning

    loc = LocalizeResult({"pnp": traj}, {}, {}, {"pnp": {"corner_bias": report}})
    warning = corner_bias_too_large_warning(loc)
    assert warning is not None and warning.name == "corner_bias_too_large" and warning.count == 1
    assert "0.3" in warning.message and "not removed" in warning.message
    ok = dict(report, too_large=False)
    assert corner_bias_too_large_warning(LocalizeResult({"pnp": traj}, {}, {}, {"pnp": {"corner_bias": ok}})) is None
    assert corner_bias_too_large_warning(LocalizeResult({"pnp": traj}, {}, {}, {"pnp": {}})) is None


def test_a_bin_that_is_not_determined_is_not_judged_and_keeps_the_flight_as_it_is(caplog):
    """100 frames of four ~53 px codes dilated by B_TRUE, and 3 frames of one ~80 px code alone
    (its pose absorbs a dilation: that bin's estimate is a few px with a σ of px, as the 90-128 px
    bin of the 30 ms rolling-shutter bench flights): the gate judges the determined bin only, so
    the flight is significant and not too large (the max-|b|-over-all-bins gate warned
    `corner_bias_too_large`), and, with a bin not determined, its poses are kept (removing the
    determined bins alone was measured worse on the rolling-shutter bench)."""
    high, _ = flight_frames(100, seed=3, b=B_TRUE, heights=(2.2, 2.3))
    low, _ = flight_frames(
        3, seed=4, b=np.array([0.0, 0.3]), heights=(1.45, 1.55), centres=FOUR[:1], first=200
    )
    traj, stats = pnp_trajectory({**high, **low}, FLOOR_CAM, WORLD, NOISE)
    est = estimate_corner_bias(stats.frame_bias, 1.0)
    j_hi, j_lo = (size_bin(next(iter(f.values()))[0].corners_px) for f in (high, low))
    assert j_hi != j_lo
    hi, lo = slice(2 * j_hi, 2 * j_hi + 2), slice(2 * j_lo, 2 * j_lo + 2)
    assert np.all(est.determined[hi]) and not np.any(est.determined[lo])
    assert np.all(GATE_SIGMAS * est.sigma_px[lo] > MAX_BIAS_PX)
    assert np.max(np.abs(est.bias_px[lo])) > MAX_BIAS_PX  # the old gate's "too large"
    assert est.significant and not est.too_large and not est.all_determined
    # the test statistic is the determined bin's alone: b_d^T Cov_dd^-1 b_d
    C = est.covariance_px2[hi, hi]
    assert est.statistic == pytest.approx(float(est.bias_px[hi] @ np.linalg.solve(C, est.bias_px[hi])))
    with caplog.at_level("INFO", logger="fusion.estimate.cornerbias"):
        out, report, consider = correct_pnp_trajectory(traj, stats.frame_bias, 1.0)
    assert out is traj and consider is None and not report["applied"]
    assert [b["determined"] for b in report["bins"]] == [j == j_hi for j in est.bins()]
    assert report["all_determined"] is False and report["too_large"] is False
    assert "corner_bias_too_large" not in caplog.text
    # the same flight without the lone frames: determined, corrected
    traj_hi, stats_hi = pnp_trajectory(high, FLOOR_CAM, WORLD, NOISE)
    _, report_hi, consider_hi = correct_pnp_trajectory(traj_hi, stats_hi.frame_bias, 1.0)
    assert report_hi["applied"] and consider_hi is not None


@pytest.mark.parametrize(
    "b, sigma, too_large, determined",
    [
        (0.12, 0.01, False, True),  # above the limit, but not by 3 σ: still the model's size
        (0.14, 0.01, True, True),  # confidently above
        (0.5, 0.05, False, False),  # not determined: not judged (3 σ > MAX_BIAS_PX)
        (-0.14, 0.01, True, True),  # a shrink as well as a dilation
    ],
)
def test_the_size_gate_calls_a_bin_too_large_only_when_confidently_so(b, sigma, too_large, determined):
    bias = np.zeros(2 * N_BINS)
    bias[2:4] = [0.001, b]
    cov = np.zeros((2 * N_BINS, 2 * N_BINS))
    cov[2:4, 2:4] = np.diag([0.001**2, sigma**2])
    est = CornerBias(bias, cov, statistic=100.0, threshold=13.8, frames=100)
    assert est.too_large == too_large
    assert list(est.determined[2:4]) == [determined] * 2 and not np.any(est.determined[4:])
    assert est.all_determined == determined
