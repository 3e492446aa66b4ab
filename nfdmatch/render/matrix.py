"""The picture of an all-pairs distance matrix (``nfdmatch matrix -o m.png``)."""

from __future__ import annotations

import math
import os
import time
from typing import Sequence

import numpy as np

from ..errors import ParameterError, RenderError, WriteError
from .layout import (
    NOTE_COLOR,
    MATRIX_LABEL_WIDTH,
    RenderResult,
    check_size,
    _reason,
    _write,
    check_output,
    picture_format,
    short_labels,
)
from .matplotlib_backend import new_figure, png_bytes

# --------------------------------------------------------------------------- matrix


def matrix_size(n: int) -> tuple[int, int]:
    """The default (width, height) in pixels of the picture of an n x n matrix."""
    side = int(np.clip(8 * n + 360, 800, 3000))
    return min(side + 120, 3000), side


def render_matrix(
    matrix: np.ndarray,
    labels: Sequence[str],
    path: str | os.PathLike[str],
    *,
    size: tuple[int, int] | None = None,
    title: str | None = None,
) -> RenderResult:
    """Draw an all-pairs distance matrix as a grey-level grid (the paper's Figure 7), with
    matplotlib: darker = smaller distance (black = 0, white = the largest), the curve names
    along both axes (shortened; every k-th one when there are too many to read), a colour bar.

    Parameters
    ----------
    matrix : (N, N) finite float, N = ``len(labels)``.
    labels : the N curve ids, in the matrix's order.
    path : the picture file to write: PNG, or SVG / PDF by the extension.
    size : (width, height) in pixels; default grows with N (about 8 px per row, 920x800 to
        3000x3000).
    title : drawn above the grid when given.

    Raises
    ------
    ParameterError : a matrix that is not square, not finite, or does not match the labels.
    WriteError : the file cannot be written.
    RenderError : matplotlib is not installed or failed.
    """
    try:
        m = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"matrix: expected an (N, N) array of numbers ({exc})") from None
    labels = [str(x) for x in labels]
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.shape[0] == 0:
        raise ParameterError(f"matrix: expected a square (N, N) array with N >= 1, got shape {m.shape}")
    if len(labels) != m.shape[0]:
        raise ParameterError(f"matrix: {m.shape[0]} rows but {len(labels)} labels")
    if not np.all(np.isfinite(m)):
        raise ParameterError("matrix: contains NaN or infinite distances")
    size = matrix_size(m.shape[0]) if size is None else check_size(size)
    out = check_output(path)
    t0 = time.perf_counter()
    try:
        data = _draw_matrix(m, labels, size, title, picture_format(out))
    except (WriteError, ParameterError):
        raise
    except Exception as exc:
        raise RenderError(f"matplotlib could not draw the matrix ({_reason(exc)})", path=out) from exc
    _write(out, data)
    return RenderResult(path=out, renderer="matplotlib", seconds=time.perf_counter() - t0)


def _draw_matrix(m: np.ndarray, labels: list[str], size, title, fmt: str = "png") -> bytes:
    from matplotlib.ticker import FixedLocator, NullLocator

    n = m.shape[0]
    W, H = size
    names = short_labels(labels, MATRIX_LABEL_WIDTH)
    longest = max(len(s) for s in names)
    # font: the tick spacing (the cell) must hold a line of text; below 6 pt label every k-th
    grid_px = min(W - 160, H - 60) * 0.8 - 0.6 * longest * 7
    cell = max(grid_px, 50) / n
    font = min(10.0, cell / 1.7)
    every = 1
    if font < 6.0:
        every = math.ceil(6.0 * 1.7 / cell)
        font = min(9.0, every * cell / 1.7)
    fig = new_figure(size, layout="constrained")
    ax = fig.add_subplot()
    lo = min(0.0, float(m.min()))
    hi = float(m.max())
    image = ax.imshow(
        m, cmap="gray", vmin=lo, vmax=hi if hi > lo else lo + 1.0, interpolation="nearest", aspect="equal"
    )
    ticks = np.arange(0, n, every)
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(FixedLocator(ticks))
    ax.set_xticklabels([names[i] for i in ticks], rotation=90, fontsize=font)
    ax.set_yticklabels([names[i] for i in ticks], fontsize=font)
    ax.tick_params(length=2 if n > 40 else 3, pad=2)
    if n <= 60:
        ax.set_xticks(np.arange(-0.5, n, 1), minor=True)
        ax.set_yticks(np.arange(-0.5, n, 1), minor=True)
        ax.grid(which="minor", color="white", linewidth=0.6 if n > 20 else 1.0)
        ax.tick_params(which="minor", length=0)
    else:
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_minor_locator(NullLocator())
    for spine in ax.spines.values():  # a frame, so the palest (farthest) cells show
        spine.set_color("#808080")
        spine.set_linewidth(0.8)
    if title:
        ax.set_title(title, fontsize=12)
    bar = fig.colorbar(image, ax=ax, shrink=0.8, pad=0.02, fraction=0.05)
    bar.set_label("distance (darker = more similar)", fontsize=10)
    bar.ax.tick_params(labelsize=9)
    if every > 1:
        fig.text(0.995, 0.005, f"one label in {every} shown", ha="right", va="bottom", fontsize=8, color=NOTE_COLOR)
    return png_bytes(fig, fmt)
