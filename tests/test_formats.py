"""Tests of the file-format layer :mod:`nfdmatch.formats`."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nfdmatch.curve import Curve
from nfdmatch.errors import (
    CurveError,
    WriteError,
    CurveSelectionError,
    NfdError,
    NoCurvesError,
    ParameterError,
    ParseError,
    ReadError,
    UnknownFormatError,
)
from nfdmatch.formats import (
    FORMATS,
    format_of,
    read_curve,
    read_curves,
    split_selector,
    supported_extensions,
    write_curves,
)
from nfdmatch.formats import csv as csv_format
from nfdmatch.formats import obj as obj_format
from nfdmatch.formats import vtk as vtk_format
from nfdmatch._graph import chain_segments

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data" / "formats"

SQUARE = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]


def data(name: str) -> str:
    return str(DATA / name)


def write(tmp_path: Path, name: str, content: str | bytes) -> str:
    p = tmp_path / name
    if isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content, encoding="utf-8")
    return str(p)


def expect(exc_type, path: str, call, *, line: int | None = None, contains=()):
    """Run ``call``; assert the exception class, the file name and the line in the message."""
    with pytest.raises(exc_type) as info:
        call()
    err = info.value
    msg = str(err)
    assert Path(path).name in msg, msg
    if line is not None:
        assert err.line == line, msg
        assert f"line {line}" in msg, msg
    for text in contains:
        assert text in msg, msg
    return err


def same_cycle(a, b) -> bool:
    """True when two vertex sequences are the same closed cycle up to start and direction."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        return False
    for cand in (b, b[::-1]):
        for k in range(len(cand)):
            if np.array_equal(a, np.roll(cand, k, axis=0)):
                return True
    return False


def random_curve(rng, n=40, scale=1.0):
    t = np.sort(rng.uniform(0, 2 * np.pi, n))
    pts = np.column_stack([np.cos(t) * 3, np.sin(t) * 2, rng.normal(size=n)]) * scale
    return pts + rng.normal(scale=1e-3 * scale, size=pts.shape)


# ---------------------------------------------------------------------------
# registry, selectors, lazy imports
# ---------------------------------------------------------------------------


def test_every_format_module_has_read_points_and_write():
    for mod in (csv_format, obj_format, vtk_format):
        assert callable(mod.write) and callable(mod.read_points)


def test_register_refuses_an_extension_of_another_format():
    from nfdmatch.formats import register

    with pytest.raises(ValueError, match=".obj"):
        register("other", (".OBJ",), obj_format.read_points, obj_format.write)
    assert format_of("x.obj") == "obj"


def test_registry():
    assert set(FORMATS) == {"csv", "obj", "vtk", "vtp", "vtu"}
    exts = supported_extensions()
    for ext in (".csv", ".tsv", ".txt", ".xyz", ".obj", ".vtk", ".vtp", ".vtu"):
        assert ext in exts
    assert format_of("a/B.TSV") == "csv"
    assert format_of("x.OBJ") == "obj"
    assert format_of("x.dat", "VTP") == "vtp"
    assert format_of("x.dat", ".xyz") == "csv"


def test_unknown_extension_lists_extensions_and_format_option(tmp_path):
    p = write(tmp_path, "curve.dat", "0 0 0\n1 0 0\n0 1 0\n")
    err = expect(UnknownFormatError, p, lambda: read_curves(p), contains=(".csv", ".obj", ".vtp", "--input-format"))
    assert isinstance(err, ValueError)
    noext = write(tmp_path, "curve", "0 0 0\n1 0 0\n0 1 0\n")
    expect(UnknownFormatError, noext, lambda: read_curves(noext), contains=("--input-format",))
    expect(UnknownFormatError, p, lambda: read_curves(p, format="stl"), contains=("csv, obj",))
    expect(UnknownFormatError, str(tmp_path / "out.stl"), lambda: write_curves(tmp_path / "out.stl", [SQUARE]))
    mesh = write(tmp_path, "part.stl", "solid x\nendsolid x\n")
    expect(UnknownFormatError, mesh, lambda: read_curves(mesh), contains=("triangle mesh", "nfdmatch extract"))


def test_format_override(tmp_path):
    p = write(tmp_path, "curve.dat", "x y z\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n")
    (c,) = read_curves(p, format="csv")
    assert c.points.tolist() == SQUARE
    q = str(tmp_path / "loops.data")
    write_curves(q, [SQUARE], format="vtp")
    assert read_curves(q, format="vtp")[0].points.tolist() == SQUARE
    r = str(tmp_path / "loops.bin")
    write_curves(r, [SQUARE], format="obj")
    assert Path(r).read_text().startswith("#")
    assert read_curve(r, format="obj").points.tolist() == SQUARE


def test_extension_case_insensitive(tmp_path):
    p = write(tmp_path, "SQUARE.CSV", (DATA / "square.csv").read_text())
    assert read_curves(p)[0].points.tolist() == SQUARE


def test_split_selector(tmp_path):
    f = write(tmp_path, "f.obj", (DATA / "two_squares.obj").read_text())
    assert split_selector(f + "#1") == (f, 1)
    assert split_selector(f) == (f, None)
    assert split_selector(f + "#") == (f + "#", None)
    assert split_selector(f + "#x") == (f + "#x", None)
    assert split_selector("missing.obj#3") == ("missing.obj", 3)  # nothing exists: split
    assert split_selector(Path(f)) == (f, None)
    # only the last '#' counts
    weird = write(tmp_path, "a#b.obj", (DATA / "two_squares.obj").read_text())
    assert split_selector(weird + "#0") == (weird, 0)
    assert split_selector(weird) == (weird, None)
    # a file really named "curve.obj#2" (and no curve.obj) is not split
    literal = write(tmp_path, "curve.obj#2", (DATA / "two_squares.obj").read_text())
    assert split_selector(literal) == (literal, None)
    assert len(read_curves(literal, format="obj")) == 2


def test_importing_formats_does_not_import_pyvista_or_trimesh():
    code = (
        "import sys, nfdmatch.formats\n"
        "bad = [m for m in ('pyvista', 'vtk', 'vtkmodules', 'trimesh') if m in sys.modules]\n"
        "print(bad)\n"
        "sys.exit(1 if bad else 0)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr


# ---------------------------------------------------------------------------
# missing / unreadable files (every format)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".csv", ".obj", ".vtk", ".vtp", ".vtu"])
def test_missing_file(tmp_path, ext):
    p = str(tmp_path / f"nope{ext}")
    err = expect(ReadError, p, lambda: read_curves(p), contains=("no such file",))
    assert isinstance(err, OSError)
    expect(ReadError, p, lambda: read_curve(p))


@pytest.mark.parametrize("ext", [".csv", ".obj", ".vtp"])
def test_directory_is_read_error(tmp_path, ext):
    d = tmp_path / f"folder{ext}"
    d.mkdir()
    expect(ReadError, str(d), lambda: read_curves(d), contains=("directory",))


def test_permission_denied_is_read_error(tmp_path, monkeypatch):
    from nfdmatch.formats import _chain

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    p = write(tmp_path, "locked.obj", (DATA / "two_squares.obj").read_text())
    monkeypatch.setattr(_chain, "open", denied, raising=False)
    monkeypatch.setattr(_chain, "_os_open", denied)
    expect(ReadError, p, lambda: read_curves(p), contains=("permission denied",))
    expect(
        WriteError,
        str(tmp_path / "out.csv"),
        lambda: write_curves(tmp_path / "out.csv", [SQUARE]),
        contains=("permission denied",),
    )


# ---------------------------------------------------------------------------
# CSV / TSV / TXT / XYZ
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name",
    [
        "square.csv",
        "square_semicolon.csv",
        "square.tsv",
        "square.xyz",
        "square_2d.txt",
        "extra_columns.csv",
        "commented.csv",
    ],
)
def test_csv_good_files(name):
    curves = read_curves(data(name))
    assert len(curves) == 1
    c = curves[0]
    assert c.points.dtype == np.float64 and c.points.shape == (4, 3)
    assert c.points.tolist() == SQUARE
    assert c.id == data(name) and c.source == data(name) and c.index is None


def test_csv_2d_gives_z_zero():
    c = read_curve(data("square_2d.txt"))
    assert c.in_xy_plane


@pytest.mark.parametrize(
    "text",
    [
        "x,y,z\r\n0,0,0\r\n1,0,0\r\n1,1,0\r\n0,1,0\r\n",  # Windows line ends
        "x,y,z\r0,0,0\r1,0,0\r1,1,0\r0,1,0\r",  # old Mac line ends
        "\ufeffx,y,z\n0,0,0\n1,0,0\n1,1,0\n0,1,0\n",  # byte-order mark
        "0,0,0\n1,0,0\n1,1,0\n0,1,0",  # no header, no final newline
        "  0 ,\t0 , 0\n1 , 0 , 0\n 1,1,0 \n0,1,0\n",  # whitespace around delimiters
        "0\t0\t0\n1\t0\t0\n1\t1\t0\n0\t1\t0\n",  # tabs, no header
        '"x","y","z"\n0,0,0\n1,0,0\n1,1,0\n0,1,0\n',  # quoted header
        "x y z\n0,0,0\n1,0,0\n1,1,0\n0,1,0\n",  # header split differently
        "a;b;c\n0;0;0\n1;0;0\n1;1;0\n0;1;0\n",  # header without x, y, z names
        "X,Y\n0,0\n1,0\n1,1\n0,1\n",  # 2 named columns
        "name,x,y\np,0,0\nq,1,0\nr,1,1\ns,0,1\n",  # text column ignored, z = 0
    ],
)
def test_csv_layouts(tmp_path, text):
    p = write(tmp_path, "c.csv", text)
    assert read_curve(p).points.tolist() == SQUARE


def test_csv_duplicates_and_closing_vertex_are_cleaned(tmp_path):
    p = write(tmp_path, "d.csv", "0,0,0\n0,0,0\n1,0,0\n1,1,0\n1,1,0\n0,1,0\n0,0,0\n0,0,0\n")
    assert read_curve(p).points.tolist() == SQUARE


@pytest.mark.parametrize(
    "rows",
    [
        "0,0,0\n1,0,0\n2,0,0\n1,0,0\n",  # collinear back and forth
        "1e12,0,0\n2e12,0,0\n2e12,1e12,3e12\n",  # huge
        "1e-12,0,0\n2e-12,0,0\n2e-12,1e-12,3e-12\n",  # tiny
    ],
)
def test_csv_degenerate_but_valid(tmp_path, rows):
    p = write(tmp_path, "g.csv", rows)
    pts = read_curve(p).points
    assert np.isfinite(pts).all() and len(pts) >= 3


def test_csv_bad_token():
    p = data("bad_token.csv")
    expect(ParseError, p, lambda: read_curves(p), line=4, contains=("'abc'",))


def test_csv_decimal_comma_hint(tmp_path):
    p = write(tmp_path, "eu.csv", "x;y;z\n0;0;0\n1,5;0;0\n1;1;0\n")
    expect(ParseError, p, lambda: read_curves(p), line=3, contains=("'1,5'", "decimal comma"))


def test_csv_empty_cell(tmp_path):
    p = write(tmp_path, "e.csv", "x,y,z\n0,0,0\n1,,0\n1,1,0\n")
    expect(ParseError, p, lambda: read_curves(p), line=3, contains=("empty",))


def test_csv_ragged():
    p = data("ragged.csv")
    expect(ParseError, p, lambda: read_curves(p), line=4, contains=("expected 3", "got 2"))


def test_csv_ragged_line_numbers_count_comments_and_blanks(tmp_path):
    p = write(tmp_path, "r.csv", "# c\n\nx,y,z\n0,0,0\n\n# c\n1,0,0,7\n")
    expect(ParseError, p, lambda: read_curves(p), line=7, contains=("got 4",))


def test_csv_header_column_mismatch(tmp_path):
    p = write(tmp_path, "h.csv", "x,y,z,w\n0,0,0\n1,0,0\n1,1,0\n")
    expect(ParseError, p, lambda: read_curves(p), line=2)


@pytest.mark.parametrize("text,line", [("0 0 0 0\n1 0 0 0\n0 1 0 0\n", 1), ("x\n0\n1\n", 2)])
def test_csv_wrong_column_count(tmp_path, text, line):
    p = write(tmp_path, "w.csv", text)
    expect(ParseError, p, lambda: read_curves(p), line=line, contains=("columns",))


@pytest.mark.parametrize("bad", ["nan", "NaN", "inf", "-Infinity", "1e999"])
def test_csv_non_finite(tmp_path, bad):
    p = write(tmp_path, "n.csv", f"x,y,z\n0,0,0\n1,0,0\n\n1,{bad},0\n0,1,0\n")
    err = expect(CurveError, p, lambda: read_curves(p), line=5)
    assert "finite" in str(err)
    expect(CurveError, data("nan.csv"), lambda: read_curves(data("nan.csv")), line=4)


def test_csv_empty_file():
    p = data("empty.csv")
    expect(ParseError, p, lambda: read_curves(p), contains=("empty",))


def test_csv_whitespace_only(tmp_path):
    p = write(tmp_path, "ws.csv", "  \n\n\t\n")
    expect(ParseError, p, lambda: read_curves(p), contains=("empty",))


def test_csv_comments_only(tmp_path):
    p = write(tmp_path, "cm.csv", "# just\n# comments\n")
    expect(ParseError, p, lambda: read_curves(p), contains=("no data rows",))


def test_csv_header_only():
    p = data("header_only.csv")
    expect(ParseError, p, lambda: read_curves(p), line=2, contains=("no data rows",))


def test_csv_too_few_points():
    p = data("two_points.csv")
    expect(CurveError, p, lambda: read_curves(p), contains=("3 distinct points",))


def test_csv_zero_perimeter_single_point(tmp_path):
    p = write(tmp_path, "z.csv", "1,1,1\n1,1,1\n1,1,1\n")
    expect(CurveError, p, lambda: read_curves(p))


@pytest.mark.parametrize("name", ["binary.csv", "latin1.csv"])
def test_csv_not_text(name):
    p = data(name)
    expect(ParseError, p, lambda: read_curves(p), contains=("not a text file",))


def test_csv_random_binary_garbage(tmp_path):
    rng = np.random.default_rng(7)
    for k in range(5):
        p = write(tmp_path, f"junk{k}.csv", rng.integers(0, 256, 500, dtype=np.uint8).tobytes())
        expect(ParseError, p, lambda: read_curves(p), contains=("not a text file",))


def test_csv_big_file_reads_exactly(tmp_path):
    # speed is measured by benchmarks, not asserted here (a busy machine would fail it)
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(100_000, 3))
    p = str(tmp_path / "big.csv")
    write_curves(p, [pts])
    (c,) = read_curves(p)
    assert np.array_equal(c.points, pts)


def test_csv_writes_exactly_one_curve(tmp_path):
    p = str(tmp_path / "two.csv")
    expect(ParameterError, p, lambda: write_curves(p, [SQUARE, SQUARE]), contains=("one curve",))
    assert not os.path.exists(p)


def test_csv_written_layout(tmp_path):
    p = tmp_path / "w.csv"
    write_curves(p, [np.array(SQUARE) + 0.1])
    lines = p.read_text().splitlines()
    assert lines[0] == "x,y,z" and lines[1] == "0.1,0.1,0.1" and len(lines) == 5
    t = tmp_path / "w.tsv"
    write_curves(t, [SQUARE])
    assert t.read_text().splitlines()[0] == "x\ty\tz"


# ---------------------------------------------------------------------------
# OBJ
# ---------------------------------------------------------------------------


def test_obj_two_polylines_with_other_elements():
    p = data("two_squares.obj")
    curves = read_curves(p)
    assert [c.id for c in curves] == [f"{p}#0", f"{p}#1"]
    assert [c.index for c in curves] == [0, 1]
    assert all(c.source == p for c in curves)
    assert curves[0].points.tolist() == SQUARE
    assert curves[1].points.tolist() == [[0, 0, 5], [2, 0, 5], [2, 2, 5], [0, 2, 5]]


def test_obj_read_curve_selector():
    p = data("two_squares.obj")
    c = read_curve(p + "#1")
    assert c.id == f"{p}#1" and c.index == 1 and c.points[0].tolist() == [0, 0, 5]


def test_multi_curve_without_selector_gives_count_and_how_to_pick():
    p = data("two_squares.obj")
    err = expect(CurveSelectionError, p, lambda: read_curve(p), contains=("2 curves", "#0", "#1"))
    assert isinstance(err, ValueError)


@pytest.mark.parametrize("sel", [2, 17, -1])
def test_selector_out_of_range(sel):
    p = data("two_squares.obj")
    expect(CurveSelectionError, p, lambda: read_curve(f"{p}#{sel}"), contains=("2 curves",))


def test_single_curve_file_selectors():
    p = data("square.csv")
    assert read_curve(p + "#0").id == p
    expect(CurveSelectionError, p, lambda: read_curve(p + "#1"))


def test_obj_segments_chained_into_one_loop():
    (c,) = read_curves(data("segments.obj"))
    h = 0.8660254037844386
    hexagon = [[1, 0, 0], [0.5, h, 0], [-0.5, h, 0], [-1, 0, 0], [-0.5, -h, 0], [0.5, -h, 0]]
    assert same_cycle(c.points, np.array(hexagon))
    # walked from the first segment (l 3 4) in its direction
    assert c.points[:2].tolist() == [hexagon[2], hexagon[3]]


@pytest.mark.parametrize("ext", [".obj", ".vtp", ".vtk"])
def test_shuffled_reversed_segment_files_give_the_curve(tmp_path, ext):
    rng = np.random.default_rng(4)
    pts = random_curve(rng, 50)
    n = len(pts)
    perm = rng.permutation(n)  # vertices stored in random order
    stored = pts[perm]
    where = np.argsort(perm)  # where[i] = stored position of vertex i
    segs = np.column_stack([where, np.roll(where, -1)])
    flip = rng.random(n) < 0.5
    segs[flip] = segs[flip][:, ::-1]
    segs = segs[rng.permutation(n)]
    p = str(tmp_path / f"segs{ext}")
    if ext == ".obj":
        lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in stored.tolist()]
        lines += [f"l {a + 1} {b + 1}" for a, b in segs.tolist()]
        Path(p).write_text("\n".join(lines) + "\n")
    else:
        pv = vtk_format._pyvista()
        cells = np.column_stack([np.full(n, 2), segs]).ravel()
        pv.PolyData(stored, lines=cells).save(p)
    (c,) = read_curves(p)
    assert same_cycle(c.points, pts)


def test_obj_continuation_lines():
    assert read_curve(data("continuation.obj")).points.tolist() == SQUARE


@pytest.mark.parametrize(
    "text",
    [
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nl 1 2 3 4\n",  # closing index implicit
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nl 1 2 3 4 1\n",  # closing index repeated
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nl -4 -3 -2 -1\n",  # relative indices
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nl 1/1 2/2 3/3 4/4 1/1\n",  # v/vt forms
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nl 1//1 2//1 3//1 4//1\n",  # v//vn forms
        "v 0 0 0 1\nv 1 0 0 1\nv 1 1 0 1\nv 0 1 0 1\nl 1 2 3 4\n",  # w coordinate
        "v 0 0 0 1 0 0\nv 1 0 0 1 0 0\nv 1 1 0 0 1 0\nv 0 1 0 0 0 1\nl 1 2 3 4\n",  # colours
        "v 0 0 0\r\nv 1 0 0\r\nv 1 1 0\r\nv 0 1 0\r\nl 1 2 3 4\r\n",  # CRLF
        "  v 0 0 0 # c\n\tv 1 0 0\nv 1 1 0\nv 0 1 0\n# l 9 9\nl 1 2 3 4 # trailing\n",
        "v 0 0 0\nv 1 0 0\nl 1 2\nv 1 1 0\nv 0 1 0\nl 2 3\nl 4 3\nl 4 1\n",  # segments in 2 groups
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nl 1 2\nl 2 3\nl 3 4\n",  # open segment path
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nl 1 2\nl 2 3\nl 3 4\nl 4 1\nl 2 1\nl 3 3\n",  # dup + self
    ],
)
def test_obj_layouts(tmp_path, text):
    p = write(tmp_path, "c.obj", text)
    (c,) = read_curves(p)
    assert same_cycle(c.points, np.array(SQUARE))
    assert c.id == p and c.index is None


def test_obj_open_segment_path_is_walked_end_to_end(tmp_path):
    # the first segment (3 4) is in the middle of the path; its direction is kept
    p = write(tmp_path, "p.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 2 0\nl 3 4\nl 2 1\nl 5 4\nl 3 2\n")
    (c,) = read_curves(p)
    assert c.points.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 2, 0]]


def test_obj_polylines_and_segment_loops_in_file_order(tmp_path):
    p = write(
        tmp_path,
        "m.obj",
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
        "v 5 0 0\nv 6 0 0\nv 6 1 0\n"
        "v 9 0 0\nv 9 1 0\nv 8 1 0\n"
        "l 1 2\n"  # curve 0 starts here (segments 1-2-3-4)
        "l 5 6 7 5\n"  # curve 1
        "l 2 3\nl 3 4\nl 4 1\n"
        "l 8 9\nl 10 8\nl 9 10\n",
    )  # curve 2
    curves = read_curves(p)
    assert [c.id for c in curves] == [f"{p}#0", f"{p}#1", f"{p}#2"]
    assert same_cycle(curves[0].points, np.array(SQUARE))
    assert curves[1].points[:, 0].min() == 5
    assert curves[2].points[:, 0].max() == 9


def test_obj_mesh_without_polylines():
    p = data("mesh.obj")
    expect(NoCurvesError, p, lambda: read_curves(p), contains=("4 faces", "no polylines", "mesh", "extract contours"))


def test_obj_no_polylines(tmp_path):
    p = write(tmp_path, "v.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    expect(NoCurvesError, p, lambda: read_curves(p), contains=("no polylines",))
    q = write(tmp_path, "c.obj", "# only a comment\n")
    expect(NoCurvesError, q, lambda: read_curves(q), contains=("no polylines",))


def test_obj_empty(tmp_path):
    p = write(tmp_path, "e.obj", "")
    expect(ParseError, p, lambda: read_curves(p), contains=("empty",))


def test_obj_index_out_of_range():
    p = data("bad_index.obj")
    expect(ParseError, p, lambda: read_curves(p), line=4, contains=("7", "3 vertices"))


@pytest.mark.parametrize(
    "text,line,snippet",
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 0 1 2\n", 4, "index 0"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 -4\n", 4, "-4"),
        ("v 0 0 0\nv 1 0 0\n\nl 1 2 -1\nv 0 1 0\nl -5 1 2\n", 6, "-5"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 two 3\n", 4, "'two'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1\n", 4, "at least 2"),
        ("v 0 0 0\nv 1 zero 0\nv 0 1 0\nl 1 2 3\n", 2, "'zero'"),
        ("v 0 0 0\nv 1 0\nv 0 1 0\nl 1 2 3\n", 2, "3 coordinates"),
        ("v 0 0 0\nv 1 0 0 1 2\nv 0 1 0\nl 1 2 3\n", 2, "got 5"),
        ("v 0 0 0\nv 1 0 \\\n 0\nv 0 1 0\nl 1 2 3 9\n", 5, "out of range"),
    ],
)
def test_obj_bad_statements(tmp_path, text, line, snippet):
    p = write(tmp_path, "bad.obj", text)
    expect(ParseError, p, lambda: read_curves(p), line=line, contains=(snippet,))


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_obj_non_finite_vertex(tmp_path, bad):
    p = write(tmp_path, "n.obj", f"v 0 0 0\n# c\nv 1 {bad} 0\nv 0 1 0\nl 1 2 3\n")
    expect(CurveError, p, lambda: read_curves(p), line=3, contains=("finite",))


def test_obj_branching_vertex():
    p = data("branching.obj")
    expect(ParseError, p, lambda: read_curves(p), contains=("vertex 3", "branching", "line 10"))


def test_obj_two_point_segment_is_not_a_curve(tmp_path):
    p = write(tmp_path, "s.obj", "v 0 0 0\nv 1 0 0\nl 1 2\n")
    expect(CurveError, p, lambda: read_curves(p), contains=("3 distinct points",))


def test_obj_one_bad_curve_names_its_number(tmp_path):
    p = write(tmp_path, "two.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3\nl 1 2 1\n")
    err = expect(CurveError, p, lambda: read_curves(p))
    assert err.curve == 1 and f"{Path(p).name}#1" in str(err)
    # the good curve can still be picked on its own
    assert read_curve(p + "#0").n_vertices == 3


@pytest.mark.parametrize("name", ["binary.obj", "latin1.obj"])
def test_obj_not_text(tmp_path, name):
    content = b"v 0 0 0\n\x00\x01\x02" if name == "binary.obj" else b"v 0 0 0 # caf\xe9\n"
    p = write(tmp_path, name, content)
    expect(ParseError, p, lambda: read_curves(p), contains=("not a text file",))


def test_obj_written_layout(tmp_path):
    p = tmp_path / "w.obj"
    write_curves(p, [SQUARE, np.array(SQUARE) * 2])
    lines = p.read_text().splitlines()
    assert [ln for ln in lines if ln.startswith("l")] == ["l 1 2 3 4 1", "l 5 6 7 8 5"]
    assert sum(ln.startswith("v ") for ln in lines) == 8


# ---------------------------------------------------------------------------
# VTK / VTP / VTU
# ---------------------------------------------------------------------------


def test_vtk_ascii_polyline():
    p = data("square_ascii.vtk")
    (c,) = read_curves(p)
    assert c.points.tolist() == SQUARE and c.id == p


def test_vtk_segments_chained_and_polyline():
    p = data("segments_ascii.vtk")
    curves = read_curves(p)
    assert [c.id for c in curves] == [f"{p}#0", f"{p}#1"]
    assert same_cycle(curves[0].points, np.array(SQUARE))
    assert curves[1].points.tolist() == [[5, 5, 5], [6, 5, 5], [5, 6, 5]]


def test_vtp_two_loops_ids_and_selector():
    p = data("two_loops_ascii.vtp")
    curves = read_curves(p)
    assert [c.id for c in curves] == [f"{p}#0", f"{p}#1"]
    assert read_curve(p + "#1").points.tolist() == [[5, 5, 5], [6, 5, 5], [5, 6, 5]]
    expect(CurveSelectionError, p, lambda: read_curve(p), contains=("2 curves",))


def test_vtu_line_cells_among_other_cells():
    (c,) = read_curves(data("mixed_ascii.vtu"))
    assert same_cycle(c.points, np.array(SQUARE))


@pytest.mark.parametrize("name", ["triangles_ascii.vtk"])
def test_vtk_mesh_without_lines(name):
    p = data(name)
    expect(NoCurvesError, p, lambda: read_curves(p), contains=("mesh", "extract contours"))


def test_vtp_vtu_mesh_without_lines(tmp_path):
    pv = vtk_format._pyvista()
    sphere = pv.Sphere(theta_resolution=6, phi_resolution=6)
    for ext, mesh in ((".vtp", sphere), (".vtu", sphere.cast_to_unstructured_grid())):
        p = str(tmp_path / f"sphere{ext}")
        mesh.save(p)
        expect(NoCurvesError, p, lambda: read_curves(p), contains=("mesh",))


def test_vtk_other_dataset_type(tmp_path):
    pv = vtk_format._pyvista()
    p = str(tmp_path / "image.vtk")
    pv.ImageData(dimensions=(2, 2, 2)).save(p)
    expect(NoCurvesError, p, lambda: read_curves(p))


def test_vtk_points_only(tmp_path):
    pv = vtk_format._pyvista()
    p = str(tmp_path / "cloud.vtp")
    pv.PolyData(np.array(SQUARE)).save(p)  # vertex cells only
    expect(NoCurvesError, p, lambda: read_curves(p), contains=("no line cells",))


def test_vtk_polydata_with_vertex_cells_and_lines(tmp_path):
    pv = vtk_format._pyvista()
    mesh = pv.PolyData(np.array(SQUARE), lines=np.array([5, 0, 1, 2, 3, 0]), verts=np.array([1, 0, 1, 2]))
    p = str(tmp_path / "mixed.vtp")
    mesh.save(p)
    assert read_curve(p).points.tolist() == SQUARE


def test_vtk_branching_segments(tmp_path):
    p = write(
        tmp_path,
        "branch.vtk",
        "# vtk DataFile Version 3.0\nb\nASCII\nDATASET POLYDATA\nPOINTS 5 double\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 2 0\n"
        "LINES 5 15\n2 0 1\n2 1 2\n2 2 3\n2 3 0\n2 2 4\n",
    )
    expect(ParseError, p, lambda: read_curves(p), contains=("vertex 2", "branching", "cell 4"))


def test_vtk_single_point_line_cell(tmp_path):
    p = write(
        tmp_path,
        "one.vtk",
        "# vtk DataFile Version 3.0\nb\nASCII\nDATASET POLYDATA\nPOINTS 4 double\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\nLINES 2 7\n4 0 1 2 3\n1 2\n",
    )
    expect(ParseError, p, lambda: read_curves(p), contains=("line cell 1",))


@pytest.mark.parametrize("name", ["garbage.vtk", "garbage.vtp", "truncated.vtk", "truncated.vtp"])
def test_vtk_garbage_and_truncated(name, capfd, caplog):
    pv = vtk_format._pyvista()
    before = pv.vtk_verbosity()
    p = data(name)
    with caplog.at_level(logging.DEBUG):
        expect(ParseError, p, lambda: read_curves(p), contains=("could not be read as VTK",))
    out, err = capfd.readouterr()
    assert out == "" and err == "", (out, err)  # VTK kept quiet
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert pv.vtk_verbosity() == before


@pytest.mark.parametrize("ext", [".vtk", ".vtp", ".vtu"])
def test_vtk_empty_file(tmp_path, ext):
    p = write(tmp_path, f"empty{ext}", b"")
    expect(ParseError, p, lambda: read_curves(p), contains=("empty",))


@pytest.mark.parametrize("ext", [".vtk", ".vtp", ".vtu"])
def test_vtk_truncated_binary_files_never_leak(tmp_path, ext, capfd):
    rng = np.random.default_rng(3)
    src = str(tmp_path / f"src{ext}")
    write_curves(src, [random_curve(rng), random_curve(rng, 9)])
    blob = Path(src).read_bytes()
    cuts = sorted({1, 10, len(blob) // 3, len(blob) // 2, len(blob) - 40, len(blob) - 2})
    for n in cuts:
        p = write(tmp_path, f"cut{n}{ext}", blob[:n])
        with pytest.raises(NfdError) as info:
            read_curves(p)
        assert Path(p).name in str(info.value)
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_vtk_random_bytes_never_leak(tmp_path):
    rng = np.random.default_rng(11)
    for k, ext in enumerate([".vtk", ".vtp", ".vtu"] * 2):
        p = write(tmp_path, f"junk{k}{ext}", rng.integers(0, 256, 300, dtype=np.uint8).tobytes())
        with pytest.raises(ParseError):
            read_curves(p)


# ---------------------------------------------------------------------------
# writers: round trips
# ---------------------------------------------------------------------------

ALL_EXTS = [".csv", ".tsv", ".txt", ".xyz", ".obj", ".vtk", ".vtp", ".vtu"]


@pytest.mark.parametrize("ext", ALL_EXTS)
def test_round_trip_single_curve_exact(tmp_path, ext):
    rng = np.random.default_rng(5)
    pts = random_curve(rng, 60)
    pts[3] = [1e12, -1e-12, 0.1]  # extreme magnitudes
    pts[4] = [-0.0, 5e-324, 1.7976931348623157e308 / 1e10]
    p = str(tmp_path / f"rt{ext}")
    write_curves(p, [Curve(pts)])
    (c,) = read_curves(p)
    assert c.points.dtype == np.float64
    np.testing.assert_allclose(c.points, pts, rtol=0, atol=0)
    assert np.array_equal(c.points, pts)
    assert c.id == p


@pytest.mark.parametrize("ext", [".obj", ".vtk", ".vtp", ".vtu"])
def test_round_trip_multi_curve(tmp_path, ext):
    rng = np.random.default_rng(6)
    curves = [random_curve(rng, 30), random_curve(rng, 5, scale=1e-6), random_curve(rng, 12)]
    p = str(tmp_path / f"multi{ext}")
    write_curves(p, curves)
    back = read_curves(p)
    assert [c.id for c in back] == [f"{p}#{i}" for i in range(3)]
    assert [c.index for c in back] == [0, 1, 2]
    for a, b in zip(back, curves):
        np.testing.assert_allclose(a.points, b, rtol=0, atol=0)
    np.testing.assert_array_equal(read_curve(p + "#2").points, curves[2])


def test_same_vertices_in_every_format(tmp_path):
    rng = np.random.default_rng(8)
    pts = random_curve(rng, 25)
    read_back = {}
    for ext in ALL_EXTS:
        p = str(tmp_path / f"same{ext}")
        write_curves(p, [pts])
        read_back[ext] = read_curve(p).points
    for ext, got in read_back.items():
        assert np.array_equal(got, read_back[".csv"]), ext
    assert np.array_equal(read_back[".csv"], pts)


def test_writers_clean_closing_vertex_and_accept_2d(tmp_path):
    closed = np.array(SQUARE + [SQUARE[0]])
    flat = np.array(SQUARE)[:, :2]
    for ext in (".csv", ".obj", ".vtp"):
        p = str(tmp_path / f"c{ext}")
        write_curves(p, [closed])
        assert read_curve(p).points.tolist() == SQUARE
        write_curves(p, flat)  # a bare 2-D array is one curve
        assert read_curve(p).points.tolist() == SQUARE


def test_write_errors(tmp_path):
    p = str(tmp_path / "x.obj")
    expect(ParameterError, p, lambda: write_curves(p, []), contains=("no curves",))
    expect(CurveError, p, lambda: write_curves(p, [[[0, 0, 0], [1, 0, 0]]]))
    for ext in (".csv", ".obj", ".vtp"):
        q = str(tmp_path / "missing_dir" / f"x{ext}")
        expect(WriteError, q, lambda: write_curves(q, [SQUARE]), contains=("cannot write",))
    d = tmp_path / "adir.vtp"
    d.mkdir()
    expect(WriteError, str(d), lambda: write_curves(d, [SQUARE]))
    assert not [f for f in os.listdir(tmp_path) if ".tmp" in f]


settings_fast = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

finite = st.floats(allow_nan=False, allow_infinity=False, width=64, min_value=-1e300, max_value=1e300)


@settings_fast
@given(st.lists(st.tuples(finite, finite, finite), min_size=3, max_size=12))
def test_text_round_trip_property(tmp_path, rows):
    pts = np.array(rows, dtype=np.float64)
    try:
        Curve(pts)
    except CurveError:
        return  # not a valid curve; writers refuse it the same way
    for ext in (".csv", ".obj"):
        p = str(tmp_path / f"prop{ext}")
        write_curves(p, [pts])
        assert np.array_equal(read_curve(p).points, Curve(pts).points)


# ---------------------------------------------------------------------------
# segment chaining
# ---------------------------------------------------------------------------


def test_chain_shuffled_reversed_segments_is_one_loop():
    rng = np.random.default_rng(2)
    for _trial in range(20):
        n = int(rng.integers(3, 40))
        labels = rng.permutation(1000)[:n]  # arbitrary vertex ids
        segs = np.column_stack([labels, np.roll(labels, -1)])
        flip = rng.random(n) < 0.5
        segs[flip] = segs[flip][:, ::-1]
        segs = segs[rng.permutation(n)]
        loops = chain_segments(segs)
        assert len(loops) == 1
        first, verts = loops[0]
        assert first == 0
        assert same_cycle(verts, labels)
        # walked from the first segment, in its direction
        assert verts[0] == segs[0, 0] and verts[1] == segs[0, 1]


def test_chain_several_loops_and_paths_in_order():
    segs = [[10, 11], [20, 21], [11, 12], [21, 22], [12, 10], [22, 23]]
    loops = chain_segments(segs)
    assert [f for f, _ in loops] == [0, 1]
    assert loops[0][1].tolist() == [10, 11, 12]
    assert loops[1][1].tolist() == [20, 21, 22, 23]


def test_chain_branching_raises_with_vertex_and_locations():
    segs = [[0, 1], [1, 2], [2, 0], [1, 3]]
    with pytest.raises(ParseError) as info:
        chain_segments(segs, path="f.obj", vertex_label=lambda v: str(v + 1), segment_where=lambda s: f"line {s + 10}")
    msg = str(info.value)
    assert "f.obj" in msg and "vertex 2" in msg and "line 13" in msg


def test_chain_empty_and_degenerate():
    assert chain_segments(np.zeros((0, 2), dtype=int)) == []
    assert chain_segments([[4, 4]]) == []
    ((first, verts),) = chain_segments([[0, 1], [1, 0], [1, 2], [2, 0]])
    assert sorted(verts.tolist()) == [0, 1, 2]


def test_obj_bulk_path_equals_the_careful_parser(tmp_path, monkeypatch):
    """Large plain OBJ files take a numpy bulk path; it must read exactly what the parser reads."""
    from nfdmatch.formats import obj as obj_module

    rng = np.random.default_rng(3)
    curves = [rng.normal(size=(int(rng.integers(3, 40)), 3)) for _ in range(30)]
    path = tmp_path / "many.obj"
    write_curves(path, curves)
    with open(path, "a") as fh:  # plus a polyline without the closing index
        fh.write("l 1 2 3\n")
    bulk = obj_module.read_points(path)
    assert obj_module._read_points_fast(path.read_text(), str(path)) is not None
    monkeypatch.setattr(obj_module, "_read_points_fast", lambda text, p: None)
    careful = obj_module.read_points(path)
    assert len(bulk) == len(careful) == 31
    assert all(np.array_equal(a, b) for a, b in zip(bulk, careful))


@pytest.mark.parametrize("seed", range(5))
def test_vectorized_cleaning_equals_one_by_one(seed):
    from nfdmatch.curve import clean_many, clean_points

    rng = np.random.default_rng(seed)
    for _ in range(60):
        arrays = []
        for _ in range(int(rng.integers(8, 20))):
            a = rng.integers(0, 3, size=(int(rng.integers(3, 12)), 3)).astype(float)
            if rng.random() < 0.3:
                a = np.vstack([a, a[:1]])
            if rng.random() < 0.3:
                a = np.repeat(a, 2, axis=0)
            arrays.append(a)
        try:
            expected, error = [clean_points(a, path="f", curve=i) for i, a in enumerate(arrays)], None
        except CurveError as exc:
            expected, error = None, str(exc)
        try:
            got, got_error = clean_many(arrays, path="f"), None
        except CurveError as exc:
            got, got_error = None, str(exc)
        assert error == got_error
        if error is None:
            assert all(np.array_equal(a, b) for a, b in zip(expected, got))


_OBJ_LINES = st.one_of(
    st.tuples(
        st.floats(-1e3, 1e3, allow_nan=False),
        st.floats(-1e3, 1e3, allow_nan=False),
        st.floats(-1e3, 1e3, allow_nan=False),
    ).map(lambda v: "v {!r} {!r} {!r}".format(*v)),
    st.lists(st.integers(-3, 12), min_size=1, max_size=6).map(lambda ix: "l " + " ".join(map(str, ix))),
    st.sampled_from(
        [
            "# comment",
            "",
            "o part",
            "vt 0.5 0.5",
            "f 1 2 3",
            "v 1 2",
            "v 1 2 3 4",
            "l",
            "v 1 2 x",
            "l 1 2.5 3",
            "  v 0 0 1",
            "\tv 0 1 0",
            "v\f1 1 1",
            "v 1  2 3",
            "l 1 2 3 # end",
            "v 1 2 3 \\",
            "g\xa0x",
            "v 1 2 3\r",
            "l +1 2 3",
            "v nan 0 0",
            "v 1_0 2 3",
            "l 1 2",
            "l 2 3",
            "l 3 1",
        ]
    ),
)


@settings(max_examples=300, deadline=None)
@given(lines=st.lists(_OBJ_LINES, min_size=1, max_size=25))
def test_obj_bulk_path_never_disagrees_with_the_careful_parser(tmp_path_factory, lines):
    """Whatever the text, the bulk path either declines (None) or reads exactly what the
    careful parser reads; where the parser fails, the bulk path declines. (It once skipped
    indented `v` lines that the parser reads.)"""
    from nfdmatch.formats import obj as obj_module

    text = "\n".join(lines) + "\n"
    path = tmp_path_factory.mktemp("obj") / "f.obj"
    path.write_text(text)
    fast = obj_module._read_points_fast(text, str(path))
    original = obj_module._read_points_fast
    try:
        obj_module._read_points_fast = lambda text, p: None
        careful = obj_module.read_points(path)
    except NfdError:
        assert fast is None
        return
    finally:
        obj_module._read_points_fast = original
    if fast is not None:
        assert len(fast) == len(careful)
        assert all(np.array_equal(a, b) for a, b in zip(fast, careful))


@pytest.mark.parametrize("odd", ["  v 9 9 9", "v\f9 9 9", "\tv 9 9 9"])
def test_obj_indented_and_oddly_spaced_statements_are_read(tmp_path, odd):
    """The parser reads `  v 9 9 9` as a vertex; the bulk path once skipped it silently,
    shifting every index after it."""
    path = tmp_path / "odd.obj"
    path.write_text(f"{odd}\nv 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3\n")
    (curve,) = read_curves(path)
    np.testing.assert_array_equal(curve.points, [[9, 9, 9], [0, 0, 0], [1, 0, 0]])


_OBJ_V = st.one_of(
    st.tuples(
        st.floats(-1e3, 1e3, allow_nan=False),
        st.floats(-1e3, 1e3, allow_nan=False),
        st.floats(-1e3, 1e3, allow_nan=False),
    ).map(lambda v: "v {!r} {!r} {!r}".format(*v)),
    st.sampled_from(
        [
            "v 1 2",
            "v 1 2 3 4",
            "v 1 2 x",
            "v 1  2 3",
            "v 1 2 3 ",
            "v nan 0 0",
            "v 1_0 2 3",
            "v",
            "v 1 2 3 # c",
            "vt 1 2",
            "",
            "# mid",
            "v +1 -.5 3e2",
            "l 1 2 3",
        ]
    ),
)
_OBJ_L = st.one_of(
    st.lists(st.integers(1, 8), min_size=3, max_size=6).map(lambda ix: "l " + " ".join(map(str, ix))),
    st.sampled_from(
        [
            "l 1 2",
            "l",
            "l 0 1 2",
            "l 1 2 99",
            "l -1 1 2",
            "l +1 2 3",
            "l 1_0 2 3",
            "l 1  2 3 ",
            "l 1 2 3 # c",
            "f 1 2 3",
            "",
            "# mid",
            "v 5 5 5",
            "l 1 2 x",
            "l 99999999999999999999 1 2",
        ]
    ),
)


@settings(max_examples=300, deadline=None)
@given(
    comments=st.lists(st.sampled_from(["# nfdmatch: 3 closed curves", "#", "# a # b", "#x"]), max_size=2),
    v_lines=st.lists(_OBJ_V, min_size=0, max_size=10),
    l_lines=st.lists(_OBJ_L, min_size=0, max_size=6),
    tail=st.sampled_from(["", "\n", "\n\n", "\nl 1 2 3"]),
)
def test_obj_block_layout_bulk_path_never_disagrees_with_the_careful_parser(
    tmp_path_factory, comments, v_lines, l_lines, tail
):
    """The layout ``write`` makes (comments, a run of `v` lines, a run of `l` lines) is read by
    the bulk path without a loop over lines; mutated by the odd line anywhere, the bulk path
    either declines or reads exactly what the careful parser reads, and declines whatever
    the parser refuses."""
    from nfdmatch.formats import obj as obj_module

    text = "\n".join(comments + v_lines + l_lines) + tail
    path = tmp_path_factory.mktemp("obj") / "f.obj"
    path.write_text(text)
    fast = obj_module._read_points_fast(text, str(path))
    original = obj_module._read_points_fast
    try:
        obj_module._read_points_fast = lambda text, p: None
        careful = obj_module.read_points(path)
    except NfdError:
        assert fast is None
        return
    finally:
        obj_module._read_points_fast = original
    if fast is not None:
        assert len(fast) == len(careful)
        assert all(np.array_equal(a, b) for a, b in zip(fast, careful))


def test_obj_block_layout_takes_the_loop_free_path(tmp_path):
    """A file as ``write`` makes it is split into rows by blocks, the same rows the loop finds."""
    from nfdmatch.formats import obj as obj_module

    rng = np.random.default_rng(5)
    path = tmp_path / "w.obj"
    write_curves(path, [rng.normal(size=(int(rng.integers(3, 30)), 3)) for _ in range(20)])
    text = path.read_text()
    rows = obj_module._block_rows(text)
    assert rows is not None and rows == obj_module._line_rows(text)
    assert obj_module._token_counts(rows[1]).tolist() == [len(r.split()) for r in rows[1]]


def test_os_error_message_gives_the_known_kinds_words_else_the_systems():
    from nfdmatch.errors import os_error_message

    known = {FileNotFoundError: "no such file", PermissionError: "permission denied"}
    assert os_error_message(FileNotFoundError(2, "No such file or directory"), known, "cannot read") == "no such file"
    assert os_error_message(PermissionError(13, "Permission denied"), known, "cannot read") == "permission denied"
    assert (
        os_error_message(OSError(5, "Input/output error"), known, "cannot read") == "cannot read (Input/output error)"
    )
    assert os_error_message(OSError("odd"), {}, "cannot read") == "cannot read (odd)"


def test_write_text_names_a_missing_folder_and_a_directory_in_the_way(tmp_path):
    from nfdmatch.formats._chain import write_text

    with pytest.raises(WriteError, match="cannot write: the folder does not exist"):
        write_text(tmp_path / "missing" / "a.csv", "x")
    with pytest.raises(WriteError, match="cannot write: is a directory"):
        write_text(tmp_path, "x")
