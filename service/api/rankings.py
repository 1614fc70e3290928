"""Rankings: candidate configurations (or a target pose's IK solutions) ordered by the
task-weighted end-effector uncertainty a succeeded calibration predicts (paper Eq. 22–23).

Synchronous, and the planners' hot path. A calibration's result and the
:class:`solver.ranking.UncertaintyModel` built from it are cached per (tenant, calibration)
(:func:`service.api.calibrations.cached_calibration`), so after the first request a ranking
does no database query, file read or JSON parsing of the result. Scoring a few hundred
configurations takes well under a millisecond of numpy, less than a thread hop under load
costs, so it runs in the event loop; larger batches and inverse kinematics run in a worker
thread. The answer is serialised from plain data (:func:`service.app.rank.rank_configurations_json`:
the RankingResult's exact JSON without a pydantic model per entry). The common case — rows or
named configurations, a key verified recently, the calibration cached — does not even reach this
route: :mod:`service.api.ranking_fast_path` answers it with these functions, without FastAPI's
routing and dependency injection, and passes everything else on to the route.

Rankings change nothing, so a repeated request (with or without ``Idempotency-Key``) gets
the same answer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
import pydantic
from fastapi import APIRouter, Depends, Request, Response
from numpy.typing import NDArray
from starlette.concurrency import run_in_threadpool

from schemas.api import RankingCreate
from schemas.calibration import CalibrationResult
from schemas.ranking import CalibrationReference, RankingResult, TargetRankingRequest
from service.api.calibrations import cached_calibration
from service.api.deps import API_PREFIX, PrincipalDep, ServiceState, StateDep
from service.api.problems import (
    STANDARD_PROBLEMS,
    ProblemException,
    problem_responses,
    validation_detail,
    validation_errors,
)
from service.api.results import CachedResult
from service.app import rank as ranking
from solver.ranking import UncertaintyModel

PREFIX = f"{API_PREFIX}/rankings"
router = APIRouter(prefix=PREFIX, tags=["rankings"])

INLINE_MAX_CONFIGURATIONS = 512
"""Larger configuration batches are scored in a worker thread, off the event loop."""
INLINE_PARSE_BYTES = 64 * 1024
"""Larger bodies (a few hundred candidates and more) are parsed in a worker thread: a 4 MB body
takes ~50 ms to validate, which in the event loop would stall every other request."""
MEMO_KEY = "ranking_context"
PARSED_BODY = "kincal.ranking_body"
"""Scope state key of (body, RankingCreate) that the fast path parsed before passing the
request on (:mod:`service.api.ranking_fast_path`): the route does not parse it again."""


@dataclass(frozen=True)
class RankingContext:
    """What rankings derive from one calibration result, built once per cache entry."""

    result: CalibrationResult
    model: UncertaintyModel
    reference: CalibrationReference  # hashes the whole result: once, not per request

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.model.chain.joint_names


def _build_context(result: CalibrationResult) -> RankingContext:
    return RankingContext(
        result, ranking.uncertainty_model(result), ranking.calibration_reference(result)
    )


def _loaded_context(state: ServiceState, tenant_id: str, calibration_id: str) -> RankingContext:
    """Cache miss: read the result (database + file) and build the model (in a thread)."""
    entry = cached_calibration(state, tenant_id, calibration_id)
    _require_covariance(entry, calibration_id)
    return entry.memo(MEMO_KEY, _build_context)


def _require_covariance(entry: CachedResult, calibration_id: str) -> None:
    if entry.result.covariance is None:
        raise ProblemException(
            409,
            f"calibration {calibration_id} has no covariances, which rankings need; start a "
            "calibration with options.covariance 'diag' or 'full'",
            slug="no-covariance",
        )


def cached_context(
    state: ServiceState, tenant_id: str, calibration_id: str
) -> RankingContext | None:
    """The calibration's ranking context if it is in memory already (no I/O), else None."""
    entry = state.results.peek(tenant_id, calibration_id)
    if entry is not None and entry.has(MEMO_KEY):
        return entry.memo(MEMO_KEY, _build_context)
    return None


async def ranking_context(
    state: ServiceState, tenant_id: str, calibration_id: str
) -> RankingContext:
    """The calibration's ranking context; 404 (unknown or another tenant's), 409 (not
    succeeded, or without covariances)."""
    context = cached_context(state, tenant_id, calibration_id)
    if context is not None:
        return context
    return await run_in_threadpool(_loaded_context, state, tenant_id, calibration_id)


# --- candidates --------------------------------------------------------------------------------


def _invalid(detail: str, location: str, pointer: str) -> ProblemException:
    error = {"location": location, "pointer": pointer, "detail": detail}
    return ProblemException(
        422, f"{location}: {detail}", slug="invalid-configurations", errors=[error]
    )


def joint_matrix(body: RankingCreate, joint_names: tuple[str, ...]) -> NDArray[np.float64]:
    """The candidates as an (N, k) array in chain order; 422 naming the first bad row."""
    k = len(joint_names)
    expected = ", ".join(joint_names)
    if body.joint_positions_rad is not None:
        for i, row in enumerate(body.joint_positions_rad):
            if len(row) != k:
                raise _invalid(
                    f"row {i} has {len(row)} joint positions; this calibration's chain has "
                    f"{k} ({expected})",
                    f"body.joint_positions_rad.{i}",
                    f"#/joint_positions_rad/{i}",
                )
        return np.array(body.joint_positions_rad, dtype=float).reshape(-1, k)
    assert body.configurations is not None
    known = set(joint_names)
    for i, named in enumerate(body.configurations):
        unknown = sorted(set(named) - known)
        missing = [name for name in joint_names if name not in named]
        if unknown or missing:
            problems = []
            if unknown:
                problems.append(f"unknown joint(s) {', '.join(unknown)}")
            if missing:
                problems.append(f"missing joint(s) {', '.join(missing)}")
            raise _invalid(
                f"configuration {i}: {'; '.join(problems)}; the chain's joints are {expected}",
                f"body.configurations.{i}",
                f"#/configurations/{i}",
            )
    return np.array([[named[name] for name in joint_names] for named in body.configurations])


def count_candidates(body: RankingCreate) -> int:
    if body.joint_positions_rad is not None:
        return len(body.joint_positions_rad)
    if body.configurations is not None:
        return len(body.configurations)
    return body.n_candidates


def check_limits(body: RankingCreate, limit: int) -> None:
    n = count_candidates(body)
    if n > limit:
        raise ProblemException(
            413,
            f"{n} candidate configurations is more than the limit of {limit} per request; "
            "split them over several requests or ask the operator to raise "
            "KINCAL_MAX_RANKING_CANDIDATES",
            slug="too-many-candidates",
        )
    if isinstance(body.payload_kg, list) and len(body.payload_kg) != n:
        raise ProblemException(
            422,
            f"payload_kg: {len(body.payload_kg)} values for {n} configurations; give one "
            "value, or one per configuration",
            slug="invalid-request",
        )


def _payload(body: RankingCreate) -> NDArray[np.float64] | float | None:
    if isinstance(body.payload_kg, list):
        return np.array(body.payload_kg, dtype=float)
    return body.payload_kg


def rank_configurations(context: RankingContext, body: RankingCreate) -> bytes:
    q = joint_matrix(body, context.joint_names)
    try:
        return ranking.rank_configurations_json(
            context.result,
            q,
            body.options,
            payload_kg=_payload(body),
            model=context.model,
            reference=context.reference,
            require_finite=True,
        )
    except ranking.NonFiniteScoreError as exc:
        raise _non_finite(exc) from exc


def _non_finite(exc: ranking.NonFiniteScoreError) -> ProblemException:
    """Extreme (finite) inputs can overflow the covariance arithmetic; answer 422, never NaN."""
    return ProblemException(
        422,
        f"the predicted uncertainty of candidate {exc.index} is not a finite number; "
        "check joint positions (rad), payload_kg and options.weights for extreme values",
        slug="invalid-configurations",
    )


def _rank_target(context: RankingContext, body: RankingCreate) -> RankingResult:
    payload = body.payload_kg if isinstance(body.payload_kg, float) else None
    request = TargetRankingRequest(
        target=body.target,  # type: ignore[arg-type]  # checked by RankingCreate
        n_candidates=body.n_candidates,
        seed=body.seed,
        free_axis=body.free_axis,
        n_free_rotations=body.n_free_rotations,
        payload_kg=context.result.options.payload_kg if payload is None else payload,
        options=body.options,
    )
    try:
        out = ranking.rank_target(
            context.result,
            request,
            model=context.model,
            reference=context.reference,
            require_finite=True,
        )
    except ranking.NonFiniteScoreError as exc:
        raise _non_finite(exc) from exc
    if not out.ranking:
        raise ProblemException(
            422,
            f"target: {ranking.NO_IK_SOLUTION.replace('(--free-axis)', '(free_axis)')}",
            slug="no-ik-solution",
            errors=[{"location": "body.target", "pointer": "#/target", "detail": "unreachable"}],
        )
    return out


def _inline_refs(schema: Any, definitions: dict[str, Any] | None = None) -> Any:
    """A pydantic JSON schema with its ``$defs`` substituted in place, so that it can stand
    alone in an OpenAPI ``requestBody`` (the models it uses are not recursive)."""
    if definitions is None and isinstance(schema, dict):
        definitions = schema.get("$defs", {})
    if isinstance(schema, dict):
        if "$ref" in schema:
            assert definitions is not None
            target = _inline_refs(definitions[schema["$ref"].rsplit("/", 1)[-1]], definitions)
            return {**target, **{k: v for k, v in schema.items() if k != "$ref"}}
        return {k: _inline_refs(v, definitions) for k, v in schema.items() if k != "$defs"}
    if isinstance(schema, list):
        return [_inline_refs(item, definitions) for item in schema]
    return schema


_REQUEST_BODY = {
    "required": True,
    "content": {"application/json": {"schema": _inline_refs(RankingCreate.model_json_schema())}},
}


async def ranking_request(request: Request) -> RankingCreate:
    """The body, parsed and validated by pydantic-core in one pass: several times faster than
    FastAPI's ``json.loads`` + validation for a few hundred numbers (a fifth of the event
    loop's time under load). Same 422 problems, naming each field. The body's size was checked
    against KINCAL_MAX_RANKING_REQUEST_BYTES before it was read (middleware)."""
    media = request.headers.get("content-type", "application/json").split(";")[0].strip()
    if media.lower() != "application/json" and not media.lower().endswith("+json"):
        raise ProblemException(
            415,
            f"Content-Type {media or '(none)'} is not accepted; send the ranking request as "
            "application/json (see /docs)",
            slug="unsupported-media-type",
        )
    body = await request.body()
    parsed = request.scope.get("state", {}).get(PARSED_BODY)
    if parsed is not None and parsed[0] == body:
        return parsed[1]  # type: ignore[no-any-return]
    try:
        if len(body) <= INLINE_PARSE_BYTES:
            return RankingCreate.model_validate_json(body)
        return await run_in_threadpool(RankingCreate.model_validate_json, body)
    except pydantic.ValidationError as exc:
        errors = validation_errors(exc.errors(include_url=False), ("body",))
        raise ProblemException(
            422,
            validation_detail(errors),
            slug="invalid-request",
            errors=errors,
        ) from exc


RankingBodyDep = Annotated[RankingCreate, Depends(ranking_request)]


@router.post(
    "",
    response_model=RankingResult,
    responses={**STANDARD_PROBLEMS, **problem_responses(404, 409, 413, 415)},
    openapi_extra={"requestBody": _REQUEST_BODY},
)
async def create_ranking(
    body: RankingBodyDep, principal: PrincipalDep, state: StateDep
) -> Response:
    """Rank candidate configurations best first (kincal.ranking/1); synchronous."""
    check_limits(body, state.settings.max_ranking_candidates)
    context = await ranking_context(state, principal.tenant_id, body.calibration_id)
    if body.target is not None:
        target = await run_in_threadpool(_rank_target, context, body)
        content = target.model_dump_json().encode()
    elif count_candidates(body) <= INLINE_MAX_CONFIGURATIONS:
        content = rank_configurations(context, body)
    else:
        content = await run_in_threadpool(rank_configurations, context, body)
    return Response(content, media_type="application/json")
