"""Discovery jobs over HTTP: POST -> 202 + Location, progress, the findings JSON (the same as
``kincal discover``), an HTML report with one figure per finding; 4xx problems otherwise."""

from __future__ import annotations

import base64
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from schemas.discovery import DiscoveryOptions, FindingsResult
from service.api import create_app
from service.api.client import KincalClient
from service.app import discover as discovery
from service.jobs.worker import WORKER_NICENESS
from service.render.discovery_html import render_discovery_report
from tests.conftest import robot
from tests.service.api.conftest import (
    AppFactory,
    assert_problem,
    client_api,
    fresh_database_url,
    make_settings,
    new_key,
    recording,
    recording_bytes,
    upload_csv,
)

URL = "/api/v1/discoveries"
# 60 UR10 samples (seed 5) whose elastic elbow a rigid model lacks: discovery names it.
N_SAMPLES, SEED = 60, 5
OPTIONS = DiscoveryOptions(bootstrap=10)


def comparable(findings: FindingsResult) -> dict[str, Any]:
    """The findings without what legitimately differs between two identical runs."""
    document = findings.model_dump(mode="json")
    for volatile in ("created_utc", "elapsed_s"):
        document.pop(volatile)
    document["dataset"].pop("source")
    return document


class Discovered:
    def __init__(self, client: TestClient) -> None:
        self.client = client
        self.api = client_api(client)
        data = recording_bytes(".csv", N_SAMPLES, SEED)
        self.dataset = upload_csv(client, data).json()
        created = client.post(
            URL,
            json={
                "dataset_id": self.dataset["id"],
                "options": OPTIONS.model_dump(mode="json"),
            },
        )
        assert created.status_code == 202, created.text
        self.created = created
        self.id: str = created.json()["id"]
        self.seen: list[dict[str, Any]] = []
        self.api.wait_discovery(self.id, poll_s=0.02, on_progress=self.seen.append)


@pytest.fixture(scope="module")
def discovered(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Discovered]:
    folder = tmp_path_factory.mktemp("discoveries")
    with fresh_database_url(folder) as url:
        settings = make_settings(folder, url, workers=1)
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            yield Discovered(client)


def test_discovery_job_round_trip_equals_kincal_discover(
    discovered: Discovered, tmp_path_factory: pytest.TempPathFactory
) -> None:
    created = discovered.created.json()
    assert discovered.created.headers["location"] == f"{URL}/{discovered.id}"
    assert created["id"].startswith("dis_") and created["status"]["state"] == "queued"
    assert created["links"]["report"] == f"{URL}/{discovered.id}/report"

    running = [s for s in discovered.seen if s["state"] == "running"]
    assert {s["stage"] for s in running} & {"loading", "discover", "report"}
    fractions = [s["fraction"] for s in discovered.seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0

    findings = discovered.api.findings(discovered.id)
    plot_dir = tmp_path_factory.mktemp("direct_plots")
    direct = discovery.discover(
        recording(N_SAMPLES, SEED), robot("ur10"), OPTIONS, plot_dir, "finding"
    )
    assert comparable(findings) == comparable(direct)  # the service adds no maths of its own
    assert [(f.effect, f.joint) for f in findings.findings] == [("joint_compliance", "elbow_joint")]

    listed = discovered.client.get(URL).json()
    assert listed["count"] == 1 and listed["data"][0]["id"] == discovered.id
    assert discovered.api.discovery_status(discovered.id)["options"]["bootstrap"] == 10


def test_discovery_report_embeds_one_figure_per_finding(discovered: Discovered) -> None:
    findings = discovered.api.findings(discovered.id)
    response = discovered.client.get(f"{URL}/{discovered.id}/report")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    assert "default-src 'none'" in response.headers["content-security-policy"]
    report = response.text
    assert "<script" not in report
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', report)
    assert len(images) == len(findings.plots) == len(findings.findings) >= 1
    assert all(base64.b64decode(image).startswith(b"\x89PNG") for image in images)
    finding = findings.findings[0]
    assert finding.explanation in report
    assert f"{findings.heldout.after.trans_mm:.3f}" in report
    assert "compliant_joints" in report  # the calibrate options that carry the found model


def test_discovery_of_another_tenant_is_404(discovered: Discovered) -> None:
    key = new_key(discovered.client, "lab-b")
    other = KincalClient(api_key=key, client=discovered.client)
    for path in ("", "/result", "/report"):
        response = discovered.client.get(f"{URL}/{discovered.id}{path}", headers={"X-API-Key": key})
        assert_problem(response, 404, discovered.id)
    assert other.discoveries()["count"] == 0
    response = discovered.client.post(
        URL, json={"dataset_id": discovered.dataset["id"]}, headers={"X-API-Key": key}
    )
    assert_problem(response, 404, "dataset_id", discovered.dataset["id"])


def test_finished_discovery_cannot_be_cancelled(discovered: Discovered) -> None:
    response = discovered.client.post(f"{URL}/{discovered.id}/cancel")
    assert_problem(response, 409, "already succeeded")


# --- no worker: accepted jobs stay queued ------------------------------------------------------


def test_queued_discovery_has_no_result_yet_and_cancels_at_once(client: TestClient) -> None:
    dataset = upload_csv(client).json()
    created = client.post(URL, json={"dataset_id": dataset["id"]})
    location = created.headers["location"]
    assert_problem(client.get(f"{location}/result"), 409, "queued", "poll")
    assert_problem(client.get(f"{location}/report"), 409, "queued")
    cancelled = client.post(f"{location}/cancel")
    assert cancelled.status_code == 200 and cancelled.json()["status"]["state"] == "cancelled"
    assert_problem(client.get(f"{location}/result"), 409, "cancelled")


def test_idempotency_key_returns_the_same_discovery(client: TestClient) -> None:
    dataset = upload_csv(client).json()
    headers = {"Idempotency-Key": "discover-once"}
    body = {"dataset_id": dataset["id"], "options": {"max_terms": 2}}
    first = client.post(URL, json=body, headers=headers)
    again = client.post(URL, json=body, headers=headers)
    assert first.status_code == again.status_code == 202
    assert first.json()["id"] == again.json()["id"]
    assert client.get(URL).json()["count"] == 1
    changed = client.post(URL, json={**body, "options": {"max_terms": 3}}, headers=headers)
    assert changed.status_code == 422


NAN_OPTIONS = b'{"dataset_id": "%s", "options": {"gravity_base_m_s2": [0, 0, NaN]}}'


@pytest.mark.parametrize(
    ("options", "fragments"),
    [
        ({"compliant_joints": ["knee"]}, ["options", "knee"]),
        ({"virtual_axes_at": ["knee"]}, ["options", "knee"]),
        ({"effects": ["magic"]}, ["body.options.effects.0"]),
        ({"alpha": 0.7}, ["body.options.alpha"]),
        ({"folds": 1}, ["body.options.folds"]),
        ({"bootstrap": 5000}, ["body.options.bootstrap"]),
        ({"surprise": True}, ["body.options.surprise"]),
    ],
)
def test_bad_discovery_options_are_422_naming_the_field(
    client: TestClient, options: dict[str, Any], fragments: list[str]
) -> None:
    dataset = upload_csv(client).json()
    response = client.post(URL, json={"dataset_id": dataset["id"], "options": options})
    assert_problem(response, 422, *fragments)
    assert client.get(URL).json()["count"] == 0  # nothing was queued


def test_non_finite_options_are_refused_before_a_job_exists(make_client: AppFactory) -> None:
    client = make_client()
    dataset = upload_csv(client).json()
    for path in (URL, "/api/v1/calibrations"):
        response = client.post(
            path,
            content=NAN_OPTIONS % dataset["id"].encode(),
            headers={"content-type": "application/json"},
        )
        assert_problem(response, 422, "options.gravity_base_m_s2.2", "finite")
    infinite = NAN_OPTIONS.replace(b"NaN", b"Infinity").replace(
        b'"gravity_base_m_s2": [0, 0, Infinity]', b'"payload_kg": Infinity'
    )
    response = client.post(
        URL, content=infinite % dataset["id"].encode(), headers={"content-type": "application/json"}
    )
    assert_problem(response, 422, "options.payload_kg is inf")
    assert client.get(URL).json()["count"] == 0
    assert client.get("/api/v1/calibrations").json()["count"] == 0


def test_unknown_dataset_or_discovery_is_404(client: TestClient) -> None:
    assert_problem(client.post(URL, json={"dataset_id": "ds_nope"}), 404, "dataset_id", "ds_nope")
    for path in ("", "/result", "/report"):
        assert_problem(client.get(f"{URL}/dis_nope{path}"), 404, "dis_nope")
    assert_problem(client.post(f"{URL}/dis_nope/cancel"), 404, "dis_nope")
    # a calibration id is not a discovery
    dataset = upload_csv(client).json()
    calibration = client.post("/api/v1/calibrations", json={"dataset_id": dataset["id"]}).json()
    assert_problem(client.get(f"{URL}/{calibration['id']}"), 404, calibration["id"])


def test_jobs_run_at_a_lower_priority_than_the_request_loop(discovered: Discovered) -> None:
    """A calibration or discovery must not take the CPU from rankings: workers are niced."""
    runner = discovered.client.app.state.kincal.runner  # type: ignore[attr-defined]
    pids = [slot.process.pid for slot in runner._slots if slot.alive()]
    assert pids

    def niceness(pid: int | str) -> int:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[16])  # field 19 of proc(5), counted after the command name

    expected = min(niceness("self") + WORKER_NICENESS, 19)
    assert all(niceness(pid) == expected for pid in pids)


def test_report_names_what_only_kincal_calibrate_model_carries(discovered: Discovered) -> None:
    findings = discovered.api.findings(discovered.id)
    assert "Undone on the recording" not in discovered.api.discovery_report(discovered.id)
    model = findings.model.model_copy(update={"corrections": ["gear_periodic (h2) on <j3>"]})
    html = render_discovery_report(findings.model_copy(update={"model": model}), {})
    assert "kincal calibrate --model findings.json" in html
    assert "gear_periodic (h2) on &lt;j3&gt;" in html  # escaped
