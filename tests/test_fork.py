"""Forked worker processes (nfdmatch._fork) and the k-NN graph searched by them: each check
of fork_checks.py runs in a new process (this one holds the threads of earlier tests)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from fork_checks import CHECKS

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")

HERE = os.path.dirname(os.path.abspath(__file__))


@pytest.mark.parametrize("name", CHECKS)
def test_fork(name, tmp_path):
    run = subprocess.run(
        [sys.executable, os.path.join(HERE, "fork_checks.py"), name, str(tmp_path)],
        cwd=HERE,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
