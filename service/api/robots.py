"""Robots: the built-in ones, and URDFs uploaded by a tenant (validated, size-limited, stored)."""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Header, Response
from sqlalchemy.orm import Session

from schemas.api import RobotCreate, RobotPublic, RobotsPublic
from schemas.robots import BUILTIN_ROBOTS, RobotDescription, load_robot
from schemas.urdf_outline import UrdfLimitError, check_urdf_limits
from service.api.deps import API_PREFIX, PrincipalDep, SessionDep, StateDep
from service.api.idempotency import IDEMPOTENCY_PROBLEMS, Idempotency, fingerprint
from service.api.problems import STANDARD_PROBLEMS, ProblemException, problem_responses
from service.app.job_params import RobotRef
from service.jobs.isolated import IsolatedFailure, run_isolated
from service.settings import Settings
from service.storage import repository
from service.storage.files import tenant_path
from service.storage.models import Robot
from solver.errors import ModelError
from solver.model import KinematicChain, build_chain

router = APIRouter(prefix=f"{API_PREFIX}/robots", tags=["robots"])


@dataclass(frozen=True)
class ResolvedRobot:
    """A robot reference, its URDF and its (default-option) chain."""

    ref: RobotRef
    description: RobotDescription
    chain: KinematicChain


@functools.lru_cache(maxsize=32)
def _chain(
    urdf_xml: str, base_frame: str, tip_frame: str, max_urdf_joints: int, max_chain_joints: int
) -> KinematicChain:
    """The chain of a URDF that passed :func:`validate_urdf` (or a built-in), its size checked
    on the XML again (the frames may differ from the upload's) before Pinocchio builds it."""
    check_urdf_limits(
        urdf_xml,
        base_frame,
        tip_frame,
        max_urdf_joints=max_urdf_joints,
        max_chain_joints=max_chain_joints,
    )
    return build_chain(urdf_xml, base_frame, tip_frame)


def settings_chain(
    settings: Settings, urdf_xml: str, base_frame: str, tip_frame: str
) -> KinematicChain:
    return _chain(urdf_xml, base_frame, tip_frame, settings.max_urdf_joints, settings.max_joints)


def _chain_summary(urdf_xml: str, base_frame: str, tip_frame: str) -> tuple[list[str], str]:
    """Runs in an isolated process: Pinocchio parses the uploaded URDF there."""
    chain = build_chain(urdf_xml, base_frame, tip_frame)
    return list(chain.joint_names), chain.urdf_sha256


@functools.lru_cache(maxsize=16)
def _builtin(name: str, base_frame: str | None, tip_frame: str | None) -> RobotDescription:
    return load_robot(name, base_frame=base_frame, tip_frame=tip_frame)


def one_line(exc: Exception, limit: int = 600) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def model_problem(exc: ModelError, prefix: str) -> ProblemException:
    """422 for a robot model that cannot be built; ``too-many-joints`` for a size limit."""
    if isinstance(exc, UrdfLimitError):
        return ProblemException(422, one_line(exc), slug="too-many-joints")
    return ProblemException(422, f"{prefix}{one_line(exc)}", slug="invalid-robot-model")


def resolve_robot(
    state: StateDep,
    session: Session,
    tenant_id: str,
    robot: str,
    base_frame: str | None = None,
    tip_frame: str | None = None,
) -> ResolvedRobot:
    """A built-in name or an uploaded robot id of ``tenant_id`` -> URDF + chain; 422 otherwise."""
    if robot in BUILTIN_ROBOTS:
        description = _builtin(robot, base_frame, tip_frame)
        ref = RobotRef(
            name=robot, base_frame=description.base_frame, tip_frame=description.tip_frame
        )
    else:
        row = repository.get_robot(session, tenant_id, robot)
        if row is None:
            raise ProblemException(
                422,
                f"robot: unknown robot {robot!r}; use a built-in name "
                f"({', '.join(BUILTIN_ROBOTS)}) or the id of a robot uploaded with "
                "POST /api/v1/robots",
                slug="unknown-robot",
            )
        xml = state.files.read(row.urdf_path).decode("utf-8")
        ref = RobotRef(
            name=row.name,
            robot_id=row.id,
            urdf_path=row.urdf_path,
            base_frame=base_frame or row.base_frame,
            tip_frame=tip_frame or row.tip_frame,
        )
        description = RobotDescription(row.name, xml, ref.base_frame, ref.tip_frame)
    try:
        chain = settings_chain(
            state.settings, description.urdf_xml, description.base_frame, description.tip_frame
        )
    except ModelError as exc:
        raise model_problem(exc, f"robot {robot!r}: ") from exc
    return ResolvedRobot(ref, description, chain)


@functools.lru_cache(maxsize=8)
def _builtin_public(name: str) -> RobotPublic:
    description = _builtin(name, None, None)
    chain = build_chain(description.urdf_xml, description.base_frame, description.tip_frame)
    return RobotPublic(
        id=name,
        name=name,
        builtin=True,
        base_frame=description.base_frame,
        tip_frame=description.tip_frame,
        joint_names=list(chain.joint_names),
        urdf_sha256=chain.urdf_sha256,
    )


def _public(row: Robot) -> RobotPublic:
    return RobotPublic(
        id=row.id,
        name=row.name,
        builtin=False,
        base_frame=row.base_frame,
        tip_frame=row.tip_frame,
        joint_names=row.joint_names,
        urdf_sha256=row.urdf_sha256,
        created_at=row.created_at,
    )


def validate_urdf(body: RobotCreate, settings: Settings) -> tuple[list[str], str]:
    """An uploaded URDF's chain joint names and SHA-256: size limit, then a streaming safe XML
    parse counting its joints and the chain's, then Pinocchio in an isolated process (a URDF
    that crashes or exhausts it is refused; the service goes on)."""
    size = len(body.urdf.encode("utf-8"))
    if size > settings.max_urdf_bytes:
        raise ProblemException(
            413,
            f"urdf: {size} bytes is more than the limit of {settings.max_urdf_bytes} bytes; strip "
            "meshes, comments and unused links",
            slug="urdf-too-large",
        )
    try:
        outline = check_urdf_limits(
            body.urdf,
            body.base_frame,
            body.tip_frame,
            max_urdf_joints=settings.max_urdf_joints,
            max_chain_joints=settings.max_joints,
        )
        if outline.n_joints == 0:
            raise ModelError("urdf: the robot has no <joint>; send the URDF of an arm")
        summary: tuple[list[str], str] = run_isolated(
            _chain_summary,
            body.urdf,
            body.base_frame,
            body.tip_frame,
            what="urdf: Pinocchio's URDF parser",
            start_method=settings.worker_start_method,
        )
    except IsolatedFailure as exc:
        raise ProblemException(422, str(exc), slug="invalid-urdf") from exc
    except UrdfLimitError as exc:
        raise model_problem(exc, "") from exc
    except ModelError as exc:
        slug = "invalid-urdf" if str(exc).startswith("urdf:") else "invalid-robot-model"
        detail = one_line(exc)
        if slug == "invalid-robot-model":
            detail = f"urdf/base_frame/tip_frame: {detail}"
        raise ProblemException(422, detail, slug=slug) from exc
    return summary


@router.get("", response_model=RobotsPublic, responses=STANDARD_PROBLEMS)
def list_robots(principal: PrincipalDep, session: SessionDep) -> RobotsPublic:
    """Built-in robots, then the URDFs this tenant uploaded."""
    robots = [_builtin_public(name) for name in BUILTIN_ROBOTS]
    robots += [_public(row) for row in repository.list_robots(session, principal.tenant_id)]
    return RobotsPublic(data=robots, count=len(robots))


@router.get(
    "/{robot_id}",
    response_model=RobotPublic,
    responses={**STANDARD_PROBLEMS, **problem_responses(404)},
)
def get_robot(robot_id: str, principal: PrincipalDep, session: SessionDep) -> RobotPublic:
    """One robot: a built-in name or an uploaded robot id."""
    if robot_id in BUILTIN_ROBOTS:
        return _builtin_public(robot_id)
    row = repository.get_robot(session, principal.tenant_id, robot_id)
    if row is None:
        raise ProblemException(404, f"robot {robot_id!r} not found", slug="not-found")
    return _public(row)


@router.post(
    "",
    status_code=201,
    response_model=RobotPublic,
    responses={**STANDARD_PROBLEMS, **IDEMPOTENCY_PROBLEMS, **problem_responses(413)},
)
def upload_robot(
    body: RobotCreate,
    principal: PrincipalDep,
    state: StateDep,
    session: SessionDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> Response:
    """Upload a URDF; it must parse safely and build a chain from base_frame to tip_frame."""
    idempotency = Idempotency(
        state.database, principal.tenant_id, idempotency_key, "POST /api/v1/robots"
    )

    def create() -> Response:
        joint_names, urdf_sha256 = validate_urdf(body, state.settings)
        sha = hashlib.sha256(body.urdf.encode()).hexdigest()
        path = state.files.write(
            tenant_path(principal.tenant_id, "robots", f"{sha}.urdf"), body.urdf.encode()
        )
        row = Robot(
            id=repository.new_id("rbt"),
            tenant_id=principal.tenant_id,
            name=body.name,
            base_frame=body.base_frame,
            tip_frame=body.tip_frame,
            joint_names=joint_names,
            urdf_sha256=urdf_sha256,
            urdf_path=path,
        )
        session.add(row)
        session.commit()
        return Response(
            _public(row).model_dump_json(),
            status_code=201,
            media_type="application/json",
            headers={"Location": f"/api/v1/robots/{row.id}"},
        )

    return idempotency.run(lambda: fingerprint(body.model_dump()), create)
