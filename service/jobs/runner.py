"""Background jobs: a registry of job kinds and a runner that executes them in worker processes.

Design
------
* **State lives in the database** (table ``jobs``): queued -> running -> succeeded / failed /
  cancelled, with stage, fraction and iteration for progress. Accepting a job is one INSERT, so
  accepted work survives kill -9 of the service.
* **CPU work never runs in the request loop.** Each of ``settings.workers`` slots owns one
  long-lived worker *process* (``forkserver`` context by default, ``spawn`` optional: no
  inherited threads or locks; the job code is imported once by the fork server, so starting
  or replacing a worker takes milliseconds; code in :mod:`service.jobs.worker`) and one thread in
  the service that feeds it jobs over a pipe and writes its progress to the database. Workers
  only read input files and write artifact files; they never open the database.
* **One runner per service.** Under ``kincal serve`` the :class:`JobRunner` lives in a process
  of its own beside the request processes (:mod:`service.jobs.supervisor`); they hold a
  :class:`RunnerHandle` (:class:`service.jobs.runner_link.RemoteRunner`) that wakes it and reads its
  status. An app built by ``create_app()`` alone (tests, the demo) runs its runner inside.
* **Claiming** is a conditional UPDATE (queued -> running, owner = ``settings.instance_name``),
  exclusive across threads, processes and service instances sharing a database.
* **Crash recovery.** At start-up, jobs this instance left running are re-queued; running jobs
  of any instance whose heartbeat is older than ``job_lease_s`` are re-queued too. A worker
  that dies mid-job (OOM killer, segfault) is replaced and the job re-queued; after
  ``job_max_attempts`` deaths the job fails instead of looping forever.
* **Cancellation**: a queued job is cancelled in the database; a running one has its worker
  killed (SIGKILL; artifacts are written atomically, so nothing half-written remains) and
  replaced.
* **Graceful shutdown**: running jobs get ``shutdown_grace_s`` to finish; the rest are handed
  back to the queue without counting an attempt.

Adding a kind of job: write ``def my_job(ctx: JobContext) -> None`` in an importable module
(it reads ``ctx.params``, reports ``ctx.progress(...)``, writes ``ctx.write_artifact(...)``,
raises :class:`~solver.errors.KincalError` for problems the user caused) and register it:
``registry.register("discovery", "service.app.job_functions:discovery_job", id_prefix="dis")``.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import multiprocessing.connection
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.context import ForkServerContext, SpawnContext
from multiprocessing.process import BaseProcess
from typing import Any, Protocol

from service.jobs import logs
from service.jobs.worker import JobContext, worker_main
from service.settings import Settings
from service.storage import repository
from service.storage.db import Database
from service.storage.files import FileStore
from service.storage.models import Job

__all__ = [
    "JobContext",
    "JobKind",
    "JobRegistry",
    "JobRunner",
    "RunnerHandle",
    "default_registry",
]

log = logging.getLogger("kincal.jobs")

PROGRESS_WRITE_INTERVAL_S = 0.25
SPAWN_GRACE_S = 30.0
"""A replaced worker process counts as healthy for this long while it starts."""


# --- registry ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class JobKind:
    """A kind of job: ``target`` is ``"package.module:function"``, imported in the worker."""

    name: str
    target: str
    id_prefix: str

    @property
    def module(self) -> str:
        return self.target.partition(":")[0]


class JobRegistry:
    """Job kinds by name. The runner only claims jobs whose kind is registered."""

    def __init__(self) -> None:
        self._kinds: dict[str, JobKind] = {}

    def register(self, name: str, target: str, *, id_prefix: str) -> JobKind:
        module, sep, function = target.partition(":")
        if not sep or not module or not function:
            raise ValueError(f"job target must look like 'package.module:function', got {target!r}")
        if name in self._kinds:
            raise ValueError(f"job kind {name!r} is already registered")
        kind = JobKind(name, target, id_prefix)
        self._kinds[name] = kind
        return kind

    def __getitem__(self, name: str) -> JobKind:
        return self._kinds[name]

    def __contains__(self, name: object) -> bool:
        return name in self._kinds

    def names(self) -> list[str]:
        return list(self._kinds)

    def modules(self) -> list[str]:
        return sorted({kind.module for kind in self._kinds.values()})


def default_registry() -> JobRegistry:
    """The job kinds the service ships with."""
    registry = JobRegistry()
    registry.register("calibration", "service.app.job_functions:calibration_job", id_prefix="cal")
    registry.register("discovery", "service.app.job_functions:discovery_job", id_prefix="dis")
    registry.register("design", "service.app.job_functions:design_job", id_prefix="des")
    return registry


# --- in the service ----------------------------------------------------------------------------


@dataclass
class _Slot:
    """One worker process and the job it is running."""

    index: int
    process: BaseProcess | None = None
    conn: multiprocessing.connection.Connection | None = None
    job_id: str | None = None
    kill_reason: str | None = None
    spawned_at: float = 0.0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def alive(self) -> bool:
        return self.process is not None and self.process.is_alive()

    def kill(self, reason: str, job_id: str | None = None) -> bool:
        """SIGKILL the worker (only if it still runs ``job_id``, when given)."""
        with self.lock:
            if job_id is not None and self.job_id != job_id:
                return False
            if self.process is not None and self.process.is_alive():
                self.kill_reason = reason
                self.process.kill()
                return True
            return False

    def assign(self, job_id: str | None) -> None:
        with self.lock:
            self.job_id = job_id


FinishedHook = Callable[[Job], None]


class RunnerHandle(Protocol):
    """What the request side needs of the job runner, whether it runs in the same process
    (:class:`JobRunner`) or in its own (:class:`service.jobs.runner_link.RemoteRunner`)."""

    def start(self) -> None: ...

    def stop(self, grace_s: float | None = None) -> None: ...

    def notify(self) -> None:
        """A job was queued: look for work now."""

    def cancel(self, job_id: str) -> bool:
        """Cancellation of ``job_id`` was recorded in the database: stop it if running here."""

    def healthy(self) -> bool: ...

    def workers_alive(self) -> int: ...


class JobRunner:
    """Runs queued jobs of registered kinds in ``settings.workers`` worker processes."""

    def __init__(
        self,
        settings: Settings,
        database: Database,
        files: FileStore,
        registry: JobRegistry,
        *,
        on_finished: FinishedHook | None = None,
    ) -> None:
        self.settings = settings
        self.database = database
        self.files = files
        self.registry = registry
        self.runner_id = settings.instance_name
        self._on_finished = on_finished
        self._context: ForkServerContext | SpawnContext
        if settings.worker_start_method == "forkserver":
            # The fork server imports the job code once; every worker (and every replacement
            # after a crash or cancel) then starts in milliseconds.
            self._context = multiprocessing.get_context("forkserver")
            self._context.set_forkserver_preload(["service.jobs.worker", *registry.modules()])
        else:
            self._context = multiprocessing.get_context("spawn")
        self._slots = [_Slot(i) for i in range(settings.workers)]
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._wakeup = threading.Condition()
        self._started = False

    # lifecycle

    def start(self) -> None:
        """Re-queue what a previous life left running; start the slot threads (each starts its
        worker process; readiness reports them once alive)."""
        with self.database.session() as session:
            orphans = repository.requeue_jobs_of_runner(session, self.runner_id)
        if orphans:
            log.warning(
                "re-queued %d job(s) left running by a previous run of this instance",
                len(orphans),
                extra={"jobs": orphans},
            )
        for slot in self._slots:  # each slot thread starts its worker (off the start-up path)
            thread = threading.Thread(
                target=self._slot_loop, args=(slot,), name=f"kincal-slot-{slot.index}", daemon=True
            )
            thread.start()
            self._threads.append(thread)
        maintenance = threading.Thread(
            target=self._maintenance_loop, name="kincal-job-leases", daemon=True
        )
        maintenance.start()
        self._threads.append(maintenance)
        self._started = True

    def stop(self, grace_s: float | None = None) -> None:
        """Stop claiming; let running jobs finish for ``grace_s``, re-queue the rest."""
        if not self._started:
            return
        grace = self.settings.shutdown_grace_s if grace_s is None else grace_s
        self._stopping.set()
        self.notify()
        deadline = time.monotonic() + grace
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        for slot in self._slots:
            if slot.job_id is not None:
                slot.kill("shutdown", slot.job_id)
        for thread in self._threads:
            thread.join(5.0)
        for slot in self._slots:
            self._retire(slot)
        self._started = False

    def notify(self) -> None:
        """Wake idle slots (a job was queued)."""
        with self._wakeup:
            self._wakeup.notify_all()

    def cancel(self, job_id: str) -> bool:
        """Kill the worker running ``job_id`` here, if any; the slot marks the job cancelled."""
        return any(slot.kill("cancel", job_id) for slot in self._slots)

    def check_cancellations(self) -> int:
        """Kill the workers of this runner's jobs whose cancellation another process recorded
        in the database; how many were running here."""
        with self.database.session() as session:
            job_ids = repository.cancel_requested_jobs(session, self.runner_id)
        return sum(self.cancel(job_id) for job_id in job_ids)

    def healthy(self) -> bool:
        """All slot threads running and every worker process alive (or being replaced)."""
        if self.settings.workers == 0:
            return True
        now = time.monotonic()
        return (
            self._started
            and all(t.is_alive() for t in self._threads)
            and all(s.alive() or now - s.spawned_at < SPAWN_GRACE_S for s in self._slots)
        )

    def workers_alive(self) -> int:
        return sum(slot.alive() for slot in self._slots)

    # worker processes

    def _spawn(self, slot: _Slot) -> None:
        parent_conn, child_conn = self._context.Pipe()
        process = self._context.Process(
            target=worker_main,
            args=(
                child_conn,
                os.getpid(),
                str(self.files.root),
                self.settings.log_level,
                self.settings.log_format,
                self.registry.modules(),
            ),
            name=f"kincal-worker-{slot.index}",
            daemon=True,
        )
        process.start()
        child_conn.close()  # so that the parent sees EOF when the child dies
        with slot.lock:
            slot.process, slot.conn, slot.kill_reason = process, parent_conn, None
            slot.spawned_at = time.monotonic()
        log.info("worker process started", extra={"pid": process.pid, "slot": slot.index})

    def _retire(self, slot: _Slot) -> None:
        if slot.conn is not None:
            with contextlib.suppress(OSError, ValueError):
                slot.conn.send(None)
        if slot.process is not None:
            slot.process.join(2.0)
            if slot.process.is_alive():
                slot.process.kill()
                slot.process.join(2.0)
        if slot.conn is not None:
            slot.conn.close()
        slot.process, slot.conn = None, None

    # the loop of one slot

    def _slot_loop(self, slot: _Slot) -> None:
        while not self._stopping.is_set():
            try:
                if not slot.alive():
                    self._retire(slot)
                    self._spawn(slot)
                job = self._claim()
                if job is None:
                    with self._wakeup:
                        self._wakeup.wait(self.settings.job_poll_s)
                    continue
                self._run(slot, job)
            except Exception:  # keep the slot alive whatever happens (e.g. database restart)
                log.exception("job slot %d: unexpected error; retrying", slot.index)
                self._stopping.wait(1.0)

    def _claim(self) -> Job | None:
        with self.database.session() as session:
            job = repository.claim_next_job(session, self.runner_id, self.registry.names())
            if job is None:
                return None
            if job.cancel_requested:  # cancelled while its previous runner was gone
                repository.finish_job(session, job.id, self.runner_id, repository.CANCELLED)
                return None
            if job.attempts > self.settings.job_max_attempts:
                message = (
                    f"gave up after {job.attempts - 1} attempts: the worker process died each "
                    f"time (search the service log for job id {job.id})"
                )
                repository.fail_job(session, job.id, message)
                log.error(message, extra={"job_id": job.id})
                return None
            return job

    def _run(self, slot: _Slot, job: Job) -> None:
        assert slot.conn is not None
        token = logs.job_id.set(job.id)
        slot.assign(job.id)
        log.info("job started", extra={"kind": job.kind, "attempt": job.attempts})
        try:
            try:
                target = self.registry[job.kind].target
                slot.conn.send(("run", job.id, job.tenant_id, target, job.params))
            except (OSError, ValueError):  # the worker died before it got the job
                outcome: tuple[Any, ...] = ("died",)
            else:
                outcome = self._follow(slot, job)
            self._record(slot, job, outcome)
        except Exception:
            # Lost track (e.g. the database went away while recording the outcome): kill the
            # worker so the pipe cannot carry stale messages into the next job; the job's lease
            # expires and it is re-queued.
            slot.kill("lost")
            raise
        finally:
            slot.assign(None)
            logs.job_id.reset(token)

    def _follow(self, slot: _Slot, job: Job) -> tuple[Any, ...]:
        """Relay progress to the database until the worker reports an outcome or dies.

        Progress is written at most every ``PROGRESS_WRITE_INTERVAL_S`` (immediately when the
        stage changes), and a heartbeat at least every ``job_heartbeat_s``.
        """
        assert slot.conn is not None
        last_write = time.monotonic()
        last_stage: str | None = None
        pending: dict[str, Any] | None = None
        while True:
            since = time.monotonic() - last_write
            wait = (
                self.settings.job_heartbeat_s - since
                if pending is None
                else PROGRESS_WRITE_INTERVAL_S - since
            )
            try:
                message = slot.conn.recv() if slot.conn.poll(max(wait, 0.0)) else None
            except (EOFError, OSError):
                return ("died",)
            if message is not None and message[0] != "progress":
                return tuple(message)
            if message is not None:
                pending = {"stage": message[1], "fraction": message[2], "iteration": message[3]}
                urgent = message[1] != last_stage
                if not urgent and time.monotonic() - last_write < PROGRESS_WRITE_INTERVAL_S:
                    continue
                last_stage = message[1]
            try:
                with self.database.session() as session:
                    cancel = repository.update_progress(
                        session, job.id, self.runner_id, **(pending or {})
                    )
            except Exception as exc:  # keep relaying; the next write retries
                log.warning("could not record job progress: %s", exc)
                cancel = False
            last_write, pending = time.monotonic(), None
            if cancel:
                slot.kill("cancel")

    def _record(self, slot: _Slot, job: Job, outcome: tuple[Any, ...]) -> None:
        kind = outcome[0]
        with self.database.session() as session:
            if kind == "died":
                reason = slot.kill_reason
                if reason == "cancel" or (reason is None and self._cancel_requested(session, job)):
                    finished = repository.finish_job(
                        session, job.id, self.runner_id, repository.CANCELLED
                    )
                elif reason == "shutdown":
                    repository.release_job(session, job.id, self.runner_id)
                    log.info("job handed back to the queue at shutdown")
                    return
                else:
                    code = None
                    if slot.process is not None:
                        slot.process.join(1.0)
                        code = slot.process.exitcode
                    log.error("worker process died during the job", extra={"exitcode": code})
                    repository.requeue_job(session, job.id, self.runner_id)
                    return
            elif kind == "done":
                finished = repository.finish_job(
                    session,
                    job.id,
                    self.runner_id,
                    repository.SUCCEEDED,
                    artifacts=outcome[1],
                    summary=outcome[2] if len(outcome) > 2 else None,
                )
            else:
                finished = repository.finish_job(
                    session, job.id, self.runner_id, repository.FAILED, error=outcome[1]
                )
        if finished is not None:
            log.info("job %s", finished.state)
            if self._on_finished is not None:
                self._on_finished(finished)

    @staticmethod
    def _cancel_requested(session: Any, job: Job) -> bool:
        current = session.get(Job, job.id, populate_existing=True)
        return bool(current is not None and current.cancel_requested)

    # leases

    def _maintenance_loop(self) -> None:
        interval = max(self.settings.job_lease_s / 3, 0.5)
        while not self._stopping.wait(interval):
            try:
                with self.database.session() as session:
                    expired = repository.requeue_expired_leases(session, self.settings.job_lease_s)
                if expired:
                    log.warning("re-queued %d job(s) with expired leases", len(expired))
                    self.notify()
            except Exception:
                log.exception("lease check failed; retrying")
