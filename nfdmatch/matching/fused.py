"""The fused distance of the elastic stage: the exact rigid distance, the elastic distance
(:mod:`.elastic`) and the pose-free statistics (:mod:`.statistics`), each mapped to [0, 1]
by a fixed quantile table and summed (docs/elastic.md).

Why quantiles: the three distances have different units and tails; what fuses them well is
each one's rank (rank fusion beat normalised sums on the 3-D development data). A per-query
rank would depend on the answer list; the quantile of a distance among the pairs of a
reference collection is a rank that depends on the pair alone: symmetric, deterministic,
the same for ``query``, ``matrix`` and the graph. The tables are the pooled pairs of the
development collections (Kimia-99, the mesh sections, psb_dev cut loops and
mid-sections; ``benchmarks/bench_3d.py --constants`` recomputes them); a collection's own
quantiles measured no better (docs/elastic.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .common import INVARIANT
from .elastic import elastic_distances
from .kernels import Kernels
from .statistics import curve_statistics, statistics_distance

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

    from . import Match

__all__ = [
    "FusedDistances",
    "fused_rows",
    "fused_distance",
    "fuse",
    "RIGID_QUANTILES",
    "ELASTIC_QUANTILES",
    "STATISTICS_QUANTILES",
    "TERMS",
    "FUSED_VERSION",
    "require_exact",
]

#: the terms summed, in this order
TERMS = ("rigid", "elastic", "statistics")
#: which fused distance this is, stamped on a graph of fused distances (``/graph``
#: attribute ``fused_version``; docs/index-format.md): 1, the elastic term at the rigid
#: optimum's pose (turn 4's second session; a graph without the attribute); 2, at the
#: lesser of both directions' best poses, with the quantile tables below. A graph of
#: another version is rebuilt by ``index build`` and named by ``query --rerank``.
FUSED_VERSION = 2
#: 17 quantiles (0, 1/16, ..., 1) of each term over the pooled development pairs
RIGID_QUANTILES = (
    0.0, 0.0706, 0.1037, 0.1283, 0.1573, 0.1872, 0.2205, 0.2582, 0.2912, 0.3261, 0.3644, 0.4074, 0.4481,
    0.4911, 0.5563, 0.6637, 1.0382,
)  # fmt: skip
ELASTIC_QUANTILES = (
    0.0, 0.9695, 1.4643, 1.8373, 2.0992, 2.3341, 2.5507, 2.7482, 2.9258, 3.1211, 3.3232, 3.5343, 3.7845,
    4.0386, 4.2732, 4.6705, 7.7741,
)  # fmt: skip
STATISTICS_QUANTILES = (
    0.0, 1.7335, 2.4573, 3.0831, 3.6837, 4.2005, 4.7502, 5.2919, 5.8266, 6.3109, 6.8421, 7.3988, 8.0112,
    8.7232, 9.5512, 10.5404, 15.9714,
)  # fmt: skip
_LEVELS = np.linspace(0.0, 1.0, 17)


def require_exact(method: str) -> None:
    """The elastic stage is taken at the exact optimum (its pose and its rigid term): a
    ``ParameterError`` for any other method."""
    from . import EXACT
    from ..errors import ParameterError

    if method != EXACT:
        raise ParameterError(f"the elastic stage is taken at the exact optimum: method must be {EXACT}")


def fuse(rigid: ArrayLike, elastic: ArrayLike, statistics: ArrayLike) -> NDArray[np.float64]:
    """The fused distance of arrays of the three terms (the same shape): in [0, 3], 0 for
    the same curve; each term through its quantile table (linear between the knots, 1
    beyond the last)."""
    total = np.interp(np.asarray(rigid, dtype=np.float64), RIGID_QUANTILES, _LEVELS)
    total = total + np.interp(np.asarray(elastic, dtype=np.float64), ELASTIC_QUANTILES, _LEVELS)
    return total + np.interp(np.asarray(statistics, dtype=np.float64), STATISTICS_QUANTILES, _LEVELS)


@dataclass(frozen=True)
class FusedDistances:
    """A query's terms against M rows, each (M,) float64: ``rigid`` (the exact distance),
    ``elastic``, ``statistics`` and ``fused`` (what the stage ranks by)."""

    rigid: np.ndarray
    elastic: np.ndarray
    statistics: np.ndarray
    fused: np.ndarray


def fused_rows(
    A: np.ndarray,
    B: np.ndarray,
    rigid: dict,
    samples: int,
    *,
    query_statistics: np.ndarray | None = None,
    row_statistics: np.ndarray | None = None,
    direction: str = INVARIANT,
    mirror: bool = False,
    weights: ArrayLike | None = None,
    kernels: Kernels | None = None,
) -> FusedDistances:
    """The fused distances of one query to many rows.

    A : (K, 3) complex, the query's half-band; B : (M, K, 3) complex, the rows'.
    rigid : the exact optimum of each row (``exact_search``'s dict, or any mapping with
        ``distance``, ``shift``, ``reversed``, ``mirrored`` as (M,) arrays): the elastic
        distance is taken at its pose (and the other direction's,
        :func:`~.elastic.elastic_distances`).
    direction, mirror, weights : the exact search's.
    samples : n of the descriptors.
    query_statistics : (LENGTH,) and row_statistics : (M, LENGTH) float, when stored; else
        computed from ``A`` and ``B`` (:func:`~.statistics.curve_statistics`).
    """
    B = np.asarray(B)
    distance = np.asarray(rigid["distance"], dtype=np.float64)
    elastic = elastic_distances(
        A, B, rigid, samples, direction=direction, mirror=mirror, weights=weights, kernels=kernels
    )
    mine = curve_statistics(A) if query_statistics is None else query_statistics
    theirs = curve_statistics(B) if row_statistics is None else row_statistics
    statistics = statistics_distance(mine, theirs) if len(B) else np.zeros(0)
    return FusedDistances(distance, elastic, statistics, fuse(distance, elastic, statistics))


def fused_distance(a: Any, b: Any, **parameters: Any) -> tuple[Match, FusedDistances]:
    """The elastic stage's terms for one pair of curves: ``(match, terms)``, ``match`` the
    exact :class:`~nfdmatch.matching.Match` (:func:`nfdmatch.distance`) and ``terms`` a
    :class:`FusedDistances` of one row (the elastic distance taken at the match's pose).

    a, b : as :func:`nfdmatch.distance`; parameters : its keywords (the method must be exact)."""
    from . import MatchParameters, _as_descriptors, match_descriptors

    p = MatchParameters(**parameters)
    require_exact(p.method)
    da = _as_descriptors(a, **p.descriptor)
    db = _as_descriptors(b, **p.descriptor)
    match = match_descriptors(da, db, **p.matching)
    rigid = {
        "distance": np.array([match.distance]),
        "shift": np.array([match.shift]),
        "reversed": np.array([match.reversed]),
        "mirrored": np.array([match.mirrored]),
    }
    terms = fused_rows(
        da.coefficients, db.coefficients[None], rigid, da.samples, direction=p.direction, mirror=p.mirror,
        weights=p.weights,
    )  # fmt: skip
    return match, terms
