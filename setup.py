"""The package build's one step beyond pyproject.toml: the ahead-of-time kernels.

``pip install .`` (and ``pipx install .``) compiles the exact-search kernels ahead of time
into the package, as ``make install`` does (the same compiler: ``nfdmatch.matching.aot``,
numba.pycc and the platform's C compiler), so that the first query of a pip install
neither compiles nor imports numba. Without a C compiler (or numba.pycc) the build goes
on without them and says so in one line: searches then use numba's just-in-time
kernels (compiled on first use), as before. ``NFDMATCH_NO_AOT=1`` skips the step.

An editable install (``pip install -e .``, what ``make install`` runs) skips it too:
``make`` builds the kernels in the source tree itself (its ``$(KERNELS)`` rule).

The kernels are built for the machine that builds them (``target_cpu = "host"``): a wheel
made here is for this machine, not for distribution.
"""

from __future__ import annotations

import importlib.util
import os
import sys

from setuptools import Distribution, setup
from setuptools.command.build_py import build_py

_HERE = os.path.dirname(os.path.abspath(__file__))


def _aot_module():
    """``nfdmatch/matching/aot.py`` of this source tree, loaded as
    ``nfdmatch.matching.aot`` without importing the package (whose runtime dependencies
    the build environment need not have)."""
    import types

    for name, path in (("nfdmatch", "nfdmatch"), ("nfdmatch.matching", "nfdmatch/matching")):
        if name not in sys.modules:
            package = types.ModuleType(name)
            package.__path__ = [os.path.join(_HERE, path)]
            sys.modules[name] = package
    spec = importlib.util.spec_from_file_location(
        "nfdmatch.matching.aot", os.path.join(_HERE, "nfdmatch", "matching", "aot.py")
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _say(message: str) -> None:
    print(f"nfdmatch: {message}", file=sys.stderr, flush=True)


def build_kernels(build_lib: str) -> str | None:
    """Compile the kernels into ``build_lib``'s package; the built file, or None (and one
    line on stderr) when they cannot be built here."""
    target = os.path.join(build_lib, "nfdmatch", "matching")
    try:
        built = _aot_module().build(output_dir=target)
    except Exception as exc:  # no C compiler, numba.pycc missing or refusing
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        _say(
            f"the ahead-of-time kernels were not built (no C compiler? {type(exc).__name__}: {first}); "
            "searches compile them just in time on first use instead (a slower first run)"
        )
        return None
    _say(f"built the ahead-of-time kernels: {os.path.basename(built)}")
    return built


class build_py_with_kernels(build_py):
    """build_py, then the ahead-of-time kernels into the built package."""

    def run(self):
        super().run()
        if not getattr(self, "editable_mode", False) and not os.environ.get("NFDMATCH_NO_AOT"):
            build_kernels(self.build_lib)


class BinaryDistribution(Distribution):
    """The package holds a compiled module: its wheel is for this platform."""

    def has_ext_modules(self):
        return not os.environ.get("NFDMATCH_NO_AOT")


if __name__ == "__main__":  # as setuptools' build backend runs it (tests import it)
    setup(cmdclass={"build_py": build_py_with_kernels}, distclass=BinaryDistribution)
