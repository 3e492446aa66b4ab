"""The shape of the code, as issue 21 counts it: long functions and modules, private names
imported across modules, imports inside functions, import circles between modules; and, as
issue 37 counts it, the public functions fully annotated (``public_functions``: the rule).

    python benchmarks/code_measures.py [PACKAGE_DIR]

Counts lines of code by the AST (a function's first to last line, docstring included).
"""

from __future__ import annotations

import ast
import os
import sys
from collections import defaultdict

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def modules(package: str) -> dict[str, str]:
    """dotted name -> file path of every module under ``package``."""
    out = {}
    base = os.path.dirname(package)
    for folder, _, files in os.walk(package):
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                dotted = os.path.relpath(path, base)[:-3].replace(os.sep, ".")
                out[dotted.removesuffix(".__init__")] = path
    return out


def resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    parts = module.split(".")
    if not is_package:
        parts = parts[:-1]
    parts = parts[: len(parts) - (node.level - 1)]
    return ".".join(parts + ([node.module] if node.module else []))


def public_module(dotted: str) -> bool:
    """A module is public when no part of its dotted name starts with ``_`` (a package's
    ``__init__.py`` is the package itself: ``nfdmatch.formats``, not ``nfdmatch.formats.__init__``)."""
    return not any(part.startswith("_") for part in dotted.split("."))


def _fully_annotated(node: ast.FunctionDef | ast.AsyncFunctionDef, method: bool) -> bool:
    args = node.args
    params = [*args.posonlyargs, *args.args]
    static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in node.decorator_list)
    if method and not static and params:
        params = params[1:]  # self or cls
    params += [*args.kwonlyargs, *(a for a in (args.vararg, args.kwarg) if a is not None)]
    return node.returns is not None and all(p.annotation is not None for p in params)


def public_functions(package: str) -> list[tuple[str, bool]]:
    """``(dotted name, fully annotated)`` of every public function under ``package``.

    Public: in a public module (``public_module``), a function defined at the module's top
    level or a method of a class defined there (classes in classes too), neither the function
    nor any enclosing class named with a leading ``_``; a class's ``__init__`` counts (it is the
    signature of calling the class), other dunder methods and functions inside functions do
    not. Fully annotated: every parameter has an annotation (but a method's first, ``self`` or
    ``cls``, unless it is a ``staticmethod``), and so has the return.
    """
    out = []

    def visit(body: list[ast.stmt], prefix: str, in_class: bool) -> None:
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if not node.name.startswith("_") or (in_class and node.name == "__init__"):
                    out.append((f"{prefix}.{node.name}", _fully_annotated(node, in_class)))
            elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                visit(node.body, f"{prefix}.{node.name}", True)

    for name, path in sorted(modules(package).items()):
        if public_module(name):
            with open(path, encoding="utf-8") as f:
                visit(ast.parse(f.read()).body, name, False)
    return out


def _is_type_checking(test: ast.expr) -> bool:
    """``TYPE_CHECKING`` or ``typing.TYPE_CHECKING``."""
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def main() -> None:
    package = sys.argv[1] if len(sys.argv) > 1 else os.path.join(ROOT, "nfdmatch")
    mods = modules(package)
    long_functions, long_modules, private, inner, edges = [], [], [], defaultdict(int), defaultdict(set)
    every_edge = defaultdict(set)  # with the imports inside functions
    type_checking_imports = 0
    for name, path in sorted(mods.items()):
        with open(path, encoding="utf-8") as f:
            source = f.read()
        tree = ast.parse(source)
        lines = len(source.splitlines())
        if lines > 500:
            long_modules.append((lines, name))
        is_package = path.endswith("__init__.py")
        # imports under `if TYPE_CHECKING:` are never run (the names of annotations, for the
        # type checker): neither circles nor imports inside functions; counted apart
        typing_only = {
            id(sub)
            for node in ast.walk(tree)
            if isinstance(node, ast.If) and _is_type_checking(node.test)
            for stmt in node.body
            for sub in ast.walk(stmt)
        }
        type_checking_imports += sum(
            isinstance(node, ast.ImportFrom) and id(node) in typing_only for node in ast.walk(tree)
        )
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > 80:
                    long_functions.append((length, f"{name}.{node.name}"))
            if isinstance(node, ast.ImportFrom):
                target = resolve(name, is_package, node)
                if not target.startswith("nfdmatch"):
                    continue
                top_level = node.col_offset == 0
                if not top_level:
                    inner[name] += 1
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    dest = sub if sub in mods else target
                    if dest != name:
                        every_edge[name].add(dest)
                        if top_level:
                            edges[name].add(dest)
                    if alias.name.startswith("_") and not alias.name.startswith("__") and sub not in mods:
                        if target != name:
                            private.append((name, f"{target}.{alias.name}"))
    circles = _circles(edges)
    held = [c for c in _circles(every_edge) if all(m.startswith("nfdmatch.index") for m in c)]
    print(f"| functions over 80 lines | {len(long_functions)} (over 150: {sum(n > 150 for n, _ in long_functions)}) |")
    for n, f in sorted(long_functions, reverse=True)[:12]:
        print(f"|   {f} | {n} |")
    print(f"| modules over 500 lines | {len(long_modules)} |")
    for n, m in sorted(long_modules, reverse=True):
        print(f"|   {m} | {n} |")
    print(f"| private names imported across modules | {len(private)} |")
    print(
        f"| imports inside functions (nfdmatch.index) | {sum(v for k, v in inner.items() if k.startswith('nfdmatch.index'))} |"
    )
    print(f"| import circles (top-level imports) | {len(circles)} {circles[:3]} |")
    print(f"| import circles in nfdmatch.index, imports inside functions counted | {len(held)} {held[:3]} |")
    # an import moved into a function hides a circle from the line above, it does not remove it
    every = _circles(every_edge)
    print(f"| import circles, every import counted (also inside functions) | {len(every)} {every[:3]} |")
    print(
        f"| imports for the type checker only (under if TYPE_CHECKING, not counted above) | {type_checking_imports} |"
    )
    functions = public_functions(package)
    bare = [name for name, annotated in functions if not annotated]
    print(f"| public functions fully annotated | {len(functions) - len(bare)} of {len(functions)} |")
    for name in bare[:12]:
        print(f"|   not: {name} | |")


def _circles(edges: dict) -> list:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in list(edges):
        if v not in index:
            visit(v)
    return out


if __name__ == "__main__":
    main()
