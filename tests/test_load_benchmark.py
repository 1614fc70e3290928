"""benchmarks/load.py on tiny settings: it starts ``kincal serve``, keeps a calibration running,
loads the rankings endpoint and reports, so it cannot rot."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks import load


def test_load_benchmark_smoke(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    tiny = ["--clients", "4", "--duration-s", "1.5", "--warmup-s", "0.3", "--interval-s", "0.1"]
    report = load.main([*tiny, "--candidates", "20", "--json", str(out), "--keep", str(tmp_path)])

    assert report.errors == 0, report.error_examples
    assert report.requests >= 10  # 4 planners, 10 slots a second each, 1.5 s
    latency = report.latency_ms
    assert 0 < latency["p50"] <= latency["p90"] <= latency["p99"] <= latency["max"]
    assert report.server_share_under_20ms is not None and 0 <= report.server_share_under_20ms <= 1
    assert report.server_cpu_ms_per_request > 0 and report.client_cpu_ms_per_request > 0
    assert report.calibration_job_running_share > 0  # a calibration ran during the load
    assert report.meets_target == (latency["p99"] < load.TARGET_P99_MS)

    document = json.loads(out.read_text())
    assert document["requests"] == report.requests and document["settings"]["candidates"] == 20
    text = load.format_report(report)
    assert "errors 0" in text and "p99" in text and "load average" in text
    log = (tmp_path / "server.log").read_text()
    assert log.count('"POST /api/v1/rankings 200"') >= report.requests
    assert log.count('"POST /api/v1/calibrations 202"') >= 2  # ranked one + background one
