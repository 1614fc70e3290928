"""Designs: which poses to record (``kincal design``, :func:`service.design.run_design`).

Synchronous (200 with the ``kincal.design/1`` document) up to :data:`SYNC_MAX_CANDIDATES`
candidates; larger sets become a job of kind ``design`` (202 + Location; the shared job routes
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
from service.design import DesignJobParams, design_model, run_design
from service.storage.models import Job
from service.tasks import robot_description

PREFIX = f"{API_PREFIX}/designs"
router = APIRouter(prefix=PREFIX, tags=["designs"])

SYNC_MAX_CANDIDATES = 2000
"""Up to this many candidates a design is answered in the request (a few seconds at most)."""


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


def _candidate_count(body: DesignCreate) -> int:
    if body.candidates_rad is not None:
        return len(body.candidates_rad)
    return body.options.n_candidates


def _params(state: ServiceState, tenant_id: str, body: DesignCreate) -> DesignJobParams:
    with state.database.sessions() as session:
        robot = resolve_robot(
            state, session, tenant_id, body.robot, body.base_frame, body.tip_frame
        )
    return DesignJobParams(robot=robot.ref, request=body)


def _matrix(rows: list[list[float]] | None, field: str, k: int) -> np.ndarray | None:
    if rows is None:
        return None
    for i, row in enumerate(rows):
        if len(row) != k:
            raise ProblemException(
                422,
                f"{field}.{i}: {len(row)} joint positions; the chain has {k}",
                slug="invalid-configurations",
                errors=[
                    {
                        "location": f"body.{field}.{i}",
                        "pointer": f"#/{field}/{i}",
                        "detail": f"needs {k} joint positions",
                    }
                ],
            )
    return np.array(rows, dtype=float).reshape(-1, k)


def design_now(state: ServiceState, params: DesignJobParams) -> DesignResult:
    """The design of a request, in the calling thread."""
    robot = robot_description(params.robot, state.files)
    body = params.request
    model = design_model(robot, body.options)
    k = model.chain.n_joints
    return run_design(
        robot,
        body.options,
        candidates=_matrix(body.candidates_rad, "candidates_rad", k),
        task=_matrix(body.task_rad, "task_rad", k),
        model=model,
    )


@router.post(
    "",
    response_model=DesignResult,
    responses={
        202: {"model": DesignJobPublic, "description": "A large design, run as a job."},
        **STANDARD_PROBLEMS,
        **IDEMPOTENCY_PROBLEMS,
        **problem_responses(404),
    },
)
async def create_design(
    body: DesignCreate,
    principal: PrincipalDep,
    state: StateDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> Response:
    """Choose the poses to record (kincal.design/1); synchronous for small candidate sets,
    a job (202 + Location) otherwise."""
    params = await run_in_threadpool(_params, state, principal.tenant_id, body)
    if _candidate_count(body) <= SYNC_MAX_CANDIDATES:
        result = await run_in_threadpool(design_now, state, params)
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
