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
#: a query's candidates for a re-ranking (``--rerank-depth``), by default and at least
#: (:mod:`nfdmatch.search.rerank`): 400 puts the same top 40 as ``matrix --rerank`` in 99.4% of
#: the places of 1,400 generated curves in families of 20, 100 in 95.7%, at 1.4x the batch's
#: time (docs/rerank.md)
DEFAULT_RERANK_DEPTH = 400
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
