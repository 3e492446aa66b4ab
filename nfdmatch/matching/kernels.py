"""Which implementation computes exact distances in this process: one choice, made once,
with its reason, named by ``--stats`` and ``-v``.

The rule (:func:`choose`), for the setting ``NFDMATCH_KERNELS`` (``auto``, the default;
``aot``, ``numba`` or ``numpy`` to force one):

1. **aot**: the kernels of :mod:`._kernels` compiled ahead of time (:mod:`.aot`, built by
   ``make install``), when present and built from this source: no import cost;
2. **numba**: else the same kernels compiled just in time, when numba imports and they
   compile (or load from numba's cache): ~0.45 s per process;
3. **numpy**: else the numpy reference path.

The choice is process-wide state and says so: :func:`current` returns it (deciding on first
use from the environment), :func:`use_kernels` makes it explicitly. Nothing switches later:
no counters of work done, no timing, no per-thread flags. A caller that needs the reference
digits passes ``kernels=NUMPY`` to the distance functions (a search recomputes the rows it
reports so, whatever the process uses: the compiled kernels agree with numpy to ~1e-15, not
bit for bit).

A call splits its rows over threads (:meth:`Kernels.workers`; the graph push its sources)
when its kernels release the GIL, the call has enough rows and it is made on the main
thread (a search answering queries on threads has its cores busy already), up to
:func:`set_call_threads`'s limit (a forked search worker sets 1: its sibling processes
have the other cores). The split's thread pool
is shut down at exit (:func:`._threads.shutdown`), or before a fork (:func:`before_fork`).
"""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import os
import threading
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import ParameterError

if TYPE_CHECKING:
    from collections.abc import Callable

__all__ = [
    "Kernels",
    "NUMPY",
    "ENVIRONMENT",
    "CHOICES",
    "choose",
    "chosen",
    "current",
    "use_kernels",
    "set_call_threads",
    "before_fork",
    "compile_kernels",
    "graph_push",
    "elastic_kernel",
]

#: the one setting: which kernels a process uses (read when the first exact distance needs it)
ENVIRONMENT = "NFDMATCH_KERNELS"
CHOICES = ("auto", "aot", "numba", "numpy")
#: rows from which a call made on the main thread splits its rows over threads
_THREAD_ROWS = 256
_MAX_THREADS = 4


@dataclass(frozen=True)
class Kernels:
    """An implementation of the exact distance's inner loops.

    ``name``: ``"aot"``, ``"numba"`` or ``"numpy"``; ``module``: what serves the calls
    (``exact_rows``, ``grid_bound_rows``), None for numpy (the callers' own code);
    ``threads``: calls on several threads run in parallel (the compiled kernels release the
    GIL; an ahead-of-time build that could not, does not); ``reason``: why this one, in words
    (for ``-v`` and ``--stats``)."""

    name: str
    module: object | None
    threads: bool
    reason: str

    def workers(self, rows: int, least: int = _THREAD_ROWS) -> int:
        """Threads a call of ``rows`` rows splits its rows over (1: no split); ``least``: the
        fewest rows for which a split pays (the graph push's: sources)."""
        if (
            self.module is None
            or not self.threads
            or rows < least
            or _call_threads <= 1
            or threading.current_thread() is not threading.main_thread()
        ):
            return 1
        return min(cpu_count(), _call_threads)

    def describe(self) -> str:
        """One line: the name and the reason."""
        return f"{self.name} ({self.reason})"


#: the numpy reference path
NUMPY = Kernels("numpy", None, True, "the numpy reference path")

#: the process's choice (None: not made yet); set by :func:`current` or :func:`use_kernels`
_chosen: Kernels | None = None
_lock = threading.Lock()


def choose(setting: str = "auto") -> Kernels:
    """The kernels the rule gives for ``setting`` (one of :data:`CHOICES`), loading them;
    never fails: what cannot be loaded falls to the next rule, with the reason."""
    setting = (setting or "auto").strip().lower()
    if setting not in CHOICES:
        raise ParameterError(f"{ENVIRONMENT} must be one of {', '.join(CHOICES)}, got {setting!r}")
    if setting == "numpy":
        return Kernels("numpy", None, True, f"{ENVIRONMENT}=numpy")
    why = []
    if setting in ("auto", "aot"):
        from . import aot

        built = aot.load()
        if built is not None:
            held = "" if built.threads else "; built holding the GIL: one thread"
            return Kernels("aot", built, built.threads, f"compiled ahead of time for this source{held}")
        why.append(aot.unused_reason() or "no ahead-of-time build for this source (make install builds it)")
    if setting in ("auto", "numba"):
        try:
            from . import _kernels

            _warm_up(_kernels)
        except Exception as exc:  # ImportError, numba errors (no writable cache): numpy it is
            why.append(f"numba unavailable ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})")
        else:
            return Kernels("numba", _kernels, True, "; ".join(why + ["compiled just in time by numba"]))
    return Kernels("numpy", None, True, "; ".join(why) or "the numpy reference path")


def chosen() -> Kernels | None:
    """The kernels this process chose, or None while no exact distance needed a choice."""
    return _chosen


def current() -> Kernels:
    """The kernels this process uses: chosen on first use by the rule for ``NFDMATCH_KERNELS``
    (:func:`choose`), unless :func:`use_kernels` chose them."""
    global _chosen
    if _chosen is None:
        with _lock:
            if _chosen is None:
                _chosen = choose(os.environ.get(ENVIRONMENT, "auto"))
    return _chosen


def use_kernels(setting: str | Kernels) -> Kernels:
    """Choose the kernels of this process explicitly (a setting of :data:`CHOICES`, or a
    :class:`Kernels`); returns what serves from now on (the rule's fallback when the one
    asked for cannot be loaded: see its ``reason``)."""
    global _chosen
    got = setting if isinstance(setting, Kernels) else choose(setting)
    with _lock:
        _chosen = got
    return got


#: the most threads one call splits its rows over (process-wide; :func:`set_call_threads`)
_call_threads = _MAX_THREADS


def set_call_threads(limit: int) -> None:
    """From now on, a call of this process splits its rows over at most ``limit`` threads
    (1: never; the default is 4, within the cores)."""
    global _call_threads
    _call_threads = max(1, int(limit))


def before_fork() -> None:
    """Stop the idle threads of the calls' pool (a later call starts it again), so that this
    process may fork workers (:func:`nfdmatch._fork.can_fork`)."""
    from ._threads import shutdown

    shutdown()


_cpu_count: list[int] = []


def cpu_count() -> int:
    """os.cpu_count(), looked up once (it reads /proc or /sys on every call: ~50 us, paid per
    kernel call of a search otherwise)."""
    if not _cpu_count:
        _cpu_count.append(os.cpu_count() or 1)
    return _cpu_count[0]


def graph_push(kernels: Kernels | None = None) -> Callable[..., Any] | None:
    """The compiled personalised-PageRank push (:func:`._graph_kernels.push_sources`) of
    ``kernels`` (default: the process's, :func:`current`): the ahead-of-time module's, or
    numba's just-in-time one; None for the numpy kernels, or when numba cannot compile it
    (the walk then pushes with numpy: the same doubles, slower)."""
    kernels = kernels or current()
    if kernels.name == "aot":
        return kernels.module.push_sources
    if kernels.name == "numba":
        return _jit_graph_push()
    return None


def elastic_kernel(kernels: Kernels | None = None) -> Callable[..., Any] | None:
    """The compiled elastic distance (:func:`._elastic_kernels.elastic_rows`) of ``kernels``
    (default: the process's): the ahead-of-time module's, or numba's just-in-time one; None
    for the numpy kernels, or when numba cannot compile it (the numpy reference of
    :mod:`.elastic` then serves)."""
    kernels = kernels or current()
    if kernels.name == "aot":
        return getattr(kernels.module, "elastic_rows", None)
    if kernels.name == "numba":
        return _jit_elastic()
    return None


@lru_cache(maxsize=1)
def _jit_elastic():
    """numba's elastic kernel, compiled (or loaded from numba's cache) and tried once on a
    one-harmonic circle; None when it cannot be."""
    try:
        from ._elastic_kernels import elastic_rows

        circle = np.zeros((1, 1, 3), dtype=np.complex128)
        circle[0, 0, 0], circle[0, 0, 1] = 0.5, -0.5j
        elastic_rows(circle[0], circle, np.zeros(1), np.array([1, 2], dtype=np.int64), 8, 1, 1e-3, np.zeros(1))
    except Exception:  # numba errors: the numpy reference serves
        return None
    return elastic_rows


@lru_cache(maxsize=1)
def _jit_graph_push():
    """numba's push, compiled (or loaded from numba's cache) and tried once; None when it
    cannot be."""
    try:
        from . import _graph_kernels

        _warm_up_push(_graph_kernels.push_sources)
    except Exception:  # numba errors: the numpy push serves
        return None
    return _graph_kernels.push_sources


def _warm_up_push(push) -> None:
    """The push on a two-node walk with the argument types the walk passes."""
    source, walk = np.zeros(1, np.int64), (np.array([[0, 1], [1, 0]]), np.full((2, 2), 0.5), np.ones(2, dtype=bool))
    state = (np.zeros(1, np.int64), np.zeros(2, np.int64), np.zeros(0, np.int64), np.zeros(0))
    state += (np.zeros(2, np.int64), np.zeros(0, np.int64), np.zeros(0))
    push(source, *state, *walk, np.full(2, -1, dtype=np.int64), 0.8, 1e-5)


def _warm_up(kernels) -> None:
    """Compile (or load from numba's cache) the kernel on a tiny input with the argument
    types exact_search passes, so that a failure shows here, once."""
    A = np.ones((2, 3), dtype=np.complex128)
    B = np.ones((1, 2, 3), dtype=np.complex128)
    basis, quarter = folded_basis(2, 8)
    kernels.exact_rows(A, A, np.ones(2), B, 1, basis, quarter, 8, False, 1, True, 1.0)
    from .common import integer_shift_basis

    one = np.ones(1)
    for harmonics in (2, 4, 8):  # the general grid bound and the ones specialised for K'
        Ah = np.ones((harmonics, 3), dtype=np.complex128)
        Bh = np.ones((1, harmonics, 3), dtype=np.complex128)
        kernels.grid_bound_rows(Ah, Bh, 2, np.array(integer_shift_basis(harmonics, 24)), 3, False, one, one, one)


def compile_kernels(ahead_of_time: bool = True) -> bool:
    """Compile (or load from numba's cache) the just-in-time kernels (and the graph push of
    :func:`graph_push`) now and keep them for this process; with ``ahead_of_time``, also
    build the extension module of :mod:`.aot` when it is missing or stale (~30 s). ``make
    install`` runs it once, so that neither the first query of a new install nor any single
    query pays for compiling or importing numba. Returns False when numba cannot be used
    (the numpy path then serves every search)."""
    try:
        from . import _kernels

        _warm_up(_kernels)
    except Exception:  # ImportError, numba errors: the numpy path serves
        return False
    _jit_graph_push()  # (numba's cache then holds the push and the elastic kernel too)
    _jit_elastic()
    if ahead_of_time:
        from . import aot

        if aot.load() is None:
            try:
                aot.build()
            except Exception:  # no C compiler, numba.pycc gone: the JIT serves
                pass
    return True


@lru_cache(maxsize=32)
def folded_basis(K: int, n: int) -> tuple[np.ndarray, bool]:
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
