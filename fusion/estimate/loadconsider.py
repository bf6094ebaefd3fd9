"""Errors common to every sighting of a load code, carried into the load maps' covariances as
"consider" terms (Schmidt's consider covariance; Bierman 1977, ch. VI), as
`timeoffset.add_stamp_covariance` and `cornerbias` do for the poses.

A load is placed from its sightings, each its camera-frame centre p_cam (the front camera's
single-code PnP) hung from the body pose of its frame; every back end combines a load's n
sightings as if their errors were independent, and so shrinks them ~1/n.  Four errors are not:

- the body pose's: the sightings of one load span a few seconds, over which the floor fixes'
  error hardly changes (the same floor codes in view, their corner biases, the floor stamps;
  what the back ends model as white).  Measured on the demo flight (BENCHMARKS.md, fourteenth
  session): the sightings placed with the true poses have mean errors of -0.04 to +0.01 mm;
  with the PnP poses 0.1-0.36 mm, the same in every back end's map, whose sigmas were 0.01-0.04
  mm (load-map NEES: smoother 18, EKF 150, of 3).  So each load's covariance is kept at least at the pose's,
  mean_i J_i P_i J_i^T (J_i the world point's Jacobian with respect to the body pose, P_i the
  `trajectory`'s pose covariance at that frame): the pose error taken as common to the
  sightings, as a floor under the map's own covariance (`at_least`: the map's covariance
  grown only where it holds less than that, since a smoother's landmark marginal already holds
  the pose error it models).  The run passes the batch smoother's trajectory for every map (pipeline.
  _add_load_consider): the slow part of the pose error is the fixes', shared by every back end,
  and the smoother's P is the closest measure of it; each map's own P, mostly white noise for PnP
  and the EKF, made their maps too conservative (NEES 0.0-1.7 of 3; BENCHMARKS.md, fourteenth
  session);
- the printed side: a label printed s (1 + e) instead of world.yaml's s puts every sighting e
  p_cam farther along its ray (e per label; sigma from world.yaml's `load_qr.side_sigma_m`,
  `World.load_side_sigma_rel`);
- the front camera's stamp error (its time offset's, `CameraOffset.stamp_variance_s2`): a
  sighting placed with the pose delta off moves by delta times the velocity of the point fixed
  to the body there;
- the front camera's mount, T_BS (sensor.yaml's `T_BS_sigma_deg` / `T_BS_sigma_m`, absent: a
  calibration's usual 0.1 deg and 2 mm, `CameraModel.mount_sigmas`; the simulator states its
  own): a rotation dtheta of the camera about its centre in the body frame moves a sighting by
  -R_wb [R_bc p_cam]x dtheta, a shift dt by R_wb dt (the level frame's R for a gimbaled
  camera).  On a real drone this is likely the largest of the four: 0.1 deg is 2 mm at 1.25 m;
- the front camera's intrinsics (sensor.yaml's `intrinsics_sigma`, absent: 0.2 % of the focal
  lengths and 1 px, `CameraModel.intrinsics_sigmas`): single-code PnP reads the depth from the
  code's size in px, Z = f s / size, so a stated fu off by dfu moves p_cam = (X, Y, Z) by
  (-X, Y, Z) dfu / (2 fu) (the depth from the mean of the two sizes, the bearing (u - cu) / fu
  scaled back), fv likewise, and a principal point off by dcu by -Z dcu / fu across the ray (a
  frontal code's first order; `intrinsics_jacobian`, within 10 % of single-code PnP for codes up
  to ~20 deg off the axis, tests/test_intrinsics.py).  fu and fv off in opposite directions are not
  first order: PnP reads the stretched square as a tilted one and takes the depth from its longer
  side; for independent errors of equal sigma the Jacobian's depth variance, sigma^2 / 2, is below
  that min / max's (~0.68 sigma^2); a calibration's fu and fv errors are mostly common.

The label's, the mount's and the intrinsics' terms are also kept apart (`LoadEstimate.cov_shared`):
every flight of that label and front camera shares them, so `fusion map merge` does not average
them down.

A common error theta moves sighting i's world point by u_i theta; the load's estimate, a mean of
its sightings, by u theta, u the mean of the u_i: covariance sigma_theta^2 u u^T.  The plain
mean, not the camera-frame information weights: those credit the sightings' bearings, 5-15x
sharper than their depth in p_cam, with triangulating a scale error away (u 0.39 of the distance
on the demo flight), while the sightings' world errors are as wide across the ray as along it
(0.4-0.5 against 0.6-1.0 mm there: the pose's error).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from fusion.camera import CameraModel
from fusion.estimate.ekf import load_points_world
from fusion.estimate.timeoffset import body_twists
from fusion.geometry import inv_T
from fusion.types import LoadEstimate, LoadMap, LoadObservation, Trajectory

MAX_POSE_GAP_S = 0.1
"""A sighting with no pose of the map's trajectory within this takes no part in the terms."""


def add_load_consider_covariance(
    load_map: LoadMap,
    observations: Sequence[LoadObservation],
    trajectory: Trajectory | None,
    camera: CameraModel,
    side_sigma_rel: float,
    stamp_variance_s2: float = 0.0,
    terms: dict[str, tuple[np.ndarray, ...]] | None = None,
) -> LoadMap:
    """`load_map` with each load's covariance plus the module docstring's consider terms, from
    its camera-frame `observations` (p_cam) hung from `trajectory` (poses and covariances) through
    `camera`'s mount.  `terms`: `common_terms` of those, when already made (the run hangs every
    map from the same trajectory).  Loads without a covariance, or without a sighting near a
    pose, are kept as they are (a new LoadMap; the estimates are not moved)."""
    if trajectory is None or not len(trajectory) or not load_map.loads:
        return load_map
    if terms is None:
        terms = common_terms(observations, trajectory, camera)
    sigma_rot, sigma_shift = camera.mount_sigmas
    sigma_intr = camera.intrinsics_sigmas

    def grow(est: LoadEstimate) -> tuple[np.ndarray, np.ndarray] | None:
        term = terms.get(est.load_id)
        if term is None:
            return None
        pose_cov, u_print, u_stamp, U_rot, U_shift, U_intr = term
        # the label's, the mount's and the intrinsics' are every flight's of this label and
        # camera (cov_shared)
        shared = side_sigma_rel**2 * np.outer(u_print, u_print)
        shared += sigma_rot**2 * U_rot @ U_rot.T + sigma_shift**2 * U_shift @ U_shift.T
        shared += (U_intr * sigma_intr**2) @ U_intr.T
        cov = at_least(np.asarray(est.cov_world, dtype=float), pose_cov) + shared
        cov += stamp_variance_s2 * np.outer(u_stamp, u_stamp)
        if est.cov_shared is not None:
            shared = shared + est.cov_shared
        return cov, 0.5 * (shared + shared.T)

    return _grown(load_map, grow)


def _grown(
    load_map: LoadMap, grow: Callable[[LoadEstimate], tuple[np.ndarray, np.ndarray | None] | None]
) -> LoadMap:
    """`load_map` with each load's covariance (and shared part) as `grow(load)` gives them, a
    (cov_world, cov_shared) pair, or as it was when `grow` gives None or the load has no
    covariance (a new LoadMap; the estimates are not moved)."""
    out = []
    for est in load_map.loads:
        new = None if est.cov_world is None else grow(est)
        if new is None:
            out.append(est)
            continue
        cov, shared = new
        out.append(LoadEstimate(est.load_id, est.p_world, 0.5 * (cov + cov.T), est.n_obs, shared))
    return LoadMap(load_map.name, out)


def at_least(C: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The least covariance >= C that is also >= D along C's whitened eigenvectors: C^1/2 Q
    max(Lambda, 1) Q^T C^T/2 with Q Lambda Q^T = C^-1/2 D C^-T/2 (C itself where it already holds
    D).  The load's own covariance already holds the part of the pose error its back end
    modelled (a smoother's landmark marginal); adding J P J^T on top counted it twice (after the
    time-correlation inflation, corr15: 11 of 108 maps below their chi2 interval, demo20's
    smoother 1.1)."""
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return C + D
    Li = np.linalg.inv(L)
    lam, Q = np.linalg.eigh(Li @ D @ Li.T)
    M = L @ Q
    out = (M * np.maximum(lam, 1.0)) @ M.T
    return 0.5 * (out + out.T)


def common_terms(
    observations: Sequence[LoadObservation], trajectory: Trajectory, camera: CameraModel, block: int = 2048
) -> dict[str, tuple[np.ndarray, ...]]:
    """{load_id: (pose covariance (3, 3), u_print (3,), u_stamp (3,), U_rot (3, 3), U_shift
    (3, 3), U_intr (3, 4))}: the means over a load's sightings of J_i P_i J_i^T (zero without
    pose covariances) and of d p_world / d theta for the printed side's relative error, the
    stamp error (s), the mount's rotation (rad) and shift (m) in the body frame and the
    intrinsics [fu, fv, cu, cv] (px, `intrinsics_jacobian`).  In blocks of `block` sightings
    (the 13 poses of each through the mount), so a long flight's ~10^5 sightings need no more
    memory than the EKF's load map."""
    obs = [o for o in observations if o.p_cam is not None]
    ts = np.asarray(trajectory.timestamps_ns, dtype=np.int64)
    if not obs or not len(ts):
        return {}
    t = np.array([int(o.timestamp_ns) for o in obs], dtype=np.int64)
    k = np.clip(np.searchsorted(ts, t), 1, max(len(ts) - 1, 1)) if len(ts) > 1 else np.zeros(len(t), int)
    if len(ts) > 1:
        k = np.where(np.abs(ts[k - 1] - t) < np.abs(ts[k] - t), k - 1, k)
    near = np.flatnonzero(np.abs(ts[k] - t) <= MAX_POSE_GAP_S * 1e9)
    if not len(near):
        return {}
    ids = sorted({obs[i].load_id for i in near})
    index = {lid: i for i, lid in enumerate(ids)}
    twists = body_twists(trajectory)
    T_all = np.asarray(trajectory.T_world_body, dtype=float)
    P_all = None if trajectory.covariances is None else np.asarray(trajectory.covariances, dtype=float)
    sums = [np.zeros((len(ids), 3, 3)), np.zeros((len(ids), 3)), np.zeros((len(ids), 3))]
    sums += [np.zeros((len(ids), 3, 3)), np.zeros((len(ids), 3, 3)), np.zeros((len(ids), 3, 4))]
    R_bc = np.asarray(camera.T_body_cam, dtype=float)[:3, :3]
    count = np.zeros(len(ids))
    for a in range(0, len(near), block):
        part = near[a : a + block]
        kk = k[part]
        which = np.array([index[obs[i].load_id] for i in part])
        T_wb = T_all[kk]
        p_cam = np.array([obs[i].p_cam for i in part], dtype=float)
        p_world, J, R_wc = load_points_world(camera, T_wb, p_cam)
        if P_all is not None:
            np.add.at(sums[0], which, J @ P_all[kk] @ J.transpose(0, 2, 1))
        np.add.at(sums[1], which, np.einsum("nij,nj->ni", R_wc, p_cam))  # p_world - camera centre
        # the velocity of the world point fixed to the body, R_wb (omega x q + v)
        xi = twists[kk]
        T_bw = inv_T(T_wb)
        q = np.einsum("nij,nj->ni", T_bw[:, :3, :3], p_world) + T_bw[:, :3, 3]
        u_stamp = np.einsum("nij,nj->ni", T_wb[:, :3, :3], np.cross(xi[:, :3], q) + xi[:, 3:])
        np.add.at(sums[2], which, u_stamp)
        # the mount: the camera's parent frame (the body, or its level frame when gimbaled)
        R_wp = R_wc @ R_bc.T
        v = np.einsum("ij,nj->ni", R_bc, p_cam)  # the point from the camera's centre, parent frame
        skew = np.zeros((len(v), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
        skew -= skew.transpose(0, 2, 1)
        np.add.at(sums[3], which, -R_wp @ skew)
        np.add.at(sums[4], which, R_wp)
        np.add.at(sums[5], which, R_wc @ intrinsics_jacobian(camera, p_cam))
        np.add.at(count, which, 1.0)
    return {lid: tuple(x[i] / count[i] for x in sums) for lid, i in index.items()}


def intrinsics_jacobian(camera: CameraModel, p_cam: np.ndarray) -> np.ndarray:
    """(n, 3, 4) d p_cam / d [fu, fv, cu, cv] of single-code PnP's code centres `p_cam` (n, 3),
    first order for a frontal code (module docstring): the depth read from the code's two sizes
    in px, the lateral position from the bearing."""
    p = np.asarray(p_cam, dtype=float).reshape(-1, 3)
    X, Y, Z = p[:, 0], p[:, 1], p[:, 2]
    fu, fv = camera.fu, camera.fv
    J = np.zeros((len(p), 3, 4))
    J[:, 0, 0], J[:, 1, 0], J[:, 2, 0] = -X / (2 * fu), Y / (2 * fu), Z / (2 * fu)
    J[:, 0, 1], J[:, 1, 1], J[:, 2, 1] = X / (2 * fv), -Y / (2 * fv), Z / (2 * fv)
    J[:, 0, 2] = -Z / fu
    J[:, 1, 3] = -Z / fv
    return J


def add_places_spread(load_map: LoadMap, places: dict[str, list[np.ndarray]]) -> LoadMap:
    """`load_map` with each load read at several `places` {load id: centres (3,)} given their
    spread about its estimate, mean_k (c_k - p)(c_k - p)^T, on top of its covariance (a
    duplicated label, or a load moved during the flight: which place is meant, the map cannot
    say; pipeline.loads_at_two_places).  Loads without a covariance are kept as they are."""

    def grow(est: LoadEstimate) -> tuple[np.ndarray, np.ndarray | None] | None:
        centres = places.get(est.load_id)
        if not centres:
            return None
        d = np.asarray(centres, dtype=float) - np.asarray(est.p_world, dtype=float)
        return np.asarray(est.cov_world, dtype=float) + d.T @ d / len(d), est.cov_shared

    return _grown(load_map, grow)


def add_floor_shift(load_map: LoadMap, centroid: np.ndarray, cov_delta: np.ndarray) -> LoadMap:
    """`load_map` with each load's share of the floor's common shift in its shared part
    (`cov_shared`): the floor codes' places are fixed only by their priors up to a planar rigid
    motion delta = (t_x, t_y, theta) about `centroid` (2,) with covariance `cov_delta`
    (asbuilt.common_shift), and every pose, so every load, moves with it: by J delta, J =
    [[1, 0, -(y - y_0)], [0, 1, x - x_0], [0, 0, 0]].  Every flight over these codes shares it
    (they are where they were laid), so `fusion map merge` must not average it down: four
    rendered 45 s flights over one floor merged had load NEES 7.1 from two flights and 14.5 from
    three (BENCHMARKS.md, twentieth session).  The load's covariance already holds it (the
    poses' covariance, `add_load_consider_covariance`); it is moved into the shared part only as
    far as the covariance keeps a positive-definite rest (scaled down to 0.9 of where it would
    not).  Loads without a covariance are kept."""
    c0 = np.asarray(centroid, dtype=float)

    def grow(est: LoadEstimate) -> tuple[np.ndarray, np.ndarray] | None:
        d = np.asarray(est.p_world, dtype=float)[:2] - c0
        J = np.array([[1.0, 0.0, -d[1]], [0.0, 1.0, d[0]], [0.0, 0.0, 0.0]])
        T = J @ cov_delta @ J.T
        P = np.asarray(est.cov_world, dtype=float)
        S = np.zeros((3, 3)) if est.cov_shared is None else np.asarray(est.cov_shared, dtype=float)
        # the largest alpha <= 1 with P - S - alpha T positive definite (0.9 of the bound)
        try:
            L = np.linalg.cholesky(0.5 * (P - S + (P - S).T))
        except np.linalg.LinAlgError:  # the shared part fills the covariance already
            return None
        M = np.linalg.solve(L, np.linalg.solve(L, T).T)
        top = float(np.linalg.eigvalsh(0.5 * (M + M.T))[-1])
        alpha = 1.0 if top <= 0.9 else 0.9 / top
        shared = S + alpha * T
        return P, 0.5 * (shared + shared.T)

    return _grown(load_map, grow)


def add_departure(load_map: LoadMap, reference: LoadMap) -> LoadMap:
    """`load_map` with each load's covariance plus d d^T, d its departure from the `reference`
    map's estimate of the same load (the batch smoother's: the best estimate the flight has).
    Why: this map's error is d plus the reference's error, and d is known in the run; for an
    estimate whose error is orthogonal to the departure (the smoother's, in the linear-Gaussian
    case: d is a function of the data) its mean squared error is the reference's plus d d^T, so
    the map's own covariance plus d d^T errs on the safe side.  The filter's lag (EKF) and the
    per-frame poses' noise (PnP) move a load slowly over its sightings, which the map's own
    covariance averages away: on the sweep's 28 flights the EKF's load maps outside the chi2
    interval of their load count on 9, on 2 with d d^T (BENCHMARKS.md, fourteenth session).
    Loads without a covariance, or that the reference does not hold, are kept."""
    ref = {est.load_id: est.p_world for est in reference.loads}

    def grow(est: LoadEstimate) -> tuple[np.ndarray, np.ndarray | None] | None:
        if est.load_id not in ref:
            return None
        d = np.asarray(est.p_world, dtype=float) - np.asarray(ref[est.load_id], dtype=float)
        return np.asarray(est.cov_world, dtype=float) + np.outer(d, d), est.cov_shared

    return _grown(load_map, grow)
