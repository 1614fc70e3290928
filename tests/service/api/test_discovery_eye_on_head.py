"""Discovery and a calibration carrying it over HTTP for a sensor on the chain (issue 15): the
eye-on-head rows of ``tests/service/test_discover_measurements.py`` (sensor after panda_joint2,
a concealed compliance of panda_joint4) uploaded once; ``POST /api/v1/discoveries`` with
``measurement: eye-on-head:panda_joint2`` names the compliance, and ``POST /api/v1/calibrations``
with that ``discovery_id`` calibrates it (the same measurement, the compliance as its option)."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from schemas.discovery import DiscoveryOptions
from service.api import create_app
from tests.service.api.conftest import client_api, fresh_database_url, make_settings
from tests.service.test_discover_measurements import (
    COMPLIANCE_RAD_PER_NM,
    write_eye_on_head_file,
)

MEASUREMENT = "eye-on-head:panda_joint2"


def test_eye_on_head_discovery_and_its_carried_calibration_over_http(tmp_path: Path) -> None:
    data = tmp_path / "eye.csv"
    write_eye_on_head_file(data, "panda_joint4", COMPLIANCE_RAD_PER_NM)
    with (
        fresh_database_url(tmp_path) as url,
        TestClient(create_app(make_settings(tmp_path, url, workers=1))) as client,
    ):
        api = client_api(client)
        dataset = api.upload_dataset(data, robot="panda")
        discovery = api.start_discovery(
            dataset["id"],
            DiscoveryOptions(measurement=MEASUREMENT, bootstrap=10, detectability=False),
        )
        api.wait_discovery(discovery["id"], poll_s=0.05)
        findings = api.findings(discovery["id"])
        assert [(f.effect, f.joint) for f in findings.findings] == [
            ("joint_compliance", "panda_joint4")
        ]
        assert findings.measurement is not None
        assert {u.joint for u in findings.measurement.not_candidates} == {
            "panda_joint1",
            "panda_joint2",
        }
        created = api.start_calibration(
            dataset["id"],
            {"measurement": MEASUREMENT, "heldout": False, "covariance": "none"},
            discovery_id=discovery["id"],
        )
        api.wait(created["id"], poll_s=0.05)
        result = api.result(created["id"])
    assert result.options.compliant_joints == ["panda_joint4"]
    (compliance,) = result.compliance
    assert compliance.joint == "panda_joint4" and compliance.significant
    assert abs(compliance.value_rad_per_nm / COMPLIANCE_RAD_PER_NM - 1.0) < 0.1
    assert result.model_corrections is not None and result.model_corrections.corrections == []
