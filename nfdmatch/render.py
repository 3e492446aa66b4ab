"""Pictures: a query and its aligned matches (``nfdmatch show``), and the all-pairs distance
matrix (``nfdmatch matrix``), drawn into PNG files.

This module only draws: the matches arrive already mapped into the query's coordinates
(:class:`MatchPanel`). It never prints and never exits; every failure is an
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
    Planar input (:func:`is_planar` of the query and all matches) is drawn in 2-D, in the
    plane of the query (its first two principal axes; simply x, y when every z is ~0).
    Otherwise a 3-D orthographic view: the camera looks along the query's smallest
    principal axis tilted by 30 degrees towards the middle one, the same for all panels.
    With matplotlib the 3-D view is projected here (not mplot3d): the curve is cut into
    short pieces drawn far to near, each with a thin white halo, so crossings read as
    over/under as in a knot diagram, and farther pieces are lighter. That gives exact
    equal aspect and identical limits in every panel, and is faster than mplot3d.

Renderers, measured with ``python benchmarks/bench_render.py --repeat 3`` (4 runs on a
noisy 2-core Xeon, software OpenGL: VTK 9.7 on Mesa EGL/llvmpipe, pyvista 0.49, matplotlib
3.11). 1600x900, a query and 5 matches; 2d: 16-300 vertices per curve, 3d: 24-777,
3d-2000: about 2,000. "first" = the first picture of a fresh process, imports included
(for pyvista also the probe below); "then" = median of the next pictures, in seconds::

    renderer    picture   first        then
    matplotlib  2d        0.52-0.80    0.14-0.21
    matplotlib  3d        0.61-0.95    0.23-0.36
    matplotlib  3d-2000   0.67-1.03    0.30-0.48
    pyvista     2d        1.86-2.36    0.49-0.64
    pyvista     3d        2.00-2.90    0.48-0.57
    pyvista     3d-2000   2.16-2.36    0.58-0.77
    matrix of 100 curves (matplotlib, 1280x1160): 0.61-1.02

Choice: ``DEFAULT_RENDERER = "matplotlib"``. It is 2-4x faster for the first picture
(what a ``show`` command pays) and 2-3x after; it needs no OpenGL, so it works on any
machine (pyvista needs EGL, OSMesa or a display, and VTK kills the process when none
works: see :func:`_probe_pyvista`); and it looked better side by side: crisp centred titles
that are shrunk to fit, clear start markers and arrows, and in 3-D the halos at crossings
and the lighter far side make over/under readable, which pyvista's shaded tubes show only
faintly in an orthographic view (its arrows and text are also coarser). pyvista stays
available (``renderer="pyvista"``) and is the fallback when matplotlib is missing.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .descriptors import points_at
from .errors import ParameterError, RenderError, WriteError

__all__ = ["RENDERERS", "DEFAULT_RENDERER", "START_STEP", "MIN_SIDE", "MAX_SIDE", "MatchPanel", "RenderResult",
           "PICTURE_FORMATS", "check_output", "picture_format", "render_matches",
           "render_matrix", "is_planar", "short_label", "short_labels"]

RENDERERS = ("matplotlib", "pyvista")
DEFAULT_RENDERER = "matplotlib"

#: picture sizes accepted, pixels per side
MIN_SIDE, MAX_SIDE = 100, 10000
#: the direction markers: this fraction of the query's length on from its start (the
#: query's own arrow here; :mod:`nfdmatch.show` places the matches' with it)
START_STEP = 0.04
#: characters of a shortened id in a panel title / on a matrix axis
LABEL_WIDTH = 32
MATRIX_LABEL_WIDTH = 28

_QUERY_COLOR = "#1f4e9c"       # the query, in its own panel
_UNDER_COLOR = "#9c9c9c"       # the query under a match
_MATCH_COLOR = "#d1421b"       # a match
_TEXT_COLOR = "#1a1a1a"
_NOTE_COLOR = "#555555"
_TILT = math.radians(30.0)     # 3-D view: tilt of the camera away from the smallest axis
_ARROW = 0.11                  # arrow length, fraction of the larger side of the view


@dataclass(frozen=True)
class MatchPanel:
    """One match to draw, already in the query's coordinates.

    Attributes
    ----------
    id : the match's curve id (a path, or ``path#i``); shortened for display.
    distance : float, shown with 4 significant digits.
    points : (m, 3) float64, the matched curve mapped into the query's coordinates
        (closed; the closing edge is implicit).
    start : (3,) float64, the point of the match that corresponds to the query's first vertex.
    forward : (3,) float64, a point a little further along the match in the query's
        direction of travel.
    reversed, mirrored : shown in the panel title when set.
    note : a short remark shown after them (e.g. ``"from index harmonics"``), or None.
    """

    id: str
    distance: float
    points: np.ndarray
    start: np.ndarray
    forward: np.ndarray
    reversed: bool = False
    mirrored: bool = False
    note: str | None = None


@dataclass(frozen=True)
class RenderResult:
    """What was written.

    Attributes
    ----------
    path : the picture file written.
    renderer : the renderer actually used (``"matplotlib"`` or ``"pyvista"``).
    seconds : wall time of drawing and saving (including the renderer's import when it is
        the first picture of the process, and a failed attempt before a fallback).
    note : why another renderer than the one asked for was used, or None.
    """

    path: str
    renderer: str
    seconds: float
    note: str | None = None


# --------------------------------------------------------------------------- labels

_SELECTOR = re.compile(r"#-?[0-9]+$")


def short_label(id: str, width: int = LABEL_WIDTH) -> str:
    """A curve id shortened for a picture: the file's base name, ``#i`` kept, and at most
    ``width`` characters (the middle replaced by an ellipsis, so the start of the name and
    the extension and ``#i`` stay readable).

    >>> short_label("/data/knots/trefoil.csv#3")
    'trefoil.csv#3'
    >>> short_label("a_very_long_curve_name_from_a_scanner_run_0042.csv", 24)
    'a_very_long_…un_0042.csv'
    """
    text = str(id)
    selector = ""
    m = _SELECTOR.search(text)
    if m and m.start() > 0:
        text, selector = text[:m.start()], m.group(0)
    base = re.split(r"[\\/]", text.rstrip("\\/"))[-1] or text
    return _ellipsize(base + selector, width)


def short_labels(ids: Sequence[str], width: int = LABEL_WIDTH) -> list[str]:
    """:func:`short_label` of each id; ids whose base names collide keep as many parent
    folders as it takes to tell them apart (``a/x.csv``, ``b/x.csv``)."""
    ids = [str(i) for i in ids]
    labels = [short_label(i, 10 ** 6) for i in ids]
    parts = [re.split(r"[\\/]", _SELECTOR.sub("", i).rstrip("\\/")) for i in ids]
    for depth in range(2, 1 + max((len(p) for p in parts), default=1)):
        distinct: dict[str, set] = {}
        for label, curve_id in zip(labels, ids):
            distinct.setdefault(label, set()).add(curve_id)
        clash = [k for k, label in enumerate(labels) if len(distinct[label]) > 1]
        if not clash:
            break
        for k in clash:
            m = _SELECTOR.search(ids[k])
            labels[k] = "/".join(parts[k][-depth:]) + (m.group(0) if m and m.start() > 0 else "")
    if len(labels) > 1 and max(len(label) for label in labels) > width:
        labels = _without_common_affixes(labels)
    return [_ellipsize(label, width) for label in labels]


_CUT = "_-. /"


def _without_common_affixes(labels: list[str]) -> list[str]:
    """Drop the prefix and suffix all labels share (cut at a separator, so words stay
    whole), marked by an ellipsis: the part that tells long similar names apart stays
    visible (``column_section-z05_at1.83333_loop0.obj`` -> ``…z05_at1.83333…``)."""
    prefix = os.path.commonprefix(labels)
    suffix = os.path.commonprefix([label[::-1] for label in labels])[::-1]
    shortest = min(len(label) for label in labels)
    cut_start = max((i + 1 for i, ch in enumerate(prefix) if ch in _CUT), default=0)
    cut_end = max((i + 1 for i, ch in enumerate(suffix[::-1]) if ch in _CUT), default=0)
    if cut_start + cut_end >= shortest:                     # nothing distinctive would be left
        return labels
    return [("\u2026" if cut_start else "") + label[cut_start:len(label) - cut_end]
            + ("\u2026" if cut_end else "") for label in labels]


def _ellipsize(text: str, width: int) -> str:
    width = max(int(width), 5)
    if len(text) <= width:
        return text
    tail = (width - 1) // 2
    head = width - 1 - tail
    return text[:head] + "\u2026" + text[len(text) - tail:]


def _format_distance(d: float) -> str:
    return f"{d:.4g}" if math.isfinite(d) else str(d)


# --------------------------------------------------------------------------- checks

def _as_points(x, what: str, min_points: int = 2) -> np.ndarray:
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{what}: expected an (m, 3) array of numbers ({exc})") from None
    if a.ndim != 2 or a.shape[1] not in (2, 3) or a.shape[0] < min_points:
        raise ParameterError(f"{what}: expected an (m, 3) array with m >= {min_points}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ParameterError(f"{what}: contains NaN or infinite coordinates")
    if a.shape[1] == 2:
        a = np.hstack([a, np.zeros((a.shape[0], 1))])
    return a


def _as_vector(x, what: str) -> np.ndarray:
    try:
        v = np.array(x, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{what}: expected 3 numbers ({exc})") from None
    if v.shape == (2,):
        v = np.append(v, 0.0)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ParameterError(f"{what}: expected 3 finite numbers, got {np.asarray(x).tolist()!r}")
    return v


def _check_size(size) -> tuple[int, int]:
    try:
        w, h = size
        if isinstance(w, bool) or isinstance(h, bool) or int(w) != w or int(h) != h:
            raise TypeError
        w, h = int(w), int(h)
    except (TypeError, ValueError):
        raise ParameterError(f"size must be (width, height) in whole pixels, got {size!r}") from None
    if not (MIN_SIDE <= w <= MAX_SIDE and MIN_SIDE <= h <= MAX_SIDE):
        raise ParameterError(f"size must be {MIN_SIDE}..{MAX_SIDE} pixels per side, got {w}x{h}")
    return w, h


#: picture formats by file extension (no extension: PNG)
PICTURE_FORMATS = {".png": "png", ".svg": "svg", ".pdf": "pdf", "": "png"}


def picture_format(path) -> str:
    """``"png"``, ``"svg"`` or ``"pdf"``: the format of a picture file, by its extension."""
    return PICTURE_FORMATS.get(os.path.splitext(str(path))[1].lower(), "png")


def check_output(path) -> str:
    """``path`` as a str if a picture can be written there (a ``.png``, ``.svg`` or ``.pdf``
    name, or none for PNG, in an existing folder, not a directory); else
    :class:`ParameterError` / :class:`WriteError`. Cheap: callers check before long work."""
    try:
        p = os.fspath(path)
    except TypeError:
        raise ParameterError(f"output path must be a file name, got {path!r}") from None
    p = p.decode() if isinstance(p, bytes) else str(p)
    if not p:
        raise WriteError("cannot write the picture: empty file name", path=p)
    ext = os.path.splitext(p)[1].lower()
    if ext not in PICTURE_FORMATS:
        raise ParameterError(f"pictures are written as PNG, SVG or PDF; use a .png, .svg or .pdf file name, "
                             f"not {ext!r}", path=p)
    if os.path.isdir(p):
        raise WriteError("cannot write the picture: it is a directory", path=p)
    folder = os.path.dirname(os.path.abspath(p))
    if not os.path.isdir(folder):
        raise WriteError("cannot write the picture: the folder does not exist", path=p)
    return p


def _write(path: str, data: bytes) -> None:
    """Write the picture whole; an identical existing file is left untouched (mtime included)."""
    from .formats._chain import write_if_changed

    def produce(temp: str) -> None:
        with open(temp, "wb") as f:
            f.write(data)

    try:
        write_if_changed(path, produce)
    except OSError as exc:
        raise WriteError(f"cannot write the picture: {exc.strerror or exc}", path=path) from None


def _check_renderer(renderer) -> str:
    if renderer != "auto" and renderer not in RENDERERS:
        raise ParameterError(f"renderer must be auto, {' or '.join(RENDERERS)}, got {renderer!r}")
    return renderer


# --------------------------------------------------------------------------- geometry

def is_planar(*point_sets, tol: float = 1e-6) -> bool:
    """True when all points of all sets lie within ``tol`` times their extent (the largest
    side of their bounding box) of one plane.

    Parameters
    ----------
    point_sets : (m_i, 3) (or (m_i, 2), planar by definition) arrays of finite floats.
    tol : relative tolerance.
    """
    if not point_sets:
        raise ParameterError("is_planar needs at least one point set")
    pts = np.vstack([_as_points(p, f"point set {i}", min_points=1) for i, p in enumerate(point_sets)])
    extent = float(np.ptp(pts, axis=0).max())
    if extent == 0.0 or len(pts) <= 3:
        return True
    centred = pts - pts.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    return bool(np.abs(centred @ normal).max() <= tol * extent)


def _canonical(v: np.ndarray) -> np.ndarray:
    """The sign of ``v`` whose largest component is positive (a deterministic PCA axis)."""
    return v if v[np.argmax(np.abs(v))] > 0 else -v


def _moments(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and covariance of the closed polyline as a uniform wire (weighted by arc
    length, so they depend on the shape, not on where its vertices happen to be)."""
    closed = np.vstack([points, points[:1]])
    d = np.diff(closed, axis=0)
    length = np.linalg.norm(d, axis=1)
    total = float(length.sum())
    if total == 0.0:
        c = points.mean(axis=0)
        return c, np.zeros((3, 3))
    mid = (closed[:-1] + closed[1:]) / 2
    c = (length[:, None] * mid).sum(axis=0) / total
    m = mid - c
    cov = (np.einsum("i,ij,ik->jk", length, m, m) + np.einsum("i,ij,ik->jk", length, d, d) / 12) / total
    return c, cov


def _principal_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows: principal axes of the curve by decreasing spread, right-handed, deterministic
    signs; and the spreads (variances)."""
    _, cov = _moments(points)
    values, vectors = np.linalg.eigh(cov)                 # ascending
    e1, e3 = _canonical(vectors[:, 2]), _canonical(vectors[:, 0])
    e2 = np.cross(e3, e1)
    return np.array([e1, e2, e3]), values[::-1]


@dataclass
class _Panel:
    title: str                 # first line
    subtitle: str              # second line
    points: np.ndarray         # view coordinates (m, 3): x right, y up, z towards the viewer
    start: np.ndarray
    forward: np.ndarray
    is_query: bool


@dataclass
class _Scene:
    """Everything both renderers need, in view coordinates."""

    planar: bool
    query: np.ndarray
    query_start: np.ndarray
    query_forward: np.ndarray
    panels: list
    size: tuple
    rows: int
    cols: int
    font_pt: float             # panel title font size (points; 1 pt = 100/72 px at dpi 100)
    title_px: int              # title band height of a panel
    pad_px: int                # padding around the data box of a panel
    window: tuple              # (x0, x1, y0, y1) view limits of a panel's data box, same for all
    zrange: tuple              # depth range of everything drawn
    arrow: float               # arrow length, view units

    @property
    def cell(self) -> tuple[float, float]:
        return self.size[0] / self.cols, self.size[1] / self.rows

    @property
    def box(self) -> tuple[float, float]:
        cw, ch = self.cell
        return cw - 2 * self.pad_px, ch - self.title_px - self.pad_px


def _font_for(cell_w: float, cell_h: float) -> float:
    return float(np.clip(min(cell_w / 40.0, cell_h / 20.0), 7.0, 13.0))


def _title_band(font_pt: float) -> int:
    return int(math.ceil(2 * 1.3 * font_pt * 100 / 72 + 8))


def _choose_grid(n: int, size: tuple[int, int], data_w: float, data_h: float) -> tuple[int, int]:
    """(rows, cols) for n panels that makes the drawn curves largest; ties: fewer empty cells."""
    W, H = size
    options = []
    for cols in range(1, n + 1):
        rows = math.ceil(n / cols)
        if (rows - 1) * cols >= n:
            continue
        cw, ch = W / cols, H / rows
        font = _font_for(cw, ch)
        pad = max(4.0, 0.03 * min(cw, ch))
        bw, bh = cw - 2 * pad, ch - _title_band(font) - pad
        scale = min(bw / data_w, bh / data_h) if bw > 0 and bh > 0 else 0.0
        options.append((scale, rows * cols - n, abs(rows - cols), rows, cols))
    top = max(o[0] for o in options)
    # within 8% of the largest drawing, prefer fewer empty cells, then a squarer grid
    _, _, _, rows, cols = min((o for o in options if o[0] >= 0.92 * top), key=lambda o: (o[1], o[2], -o[0]))
    return rows, cols


def _build_scene(query: np.ndarray, query_id: str, panels: list[MatchPanel], size) -> _Scene:
    match_points = [p.points for p in panels]
    planar = is_planar(query, *match_points)
    everything = np.vstack([query] + match_points)
    extent = float(np.ptp(everything, axis=0).max()) or 1.0
    centre, _ = _moments(query)
    if planar and np.abs(everything[:, 2] - centre[2]).max() <= 1e-6 * extent:
        view = np.eye(3)                                        # already in the x, y plane
    else:
        axes, spread = _principal_axes(query)
        if spread[1] <= 1e-12 * max(spread[0], 1e-300):        # a straight query: use everything
            vt = np.linalg.svd(everything - everything.mean(axis=0), full_matrices=True)[2]
            e1, e3 = _canonical(vt[0]), _canonical(vt[2])
            axes = np.array([e1, np.cross(e3, e1), e3])
        if planar:
            view = axes
        else:
            e1, e2, e3 = axes
            c, s = math.cos(_TILT), math.sin(_TILT)
            view = np.array([e1, c * e2 + s * e3, -s * e2 + c * e3])

    def to_view(p):
        return (np.asarray(p) - centre) @ view.T

    q = to_view(query)
    q_start, q_forward = q[0], to_view(points_at(query, [START_STEP])[0])
    # shortened together: long names that differ in the middle keep that middle
    qlabel, *match_labels = short_labels([query_id] + [p.id for p in panels])
    scene_panels = [_Panel(title=f"query: {qlabel}",
                           subtitle=_key(planar, bool(panels)),
                           points=q, start=q_start, forward=q_forward, is_query=True)]
    for rank, p in enumerate(panels, 1):
        flags = [f for f, on in (("reversed", p.reversed), ("mirrored", p.mirrored), (p.note, bool(p.note)))
                 if on]
        scene_panels.append(_Panel(
            title=f"{rank}. {match_labels[rank - 1]}",
            subtitle="  \u00b7  ".join([f"d = {_format_distance(p.distance)}"] + flags),
            points=to_view(p.points), start=to_view(p.start), forward=to_view(p.forward), is_query=False))
    allv = np.vstack([sp.points for sp in scene_panels]
                     + [np.array([sp.start for sp in scene_panels])])
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    dw, dh = max(hi[0] - lo[0], 1e-12 * extent), max(hi[1] - lo[1], 1e-12 * extent)
    # room for the arrows and markers around the curves
    margin = 0.06 * max(dw, dh)
    dw, dh = dw + 2 * margin, dh + 2 * margin
    rows, cols = _choose_grid(len(scene_panels), size, dw, dh)
    cw, ch = size[0] / cols, size[1] / rows
    font = _font_for(cw, ch)
    title_px = _title_band(font)
    pad = int(round(max(4.0, 0.03 * min(cw, ch))))
    bw, bh = cw - 2 * pad, ch - title_px - pad
    # view window of the data box: the data's bounding box grown to the box's aspect
    half = max(dw / 2, dh / 2 * bw / bh)
    units_per_px = 2 * half / bw
    hw, hh = bw / 2 * units_per_px, bh / 2 * units_per_px
    cx, cy = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2
    return _Scene(planar=planar, query=q, query_start=q_start, query_forward=q_forward,
                  panels=scene_panels, size=tuple(size), rows=rows, cols=cols, font_pt=font,
                  title_px=title_px, pad_px=pad, window=(cx - hw, cx + hw, cy - hh, cy + hh),
                  zrange=(float(lo[2]), float(hi[2])), arrow=_ARROW * max(dw, dh) / (1 + 0.12))


def _key(planar: bool, matches: bool) -> str:
    """The query panel's second line: how to read the picture."""
    parts = ["\u25cb start  \u2192 direction"]
    if matches:
        parts.append("grey: query")
    if not planar:
        parts.append("nearer = darker")
    return "  \u00b7  ".join(parts)


def _screen_direction(start: np.ndarray, forward: np.ndarray) -> np.ndarray | None:
    d = (forward - start)[:2]
    n = float(np.hypot(*d))
    full = float(np.linalg.norm(forward - start))
    if full == 0.0 or n < 0.05 * full:
        return None                   # along the line of sight: no readable arrow
    return d / n


# --------------------------------------------------------------------------- renderers

def render_matches(query: np.ndarray, query_id: str, panels: Sequence[MatchPanel], path, *,
                   size: tuple[int, int] = (1600, 900), renderer: str = "auto") -> RenderResult:
    """Draw the query and its matches, each in the query's frame, into one PNG.

    Parameters
    ----------
    query : (n, 3) float, the query's vertices (closed polyline).
    query_id : the query's id (shortened for display).
    panels : the matches, best first; each already mapped into the query's coordinates.
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
    _check_renderer(renderer)
    size = _check_size(size)
    q = _as_points(query, "query", min_points=2)
    checked = []
    for i, p in enumerate(panels):
        if not isinstance(p, MatchPanel):
            raise ParameterError(f"panel {i + 1}: expected a MatchPanel, got {type(p).__name__}")
        what = f"match {i + 1} ({p.id})"
        try:
            d = float(p.distance)
        except (TypeError, ValueError):
            raise ParameterError(f"{what}: distance must be a number, got {p.distance!r}") from None
        checked.append(MatchPanel(id=str(p.id), distance=d, points=_as_points(p.points, what),
                                  start=_as_vector(p.start, f"{what} start"),
                                  forward=_as_vector(p.forward, f"{what} forward"),
                                  reversed=bool(p.reversed), mirrored=bool(p.mirrored),
                                  note=None if p.note is None else str(p.note)))
    out = check_output(path)
    fmt = picture_format(out)
    scene = _build_scene(q, str(query_id), checked, size)
    order = [renderer] if renderer != "auto" else [DEFAULT_RENDERER] + [r for r in RENDERERS
                                                                         if r != DEFAULT_RENDERER]
    if fmt != "png":                  # pyvista draws pixels only
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
        except Exception as exc:        # ImportError, RuntimeError from VTK/EGL, anything else
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
    raise RenderError("no renderer could draw the picture: "
                      + "; ".join(f"{n}: {r}" for n, r in failures), path=out)


def _drawer(name: str):
    """The drawing function of a renderer (looked up at call time, so tests can replace it)."""
    return {"matplotlib": _draw_matplotlib, "pyvista": _draw_pyvista}[name]


class _Unavailable(RuntimeError):
    """A renderer that cannot work here; the message says why (shown as is)."""


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if isinstance(exc, _Unavailable):
        return text
    if isinstance(exc, ImportError):
        return f"{getattr(exc, 'name', None) or 'it'} is not installed" + (f": {text}" if text else "")
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _unavailable(name: str, reason: str, exc: BaseException) -> str:
    other = [r for r in RENDERERS if r != name][0]
    if name == "pyvista" and isinstance(exc, (_Unavailable, ImportError)):
        return f"pyvista cannot render off-screen on this machine ({reason}); use --renderer {other}"
    return f"{name} could not draw the picture ({reason}); use --renderer {other}"


# --------------------------------------------------------------------------- matplotlib

def _new_figure(size, **kwargs):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100.0, size[1] / 100.0), dpi=100, facecolor="white", **kwargs)
    FigureCanvasAgg(fig)
    return fig


def _png_bytes(fig, fmt: str = "png") -> bytes:
    """The figure as PNG, SVG or PDF bytes; the same figure gives the same bytes (no date in
    the metadata, fixed SVG ids), so an unchanged picture leaves its file untouched."""
    import matplotlib

    buf = io.BytesIO()
    metadata = {"png": None, "svg": {"Date": None}, "pdf": {"CreationDate": None, "ModDate": None}}[fmt]
    with matplotlib.rc_context({"svg.hashsalt": "nfdmatch"}):
        fig.savefig(buf, format=fmt, dpi=100, facecolor="white", metadata=metadata)
    return buf.getvalue()


def _mix(color, amount: np.ndarray) -> np.ndarray:
    """RGBA rows: ``color`` blended towards white by ``amount`` (0..1)."""
    from matplotlib.colors import to_rgb

    rgb = np.asarray(to_rgb(color))
    mixed = rgb[None, :] * (1 - amount[:, None]) + amount[:, None]
    return np.hstack([mixed, np.ones((len(amount), 1))])


def _depth_pieces(points: np.ndarray, pieces: int = 240):
    """The closed curve cut into about ``pieces`` runs of equal length, long edges split
    (vertices kept). Returns (paths, depth): each path a (k, 2) array overlapping the next
    by one sub-edge so the pieces join without gaps, depth its mean z."""
    closed = np.vstack([points, points[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    total = float(seg.sum()) or 1.0
    step = total / (pieces * 4)
    k = np.maximum(1, np.ceil(seg / step).astype(int))
    starts = np.repeat(closed[:-1], k, axis=0)
    deltas = np.repeat(closed[1:] - closed[:-1], k, axis=0)
    frac = np.concatenate([np.arange(n) / n for n in k])
    dense = np.vstack([starts + frac[:, None] * deltas, closed[-1:]])
    per = max(1, (len(dense) - 1) // pieces)
    paths, depth = [], []
    n = len(dense) - 1
    for i in range(0, n, per):
        j = min(i + per + 1, n)           # one sub-edge of overlap with the next piece
        chunk = dense[i:j + 1]
        paths.append(chunk[:, :2])
        depth.append(float(chunk[:, 2].mean()))
    return paths, np.array(depth)


def _draw_curve_mpl(ax, pts, color, lw_pt, *, depth: bool, zrange, zorder: float, halo: bool):
    from matplotlib.collections import LineCollection

    if not depth:
        closed = np.vstack([pts, pts[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color=color, lw=lw_pt, solid_joinstyle="round",
                solid_capstyle="round", zorder=zorder)
        return
    paths, z = _depth_pieces(pts)
    z0, z1 = zrange
    near = (z - z0) / (z1 - z0) if z1 > z0 else np.ones_like(z)
    order = np.argsort(z, kind="stable")                      # far first
    colors = _mix(color, 0.5 * (1.0 - near))
    widths = lw_pt * (0.75 + 0.5 * near)
    segs, cols, lws = [], [], []
    for i in order:
        if halo:
            segs.append(paths[i][1:-1] if len(paths[i]) > 3 else paths[i])
            cols.append((1, 1, 1, 0.85))
            lws.append(widths[i] + 2.6)
        segs.append(paths[i])
        cols.append(colors[i])
        lws.append(widths[i])
    ax.add_collection(LineCollection(segs, colors=cols, linewidths=lws, capstyle="butt",
                                     joinstyle="round", zorder=zorder))


def _mark_mpl(ax, start, forward, color, arrow_len, *, filled: bool, zorder: float):
    from matplotlib.patches import FancyArrowPatch

    d = _screen_direction(start, forward)
    if d is not None:
        end = start[:2] + arrow_len * d
        ax.add_patch(FancyArrowPatch(tuple(start[:2]), tuple(end), arrowstyle="-|>", mutation_scale=17,
                                     lw=2.2, color=color, shrinkA=0, shrinkB=0, zorder=zorder))
    ax.plot([start[0]], [start[1]], marker="o", ms=8.5, mew=2.0, zorder=zorder + 0.1,
            mfc=color if filled else "white", mec="white" if filled else color)


def _draw_matplotlib(scene: _Scene, fmt: str = "png") -> bytes:
    fig = _new_figure(scene.size)
    W, H = scene.size
    cw, ch = scene.cell
    bw, bh = scene.box
    x0, x1, y0, y1 = scene.window
    depth = not scene.planar
    texts = []
    for k, panel in enumerate(scene.panels):
        r, c = divmod(k, scene.cols)
        left = c * cw + scene.pad_px
        bottom = H - (r + 1) * ch + scene.pad_px
        ax = fig.add_axes((left / W, bottom / H, bw / W, bh / H))
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal", adjustable="box")
        ax.set_axis_off()
        if panel.is_query:
            _draw_curve_mpl(ax, panel.points, _QUERY_COLOR, 2.2, depth=depth, zrange=scene.zrange,
                            zorder=2, halo=True)
            _mark_mpl(ax, panel.start, panel.forward, _QUERY_COLOR, scene.arrow, filled=False, zorder=5)
        else:
            _draw_curve_mpl(ax, scene.query, _UNDER_COLOR, 1.2, depth=False, zrange=scene.zrange,
                            zorder=1, halo=False)
            _draw_curve_mpl(ax, panel.points, _MATCH_COLOR, 2.2, depth=depth, zrange=scene.zrange,
                            zorder=2, halo=True)
            _mark_mpl(ax, scene.query_start, scene.query_forward, _UNDER_COLOR, scene.arrow,
                      filled=False, zorder=4)
            _mark_mpl(ax, panel.start, panel.forward, _MATCH_COLOR, scene.arrow, filled=True, zorder=5)
        top = 1 - r * ch / H
        cx = (c + 0.5) * cw / W
        line = 1.3 * scene.font_pt * 100 / 72 / H
        texts.append(fig.text(cx, top - 4 / H, panel.title, ha="center", va="top", fontsize=scene.font_pt,
                              color=_TEXT_COLOR, fontweight="bold" if panel.is_query else "normal"))
        if panel.subtitle:
            texts.append(fig.text(cx, top - 4 / H - line, panel.subtitle, ha="center", va="top",
                                  fontsize=scene.font_pt * 0.92, color=_NOTE_COLOR))
    _fit_texts(fig, texts, cw - 6)
    return _png_bytes(fig, fmt)


def _fit_texts(fig, texts, max_px: float) -> None:
    """Shrink the font of any text wider than ``max_px`` pixels until it fits."""
    renderer = fig.canvas.get_renderer()
    for text in texts:
        width = text.get_window_extent(renderer=renderer).width
        if width > max_px:
            text.set_fontsize(max(4.0, text.get_fontsize() * max_px / width * 0.98))


# --------------------------------------------------------------------------- pyvista

_PROBE = r"""
import os, sys
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
from vtkmodules.vtkRenderingCore import vtkRenderWindow, vtkRenderer
import vtkmodules.vtkRenderingOpenGL2
w = vtkRenderWindow()
w.SetOffScreenRendering(1)
w.SetSize(8, 8)
w.AddRenderer(vtkRenderer())
w.Render()
sys.stdout.write("ok " + w.GetClassName())
"""
_probe_result: dict[str, str | None] = {}
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _probe_pyvista() -> str | None:
    """None when VTK can open an off-screen window here, else why not.

    VTK kills the process (segmentation fault) when no off-screen OpenGL window can be
    created (no EGL device, no OSMesa, no X display), so the first pyvista picture of a
    process is preceded by a tiny render in a child process (about 0.3-0.6 s)."""
    key = os.environ.get("VTK_DEFAULT_OPENGL_WINDOW", "")
    if key in _probe_result:
        return _probe_result[key]
    if not sys.executable:
        return None                    # cannot start a child: try in-process
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                              timeout=120, stdin=subprocess.DEVNULL, env=dict(os.environ))
    except (OSError, subprocess.SubprocessError) as exc:
        if isinstance(exc, subprocess.TimeoutExpired):
            result = "a test render did not finish in 120 s"
        else:
            return None
    else:
        if proc.returncode == 0 and proc.stdout.startswith("ok"):
            result = None
        else:
            result = _probe_reason(proc.returncode, proc.stderr)
    _probe_result[key] = result
    return result


def _probe_reason(returncode: int, stderr: str) -> str:
    lines = [_ANSI.sub("", line).strip() for line in stderr.splitlines()]
    lines = [re.sub(r"^.*?(WARN|ERR|ERROR)\|\s*", "", line) for line in lines if line]
    lines = [re.sub(r"^vtk\w+ \(0x[0-9a-f]+\):\s*", "", line) for line in lines]
    useful = [line for line in lines
              if re.search(r"fail|not found|could not|cannot|bad x server|error", line, re.I)]
    how = (f"a test render crashed (signal {-returncode})" if returncode < 0
           else f"a test render failed (exit status {returncode})")
    if useful:
        detail = "; ".join(dict.fromkeys(useful[:2]))
        return f"{how}: {detail[:240]}"
    if lines:
        return f"{how}: {lines[-1][:300]}"
    return how


@contextlib.contextmanager
def _stdout_to_stderr():
    """Send anything written to file descriptor 1 (VTK's C++ output) to stderr meanwhile:
    the CLI's stdout carries data."""
    try:
        sys.stdout.flush()
    except Exception:
        pass
    try:
        saved = os.dup(1)
    except OSError:
        yield
        return
    try:
        os.dup2(2, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _draw_pyvista(scene: _Scene) -> bytes:
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    with _stdout_to_stderr(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import pyvista as pv
        from PIL import Image

        problem = _probe_pyvista()
        if problem is not None:
            raise _Unavailable(problem)
        try:
            from vtkmodules.vtkCommonCore import vtkObject
            vtkObject.GlobalWarningDisplayOff()
        except ImportError:
            pass
        plotter = pv.Plotter(off_screen=True, window_size=list(scene.size), shape=(scene.rows, scene.cols),
                             border=False)
        try:
            _fill_pyvista(pv, plotter, scene)
            img = plotter.screenshot(None, return_img=True)
        finally:
            plotter.close()
    if img is None or img.shape[:2] != (scene.size[1], scene.size[0]):
        got = None if img is None else f"{img.shape[1]}x{img.shape[0]}"
        raise _Unavailable(f"the off-screen window gave a {got} picture, not {scene.size[0]}x{scene.size[1]}")
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img[:, :, :3])).save(buf, format="PNG")
    return buf.getvalue()


def _fill_pyvista(pv, plotter, scene: _Scene) -> None:
    cw, ch = scene.cell
    bw, bh = scene.box
    x0, x1, y0, y1 = scene.window
    units_per_px = (x1 - x0) / bw
    # the data box sits below the title band: centre the camera on the cell, not the box
    fx = (x0 + x1) / 2
    fy = (y0 + y1) / 2 + (ch / 2 - (scene.pad_px + bh / 2)) * units_per_px
    z0, z1 = scene.zrange
    depth = max(z1 - z0, x1 - x0, 1e-9)
    lift = 1e-3 * (x1 - x0)            # planar: draw the match just in front of the query
    tubes = not scene.planar
    n_cells = scene.rows * scene.cols
    for k in range(n_cells):
        r, c = divmod(k, scene.cols)
        plotter.subplot(r, c)
        plotter.set_background("white")
        if k < len(scene.panels):
            panel = scene.panels[k]
            if panel.is_query:
                _curve_pv(pv, plotter, panel.points, _QUERY_COLOR, 4.0, tubes)
                _mark_pv(pv, plotter, panel.start, panel.forward, _QUERY_COLOR, scene, lift, filled=False)
            else:
                _curve_pv(pv, plotter, scene.query, _UNDER_COLOR, 2.0, False)
                _curve_pv(pv, plotter, panel.points + [0, 0, lift], _MATCH_COLOR, 4.0, tubes)
                _mark_pv(pv, plotter, scene.query_start, scene.query_forward, _UNDER_COLOR, scene, lift,
                         filled=False)
                _mark_pv(pv, plotter, panel.start, panel.forward, _MATCH_COLOR, scene, 2 * lift, filled=True)
            subtitle = ("dots: start, arrows: direction" if panel.is_query and scene.panels[1:]
                        else panel.subtitle if not panel.is_query else "")
            text = panel.title + ("\n" + subtitle if subtitle else "")
            longest = max(len(t) for t in text.splitlines())
            font = min(scene.font_pt * 0.75, (cw - 8) / (0.62 * longest))
            plotter.add_text(text, position="upper_edge", font_size=max(5, int(font)), color=_TEXT_COLOR)
        plotter.enable_parallel_projection()
        plotter.camera_position = [(fx, fy, z1 + 4 * depth), (fx, fy, (z0 + z1) / 2), (0.0, 1.0, 0.0)]
        plotter.camera.parallel_scale = ch / 2 * units_per_px
        plotter.camera.clipping_range = (1e-3 * depth, 10 * depth)


def _curve_pv(pv, plotter, pts, color, width, tubes: bool) -> None:
    plotter.add_mesh(pv.lines_from_points(pts, close=True), color=color, line_width=width,
                     render_lines_as_tubes=tubes, lighting=tubes, reset_camera=False)


def _mark_pv(pv, plotter, start, forward, color, scene: _Scene, lift: float, *, filled: bool) -> None:
    s = np.asarray(start, dtype=float) + [0, 0, lift]
    d = np.asarray(forward, dtype=float) - np.asarray(start, dtype=float)
    n = float(np.linalg.norm(d))
    if n > 0:
        arrow = pv.Arrow(start=s, direction=d / n, scale=scene.arrow, tip_length=0.35, tip_radius=0.2,
                         shaft_radius=0.07)
        plotter.add_mesh(arrow, color=color, lighting=not scene.planar, reset_camera=False)
    plotter.add_points(s[None, :], color=color, point_size=14 if filled else 12,
                       render_points_as_spheres=True, reset_camera=False)


# --------------------------------------------------------------------------- matrix

def _matrix_size(n: int) -> tuple[int, int]:
    side = int(np.clip(8 * n + 360, 800, 3000))
    return min(side + 120, 3000), side


def render_matrix(matrix: np.ndarray, labels: Sequence[str], path, *, size: tuple[int, int] | None = None,
                  title: str | None = None) -> RenderResult:
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
    size = _matrix_size(m.shape[0]) if size is None else _check_size(size)
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
    fig = _new_figure(size, layout="constrained")
    ax = fig.add_subplot()
    lo = min(0.0, float(m.min()))
    hi = float(m.max())
    image = ax.imshow(m, cmap="gray", vmin=lo, vmax=hi if hi > lo else lo + 1.0, interpolation="nearest",
                      aspect="equal")
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
    for spine in ax.spines.values():        # a frame, so the palest (farthest) cells show
        spine.set_color("#808080")
        spine.set_linewidth(0.8)
    if title:
        ax.set_title(title, fontsize=12)
    bar = fig.colorbar(image, ax=ax, shrink=0.8, pad=0.02, fraction=0.05)
    bar.set_label("distance (darker = more similar)", fontsize=10)
    bar.ax.tick_params(labelsize=9)
    if every > 1:
        fig.text(0.995, 0.005, f"one label in {every} shown", ha="right", va="bottom", fontsize=8,
                 color=_NOTE_COLOR)
    return _png_bytes(fig, fmt)
