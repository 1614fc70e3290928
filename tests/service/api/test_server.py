"""``kincal serve`` start-up (service/api/server.py)."""

from __future__ import annotations

import gc
import sys
from pathlib import Path
from typing import Any

import pytest

from service.api import server


def test_the_startup_heap_is_frozen_before_serving(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full garbage collection over the ~3·10^5 objects of the imports stalls the request
    loop for 100-170 ms (the rankings' p99): they are frozen before uvicorn starts."""
    monkeypatch.setenv("KINCAL_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("KINCAL_DATABASE_URL", f"sqlite:///{tmp_path / 'kincal.db'}")
    seen: dict[str, Any] = {}

    def run(app: Any, **options: Any) -> None:
        seen["frozen"] = gc.get_freeze_count()
        seen["options"] = options

    monkeypatch.setattr(server.uvicorn, "run", run)
    monkeypatch.setattr(server, "configure_logging", lambda *args: None)
    try:
        server.run_server(port=8765)
    finally:
        gc.unfreeze()
    assert seen["frozen"] > 10_000
    assert seen["options"]["port"] == 8765 and seen["options"]["access_log"] is False


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
