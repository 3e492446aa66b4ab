"""The ``/graph`` group of an index: each row's K nearest other rows and their exact distances
(docs/index-format.md), what ``query --rerank`` diffuses over (docs/rerank.md).

Written by a build in one call (:func:`write_graph`) once ``/curves``, ``/files`` and
``/search`` of the new file are complete. Incremental: rows copied unchanged from the old
index keep their lists when none of their neighbours was removed or changed, and only the
new rows can enter them; every other row is searched in the new index. The result equals a
from-scratch build (each list is an exact top K, ties by id).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dataclasses import dataclass

import numpy as np

from ..defaults import DEFAULT_GRAPH_K  # neighbours per row when --graph is given without a number
from ..errors import IndexFormatError
from ..search.engine import TIE
from .arrays import unique_rows
from .schema import Problem, stored_dataset, text_attr

if TYPE_CHECKING:
    import h5py
    from numpy.typing import NDArray
    from collections.abc import Callable
    from .reader import Index

__all__ = [
    "GraphSpec",
    "GRAPH_DISTANCES",
    "graph_distance",
    "read_graph",
    "read_graph_rows",
    "read_reverse_rows",
    "reverse_of",
    "graph_changes",
    "fused_version",
    "stale_fused_graph",
    "graph_k",
    "check_lists",
    "GraphStats",
    "DEFAULT_GRAPH_K",
    "GRAPH_CHECKSUMS",
]

#: what a graph's distances are (``/graph`` attribute ``distance``; absent: ``"exact"``): the
#: exact distance, or the fused distance of the elastic stage (``index build --graph K --elastic``)
GRAPH_DISTANCES = ("exact", "fused")


@dataclass(frozen=True)
class GraphSpec:
    """The graph a build is asked for: ``k`` neighbours per row, by the ``distance`` of
    :data:`GRAPH_DISTANCES` (a build's ``graph=`` takes it, or a plain K for the exact one)."""

    k: int
    distance: str = "exact"

    def __post_init__(self):
        if self.distance not in GRAPH_DISTANCES:
            raise ValueError(f"graph distance must be one of {', '.join(GRAPH_DISTANCES)}, got {self.distance!r}")


#: ``/graph`` attribute ``checksums``: its datasets carry Fletcher-32 (docs/index-format.md)
GRAPH_CHECKSUMS = "fletcher32"
#: rows per chunk of the /graph datasets: a query reads a few hundred scattered rows
GRAPH_CHUNK_ROWS = 256

#: an index up to this many rows is searched from coefficients held in memory (16 MiB per
#: 100k rows at K = 16); larger ones read the rows each search needs from the file
IN_MEMORY_ROWS = 1 << 19


@dataclass
class GraphStats:
    """What :func:`write_graph` did: ``k`` (0: no graph written), ``searched`` (rows whose
    list came from a search of the whole index), ``updated`` (copied rows whose list a new
    row entered), ``kept`` (copied rows whose list was reused as it was), ``processes``
    (forked worker processes that searched the rows; 0: the building process, on threads, or
    a cluster), ``scheduler`` (the Dask cluster whose ``workers`` searched the rows; "": this
    machine), ``seconds``."""

    k: int = 0
    distance: str = "exact"
    searched: int = 0
    updated: int = 0
    kept: int = 0
    processes: int = 0
    seconds: float = 0.0
    scheduler: str = ""
    workers: int = 0


def check_lists(
    rows: NDArray[np.int64], neighbour: NDArray[np.int64], distance: NDArray[np.float64], N: int
) -> str | None:
    """Why some of these graph rows are not valid lists (docs/index-format.md, "/graph"), or
    None: ``rows`` (m,) their row numbers, ``neighbour`` / ``distance`` (m, K).

    A neighbour outside 0..N-1 other than the padding -1, padding before a real neighbour or
    with a finite distance, a row naming itself or a row twice, a NaN, a negative or
    infinite distance of a real neighbour, distances that decrease along a list (by more than
    the ties' 1e-9: tied distances are ordered by id)."""
    problems = list_problems(rows, neighbour, distance, N)
    for what, bad in problems.items():
        if len(bad):
            name = "neighbour" if what in NEIGHBOUR_PROBLEMS else "distance"
            return f"/graph/{name}, row {int(bad[0])}: {what}"
    return None


NEIGHBOUR_PROBLEMS = ("a neighbour outside the index", "a row naming itself", "a row named twice")


def list_problems(
    rows: NDArray[np.int64], neighbour: NDArray[np.int64], distance: NDArray[np.float64], N: int
) -> dict[str, NDArray[np.int64]]:
    """What :func:`check_lists` checks, as ``{problem: (n,) rows that have it}``."""
    rows = np.asarray(rows, dtype=np.int64).reshape(-1)
    nb = np.asarray(neighbour, dtype=np.int64)
    d = np.asarray(distance, dtype=np.float64)
    pad = nb == -1
    real = ~pad
    with np.errstate(invalid="ignore"):
        outside = ((nb < -1) | (nb >= N)).any(axis=1)
        myself = (nb == rows[:, None]).any(axis=1)
        twice = np.zeros(len(rows), dtype=bool)
        if nb.shape[1] > 1:
            ordered = np.sort(np.where(real, nb, -1 - np.arange(nb.shape[1])[None, :]), axis=1)
            twice = (ordered[:, 1:] == ordered[:, :-1]).any(axis=1)
        nan = np.isnan(d).any(axis=1)
        # padding only after the real neighbours, with distance inf
        bad_pad = (real[:, 1:] & pad[:, :-1]).any(axis=1) | (pad & (d != np.inf)).any(axis=1)
        negative = (real & (d < 0)).any(axis=1)
        infinite = (real & np.isinf(d)).any(axis=1)
        dr = np.where(real, d, np.inf)
        # ties (distances within TIE) are ordered by id: such a pair may descend by less than TIE
        descending = (dr[:, 1:] < dr[:, :-1] - TIE).any(axis=1) if nb.shape[1] > 1 else np.zeros(len(rows), bool)
    return {
        "a neighbour outside the index": rows[outside],
        "a row naming itself": rows[myself],
        "a row named twice": rows[twice & ~outside],
        "NaN": rows[nan],
        "a negative distance": rows[negative & ~nan],
        "an infinite distance for a neighbour": rows[infinite],
        "padding (-1, inf) before a neighbour or with a finite distance": rows[bad_pad & ~nan],
        "distances not ascending (nearest first)": rows[descending & ~nan & ~negative],
    }


def graph_datasets(index: Index) -> tuple[h5py.Dataset, h5py.Dataset] | None:
    """``(neighbour, distance)`` datasets of an open index's ``/graph``, checked as a reader
    checks every dataset (stored in the file, size, Fletcher-32 when the group says it has
    it, shapes (N, k) with k its attribute), or None when the index has no graph.

    Raises IndexFormatError when the group is there but malformed."""
    h5 = index._h5
    if h5 is None or "graph" not in h5:
        return None
    try:  # a damaged group header fails HDF5's own checksum here
        g = h5["graph"]
        checksums = _graph_checksums(g)
    except Exception as exc:  # noqa: BLE001 - h5py raises KeyError, OSError, ... for damage
        text = (str(exc).strip().strip("'\"").splitlines() or [type(exc).__name__])[0][:200]
        raise IndexFormatError(f"corrupted nfdmatch index: cannot read /graph ({text})", path=index.path) from None
    if checksums is None:
        raise IndexFormatError("corrupted nfdmatch index: /graph has an unknown checksums attribute", path=index.path)
    file_size = int(h5.id.get_filesize())
    try:
        nb = stored_dataset(h5, "graph/neighbour", file_size, checksums)
        d = stored_dataset(h5, "graph/distance", file_size, checksums)
    except Problem as exc:
        raise IndexFormatError(exc.message, path=index.path) from None
    N = index.n_curves
    k = old_graph_k(index)
    if len(nb.shape) != 2 or nb.shape != d.shape or nb.shape[0] != N or nb.shape[1] != k or k < 1:
        raise IndexFormatError(
            f"corrupted nfdmatch index: /graph holds {nb.shape} neighbours and {d.shape} distances "
            f"for {N} curves and k = {k}",
            path=index.path,
        )
    if nb.dtype.kind not in "iu" or d.dtype.kind != "f":
        raise IndexFormatError("corrupted nfdmatch index: /graph has the wrong types", path=index.path)
    return nb, d


def _graph_checksums(g) -> bool | None:
    if "checksums" not in g.attrs:
        return False
    value = text_attr(g.attrs, "checksums")
    return True if value == GRAPH_CHECKSUMS else None


def read_graph(index: Index) -> tuple[NDArray[np.int64], NDArray[np.float64]] | None:
    """The graph of an open :class:`~nfdmatch.index.Index`: ``(neighbour, distance)``,
    (N, K) int64 and (N, K) float64, or None when the index has none.

    Raises IndexFormatError when the group is there but malformed (:func:`graph_datasets`)
    or a list is not valid (:func:`check_lists`)."""
    found = graph_datasets(index)
    if found is None:
        return None
    ds_nb, ds_d = found

    def read():
        return np.asarray(ds_nb[...], dtype=np.int64), np.asarray(ds_d[...], dtype=np.float64)

    nb, dist = index._read(read, "/graph")
    problem = check_lists(np.arange(len(nb)), nb, dist, index.n_curves)
    if problem:
        raise IndexFormatError(f"corrupted nfdmatch index: {problem}", path=index.path)
    return nb, dist


def graph_k(index: Index) -> int:
    """Neighbours per row in an open index's graph; 0 when it has none."""
    return old_graph_k(index)


def old_graph_k(old: Index | None) -> int:
    if old is None or old._h5 is None or "graph" not in old._h5:
        return 0
    try:
        return int(old._h5["graph"].attrs["k"])
    except (KeyError, TypeError, ValueError, OSError):  # a damaged group: as if there were none
        return 0


def graph_distance(index: Index) -> str:
    """What an open index's graph holds (:data:`GRAPH_DISTANCES`): ``"exact"`` also for an
    index without a graph."""
    if index is None or index._h5 is None or "graph" not in index._h5:
        return "exact"
    return group_distance(index._h5["graph"])


def fused_version(index: Index) -> int | None:
    """The version of the fused distance (:data:`~nfdmatch.matching.fused.FUSED_VERSION`)
    an open index's graph holds: None without a graph of fused distances; 1 for one written
    before the attribute was."""
    if graph_distance(index) != "fused":
        return None
    try:
        return int(index._h5["graph"].attrs.get("fused_version", 1))
    except (KeyError, TypeError, ValueError, OSError):  # a damaged attribute: as the oldest
        return 1


def stale_fused_graph(index: Index | None) -> int | None:
    """The version of the fused distance of an index's graph when it is not this
    nfdmatch's (its lists would rank by another distance than the query's); else None."""
    from ..matching.fused import FUSED_VERSION

    try:
        version = fused_version(index) if index is not None else None
    except (KeyError, TypeError, ValueError, OSError):  # a damaged group: as if there were none
        return None
    return version if version is not None and version != FUSED_VERSION else None


def group_distance(g: h5py.Group) -> str:
    """What a ``/graph`` group's distances are, by its attribute ``distance`` (absent or
    unknown: ``"exact"``)."""
    value = text_attr(g.attrs, "distance")
    return value if value in GRAPH_DISTANCES else "exact"


def asked_graph(old: Index | None, graph: int | GraphSpec | None) -> tuple[int, str]:
    """``(k, distance)`` a build writes for its ``graph`` argument (None: the old index's
    graph, as it is; an int K: exact; a :class:`GraphSpec`)."""
    if graph is None:
        return old_graph_k(old), graph_distance(old)
    if isinstance(graph, GraphSpec):
        return int(graph.k), graph.distance
    return int(graph), "exact"


def graph_changes(old: Index | None, graph: int | GraphSpec | None) -> bool:
    """True when a build asked for ``graph`` (as :func:`asked_graph` reads it) must rewrite
    an index that is otherwise up to date (a graph asked for that it lacks or has with
    another K or distance, or one to drop; a graph of fused distances of another version
    than this nfdmatch's, also when no graph was asked for: it is kept, so computed afresh)."""
    stale = stale_fused_graph(old) is not None
    if graph is None:
        return stale  # the graph is kept as it is: of today's fused distance
    k, distance = asked_graph(old, graph)
    return (
        k != old_graph_k(old)
        or (k > 0 and distance != graph_distance(old))
        or (k > 0 and distance == "fused" and stale)
    )


def reverse_of(neighbour: NDArray[np.int64], N: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The graph's lists turned round (``/graph/reverse_start``, ``/graph/reverse_source``):
    the rows whose lists name row v are ``source[start[v]:start[v + 1]]``, ascending.
    ``neighbour``: (N, K) int, -1 padded. Returns ``start`` (N + 1,) and ``source`` (E,)
    int64, E the real entries of ``neighbour``."""
    neighbour = np.asarray(neighbour, dtype=np.int64)
    target = neighbour.reshape(-1)
    source = np.repeat(np.arange(len(neighbour), dtype=np.int64), neighbour.shape[1] if neighbour.ndim == 2 else 0)
    real = target >= 0
    source, target = source[real], target[real]
    order = np.argsort(target, kind="stable")
    start = np.zeros(N + 1, dtype=np.int64)
    np.cumsum(np.bincount(target, minlength=N)[:N], out=start[1:])
    return start, source[order]


def reverse_datasets(index: Index) -> tuple[h5py.Dataset, h5py.Dataset] | None:
    """``(reverse_start, reverse_source)`` of an open index's ``/graph``, checked as
    :func:`graph_datasets` checks its lists (shapes (N + 1,) and (E,)), or None when the graph
    has none (written before turn 4's second session: the walk then turns the lists round
    in memory). Raises IndexFormatError when they are there but malformed."""
    found = graph_datasets(index)
    g = index._h5["graph"] if found is not None else None
    if g is None or "reverse_start" not in g or "reverse_source" not in g:
        return None
    file_size, checksums = int(index._h5.id.get_filesize()), bool(_graph_checksums(g))
    try:
        start = stored_dataset(index._h5, "graph/reverse_start", file_size, checksums)
        source = stored_dataset(index._h5, "graph/reverse_source", file_size, checksums)
    except Problem as exc:
        raise IndexFormatError(exc.message, path=index.path) from None
    N = index.n_curves
    kinds = start.dtype.kind + source.dtype.kind
    if start.shape != (N + 1,) or len(source.shape) != 1 or any(kind not in "iu" for kind in kinds):
        raise IndexFormatError(
            f"corrupted nfdmatch index: /graph/reverse_start {start.shape} and reverse_source {source.shape} "
            f"do not fit {N} curves",
            path=index.path,
        )
    return start, source


def read_reverse_rows(
    index: Index,
) -> Callable[[NDArray[np.int64]], tuple[NDArray[np.int64], NDArray[np.int64]]] | None:
    """A reader of the rows that name given rows in their lists, ``rows -> (count, source)``:
    ``count`` (m,) int64 per row of ``rows`` and ``source`` their sources concatenated in that
    order (ascending within a row); or None when the graph does not store them
    (:func:`reverse_datasets`). Reads only what it is asked for; every read checked: offsets
    that do not rise within ``/graph/reverse_source``, a source outside the index, are an
    IndexFormatError."""
    found = reverse_datasets(index)
    if found is None:
        return None
    ds_start, ds_source = found
    N, E = index.n_curves, ds_source.shape[0]

    def fail(what: str) -> IndexFormatError:
        return IndexFormatError(f"corrupted nfdmatch index: /graph/reverse_{what}", path=index.path)

    def read(rows):
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if not len(rows):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        ends, inverse = unique_rows(np.concatenate([rows, rows + 1]))
        at = np.asarray(index._read(lambda: ds_start[ends], "/graph"), dtype=np.int64)[inverse]
        first, last = at[: len(rows)], at[len(rows) :]
        count = last - first
        if (count < 0).any() or first.min() < 0 or last.max() > E:
            raise fail("start: offsets that do not rise within reverse_source")
        if not count.sum():
            return count, np.zeros(0, np.int64)
        positions = np.repeat(first - np.cumsum(count) + count, count) + np.arange(count.sum())
        uniq, back = unique_rows(positions)
        source = np.asarray(index._read(lambda: ds_source[uniq], "/graph"), dtype=np.int64)[back]
        if source.min() < 0 or source.max() >= N:
            raise fail("source: a source outside the index")
        return count, source

    return read


def read_graph_rows(
    index: Index,
) -> Callable[[NDArray[np.int64]], tuple[NDArray[np.int64], NDArray[np.float64]]] | None:
    """A reader of an open index's graph rows, ``rows -> (neighbour, distance)`` ((m, K)
    int64 / float64, in the order of ``rows``, repeats allowed), or None when the index has
    no graph. Reads only the rows asked for (a query needs about M + M K of them); every
    row read is checked (:func:`check_lists`): a bad one is an IndexFormatError."""
    found = graph_datasets(index)
    if found is None:
        return None
    ds_nb, ds_d = found
    N = index.n_curves

    def read(rows):
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if len(rows) == 0:
            return np.zeros((0, ds_nb.shape[1]), np.int64), np.zeros((0, ds_nb.shape[1]))
        if rows.min() < 0 or rows.max() >= N:
            raise IndexError(f"row out of range 0..{N - 1}")
        uniq, inverse = unique_rows(rows)
        nb, d = index._read(
            lambda: (np.asarray(ds_nb[uniq], dtype=np.int64), np.asarray(ds_d[uniq], dtype=np.float64)), "/graph"
        )
        problem = check_lists(uniq, nb, d, N)
        if problem:
            raise IndexFormatError(f"corrupted nfdmatch index: {problem}", path=index.path)
        return nb[inverse], d[inverse]

    return read
