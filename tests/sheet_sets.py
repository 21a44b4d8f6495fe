"""Small COCO folders of the default textures placed on noise, for the benchmarks' tests."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

CLASSES = ["astronaut", "coffee"]


def class_textures() -> dict:
    """Each of CLASSES' texture (scikit-image's sample photographs), RGB."""
    import skimage.data

    return {name: getattr(skimage.data, name)() for name in CLASSES}


def sheet_set(folder: Path, n: int, textures: dict) -> list:
    """``n`` 200x150 images, each a texture of CLASSES (in turn) shrunk to 110 px wide, turned a
    little and placed on a blurred noise ground, as a COCO folder; the samples."""
    from workers.train.data import Sample

    rng = np.random.default_rng(5)
    (folder / "images").mkdir(parents=True)
    samples, images, annotations = [], [], []
    for index in range(n):
        label = index % len(CLASSES)
        texture = textures[CLASSES[label]]
        ground = cv2.GaussianBlur(rng.integers(0, 255, (150, 200, 3)).astype(np.uint8), (0, 0), 3)
        affine = cv2.getRotationMatrix2D((0, 0), float(rng.uniform(-15, 15)), 110 / texture.shape[1])
        affine[:, 2] += (40 + rng.uniform(-10, 10), 30 + rng.uniform(-10, 10))
        warped = cv2.warpAffine(texture, affine, (200, 150))
        mask = cv2.warpAffine(np.full(texture.shape[:2], 255, np.uint8), affine, (200, 150)) > 0
        ys, xs = np.nonzero(mask)
        box = [float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())]
        path = folder / "images" / f"{index}.png"
        cv2.imwrite(str(path), cv2.cvtColor(np.where(mask[:, :, None], warped, ground), cv2.COLOR_RGB2BGR))
        samples.append(Sample(path, np.array([box], np.float32), np.array([label]), condition="fb", difficulty="easy"))
        images.append({"id": index + 1, "file_name": f"images/{index}.png", "width": 200, "height": 150})
        x0, y0, x1, y1 = box
        annotations.append(
            {"id": index + 1, "image_id": index + 1, "category_id": label + 1, "bbox": [x0, y0, x1 - x0, y1 - y0]}
        )
    categories = [{"id": i + 1, "name": name} for i, name in enumerate(CLASSES)]
    (folder / "annotations.json").write_text(
        json.dumps({"images": images, "annotations": annotations, "categories": categories})
    )
    return samples
