"""`nfdmatch extract` and nfdmatch.extract: contours of triangle meshes (trimesh)."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from nfdmatch.errors import MeshError, ParameterError, ReadError, UnknownFormatError
from nfdmatch.extract import Contour, extract_contours, find_mesh_files, mesh_stem, section_levels, write_contours
from nfdmatch.formats import read_curves
from conftest import run_cli as run

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow

R_CYL, H_CYL, CYL_SIDES = 0.8, 8.0, 64  # a long cylinder along z
R_MAJOR, R_MINOR = 2.0, 0.5  # a torus around z


def rows_of(out: str) -> list[dict]:
    return list(csv.DictReader(io.StringIO(out)))


def signed_area(points: np.ndarray, a: int) -> float:
    """Twice the signed area of a loop projected along axis a (right-handed in-plane axes)."""
    x, y = points[:, (a + 1) % 3], points[:, (a + 2) % 3]
    return float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


# ---------------------------------------------------------------------------------- meshes


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    d = tmp_path_factory.mktemp("meshes")
    cyl = trimesh.creation.cylinder(radius=R_CYL, height=H_CYL, sections=CYL_SIDES)
    cyl.export(d / "cylinder.stl")
    cyl.export(d / "cylinder.ply")
    disk = trimesh.creation.cylinder(radius=2.0, height=0.5, sections=64)  # wider than high
    disk.export(d / "disk.stl")
    torus = trimesh.creation.torus(major_radius=R_MAJOR, minor_radius=R_MINOR, major_sections=96, minor_sections=48)
    torus.export(d / "torus.ply")
    tube = cyl.copy()  # caps removed
    tube.update_faces(np.abs(tube.face_normals[:, 2]) < 0.5)
    tube.remove_unreferenced_vertices()
    tube.export(d / "tube.stl")
    # two boxes sharing one edge (the z axis through (0.5, 0.5)): non-manifold
    a = trimesh.creation.box(extents=[1, 1, 1])
    b = a.copy()
    b.apply_translation([1, 1, 0])
    trimesh.util.concatenate([a, b]).export(d / "two_boxes.stl")
    # two triangles touching at one vertex: boundary with a branching vertex
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    trimesh.Trimesh(v, [[0, 1, 2], [0, 3, 4]], process=False).export(d / "bowtie.ply")
    # three fins sharing the edge (0,0,0)-(0,0,1): a Y-shaped section, theta-shaped boundary
    v = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0], [1, 0, 1], [-1, 1, 0], [-1, 1, 1], [-1, -1, 0], [-1, -1, 1]], float)
    f = [[0, 2, 3], [0, 3, 1], [0, 4, 5], [0, 5, 1], [0, 6, 7], [0, 7, 1]]
    trimesh.Trimesh(v, f, process=False).export(d / "fins.ply")
    # a scene of two cylinders placed apart by scene-graph transforms
    scene = trimesh.Scene()
    small = trimesh.creation.cylinder(radius=0.5, height=4.0, sections=32)
    scene.add_geometry(small, node_name="left", transform=trimesh.transformations.translation_matrix([-3, 0, 0]))
    scene.add_geometry(small, node_name="right", transform=trimesh.transformations.translation_matrix([3, 0, 0]))
    scene.export(d / "pair.glb")
    return d


@pytest.fixture
def bad_files(tmp_path):
    """name -> (path, exception class, words the message must contain)."""
    files = {
        "text": (tmp_path / "notes.stl", "this is not a mesh\njust some text\n", MeshError, "not a"),
        "text_ply": (tmp_path / "notes.ply", "hello\n", MeshError, "Not a ply"),
        "empty": (tmp_path / "empty.stl", "", MeshError, "empty"),
        "curve_csv": (tmp_path / "curve.csv", "x,y,z\n0,0,0\n1,0,0\n0,1,0\n", UnknownFormatError, "curve file"),
        "unknown_ext": (tmp_path / "model.foo", "solid x\n", UnknownFormatError, "'.foo'"),
        "no_faces": (
            tmp_path / "points.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n",
            MeshError,
            "no faces",
        ),
        "obj_curve": (tmp_path / "loop.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3 1\n", MeshError, "curve file"),
    }
    out = {}
    for name, (path, text, exc, words) in files.items():
        path.write_text(text)
        out[name] = (path, exc, words)
    out["missing"] = (tmp_path / "missing.stl", ReadError, "no such file")
    return out


# ---------------------------------------------------------------------------------- sections


@pytest.mark.parametrize("name", ["cylinder.stl", "cylinder.ply"])
def test_cylinder_sections_along_the_auto_axis_are_circles(meshes, name):
    n = 5
    result = extract_contours(meshes / name, sections=n)
    assert result.axis == "z"
    expected_levels = -H_CYL / 2 + (np.arange(n) + 0.5) * H_CYL / n
    np.testing.assert_allclose(result.levels, expected_levels, rtol=0, atol=1e-12)
    assert [c.level_index for c in result.contours] == list(range(n))
    assert result.notes == []
    chord = R_CYL * (1 - np.cos(np.pi / CYL_SIDES))  # deepest point of a side facet
    for c, level in zip(result.contours, expected_levels):
        assert (c.kind, c.axis, c.loop, c.mesh) == ("section", "z", 0, str(meshes / name))
        assert c.level == pytest.approx(level, abs=1e-12)
        assert c.points.shape[1] == 3 and c.points.dtype == np.float64 and c.n_vertices >= CYL_SIDES
        assert np.all(c.points[:, 2] == c.level)  # exactly in the plane
        radius = np.hypot(c.points[:, 0], c.points[:, 1])
        assert abs(radius.mean() - R_CYL) < 0.01 * R_CYL
        assert np.abs(radius - R_CYL).max() <= chord + 1e-6
        assert signed_area(c.points, 2) > 0  # counter-clockwise seen from +z
        assert not np.array_equal(c.points[0], c.points[-1])  # closing edge implicit


def test_explicit_axis_overrides_the_longest_extent(meshes):
    auto = extract_contours(meshes / "disk.stl", sections=3)
    assert auto.axis == "x"  # x and y tie at 4 > 0.5: the first
    assert all(c.axis == "x" for c in auto.contours)
    result = extract_contours(meshes / "disk.stl", sections=4, axis="z")
    assert result.axis == "z" and len(result.contours) == 4
    np.testing.assert_allclose([c.level for c in result.contours], -0.25 + (np.arange(4) + 0.5) * 0.5 / 4, atol=1e-12)
    for c in result.contours:
        radius = np.hypot(c.points[:, 0], c.points[:, 1])
        assert abs(radius.mean() - 2.0) < 0.02 and np.abs(radius - 2.0).max() < 2.0 * (1 - np.cos(np.pi / 64)) + 1e-6


def test_torus_across_its_axis_gives_two_concentric_circles(meshes):
    n = 5
    result = extract_contours(meshes / "torus.ply", sections=n, axis="z")
    levels = -R_MINOR + (np.arange(n) + 0.5) * 2 * R_MINOR / n  # -0.4 ... 0.4, 0 in the middle
    np.testing.assert_allclose(result.levels, levels, atol=1e-12)
    assert len(result.contours) == 2 * n and result.notes == []
    for i, z in enumerate(levels):
        outer, inner = [c for c in result.contours if c.level_index == i]
        assert (outer.loop, inner.loop) == (0, 1)  # longest first
        half = np.sqrt(R_MINOR**2 - z**2)
        for loop, expected in ((outer, R_MAJOR + half), (inner, R_MAJOR - half)):
            radius = np.hypot(loop.points[:, 0], loop.points[:, 1])
            assert abs(radius.mean() - expected) < 0.01 * expected, (i, expected, radius.mean())
            assert np.abs(radius - expected).max() < 0.02 * expected
            assert signed_area(loop.points, 2) > 0
    middle = [c for c in result.contours if c.level_index == n // 2]
    assert [c.level for c in middle] == [0.0, 0.0]
    assert [round(np.hypot(c.points[:, 0], c.points[:, 1]).mean(), 2) for c in middle] == [2.5, 1.5]


def test_torus_along_its_axis_gives_two_circles_of_the_tube_radius(meshes):
    result = extract_contours(meshes / "torus.ply", sections=3, axis="x")
    outer = R_MAJOR + R_MINOR
    np.testing.assert_allclose(result.levels, [-outer * 2 / 3, 0.0, outer * 2 / 3], atol=1e-12)
    by_level = {i: [c for c in result.contours if c.level_index == i] for i in range(3)}
    assert [len(by_level[i]) for i in range(3)] == [1, 2, 1]  # |x| in (R - r, R + r): one loop
    sides = []
    for c in by_level[1]:
        side = np.sign(c.points[:, 1].mean())
        assert np.all(np.sign(c.points[:, 1]) == side)
        sides.append(side)
        radius = np.hypot(c.points[:, 1] - side * R_MAJOR, c.points[:, 2])  # about (0, +-R, 0)
        assert abs(radius.mean() - R_MINOR) < 0.01 * R_MINOR
        assert np.abs(radius - R_MINOR).max() < 0.01 * R_MINOR
        assert np.all(c.points[:, 0] == 0.0)
    assert sorted(sides) == [-1, 1]


def test_scene_geometries_are_placed_and_concatenated(meshes):
    result = extract_contours(meshes / "pair.glb", sections=2, axis="z")
    assert len(result.contours) == 4
    centres = sorted(round(float(c.points[:, 0].mean()), 2) for c in result.contours)
    assert centres == [-3.0, -3.0, 3.0, 3.0]


def test_levels_rule():
    axis, levels = section_levels([[0, -1, 10], [4, 1, 12]], 4)
    assert axis == "x" and levels.tolist() == [0.5, 1.5, 2.5, 3.5]
    axis, levels = section_levels([[0, -1, 10], [4, 1, 12]], 1, "z")
    assert axis == "z" and levels.tolist() == [11.0]
    assert section_levels([[0, 0, 0], [1, 1, 1]], 0)[1].shape == (0,)


# ---------------------------------------------------------------------------------- boundaries and open pieces


def test_boundaries_of_an_open_tube_are_its_two_rims(meshes):
    result = extract_contours(meshes / "tube.stl", sections=0, boundaries=True)
    assert result.axis is None and len(result.contours) == 2 and result.notes == []
    rims = sorted(result.contours, key=lambda c: c.points[:, 2].mean())
    for c, z in zip(rims, (-H_CYL / 2, H_CYL / 2)):
        assert (c.kind, c.axis, c.level, c.level_index) == ("boundary", None, None, None)
        assert c.n_vertices == CYL_SIDES
        assert np.allclose(c.points[:, 2], z)
        assert np.allclose(np.hypot(c.points[:, 0], c.points[:, 1]), R_CYL)
    assert sorted(c.loop for c in result.contours) == [0, 1]


def test_a_closed_mesh_has_no_boundary_loops(meshes):
    result = extract_contours(meshes / "cylinder.stl", sections=0, boundaries=True)
    assert result.contours == []
    assert any("no boundary loops (the mesh is closed)" in n for n in result.notes)
    assert any("nothing extracted" in n for n in result.notes)
    both = extract_contours(meshes / "cylinder.stl", sections=2, boundaries=True)
    assert [c.kind for c in both.contours] == ["section", "section"]


def test_open_section_pieces_are_skipped_with_a_note(meshes):
    # planes containing the tube's axis cut it into two straight, open pieces each
    result = extract_contours(meshes / "tube.stl", sections=3, axis="x", boundaries=True)
    assert [c.kind for c in result.contours] == ["boundary", "boundary"]
    notes = [n for n in result.notes if "open piece" in n]
    assert len(notes) == 3
    assert notes[1] == f"{meshes / 'tube.stl'}: section x01 at 0: 2 open pieces skipped (not closed)"
    # across the axis the tube's sections are closed circles
    across = extract_contours(meshes / "tube.stl", sections=3)
    assert len(across.contours) == 3 and across.notes == []


def test_branching_points_are_split_into_simple_loops(meshes):
    result = extract_contours(meshes / "two_boxes.stl", sections=1, axis="z")
    assert len(result.contours) == 2
    assert any("1 branching point" in n for n in result.notes)
    for c, centre in zip(sorted(result.contours, key=lambda c: c.points[:, 0].mean()), ([0, 0], [1, 1])):
        assert np.allclose(c.points[:, :2].min(axis=0), np.subtract(centre, 0.5))
        assert np.allclose(c.points[:, :2].max(axis=0), np.add(centre, 0.5))

    bowtie = extract_contours(meshes / "bowtie.ply", sections=0, boundaries=True)
    assert len(bowtie.contours) == 2 and all(c.n_vertices == 3 for c in bowtie.contours)
    assert any("branching point" in n for n in bowtie.notes)

    fins = extract_contours(meshes / "fins.ply", sections=2, axis="z", boundaries=True)  # no crash
    assert [c.kind for c in fins.contours] == ["boundary"]
    assert sum("open piece" in n for n in fins.notes) == 3


# ---------------------------------------------------------------------------------- names and writing


def test_names_are_readable_sortable_and_safe():
    pts = np.eye(3)
    c = Contour(
        points=pts,
        mesh="dir/torus.stl",
        kind="section",
        axis="z",
        level=-0.125,
        level_index=3,
        loop=0,
        level_count=10,
        loop_count=2,
    )
    assert c.name == "torus_section-z03_at-0.125_loop0"
    c = Contour(
        points=pts,
        mesh="scan #2 v1.ply",
        kind="section",
        axis="x",
        level=-0.0,
        level_index=7,
        loop=11,
        level_count=120,
        loop_count=12,
    )
    assert c.name == "scan_2_v1_section-x007_at0_loop11"
    c = Contour(points=pts, mesh="box.obj", kind="boundary", loop=0, loop_count=1)
    assert c.name == "box_boundary_loop0"
    assert mesh_stem(".hidden.stl") == "mesh.hidden"


def test_write_read_back_and_stems_unique_across_meshes(meshes, tmp_path):
    contours = (
        extract_contours(meshes / "cylinder.stl", sections=2).contours
        + extract_contours(meshes / "cylinder.ply", sections=2).contours
    )
    written = write_contours(contours, tmp_path / "new" / "folder")
    assert [os.path.basename(p) for p in written] == [
        "cylinder-stl_section-z00_at-2_loop0.obj",
        "cylinder-stl_section-z01_at2_loop0.obj",
        "cylinder-ply_section-z00_at-2_loop0.obj",
        "cylinder-ply_section-z01_at2_loop0.obj",
    ]
    for path, c in zip(written, contours):
        (curve,) = read_curves(path)
        assert curve.id == path and np.array_equal(curve.points, c.points)
    for fmt, ext in (("csv", ".csv"), ("vtp", ".vtp")):
        (path,) = write_contours(contours[:1], tmp_path / fmt, format=fmt)
        assert path.endswith(ext) and np.array_equal(read_curves(path)[0].points, contours[0].points)


def test_find_mesh_files_walks_folders_and_skips_the_output(meshes, tmp_path):
    (tmp_path / "m").mkdir()
    for name in ("b.stl", "a.PLY", "notes.txt", ".hidden.stl"):
        (tmp_path / "m" / name).write_text("x")
    (tmp_path / "m" / "out").mkdir()
    (tmp_path / "m" / "out" / "old_section.obj").write_text("x")
    found = find_mesh_files([tmp_path / "m", tmp_path / "given.xyz"], exclude=[tmp_path / "m" / "out"])
    assert [os.path.relpath(p, tmp_path) for p in found] == [
        os.path.join("m", "a.PLY"),
        os.path.join("m", "b.stl"),
        "given.xyz",
    ]


# ---------------------------------------------------------------------------------- errors


def test_bad_inputs_raise_clean_errors_naming_the_file(bad_files):
    for name, (path, exc, words) in bad_files.items():
        with pytest.raises(exc) as info:
            extract_contours(path, sections=2)
        assert str(path) in str(info.value) and words in str(info.value), name


def test_parameters_are_checked(meshes):
    with pytest.raises(ParameterError, match="nothing to extract"):
        extract_contours(meshes / "cylinder.stl", sections=0)
    with pytest.raises(ParameterError, match="axis"):
        extract_contours(meshes / "cylinder.stl", axis="w")
    with pytest.raises(ParameterError, match="sections"):
        extract_contours(meshes / "cylinder.stl", sections=-1)


def test_cli_bad_inputs_exit_2_without_traceback(bad_files, tmp_path):
    for name, (path, _, words) in bad_files.items():
        code, out, err = run("extract", path, "-o", tmp_path / "out")
        assert code == 2, name
        assert out == "" and "Traceback" not in err, name
        assert err.startswith(f"Error: {path}: ") and words in err, (name, err)
    assert not (tmp_path / "out").exists()


def test_cli_one_bad_mesh_among_others_is_exit_3(meshes, bad_files, tmp_path):
    folder = tmp_path / "mixed"
    folder.mkdir()
    for name in ("cylinder.stl", "torus.ply"):
        (folder / name).write_bytes((meshes / name).read_bytes())
    bad = folder / "broken.stl"
    bad.write_text("solid broken\nfacet normal 0 0 1\n this is not right\n")
    code, out, err = run("extract", folder, "-o", tmp_path / "out", "--sections", "3", "--axis", "z")
    assert code == 3
    assert f"Error: {bad}: not a triangle mesh" in err and "1 of 3 meshes could not be read" in err
    assert "Traceback" not in err
    rows = rows_of(out)
    assert {r["mesh"] for r in rows} == {str(folder / "cylinder.stl"), str(folder / "torus.ply")}
    assert len(rows) == 3 + 6 and all(os.path.isfile(r["file"]) for r in rows)

    # files given one by one: a missing one does not stop the others either
    code, out, err = run("extract", meshes / "cylinder.stl", tmp_path / "nope.stl", "-o", tmp_path / "out2")
    assert code == 3 and f"Error: {tmp_path / 'nope.stl'}: no such file" in err
    assert len(rows_of(out)) == 10


def test_cli_usage_errors(meshes, tmp_path):
    code, out, err = run("extract", meshes / "cylinder.stl", "-o", tmp_path / "o", "--sections", "0")
    assert code == 2 and out == "" and "--boundaries" in err
    code, _, err = run("extract", meshes / "cylinder.stl", "-o", tmp_path / "o", "--sections", "-2")
    assert code == 2 and "--sections" in err
    code, _, err = run("extract", meshes / "cylinder.stl")
    assert code == 2 and "--output" in err
    code, _, err = run("extract", meshes / "cylinder.stl", "-o", tmp_path / "o", "--axis", "w")
    assert code == 2
    # a closed mesh asked only for boundaries gives nothing: exit 1 with notes
    code, out, err = run("extract", meshes / "cylinder.stl", "-o", tmp_path / "o", "--sections", "0", "--boundaries")
    assert code == 2 and out == ""
    assert "Note:" in err and "(the mesh is closed)" in err and "Error: no closed contour" in err


# ---------------------------------------------------------------------------------- CLI end to end


def test_cli_extract_then_index_and_query(meshes, tmp_path):
    out_dir = tmp_path / "contours"
    code, out, err = run(
        "extract",
        meshes / "torus.ply",
        meshes / "tube.stl",
        "-o",
        out_dir,
        "--sections",
        "5",
        "--axis",
        "x",
        "--boundaries",
        "--format",
        "json",
    )
    assert code == 0, err
    rows = json.loads(out)
    assert list(rows[0]) == ["file", "mesh", "kind", "axis", "level", "loop", "vertices"]
    torus_rows = [r for r in rows if r["mesh"] == str(meshes / "torus.ply")]
    # levels -2, -1, 0, 1, 2: |x| > R - r gives one loop, |x| < R - r two loops
    assert [(r["level"], r["loop"]) for r in torus_rows] == [
        (-2.0, 0),
        (-1.0, 0),
        (-1.0, 1),
        (0.0, 0),
        (0.0, 1),
        (1.0, 0),
        (1.0, 1),
        (2.0, 0),
    ]
    assert os.path.basename(torus_rows[0]["file"]) == "torus_section-x00_at-2_loop0.obj"
    tube_rows = [r for r in rows if r["mesh"] == str(meshes / "tube.stl")]
    assert [r["kind"] for r in tube_rows] == ["boundary", "boundary"]
    assert [r["axis"] for r in tube_rows] == [None, None]
    assert err.count("open pieces skipped") == 5 and "Note: " in err
    # the written files, and the manifest of what extract wrote (docs/extract.md)
    assert sorted(os.listdir(out_dir)) == sorted(
        [os.path.basename(r["file"]) for r in rows] + [".nfdmatch-extract.json"]
    )
    for r in rows:
        (curve,) = read_curves(r["file"])
        assert curve.n_vertices == r["vertices"]

    index = tmp_path / "i.h5"
    code, out, err = run("index", "build", out_dir, "--index", index, "--jobs", "1", "--format", "json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["curves"] == len(rows) and summary["failed"] == 0

    query = torus_rows[0]["file"]  # the spiric section at x = -2
    code, out, err = run("query", query, "--index", index, "--top", str(len(rows)), "--format", "csv")
    assert code == 0, err
    matches = rows_of(out)
    assert float(matches[0]["distance"]) < 1e-6
    # ids are relative to the index's folder
    mine = [m for m in matches if os.path.realpath(tmp_path / m["match"]) == os.path.realpath(query)]
    assert len(mine) == 1 and float(mine[0]["distance"]) < 1e-6
    # the mirror-image section at x = +2 is the same shape; a tube rim (a circle) is not
    far = [m for m in matches if "tube_boundary" in m["match"]]
    assert far and min(float(m["distance"]) for m in far) > 0.05


def test_cli_output_formats_and_table(meshes, tmp_path):
    code, out, err = run(
        "extract",
        meshes / "tube.stl",
        "-o",
        tmp_path / "v",
        "--sections",
        "0",
        "--boundaries",
        "--output-format",
        "vtp",
        "--format",
        "csv",
    )
    assert code == 0 and err.startswith("2 contours from 1 of 1 meshes written to")
    files = [r["file"] for r in rows_of(out)]
    assert [os.path.basename(f) for f in files] == ["tube_boundary_loop0.vtp", "tube_boundary_loop1.vtp"]
    assert all(len(read_curves(f)) == 1 for f in files)
    code, out, _ = run("extract", meshes / "cylinder.stl", "-o", tmp_path / "t", "--sections", "2", "--format", "table")
    assert code == 0 and "cylinder_section-z01_at2_loop0.obj" in out and "vertices" in out


def test_cli_import_does_not_import_trimesh():
    code = "import sys, nfdmatch.cli; print('trimesh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_a_plane_through_vertices_gives_those_vertices_once(tmp_path):
    """A section exactly at a ring of vertices: each vertex once, exactly (two edges meet at
    every such vertex; their crossing points once differed by 1e-18 and both stayed)."""
    around = 16
    theta = np.arange(around) * 2 * np.pi / around
    rings = np.stack([np.stack([np.cos(theta), np.sin(theta), np.full(around, z)], -1) for z in (0.0, 1.0, 2.0)])
    idx = np.arange(3 * around).reshape(3, around)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    trimesh.Trimesh(rings.reshape(-1, 3), faces, process=False).export(tmp_path / "tube.ply")
    (loop,) = extract_contours(tmp_path / "tube.ply", sections=1, axis="z").contours
    assert loop.level == 1.0 and loop.n_vertices == around
    stored = rings[1].astype(np.float32).astype(np.float64)  # PLY keeps float32
    assert {tuple(p) for p in loop.points} == {tuple(p) for p in stored}


@pytest.mark.parametrize("fmt", ["obj", "csv", "vtp"])
def test_rerun_keeps_unchanged_files_with_fresh_mtimes(meshes, tmp_path, fmt):
    """Make-style pipelines: a second extraction rewrites nothing that did not change, but
    leaves every output newer than its inputs (fresh mtimes: Make settles)."""
    out = tmp_path / "out"
    code, _, err = run("extract", meshes / "cylinder.stl", "-o", out, "--sections", 3, "--output-format", fmt)
    assert code == 0, err
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    for p in out.iterdir():
        os.utime(p, ns=(1, 1))  # as if written long ago
    inodes = {p.name: p.stat().st_ino for p in out.iterdir()}
    code, _, err = run("extract", meshes / "cylinder.stl", "-o", out, "--sections", 3, "--output-format", fmt)
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == sorted(before)  # no temporary files left
    assert {p.name: p.stat().st_ino for p in out.iterdir()} == inodes  # the same files, not rewritten
    assert all(p.stat().st_mtime_ns > 1 for p in out.iterdir())
    # the same mesh moved sideways: same names (same levels along z), new content, rewritten
    moved = tmp_path / "moved"
    moved.mkdir()
    trimesh.creation.cylinder(radius=R_CYL, height=H_CYL, sections=CYL_SIDES).apply_translation([5.0, 0.0, 0.0]).export(
        moved / "cylinder.stl"
    )
    code, _, err = run("extract", moved / "cylinder.stl", "-o", out, "--sections", 3, "--output-format", fmt)
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == sorted(before)
    assert all(p.stat().st_mtime_ns != 1 for p in out.iterdir())


# --------------------------------------------------------------------------- --list FILE (issue 25, item 8)


def test_a_second_output_is_a_usage_error_not_a_folder(meshes, tmp_path):
    code, out, err = run("extract", meshes / "cylinder.stl", "-o", tmp_path / "c", "-o", tmp_path / "c.list")
    assert code == 2 and out == "" and "--list" in err
    assert os.listdir(tmp_path) == []


def test_list_file_is_written_whole_as_its_extension_says(meshes, tmp_path):
    out = tmp_path / "contours"
    listing = tmp_path / "contours.list"
    code, stdout, err = run("extract", meshes / "cylinder.stl", "-o", out, "--sections", 3, "--list", listing)
    assert code == 0 and stdout == "", err
    paths = listing.read_text().splitlines()
    assert len(paths) == 3 and all(os.path.isfile(p) for p in paths)
    assert sorted(os.path.basename(p) for p in paths) == sorted(n for n in os.listdir(out) if not n.startswith("."))
    os.utime(listing, ns=(1, 1))  # an identical rerun: the list is newer than its mesh (Make)
    assert run("extract", meshes / "cylinder.stl", "-o", out, "--sections", 3, "--list", listing)[0] == 0
    assert listing.stat().st_mtime_ns > os.stat(meshes / "cylinder.stl").st_mtime_ns
    rows_file = tmp_path / "contours.csv"
    code, stdout, _ = run("extract", meshes / "cylinder.stl", "-o", out, "--sections", 3, "--list", rows_file)
    assert code == 0 and stdout == ""
    rows = list(csv.DictReader(io.StringIO(rows_file.read_text())))
    assert [r["file"] for r in rows] == paths and rows[0]["kind"] == "section"
    assert [n for n in os.listdir(tmp_path) if n.startswith(".")] == []


def test_list_file_is_checked_before_any_work_as_an_output_is(meshes, tmp_path):
    out = tmp_path / "contours"
    code, stdout, err = run("extract", meshes / "cylinder.stl", "-o", out, "--list", tmp_path / "no" / "c.list")
    assert code == 2 and stdout == "" and "the folder does not exist" in err
    assert not out.exists()  # nothing extracted
    code, stdout, _ = run("extract", meshes / "cylinder.stl", "-o", out, "--sections", 3, "--list", "-")
    assert code == 0 and stdout.startswith("file,mesh,") and len(stdout.splitlines()) == 4  # '-': stdout, as -o


def test_list_file_is_not_written_when_a_mesh_failed(meshes, tmp_path):
    bad = tmp_path / "bad.stl"
    bad.write_bytes(b"solid nothing\nendsolid\n")
    listing = tmp_path / "contours.list"
    code, _, err = run(
        "extract", meshes / "cylinder.stl", bad, "-o", tmp_path / "c", "--sections", 3, "--list", listing
    )
    assert code == 3 and "bad.stl" in err and not listing.exists()


def _write_off(path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """An OFF file with every coordinate in full (float64: PLY and STL would keep float32)."""
    lines = [f"OFF\n{len(vertices)} {len(faces)} 0\n"]
    lines += [" ".join(repr(float(x)) for x in p) + "\n" for p in vertices]
    lines += ["3 " + " ".join(str(int(i)) for i in f) + "\n" for f in faces]
    path.write_text("".join(lines))


@pytest.mark.parametrize("scale, shift", [(1e150, 0.0), (1e-9, 0.0), (1.0, 1e12)])
def test_a_mesh_far_from_unit_size_loads_and_cuts_as_the_unit_mesh(tmp_path, scale, shift):
    """trimesh merges vertices at an absolute 1e-8 through int64: a mesh with coordinates
    beyond ~1e11 collapsed into a few vertices (its sections open pieces), a mesh smaller
    than ~1e-8 into one ("every face is degenerate"). Coordinates are kept as read."""
    from nfdmatch.mesh import load_mesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    unshared = sphere.vertices[sphere.faces].reshape(-1, 3) * scale + shift  # as STL: merging needed
    path = tmp_path / "sphere.off"
    _write_off(path, unshared, np.arange(len(unshared)).reshape(-1, 3))
    mesh = load_mesh(path)
    assert (len(mesh.vertices), len(mesh.faces)) == (len(sphere.vertices), len(sphere.faces))
    assert mesh.is_watertight
    assert {tuple(p) for p in np.asarray(mesh.vertices)} == {tuple(p) for p in unshared}
    result = extract_contours(path, sections=5)
    assert len(result.contours) == 5 and result.notes == []


def test_a_mesh_near_1e210_gives_the_unit_mesh_contours_scaled_without_warnings(tmp_path):
    """Loop perimeters (ordering) and signed areas (orientation) are squares of the
    coordinates: beyond ~1e154 they overflowed, with numpy's RuntimeWarnings on stderr,
    every perimeter infinite (loops ordered by position, not size) and the orientation
    left as it came (the signed area NaN)."""
    import warnings

    small = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    big = trimesh.creation.icosphere(subdivisions=2, radius=2.0)
    small.apply_translation([-3, 0, 0])
    big.apply_translation([3, 0, 0])
    big.invert()  # its faces wound inwards: its sections come clockwise
    both = trimesh.util.concatenate([small, big])
    scale = 2.0**700
    for name, s in (("unit.off", 1.0), ("huge.off", scale)):
        _write_off(tmp_path / name, np.asarray(both.vertices) * s, both.faces)
    ref = extract_contours(tmp_path / "unit.off", sections=1, axis="z")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = extract_contours(tmp_path / "huge.off", sections=1, axis="z")
    assert len(ref.contours) == len(result.contours) == 2 and result.notes == ref.notes == []
    assert ref.contours[0].points[:, 0].min() > 0  # the big sphere's loop first
    for mine, theirs in zip(result.contours, ref.contours):
        np.testing.assert_array_equal(mine.points, theirs.points * scale)
        assert signed_area(theirs.points, 2) > 0


@pytest.mark.parametrize("fmt", ["json", "jsonl"])
def test_cli_an_extract_that_writes_nothing_says_so_in_json(bad_files, tmp_path, fmt):
    """README: with --format json or jsonl a command that cannot answer writes one JSON
    object on stdout (a cron log of JSON lines gets a line from every run); extract's exit 2
    wrote nothing on stdout."""
    path = bad_files["text"][0]
    code, out, err = run("extract", path, "-o", tmp_path / "out", "--format", fmt)
    assert code == 2 and f"Error: {path}: " in err
    record = json.loads(out)
    assert record["exit"] == 2 and [f["input"] for f in record["failed"]] == [str(path)]
    triangle = tmp_path / "triangle.off"
    triangle.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")  # its sections are open pieces
    code, out, err = run("extract", triangle, "-o", tmp_path / "out", "--format", fmt, "-q")
    assert code == 2 and err == "Error: no closed contour in the mesh; nothing written\n"
    assert json.loads(out) == {"error": "no closed contour in the mesh; nothing written", "exit": 2, "failed": []}
    assert not (tmp_path / "out").exists()


def test_a_gltf_that_is_not_json_or_misses_its_buffer_says_which(tmp_path):
    """trimesh's resolver raised a bare FileNotFoundError: the messages were 'not a readable
    triangle mesh: model.gltf' (a file that is not JSON) and '...: data.bin' (a buffer file
    missing)."""
    garbage = tmp_path / "garbage.gltf"
    garbage.write_text("{not json")
    with pytest.raises(MeshError, match=r"garbage.gltf: not a readable triangle mesh: not JSON \(Expecting"):
        extract_contours(garbage, sections=2)
    gltf = {
        "asset": {"version": "2.0"},
        "buffers": [{"uri": "data.bin", "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    }
    missing = tmp_path / "part.gltf"
    missing.write_text(json.dumps(gltf))
    with pytest.raises(
        MeshError, match="part.gltf: not a readable triangle mesh: a file it refers to is missing: data.bin"
    ):
        extract_contours(missing, sections=2)
