"""``POST /api/v1/calibrations`` with a ``discovery_id``: the HTTP form of ``kincal calibrate
--model findings.json``. A Jaco2 recording with a concealed 2nd-harmonic gear error on joint 3
is discovered over HTTP; the calibration carrying that discovery records the same
``model_corrections`` as the CLI, rankings score the corrected configurations, and the URDF is
refused with a reason. Unknown, foreign, unfinished or unfitting discoveries are problems naming
``discovery_id`` before any job exists."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from schemas.calibration import CalibrationResult
from schemas.discovery import DiscoveryOptions
from schemas.ranking import RankingOptions
from service.api import create_app
from service.app import rank as ranking
from service.render import result_json
from solver.model import sample_configurations
from tests.conftest import assert_documents_close, comparable_result
from tests.service.api.conftest import (
    AppFactory,
    assert_problem,
    client_api,
    fresh_database_url,
    make_settings,
    new_key,
    recording_bytes,
    upload_csv,
)
from tests.service.cli_support import run_ok

URL = "/api/v1/calibrations"
EFFECTS = ("geometry", "camera", "marker", "gear_error")
N_SAMPLES, SEED = 150, 5
# The same calibration on both sides: no outlier rule, no held-out splits (seconds, not tens).
OPTIONS: dict[str, Any] = {"outlier_sigma": None, "heldout": False}
CLI_OPTIONS = ["--outlier-sigma", "0", "--no-heldout"]


class Carried:
    """gear.csv with its CLI findings and ``calibrate --model`` result, and the same over HTTP:
    a discovery job, then a calibration job naming it."""

    def __init__(self, client: TestClient, folder: Path, cli: CalibrationResult) -> None:
        self.client, self.folder, self.cli = client, folder, cli
        self.api = client_api(client)
        self.dataset = self.api.upload_dataset(folder / "gear.csv", robot="kinova")
        discovery = self.api.start_discovery(
            self.dataset["id"],
            DiscoveryOptions(bootstrap=10, detectability=False),
            idempotency_key="discover-gear",
        )
        self.discovery_id: str = discovery["id"]
        self.api.wait_discovery(self.discovery_id, poll_s=0.05)
        self.created = self.api.start_calibration(
            self.dataset["id"],
            OPTIONS,
            discovery_id=self.discovery_id,
            idempotency_key="calibrate-gear",
        )
        self.id: str = self.created["id"]
        self.api.wait(self.id, poll_s=0.05)
        self.result = self.api.result(self.id)


@pytest.fixture(scope="module")
def carried(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Carried]:
    folder = tmp_path_factory.mktemp("carried")
    data, findings, model = folder / "gear.csv", folder / "findings.json", folder / "model.json"
    size = ["--n", str(N_SAMPLES), "--seed", str(SEED)]
    effects = [f"--effect={e}" for e in EFFECTS]
    run_ok(["simulate", "--robot", "kinova", *size, *effects, "-o", data])
    # the carried model does not depend on the detectable sizes (a report): both sides skip them
    discover = ["discover", data, "--robot", "kinova", "--bootstrap", "10", "--no-detectability"]
    run_ok([*discover, "-o", findings])
    run_ok(["calibrate", data, "--robot", "kinova", "--model", findings, *CLI_OPTIONS, "-o", model])
    cli_result = CalibrationResult.model_validate_json(model.read_bytes())
    with fresh_database_url(folder) as url:
        settings = make_settings(folder, url, workers=1)
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            yield Carried(client, folder, cli_result)


def test_calibration_with_a_discovery_equals_calibrate_model(carried: Carried) -> None:
    assert carried.created["discovery_id"] == carried.discovery_id
    assert carried.api.status(carried.id)["discovery_id"] == carried.discovery_id
    record = carried.result.model_corrections
    assert record is not None and carried.cli.model_corrections is not None
    (entry,) = record.corrections
    third = carried.result.robot.joint_names[2]
    assert (entry.effect, entry.joint, entry.variant) == ("gear_periodic", third, "h2")
    assert entry.applied_in_prediction
    cli_record = carried.cli.model_corrections.model_dump(mode="json")
    assert_documents_close(record.model_dump(mode="json"), cli_record)
    # the rest of the result too: the service adds no maths of its own
    assert_documents_close(comparable_result(carried.result), comparable_result(carried.cli))
    assert carried.result.options.compliant_joints == carried.cli.options.compliant_joints


def test_rankings_score_the_corrected_configurations(carried: Carried) -> None:
    chain, _ = result_json.result_chain(carried.cli)
    q = sample_configurations(chain, 12, np.random.default_rng(11))
    served = carried.api.rank(carried.id, q.tolist())
    direct = ranking.rank_configurations(carried.cli, q, RankingOptions())
    assert [e.index for e in served.ranking] == [e.index for e in direct.ranking]
    np.testing.assert_allclose(
        [e.score for e in served.ranking], [e.score for e in direct.ranking], rtol=1e-9
    )
    plain = carried.cli.model_copy(update={"model_corrections": None})
    ignored = ranking.rank_configurations(plain, q, RankingOptions())
    by_index = {e.index: e.score for e in ignored.ranking}
    scores = np.array([e.score for e in served.ranking])
    ignoring = [by_index[e.index] for e in served.ranking]
    assert not np.allclose(scores, ignoring, rtol=1e-9, atol=0)  # the corrections count


def test_urdf_of_a_calibration_with_joint_corrections_is_409_saying_why(
    carried: Carried,
) -> None:
    response = carried.client.get(f"{URL}/{carried.id}/urdf")
    body = assert_problem(response, 409, carried.id, "gear_periodic (h2)", "URDF cannot express")
    assert "discovery_id" in body["detail"] and "rankings" in body["detail"]
    assert carried.client.get(f"{URL}/{carried.id}/report").status_code == 200


def test_idempotency_key_compares_the_discovery_id(carried: Carried) -> None:
    again = carried.api.start_calibration(
        carried.dataset["id"],
        OPTIONS,
        discovery_id=carried.discovery_id,
        idempotency_key="calibrate-gear",
    )
    assert again["id"] == carried.id
    response = carried.client.post(
        URL,
        json={"dataset_id": carried.dataset["id"], "options": OPTIONS},
        headers={"Idempotency-Key": "calibrate-gear"},
    )
    assert_problem(response, 422, "calibrate-gear", "different request")


def test_unknown_or_foreign_discovery_is_404(carried: Carried) -> None:
    body = {"dataset_id": carried.dataset["id"], "discovery_id": "dis_unknown"}
    assert_problem(carried.client.post(URL, json=body), 404, "discovery_id", "dis_unknown")
    key = new_key(carried.client, "lab-b")
    headers = {"X-API-Key": key}
    gear = (carried.folder / "gear.csv").read_bytes()
    own = upload_csv(carried.client, gear, robot_name="kinova", headers=headers)
    assert own.status_code == 201, own.text
    body = {"dataset_id": own.json()["id"], "discovery_id": carried.discovery_id}
    response = carried.client.post(URL, json=body, headers=headers)
    assert_problem(response, 404, "discovery_id", carried.discovery_id)
    assert carried.client.get(URL, headers=headers).json()["count"] == 0


def test_discovery_of_another_robot_is_422(carried: Carried) -> None:
    ur10 = upload_csv(carried.client, recording_bytes()).json()
    body = {"dataset_id": ur10["id"], "discovery_id": carried.discovery_id}
    response = carried.client.post(URL, json=body)
    assert_problem(response, 422, "discovery_id", carried.discovery_id, "robot ur10")


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"compliant_joints": []}, "options.compliant_joints"),
        ({"payload_kg": 0.5}, "options.payload_kg"),
        ({"gravity_base_m_s2": [0, 0, -9.8]}, "options.gravity_base_m_s2"),
    ],
)
def test_options_the_discovery_sets_are_422(
    carried: Carried, options: dict[str, Any], field: str
) -> None:
    body = {"dataset_id": carried.dataset["id"], "discovery_id": carried.discovery_id}
    response = carried.client.post(URL, json={**body, "options": options})
    assert_problem(response, 422, field, "discovery_id sets the model")


def test_a_service_on_dask_accepts_a_discovery_with_corrections(carried: Carried) -> None:
    """The corrected recording travels with the passes, wherever they run: a service whose
    calibrations run on Dask accepts a discovery that undoes the gear error (issue 17; it
    used to refuse it)."""
    state = carried.client.app.state.kincal  # type: ignore[attr-defined]
    settings = make_settings(
        carried.folder, state.settings.database_url, dask_address="tcp://127.0.0.1:9"
    )
    with TestClient(create_app(settings)) as streamed:  # workers: 0
        body = {"dataset_id": carried.dataset["id"], "discovery_id": carried.discovery_id}
        response = streamed.post(URL, json=body)
    assert response.status_code == 202, response.text
    assert response.json()["discovery_id"] == carried.discovery_id


def test_unfinished_discovery_is_409_saying_to_wait(make_client: AppFactory) -> None:
    client = make_client()  # no workers: the discovery stays queued
    dataset = upload_csv(client).json()
    discovery = client.post("/api/v1/discoveries", json={"dataset_id": dataset["id"]}).json()
    body = {"dataset_id": dataset["id"], "discovery_id": discovery["id"]}
    response = client.post(URL, json=body)
    assert_problem(response, 409, "discovery_id", discovery["id"], "queued", "wait")
    assert response.headers["retry-after"] == "1"
    assert client.get(URL).json()["count"] == 0  # nothing was queued
