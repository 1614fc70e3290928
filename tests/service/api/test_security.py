"""API keys and tenants: keys required off loopback, stored hashed, tenants see only their own."""

from __future__ import annotations

import hashlib
import logging
import sys

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from service import cli
from service.security import KeyVerifier, revoke_api_key
from service.storage.models import ApiKey
from tests.service.api.conftest import (
    AppFactory,
    assert_problem,
    database_of,
    new_key,
    upload_csv,
)


@pytest.fixture
def remote(make_client: AppFactory) -> TestClient:
    """An app bound to all interfaces: keys are required."""
    return make_client(host="0.0.0.0")


def test_key_is_required_when_not_bound_to_loopback(remote: TestClient) -> None:
    missing = remote.get("/api/v1/datasets")
    assert_problem(missing, 401, "X-API-Key", "kincal keys create")
    assert "ApiKey" in missing.headers["www-authenticate"]
    for wrong in ("nonsense", "kc_000000000000_" + "A" * 43):
        assert_problem(remote.get("/api/v1/datasets", headers={"X-API-Key": wrong}), 401)
    key = new_key(remote, "acme")
    assert remote.get("/api/v1/datasets", headers={"X-API-Key": key}).status_code == 200
    tampered = key[:-1] + ("A" if key[-1] != "A" else "B")
    assert_problem(remote.get("/api/v1/datasets", headers={"X-API-Key": tampered}), 401)


def test_health_endpoints_need_no_key_but_metrics_do(remote: TestClient) -> None:
    """/metrics tells job counts and routes of every tenant: it answered without a key."""
    for path in ("/healthz", "/readyz"):
        assert remote.get(path).status_code == 200
    assert_problem(remote.get("/metrics"), 401, "X-API-Key")
    key = new_key(remote, "monitoring")
    metrics = remote.get("/metrics", headers={"X-API-Key": key})
    assert metrics.status_code == 200 and "kincal_http_requests_total" in metrics.text


def test_keyless_mode_only_on_loopback_and_is_announced(
    make_client: AppFactory, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.INFO):
        local = make_client(host="127.0.0.1")
    assert local.get("/api/v1/datasets").status_code == 200
    assert any("keyless mode" in r.getMessage() for r in caplog.records)
    assert_problem(local.get("/api/v1/datasets", headers={"X-API-Key": "wrong"}), 401)
    strict = make_client(host="127.0.0.1", allow_keyless_localhost=False)
    assert_problem(strict.get("/api/v1/datasets"), 401)


def test_other_tenants_get_404_for_everything(remote: TestClient) -> None:
    alice = {"X-API-Key": new_key(remote, "alice")}
    bob = {"X-API-Key": new_key(remote, "bob")}
    dataset = upload_csv(remote, headers=alice).json()
    calibration = remote.post(
        "/api/v1/calibrations", json={"dataset_id": dataset["id"]}, headers=alice
    ).json()
    urdf = (
        "<robot name='r'><link name='a'/><link name='b'/><joint name='j' type='revolute'>"
        "<parent link='a'/><child link='b'/><axis xyz='0 0 1'/>"
        "<limit lower='-1' upper='1' effort='1' velocity='1'/></joint></robot>"
    )
    robot = remote.post(
        "/api/v1/robots",
        json={"name": "r", "base_frame": "a", "tip_frame": "b", "urdf": urdf},
        headers=alice,
    ).json()

    for path in (
        f"/api/v1/datasets/{dataset['id']}",
        f"/api/v1/calibrations/{calibration['id']}",
        f"/api/v1/calibrations/{calibration['id']}/result",
        f"/api/v1/calibrations/{calibration['id']}/report",
        f"/api/v1/robots/{robot['id']}",
    ):
        assert_problem(remote.get(path, headers=bob), 404)
        assert remote.get(path, headers=alice).status_code in (200, 409)
    assert_problem(remote.delete(f"/api/v1/datasets/{dataset['id']}", headers=bob), 404)
    assert_problem(
        remote.post(f"/api/v1/calibrations/{calibration['id']}/cancel", headers=bob), 404
    )
    assert_problem(
        remote.post("/api/v1/calibrations", json={"dataset_id": dataset["id"]}, headers=bob), 404
    )
    assert_problem(upload_csv(remote, robot_name=robot["id"], headers=bob), 422, "unknown robot")
    assert remote.get("/api/v1/datasets", headers=bob).json()["count"] == 0
    assert remote.get("/api/v1/calibrations", headers=bob).json()["count"] == 0
    assert [r["id"] for r in remote.get("/api/v1/robots", headers=bob).json()["data"]] == [
        "kinova",
        "panda",
        "ur10",
    ]
    # The same file uploaded by another tenant is that tenant's own dataset (no cross-tenant dedup).
    theirs = upload_csv(remote, headers=bob)
    assert theirs.status_code == 201 and theirs.json()["id"] != dataset["id"]


def test_keys_are_stored_only_as_sha256(client: TestClient) -> None:
    key = new_key(client, "acme")
    database = database_of(client)
    with database.sessions() as session:
        rows = session.scalars(select(ApiKey)).all()
    assert len(rows) == 1
    assert rows[0].key_sha256 == hashlib.sha256(key.encode()).hexdigest()
    assert key.split("_", 2)[2] not in rows[0].key_sha256  # the secret may contain "_"
    assert key.startswith(f"kc_{rows[0].id}_")


def test_revoked_key_stops_working(client: TestClient) -> None:
    database = database_of(client)
    key = new_key(client, "acme")
    verifier = KeyVerifier(database, cache_s=0.0)
    assert verifier.verify(key) is not None
    assert revoke_api_key(database, key.split("_")[1])
    assert verifier.verify(key) is None
    assert not revoke_api_key(database, key.split("_")[1])


def test_cli_keys_create_prints_a_working_key_once(
    remote: TestClient,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    settings = remote.app.state.kincal.settings  # type: ignore[attr-defined]
    monkeypatch.setenv("KINCAL_DATA_DIR", str(settings.data_dir))
    monkeypatch.setenv("KINCAL_DATABASE_URL", settings.resolved_database_url)
    monkeypatch.setattr(sys, "argv", ["kincal", "keys", "create", "--tenant", "lab-7"])
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code in (0, None)
    out, err = capsys.readouterr()
    key = out.strip()
    assert key.startswith("kc_") and "not shown again" in err
    assert remote.get("/api/v1/datasets", headers={"X-API-Key": key}).status_code == 200

    monkeypatch.setattr(sys, "argv", ["kincal", "keys", "create", "--tenant", "Bad Name!"])
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code == 2
    assert "tenant name" in capsys.readouterr().err
