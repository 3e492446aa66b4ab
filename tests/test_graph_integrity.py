"""The stored neighbour graph is data like the rest (issue 23, item 3): checksummed, read
back checked, verified whole; a bad list is refused by `index verify` and by `query --rerank`."""

from __future__ import annotations

import os
import shutil

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from nfdmatch import read_curves
from nfdmatch.cli import main
from nfdmatch.errors import IndexFormatError
from nfdmatch.index import build_index, open_index
from nfdmatch.index.graph import check_lists, read_graph
from nfdmatch.index.verify import verify_index
from nfdmatch.search.rerank import rerank_index

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LIBRARY = os.path.join(REPO, "sample_curves", "library")
QUERY = os.path.join(REPO, "sample_curves", "queries", "trefoil-posed.obj")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The sample library (24 curves) with a graph of 8 neighbours (built once; tests copy it)."""
    path = tmp_path_factory.mktemp("graph") / "lib.h5"
    build_index([LIBRARY], str(path), jobs=1, graph=8)
    return path


@pytest.fixture
def index_copy(built, tmp_path):
    path = tmp_path / "copy.h5"
    shutil.copyfile(built, path)
    return path


def _query(index, *extra):
    result = CliRunner().invoke(
        main, ["query", QUERY, "--index", str(index), "--rerank", *extra], catch_exceptions=False
    )
    return result.exit_code, result.stdout, result.stderr


def _findings(path):
    return [(f.dataset, f.rows, f.what) for f in verify_index(path).findings]


def test_the_graph_is_checksummed_and_verified(built):
    with h5py.File(built, "r") as f:
        g = f["graph"]
        assert g.attrs["checksums"].decode() == "fletcher32"  # fixed-length: h5py gives bytes
        for name in g:
            assert g[name].fletcher32 and g[name].chunks is not None, name
    report = verify_index(built)
    assert report.ok, report.findings
    with open_index(built) as idx:
        nb, d = read_graph(idx)
        assert nb.shape == (24, 8) and check_lists(np.arange(24), nb, d, 24) is None


def test_a_graph_written_before_its_checksums_still_reads(index_copy):
    with h5py.File(index_copy, "a") as f:
        g = f["graph"]
        data = {name: g[name][...] for name in ("neighbour", "distance")}
        for name, values in data.items():
            del g[name]
            g.create_dataset(name, data=values)  # contiguous, no Fletcher-32: as written before
        del g.attrs["checksums"]
    assert verify_index(index_copy).ok
    code, out, err = _query(index_copy)
    assert code == 0 and err == "" and "trefoil.csv" in out.splitlines()[1]


def test_a_graph_declaring_checksums_without_them_is_refused(index_copy):
    with h5py.File(index_copy, "a") as f:
        values = f["graph/distance"][...]
        del f["graph/distance"]
        f["graph"].create_dataset("distance", data=values)
    assert any(ds == "/graph/distance" and "no checksum filter" in what for ds, _, what in _findings(index_copy))
    code, out, err = _query(index_copy)
    assert code == 2 and out == "" and "no checksum filter" in err and "Traceback" not in err


def test_a_flipped_bit_in_the_graph_is_found(index_copy):
    with h5py.File(index_copy, "r") as f:
        info = f["graph/distance"].id.get_chunk_info(0)
    with open(index_copy, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        byte = fh.read(1)[0]
        fh.seek(-1, 1)
        fh.write(bytes([byte ^ 0x10]))
    assert ("/graph/distance", "0..23", "checksum mismatch (damaged chunk)") in _findings(index_copy)
    code, out, err = _query(index_copy)
    assert code == 2 and out == "" and "checksum mismatch in /graph" in err


# each edit of a sound graph, what verify says about it, and what the query says
EDITS = {
    "negated distance": (
        lambda nb, d: d.__setitem__((3, 0), -d[3, 0]),
        ("/graph/distance", "3", "a negative distance, 1 rows"),
        "/graph/distance, row 3: a negative distance",
    ),
    "self neighbour": (
        lambda nb, d: nb.__setitem__((5, 2), 5),
        ("/graph/neighbour", "5", "a row naming itself, 1 rows"),
        "/graph/neighbour, row 5: a row naming itself",
    ),
    "shuffled list": (
        lambda nb, d: (nb.__setitem__((7, slice(None)), nb[7, ::-1]), d.__setitem__((7, slice(None)), d[7, ::-1])),
        ("/graph/distance", "7", "distances not ascending (nearest first), 1 rows"),
        "/graph/distance, row 7: distances not ascending",
    ),
    "row outside the index": (
        lambda nb, d: nb.__setitem__((2, 4), 99),
        ("/graph/neighbour", "2", "a neighbour outside the index, 1 rows"),
        "/graph/neighbour, row 2: a neighbour outside the index",
    ),
    "NaN": (
        lambda nb, d: d.__setitem__((9, 1), np.nan),
        ("/graph/distance", "9", "NaN, 1 rows"),
        "/graph/distance, row 9: NaN",
    ),
    "repeated neighbour": (
        lambda nb, d: nb.__setitem__((4, 1), nb[4, 0]),
        ("/graph/neighbour", "4", "a row named twice, 1 rows"),
        "/graph/neighbour, row 4: a row named twice",
    ),
}


@pytest.mark.parametrize("edit", sorted(EDITS))
def test_an_edited_graph_is_refused_by_verify_and_by_the_query(index_copy, edit):
    change, finding, message = EDITS[edit]
    with h5py.File(index_copy, "a") as f:
        nb, d = f["graph/neighbour"][...], f["graph/distance"][...]
        change(nb, d)
        f["graph/neighbour"][...] = nb
        f["graph/distance"][...] = d
    assert finding in _findings(index_copy)
    code, out, err = _query(index_copy)
    assert code == 2 and out == "", (code, out)
    assert err.startswith(f"Error: {index_copy}: corrupted nfdmatch index: {message}"), err
    assert "Traceback" not in err and "cannot convert" not in err
    with open_index(index_copy) as idx:
        with pytest.raises(IndexFormatError, match=message.split(": ")[-1]):
            rerank_index(idx, read_curves(QUERY))


def test_verify_finds_lists_that_contradict_each_other(index_copy):
    with h5py.File(index_copy, "a") as f:
        nb, d = f["graph/neighbour"][...], f["graph/distance"][...]
    # a row whose nearest neighbour also lists it: change the distance one way only
    i = next(i for i in range(len(nb)) if i in nb[nb[i, 0]])
    d[i, 0] *= 0.5
    with h5py.File(index_copy, "a") as f:
        f["graph/distance"][...] = d
    found = _findings(index_copy)
    assert any(ds == "/graph/distance" and "inconsistent" in what for ds, _, what in found), found


def test_a_graph_of_the_wrong_shape_or_k_is_refused(index_copy):
    with h5py.File(index_copy, "a") as f:
        f["graph"].attrs["k"] = np.int64(9)
    assert any(ds == "/graph" and "k = 9" in what for ds, _, what in _findings(index_copy))
    code, out, err = _query(index_copy)
    assert code == 2 and "corrupted nfdmatch index: /graph holds" in err


def test_check_lists_allows_tied_distances_in_id_order_only():
    rows = np.array([0, 1])
    nb = np.array([[1, 2, -1], [0, 2, -1]])
    d = np.array([[0.5, 0.5 - 4e-10, np.inf], [0.5, 0.7, np.inf]])  # a tie (within 1e-9), by id
    assert check_lists(rows, nb, d, 3) is None
    d[0, 1] = 0.5 - 1e-6
    assert check_lists(rows, nb, d, 3) == "/graph/distance, row 0: distances not ascending (nearest first)"
    d[0, 1] = 0.6
    d[1, 2] = 0.8  # padding with a finite distance
    assert "padding" in check_lists(rows, nb, d, 3)


def test_cli_verify_names_a_bad_graph_row(index_copy):
    with h5py.File(index_copy, "a") as f:
        f["graph/distance"][6, 0] = -f["graph/distance"][6, 0]
    result = CliRunner().invoke(main, ["index", "verify", "--index", str(index_copy)], catch_exceptions=False)
    assert result.exit_code == 1
    assert result.stdout == "bad\t/graph/distance\t6\ta negative distance, 1 rows\n"


@pytest.mark.parametrize(
    "name, dtype, stored",
    [
        ("neighbour", np.float64, "float64"),
        ("distance", np.float32, "float32"),
        ("reverse_source", np.int32, "int32"),
        ("neighbour", h5py.string_dtype("utf-8"), "variable-length utf-8 string"),
    ],
    ids=["neighbour-float", "distance-float32", "reverse-int32", "neighbour-strings"],
)
def test_verify_checks_the_types_of_the_graph_datasets(index_copy, name, dtype, stored):
    """A /graph dataset of another type (its values converted: they would pass every list
    check) is a finding of `index verify`, as any other dataset of the wrong type is."""
    with h5py.File(index_copy, "a") as f:
        values = f[f"graph/{name}"][...]
        del f[f"graph/{name}"]
        if h5py.check_string_dtype(np.dtype(dtype)) is not None:  # the numbers as text (HDF5 filters no strings)
            f["graph"].create_dataset(name, data=values.astype(str).astype(object), dtype=dtype)
        else:
            f["graph"].create_dataset(name, data=values.astype(dtype), chunks=True, fletcher32=True)
    want = "int64" if name != "distance" else "float64"
    assert _findings(index_copy) == [(f"/graph/{name}", "", f"stored as {stored}; the format says {want}")]
    result = CliRunner().invoke(main, ["index", "verify", "--index", str(index_copy)], catch_exceptions=False)
    assert result.exit_code == 1, result.output
    assert result.stdout == f"bad\t/graph/{name}\t\tstored as {stored}; the format says {want}\n"
    assert result.stderr.startswith(f"Error: {index_copy}: 1 problem found") and "Traceback" not in result.stderr
