"""What the texture check's shown-share rule costs on sheets that are there (JSON out).

A confirmed sheet whose maps explain less than ``texture_check.MIN_SHOWN`` of the texture cells
the image shows in detail (``SHOWN_KEYPOINTS`` of its keypoints taken back into a cell) is
taken for another sheet of its template and drops under the cut. On real photographs that is
what tells a target from another form of its template (``bench/real_photos.py``); on small,
blurred or grainy rendered sheets, a cell's few keypoints of grain and ground must not count as
print the maps leave unexplained.

Each true box of a COCO set is given to the check as a network box (score 0.9, its own class);
for every (SHOWN_KEYPOINTS, MIN_SHOWN) asked, the report counts the true sheets a map confirms
and how many of them the rule would withdraw.

    python bench/wild.py --sets-only                 # renders var/bench/wild-ood
    python bench/shown_share.py --data var/bench/wild-ood --out bench/results/shown_share.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402


def shares(data: Path, config_path: Path, keypoints: list[int]) -> list[dict]:
    """Each true box's fit: its inliers, coverage and shown share at each of ``keypoints``."""
    from foldwise.config import load_config
    from workers.render.assets import load_assets
    from workers.train import texture_check
    from workers.train.data import load_coco_dataset, read_image_rgb

    samples, classes = load_coco_dataset(data)
    textures = load_assets(load_config(config_path).assets).textures(classes)
    check = texture_check.TextureCheck(
        {name: texture_check.grayscale(np.asarray(textures[name])) for name in classes}, classes
    )
    rows = []
    saved = texture_check.SHOWN_KEYPOINTS
    try:
        for sample in samples:
            image = read_image_rgb(sample.image_path)
            height, width = image.shape[:2]
            every, points, labels, texture_points = check.matches(image)
            for box, label in zip(np.asarray(sample.boxes, np.float32).reshape(-1, 4), sample.labels):
                inside = texture_check._inside(points, box)
                in_box = every[texture_check._inside(every, box)]
                row = {"image": sample.image_path.name, "shown": {}}
                for count in keypoints:
                    texture_check.SHOWN_KEYPOINTS = count
                    outline, inliers, coverage, shown = check._fit(
                        points[inside], labels[inside], texture_points[inside], int(label), box, width, height, in_box
                    )
                    row.update(confirmed=outline is not None, inliers=inliers, coverage=coverage)
                    row["shown"][count] = shown
                rows.append(row)
    finally:
        texture_check.SHOWN_KEYPOINTS = saved
    return rows


def main(argv=None) -> dict:
    from workers.train import texture_check

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=ROOT / "var/bench/wild-ood", help="a COCO folder of sheets")
    parser.add_argument("--config", type=Path, default=ROOT / "configs/quick.yaml", help="whose objects the set shows")
    parser.add_argument("--keypoints", type=int, nargs="+", default=[2, 5, 10, 20])
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.45, 0.5, 0.55, 0.6])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    if not (args.data / "annotations.json").is_file():
        raise SystemExit(f"{args.data}: no annotations.json (render it with: python bench/wild.py --sets-only)")
    rows = shares(args.data, args.config, args.keypoints)
    confirmed = [row for row in rows if row["confirmed"]]
    withdrawn = {
        f"keypoints {count}, below {threshold}": sum(row["shown"][count] < threshold for row in confirmed)
        for count in args.keypoints
        for threshold in args.thresholds
    }
    chosen = f"keypoints {texture_check.SHOWN_KEYPOINTS}, below {texture_check.MIN_SHOWN}"
    report = {
        "set": str(args.data),
        "true_sheets": len(rows),
        "confirmed": len(confirmed),
        "withdrawn": withdrawn,
        "headline": (
            f"{len(confirmed)} of {len(rows)} true sheets confirmed; the rule as built ({chosen}) "
            f"withdraws {withdrawn.get(chosen, 'n/a')} of them"
        ),
        "machine": machine(),
    }
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
