"""The README's walk-through, end to end: generated meshes -> extract -> index -> query ->
show, through the CLI. A section of a re-posed, re-triangulated copy of a mesh must find
the section at the same level of the original."""

from __future__ import annotations

import csv
import importlib.util
import io
import os
import re

import pytest

from conftest import ROOT, run_cli as run

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    spec = importlib.util.spec_from_file_location("make_meshes", os.path.join(ROOT, "sample_curves", "make_meshes.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path_factory.mktemp("walk") / "meshes"
    module.main(str(out))
    return out


def test_sections_of_a_posed_copy_find_their_own_levels(meshes, tmp_path):
    code, out, err = run("extract", meshes / "column.stl", "--sections", 12, "-o", tmp_path / "contours")
    assert code == 0, err
    assert len(list(csv.DictReader(io.StringIO(out)))) == 12
    code, _, err = run("index", "build", tmp_path / "contours", "--index", tmp_path / "column.h5")
    assert code == 0, err
    code, out, err = run("extract", meshes / "column-posed.ply", "--sections", 12, "-o", tmp_path / "posed")
    assert code == 0, err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert {r["axis"] for r in rows} == {"x"}  # the posed copy lies along x
    code, out, err = run("query", tmp_path / "posed", "--index", tmp_path / "column.h5", "--top", 2, "--format", "csv")
    assert code == 0, err
    hits = list(csv.DictReader(io.StringIO(out)))
    by_query: dict[str, list[dict]] = {}
    for row in hits:
        by_query.setdefault(row["query"], []).append(row)
    assert len(by_query) == 12
    level = re.compile(r"section-[xyz](\d+)_")
    for query, (best, second) in by_query.items():
        assert level.search(query).group(1) == level.search(best["match"]).group(1), (query, best)
        assert float(best["distance"]) < 0.005
        assert float(second["distance"]) > 5 * float(best["distance"])
    # and the picture of one of them
    some = sorted(by_query)[5]
    code, out, err = run("show", some, "--index", tmp_path / "column.h5", "-o", tmp_path / "s.png")
    assert code == 0 and os.path.getsize(tmp_path / "s.png") > 10_000


def test_the_cup_rim_is_a_boundary_and_sections_across_its_opening_are_skipped(meshes, tmp_path):
    code, out, err = run(
        "extract",
        meshes / "cup.stl",
        "--sections",
        3,
        "--axis",
        "z",
        "--boundaries",
        "-o",
        tmp_path / "cup",
        "--format",
        "csv",
    )
    assert code == 0, err
    kinds = [r["kind"] for r in csv.DictReader(io.StringIO(out))]
    assert kinds == ["section", "section", "section", "boundary"]
    code, out, err = run("extract", meshes / "cup.stl", "--sections", 3, "--axis", "x", "-o", tmp_path / "cup-x")
    assert code == 2 and out == ""
    assert err.count("open piece skipped (not closed)") == 3 and "Error: no closed contour" in err
