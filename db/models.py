"""SQLAlchemy 2 typed models of the active-learning record.

The scheduler's decisions are a pure function of these rows, so everything it needs to
continue after a crash is here: which θ exist and are rendered, which ω exist, their
parents (ω_in), and their scores P. Paths are relative to the artifact store.
"""

from __future__ import annotations

import enum
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import JSON, DateTime, Enum, Float, ForeignKey, String, Text, TypeDecorator, UniqueConstraint
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC datetimes on every backend: SQLite keeps no zone, so one is attached
    on the way out, and every reader can compare and subtract times without special cases."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_result_value(self, value: datetime | None, dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON, list[Any]: JSON, datetime: UTCDateTime()}


def _enum(cls: type[enum.Enum]) -> Enum:
    # Stored as plain strings (no native enum types) so migrations stay simple on every backend.
    return Enum(cls, native_enum=False, length=20, values_callable=lambda e: [m.value for m in e])


class ExperimentStatus(str, enum.Enum):
    pending = "pending"
    running = "running"
    finished = "finished"
    failed = "failed"
    cancelled = "cancelled"


class StageStatus(str, enum.Enum):
    pending = "pending"
    running = "running"
    done = "done"


class StageEndReason(str, enum.Enum):
    plateau = "plateau"  # Algorithm 1: |P_M - P_N| <= τ
    cap = "cap"  # Algorithm 1: active_learning.max_increments reached
    # Algorithm 2 (kind: learnability): its fixed κ increments done. A new value of a
    # non-native enum column (a VARCHAR(20) without a CHECK constraint): no migration.
    kappa = "kappa"
    # kind: canonical_baseline: its canonical_baseline.increments done (no migration either).
    increments = "increments"


class Split(str, enum.Enum):
    train = "train"
    test = "test"


class RenderStatus(str, enum.Enum):
    pending = "pending"  # sampled, not yet sent to a render worker
    queued = "queued"  # sent
    rendered = "rendered"
    failed = "failed"  # every resample rejected, or the worker raised
    discarded = "discarded"  # sampled ahead, never needed: the experiment ended first


class ModelStatus(str, enum.Enum):
    pending = "pending"  # decided, not yet sent
    queued = "queued"
    training = "training"
    evaluated = "evaluated"
    failed = "failed"
    discarded = "discarded"  # the experiment ended (failed or cancelled) before it was trained


class Experiment(Base):
    __tablename__ = "experiments"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    # Experiments run side by side to be compared (one per detector, or per reset/grow choice).
    study: Mapped[str | None] = mapped_column(String(200), index=True)
    config: Mapped[dict[str, Any]]
    seed: Mapped[int]
    # Detector classes: the object names, fixed when the experiment starts.
    classes: Mapped[list[Any] | None] = mapped_column(JSON)
    status: Mapped[ExperimentStatus] = mapped_column(_enum(ExperimentStatus), default=ExperimentStatus.pending)
    error: Mapped[str | None] = mapped_column(Text)
    final_model_id: Mapped[int | None] = mapped_column(
        ForeignKey("models.id", use_alter=True, name="fk_experiments_final_model")
    )
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]

    stages: Mapped[list[Stage]] = relationship(back_populates="experiment", order_by="Stage.order")


class Stage(Base):
    """One (condition c, difficulty δ) of the curriculum: its increments k and why it ended."""

    __tablename__ = "stages"
    __table_args__ = (UniqueConstraint("experiment_id", "order"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    experiment_id: Mapped[int] = mapped_column(ForeignKey("experiments.id", ondelete="CASCADE"), index=True)
    order: Mapped[int]
    condition: Mapped[str] = mapped_column(String(20))
    difficulty: Mapped[str] = mapped_column(String(20))
    status: Mapped[StageStatus] = mapped_column(_enum(StageStatus), default=StageStatus.pending)
    end_reason: Mapped[StageEndReason | None] = mapped_column(_enum(StageEndReason))
    init_model_id: Mapped[int | None] = mapped_column(
        ForeignKey("models.id", use_alter=True, name="fk_stages_init_model")
    )
    best_model_id: Mapped[int | None] = mapped_column(
        ForeignKey("models.id", use_alter=True, name="fk_stages_best_model")
    )
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]

    experiment: Mapped[Experiment] = relationship(back_populates="stages")


class ParameterSet(Base):
    """A θ: what one image shows. Test θ have no stage; train θ belong to (stage, k).

    ``theta`` holds the record of ``foldwise.theta`` (any version: ``Theta.parse`` reads them all)."""

    __tablename__ = "parameter_sets"
    __table_args__ = (UniqueConstraint("experiment_id", "key"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    experiment_id: Mapped[int] = mapped_column(ForeignKey("experiments.id", ondelete="CASCADE"), index=True)
    # Where this θ sits in the experiment ("test/fb/easy/3", "train/2/5/17"): a second
    # scheduler decision for the same slot collides here instead of sampling twice.
    key: Mapped[str] = mapped_column(String(100))
    split: Mapped[Split] = mapped_column(_enum(Split))
    stage_id: Mapped[int | None] = mapped_column(ForeignKey("stages.id", ondelete="CASCADE"), index=True)
    increment: Mapped[int | None]
    index: Mapped[int]
    condition: Mapped[str] = mapped_column(String(20))
    difficulty: Mapped[str] = mapped_column(String(20))
    seed: Mapped[int]
    theta: Mapped[dict[str, Any]]
    status: Mapped[RenderStatus] = mapped_column(_enum(RenderStatus), default=RenderStatus.pending, index=True)
    # What was actually rendered: θ itself, or the resample that replaced a rejected θ.
    rendered_theta: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    rejections: Mapped[list[Any] | None] = mapped_column(JSON)
    # Why a mixed stage's training θ was drawn: {"sampling": "uniform"} or {"sampling": "failure",
    # "model_id": the scored model it follows, "cells": {"fb/hard": {"ap": .., "p": ..}}} for
    # each of its (condition, difficulty) components; None for test and single-condition θ.
    drawn_for: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    image_path: Mapped[str | None] = mapped_column(String(500))
    # Every target in the image ({object, label, box, amodal_box, visible_fraction} each; an
    # empty list for an image without the object); label, box, amodal_box and visible_fraction
    # repeat the first one (θ's own object), None when there is none.
    objects: Mapped[list[Any] | None] = mapped_column(JSON)
    label: Mapped[int | None]
    box: Mapped[list[Any] | None] = mapped_column(JSON)
    amodal_box: Mapped[list[Any] | None] = mapped_column(JSON)
    visible_fraction: Mapped[float | None] = mapped_column(Float)
    render_seconds: Mapped[float | None] = mapped_column(Float)
    error: Mapped[str | None] = mapped_column(Text)
    enqueued_at: Mapped[datetime | None]
    rendered_at: Mapped[datetime | None]
    # How often rendering it started: a θ that kills its worker on every delivery is given up
    # after tasks.max_deliveries instead of being redelivered forever.
    attempts: Mapped[int] = mapped_column(default=0, server_default="0")
    # The render delivery working on it and when it last renewed its claim (every lease/4): a
    # claim not renewed for a lease has lost its worker. sends counts the messages sent for it.
    task_id: Mapped[str | None] = mapped_column(String(100))
    claimed_at: Mapped[datetime | None]
    sends: Mapped[int] = mapped_column(default=0, server_default="0")


class Model(Base):
    """A detector ω_k: trained for t iterations from its parent ω_in on the θ of (stage, k)."""

    __tablename__ = "models"
    __table_args__ = (UniqueConstraint("stage_id", "increment"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    experiment_id: Mapped[int] = mapped_column(ForeignKey("experiments.id", ondelete="CASCADE"), index=True)
    stage_id: Mapped[int] = mapped_column(ForeignKey("stages.id", ondelete="CASCADE"), index=True)
    increment: Mapped[int]
    parent_id: Mapped[int | None] = mapped_column(ForeignKey("models.id"))
    detector: Mapped[str] = mapped_column(String(40))
    status: Mapped[ModelStatus] = mapped_column(_enum(ModelStatus), default=ModelStatus.pending, index=True)
    checkpoint_path: Mapped[str | None] = mapped_column(String(500))
    iterations: Mapped[int]
    train_seconds: Mapped[float | None] = mapped_column(Float)
    train_stats: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text)
    # The delivery that owns the training: a duplicate message skips, a redelivery of the
    # same message (worker lost) takes over. attempts counts how often training started.
    task_id: Mapped[str | None] = mapped_column(String(100))
    attempts: Mapped[int] = mapped_column(default=0)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    enqueued_at: Mapped[datetime | None]
    claimed_at: Mapped[datetime | None]
    trained_at: Mapped[datetime | None]
    # How many messages were sent for it (re-sends after a lost worker or broker included).
    sends: Mapped[int] = mapped_column(default=0, server_default="0")

    evaluation: Mapped[Evaluation | None] = relationship(back_populates="model", uselist=False)


class Evaluation(Base):
    """An entry of P: ω's score on the standard test set."""

    __tablename__ = "evaluations"

    id: Mapped[int] = mapped_column(primary_key=True)
    model_id: Mapped[int] = mapped_column(ForeignKey("models.id", ondelete="CASCADE"), unique=True)
    # The paper's protocol (detections below the confidence threshold dropped); None when not finite.
    map: Mapped[float | None] = mapped_column(Float)
    map_unthresholded: Mapped[float | None] = mapped_column(Float)
    details: Mapped[dict[str, Any]]
    eval_seconds: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    model: Mapped[Model] = relationship(back_populates="evaluation")
