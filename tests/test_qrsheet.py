"""Printable QR sheets: page count, exact physical symbol size, payloads decode, bad ids refused."""

from __future__ import annotations

import re

import numpy as np
import pytest

from fusion.errors import QRSheetError
from fusion.qrsheet import (
    MM_PER_INCH,
    PAGES_MM,
    page_figure,
    sheet_pages,
    symbol_modules,
    write_qr_sheet,
)


def _pdf_page_count(path) -> int:
    return len(re.findall(rb"/Type\s*/Page(?![s\w])", path.read_bytes()))


def test_pdf_written_with_expected_page_count(tmp_path):
    # 0.20 m codes need A3 (276 mm with the quiet zone): one per page; loads from a new page
    path = tmp_path / "sheet.pdf"
    n = write_qr_sheet(
        path, grid=(2, 2), side_m=0.20, page="A3", load_ids=["A1", "B-7", "C3"], load_side_m=0.10
    )
    assert n == 4 + 1  # 10 cm labels (138 mm with quiet zone): 2 x 2 per A3 page
    assert path.read_bytes()[:5] == b"%PDF-"
    assert _pdf_page_count(path) == n
    assert not list(tmp_path.glob(".*part"))


def test_symbol_side_is_exact_on_paper():
    pages = sheet_pages(grid=(3, 1), side_m=0.05, load_ids=["pallet 12"], load_side_m=0.04)
    assert [len(p.codes) for p in pages] == [3, 1]
    W, H = (v / MM_PER_INCH for v in PAGES_MM["A4"])
    for page in pages:
        fig = page_figure(page)
        assert tuple(fig.get_size_inches()) == pytest.approx((W, H), abs=1e-12)
        axes = fig.get_axes()
        for ax, code in zip(axes, page.codes):
            x0, y0, w, h = ax.get_position().bounds
            assert w * W * MM_PER_INCH == pytest.approx(code.side_m * 1000, abs=1e-9)
            assert h * H * MM_PER_INCH == pytest.approx(code.side_m * 1000, abs=1e-9)
            n = symbol_modules(code.payload).shape[0]
            assert ax.get_xlim() == (0, n) and ax.get_ylim() == (0, n)
            assert 0 <= x0 and x0 + w <= 1 and 0 <= y0 and y0 + h <= 1


def test_rendered_page_decodes_and_measures_true_size():
    import zxingcpp
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    dpi = 150
    pages = sheet_pages(grid=(2, 1), side_m=0.05)
    fig = page_figure(pages[0])
    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    canvas.draw()
    img = np.asarray(canvas.buffer_rgba())[:, :, 0]
    assert sorted(b.text for b in zxingcpp.read_barcodes(img)) == ["0/0/0", "0/1/0"]
    code = pages[0].codes[0]
    H_px = img.shape[0]
    r0 = int(round(H_px - (code.y_in + code.side_in) * dpi))
    c0 = int(round(code.x_in * dpi))
    s = code.side_in * dpi
    win = img[r0 - 10 : r0 + int(s) + 10, c0 - 10 : c0 + int(s) + 10] < 128
    ys, xs = np.nonzero(win)
    # measured dark extent = 5 cm at 150 dpi = 295.3 px (within a pixel of rasterisation)
    assert abs(xs.max() - xs.min() + 1 - s) <= 1.0 and abs(ys.max() - ys.min() + 1 - s) <= 1.0


def test_symbol_modules_crop_is_the_symbol():
    sym = symbol_modules("0/3/4")
    n = sym.shape[0]
    assert sym.shape == (21, 21)  # version 1, no quiet zone
    for r, c in ((0, 0), (0, n - 7), (n - 7, 0)):  # the three finder patterns' outer rings
        assert sym[r, c : c + 7].all() and sym[r : r + 7, c].all()


@pytest.mark.parametrize("bad", ["", " lead", "tab\there", "new\nline", "x" * 65, "bell\x07"])
def test_unprintable_load_id_is_refused(tmp_path, bad):
    with pytest.raises(QRSheetError):
        write_qr_sheet(tmp_path / "s.pdf", grid=(0, 0), load_ids=[bad])
    assert not (tmp_path / "s.pdf").exists()


def test_impossible_sheets_raise_clear_errors(tmp_path):
    with pytest.raises(QRSheetError, match="A4"):
        write_qr_sheet(tmp_path / "s.pdf", grid=(1, 1), side_m=0.20, page="A4")
    assert write_qr_sheet(tmp_path / "letter.pdf", grid=(1, 1), side_m=0.05, page="letter") == 1
    (tmp_path / "letter.pdf").unlink()
    with pytest.raises(QRSheetError, match="page size"):
        write_qr_sheet(tmp_path / "s.pdf", grid=(1, 1), side_m=0.05, page="B9")
    with pytest.raises(QRSheetError, match="twice"):
        write_qr_sheet(tmp_path / "s.pdf", grid=(0, 0), load_ids=["A", "A"])
    with pytest.raises(QRSheetError, match="nothing"):
        write_qr_sheet(tmp_path / "s.pdf", grid=(0, 0))
    with pytest.raises(QRSheetError, match="side_m"):
        write_qr_sheet(tmp_path / "s.pdf", grid=(1, 1), side_m=-0.1)
    with pytest.raises(QRSheetError, match="1000 x 1000 grid is 1,000,000 floor codes"):
        write_qr_sheet(tmp_path / "s.pdf", grid=(1000, 1000), side_m=0.05)
    assert not list(tmp_path.iterdir())


def test_floor_payloads_follow_the_grid_and_unit():
    pages = sheet_pages(grid=(3, 2), spacing_m=0.5, payload_unit_m=0.5, side_m=0.03)
    payloads = [c.payload for p in pages for c in p.codes]
    assert payloads == ["0/0/0", "0/1/0", "0/2/0", "0/0/1", "0/1/1", "0/2/1"]
    pages = sheet_pages(grid=(2, 1), spacing_m=0.25, payload_unit_m=1.0, side_m=0.03)
    assert [c.payload for p in pages for c in p.codes] == ["0/0/0", "0/0.25/0"]
