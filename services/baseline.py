"""The paper's Table 2 (§3.2): a detector trained on canonical images only, scored on every
imaging condition of the table, which tells the conditions that hurt from those that do not.

The paper trained Fast R-CNN (ImageNet initialisation) on 2,500 canonical images for 20,000
iterations and tested 990 images per condition. Two ways to build it, one table:

- ``kind: canonical_baseline``, an experiment the scheduler runs like any other (one stage of
  canonical θ, its models and scores in the database): :func:`experiment_table2` reads the
  table from its last model's evaluation, for ``foldwise report`` (``table2-{id}.csv``) and
  ``GET /experiments/{id}/table2``;
- ``foldwise baseline CONFIG`` (:func:`canonical_baseline`): the same in this process with no
  database, at the sizes given, writing ``table2.csv``.

Both turn an evaluation's per-(condition, difficulty) breakdown into rows with
:func:`table2_rows` and write them with :func:`write_table2_csv`.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from foldwise.config import ExperimentConfig

# Table 2 of the paper (Fast R-CNN), by foldwise's condition codes.
PAPER_TABLE2 = {
    "fb": 0.3377, "mb": 0.4577, "po": 0.4352, "de": 0.5644, "sc": 0.5947, "eo": 0.5724, "cl": 0.9521,
    "li": 0.6681, "sh": 0.5887, "sp": 0.8110, "wr": 0.9434, "sn": 0.8349,
}  # fmt: skip

PAPER_SETUP = (
    "Fast R-CNN from ImageNet weights, 2,500 canonical images, 20,000 iterations, 990 test images per condition"
)


@dataclass(frozen=True)
class Table2Row:
    condition: str
    name: str
    map: float | None  # every difficulty's images of the condition together
    by_difficulty: dict[str, float | None]
    paper: float | None


@dataclass(frozen=True)
class Table2:
    """An experiment's Table 2: the scores of one model, ``final`` once the experiment finished
    (before then, of its latest evaluated model; ``model_id`` None before the first)."""

    model_id: int | None
    increment: int | None
    final: bool
    difficulties: list[str]
    rows: list[Table2Row]
    detector: str  # the detector family trained
    score_threshold: float  # the mAP protocol: detections below it dropped
    iou_threshold: float


def table2_rows(breakdown: dict[str, Any], conditions: Sequence[str], difficulties: Sequence[str]) -> list[Table2Row]:
    """One row per condition from an evaluation's breakdown (``EvaluationResult.to_dict()``'s):
    its mAP over every difficulty, at each difficulty, and the paper's figure beside it. A
    condition or difficulty the breakdown lacks (no test image rendered) is None."""
    from foldwise.conditions import load_condition_table

    table = load_condition_table()
    by_condition = breakdown.get("condition", {})
    by_pair = breakdown.get("condition/difficulty", {})
    return [
        Table2Row(
            condition=code,
            name=table.name(code),
            map=by_condition.get(code, {}).get("map"),
            by_difficulty={d: by_pair.get(f"{code}/{d}", {}).get("map") for d in difficulties},
            paper=PAPER_TABLE2.get(code),
        )
        for code in conditions
    ]


def write_table2_csv(rows: Sequence[Table2Row], difficulties: Sequence[str], path: Path) -> Path:
    """condition, name, map (all difficulties), one column per difficulty, the paper's mAP."""

    def cell(value: float | None) -> str:
        return "" if value is None else f"{value:.4f}"

    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["condition", "name", "map", *difficulties, "paper_fast_rcnn"])
        for row in rows:
            writer.writerow(
                [
                    row.condition,
                    row.name,
                    cell(row.map),
                    *(cell(row.by_difficulty[d]) for d in difficulties),
                    cell(row.paper),
                ]
            )
    return path


def experiment_table2(session, experiment_id: int) -> Table2:
    """The Table 2 of a ``kind: canonical_baseline`` experiment, as ``session`` reads it: every
    condition of its test set at each difficulty, from the evaluation its train task stored (the
    breakdown of P). Raises queries.NotFound for an unknown id."""
    from sqlalchemy import select

    from db.models import Evaluation, ExperimentStatus, Model, ModelStatus
    from foldwise.conditions import load_condition_table
    from services import queries

    experiment = queries.get_experiment(session, experiment_id)
    config = ExperimentConfig.model_validate(experiment.config)
    pairs = config.test_pairs()
    conditions = list(dict.fromkeys(c for c, _ in pairs))
    difficulties = [d for d in load_condition_table().difficulties if any(pd == d for _, pd in pairs)]
    finished = experiment.status == ExperimentStatus.finished and experiment.final_model_id is not None
    query = select(Model, Evaluation).join(Evaluation, Evaluation.model_id == Model.id)
    if finished:
        query = query.where(Model.id == experiment.final_model_id)
    else:  # running (or ended early): the latest score so far
        query = query.where(Model.experiment_id == experiment_id, Model.status == ModelStatus.evaluated)
    found = session.execute(query.order_by(Model.increment.desc()).limit(1)).first()
    model, evaluation = found if found is not None else (None, None)
    breakdown = evaluation.details.get("breakdown", {}) if evaluation is not None else {}
    return Table2(
        model_id=model.id if model else None,
        increment=model.increment if model else None,
        final=finished,
        difficulties=difficulties,
        rows=table2_rows(breakdown, conditions, difficulties),
        detector=config.detector.family,
        score_threshold=config.evaluation.score_threshold,
        iou_threshold=config.evaluation.iou_threshold,
    )


def canonical_baseline(
    config: ExperimentConfig,
    out: Path,
    train_images: int,
    iterations: int,
    test_per_pair: int,
    conditions: list[str] | None = None,
    echo: Callable[[str], None] = print,
) -> list[Table2Row]:
    """Render canonical training images, train once, render and score every condition."""
    from foldwise.conditions import load_condition_table
    from foldwise.theta import CANONICAL
    from workers.render.assets import load_assets
    from workers.render.cli import render_dataset
    from workers.train.checkpoint import load_detector
    from workers.train.data import load_coco_dataset
    from workers.train.evaluation import evaluate_detector
    from workers.train.training import train_detector

    table = load_condition_table()
    conditions = conditions or list(table.codes)
    assets = load_assets(config.assets)
    render = dict(image_size=config.render.image_size, backend=config.render.backend, assets=assets,
                  max_resamples=config.render.max_resamples, samples=config.render.samples, echo=echo)  # fmt: skip
    # Canonical θ ignore their condition: any code draws the same canonical distribution.
    render_dataset(out / "train", [table.codes[0]], [CANONICAL], train_images, config.seed, **render)
    samples, classes = load_coco_dataset(out / "train")
    echo(f"training {config.detector.family} on {len(samples)} canonical images for {iterations} iterations")
    model_path = out / "canonical.pt"
    textures = assets.textures(classes) if config.detector.texture_check else None
    train_detector(samples, None, iterations, config.detector, classes, model_path, seed=config.seed, textures=textures)
    render_dataset(out / "test", conditions, list(table.difficulties), test_per_pair, config.seed + 1, **render)
    test, _ = load_coco_dataset(out / "test")
    result = evaluate_detector(
        load_detector(model_path, device="cpu"), test, classes, score_threshold=config.evaluation.score_threshold,
        iou_threshold=config.evaluation.iou_threshold, coco=False,
    ).to_dict()  # fmt: skip
    difficulties = list(table.difficulties)
    rows = table2_rows(result["breakdown"], conditions, difficulties)
    write_table2_csv(rows, difficulties, out / "table2.csv")
    return rows
