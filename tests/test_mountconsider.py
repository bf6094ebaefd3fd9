"""The floor camera's stated mount sigma as a consider term on the body poses (mountconsider.py)."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import yaml

from fusion import pipeline
from fusion.conventions import R_BODY_FLOORCAM
from fusion.estimate.mountconsider import add_mount_consider, mount_consider_covariance, mount_sigmas_rad
from fusion.geometry import inv_T, make_T, se3_log, so3_exp
from fusion.log.euroc import read_flight
from fusion.pipeline import RunConfig
from fusion.types import Trajectory

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"


def test_a_mount_error_within_its_sigma_is_covered_by_the_term():
    """Seeded: the camera's pose known exactly, the mount off by w ~ N(0, diag sigma^2) (body
    frame, about the camera: extrinsics.MountRotation); the body pose through the logged mount
    errs by xi = Log(T_true^-1 T_est), whose NEES against the term is chi-square with 3 dof (the
    error is rank 3), and far beyond it against PnP's own sub-mrad covariance alone."""
    rng = np.random.default_rng(18)
    T_body_cam = make_T(R_BODY_FLOORCAM, [0.03, 0.05, -0.06])
    sigma = np.radians([0.5, 0.2, 0.3])
    own = np.diag([1e-8] * 3 + [1e-8] * 3)  # PnP-like: 0.1 mrad, 0.1 mm
    C = own + mount_consider_covariance(T_body_cam, sigma)
    nees, nees_own = [], []
    for _ in range(3000):
        T_true = make_T(so3_exp(rng.normal(0, 0.5, 3)), rng.normal(0, 2, 3))
        w = rng.normal(0, sigma)
        T_bc_true = make_T(so3_exp(w) @ T_body_cam[:3, :3], T_body_cam[:3, 3])
        T_world_cam = T_true @ T_bc_true
        T_est = T_world_cam @ inv_T(T_body_cam)
        xi = se3_log(inv_T(T_true) @ T_est)[0]
        nees.append(xi @ np.linalg.solve(C, xi))
        nees_own.append(xi @ np.linalg.solve(own, xi))
    assert 2.85 < np.mean(nees) < 3.15
    assert np.mean(nees_own) > 1e3


def test_sigmas_stated_and_applied():
    class Cam:
        mount_sigma_deg: float | None = 0.3

    s = mount_sigmas_rad(Cam(), ["y", "z"], np.radians([1.0, 0.02, 0.03]))  # type: ignore[arg-type]
    np.testing.assert_allclose(s, np.radians([0.3, 0.02, 0.03]))
    assert np.all(mount_sigmas_rad(Cam(), [], None) == math.radians(0.3))  # type: ignore[arg-type]
    unstated = Cam()
    unstated.mount_sigma_deg = None  # not stated: no term (the 0.1 deg default is not assumed)
    np.testing.assert_array_equal(mount_sigmas_rad(unstated, [], None), 0.0)  # type: ignore[arg-type]
    np.testing.assert_allclose(
        mount_sigmas_rad(unstated, ["z"], np.radians([1, 1, 0.03])), np.radians([0, 0, 0.03])
    )  # type: ignore[arg-type]
    traj = Trajectory("t", np.array([0]), np.eye(4)[None], np.eye(6)[None])
    assert add_mount_consider(traj, np.zeros((6, 6))) is traj


def _sample_with_mount_sigma(tmp_path: Path, deg: float) -> Path:
    dst = tmp_path / f"log{deg}"
    shutil.copytree(SAMPLE, dst)
    path = dst / "mav0" / "cam0" / "sensor.yaml"
    data = yaml.safe_load(path.read_text())
    data["T_BS_sigma_deg"] = deg
    path.write_text(yaml.safe_dump(data))
    return dst


def test_a_stated_floor_mount_sigma_widens_every_pose_covariance(tmp_path):
    """The sample flight (its mount stated exact) with cam0's T_BS_sigma_deg 0.3: every PnP
    pose carries the term exactly, the fused poses a non-zero PSD widening (it is added after
    the health, to the outputs only); stated exact, nothing is added (the simulator's flights
    keep their results bit for bit).  Before, the stated sigma reached no floor pose: a
    held-out flight with its mount 0.5 / -0.3 / 0.2 deg off and 0.36 deg stated read PnP / EKF
    NEES 1.2e6 / 6.2e4 with the EKF's health ok (4.9 / 3.5 with the term)."""
    cfg = RunConfig(workers=1, progress=False, incremental=False)
    exact = pipeline.run(_sample_with_mount_sigma(tmp_path, 0.0), tmp_path / "o0", cfg, until="smooth")
    log_dir = _sample_with_mount_sigma(tmp_path, 0.3)
    stated = pipeline.run(log_dir, tmp_path / "o3", cfg, until="smooth")
    assert stated.extrinsics is not None and not stated.extrinsics.applied
    T_body_cam = read_flight(log_dir).floor.camera.T_body_cam
    added = mount_consider_covariance(T_body_cam, np.full(3, math.radians(0.3)))
    pnp, pnp0 = stated.trajectories["pnp"], exact.trajectories["pnp"]
    np.testing.assert_array_equal(pnp.T_world_body, pnp0.T_world_body)
    np.testing.assert_allclose(
        pnp.covariances - pnp0.covariances, np.broadcast_to(added, pnp.covariances.shape), atol=1e-15
    )
    for name in ("smoother", "ekf"):
        d = stated.trajectories[name].covariances - exact.trajectories[name].covariances
        assert np.linalg.eigvalsh(d).min() > -1e-12 and np.abs(d).max() > 1e-6
