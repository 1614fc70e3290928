"""Issue 7: with ``KINCAL_DASK_ADDRESS`` set, the service's calibration jobs run streamed on
that Dask cluster and give ``kincal calibrate --executor dask``'s result on the same data."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from distributed import LocalCluster

from schemas.calibration import CalibrationOptions, CalibrationResult
from service.app import job_functions as tasks
from service.jobs.worker import JobContext
from service.storage.files import FileStore
from service.storage.models import Job
from tests.conftest import assert_documents_close, comparable_result
from tests.service.api.conftest import (
    AppFactory,
    client_api,
    database_of,
    recording_bytes,
    settings_of,
)
from tests.service.cli_support import run


def test_calibration_job_runs_on_the_dask_cluster_of_the_setting(
    make_client: AppFactory,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    csv = tmp_path / "recording.csv"
    csv.write_bytes(recording_bytes(".csv", 300, 5))
    options = CalibrationOptions(covariance_estimator="moment", heldout=False)
    with LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        host="127.0.0.1",
        dashboard_address=None,
    ) as cluster:
        address = cluster.scheduler_address
        # the job worker reads the setting from its environment (spawned: it inherits ours)
        monkeypatch.setenv("KINCAL_DASK_ADDRESS", address)
        http = make_client(workers=1, worker_start_method="spawn")
        api = client_api(http)
        dataset = api.upload_dataset(csv, robot="ur10")
        job = api.start_calibration(dataset["id"], options)
        progress: list[dict[str, Any]] = []
        api.wait(job["id"], poll_s=0.05, on_progress=progress.append)
        served = api.result(job["id"])
        assert "run_block" in cluster.scheduler.task_prefixes  # the passes ran on the cluster
        # the same job function, called here, reports each streamed stage in order
        with database_of(http).sessions() as session:
            stored = session.get(Job, job["id"])
            assert stored is not None
            params = stored.params
        messages: list[tuple[Any, ...]] = []
        files = FileStore(settings_of(http).data_dir)
        tasks.calibration_job(JobContext("again", "local", params, files, messages.append))

        out = tmp_path / "cli.json"
        args = ["calibrate", str(csv), "--robot", "ur10", "--executor", "dask"]
        args += ["--dask", address, "--estimator", "moment", "--no-heldout", "-o", str(out)]
        code, text, err = run(args, capsys, monkeypatch)
    assert code == 0, err
    assert "ran on dask" in text
    fractions = [p["fraction"] for p in progress if p["fraction"] is not None]
    assert fractions == sorted(fractions) and progress[-1]["state"] == "succeeded"
    reported = [(m[1], m[2]) for m in messages if m[0] == "progress"]
    assert [stage for stage, _ in reported] == [
        "loading",
        "connecting",
        "read",
        "fit",
        "baseline",
        "covariance",
        "report",
    ]
    assert [f for _, f in reported] == sorted(f for _, f in reported)
    streamed = CalibrationResult.model_validate_json(out.read_text())
    assert served.options.heldout is False and served.covariance is not None
    assert served.covariance.estimator == "moment"
    assert served.dataset.source == streamed.dataset.source
    assert_documents_close(comparable_result(served), comparable_result(streamed))
