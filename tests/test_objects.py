"""Meshes as objects: indexed by their contours (``index build MESHES``), queried by a mesh
(``query MESH``, ``Index.search`` of a mesh), and the object distance (docs/objects.md)."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from nfdmatch.cli import main
from nfdmatch.index import build_index, open_index

trimesh = pytest.importorskip("trimesh")

HERE = os.path.dirname(os.path.abspath(__file__))
FROZEN_V3 = os.path.join(HERE, "data", "index", "v3-objects-sample.h5")


def _shapes() -> dict:
    """Small meshes of distinct shapes (a few hundred faces each)."""
    bar = trimesh.creation.box((1.0, 1.4, 4.0))
    for _ in range(3):
        bar = bar.subdivide()
    return {
        "torus.ply": trimesh.creation.torus(1.0, 0.3, major_sections=24, minor_sections=12),
        "capsule.stl": trimesh.creation.capsule(height=2.0, radius=0.5, count=[16, 16]),
        "bar.off": bar,
        "cone.obj": trimesh.creation.cone(1.0, 2.5, sections=24).subdivide().subdivide(),
    }


@pytest.fixture
def parts(tmp_path):
    folder = tmp_path / "parts"
    folder.mkdir()
    for name, mesh in _shapes().items():
        mesh.export(str(folder / name))
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    np.savetxt(folder / "ring.csv", np.c_[np.cos(t), np.sin(t), 0 * t], delimiter=",", header="x,y,z", comments="")
    return folder


def _copy_reposed(mesh, seed: int):
    """The mesh rotated, moved, scaled by 3.7 and re-triangulated (every face split in 4)."""
    m = mesh.copy()
    rng = np.random.default_rng(seed)
    m.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    m.apply_translation(rng.normal(size=3) * 10)
    m.apply_scale(3.7)
    return m.subdivide()


def test_a_folder_of_meshes_is_indexed_as_objects(parts, tmp_path):
    index = str(tmp_path / "parts.h5")
    report = build_index([str(parts)], index, jobs=1)
    assert report.added == 5 and report.failed == 0
    with open_index(index) as idx:
        assert idx.format_version == 3
        assert idx.object_ids() == ["parts/bar.off", "parts/capsule.stl", "parts/cone.obj", "parts/torus.ply"]
        objects = idx.objects()
        assert objects.rule.sections == 7
        ids = idx.ids()
        # the curve file stays a curve; each mesh's contours are its rows, tagged with axis and level
        ring = ids.index("parts/ring.csv")
        assert objects.axis[ring] == -1
        torus = [i for i, c in enumerate(ids) if c.startswith("parts/torus.ply#")]
        assert len(torus) >= 21 and set(objects.axis[torus]) == {0, 1, 2}
        assert objects.level[torus].min() == 0 and objects.level[torus].max() == 6
        assert objects.profile.shape == (4, 3 * 7 * 4)


def test_a_reposed_rescaled_retriangulated_copy_finds_its_original_first(parts, tmp_path):
    index = str(tmp_path / "parts.h5")
    build_index([str(parts)], index, jobs=1)
    with open_index(index) as idx:
        for seed, (name, mesh) in enumerate(_shapes().items()):
            found = idx.search(_copy_reposed(mesh, seed), k=2)[0]
            assert found[0].id == f"parts/{name}", (name, found)
            assert found[0].distance < 0.25 * found[1].distance, (name, found)


def test_object_distance_is_symmetric_and_zero_for_an_object_itself(parts, tmp_path):
    from nfdmatch.search.object_distance import object_distances

    index = str(tmp_path / "parts.h5")
    build_index([str(parts)], index, jobs=1)
    with open_index(index) as idx:
        loops = idx.object_loops()
        d = object_distances(loops, loops, idx.samples, processes=1)
    assert np.allclose(d.distance, d.distance.T, atol=1e-9)
    assert np.allclose(np.diag(d.distance), 0.0, atol=1e-6)
    off = d.distance[~np.eye(4, dtype=bool)]
    assert off.min() > 0.1
    assert np.allclose(d.distance, (3 * d.curves + 3 * d.profile) / 3, atol=1e-9)  # closed: no boundary


def test_builds_are_incremental_for_meshes(parts, tmp_path):
    index = str(tmp_path / "parts.h5")
    build_index([str(parts)], index, jobs=1)
    with open_index(index) as idx:
        before = idx.objects()
        torus_profile = before.profile[idx.object_ids().index("parts/torus.ply")].copy()
    trimesh.creation.icosphere(subdivisions=3).export(str(parts / "capsule.stl"))
    os.remove(parts / "cone.obj")
    report = build_index([str(parts)], index, jobs=1, allow_shrink=True)
    assert dict((p, a) for a, p in report.changes)["parts/capsule.stl"] == "updated"
    assert (report.updated, report.removed, report.unchanged) == (1, 1, 3)
    with open_index(index) as idx:
        ids = idx.object_ids()
        assert ids == ["parts/bar.off", "parts/capsule.stl", "parts/torus.ply"]
        # the unchanged mesh's record was copied, the changed one re-cut
        np.testing.assert_array_equal(idx.objects().profile[ids.index("parts/torus.ply")], torus_profile)
        found = idx.search(trimesh.creation.icosphere(subdivisions=2), k=1)[0]
        assert found[0].id == "parts/capsule.stl"


def test_a_bad_mesh_is_named_and_skipped(parts, tmp_path):
    (parts / "broken.stl").write_text("solid nothing\nthis is not a mesh\n")
    index = str(tmp_path / "parts.h5")
    result = CliRunner().invoke(main, ["index", "build", str(parts), "--index", index, "-j", "1"])
    assert result.exit_code == 3, result.output
    assert "broken.stl" in result.stderr
    with open_index(index) as idx:
        assert len(idx.object_ids()) == 4


def test_sections_are_recorded_and_a_change_recuts(parts, tmp_path):
    index = str(tmp_path / "parts.h5")
    build_index([str(parts)], index, jobs=1, sections=5)
    with open_index(index) as idx:
        assert idx.object_rule().sections == 5 and idx.objects().level.max() == 4
    report = build_index([str(parts)], index, jobs=1)  # None keeps the recorded rule
    assert report.unchanged == 5
    report = build_index([str(parts)], index, jobs=1, sections=7)
    assert any("sections 5 -> 7" in n for n in report.notices) and report.updated == 5


def test_cli_query_of_meshes_ranks_objects(parts, tmp_path):
    index = str(tmp_path / "parts.h5")
    runner = CliRunner()
    assert runner.invoke(main, ["index", "build", str(parts), "--index", index, "-j", "1"]).exit_code == 0
    copy = tmp_path / "copy.ply"
    _copy_reposed(_shapes()["torus.ply"], 3).export(str(copy))
    result = runner.invoke(main, ["query", str(copy), "--index", index, "--top", "2", "--format", "csv"])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    assert list(rows[0]) == ["query", "rank", "match", "distance", "curves"]
    assert [r["rank"] for r in rows] == ["1", "2"]
    assert rows[0]["match"].endswith("torus.ply") and rows[0]["curves"].startswith("#")
    assert float(rows[0]["distance"]) < float(rows[1]["distance"])

    # --exclude-self drops the query mesh's own object; -o writes the rows; --max-distance cuts
    out = tmp_path / "answers.jsonl"
    result = runner.invoke(
        main, ["query", str(parts / "bar.off"), "--index", index, "--exclude-self", "--top", "3", "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    answers = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(answers) == 3 and all(not a["match"].endswith("bar.off") for a in answers)
    result = runner.invoke(
        main, ["query", str(parts / "bar.off"), "--index", index, "--max-distance", "1e-6", "--format", "json"]
    )
    assert [a["match"][-7:] for a in json.loads(result.stdout)] == ["bar.off"]
    # the pruned search (--top 1 of 4 objects) answers as computing every distance does
    args = ["query", str(copy), str(parts / "cone.obj"), "--index", index, "--top", "1", "--format", "csv"]
    pruned, full = runner.invoke(main, args), runner.invoke(main, args + ["--exhaustive"])
    assert pruned.exit_code == full.exit_code == 0 and pruned.stdout == full.stdout


def test_cli_query_errors_of_meshes(parts, tmp_path):
    index = str(tmp_path / "parts.h5")
    runner = CliRunner()
    runner.invoke(main, ["index", "build", str(parts), "--index", index, "-j", "1"])
    bad = tmp_path / "bad.stl"
    bad.write_text("solid x\nnonsense\n")
    result = runner.invoke(main, ["query", str(parts / "torus.ply"), str(bad), "--index", index, "--format", "csv"])
    assert result.exit_code == 3 and "bad.stl" in result.stderr
    assert {r["query"] for r in csv.DictReader(io.StringIO(result.stdout))} == {str(parts / "torus.ply")}
    # a curve query against an index of objects still ranks curves, with each match's object
    result = runner.invoke(main, ["query", str(parts / "ring.csv"), "--index", index, "--top", "3", "--format", "csv"])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    assert list(rows[0]) == ["query", "rank", "match", "distance", "object"]
    assert rows[0]["match"].endswith("ring.csv") and rows[0]["object"] == ""
    assert all(r["object"] == r["match"].rsplit("#", 1)[0] for r in rows[1:])
    # meshes and curves in one run: their rows differ
    result = runner.invoke(main, ["query", str(parts / "torus.ply"), str(parts / "ring.csv"), "--index", index])
    assert result.exit_code == 2 and "separate runs" in result.stderr
    result = runner.invoke(main, ["query", str(parts / "torus.ply"), "--index", index, "--rerank"])
    assert result.exit_code == 2
    # an index without objects
    curves = str(tmp_path / "curves.h5")
    build_index([str(parts / "ring.csv")], curves, jobs=1)
    result = runner.invoke(main, ["query", str(parts / "torus.ply"), "--index", curves])
    assert result.exit_code == 2 and "no mesh objects" in result.stderr
    # ... asked with a folder of meshes only: the error says what the folder holds
    meshes_only = tmp_path / "meshes"
    meshes_only.mkdir()
    (meshes_only / "torus.ply").write_bytes((parts / "torus.ply").read_bytes())
    result = runner.invoke(main, ["query", str(meshes_only), "--index", curves])
    assert result.exit_code == 2 and result.stdout == ""
    assert "no curve files found (it holds 1 mesh file: a mesh query needs an index built from meshes" in result.stderr


def test_frozen_v3_index_reads_forever(tmp_path):
    """Format 3's optional /objects: the frozen sample's object and its rule."""
    with open_index(FROZEN_V3) as idx:
        assert (idx.format_version, idx.samples, idx.harmonics, idx.n_curves, idx.n_files) == (3, 32, 4, 22, 2)
        assert idx.object_ids() == ["tests/data/index/part.off"]
        rule = idx.object_rule()
        assert (rule.sections, rule.min_vertices, rule.boundaries) == (7, 8, True)
        objects = idx.objects()
        assert list(objects.file) == [1]
        assert list(objects.axis[:1]) == [-1] and list(objects.axis[1:]) == [0] * 7 + [1] * 7 + [2] * 7
        found = idx.search_objects(os.path.join(HERE, "data", "index", "part.off"), k=1)[0]
        assert found[0].id == "tests/data/index/part.off" and found[0].distance < 1e-6


def test_a_format_2_index_is_read_and_upgraded(tmp_path):
    frozen = tmp_path / "v2.h5"
    shutil.copyfile(os.path.join(HERE, "data", "index", "v2-sample.h5"), frozen)
    with open_index(frozen) as idx:
        assert idx.format_version == 2 and idx.objects() is None and idx.object_rule() is None


def test_extract_axis_principal_cuts_by_the_index_rule(parts, tmp_path):
    index = str(tmp_path / "parts.h5")
    build_index([str(parts / "torus.ply")], index, jobs=1)
    result = CliRunner().invoke(
        main, ["extract", str(parts / "torus.ply"), "-o", str(tmp_path / "c"), "--axis", "principal", "--sections", "7",
               "--format", "csv"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    with open_index(index) as idx:
        assert len(rows) == idx.n_curves
        axes = idx.objects().axis
    assert [r["axis"] for r in rows] == [("pa", "pb", "pc")[a] for a in axes]
    assert {r["kind"] for r in rows} == {"section"}


def test_an_open_mesh_has_its_boundary_loops_as_contours(parts, tmp_path):
    bowl = trimesh.creation.icosphere(subdivisions=3)
    bowl.update_faces(bowl.triangles_center[:, 2] < 0.3)  # a sphere cut open: one rim
    bowl.remove_unreferenced_vertices()
    bowl.apply_scale([1.0, 1.3, 1.0])
    bowl.export(str(parts / "bowl.ply"))
    index = str(tmp_path / "parts.h5")
    build_index([str(parts)], index, jobs=1)
    with open_index(index) as idx:
        ids, axis = idx.ids(), idx.objects().axis
        rims = [ids[i] for i in np.flatnonzero(axis == 3)]
        assert len(rims) == 1 and rims[0].startswith("parts/bowl.ply#")
        found = idx.search(_copy_reposed(bowl, 7), k=2)[0]
        assert found[0].id == "parts/bowl.ply" and found[0].distance < 0.25 * found[1].distance


def test_verify_checks_objects_and_a_query_refuses_a_bad_group(parts, tmp_path):
    import h5py

    index = str(tmp_path / "parts.h5")
    build_index([str(parts)], index, jobs=1)
    runner = CliRunner()
    assert runner.invoke(main, ["index", "verify", "--index", index]).exit_code == 0
    with h5py.File(index, "r+") as f:
        f["objects/level"][3] = 99  # past the 7 sections
    result = runner.invoke(main, ["index", "verify", "--index", index])
    assert result.exit_code == 1 and "/objects" in result.output
    result = runner.invoke(main, ["query", str(parts / "torus.ply"), "--index", index])
    assert result.exit_code == 2 and "corrupted nfdmatch index: /objects" in result.stderr
    # curves are still answered: /objects is read only by what needs it
    result = runner.invoke(main, ["query", str(parts / "ring.csv"), "--index", index, "--top", "1"])
    assert result.exit_code == 0


def _synthetic_objects(seed: int, n_objects: int, families: int = 3, sections: int = 3):
    """ObjectLoops of ``n_objects`` made-up objects: noisy copies of a few families (random
    smooth closed curves per axis and level, 0 to 2 loops a level, random sizes)."""
    from nfdmatch.descriptors import descriptors_batch
    from nfdmatch.search.object_distance import ObjectLoops

    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, 48, endpoint=False)

    def curve(c):
        return sum(np.outer(np.cos(k * t), c[k, 0]) + np.outer(np.sin(k * t), c[k, 1]) for k in range(1, 4))

    bases = []
    for _ in range(families):
        slots = [(a, lv) for a in range(3) for lv in range(sections) for _ in range(int(rng.integers(0, 3)))]
        bases.append(
            [(a, lv, rng.normal(size=(4, 2, 3)) / np.arange(1, 5)[:, None, None], rng.normal()) for a, lv in slots]
        )
    loops, axis, level, measures, owner, profile = [], [], [], [], [], []
    for m in range(n_objects):
        base = bases[int(rng.integers(families))]
        for a, lv, c, size in base:
            loops.append(curve(c + 0.15 * rng.normal(size=c.shape)))
            axis.append(a)
            level.append(lv)
            measures.append((size + 0.1 * rng.normal(), 0.1, 0.5))
            owner.append(m)
        profile.append(rng.random(3 * sections * 4))
    batch = descriptors_batch(loops, samples=64, harmonics=8, scale="rms")
    return ObjectLoops(
        coefficients=batch.coefficients.astype(np.complex64), axis=np.array(axis, dtype=np.int8),
        level=np.array(level, dtype=np.int16), measures=np.array(measures), owner=np.array(owner),
        profile=np.array(profile), sections=sections,
    )  # fmt: skip


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(2, 70),
    k=st.one_of(st.none(), st.integers(1, 6)),
    max_distance=st.one_of(st.none(), st.floats(0.5, 4.0)),
)
def test_pruned_object_search_equals_brute_force(seed, n, k, max_distance):
    """The pruned search returns exactly what computing every object distance returns."""
    from nfdmatch.search.objects import nearest_objects

    if k is None and max_distance is None:
        k = 3
    objects = _synthetic_objects(seed, n)
    query = objects.subset([0])
    how = dict(k=k, max_distance=max_distance, skip=[0])
    pruned = nearest_objects(query, objects, 64, first_round=2, **how)  # small rounds: stops early
    full = nearest_objects(query, objects, 64, prune=False, **how)
    assert [f.position for f in pruned] == [f.position for f in full]
    np.testing.assert_allclose([f.distance for f in pruned], [f.distance for f in full], rtol=1e-9, atol=1e-12)
    assert [f.matched for f in pruned] == [f.matched for f in full]


def test_the_pruned_object_search_skips_most_objects():
    from nfdmatch.search import objects as module

    objects = _synthetic_objects(11, 300, families=6)
    computed = []
    exact = module._exact

    def counting(query, objs, chosen, samples, processes):
        computed.extend(chosen)
        return exact(query, objs, chosen, samples, processes)

    module._exact = counting
    try:
        found = module.nearest_objects(objects.subset([0]), objects, 64, k=3, skip=[0])
    finally:
        module._exact = exact
    assert len(found) == 3 and len(computed) < 150


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 40))
def test_coarse_and_loop_bounds_never_exceed_the_object_distance(seed, n):
    from nfdmatch.search.object_bounds import object_coarse_bounds, object_lower_bounds
    from nfdmatch.search.object_distance import object_distances

    objects = _synthetic_objects(seed, n)
    for q in range(min(n, 3)):
        query = objects.subset([q])
        exact = object_distances(query, objects, 64).distance[0]
        assert np.all(object_coarse_bounds(query, objects) <= exact + 1e-12)
        assert np.all(object_lower_bounds(query, objects)[0] <= exact + 1e-12)


@pytest.mark.parametrize("scale", [2.0**330, 2.0**-330, 2.0**500, 2.0**-500])
def test_an_object_far_from_unit_size_is_cut_as_the_unit_object(scale):
    """The frame's moments are the 4th and 5th powers of the coordinates: beyond ~1e61 they
    overflowed (a traceback, LinAlgError; numpy's warnings on stderr; or 'its area is zero'),
    below ~1e-61 they vanished (an arbitrary frame). The cut of a mesh scaled by a power of
    two (1e99, 1e-99, 1e150) is the unit mesh's cut, scaled, to the bit."""
    from nfdmatch.mesh.objects import cut_object

    unit = _shapes()["cone.obj"]
    scaled = trimesh.Trimesh(np.asarray(unit.vertices) * scale, unit.faces, process=False)
    ref, cut = cut_object(unit), cut_object(scaled)
    assert len(cut.loops) == len(ref.loops) and cut.notes == ref.notes
    np.testing.assert_array_equal(cut.axis, ref.axis)
    np.testing.assert_array_equal(cut.level, ref.level)
    np.testing.assert_array_equal(cut.measures, ref.measures)
    np.testing.assert_array_equal(cut.profile, ref.profile)
    np.testing.assert_array_equal(cut.frame, ref.frame * [[scale], [1], [1], [1]])
    np.testing.assert_array_equal(cut.levels, ref.levels * scale)
    assert cut.area == ref.area * scale**2
    for mine, theirs in zip(cut.loops, ref.loops):
        np.testing.assert_array_equal(mine, theirs * scale)


def test_cli_a_huge_mesh_is_indexed_and_queried_without_traceback(parts, tmp_path):
    unit = _shapes()["capsule.stl"]
    big = parts / "big.off"
    lines = [f"OFF\n{len(unit.vertices)} {len(unit.faces)} 0\n"]
    lines += [" ".join(repr(float(x) * 1e150) for x in p) + "\n" for p in unit.vertices]
    lines += ["3 " + " ".join(str(int(i)) for i in f) + "\n" for f in unit.faces]
    big.write_text("".join(lines))
    index = str(tmp_path / "parts.h5")
    runner = CliRunner()
    result = runner.invoke(main, ["index", "build", str(parts), "--index", index, "-j", "1"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(main, ["query", str(big), "--index", index, "--top", "2", "--format", "csv"])
    assert result.exit_code == 0 and result.stderr == "", result.output
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    assert {r["match"] for r in rows} == {"parts/big.off", "parts/capsule.stl"}


@pytest.mark.parametrize("scale, words", [(1e300, "too large"), (1e-300, "too small")])
def test_an_object_whose_area_float64_cannot_hold_is_a_clear_error(scale, words):
    from nfdmatch.errors import MeshError
    from nfdmatch.mesh.objects import cut_object

    unit = _shapes()["cone.obj"]
    scaled = trimesh.Trimesh(np.asarray(unit.vertices) * scale, unit.faces, process=False)
    with pytest.raises(MeshError, match=f"cannot be stored: coordinates {words}") as info:
        cut_object(scaled, name="cone.off")
    assert str(info.value).startswith("cone.off: its surface area")


def test_cli_a_partial_mesh_query_writes_no_output_file_and_lists_its_failures(parts, tmp_path):
    """As for curves (README, exit 3): `-o` is not written, and the JSON failure record lists
    the meshes that could not be read (it said `"failed": []` and `-o` was written)."""
    index = str(tmp_path / "parts.h5")
    runner = CliRunner()
    assert runner.invoke(main, ["index", "build", str(parts), "--index", index, "-j", "1"]).exit_code == 0
    bad = tmp_path / "bad.stl"
    bad.write_text("solid x\nnonsense\n")
    out = tmp_path / "answers.csv"
    result = runner.invoke(main, ["query", str(parts / "torus.ply"), str(bad), "--index", index, "-o", str(out)])
    assert result.exit_code == 3 and not out.exists(), result.output
    assert f"{out} not written" in result.stderr
    for fmt in ("jsonl", "json"):
        args = ["query", str(bad), str(parts / "torus.ply"), "--index", index, "--top", "1", "--format", fmt]
        result = runner.invoke(main, args)
        assert result.exit_code == 3, result.output
        if fmt == "jsonl":
            *rows, last = [json.loads(line) for line in result.stdout.splitlines()]
            assert [r["match"] for r in rows] == ["parts/torus.ply"]
            assert last["exit"] == 3 and [f["input"] for f in last["failed"]] == [str(bad)]
            assert last["failed"][0]["error"].startswith("not a triangle mesh")
    result = runner.invoke(main, ["query", str(bad), "--index", index, "--format", "jsonl"])
    assert result.exit_code == 2 and [f["input"] for f in json.loads(result.stdout)["failed"]] == [str(bad)]


def test_cli_a_query_mesh_named_twice_is_answered_once(parts, tmp_path):
    """As a curve query's files: a mesh given twice (however its path is spelled, or also
    found in a folder given) is one query (its rows were repeated, and it was cut twice)."""
    index = str(tmp_path / "parts.h5")
    runner = CliRunner()
    assert runner.invoke(main, ["index", "build", str(parts), "--index", index, "-j", "1"]).exit_code == 0
    torus = str(parts / "torus.ply")
    again = os.path.join(str(parts), ".", "torus.ply")
    args = ["query", torus, again, str(parts), "--index", index, "--top", "1", "--format", "csv"]
    result = runner.invoke(main, args)
    assert result.exit_code == 0, result.output
    queries = [r["query"] for r in csv.DictReader(io.StringIO(result.stdout))]
    assert sorted(queries) == sorted({torus, *(str(parts / n) for n in _shapes())})


def test_cli_a_fault_while_cutting_one_query_mesh_is_that_mesh_s_error(parts, tmp_path, monkeypatch):
    """A fault that is not nfdmatch's own while cutting a query mesh (a bug, a library's
    surprise) names that mesh, as a build does ("unexpected error"), and the other meshes
    are answered (exit 3); before, the whole query ended in a traceback."""
    import nfdmatch.mesh.objects as mesh_objects

    index = str(tmp_path / "parts.h5")
    runner = CliRunner()
    assert runner.invoke(main, ["index", "build", str(parts), "--index", index, "-j", "1"]).exit_code == 0
    original = mesh_objects.cut_object

    def faulty(mesh, *args, name=None, **kwargs):
        if name and name.endswith("torus.ply"):
            raise RuntimeError("a fault inside the cut")
        return original(mesh, *args, name=name, **kwargs)

    monkeypatch.setattr(mesh_objects, "cut_object", faulty)
    args = ["query", str(parts / "torus.ply"), str(parts / "cone.obj"), "--index", index, "--top", "1"]
    result = runner.invoke(main, [*args, "--format", "csv"])
    assert result.exit_code == 3, result.output
    assert "torus.ply: unexpected error: RuntimeError: a fault inside the cut" in result.stderr
    assert "Traceback" not in result.stderr
    assert [r["query"] for r in csv.DictReader(io.StringIO(result.stdout))] == [str(parts / "cone.obj")]
