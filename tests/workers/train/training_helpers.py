"""Tiny detectors and datasets for training tests: three colour classes on noise, 64 px."""

from __future__ import annotations

import cv2
import numpy as np

from foldwise.config import DetectorConfig
from workers.train.data import Sample

CLASSES = ["red", "green", "blue"]
COLOURS = [(220, 40, 40), (40, 220, 40), (40, 40, 220)]


def config(**changes) -> DetectorConfig:
    small = {
        "input_size": 64,
        "batch_size": 2,
        "num_threads": 1,
        "device": "cpu",
        "warmup_iterations": 2,
        "rpn_proposals_train": 40,
        "fpn_channels": 32,
        "representation_size": 64,
        "rpn_proposals_test": 20,
        "roi_samples_per_image": 32,
        "edge_boxes": 30,
    }
    return DetectorConfig(**{**small, **changes})


def synthetic_samples(folder, n=6, size=64, seed=0, empty=False) -> list[Sample]:
    """Noise images with one striped coloured rectangle (the class) each, written as PNG."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    samples = []
    for index in range(n):
        image = rng.integers(60, 130, (size, size, 3)).astype(np.uint8)
        label = index % len(CLASSES)
        w, h = rng.integers(size // 3, size - 8, 2)
        x0, y0 = rng.integers(0, size - w), rng.integers(0, size - h)
        boxes, labels = np.zeros((0, 4), np.float32), np.zeros((0,), np.int64)
        if not empty:
            image[y0 : y0 + h, x0 : x0 + w] = COLOURS[label]
            image[y0 : y0 + h : 5, x0 : x0 + w] = 0
            boxes, labels = np.array([[x0, y0, x0 + w, y0 + h]], np.float32), np.array([label])
        path = folder / f"{index}.png"
        cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        samples.append(Sample(path, boxes, labels, condition="fb", difficulty="easy"))
    return samples


def with_a_few_matches(monkeypatch, checker, *rows) -> None:
    """The checker finds the image's own keypoints and matches, and for each (box, class) row three
    more of that class inside the box, each matched to a random point of its texture: some
    evidence of the class, too little for a map (a blurred or steeply tilted sheet)."""
    own = type(checker)._keypoints_and_matches
    places = np.array([[0.3, 0.3], [0.5, 0.6], [0.7, 0.4]], np.float32)

    def found(gray):
        every, points, labels, texture_points = own(checker, gray)
        added = [np.asarray(box[:2], np.float32) + places * (np.asarray(box[2:]) - box[:2]) for box, _ in rows]
        added = np.concatenate(added).astype(np.float32)
        classes = np.repeat([label for _, label in rows], len(places)).astype(np.int64)
        random_points = np.random.default_rng(0).uniform(0, 200, (len(added), 2)).astype(np.float32)
        return (
            np.concatenate([every, added]),
            np.concatenate([points, added]),
            np.concatenate([labels, classes]),
            np.concatenate([texture_points, random_points]),
        )

    monkeypatch.setattr(checker, "_keypoints_and_matches", found)
