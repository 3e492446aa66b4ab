"""The read side: :func:`open_index` and :class:`Index`."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TYPE_CHECKING

import h5py
import numpy as np

from ..search.object_distance import ObjectLoops, StoredRows
from ..search.objects import search_objects
from .objects_group import read_objects, rule_of
from ..errors import MAX_MESSAGE_CHARS, IndexFormatError, NfdError, ParameterError, excerpt
from ..matching.statistics import curve_statistics
from ..search.bounds import head_harmonics
from ..records import RowIds
from ..search.knn import SearchFace
from ..search.table import SearchTable
from .arrays import first_nonfinite, read_runs, unique_rows
from .changes import read_changes
from .graph import fused_version, graph_distance, graph_k, read_graph_rows, read_reverse_rows
from ..names import decode_name
from .paths import index_folder, openable
from .schema import (
    STATUS,
    CRC_ROWS,
    INDEX_FORMAT,
    FileRecord,
    open_checked,
    Problem,
    _short,
    block_crcs,
    default_index_path,
    text_attr,
)
from .heap import HeapProblem, check_string_rows
from .search_group import search_table

if TYPE_CHECKING:
    from ..mesh.objects import ObjectRule
    from ..search.objects import ObjectMatch
    from .objects_group import ObjectsGroup

#: stored numbers that must be finite (the /curves ones; /search is checked as it is read)
_FLOAT_COLUMNS = ("coefficients", "rotation", "centroid", "scale", "inv_norm", "inv_sv", "inv_block", "statistics")


#: rows per chunk of :meth:`Index.iter_chunks` (``nfdmatch.search.memory.CHUNK_ROWS`` is the
#: same for curves in memory)
ITER_CHUNK_ROWS = 65536


def read_error(exc: BaseException, where: str) -> str:
    """The message of a failed HDF5 read of ``where``: a failed Fletcher-32 check says so."""
    text = _short(exc)
    if "filter returned failure" in text or "checksum" in text.lower():
        return (
            f"corrupted nfdmatch index: checksum mismatch in {where} (the file is damaged; "
            f"`nfdmatch index verify` lists what is bad)"
        )
    return f"corrupted nfdmatch index: reading {where} failed ({text})"


def open_index(path: str | os.PathLike[str] | None = None) -> Index:
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
        h5, meta, files = open_checked(p)
    except Problem as exc:
        raise IndexFormatError(exc.message, path=p) from None
    return Index(p, h5, meta, files)


def _reopen(path: str, stamp: tuple) -> Index:
    """An unpickled :class:`Index`: the file reopened, refused if it changed since."""
    index = open_index(path)
    if index._stamp() != tuple(stamp):
        index.close()
        raise IndexFormatError("the index changed since it was pickled (rebuilt or replaced): open it again", path=path)
    return index


_UNREAD = object()


class Index(SearchFace):
    """An open index (read side). Use :func:`open_index`; a context manager.

    Attributes
    ----------
    path : str; format_version : int; nfdmatch_version : str (the writer's);
    checksums : bool (the file carries checksums, checked as it is read);
    samples, harmonics : int; scale_mode : str ("rms" or "a1", the ``scale`` attribute of the
    file); created, updated : str (ISO-8601 UTC); n_curves, n_files : int.
    ``scale`` is a deprecated alias of ``scale_mode`` (a descriptor's ``scale`` is its size).
    """

    def __init__(self, path: str, h5: h5py.File, meta: dict[str, Any], files: dict[str, Any]) -> None:
        self.path = path
        self._h5 = h5
        self._ds = meta["datasets"]
        self._files = files
        self._file_records = None
        self._sources: Any = _UNREAD
        self._objects = None
        self.checksums: bool = meta.get("checksums", False)
        #: HDF5 parses nothing of the file unchecked (schema.checked_metadata); False: an
        #: older file, read after a check of every heap collection, rewritten by a build
        self.checked_metadata: bool = meta.get("checked_metadata", False)
        self._crc = meta.get("crc", {})
        self.format_version: int = meta["format_version"]
        self.nfdmatch_version: str = meta["nfdmatch_version"]
        self.samples: int = meta["samples"]
        self.harmonics: int = meta["harmonics"]
        self.scale_mode: str = meta["scale"]
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

    def __reduce__(self):
        # h5py handles do not pickle: the path does, with what identifies this version of
        # the file, so that a worker's copy reads the same index or fails
        return (_reopen, (self.path, self._stamp()))

    def _stamp(self) -> tuple:
        return (self.updated, self.n_curves, self.n_files, self.harmonics, self.samples, self.scale_mode)

    def __repr__(self) -> str:
        return (
            f"Index({self.path!r}, curves={self.n_curves}, files={self.n_files}, samples={self.samples}, "
            f"harmonics={self.harmonics}, scale_mode={self.scale_mode!r})"
        )

    def _read(self, fn, where: str = "the index"):
        """``fn()``, with any failure of the read as an IndexFormatError about ``where``."""
        if self._h5 is None:
            raise IndexFormatError("the index is closed", path=self.path)
        try:
            return fn()
        except NfdError:
            raise
        except HeapProblem as exc:
            self._bad(str(exc))
        except Exception as exc:
            raise IndexFormatError(read_error(exc, where), path=self.path) from None

    def _bad(self, message: str):
        raise IndexFormatError(f"corrupted nfdmatch index: {message}", path=self.path)

    def _finite(self, name: str, values, rows, group: str = "curves"):
        row = first_nonfinite(values, rows)
        if row is not None:
            self._bad(f"non-finite value (NaN or Inf) in /{group}/{name}, row {row}")
        return values

    def _check_strings(self, crc_ds, name: str, blocks, values_of_block) -> None:
        """Compare the CRC-32 of each CRC_ROWS-row block in ``blocks`` with ``crc_ds`` (a no-op
        for a file without checksums); ``values_of_block(b)`` gives that block's strings."""
        if crc_ds is None:
            return
        blocks = [int(b) for b in blocks]
        if not blocks:
            return
        lo, hi = min(blocks), max(blocks) + 1
        stored = np.asarray(self._read(lambda: crc_ds[lo:hi], f"{crc_ds.name}"), dtype=np.uint32)
        for b in blocks:
            values = values_of_block(b)
            if int(block_crcs(values, len(values) or 1)[0] if values else 0) != int(stored[b - lo]):
                self._bad(f"checksum mismatch in {name}, rows {b * CRC_ROWS}..{b * CRC_ROWS + len(values) - 1}")

    def _strings(self, ds, runs, read):
        """``read()`` of string dataset ``ds``'s rows ``runs`` once the heap collections they
        use passed their check (heap.py: HDF5 could loop forever on a damaged one)."""

        def checked():
            check_string_rows(ds, runs)
            return read()

        return checked

    def _id_blocks(self, lo: int, hi: int) -> list[str]:
        """Ids of rows [lo, hi) read in whole CRC_ROWS-row blocks, each block's CRC checked."""
        ids = self._ds["id"]
        if not self.checksums:
            return self._read(self._strings(ids, [(lo, hi)], lambda: ids.asstr()[lo:hi].tolist()), "/curves/id")
        a, b = lo // CRC_ROWS * CRC_ROWS, min(self.n_curves, -(-hi // CRC_ROWS) * CRC_ROWS)
        values = self._read(
            self._strings(ids, [(a, b)], lambda: ids.asstr()[a:b].tolist()), f"/curves/id, rows {a}..{b - 1}"
        )
        self._check_strings(
            self._crc.get("id_crc32"),
            "/curves/id",
            range(a // CRC_ROWS, -(-b // CRC_ROWS)),
            lambda blk: values[blk * CRC_ROWS - a : (blk + 1) * CRC_ROWS - a],
        )
        return values[lo - a : hi - a]

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
                check_string_rows(fds["path"], [(0, F)])
                check_string_rows(fds["error"], [(0, F)])
                paths = fds["path"].asstr()[...].tolist()
                errors = fds["error"].asstr()[...].tolist()
                crc = self._files.get("crc", {})
                for name, values in (("path", paths), ("error", errors)):
                    if self.checksums:
                        self._check_strings(
                            crc.get(f"{name}_crc32"),
                            f"/files/{name}",
                            range(-(-F // CRC_ROWS)),
                            lambda b, v=values: v[b * CRC_ROWS : (b + 1) * CRC_ROWS],
                        )
                shas = [
                    s.decode("ascii", "replace") if isinstance(s, bytes) else str(s)
                    for s in fds["sha256"][...].tolist()
                ]
                size, mtime = fds["size"][...].tolist(), fds["mtime_ns"][...].tolist()
                status = fds["status"][...].tolist()
                starts, counts = self._files["curve_start"].tolist(), self._files["curve_count"].tolist()
                # a crafted file's messages are cut as a build cuts them (index info prints them)
                errors = [e if len(e) <= MAX_MESSAGE_CHARS else excerpt(e, MAX_MESSAGE_CHARS) for e in errors]
                return [
                    FileRecord(
                        paths[i],
                        int(size[i]),
                        int(mtime[i]),
                        shas[i],
                        STATUS.get(int(status[i]), "failed"),
                        errors[i],
                        int(starts[i]),
                        int(counts[i]),
                    )
                    for i in range(F)
                ]

            self._file_records = self._read(read, "/files")
        return list(self._file_records)

    # -- where the files are (docs/index-format.md, "Paths and ids")
    def sources(self) -> tuple[list[str], str | None] | None:
        """``(paths, glob)`` of the last build, as stored (``glob`` None for none), or None for
        an index that does not record them (format 1, or an earlier format-2 writer). Read
        once: :meth:`locate` asks for every match a batch reports."""
        if self._sources is _UNREAD:
            self._sources = self._read_sources()
        if self._sources is None:
            return None
        paths, glob = self._sources
        return list(paths), glob

    def _read_sources(self):
        def read():
            g = self._h5.get("sources")
            ds = g.get("path") if isinstance(g, h5py.Group) else None
            # optional and only a build's default: a malformed one counts as absent
            if (
                not isinstance(ds, h5py.Dataset)
                or len(ds.shape) != 1
                or ds.dtype.kind not in "OS"
                or ds.shape[0] > 100_000
            ):
                return None
            check_string_rows(ds, [(0, ds.shape[0])])
            paths = ds.asstr()[...].tolist() if ds.shape[0] else []
            glob = text_attr(g.attrs, "glob") or ""
            return paths, (glob or None)

        return self._read(read)

    def excluded(self) -> list[str]:
        """Stored paths (files, or folders and all below them) the recorded sources' walk
        leaves out (``index remove`` of a file found in a source folder); [] for none."""

        def read():
            g = self._h5.get("sources")
            ds = g.get("exclude") if isinstance(g, h5py.Group) else None
            if not isinstance(ds, h5py.Dataset) or len(ds.shape) != 1 or ds.dtype.kind not in "OS":
                return []
            return ds.asstr()[...].tolist() if ds.shape[0] else []

        return self._read(read)

    def locate(self, curve_id: str) -> str:
        """A path (``file#i`` kept) that opens the file of a stored id from the working
        directory: a relative stored path is relative to the index's folder. An index that does
        not record its sources stored paths relative to its build's working directory: ids
        are then returned as they are."""

        if os.path.isabs(curve_id) or self.sources() is None:
            return decode_name(curve_id)
        return openable(curve_id, index_folder(self.path))

    # -- curves
    @property
    def ids(self) -> RowIds:
        """The curve ids by row: ``index.ids[row]``, ``index.ids[a:b]``, ``index.ids[rows]``
        (read on demand); ``index.ids(start, stop)`` is the older spelling of a slice."""
        return RowIds(self.n_curves, self.ids_at, self._id_span)

    def _id_span(self, start: int, stop: int) -> list[str]:
        a, b = self._range(start, stop)
        if a == b:
            return []
        return self._id_blocks(a, b)

    def ids_at(self, rows: Any) -> list[str]:
        """Curve ids of the given rows (any order, repeats allowed)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if len(rows) == 0:
            return []
        if rows.min() < 0 or rows.max() >= self.n_curves:
            raise IndexError(f"row out of range 0..{self.n_curves - 1}")
        uniq, inverse = unique_rows(rows)
        lo, hi = int(uniq[0]), int(uniq[-1]) + 1
        if hi - lo <= 4 * len(uniq) + 4096:  # one contiguous read beats scattered ones
            span = np.asarray(self._id_blocks(lo, hi), dtype=object)
            got = span[uniq - lo]
        elif self.checksums:  # whole CRC blocks, to check them, in one read
            blocks = unique_rows(uniq // CRC_ROWS)[0]
            runs = [(int(b) * CRC_ROWS, min(self.n_curves, (int(b) + 1) * CRC_ROWS)) for b in blocks]
            ids = self._ds["id"]
            values = self._read(self._strings(ids, runs, lambda: read_runs(ids, runs)), "/curves/id")
            offset = {int(b): i * CRC_ROWS for i, b in enumerate(blocks)}  # every block but the last is full
            self._check_strings(
                self._crc.get("id_crc32"),
                "/curves/id",
                blocks,
                lambda blk: values[offset[blk] : offset[blk] + CRC_ROWS],
            )
            got = np.asarray([values[offset[int(r) // CRC_ROWS] + int(r) % CRC_ROWS] for r in uniq], dtype=object)
        else:
            ids = self._ds["id"]
            cut = np.flatnonzero(np.diff(uniq) != 1) + 1  # runs of consecutive rows
            runs = [(int(s[0]), int(s[-1]) + 1) for s in np.split(uniq, cut)]
            values = self._read(self._strings(ids, runs, lambda: ids.asstr()[uniq]), "/curves/id")
            got = np.asarray(values, dtype=object)
        return got[inverse].tolist()

    def coefficients_at(self, rows: Any) -> np.ndarray:
        """(m, K, 3) complex64 descriptors of the given rows (any order, repeats allowed): a
        search reads only the rows that need an exact distance."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        K = self.harmonics
        if len(rows) == 0:
            return np.zeros((0, K, 3), np.complex64)
        if rows.min() < 0 or rows.max() >= self.n_curves:
            raise IndexError(f"row out of range 0..{self.n_curves - 1}")
        uniq, inverse = unique_rows(rows)
        got = np.asarray(self._read(lambda: self._ds["coefficients"][uniq], "/curves/coefficients"))
        self._finite("coefficients", got, uniq)
        return got[inverse]

    _ALL_COLUMNS = (
        "coefficients",
        "inv_norm",
        "inv_sv",
        "inv_block",
        "centroid",
        "scale",
        "rotation",
        "plane_degenerate",
        "file",
    )

    def read_rows(self, start: int, stop: int, columns: Sequence[str] | None = None, *, upcast: bool = True) -> dict:
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
        raw = {}
        for name in names:
            raw[name] = self._read(lambda: self._ds[name][a:b], f"/curves/{name}, rows {a}..{b - 1}")
            if name in _FLOAT_COLUMNS:
                self._finite(name, raw[name], a)
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

    def iter_chunks(
        self, rows: int = ITER_CHUNK_ROWS, columns: Sequence[str] | None = None, *, upcast: bool = True
    ) -> Iterator[tuple[int, dict]]:
        """Yield ``(start, read_rows(start, start + rows, columns))`` covering every row in order."""
        if rows < 1:
            raise ParameterError(f"rows must be at least 1, got {rows}")
        for start in range(0, self.n_curves, rows):
            yield start, self.read_rows(start, min(self.n_curves, start + rows), columns, upcast=upcast)

    def statistics_at(self, rows: Any) -> np.ndarray:
        """(m, LENGTH) float64 shape statistics of the given rows (the elastic stage's,
        :func:`nfdmatch.matching.statistics.curve_statistics` of the stored coefficients):
        stored in format 3, computed from the coefficients in formats 1 and 2."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if "statistics" not in self._ds:
            return curve_statistics(np.asarray(self.coefficients_at(rows), dtype=np.complex128)).reshape(len(rows), -1)
        if len(rows) == 0:
            return np.zeros((0, self._ds["statistics"].shape[1]))
        if rows.min() < 0 or rows.max() >= self.n_curves:
            raise IndexError(f"row out of range 0..{self.n_curves - 1}")
        uniq, inverse = unique_rows(rows)
        got = np.asarray(self._read(lambda: self._ds["statistics"][uniq], "/curves/statistics"))
        self._finite("statistics", got, uniq)
        return got[inverse].astype(np.float64)

    def _raw_rows(self, a: int, b: int) -> dict:
        """Rows [a, b) in storage dtypes, ids as str (for copying into a new index)."""
        out = {}
        for name, ds in self._ds.items():
            if name not in ("id", "file"):
                out[name] = self._read(lambda: ds[a:b], f"/curves/{name}, rows {a}..{b - 1}")
                if name in _FLOAT_COLUMNS:
                    self._finite(name, out[name], a)
        out["id"] = np.asarray(self._id_blocks(a, b), dtype=object)
        return out

    def objects(self) -> ObjectsGroup | None:
        """The index's objects (:class:`~nfdmatch.index.objects_group.ObjectsGroup`: the meshes
        it holds, their contours' axes, levels and measures, their profiles), read and
        checked once; None when it holds none (docs/index-format.md, ``/objects``)."""
        if self._objects is None:

            def read():
                size = int(self._h5.id.get_filesize())
                return read_objects(self._h5, self.n_curves, self.n_files, size, self.checksums)

            self._objects = (self._read(read, "/objects"),)
        return self._objects[0]

    def object_ids(self) -> list[str]:
        """The objects' ids: their meshes' stored paths, in ``objects()`` order."""
        groups = self.objects()
        if groups is None:
            return []
        if self._file_records is not None:
            records = self._file_records
            return [records[int(f)].path for f in groups.file]
        paths = self._file_paths()  # not the whole /files table: 1 s at 100,000 files
        return [paths[int(f)] for f in groups.file]

    def _file_paths(self) -> list[str]:
        """``/files/path`` alone, read and checked as :meth:`files` reads it."""

        def read():
            ds, F = self._files["datasets"]["path"], self.n_files
            if F == 0:
                return []
            check_string_rows(ds, [(0, F)])
            paths = ds.asstr()[...].tolist()
            if self.checksums:
                self._check_strings(
                    self._files.get("crc", {}).get("path_crc32"),
                    "/files/path",
                    range(-(-F // CRC_ROWS)),
                    lambda b: paths[b * CRC_ROWS : (b + 1) * CRC_ROWS],
                )
            return paths

        return self._read(read, "/files")

    def object_loops(self) -> ObjectLoops | None:
        """Every object's contours as :class:`~nfdmatch.search.object_distance.ObjectLoops` (their
        stored descriptors, axes, levels, measures; ``rows`` their /curves rows), what a mesh
        query compares with; None when the index holds no object."""
        groups = self.objects()
        if groups is None:
            return None
        # each object's rows [curve_start, curve_start + curve_count) of its file, in order
        starts, counts = self._files["curve_start"][groups.file], self._files["curve_count"][groups.file]
        owner = np.full(self.n_curves, -1, dtype=np.int64)
        owner[_ranges_of(starts, counts)] = np.repeat(np.arange(len(starts)), counts)
        rows = np.flatnonzero((owner >= 0) & (groups.axis >= 0))
        # an index of meshes alone: one run of rows, taken as views (4 M rows: no 150 MB copy)
        at = slice(int(rows[0]), int(rows[-1]) + 1) if len(rows) and rows[-1] - rows[0] + 1 == len(rows) else rows
        return ObjectLoops(
            coefficients=StoredRows(rows, lambda at: self._runs_at(("coefficients",), at)),
            axis=groups.axis[at],
            level=groups.level[at],
            measures=groups.measures[at],
            owner=owner[at],
            profile=groups.profile,
            sections=groups.rule.sections,
            rows=rows,
            features=StoredRows(rows, lambda at: self._runs_at(("inv_sv", "inv_block"), at)),
        )

    def _runs_at(self, names: tuple[str, ...], rows: Any) -> np.ndarray:
        """The /curves datasets ``names`` (their columns side by side) at ``rows`` (any order),
        read by runs of consecutive rows: an object's contours are one run, so a mesh query
        reads a few runs per object its bounds reach, never every row of the index."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        uniq, inverse = unique_rows(rows)
        cut = np.flatnonzero(np.diff(uniq) != 1) + 1
        runs = [(int(r[0]), int(r[-1]) + 1) for r in np.split(uniq, cut) if len(r)]
        parts = []
        for name in names:
            ds = self._ds[name]
            got = np.asarray(self._read(lambda: read_runs(ds, runs), f"/curves/{name}"))
            parts.append(self._finite(name, got, uniq))
        return (parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1))[inverse]

    def search_objects(
        self,
        meshes: Any,
        k: int | None = 10,
        max_distance: float | None = None,
        exclude_self: bool = False,
        **options: Any,
    ) -> list[list[ObjectMatch]]:
        """Each query mesh's nearest objects (:func:`nfdmatch.search.objects.search_objects`):
        ``meshes`` a mesh path, a ``trimesh.Trimesh`` or a list of them; one list of
        :class:`~nfdmatch.search.objects.ObjectMatch` per mesh. ``Index.search`` of a mesh
        comes here."""
        return search_objects(self, meshes, k=k, max_distance=max_distance, exclude_self=exclude_self, **options)

    def object_rule(self) -> ObjectRule | None:
        """The :class:`~nfdmatch.mesh.objects.ObjectRule` the index's meshes were cut by, or
        None when it holds no mesh."""
        return self._read(lambda: rule_of(self._h5), "/objects")

    def graph_k(self) -> int:
        """Neighbours per row of the index's stored neighbour graph (``index build --graph``);
        0 when it has none."""
        return graph_k(self)

    def graph_distance(self) -> str:
        """What the stored graph's distances are: ``"exact"`` (also without a graph) or
        ``"fused"`` (the elastic stage's: ``index build --graph K --elastic``)."""
        return graph_distance(self)

    def graph_fused_version(self) -> int | None:
        """The version of the fused distance the stored graph holds
        (:data:`~nfdmatch.matching.fused.FUSED_VERSION`); None for a graph of exact distances
        or none."""
        return self._read(lambda: fused_version(self), "/graph")

    def graph_reader(self) -> Callable[[Any], tuple[np.ndarray, np.ndarray]] | None:
        """``rows -> (neighbour (m, K) int64, distance (m, K) float64)`` of the stored graph,
        in the order of ``rows``; None when the index has no graph (docs/index-format.md)."""
        return read_graph_rows(self)

    def graph_reverse_reader(self) -> Callable[[Any], tuple[np.ndarray, np.ndarray]] | None:
        """``rows -> (count (m,), source)``: the rows whose graph lists name each of ``rows``,
        concatenated (:func:`~nfdmatch.index.graph.read_reverse_rows`); None when the graph
        does not store them (a graph written before turn 4's second session, or none)."""
        return read_reverse_rows(self)

    def new_rows(self) -> np.ndarray | None:
        """The rows (int64, ascending) that the build which wrote the index added or
        recomputed (``/changes``, what ``pairs --new`` restricts to); None when the index
        does not record them."""
        return read_changes(self)

    def search_table(self) -> SearchTable:
        """What a search reads (:class:`~nfdmatch.search.table.SearchTable`): the stored
        cells of a format-2 index, read cell by cell as a query opens them; for format 1,
        every row's features in one cell (read whole: slower on large indexes)."""
        if self._h5 is None:
            raise IndexFormatError("the index is closed", path=self.path)
        if self.format_version >= 2:

            def fail(message):
                raise IndexFormatError(f"corrupted nfdmatch index: {message}", path=self.path)

            return self._read(
                lambda: search_table(self._h5, self.n_curves, self.harmonics, self.coefficients_at, fail, self._read),
                "/search",
            )

        def features():
            # the first harmonics only (the truncated bound's input): the exact distances
            # read their rows' descriptors on demand
            sv, block = self._ds["inv_sv"][...], self._ds["inv_block"][...]
            return np.concatenate([sv, block], axis=1), self._ds["coefficients"][:, : head_harmonics(self.harmonics)]

        F, head = self._read(features, "/curves")
        self._finite("inv_sv, inv_block", F, 0)
        self._finite("coefficients", head, 0)
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
        return {
            "path": self.path,
            "sources": None if recorded is None else recorded[0],
            "format": INDEX_FORMAT,
            "format_version": self.format_version,
            "metadata": "checked" if self.checked_metadata else "older",
            "nfdmatch_version": self.nfdmatch_version,
            "files": self.n_files,
            "curves": self.n_curves,
            "failed": failed,
            "samples": self.samples,
            "harmonics": self.harmonics,
            "scale": self.scale_mode,
            "created": self.created,
            "updated": self.updated,
            "size_bytes": size,
        }


def _ranges_of(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The positions ``[start, start + count)`` of each run, concatenated."""
    total = int(counts.sum())
    ends = np.cumsum(counts)
    return np.arange(total, dtype=np.int64) - np.repeat(ends - counts, counts) + np.repeat(starts, counts)
