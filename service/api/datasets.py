"""Datasets: upload (multipart file or JSON rows), list, get, delete.

Uploads are validated by the same readers as the CLI (:func:`schemas.dataset.read_dataset`,
:func:`schemas.dataset.dataset_from_frame`; a ROS bag by
:func:`schemas.dataset.rosbag.read_bag_bytes` with the form's ``joint_states``, ``measure`` and
``capture``, as ``kincal import``), stored as Parquet (exact float64) in the tenant's
folder, and deduplicated per tenant by a hash of the robot reference and the validated arrays:
uploading the same data again (even as another file format) returns the existing dataset (200).
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import pandas as pd
import pyarrow as pa
from fastapi import APIRouter, Header, Query, Request, Response
from pydantic import ValidationError
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException

from schemas.api import DatasetCreate, DatasetPublic, DatasetsPublic
from schemas.dataset import (
    READ_SUFFIXES,
    PoseDataset,
    TooManyRowsError,
    dataset_from_frame,
    dataset_to_frame,
    read_dataset_bytes,
)
from schemas.dataset.rosbag import (
    UPLOAD_SUFFIXES,
    MeasureSource,
    TooManyMessagesError,
    read_bag_bytes,
)
from service.api.deps import API_PREFIX, PrincipalDep, SessionDep, StateDep
from service.api.idempotency import Idempotency, fingerprint
from service.api.problems import (
    STANDARD_PROBLEMS,
    ProblemException,
    problem_responses,
    validation_errors,
)
from service.api.robots import ResolvedRobot, resolve_robot
from service.app.job_params import RobotRef
from service.app.preflight import check_dataset
from service.security import Principal
from service.storage import repository
from service.storage.files import tenant_path
from service.storage.models import Dataset
from solver.errors import DatasetError

router = APIRouter(prefix=f"{API_PREFIX}/datasets", tags=["datasets"])

MEDIA_SUFFIX = {
    "text/csv": ".csv",
    "application/csv": ".csv",
    "application/json": ".json",
    "application/vnd.apache.parquet": ".parquet",
    "application/x-parquet": ".parquet",
    "application/yaml": ".yaml",
    "application/zip": ".zip",
}
BAG_FIELDS = ("joint_states", "measure", "capture")
"""Form fields of a ROS bag upload (``kincal import``'s --joint-states, --measure, --capture)."""
OPTION_FIELDS = {"--joint-states": "joint_states", "--measure": "measure", "--capture": "capture"}
_MULTIPART_SCHEMA = {
    "type": "object",
    "required": ["file", "robot"],
    "properties": {
        "file": {
            "type": "string",
            "format": "binary",
            "description": "The recording: .csv, .parquet or .json (dataset contract), or a "
            "ROS bag (.bag, or a rosbag2 folder as .zip; docs/ros.md).",
        },
        "robot": {"type": "string", "description": "Built-in robot name or uploaded robot id."},
        "base_frame": {"type": "string"},
        "tip_frame": {"type": "string"},
        "name": {"type": "string", "description": "Name shown in results (default: file name)."},
        "joint_states": {
            "type": "string",
            "description": "ROS bag only (a .bag file, or a rosbag2 folder as .zip): the "
            "sensor_msgs/JointState topic (not for calibration-data).",
        },
        "measure": {
            "type": "string",
            "description": "ROS bag only: tf:PARENT:CHILD, pose:TOPIC, point:TOPIC or "
            "calibration-data:TOPIC[:CAMERA[:CHAIN]] (robot_calibration's captures).",
        },
        "capture": {
            "type": "string",
            "description": "ROS bag only: a topic whose messages mark the samples.",
        },
    },
}


@dataclass(frozen=True)
class Upload:
    """A parsed upload request: either a file or JSON rows, plus the robot fields."""

    robot: str
    base_frame: str | None
    tip_frame: str | None
    name: str
    file_bytes: bytes | None = None
    suffix: str | None = None
    rows: list[dict[str, Any]] | None = None
    bag: dict[str, str | None] | None = None
    """``BAG_FIELDS`` of a ROS bag upload."""

    def fingerprint(self) -> str:
        fields = [self.robot, self.base_frame, self.tip_frame, self.name, self.suffix]
        fields += [(self.bag or {}).get(field) for field in BAG_FIELDS]
        if self.file_bytes is not None:
            return fingerprint(fields, self.file_bytes)
        return fingerprint(fields, self.rows)


def public(row: Dataset) -> DatasetPublic:
    """The stored row as the API shows it: every field of ``DatasetPublic`` read by name."""
    return DatasetPublic.model_validate(row, from_attributes=True)


def content_sha256(dataset: PoseDataset, robot: RobotRef) -> str:
    """Hash of what a calibration depends on: robot reference, joint names and the arrays."""
    digest = hashlib.sha256()
    head = robot.model_dump(include={"name", "robot_id", "base_frame", "tip_frame"})
    digest.update(json.dumps([head, list(dataset.joint_names)], sort_keys=True).encode())
    for field in ("joint_positions", "position_m", "quaternion_xyzw", "time_s", "temperature_c"):
        value = getattr(dataset, field)
        digest.update(field.encode())
        digest.update(b"-" if value is None else np.ascontiguousarray(value, "<f8").tobytes())
    digest.update(b"payload_kg")
    payload = dataset.payload_kg
    digest.update(b"-" if payload is None else np.ascontiguousarray(payload, "<f8").tobytes())
    ids = dataset.sample_id
    digest.update(b"-" if ids is None else json.dumps([str(i) for i in ids.tolist()]).encode())
    return digest.hexdigest()


def parquet_bytes(dataset: PoseDataset) -> bytes:
    """The dataset in the contract layout as Parquet (float64 kept bit-exact)."""
    frame = dataset_to_frame(dataset)
    buffer = io.BytesIO()
    try:
        frame.to_parquet(buffer, index=False)
    except (pa.ArrowInvalid, pa.ArrowTypeError):  # sample ids mixing numbers and text
        frame["sample_id"] = frame["sample_id"].astype(str)
        buffer = io.BytesIO()
        frame.to_parquet(buffer, index=False)
    return buffer.getvalue()


# --- request parsing ---------------------------------------------------------------------------


def _form_text(form: Any, field: str, *, required: bool = False) -> str | None:
    value = form.get(field)
    if value is None or (isinstance(value, str) and not value.strip()):
        if required:
            raise ProblemException(
                422,
                f"{field}: missing form field; send it with the file (multipart/form-data)",
                slug="invalid-request",
            )
        return None
    if not isinstance(value, str):
        raise ProblemException(
            422, f"{field}: must be a text field, not a file", slug="invalid-request"
        )
    return value.strip()


def _suffix(upload: UploadFile) -> str:
    suffix = Path(upload.filename or "").suffix.lower()
    if suffix in READ_SUFFIXES or suffix in UPLOAD_SUFFIXES:
        return suffix
    media = (upload.content_type or "").split(";")[0].strip().lower()
    if media in MEDIA_SUFFIX:
        return MEDIA_SUFFIX[media]
    raise ProblemException(
        415,
        f"file: cannot tell the format of {upload.filename or 'the upload'!r} (content type "
        f"{media or 'none'}); send a .csv, .parquet, .json or industrial_calibration .yaml "
        "file, a ROS bag (.bag, or a rosbag2 folder as .zip), or set the part's content type "
        "to text/csv, application/vnd.apache.parquet, application/json or application/yaml",
        slug="unsupported-file-type",
    )


def _bag_fields(form: Any, suffix: str) -> dict[str, str | None] | None:
    """The ROS bag fields of a bag upload (joint_states and measure required); 422 when a bag
    lacks them or another file has them."""
    given = {field: _form_text(form, field) for field in BAG_FIELDS}
    if suffix not in UPLOAD_SUFFIXES:
        extra = [field for field, value in given.items() if value is not None]
        if extra:
            raise ProblemException(
                422,
                f"{extra[0]}: only for a ROS bag (.bag, or a rosbag2 folder as .zip); leave it "
                "out for a recording file",
                slug="invalid-request",
            )
        return None
    captures = (given["measure"] or "").startswith("calibration-data:")
    for field in ("measure",) if captures else ("joint_states", "measure"):
        if given[field] is None:
            raise ProblemException(
                422,
                f"{field}: missing form field; a ROS bag needs joint_states (the JointState "
                "topic) and measure (tf:PARENT:CHILD, pose:TOPIC or point:TOPIC), or measure "
                "calibration-data:TOPIC alone",
                slug="invalid-request",
            )
    return given


async def _parse_multipart(request: Request) -> Upload:
    try:
        async with request.form(max_files=1, max_fields=16) as form:
            file = form.get("file")
            if not isinstance(file, UploadFile):
                raise ProblemException(
                    422,
                    "file: missing file part; send the recording as form field 'file'",
                    slug="invalid-request",
                )
            robot = _form_text(form, "robot", required=True)
            assert robot is not None
            suffix = _suffix(file)
            return Upload(
                robot=robot,
                base_frame=_form_text(form, "base_frame"),
                tip_frame=_form_text(form, "tip_frame"),
                name=_form_text(form, "name") or Path(file.filename or "upload").name or "upload",
                file_bytes=await file.read(),
                suffix=suffix,
                bag=_bag_fields(form, suffix),
            )
    except (HTTPException, ProblemException):  # 413 from the body limit is an HTTPException
        raise
    except Exception as exc:  # any parse error of starlette / python-multipart
        message = getattr(exc, "message", None) or str(exc) or type(exc).__name__
        raise ProblemException(
            400,
            f"malformed multipart body ({message}); send multipart/form-data with a boundary",
            slug="bad-body",
        ) from exc


async def _parse_json(request: Request) -> Upload:
    body = await request.body()
    try:  # parsing megabytes of JSON is CPU work: keep it off the event loop
        payload = await run_in_threadpool(DatasetCreate.model_validate_json, body)
    except ValidationError as exc:
        errors = validation_errors(exc.errors(), ("body",))
        first = errors[0]
        raise ProblemException(
            422,
            f"{first['location']}: {first['detail']}; fix the field and resend (schema: /docs)",
            slug="invalid-request",
            errors=errors,
        ) from exc
    return Upload(
        robot=payload.robot,
        base_frame=payload.base_frame,
        tip_frame=payload.tip_frame,
        name=payload.name,
        rows=payload.rows,
    )


# --- validation and storage (runs in a worker thread) ------------------------------------------


def _validate(
    upload: Upload,
    robot: ResolvedRobot,
    max_rows: int,
    max_bag_messages: int,
    max_unpacked_bytes: int,
) -> PoseDataset:
    chain = robot.chain
    if upload.rows is not None:
        if len(upload.rows) > max_rows:
            raise _too_many_rows(len(upload.rows), max_rows)
        frame = pd.DataFrame.from_records(upload.rows)
        dataset = dataset_from_frame(
            frame, chain.joint_names, source=upload.name, other_joint_names=chain.other_joint_names
        )
    elif upload.bag is not None:
        dataset = _read_bag(upload, robot, max_rows, max_bag_messages, max_unpacked_bytes)
    else:
        assert upload.file_bytes is not None and upload.suffix is not None
        try:
            dataset = read_dataset_bytes(
                upload.file_bytes,
                upload.suffix,
                chain.joint_names,
                other_joint_names=chain.other_joint_names,
                source=upload.name,
                max_rows=max_rows,
            )
        except TooManyRowsError as exc:
            raise _too_many_rows(exc.n_rows, max_rows) from exc
    if dataset.n_samples > max_rows:
        raise _too_many_rows(dataset.n_samples, max_rows)
    check_dataset(dataset, chain)  # the CLI's pre-flight checks: units, limits, repeated rows
    return dataset


def _read_bag(
    upload: Upload,
    robot: ResolvedRobot,
    max_rows: int,
    max_messages: int,
    max_unpacked_bytes: int,
) -> PoseDataset:
    """A ROS bag upload as ``kincal import`` reads it (the CLI's still-segment defaults); 413
    beyond the message or row limits, 422 naming the fix otherwise."""
    assert upload.bag is not None and upload.file_bytes is not None and upload.suffix
    joint_states, measure = upload.bag["joint_states"], upload.bag["measure"]
    assert measure is not None
    try:
        recording = read_bag_bytes(
            upload.file_bytes,
            upload.suffix,
            joint_states,
            MeasureSource.parse(measure),
            source=upload.name,
            max_unpacked_bytes=max_unpacked_bytes,
            joint_names=robot.chain.joint_names,
            other_joint_names=robot.chain.other_joint_names,
            capture=upload.bag["capture"],
            max_messages=max_messages,
        )
    except TooManyMessagesError as exc:
        raise ProblemException(
            413,
            f"file: {exc}, or ask the operator to raise KINCAL_MAX_BAG_MESSAGES",
            slug="too-many-messages",
        ) from exc
    except DatasetError as exc:  # the reader names the CLI's options: name the form's fields
        detail = str(exc)
        for option, field in OPTION_FIELDS.items():
            detail = detail.replace(option, field)
        raise ProblemException(422, detail, slug="invalid-dataset") from exc
    if recording.dataset.n_samples > max_rows:
        raise _too_many_rows(recording.dataset.n_samples, max_rows)
    return recording.dataset


def _too_many_rows(n: int, limit: int) -> ProblemException:
    return ProblemException(
        413,
        f"rows: {n} samples is more than the limit of {limit}; split the recording or ask the "
        "operator to raise KINCAL_MAX_ROWS",
        slug="too-many-rows",
    )


STORE_ATTEMPTS = 3


def _store(state: StateDep, principal: Principal, upload: Upload) -> Response:
    with state.database.sessions() as session:
        robot = resolve_robot(
            state, session, principal.tenant_id, upload.robot, upload.base_frame, upload.tip_frame
        )
    try:
        settings = state.settings
        dataset = _validate(
            upload,
            robot,
            settings.max_rows,
            settings.max_bag_messages,
            max_unpacked_bytes=4 * settings.max_request_bytes,
        )
    except DatasetError as exc:
        raise ProblemException(422, str(exc), slug="invalid-dataset") from exc
    sha = content_sha256(dataset, robot.ref)
    # A concurrent delete of the same content, or a concurrent upload of it, can change the
    # answer between looking and inserting: look again (bounded).
    for _ in range(STORE_ATTEMPTS):
        existing = _existing(state, principal.tenant_id, sha)
        if existing is not None:
            return _answer(existing, 200)
        created = _create(state, principal, upload, robot, dataset, sha)
        if created is not None:
            return _answer(created, 201)
    raise ProblemException(
        409,
        "the same data is being uploaded and deleted concurrently; retry the upload",
        slug="concurrent-change",
    )


def _existing(state: StateDep, tenant_id: str, sha: str) -> Dataset | None:
    """The tenant's dataset with this content, confirmed by a write (so not one whose deletion
    has committed), or None."""
    with state.database.session() as session:
        if repository.touch_dataset_by_content(session, tenant_id, sha):
            return repository.dataset_by_content(session, tenant_id, sha)
    return None


def _create(
    state: StateDep,
    principal: Principal,
    upload: Upload,
    robot: ResolvedRobot,
    dataset: PoseDataset,
    sha: str,
) -> Dataset | None:
    """Store a new dataset; None if the same content was stored concurrently. Each dataset has
    its own file, so deleting one never removes the file of a re-upload of the same data."""
    data = parquet_bytes(dataset)
    dataset_id = repository.new_id("ds")
    path = state.files.write(
        tenant_path(principal.tenant_id, "datasets", f"{dataset_id}.parquet"), data
    )
    time_s = dataset.time_s
    row = Dataset(
        id=dataset_id,
        tenant_id=principal.tenant_id,
        name=upload.name[:200],
        robot=robot.ref.name,
        robot_id=robot.ref.robot_id,
        base_frame=robot.ref.base_frame,
        tip_frame=robot.ref.tip_frame,
        joint_names=list(dataset.joint_names),
        n_samples=dataset.n_samples,
        measures_rotation=dataset.measures_rotation,
        time_start_s=None if time_s is None else float(time_s[0]),
        time_end_s=None if time_s is None else float(time_s[-1]),
        content_sha256=sha,
        data_path=path,
        size_bytes=len(data),
    )
    try:
        with state.database.session() as session:
            session.add(row)
    except IntegrityError:  # the same content was stored concurrently
        state.files.delete(path)
        return None
    return row


def _answer(row: Dataset, status: int) -> Response:
    return Response(
        public(row).model_dump_json(),
        status_code=status,
        media_type="application/json",
        headers={"Location": f"/api/v1/datasets/{row.id}"},
    )


# --- routes ------------------------------------------------------------------------------------


@router.post(
    "",
    status_code=201,
    response_model=DatasetPublic,
    responses={
        200: {"model": DatasetPublic, "description": "The same data was already stored."},
        **STANDARD_PROBLEMS,
        **problem_responses(400, 409, 413, 415),
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "multipart/form-data": {"schema": _MULTIPART_SCHEMA},
                "application/json": {"schema": DatasetCreate.model_json_schema()},
            },
        }
    },
)
async def upload_dataset(
    request: Request,
    principal: PrincipalDep,
    state: StateDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> Response:
    """Upload a recording (multipart file or JSON rows); validated, stored, deduplicated."""
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media == "multipart/form-data":
        upload = await _parse_multipart(request)
    elif media == "application/json":
        upload = await _parse_json(request)
    else:
        raise ProblemException(
            415,
            f"Content-Type {media or '(none)'} is not accepted; send multipart/form-data with a "
            "'file' part, or application/json rows (see /docs)",
            slug="unsupported-media-type",
        )
    idempotency = Idempotency(
        state.database, principal.tenant_id, idempotency_key, "POST /api/v1/datasets"
    )
    return await run_in_threadpool(
        idempotency.run, upload.fingerprint, lambda: _store(state, principal, upload)
    )


@router.get("", response_model=DatasetsPublic, responses=STANDARD_PROBLEMS)
def list_datasets(
    principal: PrincipalDep,
    session: SessionDep,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
) -> DatasetsPublic:
    """This tenant's datasets, newest first, one page at a time."""
    rows, count = repository.list_datasets(session, principal.tenant_id, offset=offset, limit=limit)
    return DatasetsPublic(data=[public(r) for r in rows], count=count, offset=offset, limit=limit)


def _get_or_404(session: Session, tenant_id: str, dataset_id: str) -> Dataset:
    row = repository.get_dataset(session, tenant_id, dataset_id)
    if row is None:
        raise ProblemException(
            404,
            f"dataset {dataset_id!r} not found; list yours with GET /api/v1/datasets",
            slug="not-found",
        )
    return row


@router.get(
    "/{dataset_id}",
    response_model=DatasetPublic,
    responses={**STANDARD_PROBLEMS, **problem_responses(404)},
)
async def get_dataset(dataset_id: str, principal: PrincipalDep, state: StateDep) -> DatasetPublic:
    """Metadata and summary of one dataset."""

    def lookup() -> Dataset:
        with state.database.sessions() as session:
            return _get_or_404(session, principal.tenant_id, dataset_id)

    return public(await run_in_threadpool(lookup))


@router.delete(
    "/{dataset_id}",
    status_code=204,
    response_class=Response,
    responses={**STANDARD_PROBLEMS, **problem_responses(404, 409)},
)
def delete_dataset(dataset_id: str, principal: PrincipalDep, state: StateDep) -> Response:
    """Delete a dataset (refused while a job is using it); finished results are kept."""
    with state.database.session() as session:
        row = _get_or_404(session, principal.tenant_id, dataset_id)
        active = repository.count_active_jobs_for_dataset(session, principal.tenant_id, row.id)
        if active:
            raise ProblemException(
                409,
                f"dataset {dataset_id!r} is used by {active} queued or running job(s); cancel "
                "them or wait until they finish",
                slug="dataset-in-use",
            )
        session.delete(row)
        session.flush()
        orphan = repository.count_datasets_using_file(session, row.data_path) == 0
    if orphan:
        state.files.delete(row.data_path)
    return Response(status_code=204)
