"""``pip install .`` builds the ahead-of-time kernels as ``make install`` does (issue 25,
item 18): setup.py's build step, its build dependencies, and the one line it says when it
cannot build them (no C compiler)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import pytest

from conftest import ROOT


def _setup_module():
    spec = importlib.util.spec_from_file_location("nfdmatch_setup", os.path.join(ROOT, "setup.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # not as __main__: setup() is not called
    return module


def test_the_build_dependencies_are_declared():
    import re

    text = open(os.path.join(ROOT, "pyproject.toml"), encoding="utf-8").read()  # (tomllib: Python 3.11+)
    section = text.split("[build-system]", 1)[1].split("\n[", 1)[0]
    requires = re.search(r"^requires = \[(.*)\]$", section, re.M).group(1)
    names = set(re.findall(r'"([A-Za-z0-9_.-]+)', requires))
    assert {"setuptools", "numba", "numpy"} <= names


def test_without_a_compiler_the_build_goes_on_and_says_so_in_one_line(tmp_path, capsys):
    setup = _setup_module()

    class NoCompiler:
        @staticmethod
        def build(output_dir):
            raise RuntimeError("error: command 'gcc' failed: No such file or directory\nmore detail")

    setup._aot_module = lambda: NoCompiler
    assert setup.build_kernels(str(tmp_path)) is None
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("nfdmatch: the ahead-of-time kernels were not built (no C compiler?")
    assert "'gcc' failed" in line and "just in time" in line


def test_the_build_step_targets_the_built_package(tmp_path, capsys):
    setup = _setup_module()
    seen = []

    class Builds:
        @staticmethod
        def build(output_dir):
            seen.append(output_dir)
            return os.path.join(output_dir, "_kernels_aot.cpython-test.so")

    setup._aot_module = lambda: Builds
    assert setup.build_kernels(str(tmp_path)).endswith("_kernels_aot.cpython-test.so")
    assert seen == [os.path.join(str(tmp_path), "nfdmatch", "matching")]
    assert capsys.readouterr().err == "nfdmatch: built the ahead-of-time kernels: _kernels_aot.cpython-test.so\n"


@pytest.mark.slow
def test_the_build_step_compiles_kernels_that_the_built_package_loads_without_numba(tmp_path):
    """The real build step (setup.py's, with this environment's numba and C compiler) on a
    copy of the package, as build_py leaves it: the built package holds the module and its
    stamp, and loading it from there needs no numba."""
    import shutil

    build_lib = tmp_path / "lib"
    shutil.copytree(
        os.path.join(ROOT, "nfdmatch"),
        build_lib / "nfdmatch",
        ignore=shutil.ignore_patterns("__pycache__", "_kernels_aot*"),
    )
    built = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; sys.argv = ['setup.py']; import runpy; "
            f"m = runpy.run_path({os.path.join(ROOT, 'setup.py')!r}); "
            f"sys.exit(m['build_kernels']({str(build_lib)!r}) is None)",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert built.returncode == 0, built.stderr
    assert "nfdmatch: built the ahead-of-time kernels" in built.stderr
    matching = build_lib / "nfdmatch" / "matching"
    assert any(n.startswith("_kernels_aot") and n.endswith(".so") for n in os.listdir(matching))
    probe = (
        "import sys; from nfdmatch.matching import aot; "
        "assert aot.load() is not None; assert 'numba' not in sys.modules; print(aot.__file__)"
    )
    env = {**os.environ, "PYTHONPATH": str(build_lib)}
    loaded = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert loaded.returncode == 0, loaded.stderr
    assert loaded.stdout.strip() == str(matching / "aot.py")
