"""Render grayscale camera images of QR codes through the full camera model.

Geometry is exact: every output pixel (u, v) looks along the ray the camera model projects there
(`CameraModel.undistort_normalized`, precomputed once per camera), and a code's texture is sampled
where that ray meets the code's plane (one plane-to-ray homography per code, one `cv2.remap`).
Anti-aliasing: each code's texture is taken from a mip level (2^k texels per module) chosen so that
one texel covers about one pixel or more, then sampled bilinearly; a step between a black and a
white texel therefore crosses mid-grey exactly at the module edge, so rendered edges are unbiased.

Pixel coordinates follow OpenCV: the centre of pixel (col, row) is at (u, v) = (col, row).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import symbol_corners_S
from fusion.errors import SimulationError
from fusion.geometry import inv_T
from fusion.qr.symbol import SIM_ECC, encode_symbol

QUIET_ZONE_MODULES = 4
BLACK_DN = 30.0  # printed black under nominal exposure
WHITE_DN = 220.0  # printed white (paper) under nominal exposure
BLACKOUT_KINDS = ("shadow", "glare", "torn")
_MAX_TEXELS_PER_MODULE = 16


# ============================================================================ codes


def code_texture(payload: str, ecc: str = SIM_ECC) -> np.ndarray:
    """(N, N) uint8 module bitmap of the QR symbol for `payload` (0 = dark, 255 = light), one pixel
    per module, cropped to the symbol (no quiet zone).  Row 0 is the symbol's top: finders sit at
    [0, 0] (top-left), [0, N-1] (top-right) and [N-1, 0] (bottom-left)."""
    if not isinstance(payload, str) or not payload:
        raise SimulationError(f"cannot encode QR payload {payload!r}")
    return _code_texture_cached(payload, ecc).copy()


def _code_texture_cached(payload: str, ecc: str = SIM_ECC) -> np.ndarray:
    try:
        sym = encode_symbol(payload, ecc)  # cached there
    except ValueError as e:
        raise SimulationError(str(e)) from None
    if sym is None:
        raise SimulationError(f"cannot encode QR payload {payload!r}")
    return sym


@lru_cache(maxsize=8192)
def _mip(payload: str, texels_per_module: int, ecc: str = SIM_ECC) -> np.ndarray:
    """float32 texture with a white quiet zone, `texels_per_module` texels per module, in DN."""
    sym = _code_texture_cached(payload, ecc)
    q = QUIET_ZONE_MODULES
    full = np.pad(sym, q, constant_values=255)
    tex = np.where(full > 127, WHITE_DN, BLACK_DN).astype(np.float32)
    return np.ascontiguousarray(np.kron(tex, np.ones((texels_per_module, texels_per_module), np.float32)))


@dataclass
class PlacedCode:
    """A QR code in the world: payload, symbol frame S in W (conventions.py), symbol side (m)."""

    payload: str
    T_world_symbol: np.ndarray
    side_m: float
    ecc: str = SIM_ECC  # error-correction level (fusion.qr.symbol.ECC_LEVELS)

    @property
    def modules(self) -> int:
        return _code_texture_cached(self.payload, self.ecc).shape[0]

    @property
    def is_floor(self) -> bool:
        """True for a code lying flat, facing up (z_S along world +z)."""
        return float(self.T_world_symbol[2, 2]) > 0.9


def project_code_corners(camera: CameraModel, T_world_cam: np.ndarray, code: PlacedCode) -> np.ndarray:
    """(4, 2) distorted pixel coordinates of the symbol's outer corners TL, TR, BR, BL (no quiet
    zone); NaN for corners behind the camera."""
    corners_S = symbol_corners_S(code.side_m)
    T_cam_symbol = inv_T(T_world_cam) @ code.T_world_symbol
    p_cam = corners_S @ T_cam_symbol[:3, :3].T + T_cam_symbol[:3, 3]
    return camera.project(p_cam)


# ============================================================================ effects


@dataclass
class RenderEffects:
    """Photometric effects applied after the geometric rendering, in the order light meets them
    (`apply_photometric`): the scene (occlusion, glare, low contrast), the lens (vignetting,
    defocus), the exposure (motion blur, gain), the sensor (shot and read noise, clipping to
    0..255) and the encoder (JPEG).

    noise_sigma_dn: Gaussian read noise (DN, 1 sigma); shot_noise_dn: shot noise, variance
    `shot_noise_dn` x signal (DN^2 per DN: the sensor's DN per electron); gain: exposure
    multiplier (above 1 whites clip at 255: over-exposure); blur_px / blur_angle_rad: motion blur
    as a line kernel of that length (pixels moved during the exposure) and image direction;
    defocus_px: defocus as a uniform disc of that radius (px); vignetting: relative light lost
    at the image corner (cos^4-like falloff 1 - v (r / r_corner)^2); contrast: scene contrast
    kept (1 = printed contrast; 0.2 = faded print / haze: every code's black-white swing times
    0.2 about the image mean); glare_fraction: a saturated specular blob over that fraction of
    each code's symbol area (0 = none); occlusion_fraction: that fraction of each code's symbol
    hidden by a dark object entering from a random side; jpeg_quality: None (lossless) or the
    JPEG quality (1..100) the camera compresses with; blackout: None or one of BLACKOUT_KINDS,
    which makes every floor code in view unreadable ('shadow': a deep shadow over the codes,
    'glare': saturated specular glare over them, 'torn': the top half of each symbol torn
    off)."""

    noise_sigma_dn: float = 1.5
    gain: float = 1.0
    blur_px: float = 0.0
    blur_angle_rad: float = 0.0
    blackout: str | None = None
    shot_noise_dn: float = 0.0
    defocus_px: float = 0.0
    vignetting: float = 0.0
    contrast: float = 1.0
    glare_fraction: float = 0.0
    occlusion_fraction: float = 0.0
    jpeg_quality: int | None = None

    def __post_init__(self):
        if self.blackout is not None and self.blackout not in BLACKOUT_KINDS:
            raise SimulationError(
                f"unknown blackout kind {self.blackout!r}; expected one of {BLACKOUT_KINDS}"
            )
        if not (self.noise_sigma_dn >= 0 and self.gain > 0 and self.blur_px >= 0):
            raise SimulationError("render effects: noise >= 0, gain > 0 and blur >= 0 required")
        if not (self.shot_noise_dn >= 0 and self.defocus_px >= 0 and 0 <= self.vignetting < 1):
            raise SimulationError("render effects: shot noise, defocus >= 0 and 0 <= vignetting < 1 required")
        fractions = (self.glare_fraction, self.occlusion_fraction)
        if not (0 < self.contrast <= 1 and all(0 <= f <= 1 for f in fractions)):
            raise SimulationError(
                "render effects: 0 < contrast <= 1, glare and occlusion fractions in [0, 1] required"
            )
        if self.jpeg_quality is not None and not (1 <= int(self.jpeg_quality) <= 100):
            raise SimulationError(f"render effects: JPEG quality in 1..100, got {self.jpeg_quality}")


def motion_blur_kernel(length_px: float, angle_rad: float) -> np.ndarray | None:
    """Normalised line kernel of `length_px` along image direction `angle_rad` (None if < 1 px)."""
    if length_px < 1.0:
        return None
    k = int(math.ceil(length_px)) | 1
    k += 2
    kernel = np.zeros((k, k), np.float32)
    c = (k - 1) / 2.0
    dx, dy = 0.5 * length_px * math.cos(angle_rad), 0.5 * length_px * math.sin(angle_rad)
    n = max(8, int(4 * length_px))
    for s in np.linspace(-1.0, 1.0, n):
        x, y = c + s * dx, c + s * dy
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    return kernel / kernel.sum()


# ============================================================================ per-camera cache


class _CameraRays:
    """Per-camera precomputation: the undistorted normalised ray of every pixel (full resolution)
    and of every pixel of the half-resolution image (for the low-frequency background; half-res
    pixel j is full-res coordinate 2 j + 0.5, as cv2.resize by 2 assumes)."""

    def __init__(self, camera: CameraModel):
        w, h = camera.width, camera.height
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        xy = camera.undistort_normalized(np.stack([u, v], axis=-1))
        self.xn = np.ascontiguousarray(xy[..., 0], dtype=np.float64)
        self.yn = np.ascontiguousarray(xy[..., 1], dtype=np.float64)
        # largest normalised radius inside the image: projections farther out may fold back (a
        # fisheye's pixels beyond 90 degrees off the axis have no ray: NaN, left out)
        self.r_max = float(np.nanmax(np.sqrt(self.xn**2 + self.yn**2)))
        self.half_size = ((w + 1) // 2, (h + 1) // 2)
        uh, vh = np.meshgrid(
            2.0 * np.arange(self.half_size[0]) + 0.5, 2.0 * np.arange(self.half_size[1]) + 0.5
        )
        xyh = camera.undistort_normalized(np.stack([uh, vh], axis=-1))
        self.half_x = np.ascontiguousarray(xyh[..., 0], dtype=np.float32)
        self.half_y = np.ascontiguousarray(xyh[..., 1], dtype=np.float32)
        self.bounds_xy = (
            float(np.nanmin(self.xn)),
            float(np.nanmax(self.xn)),
            float(np.nanmin(self.yn)),
            float(np.nanmax(self.yn)),
        )


_RAYS: dict[tuple, _CameraRays] = {}


def _rays(camera: CameraModel) -> _CameraRays:
    key = camera.projection_key
    r = _RAYS.get(key)
    if r is None:
        if len(_RAYS) > 8:
            _RAYS.clear()
        r = _RAYS[key] = _CameraRays(camera)
    return r


@lru_cache(maxsize=4)
def _floor_texture(seed: int = 7, size: int = 512) -> np.ndarray:
    """Periodic float32 floor texture (DN): mid grey, mild low-frequency variation, fine grain."""
    rng = np.random.default_rng(seed)
    low: np.ndarray = rng.normal(0.0, 1.0, (16, 16)).astype(np.float32)
    low = np.tile(low, (3, 3))
    low = cv2.resize(low, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)[
        size : 2 * size, size : 2 * size
    ]
    low = low / (np.abs(low).max() + 1e-9)
    grain = cv2.GaussianBlur(rng.normal(0.0, 1.0, (size, size)).astype(np.float32), (0, 0), 1.0)
    return np.ascontiguousarray(120.0 + 18.0 * low + 6.0 * grain / (grain.std() + 1e-9))


FLOOR_TEXEL_M = 0.02  # floor texture resolution (m per texel), repeats every 10.24 m
FAR_DN = 105.0  # what rays that miss the floor see (far walls / shelving, unlit)


RACK_DN = (92.0, 84.0, 100.0)  # rack box faces normal to world x, y, z
RACK_BEAM_PITCH_M = 0.7  # horizontal beams (darker) every 0.7 m of height


def _box_may_be_in_view(lo, hi, T_world_cam: np.ndarray, rays: _CameraRays) -> bool:
    """False when all 8 corners of the box are in front of the camera and beyond one side of the
    field of view (then no ray meets it); True otherwise (conservative)."""
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], dtype=float
    )
    p = (corners - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    if np.any(p[:, 2] <= 1e-6):
        return True
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    x0, x1, y0, y1 = rays.bounds_xy
    return not (np.all(x < x0) or np.all(x > x1) or np.all(y < y0) or np.all(y > y1))


def _background(camera: CameraModel, rays: _CameraRays, T_world_cam: np.ndarray, occluders=()) -> np.ndarray:
    """float32 (H, W) background at half resolution, upsampled (it is low frequency): the
    textured floor plane z = 0 where the ray meets it within 60 m, else a flat far-wall grey;
    in front of both, the occluder boxes (racks) as flat grey faces with darker beams.
    `T_world_cam`: (4, 4), or (H, 4, 4) one pose per image row (rolling shutter; half-resolution
    row j takes the pose of full row 2 j)."""
    xh, yh = rays.half_x, rays.half_y
    if T_world_cam.ndim == 3:  # rolling shutter: per-row entries broadcast as (rows, 1) columns
        rows_T = T_world_cam[np.minimum(2 * np.arange(xh.shape[0]), len(T_world_cam) - 1)]
        R = rows_T[:, :3, :3].astype(np.float32).transpose(1, 2, 0)[..., None]
        c = rows_T[:, :3, 3].astype(np.float32).T[..., None]
        T_ends: list[np.ndarray] = [T_world_cam[0], T_world_cam[-1]]
    else:
        R, c = T_world_cam[:3, :3].astype(np.float32), T_world_cam[:3, 3].astype(np.float32)
        T_ends = [T_world_cam]
    d = [xh * R[i, 0] + yh * R[i, 1] + R[i, 2] for i in range(3)]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t_floor = np.where(d[2] < -1e-6, -c[2] / d[2], np.inf)
        hit = t_floor < 60.0
        t = np.where(hit, t_floor, 0.0)
        tex = _floor_texture()
        n = tex.shape[0]
        px = np.mod((c[0] + t * d[0]) / FLOOR_TEXEL_M, n).astype(np.float32)
        py = np.mod((c[1] + t * d[1]) / FLOOR_TEXEL_M, n).astype(np.float32)
        bg = cv2.remap(tex, px, py, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        if not hit.all():
            bg[~hit] = FAR_DN
        depth = t_floor
        for lo, hi in occluders or ():
            if not any(_box_may_be_in_view(lo, hi, T, rays) for T in T_ends):
                continue
            t0 = [(np.float32(lo[i]) - c[i]) / d[i] for i in range(3)]
            t1 = [(np.float32(hi[i]) - c[i]) / d[i] for i in range(3)]
            near = [np.minimum(a, b) for a, b in zip(t0, t1)]
            tmin = np.maximum(np.maximum(near[0], near[1]), near[2])
            tmax = np.minimum(
                np.minimum(np.maximum(t0[0], t1[0]), np.maximum(t0[1], t1[1])), np.maximum(t0[2], t1[2])
            )
            box = (tmin <= tmax) & (tmin > 0.0) & (tmin < depth)
            if not box.any():
                continue
            tb = tmin[box]
            n0, n1 = near[0][box], near[1][box]
            shade = np.where(tb == n0, RACK_DN[0], np.where(tb == n1, RACK_DN[1], RACK_DN[2]))
            cz = np.broadcast_to(c[2], box.shape)[box] if np.ndim(c[2]) else c[2]
            beam = np.mod(cz + tb * d[2][box], RACK_BEAM_PITCH_M) < 0.06
            bg[box] = shade - 35.0 * beam
            depth = np.where(box, tmin, depth)
    return cv2.resize(bg, (camera.width, camera.height), interpolation=cv2.INTER_LINEAR)


# ============================================================================ rendering


# quiet-zone outline in units of its half side: corners TL, TR, BR, BL, then edge midpoints
_OUTLINE_UNIT = np.array(
    [[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0], [0, 1, 0], [1, 0, 0], [0, -1, 0], [-1, 0, 0]],
    dtype=float,
)


def _draw_code(
    img: np.ndarray, camera: CameraModel, rays: _CameraRays, T_cam_world: np.ndarray, code: PlacedCode
) -> np.ndarray | None:
    """Composite one code (with its quiet zone) into `img` in place; returns the (4, 2) distorted
    pixel corners of the quiet-zone outline if drawn, else None.  `T_cam_world`: (4, 4), or
    (H, 4, 4) one pose per image row (rolling shutter: each row's rays meet the code's plane as
    that row's pose sees it; culling, bounds and mip level from the middle row's pose, the bounds
    widened to the first and last rows')."""
    rows_T = None
    if T_cam_world.ndim == 3:
        rows_T = T_cam_world
        T_cam_world = rows_T[len(rows_T) // 2]
    T_cam_symbol = T_cam_world @ code.T_world_symbol
    R, t = T_cam_symbol[:3, :3], T_cam_symbol[:3, 3]
    # back face culling: the camera must be on the printed side (z_S) of the plane
    if float(R[:, 2] @ (-t)) <= 1e-9:
        return None
    n_mod = code.modules
    q = QUIET_ZONE_MODULES
    m = code.side_m / n_mod  # module size (m)
    half_outer = 0.5 * code.side_m + q * m
    # the quiet-zone outline (corners and edge midpoints) bounds the projection; then the
    # symbol's own corners give the scale (pixels per module)
    pts_S = _OUTLINE_UNIT[:, :2] * half_outer
    pts_S = np.vstack([pts_S, _OUTLINE_UNIT[:4, :2] * (0.5 * code.side_m)])
    p_cam = pts_S @ R[:, :2].T + t
    if np.any(p_cam[:, 2] < 0.02):
        return None  # (partly) behind the camera: not renderable
    h, w = img.shape
    r_xy = np.hypot(p_cam[:, 0], p_cam[:, 1]) / p_cam[:, 2]
    uv = camera.project(p_cam)
    if np.max(r_xy[:8]) > 1.5 * rays.r_max:
        # far outside the field of view, where the distortion polynomial may fold back
        if np.min(r_xy[:8]) > 1.5 * rays.r_max:
            return None
        x0, y0, x1, y1 = 0, 0, w, h
    else:
        box_uv = uv[:8]
        if rows_T is not None:  # the outline as the first and last rows' poses see it too
            ends = [(T @ code.T_world_symbol) for T in (rows_T[0], rows_T[-1])]
            box_uv = np.vstack([box_uv] + [camera.project(pts_S[:8] @ T[:3, :2].T + T[:3, 3]) for T in ends])
            if not np.all(np.isfinite(box_uv)):
                box_uv = uv[:8]
        x0 = max(int(box_uv[:, 0].min()) - 2, 0)
        y0 = max(int(box_uv[:, 1].min()) - 2, 0)
        x1 = min(int(box_uv[:, 0].max()) + 3, w)
        y1 = min(int(box_uv[:, 1].max()) + 3, h)
    if x1 <= x0 or y1 <= y0:
        return None
    # mip level: texels per module ~ pixels per module (power of two, magnifying)
    corners_px = uv[8:]
    edge_px = np.mean(np.linalg.norm(corners_px - np.roll(corners_px, 1, axis=0), axis=1))
    px_per_module = edge_px / n_mod if np.isfinite(edge_px) else 1.0
    tpm = 1
    while tpm * 2 <= min(px_per_module, _MAX_TEXELS_PER_MODULE):
        tpm *= 2
    tex = _mip(code.payload, tpm, code.ecc)
    # ray (xn, yn, 1) meets the plane at symbol coordinates H_sc @ ray, H_cs = [r1 r2 t]
    H_cs = np.column_stack([R[:, 0], R[:, 1], t])
    H_sc = np.linalg.inv(H_cs)
    # symbol (x_S, y_S) -> texture (u_t, v_t); texel centres at integers, so the symbol's
    # outer edge (q modules in) is at q * tpm - 0.5
    A = np.array(
        [
            [tpm / m, 0.0, half_outer * tpm / m - 0.5],
            [0.0, -tpm / m, half_outer * tpm / m - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    if rows_T is not None:  # one plane-to-ray homography per row, entries as (rows, 1) columns
        T_rows = rows_T[y0:y1] @ code.T_world_symbol
        H_sc = np.linalg.inv(np.concatenate([T_rows[:, :3, :2], T_rows[:, :3, 3:]], axis=2))
        H_sc = H_sc.transpose(1, 2, 0)[..., None]
        H = np.einsum("ij,jk...->ik...", A, H_sc)
    else:
        H = A @ H_sc
    xn = rays.xn[y0:y1, x0:x1]
    yn = rays.yn[y0:y1, x0:x1]
    den = H[2, 0] * xn + H[2, 1] * yn + H[2, 2]
    lam = H_sc[2, 0] * xn + H_sc[2, 1] * yn + H_sc[2, 2]  # 1/depth sign: rays hitting in front
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(lam > 0, 1.0 / den, np.nan)
        mx = ((H[0, 0] * xn + H[0, 1] * yn + H[0, 2]) * inv).astype(np.float32)
        my = ((H[1, 0] * xn + H[1, 1] * yn + H[1, 2]) * inv).astype(np.float32)
    n_tex = tex.shape[0]
    inside = (mx >= -0.5) & (mx <= n_tex - 0.5) & (my >= -0.5) & (my <= n_tex - 0.5)
    if not inside.any():
        return None
    mx = np.where(inside, mx, -10.0).astype(np.float32)
    my = np.where(inside, my, -10.0).astype(np.float32)
    patch = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    roi = img[y0:y1, x0:x1]
    np.copyto(roi, patch, where=inside)
    return uv[:4]


def _apply_blackout(img: np.ndarray, kind: str, quads: list[np.ndarray], rng) -> None:
    """Make every code whose quiet-zone outline is in `quads` unreadable, in place."""
    h, w = img.shape
    for quad in quads:
        if not np.all(np.isfinite(quad)):
            continue
        centre = quad.mean(axis=0)
        if kind == "torn":
            # the top half of the symbol (both top finders) is torn off, showing floor below
            top = np.array([quad[0], quad[1], 0.5 * (quad[1] + quad[2]), 0.5 * (quad[0] + quad[3])])
            top = centre + 1.02 * (top - centre)
            mask = np.zeros((h, w), np.uint8)
            cv2.fillConvexPoly(mask, np.round(top * 16).astype(np.int32), 255, cv2.LINE_AA, 4)
            a: np.ndarray = mask.astype(np.float32) / 255.0
            torn = 118.0 + 4.0 * rng.standard_normal((h, w)).astype(np.float32)
            img *= 1.0 - a
            img += a * torn
            continue
        big = centre + 1.6 * (quad - centre)  # well beyond the quiet zone
        mask = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(mask, np.round(big * 16).astype(np.int32), 255, cv2.LINE_AA, 4)
        radius = max(3.0, 0.15 * float(np.linalg.norm(quad[0] - quad[2])))
        a = cv2.GaussianBlur(mask.astype(np.float32) / 255.0, (0, 0), radius)
        a = np.clip(1.6 * a, 0.0, 1.0)  # plateau of 1 over the code itself
        if kind == "glare":
            img *= 1.0 - a
            img += a * 300.0  # saturates after clipping
        else:  # shadow: almost no light, contrast below noise
            img *= 1.0 - a * 0.985
            img += a * 4.0
            img += (a * 3.0) * rng.standard_normal((h, w)).astype(np.float32)


@lru_cache(maxsize=4)
def _noise_pool(shape: tuple[int, int]) -> np.ndarray:
    """float32 standard-normal pool of twice the image size (fixed seed): each frame adds a window
    at a random offset, ten times cheaper than drawing fresh noise for every pixel."""
    return np.random.default_rng(12345).standard_normal((2 * shape[0], 2 * shape[1]), dtype=np.float32)


def _noise(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 white standard-normal noise: a window of the pool at an offset from `rng`,
    randomly flipped."""
    pool = _noise_pool(tuple(shape))
    r0 = int(rng.integers(0, shape[0]))
    c0 = int(rng.integers(0, shape[1]))
    win = pool[r0 : r0 + shape[0], c0 : c0 + shape[1]]
    flip = int(rng.integers(0, 4))
    if flip & 1:
        win = win[::-1]
    if flip & 2:
        win = win[:, ::-1]
    return win


MIN_CODE_PX = 6.0  # codes whose quiet-zone outline spans fewer pixels are not drawn


def _visible_far_to_near(
    codes: list[PlacedCode], T_cam_world: np.ndarray, rays: _CameraRays, focal_px: float
) -> np.ndarray:
    """Indices of the codes that may appear in the image (a conservative view-cone test on the
    bounding sphere of each code with its quiet zone) and span at least MIN_CODE_PX pixels,
    farthest first (painter's order)."""
    if not codes:
        return np.zeros(0, dtype=int)
    centres = np.array([c.T_world_symbol[:3, 3] for c in codes])
    radius = np.array([(0.5 + QUIET_ZONE_MODULES / c.modules) * c.side_m * 1.5 for c in codes])
    p = centres @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    r = rays.r_max * 1.05
    # inside the cone |xy| <= r z, widened by the sphere's radius
    ok = np.hypot(p[:, 0], p[:, 1]) - r * p[:, 2] <= radius * math.sqrt(1.0 + r * r)
    ok &= p[:, 2] > -radius
    ok &= focal_px * radius / 1.5 >= MIN_CODE_PX * 0.5 * np.maximum(np.linalg.norm(p, axis=1) - radius, 1e-3)
    idx = np.flatnonzero(ok)
    return idx[np.argsort(-p[idx, 2], kind="stable")]


def _occluded(T_world_cam: np.ndarray, codes: list[PlacedCode], idx: np.ndarray, occluders) -> np.ndarray:
    """Mask over `idx`: the segment from the camera centre to the code centre crosses one of the
    axis-aligned boxes (lo (3,), hi (3,)) in W (slab test)."""
    c = T_world_cam[:3, 3]
    p = np.array([codes[i].T_world_symbol[:3, 3] for i in idx]).reshape(-1, 3)
    d = p - c
    hidden = np.zeros(len(idx), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        for lo, hi in occluders:
            t0 = (np.asarray(lo) - c) * inv
            t1 = (np.asarray(hi) - c) * inv
            tmin = np.nanmax(np.minimum(t0, t1), axis=1)
            tmax = np.nanmin(np.maximum(t0, t1), axis=1)
            hidden |= (tmin <= tmax) & (tmax > 0.0) & (tmin < 0.999)
    return hidden


def render_view(
    camera: CameraModel,
    T_world_cam: np.ndarray,
    codes: list[PlacedCode],
    rng=None,
    effects: RenderEffects | None = None,
    occluders=None,
) -> np.ndarray:
    """uint8 (H, W) grayscale image seen by `camera` at pose T_world_cam (camera frame: OpenCV).

    Background: the textured floor plane (z = 0), grey elsewhere; then every code in front of the
    camera and facing it, far to near, with a white quiet zone of 4 modules; then `effects`
    (blackout, motion blur, exposure gain, sensor noise).  `rng` (np.random.Generator) drives the
    noise; None means no randomness (noise-free unless effects ask for noise, then seed 0).
    `occluders`: optional axis-aligned boxes [(lo (3,), hi (3,))] in W (racks), drawn as flat
    grey boxes; a code whose centre they hide from the camera is not drawn.

    Rolling shutter: `T_world_cam` (H, 4, 4) gives one camera pose per image row (row r's
    exposure; `rolling_shutter_poses`); every pixel's ray is then cast from its row's pose, so
    the image is exactly what a rolling-shutter sensor records of the moving scene (visibility
    and occlusion tests use the middle row's pose)."""
    effects = effects or RenderEffects(noise_sigma_dn=0.0)
    if rng is None:
        rng = np.random.default_rng(0)
    rays = _rays(camera)
    T_world_cam = np.asarray(T_world_cam, dtype=float)
    if T_world_cam.ndim == 3 and T_world_cam.shape[0] != camera.height:
        raise SimulationError(
            f"rolling-shutter render needs one pose per row ({camera.height}), got {T_world_cam.shape[0]}"
        )
    T_cam_world = inv_T(T_world_cam)
    img = _background(camera, rays, T_world_cam, occluders)
    floor_quads = []
    drawn = []
    T_world_cam_mid = T_world_cam[len(T_world_cam) // 2] if T_world_cam.ndim == 3 else T_world_cam
    T_cam_world_mid = inv_T(T_world_cam_mid)
    visible = _visible_far_to_near(codes, T_cam_world_mid, rays, max(camera.fu, camera.fv))
    if occluders and len(visible):
        visible = visible[~_occluded(T_world_cam_mid, codes, visible, occluders)]
    for i in visible:
        code = codes[i]
        quad = _draw_code(img, camera, rays, T_cam_world, code)
        if quad is not None:
            drawn.append(code)
        if quad is not None and code.is_floor:
            floor_quads.append(quad)
    if effects.blackout is not None:
        _apply_blackout(img, effects.blackout, floor_quads, rng)
    symbol_quads = []
    if effects.glare_fraction > 0 or effects.occlusion_fraction > 0:
        symbol_quads = [project_code_corners(camera, T_world_cam_mid, code) for code in drawn]
    return apply_photometric(img, effects, rng, symbol_quads, (camera.cu, camera.cv))


# ============================================================================ photometric effects

GLARE_DN = 320.0  # specular glare: well above white, so it saturates after clipping
GLARE_EDGE = 0.08  # glare blob's soft edge, Gaussian sigma as a fraction of the code's side
OCCLUDER_DN = 45.0  # a dark object (a strap, a hand, a pallet edge) in front of a code
_UNIT_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], np.float32)
_GLARE_OUTLINE_POINTS = 48
_SUBPIXEL_SHIFT = 4  # cv2 fill: 4 fractional bits


def _unit_to_image(quad: np.ndarray) -> np.ndarray:
    """Homography from the symbol's unit square ((0, 0) top-left, (1, 1) bottom-right) to its
    image quad (4, 2) TL, TR, BR, BL."""
    return cv2.getPerspectiveTransform(_UNIT_SQUARE, np.asarray(quad, np.float32))


def _fill_mask(shape: tuple[int, int], polygon_px: np.ndarray) -> np.ndarray:
    """float32 (H, W) anti-aliased coverage in [0, 1] of a convex polygon (n, 2) px."""
    mask = np.zeros(shape, np.uint8)
    pts = np.round(polygon_px * (1 << _SUBPIXEL_SHIFT)).astype(np.int32)
    cv2.fillConvexPoly(mask, pts, 255, cv2.LINE_AA, _SUBPIXEL_SHIFT)
    return mask.astype(np.float32) / 255.0


def occlusion_polygon(quad: np.ndarray, fraction: float, side: int) -> np.ndarray:
    """(4, 2) image polygon of the strip covering `fraction` of the symbol (image quad TL, TR,
    BR, BL) from its side `side` (0 left, 1 top, 2 right, 3 bottom of the symbol)."""
    f = float(fraction)
    strips = {
        0: [[0, 0], [f, 0], [f, 1], [0, 1]],
        1: [[0, 0], [1, 0], [1, f], [0, f]],
        2: [[1 - f, 0], [1, 0], [1, 1], [1 - f, 1]],
        3: [[0, 1 - f], [1, 1 - f], [1, 1], [0, 1]],
    }
    unit = np.array(strips[int(side)], np.float32)[None]
    return cv2.perspectiveTransform(unit, _unit_to_image(quad))[0]


def glare_polygon(quad: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 2) image outline of a disc in the symbol plane whose area is `fraction` of the
    symbol's, at a random place inside it (centred when it cannot fit)."""
    rho = math.sqrt(float(fraction) / math.pi)
    lo, hi = rho, 1.0 - rho
    centre = rng.uniform(lo, hi, 2) if hi > lo else np.array([0.5, 0.5])
    a = np.linspace(0.0, 2.0 * math.pi, _GLARE_OUTLINE_POINTS, endpoint=False)
    unit = centre + rho * np.column_stack([np.cos(a), np.sin(a)])
    return cv2.perspectiveTransform(unit[None].astype(np.float32), _unit_to_image(quad))[0]


def defocus_kernel(radius_px: float) -> np.ndarray | None:
    """Normalised uniform disc of `radius_px` (pillbox; edge pixels weighted by their covered
    area, 8x supersampled), None below half a pixel."""
    if radius_px < 0.5:
        return None
    n = int(math.ceil(radius_px)) + 1
    ss = 8
    g = (np.arange(-n * ss, (n + 1) * ss) + 0.5) / ss - 0.5
    inside = (g[:, None] ** 2 + g[None, :] ** 2 <= radius_px**2).astype(np.float32)
    k = inside.reshape(2 * n + 1, ss, 2 * n + 1, ss).sum(axis=(1, 3))
    return k / k.sum()


@lru_cache(maxsize=8)
def _vignetting_falloff(shape: tuple[int, int], centre: tuple[float, float]) -> np.ndarray:
    """(H, W) float32 (r / r_corner)^2 about the principal point."""
    h, w = shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    r2 = (u - centre[0]) ** 2 + (v - centre[1]) ** 2
    return (r2 / r2.max()).astype(np.float32)


def apply_photometric(
    img: np.ndarray,
    effects: RenderEffects,
    rng: np.random.Generator,
    symbol_quads: list[np.ndarray] = (),  # type: ignore[assignment]
    principal_point: tuple[float, float] | None = None,
) -> np.ndarray:
    """uint8 image from the float32 scene radiance `img` (DN at nominal exposure; modified in
    place): occlusion and glare over the codes whose symbol quads (4, 2) are given, low contrast,
    vignetting about `principal_point` (default the image centre), defocus, motion blur, gain,
    shot and read noise, clipping, JPEG (RenderEffects)."""
    shape = img.shape
    if effects.occlusion_fraction > 0:
        for quad in symbol_quads:
            if np.all(np.isfinite(quad)):
                poly = occlusion_polygon(quad, effects.occlusion_fraction, int(rng.integers(0, 4)))
                a = _fill_mask(shape, poly)
                img *= 1.0 - a
                img += a * OCCLUDER_DN
    if effects.glare_fraction > 0:
        for quad in symbol_quads:
            if np.all(np.isfinite(quad)):
                side_px = float(np.mean(np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)))
                a = _fill_mask(shape, glare_polygon(quad, effects.glare_fraction, rng))
                a = cv2.GaussianBlur(a, (0, 0), max(0.5, GLARE_EDGE * side_px))
                img *= 1.0 - a
                img += a * GLARE_DN
    if effects.contrast != 1.0:
        mean = np.float32(img.mean())
        img -= mean
        img *= np.float32(effects.contrast)
        img += mean
    if effects.vignetting > 0:
        h, w = shape
        centre = principal_point if principal_point is not None else ((w - 1) / 2.0, (h - 1) / 2.0)
        img *= 1.0 - np.float32(effects.vignetting) * _vignetting_falloff(
            shape, (float(centre[0]), float(centre[1]))
        )
    disc = defocus_kernel(effects.defocus_px)
    if disc is not None:
        img = cv2.filter2D(img, -1, disc, borderType=cv2.BORDER_REFLECT)
    kernel = motion_blur_kernel(effects.blur_px, effects.blur_angle_rad)
    if kernel is not None:
        img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if effects.gain != 1.0:
        img *= effects.gain
    if effects.shot_noise_dn > 0:
        sigma = np.sqrt(np.float32(effects.shot_noise_dn) * np.maximum(img, 0.0))
        shot = _noise(shape, rng) * sigma
    if effects.noise_sigma_dn > 0:
        img += _noise(shape, rng) * np.float32(effects.noise_sigma_dn)
    if effects.shot_noise_dn > 0:
        img += shot
    out = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    if effects.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(effects.jpeg_quality)])
        if not ok:
            raise SimulationError("JPEG encoding failed")
        decoded = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        if decoded is None:
            raise SimulationError("JPEG decoding failed")
        out = np.asarray(decoded, dtype=np.uint8)
    return out


def rolling_shutter_poses(camera: CameraModel, T_world_body_at, t_stamp_s: float) -> np.ndarray:
    """(H, 4, 4) T_world_cam of every image row of a frame stamped `t_stamp_s`: row r is exposed
    at t_stamp_s + camera.row_time_offset_s(r); `T_world_body_at(times_s (N,)) -> (N, 4, 4)` is
    the true body trajectory.  A global-shutter camera gives H copies of the stamp's pose."""
    times = t_stamp_s + camera.row_time_offset_s(np.arange(camera.height, dtype=float))
    return camera.T_world_cam(T_world_body_at(times))


ROLLING_CORNER_ITERATIONS = 6
"""Fixed-point iterations of `project_code_corners_rolling` (each shrinks the row error by the
image motion per row, far below 1 px/row)."""


def project_code_corners_rolling(
    camera: CameraModel, T_world_body_at, t_stamp_s: float, code: PlacedCode
) -> np.ndarray:
    """(4, 2) distorted pixel corners (TL, TR, BR, BL) of `code` as a rolling-shutter camera
    records them: each corner at the row v that is exposed when the camera, at the body pose
    `T_world_body_at(times_s (N,)) -> (N, 4, 4)` of that row's time, projects it onto row v
    (fixed-point iteration from the stamp's pose)."""
    corners_S = symbol_corners_S(code.side_m)
    p_world = corners_S @ code.T_world_symbol[:3, :3].T + code.T_world_symbol[:3, 3]
    dt = np.zeros(len(p_world))
    uv = np.full((len(p_world), 2), np.nan)
    for _ in range(ROLLING_CORNER_ITERATIONS):
        T_cam_world = inv_T(camera.T_world_cam(T_world_body_at(t_stamp_s + dt)))
        p_cam = np.einsum("nij,nj->ni", T_cam_world[:, :3, :3], p_world) + T_cam_world[:, :3, 3]
        uv = camera.project(p_cam)
        if not np.all(np.isfinite(uv)):
            return uv
        dt = camera.row_time_offset_s(uv[:, 1])
    return uv


def placed_floor_codes(
    xy_payload: np.ndarray, payload_unit_m: float, side_m: float, ecc: str = SIM_ECC
) -> list[PlacedCode]:
    """PlacedCodes for floor codes at payload coordinates (N, 2) (symbol frame = world axes)."""
    from fusion.conventions import floor_payload

    out = []
    for x, y in np.asarray(xy_payload, dtype=float).reshape(-1, 2):
        T = np.eye(4)
        T[:2, 3] = (x * payload_unit_m, y * payload_unit_m)
        out.append(PlacedCode(floor_payload(x, y), T, side_m, ecc))
    return out
