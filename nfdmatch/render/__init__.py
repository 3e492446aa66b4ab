"""Pictures: a query and its aligned matches (``nfdmatch show``), and the all-pairs distance
matrix (``nfdmatch matrix``), drawn into PNG, SVG or PDF files.

Modules: :mod:`.layout` (inputs, labels, the scene), :mod:`.matplotlib_backend`,
:mod:`.pyvista_backend`, :mod:`.matrix`; this one chooses the renderer.

This module only draws: the matches arrive already mapped into the query's coordinates
(:class:`~nfdmatch.records.ShownMatch`, from :mod:`nfdmatch.show`). It never prints and never exits; every failure is an
:class:`~nfdmatch.errors.NfdError`. matplotlib and pyvista are imported inside the
functions that use them, so importing this module (or the CLI) costs nothing.

Layout of :func:`render_matches`
    A grid of equal panels (the grid shape that makes the panels largest for the picture
    size): first the query alone, then one panel per match, in the order given. In a
    match panel the query is drawn thin and grey underneath and the match in a strong
    colour on top, so where they agree only the colour shows. Open circle: the query's
    first vertex; filled circle: the match's point that corresponds to it; arrows: the
    direction of travel from there. Every panel has the same view and the same limits,
    with equal aspect.

View
    Planar input (:func:`is_coplanar` of the query and all matches) is drawn in 2-D, in the
    plane of the query (its first two principal axes; simply x, y when every z is ~0).
    Otherwise a 3-D orthographic view: the camera looks along the query's smallest
    principal axis tilted by 30 degrees towards the middle one, the same for all panels.
    With matplotlib the 3-D view is projected here (not mplot3d): the curve is cut into
    short pieces drawn far to near, each with a thin white halo, so crossings read as
    over/under as in a knot diagram, and farther pieces are lighter. That gives exact
    equal aspect and identical limits in every panel, and is faster than mplot3d.

Choice: ``DEFAULT_RENDERER = "matplotlib"`` (figures in ``docs/performance.md``, from
``python benchmarks/bench_render.py``). It is 2-4x faster for the first picture
(what a ``show`` command pays) and 2-3x after; it needs no OpenGL, so it works on any
machine (pyvista needs EGL, OSMesa or a display, and VTK kills the process when none
works: see :func:`_probe_pyvista`); and it looked better side by side: crisp centred titles
that are shrunk to fit, clear start markers and arrows, and in 3-D the halos at crossings
and the lighter far side make over/under readable, which pyvista's shaded tubes show only
faintly in an orthographic view (its arrows and text are also coarser). pyvista stays
available (``renderer="pyvista"``) and is the fallback when matplotlib is missing.

Test hooks: tests replace ``draw_matplotlib`` / ``draw_pyvista`` in this module (looked up
at call time by :func:`_drawer`) and :func:`.pyvista_backend._probe_pyvista`, and raise
``Unavailable`` (a renderer that cannot draw on this machine), to act out a missing or
crashing renderer. :func:`.layout.build_scene` is public: what a picture shows can be
checked without drawing it.
"""

from __future__ import annotations

import os
import time
from typing import Sequence

import numpy as np

from ..errors import ParameterError, RenderError, WriteError
from ..records import ShownMatch
from .layout import (
    DEFAULT_RENDERER,
    MAX_SIDE,
    MIN_SIDE,
    PICTURE_FORMATS,
    RENDERERS,
    START_STEP,
    MatchPanel,
    RenderResult,
    _as_points,
    as_vector,
    build_scene,
    check_renderer,
    check_size,
    _reason,
    Unavailable,
    _write,
    check_output,
    is_coplanar,
    picture_format,
    short_label,
    short_labels,
)
from .matplotlib_backend import draw_matplotlib
from .matrix import render_matrix
from .objects import render_objects
from .pyvista_backend import draw_pyvista

__all__ = [
    "RENDERERS",
    "DEFAULT_RENDERER",
    "START_STEP",
    "MIN_SIDE",
    "MAX_SIDE",
    "ShownMatch",
    "MatchPanel",
    "RenderResult",
    "PICTURE_FORMATS",
    "check_output",
    "picture_format",
    "render_matches",
    "render_matrix",
    "render_objects",
    "is_coplanar",
    "short_label",
    "short_labels",
]


# --------------------------------------------------------------------------- renderers


def render_matches(
    query: np.ndarray,
    query_id: str,
    panels: Sequence[ShownMatch],
    path: str | os.PathLike[str],
    *,
    size: tuple[int, int] = (1600, 900),
    renderer: str = "auto",
) -> RenderResult:
    """Draw the query and its matches, each in the query's frame, into one PNG.

    Parameters
    ----------
    query : (n, 3) float, the query's vertices (closed polyline).
    query_id : the query's id (shortened for display).
    panels : the :class:`~nfdmatch.records.ShownMatch` es, best first (each already mapped
        into the query's coordinates).
    path : the picture file to write: ``.png`` (or no extension), ``.svg`` or ``.pdf``
        (SVG and PDF are drawn by matplotlib whatever ``renderer`` auto picks).
    size : (width, height) of the picture in pixels, 100..10000 each; exact.
    renderer : ``"auto"`` (:data:`DEFAULT_RENDERER`, falling back to the other one when it
        is not installed or cannot draw here: see :attr:`RenderResult.note`),
        ``"matplotlib"`` or ``"pyvista"`` (an error if it cannot draw).

    Returns
    -------
    :class:`RenderResult`.

    Raises
    ------
    ParameterError : an unknown renderer, a bad size, invalid arrays (shape, NaN).
    WriteError : the file cannot be written (missing folder, a directory, no permission).
    RenderError : the renderer asked for (or, with auto, both) cannot draw on this machine.
    """
    check_renderer(renderer)
    size = check_size(size)
    q = _as_points(query, "query", min_points=2)
    checked = [_checked_panel(i, p) for i, p in enumerate(panels)]
    out = check_output(path)
    fmt = picture_format(out)
    scene = build_scene(q, str(query_id), checked, size)
    order = [renderer] if renderer != "auto" else [DEFAULT_RENDERER] + [r for r in RENDERERS if r != DEFAULT_RENDERER]
    if fmt != "png":  # pyvista draws pixels only
        if renderer == "pyvista":
            raise ParameterError(f"pyvista draws PNG only; use --renderer matplotlib for .{fmt}", path=out)
        order = ["matplotlib"]
    failures = []
    t0 = time.perf_counter()
    for name in order:
        try:
            data = _drawer(name)(scene) if fmt == "png" else _drawer(name)(scene, fmt=fmt)
        except (WriteError, ParameterError):
            raise
        except Exception as exc:  # ImportError, RuntimeError from VTK/EGL, anything else
            reason = _reason(exc)
            if renderer != "auto":
                raise RenderError(_unavailable(name, reason, exc), path=out) from exc
            failures.append((name, reason))
            continue
        _write(out, data)
        note = None
        if failures:
            note = "; ".join(f"{n} could not draw ({r})" for n, r in failures) + f"; used {name}"
        return RenderResult(path=out, renderer=name, seconds=time.perf_counter() - t0, note=note)
    raise RenderError("no renderer could draw the picture: " + "; ".join(f"{n}: {r}" for n, r in failures), path=out)


def _checked_panel(i: int, p) -> ShownMatch:
    """Panel ``i`` (0-based) checked, as a ShownMatch of plain types and float64 arrays."""
    if not isinstance(p, ShownMatch):
        raise ParameterError(f"panel {i + 1}: expected a ShownMatch, got {type(p).__name__}")
    what = f"match {i + 1} ({p.id})"
    try:
        d = float(p.distance)
    except (TypeError, ValueError):
        raise ParameterError(f"{what}: distance must be a number, got {p.distance!r}") from None
    return ShownMatch(
        match=p.match.replace(id=str(p.id), distance=d, reversed=bool(p.reversed), mirrored=bool(p.mirrored)),
        points=_as_points(p.points, what),
        start=as_vector(p.start, f"{what} start"),
        forward=as_vector(p.forward, f"{what} forward"),
        source=p.source,
    )


def _drawer(name: str):
    """The drawing function of a renderer (looked up at call time, so tests can replace it)."""
    return {"matplotlib": draw_matplotlib, "pyvista": draw_pyvista}[name]


def _unavailable(name: str, reason: str, exc: BaseException) -> str:
    other = [r for r in RENDERERS if r != name][0]
    if name == "pyvista" and isinstance(exc, (Unavailable, ImportError)):
        return f"pyvista cannot render off-screen on this machine ({reason}); use --renderer {other}"
    return f"{name} could not draw the picture ({reason}); use --renderer {other}"
