"""service.jobs.isolated: a function that crashes, hangs or eats memory in its child process is
refused with a one-line reason; the caller lives on."""

from __future__ import annotations

import ctypes
import time

import pytest

from service.jobs.isolated import IsolatedFailure, run_isolated
from solver.errors import ModelError


def _segfault() -> None:
    ctypes.string_at(0)


def _sleep(seconds: float) -> None:
    time.sleep(seconds)


def _allocate(n_bytes: int) -> int:
    return len(bytearray(n_bytes))


def _domain_error() -> None:
    raise ModelError("frame 'x' is not in the URDF")


def _add(a: int, b: int) -> int:
    return a + b


def test_results_and_domain_errors_come_back() -> None:
    assert run_isolated(_add, 2, 3, what="adding") == 5
    with pytest.raises(ModelError, match="frame 'x'"):
        run_isolated(_domain_error, what="building")


def test_a_segfault_is_a_refusal_not_a_crash_of_the_caller() -> None:
    with pytest.raises(IsolatedFailure, match=r"parsing crashed \(SIGSEGV\)"):
        run_isolated(_segfault, what="parsing")


def test_a_hang_is_killed_at_the_timeout() -> None:
    started = time.perf_counter()
    with pytest.raises(IsolatedFailure, match="took longer than 1 s"):
        run_isolated(_sleep, 30.0, what="parsing", timeout_s=1.0)
    assert time.perf_counter() - started < 10.0


def test_memory_beyond_the_limit_is_refused() -> None:
    with pytest.raises(IsolatedFailure, match="memory"):
        run_isolated(_allocate, 3 << 30, what="parsing", extra_memory_bytes=256 << 20)
    assert run_isolated(_allocate, 1 << 20, what="parsing") == 1 << 20
