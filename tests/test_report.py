"""`nfdmatch report` (issue 37, item 1): one self-contained HTML page of a batch, its
structure read back from the markup, and the page drawn by a real browser (headless
Chromium): the screenshot shows the pictures."""

from __future__ import annotations

import html
import os
import re
import shutil
import subprocess

import numpy as np
import pytest
from conftest import ROOT, run_cli

CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if os.path.exists("/usr/bin/chromium") else None)


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    home = tmp_path_factory.mktemp("report")
    shutil.copytree(os.path.join(ROOT, "sample_curves"), home / "sample_curves")
    index = str(home / "lib.h5")
    code, _, err = run_cli("index", "build", home / "sample_curves" / "library", "--index", index, "--graph", "8")
    assert code == 0, err
    return home, index


def _report(library, *args):
    home, index = library
    out = str(home / f"r{abs(hash(args))}.html")
    code, stdout, err = run_cli("report", *args, "--index", index, "-o", out)
    return code, stdout, err, out


def _sections(page: str) -> list[str]:
    return re.findall(r'<section class="query".*?</section>', page, flags=re.S)


def test_a_report_holds_every_query_its_pictures_and_rows(library):
    home, _ = library
    code, stdout, err, out = _report(library, home / "sample_curves" / "queries", "--top", "4")
    assert code == 0, err
    assert stdout == ""  # stdout is data: the page goes to its file, the message to stderr
    assert "wrote" in err and "3 queries" in err
    page = open(out, encoding="utf-8").read()
    sections = _sections(page)
    assert len(sections) == 3
    for section in sections:
        assert section.count('<svg class="nfd"') == 5  # the query, then its 4 matches
        assert len(re.findall(r'<tr data-d="', section)) == 4
        assert "<use href=" in section  # the query under each match
        distances = [float(d) for d in re.findall(r'<tr data-d="([^"]+)"', section)]
        assert distances == sorted(distances)
    # the overview names the queries and links to each section
    assert [f"#q{n}" for n in (1, 2, 3)] == re.findall(r'<td class="mono"><a href="(#q\d+)">', page)[:3]
    # the trefoil query's best match is the trefoil
    (trefoil,) = [s for s in sections if "trefoil-posed" in s]
    first_row = re.search(r'<tr data-d="[^"]+">(.*?)</tr>', trefoil).group(1)
    assert "trefoil" in html.unescape(first_row)


def test_the_page_is_self_contained(library):
    home, _ = library
    code, _, err, out = _report(library, home / "sample_curves" / "queries" / "trefoil-posed.obj")
    assert code == 0, err
    page = open(out, encoding="utf-8").read()
    links = re.findall(r'(?:src|href)\s*=\s*"([^"]*)"', page)
    assert links and all(link.startswith("#") for link in links)
    assert "http://" not in page and "https://" not in page and "@import" not in page and "url(" not in page
    assert "default-src 'none'" in page  # the browser is told to fetch nothing
    assert page.count("<script>") == 1 and page.count("<style>") == 1


def test_the_stage_columns_and_links_between_queries(library):
    home, _ = library
    lib = home / "sample_curves" / "library"
    code, _, err, out = _report(library, lib, "--exclude-self", "--elastic", "--elastic-depth", "10", "--top", "3")
    assert code == 0, err
    page = open(out, encoding="utf-8").read()
    heads = re.findall(r"<th>(.*?)</th>", _sections(page)[0])
    assert heads[:5] == ["rank", "match", "distance", "elastic", "fused"]
    assert len(_sections(page)) == 24
    # every match is also a query of the page: its name links to that query's section
    section = _sections(page)[0]
    assert len(re.findall(r'<td class="mono"><a href="#q\d+">', section)) == 3
    code, _, err, out = _report(library, lib, "--exclude-self", "--rerank", "--top", "3")
    assert code == 0, err
    assert re.findall(r"<th>(.*?)</th>", _sections(open(out, encoding="utf-8").read())[0])[:4] == [
        "rank",
        "match",
        "distance",
        "score",
    ]


def test_the_report_is_html_and_needs_every_query(library):
    home, _ = library
    code, _, err, out = _report(library, home / "sample_curves" / "queries")
    assert code == 0
    code, _, err = run_cli("report", home / "sample_curves" / "queries", "--index", library[1], "-o", home / "r.png")
    assert code == 2 and "HTML" in err
    bad = home / "bad.csv"
    bad.write_text("x,y,z\n1,2\n")
    before = os.path.getmtime(out)
    code, _, err = run_cli("report", bad, home / "sample_curves" / "queries", "--index", library[1], "-o", out)
    assert code == 3 and "bad.csv" in err
    assert os.path.getmtime(out) == before  # a page of part of a batch is not written


def _chromium_or_skip():
    if CHROMIUM is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing: .ci/run installs it (apt-get install -y chromium)")
        pytest.skip("chromium is not installed (apt-get install -y chromium)")
    return CHROMIUM


def _chromium(chromium: str, profile, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={profile}", *args,
        ],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip


@pytest.mark.slow
def test_chromium_runs_the_script_that_filters_by_distance(library, tmp_path):
    chromium = _chromium_or_skip()
    home, _ = library
    code, _, err, out = _report(library, home / "sample_curves" / "queries", "--top", "5")
    assert code == 0, err
    page = open(out, encoding="utf-8").read()
    best = sorted(float(d) for d in re.findall(r'<tr class="qrow" data-d="([^"]+)"', page))
    limit = (best[1] + best[2]) / 2  # two of the three queries have a match this close
    run = _chromium(chromium, tmp_path / "profile", "--dump-dom", f"file://{out}?max={limit!r}")
    dom = run.stdout
    assert '<div id="tools">' in dom  # shown by the script (hidden without it)
    assert "2 of 3 queries shown" in dom
    hidden = re.findall(r'<section class="query" id="q\d+" data-d="([^"]+)" hidden', dom)
    assert [float(d) for d in hidden] == [best[2]]


_ROWS = """JSON.stringify(Array.prototype.map.call(document.querySelectorAll(%s),
  function(r){return {d: r.getAttribute('data-d'), key: r.cells[%d].getAttribute('data-v') || r.cells[%d].textContent,
                      hidden: r.hidden}}))"""


def _rows(browser, selector: str, key_column: int = 0) -> list[dict]:
    """The rows matching ``selector`` in the page's current order: distance, a key cell, hidden."""
    import json

    return json.loads(browser.evaluate(_ROWS % (json.dumps(selector), key_column, key_column)))


@pytest.mark.slow
def test_chromium_sorts_and_filters_when_clicked(library, tmp_path):
    """The inline script driven in a real browser: mouse clicks on the distance headings,
    typing into the filter; the order and what is shown read back from the page."""
    from devtools import Browser

    chromium = _chromium_or_skip()
    home, _ = library
    lib = home / "sample_curves" / "library"
    code, _, err, out = _report(library, lib, "--exclude-self", "--top", "3")
    assert code == 0, err
    overview = "#queries table tbody tr"
    with Browser(chromium, tmp_path / "profile") as browser:
        browser.open(f"file://{out}")
        rows = _rows(browser, overview)
        assert len(rows) == 24 and not any(r["hidden"] for r in rows)
        distances = [float(r["d"]) for r in rows]
        assert distances != sorted(distances) and distances != sorted(distances, reverse=True)  # not sorted yet
        numbers = [int(r["key"]) for r in rows]
        assert numbers == list(range(1, 25))

        heading = "#queries th:nth-child(5)"  # best distance
        assert browser.evaluate(f"document.querySelector({heading!r}).textContent") == "best distance"
        browser.click(heading)
        rows = _rows(browser, overview)
        assert [float(r["d"]) for r in rows] == sorted(distances)  # ascending
        assert sorted(int(r["key"]) for r in rows) == numbers  # the same rows, moved
        assert browser.evaluate(f"document.querySelector({heading!r}).getAttribute('data-dir')") == "asc"
        browser.click(heading)
        assert [float(r["d"]) for r in _rows(browser, overview)] == sorted(distances, reverse=True)
        assert browser.evaluate(f"document.querySelector({heading!r}).getAttribute('data-dir')") == "desc"
        browser.click("#queries th:nth-child(1)")  # back to the order of the queries: numbers, not text
        assert [int(r["key"]) for r in _rows(browser, overview)] == numbers

        # a query's own rows: rank ascending as written; the distance heading twice: descending
        first = "section#q1 table tbody tr"
        written = [float(r["d"]) for r in _rows(browser, first)]
        assert len(written) == 3 and written == sorted(written)
        browser.click("section#q1 th:nth-child(3)")
        browser.click("section#q1 th:nth-child(3)")
        rows = _rows(browser, first)
        assert [float(r["d"]) for r in rows] == sorted(written, reverse=True)
        assert [int(r["key"]) for r in rows] == [3, 2, 1]  # the rank column moved with its rows

        # the filter: typed into, it hides the queries (rows and sections) and matches beyond it
        limit = float(np.median(distances))
        browser.click("#maxd")
        browser.type_text(repr(limit))
        kept = sum(d <= limit for d in distances)
        assert 0 < kept < 24
        rows = _rows(browser, overview)
        assert sorted(float(r["d"]) for r in rows if not r["hidden"]) == sorted(d for d in distances if d <= limit)
        assert all(float(r["d"]) > limit for r in rows if r["hidden"])
        assert browser.evaluate("document.getElementById('shown').textContent") == f"{kept} of 24 queries shown"
        sections = browser.evaluate(
            "Array.prototype.map.call(document.querySelectorAll('section.query'),"
            "function(s){return [parseFloat(s.getAttribute('data-d')), s.hidden]})"
        )
        assert len(sections) == 24 and all(hidden == (d > limit) for d, hidden in sections)
        match_rows = _rows(browser, "section.query table tbody tr")
        assert match_rows and all(r["hidden"] == (float(r["d"]) > limit) for r in match_rows)
        # cleared, everything shows again
        browser.evaluate("document.getElementById('maxd').select()")
        browser.send("Input.dispatchKeyEvent", {"type": "keyDown", "key": "Backspace", "windowsVirtualKeyCode": 8})
        browser.send("Input.dispatchKeyEvent", {"type": "keyUp", "key": "Backspace", "windowsVirtualKeyCode": 8})
        assert browser.evaluate("document.getElementById('maxd').value") == ""
        assert not any(r["hidden"] for r in _rows(browser, overview))
        assert browser.evaluate("document.getElementById('shown').textContent") == "24 of 24 queries shown"


@pytest.mark.slow
def test_chromium_draws_the_pictures(library, tmp_path):
    from PIL import Image

    from nfdmatch.render.layout import MATCH_COLOR, QUERY_COLOR

    chromium = _chromium_or_skip()
    home, _ = library
    code, _, err, out = _report(library, home / "sample_curves" / "queries", "--top", "5")
    assert code == 0, err
    shot = tmp_path / "shot.png"
    run = _chromium(
        chromium, tmp_path / "profile", "--hide-scrollbars", "--window-size=1400,1600", f"--screenshot={shot}",
        f"file://{out}",
    )  # fmt: skip
    assert shot.exists(), run.stderr[-2000:]
    pixels = np.asarray(Image.open(shot).convert("RGB"), dtype=np.int64)

    def near(color: str) -> int:
        rgb = np.array([int(color[i : i + 2], 16) for i in (1, 3, 5)])
        return int((np.abs(pixels - rgb).sum(axis=2) < 60).sum())

    background = int((pixels.min(axis=2) > 245).sum())
    assert background < pixels.shape[0] * pixels.shape[1]  # something was drawn at all
    # the queries (blue) and the matches over them (orange) were drawn, not only text
    assert near(QUERY_COLOR) > 500 and near(MATCH_COLOR) > 2000


def test_a_query_without_matches_has_its_section_and_no_rows(library):
    home, _ = library
    code, _, err, out = _report(library, home / "sample_curves" / "queries", "--max-distance", "0.001")
    assert code == 0, err
    page = open(out, encoding="utf-8").read()
    sections = _sections(page)
    assert len(sections) == 3
    counts = sorted(len(re.findall(r'<tr data-d="', s)) for s in sections)
    assert counts[0] == 0 and counts[-1] >= 1  # 4_1-control has nothing that close; the trefoil has
    empty = [s for s in sections if '<tr data-d="' not in s]
    assert all(s.count('<svg class="nfd"') == 1 for s in empty)  # the query alone
