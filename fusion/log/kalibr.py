"""Kalibr calibration files: `camchain-imucam.yaml` (cameras + camera-IMU extrinsics) and
`imu.yaml` (IMU noise densities).

camchain-imucam.yaml (Kalibr wiki "Yaml formats"):

    cam0:
      camera_model: pinhole            # only pinhole is supported
      intrinsics: [fu, fv, pu, pv]
      distortion_model: radtan         # radial-tangential [k1, k2, r1, r2] (OpenCV's k3 may
      distortion_coeffs: [k1, k2, r1, r2]  # follow), or equidistant [k1, k2, k3, k4] (pinhole-equi)
      resolution: [w, h]
      T_cam_imu: 4x4 rows              # maps IMU-frame points into the camera frame
      timeshift_cam_imu: 0.0           # s;  t_imu = t_cam + timeshift_cam_imu
      line_delay: 0.0                  # s per row, rolling shutter (optional; stamp = row 0)
      T_BS_sigma_deg: 0.1              # ours, optional: how well T_cam_imu is known, 1 sigma per
      T_BS_sigma_m: 0.002              #   axis (as in sensor.yaml; absent: 0.1 deg / 2 mm)
      rostopic: /cam0/image_raw
    cam1: ...

Kalibr's cam0 is our floor camera, cam1 the front camera (CameraRole).  The body frame is the
IMU frame rotated by `T_body_imu` (identity unless the IMU is mounted otherwise, e.g. PX4's FRD),
so T_body_cam = T_body_imu * inv(T_cam_imu).  Extra keys we write (`mount`, `rate_hz`,
`stamp_row` for a camera stamped at its middle row, `T_BS_sigma_deg` / `T_BS_sigma_m` when
stated, `intrinsics_sigma` [fu, fv, cu, cv] px as Kalibr's results-cam.txt reports them after
"+-") are ignored by Kalibr.

imu.yaml: either Kalibr's input format (flat keys) or its output (`imu0:` block), keys
accelerometer_noise_density, accelerometer_random_walk, gyroscope_noise_density,
gyroscope_random_walk, rostopic, update_rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.camera import (
    DISTORTION_MODELS,
    MOUNTS,
    CameraModel,
    StampRow,
    check_intrinsics,
    coefficient_count,
    near_miss,
    stated_intrinsics_sigma,
    stated_mount_sigmas,
)
from fusion.errors import CameraModelError, LogError
from fusion.fileio import dump_yaml, load_yaml, strict_float
from fusion.geometry import inv_T, is_rigid_transform
from fusion.log.euroc import ImuNoise
from fusion.types import CameraRole

KALIBR_DISTORTION_MODELS = tuple(DISTORTION_MODELS)
NOISE_KEYS = (
    "gyroscope_noise_density",
    "gyroscope_random_walk",
    "accelerometer_noise_density",
    "accelerometer_random_walk",
)


@dataclass
class KalibrCamera:
    """One `camN` block: the camera model (T_body_cam already composed), its topic and the
    camera-to-IMU clock shift in ns (t_imu = t_cam + timeshift_ns)."""

    key: str  # "cam0", "cam1", ...
    camera: CameraModel
    rostopic: str | None
    timeshift_ns: int


@dataclass
class KalibrImu:
    noise: ImuNoise
    rostopic: str | None
    rate_hz: float | None


def _matrix(value, where: str) -> np.ndarray:
    try:
        T = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise LogError(f"{where}: not a 4x4 matrix of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise LogError(f"{where}: not a 4x4 matrix of finite numbers")
    if not is_rigid_transform(T, atol=1e-5):
        raise LogError(f"{where}: not a rigid transform")
    return T


def _numbers(value, n: int, where: str) -> list[float]:
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise LogError(f"{where}: expected a list of {n} numbers") from None
    if len(out) != n or not all(math.isfinite(v) for v in out):
        raise LogError(f"{where}: expected a list of {n} finite numbers")
    return out


CAMCHAIN_KEYS = (
    "camera_model",
    "intrinsics",
    "distortion_model",
    "distortion_coeffs",
    "resolution",
    "T_cam_imu",
    "timeshift_cam_imu",
    "rostopic",
    "cam_overlaps",
    "T_cn_cnm1",
    "line_delay",
    "stamp_row",
    "mount",
    "intrinsics_sigma",
    "T_BS_sigma_deg",
    "T_BS_sigma_m",
    "rate_hz",
)
"""A camchain camera block's keys: Kalibr's and the ones this project adds (write_camchain)."""


def _refuse_near_misses(block: dict, where: str) -> None:
    """LogError for a key of a camera block that misspells a known one (`distortion_coefs`): its
    default had been used silently (no distortion: PnP 0.07 -> 4.2 cm, health ok; second audit).
    Other unknown keys (other tools' additions) are left alone."""
    for key in block:
        if key in CAMCHAIN_KEYS:
            continue
        close = near_miss(str(key), CAMCHAIN_KEYS)
        if close:
            raise LogError(f"{where}: unknown key {str(key)[:60]!r} (did you mean {close!r}?)")


def read_camchain(path: Path, T_body_imu: np.ndarray | None = None) -> dict[str, KalibrCamera]:
    """Parse a Kalibr camchain(-imucam).yaml; returns {"cam0": KalibrCamera, ...}.
    Raises LogError naming the file and key."""
    path = Path(path)
    data = load_yaml(path, LogError)
    T_bi = np.eye(4) if T_body_imu is None else np.asarray(T_body_imu, float)
    out = {}
    for key in sorted(k for k in data if str(k).startswith("cam")):
        block = data[key]
        where = f"{path}: {key}"
        if not isinstance(block, dict):
            raise LogError(f"{where}: expected a mapping")
        _refuse_near_misses(block, where)
        model = block.get("camera_model", "pinhole")
        if model != "pinhole":
            raise LogError(f"{where}.camera_model: {model!r} is not supported (pinhole only)")
        dmodel = block.get("distortion_model", "radtan")
        if dmodel not in KALIBR_DISTORTION_MODELS:
            raise LogError(
                f"{where}.distortion_model: {dmodel!r} is not supported "
                f"(one of {', '.join(KALIBR_DISTORTION_MODELS)})"
            )
        for need in ("intrinsics", "resolution"):
            if need not in block:
                raise LogError(f"{where}: missing key '{need}'")
        intr = _numbers(block["intrinsics"], 4, f"{where}.intrinsics")
        res = _numbers(block["resolution"], 2, f"{where}.resolution")
        coeffs = block.get("distortion_coeffs", [0, 0, 0, 0])
        # radtan: Kalibr's four, or OpenCV's five (k3 last; an extension Kalibr does not write)
        n_coeffs = coefficient_count(dmodel, coeffs)
        dist = _numbers(coeffs, n_coeffs, f"{where}.distortion_coeffs")
        if "T_cam_imu" not in block:
            raise LogError(
                f"{where}: missing key 'T_cam_imu' (a camchain-imucam.yaml from "
                "kalibr_calibrate_imu_camera is needed for the camera-IMU extrinsics)"
            )
        T_cam_imu = _matrix(block["T_cam_imu"], f"{where}.T_cam_imu")
        try:
            shift_s = float(block.get("timeshift_cam_imu", 0.0))
        except (TypeError, ValueError):
            raise LogError(f"{where}.timeshift_cam_imu: not a number") from None
        if not math.isfinite(shift_s):
            raise LogError(f"{where}.timeshift_cam_imu: not finite")
        mount = block.get("mount", MOUNTS[0])
        if mount not in MOUNTS:
            raise LogError(f"{where}.mount: {mount!r} is not one of {MOUNTS}")
        check_intrinsics(res, intr, where, LogError)
        fu, fv, cu, cv = intr
        try:
            line_delay = float(block.get("line_delay", 0.0))
        except (TypeError, ValueError):
            raise LogError(f"{where}.line_delay: not a number") from None
        try:
            rs = {"line_delay_s": line_delay, "stamp_row": block.get("stamp_row", StampRow.FIRST.value)}
            CameraModel(int(res[0]), int(res[1]), 1.0, 1.0, 0.0, 0.0, **rs)
        except CameraModelError as e:
            raise LogError(f"{where}.line_delay/stamp_row: {e}") from None
        try:
            sigmas = stated_mount_sigmas(block, where)
            intr_sigma = stated_intrinsics_sigma(
                block.get("intrinsics_sigma"), fu, fv, str(path), f"{key}.intrinsics_sigma"
            )
        except CameraModelError as e:
            raise LogError(str(e)) from None
        cam = CameraModel(
            int(res[0]),
            int(res[1]),
            fu,
            fv,
            cu,
            cv,
            distortion=np.array(dist[:4]),
            k3=dist[4] if n_coeffs == 5 else 0.0,
            distortion_model=dmodel,
            T_body_cam=T_bi @ inv_T(T_cam_imu),
            rate_hz=strict_float(block.get("rate_hz", 30.0), f"{where}.rate_hz", LogError, positive=True),
            mount=mount,
            intrinsics_sigma_px=intr_sigma,
            mount_sigma_deg=sigmas.get("T_BS_sigma_deg"),
            mount_sigma_m=sigmas.get("T_BS_sigma_m"),
            **rs,
        )
        try:
            cam.check_lens(where)
        except CameraModelError as e:
            raise LogError(str(e)) from None
        topic = block.get("rostopic")
        out[str(key)] = KalibrCamera(str(key), cam, str(topic) if topic else None, int(round(shift_s * 1e9)))
    if not out:
        raise LogError(f"{path}: no 'cam0' block (not a Kalibr camchain)")
    return out


def write_camchain(
    path: Path,
    cameras: dict[str, CameraModel],
    topics: dict[str, str],
    T_body_imu: np.ndarray | None = None,
    timeshift_ns: dict[str, int] | None = None,
) -> None:
    """Write Kalibr camchain-imucam.yaml for cameras {"cam0": model, ...}."""
    T_bi = np.eye(4) if T_body_imu is None else np.asarray(T_body_imu, float)
    data = {}
    for key, cam in sorted(cameras.items()):
        T_cam_imu = inv_T(cam.T_body_cam) @ T_bi  # T_body_cam = T_body_imu * T_imu_cam
        block = {
            "camera_model": "pinhole",
            "intrinsics": [float(cam.fu), float(cam.fv), float(cam.cu), float(cam.cv)],
            "distortion_model": "equidistant" if cam.equidistant else "radtan",
            "distortion_coeffs": [float(v) for v in cam.distortion] + ([cam.k3] if cam.k3 else []),
            "resolution": [int(cam.width), int(cam.height)],
            "T_cam_imu": [[float(v) for v in row] for row in T_cam_imu],
            "timeshift_cam_imu": float((timeshift_ns or {}).get(key, 0)) * 1e-9,
            "rostopic": topics.get(key, f"/{key}/image_raw"),
            "rate_hz": float(cam.rate_hz),
        }
        if cam.mount != MOUNTS[0]:
            block["mount"] = cam.mount
        if cam.intrinsics_sigma_px is not None:
            block["intrinsics_sigma"] = [float(v) for v in cam.intrinsics_sigma_px]
        # how well T_BS is known: written only when stated, as in sensor.yaml (without it the
        # reader takes the default 0.1 deg / 2 mm, and a simulated video or bag's load maps read
        # NEES 0.0 against the exact mount its sensor.yaml states)
        if cam.mount_sigma_deg is not None:
            block["T_BS_sigma_deg"] = float(cam.mount_sigma_deg)
        if cam.mount_sigma_m is not None:
            block["T_BS_sigma_m"] = float(cam.mount_sigma_m)
        if cam.rolling_shutter:
            block["line_delay"] = float(cam.line_delay_s)
            if cam.stamp_row != StampRow.FIRST:
                block["stamp_row"] = cam.stamp_row.value
        data[key] = block
    dump_yaml(data, path)


def read_imu_yaml(path: Path) -> KalibrImu:
    """Kalibr imu.yaml (flat input format or `imu0:` output block)."""
    path = Path(path)
    data = load_yaml(path, LogError)
    block = data.get("imu0", data) if isinstance(data.get("imu0"), dict) else data
    vals = {}
    for key in NOISE_KEYS:
        if key not in block:
            raise LogError(f"{path}: missing key '{key}'")
        try:
            vals[key] = float(block[key])
        except (TypeError, ValueError):
            raise LogError(f"{path}: '{key}' is not a number") from None
        if not (math.isfinite(vals[key]) and vals[key] > 0):
            raise LogError(f"{path}: '{key}' must be positive")
    rate = block.get("update_rate")
    try:
        rate = float(rate) if rate is not None else None
    except (TypeError, ValueError):
        raise LogError(f"{path}: 'update_rate' is not a number") from None
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise LogError(f"{path}: 'update_rate' must be positive, not {block.get('update_rate')!r}")
    topic = block.get("rostopic")
    return KalibrImu(ImuNoise(**vals), str(topic) if topic else None, rate)


def write_imu_yaml(path: Path, noise: ImuNoise, rate_hz: float, rostopic: str = "/imu0") -> None:
    data: dict[str, float | str] = {key: float(getattr(noise, key)) for key in NOISE_KEYS}
    data.update(rostopic=rostopic, update_rate=float(rate_hz))
    dump_yaml(data, path)


def role_of_kalibr_key(key: str) -> CameraRole | None:
    """Kalibr's cam0 / cam1 are our floor / front cameras."""
    try:
        return CameraRole(key)
    except ValueError:
        return None
