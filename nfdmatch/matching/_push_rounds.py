"""One source's synchronous rounds of the compiled personalised-PageRank push
(:func:`._graph_kernels.push_sources`, whose module says why they give the numpy push's
doubles, bit for bit), and numpy's pairwise sum that they, and a done source's estimate,
sum with.

The sums are made as the values come, without sorting: a node's values of the round are
counted (the first one apart when it holds no residual), each complete block of 8 is added
into 8 accumulators (numpy's 8-way loop), the block not complete yet kept; at the round's
end the accumulators are combined as numpy does, then the incomplete block added one value
after the other (below 8 values: only those, from 0.0). A node receiving more than 128
values in one round (numpy then halves) has its values placed in order and summed by
:func:`_pairwise`. The work is the synchronous rounds' all the same (every residual of at
least the tolerance is pushed again every round): at 100,000 curves ~1,170 pushes per
source, ~90 ns each (its 8 sends included).

``cache=True``, ``nogil=True``, ``error_model="numpy"`` as in :mod:`._kernels`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["group_sum", "positions_with_room", "source_rounds", "with_room"]

_jit = dict(nogil=True, cache=True, error_model="numpy")


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
def group_sum(values, lo, n):
    """``np.add.reduceat``'s sum of one group ``values[lo:lo + n]`` (n >= 1): the first value,
    plus the pairwise sum of the rest."""
    if n == 1:
        return values[lo]
    return values[lo] + _pairwise(values, lo + 1, n - 1)


@njit(**_jit)
def with_room(a, used, need):
    """``a``, or a copy with room for ``need`` entries (its first ``used`` kept, as many as
    it has)."""
    if need <= len(a):
        return a
    b = np.empty(max(need, 2 * len(a)), dtype=a.dtype)
    used = min(used, len(a))
    b[:used] = a[:used]
    return b


@njit(**_jit)
def positions_with_room(positions, used, need):
    """The push's per-position work arrays (:func:`._graph_kernels._work_arrays`) with room
    for ``need`` positions (their first ``used`` kept)."""
    node_at, val, held, count, pend, blocks, at, row = positions
    if need > len(pend):
        size = max(need, 2 * len(pend))
        grown_pend, grown_blocks = np.empty((size, 9)), np.empty((size, 8))
        grown_pend[:used], grown_blocks[:used] = pend[:used], blocks[:used]
        pend, blocks = grown_pend, grown_blocks
    return (
        with_room(node_at, used, need),
        with_room(val, used, need),
        with_room(held, used, need),
        with_room(count, used, need),
        pend,
        blocks,
        with_room(at, used, need),
        with_room(row, used, need),
    )


@njit(**_jit)
def _rows(walk_rows, used, need):
    """The push's rows of the walk by positions (:func:`._graph_kernels._work_arrays`) with
    room for ``need`` rows (their first ``used`` kept)."""
    to_pos, to_prob, stays = walk_rows
    if need <= len(stays):
        return to_pos, to_prob, stays
    size = max(need, 2 * len(stays))
    grown_pos = np.empty((size, to_pos.shape[1]), dtype=np.int64)
    grown_prob = np.empty((size, to_pos.shape[1]))
    grown_pos[:used], grown_prob[:used] = to_pos[:used], to_prob[:used]
    return grown_pos, grown_prob, with_room(stays, used, need)


@njit(**_jit)
def source_rounds(work, m, q, targets, prob, known, slot, alpha, tolerance, missing, n_missing):
    """One source's synchronous rounds from its state in ``work`` (:func:`._graph_kernels._source_state`: ``m``
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
            act = with_room(act, 0, m)
        na = _active(positions, order, m, tolerance, act)
        if na == 0:
            break
        missing, n_missing, stopped = _unknown(act, na, known, missing, n_missing)
        if stopped:
            break
        ne = na * k
        if m + ne > len(positions[0]):
            positions = positions_with_room(positions, m, m + ne)
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
            kept = (with_room(kept[0], q, q + na), with_room(kept[1], q, q + na))
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
            missing = with_room(missing, n_missing, n_missing + 1)
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
    ``spreads[j]``), its row's targets in order, summed as they come (:func:`._graph_kernels._work_arrays`:
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
            val[p] = group_sum(placed, lo, x)
        at[p] = -1
        for b in range(8):
            blocks[p, b] = 0.0
