"""As-built floor codes (issue #12, item 1; fusion/estimate/asbuilt.py): placement sigma 0 is
today's model exactly, a misplaced code is recovered and flagged, a perfect floor flags nothing,
the exact code marginals, the CSV (escaped ids, round trip), world.yaml's fields, the simulator's
placement errors, and `fusion map merge` + `fusion run --map`."""

import csv
import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np
import pytest

from fusion import pipeline
from fusion.conventions import floor_payload
from fusion.errors import WarehouseError, WorldError
from fusion.estimate import FusionConfig, asbuilt, smooth
from fusion.estimate.asbuilt import (
    AsBuiltError,
    F,
    FloorCodeEstimate,
    FloorCodeMap,
    Placement,
    PriorMap,
    apply_prior_map,
    common_shift,
    common_shift_covs,
    read_floor_code_rows,
    read_floor_codes_csv,
    read_groundtruth_csv,
    shift_jacobians,
    write_floor_codes_csv,
    xy_yaw_cov_to_pose_cov,
)
from fusion.estimate.factors import X
from fusion.estimate.marginals import chain_marginals_with_codes
from fusion.estimate.smoother import build_problem, levenberg_marquardt
from fusion.fileio import load_yaml
from fusion.geometry import make_T, rot_z
from fusion.log.euroc import ImuNoise
from fusion.log.files import write_loads_json, write_tum
from fusion.sim.imu import synthesize_imu
from fusion.sim.placement import synthetic_sightings, true_code_poses
from fusion.sim.trajectory import random_aisle_survey
from fusion.types import LoadEstimate, LoadMap, Trajectory
from fusion.warehouse import floorcodes
from fusion.warehouse.merge import run_merge
from fusion.warehouse.runs import RUN_RECORD
from fusion.world import World

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
SIGHTING_COV = np.diag([math.radians(0.1)] * 3 + [0.003] * 3) ** 2


def _flight(seed: int, duration_s: float, offsets_of, placement: Placement, placement_in_fixes: bool = False):
    """A synthetic flight over a 1 m grid: frame_t, imu, raw (PnP from the nominal grid; with
    `placement_in_fixes` its covariance holds the placement's share, as the pipeline's PnP's does),
    AsBuiltInput, ids, true offsets (N, 3)."""
    rng = np.random.default_rng(seed)
    traj = random_aisle_survey(duration_s, rng)
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), rng)
    frame_t = np.round(np.arange(0.0, duration_s, 1 / 30.0) * 1e9).astype(np.int64)
    T_true = traj.state(frame_t * 1e-9).T_world_body
    xs, ys = np.meshgrid(np.arange(-6, 7), np.arange(-5, 6))
    xy = np.c_[xs.ravel(), ys.ravel()].astype(float)
    ids = [floor_payload(x, y) for x, y in xy]
    offsets = offsets_of(ids)
    ab, fk, fT, fcov = synthetic_sightings(
        frame_t,
        T_true,
        ids,
        xy,
        true_code_poses(xy, offsets),
        SIGHTING_COV,
        placement,
        rng,
        placement_in_fixes=placement_in_fixes,
    )
    return frame_t, imu, Trajectory("pnp", frame_t[fk], fT, fcov), ab, ids, offsets


def _busiest(ab) -> int:
    return int(np.bincount(ab.sightings.code).argmax())


def test_misplaced_code_recovered_and_flagged():
    seed = 3
    probe = _flight(seed, 20.0, lambda ids: np.zeros((len(ids), 3)), Placement())
    busiest = _busiest(probe[3])
    true = np.zeros((len(probe[4]), 3))
    true[busiest] = (0.05, -0.03, math.radians(1.0))  # 5.8 cm off
    frame_t, imu, raw, ab, ids, _ = _flight(seed, 20.0, lambda ids: true, Placement())
    res = smooth(frame_t, imu, raw, [], config=FusionConfig(), as_built=ab)
    fmap = res.floor_codes
    flagged = [c.code_id for c in fmap.misplaced]
    assert flagged == [ids[busiest]]
    est = fmap.by_id()[ids[busiest]]
    # relative to the other codes (the floor's common shift is unobservable): within 5 mm
    others = np.mean([c.offset_xy_m for c in fmap.codes if c.code_id != ids[busiest]], axis=0)
    assert np.linalg.norm(est.offset_xy_m - others - true[busiest, :2]) < 0.005
    assert est.n_obs >= 20 and est.mahalanobis_offset() > 3
    # the misplaced code no longer drags the trajectory: nominal codes (today) err by cm
    today = smooth(frame_t, imu, raw, [], config=FusionConfig())
    T_true = random_aisle_survey(20.0, np.random.default_rng(seed)).state(frame_t * 1e-9).T_world_body

    def rmse(traj):
        return math.sqrt(np.mean(np.sum((traj.positions_xyz - T_true[:, :3, 3]) ** 2, axis=1)))

    assert rmse(res.trajectory) < 0.6 * rmse(today.trajectory)


def _assert_chain_marginals_equal_gtsam(pb, n_frames: int) -> None:
    """The problem solved; its chain marginals of the codes and of every 11th pose equal
    gtsam.Marginals' to 1e-6."""
    graph = pb.graph()
    values = levenberg_marquardt(graph, pb.initial).values
    n_codes = len(pb.as_built.code_of_var)
    cov, _, ccov = chain_marginals_with_codes(graph.linearize(values), n_frames, True, 0, n_codes)
    marg = gtsam.Marginals(graph, values)
    for c in range(n_codes):
        ref = marg.marginalCovariance(F(c))
        np.testing.assert_allclose(ccov[c], ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())
    for k in range(0, n_frames, 11):
        ref = marg.marginalCovariance(X(k))
        np.testing.assert_allclose(cov[k], ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_code_marginals_equal_gtsam_with_a_maps_shift():
    """With a merged map's common shift D (a border variable on factors with no chain key), the
    chain marginals still equal gtsam's."""
    frame_t, imu, raw, ab, _, _ = _flight(
        6, 4.0, lambda ids: np.random.default_rng(2).normal(0, 0.01, (len(ids), 3)), Placement()
    )
    xy = np.array([c.T_world_nominal[:2, 3] for c in ab.codes])
    Q = np.array([np.diag([1e-4, 1e-4, math.radians(1.0) ** 2])] * len(xy))
    prior = PriorMap(
        {c.code_id: (np.r_[p, 0.0], 0.6 * q) for c, p, q in zip(ab.codes, xy, Q)},
        "map",
        dict(zip((c.code_id for c in ab.codes), 0.5 * common_shift_covs(xy, Q))),
        common_shift(xy, 0.5 * Q),
    )
    codes, shift_cov, _ = apply_prior_map(ab.codes, prior)
    pb = build_problem(
        frame_t,
        imu,
        raw,
        [],
        None,
        None,
        FusionConfig(),
        as_built=replace(ab, codes=codes, shift_cov=shift_cov),
    )
    assert pb.initial.exists(asbuilt.SHIFT_KEY)
    _assert_chain_marginals_equal_gtsam(pb, len(frame_t))


def test_perfect_floor_flags_nothing():
    frame_t, imu, raw, ab, _, _ = _flight(4, 20.0, lambda ids: np.zeros((len(ids), 3)), Placement())
    res = smooth(frame_t, imu, raw, [], config=FusionConfig(), as_built=ab)
    assert len(res.floor_codes.codes) > 10
    assert res.floor_codes.misplaced == []
    assert max(np.linalg.norm(c.offset_xy_m) for c in res.floor_codes.codes) < 0.01


@pytest.mark.parametrize("block", [512, 7])
def test_code_marginals_equal_gtsam(block, monkeypatch):
    from fusion.estimate import marginals

    monkeypatch.setattr(marginals, "BORDER_BLOCK_FRAMES", block)  # 7: blocks that do not divide 120 frames
    frame_t, imu, raw, ab, _, _ = _flight(
        5, 4.0, lambda ids: np.random.default_rng(1).normal(0, 0.01, (len(ids), 3)), Placement()
    )
    pb = build_problem(frame_t, imu, raw, [], None, None, FusionConfig(), as_built=ab)
    _assert_chain_marginals_equal_gtsam(pb, len(frame_t))


def test_approximate_code_marginals_near_exact(monkeypatch):
    """Beyond EXACT_MARGINALS_MAX_CODES the codes' covariances are approximate: their x, y, yaw
    sigma stay near the exact marginals'.  The floor's common shift is a rigid motion
    (common_shift_covs); as the summed 6 x 6 priors it had yaw 3-4.5 times too wide and x / y
    down to half."""
    from fusion.estimate import asbuilt

    placement = Placement(0.01, math.radians(1.0))

    def offsets(ids):
        rng = np.random.default_rng(5)
        return np.c_[rng.normal(0, 0.01, (len(ids), 2)), rng.normal(0, placement.sigma_rad, len(ids))]

    frame_t, imu, raw, ab, _, _ = _flight(2, 30.0, offsets, placement, True)
    maps = {}
    for mode, most in (("exact", 10**6), ("approximate", 0)):
        monkeypatch.setattr(asbuilt, "EXACT_MARGINALS_MAX_CODES", most)
        maps[mode] = smooth(frame_t, imu, raw, [], config=FusionConfig(), as_built=ab).floor_codes.by_id()
    ratios = np.array(
        [
            np.sqrt(np.diag(maps["approximate"][cid].cov_xy_yaw) / np.diag(c.cov_xy_yaw))
            for cid, c in maps["exact"].items()
            if c.n_obs >= 10
        ]
    )
    assert len(ratios) > 10
    assert ratios.min() > 0.75 and ratios.max() < 1.1, (ratios.min(axis=0), ratios.max(axis=0))


def test_floor_codes_csv_escaped_round_trip(tmp_path):
    cov = np.diag([1e-8, 1e-8, 1e-4, 4e-6, 9e-6, 1e-8])
    codes = [
        FloorCodeEstimate("=HYPERLINK(1)", np.zeros(3), make_T(rot_z(0.01), [0.03, 0.0, 0.0]), cov, 25),
        FloorCodeEstimate("0/1/2", np.array([1.0, 2.0, 0.0]), make_T(np.eye(3), [1.0, 2.0, 0.0]), cov, 3),
    ]
    for c in codes:
        c.misplaced = c.code_id.startswith("=")
    path = tmp_path / "floor_codes_smoother.csv"
    write_floor_codes_csv(path, FloorCodeMap("smoother", codes))
    rows = list(csv.reader(path.read_text().splitlines()))
    m = rows[0].index("misplaced")
    assert rows[1][0] == "'=HYPERLINK(1)" and rows[1][m] == "1" and rows[2][m] == "0"
    # no prior or common shift: empty, read as None; shift group 0; then the correlations
    assert rows[1][m + 1 : m + 11] == [""] * 9 + ["0"] and all(-1 <= float(v) <= 1 for v in rows[1][m + 11 :])
    back = read_floor_codes_csv(path)
    xyyaw, c3, n = back["=HYPERLINK(1)"]
    np.testing.assert_allclose(xyyaw, [0.03, 0.0, 0.01], atol=1e-6)
    assert n == 25
    np.testing.assert_allclose(np.sqrt(np.diag(c3)), [0.002, 0.003, 0.01], rtol=1e-3)
    assert read_floor_code_rows(path)["0/1/2"].shared_cov is None
    assert read_floor_code_rows(path)["0/1/2"].shift_group == 0
    # the x-yaw / y-yaw correlation of a code off the floor's centre comes back
    C = np.array([[4e-6, 1e-6, 2e-6], [1e-6, 9e-6, -1e-6], [2e-6, -1e-6, 4e-6]])
    turned = FloorCodeEstimate(
        "0/3/2", np.array([3.0, 2.0, 0.0]), make_T(np.eye(3), [3.0, 2.0, 0.0]), None, 9
    )
    turned.cov = xy_yaw_cov_to_pose_cov(turned.T_world_code, C)
    write_floor_codes_csv(path, FloorCodeMap("smoother", [turned]))
    np.testing.assert_allclose(read_floor_code_rows(path)["0/3/2"].cov, C, rtol=1e-5, atol=1e-12)
    write_floor_codes_csv(path, FloorCodeMap("smoother", codes))
    bad = path.read_text().splitlines()
    cells = bad[2].split(",")
    cells[-4] = "1.5"  # shift_group
    path.write_text("\n".join([*bad[:2], ",".join(cells)]) + "\n")
    with pytest.raises(AsBuiltError, match=r"floor_codes_smoother.csv:3: shift_group is not a whole number"):
        read_floor_code_rows(path)
    cells[-4], cells[-2] = "0", "1.5"  # corr_x_yaw
    path.write_text("\n".join([*bad[:2], ",".join(cells)]) + "\n")
    with pytest.raises(AsBuiltError, match=r"floor_codes_smoother.csv:3: corr_x_yaw is not a correlation"):
        read_floor_code_rows(path)


def test_world_yaml_placement_fields():
    w = World.from_yaml({"floor_qr": {"side_m": 0.2, "placement_sigma_m": 0.02, "placement_sigma_deg": 0}})
    p = Placement.from_world(w)
    assert p.sigma_m == 0.02 and p.sigma_rad == 0 and p.enabled
    assert World.from_yaml(w.to_yaml()) == w
    assert Placement.from_world(World()) == Placement()  # absent: 1 cm, 1 deg
    assert not Placement.from_world(World(placement_sigma_m=0.0, placement_sigma_deg=0.0)).enabled
    with pytest.raises(WorldError, match="floor_qr.placement_sigma_deg"):
        World.from_yaml({"floor_qr": {"side_m": 0.2, "placement_sigma_deg": -1}})
    with pytest.raises(WorldError, match="floor_qr.placement_sigma_m"):
        World.from_yaml({"floor_qr": {"side_m": 0.2, "placement_sigma_m": "1cm"}})


def test_simulator_places_codes_off_grid(tmp_path):
    from fusion.sim.simulate import simulate

    kw = dict(duration_s=0.2, camera_rate_hz=10, workers=1, progress=False)
    simulate(tmp_path / "a", placement_error_m=0.02, placement_error_deg=1.0, seed=3, **kw)
    floor = load_yaml(tmp_path / "a" / "world.yaml")["floor_qr"]
    assert floor["placement_sigma_m"] == 0.02 and floor["placement_sigma_deg"] == 1.0
    truth = read_groundtruth_csv(tmp_path / "a" / "floor_codes_groundtruth.csv")
    off = np.array([t[:2] - np.array([float(v) for v in cid.split("/")[1:]]) for cid, t in truth.items()])
    assert 0.01 < np.sqrt(np.mean(off**2)) < 0.03
    # another flight over the same floor: another seed, the placement seed of the first
    simulate(tmp_path / "c", placement_error_m=0.02, placement_error_deg=1.0, seed=4, placement_seed=3, **kw)
    same = read_groundtruth_csv(tmp_path / "c" / "floor_codes_groundtruth.csv")
    assert same.keys() == truth.keys() and all(np.array_equal(same[k], truth[k]) for k in truth)
    simulate(tmp_path / "d", placement_error_m=0.02, placement_error_deg=1.0, seed=3, placement_seed=4, **kw)
    other = read_groundtruth_csv(tmp_path / "d" / "floor_codes_groundtruth.csv")
    assert not any(np.array_equal(other[k], truth[k]) for k in truth)
    simulate(tmp_path / "b", **kw)  # default: exactly laid, and it says so
    floor = load_yaml(tmp_path / "b" / "world.yaml")["floor_qr"]
    assert floor["placement_sigma_m"] == 0.0 and floor["placement_sigma_deg"] == 0.0
    assert not (tmp_path / "b" / "floor_codes_groundtruth.csv").exists()


# ============================================================================ pipeline, merge, --map


@pytest.fixture(scope="module")
def sample_runs(tmp_path_factory):
    """The sample flight run (until the smoother) with placement 0 / 0, with today's code path,
    and as built (world.yaml's defaults); the detections cache is shared."""
    root = tmp_path_factory.mktemp("asbuilt")
    out = {}
    cache = None
    for name in ("zero", "default"):
        log = root / f"log_{name}"
        shutil.copytree(SAMPLE, log)
        world = load_yaml(log / "world.yaml")
        if name == "zero":
            world["floor_qr"].update(placement_sigma_m=0.0, placement_sigma_deg=0.0)
        else:  # world.yaml says nothing: the defaults, 1 cm and 1 deg
            world["floor_qr"].pop("placement_sigma_m", None)
            world["floor_qr"].pop("placement_sigma_deg", None)
        (log / "world.yaml").write_text(json.dumps(world))
        o = root / f"out_{name}"
        o.mkdir()
        if cache is not None:
            shutil.copy(cache, o / "detections.csv")
        cfg = pipeline.RunConfig(progress=False, incremental=False, workers=1, force=True)
        out[name] = pipeline.run(log, o, cfg, until="run")
        cache = o / "detections.csv"
    return out


def test_placement_zero_is_todays_smoother_exactly(sample_runs, monkeypatch, tmp_path):
    zero = sample_runs["zero"]
    assert zero.floor_codes == {}
    assert not (zero.out_dir / "floor_codes_smoother.csv").exists()
    # today's code path: the fusion stage never builds an as-built input
    monkeypatch.setattr(pipeline.floorcodes, "as_built_input", lambda *a, **k: (None, []))
    shutil.copy(zero.out_dir / "detections.csv", tmp_path / "detections.csv")
    today = pipeline.run(
        zero.log_summary["path"],
        tmp_path,
        pipeline.RunConfig(progress=False, incremental=False, workers=1, force=True),
        until="smooth",
    )
    a, b = zero.trajectories["smoother"], today.trajectories["smoother"]
    assert np.array_equal(a.T_world_body, b.T_world_body)
    assert np.array_equal(a.covariances, b.covariances)
    # and the as-built model does change the solution (the comparison can fail)
    c = sample_runs["default"].trajectories["smoother"]
    assert not np.array_equal(a.T_world_body, c.T_world_body)


def test_pipeline_writes_floor_codes(sample_runs):
    res = sample_runs["default"]
    fmap = res.floor_codes["smoother"]
    assert len(fmap.codes) >= 3 and fmap.misplaced == []  # the sample floor is laid exactly
    rows = list(csv.DictReader((res.out_dir / "floor_codes_smoother.csv").read_text().splitlines()))
    assert [r["id"] for r in rows] == [c.code_id for c in fmap.codes]
    assert all(int(r["n_obs"]) > 0 and float(r["offset_m"]) < 0.005 for r in rows)
    metrics = json.loads((res.out_dir / "metrics.json").read_text())
    assert metrics["floor_codes"]["smoother"]["n_codes"] == len(fmap.codes)
    report = (res.out_dir / "report.md").read_text()
    assert "## As-built floor codes" in report and "floor_code_offsets.png" in report
    assert (res.out_dir / "floor_code_offsets.png").stat().st_size > 1000
    assert "0 misplaced" in res.summary()
    # the health monitor compares the smoother with the fixes on the as-built codes
    assert str(res.health["smoother"].status) == "ok"


def test_a_malformed_floor_code_truth_is_the_runs_named_warning(sample_runs, tmp_path):
    """The simulator's floor_codes_groundtruth.csv that cannot be read: the run ends whole, the
    codes unscored, and says why by name with the file and line (`floor_codes_groundtruth_unreadable`):
    it was a log line only, so metrics.json just lacked the errors; a file that is not UTF-8
    was a traceback at the report."""
    log = tmp_path / "log"
    shutil.copytree(Path(sample_runs["default"].log_summary["path"]), log)
    truth = log / "floor_codes_groundtruth.csv"
    truth.write_text("id,x_m,y_m,yaw_deg\nnope,1.0,2.0,0.0\n")
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(sample_runs["default"].out_dir / "detections.csv", out / "detections.csv")
    cfg = pipeline.RunConfig(progress=False, incremental=False, workers=1, force=True)
    res = pipeline.run(log, out, cfg, until="run")
    (w,) = [x for x in res.warnings if x.name == "floor_codes_groundtruth_unreadable"]
    assert w.count == 1 and f"{truth}:2: 'nope' is not a floor code" in w.message
    metrics = json.loads((out / "metrics.json").read_text())
    assert "floor_codes_groundtruth_unreadable" in {x["name"] for x in metrics["warnings"]}
    assert "groundtruth" not in metrics["floor_codes"]["smoother"]
    assert "floor_codes_groundtruth_unreadable" in (out / "report.md").read_text()
    # not UTF-8: the same one line, not a traceback; a good file or none: no warning
    from fusion.warehouse.floorcodes import groundtruth_warning

    truth.write_bytes(b"id,x_m,y_m,yaw_deg\n\xff\xfe,1,2,0\n")
    w = groundtruth_warning(log)
    assert w is not None and str(truth) in w.message and "UTF-8" in w.message
    truth.unlink()
    assert groundtruth_warning(log) is None


def test_a_floor_code_truth_listing_a_code_twice_is_refused(tmp_path):
    """floor_codes_groundtruth.csv giving one code two true poses (its id spelled either way):
    one line naming the file and both lines, which the run gives as
    `floor_codes_groundtruth_unreadable`.  The later row silently replaced the earlier, so the
    codes were scored against whichever came last."""
    from fusion.warehouse.floorcodes import groundtruth_warning

    truth = tmp_path / "floor_codes_groundtruth.csv"
    truth.write_text("id,x_m,y_m,yaw_deg\n0/1/2,1.0,2.0,0.0\n0/3/2,3.0,2.0,0.0\n0/1.0/2,1.1,2.0,0.0\n")
    with pytest.raises(
        AsBuiltError,
        match=r"floor_codes_groundtruth.csv:4: floor code '0/1/2' listed twice \(first on line 2\)",
    ):
        read_groundtruth_csv(truth)
    w = groundtruth_warning(tmp_path)
    assert w is not None and w.name == "floor_codes_groundtruth_unreadable" and f"{truth}:4:" in w.message
    truth.write_text("id,x_m,y_m,yaw_deg\n0/1/2,1.0,2.0,0.0\n0/3/2,3.0,2.0,0.0\n")
    assert set(read_groundtruth_csv(truth)) == {"0/1/2", "0/3/2"} and groundtruth_warning(tmp_path) is None


def test_floor_code_csv_errors_name_the_line_an_editor_shows(tmp_path):
    """Blank lines in a floor-code CSV (a hand-edited truth file, a merged map) do not shift the
    line an error names: csv.DictReader skips them, and counting its rows named the bad row a
    line too early per blank line above it."""
    truth = tmp_path / "floor_codes_groundtruth.csv"
    truth.write_text("id,x_m,y_m,yaw_deg\n0/1/2,1.0,2.0,0.0\n\n\n0/3/2,oops,2.0,0.0\n")
    with pytest.raises(AsBuiltError, match=r"floor_codes_groundtruth.csv:5:"):
        read_groundtruth_csv(truth)
    rows = tmp_path / "floor_codes.csv"
    head = "id,x_m,y_m,yaw_deg,sigma_x_m,sigma_y_m,sigma_yaw_deg,n_obs\n"
    rows.write_text(head + "0/1/2,1,2,0,0.01,0.01,0.5,3\n\n0/1/2,1,2,0,0.01,0.01,0.5,3\n")
    with pytest.raises(AsBuiltError, match=r"floor_codes.csv:4: floor code '0/1/2' listed twice"):
        read_floor_code_rows(rows)


def _fake_floor_run(root: Path, world: dict, offsets: dict, sigma: float) -> Path:
    """A run folder with the files map merge reads, and floor_codes_smoother.csv."""
    root.mkdir(parents=True)
    T = np.array([make_T(np.eye(3), [x, 1.5, 1.4]) for x in np.linspace(1, 2, 5)])
    write_tum(root / "trajectory_smoother.tum", Trajectory("smoother", np.arange(5) * 10**8, T))
    write_loads_json(
        root / "loads_smoother.json",
        LoadMap("smoother", [LoadEstimate("L1", np.ones(3), np.eye(3) * 1e-4, 5)]),
    )
    (root / RUN_RECORD).write_text(
        json.dumps({"log": str(root / "log"), "world_yaml": world, "front_camera_sensor_yaml": None})
    )
    cov = np.diag([1e-8, 1e-8, math.radians(0.2) ** 2, sigma**2, sigma**2, 1e-8])
    codes = [
        FloorCodeEstimate(cid, np.array([*xy, 0.0]), make_T(np.eye(3), [xy[0] + d, xy[1], 0.0]), cov, 30)
        for cid, (xy, d) in offsets.items()
    ]
    write_floor_codes_csv(root / "floor_codes_smoother.csv", FloorCodeMap("smoother", codes))
    return root


def test_merge_fuses_floor_codes_and_run_uses_the_map(tmp_path, sample_runs):
    # world.yaml without the placement keys: codes laid to 1 cm / 1 deg
    world = load_yaml(Path(sample_runs["default"].log_summary["path"]) / "world.yaml")
    # code 0/1/2 read 2 and 3 cm off its payload's place, relative to codes laid right
    others = {cid: (tuple(map(float, cid.split("/")[1:])), 0.0) for cid in ("0/2/2", "0/1/3", "0/2/3")}
    a = _fake_floor_run(tmp_path / "a", world, {"0/1/2": ((1.0, 2.0), 0.02), **others}, 0.002)
    b = _fake_floor_run(tmp_path / "b", world, {"0/1/2": ((1.0, 2.0), 0.03), **others}, 0.004)
    merged = run_merge([a, b], tmp_path / "map")
    byid = {c.code_id: c for c in merged.floor_codes}

    # relative to the others (the floor's common shift is the priors' to fix): between the runs
    def off(cid):
        return byid[cid].xy_yaw[0] - float(cid.split("/")[1])

    rel = off("0/1/2") - np.mean([off(c) for c in others])
    assert 0.015 < rel < 0.025, rel  # the runs weigh 4 : 1 (2.2 cm), the priors pull a little to 0
    assert byid["0/1/2"].n_runs == 2 and byid["0/1/2"].cov[0, 0] < 0.01**2  # four codes fix the shift
    # a code seen alone says nothing of where it lies on the floor: the payload prior comes back
    alone = _fake_floor_run(tmp_path / "alone", world, {"0/1/2": ((1.0, 2.0), 0.02)}, 0.002)
    (c,) = floorcodes.merge_floor_codes([alone], "smoother", World.from_yaml(world))[0]
    assert c.xy_yaw[0] == pytest.approx(1.0) and c.cov[0, 0] == pytest.approx(0.01**2)
    prior = floorcodes.read_floor_map(tmp_path / "map", world)
    np.testing.assert_allclose(prior.codes["0/1/2"][0], byid["0/1/2"].xy_yaw, atol=1e-6)
    # a map of another warehouse is refused, in one line
    other = dict(world, floor_qr=dict(world["floor_qr"], side_m=0.25))
    with pytest.raises(WarehouseError, match="different warehouse.*floor_qr"):
        floorcodes.read_floor_map(tmp_path / "map", other)
    # `fusion run --map`: the sample flight's codes 0/1/2 and 0/2/2 start from the map
    log = Path(sample_runs["default"].log_summary["path"])
    shutil.copy(log / "world.yaml", tmp_path / "map" / "world.yaml")  # the same warehouse
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(sample_runs["default"].out_dir / "detections.csv", out / "detections.csv")

    def run_with_map():
        config = pipeline.RunConfig(
            progress=False, incremental=False, workers=1, floor_map=tmp_path / "map", force=True
        )
        return pipeline.run(log, out, config, until="smooth")

    res = run_with_map()
    assert any("2 of" in n and "from the map" in n for n in res.notes)
    est = res.floor_codes["smoother"].by_id()["0/1/2"]
    base = sample_runs["default"].floor_codes["smoother"].by_id()["0/1/2"]
    # pulled towards the map's +1.4 cm (sigma 5.9 mm: four codes fix its common shift)
    assert est.offset_xy_m[0] > base.offset_xy_m[0] + 0.002, (est.offset_xy_m, base.offset_xy_m)
    assert not any("independent priors" in n for n in res.notes)
    # a map written before the prior / shared columns: used, and the run says what that costs
    csv_path = tmp_path / "map" / "floor_codes_merged.csv"
    keep = ["id", "x_m", "y_m", "yaw_deg", "sigma_x_m", "sigma_y_m", "sigma_yaw_deg", "n_obs"]
    old_rows = list(csv.DictReader(csv_path.read_text().splitlines()))
    csv_path.write_text("\n".join([",".join(keep)] + [",".join(r[k] for k in keep) for r in old_rows]) + "\n")
    res = run_with_map()
    assert any("taken as independent priors" in n for n in res.notes)


def _independent_fusion(rows):
    """The merge before the shared columns: every run's estimate as independent."""
    info = sum(np.linalg.inv(r.cov) for r in rows)
    P = np.linalg.inv(info)
    return P @ sum(np.linalg.inv(r.cov) @ r.xy_yaw for r in rows), P


def _floor_offsets(seed, placement: Placement):
    """A floor's placement errors: the same for every flight over it (drawn from `seed`)."""

    def offsets(ids):
        rng = np.random.default_rng(seed)
        return np.c_[
            rng.normal(0, placement.sigma_m, (len(ids), 2)), rng.normal(0, placement.sigma_rad, len(ids))
        ]

    return offsets


def _surveys(root: Path, seeds, offsets, placement: Placement):
    """20 s flights over one floor, each solved by the batch smoother with the as-built codes and
    its floor_codes_smoother.csv written to root/<seed>: (folders, ids, true offsets)."""
    dirs = []
    for seed in seeds:
        frame_t, imu, raw, ab, ids, true = _flight(seed, 20.0, offsets, placement, True)
        res = smooth(frame_t, imu, raw, [], config=FusionConfig(), as_built=ab)
        dirs.append(root / str(seed))
        dirs[-1].mkdir(parents=True)
        write_floor_codes_csv(dirs[-1] / "floor_codes_smoother.csv", res.floor_codes)
    return dirs, ids, true


def test_map_merge_counts_the_prior_and_common_shift_once(tmp_path):
    """Eight flights over each of four floors (each floor's placement errors the same for its
    flights) merged: the 3-dof NEES against the true placement of the codes seen in three or
    more flights stays near 3.  Every flight's estimate holds the same payload prior and the
    floor's common shift, which only the priors fix; fused as independent they were counted
    once per flight (NEES 5.2 here, growing with the flights)."""
    sigma_m, sigma_deg = 0.01, 1.0
    placement = Placement(sigma_m, math.radians(sigma_deg))
    world = World(placement_sigma_m=sigma_m, placement_sigma_deg=sigma_deg)
    merged_z2, independent_z2 = [], []
    for floor in range(4):
        offsets = _floor_offsets([floor, 7], placement)
        dirs, ids, true = _surveys(
            tmp_path / str(floor), [100 * floor + f for f in range(8)], offsets, placement
        )
        truth = {cid: np.array([*map(float, cid.split("/")[1:]), 0.0]) + o for cid, o in zip(ids, true)}
        rows: dict[str, list] = {}
        for d in dirs:
            for cid, r in read_floor_code_rows(d / "floor_codes_smoother.csv").items():
                assert r.prior_cov is not None and r.shared_cov is not None
                rows.setdefault(cid, []).append(r)

        def z2(cid, x, P):
            e = x - truth[cid]
            e[2] = math.remainder(e[2], 2 * math.pi)
            return float(e @ np.linalg.solve(P, e))

        codes, _ = floorcodes.merge_floor_codes(dirs, "smoother", world)
        for c in codes:
            if c.n_runs >= 3 and c.n_obs >= 10:
                merged_z2.append(z2(c.code_id, c.xy_yaw, c.cov))
                independent_z2.append(z2(c.code_id, *_independent_fusion(rows[c.code_id])))
        # one flight's file merged alone is that flight's estimate, to first order
        alone = floorcodes.merge_floor_codes(dirs[:1], "smoother", world)[0]
        for c in alone:
            r = rows[c.code_id][0]
            sig = np.sqrt(np.diag(r.cov))
            assert np.all(np.abs(c.xy_yaw - r.xy_yaw) < 0.2 * sig), (c.xy_yaw - r.xy_yaw) / sig
            assert np.all(np.abs(np.sqrt(np.diag(c.cov)) / sig - 1) < 0.2), np.sqrt(np.diag(c.cov)) / sig
    assert len(merged_z2) > 30
    assert 2.0 < np.mean(merged_z2) < 4.2, np.mean(merged_z2)  # 3.3
    assert np.mean(independent_z2) > 4.6, np.mean(independent_z2)  # 5.2: the test can fail


def test_a_flight_over_a_merged_map_takes_its_common_shift_once(tmp_path, monkeypatch):
    """Four flights of a floor merged into a map; a fifth flight solved with the map as its
    codes' prior.  The map's codes share its common shift (only world.yaml's priors fix it):
    taken as independent priors, the fifth flight's codes were surer than they are (3-dof NEES
    12.4 on six floors; a rendered fifth flight's smoother read pose NEES 62); with the shift as
    one variable D, 4.1.
    The approximate marginals (beyond EXACT_MARGINALS_MAX_CODES) give the map's codes their
    share of D too: x, y, yaw sigma 0.89-1.19 of the exact ones."""
    sigma_m, sigma_deg = 0.01, 1.0
    placement = Placement(sigma_m, math.radians(sigma_deg))
    world = World(placement_sigma_m=sigma_m, placement_sigma_deg=sigma_deg)
    z2: dict[bool, list[float]] = {True: [], False: []}
    ratio = []  # the approximate marginals' sigma over the exact ones, with the map's shift
    for floor in range(6):
        offsets = _floor_offsets([floor, 11], placement)
        dirs, _, _ = _surveys(
            tmp_path / str(floor), [1000 + 10 * floor + f for f in range(4)], offsets, placement
        )
        map_dir = tmp_path / f"map{floor}"
        map_dir.mkdir()
        floorcodes.write_merged_floor_codes(
            map_dir, floorcodes.merge_floor_codes(dirs, "smoother", world)[0], 1.0
        )
        world.save(map_dir / "world.yaml")
        prior = floorcodes.read_floor_map(map_dir, world.to_yaml())
        assert prior.shift is not None and len(prior.shared) == len(prior.codes)
        frame_t, imu, raw, ab, ids, true = _flight(1000 + 10 * floor + 9, 20.0, offsets, placement, True)
        truth = {cid: np.array([*map(float, cid.split("/")[1:]), 0.0]) + o for cid, o in zip(ids, true)}
        for once in (True, False):
            used = prior if once else replace(prior, shift=None)
            codes, shift_cov, n_map = apply_prior_map(ab.codes, used)
            assert n_map > 5 and (shift_cov is not None) == once
            with_map = replace(ab, codes=codes, shift_cov=shift_cov)
            res = smooth(frame_t, imu, raw, [], config=FusionConfig(), as_built=with_map)
            for c in res.floor_codes.codes:
                if c.n_obs >= 10 and c.code_id in prior.codes:
                    e = np.r_[c.p_world[:2], c.yaw_rad] - truth[c.code_id]
                    z2[once].append(float(e @ np.linalg.solve(c.cov_xy_yaw, e)))
            if once and floor < 2:  # beyond EXACT_MARGINALS_MAX_CODES: the approximate marginals
                monkeypatch.setattr(asbuilt, "EXACT_MARGINALS_MAX_CODES", 1)
                approx = smooth(frame_t, imu, raw, [], config=FusionConfig(), as_built=with_map)
                monkeypatch.undo()
                exact = res.floor_codes.by_id()
                for c in approx.floor_codes.codes:
                    if c.n_obs >= 10 and c.code_id in prior.codes:
                        ratio.append(np.sqrt(np.diag(c.cov_xy_yaw) / np.diag(exact[c.code_id].cov_xy_yaw)))
    assert len(ratio) > 10 and 0.8 < np.min(ratio) and np.max(ratio) < 1.25, np.array(ratio)  # 0.89-1.19
    assert len(z2[True]) > 30
    assert 1.5 < np.mean(z2[True]) < 5.5, np.mean(z2[True])  # 4.1
    assert np.mean(z2[False]) > 2 * np.mean(z2[True]), (np.mean(z2[False]), np.mean(z2[True]))  # 12.4


def _window_posterior(m, t, q, r, rng):
    """A window's posterior of its codes (C, 3) x, y, yaw: each code seen with noise r
    relative to a free planar rigid motion of them all (the drone sees codes only relative to
    itself), and each code's payload prior N(m, q).  Returns x (C, 3), the marginals' variances
    (C, 3)."""
    n = len(m)
    J = shift_jacobians(m[:, :2])
    y = t + np.einsum("cij,j->ci", J, rng.normal(0, 0.05, 3)) + rng.normal(0, np.sqrt(r), (n, 3))
    A = np.zeros((3 * n, 3 * n + 3))
    A[:, : 3 * n] = np.eye(3 * n)
    A[:, 3 * n :] = J.reshape(3 * n, 3)
    H = A.T @ np.diag(np.tile(1 / r, n)) @ A
    H[: 3 * n, : 3 * n] += np.diag(np.tile(1 / q, n))
    b = A.T @ (np.tile(1 / r, n) * y.ravel())
    b[: 3 * n] += (m / q).ravel()
    P = np.linalg.inv(H)
    return (P @ b)[: 3 * n].reshape(n, 3), np.diag(P)[: 3 * n].reshape(n, 3)


def test_map_merge_gives_each_window_its_own_shift(tmp_path):
    """A long flight's floor codes come from its windows, each of which fixed its own common
    shift from the priors of the codes it saw (merge_window_maps): merged with one shift for
    the whole flight, the windows' shifts were taken as one and the merged codes read a NEES of
    4.4 where the truth asks 3 (25 floors, two flights of two windows each: linear-Gaussian
    posteriors, written as `fusion run` writes them); one shift per window (the file's
    shift_group) gives 3.2."""
    rng = np.random.default_rng(3)
    world = World(placement_sigma_m=0.01, placement_sigma_deg=1.0)
    q = np.array([0.01**2, 0.01**2, math.radians(1.0) ** 2])
    r = np.array([0.002**2, 0.002**2, math.radians(0.1) ** 2])
    ids = [floor_payload(x, 0) for x in range(12)]
    m = np.c_[np.arange(12.0), np.zeros(12), np.zeros(12)]
    windows = [np.arange(0, 8), np.arange(4, 12)]  # each code from one: 0-5 the first, 6-11 the second
    cols = ["id", "x_m", "y_m", "yaw_deg", "sigma_x_m", "sigma_y_m", "sigma_yaw_deg", "n_obs"]
    cols += ["shared_sigma_x_m", "shared_sigma_y_m", "shared_sigma_yaw_deg", "shift_group"]
    z2: dict[bool, list[float]] = {True: [], False: []}
    for floor in range(25):
        t = m + rng.normal(0, np.sqrt(q), m.shape)
        runs: dict[bool, list[Path]] = {True: [], False: []}
        for run in range(2):
            rows = []
            for w, idx in enumerate(windows):
                x, p = _window_posterior(m[idx], t[idx], q, r, rng)
                g = np.diagonal(common_shift_covs(m[idx, :2], np.array([np.diag(q)] * len(idx))), 0, 1, 2)
                keep = idx < 6 if w == 0 else idx >= 6
                for c, xc, pc, gc in zip(idx[keep], x[keep], p[keep], g[keep]):
                    sig = np.sqrt(np.r_[pc, gc])
                    sig[[2, 5]] = np.degrees(sig[[2, 5]])
                    rows.append([ids[c], xc[0], xc[1], math.degrees(xc[2]), *sig[:3], 50, *sig[3:], w])
            for grouped in (True, False):
                d = tmp_path / f"{floor}-{run}-{grouped}"
                d.mkdir()
                with open(d / "floor_codes_smoother.csv", "w", newline="") as f:
                    csv.writer(f).writerows([cols] + [row[:-1] + [row[-1] if grouped else 0] for row in rows])
                runs[grouped].append(d)
        for grouped in (True, False):
            for c in floorcodes.merge_floor_codes(runs[grouped], "smoother", world)[0]:
                e = c.xy_yaw - t[ids.index(c.code_id)]
                z2[grouped].append(float(e @ np.linalg.solve(c.cov, e)))
    assert 2.5 < np.mean(z2[True]) < 3.6
    assert np.mean(z2[False]) > 4.0  # one shift per flight: the windows' shifts taken as one


def test_report_html_highlights_misplaced_codes():
    from fusion.warehouse.view3d import build_figure

    fig = build_figure(
        {},
        None,
        np.array([[1.0, 2.0], [2.0, 2.0]]),
        misplaced_codes=[("0/1/2<b>", np.array([1.03, 2.0, 0.0]), "offset 3.0 cm (4.1 sigma), 25 sightings")],
    )
    traces = [t for t in fig.data if t.name == "misplaced floor codes"]
    assert len(traces) == 1 and traces[0].x[0] == pytest.approx(1.03)
    assert "<b>" not in traces[0].hovertext[0] and "&lt;b&gt;" in traces[0].hovertext[0]
    assert not [t for t in build_figure({}, None, np.zeros((1, 2))).data if t.name == "misplaced floor codes"]
