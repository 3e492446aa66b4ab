"""The matplotlib backend (the default): a scene drawn with Agg into PNG, SVG or PDF
bytes; 3-D views projected here and drawn far to near with halos at crossings."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import io

import numpy as np

from .layout import MATCH_COLOR, NOTE_COLOR, QUERY_COLOR, Scene, TEXT_COLOR, UNDER_COLOR, screen_direction

if TYPE_CHECKING:
    from collections.abc import Sequence
    from matplotlib.figure import Figure

# --------------------------------------------------------------------------- matplotlib


def new_figure(size: Sequence[float], **kwargs: Any) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100.0, size[1] / 100.0), dpi=100, facecolor="white", **kwargs)
    FigureCanvasAgg(fig)
    return fig


def png_bytes(fig: Figure, fmt: str = "png") -> bytes:
    """The figure as PNG, SVG or PDF bytes; the same figure gives the same bytes (no date in
    the metadata, fixed SVG ids), so an unchanged picture keeps its file's bytes."""
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
        j = min(i + per + 1, n)  # one sub-edge of overlap with the next piece
        chunk = dense[i : j + 1]
        paths.append(chunk[:, :2])
        depth.append(float(chunk[:, 2].mean()))
    return paths, np.array(depth)


def _draw_curve_mpl(ax, pts, color, lw_pt, *, depth: bool, zrange, zorder: float, halo: bool):
    from matplotlib.collections import LineCollection

    if not depth:
        closed = np.vstack([pts, pts[:1]])
        ax.plot(
            closed[:, 0],
            closed[:, 1],
            color=color,
            lw=lw_pt,
            solid_joinstyle="round",
            solid_capstyle="round",
            zorder=zorder,
        )
        return
    paths, z = _depth_pieces(pts)
    z0, z1 = zrange
    near = (z - z0) / (z1 - z0) if z1 > z0 else np.ones_like(z)
    order = np.argsort(z, kind="stable")  # far first
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
    ax.add_collection(
        LineCollection(segs, colors=cols, linewidths=lws, capstyle="butt", joinstyle="round", zorder=zorder)
    )


def _mark_mpl(ax, start, forward, color, arrow_len, *, filled: bool, zorder: float):
    from matplotlib.patches import FancyArrowPatch

    d = screen_direction(start, forward)
    if d is not None:
        end = start[:2] + arrow_len * d
        ax.add_patch(
            FancyArrowPatch(
                tuple(start[:2]),
                tuple(end),
                arrowstyle="-|>",
                mutation_scale=17,
                lw=2.2,
                color=color,
                shrinkA=0,
                shrinkB=0,
                zorder=zorder,
            )
        )
    ax.plot(
        [start[0]],
        [start[1]],
        marker="o",
        ms=8.5,
        mew=2.0,
        zorder=zorder + 0.1,
        mfc=color if filled else "white",
        mec="white" if filled else color,
    )


def draw_matplotlib(scene: Scene, fmt: str = "png") -> bytes:
    fig = new_figure(scene.size)
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
            _draw_curve_mpl(ax, panel.points, QUERY_COLOR, 2.2, depth=depth, zrange=scene.zrange, zorder=2, halo=True)
            _mark_mpl(ax, panel.start, panel.forward, QUERY_COLOR, scene.arrow, filled=False, zorder=5)
        else:
            _draw_curve_mpl(ax, scene.query, UNDER_COLOR, 1.2, depth=False, zrange=scene.zrange, zorder=1, halo=False)
            _draw_curve_mpl(ax, panel.points, MATCH_COLOR, 2.2, depth=depth, zrange=scene.zrange, zorder=2, halo=True)
            _mark_mpl(ax, scene.query_start, scene.query_forward, UNDER_COLOR, scene.arrow, filled=False, zorder=4)
            _mark_mpl(ax, panel.start, panel.forward, MATCH_COLOR, scene.arrow, filled=True, zorder=5)
        top = 1 - r * ch / H
        cx = (c + 0.5) * cw / W
        line = 1.3 * scene.font_pt * 100 / 72 / H
        texts.append(
            fig.text(
                cx,
                top - 4 / H,
                panel.title,
                ha="center",
                va="top",
                fontsize=scene.font_pt,
                color=TEXT_COLOR,
                fontweight="bold" if panel.is_query else "normal",
            )
        )
        if panel.subtitle:
            texts.append(
                fig.text(
                    cx,
                    top - 4 / H - line,
                    panel.subtitle,
                    ha="center",
                    va="top",
                    fontsize=scene.font_pt * 0.92,
                    color=NOTE_COLOR,
                )
            )
    _fit_texts(fig, texts, cw - 6)
    return png_bytes(fig, fmt)


def _fit_texts(fig, texts, max_px: float) -> None:
    """Shrink the font of any text wider than ``max_px`` pixels until it fits."""
    renderer = fig.canvas.get_renderer()
    for text in texts:
        width = text.get_window_extent(renderer=renderer).width
        if width > max_px:
            text.set_fontsize(max(4.0, text.get_fontsize() * max_px / width * 0.98))
