"""`fusion map merge`: information-weighted fusion, the changes between flights (moved, appeared,
disappeared vs. not surveyed), refusal of different warehouses, escaped ids; on synthetic run
folders written in the formats `fusion run` writes."""

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from fusion.errors import WarehouseError
from fusion.fileio import load_yaml
from fusion.geometry import make_T, rot_z
from fusion.log.files import write_loads_json, write_tum
from fusion.types import LoadEstimate, LoadMap, Trajectory
from fusion.warehouse.inventory import view_cone
from fusion.warehouse.merge import ChangeKind, merge_runs
from fusion.warehouse.runs import RUN_RECORD, load_run
from fusion.world import warehouse_differences

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
WORLD = load_yaml(SAMPLE / "world.yaml")
FRONT = load_yaml(SAMPLE / "mav0" / "cam1" / "sensor.yaml")
COV = np.diag([0.002, 0.003, 0.002]) ** 2


def _fake_run(
    root: Path,
    loads: dict,
    world: dict = WORLD,
    x_range=(1.5, 1.5),
    shared=None,
    y: float = 1.5,
    sightings: bool = False,
    log: str | None = None,
) -> Path:
    """A run folder: the smoother's trajectory (hovering at y, z = 1.4 over x_range, facing +y
    from y < 2.7, -y from beyond), its load map {id: p} with covariance COV (plus `shared`, its
    part every flight shares, when given), run.json and, with `sightings`, the raw sightings of
    every load at every pose (load_observations_pnp.csv)."""
    root.mkdir(parents=True)
    xs = np.linspace(*x_range, 20)
    yaw = math.pi / 2 if y < 2.7 else -math.pi / 2
    T = np.array([make_T(rot_z(yaw), [x, y, 1.4]) for x in xs])
    stamps = np.arange(20, dtype=np.int64) * 100_000_000
    write_tum(root / "trajectory_smoother.tum", Trajectory("smoother", stamps, T))
    if sightings:
        rows = [f"{t},{k},{v[0]},{v[1]},{v[2]},0.01,0.01,0.01" for k, v in loads.items() for t in stamps]
        (root / "load_observations_pnp.csv").write_text(
            "timestamp_ns,id,x_m,y_m,z_m,sigma_x_m,sigma_y_m,sigma_z_m\n" + "\n".join(rows) + "\n"
        )
    write_loads_json(
        root / "loads_smoother.json",
        LoadMap(
            "smoother",
            [
                LoadEstimate(k, np.asarray(v, float), COV if shared is None else COV + shared, 10, shared)
                for k, v in loads.items()
            ],
        ),
    )
    (root / RUN_RECORD).write_text(
        json.dumps({"log": log or str(root / "log"), "world_yaml": world, "front_camera_sensor_yaml": FRONT})
    )
    return root


def test_merge_fuses_and_lists_changes(tmp_path):
    rng = np.random.default_rng(5)
    a = np.array([1.5, 2.7, 1.4])  # in view of every flight
    b = np.array([1.3, 2.7, 1.4])  # in view; moves 5 cm in flight 1
    far = np.array([5.5, 4.3, 0.7])  # never in view after flight 0
    a1 = a + 0.002 * rng.normal(size=3)
    r0 = _fake_run(tmp_path / "r0", {"A": a, "B": b, "FAR": far})
    r1 = _fake_run(tmp_path / "r1", {"A": a1, "B": b + [0.05, 0, 0], "NEW": [1.7, 2.7, 1.4]})
    r2 = _fake_run(tmp_path / "r2", {"B": b + [0.05, 0, 0], "NEW": [1.7, 2.7, 1.4]})
    res = merge_runs([load_run(r) for r in (r0, r1, r2)])
    changes = {(c.load_id, c.kind, c.run_index) for c in res.changes}
    assert changes == {
        ("B", ChangeKind.MOVED, 1),
        ("NEW", ChangeKind.APPEARED, 1),
        ("A", ChangeKind.DISAPPEARED, 2),
    }
    merged = {l.load_id: l for l in res.loads}
    assert set(merged) == {"B", "FAR", "NEW"}  # FAR kept: never in view again
    np.testing.assert_allclose(merged["B"].p_world, b + [0.05, 0, 0])  # fused since the move
    assert merged["B"].n_runs == 2 and merged["FAR"].n_runs == 1
    np.testing.assert_allclose(merged["B"].cov_world, COV / 2)  # two equal informations
    moved = next(c for c in res.changes if c.kind == ChangeKind.MOVED)
    assert moved.distance_m == pytest.approx(0.05) and moved.p_value < 1e-6


def test_information_weighted_mean():
    """Two estimates with different covariances: P = (P1^-1 + P2^-1)^-1, p = P (P1^-1 p1 + ...)."""
    from fusion.warehouse.merge import _fuse

    rng = np.random.default_rng(1)
    P1, P2 = np.diag([1e-4, 4e-4, 1e-4]), np.diag([4e-4, 1e-4, 1e-4])
    p1, p2 = rng.normal(size=3) * 0.01, rng.normal(size=3) * 0.01
    p, P, S = _fuse(p1, P1, None, p2, P2, None)
    assert S is None
    np.testing.assert_allclose(P, np.diag([0.8e-4, 0.8e-4, 0.5e-4]))
    np.testing.assert_allclose(p, [(4 * p1[0] + p2[0]) / 5, (p1[1] + 4 * p2[1]) / 5, (p1[2] + p2[2]) / 2])


def test_merge_needs_the_labels_face_in_view_to_call_it_gone(tmp_path):
    """A load read from one side of its rack is not 'disappeared' when a later flight passes
    behind the rack (the label faces away, the rack is between), however close; it is when a
    later flight passes on its side without reading it."""
    a = np.array([1.5, 2.7, 1.4])
    r0 = _fake_run(tmp_path / "r0", {"A": a}, y=1.5, sightings=True)  # read from -y
    behind = _fake_run(tmp_path / "behind", {}, y=3.9, sightings=True)  # 1.2 m away, the rack's back
    res = merge_runs([load_run(r) for r in (r0, behind)])
    assert res.changes == [] and [l.load_id for l in res.loads] == ["A"]
    front = _fake_run(tmp_path / "front", {}, y=1.5, sightings=True)
    res = merge_runs([load_run(r) for r in (r0, behind, front)])
    assert [(c.load_id, c.kind, c.run_index) for c in res.changes] == [("A", ChangeKind.DISAPPEARED, 2)]
    # without the sightings' stamps the face is unknown: the flight behind the rack calls it gone
    res = merge_runs([load_run(_fake_run(tmp_path / "r0x", {"A": a})), load_run(behind)])
    assert [(c.load_id, c.kind) for c in res.changes] == [("A", ChangeKind.DISAPPEARED)]
    assert any("judged in view from any side" in n for n in res.notes)


def test_view_cone():
    d = np.array([[0.0, -1.0, 0.0], [0.5, -0.5, 0.0], [-0.5, -0.5, 0.0]])
    d /= np.linalg.norm(d, axis=1)[:, None]
    axis, cos_min = view_cone(d)
    np.testing.assert_allclose(axis, [0, -1, 0], atol=1e-12)
    assert cos_min == pytest.approx(math.cos(math.radians(45)))
    assert view_cone(np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])) is None  # both sides of a rack
    assert view_cone(np.zeros((0, 3))) is None


def test_merge_no_false_moves_on_repeated_flights(tmp_path):
    """Ten flights re-mapping the same loads with errors drawn from their covariance."""
    rng = np.random.default_rng(8)
    truth = {f"L{i}": np.array([1.0 + 0.1 * i, 2.7, 1.4]) for i in range(8)}
    runs = [
        _fake_run(
            tmp_path / f"r{k}",
            {i: p + np.linalg.cholesky(COV) @ rng.normal(size=3) for i, p in truth.items()},
        )
        for k in range(10)
    ]
    res = merge_runs([load_run(r) for r in runs])
    assert res.changes == []
    for l in res.loads:
        assert l.n_runs == 10
        d = l.p_world - truth[l.load_id]
        assert d @ np.linalg.solve(l.cov_world, d) < 16.3  # chi2(3) at 0.999


def test_merge_refuses_other_warehouse_one_line(tmp_path, capsys):
    other = dict(WORLD, floor_qr={"side_m": 0.25, "payload_unit_m": 0.5})
    r0 = _fake_run(tmp_path / "r0", {"A": [1.5, 2.7, 1.4]})
    r1 = _fake_run(tmp_path / "r1", {"A": [1.5, 2.7, 1.4]}, world=other)
    with pytest.raises(WarehouseError, match="different warehouse.*floor_qr"):
        merge_runs([load_run(r0), load_run(r1)])
    assert main(["map", "merge", str(r0), str(r1), "--out", str(tmp_path / "m"), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "refusing to merge" in err
    assert not (tmp_path / "m").exists()


def test_merge_takes_runs_stating_other_sigmas_as_one_warehouse(tmp_path):
    """A flight whose world.yaml states the labels' print sigma and one that does not (an older
    log, or another operator) fly the same warehouse: merged, with a note; a different label
    side still refuses."""
    assert "side_sigma_m" in WORLD["load_qr"]
    unstated = dict(WORLD, load_qr={"side_m": WORLD["load_qr"]["side_m"]})
    assert warehouse_differences(WORLD, unstated) == ([], ["load_qr.side_sigma_m"])
    r0 = _fake_run(tmp_path / "r0", {"A": [1.5, 2.7, 1.4]})
    r1 = _fake_run(tmp_path / "r1", {"A": [1.5, 2.7, 1.4]}, world=unstated)
    res = merge_runs([load_run(r0), load_run(r1)])
    assert res.world_yaml == WORLD and res.loads[0].n_runs == 2
    assert any("load_qr.side_sigma_m" in n for n in res.notes)
    bigger = dict(unstated, load_qr={"side_m": 0.2})
    r2 = _fake_run(tmp_path / "r2", {"A": [1.5, 2.7, 1.4]}, world=bigger)
    with pytest.raises(WarehouseError, match=r"differs in load_qr\.side_m\)"):
        merge_runs([load_run(r0), load_run(r2)])


def test_cli_merge_writes_map_with_escaped_ids(tmp_path, capsys):
    r0 = _fake_run(tmp_path / "r0", {"=cmd|' /C calc'!A0": [1.5, 2.7, 1.4], "B|x": [1.3, 2.7, 1.4]})
    r1 = _fake_run(tmp_path / "r1", {"=cmd|' /C calc'!A0": [1.5, 2.7, 1.4], "B|x": [1.3, 2.7, 1.5]})
    out = tmp_path / "map"
    assert main(["map", "merge", str(r0), str(r1), "--out", str(out), "-q"]) == 0
    assert "1 moved" in capsys.readouterr().out
    with open(out / "loads_merged.csv", encoding="utf-8") as f:
        ids = [r["id"] for r in csv.DictReader(f)]
    assert ids == ["'=cmd|' /C calc'!A0", "B|x"]
    with open(out / "changes.csv", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert [(r["id"], r["change"]) for r in rows] == [("B|x", "moved")]
    assert "B\\|x" in (out / "changes.md").read_text(encoding="utf-8")
    data = json.loads((out / "map.json").read_text(encoding="utf-8"))
    assert len(data["loads"]) == 2 and load_yaml(out / "world.yaml") == WORLD
    assert main(["map", "merge", str(r0), "--out", str(out), "-q"]) == 1  # exists, no --force


def test_merge_does_not_average_down_what_flights_share(tmp_path):
    """Ten flights of the same labels and camera: each label's print / mount error is the same in
    every flight (S), the rest independent (COV).  Fused as if all independent, the merged maps
    are overconfident; with the shared part kept, their NEES is ~3."""
    rng = np.random.default_rng(3)
    S = np.diag([0.004, 0.006, 0.004]) ** 2
    nees_kept, nees_ignored = [], []
    for trial in range(6):
        truth = {f"L{i}": np.array([1.0 + 0.1 * i, 2.7, 1.4]) for i in range(8)}
        common = {i: np.linalg.cholesky(S) @ rng.normal(size=3) for i in truth}
        flights = [
            {i: p + common[i] + np.linalg.cholesky(COV) @ rng.normal(size=3) for i, p in truth.items()}
            for _ in range(10)
        ]
        for shared, out in ((S, nees_kept), (None, nees_ignored)):
            runs = []
            for k, loads in enumerate(flights):
                root = tmp_path / f"t{trial}-{shared is None}-{k}"
                if shared is None:  # the same covariance, but nothing marked shared
                    root.mkdir(parents=True)
                    _fake_run(root / "r", loads, shared=None)
                    js = root / "r" / "loads_smoother.json"
                    data = json.loads(js.read_text())
                    for l in data["loads"]:
                        l["cov_world_m2"] = (COV + S).tolist()
                    js.write_text(json.dumps(data))
                    runs.append(load_run(root / "r"))
                else:
                    runs.append(load_run(_fake_run(root, loads, shared=S)))
            res = merge_runs(runs)
            assert res.changes == []
            for l in res.loads:
                d = l.p_world - truth[l.load_id]
                out.append(d @ np.linalg.solve(l.cov_world, d))
            if shared is not None:
                np.testing.assert_allclose(res.loads[0].cov_shared, S)
                np.testing.assert_allclose(res.loads[0].cov_world, COV / 10 + S)
    assert 1.5 < np.mean(nees_kept) < 5.0  # 48 loads, chi2(3)
    assert np.mean(nees_ignored) > 8.0


def test_merge_refuses_one_flight_twice(tmp_path, capsys):
    """The same run twice, two runs of one log, or a copied run: its sightings would count twice
    (thirty-first session's audit: n_obs doubled, every sigma / sqrt(2))."""
    loads = {"A": [1.5, 2.7, 1.4], "B": [2.0, 2.7, 1.3]}
    r0 = _fake_run(tmp_path / "r0", loads, sightings=True)
    with pytest.raises(WarehouseError, match="same flight log as .*r0"):
        merge_runs([load_run(r0), load_run(r0)])
    r1 = _fake_run(tmp_path / "r1", loads, sightings=True, log=str(tmp_path / "r0" / "log"))
    with pytest.raises(WarehouseError, match="same flight log"):
        merge_runs([load_run(r0), load_run(r1)])
    copy = tmp_path / "copy"
    shutil.copytree(r0, copy)
    record = json.loads((copy / RUN_RECORD).read_text())
    (copy / RUN_RECORD).write_text(json.dumps(dict(record, log=str(tmp_path / "elsewhere"))))
    with pytest.raises(WarehouseError, match="same load sightings as .*r0"):
        merge_runs([load_run(r0), load_run(copy)])
    assert main(["map", "merge", str(r0), str(copy), "--out", str(tmp_path / "m"), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "count them twice" in err and not (tmp_path / "m").exists()
    # another flight of the same loads (other positions, other log) is merged
    other = _fake_run(tmp_path / "r2", {k: np.add(v, 0.001) for k, v in loads.items()}, sightings=True)
    assert merge_runs([load_run(r0), load_run(other)]).loads[0].n_runs == 2
