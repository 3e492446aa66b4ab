"""Stages that re-order a search's exact candidates, behind one interface.

A stage takes each query's exact candidates (the rows the one search engine found, with
their rigid optimum) and returns them re-ordered, with its own columns filled in. A search
asks the engine for :meth:`Stage.candidates` rows, hands them to :meth:`Stage.reorder`, and
keeps the first ``top``: :func:`~nfdmatch.search.index_search.search_index` does this for
every stage, so a new stage is a class here and its name in the CLI, never a second
search. The stage of this module: :class:`ElasticStage` (``--elastic``; docs/elastic.md).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any, Optional, Protocol

import numpy as np

from ..defaults import DEFAULT_ELASTIC_DEPTH
from ..errors import ParameterError
from ..records import RankedMatch
from .engine import TIE

if TYPE_CHECKING:
    from ..matching.fused import FusedDistances
    from .engine import BestRows

__all__ = [
    "Stage",
    "ElasticStage",
    "ELASTIC_COLUMNS",
    "fused_terms",
    "statistics_of_queries",
    "fused_candidates",
    "fused_threads",
    "rank_by_fused",
    "rigid_of",
]

#: each query's exact candidates, ranked, as a stage receives them
Candidates = Sequence[Sequence[RankedMatch]]
#: each query's answer, as a stage gives it back
Answers = list[list[RankedMatch]]
#: the exact search's ``direction``, ``mirror`` and ``weights`` (None: invariant, no mirror, uniform)
Matching = Optional[Mapping[str, Any]]

#: the columns the elastic stage adds after ``distance``
ELASTIC_COLUMNS = ("elastic", "fused")


class Stage(Protocol):
    """What a re-ordering stage provides."""

    #: the stage's name (its CLI flag without dashes)
    name: str
    #: the columns it fills in, after ``distance``
    columns: tuple[str, ...]

    def candidates(self, top: int | None) -> int | None:
        """How many exact nearest rows a query needs for an answer of ``top`` rows."""
        ...

    def reorder(self, index: Any, qcoef: np.ndarray, results: Candidates, *, matching: Matching = None) -> Answers:
        """Each query's candidates (``results[i]``, query i's descriptors ``qcoef[i]``: (Q, K,
        3) complex128), re-ordered and re-ranked, the stage's columns filled in; ``matching``:
        the exact search's ``direction``, ``mirror`` and ``weights``."""
        ...


@dataclass(frozen=True)
class ElasticStage:
    """The exact top ``depth`` of a query ordered by the fused distance (rigid, elastic and
    pose-free statistics: :mod:`nfdmatch.matching.fused`); ties by exact distance, then id.

    depth : the exact candidates re-ordered (``--elastic-depth``): an integer, at least 1
        (anything else is a :class:`~nfdmatch.errors.ParameterError`)."""

    depth: int = DEFAULT_ELASTIC_DEPTH
    name: str = "elastic"
    columns: tuple[str, ...] = ELASTIC_COLUMNS

    def __post_init__(self):
        depth = self.depth
        if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < 1:
            raise ParameterError(f"the elastic depth must be an integer of at least 1, got {depth!r}")

    def candidates(self, top: int | None) -> int | None:
        return None if top is None else max(int(top), int(self.depth))

    def reorder(self, index: Any, qcoef: np.ndarray, results: Candidates, *, matching: Matching = None) -> Answers:
        rigid = [
            {
                "distance": np.array([m.distance for m in matches], dtype=np.float64),
                "shift": np.array([m.shift for m in matches], dtype=np.float64),
                "reversed": np.array([m.reversed for m in matches], dtype=bool),
                "mirrored": np.array([m.mirrored for m in matches], dtype=bool),
            }
            for matches in results
        ]
        rows = [np.array([m.row for m in matches], dtype=np.int64) for matches in results]
        out = []
        for matches, terms in zip(results, fused_candidates(index, qcoef, rows, rigid, matching=matching)):
            if terms is None:
                out.append([])
                continue
            key = np.round(terms.fused / TIE)
            ranked = sorted(range(len(matches)), key=lambda i: (key[i], matches[i].distance, matches[i].id))
            out.append(
                [
                    matches[i].replace(rank=rank, elastic=float(terms.elastic[i]), fused=float(terms.fused[i]))
                    for rank, i in enumerate(ranked, start=1)
                ]
            )
        return out


def fused_terms(
    index: Any,
    qcoef: np.ndarray,
    rows: Sequence[np.ndarray],
    *,
    matching: Matching = None,
    query_statistics: np.ndarray | None = None,
) -> Callable[[int, np.ndarray, Mapping[str, np.ndarray]], FusedDistances]:
    """``terms(query, its_rows, rigid)``: the fused distances
    (:class:`~nfdmatch.matching.fused.FusedDistances`) of query ``query`` (descriptors
    ``qcoef[query]``: (Q, K, 3) complex128) to ``its_rows`` (int64, among ``rows[query]``, any
    order) at their exact optimum ``rigid`` (``distance``, ``shift``, ``reversed``,
    ``mirrored`` arrays in the order of ``its_rows``). Every row of ``rows`` is read now, once
    for the batch (a scattered read costs about as much for one row as for many), with its
    statistics as the index stores them (``statistics_at``) or computed; ``matching``: the
    exact search's ``direction``, ``mirror`` and ``weights`` (default: invariant, no mirror,
    uniform); ``query_statistics``: (Q, LENGTH) the queries' statistics when a caller has them
    (:func:`statistics_of_queries`), else computed here. The function may be called from any
    thread (a row's distances are computed alone: the same digits on any thread, in any
    batch)."""
    from ..matching.fused import fused_rows
    from ..matching.statistics import curve_statistics

    every = np.unique(np.concatenate(rows)) if len(rows) else np.zeros(0, np.int64)
    coefficients = index.coefficients_at(every) if len(every) else None
    stored = getattr(index, "statistics_at", None)
    if coefficients is None:
        statistics = None
    else:
        statistics = stored(every) if stored is not None else curve_statistics(coefficients)
    mine = query_statistics if query_statistics is not None else statistics_of_queries(qcoef)

    def terms(query: int, its_rows: np.ndarray, rigid: Mapping[str, np.ndarray]) -> FusedDistances:
        at = np.searchsorted(every, its_rows)
        return fused_rows(
            qcoef[query], coefficients[at], dict(rigid), index.samples, query_statistics=mine[query],  # type: ignore[index]
            row_statistics=statistics[at], **(matching or {}),  # type: ignore[index]
        )  # fmt: skip

    return terms


def statistics_of_queries(qcoef: np.ndarray) -> np.ndarray:
    """(Q, LENGTH) float: the pose-free statistics of each query (descriptors ``qcoef``: (Q,
    K, 3) complex128), the fused distance's third term
    (:func:`~nfdmatch.matching.statistics.curve_statistics`)."""
    from ..matching.statistics import curve_statistics

    return curve_statistics(qcoef).reshape(len(qcoef), -1)


def fused_candidates(
    index: Any,
    qcoef: np.ndarray,
    rows: Sequence[np.ndarray],
    rigid: Sequence[Mapping[str, np.ndarray]],
    *,
    matching: Matching = None,
) -> list[FusedDistances | None]:
    """The fused distances (:class:`~nfdmatch.matching.fused.FusedDistances`, None for a query
    without candidates) of each query to its candidate ``rows[i]`` (int64), at their exact
    optimum ``rigid[i]`` (:func:`fused_terms`, the batch's rows read once; ``matching`` as
    there). The queries are spread over the kernels' threads, each query's rows on one thread
    (:func:`~nfdmatch.matching._threads.run_spread`; a row's distance is computed alone, so
    the digits do not depend on the threads)."""
    from ..matching._threads import run_spread

    total = sum(len(r) for r in rows)
    terms = fused_terms(index, qcoef, rows, matching=matching) if total else None

    def one(qi: int) -> FusedDistances | None:
        return terms(qi, rows[qi], rigid[qi]) if terms is not None and len(rows[qi]) else None

    return run_spread([partial(one, qi) for qi in range(len(rows))], fused_threads(total))


def fused_threads(rows: int) -> int:
    """The threads the fused distances of ``rows`` rows in all are spread over (the process's
    kernels': :meth:`~nfdmatch.matching.kernels.Kernels.workers`)."""
    from ..matching.elastic import ELASTIC_THREAD_ROWS
    from ..matching.kernels import current

    return current().workers(rows, ELASTIC_THREAD_ROWS)


def rigid_of(found: BestRows) -> dict[str, np.ndarray]:
    """The exact optimum of a query's candidates (a :class:`~nfdmatch.search.engine.BestRows`
    with exact distances), as :func:`fused_terms` takes it."""
    keys = ("shift", "reversed", "mirrored")
    return {"distance": found.dist, **{key: found.extra[key] for key in keys}}


def rank_by_fused(found: BestRows, terms: FusedDistances) -> None:
    """A query's candidates (a :class:`~nfdmatch.search.engine.BestRows` ranked by exact
    distance, then id) given their fused distances ``terms`` instead (the exact ones kept in
    ``extra["exact"]``, the elastic ones in ``extra["elastic"]``) and ranked by them: by
    fused distance (within TIE), then exact distance, then as they came (the sort is
    stable)."""
    order = np.lexsort((found.dist, np.round(terms.fused / TIE)))
    extra = {**found.extra, "exact": found.dist, "elastic": terms.elastic}
    found.rows, found.dist = found.rows[order], terms.fused[order]
    found.extra = {key: v[order] for key, v in extra.items()}
