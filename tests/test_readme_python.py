"""Every Python block of the README, run: the blocks in README order in one namespace (a
reader pastes them one after the other), from a folder holding a copy of the sample curves
and the walk-through's meshes (``python sample_curves/make_meshes.py meshes``), so the
README cannot show an API that no longer exists or a call that fails."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest

from conftest import ROOT

pytestmark = pytest.mark.slow

README = os.path.join(ROOT, "README.md")


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(line number, source)`` of each fenced ```python block."""
    return [
        (text[: m.start()].count("\n") + 2, m.group(1))
        for m in re.finditer(r"^```python\n(.*?)^```", text, flags=re.S | re.M)
    ]


def test_readme_has_python_blocks():
    assert len(python_blocks(open(README, encoding="utf-8").read())) >= 4


def test_readme_python_blocks_run(tmp_path, monkeypatch):
    shutil.copytree(os.path.join(ROOT, "sample_curves"), tmp_path / "sample_curves")
    subprocess.run(
        [sys.executable, "sample_curves/make_meshes.py", "meshes"], cwd=tmp_path, check=True, capture_output=True
    )
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__readme__"}
    for line, source in python_blocks(open(README, encoding="utf-8").read()):
        try:
            exec(compile(source, f"README.md:{line}", "exec"), namespace)
        except Exception as exc:  # the block's line in the message: where to fix the README
            pytest.fail(f"the README's Python block at line {line} fails: {type(exc).__name__}: {exc}")
