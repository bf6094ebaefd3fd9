"""External position fixes (issue 11 item 6): the fixes CSV reader, the merge into the back
ends' raw poses, camera-less flights (IMU + fixes) in all three back ends, fixes beside the QR
poses, and `fusion run --fixes` end to end."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_estimate import make_flight, truth_state

from fusion.cli import main
from fusion.errors import EstimationError, LogError
from fusion.estimate import run_ekf, smooth, smooth_incremental
from fusion.estimate.fixes import FREE_ROTATION_SIGMA_RAD, align_attitude, merge_fixes
from fusion.geometry import integrate_gyro, rotation_aligning, so3_exp, so3_log
from fusion.log import euroc
from fusion.log.fixes import PositionFixes, fixes_in_flight, read_fixes
from fusion.types import Trajectory

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
T_OFFSET_S = 1.0  # make_flight's frame / IMU clocks start at 1 s of flight time 0


def fixes_from_truth(t_ns: np.ndarray, sigma_m: float, seed: int) -> PositionFixes:
    rng = np.random.default_rng(seed)
    T, _, _ = truth_state(t_ns * 1e-9 - T_OFFSET_S)
    p = T[:, :3, 3] + rng.normal(size=(len(t_ns), 3)) * sigma_m
    return PositionFixes(t_ns.astype(np.int64), p, np.full(len(t_ns), sigma_m))


def errors(traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (rad) errors against make_flight's truth, per pose."""
    T, _, _ = truth_state(traj.timestamps_ns * 1e-9 - T_OFFSET_S)
    pos = np.linalg.norm(traj.T_world_body[:, :3, 3] - T[:, :3, 3], axis=1)
    rot = np.linalg.norm(
        so3_log(np.einsum("nji,njk->nik", traj.T_world_body[:, :3, :3], T[:, :3, :3])), axis=1
    )
    return pos, rot


# =========================================================================== reader


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_read_fixes_header_and_rows(tmp_path):
    f = read_fixes(
        write(tmp_path / "f.csv", "t_ns,x,y,z,sigma_m\n100000000,1,2,3,0.1\n\n200000000, 1.5 ,2,3,0.2\n")
    )
    np.testing.assert_array_equal(f.timestamps_ns, [100_000_000, 200_000_000])
    np.testing.assert_allclose(f.p_world, [[1, 2, 3], [1.5, 2, 3]])
    np.testing.assert_allclose(f.sigma_m, [0.1, 0.2])
    assert f.warnings == []


def test_read_fixes_sorts_and_counts_out_of_order(tmp_path):
    rows = "# t_ns,x,y,z,sigma_m\n3000000000,3,0,0,1\n1000000000,1,0,0,1\n2000000000,2,0,0,1\n"
    f = read_fixes(write(tmp_path / "f.csv", rows))
    np.testing.assert_array_equal(f.timestamps_ns, [1_000_000_000, 2_000_000_000, 3_000_000_000])
    np.testing.assert_allclose(f.p_world[:, 0], [1, 2, 3])
    assert [(w.name, w.count) for w in f.warnings] == [("fixes_out_of_order", 1)]


@pytest.mark.parametrize(
    "body, line, words",
    [
        ("100,1,2,3\n", 2, "expected 5 fields"),
        ("1e2,1,2,3,0.1\n", 2, "not an integer"),
        ("100,1,y,3,0.1\n", 2, "y 'y' is not a number"),
        ("100,1,2,3,0.1\n200,1,2,nan,0.1\n", 3, "not a finite number"),
        ("100,1,2,3,0\n", 2, "sigma_m must be > 0"),
        ("100,1,2,3,-0.5\n", 2, "sigma_m must be > 0"),
        # t_ns as the EuRoC readers take a timestamp: within int64, digits only
        ("100,1,2,3,0.1\n99999999999999999999,1,2,3,0.1\n", 3, "beyond int64 nanoseconds"),
        ("1_000_000_000,1,2,3,0.1\n", 2, "not an integer number of nanoseconds"),
        ("-5,1,2,3,0.1\n", 2, "negative timestamp"),
    ],
)
def test_bad_fixes_line_names_file_and_line(tmp_path, body, line, words):
    path = write(tmp_path / "f.csv", "t_ns,x,y,z,sigma_m\n" + body)
    with pytest.raises(LogError) as e:
        read_fixes(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}:{line}: ") and words in msg and "\n" not in msg


def test_duplicate_or_missing_fixes_are_errors(tmp_path):
    with pytest.raises(LogError, match="share a timestamp"):
        read_fixes(write(tmp_path / "d.csv", "100,1,2,3,0.1\n100,1,2,3,0.1\n"))
    with pytest.raises(LogError, match="no fixes"):
        read_fixes(write(tmp_path / "e.csv", "t_ns,x,y,z,sigma_m\n"))
    with pytest.raises(LogError, match="not found|no such|missing"):
        read_fixes(tmp_path / "absent.csv")


def test_fixes_in_another_unit_are_an_error(tmp_path):
    """Fixes 100 ms apart stamped in ms (or us): 0.1 ms (0.1 us) apart as ns, an error naming
    the file, not a flight of 8 us fused (numpy overflow warnings, diverged health)."""
    for unit, per_s in (("ms", 1_000), ("us", 1_000_000)):
        rows = "".join(f"{k * per_s // 10},1,2,3,0.02\n" for k in range(81))
        path = write(tmp_path / f"{unit}.csv", "t_ns,x,y,z,sigma_m\n" + rows)
        with pytest.raises(LogError, match=r"not in nanoseconds") as e:
            read_fixes(path)
        assert str(e.value).startswith(f"{path}: ")


def _span_log(t0_ns: int, t1_ns: int):
    """What fixes_in_flight reads of a FlightLog: a camera and an IMU over [t0_ns, t1_ns]."""
    ts = np.linspace(t0_ns, t1_ns, 11).astype(np.int64)
    return SimpleNamespace(
        root=Path("flight"),
        cameras={"cam0": SimpleNamespace(timestamps_ns=ts)},
        imu=SimpleNamespace(timestamps_ns=ts),
    )


def test_fixes_outside_the_flight_are_dropped_and_counted():
    t = np.arange(0, 12, 1, dtype=np.int64) * 1_000_000_000 + 4_000_000_000  # 4 .. 15 s
    fixes = PositionFixes(t, np.zeros((len(t), 3)), np.full(len(t), 0.02), "fixes.csv")
    kept = fixes_in_flight(fixes, _span_log(0, 8_000_000_000))
    np.testing.assert_array_equal(kept.timestamps_ns, t[t <= 8_000_000_000])
    (w,) = kept.warnings
    assert (w.name, w.count) == ("fixes_outside_flight", 7)
    assert w.message.startswith("fixes.csv: 7 of 12") and "0-8 s" in w.message
    # all inside: the same fixes, no warning
    assert fixes_in_flight(fixes, _span_log(0, 20_000_000_000)) is fixes


def test_fixes_in_another_clock_are_an_error():
    """UNIX-epoch fixes against a log clock starting at 0: none in the flight, refused (they had
    been "fused", adding poses 55 years after the flight)."""
    t = np.arange(81, dtype=np.int64) * 100_000_000 + 1_765_000_000 * 10**9
    fixes = PositionFixes(t, np.zeros((81, 3)), np.full(81, 0.02), "unix.csv")
    with pytest.raises(LogError) as e:
        fixes_in_flight(fixes, _span_log(0, 8_000_000_000))
    msg = str(e.value)
    assert msg.startswith("unix.csv: no fix lies within the flight's time span") and "\n" not in msg
    assert "1.765e+09" in msg and "0-8 s" in msg


# =========================================================================== geometry


def test_rotation_aligning_recovers_rotation():
    rng = np.random.default_rng(3)
    R = Rotation.random(random_state=4).as_matrix()
    u = rng.normal(size=(20, 3))
    w = u @ R.T + rng.normal(size=(20, 3)) * 1e-9
    R_est, S = rotation_aligning(u, w)
    np.testing.assert_allclose(R_est, R, atol=1e-8)
    assert np.linalg.det(R_est) == pytest.approx(1.0) and S[0] >= S[1] >= S[2] > 0


def test_integrate_gyro_constant_rate_is_exp():
    w = np.array([0.3, -0.2, 0.5])
    R = integrate_gyro(np.tile(w, (100, 1)), np.full(100, 0.01))
    assert R.shape == (101, 3, 3)
    np.testing.assert_allclose(R[-1], so3_exp(w * 1.0), atol=1e-12)
    np.testing.assert_allclose(R[0], np.eye(3))


# =========================================================================== merge


@pytest.fixture(scope="module")
def flight():
    return make_flight(seed=2, duration_s=20.0, gaps=((5.0, 12.0),))


def test_merge_adds_fix_states_and_fuses_coincident_ones(flight):
    t_fix = np.array([flight.raw.timestamps_ns[3], flight.frame_t[0] + 12_345_678], dtype=np.int64)
    fixes = fixes_from_truth(t_fix, 0.01, seed=5)
    m = merge_fixes(flight.frame_t, flight.raw, fixes, flight.imu)
    assert m.n_fixes == 2 and m.n_fused_into_qr == 1
    np.testing.assert_array_equal(m.frame_t, np.union1d(flight.frame_t, t_fix))
    assert len(m.raw) == len(flight.raw) + 1 and np.all(np.diff(m.raw.timestamps_ns) > 0)
    # the new state: the fix's position, no attitude information
    j = int(np.searchsorted(m.raw.timestamps_ns, t_fix[1]))
    np.testing.assert_allclose(m.raw.T_world_body[j, :3, 3], fixes.p_world[1])
    np.testing.assert_allclose(np.diag(m.raw.covariances[j]), [FREE_ROTATION_SIGMA_RAD**2] * 3 + [1e-4] * 3)
    # the coincident fix: the QR pose (2 mm) pulled towards the 1 cm fix by the information ratio
    i = int(np.searchsorted(m.raw.timestamps_ns, t_fix[0]))
    p_qr = flight.raw.T_world_body[3, :3, 3]
    moved = m.raw.T_world_body[i, :3, 3] - p_qr
    expected = (fixes.p_world[0] - p_qr) * 0.002**2 / (0.002**2 + 0.01**2)
    np.testing.assert_allclose(moved, expected, atol=2e-4)
    assert np.all(np.diag(m.raw.covariances[i])[3:] < 0.002**2)


def test_merge_without_camera_needs_an_imu(flight):
    fixes = fixes_from_truth(flight.frame_t[::3], 0.02, seed=1)
    with pytest.raises(EstimationError, match="need an IMU"):
        merge_fixes(None, None, fixes, None)
    few = fixes_from_truth(flight.frame_t[:2], 0.02, seed=1)
    with pytest.raises(EstimationError, match="too few or too sparse"):
        merge_fixes(None, None, few, flight.imu)


def test_alignment_finds_attitude(flight):
    fixes = fixes_from_truth(flight.frame_t[::3], 0.02, seed=1)
    R_wb, info = align_attitude(fixes, flight.imu)
    T, _, _ = truth_state(fixes.timestamps_ns * 1e-9 - T_OFFSET_S)
    err = np.linalg.norm(so3_log(np.einsum("nji,njk->nik", R_wb, T[:, :3, :3])), axis=1)
    # gyro bias (~3 mrad/s) drifts the chained attitude over 20 s: degrees, an initial guess
    assert np.degrees(err[0]) < 3.0 and np.degrees(err.max()) < 6.0
    assert info["pairs"] > 50 and info["sideways_dv_rms_m_s"] > 0.1


# =========================================================================== back ends


@pytest.fixture(scope="module")
def camera_less(flight):
    """IMU + 10 Hz fixes of 2 cm, no camera; fixes between frame times on purpose."""
    t = flight.frame_t[0] + np.arange(0, int(19.8e9), int(0.1e9), dtype=np.int64) + 7_000_000
    fixes = fixes_from_truth(t, 0.02, seed=9)
    return merge_fixes(None, None, fixes, flight.imu)


@pytest.mark.parametrize(
    "solver, max_mean_pos_m, max_mean_rot_deg",
    # the smoother's yaw rests on the fixes' accelerations alone: sigma ~7 mrad (0.42 deg) here,
    # its rotation NEES 2.8 of 3 with the midpoint attitude (0.54 deg mean error; 0.40 without)
    [(smooth, 0.01, 0.75), (smooth_incremental, 0.02, 2.0), (run_ekf, 0.02, 3.0)],
)
def test_camera_less_flight_is_fused(flight, camera_less, solver, max_mean_pos_m, max_mean_rot_deg):
    res = solver(camera_less.frame_t, flight.imu, camera_less.raw, None, front_camera=None)
    assert len(res.trajectory) >= len(camera_less.frame_t) - 1
    pos, rot = errors(res.trajectory)
    # fixes alone: 2 cm per axis, 3.5 cm in 3D; the fused track must be better than the fixes
    assert pos.mean() < max_mean_pos_m
    assert math.degrees(rot.mean()) < max_mean_rot_deg
    assert res.trajectory.covariances is not None


@pytest.mark.parametrize("solver", [smooth, smooth_incremental, run_ekf])
def test_fixes_beside_qr_bridge_a_blackout(flight, solver):
    """A 7 s floor-code blackout: IMU alone drifts (3.7 mm at most with the midpoint attitude, 7.2
    without); 3 mm fixes at 10 Hz (a total station's, a mocap's) hold the track closer (2.1 mm;
    1 cm fixes no longer beat the IMU over 7 s: 5.9 mm)."""
    t = flight.frame_t[0] + np.arange(0, int(19.8e9), int(0.1e9), dtype=np.int64) + 12_345_678
    m = merge_fixes(flight.frame_t, flight.raw, fixes_from_truth(t, 0.003, seed=4), flight.imu)
    qr = solver(flight.frame_t, flight.imu, flight.raw, None, front_camera=None).trajectory
    both = solver(m.frame_t, flight.imu, m.raw, None, front_camera=None).trajectory

    def gap_max(traj):
        s = traj.timestamps_ns * 1e-9 - T_OFFSET_S
        return errors(traj)[0][(s >= 5.0) & (s < 12.0)].max()

    assert gap_max(both) < 0.02
    assert gap_max(both) < gap_max(qr)
    pos, _ = errors(both)
    assert pos.mean() < 0.01


# =========================================================================== command line


@pytest.fixture(scope="module")
def camera_less_log(tmp_path_factory):
    """The sample flight without its cameras, and 10 Hz fixes of 1 cm from its ground truth."""
    d = tmp_path_factory.mktemp("nocam")
    log = d / "log"
    shutil.copytree(SAMPLE, log)
    for cam in ("cam0", "cam1"):
        shutil.rmtree(log / "mav0" / cam)
    gt = euroc.read_flight(SAMPLE).groundtruth
    rng = np.random.default_rng(0)
    sel = np.arange(0, len(gt.timestamps_ns), 20)
    p = gt.p_world[sel] + rng.normal(size=(len(sel), 3)) * 0.01
    lines = ["t_ns,x,y,z,sigma_m"] + [
        f"{t},{x:.5f},{y:.5f},{z:.5f},0.01" for t, (x, y, z) in zip(gt.timestamps_ns[sel], p)
    ]
    (d / "fixes.csv").write_text("\n".join(lines) + "\n")
    return log, d / "fixes.csv"


def test_cli_run_without_cameras(camera_less_log, tmp_path):
    log, fixes = camera_less_log
    out = tmp_path / "out"
    assert main(["run", str(log), "--fixes", str(fixes), "--out", str(out), "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    for name in ("smoother", "incremental", "ekf"):
        assert (out / f"trajectory_{name}.tum").exists() and (out / f"sigmas_{name}.csv").exists()
        assert metrics["trajectories"][name]["ate_rmse_m"] < 0.02
        assert metrics["health"][name]["status"] == "ok"
    assert metrics["trajectories"]["smoother"]["ate_rmse_m"] < 0.01
    assert (out / "report.md").exists() and not (out / "detections.csv").exists()


def test_camera_less_heading_without_sideways_motion_is_the_runs_named_warning(camera_less_log, tmp_path):
    """Fixes that never accelerate sideways (here a hover: every velocity change is gravity's)
    do not give the in-motion alignment a heading: the run names it (`fixes_heading_unobserved`,
    in the summary's warnings and metrics.json) instead of a log line only, and still ends."""
    log, good = camera_less_log
    rows = good.read_text().splitlines()
    hover = ["t_ns,x,y,z,sigma_m"] + [f"{r.split(',')[0]},1.0,2.0,1.5,0.01" for r in rows[1:]]
    fixes = write(tmp_path / "hover.csv", "\n".join(hover) + "\n")
    out = tmp_path / "out"
    assert main(["run", str(log), "--fixes", str(fixes), "--out", str(out), "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    (w,) = [w for w in metrics["warnings"] if w["name"] == "fixes_heading_unobserved"]
    assert w["count"] == 1 and "heading" in w["message"] and "m/s" in w["message"]
    # fixes of the flight itself accelerate sideways: no warning
    main(["run", str(log), "--fixes", str(good), "--out", str(tmp_path / "ok"), "--quiet"])
    ok = json.loads((tmp_path / "ok" / "metrics.json").read_text())
    assert not [w for w in ok["warnings"] if w["name"] == "fixes_heading_unobserved"]


def test_cli_camera_less_needs_fixes_and_good_fixes(camera_less_log, tmp_path, capsys):
    log, _ = camera_less_log
    assert main(["run", str(log), "--out", str(tmp_path / "a"), "--quiet"]) == 1
    assert "floor camera folder is missing" in capsys.readouterr().err
    bad = write(tmp_path / "bad.csv", "t_ns,x,y,z,sigma_m\n6000000000,1,2,3,0.01\n6100000000,1,2\n")
    assert main(["run", str(log), "--fixes", str(bad), "--out", str(tmp_path / "b"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}:3: expected 5 fields" in err[0]
    # fixes in another clock (UNIX epoch) than the log's: one line naming the file, no output
    unix = write(
        tmp_path / "unix.csv",
        "t_ns,x,y,z,sigma_m\n"
        + "".join(f"{1_765_000_000_000_000_000 + k * 100_000_000},1,2,3,0.01\n" for k in range(50)),
    )
    assert main(["run", str(log), "--fixes", str(unix), "--out", str(tmp_path / "c"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"fusion: error: {unix}: no fix lies within")
    assert not (tmp_path / "c" / "metrics.json").exists()
