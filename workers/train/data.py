"""Training and test samples: a rendered image on disk and its ground-truth boxes.

``load_coco_dataset`` reads the dataset folder written by ``foldwise render --out DIR``
(``DIR/annotations.json`` in COCO form, images under ``DIR/images/``) and checks every box
before any training starts, so a bad annotation fails here with the image named, not as a
NaN loss an hour later. ``load_dataset`` also reads what labelling tools export for real
photographs: a COCO JSON file anywhere, or a Pascal VOC folder.

Every image is read by ``foldwise.images`` as it is displayed (EXIF orientation applied:
labelling tools and browsers show phone photos turned, and their boxes refer to that), and a
photo longer than ``PHOTO_MAX_SIDE`` is shrunk on load; its boxes are scaled here, on loading,
so that a sample's boxes always fit the pixels ``read_image_rgb`` gives.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from foldwise.images import ImageError, image_size, read_image, shrunk_size

# Photos are shrunk on load so that their longer side is at most this (a 12-50 Mpixel phone
# photo is 4000-8700 px long): the detector resizes every image to its input size (at most
# 2048) anyway, and full-size photos would hold gigabytes in a training run.
PHOTO_MAX_SIDE = 2048
# A box may overhang the image by this many pixels (float rounding in the renderer).
_BORDER_TOLERANCE = 1e-3


class DatasetError(ValueError):
    """A dataset folder or annotation that cannot be used; the message names the file or image."""


@dataclass
class Sample:
    image_path: Path
    boxes: np.ndarray  # (n, 4) float32, xyxy in pixels
    labels: np.ndarray  # (n,) int64, 0-based class index
    condition: str | None = None
    difficulty: str | None = None

    def __post_init__(self) -> None:
        self.image_path = Path(self.image_path)
        self.boxes = np.asarray(self.boxes, dtype=np.float32).reshape(-1, 4)
        self.labels = np.asarray(self.labels, dtype=np.int64).reshape(-1)
        if len(self.boxes) != len(self.labels):
            raise DatasetError(f"{self.image_path}: {len(self.boxes)} boxes but {len(self.labels)} labels")


def validate_box(box_xyxy, width: float, height: float, where: str) -> None:
    """Raise DatasetError unless the box is finite, has positive area and lies in the image."""
    x0, y0, x1, y1 = (float(v) for v in box_xyxy)
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise DatasetError(f"{where}: box {[x0, y0, x1, y1]} is not finite")
    if x1 <= x0 or y1 <= y0:
        raise DatasetError(f"{where}: degenerate box {[x0, y0, x1, y1]} (zero or negative width or height)")
    tol = _BORDER_TOLERANCE
    if x0 < -tol or y0 < -tol or x1 > width + tol or y1 > height + tol:
        raise DatasetError(f"{where}: box {[x0, y0, x1, y1]} lies outside the {width:g}x{height:g} image")


def load_coco_dataset(directory: str | Path) -> tuple[list[Sample], list[str]]:
    """Samples (one per image, in the file's order) and the class names in category order.

    Category ids are 1-based; a category's 0-based label is its position in the list of
    categories sorted by id. ``iscrowd`` is ignored: every annotation is a target. ``directory``
    may also be a COCO JSON file; its image file names are then relative to its folder.
    """
    directory = Path(directory)
    if directory.suffix.lower() == ".json" and directory.is_file():
        directory, annotation_path = directory.parent, directory
    else:
        annotation_path = directory / "annotations.json"
    if not annotation_path.is_file():
        raise DatasetError(f"{directory}: no annotations.json (not a dataset folder written by `foldwise render`)")
    try:
        document = json.loads(annotation_path.read_text())
    except json.JSONDecodeError as error:
        raise DatasetError(f"{annotation_path}: not valid JSON: {error}") from None
    for key in ("images", "annotations", "categories"):
        if not isinstance(document.get(key), list):
            raise DatasetError(f"{annotation_path}: missing list {key!r}")

    categories = sorted(document["categories"], key=lambda c: c["id"])
    category_ids = [c["id"] for c in categories]
    if len(set(category_ids)) != len(category_ids):
        raise DatasetError(f"{annotation_path}: duplicate category ids {category_ids}")
    if not categories:
        raise DatasetError(f"{annotation_path}: no categories")
    label_of_category = {cid: index for index, cid in enumerate(category_ids)}
    classes = [str(c["name"]) for c in categories]

    images = document["images"]
    image_by_id: dict = {}
    for image in images:
        if image["id"] in image_by_id:
            raise DatasetError(f"{annotation_path}: duplicate image id {image['id']}")
        image_by_id[image["id"]] = image
    boxes_by_image: dict = {image_id: [] for image_id in image_by_id}
    labels_by_image: dict = {image_id: [] for image_id in image_by_id}

    paths = {image_id: _coco_image_path(directory, str(image["file_name"])) for image_id, image in image_by_id.items()}
    sizes = {image_id: _declared_size(paths[image_id], image.get("width"), image.get("height"), image["file_name"])
             for image_id, image in image_by_id.items()}  # fmt: skip
    for annotation in document["annotations"]:
        image = image_by_id.get(annotation["image_id"])
        if image is None:
            raise DatasetError(
                f"{annotation_path}: annotation {annotation.get('id')} refers to unknown image id {annotation['image_id']}"
            )
        where = f"{image['file_name']} (annotation {annotation.get('id')})"
        if annotation["category_id"] not in label_of_category:
            raise DatasetError(f"{where}: unknown category_id {annotation['category_id']}")
        x, y, w, h = (float(v) for v in annotation["bbox"])
        box = (x, y, x + w, y + h)
        validate_box(box, *sizes[image["id"]], where)
        boxes_by_image[image["id"]].append(box)
        labels_by_image[image["id"]].append(label_of_category[annotation["category_id"]])

    samples = []
    for image in images:
        path = paths[image["id"]]
        boxes = np.array(boxes_by_image[image["id"]], dtype=np.float32).reshape(-1, 4)
        samples.append(
            Sample(
                image_path=path,
                boxes=_shrunk_boxes(boxes, *sizes[image["id"]]),
                labels=np.array(labels_by_image[image["id"]], dtype=np.int64),
                condition=image.get("condition"),
                difficulty=image.get("difficulty"),
            )
        )
    return samples, classes


def load_dataset(path: str | Path) -> tuple[list[Sample], list[str]]:
    """Samples and class names of a dataset in any form foldwise reads: a folder holding
    ``annotations.json`` (``foldwise render --out``), a COCO JSON file (its image file names
    relative to its folder; a CVAT export's ``annotations/*.json`` finds them in ``images/``
    beside), or a Pascal VOC folder (``Annotations/*.xml`` beside ``JPEGImages/`` or ``images/``)."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    if (path.is_file() and path.suffix.lower() == ".json") or (path / "annotations.json").is_file():
        return load_coco_dataset(path)
    if (path / "Annotations").is_dir():
        return load_voc_dataset(path)
    raise DatasetError(
        f"{path}: not a dataset: no annotations.json in it (a folder `foldwise render --out` writes), "
        "nor a COCO JSON file, nor a Pascal VOC folder (Annotations/*.xml beside JPEGImages/)"
    )


def load_voc_dataset(folder: str | Path) -> tuple[list[Sample], list[str]]:
    """Samples of a Pascal VOC folder, and its class names in the order they first appear."""
    folder = Path(folder)
    classes: list[str] = []
    samples = []
    files = sorted((folder / "Annotations").glob("*.xml"))
    if not files:
        raise DatasetError(f"{folder}/Annotations holds no .xml annotation")
    for xml_path in files:
        try:
            root = ElementTree.parse(xml_path).getroot()
        except ElementTree.ParseError as error:
            raise DatasetError(f"{xml_path}: not valid XML: {error}") from None
        filename = root.findtext("filename")
        if not filename:
            raise DatasetError(f"{xml_path}: no <filename>")
        # Label Studio's VOC export puts the photos in images/, the VOC layout in JPEGImages/.
        image_path = next((folder / sub / filename for sub in ("JPEGImages", "images") if (folder / sub / filename).is_file()),
                          folder / "JPEGImages" / filename)  # fmt: skip
        if not image_path.is_file():
            raise DatasetError(f"{xml_path}: image file {image_path} does not exist")
        try:
            declared = [float(root.findtext(f"size/{key}") or 0) for key in ("width", "height")]
        except ValueError:
            raise DatasetError(f"{xml_path}: <size> needs numeric width and height") from None
        width, height = _declared_size(image_path, *declared, where=str(xml_path))
        boxes, labels = [], []
        for number, obj in enumerate(root.iter("object")):
            name = (obj.findtext("name") or "").strip()
            where = f"{xml_path} (object {number})"
            if not name:
                raise DatasetError(f"{where}: no <name>")
            try:
                # VOC pixels are 1-based and inclusive: x0 - 1 .. x1 in 0-based pixel edges.
                box = [float(obj.findtext(f"bndbox/{key}")) for key in ("xmin", "ymin", "xmax", "ymax")]
            except (TypeError, ValueError):
                raise DatasetError(f"{where}: <bndbox> needs numeric xmin, ymin, xmax, ymax") from None
            box = [box[0] - 1, box[1] - 1, box[2], box[3]]
            validate_box(box, width, height, where)
            if name not in classes:
                classes.append(name)
            boxes.append(box)
            labels.append(classes.index(name))
        boxes = _shrunk_boxes(np.asarray(boxes, np.float32).reshape(-1, 4), width, height)
        samples.append(Sample(image_path, boxes, np.asarray(labels, np.int64)))
    return samples, classes


def _coco_image_path(directory: Path, file_name: str) -> Path:
    """Where a COCO image's file is: its ``file_name`` relative to the JSON file's folder, or,
    for a CVAT export (``annotations/instances_<subset>.json`` beside ``images/<subset>/``),
    under the ``images/`` folder beside that folder. The first place when it is in none."""
    candidates = [directory / file_name, directory.parent / file_name, directory.parent / "images" / file_name]
    subsets = directory.parent / "images"
    if subsets.is_dir():
        candidates += sorted(subset / file_name for subset in subsets.iterdir() if subset.is_dir())
    return next((path for path in candidates if path.is_file()), candidates[0])


def _declared_size(path: Path, width, height, where: str) -> tuple[float, float]:
    """The image's size as displayed, checked against the size its annotation declares (when it
    declares one: 0 or absent is none). A photo whose EXIF orientation turns it and whose
    annotation gives the stored size was labelled unturned: an error that says so, since its
    boxes would not fit the photo as everyone else sees it."""
    if not path.is_file():
        raise DatasetError(f"{where}: image file {path} does not exist")
    try:
        actual = image_size(path)
    except ImageError as error:
        raise DatasetError(f"{where}: {error}") from None
    try:
        declared = (float(width or 0), float(height or 0))
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: width {width!r} and height {height!r} are not numbers") from None
    if not all(declared) or declared == actual:
        return float(actual[0]), float(actual[1])
    if declared == (actual[1], actual[0]):
        raise DatasetError(
            f"{where}: the annotation gives {declared[0]:g}x{declared[1]:g}, but the photo as displayed (its EXIF "
            f"orientation applied) is {actual[0]}x{actual[1]}: it was labelled without its EXIF turn. Re-export it "
            "from a tool that shows photos turned (CVAT, Label Studio), or save the photo turned, without the tag"
        )
    raise DatasetError(
        f"{where}: the annotation gives {declared[0]:g}x{declared[1]:g}, but the image is {actual[0]}x{actual[1]}: "
        "was the image resized or replaced after labelling?"
    )


def _shrunk_boxes(boxes: np.ndarray, width: float, height: float) -> np.ndarray:
    """Boxes of a (width, height) image in the pixels ``read_image_rgb`` gives it (a photo
    longer than PHOTO_MAX_SIDE is shrunk, each axis by its exact ratio)."""
    new_w, new_h = shrunk_size(int(width), int(height), PHOTO_MAX_SIDE)
    if (new_w, new_h) == (int(width), int(height)):
        return boxes
    return (boxes * np.array([new_w / width, new_h / height] * 2, np.float32)).astype(np.float32)


def read_image_rgb(path: str | Path) -> np.ndarray:
    """An image file as displayed (EXIF orientation applied), (H, W, 3) uint8 RGB, shrunk when
    longer than PHOTO_MAX_SIDE (the loaders scale its boxes to match); a clear error when it
    cannot be read."""
    try:
        return read_image(path, max_side=PHOTO_MAX_SIDE)[0]
    except ImageError as error:
        raise DatasetError(f"cannot read image {error}") from None


def as_rgb_uint8(image: np.ndarray, where: str = "image") -> np.ndarray:
    """Check (or gently coerce grey to) an (H, W, 3) uint8 RGB array."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise DatasetError(f"{where}: expected uint8 pixels, got {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise DatasetError(f"{where}: expected an (H, W, 3) RGB image, got shape {image.shape}")
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise DatasetError(f"{where}: empty image of shape {image.shape}")
    return np.ascontiguousarray(image)
