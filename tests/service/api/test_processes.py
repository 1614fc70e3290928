"""``kincal serve`` with two request processes and its job runner in a process of its own
(issue 18 item 8), as real processes on 127.0.0.1: both request processes answer on the one
port, /metrics sums them, each job runs once, cancellation and readiness work whichever process
is asked, a crashed request process or runner is replaced, SIGTERM drains. (kill -9 of the
supervisor: test_crash_recovery.py.)"""

from __future__ import annotations

import os
import re
import signal
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import pytest

from schemas.calibration import CalibrationOptions
from service.api.client import KincalClient
from service.security import create_api_key
from service.storage.db import Database
from service.storage.models import Job
from tests.service.api.conftest import fresh_database_url, recording_bytes
from tests.service.api.live import Server, gone, server_environment

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")

QUICK = CalibrationOptions(heldout=False)
LONG = CalibrationOptions(seeds=list(range(1, 11)))  # several seconds on 2000 samples
TERMINAL = ("succeeded", "failed", "cancelled")


@pytest.fixture
def env(tmp_path: Path) -> Iterator[dict[str, str]]:
    with fresh_database_url(tmp_path) as url:
        yield server_environment(
            tmp_path,
            url,
            "processes-test",
            web_processes="2",
            workers="1",
            shutdown_grace_s="1",
            allow_keyless_localhost="false",
        )


def _key(env: dict[str, str]) -> str:
    database = Database(env["KINCAL_DATABASE_URL"])
    try:
        return create_api_key(database, "lab")[1]
    finally:
        database.dispose()


def _job(env: dict[str, str], job_id: str) -> Job:
    database = Database(env["KINCAL_DATABASE_URL"])
    try:
        with database.sessions() as session:
            job = session.get(Job, job_id)
            assert job is not None
            return job
    finally:
        database.dispose()


def _until(condition: Callable[[], Any], timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while not (value := condition()):
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)
    return value


def _children(server: Server) -> dict[str, int]:
    """Latest pid of each child the supervisor started, by name (web-0, web-1, runner)."""
    started = {}
    for line in server.log_lines():
        if line.get("process") == "supervisor" and line["msg"].endswith(" process started"):
            started[line["msg"].split()[0]] = int(line["pid"])
    return started


def _healthz_counted(metrics: str) -> float:
    match = re.search(
        r'^kincal_http_requests_total\{method="GET",route="/healthz",status="200"\} (\S+)$',
        metrics,
        re.MULTILINE,
    )
    return 0.0 if match is None else float(match.group(1))


def _long_job_running(api: KincalClient, dataset_id: str) -> str:
    job_id = str(api.start_calibration(dataset_id, LONG)["id"])
    _until(lambda: api.status(job_id)["status"]["stage"] == "heldout", 90, "the long job to run")
    return job_id


def test_two_request_processes_one_port_one_runner_metrics_summed_jobs_run_once(
    env: dict[str, str], tmp_path: Path
) -> None:
    server = Server(env, tmp_path / "serve.log")
    try:
        server.wait_ready()
        key = _key(env)
        children = _children(server)
        assert sorted(children) == ["runner", "web-0", "web-1"]
        supervisor = server.process.pid
        assert all(int(Path(f"/proc/{pid}/stat").read_text().split()[3]) == supervisor
                   for pid in children.values())  # fmt: skip
        ready = httpx.get(f"{server.url}/readyz").json()
        assert ready["checks"]["workers"] and ready["workers_alive"] == 1

        # Both request processes answer on the one port; a scrape, whichever process answers
        # it, counts the requests of both; it still needs a key.
        assert httpx.get(f"{server.url}/metrics").status_code == 401
        scrape = f"{server.url}/metrics"
        before = _healthz_counted(httpx.get(scrape, headers={"X-API-Key": key}).text)
        sent = 0
        with ThreadPoolExecutor(8) as pool:
            for _ in range(10):
                codes = list(pool.map(lambda _: httpx.get(f"{server.url}/healthz"), range(40)))
                assert {response.status_code for response in codes} == {200}
                sent += len(codes)
                answered = {
                    line["process"]
                    for line in server.log_lines()
                    if line["msg"] == "GET /healthz 200"
                }
                if answered == {"web-0", "web-1"}:
                    break
        assert answered == {"web-0", "web-1"}
        for _ in range(3):  # several scrapes, likely answered by both processes
            after = _healthz_counted(httpx.get(scrape, headers={"X-API-Key": key}).text)
            assert after - before == sent

        # Several writers at once (both processes; SQLite in WAL mode with a busy timeout):
        # distinct recordings and one recording four times (one dataset, however it races).
        def upload(content: bytes) -> httpx.Response:
            return httpx.post(
                f"{server.url}/api/v1/datasets",
                headers={"X-API-Key": key},
                data={"robot": "ur10"},
                files={"file": ("recording.csv", content, "text/csv")},
                timeout=60,
            )

        same = recording_bytes(n=40, seed=3)
        contents = [recording_bytes(n=40, seed=seed) for seed in range(4, 10)] + [same] * 4
        with ThreadPoolExecutor(10) as pool:
            uploads = list(pool.map(upload, contents))
        assert all(response.status_code in (200, 201) for response in uploads), [
            response.text for response in uploads
        ]
        ids = [response.json()["id"] for response in uploads]
        assert len(set(ids[:6])) == 6 and len(set(ids[6:])) == 1 and ids[6] not in ids[:6]

        # Jobs accepted concurrently (by both processes) run exactly once each.
        api = KincalClient(server.url, api_key=key)
        csv = tmp_path / "small.csv"
        csv.write_bytes(recording_bytes(n=60))
        dataset = api.upload_dataset(csv, robot="ur10")
        with ThreadPoolExecutor(4) as pool:
            jobs = list(
                pool.map(lambda _: api.start_calibration(dataset["id"], QUICK)["id"], range(4))
            )
        for job_id in jobs:
            assert api.wait(job_id, timeout_s=120, poll_s=0.1)["state"] == "succeeded"
            assert _job(env, job_id).attempts == 1
        started = [line for line in server.log_lines() if line["msg"] == "job started"]
        assert sorted(line["job_id"] for line in started) == sorted(jobs)
        assert {line["process"] for line in started} == {"runner"}

        # Cancelling a running job through a request process stops it in the runner process.
        csv.write_bytes(recording_bytes(n=2000))
        big = api.upload_dataset(csv, robot="ur10")
        workers_before = len(server.worker_pids())
        long_job = _long_job_running(api, big["id"])
        asked = time.monotonic()
        assert api.cancel(long_job)["status"]["cancel_requested"]
        _until(lambda: api.status(long_job)["status"]["state"] in TERMINAL, 10, "the cancel")
        cancel_s = time.monotonic() - asked
        assert api.status(long_job)["status"]["state"] == "cancelled", cancel_s
        _until(lambda: len(server.worker_pids()) > workers_before, 30, "a new worker")
        _until(lambda: httpx.get(f"{server.url}/readyz").status_code == 200, 30, "readiness")
    finally:
        code = server.stop(signal.SIGTERM)
    assert code == 0, server.log_path.read_text()[-3000:]


def test_crashed_request_and_runner_processes_are_replaced_and_sigterm_drains(
    env: dict[str, str], tmp_path: Path
) -> None:
    server = Server(env, tmp_path / "serve.log")
    key = ""
    try:
        server.wait_ready()
        key = _key(env)
        children = _children(server)
        os.kill(children["web-0"], signal.SIGKILL)
        # The other process keeps answering meanwhile; web-0 comes back with a new pid.
        for _ in range(20):
            assert httpx.get(f"{server.url}/healthz").status_code == 200
        replaced = _until(
            lambda: (pid := _children(server)["web-0"]) != children["web-0"] and pid,
            60,
            "a new web-0",
        )
        assert not gone(replaced)
        server.wait_ready()
        assert "web-0 process (pid" in server.log_path.read_text()

        api = KincalClient(server.url, api_key=key)
        csv = tmp_path / "big.csv"
        csv.write_bytes(recording_bytes(n=2000))
        dataset = api.upload_dataset(csv, robot="ur10")
        running = _long_job_running(api, dataset["id"])
        # A crashed runner is replaced too; its workers die with it and its job runs again.
        runner, workers = _children(server)["runner"], server.worker_pids()
        os.kill(runner, signal.SIGKILL)
        _until(lambda: _children(server)["runner"] != runner, 30, "a new runner")
        _until(lambda: all(gone(pid) for pid in workers), 10, "the old workers to die")
        _until(
            lambda: (job := _job(env, running)).state == "running" and job.attempts == 2,
            60,
            "the job to run again",
        )
        queued = str(api.start_calibration(dataset["id"], QUICK)["id"])
        pids = [*_children(server).values(), *server.worker_pids()]
    finally:
        started = time.monotonic()
        code = server.stop(signal.SIGTERM)
    # Running jobs get KINCAL_SHUTDOWN_GRACE_S (1 s) and are handed back; nothing accepted is
    # lost; every process is gone, the run folder too.
    assert code == 0, server.log_path.read_text()[-3000:]
    assert time.monotonic() - started < 20
    assert all(gone(pid) for pid in pids)
    log = server.log_path.read_text()
    assert "job handed back to the queue at shutdown" in log
    assert log.rstrip().endswith('"msg": "kincal service stopped", "process": "supervisor"}')
    back = _job(env, running)
    assert back.state == "queued" and back.attempts == 1  # the crash counts, the shutdown not
    assert _job(env, queued).state == "queued"
    assert list((tmp_path / "data" / "run").iterdir()) == []
