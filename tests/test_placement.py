"""Floor codes laid off their payloads: PnP weighs them by world.yaml's placement sigma
(fusion.qr.pnp.whitening.floor_whitening), and the back ends count each code's error once
(fusion.estimate.correlation, class PLACEMENT)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_pnp import FLOOR_CAM, FOUR, SIGMA, T_FOUR, WORLD, body_pose, floor_of, local

from fusion.conventions import floor_payload
from fusion.estimate import correlation as co
from fusion.geometry import inv_T, rot_z, transform_points
from fusion.qr.pnp import estimate_floor_pose, floor_whitening
from fusion.qr.pnp.bias import FrameCodeResiduals
from fusion.qr.pnp.whitening import corner_whitening, placement_jacobians, placement_pixel_jacobians
from fusion.types import QRDetection, Trajectory
from fusion.world import Placement

PLACED = Placement(0.01, math.radians(0.5))


def misplaced_dets(T_world_body, centres_xy, offsets, rng, sigma=SIGMA):
    """Detections of floor codes whose payloads say (x, y) but which lie moved by offsets
    (n, 3) (dx m, dy m, dyaw rad), seen from T_world_body with corner noise `sigma`."""
    T_cam_world = inv_T(FLOOR_CAM.T_world_cam(T_world_body))
    out = []
    for (x, y), (dx, dy, dyaw) in zip(centres_xy, offsets):
        c = np.array([x, y, 0.0])
        nominal = WORLD.floor_corners_world(c)
        true = (nominal - c) @ rot_z(dyaw).T + c + np.array([dx, dy, 0.0])
        uv = FLOOR_CAM.project(transform_points(T_cam_world, true))
        uv = uv + rng.normal(0.0, sigma, uv.shape)
        out.append(QRDetection("cam0", 0, floor_payload(x, y), uv, np.round(uv), corner_sigma_px=sigma))
    return out


def test_placement_jacobian_is_the_corners_derivative_in_the_codes_pose():
    """d(px)/d(x, y, yaw) from the observed corners' homography against moving the code and
    projecting again (a tilted camera, so the homography is not affine)."""
    T = body_pose(0.3, 0.2, 1.4, 25.0, roll_deg=6.0, pitch_deg=-8.0)
    T_cam_world = inv_T(FLOOR_CAM.T_world_cam(T))
    c = np.array([0.0, 0.0, 0.0])
    nominal = WORLD.floor_corners_world(c)

    def corners(d):
        P = (nominal - c) @ rot_z(d[2]).T + c + np.array([d[0], d[1], 0.0])
        return FLOOR_CAM.project(transform_points(T_cam_world, P)).ravel()

    J = placement_jacobians(corners(np.zeros(3)).reshape(1, 4, 2), nominal[None, :, :2], c[None, :2])[0]
    e = 1e-6
    numeric = np.column_stack([(corners(e * u) - corners(-e * u)) / (2 * e) for u in np.eye(3)])
    # exact for a pinhole; the lens's distortion across one code bends it by a little
    assert np.allclose(J, numeric, rtol=0.02, atol=0.02 * np.abs(numeric).max()), (J, numeric)


def test_whitening_adds_the_placement_to_the_corner_covariance():
    rng = np.random.default_rng(3)
    sightings = floor_of(misplaced_dets(T_FOUR, FOUR, np.zeros((4, 3)), rng))
    W0 = corner_whitening([s.detection for s in sightings], SIGMA)
    assert np.array_equal(floor_whitening(sightings, SIGMA, None), W0)
    assert np.array_equal(floor_whitening(sightings, SIGMA, Placement(0.0, 0.0)), W0)
    W = floor_whitening(sightings, SIGMA, PLACED, FLOOR_CAM)
    uv = np.array([s.detection.corners_px for s in sightings])
    P = np.array([s.corners_world[:, :2] for s in sightings])
    J = placement_pixel_jacobians(FLOOR_CAM, uv, P, np.array([s.centre_world[:2] for s in sightings]))
    S = np.diag([PLACED.sigma_m**2, PLACED.sigma_m**2, PLACED.sigma_rad**2])
    # the turn's second order: the corners pulled towards the centre by (P - c) d^2 / 2
    r = P - np.array([s.centre_world[:2] for s in sightings])[:, None, :]
    shrink = np.einsum("nkij,nkj->nki", J[:, :, :2].reshape(-1, 4, 2, 2), r).reshape(-1, 8)
    shrink *= math.sqrt(0.75) * PLACED.sigma_rad**2
    C = SIGMA**2 * np.eye(8) + J @ S @ np.swapaxes(J, 1, 2) + shrink[:, :, None] * shrink[:, None, :]
    assert np.allclose(np.linalg.inv(np.swapaxes(W, 1, 2) @ W), C, rtol=1e-8)


@pytest.mark.parametrize(
    "centres,height,sigma,placed",
    [
        (FOUR, 2.6, SIGMA, PLACED),
        ([(0, 0), (1, 0)], 2.0, SIGMA, PLACED),
        ([(0, 0)], 1.2, SIGMA, PLACED),
        # clean renders' corners (0.026 px) and a 2 deg turn: the turn's second order counts
        (FOUR, 2.6, 0.026, Placement(0.01, math.radians(2.0))),
        ([(0, 0), (1, 0)], 2.0, 0.026, Placement(0.01, math.radians(2.0))),
    ],
)
def test_pose_from_misplaced_codes_is_consistent_with_the_placement_sigma(centres, height, sigma, placed):
    """Codes drawn off their payloads by the stated sigma: the pose's NEES is chi-square(6)
    with the placement in the whitening, and far beyond without (the poses are cm off while
    their covariance says 0.1 mm)."""
    rng = np.random.default_rng(11)
    cx, cy = np.mean(centres, axis=0)
    T = body_pose(cx + 0.05, cy - 0.04, height, 30.0, roll_deg=3.0, pitch_deg=-2.0)
    nees_with, nees_without, dropped = [], [], 0
    for _ in range(150):
        offsets = rng.normal(0.0, 1.0, (len(centres), 3)) * [placed.sigma_m, placed.sigma_m, placed.sigma_rad]
        sightings = floor_of(misplaced_dets(T, centres, offsets, rng, sigma))
        for placement, out in ((placed, nees_with), (None, nees_without)):
            res = estimate_floor_pose(sightings, FLOOR_CAM, sigma, placement=placement)
            if res is None or res.dropped_payloads:
                dropped += placement is not None
                continue
            xi = local(T, res.T_world_body)
            out.append(xi @ np.linalg.solve(res.covariance, xi))
    assert dropped == 0  # codes within their placement are no outliers
    assert 0.7 * 6 <= np.mean(nees_with) <= 1.4 * 6, np.mean(nees_with)
    assert np.mean(nees_without) > 100 * 6, np.mean(nees_without)


def test_placement_shares_are_part_of_the_class_shares():
    rng = np.random.default_rng(5)
    sightings = floor_of(misplaced_dets(T_FOUR, FOUR, np.zeros((4, 3)), rng))
    res = estimate_floor_pose(sightings, FLOOR_CAM, SIGMA, placement=PLACED)
    assert res is not None and res.placement_covariance is not None
    G, Gp = res.class_covariance, res.placement_covariance
    assert np.allclose(G.sum(axis=0), res.covariance, atol=1e-12)
    for c in range(len(G)):  # G_c - G_p,c is the corners' own share: positive semi-definite
        assert np.linalg.eigvalsh(G[c] - Gp[c]).min() >= -1e-12 * np.abs(G).max()
        assert np.linalg.eigvalsh(Gp[c]).min() >= -1e-12 * np.abs(G).max()
    # four codes at 2.6 m with 1 cm / 0.5 deg: a tenth of x's variance (the rest trades x with
    # the pitch that the corners' noise leaves once the codes' translations weigh little)
    assert 0.05 * res.covariance[3, 3] < Gp.sum(axis=0)[3, 3] < res.covariance[3, 3]
    assert estimate_floor_pose(sightings, FLOOR_CAM, SIGMA).placement_covariance is None


def _frames(payloads_per_frame):
    return [
        FrameCodeResiduals(tuple(p), np.zeros(len(p), np.int8), np.zeros((len(p), 8)))
        for p in payloads_per_frame
    ]


def test_placement_correlation_is_the_share_of_codes_seen_again():
    # code A in frames 0-9, B in 10-19: a frame's share seen l frames later is (10 - l) / 10
    frames = _frames([["A"]] * 10 + [["B"]] * 10)
    rho = co.placement_autocorrelation(np.arange(20), frames)
    expected = [2 * (10 - lag) / (20 - lag) for lag in range(1, 10)]
    assert np.allclose(rho, expected), (rho, expected)
    # half of a two-code frame's codes seen again: 0.5
    rho2 = co.placement_autocorrelation(np.arange(2), _frames([["A", "B"], ["A", "C"]]))
    assert np.allclose(rho2, [0.5])
    # a gap: frames 0 and 2 posed, 1 not; lag 1 has no pair, lag 2 has
    rho3 = co.placement_autocorrelation(np.array([0, 2]), _frames([["A"], ["A"]]))
    assert len(rho3) == 0  # lag 1: no posed frame one later, the sum stops


def test_inflation_moves_the_placement_out_of_the_classes_and_counts_each_code_once():
    n = 40
    frames = _frames([["A"]] * 20 + [["B"]] * 20)
    t = np.arange(n, dtype=np.int64) * 100_000_000
    rng = np.random.default_rng(2)
    covs, G, Gp = [], [], []
    for _ in range(n):
        a = rng.normal(size=(6, 6))
        corner = 1e-8 * (a @ a.T + np.eye(6))
        b = rng.normal(size=(6, 3))
        place = 1e-4 * b @ b.T
        G.append(np.stack([corner + place, np.zeros((6, 6))]))
        Gp.append(np.stack([place, np.zeros((6, 6))]))
        covs.append(corner + place)
    traj = Trajectory("pnp", t, np.repeat(np.eye(4)[None], n, axis=0), np.array(covs))
    report, inf = co.estimate_inflation(traj, frames, G, np.ones(2), placement_covariances=Gp)
    assert inf is not None and report["placement"]["lags_used"] == 19
    tau = float(inf.taus[co.PLACEMENT])
    assert report["placement"]["tau"] == pytest.approx(tau, abs=1e-3)
    assert tau == pytest.approx(1 + 2 * sum((40 - 2 * lag) / (40 - lag) for lag in range(1, 20)), rel=1e-3)
    # white residuals: the corner classes are not inflated; the placement by tau at any average
    out = inf.add_to(traj)
    assert np.allclose(out.covariances - traj.covariances, (tau - 1) * np.array(Gp)[:, 0], rtol=1e-5)
    assert np.allclose(inf.average_taus(np.array([[1.0, 3.0, 500.0]]), two_sided=False)[0, co.PLACEMENT], tau)
    # without placement terms: as before, no inflation of white residuals
    _, none = co.estimate_inflation(traj, frames, G, np.ones(2))
    assert none is None


def test_inspect_says_how_the_floor_codes_are_taken():
    from fusion.log.inspect import placement_line
    from fusion.world import World

    assert placement_line(World()) == "floor codes: placement sigma 1 cm, 1 deg (assumed: not in world.yaml)"
    assert placement_line(World(placement_sigma_m=0.02, placement_sigma_deg=0.5)).endswith(
        "2 cm, 0.5 deg (stated)"
    )
    assert "laid exactly" in placement_line(World(placement_sigma_m=0.0, placement_sigma_deg=0.0))


def test_a_placement_beyond_the_linear_model_is_a_named_warning():
    from fusion.pipeline import placement_too_wide_warning
    from fusion.world import World

    assert placement_too_wide_warning(World()) is None  # the 1 cm / 1 deg default
    assert placement_too_wide_warning(World(placement_sigma_m=0.05, placement_sigma_deg=5.0)) is None
    w = placement_too_wide_warning(World(placement_sigma_m=0.2, placement_sigma_deg=1.0))
    assert w is not None and w.name == "placement_sigma_too_wide" and "20 cm" in w.message
    assert placement_too_wide_warning(World(placement_sigma_m=0.01, placement_sigma_deg=20.0)) is not None
    # a map's codes known only loosely
    from fusion.world import FloorLayout

    tight = np.diag(np.square([0.002, 0.002, math.radians(0.1)]))
    loose = np.diag(np.square([0.08, 0.002, math.radians(0.1)]))
    layout = FloorLayout(Placement(), {"0/0/0": (np.zeros(3), tight), "0/1/0": (np.zeros(3), loose)})
    w = placement_too_wide_warning(World(), layout)
    assert w is not None and w.count == 1 and "0/1/0" in w.message and "--map" in w.message
    assert (
        placement_too_wide_warning(World(), FloorLayout(Placement(), {"0/0/0": (np.zeros(3), tight)})) is None
    )


def test_a_merged_map_places_its_codes_for_pnp():
    """`fusion run --map`: PnP takes the codes the map holds where it puts them, to its
    covariance (world.FloorLayout): on codes 1 cm off their payloads that a map knows to 1 mm,
    the poses are several times closer than on the nominal codes (clean corners, 0.03 px), and
    both are consistent."""
    from fusion.qr.pnp import pnp_trajectory
    from fusion.world import FloorLayout, World

    rng = np.random.default_rng(23)
    world = World(
        floor_side_m=WORLD.floor_side_m,
        payload_unit_m=WORLD.payload_unit_m,
        load_side_m=WORLD.load_side_m,
        placement_sigma_m=PLACED.sigma_m,
        placement_sigma_deg=math.degrees(PLACED.sigma_rad),
    )
    centres = [(0, 0), (1, 0)]
    cov = np.diag(np.square([0.001, 0.001, math.radians(0.05)]))
    frames, truth, codes = {}, {}, {}
    for trial in range(8):  # a new floor per trial, 15 frames each
        offsets = rng.normal(0.0, 1.0, (2, 3)) * [PLACED.sigma_m, PLACED.sigma_m, PLACED.sigma_rad]
        y = 2 * trial  # each trial's codes elsewhere on the floor
        for i, (x, _) in enumerate(centres):  # the map knows each code to its covariance
            known = np.r_[x + offsets[i, 0], y + offsets[i, 1], offsets[i, 2]] + rng.multivariate_normal(
                np.zeros(3), cov
            )
            codes[floor_payload(x, y)] = (known, cov)
        for k in range(15):
            T = body_pose(0.5 + rng.normal(0, 0.05), y + rng.normal(0, 0.05), 2.0, 20.0 * k, 2.0, -1.0)
            ts = (15 * trial + k) * 100_000_000
            frames[ts] = misplaced_dets(T, [(x, y) for x, _ in centres], offsets, rng, sigma=0.03)
            truth[ts] = T
    layout = FloorLayout(Placement.from_world(world), codes)
    rms, nees = {}, {}
    for name, lay in (("map", layout), ("nominal", None)):
        traj, stats = pnp_trajectory(frames, FLOOR_CAM, world, 0.03, layout=lay)
        assert len(traj) == len(frames) and stats.placement is not None
        xi = np.array([local(truth[int(t)], T) for t, T in zip(traj.timestamps_ns, traj.T_world_body)])
        nees[name] = np.einsum(
            "ni,ni->n", xi, np.linalg.solve(traj.covariances, xi[:, :, None])[:, :, 0]
        ).mean()
        rms[name] = np.sqrt(np.mean(xi[:, 3:5] ** 2))
    assert rms["map"] < 0.6 * rms["nominal"], rms
    for name in nees:
        assert 0.5 * 6 <= nees[name] <= 1.6 * 6, nees


def test_world_yaml_refuses_a_placement_sigma_no_hand_laid_floor_has(tmp_path):
    """A code's own side or more (cm given for m), or a turn that reads as another orientation:
    a one-line error naming the file; within the bounds, the warning's range."""
    from fusion.errors import WorldError
    from fusion.world import World

    for floor_qr, words in (
        ("{side_m: 0.2, placement_sigma_m: 1.0}", "placement_sigma_m is 1 m"),
        ("{side_m: 0.2, placement_sigma_deg: 45}", "placement_sigma_deg is 45 deg"),
    ):
        p = tmp_path / "world.yaml"
        p.write_text(f"floor_qr: {floor_qr}\nload_qr: {{side_m: 0.15}}\n")
        with pytest.raises(WorldError, match=words) as e:
            World.load(p)
        assert str(p) in str(e.value) and "\n" not in str(e.value)
    p.write_text(
        "floor_qr: {side_m: 0.2, placement_sigma_m: 0.1, placement_sigma_deg: 10}\nload_qr: {side_m: 0.15}\n"
    )
    assert World.load(p).placement_sigma_m == 0.1
