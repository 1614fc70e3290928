"""Queries, one small function each. Every client-facing lookup takes the tenant id.

Functions take an open :class:`~sqlalchemy.orm.Session`; the caller owns the transaction.
"""

from __future__ import annotations

import datetime as dt
import uuid
from collections.abc import Sequence
from typing import Any

from sqlalchemy import case, delete, func, select, update
from sqlalchemy.orm import Session

from service.storage.models import (
    ApiKey,
    Check,
    Dataset,
    IdempotencyRecord,
    Job,
    Robot,
    Tenant,
    utcnow,
)

LOCAL_TENANT = "local"
"""The tenant of requests without a key in keyless mode (service bound to a loopback address)."""

QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED = (
    "queued",
    "running",
    "succeeded",
    "failed",
    "cancelled",
)
JOB_STATES = (QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED)
ACTIVE_STATES = (QUEUED, RUNNING)
TERMINAL_STATES = (SUCCEEDED, FAILED, CANCELLED)


def new_id(prefix: str) -> str:
    """``<prefix>_<32 hex>``: random, unguessable, tells what it names."""
    return f"{prefix}_{uuid.uuid4().hex}"


# --- tenants and keys --------------------------------------------------------------------------


def tenant_by_name(session: Session, name: str) -> Tenant | None:
    return session.scalar(select(Tenant).where(Tenant.name == name))


def ensure_tenant(session: Session, name: str) -> Tenant:
    tenant = tenant_by_name(session, name)
    if tenant is None:
        tenant = Tenant(id=new_id("ten"), name=name)
        session.add(tenant)
        session.flush()
    return tenant


def api_key(session: Session, key_id: str) -> ApiKey | None:
    return session.get(ApiKey, key_id)


# --- robots ------------------------------------------------------------------------------------


def get_robot(session: Session, tenant_id: str, robot_id: str) -> Robot | None:
    return session.scalar(select(Robot).where(Robot.tenant_id == tenant_id, Robot.id == robot_id))


def list_robots(session: Session, tenant_id: str) -> Sequence[Robot]:
    query = select(Robot).where(Robot.tenant_id == tenant_id).order_by(Robot.created_at)
    return session.scalars(query).all()


# --- datasets ----------------------------------------------------------------------------------


def get_dataset(session: Session, tenant_id: str, dataset_id: str) -> Dataset | None:
    return session.scalar(
        select(Dataset).where(Dataset.tenant_id == tenant_id, Dataset.id == dataset_id)
    )


def dataset_by_content(session: Session, tenant_id: str, content_sha256: str) -> Dataset | None:
    return session.scalar(
        select(Dataset).where(
            Dataset.tenant_id == tenant_id, Dataset.content_sha256 == content_sha256
        )
    )


def touch_dataset_by_content(session: Session, tenant_id: str, content_sha256: str) -> bool:
    """A no-op write to the tenant's dataset with this content: False if there is none. As the
    transaction's first statement it serialises against a concurrent delete (PostgreSQL: row
    lock; SQLite: the write lock), so a deduplicated upload never answers with a dataset whose
    deletion committed before."""
    where = (Dataset.tenant_id == tenant_id, Dataset.content_sha256 == content_sha256)
    result = session.execute(update(Dataset).where(*where).values(name=Dataset.name))
    return bool(result.rowcount)  # type: ignore[attr-defined]


def list_datasets(
    session: Session, tenant_id: str, *, offset: int, limit: int
) -> tuple[Sequence[Dataset], int]:
    """One page, newest first, and the total count."""
    where = Dataset.tenant_id == tenant_id
    count = session.scalar(select(func.count()).select_from(Dataset).where(where)) or 0
    query = (
        select(Dataset)
        .where(where)
        .order_by(Dataset.created_at.desc(), Dataset.id)
        .offset(offset)
        .limit(limit)
    )
    return session.scalars(query).all(), count


def count_active_jobs_for_dataset(session: Session, tenant_id: str, dataset_id: str) -> int:
    query = (
        select(func.count())
        .select_from(Job)
        .where(
            Job.tenant_id == tenant_id,
            Job.dataset_id == dataset_id,
            Job.state.in_(ACTIVE_STATES),
        )
    )
    return session.scalar(query) or 0


def count_datasets_using_file(session: Session, data_path: str) -> int:
    query = select(func.count()).select_from(Dataset).where(Dataset.data_path == data_path)
    return session.scalar(query) or 0


# --- jobs (client side) ------------------------------------------------------------------------


def get_job(session: Session, tenant_id: str, kind: str, job_id: str) -> Job | None:
    return session.scalar(
        select(Job).where(Job.tenant_id == tenant_id, Job.kind == kind, Job.id == job_id)
    )


def list_jobs(
    session: Session, tenant_id: str, kind: str, *, offset: int, limit: int
) -> tuple[Sequence[Job], int]:
    where = (Job.tenant_id == tenant_id, Job.kind == kind)
    count = session.scalar(select(func.count()).select_from(Job).where(*where)) or 0
    query = (
        select(Job)
        .where(*where)
        .order_by(Job.created_at.desc(), Job.id)
        .offset(offset)
        .limit(limit)
    )
    return session.scalars(query).all(), count


def cancel_queued_job(session: Session, job_id: str) -> bool:
    """Queued -> cancelled, atomically; False if it was no longer queued."""
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == QUEUED)
        .values(state=CANCELLED, cancel_requested=True, finished_at=utcnow(), stage=None)
    )
    return bool(result.rowcount)  # type: ignore[attr-defined]


def request_cancel(session: Session, job_id: str) -> None:
    session.execute(
        update(Job).where(Job.id == job_id, Job.state == RUNNING).values(cancel_requested=True)
    )


def cancel_requested_jobs(session: Session, runner_id: str) -> list[str]:
    """Running jobs of ``runner_id`` whose cancellation was requested (by any process)."""
    ids = session.scalars(
        select(Job.id).where(
            Job.state == RUNNING, Job.runner_id == runner_id, Job.cancel_requested.is_(True)
        )
    )
    return list(ids)


def count_jobs_by_state(session: Session) -> dict[tuple[str, str], int]:
    rows = session.execute(select(Job.kind, Job.state, func.count()).group_by(Job.kind, Job.state))
    return {(kind, state): int(n) for kind, state, n in rows}


# --- jobs (runner side) ------------------------------------------------------------------------


def claim_next_job(session: Session, runner_id: str, kinds: Sequence[str]) -> Job | None:
    """Oldest queued job of a known kind -> running, owned by ``runner_id``; None if none.

    The conditional UPDATE makes the claim exclusive across threads, processes and instances.
    """
    candidates = session.scalars(
        select(Job.id)
        .where(Job.state == QUEUED, Job.kind.in_(kinds))
        .order_by(Job.created_at, Job.id)
        .limit(8)
    ).all()
    now = utcnow()
    for job_id in candidates:
        claimed = session.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == QUEUED)
            .values(
                state=RUNNING,
                runner_id=runner_id,
                started_at=now,
                heartbeat_at=now,
                attempts=Job.attempts + 1,
                stage="starting",
                fraction=0.0,
                iteration=None,
            )
        )
        if claimed.rowcount:  # type: ignore[attr-defined]
            return session.get(Job, job_id, populate_existing=True)
    return None


def requeue_jobs_of_runner(session: Session, runner_id: str) -> list[str]:
    """Jobs a previous life of this instance left running (crash, kill -9) -> queued."""
    ids = session.scalars(
        select(Job.id).where(Job.state == RUNNING, Job.runner_id == runner_id)
    ).all()
    _requeue(session, ids)
    return list(ids)


def requeue_expired_leases(session: Session, lease_s: float) -> list[str]:
    """Running jobs whose owner stopped sending heartbeats -> queued."""
    cutoff = utcnow() - dt.timedelta(seconds=lease_s)
    ids = session.scalars(
        select(Job.id).where(Job.state == RUNNING, Job.heartbeat_at < cutoff)
    ).all()
    _requeue(session, ids)
    return list(ids)


def requeue_job(session: Session, job_id: str, runner_id: str) -> None:
    """Back to the queue after its worker died (the attempt counts)."""
    session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == RUNNING, Job.runner_id == runner_id)
        .values(state=QUEUED, runner_id=None, stage="requeued", heartbeat_at=None)
    )


def _requeue(session: Session, ids: Sequence[str]) -> None:
    if ids:
        session.execute(
            update(Job)
            .where(Job.id.in_(ids), Job.state == RUNNING)
            .values(state=QUEUED, runner_id=None, stage="requeued", heartbeat_at=None)
        )


def release_job(session: Session, job_id: str, runner_id: str) -> None:
    """Give a job back to the queue without counting the attempt (graceful shutdown)."""
    session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == RUNNING, Job.runner_id == runner_id)
        .values(
            state=QUEUED,
            runner_id=None,
            stage="requeued",
            heartbeat_at=None,
            attempts=case((Job.attempts > 0, Job.attempts - 1), else_=0),
        )
    )


def update_progress(
    session: Session,
    job_id: str,
    runner_id: str,
    *,
    stage: str | None = None,
    fraction: float | None = None,
    iteration: int | None = None,
) -> bool:
    """Record progress and a heartbeat; returns whether a cancel was requested."""
    values: dict[str, object] = {"heartbeat_at": utcnow()}
    if stage is not None:
        values["stage"] = stage
    if fraction is not None:
        values["fraction"] = fraction
    if iteration is not None:
        values["iteration"] = iteration
    session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == RUNNING, Job.runner_id == runner_id)
        .values(**values)
    )
    return bool(session.scalar(select(Job.cancel_requested).where(Job.id == job_id)))


def finish_job(
    session: Session,
    job_id: str,
    runner_id: str,
    state: str,
    *,
    error: str | None = None,
    artifacts: dict[str, str] | None = None,
    summary: dict[str, Any] | None = None,
) -> Job | None:
    """running -> a terminal state, only if this runner still owns the job."""
    assert state in TERMINAL_STATES
    values: dict[str, object] = {
        "state": state,
        "finished_at": utcnow(),
        "error": error,
        "heartbeat_at": None,
    }
    if state == SUCCEEDED:
        values |= {
            "fraction": 1.0,
            "stage": "done",
            "artifacts": artifacts or {},
            "summary": summary,
        }
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == RUNNING, Job.runner_id == runner_id)
        .values(**values)
    )
    if not result.rowcount:  # type: ignore[attr-defined]
        return None
    return session.get(Job, job_id, populate_existing=True)


def fail_job(session: Session, job_id: str, error: str) -> None:
    session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state.in_(ACTIVE_STATES))
        .values(state=FAILED, error=error, finished_at=utcnow(), heartbeat_at=None)
    )


# --- checks ------------------------------------------------------------------------------------


def get_check(session: Session, tenant_id: str, calibration_id: str, check_id: str) -> Check | None:
    return session.scalar(
        select(Check).where(
            Check.tenant_id == tenant_id,
            Check.calibration_id == calibration_id,
            Check.id == check_id,
        )
    )


def list_checks(
    session: Session, tenant_id: str, calibration_id: str, *, offset: int, limit: int
) -> tuple[Sequence[Check], int]:
    """One page of a calibration's checks, newest first, and the total count."""
    where = (Check.tenant_id == tenant_id, Check.calibration_id == calibration_id)
    count = session.scalar(select(func.count()).select_from(Check).where(*where)) or 0
    query = (
        select(Check)
        .where(*where)
        .order_by(Check.created_at.desc(), Check.id.desc())
        .offset(offset)
        .limit(limit)
    )
    return session.scalars(query).all(), count


def latest_checks(session: Session, limit: int) -> list[Check]:
    """The latest check of each calibration (every tenant), for the calibrations checked most
    recently, at most ``limit`` of them."""
    newest = (
        select(Check.calibration_id, func.max(Check.created_at).label("created_at"))
        .group_by(Check.calibration_id)
        .order_by(func.max(Check.created_at).desc())
        .limit(limit)
        .subquery()
    )
    rows = session.scalars(
        select(Check)
        .join(
            newest,
            (Check.calibration_id == newest.c.calibration_id)
            & (Check.created_at == newest.c.created_at),
        )
        .order_by(Check.created_at.desc(), Check.id.desc())
    ).all()
    seen: dict[str, Check] = {}
    for row in rows:  # two checks of one calibration in the same instant: the first wins
        seen.setdefault(row.calibration_id, row)
    return list(seen.values())


# --- idempotency -------------------------------------------------------------------------------


def idempotency_record(session: Session, tenant_id: str, key: str) -> IdempotencyRecord | None:
    return session.get(IdempotencyRecord, (tenant_id, key))


def delete_idempotency_record(session: Session, tenant_id: str, key: str) -> None:
    session.execute(
        delete(IdempotencyRecord).where(
            IdempotencyRecord.tenant_id == tenant_id, IdempotencyRecord.key == key
        )
    )
