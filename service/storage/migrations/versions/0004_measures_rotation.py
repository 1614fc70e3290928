"""Datasets: whether the rows measured the marker's orientation is stored as
``measures_rotation`` (the measurement model's own word, issue 35) instead of its negation, the
old ``position_only`` flag; every existing row keeps its meaning.

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-07
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | None = None
depends_on: str | None = None

OLD, NEW = "position_only", "measures_rotation"


def _flip(source: str, target: str) -> None:
    """``target = NOT source`` on every dataset row (both columns present)."""
    datasets = sa.table("datasets", sa.column(source, sa.Boolean), sa.column(target, sa.Boolean))
    op.execute(datasets.update().values({target: sa.not_(datasets.c[source])}))


def _replace(source: str, target: str) -> None:
    with op.batch_alter_table("datasets") as batch:
        batch.add_column(sa.Column(target, sa.Boolean(), nullable=True))
    _flip(source, target)
    with op.batch_alter_table("datasets") as batch:
        batch.alter_column(target, existing_type=sa.Boolean(), nullable=False)
        batch.drop_column(source)


def upgrade() -> None:
    _replace(OLD, NEW)


def downgrade() -> None:
    _replace(NEW, OLD)
