"""`nfdmatch extract --prune` and the output folder's manifest (docs/extract.md, "Stale files")."""

from __future__ import annotations

import json
import os

import pytest
import trimesh

from nfdmatch.extract import MANIFEST, prune_contours, read_manifest
from conftest import run_cli as run


def cylinder(path, height=8.0, shift=0.0):
    trimesh.creation.cylinder(radius=0.8, height=height, sections=32).apply_translation([0.0, 0.0, shift]).export(path)


def names(folder) -> list[str]:
    return sorted(os.listdir(folder))


@pytest.fixture
def parts(tmp_path):
    d = tmp_path / "parts"
    d.mkdir()
    cylinder(d / "rod.stl")
    trimesh.creation.torus(major_radius=2.0, minor_radius=0.5, major_sections=48, minor_sections=24).export(
        d / "ring.ply"
    )
    return d


def contours_of(folder, stem):
    return [n for n in names(folder) if n.startswith(stem + "_")]


def test_a_changed_mesh_whose_levels_move_leaves_no_stale_files(parts, tmp_path):
    out = tmp_path / "contours"
    code, _, err = run("extract", parts, "-o", out, "--sections", 3)
    assert code == 0, err
    old_rod, ring = contours_of(out, "rod"), contours_of(out, "ring")
    assert len(old_rod) == 3 and len(ring) == 4 and MANIFEST in names(out)
    (out / "notes.obj").write_text("v 0 0 0\n")  # not extract's: never touched
    cylinder(parts / "rod.stl", height=12.0, shift=1.0)  # the levels move: new names
    # without --prune the old files stay (and the manifest remembers them)
    code, _, err = run("extract", parts, "-o", out, "--sections", 3)
    assert code == 0, err
    assert set(old_rod) <= set(names(out)) and len(contours_of(out, "rod")) == 6
    # a stale file the user edited since is not extract's any more: left alone, said so
    edited = out / old_rod[0]
    edited.write_text(edited.read_text() + "# my note\n")
    code, stdout, err = run("extract", parts, "-o", out, "--sections", 3, "--prune", "--format", "csv", "-v")
    assert code == 0, err
    new_rod = contours_of(out, "rod")
    assert sorted(set(new_rod) - {old_rod[0]}) == sorted(n for n in new_rod if n not in old_rod)
    assert len(new_rod) == 4 and old_rod[0] in new_rod
    assert f"{edited}: not pruned: changed since extract wrote it; left alone" in err
    assert f"removed {out / old_rod[1]}" in err and "2 stale contour files removed" in err
    assert "notes.obj" in names(out) and contours_of(out, "ring") == ring
    # stdout lists exactly the written files, and the manifest exactly those
    listed = sorted(os.path.basename(line.split(",")[0]) for line in stdout.splitlines()[1:])
    entries, problem = read_manifest(out)
    assert problem is None and sorted(entries) == listed
    assert sorted(names(out)) == sorted(listed + ["notes.obj", old_rod[0], MANIFEST])


def test_a_deleted_mesh_loses_its_contours_and_a_failed_one_keeps_them(parts, tmp_path):
    out = tmp_path / "contours"
    assert run("extract", parts, "-o", out, "--sections", 2)[0] == 0
    assert len(contours_of(out, "ring")) == 4 and len(contours_of(out, "rod")) == 2
    # the ring's file turns unreadable: this run fails it (exit 3) and keeps its contours
    ring = (parts / "ring.ply").read_bytes()
    (parts / "ring.ply").write_text("garbage\n")
    code, _, err = run("extract", parts, "-o", out, "--sections", 2, "--prune")
    assert code == 3 and len(contours_of(out, "ring")) == 4
    assert "its mesh could not be read this run" in err
    (parts / "ring.ply").write_bytes(ring)
    os.remove(parts / "ring.ply")  # deleted for good
    code, _, err = run("extract", parts, "-o", out, "--sections", 2, "--prune")
    assert code == 0, err
    assert contours_of(out, "ring") == [] and len(contours_of(out, "rod")) == 2
    assert "4 stale contour files removed" in err
    assert not [n for n in names(out) if n.startswith(".") and n != MANIFEST]  # no temporary files


def test_the_manifest_is_stable_json_and_an_identical_rerun_leaves_it(parts, tmp_path):
    out = tmp_path / "contours"
    assert run("extract", parts / "rod.stl", "-o", out, "--sections", 2)[0] == 0
    data = json.loads((out / MANIFEST).read_text())
    assert data["format"] == "nfdmatch-extract-manifest" and data["version"] == 1
    assert sorted(data["files"]) == contours_of(out, "rod")
    entry = data["files"][contours_of(out, "rod")[0]]
    assert entry["mesh"] == os.path.realpath(parts / "rod.stl") and len(entry["sha256"]) == 64
    os.utime(out / MANIFEST, ns=(1, 1))
    inode = os.stat(out / MANIFEST).st_ino
    assert run("extract", parts / "rod.stl", "-o", out, "--sections", 2, "--prune")[0] == 0
    # nothing changed: not rewritten (the same file), only its mtime refreshed
    assert os.stat(out / MANIFEST).st_ino == inode and os.stat(out / MANIFEST).st_mtime_ns > 1


def test_prune_never_follows_a_hostile_manifest(tmp_path):
    out = tmp_path / "contours"
    out.mkdir()
    victim = tmp_path / "precious.txt"
    victim.write_text("keep me\n")
    import hashlib

    sha = hashlib.sha256(victim.read_bytes()).hexdigest()
    (out / MANIFEST).write_text(
        json.dumps(
            {
                "format": "nfdmatch-extract-manifest",
                "version": 1,
                "files": {"../precious.txt": {"mesh": "x", "sha256": sha}, str(victim): {"mesh": "x", "sha256": sha}},
            }
        )
    )
    result = prune_contours(out, [])
    assert result.removed == [] and victim.read_text() == "keep me\n"
    (out / MANIFEST).write_text("{not json")
    result = prune_contours(out, [])
    assert result.removed == [] and "cannot read the manifest" in result.notes[0]


def test_a_file_extract_did_not_write_is_never_replaced_nor_pruned(parts, tmp_path):
    """Issue 24, item 1: a user's file under a contour's name was replaced, then pruned."""
    out = tmp_path / "contours"
    out.mkdir()
    # the names this run would write: learn them in a scratch folder
    scratch = tmp_path / "scratch"
    code, _, err = run("extract", parts / "rod.stl", "-o", scratch, "--sections", 2, "--axis", "z")
    assert code == 0, err
    name = contours_of(scratch, "rod")[0]
    mine = out / name
    mine.write_text("# mine\nv 0 0 0\nv 1 0 0\nv 1 1 0\nl 1 2 3 1\n")
    code, _, err = run("extract", parts, "-o", out, "--sections", 2, "--axis", "z")
    assert code == 3, err
    assert f"{mine}: not replaced: extract did not write this file" in err and "--force" in err
    assert mine.read_text().startswith("# mine")
    assert contours_of(out, "rod") == [name] and len(contours_of(out, "ring")) == 4  # the other mesh went on
    code, _, err = run("extract", parts, "-o", out, "--sections", 3, "--axis", "z", "--prune")
    assert code == 0, err  # three levels: other names, nothing in the way
    assert mine.read_text().startswith("# mine") and "1 stale contour file removed" not in err
    assert name not in read_manifest(out)[0]
    # a contour file of extract's own that the user edited since is not replaced either
    code, _, err = run("extract", parts, "-o", out, "--sections", 3, "--axis", "z")
    assert code == 0, err
    edited = out / contours_of(out, "ring")[-1]
    edited.write_text(edited.read_text() + "# note\n")
    code, _, err = run("extract", parts, "-o", out, "--sections", 3, "--axis", "z")
    assert code == 3 and f"{edited}: not replaced: changed since extract wrote it" in err
    assert edited.read_text().endswith("# note\n")
    # --force takes both over; then they are extract's and prune may remove them
    code, _, err = run("extract", parts, "-o", out, "--sections", 2, "--axis", "z", "--force")
    assert code == 0, err
    assert not mine.read_text().startswith("# mine") and name in read_manifest(out)[0]


def test_a_mesh_whose_only_contours_are_refused_exits_3_and_writes_nothing(parts, tmp_path):
    out = tmp_path / "contours"
    code, _, err = run("extract", parts / "rod.stl", "-o", out, "--sections", 1)
    assert code == 0, err
    (name,) = contours_of(out, "rod")
    os.remove(out / MANIFEST)  # an identical file is extract's output whatever the manifest says
    code, _, err = run("extract", parts / "rod.stl", "-o", out, "--sections", 1)
    assert code == 0, err
    (out / name).write_text("v 0 0 0\n")
    os.remove(out / MANIFEST)
    code, _, err = run("extract", parts / "rod.stl", "-o", out, "--sections", 1)
    assert code == 3 and "1 of 1 meshes not written" in err
    assert (out / name).read_text() == "v 0 0 0\n"
    from nfdmatch.errors import OverwriteRefusedError
    from nfdmatch.extract import extract_contours, write_contours

    contours = extract_contours(parts / "rod.stl", sections=1).contours
    with pytest.raises(OverwriteRefusedError, match="not replaced"):
        write_contours(contours, out)
    assert (out / name).read_text() == "v 0 0 0\n"


def test_a_manifest_of_deeply_nested_brackets_is_a_note_and_extract_still_writes(parts, tmp_path):
    """Issue 24, item 5: 100,000 nested brackets gave a RecursionError traceback."""
    out = tmp_path / "contours"
    out.mkdir()
    (out / MANIFEST).write_text("[" * 100_000 + "]" * 100_000)
    entries, problem = read_manifest(out)
    assert entries == {} and "nested too deeply" in problem
    code, _, err = run("extract", parts, "-o", out, "--sections", 2, "--prune")
    assert code == 0, err
    assert "cannot read the manifest (nested too deeply); nothing pruned by it" in err
    assert len(contours_of(out, "rod")) == 2 and len(read_manifest(out)[0]) == len(names(out)) - 1


def test_a_partial_jsonl_run_with_a_file_in_the_way_ends_with_its_failure_record(parts, tmp_path):
    """README: a partial jsonl run ends with the JSON record listing the failed inputs; with
    only refused meshes (a file in the way) it ended without one, rows or none."""
    out = tmp_path / "contours"
    code, _, err = run("extract", parts / "rod.stl", "-o", out, "--sections", 1, "--axis", "z")
    assert code == 0, err
    (name,) = contours_of(out, "rod")
    (out / name).write_text("v 0 0 0\n")
    os.remove(out / MANIFEST)
    for meshes, rows in (([parts / "rod.stl"], 0), ([parts / "rod.stl", parts / "ring.ply"], 2)):
        args = ["extract", *meshes, "-o", out, "--sections", 1, "--axis", "z", "--format", "jsonl", "-q"]
        code, stdout, err = run(*args)
        assert code == 3 and f"1 of {len(meshes)} meshes not written" in err
        *written, last = [json.loads(line) for line in stdout.splitlines()]
        assert len(written) == rows and all(r["mesh"] == str(parts / "ring.ply") for r in written)
        assert last["exit"] == 3 and [f["input"] for f in last["failed"]] == [str(out / name)]
        assert (out / name).read_text() == "v 0 0 0\n"
