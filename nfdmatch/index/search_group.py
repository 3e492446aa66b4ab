"""The ``/search`` group of a format-2 index: rows in cell-major order with their invariant
features, cell centres and radii (docs/index-format.md). Written once per build from the
finished ``/curves`` table; read cell by cell by a search."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import numpy as np

from ..search.bounds import TRUNCATED_HARMONICS, feature_split, squared_norms
from ..search import cells as search_cells
from ..search.table import SearchTable
from .arrays import first_nonfinite
from .arrays import read_runs as read_runs_of
from .schema import CHECKSUMS, CRC_ROWS, create_checked, set_text, write_string_checks

if TYPE_CHECKING:
    import h5py
    from collections.abc import Callable
    from numpy.typing import NDArray
    from ..search.table import SearchTable

__all__ = ["write_search_group", "search_table"]

#: /search/coefficients: (N, K, 3) complex64, checked apart (K from the harmonics)
#: rows read back from /curves at a time while gathering the features
_READ_ROWS = 1 << 18
#: positions per HDF5 chunk of the datasets a search reads cell by cell
_POSITION_CHUNK_ROWS = 256


def write_search_group(
    h5: h5py.File, harmonics: int, *, rows_per_cell: int | None = None, id_crcs: NDArray[np.uint32] | None = None
) -> int:
    """Write ``/search`` from the file's ``/curves`` (inv_sv, inv_block); returns the number of cells.

    Deterministic: the same curves give the same group (seeded k-means). ``id_crcs``: the
    ``/curves/id_crc32`` blocks of the ids as written (None: read the ids back).
    """

    curves = h5["curves"]
    N = curves["inv_sv"].shape[0] if "inv_sv" in curves else 0
    split = feature_split(harmonics)
    D = split + 3
    features = np.empty((N, D), dtype=np.float32)
    for a in range(0, N, _READ_ROWS):
        b = min(N, a + _READ_ROWS)
        features[a:b, :split] = curves["inv_sv"][a:b]
        features[a:b, split:] = curves["inv_block"][a:b]
    # (the default read when called: a test sets it for a small index)
    cells = search_cells.build_cells(features, split, rows_per_cell=rows_per_cell or search_cells.ROWS_PER_CELL)
    features = features[cells.row]
    sqnorm = squared_norms(features, split)
    # one (N, K, 3) array in position order, filled block by block through the inverse
    # permutation (no second copy of it)
    position_of = np.empty(N, dtype=np.int64)
    position_of[cells.row] = np.arange(N, dtype=np.int64)
    coefficients = np.empty((N, harmonics, 3), dtype=np.complex64)
    for a in range(0, N, _READ_ROWS):
        block = curves["coefficients"][a : a + _READ_ROWS]
        coefficients[position_of[a : a + len(block)]] = block
    g = h5.create_group("search")
    g.attrs["cells"] = np.int64(cells.count)
    for name, data in (("cell_start", cells.start), ("centre", cells.centre), ("radius", cells.radius)):
        create_checked(g, name, data)  # read whole when a search starts
    for name, data in (("row", cells.row), ("features", features), ("sqnorm", sqnorm), ("coefficients", coefficients)):
        # read cell by cell (~128 positions): small chunks, so that a query reads (and
        # checksums) ~36 KB per cell rather than a 4096-row chunk; the descriptors in
        # chunks of the first truncated bound's harmonics, which it reads alone
        columns = TRUNCATED_HARMONICS if name == "coefficients" else 0
        create_checked(g, name, data, chunk_rows=_POSITION_CHUNK_ROWS, chunk_columns=columns)
    _finish_checksums(h5, id_crcs)
    return cells.count


def _finish_checksums(h5, id_crcs=None) -> None:
    """The last step of a build: ``/curves/id_crc32`` from the ids as stored (the writer
    appends them in pieces and gives their blocks' CRCs as ``id_crcs``; without them they
    are read back, ~1 s per million rows), then the root attribute that makes readers
    require every checksum."""

    ids = h5["curves/id"] if "curves/id" in h5 else None
    values: list[str] = []
    expected = None if ids is None else (ids.shape[0] + CRC_ROWS - 1) // CRC_ROWS
    if id_crcs is not None and expected is not None and len(id_crcs) == expected:
        h5["curves"].create_dataset("id_crc32", data=np.asarray(id_crcs, dtype=np.uint32), chunks=True, fletcher32=True)
    elif ids is not None:
        step = CRC_ROWS * 256
        for a in range(0, ids.shape[0], step):
            values.extend(ids.asstr()[a : a + step].tolist())
        write_string_checks(h5["curves"], "id", values)
    set_text(h5.attrs, "checksums", CHECKSUMS)


def search_table(
    h5: h5py.File, N: int, harmonics: int, read_coefficients: Callable[[NDArray[np.int64]], NDArray[np.complex128]],
    fail: Callable[[str], Any], guard: Callable[[Callable[[], Any], str], Any] | None = None,
) -> SearchTable:  # fmt: skip
    """A :class:`~nfdmatch.search.table.SearchTable` reading ``/search`` cell by cell.

    ``fail(message)`` raises the reader's error for a corrupted file (rows out of range,
    non-finite values); ``guard(fn, where)`` runs a read and turns its failure (e.g. a
    checksum mismatch) into the reader's error (default: run it as is).
    """

    if guard is None:

        def guard(fn, where):
            return fn()

    g = h5["search"]
    start = np.asarray(g["cell_start"][...], dtype=np.int64)
    ds_row, ds_features, ds_coefficients = g["row"], g["features"], g["coefficients"]

    def finite(name, values, first):
        bad = first_nonfinite(values, first)
        if bad is not None:
            fail(f"non-finite value (NaN or Inf) in /search/{name}, position {bad}")
        return values

    def read_runs(runs):
        # two reads for any number of ranges (one HDF5 call each): the squared norms are
        # recomputed from the features (the build computes them the same way), the
        # descriptors read apart, only for the cells a search takes past the invariant bound
        where = f"/search, positions {runs[0][0]}..{runs[-1][1] - 1}"
        row, features = guard(
            lambda: (
                np.asarray(read_runs_of(ds_row, runs), dtype=np.int64),
                np.asarray(read_runs_of(ds_features, runs), dtype=np.float32),
            ),
            where,
        )
        if len(row) and (row.min() < 0 or row.max() >= N):
            fail("/search/row holds a row outside the index")
        _finite_runs("features", features, runs)
        return row, features, None, None

    def read_descriptor_runs(runs, harmonics=None):
        where = f"/search/coefficients, positions {runs[0][0]}..{runs[-1][1] - 1}"
        columns = None if harmonics is None else slice(0, harmonics)
        coefficients = guard(lambda: np.asarray(read_runs_of(ds_coefficients, runs, columns)), where)
        return _finite_runs("coefficients", coefficients, runs)

    def _finite_runs(name, values, runs):
        bad = first_nonfinite(values, 0)
        if bad is not None:
            for a, b in runs:  # the position in the file, not in the read
                if bad < b - a:
                    bad += a
                    break
                bad -= b - a
            fail(f"non-finite value (NaN or Inf) in /search/{name}, position {bad}")
        return values

    # descriptors stored in chunks of fewer harmonics than K (written so since December
    # 2026; any chunking is valid): the first chunk's harmonics can be read alone
    chunks = ds_coefficients.chunks
    head = int(chunks[1]) if chunks is not None and len(chunks) > 1 and 0 < chunks[1] < harmonics else 0
    centre = finite("centre", np.asarray(g["centre"][...], dtype=np.float64), 0)
    radius = finite("radius", np.asarray(g["radius"][...], dtype=np.float64), 0)
    return SearchTable(
        harmonics,
        start,
        centre,
        radius,
        lambda a, b: read_runs([(a, b)]),
        read_coefficients,
        lambda a, b, harmonics=None: read_descriptor_runs([(a, b)], harmonics),
        read_runs=read_runs,
        read_descriptor_runs=read_descriptor_runs,
        head_harmonics=head,
    )
