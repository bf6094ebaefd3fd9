"""Camera effects of the simulator and the noise scales estimated from residuals (issue 10,
items 3 and 6): each effect changes the image as intended (seeded); variance-component
estimation recovers a known noise scale and leaves a correctly modelled flight at 1."""

from __future__ import annotations

import math

import cv2
import gtsam
import numpy as np
import pytest
from test_estimate import FRONT_CAM, floor_sightings, make_flight, nees

from fusion.cli import _camera_options, build_parser
from fusion.errors import SimulationError
from fusion.estimate import FusionConfig, run_ekf, smooth
from fusion.estimate import variance as vc
from fusion.geometry import make_T
from fusion.qr.pnp.flight import pnp_trajectory
from fusion.sim.render import (
    OCCLUDER_DN,
    PlacedCode,
    RenderEffects,
    apply_photometric,
    defocus_kernel,
    project_code_corners,
    render_view,
)
from fusion.sim.scenarios import CameraOptions, apply_camera_options, build_scenario, make_cameras
from fusion.world import World

# ============================================================================ camera effects


def one_code_view():
    """The floor camera 0.8 m above a 0.20 m floor code (symbol centre at the origin)."""
    cam = make_cameras()["cam0"]
    T_world_cam = make_T(np.diag([1.0, -1.0, -1.0]), [0.01, -0.02, 0.8])
    code = PlacedCode("0/0/0", np.eye(4), 0.20)
    return cam, T_world_cam, [code]


def render(effects: RenderEffects, seed: int = 0) -> np.ndarray:
    cam, T_wc, codes = one_code_view()
    return render_view(cam, T_wc, codes, np.random.default_rng(seed), effects)


def symbol_mask() -> np.ndarray:
    cam, T_wc, codes = one_code_view()
    quad = project_code_corners(cam, T_wc, codes[0])
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.fillConvexPoly(mask, np.round(quad).astype(np.int32), 1)
    return mask.astype(bool)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(float) - b.astype(float)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse)


def test_effects_are_seeded():
    fx = RenderEffects(noise_sigma_dn=3.0, shot_noise_dn=0.05, glare_fraction=0.2, occlusion_fraction=0.1)
    assert np.array_equal(render(fx, seed=4), render(fx, seed=4))
    assert not np.array_equal(render(fx, seed=4), render(fx, seed=5))


def test_default_effects_leave_the_image_unchanged():
    """No new effect asked for: the same image as before the effects existed (noise 0)."""
    clean = render(RenderEffects(noise_sigma_dn=0.0))
    same = render(RenderEffects(noise_sigma_dn=0.0, contrast=1.0, vignetting=0.0, jpeg_quality=None))
    assert np.array_equal(clean, same)


def test_jpeg_quality_lowers_psnr():
    clean = render(RenderEffects(noise_sigma_dn=0.0))
    p = [psnr(clean, render(RenderEffects(noise_sigma_dn=0.0, jpeg_quality=q))) for q in (95, 60, 15)]
    assert math.isfinite(p[0]) and p[0] > p[1] > p[2], p
    assert p[2] < 40.0


def test_occlusion_hides_the_given_fraction():
    inside = symbol_mask()
    clean = render(RenderEffects(noise_sigma_dn=0.0)).astype(float)
    for f in (0.1, 0.25, 0.5):
        img = render(RenderEffects(noise_sigma_dn=0.0, occlusion_fraction=f), seed=2).astype(float)
        hidden = np.abs(img - OCCLUDER_DN) <= 2.0
        changed = hidden & (np.abs(img - clean) > 2.0)
        # black modules (30 DN) are not hidden by eye but are by the occluder: count its pixels
        frac = hidden[inside].mean()
        assert abs(frac - f) < 0.04, (f, frac)
        assert changed[~inside].sum() < 0.02 * inside.sum()  # a strip of the symbol, not beyond


def test_glare_saturates_about_the_given_fraction():
    inside = symbol_mask()
    clean = render(RenderEffects(noise_sigma_dn=0.0))
    assert (clean[inside] == 255).mean() == 0.0
    fracs = []
    for f in (0.1, 0.3):
        img = render(RenderEffects(noise_sigma_dn=0.0, glare_fraction=f), seed=3)
        fracs.append(float((img[inside] >= 254).mean()))
        assert 0.5 * f < fracs[-1] < 1.6 * f, (f, fracs[-1])
    assert fracs[1] > fracs[0]


def test_defocus_is_a_normalised_disc_and_softens_edges():
    k = defocus_kernel(3.0)
    assert k.shape == (9, 9) and abs(k.sum() - 1) < 1e-6
    assert abs(k[4, 4] - 1 / (math.pi * 9)) < 0.1 / (math.pi * 9)  # uniform inside
    assert defocus_kernel(0.2) is None
    clean = render(RenderEffects(noise_sigma_dn=0.0)).astype(float)
    soft = render(RenderEffects(noise_sigma_dn=0.0, defocus_px=3.0)).astype(float)
    grad = lambda im: np.abs(np.diff(im, axis=1)).max()
    assert grad(soft) < 0.5 * grad(clean)
    assert abs(soft.mean() - clean.mean()) < 1.0


def test_vignetting_darkens_the_corners_by_the_given_fraction():
    rng = np.random.default_rng(0)
    flat = np.full((480, 640), 200.0, np.float32)
    out = apply_photometric(flat, RenderEffects(noise_sigma_dn=0.0, vignetting=0.4), rng)
    assert out[240, 320] >= 199
    assert abs(int(out[0, 0]) - 120) <= 2 and abs(int(out[479, 639]) - 120) <= 2


def test_contrast_and_overexposure():
    rng = np.random.default_rng(0)
    img = np.tile(np.r_[np.full(32, 30.0), np.full(32, 220.0)].astype(np.float32), (48, 10))
    low = apply_photometric(img.copy(), RenderEffects(noise_sigma_dn=0.0, contrast=0.25), rng)
    assert abs(float(low.std()) - 0.25 * float(img.std())) < 1.0
    over = apply_photometric(img.copy(), RenderEffects(noise_sigma_dn=0.0, gain=1.6), rng)
    assert (over[img > 100] == 255).all() and abs(float(over[img < 100].mean()) - 48) < 1


def test_shot_noise_grows_with_the_signal():
    g, read = 0.1, 2.0
    for level in (50.0, 200.0):
        flat = np.full((200, 200), level, np.float32)
        out = apply_photometric(
            flat, RenderEffects(noise_sigma_dn=read, shot_noise_dn=g), np.random.default_rng(1)
        )
        expect = math.sqrt(g * level + read**2)
        assert abs(float(out.astype(float).std()) - expect) < 0.1 * expect, (level, out.std(), expect)


def test_render_effects_validate_new_fields():
    for bad in (
        dict(vignetting=1.0),
        dict(contrast=0.0),
        dict(glare_fraction=1.5),
        dict(occlusion_fraction=-0.1),
        dict(jpeg_quality=0),
        dict(defocus_px=-1.0),
    ):
        with pytest.raises(SimulationError):
            RenderEffects(**bad)


def test_camera_options_preset_and_lens():
    opts = CameraOptions.preset("realistic", jpeg_quality=50)
    assert opts.jpeg_quality == 50 and opts.noise_dn == 4.0 and opts.vignetting == 0.3
    assert opts.exposure_s == pytest.approx(0.020)
    with pytest.raises(SimulationError):
        CameraOptions.preset("cinematic")
    sc = build_scenario("default")
    f0 = sc.cameras["cam0"].fu
    apply_camera_options(sc, CameraOptions(focal_scale=0.8, distortion=(-0.1, 0.02, 0.0, 0.0), defocus_px=2))
    assert sc.cameras["cam0"].fu == pytest.approx(0.8 * f0)
    assert sc.cameras["cam1"].distortion[0] == -0.1
    fx = sc.effects("cam0", 1.0)
    assert fx.defocus_px == 2 and fx.jpeg_quality is None


def test_simulate_cli_options():
    args = build_parser().parse_args(
        ["simulate", "out", "--camera-effects", "realistic", "--jpeg", "60", "--resolution", "800x600"]
    )
    opts = _camera_options(args)
    assert args.resolution == (800, 600)
    assert opts.jpeg_quality == 60 and opts.noise_dn == 4.0


# ============================================================================ variance components


def test_gated_component_recovers_a_scale():
    rng = np.random.default_rng(0)
    dof = rng.integers(2, 30, 400)
    chi2 = 4.0 * rng.chisquare(dof)
    chi2[:5] *= 100.0  # gross outliers
    comp = vc.gated_variance_component(chi2, dof)
    assert comp.n_gated >= 5 and abs(comp.scale - 4.0) < 0.3
    plain = vc.gated_variance_component(chi2[5:], dof[5:], quantile=None)
    assert abs(plain.scale - 4.0) < 0.3 and plain.n_gated == 0
    assert vc.gated_variance_component([], []).dof == 0.0


def pnp_frames(sigma_true_px: float, seed: int, n_frames: int = 60):
    """Synthetic floor-camera frames of a flight (fusion's test flight), corners with N(0,
    sigma_true) noise, each detection claiming 0.15 px."""
    fl = make_flight(seed=seed, duration_s=4.0, gaps=())
    cam = make_cameras()["cam0"]
    floor = floor_sightings(fl, cam, seed=seed + 1, sigma_px=sigma_true_px)
    frames = {}
    for ts in sorted(floor)[:n_frames]:
        dets = []
        for s in floor[ts]:
            s.detection.corner_sigma_px = 0.15
            dets.append(s.detection)
        frames[ts] = dets
    return frames, cam


@pytest.mark.parametrize("factor", [1.0, 2.0])
def test_pnp_chi2_recovers_the_corner_noise_scale(factor):
    frames, cam = pnp_frames(0.15 * factor, seed=3)
    world = World(0.12, 1.0, 0.15, (-20.0, 20.0), (-20.0, 20.0), 0.0, 0.0)  # laid exactly
    traj, stats = pnp_trajectory(frames, cam, world)
    assert stats.n_posed > 40 and len(stats.frame_chi2) == stats.n_posed
    scaled, report = vc.scale_pnp_trajectory(traj, [stats])
    assert report["applied"] and report["dof"] > 500
    assert abs(report["sigma_factor"] - factor) < 0.1 * factor, report
    assert np.allclose(scaled.covariances, traj.covariances * report["scale"])


def test_pnp_noise_scales_per_corner_class_recover_each_class_and_its_nees():
    """Half the codes at the decoder's corners (claimed 1.5 px, true 0.6 px), half refined
    (claimed 0.15 px, true 0.45 px): one pooled factor cannot make both honest; Helmert's
    per-class factors recover (0.6 / 1.5)^2 and (0.45 / 0.15)^2, and the poses' NEES."""
    import dataclasses

    fl = make_flight(seed=3, duration_s=6.0, gaps=())
    cam = make_cameras()["cam0"]
    floor = floor_sightings(fl, cam, seed=4, sigma_px=0.0)
    rng = np.random.default_rng(9)
    frames = {}
    for ts in sorted(floor)[:120]:
        dets = []
        for j, s in enumerate(floor[ts]):
            sigma_true, sigma_claimed = (0.6, 1.5) if j % 2 == 0 else (0.45, 0.15)
            noisy = s.detection.corners_px + rng.normal(0.0, sigma_true, (4, 2))
            dets.append(dataclasses.replace(s.detection, corners_px=noisy, corner_sigma_px=sigma_claimed))
        frames[ts] = dets
    world = World(0.12, 1.0, 0.15, (-20.0, 20.0), (-20.0, 20.0), 0.0, 0.0)  # laid exactly
    traj, stats = pnp_trajectory(frames, cam, world)
    assert stats.n_posed == 120
    # the class pieces add up to the frame's chi2, dof and covariance
    for c, chi2, T, dof, G, cov in zip(
        stats.frame_class_chi2,
        stats.frame_chi2,
        stats.frame_class_redundancy,
        stats.frame_dof,
        stats.frame_class_covariance,
        traj.covariances,
    ):
        assert math.isclose(c.sum(), chi2, rel_tol=1e-9) and math.isclose(T.sum(), dof, rel_tol=1e-9)
        assert np.allclose(G.sum(axis=0), cov, rtol=1e-8, atol=1e-14)
    truth = dict(zip(fl.frame_t.tolist(), fl.T_true))
    T_true = np.array([truth[int(t)] for t in traj.timestamps_ns])
    pooled, _ = vc.scale_pnp_trajectory(traj, [stats])
    scaled, report = vc.scale_pnp_trajectory_by_class(traj, [stats])
    assert report["by_class"] and report["applied"]
    refined, decoder = report["classes"]["refined"], report["classes"]["decoder"]
    assert abs(refined["applied_scale"] - 9.0) < 0.15 * 9.0, refined
    assert abs(decoder["applied_scale"] - 0.16) < 0.15 * 0.16, decoder
    assert nees(pooled, T_true).mean() > 12.0  # one factor: overconfident where refined codes are
    assert 0.5 * 6 <= nees(scaled, T_true).mean() <= 1.5 * 6
    # one class alone: exactly the pooled factor
    one = {t: [dataclasses.replace(d, corner_sigma_px=0.15) for d in v] for t, v in frames.items()}
    traj1, stats1 = pnp_trajectory(one, cam, world)
    a, rep_a = vc.scale_pnp_trajectory(traj1, [stats1])
    b, rep_b = vc.scale_pnp_trajectory_by_class(traj1, [stats1])
    assert not rep_b["by_class"] and rep_b["scale"] == rep_a["scale"]
    assert np.array_equal(a.covariances, b.covariances)
    assert rep_b["classes"]["decoder"]["dof"] == 0.0


def _two_class_frames(seed: int, refined_every: int, sigma_refined: tuple[float, float]):
    """Frames of a simulated flight whose codes keep the decoder's corners (claimed 1.5 px, true
    0.6 px), except one code in every `refined_every` frames with refined corners (true, claimed
    sigma_refined px): the clipping x2.6 mix (BENCHMARKS.md, x26)."""
    import dataclasses

    fl = make_flight(seed=seed, duration_s=6.0, gaps=())
    cam = make_cameras()["cam0"]
    floor = floor_sightings(fl, cam, seed=seed + 1, sigma_px=0.0)
    rng = np.random.default_rng(seed + 2)
    frames = {}
    for i, ts in enumerate(sorted(floor)[:120]):
        dets = []
        for j, s in enumerate(floor[ts]):
            refined = j == 0 and i % refined_every == 0
            sigma_true, sigma_claimed = sigma_refined if refined else (0.6, 1.5)
            noisy = s.detection.corners_px + rng.normal(0.0, sigma_true, (4, 2))
            dets.append(dataclasses.replace(s.detection, corners_px=noisy, corner_sigma_px=sigma_claimed))
        frames[ts] = dets
    world = World(0.12, 1.0, 0.15, (-20.0, 20.0), (-20.0, 20.0), 0.0, 0.0)  # laid exactly
    traj, stats = pnp_trajectory(frames, cam, world)
    truth = dict(zip(fl.frame_t.tolist(), fl.T_true))
    return traj, stats, np.array([truth[int(t)] for t in traj.timestamps_ns])


def test_a_thin_corner_class_is_not_pooled_with_the_other():
    """A few refined codes (claimed 0.15 px, true 0.6 px) among decoder corners (claimed 1.5 px,
    true 0.6 px): too few degrees of freedom for the refined class's own estimate.  Pooled, they
    took the decoder's factor (~0.2) and their frames were far overconfident; now the refined
    class keeps its own chi2/dof (>= 1), the decoder class its Helmert factor, a warning says
    the thin class's factor is a rough one, and the refined frames' NEES comes down."""
    traj, stats, T_true = _two_class_frames(seed=11, refined_every=40, sigma_refined=(0.6, 0.15))
    comps, _ = vc.pnp_class_components([stats])
    refined = comps["refined"]
    assert 0 < refined.dof < vc.MIN_DOF and comps["decoder"].usable
    pooled, _ = vc.scale_pnp_trajectory(traj, [stats])
    scaled, report = vc.scale_pnp_trajectory_by_class(traj, [stats])
    assert report["by_class"] and report["applied"]
    r, d = report["classes"]["refined"], report["classes"]["decoder"]
    assert r["thin"] and r["significant"] and not d.get("thin")
    assert math.isclose(r["applied_scale"], refined.scale, rel_tol=1e-9) and r["applied_scale"] > 4.0
    assert abs(d["applied_scale"] - 0.16) < 0.25 * 0.16, d
    assert len(report["thin_class_warnings"]) == 1 and "refined" in report["thin_class_warnings"][0]
    with_refined = np.array([np.any(c.classes == 0) for c in stats.frame_code_residuals])
    assert with_refined.sum() >= 2
    before = nees(pooled, T_true)[with_refined].mean()
    after = nees(scaled, T_true)[with_refined].mean()
    assert before > 30.0 and after < before / 3.0, (before, after)


def test_a_thin_corner_class_is_never_scaled_down():
    """A thin class whose residuals are smaller than its model (claimed 0.6 px, true 0.3 px)
    keeps its modelled covariance (factor 1, no warning): few degrees of freedom are not enough
    to trust it more."""
    traj, stats, _ = _two_class_frames(seed=12, refined_every=40, sigma_refined=(0.3, 0.6))
    comps, scales = vc.pnp_class_components([stats])
    assert comps["refined"].scale < 1.0 and not comps["refined"].usable
    assert scales is not None and scales[0] == 1.0
    _, report = vc.scale_pnp_trajectory_by_class(traj, [stats])
    assert report["classes"]["refined"]["applied_scale"] == 1.0
    assert not report["thin_class_warnings"]


def test_smoother_noise_scale_recovers_pose_noise_and_keeps_a_right_model():
    fl = make_flight(seed=5, duration_s=8.0, gaps=())
    right = smooth(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM)
    rep = right.stats["noise_scales"]
    assert rep["solves"] == 1  # nothing to rescale
    pose = rep["groups"]["pose"]
    assert abs(pose["scale"] - 1.0) < 0.15 and pose["applied_scale"] == 1.0
    assert abs(rep["imu_chi2_per_dof"] - 1.0) < 0.25
    assert abs(rep["cameras"]["cam0"]["scale"] - 1.0) < 0.15
    # the raw poses claim half their real sigma: their covariance is 4x too small
    fl2 = make_flight(seed=5, duration_s=8.0, gaps=(), sigma_rot_rad=math.radians(0.1), sigma_pos_m=0.004)
    fl2.raw.covariances = fl2.raw.covariances / 4.0
    off = smooth(fl2.frame_t, fl2.imu, fl2.raw, fl2.load_obs, FRONT_CAM)
    rep2 = off.stats["noise_scales"]
    cam0 = rep2["cameras"]["cam0"]
    assert rep2["solves"] >= 2 and abs(cam0["scale"] - 4.0) < 0.6, rep2
    assert abs(rep2["groups"]["pose"]["scale"] - 1.0) < 0.15  # after the rescaling
    e_off = nees(off.trajectory, fl2.T_true).mean()
    unscaled = smooth(
        fl2.frame_t, fl2.imu, fl2.raw, fl2.load_obs, FRONT_CAM, config=FusionConfig(noise_scale_iterations=0)
    )
    assert "variance_components" not in unscaled.stats
    assert unscaled.stats["noise_scales"]["solves"] == 1
    e_unscaled = nees(unscaled.trajectory, fl2.T_true).mean()
    assert 3.0 < e_off < 12.0 < e_unscaled, (e_off, e_unscaled)


def test_the_imu_keeps_its_stated_noise_inside_the_band_and_is_scaled_above_it():
    """The IMU is the reference: its stated noise stands while its chi2/dof is inside
    IMU_WARN_BAND; above it (densities too small) its scale is estimated like the cameras',
    never below 1."""
    lo, hi = vc.IMU_WARN_BAND
    inside = {vc.NoiseGroup.IMU: vc.VarianceComponent(1.8 * 1000.0, 1000.0, 100)}
    assert vc.next_noise_scales(vc.NoiseScales(), inside) is None
    above = {vc.NoiseGroup.IMU: vc.VarianceComponent(6.0 * 1000.0, 1000.0, 100)}
    assert vc.next_noise_scales(vc.NoiseScales(), above).imu == pytest.approx(6.0)
    # once scaled, iterated like any group, never below 1
    again = {vc.NoiseGroup.IMU: vc.VarianceComponent(1.5 * 1000.0, 1000.0, 100)}
    assert vc.next_noise_scales(vc.NoiseScales(imu=6.0), again).imu == pytest.approx(9.0)
    quiet = {vc.NoiseGroup.IMU: vc.VarianceComponent(0.1 * 1000.0, 1000.0, 100)}
    assert vc.next_noise_scales(vc.NoiseScales(imu=2.0), quiet).imu == 1.0
    assert vc.next_noise_scales(vc.NoiseScales(), quiet) is None  # below the band: only a warning
    fl = make_flight(seed=5, duration_s=4.0, gaps=())
    assert vc.scaled_imu(fl.imu, 1.0) is fl.imu and vc.scaled_imu(None, 4.0) is None
    scaled = vc.scaled_imu(fl.imu, 4.0)
    assert scaled.gyro_rad_s is fl.imu.gyro_rad_s
    assert scaled.noise.accelerometer_random_walk == pytest.approx(
        2.0 * fl.imu.noise.accelerometer_random_walk
    )


def test_an_imu_noisier_than_stated_is_scaled_and_the_fused_poses_stay_honest():
    """An IMU whose imu0/sensor.yaml states a third of its real noise (a datasheet on a
    vibrating airframe): the smoother's IMU chi2/dof is far above the band, so its noise scale is
    estimated (~9 in variance) and applied, with a warning; the fused NEES comes back in band,
    and the scale reaches the report for the back ends after the smoother."""
    from dataclasses import replace

    from fusion.log import ImuNoise

    true = ImuNoise()
    fl = make_flight(
        seed=9,
        duration_s=8.0,
        gaps=((3.0, 5.0),),
        imu_noise=ImuNoise(**{k: 3.0 * v for k, v in vars(true).items()}),
    )
    fl.imu = replace(fl.imu, noise=true)  # stated: a third of the truth
    res = smooth(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM)
    rep = res.stats["noise_scales"]
    assert 4.0 < vc.imu_scale_of(rep) < 16.0 and rep["imu_warning"], rep
    assert abs(rep["imu_chi2_per_dof"] - 1.0) < 0.3, rep
    unscaled = smooth(
        fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM, config=FusionConfig(noise_scale_iterations=0)
    )
    e_scaled = nees(res.trajectory, fl.T_true).mean()
    e_unscaled = nees(unscaled.trajectory, fl.T_true).mean()
    assert 3.0 < e_scaled < 12.0 and e_unscaled > 1.5 * e_scaled, (e_scaled, e_unscaled)
    assert "at its noise x" in vc.summary_line({"smoother": rep})


def test_a_velocity_sensor_noisier_than_stated_is_scaled_like_the_imu():
    """A velocity sensor stating a tenth of its noise (0.005 m/s against 0.05): its factors'
    chi2/dof is far above the band, so its scale is estimated and applied (the EKF and the
    incremental smoother get it through the config); stated right, it is left alone."""
    from dataclasses import replace

    fl = make_flight(seed=4, duration_s=8.0, gaps=((3.0, 5.0),))
    right = smooth(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM, velocity=fl.velocity)
    rep = right.stats["noise_scales"]
    assert vc.velocity_scale_of(rep) == 1.0 and abs(rep["velocity_chi2_per_dof"] - 1.0) < 0.3, rep
    fl.velocity = replace(fl.velocity, noise_m_s=0.005)
    res = smooth(fl.frame_t, fl.imu, fl.raw, fl.load_obs, FRONT_CAM, velocity=fl.velocity)
    rep = res.stats["noise_scales"]
    assert 50.0 < vc.velocity_scale_of(rep) < 200.0 and rep["velocity_warning"], rep
    assert abs(rep["velocity_chi2_per_dof"] - 1.0) < 0.3, rep
    assert "velocity" in vc.summary_line({"smoother": rep})
    unscaled = smooth(
        fl.frame_t,
        fl.imu,
        fl.raw,
        fl.load_obs,
        FRONT_CAM,
        velocity=fl.velocity,
        config=FusionConfig(noise_scale_iterations=0),
    )
    e_scaled = nees(res.trajectory, fl.T_true).mean()
    e_unscaled = nees(unscaled.trajectory, fl.T_true).mean()
    assert 3.0 < e_scaled < 12.0 and e_unscaled > 1.5 * e_scaled, (e_scaled, e_unscaled)


def test_tight_corner_noise_scale():
    cam = make_cameras()["cam0"]
    fl = make_flight(seed=13, duration_s=4.0, gaps=())
    floor = floor_sightings(fl, cam, seed=14, sigma_px=0.3)  # detections claim 0.3 px ...
    for frame in floor.values():
        for s in frame:  # ... but say 0.15
            s.detection.corner_sigma_px = 0.15
    res = smooth(
        fl.frame_t,
        fl.imu,
        fl.raw,
        [],
        FRONT_CAM,
        config=FusionConfig(tight=True),
        floor_frames=floor,
        floor_camera=cam,
    )
    rep = res.stats["noise_scales"]
    assert abs(rep["cameras"]["cam0"]["sigma_factor"] - 2.0) < 0.2, rep
    assert rep["cameras"]["cam0"]["group"] == "corners"


def pose_chain(rng, n: int) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int]]:
    """A chain of n random Pose3 with a prior on each (group 0) and a between factor for each
    link (group 1): the graph, its values and each factor's group."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    groups: list[int] = []
    for k in range(n):
        values.insert(k, gtsam.Pose3(gtsam.Rot3.Expmap(0.1 * rng.normal(size=3)), rng.normal(size=3)))
        graph.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.5)))
        groups.append(0)
        if k:
            graph.add(
                gtsam.BetweenFactorPose3(k - 1, k, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.1))
            )
            groups.append(1)
    return graph, values, groups


def test_group_leverages_match_the_dense_hat_matrix():
    """Exact for a small group, Hutchinson within its bound for a large one; dof add up to
    rows - unknowns."""
    rng = np.random.default_rng(3)
    graph, values, groups = pose_chain(rng, 20)
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.05)))
    groups.append(2)  # 6 rows: exact
    lin = graph.linearize(values)
    A, _ = lin.jacobian()
    h = np.diag(A @ np.linalg.solve(A.T @ A, A.T))
    rows = np.repeat(groups, 6)
    exact = np.array([h[rows == g].sum() for g in range(3)])
    lev = vc.group_leverages(lin, values.dim(), groups, 3, [6] * len(groups))
    assert lev[2] == pytest.approx(exact[2], rel=1e-9)
    for g in (0, 1):
        assert abs(lev[g] - exact[g]) < 3 * math.sqrt(2 * exact[g] / vc.HUTCHINSON_PROBES), (g, lev, exact)
    comps = vc.graph_variance_components(
        [graph.at(i) for i in range(graph.size())], [vc.NoiseGroup.POSE] * graph.size(), values
    )
    assert comps[vc.NoiseGroup.POSE].dof == pytest.approx(A.shape[0] - A.shape[1], abs=3.0)


def test_whitened_system_is_the_triplets_matrix_to_the_bit():
    """whitened_system takes A's entries out of the triplets before building it (memory): the
    same CSR matrix (indices, index type, values) and right-hand side as the matrix built from
    all the triplets at once, and GTSAM's dense Jacobian."""
    import scipy.sparse as sp

    rng = np.random.default_rng(8)
    graph, values, _ = pose_chain(rng, 30)
    lin = graph.linearize(values)
    n, m = values.dim(), 6 * graph.size()
    A, b = vc.whitened_system(lin, n, m)
    trip = lin.sparseJacobian_()
    rows, cols = trip[0].astype(np.int64) - 1, trip[1].astype(np.int64) - 1
    keep = cols < n
    b0 = np.zeros(m)
    b0[rows[~keep]] = trip[2][~keep]
    A0 = sp.csr_matrix((trip[2][keep], (rows[keep], cols[keep])), shape=(m, n))
    assert A.indices.dtype == A0.indices.dtype and A.indptr.dtype == A0.indptr.dtype
    assert np.array_equal(A.indptr, A0.indptr) and np.array_equal(A.indices, A0.indices)
    assert np.array_equal(A.data, A0.data) and np.array_equal(b, b0)
    dense, rhs = lin.jacobian()
    assert np.array_equal(A.toarray(), dense) and np.array_equal(b, rhs)


def test_ekf_reports_pose_nis():
    fl = make_flight(seed=2, duration_s=5.0, gaps=())
    res = run_ekf(fl.frame_t, fl.imu, fl.raw, fl.load_obs, front_camera=FRONT_CAM)
    nis = res.stats["pose_nis"]
    assert nis["n"] > 100 and 0.6 < nis["scale"] < 1.5


def test_apply_smoother_scales():
    fl = make_flight(seed=2, duration_s=2.0, gaps=())
    report = {"cameras": {"cam0": {"scale": 2.5}, "cam1": {"scale": 0.5}}}
    raw, obs, s0 = vc.apply_smoother_scales(report, fl.raw, fl.load_obs)
    assert s0 == 2.5 and np.allclose(raw.covariances, 2.5 * fl.raw.covariances)
    assert np.allclose(obs[0].cov_cam, 0.5 * fl.load_obs[0].cov_cam)
    same, obs2, s1 = vc.apply_smoother_scales(None, fl.raw, fl.load_obs)
    assert same is fl.raw and obs2 is fl.load_obs and s1 == 1.0


def test_group_leverages_batched_solve_equals_probe_by_probe(monkeypatch):
    """The multi-right-hand-side solve gives the probe-by-probe sums (same seeded probes)."""
    monkeypatch.setattr(vc, "HUTCHINSON_MIN_PROBES", vc.HUTCHINSON_PROBES)  # a fixed probe count
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    rng = np.random.default_rng(5)
    graph, values, groups = pose_chain(rng, 40)
    lin = graph.linearize(values)
    n = values.dim()
    lev = vc.group_leverages(lin, n, groups, 2, [6] * len(groups))
    # the earlier loop: one solve per probe, probes drawn in the same order
    A, _ = lin.jacobian()
    lu = spla.splu(sp.csc_matrix(A.T @ A))
    rows = np.repeat(groups, 6)
    gen = np.random.default_rng(vc.HUTCHINSON_SEED)
    expect = np.zeros(2)
    for g in range(2):
        Ag = A[rows == g]
        for _ in range(vc.HUTCHINSON_PROBES):
            b = Ag.T @ gen.choice((-1.0, 1.0), Ag.shape[0])
            expect[g] += float(b @ lu.solve(b)) / vc.HUTCHINSON_PROBES
    assert lev == pytest.approx(expect, rel=1e-9)


def test_a_thin_class_warning_is_a_note_of_the_run():
    """merge_floor_parts carries the thin class's warning into the run's notes and the PnP
    noise report (metrics.json noise_scales.pnp)."""
    from fusion import pipeline

    traj, stats, _ = _two_class_frames(seed=11, refined_every=40, sigma_refined=(0.6, 0.15))
    part = {"paper_error": "not run here", "paper": None, "pnp": traj, "pnp_stats": stats}
    loc = pipeline.merge_floor_parts([part], pipeline.RunConfig(workers=1, progress=False))
    warnings = loc.stats["pnp"]["noise_scale"]["thin_class_warnings"]
    assert len(warnings) == 1 and warnings[0] in loc.notes
