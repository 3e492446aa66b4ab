"""Which implementation computes exact distances: the numpy reference path here, or the
numba kernels (:mod:`._kernels`), imported once a process has done enough exact work to pay
for importing them (:func:`use_kernels` chooses explicitly)."""

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
_CALL_WORK = 2_000
#: rows from which a call made on the main thread splits the rows over threads (a call
#: made on another thread, e.g. from search_index's pool over queries, never does)
_THREAD_ROWS = 256
_MAX_THREADS = 4
_kernel_state = {"module": None, "failed": None, "work": 0}
_kernel_lock = threading.Lock()
#: per thread: True inside :func:`reference_path`
_reference = threading.local()


@contextmanager
def reference_path():
    """Within this block, exact_search and grid_maximum on this thread take the numpy path
    (the reference), whatever the process has loaded. Which path a call takes otherwise
    depends on the work the process has done so far, which with queries on threads depends
    on timing; the two paths agree to ~1e-15 but not bit for bit, so a search recomputes the
    distances it reports here to print the same digits run after run."""
    before = getattr(_reference, "on", False)
    _reference.on = True
    try:
        yield
    finally:
        _reference.on = before


def _mode_from_environment(value: str) -> str:
    mode = value.strip().lower()
    if mode in ("0", "off", "no", "false", "numpy"):
        return "off"
    if mode in ("1", "on", "yes", "true", "numba"):
        return "on"
    return "auto"


#: "auto", "on" (numba) or "off" (numpy): NFDMATCH_NUMBA, read once when this module is first
#: imported; :func:`use_kernels` changes it
_kernel_state["mode"] = _mode_from_environment(os.environ.get(_NUMBA_ENV, ""))


def use_kernels(mode: str) -> None:
    """Choose how this process computes exact distances.

    mode : ``"auto"`` (the default: the numba kernels once the process has done enough
        exact work to pay for importing them), ``"numba"`` (from the next call on) or
        ``"numpy"`` (the reference path, never numba). The environment variable
        ``NFDMATCH_NUMBA`` (``auto``, ``1``, ``0``) sets the default when nfdmatch is
        imported; this call is the explicit way for a long-running program.
    """
    modes = {"auto": "auto", "numba": "on", "numpy": "off"}
    if mode not in modes:
        raise ParameterError(f"kernels must be one of {', '.join(modes)}, got {mode!r}")
    with _kernel_lock:
        _kernel_state["mode"] = modes[mode]


def _numba_mode() -> str:
    return _kernel_state.get("mode", "auto")


def _compiled_kernels(work: int):
    """nfdmatch._kernels when it is (or has just become) worth using, else None (numpy path).

    ``work`` is this call's rows x directions x shifts (+ _CALL_WORK). Any failure to import
    numba or to load / compile the kernels (e.g. no writable cache directory: compiling in
    every process would cost more than it saves) falls back to numpy for the rest of the
    process; with NFDMATCH_NUMBA=1 that also warns.
    """
    state = _kernel_state
    mode = _numba_mode()
    if mode == "off" or getattr(_reference, "on", False):
        return None
    if state["module"] is not None or state["failed"] is not None:
        return state["module"]
    state["work"] += work
    if mode == "auto" and state["work"] < _NUMBA_AMORTIZE:
        return None
    with _kernel_lock:
        if state["module"] is None and state["failed"] is None:
            try:
                from . import _kernels
                _warm_up(_kernels)
            except Exception as exc:             # ImportError, numba errors: numpy it is
                state["failed"] = exc
                if mode == "on":
                    import warnings
                    warnings.warn(f"nfdmatch: numba kernels unavailable, using numpy ({exc!r})",
                                  RuntimeWarning, stacklevel=3)
            else:
                state["module"] = _kernels
    return state["module"]


def _warm_up(kernels) -> None:
    """Compile (or load from numba's cache) the kernel on a tiny input with the argument
    types exact_search passes, so that a failure shows here, once."""
    A = np.ones((2, 3), dtype=np.complex128)
    B = np.ones((1, 2, 3), dtype=np.complex128)
    basis, quarter = _folded_basis(2, 8)
    kernels.exact_rows(A, A, np.ones(2), B, 1, basis, quarter, 8, False, 1, True, 1.0)
    kernels.grid_maximum_rows(A, B, 1, basis, quarter, 8, False)


def compile_kernels() -> bool:
    """Compile (or load from numba's cache) the exact-search kernels now and keep them for
    this process. ``make install`` runs it once, so that the first query of a new install
    does not pay the ~15-20 s compile. Returns False when numba cannot be used (the numpy
    path then serves every search)."""
    try:
        from . import _kernels
        _warm_up(_kernels)
    except Exception:                      # ImportError, numba errors: the numpy path serves
        return False
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
