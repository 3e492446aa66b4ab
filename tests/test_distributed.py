"""Building and querying on a Dask cluster (--scheduler): a LocalCluster of 2 worker
processes on the loopback, started once for the module."""

from __future__ import annotations

import os
import socket
import time
import sys

import h5py
import numpy as np
import pytest

pytest.importorskip("distributed")

from conftest import run_cli  # noqa: E402
from oracle import random_rigid_motion, smooth_curve_samplings, start_shift  # noqa: E402

from nfdmatch import Curve, read_curves, write_curves  # noqa: E402
from nfdmatch.distributed import ClusterError, connect  # noqa: E402
from nfdmatch.index import build_index, open_index  # noqa: E402
from nfdmatch.search import search_index  # noqa: E402

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow

#: attributes that record when a file was written, not what it holds
_TIMES = {"created", "updated"}


run = run_cli


def _families(rng, families, members):
    curves = []
    for _f in range(families):
        for _m, pts in enumerate(
            smooth_curve_samplings(
                rng, [int(rng.integers(60, 160)) for _ in range(members)], n_harmonics=int(rng.integers(2, 7))
            )
        ):
            pts = pts + rng.normal(scale=0.01, size=pts.shape)
            curves.append(random_rigid_motion(start_shift(pts, int(rng.integers(len(pts)))), rng))
    return curves


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    """600 curves in 30 OBJ files, 3 single-curve CSV files and one broken CSV file."""
    rng = np.random.default_rng(13)
    folder = tmp_path_factory.mktemp("library")
    curves = _families(rng, 60, 10)
    order = rng.permutation(len(curves))
    for f in range(30):
        write_curves(str(folder / f"part-{f:02d}.obj"), [curves[i] for i in order[f * 20 : (f + 1) * 20]])
    for f, pts in enumerate(_families(rng, 3, 1)):
        write_curves(str(folder / f"single-{f}.csv"), pts)
    (folder / "broken.csv").write_text("x,y,z\n1,2,3\n4,oops,6\n")
    queries = [
        Curve(random_rigid_motion(start_shift(c, 7)[::-1], rng), id=f"q{i}") for i, c in enumerate(curves[::37])
    ] + [Curve(c, id=f"new{i}") for i, c in enumerate(_families(rng, 4, 1))]
    return folder, queries


def _contents(path):
    """Every dataset and attribute of an HDF5 file, times of writing left out."""
    out = {}
    with h5py.File(path, "r") as h5:
        out["/"] = {k: v for k, v in h5.attrs.items() if k not in _TIMES}

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = (obj.dtype.str, obj[...])
            out[name + "@attrs"] = dict(obj.attrs.items())

        h5.visititems(visit)
    return out


def _assert_same_file(a, b):
    ca, cb = _contents(a), _contents(b)
    assert sorted(ca) == sorted(cb)
    assert "curves/coefficients" in ca and "search/cell_start" in ca and "files/path" in ca
    for name in ca:
        if isinstance(ca[name], tuple):
            assert ca[name][0] == cb[name][0], name
            assert ca[name][1].shape == cb[name][1].shape, name
            assert np.array_equal(ca[name][1], cb[name][1]), name
        else:
            assert ca[name].keys() == cb[name].keys(), name
            for key in ca[name]:
                assert np.array_equal(ca[name][key], cb[name][key]), (name, key)


def test_a_cluster_build_writes_the_index_a_local_build_writes(cluster, library, tmp_path, monkeypatch):
    from nfdmatch.search import cells

    monkeypatch.setattr(cells, "ROWS_PER_CELL", 16)  # many cells: the query test splits them
    folder, _ = library
    local, remote = tmp_path / "local.h5", tmp_path / "remote.h5"
    rl = build_index([str(folder)], str(local), jobs=1)
    rr = cluster.build_index([str(folder)], str(remote))
    assert (rr.added, rr.failed, rr.curves, rr.written) == (rl.added, rl.failed, rl.curves, True) == (33, 1, 603, True)
    assert rr.failures == rl.failures and "oops" in rr.failures[0][1]
    _assert_same_file(local, remote)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp file left

    # incremental: one file changed, one removed, one added -- still the local build's file
    os.utime(folder / "part-03.obj", ns=(1, 1))
    (folder / "single-2.csv").rename(tmp_path / "moved.csv")
    write_curves(str(folder / "late.csv"), read_curves(str(tmp_path / "moved.csv"))[0].points * 2.0)
    try:
        rl = build_index([str(folder)], str(local), jobs=2)
        rr = cluster.build_index([str(folder)], str(remote))
    finally:
        (folder / "late.csv").unlink()
        (tmp_path / "moved.csv").rename(folder / "single-2.csv")
    assert (
        (rr.added, rr.removed, rr.unchanged, rr.failed)
        == (rl.added, rl.removed, rl.unchanged, rl.failed)
        == (1, 1, 32, 1)
    )  # part-03: new mtime, same contents (hashed on the client)
    _assert_same_file(local, remote)


def test_relative_sources_are_the_clients_whatever_the_workers_folder(cluster, library, tmp_path, monkeypatch):
    import shutil

    folder, _ = library
    (tmp_path / "rel").mkdir()
    for name in ("part-00.obj", "part-01.obj", "single-0.csv", "broken.csv"):
        shutil.copy(folder / name, tmp_path / "rel" / name)
    monkeypatch.chdir(tmp_path)  # the workers stay in the folder they started in
    assert cluster.client.run(os.getcwd).popitem()[1] != str(tmp_path)
    rl = build_index(["rel"], "local.h5", jobs=1)
    calls = []
    rr = cluster.build_index(["rel"], "remote.h5", progress=lambda done, total: calls.append((done, total)))
    assert (rr.added, rr.failed, rr.curves) == (rl.added, rl.failed, rl.curves) == (3, 1, 41)
    assert calls[0] == (0, 4) and calls[-1] == (4, 4) and [d for d, _ in calls] == sorted(d for d, _ in calls)
    assert rr.failures == rl.failures == [("rel/broken.csv", "rel/broken.csv: line 3: not a number: 'oops'")]
    _assert_same_file(tmp_path / "local.h5", tmp_path / "remote.h5")
    with open_index("remote.h5") as idx:
        assert idx.ids(0, 1) == ["rel/part-00.obj#0"]


def test_cli_build_on_the_scheduler_names_a_bad_file_and_exits_3(client, library, tmp_path):
    folder, _ = library
    index = tmp_path / "i.h5"
    code, out, err = run("index", "build", folder, "--index", index, "--scheduler", client.scheduler.address)
    assert code == 3 and out == ""
    assert f"Error: {folder / 'broken.csv'}: line 3: not a number: 'oops'" in err
    assert f"indexed into {index}: 33 added, 0 updated, 0 removed, 0 unchanged, 1 failed files; 603 curves" in err
    assert "Traceback" not in err
    # the same from $NFDMATCH_SCHEDULER; nothing changed, nothing computed
    code, out, err = run(
        "index",
        "build",
        folder,
        "--index",
        index,
        "--format",
        "json",
        env={"NFDMATCH_SCHEDULER": client.scheduler.address},
    )
    assert code == 3 and '"unchanged": 33' in out and '"failed": 1' in out


def _kill_on_first_file():
    """Run on every worker: its first file kills the worker process (as a crash or an OOM
    kill would). The nanny starts a fresh process, without this trap."""
    import os as _os

    from nfdmatch.index import pool

    def die(*args, **kwargs):
        _os._exit(17)

    pool._compute_batch = die


def test_a_worker_that_dies_mid_task_is_replaced_and_its_task_rerun(client, cluster, library, tmp_path):
    folder, _ = library
    local, remote = tmp_path / "local.h5", tmp_path / "remote.h5"
    build_index([str(folder)], str(local), jobs=1)
    before = set(cluster.client.scheduler_info()["workers"])
    client.run(_kill_on_first_file)
    report = cluster.build_index([str(folder)], str(remote))
    assert (report.added, report.failed, report.curves) == (33, 1, 603)
    _assert_same_file(local, remote)
    client.wait_for_workers(2, timeout=60)
    assert not before & set(client.scheduler_info()["workers"])  # both workers died and were replaced


def _same_rows(a, b):
    """The same rows in the same order; distances (a numerical optimum, refined from a
    start that depends on which rows share a batch) to 1e-12, as pruned vs exhaustive."""
    assert len(a) == len(b)
    for ra, rb in zip(a, b):
        assert [r.replace(distance=0.0, shift=0.0) for r in ra] == [r.replace(distance=0.0, shift=0.0) for r in rb]
        assert np.allclose([r.distance for r in ra], [r.distance for r in rb], rtol=1e-12, atol=1e-12)
        assert np.allclose([r.shift for r in ra], [r.shift for r in rb], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(
    "options",
    [
        dict(k=5),
        dict(k=12, mirror=True),
        dict(k=None, max_distance=0.2),
        dict(k=3, direction="strict", method="paper"),
    ],
)
def test_a_cluster_query_equals_a_local_query_row_for_row(cluster, library, tmp_path_factory, options):
    from nfdmatch.search import cells

    folder, queries = library
    index = tmp_path_factory.getbasetemp() / "query-index.h5"
    if not index.exists():
        old = cells.ROWS_PER_CELL
        cells.ROWS_PER_CELL = 16
        try:
            build_index([str(folder)], str(index), jobs=1)
        finally:
            cells.ROWS_PER_CELL = old
    with open_index(index) as idx:
        assert idx.search_table().n_cells >= 20
        local, local_stats = search_index(idx, queries, **options)
        exhaustive, _ = search_index(idx, queries, prune=False, **options)
        # small windows: the first round's seeds are not yet the answer, the ranges must find it
        for parts, window in ((None, None), (2, None), (2, 1), (3, 40), (7, 100)):
            calls = []
            remote, stats = cluster.search_index(
                idx,
                queries,
                parts=parts,
                window=window,
                progress=lambda done, total: calls.append((done, total)),
                **options,
            )
            assert calls[0][0] == 0 and calls[-1][0] == calls[-1][1] >= len(queries)
            _same_rows(remote, local)
            assert stats.queries == len(queries) and stats.rows == 603 and stats.cell_count == local_stats.cell_count
            assert 0 < stats.exact <= len(queries) * 603
        remote, stats = cluster.search_index(str(index), queries, prune=False, parts=4, **options)
        _same_rows(remote, exhaustive)
        assert stats.exact == len(queries) * 603 and not stats.pruned
    assert any(len(r) > 1 for r in local)


def _kernels_run_on_threads():
    from nfdmatch.matching.kernels import current

    return current().threads


def test_a_worker_with_two_threads_answers_on_kernels_that_release_the_gil(library, tmp_path):
    """A worker running two tasks at once runs them on kernels that release the GIL (those
    compiled ahead of time); the answer is still the local one, row for row."""
    from distributed import Client, LocalCluster

    folder, queries = library
    index = tmp_path / "i.h5"
    build_index([str(folder)], str(index), jobs=1)
    with open_index(index) as idx:
        local, _ = search_index(idx, queries, k=5)
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=True, dashboard_address=":0", silence_logs=50) as lc,
        Client(lc, set_as_default=False) as c,
        connect(c) as cluster,
    ):
        assert cluster.threads == 2
        remote, _ = cluster.search_index(str(index), queries, k=5)
        _same_rows(remote, local)
        assert all(c.run(_kernels_run_on_threads).values())
        remote, _ = cluster.search_index(str(index), queries, k=5, parts=2)
        _same_rows(remote, local)


def test_cli_query_on_the_scheduler_prints_what_a_local_query_prints(client, library, tmp_path):
    folder, queries = library
    index = tmp_path / "i.h5"
    build_index([str(folder)], str(index), jobs=1)
    qfile = tmp_path / "queries.obj"
    write_curves(str(qfile), queries)
    args = ("query", qfile, "--index", index, "--top", "4", "--format", "csv", "--details")
    code, local, err = run(*args)
    assert code == 0 and err == ""
    code, remote, err = run(*args, "--scheduler", client.scheduler.address, "--stats")
    assert code == 0 and remote == local and len(local.splitlines()) == 1 + 4 * len(queries)
    assert f"{len(queries)} queries x 603 rows" in err and "Traceback" not in err
    code, remote, err = run(*args, "--exhaustive", env={"NFDMATCH_SCHEDULER": client.scheduler.address})
    assert code == 0 and remote == local
    code, remote, err = run(*args, "--ranges", "3", "--scheduler", client.scheduler.address)
    assert code == 0 and _csv_rows(remote) == _csv_rows(local)
    code, out, err = run(*args, "--ranges", "3")
    assert code == 2 and out == "" and "--ranges needs --scheduler" in err


def _csv_rows(text):
    """CSV rows with distances rounded to 1e-12 (the search's numerical optimum)."""
    import csv
    import io

    return [
        {k: (f"{float(v):.12f}" if k in ("distance", "shift") else v) for k, v in r.items()}
        for r in csv.DictReader(io.StringIO(text))
    ]


def _other_version():
    import nfdmatch._version

    nfdmatch._version.__version__ = "0.0.1-other"


def _own_version():
    import importlib

    import nfdmatch._version

    importlib.reload(nfdmatch._version)


def test_workers_with_another_nfdmatch_version_are_refused_at_connect(client, library, tmp_path):
    client.run(_other_version, workers=[sorted(client.scheduler_info()["workers"])[0]])
    try:
        with pytest.raises(ClusterError, match=r"must run nfdmatch 0\.1\.0 .*runs nfdmatch 0\.0\.1-other"):
            connect(client)
        code, out, err = run(
            "index", "build", library[0], "--index", tmp_path / "i.h5", "--scheduler", client.scheduler.address
        )
        assert code == 2 and out == "" and "Error: the workers must run nfdmatch" in err
        assert "Traceback" not in err and not (tmp_path / "i.h5").exists()
    finally:
        client.run(_own_version)
    with connect(client) as c:
        assert len(c.workers) == 2


def _unused_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_unreachable_scheduler_is_an_error_after_the_timeout_not_a_hang(library, tmp_path):
    address = f"tcp://127.0.0.1:{_unused_port()}"
    code, out, err = run(
        "index", "build", library[0], "--index", tmp_path / "i.h5", "--scheduler", address, "--scheduler-timeout", "1"
    )
    assert code == 2 and out == ""
    assert err.startswith(f"Error: cannot reach the Dask scheduler at {address} within 1 s")
    assert "Traceback" not in err and not (tmp_path / "i.h5").exists()
    qfile = tmp_path / "q.csv"
    write_curves(str(qfile), library[1][0])
    build_index([str(library[0])], str(tmp_path / "i.h5"), jobs=1)
    code, out, err = run(
        "query",
        qfile,
        "--index",
        tmp_path / "i.h5",
        env={"NFDMATCH_SCHEDULER": address, "NFDMATCH_SCHEDULER_TIMEOUT": "0.5"},
    )
    assert code == 2 and out == "" and "cannot reach the Dask scheduler" in err and "within 0.5 s" in err
    code, out, err = run(
        "query", qfile, "--index", tmp_path / "i.h5", "--scheduler", address, "--scheduler-timeout", "0"
    )
    assert code == 2 and "--scheduler-timeout" in err


def test_a_malformed_scheduler_address_is_one_line_and_no_traceback_at_exit(library, tmp_path):
    # Dask's Client fails in its constructor without closing itself (an address without a
    # port; a peer that answers garbage): its __del__ at interpreter exit then timed out on
    # a stopped event loop and printed "Exception ignored in: Client.__del__" and a traceback
    import subprocess

    index = tmp_path / "i.h5"
    build_index([str(library[0] / "single-0.csv"), str(library[0] / "single-1.csv")], str(index), jobs=1)
    started = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "nfdmatch", "pairs", "--index", str(index), "--max-distance", "0.1"]
        + ["--scheduler", "no-port-here", "--scheduler-timeout", "1"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.startswith("Error: cannot reach the Dask scheduler at no-port-here (")
    assert "within" not in proc.stderr  # it failed at once, not after the timeout
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert time.monotonic() - started < 20  # not the 2 x timeout of a close on a dead loop
    with pytest.raises(ClusterError, match="cannot reach the Dask scheduler at no-port-here"):
        connect("no-port-here", 1)
    from distributed import Client

    assert not [c for c in list(Client._instances) if c.status not in ("closed", "running")]


def test_bad_local_cluster_size_is_an_error(tmp_path, library):
    code, out, err = run("index", "build", library[0], "--index", tmp_path / "i.h5", "--scheduler", "local:zero")
    assert code == 2 and "local:N needs a number of workers N >= 1" in err and "Traceback" not in err


def test_without_dask_the_scheduler_option_says_what_to_install(library, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    code, out, err = run("index", "build", library[0], "--index", tmp_path / "i.h5", "--scheduler", "local:2")
    assert code == 2 and out == ""
    assert (
        "Error: --scheduler needs dask and distributed, which are not installed: "
        "pip install 'nfdmatch[distributed]'" in err
    )
    # without --scheduler, nothing changes
    code, out, err = run("index", "build", library[0], "--index", tmp_path / "i.h5", "--jobs", "1")
    assert code == 3


def test_a_ranged_query_finishes_when_every_worker_it_was_pinned_to_is_gone(client, library, tmp_path_factory):
    """Range tasks are pinned to a worker. When every worker leaves at once (an
    out-of-memory kill of all of them), Dask keeps tasks pinned to the old addresses
    "unrunnable" even after new workers join; the query re-submits them unpinned instead
    of waiting forever."""
    import threading

    folder, queries = library
    index = tmp_path_factory.getbasetemp() / "pinned-index.h5"
    if not index.exists():
        build_index([str(folder)], str(index), jobs=1)
    # by distance only: no first round, the range tasks are submitted (pinned) at once
    options = dict(k=None, max_distance=0.2)
    with open_index(index) as idx:
        local, _ = search_index(idx, queries, **options)
    cluster_object = client.cluster
    with connect(client) as c:
        old = list(c.workers)
        client.retire_workers(old)
        cluster_object.scale(0)
        deadline = time.monotonic() + 30
        while client.scheduler_info(n_workers=-1)["workers"] and time.monotonic() < deadline:
            time.sleep(0.1)
        got = {}

        def run():
            try:
                got["result"] = c.search_index(str(index), queries, parts=2, **options)
            except Exception as exc:  # reported below
                got["error"] = exc

        searching = threading.Thread(target=run, daemon=True)
        searching.start()
        time.sleep(1.0)  # the tasks are queued, pinned to workers that no longer exist
        cluster_object.scale(2)
        client.wait_for_workers(2, timeout=60)
        searching.join(timeout=90)
        assert not searching.is_alive(), "the query still waits for tasks pinned to workers that left"
        assert "error" not in got, got.get("error")
        remote, _ = got["result"]
        _same_rows(remote, local)


def _quiet_settings():
    import dask

    return [dask.config.get(key) for key in ("distributed.admin.tick.interval", "distributed.worker.profile.enabled")]


def test_a_cluster_started_here_wakes_its_processes_less_often():
    """``local:N`` shares this machine's cores with the work: its workers run with the slower
    tick and no profiler (an idle 2-worker cluster slowed a local build by 16% with Dask's
    defaults, 10% with these); this process's own settings are left as they were."""
    import dask

    before = dask.config.get("distributed.admin.tick.interval")
    with connect("local:1", timeout=60) as cluster:
        assert list(cluster.client.run(_quiet_settings).values()) == [["1s", False]]
    assert dask.config.get("distributed.admin.tick.interval") == before
