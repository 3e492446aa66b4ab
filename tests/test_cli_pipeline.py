"""The command line in pipelines (Make, cron, the shell): -o files written whole and only on
success, one policy for bad inputs, -q/-v, stdin, --exclude-self, index ls/export, tables
that fit the terminal. Exit code, stdout and stderr are checked apart."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, run_cli as run

LIBRARY = os.path.join(ROOT, "sample_curves", "library")
QUERIES = os.path.join(ROOT, "sample_curves", "queries")
TREFOIL = os.path.join(QUERIES, "trefoil-posed.obj")


@pytest.fixture
def library(tmp_path):
    folder = tmp_path / "library"
    shutil.copytree(LIBRARY, folder)
    return folder


@pytest.fixture
def index(library, tmp_path):
    path = tmp_path / "lib.h5"
    code, _, err = run("index", "build", library, "--index", path, "--jobs", "1", "-q")
    assert code == 0 and err == ""
    return path


def leftovers(folder) -> list[str]:
    """Temporary files a writer left behind."""
    return [name for name in os.listdir(folder) if name.startswith(".")]


# --------------------------------------------------------------------------- -o FILE


def test_query_output_file_is_written_whole_and_an_identical_rerun_refreshes_its_mtime(index, tmp_path):
    out = tmp_path / "matches.csv"
    code, stdout, err = run("query", TREFOIL, "--index", index, "--top", 3, "-o", out)
    assert code == 0 and stdout == "" and err == ""
    rows = list(csv.DictReader(io.StringIO(out.read_text())))
    assert [r["rank"] for r in rows] == ["1", "2", "3"] and rows[0]["match"].endswith("trefoil.csv")
    os.utime(out, ns=(1_000_000_000, 1_000_000_000))
    inode = os.stat(out).st_ino
    code, stdout, err = run("query", TREFOIL, "--index", index, "--top", 3, "-o", out, "-v")
    assert code == 0 and stdout == "" and f"{out} unchanged" in err
    # the same file (bytes kept), newer than its inputs: a Make rule on it settles
    assert os.stat(out).st_ino == inode and os.stat(out).st_mtime_ns > os.stat(index).st_mtime_ns
    # different content replaces it; the format follows the extension
    code, stdout, _ = run("query", TREFOIL, "--index", index, "--top", 2, "-o", out.with_suffix(".json"))
    assert code == 0 and [r["rank"] for r in json.loads(out.with_suffix(".json").read_text())] == [1, 2]
    assert leftovers(tmp_path) == []


def test_a_failed_command_leaves_the_output_file_untouched(index, library, tmp_path):
    out = tmp_path / "matches.csv"
    out.write_text("previous\n")
    code, stdout, err = run("query", tmp_path / "nope.csv", "--index", index, "-o", out)
    assert code == 2 and stdout == "" and "nope.csv" in err
    assert out.read_text() == "previous\n"
    # partial success: the rows are not a finished target for Make, the file is kept as it was
    code, stdout, err = run("query", TREFOIL, tmp_path / "nope.csv", "--index", index, "-o", out)
    assert code == 3 and stdout == ""
    assert f"{out} not written: some inputs could not be read" in err and "1 of 2 inputs" in err
    assert out.read_text() == "previous\n" and leftovers(tmp_path) == []
    # an output folder that does not exist is named before any work
    code, stdout, err = run("rank", TREFOIL, library, "-o", tmp_path / "no" / "r.csv")
    assert code == 2 and stdout == "" and "r.csv" in err and "folder does not exist" in err


@pytest.mark.parametrize(
    "command",
    [
        ["distance", TREFOIL, os.path.join(LIBRARY, "trefoil.csv")],
        ["distance", TREFOIL, os.path.join(LIBRARY, "trefoil.csv"), "--format", "json"],
        ["describe", os.path.join(LIBRARY, "trefoil.csv"), "-k", "4"],
        ["rank", TREFOIL, LIBRARY, "--top", "3"],
        ["matrix", os.path.join(LIBRARY, "knotess")],
        ["index", "info", "--format", "json"],
    ],
)
def test_every_row_command_writes_to_o_what_it_prints(command, index, tmp_path):
    args = [*command, "--index", index] if command[0] == "index" else command
    code, printed, err = run(*args)
    assert code == 0, err
    # the extension says the format (distance's text is .txt: a .csv would be a usage error)
    out = tmp_path / ("out.json" if "json" in command else "out.txt" if command[0] == "distance" else "out.csv")
    code, stdout, err = run(*args, "-o", out)
    assert code == 0 and stdout == "" and err == ""
    assert out.read_text() == printed


def test_matrix_splits_pictures_and_rows_by_extension(tmp_path):
    png, rows = tmp_path / "m.png", tmp_path / "m.json"
    code, stdout, err = run("matrix", os.path.join(LIBRARY, "knotess"), "-o", png, "-o", rows)
    assert code == 0 and stdout == "" and f"wrote {png}" in err
    data = json.loads(rows.read_text())
    assert open(png, "rb").read(8) == b"\x89PNG\r\n\x1a\n" and len(data["ids"]) == len(data["distances"])
    code, _, err = run("matrix", LIBRARY, "-o", tmp_path / "a.csv", "-o", tmp_path / "b.csv")
    assert code == 2 and "one -o for the rows" in err


# --------------------------------------------------------------------------- bad inputs


def test_every_command_answers_what_it_can_read_and_exits_3(index, library, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,z\n1,2,3\n4,five,6\n")
    trefoil = os.path.join(LIBRARY, "trefoil.csv")
    for args in (
        ["query", TREFOIL, bad, "--index", index],
        ["describe", trefoil, bad],
        ["rank", TREFOIL, trefoil, bad],
        ["matrix", trefoil, TREFOIL, bad],
    ):
        code, stdout, err = run(*args, "--format", "csv")
        assert code == 3, args
        assert f"Error: {bad}: line 3" in err and "could not be read" in err
        assert len(list(csv.reader(io.StringIO(stdout)))) >= 2
    # nothing readable: exit 1, every input named, no rows
    code, stdout, err = run("query", bad, tmp_path / "nope.csv", "--index", index)
    assert code == 2 and stdout == "" and str(bad) in err and "nope.csv" in err


def test_an_empty_folder_is_a_named_error_everywhere(index, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    for args in (["query", empty, "--index", index], ["describe", empty], ["rank", TREFOIL, empty], ["matrix", empty]):
        code, stdout, err = run(*args)
        assert code == 2 and stdout == "" and f"Error: {empty}: no curve files found" in err, args
    code, stdout, err = run("query", empty, TREFOIL, "--index", index, "--format", "csv")
    assert code == 3 and f"{empty}: no curve files found" in err and "trefoil" in stdout


def test_describe_takes_folders(tmp_path):
    code, stdout, err = run("describe", os.path.join(LIBRARY, "knotess"), "-k", "2")
    assert code == 0 and err == ""
    ids = [r["id"] for r in csv.DictReader(io.StringIO(stdout))]
    assert len(ids) == len(os.listdir(os.path.join(LIBRARY, "knotess"))) and all("knotess" in i for i in ids)


# --------------------------------------------------------------------------- -q / -v and summaries


def test_quiet_keeps_errors_only_and_verbose_says_more(index, library, tmp_path):
    code, stdout, err = run("index", "build", library, "--index", tmp_path / "q.h5", "-q", "--jobs", "1")
    assert code == 0 and stdout == "" and err == ""
    code, stdout, err = run("index", "build", library, "--index", tmp_path / "q.h5", "--jobs", "1")
    assert code == 0 and "up to date" in err
    code, stdout, err = run("-q", "query", TREFOIL, tmp_path / "nope.csv", "--index", index, "--stats")
    assert code == 3 and "nope.csv" in err and "exact distances" not in err and stdout
    code, stdout, err = run("query", TREFOIL, "--index", index, "-v", "--format", "csv")
    assert code == 0 and "read 1 curve from 1 of 1 inputs" in err and re.search(r"^query: [0-9.]+ s$", err, re.M)
    code, _, err = run("query", TREFOIL, "--index", index, "-q", "-v")
    assert code == 2 and "exclude each other" in err


def test_build_json_summary_names_the_index_start_time_and_failed_files(library, tmp_path):
    (library / "bad.csv").write_text("x,y,z\n1,2,3\n4,five,6\n")
    index = tmp_path / "s.h5"
    code, stdout, err = run("index", "build", library, "--index", index, "--format", "json", "--jobs", "1")
    assert code == 3
    summary = json.loads(stdout)
    assert summary["index"] == str(index)
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", summary["started"])
    assert summary["failed"] == 1 and summary["failures"][0]["path"].endswith("bad.csv")
    assert "line 3" in summary["failures"][0]["error"]
    # the same closing line as every other command that reads several inputs
    assert err.strip().splitlines()[-1] == "Error: 1 of 22 files could not be read"


# --------------------------------------------------------------------------- stdin, --exclude-self


def test_stdin_needs_an_input_format_and_is_read_like_a_file():
    text = open(os.path.join(LIBRARY, "trefoil.csv")).read()
    noisy = os.path.join(LIBRARY, "trefoil-noisy.csv")
    code, stdout, err = run("distance", "-", noisy, "--input-format", "csv", "--format", "json", input=text)
    assert code == 0 and json.loads(stdout)["a"] == "<stdin>" and json.loads(stdout)["distance"] < 0.1
    code, stdout, err = run("distance", "-", noisy, input=text)
    assert code == 2 and stdout == "" and "--input-format" in err
    code, stdout, err = run(
        "rank",
        "-",
        os.path.join(LIBRARY, "circle.tsv"),
        os.path.join(LIBRARY, "trefoil.csv"),
        "--input-format",
        "csv",
        "--top",
        1,
        "--format",
        "csv",
        input=text,
    )
    assert code == 0 and list(csv.DictReader(io.StringIO(stdout)))[0]["match"].endswith("trefoil.csv")
    code, stdout, err = run("describe", "-", "--input-format", "csv", input="x,y,z\n1,2,3\n4,five,6\n")
    assert code == 2 and stdout == "" and "Error: <stdin>: line 3" in err


def test_exclude_self_drops_the_query_however_its_path_is_spelled(index, library, tmp_path, monkeypatch):
    trefoil = library / "trefoil.csv"
    code, stdout, _ = run("query", trefoil, "--index", index, "--top", 2, "--format", "json")
    rows = json.loads(stdout)
    assert rows[0]["match"] == "library/trefoil.csv" and rows[0]["distance"] < 1e-6  # relative to lib.h5's folder
    monkeypatch.chdir(library)
    code, stdout, err = run(
        "query", "./trefoil.csv", "--index", index, "--top", 2, "--format", "json", "--exclude-self"
    )
    assert code == 0, err
    rows = json.loads(stdout)
    assert [r["rank"] for r in rows] == [1, 2] and all(not r["match"].endswith("/trefoil.csv") for r in rows)
    code, stdout, _ = run("rank", "trefoil.csv", ".", "--top", 1, "--format", "json", "--exclude-self")
    assert json.loads(stdout)[0]["match"] != "./trefoil.csv" and json.loads(stdout)[0]["rank"] == 1


# --------------------------------------------------------------------------- index ls / export


def test_index_ls_lists_files_and_curves(index, library):
    code, stdout, err = run("index", "ls", "--index", index, "--format", "json")
    assert code == 0 and err == ""
    files = json.loads(stdout)
    assert {f["status"] for f in files} == {"ok"} and any(f["file"].endswith("superellipses.vtp") for f in files)
    code, stdout, _ = run("index", "ls", "--index", index, "--curves", "--format", "csv")
    ids = [r["id"] for r in csv.DictReader(io.StringIO(stdout))]
    code, info, _ = run("index", "info", "--index", index, "--format", "json")
    assert len(ids) == json.loads(info)["curves"] and "library/superellipses.vtp#1" in ids
    code, stdout, _ = run("index", "ls", "--index", index, "--status", "failed", "--format", "csv")
    assert code == 0 and stdout.strip() == "file,status,curves,error"


def test_index_export_npz_jsonl_csv_hold_the_stored_descriptors(index, tmp_path):
    code, stdout, err = run("index", "export", "--index", index, "-o", tmp_path / "d.npz")
    assert code == 0 and stdout == "" and err == ""
    data = np.load(tmp_path / "d.npz")
    n, k = len(data["ids"]), int(data["harmonics"])
    assert data["coefficients"].shape == (n, k, 3) and data["rotation"].shape == (n, 3, 3)
    code, _, _ = run("index", "export", "--index", index, "-o", tmp_path / "d.jsonl")
    records = [json.loads(line) for line in open(tmp_path / "d.jsonl")]
    assert [r["id"] for r in records] == list(data["ids"])
    np.testing.assert_allclose(np.array(records[0]["coefficients"])[..., 0], data["coefficients"][0].real)
    code, _, _ = run("index", "export", "--index", index, "-o", tmp_path / "d.csv")
    rows = list(csv.DictReader(open(tmp_path / "d.csv")))
    assert len(rows) == n and float(rows[0]["k+1_x_re"]) == pytest.approx(data["coefficients"][0, 0, 0].real)
    code, _, err = run("index", "export", "--index", index, "-o", tmp_path / "d.xyz")
    assert code == 2 and "--format" in err


# --------------------------------------------------------------------------- terminal tables


def test_tables_fit_the_terminal_and_fold_the_query_column(index, library):
    code, stdout, err = run("query", QUERIES, "--index", index, "--top", 3, "--format", "table", env={"COLUMNS": "60"})
    assert code == 0 and err == ""
    lines = stdout.splitlines()
    assert max(len(line) for line in lines) <= 60
    assert sum(line.startswith("query: ") for line in lines) == 3 and "trefoil-posed.obj" in stdout
    assert stdout.startswith("paths under library/")
    assert "library/trefoil.csv" not in stdout.replace("\n", "")  # said once, above
    # CSV is untouched by all this: full ids, one row per match
    code, stdout, _ = run("query", QUERIES, "--index", index, "--top", 3, "--format", "csv", env={"COLUMNS": "60"})
    assert len(stdout.splitlines()) == 10 and ",library/trefoil.csv," in stdout


# --------------------------------------------------------------------------- progress


@pytest.mark.slow
def test_progress_bars_only_on_a_terminal_and_not_with_quiet(index, monkeypatch):
    from nfdmatch.cli import output

    args = ("query", QUERIES, "--index", index, "--format", "csv")
    code, stdout, err = run(*args)
    assert code == 0 and err == ""
    monkeypatch.setattr(output, "stderr_is_terminal", lambda: True)
    code, stdout_tty, err = run(*args)
    assert code == 0 and "searching" in err and stdout_tty == stdout
    code, _, err = run(*args, "-q")
    assert code == 0 and err == ""
    code, _, err = run("matrix", os.path.join(LIBRARY, "knotess"))
    assert code == 0 and "distances" in err
    # rank and describe too (issue 25: 3,000 files took seconds in silence), over the files
    # read, with the same rows as without a terminal
    for command in (["rank", TREFOIL, LIBRARY, "--top", "3"], ["describe", LIBRARY, "-k", "2"]):
        code, rows_tty, err = run(*command)
        assert code == 0 and "reading curves" in err and "21/21" in err, command
        assert run(*command, "-q")[1:] == (rows_tty, "")
        monkeypatch.setattr(output, "stderr_is_terminal", lambda: False)
        assert run(*command) == (0, rows_tty, "")
        monkeypatch.setattr(output, "stderr_is_terminal", lambda: True)


# --------------------------------------------------------------------------- the README's Makefile


def readme_makefile() -> str:
    text = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    section = text.split("### Use in Makefiles and cron", 1)[1]
    return re.search(r"```make\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_the_readme_makefile_runs_and_a_second_run_rebuilds_nothing(tmp_path):
    (tmp_path / "Makefile").write_text(readme_makefile())
    shutil.copytree(LIBRARY, tmp_path / "curves")
    shutil.copytree(QUERIES, tmp_path / "queries")
    env = {
        **os.environ,
        "NFDMATCH": f"{sys.executable} -m nfdmatch",
        "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]),
    }

    def make():
        return subprocess.run(["make"], cwd=tmp_path, env=env, capture_output=True, text=True)

    targets = ("curves.h5", "report.csv")

    def mtimes():
        return {p: os.stat(tmp_path / p).st_mtime_ns for p in targets}

    first = make()
    assert first.returncode == 0, first.stderr
    report = tmp_path / "report.csv"
    rows = list(csv.DictReader(open(report)))
    assert {r["query"] for r in rows} == {f"queries/{q}" for q in os.listdir(QUERIES)}
    before = mtimes()
    second = make()
    assert second.returncode == 0 and "Nothing to be done" in second.stdout + second.stderr
    assert mtimes() == before

    # a touch, an edit, a deletion: one run rebuilds (both targets newer than before), the
    # next one does nothing. The targets are first made older than any change, so that a
    # change in the same clock tick as the last build still counts as newer.
    def changed_then_settles(change):
        for p in targets:
            os.utime(tmp_path / p, ns=(before[p] - 10**10, before[p] - 10**10))
        old = mtimes()
        change()
        run1 = make()
        assert run1.returncode == 0, run1.stderr
        assert "index build" in run1.stdout and "query" in run1.stdout
        new = mtimes()
        assert all(new[p] > old[p] for p in targets)
        for p in targets:  # outputs newer than every input, as Make reads it
            assert all(
                new[p] >= os.stat(os.path.join(d, f)).st_mtime_ns
                for d, _, files in os.walk(tmp_path / "curves")
                for f in files
            )
        run2 = make()
        assert run2.returncode == 0 and "Nothing to be done" in run2.stdout + run2.stderr, run2.stdout
        assert mtimes() == new

    changed_then_settles(lambda: os.utime(tmp_path / "curves" / "circle.tsv"))  # the same bytes
    # a file that is not a curve: the folder changed, the index has nothing to change
    changed_then_settles(lambda: (tmp_path / "curves" / "NOTES.md").write_text("scanned on the 3rd\n"))
    changed_then_settles(lambda: (tmp_path / "curves" / "circle.tsv").write_text("0 0\n2 0\n2 1\n0 1\n"))
    changed_then_settles(lambda: os.remove(tmp_path / "curves" / "knotess" / "4_1.csv"))  # in a subfolder
    assert "knotess/4_1.csv" not in (tmp_path / "report.csv").read_text()
    before = mtimes()

    # a bad query: make fails, the report is not replaced by a partial one
    (tmp_path / "queries" / "bad.csv").write_text("x,y,z\n1,2,3\n")
    third = make()
    assert third.returncode != 0 and "bad.csv" in third.stderr
    assert os.stat(report).st_mtime_ns == before["report.csv"]
    os.remove(tmp_path / "queries" / "bad.csv")

    # a bad curve (issue 40): --strict keeps the index as it was, so every make fails until
    # it is fixed, instead of the second one taking an index with a failed file for done
    (tmp_path / "curves" / "broken.csv").write_text("x,y,z\n1,2,3\n4,oops,6\n")
    for _ in range(2):
        failing = make()
        assert failing.returncode != 0 and "broken.csv" in failing.stderr
        assert os.stat(tmp_path / "curves.h5").st_mtime_ns == before["curves.h5"]
    os.remove(tmp_path / "curves" / "broken.csv")
    fixed = make()
    assert fixed.returncode == 0, fixed.stderr
