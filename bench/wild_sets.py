"""The sets bench/wild.py scores on, each a COCO folder reused while its recipe is unchanged.

``make_ood_set``: the out-of-domain scene (bench/wild_scene.py) rendered for an ``OodRecipe``;
``make_in_domain_set``: foldwise's own renders of what a config's loop scores; ``make_reframed_set``
and ``make_rotated_set``: the in-domain images in 4:3 / 3:4 frames and turned by quarter turns.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from bench.wild_scene import OodRecipe, OodScene, load_textures


def _scene_kind(objects, fill: float, negative: bool) -> str:
    if negative:
        return "negative"
    if len(objects) > 1:
        return "several"
    if objects[0][2] < 0.8:
        return "occluded"
    return "small" if fill < 0.25 else "medium" if fill < 0.6 else "large" if fill < 1.0 else "frame-filling"


def make_ood_set(out: Path, recipe: OodRecipe, echo=print, assets=None, lookalikes: Path | None = None) -> Path:
    """Render the out-of-domain set into ``out`` (COCO folder) unless the same recipe is there
    (``assets``, ``lookalikes``: where the textures of ``recipe.classes`` and ``recipe.lookalikes`` are)."""
    import cv2

    out = Path(out)
    manifest = out / "annotations.json"
    if manifest.is_file() and json.loads(manifest.read_text()).get("info", {}).get("recipe") == recipe.key():
        echo(f"out-of-domain set: reusing {out} (recipe {recipe.key()})")
        return out
    (out / "images").mkdir(parents=True, exist_ok=True)
    scene = OodScene(
        load_textures(recipe.classes, recipe.photos, assets, lookalikes if recipe.lookalikes else None), recipe
    )
    rng = np.random.default_rng(recipe.seed)
    images, annotations = [], []
    started = time.perf_counter()
    redraws = 0
    for index in range(recipe.n):
        negative = bool(rng.random() < recipe.negatives)
        seed = int(rng.integers(0, 2**62))
        for attempt in range(20):
            result = scene.render(seed + attempt, negative)
            if result is not None:
                break
            redraws += 1
        else:
            raise RuntimeError(f"out-of-domain image {index}: no valid scene in 20 draws")
        image, objects, info = result
        file_name = f"images/wild_{index:05d}.jpg"
        cv2.imwrite(str(out / file_name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 97])
        kind = _scene_kind(objects, info["fill"], negative)
        images.append(
            {
                "id": index + 1,
                "file_name": file_name,
                "width": recipe.width,
                "height": recipe.height,
                "condition": "wild",
                "difficulty": kind,
                "scene": info,
            }
        )
        for name, box, fraction in objects:
            x0, y0, x1, y1 = box
            annotations.append(
                {
                    "id": len(annotations) + 1,
                    "image_id": index + 1,
                    "category_id": recipe.classes.index(name) + 1,
                    "bbox": [x0, y0, x1 - x0, y1 - y0],
                    "area": (x1 - x0) * (y1 - y0),
                    "iscrowd": 0,
                    "visible_fraction": fraction,
                }
            )
        if (index + 1) % 25 == 0:
            echo(f"out-of-domain: {index + 1}/{recipe.n} images, {time.perf_counter() - started:.0f} s")
    coco = {
        "info": {
            "description": "foldwise out-of-domain benchmark set (bench/wild.py)",
            "recipe": recipe.key(),
            "recipe_fields": asdict(recipe),
            "redraws": redraws,
            "seconds": time.perf_counter() - started,
        },
        "images": images,
        "annotations": annotations,
        "categories": [{"id": i + 1, "name": name} for i, name in enumerate(recipe.classes)],
    }
    manifest.write_text(json.dumps(coco, indent=1))
    echo(
        f"out-of-domain: wrote {recipe.n} images to {out} in {time.perf_counter() - started:.0f} s ({redraws} redraws)"
    )
    return out


def make_in_domain_set(config, out: Path, n_per_pair: int, seed: int, echo=print) -> Path:
    """foldwise's own renders of what the config's loop scores (``test_pairs``: every condition of
    its curriculum at every difficulty, and its mixed stages), ``n_per_pair`` each.

    The cache key holds what the renders depend on (the curriculum's conditions and
    difficulties, the render size and backend, the assets, the count and the seed), not the rest
    of the config: two configs that differ in their detector or training score on one set."""
    from workers.render.assets import load_assets
    from workers.render.cli import render_dataset

    pairs = config.test_pairs()
    conditions = sorted(
        {condition for condition, _ in pairs if condition != "canonical"}, key=[c for c, _ in pairs].index
    )
    difficulties = list(config.curriculum.difficulties)
    recipe = [
        conditions,
        difficulties,
        config.render.image_size,
        config.render.backend,
        config.assets.model_dump(mode="json"),
        n_per_pair,
        seed,
    ]
    key = hashlib.sha256(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:16]
    manifest = out / "annotations.json"
    if manifest.is_file() and json.loads(manifest.read_text()).get("info", {}).get("recipe") == key:
        echo(f"in-domain set: reusing {out}")
        return out
    assets = load_assets(config.assets)
    coco = render_dataset(
        out,
        conditions,
        difficulties,
        n_per_pair,
        seed,
        config.render.image_size,
        config.render.backend,
        assets,
        echo=lambda *_: None,
    )
    coco["info"]["recipe"] = key
    manifest.write_text(json.dumps(coco, indent=1))
    echo(f"in-domain set: {len(coco['images'])} images ({', '.join(conditions)} × {', '.join(difficulties)})")
    return out


def make_reframed_set(source: Path, out: Path) -> Path:
    """foldwise's own renders in other frames: each square image padded (mirrored edges) to 4:3
    landscape or, every other image, 3:4 portrait, boxes moved with it. The objects are the
    in-domain ones; only the frame changes, which tells framing apart from appearance."""
    import cv2

    document = json.loads((source / "annotations.json").read_text())
    (out / "images").mkdir(parents=True, exist_ok=True)
    shifts = {}
    for index, image in enumerate(document["images"]):
        pixels = cv2.imread(str(source / image["file_name"]), cv2.IMREAD_COLOR)
        height, width = pixels.shape[:2]
        if index % 2 == 0:  # landscape: pad left and right
            extra = int(round(width * 4 / 3)) - width
            left, top = extra // 2, 0
            framed = cv2.copyMakeBorder(pixels, 0, 0, left, extra - left, cv2.BORDER_REFLECT)
        else:  # portrait: pad top and bottom
            extra = int(round(height * 4 / 3)) - height
            left, top = 0, extra // 2
            framed = cv2.copyMakeBorder(pixels, top, extra - top, 0, 0, cv2.BORDER_REFLECT)
        cv2.imwrite(str(out / image["file_name"]), framed)
        image["height"], image["width"] = framed.shape[:2]
        shifts[image["id"]] = (left, top)
    for annotation in document["annotations"]:
        left, top = shifts[annotation["image_id"]]
        annotation["bbox"][0] += left
        annotation["bbox"][1] += top
        annotation.pop("amodal_bbox", None)
    (out / "annotations.json").write_text(json.dumps(document))
    return out


def make_rotated_set(source: Path, out: Path) -> Path:
    """foldwise's own renders turned by a quarter, a half and three quarters of a turn (in
    turn, image by image), boxes turned with them exactly. A camera held at any roll sees the
    sheet at any in-plane angle; the renderer turns the sheet only where a condition draws a
    rotation, so this tells whether the detector learned the object or its upright look."""
    import cv2

    document = json.loads((source / "annotations.json").read_text())
    (out / "images").mkdir(parents=True, exist_ok=True)
    turns = {}
    for index, image in enumerate(document["images"]):
        pixels = cv2.imread(str(source / image["file_name"]), cv2.IMREAD_COLOR)
        quarter = index % 3 + 1  # counter-clockwise quarter turns
        cv2.imwrite(str(out / image["file_name"]), np.ascontiguousarray(np.rot90(pixels, quarter)))
        turns[image["id"]] = (quarter, image["width"], image["height"])
        if quarter % 2:
            image["width"], image["height"] = image["height"], image["width"]
    for annotation in document["annotations"]:
        quarter, width, height = turns[annotation["image_id"]]
        x, y, w, h = annotation["bbox"]
        for _ in range(quarter):  # one counter-clockwise quarter turn: (x, y) -> (y, width - x)
            x, y, w, h = y, width - x - w, h, w
            width, height = height, width
        annotation["bbox"] = [x, y, w, h]
        annotation.pop("amodal_bbox", None)
        annotation.pop("segmentation", None)
    (out / "annotations.json").write_text(json.dumps(document))
    return out
