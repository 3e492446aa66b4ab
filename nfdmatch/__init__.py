"""nfdmatch: retrieval of closed 3-D curves by normalized Fourier descriptors.

Public API::

    from nfdmatch import read_curves, read_curve, descriptors, distance
    from nfdmatch import build_index, open_index

    report = build_index(["curves/"], "curves.h5")
    with open_index("curves.h5") as index:
        matches = index.search("query.obj", k=5)   # one list per query curve
        distances, rows = index.search("query.obj", k=5, arrays=True)   # as faiss
        index.ids[rows[0, 0]]

    memory = MemoryIndex(curves)                   # Curves or (n, 3) arrays
    memory.search(queries, k=5, arrays=True)       # the same search
    memory.save("curves.h5")                       # an index file the CLI reads

Zhang & Fiume, "Shape Matching of 3-D Contours using Normalized Fourier
Descriptors" (SMI 2002), with an exact shift x rotation search.

Every name loads its module on first use: ``import nfdmatch`` imports nothing heavy (no
numpy), so that the program's first step (``nfdmatch.cli.start``: its signal handling)
runs before any heavy import.
"""

import sys
import types

__all__ = [
    "__version__",
    "Curve",
    "Descriptors",
    "Match",
    "NfdError",
    "RankedMatch",
    "descriptors",
    "distance",
    "match_descriptors",
    "read_curve",
    "read_curves",
    "write_curves",
    "build_index",
    "open_index",
    "Index",
    "BuildReport",
    "MemoryIndex",
]

#: public names and their modules, each loaded on first use
_LAZY = {
    "__version__": "nfdmatch._version",
    "Curve": "nfdmatch.curve",
    "Descriptors": "nfdmatch.descriptors",
    "descriptors": "nfdmatch.descriptors",
    "NfdError": "nfdmatch.errors",
    "read_curve": "nfdmatch.formats",
    "read_curves": "nfdmatch.formats",
    "write_curves": "nfdmatch.formats",
    "Match": "nfdmatch.matching",
    "distance": "nfdmatch.matching",
    "match_descriptors": "nfdmatch.matching",
    "RankedMatch": "nfdmatch.records",
    "build_index": "nfdmatch.index",
    "BuildReport": "nfdmatch.index",
    "open_index": "nfdmatch.index",
    "Index": "nfdmatch.index",
    "MemoryIndex": "nfdmatch.index.memory",
}


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


class _Package(types.ModuleType):
    """The package: loading submodule ``nfdmatch.descriptors`` binds the package's name
    ``descriptors``; it stays the function of that name (``nfdmatch.descriptors(...)``)."""

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and _LAZY.get(name) == value.__name__:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
