"""Bad input, as a user's logs bring it: each case copies a small EuRoC flight (images
hard-linked), breaks one thing in it (a malformed or truncated CSV, a wrong unit, a corrupt or
resized image, a broken sensor.yaml or world.yaml, a missing stream), runs `fusion run` on it and
says how the run answered:

  error      exit 1 with one `fusion: error: ...` line and no output folder contents
  warned     exit 0, the problem named in the summary (warning / note / health lines)
  silent     exit 0 and nothing said: to look at (some cases are harmless, e.g. a colour PNG)
  traceback  a Python traceback: always a bug

Prints a Markdown table (case, what was broken, outcome, the first message).  The flight: any
EuRoC folder with cam0, cam1, imu0 and vel0, e.g. `fusion simulate --duration 8 --seed 11 F`; or
a folder of videos with Kalibr calibration (`--format video`), or a ROS 1 bag / ROS 2 MCAP file
(`--format rosbag1` / `rosbag2`): each kind of log gets its own cases (`--list`).

    python3 scripts/fuzz_inputs.py FLIGHT WORKDIR [--cases imu_text cam_zero ...] [--list]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import yaml

TEXT_SUFFIXES = (".csv", ".yaml", ".json")
GRAVITY = 9.80665


def _lines(p: Path) -> list[str]:
    return p.read_text().splitlines(keepends=True)


def _set_lines(p: Path, lines: list[str]) -> None:
    p.write_text("".join(lines))


def _map_rows(p: Path, fn: Callable[[list[str]], list[str]]) -> None:
    """Apply `fn` to the fields of every data row of a CSV (the header kept)."""
    lines = _lines(p)
    _set_lines(p, lines[:1] + [",".join(fn(line.strip().split(","))) + "\n" for line in lines[1:]])


def _set_key(p: Path, key: str, value: str) -> None:
    _set_lines(p, [f"{key}: {value}\n" if line.startswith(f"{key}:") else line for line in _lines(p)])


def _images(d: Path, cam: str = "cam0") -> list[Path]:
    return sorted((d / "mav0" / cam / "data").iterdir())


def _rewrite_image(f: Path, img: np.ndarray) -> None:
    f.unlink()  # a hard link to the original: replace, do not write through
    cv2.imwrite(str(f), img)


def _replace_bytes(f: Path, data: bytes) -> None:
    f.unlink()
    f.write_bytes(data)


IMU = "mav0/imu0/data.csv"
CAM = "mav0/cam0/data.csv"


def _imu_text(d: Path) -> None:
    ls = _lines(d / IMU)
    ls[500] = ls[500].replace(",", ",abc", 1)
    _set_lines(d / IMU, ls)


def _imu_truncated(d: Path) -> None:
    t = (d / IMU).read_text()
    (d / IMU).write_text(t[: len(t) // 2 + 17])


def _imu_seconds(d: Path) -> None:
    _map_rows(d / IMU, lambda f: [f"{int(f[0]) / 1e9:.6f}"] + f[1:])


def _imu_repeated_rows(d: Path) -> None:
    ls = _lines(d / IMU)
    ls[300:300] = ls[290:300]
    _set_lines(d / IMU, ls)


def _imu_nan(d: Path) -> None:
    ls = _lines(d / IMU)
    for i in range(700, 720):
        f = ls[i].split(",")
        f[4] = "nan"
        ls[i] = ",".join(f)
    _set_lines(d / IMU, ls)


def _imu_in_g(d: Path) -> None:
    _map_rows(d / IMU, lambda f: f[:4] + [repr(float(x) / GRAVITY) for x in f[4:7]])


def _imu_deg_s(d: Path) -> None:
    _map_rows(d / IMU, lambda f: f[:1] + [repr(float(np.degrees(float(x)))) for x in f[1:4]] + f[4:])


def _imu_empty(d: Path) -> None:
    _set_lines(d / IMU, _lines(d / IMU)[:1])


def _imu_swapped_rows(d: Path) -> None:
    ls = _lines(d / IMU)
    ls[400], ls[800] = ls[800], ls[400]
    _set_lines(d / IMU, ls)


def _imu_gap(d: Path) -> None:
    ls = _lines(d / IMU)
    del ls[300:900]
    _set_lines(d / IMU, ls)


def _imu_crlf(d: Path) -> None:
    (d / IMU).write_bytes((d / IMU).read_bytes().replace(b"\n", b"\r\n"))


def _cam_missing(d: Path) -> None:
    for f in _images(d)[::8]:
        f.unlink()


def _cam_truncated_png(d: Path) -> None:
    for f in _images(d)[:5]:
        b = f.read_bytes()
        _replace_bytes(f, b[: len(b) // 3])


def _cam_empty_file(d: Path) -> None:
    _replace_bytes(_images(d)[10], b"")


def _cam_not_png(d: Path) -> None:
    _replace_bytes(_images(d)[12], b"hello")


def _cam_resized(d: Path) -> None:
    f = _images(d)[20]
    _rewrite_image(f, cv2.resize(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), (320, 240)))


def _cam_colour(d: Path) -> None:
    for f in _images(d)[:20]:
        _rewrite_image(f, cv2.cvtColor(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2BGR))


def _cam_16bit(d: Path) -> None:
    for f in _images(d)[:20]:
        _rewrite_image(f, cv2.imread(str(f), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 256)


def _camcsv_bad_line(d: Path) -> None:
    ls = _lines(d / CAM)
    ls[50] = "garbage line here\n"
    _set_lines(d / CAM, ls)


def _camcsv_empty(d: Path) -> None:
    _set_lines(d / CAM, _lines(d / CAM)[:1])


def _camcsv_swapped_rows(d: Path) -> None:
    ls = _lines(d / CAM)
    ls[40], ls[60] = ls[60], ls[40]
    _set_lines(d / CAM, ls)


def _camcsv_duplicate(d: Path) -> None:
    ls = _lines(d / CAM)
    ls.insert(41, ls[40])
    _set_lines(d / CAM, ls)


def _camcsv_bom(d: Path) -> None:
    (d / CAM).write_bytes(b"\xef\xbb\xbf" + (d / CAM).read_bytes())


def _sensor_not_yaml(d: Path) -> None:
    (d / "mav0/cam0/sensor.yaml").write_text("intrinsics: [550, 550\n  : : ]]\n")


def _sensor_no_intrinsics(d: Path) -> None:
    p = d / "mav0/cam0/sensor.yaml"
    _set_lines(p, [line for line in _lines(p) if not line.startswith("intrinsics")])


def _sensor_zero_focal(d: Path) -> None:
    _set_key(d / "mav0/cam0/sensor.yaml", "intrinsics", "[0.0, 0.0, 321.3, 239.2]")


def _sensor_other_resolution(d: Path) -> None:
    _set_key(d / "mav0/cam0/sensor.yaml", "resolution", "[1280, 720]")


def _sensor_t_bs_17(d: Path) -> None:
    p = d / "mav0/cam0/sensor.yaml"
    t = p.read_text()
    i = t.index("data: [") + len("data: [")
    p.write_text(t[:i] + "7.0, " + t[i:])


def _sensor_negative_rate(d: Path) -> None:
    _set_key(d / "mav0/cam0/sensor.yaml", "rate_hz", "-30")


def _imu_sensor_missing(d: Path) -> None:
    (d / "mav0/imu0/sensor.yaml").unlink()


def _imu_sensor_negative_noise(d: Path) -> None:
    _set_key(d / "mav0/imu0/sensor.yaml", "gyroscope_noise_density", "-0.1")


def _world_not_yaml(d: Path) -> None:
    (d / "world.yaml").write_text("floor_qr: [1, 2\n")


def _world_missing(d: Path) -> None:
    (d / "world.yaml").unlink()


def _world_side_cm(d: Path) -> None:
    p = d / "world.yaml"
    to_cm = lambda m: f"side_m: {100 * float(m[1]):g}"  # noqa: E731
    p.write_text(re.sub(r"side_m: ([0-9.]+)", to_cm, p.read_text(), count=1))


def _world_side_zero(d: Path) -> None:
    p = d / "world.yaml"
    p.write_text(re.sub(r"side_m: [0-9.]+", "side_m: 0", p.read_text(), count=1))


def _world_load_sigma_mm(d: Path) -> None:
    """The labels' print error given in mm (0.3 meaning 0.3 mm): 0.3 m, twice the side."""
    data = yaml.safe_load((d / "world.yaml").read_text())
    data.setdefault("load_qr", {})["side_sigma_m"] = 0.3
    (d / "world.yaml").write_text(yaml.safe_dump(data))


def _world_placement_cm(d: Path) -> None:
    """The floor codes' placement sigma given in cm (1 meaning 1 cm): 1 m, five codes' sides."""
    data = yaml.safe_load((d / "world.yaml").read_text())
    data.setdefault("floor_qr", {}).update(placement_sigma_m=1.0, placement_sigma_deg=1.0)
    (d / "world.yaml").write_text(yaml.safe_dump(data))


def _world_placement_negative(d: Path) -> None:
    data = yaml.safe_load((d / "world.yaml").read_text())
    data.setdefault("floor_qr", {})["placement_sigma_deg"] = -0.5
    (d / "world.yaml").write_text(yaml.safe_dump(data))


def _sensor_intrinsics_sigma_relative(d: Path) -> None:
    """The intrinsics' sigma given as a fraction of the focal length for fu (0.002) but in px
    for the rest, and one of them negative: -1 px."""
    p = d / "mav0/cam0/sensor.yaml"
    lines = [line for line in _lines(p) if not line.startswith("intrinsics_sigma:")]
    _set_lines(p, [*lines, "intrinsics_sigma: [0.002, 0.002, 1.0, -1.0]\n"])


def _sensor_intrinsics_sigma_three(d: Path) -> None:
    """The intrinsics' sigma with three numbers (the principal point's given once)."""
    p = d / "mav0/cam0/sensor.yaml"
    lines = [line for line in _lines(p) if not line.startswith("intrinsics_sigma:")]
    _set_lines(p, [*lines, "intrinsics_sigma: [1.1, 1.1, 1.0]\n"])


def _sensor_mount_sigma_mm(d: Path) -> None:
    """The front camera's mount sigma given in mm (2 meaning 2 mm): 2 m."""
    p = d / "mav0/cam1/sensor.yaml"
    lines = [line for line in _lines(p) if not line.startswith("T_BS_sigma_m:")]
    _set_lines(p, [*lines, "T_BS_sigma_m: 2\n"])


def _groundtruth_short_row(d: Path) -> None:
    p = d / "mav0/state_groundtruth_estimate0/data.csv"
    ls = _lines(p)
    ls[100] = "1,2,3\n"
    _set_lines(p, ls)


def _groundtruth_other_frame(d: Path) -> None:
    gt = d / "mav0/state_groundtruth_estimate0/data.csv"
    _map_rows(gt, lambda f: f[:1] + [repr(float(f[1]) + 100.0)] + f[2:])


def _loads_text(d: Path) -> None:
    (d / "loads_groundtruth.csv").write_text("id,x_m,y_m,z_m\nP-01-1,1.5,abc,0.7\n")


def _velocity_short_row(d: Path) -> None:
    p = d / "mav0/vel0/data.csv"
    ls = _lines(p)
    ls[20] = "1,2\n"
    _set_lines(p, ls)


def _no_front_camera(d: Path) -> None:
    shutil.rmtree(d / "mav0/cam1")


def _no_imu(d: Path) -> None:
    shutil.rmtree(d / "mav0/imu0")


def _cam_symlink_loop(d: Path) -> None:
    f = _images(d)[50]
    f.unlink()
    f.symlink_to(f.name)  # a -> a


def _cam1_symlink_loop(d: Path) -> None:
    shutil.rmtree(d / "mav0/cam1")
    (d / "mav0/cam1").symlink_to("cam1")


def _groundtruth_one_row(d: Path) -> None:
    p = d / "mav0/state_groundtruth_estimate0/data.csv"
    _set_lines(p, _lines(p)[:2])


def _imu_starts_late(d: Path) -> None:
    p = d / "mav0/imu0/data.csv"
    ls = _lines(p)
    _set_lines(p, ls[:1] + ls[1 + (len(ls) - 1) // 2 :])


def _world_unknown_key(d: Path) -> None:
    p = d / "world.yaml"
    _set_lines(p, [line.replace("load_qr: {side_m:", "load_qr: {side_mm:") for line in _lines(p)])


def _sensor_duplicate_key(d: Path) -> None:
    p = d / "mav0/cam0/sensor.yaml"
    _set_lines(p, [*_lines(p), "intrinsics: [600.0, 600.0, 320.0, 240.0]\n"])


def _sensor_kalibr_line_delay(d: Path) -> None:
    p = d / "mav0/cam0/sensor.yaml"
    _set_lines(p, [*_lines(p), "line_delay: 2.0e-05\n"])


def _imu_frd(d: Path) -> None:  # PX4's FRD axes, T_BS saying FLU: y and z negated
    _map_rows(
        d / IMU, lambda f: [f[0]] + [repr(-float(x)) if i in (1, 2, 4, 5) else x for i, x in enumerate(f[1:])]
    )


def _sensor_principal_point_outside(d: Path) -> None:
    p = d / "mav0/cam0/sensor.yaml"
    _set_lines(p, [_intrinsics_with(line, cu=642.0) for line in _lines(p)])


def _intrinsics_with(line: str, cu: float) -> str:
    if not line.startswith("intrinsics:"):
        return line
    fu, fv, _, cv = (float(v) for v in line.split("[", 1)[1].split("]")[0].split(","))
    return f"intrinsics: [{fu!r}, {fv!r}, {cu!r}, {cv!r}]\n"


def _world_floor_side_3pct(d: Path) -> None:
    p = d / "world.yaml"
    _set_lines(
        p, [line.replace("floor_qr: {side_m: 0.2,", "floor_qr: {side_m: 0.206,") for line in _lines(p)]
    )


CASES: dict[str, tuple[str, Callable[[Path], None]]] = {
    "imu_text": ("imu0/data.csv: a field 'abc...' in row 501", _imu_text),
    "imu_truncated": ("imu0/data.csv cut in the middle of a row", _imu_truncated),
    "imu_seconds": ("imu0/data.csv stamps in seconds", _imu_seconds),
    "imu_repeated_rows": ("imu0/data.csv: 10 rows written twice", _imu_repeated_rows),
    "imu_nan": ("imu0/data.csv: 20 accelerometer values NaN", _imu_nan),
    "imu_in_g": ("imu0/data.csv accelerometer in g", _imu_in_g),
    "imu_deg_s": ("imu0/data.csv gyroscope in deg/s", _imu_deg_s),
    "imu_empty": ("imu0/data.csv header only", _imu_empty),
    "imu_swapped_rows": ("imu0/data.csv: two rows swapped", _imu_swapped_rows),
    "imu_gap": ("imu0/data.csv: 3 s of rows missing", _imu_gap),
    "imu_crlf": ("imu0/data.csv with CRLF line ends", _imu_crlf),
    "cam_missing": ("every 8th cam0 image deleted", _cam_missing),
    "cam_truncated_png": ("5 cam0 PNGs cut to a third", _cam_truncated_png),
    "cam_empty_file": ("one cam0 image 0 bytes", _cam_empty_file),
    "cam_not_png": ("one cam0 image a text file", _cam_not_png),
    "cam_resized": ("one cam0 image 320x240", _cam_resized),
    "cam_colour": ("20 cam0 images as BGR", _cam_colour),
    "cam_16bit": ("20 cam0 images 16-bit", _cam_16bit),
    "camcsv_bad_line": ("cam0/data.csv: a line of text", _camcsv_bad_line),
    "camcsv_empty": ("cam0/data.csv header only", _camcsv_empty),
    "camcsv_swapped_rows": ("cam0/data.csv: two rows swapped", _camcsv_swapped_rows),
    "camcsv_duplicate": ("cam0/data.csv: a row twice", _camcsv_duplicate),
    "camcsv_bom": ("cam0/data.csv with a UTF-8 BOM", _camcsv_bom),
    "sensor_not_yaml": ("cam0/sensor.yaml not YAML", _sensor_not_yaml),
    "sensor_no_intrinsics": ("cam0/sensor.yaml without intrinsics", _sensor_no_intrinsics),
    "sensor_zero_focal": ("cam0/sensor.yaml focal length 0", _sensor_zero_focal),
    "sensor_other_resolution": ("cam0/sensor.yaml 1280x720, images 640x480", _sensor_other_resolution),
    "sensor_t_bs_17": ("cam0/sensor.yaml T_BS with 17 numbers", _sensor_t_bs_17),
    "sensor_negative_rate": ("cam0/sensor.yaml rate_hz -30", _sensor_negative_rate),
    "imu_sensor_missing": ("imu0/sensor.yaml deleted", _imu_sensor_missing),
    "imu_sensor_negative_noise": ("imu0/sensor.yaml negative gyro noise", _imu_sensor_negative_noise),
    "world_not_yaml": ("world.yaml not YAML", _world_not_yaml),
    "world_missing": ("world.yaml deleted", _world_missing),
    "world_side_cm": ("world.yaml floor side in cm", _world_side_cm),
    "world_side_zero": ("world.yaml floor side 0", _world_side_zero),
    "world_load_sigma_mm": ("world.yaml load_qr.side_sigma_m 0.3 (mm meant)", _world_load_sigma_mm),
    "world_placement_cm": ("world.yaml placement_sigma_m 1 (cm meant)", _world_placement_cm),
    "world_placement_negative": ("world.yaml placement_sigma_deg -0.5", _world_placement_negative),
    "sensor_mount_sigma_mm": ("cam1/sensor.yaml T_BS_sigma_m 2 (mm meant)", _sensor_mount_sigma_mm),
    "sensor_intrinsics_sigma_negative": (
        "cam0/sensor.yaml intrinsics_sigma with a negative entry",
        _sensor_intrinsics_sigma_relative,
    ),
    "sensor_intrinsics_sigma_three": (
        "cam0/sensor.yaml intrinsics_sigma of 3 numbers",
        _sensor_intrinsics_sigma_three,
    ),
    "groundtruth_short_row": ("ground truth: a row of 3 fields", _groundtruth_short_row),
    "groundtruth_other_frame": ("ground truth 100 m off in x", _groundtruth_other_frame),
    "loads_text": ("loads_groundtruth.csv: a coordinate 'abc'", _loads_text),
    "velocity_short_row": ("vel0/data.csv: a row of 2 fields", _velocity_short_row),
    "no_front_camera": ("mav0/cam1 deleted", _no_front_camera),
    "no_imu": ("mav0/imu0 deleted", _no_imu),
    "cam_symlink_loop": ("a cam0 image a symbolic link to itself", _cam_symlink_loop),
    "cam1_symlink_loop": ("mav0/cam1 a symbolic link to itself", _cam1_symlink_loop),
    "groundtruth_one_row": ("ground truth of one row", _groundtruth_one_row),
    "imu_starts_late": ("imu0/data.csv: the first half of the rows missing", _imu_starts_late),
    "world_unknown_key": ("world.yaml load_qr.side_mm (misspelt side_m)", _world_unknown_key),
    "sensor_duplicate_key": ("cam0/sensor.yaml intrinsics given twice", _sensor_duplicate_key),
    "sensor_kalibr_line_delay": ("cam0/sensor.yaml Kalibr's line_delay", _sensor_kalibr_line_delay),
    # the third audit's (thirty-second session)
    "imu_frd": ("imu0/data.csv in FRD axes, T_BS saying FLU", _imu_frd),
    "sensor_principal_point_outside": ("cam0/sensor.yaml cu 642 for 640 px", _sensor_principal_point_outside),
    "world_floor_side_3pct": ("world.yaml floor side_m 3 % too large", _world_floor_side_3pct),
}


def copy_flight(src: Path, dst: Path) -> None:
    """`src` into `dst`: images hard-linked, the small text files copied (so they can be edited)."""
    subprocess.run(["cp", "-al", str(src), str(dst)], check=True)
    for p in dst.rglob("*"):
        if p.is_file() and p.suffix in TEXT_SUFFIXES:
            data = p.read_bytes()
            p.unlink()
            p.write_bytes(data)


def outcome(rc: int, stdout: str, stderr: str, out: Path) -> tuple[str, str]:
    """(outcome, first message) of one run; see the module docstring."""
    if "Traceback" in stderr:
        return "traceback", stderr.strip().splitlines()[-1]
    errors = [line for line in stderr.splitlines() if line.startswith("fusion: error:")]
    if rc != 0:
        half = out.exists() and any(out.iterdir())
        kind = "error" if errors and not half else f"error (rc {rc}{', outputs left' if half else ''})"
        return kind, (errors or stderr.strip().splitlines() or [""])[0]
    said = [
        line
        for line in stdout.splitlines() + stderr.splitlines()
        if line.startswith(("warning:", "note:", "health:", "fusion: ")) or "FAILED" in line
    ]
    said.sort(key=lambda line: not line.startswith("warning:"))  # a named warning first
    return ("warned", said[0]) if said else ("silent", "")


def run_case(name: str, flight: Path, work: Path) -> tuple[str, str]:
    case_dir = work / name
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    log = case_dir / ("log" + flight.suffix)
    if flight.is_file():
        shutil.copyfile(flight, log)
    else:
        copy_flight(flight, log)
    ALL_CASES[name][1](log)
    cmd = [sys.executable, "-m", "fusion.cli", "run", str(log), "--out", str(case_dir / "out")]
    r = subprocess.run([*cmd, "-q", "--workers", "1", "--no-incremental"], capture_output=True, text=True)
    kind, message = outcome(r.returncode, r.stdout, r.stderr, case_dir / "out")
    if kind != "traceback":  # kept for a traceback, to reproduce it
        log.unlink() if log.is_file() else shutil.rmtree(log)
    return kind, message.replace(str(case_dir) + "/", "").replace("|", "\\|")


# ---------------------------------------------------------------- video folders (Kalibr layout)


def _video_truncated(d: Path) -> None:
    data = (d / "cam0.mkv").read_bytes()
    _replace_bytes(d / "cam0.mkv", data[: int(0.6 * len(data))])


def _video_random(d: Path) -> None:
    _replace_bytes(d / "cam0.mkv", np.random.default_rng(0).bytes(20_000))


def _video_overwritten(d: Path) -> None:
    data = bytearray((d / "cam0.mkv").read_bytes())
    at = len(data) // 2
    data[at : at + 20_000] = np.random.default_rng(1).bytes(20_000)
    _replace_bytes(d / "cam0.mkv", bytes(data))


def _video_missing(d: Path) -> None:
    (d / "cam0.mkv").unlink()


def _video_times_short(d: Path) -> None:
    ls = _lines(d / "cam0.csv")
    _set_lines(d / "cam0.csv", ls[: 1 + (len(ls) - 1) // 2])


def _video_times_extra(d: Path) -> None:
    ls = _lines(d / "cam0.csv")
    t = [int(x) for x in ls[1:]]
    step = t[1] - t[0]
    _set_lines(d / "cam0.csv", ls + [f"{t[-1] + step * (i + 1)}\n" for i in range(len(t) // 4)])


def _video_times_text(d: Path) -> None:
    ls = _lines(d / "cam0.csv")
    ls[30] = "abc\n"
    _set_lines(d / "cam0.csv", ls)


def _video_times_seconds(d: Path) -> None:
    ls = _lines(d / "cam0.csv")
    _set_lines(d / "cam0.csv", ls[:1] + [f"{int(x) / 1e9:.6f}\n" for x in ls[1:]])


def _camchain_no_intrinsics(d: Path) -> None:
    p = d / "camchain-imucam.yaml"
    _set_lines(p, [line for line in _lines(p) if not line.strip().startswith("intrinsics:")])


def _camchain_not_yaml(d: Path) -> None:
    p = d / "camchain-imucam.yaml"
    p.write_text("cam0:\n  intrinsics: [550.0, 550.0\n")


def _camchain_singular(d: Path) -> None:
    p = d / "camchain-imucam.yaml"
    ls = _lines(p)
    i = next(k for k, line in enumerate(ls) if line.strip().startswith("T_cam_imu:"))
    ls[i + 1] = "  - [0.0, 0.0, 0.0, 0.0]\n"
    _set_lines(p, ls)


def _video_imu_yaml_missing(d: Path) -> None:
    (d / "imu.yaml").unlink()


# ---------------------------------------------------------------- bags (ROS 1 .bag, ROS 2 .mcap)


def _bag_cut(f: Path) -> None:
    data = f.read_bytes()
    _replace_bytes(f, data[: len(data) // 2])


def _bag_overwritten(f: Path) -> None:
    data = bytearray(f.read_bytes())
    at = int(0.4 * len(data))
    data[at : at + 50_000] = np.random.default_rng(2).bytes(50_000)
    _replace_bytes(f, bytes(data))


def _bag_header(f: Path) -> None:
    data = bytearray(f.read_bytes())
    data[:16] = b"\0" * 16
    _replace_bytes(f, bytes(data))


def _bag_empty(f: Path) -> None:
    _replace_bytes(f, b"")


VIDEO_CASES: dict[str, tuple[str, Callable[[Path], None]]] = {
    "video_truncated": ("cam0.mkv cut at 60 %", _video_truncated),
    "video_random": ("cam0.mkv replaced by 20 kB of random bytes", _video_random),
    "video_overwritten": ("20 kB of cam0.mkv overwritten mid-file", _video_overwritten),
    "video_missing": ("cam0.mkv deleted", _video_missing),
    "video_times_short": ("cam0.csv: the first half of the frame times only", _video_times_short),
    "video_times_extra": ("cam0.csv: a quarter more frame times than frames", _video_times_extra),
    "video_times_text": ("cam0.csv: a line 'abc'", _video_times_text),
    "video_times_seconds": ("cam0.csv: stamps in seconds", _video_times_seconds),
    "camchain_no_intrinsics": ("camchain-imucam.yaml without intrinsics", _camchain_no_intrinsics),
    "camchain_not_yaml": ("camchain-imucam.yaml not YAML", _camchain_not_yaml),
    "camchain_singular": ("camchain-imucam.yaml: cam0's T_cam_imu with a zero row", _camchain_singular),
    "video_imu_yaml_missing": ("imu.yaml (IMU noise) deleted", _video_imu_yaml_missing),
}
BAG_CASES: dict[str, tuple[str, Callable[[Path], None]]] = {
    "bag_cut": ("the bag cut at 50 %", _bag_cut),
    "bag_overwritten": ("50 kB of the bag overwritten at 40 %", _bag_overwritten),
    "bag_header": ("the bag's first 16 bytes zeroed", _bag_header),
    "bag_empty": ("the bag 0 bytes", _bag_empty),
}
EUROC_CASES = CASES
CASES_BY_KIND = {"euroc": EUROC_CASES, "video": VIDEO_CASES, "bag": BAG_CASES}
ALL_CASES = {**EUROC_CASES, **VIDEO_CASES, **BAG_CASES}


NEED_ROWS = (("imu0", 901), ("cam0", 61))
"""Rows a EuRoC flight's streams need: the cases break rows at fixed places (IMU row 900, camera
row 60), an 8 s simulated flight has them."""


def flight_kind(flight: Path) -> str:
    """'bag' (a .bag or .mcap file), 'video' (a folder with cam0.mkv / camchain) or 'euroc'."""
    if flight.is_file():
        return "bag"
    if (flight / "camchain-imucam.yaml").exists():
        return "video"
    return "euroc"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flight", type=Path, nargs="?")
    ap.add_argument("workdir", type=Path, nargs="?")
    ap.add_argument("--cases", nargs="+", choices=sorted(ALL_CASES), help="default: all of the log's kind")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    args = ap.parse_args()
    if args.list:
        for kind, cases in CASES_BY_KIND.items():
            for name, (what, _) in cases.items():
                print(f"{name:<28} {kind:<6} {what}")
        return 0
    if args.flight is None or args.workdir is None:
        ap.error("FLIGHT and WORKDIR are required")
    log_kind = flight_kind(args.flight)
    wrong = [c for c in args.cases or () if c not in CASES_BY_KIND[log_kind]]
    if wrong:
        ap.error(f"{', '.join(wrong)}: not a case for a {log_kind} log (see --list)")
    args.cases = args.cases or list(CASES_BY_KIND[log_kind])
    if log_kind == "euroc":
        short = [
            f"{p.relative_to(args.flight)} has {n - 1} rows, the cases need {need}"
            for p, need in ((args.flight / f"mav0/{stream}/data.csv", need) for stream, need in NEED_ROWS)
            if p.exists() and (n := len(_lines(p))) - 1 < need
        ]
        if short:
            ap.error(f"{args.flight}: too short a flight ({'; '.join(short)}): simulate one of 8 s or more")
    print(
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.machine()}, "
        f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; flight {args.flight}\n"
    )
    print("| case | broken | outcome | first message |\n|---|---|---|---|")
    counts: dict[str, int] = {}
    for name in args.cases:
        kind, message = run_case(name, args.flight, args.workdir)
        counts[kind] = counts.get(kind, 0) + 1
        print(f"| {name} | {ALL_CASES[name][0]} | {kind} | {message[:200]} |", flush=True)
    print("\n" + ", ".join(f"{k}: {v}" for k, v in sorted(counts.items())))
    return 1 if counts.get("traceback") else 0


if __name__ == "__main__":
    sys.exit(main())
