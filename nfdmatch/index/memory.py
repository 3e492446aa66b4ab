"""Curves in memory that can be written as an index file: the public
:class:`nfdmatch.MemoryIndex` (the search side's :class:`nfdmatch.search.MemoryIndex` and a
``save``; here because only ``index/`` writes index files)."""

from __future__ import annotations

import os

from ..search.memory import MemoryIndex as _SearchMemoryIndex
from .build import BuildReport, build_index

__all__ = ["MemoryIndex"]


class MemoryIndex(_SearchMemoryIndex):
    __doc__ = _SearchMemoryIndex.__doc__

    def save(self, path: str | os.PathLike[str], *, curves_file: str | os.PathLike[str] | None = None) -> BuildReport:
        """Write the curves as an index file at ``path``, with this index's samples,
        harmonics and scale: the CLI (``query``, ``show``, ``report``) and
        :func:`nfdmatch.open_index` read it with the same answers, row i being row i here.
        The curves go first into one OBJ file beside it (``curves_file``, default: the
        path with ``.curves.obj``), the index's source; an index already at ``path`` is
        replaced. Returns the build's :class:`~nfdmatch.index.BuildReport`."""
        return build_index(
            self.curves, path, samples=self.samples, harmonics=self.harmonics, scale=self.scale_mode,
            jobs=1, allow_shrink=True, curves_file=curves_file,
        )  # fmt: skip
