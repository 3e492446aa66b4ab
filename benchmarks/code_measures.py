"""The shape of the code, as issue 21 counts it: long functions and modules, private names
imported across modules, imports inside functions, import circles between modules.

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


def main() -> None:
    package = sys.argv[1] if len(sys.argv) > 1 else os.path.join(ROOT, "nfdmatch")
    mods = modules(package)
    long_functions, long_modules, private, inner, edges = [], [], [], defaultdict(int), defaultdict(set)
    every_edge = defaultdict(set)  # with the imports inside functions
    for name, path in sorted(mods.items()):
        with open(path, encoding="utf-8") as f:
            source = f.read()
        tree = ast.parse(source)
        lines = len(source.splitlines())
        if lines > 500:
            long_modules.append((lines, name))
        is_package = path.endswith("__init__.py")
        for node in ast.walk(tree):
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
