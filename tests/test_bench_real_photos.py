"""bench/real_photos.py and its set, bench/data/inv3d_real: the photographs are what their
annotations say, and a folder laid out otherwise is refused by name."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import real_photos  # noqa: E402

DATA = ROOT / "bench/data/inv3d_real"


def test_every_target_photograph_holds_one_box_of_its_own_class_and_no_other_photograph_any():
    import cv2

    coco = json.loads((DATA / "annotations.json").read_text())
    targets = sorted(path.stem for path in (DATA / "targets").glob("*.png"))
    lookalikes = sorted(path.stem for path in (DATA / "lookalikes").glob("*.png"))
    assert sorted(c["name"] for c in coco["categories"]) == targets
    assert len(targets) == 5 and len(lookalikes) == 5 and not set(targets) & set(lookalikes)
    class_of = {c["id"]: c["name"] for c in coco["categories"]}
    boxes = {}
    for annotation in coco["annotations"]:
        boxes.setdefault(annotation["image_id"], []).append(annotation)
    for image in coco["images"]:
        path = DATA / image["file_name"]
        height, width = cv2.imread(str(path)).shape[:2]
        assert (width, height) == (image["width"], image["height"]) and max(width, height) == 1024
        kind, document = path.stem.split("-")[:2]
        if kind == "target":
            (annotation,) = boxes[image["id"]]
            assert class_of[annotation["category_id"]] == f"invoice-{document}"
            x, y, w, h = annotation["bbox"]
            # A sheet fills most of its frame here: its box is no sliver.
            assert 0 <= x and 0 <= y and x + w <= width + 0.5 and y + h <= height + 0.5
            assert w * h >= 0.3 * width * height
        else:
            assert kind == "other" and image["id"] not in boxes and f"invoice-{document}" not in targets
    kinds = [Path(image["file_name"]).stem.split("-")[0] for image in coco["images"]]
    assert kinds.count("target") == 90 and kinds.count("other") == 60


@pytest.mark.parametrize("missing", ["targets", "lookalikes", "annotations.json"])
def test_a_folder_without_its_parts_is_refused_by_name(tmp_path, missing):
    for part in ("targets", "lookalikes"):
        (tmp_path / part).mkdir()
    (tmp_path / "annotations.json").write_text("{}")
    target = tmp_path / missing
    target.rmdir() if target.is_dir() else target.unlink()
    with pytest.raises(SystemExit, match=f"no {missing}"):
        real_photos.main(["--model", str(tmp_path / "model.pt"), "--data", str(tmp_path)])


def test_the_report_scores_the_set_with_every_lookalike_given_and_writes_its_rows(tmp_path, monkeypatch, capsys):
    asked, asked_parts = {}, {}
    row = {"images": 150, "map": 0.5, "at_threshold": {"precision": 0.25, "recall": 1.0}, "seconds_per_image": 2.0}

    def scored(model, documents, data, given, parts):
        asked.update(model=model, documents=documents, data=data, given=given)
        asked_parts.update(parts)
        return {"as built": row, "keypoint recipe": row}

    monkeypatch.setattr(real_photos, "score_rows", scored)
    out = tmp_path / "real.json"
    report = real_photos.main(["--model", "m.pt", "--out", str(out)])
    capsys.readouterr()
    lookalikes = tuple(sorted(path.stem for path in (DATA / "lookalikes").glob("*.png")))
    assert asked == {"model": Path("m.pt"), "documents": DATA, "data": DATA, "given": lookalikes}
    assert json.loads(out.read_text())["rows"] == report["rows"] == {"as built": row, "keypoint recipe": row}
    assert report["headline"].startswith("150 real photographs: as built 0.500 (P 0.25, R 1.00, 2.00 s/image)")
    assert report["set"]["given"] == list(lookalikes) and report["machine"]["cores"]
    # Every photograph is in one half: the one the texture check's setting was chosen on, or the held-out one.
    chosen, held_out = asked_parts[real_photos.CHOSEN_ON], asked_parts[real_photos.HELD_OUT]
    assert len(asked_parts) == 2 and sorted(chosen + held_out) == list(range(150)) and len(chosen) == 75
    assert report["set"]["parts"] == [real_photos.CHOSEN_ON, real_photos.HELD_OUT]
