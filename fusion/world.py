"""The warehouse: floor QR codes on a grid, load QR codes on vertical faces (`world.yaml`).

`world.yaml` holds what an estimator may know in advance (the paper's assumptions 1, 6 and 9):

    floor_qr: {side_m: 0.20, payload_unit_m: 1.0,
               placement_sigma_m: 0.01, placement_sigma_deg: 1.0}  # optional: how exactly the
                                                    # codes were laid (0 and 0: exactly)
    load_qr:  {side_m: 0.15, side_sigma_m: 0.0003}     # optional: how exactly the labels
                                                    # were printed (absent: 0.2 % of the side)
    bounds_m: {x: [xmin, xmax], y: [ymin, ymax]}      # optional: the size of the space

Load code positions are what we map, so they are not in `world.yaml`; a simulated flight writes
them to `loads_groundtruth.csv`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from fusion.conventions import FloorPayload, floor_payload, symbol_corners_S
from fusion.errors import WorldError
from fusion.fileio import dump_yaml, load_yaml, strict_float, strict_floats
from fusion.geometry import R_world_loadsymbol, make_T, rot_z, transform_points


@dataclass(frozen=True)
class LoadCode:
    """A load QR code: id, symbol-centre position in W (m), heading of its face's outward normal (rad)."""

    id: str
    p_world: tuple[float, float, float]
    normal_yaw: float

    @property
    def T_world_symbol(self) -> np.ndarray:
        return make_T(R_world_loadsymbol(self.normal_yaw), np.asarray(self.p_world, dtype=float))


DEFAULT_LOAD_SIDE_SIGMA_REL = 0.002
"""A load label's printed side's relative error (1 sigma) when world.yaml does not state it: an
office printer's scale error, a few tenths of a percent (0.3 mm on a 15 cm label).  It moves the
mapped load along the camera's ray by as much, in every sighting (fusion.estimate.loadconsider).
A simulated flight states 0 (its codes are exact)."""

CODE_SIDE_RANGE_M = (0.01, 2.0)
"""Printed QR codes from a 1 cm label to a 2 m floor tile: a side outside this range in world.yaml
is a unit mistake (cm or mm for m), not a code: every metric output would scale with it."""


DEFAULT_PLACEMENT_SIGMA_M = 0.01
"""world.yaml's `placement_sigma_m` when absent: codes stuck down by hand, 1 cm per axis."""
DEFAULT_PLACEMENT_SIGMA_DEG = 1.0
"""world.yaml's `placement_sigma_deg` when absent."""


MAX_PLACEMENT_SIGMA_DEG = 30.0
"""world.yaml's floor_qr.placement_sigma_deg must be below this: a code turned by ~45 deg has its
edges on the other diagonal (PnP's edge-implied yaw then picks the wrong quarter turn)."""


UNCERTAINTY_KEYS = frozenset(
    {"floor_qr.placement_sigma_m", "floor_qr.placement_sigma_deg", "load_qr.side_sigma_m"}
)
"""world.yaml's statements of how exactly the codes were laid and printed: one flight's may
state them and another's not (then the defaults apply) for the same codes; they do not tell
warehouses apart (warehouse_differences)."""


def _flat(data: dict, prefix: str = "") -> dict[str, object]:
    """{"section.key": value} of a world.yaml mapping, nested mappings flattened."""
    out: dict[str, object] = {}
    for k, v in data.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, f"{name}."))
        else:
            out[name] = v
    return out


def warehouse_differences(a: dict, b: dict) -> tuple[list[str], list[str]]:
    """(keys in which two world.yaml mappings describe different warehouses, uncertainty keys
    in which they differ), each as sorted "section.key" names.  Every key but UNCERTAINTY_KEYS
    tells warehouses apart (codes' sizes, payload unit, bounds, and any key this version does
    not know, conservatively); a flight stating a print or placement sigma and one that does not
    (or another value) fly the same warehouse."""
    fa, fb = _flat(a), _flat(b)
    differ = sorted(k for k in set(fa) | set(fb) if fa.get(k) != fb.get(k))
    return [k for k in differ if k not in UNCERTAINTY_KEYS], [k for k in differ if k in UNCERTAINTY_KEYS]


@dataclass
class World:
    """What is known of the warehouse before flying."""

    floor_side_m: float = 0.20
    payload_unit_m: float = 1.0
    load_side_m: float = 0.15
    bounds_x_m: tuple[float, float] | None = None
    bounds_y_m: tuple[float, float] | None = None
    # how far floor codes lie off their payload's pose (1 sigma; fusion.estimate.asbuilt);
    # None: not stated in world.yaml (the estimator's defaults, 1 cm and 1 deg)
    placement_sigma_m: float | None = None
    placement_sigma_deg: float | None = None
    # how far a load label's printed side is off side_m (1 sigma, m; fusion.estimate.loadconsider);
    # None: not stated in world.yaml (DEFAULT_LOAD_SIDE_SIGMA_REL of the side)
    load_side_sigma_m: float | None = None

    def __post_init__(self):
        for name in ("floor_side_m", "payload_unit_m", "load_side_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise WorldError(f"world: {name} must be a positive number, got {v!r}")
        for name in ("placement_sigma_m", "placement_sigma_deg", "load_side_sigma_m"):
            v = getattr(self, name)
            if v is not None and (
                isinstance(v, bool) or not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0)
            ):
                key = "load_qr.side_sigma_m" if name == "load_side_sigma_m" else f"floor_qr.{name}"
                raise WorldError(f"world: {key} must be a number >= 0, got {v!r}")

    @property
    def load_side_sigma_rel(self) -> float:
        """The load labels' printed side's relative error (1 sigma): world.yaml's
        load_qr.side_sigma_m / side_m, or DEFAULT_LOAD_SIDE_SIGMA_REL when it is not stated."""
        if self.load_side_sigma_m is None:
            return DEFAULT_LOAD_SIDE_SIGMA_REL
        return self.load_side_sigma_m / self.load_side_m

    # ---------------------------------------------------------------- floor codes
    def floor_code_position(self, payload: FloorPayload) -> np.ndarray:
        """(3,) world position of a floor code's symbol centre (z = 0)."""
        return payload.position_m(self.payload_unit_m)

    def contains(self, p_world: np.ndarray, margin_m: float = 0.0) -> bool:
        """True if (x, y) lies inside the known bounds (always True when no bounds are set)."""
        x, y = float(p_world[0]), float(p_world[1])
        if self.bounds_x_m is not None and not (
            self.bounds_x_m[0] - margin_m <= x <= self.bounds_x_m[1] + margin_m
        ):
            return False
        if self.bounds_y_m is not None and not (
            self.bounds_y_m[0] - margin_m <= y <= self.bounds_y_m[1] + margin_m
        ):
            return False
        return True

    def floor_corners_world(self, centre_world: np.ndarray) -> np.ndarray:
        """(4, 3) world corners of a floor code (TL, TR, BR, BL): symbol axes = world axes."""
        return symbol_corners_S(self.floor_side_m) + np.asarray(centre_world, dtype=float)

    def load_corners_world(self, code: LoadCode) -> np.ndarray:
        """(4, 3) world corners of a load code (TL, TR, BR, BL)."""
        return transform_points(code.T_world_symbol, symbol_corners_S(self.load_side_m))

    # ---------------------------------------------------------------- world.yaml
    def to_yaml(self) -> dict:
        data: dict[str, dict[str, float | list[float]]] = {
            "floor_qr": {"side_m": float(self.floor_side_m), "payload_unit_m": float(self.payload_unit_m)},
            "load_qr": {"side_m": float(self.load_side_m)},
        }
        if self.load_side_sigma_m is not None:
            data["load_qr"]["side_sigma_m"] = float(self.load_side_sigma_m)
        for name in ("placement_sigma_m", "placement_sigma_deg"):
            if getattr(self, name) is not None:
                data["floor_qr"][name] = float(getattr(self, name))
        if self.bounds_x_m is not None and self.bounds_y_m is not None:
            data["bounds_m"] = {
                "x": [float(v) for v in self.bounds_x_m],
                "y": [float(v) for v in self.bounds_y_m],
            }
        return data

    @classmethod
    def from_yaml(cls, data: dict, source: str = "world.yaml") -> World:
        """Build from parsed world.yaml.  Numbers are parsed strictly (a bool or a string is not
        a number: `side_m: true` would otherwise read as 1 m); every error names the field."""
        _known_keys(data, WORLD_YAML_KEYS, "", source)
        floor = _section(data, "floor_qr", source, required=True)
        load = _section(data, "load_qr", source)
        _known_keys(floor, WORLD_YAML_KEYS["floor_qr"], "floor_qr.", source)
        _known_keys(load, WORLD_YAML_KEYS["load_qr"], "load_qr.", source)
        if "side_m" not in floor:
            raise WorldError(f"{source}: floor_qr.side_m is missing")
        floor_side_m = strict_float(floor["side_m"], f"{source}: floor_qr.side_m", WorldError, positive=True)
        payload_unit_m = strict_float(
            floor.get("payload_unit_m", 1.0),
            f"{source}: floor_qr.payload_unit_m",
            WorldError,
            positive=True,
        )
        placement = {
            name: strict_float(floor.get(name), f"{source}: floor_qr.{name}", WorldError, allow_none=True)
            for name in ("placement_sigma_m", "placement_sigma_deg")
        }
        for name, v in placement.items():
            if v is not None and v < 0:
                raise WorldError(f"{source}: floor_qr.{name} must be >= 0, got {v!r}")
        sm, sd = placement["placement_sigma_m"], placement["placement_sigma_deg"]
        if sm is not None and sm >= floor_side_m:
            raise WorldError(
                f"{source}: floor_qr.placement_sigma_m is {sm:g} m, a code's own side ({floor_side_m:g} m) "
                "or more: codes laid that loosely are not a grid (in metres: cm or mm given?)"
            )
        if sd is not None and sd >= MAX_PLACEMENT_SIGMA_DEG:
            raise WorldError(
                f"{source}: floor_qr.placement_sigma_deg is {sd:g} deg: a code turned that far reads as "
                f"another orientation (it must be below {MAX_PLACEMENT_SIGMA_DEG:g})"
            )
        load_side_m = strict_float(
            load.get("side_m", 0.15), f"{source}: load_qr.side_m", WorldError, positive=True
        )
        load_side_sigma_m = strict_float(
            load.get("side_sigma_m"), f"{source}: load_qr.side_sigma_m", WorldError, allow_none=True
        )
        if load_side_sigma_m is not None and not 0 <= load_side_sigma_m < load_side_m:
            raise WorldError(
                f"{source}: load_qr.side_sigma_m is {load_side_sigma_m:g} m: a print error must be "
                f">= 0 and below the side ({load_side_m:g} m; in metres: cm or mm given?)"
            )
        for key, side in (("floor_qr.side_m", floor_side_m), ("load_qr.side_m", load_side_m)):
            lo, hi = CODE_SIDE_RANGE_M
            if not lo <= side <= hi:
                raise WorldError(
                    f"{source}: {key} is {side:g} m: a QR code's side is {lo:g}-{hi:g} m; "
                    "world.yaml's lengths are in metres (cm or mm given?)"
                )
        bounds_m: dict[str, tuple[float, float]] = {}
        bounds = data.get("bounds_m")
        if bounds is not None:
            if not isinstance(bounds, dict):
                raise WorldError(f"{source}: bounds_m must be a mapping with x and y")
            _known_keys(bounds, WORLD_YAML_KEYS["bounds_m"], "bounds_m.", source)
            for axis in ("x", "y"):
                if axis not in bounds:
                    raise WorldError(f"{source}: bounds_m.{axis} is missing")
                lo, hi = strict_floats(bounds[axis], 2, f"{source}: bounds_m.{axis}", WorldError)
                if not lo < hi:
                    raise WorldError(
                        f"{source}: bounds_m.{axis} is [{lo:g}, {hi:g}]: the minimum "
                        "must come first and be below the maximum (reversed?)"
                    )
                bounds_m[axis] = (lo, hi)
        try:
            return cls(
                floor_side_m=floor_side_m,
                payload_unit_m=payload_unit_m,
                load_side_m=load_side_m,
                bounds_x_m=bounds_m.get("x"),
                bounds_y_m=bounds_m.get("y"),
                load_side_sigma_m=load_side_sigma_m,
                **placement,
            )
        except WorldError as e:
            raise WorldError(f"{source}: {e}") from None

    @classmethod
    def load(cls, path: Path) -> World:
        return cls.from_yaml(load_yaml(path, WorldError), str(path))

    def save(self, path: Path) -> None:
        dump_yaml(self.to_yaml(), path)


WORLD_YAML_KEYS: dict[str, tuple[str, ...]] = {
    "floor_qr": ("side_m", "payload_unit_m", "placement_sigma_m", "placement_sigma_deg"),
    "load_qr": ("side_m", "side_sigma_m"),
    "bounds_m": ("x", "y"),
}
"""world.yaml's sections and their keys: anything else is an error (a misspelt optional key,
`load_qr: {side_mm: 100}` or `payload_units_m`, had been ignored and its default used, unsaid)."""


def _known_keys(data: dict, known, prefix: str, source: str) -> None:
    """WorldError naming the first key of `data` not in `known` (with the known ones)."""
    for key in data:
        if key not in known:
            raise WorldError(
                f"{source}: unknown key {prefix}{str(key)[:60]} (known {prefix.rstrip('.') or 'keys'}: "
                f"{', '.join(known)})"
            )


def _section(data: dict, key: str, source: str, required: bool = False) -> dict:
    """A mapping-valued entry of world.yaml ({} when absent and optional)."""
    if key not in data or data[key] is None:
        if required:
            raise WorldError(f"{source}: {key} is missing")
        return {}
    value = data[key]
    if not isinstance(value, dict):
        raise WorldError(f"{source}: {key} must be a mapping, got {type(value).__name__}")
    return value


@dataclass
class Layout:
    """Where every code actually is: what the simulator renders and the evaluation compares to.

    `floor_codes`: (N, 2) payload coordinates (x, y) in payload units; `loads`: load codes;
    `floor_offsets`: (N, 3) where each floor code really lies off its payload's pose (dx m,
    dy m, dyaw rad; None: exactly on it)."""

    world: World
    floor_codes_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    loads: list[LoadCode] = field(default_factory=list)
    floor_offsets: np.ndarray | None = None

    def floor_centres_world(self) -> np.ndarray:
        """(N, 3) world positions of the floor codes' centres."""
        xy = np.asarray(self.floor_codes_xy, dtype=float) * self.world.payload_unit_m
        return np.column_stack([xy, np.zeros(len(xy))])


@dataclass(frozen=True)
class Placement:
    """How far floor codes may lie from their payload's pose (1 sigma per axis: x and y in m, yaw
    in rad): world.yaml's floor_qr.placement_sigma_m / _deg, the defaults where it says nothing.
    Used by the batch smoother's as-built codes (fusion.estimate.asbuilt) and by PnP's corner
    whitening (fusion.qr.pnp.whitening.floor_whitening)."""

    sigma_m: float = DEFAULT_PLACEMENT_SIGMA_M
    sigma_rad: float = math.radians(DEFAULT_PLACEMENT_SIGMA_DEG)

    @property
    def enabled(self) -> bool:
        """0 m and 0 deg: the payloads are exact (today's model)."""
        return self.sigma_m > 0 or self.sigma_rad > 0

    def covariance(self, code_id: str | None = None) -> np.ndarray:
        """(3, 3) covariance of a code's (x, y, yaw) about its payload's pose (any code)."""
        return np.diag(np.square([self.sigma_m, self.sigma_m, self.sigma_rad]))

    @classmethod
    def from_world(cls, world: World) -> Placement:
        sm = getattr(world, "placement_sigma_m", None)
        sd = getattr(world, "placement_sigma_deg", None)
        return cls(
            DEFAULT_PLACEMENT_SIGMA_M if sm is None else float(sm),
            math.radians(DEFAULT_PLACEMENT_SIGMA_DEG if sd is None else float(sd)),
        )


@dataclass(frozen=True)
class FloorLayout:
    """Where the floor codes lie, as far as the run knows: a merged map's (x, y, yaw) and its
    (3, 3) covariance per code id (`fusion map merge`, given to `fusion run --map`), and about
    its payload's pose by world.yaml's placement sigma (`default`) for every other code.  Like
    Placement, `enabled` and `covariance(code_id)`; `place` moves a floor sighting's world
    corners to the map's pose of its code."""

    default: Placement
    codes: dict = field(default_factory=dict)  # id -> ((3,) x m, y m, yaw rad; (3, 3) covariance)

    @property
    def enabled(self) -> bool:
        return self.default.enabled or bool(self.codes)

    def covariance(self, code_id: str | None = None) -> np.ndarray:
        if code_id is not None and code_id in self.codes:
            return np.asarray(self.codes[code_id][1], dtype=float)
        return self.default.covariance()

    def place(self, sighting):
        """`sighting` (fusion.qr.codes.FloorSighting) with its world corners and centre where the
        map puts its code (turned about the centre by the map's yaw), or as it is."""
        entry = self.codes.get(floor_payload(sighting.payload.x, sighting.payload.y))
        if entry is None:
            return sighting
        x, y, yaw = (float(v) for v in entry[0])
        c0 = np.asarray(sighting.centre_world, dtype=float)
        centre = np.array([x, y, float(c0[2])])
        corners = (np.asarray(sighting.corners_world, dtype=float) - c0) @ rot_z(yaw).T + centre
        return replace(sighting, centre_world=centre, corners_world=corners)
