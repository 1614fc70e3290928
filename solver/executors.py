"""One way to run a plain function over many items: in this process, in local worker
processes, or on a Dask cluster — with the same numbers from each.

``executor.map(fn, shared, items)`` returns ``[fn(shared, item) for item in items]`` in item
order; ``executor.map_async`` starts the same work and returns at once (:class:`Pending`),
so the caller can do its own work meanwhile. ``fn`` must be a module-level function and
``shared``/``items`` picklable for the process and Dask backends; ``shared`` (e.g. the
kinematic chain and the current parameters of a Gauss–Newton pass) travels once per worker
and call, each item once. The caller combines the results in item order, so the backends
differ only in where the work runs, never in the arithmetic (results are bit-identical when
the workers run the same numpy/BLAS).

Items are split into contiguous blocks, block w always to worker w, so a process that read and
prepared chunk i in one pass sees chunk i again in the next (per-process caches keep hitting).

The maths never imports Dask: it is imported only when a :class:`DaskExecutor` is made.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Generic, Literal, Protocol, TypeVar

from solver.errors import KincalError

S = TypeVar("S")
T = TypeVar("T")
R = TypeVar("R")

ExecutorKind = Literal["inprocess", "processes", "dask"]
EXECUTOR_KINDS: tuple[ExecutorKind, ...] = ("inprocess", "processes", "dask")


class Pending(Generic[R]):
    """Work started by :meth:`Executor.map_async`; :meth:`result` waits for its results."""

    def __init__(self, collect: Callable[[], list[R]]) -> None:
        self._collect = collect

    def result(self) -> list[R]:
        return self._collect()


class Executor(Protocol):
    """Where map-reduce work runs (see the module docstring)."""

    name: str

    @property
    def n_workers(self) -> int: ...

    def map(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> list[R]: ...

    def map_async(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> Pending[R]:
        """:meth:`map` started in the workers; the in-process executor does it at once."""
        ...

    def run_on_workers(self, fn: Callable[[], R]) -> list[R]:
        """``fn()`` once in every worker process (e.g. to read its peak memory)."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> Executor: ...

    def __exit__(self, *exc: object) -> None: ...


WORKER_MODULES: list[str] = ["solver.stream.fit", "solver.stream.covariance"]
"""Modules each local worker process has imported before its first task (imported once, in
the fork server): the solver's, and those a layer above adds with :func:`preload_in_workers`
— e.g. the module of its chunk loaders, which unpickling a pass's arguments would otherwise
import again in every worker."""


def preload_in_workers(module: str) -> None:
    """Have local worker processes started from now on import ``module`` up front."""
    if module not in WORKER_MODULES:
        WORKER_MODULES.append(module)


def blocks(n_items: int, n_workers: int) -> list[range]:
    """Contiguous, near-equal item ranges, one per worker (some empty if items are few)."""
    bounds = [round(w * n_items / n_workers) for w in range(n_workers + 1)]
    return [range(bounds[w], bounds[w + 1]) for w in range(n_workers)]


def _run_block(fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> list[R]:
    return [fn(shared, item) for item in items]


def _call(fn: Callable[[], R]) -> R:
    return fn()


def peak_rss_bytes() -> int:
    """Peak resident memory of this process (Linux VmHWM; else ``ru_maxrss``), in bytes; run
    it on the workers with :meth:`Executor.run_on_workers`."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


class InProcessExecutor:
    """Everything in the calling process, one item after the other (the default)."""

    name = "inprocess"

    @property
    def n_workers(self) -> int:
        return 1

    def map(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> list[R]:
        return _run_block(fn, shared, items)

    def map_async(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> Pending[R]:
        results = self.map(fn, shared, items)
        return Pending(lambda: results)

    def run_on_workers(self, fn: Callable[[], R]) -> list[R]:
        return [fn()]

    def close(self) -> None:
        return None

    def __enter__(self) -> InProcessExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ProcessExecutor:
    """``n_workers`` local worker processes (default: every core), started once and reused.

    One single-process pool per worker, so block w of every call lands on the same process.
    Workers start with ``forkserver`` (clean interpreter, no inherited threads) from a server
    that imported :data:`WORKER_MODULES` once; they are started at construction, in the
    background, so their start overlaps the caller's own preparations. BLAS runs one thread
    per worker (see :mod:`solver`).
    """

    name = "processes"

    def __init__(self, n_workers: int | None = None) -> None:
        count = n_workers or os.cpu_count() or 1
        if count < 1:
            raise KincalError(f"processes executor needs at least 1 worker, got {count}")
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(list(WORKER_MODULES))
        self._pools = [ProcessPoolExecutor(1, mp_context=context) for _ in range(count)]
        # Starting the fork server (and its imports) blocks for a second: do it beside the
        # caller, which meanwhile plans its work; a first task simply waits for its worker.
        self._starting = threading.Thread(target=self._start, daemon=True)
        self._starting.start()

    def _start(self) -> None:
        for pool in self._pools:
            pool.submit(int)

    @property
    def n_workers(self) -> int:
        return len(self._pools)

    def map(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> list[R]:
        return self.map_async(fn, shared, items).result()

    def map_async(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> Pending[R]:
        if not self._starting.is_alive():
            futures = self._submit(fn, shared, items)
            return Pending(lambda: [result for future in futures for result in future.result()])
        # While the workers start, submitting blocks until the fork server has imported its
        # modules (a second or more): submit beside the caller, who gets on with its own work.
        submitted: list[list[Future[list[R]]]] = []
        submitting = threading.Thread(
            target=lambda: submitted.append(self._submit(fn, shared, items)), daemon=True
        )
        submitting.start()

        def collect() -> list[R]:
            submitting.join()
            if not submitted:
                raise KincalError("the worker processes could not be started")
            return [result for future in submitted[0] for result in future.result()]

        return Pending(collect)

    def _submit(
        self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]
    ) -> list[Future[list[R]]]:
        return [
            pool.submit(_run_block, fn, shared, [items[i] for i in block])
            for pool, block in zip(self._pools, blocks(len(items), self.n_workers), strict=True)
            if len(block)
        ]

    def run_on_workers(self, fn: Callable[[], R]) -> list[R]:
        return [pool.submit(_call, fn).result() for pool in self._pools]

    def close(self) -> None:
        self._starting.join()
        for pool in self._pools:
            pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ProcessExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_WORKER_ENVIRON = {
    f"distributed.nanny.pre-spawn-environ.{name}": value
    for name, value in {
        "MALLOC_MMAP_THRESHOLD_": 256 * 1024 * 1024,
        "MALLOC_TRIM_THRESHOLD_": 256 * 1024 * 1024,
        "MALLOC_ARENA_MAX": 1,
    }.items()
}
"""glibc settings for the worker processes of a LocalCluster. Tasks run in a worker thread,
whose allocator otherwise maps and unmaps every large temporary (several MB per block): ~20x
the page faults and as much system as user time. Workers of an external cluster should be
started with the same environment variables."""


class DaskExecutor:
    """Items as tasks on a Dask distributed cluster.

    ``address``: a running scheduler (``tcp://host:8786``); its workers need kincal installed
    and, for files, the same paths. None starts a LocalCluster of ``n_workers`` single-threaded
    worker processes (``processes=False``: threads in this process, for tests) that is shut down
    on :meth:`close`. ``shared`` is scattered to every worker once per call; each worker gets
    one task per call with its block of items (preferring, not requiring, that worker: a lost
    worker's block runs elsewhere), so work stealing cannot scatter a worker's cached chunks.
    """

    name = "dask"

    def __init__(
        self, address: str | None = None, *, n_workers: int | None = None, processes: bool = True
    ) -> None:
        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:  # pragma: no cover - pinned in requirements.lock
            raise KincalError("the dask executor needs dask[distributed] installed") from exc
        self._cluster: Any = None
        if address is None:
            import dask

            with dask.config.set(_WORKER_ENVIRON):
                self._cluster = LocalCluster(
                    n_workers=n_workers or os.cpu_count() or 1,
                    threads_per_worker=1,
                    processes=processes,
                    dashboard_address=None,
                )
            self._client: Any = Client(self._cluster)
        else:
            try:
                self._client = Client(address, timeout="20s")
            except OSError as exc:
                raise KincalError(f"cannot reach the Dask scheduler at {address}: {exc}") from exc

    def _workers(self) -> list[str]:
        return sorted(self._client.scheduler_info(n_workers=-1)["workers"])

    @property
    def n_workers(self) -> int:
        return len(self._workers())

    def map(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> list[R]:
        return self.map_async(fn, shared, items).result()

    def map_async(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T]) -> Pending[R]:
        if not items:
            return Pending(list)
        workers = self._workers()
        if not workers:
            raise KincalError("the Dask cluster has no workers")
        remote = self._client.scatter(shared, broadcast=True, hash=False)
        futures = [
            self._client.submit(
                _run_block,
                fn,
                remote,
                [items[i] for i in block],
                workers=[worker],
                allow_other_workers=True,
                pure=False,
            )
            for worker, block in zip(workers, blocks(len(items), len(workers)), strict=True)
            if len(block)
        ]
        client = self._client
        return Pending(lambda: [result for part in client.gather(futures) for result in part])

    def run_on_workers(self, fn: Callable[[], R]) -> list[R]:
        return list(self._client.run(fn).values())

    def close(self) -> None:
        self._client.close()
        if self._cluster is not None:
            self._cluster.close()

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_executor(
    kind: ExecutorKind = "inprocess",
    *,
    n_workers: int | None = None,
    dask_address: str | None = None,
    dask_processes: bool = True,
) -> Executor:
    """The executor named ``kind``; ``dask_address`` None starts a LocalCluster."""
    if kind == "inprocess":
        return InProcessExecutor()
    if kind == "processes":
        return ProcessExecutor(n_workers)
    if kind == "dask":
        return DaskExecutor(dask_address, n_workers=n_workers, processes=dask_processes)
    raise KincalError(f"unknown executor {kind!r}; choose one of {', '.join(EXECUTOR_KINDS)}")
