"""Job functions used only by the tests (imported by worker processes by name)."""

from __future__ import annotations

import json
import os

from service.jobs.worker import JobContext


def crash(ctx: JobContext) -> None:
    """Die like a worker hit by the OOM killer or a segfault."""
    ctx.progress("about to crash", 0.5)
    os._exit(13)


def echo(ctx: JobContext) -> None:
    """Write the job's parameters back as its result."""
    ctx.progress("echoing", 0.5, 1)
    ctx.write_artifact("result", "echo.json", json.dumps(ctx.params).encode())
