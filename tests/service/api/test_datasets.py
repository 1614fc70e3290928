"""Datasets over HTTP: validated by the CLI's readers, stored exactly, deduplicated, limited."""

from __future__ import annotations

import io
import json
import math
import tempfile
import threading

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient

from schemas.dataset import read_dataset, read_dataset_bytes
from service.storage import repository
from service.storage.models import Dataset
from tests.service.api.conftest import (
    AppFactory,
    assert_problem,
    recording,
    recording_bytes,
    settings_of,
    upload_csv,
)


def _csv_with(edit: dict[tuple[int, str], object], drop: list[str] | None = None) -> bytes:
    frame = pd.read_csv(io.BytesIO(recording_bytes()))
    for (row, column), value in edit.items():
        frame.loc[row, column] = value
    if drop:
        frame = frame.drop(columns=drop)
    return frame.to_csv(index=False).encode()


def test_csv_upload_is_validated_stored_exactly_and_summarised(client: TestClient) -> None:
    response = upload_csv(client)
    assert response.status_code == 201, response.text
    body = response.json()
    assert response.headers["location"] == f"/api/v1/datasets/{body['id']}"
    expected = recording()
    assert body["n_samples"] == expected.n_samples
    assert body["joint_names"] == list(expected.joint_names)
    assert body["measures_rotation"] is True
    assert expected.time_s is not None
    assert body["time_start_s"] == expected.time_s[0]
    assert body["time_end_s"] == expected.time_s[-1]
    assert client.get(response.headers["location"]).json() == body

    state = client.app.state.kincal  # type: ignore[attr-defined]
    with state.database.sessions() as session:
        from service.storage import repository

        row = repository.get_dataset(session, state.local_tenant.tenant_id, body["id"])
    assert row is not None
    stored = read_dataset(state.files.path(row.data_path), expected.joint_names)
    np.testing.assert_array_equal(stored.joint_positions, expected.joint_positions)
    np.testing.assert_array_equal(stored.position_m, expected.position_m)
    np.testing.assert_array_equal(stored.quaternion_xyzw, expected.quaternion_xyzw)


def test_same_data_uploaded_again_in_any_format_returns_the_existing_dataset(
    client: TestClient,
) -> None:
    first = upload_csv(client)
    assert first.status_code == 201
    again = upload_csv(client, filename="copy.csv")
    parquet = upload_csv(
        client, recording_bytes(".parquet"), filename="r.parquet", media="application/x-parquet"
    )
    rows = pd.read_csv(io.BytesIO(recording_bytes())).to_dict(orient="records")
    as_json = client.post("/api/v1/datasets", json={"robot": "ur10", "rows": rows})
    for response in (again, parquet, as_json):
        assert response.status_code == 200, response.text
        assert response.json()["id"] == first.json()["id"]
    assert client.get("/api/v1/datasets").json()["count"] == 1


def test_different_data_or_robot_frames_make_a_new_dataset(client: TestClient) -> None:
    first = upload_csv(client).json()
    other = upload_csv(client, recording_bytes(".csv", 40, 3))
    assert other.status_code == 201 and other.json()["id"] != first["id"]
    assert other.json()["content_sha256"] != first["content_sha256"]


def test_json_rows_are_validated_like_files(client: TestClient) -> None:
    rows = pd.read_csv(io.BytesIO(recording_bytes())).to_dict(orient="records")
    rows[4]["elbow_joint"] = None
    response = client.post("/api/v1/datasets", json={"robot": "ur10", "rows": rows})
    assert_problem(response, 422, "data row 5", "elbow_joint")


def test_missing_value_is_422_naming_row_and_column(client: TestClient) -> None:
    response = upload_csv(client, _csv_with({(4, "elbow_joint"): math.nan}))
    body = assert_problem(response, 422, "recording.csv", "data row 5", "column elbow_joint")
    assert body["type"].endswith("invalid-dataset")


def test_non_unit_quaternion_is_422(client: TestClient) -> None:
    response = upload_csv(client, _csv_with({(6, "qw"): 3.0}))
    assert_problem(response, 422, "data row 7", "quaternion is not unit-norm")


def test_unknown_column_is_422_naming_it(client: TestClient) -> None:
    frame = pd.read_csv(io.BytesIO(recording_bytes()))
    frame["gripper_joint"] = 0.0
    response = upload_csv(client, frame.to_csv(index=False).encode())
    assert_problem(response, 422, "gripper_joint")


def test_missing_joint_column_is_422(client: TestClient) -> None:
    response = upload_csv(client, _csv_with({}, drop=["wrist_3_joint"]))
    assert_problem(response, 422, "missing joint column", "wrist_3_joint")


def test_garbage_file_is_422_not_500(client: TestClient) -> None:
    response = upload_csv(client, b"\x00\xff\x00garbage\n\x01", filename="r.parquet")
    assert_problem(response, 422, "r.parquet")


def test_unknown_robot_is_422(client: TestClient) -> None:
    response = upload_csv(client, robot_name="r2d2")
    assert_problem(response, 422, "r2d2", "kinova")


def test_wrong_content_type_is_415(client: TestClient) -> None:
    response = client.post(
        "/api/v1/datasets", content=recording_bytes(), headers={"content-type": "text/csv"}
    )
    assert_problem(response, 415, "text/csv", "multipart/form-data")


def test_unrecognised_file_format_is_415(client: TestClient) -> None:
    response = upload_csv(
        client, b"a,b\n1,2\n", filename="data.xlsx", media="application/vnd.ms-excel"
    )
    assert_problem(response, 415, "data.xlsx", ".csv")


def test_missing_form_fields_are_422(client: TestClient) -> None:
    no_file = client.post("/api/v1/datasets", data={"robot": "ur10"}, files={"x": ("a", b"1")})
    assert_problem(no_file, 422, "file")
    no_robot = client.post(
        "/api/v1/datasets", files={"file": ("r.csv", recording_bytes(), "text/csv")}
    )
    assert_problem(no_robot, 422, "robot")


def test_body_over_the_limit_is_413_whether_declared_or_streamed(
    make_client: AppFactory,
) -> None:
    client = make_client(max_request_bytes=64 * 1024)
    big = b"x" * (100 * 1024)
    declared = upload_csv(client, big)
    assert_problem(declared, 413, "65536")

    def chunks() -> object:
        for _ in range(100):
            yield b"y" * 1024

    streamed = client.post(
        "/api/v1/datasets", content=chunks(), headers={"content-type": "application/json"}
    )
    assert_problem(streamed, 413, "65536")
    assert client.get("/healthz").status_code == 200


def test_more_rows_than_the_limit_is_413(make_client: AppFactory) -> None:
    client = make_client(max_rows=10)
    assert_problem(upload_csv(client), 413, "40 samples", "10")


def many_rows_parquet(n_rows: int) -> bytes:
    """A valid-looking UR10 recording of ``n_rows`` identical rows: a few hundred KB of Parquet
    that decodes to hundreds of MB."""
    columns = [*pd.read_csv(io.BytesIO(recording_bytes())).columns]
    table = pa.table({c: pa.repeat(pa.scalar(0.5 if c == "qw" else 0.0), n_rows) for c in columns})
    buffer = io.BytesIO()
    pq.write_table(table, buffer, compression="zstd")
    return buffer.getvalue()


def test_a_parquet_file_is_refused_on_its_row_count_before_it_is_decoded(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """5 M rows in ~200 KB used to be decoded in full (GBs) before the row limit."""
    data = many_rows_parquet(5_000_000)
    assert len(data) < 1_000_000
    decoded: list[int] = []
    original = pq.ParquetFile.read

    def read(self: pq.ParquetFile, *args: object, **kwargs: object) -> pa.Table:
        decoded.append(self.metadata.num_rows)
        return original(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(pq.ParquetFile, "read", read)
    monkeypatch.setattr(pd, "read_parquet", lambda *a, **k: pytest.fail("decoded in full"))
    response = upload_csv(client, data, filename="big.parquet")
    assert_problem(response, 413, "5000000 samples", "100000")
    assert decoded == []
    small = upload_csv(client, recording_bytes(".parquet"), filename="small.parquet")
    assert small.status_code == 201 and decoded == [40]


@pytest.mark.parametrize("how", ["rows", "json file", "csv file"])
@pytest.mark.parametrize("value", [10**400, 1e308, -2e244])
def test_huge_numbers_are_422_at_upload_not_a_500_or_a_failed_job(
    client: TestClient, how: str, value: float
) -> None:
    """A 400-digit integer was an OverflowError (500); 1e308 was accepted and failed the job
    (SVD did not converge). Same range as rankings: |q| <= 1e4."""
    rows = pd.read_csv(io.BytesIO(recording_bytes())).to_dict(orient="records")
    rows[2]["elbow_joint"] = value
    if how == "rows":
        response = client.post("/api/v1/datasets", json={"robot": "ur10", "rows": rows})
    elif how == "json file":
        response = upload_csv(client, json.dumps(rows).encode(), filename="r.json")
    else:
        response = upload_csv(client, pd.DataFrame(rows).to_csv(index=False).encode())
    assert_problem(response, 422, "data row 3, column elbow_joint", "-10000 to 10000 rad")


def test_a_broken_parquet_file_is_described_without_a_server_path(client: TestClient) -> None:
    data = recording_bytes(".parquet")
    response = upload_csv(client, data[: len(data) // 2] + data[-8:], filename="cut.parquet")
    body = assert_problem(response, 422, "cut.parquet: cannot read as parquet")
    assert tempfile.gettempdir() not in body["detail"] and "upload" not in body["detail"]


def test_list_is_paginated_newest_first(client: TestClient) -> None:
    ids = [upload_csv(client, recording_bytes(".csv", 40, seed)).json()["id"] for seed in (5, 6, 7)]
    page = client.get("/api/v1/datasets", params={"limit": 2}).json()
    assert page["count"] == 3 and page["limit"] == 2 and page["offset"] == 0
    assert [d["id"] for d in page["data"]] == ids[::-1][:2]
    rest = client.get("/api/v1/datasets", params={"limit": 2, "offset": 2}).json()
    assert [d["id"] for d in rest["data"]] == ids[:1]
    assert_problem(client.get("/api/v1/datasets", params={"limit": 0}), 422, "query.limit")


def test_delete_removes_row_and_file(client: TestClient) -> None:
    body = upload_csv(client).json()
    state = client.app.state.kincal  # type: ignore[attr-defined]
    files = list((settings_of(client).data_dir / "tenants").rglob("*.parquet"))
    assert len(files) == 1
    assert client.delete(f"/api/v1/datasets/{body['id']}").status_code == 204
    assert_problem(client.get(f"/api/v1/datasets/{body['id']}"), 404, body["id"])
    assert not files[0].exists()
    assert_problem(client.delete(f"/api/v1/datasets/{body['id']}"), 404)
    assert state.files.writable()


def test_dataset_in_use_by_a_queued_job_cannot_be_deleted(client: TestClient) -> None:
    dataset = upload_csv(client).json()
    created = client.post("/api/v1/calibrations", json={"dataset_id": dataset["id"]})
    assert created.status_code == 202
    assert_problem(client.delete(f"/api/v1/datasets/{dataset['id']}"), 409, "job")


def test_a_delete_committed_during_a_duplicate_upload_makes_a_new_dataset(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The upload used to look the content up, and answer 200 with that id even when its
    deletion committed in between."""
    first = upload_csv(client).json()
    state = client.app.state.kincal  # type: ignore[attr-defined]
    original = repository.touch_dataset_by_content

    def delete_first_then_touch(session: object, tenant_id: str, sha: str) -> bool:
        with state.database.session() as other:  # a DELETE that commits just before
            other.delete(other.get(Dataset, first["id"]))
        return original(session, tenant_id, sha)  # type: ignore[arg-type]

    monkeypatch.setattr(repository, "touch_dataset_by_content", delete_first_then_touch)
    again = upload_csv(client)
    assert again.status_code == 201, again.text
    assert again.json()["id"] != first["id"]
    monkeypatch.undo()
    assert client.get(f"/api/v1/datasets/{first['id']}").status_code == 404
    assert client.get(again.headers["location"]).status_code == 200


def test_deleting_and_re_uploading_the_same_data_concurrently_keeps_every_file(
    client: TestClient,
) -> None:
    """Datasets shared one file per content: a delete could remove the file of a re-upload
    stored meanwhile. No 5xx, and every dataset that remains can be read."""
    statuses: list[int] = []

    def upload() -> None:
        for _ in range(15):
            statuses.append(upload_csv(client).status_code)

    def delete() -> None:
        for _ in range(15):
            for row in client.get("/api/v1/datasets").json()["data"]:
                statuses.append(client.delete(f"/api/v1/datasets/{row['id']}").status_code)

    threads = [threading.Thread(target=upload), threading.Thread(target=delete)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert statuses and all(code < 500 for code in statuses), statuses
    state = client.app.state.kincal  # type: ignore[attr-defined]
    upload_csv(client)
    for row in client.get("/api/v1/datasets").json()["data"]:
        with state.database.sessions() as session:
            stored = session.get(Dataset, row["id"])
        assert (
            read_dataset_bytes(
                state.files.read(stored.data_path), ".parquet", stored.joint_names, source="x"
            ).n_samples
            == row["n_samples"]
        )
