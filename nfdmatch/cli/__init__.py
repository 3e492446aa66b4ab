"""The command-line interface: parses arguments, calls the library, formats the results.

The only package that imports click and rich. One module per command group, and
``options`` (the group, shared options, messages, the exit-code policy), ``inputs``
(reading inputs) and ``output`` (row formats, ``-o``, tables) for what they share;
``start`` is the program's entry (the watchdog process and the signal handling that
precede every import but the standard library's).
Importing it must stay cheap: renderers, mesh and HDF5 libraries are imported inside
the commands that need them; ``main`` (the click group with every command registered) is
loaded on first use, so that ``start`` runs before click and numpy are imported.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import click

__all__ = ["main"]


def __getattr__(name: str) -> click.Group:
    if name == "main":
        from . import curves, export_cmd, extract_cmd, help_cmds, index_cmds, join_cmds, pictures, query_cmd, report_cmd  # noqa: F401  (register the commands)
        from .group import main

        globals()["main"] = main
        return main
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
