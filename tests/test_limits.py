"""How many matches: one rule for the library and the CLI (issue 34, item 3): ``top``/``k``
an integer >= 1, ``max_distance`` a number >= 0 (``inf``: no limit; NaN refused, also by
the CLI); a huge ``max_distance`` answers as ``inf`` does (its square overflowed);
``show --exclude-self`` leaves the query's own curve out, as ``query`` does."""

from __future__ import annotations

import os
import shutil

import pytest
from conftest import ROOT, run_cli

from nfdmatch import build_index, open_index, read_curve
from nfdmatch.errors import ParameterError
from nfdmatch.search import search_index

QUERY = "sample_curves/queries/trefoil-posed.obj"


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    folder = tmp_path_factory.mktemp("limits")
    shutil.copytree(os.path.join(ROOT, "sample_curves"), folder / "sample_curves")
    build_index([str(folder / "sample_curves" / "library")], str(folder / "lib.h5"))
    return folder


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(max_distance=float("nan")),
        dict(max_distance=-1.0),
        dict(max_distance="1"),
        dict(k=0),
        dict(k=2.5),
        dict(k=True),
    ],
)
def test_index_search_refuses_what_the_cli_refuses(library, kwargs):
    with open_index(library / "lib.h5") as idx, pytest.raises(ParameterError):
        idx.search(str(library / QUERY), **kwargs)


@pytest.mark.parametrize("value", ["nan", "-1"])
@pytest.mark.parametrize("command", ["query", "pairs"])
def test_the_cli_refuses_a_distance_that_is_not_one(library, command, value):
    args = [command, str(library / QUERY)] if command == "query" else [command]
    code, out, err = run_cli(*args, "--index", library / "lib.h5", "--max-distance", value)
    assert code == 2 and out == ""
    assert "Invalid value for '--max-distance'" in err and "Traceback" not in err


def test_a_distance_whose_square_overflows_answers_as_inf(library):
    with open_index(library / "lib.h5") as idx:
        query = str(library / QUERY)
        for exhaustive in (False, True):
            curve = read_curve(query)
            huge, _ = search_index(idx, [curve], top=5, max_distance=1e155, prune=not exhaustive)
            endless, _ = search_index(idx, [curve], top=5, max_distance=float("inf"), prune=not exhaustive)
            assert huge == endless and len(huge[0]) == 5
        inf = float("inf")
        assert idx.search(query, k=3, max_distance=1e300, pose=False) == idx.search(
            query, k=3, max_distance=inf, pose=False
        )
    for command in (["query", str(library / QUERY), "--top", "4"], ["pairs"]):
        answers = [run_cli(*command, "--index", library / "lib.h5", "--max-distance", d) for d in ("1e155", "inf")]
        assert answers[0][0] == 0 and answers[0] == answers[1], answers[0][2]


def test_show_excludes_the_query_itself_as_query_does(library, tmp_path):
    stored = str(library / "sample_curves" / "library" / "trefoil.csv")
    args = ["show", stored, "--index", library / "lib.h5", "--top", 2, "--format", "csv", "-o", tmp_path / "m.png"]
    code, out, err = run_cli(*args)
    assert code == 0, err
    assert out.splitlines()[1].split(",")[2].endswith("library/trefoil.csv")  # itself, at distance ~0
    code, out, err = run_cli(*args, "--exclude-self")
    assert code == 0, err
    matches = [line.split(",")[2] for line in out.splitlines()[1:]]
    assert len(matches) == 2 and not any(m.endswith("library/trefoil.csv") for m in matches)
    code, listed, _ = run_cli(
        "query", stored, "--index", library / "lib.h5", "--top", 2, "--exclude-self", "--format", "csv"
    )
    assert matches == [line.split(",")[2] for line in listed.splitlines()[1:]]
    code, out, err = run_cli(*args[:2], "--against", library / "sample_curves" / "library", *args[4:], "--exclude-self")
    assert code == 0, err
    assert not any(line.split(",")[2].endswith("library/trefoil.csv") for line in out.splitlines()[1:])
