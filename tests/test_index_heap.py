"""A damaged index is an error, never a hang (issue 34, item 1).

HDF5 keeps variable-length strings in global heap collections, which carry no checksum, and
loops forever on a collection whose free-space object says it is 0 bytes long. The frozen
``tests/data/index/hang-heap-v2.h5`` is the sample library indexed by nfdmatch before
issue 34 (string attributes in the global heap) with one byte changed: byte 5256 XOR 0x80,
the free-space object's size, the place the issue's random flip (``random.Random(3)``, flip
315: byte 5456 XOR 97 of its build) hit; ``query`` then never stopped, even on SIGTERM.

Every command here runs in a subprocess under a hard time limit: a hang fails the test
instead of stopping the suite."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import h5py
import pytest

from nfdmatch.index import build_index, open_index

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
HANG = os.path.join(HERE, "data", "index", "hang-heap-v2.h5")
FROZEN_V2 = os.path.join(HERE, "data", "index", "v2-sample.h5")
QUERY = os.path.join(ROOT, "sample_curves", "queries", "trefoil-posed.obj")
LIMIT = 120  # seconds: far above any answer, far below "forever"


def nfdmatch(*args, cwd=None):
    """(exit code, stdout, stderr) of the CLI in a fresh process; a hang fails the test."""
    try:
        done = subprocess.run(
            [sys.executable, "-m", "nfdmatch", *map(str, args)],
            capture_output=True,
            text=True,
            timeout=LIMIT,
            cwd=cwd,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"nfdmatch {' '.join(map(str, args))} did not stop within {LIMIT} s")
    return done.returncode, done.stdout, done.stderr


def _free_space_header(data: bytes, collection: int) -> int:
    """Offset of the free-space object of the global heap collection at ``collection``."""
    at = collection + 16
    while True:
        index = int.from_bytes(data[at : at + 2], "little")
        size = int.from_bytes(data[at + 8 : at + 16], "little")
        if index == 0:
            return at
        at += 16 + (size + 7) // 8 * 8


@pytest.mark.parametrize("command", [("query", QUERY), ("query", QUERY, "--exhaustive"), ("index", "info")])
def test_the_damaged_heap_of_issue_34_is_a_clear_error(command, tmp_path):
    damaged = tmp_path / "hang.h5"
    shutil.copyfile(HANG, damaged)
    code, out, err = nfdmatch(*command, "--index", damaged)
    assert code == 2  # an error (issue 40's exit statuses)
    assert out == ""
    assert err.startswith(f"Error: {damaged}: corrupted nfdmatch index")
    assert "global heap collection at byte 2048" in err and "Traceback" not in err


def test_verify_names_the_damaged_heap(tmp_path):
    damaged = tmp_path / "hang.h5"
    shutil.copyfile(HANG, damaged)
    code, out, err = nfdmatch("index", "verify", "--index", damaged)
    assert code == 2  # the index cannot be opened: an error, not a list of problems
    assert "global heap collection" in out + err and "Traceback" not in err


def test_a_new_index_keeps_no_attribute_in_the_heap_and_says_so(tmp_path):
    index = tmp_path / "lib.h5"
    code, _, err = nfdmatch("index", "build", os.path.join(ROOT, "sample_curves", "library"), "--index", index)
    assert code == 0, err
    with h5py.File(index, "r") as f:
        assert f.id.get_create_plist().get_version()[0] >= 3  # checksummed metadata
        for name in f.attrs:
            tid = f.attrs.get_id(name).get_type()
            assert not (isinstance(tid, h5py.h5t.TypeStringID) and tid.is_variable_str()), name
        assert f.attrs["format"].decode() == "nfdmatch-index"
    code, out, _ = nfdmatch("index", "info", "--index", index)
    assert code == 0 and "metadata\tchecked\n" in out
    code, out, _ = nfdmatch("index", "info", "--index", FROZEN_V2)
    assert code == 0 and "metadata\tolder\n" in out
    # a query says once that an older file is read whole at each open, and how to fix it
    code, _, err = nfdmatch("query", QUERY, "--index", FROZEN_V2)
    assert code == 0 and "was written before its metadata was checked" in err and "index build" in err
    code, _, err = nfdmatch("query", QUERY, "--index", index)
    assert code == 0 and "metadata" not in err


def test_a_damaged_heap_of_ids_in_a_new_index_is_a_clear_error(tmp_path):
    index = tmp_path / "lib.h5"
    build_index([os.path.join(ROOT, "sample_curves", "library")], str(index))
    data = bytearray(index.read_bytes())
    collection = data.find(b"GCOL")
    assert collection > 0  # the ids: variable-length strings
    data[_free_space_header(data, collection) + 8 : _free_space_header(data, collection) + 16] = bytes(8)
    damaged = tmp_path / "damaged.h5"
    damaged.write_bytes(bytes(data))
    for args in (("query", QUERY), ("index", "verify")):
        code, out, err = nfdmatch(*args, "--index", damaged)
        # query cannot answer (an error, 2); verify reads on and lists the problem (1)
        assert code == (2 if args[0] == "query" else 1), err
        assert "global heap collection" in out + err and "Traceback" not in err  # verify lists on stdout


def test_a_build_rewrites_an_older_index_with_checked_metadata(tmp_path):
    folder = tmp_path / "lib"
    shutil.copytree(os.path.join(ROOT, "sample_curves", "library"), folder)
    index = tmp_path / "lib.h5"
    build_index([str(folder)], str(index))
    with h5py.File(index, "r+") as f:  # as nfdmatch wrote it before issue 34
        for name in ("format", "scale", "checksums"):
            value = f.attrs[name].decode()
            del f.attrs[name]
            f.attrs[name] = value
    with open_index(index) as idx:
        assert not idx.checked_metadata and idx.info()["metadata"] == "older"
        before = idx.ids()
    code, _, err = nfdmatch("index", "build", folder, "--index", index)
    assert code == 0, err
    assert "rewriting the index with checked metadata" in err
    with open_index(index) as idx:
        assert idx.checked_metadata and idx.ids() == before
    code, _, err = nfdmatch("index", "build", folder, "--index", index)
    assert code == 0 and "rewriting" not in err  # once


def test_a_damaged_graph_header_is_a_clear_error_for_rerank(tmp_path):
    """HDF5's checksum of /graph's object header fails when the group is opened: that is a
    corrupted index for query --rerank (found by benchmarks/fuzz_index.py --graph 10)."""
    index = tmp_path / "lib.h5"
    build_index([os.path.join(ROOT, "sample_curves", "library")], str(index), graph=10)
    with h5py.File(index, "r") as f:
        header = h5py.h5o.get_info(f["graph"].id).addr
    data = bytearray(index.read_bytes())
    data[header + 6] ^= 0x5A  # inside the header, under its checksum
    index.write_bytes(bytes(data))
    code, out, err = nfdmatch("query", QUERY, "--index", index, "--rerank")
    assert code == 2 and out == ""
    assert "corrupted nfdmatch index: cannot read /graph" in err and "Traceback" not in err
