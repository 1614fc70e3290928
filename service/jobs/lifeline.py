"""Child processes that die with their parent.

``kill -9`` of ``kincal serve`` gives it no chance to stop its request processes, job runner
and workers; an orphan would keep the port or run jobs that the next start re-queues (so they
would run twice). Two guards, both cheap:

* on Linux, ``prctl(PR_SET_PDEATHSIG, SIGKILL)``: the kernel kills the child the moment the
  parent thread that started it exits (the supervisor starts every child from its main thread);
* everywhere, a daemon thread that exits the process when its parent changes or a named process
  disappears (twice a second).

Imports nothing heavier than ``ctypes``: worker processes use it too.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1
WATCH_INTERVAL_S = 0.5
ORPHAN_EXIT_CODE = 3


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists (a zombie counts: its parent has not reaped it)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _set_parent_death_signal(sig: int) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent exits (Linux only)."""
    if not sys.platform.startswith("linux"):
        return False
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return bool(libc.prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0) == 0)
    return False


def _watch(parent_pid: int, also_alive: int | None) -> None:
    while True:
        if os.getppid() != parent_pid or (also_alive is not None and not pid_alive(also_alive)):
            os._exit(ORPHAN_EXIT_CODE)
        time.sleep(WATCH_INTERVAL_S)


def die_with_parent(
    parent_pid: int | None = None, *, also_alive: int | None = None, kernel_signal: bool = True
) -> None:
    """Exit (code 3) or be killed as soon as the parent process is gone.

    ``parent_pid``: the parent this process was started by (default: the current one); if it
    is already gone (re-parented before this call) the process exits at once. ``also_alive``:
    another process whose death also ends this one. ``kernel_signal``: also arm
    ``PR_SET_PDEATHSIG`` (SIGKILL) where available.
    """
    expected = os.getppid() if parent_pid is None else parent_pid
    if kernel_signal:
        _set_parent_death_signal(signal.SIGKILL)
    if os.getppid() != expected:  # the parent died before the signal was armed
        os._exit(ORPHAN_EXIT_CODE)
    threading.Thread(
        target=_watch, args=(expected, also_alive), name="kincal-lifeline", daemon=True
    ).start()
