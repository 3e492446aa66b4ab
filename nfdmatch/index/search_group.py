"""The ``/search`` group of a format-2 index: rows in cell-major order with their invariant
features, cell centres and radii (docs/index-format.md). Written once per build from the
finished ``/curves`` table; read cell by cell by a search."""

from __future__ import annotations

import numpy as np


__all__ = ["write_search_group", "check_search_group", "search_table", "SEARCH_DATASETS"]

#: /search datasets: name -> (dtype, shape as a function of N rows, C cells, D feature columns)
SEARCH_DATASETS = {
    "row": (np.int64, lambda N, C, D: (N,)),
    "cell_start": (np.int64, lambda N, C, D: (C + 1,)),
    "centre": (np.float64, lambda N, C, D: (C, D)),
    "radius": (np.float64, lambda N, C, D: (C, 2)),
    "features": (np.float32, lambda N, C, D: (N, D)),
    "sqnorm": (np.float64, lambda N, C, D: (N, 2)),
}
#: /search/coefficients: (N, K, 3) complex64, checked apart (K from the harmonics)
#: rows read back from /curves at a time while gathering the features
_READ_ROWS = 1 << 18


def write_search_group(h5, harmonics: int, *, rows_per_cell: int | None = None) -> int:
    """Write ``/search`` from the file's ``/curves`` (inv_sv, inv_block); returns the number of cells.

    Deterministic: the same curves give the same group (seeded k-means).
    """
    from ..search.bounds import feature_split, squared_norms
    from ..search.cells import ROWS_PER_CELL, build_cells

    curves = h5["curves"]
    N = curves["inv_sv"].shape[0] if "inv_sv" in curves else 0
    split = feature_split(harmonics)
    D = split + 3
    features = np.empty((N, D), dtype=np.float32)
    for a in range(0, N, _READ_ROWS):
        b = min(N, a + _READ_ROWS)
        features[a:b, :split] = curves["inv_sv"][a:b]
        features[a:b, split:] = curves["inv_block"][a:b]
    cells = build_cells(features, split, rows_per_cell=rows_per_cell or ROWS_PER_CELL)
    features = features[cells.row]
    sqnorm = squared_norms(features, split)
    # one (N, K, 3) array in position order, filled block by block through the inverse
    # permutation (no second copy of it)
    position_of = np.empty(N, dtype=np.int64)
    position_of[cells.row] = np.arange(N, dtype=np.int64)
    coefficients = np.empty((N, harmonics, 3), dtype=np.complex64)
    for a in range(0, N, _READ_ROWS):
        block = curves["coefficients"][a:a + _READ_ROWS]
        coefficients[position_of[a:a + len(block)]] = block
    g = h5.create_group("search")
    g.attrs["cells"] = np.int64(cells.count)
    g.create_dataset("row", data=cells.row)
    g.create_dataset("cell_start", data=cells.start)
    g.create_dataset("centre", data=cells.centre)
    g.create_dataset("radius", data=cells.radius)
    g.create_dataset("features", data=features)
    g.create_dataset("sqnorm", data=sqnorm)
    g.create_dataset("coefficients", data=coefficients)
    return cells.count


def check_search_group(h5, N: int, harmonics: int) -> str | None:
    """Why the file's ``/search`` group is not valid for N rows and K harmonics, or None."""
    g = h5.get("search")
    if g is None:
        return "missing group /search"
    D = 2 * harmonics + 3
    start = g.get("cell_start")
    if start is None or len(start.shape) != 1 or start.shape[0] < 1:
        return "missing or bad dataset /search/cell_start"
    C = start.shape[0] - 1
    for name, (dtype, shape) in SEARCH_DATASETS.items():
        ds = g.get(name)
        if ds is None or not hasattr(ds, "shape"):
            return f"missing dataset /search/{name}"
        if tuple(ds.shape) != shape(N, C, D):
            return f"/search/{name} has shape {ds.shape}, expected {shape(N, C, D)}"
    coefficients = g.get("coefficients")
    want = (N, harmonics, 3)
    if (coefficients is None or not hasattr(coefficients, "shape") or tuple(coefficients.shape) != want
            or coefficients.dtype.kind != "c"):
        return f"missing or bad dataset /search/coefficients (expected complex, shape {want})"
    starts = np.asarray(start[...], dtype=np.int64)
    if starts[0] != 0 or starts[-1] != N or (np.diff(starts) < 0).any():
        return "/search/cell_start does not run from 0 to the row count without decreasing"
    return None


def search_table(h5, N: int, harmonics: int, read_coefficients, fail):
    """A :class:`~nfdmatch.search.table.SearchTable` reading ``/search`` cell by cell.

    ``fail(message)`` raises the reader's error for a corrupted file (rows out of range).
    """
    from ..search.table import SearchTable

    g = h5["search"]
    start = np.asarray(g["cell_start"][...], dtype=np.int64)
    ds_row, ds_features, ds_sqnorm, ds_coefficients = g["row"], g["features"], g["sqnorm"], g["coefficients"]

    def read_positions(a: int, b: int):
        row = np.asarray(ds_row[a:b], dtype=np.int64)
        if len(row) and (row.min() < 0 or row.max() >= N):
            fail("/search/row holds a row outside the index")
        return (row, np.asarray(ds_features[a:b], dtype=np.float32), np.asarray(ds_sqnorm[a:b], dtype=np.float64),
                np.asarray(ds_coefficients[a:b]))

    return SearchTable(harmonics, start, np.asarray(g["centre"][...], dtype=np.float64),
                       np.asarray(g["radius"][...], dtype=np.float64), read_positions, read_coefficients)
