"""Job outcome: ``jobs.outcome`` (executable / not_executable / unknown) and its short form, set with the result,
so jobs and batches can be listed and counted by outcome (issue #53 item 1).

Revision ID: 0004_job_outcome
Revises: 0003_batches_events
Create Date: 2026-12-10

Results stored before this revision carry no outcome: their jobs become ``unknown``.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004_job_outcome"
down_revision: str | None = "0003_batches_events"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("jobs", sa.Column("outcome", sa.String(length=16), nullable=True))
    op.add_column("jobs", sa.Column("outcome_detail", sa.JSON(), nullable=True))
    op.create_index("ix_jobs_owner_outcome", "jobs", ["owner_key_id", "outcome", "created_at", "id"], unique=False)
    op.execute("UPDATE jobs SET outcome = 'unknown' WHERE state = 'SUCCEEDED'")


def downgrade() -> None:
    op.drop_index("ix_jobs_owner_outcome", table_name="jobs")
    op.drop_column("jobs", "outcome_detail")
    op.drop_column("jobs", "outcome")
