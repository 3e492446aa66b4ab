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

__all__ = ["write_changes", "read_changes"]


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


def read_changes(index: Index) -> NDArray[np.int64] | None:
    """The rows (int64, ascending) that the build which wrote an open
    :class:`~nfdmatch.index.Index` added or recomputed; None when the index does not record
    them. Raises IndexFormatError when the group is there but malformed."""
    h5 = index._h5
    if h5 is None or "changes" not in h5 or "rows" not in h5["changes"]:
        return None
    runs = index._read(lambda: np.asarray(h5["changes"]["rows"][...]), "/changes")
    N = index.n_curves
    if (
        runs.ndim != 2
        or runs.shape[1] != 2
        or not np.issubdtype(runs.dtype, np.integer)
        or (len(runs) and (runs.min() < 0 or runs.max() > N or (runs[:, 1] < runs[:, 0]).any()))
    ):
        raise IndexFormatError("corrupted nfdmatch index: /changes/rows does not match /curves", path=index.path)
    if not len(runs):
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate([np.arange(a, b, dtype=np.int64) for a, b in runs]))
