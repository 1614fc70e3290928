"""ROS bags uploaded over HTTP (issue 34): the service stores from a ROS 1 bag, and from a
rosbag2 folder (sqlite3, MCAP) that the Python client sends zipped, the rows ``kincal import``
writes from the same bag; a bag without its topic fields, with a topic it does not hold,
beyond the message limit, or an archive that is not a rosbag2 folder is a 4xx problem naming
the field and the fix."""

from __future__ import annotations

import contextlib
import io
import zipfile
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from schemas.dataset import read_dataset
from service.storage import repository
from tests.schemas.bag_writer import (
    CAPTURE_TOPIC,
    PANDA_JOINTS,
    STORAGES,
    Truth,
    capture_bags,
    fr3_bags,
)
from tests.schemas.test_rosbag import assert_same_rows
from tests.service.api.conftest import AppFactory, assert_problem, client_api, recording_bytes
from tests.service.cli_support import run_ok

TOPICS = {"joint_states": "/joint_states", "measure": "tf:camera_link:board"}
MiB = 1024 * 1024


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Truth]]:
    return fr3_bags(tmp_path_factory)


def _bag_file(bags: dict[str, tuple[Path, Truth]], storage: str) -> tuple[bytes, str]:
    path, _ = bags[storage]
    return path.read_bytes(), path.name


def _upload(client: TestClient, data: bytes, filename: str, /, **fields: str) -> Any:
    return client.post(
        "/api/v1/datasets",
        files={"file": (filename, io.BytesIO(data), "application/octet-stream")},
        data={"robot": "panda", **fields},
    )


@pytest.mark.parametrize("storage", STORAGES)
def test_a_bag_upload_stores_the_rows_kincal_import_writes(
    bags: dict[str, tuple[Path, Truth]], make_client: AppFactory, tmp_path: Path, storage: str
) -> None:
    path, _ = bags[storage]
    imported = tmp_path / "recording.parquet"
    flags = ["--joint-states", TOPICS["joint_states"], "--measure", TOPICS["measure"]]
    with contextlib.redirect_stdout(io.StringIO()):
        run_ok(["import", path, "--robot", "panda", *flags, "-o", imported])
    want = read_dataset(imported, PANDA_JOINTS)

    client = make_client()  # the default limits: the bags are 10-11 MB
    api = client_api(client)  # a rosbag2 folder goes zipped
    body = api.upload_dataset(path, robot="panda", **TOPICS)
    assert body["n_samples"] == want.n_samples == 114
    assert body["joint_names"] == list(PANDA_JOINTS)
    state = client.app.state.kincal  # type: ignore[attr-defined]
    with state.database.sessions() as session:
        row = repository.get_dataset(session, state.local_tenant.tenant_id, body["id"])
    assert row is not None
    assert_same_rows(read_dataset(state.files.path(row.data_path), PANDA_JOINTS), want, atol=0)
    assert api.upload_dataset(path, robot="panda", **TOPICS)["id"] == body["id"]  # deduplicated


def test_a_bag_needs_its_topic_fields_and_a_recording_file_refuses_them(
    bags: dict[str, tuple[Path, Truth]], make_client: AppFactory
) -> None:
    client = make_client()
    data, name = _bag_file(bags, "ros1")
    assert_problem(
        _upload(client, data, name, joint_states="/joint_states"),
        422,
        "measure: missing form field",
    )
    response = client.post(
        "/api/v1/datasets",
        files={"file": ("recording.csv", io.BytesIO(recording_bytes()), "text/csv")},
        data={"robot": "ur10", "measure": TOPICS["measure"]},
    )
    assert_problem(response, 422, "measure: only for a ROS bag")


def test_a_topic_the_bag_does_not_hold_is_named_with_the_bags_topics(
    bags: dict[str, tuple[Path, Truth]], make_client: AppFactory
) -> None:
    client = make_client()
    data, name = _bag_file(bags, "ros1")
    problem = assert_problem(
        _upload(client, data, name, joint_states="/nope", measure=TOPICS["measure"]),
        422,
        "no topic '/nope' in the bag",
        "/joint_states (sensor_msgs/msg/JointState",
        "pass one of them to joint_states",
    )
    assert "--joint-states" not in problem["detail"]
    assert_problem(
        _upload(client, data, name, joint_states="/joint_states", measure="tf:camera_link"),
        422,
        "measure 'tf:camera_link': give tf:PARENT:CHILD",
    )


def test_a_bag_beyond_the_message_limit_is_refused_before_decoding(
    bags: dict[str, tuple[Path, Truth]], make_client: AppFactory
) -> None:
    client = make_client(max_bag_messages=1000)
    data, name = _bag_file(bags, "ros1")
    problem = assert_problem(
        _upload(client, data, name, **TOPICS), 413, "more than the limit of 1000"
    )
    assert "KINCAL_MAX_BAG_MESSAGES" in problem["detail"]


def _archive(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        (b"not a zip", "not a zip archive"),
        (_archive({"bag/metadata.yaml": b"x", "../evil.db3": b"x"}), "points outside"),
        (_archive({"a/metadata.yaml": b"x", "b/metadata.yaml": b"x"}), "2 metadata.yaml"),
        (_archive({"bag/metadata.yaml": b"x", "bag/big.db3": bytes(5 * MiB)}), "unpacked"),
        (_archive({"bag/metadata.yaml": b"rosbag2_bagfile_information: 3"}), "cannot read"),
    ],
    ids=["not-zip", "outside", "two-bags", "too-big-unpacked", "not-rosbag2"],
)
def test_an_archive_that_is_not_one_small_rosbag2_folder_is_refused(
    make_client: AppFactory, data: bytes, fragment: str
) -> None:
    client = make_client(max_request_bytes=MiB)  # 4 MiB unpacked at most
    assert_problem(_upload(client, data, "bag.zip", **TOPICS), 422, fragment)


def test_a_robot_calibration_capture_bag_uploads_with_measure_only(
    tmp_path_factory: pytest.TempPathFactory, make_client: AppFactory
) -> None:
    """A rosbag2 folder of robot_calibration captures, without message definitions (as Humble
    records): the joint states are in the captures (tests/schemas/test_calibration_data.py)."""
    api = client_api(make_client())
    measure = f"calibration-data:{CAPTURE_TOPIC}"
    dataset = api.upload_dataset(
        capture_bags(tmp_path_factory)["sqlite3"], robot="panda", measure=measure
    )
    assert dataset["n_samples"] == 114 and dataset["joint_names"] == list(PANDA_JOINTS)
