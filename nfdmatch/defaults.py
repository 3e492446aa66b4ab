"""Defaults that the CLI shows and the library uses, kept here because the modules that own
them are too heavy for the CLI's start-up (it must not import h5py; docs/architecture.md):
the index path, the neighbours a ``--graph`` stores, the depth of a re-ranking.

The descriptor defaults (:mod:`nfdmatch.descriptors`) and the method and direction names
(:mod:`nfdmatch.matching`) live with their owners, which the CLI imports.
"""

from __future__ import annotations

import os

__all__ = [
    "INDEX_ENV",
    "DEFAULT_INDEX",
    "default_index_path",
    "DEFAULT_GRAPH_K",
    "FUSED_CANDIDATES",
    "DEFAULT_RERANK_DEPTH",
    "MIN_RERANK_DEPTH",
    "RERANK_CANDIDATES",
    "DEFAULT_RERANK_CANDIDATES",
    "DEFAULT_ELASTIC_DEPTH",
]

#: the environment variable naming the index of every command and function that takes one
INDEX_ENV = "NFDMATCH_INDEX"
#: the index when neither a path nor ``$NFDMATCH_INDEX`` is given
DEFAULT_INDEX = "nfdmatch.h5"
#: neighbours per row when ``--graph`` is given without a number (:mod:`nfdmatch.index.graph`)
DEFAULT_GRAPH_K = 10
#: a fused graph's (``--graph K --elastic``) candidates per row: its exact nearest, at least
#: 3 K (:mod:`nfdmatch.index.graph_build`, :func:`nfdmatch.search.rerank.fused_graph_lists`)
FUSED_CANDIDATES = 30
#: a query's candidates for a re-ranking (``--rerank-depth``), by default and at least
#: (:mod:`nfdmatch.search.rerank`; docs/rerank.md, "Depth": 400 measured no better)
DEFAULT_RERANK_DEPTH = 100
MIN_RERANK_DEPTH = 100
#: where a re-ranking's candidates can come from (``--rerank-candidates``;
#: :mod:`nfdmatch.search.rerank`), and by default
RERANK_CANDIDATES = ("walk", "exact")
DEFAULT_RERANK_CANDIDATES = RERANK_CANDIDATES[0]


def default_index_path() -> str:
    """``$NFDMATCH_INDEX`` if set (and not empty), else ``"nfdmatch.h5"``."""
    return os.environ.get(INDEX_ENV) or DEFAULT_INDEX


#: ``--elastic-depth``: the exact candidates the elastic stage re-orders
DEFAULT_ELASTIC_DEPTH = 100
