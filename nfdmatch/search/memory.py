"""Curves held in memory behind the reading interface of an index."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from ..curve import Curve
from ..records import RowIds
from .knn import SearchFace
from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE
from .table import SearchTable

#: rows per chunk of iter_chunks (as an index file's reader)
CHUNK_ROWS = 65536


def _as_curves(curves: Any, ids: Sequence[str] | None) -> list[Curve]:
    """Curves from Curves or (n, 3) / (n, 2) arrays (a single array is one curve), named
    by ``ids`` when given (else their own id, or ``<array i>``)."""
    from ..errors import ParameterError

    if isinstance(curves, Curve) or (isinstance(curves, np.ndarray) and curves.ndim == 2):
        curves = [curves]
    out = [
        c if isinstance(c, Curve) else Curve(np.asarray(c, dtype=np.float64), id=f"<array {i}>")
        for i, c in enumerate(curves)
    ]
    if ids is not None:
        ids = [str(i) for i in ids]
        if len(ids) != len(out):
            raise ParameterError(f"{len(ids)} ids for {len(out)} curves")
        out = [Curve.trusted(c.points, name) for c, name in zip(out, ids)]
    return out


class MemoryIndex(SearchFace):
    """Curves held in memory with the same interface as :class:`nfdmatch.index.Index`:
    ``search`` (the same function, every option named; ``arrays=True`` for faiss's
    ``(distances, rows)``), ``ids[row]``, and the reading interface (``samples``,
    ``harmonics``, ``scale_mode``, ``n_curves``, ``iter_chunks``, ``ids_at``,
    ``search_table``; ``scale`` a deprecated alias of ``scale_mode``), so that
    :func:`search_index` serves both ``rank`` (no index file) and ``query``.

    curves : :class:`~nfdmatch.Curve` s or (n, 3) / (n, 2) arrays; row i is curve i.
    ids : names of the rows (default: each curve's id, ``<array i>`` for an array).
    """

    def __init__(
        self,
        curves: Any,
        ids: Sequence[str] | None = None,
        *,
        samples: int = DEFAULT_SAMPLES,
        harmonics: int = DEFAULT_HARMONICS,
        scale: str = DEFAULT_SCALE,
        rows_per_cell: int | None = None,
    ) -> None:
        from ..descriptors import descriptors_batch
        from ..matching import invariants

        curves = _as_curves(curves, ids)
        #: the curves, row by row (what :meth:`nfdmatch.MemoryIndex.save` writes)
        self.curves = curves
        self.samples, self.harmonics, self.scale_mode = samples, harmonics, scale
        batch = descriptors_batch(curves, samples=samples, harmonics=harmonics, scale=scale)
        self._ids = [c.id for c in curves]
        self._pose = {
            "rotation": batch.rotation,
            "centroid": batch.centroid,
            "scale": batch.scale,
            "plane_degenerate": batch.plane_degenerate,
        }
        self._rows = {
            "coefficients": batch.coefficients,
            **{f"inv_{k}": v for k, v in invariants(batch.coefficients).items()},  # (N, width) each
        }
        self.n_curves = len(curves)
        #: None: every row in one cell; else cells of about this many rows (as an index file)
        self.rows_per_cell = rows_per_cell

    def __repr__(self) -> str:
        return (
            f"MemoryIndex(curves={self.n_curves}, samples={self.samples}, harmonics={self.harmonics}, "
            f"scale_mode={self.scale_mode!r})"
        )

    @property
    def ids(self) -> RowIds:
        """The curve ids by row: ``ids[row]``, a slice, an array of rows."""
        return RowIds(self.n_curves, self.ids_at, lambda a, b: self._ids[a:b])

    def read_rows(self, start: int, stop: int, columns: Sequence[str] | None = None, **_: Any) -> dict:
        """Rows ``[start, stop)``: ``coefficients`` and the pose (``rotation``, ``centroid``,
        ``scale``, ``plane_degenerate``), as :meth:`nfdmatch.index.Index.read_rows`."""
        every = {"coefficients": self._rows["coefficients"], **self._pose}
        return {k: v[start:stop] for k, v in every.items() if columns is None or k in columns}

    def iter_chunks(
        self, rows: int = CHUNK_ROWS, columns: slice | None = None, *, upcast: bool = True
    ) -> Iterator[tuple[int, dict]]:
        for start in range(0, self.n_curves, rows):
            yield start, {k: v[start : start + rows] for k, v in self._rows.items() if columns is None or k in columns}

    def ids_at(self, rows: Any) -> list[str]:
        return [self._ids[int(r)] for r in rows]

    def coefficients_at(self, rows: Any) -> np.ndarray:
        return self._rows["coefficients"][np.asarray(rows, dtype=np.int64)]

    def statistics_at(self, rows: Any) -> np.ndarray:
        """(m, LENGTH) float64 shape statistics of the rows (the elastic stage's), computed
        for every row on first use."""
        if "statistics" not in self._rows:
            from ..matching.statistics import curve_statistics

            coefficients = np.asarray(self._rows["coefficients"], dtype=np.complex128)
            self._rows["statistics"] = curve_statistics(coefficients).reshape(len(coefficients), -1)
        return self._rows["statistics"][np.asarray(rows, dtype=np.int64)]

    def search_table(self) -> SearchTable:
        """Every row in one cell, or cells of ``rows_per_cell`` rows built as for an index."""
        K = self._rows["coefficients"].shape[1]
        features = np.concatenate([self._rows["inv_sv"], self._rows["inv_block"]], axis=1)
        coefficients = self._rows["coefficients"]
        if self.rows_per_cell is None:
            return SearchTable.single_cell(K, features, coefficients, self.coefficients_at)
        return SearchTable.from_cells(K, features, coefficients, self.coefficients_at, rows_per_cell=self.rows_per_cell)
