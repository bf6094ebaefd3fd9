"""Simulated warehouses and flights: where the codes are, how the drone flies, what goes wrong.

A `Scenario` is everything `simulate()` needs: the world (floor grid, load codes), the cameras,
the trajectory, the IMU noise, the photometric effects and the floor-camera blackouts.
Scenarios: "default", "gimbaled", "oblique", "paper_a5" (see each builder's docstring).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

from fusion.camera import DISTORTION_MODELS, CameraModel
from fusion.conventions import R_BODY_FLOORCAM, R_BODY_FRONTCAM, load_payload
from fusion.errors import CameraModelError, SimulationError
from fusion.geometry import make_T
from fusion.log import ImuNoise
from fusion.qr.symbol import SIM_ECC
from fusion.sim.placement import true_code_poses
from fusion.sim.render import PlacedCode, RenderEffects, placed_floor_codes
from fusion.sim.trajectory import KeyframeTrajectory, survey_keyframes
from fusion.world import Layout, LoadCode, World

SCENARIOS = ("default", "gimbaled", "oblique", "paper_a5")
RESOLUTIONS = {"640x480": (640, 480), "1280x720": (1280, 720)}

# Focal length (px) of both cameras at 640x480 (60 deg horizontal field of view).  zxing-cpp
# decodes our renders down to about 2.1 px per module, so a 0.20 m version-1 floor code (9.5 mm
# modules) reads up to about 2.5 m above the floor, and a 0.15 m load code from up to 1.6 m.
FOCAL_640_PX = 550.0
GROUND_Z_M = 0.15  # body height standing on the floor (landing gear)
MAX_SURVEY_S = 4 * 3600.0  # the repeating survey is built up to this length


@dataclass
class Scenario:
    """A warehouse, a drone and a flight."""

    name: str
    layout: Layout
    cameras: dict[str, CameraModel]  # "cam0" floor, "cam1" front
    trajectory: KeyframeTrajectory
    duration_s: float
    blackouts: list[tuple[float, float, str]] = field(default_factory=list)  # (t0_s, t1_s, kind)
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    imu_rate_hz: float = 200.0
    velocity_rate_hz: float = 30.0
    velocity_noise_m_s: float = 0.05
    noise_sigma_dn: float = 2.0
    gain_swing: float = 0.15  # exposure gain 1 +- this, slowly varying
    exposure_s: float = 0.008  # motion blur = image motion during the exposure
    occluders: list = field(default_factory=list)  # axis-aligned boxes (lo, hi) in W: racks
    floor_ecc: str = SIM_ECC  # floor codes' error-correction level (fusion.qr.symbol)
    readout_s: float = 0.0  # rolling shutter: whole-frame readout time of every camera (0: global)

    def apply_readout(self) -> None:
        """Give every camera the line delay of `readout_s` (stamp at the first row)."""
        if not (math.isfinite(self.readout_s) and self.readout_s >= 0.0):
            raise SimulationError(
                f"readout time must be a non-negative number of seconds, got {self.readout_s!r}"
            )
        for cam in self.cameras.values():
            cam.line_delay_s = self.readout_s / cam.height

    photometric: dict = field(default_factory=dict)  # extra RenderEffects fields (CameraOptions)

    def codes(self) -> list[PlacedCode]:
        """Every code to render: floor grid and load codes."""
        w = self.layout.world
        out = placed_floor_codes(self.layout.floor_codes_xy, w.payload_unit_m, w.floor_side_m, self.floor_ecc)
        if self.layout.floor_offsets is not None:  # codes stuck down off their nominal poses
            for code, T in zip(out, self.floor_codes_true_T()):
                code.T_world_symbol = T
        out += [PlacedCode(load_payload(l.id), l.T_world_symbol, w.load_side_m) for l in self.layout.loads]
        return out

    def floor_codes_true_T(self) -> np.ndarray:
        """(N, 4, 4) where the floor codes really lie (nominal + Layout.floor_offsets)."""
        w = self.layout.world
        xy = np.asarray(self.layout.floor_codes_xy, float).reshape(-1, 2) * w.payload_unit_m
        off = self.layout.floor_offsets if self.layout.floor_offsets is not None else np.zeros((len(xy), 3))
        return true_code_poses(xy, off)

    def effects(
        self, camera_name: str, t_s: float, blur_px: float = 0.0, blur_angle_rad: float = 0.0
    ) -> RenderEffects:
        """Photometric effects of one frame (blur measured by the caller)."""
        phase = 0.7 if camera_name == "cam1" else 0.0
        gain = 1.0 + self.gain_swing * (
            0.7 * math.sin(2 * math.pi * t_s / 17.0 + phase)
            + 0.3 * math.sin(2 * math.pi * t_s / 5.3 + 2 * phase)
        )
        blackout = None
        if camera_name == "cam0":
            for t0, t1, kind in self.blackouts:
                if t0 <= t_s <= t1:
                    blackout = kind
        extra = dict(self.photometric)
        gain *= extra.pop("gain", 1.0)
        return RenderEffects(self.noise_sigma_dn, gain, blur_px, blur_angle_rad, blackout, **extra)


def make_cameras(resolution=(640, 480), mount: str = "body_fixed") -> dict[str, CameraModel]:
    """Floor (cam0) and front (cam1) cameras at `resolution`; focal length scales with the width
    so the field of view stays 60 deg horizontally."""
    w, h = resolution
    f = FOCAL_640_PX * w / 640.0
    s = w / 640.0
    floor = CameraModel(
        w,
        h,
        f,
        f * 1.0005,
        w / 2 + 1.3 * s,
        h / 2 - 0.8 * s,
        distortion=np.array([-0.05, 0.012, 4e-4, -3e-4]),
        T_body_cam=make_T(R_BODY_FLOORCAM, np.array([0.05, 0.0, -0.06])),
        mount=mount,
    )
    front = CameraModel(
        w,
        h,
        f,
        f * 0.9995,
        w / 2 - 1.8 * s,
        h / 2 + 2.6 * s,
        distortion=np.array([-0.07, 0.02, -5e-4, 4e-4]),
        T_body_cam=make_T(R_BODY_FRONTCAM, np.array([0.12, 0.0, 0.0])),
        mount=mount,
    )
    return {"cam0": floor, "cam1": front}


# ============================================================================ camera options


CAMERA_EFFECT_PRESETS = ("none", "realistic")


@dataclass
class CameraOptions:
    """How the simulated cameras differ from the scenario's (`fusion simulate` options).

    Photometric (fusion.sim.render.RenderEffects): `noise_dn` read noise (None: the scenario's
    2 DN), `shot_noise_dn`, `jpeg_quality`, `defocus_px`, `vignetting`, `overexposure` (exposure
    gain on top of the scenario's slow swing; above 1 whites clip), `contrast`, `glare_fraction`,
    `occlusion_fraction`; `exposure_s` (None: the scenario's 8 ms): motion blur is the image
    motion during it.  Geometric: `focal_scale` multiplies both cameras' focal lengths (a
    narrower or wider lens), `distortion` (four coefficients: k1, k2, p1, p2, or k1..k4 with
    `distortion_model` "equidistant") replaces both cameras' coefficients (None: the scenario's),
    `distortion_model` both cameras' model (None: the scenario's, radial-tangential; a model
    without coefficients starts from zero distortion).  Resolution is simulate()'s own argument."""

    noise_dn: float | None = None
    shot_noise_dn: float = 0.0
    jpeg_quality: int | None = None
    defocus_px: float = 0.0
    vignetting: float = 0.0
    overexposure: float = 1.0
    contrast: float = 1.0
    glare_fraction: float = 0.0
    occlusion_fraction: float = 0.0
    exposure_s: float | None = None
    focal_scale: float = 1.0
    distortion: tuple[float, float, float, float] | None = None
    distortion_model: str | None = None

    def __post_init__(self):
        if not (self.focal_scale > 0 and math.isfinite(self.focal_scale)):
            raise SimulationError(f"focal scale must be positive, got {self.focal_scale}")
        if self.exposure_s is not None and not (0 <= self.exposure_s < 1.0):
            raise SimulationError(f"exposure must be in [0, 1) s, got {self.exposure_s}")
        if self.distortion is not None and len(self.distortion) != 4:
            raise SimulationError("distortion: four coefficients k1, k2, p1, p2 (equidistant: k1..k4)")
        if self.distortion_model is not None and self.distortion_model not in DISTORTION_MODELS:
            raise SimulationError(
                f"unknown distortion model {self.distortion_model!r}; "
                f"expected one of {sorted(DISTORTION_MODELS)}"
            )
        RenderEffects(**self.render_fields())  # validates the photometric values

    def render_fields(self) -> dict:
        """The RenderEffects fields these options set (besides the scenario's noise and blur)."""
        return dict(
            shot_noise_dn=self.shot_noise_dn,
            jpeg_quality=self.jpeg_quality,
            defocus_px=self.defocus_px,
            vignetting=self.vignetting,
            gain=self.overexposure,
            contrast=self.contrast,
            glare_fraction=self.glare_fraction,
            occlusion_fraction=self.occlusion_fraction,
        )

    @classmethod
    def preset(cls, name: str, **overrides) -> CameraOptions:
        """`none` (the scenario's cameras) or `realistic`: JPEG quality 80, read noise 4 DN with
        shot noise, a 20 ms exposure (motion blur of several px at the survey's speeds) and 30 %
        vignetting; `overrides` (fields not None) replace the preset's values."""
        if name not in CAMERA_EFFECT_PRESETS:
            raise SimulationError(
                f"unknown camera-effects preset {name!r}; expected one of {CAMERA_EFFECT_PRESETS}"
            )
        base = cls()
        if name == "realistic":
            base = cls(
                noise_dn=REALISTIC_NOISE_DN,
                shot_noise_dn=REALISTIC_SHOT_NOISE_DN,
                jpeg_quality=REALISTIC_JPEG_QUALITY,
                exposure_s=REALISTIC_EXPOSURE_S,
                vignetting=REALISTIC_VIGNETTING,
            )
        names = {f.name for f in fields(cls)}
        bad = set(overrides) - names
        if bad:
            raise SimulationError(f"unknown camera options {sorted(bad)}")
        return replace(base, **{k: v for k, v in overrides.items() if v is not None})


REALISTIC_JPEG_QUALITY = 80
REALISTIC_NOISE_DN = 4.0
REALISTIC_SHOT_NOISE_DN = 0.02  # 2 DN at mid grey, 2.1 DN on white paper
REALISTIC_EXPOSURE_S = 0.020
REALISTIC_VIGNETTING = 0.3


def apply_camera_options(sc: Scenario, options: CameraOptions) -> Scenario:
    """`sc` with its cameras and photometric effects changed as `options` say (in place)."""
    for cam in sc.cameras.values():
        if options.focal_scale != 1.0:
            cam.fu *= options.focal_scale
            cam.fv *= options.focal_scale
        if (
            options.distortion_model is not None
            and DISTORTION_MODELS[options.distortion_model] != cam.distortion_model
        ):
            cam.distortion_model = DISTORTION_MODELS[options.distortion_model]
            cam.distortion = np.zeros(4)  # the other model's coefficients mean something else
        if options.distortion is not None:
            cam.distortion = np.asarray(options.distortion, dtype=float)
        if options.distortion is not None or options.distortion_model is not None:
            try:
                cam.check_lens("--distortion")
            except CameraModelError as e:
                raise SimulationError(str(e)) from None
    if options.noise_dn is not None:
        sc.noise_sigma_dn = float(options.noise_dn)
    if options.exposure_s is not None:
        sc.exposure_s = float(options.exposure_s)
    defaults = {f.name: f.default for f in fields(RenderEffects)}
    sc.photometric = {k: v for k, v in options.render_fields().items() if v != defaults[k]}
    return sc


# ============================================================================ default / gimbaled


OBLIQUE_YAW_RAD = 0.4
"""The "oblique" scenario's turn from square to the rack at each aisle waypoint, alternately
+ and - (23 deg): its front camera sees the load codes at an angle."""


def _default(
    name: str, resolution, mount: str, min_duration_s: float | None = None, oblique_rad: float = 0.0
) -> Scenario:
    """A 10 m x 7 m warehouse, one double-sided rack between two aisles, a 60 s survey.

    Floor: 0.20 m codes on a 1 m grid, x = 0..10, y = 0..7, none under the rack (y = 3, 4 for
    x = 1..9).  Rack: faces at y = 2.7 (normal -y, ids "P-cc-l") and y = 4.3 (normal +y, ids
    "Q-cc-l"), columns at x = 1.5, 3.5, 5.5, 7.5, levels l = 1, 2, 3 at z = 0.7, 1.4, 2.1 m;
    0.15 m load codes.  Flight: take-off, aisle 1 (y = 1.5, facing the P face 1.2 m away) at 1.4 m
    with hovers at each column, back at 2.1 m, a high pass at 2.6 m along x = 0.5 to aisle 2
    (y = 5.5, a 180 deg yaw turn), aisle 2 at 1.6 m and low at 0.9 m, climb.  Floor-camera
    blackouts of 0.5, 1, 2 and 5 s (shadow, glare, torn, shadow) where floor codes are in view.

    Longer flights (`min_duration_s` beyond one lap): the survey repeats, each lap returning
    along x = 0.5 to aisle 1 and flying the same passes with the same four blackouts at the same
    places, so a 10-minute flight is eight or nine laps of the same warehouse.

    `oblique_rad` (the "oblique" scenario): the same survey with the drone turned alternately by
    +- that yaw from square to the rack at each aisle waypoint (the high pass between the aisles
    as flown), so the front camera sees the codes at an angle."""
    # laid exactly on the grid (Layout.floor_offsets: not)
    world = World(0.20, 1.0, 0.15, (0.0, 10.0), (0.0, 7.0), placement_sigma_m=0.0, placement_sigma_deg=0.0)
    floor = [(x, y) for x in range(0, 11) for y in range(0, 8) if not (y in (3, 4) and 1 <= x <= 9)]
    loads = []
    for col, x in enumerate([1.5, 3.5, 5.5, 7.5], start=1):
        for level, z in enumerate([0.7, 1.4, 2.1], start=1):
            loads.append(LoadCode(f"P-{col:02d}-{level}", (x, 2.7, z), -math.pi / 2))
            loads.append(LoadCode(f"Q-{col:02d}-{level}", (x, 4.3, z), math.pi / 2))
    layout = Layout(world, np.array(floor, dtype=float), loads)
    up = math.pi / 2
    g = GROUND_Z_M
    wps = [
        (0.5, 1.5, g, up, 0.8),
        (0.5, 1.5, 1.4, up, 0.4),
        (1.5, 1.5, 1.4, up, 0.8),
        (3.5, 1.5, 1.4, up, 0.8),
        (5.5, 1.5, 1.4, up, 0.8),
        (7.5, 1.5, 1.4, up, 0.8),
        (7.5, 1.5, 2.1, up, 0.5),
        (5.5, 1.4, 2.1, up, 0.5),
        (3.5, 1.6, 2.1, up, 0.5),
        (1.5, 1.5, 2.1, up, 0.3),
        (0.5, 2.0, 2.6, up + 0.4),
        (0.5, 4.5, 2.6, up + math.pi / 2),
        (0.6, 5.5, 1.6, 3 * math.pi / 2, 0.5),
        (2.5, 5.5, 1.6, 3 * math.pi / 2, 0.6),
        (4.5, 5.4, 1.6, 3 * math.pi / 2, 0.6),
        (6.5, 5.5, 1.6, 3 * math.pi / 2, 0.6),
        (8.0, 5.6, 0.9, 3 * math.pi / 2, 0.5),
        (5.5, 5.5, 0.9, 3 * math.pi / 2 + 0.3, 0.3),
        (3.0, 5.5, 1.3, 3 * math.pi / 2),
        (1.5, 5.0, 2.0, 3 * math.pi / 2 - 0.5),
    ]
    if oblique_rad:
        aisle = [i for i in range(2, len(wps)) if i not in (10, 11)]  # not the high pass
        for n, i in enumerate(aisle):
            x, y, z, yaw, *rest = wps[i]
            wps[i] = (x, y, z, yaw + (oblique_rad if n % 2 == 0 else -oblique_rad), *rest)
    lap = wps[2:]  # from the first hover in aisle 1 to the end
    all_wps = list(wps)
    if min_duration_s is not None and not (math.isfinite(min_duration_s) and min_duration_s <= MAX_SURVEY_S):
        min_duration_s = None  # simulate() refuses it with a clear message
    while True:
        traj = KeyframeTrajectory(survey_keyframes(all_wps, speed_m_s=0.55, yaw_rate_rad_s=0.5))
        if min_duration_s is None or traj.duration_s >= min_duration_s:
            break
        k = (len(all_wps) - len(wps)) // (len(lap) + 2) + 1
        turn = 2.0 * math.pi * k  # keep yaw continuous: each lap turns the same way
        all_wps += [(0.5, 5.0, 2.0, all_wps[-1][3]), (0.5, 1.5, 1.4, up + turn, 0.4)]
        all_wps += [(x, y, z, yaw + turn, *rest) for x, y, z, yaw, *rest in lap]
    if traj.duration_s < 60.0:
        raise SimulationError(f"scenario {name}: trajectory only {traj.duration_s:.1f} s")
    lap_blackouts = [
        (9.0, 9.5, "shadow"),
        (17.0, 18.0, "glare"),
        (27.0, 29.0, "torn"),
        (40.0, 45.0, "shadow"),
    ]
    # the same blackouts at the same places of every lap: shift by the arrival times at the
    # lap's first hover (1.5, 1.5, 1.4)
    arrivals = [
        kf.t_s
        for i, kf in enumerate(traj.keyframes)
        if np.allclose(kf.p_world, (1.5, 1.5, 1.4))
        and not np.allclose(traj.keyframes[i - 1].p_world, (1.5, 1.5, 1.4))
    ]
    blackouts = [
        (a + arr - arrivals[0], b + arr - arrivals[0], kind)
        for arr in arrivals
        for a, b, kind in lap_blackouts
        if b + arr - arrivals[0] <= traj.duration_s
    ]
    rack = (np.array([1.0, 2.72, 0.0]), np.array([9.0, 4.28, 2.6]))  # just behind the faces
    duration = 60.0 if min_duration_s is None or min_duration_s <= 60.0 else traj.duration_s
    return Scenario(
        name, layout, make_cameras(resolution, mount), traj, duration, blackouts, occluders=[rack]
    )


# ============================================================================ paper Table A5

# Table A5 of Kang & Jung (2024), "Real Position (a)", cm.  The table prints z = 681.17 and 682.70
# for QR 9 and QR 10 with y = 190.90 and 180.30; every other code lies in a row at y = 2.9, 5.0 or
# 6.8 m and below 2.9 m height, and QR 9 then sits right under QR 8 (x = 3.83 m, y = 6.75 m), so we
# read those two rows as y and z swapped: QR 9 = (387.40, 681.17, 190.90), QR 10 = (808.10,
# 682.70, 180.30).
PAPER_A5_CM = [
    (32.50, 285.30, 236.50),
    (32.50, 286.40, 126.40),
    (823.46, 291.40, 75.60),
    (399.20, 291.20, 171.31),
    (27.00, 500.10, 82.40),
    (604.00, 498.20, 73.54),
    (26.50, 683.80, 78.10),
    (382.90, 675.10, 286.30),
    (387.40, 681.17, 190.90),
    (808.10, 682.70, 180.30),
]


def _paper_a5(name: str, resolution, mount: str) -> Scenario:
    """The ten load codes of the paper's Table A5, each visited and hovered in front of.

    Each code hangs on a face whose outward normal is world -y (the codes form rows at y = 2.9,
    5.0 and 6.8 m).  The drone hovers at the code's x and height (the paper's MatchedMapping
    case, assumption 8: front camera perpendicular to the code, centres aligned), facing +y, at
    the largest y on the 0.5 m floor grid that is at least 0.9 m in front of the face (0.9-1.4 m).
    Floor: 0.25 m codes on a 0.5 m grid (payload_unit_m = 0.5), x = -1..9.5, y = 0..7 m, so that
    a code is in full view of the floor camera at the lowest hover (0.74 m, 0.8 m x 0.6 m
    footprint) and still has 2.3 px modules at the highest (2.86 m).  Load codes 0.15 m.  Flight:
    take-off, the codes in table order with a 2.5 s hover each, landing; about 100 s.  Blackouts
    on the floor camera during three transits (0.5, 1, 2 s)."""
    # laid exactly on the grid (Layout.floor_offsets: not)
    world = World(0.25, 0.5, 0.15, (-1.0, 9.5), (0.0, 7.0), placement_sigma_m=0.0, placement_sigma_deg=0.0)
    floor = [(i, j) for i in range(-2, 20) for j in range(0, 15)]
    loads = [
        LoadCode(f"QR{k + 1}", (x / 100, y / 100, z / 100), -math.pi / 2)
        for k, (x, y, z) in enumerate(PAPER_A5_CM)
    ]
    layout = Layout(world, np.array(floor, dtype=float), loads)
    up = math.pi / 2
    g = GROUND_Z_M
    wps = [(0.5, 1.0, g, up, 0.8)]
    for l in loads:
        x, y, z = l.p_world
        y_hover = math.floor((y - 0.9) / 0.5) * 0.5
        wps.append((x, y_hover, z, up, 2.5))
    wps.append((wps[-1][0], wps[-1][1], g, up, 0.5))
    traj = KeyframeTrajectory(survey_keyframes(wps, speed_m_s=0.6, yaw_rate_rad_s=0.5))
    kf = traj.keyframes
    # blackouts in the middle of three transits (between the hover keyframes)
    mids = [0.5 * (kf[i].t_s + kf[i + 1].t_s) for i in (4, 8, 12)]
    blackouts = [
        (mids[0] - 0.25, mids[0] + 0.25, "glare"),
        (mids[1] - 0.5, mids[1] + 0.5, "torn"),
        (mids[2] - 1.0, mids[2] + 1.0, "shadow"),
    ]
    return Scenario(name, layout, make_cameras(resolution, mount), traj, traj.duration_s, blackouts)


def build_scenario(
    name: str = "default", resolution=(640, 480), min_duration_s: float | None = None
) -> Scenario:
    """The scenario called `name` at camera `resolution` (width, height), flying at least
    `min_duration_s` where the scenario can repeat (default, gimbaled, oblique); raises
    SimulationError."""
    if isinstance(resolution, str):
        if resolution not in RESOLUTIONS:
            raise SimulationError(f"unknown resolution {resolution!r}; expected one of {list(RESOLUTIONS)}")
        resolution = RESOLUTIONS[resolution]
    w, h = (int(v) for v in resolution)
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise SimulationError(f"bad camera resolution {w}x{h}")
    if name == "default":
        return _default(name, (w, h), "body_fixed", min_duration_s)
    if name == "gimbaled":
        return _default(name, (w, h), "gimbaled", min_duration_s)
    if name == "oblique":
        return _default(name, (w, h), "body_fixed", min_duration_s, oblique_rad=OBLIQUE_YAW_RAD)
    if name == "paper_a5":
        return _paper_a5(name, (w, h), "body_fixed")
    raise SimulationError(f"unknown scenario {name!r}; expected one of {SCENARIOS}")
