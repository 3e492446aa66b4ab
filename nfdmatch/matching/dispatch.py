"""Which implementation computes exact distances: the numpy reference path here, the
kernels of :mod:`._kernels` compiled ahead of time (:mod:`.aot`, built by ``make
install``: no import cost), or the same kernels compiled just in time by numba, imported
once a process has done enough exact work to pay for importing them (:func:`use_kernels`
chooses explicitly).

Test hook: ``_kernel_state`` (module, failed, work, mode, aot) is the process's choice; the
kernel tests replace it with a fresh dict to act out a new process."""

from __future__ import annotations

import os
import threading
from contextlib import contextmanager
from functools import lru_cache

import numpy as np

from ..errors import ParameterError


# exact_search also exists as one numba kernel (_kernels.py), same results as the numpy path
# here (the reference) to ~1e-15; speed figures: docs/performance.md, from
# benchmarks/bench_distance.py. numba is imported lazily, once the process has done enough
# exact work to amortize importing it: a ski-rental rule -- switch once the numpy work done
# so far would have paid for the import -- keeps `import nfdmatch`, the CLI start-up and
# small queries free of numba, and costs a long run at most that one import. The first use
# after an install or an edit of _kernels.py compiles (cached next to the module or in
# numba's user cache); `make install` does that once (compile_kernels).

_NUMBA_ENV = "NFDMATCH_NUMBA"
#: numpy exact work (rows x directions x shifts, plus _CALL_WORK per call) worth one numba
#: import: the numpy path costs ~0.5 us per unit (~1 ms per call), importing numba and
#: loading the cached kernels ~0.4 s
_NUMBA_AMORTIZE = 800_000
#: work done on the ahead-of-time kernels (~0.065 us per unit) worth importing the
#: just-in-time ones (0.4-0.5 s), which split big calls and queries over the cores
_JIT_AFTER_AOT = 8_000_000
_CALL_WORK = 2_000
#: rows from which a call made on the main thread splits the rows over threads (a call
#: made on another thread, e.g. from search_index's pool over queries, never does)
_THREAD_ROWS = 256
_MAX_THREADS = 4
_kernel_state = {"module": None, "failed": None, "work": 0}
_kernel_lock = threading.Lock()
#: per thread: True inside :func:`reference_path`
_reference = threading.local()
#: per thread: True inside :func:`no_switch_by_work`
_held = threading.local()


@contextmanager
def _on_this_thread(flag: threading.local):
    """``flag.on`` True on this thread within the block (nested blocks restore it)."""
    before = getattr(flag, "on", False)
    flag.on = True
    try:
        yield
    finally:
        flag.on = before


def reference_path():
    """Within this block, exact_search and grid_maximum on this thread take the numpy path
    (the reference), whatever the process has loaded. Which path a call takes otherwise
    depends on the work the process has done so far, which with queries on threads depends
    on timing; the two paths agree to ~1e-15 but not bit for bit, so a search recomputes the
    distances it reports here to print the same digits run after run."""
    return _on_this_thread(_reference)


def no_switch_by_work():
    """Within this block, calls on this thread keep to the ahead-of-time kernels when those
    serve them: no switch to the just-in-time ones by the work done so far. For a caller
    that makes that choice itself (``search_index`` answering a batch on one thread loads
    them only when its threads would gain more than their import costs)."""
    return _on_this_thread(_held)


def _mode_from_environment(value: str) -> str:
    mode = value.strip().lower()
    if mode in ("0", "off", "no", "false", "numpy"):
        return "off"
    if mode in ("1", "on", "yes", "true", "numba"):
        return "on"
    if mode == "aot":
        return "aot"
    return "auto"


#: "auto", "on" (numba) or "off" (numpy): NFDMATCH_NUMBA, read once when this module is first
#: imported; :func:`use_kernels` changes it
_kernel_state["mode"] = _mode_from_environment(os.environ.get(_NUMBA_ENV, ""))


def use_kernels(mode: str) -> None:
    """Choose how this process computes exact distances.

    mode : ``"auto"`` (the default: the kernels compiled ahead of time when ``make install``
        built them, else numpy until the process has done enough exact work to pay for
        importing the just-in-time numba kernels), ``"numba"`` (the just-in-time kernels,
        from the next call on), ``"aot"`` (the ahead-of-time kernels when built, else numpy)
        or ``"numpy"`` (the reference path). The environment variable ``NFDMATCH_NUMBA``
        (``auto``, ``1``, ``0``, ``aot``) sets the default when nfdmatch is imported; this
        call is the explicit way for a long-running program.
    """
    modes = {"auto": "auto", "numba": "on", "numpy": "off", "aot": "aot"}
    if mode not in modes:
        raise ParameterError(f"kernels must be one of {', '.join(modes)}, got {mode!r}")
    with _kernel_lock:
        _kernel_state["mode"] = modes[mode]


def _numba_mode() -> str:
    return _kernel_state.get("mode", "auto")


_UNLOADED = object()
_kernel_state["aot"] = _UNLOADED


def _aot_kernels():
    """The ahead-of-time kernels (:mod:`.aot`) when built for this source, else None; looked
    up once per process (~1 ms)."""
    got = _kernel_state.get("aot", _UNLOADED)
    if got is _UNLOADED:
        from . import aot

        got = _kernel_state["aot"] = aot.load()
    return got


def _compiled_kernels(work: int):
    """The kernels a call of ``work`` units should use, or None for the numpy path.

    ``work`` is this call's rows x directions x shifts (+ _CALL_WORK). In ``auto`` mode the
    ahead-of-time kernels serve every call when built (no import cost); without them numpy
    serves until the work done so far would have paid for importing numba, then the
    just-in-time kernels. Once these are loaded (``numba`` mode, the switch above, or
    :func:`load_threaded_kernels`) they serve every call. Any failure to import numba or to
    load / compile its kernels (e.g. no writable cache directory: compiling in every process
    would cost more than it saves) falls back for the rest of the process; with
    NFDMATCH_NUMBA=1 that also warns.
    """
    state = _kernel_state
    mode = _numba_mode()
    if mode == "off" or getattr(_reference, "on", False):
        return None
    if state["module"] is not None:
        return state["module"]
    if mode == "aot":
        return _aot_kernels()
    if mode == "auto":
        aot = _aot_kernels()
        if state["failed"] is not None:
            return aot
        state["work"] += work
        if aot is not None:
            # built releasing the GIL (aot.py), they are the threaded kernels already; else
            # the same ski-rental, against them: a long run (an all-pairs matrix, a graph, a
            # big batch) pays for the threaded ones once it has done as much work as their
            # import costs; one core gains nothing from them
            if aot.threads or state["work"] < _JIT_AFTER_AOT or cpu_count() < 2 or getattr(_held, "on", False):
                return aot
            return state["module"] if _load_jit(warn=False) else aot
        if state["work"] < _NUMBA_AMORTIZE:
            return None
    elif state["failed"] is not None:
        return None
    _load_jit(warn=mode == "on")
    return state["module"]


def _load_jit(warn: bool) -> bool:
    """Import the just-in-time kernels once (compiling them on a first use); False when they
    cannot be used in this process."""
    state = _kernel_state
    with _kernel_lock:
        if state["module"] is None and state["failed"] is None:
            try:
                from . import _kernels

                _warm_up(_kernels)
            except Exception as exc:  # ImportError, numba errors: numpy it is
                state["failed"] = exc
                if warn:
                    import warnings

                    warnings.warn(
                        f"nfdmatch: numba kernels unavailable, using numpy ({exc!r})", RuntimeWarning, stacklevel=4
                    )
            else:
                state["module"] = _kernels
    return state["module"] is not None


def threads_help() -> bool:
    """Whether exact work spread over threads runs in parallel: False when the calls would
    go to ahead-of-time kernels built holding the GIL (threads would only take turns)."""
    kernels = _compiled_kernels(0) if _numba_mode() != "off" else None
    return kernels is None or getattr(kernels, "threads", True)


def load_threaded_kernels() -> bool:
    """Switch this process to the just-in-time kernels (they release the GIL, so queries on
    threads run in parallel), unless the mode forbids it; True when they now serve calls.
    For a caller that has measured enough work ahead to pay for importing numba (~0.45 s)."""
    if _numba_mode() not in ("auto", "on"):
        return False
    return _load_jit(warn=False)


_cpu_count: list[int] = []


def cpu_count() -> int:
    """os.cpu_count(), looked up once (it reads /proc or /sys on every call: ~50 us, paid per
    kernel call of a search otherwise)."""
    if not _cpu_count:
        _cpu_count.append(os.cpu_count() or 1)
    return _cpu_count[0]


def _warm_up(kernels) -> None:
    """Compile (or load from numba's cache) the kernel on a tiny input with the argument
    types exact_search passes, so that a failure shows here, once."""
    A = np.ones((2, 3), dtype=np.complex128)
    B = np.ones((1, 2, 3), dtype=np.complex128)
    basis, quarter = _folded_basis(2, 8)
    kernels.exact_rows(A, A, np.ones(2), B, 1, basis, quarter, 8, False, 1, True, 1.0)
    from .common import _integer_shift_basis

    one = np.ones(1)
    for harmonics in (2, 4, 8):  # the general grid bound and the ones specialised for K'
        Ah = np.ones((harmonics, 3), dtype=np.complex128)
        Bh = np.ones((1, harmonics, 3), dtype=np.complex128)
        kernels.grid_bound_rows(Ah, Bh, 2, np.array(_integer_shift_basis(harmonics, 24)), 3, False, one, one, one)


def compile_kernels(ahead_of_time: bool = True) -> bool:
    """Compile (or load from numba's cache) the just-in-time kernels now and keep them for
    this process; with ``ahead_of_time``, also build the extension module of :mod:`.aot`
    when it is missing or stale (~30 s). ``make install`` runs it once, so that neither the
    first query of a new install nor any single query pays for compiling or importing
    numba. Returns False when numba cannot be used (the numpy path then serves every
    search)."""
    try:
        from . import _kernels

        _warm_up(_kernels)
    except Exception:  # ImportError, numba errors: the numpy path serves
        return False
    if ahead_of_time:
        from . import aot

        if aot.load() is None:
            try:
                aot.build()
            except Exception:  # no C compiler, numba.pycc gone: the JIT serves
                pass
        _kernel_state["aot"] = _UNLOADED
    with _kernel_lock:
        _kernel_state["module"] = _kernels
    return True


@lru_cache(maxsize=32)
def _folded_basis(K: int, n: int) -> tuple[np.ndarray, bool]:
    """The integer-shift basis for the kernels: (2K, width) columns s = 0..n/4 (when n is
    divisible by 4, ``quarter``) or 0..n/2 of [2 cos(2 pi k s / n); -2 sin(2 pi k s / n)], the
    angle reduced exactly ((k s) mod n), zero-padded to a multiple of 8 columns."""
    quarter = n % 4 == 0
    count = n // 4 + 1 if quarter else n // 2 + 1
    width = -(-count // 8) * 8
    s = np.arange(count)
    theta = (2.0 * np.pi / n) * ((np.arange(1, K + 1)[:, None] * s[None, :]) % n)
    basis = np.zeros((2 * K, width))
    basis[:K, :count] = 2.0 * np.cos(theta)
    basis[K:, :count] = -2.0 * np.sin(theta)
    basis.setflags(write=False)
    return basis, quarter
