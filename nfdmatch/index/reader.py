"""The read side: :func:`open_index` and :class:`Index`."""

from __future__ import annotations

import os

import h5py
import numpy as np

from ..errors import IndexFormatError, NfdError, ParameterError
from .schema import _STATUS, INDEX_FORMAT, FileRecord, _open_checked, _Problem, _short, default_index_path


def open_index(path=None) -> "Index":
    """Open an index for reading (formats 1 and 2; ``path`` None: :func:`default_index_path`).

    The file is opened without HDF5 file locking, so a running build never blocks or
    breaks a reader (builds replace the file atomically, never write into it).

    Raises
    ------
    ReadError : no file at ``path`` ("no index at PATH; build one with ..."), a directory,
        no permission.
    IndexFormatError : an empty file, not HDF5, truncated/corrupted, an HDF5 file of
        another kind, a newer format version, missing or inconsistent datasets.
    """
    p = default_index_path() if path is None else str(os.fspath(path))
    try:
        h5, meta, files = _open_checked(p)
    except _Problem as exc:
        raise IndexFormatError(exc.message, path=p) from None
    return Index(p, h5, meta, files)


class Index:
    """An open index (read side). Use :func:`open_index`; a context manager.

    Attributes
    ----------
    path : str; format_version : int; nfdmatch_version : str (the writer's);
    samples, harmonics : int; scale : str ("rms" or "a1"); created, updated : str (ISO-8601 UTC);
    n_curves, n_files : int.
    """

    def __init__(self, path: str, h5, meta: dict, files: dict):
        self.path = path
        self._h5 = h5
        self._ds = meta["datasets"]
        self._files = files
        self._file_records = None
        self.format_version: int = meta["format_version"]
        self.nfdmatch_version: str = meta["nfdmatch_version"]
        self.samples: int = meta["samples"]
        self.harmonics: int = meta["harmonics"]
        self.scale: str = meta["scale"]
        self.created: str = meta["created"]
        self.updated: str = meta["updated"]
        self.n_curves: int = meta["n_curves"]
        self.n_files: int = meta["n_files"]

    # -- life cycle
    def close(self) -> None:
        if self._h5 is not None:
            try:
                self._h5.close()
            finally:
                self._h5 = None

    def __enter__(self) -> "Index":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    def __repr__(self) -> str:
        return (f"Index({self.path!r}, curves={self.n_curves}, files={self.n_files}, samples={self.samples}, "
                f"harmonics={self.harmonics}, scale={self.scale!r})")

    def _read(self, fn):
        if self._h5 is None:
            raise IndexFormatError("the index is closed", path=self.path)
        try:
            return fn()
        except NfdError:
            raise
        except Exception as exc:
            raise IndexFormatError(f"corrupted nfdmatch index: reading failed ({_short(exc)})",
                                   path=self.path) from None

    def _range(self, start, stop) -> tuple[int, int]:
        start, stop, _ = slice(start, stop).indices(self.n_curves)
        return start, max(start, stop)

    # -- the file table
    def files(self) -> list[FileRecord]:
        """The ``/files`` table, sorted by path (read on first use)."""
        if self._file_records is None:
            def read():
                fds, F = self._files["datasets"], self.n_files
                if F == 0:
                    return []
                paths = fds["path"].asstr()[...].tolist()
                errors = fds["error"].asstr()[...].tolist()
                shas = [s.decode("ascii", "replace") if isinstance(s, bytes) else str(s)
                        for s in fds["sha256"][...].tolist()]
                size, mtime = fds["size"][...].tolist(), fds["mtime_ns"][...].tolist()
                status = fds["status"][...].tolist()
                starts, counts = self._files["curve_start"].tolist(), self._files["curve_count"].tolist()
                return [FileRecord(paths[i], int(size[i]), int(mtime[i]), shas[i],
                                   _STATUS.get(int(status[i]), "failed"), errors[i], int(starts[i]),
                                   int(counts[i])) for i in range(F)]
            self._file_records = self._read(read)
        return list(self._file_records)

    # -- where the files are (docs/index-format.md, "Paths and ids")
    def sources(self):
        """``(paths, glob)`` of the last build, as stored (``glob`` None for none), or None for
        an index that does not record them (format 1, or an earlier format-2 writer)."""
        def read():
            g = self._h5.get("sources")
            ds = g.get("path") if isinstance(g, h5py.Group) else None
            # optional and only a build's default: a malformed one counts as absent
            if not isinstance(ds, h5py.Dataset) or len(ds.shape) != 1 or ds.dtype.kind not in "OS" \
                    or ds.shape[0] > 100_000:
                return None
            paths = ds.asstr()[...].tolist() if ds.shape[0] else []
            glob = g.attrs.get("glob", "")
            glob = glob.decode("utf-8", "replace") if isinstance(glob, bytes) else str(glob)
            return paths, (glob or None)
        return self._read(read)

    def locate(self, curve_id: str) -> str:
        """A path (``file#i`` kept) that opens the file of a stored id from the working
        directory: a relative stored path is relative to the index's folder. An index that does
        not record its sources stored paths relative to its build's working directory: ids
        are then returned as they are."""
        from .paths import index_folder, openable

        if os.path.isabs(curve_id) or self.sources() is None:
            return curve_id
        return openable(curve_id, index_folder(self.path))

    # -- curves
    def ids(self, start: int = 0, stop: int | None = None) -> list[str]:
        """Curve ids of rows ``[start, stop)`` (Python slice rules)."""
        a, b = self._range(start, stop)
        if a == b:
            return []
        return self._read(lambda: self._ds["id"].asstr()[a:b].tolist())

    def ids_at(self, rows) -> list[str]:
        """Curve ids of the given rows (any order, repeats allowed)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if len(rows) == 0:
            return []
        if rows.min() < 0 or rows.max() >= self.n_curves:
            raise IndexError(f"row out of range 0..{self.n_curves - 1}")
        uniq, inverse = np.unique(rows, return_inverse=True)
        lo, hi = int(uniq[0]), int(uniq[-1]) + 1
        if hi - lo <= 4 * len(uniq) + 4096:       # one contiguous read beats scattered ones
            span = np.asarray(self._read(lambda: self._ds["id"].asstr()[lo:hi]), dtype=object)
            got = span[uniq - lo]
        else:
            got = np.asarray(self._read(lambda: self._ds["id"].asstr()[uniq]), dtype=object)
        return got[inverse].tolist()

    def coefficients_at(self, rows) -> np.ndarray:
        """(m, K, 3) complex64 descriptors of the given rows (any order, repeats allowed): a
        search reads only the rows that need an exact distance."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        K = self.harmonics
        if len(rows) == 0:
            return np.zeros((0, K, 3), np.complex64)
        if rows.min() < 0 or rows.max() >= self.n_curves:
            raise IndexError(f"row out of range 0..{self.n_curves - 1}")
        uniq, inverse = np.unique(rows, return_inverse=True)
        got = np.asarray(self._read(lambda: self._ds["coefficients"][uniq]))
        return got[inverse]

    _ALL_COLUMNS = ("coefficients", "inv_norm", "inv_sv", "inv_block", "centroid", "scale", "rotation",
                    "plane_degenerate", "file")

    def read_rows(self, start: int, stop: int, columns=None, *, upcast: bool = True) -> dict:
        """Rows ``[start, stop)`` as float64/complex128 arrays.

        Keys (all by default, or those in ``columns``): ``coefficients`` (m, K, 3) complex128;
        ``inv_norm`` (m, K), ``inv_sv`` (m, 2K), ``inv_block`` (m, 3) float64; ``centroid``
        (m, 3) float64; ``scale`` (m,) float64; ``rotation`` (m, 3, 3) float64;
        ``plane_degenerate`` (m,) bool; ``file`` (m,) int64 (row in :meth:`files`).
        ``upcast=False`` keeps the stored complex64/float32 (a search upcasts only the rows it
        needs, which matters for large indexes).
        """
        a, b = self._range(start, stop)
        names = self._ALL_COLUMNS if columns is None else tuple(columns)
        unknown = set(names) - set(self._ALL_COLUMNS)
        if unknown:
            raise ParameterError(f"unknown index columns: {', '.join(sorted(unknown))}")
        raw = self._read(lambda: {name: self._ds[name][a:b] for name in names})
        if not upcast:
            return raw
        out = {}
        for name, value in raw.items():
            if name == "coefficients":
                out[name] = value.astype(np.complex128)
            elif name == "plane_degenerate":
                out[name] = value.astype(bool)
            elif name == "file":
                out[name] = value.astype(np.int64)
            else:
                out[name] = value.astype(np.float64)
        return out

    def iter_chunks(self, rows: int = 65536, columns=None, *, upcast: bool = True):
        """Yield ``(start, read_rows(start, start + rows, columns))`` covering every row in order."""
        if rows < 1:
            raise ParameterError(f"rows must be at least 1, got {rows}")
        for start in range(0, self.n_curves, rows):
            yield start, self.read_rows(start, min(self.n_curves, start + rows), columns, upcast=upcast)

    def _raw_rows(self, a: int, b: int) -> dict:
        """Rows [a, b) in storage dtypes, ids as str (for copying into a new index)."""
        def read():
            out = {name: ds[a:b] for name, ds in self._ds.items() if name not in ("id", "file")}
            out["id"] = np.asarray(self._ds["id"].asstr()[a:b], dtype=object)
            return out
        return self._read(read)

    def search_table(self):
        """What a search reads (:class:`~nfdmatch.search.table.SearchTable`): the stored
        cells of a format-2 index, read cell by cell as a query opens them; for format 1,
        every row's features in one cell (read whole: slower on large indexes)."""
        if self._h5 is None:
            raise IndexFormatError("the index is closed", path=self.path)
        if self.format_version >= 2:
            from .search_group import search_table

            def fail(message):
                raise IndexFormatError(f"corrupted nfdmatch index: {message}", path=self.path)

            return self._read(lambda: search_table(self._h5, self.n_curves, self.harmonics,
                                                   self.coefficients_at, fail))
        from ..search.table import SearchTable

        from ..search.bounds import head_harmonics

        def features():
            # the first harmonics only (the truncated bound's input): the exact distances
            # read their rows' descriptors on demand
            sv, block = self._ds["inv_sv"][...], self._ds["inv_block"][...]
            return np.concatenate([sv, block], axis=1), self._ds["coefficients"][:, :head_harmonics(self.harmonics)]

        F, head = self._read(features)
        return SearchTable.single_cell(self.harmonics, F, head, self.coefficients_at)

    def info(self) -> dict:
        """Summary: ``path, format, format_version, nfdmatch_version, files, curves, failed``
        (list of ``{path, error}``), ``samples, harmonics, scale, created, updated, size_bytes``."""
        try:
            size = int(self._h5.id.get_filesize()) if self._h5 is not None else os.path.getsize(self.path)
        except Exception:
            size = os.path.getsize(self.path) if os.path.exists(self.path) else 0
        failed = [{"path": r.path, "error": r.error} for r in self.files() if r.status != "ok"]
        recorded = self.sources()
        return {"path": self.path, "sources": None if recorded is None else recorded[0], "format": INDEX_FORMAT, "format_version": self.format_version,
                "nfdmatch_version": self.nfdmatch_version, "files": self.n_files, "curves": self.n_curves,
                "failed": failed, "samples": self.samples, "harmonics": self.harmonics, "scale": self.scale,
                "created": self.created, "updated": self.updated, "size_bytes": size}
