"""The one parallel helper (fusion.parallel) and the stages that use it: workers=2 must give
exactly what workers=1 gives (simulate and detect have theirs in test_sim / test_detect)."""

from pathlib import Path

import numpy as np
import pytest

from fusion.log import read_flight
from fusion.parallel import chunk_bounds, parallel_map
from fusion.pipeline import RunConfig, localize_stage
from fusion.qr.detect import detect_flight

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"


def _square_plus(offset: int, x: int) -> int:
    return x * x + offset


@pytest.mark.parametrize("n_items, n_chunks", [(0, 3), (1, 4), (10, 3), (52, 2), (7, 7), (5, 9)])
def test_chunk_bounds_cover_every_item_once_in_order(n_items, n_chunks):
    bounds = chunk_bounds(n_items, n_chunks)
    covered = [i for a, b in bounds for i in range(a, b)]
    assert covered == list(range(n_items))
    assert len(bounds) <= n_chunks
    assert all(b > a for a, b in bounds)


@pytest.mark.parametrize("workers", [1, 2])
def test_parallel_map_keeps_task_order_and_passes_the_context(workers):
    tasks = list(range(23))
    assert list(parallel_map(_square_plus, tasks, workers, 5)) == [t * t + 5 for t in tasks]


@pytest.fixture(scope="module")
def sample_detections():
    return detect_flight(read_flight(SAMPLE), workers=1, progress=False)


def test_localize_on_two_workers_equals_one_worker(sample_detections):
    log = read_flight(SAMPLE)
    one = localize_stage(log, sample_detections, RunConfig(workers=1, progress=False))
    two = localize_stage(log, sample_detections, RunConfig(workers=2, progress=False))
    assert one.trajectories.keys() == two.trajectories.keys()
    for name, traj in one.trajectories.items():
        other = two.trajectories[name]
        assert len(traj) > 0
        np.testing.assert_array_equal(traj.timestamps_ns, other.timestamps_ns)
        np.testing.assert_allclose(traj.T_world_body, other.T_world_body, atol=1e-12)
    for name, obs in one.load_observations.items():
        other = two.load_observations[name]
        assert [(o.timestamp_ns, o.load_id) for o in obs] == [(o.timestamp_ns, o.load_id) for o in other]
        np.testing.assert_allclose([o.p_world for o in obs], [o.p_world for o in other], atol=1e-12)
    a, b = dict(one.stats["pnp"]), dict(two.stats["pnp"])
    # a weighted mean over chunks: equal up to the order of summation
    assert a.pop("mean_reprojection_rms_px") == pytest.approx(b.pop("mean_reprojection_rms_px"), rel=1e-9)
    assert a == b


def _malloc_state(context, task):
    import fusion.parallel

    return fusion.parallel._MALLOC_TUNED


@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_workers_raise_the_malloc_thresholds_once():
    from fusion.parallel import keep_freed_memory

    assert keep_freed_memory() is True
    assert keep_freed_memory() is True  # idempotent
    assert list(parallel_map(_malloc_state, [0, 1], 2)) == [True, True]
