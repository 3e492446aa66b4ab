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

The index side (h5py) loads on first use of its names: ``import nfdmatch`` does not import it.
"""

from ._version import __version__
from .curve import Curve
from .descriptors import Descriptors, descriptors
from .errors import NfdError
from .formats import read_curve, read_curves, write_curves
from .matching import Match, distance, match_descriptors
from .records import RankedMatch

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

#: names loaded on first use, and their modules
_LAZY = {
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
