"""Robots: the built-in ones, and URDFs uploaded by a tenant (validated, size-limited, stored)."""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass
from typing import Annotated
from xml.etree.ElementTree import ParseError

import defusedxml.ElementTree as SafeET
from defusedxml import DefusedXmlException
from fastapi import APIRouter, Header, Response
from sqlalchemy.orm import Session

from schemas.api import RobotCreate, RobotPublic, RobotsPublic
from service.api.deps import API_PREFIX, PrincipalDep, SessionDep, StateDep
from service.api.idempotency import IDEMPOTENCY_PROBLEMS, Idempotency, fingerprint
from service.api.problems import STANDARD_PROBLEMS, ProblemException, problem_responses
from service.robots import BUILTIN_ROBOTS, RobotDescription, load_robot
from service.settings import Settings
from service.storage import repository
from service.storage.files import tenant_path
from service.storage.models import Robot
from service.tasks import RobotRef
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
def _chain(urdf_xml: str, base_frame: str, tip_frame: str) -> KinematicChain:
    return build_chain(urdf_xml, base_frame, tip_frame)


@functools.lru_cache(maxsize=16)
def _builtin(name: str, base_frame: str | None, tip_frame: str | None) -> RobotDescription:
    return load_robot(name, base_frame=base_frame, tip_frame=tip_frame)


def one_line(exc: Exception, limit: int = 600) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def check_joint_count(chain: KinematicChain, settings: Settings, field: str) -> None:
    if chain.n_joints > settings.max_joints:
        raise ProblemException(
            422,
            f"{field}: the chain has {chain.n_joints} joints, more than the limit of "
            f"{settings.max_joints}; choose base/tip frames spanning fewer joints",
            slug="too-many-joints",
        )


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
        chain = _chain(description.urdf_xml, description.base_frame, description.tip_frame)
    except ModelError as exc:
        raise ProblemException(
            422, f"robot {robot!r}: {one_line(exc)}", slug="invalid-robot-model"
        ) from exc
    check_joint_count(chain, state.settings, "base_frame/tip_frame")
    return ResolvedRobot(ref, description, chain)


def _builtin_public(name: str) -> RobotPublic:
    description = _builtin(name, None, None)
    chain = _chain(description.urdf_xml, description.base_frame, description.tip_frame)
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


def validate_urdf(urdf: str, settings: Settings) -> None:
    """Size limit, then a safe XML parse (no DTDs, entities or external references)."""
    size = len(urdf.encode("utf-8"))
    if size > settings.max_urdf_bytes:
        raise ProblemException(
            413,
            f"urdf: {size} bytes is more than the limit of {settings.max_urdf_bytes} bytes; strip "
            "meshes, comments and unused links",
            slug="urdf-too-large",
        )
    try:
        root = SafeET.fromstring(urdf, forbid_dtd=True)
    except DefusedXmlException as exc:
        raise ProblemException(
            422,
            f"urdf: {type(exc).__name__}: DTDs, entity declarations and external references are "
            "not allowed in an uploaded URDF; remove them",
            slug="invalid-urdf",
        ) from exc
    except ParseError as exc:
        raise ProblemException(
            422, f"urdf: not well-formed XML ({exc}); fix the XML", slug="invalid-urdf"
        ) from exc
    if root.tag != "robot":
        raise ProblemException(
            422,
            f"urdf: the root element is <{root.tag}>, expected <robot>; send a URDF document",
            slug="invalid-urdf",
        )


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
        validate_urdf(body.urdf, state.settings)
        try:
            chain = _chain(body.urdf, body.base_frame, body.tip_frame)
        except ModelError as exc:
            raise ProblemException(
                422, f"urdf/base_frame/tip_frame: {one_line(exc)}", slug="invalid-robot-model"
            ) from exc
        check_joint_count(chain, state.settings, "base_frame/tip_frame")
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
            joint_names=list(chain.joint_names),
            urdf_sha256=chain.urdf_sha256,
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
