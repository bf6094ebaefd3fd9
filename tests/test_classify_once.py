"""The localize stage's chunks classify each frame's codes once (fusion.qr.codes.classify) and
share the result between the paper's Algorithms and PnP: the same outputs as each estimator
classifying on its own, and one classification a frame."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from test_cornerbias import B_TRUE, flight_frames
from test_pnp import FLOOR_CAM, FRONT_CAM, SIGMA, WORLD, body_pose, floor_dets, load_dets

from fusion import pipeline
from fusion.qr import codes, paper
from fusion.qr.pnp import flight as pnp_flight
from fusion.qr.pnp import pnp_load_observations, pnp_trajectory
from fusion.types import QRDetection
from fusion.world import LoadCode

CALLERS = (pipeline, paper, pnp_flight)  # the modules that call classify by name


@pytest.fixture
def classify_calls(monkeypatch):
    """Every classify call of the callers' modules, as the timestamps of its detections."""
    calls: list[tuple[int, ...]] = []

    def counted(dets, world):
        calls.append(tuple(sorted({int(d.timestamp_ns) for d in dets})))
        return codes.classify(dets, world)

    for module in CALLERS:
        monkeypatch.setattr(module, "classify", counted)
    return calls


def _same_trajectory(a, b):
    assert np.array_equal(a.timestamps_ns, b.timestamps_ns)
    assert np.array_equal(a.T_world_body, b.T_world_body)
    if a.covariances is None:
        assert b.covariances is None
    else:
        assert np.array_equal(a.covariances, b.covariances)


def _floor_frames(tracked: bool):
    """40 seeded floor frames; frame 3 with a payload not ours, frame 4 with no detection;
    `tracked`: frame 5 with a tracked copy of one of its codes (decoded, the code is valid for
    the paper; with the copy, PnP drops both as a duplicate), frame 7 with only a tracked code."""
    frames, _ = flight_frames(40, seed=21, b=B_TRUE)
    ts = sorted(frames)
    frames[ts[3]] = frames[ts[3]] + [dataclasses.replace(frames[ts[3]][0], payload="not ours")]
    frames[ts[4]] = []
    if tracked:
        frames[ts[5]] = frames[ts[5]] + [dataclasses.replace(frames[ts[5]][0], tracked=True)]
        frames[ts[7]] = [dataclasses.replace(frames[ts[7]][0], tracked=True)]
    return frames


@pytest.mark.parametrize("tracked", [False, True])
def test_floor_chunk_classifies_each_frame_once_with_the_same_outputs(classify_calls, tracked):
    frames = _floor_frames(tracked)
    cfg = pipeline.RunConfig(workers=1, progress=False, corner_sigma_px=0.02)
    part = pipeline.localize_floor_chunk((FLOOR_CAM, WORLD, cfg, None), frames)
    ts = sorted(frames)
    # one call a frame; with tracked codes, frame 5 once more without its tracked one (the paper)
    once = [(t,) for t in ts if frames[t]] + [()]  # the empty frame's call has no timestamps
    assert sorted(classify_calls) == sorted(once + ([(ts[5],)] if tracked else []))
    assert part["paper_error"] is None
    decoded = {t: kept for t, ds in frames.items() if (kept := [d for d in ds if not d.tracked])}
    _same_trajectory(part["paper"], paper.paper_trajectory(decoded, FLOOR_CAM, WORLD, cfg.th_px))
    assert ts[5] in part["paper"].timestamps_ns and ts[4] not in part["paper"].timestamps_ns
    traj, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD, cfg.corner_sigma_px)
    _same_trajectory(part["pnp"], traj)
    assert part["pnp_stats"].rejections == stats.rejections
    assert stats.rejections.get("duplicate_floor", 0) == (2 if tracked else 0)
    assert stats.rejections["not_ours"] == 1
    assert dataclasses.asdict(part["pnp_stats"]).keys() == dataclasses.asdict(stats).keys()
    assert part["pnp_stats"].n_without_floor_code == stats.n_without_floor_code


def test_front_chunk_classifies_each_frame_once_with_the_same_outputs(classify_calls):
    rng = np.random.default_rng(22)
    floor, front = {}, {}
    box = LoadCode("box-1", (3.5, 0.6, 2.0), math.pi)
    for k in range(12):
        t = (k + 1) * 100_000_000
        T = body_pose(1.0 + 0.05 * k, 0.5, 2.2, 0.0)
        floor[t] = floor_dets(T, [(1, 0), (1, 1)], rng=rng, sigma=SIGMA, ts=t)
        front[t + 10_000_000] = load_dets(T, [box], rng=rng, sigma=SIGMA, ts=t + 10_000_000)
    # a frame long after the last pose (its loads are unposed), and one with a payload not ours
    late = 5_000_000_000
    front[late] = load_dets(body_pose(1.6, 0.5, 2.2, 0.0), [box], ts=late)
    t1 = sorted(front)[1]
    front[t1] = front[t1] + [QRDetection("cam1", t1, "not ours", np.zeros((4, 2)), np.zeros((4, 2)))]
    traj_pnp, _ = pnp_trajectory(floor, FLOOR_CAM, WORLD)
    traj_paper = paper.paper_trajectory(floor, FLOOR_CAM, WORLD)
    expected = {
        "paper": paper.paper_load_observations(front, FRONT_CAM, WORLD, traj_paper, 5.0),
        "pnp": pnp_load_observations(front, FRONT_CAM, WORLD, traj_pnp, 0.3),
    }
    expected["unposed"] = pipeline._unposed_load_observations(
        front, {o.timestamp_ns for o in expected["pnp"]}, FRONT_CAM, WORLD, 0.3
    )
    del classify_calls[:]
    cfg = pipeline.RunConfig(workers=1, progress=False, corner_sigma_px=0.3, th_px=5.0)
    part = pipeline.localize_front_chunk((FRONT_CAM, WORLD, traj_paper, traj_pnp, cfg), front)
    assert sorted(classify_calls) == [(t,) for t in sorted(front)]
    assert part["paper_error"] is None
    for key in ("paper", "pnp", "unposed"):
        assert len(part[key]) == len(expected[key]) > 0, key
        for a, b in zip(part[key], expected[key]):
            assert a.timestamp_ns == b.timestamp_ns and a.load_id == b.load_id
            for name in ("p_world", "cov_world", "p_cam", "cov_cam", "corners_px"):
                x, y = getattr(a, name, None), getattr(b, name, None)
                assert (x is None and y is None) or np.array_equal(x, y), (key, name)
