"""Codes whose finder patterns are hidden, decoded by re-stamping them (fusion.qr.restamp)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fusion.camera import CameraModel
from fusion.geometry import make_T
from fusion.qr.detect import detect_image
from fusion.qr.restamp import candidate_quads, function_patterns, restamp_image, sample_modules
from fusion.qr.symbol import encode_symbol
from fusion.sim.render import (
    OCCLUDER_DN,
    PlacedCode,
    RenderEffects,
    occlusion_polygon,
    project_code_corners,
    render_view,
)

CAMERA = CameraModel(640, 480, 520.0, 520.0, 320.0, 240.0)
R_DOWN = np.diag([1.0, -1.0, -1.0])


def _view(ecc: str, payload: str = "0/1/2", seed: int = 0, blur_px: float = 0.0):
    """A down-looking camera 0.8 m above one floor code (slightly off centre and turned):
    (image, true corners (4, 2), modules)."""
    from fusion.geometry import rot_z

    code = PlacedCode(payload, make_T(rot_z(0.3), np.zeros(3)), 0.20, ecc)
    T = make_T(R_DOWN, [0.03, -0.02, 0.8])
    rng = np.random.default_rng(seed)
    img = render_view(CAMERA, T, [code], rng, RenderEffects(1.5, 1.0, blur_px, 0.0))
    return img, project_code_corners(CAMERA, T, code), code.modules


def _strip(img: np.ndarray, quad: np.ndarray, side: int, fraction: float = 0.1) -> np.ndarray:
    """`img` with the simulator's strip occluder (render.occlusion_polygon) over `fraction` of
    the symbol from `side`."""
    mask = np.zeros(img.shape, np.uint8)
    poly = occlusion_polygon(quad, fraction, side)
    cv2.fillConvexPoly(mask, np.round(poly * 16).astype(np.int32), 255, cv2.LINE_AA, 4)
    a = mask.astype(np.float32) / 255.0
    return np.clip(np.round(img * (1.0 - a) + a * OCCLUDER_DN), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("payload", ["0/1/2", "0/12/7", "0/123/456789"])
@pytest.mark.parametrize("ecc", ["L", "H"])
def test_function_patterns_are_the_encoders_fixed_modules(payload, ecc):
    sym = encode_symbol(payload, ecc)
    assert sym is not None
    known, dark = function_patterns(sym.shape[0])
    assert known.sum() > 3 * 64  # three finders with their separators at least
    assert np.array_equal((sym < 128)[known], dark[known])


def test_sample_modules_reads_a_clean_code_exactly():
    img, truth, n = _view("H")
    modules = sample_modules(img, truth, n)
    assert modules is not None
    assert np.array_equal(modules, encode_symbol("0/1/2", "H") < 128)


@pytest.mark.parametrize("side", [0, 1, 2, 3])
def test_a_code_whose_finders_a_strip_hides_is_decoded_by_restamping(side):
    img, truth, _ = _view("H", seed=side)
    occluded = _strip(img, truth, side)
    assert detect_image(occluded) == []  # zxing needs all three finders
    got = restamp_image(occluded)
    assert [g.payload for g in got] == ["0/1/2"]
    assert got[0].modules == 21
    assert np.max(np.linalg.norm(got[0].corners_px - truth, axis=1)) < 1.5  # TL, TR, BR, BL


def test_a_decoded_code_is_left_out():
    img, truth, _ = _view("H")
    assert restamp_image(img, [truth]) == [] and len(candidate_quads(img)) == 1


@pytest.mark.parametrize("seed", range(6))
def test_a_symbol_with_scrambled_data_modules_gives_no_identity(seed):
    """Finders intact, data modules random: the Reed-Solomon check fails in every orientation,
    nothing is named (the identity is never guessed)."""
    img, truth, n = _view("H", seed=seed)
    rng = np.random.default_rng(seed)
    known, _ = function_patterns(n)
    k = 8
    grid = np.array([[0, 0], [n * k, 0], [n * k, n * k], [0, n * k]], np.float32)
    H = cv2.getPerspectiveTransform(grid, truth.astype(np.float32))
    noise = np.kron(rng.integers(0, 2, (n, n)) * 200 + 20, np.ones((k, k))).astype(np.float32)
    warped = cv2.warpPerspective(noise, H, (img.shape[1], img.shape[0]), flags=cv2.INTER_NEAREST)
    data = cv2.warpPerspective(
        np.kron(~known, np.ones((k, k))).astype(np.uint8),
        H,
        (img.shape[1], img.shape[0]),
        flags=cv2.INTER_NEAREST,
    )
    scrambled = np.where(data > 0, warped, img).astype(np.uint8)
    assert len(candidate_quads(scrambled)) == 1  # found, and tried in every orientation
    assert restamp_image(scrambled) == []


def test_nothing_is_found_on_a_bare_floor():
    rng = np.random.default_rng(0)
    img = render_view(CAMERA, make_T(R_DOWN, [5.5, 5.5, 0.8]), [], rng, RenderEffects(1.5, 1.0, 0.0, 0.0))
    assert candidate_quads(img) == [] and restamp_image(img) == []
