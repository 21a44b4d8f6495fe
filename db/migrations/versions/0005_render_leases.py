"""render leases and message counts: a render batch claims its θ and renews the claim while it
renders; every θ and model counts the messages sent for it

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-25 05:30:00

A render worker killed whole (main process and pool child) left its θ ``queued`` for the hour
of ``FOLDWISE_REQUEUE_AFTER_S``; with a claim renewed every lease/4 the scheduler sees the
lapse within one lease. ``sends`` makes "re-sent once" something one can check.
"""

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("parameter_sets") as batch:
        batch.add_column(sa.Column("task_id", sa.String(length=100), nullable=True))
        batch.add_column(sa.Column("claimed_at", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(sa.Column("sends", sa.Integer(), nullable=False, server_default="0"))
    with op.batch_alter_table("models") as batch:
        batch.add_column(sa.Column("sends", sa.Integer(), nullable=False, server_default="0"))


def downgrade() -> None:
    with op.batch_alter_table("models") as batch:
        batch.drop_column("sends")
    with op.batch_alter_table("parameter_sets") as batch:
        batch.drop_column("sends")
        batch.drop_column("claimed_at")
        batch.drop_column("task_id")
