"""`nfdmatch index build/info` and `nfdmatch query` through CliRunner."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil

import numpy as np
import pytest


from nfdmatch import write_curves
from conftest import ROOT, run_cli as run

LIBRARY = os.path.join(ROOT, "sample_curves", "library")
QUERIES = os.path.join(ROOT, "sample_curves", "queries")


@pytest.fixture
def library(tmp_path):
    folder = tmp_path / "library"
    shutil.copytree(LIBRARY, folder)
    return folder


def build_json(*args):
    code, out, err = run("index", "build", *args, "--format", "json", "--jobs", "1")
    return code, (json.loads(out) if out.strip() else None), err


def test_build_info_query_round_trip(library, tmp_path):
    index = tmp_path / "idx.h5"
    code, summary, err = build_json(library, "--index", index)
    assert code == 0, err
    assert summary["added"] == len([p for p in library.rglob("*") if p.is_file()])
    assert summary["failed"] == summary["updated"] == summary["removed"] == summary["unchanged"] == 0
    assert summary["curves"] == 24 and isinstance(summary["seconds"], float)

    code, out, _ = run("index", "info", "--index", index, "--format", "json")
    info = json.loads(out)
    assert code == 0 and info["curves"] == 24 and info["files"] == summary["added"]
    assert (info["samples"], info["harmonics"], info["scale"]) == (128, 16, "rms")
    assert info["format_version"] == 3

    code, out, _ = run("index", "info", "--index", index)
    assert code == 0 and "curves\t24" in out

    code, out, err = run(
        "query", os.path.join(QUERIES, "trefoil-posed.obj"), "--index", index, "--top", "3", "--format", "csv"
    )
    rows = list(csv.DictReader(io.StringIO(out)))
    assert code == 0 and list(rows[0])[:4] == ["query", "rank", "match", "distance"]
    assert rows[0]["match"].endswith(os.path.join("library", "trefoil.csv"))
    assert float(rows[0]["distance"]) < 0.01 and [r["rank"] for r in rows] == ["1", "2", "3"]

    # an indexed curve queried against its own index: itself, first, at ~0
    code, out, _ = run("query", library / "lissajous-family.obj#1", "--index", index, "--top", "1", "--format", "json")
    top = json.loads(out)[0]
    # ids are stored relative to the index's folder (docs/index-format.md, "Paths and ids")
    assert top["match"] == "library/lissajous-family.obj#1" and top["distance"] < 1e-5


def test_rerun_is_incremental_and_idempotent(library, tmp_path):
    index = tmp_path / "idx.h5"
    assert build_json(library, "--index", index)[0] == 0
    before = index.read_bytes()
    code, summary, _ = build_json(library, "--index", index)
    assert code == 0 and summary["unchanged"] > 0 and summary["added"] == summary["updated"] == 0
    (library / "circle.tsv").unlink()
    write_curves(library / "new.csv", np.random.default_rng(0).normal(size=(30, 3)))
    code, summary, _ = build_json(library, "--index", index)
    assert (summary["added"], summary["removed"]) == (1, 1)
    assert before != index.read_bytes()


def test_dry_run_prints_the_plan_and_writes_nothing(library, tmp_path):
    index = tmp_path / "idx.h5"
    build_json(library, "--index", index)
    stamp = (index.read_bytes(), os.stat(index).st_mtime_ns)
    write_curves(library / "extra.csv", np.random.default_rng(1).normal(size=(20, 3)))
    code, out, err = run("index", "build", library, "--index", index, "--dry-run")
    assert code == 0
    assert "added\tlibrary/extra.csv" in out
    assert (index.read_bytes(), os.stat(index).st_mtime_ns) == stamp
    code, summary, _ = build_json(library, "--index", index, "--dry-run")
    assert summary["added"] == 1 and summary["dry_run"] is True
    assert summary["changes"] == [{"action": "added", "path": "library/extra.csv"}]


def test_bad_file_is_reported_recorded_and_exit_3(library, tmp_path):
    index = tmp_path / "idx.h5"
    (library / "broken.csv").write_text("x,y,z\n1,2,3\n4,oops,6\n")
    code, summary, err = build_json(library, "--index", index)
    assert code == 3
    assert summary["failed"] == 1 and summary["curves"] == 24
    assert "broken.csv" in err and "line 3" in err and "Traceback" not in err
    code, out, _ = run("index", "info", "--index", index, "--format", "json")
    failed = json.loads(out)["failed"]
    assert len(failed) == 1 and failed[0]["path"].endswith("broken.csv") and "line 3" in failed[0]["error"]


def test_index_path_from_environment(library, tmp_path):
    index = tmp_path / "env.h5"
    env = {"NFDMATCH_INDEX": str(index)}
    code, out, err = run("index", "build", library, "--jobs", "1", env=env)
    assert code == 0 and index.exists()
    assert "24 curves" in err
    code, out, _ = run("query", os.path.join(QUERIES, "ellipse-posed.csv"), "--top", "1", "--format", "jsonl", env=env)
    assert code == 0 and json.loads(out)["match"].endswith("ellipse-2to1.csv")


@pytest.mark.parametrize(
    "content, needle",
    [
        (b"", "idx.h5"),
        (b"\x89HDF\r\n\x1a\n" + b"\0" * 100, "idx.h5"),
        (b"not an index at all" * 100, "idx.h5"),
    ],
)
def test_query_on_a_bad_index_is_exit_2(tmp_path, content, needle):
    index = tmp_path / "idx.h5"
    index.write_bytes(content)
    code, out, err = run("query", os.path.join(QUERIES, "ellipse-posed.csv"), "--index", index)
    assert code == 2 and out == "" and err.startswith("Error: ") and needle in err
    assert "Traceback" not in err


def test_missing_index_is_exit_2_with_a_hint(tmp_path):
    code, out, err = run("query", os.path.join(QUERIES, "ellipse-posed.csv"), "--index", tmp_path / "none.h5")
    assert code == 2 and "none.h5" in err and "index build" in err


def test_query_folder_every_format_and_details(library, tmp_path):
    index = tmp_path / "idx.h5"
    build_json(library, "--index", index)
    for fmt in ("csv", "tsv", "json", "jsonl", "table"):
        code, out, err = run("query", QUERIES, "--index", index, "--top", "2", "--format", fmt, "--details")
        assert code == 0, err
        if fmt == "table":
            assert "trefoil.csv" in out
            continue
        if fmt in ("csv", "tsv"):
            rows = list(csv.DictReader(io.StringIO(out), delimiter="," if fmt == "csv" else "\t"))
        elif fmt == "json":
            rows = json.loads(out)
        else:
            rows = [json.loads(line) for line in out.splitlines()]
        assert len(rows) == 6 and {"shift", "reversed", "mirrored"} <= set(rows[0])
        assert len({r["query"] for r in rows}) == 3


def test_query_partial_failure_exit_3_and_stats(library, tmp_path):
    index = tmp_path / "idx.h5"
    build_json(library, "--index", index)
    bad = tmp_path / "q" / "bad.csv"
    bad.parent.mkdir()
    bad.write_text("1,2\n")
    shutil.copy(os.path.join(QUERIES, "ellipse-posed.csv"), bad.parent)
    code, out, err = run("query", bad.parent, "--index", index, "--top", "1", "--stats", "--format", "csv")
    assert code == 3 and len(out.strip().splitlines()) == 2
    assert "bad.csv" in err and "exact distances" in err


def test_parameter_change_recomputes_with_a_notice(library, tmp_path):
    index = tmp_path / "idx.h5"
    build_json(library, "--index", index)
    code, summary, err = build_json(library, "--index", index, "--samples", "64", "--harmonics", "8")
    assert code == 0 and "Notice" in err and summary["updated"] + summary["added"] > 0
    code, out, _ = run("index", "info", "--index", index, "--format", "json")
    assert (json.loads(out)["samples"], json.loads(out)["harmonics"]) == (64, 8)
    code, summary, _ = build_json(library, "--index", index)  # no flags: keep the index's
    assert summary["unchanged"] > 0 and summary["updated"] == 0


def test_lock_held_is_exit_2(library, tmp_path):
    import fcntl

    index = tmp_path / "idx.h5"
    with open(f"{index}.lock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        code, out, err = run("index", "build", library, "--index", index)
    assert code == 2 and "lock" in err and not index.exists()


def test_query_exhaustive_gives_the_pruned_answer_and_stats_say_what_was_done(library, tmp_path):
    index = tmp_path / "idx.h5"
    assert build_json(library, "--index", index)[0] == 0
    query = library / "trefoil.csv"
    code, pruned, err = run("query", query, "--index", index, "--top", "5", "--format", "csv", "--details", "--stats")
    assert code == 0, err
    assert "exact distances" in err and "rows bounded in" in err and "MiB read" in err
    assert "kernels: aot (compiled ahead of time for this source)" in err  # make install built them
    code, verbose, err = run("-v", "query", query, "--index", index, "--top", "5", "--format", "csv", "--details")
    assert code == 0 and verbose == pruned and "kernels: aot (" in err
    code, full, err = run(
        "query", query, "--index", index, "--top", "5", "--format", "csv", "--details", "--exhaustive", "--stats"
    )
    assert code == 0 and full == pruned
    curves = int(err.split(" rows:")[0].split(" x ")[1])
    assert f"{curves} exact distances" in err  # every row, for the one query


def test_query_on_a_format_1_index_says_how_to_upgrade(tmp_path):
    frozen = os.path.join(ROOT, "tests", "data", "index", "v1-sample.h5")
    index = tmp_path / "old.h5"
    shutil.copyfile(frozen, index)
    query = os.path.join(ROOT, "sample_curves", "library", "trefoil.csv")
    code, out, err = run("query", query, "--index", index, "--top", "2", "--format", "csv")
    assert code == 0 and len(out.strip().splitlines()) == 3
    assert "format 1" in err and "index build" in err
