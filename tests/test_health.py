"""fusion.estimate.health: the consistency monitor's statuses on runs whose truth is known."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from fusion.errors import EstimationError
from fusion.estimate.common import FusionResult
from fusion.estimate.ekf import EkfRecovery
from fusion.estimate.health import (
    Health,
    HealthConfig,
    Status,
    assess,
    assess_result,
    fix_nis,
    tilt_disagreement,
    tilt_nis,
)
from fusion.types import LoadMap, Trajectory
from tests.test_ekf import ekf, faulty, make_flight

SIGMA_ROT_RAD = math.radians(0.03)


@pytest.fixture(scope="module")
def healthy():
    fl = make_flight(seed=21)
    return fl, ekf(fl)


def fused_from_truth(fl, sigma_pos=0.001, sigma_rot=SIGMA_ROT_RAD, seed=0, drift=None):
    """A fused trajectory = truth * Exp(n) with a stated covariance; `drift` (m/s) moves it away
    from the truth linearly in time."""
    rng = np.random.default_rng(seed)
    cov = np.diag([sigma_rot**2] * 3 + [sigma_pos**2] * 3)
    xi = rng.multivariate_normal(np.zeros(6), cov, size=len(fl["frame_t"]))
    T = np.array([Tt @ gtsam.Pose3.Expmap(x).matrix() for Tt, x in zip(fl["T_true"], xi)])
    if drift is not None:
        T[:, :3, 3] += np.outer(fl["frame_t"] * 1e-9, drift)
    return Trajectory("fused", fl["frame_t"].copy(), T, np.repeat(cov[None], len(T), 0))


def test_healthy_run_is_ok(healthy):
    fl, res = healthy
    h = assess_result(res, fl["raw"])
    assert isinstance(h, Health)
    assert h.status == Status.OK, h.reason
    assert h.coverage == 1.0 and h.lost_share == 0.0
    # the windowed mean NIS (per dimension) of a consistent run lies around or below 1
    assert 0.2 < np.median(h.window_nis) < 1.5
    d = h.to_dict()
    assert d["status"] == "ok" and d["reason"] == "consistent with the raw fixes"


def test_runaway_ekf_is_diverged():
    """Gyro dead band, plain gated filter: it runs away although fixes arrive at every frame."""
    fl = faulty(make_flight(seed=22, duration_s=15.0), "dead_band")
    res = ekf(fl, recovery=EkfRecovery(enabled=False))
    h = assess_result(res, fl["raw"])
    assert h.status == Status.DIVERGED
    assert "lost the raw fixes" in h.reason and h.lost_share > 0.5


def test_many_gated_fixes_degraded(healthy):
    fl, res = healthy
    h = assess(res.trajectory, fl["raw"], gated_fraction=0.2)
    assert h.status == Status.DEGRADED and "20 % of the fixes gated" in h.reason
    assert assess(res.trajectory, fl["raw"], gated_fraction=0.6).status == Status.DIVERGED


def test_iteration_limit_resets_and_inflation_degrade(healthy):
    fl, res = healthy
    assert assess(res.trajectory, fl["raw"], iteration_limit_hits=1).status == Status.DEGRADED
    assert assess(res.trajectory, fl["raw"], resets=2).status == Status.DEGRADED
    assert assess(res.trajectory, fl["raw"], inflated_fraction=0.2).status == Status.DEGRADED
    stats = dict(res.stats, iterations=100)
    hit = assess_result(FusionResult(res.trajectory, LoadMap("ekf"), stats), fl["raw"], max_iterations=100)
    assert hit.iteration_limit_hits == 1 and hit.status == Status.DEGRADED


def test_overconfident_estimate_degraded():
    """Right on average but claiming half the sigma than it has; fixes honest."""
    fl = make_flight(seed=23)
    fused = fused_from_truth(fl, sigma_pos=0.004, sigma_rot=math.radians(0.1))
    fused.covariances = fused.covariances / 4.0
    h = assess(fused, fl["raw"])
    assert h.status == Status.DEGRADED
    assert h.overconfident_windows > 0 and "overconfident" in h.reason
    honest = fused_from_truth(fl, sigma_pos=0.004, sigma_rot=math.radians(0.1))
    assert assess(honest, fl["raw"]).status == Status.OK


def test_drift_diverged_and_misreads_ok():
    """A fused estimate drifting 5 cm/s away is DIVERGED; an exact one judged against fixes of
    which 5 % are misreads (1-3 m off) stays OK: single fixes do not make an estimate wrong."""
    fl = make_flight(seed=24)
    assert assess(fused_from_truth(fl, drift=[0.05, 0.0, 0.0]), fl["raw"]).status == Status.DIVERGED
    rng = np.random.default_rng(1)
    raw = fl["raw"]
    T = raw.T_world_body.copy()
    bad = rng.choice(len(T), size=len(T) // 20, replace=False)
    T[bad, :2, 3] += rng.uniform(1, 3, (len(bad), 2))
    misread = Trajectory("pnp", raw.timestamps_ns, T, raw.covariances)
    h = assess(fused_from_truth(fl), misread)
    assert h.status == Status.OK, h.reason
    assert 0.03 < h.inconsistent_share < 0.07


def test_short_loss_is_degraded_not_diverged():
    """A 2.5 s run of wrong fixes (a misprinted code) against a right estimate: one or two lost
    windows, not in a long run: DEGRADED with the reason, not DIVERGED; the same share lost for
    good (the fixes 1 m off from 8 s on, the estimate stuck) is DIVERGED."""
    fl = make_flight(seed=25)
    raw = fl["raw"]
    t = raw.timestamps_ns * 1e-9
    T = raw.T_world_body.copy()
    T[(t >= 6.0) & (t < 8.5), 0, 3] += 1.0
    h = assess(fused_from_truth(fl), Trajectory("pnp", raw.timestamps_ns, T, raw.covariances))
    assert h.status == Status.DEGRADED and "for at most" in h.reason
    T = raw.T_world_body.copy()
    T[t >= 8.0, 0, 3] += 1.0
    h = assess(fused_from_truth(fl), Trajectory("pnp", raw.timestamps_ns, T, raw.covariances))
    assert h.status == Status.DIVERGED and h.lost_run >= 2


def test_covariance_growth_and_coverage(healthy):
    fl, res = healthy
    tr = res.trajectory
    grown = Trajectory(tr.name, tr.timestamps_ns, tr.T_world_body, tr.covariances.copy())
    grown.covariances[len(tr) // 2, 3:, 3:] = np.eye(3)  # 1 m sigma once
    h = assess(grown, fl["raw"])
    assert h.status == Status.DEGRADED and h.max_sigma_m == pytest.approx(1.0)
    grown.covariances[len(tr) // 2, 3:, 3:] = np.eye(3) * 400.0  # 20 m
    assert assess(grown, fl["raw"]).status == Status.DIVERGED
    half = Trajectory(
        tr.name,
        tr.timestamps_ns[len(tr) // 2 :],
        tr.T_world_body[len(tr) // 2 :],
        tr.covariances[len(tr) // 2 :],
    )
    h = assess(half, fl["raw"])
    assert h.status == Status.DEGRADED and h.coverage == pytest.approx(0.5, abs=0.01)
    assert assess(Trajectory.empty("ekf"), fl["raw"]).status == Status.DIVERGED
    with pytest.raises(EstimationError):
        assess(tr, Trajectory.empty("pnp"))


def test_position_yaw_fixes_without_covariance(healthy):
    """The paper's estimator (no covariance): 4-d innovation with HealthConfig's sigmas."""
    fl, res = healthy
    raw = fl["raw"]
    paper = Trajectory("paper", raw.timestamps_ns, raw.T_world_body, None)
    idx, _nis, dim = fix_nis(res.trajectory, paper)
    assert dim == 4 and len(idx) == len(raw)
    assert assess(res.trajectory, paper).status == Status.OK
    tight = HealthConfig(raw_sigma_xyz_m=1e-5, raw_sigma_yaw_rad=1e-6)
    fused_nocov = Trajectory("f", res.trajectory.timestamps_ns, res.trajectory.T_world_body, None)
    assert assess(fused_nocov, paper, config=tight).status != Status.OK


def test_status_is_str_valued():
    assert Status.DIVERGED == "diverged" and str(Status.OK) == "ok"


def test_level_fixes_compare_position_and_yaw_only():
    """A gimbaled floor camera gives level-frame poses: a fused body that is tilted 8 degrees
    but agrees in position and yaw is consistent with them (NIS over position + yaw only)."""
    from fusion.estimate.health import fix_nis
    from fusion.geometry import R_from_euler, make_T

    rng = np.random.default_rng(3)
    n = 200
    t = np.arange(n, dtype=np.int64) * 33_000_000
    yaw = np.linspace(-3.0, 3.0, n)
    T_body = np.stack(
        [make_T(R_from_euler("ZYX", [y, 0.14, -0.1]), [0.01 * k, 1.0, 1.2]) for k, y in enumerate(yaw)]
    )
    T_level = T_body.copy()
    sig_p, sig_yaw = 0.002, 0.001
    for k in range(n):
        T_level[k, :3, :3] = R_from_euler("Z", yaw[k] + rng.normal(0, sig_yaw))
        T_level[k, :3, 3] += rng.normal(0, sig_p, 3)
    cov = np.tile(np.diag([np.radians(10) ** 2] * 2 + [sig_yaw**2] + [sig_p**2] * 3), (n, 1, 1))
    fused = Trajectory("smoother", t, T_body, np.tile(np.eye(6) * 1e-12, (n, 1, 1)))
    raw = Trajectory("pnp", t, T_level, cov)
    idx, nis, dim = fix_nis(fused, raw, level_fixes=True)
    assert dim == 4 and len(idx) == n
    assert 2.5 < nis.mean() < 6.0  # chi-square with 4 dof: mean 4
    assert assess(fused, raw, level_fixes=True).status == Status.OK


# ---------------------------------------------------------------- tilt of level-frame fixes


def _tilted(T_true: np.ndarray, sigma_rad: float, offset_rad: np.ndarray, rng) -> Trajectory:
    """Estimates of T_true whose roll / pitch err by N(0, sigma^2) plus a constant offset
    (body frame), reported with sigma (roll / pitch) and 1 mm / 1 mrad elsewhere."""
    xi = np.zeros((len(T_true), 6))
    xi[:, :2] = rng.normal(0.0, sigma_rad, (len(T_true), 2)) + offset_rad
    T = np.array([t @ gtsam.Pose3.Expmap(x).matrix() for t, x in zip(T_true, xi)])
    cov = np.diag([sigma_rad**2] * 2 + [1e-6] + [1e-6] * 3)
    stamps = np.arange(len(T_true), dtype=np.int64) * 33_333_333
    return Trajectory("x", stamps, T, np.repeat(cov[None], len(T_true), 0))


def test_tilt_disagreement_names_the_estimate_the_others_contradict():
    """A gimbaled floor camera's fixes do not see roll / pitch; among three fused estimates
    the one whose tilt is 20 mrad off with a 2 mrad sigma is named, the two consistent ones
    (5 mrad sigma) are not; with two estimates that disagree both are; consistent ones never.
    (The incremental smoother on the sweep's gimbaled flights: NEES 480 / 462, health ok.)"""
    rng = np.random.default_rng(14)
    yaw = np.linspace(0.0, 3.0, 300)
    T_true = np.array(
        [gtsam.Pose3(gtsam.Rot3.Ypr(y, 0.0, 0.2 * math.sin(y)), gtsam.Point3(y, 0, 1)).matrix() for y in yaw]
    )
    good_a = _tilted(T_true, 0.005, np.zeros(2), rng)
    good_b = _tilted(T_true, 0.005, np.zeros(2), rng)
    wrong = _tilted(T_true, 0.002, np.array([0.0, 0.02]), rng)
    assert np.mean(tilt_nis(good_a, good_b)) < 2 * 1.5  # ~2 (dof) when consistent
    out = tilt_disagreement({"smoother": good_a, "incremental": wrong, "ekf": good_b})
    assert list(out) == ["incremental"] and "roll / pitch disagree with smoother, ekf" in out["incremental"]
    assert set(tilt_disagreement({"smoother": good_a, "ekf": wrong})) == {"smoother", "ekf"}
    assert tilt_disagreement({"smoother": good_a, "ekf": good_b}) == {}
    assert tilt_disagreement({"smoother": good_a}) == {}
