"""Reaching a cluster: :func:`connect` (a scheduler address, ``local:N`` or a Dask client)."""

from __future__ import annotations

from typing import Any

import os
import time

from ..errors import ParameterError
from .cluster import Cluster
from .settings import DEFAULT_TIMEOUT, INSTALL_HINT, ClusterError, first_line

__all__ = ["connect"]


def _import_distributed():
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise ClusterError(f"--scheduler needs dask and distributed, which are not installed: {INSTALL_HINT}") from None
    return distributed


def _close_half_built(exc: BaseException, client_class: Any) -> None:
    """Close the Client whose constructor raised ``exc``, now, while its event loop runs.

    Dask closes it itself only on OSError; after another error (an address without a
    port, a peer answering garbage) it stays "connecting", and its ``__del__`` at
    interpreter exit waited on the stopped loop, then printed a traceback."""
    tb = exc.__traceback__
    while tb is not None:
        half = tb.tb_frame.f_locals.get("self")
        if isinstance(half, client_class):
            try:
                half.close(timeout=1)
            except Exception:
                pass
            return
        tb = tb.tb_next


# --------------------------------------------------------------------------- connecting


#: Dask settings for a cluster nfdmatch starts on this machine (``local:N``): its scheduler,
#: nannies and workers wake up less often (event-loop tick 20 ms -> 1 s, worker memory check
#: 100 ms -> 2 s, system monitor 500 ms -> 5 s, no statistical profiler). Idle, a 2-worker
#: cluster slowed a local build on the same 2 cores by 16% with Dask's defaults, 10% with
#: these (benchmarks/bench_distributed.py; docs/distributed.md). What they give up: the
#: dashboard's fine-grained figures and a worker's reaction to a memory spike within 2 s
#: instead of 0.1 s (a task holds at most TASK_BYTES of files).
_LOCAL_CLUSTER_CONFIG = {
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.memory.monitor-interval": "2s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.profile.enabled": False,
}


def connect(scheduler: Any, timeout: float = DEFAULT_TIMEOUT) -> Cluster:
    """Connect to a Dask cluster and check its workers.

    Parameters
    ----------
    scheduler : ``"local:N"`` (start a LocalCluster of N single-threaded worker processes
        on this machine; ``"local"``: one per core), a scheduler address
        (``"tcp://host:8786"``, ``"host:8786"``), or an existing ``distributed.Client``
        (not closed by :meth:`Cluster.close`).
    timeout : seconds to reach the scheduler and to see at least one worker.

    Raises
    ------
    ClusterError : dask not installed; scheduler unreachable or no worker within
        ``timeout``; a worker whose nfdmatch, index format or Python version differs from
        this process's.
    ParameterError : a malformed ``local:N``, a timeout not > 0.
    """
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0:
        raise ParameterError(f"the scheduler timeout must be a number of seconds > 0, got {timeout!r}")
    _import_distributed()
    import logging

    from distributed import Client, LocalCluster

    owned_cluster = None
    if isinstance(scheduler, Client):
        client, owned_client = scheduler, False
        where = str(scheduler.scheduler.address if scheduler.scheduler else scheduler)
    else:
        where = str(scheduler).strip()
        if where == "local" or where.startswith("local:"):
            n = where.partition(":")[2]
            try:
                workers = int(n) if n else (os.cpu_count() or 1)
            except ValueError:
                workers = 0
            if workers < 1:
                raise ParameterError(f"--scheduler local:N needs a number of workers N >= 1, got {where!r}")
            import dask

            try:
                # its processes share this machine's cores with the work: fewer wake-ups
                with dask.config.set(_LOCAL_CLUSTER_CONFIG):
                    owned_cluster = LocalCluster(
                        n_workers=workers,
                        threads_per_worker=1,
                        processes=True,
                        # its HTTP routes on a free port: None still binds 8787, and
                        # warns when another cluster on this machine holds it
                        dashboard_address=":0",
                        silence_logs=logging.ERROR,
                    )
            except Exception as exc:
                raise ClusterError(
                    f"cannot start a local Dask cluster of {workers} workers: {type(exc).__name__}: {exc}"
                ) from None
            target = owned_cluster
        else:
            target = where
        started = time.monotonic()
        try:
            client = Client(target, timeout=timeout, set_as_default=False)
        except Exception as exc:  # OSError / TimeoutError: nothing listening, wrong host
            # "within" only when the timeout ran out: an address Dask cannot parse, or a
            # peer answering garbage, fails at once
            waited = f"within {timeout:g} s " if time.monotonic() - started >= 0.9 * timeout else ""
            _close_half_built(exc, Client)
            if owned_cluster is not None:
                owned_cluster.close()
            raise ClusterError(
                f"cannot reach the Dask scheduler at {where} {waited}"
                f"({type(exc).__name__}: {first_line(exc)}); start one with "
                f"`dask scheduler` or use --scheduler local:N"
            ) from None
        owned_client = True
    cluster = Cluster(client, owned_client, owned_cluster, where)
    try:
        cluster._check_workers(timeout)
    except BaseException:
        cluster.close()
        raise
    return cluster
