"""benchmarks/load.py on tiny settings: it starts ``kincal serve``, keeps a calibration running,
loads the rankings endpoint and reports, so it cannot rot."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks import load
from service.settings import default_web_processes


def test_load_benchmark_smoke(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    tiny = ["--clients", "4", "--duration-s", "1.5", "--warmup-s", "0.3", "--interval-s", "0.1"]
    [report] = load.main([*tiny, "--candidates", "20", "--json", str(out), "--keep", str(tmp_path)])

    assert report.errors == 0, report.error_examples
    assert report.requests >= 10  # 4 planners, 10 slots a second each, 1.5 s
    latency = report.latency_ms
    assert 0 < latency["p50"] <= latency["p90"] <= latency["p99"] <= latency["max"]
    assert report.server_share_under_20ms is not None and 0 <= report.server_share_under_20ms <= 1
    assert report.server_cpu_ms_per_request > 0 and report.client_cpu_ms_per_request > 0
    # the request processes' CPU, not the idle supervisor's (the default: one per CPU, <= 4)
    assert len(report.web_process_cpu_s) == default_web_processes()
    assert sum(report.web_process_cpu_s) > 0
    assert report.calibration_job_running_share > 0  # a calibration ran during the load
    assert report.meets_target == (latency["p99"] < load.TARGET_P99_MS)

    document = json.loads(out.read_text())
    assert document["requests"] == report.requests and document["settings"]["candidates"] == 20
    text = load.format_report(report)
    assert "errors 0" in text and "p99" in text and "load average" in text
    assert "request process(es), CPU s each" in text
    log = (tmp_path / "server.log").read_text()
    assert log.count('"POST /api/v1/rankings 200"') >= report.requests
    assert log.count('"POST /api/v1/calibrations 202"') >= 2  # ranked one + background one


def test_the_runs_table_counts_the_runs_that_meet_the_target() -> None:
    def report(p99_ms: float, errors: int = 0) -> load.LoadReport:
        return load.LoadReport(
            settings=load.LoadSettings(),
            requests=6000,
            errors=errors,
            error_examples=[],
            requests_per_s=200.0,
            offered_per_s=200.0,
            latency_ms={"p50": 2.0, "p90": 4.0, "p99": p99_ms, "max": 2 * p99_ms},
            server_share_under_20ms=0.99,
            server_cpu_ms_per_request=2.0,
            client_cpu_ms_per_request=1.0,
            calibration_jobs_finished=3,
            calibration_job_running_share=0.9,
            load_average=(2.0, 2.0),
            cpu_count=2,
        )

    table = load.format_runs([report(9.5), report(25.0), report(12.0, errors=1), report(19.9)])
    lines = table.splitlines()
    assert len(lines) == 6 and lines[2].endswith("NO") and lines[3].endswith("NO")
    assert lines[-1].startswith("p99 < 20 ms with 0 errors in 2 of 4 runs")
    assert lines[-1].endswith("9.5, 12.0, 19.9, 25.0")
