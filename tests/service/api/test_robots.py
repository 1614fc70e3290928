"""Robots: built-ins listed; uploaded URDFs parsed safely, size-limited, must build the chain."""

from __future__ import annotations

import io

import httpx
import pandas as pd
from fastapi.testclient import TestClient

from tests.conftest import robot
from tests.service.api.conftest import AppFactory, assert_problem, recording_bytes, upload_csv

BOMB = """<?xml version="1.0"?>
<!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;">]>
<robot name="x">&lol2;</robot>"""
EXTERNAL = """<?xml version="1.0"?>
<!DOCTYPE r [<!ENTITY xxe SYSTEM "file:///etc/passwd">]><robot name="&xxe;"/>"""


def _upload(
    client: TestClient, urdf: str, base: str = "base_link", tip: str = "tool0"
) -> httpx.Response:
    body = {"name": "my-ur10", "base_frame": base, "tip_frame": tip, "urdf": urdf}
    return client.post("/api/v1/robots", json=body)


def test_builtins_are_listed_with_their_chains(client: TestClient) -> None:
    robots = {r["id"]: r for r in client.get("/api/v1/robots").json()["data"]}
    assert set(robots) == {"kinova", "panda", "ur10"}
    assert robots["ur10"]["builtin"] and len(robots["ur10"]["joint_names"]) == 6
    assert client.get("/api/v1/robots/panda").json()["base_frame"] == "panda_link0"


def test_uploaded_urdf_is_stored_and_usable_for_datasets(client: TestClient) -> None:
    created = _upload(client, robot("ur10").urdf_xml)
    assert created.status_code == 201, created.text
    body = created.json()
    assert body["id"].startswith("rbt_") and not body["builtin"]
    assert body["joint_names"] == client.get("/api/v1/robots/ur10").json()["joint_names"]
    assert client.get(created.headers["location"]).json() == body
    dataset = upload_csv(client, robot_name=body["id"])
    assert dataset.status_code == 201, dataset.text
    assert dataset.json()["robot_id"] == body["id"] and dataset.json()["robot"] == "my-ur10"
    # q-style joint columns work with an uploaded robot too.
    frame = pd.read_csv(io.BytesIO(recording_bytes()))
    frame = frame.rename(columns={n: f"q{i + 1}" for i, n in enumerate(body["joint_names"])})
    q_style = upload_csv(client, frame.to_csv(index=False).encode(), robot_name=body["id"])
    assert q_style.status_code == 200 and q_style.json()["id"] == dataset.json()["id"]


def test_entity_expansion_and_external_entities_are_refused(client: TestClient) -> None:
    for document in (BOMB, EXTERNAL):
        assert_problem(_upload(client, document), 422, "urdf:", "not allowed")


def test_garbage_or_non_urdf_xml_is_422(client: TestClient) -> None:
    assert_problem(_upload(client, "<robot"), 422, "not well-formed")
    assert_problem(_upload(client, "<html/>"), 422, "<robot>")
    assert_problem(_upload(client, "<robot name='x'/>"), 422, "urdf")


def test_frames_not_in_the_urdf_are_422(client: TestClient) -> None:
    response = _upload(client, robot("ur10").urdf_xml, tip="no_such_link")
    assert_problem(response, 422, "no_such_link")


def test_urdf_over_the_size_limit_is_413(make_client: AppFactory) -> None:
    client = make_client(max_urdf_bytes=4096)
    assert_problem(_upload(client, robot("ur10").urdf_xml), 413, "4096")


def test_chain_longer_than_the_joint_limit_is_422(make_client: AppFactory) -> None:
    client = make_client(max_joints=3)
    assert_problem(_upload(client, robot("ur10").urdf_xml), 422, "6 joints", "3")
    assert_problem(upload_csv(client), 422, "6 joints")
