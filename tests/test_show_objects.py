"""``show`` of a mesh query: the query's contours beside its best objects' matched contours
(docs/objects.md), from the library (``show_objects``, ``render_objects``) and the CLI."""

from __future__ import annotations

import csv
import io
import os

import numpy as np
import pytest
from click.testing import CliRunner

from nfdmatch.cli import main
from nfdmatch.index import build_index, open_index

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("matplotlib")


def _shapes() -> dict:
    bar = trimesh.creation.box((1.0, 1.4, 4.0))
    for _ in range(3):
        bar = bar.subdivide()
    return {
        "torus.ply": trimesh.creation.torus(1.0, 0.3, major_sections=24, minor_sections=12),
        "capsule.stl": trimesh.creation.capsule(height=2.0, radius=0.5, count=[16, 16]),
        "bar.off": bar,
    }


@pytest.fixture
def indexed(tmp_path):
    """An index of three meshes and a re-posed, re-scaled, re-triangulated copy of the torus
    (outside the indexed folder) to query it with."""
    folder = tmp_path / "parts"
    folder.mkdir()
    for name, mesh in _shapes().items():
        mesh.export(str(folder / name))
    index = str(tmp_path / "parts.h5")
    build_index([str(folder)], index, jobs=1)
    copy = _shapes()["torus.ply"].copy()
    rng = np.random.default_rng(3)
    copy.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    copy.apply_translation([4.0, -2.0, 7.0])
    copy.apply_scale(2.5)
    query = str(tmp_path / "torus-copy.stl")
    copy.subdivide().export(query)
    return folder, index, query


def _extent(loops) -> np.ndarray:
    every = np.vstack(loops)
    return every.max(axis=0) - every.min(axis=0)


def test_show_objects_puts_query_and_answers_in_their_principal_frames(indexed):
    from nfdmatch.show_objects import show_objects

    folder, index, query = indexed
    with open_index(index) as idx:
        (shown,), notes = show_objects(idx, query, k=2)
        n_rows = {r.path: r.curve_count for r in idx.files()}
    assert notes == []
    assert shown.id == query and [s.id for s in shown.shown][0] == "parts/torus.ply"
    best = shown.shown[0]
    assert best.source == "file" and best.rank == 1
    assert len(best.loops) == len(best.match.curves) and 0 < len(best.loops) <= n_rows["parts/torus.ply"]
    # the copy is 2.5 times larger and turned: in the principal frames, with the surface's
    # square root of area as the unit, query and original are drawn the same size and way up
    query_extent, match_extent = _extent(shown.loops), _extent(best.loops)
    np.testing.assert_allclose(match_extent, query_extent, rtol=0.05)
    assert query_extent[0] > 1.5 * query_extent[2]  # the ring's plane holds the first axis


def test_a_changed_mesh_is_drawn_from_the_index_with_a_note(indexed):
    from nfdmatch.show_objects import show_objects

    folder, index, query = indexed
    trimesh.creation.icosphere(subdivisions=2).export(str(folder / "torus.ply"))  # not what was indexed
    with open_index(index) as idx:
        (shown,), notes = show_objects(idx, query, k=1)
    best = shown.shown[0]
    assert best.id == "parts/torus.ply" and best.source == "index"
    assert notes == ["parts/torus.ply: drawn from its 16 indexed harmonics: the file changed since it was indexed"]
    # the stored harmonics rebuild the contours in the mesh's pose: the same frame's picture
    np.testing.assert_allclose(_extent(best.loops), _extent(shown.loops), rtol=0.08)


def _coloured_pixels(path: str, colour: str, box) -> int:
    """Pixels of ``path`` within 60/255 of ``colour`` inside ``box`` (x0, x1 as fractions of the width)."""
    import matplotlib.image
    from matplotlib.colors import to_rgb

    image = matplotlib.image.imread(path)[:, :, :3]
    w = image.shape[1]
    part = image[:, int(box[0] * w) : int(box[1] * w)]
    return int((np.abs(part - np.asarray(to_rgb(colour))).max(axis=2) < 60 / 255).sum())


def test_the_cli_draws_a_mesh_query_and_prints_the_rows(indexed, tmp_path):
    from nfdmatch.render.layout import MATCH_COLOR, QUERY_COLOR

    folder, index, query = indexed
    picture = str(tmp_path / "torus.png")
    result = CliRunner().invoke(
        main, ["show", query, "--index", index, "--top", "2", "-o", picture, "--size", "900x400", "--format", "csv"]
    )
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    assert list(rows[0]) == ["query", "rank", "match", "distance", "curves", "source"]
    assert [(r["query"], r["rank"], r["match"], r["source"]) for r in rows] == [
        (query, "1", "parts/torus.ply", "file"),
        (query, "2", rows[1]["match"], "file"),
    ]
    assert rows[1]["match"] in ("parts/capsule.stl", "parts/bar.off")
    assert float(rows[0]["distance"]) < 0.25 * float(rows[1]["distance"])
    assert all(c.startswith("#") for c in rows[0]["curves"].split())
    assert f"wrote {picture}" in result.stderr and "Traceback" not in result.stderr
    # three panels side by side (900 x 400): the query's contours in its colour in the first,
    # the first answer's in the match colour in the second, none of them in the first
    assert _coloured_pixels(picture, QUERY_COLOR, (0.0, 0.33)) > 500
    assert _coloured_pixels(picture, MATCH_COLOR, (0.34, 0.66)) > 500
    assert _coloured_pixels(picture, MATCH_COLOR, (0.0, 0.33)) == 0


def test_the_cli_excludes_the_query_mesh_itself(indexed, tmp_path):
    folder, index, _ = indexed
    picture = str(tmp_path / "self.png")
    result = CliRunner().invoke(
        main, ["show", str(folder / "torus.ply"), "--index", index, "--exclude-self", "-o", picture, "--format", "csv"]
    )
    assert result.exit_code == 0, result.output
    matches = [r["match"] for r in csv.DictReader(io.StringIO(result.stdout))]
    assert sorted(matches) == ["parts/bar.off", "parts/capsule.stl"]
    assert os.path.getsize(picture) > 0


def test_the_cli_refuses_a_mesh_query_it_cannot_draw(indexed, tmp_path):
    folder, index, query = indexed
    runner = CliRunner()
    picture = str(tmp_path / "q.png")
    result = runner.invoke(main, ["show", query, "--index", index, "--elastic", "-o", picture])
    assert result.exit_code == 2 and "--elastic does not apply to a mesh query" in result.stderr
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    ring = tmp_path / "ring.csv"
    np.savetxt(ring, np.c_[np.cos(t), np.sin(t), 0 * t], delimiter=",", header="x,y,z", comments="")
    curves = str(tmp_path / "curves.h5")
    build_index([str(ring)], curves, jobs=1)
    result = runner.invoke(main, ["show", query, "--index", curves, "-o", picture])
    assert result.exit_code == 2 and "no mesh objects" in result.stderr and "Traceback" not in result.stderr
    assert not os.path.exists(picture)


def test_the_cli_writes_no_rows_file_when_a_query_mesh_fails(indexed, tmp_path):
    """As `show` of curves and `query` (README, exit 3): neither the pictures nor the rows'
    -o are written, and the JSON failure record lists the mesh (the rows file was written,
    `"failed": []`)."""
    import json

    folder, index, query = indexed
    bad = tmp_path / "bad.stl"
    bad.write_text("solid x\nnonsense\n")
    pattern, rows = str(tmp_path / "s-{stem}.png"), tmp_path / "rows.csv"
    runner = CliRunner()
    result = runner.invoke(main, ["show", query, str(bad), "--index", index, "-o", pattern, "-o", str(rows)])
    assert result.exit_code == 3, result.output
    assert not rows.exists() and f"{rows} not written" in result.stderr
    assert not list(tmp_path.glob("s-*.png"))
    args = ["show", query, str(bad), "--index", index, "-o", pattern, "--format", "jsonl"]
    result = runner.invoke(main, args)
    assert result.exit_code == 3, result.output
    last = json.loads(result.stdout.splitlines()[-1])
    assert last["exit"] == 3 and [f["input"] for f in last["failed"]] == [str(bad)]
