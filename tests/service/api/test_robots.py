"""Robots: built-ins listed; uploaded URDFs parsed safely, size-limited, must build the chain."""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import Any

import httpx
import pandas as pd
import pytest
from fastapi.testclient import TestClient

from service.api import robots as robots_route
from service.jobs.isolated import run_isolated
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


def long_chain_urdf(n_joints: int) -> str:
    """A serial chain l0 -> l1 -> ... of ``n_joints`` revolute joints with masses."""
    parts = ['<robot name="long">', '<link name="l0"/>']
    inertia = '<inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/>'
    for i in range(1, n_joints + 1):
        parts.append(
            f'<link name="l{i}"><inertial><mass value="1"/><origin xyz="0 0 0.05"/>{inertia}'
            "</inertial></link>"
        )
        parts.append(
            f'<joint name="j{i}" type="revolute"><parent link="l{i - 1}"/><child link="l{i}"/>'
            '<origin xyz="0 0 0.1"/><axis xyz="0 1 0"/>'
            '<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>'
        )
    return "\n".join([*parts, "</robot>"])


@pytest.fixture
def pinocchio_runs(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The tip frames of the URDFs handed to Pinocchio (its isolated process) from now on."""
    runs: list[str] = []

    def recorded(function: Callable[..., Any], urdf: str, base: str, tip: str, **kw: Any) -> Any:
        runs.append(tip)
        return run_isolated(function, urdf, base, tip, **kw)

    monkeypatch.setattr(robots_route, "run_isolated", recorded)
    return runs


def test_a_urdf_with_thousands_of_joints_is_refused_before_pinocchio_parses_it(
    client: TestClient, pinocchio_runs: list[str]
) -> None:
    """~4000 joints overflow the stack of Pinocchio's recursive URDF reader (a segfault that
    would end this test process); the joint count is read off the XML first."""
    urdf = long_chain_urdf(4000)
    assert len(urdf) > 800_000
    response = _upload(client, urdf, base="l0", tip="l6")
    assert_problem(response, 422, "4000 <joint> elements", "512")
    assert response.json()["type"].endswith("too-many-joints")
    assert pinocchio_runs == []
    assert client.get("/healthz").status_code == 200


def test_a_long_chain_is_refused_from_the_xml_before_pinocchio(
    client: TestClient, pinocchio_runs: list[str]
) -> None:
    """200 chain joints took a minute of server CPU in Pinocchio before the 32-joint check:
    the chain's length is read off the XML, Pinocchio never sees it. (Checked by what runs,
    not by a wall time, which a busy CI machine failed.)"""
    response = _upload(client, long_chain_urdf(200), base="l0", tip="l200")
    assert_problem(response, 422, "the chain has 200 joints", "32")
    assert pinocchio_runs == []
    # The same URDF with a short chain in it is fine, and so is a dataset naming other frames
    # of it, as long as their chain is within the limit too.
    created = _upload(client, long_chain_urdf(200), base="l0", tip="l6")
    assert created.status_code == 201, created.text
    assert created.json()["joint_names"] == [f"j{i}" for i in range(1, 7)]
    assert pinocchio_runs == ["l6"]  # the short chain went to Pinocchio, and only it
    too_long = client.post(
        "/api/v1/datasets",
        files={"file": ("r.csv", io.BytesIO(b"j1,x,y,z\n0,0,0,0\n"), "text/csv")},
        data={"robot": created.json()["id"], "tip_frame": "l150"},
    )
    assert_problem(too_long, 422, "150 joints")
