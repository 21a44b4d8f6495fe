"""Printed documents as a phone photographs them, drawn by code: foldwise beside the keypoint
recipe (JSON out).

The sets foldwise renders itself hold small sheets in small frames. A user's photograph of their
own printed sheet is mostly another picture: a large frame, the sheet a half or more of its
height, held at an angle (strong perspective), often curled, under uneven and coloured light,
with other sheets of the same kind beside it. This bench draws such pictures without Blender or
anything foldwise trains on:

* the documents and their lookalikes come from ``bench/printed_documents.py`` (five companies'
  sheets as the targets; more sheets of their templates, other companies and text pages as
  lookalikes);
* each picture (``--size``, default 1024x768) lies one to three sheets side by side on one of
  scikit-image's photographs (a training path reads none of them): the first a target in 9 of
  10 pictures, the others targets or lookalikes. Each sheet is curled around a vertical cylinder
  (up to 1.6 rad across its width, shaded by its normal), turned by up to ±29°, seen with one
  edge up to 45% nearer the camera, then lit by a gradient and a colour cast, blurred, noised
  and saved as JPEG at quality 60-95;
* a target's box is the extent of its visible pixels.

Scored on one set (``--seed``, ``--n``) as a user would see it: ``--model`` (a detector trained
on the targets, e.g. ``foldwise run`` with ``assets.objects`` set to ``DOCS/targets``) as
built; the same detector given 7 of the lookalikes (``GIVEN``, as ``foldwise lookalikes``
gives a user's other forms); and the keypoint recipe (``bench/keypoint_baseline.py``). Each row
reports the paper's mAP, precision and recall at the 0.8 cut, the boxes drawn and seconds per
image.

    python bench/printed_documents.py --out var/bench/documents
    foldwise run docs.yaml --members 2   # quick.yaml with assets.objects: var/bench/documents/targets
    python bench/document_photos.py --documents var/bench/documents \\
        --model var/studies/S/ensemble.pt --out bench/results/document_photos.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402
from bench.standin_real import BACKGROUNDS, _photo  # noqa: E402

# Lookalikes a user gives the detector by default: one more sheet of each target's template, one
# of another company, a text page (7 of the 17 printed_documents draws).
GIVEN = ("same1-1", "same2-1", "same3-1", "same4-1", "same5-1", "other1", "text1")
TARGET_SHARE = 0.9  # pictures whose first sheet is a target
OTHER_TARGET_SHARE = 0.4  # the other sheets: a target this often, else a lookalike
MAX_CURL = 1.6  # rad of bend across a sheet's width
MAX_TURN = 0.5  # rad
MAX_NEAR = 0.45  # how much nearer the camera one edge of a sheet is, as a share of its span
MIN_VISIBLE_PX = 400  # a target showing fewer pixels than this is no target to find


def read_sheets(folder: Path) -> dict[str, np.ndarray]:
    """Each PNG sheet in ``folder`` by its file's stem, RGB."""
    from workers.train.data import read_image_rgb

    return {path.stem: read_image_rgb(path) for path in sorted(folder.glob("*.png"))}


def curled(sheet: np.ndarray, bend: float) -> np.ndarray:
    """``sheet`` curled around a vertical cylinder by ``bend`` rad across its width, as seen from
    in front: narrower, its sides foreshortened and darker as they turn away (0: as it is)."""
    import cv2

    height, width = sheet.shape[:2]
    if bend <= 0:
        return sheet
    along = np.linspace(-0.5, 0.5, width)  # arc length across the sheet, in widths
    radius = 1.0 / bend
    seen = radius * np.sin(along / radius)
    seen = (seen - seen.min()) * (width - 1)  # in pixels: the chord is shorter than the arc
    out_width = int(round(seen.max())) + 1
    source_x = np.interp(np.arange(out_width), seen, np.arange(width)).astype(np.float32)
    map_x = np.repeat(source_x[None], height, 0)
    map_y = np.repeat(np.arange(height, dtype=np.float32)[:, None], out_width, 1)
    out = cv2.remap(sheet, map_x, map_y, cv2.INTER_LINEAR)
    shade = np.cos(np.interp(np.arange(out_width), seen, along) / radius)[None, :, None]
    return np.clip(out * (0.55 + 0.45 * shade), 0, 255).astype(np.uint8)


def make_photo_set(documents: Path, out: Path, n: int, seed: int, size: tuple[int, int] = (1024, 768)) -> Path:
    """Write ``out/images/*.jpg`` and ``out/annotations.json`` (COCO, the targets' names as
    categories): ``n`` pictures of the documents in ``documents`` (``printed_documents``'s
    ``targets/`` and ``lookalikes/``) as described in the module's docstring."""
    import cv2

    rng = np.random.default_rng(seed)
    targets = read_sheets(documents / "targets")
    lookalikes = list(read_sheets(documents / "lookalikes").values())
    if not targets or not lookalikes:
        raise SystemExit(f"{documents}: no targets/*.png or lookalikes/*.png (bench/printed_documents.py writes them)")
    classes = sorted(targets)
    width, height = size
    (out / "images").mkdir(parents=True, exist_ok=True)
    coco = {"images": [], "annotations": [], "categories": [{"id": i + 1, "name": c} for i, c in enumerate(classes)]}
    for index in range(n):
        background = _photo(BACKGROUNDS[rng.integers(len(BACKGROUNDS))])
        canvas = cv2.resize(background, (width, height), interpolation=cv2.INTER_AREA)
        slots = int(rng.integers(1, 4))
        objects = []
        for slot in range(slots):
            is_target = rng.random() < (TARGET_SHARE if slot == 0 else OTHER_TARGET_SHARE)
            name = classes[int(rng.integers(len(classes)))] if is_target else None
            sheet = targets[name] if is_target else lookalikes[int(rng.integers(len(lookalikes)))]
            bend = rng.uniform(0.0, MAX_CURL)
            sheet = curled(sheet, bend if bend >= 0.2 else 0.0)  # a slighter bend is flat to the eye
            sheet_height, sheet_width = sheet.shape[:2]
            left, right = width * slot / slots, width * (slot + 1) / slots
            side = rng.uniform(0.45, 0.85) * height  # the sheet's height in the picture
            half = np.array([side * sheet_width / sheet_height / 2, side / 2])
            half *= min(1.0, (right - left) * 0.95 / (2 * half[0] * 1.2))
            angle = rng.uniform(-MAX_TURN, MAX_TURN)
            turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
            quad = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half @ turn.T
            near = rng.uniform(0.0, MAX_NEAR)  # one edge nearer the camera: the far one shrinks
            edge = int(rng.integers(4))
            quad[edge] += (quad[(edge + 2) % 4] - quad[edge]) * near * 0.5
            quad[(edge + 1) % 4] += (quad[(edge + 3) % 4] - quad[(edge + 1) % 4]) * near * 0.5
            quad += rng.normal(0, 0.04 * side, quad.shape) + [(left + right) / 2, rng.uniform(0.45, 0.55) * height]
            corners = np.array(
                [[0, 0], [sheet_width - 1, 0], [sheet_width - 1, sheet_height - 1], [0, sheet_height - 1]], np.float32
            )
            matrix = cv2.getPerspectiveTransform(corners, quad.astype(np.float32))
            warped = cv2.warpPerspective(sheet, matrix, (width, height), flags=cv2.INTER_AREA)
            mask = cv2.warpPerspective(np.full(sheet.shape[:2], 255, np.uint8), matrix, (width, height)) > 127
            canvas[mask] = warped[mask]
            if name is not None:
                ys, xs = np.nonzero(mask)
                if len(xs) >= MIN_VISIBLE_PX:
                    objects.append((name, [float(xs.min()), float(ys.min()), float(xs.max()) + 1, float(ys.max()) + 1]))
        gradient = np.linspace(rng.uniform(0.5, 1.1), rng.uniform(0.7, 1.3), width)[None, :, None]
        cast = rng.uniform(0.8, 1.15, 3)[None, None, :]
        canvas = np.clip(canvas * gradient * cast, 0, 255).astype(np.uint8)
        canvas = cv2.GaussianBlur(canvas, (0, 0), rng.uniform(0.3, 1.2))
        canvas = np.clip(canvas + rng.normal(0, 4, canvas.shape), 0, 255).astype(np.uint8)
        filename = f"photo_{index:04d}.jpg"
        quality = int(rng.integers(60, 96))
        cv2.imwrite(
            str(out / "images" / filename), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality]
        )
        coco["images"].append({"id": index + 1, "file_name": f"images/{filename}", "width": width, "height": height})
        for name, (x0, y0, x1, y1) in objects:
            coco["annotations"].append(
                {
                    "id": len(coco["annotations"]) + 1,
                    "image_id": index + 1,
                    "category_id": classes.index(name) + 1,
                    "bbox": [x0, y0, x1 - x0, y1 - y0],
                    "area": (x1 - x0) * (y1 - y0),
                    "iscrowd": 0,
                }
            )
    (out / "annotations.json").write_text(json.dumps(coco))
    return out


def score_rows(model: Path, documents: Path, data: Path, given: tuple[str, ...] = GIVEN, parts=None) -> dict:
    """The three rows on the COCO folder ``data``: the detector as built, given ``given`` of the
    lookalikes, and the keypoint recipe (``parts``: named lists of image indices, each also scored
    alone)."""
    from bench.wild_scoring import _scores, score_keypoint_baseline
    from workers.train.checkpoint import load_detector
    from workers.train.data import load_coco_dataset
    from workers.train.evaluation import detector_predictions
    from workers.train.texture_check import grayscale

    samples, classes = load_coco_dataset(data)
    detector = load_detector(model, device="cpu")
    sheets = read_sheets(documents / "lookalikes")
    given_sheets = {name: grayscale(sheets[name]) for name in given}
    with_lookalikes = dataclasses.replace(detector, lookalikes={**(detector.lookalikes or {}), **given_sheets})
    rows = {}
    for name, which in (("as built", detector), (f"given {len(given)} lookalikes", with_lookalikes)):
        started = time.perf_counter()
        predictions, truth, groups, model_classes = detector_predictions(which, samples, classes)
        seconds = time.perf_counter() - started
        rows[name] = _scores(predictions, truth, model_classes, groups, 0.8, 0.5, seconds, parts)
    rows["keypoint recipe"] = score_keypoint_baseline(read_sheets(documents / "targets"), data, 0.8, 0.5, parts)
    return rows


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--documents", type=Path, default=ROOT / "var/bench/documents")
    parser.add_argument("--model", type=Path, required=True, help="a detector trained on DOCUMENTS/targets")
    parser.add_argument("--n", type=int, default=40)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--size", default="1024x768", help="WIDTHxHEIGHT of the pictures")
    parser.add_argument(
        "--data", type=Path, default=None, help="where the set is written (default var/bench/document-photos-SEED)"
    )
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    data = args.data or ROOT / f"var/bench/document-photos-{args.seed}"
    if not (data / "annotations.json").is_file():
        make_photo_set(args.documents, data, args.n, args.seed, (width, height))
    rows = score_rows(args.model, args.documents, data)
    described = {"dir": str(data), "n": args.n, "seed": args.seed, "size": [width, height], "given": list(GIVEN)}
    return write_rows(args.model, described, rows, f"{args.n} pictures at {width}x{height}", args.out)


def write_rows(model: Path, described: dict, rows: dict, what: str, out: Path | None) -> dict:
    """The JSON report of ``score_rows``'s rows on a set (``described``), its headline opening with ``what``."""
    headline = "; ".join(
        f"{name} {row['map']:.3f} (P {row['at_threshold']['precision'] or 0:.2f}, R {row['at_threshold']['recall']:.2f}, "
        f"{row['seconds_per_image']:.2f} s/image)"
        for name, row in rows.items()
    )
    report = {
        "model": str(model),
        "set": described,
        "rows": rows,
        "headline": f"{what}: {headline}",
        "machine": machine(),
    }
    return write_report(report, out)


if __name__ == "__main__":
    main()
