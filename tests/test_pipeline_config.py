"""RunConfig choices checked at the pipeline boundary: a bad one is one EstimationError line; what
the fusion takes of the detections (floor_inputs) is what it took of the detections themselves."""

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fusion.errors import EstimationError
from fusion.log import read_flight
from fusion.pipeline import RunConfig, floor_inputs, fuse_stage, localize_stage
from fusion.qr.codes import classify
from fusion.qr.detect import detect_flight
from fusion.types import Trajectory
from fusion.warehouse.floorcodes import as_built_input
from fusion.warehouse.view3d import floor_codes_from_payloads


def test_unknown_robust_kernel_is_an_estimation_error():
    raw = Trajectory("pnp", np.array([0, 1], np.int64), np.stack([np.eye(4)] * 2), None)
    log = SimpleNamespace(imu=object(), velocity=None)
    loc = SimpleNamespace(trajectories={"pnp": raw})
    with pytest.raises(EstimationError, match="robust kernel 'bogus' is not one of none, huber"):
        fuse_stage(log, loc, RunConfig(robust="bogus"))


# =========================================================================== floor inputs

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"


@pytest.fixture(scope="module")
def sample_as_built():
    """The sample flight (51 frames) with its floor codes laid as built (placement sigmas set:
    its world.yaml says exact), its detections and per-frame estimates."""
    log = read_flight(SAMPLE)
    log = replace(log, world=replace(log.world, placement_sigma_m=0.01, placement_sigma_deg=1.0))
    det = detect_flight(log, workers=1, progress=False)
    return log, det, localize_stage(log, det, RunConfig(workers=1, progress=False))


@pytest.mark.parametrize("tight", [False, True])
def test_fuse_stage_gets_the_same_floor_inputs_from_floor_inputs_as_from_detections(
    sample_as_built, monkeypatch, tight
):
    """The run passes floor_inputs(det), having let the detections go; the back ends must get
    what fuse_stage took from the detections themselves: each floor frame's classified
    sightings (tight corner factors) and the as-built input built from them."""
    import fusion.pipeline as P

    log, det, loc = sample_as_built
    cfg = RunConfig(workers=1, progress=False, tight=tight)
    called: list[tuple[str, dict]] = []

    def capturing(name):
        def capture(*args, **kwargs):
            called.append((name, kwargs))
            raise EstimationError("captured")

        return capture

    for name in ("smooth_windowed", "smooth_incremental", "run_ekf"):
        monkeypatch.setattr(P, name, capturing(name))
    outs = [P.fuse_stage(log, loc, cfg, d) for d in (det, P.floor_inputs(log, det, cfg))]
    assert outs[0].notes == outs[1].notes
    # per way: the batch and the incremental smoother (the EKF, and its causal pass of the
    # placement's correlation inflation, take poses only)
    smoothers = [kw for name, kw in called if name != "run_ekf"]
    assert [name for name, _ in called if name != "run_ekf"] == ["smooth_windowed", "smooth_incremental"] * 2
    # the reference: the sightings and as-built input as fuse_stage built them before
    sightings = {t: classify(d, log.world).floor for t, d in det.by_frame("cam0").items()}
    ref, _ = as_built_input(log.world, {}, sightings, log.floor.camera, cfg.corner_sigma_px, tight)
    for smoother in smoothers:  # batch, incremental; both ways
        if tight:
            frames = smoother["floor_frames"]
            assert frames.keys() == sightings.keys() and len(frames) > 0
            for t in frames:
                assert [s.detection for s in frames[t]] == [s.detection for s in sightings[t]]
        else:
            assert "floor_frames" not in smoother
    for batch in (smoothers[0], smoothers[2]):
        if tight:  # as-built codes are not estimated with --tight
            assert ref is None and "as_built" not in batch
            continue
        got = batch["as_built"]
        assert ref is not None and len(ref.sightings) > 0
        assert [c.code_id for c in got.codes] == [c.code_id for c in ref.codes]
        for field in ("timestamps_ns", "code", "T_code_body", "cov"):
            np.testing.assert_array_equal(getattr(got.sightings, field), getattr(ref.sightings, field))


def test_floor_inputs_keep_the_floor_code_grid_of_the_detections(sample_as_built):
    log, det, _ = sample_as_built
    xy = floor_inputs(log, det, RunConfig(workers=1, progress=False)).codes_xy
    expected = floor_codes_from_payloads((d.payload for d in det.for_camera("cam0")), 1.0)
    assert xy is not None and len(xy) > 0
    np.testing.assert_array_equal(xy, expected)


def test_a_gimbaled_floor_camera_says_its_fused_tilt_is_unchecked(sample_as_built, monkeypatch):
    """Level-frame fixes give position and yaw: the fused roll / pitch are the IMU's against the
    fixes' motion, which the health does not check (14-40 mrad off with sigma 1-6 mrad on
    simulated gimbaled flights, BENCHMARKS.md): the run says so; a body-fixed camera does not."""
    import fusion.pipeline as P

    log, det, loc = sample_as_built

    def capture(*args, **kwargs):
        raise EstimationError("captured")

    for name in ("smooth_windowed", "smooth_incremental", "run_ekf"):
        monkeypatch.setattr(P, name, capture)
    cfg = RunConfig(workers=1, progress=False)
    floor = log.floor
    gimbaled = replace(
        log, cameras={**log.cameras, "cam0": replace(floor, camera=replace(floor.camera, mount="gimbaled"))}
    )
    assert P.GIMBALED_TILT_NOTE in P.fuse_stage(gimbaled, loc, cfg, det).notes
    assert P.GIMBALED_TILT_NOTE not in P.fuse_stage(log, loc, cfg, det).notes


def test_the_tilt_consider_reaches_a_gimbaled_camera_whose_level_is_not_stated_exact(sample_as_built):
    """With level fixes and an IMU, every fused trajectory's rotation block gains the levelling
    limit (tiltconsider.py) after the health, scaled by the share of the fixes' tilt-coupled
    error that PnP's level conditioning keeps (floor.condition_on_level,
    tiltconsider.level_kept_fraction): none with the level stated exact (mount sigma 0), the full
    limit without the free tilt covariances; a body-fixed floor camera gets nothing."""
    import fusion.pipeline as P
    from fusion.estimate import FusionConfig
    from fusion.estimate.tiltconsider import tilt_consider_covariance, tilt_consider_sigma_rad

    log, det, loc = sample_as_built
    cfg = RunConfig(workers=1, progress=False, incremental=False)
    floor = log.floor

    def with_camera(**changes):
        return replace(
            log, cameras={**log.cameras, "cam0": replace(floor, camera=replace(floor.camera, **changes))}
        )

    full = tilt_consider_sigma_rad(FusionConfig().bias_prior_sigma_accel_m_s2)
    # PnP's free tilt known to 0.2 mrad on every frame: a level stated to 0.01 deg keeps the share
    # f = s^2 / (c + s^2) of the tilt-coupled error (tiltconsider.level_kept_fraction)
    c, s = (2e-4) ** 2, np.radians(0.01)
    known = replace(loc, free_tilt_covariances=np.tile(c * np.eye(2), (5, 1, 1)))
    cases = (
        # 0.1 deg, the default; the sample's PnP ran body-fixed, so no free tilt: the full term
        (with_camera(mount="gimbaled", mount_sigma_deg=None), loc, full),
        (with_camera(mount="gimbaled", mount_sigma_deg=0.01), known, np.sqrt(s**2 / (c + s**2)) * full),
        (with_camera(mount="gimbaled", mount_sigma_deg=0.0), loc, None),
        (with_camera(mount="gimbaled", mount_sigma_deg=0.0), known, None),
        (log, loc, None),
    )
    for flight, localized, sigma in cases:
        added = sigma is not None
        result = P.RunResult(Path("."), {})
        stats = P._fuse_into_result(flight, localized, cfg, det, None, result)
        assert result.trajectories and not result.failures
        for name, traj in result.trajectories.items():
            assert ("tilt_consider_sigma_rad" in stats[name]) is added
            if added:
                assert np.isclose(stats[name]["tilt_consider_sigma_rad"], sigma, rtol=1e-12)
                extra = traj.covariances[:, :3, :3] - tilt_consider_covariance(traj.T_world_body, sigma)
                assert np.all(np.linalg.eigvalsh(extra)[:, 0] > 0)


def test_frames_repeating_the_frame_before_to_the_last_bit_are_named():
    """A frozen camera (or a driver re-sending its last image) repeats every refined corner to the
    last bit, which sensor noise never does: the warning `repeated_frames` names the camera.
    The decoder's fall-back corners (half-pixel grid, refinement refused) may repeat honestly
    under slow motion and are not counted (thirty-first session's audit: a frozen floor camera
    was read as a mount 77 deg off)."""
    from fusion.pipeline import repeated_frames_warning
    from fusion.qr.detect import DetectionResult
    from fusion.types import QRDetection

    raw = np.array([[100.5, 100.5], [140.5, 100.5], [140.5, 140.5], [100.5, 140.5]])
    refined = raw + np.array([0.137, -0.071])
    rng = np.random.default_rng(0)

    def frames(corners_of, n=6, camera="cam0"):
        return [QRDetection(camera, k * 33_000_000, "0/1/2", corners_of(k), raw) for k in range(n)]

    noisy = frames(lambda k: refined + rng.normal(0, 0.01, (4, 2)))
    assert repeated_frames_warning(DetectionResult(noisy, {})) is None
    assert repeated_frames_warning(DetectionResult(frames(lambda k: raw.copy()), {})) is None
    frozen = frames(lambda k: refined.copy()) + frames(lambda k: refined + k, 3, "cam1")
    w = repeated_frames_warning(DetectionResult(frozen, {}))
    assert w is not None and w.name == "repeated_frames" and w.count == 5
    assert "cam0 (floor) 5 frame(s), the first at 0.033 s" in w.message and "cam1" not in w.message


def test_a_front_camera_none_of_whose_frames_reads_is_a_named_warning():
    from fusion.pipeline import unreadable_front_warning
    from fusion.qr.detect import CameraStats, DetectionResult

    skipped = [
        "f/mav0/cam1/data.csv:2: image 0.png is missing",
        "f/mav0/cam0/data.csv:9: image 7.png is missing",
    ]
    det = DetectionResult([], {"cam0": CameraStats(10, 1), "cam1": CameraStats(10, 10)}, skipped)
    w = unreadable_front_warning(det)
    assert w is not None and w.name == "front_camera_unreadable" and w.count == 10
    assert "cam1/data.csv:2" in w.message and "no load is mapped" in w.message
    assert unreadable_front_warning(DetectionResult([], {"cam1": CameraStats(10, 9)})) is None
    assert unreadable_front_warning(DetectionResult([], {"cam0": CameraStats(10, 10)})) is None


def test_a_stamp_jitter_warning_names_what_else_reads_as_jitter():
    """Without an IMU, or with its gaps, the motion between frames is uncertain and reads as
    stamp jitter: the warning says so instead of only "stamp frames at exposure" (thirty-first
    session's fuzz run: a log without imu0 warned front_stamp_jitter 6.3 ms)."""
    from types import SimpleNamespace

    from fusion.log import LogWarning
    from fusion.pipeline import _jitter_imu_caveat

    assert "no IMU" in _jitter_imu_caveat(SimpleNamespace(imu=None, warnings=[]))
    gappy = SimpleNamespace(imu=object(), warnings=[LogWarning("imu_gaps", 3, "...")])
    assert "(imu_gaps)" in _jitter_imu_caveat(gappy)
    assert _jitter_imu_caveat(SimpleNamespace(imu=object(), warnings=[])) == ""
