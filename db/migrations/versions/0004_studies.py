"""studies: experiments run side by side under one study id

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-25 00:05:00

``foldwise study`` (and ``POST /experiments?study=``) runs one experiment per detector, or per
reset/grow choice, of one config; ``experiments.study`` names the group so its figures draw
them side by side. Experiments recorded before belong to none.
"""

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("experiments") as batch:
        batch.add_column(sa.Column("study", sa.String(length=200), nullable=True))
        batch.create_index("ix_experiments_study", ["study"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("experiments") as batch:
        batch.drop_index("ix_experiments_study")
        batch.drop_column("study")
