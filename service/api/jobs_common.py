"""What every job-backed resource (calibrations, discoveries, ...) shares: submit, look up,
status, artifacts, cancel, and :func:`add_job_routes`, which gives a resource its list, status,
artifact and cancel routes. A new job resource is a POST route plus one call to it.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, TypeVar

from fastapi import APIRouter, Header, Path, Query, Response
from pydantic import BaseModel
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from schemas.api import JobStatus
from schemas.robots import RobotDescription
from service.api.deps import PrincipalDep, ServiceState, StateDep
from service.api.idempotency import IDEMPOTENCY_PROBLEMS, Idempotency, fingerprint
from service.api.problems import STANDARD_PROBLEMS, ProblemException, problem_responses
from service.api.robots import ResolvedRobot, one_line, resolve_robot
from service.app.job_params import DatasetRef, RobotRef
from service.storage import repository
from service.storage.models import Job
from solver.errors import ModelError

RETRY_AFTER_S = "1"
CheckedT = TypeVar("CheckedT")


def submit_job(
    state: ServiceState,
    tenant_id: str,
    kind: str,
    params: dict[str, Any],
    *,
    dataset_id: str | None = None,
) -> Job:
    """Persist a queued job (durable from here on) and wake the workers."""
    job = Job(
        id=repository.new_id(state.registry[kind].id_prefix),
        tenant_id=tenant_id,
        kind=kind,
        dataset_id=dataset_id,
        params=params,
        state=repository.QUEUED,
        stage="queued",
        fraction=0.0,
        attempts=0,
        cancel_requested=False,
        artifacts={},
    )
    with state.database.session() as session:
        session.add(job)
    state.runner.notify()
    return job


def dataset_for_job(
    state: ServiceState, tenant_id: str, dataset_id: str
) -> tuple[DatasetRef, ResolvedRobot]:
    """A job's input: the tenant's dataset (404 naming ``dataset_id`` otherwise) and its robot."""
    with state.database.sessions() as session:
        dataset = repository.get_dataset(session, tenant_id, dataset_id)
        if dataset is None:
            raise ProblemException(
                404,
                f"dataset_id: dataset {dataset_id!r} not found; upload it with "
                "POST /api/v1/datasets or list yours with GET /api/v1/datasets",
                slug="not-found",
            )
        robot = resolve_robot(
            state,
            session,
            tenant_id,
            dataset.robot_id or dataset.robot,
            dataset.base_frame,
            dataset.tip_frame,
        )
    return DatasetRef(id=dataset.id, name=dataset.name, data_path=dataset.data_path), robot


def accept_dataset_job(
    state: ServiceState,
    tenant_id: str,
    resource: JobResource,
    request: BaseModel,
    idempotency_key: str | None,
    *,
    dataset_id: str,
    check_options: Callable[[RobotDescription], CheckedT],
    make_params: Callable[[DatasetRef, RobotRef, CheckedT], BaseModel],
) -> Response:
    """The POST of a job on a stored dataset: 202 + Location (the same answer again for a
    repeated ``Idempotency-Key``), 404 for a dataset the tenant does not have, 422 when
    ``check_options`` finds options naming joints the robot lacks (now, rather than a failed
    job later; it may raise its own problems too). ``make_params`` gets what it returned."""
    idempotency = Idempotency(state.database, tenant_id, idempotency_key, f"POST {resource.prefix}")

    def create() -> Response:
        dataset, robot = dataset_for_job(state, tenant_id, dataset_id)
        try:
            checked = check_options(robot.description)
        except ModelError as exc:
            raise ProblemException(
                422, f"options: {one_line(exc)}", slug="invalid-options"
            ) from exc
        params = make_params(dataset, robot.ref, checked)
        job = submit_job(
            state, tenant_id, resource.kind, params.model_dump(mode="json"), dataset_id=dataset.id
        )
        return resource.accepted(job)

    return idempotency.run(lambda: fingerprint(request.model_dump(mode="json")), create)


def job_or_404(session: Session, tenant_id: str, kind: str, job_id: str, noun: str) -> Job:
    job = repository.get_job(session, tenant_id, kind, job_id)
    if job is None:
        raise ProblemException(404, f"{noun} {job_id!r} not found", slug="not-found")
    return job


def job_status(job: Job) -> JobStatus:
    return JobStatus(
        state=job.state,  # type: ignore[arg-type]
        stage=job.stage,
        fraction=job.fraction,
        iteration=job.iteration,
        attempts=job.attempts,
        cancel_requested=job.cancel_requested,
        error=job.error,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
    )


def poll_headers(job: Job) -> dict[str, str]:
    return {"Retry-After": RETRY_AFTER_S} if job.state in repository.ACTIVE_STATES else {}


def artifact(
    state: ServiceState,
    job: Job,
    name: str,
    noun: str,
    absent: Callable[[ServiceState, Job], str | None] | None = None,
    refusal: Callable[[ServiceState, Job], str | None] | None = None,
) -> bytes:
    """A succeeded job's artifact; 409 (with the state and what to do) otherwise, when
    ``absent`` says why a succeeded job has none, or when ``refusal`` says why it is not
    served (unless the caller forced it: ``refusal`` None)."""
    if job.state != repository.SUCCEEDED:
        if job.state in repository.ACTIVE_STATES:
            detail = (
                f"{noun} {job.id} is {job.state} (stage {job.stage}, {job.fraction:.0%}); poll "
                "its status until state is 'succeeded'"
            )
        elif job.state == repository.FAILED:
            detail = f"{noun} {job.id} failed: {job.error}"
        else:
            detail = f"{noun} {job.id} was cancelled; start a new one"
        raise ProblemException(409, detail, slug="not-ready", headers=poll_headers(job) or None)
    refused = None if refusal is None else refusal(state, job)
    if refused is not None:
        raise ProblemException(409, f"{noun} {job.id}: {refused}", slug="refused-" + name)
    if name not in job.artifacts:
        reason = None if absent is None else absent(state, job)
        if reason is not None:
            raise ProblemException(409, f"{noun} {job.id}: {reason}", slug="no-" + name)
        raise ProblemException(404, f"{noun} {job.id} has no {name}", slug="not-found")
    return state.files.read(job.artifacts[name])


def cancel(state: ServiceState, job: Job, noun: str) -> tuple[Job, int]:
    """Cancel a queued or running job: (current job row, HTTP status 200 or 202)."""
    if job.state in repository.TERMINAL_STATES:
        raise ProblemException(
            409, f"{noun} {job.id} already {job.state}; nothing to cancel", slug="not-cancellable"
        )
    with state.database.session() as session:
        if repository.cancel_queued_job(session, job.id):
            status = 200
        else:
            repository.request_cancel(session, job.id)
            status = 202
    if status == 202:
        state.runner.cancel(job.id)
    with state.database.sessions() as session:
        current = session.get(Job, job.id)
        assert current is not None
    if current.state == repository.CANCELLED:
        status = 200
    return current, status


def json_response(
    body: str, status: int, *, location: str | None = None, headers: dict[str, str] | None = None
) -> Response:
    extra = dict(headers or {})
    if location:
        extra["Location"] = location
    return Response(body, status_code=status, media_type="application/json", headers=extra)


# --- routes shared by every job resource ------------------------------------------------------


@dataclass(frozen=True)
class Artifact:
    """A file a succeeded job serves at ``GET <prefix>/{id}/<name>``."""

    name: str
    media_type: str
    summary: str
    headers: Mapping[str, str] = field(default_factory=dict)
    download_suffix: str | None = None  # set: served as an attachment "<id><suffix>"
    # Why a succeeded job has none (answered as 409), or None (404): a job may skip an artifact.
    absent: Callable[[ServiceState, Job], str | None] | None = None
    # Why a succeeded job's artifact is withheld (409) unless asked for with ?force=true.
    refusal: Callable[[ServiceState, Job], str | None] | None = None
    force_description: str = "Serve it even though the job's result says it should not be used."


@dataclass(frozen=True)
class JobResource:
    """A job kind exposed over HTTP (``/calibrations``, ``/discoveries``, ...)."""

    kind: str
    noun: str
    prefix: str
    public_model: type[BaseModel]
    page_model: type[BaseModel]
    to_public: Callable[[Job], BaseModel]

    def accepted(self, job: Job) -> Response:
        """202 with the new job and its Location."""
        return json_response(
            self.to_public(job).model_dump_json(),
            202,
            location=f"{self.prefix}/{job.id}",
            headers=poll_headers(job),
        )

    def lookup(self, state: ServiceState, tenant_id: str, job_id: str) -> Job:
        with state.database.sessions() as session:
            return job_or_404(session, tenant_id, self.kind, job_id, self.noun)

    def artifact(
        self,
        state: ServiceState,
        tenant_id: str,
        job_id: str,
        name: str,
        absent: Callable[[ServiceState, Job], str | None] | None = None,
        refusal: Callable[[ServiceState, Job], str | None] | None = None,
    ) -> bytes:
        job = self.lookup(state, tenant_id, job_id)
        return artifact(state, job, name, self.noun, absent, refusal)


def add_job_routes(router: APIRouter, resource: JobResource, artifacts: Sequence[Artifact]) -> None:
    """Add list, status, one GET per artifact and cancel to ``router`` (whose prefix is
    ``resource.prefix``). Polled routes are async with one thread hop for the database."""
    noun, kind = resource.noun, resource.kind
    # A default value, not an Annotated alias: annotations are strings here (PEP 563) and
    # FastAPI resolves them in the module namespace, where a local alias does not exist.
    id_path: Any = Path(alias=f"{noun}_id", description=f"The {noun} id.")
    idempotency_header: Any = Header(None, alias="Idempotency-Key")
    not_found = {**STANDARD_PROBLEMS, **problem_responses(404)}

    def list_jobs(
        principal: PrincipalDep,
        state: StateDep,
        offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
        limit: Annotated[int, Query(ge=1, le=200)] = 50,
    ) -> BaseModel:
        with state.database.sessions() as session:
            jobs, count = repository.list_jobs(
                session, principal.tenant_id, kind, offset=offset, limit=limit
            )
            data = [resource.to_public(j) for j in jobs]
        return resource.page_model(data=data, count=count, offset=offset, limit=limit)

    async def get_job(
        principal: PrincipalDep, state: StateDep, response: Response, job_id: str = id_path
    ) -> BaseModel:
        job = await run_in_threadpool(resource.lookup, state, principal.tenant_id, job_id)
        response.headers.update(poll_headers(job))
        return resource.to_public(job)

    def cancel_job(
        principal: PrincipalDep,
        state: StateDep,
        job_id: str = id_path,
        idempotency_key: str | None = idempotency_header,
    ) -> Response:
        def produce() -> Response:
            job = resource.lookup(state, principal.tenant_id, job_id)
            current, status = cancel(state, job, noun)
            return json_response(resource.to_public(current).model_dump_json(), status)

        scope = f"POST {resource.prefix}/{{id}}/cancel"
        idempotency = Idempotency(state.database, principal.tenant_id, idempotency_key, scope)
        return idempotency.run(lambda: job_id, produce)

    router.add_api_route(
        "",
        list_jobs,
        methods=["GET"],
        response_model=resource.page_model,
        responses=STANDARD_PROBLEMS,
        name=f"list_{kind}s",
        summary=f"This tenant's {noun}s, newest first.",
    )
    router.add_api_route(
        f"/{{{noun}_id}}",
        get_job,
        methods=["GET"],
        response_model=resource.public_model,
        responses=not_found,
        name=f"get_{kind}",
        summary="Status and progress (state, stage, fraction, iteration).",
    )
    for item in artifacts:
        router.add_api_route(
            f"/{{{noun}_id}}/{item.name}",
            _artifact_endpoint(resource, item),
            methods=["GET"],
            response_class=Response,
            responses={
                200: {"content": {item.media_type: {}}, "description": item.summary},
                **not_found,
                **problem_responses(409),
            },
            name=f"get_{kind}_{item.name}",
            summary=item.summary,
        )
    router.add_api_route(
        f"/{{{noun}_id}}/cancel",
        cancel_job,
        methods=["POST"],
        response_model=resource.public_model,
        responses={
            202: {"model": resource.public_model, "description": "Cancellation under way."},
            **not_found,
            **IDEMPOTENCY_PROBLEMS,
        },
        name=f"cancel_{kind}",
        summary=f"Cancel a queued or running {noun}.",
    )


def _artifact_endpoint(resource: JobResource, item: Artifact) -> Callable[..., Awaitable[Response]]:
    id_path: Any = Path(alias=f"{resource.noun}_id", description=f"The {resource.noun} id.")

    async def serve(tenant_id: str, state: ServiceState, job_id: str, force: bool) -> Response:
        refusal = None if force else item.refusal
        body = await run_in_threadpool(
            resource.artifact, state, tenant_id, job_id, item.name, item.absent, refusal
        )
        headers = dict(item.headers)
        if item.download_suffix:
            filename = f"{job_id}{item.download_suffix}"
            headers["Content-Disposition"] = f'attachment; filename="{filename}"'
        return Response(body, media_type=item.media_type, headers=headers)

    if item.refusal is None:

        async def get_artifact(
            principal: PrincipalDep, state: StateDep, job_id: str = id_path
        ) -> Response:
            return await serve(principal.tenant_id, state, job_id, False)

        return get_artifact
    force_query: Any = Query(False, description=item.force_description)

    async def get_forcible_artifact(
        principal: PrincipalDep, state: StateDep, job_id: str = id_path, force: bool = force_query
    ) -> Response:
        return await serve(principal.tenant_id, state, job_id, force)

    return get_forcible_artifact
