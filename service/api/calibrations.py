"""Calibrations: jobs of kind ``calibration`` (see :func:`service.tasks.calibration_job`).

POST creates one; :func:`service.api.jobs_common.add_job_routes` adds list, status, result,
report, URDF and cancel.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Response

from schemas.api import (
    CalibrationCreate,
    CalibrationLinks,
    CalibrationPublic,
    CalibrationsPublic,
)
from schemas.calibration import CalibrationOptions, CalibrationResult
from service import pipeline
from service.api import jobs_common
from service.api.deps import API_PREFIX, PrincipalDep, StateDep
from service.api.idempotency import IDEMPOTENCY_PROBLEMS
from service.api.jobs_common import Artifact, JobResource
from service.api.problems import STANDARD_PROBLEMS, ProblemException, problem_responses
from service.api.results import CachedResult
from service.storage.models import Job
from service.tasks import CalibrationJobParams

PREFIX = f"{API_PREFIX}/calibrations"
router = APIRouter(prefix=PREFIX, tags=["calibrations"])

# The HTML report may not run scripts; its images are data URIs.
REPORT_HEADERS = {
    "Content-Security-Policy": "default-src 'none'; img-src data:; style-src 'unsafe-inline'",
    "X-Content-Type-Options": "nosniff",
}


def public(job: Job) -> CalibrationPublic:
    base = f"{PREFIX}/{job.id}"
    return CalibrationPublic(
        id=job.id,
        dataset_id=job.dataset_id,
        status=jobs_common.job_status(job),
        options=CalibrationOptions.model_validate(job.params["options"]),
        links=CalibrationLinks(
            self=base,
            result=f"{base}/result",
            report=f"{base}/report",
            urdf=f"{base}/urdf",
            cancel=f"{base}/cancel",
        ),
    )


RESOURCE = JobResource(
    kind="calibration",
    noun="calibration",
    prefix=PREFIX,
    public_model=CalibrationPublic,
    page_model=CalibrationsPublic,
    to_public=public,
)


def cached_calibration(state: StateDep, tenant_id: str, calibration_id: str) -> CachedResult:
    """A succeeded calibration through the in-process LRU cache: no database query on a hit;
    404 (unknown, or another tenant's) or 409 (not succeeded yet) otherwise.

    Rankings call this on their hot path (from a worker thread: a miss reads the database),
    and use ``entry.memo("uncertainty_model", build)`` for what they derive from the result.
    """

    def load() -> Job | None:
        job = RESOURCE.lookup(state, tenant_id, calibration_id)
        jobs_common.artifact(state, job, "result", RESOURCE.noun)  # 409 unless succeeded
        return job

    entry = state.results.entry(tenant_id, calibration_id, load)
    if entry is None:
        raise ProblemException(404, f"calibration {calibration_id!r} not found", slug="not-found")
    return entry


def result_of(state: StateDep, tenant_id: str, calibration_id: str) -> CalibrationResult:
    """The result of a succeeded calibration (see :func:`cached_calibration`)."""
    return cached_calibration(state, tenant_id, calibration_id).result


@router.post(
    "",
    status_code=202,
    response_model=CalibrationPublic,
    responses={**STANDARD_PROBLEMS, **IDEMPOTENCY_PROBLEMS, **problem_responses(404)},
)
def create_calibration(
    body: CalibrationCreate,
    principal: PrincipalDep,
    state: StateDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> Response:
    """Start calibrating a dataset; poll the Location for progress."""
    return jobs_common.accept_dataset_job(
        state,
        principal.tenant_id,
        RESOURCE,
        body,
        idempotency_key,
        dataset_id=body.dataset_id,
        check_options=lambda robot: pipeline.chain_for(robot, body.options),
        make_params=lambda dataset, robot: CalibrationJobParams(
            dataset=dataset, robot=robot, options=body.options
        ),
    )


jobs_common.add_job_routes(
    router,
    RESOURCE,
    [
        Artifact("result", "application/json", "The result JSON (kincal.calibration/1)."),
        Artifact(
            "report",
            "text/html; charset=utf-8",
            "HTML report: fit table, residuals before/after, identifiability, σ per frame.",
            headers=REPORT_HEADERS,
        ),
        Artifact(
            "urdf",
            "application/xml",
            "The calibrated robot as a plain URDF.",
            download_suffix=".urdf",
        ),
    ],
)
