"""A batch of queries and their matches as one self-contained HTML page (``nfdmatch
report``): a summary, a table of the queries, then per query its picture strip (the query,
then each match aligned onto it, drawn as ``show`` draws them: :mod:`nfdmatch.render.svg`)
and its rows, with links between queries.

Self-contained: styles, pictures (inline SVG) and a small script are in the file; nothing
is fetched. The script only sorts tables (click a heading) and filters by distance (also
from the address: ``report.html?max=0.1``); the page reads the same without it. A page
of a thousand queries stays light for the browser: each query's section is laid out and
painted only near the viewport (``content-visibility``).
"""

from __future__ import annotations

import functools
import html
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._io import write_file
from .curve import Curve
from .errors import WriteError
from .records import RankedMatch, ShownMatch

__all__ = ["ReportQuery", "report_query", "report_html", "write_report", "cached_reader"]


@dataclass
class ReportQuery:
    """One query of a report: its curve, its matches aligned onto it (``shown``, drawn),
    its ``rows`` (one dict per match, the page's columns; ``distance`` filters), and
    ``notes`` (e.g. a match drawn from the index's harmonics, and why). ``key`` names the
    query's curve however it is spelled (default: its id): a row whose ``"key"`` is a
    query's key links to that query's section."""

    id: str
    points: np.ndarray
    shown: list[ShownMatch]
    rows: list[dict]
    notes: list[str] = field(default_factory=list)
    key: str | None = None


def cached_reader(read_curve: Callable[..., Curve], files: int = 256) -> Callable[[str], Curve]:
    """``spec -> Curve`` reading each file once (its curves kept for the ``files`` most
    recently used files): a batch's matches name the same files again and again, and a
    ``file#i`` of a multi-curve file would otherwise read the whole file for each curve."""
    from .formats import read_curves, split_selector

    @functools.lru_cache(maxsize=files)
    def whole(path: str) -> tuple[Curve, ...]:
        return tuple(read_curves(path))

    @functools.lru_cache(maxsize=16 * files)
    def alone(spec: str) -> Curve:
        return read_curve(spec)

    def read(spec: str) -> Curve:
        path, selected = split_selector(spec)
        if selected is None:
            return alone(spec)
        curves = whole(path)
        if not 0 <= selected < len(curves):
            return read_curve(spec)  # its own error message
        return curves[selected]

    return read


def report_query(
    query: Curve,
    matches: Sequence[RankedMatch],
    index: Any,
    rows: list[dict],
    *,
    method: str = "exact",
    direction: str = "invariant",
    mirror: bool = False,
    read_curve: Callable[[str], Curve] | None = None,
) -> ReportQuery:
    """A query of a report from one query's matches in ``index`` (aligned onto it as
    ``show`` aligns them: from their files, or the index's harmonics when a file is gone or
    changed) and its ``rows``."""
    from .show import matches_from_index

    shown, notes = matches_from_index(
        query, list(matches), index, method=method, direction=direction, mirror=mirror, read_curve=read_curve
    )
    return ReportQuery(query.id, query.points, shown, rows, notes)


_STYLE = """
body{font:14px/1.4 system-ui,-apple-system,"Segoe UI",sans-serif;color:#1a1a1a;margin:0 auto;max-width:1400px;
padding:0 16px 48px}
h1{font-size:22px;margin:16px 0 4px}h2{font-size:16px;margin:0 0 6px;word-break:break-all}
code,.mono{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:12.5px}
dl.summary{display:grid;grid-template-columns:max-content 1fr;gap:2px 14px;margin:8px 0 16px}
dl.summary dt{color:#555}dl.summary dd{margin:0;word-break:break-all}
table{border-collapse:collapse;margin:4px 0 8px}th,td{padding:2px 8px;text-align:left;border-bottom:1px solid #e4e4e4}
th{background:#f4f4f4;position:sticky;top:0}td.n{text-align:right;font-variant-numeric:tabular-nums}
table.sortable th{cursor:pointer}table.sortable th[data-dir=asc]::after{content:" \\25B2"}
table.sortable th[data-dir=desc]::after{content:" \\25BC"}
section.query{border-top:2px solid #ddd;padding:12px 0;content-visibility:auto;contain-intrinsic-size:auto 520px}
nav.steps{font-size:13px;margin-bottom:6px}nav.steps a{margin-right:12px}
.strip{display:flex;flex-wrap:wrap;gap:8px;margin:6px 0}
figure{margin:0;border:1px solid #e4e4e4;border-radius:4px;padding:4px;background:#fff}
figcaption{font-size:12px;max-width:204px;overflow:hidden;text-overflow:ellipsis;white-space:nowrap}
figcaption small{display:block;color:#555}
.notes{color:#555;font-size:12.5px}#tools{margin:8px 0;padding:8px;background:#f7f7f7;border-radius:4px}
#tools input{width:8em}
"""

_SCRIPT = """
(function(){
  function key(c){var v=c.getAttribute('data-v');return v===null?c.textContent.trim():v}
  document.querySelectorAll('table.sortable th').forEach(function(th){
    th.addEventListener('click',function(){
      var t=th.closest('table'),b=t.tBodies[0],i=th.cellIndex,asc=th.getAttribute('data-dir')!=='asc';
      t.querySelectorAll('th').forEach(function(h){h.removeAttribute('data-dir')});
      th.setAttribute('data-dir',asc?'asc':'desc');
      var rows=Array.prototype.slice.call(b.rows);
      rows.sort(function(x,y){var a=key(x.cells[i]),c=key(y.cells[i]),na=parseFloat(a),nc=parseFloat(c);
        var r=(isNaN(na)||isNaN(nc))?a.localeCompare(c):na-nc;return asc?r:-r});
      rows.forEach(function(r){b.appendChild(r)});
    });
  });
  var tools=document.getElementById('tools'),f=document.getElementById('maxd'),said=document.getElementById('shown');
  tools.hidden=false;
  function apply(){
    var m=parseFloat(f.value),n=0;
    document.querySelectorAll('[data-d]').forEach(function(e){
      var keep=isNaN(m)||parseFloat(e.getAttribute('data-d'))<=m;e.hidden=!keep;
      if(keep&&e.classList.contains('qrow'))n++;});
    said.textContent=n+' of '+document.querySelectorAll('.qrow').length+' queries shown';
  }
  // report.html?max=D opens the page filtered (a link that shows only the close matches)
  var given=new URLSearchParams(location.search).get('max');if(given!==null)f.value=given;
  f.addEventListener('input',apply);apply();
})();
"""


#: queries up to which the table of queries starts unfolded
OPEN_OVERVIEW = 50


def _id_of(n: int) -> str:
    return f"q{n}"


def _number(value: Any) -> str:
    if isinstance(value, float):
        return "inf" if not np.isfinite(value) else f"{value:.6g}"
    return html.escape(str(value))


def _cell(column: str, value: Any, link: str | None = None) -> str:
    if value is None:
        return "<td></td>"
    if isinstance(value, bool):
        return f"<td>{'yes' if value else 'no'}</td>"
    if isinstance(value, (int, float)):
        return f'<td class="n" data-v="{value!r}">{_number(value)}</td>'
    text = html.escape(str(value))
    if link is not None:
        text = f'<a href="#{link}">{text}</a>'
    return f'<td class="mono">{text}</td>'


def report_html(queries: Sequence[ReportQuery], columns: Sequence[str], summary: dict[str, Any]) -> str:
    """The page (str). ``columns``: the per-match columns shown, in order (``distance``
    among them); ``summary``: label -> value of the page's summary, in order (``title``,
    if present, is the page's title)."""
    from .render.svg import SVG_STYLE, panel_svgs

    title = str(summary.get("title", "nfdmatch report"))
    where = {q.key or q.id: _id_of(n) for n, q in enumerate(queries, start=1)}
    out = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width,initial-scale=1">',
        # nothing may be fetched: the page is one file, read anywhere
        "<meta http-equiv=\"Content-Security-Policy\" content=\"default-src 'none'; style-src 'unsafe-inline'; "
        "script-src 'unsafe-inline'; img-src data:\">",
        f"<title>{html.escape(title)}</title>",
        f"<style>{_STYLE.strip()}{SVG_STYLE}</style></head><body>",
        f'<h1 id="top">{html.escape(title)}</h1>',
        '<dl class="summary">',
    ]
    for label, value in summary.items():
        if label != "title":
            out.append(f"<dt>{html.escape(str(label))}</dt><dd>{_number(value)}</dd>")
    out.append("</dl>")
    out.append(
        '<div id="tools" hidden><label>distance at most <input id="maxd" type="number" min="0" step="any" '
        'placeholder="any"></label> <span id="shown"></span> &middot; click a column heading to sort</div>'
    )
    # a long batch's table is folded: the first screen then shows pictures
    opened = " open" if len(queries) <= OPEN_OVERVIEW else ""
    out.append(
        f'<details id="queries"{opened}><summary><h2 style="display:inline">Queries ({len(queries)})</h2></summary>'
    )
    out.append('<table class="sortable"><thead><tr>')
    out.append("<th>#</th><th>query</th><th>matches</th><th>best match</th><th>best distance</th></tr></thead><tbody>")
    for n, q in enumerate(queries, start=1):
        best = q.rows[0] if q.rows else None
        d = best["distance"] if best else float("inf")
        out.append(
            f'<tr class="qrow" data-d="{d!r}"><td class="n" data-v="{n}">{n}</td>'
            f'{_cell("query", q.id, _id_of(n))}<td class="n" data-v="{len(q.rows)}">{len(q.rows)}</td>'
            f"{_cell('match', best['match'] if best else None, _link(best, where))}"
            f"{_cell('distance', d)}</tr>"
        )
    out.append("</tbody></table></details>")
    for n, q in enumerate(queries, start=1):
        out.append(_section(n, q, len(queries), columns, where, panel_svgs))
    out.append(f"<script>{_SCRIPT.strip()}</script></body></html>")
    return "\n".join(out) + "\n"


def _link(row: dict | None, where: dict) -> str | None:
    """The section a row's match links to: the query that is the same curve, if any."""
    if row is None:
        return None
    return where.get(row.get("key", row.get("match")))


def _section(n: int, q: ReportQuery, total: int, columns: Sequence[str], where: dict, panel_svgs) -> str:
    best = q.rows[0]["distance"] if q.rows else float("inf")
    steps = [f'<a href="#{_id_of(n - 1)}">&larr; previous</a>' if n > 1 else ""]
    steps.append('<a href="#queries">all queries</a>')
    steps.append(f'<a href="#{_id_of(n + 1)}">next &rarr;</a>' if n < total else "")
    parts = [
        f'<section class="query" id="{_id_of(n)}" data-d="{best!r}">',
        f'<nav class="steps">{"".join(steps)}</nav>',
        f'<h2><span class="mono">{html.escape(q.id)}</span> <small>(query {n} of {total})</small></h2>',
        '<div class="strip">',
    ]
    for panel, shown in zip(panel_svgs(q.points, q.id, q.shown, _id_of(n)), [None, *q.shown]):
        d = "" if shown is None else f' data-d="{shown.distance!r}"'
        parts.append(
            f'<figure{d}>{panel.svg}<figcaption title="{html.escape(panel.title)}">{html.escape(panel.title)}'
            f"<small>{html.escape(panel.subtitle)}</small></figcaption></figure>"
        )
    parts.append("</div>")
    if q.notes:
        parts.append('<p class="notes">' + "<br>".join(html.escape(m) for m in q.notes) + "</p>")
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    parts.append(f'<table class="sortable"><thead><tr>{head}</tr></thead><tbody>')
    for row in q.rows:
        cells = "".join(_cell(c, row.get(c), _link(row, where) if c == "match" else None) for c in columns)
        parts.append(f'<tr data-d="{row["distance"]!r}">{cells}</tr>')
    parts.append("</tbody></table></section>")
    return "\n".join(parts)


def write_report(
    path: str | os.PathLike[str], queries: Sequence[ReportQuery], columns: Sequence[str], summary: dict[str, Any]
) -> int:
    """Write the page at ``path`` (whole, atomically); returns its size in bytes.

    Raises WriteError when the file cannot be written."""
    data = report_html(queries, columns, summary).encode("utf-8")
    try:
        write_file(path, data)
    except OSError as exc:
        raise WriteError(f"cannot write the report: {exc.strerror or exc}", path=os.fspath(path)) from None
    return len(data)
