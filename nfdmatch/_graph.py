"""Undirected segment graphs: chaining 2-point segments into loops, splitting loops at
branching points, counting connected components.

Used by the curve readers (OBJ ``l a b`` and VTK_LINE segments: :func:`chain_segments`,
which refuses a branching point) and by mesh extraction (section and boundary edges:
:func:`closed_loops`, which splits loops at branching points and counts the open pieces).
Both first drop self-segments and repeated segments the same way (:func:`unique_segments`).
An internal module (no public API): its functions are tested directly.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .errors import ParseError

__all__ = ["unique_segments", "chain_segments", "closed_loops", "split_branching", "count_components"]


def unique_segments(segments) -> tuple[np.ndarray, np.ndarray]:
    """``segments`` (array-like (m, 2) of int) without self-segments ``(a, a)`` and without
    repeats (``a b`` again, in either direction; the first occurrence kept), in their order:
    ``(seg (k, 2) int64, order (k,) int64)``, ``order`` the kept segments' positions."""
    seg = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    order = np.arange(len(seg))
    keep = seg[:, 0] != seg[:, 1]
    seg, order = seg[keep], order[keep]
    if len(seg) == 0:
        return seg, order
    key = np.sort(seg, axis=1)
    _, first_idx = np.unique(key, axis=0, return_index=True)
    first_idx.sort()
    return seg[first_idx], order[first_idx]


def chain_segments(
    segments,
    *,
    path: str | None = None,
    vertex_label: Callable[[int], str] | None = None,
    segment_where: Callable[[int], str] | None = None,
) -> list[tuple[int, np.ndarray]]:
    """Chain undirected 2-point segments into loops (or open paths).

    Parameters
    ----------
    segments : array-like (m, 2) of int, vertex indices (any non-negative base).
        Self-segments ``(a, a)`` and repeated segments (``a b`` twice, in
        either direction) are dropped silently.
    path : file name used in error messages.
    vertex_label : maps a vertex index to how the format names it in messages
        (e.g. 1-based for OBJ). Default: ``str(v)``.
    segment_where : maps a segment's position in ``segments`` to a location
        text for messages (e.g. ``"line 12"``). Optional.

    Returns
    -------
    list of ``(first, vertices)`` in order of ``first``, where ``first`` is the
    position in ``segments`` of the component's earliest segment and
    ``vertices`` is an (k,) int64 array of vertex indices in walking order,
    never repeating the start. Each connected component whose vertices all have
    degree 2 is a closed loop, walked from the earliest segment in that
    segment's direction; a simple path (two degree-1 ends) is returned the same
    way, its closing edge being implicit.

    Raises
    ------
    ParseError : a vertex used by more than two segments (a branching point).
    """
    label = vertex_label or str
    seg = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    if len(seg) == 0:
        return []
    seg, order = unique_segments(seg)
    if len(seg) == 0:
        return []

    verts, inv = np.unique(seg.ravel(), return_inverse=True)
    local = inv.reshape(-1, 2)
    nv = len(verts)
    degree = np.bincount(local.ravel(), minlength=nv)
    if degree.max() > 2:
        _refuse_branching(local, degree, verts, order, path, label, segment_where)
    nbr_l = _neighbours(local, degree, nv)
    visited = bytearray(nv)
    result: list[tuple[int, np.ndarray]] = []

    def walk(start: int, nxt: int) -> tuple[list[int], bool]:
        """Vertices from ``start`` via ``nxt`` until a dead end or back at ``start``."""
        out = [start]
        visited[start] = 1
        prev, cur = start, nxt
        while cur != -1 and cur != start:
            out.append(cur)
            visited[cur] = 1
            n0, n1 = nbr_l[cur]
            prev, cur = cur, (n1 if n0 == prev else n0)
        return out, cur == start

    # segments are in file order (first_idx sorted): the earliest segment of a
    # component not yet visited starts that component, in its own direction
    for s, (a, b) in enumerate(local.tolist()):
        if visited[a]:
            continue
        forward, closed = walk(a, b)
        if not closed:
            n0, n1 = nbr_l[a]
            other = n1 if n0 == b else n0
            if other != -1:
                backward, _ = walk(a, other)
                forward = backward[:0:-1] + forward
        result.append((int(order[s]), verts[np.array(forward, dtype=np.int64)]))
    return result


def _refuse_branching(local, degree, verts, order, path, label, segment_where) -> None:
    """The ParseError for the first vertex of degree above 2, naming (where given) the
    places of up to five of its segments."""
    v = int(np.flatnonzero(degree > 2)[0])
    users = np.flatnonzero((local == v).any(axis=1))
    where = ""
    if segment_where is not None:
        shown = ", ".join(segment_where(int(order[u])) for u in users[:5])
        more = ", ..." if len(users) > 5 else ""
        where = f" ({shown}{more})"
    raise ParseError(
        f"vertex {label(int(verts[v]))} is shared by {int(degree[v])} line segments{where}: "
        "it is a branching point, but each curve must be a simple loop",
        path=path,
    )


def _neighbours(local: np.ndarray, degree: np.ndarray, nv: int) -> list[list[int]]:
    """Adjacency of a graph whose vertices have degree 1 or 2: per vertex its two
    neighbours (-1 for none), as lists (walked vertex by vertex in Python)."""
    ends = np.concatenate([local[:, 0], local[:, 1]])
    others = np.concatenate([local[:, 1], local[:, 0]])
    by_vertex = np.argsort(ends, kind="stable")
    start = np.searchsorted(ends[by_vertex], np.arange(nv))
    nbr = np.full((nv, 2), -1, dtype=np.int64)
    nbr[:, 0] = others[by_vertex[start]]
    two = degree == 2
    nbr[two, 1] = others[by_vertex[start[two] + 1]]
    return nbr.tolist()


def closed_loops(segments) -> tuple[list[np.ndarray], int, int]:
    """Closed loops of an undirected segment graph.

    Parameters
    ----------
    segments : (m, 2) int array of vertex ids; self-segments and repeated
        segments are ignored.

    Returns
    -------
    ``(loops, open_pieces, branching)``: loops as (k,) int64 id arrays in walking
    order (closing edge implicit); the number of open pieces dropped; the number
    of ids used by more than two segments. Without branching this is
    :func:`chain_segments` keeping its closed
    components; with branching see :func:`split_branching`.
    """
    seg, _ = unique_segments(segments)
    if len(seg) == 0:
        return [], 0, 0
    degree = np.bincount(seg.ravel())
    branching = int((degree > 2).sum())
    if branching:
        loops, open_pieces = split_branching(seg)
        return loops, open_pieces, branching
    components = chain_segments(seg)  # degree <= 2 here: it cannot find a branch
    loops, open_pieces = [], 0
    for _, ids in components:
        if (degree[ids] == 2).all():
            loops.append(ids)
        else:
            open_pieces += 1
    return loops, open_pieces, 0


def split_branching(seg: np.ndarray) -> tuple[list[np.ndarray], int]:
    """Simple loops of a segment graph with branching vertices, and the number of open pieces.

    ``seg`` (m, 2) int64, no self or repeated segments. Dangling branches are
    pruned first (each connected group of pruned segments is one open piece);
    the rest is walked edge by edge, cutting off a simple loop whenever the walk
    comes back to a vertex already on it; a walk that gets stuck (possible with
    odd degrees, e.g. a theta shape) leaves its unclosed part as an open piece.
    """
    m = len(seg)
    adjacency: dict[int, list[tuple[int, int]]] = {}
    for e, (u, v) in enumerate(seg.tolist()):
        adjacency.setdefault(u, []).append((v, e))
        adjacency.setdefault(v, []).append((u, e))
    alive = [True] * m
    degree = {v: len(n) for v, n in adjacency.items()}

    # prune dangling branches
    pruned: list[int] = []
    stack = [v for v, k in degree.items() if k == 1]
    while stack:
        v = stack.pop()
        if degree[v] != 1:
            continue
        for w, e in adjacency[v]:
            if alive[e]:
                alive[e] = False
                pruned.append(e)
                degree[v] -= 1
                degree[w] -= 1
                if degree[w] == 1:
                    stack.append(w)
                break
    open_pieces = count_components(seg[pruned]) if pruned else 0

    loops: list[np.ndarray] = []
    used = [not a for a in alive]
    cursor = {v: 0 for v in adjacency}

    def next_edge(v: int):
        nbrs = adjacency[v]
        i = cursor[v]
        while i < len(nbrs) and used[nbrs[i][1]]:
            i += 1
        cursor[v] = i
        return nbrs[i] if i < len(nbrs) else None

    for e0 in range(m):
        if used[e0]:
            continue
        used[e0] = True
        u, v = int(seg[e0, 0]), int(seg[e0, 1])
        path, position = [u, v], {u: 0, v: 1}
        while True:
            step = next_edge(path[-1])
            if step is None:
                if len(path) > 1:
                    open_pieces += 1
                break
            w, e = step
            used[e] = True
            if w in position:
                i = position[w]
                loops.append(np.array(path[i:], dtype=np.int64))
                for x in path[i + 1 :]:
                    del position[x]
                del path[i + 1 :]
                if len(path) == 1 and next_edge(w) is None:
                    break
            else:
                position[w] = len(path)
                path.append(w)
    return loops, open_pieces


def count_components(seg: np.ndarray) -> int:
    """Number of connected components of the graph with edges ``seg`` (m, 2) int64."""
    parent: dict[int, int] = {}

    def find(x: int) -> int:
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for u, v in seg.tolist():
        ru, rv = find(u), find(v)
        if ru != rv:
            parent[ru] = rv
    return len({find(x) for x in parent})
