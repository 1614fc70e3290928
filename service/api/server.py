"""The two kinds of child process of ``kincal serve`` (:mod:`service.jobs.supervisor` starts
them through :mod:`service.api.child`): a request process serving the app, and the job
runner."""

from __future__ import annotations

import gc
import logging
import signal
import socket
import time
from pathlib import Path
from types import FrameType

from service.api.metrics import Metrics
from service.jobs.runner import JobRunner, default_registry
from service.jobs.runner_link import STATUS_INTERVAL_S, RemoteRunner, listen_for_wakes, write_status
from service.settings import Settings
from service.storage.db import Database
from service.storage.files import FileStore

log = logging.getLogger("kincal.jobs")


def serve_requests(settings: Settings, listen_fd: int, run_dir: Path, wake_fd: int) -> None:
    """A request process: the app on the inherited listening socket, jobs left to the runner
    process (reached through ``run_dir`` and the wake pipe). Returns after SIGTERM/SIGINT once
    the requests in flight are answered. The app (every route and use case, ~2.5 s of
    imports) is imported here, not by the module: the job runner needs none of it."""
    import uvicorn

    from service.api.app import create_app

    sock = socket.socket(fileno=listen_fd)
    app = create_app(settings, runner=RemoteRunner(run_dir, wake_fd, workers=settings.workers))
    freeze_startup_heap()
    config = uvicorn.Config(
        app,
        log_config=None,
        access_log=False,  # the request middleware writes one structured line per request
        timeout_graceful_shutdown=int(settings.shutdown_grace_s) + 5,
        server_header=False,
    )
    uvicorn.Server(config).run(sockets=[sock])


def run_job_runner(settings: Settings, run_dir: Path, wake_fd: int) -> None:
    """The job-runner process: claims jobs and runs them in ``settings.workers`` worker
    processes; woken by the request processes, writes its status for their readiness. On
    SIGTERM/SIGINT running jobs get ``shutdown_grace_s`` to finish, the rest are re-queued."""
    stop: list[int] = []

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        stop.append(signum)

    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, on_signal)
    database = Database(settings.resolved_database_url)
    registry = default_registry()
    metrics = Metrics(database, registry.names, lambda: runner.workers_alive())
    runner = JobRunner(
        settings, database, FileStore(settings.data_dir), registry, on_finished=metrics.observe_job
    )
    runner.start()

    def wake() -> None:
        runner.notify()
        runner.check_cancellations()

    listen_for_wakes(wake_fd, wake)
    next_check = 0.0
    while not stop:
        if time.monotonic() >= next_check:
            write_status(run_dir, runner.healthy(), runner.workers_alive())
            try:  # in case a wake-up was missed (e.g. sent while this process restarted)
                runner.check_cancellations()
            except Exception as exc:
                log.warning("could not check for cancelled jobs: %s", exc)
            next_check = time.monotonic() + STATUS_INTERVAL_S
        time.sleep(0.1)
    write_status(run_dir, False, runner.workers_alive())
    log.info(
        "job runner stopping: waiting up to %.0f s for running jobs", settings.shutdown_grace_s
    )
    runner.stop()
    database.dispose()
    log.info("job runner stopped")


def freeze_startup_heap() -> None:
    """Move every object that exists now (the imports: numpy, Pinocchio, pandas, the pydantic
    schemas, ~3·10^5 objects) to the garbage collector's permanent generation. A full
    collection traversing them stalls the request loop for 100-170 ms, which is the rankings'
    p99 under load; after this, full collections only traverse what the service allocated
    since (startup garbage is collected first, and nothing frozen is ever freed)."""
    gc.collect()
    gc.freeze()
