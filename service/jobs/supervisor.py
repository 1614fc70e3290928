"""``kincal serve``: a supervisor process, ``web_processes`` request processes, one job runner.

* The supervisor migrates the database, creates tenant 'local' in keyless mode, binds the
  listening socket once and starts its children from its main thread (see
  :mod:`service.jobs.lifeline`: they die with it, even after ``kill -9``). It imports no web or
  solver code and serves nothing itself.
* Request processes (``service.api.child web``) share the socket: the kernel hands each new
  connection to whichever process accepts it first. Each runs uvicorn with the whole app; their
  job runner is a :class:`~service.jobs.runner_link.RemoteRunner` (wake pipe + status file).
* The job-runner process (``service.api.child runner``, only when ``workers > 0``) claims jobs
  and feeds them to its worker processes. There is exactly one per ``kincal serve``, so a job
  runs once.
* Metrics: each child records in ``<run dir>/metrics`` (``PROMETHEUS_MULTIPROC_DIR``); a scrape
  of any request process sums them. The run directory is ``<data_dir>/run/<host>-<pid>``,
  emptied at start and removed at exit; those of dead supervisors on this host are removed at
  start.
* A child that exits unexpectedly is restarted (a request process at once, the runner too: its
  start re-queues the jobs it was running). More than ``MAX_RESTARTS`` exits of one kind within
  ``RESTART_WINDOW_S``: the supervisor logs why, stops everything and exits with status 1.
* SIGTERM or SIGINT: every child gets SIGTERM (request processes finish the requests they have,
  the runner lets running jobs finish for ``shutdown_grace_s`` and re-queues the rest); after
  ``shutdown_grace_s`` + ``STOP_MARGIN_S`` what is left is killed. Exit status 0. A second
  signal kills them at once (the next start re-queues the jobs they ran). Children are in
  process groups of their own, so Ctrl-C in a terminal reaches the supervisor only.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

from service import kincal_version
from service.jobs import logs
from service.jobs.lifeline import pid_alive
from service.settings import Settings, load_settings
from service.storage import repository
from service.storage.db import Database
from service.storage.repository import LOCAL_TENANT
from solver.errors import KincalError

log = logging.getLogger("kincal.service")

POLL_S = 0.2
MAX_RESTARTS = 5
RESTART_WINDOW_S = 60.0
STOP_MARGIN_S = 15.0
LISTEN_BACKLOG = 2048
WEB, RUNNER = "web", "runner"


@dataclass
class Child:
    role: str
    index: int
    process: subprocess.Popen[bytes]

    @property
    def name(self) -> str:
        return RUNNER if self.role == RUNNER else f"{WEB}-{self.index}"


@dataclass
class _Restarts:
    times: dict[str, collections.deque[float]] = field(
        default_factory=lambda: collections.defaultdict(collections.deque)
    )

    def too_many(self, role: str, now: float) -> bool:
        """Record an exit of a ``role`` child at ``now``; whether it is one too many."""
        times = self.times[role]
        times.append(now)
        while times and now - times[0] > RESTART_WINDOW_S:
            times.popleft()
        return len(times) > MAX_RESTARTS


def run_dir_for(data_dir: Path) -> Path:
    """``<data_dir>/run/<host>-<pid>``, emptied; run folders of dead supervisors on this host
    are removed (their metric files would otherwise pile up)."""
    runs = data_dir / "run"
    runs.mkdir(parents=True, exist_ok=True)
    host = socket.gethostname()
    for entry in runs.iterdir():
        owner, _, pid = entry.name.rpartition("-")
        if owner == host and pid.isdigit() and not pid_alive(int(pid)):
            shutil.rmtree(entry, ignore_errors=True)
    run_dir = runs / f"{host}-{os.getpid()}"
    shutil.rmtree(run_dir, ignore_errors=True)
    (run_dir / "metrics").mkdir(parents=True)
    return run_dir


def listen(host: str, port: int) -> socket.socket:
    """The service's listening socket (inherited by the request processes)."""
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
        sock = socket.create_server((host, port), family=family, backlog=LISTEN_BACKLOG)
    except OSError as exc:
        raise KincalError(
            f"cannot listen on {host}:{port}: {exc.strerror or exc}; choose another "
            "--port/--host (KINCAL_PORT, KINCAL_HOST) or stop what uses it"
        ) from exc
    sock.set_inheritable(True)
    return sock


def prepare_database(settings: Settings) -> str:
    """Migrate once, before any child starts (they never migrate concurrently); the backend."""
    database = Database(settings.resolved_database_url)
    try:
        database.migrate()
        if settings.keyless:
            with database.session() as session:
                repository.ensure_tenant(session, LOCAL_TENANT)
        return database.backend
    finally:
        database.dispose()


class Supervisor:
    def __init__(self, settings: Settings, announce: Callable[[str], None] | None = None) -> None:
        self.settings = settings
        self.announce = announce
        """Told, once the service's processes are started, where it listens (``kincal serve``
        prints it on stdout)."""
        self.children: list[Child] = []
        self._signal: int | None = None
        self._stopping = False
        self._restarts = _Restarts()

    # signals

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        if self._stopping:  # a second Ctrl-C: stop now (running jobs are re-queued at start)
            log.warning("second signal: killing the service's processes")
            for child in self.children:
                with contextlib.suppress(ProcessLookupError):
                    child.process.kill()
        self._signal = signum

    # children

    def _spawn(self, role: str, index: int) -> Child:
        args = ["--parent-pid", str(os.getpid()), "--run-dir", str(self.run_dir)]
        args += ["--index", str(index), "--wake-fd", str(self._wake[0 if role == RUNNER else 1])]
        fds: tuple[int, ...] = (self._wake[0],) if role == RUNNER else (self._wake[1],)
        if role == WEB:
            args += ["--listen-fd", str(self.sock.fileno())]
            fds += (self.sock.fileno(),)
        env = {
            **os.environ,
            "KINCAL_HOST": self.settings.host,
            "KINCAL_PORT": str(self.settings.port),
            "PROMETHEUS_MULTIPROC_DIR": str(self.run_dir / "metrics"),
        }
        process = subprocess.Popen(
            [sys.executable, "-m", "service.api.child", role, *args],
            env=env,
            stdin=subprocess.DEVNULL,
            pass_fds=fds,
            process_group=0,  # Ctrl-C reaches the supervisor only; it decides what stops
        )
        child = Child(role, index, process)
        log.info("%s process started", child.name, extra={"pid": process.pid, "role": role})
        return child

    def _start_children(self) -> None:
        if self.settings.workers > 0:
            self.children.append(self._spawn(RUNNER, 0))
        for index in range(self.settings.web_processes):
            self.children.append(self._spawn(WEB, index))

    def _watch_children(self) -> int | None:
        """Restart children that exited; an exit status for the supervisor if it must stop."""
        for position, child in enumerate(self.children):
            code = child.process.poll()
            if code is None:
                continue
            if self._restarts.too_many(child.role, time.monotonic()):
                log.critical(
                    "%s process exited with status %s, the %d-th exit of a %s process within "
                    "%.0f s; stopping the service (see the lines above for why)",
                    child.name,
                    code,
                    MAX_RESTARTS + 1,
                    child.role,
                    RESTART_WINDOW_S,
                )
                return 1
            log.error(
                "%s process (pid %d) exited with status %s; restarting it",
                child.name,
                child.process.pid,
                code,
            )
            self.children[position] = self._spawn(child.role, child.index)
        return None

    def _stop_children(self) -> None:
        self._stopping = True
        for child in self.children:
            if child.process.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    child.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.settings.shutdown_grace_s + STOP_MARGIN_S
        for child in self.children:
            try:
                child.process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("%s process did not stop in time; killing it", child.name)
                child.process.kill()
                child.process.wait()

    # the whole life

    def where(self) -> str:
        """Where the service listens and where its documentation is, for a person."""
        host, port = self.sock.getsockname()[:2]
        shown = f"[{host}]" if ":" in host else host
        url = f"http://{shown}:{port}"
        keys = (
            "keyless on loopback"
            if self.settings.keyless
            else "send X-API-Key (kincal keys create)"
        )
        return (
            f"kincal {kincal_version()} listening on {url} ({keys}); API {url}/api/v1, "
            f"interactive docs {url}/docs, ready when {url}/readyz answers 200; Ctrl-C stops it"
        )

    def run(self) -> int:
        """Serve until SIGTERM/SIGINT (exit status 0) or a child keeps dying (1)."""
        settings = self.settings
        backend = prepare_database(settings)
        self.sock = listen(settings.host, settings.port)
        self.run_dir = run_dir_for(settings.data_dir)
        read_end, write_end = os.pipe()
        os.set_blocking(write_end, False)  # request processes never wait for the runner
        self._wake = (read_end, write_end)
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, self._on_signal)
        if settings.keyless:
            log.warning(
                "keyless mode: bound to loopback address %s, requests without X-API-Key act "
                "as tenant '%s' (set KINCAL_ALLOW_KEYLESS_LOCALHOST=false to require keys)",
                settings.host,
                LOCAL_TENANT,
            )
        else:
            log.info("API keys required (bound to %s)", settings.host)
        status = 0
        try:
            self._start_children()
            log.info(
                "kincal service started",
                extra={
                    "version": kincal_version(),
                    "database": backend,
                    "data_dir": str(settings.data_dir),
                    "address": f"{settings.host}:{settings.port}",
                    "web_processes": settings.web_processes,
                    "workers": settings.workers,
                },
            )
            if self.announce is not None:
                self.announce(self.where())
            while self._signal is None:
                failure = self._watch_children()
                if failure is not None:
                    status = failure
                    break
                time.sleep(POLL_S)
            log.info(
                "shutting down: waiting up to %.0f s for running jobs", settings.shutdown_grace_s
            )
        finally:
            self._stop_children()
            self.sock.close()
            os.close(read_end)
            os.close(write_end)
            shutil.rmtree(self.run_dir, ignore_errors=True)
        log.info("kincal service stopped")
        return status


def run_server(
    host: str | None = None,
    port: int | None = None,
    announce: Callable[[str], None] | None = None,
) -> int:
    """Serve until SIGINT/SIGTERM; then finish or re-queue running jobs. The exit status.
    ``announce`` is told where the service listens once its processes are started."""
    overrides = {name: value for name, value in (("host", host), ("port", port)) if value}
    settings = load_settings(**overrides)
    logs.process_name = "supervisor"
    logs.configure_logging(settings.log_level, settings.log_format)
    return Supervisor(settings, announce).run()
