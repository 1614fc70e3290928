"""``kincal serve`` as a real process on 127.0.0.1: kill -9 during a job, restart, same result.

(Named to sort first: it is the longest test, so xdist should start it early.)"""

from __future__ import annotations

import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas.calibration import CalibrationOptions
from service.api.client import KincalClient
from service.app import calibrate as pipeline
from service.storage.db import Database
from service.storage.models import Job
from tests.conftest import comparable_result, robot
from tests.service.api.conftest import (
    fresh_database_url,
    recording,
    recording_bytes,
)
from tests.service.api.live import Server, descendants, gone, port_free, server_environment

# A job long enough (several seconds, most of it in the held-out stage) that the test sees it
# running on any machine, however fast: 1200 samples, 6 held-out splits (each also estimating
# the covariances of its predictive coverage, 4 times, since issue 13).
N_SAMPLES = 1200
OPTIONS = CalibrationOptions(seeds=list(range(1, 7)))


@pytest.fixture
def env(tmp_path: Path) -> Iterator[dict[str, str]]:
    with fresh_database_url(tmp_path) as url:
        yield server_environment(tmp_path, url, "kill9-test")


def test_kill_9_during_a_job_then_restart_completes_it_with_the_same_result(
    env: dict[str, str], tmp_path: Path
) -> None:
    first = Server(env, tmp_path / "first.log")
    try:
        first.wait_live()
        api = KincalClient(first.url)
        csv = tmp_path / "recording.csv"
        csv.write_bytes(recording_bytes(n=N_SAMPLES))
        dataset = api.upload_dataset(csv, robot="ur10")
        calibration = api.start_calibration(dataset["id"], OPTIONS)
        deadline = time.monotonic() + 60
        while True:
            status = api.status(calibration["id"])["status"]
            if status["stage"] == "heldout" and (status["iteration"] or 0) >= 2:
                break
            assert status["state"] in ("queued", "running") and time.monotonic() < deadline
            time.sleep(0.02)
        workers = first.worker_pids()
        # request processes, the runner, its fork server and workers
        everyone = descendants(first.process.pid)
    finally:
        first.stop(signal.SIGKILL)
    assert workers and all(pid != first.process.pid for pid in workers)
    assert len(everyone) >= 5 and set(workers) <= set(everyone)
    deadline = time.monotonic() + 10
    while not all(gone(pid) for pid in everyone):  # children die with the supervisor
        assert time.monotonic() < deadline, "a process outlived the killed service"
        time.sleep(0.1)
    assert port_free(first.port)

    database = Database(env["KINCAL_DATABASE_URL"])
    with database.sessions() as session:
        job = session.get(Job, calibration["id"])
        assert job is not None and job.state == "running" and job.attempts == 1
    time.sleep(1.5)  # 3 heartbeat intervals: nobody relays the job's progress any more
    with database.sessions() as session:
        again = session.get(Job, calibration["id"])
        assert again is not None and again.heartbeat_at == job.heartbeat_at
    database.dispose()

    second = Server(env, tmp_path / "second.log")
    try:
        second.wait_live()
        undisturbed = pipeline.calibrate(recording(N_SAMPLES), robot("ur10"), OPTIONS)
        api = KincalClient(second.url)
        final = api.wait(calibration["id"], timeout_s=120)
        assert final["attempts"] == 2
        assert comparable_result(api.result(calibration["id"])) == comparable_result(undisturbed)
        assert "re-queued 1 job(s)" in second.log_path.read_text()
    finally:
        # uvicorn re-raises the signal after a graceful shutdown, so the exit status shows it.
        assert second.stop(signal.SIGTERM) in (0, -signal.SIGTERM)
    assert "kincal service stopped" in second.log_path.read_text()
