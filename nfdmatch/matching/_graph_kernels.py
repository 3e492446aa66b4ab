"""Compiled (numba) personalised-PageRank push of :class:`nfdmatch.search.diffusion.GraphWalk`.

Optional, as :mod:`._kernels` is: :mod:`.kernels` (:func:`~.kernels.graph_push`) hands it to
the walk when the process's kernels are numba's or the ahead-of-time module (:mod:`.aot`
compiles this file, with :mod:`._push_rounds`, into the same extension module); the numpy
push of ``GraphWalk._push`` stays the reference and serves without numba.

Bit for bit the numpy push. That push runs synchronous rounds over a block of sources, its
residuals and estimates kept as sorted keys ``source * (N + 1) + node``; every round pushes
every residual of at least the tolerance and re-sums the residuals with
``diffusion.sum_by_key`` (a stable sort by key, then ``np.add.reduceat``). Nothing in a
round mixes two sources, and a source with nothing left to push keeps its residuals
unchanged (a key alone in its group sums to its own value), so each source's estimate is
that of its own rounds, whatever else the block holds. This kernel runs each source's
rounds in turn with the same arithmetic in the same order:

* the pushed nodes of a round in ascending order; for each, ``stay = 1 / (1 - alpha P_uu)``,
  kept ``((1 - alpha) r_u) stay``, sent ``(alpha (r_u stay)) P_uv`` to its row's targets in
  the row's order (numpy's element-wise operations, left to right: IEEE rounding of each
  product and quotient is the same in compiled code, and nothing here is fused or
  reordered: no fastmath);
* a node's new residual sums, in this order, its residual of the round before (when it had
  one and was not pushed) then what it received, pusher by pusher in ascending order, each
  pusher's targets in row order: the order a stable sort by key leaves them in;
* each such sum as ``np.add.reduceat`` computes it: the first value plus numpy's pairwise
  sum of the others (:func:`._push_rounds._pairwise`: fewer than 8 values one after the other from 0.0,
  up to 128 with 8 accumulators, above that halves at a multiple of 8);
* a node's estimate: its kept shares over the rounds, in round order, summed the same way.

numba compiles the same operations as numpy's loops (no fastmath: no reassociation, no
fused multiply-add), so the results are the same doubles (tests/test_diffusion.py checks
that on random graphs and on an index's graph). The identity rests on numpy's reduction
order (``np.add.reduceat`` as ``DOUBLE_pairwise_sum``, numpy 1.x to 2.4): a numpy that sums
otherwise would make the numpy push's digits move, and those tests say so.

One source's rounds (:mod:`._push_rounds`, :func:`~._push_rounds.source_rounds`) sum as the
values come, without sorting (that module says how); this one holds the block's state in
and out, and a done source's estimate.

The walk's rows (``targets``, ``prob``: node u's row, the self loop first) are numpy's,
computed by the walk (``exp`` in numpy), and read here only where ``known``. A source that
reaches a node whose row is not known stops before that round and says which nodes it
needs; the caller computes their rows (for every stopped source at once) and calls again:
each source resumes where it stopped. Hence the resumable state in and out of
:func:`push_sources`.

``cache=True``, ``nogil=True``, ``error_model="numpy"`` as in :mod:`._kernels`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._push_rounds import group_sum, positions_with_room, source_rounds, with_room

__all__ = ["push_sources", "NEW", "STOPPED", "DONE"]

_jit = dict(nogil=True, cache=True, error_model="numpy")

#: a source's state between calls of :func:`push_sources`
NEW, STOPPED, DONE = 0, 1, 2


@njit(**_jit)
def _grouped(nodes, values, count, slot, order_out, sums_out):
    """The ``count`` entries ``(nodes, values)`` grouped by node, each group in the entries'
    order and summed as :func:`._push_rounds.group_sum`; writes the distinct nodes ascending
    into ``order_out`` and their sums into ``sums_out``; returns how many. ``slot``: (N + 1,)
    -1 everywhere, left so."""
    distinct = np.empty(count, dtype=np.int64)
    size = np.zeros(count + 1, dtype=np.int64)
    m = 0
    for j in range(count):
        u = nodes[j]
        if slot[u] == -1:
            slot[u] = m
            distinct[m] = u
            m += 1
        size[slot[u] + 1] += 1
    for s in range(m):
        size[s + 1] += size[s]
    placed = np.empty(count)
    fill = size[:m].copy()
    for j in range(count):
        s = slot[nodes[j]]
        placed[fill[s]] = values[j]
        fill[s] += 1
    order = np.argsort(distinct[:m])
    for i in range(m):
        s = order[i]
        order_out[i] = distinct[s]
        sums_out[i] = group_sum(placed, size[s], size[s + 1] - size[s])
    for s in range(m):
        slot[distinct[s]] = -1
    return m


@njit(**_jit)
def push_sources(
    sources, status, r_start, r_node, r_val, p_start, p_node, p_val, targets, prob, known, slot, alpha, tolerance
):
    """Push a block of sources as far as the known rows of the walk allow.

    Parameters
    ----------
    sources : (n,) int64, the sources (nodes of the walk).
    status : (n,) int64, each source's state: :data:`NEW` (not pushed yet), :data:`STOPPED`
        (its residuals and kept shares below), :data:`DONE` (its estimate below).
    r_start : (n + 1,) int64; r_node (int64), r_val (float64): a stopped source i's residuals,
        ``r_node[r_start[i]:r_start[i + 1]]`` and their values (any order of nodes).
    p_start : (n + 1,) int64; p_node (int64), p_val (float64): a stopped source's kept shares
        in the order they were kept (round by round, ascending nodes within a round); a
        done source's estimate, ascending nodes, one entry each.
    targets : (N + 1, k + 1) int64, prob (N + 1, k + 1) float64: each node's row of the
        walk (the self loop first), valid where ``known``.
    known : (N + 1,) bool.
    slot : (N + 1,) int64, -1 everywhere (a work array, left so).
    alpha, tolerance : float.

    Returns
    -------
    ``(status, r_start, r_node, r_val, p_start, p_node, p_val, missing)``: the same after
    pushing every source that is not done until it is done or a round needs the row of a
    node that is not known; ``missing``: those nodes, ascending, unique (empty: every
    source is done). The arrays may be longer than their last start.
    """
    n = len(sources)
    o_status = np.empty(n, dtype=np.int64)
    o_rs = np.zeros(n + 1, dtype=np.int64)
    o_ps = np.zeros(n + 1, dtype=np.int64)
    o_rn = np.empty(max(16, len(r_node)), dtype=np.int64)
    o_rv = np.empty(len(o_rn))
    o_pn = np.empty(max(16, len(p_node)), dtype=np.int64)
    o_pv = np.empty(len(o_pn))
    missing = np.empty(16, dtype=np.int64)
    n_missing = 0
    work = _work_arrays(targets.shape[1] - 1)
    for i in range(n):
        o_rs[i + 1] = o_rs[i]
        o_ps[i + 1] = o_ps[i]
        if status[i] == DONE:  # its estimate, as it is
            o_pn, o_pv = _appended(o_pn, o_pv, o_ps[i], p_node, p_val, p_start[i], p_start[i + 1])
            o_ps[i + 1] = o_ps[i] + p_start[i + 1] - p_start[i]
            o_status[i] = DONE
            continue
        work, m, q = _source_state(
            work,
            sources[i],
            status[i],
            r_node,
            r_val,
            r_start[i],
            r_start[i + 1],
            p_node,
            p_val,
            p_start[i],
            p_start[i + 1],
            slot,
        )
        stopped, work, m, q, missing, n_missing = source_rounds(
            work, m, q, targets, prob, known, slot, alpha, tolerance, missing, n_missing
        )
        positions, _, kept, _ = work
        if stopped:  # the state for the next call: the residuals held, the kept shares
            o_status[i] = STOPPED
            o_rn, o_rv, held_end = _held_residuals(positions, m, o_rn, o_rv, o_rs[i])
            o_rs[i + 1] = held_end
            o_pn, o_pv = _appended(o_pn, o_pv, o_ps[i], kept[0], kept[1], 0, q)
            o_ps[i + 1] = o_ps[i] + q
        else:  # the estimate: each node's kept shares in round order, summed
            o_status[i] = DONE
            o_pn = with_room(o_pn, o_ps[i], o_ps[i] + q)
            o_pv = with_room(o_pv, o_ps[i], o_ps[i] + q)
            o_ps[i + 1] = o_ps[i] + _grouped(kept[0], kept[1], q, slot, o_pn[o_ps[i] :], o_pv[o_ps[i] :])
    return o_status, o_rs, o_rn, o_rv, o_ps, o_pn, o_pv, _sorted_unique(missing, n_missing)


@njit(**_jit)
def _work_arrays(k):
    """:func:`push_sources`'s work arrays for a walk of ``k`` neighbours, reused from source to
    source (grown as a source needs): ``(positions, walk_rows, kept, round_arrays)``.

    One source's nodes by position (slot[node]), ``positions``: ``node_at`` the node, ``val``
    its residual, ``held`` whether it holds one (a pushed node holds none until it receives
    again), ``row`` its row of the walk once pushed (-1, or where in ``walk_rows``: ``to_pos``
    the targets' positions, ``to_prob`` their probabilities, ``stays`` its
    1 / (1 - alpha P_uu)). Within a round, what a node receives is summed as it comes, as
    np.add.reduceat sums its group: the first value (its residual when it holds one, else
    the first send: pend[:, 8]) plus numpy's pairwise sum of the others (the sends): those
    pairwise are counted by ``count`` (-1 before the first send of a node that holds no
    residual, else 0, between rounds), their blocks of 8 summed into blocks[:, 0:8] (zero
    between rounds) as each block completes, the block not yet complete in pend[:, 0:8].
    ``kept``: the kept shares (nodes, values), in order.
    """
    node_at = np.empty(64, dtype=np.int64)
    val = np.empty(64)
    held = np.empty(64, dtype=np.bool_)
    count = np.empty(64, dtype=np.int64)
    pend = np.empty((64, 9))
    blocks = np.empty((64, 8))
    at = np.empty(64, dtype=np.int64)  # where the sends of a node receiving more than 128 go, else -1
    row = np.empty(64, dtype=np.int64)
    walk_rows = (np.empty((16, k), dtype=np.int64), np.empty((16, k)), np.empty(16))
    kept = (np.empty(64, dtype=np.int64), np.empty(64))
    return (node_at, val, held, count, pend, blocks, at, row), walk_rows, kept, _round_arrays(64)


@njit(**_jit)
def _round_arrays(size):
    """A round's work arrays, each of ``size`` entries: ``(act, pushed, spreads, receivers,
    many, placed)``."""
    act = np.empty(size, dtype=np.int64)  # a round's pushed nodes, ascending
    pushed = np.empty(size, dtype=np.int64)  # their rows (in to_pos)
    spreads = np.empty(size)  # alpha r_u stay_u
    receivers = np.empty(size, dtype=np.int64)  # a round's receivers (positions), as first reached
    many = np.empty(size, dtype=np.int64)  # those with more than 128 sends
    placed = np.empty(size)  # their sends, grouped
    return act, pushed, spreads, receivers, many, placed


@njit(**_jit)
def _source_state(work, source, status, r_node, r_val, r_lo, r_hi, p_node, p_val, p_lo, p_hi, slot):
    """A source's state into the work arrays ``work`` (:func:`_work_arrays`): its residuals
    at the first ``m`` positions (a :data:`NEW` source: 1 on itself; a :data:`STOPPED` one:
    ``r_node[r_lo:r_hi]``, ``r_val[r_lo:r_hi]``), its first ``q`` kept shares (none, or
    ``p_node[p_lo:p_hi]``, ``p_val[p_lo:p_hi]``), each position's node in ``slot``, nothing
    pushed nor received yet. Returns ``(work, m, q)`` (``work`` grown as needed)."""
    positions, walk_rows, kept, round_arrays = work
    if status == NEW:
        m, q = 1, 0
        positions[0][0], positions[1][0] = source, 1.0
    else:
        m = r_hi - r_lo
        if m > len(positions[0]):
            positions = positions_with_room(positions, 0, m)
        positions[0][:m], positions[1][:m] = r_node[r_lo:r_hi], r_val[r_lo:r_hi]
        q = p_hi - p_lo
        if q > len(kept[0]):
            kept = (with_room(kept[0], 0, q), with_room(kept[1], 0, q))
        kept[0][:q], kept[1][:q] = p_node[p_lo:p_hi], p_val[p_lo:p_hi]
    node_at, _, held, count, _, blocks, at, row = positions
    for j in range(m):
        slot[node_at[j]] = j
        held[j], count[j], at[j], row[j] = True, 0, -1, -1
        for b in range(8):
            blocks[j, b] = 0.0
    return (positions, walk_rows, kept, round_arrays), m, q


@njit(**_jit)
def _held_residuals(positions, m, o_node, o_value, at):
    """The residuals held at the first ``m`` positions, written into ``o_node``, ``o_value``
    from entry ``at`` (grown as needed). Returns ``(o_node, o_value, their end)``."""
    node_at, val, held = positions[0], positions[1], positions[2]
    o_node = with_room(o_node, at, at + m)
    o_value = with_room(o_value, at, at + m)
    for j in range(m):
        if held[j]:
            o_node[at], o_value[at] = node_at[j], val[j]
            at += 1
    return o_node, o_value, at


@njit(**_jit)
def _appended(o_node, o_value, at, node, value, lo, hi):
    """``node[lo:hi]``, ``value[lo:hi]`` written into ``o_node``, ``o_value`` from entry
    ``at`` (grown as needed); returns them."""
    o_node = with_room(o_node, at, at + hi - lo)
    o_value = with_room(o_value, at, at + hi - lo)
    o_node[at : at + hi - lo] = node[lo:hi]
    o_value[at : at + hi - lo] = value[lo:hi]
    return o_node, o_value


@njit(**_jit)
def _sorted_unique(values, n):
    """The first ``n`` of ``values`` (int64), sorted, each once."""
    values = np.sort(values[:n])
    unique = np.ones(n, dtype=np.bool_)
    for j in range(1, n):
        unique[j] = values[j] != values[j - 1]
    return values[unique]
