"""The paper's Algorithms 1-6 (fusion.qr.paper): hand-computed cases from its equations and an
end-to-end check with corners projected by the camera model; the transcribed tables."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from fusion.camera import CameraModel
from fusion.conventions import R_BODY_FLOORCAM, R_BODY_FRONTCAM
from fusion.errors import EstimationError
from fusion.geometry import inv_T, make_T, rot_z, transform_points
from fusion.qr import paper
from fusion.types import LoadObservation, QRDetection, Trajectory
from fusion.world import LoadCode, World

DATA = Path(__file__).resolve().parents[1] / "data" / "paper"
FL = 500.0
W, H = 640, 480
FC = np.array([(W - 1) / 2, (H - 1) / 2])


def floor_camera(**kw) -> CameraModel:
    args = dict(cu=FC[0], cv=FC[1], T_body_cam=make_T(R_BODY_FLOORCAM, np.zeros(3)), mount="gimbaled")
    args.update(kw)
    return CameraModel(W, H, FL, FL, **args)


def front_camera() -> CameraModel:
    return CameraModel(W, H, FL, FL, FC[0], FC[1], T_body_cam=make_T(R_BODY_FRONTCAM, np.zeros(3)))


WORLD = World(floor_side_m=0.20, payload_unit_m=1.0, load_side_m=0.15)


def square_corners(centre_px, side_px: float, beta_rad: float) -> np.ndarray:
    """Corners TL, TR, BR, BL (u right, v down) of a square whose symbol 'right' points at angle
    beta counter-clockwise from image right in y-up image coordinates."""
    r = 0.5 * side_px * np.array([math.cos(beta_rad), -math.sin(beta_rad)])  # v down
    up = 0.5 * side_px * np.array([-math.sin(beta_rad), -math.cos(beta_rad)])
    c = np.asarray(centre_px, float)
    return np.array([c - r + up, c + r + up, c + r - up, c - r - up])


def floor_det(payload, corners, t=0):
    return QRDetection("cam0", t, payload, corners, corners)


def project_floor(camera, payload, xy, T_world_body, t=0):
    T_world_cam = T_world_body @ camera.T_body_cam
    cw = WORLD.floor_corners_world(np.array([xy[0], xy[1], 0.0]))
    uv = camera.project(transform_points(inv_T(T_world_cam), cw))
    return floor_det(payload, uv, t)


# --------------------------------------------------------------------------- Algorithms 1-3


def test_matched_code_under_centre_gives_eq2_height():
    side_px = 80.0
    corners = square_corners(FC, side_px, math.pi / 2)  # yaw 0: world +x is image up
    pose = paper.localize_frame([floor_det("0/3/4", corners)], floor_camera(), WORLD)
    assert pose.case == paper.MATCHED
    assert pose.z == pytest.approx(0.20 * FL / side_px)  # Eq. 2
    assert (pose.x, pose.y) == (3.0, 4.0)  # Alg. 2 lines 4-5
    assert pose.yaw_rad == pytest.approx(0.0, abs=1e-12)
    assert pose.floor_payload == "0/3/4"


@pytest.mark.parametrize(
    "yaw_deg, expected_dxy",
    [
        (0, (0.0, +1.0)),  # heading +x: image right = world -y, so the drone is at +y of the code
        (90, (-1.0, 0.0)),  # heading +y: image right = world +x
        (180, (0.0, -1.0)),
        (270, (+1.0, 0.0)),
    ],
)
def test_not_matched_offset_to_the_right(yaw_deg, expected_dxy):
    side_px, du = 50.0, 40.0
    yaw = math.radians(yaw_deg)
    corners = square_corners(FC + [du, 0.0], side_px, math.pi / 2 - yaw)
    pose = paper.localize_frame([floor_det("0/2/5", corners)], floor_camera(), WORLD)
    assert pose.case == paper.NOT_MATCHED
    d = 0.20 * du / side_px  # Eq. 7
    assert pose.x == pytest.approx(2.0 + expected_dxy[0] * d, abs=1e-12)
    assert pose.y == pytest.approx(5.0 + expected_dxy[1] * d, abs=1e-12)
    assert pose.z == pytest.approx((0.20 / math.sqrt(2)) * FL / (side_px / math.sqrt(2)))  # Eq. 5
    assert math.degrees(pose.yaw_rad) % 360 == pytest.approx(yaw_deg, abs=1e-9)


def test_not_matched_offset_ahead_at_yaw_45():
    # code 30 px above the image centre = ahead of the drone; heading 45 deg
    side_px, dv = 60.0, -30.0
    yaw = math.radians(45)
    corners = square_corners(FC + [0.0, dv], side_px, math.pi / 2 - yaw)
    pose = paper.localize_frame([floor_det("0/0/0", corners)], floor_camera(), WORLD)
    d = 0.20 * 30 / side_px
    assert pose.x == pytest.approx(-d * math.cos(yaw))
    assert pose.y == pytest.approx(-d * math.sin(yaw))


def test_algorithm1_picks_the_code_nearest_the_centre_and_th_decides_the_branch():
    near = square_corners(FC + [6.0, 0.0], 50.0, math.pi / 2)
    far = square_corners(FC + [150.0, 0.0], 50.0, math.pi / 2)
    dets = [floor_det("0/9/9", far), floor_det("0/1/1", near)]
    pose = paper.localize_frame(dets, floor_camera(), WORLD, th_px=5.0)
    assert pose.floor_payload == "0/1/1" and pose.case == paper.NOT_MATCHED
    assert pose.min_dist_px == pytest.approx(6.0)
    pose = paper.localize_frame(dets, floor_camera(), WORLD, th_px=6.5)
    assert pose.case == paper.MATCHED and (pose.x, pose.y) == (1.0, 1.0)


def test_no_valid_floor_code_returns_none():
    c = square_corners(FC, 50.0, math.pi / 2)
    cam = floor_camera()
    assert paper.localize_frame([], cam, WORLD) is None
    assert paper.localize_frame([floor_det("hello", c)], cam, WORLD) is None
    assert paper.localize_frame([floor_det("1/box", c)], cam, WORLD) is None  # load on cam0
    bounded = World(bounds_x_m=(0.0, 5.0), bounds_y_m=(0.0, 5.0))
    assert paper.localize_frame([floor_det("0/50/1", c)], cam, bounded) is None
    # a bad code next to a good one is ignored
    pose = paper.localize_frame([floor_det("../etc", c), floor_det("0/1/2", c)], cam, WORLD)
    assert (pose.x, pose.y) == (1.0, 2.0)


def test_a_camera_mount_unlike_the_papers_is_refused():
    cam = floor_camera(T_body_cam=make_T(R_BODY_FLOORCAM @ rot_z(math.radians(30)), np.zeros(3)))
    with pytest.raises(EstimationError):
        paper.localize_frame([floor_det("0/0/0", square_corners(FC, 50, 0.0))], cam, WORLD)


def random_level_pose(rng):
    return make_T(
        rot_z(rng.uniform(-math.pi, math.pi)),
        [rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(0.8, 3.0)],
    )


def test_end_to_end_projected_perpendicular_camera_is_exact_when_not_matched():
    """Gimbaled camera straight down: Algorithm 3 is exact (the image is a similarity of the
    floor), so (x, y, h, yaw) come back to rounding error."""
    rng = np.random.default_rng(1)
    cam = floor_camera()
    for _ in range(40):
        T = random_level_pose(rng)
        dets = [project_floor(cam, f"0/{i}/{j}", (i, j), T) for i in (-1, 0, 1) for j in (-1, 0, 1)]
        dets = [d for d in dets if np.all((d.corners_px >= 0) & (d.corners_px < [W, H]))]
        pose = paper.localize_frame(dets, cam, WORLD, th_px=0.0)
        assert pose is not None and pose.case == paper.NOT_MATCHED
        np.testing.assert_allclose(pose.xyz, T[:3, 3], atol=1e-9)
        assert math.remainder(pose.yaw_rad - math.atan2(T[1, 0], T[0, 0]), 2 * math.pi) == pytest.approx(
            0.0, abs=1e-9
        )


def test_matched_case_error_is_bounded_by_th_times_depth_over_fl():
    """Algorithm 2 drops the up-to-Th-pixel offset: x/y error <= Th * h / FL (its approximation)."""
    rng = np.random.default_rng(2)
    cam = floor_camera()
    th = 8.0
    for _ in range(30):
        h = rng.uniform(0.8, 3.0)
        r = rng.uniform(0, th) * h / FL
        a = rng.uniform(-math.pi, math.pi)
        T = make_T(rot_z(rng.uniform(-math.pi, math.pi)), [r * math.cos(a), r * math.sin(a), h])
        pose = paper.localize_frame([project_floor(cam, "0/0/0", (0, 0), T)], cam, WORLD, th)
        assert pose.case == paper.MATCHED
        assert np.hypot(pose.x - T[0, 3], pose.y - T[1, 3]) <= th * h / FL + 1e-12
        assert pose.z == pytest.approx(h, rel=1e-9)  # Eq. 2 is exact when perpendicular


def test_geometric_centre_vs_principal_point_and_distortion():
    rng = np.random.default_rng(3)
    T = random_level_pose(rng)
    off = floor_camera(cu=FC[0] + 12.0, cv=FC[1] - 7.0)
    det = project_floor(off, "0/0/0", (0, 0), T)
    faithful = paper.localize_frame([det], off, WORLD, th_px=0.0)
    principal = paper.localize_frame([det], off, WORLD, th_px=0.0, centre="principal")
    np.testing.assert_allclose(principal.xyz, T[:3, 3], atol=1e-9)
    assert np.hypot(*(faithful.xyz - T[:3, 3])[:2]) > 0.01  # 14 px * h / FL
    dist = floor_camera(distortion=[-0.25, 0.08, 0.001, -0.0005])
    det = project_floor(dist, "0/0/0", (0, 0), T)
    raw = paper.localize_frame([det], dist, WORLD, th_px=0.0)
    und = paper.localize_frame([det], dist, WORLD, th_px=0.0, undistort=True)
    np.testing.assert_allclose(und.xyz, T[:3, 3], atol=1e-7)
    assert np.max(np.abs(raw.xyz - T[:3, 3])) > 1e-3


def test_paper_trajectory_skips_frames_without_floor_codes():
    cam = floor_camera()
    T = make_T(rot_z(0.3), [0.1, 0.2, 1.5])
    frames = {
        200: [project_floor(cam, "0/0/0", (0, 0), T, 200)],
        100: [],
        300: [floor_det("x", np.zeros((4, 2)))],
    }
    traj = paper.paper_trajectory(frames, cam, WORLD)
    assert traj.name == "paper" and traj.timestamps_ns.tolist() == [200]
    assert traj.covariances is None
    np.testing.assert_allclose(traj.T_world_body[0], T, atol=1e-9)


# --------------------------------------------------------------------------- Algorithms 4-6

DRONE = np.array([1.0, 2.0, 1.5])
SIDE_PX = 50.0
S = 0.15 / SIDE_PX  # m per px on the load's face
DQW = 0.15 * FL / SIDE_PX  # Alg. 6 line 4 for a square: VC_r FL / VC_f = QR_Lr FL / QR_Lf


def load_det(du, dv, side_px=SIDE_PX):
    c = square_corners(FC + [du, dv], side_px, 0.0)
    return QRDetection("cam1", 7, "1/box-1", c, c)


@pytest.mark.parametrize(
    "yaw_deg, expected",
    [
        # code 30 px right of and 20 px above the centre: right of the heading is heading - 90 deg
        (0, (1.0 + DQW, 2.0 - 30 * S)),
        (90, (1.0 + 30 * S, 2.0 + DQW)),
        (180, (1.0 - DQW, 2.0 + 30 * S)),
        (270, (1.0 - 30 * S, 2.0 - DQW)),
        (
            45,
            (
                1.0 + DQW * math.cos(math.pi / 4) + 30 * S * math.cos(-math.pi / 4),
                2.0 + DQW * math.sin(math.pi / 4) + 30 * S * math.sin(-math.pi / 4),
            ),
        ),
    ],
)
def test_not_matched_mapping_branches(yaw_deg, expected):
    obs = paper.map_loads_frame([load_det(30.0, -20.0)], front_camera(), WORLD, DRONE, math.radians(yaw_deg))
    assert len(obs) == 1 and obs[0].load_id == "box-1" and obs[0].timestamp_ns == 7
    np.testing.assert_allclose(obs[0].p_world, [*expected, 1.5 + 20 * S], atol=1e-12)


@pytest.mark.parametrize("yaw_deg", [0, 90, 180, 270, 123])
def test_not_matched_mapping_left_side_below_and_on_the_centre_column(yaw_deg):
    yaw = math.radians(yaw_deg)
    fwd = np.array([math.cos(yaw), math.sin(yaw)])
    right = np.array([math.sin(yaw), -math.cos(yaw)])
    obs = paper.map_loads_frame([load_det(-25.0, 15.0)], front_camera(), WORLD, DRONE, yaw)
    np.testing.assert_allclose(
        obs[0].p_world, [*(DRONE[:2] + DQW * fwd - 25 * S * right), 1.5 - 15 * S], atol=1e-12
    )
    obs = paper.map_loads_frame([load_det(0.0, 15.0)], front_camera(), WORLD, DRONE, yaw)
    np.testing.assert_allclose(obs[0].p_world[:2], DRONE[:2] + DQW * fwd, atol=1e-12)


def test_matched_mapping_and_axis_tolerance():
    # matched: Alg. 5 -- the code's offset (< Th) is dropped, QR_rz = D_rz
    obs = paper.map_loads_frame([load_det(3.0, -2.0)], front_camera(), WORLD, DRONE, 0.0)
    np.testing.assert_allclose(obs[0].p_world, [1.0 + DQW, 2.0, 1.5], atol=1e-12)
    # 90.3 deg is within AXIS_TOL_DEG of 90: the axis branch snaps the heading
    obs = paper.map_loads_frame([load_det(30.0, 0.0)], front_camera(), WORLD, DRONE, math.radians(90.3))
    np.testing.assert_allclose(obs[0].p_world[:2], [1.0 + 30 * S, 2.0 + DQW], atol=1e-12)
    obs = paper.map_loads_frame(
        [load_det(30.0, 0.0)], front_camera(), WORLD, DRONE, math.radians(90.3), axis_tol_deg=0.0
    )
    assert abs(obs[0].p_world[0] - (1.0 + 30 * S)) > 1e-3


def test_end_to_end_load_mapping_perpendicular_is_exact():
    rng = np.random.default_rng(4)
    cam = front_camera()
    for yaw_deg in [0, 90, 180, 270, *rng.uniform(0, 360, 8)]:
        yaw = math.radians(yaw_deg)
        fwd = np.array([math.cos(yaw), math.sin(yaw), 0])
        right = np.array([math.sin(yaw), -math.cos(yaw), 0])
        drone = np.array([*rng.uniform(-3, 3, 2), rng.uniform(0.5, 3)])
        p = (
            drone
            + rng.uniform(0.8, 2.5) * fwd
            + rng.uniform(-0.4, 0.4) * right
            + [0, 0, rng.uniform(-0.3, 0.3)]
        )
        code = LoadCode("L", tuple(p), yaw + math.pi)
        T_world_cam = make_T(rot_z(yaw), drone) @ cam.T_body_cam
        uv = cam.project(transform_points(inv_T(T_world_cam), WORLD.load_corners_world(code)))
        obs = paper.map_loads_frame(
            [QRDetection("cam1", 0, "1/L", uv, uv)], cam, WORLD, drone, yaw, th_px=0.0, axis_tol_deg=1e-9
        )
        np.testing.assert_allclose(obs[0].p_world, p, atol=1e-9)


def test_map_loads_frame_ignores_floor_and_foreign_codes():
    c = square_corners(FC, 50, 0.0)
    dets = [QRDetection("cam1", 0, "0/1/1", c, c), QRDetection("cam1", 0, "\x00bad", c, c)]
    assert paper.map_loads_frame(dets, front_camera(), WORLD, DRONE, 0.0) == []


def test_aggregate_loads_means_and_covariance_of_the_mean():
    rng = np.random.default_rng(5)
    P = rng.normal([1, 2, 3], 0.01, size=(5, 3))
    obs = [LoadObservation(i, "a", p) for i, p in enumerate(P)] + [LoadObservation(9, "b", np.ones(3))]
    m = paper.aggregate_loads(obs).by_id()
    np.testing.assert_allclose(m["a"].p_world, P.mean(axis=0))
    np.testing.assert_allclose(m["a"].cov_world, np.cov(P.T) / 5)
    assert m["a"].n_obs == 5 and m["b"].n_obs == 1 and m["b"].cov_world is None


# --------------------------------------------------------------------------- transcribed tables


def _read(name):
    with open(DATA / name, newline="") as f:
        return list(csv.DictReader(f))


def test_tables_a1_a4_cover_50_images_and_only_the_listed_rows_disagree():
    rows = sum((_read(f"table_a{i}.csv") for i in range(1, 5)), [])
    assert sorted({int(r["image"]) for r in rows}) == list(range(1, 51))
    assert len(rows) == 200
    bad = set()
    for r in rows:
        d = abs(float(r["real"]) - float(r["estimate"]))
        if r["axis"] == "yaw":
            d = min(d, 360 - d)
        if abs(d - float(r["abs_error"])) > 0.015:
            bad.add((int(r["image"]), r["axis"]))
    assert bad == {
        (1, "y"),
        (2, "y"),
        (2, "z"),
        (3, "z"),
        (4, "z"),
        (7, "z"),
        (9, "yaw"),
        (14, "z"),
        (17, "x"),
        (18, "z"),
        (19, "z"),
        (27, "z"),
        (28, "z"),
        (32, "yaw"),
        (33, "yaw"),
    }
    means = {ax: np.mean([float(r["abs_error"]) for r in rows if r["axis"] == ax]) for ax in "xyz"}
    assert means == pytest.approx({"x": 0.83, "y": 0.32, "z": 2.95}, abs=0.08)


def test_table_a5_averages_are_the_mean_of_five_results():
    rows = _read("table_a5.csv")
    assert len(rows) == 30
    for r in rows:
        res = [float(r[f"result{k}"]) for k in range(1, 6)]
        assert np.mean(res) == pytest.approx(float(r["average"]), abs=0.011)
        assert abs(float(r["real"]) - float(r["average"])) == pytest.approx(float(r["abs_error"]), abs=0.011)
    means = [np.mean([float(r["abs_error"]) for r in rows if r["axis"] == ax]) for ax in "xyz"]
    assert means == pytest.approx([0.93, 1.64, 2.11], abs=0.005)


def test_paper_load_observations_use_the_nearest_floor_pose():
    traj = paper.paper_trajectory(
        {0: [project_floor(floor_camera(), "0/0/0", (0, 0), make_T(rot_z(0.0), DRONE - [1, 2, 0]))]},
        floor_camera(),
        WORLD,
    )
    frames = {10_000_000: [load_det(0.0, 0.0)], 900_000_000: [load_det(0.0, 0.0)]}
    obs = paper.paper_load_observations(frames, front_camera(), WORLD, traj)
    assert [o.timestamp_ns for o in obs] == [7]  # the second frame has no pose near it
    np.testing.assert_allclose(obs[0].p_world, [0.0 + DQW, 0.0, 1.5], atol=1e-9)


# --------------------------------------------------------------------------- found by a mutation sample
# (scripts/mutation.py --paths fusion/qr/paper.py, thirty-first session: each test below fails
# under a mutant that survived the tests above)


def test_yaw_averages_the_unit_directions_of_a_non_square_code():
    """Sec. 3.2.5: the two directions (symbol right, symbol up turned by -90 deg) are averaged as
    unit vectors, so a code foreshortened along one side does not weigh that side less."""
    tl = np.array([100.0, 100.0])
    b1, b2 = math.radians(20.0), math.radians(26.0)  # world +x at b1, world +y at b2 + 90 deg
    tr = tl + 80.0 * np.array([math.cos(b1), -math.sin(b1)])  # v down
    bl = tl - 40.0 * np.array([math.cos(b2 + math.pi / 2), -math.sin(b2 + math.pi / 2)])
    corners = np.array([tl, tr, tr + (bl - tl), bl])
    assert paper.yaw_from_floor_corners(corners) == pytest.approx(math.pi / 2 - math.radians(23.0), abs=1e-12)


def test_algorithm1_skips_a_code_with_unusable_corners_and_keeps_the_first_of_a_tie():
    good = square_corners(FC + [40.0, 0.0], 50.0, math.pi / 2)
    nan = np.full((4, 2), np.nan)
    pose = paper.localize_frame([floor_det("0/7/7", nan), floor_det("0/1/1", good)], floor_camera(), WORLD)
    assert pose is not None and pose.floor_payload == "0/1/1"
    # two codes equally far from the centre: line 7's strict '<' keeps the first one listed
    twin = square_corners(FC - [40.0, 0.0], 50.0, math.pi / 2)
    pose = paper.localize_frame([floor_det("0/1/1", good), floor_det("0/2/2", twin)], floor_camera(), WORLD)
    assert pose.floor_payload == "0/1/1"
    pose = paper.localize_frame([floor_det("0/2/2", twin), floor_det("0/1/1", good)], floor_camera(), WORLD)
    assert pose.floor_payload == "0/2/2"


def test_a_code_exactly_th_from_the_centre_is_matched():
    """Algorithm 1 line 10 and Algorithm 4 line 5: MinDist <= Th is the matched case."""
    corners = square_corners(FC + [3.0, 4.0], 50.0, math.pi / 2)
    d = paper.localize_frame([floor_det("0/1/1", corners)], floor_camera(), WORLD, th_px=0.0).min_dist_px
    assert (
        paper.localize_frame([floor_det("0/1/1", corners)], floor_camera(), WORLD, th_px=d).case
        == paper.MATCHED
    )
    load = QRDetection("cam1", 7, "1/box-1", corners, corners)
    obs = paper.map_loads_frame([load], front_camera(), WORLD, DRONE, 0.0, th_px=d)
    np.testing.assert_allclose(obs[0].p_world, [1.0 + 0.15 * FL / 50.0, 2.0, 1.5], atol=1e-12)  # Alg. 5


def test_a_refused_mount_names_the_camera():
    turned = make_T(R_BODY_FLOORCAM @ rot_z(math.radians(30)), np.zeros(3))
    with pytest.raises(EstimationError, match="floor camera mount is 30.0 deg"):
        paper.localize_frame(
            [floor_det("0/0/0", square_corners(FC, 50, 0.0))], floor_camera(T_body_cam=turned), WORLD
        )
    cam = CameraModel(
        W, H, FL, FL, FC[0], FC[1], T_body_cam=make_T(R_BODY_FRONTCAM @ rot_z(0.5), np.zeros(3))
    )
    with pytest.raises(EstimationError, match="front camera mount"):
        paper.map_loads_frame([load_det(0.0, 0.0)], cam, WORLD, DRONE, 0.0)


def test_paper_trajectory_passes_its_options_to_every_frame():
    rng = np.random.default_rng(6)
    off = floor_camera(cu=FC[0] + 12.0, cv=FC[1] - 7.0, distortion=[-0.25, 0.08, 0.001, -0.0005])
    Ts = {t: random_level_pose(rng) for t in (300, 100, 200)}
    frames = {t: [project_floor(off, "0/0/0", (0, 0), T, t)] for t, T in Ts.items()}
    exact = paper.paper_trajectory(frames, off, WORLD, 0.0, undistort=True, centre="principal", name="alg1")
    assert exact.name == "alg1" and exact.timestamps_ns.tolist() == [100, 200, 300]
    assert exact.timestamps_ns.dtype == np.int64
    for T_est, t in zip(exact.T_world_body, exact.timestamps_ns, strict=True):
        np.testing.assert_allclose(T_est, Ts[int(t)], atol=1e-7)
    for kwargs in ({"undistort": False}, {"centre": "geometric"}):
        other = paper.paper_trajectory(
            frames, off, WORLD, 0.0, **{"undistort": True, "centre": "principal", **kwargs}
        )
        assert np.max(np.abs(other.T_world_body[:, :3, 3] - exact.T_world_body[:, :3, 3])) > 1e-3
    # Th: with a large one every frame is the matched case, placed on the code itself
    matched = paper.paper_trajectory(frames, off, WORLD, 1e4, undistort=True, centre="principal")
    np.testing.assert_allclose(matched.T_world_body[:, :2, 3], 0.0, atol=1e-12)
    # codes classified by the caller are used instead of the frame's detections
    from fusion.qr.codes import classify

    codes = {200: classify(frames[200], WORLD)}
    only = paper.paper_trajectory({t: [] for t in frames}, off, WORLD, 0.0, codes=codes)
    assert only.timestamps_ns.tolist() == [200]


@pytest.mark.parametrize("axis", [0, 90, 180, 270])
def test_each_axis_branch_snaps_a_heading_within_the_tolerance(axis):
    """Algorithm 6 lines 11, 17, 23, 29: D_r-theta within AXIS_TOL_DEG of an axis is that axis
    (also from below, across 360 deg for the 0 axis)."""
    assert paper._axis_branch((axis - 0.3) % 360.0, 0.5) == axis
    assert paper._axis_branch(axis + 0.5, 0.5) == axis
    assert paper._axis_branch(axis + 0.6, 0.5) is None
    yaw = math.radians(axis + 0.3)
    snapped = paper.map_loads_frame([load_det(30.0, 0.0)], front_camera(), WORLD, DRONE, yaw)
    exact = paper.map_loads_frame([load_det(30.0, 0.0)], front_camera(), WORLD, DRONE, math.radians(axis))
    np.testing.assert_allclose(snapped[0].p_world, exact[0].p_world, atol=1e-12)
    general = paper.map_loads_frame(
        [load_det(30.0, 0.0)], front_camera(), WORLD, DRONE, yaw, axis_tol_deg=0.0
    )
    assert np.max(np.abs(general[0].p_world - exact[0].p_world)) > 1e-3


def test_matched_mapping_goes_along_the_heading():
    yaw = math.radians(30.0)
    obs = paper.map_loads_frame([load_det(1.0, -1.0)], front_camera(), WORLD, DRONE, yaw)
    np.testing.assert_allclose(
        obs[0].p_world, [1.0 + DQW * math.cos(yaw), 2.0 + DQW * math.sin(yaw), 1.5], atol=1e-12
    )


def distorted_front_camera() -> CameraModel:
    """A front camera whose principal point is off the image centre and whose lens distorts:
    what `undistort` and `centre="principal"` are for."""
    return CameraModel(
        W,
        H,
        FL,
        FL,
        FC[0] + 9.0,
        FC[1] + 5.0,
        distortion=[-0.2, 0.05, 0.0, 0.0],
        T_body_cam=make_T(R_BODY_FRONTCAM, np.zeros(3)),
    )


def test_map_loads_frame_keeps_the_raw_corners_and_uses_the_camera_options():
    rng = np.random.default_rng(7)
    cam = distorted_front_camera()
    yaw = math.radians(rng.uniform(5, 85))
    fwd, right = np.array([math.cos(yaw), math.sin(yaw), 0]), np.array([math.sin(yaw), -math.cos(yaw), 0])
    p = DRONE + 1.6 * fwd + 0.3 * right + [0, 0, 0.2]
    T_world_cam = make_T(rot_z(yaw), DRONE) @ cam.T_body_cam
    uv = cam.project(
        transform_points(inv_T(T_world_cam), WORLD.load_corners_world(LoadCode("L", tuple(p), yaw + math.pi)))
    )
    nan = np.full((4, 2), np.nan)
    dets = [QRDetection("cam1", 0, "1/bad", nan, nan), QRDetection("cam1", 0, "1/L", uv, uv)]
    obs = paper.map_loads_frame(dets, cam, WORLD, DRONE, yaw, 0.0, undistort=True, centre="principal")
    assert [o.load_id for o in obs] == ["L"]  # the unusable code is skipped, not the end of the frame
    np.testing.assert_allclose(obs[0].p_world, p, atol=1e-7)
    np.testing.assert_array_equal(obs[0].corners_px, uv)  # as detected, not undistorted
    for kwargs in ({"undistort": False}, {"centre": "geometric"}):
        o = paper.map_loads_frame(
            dets, cam, WORLD, DRONE, yaw, 0.0, **{"undistort": True, "centre": "principal", **kwargs}
        )
        assert np.max(np.abs(o[0].p_world - p)) > 1e-3


def test_aggregate_loads_gives_two_sightings_a_covariance_and_keeps_the_name():
    P = np.array([[1.0, 2.0, 3.0], [1.2, 2.0, 2.9]])
    m = paper.aggregate_loads([LoadObservation(i, "a", p) for i, p in enumerate(P)], name="alg4")
    assert m.name == "alg4"
    np.testing.assert_allclose(m.by_id()["a"].cov_world, np.cov(P.T) / 2)
    assert paper.aggregate_loads([]).name == "paper"


def test_paper_load_observations_take_the_nearest_pose_of_several():
    cam = floor_camera()
    poses = {
        0: make_T(rot_z(0.0), [0.0, 0.0, 1.5]),
        100_000_000: make_T(rot_z(math.radians(60.0)), [0.5, -0.2, 1.5]),
    }
    traj = paper.paper_trajectory(
        {t: [project_floor(cam, "0/0/0", (0, 0), T, t)] for t, T in poses.items()}, cam, WORLD
    )
    # front frames: one with no pose within 50 ms (first, so it must not end the loop), one
    # nearer the second pose, one exactly 50 ms from the first (kept: the gap is not > max_gap_s)
    frames = {
        -300_000_000: [load_det(0.0, 0.0)],
        70_000_000: [load_det(0.0, 0.0)],
        50_000_000: [load_det(0.0, 0.0)],
    }
    obs = paper.paper_load_observations(frames, front_camera(), WORLD, traj)
    assert len(obs) == 2
    yaw = math.radians(60.0)
    far = np.array([0.5 + DQW * math.cos(yaw), -0.2 + DQW * math.sin(yaw), 1.5])
    near = np.array([0.0 + DQW, 0.0, 1.5])
    # frames in time order: 50 ms on the first pose (a tie, the earlier pose), 70 ms on the second
    np.testing.assert_allclose([o.p_world for o in obs], [near, far], atol=1e-9)
    # Th is passed on: a code 3.6 px off the centre is the matched case with the default Th only
    off = {70_000_000: [load_det(3.0, -2.0)]}
    matched = paper.paper_load_observations(off, front_camera(), WORLD, traj)
    general = paper.paper_load_observations(off, front_camera(), WORLD, traj, 0.0)
    assert np.max(np.abs(matched[0].p_world - general[0].p_world)) > 1e-3
    # codes classified by the caller: a frame missing from `loads` has none
    assert paper.paper_load_observations(frames, front_camera(), WORLD, traj, loads={}) == []


def test_paper_load_observations_pass_the_camera_options_and_the_callers_codes():
    from fusion.qr.codes import classify

    cam = distorted_front_camera()
    yaw = math.radians(-40.0)  # a negative heading, as atan2 gives it: D_r-theta is taken mod 360
    traj = Trajectory("t", np.array([0]), make_T(rot_z(yaw), DRONE)[None], None)
    fwd, right = np.array([math.cos(yaw), math.sin(yaw), 0]), np.array([math.sin(yaw), -math.cos(yaw), 0])
    p = DRONE + 1.6 * fwd - 0.4 * right + [0, 0, -0.1]
    T_world_cam = make_T(rot_z(yaw), DRONE) @ cam.T_body_cam
    corners = WORLD.load_corners_world(LoadCode("L", tuple(p), yaw + math.pi))
    uv = cam.project(transform_points(inv_T(T_world_cam), corners))
    frames = {0: [QRDetection("cam1", 0, "1/L", uv, uv)]}
    exact = paper.paper_load_observations(frames, cam, WORLD, traj, 0.0, undistort=True, centre="principal")
    np.testing.assert_allclose(exact[0].p_world, p, atol=1e-7)
    for kwargs in ({"undistort": False}, {"centre": "geometric"}):
        o = paper.paper_load_observations(
            frames, cam, WORLD, traj, 0.0, **{"undistort": True, "centre": "principal", **kwargs}
        )
        assert np.max(np.abs(o[0].p_world - p)) > 1e-3
    # the faithful default: distorted pixels as given (the paper ignores the lens, Sec. 4.2.3)
    default = paper.paper_load_observations(frames, cam, WORLD, traj, 0.0, centre="principal")
    np.testing.assert_allclose(
        default[0].p_world,
        paper.paper_load_observations(frames, cam, WORLD, traj, 0.0, undistort=False, centre="principal")[
            0
        ].p_world,
    )
    given = paper.paper_load_observations(
        frames,
        cam,
        WORLD,
        traj,
        0.0,
        undistort=True,
        centre="principal",
        loads={0: classify(frames[0], WORLD).loads},
    )
    np.testing.assert_allclose(given[0].p_world, p, atol=1e-7)
