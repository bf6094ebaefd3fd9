"""The causal estimators' memory-bounding changes compute exactly what they replaced.

The incremental smoother takes its IMU factors from LazyPims (one interval integrated when it is
reached) instead of a whole-flight problem; imu_subintervals and inlier_raw_mask work in blocks.
Each must equal the whole-flight computation bit for bit (batch = loop).
"""

from __future__ import annotations

import numpy as np
import pytest

from fusion.estimate import common, factors, smoother
from fusion.estimate.common import FusionConfig, inlier_raw_mask, prepare_raw
from fusion.estimate.smoother import LazyPims, imu_coverage, imu_subintervals, preintegrate
from tests.test_estimate import FRONT_CAM, make_flight


@pytest.fixture(scope="module")
def flight():
    # 40 s at 30 fps (1200 frames), a 2 s blackout; IMU holes cut a few intervals below
    return make_flight(seed=3, duration_s=40.0, gaps=((12.0, 14.0),))


def _covered(fl) -> np.ndarray:
    covered = imu_coverage(fl.frame_t, fl.imu, FusionConfig().max_imu_gap_s)
    covered[[100, 101, 500, 777]] = False  # intervals without IMU inside the flight
    return covered


def test_imu_subintervals_in_blocks_equal_whole(flight, monkeypatch):
    covered = _covered(flight)
    whole = imu_subintervals(flight.frame_t, flight.imu, covered)
    monkeypatch.setattr(smoother, "SUBINTERVAL_BLOCK", 97)  # 12 blocks, some cut at a hole
    blocks = imu_subintervals(flight.frame_t, flight.imu, covered)
    for a, b in zip(whole, blocks):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("midpoint", [False, True])
def test_lazy_pims_equal_preintegrate(flight, midpoint):
    covered = _covered(flight)
    params = factors.imu_params(flight.imu.noise, flight.imu.T_body_imu, FusionConfig().integration_sigma)
    eager = preintegrate(flight.frame_t, flight.imu, covered, params, midpoint)
    lazy = LazyPims(flight.frame_t, flight.imu, covered, params, midpoint, keep=2)
    assert sorted(lazy) == sorted(eager) and len(lazy) == len(eager)
    assert 100 not in lazy and 777 not in lazy and -1 not in lazy and len(covered) not in lazy
    assert np.int64(5) in lazy and 5 in lazy and "5" not in lazy and 5.0 not in lazy
    with pytest.raises(KeyError):
        lazy[100]
    rng = np.random.default_rng(0)
    order = list(eager) + rng.permutation(list(eager)).tolist()[:50]  # and again, out of order
    for k in order:
        a, b = eager[k], lazy[k]
        assert a.deltaTij() == b.deltaTij()
        np.testing.assert_array_equal(a.deltaRij().matrix(), b.deltaRij().matrix())
        np.testing.assert_array_equal(a.deltaPij(), b.deltaPij())
        np.testing.assert_array_equal(a.deltaVij(), b.deltaVij())
        np.testing.assert_array_equal(a.preintMeasCov(), b.preintMeasCov())
    assert len(lazy._cache) <= 2


def test_lazy_problem_leaves_out_only_the_imu_factors(flight):
    args = (flight.frame_t, flight.imu, flight.raw, flight.load_obs, FRONT_CAM)
    eager = smoother.build_problem(*args)
    lazy = smoother.build_problem(*args, lazy_imu=True)
    imu = [i for i, f in enumerate(eager.factors) if type(f).__name__ == "CombinedImuFactor"]
    assert len(imu) == len(eager.pims) == len(lazy.pims) > 0
    assert len(lazy.factors) == len(eager.factors) - len(imu)
    assert not any(type(f).__name__ == "CombinedImuFactor" for f in lazy.factors)
    assert lazy.initial.size() == 0 and eager.initial.size() > 0
    np.testing.assert_array_equal(lazy.T_init, eager.T_init)
    assert lazy.counts.as_dict() == eager.counts.as_dict()


def test_inlier_mask_in_blocks_equals_whole(flight, monkeypatch):
    cfg = FusionConfig()
    raw = flight.raw
    T = raw.T_world_body.copy()
    T[[50, 51, 400, 999], :3, 3] += 0.8  # outliers, two of them neighbours
    raw = type(raw)(raw.name, raw.timestamps_ns, T, raw.covariances)
    rawp = prepare_raw(flight.frame_t, raw, cfg)
    monkeypatch.setattr(common, "INLIER_BLOCK", 10**9)
    whole = inlier_raw_mask(rawp, cfg, flight.frame_t)
    monkeypatch.setattr(common, "INLIER_BLOCK", 37)
    blocks = inlier_raw_mask(rawp, cfg, flight.frame_t)
    np.testing.assert_array_equal(whole, blocks)
    assert not whole[[50, 51, 400, 999]].any() and whole.sum() == len(whole) - 4
