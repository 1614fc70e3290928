"""``kincal serve`` start-up (service/api/server.py)."""

from __future__ import annotations

import gc
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import uvicorn

from service.api import server
from service.settings import Settings


def test_the_startup_heap_is_frozen_before_serving(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full garbage collection over the ~3·10^5 objects of the imports stalls the request
    loop for 100-170 ms (the rankings' p99): a request process freezes them before uvicorn
    starts serving on the socket it inherited."""
    monkeypatch.setenv("KINCAL_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("KINCAL_DATABASE_URL", f"sqlite:///{tmp_path / 'kincal.db'}")
    seen: dict[str, Any] = {}

    class FakeServer:
        def __init__(self, config: Any) -> None:
            seen["config"] = config

        def run(self, sockets: list[socket.socket]) -> None:
            seen["frozen"] = gc.get_freeze_count()
            seen["addresses"] = [sock.getsockname() for sock in sockets]

    monkeypatch.setattr(uvicorn, "Server", FakeServer)
    listening = socket.create_server(("127.0.0.1", 0))
    address = listening.getsockname()
    read_end, write_end = os.pipe()
    try:
        server.serve_requests(Settings(), os.dup(listening.fileno()), tmp_path, write_end)
    finally:
        gc.unfreeze()
        listening.close()
        os.close(read_end)
        os.close(write_end)
    assert seen["frozen"] > 10_000
    assert seen["addresses"] == [address]
    assert seen["config"].access_log is False and seen["config"].server_header is False


@pytest.mark.skipif(sys.platform == "win32", reason="uvloop is not a dependency on Windows")
def test_uvicorn_runs_on_its_fast_stack() -> None:
    """uvloop and httptools are dependencies (pyproject.toml): uvicorn's "auto" loop and HTTP
    protocol pick them (h11 and the asyncio loop cost ~15 % more CPU per ranking)."""
    from uvicorn.loops.auto import auto_loop_factory
    from uvicorn.protocols.http.auto import AutoHTTPProtocol

    assert AutoHTTPProtocol.__name__ == "HttpToolsProtocol"
    loop = auto_loop_factory()()
    try:
        assert type(loop).__module__.startswith("uvloop")
    finally:
        loop.close()


def test_the_job_runner_process_imports_no_web_application() -> None:
    """The runner child (``python -m service.api.child runner``) imports
    :mod:`service.api.server` for its job loop; the app (FastAPI, every route and use case,
    ~2.5 s) is imported by the request processes only, so a runner starts (and is replaced
    after a crash) in a fraction of that."""
    code = (
        "import sys; import service.api.server; "
        "print(sorted(m for m in ('fastapi', 'service.api.app', 'service.app.job_functions', "
        "'pinocchio', 'matplotlib') if m in sys.modules))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "[]", run.stdout


def test_a_request_process_starts_without_the_pipelines(tmp_path: Path) -> None:
    """A request process (the app built, as ``kincal serve`` builds it) imports no calibration,
    discovery or design pipeline, nor cvxpy, scipy.stats or matplotlib: those load on the
    first request that needs them (~1 s of start-up less per request process)."""
    heavy = (
        "cvxpy",
        "scipy.stats",
        "matplotlib",
        "service.app.calibrate",
        "service.app.discover",
        "service.app.design",
        "service.app.job_functions",
    )
    code = (
        "import sys; from service.api.app import create_app; from service.settings import "
        f"Settings; create_app(Settings()); print(sorted(m for m in {heavy!r} "
        "if m in sys.modules))"
    )
    env = {
        **os.environ,
        "KINCAL_DATA_DIR": str(tmp_path),
        "KINCAL_DATABASE_URL": f"sqlite:///{tmp_path / 'kincal.db'}",
    }
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
    )
    assert run.stdout.strip() == "[]", run.stdout
