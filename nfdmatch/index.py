"""The HDF5 index of curve descriptors: reading (:func:`open_index`) and building (:func:`build_index`).

The on-disk format is specified in ``docs/index-format.md`` (format 1). This is the only
module that imports h5py; ``import nfdmatch`` does not import it.

Reading::

    with open_index("curves.h5") as idx:
        for start, rows in idx.iter_chunks():
            rows["coefficients"]            # (m, K, 3) complex128
        idx.ids(0, 10)

Building (incremental, crash-safe, parallel over files)::

    report = build_index(["curves/"], "curves.h5", jobs=2)
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import stat as _stat
import threading
import time
from dataclasses import dataclass, field

import h5py
import numpy as np

from ._version import __version__
from .descriptors import (DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, descriptors_batch,
                          validate_parameters)
from .errors import (IndexFormatError, IndexLockedError, InputError, NfdError, ParameterError, ReadError,
                     WriteError)
from .formats import format_of, read_curves
from .matching import invariants
from .sources import find_curve_files

__all__ = ["INDEX_FORMAT", "FORMAT_VERSION", "Index", "FileRecord", "BuildReport", "open_index",
           "build_index", "default_index_path"]

INDEX_FORMAT = "nfdmatch-index"
FORMAT_VERSION = 1

#: rows per HDF5 chunk of the /curves datasets (any layout is valid for readers)
CHUNK_ROWS = 4096
#: rows buffered before one write per dataset
_WRITE_ROWS = 65536
#: curves described per descriptors_batch call (bounds the (rows x samples x 3) work arrays)
_DESCRIBE_ROWS = 4096

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_STR = h5py.string_dtype("utf-8")
_SHA = "S64"
_STATUS = {0: "ok", 1: "failed"}

_FILE_FIELDS = ("path", "size", "mtime_ns", "sha256", "status", "error", "curve_start", "curve_count")


def _curve_layout(K: int) -> dict:
    """/curves dataset name -> (storage dtype, shape after the row axis)."""
    return {
        "id": (_STR, ()),
        "file": (np.int32, ()),
        "coefficients": (np.complex64, (K, 3)),
        "rotation": (np.float32, (3, 3)),
        "centroid": (np.float64, (3,)),
        "scale": (np.float64, ()),
        "plane_degenerate": (np.uint8, ()),
        "inv_norm": (np.float32, (K,)),
        "inv_sv": (np.float32, (2 * K,)),
        "inv_block": (np.float32, (3,)),
    }


def default_index_path() -> str:
    """``$NFDMATCH_INDEX`` if set (and not empty), else ``"nfdmatch.h5"``."""
    return os.environ.get("NFDMATCH_INDEX") or "nfdmatch.h5"


def _utcnow() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


@dataclass(frozen=True)
class FileRecord:
    """One row of the ``/files`` table.

    ``status`` is ``"ok"`` or ``"failed"``; ``error`` is ``""`` when ok; the file's
    curves are index rows ``[curve_start, curve_start + curve_count)``.
    """

    path: str
    size: int
    mtime_ns: int
    sha256: str
    status: str
    error: str
    curve_start: int
    curve_count: int


# --------------------------------------------------------------------------- opening

class _Problem(Exception):
    """Why a file is not a readable index; ``kind`` drives what a build may do with it:
    ``empty``, ``not_hdf5``, ``foreign`` (never overwritten), ``corrupt``, ``newer``."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind, self.message = kind, message


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[:200]


def _has_hdf5_signature(path: str) -> bool:
    """The HDF5 signature at offset 0, 512, 1024, 2048, ... (where HDF5 looks for it)."""
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            offset = 0
            while offset + 8 <= size:
                fh.seek(offset)
                if fh.read(8) == _HDF5_SIGNATURE:
                    return True
                offset = 512 if offset == 0 else offset * 2
    except OSError:
        return False
    return False


def _attr_str(attrs, name):
    value = attrs.get(name)
    if value is None:
        return None
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return value if isinstance(value, str) else None


def _attr_int(attrs, name):
    value = attrs.get(name)
    if isinstance(value, np.ndarray) and value.shape in ((), (1,)):
        value = value.reshape(())[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        return None
    return int(value)


def _open_checked(path: str):
    """Open ``path`` read-only and validate it as a format-1 index.

    Returns ``(h5py.File, meta dict, files dict of arrays)``.
    Raises ReadError (missing, directory, unreadable) or _Problem.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ReadError(f"no index at {path}; build one with `nfdmatch index build`") from None
    except OSError as exc:
        raise ReadError(f"cannot read the index: {exc.strerror or exc}", path=path) from None
    if _stat.S_ISDIR(st.st_mode):
        raise ReadError("is a directory, not an index file", path=path)
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise ReadError(f"cannot read the index: {exc.strerror or exc}", path=path) from None
    if st.st_size == 0:
        raise _Problem("empty", "empty file, not an nfdmatch index")
    try:
        h5 = h5py.File(path, "r", locking=False)
    except Exception as exc:  # h5py raises OSError, sometimes others, for damaged files
        if not _has_hdf5_signature(path):
            raise _Problem("not_hdf5", "not an nfdmatch index (not an HDF5 file)") from None
        raise _Problem("corrupt", f"truncated or corrupted HDF5 file ({_short(exc)})") from None
    try:
        meta, files = _validate(h5)
    except _Problem:
        h5.close()
        raise
    except Exception as exc:
        h5.close()
        raise _Problem("corrupt", f"corrupted nfdmatch index ({_short(exc)})") from None
    return h5, meta, files


def _validate(h5) -> tuple[dict, dict]:
    attrs = h5.attrs
    fmt = _attr_str(attrs, "format")
    if fmt != INDEX_FORMAT:
        what = "no 'format' attribute" if fmt is None else f"format attribute {fmt!r}"
        raise _Problem("foreign", f"an HDF5 file but not an nfdmatch index ({what})")
    version = _attr_int(attrs, "format_version")
    if version is None or version < 1:
        raise _Problem("corrupt", f"corrupted nfdmatch index: bad format_version {attrs.get('format_version')!r}")
    if version > FORMAT_VERSION:
        raise _Problem("newer", f"written by a newer nfdmatch (format {version}); "
                                f"this version reads format {FORMAT_VERSION}")
    samples, harmonics, scale = _attr_int(attrs, "samples"), _attr_int(attrs, "harmonics"), _attr_str(attrs, "scale")
    try:
        validate_parameters(samples, harmonics, scale)
    except ParameterError as exc:
        raise _Problem("corrupt", f"corrupted nfdmatch index: {exc.message}") from None
    meta = {"format_version": version, "samples": samples, "harmonics": harmonics, "scale": scale,
            "nfdmatch_version": _attr_str(attrs, "nfdmatch_version") or "",
            "created": _attr_str(attrs, "created") or "", "updated": _attr_str(attrs, "updated") or ""}

    def dataset(group, name, tail):
        obj = h5.get(f"{group}/{name}")
        if not isinstance(obj, h5py.Dataset):
            raise _Problem("corrupt", f"corrupted nfdmatch index: missing dataset /{group}/{name}")
        if len(obj.shape) != 1 + len(tail) or tuple(obj.shape[1:]) != tail:
            raise _Problem("corrupt", f"corrupted nfdmatch index: /{group}/{name} has shape {obj.shape}, "
                                      f"expected (rows, {', '.join(map(str, tail))})".replace(", )", ")"))
        return obj

    fds = {name: dataset("files", name, ()) for name in _FILE_FIELDS}
    F = fds["path"].shape[0]
    if any(d.shape[0] != F for d in fds.values()):
        raise _Problem("corrupt", "corrupted nfdmatch index: the /files datasets differ in length")
    cds = {name: dataset("curves", name, tail) for name, (_, tail) in _curve_layout(harmonics).items()}
    N = cds["id"].shape[0]
    if any(d.shape[0] != N for d in cds.values()):
        raise _Problem("corrupt", "corrupted nfdmatch index: the /curves datasets differ in length")
    if cds["coefficients"].dtype.kind != "c":
        raise _Problem("corrupt", "corrupted nfdmatch index: /curves/coefficients is not complex")
    counts = fds["curve_count"][...].astype(np.int64)
    starts = fds["curve_start"][...].astype(np.int64)
    expected = np.concatenate([[0], np.cumsum(counts)[:-1]]) if F else starts
    if (counts < 0).any() or not np.array_equal(starts, expected) or int(counts.sum()) != N:
        raise _Problem("corrupt", "corrupted nfdmatch index: the /files curve_start/curve_count blocks "
                                  "do not tile the /curves rows")
    files = {"datasets": fds, "curve_start": starts, "curve_count": counts}
    meta["datasets"] = cds
    meta["n_curves"], meta["n_files"] = int(N), int(F)
    return meta, files


def open_index(path=None) -> "Index":
    """Open an index for reading (format 1; ``path`` None: :func:`default_index_path`).

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

    def info(self) -> dict:
        """Summary: ``path, format, format_version, nfdmatch_version, files, curves, failed``
        (list of ``{path, error}``), ``samples, harmonics, scale, created, updated, size_bytes``."""
        try:
            size = int(self._h5.id.get_filesize()) if self._h5 is not None else os.path.getsize(self.path)
        except Exception:
            size = os.path.getsize(self.path) if os.path.exists(self.path) else 0
        failed = [{"path": r.path, "error": r.error} for r in self.files() if r.status != "ok"]
        return {"path": self.path, "format": INDEX_FORMAT, "format_version": self.format_version,
                "nfdmatch_version": self.nfdmatch_version, "files": self.n_files, "curves": self.n_curves,
                "failed": failed, "samples": self.samples, "harmonics": self.harmonics, "scale": self.scale,
                "created": self.created, "updated": self.updated, "size_bytes": size}


# --------------------------------------------------------------------------- the lock

class _Lock:
    """``flock(LOCK_EX)`` on ``INDEX.lock``; released by the kernel when the process dies."""

    def __init__(self, index_path: str, wait: float):
        self.path = index_path + ".lock"
        try:
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as exc:
            raise WriteError(f"cannot create the lock file {self.path}: {exc.strerror or exc}",
                             path=index_path) from None
        deadline = time.monotonic() + max(0.0, float(wait or 0.0))
        while True:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    os.close(self.fd)
                    raise WriteError(f"cannot lock {self.path}: {exc.strerror or exc}", path=index_path) from None
                left = deadline - time.monotonic()
                if left <= 0:
                    holder = self._holder()
                    os.close(self.fd)
                    waited = f" (waited {wait:g} s)" if wait else ""
                    raise IndexLockedError(
                        f"another build holds the lock on {self.path} (pid {holder}){waited}; "
                        f"retry later or pass --wait SECONDS", path=index_path) from None
                time.sleep(min(0.05, left))
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, f"{os.getpid()}\n".encode(), 0)

    def _holder(self) -> str:
        try:
            text = os.pread(self.fd, 32, 0).decode("ascii", "replace").strip()
            return text if text.isdigit() else "unknown"
        except OSError:
            return "unknown"

    def release(self) -> None:
        if self.fd is not None:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_UN)
            finally:
                os.close(self.fd)
                self.fd = None


# --------------------------------------------------------------------------- per-file work

def _sha256(path: str) -> str:
    import hashlib

    h = hashlib.sha256()
    buf = bytearray(1 << 20)
    view = memoryview(buf)
    with open(path, "rb") as fh:
        while True:
            n = fh.readinto(buf)
            if not n:
                break
            h.update(view[:n])
    return h.hexdigest()


def _describe(curves, samples: int, harmonics: int, scale: str) -> dict:
    """Storage-dtype arrays of the /curves datasets (except id and file) for ``curves``."""
    parts = []
    for i in range(0, len(curves), _DESCRIBE_ROWS):
        b = descriptors_batch(curves[i:i + _DESCRIBE_ROWS], samples=samples, harmonics=harmonics, scale=scale)
        m = len(b)
        c64 = b.coefficients.astype(np.complex64)
        inv = invariants(c64.astype(np.complex128))
        parts.append({
            "coefficients": c64,
            "rotation": b.rotation.astype(np.float32),
            "centroid": np.asarray(b.centroid, dtype=np.float64),
            "scale": np.asarray(b.scale, dtype=np.float64),
            "plane_degenerate": np.asarray(b.plane_degenerate, dtype=np.uint8),
            "inv_norm": inv["norm"].reshape(m, harmonics).astype(np.float32),
            "inv_sv": inv["sv"].reshape(m, 2 * harmonics).astype(np.float32),
            "inv_block": inv["block"].reshape(m, 3).astype(np.float32),
        })
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _compute_file(path: str, input_format, samples: int, harmonics: int, scale: str, old_sha) -> dict:
    """Stat, hash, read and describe one file. Never raises (except BaseException such as
    KeyboardInterrupt): a failure is returned as ``status "failed"`` with its message.

    With ``old_sha`` given and equal to the file's hash, returns ``status "same"`` without
    parsing the file.
    """
    out = {"path": path, "size": 0, "mtime_ns": 0, "sha256": "", "status": "failed", "error": ""}
    try:
        st = os.stat(path)
        out["size"], out["mtime_ns"] = int(st.st_size), int(st.st_mtime_ns)
        if _stat.S_ISDIR(st.st_mode):
            raise ReadError("is a directory, not a curve file", path=path)
        out["sha256"] = _sha256(path)
        if old_sha and out["sha256"] == old_sha:
            out["status"] = "same"
            return out
        curves = read_curves(path, format=input_format)
        out["arrays"] = _describe(curves, samples, harmonics, scale)
        out["ids"] = [c.id for c in curves]
        out["status"] = "ok"
    except NfdError as exc:
        out["error"] = str(exc)
    except OSError as exc:
        out["error"] = str(ReadError(f"cannot read: {exc.strerror or exc}", path=path))
    except Exception as exc:  # a bug must not sink the build: record it against the file
        out["error"] = f"{path}: unexpected error: {type(exc).__name__}: {exc}"
    return out


def _worker_init(lock_fd) -> None:
    """Pool worker set-up: drop the inherited lock descriptor (so a worker outliving its
    parent cannot keep the index locked) and exit when the parent goes away."""
    if lock_fd is not None:
        try:
            os.close(lock_fd)
        except OSError:
            pass
    parent = os.getppid()

    def watch():
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, daemon=True, name="nfdmatch-parent-watch").start()


def _needs_pyvista(tasks) -> bool:
    """True when some task reads a VTK-family file (pyvista costs ~0.3 s to import)."""
    for path, input_format, *_ in tasks:
        try:
            if format_of(path, input_format) in ("vtk", "vtp", "vtu"):
                return True
        except NfdError:
            continue
    return False


def _run_tasks(tasks: list[tuple], jobs: int, lock_fd):
    """Yield ``(task_number, result)`` as tasks finish; in-process when jobs == 1."""
    if jobs <= 1 or len(tasks) <= 1:
        for i, t in enumerate(tasks):
            yield i, _compute_file(*t)
        return
    import multiprocessing  # build-only imports: kept out of query start-up
    from concurrent.futures import ProcessPoolExecutor, as_completed

    if "fork" in multiprocessing.get_all_start_methods() and threading.active_count() == 1:
        ctx, fd = multiprocessing.get_context("fork"), lock_fd      # fast, and safe without threads
        if _needs_pyvista(tasks):           # imported once here rather than once per worker
            try:
                import pyvista  # noqa: F401
            except Exception:
                pass
    else:                                   # forking a multi-threaded process can deadlock
        method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
        ctx, fd = multiprocessing.get_context(method), None
        if method == "forkserver":
            ctx.set_forkserver_preload(["nfdmatch.index"] + (["pyvista"] if _needs_pyvista(tasks) else []))
    executor = ProcessPoolExecutor(max_workers=min(jobs, len(tasks)), mp_context=ctx,
                                   initializer=_worker_init, initargs=(fd,))
    try:
        futures = {executor.submit(_compute_file, *t): i for i, t in enumerate(tasks)}
        for fut in as_completed(futures):
            i = futures[fut]
            try:
                result = fut.result()
            except Exception as exc:   # the worker process died (BrokenProcessPool), pickling, ...
                path = tasks[i][0]
                result = {"path": path, "size": 0, "mtime_ns": 0, "sha256": "", "status": "failed",
                          "error": f"{path}: the worker reading it failed: {type(exc).__name__}: {exc}"}
            yield i, result
    finally:
        executor.shutdown(wait=True, cancel_futures=True)


# --------------------------------------------------------------------------- writing

class _CurveWriter:
    """Appends rows to resizable /curves datasets with few large writes.

    The datasets are created at the first write, chunked by ``min(CHUNK_ROWS, rows of that
    write)`` rows, so that a small index is not padded to whole large chunks."""

    def __init__(self, h5, K: int):
        self.group = h5.create_group("curves")
        self.K = K
        self.ds = None
        self.pending: list[dict] = []
        self.pending_rows = 0
        self.rows = 0

    def _create(self, first_rows: int) -> None:
        chunk = max(1, min(CHUNK_ROWS, first_rows))
        self.ds = {}
        for name, (dtype, tail) in _curve_layout(self.K).items():
            self.ds[name] = self.group.create_dataset(name, shape=(0,) + tail, maxshape=(None,) + tail,
                                                      chunks=(chunk,) + tail, dtype=dtype)

    def append(self, piece: dict) -> None:
        n = len(piece["file"])
        if n == 0:
            return
        self.pending.append(piece)
        self.pending_rows += n
        if self.pending_rows >= _WRITE_ROWS:
            self.flush()

    def flush(self) -> None:
        if self.ds is None:
            self._create(self.pending_rows)
        if not self.pending:
            return
        n = self.pending_rows
        for name, ds in self.ds.items():
            parts = [p[name] for p in self.pending]
            data = parts[0] if len(parts) == 1 else np.concatenate(parts)
            ds.resize(self.rows + n, axis=0)
            ds[self.rows:self.rows + n] = data
        self.rows += n
        self.pending, self.pending_rows = [], 0


def _write_files_table(h5, records: list[FileRecord]) -> None:
    g = h5.create_group("files")
    F = len(records)
    g.create_dataset("path", data=np.array([r.path for r in records], dtype=object), dtype=_STR, shape=(F,))
    g.create_dataset("size", data=np.array([r.size for r in records], dtype=np.int64), shape=(F,))
    g.create_dataset("mtime_ns", data=np.array([r.mtime_ns for r in records], dtype=np.int64), shape=(F,))
    g.create_dataset("sha256", data=np.array([r.sha256.encode("ascii") for r in records], dtype=_SHA),
                     shape=(F,), dtype=_SHA)
    g.create_dataset("status", data=np.array([0 if r.status == "ok" else 1 for r in records], dtype=np.uint8),
                     shape=(F,))
    g.create_dataset("error", data=np.array([r.error for r in records], dtype=object), dtype=_STR, shape=(F,))
    g.create_dataset("curve_start", data=np.array([r.curve_start for r in records], dtype=np.int64), shape=(F,))
    g.create_dataset("curve_count", data=np.array([r.curve_count for r in records], dtype=np.int64), shape=(F,))


def _fsync_path(path: str, directory: bool = False) -> None:
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _temp_pattern(index_path: str):
    name = os.path.basename(index_path)
    return re.compile(rf"^\.{re.escape(name)}\.tmp-\d+-[0-9a-f]+\.h5$")


def _remove_stale_temps(index_path: str) -> list[str]:
    """Temporary files of builds into this index that were killed (call with the lock held)."""
    folder = os.path.dirname(index_path) or "."
    pattern = _temp_pattern(index_path)
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        if pattern.match(name):
            try:
                os.unlink(os.path.join(folder, name))
                removed.append(os.path.join(folder, name))
            except OSError:
                pass
    return removed


# --------------------------------------------------------------------------- building

@dataclass
class BuildReport:
    """What :func:`build_index` did (or, for a dry run, would do).

    ``added, updated, removed, unchanged, failed`` count FILES; ``curves`` is the number of
    rows in the index after the build (dry run: in the existing index); ``failures`` lists
    ``(path, message)`` of every failed file (new failures and files that stay failed);
    ``changes`` lists ``(action, path)`` for every file, in path order, with action one of
    ``added, updated, removed, unchanged, failed``; ``notices`` are messages for the user;
    ``written`` is True when a new index file was moved into place (False for a dry run and
    for a build that found nothing to change).
    """

    added: int = 0
    updated: int = 0
    removed: int = 0
    unchanged: int = 0
    failed: int = 0
    curves: int = 0
    seconds: float = 0.0
    failures: list = field(default_factory=list)
    changes: list = field(default_factory=list)
    notices: list = field(default_factory=list)
    written: bool = False
    dry_run: bool = False


def _load_old(index_path: str, rebuild: bool, notices: list):
    """The existing index (an :class:`Index`), or None when there is none or it may be replaced."""
    try:
        h5, meta, files = _open_checked(index_path)
    except ReadError:
        if not os.path.lexists(index_path):
            return None
        raise
    except _Problem as exc:
        if exc.kind == "empty":
            notices.append(f"replacing the empty file at {index_path}")
            return None
        if exc.kind in ("foreign", "not_hdf5"):
            raise IndexFormatError(f"{exc.message}; refusing to overwrite it: move it away or choose "
                                   f"another --index", path=index_path) from None
        if rebuild:
            notices.append(f"replacing {index_path}: {exc.message}")
            return None
        raise IndexFormatError(f"{exc.message}; move it away or pass --rebuild to replace it",
                               path=index_path) from None
    return Index(index_path, h5, meta, files)


def build_index(sources, index_path=None, *, samples=None, harmonics=None, scale=None, glob=None,
                input_format=None, rebuild=False, dry_run=False, jobs=None, wait=0.0,
                progress=None) -> BuildReport:
    """Build or update the index of every curve under ``sources``.

    Parameters
    ----------
    sources : path or list of paths: files (taken whatever their extension) or folders
        (recursive; known extensions; hidden files and folders skipped).
    index_path : the index file (None: :func:`default_index_path`). Its folder must exist.
    samples, harmonics, scale : descriptor parameters; None keeps the existing index's value
        (defaults 128, 16, "rms" for a new index). An explicit value that differs from the
        index's recomputes every curve (with a notice).
    glob : fnmatch pattern on file names found in folders.
    input_format : force this reader for every file (not recorded in the index).
    rebuild : recompute every file, even unchanged ones.
    dry_run : only plan: stat, hash files whose mtime changed, report; write nothing.
    jobs : worker processes (None: ``os.cpu_count()``; 1: in this process).
    wait : seconds to wait for another build's lock (0: fail at once).
    progress : optional ``progress(done_files, total_files)``, called with (0, total) first and
        then as files finish; total counts the files that must be read or hashed (unchanged
        files are not counted).

    Returns
    -------
    :class:`BuildReport`.

    Raises
    ------
    ReadError : a source that does not exist; the index path is a directory.
    InputError : no curve files under the sources and no existing index.
    ParameterError : invalid parameters or jobs.
    IndexLockedError : another build holds the lock (after ``wait`` seconds).
    IndexFormatError : the existing file is not a readable index (see docs/index-format.md for
        which files ``rebuild`` may replace; an HDF5 file of another kind never is).
    WriteError : the index cannot be written (missing folder, no permission, disk full).
    """
    t0 = time.perf_counter()
    index_path = default_index_path() if index_path is None else str(os.fspath(index_path))
    if isinstance(sources, (str, bytes, os.PathLike)):
        sources = [sources]
    sources = [str(os.fspath(s)) for s in sources]
    if jobs is None:
        jobs = os.cpu_count() or 1
    if isinstance(jobs, bool) or not isinstance(jobs, (int, np.integer)) or jobs < 1:
        raise ParameterError(f"jobs must be an integer >= 1, got {jobs!r}")
    if input_format is not None:
        format_of("x", input_format)              # an unknown format name fails before any work
    for name, value in (("samples", samples), ("harmonics", harmonics)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))):
            raise ParameterError(f"{name} must be an integer, got {value!r}")
    if os.path.isdir(index_path):
        raise ReadError("is a directory, not an index file", path=index_path)
    folder = os.path.dirname(index_path) or "."
    if not os.path.isdir(folder):
        raise WriteError(f"cannot write the index: no folder {folder}", path=index_path)

    found = sorted({os.path.normpath(p) for p in find_curve_files(sources, glob=glob)})
    report = BuildReport(dry_run=bool(dry_run))
    lock = None if dry_run else _Lock(index_path, wait)
    old = None
    try:
        old = _load_old(index_path, rebuild, report.notices)
        if not found and old is None:
            raise InputError(f"no curve files found under {', '.join(sources) or '(no sources)'}")

        # parameters
        given = {"samples": samples, "harmonics": harmonics, "scale": scale}
        defaults = {"samples": DEFAULT_SAMPLES, "harmonics": DEFAULT_HARMONICS, "scale": DEFAULT_SCALE}
        params = {}
        changed = []
        for name in given:
            previous = getattr(old, name) if old is not None else None
            params[name] = given[name] if given[name] is not None else (
                previous if previous is not None else defaults[name])
            if old is not None and given[name] is not None and given[name] != previous:
                changed.append(f"{name} {previous} -> {given[name]}")
        params["samples"], params["harmonics"] = int(params["samples"]), int(params["harmonics"])
        validate_parameters(params["samples"], params["harmonics"], params["scale"])
        if changed:
            report.notices.append(f"parameters changed ({', '.join(changed)}): recomputing all curves")
        recompute_all = bool(rebuild) or bool(changed) or old is None
        if not found and old is not None:
            report.notices.append(f"no curve files found under {', '.join(sources)}: "
                                  f"every file is removed from the index")

        # the plan
        old_rows = {}
        old_files = [] if old is None else old.files()
        for i, r in enumerate(old_files):
            old_rows[r.path] = (i, r)
        found_set = set(found)
        items = []          # (path, kind, old record or None, task number or None)
        tasks = []
        for path in found:
            entry = old_rows.get(path)
            r = entry[1] if entry else None
            try:
                st = os.stat(path)
                size, mtime = int(st.st_size), int(st.st_mtime_ns)
            except OSError:
                size = mtime = None
            if r is None or recompute_all or size is None:
                kind, old_sha = "compute", None
            elif size == r.size and mtime == r.mtime_ns:
                kind, old_sha = ("reuse" if r.status == "ok" else "keepfailed"), None
            elif size == r.size and r.sha256:
                kind, old_sha = "check", r.sha256
            else:
                kind, old_sha = "compute", None
            task = None
            if kind in ("compute", "check"):
                task = len(tasks)
                tasks.append((path, input_format, params["samples"], params["harmonics"], params["scale"], old_sha))
            items.append((path, kind, r, task))
        removed = [r.path for r in old_files if r.path not in found_set]

        if dry_run:
            _dry_run_report(report, items, removed, old, progress)
            report.seconds = time.perf_counter() - t0
            return report

        stale = _remove_stale_temps(index_path)
        if stale:
            report.notices.append(f"removed {len(stale)} temporary file(s) left by an interrupted build: "
                                  f"{', '.join(stale)}")
        needs_write = old is None or recompute_all or bool(tasks) or bool(removed)
        if not needs_write:
            if progress is not None:
                progress(0, 0)
            for path, kind, r, _ in items:
                if kind == "reuse":
                    report.unchanged += 1
                    report.changes.append(("unchanged", path))
                else:
                    report.failed += 1
                    report.changes.append(("failed", path))
                    report.failures.append((path, r.error))
            report.curves = old.n_curves
            report.seconds = time.perf_counter() - t0
            return report

        _write(report, index_path, items, tasks, removed, old, params, jobs, lock, progress)
    finally:
        if old is not None:
            old.close()
        if lock is not None:
            lock.release()
    report.seconds = time.perf_counter() - t0
    return report


def _dry_run_report(report: BuildReport, items, removed, old, progress) -> None:
    total = len([it for it in items if it[1] in ("check", "compute")])
    done = 0
    if progress is not None:
        progress(0, total)
    actions = {}
    for path, kind, r, _ in items:
        if kind == "reuse":
            actions[path] = "unchanged"
        elif kind == "keepfailed":
            actions[path] = "failed"
            report.failures.append((path, r.error))
        elif kind == "compute":
            actions[path] = "added" if r is None else "updated"
            done += 1
        else:
            try:
                same = _sha256(path) == r.sha256
            except OSError:
                same = False
            if same and r.status == "ok":
                actions[path] = "unchanged"
            elif same:
                actions[path] = "failed"
                report.failures.append((path, r.error))
            else:
                actions[path] = "updated"
            done += 1
        if progress is not None and kind in ("check", "compute"):
            progress(done, total)
    for path in removed:
        actions[path] = "removed"
    for path in sorted(actions):
        action = actions[path]
        report.changes.append((action, path))
        setattr(report, action, getattr(report, action) + 1)
    report.curves = 0 if old is None else old.n_curves


def _write(report: BuildReport, index_path: str, items, tasks, removed, old, params, jobs, lock, progress):
    folder = os.path.dirname(index_path) or "."
    name = os.path.basename(index_path)
    import secrets

    tmp = os.path.join(folder, f".{name}.tmp-{os.getpid()}-{secrets.token_hex(4)}.h5")
    K = params["harmonics"]
    results: dict[int, dict] = {}
    total = len(tasks)
    if progress is not None:
        progress(0, total)
    stream = _run_tasks(tasks, jobs, None if lock is None else lock.fd)
    done = 0

    def result_of(task: int) -> dict:
        nonlocal done
        while task not in results:
            i, res = next(stream)
            results[i] = res
            done += 1
            if progress is not None:
                progress(done, total)
        return results.pop(task)

    records: list[FileRecord] = []
    actions: dict[str, str] = {p: "removed" for p in removed}
    now = _utcnow()
    try:
        try:
            h5 = h5py.File(tmp, "w", locking=False)
        except Exception as exc:
            raise WriteError(f"cannot write the index: {_short(exc)}", path=index_path) from None
        try:
            attrs = h5.attrs
            attrs["format"] = INDEX_FORMAT
            attrs["format_version"] = np.int64(FORMAT_VERSION)
            attrs["nfdmatch_version"] = __version__
            attrs["samples"] = np.int64(params["samples"])
            attrs["harmonics"] = np.int64(params["harmonics"])
            attrs["scale"] = params["scale"]
            attrs["created"] = (old.created if old is not None and old.created else now)
            attrs["updated"] = now
            writer = _CurveWriter(h5, K)
            run = _CopyRun(old, writer)
            for path, kind, r, task in items:
                file_row = len(records)
                start = writer.rows + writer.pending_rows + run.rows
                if kind == "reuse":
                    run.add(r.curve_start, r.curve_count, file_row)
                    records.append(FileRecord(path, r.size, r.mtime_ns, r.sha256, "ok", "", start, r.curve_count))
                    actions[path] = "unchanged"
                    continue
                if kind == "keepfailed":
                    records.append(FileRecord(path, r.size, r.mtime_ns, r.sha256, "failed", r.error, start, 0))
                    actions[path] = "failed"
                    report.failures.append((path, r.error))
                    continue
                res = result_of(task)
                if res["status"] == "same":            # mtime changed, contents did not
                    if r.status == "ok":
                        run.add(r.curve_start, r.curve_count, file_row)
                        records.append(FileRecord(path, res["size"], res["mtime_ns"], r.sha256, "ok", "", start,
                                                  r.curve_count))
                        actions[path] = "unchanged"
                    else:
                        records.append(FileRecord(path, res["size"], res["mtime_ns"], r.sha256, "failed", r.error,
                                                  start, 0))
                        actions[path] = "failed"
                        report.failures.append((path, r.error))
                    continue
                run.flush()
                if res["status"] == "ok":
                    n = len(res["ids"])
                    piece = dict(res["arrays"])
                    piece["id"] = np.asarray(res["ids"], dtype=object)
                    piece["file"] = np.full(n, file_row, dtype=np.int32)
                    writer.append(piece)
                    records.append(FileRecord(path, res["size"], res["mtime_ns"], res["sha256"], "ok", "", start, n))
                    actions[path] = "added" if r is None else "updated"
                else:
                    records.append(FileRecord(path, res["size"], res["mtime_ns"], res["sha256"], "failed",
                                              res["error"], start, 0))
                    actions[path] = "failed"
                    report.failures.append((path, res["error"]))
            run.flush()
            writer.flush()
            _write_files_table(h5, records)
            report.curves = writer.rows
        finally:
            stream.close()                          # shuts the worker pool down
            h5.close()
        _fsync_path(tmp)
        os.replace(tmp, index_path)
        _fsync_path(folder, directory=True)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError) and not isinstance(exc, NfdError):
            raise WriteError(f"cannot write the index: {exc.strerror or _short(exc)}", path=index_path) from exc
        raise
    report.written = True
    for path in sorted(actions):
        action = actions[path]
        report.changes.append((action, path))
        setattr(report, action, getattr(report, action) + 1)


class _CopyRun:
    """Rows copied from the old index, merged into contiguous runs (one read per run)."""

    def __init__(self, old, writer: _CurveWriter):
        self.old, self.writer = old, writer
        self.start = self.stop = 0
        self.file_rows: list[int] = []
        self.counts: list[int] = []

    @property
    def rows(self) -> int:
        return self.stop - self.start

    def add(self, start: int, count: int, file_row: int) -> None:
        if count == 0:
            return
        if self.rows and start != self.stop:
            self.flush()
        if not self.rows:
            self.start = self.stop = start
            self.file_rows, self.counts = [], []
        self.stop += count
        self.file_rows.append(file_row)
        self.counts.append(count)
        if self.rows >= _WRITE_ROWS:
            self.flush()

    def flush(self) -> None:
        if not self.rows:
            return
        file_col = np.repeat(np.asarray(self.file_rows, dtype=np.int32), self.counts)
        for a in range(self.start, self.stop, _WRITE_ROWS):
            b = min(self.stop, a + _WRITE_ROWS)
            piece = self.old._raw_rows(a, b)
            piece["file"] = file_col[a - self.start:b - self.start]
            self.writer.append(piece)
        self.start = self.stop = 0
        self.file_rows, self.counts = [], []
