"""The command-line interface: parses arguments, calls the library, formats the results.

The only package that imports click and rich. One module per command group, and
``options`` (the group, shared options, messages, the exit-code policy), ``inputs``
(reading inputs) and ``output`` (row formats, ``-o``, tables) for what they share.
Importing it must stay cheap: renderers, mesh and HDF5 libraries are imported inside
the commands that need them.
"""

from __future__ import annotations

from . import curves, export_cmd, extract_cmd, help_cmds, index_cmds, join_cmds, pictures, query_cmd  # noqa: F401  (register the commands)
from .group import main

__all__ = ["main"]
