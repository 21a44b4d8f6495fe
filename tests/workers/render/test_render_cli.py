"""``foldwise render`` (COCO dataset, preview sheet) and ``foldwise mesh``."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from workers.render.cli import register


@pytest.fixture(scope="module")
def app():
    application = typer.Typer()
    register(application)
    return application


def invoke(app, *args):
    return CliRunner().invoke(app, [str(a) for a in args], catch_exceptions=False)


def test_render_writes_a_coco_dataset_pycocotools_can_load(app, tmp_path):
    from pycocotools.coco import COCO

    out = tmp_path / "data"
    result = invoke(
        app,
        "render",
        "--condition",
        "pose,eo",
        "--difficulty",
        "hard",
        "-n",
        3,
        "--backend",
        "raster",
        "--out",
        out,
        "--seed",
        5,
        "--image-size",
        48,
    )
    assert result.exit_code == 0, result.output
    coco = COCO(str(out / "annotations.json"))
    assert len(coco.getImgIds()) == 6
    assert [c["name"] for c in coco.loadCats(coco.getCatIds())] == [
        "astronaut",
        "coffee",
        "chelsea",
        "rocket",
        "motorcycle_left",
    ]
    for image in coco.loadImgs(coco.getImgIds()):
        assert image["file_name"].startswith("images/")
        pixels = cv2.imread(str(out / image["file_name"]))
        assert pixels.shape == (48, 48, 3) == (image["height"], image["width"], 3)
        assert image["condition"] in ("po", "eo") and image["difficulty"] == "hard"
        assert image["theta"]["condition"] == image["condition"]
        (annotation,) = coco.loadAnns(coco.getAnnIds(imgIds=image["id"]))
        x, y, w, h = annotation["bbox"]
        assert w >= 2 and h >= 2 and 0 <= x and x + w <= 48 and 0 <= y and y + h <= 48
        assert 1 <= annotation["category_id"] <= 5
        assert annotation["category_id"] == image["theta"]["label"] + 1
        assert 0 < annotation["visible_fraction"] <= 1 and annotation["iscrowd"] == 0
        assert len(annotation["amodal_bbox"]) == 4 and annotation["area"] > 0
    # Deterministic: the same command writes the same annotations and pixels.
    again = tmp_path / "again"
    invoke(app, "render", "-c", "po,eo", "-d", "hard", "-n", 3, "--out", again, "--seed", 5, "--image-size", 48)
    first = json.loads((out / "annotations.json").read_text())
    second = json.loads((again / "annotations.json").read_text())
    assert first["annotations"] == second["annotations"]
    assert (out / "images" / "po_hard_00000.png").read_bytes() == (again / "images" / "po_hard_00000.png").read_bytes()


def test_render_accepts_names_and_the_canonical_difficulty(app, tmp_path):
    result = invoke(
        app,
        "render",
        "--condition",
        "focus_blur",
        "--difficulty",
        "canonical,easy",
        "-n",
        1,
        "--out",
        tmp_path,
        "--image-size",
        32,
    )
    assert result.exit_code == 0, result.output
    data = json.loads((tmp_path / "annotations.json").read_text())
    assert [(i["condition"], i["difficulty"]) for i in data["images"]] == [("fb", "canonical"), ("fb", "easy")]


def test_render_rejects_unknown_names(app, tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["render", "--condition", "wobble", "--out", str(tmp_path)])
    assert result.exit_code != 0 and "unknown condition 'wobble'" in result.output
    result = runner.invoke(app, ["render", "--condition", "po", "--difficulty", "extreme", "--out", str(tmp_path)])
    assert result.exit_code != 0 and "unknown difficulty 'extreme'" in result.output
    result = runner.invoke(app, ["render", "--backend", "povray", "--out", str(tmp_path)])
    assert result.exit_code != 0 and "povray" in result.output
    empty = tmp_path / "empty"
    empty.mkdir()
    result = runner.invoke(app, ["render", "--backgrounds", str(empty), "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and "holds no images" in result.output


def test_preview_contact_sheet(app, tmp_path):
    out = tmp_path / "sheet.png"
    result = invoke(app, "render", "--preview", "--out", out, "--image-size", 32, "--condition", "fb,eo")
    assert result.exit_code == 0, result.output
    sheet = cv2.imread(str(out))
    # Two rows of four cells (canonical, easy, medium, hard) beside a label column.
    assert sheet.shape[0] > 2 * 32 and sheet.shape[1] > 4 * 32
    assert not (sheet == 255).all()


def test_preview_shows_every_variant_of_a_condition_in_a_row_of_its_own(app, tmp_path):
    from foldwise.conditions import load_condition_table
    from workers.render.cli import preview_rows

    rows = preview_rows(load_condition_table(), ["fb", "sc", "li"])
    assert rows == [("fb", None), ("sc", "small"), ("sc", "large"), ("li", "dark"), ("li", "bright")]
    out = tmp_path / "sheet.png"
    result = invoke(app, "render", "--preview", "--out", out, "--image-size", 32, "--condition", "li")
    assert result.exit_code == 0, result.output
    sheet = cv2.imread(str(out))[:, :, ::-1]
    header, cell, caption, pad, label = 24, 32, 16, 4, 150
    assert sheet.shape[0] == header + 2 * (cell + caption + pad)
    # Same objects and backgrounds in both rows: at hard, the dark cell is far darker than the bright one.
    x = label + 3 * (cell + pad)
    dark = sheet[header : header + cell, x : x + cell].astype(float).mean()
    y = header + cell + caption + pad
    bright = sheet[y : y + cell, x : x + cell].astype(float).mean()
    assert bright > dark + 20


def test_mesh_writes_an_obj(app, tmp_path):
    out = tmp_path / "sheet.obj"
    result = invoke(app, "mesh", "--rulings", 3, "--seed", 2, "--out", out)
    assert result.exit_code == 0, result.output
    lines = out.read_text().splitlines()
    vertices = [line for line in lines if line.startswith("v ")]
    uvs = [line for line in lines if line.startswith("vt ")]
    faces = [line for line in lines if line.startswith("f ")]
    assert vertices and len(uvs) == len(vertices) and faces
    indices = np.array([[int(p.split("/")[0]) for p in f.split()[1:]] for f in faces])
    assert indices.min() == 1 and indices.max() == len(vertices)
    assert "3 guiding rulings" in result.output


def test_images_that_fail_every_resample_are_recorded_and_fail_the_command(app, tmp_path, monkeypatch):
    import types

    from workers.render import paper_model, pipeline

    def intersecting(*args, **kwargs):
        raise paper_model.SelfIntersection("always")

    monkeypatch.setattr(
        pipeline,
        "_paper_model",
        lambda: types.SimpleNamespace(sample_sheet=intersecting, SelfIntersection=paper_model.SelfIntersection),
    )
    result = CliRunner().invoke(
        app,
        [
            "render",
            "-c",
            "de",
            "-d",
            "hard",
            "-n",
            "2",
            "--max-resamples",
            "1",
            "--out",
            str(tmp_path),
            "--image-size",
            "32",
        ],
    )
    assert result.exit_code == 1
    data = json.loads((tmp_path / "annotations.json").read_text())
    assert data["images"] == [] and len(data["failures"]) == 2
    assert data["failures"][0]["reasons"] == ["self-intersecting sheet: always"] * 2
