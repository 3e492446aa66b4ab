"""`nfdmatch pairs` and `nfdmatch groups`: the whole index against itself."""

from __future__ import annotations

import csv
import io
import json
import os

import numpy as np
import pytest

from conftest import run_cli as run
from oracle import random_rigid_motion, smooth_curve_samplings, start_shift

from nfdmatch import Curve, write_curves
from nfdmatch.index import build_index, open_index
from nfdmatch.matching import exact_search

#: families of near-duplicates far apart from each other
FAMILIES, MEMBERS = 5, 4


def _families(rng, families=FAMILIES, members=MEMBERS, prefix="f"):
    curves = []
    for f in range(families):
        base = smooth_curve_samplings(rng, [80], n_harmonics=4)[0]
        for m in range(members):
            pts = start_shift(base + rng.normal(scale=0.002, size=base.shape), int(rng.integers(80)))
            curves.append(Curve(random_rigid_motion(pts * float(rng.uniform(0.5, 2)), rng), id=f"{prefix}{f}-{m}"))
    return curves


@pytest.fixture
def library(tmp_path, rng):
    curves = _families(rng)
    folder = tmp_path / "lib"
    folder.mkdir()
    for f in range(FAMILIES):
        write_curves(folder / f"fam{f}.obj", curves[f * MEMBERS : (f + 1) * MEMBERS])
    index = tmp_path / "lib.h5"
    build_index([folder], index, jobs=1)
    return folder, index


def _all_distances(index):
    with open_index(index) as idx:
        N = idx.n_curves
        C = idx.coefficients_at(np.arange(N))
        ids = idx.ids_at(np.arange(N))
        D = np.array([exact_search(np.asarray(C[i], np.complex128), C, idx.samples)["distance"] for i in range(N)])
    return ids, D


def _threshold(D):
    """A distance between the families' spread and the gap between families."""
    np.fill_diagonal(D, np.inf)
    inside = D.shape[0] and max(np.sort(D, axis=1)[:, MEMBERS - 2])
    across = np.sort(D, axis=1)[:, MEMBERS - 1].min()
    assert inside < across / 3
    return float(2 * inside)


def test_pairs_lists_every_pair_within_the_distance_once(library):
    _, index = library
    ids, D = _all_distances(index)
    limit = _threshold(D)
    code, out, err = run("pairs", "--index", index, "--max-distance", limit, "--format", "csv")
    assert code == 0 and err == ""
    rows = list(csv.DictReader(io.StringIO(out)))
    assert list(rows[0]) == ["a", "b", "distance"]
    got = {(r["a"], r["b"]) for r in rows}
    assert len(got) == len(rows) == FAMILIES * MEMBERS * (MEMBERS - 1) // 2
    assert all(a < b for a, b in got)
    expected = {
        tuple(sorted((ids[i], ids[j]))) for i in range(len(ids)) for j in range(i + 1, len(ids)) if D[i, j] <= limit
    }
    assert got == expected
    assert [(r["a"], r["b"]) for r in rows] == sorted(got)
    for r in rows:
        i, j = ids.index(r["a"]), ids.index(r["b"])
        assert float(r["distance"]) == pytest.approx(min(D[i, j], D[j, i]), rel=1e-9, abs=1e-12)
    # the other formats carry the same rows
    code, out, _ = run("pairs", "--index", index, "--max-distance", limit, "--format", "jsonl")
    assert code == 0 and [json.loads(line)["a"] for line in out.splitlines()] == [r["a"] for r in rows]
    code, out, _ = run("pairs", "--index", index, "--max-distance", limit, "--format", "tsv")
    assert code == 0 and out.splitlines()[0] == "a\tb\tdistance" and len(out.splitlines()) == len(rows) + 1
    code, out, _ = run("pairs", "--index", index, "--max-distance", limit, "--format", "json")
    assert code == 0 and len(json.loads(out)) == len(rows)


def test_pairs_to_a_file_and_none_below_zero_distance(library, tmp_path):
    _, index = library
    target = tmp_path / "pairs.jsonl"
    code, out, err = run("pairs", "--index", index, "--max-distance", "0", "-o", target)
    assert code == 1 and out == "" and err == ""  # nothing matched, as grep says it (issue 40)
    assert target.read_text() == ""
    code, out, err = run("pairs", "--index", index, "--max-distance", "0", "-v", "--format", "csv")
    assert code == 1 and out == "a,b,distance\n" and "0 pairs: 20 curves" in err


def test_pairs_new_lists_only_pairs_with_a_curve_of_the_last_build(library, rng):
    folder, index = library
    ids, D = _all_distances(index)
    limit = _threshold(D)
    # the first build added everything: --new is every pair
    _, everything, _ = run("pairs", "--index", index, "--max-distance", limit, "--format", "csv")
    code, out, _ = run("pairs", "--index", index, "--max-distance", limit, "--format", "csv", "--new")
    assert code == 0 and out == everything
    # a new file: a copy of one family member (a duplicate) and a curve like nothing else
    from nfdmatch import read_curves

    original = read_curves(folder / "fam2.obj")[1]
    fresh = Curve(random_rigid_motion(original.points, rng), id="copy")
    write_curves(folder / "new.obj", [fresh, _families(rng, 1, 1, prefix="x")[0]])
    build_index([folder], index, jobs=1)
    code, out, err = run("pairs", "--index", index, "--max-distance", limit, "--format", "csv", "--new")
    assert code == 0 and err == ""
    rows = list(csv.DictReader(io.StringIO(out)))
    new_ids = {r["a"] for r in rows} | {r["b"] for r in rows}
    assert all("new.obj" in r["a"] or "new.obj" in r["b"] for r in rows)
    assert len(rows) == MEMBERS  # the copy pairs with its family of four
    assert any("fam2.obj" in i for i in new_ids)
    # a build that changes nothing keeps the record of the last one that wrote the index
    assert not build_index([folder], index, jobs=1).written
    assert run("pairs", "--index", index, "--max-distance", limit, "--format", "csv", "--new")[1] == out


def test_pairs_new_on_an_index_without_the_record_is_a_clean_error(library):
    import h5py

    _, index = library
    with h5py.File(index, "a") as f:
        del f["changes"]
    code, out, err = run("pairs", "--index", index, "--max-distance", "0.1", "--new")
    assert code == 2 and out == ""
    assert err.startswith("Error: ") and "--rebuild" in err


@pytest.mark.parametrize(
    "damage",
    ["text", "float", "outside", "no rows", "a dataset"],
)
def test_a_malformed_changes_record_is_found_by_verify_and_refused_by_pairs_new(library, damage):
    import h5py

    _, index = library
    with h5py.File(index, "a") as f:
        rows = f["changes/rows"][...]
        if damage == "a dataset":
            del f["changes"]
            f["changes"] = np.zeros(3)
        else:
            del f["changes/rows"]
            if damage != "no rows":
                value = {
                    "text": rows.astype("S8"),
                    "float": rows.astype(float),
                    "outside": rows + 10_000,
                }[damage]
                f["changes/rows"] = value
    code, out, err = run("index", "verify", "--index", index)
    assert code == 1 and "/changes" in out and err.startswith("Error: ")
    code, out, err = run("pairs", "--index", index, "--max-distance", "0.1", "--new")
    assert code == 2 and out == ""
    assert err.startswith("Error: ") and "corrupted nfdmatch index: /changes" in err
    assert "Traceback" not in err


def test_pairs_usage_errors(library, tmp_path):
    _, index = library
    code, out, err = run("pairs", "--index", index)
    assert code == 2 and out == "" and "--max-distance" in err
    code, out, err = run("pairs", "--index", index, "--max-distance", "-1")
    assert code == 2 and out == ""
    code, out, err = run("pairs", "--index", tmp_path / "missing.h5", "--max-distance", "1")
    assert code == 2 and out == "" and err.startswith("Error: ")


def test_groups_are_the_families_with_their_representative(library):
    _, index = library
    ids, D = _all_distances(index)
    limit = _threshold(D)
    code, out, err = run("groups", "--index", index, "--max-distance", limit, "--format", "csv")
    assert code == 0 and err == ""
    rows = list(csv.DictReader(io.StringIO(out)))
    assert list(rows[0]) == ["id", "group", "size", "representative"]
    assert len(rows) == FAMILIES * MEMBERS
    by_group = {}
    for r in rows:
        by_group.setdefault(r["group"], []).append(r)
    assert sorted(by_group) == [str(g) for g in range(1, FAMILIES + 1)]
    for members in by_group.values():
        names = [r["id"] for r in members]
        assert len({os.path.basename(n).split("#")[0] for n in names}) == 1  # one family (one file)
        assert all(r["size"] == str(MEMBERS) for r in members)
        rep = {r["representative"] for r in members}
        assert len(rep) == 1
        at = [ids.index(n) for n in names]
        total = [sum(min(D[i, j], D[j, i]) for j in at if j != i) for i in at]
        assert rep == {names[int(np.argmin(total))]}
    # JSON: the groups as lists
    code, out, _ = run("groups", "--index", index, "--max-distance", limit, "--format", "json")
    groups = json.loads(out)
    assert code == 0 and len(groups) == FAMILIES
    assert all(len(g["members"]) == g["size"] == MEMBERS and g["representative"] in g["members"] for g in groups)


def test_groups_single_linkage_and_min_size(library):
    _, index = library
    # no pair at distance 0: every curve its own group, which --min-size 2 drops
    code, out, _ = run("groups", "--index", index, "--max-distance", "0", "--format", "csv")
    rows = list(csv.DictReader(io.StringIO(out)))
    assert code == 0 and len(rows) == FAMILIES * MEMBERS
    assert all(r["size"] == "1" and r["representative"] == r["id"] for r in rows)
    code, out, err = run("groups", "--index", index, "--max-distance", "0", "--min-size", "2", "--format", "csv")
    assert code == 1 and out == "id,group,size,representative\n" and err == ""  # nothing matched
    # a distance past every pair: one group
    code, out, _ = run("groups", "--index", index, "--max-distance", "100", "--format", "jsonl")
    rows = [json.loads(line) for line in out.splitlines()]
    assert code == 0 and {r["group"] for r in rows} == {1} and {r["size"] for r in rows} == {FAMILIES * MEMBERS}


def test_groups_chain_into_one_by_single_linkage(tmp_path, rng):
    """Three curves a - b - c with a, b and b, c within D but a, c not: one group of 3."""
    from nfdmatch.search import MemoryIndex
    from nfdmatch.search.groups import index_groups, index_pairs

    t = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    curves = [Curve(np.c_[np.cos(t), (1 + 0.1 * s) * np.sin(t), 0.3 * np.sin(2 * t)], id=f"c{s}") for s in range(3)]
    index = MemoryIndex(curves)
    d_ab = exact_search(
        index.coefficients_at([0])[0].astype(np.complex128), index.coefficients_at([1, 2]), index.samples
    )["distance"]
    limit = float(d_ab[0]) * 1.2
    assert d_ab[1] > limit  # a and c are not a pair
    found, _ = index_pairs(index, limit)
    assert [(p.a, p.b) for p in found] == [("c0", "c1"), ("c1", "c2")]
    members, _ = index_groups(index, limit)
    assert [(m.id, m.group, m.size, m.representative) for m in members] == [
        ("c0", 1, 3, "c1"),
        ("c1", 1, 3, "c1"),
        ("c2", 1, 3, "c1"),
    ]


def test_pairs_and_groups_write_file_names_not_the_index_ids(tmp_path, rng):
    # an id is a file's name encoded (a backslash doubled, a byte that is not UTF-8 as \xNN):
    # every column naming a curve (a, b, id, representative, members) writes the name itself,
    # as query does: raw bytes in CSV, \udcNN in JSON
    from click.testing import CliRunner

    from nfdmatch.cli import main

    folder = tmp_path / "lib"
    folder.mkdir()
    pts = smooth_curve_samplings(rng, [80], n_harmonics=4)[0]
    names = [b"back\\slash.csv", b"c\xff.csv", b"plain.csv"]
    for name in names:
        write_curves(os.path.join(str(folder), os.fsdecode(name)), pts)
    index = tmp_path / "lib.h5"
    build_index([folder], index, jobs=1)
    expected = sorted(b"lib/" + name for name in names)  # ids relative to the index's folder

    def stdout_of(*args):
        result = CliRunner().invoke(main, [*args, "--index", str(index), "--max-distance", "0.01"])
        assert result.exit_code == 0, result.stderr
        return result.stdout_bytes

    rows = stdout_of("pairs", "--format", "csv").splitlines()[1:]
    assert sorted({field for row in rows for field in row.split(b",")[:2]}) == expected
    rows = stdout_of("groups", "--format", "csv").splitlines()[1:]
    assert sorted(row.split(b",")[0] for row in rows) == expected
    assert {row.split(b",")[3] for row in rows} <= set(expected)
    (group,) = json.loads(stdout_of("groups", "--format", "json"))
    assert sorted(os.fsencode(m) for m in group["members"]) == expected
    assert os.fsencode(group["representative"]) in expected
    pairs = [json.loads(line) for line in stdout_of("pairs", "--format", "jsonl").splitlines()]
    assert sorted({os.fsencode(p[c]) for p in pairs for c in "ab"}) == expected
