"""The personalised-PageRank push of the re-ranking (nfdmatch/search/diffusion.py): the
compiled push (nfdmatch/matching/_graph_kernels.py, ahead of time and numba's) gives the
numpy push's doubles, bit for bit, on random graphs and on an index's graph, and the
re-ranked answers are the same bytes whichever kernels serve (issue 23); so does the
compiled push split over threads, and the answers on one thread and two are the same."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nfdmatch.matching.kernels import NUMPY, choose, graph_push
from nfdmatch.search.diffusion import REVERSE_TOLERANCE, TOLERANCE, GraphWalk

COMPILED = ("aot", "numba")


def compiled(kind):
    """The kernels of ``kind`` (which ``make install`` provides: a fallback is a failure)."""
    kernels = choose(kind)
    assert kernels.name == kind, kernels.reason
    assert graph_push(kernels) is not None
    return kernels


def random_graph(rng, N, K, padded=0.0, hub=False, ties=False):
    """A stored graph as the index keeps it: each row's K nearest other rows, ascending
    distances, a list cut short padded with -1 / inf (a share ``padded`` of the rows).
    ``hub``: every full list ends with row 0 (a node every walk reaches at once); ``ties``:
    distances on a coarse grid (equal ones)."""
    nb = np.full((N, K), -1, dtype=np.int64)
    d = np.full((N, K), np.inf)
    for i in range(N):
        size = min(K, N - 1) if rng.random() >= padded else int(rng.integers(0, min(K, N - 1) + 1))
        others = rng.choice(N - 1, size=size, replace=False)
        others[others >= i] += 1
        dist = rng.random(size)
        if ties:
            dist = np.round(dist * 4) / 4
        dist = np.sort(dist)
        if hub and size == K and i != 0 and 0 not in others:
            others[-1], dist[-1] = 0, 1.5
        nb[i, :size], d[i, :size] = others, dist
    return nb, d


def local_graph(rng, N, K, window=30, hub=False):
    """A graph whose lists are near each row (rows i - window .. i + window, as a collection's
    families are), so that a walk stays local; ``hub``: every list ends with row 0."""
    nb = np.empty((N, K), dtype=np.int64)
    d = np.empty((N, K))
    for i in range(N):
        near = np.arange(max(0, i - window), min(N, i + window + 1))
        nb[i] = rng.choice(near[near != i], size=K, replace=False)
        d[i] = np.sort(rng.random(K))
        if hub and i and 0 not in nb[i]:
            nb[i, -1], d[i, -1] = 0, 1.5
    return nb, d


def reader_of(nb, d):
    return lambda rows: (nb[rows], d[rows])


def push(nb, d, sources, kernels, k=8, alpha=0.8, tolerance=TOLERANCE, walk=None):
    walk = walk or GraphWalk(reader_of(nb, d), len(nb), k, alpha)
    return walk.pagerank(sources, tolerance, kernels=kernels), walk


def assert_same_doubles(got, want):
    """Two pushes' triples ((start, node, value) or (src, node, value)): the same, values bit
    for bit."""
    start, node, value = got
    assert np.array_equal(start, want[0]) and np.array_equal(node, want[1])
    assert value.dtype == want[2].dtype == np.float64
    assert np.array_equal(value.view(np.int64), want[2].view(np.int64))  # bit for bit


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    N=st.integers(2, 400),
    K=st.integers(1, 10),
    k=st.integers(1, 10),
    alpha=st.sampled_from([0.5, 0.8, 0.95]),
    tolerance=st.sampled_from([1e-2, 1e-4, TOLERANCE]),
    padded=st.sampled_from([0.0, 0.2]),
    ties=st.booleans(),
    hub=st.booleans(),
)
def test_the_compiled_push_gives_the_numpy_push_bit_for_bit(seed, N, K, k, alpha, tolerance, padded, ties, hub):
    rng = np.random.default_rng(seed)
    nb, d = random_graph(rng, N, K, padded=padded, hub=hub, ties=ties)
    # any sources: repeated, in any order, the graph's every row or a few
    sources = rng.integers(0, N, size=int(rng.integers(1, 2 * N + 2)))
    want, _ = push(nb, d, sources, NUMPY, min(k, K), alpha, tolerance)
    for kind in COMPILED:
        got, walk = push(nb, d, sources, compiled(kind), min(k, K), alpha, tolerance)
        assert_same_doubles(got, want)
        again, _ = push(nb, d, sources[::-1], compiled(kind), min(k, K), alpha, tolerance, walk=walk)  # rows known
        assert_same_doubles(again, push(nb, d, sources[::-1], NUMPY, min(k, K), alpha, tolerance)[0])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    N=st.integers(2, 150),
    K=st.integers(1, 10),
    alpha=st.sampled_from([0.5, 0.8, 0.95]),
    tolerance=st.sampled_from([1e-2, 1e-4, REVERSE_TOLERANCE]),
    padded=st.sampled_from([0.0, 0.2]),
    hub=st.booleans(),
)
def test_the_walk_backwards_estimates_the_pagerank_columns_from_below(seed, N, K, alpha, tolerance, padded, hub):
    """reverse_pagerank against the dense (1 - alpha) (I - alpha P)^-1 of the same walk: for
    every row u, c_u is below sum_v A[u, v] r_v (the starting residuals r: one source on
    itself, another spread over several rows as a query laid over the graph starts) by less
    than the tolerance."""
    rng = np.random.default_rng(seed)
    nb, d = random_graph(rng, N, K, padded=padded, hub=hub)
    walk = GraphWalk(reader_of(nb, d), N, min(K, 8), alpha)
    targets, prob = walk.transitions(np.arange(N))
    P = np.zeros((N, N))
    np.add.at(P, (np.repeat(np.arange(N), targets.shape[1]), targets.ravel()), prob.ravel())
    A = (1 - alpha) * np.linalg.inv(np.eye(N) - alpha * P)
    spread = rng.choice(N, size=min(N, 3), replace=False)
    start = np.zeros((2, N))
    start[0, int(rng.integers(N))] = 1.0
    start[1, spread] = rng.random(len(spread)) * alpha
    owner = np.concatenate([[0], np.ones(len(spread), np.int64)])
    node = np.concatenate([np.flatnonzero(start[0]), spread])
    src, reached, mass = walk.reverse_pagerank(owner, node, np.concatenate([[1.0], start[1, spread]]), tolerance)
    for s in (0, 1):
        got = np.zeros(N)
        got[reached[src == s]] = mass[src == s]
        want = A @ start[s]
        assert np.all(got <= want + 1e-12) and np.all(want - got < tolerance + 1e-12)


@pytest.mark.parametrize("kind", COMPILED)
def test_a_node_receiving_from_hundreds_in_one_round_sums_as_numpy(kind):
    """A hub that every list ends with: in the rounds where hundreds of nodes push at once it
    receives hundreds of values (numpy's pairwise sum by halves above 128, by blocks of 8
    from 8); a node several rows name twice gets two values from one pusher."""
    rng = np.random.default_rng(11)
    nb, d = local_graph(rng, 3000, 10, window=200, hub=True)
    nb[5, 3] = nb[5, 2]  # the same neighbour twice in one list
    d[5, 3] = d[5, 2]
    sources = np.concatenate([[5], rng.choice(3000, 12, replace=False)])
    for k, alpha, tolerance in ((10, 0.95, 1e-6), (8, 0.8, 1e-6), (3, 0.8, TOLERANCE)):
        want, _ = push(nb, d, sources, NUMPY, k, alpha, tolerance)
        got, _ = push(nb, d, sources, compiled(kind), k, alpha, tolerance)
        assert_same_doubles(got, want)


def test_the_push_of_a_source_does_not_depend_on_the_others():
    """Each source's estimate is that of its own rounds: pushed alone, in a block of others
    or in another block of the same call (blocks of 2,048), the same doubles."""
    from nfdmatch.search import diffusion

    rng = np.random.default_rng(3)
    nb, d = local_graph(rng, 3000, 8, window=8)
    sources = rng.integers(0, 3000, size=2500)
    for kernels in (NUMPY, compiled("aot")):
        start, node, value = push(nb, d, sources, kernels, tolerance=1e-3)[0]
        for i in (0, 2047, 2048, 2499):
            alone = push(nb, d, sources[i : i + 1], kernels, tolerance=1e-3)[0]
            assert np.array_equal(alone[1], node[start[i] : start[i + 1]])
            assert np.array_equal(alone[2], value[start[i] : start[i + 1]])
    assert diffusion._SOURCE_BLOCK == 2048


class Counted:
    """A compiled push that records the sources of each of its calls (from any thread)."""

    def __init__(self, push):
        self.push, self.calls = push, []

    def __call__(self, sources, *args):
        self.calls.append(len(sources))
        return self.push(sources, *args)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    N=st.integers(2, 300),
    K=st.integers(1, 10),
    k=st.integers(1, 10),
    alpha=st.sampled_from([0.5, 0.8, 0.95]),
    tolerance=st.sampled_from([1e-2, 1e-4, TOLERANCE]),
    padded=st.sampled_from([0.0, 0.2]),
    ties=st.booleans(),
    hub=st.booleans(),
    computed=st.sampled_from([0.0, 0.5]),
)
def test_the_push_over_threads_gives_the_one_thread_push_and_the_numpy_push_bit_for_bit(
    seed, N, K, k, alpha, tolerance, padded, ties, hub, computed
):
    """The sources split over 1, 2, 3 or 8 threads: every part stops for rows of the walk
    not computed yet, at least once on a fresh walk (its sources' own rows), and resumes
    after the barrier; with a share ``computed`` of the rows computed before, parts finish
    in different rounds. The same doubles as one thread's push and as the numpy push."""
    rng = np.random.default_rng(seed)
    nb, d = random_graph(rng, N, K, padded=padded, hub=hub, ties=ties)
    k = min(k, K)
    sources = rng.integers(0, N, size=int(rng.integers(1, 2 * N + 2)))
    before = np.flatnonzero(rng.random(N) < computed)
    want = GraphWalk(reader_of(nb, d), N, k, alpha)._push(sources, tolerance)
    for kind in COMPILED:
        for workers in (1, 2, 3, 8):
            walk = GraphWalk(reader_of(nb, d), N, k, alpha)
            walk.transitions(before)
            push = Counted(graph_push(compiled(kind)))
            assert_same_doubles(walk._push_compiled(push, sources, tolerance, workers), want)
            parts = min(workers, len(sources))
            assert sum(push.calls[:parts]) == len(sources)  # the first round: every part once
            if not len(before):  # every part stopped at least once
                assert len(push.calls) >= 2 * parts


@pytest.mark.parametrize("kind", COMPILED)
def test_pagerank_splits_a_block_over_the_threads_of_a_kernel_call(kind, monkeypatch):
    """GraphWalk.pagerank pushes a block of at least _THREAD_SOURCES sources on the threads
    Kernels.workers gives a call (here as on 4 cores: set_call_threads' limit), a smaller
    block on one, and a process limited to one thread (a forked worker) on one: the same
    doubles every way."""
    from nfdmatch.matching import kernels as kernels_module
    from nfdmatch.search import diffusion

    rng = np.random.default_rng(8)
    nb, d = local_graph(rng, 2000, 8, window=20)
    sources = rng.integers(0, 2000, 300)
    threads = []
    run_all = diffusion.run_all

    def counted(calls):
        threads.append(len(calls))
        return run_all(calls)

    monkeypatch.setattr(diffusion, "run_all", counted)
    monkeypatch.setattr(kernels_module, "cpu_count", lambda: 4)
    limit = kernels_module._call_threads
    few = diffusion._THREAD_SOURCES - 1
    try:
        for call_threads, n, used in ((4, 300, 4), (2, 300, 2), (1, 300, 1), (4, few, 1), (4, few + 1, 4)):
            kernels_module.set_call_threads(call_threads)
            threads.clear()
            got, _ = push(nb, d, sources[:n], compiled(kind))
            assert max(threads) == used
            assert_same_doubles(got, push(nb, d, sources[:n], NUMPY)[0])
    finally:
        kernels_module.set_call_threads(limit)


def _slow_and_failing_calls():
    """``(finished, slow, fails)``: a call that sets the event ``finished`` after 0.2 s, and one
    that raises ValueError at once (a barrier must wait for the first before raising)."""
    import threading
    import time

    finished = threading.Event()

    def slow():
        time.sleep(0.2)
        finished.set()

    def fails():
        raise ValueError("a call that fails")

    return finished, slow, fails


def test_run_all_returns_in_order_and_raises_only_once_every_call_is_done():
    """The threaded push's barrier: no call runs on once run_all has returned or raised (the
    walk then writes the rows the kernels read)."""

    from nfdmatch.matching._threads import run_all

    assert run_all([]) == [] and run_all([lambda: 1]) == [1]
    assert run_all([lambda: 1, lambda: 2, lambda: 3]) == [1, 2, 3]
    finished, slow, fails = _slow_and_failing_calls()
    for calls in ([fails, slow], [slow, fails]):  # on the calling thread, on the pool
        finished.clear()
        with pytest.raises(ValueError):
            run_all(calls)
        assert finished.is_set()


def test_run_spread_returns_in_order_on_at_most_its_threads_never_the_callers():
    """run_spread (the fused distances per query, a push alongside): each call once, the
    results in order; with 2 threads never more than 2 calls at once and none on the calling
    thread (where a kernel call would split its rows over the busy pool); one thread: on the
    calling thread; a call's exception raised once every call is done."""
    import threading
    import time

    from nfdmatch.matching._threads import run_spread

    assert run_spread([], 2) == [] and run_spread([lambda: 1], 2) == [1]
    lock, running, most, where = threading.Lock(), [0], [0], []

    def call(i):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
            where.append(threading.current_thread())
        time.sleep(0.01 * (i % 3))
        with lock:
            running[0] -= 1
        return i * i

    calls = [lambda i=i: call(i) for i in range(12)]
    assert run_spread(calls, 2) == [i * i for i in range(12)]
    assert most[0] == 2 and len(where) == 12 and threading.current_thread() not in where
    where.clear()
    assert run_spread(calls[:3], 1) == [0, 1, 4] and set(where) == {threading.current_thread()}
    finished, slow, fails = _slow_and_failing_calls()
    with pytest.raises(ValueError):
        run_spread([fails, slow, lambda: 1], 2)
    assert finished.is_set()


def test_the_walk_backwards_reads_each_rows_stored_in_edges_once():
    """With the index's in-edges (GraphWalk(reverse=)), a walk backwards asks for each row's
    once however many rounds push it, and again for none in a second walk on the same
    GraphWalk; the same doubles as the lists turned round in memory (no reader)."""
    from nfdmatch.index.graph import reverse_of

    rng = np.random.default_rng(5)
    nb, d = local_graph(rng, 600, 10, window=25)
    start, source = reverse_of(nb[:, :8], len(nb))
    asked = []

    def in_edges(rows):
        asked.extend(rows.tolist())
        return start[rows + 1] - start[rows], np.concatenate([source[start[r] : start[r + 1]] for r in rows])

    owner = np.array([0, 1, 1, 2])
    node, residual = np.array([7, 300, 310, 599]), np.array([1.0, 0.3, 0.2, 1.0])
    stored = GraphWalk(reader_of(nb, d), len(nb), 8, 0.8, in_edges)
    got = stored.reverse_pagerank(owner, node, residual)
    assert len(asked) == len(set(asked)) > 100  # pushed in many rounds, each row asked for once
    again = stored.reverse_pagerank(owner[::-1], node[::-1], residual[::-1])
    assert len(asked) == len(set(asked))
    in_memory = GraphWalk(reader_of(nb, d), len(nb), 8, 0.8)
    assert_same_doubles(got, in_memory.reverse_pagerank(owner, node, residual))
    assert_same_doubles(again, in_memory.reverse_pagerank(owner[::-1], node[::-1], residual[::-1]))


def test_the_kernels_choose_the_push():
    from nfdmatch.matching import aot

    assert graph_push(NUMPY) is None and graph_push(choose("numpy")) is None
    assert graph_push(compiled("aot")) is aot.load().push_sources
    assert graph_push(compiled("numba")).__name__ == "push_sources"


def test_the_ahead_of_time_push_export_forwards_and_returns():
    pytest.importorskip("numba")
    import inspect

    from nfdmatch.matching import _graph_kernels, aot

    forward = aot._forwarding(_graph_kernels.push_sources, returns=True)
    assert list(inspect.signature(forward).parameters) == list(
        inspect.signature(_graph_kernels.push_sources.py_func).parameters
    )
    rng = np.random.default_rng(5)
    nb, d = random_graph(rng, 50, 8)
    walk = GraphWalk(reader_of(nb, d), 50, 8, 0.8)
    walk.transitions(np.arange(50))
    n = 3
    state = (np.zeros(n, np.int64), np.zeros(n + 1, np.int64), np.zeros(0, np.int64), np.zeros(0))
    state += (np.zeros(n + 1, np.int64), np.zeros(0, np.int64), np.zeros(0))
    args = (np.array([0, 7, 7]), *state, walk._targets, walk._prob, walk._walk_known, np.full(51, -1), 0.8, 1e-5)
    got, want = forward(*args), _graph_kernels.push_sources(*args)
    assert all(np.array_equal(a, b) for a, b in zip(got[:2] + got[4:5] + got[-1:], want[:2] + want[4:5] + want[-1:]))
    used = got[4][-1]  # (the arrays have room beyond what they hold)
    assert np.array_equal(got[5][:used], want[5][:used]) and np.array_equal(got[6][:used], want[6][:used])
    assert list(got[0]) == [_graph_kernels.DONE] * 3 and len(got[-1]) == 0 and got[1][-1] == 0


def test_a_process_pushing_on_the_ahead_of_time_kernels_does_not_import_numba():
    compiled("aot")
    code = (
        "import sys, numpy as np\n"
        "from nfdmatch.search.diffusion import GraphWalk\n"
        "rng = np.random.default_rng(0)\n"
        "nb = np.array([rng.permutation(np.delete(np.arange(200), i))[:10] for i in range(200)])\n"
        "d = np.sort(rng.random((200, 10)), axis=1)\n"
        "start, node, value = GraphWalk(lambda r: (nb[r], d[r]), 200, 8, 0.8).pagerank(np.arange(200))\n"
        "print(sys.modules.get('numba') is not None, len(start) == 201)\n"
    )
    env = {key: v for key, v in os.environ.items() if key != "NFDMATCH_KERNELS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == ["False", "True"]


# --------------------------------------------------------------------------- an index's graph


@pytest.fixture(scope="module")
def families(tmp_path_factory):
    """An index of 12 generated families of 10 curves with its graph (--graph 10)."""
    from test_rerank import family_curves, write_parts

    from nfdmatch.index import build_index

    folder = tmp_path_factory.mktemp("push")
    curves, _ = family_curves(np.random.default_rng(23), families=12, members=10)
    write_parts(folder / "c", curves, 2)
    build_index([folder / "c"], folder / "i.h5", jobs=1, graph=10)
    return folder


@pytest.mark.slow
def test_the_compiled_push_on_an_index_graph_is_the_numpy_push(families):
    from nfdmatch.index import open_index
    from nfdmatch.search.rerank import ALPHA, SCALE_NEIGHBOURS

    with open_index(families / "i.h5") as idx:
        every = np.arange(idx.n_curves)
        want = GraphWalk(idx.graph_reader(), idx.n_curves, SCALE_NEIGHBOURS, ALPHA).pagerank(every, kernels=NUMPY)
        for kind in COMPILED:
            walk = GraphWalk(idx.graph_reader(), idx.n_curves, SCALE_NEIGHBOURS, ALPHA)
            assert_same_doubles(walk.pagerank(every, kernels=compiled(kind)), want)


@pytest.mark.slow
@pytest.mark.parametrize("kind", COMPILED)
@pytest.mark.parametrize("candidates", ["exact", "walk"])
def test_the_reranked_answers_are_the_same_with_the_numpy_push(families, candidates, kind, monkeypatch):
    """The compiled push changes no answer: the same bytes as with the numpy push under the
    same kernels. (Across kernel kinds the exact distances of the reported rows differ at
    the rounding level, ~1e-15 relative, as every search's do; so scores may in the last
    digit: docs/architecture.md, "Which kernels compute".)"""
    from test_rerank import _read_back

    from nfdmatch import Curve
    from nfdmatch.index import open_index
    from nfdmatch.matching import kernels
    from nfdmatch.search import diffusion
    from nfdmatch.search.rerank import rerank_index

    stored = _read_back(families / "c")
    queries = stored[::7] + [Curve(stored[3].points * 1.01 + 0.002, id="perturbed")]
    before = kernels.current()
    answers = []
    try:
        assert kernels.use_kernels(kind).name == kind
        for numpy_push in (False, True):
            if numpy_push:  # the test hook: the walk then pushes with numpy
                monkeypatch.setattr(diffusion, "graph_push", lambda kernels=None: None)
            with open_index(families / "i.h5") as idx:
                answers.append(
                    [
                        rerank_index(idx, queries, k=20, exclude_self=exclude, candidates=candidates)[0]
                        for exclude in (False, True)
                    ]
                )
    finally:
        kernels.use_kernels(before)
    assert answers[0] == answers[1]
    assert all(len(res) == 20 for res in answers[0][0])


@pytest.mark.slow
@pytest.mark.parametrize("kind", COMPILED)
@pytest.mark.parametrize("candidates", ["exact", "walk"])
def test_the_reranked_answers_are_the_same_with_the_push_on_one_and_two_threads(
    families, candidates, kind, monkeypatch
):
    from test_rerank import _read_back

    from nfdmatch.index import open_index
    from nfdmatch.matching import kernels
    from nfdmatch.search import diffusion
    from nfdmatch.search.rerank import rerank_index

    stored = _read_back(families / "c")
    queries = stored[::5]
    threads = []
    run_all = diffusion.run_all

    def counted(calls):
        threads.append(len(calls))
        return run_all(calls)

    monkeypatch.setattr(diffusion, "run_all", counted)
    monkeypatch.setattr(kernels, "cpu_count", lambda: 2)
    before, limit = kernels.current(), kernels._call_threads
    answers = []
    try:
        assert kernels.use_kernels(kind).name == kind
        for call_threads in (1, 2):
            kernels.set_call_threads(call_threads)
            threads.clear()
            with open_index(families / "i.h5") as idx:
                answers.append(rerank_index(idx, queries, k=20, candidates=candidates)[0])
            assert max(threads) == call_threads
    finally:
        kernels.use_kernels(before)
        kernels.set_call_threads(limit)
    assert answers[0] == answers[1]
    assert all(len(res) == 20 for res in answers[0])
