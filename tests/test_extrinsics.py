"""Floor camera mount rotation (fusion.estimate.extrinsics, issue 11 item 5): the factor's
Jacobians, recovery of a 2 deg error on short synthetic flights, an honest (large) sigma on an
axis the flight does not excite, the simulator's wrong calibration, and the check's warning and
--calibrate-extrinsics end to end on the sample flight."""

import json
import math
import shutil
from pathlib import Path

import gtsam
import numpy as np
import pytest

from fusion.camera import CameraModel
from fusion.cli import main
from fusion.conventions import R_BODY_FLOORCAM, R_BODY_FRONTCAM
from fusion.errors import EstimationError
from fusion.estimate.extrinsics import (
    EXTRINSICS_GROUNDTRUTH_CSV,
    FRONT_WARNING_NAME,
    WARNING_NAME,
    ExtrinsicsConfig,
    MountRotation,
    MountSource,
    check_mount,
    corrected_camera,
    corrected_mount,
    estimate_front_mount,
    estimate_mount_and_states,
    estimate_mount_rotation,
    merge_mount_rotations,
    mount_pose_error,
    read_extrinsics_groundtruth,
)
from fusion.estimate.window import WindowConfig, estimate_mount_windowed, plan_windows
from fusion.fileio import dump_yaml, load_yaml
from fusion.geometry import inv_T, make_T, so3_exp, so3_log
from fusion.log.euroc import CameraStream, FlightLog, ImuNoise, read_flight
from fusion.log.files import read_tum
from fusion.sim.imu import synthesize_imu
from fusion.sim.simulate import simulate
from fusion.sim.trajectory import Keyframe, KeyframeTrajectory, random_aisle_survey
from fusion.types import LoadObservation, Trajectory

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
FLOOR_CAM = CameraModel(
    640, 480, 550.0, 550.0, 320.0, 240.0, T_body_cam=make_T(R_BODY_FLOORCAM, [0.05, 0.0, -0.06])
)
SIGMA_POS_M, SIGMA_ROT_RAD = 0.002, math.radians(0.05)
TARGET_DEG = 0.05  # the accuracy for a 2 deg error


def _pnp_poses(traj, duration_s: float, w_deg, rng) -> tuple[np.ndarray, Trajectory]:
    """PnP-like body poses at 30 Hz computed with the nominal mount while the camera sits at the
    true one (turned by w_deg): Z = T_world_body_true T_bc_true T_bc_nominal^-1 exp(noise)."""
    t = np.round(np.arange(0.0, duration_s, 1 / 30.0) * 1e9).astype(np.int64)
    T_true = traj.state(t * 1e-9).T_world_body
    E = corrected_mount(FLOOR_CAM.T_body_cam, np.radians(w_deg)) @ inv_T(FLOOR_CAM.T_body_cam)
    cov = np.diag([SIGMA_ROT_RAD**2] * 3 + [SIGMA_POS_M**2] * 3)
    xi = rng.standard_normal((len(t), 6)) @ np.linalg.cholesky(cov).T
    Z = np.array([T @ E @ gtsam.Pose3.Expmap(x).matrix() for T, x in zip(T_true, xi)])
    return t, Trajectory("pnp", t, Z, np.repeat(cov[None], len(t), 0))


def _survey(duration_s: float, seed: int, w_deg):
    rng = np.random.default_rng(seed)
    traj = random_aisle_survey(duration_s, rng)
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), rng)
    t, raw = _pnp_poses(traj, duration_s, w_deg, rng)
    return t, imu, raw


# ============================================================================ the factor


def test_mount_pose_error_jacobians_match_numerical_derivatives():
    rng = np.random.default_rng(3)
    Z = gtsam.Pose3.Expmap(rng.standard_normal(6))
    A = gtsam.Pose3(gtsam.Rot3(), rng.standard_normal(3) * 0.1)
    X = gtsam.Pose3.Expmap(rng.standard_normal(6))
    R = gtsam.Rot3.Expmap(rng.standard_normal(3) * 0.05)
    e, Hx, Hr = mount_pose_error(Z, A, X, R, True)
    assert Hx is not None and Hr is not None
    h = 1e-6
    num_x = np.column_stack(
        [
            (
                mount_pose_error(Z, A, X.retract(h * d), R, False)[0]
                - mount_pose_error(Z, A, X.retract(-h * d), R, False)[0]
            )
            / (2 * h)
            for d in np.eye(6)
        ]
    )
    num_r = np.column_stack(
        [
            (
                mount_pose_error(Z, A, X, R.retract(h * d), False)[0]
                - mount_pose_error(Z, A, X, R.retract(-h * d), False)[0]
            )
            / (2 * h)
            for d in np.eye(3)
        ]
    )
    np.testing.assert_allclose(Hx, num_x, atol=1e-6)
    np.testing.assert_allclose(Hr, num_r, atol=1e-6)
    np.testing.assert_allclose(e, mount_pose_error(Z, A, X, R, False)[0])


def test_a_pose_seen_through_the_true_mount_has_zero_residual():
    """Z = X T_bc_true T_bc^-1 (what PnP with the nominal mount reports) against E(w)."""
    rng = np.random.default_rng(4)
    w = np.radians([1.0, -2.0, 0.5])
    X = gtsam.Pose3.Expmap(rng.standard_normal(6))
    Z = X.matrix() @ corrected_mount(FLOOR_CAM.T_body_cam, w) @ inv_T(FLOOR_CAM.T_body_cam)
    A = gtsam.Pose3(gtsam.Rot3(), FLOOR_CAM.T_body_cam[:3, 3])
    e, _, _ = mount_pose_error(gtsam.Pose3(Z), A, X, gtsam.Rot3(so3_exp(w)), False)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    cam = corrected_camera(FLOOR_CAM, w)
    np.testing.assert_allclose(cam.T_body_cam[:3, 3], FLOOR_CAM.T_body_cam[:3, 3])
    np.testing.assert_allclose(cam.T_body_cam[:3, :3], so3_exp(w) @ FLOOR_CAM.T_body_cam[:3, :3])
    np.testing.assert_allclose(FLOOR_CAM.T_body_cam, corrected_mount(cam.T_body_cam, -w), atol=1e-12)


# ============================================================================ estimation


@pytest.mark.parametrize("w_deg", [(2.0, 0.0, 0.0), (0.0, 2.0, 0.0), (0.0, 0.0, 2.0), (1.2, -1.2, 1.0)])
def test_two_degree_error_recovered_within_target(w_deg):
    t, imu, raw = _survey(30.0, 1, w_deg)
    m = estimate_mount_rotation(t, imu, raw, None, FLOOR_CAM)
    assert m.source is MountSource.ESTIMATED and m.rotvec_rad is not None and m.sigma_rad is not None
    err = np.degrees(m.rotvec_rad) - np.asarray(w_deg)
    assert np.all(np.abs(err) < TARGET_DEG), err
    assert np.all(np.abs(err) < 4 * np.degrees(m.sigma_rad))  # the sigma is honest
    assert set(m.significant_axes) == {a for a, v in zip("xyz", w_deg) if v}
    assert m.unexcited_axes == []
    warning = m.warning()
    assert warning is not None and warning.name == WARNING_NAME
    assert warning.count == len(m.significant_axes) and "--calibrate-extrinsics" in warning.message


def test_no_error_is_not_significant():
    t, imu, raw = _survey(20.0, 2, (0.0, 0.0, 0.0))
    m = estimate_mount_rotation(t, imu, raw, None, FLOOR_CAM)
    assert m.significant_axes == [] and m.warning() is None
    assert np.all(np.degrees(np.abs(m.rotvec_rad)) < 3 * np.degrees(m.sigma_rad) + 1e-9)


def test_hovering_flight_reports_a_large_sigma_not_a_confident_wrong_yaw():
    """Hovering, the yaw of the mount is unobservable (no horizontal acceleration against the
    positions) and the tilt is confounded with the accelerometer bias: the sigmas say so."""
    rng = np.random.default_rng(5)
    hover = KeyframeTrajectory([Keyframe(0.0, (1.0, 2.0, 1.5), 0.3), Keyframe(20.0, (1.0, 2.0, 1.5), 0.3)])
    imu, _, _ = synthesize_imu(hover, 200.0, ImuNoise(), rng)
    w_deg = (0.0, 0.0, 2.0)
    t, raw = _pnp_poses(hover, 20.0, w_deg, rng)
    m = estimate_mount_rotation(t, imu, raw, None, FLOOR_CAM)
    sig = np.degrees(m.sigma_rad)
    assert sig[2] > 2.5  # about the prior's 5 deg
    assert "z" in m.unexcited_axes and "z" not in m.significant_axes
    assert np.all(sig[:2] > 0.2)  # tilt pinned only through the bias prior
    err = np.degrees(m.rotvec_rad) - np.asarray(w_deg)
    assert np.all(np.abs(err) < 3 * sig)


def test_mount_rotation_cannot_be_estimated_without_imu_or_with_a_gimbal():
    t, imu, raw = _survey(5.0, 3, (0.0, 0.0, 0.0))
    with pytest.raises(EstimationError, match="no IMU"):
        estimate_mount_rotation(t, None, raw, None, FLOOR_CAM)
    gimbaled = CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0, mount="gimbaled")
    with pytest.raises(EstimationError, match="gimbaled"):
        estimate_mount_rotation(t, imu, raw, None, gimbaled)
    log = FlightLog(Path("."), None, {"cam0": CameraStream("cam0", gimbaled, t, [], [])}, imu)
    m = check_mount(log, raw)
    assert m.source is MountSource.NOT_ESTIMATED and "gimbaled" in m.note
    assert m.warning() is None and m.as_dict()["rotvec_deg"] is None


# ============================================================================ simulator


def test_simulate_cli_turns_the_front_camera_mount_when_asked(tmp_path):
    """`fusion simulate --extrinsic-error-deg ... --extrinsic-error-camera cam1`: the front
    camera's mount is the one turned (the library's {camera: rotation}); the default stays cam0."""
    from fusion.cli import main

    common = ["--duration", "0.1", "--workers", "1", "-q", "--extrinsic-error-deg", "0", "0.1", "0"]
    assert main(["simulate", str(tmp_path / "front"), *common, "--extrinsic-error-camera", "cam1"]) == 0
    assert main(["simulate", str(tmp_path / "floor"), *common]) == 0
    front, floor = (
        read_extrinsics_groundtruth(tmp_path / "front"),
        read_extrinsics_groundtruth(tmp_path / "floor"),
    )
    assert list(front) == ["cam1"] and list(floor) == ["cam0"]
    np.testing.assert_allclose(np.degrees(front["cam1"]), [0.0, 0.1, 0.0])


def test_simulator_renders_the_true_mount_and_logs_the_nominal_one(tmp_path):
    kw = dict(duration_s=0.1, seed=0, progress=False, workers=1)
    simulate(tmp_path / "nominal", **kw)
    simulate(tmp_path / "wrong", extrinsic_error_deg={"cam0": (0.0, 0.0, 2.0)}, **kw)
    a, b = read_flight(tmp_path / "nominal"), read_flight(tmp_path / "wrong")
    np.testing.assert_array_equal(a.floor.camera.T_body_cam, b.floor.camera.T_body_cam)
    truth = read_extrinsics_groundtruth(tmp_path / "wrong")
    assert list(truth) == ["cam0"]
    np.testing.assert_allclose(np.degrees(truth["cam0"]), [0.0, 0.0, 2.0])
    assert read_extrinsics_groundtruth(tmp_path / "nominal") == {}
    assert not (tmp_path / "nominal" / EXTRINSICS_GROUNDTRUTH_CSV).exists()
    img_a, img_b = a.floor.load_image(0), b.floor.load_image(0)
    assert img_a is not None and img_b is not None and np.any(img_a != img_b)
    front_a, front_b = a.cameras["cam1"].load_image(0), b.cameras["cam1"].load_image(0)
    np.testing.assert_array_equal(front_a, front_b)


# ============================================================================ pipeline


def _miscalibrated_sample(tmp_path: Path, w_deg, camera: str = "cam0") -> Path:
    """The sample flight whose `camera`'s sensor.yaml is off: the images were made with its mount,
    the yaml now says that mount turned by -w (so the true mount is the logged one turned by w)."""
    dst = tmp_path / "log"
    shutil.copytree(SAMPLE, dst)
    path = dst / "mav0" / camera / "sensor.yaml"
    data = load_yaml(path, EstimationError)
    T = np.array(data["T_BS"]["data"], float).reshape(4, 4)
    data["T_BS"]["data"] = [float(v) for v in corrected_mount(T, -np.radians(w_deg)).reshape(-1)]
    dump_yaml(data, path)
    return dst


def _run(log_dir: Path, out: Path, *extra: str) -> dict:
    args = ["run", str(log_dir), "--out", str(out), "--quiet", "--workers", "1", "--no-incremental"]
    assert main([*args, *extra]) == 0
    return json.loads((out / "metrics.json").read_text())


def test_check_warns_and_calibration_applies_on_the_sample_flight(tmp_path):
    w_deg = (0.0, 2.0, 0.0)  # pitch: observed on this short flight (its roll is not)
    log_dir = _miscalibrated_sample(tmp_path, w_deg)
    m = _run(log_dir, tmp_path / "check")
    e = m["extrinsics"]
    assert e["source"] == "estimated" and not e["applied"] and "y" in e["significant_axes"]
    assert [w["name"] for w in m["warnings"]].count(WARNING_NAME) == 1
    assert abs(e["rotvec_deg"][1] - w_deg[1]) < 0.2
    m = _run(log_dir, tmp_path / "cal", "--calibrate-extrinsics")
    e = m["extrinsics"]
    assert e["applied"] and WARNING_NAME not in [w["name"] for w in m["warnings"]]
    assert "mount rotation" in (tmp_path / "cal" / "report.md").read_text()
    ok = _run(SAMPLE, tmp_path / "nominal")
    assert ok["extrinsics"]["significant_axes"] == [] and ok["extrinsics"]["applied"] is False
    assert WARNING_NAME not in [w["name"] for w in ok["warnings"]]
    assert (
        ok["front_extrinsics"]["source"] == "estimated" and ok["front_extrinsics"]["significant_axes"] == []
    )
    # the corrected mount reaches the per-frame estimates: PnP's attitudes move back to the
    # correctly calibrated run's
    ref = read_tum(tmp_path / "nominal" / "trajectory_pnp.tum")
    for name, lo, hi in (("check", 1.8, 2.2), ("cal", 0.0, 0.2)):
        traj = read_tum(tmp_path / name / "trajectory_pnp.tum")
        np.testing.assert_array_equal(traj.timestamps_ns, ref.timestamps_ns)
        d = np.degrees(
            [
                np.linalg.norm(so3_log(a[:3, :3].T @ b[:3, :3]))
                for a, b in zip(ref.T_world_body, traj.T_world_body)
            ]
        )
        assert lo < np.median(d) < hi, (name, np.median(d))


# ============================================================================ long flights in windows


def test_merged_mount_counts_the_prior_once_and_keeps_an_unexcited_axis_at_the_prior():
    """Two windows that each saw x and y (sigma 0.02 deg) but not z (the prior's 5 deg, inflated):
    x, y combine like independent measurements; z keeps the prior's sigma, neither shrunk by
    the prior counted twice nor driven below it by an inflated part."""
    prior = math.radians(ExtrinsicsConfig().prior_sigma_deg)
    s = math.radians(0.02)

    def part(w_deg, inflation):
        info = np.diag([1 / s**2, 1 / s**2, 0.0]) + np.eye(3) / prior**2
        cov = np.linalg.inv(info) * inflation
        return MountRotation("cam0", MountSource.ESTIMATED, np.radians(w_deg), cov, fixes=100, iterations=3)

    m = merge_mount_rotations([part([0.10, -0.20, 0.0], 1.0), part([0.14, -0.16, 0.0], 1.5)])
    sig = np.degrees(m.sigma_rad)
    w1, w2 = 1 / 0.02**2, 1 / (0.02**2 * 1.5)
    assert sig[0] == pytest.approx(math.sqrt(1 / (w1 + w2)), rel=1e-3)
    assert np.degrees(m.rotvec_rad[0]) == pytest.approx((0.10 * w1 + 0.14 * w2) / (w1 + w2), rel=1e-3)
    assert sig[2] == pytest.approx(ExtrinsicsConfig().prior_sigma_deg, rel=1e-6)
    assert m.unexcited_axes == ["z"] and m.fixes == 200 and m.iterations == 6
    assert set(m.significant_axes) == {"x", "y"}


def test_mount_estimated_in_windows_agrees_with_the_whole_flight():
    """A 60 s survey with a 1 deg error solved in four 22.5 s windows: the merged mount within
    its sigma of the whole-flight one (and of the truth within the issue's 0.05 deg), the
    stitched trajectory within 1 mm of the whole-flight one."""
    w_deg = (1.0, -0.5, 0.8)
    t, imu, raw = _survey(60.0, 3, w_deg)
    whole, traj_whole, _ = estimate_mount_and_states(t, imu, raw, None, FLOOR_CAM)
    windows = WindowConfig(window_s=25.0, overlap_s=10.0, min_flight_s=0.0)
    assert len(plan_windows(t, windows)) == 4
    merged, traj, states = estimate_mount_windowed(
        t, imu, raw, None, FLOOR_CAM, window=windows, frame_rate_hz=None
    )
    assert states is None and traj is not None and traj_whole is not None
    diff = np.degrees(merged.rotvec_rad - whole.rotvec_rad)
    assert np.all(np.abs(diff) < 3 * np.degrees(merged.sigma_rad)), diff
    assert np.all(np.abs(np.degrees(merged.rotvec_rad) - w_deg) < TARGET_DEG)
    # the windows share only their overlaps: sigma no smaller than the whole flight's / 1.2
    assert np.all(merged.sigma_rad > whole.sigma_rad / 1.2)
    np.testing.assert_array_equal(traj.timestamps_ns, traj_whole.timestamps_ns)
    gap = np.linalg.norm(traj.T_world_body[:, :3, 3] - traj_whole.T_world_body[:, :3, 3], axis=1)
    assert gap.max() < 1e-3
    # a flight of one window is the whole-flight solve itself
    one, _, _ = estimate_mount_windowed(t, imu, raw, None, FLOOR_CAM, window=WindowConfig())
    np.testing.assert_array_equal(one.rotvec_rad, whole.rotvec_rad)


def test_mount_in_windows_on_every_third_frame():
    """The windowed solve of a long flight keeps every k-th frame (MOUNT_FRAME_RATE_HZ: 10 Hz of
    30 fps, k = 3) and its fixes: the mount stays within 3 sigma of the every-frame solve and
    within the issue's 0.05 deg of the truth, its sigma grows by at most sqrt(3) (fewer fixes),
    and the trajectory is still at every frame (the others filled by the IMU, imu_fill), within
    1 mm RMS of the every-frame windowed solve (3 mm at worst: a third of the 2 mm fixes)."""
    w_deg = (1.0, -0.5, 0.8)
    t, imu, raw = _survey(60.0, 3, w_deg)
    windows = WindowConfig(window_s=25.0, overlap_s=10.0, min_flight_s=0.0)
    full, traj_full, _ = estimate_mount_windowed(
        t, imu, raw, None, FLOOR_CAM, window=windows, frame_rate_hz=None
    )
    third, traj, states = estimate_mount_windowed(t, imu, raw, None, FLOOR_CAM, window=windows)
    assert states is None and traj is not None and traj_full is not None
    assert third.fixes == pytest.approx(full.fixes / 3, rel=0.05)
    diff = np.degrees(third.rotvec_rad - full.rotvec_rad)
    assert np.all(np.abs(diff) < 3 * np.degrees(third.sigma_rad)), diff
    assert np.all(np.abs(np.degrees(third.rotvec_rad) - w_deg) < TARGET_DEG)
    assert np.all(third.sigma_rad >= full.sigma_rad) and np.all(third.sigma_rad < 1.8 * full.sigma_rad)
    np.testing.assert_array_equal(traj.timestamps_ns, t)
    gap = np.linalg.norm(traj.T_world_body[:, :3, 3] - traj_full.T_world_body[:, :3, 3], axis=1)
    assert np.sqrt(np.mean(gap**2)) < 1e-3 and gap.max() < 3e-3
    # a rate at or above the frames' keeps every frame: the every-frame solve itself
    same, _, _ = estimate_mount_windowed(t, imu, raw, None, FLOOR_CAM, window=windows, frame_rate_hz=30.0)
    np.testing.assert_array_equal(same.rotvec_rad, full.rotvec_rad)


def test_an_imu_scale_beside_a_significant_mount_is_said_to_be_the_mounts():
    """held18's to6_ext: a 0.5 deg mount error read as IMU noise (x2.89); the run says so when the
    mount check found it and did not apply it, and says nothing otherwise."""
    from fusion.estimate.extrinsics import MountRotation, MountSource
    from fusion.pipeline import _imu_scale_or_mount_note

    stats = {
        "smoother": {"noise_scales": {"imu": {"scale": 8.38, "sigma_factor": 2.89}, "imu_warning": True}}
    }
    off = MountRotation("cam0", MountSource.ESTIMATED, significant_axes=["y", "z"])
    note = _imu_scale_or_mount_note([off, None], stats)
    assert note is not None and "x2.89" in note and "(y, z; extrinsic_rotation_bias)" in note
    assert _imu_scale_or_mount_note([MountRotation("cam0", MountSource.ESTIMATED)], stats) is None
    applied = MountRotation("cam0", MountSource.ESTIMATED, significant_axes=["y"], applied=True)
    assert _imu_scale_or_mount_note([applied], stats) is None
    assert _imu_scale_or_mount_note([off], {"smoother": {"noise_scales": {}}}) is None
    assert _imu_scale_or_mount_note([None, None], stats) is None
    front = MountRotation("cam1", MountSource.ESTIMATED, significant_axes=["x"])
    note = _imu_scale_or_mount_note([None, front], stats)
    assert note is not None and "front camera's (x; front_extrinsic_rotation_bias)" in note


# ============================================================================ the front camera

FRONT_CAM = CameraModel(
    640, 480, 500.0, 500.0, 320.0, 240.0, T_body_cam=make_T(R_BODY_FRONTCAM, [0.08, 0.0, 0.02])
)


def _front_sightings(
    f_deg, seed: int, sigma_m: float = 0.002, stated_m: float | None = None, noise_seed=None, rho: float = 0.0
):
    """A 20 s survey's body trajectory at 30 Hz and load sightings by a front camera whose true
    mount is FRONT_CAM's turned by f_deg: loads ahead of the drone, each sighting p_cam with
    noise of `sigma_m` per axis, its covariance stated as `stated_m` (default: as it is).
    `noise_seed`: the sightings' noise drawn apart from the survey (same flight, new noise).
    `rho`: the noise of a load's sightings in consecutive frames correlated as AR(1) (0: white)."""
    rng = np.random.default_rng(seed)
    traj = random_aisle_survey(20.0, rng)
    if noise_seed is not None:
        rng = np.random.default_rng([seed, noise_seed])
    stated_m = sigma_m if stated_m is None else stated_m
    t = np.round(np.arange(0.0, 20.0, 1 / 30.0) * 1e9).astype(np.int64)
    T_wb = traj.state(t * 1e-9).T_world_body
    true_cam = corrected_camera(FRONT_CAM, np.radians(f_deg))
    loads = {
        f"L{i}": T_wb[k] @ np.array([2.0, rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3), 1.0])
        for i, k in enumerate(range(0, len(t), 60))
    }
    out = []
    noise = {lid: sigma_m * rng.standard_normal(3) for lid in loads}
    for k, T in enumerate(T_wb):
        T_cw = inv_T(T @ true_cam.T_body_cam)
        for lid, p in loads.items():
            pc = (T_cw @ p)[:3]
            noise[lid] = rho * noise[lid] + np.sqrt(1.0 - rho * rho) * sigma_m * rng.standard_normal(3)
            if pc[2] > 0.5 and abs(pc[0]) < 0.8 * pc[2] and abs(pc[1]) < 0.6 * pc[2]:
                pc = pc + noise[lid]
                out.append(LoadObservation(int(t[k]), lid, np.zeros(3), None, pc, stated_m**2 * np.eye(3)))
    return Trajectory("smoother", t, T_wb, None), out


@pytest.mark.parametrize("f_deg", [(0.5, 0.0, 0.0), (0.0, -0.4, 0.3), (0.05, 0.0, 0.0)])
def test_front_mount_recovered_against_the_body_trajectory(f_deg):
    traj, obs = _front_sightings(f_deg, seed=3)
    m = estimate_front_mount(traj, obs, FRONT_CAM)
    assert m.camera == "cam1" and m.source is MountSource.ESTIMATED
    err = np.degrees(so3_log(so3_exp(m.rotvec_rad) @ so3_exp(np.radians(f_deg)).T))
    sig = np.degrees(m.sigma_rad)
    assert np.all(np.abs(err) < 4 * sig + 1e-3), (err, sig)
    assert np.all(sig < 0.05)
    assert set(m.significant_axes) == {a for a, v in zip("xyz", f_deg) if v}
    w = m.warning()
    assert w is not None and w.name == FRONT_WARNING_NAME and "front camera" in w.message
    assert "(front)" in m.describe()


def test_front_mount_right_is_not_significant_and_too_few_sightings_is_an_error():
    traj, obs = _front_sightings((0.0, 0.0, 0.0), seed=4)
    m = estimate_front_mount(traj, obs, FRONT_CAM)
    assert not m.significant and m.warning() is None
    with pytest.raises(EstimationError, match="sightings"):
        estimate_front_mount(traj, obs[:5], FRONT_CAM)
    with pytest.raises(EstimationError, match="gimbaled"):
        from dataclasses import replace

        estimate_front_mount(traj, obs, replace(FRONT_CAM, mount="gimbaled"))


def test_front_mount_check_and_calibration_on_the_sample_flight(tmp_path):
    """A front camera whose sensor.yaml is 0.5 deg off in roll (about its optical axis): the
    floor check cannot see it, the front check warns, --calibrate-extrinsics applies it and the
    batch smoother's load sightings fit again."""
    f_deg = (0.5, 0.0, 0.0)
    dst = _miscalibrated_sample(tmp_path, f_deg, "cam1")
    m = _run(dst, tmp_path / "check")
    e = m["front_extrinsics"]
    assert e["source"] == "estimated" and not e["applied"] and e["significant_axes"] == ["x"]
    assert abs(e["rotvec_deg"][0] - f_deg[0]) < 0.1
    assert [w["name"] for w in m["warnings"]].count(FRONT_WARNING_NAME) == 1
    m = _run(dst, tmp_path / "cal", "--calibrate-extrinsics")
    e = m["front_extrinsics"]
    assert e["applied"] and FRONT_WARNING_NAME not in [w["name"] for w in m["warnings"]]
    assert "**Front camera mount rotation** (`cam1`)" in (tmp_path / "cal" / "report.md").read_text()


def test_front_mount_is_not_checked_against_a_gimbaled_floor_cameras_level_poses(tmp_path):
    """A gimbaled floor camera's PnP poses are level (roll = pitch = 0): the front camera hung
    from them would read the body's tilt as its own mount error, so it is not estimated."""
    dst = tmp_path / "log"
    shutil.copytree(SAMPLE, dst)
    path = dst / "mav0" / "cam0" / "sensor.yaml"
    data = load_yaml(path, EstimationError)
    data["mount"] = "gimbaled"
    dump_yaml(data, path)
    m = _run(dst, tmp_path / "out")
    e = m["front_extrinsics"]
    assert e["source"] == "not_estimated" and "gimbaled floor camera" in e["note"]
    assert FRONT_WARNING_NAME not in [w["name"] for w in m["warnings"]]


def test_front_mount_sigma_matches_the_spread_of_its_estimates_and_widens_with_the_noise():
    """Over 30 noise draws of one flight the estimates scatter as the fit's sigma says (the
    reported sigma less the trajectory's FRONT_MOUNT_TRAJECTORY_SIGMA_DEG), and sightings twice
    as noisy as stated give a fit sigma about twice as large (the chi2 / dof inflation)."""
    from fusion.estimate.extrinsics import FRONT_MOUNT_TRAJECTORY_SIGMA_DEG

    def fit_sigma_deg(m):
        return np.sqrt(np.degrees(m.sigma_rad) ** 2 - FRONT_MOUNT_TRAJECTORY_SIGMA_DEG**2)

    runs = [
        estimate_front_mount(*_front_sightings((0.3, 0.0, 0.0), seed=3, noise_seed=i), FRONT_CAM)
        for i in range(30)
    ]
    w = np.degrees([m.rotvec_rad for m in runs])
    sig = np.mean([fit_sigma_deg(m) for m in runs], axis=0)
    spread = w.std(axis=0, ddof=1)
    assert np.all(np.abs(spread / sig - 1.0) < 0.35), (spread, sig)
    noisy = estimate_front_mount(
        *_front_sightings((0.3, 0.0, 0.0), seed=3, sigma_m=0.004, stated_m=0.002), FRONT_CAM
    )
    ratio = fit_sigma_deg(noisy) / sig
    assert np.all((ratio > 1.6) & (ratio < 2.5)), ratio


def test_front_mount_sigma_holds_for_errors_correlated_over_frames():
    """A load's sightings whose errors persist over frames (AR(1), rho 0.8: tau = 9 frames, as
    a rolling shutter's motion error or a PnP pose's slow error) are worth fewer independent
    ones: the reported sigma widens by ~sqrt(tau) and matches the spread of 30 draws (it was
    ~3x too small, and a 30 ms readout read a 0.08 deg pitch at 5.7 of its sigmas)."""
    from fusion.estimate.extrinsics import FRONT_MOUNT_TRAJECTORY_SIGMA_DEG

    def fit_sigma_deg(m):
        return np.sqrt(np.degrees(m.sigma_rad) ** 2 - FRONT_MOUNT_TRAJECTORY_SIGMA_DEG**2)

    runs = [
        estimate_front_mount(*_front_sightings((0.3, 0.0, 0.0), seed=3, noise_seed=i, rho=0.8), FRONT_CAM)
        for i in range(30)
    ]
    w = np.degrees([m.rotvec_rad for m in runs])
    sig = np.mean([fit_sigma_deg(m) for m in runs], axis=0)
    spread = w.std(axis=0, ddof=1)
    assert np.all(np.abs(spread / sig - 1.0) < 0.35), (spread, sig)
    white = estimate_front_mount(*_front_sightings((0.3, 0.0, 0.0), seed=3, noise_seed=0), FRONT_CAM)
    assert np.all(sig / fit_sigma_deg(white) > 2.0), (sig, fit_sigma_deg(white))


def test_front_mount_leaves_out_sightings_across_a_gap_in_the_trajectory():
    """A sighting whose body pose would be interpolated over more than LOAD_INTERP_MAX_GAP_S
    (a floor-camera blackout) is not used: the same estimate and count as without it."""
    traj, obs = _front_sightings((0.3, 0.0, 0.0), seed=3)
    t = traj.timestamps_ns
    gap = (t > t[200]) & (t < t[260])  # 2 s without a pose
    holed = Trajectory(traj.name, t[~gap], traj.T_world_body[~gap], None)
    inside = [o for o in obs if t[200] < o.timestamp_ns < t[260]]
    assert len(inside) > 20
    m = estimate_front_mount(holed, obs, FRONT_CAM)
    ref = estimate_front_mount(holed, [o for o in obs if o not in inside], FRONT_CAM)
    assert m.fixes == ref.fixes == len(obs) - len(inside)
    np.testing.assert_allclose(m.rotvec_rad, ref.rotvec_rad, atol=1e-12)


def test_front_mount_does_not_interpolate_the_pnp_poses_over_missing_frames():
    """The PnP poses have no IMU between them: a sighting more than one missing frame from a pose
    (here 5 frames missing, 200 ms at 30 Hz, within LOAD_INTERP_MAX_GAP_S) is left out, as a
    straight line over such a gap of a turning drone is mm off (the sweep's pincushion flight
    read a false 0.15 deg pitch from 20 such sightings); one missing frame still interpolates."""
    traj, obs = _front_sightings((0.3, 0.0, 0.0), seed=3)
    t = traj.timestamps_ns
    for missing, left_out in ((range(201, 206), True), ([300], False)):
        keep = ~np.isin(np.arange(len(t)), list(missing))
        holed = Trajectory(traj.name, t[keep], traj.T_world_body[keep], None)
        inside = [o for o in obs if o.timestamp_ns in set(t[list(missing)].tolist())]
        assert inside
        m = estimate_front_mount(holed, obs, FRONT_CAM)
        assert m.fixes == len(obs) - (len(inside) if left_out else 0)


def test_front_mount_takes_the_body_poses_own_error():
    """Body poses whose attitude error is stated in their covariances, one frame in ten 0.5 deg
    off, the rest 0.01 deg: carried to each sighting, those covariances weigh the bad frames
    down, so over 20 draws the estimates scatter less (by a third) than a fit that takes the
    poses as equal (the trajectory without covariances: its Huber weights do part of it), and
    as the reported sigma says, though ~5 sightings of a frame share its pose's error."""
    from fusion.estimate.extrinsics import FRONT_MOUNT_TRAJECTORY_SIGMA_DEG

    est, bare, claimed = [], [], []
    for i in range(20):
        traj, obs = _front_sightings((0.0, 0.0, 0.0), seed=3, noise_seed=i)
        rng = np.random.default_rng([7, i])
        n = len(traj)
        sig_r = np.radians(np.where(rng.random(n) < 0.1, 0.5, 0.01))
        noisy = np.array(
            [
                T @ make_T(so3_exp(s_ * rng.standard_normal(3)), np.zeros(3))
                for T, s_ in zip(traj.T_world_body, sig_r)
            ]
        )
        cov = np.zeros((n, 6, 6))
        cov[:, :3, :3] = sig_r[:, None, None] ** 2 * np.eye(3)
        cov[:, 3:, 3:] = 1e-8 * np.eye(3)
        m = estimate_front_mount(Trajectory("pnp", traj.timestamps_ns, noisy, cov), obs, FRONT_CAM)
        b = estimate_front_mount(Trajectory("pnp", traj.timestamps_ns, noisy, None), obs, FRONT_CAM)
        est.append(np.degrees(m.rotvec_rad))
        bare.append(np.degrees(b.rotvec_rad))
        claimed.append(np.sqrt(np.degrees(m.sigma_rad) ** 2 - FRONT_MOUNT_TRAJECTORY_SIGMA_DEG**2))
        assert not m.significant
    spread = np.std(est, axis=0, ddof=1)
    assert spread.sum() < 0.75 * np.std(bare, axis=0, ddof=1).sum(), (spread, np.std(bare, axis=0, ddof=1))
    assert np.all(np.abs(spread / np.mean(claimed, axis=0) - 1.0) < 0.4), (spread, np.mean(claimed, axis=0))


def test_front_mount_takes_a_pose_without_a_usable_covariance_as_exact():
    """A trajectory whose pose covariances are partly NaN (a pose PnP could not bound) still gives
    a finite estimate: those poses count as exact, the others as stated."""
    traj, obs = _front_sightings((0.3, 0.0, 0.0), seed=3)
    cov = np.repeat((1e-8 * np.eye(6))[None], len(traj), 0)
    cov[::7] = np.nan
    m = estimate_front_mount(Trajectory("pnp", traj.timestamps_ns, traj.T_world_body, cov), obs, FRONT_CAM)
    assert np.all(np.isfinite(m.rotvec_rad)) and np.all(np.isfinite(m.cov_rad2))
    assert abs(np.degrees(m.rotvec_rad[0]) - 0.3) < 0.01 and m.significant_axes == ["x"]


def test_a_mount_reading_beyond_any_calibration_error_is_named_and_never_applied():
    """A frozen floor camera read as a mount 77 deg off, and --calibrate-extrinsics applied it
    (thirty-first session's audit).  Above MAX_CORRECTION_DEG the check is no mount error: the
    run warns `mount_check_implausible` and leaves the mount, with or without the flag."""
    from fusion.estimate.extrinsics import MAX_CORRECTION_DEG
    from fusion.pipeline import RunConfig, RunResult, _warn_or_apply_mount

    cov = np.eye(3) * math.radians(0.5) ** 2
    big = MountRotation("cam0", MountSource.ESTIMATED, np.radians([76.7, -55.1, -63.6]), cov, ["x", "y", "z"])
    small = MountRotation(
        "cam0", MountSource.ESTIMATED, np.radians([0, 0, 0.8 * MAX_CORRECTION_DEG]), cov, ["z"]
    )
    assert big.implausible and not small.implausible
    assert "not applied" in big.describe() and "--calibrate-extrinsics" not in big.describe()
    log = read_flight(Path(__file__).resolve().parents[1] / "data" / "sample-flight")
    for flag in (False, True):
        result = RunResult(Path("."), {})
        out_log, loc = _warn_or_apply_mount(
            log, None, "loc", RunConfig(calibrate_extrinsics=flag), result, big
        )
        assert out_log is log and loc == "loc" and not big.applied
        assert [w.name for w in result.warnings] == ["mount_check_implausible"]
        assert "frozen camera" in result.warnings[0].message


def test_a_large_applied_correction_is_named():
    """--calibrate-extrinsics applied a 4.5 deg front pitch that was a load code 10 % larger
    than world.yaml says, with no warning (thirty-second session's audit): a correction above
    LARGE_CORRECTION_DEG is `mount_correction_large`, naming what else it may hide; 2 deg (the
    benchmarks' error) and a correction not applied say nothing."""
    from fusion.estimate.extrinsics import LARGE_CORRECTION_DEG, LARGE_WARNING_NAME

    def mount(camera, w_deg, applied=True):
        m = MountRotation(
            camera, MountSource.ESTIMATED, np.radians(w_deg), np.diag(np.radians([0.05] * 3) ** 2)
        )
        m.significant_axes = [a for a, v in zip("xyz", w_deg) if abs(v) > 0.5]
        m.applied = applied
        return m

    w = mount("cam1", (0.0, -4.5, 0.0)).large_correction_warning()
    assert w is not None and w.name == LARGE_WARNING_NAME and "load_qr side_m" in w.message
    assert "front camera's (cam1) mount was corrected by 4.5 deg" in w.message
    w = mount("cam0", (3.5, 0.0, 0.0)).large_correction_warning()
    assert w is not None and "floor_qr side_m" in w.message
    assert mount("cam0", (0.0, 2.0, 0.0)).large_correction_warning() is None
    assert mount("cam1", (0.0, -4.5, 0.0), applied=False).large_correction_warning() is None
    assert LARGE_CORRECTION_DEG == 3.0
