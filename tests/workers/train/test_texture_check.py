"""The texture check confirms a box its texture's outline agrees with, turns a piece of a sheet
into the whole, renames a box that matches another texture, and leaves alone what it has no
evidence on."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from workers.train.texture_check import CONFIRMED_FLOOR, TextureCheck

CLASSES = ["astronaut", "coffee"]


@pytest.fixture(scope="module")
def textures():
    return {"astronaut": skimage.data.astronaut(), "coffee": skimage.data.coffee()}


@pytest.fixture(scope="module")
def checker(textures):
    return TextureCheck(textures, CLASSES)


@pytest.fixture(scope="module")
def scene(textures):
    """A 320x240 image: the astronaut texture turned by 12°, shrunk to 150 px and placed at
    (40, 30), over a blurred noise ground with a flat grey card at the right. Its true box."""
    rng = np.random.default_rng(3)
    ground = cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3)).astype(np.uint8), (0, 0), 3)
    ground[60:200, 230:310] = 128
    texture = textures["astronaut"]
    scale = 150 / texture.shape[1]
    affine = cv2.getRotationMatrix2D((0, 0), 12, scale)
    affine[:, 2] += (40, 60)
    warped = cv2.warpAffine(texture, affine, (320, 240))
    mask = cv2.warpAffine(np.full(texture.shape[:2], 255, np.uint8), affine, (320, 240)) > 0
    image = np.where(mask[:, :, None], warped, ground)
    ys, xs = np.nonzero(mask)
    return image, np.array([xs.min(), ys.min(), xs.max(), ys.max()], np.float32)


def detections(*rows):
    """(box, score, label) rows as detect_object gives them."""
    return {
        "boxes": np.array([row[0] for row in rows], np.float32).reshape(-1, 4),
        "scores": np.array([row[1] for row in rows], np.float32),
        "labels": np.array([row[2] for row in rows], np.int64),
    }


def test_a_box_the_outline_agrees_with_is_raised_over_the_cut_and_keeps_its_order(checker, scene):
    image, box = scene
    checked = checker.apply(image, detections((box, 0.5, 0)))
    assert checked["scores"][0] == pytest.approx(CONFIRMED_FLOOR + (1 - CONFIRMED_FLOOR) * 0.5)
    assert checked["labels"][0] == 0
    np.testing.assert_array_equal(checked["boxes"][0], box)
    higher = checker.apply(image, detections((box, 0.9, 0)))["scores"][0]
    assert higher > checked["scores"][0]  # a surer box stays surer


def test_a_piece_of_the_sheet_becomes_the_outline_and_merges_with_the_whole(checker, scene):
    image, box = scene
    x0, y0, x1, y1 = box
    piece = [x0, y0, (x0 + x1) / 2, (y0 + y1) / 2]
    alone = checker.apply(image, detections((piece, 0.9, 0)))
    assert alone["scores"][0] == pytest.approx(0.8 + 0.2 * 0.9)
    assert _iou(alone["boxes"][0], box) > 0.8  # the whole sheet, not the piece
    found = detections((piece, 0.9, 0), (box, 0.6, 0))
    merged = checker.apply(image, found)
    assert len(merged["scores"]) == 1 and merged["scores"][0] == pytest.approx(0.8 + 0.2 * 0.9)
    np.testing.assert_array_equal(found["boxes"][0], piece)  # the caller's arrays are left as they were


def _iou(a, b) -> float:
    from workers.train.texture_check import _box_iou

    return _box_iou(np.asarray(a, np.float64), np.asarray(b, np.float64))


def test_a_box_named_wrong_is_renamed_to_the_texture_it_matches(checker, scene):
    image, box = scene
    checked = checker.apply(image, detections((box, 0.85, 1)))  # called coffee
    assert checked["labels"][0] == 0 and checked["scores"][0] > 0.85


def test_without_evidence_nothing_changes(checker, scene):
    image, box = scene
    found = detections(([250, 20, 300, 50], 0.95, 0), ([232, 62, 308, 198], 0.9, 1), (box, 0.2, 1))
    checked = checker.apply(image, found)  # a flat card, blurred noise, and a box under the floor
    for key in ("boxes", "scores", "labels"):
        np.testing.assert_array_equal(checked[key], found[key])
    blank = np.full((240, 320, 3), 90, np.uint8)  # no keypoint at all
    for key, value in checker.apply(blank, detections((box, 0.7, 0))).items():
        np.testing.assert_array_equal(value, detections((box, 0.7, 0))[key])
    empty = checker.apply(image, detections())
    assert empty["boxes"].shape == (0, 4) and len(empty["scores"]) == len(empty["labels"]) == 0


def test_grayscale_images_and_textures_work_and_a_missing_texture_is_named(textures, scene):
    image, box = scene
    gray = {name: cv2.cvtColor(t, cv2.COLOR_RGB2GRAY) for name, t in textures.items()}
    checked = TextureCheck(gray, CLASSES).apply(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), detections((box, 0.5, 0)))
    assert checked["scores"][0] >= CONFIRMED_FLOOR
    with pytest.raises(ValueError, match=r"no texture for class\(es\) \['rocket'\]"):
        TextureCheck(textures, CLASSES + ["rocket"])


def test_a_mirrored_fit_is_no_evidence(checker, scene, monkeypatch):
    """Matches whose map mirrors the texture (a printed sheet shows its front only) leave the box
    as the network gave it, where the same matches unmirrored confirm it."""
    image, box = scene
    x0, y0, x1, y1 = box
    rng = np.random.default_rng(0)
    texture_points = rng.uniform(0, 512, (40, 2)).astype(np.float32)
    scale = (x1 - x0) / 512
    upright = np.stack([x0 + texture_points[:, 0] * scale, y0 + texture_points[:, 1] * scale], axis=1)
    mirrored = np.stack([x1 - texture_points[:, 0] * scale, upright[:, 1]], axis=1)
    found = detections((box, 0.5, 0))
    for points, raised in ((upright, True), (mirrored, False)):
        monkeypatch.setattr(checker, "_matches", lambda gray, p=points: (p, np.zeros(len(p), np.int64), texture_points))
        assert bool(checker.apply(image, found)["scores"][0] > 0.8) == raised
