"""Compiled (numba) personalised-PageRank push of :class:`nfdmatch.search.diffusion.GraphWalk`.

Optional, as :mod:`._kernels` is: :mod:`.kernels` (:func:`~.kernels.graph_push`) hands it to
the walk when the process's kernels are numba's or the ahead-of-time module (:mod:`.aot`
compiles this file into the same extension module); the numpy push of ``GraphWalk._push``
stays the reference and serves without numba.

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
  sum of the others (:func:`_pairwise`: fewer than 8 values one after the other from 0.0,
  up to 128 with 8 accumulators, above that halves at a multiple of 8);
* a node's estimate: its kept shares over the rounds, in round order, summed the same way.

numba compiles the same operations as numpy's loops (no fastmath: no reassociation, no
fused multiply-add), so the results are the same doubles (tests/test_diffusion.py checks
that on random graphs and on an index's graph). The identity rests on numpy's reduction
order (``np.add.reduceat`` as ``DOUBLE_pairwise_sum``, numpy 1.x to 2.4): a numpy that sums
otherwise would make the numpy push's digits move, and those tests say so.

The sums are made as the values come, without sorting: a node's values of the round are
counted (the first one apart when it holds no residual), each complete block of 8 is added
into 8 accumulators (numpy's 8-way loop), the block not complete yet kept; at the round's
end the accumulators are combined as numpy does, then the incomplete block added one value
after the other (below 8 values: only those, from 0.0). A node receiving more than 128
values in one round (numpy then halves) has its values placed in order and summed by
:func:`_pairwise`. The work is the synchronous rounds' all the same (every residual of at
least the tolerance is pushed again every round): at 100,000 curves ~1,170 pushes per
source, ~90 ns each (its 8 sends included).

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

__all__ = ["push_sources", "NEW", "STOPPED", "DONE"]

_jit = dict(nogil=True, cache=True, error_model="numpy")

#: a source's state between calls of :func:`push_sources`
NEW, STOPPED, DONE = 0, 1, 2


@njit(**_jit)
def _pairwise(values, lo, n):
    """numpy's pairwise sum of ``values[lo:lo + n]`` (``DOUBLE_pairwise_sum``, numpy's
    ``loops_utils.h``), which its add reductions use (``np.add.reduceat`` for every value of a
    group but the first)."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += values[lo + i]
        return res
    if n <= 128:
        r0, r1, r2, r3 = values[lo], values[lo + 1], values[lo + 2], values[lo + 3]
        r4, r5, r6, r7 = values[lo + 4], values[lo + 5], values[lo + 6], values[lo + 7]
        i = 8
        end = n - n % 8
        while i < end:
            r0 += values[lo + i]
            r1 += values[lo + i + 1]
            r2 += values[lo + i + 2]
            r3 += values[lo + i + 3]
            r4 += values[lo + i + 4]
            r5 += values[lo + i + 5]
            r6 += values[lo + i + 6]
            r7 += values[lo + i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += values[lo + i]
            i += 1
        return res
    half = n // 2
    half -= half % 8
    return _pairwise(values, lo, half) + _pairwise(values, lo + half, n - half)


@njit(**_jit)
def _group_sum(values, lo, n):
    """``np.add.reduceat``'s sum of one group ``values[lo:lo + n]`` (n >= 1): the first value,
    plus the pairwise sum of the rest."""
    if n == 1:
        return values[lo]
    return values[lo] + _pairwise(values, lo + 1, n - 1)


@njit(**_jit)
def _room(a, used, need):
    """``a``, or a copy with room for ``need`` entries (its first ``used`` kept, as many as
    it has)."""
    if need <= len(a):
        return a
    b = np.empty(max(need, 2 * len(a)), dtype=a.dtype)
    used = min(used, len(a))
    b[:used] = a[:used]
    return b


@njit(**_jit)
def _grouped(nodes, values, count, slot, order_out, sums_out):
    """The ``count`` entries ``(nodes, values)`` grouped by node, each group in the entries'
    order and summed as :func:`_group_sum`; writes the distinct nodes ascending into
    ``order_out`` and their sums into ``sums_out``; returns how many. ``slot``: (N + 1,) -1
    everywhere, left so."""
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
        sums_out[i] = _group_sum(placed, size[s], size[s + 1] - size[s])
    for s in range(m):
        slot[distinct[s]] = -1
    return m


@njit(**_jit)
def _positions(positions, used, need):
    """:func:`push_sources`'s per-position work arrays (:func:`_work_arrays`) with room for
    ``need`` positions (their first ``used`` kept)."""
    node_at, val, held, count, pend, blocks, at, row = positions
    if need > len(pend):
        size = max(need, 2 * len(pend))
        grown_pend, grown_blocks = np.empty((size, 9)), np.empty((size, 8))
        grown_pend[:used], grown_blocks[:used] = pend[:used], blocks[:used]
        pend, blocks = grown_pend, grown_blocks
    return (
        _room(node_at, used, need),
        _room(val, used, need),
        _room(held, used, need),
        _room(count, used, need),
        pend,
        blocks,
        _room(at, used, need),
        _room(row, used, need),
    )


@njit(**_jit)
def _rows(walk_rows, used, need):
    """:func:`push_sources`'s rows of the walk by positions (:func:`_work_arrays`) with room
    for ``need`` rows (their first ``used`` kept)."""
    to_pos, to_prob, stays = walk_rows
    if need <= len(stays):
        return to_pos, to_prob, stays
    size = max(need, 2 * len(stays))
    grown_pos = np.empty((size, to_pos.shape[1]), dtype=np.int64)
    grown_prob = np.empty((size, to_pos.shape[1]))
    grown_pos[:used], grown_prob[:used] = to_pos[:used], to_prob[:used]
    return grown_pos, grown_prob, _room(stays, used, need)


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
        stopped, work, m, q, missing, n_missing = _rounds(
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
            o_pn = _room(o_pn, o_ps[i], o_ps[i] + q)
            o_pv = _room(o_pv, o_ps[i], o_ps[i] + q)
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
            positions = _positions(positions, 0, m)
        positions[0][:m], positions[1][:m] = r_node[r_lo:r_hi], r_val[r_lo:r_hi]
        q = p_hi - p_lo
        if q > len(kept[0]):
            kept = (_room(kept[0], 0, q), _room(kept[1], 0, q))
        kept[0][:q], kept[1][:q] = p_node[p_lo:p_hi], p_val[p_lo:p_hi]
    node_at, _, held, count, _, blocks, at, row = positions
    for j in range(m):
        slot[node_at[j]] = j
        held[j], count[j], at[j], row[j] = True, 0, -1, -1
        for b in range(8):
            blocks[j, b] = 0.0
    return (positions, walk_rows, kept, round_arrays), m, q


@njit(**_jit)
def _rounds(work, m, q, targets, prob, known, slot, alpha, tolerance, missing, n_missing):
    """One source's synchronous rounds from its state in ``work`` (:func:`_source_state`: ``m``
    positions, ``q`` kept shares) until it holds no residual of at least ``tolerance``, or a
    round would push nodes whose rows are not ``known``: that round is not pushed, and those
    nodes are appended to ``missing`` (its first ``n_missing`` entries). Leaves ``slot`` -1
    everywhere.

    Returns ``(stopped, work, m, q, missing, n_missing)``: whether it stopped so, the work
    arrays (grown as needed), the positions and kept shares they hold, the missing nodes."""
    k = targets.shape[1] - 1
    positions, walk_rows, kept, round_arrays = work
    act, pushed, spreads, receivers, many, placed = round_arrays
    rows, ordered = 0, 0
    order = np.empty(0, dtype=np.int64)  # the positions by ascending node (its first ``ordered``)
    stopped = False
    while True:
        # the round's pushes: every residual of at least the tolerance, in ascending order
        # as the keys sort (the positions sorted again only when some were added)
        if ordered < m:
            order = np.argsort(positions[0][:m])
            ordered = m
        if m > len(act):
            act = _room(act, 0, m)
        na = _active(positions, order, m, tolerance, act)
        if na == 0:
            break
        missing, n_missing, stopped = _unknown(act, na, known, missing, n_missing)
        if stopped:
            break
        ne = na * k
        if m + ne > len(positions[0]):
            positions = _positions(positions, m, m + ne)
        if rows + na > len(walk_rows[2]):
            walk_rows = _rows(walk_rows, rows, rows + na)
        if ne > len(receivers):
            receivers, many, placed = (
                np.empty(2 * ne, dtype=np.int64),
                np.empty(2 * ne, dtype=np.int64),
                np.empty(2 * ne),
            )
        if na > len(pushed):
            pushed, spreads = np.empty(2 * na, dtype=np.int64), np.empty(2 * na)
        if q + na > len(kept[0]):
            kept = (_room(kept[0], q, q + na), _room(kept[1], q, q + na))
        m, rows, q = _take(positions, walk_rows, kept, act, na, pushed, spreads, m, rows, q, targets, prob, slot, alpha)
        nr = _send(positions, walk_rows, pushed, spreads, na, receivers)
        nb = _received(positions, receivers, nr, many)
        if nb:  # (rare) numpy's pairwise sum by halves
            _received_by_halves(positions, walk_rows, pushed, spreads, na, many, nb, placed)
        held, count = positions[2], positions[3]
        for j in range(nr):
            p = receivers[j]
            held[p], count[p] = True, 0
    node_at = positions[0]
    for j in range(m):
        slot[node_at[j]] = -1
    work = (positions, walk_rows, kept, (act, pushed, spreads, receivers, many, placed))
    return stopped, work, m, q, missing, n_missing


@njit(**_jit)
def _active(positions, order, m, tolerance, act):
    """The round's pushed nodes into ``act``, ascending: those of the first ``m`` positions
    (``order``: them by ascending node) that hold a residual of at least ``tolerance``.
    Returns how many."""
    node_at, val, held = positions[0], positions[1], positions[2]
    na = 0
    for j in range(m):
        p = order[j]
        if held[p] and val[p] >= tolerance:
            act[na] = node_at[p]
            na += 1
    return na


@njit(**_jit)
def _unknown(act, na, known, missing, n_missing):
    """The nodes of ``act[:na]`` whose rows are not ``known``, appended to ``missing`` (its
    first ``n_missing`` entries). Returns ``(missing, n_missing, whether there were any)``."""
    stopped = False
    for j in range(na):
        if not known[act[j]]:
            missing = _room(missing, n_missing, n_missing + 1)
            missing[n_missing] = act[j]
            n_missing += 1
            stopped = True
    return missing, n_missing, stopped


@njit(**_jit)
def _take(positions, walk_rows, kept, act, na, pushed, spreads, m, rows, q, targets, prob, slot, alpha):
    """The round's pushes of the nodes ``act[:na]`` (the work arrays have room for them): each
    one's residual leaves it, its kept share ``((1 - alpha) r_u) stay`` is appended to
    ``kept`` (its first ``q``), its row (made on its first push: :func:`_walk_row`) goes into
    ``pushed`` and its ``alpha (r_u stay)`` into ``spreads``. Returns ``(m, rows, q)``: the
    positions, rows of the walk and kept shares now held."""
    val, held, count, row = positions[1], positions[2], positions[3], positions[7]
    stays = walk_rows[2]
    kn, kv = kept
    keep = 1.0 - alpha
    for j in range(na):  # a pushed residual leaves (what the node receives is new)
        u = act[j]
        s = slot[u]
        if row[s] == -1:  # pushed for the first time: its row, by positions
            m = _walk_row(positions, walk_rows, u, rows, m, targets, prob, slot, alpha)
            row[s] = rows
            rows += 1
        r = val[s]
        pushed[j] = row[s]
        stay = stays[row[s]]
        kn[q] = u
        kv[q] = (keep * r) * stay
        q += 1
        spreads[j] = alpha * (r * stay)
        held[s], count[s] = False, -1
    return m, rows, q


@njit(**_jit)
def _walk_row(positions, walk_rows, u, w, m, targets, prob, slot, alpha):
    """Node u's row of the walk by positions, into row ``w`` of ``walk_rows``: its targets'
    positions (a target reached for the first time takes the next position, from ``m``),
    their probabilities, its ``stay = 1 / (1 - alpha P_uu)``. Returns the positions now
    held."""
    node_at, _, held, count, _, blocks, at, row = positions
    to_pos, to_prob, stays = walk_rows
    for c in range(to_pos.shape[1]):
        t = targets[u, c + 1]
        p = slot[t]
        if p == -1:  # reached for the first time
            p = m
            node_at[m], held[m], count[m], at[m], row[m] = t, False, -1, -1, -1
            for b in range(8):
                blocks[m, b] = 0.0
            slot[t] = m
            m += 1
        to_pos[w, c] = p
        to_prob[w, c] = prob[u, c + 1]
    stays[w] = 1.0 / (1.0 - alpha * prob[u, 0])
    return m


@njit(**_jit)
def _send(positions, walk_rows, pushed, spreads, na, receivers):
    """The round's sends: each pushed node in turn (its row ``pushed[j]``, its spread
    ``spreads[j]``), its row's targets in order, summed as they come (:func:`_work_arrays`:
    ``count``, ``pend``, ``blocks``). Writes the receivers' positions into ``receivers`` as
    first reached; returns how many."""
    held, count, pend, blocks = positions[2], positions[3], positions[4], positions[5]
    to_pos, to_prob = walk_rows[0], walk_rows[1]
    k = to_pos.shape[1]
    nr = 0
    for j in range(na):
        w, spread = pushed[j], spreads[j]
        for c in range(k):
            p = to_pos[w, c]
            x = count[p]
            receivers[nr] = p
            nr += x == np.int64(held[p]) - 1  # its first send of the round
            pend[p, (x & 7) + (x < 0)] = spread * to_prob[w, c]  # (the first, x = -1: pend[p, 8])
            x += 1
            count[p] = x
            if x > 0 and (x & 7) == 0:  # a block of 8 complete
                for b in range(8):
                    blocks[p, b] += pend[p, b]
    return nr


@njit(**_jit)
def _received(positions, receivers, nr, many):
    """Each receiver's new residual (of ``receivers[:nr]``): the first value plus the
    pairwise sum of the others, from what :func:`_send` summed. A receiver of more than 128
    sends is left to :func:`_received_by_halves`: written into ``many`` with where its sends
    go (``at``, in the order of ``many``); returns how many such."""
    val, held, count, pend, blocks, at = (
        positions[1],
        positions[2],
        positions[3],
        positions[4],
        positions[5],
        positions[6],
    )
    nb, grouped = 0, 0
    for j in range(nr):
        p = receivers[j]
        x = count[p]
        if x > 128:  # (rare) numpy's pairwise sum by halves
            many[nb] = p
            nb += 1
            at[p] = grouped
            grouped += x + 1 - held[p]
            continue
        first = val[p] if held[p] else pend[p, 8]
        if x == 0:
            val[p] = first
            continue
        if x >= 8:
            res = ((blocks[p, 0] + blocks[p, 1]) + (blocks[p, 2] + blocks[p, 3])) + (
                (blocks[p, 4] + blocks[p, 5]) + (blocks[p, 6] + blocks[p, 7])
            )
            for b in range(8):
                blocks[p, b] = 0.0
        else:
            res = 0.0
        for b in range(x & 7):
            res += pend[p, b]
        val[p] = first + res
    return nb


@njit(**_jit)
def _received_by_halves(positions, walk_rows, pushed, spreads, na, many, nb, placed):
    """The new residual of each receiver ``many[:nb]`` of more than 128 sends: its sends
    again (the same products), grouped into ``placed`` (where :func:`_received` said), and
    summed by :func:`_pairwise` (numpy's halves)."""
    val, held, count, blocks, at = positions[1], positions[2], positions[3], positions[5], positions[6]
    to_pos, to_prob = walk_rows[0], walk_rows[1]
    for j in range(na):
        w, spread = pushed[j], spreads[j]
        for c in range(to_pos.shape[1]):
            p = to_pos[w, c]
            if at[p] >= 0:
                placed[at[p]] = spread * to_prob[w, c]
                at[p] += 1
    for j in range(nb):
        p = many[j]
        x = count[p] + 1 - held[p]  # all its values
        lo = at[p] - x + held[p]
        if held[p]:
            val[p] = val[p] + _pairwise(placed, lo, x)
        else:
            val[p] = _group_sum(placed, lo, x)
        at[p] = -1
        for b in range(8):
            blocks[p, b] = 0.0


@njit(**_jit)
def _held_residuals(positions, m, o_node, o_value, at):
    """The residuals held at the first ``m`` positions, written into ``o_node``, ``o_value``
    from entry ``at`` (grown as needed). Returns ``(o_node, o_value, their end)``."""
    node_at, val, held = positions[0], positions[1], positions[2]
    o_node = _room(o_node, at, at + m)
    o_value = _room(o_value, at, at + m)
    for j in range(m):
        if held[j]:
            o_node[at], o_value[at] = node_at[j], val[j]
            at += 1
    return o_node, o_value, at


@njit(**_jit)
def _appended(o_node, o_value, at, node, value, lo, hi):
    """``node[lo:hi]``, ``value[lo:hi]`` written into ``o_node``, ``o_value`` from entry
    ``at`` (grown as needed); returns them."""
    o_node = _room(o_node, at, at + hi - lo)
    o_value = _room(o_value, at, at + hi - lo)
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
