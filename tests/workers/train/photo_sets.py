"""Labelled "phone photo" sets for tests: portrait, landscape and EXIF-rotated JPEGs, as a
labelling tool exports them (COCO JSON or Pascal VOC), boxes given on the photo as displayed.

Pictures are made of flat 8 x 8 cells, stored as 4:4:4 JPEG: every block is flat, so a photo
and its twin stored turned with an EXIF Orientation tag decode to exactly the same displayed
pixels, and any difference in what a command finds for them comes from how it reads them.
"""

from __future__ import annotations

import io
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

CLASSES = ["red", "green", "blue"]
COLOURS = [(220, 40, 40), (40, 220, 40), (40, 40, 220)]
CELL = 8
# EXIF Orientation -> turns (numpy rot90 of the displayed image) that give the stored pixels.
STORED_TURNS = {3: 2, 6: 1, 8: -1}


@dataclass
class Photo:
    name: str
    pixels: np.ndarray  # as displayed, (H, W, 3) uint8
    boxes: np.ndarray  # (n, 4) xyxy on the displayed photo
    labels: np.ndarray  # (n,) 0-based
    orientation: int = 1  # EXIF tag of the stored file


def picture(height_cells: int, width_cells: int, label: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Noise cells with one striped coloured sheet on them; (pixels, its box)."""
    rng = np.random.default_rng(seed)
    cells = rng.integers(60, 130, (height_cells, width_cells, 3)).astype(np.uint8)
    h = int(rng.integers(height_cells // 2, height_cells - 1))
    w = int(rng.integers(width_cells // 2, width_cells - 1))
    y0, x0 = int(rng.integers(0, height_cells - h + 1)), int(rng.integers(0, width_cells - w + 1))
    cells[y0 : y0 + h, x0 : x0 + w] = COLOURS[label]
    cells[y0 : y0 + h : 2, x0 : x0 + w] = 0
    pixels = np.kron(cells, np.ones((CELL, CELL, 1), np.uint8))
    box = np.array([[x0, y0, x0 + w, y0 + h]], np.float32) * CELL
    return pixels, box


def photos(n: int = 6, seed: int = 0) -> list[Photo]:
    """n photos: landscape, portrait and square by turns, each of one class; every third stored
    turned with an EXIF tag (6, 8, 3 by turns)."""
    shapes = [(6, 10), (10, 6), (8, 8)]
    tags = [6, 8, 3]
    out = []
    for index in range(n):
        label = index % len(CLASSES)
        pixels, box = picture(*shapes[index % 3], label, seed * 1000 + index)
        orientation = tags[(index // 3) % 3] if index % 3 == 2 else 1
        out.append(Photo(f"photo{index:02d}", pixels, box, np.array([label]), orientation))
    return out


def twin(photo: Photo, orientation: int = 6) -> Photo:
    """The same photo stored turned with the EXIF tag that shows it as before."""
    return Photo(photo.name + f"-exif{orientation}", photo.pixels, photo.boxes, photo.labels, orientation)


def jpeg_bytes(photo: Photo) -> bytes:
    stored = photo.pixels
    options = {}
    if photo.orientation != 1:
        stored = np.ascontiguousarray(np.rot90(photo.pixels, STORED_TURNS[photo.orientation]))
        exif = Image.Exif()
        exif[0x0112] = photo.orientation
        options["exif"] = exif.tobytes()
    buffer = io.BytesIO()
    Image.fromarray(stored).save(buffer, "JPEG", quality=95, subsampling=0, **options)
    return buffer.getvalue()


def write_coco(folder: Path, items: list[Photo], classes: list[str] = CLASSES) -> Path:
    """A labelling tool's COCO export: ``folder/annotations.json`` (image sizes as displayed,
    category ids from 1), photos under ``folder/images/``; returns the JSON file."""
    (folder / "images").mkdir(parents=True, exist_ok=True)
    document: dict = {
        "images": [],
        "annotations": [],
        "categories": [{"id": k + 1, "name": n} for k, n in enumerate(classes)],
    }
    for image_id, photo in enumerate(items, start=1):
        (folder / "images" / f"{photo.name}.jpg").write_bytes(jpeg_bytes(photo))
        height, width = photo.pixels.shape[:2]
        document["images"].append(
            {"id": image_id, "file_name": f"images/{photo.name}.jpg", "width": width, "height": height}
        )
        for box, label in zip(photo.boxes, photo.labels):
            x0, y0, x1, y1 = (float(v) for v in box)
            document["annotations"].append(
                {"id": len(document["annotations"]) + 1, "image_id": image_id, "category_id": int(label) + 1,
                 "bbox": [x0, y0, x1 - x0, y1 - y0], "area": (x1 - x0) * (y1 - y0), "iscrowd": 0}
            )  # fmt: skip
    path = folder / "annotations.json"
    path.write_text(json.dumps(document))
    return path


def write_voc(folder: Path, items: list[Photo], classes: list[str] = CLASSES) -> Path:
    """A Pascal VOC export (1-based inclusive pixel boxes); returns the folder."""
    (folder / "Annotations").mkdir(parents=True, exist_ok=True)
    (folder / "JPEGImages").mkdir(parents=True, exist_ok=True)
    for photo in items:
        (folder / "JPEGImages" / f"{photo.name}.jpg").write_bytes(jpeg_bytes(photo))
        height, width = photo.pixels.shape[:2]
        objects = "".join(
            f"<object><name>{classes[int(label)]}</name><bndbox><xmin>{int(box[0]) + 1}</xmin><ymin>{int(box[1]) + 1}</ymin>"
            f"<xmax>{int(box[2])}</xmax><ymax>{int(box[3])}</ymax></bndbox></object>"
            for box, label in zip(photo.boxes, photo.labels)
        )
        (folder / "Annotations" / f"{photo.name}.xml").write_text(
            f"<annotation><filename>{photo.name}.jpg</filename><size><width>{width}</width><height>{height}</height>"
            f"<depth>3</depth></size>{objects}</annotation>"
        )
    return folder


def copy_with_twins(source: Path, target: Path, orientation: int = 6) -> None:
    """``target``: the COCO set at ``source`` with every photo replaced by its EXIF-turned twin."""
    shutil.copytree(source, target)
    document = json.loads((target / "annotations.json").read_text())
    for image in document["images"]:
        path = target / image["file_name"]
        with Image.open(path) as stored:
            displayed = np.asarray(ImageOps.exif_transpose(stored).convert("RGB"))
        path.write_bytes(jpeg_bytes(Photo("", displayed, np.zeros((0, 4)), np.zeros(0), orientation)))


def decoded(photo: Photo) -> np.ndarray:
    """The pixels a reader should give for the photo: its upright JPEG, decoded."""
    upright = Photo(photo.name, photo.pixels, photo.boxes, photo.labels)
    return np.asarray(Image.open(io.BytesIO(jpeg_bytes(upright))).convert("RGB"))
