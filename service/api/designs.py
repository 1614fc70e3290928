"""Designs: which poses to record (``kincal design``, :func:`service.app.design.run_design`).

Synchronous (200 with the ``kincal.design/1`` document) up to :data:`SYNC_MAX_CANDIDATES`
candidates (with the recording of a sequential design: ``calibration_id``); larger sets become
a job of kind ``design`` (202 + Location; the shared job routes
give status, result and cancel).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Header, Response
from starlette.concurrency import run_in_threadpool

from schemas.design import (
    DesignCreate,
    DesignJobPublic,
    DesignJobsPublic,
    DesignLinks,
    DesignResult,
)
from service.api import jobs_common
from service.api.deps import API_PREFIX, PrincipalDep, ServiceState, StateDep
from service.api.idempotency import IDEMPOTENCY_PROBLEMS
from service.api.jobs_common import Artifact, JobResource
from service.api.problems import STANDARD_PROBLEMS, ProblemException, problem_responses
from service.api.robots import resolve_robot
from service.app.job_params import DatasetRef, DesignJobParams, RecordedRef
from service.storage import repository
from service.storage.files import FileStore
from service.storage.models import Job

PREFIX = f"{API_PREFIX}/designs"
CALIBRATIONS = f"{API_PREFIX}/calibrations"
router = APIRouter(prefix=PREFIX, tags=["designs"])

SYNC_MAX_CANDIDATES = 2000
"""Up to this many candidates (plus recorded configurations, for a sequential design) a
design is answered in the request (a few seconds at most)."""


def public(job: Job) -> DesignJobPublic:
    base = f"{PREFIX}/{job.id}"
    return DesignJobPublic(
        id=job.id,
        status=jobs_common.job_status(job),
        links=DesignLinks(self=base, result=f"{base}/result", cancel=f"{base}/cancel"),
    )


RESOURCE = JobResource(
    kind="design",
    noun="design",
    prefix=PREFIX,
    public_model=DesignJobPublic,
    page_model=DesignJobsPublic,
    to_public=public,
)


def _work(body: DesignCreate, params: DesignJobParams, recorded_rows: int) -> int:
    """Configurations whose information a design evaluates: candidates and recording."""
    candidates = (
        len(body.candidates_rad) if body.candidates_rad is not None else body.options.n_candidates
    )
    return candidates + (recorded_rows if params.recorded is not None else 0)


def invalid(field: str, detail: str, slug: str = "invalid-request") -> ProblemException:
    """A 422 problem naming one body field (dotted path) and what to do."""
    return ProblemException(
        422,
        f"{field}: {detail}",
        slug=slug,
        errors=[
            {
                "location": f"body.{field}",
                "pointer": "#/" + field.replace(".", "/"),
                "detail": detail,
            }
        ],
    )


def _params(state: ServiceState, tenant_id: str, body: DesignCreate) -> tuple[DesignJobParams, int]:
    """The job parameters of a request and the size of its recording (0 unless sequential):
    the robot resolved, or for a sequential design the calibration and its dataset."""
    if body.calibration_id is None:
        if body.robot is None:
            raise invalid(
                "robot",
                "required: a built-in robot name or an uploaded robot id (or calibration_id "
                "for a sequential design)",
            )
        with state.database.sessions() as session:
            robot = resolve_robot(
                state, session, tenant_id, body.robot, body.base_frame, body.tip_frame
            )
        return DesignJobParams(robot=robot.ref, request=body), 0
    for field in ("robot", "base_frame", "tip_frame"):
        if getattr(body, field) is not None:
            raise invalid(
                field,
                "a sequential design uses the robot and chain of calibration_id's calibration; "
                f"leave {field} out",
            )
    if "calibration" in body.options.model_fields_set:
        raise invalid(
            "options.calibration",
            "a sequential design uses the options calibration_id was calibrated with; leave "
            "options.calibration out",
        )
    return _recorded(state, tenant_id, body)


def _recorded(
    state: ServiceState, tenant_id: str, body: DesignCreate
) -> tuple[DesignJobParams, int]:
    calibration_id = body.calibration_id
    assert calibration_id is not None
    with state.database.sessions() as session:
        job = repository.get_job(session, tenant_id, "calibration", calibration_id)
        dataset = (
            None
            if job is None or job.dataset_id is None
            else repository.get_dataset(session, tenant_id, job.dataset_id)
        )
    if job is None:
        raise ProblemException(
            404,
            f"calibration_id: calibration {calibration_id!r} not found; list yours with "
            f"GET {CALIBRATIONS}",
            slug="not-found",
        )
    if job.state != repository.SUCCEEDED or "result" not in job.artifacts:
        fix = (
            f"wait for it (poll GET {CALIBRATIONS}/{job.id} until state is 'succeeded')"
            if job.state in repository.ACTIVE_STATES
            else "calibrate the dataset again"
        )
        raise ProblemException(
            409,
            f"calibration_id: calibration {job.id} is {job.state}, it has no result; {fix}",
            slug="not-ready",
            headers=jobs_common.poll_headers(job) or None,
        )
    if dataset is None:
        raise ProblemException(
            409,
            f"calibration_id: the dataset of calibration {job.id} was deleted; a sequential "
            "design needs the recording: upload it again and calibrate it",
            slug="no-dataset",
        )
    recorded = RecordedRef(
        calibration_id=job.id,
        result_path=job.artifacts["result"],
        dataset=DatasetRef(id=dataset.id, name=dataset.name, data_path=dataset.data_path),
    )
    return DesignJobParams(recorded=recorded, request=body), dataset.n_samples


def _matrix(rows: list[list[float]] | None, field: str, k: int) -> np.ndarray | None:
    if rows is None:
        return None
    for i, row in enumerate(rows):
        if len(row) != k:
            raise invalid(
                f"{field}.{i}",
                f"{len(row)} joint positions; the chain has {k}",
                slug="invalid-configurations",
            )
    return np.array(rows, dtype=float).reshape(-1, k)


def _design_now(files: FileStore, params: DesignJobParams) -> DesignResult:
    """A small design answered in the request (in a worker thread). The design pipeline is
    imported by the first design a request process answers, not when the process starts."""
    from service.app.job_functions import design_now

    return design_now(files, params, _matrix)


@router.post(
    "",
    response_model=DesignResult,
    responses={
        202: {"model": DesignJobPublic, "description": "A large design, run as a job."},
        **STANDARD_PROBLEMS,
        **IDEMPOTENCY_PROBLEMS,
        **problem_responses(404, 409),
    },
)
async def create_design(
    body: DesignCreate,
    principal: PrincipalDep,
    state: StateDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> Response:
    """Choose the poses to record (kincal.design/1); with calibration_id, the next poses after
    that calibration's dataset (sequential design). Synchronous for small candidate sets (and
    recordings), a job (202 + Location) otherwise."""
    params, recorded_rows = await run_in_threadpool(_params, state, principal.tenant_id, body)
    if _work(body, params, recorded_rows) <= SYNC_MAX_CANDIDATES:
        result = await run_in_threadpool(_design_now, state.files, params)
        return Response(result.model_dump_json(), media_type="application/json")

    def submit() -> Response:
        job = jobs_common.submit_job(
            state, principal.tenant_id, "design", params.model_dump(mode="json")
        )
        return RESOURCE.accepted(job)

    from service.api.idempotency import Idempotency, fingerprint

    idempotency = Idempotency(
        state.database, principal.tenant_id, idempotency_key, f"POST {PREFIX}"
    )
    return await run_in_threadpool(
        idempotency.run, lambda: fingerprint(body.model_dump(mode="json")), submit
    )


jobs_common.add_job_routes(
    router,
    RESOURCE,
    [Artifact("result", "application/json", "The design document (kincal.design/1).")],
)
