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
