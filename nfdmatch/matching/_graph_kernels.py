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
def _positions(node_at, val, held, count, pend, blocks, at, row, used, need):
    """:func:`push_sources`'s per-position work arrays with room for ``need`` positions
    (their first ``used`` kept)."""
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
def _rows(to_pos, to_prob, stays, used, need):
    """:func:`push_sources`'s rows of the walk by positions with room for ``need`` rows."""
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
    k = targets.shape[1] - 1
    keep = 1.0 - alpha
    o_status = np.empty(n, dtype=np.int64)
    o_rs = np.zeros(n + 1, dtype=np.int64)
    o_ps = np.zeros(n + 1, dtype=np.int64)
    o_rn = np.empty(max(16, len(r_node)), dtype=np.int64)
    o_rv = np.empty(len(o_rn))
    o_pn = np.empty(max(16, len(p_node)), dtype=np.int64)
    o_pv = np.empty(len(o_pn))
    missing = np.empty(16, dtype=np.int64)
    n_missing = 0
    # One source's nodes by position (slot[node]): the node, its residual, whether it holds one
    # (a pushed node holds none until it receives again), its row of the walk once pushed
    # (row: -1, or where: to_pos the targets' positions, to_prob their probabilities, stays its
    # 1 / (1 - alpha P_uu)). Within a round, what a node receives is summed as it comes, as
    # np.add.reduceat sums its group: the first value (its residual when it holds one, else
    # the first send: pend[:, 8]) plus numpy's pairwise sum of the others (the sends): those
    # pairwise are counted by ``count`` (-1 before the first send of a node that holds no
    # residual, else 0, between rounds), their blocks of 8 summed into blocks[:, 0:8] (zero
    # between rounds) as each block completes, the block not yet complete in pend[:, 0:8].
    node_at = np.empty(64, dtype=np.int64)
    val = np.empty(64)
    held = np.empty(64, dtype=np.bool_)
    count = np.empty(64, dtype=np.int64)
    pend = np.empty((64, 9))
    blocks = np.empty((64, 8))
    at = np.empty(64, dtype=np.int64)  # where the sends of a node receiving more than 128 go, else -1
    row = np.empty(64, dtype=np.int64)
    to_pos = np.empty((16, k), dtype=np.int64)
    to_prob = np.empty((16, k))
    stays = np.empty(16)
    act = np.empty(64, dtype=np.int64)  # a round's pushed nodes, ascending
    order = np.empty(64, dtype=np.int64)  # the positions by ascending node (its first ``ordered``)
    pushed = np.empty(64, dtype=np.int64)  # their rows (in to_pos)
    spreads = np.empty(64)  # alpha r_u stay_u
    recv = np.empty(64, dtype=np.int64)  # a round's receivers (positions), as first reached
    big = np.empty(64, dtype=np.int64)  # those with more than 128 sends
    placed = np.empty(64)  # their sends, grouped
    kn = np.empty(64, dtype=np.int64)  # the kept shares, in order
    kv = np.empty(64)
    for i in range(n):
        o_rs[i + 1] = o_rs[i]
        o_ps[i + 1] = o_ps[i]
        if status[i] == DONE:
            a, b = p_start[i], p_start[i + 1]
            o_pn = _room(o_pn, o_ps[i], o_ps[i] + b - a)
            o_pv = _room(o_pv, o_ps[i], o_ps[i] + b - a)
            o_pn[o_ps[i] : o_ps[i] + b - a] = p_node[a:b]
            o_pv[o_ps[i] : o_ps[i] + b - a] = p_val[a:b]
            o_ps[i + 1] = o_ps[i] + b - a
            o_status[i] = DONE
            continue
        # the source's state
        if status[i] == NEW:
            m, q = 1, 0
            node_at[0], val[0] = sources[i], 1.0
        else:
            a, b = r_start[i], r_start[i + 1]
            m = b - a
            if m > len(node_at):
                node_at, val, held, count, pend, blocks, at, row = _positions(
                    node_at, val, held, count, pend, blocks, at, row, 0, m
                )
            node_at[:m], val[:m] = r_node[a:b], r_val[a:b]
            a, b = p_start[i], p_start[i + 1]
            q = b - a
            if q > len(kn):
                kn, kv = _room(kn, 0, q), _room(kv, 0, q)
            kn[:q], kv[:q] = p_node[a:b], p_val[a:b]
        rows, ordered = 0, 0
        for j in range(m):
            slot[node_at[j]] = j
            held[j], count[j], at[j], row[j] = True, 0, -1, -1
            for b in range(8):
                blocks[j, b] = 0.0
        stopped = False
        while True:
            # the round's pushes: every residual of at least the tolerance, in ascending order
            # as the keys sort (the positions sorted again only when some were added)
            if ordered < m:
                order = np.argsort(node_at[:m])
                ordered = m
            if m > len(act):
                act = _room(act, 0, m)
            na = 0
            for j in range(m):
                p = order[j]
                if held[p] and val[p] >= tolerance:
                    act[na] = node_at[p]
                    na += 1
            if na == 0:
                break
            for j in range(na):
                if not known[act[j]]:
                    missing = _room(missing, n_missing, n_missing + 1)
                    missing[n_missing] = act[j]
                    n_missing += 1
                    stopped = True
            if stopped:
                break
            ne = na * k
            if m + ne > len(node_at):
                node_at, val, held, count, pend, blocks, at, row = _positions(
                    node_at, val, held, count, pend, blocks, at, row, m, m + ne
                )
            if rows + na > len(stays):
                to_pos, to_prob, stays = _rows(to_pos, to_prob, stays, rows, rows + na)
            if ne > len(recv):
                recv, big, placed = np.empty(2 * ne, dtype=np.int64), np.empty(2 * ne, dtype=np.int64), np.empty(2 * ne)
            if na > len(pushed):
                pushed, spreads = np.empty(2 * na, dtype=np.int64), np.empty(2 * na)
            if q + na > len(kn):
                kn, kv = _room(kn, q, q + na), _room(kv, q, q + na)
            for j in range(na):  # a pushed residual leaves (what the node receives is new)
                u = act[j]
                s = slot[u]
                if row[s] == -1:  # pushed for the first time: its row, by positions
                    for c in range(k):
                        t = targets[u, c + 1]
                        p = slot[t]
                        if p == -1:  # reached for the first time
                            p = m
                            node_at[m], held[m], count[m], at[m], row[m] = t, False, -1, -1, -1
                            for b in range(8):
                                blocks[m, b] = 0.0
                            slot[t] = m
                            m += 1
                        to_pos[rows, c] = p
                        to_prob[rows, c] = prob[u, c + 1]
                    stays[rows] = 1.0 / (1.0 - alpha * prob[u, 0])
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
            # the sends: each pushed node in turn, its row's targets in order, summed as they come
            nr = 0
            for j in range(na):
                w, spread = pushed[j], spreads[j]
                for c in range(k):
                    p = to_pos[w, c]
                    x = count[p]
                    recv[nr] = p
                    nr += x == np.int64(held[p]) - 1  # its first send of the round
                    pend[p, (x & 7) + (x < 0)] = spread * to_prob[w, c]  # (the first, x = -1: pend[p, 8])
                    x += 1
                    count[p] = x
                    if x > 0 and (x & 7) == 0:  # a block of 8 complete
                        for b in range(8):
                            blocks[p, b] += pend[p, b]
            # each receiver's new residual: the first value plus the pairwise sum of the others
            nb, grouped = 0, 0
            for j in range(nr):
                p = recv[j]
                x = count[p]
                if x > 128:  # (rare) numpy's pairwise sum by halves
                    big[nb] = p
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
            if nb:  # their sends again (the same products), grouped
                for j in range(na):
                    w, spread = pushed[j], spreads[j]
                    for c in range(k):
                        p = to_pos[w, c]
                        if at[p] >= 0:
                            placed[at[p]] = spread * to_prob[w, c]
                            at[p] += 1
                for j in range(nb):
                    p = big[j]
                    x = count[p] + 1 - held[p]  # all its values
                    lo = at[p] - x + held[p]
                    if held[p]:
                        val[p] = val[p] + _pairwise(placed, lo, x)
                    else:
                        val[p] = _group_sum(placed, lo, x)
                    at[p] = -1
                    for b in range(8):
                        blocks[p, b] = 0.0
            for j in range(nr):
                p = recv[j]
                held[p], count[p] = True, 0
        for j in range(m):
            slot[node_at[j]] = -1
        if stopped:  # the state for the next call: the residuals held, the kept shares
            o_status[i] = STOPPED
            h = o_rs[i]
            o_rn = _room(o_rn, h, h + m)
            o_rv = _room(o_rv, h, h + m)
            for j in range(m):
                if held[j]:
                    o_rn[h], o_rv[h] = node_at[j], val[j]
                    h += 1
            o_rs[i + 1] = h
            o_pn = _room(o_pn, o_ps[i], o_ps[i] + q)
            o_pv = _room(o_pv, o_ps[i], o_ps[i] + q)
            o_pn[o_ps[i] : o_ps[i] + q] = kn[:q]
            o_pv[o_ps[i] : o_ps[i] + q] = kv[:q]
            o_ps[i + 1] = o_ps[i] + q
        else:  # the estimate: each node's kept shares in round order, summed
            o_status[i] = DONE
            o_pn = _room(o_pn, o_ps[i], o_ps[i] + q)
            o_pv = _room(o_pv, o_ps[i], o_ps[i] + q)
            o_ps[i + 1] = o_ps[i] + _grouped(kn, kv, q, slot, o_pn[o_ps[i] :], o_pv[o_ps[i] :])
    missing = np.sort(missing[:n_missing])
    unique = np.ones(n_missing, dtype=np.bool_)
    for j in range(1, n_missing):
        unique[j] = missing[j] != missing[j - 1]
    return o_status, o_rs, o_rn, o_rv, o_ps, o_pn, o_pv, missing[unique]
