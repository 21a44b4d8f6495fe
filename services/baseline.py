"""The paper's Table 2 (§3.2): a detector trained on canonical images only, scored on every
imaging condition of the table, which tells the conditions that hurt from those that do not.

The paper trained Fast R-CNN (ImageNet initialisation) on 2,500 canonical images for 20,000
iterations and tested 990 images per condition. `foldwise baseline CONFIG` does the same at the
sizes given (the config's detector, renderer, image size, assets and seed), in this process,
for every condition of ``configs/conditions.yaml``, including those added since the paper,
and prints its mAP per condition beside the paper's.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from foldwise.config import ExperimentConfig

# Table 2 of the paper (Fast R-CNN), by foldwise's condition codes.
PAPER_TABLE2 = {
    "fb": 0.3377, "mb": 0.4577, "po": 0.4352, "de": 0.5644, "sc": 0.5947, "eo": 0.5724, "cl": 0.9521,
    "li": 0.6681, "sh": 0.5887, "sp": 0.8110, "wr": 0.9434, "sn": 0.8349,
}  # fmt: skip


@dataclass(frozen=True)
class BaselineRow:
    condition: str
    name: str
    map: float | None  # every difficulty's images of the condition together
    by_difficulty: dict[str, float | None]
    paper: float | None


def canonical_baseline(
    config: ExperimentConfig,
    out: Path,
    train_images: int,
    iterations: int,
    test_per_pair: int,
    conditions: list[str] | None = None,
    echo: Callable[[str], None] = print,
) -> list[BaselineRow]:
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
    train_detector(samples, None, iterations, config.detector, classes, model_path, seed=config.seed)
    render_dataset(out / "test", conditions, list(table.difficulties), test_per_pair, config.seed + 1, **render)
    test, _ = load_coco_dataset(out / "test")
    result = evaluate_detector(
        load_detector(model_path, device="cpu"), test, classes, score_threshold=config.evaluation.score_threshold,
        iou_threshold=config.evaluation.iou_threshold, coco=False,
    ).to_dict()  # fmt: skip
    by_condition = result["breakdown"].get("condition", {})
    by_pair = result["breakdown"].get("condition/difficulty", {})
    rows = [
        BaselineRow(
            condition=code,
            name=table.name(code),
            map=by_condition.get(code, {}).get("map"),
            by_difficulty={d: by_pair.get(f"{code}/{d}", {}).get("map") for d in table.difficulties},
            paper=PAPER_TABLE2.get(code),
        )
        for code in conditions
    ]
    with open(out / "table2.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["condition", "name", "map", *table.difficulties, "paper_fast_rcnn"])
        for row in rows:
            writer.writerow([row.condition, row.name, row.map, *row.by_difficulty.values(), row.paper])
    return rows
