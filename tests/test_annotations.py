"""Every public function of the library annotated (issue 37), counted by the rule of
``benchmarks/code_measures.py`` (``public_functions``): a function at a public module's top
level or a method of a public class there (``__init__`` included), every parameter but
``self``/``cls`` and the return annotated. mypy checks what the annotations say
(pyproject.toml [tool.mypy]); this test checks that they are there."""

from __future__ import annotations

import os
import sys

from conftest import ROOT

sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
from code_measures import public_functions  # noqa: E402


def test_every_public_function_is_annotated():
    functions = public_functions(os.path.join(ROOT, "nfdmatch"))
    assert len(functions) > 400  # the rule finds the library's functions at all
    bare = [name for name, annotated in functions if not annotated]
    assert not bare, f"public functions without full annotations: {bare}"


def test_the_rule_of_the_count(tmp_path):
    """What counts as public and as fully annotated, on a small package."""
    package = tmp_path / "pkg"
    (package / "_private").mkdir(parents=True)
    (package / "__init__.py").write_text("def top(a: int) -> int: ...\n")
    (package / "_private" / "__init__.py").write_text("def hidden(a): ...\n")
    (package / "mod.py").write_text(
        "def full(a: int, *b: int, c: str = '', **d: float) -> None: ...\n"
        "def no_return(a: int): ...\n"
        "def bare_param(a, b: int) -> None: ...\n"
        "def _helper(a): ...\n"
        "class Thing:\n"
        "    def __init__(self, a: int) -> None: ...\n"
        "    def method(self, a: int) -> int: ...\n"
        "    @classmethod\n"
        "    def make(cls, a) -> 'Thing': ...\n"
        "    @staticmethod\n"
        "    def static(a: int) -> int: ...\n"
        "    @staticmethod\n"
        "    def static_bare(a) -> int: ...\n"
        "    def __repr__(self): ...\n"
        "    def _private(self, a): ...\n"
        "class _Hidden:\n"
        "    def method(self, a): ...\n"
        "def outer() -> None:\n"
        "    def inner(a): ...\n"
    )
    got = dict(public_functions(str(package)))
    assert got == {
        "pkg.top": True,
        "pkg.mod.full": True,
        "pkg.mod.no_return": False,
        "pkg.mod.bare_param": False,
        "pkg.mod.Thing.__init__": True,
        "pkg.mod.Thing.method": True,
        "pkg.mod.Thing.make": False,
        "pkg.mod.Thing.static": True,
        "pkg.mod.Thing.static_bare": False,
        "pkg.mod.outer": True,
    }
