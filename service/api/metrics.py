"""Prometheus metrics of the service (own registry per app, so several apps coexist in tests).

Under ``kincal serve`` several request processes and the job runner each count their own
requests and jobs: ``prometheus_client``'s multiprocess mode (``PROMETHEUS_MULTIPROC_DIR``, a
directory per run of the supervisor, emptied at its start) keeps the counters and histograms in
per-process files, and every scrape, whichever process answers it, sums them over all
processes (a restarted process's counts are kept, so totals never go down). The gauges
(``kincal_jobs``, ``kincal_workers_alive``) are not per process: they are read at scrape time
from the database and the runner's status, so they are neither summed nor duplicated.

* ``kincal_http_requests_total{method,route,status}`` and
  ``kincal_http_request_duration_seconds{method,route}``: route is the path template
  (``/api/v1/calibrations/{calibration_id}``), never the raw path, to bound cardinality;
* ``kincal_jobs{kind,state}``: jobs in the database per state, read at scrape time;
* ``kincal_job_duration_seconds{kind,state}``: start to finish of jobs run by this instance;
* ``kincal_workers_alive``: worker processes alive;
* ``kincal_check_statistic{calibration_id}``, ``kincal_check_threshold{calibration_id}``: the
  global test (Σ d²) of each calibration's latest check and its limit, read at scrape time
  from the database (no sample while the latest check was inconclusive), and
  ``kincal_check_drifted{calibration_id}`` (1 when its verdict was drifted, else 0). One
  series per calibration, for the :data:`MAX_CHECKED_CALIBRATIONS` checked most recently, so
  the label's cardinality stays bounded however many calibrations were ever checked.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Histogram,
    disable_created_metrics,
    generate_latest,
    multiprocess,
    values,
)
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from service.storage import repository
from service.storage.db import Database
from service.storage.models import Job

disable_created_metrics()  # no *_created series: they double the output and nobody reads them

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
JOB_BUCKETS_S = (0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 900.0, 3600.0)
MAX_CHECKED_CALIBRATIONS = 500
"""The check gauges show the calibrations checked most recently, at most this many."""


class _JobCollector(Collector):
    def __init__(
        self, database: Database, kinds: Callable[[], list[str]], alive: Callable[[], int]
    ) -> None:
        self._database = database
        self._kinds = kinds
        self._alive = alive

    def collect(self) -> Iterator[Metric]:
        jobs = GaugeMetricFamily("kincal_jobs", "Jobs by kind and state.", labels=["kind", "state"])
        with self._database.session() as session:
            counts = repository.count_jobs_by_state(session)
        kinds = sorted(set(self._kinds()) | {kind for kind, _ in counts})
        for kind in kinds:
            for state in repository.JOB_STATES:
                jobs.add_metric([kind, state], counts.get((kind, state), 0))
        yield jobs
        workers = GaugeMetricFamily("kincal_workers_alive", "Worker processes alive.")
        workers.add_metric([], self._alive())
        yield workers


class _CheckCollector(Collector):
    """The latest check of each calibration (every tenant), read from the database."""

    def __init__(self, database: Database) -> None:
        self._database = database

    def collect(self) -> Iterator[Metric]:
        labels = ["calibration_id"]
        statistic = GaugeMetricFamily(
            "kincal_check_statistic",
            "Global test statistic (sum of d2) of the calibration's latest check.",
            labels=labels,
        )
        threshold = GaugeMetricFamily(
            "kincal_check_threshold",
            "Limit of that statistic at the check's level (drift above it).",
            labels=labels,
        )
        drifted = GaugeMetricFamily(
            "kincal_check_drifted",
            "1 when the calibration's latest check found drift, else 0.",
            labels=labels,
        )
        with self._database.session() as session:
            latest = repository.latest_checks(session, MAX_CHECKED_CALIBRATIONS)
        for check in latest:
            label = [check.calibration_id]
            if check.statistic is not None and check.threshold is not None:
                statistic.add_metric(label, check.statistic)
                threshold.add_metric(label, check.threshold)
            drifted.add_metric(label, 1.0 if check.verdict == "drifted" else 0.0)
        yield statistic
        yield threshold
        yield drifted


def multiprocess_dir() -> str | None:
    """The directory of per-process metric files if this process records in multiprocess mode
    (decided by ``prometheus_client`` when it is imported: ``PROMETHEUS_MULTIPROC_DIR``)."""
    if values.ValueClass is values.MutexValue:
        return None
    return os.environ.get("PROMETHEUS_MULTIPROC_DIR")


class Metrics:
    def __init__(
        self, database: Database, kinds: Callable[[], list[str]], alive: Callable[[], int]
    ) -> None:
        self._jobs = _JobCollector(database, kinds, alive)
        self._checks = _CheckCollector(database)
        self._multiprocess_dir = multiprocess_dir()
        # In multiprocess mode the values live in files; registering them too would count this
        # process twice in a scrape.
        self.registry = CollectorRegistry() if self._multiprocess_dir is None else None
        self.requests = Counter(
            "kincal_http_requests",
            "HTTP requests by route template and status.",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "kincal_http_request_duration_seconds",
            "HTTP request latency by route template.",
            ["method", "route"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )
        self.job_duration = Histogram(
            "kincal_job_duration_seconds",
            "Job run time (start to finish) by kind and final state.",
            ["kind", "state"],
            buckets=JOB_BUCKETS_S,
            registry=self.registry,
        )
        if self.registry is not None:
            self.registry.register(self._jobs)
            self.registry.register(self._checks)

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests.labels(method, route, str(status)).inc()
        self.latency.labels(method, route).observe(seconds)

    def observe_job(self, job: Job) -> None:
        if job.started_at is not None and job.finished_at is not None:
            seconds = (job.finished_at - job.started_at).total_seconds()
            self.job_duration.labels(job.kind, job.state).observe(max(seconds, 0.0))

    def render(self) -> bytes:
        if self.registry is not None:
            return generate_latest(self.registry)
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry, self._multiprocess_dir)
        registry.register(self._jobs)
        registry.register(self._checks)
        return generate_latest(registry)
