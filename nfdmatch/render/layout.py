"""What a picture shows, independent of the renderer: the checked inputs
(:class:`~nfdmatch.records.ShownMatch`), labels, output paths, and the scene (panel grid, view, limits)
that both backends draw."""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from typing import Any, Sequence, TYPE_CHECKING

import numpy as np

from ..descriptors import START_STEP, points_at
from ..errors import ParameterError, WriteError
from ..records import ShownMatch

if TYPE_CHECKING:
    from numpy.typing import ArrayLike
    from collections.abc import Sequence


RENDERERS = ("matplotlib", "pyvista")
DEFAULT_RENDERER = "matplotlib"

#: picture sizes accepted, pixels per side
MIN_SIDE, MAX_SIDE = 100, 10000
#: characters of a shortened id in a panel title / on a matrix axis
LABEL_WIDTH = 32
MATRIX_LABEL_WIDTH = 28

QUERY_COLOR = "#1f4e9c"  # the query, in its own panel
UNDER_COLOR = "#9c9c9c"  # the query under a match
MATCH_COLOR = "#d1421b"  # a match
TEXT_COLOR = "#1a1a1a"
NOTE_COLOR = "#555555"
_TILT = math.radians(30.0)  # 3-D view: tilt of the camera away from the smallest axis
_ARROW = 0.11  # arrow length, fraction of the larger side of the view


#: the old name of :class:`~nfdmatch.records.ShownMatch`, which drawing reads (deprecated)
MatchPanel = ShownMatch


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
        text, selector = text[: m.start()], m.group(0)
    base = re.split(r"[\\/]", text.rstrip("\\/"))[-1] or text
    return _ellipsize(base + selector, width)


def short_labels(ids: Sequence[str], width: int = LABEL_WIDTH) -> list[str]:
    """:func:`short_label` of each id; ids whose base names collide keep as many parent
    folders as it takes to tell them apart (``a/x.csv``, ``b/x.csv``)."""
    ids = [str(i) for i in ids]
    labels = [short_label(i, 10**6) for i in ids]
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
    return _distinct_cuts(labels, ids, width)


def _distinct_cuts(labels: list[str], ids: list[str], width: int) -> list[str]:
    """Each label cut to ``width`` (:func:`_ellipsize`); labels of different ids that the
    cut made equal are cut around where they differ instead (a section number, a sign in
    the middle of a long name), so that two panels never carry the same title."""
    cut = [_ellipsize(label, width) for label in labels]
    groups: dict[str, set] = {}
    for text, curve_id in zip(cut, ids):
        groups.setdefault(text, set()).add(curve_id)
    for text, members in groups.items():
        if len(members) < 2:
            continue
        clash = [k for k, t in enumerate(cut) if t == text]
        full = [labels[k] for k in clash]
        start = len(os.path.commonprefix(full))  # the first character that tells them apart
        for k in clash:
            cut[k] = _window(labels[k], start, width)
    seen: dict[str, set] = {}
    for text, curve_id in zip(cut, ids):
        seen.setdefault(text, set()).add(curve_id)
    # still equal (ids that differ in several far-apart places): whole, however long
    return [labels[k] if len(seen[t]) > 1 else t for k, t in enumerate(cut)]


def _window(text: str, at: int, width: int) -> str:
    """``width`` characters of ``text`` that include position ``at`` (a third of the way in),
    with an ellipsis for each side cut away."""
    width = max(int(width), 5)
    if len(text) <= width:
        return text
    keep = width - 2  # room for an ellipsis on both sides
    begin = min(max(at - keep // 3, 0), len(text) - (width - 1))
    if begin == 0:
        return text[: width - 1] + "\u2026"
    if begin + width - 1 >= len(text):
        return "\u2026" + text[len(text) - (width - 1) :]
    return "\u2026" + text[begin : begin + keep] + "\u2026"


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
    if cut_start + cut_end >= shortest:  # nothing distinctive would be left
        return labels
    return [
        ("\u2026" if cut_start else "") + label[cut_start : len(label) - cut_end] + ("\u2026" if cut_end else "")
        for label in labels
    ]


def _ellipsize(text: str, width: int) -> str:
    width = max(int(width), 5)
    if len(text) <= width:
        return text
    tail = (width - 1) // 2
    head = width - 1 - tail
    return text[:head] + "\u2026" + text[len(text) - tail :]


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


def as_vector(x: ArrayLike, what: str) -> np.ndarray:
    try:
        v = np.array(x, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{what}: expected 3 numbers ({exc})") from None
    if v.shape == (2,):
        v = np.append(v, 0.0)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ParameterError(f"{what}: expected 3 finite numbers, got {np.asarray(x).tolist()!r}")
    return v


def check_size(size: Any) -> tuple[int, int]:
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


def picture_format(path: str | os.PathLike[str]) -> str:
    """``"png"``, ``"svg"`` or ``"pdf"``: the format of a picture file, by its extension."""
    return PICTURE_FORMATS.get(os.path.splitext(str(path))[1].lower(), "png")


def check_output(path: str | os.PathLike[str]) -> str:
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
        raise ParameterError(
            f"pictures are written as PNG, SVG or PDF; use a .png, .svg or .pdf file name, not {ext!r}", path=p
        )
    if os.path.isdir(p):
        raise WriteError("cannot write the picture: it is a directory", path=p)
    folder = os.path.dirname(os.path.abspath(p))
    if not os.path.isdir(folder):
        raise WriteError("cannot write the picture: the folder does not exist", path=p)
    return p


def _write(path: str, data: bytes) -> None:
    """Write the picture whole (nfdmatch._io); an identical existing file is kept, with a fresh mtime."""
    from ..formats._chain import write_if_changed

    def produce(temp: str) -> None:
        with open(temp, "wb") as f:
            f.write(data)

    try:
        write_if_changed(path, produce)
    except OSError as exc:
        raise WriteError(f"cannot write the picture: {exc.strerror or exc}", path=path) from None


def check_renderer(renderer: str | None) -> str:
    if renderer != "auto" and renderer not in RENDERERS:
        raise ParameterError(f"renderer must be auto, {' or '.join(RENDERERS)}, got {renderer!r}")
    return renderer


# --------------------------------------------------------------------------- geometry


def is_coplanar(*point_sets: np.ndarray, tol: float = 1e-6) -> bool:
    """True when all points of all sets lie within ``tol`` times their extent (the largest
    side of their bounding box) of one plane.

    Parameters
    ----------
    point_sets : (m_i, 3) (or (m_i, 2), planar by definition) arrays of finite floats.
    tol : relative tolerance.
    """
    if not point_sets:
        raise ParameterError("is_coplanar needs at least one point set")
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
    values, vectors = np.linalg.eigh(cov)  # ascending
    e1, e3 = _canonical(vectors[:, 2]), _canonical(vectors[:, 0])
    e2 = np.cross(e3, e1)
    return np.array([e1, e2, e3]), values[::-1]


@dataclass
class ScenePanel:
    """One panel of a :class:`Scene`: the query alone, or a match over it."""

    title: str  # first line
    subtitle: str  # second line
    points: np.ndarray  # view coordinates (m, 3): x right, y up, z towards the viewer
    start: np.ndarray
    forward: np.ndarray
    is_query: bool


@dataclass
class Scene:
    """Everything both renderers need, in view coordinates."""

    planar: bool
    query: np.ndarray
    query_start: np.ndarray
    query_forward: np.ndarray
    panels: list
    size: tuple
    rows: int
    cols: int
    font_pt: float  # panel title font size (points; 1 pt = 100/72 px at dpi 100)
    title_px: int  # title band height of a panel
    pad_px: int  # padding around the data box of a panel
    window: tuple  # (x0, x1, y0, y1) view limits of a panel's data box, same for all
    zrange: tuple  # depth range of everything drawn
    arrow: float  # arrow length, view units

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


def choose_grid(n: int, size: tuple[int, int], data_w: float, data_h: float) -> tuple[int, int]:
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


def build_scene(query: np.ndarray, query_id: str, panels: list[ShownMatch], size: Sequence[int]) -> Scene:
    """The :class:`Scene` both renderers draw: ``query`` ((n, 3) float64) and the checked
    ``panels`` in view coordinates, the panel grid for ``size`` (width, height) pixels,
    titles and subtitles (what a picture shows, testable without drawing it)."""
    match_points = [p.points for p in panels]
    planar = is_coplanar(query, *match_points)
    everything = np.vstack([query] + match_points)
    extent = float(np.ptp(everything, axis=0).max()) or 1.0
    centre, _ = _moments(query)
    view = _view_rotation(query, everything, planar, centre, extent)

    def to_view(p):
        return (np.asarray(p) - centre) @ view.T

    q = to_view(query)
    q_start, q_forward = q[0], to_view(points_at(query, [START_STEP])[0])
    # shortened together: long names that differ in the middle keep that middle
    qlabel, *match_labels = short_labels([query_id] + [p.id for p in panels])
    scene_panels = [
        ScenePanel(
            title=f"query: {qlabel}",
            subtitle=_key(planar, bool(panels)),
            points=q,
            start=q_start,
            forward=q_forward,
            is_query=True,
        )
    ]
    for rank, p in enumerate(panels, 1):
        flags = [f for f, on in (("reversed", p.reversed), ("mirrored", p.mirrored), (p.note, bool(p.note))) if on]
        scene_panels.append(
            ScenePanel(
                title=f"{rank}. {match_labels[rank - 1]}",
                subtitle="  \u00b7  ".join([f"d = {_format_distance(p.distance)}"] + flags),
                points=to_view(p.points),
                start=to_view(p.start),
                forward=to_view(p.forward),
                is_query=False,
            )
        )
    allv = np.vstack([sp.points for sp in scene_panels] + [np.array([sp.start for sp in scene_panels])])
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    dw, dh = max(hi[0] - lo[0], 1e-12 * extent), max(hi[1] - lo[1], 1e-12 * extent)
    # room for the arrows and markers around the curves
    margin = 0.06 * max(dw, dh)
    dw, dh = dw + 2 * margin, dh + 2 * margin
    rows, cols = choose_grid(len(scene_panels), size, dw, dh)
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
    return Scene(
        planar=planar,
        query=q,
        query_start=q_start,
        query_forward=q_forward,
        panels=scene_panels,
        size=tuple(size),
        rows=rows,
        cols=cols,
        font_pt=font,
        title_px=title_px,
        pad_px=pad,
        window=(cx - hw, cx + hw, cy - hh, cy + hh),
        zrange=(float(lo[2]), float(hi[2])),
        arrow=_ARROW * max(dw, dh) / (1 + 0.12),
    )


def _view_rotation(query, everything, planar: bool, centre, extent: float) -> np.ndarray:
    """The (3, 3) rotation into view coordinates: the identity for curves already in the
    x, y plane; else the query's principal axes (of everything for a straight query),
    tilted by :data:`_TILT` when the curves are not planar."""
    if planar and np.abs(everything[:, 2] - centre[2]).max() <= 1e-6 * extent:
        return np.eye(3)  # already in the x, y plane
    axes, spread = _principal_axes(query)
    if spread[1] <= 1e-12 * max(spread[0], 1e-300):  # a straight query: use everything
        vt = np.linalg.svd(everything - everything.mean(axis=0), full_matrices=True)[2]
        e1, e3 = _canonical(vt[0]), _canonical(vt[2])
        axes = np.array([e1, np.cross(e3, e1), e3])
    if planar:
        return axes
    e1, e2, e3 = axes
    c, s = math.cos(_TILT), math.sin(_TILT)
    return np.array([e1, c * e2 + s * e3, -s * e2 + c * e3])


def _key(planar: bool, matches: bool) -> str:
    """The query panel's second line: how to read the picture."""
    parts = ["\u25cb start  \u2192 direction"]
    if matches:
        parts.append("grey: query")
    if not planar:
        parts.append("nearer = darker")
    return "  \u00b7  ".join(parts)


def screen_direction(start: np.ndarray, forward: np.ndarray) -> np.ndarray | None:
    d = (forward - start)[:2]
    n = float(np.hypot(*d))
    full = float(np.linalg.norm(forward - start))
    if full == 0.0 or n < 0.05 * full:
        return None  # along the line of sight: no readable arrow
    return d / n


class Unavailable(RuntimeError):
    """A renderer that cannot work here; the message says why (shown as is)."""


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if isinstance(exc, Unavailable):
        return text
    if isinstance(exc, ImportError):
        return f"{getattr(exc, 'name', None) or 'it'} is not installed" + (f": {text}" if text else "")
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
