"""The neighbour graph of `index build --graph K --scheduler`: its rows searched by the Dask
workers, which read them from the new index file (closed meanwhile, then reopened to write
the graph); the stored graph is the local build's, byte for byte, fresh and incremental.
A LocalCluster of 2 worker processes, once for the module."""

from __future__ import annotations

import json
import os
import signal

import h5py
import numpy as np
import pytest

pytest.importorskip("distributed")

from conftest import run_cli as run  # noqa: E402
from oracle import random_rigid_motion, smooth_curve_samplings, start_shift  # noqa: E402

from nfdmatch import Curve, write_curves  # noqa: E402
from nfdmatch.distributed import ClusterError  # noqa: E402
from nfdmatch.index import build_index, open_index  # noqa: E402

pytestmark = pytest.mark.slow


def _family_files(folder, rng, families: int, first: int = 0) -> None:
    """``families`` families of 6 curves, one OBJ file each."""
    for f in range(first, first + families):
        versions = smooth_curve_samplings(rng, [int(rng.integers(60, 120)) for _ in range(6)], n_harmonics=4)
        curves = [
            Curve(random_rigid_motion(start_shift(pts + rng.normal(scale=0.01, size=pts.shape), 5), rng), id=str(m))
            for m, pts in enumerate(versions)
        ]
        write_curves(folder / f"family-{f:02d}.obj", curves)


@pytest.fixture
def library(tmp_path):
    """240 curves in 40 files, and the folder their indexes go to."""
    folder = tmp_path / "curves"
    folder.mkdir()
    _family_files(folder, np.random.default_rng(6), 40)
    return folder


def _graph_bytes(path):
    with h5py.File(path, "r") as h5:
        g = h5["graph"]
        return dict(g.attrs.items()), g["neighbour"][...].tobytes(), g["distance"][...].tobytes()


def _no_temp_files(folder) -> bool:
    return [p.name for p in folder.iterdir() if ".tmp-" in p.name] == []


def test_a_cluster_graph_is_the_local_graph_byte_for_byte_fresh_and_incremental(cluster, library, monkeypatch):
    from nfdmatch.search import graph

    monkeypatch.setattr(graph, "_BLOCK_ROWS", 32)  # several blocks: several tasks on both workers
    local, remote = library.parent / "local.h5", library.parent / "remote.h5"
    seen = {"local": [], "remote": []}  # the progress of the graph's search, row counts
    rl = build_index([library], local, jobs=2, graph=8, graph_progress=lambda *c: seen["local"].append(c))
    rr = cluster.build_index([library], remote, graph=8, graph_progress=lambda *c: seen["remote"].append(c))
    assert _graph_bytes(local) == _graph_bytes(remote)
    assert (rl.graph.searched, rr.graph.searched) == (240, 240)
    for calls in seen.values():
        assert calls[0] == (0, 240) and calls[-1] == (240, 240) and len(calls) > 2
        assert [done for done, _ in calls] == sorted(done for done, _ in calls)
    assert (rl.graph.scheduler, rl.graph.workers) == ("", 0)
    assert (rr.graph.scheduler, rr.graph.workers, rr.graph.processes) == (cluster.address, 2, 0)
    assert _no_temp_files(library.parent)
    # every worker closed the file it read the rows from
    assert all(not any(".tmp-" in p for p in paths) for paths in cluster.client.run(_open_paths).values())

    # incremental: a family changed, one removed, two added: the new rows join the whole
    # index, the copied rows' lists take the new rows in
    rng = np.random.default_rng(7)
    (library / "family-03.obj").unlink()
    _family_files(library, rng, 1, first=5)
    _family_files(library, rng, 2, first=40)
    rl = build_index([library], local, jobs=2, allow_shrink=True)
    rr = cluster.build_index([library], remote, allow_shrink=True)
    assert _graph_bytes(local) == _graph_bytes(remote)
    assert (rr.graph.searched, rr.graph.updated, rr.graph.kept) == (rl.graph.searched, rl.graph.updated, rl.graph.kept)
    assert 0 < rr.graph.searched < 240 and rr.graph.updated > 0 and rr.graph.scheduler == cluster.address
    with open_index(remote) as idx:
        assert idx.n_curves == 246 and idx.graph_k() == 8


def test_a_cluster_graph_of_fused_distances_is_the_local_one(cluster, library):
    """--graph K --elastic on the cluster: the exact candidates searched by the workers, the
    fused lists computed in the building process from the reopened file (it had no reader of
    the rows left: a TypeError before), the same bytes as a local build's over 2 processes."""
    from nfdmatch.index.graph import GraphSpec

    local, remote = library.parent / "local.h5", library.parent / "remote.h5"
    build_index([library], local, jobs=2, graph=GraphSpec(8, "fused"))
    rr = cluster.build_index([library], remote, graph=GraphSpec(8, "fused"))
    assert _graph_bytes(local) == _graph_bytes(remote)
    assert rr.graph.distance == "fused" and rr.graph.scheduler == cluster.address
    assert _no_temp_files(library.parent)


def _open_paths():
    """Run on a worker: the index files its search tasks hold open."""
    from nfdmatch.distributed import search_tasks

    return [key[0] for key in search_tasks._OPEN]


def test_cli_build_with_graph_on_the_scheduler_says_where_the_graph_was_searched(client, library):
    index = library.parent / "i.h5"
    address = client.scheduler.address
    code, out, err = run("index", "build", library, "--index", index, "--graph", "8", "--scheduler", address)
    assert code == 0 and out == "" and "Traceback" not in err
    assert "graph of 8 neighbours: 240 rows searched, 0 updated by new curves, 0 kept;" in err
    assert f"on the cluster at {address} (2 workers)" in err
    code, out, err = run("index", "build", "--index", index, "--graph", "6", "--scheduler", address, "--format", "json")
    assert code == 0
    summary = json.loads(out)["graph"]
    assert summary["k"] == 6 and summary["searched"] == 240
    assert (summary["where"], summary["scheduler"], summary["workers"], summary["processes"]) == (
        "cluster",
        address,
        2,
        0,
    )
    code, out, err = run("index", "build", "--index", index, "--graph", "5", "--jobs", "1", "--format", "json")
    summary = json.loads(out)["graph"]
    assert (summary["where"], summary["scheduler"], summary["workers"]) == ("local", None, 0)


def _graph_tasks_fail():
    """Run on every worker: each graph search raises (a bug, a bad node)."""
    from nfdmatch.search import graph

    def fail(*args, **kwargs):
        raise RuntimeError("the node's search broke")

    graph.real_nearest_others = graph.nearest_others
    graph.nearest_others = fail


def _graph_tasks_work():
    from nfdmatch.search import graph

    graph.nearest_others = graph.real_nearest_others


def test_a_graph_task_failing_on_every_try_is_a_clear_error_and_the_old_index_stays(client, library):
    index = library.parent / "i.h5"
    build_index([library], index, jobs=1)
    before = index.read_bytes()
    client.run(_graph_tasks_fail)
    try:
        code, out, err = run(
            "index", "build", "--index", index, "--graph", "8", "--scheduler", client.scheduler.address
        )
    finally:
        client.run(_graph_tasks_work)
    assert code == 2 and out == ""
    assert err.startswith("Error: a graph task failed on every try: RuntimeError: the node's search broke")
    assert "Traceback" not in err
    assert index.read_bytes() == before and _no_temp_files(library.parent)
    with open_index(index) as idx:
        assert idx.graph_k() == 0


def _kill_on_first_graph_task():
    """Run on every worker: its first graph search kills the worker process (a crash, an OOM
    kill); the nanny starts a fresh process, without this trap."""
    from nfdmatch.search import graph

    def die(*args, **kwargs):
        os._exit(17)

    graph.nearest_others = die


def test_a_worker_that_dies_in_a_graph_task_is_replaced_and_the_graph_is_the_same(
    client, cluster, library, monkeypatch
):
    from nfdmatch.search import graph

    monkeypatch.setattr(graph, "_BLOCK_ROWS", 32)
    local, remote = library.parent / "local.h5", library.parent / "remote.h5"
    build_index([library], local, jobs=1, graph=8)
    before = set(client.scheduler_info()["workers"])
    client.run(_kill_on_first_graph_task)
    report = cluster.build_index([library], remote, graph=8)
    assert report.graph.searched == 240 and _graph_bytes(local) == _graph_bytes(remote)
    client.wait_for_workers(2, timeout=60)
    assert before - set(client.scheduler_info()["workers"])  # workers died and were replaced


def test_a_worker_that_cannot_see_the_index_folder_says_so(tmp_path):
    from nfdmatch.distributed.search_tasks import graph_part

    missing = str(tmp_path / "elsewhere" / ".i.h5.tmp-1-00.h5")
    with pytest.raises(ClusterError, match="storage every worker sees under the same path") as got:
        graph_part(missing, (1, "", 128, 16, "rms"), np.arange(1), 8)
    assert got.value.path == missing


def _slow_graph_tasks():
    """Run on every worker: each graph search waits first (time to interrupt the build)."""
    import time

    from nfdmatch.search import graph

    real = graph.real_nearest_others = graph.nearest_others

    def slow(*args, **kwargs):
        time.sleep(1.0)
        return real(*args, **kwargs)

    graph.nearest_others = slow


def test_an_interrupted_cluster_graph_leaves_the_old_index_and_no_file_open(client, cluster, library, monkeypatch):
    import _thread
    import threading

    from nfdmatch.search import graph

    monkeypatch.setattr(graph, "_BLOCK_ROWS", 16)  # 15 blocks of a second each
    index = library.parent / "i.h5"
    build_index([library], index, jobs=1)
    before = index.read_bytes()
    client.run(_slow_graph_tasks)
    timers = []
    searching = cluster._run_graph_tasks

    def interrupted(*args):
        # Ctrl-C (as the CLI's handler raises it) half a second into the graph's search
        timers.append(threading.Timer(0.5, _thread.interrupt_main))
        timers[-1].start()
        return searching(*args)

    monkeypatch.setattr(cluster, "_run_graph_tasks", interrupted)
    # Python's own Ctrl-C handler even when the test run inherited SIGINT ignored (`make test &`
    # from a non-interactive shell): interrupt_main does nothing then
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            cluster.build_index([library], index, graph=8)
    finally:
        signal.signal(signal.SIGINT, previous)
        for timer in timers:
            timer.cancel()
        client.run(_graph_tasks_work)
    assert len(timers) == 1
    assert index.read_bytes() == before and _no_temp_files(library.parent)
    assert all(not any(".tmp-" in p for p in paths) for paths in client.run(_open_paths).values())
