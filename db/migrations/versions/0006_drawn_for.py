"""why each training θ was drawn: parameter_sets.drawn_for

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-28 17:30:00

A mixed stage with ``curriculum.mixed.sampling: failure`` draws its θ where the latest scored
model fails; the rule, that model and the weight of each drawn (condition, difficulty) are kept
with the θ, so that the record says why the detector saw what it saw.
"""

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("parameter_sets") as batch:
        batch.add_column(sa.Column("drawn_for", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("parameter_sets") as batch:
        batch.drop_column("drawn_for")
