"""How well the intrinsics are known (sensor.yaml `intrinsics_sigma`, camera.intrinsics_sigmas):
the floor PnP pose's first-order sensitivity to them (fusion.qr.pnp.bias), the front camera's
code centres' (fusion.estimate.loadconsider.intrinsics_jacobian), and a run whose calibration is
off: every output says so in its covariance (fusion.estimate.cornerbias.intrinsics_consider)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from test_pnp import (
    FLOOR_CAM,
    FOUR,
    FRONT_CAM,
    LOADS,
    SIGMA,
    T_FOUR,
    T_FRONT,
    WORLD,
    floor_dets,
    floor_of,
    load_dets,
    local,
)

from fusion.camera import DEFAULT_FOCAL_SIGMA_REL, DEFAULT_PRINCIPAL_POINT_SIGMA_PX, CameraModel
from fusion.errors import CameraModelError, LogError
from fusion.estimate.cornerbias import BiasConsider
from fusion.estimate.loadconsider import intrinsics_jacobian
from fusion.qr.codes import classify
from fusion.qr.pnp import estimate_floor_pose, estimate_load_observations
from fusion.qr.pnp.bias import frame_bias_terms


def misstated(camera: CameraModel, d) -> CameraModel:
    """`camera` as a calibration that is off by d = [dfu, dfv, dcu, dcv] px states it."""
    return dataclasses.replace(
        camera, fu=camera.fu + d[0], fv=camera.fv + d[1], cu=camera.cu + d[2], cv=camera.cv + d[3]
    )


def test_the_floor_pose_sensitivity_predicts_misstated_intrinsics():
    """PnP on corners rendered with the true intrinsics but solved with misstated ones moves by
    S_K d (to first order: within 2 % for d / 100, within 15 % for the pixel-sized d of a real
    calibration); a focal length e too long puts the camera e farther from the floor."""
    dets = floor_of(floor_dets(T_FOUR, FOUR))
    S = frame_bias_terms(FLOOR_CAM, dets, T_FOUR, SIGMA).intrinsics_sensitivity
    for d in ([3.0, 1.8, 0.0, 0.0], [0.0, 0.0, 1.2, -0.7], [-1.5, 2.0, -0.6, 0.9]):
        d = np.asarray(d)
        for k, rtol in ((0.01, 0.02), (1.0, 0.15)):
            xi = local(T_FOUR, estimate_floor_pose(dets, misstated(FLOOR_CAM, k * d), SIGMA).T_world_body)
            assert np.linalg.norm(xi - S @ (k * d)) < rtol * np.linalg.norm(xi), (k, xi, S @ (k * d))
        assert np.linalg.norm(xi) > 1e-3  # the error does move the pose
    e = 0.005
    res = estimate_floor_pose(dets, misstated(FLOOR_CAM, [e * FLOOR_CAM.fu, e * FLOOR_CAM.fv, 0, 0]), SIGMA)
    T_wc, T_wc_est = FLOOR_CAM.T_world_cam(T_FOUR), FLOOR_CAM.T_world_cam(res.T_world_body)
    assert T_wc_est[2, 3] - T_wc[2, 3] == pytest.approx(e * T_wc[2, 3], rel=0.1)


def test_the_front_code_centre_jacobian_predicts_misstated_intrinsics():
    """The loads' first-order d p_cam / d [fu, fv, cu, cv] (a frontal code's) against single-code
    PnP solved with misstated intrinsics: within 10 % of the move, for codes up to ~20 deg off
    the axis.  Focal lengths off in opposite directions are not first order (PnP reads the
    stretched square as a tilted one, its depth from the longer side: loadconsider's docstring)."""
    codes = classify(load_dets(T_FRONT, LOADS), WORLD).loads
    exact = estimate_load_observations(codes, FRONT_CAM, WORLD, T_FRONT)
    for d in ([3.0, 3.0, 0.0, 0.0], [-2.0, -2.0, 0.0, 0.0], [0.0, 0.0, 1.5, -1.0]):
        moved = estimate_load_observations(codes, misstated(FRONT_CAM, d), WORLD, T_FRONT)
        for a, b in zip(exact, moved):
            shift = b.p_cam - a.p_cam
            predicted = intrinsics_jacobian(FRONT_CAM, a.p_cam)[0] @ np.asarray(d)
            assert np.linalg.norm(shift - predicted) < 0.1 * np.linalg.norm(shift), (d, shift, predicted)


def test_intrinsics_sigma_in_sensor_yaml_and_camchain(tmp_path):
    data = FLOOR_CAM.to_sensor_yaml()
    assert "intrinsics_sigma" not in data  # not stated: not written
    f = DEFAULT_FOCAL_SIGMA_REL
    c = DEFAULT_PRINCIPAL_POINT_SIGMA_PX
    np.testing.assert_allclose(
        CameraModel.from_sensor_yaml(data).intrinsics_sigmas, [f * FLOOR_CAM.fu, f * FLOOR_CAM.fv, c, c]
    )
    stated = CameraModel.from_sensor_yaml({**data, "intrinsics_sigma": [0.9, 0.8, 0.5, 0.4]})
    np.testing.assert_allclose(stated.intrinsics_sigmas, [0.9, 0.8, 0.5, 0.4])
    assert stated.to_sensor_yaml()["intrinsics_sigma"] == [0.9, 0.8, 0.5, 0.4]
    for bad in ([1, 2, 3], [-1, 0, 0, 0], [200.0, 0, 0, 0], ["1px", 0, 0, 0]):
        with pytest.raises(CameraModelError, match="cam0/sensor.yaml.*intrinsics_sigma"):
            CameraModel.from_sensor_yaml({**data, "intrinsics_sigma": bad}, "cam0/sensor.yaml")

    from fusion.log.kalibr import read_camchain, write_camchain

    path = tmp_path / "camchain.yaml"
    write_camchain(path, {"cam0": stated, "cam1": FRONT_CAM}, {})
    back = read_camchain(path)
    np.testing.assert_allclose(back["cam0"].camera.intrinsics_sigmas, [0.9, 0.8, 0.5, 0.4])
    assert back["cam1"].camera.intrinsics_sigma_px is None
    text = path.read_text().replace("intrinsics_sigma: [0.9", "intrinsics_sigma: [-0.9", 1)
    path.write_text(text)
    with pytest.raises(LogError, match="cam0.intrinsics_sigma"):
        read_camchain(path)


def test_the_focal_lengths_errors_are_one():
    """fu and fv off by one factor (their ratio, the pixel aspect, is known far better), the
    principal point's independent."""
    from fusion.estimate.cornerbias import intrinsics_covariance

    C = intrinsics_covariance(np.array([1.2, 1.1, 1.0, 0.5]))
    np.testing.assert_allclose(C, [[1.44, 1.32, 0, 0], [1.32, 1.21, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 0.25]])
    assert np.linalg.matrix_rank(C) == 3


def test_the_consider_is_averaged_over_the_window():
    """A fused pose's share spans the sensitivities of the fixes around it (rank 6 where one
    frame's is rank 1 here); without a window, the nearest frame's."""
    t = np.arange(5) * 100_000_000
    S = np.zeros((5, 6, 1), dtype=np.float32)
    for i in range(5):
        S[i, i, 0] = 1.0
    c = BiasConsider(t, S, np.eye(1))
    np.testing.assert_allclose(c.covariances(t[2:3])[0], np.diag([0, 0, 1.0, 0, 0, 0]))
    avg = c.covariances(t[2:3], window_s=0.1)[0]
    np.testing.assert_allclose(avg, np.diag([0, 1, 1, 1, 0, 0]) / 3.0)
    far = c.covariances(np.array([10_000_000_000]), window_s=0.1)[0]  # no frame near: the nearest
    np.testing.assert_allclose(far, np.diag([0, 0, 0, 0, 1.0, 0]))


@pytest.fixture(scope="module")
def miscalibrated(tmp_path_factory):
    """A short simulated flight whose floor camera's sensor.yaml states a focal length 0.5 %
    too long, run as it is (no intrinsics_sigma: the default 0.2 %) and stating it exact."""
    from fusion.fileio import dump_yaml, load_yaml
    from fusion.pipeline import RunConfig, run
    from fusion.sim.simulate import simulate

    root = tmp_path_factory.mktemp("intrinsics")
    log = root / "log"
    simulate(log, duration_s=6.0, seed=5, workers=1, progress=False)
    path = log / "mav0" / "cam0" / "sensor.yaml"
    data = load_yaml(path)
    assert data["intrinsics_sigma"] == [0.0, 0.0, 0.0, 0.0]  # the simulator's are exact
    fu, fv, cu, cv = data["intrinsics"]
    data["intrinsics"] = [fu * 1.005, fv * 1.005, cu, cv]
    out = {}
    for name, sigma in (("stated_exact", [0.0] * 4), ("default", None)):
        if sigma is None:
            data.pop("intrinsics_sigma")
        else:
            data["intrinsics_sigma"] = sigma
        dump_yaml(data, path)
        run(log, root / name, RunConfig(workers=1, progress=False, force=True))
        out[name] = json.loads((root / name / "metrics.json").read_text())
    return out


def test_a_misstated_focal_length_is_in_every_outputs_covariance(miscalibrated):
    """0.5 % too long: every pose ~0.5 % too high (a few mm at the flight's height), which no
    back end can average away.  Stated exact, the outputs claim a tenth of a millimetre (NEES in
    the thousands); with the default 0.2 % it is a 2.5-sigma error of every output."""
    for name in ("pnp", "smoother", "incremental", "ekf"):
        exact = miscalibrated["stated_exact"]["trajectories"][name]
        default = miscalibrated["default"]["trajectories"][name]
        assert exact["axis"]["bias_z_m"] > 0.003  # the camera reads itself higher
        assert exact["nees_pose_6dof"]["nees_mean"] > 500, name
        assert default["nees_pose_6dof"]["nees_mean"] < 25, name
        for loads in ("stated_exact", "default"):
            assert miscalibrated[loads]["load_maps"][name]["nees_3dof"]["n"] > 0
        assert miscalibrated["default"]["load_maps"][name]["nees_3dof"]["nees_mean"] < 15, name
        assert miscalibrated["stated_exact"]["load_maps"][name]["nees_3dof"]["nees_mean"] > 100, name
    # the run says what it assumed for the camera that states nothing
    said = [n for n in miscalibrated["default"]["notes"] if "intrinsics_sigma" in n]
    assert len(said) == 1 and said[0].startswith("cam0: ") and "0.2 %" in said[0]
    assert not [n for n in miscalibrated["stated_exact"]["notes"] if "intrinsics_sigma" in n]


def test_inspect_says_how_well_each_camera_is_known():
    """`fusion inspect` lists each camera's intrinsics and mount sigma, stated or assumed."""
    from fusion.log.inspect import calibration_line

    line = calibration_line("cam0", FLOOR_CAM)
    assert "fu 1.2 fv 1.2 cu 1 cv 1 px (assumed: not in sensor.yaml)" in line
    assert "mount sigma not stated (the run's mount check measures it)" in line
    stated = dataclasses.replace(FRONT_CAM, intrinsics_sigma_px=(0.5, 0.5, 0.3, 0.3))
    line = calibration_line("cam1", stated)
    assert "fu 0.5 fv 0.5 cu 0.3 cv 0.3 px (stated)" in line
    assert "mount sigma 0.1 deg, 2 mm (assumed: not in sensor.yaml)" in line
