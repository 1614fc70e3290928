"""Checks: is a succeeded calibration still valid? New poses (an uploaded dataset) tested
against its total predictive covariance (``kincal check``, :func:`service.app.check.run_check`).

A check of ten poses takes well under a second, so POST runs it in a worker thread and answers
201 with the stored check (its ``kincal.check/1`` document); the row is committed before the
answer, so a check that was answered is never lost. Checks are kept with their time in the
``checks`` table (the document in the tenant's folder) and listed per calibration, newest
first. ``GET .../checks/report`` is their HTML page (:mod:`service.render.checks_html`).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Path, Query, Response
from starlette.concurrency import run_in_threadpool

from schemas.api import CheckCreate, CheckLinks, CheckPublic, ChecksPublic, CheckSummary
from schemas.check import CheckResult
from service.api.calibrations import PREFIX as CALIBRATIONS
from service.api.calibrations import REPORT_HEADERS, cached_calibration
from service.api.deps import API_PREFIX, PrincipalDep, ServiceState, StateDep
from service.api.idempotency import IDEMPOTENCY_PROBLEMS, Idempotency, fingerprint
from service.api.jobs_common import job_or_404, json_response
from service.api.problems import STANDARD_PROBLEMS, ProblemException, problem_responses
from service.render.checks_html import CheckEntry, render_checks_page
from service.storage import repository
from service.storage.files import tenant_path
from service.storage.models import Check
from solver.errors import KincalError

router = APIRouter(prefix=CALIBRATIONS, tags=["checks"])
DATASETS = f"{API_PREFIX}/datasets"
HTTP_RECALIBRATE_FIX = (
    f"start a new calibration of its dataset (POST {CALIBRATIONS}) with options.covariance "
    "'diag' and options.heldout true (both the defaults)"
)

MAX_CHECK_POSES = 200
"""A check is a few new poses (ten is typical); its joint covariance grows with the square of
their number (200 poses of 6 rows: a 1200 × 1200 matrix, a few seconds), so a larger dataset
is refused rather than left to tie up a request thread and its memory."""

REPORT_CHECKS = 200
"""The HTML page shows a calibration's newest 200 checks (and says how many it has)."""

CalibrationId = Annotated[str, Path(description="The calibration id.")]
CheckId = Annotated[str, Path(description="The check id.")]


def checks_url(calibration_id: str) -> str:
    return f"{CALIBRATIONS}/{calibration_id}/checks"


def summary(row: Check) -> CheckSummary:
    return CheckSummary(
        id=row.id,
        calibration_id=row.calibration_id,
        dataset_id=row.dataset_id,
        dataset_name=row.dataset_name,
        created_at=row.created_at,
        level=row.level,
        n_poses=row.n_poses,
        verdict=row.verdict,  # type: ignore[arg-type]
        statistic=row.statistic,
        threshold=row.threshold,
        located=row.located,
        links=CheckLinks(
            self=f"{checks_url(row.calibration_id)}/{row.id}",
            calibration=f"{CALIBRATIONS}/{row.calibration_id}",
            dataset=f"{DATASETS}/{row.dataset_id}",
        ),
    )


def public(row: Check, document: CheckResult) -> CheckPublic:
    return CheckPublic(**summary(row).model_dump(), check=document)


def invalid_dataset(detail: str) -> ProblemException:
    """422 naming ``dataset_id``: a recording the calibration cannot be checked with."""
    error = {"location": "body.dataset_id", "pointer": "#/dataset_id", "detail": detail}
    return ProblemException(
        422, f"dataset_id: {detail}", slug="invalid-check-dataset", errors=[error]
    )


def run(state: ServiceState, tenant_id: str, calibration_id: str, body: CheckCreate) -> CheckPublic:
    """Check the calibration against the dataset and store the check (committed on return).
    In a worker thread; the check's maths is imported by the first check a request process
    answers, not when it starts."""
    from service.app import check as checking

    result = cached_calibration(state, tenant_id, calibration_id).result  # 404, 409
    result_name = f"calibration {calibration_id}"
    try:
        checking.refuse_unsupported(result, result_name)
    except KincalError as exc:
        detail = str(exc).replace(checking.RECALIBRATE_FIX, HTTP_RECALIBRATE_FIX)
        raise ProblemException(409, detail, slug="not-checkable") from exc
    with state.database.sessions() as session:
        dataset = repository.get_dataset(session, tenant_id, body.dataset_id)
    if dataset is None:
        raise ProblemException(
            404,
            f"dataset_id: dataset {body.dataset_id!r} not found; upload the check poses with "
            f"POST {DATASETS} or list yours with GET {DATASETS}",
            slug="not-found",
        )
    if dataset.n_samples > MAX_CHECK_POSES:
        raise invalid_dataset(
            f"dataset {dataset.id} holds {dataset.n_samples} poses, more than the "
            f"{MAX_CHECK_POSES} a check takes; a check is a few new poses (ten is typical): "
            "upload a subset of them"
        )
    try:
        document = checking.run_check(
            result,
            state.files.path(dataset.data_path),
            level=body.options.level,
            result_name=result_name,
            source_name=dataset.name,
        )
    except KincalError as exc:
        if not state.files.exists(dataset.data_path):  # deleted since it was looked up
            raise ProblemException(
                404, f"dataset_id: dataset {dataset.id} was deleted", slug="not-found"
            ) from exc
        raise invalid_dataset(str(exc)) from exc
    check_id = repository.new_id("chk")
    path = state.files.write(
        tenant_path(tenant_id, "checks", f"{check_id}.json"),
        document.model_dump_json(indent=1).encode(),
    )
    located = document.located
    row = Check(
        id=check_id,
        tenant_id=tenant_id,
        calibration_id=calibration_id,
        dataset_id=dataset.id,
        dataset_name=dataset.name,
        level=document.level,
        n_poses=len(document.poses),
        verdict=document.verdict,
        statistic=None if document.global_test is None else document.global_test.statistic,
        threshold=None if document.global_test is None else document.global_test.threshold,
        located=None if located is None else located.name[:200],
        document_path=path,
    )
    with state.database.session() as session:
        session.add(row)
    return public(row, document)


@router.post(
    "/{calibration_id}/checks",
    status_code=201,
    response_model=CheckPublic,
    responses={**STANDARD_PROBLEMS, **IDEMPOTENCY_PROBLEMS, **problem_responses(404, 409)},
)
async def create_check(
    calibration_id: CalibrationId,
    body: CheckCreate,
    principal: PrincipalDep,
    state: StateDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> Response:
    """Test the calibration against new poses (kincal.check/1): holds, drifted (the change
    located and sized) or inconclusive; stored with its time. Synchronous."""

    def produce() -> Response:
        check = run(state, principal.tenant_id, calibration_id, body)
        return json_response(check.model_dump_json(), 201, location=check.links.self)

    def request_fingerprint() -> str:
        return fingerprint(calibration_id, body.model_dump(mode="json"))

    def answer() -> Response:
        scope = f"POST {CALIBRATIONS}/{{id}}/checks"
        idempotency = Idempotency(state.database, principal.tenant_id, idempotency_key, scope)
        return idempotency.run(request_fingerprint, produce)

    return await run_in_threadpool(answer)


@router.get(
    "/{calibration_id}/checks",
    response_model=ChecksPublic,
    responses={**STANDARD_PROBLEMS, **problem_responses(404)},
)
async def list_checks(
    calibration_id: CalibrationId,
    principal: PrincipalDep,
    state: StateDep,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
) -> ChecksPublic:
    """The calibration's checks, newest first: time, verdict, statistic and threshold."""

    def page() -> ChecksPublic:
        with state.database.sessions() as session:
            job_or_404(session, principal.tenant_id, "calibration", calibration_id, "calibration")
            rows, count = repository.list_checks(
                session, principal.tenant_id, calibration_id, offset=offset, limit=limit
            )
        return ChecksPublic(
            data=[summary(row) for row in rows], count=count, offset=offset, limit=limit
        )

    return await run_in_threadpool(page)


def page_entry(state: ServiceState, row: Check) -> CheckEntry:
    """The row, and for a located drift the located change of its document (its size)."""
    if row.located is None:
        return CheckEntry(summary(row))
    document = CheckResult.model_validate_json(state.files.read(row.document_path))
    return CheckEntry(summary(row), document.located)


# Named "report" like a calibration's and a discovery's HTML; registered before
# /{check_id}, which it would otherwise match (check ids all start with "chk_").
@router.get(
    "/{calibration_id}/checks/report",
    response_class=Response,
    responses={
        200: {
            "content": {"text/html; charset=utf-8": {}},
            "description": "A self-contained HTML page (no scripts, no external resources).",
        },
        **STANDARD_PROBLEMS,
        **problem_responses(404),
    },
)
async def checks_report(
    calibration_id: CalibrationId, principal: PrincipalDep, state: StateDep
) -> Response:
    """HTML page of the calibration's checks over time: each check's statistic against its
    threshold, the drifts and the changes located."""

    def page() -> bytes:
        with state.database.sessions() as session:
            job_or_404(session, principal.tenant_id, "calibration", calibration_id, "calibration")
            rows, count = repository.list_checks(
                session, principal.tenant_id, calibration_id, offset=0, limit=REPORT_CHECKS
            )
        how_to_check = (
            f"To check it, POST {checks_url(calibration_id)} with the dataset_id of a few new "
            f"poses (upload them with POST {DATASETS})."
        )
        entries = [page_entry(state, row) for row in rows]
        return render_checks_page(
            calibration_id, entries, count=count, how_to_check=how_to_check
        ).encode()

    body = await run_in_threadpool(page)
    return Response(body, media_type="text/html; charset=utf-8", headers=REPORT_HEADERS)


@router.get(
    "/{calibration_id}/checks/{check_id}",
    response_model=CheckPublic,
    responses={**STANDARD_PROBLEMS, **problem_responses(404)},
)
async def get_check(
    calibration_id: CalibrationId, check_id: CheckId, principal: PrincipalDep, state: StateDep
) -> Response:
    """One check with its document (kincal.check/1) and time."""

    def one() -> Response:
        with state.database.sessions() as session:
            row = repository.get_check(session, principal.tenant_id, calibration_id, check_id)
        if row is None:
            raise ProblemException(
                404,
                f"check {check_id!r} of calibration {calibration_id!r} not found; list them "
                f"with GET {checks_url(calibration_id)}",
                slug="not-found",
            )
        document = CheckResult.model_validate_json(state.files.read(row.document_path))
        return json_response(public(row, document).model_dump_json(), 200)

    return await run_in_threadpool(one)
