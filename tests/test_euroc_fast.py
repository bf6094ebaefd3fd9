"""The EuRoC reader's fast paths (fusion.log.euroc): numeric CSVs by numpy's C parser
(`_numeric_csv_fast`) and image paths without a `resolve()` per frame.  Each must give what the
row parser / resolve() gives, to the bit, and leave every error to them (same message)."""

import os

import numpy as np
import pytest

import fusion.log.euroc as euroc
from fusion.errors import LogError
from fusion.log import read_flight
from tests.test_log import write_small_log

HEADER = "#timestamp [ns],a,b,c\n"


def _row_parser(path, ncols, with_lines=False):
    """_numeric_csv with the fast path switched off: the reference."""
    saved = euroc._numeric_csv_fast
    euroc._numeric_csv_fast = lambda *a: None
    try:
        return euroc._numeric_csv(path, ncols, with_lines)
    finally:
        euroc._numeric_csv_fast = saved


def _same(a, b):
    return all(x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes() for x, y in zip(a, b))


def _number_texts(rng, n):
    """Decimal spellings a logger may write: repr, %g / %e at several precisions, signs, a bare
    point, leading zeros, long mantissas (rounding), large and tiny exponents, subnormals."""
    x = rng.normal(size=n) * 10.0 ** rng.integers(-30, 30, n)
    out = []
    for i, v in enumerate(x):
        k = i % 12
        if k == 0:
            out.append(repr(float(v)))
        elif k == 1:
            out.append(f"{v:.17g}")
        elif k == 2:
            out.append(f"{v:.3e}")
        elif k == 3:
            out.append(f"{v:+.6f}")
        elif k == 4:
            out.append(f"{abs(v):.0f}.")
        elif k == 5:
            out.append("." + "".join(str(d) for d in rng.integers(0, 10, 25)))
        elif k == 6:
            out.append("000" + "".join(str(d) for d in rng.integers(0, 10, 30)) + "E-40")
        elif k == 7:
            out.append(f"{v:.25e}")
        elif k == 8:
            out.append(f"{rng.integers(1, 9)}e-{rng.integers(300, 324)}")  # subnormal range
        elif k == 9:
            out.append("-0")
        elif k == 10:
            out.append(f"{v:E}")
        else:
            out.append(str(int(rng.integers(-(10**6), 10**6))))
    return out


@pytest.fixture(params=[None, 7, 64, 1000], ids=["block-default", "block-7", "block-64", "block-1000"])
def block(request, monkeypatch):
    """The fast path's block size: the default (one block for these small files) and blocks
    smaller than a line, than a few lines, than the file (rows, comments and errors straddling
    the blocks' ends)."""
    if request.param is not None:
        monkeypatch.setattr(euroc, "_FAST_BLOCK_BYTES", request.param)
    return request.param


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_path_equals_the_row_parser_to_the_bit(tmp_path, seed, block):
    rng = np.random.default_rng(seed)
    n = 300
    t = np.cumsum(rng.integers(1, 10**7, n)) + int(rng.integers(0, 10**18))
    texts = _number_texts(rng, 3 * n)
    lines = [HEADER.rstrip("\n")]
    for i in range(n):
        lines.append(f"{t[i]}," + ",".join(texts[3 * i : 3 * i + 3]))
        if i % 97 == 5:
            lines.append("")  # an empty line, skipped
        if i % 89 == 7:
            lines.append("# a comment, with commas, and \t tabs")
    path = tmp_path / "data.csv"
    path.write_text("\n".join(lines) + ("\n" if seed else ""))  # seed 0: no final newline
    fast = euroc._numeric_csv_fast(path, 4)
    assert fast is not None
    assert _same(fast, _row_parser(path, 4, with_lines=True))
    assert _same(euroc._numeric_csv(path, 4), _row_parser(path, 4))


GOOD = [HEADER.rstrip("\n"), "10,1.5,2,3", "20,4,5,6", "30,7,8,9"]


@pytest.mark.parametrize(
    "edit",
    [
        # errors the row parser names (file and line)
        lambda L: L[:2] + ["20,4,5"] + L[3:],  # short row
        lambda L: L[:2] + ["20,4,5,6,7"] + L[3:],  # long row
        lambda L: L[:2] + ["20,4,,6"] + L[3:],  # empty field
        lambda L: L[:2] + ["20,4,5,"] + L[3:],  # trailing comma, a field short
        lambda L: L[:2] + ["20,4,nan,6"] + L[3:],
        lambda L: L[:2] + ["20,4,inf,6"] + L[3:],
        lambda L: L[:2] + ["20,4,1e999,6"] + L[3:],  # overflows to inf
        lambda L: L[:2] + ["20,4,abc,6"] + L[3:],
        lambda L: L[:2] + ["20,4,1.2.3,6"] + L[3:],
        lambda L: L[:2] + ["20,4,1e,6"] + L[3:],
        lambda L: L[:2] + ["20,4,--1,6"] + L[3:],
        lambda L: L[:2] + ["20,4,1-2,6"] + L[3:],
        lambda L: L[:2] + ["20,4,.,6"] + L[3:],
        lambda L: L[:2] + ["20,4,5#x,6"] + L[3:],  # '#' inside a row
        lambda L: L[:2] + ["20,4,5,6 # x"] + L[3:],
        lambda L: L[:2] + ["-20,4,5,6"] + L[3:],  # negative timestamp
        lambda L: L[:2] + ["+20,4,5,6"] + L[3:],
        lambda L: L[:2] + ["2e1,4,5,6"] + L[3:],
        lambda L: L[:2] + ["20.0,4,5,6"] + L[3:],
        lambda L: L[:2] + [",4,5,6"] + L[3:],
        lambda L: L[:2] + ["99999999999999999999,4,5,6"] + L[3:],  # 20 digits
        lambda L: L[:2] + ["9223372036854775808,4,5,6"] + L[3:],  # INT64_MAX + 1
        lambda L: L[:2] + ["10,4,5,6"] + L[3:],  # duplicate timestamp
        lambda L: L[:2] + ["5,4,5,6"] + L[3:],  # backwards
        lambda L: L + ["#" + "x" * 70] + ["30,1,2,3"],  # duplicate after a long comment
        lambda L: L + ["29,1,2,3"],  # backwards in the last row
        lambda L: L[:2] + ['20,"4",5,6'] + L[3:],  # quoted (the row parser reads it)
        lambda L: L[:1],  # no data rows
        lambda L: [],  # empty file
        # accepted by the row parser only: it must still read them
        lambda L: L[:2] + ["20, 4,5 ,6"] + L[3:],  # blanks around fields
        lambda L: L[:2] + ["  "] + L[2:],  # a blank line
        lambda L: L[:2] + ["  # indented comment"] + L[2:],
        lambda L: L[:2] + ["20,4_0,5,6"] + L[3:],  # float() takes underscores
        lambda L: L[:2] + ["20,4,\u0665,6"] + L[3:],  # float() takes Arabic-Indic digits
        lambda L: [L[0] + " \u00b5s"] + L[1:],  # non-ASCII header
    ],
)
def test_anything_unusual_is_left_to_the_row_parser(tmp_path, edit, block):
    """The fast path declines (None) every file it cannot read exactly as the row parser does;
    _numeric_csv then gives the row parser's value or its one-line error, naming file and line."""
    path = tmp_path / "data.csv"
    path.write_text("\n".join(edit(list(GOOD))) + "\n")
    assert euroc._numeric_csv_fast(path, 4) is None
    try:
        want = _row_parser(path, 4, with_lines=True)
    except LogError as e:
        with pytest.raises(LogError) as got:
            euroc._numeric_csv(path, 4, with_lines=True)
        assert str(got.value) == str(e)
        assert str(got.value).startswith(f"{path}")
    else:
        assert _same(euroc._numeric_csv(path, 4, with_lines=True), want)


@pytest.mark.parametrize(
    "data",
    [
        b"\xef\xbb\xbf" + "\n".join(GOOD).encode(),
        "\r\n".join(GOOD).encode(),
        b"10,1,2,3\n\xff\n",
        b"10,1,2\x00,3\n",
    ],
)
def test_byte_order_mark_crlf_and_bad_bytes_left_to_the_row_parser(tmp_path, data, block):
    path = tmp_path / "data.csv"
    path.write_bytes(data)
    assert euroc._numeric_csv_fast(path, 4) is None
    try:
        want = _row_parser(path, 4, with_lines=True)
    except LogError as e:
        with pytest.raises(LogError, match="^" + str(e).replace("(", r"\(").replace(")", r"\)") + "$"):
            euroc._numeric_csv(path, 4, with_lines=True)
    else:
        assert _same(euroc._numeric_csv(path, 4, with_lines=True), want)


def test_not_a_regular_file_is_the_same_error(tmp_path):
    with pytest.raises(LogError, match="file not found"):
        euroc._numeric_csv(tmp_path / "missing.csv", 4)
    with pytest.raises(LogError, match="is a folder"):
        euroc._numeric_csv(tmp_path, 4)


def _resolved_paths(log):
    return [p.resolve() for p in log.floor.paths]


def test_image_paths_are_what_resolve_gives(tmp_path):
    root = tmp_path / "flight"
    write_small_log(root)
    log = read_flight(root)
    assert log.floor.paths == _resolved_paths(log)
    assert all(p.parent == (root / "mav0" / "cam0" / "data").resolve() for p in log.floor.paths)


def test_image_symlinks_are_still_resolved_and_checked(tmp_path):
    """A frame's file that is a symbolic link is resolved as before: one to a file inside the
    data folder is read through its target; one leading outside is refused naming the line."""
    root = tmp_path / "flight"
    write_small_log(root)
    data = root / "mav0" / "cam0" / "data"
    files = sorted(data.iterdir())
    inside = data / "inside.png"
    os.replace(files[1], inside)
    files[1].symlink_to(inside.name)
    log = read_flight(root)
    assert log.floor.paths[1] == inside.resolve()
    assert log.floor.paths == _resolved_paths(log)
    outside = tmp_path / "elsewhere.png"
    outside.write_bytes(inside.read_bytes())
    files[1].unlink()
    files[1].symlink_to(outside)
    csv_lines = (root / "mav0" / "cam0" / "data.csv").read_text().splitlines()
    line = next(i for i, l in enumerate(csv_lines, 1) if l.endswith(files[1].name))
    with pytest.raises(LogError, match=rf"cam0/data.csv:{line}: file name .* points outside"):
        read_flight(root)


def test_the_data_folder_a_symlink_and_dotted_names(tmp_path):
    root = tmp_path / "flight"
    write_small_log(root)
    cam = root / "mav0" / "cam0"
    real = tmp_path / "images"
    os.replace(cam / "data", real)
    (cam / "data").symlink_to(real)
    log = read_flight(root)
    assert log.floor.paths == _resolved_paths(log)
    assert all(p.parent == real.resolve() for p in log.floor.paths)
    csv_path = cam / "data.csv"
    lines = csv_path.read_text().splitlines()
    t, name = lines[2].split(",")
    lines[2] = f"{t},./{name}"  # not a plain name: resolved, the same file
    csv_path.write_text("\n".join(lines) + "\n")
    log = read_flight(root)
    assert log.floor.paths == _resolved_paths(log)
    lines[2] = f"{t},.."
    csv_path.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogError, match=r"cam0/data.csv:3: file name '..' points outside"):
        read_flight(root)


def test_a_link_differing_only_in_case_is_resolved(tmp_path, monkeypatch):
    """On a case-insensitive file system 'X.PNG' in data.csv opens the link 'x.png': a name
    whose lower case is a link's is resolved like a link (here, on a case-sensitive one, it
    resolves to itself; the point is that it goes through resolve())."""
    root = tmp_path / "flight"
    write_small_log(root)
    data = root / "mav0" / "cam0" / "data"
    files = sorted(data.iterdir())
    (data / "link.png").symlink_to(files[0].name)
    csv_path = root / "mav0" / "cam0" / "data.csv"
    lines = csv_path.read_text().splitlines()
    t, _ = lines[1].split(",")
    lines[1] = f"{t},LINK.png"
    csv_path.write_text("\n".join(lines) + "\n")
    resolved = []
    real_resolve = type(data).resolve

    def spy(self, *a, **k):
        resolved.append(self.name)
        return real_resolve(self, *a, **k)

    monkeypatch.setattr(type(data), "resolve", spy)
    log = read_flight(root)
    assert "LINK.png" in resolved
    assert log.floor.paths[0] == real_resolve(data) / "LINK.png"
    assert sum(n.endswith(".png") for n in resolved) == 1  # the plain names are not resolved
