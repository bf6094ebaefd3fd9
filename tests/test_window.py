"""The batch smoother in overlapping windows (fusion.estimate.window): the plan covers the flight,
a windowed solve agrees with the whole-flight one, its covariances are not smaller, and short
flights keep the whole-flight solution exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.errors import EstimationError
from fusion.estimate import FusionConfig, smooth
from fusion.estimate.window import (
    AS_BUILT_WINDOW_S,
    WINDOW_MIN_FLIGHT_S,
    WINDOW_S,
    WindowConfig,
    merge_loads,
    plan_windows,
    smooth_windowed,
)
from fusion.types import LoadEstimate, LoadMap
from tests.test_estimate import FRONT_CAM, make_flight, pos_err

# a 60 s flight in four 22.5 s windows overlapping by 10 s; a 2 s blackout across a cut (42.5 s)
WINDOWS = WindowConfig(window_s=25.0, overlap_s=10.0, min_flight_s=0.0)
POSITION_TOL_M = 1e-3  # windowed vs whole-flight position, every frame
LOAD_TOL_M = 1e-4  # windowed vs whole-flight load position
POSE_COV_TOL = 1e-4  # a pose's covariance may be this much below (linearisation points differ)
LOAD_COV_TOL = 0.01  # a load's merged covariance may be this much (relative) below the whole flight's


@pytest.fixture(scope="module")
def solved():
    fl = make_flight(seed=4, duration_s=60.0, gaps=((20.0, 22.0), (41.0, 43.0)))
    config = FusionConfig()
    whole = smooth(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM, config=config)
    win = smooth_windowed(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM, config=config, window=WINDOWS)
    return fl, whole, win


@pytest.mark.parametrize("seed", range(5))
def test_plan_partitions_the_flight_with_margins(seed):
    rng = np.random.default_rng(seed)
    hz = rng.uniform(10.0, 40.0)
    duration = rng.uniform(60.0, 2000.0)
    cfg = WindowConfig(window_s=rng.uniform(30.0, 300.0), overlap_s=rng.uniform(0.0, 25.0), min_flight_s=0.0)
    frame_t = np.round(np.arange(0.0, duration, 1.0 / hz) * 1e9).astype(np.int64) + 10**9
    t = (frame_t - frame_t[0]) * 1e-9
    plan = plan_windows(frame_t, cfg)
    assert len(plan) == max(1, math.ceil((t[-1] - cfg.overlap_s) / (cfg.window_s - cfg.overlap_s)))
    assert plan[0].first == plan[0].out_first == 0 and plan[-1].stop == plan[-1].out_stop == len(frame_t)
    for a, b in zip(plan, plan[1:]):
        assert a.out_stop == b.out_first  # the outputs partition the frames
        assert t[a.stop - 1] - t[b.first] >= cfg.overlap_s - 2.0 / hz  # they overlap by O
    for w in plan:
        assert w.first <= w.out_first < w.out_stop <= w.stop
        assert t[w.stop - 1] - t[w.first] <= cfg.window_s + 1e-9
        # every output frame is at least O/2 from its window's ends (the flight's ends excepted)
        if w.first > 0:
            assert t[w.out_first] - t[w.first] >= cfg.overlap_s / 2 - 1.0 / hz
        if w.stop < len(frame_t):
            assert t[w.stop - 1] - t[w.out_stop - 1] >= cfg.overlap_s / 2 - 1.0 / hz


def test_short_flight_is_one_window():
    frame_t = np.arange(0, int(WINDOW_MIN_FLIGHT_S * 1e9), int(1e9 / 30), dtype=np.int64)
    plan = plan_windows(frame_t, WindowConfig())
    assert len(plan) == 1 and (plan[0].first, plan[0].stop) == (0, len(frame_t))


def test_bad_window_config_is_refused():
    with pytest.raises(EstimationError, match="overlap_s"):
        plan_windows(np.arange(10, dtype=np.int64), WindowConfig(window_s=10.0, overlap_s=10.0))


def test_windowed_positions_agree_with_the_whole_flight(solved):
    fl, whole, win = solved
    assert len(win.stats["windows"]) == 4
    assert np.array_equal(win.trajectory.timestamps_ns, whole.trajectory.timestamps_ns)
    d = pos_err(win.trajectory.T_world_body, whole.trajectory.T_world_body)
    assert d.max() < POSITION_TOL_M, d.max()
    # and not a much worse estimate of the truth: within 5 % on this worst case, a blackout
    # across a cut with 5 s margins (2.6 % at seed 4; production windows keep 15 s margins)
    rms = [np.sqrt(np.mean(pos_err(r.trajectory.T_world_body, fl.T_true) ** 2)) for r in (whole, win)]
    assert rms[1] < 1.05 * rms[0], rms


def test_windowed_covariances_are_not_smaller(solved):
    _, whole, win = solved
    for P_win, P_whole in zip(win.trajectory.covariances, whole.trajectory.covariances):
        # P_win - P_whole is positive semidefinite: the generalized eigenvalues are >= 1
        L = np.linalg.cholesky(P_whole)
        M = np.linalg.solve(L, np.linalg.solve(L, P_win).T)
        assert np.linalg.eigvalsh(0.5 * (M + M.T)).min() > 1.0 - POSE_COV_TOL


def test_windowed_loads_agree_with_the_whole_flight(solved):
    fl, whole, win = solved
    a, b = whole.loads.by_id(), win.loads.by_id()
    assert set(a) == set(b) == set(fl.loads_true)
    for lid in a:
        assert np.linalg.norm(a[lid].p_world - b[lid].p_world) < LOAD_TOL_M
        assert b[lid].n_obs == a[lid].n_obs  # each sighting used by exactly one window
        assert np.trace(b[lid].cov_world) > (1.0 - LOAD_COV_TOL) * np.trace(a[lid].cov_world)


def test_windowed_stats_and_health(solved):
    _, whole, win = solved
    s = win.stats
    assert s["pose_factors"] > whole.stats["pose_factors"]  # summed: the overlaps are solved twice
    assert sum(w["output_frames"] for w in s["windows"]) == len(whole.trajectory)
    assert s["health"]["iteration_limit_hits"] == 0 and not win.health.loads_dropped
    assert set(s["noise_scales"]["cameras"]) == set(whole.stats["noise_scales"]["cameras"])


def test_short_flight_keeps_the_exact_whole_flight_solution():
    fl = make_flight(seed=2, duration_s=8.0, gaps=())
    a = smooth(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM)
    b = smooth_windowed(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM)
    assert "windows" not in b.stats
    assert np.array_equal(a.trajectory.T_world_body, b.trajectory.T_world_body)
    assert np.array_equal(a.trajectory.covariances, b.trajectory.covariances)


def test_a_window_that_cannot_be_solved_falls_back_to_the_whole_flight():
    fl = make_flight(seed=2, duration_s=30.0, gaps=())

    def failing(frame_t, *args, **kwargs):
        if frame_t[0] > fl.frame_t[0]:
            raise EstimationError("no floor code was read in this flight")
        return smooth(frame_t, *args, **kwargs)

    cfg = WindowConfig(window_s=20.0, overlap_s=5.0, min_flight_s=0.0)
    res = smooth_windowed(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM, window=cfg, solver=failing)
    whole = smooth(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM)
    assert np.array_equal(res.trajectory.T_world_body, whole.trajectory.T_world_body)
    assert any(r.startswith("window 2 of 2 (from 12.5 s) not solvable") for r in res.health.reasons)
    assert "windows" not in res.stats


def test_merge_loads_is_the_information_weighted_mean():
    rng = np.random.default_rng(7)
    covs = []
    for _ in range(3):
        A = rng.normal(size=(3, 3))
        covs.append(A @ A.T + 0.1 * np.eye(3))
    ps = [rng.normal(size=3) for _ in covs]
    maps = [LoadMap("w", [LoadEstimate("A", p, c, 5)]) for p, c in zip(ps, covs)]
    maps[1].loads.append(LoadEstimate("B", np.ones(3), None, 2))
    out = merge_loads(maps, "smoother").by_id()
    info = sum(np.linalg.inv(c) for c in covs)
    P = np.linalg.inv(info)
    assert np.allclose(out["A"].cov_world, P)
    assert np.allclose(out["A"].p_world, P @ sum(np.linalg.solve(c, p) for c, p in zip(covs, ps)))
    assert out["A"].n_obs == 15 and out["B"].n_obs == 2 and np.allclose(out["B"].p_world, 1.0)
    # without a covariance: the mean weighted by sightings
    maps = [
        LoadMap("w", [LoadEstimate("C", np.zeros(3), None, 1)]),
        LoadMap("w", [LoadEstimate("C", np.ones(3), None, 3)]),
    ]
    c = merge_loads(maps, "smoother").by_id()["C"]
    assert c.cov_world is None and np.allclose(c.p_world, 0.75)


def test_merge_window_maps_takes_each_code_from_the_window_that_saw_it_most():
    from fusion.estimate.asbuilt import FloorCodeEstimate, FloorCodeMap, Placement, merge_window_maps

    def code(cid, x, n):
        return FloorCodeEstimate(
            cid, np.zeros(3), np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * x, None, n
        )

    maps = [
        FloorCodeMap("smoother", [code("0/1/0", 0.1, 5), code("0/2/0", 0.2, 9)]),
        FloorCodeMap("smoother", [code("0/1/0", 0.3, 7), code("0/2/0", 0.4, 9), code("0/3/0", 0.5, 1)]),
    ]
    placement = Placement(0.01, math.radians(1.0))
    out = merge_window_maps(maps, "smoother", placement).by_id()
    assert [out[k].p_world[0] for k in ("0/1/0", "0/2/0", "0/3/0")] == [0.3, 0.2, 0.5]  # a tie: the first
    assert [out[k].n_obs for k in ("0/1/0", "0/2/0", "0/3/0")] == [7, 9, 1]
    empty = merge_window_maps([], "smoother", placement)
    assert empty.codes == [] and empty.estimator == "smoother" and empty.placement == placement


def test_cli_option_sets_the_window_and_refuses_a_window_inside_the_overlap(capsys):
    from fusion.cli import _run_config, build_parser
    from fusion.pipeline import _window_config

    args = build_parser().parse_args(["run", "log", "--out", "out", "--smoother-window-s", "0"])
    assert _run_config(args).smoother_window_s == 0.0
    args = build_parser().parse_args(["run", "log", "--out", "out"])
    assert _run_config(args).smoother_window_s is None  # the flight decides:
    assert _window_config(_run_config(args)).window_s == WINDOW_S
    assert _window_config(_run_config(args), as_built=True).window_s == AS_BUILT_WINDOW_S
    args = build_parser().parse_args(["run", "log", "--out", "out", "--smoother-window-s", "180"])
    assert _window_config(_run_config(args), as_built=True).window_s == 180.0  # as asked
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", "log", "--out", "out", "--smoother-window-s", "20"])
    assert "more than the windows' 30 s overlap" in capsys.readouterr().err


def test_pipeline_run_with_windows_writes_every_output(tmp_path, monkeypatch):
    """`fusion run` end to end with the batch smoother in windows (the sample flight is short:
    the threshold and windows shrunk to make three windows of it)."""
    from pathlib import Path

    from fusion import pipeline

    sample = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
    monkeypatch.setattr(
        pipeline,
        "WindowConfig",
        lambda window_s: WindowConfig(window_s=window_s, overlap_s=0.3, min_flight_s=0.0),
    )
    calls = []
    whole = pipeline.smooth

    def counted(frame_t, *args, **kwargs):
        calls.append(len(frame_t))
        return whole(frame_t, *args, **kwargs)

    monkeypatch.setattr(pipeline, "smooth", counted)
    cfg = pipeline.RunConfig(progress=False, incremental=False, smoother_window_s=0.8)
    res = pipeline.run(sample, tmp_path / "out", cfg)
    assert not res.failures
    n = len(res.trajectories["smoother"])
    assert len(calls) >= 2 and sum(calls) > n  # solved in overlapping windows
    assert np.all(np.diff(res.trajectories["smoother"].timestamps_ns) > 0)
    assert res.metrics["trajectories"]["smoother"]["n_poses"] == n
    assert (tmp_path / "out" / "trajectory_smoother.tum").is_file()
    assert (tmp_path / "out" / "report.md").is_file()


def test_as_built_floor_codes_are_windowed_too():
    """A flight with as-built floor codes (codes 1 cm / 1 deg off their payloads) in four windows:
    each window estimates the codes it sees from their priors, each code is taken from the window
    that saw it most, and the result stays consistent with the truth (before, such a flight was
    solved whole whatever its length: 4.2 GB at 30 minutes)."""
    from fusion.estimate.asbuilt import Placement
    from fusion.estimate.health import Status, assess_result
    from fusion.geometry import inv_T, se3_log
    from fusion.sim.trajectory import random_aisle_survey
    from tests.test_asbuilt import _flight

    rng = np.random.default_rng(11)
    placement = Placement(0.01, math.radians(1.0))

    def offsets(ids):
        return np.c_[rng.normal(0, 0.01, (len(ids), 2)), rng.normal(0, math.radians(1.0), len(ids))]

    frame_t, imu, raw, ab, ids, true = _flight(8, 60.0, offsets, placement, placement_in_fixes=True)
    # the whole flight as the pipeline solves it (smooth_windowed: one window, its as-built fixes)
    one = WindowConfig(min_flight_s=math.inf)
    whole = smooth_windowed(frame_t, imu, raw, [], config=FusionConfig(), as_built=ab, window=one)
    win = smooth_windowed(frame_t, imu, raw, [], config=FusionConfig(), as_built=ab, window=WINDOWS)
    assert len(win.stats["windows"]) == 4
    assert win.stats["floor_code_variables"] == len(win.floor_codes.codes) == len(whole.floor_codes.codes)
    T_true = random_aisle_survey(60.0, np.random.default_rng(8)).state(frame_t * 1e-9).T_world_body

    def pose_nees_rms(res):
        T_inv = np.array([inv_T(T) for T in res.trajectory.T_world_body])
        e = se3_log(np.einsum("nij,njk->nik", T_inv, T_true))
        C = res.trajectory.covariances
        nees = np.einsum("ni,ni->n", e, np.linalg.solve(C, e[..., None])[..., 0])
        return float(np.mean(nees)), float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, axis=1))))

    (nees_whole, rms_whole), (nees_win, rms_win) = pose_nees_rms(whole), pose_nees_rms(win)
    assert 3.0 < nees_win < 12.0 and rms_win < 1.5 * rms_whole, (nees_win, rms_win, nees_whole, rms_whole)
    truth = dict(zip(ids, true))
    whole_codes = whole.floor_codes.by_id()
    n2 = []
    for c in win.floor_codes.codes:
        ref = whole_codes[c.code_id]
        assert 0 < c.n_obs <= ref.n_obs  # from one window
        assert np.trace(c.cov_xy_yaw) > 0.99 * np.trace(ref.cov_xy_yaw)  # never surer than the whole flight
        t = truth[c.code_id]
        e = np.r_[c.offset_xy_m - t[:2], math.remainder(c.yaw_rad - t[2], 2 * math.pi)]
        n2.append(e @ np.linalg.solve(c.cov_xy_yaw, e))
    assert 1.0 < np.mean(n2) < 6.0, np.mean(n2)  # 3 dof
    # the health monitor's fixes: each frame's sightings on the codes of the window it comes from
    # (on the merged map's, the windows' different common shifts read as lost fixes: 4.7 % of
    # the 10-minute flight's, BENCHMARKS.md; not on this short one)
    t = win.code_fixes.timestamps_ns
    assert np.array_equal(t, whole.code_fixes.timestamps_ns)
    for res in (whole, win):
        health = assess_result(res, res.code_fixes)
        assert health.status == Status.OK, health.reason
