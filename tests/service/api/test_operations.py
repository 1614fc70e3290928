"""Operations: liveness, readiness, Prometheus metrics, request ids, structured logs."""

from __future__ import annotations

import json
import logging
import subprocess
import sys

import pytest
from alembic import command
from fastapi.testclient import TestClient

from service.jobs import logs
from service.storage.db import alembic_config
from tests.service.api.conftest import database_of, upload_csv


def test_liveness_and_readiness(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["checks"] == {
        "database": True,
        "migrations": True,
        "workers": True,
        "storage": True,
    }


def test_not_ready_when_migrations_are_missing(client: TestClient) -> None:
    database = database_of(client)
    config = alembic_config(database.url)
    with database.engine.begin() as connection:
        config.attributes["connection"] = connection
        command.downgrade(config, "base")
    response = client.get("/readyz")
    assert response.status_code == 503
    assert response.json()["checks"]["migrations"] is False
    assert response.json()["status"] == "not ready"


def test_metrics_count_requests_by_route_template_and_status(client: TestClient) -> None:
    for _ in range(3):
        client.get("/api/v1/datasets/ds_nope")
    upload_csv(client)
    text = client.get("/metrics").text
    assert (
        'kincal_http_requests_total{method="GET",route="/api/v1/datasets/{dataset_id}",'
        'status="404"} 3.0' in text
    )
    assert 'route="/api/v1/datasets",status="201"} 1.0' in text
    assert 'kincal_http_request_duration_seconds_bucket{le="0.02",method="POST"' in text
    assert 'kincal_jobs{kind="calibration",state="queued"} 0.0' in text
    assert "ds_nope" not in text  # raw paths never become labels


def test_request_id_is_echoed_and_logged(
    client: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.INFO, logger="kincal.http"):
        response = client.get("/api/v1/datasets", headers={"X-Request-ID": "trace-42"})
    assert response.headers["x-request-id"] == "trace-42"
    generated = client.get("/healthz").headers["x-request-id"]
    assert len(generated) == 32
    assert (
        client.get("/healthz", headers={"X-Request-ID": "bad id!"}).headers["x-request-id"]
        != "bad id!"
    )
    access = [r for r in caplog.records if r.getMessage() == "GET /api/v1/datasets 200"]
    assert [getattr(r, "request_id", None) for r in access] == ["trace-42"]


def test_json_log_lines_carry_request_and_job_ids() -> None:
    formatter = logs.JsonFormatter()
    record = logging.makeLogRecord(
        {"name": "kincal.jobs", "levelname": "INFO", "msg": "job %s", "args": ("started",)}
    )
    record.kind = "calibration"
    request_token = logs.request_id.set("req-1")
    job_token = logs.job_id.set("cal_1")
    try:
        line = json.loads(formatter.format(record))
    finally:
        logs.request_id.reset(request_token)
        logs.job_id.reset(job_token)
    assert line["msg"] == "job started" and line["level"] == "info"
    assert line["request_id"] == "req-1" and line["job_id"] == "cal_1"
    assert line["kind"] == "calibration" and line["ts"].endswith("+00:00")


def test_every_line_python_writes_to_stderr_is_json_in_a_json_log() -> None:
    """Warnings (e.g. numpy's on extreme input) and uncaught exceptions in threads were plain
    text lines in the JSON log."""
    script = (
        "import threading, warnings\n"
        "from service.jobs.logs import configure_logging\n"
        "configure_logging('INFO', 'json')\n"
        "warnings.warn('something odd', RuntimeWarning)\n"
        "thread = threading.Thread(target=lambda: 1 / 0, name='t1')\n"
        "thread.start(); thread.join()\n"
        "raise ValueError('boom')\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 1
    lines = done.stderr.splitlines()
    entries = [json.loads(line) for line in lines]  # fails on any non-JSON line
    messages = " ".join(e["msg"] + e.get("exc", "") for e in entries)
    for fragment in ("something odd", "ZeroDivisionError", "thread t1", "ValueError: boom"):
        assert fragment in messages
