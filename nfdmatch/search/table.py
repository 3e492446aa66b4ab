"""What a search reads: rows' features grouped in cells, and their descriptors on demand.

A :class:`SearchTable` hides where the rows live (an index file of format 2, read cell by
cell as the search opens them; a format-1 file or curves in memory, one cell holding
every row) behind the same calls, so the best-first loop has one form.
"""

from __future__ import annotations

import threading
from typing import Callable, TYPE_CHECKING

import numpy as np

from .bounds import cell_lower_bounds, feature_split, squared_norms

if TYPE_CHECKING:
    from collections.abc import Sequence

__all__ = ["SearchTable"]


def _concatenated(parts: list) -> tuple:
    """Reads of several ranges as one: each field concatenated (None stays None)."""
    return tuple(None if parts[0][i] is None else np.concatenate([p[i] for p in parts]) for i in range(4))


def _ranges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The positions of the runs [lo_i, hi_i) concatenated, (sum(hi - lo),) int64."""
    lengths = hi - lo
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    steps = np.ones(total, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    nonempty = lengths > 0
    steps[starts[nonempty]] = lo[nonempty] - np.concatenate([[lo[nonempty][0]], (hi[nonempty] - 1)[:-1]])
    steps[0] = lo[nonempty][0]
    return np.cumsum(steps)


#: once reads would pass this fraction of the positions, the table is read whole at once
_READ_ALL_FRACTION = 0.25
#: the same for the descriptors, read apart (most rows a search bounds never need them)
_READ_ALL_DESCRIPTORS_FRACTION = 0.5
#: a search expecting fewer rows than this for the first truncated bound reads their cells'
#: descriptors whole, not their first harmonics apart: on a clustered index (15 rows a
#: query) the exact distances soon need the rest, and a second read of the same cells cost
#: more than the bytes saved (a 1,000-query cluster batch went from 5-7 s to 9-11 s)
_HEAD_FROM_ROWS = 2048
#: an HDF5 read call costs about as much as reading this many more bytes: cells closer than
#: that are read in one call, the positions between them with them. Chosen by timing queries
#: in new processes (48 KB, from ~60 us per call measured in a loop at ~0.7 GB/s, was
#: slower: a new process pays more per call than a warm loop)
_CALL_BYTES = 280 * 1024


class _Tier:
    """Descriptors read so far at one width: ``harmonics`` first harmonics of each row
    (None: all of them), by cell or (``all``) for every position."""

    def __init__(self, harmonics: int | None):
        self.harmonics = harmonics
        self.how = {} if harmonics is None else {"harmonics": harmonics}
        self.cells: dict[int, np.ndarray] = {}  # cell -> (m, H, 3) descriptors
        self.all = None
        self.read = 0  # positions read


class SearchTable:
    """Rows in cell-major order with their invariant features.

    Parameters
    ----------
    harmonics : K.
    start : (C + 1,) int64 cell offsets into the positions; centre : (C, D) float64;
        radius : (C, 2) float64 (see :class:`nfdmatch.search.cells.Cells`).
    read_positions : ``read_positions(a, b) -> (row (m,) int64, features (m, D) float32,
        sqnorm (m, 2) float64, coefficients (m, K'', 3) complex)`` for positions [a, b):
        the rows' descriptors, all K harmonics (an index of format 2, curves in memory: the
        exact distance needs no other read) or only the first K'' <= K (a format-1 file,
        where reading every descriptor at once would cost too much; the truncated bound
        needs K'' >= min(4, K)).
        ``sqnorm`` may be None (computed here from the features, as the build computes it);
        ``coefficients`` may be None when ``read_descriptors`` is given.
    read_coefficients : ``read_coefficients(rows) -> (m, K, 3)`` complex for index rows.
    read_descriptors : ``read_descriptors(a, b) -> (m, K'', 3)`` complex for positions [a, b),
        called only for the cells whose rows a search takes past the invariant bound (an
        index file: most opened cells never need their descriptors, the largest part of a
        row).
    read_runs, read_descriptor_runs : optional, the same for a list of ``(a, b)`` ranges at
        once (concatenated): an index file reads them in one HDF5 call.
    head_harmonics : H > 0 when the descriptor readers also take ``harmonics=H`` and then
        return only the first H harmonics for fewer bytes (an index whose descriptors are
        stored in chunks of H harmonics): the first truncated bound, which needs no more,
        is then served from those (a search bounds many rows there, and computes exact
        distances for few).

    Thread-safe: the search answers several queries on threads over one table.
    """

    def __init__(
        self,
        harmonics: int,
        start: np.ndarray,
        centre: np.ndarray,
        radius: np.ndarray,
        read_positions: Callable,
        read_coefficients: Callable,
        read_descriptors: Callable | None = None,
        *,
        read_runs: Callable | None = None,
        read_descriptor_runs: Callable | None = None,
        head_harmonics: int = 0,
    ) -> None:
        self.harmonics = harmonics
        self.split = feature_split(harmonics)
        self.start = np.asarray(start, dtype=np.int64)
        self.centre = np.asarray(centre, dtype=np.float64)
        self.radius = np.asarray(radius, dtype=np.float64)
        self._centre_sqnorm = None
        self.n_positions = int(self.start[-1]) if len(self.start) else 0
        self._read_positions = read_positions
        self._read_coefficients = read_coefficients
        self._read_descriptors = read_descriptors
        self._read_runs = read_runs or (lambda runs: _concatenated([read_positions(a, b) for a, b in runs]))
        if read_descriptor_runs is None and read_descriptors is not None:

            def read_descriptor_runs(runs, **how):
                return np.concatenate([read_descriptors(a, b, **how) for a, b in runs])

        self._read_descriptor_runs = read_descriptor_runs
        self._cells: dict[int, tuple] = {}  # cell -> (row, features, sqnorm)
        self._all = None  # the same for every position, once read whole
        self._full = _Tier(None)  # descriptors, every harmonic the table holds
        self._head = _Tier(head_harmonics) if head_harmonics and read_descriptors is not None else None
        self._positions_read = 0
        self._lock = threading.Lock()
        self._coefficient_shape, self._coefficient_dtype = (harmonics, 3), np.complex64
        self.bytes_read = 0

    @classmethod
    def single_cell(
        cls, harmonics: int, features: np.ndarray, coefficients: np.ndarray, read_coefficients: Callable
    ) -> "SearchTable":
        """Every row in one cell, in row order (a format-1 index, curves in memory).

        harmonics : K; features : (N, 2K + 3) float features (rounded to float32 here, as an
        index stores them); coefficients : (N, K'', 3) complex, the rows' descriptors (or
        their first K'' harmonics);
        read_coefficients : as for the constructor.
        """
        F = np.ascontiguousarray(features, dtype=np.float32)
        N = len(F)
        sq = squared_norms(F, feature_split(harmonics))
        rows = np.arange(N, dtype=np.int64)
        # radius inf: the one cell's bound is 0, every row gets its own bound
        return cls(
            harmonics,
            [0, N],
            np.zeros((1, F.shape[1])),
            np.full((1, 2), np.inf),
            lambda a, b: (rows[a:b], F[a:b], sq[a:b], coefficients[a:b]),
            read_coefficients,
        )

    @classmethod
    def from_cells(
        cls,
        harmonics: int,
        features: np.ndarray,
        coefficients: np.ndarray,
        read_coefficients: Callable,
        *,
        rows_per_cell: int,
    ) -> "SearchTable":
        """Cells built in memory (:func:`~nfdmatch.search.cells.build_cells`), as an index
        file stores them; arguments as :meth:`single_cell`."""
        from .cells import build_cells

        split = feature_split(harmonics)
        F = np.ascontiguousarray(features, dtype=np.float32)
        cells = build_cells(F, split, rows_per_cell=rows_per_cell)
        F = F[cells.row]
        sq = squared_norms(F, split)
        row = cells.row
        coefficients = np.asarray(coefficients)[row]
        return cls(
            harmonics,
            cells.start,
            cells.centre,
            cells.radius,
            lambda a, b: (row[a:b], F[a:b], sq[a:b], coefficients[a:b]),
            read_coefficients,
        )

    def subset(self, cells: Sequence[int] | np.ndarray | tuple[int, int]) -> SearchTable:
        """The table of the given cells only (ascending cell numbers, or a ``(first, stop)``
        range); their rows keep their index row numbers. A search over it answers for that
        part of the index, so parts searched apart merge into the whole table's answer
        (``--scheduler``: a range of cells per task). A range reads its positions directly;
        scattered cells read through this table (its coalesced reads and cache)."""
        C = self.n_cells
        if isinstance(cells, tuple):
            first, stop = cells
            if not 0 <= first < stop <= C:
                raise IndexError(f"cells [{first}, {stop}) outside 0..{C}")
            offset = int(self.start[first])
            read, read_descriptors = self._read_positions, self._read_descriptors
            shifted = (
                None
                if read_descriptors is None
                else (lambda a, b, **how: read_descriptors(a + offset, b + offset, **how))
            )
            return SearchTable(
                self.harmonics,
                self.start[first : stop + 1] - offset,
                self.centre[first:stop],
                self.radius[first:stop],
                lambda a, b: read(a + offset, b + offset),
                self._read_coefficients,
                shifted,
                head_harmonics=self._head.harmonics if self._head is not None else 0,
            )
        cells = np.asarray(cells, dtype=np.int64)
        if len(cells) == 0 or cells.min() < 0 or cells.max() >= C or (np.diff(cells) <= 0).any():
            raise IndexError(f"cells must be ascending numbers in 0..{C - 1}")
        start = np.concatenate([[0], np.cumsum(self.start[cells + 1] - self.start[cells])])

        def read_cells(a: int, b: int):
            # the sub-table reads whole cells (runs of them, or everything): map to ours
            i, j = int(np.searchsorted(start, a, side="right")) - 1, int(np.searchsorted(start, b, side="left"))
            got = self.cell_rows(cells[i:j])
            lo = a - int(start[i])
            return tuple(x[lo : lo + (b - a)] for x in got)

        return SearchTable(
            self.harmonics, start, self.centre[cells], self.radius[cells], read_cells, self._read_coefficients
        )

    @property
    def n_cells(self) -> int:
        return len(self.start) - 1

    def cell_bounds(self, query_features: np.ndarray, *, clip: bool = True) -> np.ndarray:
        """(C,) :func:`~nfdmatch.search.bounds.cell_lower_bounds` of every cell for a query's
        (D,) float64 features (the centres' squared norms computed once per table)."""
        if self._centre_sqnorm is None:
            self._centre_sqnorm = squared_norms(self.centre, self.split)
        return cell_lower_bounds(query_features, self.split, self.centre, self.radius, self._centre_sqnorm, clip=clip)

    @property
    def stored_harmonics(self) -> int:
        """K'': the harmonics the table hands out per row (known once a cell was read; a
        table reading descriptors apart holds all K)."""
        return self._coefficient_shape[0]

    def cell_rows(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The rows of the given cells, concatenated: ``(row (m,) int64, features (m, D)
        float32, sqnorm (m, 2) float64, coefficients (m, K'', 3) complex)``."""
        positions, rows, F, sq = self.open_cells(cells)
        return rows, F, sq, self.coefficients_at_positions(positions)

    def open_cells(self, cells: np.ndarray, expect: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What a search needs to bound the rows of the given cells: ``(positions (m,)
        int64, row (m,) int64, features (m, D) float32, sqnorm (m, 2) float64)``; their
        descriptors stay in the table (:meth:`coefficients_at_positions`).

        Cells not read yet are read in few calls: runs of cells whose positions are close
        are read as one range (each call costs far more than the bytes between them), and
        every cell of a range is kept for later queries. Once the reads would pass
        :data:`_READ_ALL_FRACTION` of the table, the whole table is read at once; so also
        when the caller expects (``expect``) to open that many positions in all (a hint: the cells
        its threshold does not rule out yet), rather than reading runs first.
        """
        cells = np.asarray(cells, dtype=np.int64)
        if self._all is None:
            missing = [int(c) for c in cells if int(c) not in self._cells]
            if missing:
                wanted = int((self.start[np.array(missing) + 1] - self.start[np.array(missing)]).sum())
                wanted = max(wanted, expect - self._positions_read)
                if self._positions_read + wanted > _READ_ALL_FRACTION * self.n_positions:
                    self._load_all()
                else:
                    self._read_cells(sorted(missing))
        if len(cells) == 1:
            a, b = int(self.start[cells[0]]), int(self.start[cells[0] + 1])
            positions = np.arange(a, b, dtype=np.int64)
            if self._all is not None:
                return (positions,) + tuple(x[a:b] for x in self._all[:3])
            return (positions,) + self._cells[int(cells[0])]
        lo, hi = self.start[cells], self.start[cells + 1]
        positions = _ranges(lo, hi)
        if self._all is not None:
            return (positions,) + tuple(x[positions] for x in self._all[:3])
        parts = [self._cells[int(c)] for c in cells]
        return (positions,) + tuple(np.concatenate([p[i] for p in parts]) for i in range(3))

    def expect_more(self, queries: int) -> None:
        """The caller will answer ``queries`` more queries like those answered so far (a
        batch, after its first): the cells' features, and each width of descriptors, whose
        reads so far repeated that many times would pass the read-all fraction are read
        whole now, in one call, rather than in runs by every query."""
        if not self.n_positions or queries <= 0 or self._read_descriptors is None:
            return  # (a table in memory reads nothing)
        if self._all is None and self._positions_read * (1 + queries) > _READ_ALL_FRACTION * self.n_positions:
            self._load_all()
        for tier in (self._head, self._full):
            if tier is not None and tier.all is None:
                if tier.read * (1 + queries) > _READ_ALL_DESCRIPTORS_FRACTION * self.n_positions:
                    self._load_all_descriptors(tier)

    def read_whole(self) -> None:
        """Read every position's row, features and descriptors now: a table shared with
        forked worker processes must hold everything (they never read the file)."""
        if not self.n_positions:
            return
        self._load_all()
        if self._full.all is None and self._read_descriptors is not None:
            self._load_all_descriptors(self._full)

    def coefficients_at_positions(
        self, positions: np.ndarray, harmonics: int | None = None, expect: int = 0
    ) -> np.ndarray:
        """(m, K', 3) complex descriptors (as stored) at positions of opened cells: the
        first ``harmonics`` (default: all the table holds, K''). Descriptors not read yet
        are read here, for the cells holding ``positions`` (all at once once the reads
        would pass :data:`_READ_ALL_DESCRIPTORS_FRACTION` of the table); only their first
        H harmonics when those are enough and the table reads them apart
        (``head_harmonics``) and the caller expects (``expect``, as for :meth:`open_cells`)
        at least :data:`_HEAD_FROM_ROWS` rows at this width in all."""
        positions = np.asarray(positions, dtype=np.int64)
        h = self._coefficient_shape[0] if harmonics is None else min(harmonics, self._coefficient_shape[0])
        full, head = self._full, self._head
        if full.all is not None:
            return full.all[positions, :h]
        tier = head if head is not None and h <= head.harmonics else full
        if tier.all is not None:
            return tier.all[positions, :h]
        out = np.empty((len(positions), h, 3), dtype=self._coefficient_dtype)
        if not len(positions):
            return out
        cell = np.searchsorted(self.start, positions, side="right") - 1
        order = np.argsort(cell, kind="stable")
        bounds = np.flatnonzero(np.diff(cell[order])) + 1
        groups = np.split(order, bounds)
        missing = sorted({int(cell[g[0]]) for g in groups} - full.cells.keys() - tier.cells.keys())
        if missing:
            wanted = int((self.start[np.array(missing) + 1] - self.start[np.array(missing)]).sum())
            if tier is head and expect < _HEAD_FROM_ROWS:
                tier = full  # few rows: most go on to the exact distance, which reads them whole
            wanted = max(wanted, expect - tier.read)
            if tier.read + wanted > _READ_ALL_DESCRIPTORS_FRACTION * self.n_positions:
                self._load_all_descriptors(tier)
                return tier.all[positions, :h]
            self._read_cell_descriptors(tier, missing)
        for group in groups:
            c = int(cell[group[0]])
            held = full.cells.get(c)
            if held is None:
                held = tier.cells[c] if c in tier.cells else head.cells[c]
            out[group] = held[positions[group] - self.start[c], :h]
        return out

    def _runs(self, cells: list[int], row_bytes: int, datasets: int = 1) -> list[list[int]]:
        """Position ranges covering ``cells`` (ascending), cells joined when the positions
        between them (``row_bytes`` each) cost less to read than one more call on each of
        ``datasets`` datasets."""
        gap = datasets * _CALL_BYTES // max(1, row_bytes)
        runs: list[list[int]] = []
        for c in cells:
            a, b = int(self.start[c]), int(self.start[c + 1])
            if runs and a - runs[-1][1] <= gap:
                runs[-1][1] = max(runs[-1][1], b)
            else:
                runs.append([a, b])
        return runs

    def _descriptor_bytes(self, tier: "_Tier") -> int:
        """Bytes per position of the descriptors ``tier`` reads."""
        harmonics = tier.harmonics or self._coefficient_shape[0]
        return harmonics * 3 * np.dtype(self._coefficient_dtype).itemsize

    def _position_bytes(self) -> int:
        """Bytes per position of a cell read (row number and features)."""
        return 8 + 4 * self.centre.shape[1]

    def _read_cell_descriptors(self, tier: "_Tier", cells: list[int]) -> None:
        with self._lock:
            runs = self._runs([c for c in cells if c not in tier.cells], self._descriptor_bytes(tier))
            if not runs:
                return
            got = self._read_descriptor_runs(runs, **tier.how)  # type: ignore[misc]
            self.bytes_read += got.nbytes
            self._store_descriptors(tier, runs, got)

    def _cells_of_runs(self, runs):
        """``(cell, lo, hi)`` of every cell the position runs ``[(a, b), ...]`` hold: where
        its positions lie in the runs' rows read one after the other."""
        at = 0
        for a, b in runs:
            first = int(np.searchsorted(self.start, a, side="left"))
            last = int(np.searchsorted(self.start, b, side="left"))
            for c in range(first, last):
                yield c, at + int(self.start[c]) - a, at + int(self.start[c + 1]) - a
            at += b - a

    def _store_descriptors(self, tier: "_Tier", runs, got) -> None:
        tier.read += sum(b - a for a, b in runs)
        for c, lo, hi in self._cells_of_runs(runs):
            tier.cells.setdefault(c, got[lo:hi])

    def _load_all_descriptors(self, tier: "_Tier") -> None:
        with self._lock:
            if tier.all is None:
                got = self._read_descriptors(0, self.n_positions, **tier.how)  # type: ignore[misc]
                self.bytes_read += got.nbytes
                tier.all = got

    def _read_cells(self, cells: list[int]) -> None:
        """Read ``cells`` (ascending) in runs of nearby positions, all runs in one call;
        cache every cell read."""
        with self._lock:
            runs = self._runs(cells, self._position_bytes(), 2)
            got = self._complete(self._read_runs(runs))
            self.bytes_read += sum(x.nbytes for x in got if x is not None)
            self._positions_read += sum(b - a for a, b in runs)
            for c, lo, hi in self._cells_of_runs(runs):
                self._cells[c] = tuple(x[lo:hi] for x in got[:3])
            if got[3] is not None:
                self._store_descriptors(self._full, runs, got[3])

    def _load_all(self) -> None:
        with self._lock:
            if self._all is None:
                got = self._complete(self._read_positions(0, self.n_positions))
                self.bytes_read += sum(x.nbytes for x in got if x is not None)
                self._all = tuple(got[:3])
                if got[3] is not None and self._full.all is None:
                    self._full.all = got[3]

    def _complete(self, got) -> list:
        """A read's (row, features, sqnorm, coefficients) with the squared norms computed
        when the reader left them out, and the descriptors' shape noted."""
        row, features, sqnorm, coefficients = got
        if sqnorm is None:
            sqnorm = squared_norms(features, self.split)
        if coefficients is not None:
            self._coefficient_shape = tuple(coefficients.shape[1:])
            self._coefficient_dtype = coefficients.dtype
        elif self._read_descriptors is None:
            raise ValueError("a search table without descriptors needs read_descriptors")
        return [row, features, sqnorm, coefficients]

    def coefficients(self, rows: np.ndarray) -> np.ndarray:
        """(m, K, 3) complex descriptors of index rows."""
        got = self._read_coefficients(rows)
        self.bytes_read += got.nbytes
        return got
