"""Output options that must not surprise (issue 25): -o - is stdout, the extension of -o
picks the format everywhere (an unknown one is a usage error naming the formats), index
export without -o writes stdout, picture and curve outputs name a wrong extension, and
every output of reconstruct has its distance. Exit code, stdout and stderr apart."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil

import pytest

from conftest import ROOT, run_cli as run

LIBRARY = os.path.join(ROOT, "sample_curves", "library")
QUERIES = os.path.join(ROOT, "sample_curves", "queries")
TREFOIL = os.path.join(QUERIES, "trefoil-posed.obj")


@pytest.fixture(scope="module")
def index(tmp_path_factory):
    folder = tmp_path_factory.mktemp("outputs")
    shutil.copytree(LIBRARY, folder / "library")
    path = folder / "lib.h5"
    code, _, err = run("index", "build", folder / "library", "--index", path, "--jobs", "1", "-q")
    assert code == 0 and err == ""
    return path


# --------------------------------------------------------------------------- item 6: -o - is stdout


@pytest.mark.parametrize(
    "args",
    [
        ["query", TREFOIL, "--top", 2],
        ["index", "export"],
        ["index", "ls"],
        ["index", "info", "--format", "json"],
    ],
)
def test_dash_output_is_stdout_and_writes_no_file(index, tmp_path, monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    code, out, err = run(*args, "--index", index, "-o", "-")
    assert code == 0, err
    assert not os.path.exists(tmp_path / "-") and out
    assert out == run(*args, "--index", index)[1]  # the same as without -o


def test_dash_among_the_outputs_of_matrix_is_stdout(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run("matrix", os.path.join(LIBRARY, "knotess"), "-o", "-")
    assert code == 0 and out.startswith("id,") and os.listdir(tmp_path) == []


# --------------------------------------------------------------------------- item 4: export without -o


def test_index_export_without_output_writes_csv_on_stdout(index):
    code, out, err = run("index", "export", "--index", index)
    assert code == 0 and err == ""
    rows = list(csv.DictReader(io.StringIO(out)))
    assert len(rows) == 24 and rows[0]["id"] and "k+1_x_re" in rows[0]
    code, out, err = run("index", "export", "--index", index, "--format", "jsonl")
    assert code == 0 and len(out.splitlines()) == 24 and json.loads(out.splitlines()[0])["id"] == rows[0]["id"]


def test_index_export_npz_goes_to_a_pipe_as_bytes(index, tmp_path):
    import numpy as np
    from click.testing import CliRunner

    from nfdmatch.cli import main

    result = CliRunner().invoke(main, ["index", "export", "--index", str(index), "--format", "npz"])
    assert result.exit_code == 0
    (tmp_path / "x.npz").write_bytes(result.stdout_bytes)
    with np.load(tmp_path / "x.npz") as data:
        assert data["coefficients"].shape[0] == 24


def test_index_export_writes_the_file_column_as_the_name_as_index_ls_does(tmp_path):
    # the index stores a file's name encoded (backslash doubled, a byte not UTF-8 as \xNN):
    # the id column was written as the name, the file column as the encoded form
    from click.testing import CliRunner

    from nfdmatch.cli import main

    folder = tmp_path / "lib"
    folder.mkdir()
    names = [b"back\\slash.csv", b"c\xff.csv"]
    for name in names:
        shutil.copy(os.path.join(LIBRARY, "trefoil.csv"), os.path.join(str(folder), os.fsdecode(name)))
    index = tmp_path / "lib.h5"
    assert run("index", "build", folder, "--index", index, "--jobs", "1", "-q")[0] == 0
    expected = sorted(b"lib/" + name for name in names)
    out = CliRunner().invoke(main, ["index", "export", "--index", str(index)]).stdout_bytes
    rows = [row.split(b",")[:2] for row in out.splitlines()[1:]]
    assert sorted(row[0] for row in rows) == expected and all(row[0] == row[1] for row in rows)
    out = CliRunner().invoke(main, ["index", "export", "--index", str(index), "--format", "jsonl"]).stdout_bytes
    records = [json.loads(line) for line in out.splitlines()]
    assert all(r["id"] == r["file"] for r in records)
    assert sorted(os.fsencode(r["file"]) for r in records) == expected


# --------------------------------------------------------------------------- items 5, 7: the extension picks the format


def test_index_info_json_by_extension(index, tmp_path):
    out = tmp_path / "info.json"
    code, stdout, err = run("index", "info", "--index", index, "-o", out)
    assert code == 0 and stdout == "" and err == ""
    info = json.loads(out.read_text())
    assert info["curves"] == 24 and info["files"] == 21
    text = tmp_path / "info.txt"
    assert run("index", "info", "--index", index, "-o", text)[0] == 0
    assert text.read_text().startswith("path\t")


def test_distance_json_by_extension(tmp_path):
    out = tmp_path / "d.json"
    code, _, err = run("distance", os.path.join(LIBRARY, "trefoil.csv"), TREFOIL, "-o", out)
    assert code == 0, err
    assert json.loads(out.read_text())["distance"] < 1e-3


_COMMANDS = [
    (["query", TREFOIL], ".csv, .tsv, .json, .jsonl"),
    (["index", "ls"], ".csv, .tsv, .json, .jsonl"),
    (["index", "info"], ".json, .txt"),
    (["index", "export"], ".csv, .jsonl, .npz"),
]


@pytest.mark.parametrize(
    "args, formats, name",
    [
        (args, formats, name)
        for args, formats in _COMMANDS
        for name in ("out.txt", "out.xlsx", "out")
        if not (name == "out.txt" and args[1] == "info")  # .txt is info's text format
    ],
)
def test_an_unknown_extension_is_a_usage_error_naming_the_formats(index, tmp_path, args, formats, name):
    out = tmp_path / name
    code, stdout, err = run(*args, "--index", index, "-o", out)
    assert code == 2 and stdout == ""
    assert f"-o {out}" in err and formats in err and "--format" in err and "Traceback" not in err
    assert not out.exists()


def test_format_table_into_a_file_is_plain_text(index, tmp_path):
    out = tmp_path / "out.txt"
    code, _, err = run("query", TREFOIL, "--index", index, "--top", 2, "--format", "table", "-o", out)
    assert code == 0, err
    text = out.read_text()
    assert "trefoil.csv" in text and "\x1b[" not in text


def test_describe_and_rank_check_the_extension_before_any_work(tmp_path):
    for args in (
        ["describe", LIBRARY],
        ["rank", TREFOIL, LIBRARY],
        ["matrix", os.path.join(LIBRARY, "knotess")],
    ):
        code, out, err = run(*args, "-o", tmp_path / "x.yaml")
        assert code == 2 and out == "" and "'.yaml'" in err, args


# --------------------------------------------------------------------------- item 9: wrong extensions named


def test_show_names_a_wrong_picture_extension(index, tmp_path):
    code, out, err = run("show", TREFOIL, "--index", index, "-o", tmp_path / "x.jpg")
    assert code == 2 and out == ""
    assert "'.jpg'" in err and ".png, .svg, .pdf" in err and "one picture per query" not in err


def test_reconstruct_names_a_wrong_curve_extension_before_reading(tmp_path):
    code, out, err = run("reconstruct", os.path.join(LIBRARY, "trefoil.csv"), "-k", 3, "-o", tmp_path / "x.ply")
    assert code == 2 and out == ""
    assert "'.ply'" in err and ".obj" in err and ".vtp" in err and "extract its contours" not in err
    assert os.listdir(tmp_path) == []


# --------------------------------------------------------------------------- item 12: reconstruct --normalized


def test_reconstruct_normalized_keeps_the_distance_column(tmp_path):
    rows = {}
    for extra in ([], ["--normalized"]):
        code, out, err = run(
            "reconstruct", os.path.join(LIBRARY, "trefoil.csv"), "-k", 4, "-o", tmp_path / "t.obj", *extra
        )
        assert code == 0, err
        (rows[bool(extra)],) = list(csv.DictReader(io.StringIO(out)))
    assert list(rows[True]) == ["curve", "harmonics", "vertices", "distance"]
    # the distance ignores pose and size: the normalized curve is as far from the input
    assert float(rows[True]["distance"]) == pytest.approx(float(rows[False]["distance"]), rel=1e-6)


# --------------------------------------------------------------------------- items 10, 11: index build's dry run and JSON


@pytest.fixture
def built(tmp_path):
    shutil.copytree(LIBRARY, tmp_path / "lib")
    index = tmp_path / "lib.h5"
    assert run("index", "build", tmp_path / "lib", "--index", index, "--jobs", 1, "-q")[0] == 0
    return tmp_path / "lib", index


def test_dry_run_reports_a_broken_file_failed_the_results_count_and_the_builds_exit_code(built, tmp_path):
    lib, index = built
    (lib / "broken.csv").write_text("x,y,z\n1,2,3\n4,oops,6\n")
    (lib / "extra.csv").write_text("0 0\n1 0\n1 1\n0 1\n")
    code, out, err = run("index", "build", lib, "--index", index, "--dry-run", "--format", "json")
    assert code == 3 and "broken.csv: line 3" in err
    summary = json.loads(out)
    assert {c["path"]: c["action"] for c in summary["changes"]} == {
        "lib/broken.csv": "failed",
        "lib/extra.csv": "added",
    }
    assert summary["curves"] == 25 and summary["failed"] == 1 and summary["added"] == 1
    # the build does what its dry run said, with the same exit code
    code, out, _ = run("index", "build", lib, "--index", index, "--format", "json")
    real = json.loads(out)
    assert code == 3 and real["curves"] == 25 and (real["added"], real["failed"]) == (1, 1)


def test_dry_run_of_a_build_that_would_refuse_to_shrink_exits_2(built):
    lib, index = built
    shutil.rmtree(lib / "knotess")
    for name in (
        "trefoil.csv",
        "trefoil-noisy.csv",
        "trefoil-mirror.csv",
        "ellipse-2to1.csv",
        "ellipse-4to1.csv",
        "circle.tsv",
    ):
        os.remove(lib / name)
    code, out, err = run("index", "build", lib, "--index", index, "--dry-run")
    assert code == 2 and "removed\tlib/trefoil.csv" in out and "--allow-shrink" in err
    assert run("index", "build", lib, "--index", index, "--dry-run", "--allow-shrink")[0] == 0
    assert run("index", "build", lib, "--index", index)[0] == 2  # the build refuses alike


@pytest.mark.parametrize("dry_run", [[], ["--dry-run"]])
def test_every_json_build_writes_its_one_line_even_when_it_fails(built, tmp_path, dry_run):
    _, index = built
    missing = tmp_path / "unmounted"
    code, out, err = run("index", "build", missing, "--index", index, "--format", "json", *dry_run)
    assert code == 2 and "unmounted" in err
    (line,) = out.splitlines()
    record = json.loads(line)
    assert record["index"] == str(index) and record["written"] is False and "unmounted" in record["error"]
    assert record["started"].endswith("Z")


# --------------------------------------------------------------------------- item 2: one spelling of a path, from cron's /


def test_from_the_root_folder_failures_and_index_ls_spell_a_path_alike(tmp_path, monkeypatch):
    scans, data = tmp_path / "scans", tmp_path / "data"
    shutil.copytree(os.path.join(LIBRARY, "knotess"), scans / "knots")
    (scans / "knots" / "broken.csv").write_text("x,y,z\n1,2,3\n4,oops,6\n")
    data.mkdir()
    index = data / "contours.h5"
    monkeypatch.chdir("/")  # as cron runs it
    code, out, err = run("index", "build", scans, "--index", index, "--format", "json", "-j", 1)
    assert code == 3
    broken = str(scans / "knots" / "broken.csv")
    assert json.loads(out)["failures"][0]["path"] == broken
    assert err.startswith(f"Error: {broken}: line 3")
    code, out, _ = run("index", "ls", "--index", index, "--status", "failed", "--format", "json")
    (row,) = json.loads(out)
    assert row["file"] == broken and row["error"].startswith(f"{broken}: line 3")
    # a rebuild from the recorded sources (the cron line: no SOURCE) spells it the same
    os.utime(scans / "knots" / "broken.csv", ns=(10**9, 10**9))
    code, out, err = run("index", "build", "--index", index, "--format", "json", "-j", 1)
    assert code == 3 and json.loads(out)["failures"][0]["path"] == broken


# --------------------------------------------------------------------------- item 3: --paths


@pytest.mark.parametrize("mode", ["absolute", "relative"])
def test_query_paths_work_from_another_folder(index, tmp_path, monkeypatch, mode):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    query = os.path.relpath(TREFOIL)
    code, out, err = run("query", query, "--index", index, "--top", 3, "--paths", mode)
    assert code == 0, err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert len(rows) == 3
    for row in rows:
        for column in ("query", "match"):
            assert os.path.isabs(row[column]) == (mode == "absolute")
        # `query ... | cut -d, -f1,3 | xargs nfdmatch distance`: the pair opens from here
        assert run("distance", row["query"], row["match"])[0] == 0
    # the default is the ids as today: the match relative to the index's folder, which
    # does not open from here
    code, out, _ = run("query", query, "--index", index, "--top", 1)
    (row,) = list(csv.DictReader(io.StringIO(out)))
    assert row["query"] == query and row["match"] == "library/trefoil.csv"
    assert run("distance", row["query"], row["match"])[0] == 2


def test_rank_paths_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    code, out, err = run(
        "rank", "sample_curves/queries/trefoil-posed.obj", "sample_curves/library", "--top", 2, "--paths", "absolute"
    )
    assert code == 0, err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert rows[0]["query"] == TREFOIL and rows[0]["match"] == os.path.join(LIBRARY, "trefoil.csv")


# --------------------------------------------------------------------------- item 16: --color, NO_COLOR


@pytest.mark.parametrize(
    "terminal, no_color, option, styled",
    [
        (True, None, [], True),
        (True, "1", [], False),  # NO_COLOR: no colour and no bold either
        (True, "", [], True),  # set but empty: ignored (no-color.org)
        (True, None, ["--color", "never"], False),
        (True, "1", ["--color", "always"], True),
        (False, None, [], False),
        (False, None, ["--color", "always"], True),
    ],
)
def test_color_option_and_no_color(index, monkeypatch, terminal, no_color, option, styled):
    from nfdmatch.cli import output

    monkeypatch.setattr(output, "stdout_is_terminal", lambda: terminal)
    env = {"NO_COLOR": no_color}
    code, out, err = run("query", TREFOIL, "--index", index, "--top", 2, "--format", "table", *option, env=env)
    assert code == 0, err
    assert "trefoil.csv" in out and ("\x1b[" in out) == styled
    # the group takes it too (nfdmatch --color never query ...)
    code, out, _ = run(*option[:2], "query", TREFOIL, "--index", index, "--top", 2, "--format", "table", env=env)
    assert code == 0 and ("\x1b[" in out) == styled


def test_machine_formats_never_carry_escapes(index):
    code, out, _ = run("query", TREFOIL, "--index", index, "--top", 2, "--color", "always")
    assert code == 0 and out.startswith("query,rank,match,distance\n") and "\x1b" not in out


# --------------------------------------------------------------------------- item 15: .gitignore


def test_the_repository_ignores_build_locks_as_the_readme_tells_users():
    from fnmatch import fnmatch

    patterns = [line.strip() for line in open(os.path.join(ROOT, ".gitignore")) if line.strip()]
    assert any(fnmatch("curves.h5.lock", p) for p in patterns if not p.startswith("!"))
    assert "`*.h5.lock`" in open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
