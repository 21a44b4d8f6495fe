"""initial schema

Revision ID: 0001
Revises:
Create Date: 2026-11-21 11:27:12.290296
"""

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "experiments",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("config", sa.JSON(), nullable=False),
        sa.Column("seed", sa.Integer(), nullable=False),
        sa.Column("classes", sa.JSON(), nullable=True),
        sa.Column(
            "status",
            sa.Enum(
                "pending",
                "running",
                "finished",
                "failed",
                "cancelled",
                name="experimentstatus",
                native_enum=False,
                length=20,
            ),
            nullable=False,
        ),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("final_model_id", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_table(
        "stages",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("experiment_id", sa.Integer(), nullable=False),
        sa.Column("order", sa.Integer(), nullable=False),
        sa.Column("condition", sa.String(length=20), nullable=False),
        sa.Column("difficulty", sa.String(length=20), nullable=False),
        sa.Column(
            "status",
            sa.Enum("pending", "running", "done", name="stagestatus", native_enum=False, length=20),
            nullable=False,
        ),
        sa.Column(
            "end_reason", sa.Enum("plateau", "cap", name="stageendreason", native_enum=False, length=20), nullable=True
        ),
        sa.Column("init_model_id", sa.Integer(), nullable=True),
        sa.Column("best_model_id", sa.Integer(), nullable=True),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(["experiment_id"], ["experiments.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("experiment_id", "order"),
    )
    with op.batch_alter_table("stages", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_stages_experiment_id"), ["experiment_id"], unique=False)

    op.create_table(
        "models",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("experiment_id", sa.Integer(), nullable=False),
        sa.Column("stage_id", sa.Integer(), nullable=False),
        sa.Column("increment", sa.Integer(), nullable=False),
        sa.Column("parent_id", sa.Integer(), nullable=True),
        sa.Column("detector", sa.String(length=40), nullable=False),
        sa.Column(
            "status",
            sa.Enum(
                "pending", "queued", "training", "evaluated", "failed", name="modelstatus", native_enum=False, length=20
            ),
            nullable=False,
        ),
        sa.Column("checkpoint_path", sa.String(length=500), nullable=True),
        sa.Column("iterations", sa.Integer(), nullable=False),
        sa.Column("train_seconds", sa.Float(), nullable=True),
        sa.Column("train_stats", sa.JSON(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("task_id", sa.String(length=100), nullable=True),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("enqueued_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("claimed_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("trained_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(["experiment_id"], ["experiments.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(
            ["parent_id"],
            ["models.id"],
        ),
        sa.ForeignKeyConstraint(["stage_id"], ["stages.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("stage_id", "increment"),
    )
    with op.batch_alter_table("models", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_models_experiment_id"), ["experiment_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_models_stage_id"), ["stage_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_models_status"), ["status"], unique=False)

    op.create_table(
        "parameter_sets",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("experiment_id", sa.Integer(), nullable=False),
        sa.Column("key", sa.String(length=100), nullable=False),
        sa.Column("split", sa.Enum("train", "test", name="split", native_enum=False, length=20), nullable=False),
        sa.Column("stage_id", sa.Integer(), nullable=True),
        sa.Column("increment", sa.Integer(), nullable=True),
        sa.Column("index", sa.Integer(), nullable=False),
        sa.Column("condition", sa.String(length=20), nullable=False),
        sa.Column("difficulty", sa.String(length=20), nullable=False),
        sa.Column("seed", sa.Integer(), nullable=False),
        sa.Column("theta", sa.JSON(), nullable=False),
        sa.Column(
            "status",
            sa.Enum("pending", "queued", "rendered", "failed", name="renderstatus", native_enum=False, length=20),
            nullable=False,
        ),
        sa.Column("rendered_theta", sa.JSON(), nullable=True),
        sa.Column("rejections", sa.JSON(), nullable=True),
        sa.Column("image_path", sa.String(length=500), nullable=True),
        sa.Column("label", sa.Integer(), nullable=True),
        sa.Column("box", sa.JSON(), nullable=True),
        sa.Column("amodal_box", sa.JSON(), nullable=True),
        sa.Column("visible_fraction", sa.Float(), nullable=True),
        sa.Column("render_seconds", sa.Float(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("enqueued_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("rendered_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(["experiment_id"], ["experiments.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["stage_id"], ["stages.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("experiment_id", "key"),
    )
    with op.batch_alter_table("parameter_sets", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_parameter_sets_experiment_id"), ["experiment_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_parameter_sets_stage_id"), ["stage_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_parameter_sets_status"), ["status"], unique=False)

    op.create_table(
        "evaluations",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("model_id", sa.Integer(), nullable=False),
        sa.Column("map", sa.Float(), nullable=True),
        sa.Column("map_unthresholded", sa.Float(), nullable=True),
        sa.Column("details", sa.JSON(), nullable=False),
        sa.Column("eval_seconds", sa.Float(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["model_id"], ["models.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("model_id"),
    )

    # Circular references (experiment -> final model, stage -> initial/best model) are added
    # once every table exists: PostgreSQL checks a foreign key's target at CREATE TABLE.
    with op.batch_alter_table("experiments") as batch_op:
        batch_op.create_foreign_key("fk_experiments_final_model", "models", ["final_model_id"], ["id"])
    with op.batch_alter_table("stages") as batch_op:
        batch_op.create_foreign_key("fk_stages_init_model", "models", ["init_model_id"], ["id"])
        batch_op.create_foreign_key("fk_stages_best_model", "models", ["best_model_id"], ["id"])


def downgrade() -> None:
    with op.batch_alter_table("stages") as batch_op:
        batch_op.drop_constraint("fk_stages_best_model", type_="foreignkey")
        batch_op.drop_constraint("fk_stages_init_model", type_="foreignkey")
    with op.batch_alter_table("experiments") as batch_op:
        batch_op.drop_constraint("fk_experiments_final_model", type_="foreignkey")
    op.drop_table("evaluations")
    with op.batch_alter_table("parameter_sets", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_parameter_sets_status"))
        batch_op.drop_index(batch_op.f("ix_parameter_sets_stage_id"))
        batch_op.drop_index(batch_op.f("ix_parameter_sets_experiment_id"))

    op.drop_table("parameter_sets")
    with op.batch_alter_table("models", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_models_status"))
        batch_op.drop_index(batch_op.f("ix_models_stage_id"))
        batch_op.drop_index(batch_op.f("ix_models_experiment_id"))

    op.drop_table("models")
    with op.batch_alter_table("stages", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_stages_experiment_id"))

    op.drop_table("stages")
    op.drop_table("experiments")
