"""Small inline SVG pictures of a query and its aligned matches, for HTML pages
(``nfdmatch report``): the scene of ``show`` (:func:`.layout.build_scene`: the same view,
labels and alignment) drawn as one small ``<svg>`` per panel, with no library but numpy.

A page of a thousand queries holds thousands of these, so each is kept small: curves
decimated to :data:`MAX_POINTS` vertices, integer coordinates, and the query's outline
written once per query (``<symbol>``-like ``<defs>``) and reused (``<use>``) under each
match. Colours are those of ``show`` (:data:`.layout.QUERY_COLOR`, ...), set by classes the
page's style sheet defines (:data:`SVG_STYLE`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..records import ShownMatch
from .layout import MATCH_COLOR, QUERY_COLOR, UNDER_COLOR, Scene, build_scene, screen_direction

__all__ = ["PanelSvg", "panel_svgs", "SVG_STYLE", "MAX_POINTS", "PANEL_SIZE"]

#: vertices drawn per curve at most (evenly spaced along the curve's vertices)
MAX_POINTS = 160
#: the viewBox of a panel, and its size on the page in CSS pixels (integer coordinates are
#: then finer than a pixel)
PANEL_SIZE = (480, 400)
DRAWN = (204, 170)

#: the classes the pictures use, for the page's <style>
SVG_STYLE = (
    f"svg.nfd{{display:block}}"
    f"svg.nfd .q{{fill:none;stroke:{QUERY_COLOR};stroke-width:4;stroke-linejoin:round}}"
    f"svg.nfd .u{{fill:none;stroke:{UNDER_COLOR};stroke-width:3;stroke-linejoin:round}}"
    f"svg.nfd .m{{fill:none;stroke:{MATCH_COLOR};stroke-width:4;stroke-linejoin:round}}"
    f"svg.nfd .sq{{fill:#fff;stroke:{QUERY_COLOR};stroke-width:3}}"
    f"svg.nfd .sm{{fill:{MATCH_COLOR};stroke:none}}"
    f"svg.nfd .aq{{fill:{QUERY_COLOR}}}"
    f"svg.nfd .am{{fill:{MATCH_COLOR}}}"
)


@dataclass(frozen=True)
class PanelSvg:
    """One panel: ``svg`` the picture's markup; ``title`` and ``subtitle`` its labels (as
    ``show`` writes them); ``is_query`` for the query's own panel."""

    svg: str
    title: str
    subtitle: str
    is_query: bool


def _decimated(points: np.ndarray) -> np.ndarray:
    if len(points) <= MAX_POINTS:
        return points
    return points[np.linspace(0, len(points), MAX_POINTS, endpoint=False).astype(np.int64)]


class _Frame:
    """View coordinates -> the panel's integer coordinates (y down), one for every panel
    of a query: the same limits and equal aspect, as ``show`` draws them."""

    def __init__(self, scene: Scene):
        everything = np.vstack([p.points[:, :2] for p in scene.panels])
        lo, hi = everything.min(axis=0), everything.max(axis=0)
        span = np.maximum(hi - lo, 1e-12 * max(float(np.ptp(everything)), 1e-300))
        w, h = PANEL_SIZE
        margin = 0.08
        self.scale = (1 - 2 * margin) * min(w / span[0], h / span[1])
        self.centre = (lo + hi) / 2
        self.arrow = 0.07 * max(w, h)

    def xy(self, points: np.ndarray) -> np.ndarray:
        w, h = PANEL_SIZE
        p = (np.atleast_2d(points)[:, :2] - self.centre) * self.scale
        return np.column_stack([w / 2 + p[:, 0], h / 2 - p[:, 1]])

    def polyline(self, points: np.ndarray) -> str:
        return " ".join(f"{x},{y}" for x, y in np.rint(self.xy(_decimated(points))).astype(np.int64).tolist())

    def marks(self, start: np.ndarray, forward: np.ndarray, circle: str, arrow: str) -> str:
        """The start circle and the arrow of the direction of travel (none when the
        direction is along the line of sight)."""
        ((sx, sy),) = self.xy(start)
        out = f'<circle class="{circle}" cx="{sx:.0f}" cy="{sy:.0f}" r="7"/>'
        d = screen_direction(np.asarray(start, float), np.asarray(forward, float))
        if d is not None:
            d = np.array([d[0], -d[1]])  # y down
            n = np.array([-d[1], d[0]])
            base = np.array([sx, sy]) + d * 10
            tip = base + d * self.arrow
            wing = tip - d * 14
            pts = [tip, wing + n * 7, wing - n * 7]
            (x1, y1), (x2, y2) = base, wing
            body = f'<line x1="{x1:.0f}" y1="{y1:.0f}" x2="{x2:.0f}" y2="{y2:.0f}" class="{circle[-1]}"/>'
            out += body + f'<polygon class="{arrow}" points="{" ".join(f"{x:.0f},{y:.0f}" for x, y in pts)}"/>'
        return out


def panel_svgs(query: np.ndarray, query_id: str, shown: Sequence[ShownMatch], key: str) -> list[PanelSvg]:
    """The query's panel, then one per match, as ``<svg>`` markup. ``key``: a name unique
    in the page (an HTML id: letters, digits, ``-``) for the query's outline the match
    panels reuse."""
    w, h = PANEL_SIZE
    scene = build_scene(np.asarray(query, dtype=np.float64), query_id, list(shown), (w * (len(shown) + 1), h))
    frame = _Frame(scene)
    outline = f"o-{key}"
    head = f'<svg class="nfd" viewBox="0 0 {w} {h}" width="{DRAWN[0]}" height="{DRAWN[1]}" role="img"'
    first = scene.panels[0]
    # no depth shading here: the key says only what these pictures show
    key_text = "  \u00b7  ".join(part for part in first.subtitle.split("  \u00b7  ") if "darker" not in part)
    panels = [
        PanelSvg(
            f'{head} aria-label="the query"><defs><polyline id="{outline}" points="{frame.polyline(first.points)} '
            f'{frame.polyline(first.points[:1])}"/></defs><use href="#{outline}" class="q"/>'
            f"{frame.marks(first.start, first.forward, 'sq', 'aq')}</svg>",
            first.title,
            key_text,
            True,
        )
    ]
    for p in scene.panels[1:]:
        closed = frame.polyline(p.points) + " " + frame.polyline(p.points[:1])
        panels.append(
            PanelSvg(
                f'{head} aria-label="a match over the query"><use href="#{outline}" class="u"/>'
                f'<polyline class="m" points="{closed}"/>{frame.marks(p.start, p.forward, "sm", "am")}</svg>',
                p.title,
                p.subtitle,
                False,
            )
        )
    return panels
