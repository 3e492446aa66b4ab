"""nfdmatch._graph: segment graphs shared by the curve readers and mesh extraction (an
internal module, tested directly; the readers' chaining is also tested in test_formats)."""

import numpy as np
import pytest

from nfdmatch._graph import chain_segments, closed_loops, count_components, unique_segments
from nfdmatch.errors import ParseError


def _lists(loops):
    return [list(map(int, ids)) for ids in loops]


def test_unique_segments_drops_self_and_repeated_segments_keeping_the_first():
    seg, order = unique_segments([[0, 1], [1, 1], [1, 0], [1, 2], [2, 1]])
    assert seg.tolist() == [[0, 1], [1, 2]] and order.tolist() == [0, 3]
    seg, order = unique_segments(np.zeros((0, 2), dtype=int))
    assert seg.shape == (0, 2) and len(order) == 0


def test_closed_loops_without_branching_are_the_closed_chains():
    loops, open_pieces, branching = closed_loops([[0, 1], [1, 2], [2, 0], [0, 0], [1, 0], [5, 6], [6, 7]])
    assert _lists(loops) == [[0, 1, 2]] and (open_pieces, branching) == (1, 0)
    assert _lists(loops) == [list(ids) for _, ids in chain_segments([[0, 1], [1, 2], [2, 0]])]


def test_closed_loops_split_at_branching_points():
    # a figure eight: two loops through one vertex of degree 4
    loops, open_pieces, branching = closed_loops([[0, 1], [1, 2], [2, 0], [0, 3], [3, 4], [4, 0]])
    assert _lists(loops) == [[0, 1, 2], [0, 3, 4]] and (open_pieces, branching) == (0, 1)
    # a theta (two vertices of degree 3): one loop, the chord left as an open piece
    loops, open_pieces, branching = closed_loops([[0, 1], [1, 2], [2, 3], [3, 0], [0, 2]])
    assert _lists(loops) == [[0, 1, 2, 3]] and (open_pieces, branching) == (1, 2)
    # a dangling branch and a separate segment: pruned, each an open piece
    loops, open_pieces, branching = closed_loops([[0, 1], [1, 2], [2, 0], [2, 3], [3, 4], [5, 6]])
    assert _lists(loops) == [[0, 1, 2]] and (open_pieces, branching) == (2, 1)


def test_count_components_and_chain_segments_refusing_a_branch():
    assert count_components(np.array([[0, 1], [1, 2], [5, 6]])) == 2
    with pytest.raises(ParseError, match="branching point"):
        chain_segments([[0, 1], [1, 2], [2, 0], [0, 3], [3, 4], [4, 0]])
