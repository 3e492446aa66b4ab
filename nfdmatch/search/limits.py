"""How many matches a search may be asked for: one rule for the library and the CLI (whose
``--top`` and ``--max-distance`` call it), so that a value one refuses the other refuses.
Light: the CLI checks its options with it before any search module is imported."""

from __future__ import annotations

import math
import numbers

from ..errors import ParameterError

__all__ = ["check_limits"]


def check_limits(top: int | None = None, max_distance: float | None = None, *, top_name: str = "top") -> None:
    """Raise ParameterError unless ``top`` is None or an integer >= 1 and ``max_distance`` is
    None or a number >= 0 (``inf``: no limit; NaN refused: it would compare false with
    every distance, and a search would quietly answer nothing)."""
    if top is not None and (isinstance(top, bool) or not isinstance(top, numbers.Integral) or top < 1):
        raise ParameterError(f"{top_name} must be an integer >= 1, got {top!r}")
    if max_distance is not None:
        ok = isinstance(max_distance, numbers.Real) and not isinstance(max_distance, bool)
        if not ok or math.isnan(max_distance) or max_distance < 0:
            raise ParameterError(f"max_distance must be a number >= 0 (inf: no limit), got {max_distance!r}")
