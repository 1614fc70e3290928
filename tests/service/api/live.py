"""``kincal serve`` as a real process for the tests that need one (kill -9, signals, several
request processes)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx


def server_environment(
    tmp_path: Path, database_url: str, instance: str, **settings: str
) -> dict[str, str]:
    """The environment of a live ``kincal serve`` in ``tmp_path``: its data folder and
    database, a fast job heartbeat, JSON logs, and ``settings`` (KINCAL_<NAME> = value)."""
    return {
        **os.environ,
        "KINCAL_DATA_DIR": str(tmp_path / "data"),
        "KINCAL_DATABASE_URL": database_url,
        "KINCAL_INSTANCE_NAME": instance,
        "KINCAL_JOB_HEARTBEAT_S": "0.5",
        "KINCAL_LOG_FORMAT": "json",
        **{f"KINCAL_{name.upper()}": value for name, value in settings.items()},
    }


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class Server:
    """``kincal serve`` in its own process group, logging JSON lines to a file."""

    def __init__(self, env: dict[str, str], log_path: Path) -> None:
        self.port = _free_port()
        self.log_path = log_path
        self._log = log_path.open("ab")
        command = [sys.executable, "-c", "from service.cli import main; main()", "serve"]
        self.process = subprocess.Popen(
            [*command, "--port", str(self.port)],
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        self.url = f"http://127.0.0.1:{self.port}"

    def wait_live(self, timeout_s: float = 60.0, path: str = "/healthz") -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            assert self.process.poll() is None, self.log_path.read_text()
            try:
                if httpx.get(f"{self.url}{path}", timeout=1.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise AssertionError(f"server not ready:\n{self.log_path.read_text()}")

    def wait_ready(self, timeout_s: float = 90.0) -> None:
        """Until /readyz says ready (request processes up, the runner's workers alive)."""
        self.wait_live(timeout_s, "/readyz")

    def log_lines(self) -> list[dict[str, Any]]:
        """The JSON lines of the log so far."""
        lines = []
        for line in self.log_path.read_text().splitlines():
            if line.startswith("{"):
                lines.append(json.loads(line))
        return lines

    def pids(self, message: str) -> list[int]:
        """The ``pid`` of every log line whose message is ``message``, in order."""
        return [int(line["pid"]) for line in self.log_lines() if line["msg"] == message]

    def worker_pids(self) -> list[int]:
        return self.pids("worker process started")

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.process.poll() is None:
            self.process.send_signal(sig)
        code = self.process.wait(timeout=30)
        self._log.close()
        return code


def gone(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return True
    return "\nState:\tZ" in status


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (children, their children, ...), from /proc."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    found: list[int] = []
    frontier = [pid]
    while frontier:
        current = frontier.pop()
        children = [child for child, parent in parents.items() if parent == current]
        found += children
        frontier += children
    return found


def port_free(port: int) -> bool:
    """Whether 127.0.0.1:``port`` can be listened on (nobody holds it)."""
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True
