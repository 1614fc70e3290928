"""How request processes talk to the job-runner process of the same ``kincal serve``.

The database stays the only shared state of jobs (queue, progress, cancellation requests). Two
small channels make the runner react at once and let readiness see it:

* **wake pipe**: the supervisor creates one pipe; request processes hold its write end, the
  runner its read end. A byte means "look at the database now": claim newly queued jobs, kill
  workers whose job's cancellation was recorded. Writes never block (a full pipe already holds
  a wake-up); without them the runner still polls every ``job_poll_s`` and sees cancellations
  at its next progress write or heartbeat.
* **status file** (``<run dir>/runner.json``, replaced atomically every
  ``STATUS_INTERVAL_S``): the runner's pid, health and live workers, read by ``/readyz`` and
  ``/metrics`` of every request process. A status older than ``STATUS_MAX_AGE_S`` means the
  runner is gone or stuck: not ready, 0 workers.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("kincal.jobs")

STATUS_FILE = "runner.json"
STATUS_INTERVAL_S = 1.0
STATUS_MAX_AGE_S = 5.0
WAKE = b"!"


def send_wake(fd: int) -> None:
    """Nudge the runner (never blocks; a full pipe or an absent runner are not errors)."""
    with contextlib.suppress(BlockingIOError, BrokenPipeError, OSError):
        os.write(fd, WAKE)


def listen_for_wakes(fd: int, on_wake: Callable[[], None]) -> threading.Thread:
    """Call ``on_wake`` (in a daemon thread) after each batch of bytes read from ``fd``."""

    def loop() -> None:
        os.set_blocking(fd, True)
        while True:
            try:
                if not os.read(fd, 4096):
                    return
                on_wake()
            except Exception:  # keep listening (e.g. the database restarts)
                log.exception("handling a wake-up failed")
                time.sleep(0.5)

    thread = threading.Thread(target=loop, name="kincal-runner-wake", daemon=True)
    thread.start()
    return thread


@dataclass(frozen=True)
class RunnerStatus:
    pid: int
    healthy: bool
    workers_alive: int
    written_at: float
    """``time.time()`` of the write (processes share the wall clock, not ``monotonic``)."""

    def fresh(self, now: float | None = None) -> bool:
        return (time.time() if now is None else now) - self.written_at < STATUS_MAX_AGE_S


def write_status(run_dir: Path, healthy: bool, workers_alive: int) -> None:
    """Replace ``<run_dir>/runner.json`` atomically (readers see the old or the new one)."""
    status = RunnerStatus(os.getpid(), healthy, workers_alive, time.time())
    target = run_dir / STATUS_FILE
    tmp = target.with_name(f".{STATUS_FILE}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(status.__dict__), encoding="utf-8")
    os.replace(tmp, target)


def read_status(run_dir: Path) -> RunnerStatus | None:
    """The runner's last status, or None if it never wrote one (or it cannot be read)."""
    try:
        return RunnerStatus(**json.loads((run_dir / STATUS_FILE).read_text(encoding="utf-8")))
    except (OSError, ValueError, TypeError):
        return None


class RemoteRunner:
    """The request side's handle on the runner process
    (see :class:`service.jobs.runner.RunnerHandle`).

    ``start``/``stop`` do nothing: the supervisor owns the runner's life.
    """

    def __init__(self, run_dir: Path, wake_fd: int | None, *, workers: int) -> None:
        self.run_dir = run_dir
        self.wake_fd = wake_fd
        self.workers = workers

    def start(self) -> None:
        """Nothing to start here: the supervisor owns the runner process."""

    def stop(self, grace_s: float | None = None) -> None:
        """Nothing to stop here: the supervisor owns the runner process."""

    def notify(self) -> None:
        if self.wake_fd is not None:
            send_wake(self.wake_fd)

    def cancel(self, job_id: str) -> bool:
        """The cancellation is in the database already; the runner kills the worker."""
        self.notify()
        return False

    def _status(self) -> RunnerStatus | None:
        status = read_status(self.run_dir)
        return status if status is not None and status.fresh() else None

    def healthy(self) -> bool:
        if self.workers == 0:
            return True
        status = self._status()
        return status is not None and status.healthy

    def workers_alive(self) -> int:
        status = self._status()
        return 0 if status is None else status.workers_alive
