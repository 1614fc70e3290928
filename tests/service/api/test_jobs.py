"""Calibration jobs in real worker processes: round trip, progress, cancel, crash and restart."""

from __future__ import annotations

import io
import time
from collections.abc import Callable, Iterator
from typing import Any

import pandas as pd
import pinocchio as pin
import pytest
from fastapi.testclient import TestClient

from schemas.calibration import CalibrationOptions, CalibrationResult
from service.api import calibrations, create_app
from service.api.jobs_common import submit_job
from service.api.problems import ProblemException
from service.app import calibrate as pipeline
from service.jobs.runner import JobRegistry
from service.render.urdf_export import MARKER_LINK
from service.storage import repository
from service.storage.models import Job
from tests.conftest import comparable_result, robot
from tests.service.api.conftest import (
    assert_problem,
    client_api,
    database_of,
    fresh_database_url,
    make_settings,
    recording,
    recording_bytes,
    upload_csv,
)

# Many held-out splits make a job that runs for several seconds (each split is two fits).
LONG_OPTIONS = {"seeds": list(range(1, 101))}


@pytest.fixture(scope="module")
def worker_client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """One app with one real worker process, shared by the tests of this module."""
    folder = tmp_path_factory.mktemp("jobs")
    with fresh_database_url(folder) as url:
        settings = make_settings(folder, url, workers=1)
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            yield client


def _job(client: TestClient, job_id: str) -> Job:
    with database_of(client).sessions() as session:
        job = session.get(Job, job_id)
    assert job is not None
    return job


def wait_for(
    client: TestClient,
    location: str,
    predicate: Callable[[dict[str, Any]], bool],
    timeout_s: float = 60,
) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        status: dict[str, Any] = client.get(location).json()["status"]
        if predicate(status):
            return status
        assert time.monotonic() < deadline, f"timed out; last status {status}"
        time.sleep(0.05)


def test_upload_calibrate_poll_result_report_urdf_round_trip(
    worker_client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    api = client_api(worker_client)
    upload = upload_csv(worker_client).json()
    calibration = api.start_calibration(upload["id"], CalibrationOptions())
    assert calibration["status"]["state"] == "queued"
    seen: list[dict[str, Any]] = []
    api.wait(calibration["id"], poll_s=0.02, on_progress=seen.append)

    running = [s for s in seen if s["state"] == "running"]
    assert running, seen
    assert {s["stage"] for s in running} & {"fit", "baseline", "heldout", "report"}
    fractions = [s["fraction"] for s in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    final = api.status(calibration["id"])["status"]
    assert final["state"] == "succeeded" and final["attempts"] == 1
    assert final["started_at"] <= final["finished_at"]

    result = api.result(calibration["id"])
    direct = pipeline.calibrate(recording(), robot("ur10"), CalibrationOptions())
    # the service adds no maths of its own
    assert comparable_result(result) == comparable_result(direct)

    report = api.report(calibration["id"])
    assert report.count("data:image/png;base64,") >= 1
    assert "Residuals before and after calibration" in report and "Identifiability" in report
    assert f"{result.fit.after.train.translation_mean_mm:.3f}" in report
    response = worker_client.get(f"/api/v1/calibrations/{calibration['id']}/report")
    assert "default-src 'none'" in response.headers["content-security-policy"]

    urdf = api.urdf(calibration["id"])
    model = pin.buildModelFromXML(urdf)
    assert not model.existFrame(MARKER_LINK)  # the robot's own root and tip (issue 15)
    exported = worker_client.get(
        f"/api/v1/calibrations/{calibration['id']}/export",
        params={"format": "urdf", "measurement_frame": True, "force": True},
    )
    assert exported.status_code == 200, exported.text
    assert pin.buildModelFromXML(exported.text).existFrame(MARKER_LINK)
    pal = worker_client.get(
        f"/api/v1/calibrations/{calibration['id']}/export",
        params={"format": "pal-master", "force": True},
    )
    assert pal.status_code == 200 and "geometric_calibration" in pal.text
    ur = worker_client.get(
        f"/api/v1/calibrations/{calibration['id']}/export",
        params={"format": "ur-kinematics", "force": True},
    )
    assert ur.status_code == 200 and ur.text.count("\n  wrist_") == 3, ur.text
    bad = worker_client.get(
        f"/api/v1/calibrations/{calibration['id']}/export", params={"format": "sdf"}
    )
    assert bad.status_code == 422
    assert bad.headers["content-type"].startswith("application/problem+json")

    metrics = worker_client.get("/metrics").text
    succeeded = 'kincal_jobs{kind="calibration",state="succeeded"}'
    line = next(row for row in metrics.splitlines() if row.startswith(succeeded))
    assert float(line.split()[-1]) >= 1
    assert 'kincal_job_duration_seconds_count{kind="calibration",state="succeeded"}' in metrics
    assert "kincal_workers_alive 1.0" in metrics
    _check_result_cache(worker_client, calibration["id"], monkeypatch)


def _check_result_cache(
    client: TestClient, calibration_id: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Results are cached per tenant; a hit needs no database; derived objects built once."""
    state = client.app.state.kincal  # type: ignore[attr-defined]
    tenant = state.local_tenant.tenant_id
    first = calibrations.cached_calibration(state, tenant, calibration_id)
    assert first.result.robot.name == "ur10"

    def no_database(*args: object) -> None:
        raise AssertionError("a cache hit must not query the database")

    with monkeypatch.context() as patch:
        patch.setattr(state.database, "sessions", no_database)
        assert calibrations.cached_calibration(state, tenant, calibration_id) is first
    builds: list[str] = []

    def build(result: CalibrationResult) -> int:
        builds.append("built")
        return len(result.links)

    assert [first.memo("n_links", build) for _ in range(3)] == [len(first.result.links)] * 3
    assert builds == ["built"]
    with pytest.raises(ProblemException) as other:
        calibrations.cached_calibration(state, "another-tenant", calibration_id)
    assert other.value.status == 404


def test_cancelling_a_running_job_stops_it_and_the_worker_is_replaced(
    worker_client: TestClient,
) -> None:
    dataset = upload_csv(worker_client).json()
    created = worker_client.post(
        "/api/v1/calibrations", json={"dataset_id": dataset["id"], "options": LONG_OPTIONS}
    )
    location = created.headers["location"]
    wait_for(worker_client, location, lambda s: s["stage"] == "heldout")
    cancelled = worker_client.post(f"{location}/cancel")
    assert cancelled.status_code in (200, 202)
    assert cancelled.json()["status"]["cancel_requested"]
    final = wait_for(worker_client, location, lambda s: s["state"] != "running", timeout_s=10)
    assert final["state"] == "cancelled"
    assert_problem(worker_client.post(f"{location}/cancel"), 409, "already cancelled")
    assert_problem(worker_client.get(f"{location}/result"), 409, "cancelled")

    quick = worker_client.post(
        "/api/v1/calibrations", json={"dataset_id": dataset["id"], "options": {"heldout": False}}
    )
    done = wait_for(
        worker_client,
        quick.headers["location"],
        lambda s: s["state"] != "queued" and s["state"] != "running",
    )
    assert done["state"] == "succeeded"
    assert worker_client.get("/readyz").json()["checks"]["workers"]


def test_cancelling_a_queued_job_is_immediate(client: TestClient) -> None:
    dataset = upload_csv(client).json()
    created = client.post("/api/v1/calibrations", json={"dataset_id": dataset["id"]})
    cancelled = client.post(f"{created.headers['location']}/cancel")
    assert cancelled.status_code == 200
    assert cancelled.json()["status"]["state"] == "cancelled"


def test_failed_job_reports_the_domain_error(worker_client: TestClient) -> None:
    # Fewer samples than identifiable parameters: accepted as a dataset, refused by the solver.
    frame = pd.read_csv(io.BytesIO(recording_bytes())).head(5)
    small = upload_csv(worker_client, frame.to_csv(index=False).encode()).json()
    assert small["n_samples"] == 5
    created = worker_client.post(
        "/api/v1/calibrations", json={"dataset_id": small["id"], "options": {"heldout": False}}
    )
    final = wait_for(worker_client, created.headers["location"], lambda s: s["state"] == "failed")
    assert "fewer samples than identifiable parameters" in final["error"]
    assert_problem(worker_client.get(f"{created.headers['location']}/result"), 409, "failed")


def test_job_left_running_by_a_crashed_instance_is_resumed_at_start_up(
    make_app: Callable[..., TestClient],
) -> None:
    with make_app(workers=0) as first:
        dataset = upload_csv(first).json()
        created = first.post(
            "/api/v1/calibrations",
            json={"dataset_id": dataset["id"], "options": {"heldout": False}},
        ).json()
        # The crash: this instance had claimed the job, then died without a trace.
        with database_of(first).session() as session:
            claimed = repository.claim_next_job(session, "test-instance", ["calibration"])
        assert claimed is not None and claimed.id == created["id"]
    assert _job(first, created["id"]).state == "running"

    with make_app(workers=1) as second:
        final = wait_for(
            second, f"/api/v1/calibrations/{created['id']}", lambda s: s["state"] == "succeeded"
        )
        assert final["attempts"] == 2
        assert second.get(f"/api/v1/calibrations/{created['id']}/result").status_code == 200


def test_dead_worker_requeues_its_job_and_gives_up_after_max_attempts(
    make_app: Callable[..., TestClient],
) -> None:
    registry = JobRegistry()  # only the crashing kind: its worker starts in a fraction of a second
    registry.register("crash", "tests.service.api.jobs_for_tests:crash", id_prefix="crash")
    with make_app(registry=registry, workers=1, job_max_attempts=2) as client:
        state = client.app.state.kincal  # type: ignore[attr-defined]
        tenant = state.local_tenant.tenant_id
        job = submit_job(state, tenant, "crash", {})
        deadline = time.monotonic() + 60
        while _job(client, job.id).state not in ("failed", "succeeded"):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        final = _job(client, job.id)
        assert final.state == "failed"
        assert "gave up after 2 attempts" in (final.error or "")
        assert client.get("/readyz").status_code == 200


def test_shutdown_hands_a_running_job_back_to_the_queue(
    make_app: Callable[..., TestClient],
) -> None:
    with make_app(workers=1, shutdown_grace_s=0.0) as client:
        dataset = upload_csv(client).json()
        created = client.post(
            "/api/v1/calibrations", json={"dataset_id": dataset["id"], "options": LONG_OPTIONS}
        )
        location = created.headers["location"]
        wait_for(client, location, lambda s: s["state"] == "running")
    job = _job(client, created.json()["id"])
    assert job.state == "queued" and job.attempts == 0 and job.runner_id is None


def test_an_accepted_calibration_is_still_queued_after_a_restart(
    make_app: Callable[..., TestClient],
) -> None:
    with make_app(workers=0) as first:
        dataset = upload_csv(first).json()
        created = first.post("/api/v1/calibrations", json={"dataset_id": dataset["id"]}).json()
    with make_app(workers=0) as second:
        status = second.get(f"/api/v1/calibrations/{created['id']}").json()["status"]
        assert status["state"] == "queued" and status["attempts"] == 0
