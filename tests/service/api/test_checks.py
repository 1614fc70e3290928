"""Checks over HTTP (issue 33): the real FR3 recording calibrated through the service on all
but 10 rows, the 10 held-out rows uploaded and checked. The stored document is ``kincal
check``'s on the same files; checks are listed newest first and survive a restart; unknown
ids are 404, a calibration that cannot be checked 409, a dataset it cannot be checked with 422
naming ``dataset_id``; another tenant sees none of it."""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from fastapi.testclient import TestClient

from schemas.calibration import CalibrationResult
from schemas.check import CheckResult
from service.api import checks, create_app
from service.api.client import KincalClient
from service.settings import Settings
from service.storage import repository
from service.storage.files import tenant_path
from service.storage.models import Job
from tests.conftest import REAL_DATA
from tests.service.api.conftest import (
    assert_problem,
    client_api,
    database_of,
    fresh_database_url,
    make_settings,
    new_key,
    upload_csv,
)
from tests.service.cli_support import run_ok

FR3 = REAL_DATA / "philnad_fr3_eye_in_hand" / "fr3_poses.csv"
BAD_ROWS = (43, 112, 113)
"""sample_id of the FR3 rows 3.5–8 mm off (as in tests/service/test_check_cli.py)."""
URL = "/api/v1/calibrations"


def checks_url(calibration_id: str) -> str:
    return f"{URL}/{calibration_id}/checks"


@dataclass
class Checked:
    """The FR3 calibrated through the service and its held-out rows checked, on a database
    whose first app has stopped; ``settings`` start it again (no worker processes)."""

    folder: Path
    settings: Settings
    calibration_id: str
    dataset_id: str
    created: dict[str, Any]
    location: str
    check_csv: Path
    held: pd.DataFrame


def split(folder: Path) -> tuple[Path, Path, pd.DataFrame]:
    """10 held-out rows (not the bad ones) and the others, as CSV files."""
    data = pd.read_csv(FR3)
    rng = np.random.default_rng(0)
    clean = data[~data["sample_id"].isin(BAD_ROWS)]
    held = np.sort(rng.choice(clean.index.to_numpy(), 10, replace=False))
    train, check = folder / "train.csv", folder / "check.csv"
    data.drop(index=held).to_csv(train, index=False, float_format="%.17g")
    data.loc[held].to_csv(check, index=False, float_format="%.17g")
    return train, check, data.loc[held]


@dataclass
class Calibrated:
    """The FR3 (all but its 10 held-out rows) calibrated through a running service."""

    client: TestClient
    api: KincalClient
    calibration_id: str
    check_csv: Path
    held: pd.DataFrame


@contextlib.contextmanager
def calibrated_service(folder: Path, database_url: str) -> Iterator[Calibrated]:
    """A service with one worker on ``database_url`` and ``folder`` that has calibrated the FR3
    without its held-out rows (:func:`split`); stopped on exit."""
    train, check_csv, held = split(folder)
    with TestClient(
        create_app(make_settings(folder, database_url, workers=1)), raise_server_exceptions=False
    ) as client:
        api = client_api(client)
        calibration = api.start_calibration(api.upload_dataset(train, robot="panda")["id"])
        api.wait(calibration["id"], poll_s=0.05)
        yield Calibrated(client, api, calibration["id"], check_csv, held)


@pytest.fixture(scope="module")
def checked(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Checked]:
    folder = tmp_path_factory.mktemp("checks")
    with fresh_database_url(folder) as url:
        with calibrated_service(folder, url) as service:
            client, calibration_id = service.client, service.calibration_id
            (folder / "result.json").write_bytes(
                client.get(f"{URL}/{calibration_id}/result").content
            )
            dataset = service.api.upload_dataset(service.check_csv, robot="panda")
            created = client.post(checks_url(calibration_id), json={"dataset_id": dataset["id"]})
            assert created.status_code == 201, created.text
        yield Checked(
            folder,
            make_settings(folder, url, workers=0),
            calibration_id,
            dataset["id"],
            created.json(),
            created.headers["location"],
            service.check_csv,
            service.held,
        )


@pytest.fixture(scope="module")
def restarted(checked: Checked) -> Iterator[TestClient]:
    """The service started again on the same database and data folder."""
    with TestClient(create_app(checked.settings), raise_server_exceptions=False) as client:
        yield client


def comparable(document: dict[str, Any]) -> dict[str, Any]:
    """A check document without its time and the recording's name."""
    return {k: v for k, v in document.items() if k not in ("created_utc", "recording")}


def upload_rows(client: TestClient, rows: pd.DataFrame, name: str, **headers: str) -> str:
    data = rows.to_csv(index=False, float_format="%.17g").encode()
    response = upload_csv(
        client, data, filename=name, robot_name="panda", headers=dict(headers) or None
    )
    assert response.status_code in (200, 201), response.text
    return str(response.json()["id"])


def test_a_check_over_http_is_kincal_check_on_the_same_files(checked: Checked) -> None:
    created = checked.created
    assert created["id"].startswith("chk_")
    assert checked.location == created["links"]["self"]
    assert checked.location == f"{checks_url(checked.calibration_id)}/{created['id']}"
    out = checked.folder / "cli_check.json"
    run_ok(["check", checked.folder / "result.json", checked.check_csv, "-o", out])
    cli = CheckResult.model_validate_json(out.read_bytes()).model_dump(mode="json")
    document = created["check"]
    assert comparable(document) == comparable(cli)  # the same numbers: no maths of its own
    assert document["recording"] == "check.csv"  # the dataset's name, not a server path
    assert created["verdict"] == document["verdict"] == "holds"
    assert created["statistic"] == document["global_test"]["statistic"]
    assert created["threshold"] == document["global_test"]["threshold"]
    assert created["n_poses"] == 10 and created["level"] == 0.05
    assert created["dataset_id"] == checked.dataset_id and created["located"] is None


def test_checks_survive_a_restart(checked: Checked, restarted: TestClient) -> None:
    listed = restarted.get(checks_url(checked.calibration_id))
    assert listed.status_code == 200, listed.text
    page = listed.json()
    ours = [c for c in page["data"] if c["id"] == checked.created["id"]]
    assert len(ours) == 1
    summary = ours[0]
    assert "check" not in summary
    assert summary["created_at"] == checked.created["created_at"]
    for field in ("verdict", "statistic", "threshold", "n_poses", "dataset_name"):
        assert summary[field] == checked.created[field]
    one = restarted.get(checked.location)
    assert one.status_code == 200, one.text
    assert one.json() == checked.created


def test_a_drift_is_located_stored_and_listed_first(
    checked: Checked, restarted: TestClient
) -> None:
    rows = checked.held.copy()
    rows["q3"] += 0.002  # joint 3 reads 2 mrad off
    dataset_id = upload_rows(restarted, rows, "drifted.csv")
    api = client_api(restarted)
    drifted = api.check(checked.calibration_id, dataset_id, {"level": 0.05})
    assert drifted["verdict"] == "drifted"
    assert drifted["located"] == drifted["check"]["located"]["name"] == "panda_joint3 offset"
    assert drifted["statistic"] > drifted["threshold"]
    page = api.checks(checked.calibration_id)
    assert page["data"][0]["id"] == drifted["id"]  # newest first
    times = [c["created_at"] for c in page["data"]]
    assert times == sorted(times, reverse=True) and page["count"] == len(times) >= 2
    assert api.get_check(checked.calibration_id, drifted["id"]) == drifted


def test_the_latest_check_of_each_calibration_is_a_gauge(
    checked: Checked, restarted: TestClient
) -> None:
    api = client_api(restarted)
    latest = api.check(checked.calibration_id, checked.dataset_id)
    text = restarted.get("/metrics").text
    label = f'{{calibration_id="{checked.calibration_id}"}}'

    def value(name: str) -> float:
        found = re.search(rf"^{name}{re.escape(label)} (\S+)$", text, flags=re.MULTILINE)
        assert found, (name, text[:2000])
        return float(found.group(1))

    assert value("kincal_check_statistic") == pytest.approx(latest["statistic"], rel=1e-12)
    assert value("kincal_check_threshold") == pytest.approx(latest["threshold"], rel=1e-12)
    assert value("kincal_check_drifted") == 0.0
    assert text.count("kincal_check_drifted{") == 1  # one series per checked calibration


def test_a_repeated_idempotency_key_replays_the_check(
    checked: Checked, restarted: TestClient
) -> None:
    url = checks_url(checked.calibration_id)
    body = {"dataset_id": checked.dataset_id}
    headers = {"Idempotency-Key": "check-once"}
    first = restarted.post(url, json=body, headers=headers)
    before = restarted.get(url).json()["count"]
    again = restarted.post(url, json=body, headers=headers)
    assert first.status_code == again.status_code == 201
    assert again.headers["idempotent-replayed"] == "true"
    assert again.json()["id"] == first.json()["id"]
    assert restarted.get(url).json()["count"] == before


def test_unknown_calibration_dataset_or_check_is_404(
    checked: Checked, restarted: TestClient
) -> None:
    body = {"dataset_id": checked.dataset_id}
    assert_problem(restarted.post(checks_url("cal_nope"), json=body), 404, "cal_nope")
    assert_problem(restarted.get(checks_url("cal_nope")), 404, "cal_nope")
    assert_problem(restarted.get(f"{checks_url('cal_nope')}/chk_nope"), 404, "chk_nope")
    missing = restarted.post(checks_url(checked.calibration_id), json={"dataset_id": "ds_nope"})
    assert_problem(missing, 404, "dataset_id", "ds_nope", "POST /api/v1/datasets")
    unknown = restarted.get(f"{checks_url(checked.calibration_id)}/chk_nope")
    assert_problem(unknown, 404, "chk_nope", f"GET {checks_url(checked.calibration_id)}")


def test_a_calibration_not_succeeded_is_409(checked: Checked, restarted: TestClient) -> None:
    train = client_api(restarted).datasets()["data"][-1]["id"]
    queued = restarted.post(URL, json={"dataset_id": train}).json()  # no workers: stays queued
    response = restarted.post(checks_url(queued["id"]), json={"dataset_id": checked.dataset_id})
    assert_problem(response, 409, "queued", "poll its status")


def test_a_result_without_predictive_covariance_is_409(
    checked: Checked, restarted: TestClient
) -> None:
    """A calibration run with options.heldout false has no Cov(θ̂) nor model error."""
    state = restarted.app.state.kincal  # type: ignore[attr-defined]
    tenant_id = state.local_tenant.tenant_id
    result = CalibrationResult.model_validate_json((checked.folder / "result.json").read_bytes())
    job_id = repository.new_id("cal")
    path = state.files.write(
        tenant_path(tenant_id, "jobs", job_id, "result.json"),
        result.model_copy(update={"predictive": None}).model_dump_json().encode(),
    )
    with database_of(restarted).session() as session:
        session.add(
            Job(
                id=job_id,
                tenant_id=tenant_id,
                kind="calibration",
                params={"options": {}},
                state=repository.SUCCEEDED,
                fraction=1.0,
                attempts=1,
                cancel_requested=False,
                artifacts={"result": path},
            )
        )
    response = restarted.post(checks_url(job_id), json={"dataset_id": checked.dataset_id})
    body = assert_problem(response, 409, "predictive covariance", "options.heldout true")
    assert "kincal calibrate" not in body["detail"]  # the fix in the service's words


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ("ur10", "not a recording of the calibrated robot"),
        ("positions", "holds positions only"),
        ("other_frames", "not in the calibration's measurement frame"),
    ],
)
def test_a_dataset_it_cannot_be_checked_with_is_422_naming_dataset_id(
    checked: Checked, restarted: TestClient, change: str, fragment: str
) -> None:
    rows = checked.held.copy()
    if change == "ur10":
        response = upload_csv(restarted)  # a simulated UR10 recording
        assert response.status_code in (200, 201), response.text
        dataset_id = response.json()["id"]
    elif change == "positions":
        dataset_id = upload_rows(restarted, rows.drop(columns=["qx", "qy", "qz", "qw"]), "p.csv")
    else:
        rows["x"] += 0.5  # the camera 0.5 m elsewhere
        dataset_id = upload_rows(restarted, rows, "moved.csv")
    url = checks_url(checked.calibration_id)
    before = restarted.get(url).json()["count"]
    response = restarted.post(url, json={"dataset_id": dataset_id})
    body = assert_problem(response, 422, "dataset_id: ", fragment)
    assert body["errors"][0]["location"] == "body.dataset_id"
    assert str(checked.settings.data_dir) not in body["detail"]  # no server paths
    assert restarted.get(url).json()["count"] == before  # nothing stored


@pytest.mark.parametrize(
    ("body", "location"),
    [
        ({"dataset_id": "ds_x", "options": {"level": 1.5}}, "body.options.level"),
        ({"dataset_id": "ds_x", "options": {"level": 0}}, "body.options.level"),
        ({"dataset_id": "ds_x", "options": {"power": 0.9}}, "body.options.power"),
        ({}, "body.dataset_id"),
    ],
)
def test_invalid_options_are_422_naming_the_field(
    checked: Checked, restarted: TestClient, body: dict[str, Any], location: str
) -> None:
    response = restarted.post(checks_url(checked.calibration_id), json=body)
    problem = assert_problem(response, 422, location)
    assert problem["errors"][0]["location"] == location


def test_another_tenant_sees_no_check(checked: Checked, restarted: TestClient) -> None:
    key = new_key(restarted, "other-lab")
    theirs = {"X-API-Key": key}
    url = checks_url(checked.calibration_id)
    assert_problem(restarted.get(url, headers=theirs), 404)
    assert_problem(restarted.get(checked.location, headers=theirs), 404)
    own_dataset = upload_rows(restarted, checked.held, "theirs.csv", **theirs)
    posted = restarted.post(url, json={"dataset_id": own_dataset}, headers=theirs)
    assert_problem(posted, 404, checked.calibration_id)
    # ... nor can the calibration's tenant check with the other tenant's dataset
    assert_problem(restarted.post(url, json={"dataset_id": own_dataset}), 404, "dataset_id")


def test_a_dataset_of_more_poses_than_a_check_takes_is_422(
    checked: Checked, restarted: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(checks, "MAX_CHECK_POSES", 5)
    response = restarted.post(
        checks_url(checked.calibration_id), json={"dataset_id": checked.dataset_id}
    )
    body = assert_problem(response, 422, "dataset_id: ", "10 poses, more than the 5")
    assert body["errors"][0]["location"] == "body.dataset_id"


def test_a_dataset_whose_file_went_away_is_404_without_a_server_path(
    checked: Checked, restarted: TestClient
) -> None:
    """A dataset deleted between its lookup and its reading (here: its file only)."""
    dataset_id = upload_rows(restarted, checked.held.iloc[:5], "gone.csv")
    state = restarted.app.state.kincal  # type: ignore[attr-defined]
    with database_of(restarted).sessions() as session:
        row = repository.get_dataset(session, state.local_tenant.tenant_id, dataset_id)
        assert row is not None
    state.files.delete(row.data_path)
    response = restarted.post(checks_url(checked.calibration_id), json={"dataset_id": dataset_id})
    body = assert_problem(response, 404, f"dataset {dataset_id} was deleted")
    assert str(checked.settings.data_dir) not in body["detail"]
