"""Codes tracked through frames where they do not decode (fusion.qr.track): identity from the
prediction, gated; counted; written to and read from the detection cache."""

from __future__ import annotations

import numpy as np

from fusion.camera import CameraModel
from fusion.geometry import make_T
from fusion.qr.detect import CameraStats, detect_frames
from fusion.qr.track import CodeTracker
from fusion.sim.render import PlacedCode, RenderEffects, project_code_corners, render_view
from fusion.types import QRDetection

CAMERA = CameraModel(640, 480, 520.0, 520.0, 320.0, 240.0)
CODE = PlacedCode("0/1/2", np.eye(4), 0.20)
R_DOWN = np.diag([1.0, -1.0, -1.0])
SPEED_M_S = 0.6
RATE_HZ = 30.0


def _frames(n: int, blur_from: int, seed: int = 0, occlude_from: int | None = None):
    """A down-looking camera 0.9 m above the code moving along x at SPEED_M_S: frames, stamps,
    true corners; frames from `blur_from` on have 10 px motion blur (the decoder fails)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        T = make_T(R_DOWN, [-0.15 + SPEED_M_S * k / RATE_HZ, 0.02, 0.9])
        blur = 10.0 if k >= blur_from else 0.0
        img = render_view(CAMERA, T, [CODE], rng, RenderEffects(1.5, 1.0, blur, 0.0))
        truth = project_code_corners(CAMERA, T, CODE)
        if occlude_from is not None and k >= occlude_from:
            img[:, :] = 128  # the code is gone: nothing may be tracked
        out.append((img, int(k * 1e9 / RATE_HZ), truth))
    return out


def test_code_tracked_through_motion_blur_with_its_identity_and_counted():
    frames = _frames(8, blur_from=2)
    tracker = CodeTracker(CAMERA)
    stats = CameraStats()
    per_frame = detect_frames(
        [f[0] for f in frames], "cam0", [f[1] for f in frames], CAMERA, stats=stats, tracker=tracker
    )
    assert [len(d) for d in per_frame[:2]] == [1, 1] and not any(
        d.tracked for d in per_frame[0] + per_frame[1]
    )
    tracked = [d for dets in per_frame[2:] for d in dets]
    assert len(tracked) == 6 and all(d.tracked and d.payload == CODE.payload for d in tracked)
    for d, (_, ts, truth) in zip(tracked, frames[2:]):
        assert d.timestamp_ns == ts
        assert np.max(np.linalg.norm(d.corners_px - truth, axis=1)) < 0.5
        assert d.corner_cov_px2 is not None
    assert stats.tracked == 6 and stats.frames_with_tracked_only == 6 and stats.detections == 8
    assert tracker.stats.tracked == 6


def test_nothing_is_tracked_where_the_code_is_gone():
    frames = _frames(5, blur_from=2, occlude_from=2)
    tracker = CodeTracker(CAMERA)
    per_frame = detect_frames([f[0] for f in frames], "cam0", [f[1] for f in frames], CAMERA, tracker=tracker)
    assert [len(d) for d in per_frame] == [1, 1, 0, 0, 0]
    assert tracker.stats.refine_failed >= 1 and tracker.stats.tracked == 0
    assert not tracker.tracks  # dropped after TRACK_MAX_MISSES frames without a sighting


def test_a_prediction_off_by_more_than_the_gate_gives_no_identity():
    """A code predicted 3 modules from where a (visible, undecodable) code lies: refinement may
    lock onto the real symbol, but the innovation gate refuses to name it."""
    ((img, ts, truth),) = _frames(1, blur_from=0)
    module = np.linalg.norm(truth[1] - truth[0]) / CODE.modules
    tracker = CodeTracker(CAMERA)
    pred = truth + [3.0 * module, 0.0]
    out = tracker.step(img, "cam0", ts, [], [], {"0/5/5": (pred, 1.0, CODE.modules)})
    assert out == []
    assert tracker.stats.gated + tracker.stats.refine_failed == 1
    ok = tracker.step(img, "cam0", ts + 1, [], [], {"0/1/2": (truth + 0.8, 1.5, CODE.modules)})
    assert len(ok) == 1 and ok[0].payload == "0/1/2" and ok[0].tracked


def test_no_track_where_a_decoded_code_lies():
    ((img, ts, truth),) = _frames(1, blur_from=0)
    decoded = QRDetection("cam0", ts, "0/1/2", truth, truth, 0.05, 0.0025 * np.eye(8))
    tracker = CodeTracker(CAMERA)
    out = tracker.step(img, "cam0", ts, [decoded], [21], {"0/9/9": (truth + 1.0, 1.5, 21)})
    assert out == [] and tracker.stats.ambiguous == 1


def test_tracked_flag_survives_the_detection_cache(tmp_path):
    from fusion.qr.detect import DetectionResult, read_cache, write_cache

    c = np.array([[10.0, 10.0], [50.0, 10.0], [50.0, 50.0], [10.0, 50.0]])
    dets = [
        QRDetection("cam0", 1, "0/1/2", c, c + 0.5, 0.05, 0.0025 * np.eye(8)),
        QRDetection("cam0", 2, "0/1/2", c + 1, c + 1.2, 0.05, 0.0025 * np.eye(8), tracked=True),
    ]
    stats = {"cam0": CameraStats(frames_total=2, detections=2, tracked=1)}
    write_cache(DetectionResult(dets, stats), tmp_path / "detections.csv", "f" * 64)
    back = read_cache(tmp_path / "detections.csv", "f" * 64)
    assert back is not None and [d.tracked for d in back.detections] == [False, True]
    assert back.stats["cam0"].tracked == 1
