"""Tests of the flight simulator: rendering geometry, trajectory derivatives, IMU synthesis,
determinism and the written flight log."""

from __future__ import annotations

import numpy as np
import pytest
import zxingcpp

from fusion.camera import CameraModel
from fusion.conventions import R_BODY_FLOORCAM, R_BODY_FRONTCAM, symbol_corners_S
from fusion.errors import SimulationError
from fusion.geometry import inv_T, make_T, rot_z
from fusion.sim.render import (
    BLACKOUT_KINDS,
    PlacedCode,
    RenderEffects,
    code_texture,
    placed_floor_codes,
    project_code_corners,
    render_view,
)
from fusion.world import LoadCode

# ============================================================================ rendering


def _floor_camera(distortion=(-0.08, 0.02, 0.001, -0.0005)) -> CameraModel:
    return CameraModel(
        640,
        480,
        600.0,
        600.0,
        321.3,
        238.7,
        distortion=list(distortion),
        T_body_cam=make_T(R_BODY_FLOORCAM, [0.05, 0.0, -0.05]),
    )


def _front_camera() -> CameraModel:
    return CameraModel(
        640,
        480,
        550.0,
        550.0,
        318.2,
        242.6,
        distortion=[-0.06, 0.01, -0.0008, 0.0006],
        T_body_cam=make_T(R_BODY_FRONTCAM, [0.1, 0.0, 0.0]),
    )


def _bilinear(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples of img at (N, 2) float pixel positions (u, v)."""
    u, v = pts[:, 0], pts[:, 1]
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - u0, v - v0
    h, w = img.shape
    u0c, v0c = np.clip(u0, 0, w - 2), np.clip(v0, 0, h - 2)
    a = img[v0c, u0c] * (1 - fu) * (1 - fv) + img[v0c, u0c + 1] * fu * (1 - fv)
    return a + img[v0c + 1, u0c] * (1 - fu) * fv + img[v0c + 1, u0c + 1] * fu * fv


def refine_corners(img: np.ndarray, rough: np.ndarray, n_modules: int, camera: CameraModel) -> np.ndarray:
    """Sub-pixel symbol corners from a detector's rough corners (TL, TR, BR, BL): locate the outer
    edges of the three finder patterns along their normals (mid-level crossing), undistort those
    edge points, fit the four outer lines, intersect them and distort the corners back."""
    import cv2

    img = img.astype(float)
    src = np.array([[0, 0], [n_modules, 0], [n_modules, n_modules], [0, n_modules]], float)
    H = cv2.getPerspectiveTransform(src.astype(np.float32), rough.astype(np.float32)).astype(float)

    def to_img(m):
        p = np.c_[m, np.ones(len(m))] @ H.T
        return p[:, :2] / p[:, 2:]

    module_px = np.mean(np.linalg.norm(rough - np.roll(rough, 1, axis=0), axis=1)) / n_modules
    # edges as (start module point, end module point, outward direction in module coords)
    n = n_modules
    segments = {
        "top": [((0, 0), (7, 0), (0, -1)), ((n - 7, 0), (n, 0), (0, -1))],
        "left": [((0, 0), (0, 7), (-1, 0)), ((0, n - 7), (0, n), (-1, 0))],
        "right": [((n, 0), (n, 7), (1, 0))],
        "bottom": [((0, n), (7, n), (0, 1))],
    }
    lines = {}
    for name, segs in segments.items():
        pts = []
        for a, b, out in segs:
            for s in np.linspace(0.15, 0.85, 15):
                m = np.array(a, float) + s * (np.array(b, float) - np.array(a, float))
                p0, p1 = to_img(np.array([m, m + 0.1 * np.array(out, float)]))
                normal = (p1 - p0) / np.linalg.norm(p1 - p0)
                offs = np.linspace(-0.6 * module_px, 0.6 * module_px, 121)
                prof = _bilinear(img, p0 + offs[:, None] * normal)
                mid = 0.5 * (prof.min() + prof.max())
                above = prof > mid  # outward = white quiet zone
                k = np.flatnonzero(above[1:] != above[:-1])
                if len(k) != 1 or prof.max() - prof.min() < 40:
                    continue
                k = k[0]
                f = (mid - prof[k]) / (prof[k + 1] - prof[k])
                pts.append(p0 + (offs[k] + f * (offs[1] - offs[0])) * normal)
        und = camera.undistort_pixels(np.array(pts))
        c = und.mean(axis=0)
        _, _, vt = np.linalg.svd(und - c)
        d = vt[0]
        lines[name] = (c, d)

    def meet(l1, l2):
        (c1, d1), (c2, d2) = l1, l2
        t = np.linalg.solve(np.column_stack([d1, -d2]), c2 - c1)
        return c1 + t[0] * d1

    corners_und = np.array(
        [
            meet(lines["top"], lines["left"]),
            meet(lines["top"], lines["right"]),
            meet(lines["bottom"], lines["right"]),
            meet(lines["bottom"], lines["left"]),
        ]
    )
    xy = np.column_stack(
        [(corners_und[:, 0] - camera.cu) / camera.fu, (corners_und[:, 1] - camera.cv) / camera.fv, np.ones(4)]
    )
    return camera.project(xy)


def _zxing_corners(result) -> np.ndarray:
    p = result.position
    return np.array(
        [
            [p.top_left.x, p.top_left.y],
            [p.top_right.x, p.top_right.y],
            [p.bottom_right.x, p.bottom_right.y],
            [p.bottom_left.x, p.bottom_left.y],
        ],
        float,
    )


def test_code_texture_finders_at_symbol_corners():
    sym = code_texture("0/3/-2")
    n = sym.shape[0]
    assert n == 21 and sym.dtype == np.uint8
    finder = np.zeros((7, 7), bool)
    finder[[0, 6], :] = finder[:, [0, 6]] = True
    finder[2:5, 2:5] = True
    for r, c in [(0, 0), (0, n - 7), (n - 7, 0)]:
        assert np.array_equal(sym[r : r + 7, c : c + 7] < 128, finder)
    assert not np.array_equal(sym[n - 7 :, n - 7 :] < 128, finder)  # no finder bottom-right


def _views():
    """(camera, T_world_cam, codes, is_floor) of a few floor and front views with tilt."""
    rng = np.random.default_rng(3)
    floor = _floor_camera()
    grid = placed_floor_codes(np.array([[x, y] for x in range(-2, 3) for y in range(-2, 3)]), 1.0, 0.2)
    views = []
    for k in range(4):
        yaw = rng.uniform(-np.pi, np.pi)
        tilt = rng.normal(0, 0.08, 2)
        from scipy.spatial.transform import Rotation

        R = rot_z(yaw) @ Rotation.from_rotvec([tilt[0], tilt[1], 0]).as_matrix()
        T_wb = make_T(R, [rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15), rng.uniform(0.9, 1.3)])
        views.append((floor, floor.T_world_cam(T_wb), grid))
    front = _front_camera()
    loads = [PlacedCode("1/P-03-2", LoadCode("P-03-2", (3.0, 0.0, 1.5), np.pi).T_world_symbol, 0.15)]
    for k in range(3):
        yaw = rng.normal(0, 0.3)
        T_wb = make_T(rot_z(yaw), [rng.uniform(1.6, 2.1), rng.uniform(-0.2, 0.2), 1.5 + rng.normal(0, 0.1)])
        views.append((front, front.T_world_cam(T_wb), loads))
    return views


def test_rendered_corners_match_projection_within_half_pixel():
    """The issue's acceptance test: corners found in rendered frames by a detector (zxing-cpp +
    sub-pixel refinement of the finder edges) lie within 0.5 px of project_code_corners."""
    errors = []
    for camera, T_wc, codes in _views():
        img = render_view(camera, T_wc, codes, np.random.default_rng(1), RenderEffects(noise_sigma_dn=1.0))
        found = zxingcpp.read_barcodes(img, formats=zxingcpp.BarcodeFormat.QRCode)
        assert found, "no code decoded in a rendered view"
        by_payload = {c.payload: c for c in codes}
        for res in found:
            code = by_payload[res.text]
            truth = project_code_corners(camera, T_wc, code)
            if (
                np.any(truth < 3)
                or np.any(truth[:, 0] > camera.width - 4)
                or np.any(truth[:, 1] > camera.height - 4)
            ):
                continue
            rough = _zxing_corners(res)
            # finder order: the decoder's top-left is the symbol's top-left (TL, TR, BR, BL)
            assert np.max(np.linalg.norm(rough - truth, axis=1)) < 3.0
            refined = refine_corners(img, rough, code.modules, camera)
            errors.append(np.linalg.norm(refined - truth, axis=1))
    errors = np.concatenate(errors)
    assert len(errors) >= 4 * 6
    assert errors.max() < 0.5, f"corner errors (px): max {errors.max():.3f} mean {errors.mean():.3f}"


def test_projection_is_full_camera_model():
    camera = _floor_camera()
    T_wc = camera.T_world_cam(make_T(rot_z(0.4), [0.3, -0.2, 1.2]))
    code = placed_floor_codes(np.array([[0, 0]]), 1.0, 0.2)[0]
    uv = project_code_corners(camera, T_wc, code)
    p_cam = (symbol_corners_S(0.2) - T_wc[:3, 3]) @ T_wc[:3, :3]
    import cv2

    ref, _ = cv2.projectPoints(p_cam, np.zeros(3), np.zeros(3), camera.K, camera.dist_cv)
    np.testing.assert_allclose(uv, ref.reshape(4, 2), atol=1e-9)


@pytest.mark.parametrize("kind", BLACKOUT_KINDS)
def test_blackouts_make_floor_codes_unreadable(kind):
    camera = _floor_camera()
    grid = placed_floor_codes(np.array([[x, y] for x in range(-2, 3) for y in range(-2, 3)]), 1.0, 0.2)
    readable = blacked = 0
    for k, h in enumerate([0.9, 1.3, 1.8]):
        T_wc = camera.T_world_cam(make_T(rot_z(0.5 * k), [0.05 * k, -0.1, h]))
        clean = render_view(camera, T_wc, grid, np.random.default_rng(k), RenderEffects())
        dark = render_view(camera, T_wc, grid, np.random.default_rng(k), RenderEffects(blackout=kind))
        readable += len(zxingcpp.read_barcodes(clean))
        blacked += len(zxingcpp.read_barcodes(dark))
    assert readable >= 3 and blacked == 0


def test_render_effects_validate():
    with pytest.raises(SimulationError):
        RenderEffects(blackout="fog")
    with pytest.raises(SimulationError):
        RenderEffects(gain=0.0)


# ============================================================================ trajectory and IMU

from fusion.sim.imu import synthesize_imu, synthesize_velocity  # noqa: E402
from fusion.sim.trajectory import KeyframeTrajectory, survey_keyframes  # noqa: E402


def _test_trajectory() -> KeyframeTrajectory:
    wps = [
        (0.0, 0.0, 0.0, 0.0, 0.5),
        (0.0, 0.0, 1.5, 0.3),
        (2.0, 0.5, 1.5, 1.6, 0.7),
        (2.5, 2.0, 2.2, -0.5),
        (1.0, 1.0, 1.2, 0.2, 0.5),
        (0.0, 0.5, 1.8, 0.0),
    ]
    return KeyframeTrajectory(survey_keyframes(wps, speed_m_s=0.9, yaw_rate_rad_s=0.8))


def _vee(S):
    return np.stack([S[..., 2, 1], S[..., 0, 2], S[..., 1, 0]], axis=-1)


def test_trajectory_derivatives_match_finite_differences():
    traj = _test_trajectory()
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0.01, traj.duration_s - 0.01, 200))
    h = 1e-5
    s, sp, sm = traj.state(t), traj.state(t + h), traj.state(t - h)
    np.testing.assert_allclose(s.v_world, (sp.p_world - sm.p_world) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(s.a_world, (sp.v_world - sm.v_world) / (2 * h), atol=1e-5)
    Rdot = (sp.R_world_body - sm.R_world_body) / (2 * h)
    omega_fd = _vee(np.einsum("nji,njk->nik", s.R_world_body, Rdot))
    np.testing.assert_allclose(s.omega_body, omega_fd, atol=1e-6)
    # attitude: thrust along body z, heading from the plan, rotations orthonormal
    thrust = s.a_world + [0, 0, 9.81]
    np.testing.assert_allclose(
        s.R_world_body[:, :, 2], thrust / np.linalg.norm(thrust, axis=1)[:, None], atol=1e-12
    )
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", s.R_world_body, s.R_world_body),
        np.broadcast_to(np.eye(3), (len(t), 3, 3)),
        atol=1e-12,
    )
    # continuity of the angular rate at keyframes (jerk is continuous)
    tk = np.array([k.t_s for k in traj.keyframes[1:-1]])
    jump = traj.state(tk + 1e-7).omega_body - traj.state(tk - 1e-7).omega_body
    assert np.abs(jump).max() < 1e-4
    assert np.abs(s.omega_body).max() > 0.1 and np.abs(s.a_world).max() > 0.3  # it does move


def _integrate_rk4(imu, R0, v0, p0):
    """RK4 on (R, v, p) with steps of two IMU intervals (samples k, k+1, k+2 = start, middle, end)."""
    g = np.array([0.0, 0.0, -9.81])
    t = imu.timestamps_ns * 1e-9
    w, f = imu.gyro_rad_s, imu.accel_m_s2

    def skew(x):
        return np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])

    def deriv(R, v, k):
        return R @ skew(w[k]), R @ f[k] + g, v

    R, v, p = R0.copy(), v0.copy(), p0.copy()
    out = [p.copy()]
    for k in range(0, len(t) - 2, 2):
        h = t[k + 2] - t[k]
        k1 = deriv(R, v, k)
        k2 = deriv(R + 0.5 * h * k1[0], v + 0.5 * h * k1[1], k + 1)
        k3 = deriv(R + 0.5 * h * k2[0], v + 0.5 * h * k2[1], k + 1)
        k4 = deriv(R + h * k3[0], v + h * k3[1], k + 2)
        p = p + h / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        v = v + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        R = R + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
        out.append(p.copy())
    return np.array(out)


def test_noise_free_imu_integrates_to_ground_truth_within_1mm():
    traj = _test_trajectory()
    assert traj.duration_s >= 10.0
    imu, bg, ba = synthesize_imu(traj, rate_hz=200.0, noise_free=True)
    n = 2001  # 10 s at 200 Hz
    imu.timestamps_ns, imu.gyro_rad_s, imu.accel_m_s2 = (
        imu.timestamps_ns[:n],
        imu.gyro_rad_s[:n],
        imu.accel_m_s2[:n],
    )
    s0 = traj.state(np.array([0.0]))
    p = _integrate_rk4(imu, s0.R_world_body[0], s0.v_world[0], s0.p_world[0])
    truth = traj.state(imu.timestamps_ns[::2] * 1e-9).p_world
    err = np.linalg.norm(p - truth, axis=1)
    assert err.max() < 1e-3, f"max drift {err.max() * 1e3:.3f} mm"
    # the check can fail: gravity of the wrong sign or a frame mix-up drifts metres
    wrong = _integrate_rk4(imu, s0.R_world_body[0] @ rot_z(0.01), s0.v_world[0], s0.p_world[0])
    assert np.linalg.norm(wrong - truth, axis=1).max() > 1e-3


def test_imu_noise_statistics():
    traj = _test_trajectory()
    from fusion.log import ImuNoise

    noise = ImuNoise(1e-3, 1e-4, 1e-2, 1e-3)
    clean, _, _ = synthesize_imu(traj, 200.0, noise_free=True)
    imu, bg, ba = synthesize_imu(traj, 200.0, noise, np.random.default_rng(2))
    white_g = imu.gyro_rad_s - clean.gyro_rad_s - bg
    white_a = imu.accel_m_s2 - clean.accel_m_s2 - ba
    np.testing.assert_allclose(white_g.std(), 1e-3 * np.sqrt(200), rtol=0.05)
    np.testing.assert_allclose(white_a.std(), 1e-2 * np.sqrt(200), rtol=0.05)
    steps = np.diff(ba, axis=0)
    np.testing.assert_allclose(steps.std(), 1e-3 * np.sqrt(1 / 200), rtol=0.05)
    vel = synthesize_velocity(traj, 30.0, 0.05, np.random.default_rng(0))
    st = traj.state(vel.timestamps_ns * 1e-9)
    v_true = np.einsum("nji,nj->ni", st.R_world_body, st.v_world)
    np.testing.assert_allclose((vel.v_body_m_s - v_true).std(), 0.05, rtol=0.1)


# ============================================================================ simulate()

from fusion.log import read_flight  # noqa: E402
from fusion.sim.scenarios import build_scenario  # noqa: E402
from fusion.sim.simulate import simulate  # noqa: E402


def test_simulate_writes_a_readable_deterministic_log(tmp_path):
    kw = dict(scenario="default", duration_s=2.0, seed=4, progress=False, camera_rate_hz=10.0)
    r1 = simulate(tmp_path / "a", workers=2, **kw)
    r2 = simulate(tmp_path / "b", workers=1, **kw)
    log = read_flight(r1.root)
    assert len(log.floor) == len(log.front) == r1.n_frames == 21
    np.testing.assert_array_equal(log.floor.timestamps_ns, log.front.timestamps_ns)
    assert len(log.imu.timestamps_ns) == 401 and log.velocity is not None
    assert len(log.groundtruth.timestamps_ns) == 401
    assert log.loads_groundtruth and "P-02-3" in log.loads_groundtruth
    np.testing.assert_allclose(log.loads_groundtruth["P-02-3"], [3.5, 2.7, 2.1])
    assert log.floor.camera.fu == 550.0 and log.floor.camera.mount == "body_fixed"
    # ground truth matches the scenario's trajectory
    st = build_scenario("default").trajectory.state(log.groundtruth.timestamps_ns * 1e-9)
    np.testing.assert_allclose(log.groundtruth.p_world, st.p_world, atol=1e-12)
    # determinism for a seed, whatever the number of workers
    log2 = read_flight(r2.root)
    np.testing.assert_array_equal(log.imu.accel_m_s2, log2.imu.accel_m_s2)
    for name in ("cam0", "cam1"):
        s1, s2 = log.cameras[name], log2.cameras[name]
        for i in (0, 7, 20):
            np.testing.assert_array_equal(s1.load_image(i), s2.load_image(i))
    # another seed gives other noise
    r3 = simulate(tmp_path / "c", workers=1, **{**kw, "seed": 5, "duration_s": 0.5, "velocity_rate_hz": 8.0})
    log3 = read_flight(r3.root)
    assert len(log3.velocity.timestamps_ns) == 5  # its own rate: 0, 125, ... 500 ms
    assert not np.array_equal(log3.imu.accel_m_s2, log.imu.accel_m_s2[: len(log3.imu.accel_m_s2)])
    assert not np.array_equal(log3.floor.load_image(3), log.floor.load_image(3))


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(scenario="mars"),
        dict(duration_s=-1.0),
        dict(duration_s=0),
        dict(duration_s=float("nan")),
        dict(duration_s=1e6),
        dict(duration_s="long"),
        dict(seed=-1),
        dict(start_s=-2.0),
        dict(resolution="800x600"),
        dict(velocity_rate_hz=0.0),
        dict(velocity_rate_hz=float("inf")),
        dict(imu_noise_scale=0.0),
        dict(imu_noise_stated=-1.0),
        dict(imu_noise_scale=float("nan")),
    ],
)
def test_simulate_rejects_bad_input(tmp_path, kwargs):
    with pytest.raises(SimulationError):
        simulate(tmp_path / "x", progress=False, workers=1, **kwargs)
    assert not (tmp_path / "x").exists()


def test_simulate_imu_noise_scaled_and_stated(tmp_path):
    """--imu-noise-scale K: the samples' white noise K x the scenario's; --imu-noise-stated F:
    sensor.yaml states F x the truth (an optimistic datasheet at F < 1)."""
    from fusion.log import ImuNoise
    from fusion.sim.imu import true_imu

    res = simulate(
        tmp_path / "n",
        duration_s=4.0,
        camera_rate_hz=5.0,
        seed=3,
        workers=1,
        progress=False,
        imu_noise_scale=3.0,
        imu_noise_stated=1 / 3,
    )
    log = read_flight(res.root)
    nominal = ImuNoise()
    assert log.imu.noise.accelerometer_noise_density == pytest.approx(nominal.accelerometer_noise_density)
    assert log.imu.noise.gyroscope_random_walk == pytest.approx(nominal.gyroscope_random_walk)
    gyro, _ = true_imu(build_scenario("default").trajectory, log.imu.timestamps_ns * 1e-9)
    white = log.imu.gyro_rad_s - gyro - log.groundtruth.bias_gyro
    expected = 3.0 * nominal.gyroscope_noise_density * np.sqrt(log.imu.rate_hz)
    np.testing.assert_allclose(white.std(), expected, rtol=0.05)


def test_simulate_refuses_to_overwrite(tmp_path):
    from fusion.errors import FusionError

    (tmp_path / "x").mkdir()
    with pytest.raises(FusionError):
        simulate(tmp_path / "x", duration_s=0.2, progress=False, workers=1)


def test_scenarios_build_and_gimbal_keeps_cameras_level():
    for name in ("default", "gimbaled", "oblique", "paper_a5"):
        sc = build_scenario(name)
        assert sc.trajectory.duration_s >= sc.duration_s >= 60.0
        kinds = {k for _, _, k in sc.blackouts}
        assert kinds <= {"shadow", "glare", "torn"} and sc.blackouts
    sc = build_scenario("default")
    assert sorted(round(b - a, 3) for a, b, _ in sc.blackouts) == [0.5, 1.0, 2.0, 5.0]
    a5 = build_scenario("paper_a5")
    assert len(a5.layout.loads) == 10
    np.testing.assert_allclose(a5.layout.loads[0].p_world, [0.325, 2.853, 2.365])
    gim = build_scenario("gimbaled")
    st = gim.trajectory.state(np.linspace(5, 30, 50))
    tilt = [gim.cameras["cam0"].T_world_cam(T)[:3, 2] @ [0, 0, -1] for T in st.T_world_body]
    np.testing.assert_allclose(tilt, 1.0, atol=1e-12)  # floor camera looks straight down
    body = [sc.cameras["cam0"].T_world_cam(T)[:3, 2] @ [0, 0, -1] for T in st.T_world_body]
    assert min(body) < 0.999  # a body-fixed one tilts
    with pytest.raises(SimulationError):
        build_scenario("default", resolution=(0, 10))


def test_oblique_survey_sees_its_loads_at_an_angle():
    """The "oblique" scenario flies the default survey turned +-0.4 rad from square to the rack
    at each aisle waypoint: the same positions and blackouts, the heading alternately off by
    +-0.4 rad at the hovers, and the front camera sees load codes there at 15-35 deg off their
    normal (the default's at < 5 deg)."""
    from fusion.sim.scenarios import OBLIQUE_YAW_RAD

    default, oblique = build_scenario("default"), build_scenario("oblique")
    assert default.blackouts == oblique.blackouts
    kd, ko = default.trajectory.keyframes, oblique.trajectory.keyframes
    assert len(kd) == len(ko)
    np.testing.assert_allclose([k.p_world for k in ko], [k.p_world for k in kd])
    hover = [i for i in range(4, 12) if np.allclose(kd[i].p_world, kd[i - 1].p_world)]  # aisle 1
    turns = [ko[i].yaw_rad - kd[i].yaw_rad for i in hover]
    assert len(turns) >= 3 and np.allclose(np.abs(turns), OBLIQUE_YAW_RAD) and len(set(np.sign(turns))) == 2

    def angles(sc, t):
        T_wc = sc.cameras["cam1"].T_world_cam(sc.trajectory.state(np.array([t])).T_world_body[0])
        out = []
        for load in sc.layout.loads:
            p_cam = inv_T(T_wc) @ np.append(load.p_world, 1.0)
            uv = sc.cameras["cam1"].project(p_cam[None, :3])[0]
            if p_cam[2] > 0 and np.all(uv > 0) and np.all(uv < [640, 480]):
                normal = load.T_world_symbol[:3, 2]
                out.append(np.degrees(np.arccos(abs(normal @ T_wc[:3, 2]))))
        return out

    t_hover = [kd[i].t_s - 0.1 for i in hover]
    assert max(max(angles(default, t), default=0.0) for t in t_hover) < 5.0
    seen = [a for t in t_hover for a in angles(oblique, t)]
    assert seen and 15.0 < min(seen) and max(seen) < 35.0


def test_default_blackouts_hide_codes_that_would_be_readable():
    """Each blackout of the default scenario sits where the floor camera would read a code."""
    from fusion.sim.simulate import floor_code_readable

    sc = build_scenario("default")
    cam = sc.cameras["cam0"]
    codes = sc.codes()
    for t0, t1, kind in sc.blackouts:
        for t in (t0 + 0.1 * (t1 - t0), 0.5 * (t0 + t1)):
            T_wc = cam.T_world_cam(sc.trajectory.state(np.array([t])).T_world_body[0])
            fx = sc.effects("cam0", t)
            assert fx.blackout == kind
            dark = render_view(cam, T_wc, codes, np.random.default_rng(0), fx, sc.occluders)
            fx.blackout = None
            clean = render_view(cam, T_wc, codes, np.random.default_rng(0), fx, sc.occluders)
            assert floor_code_readable(clean), f"{kind} at {t:.2f} s hides nothing"
            assert not floor_code_readable(dark), f"{kind} at {t:.2f} s leaves a code readable"


def test_simulator_png_settings_are_lossless_at_every_level():
    import cv2

    from fusion.sim.simulate import png_params

    rng = np.random.default_rng(8)
    img = np.clip(rng.normal(128.0, 40.0, (48, 64)), 0, 255).astype(np.uint8)
    sizes = {}
    for level in (0, 1, 5, 9):
        ok, buf = cv2.imencode(".png", img, png_params(level))
        assert ok
        np.testing.assert_array_equal(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), img)
        sizes[level] = len(buf)
    assert sizes[0] >= img.size  # stored: no compression
    assert sizes[9] <= sizes[1] < sizes[0]
