"""nfdmatch: retrieval of closed 3-D curves by normalized Fourier descriptors.

Public API::

    from nfdmatch import read_curves, read_curve, descriptors, distance

Zhang & Fiume, "Shape Matching of 3-D Contours using Normalized Fourier
Descriptors" (SMI 2002), with an exact shift x rotation search.
"""

from ._version import __version__
from .curve import Curve
from .descriptors import Descriptors, descriptors
from .errors import NfdError
from .formats import read_curve, read_curves, write_curves
from .matching import Match, distance, match_descriptors

__all__ = [
    "__version__",
    "Curve",
    "Descriptors",
    "Match",
    "NfdError",
    "descriptors",
    "distance",
    "match_descriptors",
    "read_curve",
    "read_curves",
    "write_curves",
]
