"""The HDF5 index (nfdmatch.index): the frozen format-1 file, incremental builds, bad files,
parameters, dry runs, crash safety (kill -9), readers during builds, the lock, bad index files."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import random
import shutil
import subprocess
import sys
import threading
import time

import h5py
import numpy as np
import pytest

from oracle import random_smooth_curve

import nfdmatch.index as nindex
from nfdmatch.index import lock as index_lock
from nfdmatch import Curve, descriptors, read_curves, write_curves
from nfdmatch.errors import (
    IndexFormatError,
    IndexLockedError,
    InputError,
    NfdError,
    ParameterError,
    ReadError,
    ShrinkRefusedError,
)
from nfdmatch.index import (
    FORMAT_VERSION,
    INDEX_FORMAT,
    BuildReport,
    FileRecord,
    build_index,
    default_index_path,
    open_index,
)
from nfdmatch.matching import invariants

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
FROZEN = os.path.join(HERE, "data", "index", "v1-sample.h5")


def _sha256(path) -> str:
    """SHA-256 of a file's bytes, as the index stores it (docs/index-format.md)."""
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


# --------------------------------------------------------------------------- helpers


def _curves(rng, n, vertices=(40, 120)):
    return [random_smooth_curve(rng, int(rng.integers(*vertices)), 4) for _ in range(n)]


def _library(folder, rng):
    """5 files, 8 curves: 2 single-curve CSV, a 3-curve OBJ, a 2-curve VTP, a 1-curve OBJ."""
    (folder / "sub").mkdir(parents=True)
    write_curves(folder / "a.csv", _curves(rng, 1)[0])
    write_curves(folder / "b.csv", _curves(rng, 1)[0])
    write_curves(folder / "sub" / "multi.obj", _curves(rng, 3))
    write_curves(folder / "sub" / "two.vtp", _curves(rng, 2))
    write_curves(folder / "single.obj", _curves(rng, 1))
    return folder


def _paths(folder):
    return sorted(
        os.path.normpath(os.path.join(folder, p))
        for p in ("a.csv", "b.csv", "sub/multi.obj", "sub/two.vtp", "single.obj")
    )


def _keys(folder):
    """The stored paths of the _library files for an index in the folder above it."""
    return [os.path.relpath(p, os.path.dirname(folder)) for p in _paths(folder)]


@pytest.fixture
def lib(tmp_path, rng):
    return _library(tmp_path / "lib", rng)


def _snapshot(path):
    with open_index(path) as idx:
        return {
            "ids": idx.ids(),
            "files": idx.files(),
            "rows": idx.read_rows(0, idx.n_curves),
            "params": (idx.samples, idx.harmonics, idx.scale_mode),
            "created": idx.created,
            "updated": idx.updated,
            "n": idx.n_curves,
        }


def _assert_rows_equal(a, b):
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def _raw_datasets(path):
    out = {}
    with h5py.File(path, "r", locking=False) as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[...]) if isinstance(obj, h5py.Dataset) else None)
        attrs = {k: f.attrs[k] for k in f.attrs if k not in ("created", "updated")}
    return out, attrs


def _digest(a):
    a = np.ascontiguousarray(a)
    if a.dtype.kind in "cfiu":
        a = a.astype("<" + a.dtype.str[1:])
    return hashlib.sha256(a.tobytes()).hexdigest()


def _same_size_edit(path):
    """Change one digit of a CSV file: same size, other contents, still a valid curve."""
    data = path.read_bytes()
    lines = data.split(b"\n")
    k = lines[1].index(b".") + 3
    digit = lines[1][k : k + 1]
    lines[1] = lines[1][:k] + (b"5" if digit != b"5" else b"6") + lines[1][k + 1 :]
    new = b"\n".join(lines)
    assert len(new) == len(data) and new != data
    path.write_bytes(new)


# --------------------------------------------------------------------------- the frozen v1 file

FROZEN_IDS = [
    "sample_curves/library/circle.tsv",
    "sample_curves/library/lissajous-family.obj#0",
    "sample_curves/library/lissajous-family.obj#1",
    "sample_curves/library/lissajous-family.obj#2",
    "sample_curves/library/superellipses.vtp#0",
    "sample_curves/library/superellipses.vtp#1",
    "sample_curves/library/trefoil.csv",
]
FROZEN_FILES = [
    FileRecord(
        "sample_curves/library/circle.tsv",
        3856,
        1795441386657119773,
        "71d6f8c8721c5fff65c7ae384a0835d1ab081dd7b28ac7182c2567add948cff1",
        "ok",
        "",
        0,
        1,
    ),
    FileRecord(
        "sample_curves/library/lissajous-family.obj",
        104152,
        1795441386652753294,
        "db9fab8a4a0f6e290f403af136ebc77a98ce4a13c97ca732041b21fd99cece58",
        "ok",
        "",
        1,
        3,
    ),
    FileRecord(
        "sample_curves/library/superellipses.vtp",
        7880,
        1795441386657119773,
        "3ec1b033fb9146f301c1454b80e315186b39d678d0d0e279c40027289a3c3e99",
        "ok",
        "",
        4,
        2,
    ),
    FileRecord(
        "sample_curves/library/trefoil.csv",
        23281,
        1795441386409285493,
        "9cb26df2948dfa6dc0d45fe3bc975a462d2f17340988de7e9868493a03245010",
        "ok",
        "",
        6,
        1,
    ),
    FileRecord(
        "tests/data/index/bad.csv",
        27,
        1795443109321567493,
        "375c163f17b8271b2e60771929baeb041fcdeb8a551453da4a3c2d31de59c3cd",
        "failed",
        "tests/data/index/bad.csv: line 3: not a number: 'zero'",
        7,
        0,
    ),
]
# sha256 of each /curves dataset's values in little-endian storage dtypes
FROZEN_DIGESTS = {
    "coefficients": "f23239a2576cb0e8fab1f77e63d47f34dd155316c068aea7ec05682845c8a56f",
    "rotation": "1b1b7cdd2f37eff5d6f08036a6c6b7b353218383a1ce381cc1353b483383af70",
    "centroid": "6bb5ad033de4e0a4a0c99135090b13dd867e723a270b94a2951d8c92b481951c",
    "scale": "b5f55f967d73fb9b5726043abd1e51bef6592f00d67d977d6ef9c87d43369154",
    "plane_degenerate": "837885c8f8091aeaeb9ec3c3f85a6ff470a415e610b8ba3e49f9b33c9cf9d619",
    "inv_norm": "ff30345ea4cb7952d1fe1819ea2a2398a90b0465f1cee93b0853b65d2cacda0f",
    "inv_sv": "fe2ebcfcd3f6ab590dfd4af819e97931da5a49bef8df4a508d5a4b51e5988519",
    "inv_block": "830af7e5da18b353fdc6f1f4da0dd9983064ab808a89f8bef18f30327bd82931",
    "file": "b2fc5b74e1d0ddd549d6a267559d30bea5146adce22d2cecea8d34e013c50cfb",
}


def test_frozen_v1_index_reads_forever():
    with open_index(FROZEN) as idx:
        assert (idx.format_version, idx.nfdmatch_version) == (1, "0.1.0")
        assert (idx.samples, idx.harmonics, idx.scale_mode) == (32, 4, "rms")
        assert idx.scale == idx.scale_mode  # the deprecated name
        assert (idx.created, idx.updated) == ("2026-01-01T00:00:00Z", "2026-01-01T00:00:00Z")
        assert (idx.n_curves, idx.n_files) == (7, 5)
        assert idx.ids() == FROZEN_IDS
        assert idx.ids(2, 4) == FROZEN_IDS[2:4]
        assert idx.ids_at([6, 0, 6, 3]) == [FROZEN_IDS[6], FROZEN_IDS[0], FROZEN_IDS[6], FROZEN_IDS[3]]
        assert idx.files() == FROZEN_FILES
        rows = idx.read_rows(0, 7)
        K = 4
        expected = {
            "coefficients": ((7, K, 3), np.complex128),
            "inv_norm": ((7, K), np.float64),
            "inv_sv": ((7, 2 * K), np.float64),
            "inv_block": ((7, 3), np.float64),
            "centroid": ((7, 3), np.float64),
            "scale": ((7,), np.float64),
            "rotation": ((7, 3, 3), np.float64),
            "plane_degenerate": ((7,), np.bool_),
        }
        for key, (shape, dtype) in expected.items():
            assert rows[key].shape == shape and rows[key].dtype == dtype, key
        np.testing.assert_array_equal(rows["file"], [0, 1, 1, 1, 2, 2, 3])
        # exact stored values (they are float32/complex64 on disk, upcast exactly)
        f32 = np.float32
        assert rows["coefficients"][0, 0, 0] == complex(f32(0.500003457069397), f32(1.299552676028385e-15))
        assert rows["coefficients"][0, 0, 1] == complex(f32(1.2117691459902647e-15), f32(-0.499996542930603))
        assert rows["coefficients"][0, 2, 0].real == np.float32(6.215435860212892e-06)
        assert rows["scale"].tolist() == [
            0.9995955124763377,
            1.161999396947542,
            1.170109796751126,
            1.1584850780453646,
            1.121160597667193,
            1.6762282668972879,
            2.36950560781353,
        ]
        assert rows["centroid"][1].tolist() == [7.223158161005772e-16, -0.015161576506931203, 4.144878884559944e-16]
        assert rows["inv_block"][2].tolist() == [0.6022557020187378, 0.5785418152809143, 0.545386016368866]
        assert not rows["plane_degenerate"].any()
        # the lower-bound features are those of the stored coefficients
        inv = invariants(rows["coefficients"])
        for key in ("norm", "sv", "block"):
            np.testing.assert_allclose(rows[f"inv_{key}"], inv[key].reshape(7, -1), rtol=1e-6, atol=1e-7)
        # chunked reading covers every row in order
        chunks = list(idx.iter_chunks(rows=3))
        assert [s for s, _ in chunks] == [0, 3, 6]
        np.testing.assert_array_equal(np.concatenate([c["coefficients"] for _, c in chunks]), rows["coefficients"])
        info = idx.info()
        assert info["files"] == 5 and info["curves"] == 7
        assert info["failed"] == [
            {"path": "tests/data/index/bad.csv", "error": "tests/data/index/bad.csv: line 3: not a number: 'zero'"}
        ]
        assert (info["format"], info["format_version"], info["samples"], info["harmonics"], info["scale"]) == (
            INDEX_FORMAT,
            1,
            32,
            4,
            "rms",
        )
        assert info["size_bytes"] == os.path.getsize(FROZEN)
    with h5py.File(FROZEN, "r", locking=False) as f:
        for key, digest in FROZEN_DIGESTS.items():
            assert _digest(f["curves"][key][...]) == digest, key
        assert f["curves/coefficients"].dtype == np.complex64


FROZEN_V2 = os.path.join(HERE, "data", "index", "v2-sample.h5")


def test_frozen_v2_index_reads_forever():
    """Format 2 = format 1's tables (same sources, same values) plus /search."""
    with open_index(FROZEN_V2) as idx, open_index(FROZEN) as v1:
        assert (idx.format_version, idx.samples, idx.harmonics, idx.scale_mode) == (2, 32, 4, "rms")
        assert (idx.n_curves, idx.n_files) == (7, 5)
        assert idx.ids() == FROZEN_IDS
        # the same files (the modification times are the clone's that froze each file)
        assert [dataclasses.replace(r, mtime_ns=0) for r in idx.files()] == [
            dataclasses.replace(r, mtime_ns=0) for r in FROZEN_FILES
        ]
        rows, old = idx.read_rows(0, 7), v1.read_rows(0, 7)
        for key in rows:  # v1 was written before a rounding-level fix of the plane rotation
            np.testing.assert_allclose(rows[key], old[key], rtol=1e-5, atol=1e-5, err_msg=key)
        table = idx.search_table()
        assert table.n_cells == 4
        np.testing.assert_array_equal(table.start, [0, 2, 4, 5, 7])
        got_rows, features, sqnorm, coefficients = table.cell_rows(np.arange(4))
        np.testing.assert_array_equal(coefficients, rows["coefficients"][got_rows].astype(np.complex64))
        np.testing.assert_array_equal(got_rows, [1, 2, 3, 6, 5, 0, 4])
        np.testing.assert_array_equal(
            features, np.concatenate([rows["inv_sv"], rows["inv_block"]], axis=1)[got_rows].astype(np.float32)
        )
        # every member within its cell's radius: what the search relies on
        for c in range(4):
            a, b = table.start[c], table.start[c + 1]
            X = features[a:b].astype(np.float64)
            assert np.all(np.linalg.norm(X[:, :8] - table.centre[c, :8], axis=1) <= table.radius[c, 0])
            assert np.all(np.linalg.norm(X[:, 8:] - table.centre[c, 8:], axis=1) <= table.radius[c, 1])
    with h5py.File(FROZEN_V2, "r", locking=False) as f:
        assert int(f["search"].attrs["cells"]) == 4
        # the checksums of docs/index-format.md: Fletcher-32 on the numbers, CRC-32 blocks of the strings
        assert f.attrs["checksums"] == "fletcher32+crc32"  # variable length in the frozen file
        assert f["curves/coefficients"].fletcher32 and f["search/features"].fletcher32
        assert f["curves/id_crc32"][...].tolist() == [zlib_crc32_of(FROZEN_IDS)]
        for key, digest in FROZEN_V2_SEARCH_DIGESTS.items():
            assert _digest(f["search"][key][...]) == digest, key
        for key, digest in FROZEN_V2_CURVE_DIGESTS.items():
            assert _digest(f["curves"][key][...]) == digest, key


FROZEN_V3 = os.path.join(HERE, "data", "index", "v3-sample.h5")
FROZEN_V3_STATISTICS_DIGEST = "97e0e9da76e4b286b985e3db514c1925a229139d9a75fd9748386289f123cdfb"


def test_frozen_v3_index_reads_forever():
    """Format 3 = format 2 plus /curves/statistics: the same rows and cells as the v2 file,
    and the elastic stage's shape statistics of the stored coefficients."""
    from nfdmatch.matching.statistics import LENGTH, curve_statistics

    with open_index(FROZEN_V3) as idx, open_index(FROZEN_V2) as v2:
        assert (idx.format_version, idx.samples, idx.harmonics, idx.scale_mode) == (3, 32, 4, "rms")
        assert (idx.n_curves, idx.n_files) == (7, 5) and idx.ids() == FROZEN_IDS
        rows, old = idx.read_rows(0, 7), v2.read_rows(0, 7)
        for key in old:  # the same computation, to rounding (BLAS) where a value is ~0
            np.testing.assert_allclose(rows[key], old[key], rtol=1e-5, atol=1e-6, err_msg=key)
        stored = idx.statistics_at(np.arange(7))
        assert stored.shape == (7, LENGTH)
        # format 2 has none stored: computed on read from the same coefficients
        np.testing.assert_allclose(v2.statistics_at(np.arange(7)), stored, rtol=1e-5, atol=1e-6)
        want = curve_statistics(rows["coefficients"].astype(np.complex64).astype(np.complex128))
        np.testing.assert_allclose(stored, want, rtol=1e-5, atol=1e-6)
    with h5py.File(FROZEN_V3, "r", locking=False) as f:
        assert f["curves/statistics"].dtype == np.float32 and f["curves/statistics"].fletcher32
        assert _digest(f["curves/statistics"][...]) == FROZEN_V3_STATISTICS_DIGEST


def test_build_into_a_format_2_index_upgrades_it_with_statistics(tmp_path, monkeypatch):
    """A format-2 index is rewritten as format 3: the rows copied, their statistics computed
    from the stored coefficients (what verify checks)."""
    from nfdmatch.index.verify import verify_index

    monkeypatch.chdir(REPO)
    target = tmp_path / "old.h5"
    shutil.copyfile(FROZEN_V2, target)
    with open_index(FROZEN_V2) as v2:
        sources = sorted({r.path for r in v2.files()})
        unchanged_sha = {r.path: r.sha256 for r in v2.files()}
    for path in sources:
        if os.path.exists(path) and _sha256(path) != unchanged_sha[path]:
            pytest.skip(f"{path} changed since the frozen index was made")
    report = build_index(sources, str(target), jobs=1)
    assert report.written and any("upgrading the index from format 2 to 3" in n for n in report.notices)
    with open_index(target) as idx, open_index(FROZEN_V3) as v3:
        assert idx.format_version == 3
        np.testing.assert_allclose(
            idx.statistics_at(np.arange(7)), v3.statistics_at(np.arange(7)), rtol=1e-5, atol=1e-6
        )
    assert verify_index(str(target)).ok


def zlib_crc32_of(strings):
    import zlib

    return zlib.crc32(b"".join(v.encode("utf-8") + b"\0" for v in strings))


FROZEN_V2_SEARCH_DIGESTS = {
    "cell_start": "fa0bdd096a3862cdea58d24219e92c5271eed19b31fa1fdd93fed9987ba321e6",
    "centre": "456187140894a448c40344c188141598159dc5b79fe416e6ee264611ffc7eb48",
    "features": "0c7a15a0fe719b2ecbece26a435a6781ab0685d9f56d985fe476ad3ecfeab3ba",
    "coefficients": "2255ed682828107810879712c7c1c796f07b9bb88b0cddcd731e93afa8d6be78",
    "radius": "4b5d0fb900a033448c6ae8a1cd9aa4e9473b29cbf48ed19e8c1831f4cc287cee",
    "row": "758cc90cb2b0e29822cf95cf373e1988fb076369ee42b69421b35d602e45e18a",
    "sqnorm": "1bd887b4fed687f562923a946adb7f2db60d87a33d606a961c492c292c94ed86",
}
FROZEN_V2_CURVE_DIGESTS = {
    "centroid": "6bb5ad033de4e0a4a0c99135090b13dd867e723a270b94a2951d8c92b481951c",
    "coefficients": "be0cf53047e6990035948a8d141f2e300705027e2df0ce3c30a4c0fe379f3b4d",
    "file": "b2fc5b74e1d0ddd549d6a267559d30bea5146adce22d2cecea8d34e013c50cfb",
    "inv_block": "830af7e5da18b353fdc6f1f4da0dd9983064ab808a89f8bef18f30327bd82931",
    "inv_norm": "ff30345ea4cb7952d1fe1819ea2a2398a90b0465f1cee93b0853b65d2cacda0f",
    "inv_sv": "1ebb3a54803c22c2d20f1ccf190067c5f62ef0f42a81cf8725b1c76a882b9c6e",
    "plane_degenerate": "837885c8f8091aeaeb9ec3c3f85a6ff470a415e610b8ba3e49f9b33c9cf9d619",
    "rotation": "a7281694ec5064f9ce6b93af49a7df5124176c2bdaeab008d4a6daa06caa6cf3",
    "scale": "aee6480970e5bdc8ca659e47b3bb5893af09e4302f8937962ca2470b9b030a43",
}


@pytest.mark.parametrize("frozen", [FROZEN, FROZEN_V2], ids=["v1", "v2"])
def test_frozen_indexes_answer_queries_as_the_exhaustive_search(frozen):
    from nfdmatch.search import search_index

    queries = [Curve(random_smooth_curve(np.random.default_rng(i), 100), id=f"q{i}") for i in range(3)]
    with open_index(frozen) as idx:
        pruned, _ = search_index(idx, queries, k=3)
        full, _ = search_index(idx, queries, k=3, prune=False)
    assert [[r.id for r in p] for p in pruned] == [[r.id for r in f] for f in full]


def test_build_into_a_format_1_index_upgrades_it(tmp_path, monkeypatch):
    """Nothing changed in the sources, yet the build rewrites a format-1 index in today's
    format (search cells, shape statistics), with the same rows, and says so."""
    monkeypatch.chdir(REPO)
    target = tmp_path / "old.h5"
    shutil.copyfile(FROZEN, target)
    with open_index(FROZEN) as v1:
        sources = sorted({r.path for r in v1.files()})
        before = v1.read_rows(0, v1.n_curves)
        unchanged_sha = {r.path: r.sha256 for r in v1.files()}
    for path in sources:
        if os.path.exists(path) and _sha256(path) != unchanged_sha[path]:
            pytest.skip(f"{path} changed since the frozen index was made")
    report = build_index(sources, str(target), jobs=1)
    assert report.written and any(f"upgrading the index from format 1 to {FORMAT_VERSION}" in n for n in report.notices)
    with open_index(target) as idx:
        assert idx.format_version == FORMAT_VERSION and idx.n_curves == 7
        after = idx.read_rows(0, 7)
        np.testing.assert_array_equal(after["coefficients"], before["coefficients"])
        assert idx.search_table().n_cells >= 1
    again = build_index(sources, str(target), jobs=1)
    assert not again.written  # today's format now: nothing to do


def test_frozen_rows_match_the_sample_curves_to_complex64():
    """While the sample curves exist unchanged, the frozen descriptors are theirs."""
    with open_index(FROZEN) as idx:
        rows = idx.read_rows(0, idx.n_curves)
        ids = idx.ids()
        files = idx.files()
    for record in files:
        path = os.path.join(REPO, record.path)
        if record.status != "ok" or not os.path.exists(path) or _sha256(path) != record.sha256:
            continue
        for curve in read_curves(path):
            row = ids.index(curve.id.replace(REPO + os.sep, ""))
            d = descriptors(curve, samples=32, harmonics=4, scale="rms")
            # 1e-6, not complex64's 2e-7: the frozen rows of planar clockwise curves (normal at
            # -z) carry the rounding of the plane rotation before it was made stable
            np.testing.assert_allclose(rows["coefficients"][row], d.coefficients, atol=1e-6)


# --------------------------------------------------------------------------- building


def test_build_ids_file_table_and_descriptors(lib, tmp_path):
    idx_path = tmp_path / "idx.h5"
    report = build_index([str(lib)], idx_path, jobs=1)
    assert isinstance(report, BuildReport)
    assert (report.added, report.updated, report.removed, report.unchanged, report.failed) == (5, 0, 0, 0, 0)
    assert report.curves == 8 and report.written and not report.dry_run
    assert report.changes == [("added", p) for p in _keys(lib)]  # relative to the index's folder
    with open_index(idx_path) as idx:
        assert (idx.samples, idx.harmonics, idx.scale_mode, idx.format_version) == (128, 16, "rms", FORMAT_VERSION)
        assert idx.created == idx.updated and idx.created.endswith("Z")
        files = idx.files()
        assert [f.path for f in files] == _keys(lib) and idx.sources() == (["lib"], None)
        ids = idx.ids()
        rows = idx.read_rows(0, idx.n_curves)
        expected_ids = []
        for f in files:
            path = str(tmp_path / f.path)
            st = os.stat(path)
            assert (f.size, f.mtime_ns, f.status, f.error) == (st.st_size, st.st_mtime_ns, "ok", "")
            assert f.sha256 == hashlib.sha256(open(path, "rb").read()).hexdigest()
            assert f.curve_start == len(expected_ids)
            curves = read_curves(path)
            assert f.curve_count == len(curves)
            expected_ids += [f.path] if len(curves) == 1 else [f"{f.path}#{i}" for i in range(len(curves))]
        assert ids == expected_ids
        assert sum(1 for i in ids if i.endswith(("multi.obj#0", "multi.obj#1", "multi.obj#2"))) == 3
        assert "lib/single.obj" in ids and "lib/a.csv" in ids
        np.testing.assert_array_equal(rows["file"], np.repeat(np.arange(5), [f.curve_count for f in files]))
        curves = [c for f in files for c in read_curves(str(tmp_path / f.path))]
        for i, c in enumerate(curves):
            d = descriptors(c)
            scale = np.abs(d.coefficients).max()
            np.testing.assert_allclose(rows["coefficients"][i], d.coefficients, atol=1e-6 * scale, rtol=0)
            np.testing.assert_allclose(rows["rotation"][i], d.rotation, atol=1e-6)
            np.testing.assert_allclose(rows["centroid"][i], d.centroid, rtol=1e-9, atol=1e-12)
            assert rows["scale"][i] == pytest.approx(d.scale, rel=1e-9)
            assert rows["plane_degenerate"][i] == d.plane_degenerate
        inv = invariants(rows["coefficients"])
        for key in ("norm", "sv", "block"):
            np.testing.assert_allclose(rows[f"inv_{key}"], inv[key].reshape(len(ids), -1), rtol=1e-6, atol=1e-7)
        assert idx.ids_at([7, 0]) == [ids[7], ids[0]]
        info = idx.info()
        assert (info["files"], info["curves"], info["failed"]) == (5, 8, [])
        assert isinstance(info["files"], int) and isinstance(info["curves"], int)


def test_unchanged_rerun_reads_nothing(lib, tmp_path, reads):
    idx_path = tmp_path / "idx.h5"
    build_index([str(lib)], idx_path, jobs=1)
    before = _snapshot(idx_path)
    os.utime(idx_path, ns=(1, 1))  # as if built long ago
    inode = os.stat(idx_path).st_ino
    reads.clear()
    # contents changed, but size and mtime restored: by design not even opened
    a = lib / "a.csv"
    st = os.stat(a)
    _same_size_edit(a)
    os.utime(a, ns=(st.st_atime_ns, st.st_mtime_ns))
    report = build_index([str(lib)], idx_path, jobs=1)
    assert reads == []
    assert (report.added, report.updated, report.removed, report.unchanged, report.failed) == (0, 0, 0, 5, 0)
    assert report.curves == 8 and not report.written
    # not rewritten (the same file), but newer than its sources: Make sees the build ran
    assert os.stat(idx_path).st_ino == inode and os.stat(idx_path).st_mtime_ns > os.stat(a).st_mtime_ns
    after = _snapshot(idx_path)
    assert after["ids"] == before["ids"] and after["files"] == before["files"]
    _assert_rows_equal(after["rows"], before["rows"])


def test_touched_file_is_hashed_not_recomputed(lib, tmp_path, reads):
    idx_path = tmp_path / "idx.h5"
    build_index([str(lib)], idx_path, jobs=1)
    before = _snapshot(idx_path)
    reads.clear()
    target = lib / "sub" / "multi.obj"
    st = os.stat(target)
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns + 7_000_000_000))
    report = build_index([str(lib)], idx_path, jobs=1)
    assert reads == []
    assert (report.added, report.updated, report.removed, report.unchanged, report.failed) == (0, 0, 0, 5, 0)
    assert report.written  # the new mtime is recorded
    after = _snapshot(idx_path)
    _assert_rows_equal(after["rows"], before["rows"])
    assert after["ids"] == before["ids"] and after["created"] == before["created"]
    record = next(f for f in after["files"] if f.path == "lib/sub/multi.obj")
    assert record.mtime_ns == st.st_mtime_ns + 7_000_000_000
    reads.clear()
    assert build_index([str(lib)], idx_path, jobs=1).written is False
    assert reads == []


def test_modified_deleted_added_renamed(lib, tmp_path, reads, rng):
    idx_path = tmp_path / "idx.h5"
    build_index([str(lib)], idx_path, jobs=1)
    before = _snapshot(idx_path)
    a, b, multi = str(lib / "a.csv"), str(lib / "b.csv"), str(lib / "sub" / "multi.obj")
    key = {p: os.path.relpath(p, tmp_path) for p in (a, b, multi)}

    # modified: new contents (a 4-curve file now)
    write_curves(multi, _curves(rng, 4))
    reads.clear()
    report = build_index([str(lib)], idx_path, jobs=1)
    assert reads == [multi]
    assert (report.added, report.updated, report.removed, report.unchanged) == (0, 1, 0, 4)
    assert ("updated", key[multi]) in report.changes and report.curves == 9
    after = _snapshot(idx_path)
    assert [i for i in after["ids"] if i.startswith(key[multi])] == [f"{key[multi]}#{k}" for k in range(4)]
    keep = [i for i, x in enumerate(before["ids"]) if not x.startswith(key[multi])]
    keep_after = [after["ids"].index(before["ids"][i]) for i in keep]
    np.testing.assert_array_equal(after["rows"]["coefficients"][keep_after], before["rows"]["coefficients"][keep])

    # deleted
    os.remove(b)
    reads.clear()
    report = build_index([str(lib)], idx_path, jobs=1)
    assert reads == [] and (report.removed, report.unchanged, report.curves) == (1, 4, 8)
    assert report.changes[1] == ("removed", key[b])
    assert key[b] not in _snapshot(idx_path)["ids"]

    # added
    new = str(lib / "sub" / "new.csv")
    write_curves(new, _curves(rng, 1)[0])
    reads.clear()
    report = build_index([str(lib)], idx_path, jobs=1)
    assert reads == [new] and (report.added, report.unchanged, report.curves) == (1, 4, 9)

    # renamed = removed + added
    renamed = str(lib / "z-renamed.csv")
    os.rename(a, renamed)
    report = build_index([str(lib)], idx_path, jobs=1)
    assert (report.added, report.removed, report.unchanged) == (1, 1, 4)
    assert ("removed", key[a]) in report.changes and ("added", "lib/z-renamed.csv") in report.changes
    snap = _snapshot(idx_path)
    assert "lib/z-renamed.csv" in snap["ids"] and key[a] not in snap["ids"]
    starts = [f.curve_start for f in snap["files"]]
    counts = [f.curve_count for f in snap["files"]]
    assert starts == list(np.concatenate([[0], np.cumsum(counts)[:-1]])) and sum(counts) == snap["n"]


def test_bad_files_are_recorded_and_the_rest_indexed(tmp_path, rng, reads):
    folder = tmp_path / "mixed"
    folder.mkdir()
    write_curves(folder / "good.csv", _curves(rng, 1)[0])
    write_curves(folder / "good.obj", _curves(rng, 3))
    (folder / "nan.csv").write_text("x,y,z\n0,0,0\n1,nan,0\n0,1,0\n")
    (folder / "empty.csv").write_bytes(b"")
    (folder / "garbage.vtp").write_bytes(bytes(rng.integers(0, 256, 3000, dtype=np.uint8)))
    (folder / "two_points.csv").write_text("0 0 0\n1 1 1\n")
    (folder / ".hidden.csv").write_text("junk\n")
    (folder / "notes.md").write_text("not a curve\n")
    explicit = tmp_path / "curve.dat"  # given explicitly: unknown extension
    write_curves(explicit, _curves(rng, 1)[0], format="csv")
    idx_path = tmp_path / "idx.h5"
    report = build_index([str(folder), str(explicit)], idx_path, jobs=1)
    bad = sorted(str(folder / n) for n in ("nan.csv", "empty.csv", "garbage.vtp", "two_points.csv")) + [str(explicit)]
    assert (report.added, report.failed, report.curves) == (2, 5, 4)
    assert report.written
    assert sorted(p for p, _ in report.failures) == sorted(bad)
    messages = dict(report.failures)
    for path, message in messages.items():
        assert message.startswith(path + ":"), message
    assert "line 3" in messages[str(folder / "nan.csv")]
    assert "unknown file extension" in messages[str(explicit)]
    with open_index(idx_path) as idx:  # stored relative to the index's folder
        files = {str(tmp_path / f.path): f for f in idx.files()}
        assert set(files) == set(bad) | {str(folder / "good.csv"), str(folder / "good.obj")}
        for path in bad:
            assert (files[path].status, files[path].curve_count, files[path].error) == ("failed", 0, messages[path])
        assert sorted(str(tmp_path / x["path"]) for x in idx.info()["failed"]) == sorted(bad)
        assert idx.ids() == ["mixed/good.csv"] + [f"mixed/good.obj#{k}" for k in range(3)]

    # failed files unchanged since last time stay failed without being read again
    reads.clear()
    report = build_index([str(folder), str(explicit)], idx_path, jobs=1)
    assert reads == []
    assert (report.unchanged, report.failed, report.added, report.updated) == (2, 5, 0, 0)
    assert dict(report.failures) == messages and not report.written

    # a fixed file is retried and indexed
    write_curves(folder / "nan.csv", _curves(rng, 1)[0])
    reads.clear()
    report = build_index([str(folder), str(explicit)], idx_path, jobs=1)
    assert reads == [str(folder / "nan.csv")]
    assert (report.updated, report.failed, report.curves) == (1, 4, 5)


@pytest.mark.parametrize("where", ["reader", "bulk path"])
def test_unexpected_worker_exception_becomes_a_failure(lib, tmp_path, monkeypatch, where):
    real = nindex.pool.read_curves
    real_fast = nindex.pool._fast_points
    victim = str(lib / "b.csv")

    def flaky(path, format=None):
        if str(path) == victim:
            raise RuntimeError("boom")
        return real(path, format=format)

    def flaky_fast(path, data, input_format):
        if str(path) == victim:
            if where == "bulk path":
                raise RuntimeError("boom")
            return None  # declined: read_curves reads it
        return real_fast(path, data, input_format)

    monkeypatch.setattr(nindex.pool, "read_curves", flaky)
    monkeypatch.setattr(nindex.pool, "_fast_points", flaky_fast)
    report = build_index([str(lib)], tmp_path / "idx.h5", jobs=1)
    assert (report.added, report.failed, report.curves) == (4, 1, 7)
    assert report.failures == [(victim, f"{victim}: unexpected error: RuntimeError: boom")]


def test_parameters_none_keep_the_index_and_changes_recompute(lib, tmp_path, reads):
    idx_path = tmp_path / "idx.h5"
    build_index([str(lib)], idx_path, samples=64, harmonics=8, scale="a1", jobs=1)
    reads.clear()
    report = build_index([str(lib)], idx_path, jobs=1)
    assert reads == [] and report.unchanged == 5 and report.notices == []
    with open_index(idx_path) as idx:
        assert (idx.samples, idx.harmonics, idx.scale_mode) == (64, 8, "a1")
    # same values given explicitly: nothing to do
    assert build_index([str(lib)], idx_path, samples=64, jobs=1).unchanged == 5
    report = build_index([str(lib)], idx_path, harmonics=4, jobs=1)
    assert report.notices == ["parameters changed (harmonics 8 -> 4): recomputing all curves"]
    assert (report.updated, report.unchanged) == (5, 0) and len(reads) == 5
    with open_index(idx_path) as idx:
        assert (idx.samples, idx.harmonics, idx.scale_mode) == (64, 4, "a1")
        assert idx.read_rows(0, 1)["coefficients"].shape == (1, 4, 3)
    report = build_index([str(lib)], idx_path, samples=128, scale="rms", jobs=1)
    assert report.notices == ["parameters changed (samples 64 -> 128, scale a1 -> rms): recomputing all curves"]
    with pytest.raises(ParameterError):
        build_index([str(lib)], idx_path, samples=8, jobs=1)  # 2K >= n with the index's K = 4


def test_rebuild_recomputes_everything(lib, tmp_path, reads):
    idx_path = tmp_path / "idx.h5"
    build_index([str(lib)], idx_path, jobs=1)
    before = _snapshot(idx_path)
    reads.clear()
    report = build_index([str(lib)], idx_path, rebuild=True, jobs=1)
    assert sorted(reads) == _paths(lib) and (report.updated, report.unchanged) == (5, 0)
    after = _snapshot(idx_path)
    assert after["created"] == before["created"]
    _assert_rows_equal(after["rows"], before["rows"])


def test_dry_run_writes_nothing_and_reports_the_plan(lib, tmp_path, rng, reads):
    idx_path = tmp_path / "idx.h5"
    # no index yet: nothing is created
    report = build_index([str(lib)], idx_path, dry_run=True, jobs=1)
    assert report.dry_run and not report.written and report.added == 5
    assert not idx_path.exists() and not os.path.exists(str(idx_path) + ".lock")
    build_index([str(lib)], idx_path, jobs=1)
    data, stamp = idx_path.read_bytes(), os.stat(idx_path).st_mtime_ns
    a, b, multi, single = (
        str(lib / "a.csv"),
        str(lib / "b.csv"),
        str(lib / "sub" / "multi.obj"),
        str(lib / "single.obj"),
    )
    write_curves(multi, _curves(rng, 2))  # modified
    os.remove(b)  # deleted
    new = str(lib / "c.csv")
    write_curves(new, _curves(rng, 1)[0])  # added
    st = os.stat(single)
    os.utime(single, ns=(st.st_atime_ns, st.st_mtime_ns + 3_000_000_000))  # touched
    st = os.stat(a)
    _same_size_edit(lib / "a.csv")  # same size, new mtime, new contents
    os.utime(a, ns=(st.st_atime_ns, st.st_mtime_ns + 3_000_000_000))
    reads.clear()
    calls = []
    report = build_index([str(lib)], idx_path, dry_run=True, jobs=1, progress=lambda d, t: calls.append((d, t)))
    # the files the build would read are read (a broken one must be reported failed, the
    # curve count is the result's); the touched one with the same bytes is only hashed
    assert sorted(reads) == sorted([a, new, multi])
    assert report.dry_run and not report.written
    k = {p: os.path.relpath(p, tmp_path) for p in (a, b, new, multi, single, str(lib / "sub" / "two.vtp"))}
    assert report.changes == sorted(
        [
            ("updated", k[a]),
            ("removed", k[b]),
            ("added", k[new]),
            ("updated", k[multi]),
            ("unchanged", k[single]),
            ("unchanged", "lib/sub/two.vtp"),
        ],
        key=lambda x: x[1],
    )
    assert (report.added, report.updated, report.removed, report.unchanged, report.failed) == (1, 2, 1, 2, 0)
    assert calls[0] == (0, 4) and calls[-1] == (4, 4)
    assert idx_path.read_bytes() == data and os.stat(idx_path).st_mtime_ns == stamp
    assert sorted(os.listdir(tmp_path)) == ["idx.h5", "idx.h5.lock", "lib"]
    # what the dry run said is what the build does, the curve count included
    real = build_index([str(lib)], idx_path, jobs=1)
    assert real.changes == report.changes and real.curves == report.curves != 8
    assert real.failures == report.failures == []


def test_no_sources_is_an_error_without_an_index(tmp_path, lib):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.md").write_text("no curves here")
    with pytest.raises(InputError, match="no curve files found under"):
        build_index([str(empty)], tmp_path / "idx.h5")
    assert not (tmp_path / "idx.h5").exists()
    with pytest.raises(ReadError):
        build_index([str(tmp_path / "missing")], tmp_path / "idx.h5")
    # with an index, an empty source (a failed mount) is refused: the index is kept whole
    build_index([str(lib)], tmp_path / "idx.h5", jobs=1)
    before = (tmp_path / "idx.h5").read_bytes()
    with pytest.raises(
        ShrinkRefusedError,
        match=r"would remove all of the index's 5 files \(no curve files "
        r"found under .*empty; an empty or unmounted folder\?\); pass "
        r"--allow-shrink",
    ):
        build_index([str(empty)], tmp_path / "idx.h5", jobs=1)
    assert (tmp_path / "idx.h5").read_bytes() == before
    # a dry run says a build would refuse; allow_shrink empties it (every file removed), with a notice
    report = build_index([str(empty)], tmp_path / "idx.h5", jobs=1, dry_run=True)
    assert report.removed == 5 and report.shrink == (5, 5) and any("--allow-shrink" in n for n in report.notices)
    report = build_index([str(empty)], tmp_path / "idx.h5", jobs=1, allow_shrink=True)
    assert (report.removed, report.curves, report.shrink) == (5, 0, (5, 5)) and report.notices
    with open_index(tmp_path / "idx.h5") as idx:
        assert (idx.n_curves, idx.n_files, idx.ids()) == (0, 0, [])
        assert idx.read_rows(0, 0)["coefficients"].shape == (0, 16, 3)
        assert list(idx.iter_chunks()) == []


def test_parallel_and_serial_builds_are_identical(lib, tmp_path, rng):
    for i in range(3):
        write_curves(lib / f"extra{i}.vtp", _curves(rng, 5))
    (lib / "bad.csv").write_text("1 2\n")
    calls = []
    serial = build_index([str(lib)], tmp_path / "serial.h5", jobs=1)
    parallel = build_index(
        [str(lib)], tmp_path / "parallel.h5", jobs=2, progress=lambda done, total: calls.append((done, total))
    )
    assert serial.changes == parallel.changes and serial.failures == parallel.failures
    assert calls[0] == (0, 9) and calls[-1] == (9, 9) and len(calls) == 10
    a, a_attrs = _raw_datasets(tmp_path / "serial.h5")
    b, b_attrs = _raw_datasets(tmp_path / "parallel.h5")
    assert a.keys() == b.keys() and a_attrs == b_attrs
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_parallel_build_with_threads_running(lib, tmp_path):
    """With other threads alive, workers are not forked from this process (forkserver)."""
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        report = build_index([str(lib)], tmp_path / "idx.h5", jobs=2)
    finally:
        stop.set()
        t.join()
    assert (report.added, report.curves) == (5, 8)


def test_default_index_path(monkeypatch):
    monkeypatch.delenv("NFDMATCH_INDEX", raising=False)
    assert default_index_path() == "nfdmatch.h5"
    monkeypatch.setenv("NFDMATCH_INDEX", "/somewhere/x.h5")
    assert default_index_path() == "/somewhere/x.h5"


def test_build_rejects_bad_arguments(lib, tmp_path):
    with pytest.raises(ParameterError):
        build_index([str(lib)], tmp_path / "idx.h5", jobs=0)
    with pytest.raises(NfdError, match="unknown format"):
        build_index([str(lib)], tmp_path / "idx.h5", input_format="nope")
    with pytest.raises(NfdError, match="no folder"):
        build_index([str(lib)], tmp_path / "missing" / "idx.h5")
    with pytest.raises(ReadError, match="directory"):
        build_index([str(lib)], lib)
    assert sorted(os.listdir(tmp_path)) == ["lib"]


# --------------------------------------------------------------------------- bad index files


def _make_bad(kind, path):
    if kind == "wrong_kind":
        with h5py.File(path, "w") as f:
            f.create_dataset("x", data=np.arange(10))
            f.attrs["format"] = "something-else"
    elif kind == "no_format_attr":
        with h5py.File(path, "w") as f:
            f.create_dataset("x", data=np.arange(10))
    elif kind == "newer":
        shutil.copyfile(FROZEN, path)
        with h5py.File(path, "r+") as f:
            f.attrs["format_version"] = np.int64(4)
    elif kind == "truncated":
        data = open(FROZEN, "rb").read()
        open(path, "wb").write(data[: len(data) // 2])
    elif kind == "random":
        open(path, "wb").write(bytes(np.random.default_rng(5).integers(0, 256, 5000, dtype=np.uint8)))
    elif kind == "empty":
        open(path, "wb").close()
    elif kind == "missing_dataset":
        shutil.copyfile(FROZEN, path)
        with h5py.File(path, "r+") as f:
            del f["curves/inv_sv"]
    elif kind == "bad_blocks":
        shutil.copyfile(FROZEN, path)
        with h5py.File(path, "r+") as f:
            f["files/curve_count"][0] = 2
    elif kind == "text":
        open(path, "w").write("x,y,z\n0,0,0\n")


BAD = {
    "wrong_kind": "an HDF5 file but not an nfdmatch index (format attribute 'something-else')",
    "no_format_attr": "an HDF5 file but not an nfdmatch index (no 'format' attribute)",
    "newer": "written by a newer nfdmatch (format 4); this version reads formats 1, 2 and 3",
    "truncated": "truncated or corrupted HDF5 file",
    "random": "not an nfdmatch index (not an HDF5 file)",
    "empty": "empty file, not an nfdmatch index",
    "missing_dataset": "corrupted nfdmatch index: missing dataset /curves/inv_sv",
    "bad_blocks": "curve_start/curve_count blocks do not tile",
    "text": "not an nfdmatch index (not an HDF5 file)",
}


@pytest.mark.parametrize("kind", sorted(BAD))
def test_bad_index_files_are_clear_errors(tmp_path, kind):
    path = str(tmp_path / f"{kind}.h5")
    _make_bad(kind, path)
    with pytest.raises(IndexFormatError) as err:
        open_index(path)
    message = str(err.value)
    assert message.startswith(path + ": ") and BAD[kind] in message, message
    assert isinstance(err.value, NfdError) and isinstance(err.value, ValueError)
    assert err.value.__cause__ is None and err.value.__suppress_context__


def test_missing_index_and_directory(tmp_path):
    with pytest.raises(ReadError, match=r"no index at .*nope\.h5; build one with `nfdmatch index build`"):
        open_index(tmp_path / "nope.h5")
    with pytest.raises(ReadError, match="directory"):
        open_index(tmp_path)


@pytest.mark.parametrize(
    "kind,policy",
    [
        # a truncated HDF5 file does not open: it cannot be shown to be an index, so even
        # --rebuild leaves it (issue 9: it was overwritten)
        ("wrong_kind", "never"),
        ("random", "never"),
        ("text", "never"),
        ("truncated", "never"),
        ("newer", "rebuild"),
        ("missing_dataset", "rebuild"),
        ("empty", "always"),
    ],
)
def test_build_over_a_bad_index_file(tmp_path, lib, kind, policy):
    path = str(tmp_path / "idx.h5")
    _make_bad(kind, path)
    original = open(path, "rb").read()
    if policy == "always":
        report = build_index([str(lib)], path, jobs=1)
        assert report.written and report.notices
    else:
        with pytest.raises(IndexFormatError) as err:
            build_index([str(lib)], path, jobs=1)
        assert str(err.value).startswith(path + ": ") and BAD[kind] in str(err.value)
        assert ("--rebuild" in str(err.value)) == (policy == "rebuild")
        assert open(path, "rb").read() == original
        if policy == "never":
            with pytest.raises(IndexFormatError, match="refusing to overwrite"):
                build_index([str(lib)], path, jobs=1, rebuild=True)
            assert open(path, "rb").read() == original
            return
        report = build_index([str(lib)], path, jobs=1, rebuild=True)
        assert report.written and any("replacing" in n for n in report.notices)
    with open_index(path) as idx:
        assert idx.n_curves == 8


# --------------------------------------------------------------------------- the lock


def test_lock_fails_at_once_or_waits(lib, tmp_path):
    idx_path = str(tmp_path / "idx.h5")
    lock = index_lock.Lock(idx_path, 0)
    timer = None
    try:
        start = time.monotonic()
        with pytest.raises(IndexLockedError) as err:
            build_index([str(lib)], idx_path, jobs=1)
        assert time.monotonic() - start < 1.0
        message = str(err.value)
        assert f"another build holds the lock on {idx_path}.lock (pid {os.getpid()})" in message
        assert "--wait" in message and isinstance(err.value, OSError)
        assert not os.path.exists(idx_path)
        # a dry run does not need the lock
        assert build_index([str(lib)], idx_path, jobs=1, dry_run=True).added == 5
        timer = threading.Timer(0.4, lock.release)
        timer.start()
        start = time.monotonic()
        report = build_index([str(lib)], idx_path, jobs=1, wait=20)
        assert report.written and 0.3 < time.monotonic() - start < 15
    finally:
        if timer is not None:
            timer.join()
        lock.release()
    # released: the next build takes it at once
    assert build_index([str(lib)], idx_path, jobs=1).unchanged == 5


# --------------------------------------------------------------------------- processes: kill -9, readers

BUILD_SCRIPT = """
import sys
from nfdmatch import index
index.writer._WRITE_ROWS = 256  # many small writes: a kill lands in the middle of writing
index.build_index([sys.argv[1]], sys.argv[2], samples=int(sys.argv[3]), rebuild=True, jobs=int(sys.argv[4]))
"""


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    """6 VTP files x 1000 curves; a rebuild with samples=1024 takes a few seconds."""
    folder = tmp_path_factory.mktemp("big")
    rng = np.random.default_rng(7)
    base = [random_smooth_curve(rng, 64, 4) for _ in range(50)]
    for f in range(6):
        write_curves(
            folder / f"f{f}.vtp",
            [base[i % 50] * (1 + 0.01 * f) + rng.normal(scale=1e-3, size=(64, 3)) for i in range(1000)],
        )
    return str(folder)


def _start_build(big, idx_path, samples=1024, jobs=1):
    return subprocess.Popen(
        [sys.executable, "-c", BUILD_SCRIPT, big, str(idx_path), str(samples), str(jobs)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )


def _children(pid):
    out = []
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            out += [int(x) for x in open(f"/proc/{pid}/task/{task}/children").read().split()]
        except OSError:  # the thread ended while we looked
            continue
    return out


def _gone(pid):
    try:
        return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def _temps(folder):
    return [n for n in os.listdir(folder) if n.startswith(".idx.h5.tmp-")]


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc and kill -9")
def test_kill_9_during_a_build_leaves_the_previous_index(big, tmp_path):
    idx_path = tmp_path / "idx.h5"
    build_index([big], idx_path, jobs=2)
    original = idx_path.read_bytes()
    before = _snapshot(idx_path)
    rnd = random.Random(20261123)
    # (how to pick the moment, jobs): as soon as the temporary file exists, somewhere while it is
    # written, and at random moments from the start (imports, planning, computing, writing)
    plans = [
        ("temp", 0.0, 1),
        ("temp", rnd.uniform(0.2, 1.2), 2),
        ("start", rnd.uniform(0.1, 1.5), 1),
        ("start", rnd.uniform(0.1, 1.5), 2),
    ]
    for how, delay, jobs in plans:
        proc = _start_build(big, idx_path, samples=2048, jobs=jobs)  # takes ~3 s or more
        start = time.monotonic()
        if how == "temp":
            while not _temps(tmp_path) and time.monotonic() - start < 20:
                assert proc.poll() is None, proc.stderr.read().decode()
                time.sleep(0.002)
        time.sleep(delay)
        assert proc.poll() is None, f"the build finished before the kill ({how} + {delay:.2f} s)"
        workers = _children(proc.pid)
        proc.kill()
        proc.wait()
        assert idx_path.read_bytes() == original, (how, delay, jobs)
        after = _snapshot(idx_path)
        assert after["ids"] == before["ids"] and after["files"] == before["files"]
        _assert_rows_equal(after["rows"], before["rows"])
        leftovers = set(os.listdir(tmp_path)) - {"idx.h5", "idx.h5.lock"}
        assert all(n.startswith(".idx.h5.tmp-") for n in leftovers), leftovers
        if how == "temp":
            assert leftovers  # killed while writing its temporary file
        deadline = time.monotonic() + 10  # pool workers notice their parent died and exit
        while not all(_gone(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert all(_gone(w) for w in workers), workers
    # the lock died with the killed builds; the next build cleans the temporary files up
    report = build_index([big], idx_path, jobs=1, wait=0)
    assert report.unchanged == 6 and not report.written
    assert _temps(tmp_path) == []
    assert any("temporary file(s) left by an interrupted build" in n for n in report.notices)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses fork and flock")
def test_readers_and_a_second_build_while_a_build_runs(big, tmp_path):
    idx_path = tmp_path / "idx.h5"
    build_index([big], idx_path, jobs=2)
    before = _snapshot(idx_path)
    proc = _start_build(big, idx_path, samples=1024, jobs=1)
    lock_file = str(idx_path) + ".lock"
    start = time.monotonic()
    while time.monotonic() - start < 20:
        with open(lock_file) as fh:
            if fh.read().strip() == str(proc.pid):
                break
        assert proc.poll() is None, proc.stderr.read().decode()
        time.sleep(0.005)
    # a second build fails at once while the first holds the lock ...
    with pytest.raises(IndexLockedError, match=f"pid {proc.pid}"):
        build_index([big], idx_path, jobs=1, wait=0)
    # ... or waits for it
    waited = {}
    second = threading.Thread(
        target=lambda: waited.update(report=build_index([big], idx_path, jobs=1, wait=60, samples=128))
    )
    second.start()
    # readers never fail and always see a whole index: the old one or a new one
    reads, seen = 0, set()
    while proc.poll() is None or second.is_alive():
        with open_index(idx_path) as idx:
            ids, rows = idx.ids(), idx.read_rows(0, idx.n_curves)
            seen.add(idx.samples)
            assert len(ids) == idx.n_curves == len(rows["coefficients"]) == 6000
            if idx.samples == 128 and idx.updated == before["updated"]:
                _assert_rows_equal(rows, before["rows"])
            inv = invariants(rows["coefficients"][:50])
            np.testing.assert_allclose(rows["inv_norm"][:50], inv["norm"], rtol=1e-6, atol=1e-7)
        reads += 1
    second.join()
    assert proc.returncode == 0, proc.stderr.read().decode()
    assert reads >= 3 and 128 in seen
    report = waited["report"]
    assert report.written and report.notices == ["parameters changed (samples 1024 -> 128): recomputing all curves"]
    with open_index(idx_path) as idx:
        assert idx.samples == 128 and idx.created == before["created"]
        _assert_rows_equal(idx.read_rows(0, idx.n_curves), before["rows"])


def test_scattered_runs_of_strings_read_in_one_call_give_each_run_in_order(tmp_path):
    """``read_runs`` on a string dataset: several runs are one HDF5 read of their union
    (the ids of a batch's matches), decoded as ``asstr()`` decodes, in run order."""
    from nfdmatch.index.arrays import read_runs

    values = [f"lib/курва-{i}.obj#{i % 7}" if i % 3 else f"c{i}" for i in range(1000)]
    with h5py.File(tmp_path / "s.h5", "w") as f:
        f.create_dataset("id", data=values, dtype=h5py.string_dtype(), chunks=(256,))
    runs = [(3, 7), (100, 101), (255, 290), (500, 532), (999, 1000)]
    with h5py.File(tmp_path / "s.h5", "r") as f:
        got = read_runs(f["id"], runs)
        assert got == [v for a, b in runs for v in values[a:b]]
        assert read_runs(f["id"], [(10, 12)]) == values[10:12]


def test_one_harmonic_indexes_with_a_zero_third_block_value(tmp_path):
    """-k 1: the blocks side by side are a 3x2 matrix, two singular values; the bound features
    (``inv_block``, 3 of them) got two, and every file failed ("cannot reshape array of size
    2 into shape (1,3)"). Its third value is 0; nothing stored is NaN."""
    from conftest import ROOT, run_cli

    C = descriptors(random_smooth_curve(np.random.default_rng(3), 300, 4), harmonics=1).coefficients
    block = invariants(C)["block"]
    assert block.shape == (3,) and block[2] == 0 and np.isfinite(block).all()
    library, index = os.path.join(ROOT, "sample_curves", "library"), str(tmp_path / "k1.h5")
    code, out, err = run_cli("index", "build", library, "--index", index, "-k", "1", "--graph", "8", "--elastic")
    assert code == 0 and "Error" not in err, err
    assert run_cli("index", "verify", "--index", index)[0] == 0
    with h5py.File(index, "r") as f:
        assert f["curves/inv_block"].shape == (24, 3) and not f["curves/inv_block"][:, 2].any()
        floats = [
            f[name][...] for name in ("curves/inv_block", "curves/statistics", "search/features", "graph/distance")
        ]
    assert all(np.isfinite(values).all() for values in floats)
    query = os.path.join(ROOT, "sample_curves", "queries", "trefoil-posed.obj")
    for extra in ([], ["--elastic"], ["--rerank"]):
        code, out, err = run_cli("query", query, "--index", index, "--top", "3", *extra)
        assert code == 0 and err == "" and len(out.splitlines()) == 4 and "nan" not in out, (extra, err)
