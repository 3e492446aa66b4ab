"""Curves held in memory behind the reading interface of an index."""

from __future__ import annotations

import numpy as np

from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE
from .table import SearchTable

#: rows per chunk of iter_chunks (as an index file's reader)
CHUNK_ROWS = 65536


class MemoryIndex:
    """Curves held in memory with the same reading interface as :class:`nfdmatch.index.Index`
    (``samples``, ``harmonics``, ``scale_mode``, ``n_curves``, ``iter_chunks``, ``ids_at``,
    ``search_table``; ``scale`` a deprecated alias of ``scale_mode``), so that
    :func:`search_index` serves both ``rank`` (no index file) and ``query``."""

    def __init__(
        self,
        curves,
        *,
        samples: int = DEFAULT_SAMPLES,
        harmonics: int = DEFAULT_HARMONICS,
        scale: str = DEFAULT_SCALE,
        rows_per_cell: int | None = None,
    ):
        from ..descriptors import descriptors_batch
        from ..matching import invariants

        self.samples, self.harmonics, self.scale_mode = samples, harmonics, scale
        batch = descriptors_batch(curves, samples=samples, harmonics=harmonics, scale=scale)
        self._ids = [c.id for c in curves]
        self._rows = {
            "coefficients": batch.coefficients,
            **{f"inv_{k}": v.reshape(len(curves), -1) for k, v in invariants(batch.coefficients).items()},
        }
        self.n_curves = len(curves)
        #: None: every row in one cell; else cells of about this many rows (as an index file)
        self.rows_per_cell = rows_per_cell

    @property
    def scale(self) -> str:
        """Deprecated alias of :attr:`scale_mode`."""
        return self.scale_mode

    def iter_chunks(self, rows: int = CHUNK_ROWS, columns=None, *, upcast: bool = True):
        for start in range(0, self.n_curves, rows):
            yield start, {k: v[start : start + rows] for k, v in self._rows.items() if columns is None or k in columns}

    def ids_at(self, rows) -> list[str]:
        return [self._ids[int(r)] for r in rows]

    def coefficients_at(self, rows) -> np.ndarray:
        return self._rows["coefficients"][np.asarray(rows, dtype=np.int64)]

    def statistics_at(self, rows) -> np.ndarray:
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
