"""Reads of what an experiment produced on disk: rendered images θ with their boxes, COCO
documents of a split, checkpoints. The API serves them (``services/api/routes/artifacts.py``)
and the dashboard shows them; files are resolved in the artifact store, never outside it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.models import Model, ParameterSet, RenderStatus, Split, Stage
from foldwise import store
from services.queries import NotFound, get_experiment


def _objects(row: ParameterSet) -> list[dict[str, Any]]:
    """Every target of an image (0..n), as the train worker reads them."""
    if row.objects is not None:
        return [{"box": list(o["box"]), "label": int(o["label"])} for o in row.objects]
    return [{"box": list(row.box), "label": int(row.label)}] if row.box else []


def image_url(experiment_id: int, parameter_set_id: int) -> str:
    return f"/experiments/{experiment_id}/images/{parameter_set_id}.png"


def latest_increment(session: Session, experiment_id: int) -> tuple[int, int] | None:
    """(stage order, k) of the newest increment a model trains or trained on; before the first
    model, of the newest rendered training images. Images rendered ahead for the next increment
    are not "the current increment": nothing has trained on them yet."""
    trained = session.execute(
        select(Stage.order, Model.increment)
        .join(Stage, Stage.id == Model.stage_id)
        .where(Model.experiment_id == experiment_id)
        .order_by(Stage.order.desc(), Model.increment.desc())
        .limit(1)
    ).first()
    if trained:
        return trained[0], trained[1]
    row = session.execute(
        select(Stage.order, ParameterSet.increment)
        .join(Stage, Stage.id == ParameterSet.stage_id)
        .where(
            ParameterSet.experiment_id == experiment_id,
            ParameterSet.split == Split.train,
            ParameterSet.status == RenderStatus.rendered,
        )
        .order_by(Stage.order.desc(), ParameterSet.increment.desc())
        .limit(1)
    ).first()
    return (row[0], row[1]) if row else None


def images(
    session: Session,
    experiment_id: int,
    split: Split,
    stage: int | None = None,
    k: int | None = None,
    limit: int = 100,
) -> dict[str, Any]:
    """Rendered images of a split with their boxes. Training images default to the newest
    increment (``stage`` and ``k`` pick another); test images are the whole test set."""
    get_experiment(session, experiment_id)
    query = select(ParameterSet).where(
        ParameterSet.experiment_id == experiment_id,
        ParameterSet.split == split,
        ParameterSet.status == RenderStatus.rendered,
    )
    if split == Split.train:
        if stage is None or k is None:
            newest = latest_increment(session, experiment_id)
            stage, k = (stage, k) if newest is None else (stage if stage is not None else newest[0], k or newest[1])
        query = query.join(Stage, Stage.id == ParameterSet.stage_id).where(
            Stage.order == stage, ParameterSet.increment == k
        )
    rows = session.scalars(query.order_by(ParameterSet.id).limit(limit)).all()
    return {
        "split": split.value,
        "stage": stage if split == Split.train else None,
        "k": k if split == Split.train else None,
        "images": [
            {
                "id": row.id,
                "url": image_url(experiment_id, row.id),
                "condition": row.condition,
                "difficulty": row.difficulty,
                "objects": _objects(row),
            }
            for row in rows
        ],
    }


def image_file(session: Session, experiment_id: int, parameter_set_id: int) -> Path:
    row = session.get(ParameterSet, parameter_set_id)
    if row is None or row.experiment_id != experiment_id:
        raise NotFound(f"image {parameter_set_id} is not part of experiment {experiment_id}")
    if row.status != RenderStatus.rendered or not row.image_path:
        raise NotFound(f"image {parameter_set_id} of experiment {experiment_id} is not rendered ({row.status.value})")
    path = store.resolve(row.image_path)
    if not path.is_file():
        raise NotFound(f"image {parameter_set_id} is recorded but its file is missing from the store")
    return path


def coco_document(session: Session, experiment_id: int, split: Split) -> dict[str, Any]:
    """The split's rendered images as COCO (the layout ``foldwise render --out`` writes), with
    ``file_name`` the URL each image is served at, and θ kept per image."""
    experiment = get_experiment(session, experiment_id)
    classes = list(experiment.classes or [])
    rows = session.scalars(
        select(ParameterSet)
        .where(
            ParameterSet.experiment_id == experiment_id,
            ParameterSet.split == split,
            ParameterSet.status == RenderStatus.rendered,
        )
        .order_by(ParameterSet.id)
    ).all()
    size = int(experiment.config.get("render", {}).get("image_size", 0)) or None
    document_images, annotations = [], []
    for row in rows:
        document_images.append(
            {
                "id": row.id,
                "file_name": image_url(experiment_id, row.id),
                "width": size,
                "height": size,
                "condition": row.condition,
                "difficulty": row.difficulty,
                "theta": row.rendered_theta or row.theta,
            }
        )
        for target in _objects(row):
            x0, y0, x1, y1 = target["box"]
            annotations.append(
                {
                    "id": len(annotations) + 1,
                    "image_id": row.id,
                    "category_id": target["label"] + 1,
                    "bbox": [x0, y0, x1 - x0, y1 - y0],
                    "area": (x1 - x0) * (y1 - y0),
                    "iscrowd": 0,
                }
            )
    return {
        "info": {"description": f"foldwise experiment {experiment_id} ({experiment.name}), {split.value} split"},
        "images": document_images,
        "annotations": annotations,
        "categories": [{"id": i + 1, "name": name} for i, name in enumerate(classes)],
    }


def checkpoint_file(session: Session, model_id: int) -> Path:
    model = session.get(Model, model_id)
    if model is None:
        raise NotFound(f"model {model_id} does not exist")
    if not model.checkpoint_path:
        raise NotFound(f"model {model_id} has no checkpoint yet ({model.status.value})")
    path = store.resolve(model.checkpoint_path)
    if not path.is_file():
        raise NotFound(f"model {model_id}'s checkpoint is recorded but missing from the store")
    return path
