"""The load maps' consider terms (fusion.estimate.loadconsider): errors common to all sightings
of a load code (the body pose's, its printed side's, the front camera's stamps')."""

import numpy as np
import pytest
from scipy.stats import chi2

from fusion.camera import CameraModel
from fusion.errors import WorldError
from fusion.estimate.loadconsider import add_load_consider_covariance
from fusion.geometry import make_T
from fusion.types import LoadEstimate, LoadMap, LoadObservation, Trajectory
from fusion.world import DEFAULT_LOAD_SIDE_SIGMA_REL, World

LOAD = np.array([2.0, 2.7, 1.4])
# a front camera looking along body x (z_cam = x_body, x_cam = -y_body, y_cam = -z_body)
R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
CAMERA = CameraModel(
    640,
    480,
    550.0,
    550.0,
    320.0,
    240.0,
    T_body_cam=make_T(R_BODY_CAM, np.zeros(3)),
    mount_sigma_deg=0.0,
    mount_sigma_m=0.0,
    intrinsics_sigma_px=(0.0,) * 4,
)
YAW_90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _pass(n: int = 60, speed: float = 1.0, rate: float = 30.0, pose_cov=None):
    """A drone facing +y flying along x past the load at 1.25 m, centred on it: its trajectory (pose
    covariance `pose_cov` at every frame, or none) and the true camera-frame code centres."""
    t = np.arange(n) / rate
    T = np.array([make_T(YAW_90, [LOAD[0] + speed * (ti - t[-1] / 2), LOAD[1] - 1.25, LOAD[2]]) for ti in t])
    T_cw = np.linalg.inv(CAMERA.T_world_cam(T))
    p_cam = np.einsum("nij,j->ni", T_cw[:, :3, :3], LOAD) + T_cw[:, :3, 3]
    covs = None if pose_cov is None else np.tile(pose_cov, (n, 1, 1))
    return Trajectory("pnp", (t * 1e9).astype(np.int64), T, covs), p_cam


def _observations(traj, p_cam, sigma_m=1e-4):
    cov = np.eye(3) * sigma_m**2
    return [LoadObservation(int(ts), "L1", LOAD, None, p, cov) for ts, p in zip(traj.timestamps_ns, p_cam)]


def _added(traj, p_cam, **kw):
    lm = LoadMap("pnp", [LoadEstimate("L1", LOAD, np.zeros((3, 3)), len(p_cam))])
    out = add_load_consider_covariance(lm, _observations(traj, p_cam), traj, CAMERA, **kw)
    assert out.loads[0].p_world is LOAD  # the estimate is not moved
    return out.loads[0].cov_world


def test_a_print_error_is_carried_along_the_mean_ray():
    traj, p_cam = _pass()
    rays = LOAD - CAMERA.T_world_cam(traj.T_world_body)[:, :3, 3]
    u = rays.mean(axis=0)
    assert np.allclose(_added(traj, p_cam, side_sigma_rel=1e-3), 1e-6 * np.outer(u, u), atol=1e-15)
    assert u[1] == pytest.approx(1.25) and abs(u[0]) < 1e-9  # the pass is symmetric about the load


def test_a_stamp_error_is_carried_along_the_motion():
    traj, p_cam = _pass(speed=1.0)
    added = _added(traj, p_cam, side_sigma_rel=0.0, stamp_variance_s2=(1e-3) ** 2)
    # no rotation, 1 m/s along x: a 1 ms stamp error moves every sighting by 1 mm along x
    assert np.allclose(added, np.diag([1e-6, 0.0, 0.0]), atol=1e-12)


def test_the_front_mount_error_moves_the_load_across_the_ray():
    """A load straight ahead at 1.25 m, seen from one pose: a mount rotation sigma moves it by
    1.25 m x sigma across the ray (x by the yaw, z by the pitch) and not along it; a shift
    sigma by as much along each axis.  Not stated in sensor.yaml: 0.1 deg and 2 mm."""
    from dataclasses import replace

    traj, p_cam = _pass(n=1)
    cam = replace(CAMERA, mount_sigma_deg=0.5, mount_sigma_m=0.0)
    lm = LoadMap("pnp", [LoadEstimate("L1", LOAD, np.zeros((3, 3)), 1)])
    added = add_load_consider_covariance(lm, _observations(traj, p_cam), traj, cam, 0.0).loads[0].cov_world
    s = np.radians(0.5) * 1.25
    assert np.allclose(added, np.diag([s**2, 0.0, s**2]), atol=1e-12)
    cam = replace(CAMERA, mount_sigma_deg=0.0, mount_sigma_m=0.003)
    added = add_load_consider_covariance(lm, _observations(traj, p_cam), traj, cam, 0.0).loads[0].cov_world
    assert np.allclose(added, np.eye(3) * 0.003**2, atol=1e-15)
    assert replace(CAMERA, mount_sigma_deg=None, mount_sigma_m=None).mount_sigmas == (np.radians(0.1), 0.002)


def test_mount_sigmas_in_sensor_yaml():
    from fusion.errors import CameraModelError

    data = CAMERA.to_sensor_yaml()
    assert data["T_BS_sigma_deg"] == 0.0 and CameraModel.from_sensor_yaml(data).mount_sigmas == (0.0, 0.0)
    for key in ("T_BS_sigma_deg", "T_BS_sigma_m"):
        del data[key]
    assert (
        "T_BS_sigma_deg" not in CameraModel.from_sensor_yaml(data).to_sensor_yaml()
    )  # not stated: not written
    for key, bad in (
        ("T_BS_sigma_deg", 45.0),
        ("T_BS_sigma_m", -1.0),
        ("T_BS_sigma_m", "2mm"),
        ("T_BS_sigma_deg", True),
    ):
        with pytest.raises(CameraModelError, match=key):
            CameraModel.from_sensor_yaml({**data, key: bad}, "cam1/sensor.yaml")


def test_the_pose_error_is_not_averaged_down():
    """A position-only pose covariance s^2 I at every frame: the load can be no better known
    than the pose it hangs from (s^2 I); a yaw sigma adds its lever arm across the ray."""
    s = 2e-4
    P = np.zeros((6, 6))
    P[3:, 3:] = np.eye(3) * s**2
    traj, p_cam = _pass(pose_cov=P)
    assert np.allclose(_added(traj, p_cam, side_sigma_rel=0.0), np.eye(3) * s**2, rtol=1e-6)
    P[2, 2] = 1e-8  # yaw 0.1 mrad, about body z = world z
    traj, p_cam = _pass(pose_cov=P)
    added = _added(traj, p_cam, side_sigma_rel=0.0)
    rays = LOAD - traj.T_world_body[:, :3, 3]
    lever_x = np.mean(rays[:, 1] ** 2)  # the yaw moves the load along x by its y distance
    assert added[0, 0] == pytest.approx(s**2 + 1e-8 * lever_x, rel=1e-6)


def test_maps_with_common_errors_are_consistent_with_the_terms():
    """Monte Carlo: each trial has one pose error for the whole pass (position, s per axis) and
    a label printed (1 + e) too large; the map is the information-weighted mean of the sightings
    as the EKF / PnP maps make it: its NEES against that covariance is far above 3, ~3 with the
    terms."""
    rng = np.random.default_rng(4)
    s, sigma_m, sigma_rel = 2e-4, 2e-4, 1e-3
    P = np.zeros((6, 6))
    P[3:, 3:] = np.eye(3) * s**2
    traj, p_cam = _pass(n=90, pose_cov=P)
    T_wc = CAMERA.T_world_cam(traj.T_world_body)
    nees_before, nees_after = [], []
    for _ in range(300):
        offset = rng.normal(0.0, s, 3)  # the poses' common position error
        e = rng.normal(0.0, sigma_rel)
        meas = p_cam / (1.0 + e) + rng.normal(0.0, sigma_m, p_cam.shape)
        pts = np.einsum("nij,nj->ni", T_wc[:, :3, :3], meas) + T_wc[:, :3, 3] + offset
        est = pts.mean(axis=0)
        cov = np.eye(3) * (sigma_m**2 + s**2) / len(pts)  # each sighting's, averaged
        lm = LoadMap("pnp", [LoadEstimate("L1", est, cov, len(pts))])
        out = add_load_consider_covariance(lm, _observations(traj, meas, sigma_m), traj, CAMERA, sigma_rel)
        d = est - LOAD
        nees_before.append(d @ np.linalg.solve(cov, d))
        nees_after.append(d @ np.linalg.solve(out.loads[0].cov_world, d))
    lo, hi = chi2.ppf([0.001, 0.999], 3 * 300) / 300
    assert np.mean(nees_before) > 20.0
    assert lo < np.mean(nees_after) < hi


def test_loads_without_covariance_or_pose_are_kept():
    traj, p_cam = _pass()
    obs = _observations(traj, p_cam)
    far = LoadObservation(int(traj.timestamps_ns[-1] + 5e9), "L2", LOAD, None, p_cam[0], np.eye(3))
    lm = LoadMap("paper", [LoadEstimate("L1", LOAD, None, 1), LoadEstimate("L2", LOAD, np.eye(3), 1)])
    out = add_load_consider_covariance(lm, [*obs, far], traj, CAMERA, 1e-3)
    assert out.loads[0].cov_world is None
    assert np.array_equal(out.loads[1].cov_world, np.eye(3))  # its one sighting 5 s from any pose
    assert add_load_consider_covariance(lm, obs, None, CAMERA, 1e-3) is lm


def test_world_yaml_load_side_sigma():
    w = World.from_yaml({"floor_qr": {"side_m": 0.2}, "load_qr": {"side_m": 0.15, "side_sigma_m": 0.0003}})
    assert w.load_side_sigma_rel == pytest.approx(0.002)
    assert World.from_yaml(w.to_yaml()) == w
    assert World().load_side_sigma_rel == DEFAULT_LOAD_SIDE_SIGMA_REL  # not stated
    assert World(load_side_sigma_m=0.0).load_side_sigma_rel == 0.0
    for bad, why in ((-1, ">= 0"), (0.3, "below the side"), ("1mm", "load_qr.side_sigma_m")):
        with pytest.raises(WorldError, match=why):
            World.from_yaml({"floor_qr": {"side_m": 0.2}, "load_qr": {"side_m": 0.15, "side_sigma_m": bad}})


def test_simulated_flights_state_exact_labels_and_mounts(tmp_path):
    from fusion.fileio import load_yaml
    from fusion.sim.simulate import simulate

    simulate(tmp_path / "a", duration_s=0.2, camera_rate_hz=10, workers=1, progress=False)
    assert load_yaml(tmp_path / "a" / "world.yaml")["load_qr"]["side_sigma_m"] == 0.0
    front = load_yaml(tmp_path / "a" / "mav0" / "cam1" / "sensor.yaml")
    assert front["T_BS_sigma_deg"] == 0.0 and front["T_BS_sigma_m"] == 0.0  # exact mounts
    simulate(
        tmp_path / "b",
        extrinsic_error_deg={"cam1": (0.3, 0.0, 0.4)},
        duration_s=0.2,
        camera_rate_hz=10,
        workers=1,
        progress=False,
    )
    front = load_yaml(tmp_path / "b" / "mav0" / "cam1" / "sensor.yaml")
    assert front["T_BS_sigma_deg"] == pytest.approx(np.sqrt(0.25 / 3))  # the error's RMS per axis


def test_blocks_give_the_same_terms():
    from fusion.estimate.loadconsider import common_terms

    P = np.diag([1e-8, 2e-8, 3e-8, 1e-8, 4e-8, 9e-8])
    traj, p_cam = _pass(n=50, pose_cov=P)
    obs = _observations(traj, p_cam)
    obs += [LoadObservation(o.timestamp_ns, "L2", LOAD, None, o.p_cam * 1.1, None) for o in obs[::3]]
    one = common_terms(obs, traj, CAMERA, block=10_000)
    many = common_terms(obs, traj, CAMERA, block=7)
    assert one.keys() == many.keys() == {"L1", "L2"}
    for lid in one:
        for a, b in zip(one[lid], many[lid]):
            assert np.allclose(a, b, rtol=1e-12, atol=1e-18)


def test_an_id_at_two_places_is_found_and_its_sigma_covers_them():
    from fusion.estimate.loadconsider import add_places_spread
    from fusion.pipeline import loads_at_two_places, loads_at_two_places_warning

    rng = np.random.default_rng(2)
    a = LOAD + rng.normal(0, 0.002, (40, 3))
    b = LOAD + [2.0, 0, 0] + rng.normal(0, 0.002, (30, 3))
    obs = [LoadObservation(i, "L1", p) for i, p in enumerate(np.vstack([a, b]))]
    obs += [LoadObservation(i, "L2", p) for i, p in enumerate(a)]  # one place
    obs += [LoadObservation(99, "L2", LOAD + [5.0, 0, 0])]  # and one stray sighting
    found = loads_at_two_places(obs)
    assert list(found) == ["L1"] and len(found["L1"]) == 2
    w = loads_at_two_places_warning(found)
    assert w.name == "load_seen_at_two_places" and w.count == 1 and "L1 at (2.00, 2.70, 1.40)" in w.message
    mid = LOAD + [0.9, 0, 0]  # e.g. the information-weighted mean of both places
    lm = LoadMap(
        "ekf", [LoadEstimate("L1", mid, np.eye(3) * 1e-8, 70), LoadEstimate("L2", LOAD, np.eye(3) * 1e-8, 40)]
    )
    out = add_places_spread(lm, found)
    sx = np.sqrt(out.loads[0].cov_world[0, 0])
    assert 0.9 < sx < 1.2  # the places 0.9 and 1.1 m either side
    assert np.array_equal(out.loads[1].cov_world, lm.loads[1].cov_world)


def test_a_run_names_a_label_read_at_two_places(tmp_path, capsys):
    """The sample flight with its second load's label read as the first's id (a duplicated
    label): the run warns, and no map keeps a millimetre sigma for that id."""
    import csv
    import json
    import shutil
    from pathlib import Path

    from fusion.cli import main

    sample = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
    log = tmp_path / "log"
    shutil.copytree(sample, log)
    out = tmp_path / "out"
    args = ["run", str(log), "--out", str(out), "--quiet", "--workers", "1", "--no-incremental"]
    assert main(args) == 0
    assert "load_seen_at_two_places" not in capsys.readouterr().out
    cache = out / "detections.csv"
    cache.write_text(cache.read_text().replace(",1/P-02-2,", ",1/P-01-2,"))
    assert main([*args, "--force"]) == 0
    text = capsys.readouterr().out
    assert "detections reused" in text and "warning: [load_seen_at_two_places] x1" in text
    assert "P-01-2 at (1.50, 2.70, 1.40), (3.50, 2.70, 1.40)" in text
    names = [w["name"] for w in json.loads((out / "metrics.json").read_text())["warnings"]]
    assert "load_seen_at_two_places" in names
    for est in ("pnp", "smoother", "ekf"):
        with open(out / f"loads_{est}.csv", encoding="utf-8") as f:
            row = next(r for r in csv.DictReader(f) if r["id"] == "P-01-2")
        assert float(row["sigma_x_m"]) > 0.5, est  # the places are 2 m apart along x


def test_a_maps_departure_from_the_smoothers_is_added():
    from fusion.estimate.loadconsider import add_departure

    own = np.diag([1e-8, 4e-8, 1e-8])
    ref = LoadMap("smoother", [LoadEstimate("L1", LOAD, np.eye(3) * 1e-8, 50)])
    moved = LOAD + [0.0003, -0.0004, 0.0]
    lm = LoadMap("ekf", [LoadEstimate("L1", moved, own, 50, np.eye(3)), LoadEstimate("L2", LOAD, own, 9)])
    out = add_departure(lm, ref)
    d = moved - LOAD
    assert np.allclose(out.loads[0].cov_world, own + np.outer(d, d), atol=1e-18)
    assert out.loads[0].p_world is moved and np.array_equal(out.loads[0].cov_shared, np.eye(3))
    assert out.loads[1].cov_world is own  # not in the smoother's map: kept


def test_the_floors_common_shift_is_shared():
    """A load's share of the floor's common shift (a rigid motion of the codes only their
    priors fix) moves into its shared part: J Cov(delta) J^T, J turning about the codes'
    centroid; the covariance stays; a share the covariance cannot hold is scaled into it."""
    from fusion.estimate.asbuilt import common_shift
    from fusion.estimate.loadconsider import add_floor_shift
    from fusion.warehouse.merge import _fuse

    xy = np.array([[x, y] for x in range(3) for y in range(3)], dtype=float)
    Q = np.repeat(np.diag([0.01**2, 0.01**2, np.radians(1.0) ** 2])[None], len(xy), axis=0)
    centroid, cov_delta = common_shift(xy, Q)
    assert np.allclose(centroid, [1.0, 1.0])
    p = np.array([4.0, 1.0, 1.5])  # 3 m from the centroid along x: the turn moves it along y
    J = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 3.0], [0.0, 0.0, 0.0]])
    T = J @ cov_delta @ J.T
    wide, tight = 2 * T + np.eye(3) * 1e-6, np.eye(3) * 1e-6
    lm = LoadMap("smoother", [LoadEstimate("L1", p, wide, 40), LoadEstimate("L2", p, tight, 40, tight / 4)])
    out = add_floor_shift(lm, centroid, cov_delta)
    a, b = out.loads
    assert np.array_equal(a.cov_world, wide) and np.allclose(a.cov_shared, T)
    assert T[1, 1] > T[0, 0] > 0 and T[2, 2] == 0
    assert np.all(np.linalg.eigvalsh(b.cov_world - b.cov_shared) > 0)  # scaled into what it holds
    # two flights' estimates fused: the shift is not averaged down
    _, P, _ = _fuse(p, a.cov_world, a.cov_shared, p, a.cov_world, a.cov_shared)
    assert np.all(np.linalg.eigvalsh(P - T) > 0) and P[1, 1] < a.cov_world[1, 1]


def test_at_least_grows_a_covariance_only_where_it_holds_less():
    from fusion.estimate.loadconsider import at_least

    C = np.diag([4.0, 1.0, 1.0])
    D = np.diag([1.0, 3.0, 0.5])
    assert np.allclose(at_least(C, D), np.diag([4.0, 3.0, 1.0]))
    rng = np.random.default_rng(0)
    for _ in range(20):
        A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        C, D = A @ A.T + 0.1 * np.eye(3), B @ B.T
        out = at_least(C, D)
        assert np.linalg.eigvalsh(out - C).min() > -1e-9 and np.linalg.eigvalsh(out - D).min() > -1e-9
        assert np.allclose(at_least(C, 0.5 * C), C)  # already held: unchanged
    assert np.allclose(at_least(np.zeros((3, 3)), D), D)  # no own covariance: the pose's


def _code_centre_stated(camera, p_cam, side, d):
    """What single-code PnP's size-and-bearing model reads for a frontal code of `side` m at the
    true centre p_cam once the intrinsics are stated off by d = [dfu, dfv, dcu, dcv]: the depth
    from the mean of the depths its two sizes in px give, the lateral position from the
    bearing (loadconsider's docstring)."""
    X, Y, Z = p_cam
    fu, fv, cu, cv = camera.fu, camera.fv, camera.cu, camera.cv
    u, v = cu + fu * X / Z, cv + fv * Y / Z  # the centre in px (the true intrinsics)
    size_u, size_v = fu * side / Z, fv * side / Z
    fu_, fv_, cu_, cv_ = fu + d[0], fv + d[1], cu + d[2], cv + d[3]
    Z_ = 0.5 * (fu_ * side / size_u + fv_ * side / size_v)
    return np.array([(u - cu_) * Z_ / fu_, (v - cv_) * Z_ / fv_, Z_])


def test_each_intrinsic_moves_the_code_centre_as_the_size_and_bearing_model_does():
    """intrinsics_jacobian column by column against the model it linearises (the PnP test in
    test_intrinsics.py moves fu and fv together, where the two columns' lateral terms cancel)."""
    from fusion.estimate.loadconsider import intrinsics_jacobian

    p = np.array([0.31, -0.22, 1.4])
    J = intrinsics_jacobian(CAMERA, p)[0]
    for i, step in enumerate((0.05, 0.05, 0.01, 0.01)):
        d = np.zeros(4)
        d[i] = step
        moved = (_code_centre_stated(CAMERA, p, 0.1, d) - _code_centre_stated(CAMERA, p, 0.1, -d)) / (2 * step)
        np.testing.assert_allclose(J[:, i], moved, rtol=1e-4, atol=1e-12, err_msg=f"column {i}")


def test_the_mount_rotation_term_is_the_sightings_derivative():
    """common_terms' U_rot, the mean over a load's sightings of d p_world / d theta for a small
    rotation theta of the front camera about its centre in the body frame, against central
    differences of the world point, for a load off the camera's axis in every direction."""
    from dataclasses import replace

    from fusion.estimate.loadconsider import common_terms
    from fusion.geometry import so3_exp

    traj, _ = _pass(n=5)
    target = LOAD + np.array([0.2, 0.0, -0.15])  # off the axis: every component of the ray
    T_cw = np.linalg.inv(CAMERA.T_world_cam(traj.T_world_body))
    p_cam = np.einsum("nij,j->ni", T_cw[:, :3, :3], target) + T_cw[:, :3, 3]
    _, _, _, U_rot, U_shift, _ = common_terms(_observations(traj, p_cam), traj, CAMERA)["L1"]

    def world_points(theta):
        T_bc = CAMERA.T_body_cam.copy()
        T_bc[:3, :3] = so3_exp(theta) @ T_bc[:3, :3]
        T_wc = replace(CAMERA, T_body_cam=T_bc).T_world_cam(traj.T_world_body)
        return np.einsum("nij,nj->ni", T_wc[:, :3, :3], p_cam) + T_wc[:, :3, 3]

    h = 1e-6
    numeric = np.column_stack(
        [(world_points(h * e) - world_points(-h * e)).mean(axis=0) / (2 * h) for e in np.eye(3)]
    )
    np.testing.assert_allclose(U_rot, numeric, atol=1e-7)
    np.testing.assert_allclose(U_shift, traj.T_world_body[0, :3, :3], atol=1e-12)  # yaw only: every R_wb alike


def test_a_sighting_takes_the_nearest_poses_covariance():
    """A sighting between two poses hangs from the nearer one: with a different position sigma
    at each of three poses 0.1 s apart, a sighting 30 ms after the first takes the first's."""
    sigmas = (1e-4, 2e-4, 4e-4)
    covs = np.zeros((3, 6, 6))
    for k, s in enumerate(sigmas):
        covs[k, 3:, 3:] = np.eye(3) * s**2
    T = np.array([make_T(YAW_90, [LOAD[0], LOAD[1] - 1.25, LOAD[2]])] * 3)
    traj = Trajectory("pnp", np.array([0, 100_000_000, 200_000_000]), T, covs)
    p_cam = (np.linalg.inv(CAMERA.T_world_cam(T[0])) @ np.append(LOAD, 1.0))[:3]
    for t_ns, k in ((30_000_000, 0), (70_000_000, 1), (130_000_000, 1), (190_000_000, 2)):
        obs = [LoadObservation(t_ns, "L1", LOAD, None, p_cam, np.eye(3) * 1e-8)]
        lm = LoadMap("pnp", [LoadEstimate("L1", LOAD, np.zeros((3, 3)), 1)])
        cov = add_load_consider_covariance(lm, obs, traj, CAMERA, 0.0).loads[0].cov_world
        np.testing.assert_allclose(cov, np.eye(3) * sigmas[k] ** 2, rtol=1e-9, err_msg=f"t {t_ns} ns")
