"""A user's labelled photographs in the loop (test_set.photographs): every increment is scored
on them, beside the renders or as the standard test set that P and the stopping rule read."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml
from sqlalchemy import select
from typer.testing import CliRunner

from db.models import Evaluation, Model
from db.session import session_scope
from foldwise.settings import REPO_ROOT


def _photographs(folder, classes=("astronaut", "coffee")):
    """A COCO export of four labelled photos, portrait and landscape."""
    (folder / "images").mkdir(parents=True)
    rng = np.random.default_rng(5)
    images, annotations = [], []
    for i, (width, height) in enumerate([(96, 64), (64, 96), (80, 80), (96, 72)]):
        pixels = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
        name = f"photo{i}.jpg"
        assert cv2.imwrite(str(folder / "images" / name), pixels)
        images.append({"id": i + 1, "file_name": f"images/{name}", "width": width, "height": height})
        box = [8, 8, width // 2, height // 2]  # x, y, w, h
        annotations.append({"id": i + 1, "image_id": i + 1, "category_id": 1 + i % 2, "bbox": box, "area": 1})
    categories = [{"id": i + 1, "name": name} for i, name in enumerate(classes)]
    coco = {"images": images, "annotations": annotations, "categories": categories}
    (folder / "annotations.json").write_text(json.dumps(coco))
    return folder


@pytest.mark.parametrize("role", ["beside", "standard"])
def test_every_increment_is_scored_on_the_photographs(database, tmp_path, role):
    from services.cli import _register_worker_commands, app

    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["curriculum"]["difficulties"] = ["easy"]
    config["active_learning"]["max_increments"] = 1
    config["test_set"] = {
        **config["test_set"],
        "photographs": str(_photographs(tmp_path / "photos")),
        "photographs_role": role,
    }
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    _register_worker_commands()
    result = CliRunner().invoke(app, ["run", str(path), "--report-dir", str(tmp_path / "report")])
    assert result.exit_code == 0, result.output

    with session_scope() as session:
        rows = session.execute(select(Evaluation).join(Model, Model.id == Evaluation.model_id)).scalars().all()
        assert rows
        for evaluation in rows:
            photos = evaluation.details["photographs"]
            assert photos["role"] == role and photos["num_images"] == 4 and photos["num_ground_truth"] == 4
            # P is the photographs' score as the standard set, else the renders' (the details' own).
            expected = photos if role == "standard" else evaluation.details
            assert evaluation.map_unthresholded == pytest.approx(expected["map_unthresholded"])
            assert evaluation.details["num_images"] == 4  # the renders' standard test set is still scored
