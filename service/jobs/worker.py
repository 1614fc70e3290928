"""The worker-process side of :mod:`service.jobs.runner`: runs job functions, reports over a pipe.

A worker never touches the database (it does not even import it): it reads input files, writes
artifact files atomically, and sends ``("progress", stage, fraction, iteration)`` messages and
one outcome (``("done", artifacts, summary)`` or ``("failed", message)``) per job. Cancellation
kills the process (the service replaces it), so job functions need no cancellation checks.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import multiprocessing.connection
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service.jobs import logs
from service.jobs.lifeline import die_with_parent
from service.storage.files import FileStore, tenant_path
from solver.errors import KincalError

log = logging.getLogger("kincal.worker")
WORKER_NICENESS = 10
"""Jobs run behind the service's request loop: a calibration must not slow rankings down."""


@dataclass
class JobContext:
    """What a job function gets: its parameters, the data folder, progress and artifacts."""

    job_id: str
    tenant_id: str
    params: dict[str, Any]
    files: FileStore
    _send: Callable[[tuple[Any, ...]], None] = field(repr=False)
    artifacts: dict[str, str] = field(default_factory=dict)
    summary: dict[str, Any] = field(default_factory=dict)
    """What the job's status shows of its result once it succeeded (JSON-able)."""

    def progress(
        self, stage: str, fraction: float | None = None, iteration: int | None = None
    ) -> None:
        """Report progress: ``stage`` name, overall ``fraction`` in [0, 1], ``iteration``."""
        clipped = None if fraction is None else min(max(float(fraction), 0.0), 1.0)
        self._send(("progress", stage, clipped, iteration))

    def write_artifact(self, name: str, filename: str, data: bytes) -> str:
        """Store an output file atomically under the job's folder; returns its stored path."""
        path = self.files.write(tenant_path(self.tenant_id, "jobs", self.job_id, filename), data)
        self.artifacts[name] = path
        return path


def _resolve(target: str) -> Callable[[JobContext], None]:
    module, _, function = target.partition(":")
    return getattr(importlib.import_module(module), function)  # type: ignore[no-any-return]


def worker_main(
    conn: multiprocessing.connection.Connection,
    service_pid: int,
    data_dir: str,
    log_level: str,
    log_format: str,
    preload: list[str],
) -> None:
    """Entry point of a worker process: run jobs sent over ``conn`` until told to stop."""
    logs.configure_logging(log_level, log_format)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the service decides what stops
    with contextlib.suppress(OSError):  # lowering one's own priority is always allowed
        os.nice(WORKER_NICENESS)
    # kill -9 of the service leaves it no chance to tell us: exit when our parent (the
    # service, or its fork server) changes or the service's process disappears.
    die_with_parent(also_alive=service_pid)
    for module in preload:
        importlib.import_module(module)
    files = FileStore(Path(data_dir))
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        _, job_id, tenant_id, target, params = message
        token = logs.job_id.set(job_id)
        try:
            conn.send(_run_job(conn, files, job_id, tenant_id, target, params))
        finally:
            logs.job_id.reset(token)


def _run_job(
    conn: multiprocessing.connection.Connection,
    files: FileStore,
    job_id: str,
    tenant_id: str,
    target: str,
    params: dict[str, Any],
) -> tuple[Any, ...]:
    ctx = JobContext(job_id, tenant_id, params, files, conn.send)
    started = time.perf_counter()
    try:
        _resolve(target)(ctx)
    except KincalError as exc:
        log.info("job failed: %s", exc)
        return ("failed", str(exc))
    except Exception:
        log.exception("job failed with an internal error")
        return ("failed", f"internal error in job {job_id}; the service log has the details")
    log.info("job finished", extra={"duration_s": round(time.perf_counter() - started, 3)})
    return ("done", ctx.artifacts, ctx.summary or None)
