"""The layout of ``/search`` (docs/index-format.md): its datasets, their dtypes and shapes,
and the check of a file's group against them."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import h5py
    from collections.abc import Callable

__all__ = ["SEARCH_DATASETS", "NUMBER_KINDS", "check_search_group", "not_numbers"]

#: the kinds of stored type a reader converts to the numbers the format stores (bool,
#: integers, floats, complex, of any width or byte order: ``index verify`` names a type that
#: differs from the format's); strings, compounds and opaque bytes are not numbers
NUMBER_KINDS = "biufc"


def not_numbers(ds: Any, where: str) -> str | None:
    """Why dataset ``ds`` (at ``where``), where the format stores numbers, holds none (a string
    type: a reader would parse its text, and fail on text that is not a number), or None."""
    kind = ds.dtype.kind
    if kind in NUMBER_KINDS:
        return None
    what = "strings" if kind in "OSU" else f"values of type {ds.dtype}"
    return f"{where} holds {what}, not numbers"


#: /search datasets: name -> (dtype, shape as a function of N rows, C cells, D feature columns)
SEARCH_DATASETS = {
    "row": (np.int64, lambda N, C, D: (N,)),
    "cell_start": (np.int64, lambda N, C, D: (C + 1,)),
    "centre": (np.float64, lambda N, C, D: (C, D)),
    "radius": (np.float64, lambda N, C, D: (C, 2)),
    "features": (np.float32, lambda N, C, D: (N, D)),
    "sqnorm": (np.float64, lambda N, C, D: (N, 2)),
}


def check_search_group(h5: h5py.File, N: int, harmonics: int, get: Callable[[str], Any] | None = None) -> str | None:
    """Why the file's ``/search`` group is not valid for N rows and K harmonics, or None.

    ``get(name)`` returns dataset ``/search/NAME`` after checking how it is stored (raising
    the reader's error otherwise); by default, plain lookup."""
    g = h5.get("search")
    if g is None or not hasattr(g, "keys"):
        return "missing group /search"
    if get is None:
        get = g.get
    D = 2 * harmonics + 3
    start = get("cell_start")
    if start is None or len(start.shape) != 1 or start.shape[0] < 1:
        return "missing or bad dataset /search/cell_start"
    C = start.shape[0] - 1
    cells = g.attrs.get("cells")
    if cells is not None and (not isinstance(cells, (int, np.integer)) or int(cells) != C):
        return f"/search attribute cells {cells!r} does not match /search/cell_start ({C} cells)"
    for name, (_dtype, shape) in SEARCH_DATASETS.items():
        ds = get(name)
        if ds is None or not hasattr(ds, "shape"):
            return f"missing dataset /search/{name}"
        if tuple(ds.shape) != shape(N, C, D):
            return f"/search/{name} has shape {ds.shape}, expected {shape(N, C, D)}"
        problem = not_numbers(ds, f"/search/{name}")
        if problem:
            return problem
    coefficients = get("coefficients")
    want = (N, harmonics, 3)
    if (
        coefficients is None
        or not hasattr(coefficients, "shape")
        or tuple(coefficients.shape) != want
        or coefficients.dtype.kind != "c"
    ):
        return f"missing or bad dataset /search/coefficients (expected complex, shape {want})"
    starts = np.asarray(start[...], dtype=np.int64)
    if starts[0] != 0 or starts[-1] != N or (np.diff(starts) < 0).any():
        return "/search/cell_start does not run from 0 to the row count without decreasing"
    return None
