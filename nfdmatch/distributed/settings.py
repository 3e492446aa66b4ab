"""What the cluster side shares: its settings (task sizes, the window, retries) and its error."""

from __future__ import annotations

from typing import Any

from ..errors import NfdError

__all__ = [
    "ClusterError",
    "DEFAULT_TIMEOUT",
    "CLEANUP_TIMEOUT",
    "TASK_BYTES",
    "TASK_FILES",
    "QUERY_BLOCK",
    "WINDOW_ROWS",
    "RANGE_BYTES",
    "RETRIES",
    "INSTALL_HINT",
]

#: seconds to reach the scheduler and see a worker before giving up (``--scheduler-timeout``)
DEFAULT_TIMEOUT = 10.0
#: seconds the clean-up after a graph search (each worker closes the index it held) may take:
#: a worker stuck in a long call must not hold the build, whose result is complete
CLEANUP_TIMEOUT = 10.0
#: bytes of input files per build task at most: big enough that a task's overhead (~1 ms on
#: the scheduler, a round trip) is small next to reading and describing, small enough that
#: a retried task redoes little and that every worker gets several tasks
TASK_BYTES = 16 << 20
#: files per build task at most (many tiny files: keeps progress and retries fine-grained)
TASK_FILES = 2048
#: build tasks per worker thread at least, when the files allow (load balance)
TASKS_PER_THREAD = 4
#: queries per search task at most: progress granularity and the size of one task's answer
QUERY_BLOCK = 256
#: positions of a query's first-round window (its cells of lowest bound over the whole
#: index): enough to hold its near neighbours, whose distances then seed every range
WINDOW_ROWS = 2048
#: a search table (features, norms, first harmonics, row numbers of every row) up to this
#: size is searched whole by each worker; a bigger one is split in ranges, one per thread
RANGE_BYTES = 2 << 30
#: bytes per index row of a search table held in memory, at K = 16 (35 float32 features,
#: 2 float64 norms, 4 x 3 complex64 harmonics, an int64 row)
TABLE_ROW_BYTES = 260
#: seconds between checks, while a query waits for its range tasks, that the workers they
#: are pinned to are still there
PIN_CHECK_SECONDS = 2.0
#: times Dask re-runs a task that raised (a worker that died is rescheduled by the scheduler
#: itself, up to ``distributed.scheduler.allowed-failures`` times)
RETRIES = 2
INSTALL_HINT = "pip install 'nfdmatch[distributed]' (dask and distributed)"


class ClusterError(NfdError, RuntimeError):
    """The cluster cannot be used: dask missing, scheduler unreachable, no workers, workers
    running another nfdmatch or index format version, a task that failed on every retry."""


def worker_info() -> dict:
    """Run on each worker at connect: what must equal the client's (read at call time)."""
    import sys

    from .. import _version
    from ..index.schema import FORMAT_VERSION

    return {
        "nfdmatch": _version.__version__,
        "format_version": int(FORMAT_VERSION),
        "python": "%d.%d" % sys.version_info[:2],
    }


def first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def task_result(fut: Any, what: str) -> Any:
    """A finished task's answer; a task that failed on every retry is a ClusterError (an
    NfdError it raised stays what it is)."""
    try:
        return fut.result()
    except NfdError:
        raise
    except Exception as exc:
        raise ClusterError(f"a {what} task failed on every try: {type(exc).__name__}: {first_line(exc)}") from None
