"""Real photographs of bent printed invoices: foldwise beside the keypoint recipe (JSON out).

The set is ``bench/data/inv3d_real`` (its README says where the photographs come from, their
licence and how the boxes were drawn): 150 phone photographs of printed invoices, curled, folded
once or many times, crumpled lightly and hard, or lying flat at an angle, each under bright,
coloured and shadowed light. 90 show one of five target invoices; 60 show one of ten others of
the same kind (six of them printed from a target's own template), which must draw no box.
``lookalikes/`` holds the flat originals of five of those ten, as a user would give their other
forms (``foldwise lookalikes``); the other five are photographed only.

Four choices of foldwise were made on these photographs, on one half of them (``CHOSEN_ON``:
the even-numbered photographs in the order the set is read): how much of what the image shows of
a confirmed sheet its maps must explain (``texture_check.MIN_SHOWN``), with how far an inlier may
lie off the map its neighbours agree on (``texture_check.LOCAL_TOLERANCE``); how many keypoints
a box that fits no map may hold before it counts as unmatched
(``texture_check.DETAILED_KEYPOINTS``); and confirmed boxes ranked by the share of the texture
they cover alone (``texture_check.confirmed_score``). Every row is also scored on each half
alone (``parts``), and the other half (``HELD_OUT``) is the one to judge it by. Rows,
as ``bench/document_photos.py`` scores its drawn pictures: the detector as built, the same
detector given the five lookalikes, and the keypoint recipe; each with the paper's mAP,
precision and recall at the 0.8 cut, the boxes drawn and seconds per image, also by light
(``by_kind``).

    foldwise run CONFIG --members 2   # quick.yaml with assets.objects: bench/data/inv3d_real/targets
    python bench/real_photos.py --model var/studies/S/ensemble.pt --out bench/results/real_photos.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.document_photos import read_sheets, score_rows, write_rows  # noqa: E402

DATA = ROOT / "bench/data/inv3d_real"
CHOSEN_ON = "even photographs (a setting chosen on them)"
HELD_OUT = "odd photographs (held out)"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="a detector trained on DATA/targets")
    parser.add_argument("--data", type=Path, default=DATA, help="targets/, lookalikes/ and a COCO annotations.json")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    for part in ("targets", "lookalikes", "annotations.json"):
        if not (args.data / part).exists():
            raise SystemExit(f"{args.data}: no {part} (a folder laid out as bench/data/inv3d_real)")
    given = tuple(sorted(read_sheets(args.data / "lookalikes")))
    from workers.train.data import load_coco_dataset

    images = len(load_coco_dataset(args.data)[0])
    parts = {CHOSEN_ON: list(range(0, images, 2)), HELD_OUT: list(range(1, images, 2))}
    rows = score_rows(args.model, args.data, args.data, given=given, parts=parts)
    described = {"dir": str(args.data), "given": list(given), "parts": list(parts)}
    return write_rows(args.model, described, rows, f"{rows['as built']['images']} real photographs", args.out)


if __name__ == "__main__":
    main()
