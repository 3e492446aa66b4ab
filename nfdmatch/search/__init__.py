"""Exact k nearest curves: lower-bound pruning, then exact distances in batches, over an
index file or curves held in memory.

The modules: ``index_search`` is the search over an index (:func:`search_index`, the
invariant lower bounds, the running top k, :class:`SearchStats`); ``memory`` holds curves in
memory behind the same reading interface (:class:`MemoryIndex`); ``rank`` ranks curves in
memory against one query (:func:`rank_curves`); ``matrix`` computes all-pairs distances and
an order that groups similar curves (:func:`distance_matrix`, :func:`similarity_order`).
"""

from .index_search import CHUNK_ROWS, SearchStats, search_index
from .matrix import BATCH_ROWS, distance_matrix, similarity_order
from .memory import MemoryIndex
from .rank import rank_curves

__all__ = ["rank_curves", "search_index", "distance_matrix", "similarity_order", "SearchStats", "BATCH_ROWS", "CHUNK_ROWS"]
