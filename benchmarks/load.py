"""Load test of the rankings hot path: many concurrent planners against a real ``kincal serve``
process while a calibration job runs (issue 6: p99 < 20 ms for 100 candidates, 0 errors).

What it does:

1. starts ``kincal serve`` on 127.0.0.1 (free port, temporary data folder, SQLite, API keys
   required, one worker process, ``--web-processes`` request processes: default the
   service's, one per CPU up to 4) and creates a key;
2. uploads a simulated UR10 recording with :class:`service.api.client.KincalClient` and calibrates
   it (the calibration the planners rank with);
3. keeps a long calibration job (many held-out splits) running in the worker process for the
   whole measurement, starting the next one as soon as one ends;
4. runs ``--clients`` planners in one asyncio loop, each on its own keep-alive HTTP/1.1
   connection (bare asyncio streams: a general client costs more CPU than the service). Each
   planner sends ``POST /api/v1/rankings`` with ``--candidates`` configurations, waits for the
   answer, then waits for its next slot: slots are ``--interval-s`` apart with a random phase
   per planner (``--interval-s 0``: back to back, which measures saturation throughput, not
   latency). Latency is measured by the planner, send to last byte;
5. reports requests, errors (non-200 or transport errors), achieved requests/s, p50/p90/p99/max
   latency, the server's own view (share of ranking requests under 20 ms from ``/metrics``), the
   calibration jobs that ran meanwhile, and the machine's load average.

Usage: ``python -m benchmarks.load [--clients 200] [--duration-s 30] [--candidates 100]
[--interval-s 1.0] [--web-processes N] [--runs 20] [--json report.json] [--write-results]``;
``--quick`` is a smoke test (a few clients, 3 s). ``--runs N`` repeats the whole measurement (a
fresh server each time) and ends with a table of the runs and how many met p99 < 20 ms (the
acceptance is 19 of 20 runs of 30 s). ``--write-results`` writes ``docs/results/load.{json,md}``
(one row per run, the table docs/http.md includes).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import httpx
import numpy as np

from benchmarks.results import Row, markdown_table, write_results
from schemas.calibration import CalibrationOptions
from schemas.dataset import write_dataset
from schemas.robots import load_robot
from service.api.client import KincalClient
from service.app import simulate as scenarios
from service.render import result_json
from service.security import create_api_key
from service.storage.db import Database

TARGET_P99_MS = 20.0
RANKINGS = "/api/v1/rankings"
# The calibration the planners rank with: quick (no held-out splits).
RANKING_CALIBRATION = CalibrationOptions(heldout=False)
# The job kept running meanwhile: 40 held-out splits of two fits each, several seconds or more.
BACKGROUND_CALIBRATION = CalibrationOptions(seeds=list(range(1, 41)))


@dataclass(frozen=True)
class LoadSettings:
    clients: int = 200
    duration_s: float = 30.0
    candidates: int = 100
    interval_s: float = 1.0
    samples: int = 60
    warmup_s: float = 2.0
    background_job: bool = True
    web_processes: int | None = None
    """Request processes of the server (None: the service's default)."""


QUICK = LoadSettings(clients=8, duration_s=3.0, candidates=100, interval_s=0.2, warmup_s=0.5)


@dataclass
class LoadReport:
    settings: LoadSettings
    requests: int
    errors: int
    error_examples: list[str]
    requests_per_s: float
    offered_per_s: float
    latency_ms: dict[str, float]
    server_share_under_20ms: float | None
    server_cpu_ms_per_request: float
    client_cpu_ms_per_request: float
    calibration_jobs_finished: int
    calibration_job_running_share: float
    load_average: tuple[float, float]
    cpu_count: int
    web_process_cpu_s: list[float] = field(default_factory=list)
    """CPU time of each request process during the measurement (how evenly they share)."""
    meets_target: bool = field(init=False)

    def __post_init__(self) -> None:
        self.meets_target = self.errors == 0 and self.latency_ms["p99"] < TARGET_P99_MS


# --- the server --------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextmanager
def kincal_serve(folder: Path, web_processes: int | None = None) -> Iterator[tuple[str, str, int]]:
    """``kincal serve`` in its own process group: yields (base URL, API key, supervisor pid)."""
    port = _free_port()
    url = f"sqlite:///{folder / 'kincal.db'}"
    env = {
        **os.environ,
        "KINCAL_DATA_DIR": str(folder / "data"),
        "KINCAL_DATABASE_URL": url,
        "KINCAL_WORKERS": "1",
        "KINCAL_ALLOW_KEYLESS_LOCALHOST": "false",
        "KINCAL_LOG_FORMAT": "json",
        "KINCAL_INSTANCE_NAME": "load-benchmark",
    }
    if web_processes is not None:
        env["KINCAL_WEB_PROCESSES"] = str(web_processes)
    command = [sys.executable, "-c", "from service.cli import main; main()", "serve"]
    with (folder / "server.log").open("ab") as log:
        process = subprocess.Popen(
            [*command, "--port", str(port)],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    base = f"http://127.0.0.1:{port}"
    try:
        _wait_live(process, base, folder / "server.log")
        database = Database(url)
        try:
            key = create_api_key(database, "load-benchmark")[1]
        finally:
            database.dispose()
        yield base, key, process.pid
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _wait_live(process: subprocess.Popen[bytes], base: str, log: Path) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"kincal serve exited:\n{log.read_text()}")
        try:
            if httpx.get(f"{base}/readyz", timeout=1.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"kincal serve did not become ready:\n{log.read_text()}")


# --- set-up: a calibration to rank with, and one kept running ----------------------------------


def prepare(api: KincalClient, folder: Path, samples: int) -> tuple[str, str, list[str]]:
    """Upload a recording and calibrate it: (dataset id, calibration id, joint names)."""
    robot = load_robot("ur10")
    scn, recording = scenarios.simulate(robot, n_samples=samples, seed=7)
    path = folder / "recording.csv"
    write_dataset(scenarios.recording_dataset(recording, scn.chain, rotation=True), path)
    dataset = api.upload_dataset(path, robot="ur10")
    calibration = api.start_calibration(dataset["id"], RANKING_CALIBRATION)
    api.wait(calibration["id"], poll_s=0.1)
    result = api.result(calibration["id"])
    chain, _ = result_json.result_chain(result)
    return dataset["id"], calibration["id"], list(chain.joint_names)


class BackgroundCalibrations:
    """Keeps one long calibration job queued or running until stopped."""

    def __init__(self, api: KincalClient, dataset_id: str) -> None:
        self._api = api
        self._dataset_id = dataset_id
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="background-calibrations")
        self.finished = 0
        self.running_s = 0.0
        self.current: str | None = None

    def start(self) -> None:
        self.current = self._api.start_calibration(self._dataset_id, BACKGROUND_CALIBRATION)["id"]
        deadline = time.monotonic() + 60
        while self._api.status(self.current)["status"]["state"] != "running":
            if time.monotonic() > deadline:
                raise RuntimeError("the background calibration never started running")
            time.sleep(0.05)
        self._thread.start()

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(0.25):
            assert self.current is not None
            state = self._api.status(self.current)["status"]["state"]
            now = time.monotonic()
            if state == "running":
                self.running_s += now - last
            last = now
            if state in ("succeeded", "failed", "cancelled"):
                self.finished += state == "succeeded"
                job = self._api.start_calibration(self._dataset_id, BACKGROUND_CALIBRATION)
                self.current = job["id"]

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        if self.current is not None:
            with contextlib.suppress(Exception):  # it may have just finished
                self._api.cancel(self.current)


# --- the planners ------------------------------------------------------------------------------


def ranking_bodies(
    calibration_id: str, joint_names: list[str], candidates: int, n: int = 32
) -> list[bytes]:
    """``n`` different request bodies of ``candidates`` configurations each, pre-encoded."""
    rng = np.random.default_rng(11)
    lower, upper = np.full(len(joint_names), -3.0), np.full(len(joint_names), 3.0)
    bodies = []
    for _ in range(n):
        q = rng.uniform(lower, upper, size=(candidates, len(joint_names)))
        document = {"calibration_id": calibration_id, "joint_positions_rad": q.tolist()}
        bodies.append(json.dumps(document).encode())
    return bodies


@dataclass
class _Tally:
    """What the planners record: latencies (s) and errors of the measured window, and every
    request sent (warm-up included, to divide the server's CPU time by)."""

    latencies: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    sent: int = 0


@dataclass(frozen=True)
class _Window:
    start: float
    measure_from: float
    stop: float


class _Connection:
    """One planner's keep-alive HTTP/1.1 connection, on bare asyncio streams.

    A general client (httpx) spends more CPU per request than the service does once it holds
    200 connections, and on a 2-core machine the load generator's CPU is taken from the server;
    a planner needs only one kind of request, so the request bytes are built once.
    """

    def __init__(self, host: str, port: int, key: str) -> None:
        self.host, self.port = host, port
        self.head = (
            f"POST {RANKINGS} HTTP/1.1\r\nHost: {host}:{port}\r\nX-API-Key: {key}\r\n"
            "Content-Type: application/json\r\nContent-Length: {length}\r\n\r\n"
        )
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def post(self, body: bytes) -> int:
        """Send one ranking request; the response's status code (its body is read and
        dropped)."""
        if self.reader is None or self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        self.writer.write(self.head.format(length=len(body)).encode() + body)
        await self.writer.drain()
        head = await self.reader.readuntil(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        headers = dict(line.lower().split(": ", 1) for line in lines[1:] if ": " in line)
        await self.reader.readexactly(int(headers.get("content-length", "0")))
        if headers.get("connection") == "close":
            await self.close()
        return status

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            with contextlib.suppress(OSError):
                await self.writer.wait_closed()
        self.reader = self.writer = None


async def _planner(
    connection: _Connection,
    bodies: list[bytes],
    interval_s: float,
    window: _Window,
    seed: int,
    tally: _Tally,
) -> None:
    rng = random.Random(seed)
    next_slot = window.start + rng.uniform(0.0, interval_s)
    try:
        while True:
            now = time.perf_counter()
            if next_slot > now:
                await asyncio.sleep(next_slot - now)
            sent = time.perf_counter()
            if sent >= window.stop:
                return
            try:
                status = await connection.post(rng.choice(bodies))
                failure = None if status == 200 else f"HTTP {status}"
            except (OSError, asyncio.IncompleteReadError, ValueError) as exc:
                failure = f"{type(exc).__name__}: {exc}"
                await connection.close()
            elapsed = time.perf_counter() - sent
            tally.sent += 1
            if sent >= window.measure_from:
                tally.latencies.append(elapsed)
                if failure is not None:
                    tally.errors.append(failure)
            next_slot = max(next_slot + interval_s, time.perf_counter())
    finally:
        await connection.close()


async def run_planners(base: str, key: str, bodies: list[bytes], settings: LoadSettings) -> _Tally:
    """All planners, each on its own keep-alive connection."""
    address = httpx.URL(base)
    host, port = address.host, address.port or 80
    tally = _Tally()
    start = time.perf_counter()
    window = _Window(
        start, start + settings.warmup_s, start + settings.warmup_s + settings.duration_s
    )
    await asyncio.gather(
        *(
            _planner(_Connection(host, port, key), bodies, settings.interval_s, window, i, tally)
            for i in range(settings.clients)
        )
    )
    return tally


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (all its threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def web_processes_of(supervisor: int) -> list[int]:
    """The request processes ``kincal serve`` (pid ``supervisor``) started (not its job runner,
    whose worker processes run the calibrations)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            command = (entry / "cmdline").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        if parent == supervisor and b"service.api.child" in command and b"web" in command:
            found.append(int(entry.name))
    return sorted(found)


def _web_cpu_seconds(pids: list[int]) -> list[float]:
    return [_cpu_seconds(pid) for pid in pids]


def _server_share_under(base: str, key: str, seconds: float) -> float | None:
    """Share of POST /api/v1/rankings requests the server itself timed under ``seconds``."""
    text = httpx.get(f"{base}/metrics", headers={"X-API-Key": key}, timeout=10).text
    buckets: dict[float, float] = {}
    for line in text.splitlines():
        if line.startswith("kincal_http_request_duration_seconds_bucket{") and (
            'method="POST"' in line and f'route="{RANKINGS}"' in line
        ):
            bound = line.split('le="', 1)[1].split('"', 1)[0]
            buckets[float("inf") if bound == "+Inf" else float(bound)] = float(line.split()[-1])
    total = buckets.get(float("inf"))
    if not total or seconds not in buckets:
        return None
    return buckets[seconds] / total


def run(settings: LoadSettings, folder: Path | None = None) -> LoadReport:
    """Start a server, calibrate, keep a calibration running, load it; the report."""
    with _folder(folder) as work, kincal_serve(work, settings.web_processes) as (base, key, pid):
        api = KincalClient(base, api_key=key)
        dataset_id, calibration_id, joint_names = prepare(api, work, settings.samples)
        bodies = ranking_bodies(calibration_id, joint_names, settings.candidates)
        background = BackgroundCalibrations(api, dataset_id)
        if settings.background_job:
            background.start()
        web = web_processes_of(pid)
        cpu_before, client_before = _web_cpu_seconds(web), time.process_time()
        try:
            tally = asyncio.run(run_planners(base, key, bodies, settings))
            web_cpu_s = [a - b for a, b in zip(_web_cpu_seconds(web), cpu_before, strict=True)]
            cpu_s = sum(web_cpu_s)
            client_cpu_s = time.process_time() - client_before
        finally:
            if settings.background_job:
                background.stop()
        share = _server_share_under(base, key, TARGET_P99_MS / 1000)
        api.close()
    ms = np.array(tally.latencies) * 1000 if tally.latencies else np.array([float("nan")])
    offered = settings.clients / settings.interval_s if settings.interval_s > 0 else float("inf")
    return LoadReport(
        settings=settings,
        requests=len(tally.latencies),
        errors=len(tally.errors),
        error_examples=sorted(set(tally.errors))[:5],
        requests_per_s=len(tally.latencies) / settings.duration_s,
        offered_per_s=offered,
        latency_ms={
            "p50": float(np.percentile(ms, 50)),
            "p90": float(np.percentile(ms, 90)),
            "p99": float(np.percentile(ms, 99)),
            "max": float(ms.max()),
        },
        server_share_under_20ms=share,
        server_cpu_ms_per_request=1000 * cpu_s / max(tally.sent, 1),
        client_cpu_ms_per_request=1000 * client_cpu_s / max(tally.sent, 1),
        calibration_jobs_finished=background.finished,
        calibration_job_running_share=min(
            background.running_s / (settings.duration_s + settings.warmup_s), 1.0
        ),
        load_average=os.getloadavg()[:2],
        cpu_count=os.cpu_count() or 0,
        web_process_cpu_s=web_cpu_s,
    )


@contextmanager
def _folder(folder: Path | None) -> Iterator[Path]:
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        yield folder
        return
    with tempfile.TemporaryDirectory(prefix="kincal-load-") as temporary:
        yield Path(temporary)


def format_report(report: LoadReport) -> str:
    s = report.settings
    latency = report.latency_ms
    share = report.server_share_under_20ms
    verdict = "meets" if report.meets_target else "MISSES"
    lines = [
        f"{s.clients} planners, {s.candidates} candidates per ranking, one request per planner "
        f"every {s.interval_s:g} s (offered {report.offered_per_s:.0f}/s), {s.duration_s:g} s "
        f"measured after {s.warmup_s:g} s warm-up",
        f"requests {report.requests}, errors {report.errors}, {report.requests_per_s:.1f} req/s",
        f"latency ms: p50 {latency['p50']:.1f}  p90 {latency['p90']:.1f}  "
        f"p99 {latency['p99']:.1f}  max {latency['max']:.1f}",
        "server-timed share under 20 ms: "
        + ("n/a" if share is None else f"{share:.1%}")
        + f"; CPU per request: server {report.server_cpu_ms_per_request:.2f} ms, "
        f"load generator {report.client_cpu_ms_per_request:.2f} ms",
        f"{len(report.web_process_cpu_s)} request process(es), CPU s each: "
        + ", ".join(f"{seconds:.1f}" for seconds in report.web_process_cpu_s),
        f"background calibration running {report.calibration_job_running_share:.0%} of the "
        f"time, {report.calibration_jobs_finished} job(s) finished meanwhile",
        f"machine: {report.cpu_count} CPUs, load average {report.load_average[0]:.1f} "
        f"(1 min) / {report.load_average[1]:.1f} (5 min)",
        f"target p99 < {TARGET_P99_MS:g} ms with 0 errors: {verdict}",
    ]
    if report.error_examples:
        lines.append("errors seen: " + "; ".join(report.error_examples))
    return "\n".join(lines)


def format_runs(reports: list[LoadReport]) -> str:
    """One line per run (p50, p99, max, errors, calibrations finished) and the count of runs
    that met the target."""
    lines = ["run  requests  errors  p50 ms  p99 ms  max ms  calibrations  meets"]
    for number, report in enumerate(reports, start=1):
        latency = report.latency_ms
        lines.append(
            f"{number:>3}  {report.requests:>8}  {report.errors:>6}  {latency['p50']:>6.1f}  "
            f"{latency['p99']:>6.1f}  {latency['max']:>6.1f}  "
            f"{report.calibration_jobs_finished:>12}  {'yes' if report.meets_target else 'NO'}"
        )
    met = sum(report.meets_target for report in reports)
    p99 = sorted(report.latency_ms["p99"] for report in reports)
    lines.append(
        f"p99 < {TARGET_P99_MS:g} ms with 0 errors in {met} of {len(reports)} runs; "
        "p99 sorted (ms): " + ", ".join(f"{value:.1f}" for value in p99)
    )
    return "\n".join(lines)


def result_row(report: LoadReport) -> Row:
    """One run as a row of ``docs/results/load.json``."""
    return {
        "requests": report.requests,
        "errors": report.errors,
        "p50_ms": round(report.latency_ms["p50"], 2),
        "p99_ms": round(report.latency_ms["p99"], 2),
        "max_ms": round(report.latency_ms["max"], 2),
        "calibrations_finished": report.calibration_jobs_finished,
        "calibration_running_share": round(report.calibration_job_running_share, 3),
        "web_processes": len(report.web_process_cpu_s),
        "server_cpu_ms_per_request": round(report.server_cpu_ms_per_request, 2),
        "load_average_1min": round(report.load_average[0], 2),
        "meets_target": report.meets_target,
    }


def render(rows: list[Row]) -> str:
    """The runs' summary line and one table row per run (docs/http.md includes it)."""
    met = sum(row["meets_target"] for row in rows)
    p99 = sorted(row["p99_ms"] for row in rows)
    summary = (
        f"p99 < {TARGET_P99_MS:g} ms with 0 errors in **{met} of {len(rows)}** runs; "
        f"p99 from {p99[0]:.1f} to {p99[-1]:.1f} ms (median {float(np.median(p99)):.1f} ms)."
    )
    table = markdown_table(
        (
            "run",
            "requests",
            "errors",
            "p50 ms",
            "p99 ms",
            "max ms",
            "calibrations finished",
            "calibration running",
            "server CPU ms / request",
            "load average (1 min)",
        ),
        [
            (
                number,
                row["requests"],
                row["errors"],
                f"{row['p50_ms']:.1f}",
                f"{row['p99_ms']:.1f}",
                f"{row['max_ms']:.1f}",
                row["calibrations_finished"],
                f"{100 * row['calibration_running_share']:.0f} %",
                f"{row['server_cpu_ms_per_request']:.2f}",
                f"{row['load_average_1min']:.1f}",
            )
            for number, row in enumerate(rows, start=1)
        ],
    )
    return summary + "\n\n" + table


def main(argv: list[str] | None = None) -> list[LoadReport]:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--clients", type=int, default=LoadSettings.clients)
    parser.add_argument("--duration-s", type=float, default=LoadSettings.duration_s)
    parser.add_argument("--candidates", type=int, default=LoadSettings.candidates)
    parser.add_argument(
        "--interval-s",
        type=float,
        default=LoadSettings.interval_s,
        help="Time between one planner's requests (0: back to back).",
    )
    parser.add_argument("--warmup-s", type=float, default=LoadSettings.warmup_s)
    parser.add_argument(
        "--no-background-job", action="store_true", help="Measure without a calibration."
    )
    parser.add_argument(
        "--web-processes",
        type=int,
        help="Request processes of the server (KINCAL_WEB_PROCESSES; default: the service's).",
    )
    parser.add_argument(
        "--runs", type=int, default=1, help="Repeat the measurement, a fresh server each time."
    )
    parser.add_argument("--quick", action="store_true", help="Smoke test: 8 planners, 3 s.")
    parser.add_argument("--json", type=Path, help="Also write the report as JSON here.")
    parser.add_argument("--keep", type=Path, help="Work in this folder (server log, data).")
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="Write docs/results/load.{json,md} (one row per run; docs/http.md includes it).",
    )
    args = parser.parse_args(argv)
    settings = (
        QUICK
        if args.quick
        else LoadSettings(
            clients=args.clients,
            duration_s=args.duration_s,
            candidates=args.candidates,
            interval_s=args.interval_s,
            warmup_s=args.warmup_s,
        )
    )
    settings = LoadSettings(
        **{
            **asdict(settings),
            "background_job": not args.no_background_job,
            "web_processes": args.web_processes,
        }
    )
    reports = []
    for number in range(1, args.runs + 1):
        keep = args.keep
        if keep is not None and args.runs > 1:
            keep = keep / f"run-{number}"
        reports.append(run(settings, keep))
        if args.runs > 1:
            print(f"--- run {number} of {args.runs}")
        print(format_report(reports[-1]), flush=True)
    if args.runs > 1:
        print(format_runs(reports))
    if args.json:
        document = asdict(reports[0]) if args.runs == 1 else [asdict(r) for r in reports]
        args.json.write_text(json.dumps(document, indent=1), encoding="utf-8")
    if args.write_results:
        given = argv if argv is not None else sys.argv[1:]
        command = " ".join(["python -m benchmarks.load", *given])
        rows = [result_row(report) for report in reports]
        for path in write_results("load", command, rows, render):
            print(f"wrote {path}")
    return reports


if __name__ == "__main__":
    main()
