"""Ranking curves by similarity to a query: in memory now, over an index later."""

from __future__ import annotations

import numpy as np

from .descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, descriptors
from .errors import ParameterError
from .matching import exact_search, paper_search

__all__ = ["rank_curves", "BATCH_ROWS"]

#: rows matched per vectorized batch: bounds the (rows x shifts x 9) working set
BATCH_ROWS = 2048


def rank_curves(query, curves, *, top: int | None = None, max_distance: float | None = None,
                samples: int = DEFAULT_SAMPLES, harmonics: int = DEFAULT_HARMONICS,
                scale: str = DEFAULT_SCALE, method: str = "exact", direction: str = "invariant",
                mirror: bool = False, weights=None) -> list[dict]:
    """Rank ``curves`` by distance to ``query``.

    Parameters
    ----------
    query : :class:`~nfdmatch.curve.Curve` (or (n, 3) array).
    curves : sequence of :class:`~nfdmatch.curve.Curve`.
    top : keep the best ``top`` (all when None).
    max_distance : drop matches farther than this.
    Other parameters as in :func:`nfdmatch.distance`.

    Returns
    -------
    list of dicts ``{rank, match, distance, shift, reversed, mirrored}`` sorted by
    distance, ties broken by id so the order is deterministic; ``rank`` is 1-based.
    """
    if top is not None and top < 1:
        raise ParameterError(f"top must be at least 1, got {top}")
    if method not in ("exact", "paper"):
        raise ParameterError(f"method must be exact or paper, got {method!r}")
    dq = descriptors(query, samples=samples, harmonics=harmonics, scale=scale)
    if not curves:
        return []
    rows = np.stack([descriptors(c, samples=samples, harmonics=harmonics, scale=scale).coefficients
                     for c in curves])
    search = exact_search if method == "exact" else paper_search
    parts = [search(dq.coefficients, rows[i:i + BATCH_ROWS], samples, weights=weights,
                    direction=direction, mirror=mirror) for i in range(0, len(rows), BATCH_ROWS)]
    result = {key: np.concatenate([p[key] for p in parts]) for key in ("distance", "shift", "reversed", "mirrored")}
    ids = [c.id for c in curves]
    order = sorted(range(len(curves)), key=lambda i: (result["distance"][i], ids[i]))
    out = []
    for i in order:
        d = float(result["distance"][i])
        if max_distance is not None and d > max_distance:
            break
        out.append({"rank": len(out) + 1, "match": ids[i], "distance": d,
                    "shift": float(result["shift"][i]), "reversed": bool(result["reversed"][i]),
                    "mirrored": bool(result["mirrored"][i])})
        if top is not None and len(out) >= top:
            break
    return out
