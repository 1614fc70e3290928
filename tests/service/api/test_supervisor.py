"""The pieces of ``kincal serve``'s process model without starting it: the runner link seen
from a request process, the supervisor's restart limit, its run folder, its socket, the
parent-death guard."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.jobs import runner_link, supervisor
from service.jobs.runner_link import RemoteRunner, read_status, send_wake, write_status
from service.jobs.supervisor import Child, Supervisor
from service.settings import Settings
from solver.errors import KincalError
from tests.service import cli_support
from tests.service.api.live import gone


def test_a_request_process_sees_the_runner_only_through_a_fresh_status(tmp_path: Path) -> None:
    remote = RemoteRunner(tmp_path, None, workers=2)
    assert not remote.healthy() and remote.workers_alive() == 0  # never written
    write_status(tmp_path, True, 2)
    assert remote.healthy() and remote.workers_alive() == 2
    status = read_status(tmp_path)
    assert status is not None and status.pid == os.getpid() and status.fresh()
    write_status(tmp_path, False, 1)  # a worker is being replaced
    assert not remote.healthy() and remote.workers_alive() == 1
    stale = json.loads((tmp_path / runner_link.STATUS_FILE).read_text())
    stale |= {"healthy": True, "written_at": time.time() - runner_link.STATUS_MAX_AGE_S - 1}
    (tmp_path / runner_link.STATUS_FILE).write_text(json.dumps(stale))
    assert not remote.healthy() and remote.workers_alive() == 0  # runner gone or stuck
    assert RemoteRunner(tmp_path, None, workers=0).healthy()  # no runner configured


def test_wake_ups_never_block_a_request_process(tmp_path: Path) -> None:
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    try:
        started = time.monotonic()
        for _ in range(100_000):  # far more than a pipe holds; nobody reads
            send_wake(write_end)
        assert time.monotonic() - started < 5
        assert os.read(read_end, 16) == runner_link.WAKE * 16
        remote = RemoteRunner(tmp_path, write_end, workers=1)
        assert remote.cancel("cal_x") is False  # the runner process does the killing
    finally:
        os.close(read_end)
        os.close(write_end)


class _DeadProcess:
    pid = 4242

    def poll(self) -> int:
        return 1


def test_a_child_that_keeps_dying_stops_the_service_loudly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Restarted up to MAX_RESTARTS times within RESTART_WINDOW_S; then exit status 1."""
    boss = Supervisor(Settings(data_dir=tmp_path, web_processes=1))
    spawned: list[tuple[str, int]] = []

    def spawn(role: str, index: int) -> Child:
        spawned.append((role, index))
        return Child(role, index, _DeadProcess())  # type: ignore[arg-type]

    monkeypatch.setattr(boss, "_spawn", spawn)
    boss.children = [spawn(supervisor.WEB, 0)]
    outcomes = [boss._watch_children() for _ in range(supervisor.MAX_RESTARTS + 1)]
    assert outcomes == [None] * supervisor.MAX_RESTARTS + [1]
    assert spawned == [(supervisor.WEB, 0)] * (supervisor.MAX_RESTARTS + 1)
    assert "restarting it" in caplog.text and "stopping the service" in caplog.text


def test_the_run_folder_is_fresh_and_dead_supervisors_folders_go(tmp_path: Path) -> None:
    runs = tmp_path / "run"
    host = socket.gethostname()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], stdout=-1)
    stale, live, other_host = (
        runs / f"{host}-{int(dead.stdout)}",
        runs / f"{host}-{os.getppid()}",
        runs / f"elsewhere-{int(dead.stdout)}",
    )
    for folder in (stale, live, other_host, runs / f"{host}-{os.getpid()}" / "metrics"):
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "counter_1.db").write_bytes(b"old")
    run_dir = supervisor.run_dir_for(tmp_path)
    assert run_dir == runs / f"{host}-{os.getpid()}"
    assert list(run_dir.rglob("*")) == [run_dir / "metrics"]  # emptied
    assert not stale.exists() and live.exists() and other_host.exists()


def test_a_taken_port_is_a_clear_error_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        with pytest.raises(KincalError, match=f"cannot listen on 127.0.0.1:{port}.*--port"):
            supervisor.listen("127.0.0.1", port)
        monkeypatch.setenv("KINCAL_DATA_DIR", str(tmp_path))
        monkeypatch.setenv("KINCAL_DATABASE_URL", f"sqlite:///{tmp_path / 'kincal.db'}")
        monkeypatch.setattr("service.jobs.logs.configure_logging", lambda *args: None)
        code, _, err = cli_support.run(["serve", "--port", port], capsys, monkeypatch)
    assert code == 2 and f"cannot listen on 127.0.0.1:{port}" in err


def _orphan_script() -> str:
    """A parent that starts a child calling die_with_parent, prints its pid and sleeps."""
    child = "from service.jobs.lifeline import die_with_parent; import time; die_with_parent(); "
    child += "time.sleep(60)"
    return (
        "import subprocess, sys, time\n"
        f"p = subprocess.Popen([sys.executable, '-c', {child!r}])\n"
        "print(p.pid, flush=True)\n"
        "time.sleep(60)\n"
    )


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_child_dies_with_its_parent_even_after_kill_9(tmp_path: Path) -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", _orphan_script()], stdout=subprocess.PIPE, text=True
    )
    assert parent.stdout is not None
    child = int(parent.stdout.readline())
    time.sleep(1.0)  # the child armed its guard
    assert not gone(child)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 5
    while not gone(child):
        assert time.monotonic() < deadline, "the child outlived its parent"
        time.sleep(0.05)


def test_a_second_signal_while_stopping_kills_the_children(tmp_path: Path) -> None:
    boss = Supervisor(Settings(data_dir=tmp_path, web_processes=1))
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    boss.children = [Child(supervisor.WEB, 0, sleeper)]
    try:
        boss._on_signal(signal.SIGINT, None)  # the first asks for a graceful stop
        time.sleep(0.2)
        assert sleeper.poll() is None and boss._signal == signal.SIGINT
        boss._stopping = True  # what _stop_children sets
        boss._on_signal(signal.SIGINT, None)
        assert sleeper.wait(5) == -signal.SIGKILL
    finally:
        sleeper.kill()
        sleeper.wait()


def test_an_invalid_setting_is_a_clear_error_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("KINCAL_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("KINCAL_WEB_PROCESSES", "0")
    code, _, err = cli_support.run(["serve"], capsys, monkeypatch)
    assert code == 2
    assert (
        "invalid setting KINCAL_WEB_PROCESSES='0': Input should be greater than or equal to 1"
        in err
    )
    assert "Traceback" not in err and not list(tmp_path.iterdir())  # refused before anything


def test_the_supervisor_imports_no_web_or_solver_code() -> None:
    """It only starts and watches its children: importing it must not pull in the web app,
    numpy or Pinocchio (each child would otherwise be forked from a 350 MB parent and the
    start take seconds longer)."""
    heavy = ("fastapi", "numpy", "pinocchio", "service.api.app", "solver.stream")
    code = (
        "import sys; import service.jobs.supervisor; "
        f"print([m for m in {heavy!r} if m in sys.modules])"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert loaded == "[]", loaded
