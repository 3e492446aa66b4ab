"""The exact-search kernels, and the graph push, compiled ahead of time: a plain extension
module that imports in a millisecond, without numba.

The kernels of :mod:`._kernels` (and the push of :mod:`._graph_kernels` and
:mod:`._push_rounds`) are numba code. Compiled just in time they cost a process ~0.45 s
before the first row (importing numba and loading the cached machine code), more than a
whole single query needs. ``make install`` (through :func:`compile_kernels`) also compiles
the entry points ahead of time with ``numba.pycc`` into ``nfdmatch/matching/_kernels_aot*.so``,
next to a stamp holding the digest of the kernel sources it was built from; :func:`load`
returns it only when the stamp matches the sources (an edited ``_kernels.py``,
``_graph_kernels.py``, ``_push_rounds.py`` or ``common.py`` is never served by a stale
build). Without it a process uses the just-in-time kernels, or numpy
(:mod:`.kernels`: the rule).

The compiled functions release the GIL, as the just-in-time ones do, so queries on threads
and a call's rows split over threads (:func:`._threads.split_rows`) run in parallel without
importing numba. ``numba.pycc`` has no ``nogil`` option (numba issue #6382): its module
compiler builds every export with a fresh ``Flags()``, and :func:`_releasing_gil` hands it
flags with ``release_gil`` set while the module compiles. Should a numba version refuse
that, the module is built holding the GIL, the stamp says so, and a search on these kernels
answers on one thread (:mod:`.kernels`).
"""

from __future__ import annotations

from typing import Any

import importlib
import importlib.util
import os
import sys
from contextlib import contextmanager

import numpy as np

from ._threads import exact_rows, grid_bound_rows

__all__ = ["MODULE", "build", "load", "load_checked", "module_digest", "source_digest", "unused_reason"]

#: the extension module's name (in this package)
MODULE = "_kernels_aot"
_HERE = os.path.dirname(os.path.abspath(__file__))
_STAMP = os.path.join(_HERE, MODULE + ".stamp")

#: the exported signatures: the arrays' layouts are the ones exact.py passes
_EXACT_SIGNATURE = (
    "void(c16[:,::1], c16[:,::1], f8[::1], c16[:,:,::1], i8, f8[:,::1], b1, i8, b1, i8, b1, f8, b1, "
    "f8[::1], f8[::1], f8[:,:,::1], b1[::1], b1[::1], i8, i8)"
)
_BOUND_SIGNATURE = "void(c16[:,::1], c16[:,:,::1], i8, f8[:,::1], i8, b1, f8[::1], f8[::1], f8[::1], f8[::1], i8, i8)"
#: the grid bound's versions: specialised for the truncated stages' K' (4, 8), and any K'
_BOUND_HARMONICS = (0, 4, 8)
#: the personalised-PageRank push of _graph_kernels.py: its state in and out (arrays the walk
#: makes contiguous), the walk's rows, its work array, alpha and the tolerance
_PUSH_SIGNATURE = (
    "Tuple((i8[::1], i8[::1], i8[::1], f8[::1], i8[::1], i8[::1], f8[::1], i8[::1]))"
    "(i8[::1], i8[::1], i8[::1], i8[::1], f8[::1], i8[::1], i8[::1], f8[::1], i8[:,::1], f8[:,::1], b1[::1], "
    "i8[::1], f8, f8)"
)
#: the sources compiled into the module (and common.py, whose gram_entries _kernels.py compiles)
_SOURCES = ("_kernels.py", "_graph_kernels.py", "_push_rounds.py", "_elastic_kernels.py", "common.py", "aot.py")
#: the elastic distance of _elastic_kernels.py: the query, the posed rows, the shifts as
#: fractions, the offsets, samples, band, the oriented-area share and the distances out
_ELASTIC_SIGNATURE = "void(c16[:,::1], c16[:,:,::1], f8[::1], i8[::1], i8, i8, f8, f8[::1])"


def source_digest() -> str:
    """What a build is for: the CRC-32 and length of the kernel sources (``_kernels.py``,
    ``_graph_kernels.py``, ``_push_rounds.py``), of ``common.py`` (whose ``gram_entries`` the kernels compile) and
    of this module, and the Python version (the built module needs neither numba nor its
    version once compiled). It guards against a stale build after an edit, not against
    tampering; every query checks it, and ``hashlib`` alone costs a process ~6 ms to import
    (OpenSSL)."""
    import zlib

    parts = []
    for name in _SOURCES:
        with open(os.path.join(_HERE, name), "rb") as f:
            data = f.read()
        parts.append(f"{zlib.crc32(data):08x}{len(data):x}")
    parts.append(f"{zlib.crc32(sys.version.encode()):08x}")
    return "-".join(parts)


# The stamp also holds the built module's own digest (its third line), checked before every
# load: a module damaged or replaced since its build is never loaded (load_checked), and the
# CLI says why in one line (unused_reason).


def module_digest(path: str) -> str:
    """The built extension module's own digest: CRC-32 and length of its bytes (~1 ms for
    its ~1 MB). Recorded in the stamp at build time and checked before every load: a module
    truncated, damaged or replaced since would crash the process that loads it (SIGBUS,
    SIGSEGV, SIGILL), which no exception handler can catch."""
    import zlib

    crc, size = 0, 0
    with open(path, "rb") as f:
        while True:
            block = f.read(1 << 20)
            if not block:
                break
            crc = zlib.crc32(block, crc)
            size += len(block)
    return f"{crc:08x}{size:x}"


def _module_path(folder: str) -> str | None:
    """The extension module's file in ``folder`` (its platform suffix), or None."""
    from importlib.machinery import EXTENSION_SUFFIXES

    for suffix in EXTENSION_SUFFIXES:
        path = os.path.join(folder, MODULE + suffix)
        if os.path.isfile(path):
            return path
    return None


def build(output_dir: str | None = None) -> str:
    """Compile the kernels ahead of time into ``output_dir`` (default: this package's folder)
    and write the stamp; returns the extension's path. Takes ~30 s; needs numba and a C
    compiler (numba.pycc links with the platform's compiler through distutils/setuptools).
    Raises whatever numba raises when it cannot."""
    import warnings

    out = output_dir or _HERE
    digest = source_digest()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba.pycc announces its deprecation
        try:
            with _releasing_gil():
                cc = _module_compiler(out)
                cc.compile()
            gil = _NOGIL
        except Exception:  # a numba whose module compiler refuses the flag: hold the GIL
            cc = _module_compiler(out)
            cc.compile()
            gil = _GIL
    built = os.path.join(out, cc.output_file)
    stamp = os.path.join(out, MODULE + ".stamp")
    with open(stamp + ".part", "w") as f:
        f.write(f"{digest}\n{gil}\n{module_digest(built)}\n")
    os.replace(stamp + ".part", stamp)
    return built


def _module_compiler(out: str):
    """numba.pycc's compiler of the extension module into ``out``, every kernel exported."""
    from numba.pycc import CC

    from . import _elastic_kernels as e
    from . import _graph_kernels as g
    from . import _kernels as k

    cc = CC(MODULE)
    cc.output_dir = out
    cc.verbose = False
    # built on the machine that runs it (make install): use its instruction set, as the
    # just-in-time kernels do
    cc.target_cpu = "host"

    cc.export("exact_rows", _EXACT_SIGNATURE)(_forwarding(k._exact_rows))
    for harmonics in _BOUND_HARMONICS:
        cc.export(f"grid_bound_rows_{harmonics}", _BOUND_SIGNATURE)(_forwarding(k.grid_bound_kernel(harmonics)))
    cc.export("push_sources", _PUSH_SIGNATURE)(_forwarding(g.push_sources, returns=True))
    cc.export("elastic_rows", _ELASTIC_SIGNATURE)(_forwarding(e.elastic_rows))
    return cc


def _forwarding(kernel, returns: bool = False):
    """A plain function that calls ``kernel`` (a numba dispatcher) with the kernel's own
    parameters (and, with ``returns``, returns what it returns), for ``numba.pycc`` to
    export: it compiles Python functions, not dispatchers, and the kernel then compiles as
    the callee with its own options (error model, inlining)."""
    import inspect

    names = ", ".join(inspect.signature(kernel.py_func).parameters)
    scope = {"kernel": kernel, "__name__": __name__}
    exec(f"def forward({names}):\n    {'return ' if returns else ''}kernel({names})\n", scope)
    return scope["forward"]


#: the stamp's second line: whether the module's functions release the GIL
_NOGIL, _GIL = "nogil", "gil"


@contextmanager
def _releasing_gil():
    """While compiling, every function ``numba.pycc`` exports releases the GIL: its module
    compiler creates the compile flags with ``Flags()`` (numba.pycc.compiler, numba 0.5x-0.6x);
    this swaps in a subclass that sets ``release_gil``, as ``@njit(nogil=True)`` does."""
    from numba.pycc import compiler

    base = compiler.Flags

    class Flags(base):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True

    compiler.Flags = Flags
    try:
        yield
    finally:
        compiler.Flags = base


class _Kernels:
    """The compiled module behind the interface of :mod:`._kernels` (``exact_rows``,
    ``grid_bound_rows``), of :mod:`._graph_kernels` (``push_sources``) and of
    :mod:`._elastic_kernels` (``elastic_rows``); ``threads``: its
    functions release the GIL, and ``workers`` then splits a call's rows over threads (else
    it is ignored)."""

    def __init__(self, module, threads: bool):
        self._module = module
        self.threads = threads
        self.push_sources = module.push_sources
        self.elastic_rows = module.elastic_rows

    def _workers(self, workers: int) -> int:
        return workers if self.threads else 1

    def exact_rows(self, A, Aw, w, B, D, basis, quarter, n, mirror, C, refine, refine_limit, workers=1, prune=True):
        kernel = self._module.exact_rows
        basis, workers = _writable(basis, n), self._workers(workers)
        return exact_rows(kernel, A, Aw, w, B, D, basis, quarter, n, mirror, C, refine, refine_limit, workers, prune)

    def grid_bound_rows(self, Aw, B, D, basis, ratio, mirror, slack_coarse, slack_fine, need, workers=1):
        K = Aw.shape[0]
        kernel = getattr(self._module, f"grid_bound_rows_{K if K in _BOUND_HARMONICS else 0}")
        workers = self._workers(workers)
        return grid_bound_rows(kernel, Aw, B, D, basis, ratio, mirror, slack_coarse, slack_fine, need, workers)


_writable_cache: dict[tuple, np.ndarray] = {}


def _writable(basis: np.ndarray, n: int) -> np.ndarray:
    """The compiled signatures take writable arrays; the shared bases (one per K and n,
    :func:`.kernels.folded_basis`) are read-only: a writable copy of each, kept."""
    if basis.flags.writeable:
        return basis
    key = (basis.shape, int(n))
    got = _writable_cache.get(key)
    if got is None:
        got = _writable_cache[key] = basis.copy()
    return got


#: why the last :func:`load` in this process returned None although a build is present (the
#: module does not match its stamp), for the CLI to say once; None when nothing to say
_unused: list = [None]


def unused_reason() -> str | None:
    """Why this process does not use the ahead-of-time kernels although a build of them is
    present (a module damaged or replaced since it was built, so not loaded), or None. One
    line, for the CLI to print on stderr (the library does not print); a missing or stale
    build (an edited kernel source) is not reported: that is what ``make install`` fixes
    silently, and the other kernels serve meanwhile."""
    return _unused[0]


def load_checked(folder: str | None = None, stamp_path: str | None = None) -> tuple[Any, str | None]:
    """``(kernels, reason)``: the compiled kernels when a build for the current source is
    present and the module file is the one that build wrote (its digest, :func:`module_digest`,
    equal to the stamp's), else ``(None, reason)``; ``reason`` is None when there is simply
    no usable build (none, or one for another source), else one line saying what is wrong
    with the module (truncated, damaged, replaced: loading it could crash the process). The
    module is checked before it is loaded, never loaded when the check fails."""
    folder = folder or _HERE
    stamp_path = stamp_path or _STAMP
    try:
        with open(stamp_path) as f:
            stamp = f.read().split()
    except OSError:
        return None, None
    try:
        if not stamp or stamp[0] != source_digest():
            return None, None
    except OSError:
        return None, None
    path = _module_path(folder)
    if path is None:
        return None, None
    shown = os.path.relpath(path) if not os.path.relpath(path).startswith("..") else path
    recorded = stamp[2] if len(stamp) > 2 else None
    try:
        actual = module_digest(path)
    except OSError as exc:
        return None, f"compiled kernels not used: cannot read {shown} ({exc.strerror or exc}); using the other kernels"
    if recorded is None:
        return None, (
            f"compiled kernels not used: {shown} has no recorded digest (built before they were "
            "checked); using the other kernels (`make install` rebuilds it)"
        )
    if actual != recorded:
        return None, (
            f"compiled kernels not used: {shown} does not match its build stamp (damaged or "
            "replaced since it was built); using the other kernels (`make install` rebuilds it)"
        )
    try:
        if folder == _HERE:
            module = importlib.import_module(f"{__package__}.{MODULE}")
        else:  # a build elsewhere (the tests check copies through this)
            spec = importlib.util.spec_from_file_location(MODULE, path)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
    except (ImportError, OSError) as exc:
        return None, f"compiled kernels not used: {shown} does not load ({exc}); using the other kernels"
    return _Kernels(module, threads=stamp[1:2] == [_NOGIL]), None


def load() -> Any:
    """The compiled kernels when a build for the current source is present and its module is
    intact (:func:`load_checked`), else None; why not, when something is wrong with the
    module, is then :func:`unused_reason`."""
    kernels, reason = load_checked()
    _unused[0] = reason
    return kernels
