"""A stand-in for real photographs, to try `foldwise finetune` without any: NOT real photos.

Each image is a photograph that ships with scikit-image (a brick wall, grass, gravel, the
cameraman, coins, a page of text...) with one or two object textures printed onto it through a
random homography (a flat print seen at an angle, cv2.warpPerspective), with a little blur,
noise and JPEG. The boxes are the warped corners' extent. It is written as a Pascal VOC folder
and as COCO, so both importers can be tried:

    python bench/standin_real.py --out var/standin --n 80 --classes coffee,astronaut
    foldwise finetune --model M.pt --data var/standin/voc --sweep 0,10,20,40 --out var/finetune

Nothing of foldwise's renderer is used, but these are still synthetic images: measure on
photographs of your own object before trusting a number.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

BACKGROUNDS = ("brick", "grass", "gravel", "camera", "coins", "page", "moon", "text", "clock")


def _photo(name: str) -> np.ndarray:
    import skimage.data

    image = skimage.data.stereo_motorcycle()[0] if name == "motorcycle_left" else getattr(skimage.data, name)()
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    return np.ascontiguousarray(image[:, :, :3].astype(np.uint8))


def make_standin_set(out: Path, n: int, classes: list[str], size: tuple[int, int] = (160, 120), seed: int = 0) -> Path:
    """Write ``out/voc`` (Annotations, JPEGImages) and ``out/coco.json`` (file names relative to ``out``)."""
    import cv2

    rng = np.random.default_rng(seed)
    width, height = size
    textures = {name: _photo(name) for name in classes}
    (out / "voc" / "Annotations").mkdir(parents=True, exist_ok=True)
    (out / "voc" / "JPEGImages").mkdir(parents=True, exist_ok=True)
    coco = {"images": [], "annotations": [], "categories": [{"id": i + 1, "name": c} for i, c in enumerate(classes)]}
    for index in range(n):
        background = _photo(BACKGROUNDS[rng.integers(len(BACKGROUNDS))])
        canvas = cv2.resize(background, (width, height), interpolation=cv2.INTER_AREA)
        objects = []
        for _ in range(int(rng.integers(1, 3))):
            name = classes[int(rng.integers(len(classes)))]
            texture = textures[name]
            h, w = texture.shape[:2]
            side = rng.uniform(0.3, 0.6) * min(width, height)
            cx, cy = rng.uniform(side / 2, width - side / 2), rng.uniform(side / 2, height - side / 2)
            aspect = w / h
            half = np.array([side * aspect / 2, side / 2]) if aspect < 1.6 else np.array([side / 2, side / 2 / aspect])
            corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half
            angle = rng.uniform(-0.6, 0.6)
            rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
            quad = corners @ rotation.T * (1 + rng.uniform(-0.15, 0.15, (4, 1))) + [
                cx,
                cy,
            ]  # perspective: corners apart
            quad = np.clip(quad, 0, [width - 1, height - 1]).astype(np.float32)
            source = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float32)
            matrix = cv2.getPerspectiveTransform(source, quad)
            warped = cv2.warpPerspective(texture, matrix, (width, height), flags=cv2.INTER_AREA)
            mask = cv2.warpPerspective(np.full((h, w), 255, np.uint8), matrix, (width, height)) > 127
            canvas[mask] = warped[mask]
            x0, y0 = quad.min(axis=0)
            x1, y1 = quad.max(axis=0)
            objects.append((name, [float(x0), float(y0), float(x1) + 1, float(y1) + 1]))
        canvas = cv2.GaussianBlur(canvas, (3, 3), rng.uniform(0.1, 0.8))
        canvas = np.clip(canvas + rng.normal(0, 3, canvas.shape), 0, 255).astype(np.uint8)
        filename = f"standin_{index:04d}.jpg"
        cv2.imwrite(str(out / "voc" / "JPEGImages" / filename), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(60, 95))])  # fmt: skip
        xml_objects = "".join(
            f"<object><name>{name}</name><bndbox><xmin>{box[0] + 1:.1f}</xmin><ymin>{box[1] + 1:.1f}</ymin>"
            f"<xmax>{box[2]:.1f}</xmax><ymax>{box[3]:.1f}</ymax></bndbox></object>"
            for name, box in objects
        )
        (out / "voc" / "Annotations" / f"standin_{index:04d}.xml").write_text(
            f"<annotation><filename>{filename}</filename><size><width>{width}</width><height>{height}</height>"
            f"<depth>3</depth></size>{xml_objects}</annotation>"
        )
        coco["images"].append(
            {"id": index + 1, "file_name": f"voc/JPEGImages/{filename}", "width": width, "height": height}
        )
        for name, box in objects:
            coco["annotations"].append({
                "id": len(coco["annotations"]) + 1, "image_id": index + 1, "category_id": classes.index(name) + 1,
                "bbox": [box[0], box[1], box[2] - box[0], box[3] - box[1]], "iscrowd": 0,
                "area": (box[2] - box[0]) * (box[3] - box[1]),
            })  # fmt: skip
    (out / "coco.json").write_text(json.dumps(coco))
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--n", type=int, default=80)
    parser.add_argument("--classes", default="coffee,astronaut", help="object textures (foldwise's default classes)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    out = make_standin_set(args.out, args.n, args.classes.split(","), seed=args.seed)
    print(f"{args.n} stand-in images: {out / 'voc'} (Pascal VOC) and {out / 'coco.json'} (COCO)")


if __name__ == "__main__":
    main()
