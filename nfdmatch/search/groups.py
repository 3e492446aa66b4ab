"""Pairs and groups of an index: every pair of curves within a distance (:func:`index_pairs`)
and the groups they chain into (:func:`index_groups`, single linkage), from the self-join
(:mod:`.join`) of the index as a whole; the library behind ``nfdmatch pairs`` and
``nfdmatch groups`` (docs/selfjoin.md).

Test hook: ``tests/test_join.py`` compares :func:`_components` (the connected components
of the pairs, in whole-array steps) with a plain union-find on random graphs."""

from __future__ import annotations

from typing import Any

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from .engine import TIE, Cascade
from .join import JoinStats, pairs_within
from .limits import check_limits

__all__ = ["Pair", "GroupMember", "index_pairs", "index_groups"]


@dataclass(frozen=True)
class Pair:
    """Two curves at most the asked distance apart: ids ``a < b``, their exact distance."""

    a: str
    b: str
    distance: float


@dataclass(frozen=True)
class GroupMember:
    """One curve of a near-duplicate group: its ``id``, the ``group`` number (1, 2, ... in
    the order of the groups' smallest ids), the group's ``size`` and ``representative``
    (the member with the smallest total distance to the others, ties by id)."""

    id: str
    group: int
    size: int
    representative: str


def _cascade(index, options: dict) -> Cascade:
    from ..matching import DEFAULT_DIRECTION, DEFAULT_METHOD, METHODS

    method = options.get("method", DEFAULT_METHOD)
    if method not in METHODS:
        raise ParameterError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    return Cascade(
        index.samples, method, options.get("direction", DEFAULT_DIRECTION), bool(options.get("mirror", False))
    )


def _new_rows(index) -> np.ndarray:
    rows = index.new_rows() if hasattr(index, "new_rows") else None
    if rows is None:
        raise ParameterError(
            f"{getattr(index, 'path', 'the index')} does not record which curves its last build added: "
            f"any build that writes it records them (`nfdmatch index build --rebuild` marks every curve as new)"
        )
    return rows


def index_pairs(
    index: Any,
    max_distance: float,
    *,
    new: bool = False,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
    cluster: Any = None,
    **options: Any,
) -> tuple[list[Pair], JoinStats]:
    """Every pair of curves of an open :class:`~nfdmatch.index.Index` (or a
    :class:`~nfdmatch.search.MemoryIndex`) at most ``max_distance`` apart, each once.

    new : only pairs with at least one curve that the index's last build added or
        recomputed (``/changes``; ParameterError for an index that does not record them).
    options : ``method``, ``direction``, ``mirror`` as :func:`nfdmatch.distance`.
    cluster : a :class:`nfdmatch.distributed.Cluster`: the join split by ranges of cells
        over its workers (the same pairs; an index file every worker sees).

    Returns ``(pairs, stats)``: :class:`Pair` sorted by (a, b), ids a < b.
    """
    cascade = _cascade(index, options)
    rows = _new_rows(index) if new else None
    a, b, d, stats = _pairs(index, max_distance, cascade, rows, progress, threads, cluster)
    ids = index.ids_at(np.concatenate([a, b])) if len(a) else []
    ia, ib = ids[: len(a)], ids[len(a) :]
    pairs = [Pair(x, y, float(t)) if x < y else Pair(y, x, float(t)) for x, y, t in zip(ia, ib, d)]
    pairs.sort(key=lambda p: (p.a, p.b))
    return pairs, stats


def index_groups(
    index: Any,
    max_distance: float,
    *,
    min_size: int = 1,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
    cluster: Any = None,
    **options: Any,
) -> tuple[list[GroupMember], JoinStats]:
    """The near-duplicate groups of an index: the connected components of the pairs within
    ``max_distance`` (single linkage: a chain of near-duplicates is one group, however far
    apart its ends), one :class:`GroupMember` per curve, groups of at least ``min_size``.

    A group's representative is its member with the smallest sum of exact distances to the
    other members (every pair of the group: those not within ``max_distance`` are computed
    here, ~size^2 / 2 distances for a loose group), ties by id.

    progress, threads, cluster, options : as :func:`index_pairs`.

    Returns ``(members, stats)`` sorted by group, then id; groups numbered 1, 2, ... in the
    order of their smallest ids (among the groups listed).
    """
    if min_size < 1:
        raise ParameterError(f"min_size must be at least 1, got {min_size}")
    cascade = _cascade(index, options)
    a, b, d, stats = _pairs(index, max_distance, cascade, None, progress, threads, cluster)
    N = index.n_curves
    label = _components(N, a, b)
    ids = index.ids_at(np.arange(N)) if N else []
    members: dict[int, list[int]] = {}
    for r in np.argsort(label, kind="stable"):
        members.setdefault(int(label[r]), []).append(int(r))
    known = {}
    for x, y, t in zip(a.tolist(), b.tolist(), d.tolist()):
        known[(x, y)] = t
    groups = []
    for rows in members.values():
        if len(rows) < min_size:
            continue
        rows.sort(key=lambda r: ids[r])
        groups.append((ids[rows[0]], rows))
    groups.sort()
    out = []
    for number, (_, rows) in enumerate(groups, start=1):
        rep = rows[0] if len(rows) == 1 else _representative(index, cascade, rows, known, ids)
        out.extend(GroupMember(ids[r], number, len(rows), ids[rep]) for r in rows)
    return out, stats


def _pairs(index, max_distance, cascade, rows, progress, threads, cluster):
    check_limits(max_distance=max_distance)
    if cluster is not None:
        return cluster.pairs_within(index, max_distance, cascade, rows=rows, progress=progress)
    return pairs_within(
        index.search_table(),
        index.coefficients_at,
        max_distance,
        cascade,
        rows=rows,
        progress=progress,
        threads=threads,
    )


def _components(N: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) int64 the smallest row of each row's connected component.

    In whole-array steps (a Python loop over the pairs took 1.6 s at a million rows): each
    round hooks every label to the smallest label across its pairs, then follows labels to
    their fixed point (pointer jumping). A label is always a row of the same component and
    never above its row, so at the fixed point the smallest row of a component labels it."""
    label = np.arange(N, dtype=np.int64)
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    if len(a) == 0:
        return label
    while True:
        la, lb = label[a], label[b]
        low = np.minimum(la, lb)
        hooked = label.copy()
        np.minimum.at(hooked, la, low)
        np.minimum.at(hooked, lb, low)
        while True:
            jumped = hooked[hooked]
            if np.array_equal(jumped, hooked):
                break
            hooked = jumped
        if np.array_equal(hooked, label):
            return label
        label = hooked


def _representative(index, cascade: Cascade, rows: list[int], known: dict, ids) -> int:
    """The row of ``rows`` with the smallest total exact distance to the others (ties by
    id): the distances ``known`` (row pair -> distance) reused, the rest computed."""
    coef = np.asarray(index.coefficients_at(np.asarray(rows, dtype=np.int64)))
    m = len(rows)
    D = np.zeros((m, m))
    for i in range(m):
        todo = []
        for j in range(i + 1, m):
            key = (min(rows[i], rows[j]), max(rows[i], rows[j]))
            if key in known:
                D[i, j] = D[j, i] = known[key]
            else:
                todo.append(j)
        if todo:
            r = cascade.distance(
                np.asarray(coef[i], dtype=np.complex128),
                coef[todo],
                cascade.samples,
                direction=cascade.direction,
                mirror=cascade.mirror,
            )
            D[i, todo] = D[todo, i] = r["distance"]
    total = D.sum(axis=1)
    best = min(range(m), key=lambda i: (round(float(total[i]) / TIE), ids[rows[i]]))
    return rows[best]
