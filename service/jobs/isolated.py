"""Run a function on untrusted input in a child process that may crash, run out of memory or
hang without harming the caller: address-space and CPU limits, a wall-clock timeout, and the
child killed when it overruns. Used for the Pinocchio parse of uploaded URDFs."""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import resource
import signal
from collections.abc import Callable
from multiprocessing.context import ForkServerContext, SpawnContext
from typing import Any, Literal

from solver.errors import KincalError

DEFAULT_TIMEOUT_S = 20.0
DEFAULT_EXTRA_MEMORY_BYTES = 1 << 30


class IsolatedFailure(KincalError):
    """The isolated function crashed, ran out of its limits or took too long."""


def _child(
    conn: multiprocessing.connection.Connection,
    function: Callable[..., Any],
    args: tuple[Any, ...],
    extra_memory_bytes: int,
    cpu_s: int,
) -> None:
    with contextlib.suppress(ValueError, OSError):  # limits the platform lacks are skipped
        with open("/proc/self/statm") as statm:
            current = int(statm.read().split()[0]) * resource.getpagesize()
        limit = current + extra_memory_bytes
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_CPU, (cpu_s, cpu_s + 1))
    try:
        conn.send(("ok", function(*args)))
    except KincalError as exc:
        conn.send(("error", type(exc), str(exc)))
    except MemoryError:
        conn.send(("limit", "ran out of its memory limit"))
    except Exception as exc:
        conn.send(("limit", f"failed ({type(exc).__name__}: {exc})"))
    finally:
        conn.close()


def run_isolated(
    function: Callable[..., Any],
    *args: Any,
    what: str,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    extra_memory_bytes: int = DEFAULT_EXTRA_MEMORY_BYTES,
    start_method: Literal["forkserver", "spawn"] = "forkserver",
) -> Any:
    """``function(*args)`` in a child process; its :class:`KincalError` is re-raised here,
    anything else (a crash, a signal, memory or time exhausted) becomes
    :class:`IsolatedFailure` naming ``what``. ``function`` and its result must pickle."""
    context: ForkServerContext | SpawnContext = (
        multiprocessing.get_context("forkserver")
        if start_method == "forkserver"
        else multiprocessing.get_context("spawn")
    )
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(
        target=_child,
        args=(sender, function, args, extra_memory_bytes, max(1, int(timeout_s))),
        name="kincal-isolated",
        daemon=True,
    )
    process.start()
    sender.close()
    message = None
    timed_out = not receiver.poll(timeout_s)
    try:
        if not timed_out:
            message = receiver.recv()
    except (EOFError, OSError):
        pass
    finally:
        receiver.close()
        if message is None:
            process.kill()
        process.join(5.0)
    if message is None:
        code = process.exitcode
        if timed_out:
            reason = f"took longer than {timeout_s:g} s"
        elif code is not None and code < 0:
            reason = f"crashed ({signal.Signals(-code).name})"
        else:
            reason = f"exited with status {code}"
        raise IsolatedFailure(f"{what} {reason}; the input is refused")
    if message[0] == "ok":
        return message[1]
    if message[0] == "error":
        raise message[1](message[2])
    raise IsolatedFailure(f"{what} {message[1]}; the input is refused")
