"""The ``nfdmatch`` program's first steps: gone within a second of SIGINT or SIGTERM, whatever
it is doing.

Python runs a signal handler only between two bytecodes of the main thread: inside a long C
call that keeps the GIL (HDF5 through h5py does; an HDF5 loop on a damaged file never
returns, issue 34) no handler runs, and no Python thread either, so no watchdog thread can
help. So :func:`run` forks before anything heavy is imported: the **command** runs in the
child; the parent, the **watchdog**, holds nothing but the interpreter and waits. On
SIGINT/SIGTERM (its own, or its process group's: a terminal, ``timeout``, systemd) the
watchdog passes the signal on to a command still running :data:`PASS_ON_AFTER` seconds
later (a group's signal reached it already) and gives it :data:`GRACE` seconds to clean
up and exit as usual (130 / 143, one line: ``cli/options.py``); a command still there then
is killed (SIGKILL) and the watchdog exits 130 / 143 with one line. What such a command
leaves is what ``kill -9`` leaves: its temporary index file (removed by the next build into
that index, docs/index-format.md) and its lock (released by the kernel at its death).

Until a command runs (imports, argument parsing) a signal ends the process at once with
that one line and exit code: nothing is held yet. While a command runs, the first signal
raises in the main thread (:class:`KeyboardInterrupt`, or :class:`Terminated` for SIGTERM)
and later ones are ignored, so that the first unwinds with its clean-ups uninterrupted
(:func:`raising`, installed by the group for the duration of a command).

The command's exit status is the watchdog's: its exit code, or, when a signal killed it
(a crash), the same signal. ``NFDMATCH_NO_WATCHDOG=1`` runs the command in the one process
(no fork; a command inside a long C call then waits for the call).

Imports here: the standard library's cheapest modules only (it runs before numpy).
"""

from __future__ import annotations

import os
import signal
import time

#: seconds a command has after SIGINT/SIGTERM before the watchdog kills it (the goal: gone
#: within 1 s; a command's own clean-up takes milliseconds)
GRACE = 0.8
#: seconds after which the watchdog passes its signal on to a command still running
PASS_ON_AFTER = 0.05
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143
_STOPPING = (signal.SIGINT, signal.SIGTERM)


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM, so that a command unwinds as on Ctrl-C
    (temporary files removed, worker processes stopped) and exits 143."""


def exit_code(signum: int) -> int:
    return EXIT_TERMINATED if signum == signal.SIGTERM else EXIT_INTERRUPTED


def message(signum: int) -> str:
    return "terminated (SIGTERM)" if signum == signal.SIGTERM else "interrupted (SIGINT)"


def _say(line: str) -> None:
    try:
        os.write(2, f"Error: {line}\n".encode())
    except OSError:
        pass


def _exit_now(signum, frame):
    """Before a command runs: nothing to clean up, so the one line and the exit code now."""
    for s in _STOPPING:  # a second signal would run this again, between two of its lines
        signal.signal(s, signal.SIG_IGN)
    _say(message(signum))
    os._exit(exit_code(signum))


_raised = False
#: this process runs the command of the program (run()), not a test's or a library caller's
_program = False


def _deaf() -> None:
    """SIGINT/SIGTERM ignored from now on: the process is on its way out (a signal passed on
    by the watchdog after the first must not cut its clean-up or its exit short; Python's
    finalisation resets handlers, not an ignored signal)."""
    for s in _heeded(_STOPPING):
        signal.signal(s, signal.SIG_IGN)


def _raise_once(signum, frame):
    global _raised
    if _raised:
        return  # the first signal is unwinding; the watchdog keeps the deadline
    _raised = True
    raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def raising():
    """While a command runs (main thread only): the first SIGINT/SIGTERM raises
    KeyboardInterrupt/Terminated, later ones are ignored. Returns what restores the
    previous handlers, or None off the main thread."""
    import threading

    global _raised
    if threading.current_thread() is not threading.main_thread():
        return None
    _raised = False
    previous = {s: signal.signal(s, _raise_once) for s in _heeded(_STOPPING)}

    def restore():
        if _raised and _program:
            _deaf()
            return
        for s, handler in previous.items():
            signal.signal(s, handler)

    return restore


#: what the watchdog waits for, blocked in it (no handler: nothing raises at a bad moment)
_WAITED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD)


def _mirror(status: int) -> None:
    """Exit as the command did: its code, or killed by the same signal."""
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        signal.signal(sig, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, [sig])
        os.kill(os.getpid(), sig)
        os._exit(128 + sig)
    os._exit(os.WEXITSTATUS(status) if os.WIFEXITED(status) else 1)


def _watch(pid: int) -> None:
    """The watchdog's life: wait for the command; on SIGINT/SIGTERM/SIGHUP pass it on and
    keep the deadline. Never returns."""
    signum = deadline = None
    passed_on, passed_on_at = False, 0.0
    waited = _heeded(_WAITED)
    while True:
        if deadline is None:
            info = signal.sigwaitinfo(waited)
        else:
            wake = deadline if passed_on else min(deadline, passed_on_at)
            info = signal.sigtimedwait(waited, max(0.0, wake - time.monotonic()))
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            _mirror(status)
        now = time.monotonic()
        if signum is not None and not passed_on and now >= passed_on_at:
            # still there: the signal was this process's alone (`kill PID`), or the command
            # is inside a long call (where the signal waits, and the deadline ends it)
            os.kill(pid, signum)
            passed_on = True
        if deadline is not None and now >= deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            _say(f"{message(signum)}: the command did not stop within {GRACE} s (inside a long call); killed")
            os._exit(exit_code(signum))
        if info is not None and info.si_signo != signal.SIGCHLD and signum is None:
            signum = info.si_signo
            # a signal to the process group (a terminal, `timeout`) reached the command too:
            # it is passed on only if the command has not ended a moment later, so that it
            # does not come twice
            passed_on_at = now + PASS_ON_AFTER
            deadline = now + GRACE


def _heeded(signals) -> list:
    """``signals`` minus those ignored when the program started (a job started in the
    background of a non-interactive shell, or by nohup: it must stay deaf to them)."""
    return [s for s in signals if s not in _IGNORED]


_IGNORED = frozenset(s for s in _WAITED if s != signal.SIGCHLD and signal.getsignal(s) == signal.SIG_IGN)


def install() -> None:
    """The command's side: until a command runs, SIGINT/SIGTERM exit at once."""
    for s in _heeded(_STOPPING):
        signal.signal(s, _exit_now)


def run() -> None:
    """The console script ``nfdmatch`` and ``python -m nfdmatch``."""
    watchdog = hasattr(os, "fork") and hasattr(signal, "sigtimedwait") and not os.environ.get("NFDMATCH_NO_WATCHDOG")
    if watchdog:
        # blocked before the fork: in the watchdog for good, in the command until its handlers are set
        signal.pthread_sigmask(signal.SIG_BLOCK, _heeded(_WAITED))
        child_handler = signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # ignored: no status to wait for
        pid = os.fork()
        if pid:
            _watch(pid)
        signal.signal(signal.SIGCHLD, child_handler)
    global _program
    _program = True
    install()
    if watchdog:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _heeded(_WAITED))
    from . import main

    try:
        main(prog_name="nfdmatch")
    finally:
        _deaf()  # done: a signal now would only turn a finished command into a killed one
