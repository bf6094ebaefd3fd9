"""PnP estimator (fusion/qr/pnp/) and its measurement model / CRB (fusion/qr/reprojection.py).

Corners are projected with CameraModel.project from known poses plus seeded Gaussian noise."""

import math

import cv2
import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.camera import CameraModel
from fusion.conventions import (
    R_BODY_FLOORCAM,
    R_BODY_FRONTCAM,
    floor_payload,
    load_payload,
)
from fusion.geometry import (
    inv_T,
    level_frame,
    make_T,
    rot_z,
    se3_exp,
    so3_log,
    transform_points,
    wrap_angle,
    yaw_of,
)
from fusion.qr.codes import classify
from fusion.qr.pnp import (
    aggregate_load_observations,
    edge_implied_yaw,
    estimate_floor_pose,
    estimate_floor_poses,
    estimate_load_observations,
    estimate_load_observations_frames,
    pnp_load_observations,
    pnp_trajectory,
    pose_at,
)
from fusion.qr.reprojection import (
    floor_pose_crb,
    floor_reprojection,
    load_position_crb,
    symbol_reprojection,
)
from fusion.types import QRDetection, Trajectory
from fusion.world import LoadCode, World

WORLD = World(
    floor_side_m=0.20,
    payload_unit_m=1.0,
    load_side_m=0.15,
    bounds_x_m=(-10.0, 10.0),
    bounds_y_m=(-10.0, 10.0),
    # the codes these tests draw lie exactly on their payloads (tests/test_placement.py: not)
    placement_sigma_m=0.0,
    placement_sigma_deg=0.0,
)
DIST = [-0.12, 0.03, 0.0008, -0.0005]
FLOOR_CAM = CameraModel(
    640,
    480,
    600.0,
    602.0,
    321.0,
    238.5,
    distortion=DIST,
    T_body_cam=make_T(R_BODY_FLOORCAM, [0.06, -0.02, -0.04]),
)
FRONT_CAM = CameraModel(
    640,
    480,
    600.0,
    600.0,
    319.5,
    239.5,
    distortion=DIST,
    T_body_cam=make_T(R_BODY_FRONTCAM, [0.10, 0.0, 0.02]),
)
SIGMA = 0.15


def body_pose(x, y, z, yaw_deg, roll_deg=0.0, pitch_deg=0.0):
    R = Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()
    return make_T(R, [x, y, z])


def aim(T_world_body, xy, camera=FLOOR_CAM):
    """T_world_body shifted horizontally so that the camera's optical axis meets the floor at xy."""
    T_wc = camera.T_world_cam(T_world_body)
    z = T_wc[:3, 2]
    hit = T_wc[:3, 3] + (-T_wc[2, 3] / z[2]) * z
    out = T_world_body.copy()
    out[:2, 3] += np.asarray(xy, dtype=float) - hit[:2]
    return out


def floor_dets(T_world_body, centres_xy, camera=FLOOR_CAM, rng=None, sigma=0.0, ts=0):
    """Detections of floor codes at payload (x, y) seen from T_world_body."""
    out = []
    T_cam_world = inv_T(camera.T_world_cam(T_world_body))
    for x, y in centres_xy:
        cw = WORLD.floor_corners_world(np.array([x, y, 0.0]))
        uv = camera.project(transform_points(T_cam_world, cw))
        assert np.all(np.isfinite(uv)) and np.all((uv > 0) & (uv < [640, 480]))
        if rng is not None:
            uv = uv + rng.normal(0.0, sigma, uv.shape)
        out.append(QRDetection("cam0", ts, floor_payload(x, y), uv, np.round(uv)))
    return out


def load_dets(T_world_body, codes, camera=FRONT_CAM, rng=None, sigma=0.0, ts=0):
    out = []
    T_cam_world = inv_T(camera.T_world_cam(T_world_body))
    for code in codes:
        uv = camera.project(transform_points(T_cam_world, WORLD.load_corners_world(code)))
        assert np.all(np.isfinite(uv)) and np.all((uv > 0) & (uv < [640, 480]))
        if rng is not None:
            uv = uv + rng.normal(0.0, sigma, uv.shape)
        out.append(QRDetection("cam1", ts, load_payload(code.id), uv, np.round(uv)))
    return out


def floor_of(dets):
    return classify(dets, WORLD).floor


def local(T_true, T_est):
    """GTSAM's local coordinates of T_est around T_true: xi with T_est = T_true * Exp(xi)."""
    return gtsam.Pose3(T_true).localCoordinates(gtsam.Pose3(T_est))


FOUR = [(0, 0), (1, 0), (0, 1), (1, 1)]
T_FOUR = aim(body_pose(0, 0, 2.6, 35.0, roll_deg=4.0, pitch_deg=-3.0), (0.45, 0.6))


# ============================================================================ model and Jacobians


def gimbaled_camera(**kw) -> CameraModel:
    """A 640x480 floor camera on a gimbal (mount "gimbaled") at FLOOR_CAM's mount; `kw`: more
    CameraModel fields (distortion, mount_sigma_deg)."""
    return CameraModel(
        640, 480, 600.0, 600.0, 319.5, 239.5, T_body_cam=FLOOR_CAM.T_body_cam, mount="gimbaled", **kw
    )


def test_se3_exp_matches_gtsam_expmap():
    rng = np.random.default_rng(1)
    for _ in range(20):
        xi = rng.normal(0, 1.0, 6)
        np.testing.assert_allclose(se3_exp(xi), gtsam.Pose3.Expmap(xi).matrix(), atol=1e-12)
    np.testing.assert_allclose(se3_exp(np.r_[0, 0, 0, 1, 2, 3.0]), make_T(np.eye(3), [1, 2, 3]))


def test_floor_jacobian_matches_numerical_derivative_through_gtsam_expmap():
    T = body_pose(0.3, 0.2, 1.5, 120.0, 5.0, -4.0)
    pts = np.vstack([WORLD.floor_corners_world(np.array([x, y, 0.0])) for x, y in [(0, 0), (1, 0)]])
    _, J = floor_reprojection(FLOOR_CAM, T, pts)
    h = 1e-6
    Jn = np.column_stack(
        [
            (
                FLOOR_CAM.project(
                    transform_points(
                        inv_T((gtsam.Pose3(T) * gtsam.Pose3.Expmap(d)).matrix() @ FLOOR_CAM.T_body_cam), pts
                    )
                )
                - FLOOR_CAM.project(
                    transform_points(
                        inv_T((gtsam.Pose3(T) * gtsam.Pose3.Expmap(-d)).matrix() @ FLOOR_CAM.T_body_cam), pts
                    )
                )
            ).reshape(-1)
            / (2 * h)
            for d in np.eye(6) * h
        ]
    )
    np.testing.assert_allclose(J, Jn, atol=1e-4 * np.abs(J).max())


def test_symbol_jacobian_matches_numerical_derivative():
    from fusion.conventions import symbol_corners_S
    from fusion.geometry import so3_exp

    T = make_T(Rotation.from_rotvec([0.2, -2.9, 0.1]).as_matrix(), [0.3, -0.1, 2.0])
    S = symbol_corners_S(0.15)
    _, J = symbol_reprojection(FRONT_CAM, T, S)

    def f(d):
        Tp = make_T(T[:3, :3] @ so3_exp(d[:3]), T[:3, 3] + d[3:])
        return FRONT_CAM.project(transform_points(Tp, S)).reshape(-1)

    h = 1e-6
    Jn = np.column_stack([(f(d) - f(-d)) / (2 * h) for d in np.eye(6) * h])
    np.testing.assert_allclose(J, Jn, atol=1e-4 * np.abs(J).max())


# ============================================================================ exact recovery


@pytest.mark.parametrize("centres", [[(0, 0)], [(1, 1)], FOUR, [(0, 0), (1, 0)]])
@pytest.mark.parametrize("yaw_deg", [0.0, 35.0, 179.0, -100.0])
def test_exact_recovery_without_noise_body_fixed(centres, yaw_deg):
    cx = np.mean([c[0] for c in centres])
    cy = np.mean([c[1] for c in centres])
    height = 1.2 if len(centres) == 1 else 2.8
    T = aim(body_pose(0, 0, height, yaw_deg, roll_deg=6.0, pitch_deg=-5.0), (cx + 0.1, cy - 0.05))
    res = estimate_floor_pose(floor_of(floor_dets(T, centres)), FLOOR_CAM)
    assert res is not None and res.n_codes == len(centres)
    np.testing.assert_allclose(res.T_world_body, T, atol=1e-9)
    np.testing.assert_allclose(res.T_world_cam, T @ FLOOR_CAM.T_body_cam, atol=1e-9)
    assert res.reprojection_rms_px < 1e-8
    assert sorted(res.payloads) == sorted(floor_payload(*c) for c in centres)
    # The covariance at a noise-free solution is the CRB there.
    crb = floor_pose_crb(
        FLOOR_CAM, T, [WORLD.floor_corners_world(np.array([x, y, 0.0])) for x, y in centres], SIGMA
    )
    np.testing.assert_allclose(res.covariance, crb, rtol=1e-6, atol=1e-15)


def test_gimbaled_camera_gives_level_frame_and_inflated_roll_pitch():
    cam = gimbaled_camera(distortion=DIST)
    T_tilted = body_pose(0.5, 0.5, 2.6, -60.0, roll_deg=12.0, pitch_deg=8.0)
    res = estimate_floor_pose(floor_of(floor_dets(T_tilted, FOUR, camera=cam)), cam)
    level = make_T(rot_z(math.radians(-60.0)), [0.5, 0.5, 2.6])
    np.testing.assert_allclose(res.T_world_body, level, atol=1e-9)
    assert res.covariance[0, 0] == pytest.approx(math.radians(10.0) ** 2)
    assert res.covariance[1, 1] == pytest.approx(math.radians(10.0) ** 2)
    assert np.all(res.covariance[:2, 2:] == 0.0)
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_gimbaled_yaw_and_position_covariance_is_consistent():
    cam = gimbaled_camera(distortion=DIST)
    rng = np.random.default_rng(17)
    nees = []
    for _ in range(150):
        T_tilted = body_pose(0.5, 0.5, 2.6, -60.0, roll_deg=rng.normal(0, 8), pitch_deg=rng.normal(0, 8))
        res = estimate_floor_pose(
            floor_of(floor_dets(T_tilted, FOUR, camera=cam, rng=rng, sigma=SIGMA)), cam, SIGMA
        )
        xi = local(make_T(rot_z(math.radians(-60.0)), [0.5, 0.5, 2.6]), res.T_world_body)
        assert abs(xi[0]) < 1e-9 and abs(xi[1]) < 1e-9  # the level frame, exactly
        nees.append(xi[2:] @ np.linalg.solve(res.covariance[2:, 2:], xi[2:]))
    assert 0.5 * 4 <= np.mean(nees) <= 2.0 * 4, np.mean(nees)


def test_edge_implied_yaw_is_close_to_truth_for_tilted_views():
    for yaw in (-170.0, -45.0, 0.0, 90.0, 178.0):
        T = aim(body_pose(0, 0, 1.5, yaw, roll_deg=15.0, pitch_deg=-15.0), (0.05, 0.0))
        y = edge_implied_yaw(floor_of(floor_dets(T, [(0, 0)])), FLOOR_CAM)
        assert abs(wrap_angle(y - math.radians(yaw))) < math.radians(20.0)


# ============================================================================ covariance


def _floor_draws(T, centres, n, seed):
    rng = np.random.default_rng(seed)
    xis, nees, covs = [], [], []
    for _ in range(n):
        res = estimate_floor_pose(floor_of(floor_dets(T, centres, rng=rng, sigma=SIGMA)), FLOOR_CAM, SIGMA)
        xi = local(T, res.T_world_body)
        xis.append(xi)
        covs.append(res.covariance)
        nees.append(xi @ np.linalg.solve(res.covariance, xi))
    return np.array(xis), np.array(nees), np.array(covs)


@pytest.mark.parametrize(
    "centres,T",
    [
        (FOUR, T_FOUR),
        ([(0, 0)], body_pose(0.15, -0.1, 0.9, -20.0, roll_deg=3.0, pitch_deg=8.0)),
    ],
)
def test_pose_nees_is_consistent(centres, T):
    xis, nees, _ = _floor_draws(T, centres, 200, seed=7)
    assert 0.5 * 6 <= nees.mean() <= 2.0 * 6, nees.mean()


def test_covariance_convention_is_gtsams_body_frame_right_perturbation():
    """The covariance describes xi = Logmap(T_true^-1 T_est) (GTSAM's localCoordinates), in
    [rx, ry, rz, tx, ty, tz]; a PriorFactorPose3 with it gives error = NEES / 2; other
    conventions (world frame, [t, r] order) are clearly inconsistent with the same draws."""
    xis, nees, covs = _floor_draws(T_FOUR, FOUR, 200, seed=11)
    cov = covs.mean(axis=0)
    # whitened sample covariance ~ identity
    L = np.linalg.cholesky(np.linalg.inv(cov))
    w = xis @ L
    eig = np.linalg.eigvalsh(np.cov(w.T))
    assert 0.6 < eig.min() and eig.max() < 1.5, eig
    # what the back end does with it
    noise = gtsam.noiseModel.Gaussian.Covariance(cov)
    factor = gtsam.PriorFactorPose3(0, gtsam.Pose3(T_FOUR), noise)
    for xi in xis[:5]:
        v = gtsam.Values()
        v.insert(0, gtsam.Pose3(T_FOUR) * gtsam.Pose3.Expmap(xi))
        assert factor.error(v) == pytest.approx(0.5 * xi @ np.linalg.solve(cov, xi), rel=1e-6)
    # sampling T * Exp(xi), xi ~ N(0, cov), reproduces the estimates' world-frame position spread
    rng = np.random.default_rng(3)
    samples = rng.multivariate_normal(np.zeros(6), cov, 2000)
    p_samp = np.array([(gtsam.Pose3(T_FOUR) * gtsam.Pose3.Expmap(s)).translation() for s in samples])
    p_est = np.array([(gtsam.Pose3(T_FOUR) * gtsam.Pose3.Expmap(x)).translation() for x in xis])
    ratio = np.sqrt(np.diag(np.cov(p_est.T)) / np.diag(np.cov(p_samp.T)))
    assert np.all((0.75 < ratio) & (ratio < 1.33)), ratio
    # wrong conventions fail the same consistency check
    Ad = gtsam.Pose3(T_FOUR).AdjointMap()  # body -> world (left) perturbation
    swap = np.r_[3, 4, 5, 0, 1, 2]
    for bad in (Ad @ cov @ Ad.T, cov[np.ix_(swap, swap)]):
        bad_nees = np.mean([x @ np.linalg.solve(bad, x) for x in xis])
        assert not 3.0 <= bad_nees <= 12.0, bad_nees


def test_single_code_fronto_parallel_never_flips_yaw():
    """Nearly fronto-parallel single code from 2-3 m: IPPE's two solutions are close; whatever is
    picked, the yaw is never flipped by 180 deg, and the error stays near the CRB."""
    rng = np.random.default_rng(2024)
    yaw_err = []
    for k in range(250):
        yaw = rng.uniform(-180.0, 180.0)
        h = rng.uniform(2.0, 3.0)
        T = body_pose(
            rng.uniform(-0.05, 0.05),
            rng.uniform(-0.05, 0.05),
            h,
            yaw,
            roll_deg=rng.normal(0, 2.0),
            pitch_deg=rng.normal(0, 2.0),
        )
        # shift the body so that the camera (not the body origin) is over the code
        T[:2, 3] -= (T @ FLOOR_CAM.T_body_cam)[:2, 3] - T[:2, 3]
        res = estimate_floor_pose(floor_of(floor_dets(T, [(0, 0)], rng=rng, sigma=SIGMA)), FLOOR_CAM, SIGMA)
        assert res is not None
        yaw_err.append(abs(wrap_angle(yaw_of(res.T_world_body[:3, :3]) - math.radians(yaw))))
    assert max(yaw_err) < math.radians(10.0), math.degrees(max(yaw_err))


# ============================================================================ robustness


def test_rejected_codes_are_not_used():
    T = T_FOUR
    good = floor_dets(T, FOUR[:2])
    # a code outside the world's bounds, a duplicated floor code (both copies dropped), a load code
    # on the floor camera and a foreign payload, all with corners that would wreck the pose
    junk_uv = good[0].corners_px + np.array([40.0, -25.0])
    junk = [
        QRDetection("cam0", 0, "0/500/0", junk_uv, junk_uv),
        QRDetection("cam0", 0, "0/1/1", junk_uv + 5, junk_uv),
        QRDetection("cam0", 0, "0/1/1", junk_uv + 9, junk_uv),
        QRDetection("cam0", 0, "1/box-7", junk_uv, junk_uv),
        QRDetection("cam0", 0, "http://example.com", junk_uv, junk_uv),
    ]
    codes = classify(good + junk, WORLD)
    assert len(codes.floor) == 2 and len(codes.rejected) == 5
    res = estimate_floor_pose(codes.floor, FLOOR_CAM)
    np.testing.assert_allclose(res.T_world_body, T, atol=1e-9)
    traj, stats = pnp_trajectory({5: good + junk}, FLOOR_CAM, WORLD)
    np.testing.assert_allclose(traj.T_world_body[0], T, atol=1e-9)
    assert stats.rejections == {"outside_world": 1, "duplicate_floor": 2, "wrong_camera": 1, "not_ours": 1}


def test_detection_statistics_one_frame_at_a_time_are_those_of_the_whole_flight():
    """pipeline.detection_statistics classifies a frame at a time (memory): the counts and the
    rejection reasons, in their order, as classifying every frame first gives them."""
    from types import SimpleNamespace

    from fusion.pipeline import detection_statistics
    from fusion.qr.codes import rejection_counts
    from fusion.qr.detect import CameraStats, DetectionResult

    good = floor_dets(T_FOUR, FOUR[:3])
    uv = good[0].corners_px
    dets = []
    for k in range(6):
        ts = 10 * k
        dets += [QRDetection(d.camera, ts, d.payload, d.corners_px, d.corners_raw_px) for d in good[: k % 4]]
        if k % 2:
            dets += [QRDetection("cam0", ts, "http://example.com", uv, uv)]
        if k == 3:
            dets += [QRDetection("cam0", ts, "0/1/1", uv, uv), QRDetection("cam0", ts, "0/1/1", uv, uv)]
            dets += [QRDetection("cam0", ts, "0/500/0", uv, uv), QRDetection("cam0", ts, "1/box-7", uv, uv)]
        dets += [QRDetection("cam1", ts + 5, "1/box-7", uv, uv)] * (k % 3)
        if k == 4:
            dets += [QRDetection("cam1", ts + 5, "0/0/0", uv, uv), QRDetection("cam1", ts + 5, "1/", uv, uv)]
    det = DetectionResult(dets, {"cam0": CameraStats(), "cam1": CameraStats()})
    log = SimpleNamespace(floor=[0] * 6, front=[0] * 6)
    got = detection_statistics(log, det, WORLD)
    # the former formulation: every frame classified, then counted
    classified = [classify(d, WORLD) for d in det.by_frame("cam0").values()]
    front = [classify(d, WORLD) for d in det.by_frame("cam1").values()]
    n_valid = [len(c.floor) for c in classified if c.floor]
    rejected = rejection_counts(classified + front)
    assert list(got["rejected_by_reason"].items()) == list(rejected.items()) and len(rejected) >= 4
    assert got["rejected_total"] == sum(rejected.values())
    assert got["floor_frames_with_code"] == len(n_valid)
    assert got["floor_codes_per_frame_with_code"] == float(np.mean(n_valid))
    assert got["front_frames_with_load_code"] == sum(1 for c in front if c.loads) > 0
    assert got["load_sightings"] == sum(len(c.loads) for c in front)


def test_misplaced_code_is_dropped_as_outlier():
    T = T_FOUR
    dets = floor_dets(T, FOUR)
    # the code that says (1, 1) is really printed at (0.7, 0.8): its corners contradict the others
    wrong = floor_dets(T, [(0.7, 0.8)])[0]
    dets[3] = QRDetection("cam0", 0, floor_payload(1, 1), wrong.corners_px, wrong.corners_px)
    res = estimate_floor_pose(floor_of(dets), FLOOR_CAM)
    assert res.dropped_payloads == [floor_payload(1, 1)] and res.n_codes == 3
    np.testing.assert_allclose(res.T_world_body, T, atol=1e-9)


def test_no_usable_code_gives_none():
    assert estimate_floor_pose([], FLOOR_CAM) is None
    d = floor_dets(T_FOUR, [(0, 0)])[0]
    nan = QRDetection("cam0", 0, d.payload, np.full((4, 2), np.nan), d.corners_raw_px)
    assert estimate_floor_pose(floor_of([nan]), FLOOR_CAM) is None
    # corners that fit no square (a code's TR and BL swapped)
    twisted = QRDetection("cam0", 0, d.payload, d.corners_px[[0, 3, 2, 1]], d.corners_raw_px)
    assert estimate_floor_pose(floor_of([twisted]), FLOOR_CAM) is None


def test_pnp_trajectory_counts_frames():
    T1 = T_FOUR
    T2 = aim(body_pose(0, 0, 2.6, 10.0), (0.4, 0.4))
    frames = {300: floor_dets(T2, FOUR[:3], ts=300), 100: floor_dets(T1, FOUR, ts=100), 200: []}
    traj, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD)
    assert traj.timestamps_ns.tolist() == [100, 300]
    np.testing.assert_allclose(traj.T_world_body, np.stack([T1, T2]), atol=1e-9)
    assert traj.covariances.shape == (2, 6, 6)
    assert (stats.n_frames, stats.n_posed, stats.n_without_floor_code) == (3, 2, 1)
    assert stats.codes_per_pose == {3: 1, 4: 1}


# ============================================================================ load codes

LOADS = [LoadCode("box-1", (3.0, 0.3, 1.2), math.pi), LoadCode("box-2", (3.0, -0.4, 0.9), math.pi)]
T_FRONT = body_pose(1.2, 0.0, 1.1, 5.0, roll_deg=2.0, pitch_deg=3.0)


def test_load_positions_exact_without_noise():
    codes = classify(load_dets(T_FRONT, LOADS), WORLD)
    obs = estimate_load_observations(codes.loads, FRONT_CAM, WORLD, T_FRONT)
    assert [o.load_id for o in obs] == ["box-1", "box-2"]
    for o, code in zip(obs, LOADS):
        np.testing.assert_allclose(o.p_world, code.p_world, atol=1e-9)
        T_cam_world = inv_T(FRONT_CAM.T_world_cam(T_FRONT))
        np.testing.assert_allclose(
            o.p_cam, transform_points(T_cam_world, np.array([code.p_world]))[0], atol=1e-9
        )
        T_cam_sym = T_cam_world @ code.T_world_symbol
        from fusion.conventions import symbol_corners_S

        crb = load_position_crb(FRONT_CAM, T_cam_sym, symbol_corners_S(WORLD.load_side_m), SIGMA)
        np.testing.assert_allclose(o.cov_cam, crb, rtol=1e-6)


def test_load_position_nees_with_drone_pose_uncertainty():
    rng = np.random.default_rng(5)
    cov_body = np.diag([0.01, 0.01, 0.004, 0.02, 0.02, 0.01]) ** 2
    cov_body[3, 1] = cov_body[1, 3] = 0.5 * 0.01 * 0.02  # some roll/lateral coupling
    nees_cam, nees_world = [], []
    for _ in range(200):
        # truth: the drone is at T_true; the estimator believes T_hat = T_true * Exp(-xi)
        xi = rng.multivariate_normal(np.zeros(6), cov_body)
        T_hat = (gtsam.Pose3(T_FRONT) * gtsam.Pose3.Expmap(-xi)).matrix()
        dets = load_dets(T_FRONT, LOADS[:1], rng=rng, sigma=SIGMA)
        (o,) = estimate_load_observations(
            classify(dets, WORLD).loads, FRONT_CAM, WORLD, T_hat, cov_body, SIGMA
        )
        p_cam_true = transform_points(inv_T(FRONT_CAM.T_world_cam(T_FRONT)), np.array([LOADS[0].p_world]))[0]
        e = o.p_cam - p_cam_true
        nees_cam.append(e @ np.linalg.solve(o.cov_cam, e))
        e = o.p_world - np.array(LOADS[0].p_world)
        nees_world.append(e @ np.linalg.solve(o.cov_world, e))
    assert 0.5 * 3 <= np.mean(nees_cam) <= 2.0 * 3, np.mean(nees_cam)
    assert 0.5 * 3 <= np.mean(nees_world) <= 2.0 * 3, np.mean(nees_world)


def test_load_observations_along_a_flight_and_the_map():
    rng = np.random.default_rng(9)
    floor_frames, front_frames = {}, {}
    truth = {}
    for k in range(7):
        ts = 1_000_000_000 + k * 50_000_000
        T = body_pose(1.0 + 0.05 * k, 0.5, 2.2, 0.0, roll_deg=1.0)
        truth[ts] = T
        floor_frames[ts] = floor_dets(T, [(1, 0), (1, 1)], rng=rng, sigma=SIGMA, ts=ts)
        if k % 2 == 1:  # front frames between floor frames: poses interpolated
            front_frames[ts + 25_000_000] = load_dets(
                body_pose(1.025 + 0.05 * k, 0.5, 2.2, 0.0, roll_deg=1.0),
                [LoadCode("box-1", (3.5, 0.6, 2.0), math.pi)],
                rng=rng,
                sigma=SIGMA,
                ts=ts + 25_000_000,
            )
    front_frames[0] = front_frames[1_075_000_000]  # before the first pose: skipped
    traj, _ = pnp_trajectory(floor_frames, FLOOR_CAM, WORLD)
    obs = pnp_load_observations(front_frames, FRONT_CAM, WORLD, traj)
    assert len(obs) == 3
    lmap = aggregate_load_observations(obs)
    (est,) = lmap.loads
    assert est.load_id == "box-1" and est.n_obs == 3
    err = est.p_world - np.array([3.5, 0.6, 2.0])
    assert np.linalg.norm(err) < 0.05
    info = sum(np.linalg.inv(o.cov_world) for o in obs)
    np.testing.assert_allclose(est.cov_world, np.linalg.inv(info), rtol=1e-9)


def test_pose_at_interpolates_and_refuses_gaps():
    T0, T1 = body_pose(0, 0, 1, 0.0), body_pose(1, 0, 1, 90.0)
    traj = Trajectory(
        "t", np.array([0, 100_000_000]), np.stack([T0, T1]), np.stack([np.eye(6), 2 * np.eye(6)])
    )
    T, cov = pose_at(traj, 75_000_000)
    np.testing.assert_allclose(T, body_pose(0.75, 0, 1, 67.5), atol=1e-12)
    np.testing.assert_allclose(cov, 2 * np.eye(6))
    assert pose_at(traj, 50_000_000, max_gap_s=0.05) is None
    assert pose_at(traj, 200_000_000) is None
    np.testing.assert_array_equal(pose_at(traj, 100_000_500)[0], T1)  # within 1 ms: that pose


def test_per_detection_corner_sigmas_weight_the_fit_and_the_covariance():
    """Detections carrying corner_sigma_px: the pose is the weighted least-squares one, its
    covariance (J^T W J)^-1 with W = diag(1/sigma_i^2), consistent (NEES) where a single sigma
    would not be, and closer to the truth than the unweighted fit."""
    import dataclasses

    T = aim(body_pose(0, 0, 2.4, 25.0, roll_deg=2.0, pitch_deg=-3.0), (0.35, 0.35))
    centres = [(0, 0), (1, 0), (0, 1)]
    sig = np.array([0.03, 0.6, 0.6])
    rng = np.random.default_rng(5)
    nees_w, nees_1, err_w, err_1 = [], [], [], []
    for _ in range(80):
        dets = floor_dets(T, centres)
        dets = [
            dataclasses.replace(
                d, corners_px=d.corners_px + rng.normal(0.0, s, (4, 2)), corner_sigma_px=float(s)
            )
            for d, s in zip(dets, sig)
        ]
        res = estimate_floor_pose(floor_of(dets), FLOOR_CAM, 0.2)
        plain = estimate_floor_pose(
            floor_of([dataclasses.replace(d, corner_sigma_px=None) for d in dets]), FLOOR_CAM, 0.2
        )
        xi, xi1 = local(T, res.T_world_body), local(T, plain.T_world_body)
        nees_w.append(xi @ np.linalg.solve(res.covariance, xi))
        nees_1.append(xi1 @ np.linalg.solve(plain.covariance, xi1))
        err_w.append(np.linalg.norm(xi[3:]))
        err_1.append(np.linalg.norm(xi1[3:]))
    # the covariance is (J^T W J)^-1 at the returned pose
    pts = np.vstack([s.corners_world for s in floor_of(dets)])
    _, J = floor_reprojection(FLOOR_CAM, res.T_world_body, pts)
    w = 1.0 / np.repeat(sig, 8) ** 2
    assert np.allclose(res.covariance, np.linalg.inv(J.T @ (J * w[:, None])), rtol=1e-6, atol=1e-14)
    assert 0.5 * 6 <= np.mean(nees_w) <= 2.0 * 6
    assert np.mean(nees_1) > 3.0 * 6  # one sigma for all: overconfident here
    assert np.mean(err_w) < 0.7 * np.mean(err_1)


# ============================================================================ rendered corners

RENDER_WORLD = World(
    floor_side_m=0.30,
    payload_unit_m=0.5,
    load_side_m=0.30,
    bounds_x_m=(-10.0, 10.0),
    bounds_y_m=(-10.0, 10.0),
    placement_sigma_m=0.0,
    placement_sigma_deg=0.0,
)


def rendered_nees(n_frames: int, seed: int, use_cov: bool = True):
    """Full-pose NEES of PnP on refined corners of rendered frames: a floor camera at 0.8-2.5 m
    (random yaw, tilt up to ~5 deg) over a 0.5 m grid of 0.3 m floor codes, blur 0-8 px, noise
    0.5-4 DN; and the 3-D NEES of a 0.3 m load code's centre (p_cam) seen by the front camera from
    0.8-2.5 m.  Decoder corners are simulated (truth + 0.7 px noise, rounded) so that heavy blur
    still tests the refinement.  `use_cov` False drops corner_cov_px2 (one sigma per code, the
    previous whitening).  Returns {"single": [...], "multi": [...], "load": [...]} NEES lists."""
    import dataclasses

    from fusion.qr.refine import refine_frames
    from fusion.sim.render import (
        QUIET_ZONE_MODULES,
        PlacedCode,
        RenderEffects,
        placed_floor_codes,
        project_code_corners,
        render_view,
    )

    rng = np.random.default_rng(seed)
    grid = np.array([[x, y] for x in range(-4, 5) for y in range(-4, 5)], float)
    floor = placed_floor_codes(grid, RENDER_WORLD.payload_unit_m, RENDER_WORLD.floor_side_m)
    out = {"single": [], "multi": [], "load": []}

    def refined(camera, T_world_cam, codes, img):
        dets = []
        cand = []
        for c in codes:
            truth = project_code_corners(camera, T_world_cam, c)
            centre = truth.mean(axis=0)
            outline = centre + (1.0 + 2.0 * QUIET_ZONE_MODULES / c.modules) * (truth - centre)
            if (
                np.all(np.isfinite(outline))
                and np.all(outline >= 1)
                and np.all(outline < np.array([camera.width, camera.height]) - 2)
            ):
                cand.append((c, np.round(truth + rng.normal(0.0, 0.7, truth.shape))))
        [res] = refine_frames([img], [[(raw, c.modules) for c, raw in cand]], camera)
        for (c, raw), r in zip(cand, res):
            if r is not None and r.stage == 2:
                d = QRDetection(
                    camera.name if hasattr(camera, "name") else "cam",
                    0,
                    c.payload,
                    r.corners_px,
                    raw,
                    r.corner_sigma_px,
                    r.corner_cov_px2,
                )
                dets.append(d if use_cov else dataclasses.replace(d, corner_cov_px2=None))
        return dets

    def effects():
        return RenderEffects(
            noise_sigma_dn=rng.uniform(0.5, 4.0),
            blur_px=rng.uniform(0.0, 8.0),
            blur_angle_rad=rng.uniform(0.0, np.pi),
        )

    for _ in range(n_frames):
        T = body_pose(
            rng.uniform(-0.25, 0.25),
            rng.uniform(-0.25, 0.25),
            rng.uniform(0.8, 2.5),
            rng.uniform(-180, 180),
            roll_deg=rng.normal(0, 3),
            pitch_deg=rng.normal(0, 3),
        )
        T_wc = FLOOR_CAM.T_world_cam(T)
        img = render_view(FLOOR_CAM, T_wc, floor, rng, effects())
        dets = [dataclasses.replace(d, camera="cam0") for d in refined(FLOOR_CAM, T_wc, floor, img)]
        sightings = classify(dets, RENDER_WORLD).floor
        for key, sub in (("single", sightings[:1]), ("multi", sightings if len(sightings) > 1 else [])):
            if not sub:
                continue
            res = estimate_floor_pose(sub, FLOOR_CAM)
            if res is not None:
                xi = local(T, res.T_world_body)
                out[key].append(float(xi @ np.linalg.solve(res.covariance, xi)))
        # a load code facing the front camera from 0.8-2.5 m, seen off-centre and obliquely
        dist = rng.uniform(0.8, 2.5)
        T_wc1 = FRONT_CAM.T_world_cam(T)
        ray = T_wc1[:3, :3] @ np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), 1.0])
        p = T_wc1[:3, 3] + dist * ray / np.linalg.norm(ray)
        view_yaw = math.atan2(-ray[1], -ray[0]) + rng.uniform(-0.4, 0.4)
        code = LoadCode("box-9", tuple(p), view_yaw)
        placed = PlacedCode(load_payload(code.id), code.T_world_symbol, RENDER_WORLD.load_side_m)
        img = render_view(FRONT_CAM, T_wc1, [placed], rng, effects())
        dets = [dataclasses.replace(d, camera="cam1") for d in refined(FRONT_CAM, T_wc1, [placed], img)]
        obs = estimate_load_observations(classify(dets, RENDER_WORLD).loads, FRONT_CAM, RENDER_WORLD, T)
        if obs:
            e = obs[0].p_cam - transform_points(inv_T(T_wc1), p[None])[0]
            out["load"].append(float(e @ np.linalg.solve(obs[0].cov_cam, e)))
    return out


def test_pose_nees_on_rendered_corners_with_their_covariance():
    """PnP on refined corners of rendered, blurred, noisy frames: whitened by each code's (8, 8)
    corner covariance, the full-pose NEES is near 6 for one code and for several, and the
    load-centre NEES near 3 (measured 4.8, 4.6, 4.0; seed 77: 4.8, 5.8, 3.4).  The errors are
    heavy-tailed (medians 3.5, 4.1, 2.2; see fusion.qr.refine's covariance comment), so the
    means need ~100 frames to settle, and other seeds put the load NEES at up to ~2x ideal."""
    nees = rendered_nees(100, seed=31)
    assert len(nees["single"]) >= 80 and len(nees["multi"]) >= 60 and len(nees["load"]) >= 90
    for key, dof in (("single", 6), ("multi", 6), ("load", 3)):
        assert 0.7 * dof <= np.mean(nees[key]) <= 1.4 * dof, (key, np.mean(nees[key]))


# ============================================================================ batches and fast paths


def test_many_frames_at_once_equal_one_at_a_time():
    """estimate_floor_poses (vectorised IPPE + LM over all views with the same code count) gives
    what estimate_floor_pose gives frame by frame (OpenCV's IPPE there), to well within a tenth of
    a standard deviation; an empty frame and a frame with a misplaced code are handled alike."""
    import dataclasses

    rng = np.random.default_rng(41)
    frames = []
    for i in range(14):
        centres = [FOUR[:1], FOUR[:2], FOUR[:3], FOUR][i % 4]
        cx, cy = np.mean(centres, axis=0)
        T = aim(
            body_pose(
                0,
                0,
                1.3 if len(centres) == 1 else 2.7,
                rng.uniform(-180, 180),
                roll_deg=rng.normal(0, 4),
                pitch_deg=rng.normal(0, 4),
            ),
            (cx + rng.uniform(-0.1, 0.1), cy + rng.uniform(-0.1, 0.1)),
        )
        frames.append(floor_of(floor_dets(T, centres, rng=rng, sigma=SIGMA)))
    bad = floor_dets(T_FOUR, FOUR)
    wrong = floor_dets(T_FOUR, [(0.7, 0.8)])[0]
    bad[3] = dataclasses.replace(bad[3], corners_px=wrong.corners_px)
    frames += [[], floor_of(bad)]
    batch = estimate_floor_poses(frames, FLOOR_CAM, SIGMA)
    assert len(batch) == len(frames) and batch[-2] is None
    assert batch[-1].dropped_payloads == [floor_payload(1, 1)]
    for sightings, b in zip(frames, batch):
        one = estimate_floor_pose(sightings, FLOOR_CAM, SIGMA)
        assert (one is None) == (b is None)
        if one is None:
            continue
        xi = local(one.T_world_body, b.T_world_body)
        assert xi @ np.linalg.solve(one.covariance, xi) < 1e-4
        assert np.linalg.norm(b.covariance - one.covariance) < 1e-3 * np.linalg.norm(one.covariance)
        assert (b.payloads, b.dropped_payloads, b.ambiguous) == (
            one.payloads,
            one.dropped_payloads,
            one.ambiguous,
        )
    # load codes: many frames together = one frame at a time
    items = []
    for k in range(6):
        T = body_pose(1.2 + 0.1 * k, 0.05 * k, 1.1, 5.0 - 3 * k, roll_deg=2.0, pitch_deg=3.0)
        items.append(
            (
                classify(load_dets(T, LOADS[: 1 + k % 2], rng=rng, sigma=SIGMA), WORLD).loads,
                T,
                np.diag([1e-4] * 3 + [4e-4] * 3) if k % 2 else None,
            )
        )
    many = estimate_load_observations_frames(items, FRONT_CAM, WORLD, SIGMA)
    for (loads, T, cov), obs in zip(items, many):
        one = estimate_load_observations(loads, FRONT_CAM, WORLD, T, cov, SIGMA)
        assert [o.load_id for o in obs] == [o.load_id for o in one]
        for a, b in zip(obs, one):
            e = a.p_cam - b.p_cam
            assert e @ np.linalg.solve(b.cov_cam, e) < 1e-4
            assert np.linalg.norm(a.cov_world - b.cov_world) < 1e-3 * np.linalg.norm(b.cov_world)


@pytest.mark.parametrize("n_points", [4, 8, 16])
def test_vectorised_ippe_matches_opencv(n_points):
    """_ippe's two poses are OpenCV's SOLVEPNP_IPPE ones (its homography estimate differs slightly
    from ours beyond 4 points), and one of them is the true pose for noise-free points."""
    from fusion.qr.pnp.ippe import ippe as _ippe

    rng = np.random.default_rng(n_points)
    K = 30
    if n_points == 4:
        X = np.array([[-0.1, 0.1], [0.1, 0.1], [0.1, -0.1], [-0.1, -0.1]]) + rng.uniform(-1, 1, (K, 1, 2))
    else:
        X = rng.uniform(-1.0, 1.0, (K, n_points, 2))
    R_true = np.array(
        [Rotation.from_rotvec([math.pi, 0, 0] + rng.normal(0, 0.3, 3)).as_matrix() for _ in range(K)]
    )
    t_true = np.column_stack([rng.uniform(-0.5, 0.5, (K, 2)), rng.uniform(1.5, 3.0, K)])
    P = np.concatenate([X, np.zeros((K, n_points, 1))], axis=2)
    p_cam = P @ R_true.transpose(0, 2, 1) + t_true[:, None]
    xn = p_cam[..., :2] / p_cam[..., 2:]
    R, t = _ippe(X, xn)
    for k in range(K):
        err = min(np.abs(R[k, j] - R_true[k]).max() + np.abs(t[k, j] - t_true[k]).max() for j in range(2))
        assert err < 1e-9
        noisy = xn[k] + rng.normal(0.0, 3e-4, xn[k].shape)
        R2, t2 = _ippe(X[k : k + 1], noisy[None])
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            P[k].reshape(-1, 1, 3), noisy.reshape(-1, 1, 2), np.eye(3), None, flags=cv2.SOLVEPNP_IPPE
        )
        for rv, tv in zip(rvecs[:n], tvecs[:n]):
            err = min(
                np.abs(R2[0, j] - cv2.Rodrigues(rv)[0]).max() + np.abs(t2[0, j] - tv.ravel()).max()
                for j in range(2)
            )
            assert err < (1e-8 if n_points == 4 else 1e-4), err


@pytest.mark.parametrize("mount", ["body_fixed", "gimbaled"])
def test_load_position_jacobian_matches_numerical_derivative(mount):
    from fusion.geometry import se3_exp
    from fusion.qr.pnp import position_jacobian_wrt_body

    cam = CameraModel(640, 480, 600.0, 600.0, 319.5, 239.5, T_body_cam=FRONT_CAM.T_body_cam, mount=mount)
    T = body_pose(1.0, -0.5, 1.4, 130.0, roll_deg=7.0, pitch_deg=-9.0)
    p_cam = np.array([0.2, -0.3, 2.1])

    def f(xi):
        return transform_points(cam.T_world_cam(T @ se3_exp(xi)), p_cam[None])[0]

    h = 1e-6
    Jn = np.column_stack([(f(d) - f(-d)) / (2 * h) for d in np.eye(6) * h])
    np.testing.assert_allclose(position_jacobian_wrt_body(T, cam, p_cam), Jn, atol=1e-7)


def test_fast_model_pieces_match_their_references():
    """Projector = CameraModel.project (NaN behind the camera) with a numerical Jacobian;
    so3_exp / so3_exp_stack = GTSAM's Rot3.Expmap; pnp.undistort = CameraModel.undistort_normalized,
    also where OpenCV's iteration fails (strong distortion: the Newton fallback)."""
    from fusion.geometry import so3_exp, so3_exp_stack
    from fusion.qr.pnp import undistort
    from fusion.qr.reprojection import Projector

    rng = np.random.default_rng(8)
    p = np.column_stack([rng.uniform(-1, 1, (50, 2)), rng.uniform(0.5, 3.0, 50)])
    p[0, 2] = -1.0
    uv, J = Projector(FLOOR_CAM).project(p)
    np.testing.assert_array_equal(np.isnan(uv), np.isnan(FLOOR_CAM.project(p)))
    np.testing.assert_allclose(uv[1:], FLOOR_CAM.project(p)[1:], atol=1e-9)
    h = 1e-6
    Jn = np.stack(
        [(FLOOR_CAM.project(p + d) - FLOOR_CAM.project(p - d)) / (2 * h) for d in np.eye(3) * h], axis=-1
    )
    np.testing.assert_allclose(J[1:], Jn[1:], atol=1e-4 * np.abs(J[1:]).max())
    w = np.vstack([rng.normal(0, 1.0, (5, 3)), rng.normal(0, 1e-5, (3, 3)), np.zeros((1, 3))])
    for wk, Rk in zip(w, so3_exp_stack(w)):
        np.testing.assert_allclose(so3_exp(wk), gtsam.Rot3.Expmap(wk).matrix(), atol=1e-15)
        np.testing.assert_allclose(Rk, gtsam.Rot3.Expmap(wk).matrix(), atol=1e-15)
    for cam in (
        FLOOR_CAM,
        CameraModel(640, 480, 300.0, 300.0, 320.0, 240.0, distortion=[-0.45, 0.2, 0.0, 0.0]),
    ):
        px = np.vstack([rng.uniform([0, 0], [640, 480], (40, 2)), [[0.0, 0.0], [639.0, 479.0]]])
        np.testing.assert_allclose(undistort(cam, px), cam.undistort_normalized(px), atol=1e-10)


def test_whitening_of_a_batch_with_one_bad_covariance():
    """corner_whitening: a corner covariance that is not positive definite (or not finite) falls
    back to diag(1 / sigma) for that detection only; the others are whitened by their Cholesky."""
    import dataclasses

    from fusion.qr.pnp import corner_whitening

    rng = np.random.default_rng(2)
    A = rng.normal(0, 0.1, (8, 8))
    C = A @ A.T + 0.01 * np.eye(8)
    d = floor_dets(T_FOUR, FOUR)
    dets = [
        dataclasses.replace(d[0], corner_cov_px2=C),
        dataclasses.replace(d[1], corner_cov_px2=-C, corner_sigma_px=0.3),
        dataclasses.replace(d[2], corner_cov_px2=np.full((8, 8), np.nan)),
        d[3],
    ]
    W = corner_whitening(dets, 0.2)
    np.testing.assert_allclose(W[0] @ C @ W[0].T, np.eye(8), atol=1e-9)
    np.testing.assert_allclose(W[1], np.eye(8) / 0.3)
    np.testing.assert_allclose(W[2], np.eye(8) / 0.2)
    np.testing.assert_allclose(W[3], np.eye(8) / 0.2)


def test_lm_reports_which_starts_converged():
    """levenberg_marquardt flags a start it could not take to a minimum within its iterations
    (such a point is no candidate pose: its cost can pass for a second, ambiguous minimum)."""
    from fusion.geometry import so3_exp
    from fusion.qr.pnp import corner_whitening
    from fusion.qr.pnp.floor import FloorProblems
    from fusion.qr.pnp.lm import levenberg_marquardt, same_minimum

    sightings = floor_of(floor_dets(T_FOUR, FOUR, rng=np.random.default_rng(4), sigma=SIGMA))
    P = np.vstack([s.corners_world for s in sightings])[None]
    z = np.vstack([s.detection.corners_px for s in sightings])[None]
    W = corner_whitening([s.detection for s in sightings], SIGMA)[None]
    problems = FloorProblems.for_camera(
        FLOOR_CAM, np.repeat(P, 2, axis=0), np.repeat(z, 2, axis=0), np.repeat(W, 2, axis=0)
    )
    R0 = np.stack([T_FOUR[:3, :3], T_FOUR[:3, :3] @ so3_exp([0.25, -0.2, 0.3])])
    t0 = np.stack([T_FOUR[:3, 3], T_FOUR[:3, 3] + [0.3, -0.2, 0.4]])
    normal = problems.normal_equations(R0, t0)
    res = levenberg_marquardt(problems, R0, t0, normal, max_iter=3)
    assert res.converged.tolist() == [True, False] and res.normal.cost[1] > res.normal.cost[0]
    res = levenberg_marquardt(problems, R0, t0, normal)
    assert res.converged.all()  # both at the same minimum:
    assert same_minimum(res.R[0], res.t[0], res.normal.H[0], res.R[1], res.t[1])  # < 0.1 sigma


# ============================================================================ decisions pinned


def _four_code_problems(n_starts: int):
    """`n_starts` copies of one noisy four-code floor view as LM problems (FloorProblems)."""
    from fusion.qr.pnp import corner_whitening
    from fusion.qr.pnp.floor import FloorProblems

    sightings = floor_of(floor_dets(T_FOUR, FOUR, rng=np.random.default_rng(4), sigma=SIGMA))
    P = np.vstack([s.corners_world for s in sightings])[None]
    z = np.vstack([s.detection.corners_px for s in sightings])[None]
    W = corner_whitening([s.detection for s in sightings], SIGMA)[None]
    return FloorProblems.for_camera(
        FLOOR_CAM,
        np.repeat(P, n_starts, axis=0),
        np.repeat(z, n_starts, axis=0),
        np.repeat(W, n_starts, axis=0),
    )


def test_lm_damps_a_step_that_raises_the_cost():
    """From a poor start (0.65 rad and 0.53 m off) the full Gauss-Newton step raises the cost
    (5.2e8 from 3.0e8): undamped, the LM would repeat that step and never converge; damped, it
    reaches the minimum that the start at the truth reaches."""
    from fusion.geometry import so3_exp
    from fusion.qr.pnp.lm import levenberg_marquardt, same_minimum

    problems = _four_code_problems(2)
    R0 = np.stack([T_FOUR[:3, :3], T_FOUR[:3, :3] @ so3_exp([0.475, 0.396, 0.19])])
    t0 = np.stack([T_FOUR[:3, 3], T_FOUR[:3, 3] + [-0.447, 0.266, 0.117]])
    normal = problems.normal_equations(R0, t0)
    gauss_newton = np.linalg.solve(normal.H[1], -normal.g[1])
    R1, t1 = problems.subset([1]).retract(R0[1:], t0[1:], gauss_newton[None])
    assert problems.subset([1]).normal_equations(R1, t1).cost[0] > normal.cost[1]
    res = levenberg_marquardt(problems, R0, t0, normal)
    assert res.converged.all()
    assert same_minimum(res.R[0], res.t[0], res.normal.H[0], res.R[1], res.t[1])


@pytest.mark.parametrize("yaw_deg", [0.0, 40.0, 120.0])
@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.3, 0.0), (0.5, 0.3)])
def test_level_body_single_frame_is_recovered_exactly(yaw_deg, offset):
    """A level body with a down-looking camera puts R_cam_world at a rotation of exactly pi, where
    OpenCV's IPPE returns a broken rotation vector (opencv-contrib 5.0: e.g. [13.6, -13.6, 0]
    for [2.22, -2.22, 0]); the one-frame path must still recover the pose exactly, for one code
    (no SQPnP fallback) and for two."""
    T = aim(body_pose(0, 0, 2.0, yaw_deg), offset)
    for centres in ([(0, 0)], [(0, 0), (1, 0)]):
        T_view = (
            T
            if len(centres) == 1
            else aim(body_pose(0, 0, 2.6, yaw_deg), (0.5 + 0.3 * offset[0], 0.3 * offset[1]))
        )
        res = estimate_floor_pose(floor_of(floor_dets(T_view, centres)), FLOOR_CAM)
        assert res is not None  # exact to the LM's tolerance (the bug: 0.1-2 rad)
        np.testing.assert_allclose(res.T_world_body, T_view, atol=1e-6)


@pytest.mark.parametrize("yaw_deg", [0.0, 70.0, -150.0])
def test_ambiguous_floor_pose_takes_the_more_level_solution(yaw_deg):
    """One small code far off-centre (3 m up, 0.2 m code, sigma 0.3 px): IPPE's mirror solution,
    tilted by ~20 deg, fits the noise-free corners within AMBIGUITY_CHI2 of the true, level
    one; the near-level rule must take the level one (the inverted rule is off by ~0.95)."""
    T = aim(body_pose(0, 0, 3.0, yaw_deg), (0.5, 0.3))
    res = estimate_floor_pose(floor_of(floor_dets(T, [(0, 0)])), FLOOR_CAM, 0.3)
    assert res.ambiguous
    np.testing.assert_allclose(res.T_world_body, T, atol=1e-9)


@pytest.mark.parametrize("distance_m", [3.0, 4.0])
def test_ambiguous_load_code_takes_the_solution_with_up_along_world_z(distance_m):
    """A load code 3-4 m ahead (sigma 0.3 px): both IPPE solutions fit within AMBIGUITY_CHI2;
    the one whose symbol "up" is nearer world +z is the true one, and its centre is exact (the
    other's is 3-4 mm off)."""
    code = LoadCode("box-1", (distance_m, 0.3, 1.3), math.pi)
    T = body_pose(0.0, 0.0, 1.1, 0.0)
    obs = estimate_load_observations(
        classify(load_dets(T, [code]), WORLD).loads, FRONT_CAM, WORLD, T, None, 0.3
    )
    assert len(obs) == 1
    np.testing.assert_allclose(obs[0].p_world, code.p_world, atol=1e-9)


@pytest.mark.parametrize("yaw_deg", [120.0, 124.6, 130.0])
def test_sqpnp_start_finds_the_misplaced_code_where_ippe_does_not(yaw_deg):
    """Two codes, one printed 0.55 m from where its payload says (0/0/-2 at (0.21, -1.51)), seen
    tilted by 17 deg: no IPPE start refines to a plausible fit, and at the minimum they reach the
    GOOD code fits worst, so it would be left out and the pose taken from the misplaced one
    (0.49 m off).  SQPnP's start reaches the minimum where the misplaced code fits worst: it is
    dropped and the pose is exact."""
    T = body_pose(0.70, -0.98, 2.65, yaw_deg, roll_deg=2.9, pitch_deg=16.5)
    misplaced = floor_dets(T, [(0.21, -1.51)])[0]
    dets = [
        QRDetection("cam0", 0, floor_payload(0, -2), misplaced.corners_px, misplaced.corners_px)
    ] + floor_dets(T, [(2, -1)])
    res = estimate_floor_pose(floor_of(dets), FLOOR_CAM)
    assert res.dropped_payloads == [floor_payload(0, -2)]
    np.testing.assert_allclose(res.T_world_body, T, atol=1e-9)


def test_gimbaled_pose_is_conditioned_on_its_level_attitude():
    """One code in view from 1.3 m: the free PnP pose trades a small tilt against a horizontal
    shift, and levelling it keeps the shift.  With the gimbal's level attitude known exactly
    (mount sigma 0) the conditioned level pose (floor.condition_on_level) is several times more
    precise in x / y than the free pose levelled, and its [rz, tx, ty, tz] covariance is
    consistent (4-dof NEES ~4 over seeded draws)."""
    from dataclasses import replace

    gimbaled = gimbaled_camera(distortion=DIST, mount_sigma_deg=0.0)
    free = replace(gimbaled, mount="body_fixed")
    truth = aim(body_pose(0.5, 0.5, 1.3, -60.0), (0.0, 0.0), camera=gimbaled)
    rng = np.random.default_rng(23)
    err_free, err_cond, nees = [], [], []
    for _ in range(200):
        floor = floor_of(floor_dets(truth, [(0, 0)], camera=gimbaled, rng=rng, sigma=SIGMA))
        res_free = estimate_floor_pose(floor, free, SIGMA)
        res = estimate_floor_pose(floor, gimbaled, SIGMA)
        err_free.append(local(truth, level_frame(res_free.T_world_body))[3:5])
        xi = local(truth, res.T_world_body)
        assert abs(xi[0]) < 1e-9 and abs(xi[1]) < 1e-9  # the level frame
        err_cond.append(xi[3:5])
        nees.append(xi[2:] @ np.linalg.solve(res.covariance[2:, 2:], xi[2:]))
    rms_free = np.sqrt(np.mean(np.square(err_free), axis=0))
    rms_cond = np.sqrt(np.mean(np.square(err_cond), axis=0))
    assert np.all(rms_cond < 0.5 * rms_free), (rms_cond, rms_free)
    assert 0.7 * 4 <= np.mean(nees) <= 1.3 * 4, np.mean(nees)


def test_gimbaled_pose_keeps_its_free_tilt_covariance():
    """PnPResult.free_tilt_covariance: a gimbaled camera's free solve's [rx, ry] block before the
    level conditioning (the body-fixed solve of the same corners), for the tilt consider's share
    (tiltconsider.level_kept_fraction); None for a body-fixed camera."""
    from dataclasses import replace

    gimbaled = gimbaled_camera(mount_sigma_deg=0.01)
    free = replace(gimbaled, mount="body_fixed")
    truth = aim(body_pose(0.5, 0.5, 1.3, -60.0), (0.0, 0.0), camera=gimbaled)
    floor = floor_of(floor_dets(truth, [(0, 0)], camera=gimbaled, rng=np.random.default_rng(2), sigma=SIGMA))
    res = estimate_floor_pose(floor, gimbaled, SIGMA)
    res_free = estimate_floor_pose(floor, free, SIGMA)
    assert res_free.free_tilt_covariance is None
    np.testing.assert_allclose(res.free_tilt_covariance, res_free.covariance[:2, :2], rtol=1e-9)


def test_condition_on_level_is_the_gaussian_conditional():
    """sigma 0: the [rz, tx, ty, tz] block is the Schur complement C_22 - C_21 C_11^-1 C_12, the
    returned pose is level to second order, and the class shares keep summing to the covariance."""
    from fusion.qr.pnp.floor import condition_on_level

    rng = np.random.default_rng(4)
    A = rng.standard_normal((6, 6))
    C = A @ A.T * 1e-6
    G = np.stack([0.3 * C, 0.7 * C])
    T = body_pose(1.0, 2.0, 1.3, 40.0, roll_deg=0.05, pitch_deg=-0.08)
    T_c, C_c, G_c = condition_on_level(T, C, G, 0.0)
    schur = C[2:, 2:] - C[2:, :2] @ np.linalg.solve(C[:2, :2], C[:2, 2:])
    np.testing.assert_allclose(C_c[2:, 2:], schur, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(C_c[:2, :], 0.0, atol=1e-18)
    np.testing.assert_allclose(G_c.sum(axis=0), C_c, rtol=1e-9, atol=1e-18)
    tilt = so3_log(level_frame(T_c)[:3, :3].T @ T_c[:3, :3])[:2]
    assert np.all(np.abs(tilt) < 1e-5)  # from 1.4e-3 rad: second order
    T_s, C_s, _ = condition_on_level(T, C, G, 1.0)  # a gimbal known to a radian: nothing learnt
    np.testing.assert_allclose(C_s, C, rtol=1e-4, atol=1e-15)


def test_gimbaled_bias_sensitivity_keeps_the_level_attitude():
    """The corner bias's pose sensitivity (bias.frame_bias_terms) of a gimbaled camera whose level
    is known exactly moves no roll / pitch (the pose is conditioned on them,
    floor.condition_on_level); a body-fixed camera's does."""
    from dataclasses import replace

    from fusion.qr.pnp.bias import frame_bias_terms

    gimbaled = gimbaled_camera(mount_sigma_deg=0.0)
    T = aim(body_pose(0.5, 0.5, 1.3, -60.0), (0.2, 0.15), camera=gimbaled)  # the code off-centre
    floor = floor_of(floor_dets(T, [(0, 0)], camera=gimbaled))
    level = estimate_floor_pose(floor, gimbaled, SIGMA).T_world_body
    S_g = frame_bias_terms(gimbaled, floor, level, SIGMA).sensitivity
    S_b = frame_bias_terms(replace(gimbaled, mount="body_fixed"), floor, level, SIGMA).sensitivity
    assert np.all(S_g[:2] == 0.0) and np.any(np.abs(S_g[2:]) > 0.0)
    assert np.any(np.abs(S_b[:2]) > 1e-3 * np.abs(S_b).max())
