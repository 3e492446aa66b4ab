"""Building and querying on a Dask cluster (``--scheduler``; docs/distributed.md).

The client keeps everything that decides the result: the build plan (stat, hash), the
writing of the index (temp file, atomic replace, lock), the merge of a query's per-range
top K. The workers only do the bulk work on files and index ranges they read from a path
every machine sees, and return plain numpy arrays, lists and dicts of builtins (never
pickled nfdmatch objects), so that what crosses the network does not depend on the
classes of either side -- only on the nfdmatch and index format versions, which
:func:`connect` checks.

Dask (``dask`` and ``distributed``, the ``distributed`` extra) is imported only here and
only when a cluster is asked for.

Library use::

    with connect("local:2") as cluster:            # or "tcp://host:8786", or a dask Client
        report = cluster.build_index(["curves/"], "curves.h5")
        results, stats = cluster.search_index("curves.h5", queries, k=10)

Test hook: a worker reports ``nfdmatch._version.__version__`` as its version (read when
:func:`connect` asks); tests change it on workers to act out a version mismatch.
"""

from .cluster import Cluster
from .connect import connect
from .settings import DEFAULT_TIMEOUT, INSTALL_HINT, TASK_BYTES, ClusterError

__all__ = ["ClusterError", "Cluster", "connect", "DEFAULT_TIMEOUT", "TASK_BYTES", "INSTALL_HINT"]
