"""`nfdmatch reconstruct`, `matrix` and `show` end to end through CliRunner: exit codes,
stdout (data) and stderr (messages) apart, files written and read back."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import shutil

import numpy as np
import pytest

from oracle import random_rigid_motion, random_smooth_curve, reverse, start_shift, torus_knot

from nfdmatch import read_curve, read_curves, write_curves
from conftest import ROOT, run_cli as run

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow

SAMPLES = os.path.join(ROOT, "sample_curves")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(path) -> tuple[int, int]:
    data = open(path, "rb").read(24)
    assert data[:8] == PNG_SIGNATURE
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def png_pixels(path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


@pytest.fixture
def folder(tmp_path, rng):
    """Five curves: a knot, a posed/restarted/reversed copy of it, and three others."""
    lib = tmp_path / "lib"
    lib.mkdir()
    knot = torus_knot(2, 3, 600)
    write_curves(lib / "knot.csv", knot)
    write_curves(lib / "knot-posed.obj", random_rigid_motion(reverse(start_shift(knot, 77)), rng))
    write_curves(lib / "other.vtp", [random_smooth_curve(rng, n_vertices=500), torus_knot(2, 5, 400)])
    write_curves(lib / "blob.csv", random_smooth_curve(rng, n_vertices=300))
    return lib


# --------------------------------------------------------------------------- reconstruct


def test_reconstruct_writes_the_format_of_the_extension_and_reports_the_distance(tmp_path):
    src = os.path.join(SAMPLES, "library", "knotess", "5_2.csv")
    dists = []
    for k, ext in [(1, "csv"), (4, "obj"), (16, "vtp")]:
        out = tmp_path / f"r{k}.{ext}"
        code, stdout, stderr = run("reconstruct", src, "-k", k, "-o", out, "--format", "csv")
        assert code == 0, stderr
        assert f"wrote {out}" in stderr
        rows = list(csv.DictReader(io.StringIO(stdout)))
        assert [r["curve"] for r in rows] == [src] and rows[0]["harmonics"] == str(k)
        curve = read_curve(out)
        assert curve.n_vertices == 128 == int(rows[0]["vertices"])
        dists.append(float(rows[0]["distance"]))
    assert dists[0] > dists[1] > dists[2] and dists[2] < 2e-3
    # what the file holds is the curve the row measured
    code, stdout, _ = run("distance", src, tmp_path / "r16.vtp", "--format", "json")
    assert json.loads(stdout)["distance"] == pytest.approx(dists[2], rel=1e-9)


def test_reconstruct_multi_curve_file_points_and_normalized(folder, tmp_path):
    out = tmp_path / "other-k8.obj"
    code, stdout, stderr = run("reconstruct", folder / "other.vtp", "-k", 8, "-m", 300, "-o", out, "--format", "json")
    assert code == 0, stderr
    rows = json.loads(stdout)
    assert [r["curve"] for r in rows] == [f"{folder / 'other.vtp'}#0", f"{folder / 'other.vtp'}#1"]
    back = read_curves(out)
    assert [c.n_vertices for c in back] == [300, 300]
    code, stdout, stderr = run(
        "reconstruct",
        f"{folder / 'other.vtp'}#1",
        "-k",
        8,
        "--normalized",
        "-o",
        tmp_path / "n.csv",
        "--format",
        "json",
    )
    # the distance ignores pose and size: a normalized rebuild has it too (issue 25, item 12)
    assert code == 0 and json.loads(stdout)[0]["distance"] > 0
    pts = read_curve(tmp_path / "n.csv").points
    assert np.abs(pts.mean(0)).max() < 1e-9


def test_reconstruct_errors(folder, tmp_path):
    code, out, err = run("reconstruct", folder / "other.vtp", "-k", 4, "-o", tmp_path / "x.csv")
    assert code == 2 and out == "" and "x.csv" in err and "exactly one curve" in err
    # named as given, not as the temporary file the curves are written to first
    assert err.startswith(f"Error: {tmp_path / 'x.csv'}: a CSV file holds exactly one curve") and ".tmp" not in err
    code, out, err = run("reconstruct", folder / "missing.csv", "-k", 4, "-o", tmp_path / "y.csv")
    assert code == 2 and "missing.csv" in err and "Traceback" not in err
    code, out, err = run("reconstruct", folder / "knot.csv", "-k", 70, "-n", 128, "-o", tmp_path / "z.csv")
    assert code == 2 and "samples/2" in err
    code, out, err = run("reconstruct", folder / "knot.csv", "-k", 4, "-o", tmp_path / "z.xyzzy")
    assert code == 2 and "z.xyzzy" in err and ".vtp" in err  # a usage error naming the formats
    assert not (tmp_path / "z.csv").exists()


# --------------------------------------------------------------------------- matrix


def test_matrix_csv_matches_distance_for_every_pair(folder):
    code, out, err = run("matrix", folder)
    assert code == 0 and err == ""
    rows = list(csv.reader(io.StringIO(out)))
    header, body = rows[0], rows[1:]
    ids = header[1:]
    assert header[0] == "id" and [r[0] for r in body] == ids and len(ids) == 5
    M = np.array([[float(v) for v in r[1:]] for r in body])
    np.testing.assert_array_equal(M, M.T)
    np.testing.assert_array_equal(np.diag(M), 0)
    for i in range(5):
        for j in range(5):
            if i != j:
                code, out, _ = run("distance", ids[i], ids[j], "--format", "json")
                assert M[i, j] == pytest.approx(json.loads(out)["distance"], rel=1e-9, abs=1e-12)
    knot, posed = ids.index(str(folder / "knot.csv")), ids.index(str(folder / "knot-posed.obj"))
    assert M[knot, posed] < 1e-3 and np.sort(M[knot])[1] == M[knot, posed]


@pytest.mark.parametrize("fmt, sep", [("csv", ","), ("tsv", "\t")])
def test_matrix_rows_read_back_whatever_the_file_names(folder, tmp_path, fmt, sep):
    # the ids are quoted by the csv rules (TSV: escaped); the entries are every float's repr, both triangles
    names = tmp_path / "names"
    names.mkdir()
    for name in ('a,b "c".csv', "tab\there.csv", "plain.csv"):
        shutil.copy(folder / "knot.csv", names / name)
    shutil.copy(folder / "blob.csv", names / "blob.csv")
    code, out, err = run("matrix", names, "--format", fmt)
    assert code == 0 and err == ""
    if fmt == "tsv":  # backslash escapes, never quotes (issue 40)
        unescape = {"t": "\t", "n": "\n", "r": "\r", "\\": "\\"}
        rows = [
            [re.sub(r"\\(.)", lambda m: unescape[m.group(1)], f) for f in line.split(sep)] for line in out.splitlines()
        ]
    else:
        rows = list(csv.reader(io.StringIO(out), delimiter=sep))
    ids = rows[0][1:]
    assert sorted(os.path.basename(i) for i in ids) == sorted(['a,b "c".csv', "tab\there.csv", "plain.csv", "blob.csv"])
    assert [r[0] for r in rows[1:]] == ids
    M = np.array([[float(v) for v in r[1:]] for r in rows[1:]])
    code, out, _ = run("matrix", names, "--format", "json")
    np.testing.assert_array_equal(M, np.array(json.loads(out)["distances"]))  # every digit
    assert all(v == repr(float(v)) for r in rows[1:] for v in r[1:])


def test_matrix_rows_name_the_files_not_their_ids(folder, tmp_path):
    # a curve's id is its file name encoded (a backslash doubled, a byte not UTF-8 as \xNN);
    # the rows write the name itself, as describe's id column: raw bytes in CSV, \udcNN in JSON
    from click.testing import CliRunner

    from nfdmatch.cli import main

    names = tmp_path / "names"
    names.mkdir()
    raw = [b"back\\slash.csv", b"c\xff.csv"]
    for name in raw:
        shutil.copy(folder / "knot.csv", os.path.join(str(names), os.fsdecode(name)))
    expected = sorted(os.fsencode(str(names)) + b"/" + name for name in raw)
    out = CliRunner().invoke(main, ["matrix", str(names), "--format", "csv"]).stdout_bytes
    lines = out.splitlines()
    assert sorted(lines[0].split(b",")[1:]) == expected
    assert sorted(line.split(b",")[0] for line in lines[1:]) == expected
    out = CliRunner().invoke(main, ["matrix", str(names), "--format", "json"]).stdout_bytes
    assert sorted(os.fsencode(i) for i in json.loads(out)["ids"]) == expected


def test_matrix_json_tsv_picture_and_partial_failure(folder, tmp_path):
    (folder / "bad.csv").write_text("x,y,z\n1,2,3\n4,five,6\n")
    png = tmp_path / "m.png"
    code, out, err = run("matrix", folder, "--format", "json", "-o", png)
    assert code == 3
    assert "bad.csv" in err and "line 3" in err and "1 of 5 inputs could not be read" in err
    # the rows of what could be read are printed; the picture (a file, for Make) waits for success
    assert f"{png} not written: some inputs could not be read" in err and not png.exists()
    data = json.loads(out)
    assert len(data["ids"]) == 5 and np.array(data["distances"]).shape == (5, 5)
    os.remove(folder / "bad.csv")
    code, out, err = run("matrix", folder, "--format", "json", "-o", png)
    assert code == 0 and f"wrote {png}" in err
    width, height = png_size(png)
    assert width >= 400 and height >= 400
    assert len(np.unique(png_pixels(png).reshape(-1, 3), axis=0)) > 10
    code, out, err = run(
        "matrix", folder / "knot.csv", folder / "blob.csv", "--format", "tsv", "--method", "paper", "--strict-direction"
    )
    assert code == 0 and out.splitlines()[0].split("\t")[0] == "id"
    code, out, err = run("matrix", folder / "bad.csv")
    assert code == 2 and out == "" and "bad.csv" in err


# --------------------------------------------------------------------------- show


def test_show_against_files_writes_the_picture_and_lists_the_rows(folder, tmp_path):
    png = tmp_path / "show.png"
    query = folder / "knot.csv"
    code, out, err = run("show", query, "--against", folder, "--top", 3, "-o", png, "--format", "csv")
    assert code == 0, err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert [r["rank"] for r in rows] == ["1", "2", "3"]
    assert rows[0]["match"] == str(query) and float(rows[0]["distance"]) < 1e-9
    assert rows[1]["match"] == str(folder / "knot-posed.obj") and all(r["source"] == "file" for r in rows)
    assert png_size(png) == (1600, 900) and f"wrote {png}" in err
    pixels = png_pixels(png)
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 10
    # another query gives another picture
    png2 = tmp_path / "show2.png"
    code, out, err = run("show", folder / "blob.csv", "--against", folder, "--top", 3, "-o", png2, "--size", "800x600")
    assert code == 0 and png_size(png2) == (800, 600)
    code, out, err = run("show", folder / "blob.csv", "--against", folder, "--top", 3, "-o", png2, "--size", "1600x900")
    assert not np.array_equal(png_pixels(png2), pixels)


def test_show_from_an_index_draws_from_files_or_stored_harmonics(folder, tmp_path):
    index = tmp_path / "i.h5"
    code, out, err = run("index", "build", folder, "--index", index)
    assert code == 0, err
    png = tmp_path / "idx.png"
    query = folder / "knot-posed.obj"
    code, out, err = run("show", query, "--index", index, "--top", 2, "-o", png, "--format", "json")
    assert code == 0, err
    rows = json.loads(out)
    # ids relative to the index's folder; the files are found from there, whatever the cwd
    rel = os.path.relpath(folder, tmp_path)
    assert [r["match"] for r in rows] == [f"{rel}/knot-posed.obj", f"{rel}/knot.csv"]
    assert [r["source"] for r in rows] == ["file", "file"]
    before = png_pixels(png)
    # the source file is gone: the match is drawn from the index's harmonics, with a note
    os.rename(folder / "knot.csv", tmp_path / "moved.csv")
    code, out, err = run("show", query, "--index", index, "--top", 2, "-o", png, "--format", "json")
    assert code == 0, err
    assert [r["source"] for r in json.loads(out)] == ["file", "index"]
    assert "knot.csv: drawn from its 16 indexed harmonics" in err
    assert png_size(png) == (1600, 900) and before.shape == png_pixels(png).shape
    # the panel says so too
    from nfdmatch import render

    drawn = []
    original = render.build_scene
    render.build_scene = lambda q, qid, panels, size: drawn.extend(panels) or original(q, qid, panels, size)
    try:
        run("show", query, "--index", index, "--top", 2, "-o", png)
    finally:
        render.build_scene = original
    assert [p.note for p in drawn] == [None, "drawn from index harmonics"]


def test_show_usage_and_input_errors(folder, tmp_path):
    png = tmp_path / "x.png"
    code, out, err = run("show", folder / "knot.csv", "--against", "-o", png)
    assert code == 2 and "--against needs" in err
    # without --against, every argument is a query: several need a picture name pattern
    code, out, err = run("show", folder / "knot.csv", folder, "-o", png, "--index", tmp_path / "i.h5")
    assert code == 2 and out == "" and "5 queries give 5 pictures" in err and "{stem}" in err
    code, out, err = run("show", folder, "-o", tmp_path / "{name}.png", "--index", tmp_path / "i.h5")
    assert code == 2 and "{stem} and {n} only" in err
    code, out, err = run("show", folder / "knot.csv", "--against", folder, "-o", png, "--size", "big")
    assert code == 2 and "WIDTHxHEIGHT" in err
    code, out, err = run("show", folder / "knot.csv", "--index", tmp_path / "none.h5", "-o", png)
    assert code == 2 and "none.h5" in err and "Traceback" not in err
    code, out, err = run("show", folder / "nope.csv", "--against", folder, "-o", png)
    assert code == 2 and "nope.csv" in err
    code, out, err = run("show", folder / "knot.csv", "--against", folder, "-o", tmp_path / "no" / "dir.png")
    assert code == 2 and "dir.png" in err and "Traceback" not in err
    assert not png.exists()


def test_picture_commands_do_not_import_renderers_at_startup():
    import subprocess
    import sys

    code = (
        "import sys, nfdmatch.cli; "
        "print(sorted(m for m in ('matplotlib', 'pyvista', 'trimesh', 'vtk', 'numba', 'h5py', 'dask', 'distributed') "
        "if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_matrix_and_show_name_an_empty_source_and_check_the_picture_path_first(folder, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    code, out, err = run("matrix", empty)
    assert code == 2 and out == "" and f"Error: {empty}: no curve files found" in err
    code, out, err = run("matrix", folder, "--glob", "*.xyz")
    assert code == 2 and "no curve files found matching '*.xyz'" in err
    code, out, err = run("show", folder / "knot.csv", "--against", empty, "-o", tmp_path / "s.png")
    assert code == 2 and "no curve files found" in err
    # a picture that cannot be written is reported before any distance is computed or printed
    code, out, err = run("matrix", folder, "-o", tmp_path / "missing" / "m.png")
    assert code == 2 and out == "" and "m.png" in err and "folder does not exist" in err
    code, out, err = run("show", folder / "knot.csv", "--glob", "*.csv", "-o", tmp_path / "s.png")
    assert code == 2 and "--glob" in err


def test_show_reads_match_files_with_the_input_format(tmp_path, rng):
    lib = tmp_path / "lib"
    lib.mkdir()
    knot = torus_knot(2, 3, 300)
    for name, pts in (("a.dat", knot), ("b.dat", random_smooth_curve(rng, n_vertices=200))):
        write_curves(lib / name, pts, format="csv")
    index = tmp_path / "i.h5"
    code, _, err = run("index", "build", lib / "a.dat", lib / "b.dat", "--index", index, "--input-format", "csv")
    assert code == 0, err
    code, out, err = run(
        "show",
        lib / "a.dat",
        "--index",
        index,
        "--input-format",
        "csv",
        "--top",
        2,
        "-o",
        tmp_path / "s.png",
        "--format",
        "json",
    )
    assert code == 0, err
    assert [r["source"] for r in json.loads(out)] == ["file", "file"] and "Note" not in err


def test_matrix_order_similar_permutes_rows_and_columns_together(folder):
    code, out, _ = run("matrix", folder, "--format", "json")
    plain = json.loads(out)
    code, out, err = run("matrix", folder, "--format", "json", "--order", "similar")
    assert code == 0, err
    ordered = json.loads(out)
    assert sorted(ordered["ids"]) == sorted(plain["ids"])
    where = [plain["ids"].index(i) for i in ordered["ids"]]
    np.testing.assert_array_equal(np.array(plain["distances"])[np.ix_(where, where)], ordered["distances"])
    pos = {curve_id: k for k, curve_id in enumerate(ordered["ids"])}
    assert abs(pos[str(folder / "knot.csv")] - pos[str(folder / "knot-posed.obj")]) == 1


def test_show_several_queries_one_picture_each_named_by_the_pattern(folder, tmp_path):
    index = tmp_path / "i.h5"
    assert run("index", "build", folder, "--index", index, "-q")[0] == 0
    rows_file = tmp_path / "rows.csv"
    code, out, err = run(
        "show",
        folder / "knot.csv",
        folder / "other.vtp",
        "--index",
        index,
        "--top",
        2,
        "-o",
        tmp_path / "m-{stem}.png",
        "-o",
        rows_file,
    )
    assert code == 0 and out == "", err
    names = sorted(p.name for p in tmp_path.glob("m-*.png"))
    assert names == ["m-knot.png", "m-other-0.png", "m-other-1.png"]
    assert all(png_size(tmp_path / n) == (1600, 900) for n in names)
    assert err.count("wrote ") == 3
    rows = list(csv.DictReader(open(rows_file)))
    assert [r["query"] for r in rows] == [str(folder / "knot.csv")] * 2 + [f"{folder / 'other.vtp'}#0"] * 2 + [
        f"{folder / 'other.vtp'}#1"
    ] * 2
    # a query that cannot be read: the others are answered on stdout, no picture is written (exit 3)
    code, out, err = run(
        "show",
        folder / "knot.csv",
        tmp_path / "nope.csv",
        "--index",
        index,
        "-o",
        tmp_path / "n-{n}.png",
        "--format",
        "csv",
    )
    assert code == 3 and "nope.csv" in err and "n-1.png not written" in err
    assert not list(tmp_path.glob("n-*.png")) and len(out.splitlines()) == 6


@pytest.mark.parametrize("ext, magic", [(".svg", b"<?xml"), (".pdf", b"%PDF")])
def test_show_and_matrix_write_svg_and_pdf_by_extension(folder, tmp_path, ext, magic):
    picture = tmp_path / f"show{ext}"
    code, out, err = run("show", folder / "knot.csv", "--against", folder, "--top", 2, "-o", picture)
    assert code == 0 and f"wrote {picture}" in err
    assert picture.read_bytes().startswith(magic)
    # the same picture again: identical bytes, the file is kept, with a fresh mtime (Make)
    os.utime(picture, ns=(10**9, 10**9))
    inode = os.stat(picture).st_ino
    assert run("show", folder / "knot.csv", "--against", folder, "--top", 2, "-o", picture)[0] == 0
    assert os.stat(picture).st_mtime_ns > 10**9 and os.stat(picture).st_ino == inode
    matrix_picture = tmp_path / f"matrix{ext}"
    code, out, err = run("matrix", folder, "-o", matrix_picture)
    assert code == 0 and out.startswith("id,") and matrix_picture.read_bytes().startswith(magic)
    code, out, err = run("show", folder / "knot.csv", "--against", folder, "-o", picture, "--renderer", "pyvista")
    assert code == 2 and "PNG only" in err
