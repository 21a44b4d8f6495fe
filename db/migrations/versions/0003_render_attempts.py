"""render attempts: how often rendering a θ started

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24 23:55:00

A θ whose render kills its worker (out of memory) or runs past its time limit on every
delivery is redelivered forever; counting the attempts lets the render worker give up after
``tasks.max_deliveries`` and record why. Rows rendered before count 0.
"""

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("parameter_sets") as batch:
        batch.add_column(sa.Column("attempts", sa.Integer(), nullable=False, server_default="0"))


def downgrade() -> None:
    with op.batch_alter_table("parameter_sets") as batch:
        batch.drop_column("attempts")
