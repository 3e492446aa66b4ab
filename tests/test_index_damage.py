"""Damaged HDF5 metadata (issue 24, item 2): a flipped byte anywhere outside the stored
values (superblock, object headers, chunk indexes, heaps) gives the same answers or a clear
error, never a different answer; a chunk that HDF5 cannot find never reads as data.

The sweeps here sample the metadata bytes of a tiny index (every byte would take minutes);
``benchmarks/fuzz_index.py --sweep`` flips every one of them."""

from __future__ import annotations

import os
import shutil

import h5py
import numpy as np
import pytest

from fuzzing import in_child, metadata_offsets, value_ranges
from oracle import random_smooth_curve

from nfdmatch import Curve, write_curves
from nfdmatch.errors import IndexFormatError
from nfdmatch.index import build_index, open_index
from conftest import run_cli

pytestmark = pytest.mark.slow  # forked children, a few hundred index reads

HERE = os.path.dirname(os.path.abspath(__file__))
FROZEN_V2 = os.path.join(HERE, "data", "index", "v2-sample.h5")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny index (6 curves, 16 samples, 3 harmonics) and two query files."""
    rng = np.random.default_rng(24)
    folder = tmp_path_factory.mktemp("tiny")
    for i in range(3):
        write_curves(folder / f"c{i}.obj", [Curve(random_smooth_curve(rng, 30, 3), id=f"c{i}-{j}") for j in range(2)])
    write_curves(folder / "q0.csv", random_smooth_curve(rng, 30, 3))
    write_curves(folder / "q1.csv", random_smooth_curve(rng, 30, 3))
    build_index([str(folder / f"c{i}.obj") for i in range(3)], str(folder / "tiny.h5"), samples=16, harmonics=3)
    return folder


def _answers(index, queries) -> tuple:
    """(exit code, stdout) of each query, and of `index verify`; a traceback is an answer too."""
    out = []
    for q in queries:
        code, stdout, stderr = run_cli("query", q, "--index", index, "--top", 3, "--format", "csv")
        assert code == 0 or (code == 2 and stderr.startswith("Error: ")), stderr
        out.append((code, stdout))
    code, stdout, stderr = run_cli("index", "verify", "--index", index)
    assert code in (0, 1, 2), stderr  # sound, problems found, not an index at all
    out.append((code, None))
    return tuple(out)


def _sweep(intact, queries, tmp_path, tries: int, seed: int) -> dict:
    """Flip ``tries`` metadata bytes of ``intact`` (spread evenly, a random XOR each), each in a
    fresh copy read in a forked child; every answer must equal the intact file's or be a clear
    error. Returns the outcome counts."""
    with open(intact, "rb") as fh:
        data = fh.read()
    meta = metadata_offsets(len(data), value_ranges(intact))
    status, ref = in_child(lambda: _answers(intact, queries), 120)
    assert status == "ok" and all(code == 0 for code, _ in ref), (status, ref)
    rng = np.random.default_rng(seed)
    picks = [meta[int(i)] for i in np.linspace(0, len(meta) - 1, min(tries, len(meta)))]
    damaged = str(tmp_path / "damaged.h5")
    counts = {"same": 0, "refused": 0}
    for at in picks:
        mutant = bytearray(data)
        mutant[at] ^= int(rng.integers(1, 256))
        with open(damaged, "wb") as fh:
            fh.write(mutant)
        status, got = in_child(lambda: _answers(damaged, queries), 120)
        assert status == "ok", (at, status, got)  # no crash, no hang, no traceback
        for (_, rout), (code, out) in zip(ref[:-1], got[:-1]):
            assert code == 2 or out == rout, f"byte {at}: a different answer, exit 0"
        counts["same" if got[:-1] == ref[:-1] else "refused"] += 1
    return counts


def test_flipped_metadata_bytes_of_a_new_index_give_the_same_answer_or_a_clear_error(tiny, tmp_path):
    counts = _sweep(str(tiny / "tiny.h5"), [tiny / "q0.csv", tiny / "q1.csv"], tmp_path, 100, 1)
    assert counts["refused"] > 0 and counts["same"] > 0, counts


def test_flipped_metadata_bytes_of_a_frozen_format_2_index_give_the_same_answer_or_a_clear_error(tiny, tmp_path):
    """The frozen file has HDF5's older structures (chunk indexes with stored offsets, no
    metadata checksums): the chunk-index check on open is what holds here."""
    index = tmp_path / "v2.h5"
    shutil.copyfile(FROZEN_V2, index)
    counts = _sweep(str(index), [tiny / "q0.csv"], tmp_path, 100, 2)
    assert counts["refused"] > 0 and counts["same"] > 0, counts


def _chunk_btree_keys(data: bytes):
    """``(offset, entries)`` of every
    version-1 B-tree leaf of chunked raw data: ``TREE``, type 1, level 0 (HDF5 file format,
    "Version 1 B-trees": a 24-byte header, then keys of 4 + 4 + 8 (rank + 1) bytes between
    8-byte child addresses)."""
    out = []
    at = data.find(b"TREE")
    while at >= 0:
        if data[at + 4] == 1 and data[at + 5] == 0:
            entries = int.from_bytes(data[at + 6 : at + 8], "little")
            out.append((at, entries))
        at = data.find(b"TREE", at + 4)
    return out


def test_a_chunk_moved_by_a_damaged_chunk_index_is_refused_on_open(tmp_path):
    """Issue 24, item 2 (byte 85,206 of the sample index, XOR 0xfb): a flipped byte in a chunk's
    stored offset moved the chunk; HDF5 read the place it left as the fill value (zeros, which
    pass every check) and `query` answered differently. Every such move in the frozen file's
    chunk indexes is now refused when the index is opened."""
    with open(FROZEN_V2, "rb") as fh:
        data = fh.read()
    nodes = _chunk_btree_keys(data)
    assert nodes
    moved = 0
    for at, entries in nodes:
        for rank in (1, 2, 3):  # the key size depends on the dataset's rank: try each
            key = 8 + 8 * (rank + 1)
            for i in range(entries):
                first = at + 24 + i * (key + 8) + 8  # key i's offset along the rows
                if first + 8 > len(data) or int.from_bytes(data[first : first + 8], "little") % 4:
                    continue
                mutant = bytearray(data)
                mutant[first + 1] ^= 0x40  # the rows' offset moved by 16,384 rows
                damaged = tmp_path / "moved.h5"
                damaged.write_bytes(bytes(mutant))
                try:
                    with open_index(damaged) as idx:
                        idx.ids(0, None)
                        for _, _rows in idx.iter_chunks():
                            pass
                except IndexFormatError:
                    moved += 1
                    continue
                except OSError:  # not a key after all (another rank): HDF5 cannot read it
                    continue
                raise AssertionError(f"a chunk moved at byte {first + 1} was read as data")
    assert moved > 0


def test_a_new_index_fills_its_float_datasets_with_nan(tiny):
    """New files give every float dataset a NaN fill value: a chunk HDF5 cannot find reads as
    NaN, which every reader refuses, not as zeros."""
    with h5py.File(tiny / "tiny.h5", "r") as h5:
        for name in ("curves/coefficients", "curves/inv_sv", "search/coefficients", "search/features"):
            fill = h5[name].fillvalue
            assert np.isnan(fill.real if np.iscomplexobj(fill) else fill), name
