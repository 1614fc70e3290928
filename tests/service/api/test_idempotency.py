"""Idempotency-Key: a retried POST has one effect; a reused key with another body is refused."""

from __future__ import annotations

import httpx
from fastapi.testclient import TestClient

from tests.service.api.conftest import assert_problem, recording_bytes, upload_csv


def _calibrate(client: TestClient, body: dict[str, object], key: str) -> httpx.Response:
    return client.post("/api/v1/calibrations", json=body, headers={"Idempotency-Key": key})


def test_same_key_and_body_replay_the_first_answer(client: TestClient) -> None:
    dataset = upload_csv(client).json()
    body = {"dataset_id": dataset["id"], "options": {"heldout": False}}
    first = _calibrate(client, body, "key-1")
    second = _calibrate(client, body, "key-1")
    assert first.status_code == second.status_code == 202
    assert second.json() == first.json()
    assert second.headers["location"] == first.headers["location"]
    assert second.headers["idempotent-replayed"] == "true"
    assert client.get("/api/v1/calibrations").json()["count"] == 1
    # Same options spelled differently (defaults written out) are the same request.
    explicit = {"dataset_id": dataset["id"], "options": {"heldout": False, "max_iterations": 50}}
    assert _calibrate(client, explicit, "key-1").json() == first.json()
    # Without a key every POST is a new job.
    client.post("/api/v1/calibrations", json=body)
    assert client.get("/api/v1/calibrations").json()["count"] == 2


def test_same_key_with_a_different_body_is_422(client: TestClient) -> None:
    dataset = upload_csv(client).json()
    _calibrate(client, {"dataset_id": dataset["id"]}, "key-2")
    other = _calibrate(
        client, {"dataset_id": dataset["id"], "options": {"heldout": False}}, "key-2"
    )
    assert_problem(other, 422, "key-2", "different request")
    upload = upload_csv(client, headers={"Idempotency-Key": "key-2"})
    assert_problem(upload, 422, "key-2")


def test_dataset_upload_replays_across_multipart_boundaries(client: TestClient) -> None:
    headers = {"Idempotency-Key": "upload-1"}
    first = upload_csv(client, headers=headers)
    second = upload_csv(client, headers=headers)  # httpx picks a new random boundary
    assert first.status_code == second.status_code == 201
    assert second.json()["id"] == first.json()["id"]
    assert second.headers["idempotent-replayed"] == "true"
    changed = upload_csv(client, recording_bytes(".csv", 40, 9), headers=headers)
    assert_problem(changed, 422, "upload-1")


def test_key_is_released_after_an_error(client: TestClient) -> None:
    missing = _calibrate(client, {"dataset_id": "ds_not_yet"}, "key-3")
    assert_problem(missing, 404)
    dataset = upload_csv(client).json()
    created = _calibrate(client, {"dataset_id": dataset["id"]}, "key-3")
    assert created.status_code == 202


def test_malformed_key_is_400(client: TestClient) -> None:
    response = _calibrate(client, {"dataset_id": "x"}, "k" * 300)
    assert_problem(response, 400, "Idempotency-Key")


def test_cancel_with_a_key_replays_its_first_answer(client: TestClient) -> None:
    dataset = upload_csv(client).json()
    location = client.post("/api/v1/calibrations", json={"dataset_id": dataset["id"]}).headers[
        "location"
    ]
    headers = {"Idempotency-Key": "cancel-1"}
    first = client.post(f"{location}/cancel", headers=headers)
    again = client.post(f"{location}/cancel", headers=headers)
    assert first.status_code == again.status_code == 200
    assert again.json() == first.json() and again.headers["idempotent-replayed"] == "true"
    assert_problem(client.post(f"{location}/cancel"), 409, "already cancelled")
