"""The ``/changes`` group of an index: which curve rows the build that wrote the file added
or recomputed (docs/index-format.md), what ``pairs --new`` restricts one side to.

Optional: an index written before it was recorded has none (a build that writes the file
adds it). A build that changes nothing does not rewrite the file, so ``/changes`` always
names the rows of the last build that wrote it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import IndexFormatError
from .schema import create_checked

if TYPE_CHECKING:
    import h5py
    from numpy.typing import NDArray
    from .reader import Index

__all__ = ["write_changes", "read_changes", "changes_rows", "changes_problem"]


def write_changes(h5: h5py.File, runs: list[tuple[int, int]]) -> None:
    """``/changes/rows``: (R, 2) int64 ``[start, stop)`` ranges of the rows the build added
    or recomputed (adjacent ranges joined), in row order."""
    merged: list[list[int]] = []
    for start, count in sorted(runs):
        if count <= 0:
            continue
        if merged and merged[-1][1] == start:
            merged[-1][1] = start + count
        else:
            merged.append([start, start + count])
    g = h5.create_group("changes")
    # with the format's checksums (Fletcher-32), as every dataset of the file
    create_checked(g, "rows", np.asarray(merged, dtype=np.int64).reshape(-1, 2), np.int64)


def changes_rows(h5: h5py.File) -> np.ndarray | None:
    """``/changes/rows`` of an open file as stored (any shape and type: :func:`changes_problem`
    checks them), None when the file has no ``/changes``. Raises ValueError (what is wrong)
    when ``/changes`` is not a group holding that dataset; h5py's OSError when unreadable."""
    import h5py

    g = h5.get("changes")
    if g is None:
        return None
    if not isinstance(g, h5py.Group) or not isinstance(g.get("rows"), h5py.Dataset):
        raise ValueError("/changes is not a group holding the dataset rows")
    return np.asarray(g["rows"][...])


def changes_problem(runs: np.ndarray, n_curves: int) -> str | None:
    """What is wrong with ``/changes/rows`` as read (``runs``) for an index of ``n_curves``
    rows, or None: it must be (R, 2) integer ``[start, stop)`` ranges within 0..N."""
    if runs.ndim != 2 or runs.shape[1] != 2 or not np.issubdtype(runs.dtype, np.integer):
        return f"/changes/rows is {runs.shape} of {runs.dtype}, not (R, 2) integer ranges"
    if len(runs) and (runs.min() < 0 or runs.max() > n_curves or (runs[:, 1] < runs[:, 0]).any()):
        return f"/changes/rows does not match /curves: a range outside 0..{n_curves}"
    return None


def read_changes(index: Index) -> NDArray[np.int64] | None:
    """The rows (int64, ascending) that the build which wrote an open
    :class:`~nfdmatch.index.Index` added or recomputed; None when the index does not record
    them. Raises IndexFormatError when the group is there but malformed."""
    h5 = index._h5
    if h5 is None:
        return None

    def read() -> tuple[np.ndarray | None, str | None]:
        try:
            return changes_rows(h5), None
        except ValueError as exc:  # malformed, as distinct from unreadable (index._read's)
            return None, str(exc)

    runs, problem = index._read(read, "/changes")
    if runs is None and problem is None:
        return None
    problem = problem or changes_problem(runs, index.n_curves)
    if problem:
        raise IndexFormatError(f"corrupted nfdmatch index: {problem}", path=index.path)
    if not len(runs):
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate([np.arange(a, b, dtype=np.int64) for a, b in runs]))
