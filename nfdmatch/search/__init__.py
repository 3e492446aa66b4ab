"""Exact k nearest curves over an index file or curves held in memory.

The modules, in the order a query passes through them: ``index_search`` answers a batch of
queries (:func:`search_index`, :class:`SearchStats`, the exhaustive reference path);
``engine`` is one query's best-first loop (cells, then rows by invariant bound, then the
truncated-harmonic bound, then exact distances); ``bounds`` holds the lower bounds it prunes
with and their proofs; ``cells`` partitions rows by their features (built with an index);
``table`` is what a search reads (:class:`SearchTable`: an index's stored cells, or one cell
of rows in memory). ``memory`` holds curves in memory behind the reading interface of an
index (:class:`MemoryIndex`); ``rank`` ranks curves in memory against one query
(:func:`rank_curves`); ``matrix`` computes all-pairs distances and an order that groups
similar curves (:func:`distance_matrix`, :func:`similarity_order`); ``rerank`` re-orders by a
diffusion over the collection's neighbour graph (:func:`rerank_index`,
:func:`diffused_similarity`; docs/rerank.md).
"""

#: the public names and their modules, loaded on first use: the index side imports the
#: search's table and bounds (and a query its engine) without loading every search
_LAZY = {
    "search_index": "index_search",
    "SearchStats": "index_search",
    "distance_matrix": "matrix",
    "similarity_order": "matrix",
    "BATCH_ROWS": "matrix",
    "MemoryIndex": "memory",
    "rank_curves": "rank",
    "diffused_similarity": "rerank",
    "rerank_index": "rerank",
}

__all__ = list(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
