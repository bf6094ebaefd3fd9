"""Kalibr camchain-imucam.yaml / imu.yaml: the meaning of T_cam_imu and timeshift_cam_imu,
round trips, bad files."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from fusion.camera import CameraModel
from fusion.conventions import R_BODY_FLOORCAM
from fusion.errors import CameraModelError, LogError
from fusion.geometry import inv_T, make_T, rot_z
from fusion.log.euroc import ImuNoise
from fusion.log.kalibr import read_camchain, read_imu_yaml, write_camchain, write_imu_yaml
from fusion.log.ulog import T_FLU_FRD

# Kalibr's own sample output (kalibr wiki, "Yaml formats"; numbers shortened)
CAMCHAIN = """
cam0:
  T_cam_imu:
  - [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975]
  - [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768]
  - [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
  distortion_model: radtan
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  resolution: [752, 480]
  rostopic: /cam0/image_raw
  timeshift_cam_imu: 0.0021
cam1:
  T_cam_imu:
  - [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556]
  - [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024]
  - [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05]
  distortion_model: radtan
  intrinsics: [457.587, 456.134, 379.999, 255.238]
  resolution: [752, 480]
  rostopic: /cam1/image_raw
  timeshift_cam_imu: -0.0005
"""


def _orthonormalise(T):
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T = T.copy()
    T[:3, :3] = U @ Vt
    return T


def test_camchain_meaning(tmp_path):
    data = yaml.safe_load(CAMCHAIN)
    for k in ("cam0", "cam1"):  # the published numbers are orthonormal to 1e-9 only
        data[k]["T_cam_imu"] = _orthonormalise(np.array(data[k]["T_cam_imu"])).tolist()
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(yaml.safe_dump(data))
    cams = read_camchain(path)
    assert sorted(cams) == ["cam0", "cam1"]
    c0 = cams["cam0"]
    assert c0.rostopic == "/cam0/image_raw" and c0.timeshift_ns == 2_100_000
    assert cams["cam1"].timeshift_ns == -500_000
    assert (c0.camera.width, c0.camera.height, c0.camera.fu, c0.camera.cv) == (752, 480, 458.654, 248.375)
    # T_cam_imu maps IMU-frame points into the camera: the IMU origin sits at its translation
    T_cam_imu = np.array(data["cam0"]["T_cam_imu"])
    p_cam_of_imu_origin = T_cam_imu[:3, 3]
    T_body_cam = c0.camera.T_body_cam  # body = IMU here
    np.testing.assert_allclose(inv_T(T_body_cam)[:3, 3], p_cam_of_imu_origin, atol=1e-12)
    # with an FRD IMU (PX4) the body (FLU) pose composes: T_body_cam = T_FLU_FRD inv(T_cam_imu)
    c0_frd = read_camchain(path, T_FLU_FRD)["cam0"].camera
    np.testing.assert_allclose(c0_frd.T_body_cam, T_FLU_FRD @ T_body_cam, atol=1e-12)


def test_camchain_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    cams = {
        "cam0": CameraModel(
            640,
            480,
            500.0,
            501.0,
            320.5,
            239.5,
            rng.normal(0, 0.01, 4),
            make_T(R_BODY_FLOORCAM, [0.01, 0.02, -0.03]),
            rate_hz=30.0,
        ),
        "cam1": CameraModel(
            640,
            480,
            400.0,
            400.0,
            320.0,
            240.0,
            np.zeros(4),
            make_T(rot_z(0.3), [0.1, 0, 0]),
            rate_hz=15.0,
            mount="gimbaled",
        ),
    }
    path = tmp_path / "c.yaml"
    T_bi = make_T(rot_z(0.1), [0.0, 0.01, 0.0])
    write_camchain(path, cams, {"cam0": "/a", "cam1": "/b"}, T_bi, {"cam1": 3_000_000})
    back = read_camchain(path, T_bi)
    for k, cam in cams.items():
        got = back[k].camera
        np.testing.assert_allclose(got.T_body_cam, cam.T_body_cam, atol=1e-14)
        assert (got.fu, got.fv, got.cu, got.cv, got.rate_hz, got.mount) == (
            cam.fu,
            cam.fv,
            cam.cu,
            cam.cv,
            cam.rate_hz,
            cam.mount,
        )
        np.testing.assert_array_equal(got.distortion, cam.distortion)
    assert back["cam1"].timeshift_ns == 3_000_000 and back["cam0"].rostopic == "/a"


def test_camchain_keeps_the_stated_mount_sigmas(tmp_path):
    """A simulated flight states its mount exactly (T_BS_sigma 0 / 0); written as a video log's
    camchain and read back it must still say so, not fall back to the 0.1 deg / 2 mm default
    (the video flight's load maps read NEES 0.0 of 3 on it); unstated stays unstated."""
    stated = CameraModel(
        640,
        480,
        500.0,
        500.0,
        320.0,
        240.0,
        np.zeros(4),
        make_T(R_BODY_FLOORCAM, [0, 0, -0.05]),
        mount_sigma_deg=0.0,
        mount_sigma_m=0.0,
    )
    unstated = CameraModel(640, 480, 400.0, 400.0, 320.0, 240.0, np.zeros(4), make_T(rot_z(0.3), [0.1, 0, 0]))
    other = CameraModel(
        640,
        480,
        400.0,
        400.0,
        320.0,
        240.0,
        np.zeros(4),
        np.eye(4),
        mount_sigma_deg=0.05,
        mount_sigma_m=0.001,
    )
    path = tmp_path / "c.yaml"
    write_camchain(path, {"cam0": stated, "cam1": unstated, "cam2": other}, {})
    back = read_camchain(path)
    assert back["cam0"].camera.mount_sigmas == (0.0, 0.0)
    assert (back["cam1"].camera.mount_sigma_deg, back["cam1"].camera.mount_sigma_m) == (None, None)
    assert (back["cam2"].camera.mount_sigma_deg, back["cam2"].camera.mount_sigma_m) == (0.05, 0.001)
    data = yaml.safe_load(path.read_text())
    data["cam0"]["T_BS_sigma_deg"] = 90.0  # a unit mistake is named, not taken
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(LogError, match=r"cam0: 'T_BS_sigma_deg' must be a number"):
        read_camchain(path)


def test_imu_yaml_both_layouts(tmp_path):
    noise = ImuNoise(1.1e-4, 2.2e-5, 3.3e-3, 4.4e-4)
    flat = tmp_path / "imu.yaml"
    write_imu_yaml(flat, noise, 200.0, "/imu0")
    got = read_imu_yaml(flat)
    assert got.noise == noise and got.rate_hz == 200.0 and got.rostopic == "/imu0"
    nested = tmp_path / "camchain-imucam-imu.yaml"
    nested.write_text(yaml.safe_dump({"imu0": yaml.safe_load(flat.read_text())}))
    assert read_imu_yaml(nested).noise == noise


@pytest.mark.parametrize(
    "edit,match",
    [
        (lambda d: d["cam0"].pop("T_cam_imu"), r"cam0: missing key 'T_cam_imu'"),
        (lambda d: d["cam0"].update(camera_model="omni"), r"cam0.camera_model: 'omni'"),
        (lambda d: d["cam0"].update(distortion_model="omni"), r"cam0.distortion_model"),
        (lambda d: d["cam0"].update(intrinsics=[1, 2, 3]), r"cam0.intrinsics: expected a list of 4"),
        (lambda d: d["cam0"]["T_cam_imu"][0].__setitem__(0, 2.0), r"cam0.T_cam_imu: not a rigid"),
        (lambda d: d["cam0"].update(timeshift_cam_imu="soon"), r"timeshift_cam_imu: not a number"),
        (lambda d: d.clear() or d.update(foo=1), r"no 'cam0' block"),
    ],
)
def test_bad_camchain_names_file_and_key(tmp_path, edit, match):
    data = yaml.safe_load(CAMCHAIN)
    data["cam0"]["T_cam_imu"] = np.eye(4).tolist()
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(LogError, match=match):
        read_camchain(path)


def test_bad_imu_yaml(tmp_path):
    path = tmp_path / "imu.yaml"
    path.write_text("gyroscope_noise_density: 1e-4\n")
    with pytest.raises(LogError, match="imu.yaml: missing key 'gyroscope_random_walk'"):
        read_imu_yaml(path)


@pytest.mark.parametrize("rate", [-200, 0, ".nan"])
def test_an_imu_update_rate_that_is_no_rate_is_refused(tmp_path, rate):
    """`update_rate: -200` was taken silently (second audit's minor points)."""
    path = tmp_path / "imu.yaml"
    keys = (
        "gyroscope_noise_density",
        "gyroscope_random_walk",
        "accelerometer_noise_density",
        "accelerometer_random_walk",
    )
    path.write_text("".join(f"{k}: 1.0e-3\n" for k in keys) + f"update_rate: {rate}\n")
    with pytest.raises(LogError, match=r"imu.yaml: 'update_rate' must be positive"):
        read_imu_yaml(path)


def _camchain_with(tmp_path, camera: str, **keys) -> Path:
    """CAMCHAIN (its T_cam_imu made exactly rigid) with `keys` set in `camera`'s block, written
    to tmp_path/camchain-imucam.yaml."""
    data = yaml.safe_load(CAMCHAIN)
    for k in ("cam0", "cam1"):
        data[k]["T_cam_imu"] = _orthonormalise(np.array(data[k]["T_cam_imu"])).tolist()
    data[camera].update(keys)
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("rate, words", [("thirty", "expected a number"), (-30, "positive")])
def test_a_camchain_rate_that_is_no_rate_names_the_file_and_key(tmp_path, rate, words):
    """`rate_hz: thirty` ended in a ValueError traceback, `-30` was taken (second audit)."""
    path = _camchain_with(tmp_path, "cam1", rate_hz=rate)
    with pytest.raises(LogError, match=rf"camchain-imucam.yaml: cam1.rate_hz: .*{words}"):
        read_camchain(path)


@pytest.mark.parametrize(
    "intrinsics", [[458.654, 457.296, 760.0, 248.375], [458.654, 457.296, 248.375, 767.2]]
)
def test_a_principal_point_outside_the_image_is_refused(tmp_path, intrinsics):
    """cx 642 for a 640 px width was taken (third audit): a principal point outside the image is
    another resolution's calibration or cu / cv swapped, refused naming the file and camera, as
    sensor.yaml's is."""
    path = _camchain_with(tmp_path, "cam0", intrinsics=intrinsics)
    with pytest.raises(
        LogError, match=r"camchain-imucam.yaml: cam0: principal point .* outside the 752x480 image"
    ):
        read_camchain(path)
    cam = CameraModel(752, 480, 458.0, 457.0, 700.0, 240.0)
    cam.save(tmp_path / "sensor.yaml")
    text = (tmp_path / "sensor.yaml").read_text().replace("700.0", "760.0")
    (tmp_path / "sensor.yaml").write_text(text)
    with pytest.raises(CameraModelError, match=r"sensor.yaml: principal point \(760, 240\) px lies outside"):
        CameraModel.load(tmp_path / "sensor.yaml")


def test_a_misspelt_camchain_key_is_named_not_defaulted(tmp_path):
    """`distortion_coefs` (one e) was ignored and the lens taken as distortion-free: PnP 0.07 ->
    4.2 cm with health ok (second audit).  A near miss of a known key is an error naming both;
    other tools' keys pass."""
    data = yaml.safe_load(CAMCHAIN)
    for k in ("cam0", "cam1"):
        data[k]["T_cam_imu"] = _orthonormalise(np.array(data[k]["T_cam_imu"])).tolist()
    data["cam0"]["some_tools_note"] = "kept"
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(yaml.safe_dump(data))
    assert sorted(read_camchain(path)) == ["cam0", "cam1"]
    data["cam0"]["distortion_coefs"] = data["cam0"].pop("distortion_coeffs")
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(
        LogError, match=r"cam0: unknown key 'distortion_coefs' \(did you mean 'distortion_coeffs'\?\)"
    ):
        read_camchain(path)
