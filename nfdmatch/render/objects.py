"""The picture of a mesh query (``nfdmatch show MESH --index parts.h5``): the query's
contours beside each best object's matched contours, drawn with matplotlib.

Layout: a grid of equal panels (the grid that draws the contours largest), first the query's
contours alone, then one panel per answer: the query's contours thin and grey underneath,
the answer's matched contours in a strong colour on top. Every object arrives in its
principal frame (:mod:`nfdmatch.show_objects`), so one view serves every panel: the first
principal axis upright, the view turned 30 degrees about it and tilted 20 degrees from
above, so that sections across each of the three axes read as loops; farther contours are
lighter. The same limits in every panel, equal aspect.
"""

from __future__ import annotations

import math
import os
import time
from typing import Any, Sequence

import numpy as np

from ..errors import ParameterError, RenderError, WriteError
from .layout import (
    MATCH_COLOR,
    NOTE_COLOR,
    QUERY_COLOR,
    TEXT_COLOR,
    UNDER_COLOR,
    RenderResult,
    _reason,
    _write,
    check_output,
    check_renderer,
    check_size,
    choose_grid,
    picture_format,
    short_labels,
)
from .matplotlib_backend import _fit_texts, new_figure, png_bytes

__all__ = ["render_objects", "object_view"]

_TURN = math.radians(30.0)  # about the first principal axis
_TILT = math.radians(20.0)  # from above


def object_view(points: np.ndarray) -> np.ndarray:
    """Points of a principal frame (x: first axis) in view coordinates: x right, y up (the
    first axis, tilted), z towards the viewer."""
    p = np.asarray(points, dtype=np.float64)
    ct, st, cu, su = math.cos(_TURN), math.sin(_TURN), math.cos(_TILT), math.sin(_TILT)
    across = ct * p[:, 1] + st * p[:, 2]  # the second and third axes turned about the first
    depth = -st * p[:, 1] + ct * p[:, 2]
    return np.column_stack([across, cu * p[:, 0] + su * depth, -su * p[:, 0] + cu * depth])


def render_objects(
    query_id: str,
    query_loops: Sequence[np.ndarray],
    shown: Sequence[Any],
    path: str | os.PathLike[str],
    *,
    size: tuple[int, int] = (1600, 900),
    renderer: str = "auto",
) -> RenderResult:
    """Draw a mesh query's contours and its answers' matched contours into one picture.

    query_id : the query's name (shortened for display).
    query_loops : its contours, (m, 3) each, in its principal frame.
    shown : the answers, best first: each with ``rank``, ``id``, ``distance``, ``loops``
        (its matched contours in its principal frame) and ``note`` (drawn under its title,
        or None): :class:`~nfdmatch.show_objects.ShownObject`.
    path : PNG, or SVG / PDF by the extension. size : (width, height) pixels.
    renderer : ``"auto"`` or ``"matplotlib"`` (pyvista does not draw these pictures).

    Raises ParameterError (a bad size, renderer or contour), WriteError, RenderError
    (matplotlib missing or failing)."""
    if check_renderer(renderer) == "pyvista":
        raise ParameterError("the contours of a mesh query are drawn by matplotlib: use --renderer matplotlib or auto")
    size = check_size(size)
    out = check_output(path)
    query = [_loop(p, "the query's contour") for p in query_loops]
    if not query:
        raise ParameterError("the query has no contour to draw", path=str(query_id))
    answers = [(a, [_loop(p, f"{a.id}'s contour") for p in a.loops]) for a in shown]
    t0 = time.perf_counter()
    try:
        data = _draw(str(query_id), query, answers, size, picture_format(out))
    except (WriteError, ParameterError):
        raise
    except Exception as exc:  # ImportError, a failure inside matplotlib
        raise RenderError(f"matplotlib could not draw the picture ({_reason(exc)})", path=out) from exc
    _write(out, data)
    return RenderResult(path=out, renderer="matplotlib", seconds=time.perf_counter() - t0)


def _loop(points, what: str) -> np.ndarray:
    a = np.asarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or len(a) < 2 or not np.all(np.isfinite(a)):
        raise ParameterError(f"{what}: expected an (m, 3) array of finite numbers, got shape {a.shape}")
    return object_view(a)


def _draw(query_id: str, query: list, answers: list, size: tuple[int, int], fmt: str) -> bytes:
    """The figure's bytes: panels laid out as :func:`~.layout.choose_grid` finds best."""
    every = np.vstack(query + [p for _, loops in answers for p in loops])
    lo, hi = every.min(axis=0), every.max(axis=0)
    span = max(float((hi - lo)[:2].max()), 1e-9)
    dw, dh = (hi[0] - lo[0]) + 0.08 * span, (hi[1] - lo[1]) + 0.08 * span
    rows, cols = choose_grid(1 + len(answers), size, dw, dh)
    W, H = size
    cw, ch = W / cols, H / rows
    font = float(np.clip(min(cw / 40.0, ch / 20.0), 7.0, 13.0))
    band = int(math.ceil(2 * 1.3 * font * 100 / 72 + 8))
    pad = max(4.0, 0.03 * min(cw, ch))
    labels = short_labels([query_id] + [a.id for a, _ in answers])
    panels = [(f"query: {labels[0]}", f"{len(query)} contours \u00b7 principal frame", None)]
    for (a, loops), label in zip(answers, labels[1:]):
        extra = f" \u00b7 {a.note}" if a.note else ""
        panels.append((f"{a.rank}. {label}", f"d = {a.distance:.4g} \u00b7 {len(loops)} matched{extra}", loops))
    fig = new_figure(size)
    texts = []
    zrange = (float(lo[2]), float(hi[2]))
    for k, (title, subtitle, loops) in enumerate(panels):
        r, c = divmod(k, cols)
        ax = fig.add_axes(((c * cw + pad) / W, (H - (r + 1) * ch + pad) / H, (cw - 2 * pad) / W, (ch - band - pad) / H))
        ax.set_xlim((lo[0] + hi[0]) / 2 - dw / 2, (lo[0] + hi[0]) / 2 + dw / 2)
        ax.set_ylim((lo[1] + hi[1]) / 2 - dh / 2, (lo[1] + hi[1]) / 2 + dh / 2)
        ax.set_aspect("equal", adjustable="box")
        ax.set_axis_off()
        if loops is None:
            _draw_loops(ax, query, QUERY_COLOR, 1.6, zrange)
        else:
            _draw_loops(ax, query, UNDER_COLOR, 0.8, None)
            _draw_loops(ax, loops, MATCH_COLOR, 1.8, zrange)
        top, cx = 1 - r * ch / H - 4 / H, (c + 0.5) * cw / W
        bold = "bold" if loops is None else "normal"
        texts.append(fig.text(cx, top, title, ha="center", va="top", fontsize=font, color=TEXT_COLOR, fontweight=bold))
        line = 1.3 * font * 100 / 72 / H
        texts.append(fig.text(cx, top - line, subtitle, ha="center", va="top", fontsize=0.92 * font, color=NOTE_COLOR))
    _fit_texts(fig, texts, cw - 6)
    return png_bytes(fig, fmt)


def _draw_loops(ax, loops: list, color: str, width: float, zrange) -> None:
    """Closed contours in one collection, farther ones lighter (``zrange`` None: all alike)."""
    from matplotlib.collections import LineCollection
    from matplotlib.colors import to_rgb

    rgb = np.asarray(to_rgb(color))
    segments, colors = [], []
    for p in sorted(loops, key=lambda p: float(p[:, 2].mean())):  # far first
        segments.append(np.vstack([p[:, :2], p[:1, :2]]))
        near = 1.0
        if zrange is not None and zrange[1] > zrange[0]:
            near = (float(p[:, 2].mean()) - zrange[0]) / (zrange[1] - zrange[0])
        colors.append(np.append(rgb + (1 - rgb) * 0.55 * (1 - near), 1.0))
    ax.add_collection(LineCollection(segments, colors=colors, linewidths=width, joinstyle="round", zorder=2))
