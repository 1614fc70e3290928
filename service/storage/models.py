"""Database tables (SQLAlchemy 2 typed ORM). Same code on SQLite and PostgreSQL.

Bulky things (datasets, URDFs, results, reports) live in files (:mod:`service.storage.files`);
rows hold their metadata and the file's path relative to the data folder. Every row that a
client can name belongs to one tenant; queries always filter by it.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


class UTCDateTime(TypeDecorator[dt.datetime]):
    """Timezone-aware UTC datetimes on every backend (SQLite drops the offset)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: dt.datetime | None, dialect: Dialect) -> dt.datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime; use timezone-aware UTC")
        return value.astimezone(dt.UTC)

    def process_result_value(
        self, value: dt.datetime | None, dialect: Dialect
    ) -> dt.datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=dt.UTC) if value.tzinfo is None else value.astimezone(dt.UTC)


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)


class Tenant(Base):
    __tablename__ = "tenants"

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class ApiKey(Base):
    """An API key: ``kc_<id>_<secret>``; only the SHA-256 of the whole key is stored."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(16), primary_key=True)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"))
    key_sha256: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    revoked_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)


class Robot(Base):
    """An uploaded URDF with the chain (base -> tip) it was validated for."""

    __tablename__ = "robots"
    __table_args__ = (Index("ix_robots_tenant_created", "tenant_id", "created_at"),)

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(64))
    base_frame: Mapped[str] = mapped_column(String(200))
    tip_frame: Mapped[str] = mapped_column(String(200))
    joint_names: Mapped[list[str]] = mapped_column(JSON)
    urdf_sha256: Mapped[str] = mapped_column(String(64))
    urdf_path: Mapped[str] = mapped_column(String(300))
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class Dataset(Base):
    """A validated recording; ``content_sha256`` covers the robot reference and the data."""

    __tablename__ = "datasets"
    __table_args__ = (
        UniqueConstraint("tenant_id", "content_sha256", name="uq_datasets_tenant_content"),
        Index("ix_datasets_tenant_created", "tenant_id", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(200))
    robot: Mapped[str] = mapped_column(String(64))
    robot_id: Mapped[str | None] = mapped_column(String(40), nullable=True)
    base_frame: Mapped[str] = mapped_column(String(200))
    tip_frame: Mapped[str] = mapped_column(String(200))
    joint_names: Mapped[list[str]] = mapped_column(JSON)
    n_samples: Mapped[int] = mapped_column(Integer)
    measures_rotation: Mapped[bool] = mapped_column(Boolean)
    time_start_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    time_end_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    content_sha256: Mapped[str] = mapped_column(String(64))
    data_path: Mapped[str] = mapped_column(String(300))
    size_bytes: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class Job(Base):
    """One unit of background work (calibration, discovery, ...) and its progress.

    ``params`` is everything the job function needs (resolved at submission, so the worker
    reads files only); ``artifacts`` maps artifact names to files once it succeeded, and
    ``summary`` holds what its status shows of the result (a calibration's verdict).
    """

    __tablename__ = "jobs"
    __table_args__ = (
        Index("ix_jobs_state_created", "state", "created_at"),
        Index("ix_jobs_tenant_kind_created", "tenant_id", "kind", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"))
    kind: Mapped[str] = mapped_column(String(32))
    dataset_id: Mapped[str | None] = mapped_column(String(40), nullable=True, index=True)
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    state: Mapped[str] = mapped_column(String(16), default="queued")
    stage: Mapped[str | None] = mapped_column(String(64), nullable=True)
    fraction: Mapped[float] = mapped_column(Float, default=0.0)
    iteration: Mapped[int | None] = mapped_column(Integer, nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    artifacts: Mapped[dict[str, str]] = mapped_column(JSON, default=dict)
    # What a succeeded job says about its result in its status (a calibration's verdict).
    summary: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    runner_id: Mapped[str | None] = mapped_column(String(200), nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    heartbeat_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)


class Check(Base):
    """A check of a succeeded calibration against new poses (``kincal check`` over HTTP).

    The ``kincal.check/1`` document is a file (``document_path``); the row holds what a list
    and the metrics show without reading it: the verdict and the global test's statistic and
    threshold (None when the check was inconclusive: too few poses for a test).
    """

    __tablename__ = "checks"
    __table_args__ = (
        Index("ix_checks_tenant_calibration_created", "tenant_id", "calibration_id", "created_at"),
        Index("ix_checks_created", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"))
    calibration_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"))
    # No foreign key: a dataset may be deleted, its checks stay.
    dataset_id: Mapped[str] = mapped_column(String(40))
    dataset_name: Mapped[str] = mapped_column(String(200))
    level: Mapped[float] = mapped_column(Float)
    n_poses: Mapped[int] = mapped_column(Integer)
    verdict: Mapped[str] = mapped_column(String(16))
    statistic: Mapped[float | None] = mapped_column(Float, nullable=True)
    threshold: Mapped[float | None] = mapped_column(Float, nullable=True)
    located: Mapped[str | None] = mapped_column(String(200), nullable=True)
    document_path: Mapped[str] = mapped_column(String(300))
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class IdempotencyRecord(Base):
    """The stored answer to a POST made with an ``Idempotency-Key`` header.

    ``status_code`` is 0 while the first request is still being handled.
    """

    __tablename__ = "idempotency_keys"

    tenant_id: Mapped[str] = mapped_column(
        ForeignKey("tenants.id", ondelete="CASCADE"), primary_key=True
    )
    key: Mapped[str] = mapped_column(String(255), primary_key=True)
    scope: Mapped[str] = mapped_column(String(200))
    request_sha256: Mapped[str] = mapped_column(String(64))
    status_code: Mapped[int] = mapped_column(Integer, default=0)
    body: Mapped[bytes] = mapped_column(LargeBinary, default=b"")
    location: Mapped[str | None] = mapped_column(String(300), nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
