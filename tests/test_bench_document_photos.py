"""bench/document_photos.py: phone-like pictures of the printed documents, and the rows scored on
them (the detector as built, given lookalikes, the keypoint recipe)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import document_photos  # noqa: E402
from bench.printed_documents import make_documents  # noqa: E402


@pytest.fixture(scope="module")
def documents(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("documents")
    # Two targets and one lookalike of each kind: the tests check what is drawn, scored and given
    # to the check, and SIFT on each sheet's tilted views is most of their time.
    make_documents(folder, n_targets=2, n_same_template=1, n_other_template=1, n_text=1)
    return folder


def test_a_curled_sheet_is_narrower_and_darker_where_it_turns_away():
    sheet = np.full((40, 100, 3), 200, np.uint8)
    assert document_photos.curled(sheet, 0.0) is sheet
    bent = document_photos.curled(sheet, 1.5)
    assert bent.shape[0] == 40 and bent.shape[1] < 100
    assert bent[:, 0].mean() < bent[:, bent.shape[1] // 2].mean()


def test_the_pictures_hold_the_targets_where_their_boxes_say_and_repeat_with_their_seed(documents, tmp_path):
    import cv2

    first = document_photos.make_photo_set(documents, tmp_path / "a", 6, seed=3, size=(320, 240))
    again = document_photos.make_photo_set(documents, tmp_path / "b", 6, seed=3, size=(320, 240))
    other = document_photos.make_photo_set(documents, tmp_path / "c", 6, seed=4, size=(320, 240))
    coco = json.loads((first / "annotations.json").read_text())
    assert [c["name"] for c in coco["categories"]] == sorted(p.stem for p in (documents / "targets").glob("*.png"))
    assert coco["annotations"], "no target in six pictures"
    for annotation in coco["annotations"]:
        x, y, w, h = annotation["bbox"]
        assert 0 <= x and 0 <= y and x + w <= 320 and y + h <= 240
        assert w * h >= document_photos.MIN_VISIBLE_PX
    for image in coco["images"]:
        assert cv2.imread(str(first / image["file_name"])).shape == (240, 320, 3)
    assert coco == json.loads((again / "annotations.json").read_text())
    assert coco != json.loads((other / "annotations.json").read_text())


def test_the_lookalike_row_gives_the_check_the_named_lookalikes_and_the_built_row_none(
    documents, tmp_path, monkeypatch
):
    from tests.workers.train.training_helpers import config
    from workers.train import texture_check
    from workers.train.data import load_coco_dataset
    from workers.train.training import train_detector

    data = document_photos.make_photo_set(documents, tmp_path / "set", 4, seed=5, size=(256, 192))
    samples, classes = load_coco_dataset(data)
    textures = document_photos.read_sheets(documents / "targets")
    model = tmp_path / "model.pt"
    train_detector(samples, None, 2, config(texture_check=True, texture_search=True), classes, model, textures=textures)
    seen = []
    built = texture_check.TextureCheck.__init__

    def recording(self, *args, lookalikes=None, **kwargs):
        seen.append(sorted(lookalikes or {}))
        built(self, *args, lookalikes=lookalikes, **kwargs)

    monkeypatch.setattr(texture_check.TextureCheck, "__init__", recording)
    rows = document_photos.score_rows(model, documents, data, given=("same1-1", "text1"))
    assert list(rows) == ["as built", "given 2 lookalikes", "keypoint recipe"]
    assert seen == [[], ["same1-1", "text1"]]
    for row in rows.values():
        assert row["images"] == 4 and 0 <= row["map"] <= 1 and "precision" in row["at_threshold"]


def test_a_folder_without_the_documents_is_refused_by_name(tmp_path):
    (tmp_path / "targets").mkdir()
    with pytest.raises(SystemExit, match="no targets"):
        document_photos.make_photo_set(tmp_path, tmp_path / "set", 2, seed=0)
    assert not (tmp_path / "set" / "annotations.json").exists()
