"""The README's picture (docs/images/overview.png): what foldwise renders, what the model it
hands over finds in images foldwise did not render, and its error against time.

Three panels from a finished ``make run``:

- the renders: ``foldwise render --preview`` (docs/images/preview.png), the paper's conditions
  from easy to hard;
- detections: the first images of an out-of-domain COCO folder (``bench/wild.py --sets-only``
  renders them with code training never runs) through the ensemble, boxes at the default
  threshold drawn as ``foldwise detect`` draws them (solid: the texture confirmed the box;
  dashed: the network's word alone), the set's true boxes in thin white;
- error against time: the experiment's ``report.png`` (``foldwise report``).

    python docs/overview_figure.py --model var/studies/S/ensemble.pt \\
        --images var/bench/wild-ood-apart --report var/experiments/1/report/report.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PREVIEW = ROOT / "docs/images/preview.png"
OUT = ROOT / "docs/images/overview.png"
THRESHOLD = 0.8  # the paper's cut, foldwise detect's default


def detection_tiles(model: Path, images: Path, count: int, pick: list[int] | None) -> list:
    """``count`` images of a COCO folder with the model's detections drawn (RGB arrays)."""
    import cv2

    from workers.train.checkpoint import detect_object, load_detector
    from workers.train.cli import draw_detections
    from workers.train.data import load_coco_dataset, read_image_rgb

    detector = load_detector(model, device="cpu")
    samples, _classes = load_coco_dataset(images)
    chosen = [samples[index] for index in pick] if pick else samples[:count]
    tiles = []
    for sample in chosen:
        image = read_image_rgb(sample.image_path)
        (found,) = detect_object(detector, [image])
        drawn = draw_detections(image, found, detector.classes, THRESHOLD)
        for box in sample.boxes:
            x0, y0, x1, y1 = (int(round(float(v))) for v in box)
            cv2.rectangle(drawn, (x0, y0), (x1, y1), (255, 255, 255), 1)
        tiles.append(drawn)
    return tiles


def mosaic(tiles: list, columns: int = 2, gap: int = 4):
    """The tiles (RGB uint8, cut to the first one's size) in rows of ``columns``, on white."""
    import numpy as np

    height, width = tiles[0].shape[:2]
    rows = -(-len(tiles) // columns)
    canvas = np.full((rows * (height + gap) - gap, columns * (width + gap) - gap, 3), 255, np.uint8)
    for index, tile in enumerate(tiles):
        top, left = (index // columns) * (height + gap), (index % columns) * (width + gap)
        canvas[top : top + height, left : left + width] = tile[:height, :width, :3]
    return canvas


def compose(preview, tiles: list, report, out: Path) -> None:
    """The contact sheet down the left; the detections (two columns) above the report on the right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    detections = mosaic(tiles)
    # Both right-hand images at one width: their heights in that width set the rows' ratio.
    right_heights = (detections.shape[0] / detections.shape[1], report.shape[0] / report.shape[1])
    left_width = preview.shape[1] / preview.shape[0] * sum(right_heights)
    figure = plt.figure(figsize=(14, 14 * sum(right_heights) / (left_width + 1) + 0.6), dpi=100)
    outer = figure.add_gridspec(1, 2, width_ratios=(left_width, 1.0), wspace=0.02)
    right = outer[1].subgridspec(2, 1, height_ratios=right_heights, hspace=0.08)
    panels = (
        (outer[0], preview, "renders: a row per imaging condition, easy → hard"),
        (right[0], detections, f"make run's model on scenes it never rendered: boxes ≥ {THRESHOLD}, truth in white"),
        (right[1], report, "its error 1 − mAP against wall time"),
    )
    for place, picture, title in panels:
        axis = figure.add_subplot(place)
        axis.imshow(picture)
        axis.set_title(title, fontsize=10)
        axis.set_axis_off()
    figure.savefig(out, bbox_inches="tight", pad_inches=0.05)
    plt.close(figure)


def main(argv=None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="make run's ensemble")
    parser.add_argument("--images", type=Path, required=True, help="an out-of-domain COCO folder")
    parser.add_argument("--report", type=Path, required=True, help="an experiment's report.png")
    parser.add_argument("--count", type=int, default=4, help="detection images shown")
    parser.add_argument("--pick", type=int, nargs="*", help="indices of the images shown (default: the first)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)

    import matplotlib.image

    tiles = detection_tiles(args.model, args.images, args.count, args.pick)
    compose(matplotlib.image.imread(PREVIEW), tiles, matplotlib.image.imread(args.report), args.out)
    print(args.out)
    return args.out


if __name__ == "__main__":
    main()
