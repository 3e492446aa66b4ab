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

from .index_search import SearchStats, search_index
from .matrix import BATCH_ROWS, distance_matrix, similarity_order
from .memory import MemoryIndex
from .rank import rank_curves
from .rerank import diffused_similarity, rerank_index

__all__ = [
    "rank_curves",
    "search_index",
    "distance_matrix",
    "similarity_order",
    "SearchStats",
    "MemoryIndex",
    "BATCH_ROWS",
    "diffused_similarity",
    "rerank_index",
]
