"""Discoveries: jobs of kind ``discovery`` (see
:func:`service.app.job_functions.discovery_job`), which look for the physics a dataset shows
and the user's model lacks (``kincal discover``).

POST creates one; :func:`service.api.jobs_common.add_job_routes` adds list, status, result
(the findings JSON, ``kincal.findings/1``), report and cancel.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Response

from schemas.api import DiscoveriesPublic, DiscoveryCreate, DiscoveryLinks, DiscoveryPublic
from schemas.discovery import DiscoveryOptions
from schemas.robots import RobotDescription
from service.api import jobs_common
from service.api.calibrations import REPORT_HEADERS
from service.api.deps import API_PREFIX, PrincipalDep, StateDep
from service.api.idempotency import IDEMPOTENCY_PROBLEMS
from service.api.jobs_common import Artifact, JobResource
from service.api.problems import STANDARD_PROBLEMS, problem_responses
from service.app.job_params import DiscoveryJobParams
from service.app.measurement_input import check_sensor_joint, refuse_file_measurement
from service.render.chain import chain_for
from service.storage.models import Job
from solver.model import KinematicChain

PREFIX = f"{API_PREFIX}/discoveries"
router = APIRouter(prefix=PREFIX, tags=["discoveries"])


def public(job: Job) -> DiscoveryPublic:
    base = f"{PREFIX}/{job.id}"
    return DiscoveryPublic(
        id=job.id,
        dataset_id=job.dataset_id,
        status=jobs_common.job_status(job),
        options=DiscoveryOptions.model_validate(job.params["options"]),
        links=DiscoveryLinks(
            self=base, result=f"{base}/result", report=f"{base}/report", cancel=f"{base}/cancel"
        ),
    )


RESOURCE = JobResource(
    kind="discovery",
    noun="discovery",
    prefix=PREFIX,
    public_model=DiscoveryPublic,
    page_model=DiscoveriesPublic,
    to_public=public,
)


def _checked(robot: RobotDescription, options: DiscoveryOptions) -> KinematicChain:
    """The user's chain; measurements the service cannot read from one dataset refused."""
    refuse_file_measurement(options.measurement, "discover")
    chain = chain_for(robot, options)
    check_sensor_joint(options.measurement, chain)
    return chain


@router.post(
    "",
    status_code=202,
    response_model=DiscoveryPublic,
    responses={**STANDARD_PROBLEMS, **IDEMPOTENCY_PROBLEMS, **problem_responses(404)},
)
def create_discovery(
    body: DiscoveryCreate,
    principal: PrincipalDep,
    state: StateDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> Response:
    """Start looking for missing physics in a dataset; poll the Location for progress."""
    return jobs_common.accept_dataset_job(
        state,
        principal.tenant_id,
        RESOURCE,
        body,
        idempotency_key,
        dataset_id=body.dataset_id,
        check_options=lambda robot: _checked(robot, body.options),
        make_params=lambda dataset, robot, _chain: DiscoveryJobParams(
            dataset=dataset, robot=robot, options=body.options
        ),
    )


jobs_common.add_job_routes(
    router,
    RESOURCE,
    [
        Artifact("result", "application/json", "The findings JSON (kincal.findings/1)."),
        Artifact(
            "report",
            "text/html; charset=utf-8",
            "HTML report: findings with residuals before/after, ambiguities, held-out error.",
            headers=REPORT_HEADERS,
        ),
    ],
)
