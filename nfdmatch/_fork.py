"""Work shared out to forked worker processes that read the parent's memory.

A search over a table held in memory is mostly short numpy calls that hold the GIL; threads
take turns there, processes do not. A worker forked after the table is read shares its
pages with the parent (copy on write: nothing is copied or pickled), gets tasks and sends
results through a pipe, and never touches a file the parent has open: it ends with
``os._exit`` (no finalizers, no atexit handlers), ignores SIGINT (the terminal's Ctrl-C
reaches the whole process group: only the parent acts on it) and exits by itself when the
parent is gone, so that it never holds the index lock for long.

Forking is safe only in a process with one thread (a lock held by another thread at the
fork stays held in the child): :func:`can_fork` says whether this process may.
"""

from __future__ import annotations

import gc
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from typing import cast

from .errors import WorkerError

__all__ = ["can_fork", "fork_map", "SIGNALS"]

#: blocked across a fork, so that none arrives in a child before its handlers are set
SIGNALS = {signal.SIGINT, signal.SIGTERM}
#: how often a worker looks whether its parent is still there (seconds)
_WATCH_SECONDS = 0.5


def can_fork() -> bool:
    """True when this process may fork workers: the platform forks, and this process runs
    one thread only."""
    return hasattr(os, "fork") and threading.active_count() == 1


def become_worker(close_fds: Iterable[int] = ()) -> None:
    """The first steps of a forked worker: SIGINT ignored, SIGTERM the default, the signals
    blocked across the fork unblocked, ``close_fds`` closed (a lock the parent holds must
    not outlive it in a worker), and a thread that ends the worker once its parent is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, SIGNALS)
    for fd in close_fds:
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass
    parent = os.getppid()

    def watch():
        while True:
            time.sleep(_WATCH_SECONDS)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, daemon=True, name="nfdmatch-parent-watch").start()


def _serve(conn, work: Callable, close_fds) -> None:
    """A worker's loop: ``(number, task)`` in, ``(number, True, work(task))`` out, or
    ``(number, False, traceback text)`` when it raised; None ends it."""
    become_worker(close_fds)
    try:
        while True:
            msg = conn.recv()
            if msg is None:
                break
            number, task = msg
            try:
                conn.send((number, True, work(task)))
            except Exception as exc:
                conn.send((number, False, (_one_line(exc), traceback.format_exc())))
    except (EOFError, OSError):  # the parent went away: nothing to report to
        pass
    finally:
        os._exit(0)


def _one_line(exc: BaseException) -> str:
    """``Type: first line of the message`` (or the type alone)."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def fork_map(
    work: Callable, tasks: Sequence, workers: int, collect: Callable, *, close_fds: Iterable[int] = ()
) -> list[int]:
    """Run ``work(task)`` for every task in ``workers`` forked processes, calling
    ``collect(number, result)`` in this process as results come (in any order; ``number``:
    the task's position in ``tasks``). Call only when :func:`can_fork`.

    ``work`` and what it reads are the parent's as of the call (the workers are forked
    here); a task and a result must pickle. Returns the numbers of the tasks no worker
    finished because workers died (killed, out of memory): the caller computes them another
    way (all of them when not one worker could be forked). An exception in ``work`` is
    raised here as :class:`~nfdmatch.errors.WorkerError` (a ``RuntimeError``), its message
    one line naming the worker's exception, its ``detail`` the worker's traceback; the
    workers are stopped on every way out (also KeyboardInterrupt).
    """
    from multiprocessing.connection import Pipe, wait

    close_fds = tuple(close_fds)
    pending = list(range(len(tasks)))[::-1]  # popped from the end: task order
    running: dict = {}  # connection -> (pid, task number or None)
    # no garbage of the parent's is finalized in a worker (a file object collected there
    # would be flushed and closed behind the parent's back): collected here first, and the
    # rest frozen for the workers' collector (which then also leaves its pages unshared)
    gc.collect()
    gc.freeze()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)
    lost: list[int] = []
    finished = False
    try:
        try:
            for _ in range(max(1, min(workers, len(tasks)))):
                mine, theirs = Pipe()
                try:
                    pid = os.fork()
                except OSError:  # no more processes (ulimit -u, memory): those forked do the work
                    mine.close()
                    theirs.close()
                    break
                if pid == 0:  # the worker: the parent's ends of its siblings' pipes are not its own
                    for conn in (mine, *running):
                        conn.close()
                    _serve(theirs, work, close_fds)
                theirs.close()
                running[mine] = [pid, None]
        finally:
            gc.unfreeze()
            # a signal held meanwhile raises here: in the try that stops the workers
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        for conn, state in running.items():
            _give(conn, state, pending, tasks)
        while any(state[1] is not None for state in running.values()):
            for conn in wait([c for c, s in running.items() if s[1] is not None]):
                state = running[conn]
                try:
                    number, ok, result = conn.recv()  # type: ignore[call-arg]
                except (EOFError, OSError):  # the worker died with a task
                    lost.append(state[1])
                    state[1] = None
                    continue
                if not ok:
                    summary, detail = cast("tuple[str, str]", result)  # what _serve sends for a task that raised
                    raise WorkerError.failed_task(summary, detail)
                state[1] = None
                collect(number, result)
                _give(conn, state, pending, tasks)
        finished = True
        return sorted(lost + pending)
    finally:
        # done: the workers wait for a task and go when told; on any other way out (Ctrl-C,
        # SIGTERM, a failed task) they are busy with tasks nobody wants: killed at once, as
        # a command has a moment to clean up before its watchdog kills it (cli/start.py)
        _stop(running, at_once=not finished)


def _give(conn, state: list, pending: list, tasks: Sequence) -> None:
    """The next pending task to the worker behind ``conn``, if there is one."""
    if pending:
        number = pending.pop()
        try:
            conn.send((number, tasks[number]))
        except OSError:  # that worker is gone: the task stays pending
            pending.append(number)
            return
        state[1] = number


def _stop(running: dict, at_once: bool = False) -> None:
    """End the workers: asked first, killed when they do not go within a second; killed
    at once when ``at_once``. Every one is waited for (no zombie is left)."""
    for conn, (pid, _) in running.items():
        try:
            if at_once:
                os.kill(pid, signal.SIGKILL)
            else:
                conn.send(None)
        except OSError:
            pass
    deadline = time.monotonic() + (0.0 if at_once else 1.0)
    for conn, (pid, _) in running.items():
        while True:
            try:
                done, _status = os.waitpid(pid, os.WNOHANG)
            except ChildProcessError:
                break
            if done or time.monotonic() > deadline:
                if not done:
                    try:
                        os.kill(pid, signal.SIGKILL)
                        os.waitpid(pid, 0)
                    except (ProcessLookupError, ChildProcessError):
                        pass
                break
            time.sleep(0.01)
        conn.close()
