"""Error-correction levels: the sheet prints H by default, the simulator renders either level,
and each level decodes as itself (zxing-cpp reports the level it read)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import zxingcpp

from fusion.errors import QRSheetError, SimulationError
from fusion.qr.symbol import ECC_LEVELS, encode_symbol
from fusion.qrsheet import sheet_pages, symbol_modules
from fusion.sim.render import PlacedCode, code_texture, placed_floor_codes


def _read(sym: np.ndarray):
    img = cv2.resize(np.pad(sym, 4, constant_values=255), None, fx=6, fy=6, interpolation=cv2.INTER_NEAREST)
    return zxingcpp.read_barcodes(img, formats=zxingcpp.BarcodeFormat.QRCode)


@pytest.mark.parametrize("ecc", ECC_LEVELS)
def test_each_level_decodes_as_itself(ecc):
    (b,) = _read(encode_symbol("0/12/-7", ecc))
    assert b.text == "0/12/-7" and b.ec_level == ecc


def test_levels_differ_and_unknown_level_refused():
    syms = {e: encode_symbol("0/3/4", e) for e in ECC_LEVELS}
    assert len({s.tobytes() for s in syms.values()}) == 4
    with pytest.raises(ValueError, match="not one of"):
        encode_symbol("0/3/4", "X")


def test_sheet_defaults_to_level_h_and_takes_ecc():
    pages = sheet_pages(grid=(1, 1), side_m=0.05, load_ids=["A1"], load_side_m=0.04)
    codes = [c for p in pages for c in p.codes]
    assert codes and all(c.ecc == "H" for c in codes)
    assert "error correction H" in pages[0].title
    (b,) = _read(np.where(symbol_modules("0/0/0"), 0, 255).astype(np.uint8))
    assert b.ec_level == "H"
    pages = sheet_pages(grid=(1, 1), side_m=0.05, ecc="L")
    assert pages[0].codes[0].ecc == "L"
    with pytest.raises(QRSheetError, match="error-correction level"):
        sheet_pages(grid=(1, 1), side_m=0.05, ecc="Z")


def test_simulator_renders_either_level():
    assert code_texture("0/1/2").tobytes() == encode_symbol("0/1/2", "L").tobytes()  # default L
    assert code_texture("0/1/2", "H").tobytes() == encode_symbol("0/1/2", "H").tobytes()
    (code,) = placed_floor_codes(np.array([[1.0, 2.0]]), 1.0, 0.2, "H")
    assert code.ecc == "H" and code.modules == 21
    with pytest.raises(SimulationError):
        code_texture("0/1/2", "X")
    assert PlacedCode("1/a", np.eye(4), 0.1).ecc == "L"
