"""The command-line interface: parses arguments, calls the library, formats the results.

The only package that imports click and rich. One module per command group, and
``common`` for what they share (output formats, input format, matching options, the
exit-code policy). Importing it must stay cheap: renderers, mesh and HDF5 libraries are
imported inside the commands that need them.
"""

from __future__ import annotations

from . import curves, extract_cmd, index_cmds, join_cmds, pictures  # noqa: F401  (register the commands)
from .group import main

__all__ = ["main"]
