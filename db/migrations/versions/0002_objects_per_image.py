"""objects per image: 0..n targets per θ

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24 18:00:00

A rendered θ records every target it shows (several objects, or none) in
``parameter_sets.objects``; rows rendered before hold their one target in label, box,
amodal_box and visible_fraction, which the upgrade copies into the list. Stored θ keep their
version: ``foldwise.theta.Theta.parse`` reads version 1 and renders it to the same bytes.
"""

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("parameter_sets") as batch:
        batch.add_column(sa.Column("objects", sa.JSON(), nullable=True))
    rows = sa.table(
        "parameter_sets",
        sa.column("id", sa.Integer),
        sa.column("theta", sa.JSON),
        sa.column("objects", sa.JSON),
        sa.column("label", sa.Integer),
        sa.column("box", sa.JSON),
        sa.column("amodal_box", sa.JSON),
        sa.column("visible_fraction", sa.Float),
    )
    connection = op.get_bind()
    found = connection.execute(
        sa.select(rows.c.id, rows.c.theta, rows.c.label, rows.c.box, rows.c.amodal_box, rows.c.visible_fraction).where(
            rows.c.box.isnot(None)
        )
    ).all()
    for row_id, theta, label, box, amodal_box, visible_fraction in found:
        if box is None:  # a JSON null passes IS NOT NULL
            continue
        target = {
            "object": (theta or {}).get("object"),
            "label": label,
            "box": box,
            "amodal_box": amodal_box,
            "visible_fraction": visible_fraction,
        }
        connection.execute(sa.update(rows).where(rows.c.id == row_id).values(objects=[target]))


def downgrade() -> None:
    with op.batch_alter_table("parameter_sets") as batch:
        batch.drop_column("objects")
