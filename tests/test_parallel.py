"""topomap.parallel: ordered maps on every executor, bounded look-ahead, errors carried back, bad
options; and the build's promise on top of it: the same map at any worker count and on Dask."""

from __future__ import annotations

import itertools
import json
import os
import pickle
import sqlite3

import numpy as np
import pytest
from conftest import castle_map_file, dataset
from map_synth import FAST, SHORT_WALK_PX, write_out_and_back

from topomap.build import build_map
from topomap.camera import load_camera
from topomap.errors import ClusterError, ConfigError, DatasetError
from topomap.parallel import (DaskExecutor, InlineExecutor, ProcessExecutor, available_cores, make_executor,
                              shared_value)
from topomap.store import save_map


def square(x: int) -> int:
    return x * x


def fail_on_three(x: int) -> int:
    if x == 3:
        raise DatasetError("three is unreadable")
    return x


def pid_of(_x: int) -> int:
    return os.getpid()


def read_shared(item) -> tuple[int, int, int, int]:
    shared, i = item
    value = shared_value(shared)
    return i, int(value.sum()), os.getpid(), id(value)


@pytest.fixture(scope="module")
def pool():
    with ProcessExecutor(2) as ex:
        yield ex


@pytest.fixture(scope="module")
def dask_threads():
    """A small Dask LocalCluster of two single-threaded workers in this process (quick to start)."""
    with DaskExecutor(None, 2, processes=False) as ex:
        yield ex


@pytest.mark.parametrize("which", ["inline", "pool", "dask"])
def test_map_keeps_the_order(which, request, pool, dask_threads):
    ex = {"inline": InlineExecutor(), "pool": pool, "dask": dask_threads}[which]
    assert list(ex.map(square, range(40), window=3)) == [i * i for i in range(40)]
    assert ex.submit(square, 7).result() == 49


@pytest.mark.parametrize("which", ["inline", "pool", "dask"])
def test_errors_come_back_with_their_type(which, pool, dask_threads):
    ex = {"inline": InlineExecutor(), "pool": pool, "dask": dask_threads}[which]
    out = ex.map(fail_on_three, range(6))
    assert [next(out) for _ in range(3)] == [0, 1, 2]
    with pytest.raises(DatasetError, match="three is unreadable"):
        next(out)


def test_map_consumes_lazily(pool):
    """At most ``window`` items are taken ahead of the consumer: an endless source works."""
    taken = []

    def source():
        for i in itertools.count():
            taken.append(i)
            yield i

    out = pool.map(square, source(), window=4)
    assert [next(out) for _ in range(5)] == [0, 1, 4, 9, 16]
    assert len(taken) <= 5 + 4


@pytest.mark.parametrize("which", ["inline", "pool", "dask"])
def test_a_shared_value_is_read_once_per_worker(which, pool, dask_threads):
    ex = {"inline": InlineExecutor(), "pool": pool, "dask": dask_threads}[which]
    value = np.arange(100_000)
    with ex.shared(value) as shared:
        if which == "pool":
            assert len(pickle.dumps(shared)) < 1000  # what a task carries: a reference, not the value
        out = list(ex.map(read_shared, ((shared, i) for i in range(12))))
    assert [(i, s) for i, s, _, _ in out] == [(i, int(value.sum())) for i in range(12)]
    copies = {(pid, ident) for _, _, pid, ident in out}
    assert len(copies) == len({pid for pid, _ in copies})  # one copy per worker process, whatever its tasks


def test_pool_runs_in_other_processes(pool):
    pids = set(pool.map(pid_of, range(16)))
    assert os.getpid() not in pids and 1 <= len(pids) <= 2


def test_make_executor_choices():
    assert isinstance(make_executor(1), InlineExecutor)
    with make_executor(2) as ex:
        assert isinstance(ex, ProcessExecutor) and ex.workers == 2
    with make_executor() as ex:
        assert ex.workers == available_cores()


@pytest.mark.parametrize("kwargs, fragment", [
    ({"workers": 0}, "--workers must be at least 1"),
    ({"workers": -2}, "--workers must be at least 1"),
    ({"dask": "remote"}, "--dask takes 'local'"),
    ({"dask": "local", "scheduler": "tcp://127.0.0.1:1"}, "exclude each other"),
    ({"workers": 2, "scheduler": "tcp://127.0.0.1:1"}, "--workers does not apply"),
])
def test_bad_options(kwargs, fragment):
    with pytest.raises(ConfigError, match=fragment):
        make_executor(**kwargs)


def test_unreachable_scheduler_is_one_clear_error():
    with pytest.raises(ClusterError, match=r"cannot reach the Dask scheduler at tcp://127.0.0.1:9 .*dask scheduler"):
        make_executor(scheduler="127.0.0.1:9")
    with pytest.raises(ClusterError, match="not a tcp://HOST:PORT address"):
        make_executor(scheduler="tcp://127.0.0.1")


# ----------------------------------------------------------------------------- the same map everywhere
def map_rows(path) -> dict:
    """Every row of a map file; of the header, all but what records when and how fast it was built."""
    con = sqlite3.connect(path)
    try:
        rows = {t: con.execute(f"SELECT * FROM {t} ORDER BY 1, 2").fetchall() for t in ("node", "feature", "edge", "frame", "array")}
        meta = dict(con.execute("SELECT key, value FROM meta").fetchall())
    finally:
        con.close()
    for k in ("created_utc", "modified_utc"):
        meta.pop(k)
    seqs = json.loads(meta.pop("sequences"))
    for s in seqs:
        s.pop("seconds")
    rows["meta"] = sorted(meta.items()) + [("sequences", seqs)]
    return rows


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """The short out-and-back walk (built three times, on three executors; loop closures included)."""
    folder = tmp_path_factory.mktemp("pwalk")
    write_out_and_back(folder, length_px=SHORT_WALK_PX)
    return folder


@pytest.fixture(scope="module")
def walk_inline(walk, tmp_path_factory):
    return map_rows(save_map(build_map(walk, FAST), tmp_path_factory.mktemp("p1") / "m.topomap"))


@pytest.mark.slow
def test_two_workers_build_the_same_map(walk, walk_inline, pool, tmp_path):
    m = build_map(walk, FAST, executor=pool)
    assert len(m.nodes) >= 3 and m.edges_by_kind()["loop"] >= 1
    assert map_rows(save_map(m, tmp_path / "m.topomap")) == walk_inline


@pytest.mark.slow
def test_dask_builds_the_same_map(walk, walk_inline, dask_threads, tmp_path):
    m = build_map(walk, FAST, executor=dask_threads)
    assert map_rows(save_map(m, tmp_path / "m.topomap")) == walk_inline


@pytest.mark.slow
def test_castle_identical_on_processes_and_a_dask_local_cluster(tmp_path, tmp_path_factory):
    """The real-image case, with worker *processes* for Dask too (what ``--dask local`` starts)."""
    root = dataset("castle-p30")
    cam = load_camera(root / "K.txt")
    rows = [map_rows(castle_map_file(tmp_path_factory))]  # the session's castle map, built in one process
    for i, ex in enumerate([ProcessExecutor(2), DaskExecutor(None, 2)], start=1):
        with ex:
            m = build_map(root / "images", None, cam, executor=ex)
        rows.append(map_rows(save_map(m, tmp_path / f"m{i}.topomap")))
    assert len(rows[0]["node"]) > 10 and any(r[2] == "loop" for r in rows[0]["edge"])
    assert rows[1] == rows[0] and rows[2] == rows[0]


def test_a_worker_that_cannot_read_the_images(walk, tmp_path, monkeypatch):
    """Workers of a remote cluster that do not see the files this machine lists: one clear error
    (not a map of skipped frames). Simulated by workers (threads here) whose reads find no file."""
    import topomap.build as build_mod

    def blind(task):
        if task.image is not None:  # decoded here (the first frame fixes the working size)
            return task.image, None, False
        return None, f"image {task.path} does not exist", True

    monkeypatch.setattr(build_mod, "_decode", blind)
    with DaskExecutor(None, 2, processes=False) as ex:
        ex.remote = True  # as for --scheduler: the workers' file system may differ
        with pytest.raises(ClusterError, match="a Dask worker cannot read .* same path"):
            build_map(walk, FAST, executor=ex)
    # the same failure with this machine's own workers means the files are unreadable here too:
    # skipped and counted, as ever (the first frame is read before any work is handed out)
    m = build_map(walk, FAST, executor=InlineExecutor())
    assert m.frames[0].status == "ok" and {f.status for f in m.frames[1:]} == {"unreadable"}
    assert m.sequences[-1]["frames_skipped"] == len(m.frames) - 1
