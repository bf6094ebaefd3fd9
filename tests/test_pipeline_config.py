"""RunConfig choices checked at the pipeline boundary: a bad one is one EstimationError line."""

from types import SimpleNamespace

import numpy as np
import pytest

from fusion.errors import EstimationError
from fusion.pipeline import RunConfig, fuse_stage
from fusion.types import Trajectory


def test_unknown_robust_kernel_is_an_estimation_error():
    raw = Trajectory("pnp", np.array([0, 1], np.int64), np.stack([np.eye(4)] * 2), None)
    log = SimpleNamespace(imu=object(), velocity=None)
    loc = SimpleNamespace(trajectories={"pnp": raw})
    with pytest.raises(EstimationError, match="robust kernel 'bogus' is not one of none, huber"):
        fuse_stage(log, loc, RunConfig(robust="bogus"))
