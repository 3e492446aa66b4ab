"""Where an index and its files are: ids independent of the working directory and of the
spelling of the sources, recorded sources, the shrink guard, a symbolic link as the index
path, a write that fails (disk full), and --rebuild over a file that is not an index."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from oracle import random_smooth_curve

import nfdmatch.index as nindex
from nfdmatch.index import lock as index_lock
from nfdmatch import write_curves
from nfdmatch.errors import IndexFormatError, IndexLockedError, ShrinkRefusedError, WriteError
from nfdmatch.index import build_index, open_index
from conftest import ROOT, run_cli as run


def _library(folder, rng, n=5):
    (folder / "sub").mkdir(parents=True)
    for i in range(n - 2):
        write_curves(folder / f"c{i}.csv", random_smooth_curve(rng, 60, 4))
    write_curves(folder / "sub" / "multi.obj", [random_smooth_curve(rng, 50, 4) for _ in range(3)])
    write_curves(folder / "sub" / "one.obj", [random_smooth_curve(rng, 50, 4)])
    return folder


@pytest.fixture
def lib(tmp_path, rng):
    return _library(tmp_path / "lib", rng)


KEYS = ["lib/c0.csv", "lib/c1.csv", "lib/c2.csv", "lib/sub/multi.obj", "lib/sub/one.obj"]
IDS = ["lib/c0.csv", "lib/c1.csv", "lib/c2.csv"] + [f"lib/sub/multi.obj#{i}" for i in range(3)] + ["lib/sub/one.obj"]


# --------------------------------------------------------------------------- ids and sources


def test_the_same_files_are_the_same_rows_however_the_source_is_spelled(lib, tmp_path, monkeypatch, reads):
    index = tmp_path / "idx.h5"
    monkeypatch.chdir(tmp_path)
    first = build_index(["lib"], "idx.h5", jobs=1)
    assert first.added == 5 and [p for _, p in first.changes] == KEYS
    with open_index(index) as idx:
        assert [f.path for f in idx.files()] == KEYS and idx.ids() == IDS and idx.sources() == (["lib"], None)
    data = index.read_bytes()
    link = tmp_path / "elsewhere"
    link.mkdir()
    os.symlink(lib, link / "lib-link")
    spellings = [
        ("./lib/", tmp_path),
        (str(lib), tmp_path),
        (str(lib), link),
        ("lib-link", link),
        (str(link / "lib-link"), "/"),
        ("../lib", link),
    ]
    for source, cwd in spellings:
        monkeypatch.chdir(cwd)
        reads.clear()
        report = build_index([source], str(index), jobs=1)
        assert (report.unchanged, report.added, report.removed) == (5, 0, 0), (source, cwd)
        assert reads == [] and not report.written and index.read_bytes() == data, (source, cwd)
    # both spellings at once are still one set of files
    monkeypatch.chdir(tmp_path)
    report = build_index(["lib", str(link / "lib-link"), "lib/c0.csv"], str(index), jobs=1)
    assert (report.unchanged, report.added) == (5, 0) and report.written  # the sources changed
    with open_index(index) as idx:
        assert idx.ids() == IDS and idx.sources() == (["lib", "lib/c0.csv"], None)


def test_files_outside_the_index_folder_are_stored_absolute(lib, tmp_path, monkeypatch):
    (tmp_path / "indexes").mkdir()
    monkeypatch.chdir(tmp_path)
    build_index(["lib"], "indexes/i.h5", jobs=1)
    with open_index(tmp_path / "indexes" / "i.h5") as idx:
        real = os.path.realpath(lib)
        assert [f.path for f in idx.files()] == [os.path.join(real, k[4:]) for k in KEYS]
        assert idx.sources() == ([real], None)


def test_build_without_sources_rescans_the_recorded_ones(lib, tmp_path, monkeypatch, rng):
    index = tmp_path / "idx.h5"
    write_curves(lib / "skip.obj", [random_smooth_curve(rng, 40, 4)])
    code, out, err = run("index", "build", lib, "--index", index, "--glob", "*.csv", "-j", 1, "--format", "json")
    assert code == 0, err
    assert json.loads(out)["sources"] == ["lib"] and json.loads(out)["added"] == 3
    write_curves(lib / "new.csv", random_smooth_curve(rng, 40, 4))
    os.remove(lib / "c1.csv")
    monkeypatch.chdir("/")  # the cron line: one short command, from anywhere
    code, out, err = run("index", "build", "--index", index, "-j", 1, "--format", "json")
    assert code == 0, err
    summary = json.loads(out)
    assert (summary["added"], summary["removed"], summary["unchanged"]) == (1, 1, 2)
    with open_index(index) as idx:
        assert [f.path for f in idx.files()] == ["lib/c0.csv", "lib/c2.csv", "lib/new.csv"]
        assert idx.sources() == (["lib"], "*.csv")
    code, out, _ = run("index", "info", "--index", index)
    assert code == 0 and "\nsources\tlib\n" in out
    assert json.loads(run("index", "info", "--index", index, "--format", "json")[1])["sources"] == ["lib"]
    # no sources and no index, or an index that does not record them: clear errors, exit 1
    code, out, err = run("index", "build", "--index", tmp_path / "none.h5")
    assert (code, out) == (2, "") and "no SOURCE given and no index to take them from" in err
    with h5py.File(index, "r+") as h5:
        del h5["sources"]
    code, out, err = run("index", "build", "--index", index)
    assert code == 2 and "does not record its sources" in err and "Traceback" not in err


def test_an_index_without_recorded_sources_is_upgraded_keeping_its_rows(lib, tmp_path, monkeypatch, reads):
    """An index of an earlier writer stored paths relative to its build's cwd: a build maps
    them, copies the unchanged rows under new ids and records its sources."""
    index = tmp_path / "idx.h5"
    monkeypatch.chdir(lib)
    build_index(["."], str(index), jobs=1)
    with h5py.File(index, "r+") as h5:  # what an earlier writer wrote
        del h5["sources"]
        del h5.attrs["checksums"]  # (no checksums either)
        for name in ("files/path_crc32", "files/error_crc32", "curves/id_crc32"):
            del h5[name]
        old = sorted(os.path.relpath(os.path.join(str(lib), k[4:])) for k in KEYS)
        del h5["files/path"]
        h5["files"].create_dataset("path", data=np.array(old, dtype=object), dtype=h5py.string_dtype())
        ids = h5["curves/id"].asstr()[...].tolist()
        del h5["curves/id"]
        h5["curves"].create_dataset("id", data=np.array([i[4:] for i in ids], dtype=object), dtype=h5py.string_dtype())
    with open_index(index) as idx:
        assert idx.sources() is None and idx.ids()[0] == "c0.csv" and idx.locate("c0.csv") == "c0.csv"
        before = idx.read_rows(0, idx.n_curves)["coefficients"]
    reads.clear()
    report = build_index(["."], str(index), jobs=1)
    assert reads == [] and (report.unchanged, report.added, report.removed) == (5, 0, 0) and report.written
    with open_index(index) as idx:
        assert idx.ids() == IDS and idx.sources() == (["lib"], None)
        np.testing.assert_array_equal(idx.read_rows(0, idx.n_curves)["coefficients"], before)


def test_show_and_exclude_self_find_the_files_from_another_directory(lib, tmp_path, monkeypatch):
    index = tmp_path / "idx.h5"
    monkeypatch.chdir(tmp_path)
    assert run("index", "build", "lib", "--index", "idx.h5", "-j", 1)[0] == 0
    elsewhere = tmp_path / "else"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    query = lib / "c0.csv"
    code, out, err = run("show", query, "--index", index, "--top", 2, "-o", "m.png", "--format", "json")
    assert code == 0, err
    rows = json.loads(out)
    assert rows[0]["match"] == "lib/c0.csv" and rows[0]["source"] == "file"  # found, not redrawn
    assert "drawn from its" not in err
    code, out, err = run("query", query, "--index", index, "--top", 2, "--exclude-self", "--format", "json")
    assert code == 0, err
    assert all(r["match"] != "lib/c0.csv" for r in json.loads(out))
    with open_index(index) as idx:
        assert os.path.realpath(idx.locate("lib/sub/multi.obj#2")[:-2]) == os.path.realpath(lib / "sub" / "multi.obj")


# --------------------------------------------------------------------------- the shrink guard


def test_an_empty_or_unmounted_source_does_not_wipe_the_index(lib, tmp_path):
    index = tmp_path / "idx.h5"
    assert run("index", "build", lib, "--index", index, "-j", 1)[0] == 0
    data = index.read_bytes()
    empty = tmp_path / "mnt"
    empty.mkdir()
    code, out, err = run("index", "build", empty, "--index", index, "-j", 1)
    assert code == 2 and out == ""
    assert err.startswith(
        f"Error: {index}: refusing to build: it would remove all of the index's 5 files "
        f"(no curve files found under {empty}; an empty or unmounted folder?); pass "
        "--allow-shrink"
    )
    assert index.read_bytes() == data
    code, out, err = run("index", "build", empty, "--index", index, "-j", 1, "--format", "json")
    summary = json.loads(out)
    assert code == 2 and summary["shrink"] == {"removed": 5, "of": 5, "allowed": False}
    assert summary["written"] is False and "refusing to build" in summary["refused"]
    code, out, err = run("index", "build", empty, "--index", index, "--dry-run")
    # the dry run says so, and exits as the build would (issue 25, item 10)
    assert code == 2 and "a build would refuse to remove 5 of 5 files" in err
    assert index.read_bytes() == data
    code, out, err = run("index", "build", empty, "--index", index, "--allow-shrink", "--format", "json")
    summary = json.loads(out)
    assert code == 0 and summary["removed"] == 5 and summary["shrink"] == {"removed": 5, "of": 5, "allowed": True}
    assert "removing 5 of the index's 5 files (--allow-shrink)" in err


def test_more_than_half_removed_is_refused_half_is_not(lib, tmp_path):
    index = str(tmp_path / "idx.h5")
    build_index([str(lib)], index, jobs=1)
    for name in ("c0.csv", "c1.csv"):
        os.remove(lib / name)
    report = build_index([str(lib)], index, jobs=1)  # 2 of 5: allowed, no notice
    assert report.removed == 2 and report.shrink is None
    build_index([str(lib)], index, jobs=1)
    for name in ("c2.csv", "sub/one.obj"):
        os.remove(lib / name)
    with pytest.raises(ShrinkRefusedError, match=r"would remove 2 of the index's 3 files \(1 files found"):
        build_index([str(lib)], index, jobs=1)
    assert build_index([str(lib)], index, jobs=1, allow_shrink=True).curves == 3


# --------------------------------------------------------------------------- the index path


def test_a_symlinked_index_updates_its_target_and_shares_its_lock(lib, tmp_path, rng):
    real_dir = tmp_path / "store"
    real_dir.mkdir()
    target = real_dir / "real.h5"
    link = tmp_path / "idx.h5"
    os.symlink(target, link)  # dangling at first: the build creates the target
    report = build_index([str(lib)], str(link), jobs=1)
    assert report.written and os.path.islink(link) and target.is_file()
    assert sorted(os.listdir(real_dir)) == ["real.h5", "real.h5.lock"]
    assert sorted(os.listdir(tmp_path)) == ["idx.h5", "lib", "store"]
    with open_index(target) as idx:  # stored relative to the real file's folder
        assert idx.files()[0].path == os.path.join(os.path.realpath(lib), "c0.csv")
    write_curves(lib / "c9.csv", random_smooth_curve(rng, 40, 4))
    assert build_index([str(lib)], str(link), jobs=1).added == 1
    assert os.path.islink(link) and os.readlink(link) == str(target)
    with open_index(target) as idx:
        assert idx.n_files == 6
    # two names for one index take one lock
    lock = index_lock.Lock(str(target), 0)
    try:
        with pytest.raises(IndexLockedError, match=r"real\.h5\.lock"):
            build_index([str(lib)], str(link), jobs=1, rebuild=True)
    finally:
        lock.release()
    # and a link to a link is the same file
    os.symlink(link, tmp_path / "again.h5")
    assert build_index([str(lib)], str(tmp_path / "again.h5"), jobs=1).unchanged == 6


@pytest.mark.parametrize("where", ["datasets", "fsync"])
def test_disk_full_while_writing_keeps_the_old_index(lib, tmp_path, rng, monkeypatch, where):
    index = tmp_path / "idx.h5"
    assert run("index", "build", lib, "--index", index, "-j", 1)[0] == 0
    data = index.read_bytes()
    write_curves(lib / "c9.csv", random_smooth_curve(rng, 40, 4))

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    if where == "datasets":
        monkeypatch.setattr(nindex.commit, "write_files_table", full)
    else:
        monkeypatch.setattr(nindex.writer.os, "fsync", full)
    code, out, err = run("index", "build", lib, "--index", index, "-j", 1)
    assert (code, out) == (2, "")
    assert err == f"Error: {index}: cannot write the index: No space left on device\n"
    assert index.read_bytes() == data
    assert sorted(os.listdir(tmp_path)) == ["idx.h5", "idx.h5.lock", "lib"]  # no temporary file left
    with pytest.raises(WriteError, match="No space left on device"):
        build_index([str(lib)], str(index), jobs=1)


def test_a_real_failing_write_is_a_clear_error(lib, tmp_path):
    """HDF5 itself fails to write (a file-size limit, as a full disk would): exit 1, no
    traceback, no crash, the old index intact, no temporary file."""
    index = tmp_path / "idx.h5"
    assert run("index", "build", lib, "--index", index, "-j", 1)[0] == 0
    data = index.read_bytes()
    big = tmp_path / "lib" / "big"
    big.mkdir()
    rng = np.random.default_rng(3)
    write_curves(big / "many.obj", [random_smooth_curve(rng, 30, 3) for _ in range(600)])
    code = (
        "import resource, signal, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        f"resource.setrlimit(resource.RLIMIT_FSIZE, ({len(data) + 4096}, {len(data) + 4096}))\n"
        "from nfdmatch.cli import main\n"
        "sys.exit(main(['index', 'build', sys.argv[1], '--index', sys.argv[2], '-j', '1', '--allow-shrink']))\n"
    )
    env = dict(os.environ, PYTHONPATH=ROOT, PYTHONDONTWRITEBYTECODE="1")
    proc = subprocess.run(
        [sys.executable, "-c", code, str(lib), str(index)], capture_output=True, text=True, env=env, timeout=120
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith(f"Error: {index}: cannot write the index: ") and "Traceback" not in proc.stderr
    assert index.read_bytes() == data
    assert sorted(os.listdir(tmp_path)) == ["idx.h5", "idx.h5.lock", "lib"]


@pytest.mark.parametrize("kind", ["truncated", "text"])
def test_rebuild_never_overwrites_a_file_that_is_not_an_index(lib, tmp_path, kind):
    index = tmp_path / "idx.h5"
    build_index([str(lib)], str(index), jobs=1)
    data = index.read_bytes()
    if kind == "truncated":
        index.write_bytes(data[: len(data) // 3])
    else:
        index.write_text("my notes, not an index\n")
    before = index.read_bytes()
    code, out, err = run("index", "build", lib, "--index", index, "--rebuild", "-j", 1)
    assert code == 2 and out == "" and "refusing to overwrite it" in err and "Traceback" not in err
    assert index.read_bytes() == before
    with pytest.raises(IndexFormatError):
        build_index([str(lib)], str(index), jobs=1, rebuild=True)


# --------------------------------------------------------------------------- what a walk skips


def test_an_unlistable_folder_keeps_its_rows_and_a_fifo_is_skipped(lib, tmp_path, monkeypatch):
    index = tmp_path / "idx.h5"
    assert run("index", "build", lib, "--index", index, "-j", 1)[0] == 0
    with open_index(index) as idx:
        before = idx.ids()
    os.mkfifo(lib / "pipe.csv")  # opening it would block the build forever
    locked = str(lib / "sub")
    real_scandir = os.scandir

    def scandir(path="."):
        if os.fspath(path) == locked:
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", scandir)  # root reads any folder: simulate chmod 000
    code, out, err = run("index", "build", lib, "--index", index, "-j", 1, "--format", "json")
    assert code == 3, err
    assert f"Error: {locked}: cannot list the folder (Permission denied); its files are skipped" in err
    assert f"Error: {lib / 'pipe.csv'}: is a FIFO (named pipe), not a regular file; skipped" in err
    summary = json.loads(out)
    assert (summary["removed"], summary["unchanged"]) == (0, 5) and len(summary["skipped"]) == 2
    with open_index(index) as idx:
        assert idx.ids() == before  # the sub-folder's curves are still there
    # a FIFO named directly is skipped too, never opened
    monkeypatch.setattr(os, "scandir", real_scandir)
    code, out, err = run("index", "build", lib, lib / "pipe.csv", "--index", index, "-j", 1)
    assert (
        code == 3
        and err.count(f"Error: {lib / 'pipe.csv'}: is a FIFO (named pipe), not a regular file; skipped\n") == 1
    )  # named once


def test_a_non_utf8_file_name_is_indexed_under_an_escaped_id(tmp_path, rng, monkeypatch):
    lib = tmp_path / "lib"
    lib.mkdir()
    write_curves(os.path.join(str(lib), os.fsdecode(b"c\xff.csv")), random_smooth_curve(rng, 40, 4))
    write_curves(lib / "ok.csv", random_smooth_curve(rng, 40, 4))
    monkeypatch.chdir(tmp_path)
    assert build_index(["lib"], "i.h5", jobs=1).added == 2
    report = build_index([str(lib)], "i.h5", jobs=1)  # the escaped id still matches its file
    assert (report.unchanged, report.written) == (2, False)
    with open_index(tmp_path / "i.h5") as idx:
        assert idx.ids() == ["lib/c\\xff.csv", "lib/ok.csv"]


# --------------------------------------------------------------------------- messages (issue 24, item 6)


def test_an_unreadable_source_folder_is_said_to_be_unreadable_and_keeps_its_rows(lib, tmp_path, monkeypatch):
    """It was "refusing to build: it would remove all of the index's 6 files (...; an empty or
    unmounted folder?)", the permission problem never named."""
    index = tmp_path / "idx.h5"
    assert run("index", "build", lib, "--index", index, "-j", 1)[0] == 0
    with open_index(index) as idx:
        before = idx.ids()
    real_scandir = os.scandir

    def scandir(path="."):
        if os.path.realpath(os.fspath(path)) == os.path.realpath(lib):
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", scandir)  # root reads any folder: simulate chmod 000
    code, _, err = run("index", "build", lib, "--index", index, "-j", 1)
    assert code == 3, err
    assert f"Error: {lib}: cannot list the folder (Permission denied); its files are skipped" in err
    assert "unmounted" not in err and "would be removed" not in err
    with open_index(index) as idx:
        assert idx.ids() == before


def test_an_index_moved_away_from_its_files_says_so_and_how_to_rebuild(lib, tmp_path, monkeypatch):
    index = tmp_path / "idx.h5"
    monkeypatch.chdir(tmp_path)
    assert run("index", "build", "lib", "--index", "idx.h5", "-j", 1)[0] == 0
    (tmp_path / "sub").mkdir()
    os.replace(index, tmp_path / "sub" / "idx.h5")
    code, _, err = run("index", "build", "lib", "--index", "sub/idx.h5", "-j", 1)
    assert code == 2
    assert "stored paths are relative to its folder and no longer lead to its files" in err
    assert "was the index moved? Move it back, or rebuild it here with" in err
    assert "`nfdmatch index build lib --index sub/idx.h5 --rebuild --allow-shrink`" in err
    code, _, err = run("index", "build", "--index", "sub/idx.h5", "-j", 1)  # its recorded sources
    assert code == 2 and "the index records the source 'lib' relative to its folder" in err
    assert "was the index moved?" in err
    code, _, err = run("index", "build", "lib", "--index", "sub/idx.h5", "-j", 1, "--rebuild", "--allow-shrink")
    assert code == 0, err


def test_index_build_of_stdin_is_a_usage_error(tmp_path):
    code, _, err = run("index", "build", "-", "--index", tmp_path / "x.h5")
    assert code == 2 and "index build reads files and folders, not stdin ('-')" in err
    assert "no such file" not in err


def test_a_disk_full_before_the_index_is_created_is_said_in_our_words(lib, tmp_path, monkeypatch):
    """At 0 bytes free the lock's pid failed with a traceback, then HDF5's own text was printed
    ("Unable to synchronously create file (file write failed: time = ..., errno = 28 ...")."""

    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    class H5:
        def __getattr__(self, name):
            return getattr(h5py, name)

        @staticmethod
        def File(path, mode="r", **kwargs):
            if mode == "w":
                raise OSError(
                    errno.ENOSPC,
                    "Unable to synchronously create file (file write failed: time = Thu Dec  3 10:07:25 2026, "
                    f"filename = '{path}', file descriptor = 5, errno = 28, error message = 'No space left on device')",
                )
            return h5py.File(path, mode, **kwargs)

    monkeypatch.setattr(index_lock.os, "pwrite", no_space)
    monkeypatch.setattr(nindex.commit, "h5py", H5())
    index = tmp_path / "idx.h5"
    code, out, err = run("index", "build", lib, "--index", index, "-j", 1)
    assert (code, out) == (2, "")
    assert err == f"Error: {index}: cannot write the index: No space left on device\n"


def test_extract_on_a_full_disk_names_the_contour_not_its_temporary_file(tmp_path, monkeypatch):
    import trimesh

    from nfdmatch.errors import WriteError as _WriteError
    from nfdmatch.mesh import naming

    trimesh.creation.cylinder(radius=1.0, height=4.0, sections=32).export(tmp_path / "rod.stl")

    def full(path, curves, format=None):
        raise _WriteError("cannot write the file (No space left on device)", path=path)

    monkeypatch.setattr(naming, "write_curves", full)
    code, _, err = run("extract", tmp_path / "rod.stl", "-o", tmp_path / "out", "--sections", 1)
    assert code == 2
    name = next(iter(os.listdir(tmp_path / "out")), None)
    assert name is None  # nothing left behind
    assert err.startswith(f"Error: {tmp_path / 'out' / 'rod_section-z00_at0_loop0.obj'}: cannot write the file")
    assert ".tmp" not in err
