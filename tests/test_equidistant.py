"""The equidistant (fisheye, Kalibr's pinhole-equi) lens: its model against OpenCV's cv2.fisheye
(an independent implementation), its Jacobian, PnP through it, the renderer and the refinement
through it, and every file that states it (sensor.yaml, Kalibr camchain, ROS CameraInfo)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml
import zxingcpp

from fusion.camera import CameraModel
from fusion.conventions import R_BODY_FLOORCAM
from fusion.errors import CameraModelError, LogError, SimulationError
from fusion.geometry import make_T, rot_z
from fusion.qr.detect import detect_frame
from fusion.qr.pnp import estimate_floor_pose, undistort
from fusion.qr.reprojection import Projector
from fusion.sim.render import RenderEffects, placed_floor_codes, project_code_corners, render_view
from tests.test_pnp import FOUR, aim, body_pose, floor_dets, floor_of

K4 = (-0.012, 0.021, -0.006, 0.0009)  # a wide-angle lens's k1..k4, as Kalibr reports them


def fisheye(k=K4, fu=260.0, fv=261.0) -> CameraModel:
    return CameraModel(
        640,
        480,
        fu,
        fv,
        318.0,
        243.0,
        np.array(k),
        make_T(R_BODY_FLOORCAM, [0.05, 0.0, -0.03]),
        distortion_model="equidistant",
    )


def _points(n, rng, half_angle_deg=70.0):
    """Camera-frame points up to half_angle_deg off the axis."""
    a = np.radians(rng.uniform(0, half_angle_deg, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    d = np.column_stack([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)])
    return d * rng.uniform(0.5, 3.0, (n, 1))


def test_projection_and_its_inverse_match_opencv_fisheye():
    cam = fisheye()
    rng = np.random.default_rng(0)
    p = _points(400, rng)
    p[0] = [0.0, 0.0, 1.0]  # the centre, where theta_d / r is a limit
    ref, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist_cv)
    uv = cam.project(p)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(Projector(cam).project(p, jacobian=False)[0], uv, atol=1e-9)
    xy = p[:, :2] / p[:, 2:]
    np.testing.assert_allclose(cam.undistort_normalized(uv), xy, atol=1e-12)
    np.testing.assert_allclose(undistort(cam, uv), xy, atol=1e-10)  # the PnP's fast path
    # far from pinhole: a radial-tangential reading of the same pixels is off by degrees
    as_radtan = CameraModel(640, 480, cam.fu, cam.fv, cam.cu, cam.cv)
    assert np.max(np.abs(as_radtan.undistort_normalized(uv) - xy)) > 0.1


def test_a_radius_beyond_the_lens_is_nan_not_a_wrong_ray():
    cam = fisheye(k=(-0.2, 0.0, 0.0, 0.0))  # theta_d peaks at theta = 74.5 deg, 0.86 rad
    xy = cam.undistort_normalized(
        np.array([[cam.cu + 0.95 * cam.fu, cam.cv], [cam.cu + 0.5 * cam.fu, cam.cv]])
    )
    assert np.all(np.isnan(xy[0])) and np.all(np.isfinite(xy[1]))


def test_projector_jacobian_matches_numerical_derivative():
    cam = fisheye()
    rng = np.random.default_rng(1)
    p = _points(60, rng)
    p[0] = [0.0, 0.0, 1.5]
    p[1] = [1e-10, 0.0, 1.0]
    proj = Projector(cam)
    _, J = proj.project(p)
    h = 1e-6
    Jn = np.stack(
        [
            (proj.project(p + h * e, False)[0] - proj.project(p - h * e, False)[0]) / (2 * h)
            for e in np.eye(3)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(J, Jn, atol=1e-5)


@pytest.mark.parametrize("yaw_deg", [0.0, 35.0, -100.0])
def test_pnp_recovers_the_pose_through_a_fisheye_exactly(yaw_deg):
    cam = fisheye()
    T = aim(body_pose(0, 0, 1.4, yaw_deg, roll_deg=5.0, pitch_deg=-4.0), (0.45, 0.6), camera=cam)
    res = estimate_floor_pose(floor_of(floor_dets(T, FOUR, camera=cam)), cam)
    assert res is not None and res.n_codes == 4
    np.testing.assert_allclose(res.T_world_body, T, atol=1e-9)
    assert res.reprojection_rms_px < 1e-8
    # the same pixels read through a pinhole model: metres off, not a small error
    flat = CameraModel(640, 480, cam.fu, cam.fv, cam.cu, cam.cv, T_body_cam=cam.T_body_cam)
    wrong = estimate_floor_pose(floor_of(floor_dets(T, FOUR, camera=cam)), flat)
    assert wrong is None or np.linalg.norm(wrong.T_world_body[:3, 3] - T[:3, 3]) > 0.05


@pytest.mark.parametrize("k", [K4, (0.0, 0.0, 0.0, 0.0)])
def test_rendered_fisheye_codes_are_decoded_and_refined_to_a_tenth_of_a_pixel(k):
    """The renderer draws through the lens model; the decoder reads the codes on the pinhole image
    of the same intrinsics (zxing on the fisheye image itself read 1 code per view of this grid,
    on the pinhole one 7) and the refinement fits the finder edges through the lens model: every
    refined corner lies within 0.1 px of the projection.  k = 0 is the f-theta lens, not a
    pinhole."""
    cam = fisheye(k)
    grid = placed_floor_codes(np.array([[x, y] for x in range(-3, 4) for y in range(-3, 4)]), 0.4, 0.2)
    by_payload = {c.payload: c for c in grid}
    rng = np.random.default_rng(3)
    errors, n_codes = [], []
    for _ in range(3):
        T_wb = make_T(
            rot_z(rng.uniform(-np.pi, np.pi)), [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.6]
        )
        T_wc = cam.T_world_cam(T_wb)
        img = render_view(cam, T_wc, grid, np.random.default_rng(1), RenderEffects(noise_sigma_dn=1.0))
        dets = detect_frame(img, "cam0", 0, cam)
        n_codes.append(len(dets))
        for det in dets:
            assert det.corner_cov_px2 is not None and det.corner_sigma_px < 0.1  # refined, not raw
            truth = project_code_corners(cam, T_wc, by_payload[det.payload])
            errors.append(np.linalg.norm(det.corners_px - truth, axis=1))
    assert min(n_codes) >= 5, n_codes
    errors = np.concatenate(errors)
    assert errors.max() < 0.1, f"corner errors (px): max {errors.max():.3f} mean {errors.mean():.3f}"


def test_sensor_yaml_states_the_model_and_refuses_an_unknown_one(tmp_path):
    cam = fisheye()
    cam.save(tmp_path / "sensor.yaml")
    back = CameraModel.load(tmp_path / "sensor.yaml")
    assert back.distortion_model == "equidistant" and np.allclose(back.distortion, K4)
    np.testing.assert_allclose(
        back.project(_points(20, np.random.default_rng(2))),
        cam.project(_points(20, np.random.default_rng(2))),
    )
    data = yaml.safe_load((tmp_path / "sensor.yaml").read_text())
    data["distortion_model"] = "fov"
    (tmp_path / "sensor.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(CameraModelError, match=r"sensor\.yaml.*'fov' is not supported"):
        CameraModel.load(tmp_path / "sensor.yaml")


def test_kalibr_pinhole_equi_camchain_is_read_and_written(tmp_path):
    from fusion.log.kalibr import read_camchain, write_camchain

    cam = fisheye()
    write_camchain(tmp_path / "camchain.yaml", {"cam0": cam}, {})
    assert (
        yaml.safe_load((tmp_path / "camchain.yaml").read_text())["cam0"]["distortion_model"] == "equidistant"
    )
    back = read_camchain(tmp_path / "camchain.yaml")["cam0"].camera
    assert back.equidistant and np.allclose(back.distortion, K4)
    np.testing.assert_allclose(back.T_body_cam, cam.T_body_cam, atol=1e-12)
    data = yaml.safe_load((tmp_path / "camchain.yaml").read_text())
    data["cam0"]["distortion_model"] = "fov"
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(LogError, match=r"camchain\.yaml: cam0\.distortion_model: 'fov' is not supported"):
        read_camchain(tmp_path / "camchain.yaml")


@pytest.mark.parametrize("ros1", [True, False])
def test_ros_camera_info_equidistant_round_trip(ros1):
    from fusion.log.rosbag import CAMERA_INFO, camera_from_info, camera_info_msg, typestore_for

    ts = typestore_for(ros1)
    cam = fisheye()
    msg = camera_info_msg(cam, 1_000_000_000, "cam", ros1, ts)
    data = ts.serialize_ros1(msg, CAMERA_INFO) if ros1 else ts.serialize_cdr(msg, CAMERA_INFO)
    back_msg = ts.deserialize_ros1(data, CAMERA_INFO) if ros1 else ts.deserialize_cdr(data, CAMERA_INFO)
    assert back_msg.distortion_model == "equidistant"
    back = camera_from_info(back_msg, "bag")
    assert back.equidistant and np.allclose(back.distortion, K4) and np.allclose(back.K, cam.K)


def test_simulated_fisheye_flight_states_its_lens(tmp_path):
    from fusion.log import read_flight
    from fusion.sim.scenarios import CameraOptions
    from fusion.sim.simulate import simulate

    opts = CameraOptions(distortion_model="equidistant", distortion=K4, focal_scale=0.5)
    simulate(
        tmp_path / "f",
        scenario="default",
        duration_s=1.0,
        seed=2,
        progress=False,
        camera_rate_hz=5.0,
        camera_options=opts,
    )
    flight = read_flight(tmp_path / "f")
    assert len(flight.cameras) == 2
    for stream in flight.cameras.values():
        assert stream.camera.equidistant and np.allclose(stream.camera.distortion, K4)
    with pytest.raises(SimulationError, match="distortion model"):
        CameraOptions(distortion_model="fov")
    # an EuRoC folder whose sensor.yaml gives OpenCV's five radial-tangential coefficients
    sensor = tmp_path / "f" / "mav0" / "cam0" / "sensor.yaml"
    data = yaml.safe_load(sensor.read_text())
    data.update(
        distortion_model="radial-tangential",
        distortion_coefficients=list(CV5),
        intrinsics=[600, 601, 322, 241],
    )
    sensor.write_text(yaml.safe_dump(data))
    cam0 = read_flight(tmp_path / "f").cameras["cam0"].camera
    assert not cam0.equidistant and cam0.k3 == CV5[4] and np.allclose(cam0.distortion, CV5[:4])


# A real lens: the TUM VI dataset's cam0 (Schubert et al., "The TUM VI Benchmark for Evaluating
# Visual-Inertial Odometry", IROS 2018; CC BY 4.0), 512 x 512, Kalibr pinhole-equi, ~190 degrees
# across the diagonal: the image corners lie beyond 90 degrees off the axis.
TUMVI_CAM0 = {
    "camera_model": "pinhole",
    "intrinsics": [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504],
    "distortion_model": "equidistant",
    "distortion_coeffs": [
        0.0034823894022493434,
        0.0007150348452162257,
        -0.0020532361418706202,
        0.00020293673591811182,
    ],
    "resolution": [512, 512],
}


def test_a_real_fisheye_calibration_renders_decodes_and_refines(tmp_path):
    """TUM VI's cam0 read from a Kalibr camchain: pixels beyond 90 degrees have no ray (NaN, and
    the renderer leaves them out instead of culling every code, as it did); a floor grid seen
    from 0.45 m through it: zxing reads 1 code on the fisheye image, the pinhole decode 9, all
    refined within 0.15 px of the projection."""
    from fusion.log.kalibr import read_camchain

    T_cam_imu = np.linalg.inv(make_T(R_BODY_FLOORCAM, [0.0, 0.0, 0.0]))
    block = {**TUMVI_CAM0, "T_cam_imu": T_cam_imu.tolist(), "rostopic": "/cam0/image_raw"}
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump({"cam0": block}))
    cam = read_camchain(tmp_path / "camchain.yaml")["cam0"].camera
    assert cam.equidistant
    corner_and_edge = cam.undistort_normalized(np.array([[0.0, 0.0], [511.0, 511.0], [255.0, 0.0]]))
    assert np.all(np.isnan(corner_and_edge[:2])) and np.all(np.isfinite(corner_and_edge[2]))
    grid = placed_floor_codes(np.array([[x, y] for x in range(-4, 5) for y in range(-4, 5)]), 0.3, 0.15)
    by_payload = {c.payload: c for c in grid}
    T_wc = cam.T_world_cam(make_T(rot_z(0.4), [0.03, 0.01, 0.45]))
    img = render_view(cam, T_wc, grid, np.random.default_rng(1), RenderEffects(noise_sigma_dn=1.0))
    raw = zxingcpp.read_barcodes(img, formats=zxingcpp.BarcodeFormat.QRCode)
    dets = detect_frame(img, "cam0", 0, cam)
    assert len(raw) <= 2 and len(dets) >= 6, (len(raw), len(dets))
    err = [np.abs(d.corners_px - project_code_corners(cam, T_wc, by_payload[d.payload])).max() for d in dets]
    assert max(err) < 0.15, err


# ============================================================================ OpenCV's k3 (radtan)

CV5 = (-0.29, 0.095, 4e-4, -3e-4, -0.014)  # k1, k2, p1, p2, k3 as cv2.calibrateCamera gives them


def radtan5() -> CameraModel:
    return CameraModel(
        640,
        480,
        600.0,
        601.0,
        322.0,
        241.0,
        np.array(CV5[:4]),
        make_T(R_BODY_FLOORCAM, [0.05, 0, -0.03]),
        k3=CV5[4],
    )


def test_radtan_k3_matches_opencv_and_inverts():
    cam = radtan5()
    rng = np.random.default_rng(4)
    p = np.column_stack([rng.uniform(-0.5, 0.5, 200), rng.uniform(-0.38, 0.38, 200), np.ones(200)])
    ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, np.array(CV5))
    np.testing.assert_allclose(cam.project(p), ref.reshape(-1, 2), atol=1e-9)
    uv, J = Projector(cam).project(p)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    h = 1e-6
    proj = Projector(cam)
    Jn = np.stack(
        [
            (proj.project(p + h * e, False)[0] - proj.project(p - h * e, False)[0]) / (2 * h)
            for e in np.eye(3)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(J, Jn, atol=1e-5)
    np.testing.assert_allclose(cam.undistort_normalized(uv), p[:, :2], atol=1e-10)
    np.testing.assert_allclose(undistort(cam, uv), p[:, :2], atol=1e-10)
    T = aim(body_pose(0, 0, 2.6, 35.0, roll_deg=4.0, pitch_deg=-3.0), (0.45, 0.6), camera=cam)
    res = estimate_floor_pose(floor_of(floor_dets(T, FOUR, camera=cam)), cam)
    assert res is not None
    np.testing.assert_allclose(res.T_world_body, T, atol=1e-9)


def test_k3_in_every_file_that_can_state_it(tmp_path):
    from fusion.log.kalibr import read_camchain, write_camchain
    from fusion.log.rosbag import CAMERA_INFO, camera_from_info, camera_info_msg, typestore_for

    cam = radtan5()
    cam.save(tmp_path / "sensor.yaml")
    assert CameraModel.load(tmp_path / "sensor.yaml").k3 == CV5[4]
    write_camchain(tmp_path / "camchain.yaml", {"cam0": cam}, {})
    assert read_camchain(tmp_path / "camchain.yaml")["cam0"].camera.k3 == CV5[4]
    ts = typestore_for(False)
    msg = ts.deserialize_cdr(
        ts.serialize_cdr(camera_info_msg(cam, 0, "cam", False, ts), CAMERA_INFO), CAMERA_INFO
    )
    assert msg.distortion_model == "plumb_bob" and len(msg.d) == 5
    assert camera_from_info(msg, "bag").k3 == CV5[4]
    # without k3 the files stay as they were: four coefficients
    CameraModel(640, 480, 600.0, 601.0, 322.0, 241.0, np.array(CV5[:4])).save(tmp_path / "s4.yaml")
    assert len(yaml.safe_load((tmp_path / "s4.yaml").read_text())["distortion_coefficients"]) == 4
    # the equidistant model has no k3 of its own: refused, not ignored
    with pytest.raises(CameraModelError, match="k3"):
        CameraModel(640, 480, 600.0, 601.0, 322.0, 241.0, np.zeros(4), distortion_model="equidistant", k3=0.1)
    data = yaml.safe_load((tmp_path / "sensor.yaml").read_text())
    data["distortion_coefficients"] = [0.1, 0.0, 0.0]
    (tmp_path / "sensor.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(
        CameraModelError, match=r"sensor\.yaml: 'distortion_coefficients' must be a list of 4"
    ):
        CameraModel.load(tmp_path / "sensor.yaml")


def test_a_lens_that_folds_inside_the_image_is_refused_where_it_is_read(tmp_path):
    """k1 = -0.9 at f = 300 px turns the radial factor negative before the image's corners: its
    inverse there came back 1e14 px off, silently.  sensor.yaml, the camchain, a CameraInfo and
    the simulator's options now refuse it, naming the file / key; ordinary and real lenses (TUM
    VI's fisheye, whose corners lie beyond 90 degrees) pass."""
    from fusion.log.kalibr import read_camchain, write_camchain
    from fusion.log.rosbag import CAMERA_INFO, camera_from_info, camera_info_msg, typestore_for
    from fusion.sim.scenarios import CameraOptions, apply_camera_options, build_scenario

    bad = CameraModel(640, 480, 300.0, 300.0, 320.0, 240.0, np.array([-0.9, 0.0, 0.0, 0.0]))
    assert bad.lens_fold() is not None
    assert radtan5().lens_fold() is None and fisheye().lens_fold() is None
    t = TUMVI_CAM0
    tumvi = CameraModel(
        512, 512, *t["intrinsics"], np.array(t["distortion_coeffs"]), distortion_model="equidistant"
    )
    assert tumvi.lens_fold() is None
    assert fisheye(k=(-0.2, 0.0, 0.0, 0.0)).lens_fold() is not None  # theta_d turns back before 90 deg
    bad.save(tmp_path / "sensor.yaml")
    with pytest.raises(
        CameraModelError, match=r"sensor\.yaml: the radtan distortion .* folds inside the image"
    ):
        CameraModel.load(tmp_path / "sensor.yaml")
    write_camchain(tmp_path / "camchain.yaml", {"cam0": bad}, {})
    with pytest.raises(LogError, match=r"camchain\.yaml: cam0: the radtan distortion .* folds"):
        read_camchain(tmp_path / "camchain.yaml")
    ts = typestore_for(True)
    msg = ts.deserialize_ros1(
        ts.serialize_ros1(camera_info_msg(bad, 0, "cam", True, ts), CAMERA_INFO), CAMERA_INFO
    )
    with pytest.raises(LogError, match="bag: CameraInfo: the radtan distortion .* folds"):
        camera_from_info(msg, "bag")
    with pytest.raises(SimulationError, match="--distortion: .* folds"):
        apply_camera_options(build_scenario("default"), CameraOptions(distortion=(-3.0, 0.0, 0.0, 0.0)))


def test_inspect_says_which_lens_it_read():
    from fusion.log.inspect import lens_line

    assert "equidistant [-0.012, 0.021, -0.006, 0.0009] (k1..k4)" in lens_line("cam0", fisheye())
    assert "radtan [-0.29, 0.095, 0.0004, -0.0003, -0.014] (k1, k2, p1, p2, k3)" in lens_line(
        "cam0", radtan5()
    )
    assert lens_line("cam1", radtan5()).startswith("cam1 lens   : 640x480, f 600.0 / 601.0")
