"""The HDF5 index of curve descriptors: reading (:func:`open_index`) and building (:func:`build_index`).

The on-disk format is specified in ``docs/index-format.md`` (format 1). This package is the
only code that imports h5py; ``import nfdmatch`` does not import it.

Reading::

    with open_index("curves.h5") as idx:
        for start, rows in idx.iter_chunks():
            rows["coefficients"]            # (m, K, 3) complex128
        idx.ids(0, 10)

Building (incremental, crash-safe, parallel over files)::

    report = build_index(["curves/"], "curves.h5", jobs=2)

The modules: ``schema`` holds the format (names, dataset layout and dtypes, the file record)
and opens a file with validation; ``reader`` is the read side (:class:`Index`,
:func:`open_index`); ``lock`` is the flock that lets one build at a time write an index;
``pool`` does the per-file work of a build (stat, hash, read, describe) in worker
processes; ``writer`` writes the datasets of a new file into a temporary file and syncs it;
``build`` plans what each file needs and runs the build (:func:`build_index`).
"""

from .reader import Index, open_index
from .schema import FORMAT_VERSION, INDEX_FORMAT, FileRecord, default_index_path

__all__ = [
    "INDEX_FORMAT",
    "FORMAT_VERSION",
    "Index",
    "FileRecord",
    "BuildReport",
    "open_index",
    "build_index",
    "default_index_path",
]


#: the submodules, loaded on first use (the build side stays out of a query's start-up)
_SUBMODULES = (
    "build",
    "plan",
    "commit",
    "pool",
    "writer",
    "graph",
    "graph_build",
    "lock",
    "verify",
    "paths",
    "search_group",
    "arrays",
)


def __getattr__(name):
    # the build side (worker pool, writer, graph) loads only when a build asks for it: a
    # query's start-up does not pay for it
    import importlib

    if name in ("build_index", "BuildReport"):
        return getattr(importlib.import_module(f"{__name__}.build"), name)
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")  # submodules, as before the lazy import
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
