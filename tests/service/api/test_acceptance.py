"""Issue 6 acceptance: upload -> job -> result -> report -> ranking -> discovery over HTTP, with
the client, against ``kincal serve`` as a real uvicorn process on 127.0.0.1 (API keys on)."""

from __future__ import annotations

import os
import re
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from schemas.calibration import CalibrationOptions
from schemas.discovery import DiscoveryOptions
from schemas.ranking import RankingOptions, TargetPose
from service.api.client import KincalAPIError, KincalClient
from service.app import rank as ranking
from service.render import result_json
from service.security import create_api_key
from service.storage.db import Database
from solver import lie
from solver.model import sample_configurations
from tests.service.api.conftest import fresh_database_url, recording_bytes
from tests.service.api.test_crash_recovery import Server


@pytest.fixture
def server(tmp_path: Path) -> Iterator[tuple[Server, str]]:
    with fresh_database_url(tmp_path) as url:
        env = {
            **os.environ,
            "KINCAL_DATA_DIR": str(tmp_path / "data"),
            "KINCAL_DATABASE_URL": url,
            "KINCAL_ALLOW_KEYLESS_LOCALHOST": "false",
            "KINCAL_LOG_FORMAT": "json",
        }
        process = Server(env, tmp_path / "server.log")
        try:
            process.wait_live()
            yield process, url
        finally:
            assert process.stop(signal.SIGTERM) in (0, -signal.SIGTERM)


def _key(url: str, tenant: str) -> str:
    database = Database(url)  # the server migrated it at start-up
    try:
        return create_api_key(database, tenant)[1]
    finally:
        database.dispose()


def _pngs(html: str) -> int:
    return len(re.findall(r'src="data:image/png;base64,', html))


def test_upload_job_result_report_ranking_discovery_over_http_with_the_client(
    server: tuple[Server, str], tmp_path: Path
) -> None:
    process, url = server
    api = KincalClient(process.url, api_key=_key(url, "lab-a"))
    other = KincalClient(process.url, api_key=_key(url, "lab-b"))
    csv = tmp_path / "recording.csv"
    csv.write_bytes(recording_bytes(".csv", 60, 5))  # UR10 with an elastic elbow

    # upload -> calibration job with progress -> result, report, URDF
    dataset = api.upload_dataset(csv, robot="ur10")
    assert dataset["n_samples"] == 60 and dataset["robot"] == "ur10"
    calibration = api.start_calibration(dataset["id"], CalibrationOptions(seeds=[1, 2, 3]))
    progress: list[dict[str, Any]] = []
    api.wait(calibration["id"], poll_s=0.05, on_progress=progress.append)
    assert progress[-1]["state"] == "succeeded" and progress[-1]["fraction"] == 1.0
    result = api.result(calibration["id"])
    assert result.covariance is not None and result.fit.after.heldout is not None
    assert result.fit.before.heldout is not None
    assert (
        result.fit.after.heldout.translation_mean_mm < result.fit.before.heldout.translation_mean_mm
    )
    report = api.report(calibration["id"])
    assert _pngs(report) >= 2 and "Identifiability" in report
    assert "<robot" in api.urdf(calibration["id"])

    # ranking: rows and a target pose, the same numbers as the pipeline computes directly
    chain, _ = result_json.result_chain(result)
    q = sample_configurations(chain, 100, np.random.default_rng(3), 0.8)
    ranked = api.rank(calibration["id"], q.tolist())
    assert ranked == ranking.rank_configurations(result, q, RankingOptions())
    pose = result_json.predict_poses(result, q[:1])[0]
    target = TargetPose(
        position_m=tuple(pose[:3, 3].tolist()),
        quaternion_xyzw=tuple(lie.matrix_to_quaternion_xyzw(pose[:3, :3]).tolist()),
    )
    candidates = api.rank(calibration["id"], target=target, n_candidates=4)
    assert 1 <= len(candidates.ranking) <= 4 and candidates.target == target

    # discovery job -> findings JSON -> report with its figures
    discovery = api.start_discovery(dataset["id"], DiscoveryOptions(bootstrap=10))
    api.wait_discovery(discovery["id"], poll_s=0.05)
    findings = api.findings(discovery["id"])
    assert ("joint_compliance", "elbow_joint") in [(f.effect, f.joint) for f in findings.findings]
    discovery_report = api.discovery_report(discovery["id"])
    assert _pngs(discovery_report) == len(findings.plots) >= 1

    # another tenant sees none of it; no key at all is a 401
    for call in (
        lambda: other.rank(calibration["id"], q[:2].tolist()),
        lambda: other.result(calibration["id"]),
        lambda: other.findings(discovery["id"]),
        lambda: other.start_discovery(dataset["id"]),
    ):
        with pytest.raises(KincalAPIError) as error:
            call()
        assert error.value.status == 404
    keyless = httpx.post(
        f"{process.url}/api/v1/rankings",
        json={"calibration_id": calibration["id"], "joint_positions_rad": q[:1].tolist()},
    )
    assert keyless.status_code == 401
    assert keyless.headers["content-type"].startswith("application/problem+json")

    assert httpx.get(f"{process.url}/metrics").status_code == 401  # keys are required here
    metrics = httpx.get(f"{process.url}/metrics", headers=api._headers).text
    assert 'route="/api/v1/rankings",status="200"' in metrics
    assert 'kincal_jobs{kind="discovery",state="succeeded"} 1.0' in metrics
