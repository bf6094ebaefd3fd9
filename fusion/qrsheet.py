"""Printable QR sheets: floor codes `0/<x>/<y>` for a grid and load labels `1/<id>`, at true size.

Each symbol is drawn as vector squares (one per dark module) in an axes placed in inches on a
figure whose size is the paper size, so the symbol's side (its outer edge, quiet zone excluded,
DESIGN.md "Conventions") is exactly `side_m` on paper when printed at 100 % ("actual size", not
"fit to page").  Every page carries a 10 cm scale bar to check the printer with a ruler.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch
from matplotlib.path import Path as MplPath

from fusion.conventions import FloorPayload, LoadPayload, floor_payload, load_payload, parse_payload
from fusion.errors import PayloadError, QRSheetError
from fusion.fileio import atomic_open
from fusion.qr.symbol import ECC_LEVELS, SHEET_ECC, encode_symbol

MM_PER_INCH = 25.4
PAGES_MM = {
    "A3": (297.0, 420.0),
    "A4": (210.0, 297.0),
    "A5": (148.0, 210.0),
    "Letter": (215.9, 279.4),
    "Legal": (215.9, 355.6),
}
MARGIN_MM = 10.0  # printers cannot print to the edge
HEADER_MM = 10.0  # title line
FOOTER_MM = 16.0  # scale bar
LABEL_MM = 11.0  # two text lines under each code
QUIET_ZONE_MODULES = 4  # ISO/IEC 18004 quiet zone


def symbol_modules(payload: str, ecc: str = SHEET_ECC) -> np.ndarray:
    """(n, n) bool, True = dark module, of the QR symbol for `payload` at error-correction level
    `ecc` (L, M, Q, H; fusion.qr.symbol, the simulator's encoder), cropped to the symbol's outer
    edge (no quiet zone); row 0 is the top."""
    try:
        img = encode_symbol(payload, ecc)
    except ValueError as e:
        raise QRSheetError(str(e)) from None
    if img is None:
        raise QRSheetError(f"cannot encode {payload!r} as a QR code")
    return img < 128


def _modules_path(sym: np.ndarray) -> MplPath:
    """One compound path of the dark modules, merged into horizontal runs (no seams between
    squares of one fill), in module units with y up: module (r, c) covers [c, c+1] x [n-r-1, n-r]."""
    n = sym.shape[0]
    verts, codes = [], []
    for r in range(n):
        row = np.r_[False, sym[r], False].astype(np.int8)
        starts = np.flatnonzero(np.diff(row) == 1)
        ends = np.flatnonzero(np.diff(row) == -1)
        y0, y1 = n - r - 1, n - r
        for a, b in zip(starts, ends):
            verts += [(a, y0), (b, y0), (b, y1), (a, y1), (a, y0)]
            codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY]
    return MplPath(np.asarray(verts, dtype=float), codes)


@dataclass
class SheetCode:
    """One code to print: payload, symbol side (m), caption lines, and its place on the page
    (symbol's lower-left corner, inches from the page's lower-left corner)."""

    payload: str
    side_m: float
    caption: tuple[str, str]
    ecc: str = SHEET_ECC  # error-correction level (fusion.qr.symbol.ECC_LEVELS)
    x_in: float = 0.0
    y_in: float = 0.0

    @property
    def side_in(self) -> float:
        return self.side_m * 1000.0 / MM_PER_INCH


@dataclass
class SheetPage:
    size_in: tuple[float, float]
    title: str
    codes: list[SheetCode] = field(default_factory=list)


def _check_load_id(load_id) -> str:
    if not isinstance(load_id, str):
        raise QRSheetError(f"load id {load_id!r} is not text")
    text = load_payload(load_id)
    try:
        parsed = parse_payload(text)
    except PayloadError as e:
        raise QRSheetError(f"load id {load_id!r} cannot be printed: {e}") from None
    if not isinstance(parsed, LoadPayload) or parsed.id != load_id:
        raise QRSheetError(f"load id {load_id!r} does not survive its own payload grammar")
    return text


def _codes(
    grid: tuple[int, int],
    spacing_m: float,
    side_m: float,
    payload_unit_m: float,
    load_ids: Iterable[str],
    load_side_m: float,
    ecc: str = SHEET_ECC,
) -> tuple[list[SheetCode], list[SheetCode]]:
    if ecc not in ECC_LEVELS:
        raise QRSheetError(f"error-correction level {ecc!r} is not one of {', '.join(ECC_LEVELS)}")
    nx, ny = (int(v) for v in grid)
    if nx < 0 or ny < 0:
        raise QRSheetError(f"grid {grid} has a negative size")
    for name, v in (
        ("spacing_m", spacing_m),
        ("side_m", side_m),
        ("payload_unit_m", payload_unit_m),
        ("load_side_m", load_side_m),
    ):
        if not (np.isfinite(v) and v > 0):
            raise QRSheetError(f"{name} must be a positive number, got {v!r}")
    floor = []
    for j in range(ny):
        for i in range(nx):
            x_m, y_m = i * spacing_m, j * spacing_m
            payload = floor_payload(round(x_m / payload_unit_m, 6), round(y_m / payload_unit_m, 6))
            parsed = parse_payload(payload)
            if not isinstance(parsed, FloorPayload):
                raise QRSheetError(f"floor payload {payload!r} does not parse as a floor code")
            p = parsed.position_m(payload_unit_m)
            if abs(p[0] - x_m) > 1e-6 or abs(p[1] - y_m) > 1e-6:
                raise QRSheetError(
                    f"position ({x_m}, {y_m}) m is not a payload number of {payload_unit_m} m units to 1 um"
                )
            floor.append(
                SheetCode(
                    payload,
                    side_m,
                    (payload, f"x = {x_m:.3f} m, y = {y_m:.3f} m; symbol top toward world +y"),
                    ecc,
                )
            )
    loads = []
    seen = set()
    for load_id in load_ids:
        text = _check_load_id(load_id)
        if load_id in seen:
            raise QRSheetError(f"load id {load_id!r} is listed twice")
        seen.add(load_id)
        loads.append(
            SheetCode(
                text, load_side_m, (text, f"load {load_id}; hang upright, this text below the code"), ecc
            )
        )
    return floor, loads


def _cell_in(code: SheetCode, n_modules: int) -> tuple[float, float, float]:
    """(cell width, cell height, quiet zone) in inches for a code of `n_modules` modules."""
    q = code.side_in * QUIET_ZONE_MODULES / n_modules
    return code.side_in + 2 * q, code.side_in + 2 * q + LABEL_MM / MM_PER_INCH, q


def layout_pages(codes: list[SheetCode], page: str, title: str) -> list[SheetPage]:
    """Flow codes row by row onto pages (left to right, top to bottom); sets each x_in / y_in.
    A code whose cell (symbol + quiet zone + caption) does not fit on a page raises QRSheetError."""
    sizes = {k.lower(): v for k, v in PAGES_MM.items()}
    if not isinstance(page, str) or page.lower() not in sizes:
        raise QRSheetError(f"unknown page size {page!r} (known: {', '.join(PAGES_MM)})")
    W, H = (v / MM_PER_INCH for v in sizes[page.lower()])
    m = MARGIN_MM / MM_PER_INCH
    left, right = m, W - m
    top, bottom = H - m - HEADER_MM / MM_PER_INCH, m + FOOTER_MM / MM_PER_INCH
    pages: list[SheetPage] = []
    x, y_top, row_h = left, top, 0.0  # the first code opens the first page at its top-left
    for code in codes:
        n = symbol_modules(code.payload, code.ecc).shape[0]
        cw, ch, q = _cell_in(code, n)
        if cw > right - left or ch > top - bottom:
            raise QRSheetError(
                f"a {code.side_m * 100:g} cm code needs {cw * MM_PER_INCH:.0f} x "
                f"{ch * MM_PER_INCH:.0f} mm with its quiet zone and caption, more than the "
                f"{(right - left) * MM_PER_INCH:.0f} x {(top - bottom) * MM_PER_INCH:.0f} mm "
                f"printable on {page}; use a larger page or smaller codes"
            )
        if not pages:
            pages.append(SheetPage((W, H), title))
        if x + cw > right + 1e-9:  # next row
            x, y_top, row_h = left, y_top - row_h, 0.0
        if y_top - ch < bottom - 1e-9:  # next page
            pages.append(SheetPage((W, H), title))
            x, y_top, row_h = left, top, 0.0
        code.x_in = x + q
        code.y_in = y_top - q - code.side_in
        pages[-1].codes.append(code)
        x += cw
        row_h = max(row_h, ch)
    return pages


def page_figure(page: SheetPage, page_no: int = 1, n_pages: int = 1) -> Figure:
    """The page as a matplotlib Figure of the paper's size (inches); axes placed in inches."""
    W, H = page.size_in
    fig = Figure(figsize=(W, H))
    for code in page.codes:
        sym = symbol_modules(code.payload, code.ecc)
        n = sym.shape[0]
        ax = fig.add_axes((code.x_in / W, code.y_in / H, code.side_in / W, code.side_in / H))
        ax.set_xlim(0, n)
        ax.set_ylim(0, n)
        ax.set_axis_off()
        ax.add_patch(PathPatch(_modules_path(sym), facecolor="black", edgecolor="none", lw=0))
        q = code.side_in * QUIET_ZONE_MODULES / n
        # cut guide around the quiet zone (light, outside the code)
        fig.add_artist(
            _rect_in(fig, code.x_in - q, code.y_in - q, code.side_in + 2 * q, code.side_in + 2 * q)
        )
        cx = (code.x_in + code.side_in / 2) / W
        fig.text(
            cx,
            (code.y_in - q - 0.12) / H,
            code.caption[0],
            ha="center",
            va="top",
            family="monospace",
            fontsize=9,
            weight="bold",
        )
        fig.text(cx, (code.y_in - q - 0.27) / H, code.caption[1], ha="center", va="top", fontsize=6)
    m = MARGIN_MM / MM_PER_INCH
    fig.text(m / W, (H - m) / H, f"{page.title} (page {page_no}/{n_pages})", ha="left", va="top", fontsize=7)
    _scale_bar(fig, m, m + 0.15)
    fig.text(
        m / W,
        m / H,
        "Print at 100 % (actual size, no fit-to-page): the bar above must measure 10 cm.",
        ha="left",
        va="bottom",
        fontsize=6,
    )
    return fig


def _rect_in(fig: Figure, x: float, y: float, w: float, h: float):
    from matplotlib.patches import Rectangle

    W, H = fig.get_size_inches()
    return Rectangle(
        (x / W, y / H),
        w / W,
        h / H,
        transform=fig.transFigure,
        fill=False,
        ec="#c8c8c8",
        lw=0.4,
        ls=(0, (4, 4)),
    )


def _scale_bar(fig: Figure, x_in: float, y_in: float) -> None:
    """A 10 cm bar with 1 cm ticks, lower-left corner at (x_in, y_in) inches."""
    from matplotlib.lines import Line2D

    W, H = fig.get_size_inches()
    L = 100.0 / MM_PER_INCH
    tr = fig.transFigure
    fig.add_artist(
        Line2D([x_in / W, (x_in + L) / W], [y_in / H, y_in / H], transform=tr, color="black", lw=0.8)
    )
    for k in range(11):
        t = 0.12 if k in (0, 5, 10) else 0.06
        xk = (x_in + k * 10.0 / MM_PER_INCH) / W
        fig.add_artist(Line2D([xk, xk], [y_in / H, (y_in + t) / H], transform=tr, color="black", lw=0.6))
    fig.text((x_in + L + 0.1) / W, y_in / H, "10 cm", va="bottom", fontsize=7)


MAX_SHEET_FLOOR_CODES = 50_000
"""Floor codes one sheet may hold: 5 hectares at 1 m spacing, far beyond a warehouse hall; a
1000 x 1000 grid (a million codes) was still rendering after minutes (thirty-first session's
audit)."""


def sheet_pages(
    grid=(10, 6),
    spacing_m: float = 1.0,
    side_m: float = 0.20,
    payload_unit_m: float = 1.0,
    load_ids: Iterable[str] = (),
    load_side_m: float = 0.15,
    page: str = "A4",
    ecc: str = SHEET_ECC,
) -> list[SheetPage]:
    """The laid-out pages (floor codes first, load labels from a new page); every code at
    error-correction level `ecc` (default H: fusion.qr.symbol says why).  QRSheetError for more
    than MAX_SHEET_FLOOR_CODES floor codes (a mistyped grid ran for hours)."""
    if grid[0] * grid[1] > MAX_SHEET_FLOOR_CODES:
        raise QRSheetError(
            f"a {grid[0]} x {grid[1]} grid is {grid[0] * grid[1]:,} floor codes, over "
            f"{MAX_SHEET_FLOOR_CODES:,} (5 hectares at 1 m): a mistyped --grid?"
        )
    floor, loads = _codes(grid, spacing_m, side_m, payload_unit_m, load_ids, load_side_m, ecc)
    pages = []
    if floor:
        pages += layout_pages(
            floor,
            page,
            f"fusion floor codes: {grid[0]} x {grid[1]} grid, "
            f"spacing {spacing_m:g} m, payload unit {payload_unit_m:g} m, "
            f"side {side_m * 100:g} cm, error correction {ecc}",
        )
    if loads:
        pages += layout_pages(loads, page, f"fusion load labels: side {load_side_m * 100:g} cm")
    return pages


def write_qr_sheet(
    path: Path,
    grid=(10, 6),
    spacing_m: float = 1.0,
    side_m: float = 0.20,
    payload_unit_m: float = 1.0,
    load_ids: Iterable[str] = (),
    load_side_m: float = 0.15,
    page: str = "A4",
    ecc: str = SHEET_ECC,
) -> int:
    """Write a multi-page PDF of floor codes `0/<x>/<y>` at every grid point (x = i * spacing_m,
    y = j * spacing_m, payload in units of payload_unit_m) and load labels `1/<id>`, each symbol
    exactly `side_m` (`load_side_m`) wide on paper, at error-correction level `ecc` (default H,
    fusion.qr.symbol: a floor code still reads with up to ~30 % of it dirty or glared).
    Returns the number of pages written.
    Raises QRSheetError for codes larger than the page, unprintable ids or an unknown page."""
    pages = sheet_pages(grid, spacing_m, side_m, payload_unit_m, load_ids, load_side_m, page, ecc)
    if not pages:
        raise QRSheetError("nothing to print: the grid is empty and no load ids were given")
    path = Path(path)
    with atomic_open(path, "wb") as f:
        with PdfPages(f, metadata={"Title": "fusion QR sheet", "Creator": "fusion"}) as pdf:
            for k, pg in enumerate(pages, start=1):
                pdf.savefig(page_figure(pg, k, len(pages)))
    return len(pages)
