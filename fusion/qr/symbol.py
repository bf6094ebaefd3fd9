"""QR symbols as module bitmaps, at a chosen error-correction level (one encoder for the printed
sheets, fusion.qrsheet, and the simulator, fusion.sim.render).

Error-correction levels (ISO/IEC 18004 Table 13): the share of codewords that may be wrong and
the symbol still decodes, about L 7 %, M 15 %, Q 25 %, H 30 %.  A floor code is walked and
driven on (dirt, tyre marks) and lit from above (specular glare): H is the level to print.  The
price is a larger version for the same payload (a floor payload `0/<x>/<y>` of up to 10
characters still fits version 1 at H: alphanumeric mode), so smaller modules at a given side.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

ECC_LEVELS = ("L", "M", "Q", "H")
SHEET_ECC = "H"  # printed codes (fusion qr-sheet): the most robust level
SIM_ECC = "L"  # the simulator's default (what its benchmarks were measured with)
_CV2_LEVEL = {
    "L": cv2.QRCODE_ENCODER_CORRECT_LEVEL_L,
    "M": cv2.QRCODE_ENCODER_CORRECT_LEVEL_M,
    "Q": cv2.QRCODE_ENCODER_CORRECT_LEVEL_Q,
    "H": cv2.QRCODE_ENCODER_CORRECT_LEVEL_H,
}


def check_ecc(ecc: str) -> str:
    """`ecc` if it is one of ECC_LEVELS, else ValueError naming the choices."""
    if ecc not in _CV2_LEVEL:
        raise ValueError(f"error-correction level {ecc!r} is not one of {', '.join(ECC_LEVELS)}")
    return ecc


@lru_cache(maxsize=4096)
def _encode(payload: str, ecc: str) -> np.ndarray | None:
    params = cv2.QRCodeEncoder.Params()
    params.correction_level = _CV2_LEVEL[ecc]
    try:
        img = cv2.QRCodeEncoder.create(params).encode(payload)
    except cv2.error:
        return None
    if img is None or img.size == 0:
        return None
    dark = np.argwhere(img < 128)
    (r0, c0), (r1, c1) = dark.min(axis=0), dark.max(axis=0)
    sym = np.ascontiguousarray(img[r0 : r1 + 1, c0 : c1 + 1])
    if sym.shape[0] != sym.shape[1] or (sym.shape[0] - 17) % 4:
        return None
    sym.setflags(write=False)
    return sym


def encode_symbol(payload: str, ecc: str = SIM_ECC) -> np.ndarray | None:
    """(N, N) uint8 module bitmap (0 dark, 255 light, one pixel per module, no quiet zone; row 0
    the symbol's top, finders at [0, 0], [0, N-1], [N-1, 0]) of `payload` at error-correction
    level `ecc` (ECC_LEVELS), or None when OpenCV's encoder cannot encode it.  Read-only (cached)."""
    return _encode(payload, check_ecc(ecc))
