"""Reading arrays of an index: runs of rows in one HDF5 call, the first non-finite value of
a read, unique rows. Plain numpy and h5py datasets: no format knowledge (schema.py has it)."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import h5py
import numpy as np

if TYPE_CHECKING:
    from collections.abc import Sequence
    from collections.abc import Iterable
    from numpy.typing import NDArray

__all__ = ["read_runs", "read_string_runs", "first_nonfinite", "unique_rows"]


def read_runs(
    ds: h5py.Dataset, runs: Iterable[tuple[int, int]], columns: slice | None = None
) -> NDArray[Any] | list[str]:
    """Rows ``[a, b)`` of dataset ``ds`` for each ``(a, b)`` of ``runs``, concatenated (a
    read per run: HDF5 reads a union of hyperslabs ~10x slower than the runs one by one);
    ``columns``: only that slice of the second axis. Variable-length strings come back as
    a list of str."""
    runs = [(int(a), int(b)) for a, b in runs if b > a]
    if h5py.check_string_dtype(ds.dtype) is not None:
        if len(runs) > 1:
            return read_string_runs(ds, runs)
        strings = ds.asstr()
        return [v for a, b in runs for v in strings[a:b].tolist()]
    tail = () if columns is None else (columns,)
    if len(runs) == 1:
        return ds[(slice(*runs[0]),) + tail]
    if not runs:
        return np.empty((0,) + tuple(ds.shape[1:]), dtype=ds.dtype)[(slice(None),) + tail]
    return np.concatenate([ds[(slice(a, b),) + tail] for a, b in runs])


def read_string_runs(ds: h5py.Dataset, runs: Sequence[tuple[int, int]]) -> list[str]:
    """Variable-length strings of the (ascending, disjoint) ``runs`` of a 1-D dataset in one
    HDF5 call on their union: a string read costs ~40-250 us whatever its length (type
    conversion, global heap), so the ids of a batch's matches, 10-200 scattered blocks,
    cost one call instead of one per block. Decoded as ``ds.asstr()`` does (UTF-8, strict)."""
    space = ds.id.get_space()
    space.select_none()
    for a, b in runs:
        space.select_hyperslab((a,), (b - a,), op=h5py.h5s.SELECT_OR)
    out = np.empty(sum(b - a for a, b in runs), dtype=object)
    ds.id.read(h5py.h5s.create_simple(out.shape), space, out)
    return [v.decode("utf-8") for v in out.tolist()]


def first_nonfinite(
    values: NDArray[np.floating] | NDArray[np.complexfloating], rows: NDArray[np.int64] | int
) -> int | None:
    """The row (of ``rows``, (m,) ints, or a start row) of the first non-finite entry of
    ``values`` (m, ...) float or complex, or None when all are finite."""
    values = np.asarray(values)
    if values.dtype.kind not in "fc" or not values.size:
        return None
    flat = values.reshape(len(values), -1)
    if values.dtype.kind == "c" and flat.flags.c_contiguous:
        flat = flat.view(values.real.dtype)  # isfinite on the parts: ~3x faster
    # the common case in one cheap pass: a sum is finite only if every term is (NaN and inf
    # propagate; an overflow to inf only sends the values to the exact check below)
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(flat.sum()):
            return None
    bad = ~np.isfinite(flat).all(axis=1)
    if not bad.any():
        return None
    i = int(np.argmax(bad))
    return int(rows[i]) if np.ndim(rows) else int(rows) + i


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(rows, return_inverse=True)`` for (m,) int64 rows, without importing
    ``numpy.ma`` (np.unique does: ~25 ms of a query's start-up)."""
    order = np.argsort(rows, kind="stable")
    ordered = rows[order]
    first = np.ones(len(rows), dtype=bool)
    first[1:] = ordered[1:] != ordered[:-1]
    inverse = np.empty(len(rows), dtype=np.int64)
    inverse[order] = np.cumsum(first) - 1
    return ordered[first], inverse
