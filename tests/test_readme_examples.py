"""Every shell example of the README, run: each ``$ command`` of a transcript block is run
with bash in a copy of the repository's sample data (in README order, one folder for all,
as a reader following the README would), and what it prints (stdout and stderr, as a
terminal shows them, in the order written) is compared with the lines under it.

The comparison allows what changes from run to run: timings (``0.29 s``, ``"seconds":``),
dates (``2026-11-28T02:15:00Z``), the index's size in bytes, and the folder the
repository is in (``/home/me/nfdmatch``). ``...`` in a line stands for any text, a line
``...`` alone for any number of lines. So the README cannot show output the code no
longer prints (issue 25, item 17)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest

from conftest import ROOT

#: end-to-end as a whole (the README's shell transcripts): left out by `make test-fast`
pytestmark = pytest.mark.slow

README = os.path.join(ROOT, "README.md")
#: the repository's folder as the README spells it
README_ROOT = "/home/me/nfdmatch"

_NORMALIZE = [
    (re.compile(r"\b\d+(?:\.\d+)? s\b"), "<T> s"),  # timings
    (re.compile(r'"seconds": [0-9.e-]+'), '"seconds": <T>'),
    (re.compile(r"\b\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ"), "<DATE>"),
    (re.compile(r"(size_bytes\t)\d+"), r"\1<N>"),
    # a distance's last digits are those of the install's kernels (they agree to ~1e-15):
    # compared to 10 significant digits
    (re.compile(r"(?<![\w.])\d+\.\d{12,}(?:e-?\d+)?"), lambda m: f"{float(m.group()):.10g}"),
]


def transcripts(text: str) -> list[tuple[int, list[tuple[str, list[str]]]]]:
    """``(line number, [(command, expected output lines), ...])`` of every code block whose
    lines start with ``$ `` (the transcripts; other blocks are files, not sessions)."""
    found = []
    lines = text.split("\n")
    i = 0
    while i < len(lines):
        if lines[i].startswith("```"):
            start, body = i + 1, []
            i += 1
            while not lines[i].startswith("```"):
                body.append(lines[i])
                i += 1
            if body and body[0].startswith("$ "):
                steps: list[tuple[str, list[str]]] = []
                for line in body:
                    if line.startswith("$ "):
                        steps.append((line[2:], []))
                    else:
                        steps[-1][1].append(line)
                found.append((start, steps))
        i += 1
    return found


def normalize(text: str, root: str) -> str:
    text = text.replace(root, README_ROOT)
    for pattern, replacement in _NORMALIZE:
        text = pattern.sub(replacement, text)
    return "\n".join(line.rstrip() for line in text.rstrip("\n").split("\n")) if text.strip() else ""


def pattern_of(expected: list[str]) -> re.Pattern:
    """The regular expression of the expected lines: ``...`` in a line is any text, a line
    ``...`` alone any number of lines."""
    parts = []
    for line in expected:
        if line.strip() == "...":
            parts.append(r"(?:[^\n]*\n)*?")
        else:
            parts.append(".*".join(re.escape(piece) for piece in line.rstrip().split("...")) + r"\n")
    return re.compile("".join(parts), re.S)


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory):
    """A folder like the repository's (its sample data), with ``nfdmatch`` and ``python`` on
    the PATH running this checkout, and the walk-through's meshes made (the extract example
    comes before the walk-through that makes them)."""
    home = tmp_path_factory.mktemp("readme")
    shutil.copytree(os.path.join(ROOT, "sample_curves"), home / "sample_curves")
    bin_dir = home / ".bin"
    bin_dir.mkdir()
    for name, script in (
        ("nfdmatch", f'exec "{sys.executable}" -m nfdmatch "$@"'),
        ("python", f'exec "{sys.executable}" "$@"'),
    ):
        (bin_dir / name).write_text(f"#!/bin/sh\n{script}\n")
        (bin_dir / name).chmod(0o755)
    env = {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]),
        "PYTHONUNBUFFERED": "1",  # stdout and stderr interleaved as written, as on a terminal
        "COLUMNS": "120",
    }
    for name in ("NFDMATCH_INDEX", "NO_COLOR", "NFDMATCH_SCHEDULER"):
        env.pop(name, None)
    made = subprocess.run(
        ["python", "sample_curves/make_meshes.py", "demo-out/walk/meshes"], cwd=home, env=env, capture_output=True
    )
    assert made.returncode == 0, made.stderr
    return home, env


def test_every_shell_example_of_the_readme_prints_what_it_shows(sandbox):
    home, env = sandbox
    blocks = transcripts(open(README, encoding="utf-8").read())
    assert len(blocks) >= 10  # the README's transcripts are found
    failures = []
    for line_no, steps in blocks:
        for command, expected in steps:
            run = subprocess.run(["bash", "-c", command], cwd=home, env=env, capture_output=False, **_merged())
            actual = normalize(run.stdout, str(home))
            want = pattern_of([normalize(line, "\0") if line.strip() != "..." else line for line in expected])
            if not want.fullmatch(actual + "\n" if actual else ""):
                failures.append(
                    f"README.md line {line_no}: $ {command}\n--- shown:\n"
                    + "\n".join(expected)
                    + f"\n--- printed:\n{actual}"
                )
    assert not failures, "\n\n".join(failures)


def _merged() -> dict:
    return {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT, "text": True}


def test_the_comparison_can_fail():
    """The matcher is not so loose that any output passes."""
    assert pattern_of(["a", "...", "b ... c"]).fullmatch("a\nx\ny\nb 1 c\n")
    assert not pattern_of(["a", "b ... c"]).fullmatch("a\nb 1 d\n")
    assert not pattern_of(["a"]).fullmatch("a\nmore\n")
    assert normalize("took 0.29 s at 2026-11-28T02:15:00Z in /x/y", "/x") == f"took <T> s at <DATE> in {README_ROOT}/y"
