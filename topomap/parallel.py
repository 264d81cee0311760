"""One executor interface for the build's parallel stages: in-process, a local process pool, or Dask.

``build.py`` hands an :class:`Executor` pure functions (module-level, arguments and results plain
data: numpy arrays, dataclasses, no open files) and gets the results back **in submission order**,
so a map is the same at any worker count:

* :class:`InlineExecutor` — runs each call at once in this process (``workers=1``);
* :class:`ProcessExecutor` — a local pool of worker processes (``--workers N``);
* :class:`DaskExecutor` — the tasks of a ``dask.distributed`` cluster: a ``LocalCluster`` started
  here (``--dask local``) or an existing scheduler (``--scheduler tcp://HOST:8786``), e.g. one that
  dask-jobqueue or dask-kubernetes started. Workers need topomap installed and must read the
  images at the same paths as this process (a shared file system). Optional extra ``cluster``.

Each worker runs OpenCV single-threaded: the parallelism is across frames, and N processes each
running N OpenCV threads on N cores only add contention.

:func:`make_executor` turns the CLI's options into one of these; close it (or use ``with``).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import pickle
import tempfile
import threading
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from topomap.errors import ClusterError, ConfigError

__all__ = ["Executor", "InlineExecutor", "ProcessExecutor", "DaskExecutor", "make_executor", "available_cores",
           "shared_value", "worker_local"]

log = logging.getLogger(__name__)

#: Seconds to wait for a Dask scheduler to answer before giving up with a one-line error.
CONNECT_TIMEOUT_S = 10.0


class _Future(Protocol):
    def result(self) -> Any: ...


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells, else ``os.cpu_count``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def _init_worker() -> None:
    """Worker process set-up: OpenCV single-threaded (see the module docstring)."""
    import cv2

    cv2.setNumThreads(1)


@dataclass(frozen=True)
class _Spooled:
    """A shared value written once to a local file, which each worker process reads once (:func:`shared_value`)."""

    token: str
    path: str


#: This process's copy of the last spooled value it read: ``(token, value)``.
_SPOOLED: list[tuple[str, Any]] = []
_SPOOLED_LOCK = threading.Lock()
_LOCAL = threading.local()


def shared_value(shared: tuple) -> Any:
    """The value behind a reference from :meth:`Executor.shared`, in a task: read at most once per
    worker process (later tasks get the same object back; treat it as read-only)."""
    _token, ref = shared
    if not isinstance(ref, _Spooled):
        return ref  # in-process, or a Dask future the worker has already replaced by its value
    with _SPOOLED_LOCK:
        if not _SPOOLED or _SPOOLED[0][0] != ref.token:
            _SPOOLED.clear()  # only the latest shared value: an earlier stage's is not read again
            with open(ref.path, "rb") as f:
                _SPOOLED.append((ref.token, pickle.load(f)))
        return _SPOOLED[0][1]


def worker_local(shared: tuple, key: str, make: Callable[[Any], Any]) -> Any:
    """``make(shared_value(shared))``, made once per worker thread and shared value and kept for the
    later tasks of that thread (the last one per ``key``): e.g. a localizer over a shared map."""
    token = shared[0]
    memo = getattr(_LOCAL, "memo", None)
    if memo is None:
        memo = _LOCAL.memo = {}
    if key not in memo or memo[key][0] != token:
        memo.pop(key, None)  # the previous value goes before the next is made
        memo[key] = (token, make(shared_value(shared)))
    return memo[key][1]


class Executor:
    """Runs pure functions, possibly elsewhere. ``workers``: how many calls run at once;
    ``remote``: the workers may not share this process's file system view (Dask)."""

    workers: int = 1
    kind: str = "inline"
    remote: bool = False

    def submit(self, fn: Callable, *args) -> _Future:
        raise NotImplementedError

    def map(self, fn: Callable, items: Iterable, *, window: int | None = None) -> Iterator:
        """``fn(item)`` for every item, yielded in the items' order. Items are consumed lazily and at
        most ``window`` calls (default ``4 * workers``) are in flight: memory stays bounded however
        long the iterable is."""
        window = max(1, window or 4 * self.workers)
        pending: deque[_Future] = deque()
        for item in items:
            pending.append(self.submit(fn, item))
            if len(pending) >= window:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()

    @contextmanager
    def shared(self, value: Any) -> Iterator[tuple]:
        """``value`` for the workers of the tasks submitted inside the ``with``, sent once per worker
        instead of in every task: yields a small reference (a plain tuple) to put in the tasks'
        arguments, which a task turns back into the value with :func:`shared_value`. Here (workers
        in this process) the reference holds the value itself."""
        yield (uuid.uuid4().hex, value)

    def close(self) -> None:
        pass

    def describe(self) -> str:
        return f"{self.kind}, {self.workers} worker{'s' if self.workers != 1 else ''}"

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Done:
    """An already computed result (or the error computing it raised, re-raised by ``result``)."""

    __slots__ = ("_value", "_error")

    def __init__(self, fn: Callable, args: tuple):
        self._value = self._error = None
        try:
            self._value = fn(*args)
        except BaseException as e:  # re-raised where the result is asked for, as a pool would
            self._error = e

    def result(self) -> Any:
        if self._error is not None:
            raise self._error
        return self._value


class InlineExecutor(Executor):
    """Everything in this process, one call at a time (``workers=1``)."""

    def submit(self, fn: Callable, *args) -> _Future:
        return _Done(fn, args)

    def map(self, fn: Callable, items: Iterable, *, window: int | None = None) -> Iterator:
        for item in items:  # no look-ahead: nothing would run meanwhile
            yield fn(item)


class ProcessExecutor(Executor):
    """A pool of ``workers`` local processes (``concurrent.futures``), started at once from a fork
    server that imports topomap once (about a second, once per process; later pools start in
    milliseconds), else (Windows) spawned. Never forked from this process:
    numpy and OpenCV run native threads from import on, and OpenCV's thread pool does not survive a
    fork (a forked worker that called OpenCV after the parent had used it waited forever)."""

    kind = "processes"

    def __init__(self, workers: int):
        if workers < 1:
            raise ConfigError(f"--workers must be at least 1, got {workers}")
        self.workers = int(workers)
        methods = mp.get_all_start_methods()
        if "forkserver" in methods:
            ctx = mp.get_context("forkserver")
            ctx.set_forkserver_preload(["topomap.build"])
        else:
            ctx = mp.get_context("spawn")
        self.start_method = ctx.get_start_method()
        self._pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_init_worker)
        self._pool.submit(_init_worker).result()  # start-up costs land here, not in the first task

    def submit(self, fn: Callable, *args) -> _Future:
        return self._pool.submit(fn, *args)

    @contextmanager
    def shared(self, value: Any) -> Iterator[tuple]:
        """See :meth:`Executor.shared`: the value is pickled once, streamed to a private temporary
        file (deleted when the ``with`` ends; never part of a map) that each worker reads once."""
        with tempfile.TemporaryDirectory(prefix="topomap-shared-") as tmp:
            path = Path(tmp) / "value.pickle"
            with open(path, "wb") as f:  # streamed: no second copy of the value in this process
                pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
            token = uuid.uuid4().hex
            yield (token, _Spooled(token, str(path)))

    def worker_pids(self) -> list[int]:
        """Process ids of the live workers (for memory accounting: they are not this process's children)."""
        return sorted(p.pid for p in (self._pool._processes or {}).values() if p.pid is not None)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor(Executor):
    """The workers of a ``dask.distributed`` cluster. ``address``: a running scheduler
    (``tcp://HOST:8786``); ``None`` starts a ``LocalCluster`` of ``workers`` single-threaded worker
    processes on this machine (``processes=False``: threads of this process, for tests)."""

    kind = "dask"

    def __init__(self, address: str | None = None, workers: int | None = None, *, processes: bool = True):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise ConfigError("Dask is not installed; install it with: pip install 'appearance-topomap[cluster]'") from None
        self._cluster = None
        self.remote = address is not None
        try:
            if address is None:
                n = int(workers or available_cores())
                if n < 1:
                    raise ConfigError(f"--workers must be at least 1, got {n}")
                where = {"host": "127.0.0.1"} if processes else {}  # this machine only; threads talk in-process
                self._cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=processes, dashboard_address=":0",
                                             silence_logs=logging.ERROR, **where)
                self._client = Client(self._cluster, set_as_default=False)
            else:
                _probe(address)
                self._client = Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
        except ConfigError:
            raise
        except Exception as e:  # a foreign service answering the port fails in many ways; none is a bug here
            self.close()
            where = f"the Dask scheduler at {address}" if address else "a local Dask cluster"
            detail = " ".join(str(e).split()) or type(e).__name__
            raise ClusterError(f"cannot reach {where} ({detail[:160]}); start one with `dask scheduler` "
                               "and `dask worker`, check the address, or use --dask local") from None
        nthreads = self._client.nthreads()
        self.workers = max(1, sum(nthreads.values()))
        if not nthreads:
            self.close()
            raise ClusterError(f"the Dask scheduler at {address} has no workers; start some with `dask worker {address}`")
        if processes or self._cluster is None:  # worker processes (threads would share this one's OpenCV)
            self._client.run(_init_worker)
        self.address = address or self._cluster.scheduler_address

    def submit(self, fn: Callable, *args) -> _Future:
        return self._client.submit(fn, *args, pure=False)

    @contextmanager
    def shared(self, value: Any) -> Iterator[tuple]:
        """See :meth:`Executor.shared`: scattered to every worker once (they may not share a file
        system with this process); Dask hands each task its worker's copy in place of the future."""
        future = self._client.scatter(value, broadcast=True, hash=False)
        try:
            yield (uuid.uuid4().hex, future)
        finally:
            future.release()

    def describe(self) -> str:
        return f"dask at {self.address}, {self.workers} worker thread{'s' if self.workers != 1 else ''}"

    def close(self) -> None:
        client, cluster = getattr(self, "_client", None), self._cluster
        self._client = self._cluster = None
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def _probe(address: str) -> None:
    """Fail fast (``OSError``) when nothing listens at a ``tcp://HOST:PORT`` address: Dask's own
    client retries until its timeout and leaves a closing client behind that blocks the exit."""
    import socket
    from urllib.parse import urlsplit

    parts = urlsplit(address)
    if parts.scheme not in ("tcp", "tls") or not parts.hostname or parts.port is None:
        raise ValueError(f"{address} is not a tcp://HOST:PORT address")
    with socket.create_connection((parts.hostname, parts.port), timeout=CONNECT_TIMEOUT_S):
        pass


def make_executor(workers: int | None = None, *, dask: str | None = None, scheduler: str | None = None) -> Executor:
    """The executor for the CLI's options: ``workers`` (``None``: every core; 1: in-process),
    ``dask="local"`` (a LocalCluster of ``workers`` processes) or ``scheduler`` (an address)."""
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {workers}")
    if dask is not None and scheduler is not None:
        raise ConfigError("--dask and --scheduler exclude each other: --dask local starts a cluster, --scheduler joins one")
    if dask is not None:
        if dask != "local":
            raise ConfigError(f"--dask takes 'local' (a cluster on this machine), got {dask!r}; for a running cluster use --scheduler tcp://HOST:8786")
        return DaskExecutor(None, workers)
    if scheduler is not None:
        if workers is not None:
            raise ConfigError("--workers does not apply to --scheduler: the cluster's workers decide")
        if "://" not in scheduler:
            scheduler = f"tcp://{scheduler}"
        return DaskExecutor(scheduler)
    n = available_cores() if workers is None else int(workers)
    return InlineExecutor() if n == 1 else ProcessExecutor(n)
