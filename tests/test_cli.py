"""The command line through click's CliRunner: exit codes, stdout and stderr apart."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from oracle import random_rigid_motion, random_smooth_curve, reverse, start_shift, torus_knot

from nfdmatch import __version__, write_curves
from conftest import ROOT, run_cli as run

SAMPLES = os.path.join(ROOT, "sample_curves")


@pytest.fixture
def curves(tmp_path, rng):
    a = random_smooth_curve(rng, n_vertices=900)
    paths = {
        "a": tmp_path / "a.csv",
        "a_posed": tmp_path / "a_posed.obj",
        "b": tmp_path / "b.vtp",
        "multi": tmp_path / "multi.obj",
        "bad": tmp_path / "bad.csv",
    }
    write_curves(paths["a"], a)
    write_curves(paths["a_posed"], random_rigid_motion(reverse(start_shift(a, 100)), rng))
    write_curves(paths["b"], random_smooth_curve(rng, n_vertices=700))
    write_curves(paths["multi"], [torus_knot(2, 3, 300), torus_knot(2, 5, 300), a])
    paths["bad"].write_text("x,y,z\n1,2,3\n4,five,6\n7,8,9\n")
    return paths


def test_version_and_help():
    code, out, err = run("--version")
    assert code == 0 and __version__ in out
    for command in ([], ["distance"], ["describe"], ["rank"]):
        code, out, _ = run(*command, "--help")
        assert code == 0 and "Usage:" in out
        if command:
            assert "Example" in out


def test_distance_text_and_json(curves):
    code, out, err = run("distance", curves["a"], curves["a_posed"])
    assert code == 0 and err == ""
    fields = dict(line.split("\t", 1) for line in out.strip().splitlines())
    assert float(fields["distance"]) < 0.01
    assert fields["reversed"] == "true" and fields["method"] == "exact"
    code, out, err = run("distance", curves["a"], curves["b"], "--format", "json")
    assert code == 0
    record = json.loads(out)
    assert {"distance", "shift", "rotation", "reversed", "mirrored", "method"} <= set(record)
    assert record["distance"] > 0.05 and np.array(record["rotation"]).shape == (3, 3)


def test_distance_json_names_the_files_not_their_ids(curves, tmp_path):
    # a curve's id is its file name encoded (a backslash doubled, a byte not UTF-8 as \xNN):
    # "a" and "b" hold the names, as every row format does (\udcNN for such a byte)
    import shutil

    a = os.path.join(str(tmp_path), os.fsdecode(b"back\\slash.csv"))
    b = os.path.join(str(tmp_path), os.fsdecode(b"c\xff.csv"))
    shutil.copy(curves["a"], a)
    shutil.copy(curves["a"], b)
    code, out, err = run("distance", a, b, "--format", "json")
    assert code == 0 and err == ""
    record = json.loads(out)
    assert (record["a"], record["b"]) == (a, b)


def test_distance_options_change_the_result(curves):
    def dist(*extra):
        code, out, _ = run("distance", curves["a"], curves["a_posed"], "--format", "json", *extra)
        assert code == 0
        return json.loads(out)

    assert dist()["distance"] < 0.01
    assert dist("--strict-direction")["distance"] > 0.05
    paper = dist("--method", "paper", "--scale", "a1", "--samples", "64", "--harmonics", "8")
    assert paper["method"] == "paper"
    assert dist("--mirror")["distance"] <= dist()["distance"] + 1e-12


def test_distance_selects_a_curve_of_a_multi_curve_file(curves):
    code, out, err = run("distance", f"{curves['multi']}#2", curves["a"], "--format", "json")
    assert code == 0 and json.loads(out)["distance"] < 1e-6
    code, out, err = run("distance", curves["multi"], curves["a"])
    assert code == 2 and out == ""
    assert err.startswith("Error: ") and "multi.obj" in err and "3 curves" in err and "#0" in err
    code, out, err = run("distance", f"{curves['multi']}#7", curves["a"])
    assert code == 2 and "#7" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "bad_args, needle",
    [
        (["missing.csv"], "missing.csv"),
        (["bad"], "line 3"),
        (["unknown.xyz123"], "supported extensions"),
    ],
)
def test_distance_bad_input_is_exit_2_with_message(curves, tmp_path, bad_args, needle):
    target = str(curves[bad_args[0]]) if bad_args[0] in curves else str(tmp_path / bad_args[0])
    if target.endswith(".xyz123"):
        open(target, "w").write("1 2 3\n")
    code, out, err = run("distance", target, curves["a"])
    assert code == 2 and out == ""
    assert err.startswith("Error: ") and needle in err and "Traceback" not in err


def test_usage_errors_are_exit_2(curves):
    assert run("distance", curves["a"])[0] == 2
    assert run("distance", curves["a"], curves["b"], "--method", "best")[0] == 2
    assert run("distance", curves["a"], curves["b"], "--samples", "0")[0] == 2
    assert run("nonsense")[0] == 2


def test_bad_parameter_combination_is_exit_2(curves):
    code, out, err = run("distance", curves["a"], curves["b"], "--samples", "16", "--harmonics", "8")
    assert code == 2 and "harmonics" in err


def test_describe_csv_round_trips_the_descriptors(curves):
    code, out, err = run("describe", curves["a"], curves["multi"], "--harmonics", "4")
    assert code == 0 and err == ""
    rows = list(csv.DictReader(io.StringIO(out)))
    assert [r["id"] for r in rows] == [str(curves["a"])] + [f"{curves['multi']}#{i}" for i in range(3)]
    assert "k+1_x_re" in rows[0] and "k-4_z_im" in rows[0] and "k+5_x_re" not in rows[0]
    # the last curve of multi.obj is a.csv itself: same descriptors
    a_vals = np.array([float(v) for k, v in rows[0].items() if k.startswith("k")])
    m_vals = np.array([float(v) for k, v in rows[3].items() if k.startswith("k")])
    assert np.allclose(a_vals, m_vals, atol=1e-12)
    # negative frequencies are the conjugates
    assert float(rows[0]["k-1_y_re"]) == pytest.approx(float(rows[0]["k+1_y_re"]))
    assert float(rows[0]["k-1_y_im"]) == pytest.approx(-float(rows[0]["k+1_y_im"]))


def test_describe_json_and_partial_failure(curves):
    code, out, err = run("describe", curves["a"], curves["bad"], "--format", "json")
    assert code == 3
    records = json.loads(out)
    assert len(records) == 1 and records[0]["id"] == str(curves["a"])
    assert len(records[0]["coefficients"]) == 32 and records[0]["frequencies"][:2] == [1, 2]
    assert "bad.csv" in err and "line 3" in err
    code, out, err = run("describe", curves["bad"])
    assert code == 2 and out == "" and "bad.csv" in err


def test_describe_jsonl_one_object_per_line(curves):
    code, out, _ = run("describe", curves["multi"], "--format", "jsonl")
    assert code == 0
    assert [json.loads(line)["id"].endswith(f"#{i}") for i, line in enumerate(out.splitlines())] == [True] * 3


@pytest.mark.parametrize("fmt", ["csv", "tsv", "json", "jsonl", "table"])
def test_rank_every_output_format(fmt):
    query = os.path.join(SAMPLES, "queries", "trefoil-posed.obj")
    code, out, err = run("rank", query, os.path.join(SAMPLES, "library"), "--top", "3", "--format", fmt)
    assert code == 0, err
    if fmt in ("csv", "tsv"):
        rows = list(csv.DictReader(io.StringIO(out), delimiter="," if fmt == "csv" else "\t"))
        assert list(rows[0])[:4] == ["query", "rank", "match", "distance"]
    elif fmt == "json":
        rows = json.loads(out)
    elif fmt == "jsonl":
        rows = [json.loads(line) for line in out.splitlines()]
    else:
        assert "trefoil.csv" in out and "┃" in out
        return
    assert [int(r["rank"]) for r in rows] == [1, 2, 3]
    assert rows[0]["match"].endswith(os.path.join("library", "trefoil.csv"))
    assert float(rows[0]["distance"]) < 0.01
    assert [float(r["distance"]) for r in rows] == sorted(float(r["distance"]) for r in rows)


def test_rank_skips_a_bad_file_and_exits_3(curves):
    code, out, err = run("rank", curves["a"], curves["a"].parent, "--format", "csv", "--details")
    assert code == 3
    rows = list(csv.DictReader(io.StringIO(out)))
    assert rows[0]["match"] in (str(curves["a"]), f"{curves['multi']}#2") and float(rows[0]["distance"]) < 1e-6
    assert {"shift", "reversed", "mirrored"} <= set(rows[0])
    assert "bad.csv" in err and "line 3" in err and "1 of" in err


def test_rank_max_distance_and_glob(curves):
    code, out, _ = run(
        "rank", curves["a"], curves["a"].parent, "--glob", "*.obj", "--max-distance", "0.02", "--format", "json"
    )
    assert code == 0
    rows = json.loads(out)
    assert {r["match"] for r in rows} == {str(curves["a_posed"]), f"{curves['multi']}#2"}


def test_python_dash_m_and_console_script_do_not_import_heavy_libraries():
    code = (
        "import sys, runpy; sys.argv=['nfdmatch','--help']\n"
        "try:\n    runpy.run_module('nfdmatch', run_name='__main__')\n"
        "except SystemExit: pass\n"
        "heavy=[m for m in ('pyvista','vtk','trimesh','matplotlib','h5py') if m in sys.modules]\n"
        "print('HEAVY', heavy)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "HEAVY []" in out and "Usage:" in out


def test_match_listing_gives_the_library_its_search_keywords():
    from nfdmatch.cli.options import MatchListing

    listing = MatchListing(top=3, max_distance=0.5, glob="*.csv", details=True, paths="id", exclude_self=True)
    assert listing.search() == {"k": 3, "max_distance": 0.5, "exclude_self": True}
