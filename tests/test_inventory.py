"""`fusion inventory`: manifest parsing and its bad input, the moved test's statistics, the
field-of-view test, ambiguous ids, escaping, and the command end to end on the sample flight."""

import csv
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from fusion.errors import WarehouseError
from fusion.geometry import make_T, rot_z
from fusion.sim.scenarios import make_cameras
from fusion.types import Trajectory
from fusion.warehouse import escape
from fusion.warehouse.inventory import (
    MIN_READABLE_SIDE_PX,
    MOVED_ALPHA,
    Status,
    ambiguous_places,
    face_cone,
    moved_test,
    run_inventory,
    sighting_directions,
    visibility,
)
from fusion.warehouse.manifest import DEFAULT_TOLERANCE_M, read_manifest
from fusion.warehouse.runs import read_observation_rows

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


# ----------------------------------------------------------------------------- manifest


def test_a_spreadsheets_empty_trailing_cells_are_no_extra_column(tmp_path):
    (e,) = read_manifest(_write(tmp_path / "m.csv", "id,x_m,y_m,z_m\nA,1,2,3,,\n"))
    assert e.load_id == "A" and e.p_world.tolist() == [1.0, 2.0, 3.0]


def test_plain_manifest_with_and_without_tolerance(tmp_path):
    m = read_manifest(_write(tmp_path / "m.csv", "id,x_m,y_m,z_m,tolerance_m\nA,1,2,3,0.05\nB, 4 ,5,6,\n"))
    assert [e.load_id for e in m] == ["A", "B"]
    np.testing.assert_allclose(m[1].p_world, [4, 5, 6])
    assert m[0].tolerance_m == 0.05 and m[1].tolerance_m == DEFAULT_TOLERANCE_M
    assert m[0].line == 2 and m[1].line == 3


def test_wms_export_units_converted(tmp_path):
    m = read_manifest(
        _write(
            tmp_path / "wms.csv",
            "\ufeffLocation;Pallet_ID;X;Y;Z;Unit;Tolerance\n"
            "A-01-01;PAL-1;1500;2700;700;mm;20\n"
            "A-01-02;PAL-2;150;270;140;CM;\n"
            "A-01-03;PAL-3;1.5;2.7;2.1;m;0.01\n",
        )
    )
    np.testing.assert_allclose([e.p_world for e in m], [[1.5, 2.7, 0.7], [1.5, 2.7, 1.4], [1.5, 2.7, 2.1]])
    assert [e.location for e in m] == ["A-01-01", "A-01-02", "A-01-03"]
    assert m[0].tolerance_m == pytest.approx(0.02) and m[1].tolerance_m == DEFAULT_TOLERANCE_M


def test_manifest_face_yaw_optional_in_both_layouts(tmp_path):
    m = read_manifest(_write(tmp_path / "m.csv", "id,x_m,y_m,z_m,face_yaw_deg\nA,1,2,3,-90\nB,4,5,6,\n"))
    assert m[0].face_yaw_rad == pytest.approx(-math.pi / 2) and m[1].face_yaw_rad is None
    w = read_manifest(
        _write(tmp_path / "w.csv", "location,pallet_id,x,y,z,unit,face_yaw_deg\nL1,P1,1500,2700,700,mm,90\n")
    )
    assert w[0].face_yaw_rad == pytest.approx(math.pi / 2)
    assert read_manifest(_write(tmp_path / "n.csv", "id,x_m,y_m,z_m\nA,1,2,3\n"))[0].face_yaw_rad is None


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("id,x_m,y_m,z_m\nA,1,2,3\nB,1,2,3\nA,4,5,6\n", 4, "duplicate id 'A' (first on line 2)"),
        ("id,x_m,z_m\nA,1,2\n", 1, "missing column(s) y_m"),
        ("id,x_m,y_m,z_m\nA,1,two,3\n", 2, "column y_m: 'two' is not a number"),
        ("id,x_m,y_m,z_m\nA,1,2,nan\n", 2, "not finite"),
        ("id,x_m,y_m,z_m\nA,1,2\n", 2, "expected 4 fields, found 3"),
        ("id,x_m,y_m,z_m\n,1,2,3\n", 2, "empty id"),
        ("id,x_m,y_m,z_m,tolerance_m\nA,1,2,3,-1\n", 2, "negative tolerance"),
        ("location,pallet_id,x,y,z,unit\nL1,P1,1,2,3,m\nL2,P2,1,2,3,in\n", 3, "unit: 'in' is not one of"),
        ("location,pallet_id,x,y,z\nL1,P1,1,2,3\n", 1, "missing column(s) unit"),
        ("id,x_m,y_m,z_m,face_yaw_deg\nA,1,2,3,south\n", 2, "column face_yaw_deg: 'south' is not a number"),
        ("id,x_m,y_m,z_m\nA,1,2,3\nB,1,2,3,0.05\n", 3, "5 fields, the header names 4"),
    ],
)
def test_bad_manifest_one_line_error_naming_line(tmp_path, text, line, words):
    path = _write(tmp_path / "bad.csv", text)
    with pytest.raises(WarehouseError) as e:
        read_manifest(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}:{line}: ") and words in msg and "\n" not in msg


def test_cli_bad_manifest_one_line_exit_1(tmp_path, capsys):
    path = _write(tmp_path / "bad.csv", "id,x_m,y_m,z_m\nA,1,2,3\nA,1,2,3\n")
    assert main(["inventory", str(tmp_path), "--expected", str(path), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{path}:3: duplicate id" in err


# ----------------------------------------------------------------------------- statistics


def _random_cov(rng, sigma_m):
    A = rng.normal(size=(3, 3))
    Q, _ = np.linalg.qr(A)
    return Q @ np.diag((sigma_m * rng.uniform(0.3, 1.0, 3)) ** 2) @ Q.T


def test_moved_test_false_alarm_rate_and_5cm_power():
    """Seeded Monte Carlo: offsets drawn from the test's own covariance fail at about alpha; a
    5 cm displacement (map sigma up to 3 mm, default tolerance) fails at >= 95 %."""
    rng = np.random.default_rng(12)
    n = 3000
    false = detected = 0
    for _ in range(n):
        cov = _random_cov(rng, 0.003)
        S = cov + DEFAULT_TOLERANCE_M**2 * np.eye(3)
        err = np.linalg.cholesky(S) @ rng.normal(size=3)
        false += moved_test(err, cov, np.zeros(3), DEFAULT_TOLERANCE_M)[3] < MOVED_ALPHA
        u = rng.normal(size=3)
        move = 0.05 * u / np.linalg.norm(u)
        map_err = np.linalg.cholesky(cov) @ rng.normal(size=3)
        detected += moved_test(move + map_err, cov, np.zeros(3), DEFAULT_TOLERANCE_M)[3] < MOVED_ALPHA
    assert false / n < 3 * MOVED_ALPHA
    assert detected / n >= 0.95


def test_moved_test_reports_distance_and_sigma_along_it():
    cov = np.diag([0.01**2, 0.02**2, 0.03**2])
    dist, sigma, stat, p = moved_test(np.array([0.0, 0.1, 0.0]), cov, np.zeros(3), 0.0)
    assert dist == pytest.approx(0.1) and sigma == pytest.approx(0.02)
    assert stat == pytest.approx(25.0) and p < MOVED_ALPHA


def _hover_trajectory(x0, x1, n=30, y=1.5, z=1.4, yaw=math.pi / 2):
    xs = np.linspace(x0, x1, n)
    T = np.array([make_T(rot_z(yaw), [x, y, z]) for x in xs])
    return Trajectory("smoother", np.arange(n, dtype=np.int64) * 100_000_000, T)


def test_visibility_field_of_view_and_readable_range():
    camera = make_cameras()["cam1"]  # front camera, f = 550 px, 640x480
    traj = _hover_trajectory(1.5, 1.5)  # hovering 1.2 m in front of the P face
    pts = np.array(
        [
            [1.5, 2.7, 1.4],  # straight ahead: in view, 69 px
            [1.5, 0.5, 1.4],  # behind the drone
            [1.5, 2.7, 0.7],  # below the vertical field of view
            [1.5, 4.5, 1.4],  # ahead but 3 m away: 27 px
            [3.0, 2.7, 1.4],
        ]
    )  # 51 deg to the side: outside 60 deg FOV
    n, side = visibility(pts, traj, camera, 0.15)
    assert n.tolist() == [30, 0, 0, 0, 0]
    assert side[0] == pytest.approx(camera.fu * 0.15 / (1.2 - 0.12), rel=1e-3)
    assert side[3] < MIN_READABLE_SIDE_PX < side[0]


def test_visibility_from_in_front_of_the_label_only():
    """A label on the rack's -y face (facing -y), 1.2 m from a drone in the next aisle (y = 3.9)
    looking at the rack's back: in the image at readable range, so 'in view' without its face;
    with it (face_cone), not; the drone in front of it (y = 1.5) sees it either way."""
    camera = make_cameras()["cam1"]
    p = np.array([[1.5, 2.7, 1.4]])
    behind = _hover_trajectory(1.5, 1.5, y=3.9, yaw=-math.pi / 2)
    front = _hover_trajectory(1.5, 1.5)
    assert visibility(p, behind, camera, 0.15)[0].tolist() == [30]
    assert visibility(p, behind, camera, 0.15, [face_cone(-math.pi / 2)])[0].tolist() == [0]
    assert visibility(p, front, camera, 0.15, [face_cone(-math.pi / 2)])[0].tolist() == [30]
    assert visibility(p, behind, camera, 0.15, [face_cone(None)])[0].tolist() == [30]


def test_ambiguous_places_two_clusters_not_one_outlier():
    rng = np.random.default_rng(3)
    a = np.array([1.5, 2.7, 1.4]) + 0.01 * rng.normal(size=(20, 3))
    b = np.array([5.5, 2.7, 0.7]) + 0.01 * rng.normal(size=(8, 3))
    places = ambiguous_places(np.vstack([a, b]))
    assert len(places) == 2
    np.testing.assert_allclose(places[0], [1.5, 2.7, 1.4], atol=0.02)
    assert len(ambiguous_places(np.vstack([a, b[:1]]))) == 1


def test_escape_csv_and_markdown():
    for bad in ("=1+1", "+1", "-1", "@SUM(A1)", "\tx", "\rx"):
        assert escape.csv_cell(bad) == "'" + bad
    assert escape.csv_cell("P-01-1") == "P-01-1"
    md = escape.markdown("a|b [x](javascript:alert(1)) <img src=x>")
    assert "|" not in md.replace("\\|", "") and "<" not in md and "](" not in md


# ----------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("inv") / "out"
    assert main(["run", str(SAMPLE), "--out", str(out), "--quiet", "--workers", "1", "--no-incremental"]) == 0
    return out


def _truth():
    with open(SAMPLE / "loads_groundtruth.csv", encoding="utf-8") as f:
        return {r["id"]: [float(r[k]) for k in ("x_m", "y_m", "z_m")] for r in csv.DictReader(f)}


def _manifest(path: Path, loads: dict) -> Path:
    with open(path, "w", encoding="utf-8", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "x_m", "y_m", "z_m"])
        for k, v in loads.items():
            w.writerow([k, *v])
    return path


def test_run_writes_report_html_and_record(sample_run):
    assert (sample_run / "report.html").stat().st_size > 1_000_000  # plotly.js embedded
    assert "](report.html)" in (sample_run / "report.md").read_text(encoding="utf-8")
    assert (sample_run / "run.json").exists()


def test_inventory_sample_flight_statuses(sample_run, tmp_path):
    """The sample flight (5 s hovering in front of P-01-2 and P-02-2): those two present, a
    phantom entry between them on the flown face missing, the rest of the warehouse not
    surveyed, an entry moved by 5 cm moved, one omitted from the manifest unexpected, and a
    formula-like id neutralised in inventory.csv and escaped in the report."""
    truth = _truth()
    loads = {k: v for k, v in truth.items() if k != "P-01-2"}
    loads["P-02-2"] = [truth["P-02-2"][0] + 0.05, *truth["P-02-2"][1:]]
    loads["PHANTOM"] = [2.5, 2.7, 1.4]
    loads["=HYPERLINK(1)|x"] = [2.6, 2.7, 1.4]
    res = run_inventory(sample_run, _manifest(tmp_path / "m.csv", loads))
    st = res.statuses()
    assert st["P-02-2"] == Status.MOVED and st["P-01-2"] == Status.UNEXPECTED
    assert st["PHANTOM"] == Status.MISSING and st["=HYPERLINK(1)|x"] == Status.MISSING
    assert all(st[k] == Status.NOT_SURVEYED for k in truth if k not in ("P-01-2", "P-02-2"))
    row = next(r for r in res.rows if r.load_id == "P-02-2")
    assert row.distance_m == pytest.approx(0.05, abs=0.002) and row.sigma_m < 0.002
    with open(sample_run / "inventory.csv", encoding="utf-8") as f:
        ids = [r["id"] for r in csv.DictReader(f)]
    assert "'=HYPERLINK(1)|x" in ids and "=HYPERLINK(1)|x" not in ids
    report = (sample_run / "report.md").read_text(encoding="utf-8")
    assert "## Inventory" in report and "=HYPERLINK\\(1\\)\\|x" in report
    assert report.count("## Inventory") == 1
    # clean manifest (the truth): no false "moved"; running again replaces the section
    res = run_inventory(sample_run, _manifest(tmp_path / "t.csv", truth))
    assert res.counts()["moved"] == 0 and res.counts()["present"] == 2
    assert (sample_run / "report.md").read_text(encoding="utf-8").count("## Inventory") == 1


def test_inventory_ambiguous_from_raw_observations(sample_run, tmp_path):
    """The same id read at two places (a second cluster 1 m away in load_observations_pnp.csv)."""
    run = tmp_path / "run"
    shutil.copytree(sample_run, run)
    path = run / "load_observations_pnp.csv"
    rows = list(csv.reader(open(path, encoding="utf-8")))
    extra = [[r[0], r[1], f"{float(r[2]) + 1.0:.6f}", *r[3:]] for r in rows[1:] if r[1] == "P-01-2"]
    with open(path, "a", encoding="utf-8", newline="") as f:
        csv.writer(f).writerows(extra)
    res = run_inventory(run, _manifest(tmp_path / "m.csv", _truth()), write=False)
    st = res.statuses()
    assert st["P-01-2"] == Status.AMBIGUOUS and st["P-02-2"] == Status.PRESENT
    row = next(r for r in res.rows if r.load_id == "P-01-2")
    assert len(row.places) == 2


def test_inventory_log_option_and_no_record(sample_run, tmp_path):
    """Without run.json and without --log the front camera is unknown: unread loads are not
    surveyed, with a note; --log gives the camera back."""
    run = tmp_path / "run"
    shutil.copytree(sample_run, run)
    (run / "run.json").unlink()
    manifest = _manifest(tmp_path / "m.csv", {"PHANTOM": [2.5, 2.7, 1.4]})
    res = run_inventory(run, manifest, write=False)
    assert res.statuses()["PHANTOM"] == Status.NOT_SURVEYED and "front camera unknown" in res.notes[0]
    assert main(["inventory", str(run), "--expected", str(manifest), "--log", str(SAMPLE), "-q"]) == 0
    with open(run / "inventory.csv", encoding="utf-8") as f:
        rows = {r["id"]: r["status"] for r in csv.DictReader(f)}
    assert rows == {"PHANTOM": "missing", "P-01-2": "unexpected", "P-02-2": "unexpected"}


@pytest.mark.parametrize(
    "row, words",
    [
        ("100,A,1,2", "expected at least 5 fields, found 4"),
        ("1.5e9,A,1,2,3", "timestamp_ns is not an integer"),
        ("100,A,1,two,3", "a position is not a number"),
        ("100,A,1,inf,3", "NaN or infinite position"),
    ],
)
def test_bad_load_observations_one_line_error(tmp_path, row, words):
    path = _write(
        tmp_path / "load_observations_pnp.csv", f"timestamp_ns,id,x_m,y_m,z_m\n100,A,1,2,3\n{row}\n"
    )
    with pytest.raises(WarehouseError) as e:
        read_observation_rows(path)
    assert str(e.value).startswith(f"{path}:3: ") and words in str(e.value)
    times, points = read_observation_rows(
        _write(path, "timestamp_ns,id,x_m,y_m,z_m\n100,A,1,2,3\n200,A,1,2,4\n")
    )
    assert times["A"].tolist() == [100, 200] and points["A"].shape == (2, 3)


def test_sighting_directions_take_the_nearest_pose():
    camera = make_cameras()["cam1"]
    traj = _hover_trajectory(0.0, 2.9, n=30)  # x = 0.1 m per 0.1 s
    p = np.array([1.5, 2.7, 1.4])
    d = sighting_directions(p, np.array([1_040_000_000, 1_060_000_000]), traj, camera)  # poses 10, 11
    centres = camera.T_world_cam(traj.T_world_body[[10, 11]])[:, :3, 3] - p
    np.testing.assert_allclose(d, centres / np.linalg.norm(centres, axis=1)[:, None])
    one = Trajectory("smoother", traj.timestamps_ns[:1], traj.T_world_body[:1])
    assert sighting_directions(p, np.array([5, 10**12]), one, camera).shape == (2, 3)


def test_load_observations_of_an_id_escaped_on_writing_are_read_under_the_id(tmp_path):
    """An id starting with - + = @ or ' is written csv_safe (a spreadsheet would run it as a
    formula); the reader unescapes it, or inventory's ambiguity test and map merge's view
    directions would never find that load's sightings (thirty-first session's audit)."""
    from fusion.pipeline import write_load_observations_csv
    from fusion.types import LoadObservation

    path = tmp_path / "load_observations_pnp.csv"
    obs = [LoadObservation(100, "-P-01-2", np.array([1.0, 2.0, 3.0])), LoadObservation(200, "'q", np.ones(3))]
    write_load_observations_csv(path, obs)
    assert "'-P-01-2" in path.read_text()
    times, points = read_observation_rows(path)
    assert sorted(times) == ["'q", "-P-01-2"] and times["-P-01-2"].tolist() == [100]


def test_a_manifest_outside_the_warehouse_is_refused_naming_its_line(sample_run, tmp_path, capsys):
    """A plain manifest filled in millimetres: every load would be "moved" by kilometres; the
    positions lie outside world.yaml's bounds (10 x 7 m), so the line is named instead
    (thirty-first session's audit)."""
    truth = _truth()
    mm = {k: [1000 * v for v in p] for k, p in truth.items()}
    manifest = _manifest(tmp_path / "mm.csv", mm)
    with pytest.raises(WarehouseError, match=r"mm\.csv:2: .* outside the warehouse .*metres"):
        run_inventory(sample_run, manifest, write=False)
    assert main(["inventory", str(sample_run), "--expected", str(manifest), "-q"]) == 1
    assert "\n" not in capsys.readouterr().err.strip()
    # just beyond the bounds (a label on a rack's outer face at the wall) is fine
    edge = _manifest(tmp_path / "edge.csv", {"EDGE": [10.5, 3.0, 1.4]})
    assert run_inventory(sample_run, edge, write=False).statuses()["EDGE"] == Status.NOT_SURVEYED
