"""The index file format: names, dataset layout and dtypes, and opening with validation."""

from __future__ import annotations

import os
import stat as _stat
from dataclasses import dataclass

import h5py
import numpy as np

from ..descriptors import validate_parameters
from ..errors import ParameterError, ReadError

INDEX_FORMAT = "nfdmatch-index"
FORMAT_VERSION = 2
#: format versions this code reads (format 1: no /search group; queries scan every row)
READABLE_VERSIONS = (1, 2)

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
    ``empty``, ``not_hdf5``, ``foreign``, ``unopenable`` (HDF5 that does not open: never
    overwritten), ``corrupt``, ``newer``."""

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
    """Open ``path`` read-only and validate it as a format-1 or format-2 index.

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
        raise _Problem("unopenable", f"truncated or corrupted HDF5 file ({_short(exc)})") from None
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
                                f"this version reads formats {' and '.join(map(str, READABLE_VERSIONS))}")
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
    if version >= 2:
        from .search_group import check_search_group

        problem = check_search_group(h5, int(N), harmonics)
        if problem:
            raise _Problem("corrupt", f"corrupted nfdmatch index: {problem}")
    files = {"datasets": fds, "curve_start": starts, "curve_count": counts}
    meta["datasets"] = cds
    meta["n_curves"], meta["n_files"] = int(N), int(F)
    return meta, files
