"""``--scheduler`` and ``--scheduler-timeout`` of ``index build`` and ``query``: the cluster
options and opening the cluster (nfdmatch.distributed, imported only when asked for)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

from .options import VERBOSE, F, detail, int_option, verbosity

if TYPE_CHECKING:
    from ..distributed import Cluster

#: the default of --scheduler-timeout (nfdmatch.distributed.DEFAULT_TIMEOUT, not imported here
#: so that the CLI starts without dask)
_TIMEOUT = 10.0


def scheduler_options(f: F) -> F:
    """``--scheduler ADDRESS`` (or $NFDMATCH_SCHEDULER) and ``--scheduler-timeout SECONDS``."""
    f = click.option(
        "--scheduler-timeout",
        type=click.FloatRange(min=0, min_open=True),
        default=_TIMEOUT,
        show_default=True,
        envvar="NFDMATCH_SCHEDULER_TIMEOUT",
        help="Seconds to reach the scheduler and see a worker before failing.",
    )(f)
    return click.option(
        "--scheduler",
        default=None,
        envvar="NFDMATCH_SCHEDULER",
        metavar="ADDRESS",
        help="Run on a Dask cluster: a scheduler address (tcp://host:8786; also "
        "$NFDMATCH_SCHEDULER) or local:N for N local worker processes. Needs "
        "pip install 'nfdmatch[distributed]'; see docs/distributed.md.",
    )(f)


def open_cluster(scheduler: str, timeout: float) -> Cluster:
    """The connected :class:`nfdmatch.distributed.Cluster` (a context manager); dask's own
    log lines (worker restarts, lost connections) are shown only with -v."""
    import logging

    from ..distributed import connect

    level = logging.WARNING if verbosity() >= VERBOSE else logging.CRITICAL
    for name in ("distributed", "dask"):
        logging.getLogger(name).setLevel(level)
    cluster = connect(scheduler, timeout)
    detail(f"connected to {cluster.address}: {len(cluster.workers)} workers, {cluster.threads} threads")
    return cluster


def ranges_option(f: F) -> F:
    """``--ranges N`` of ``query``: how the cluster splits the index."""
    return int_option(
        "--ranges",
        metavar="N",
        help="With --scheduler: split the index into N row ranges, each searched by one "
        "worker for every query [default: 1 (each worker searches the whole index for "
        "its share of the queries) up to ~8M curves, else one per worker thread].",
    )(f)
