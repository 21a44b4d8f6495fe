"""Fine-tuning a foldwise model on real photographs (the paper's §5.5.2 and Fig. 11).

A real set is read by ``workers.train.data.load_dataset``: a COCO JSON file (or a folder holding
``annotations.json``) or a Pascal VOC folder (``Annotations/*.xml`` beside ``JPEGImages/``). Its classes are matched to the
checkpoint's by name, and it may hold a subset of them; labels are renumbered to the
checkpoint's order, so the fine-tuned model keeps every class it had. The set is split once,
by a seeded shuffle, into a training pool and a test split; for each size n of the sweep the
checkpoint is fine-tuned on the first n pool images, a fresh model (the checkpoint's
architecture, new weights) is trained on the same n beside it, and both are scored on the
test split under the paper's protocol.

An ensemble (what ``foldwise run --members`` hands over) is fine-tuned member by member, each
from its own weights with its own settings, and the members are joined again into an ensemble
file; its fresh baseline is an ensemble of as many fresh models, one per member's
architecture. Fig. 11 then reports the ensemble on both lines.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from workers.train.data import DatasetError, Sample


def match_classes(samples: list[Sample], classes: list[str], model_classes: list[str]) -> list[Sample]:
    """The samples with labels renumbered to ``model_classes`` (matched by name); a class the
    model does not know is an error that lists the ones it does."""
    unknown = [name for name in classes if name not in model_classes]
    if unknown:
        raise DatasetError(
            f"the real set has class(es) {unknown} that the model does not know; its classes: {', '.join(model_classes)}"
        )
    mapping = np.asarray([model_classes.index(name) for name in classes], dtype=np.int64)
    return [
        Sample(s.image_path, s.boxes, mapping[s.labels] if len(s.labels) else s.labels, s.condition, s.difficulty)
        for s in samples
    ]


def split(samples: list[Sample], test_fraction: float, seed: int) -> tuple[list[Sample], list[Sample]]:
    """(training pool, test split), by one seeded shuffle: the pool's first n are the sweep's n."""
    if not 0 < test_fraction < 1:
        raise ValueError(f"test fraction must be between 0 and 1, got {test_fraction}")
    order = np.random.default_rng(seed).permutation(len(samples))
    n_test = max(1, int(round(len(samples) * test_fraction)))
    if n_test >= len(samples):
        raise DatasetError(f"{len(samples)} real images cannot make both a training pool and a test split")
    test = [samples[i] for i in order[:n_test]]
    pool = [samples[i] for i in order[n_test:]]
    return pool, test


@dataclass(frozen=True)
class SweepPoint:
    n: int
    finetuned_map: float
    fresh_map: float | None  # None at n = 0: a fresh model trained on nothing is not a model
    finetuned_unthresholded: float
    fresh_unthresholded: float | None


def member_checkpoints(checkpoint: Path, folder: Path) -> list[Path]:
    """The detector checkpoints a file joins: itself for one detector; for an ensemble, each
    member written whole to ``folder/member-<i>.pt`` (training starts from one network's file)."""
    import torch

    from workers.train.checkpoint import ENSEMBLE_FORMAT, _load_payload

    payload = _load_payload(checkpoint)
    if payload["format"] != ENSEMBLE_FORMAT:
        return [Path(checkpoint)]
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for index, member in enumerate(payload["members"], start=1):
        path = folder / f"member-{index}.pt"
        torch.save(member, path)
        paths.append(path)
    return paths


def sweep(
    checkpoint: Path,
    pool: list[Sample],
    test: list[Sample],
    sizes: list[int],
    iterations: int,
    out_dir: Path,
    seed: int = 0,
    on_point: Callable[[SweepPoint], None] | None = None,
) -> list[SweepPoint]:
    """Fine-tune the checkpoint and train a fresh model on the first n pool images for each n.
    An ensemble checkpoint gives ensembles (``finetuned-<n>.pt``, ``fresh-<n>.pt``) of models
    trained member by member (``members/``)."""
    from foldwise.config import DetectorConfig
    from workers.train.checkpoint import load_detector, payload_textures, read_checkpoint, save_ensemble
    from workers.train.evaluation import evaluate_detector
    from workers.train.training import train_detector

    too_many = [n for n in sizes if n > len(pool)]
    if too_many:
        raise DatasetError(f"sweep sizes {too_many} exceed the {len(pool)} images of the training pool")
    out_dir.mkdir(parents=True, exist_ok=True)
    members = member_checkpoints(checkpoint, out_dir / "members")
    payloads = [read_checkpoint(path) for path in members]
    classes = list(payloads[0]["meta"]["classes"])

    def score(path: Path) -> tuple[float, float]:
        result = evaluate_detector(
            load_detector(path, device="cpu"), test, classes, score_threshold=0.8, iou_threshold=0.5, coco=False
        )
        return result.map, result.map_unthresholded

    def train_all(n: int, kind: str) -> Path:
        """One model per member, on the first n pool images, joined when there are several."""
        target = out_dir / f"{kind}-{n}.pt"
        paths = (
            [target]
            if len(members) == 1
            else [out_dir / "members" / f"{kind}-{n}-{i}.pt" for i in range(1, len(members) + 1)]
        )
        for index, (member, payload, path) in enumerate(zip(members, payloads, paths)):
            config = DetectorConfig.model_validate(payload["meta"]["config"])
            # Members differ by seed: a fresh ensemble of one seed would be one model repeated.
            member_seed = seed + index
            if kind == "finetuned":
                train_detector(
                    pool[:n],
                    init=member,
                    iterations=iterations,
                    config=config,
                    classes=classes,
                    out=path,
                    seed=member_seed,
                )
            else:  # the fresh model checks with the same textures
                train_detector(
                    pool[:n], init=None, iterations=iterations, config=config, classes=classes, out=path, seed=member_seed,
                    textures=payload_textures(payload), lookalikes=payload_textures(payload, "lookalikes"),
                )  # fmt: skip
        if len(paths) > 1:
            save_ensemble(paths, target)
        return target

    points = []
    for n in sizes:
        if n == 0:
            finetuned, fresh = score(checkpoint), (None, None)
        else:
            finetuned, fresh = score(train_all(n, "finetuned")), score(train_all(n, "fresh"))
        point = SweepPoint(n, finetuned[0], fresh[0], finetuned[1], fresh[1])
        points.append(point)
        if on_point:
            on_point(point)
    return points


def write_fig11(points: list[SweepPoint], out_dir: Path, title: str) -> list[Path]:
    """Fig. 11: mAP on the real test split against the number of real training images."""
    import matplotlib

    matplotlib.use("Agg")
    matplotlib.rcParams["svg.fonttype"] = "none"
    import matplotlib.pyplot as plt

    paths = [out_dir / f"fig11.{suffix}" for suffix in ("png", "svg", "csv")]
    with open(paths[2], "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(SweepPoint.__dataclass_fields__))
        writer.writeheader()
        writer.writerows(point.__dict__ for point in points)
    figure, ax = plt.subplots(figsize=(7, 4.2), constrained_layout=True)
    ax.plot([p.n for p in points], [p.finetuned_map for p in points], "o-", label="fine-tuned from the foldwise model")
    fresh = [(p.n, p.fresh_map) for p in points if p.fresh_map is not None]
    if fresh:
        ax.plot(*zip(*fresh), "s--", label="fresh initialisation, same images")
    ax.set_xlabel("real training images (count)")
    ax.set_ylabel("mAP on the real test split")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"Fig. 11: fine-tuning on real images ({title}); mAP (score ≥ 0.8, IoU ≥ 0.5)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    figure.savefig(paths[0], dpi=120)
    figure.savefig(paths[1])
    plt.close(figure)
    (out_dir / "fig11.json").write_text(json.dumps([p.__dict__ for p in points], indent=2))
    return paths
