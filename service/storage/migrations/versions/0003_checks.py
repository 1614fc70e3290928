"""Checks: a succeeded calibration tested against new poses (``kincal check`` over HTTP), kept
with their time; the document is a file, the row holds the verdict, statistic and threshold.

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-06
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    op.create_table(
        "checks",
        sa.Column("id", sa.String(40), nullable=False),
        sa.Column("tenant_id", sa.String(40), nullable=False),
        sa.Column("calibration_id", sa.String(40), nullable=False),
        sa.Column("dataset_id", sa.String(40), nullable=False),
        sa.Column("dataset_name", sa.String(200), nullable=False),
        sa.Column("level", sa.Float(), nullable=False),
        sa.Column("n_poses", sa.Integer(), nullable=False),
        sa.Column("verdict", sa.String(16), nullable=False),
        sa.Column("statistic", sa.Float(), nullable=True),
        sa.Column("threshold", sa.Float(), nullable=True),
        sa.Column("located", sa.String(200), nullable=True),
        sa.Column("document_path", sa.String(300), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["tenant_id"], ["tenants.id"], name="fk_checks_tenant_id_tenants", ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["calibration_id"],
            ["jobs.id"],
            name="fk_checks_calibration_id_jobs",
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name="pk_checks"),
    )
    op.create_index(
        "ix_checks_tenant_calibration_created",
        "checks",
        ["tenant_id", "calibration_id", "created_at"],
    )
    op.create_index("ix_checks_created", "checks", ["created_at"])


def downgrade() -> None:
    op.drop_table("checks")
