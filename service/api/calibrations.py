"""Calibrations: jobs of kind ``calibration``
(see :func:`service.app.job_functions.calibration_job`).

POST creates one; :func:`service.api.jobs_common.add_job_routes` adds list, status, result,
report, URDF and cancel.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Response
from fastapi.concurrency import run_in_threadpool

from schemas.api import (
    CalibrationCreate,
    CalibrationLinks,
    CalibrationPublic,
    CalibrationsPublic,
)
from schemas.calibration import CalibrationOptions, CalibrationResult, Verdict
from schemas.discovery import FindingsResult
from schemas.robots import RobotDescription
from service.api import jobs_common
from service.api.deps import API_PREFIX, PrincipalDep, ServiceState, StateDep
from service.api.idempotency import IDEMPOTENCY_PROBLEMS
from service.api.jobs_common import Artifact, JobResource
from service.api.problems import STANDARD_PROBLEMS, ProblemException, problem_responses
from service.api.results import CachedResult
from service.api.robots import one_line
from service.app.job_params import CalibrationJobParams, DiscoveryRef
from service.app.measurement_input import refuse_file_measurement
from service.render import exports
from service.render.urdf_export import refusal as urdf_refusal
from service.storage import repository
from service.storage.models import Job
from solver.errors import KincalError, ModelError

PREFIX = f"{API_PREFIX}/calibrations"
DISCOVERIES = f"{API_PREFIX}/discoveries"
HTTP_URDF_FIX = (
    "rank and predict with its result (POST /api/v1/rankings applies the corrections), or "
    "calibrate without discovery_id for a plain URDF"
)
router = APIRouter(prefix=PREFIX, tags=["calibrations"])

# The HTML report may not run scripts; its images are data URIs.
REPORT_HEADERS = {
    "Content-Security-Policy": "default-src 'none'; img-src data:; style-src 'unsafe-inline'",
    "X-Content-Type-Options": "nosniff",
}


def public(job: Job) -> CalibrationPublic:
    base = f"{PREFIX}/{job.id}"
    carried = job.params.get("discovery")
    return CalibrationPublic(
        id=job.id,
        dataset_id=job.dataset_id,
        discovery_id=None if carried is None else carried["id"],
        status=jobs_common.job_status(job),
        verdict=summary_verdict(job),
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


def carried_discovery(
    state: ServiceState, tenant_id: str, body: CalibrationCreate, robot: RobotDescription
) -> tuple[DiscoveryRef, FindingsResult]:
    """The succeeded discovery ``body.discovery_id`` of this tenant whose findings fit the
    dataset's robot and options: 404, 409 (not succeeded) or 422 naming discovery_id otherwise."""
    discovery_id = body.discovery_id
    assert discovery_id is not None
    with state.database.sessions() as session:
        job = repository.get_job(session, tenant_id, "discovery", discovery_id)
    if job is None:
        raise ProblemException(
            404,
            f"discovery_id: discovery {discovery_id!r} not found; start one with "
            "POST /api/v1/discoveries or list yours with GET /api/v1/discoveries",
            slug="not-found",
        )
    if job.state != repository.SUCCEEDED:
        if job.state in repository.ACTIVE_STATES:
            fix = f"wait for it (poll GET {DISCOVERIES}/{job.id} until state is 'succeeded')"
        else:
            fix = "start a new discovery"
        raise ProblemException(
            409,
            f"discovery_id: discovery {job.id} is {job.state}, its findings are not ready; {fix}",
            slug="not-ready",
            headers=jobs_common.poll_headers(job) or None,
        )
    from service.app import discover_carry  # the discovery code: on the first such request

    findings = FindingsResult.model_validate_json(state.files.read(job.artifacts["result"]))
    try:
        discover_carry.findings_chain(findings, robot)
    except ModelError as exc:
        raise ProblemException(
            422,
            f"discovery_id: discovery {job.id} does not fit the dataset's robot ({one_line(exc)}"
            f"); name a discovery of a dataset of robot {robot.name}",
            slug="invalid-discovery",
        ) from exc
    given = discover_carry.model_options_set(body.options)
    if given:
        fields = ", ".join(f"options.{name}" for name in given)
        raise ProblemException(
            422,
            f"{fields}: discovery_id sets the model; leave {fields} at the default (run the "
            "discovery with them instead)",
            slug="invalid-options",
        )
    return DiscoveryRef(id=job.id, findings_path=job.artifacts["result"]), findings


@router.post(
    "",
    status_code=202,
    response_model=CalibrationPublic,
    responses={
        **STANDARD_PROBLEMS,
        **IDEMPOTENCY_PROBLEMS,
        **problem_responses(404, 409),
    },
)
def create_calibration(
    body: CalibrationCreate,
    principal: PrincipalDep,
    state: StateDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> Response:
    """Start calibrating a dataset (carrying a discovery's findings if given); poll the
    Location for progress."""

    def check(robot: RobotDescription) -> DiscoveryRef | None:
        from service.app import calibrate as pipeline  # on the first calibration, not at start

        carried, findings = None, None
        if body.discovery_id is not None:
            carried, findings = carried_discovery(state, principal.tenant_id, body, robot)
        pipeline.check_calibration(robot, body.options, findings)
        refuse_file_measurement(body.options.measurement, "calibrate")
        return carried

    return jobs_common.accept_dataset_job(
        state,
        principal.tenant_id,
        RESOURCE,
        body,
        idempotency_key,
        dataset_id=body.dataset_id,
        check_options=check,
        make_params=lambda dataset, robot, carried: CalibrationJobParams(
            dataset=dataset, robot=robot, options=body.options, discovery=carried
        ),
    )


def summary_verdict(job: Job) -> Verdict | None:
    """The verdict a succeeded calibration left in its job summary (None before)."""
    found = (job.summary or {}).get("verdict")
    return None if found is None else Verdict.model_validate(found)


def job_verdict(state: ServiceState, job: Job) -> Verdict | None:
    """The verdict of a succeeded calibration: from its job summary (from the result file for
    a job recorded before summaries existed)."""
    found = summary_verdict(job)
    return found if found is not None else result_of(state, job.tenant_id, job.id).verdict


def urdf_withheld(state: ServiceState, job: Job) -> str | None:
    """Why the URDF of a succeeded calibration is not served unless forced: its verdict is
    failed (the causes named)."""
    verdict = job_verdict(state, job)
    if verdict is None or verdict.status != "failed":
        return None
    causes = "; ".join(r.message for r in verdict.reasons if r.severity == "failed")
    return (
        f"the calibration's verdict is failed ({causes}); see verdict in its status or result, "
        "or get the URDF anyway with ?force=true"
    )


def urdf_absent(state: ServiceState, job: Job) -> str | None:
    """Why a succeeded calibration has no URDF: it corrects the joint readings."""
    result = result_of(state, job.tenant_id, job.id)
    return urdf_refusal(result.model_corrections, HTTP_URDF_FIX)


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
            "The calibrated robot as a plain URDF (409 for a calibration carrying joint "
            "corrections of a discovery, which a URDF cannot express, and for a calibration "
            "whose verdict is failed unless ?force=true).",
            download_suffix=".urdf",
            absent=urdf_absent,
            refusal=urdf_withheld,
            force_description="Serve the URDF of a calibration whose verdict is failed.",
        ),
    ],
)


@router.get(
    "/{calibration_id}/export",
    responses={
        200: {
            "content": {media: {} for media in sorted(set(exports.MEDIA_TYPES.values()))},
            "description": "The calibration in the chosen format.",
        },
        **STANDARD_PROBLEMS,
        **problem_responses(404, 409),
    },
    response_class=Response,
)
async def export_calibration(
    calibration_id: str,
    principal: PrincipalDep,
    state: StateDep,
    format: Annotated[
        exports.ExportFormat,
        Query(
            description="urdf (the robot's URDF, calibrated joint origins), offsets-yaml / "
            "offsets-csv (joint-offset table), dh / mdh (DH or modified-DH table), pal-master "
            "(PAL's master_calibration.yaml), ur-kinematics (Universal Robots' kinematics "
            "YAML); docs/exports.md."
        ),
    ] = "urdf",
    measurement_frame: Annotated[
        bool,
        Query(description="urdf, dh, mdh: add the measurement frame and marker."),
    ] = False,
    force: Annotated[
        bool, Query(description="Export even when the calibration's verdict is failed.")
    ] = False,
) -> Response:
    """A succeeded calibration in a format a robot controller uses; each reproduces kincal's
    calibrated forward kinematics where the format can express it (the X-Kincal-Not-Expressed
    header and the file say what it cannot). 409 for a failed verdict (unless ``force``) or a
    calibration carrying a discovery's joint corrections or of a robot the format cannot
    describe (ur-kinematics of an arm that is not a UR)."""

    def render() -> tuple[str, list[str]]:
        result = result_of(state, principal.tenant_id, calibration_id)
        verdict = result.verdict
        if verdict is not None and verdict.status == "failed" and not force:
            causes = "; ".join(r.message for r in verdict.reasons if r.severity == "failed")
            raise ProblemException(
                409,
                f"calibration {calibration_id}: its verdict is failed ({causes}); pass "
                "force=true to export it anyway",
                slug="no-export",
            )
        try:
            text = exports.export(result, format, measurement_frame=measurement_frame)
        except KincalError as exc:
            detail = f"calibration {calibration_id}: {exc}"
            raise ProblemException(409, detail, slug="no-export") from exc
        missing = exports.not_expressed(result) + exports.offsets_not_exact(result, format)
        return text, missing

    text, missing = await run_in_threadpool(render)
    headers = {
        "Content-Disposition": f'attachment; filename="{calibration_id}-{format}'
        f'{exports.SUFFIX[format]}"'
    }
    if missing:
        headers["X-Kincal-Not-Expressed"] = " | ".join(missing).encode("ascii", "replace").decode()
    return Response(text, media_type=exports.MEDIA_TYPES[format], headers=headers)
