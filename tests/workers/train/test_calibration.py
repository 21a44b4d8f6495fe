"""Scores that mean something: the calibration learns how likely a detection is true from the
network's score and the texture's evidence, travels in the checkpoint, and the texture check's
evidence tells a sheet from a lookalike of its template and follows a creased sheet."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from workers.train import texture_check
from workers.train.calibration import FEATURES, Calibration, fit
from workers.train.texture_check import TextureCheck


def test_fit_recovers_a_logistic_model_and_its_probabilities_are_calibrated():
    rng = np.random.default_rng(0)
    features = rng.normal(size=(4000, len(FEATURES)))
    true_weights = np.array([1.5, 2.0, -1.0, 0.0, 0.5, 1.0])
    probability = 1 / (1 + np.exp(-(0.3 + features @ true_weights)))
    truths = rng.random(4000) < probability
    fitted = fit(features, truths)
    np.testing.assert_allclose(fitted.weights, true_weights, atol=0.25)
    predicted = fitted.probability(features)
    sure = predicted >= 0.8
    # Of the detections scored 0.8 or more, at least as many are true as the scores promise.
    assert truths[sure].mean() >= 0.8
    assert abs(truths[sure].mean() - predicted[sure].mean()) < 0.03


def test_a_calibration_round_trips_and_bad_records_are_named():
    fitted = Calibration(weights=(1.0, 2.0, 0.5, 1.0, 0.1, 0.2), bias=-3.0, fitted_on="a set")
    assert Calibration.from_dict(fitted.to_dict()) == fitted
    with pytest.raises(ValueError, match="features"):
        Calibration.from_dict({**fitted.to_dict(), "features": ["network"]})
    with pytest.raises(ValueError, match="finite"):
        Calibration(weights=(float("nan"),) * len(FEATURES), bias=0.0)
    with pytest.raises(ValueError, match="malformed"):
        Calibration.from_dict({"weights": [1.0]})
    with pytest.raises(ValueError, match="both true and false"):
        fit(np.zeros((3, len(FEATURES))), [True, True, True])


def _page(seed: int, letterhead_seed: int = 0) -> np.ndarray:
    """A 400x560 printed page: a letterhead and footer of ``letterhead_seed``'s template, and a
    body of shapes of its own (``seed``)."""
    page = np.full((560, 400, 3), 250, np.uint8)
    template = np.random.default_rng(letterhead_seed)
    for _ in range(25):  # letterhead and footer: the template's
        y = int(template.choice([template.integers(10, 70), template.integers(500, 550)]))
        x = int(template.integers(10, 380))
        cv2.circle(page, (x, y), int(template.integers(3, 9)), tuple(int(v) for v in template.integers(0, 200, 3)), -1)
    body = np.random.default_rng(100 + seed)
    for _ in range(160):  # the body: the sheet's own
        x, y = int(body.integers(10, 390)), int(body.integers(90, 480))
        w, h = int(body.integers(3, 20)), int(body.integers(3, 12))
        colour = tuple(int(v) for v in body.integers(0, 200, 3))
        cv2.rectangle(page, (x, y), (x + w, y + h), colour, -1) if body.random() < 0.5 else cv2.circle(
            page, (x, y), w // 2 + 2, colour, -1
        )
    return page


def _placed(texture: np.ndarray, scale: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    image = np.full((360, 480, 3), 90, np.uint8)
    affine = np.array([[scale, 0, 80], [0, scale, 30]], np.float64)
    cv2.warpAffine(texture, affine, (480, 360), dst=image, borderMode=cv2.BORDER_TRANSPARENT)
    h, w = texture.shape[:2]
    return image, np.array([80, 30, 80 + w * scale, 30 + h * scale], np.float32)


def test_a_lookalike_of_the_template_covers_less_of_the_texture_and_ranks_below_the_sheet(monkeypatch):
    """Both confirmed (``MIN_SHOWN`` off: the rule that withdraws such a sheet is tested below),
    the lookalike ranks below the sheet by the share of the texture it covers, however much surer
    the network is of it (the sheet at the least score the check looks at, the lookalike near 1)."""
    monkeypatch.setattr(texture_check, "MIN_SHOWN", 0.0)
    sheet, lookalike = _page(seed=1), _page(seed=2)  # one template, other bodies
    check = TextureCheck({"sheet": sheet}, ["sheet"])
    checked = []
    for page, network in ((sheet, texture_check.MIN_SCORE), (lookalike, 0.999)):
        image, box = _placed(page)
        found = {"boxes": box[None], "scores": np.array([network], np.float32), "labels": np.array([0])}
        checked.append(check.apply(image, found, with_evidence=True))
    coverages = [found["evidence"][0, FEATURES.index("coverage")] for found in checked]
    assert coverages[0] > 0.5
    assert coverages[1] < coverages[0] / 2
    assert [found["confirmed"].tolist() for found in checked] == [[True], [True]]
    assert checked[0]["scores"][0] > checked[1]["scores"][0] >= texture_check.CONFIRMED_FLOOR


def _photographed(page: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The page nearly at its own size in a 600x640 frame, as a phone photographs a sheet: every
    part of it shows enough print for the check to tell whether its maps explain it."""
    image = np.full((640, 600, 3), 90, np.uint8)
    affine = np.array([[0.95, 0, 60], [0, 0.95, 40]], np.float64)
    cv2.warpAffine(page, affine, (600, 640), dst=image, borderMode=cv2.BORDER_TRANSPARENT)
    h, w = page.shape[:2]
    return image, np.array([60, 40, 60 + w * 0.95, 40 + h * 0.95], np.float32)


def test_a_sheet_of_the_targets_template_is_not_confirmed_by_the_print_the_two_share(monkeypatch):
    """Another sheet of the target's template matches its letterhead and footer, enough for a
    map; its own body shows print those maps do not explain, so it is not confirmed and drops
    under the cut. The target itself is confirmed over it."""
    check = TextureCheck({"sheet": _page(seed=1)}, ["sheet"])

    def checked(page):
        image, box = _photographed(page)
        return check.apply(image, {"boxes": box[None], "scores": np.array([0.9], np.float32), "labels": np.array([0])})

    sheet, form = checked(_page(seed=1)), checked(_page(seed=2))
    assert sheet["confirmed"].tolist() == [True] and sheet["scores"][0] >= texture_check.CONFIRMED_FLOOR
    assert form["confirmed"].tolist() == [False] and form["scores"][0] < texture_check.PAPER_CUT
    monkeypatch.setattr(texture_check, "MIN_SHOWN", 0.0)  # the template's matches alone: a map, so confirmed
    assert checked(_page(seed=2))["confirmed"].tolist() == [True]


def test_a_small_sheet_showing_little_print_keeps_its_confirmation():
    """Far away, a cell of the sheet holds too few keypoints to say its print is unexplained: the
    few matches that agree on a map confirm it."""
    page = _page(seed=1)
    check = TextureCheck({"sheet": page}, ["sheet"])
    image, box = _placed(page, scale=0.35)
    found = check.apply(image, {"boxes": box[None], "scores": np.array([0.9], np.float32), "labels": np.array([0])})
    assert found["confirmed"].tolist() == [True] and found["scores"][0] >= texture_check.CONFIRMED_FLOOR


def test_no_box_is_drawn_on_a_sheet_shown_to_be_another():
    """A box without evidence (another class, no map) over much of a sheet whose own box was shown
    to be a sheet of the target's template drops under the cut with it: the sheet is accounted
    for. The box reaches past the sheet, so it is no piece of the confirmed outline the merges
    drop, and holds the body, not the letterhead, so the target's texture does not rename it."""
    check = TextureCheck({"sheet": _page(seed=1), "other": _page(seed=5, letterhead_seed=9)}, ["sheet", "other"])
    image, box = _photographed(_page(seed=2))
    x0, y0, x1, y1 = box
    width, height = x1 - x0, y1 - y0
    beside = [x0 + 0.3 * width, y0 + 0.15 * height, x1 + 0.2 * width, y0 + 0.88 * height]
    found = {
        "boxes": np.array([box, beside], np.float32),
        "scores": np.array([0.9, 0.85], np.float32),
        "labels": np.array([0, 1]),
    }
    checked = check.apply(image, found)
    assert len(checked["scores"]) == 2 and not checked["confirmed"].any()
    assert (checked["scores"] < texture_check.PAPER_CUT).all(), checked["scores"]


def test_a_creased_sheet_is_followed_by_a_second_map(monkeypatch):
    """A sheet folded across its middle (each half its own affine image, 40° apart): the box
    takes both halves in, where the map of one half alone leaves the other out."""
    texture = _page(seed=3)
    image = np.full((360, 480, 3), 90, np.uint8)
    top, bottom = texture[:280], texture[280:]
    first = np.array([[0.45, 0.0, 40.0], [0.0, 0.45, 10.0]])
    fold = cv2.getRotationMatrix2D((0, 0), 40, 0.45)
    fold[:, 2] = (40.0, 10.0 + 126.0)
    for half, affine in ((top, first), (bottom, fold)):
        cv2.warpAffine(half, affine, (480, 360), dst=image, borderMode=cv2.BORDER_TRANSPARENT)
    corners = np.array([[0, 0, 1], [400, 0, 1], [400, 280, 1], [0, 280, 1]], np.float64)
    extent = np.vstack([corners @ first.T, corners @ fold.T])
    truth = np.array([extent[:, 0].min(), extent[:, 1].min(), extent[:, 0].max(), extent[:, 1].max()], np.float32)
    found = {"boxes": truth[None], "scores": np.array([0.9], np.float32), "labels": np.array([0])}

    def reach(check) -> float:
        checked = check.apply(image, found, with_evidence=True)
        assert checked["confirmed"].tolist() == [True]
        return _iou(checked["boxes"][0], truth)

    followed = reach(TextureCheck({"sheet": texture}, ["sheet"]))
    monkeypatch.setattr(texture_check, "LOCAL_MAPS", 1)
    one_map = reach(TextureCheck({"sheet": texture}, ["sheet"]))
    assert followed > one_map + 0.05, (followed, one_map)


def _iou(a, b) -> float:
    import torch
    from torchvision.ops import box_iou

    return float(
        box_iou(torch.as_tensor(np.asarray(a, np.float32))[None], torch.as_tensor(np.asarray(b, np.float32))[None])
    )


def test_one_box_per_sheet_drops_a_piece_and_another_name_inside_a_confirmed_sheet():
    texture = _page(seed=4)
    check = TextureCheck({"sheet": texture, "other": _page(seed=5, letterhead_seed=9)}, ["sheet", "other"])
    image, box = _placed(texture)
    x0, y0, x1, y1 = box
    piece = [x0 + 10, (y0 + y1) / 2, x1 - 10, y1 - 5]  # a piece the network boxed on its own
    found = {
        "boxes": np.array([box, piece, box + 2], np.float32),
        "scores": np.array([0.9, 0.85, 0.8], np.float32),
        "labels": np.array([0, 0, 1]),  # the third: the sheet named as the other class
    }
    checked = check.apply(image, found)
    assert len(checked["boxes"]) == 1 and checked["labels"].tolist() == [0]


def test_a_detector_trained_with_the_shipped_calibration_records_it_and_scores_by_it(tmp_path):
    from foldwise.config import ConfigError, parse_config
    from tests.workers.train.training_helpers import CLASSES, config, synthetic_samples
    from workers.train.calibration import shipped_calibration
    from workers.train.checkpoint import load_detector, read_checkpoint
    from workers.train.training import train_detector

    samples = synthetic_samples(tmp_path / "images", n=3)
    textures = {name: _page(seed=index) for index, name in enumerate(CLASSES)}
    out = tmp_path / "model.pt"
    train_detector(samples, None, 1, config(texture_check=True, calibration="shipped"), CLASSES, out, textures=textures)
    assert read_checkpoint(out)["meta"]["calibration"] == shipped_calibration().to_dict()
    detector = load_detector(out)
    assert detector.calibration == shipped_calibration()
    assert detector.texture_check().calibration == shipped_calibration()
    tiers = tmp_path / "tiers.pt"
    train_detector(samples, None, 1, config(texture_check=True), CLASSES, tiers, textures=textures)
    assert load_detector(tiers).calibration is None
    with pytest.raises(ConfigError, match="calibration"):
        parse_config({"name": "c", "detector": {"calibration": "shipped"}})


def test_lookalikes_given_to_the_check_stop_a_shared_template_from_confirming():
    """A lookalike of the sheet's template (its letterhead and footer) matches the sheet's texture
    there; given to the check as a lookalike, those shared keypoints are no evidence: the
    lookalike is not confirmed, the sheet itself still is."""
    sheet, lookalike = _page(seed=1), _page(seed=2)
    plain = TextureCheck({"sheet": sheet}, ["sheet"])
    knowing = TextureCheck({"sheet": sheet}, ["sheet"], lookalikes={"other form": lookalike})
    inliers = FEATURES.index("inliers")
    results = {}
    for name, page in (("sheet", sheet), ("lookalike", lookalike)):
        image, box = _placed(page)
        found = {"boxes": box[None], "scores": np.array([0.9], np.float32), "labels": np.array([0])}
        results[name] = [check.apply(image, found, with_evidence=True) for check in (plain, knowing)]
    assert results["lookalike"][0]["evidence"][0][inliers] > 0  # the template alone agrees on a map
    assert results["lookalike"][1]["confirmed"].tolist() == [False]
    assert results["lookalike"][1]["evidence"][0][inliers] < results["lookalike"][0]["evidence"][0][inliers]
    assert results["sheet"][1]["confirmed"].tolist() == [True]


def test_a_box_showing_a_given_lookalike_drops_under_the_cut_however_sure_the_network(monkeypatch):
    """The network boxes a lookalike at 0.95, and a few keypoints in it match the sheet's texture
    (too few for a map: no evidence either way). Known to the check, the lookalike's own texture
    fits a map there, so the box is that lookalike and drops under the cut; the sheet itself is
    still confirmed."""
    from tests.workers.train.training_helpers import with_a_few_matches

    sheet, lookalike = _page(seed=1), _page(seed=2)
    knowing = TextureCheck({"sheet": sheet}, ["sheet"], lookalikes={"other form": lookalike})
    sure = np.array([0.95], np.float32)
    image, box = _placed(lookalike)
    with_a_few_matches(monkeypatch, knowing, (box, 0))
    checked = knowing.apply(image, {"boxes": box[None], "scores": sure, "labels": np.array([0])})
    assert checked["confirmed"].tolist() == [False]
    assert checked["scores"][0] < texture_check.PAPER_CUT
    image, box = _placed(sheet)
    checked = knowing.apply(image, {"boxes": box[None], "scores": sure, "labels": np.array([0])})
    assert checked["confirmed"].tolist() == [True] and checked["scores"][0] >= texture_check.CONFIRMED_FLOOR


def test_matches_to_a_lookalike_are_no_class_s_matches():
    """The lookalike's keypoints are found (they decide the rule above) but never counted as the
    class's: the class's matches on a picture of the lookalike are those of the sheet alone."""
    sheet, lookalike = _page(seed=1), _page(seed=2)
    knowing = TextureCheck({"sheet": sheet}, ["sheet"], lookalikes={"other form": lookalike})
    image, _ = _placed(lookalike)
    gray = texture_check.grayscale(image)
    _, _, labels, _ = knowing._keypoints_and_matches(gray)
    assert (labels == 1).sum() >= 20  # the lookalike's own matches
    assert set(knowing._matches(gray)[1].tolist()) <= {0}


def test_a_checkpoint_carries_the_lookalikes_for_its_texture_check(tmp_path):
    """What training saves with ``assets.lookalikes`` (save_checkpoint's ``lookalikes``) is what
    the loaded detector's texture check knows as no class."""
    from foldwise.config import load_config
    from workers.render.assets import load_assets
    from workers.train.checkpoint import load_detector, save_checkpoint
    from workers.train.detectors import build_detector

    config = load_config("configs/smoke.yaml").detector.model_copy(update={"texture_check": True})
    classes = ["astronaut", "coffee"]
    model = build_detector(config, num_classes=len(classes))
    textures = load_assets().textures(classes)
    meta = {
        "family": config.family,
        "backbone": config.backbone,
        "classes": classes,
        "input_size": config.input_size,
        "config": config.model_dump(mode="json"),
    }
    path = save_checkpoint(
        model, meta, tmp_path / "m.pt", textures=textures, lookalikes={"form-b": np.full((96, 68, 3), 200, np.uint8)}
    )
    detector = load_detector(path)
    assert set(detector.lookalikes) == {"form-b"}
    assert detector.texture_check().lookalikes == ["form-b"]


def test_a_calibration_is_fitted_on_the_detections_the_detector_draws(tmp_path, monkeypatch):
    """``calibrate_detector`` reads the evidence of what the detector gives when used: its
    cascade's passes (one view first, every view where the texture confirmed nothing), its
    lookalikes; a calibration the detector already records does not change the fit."""
    from dataclasses import replace

    from tests.sheet_sets import CLASSES, class_textures, sheet_set
    from tests.workers.train.training_helpers import config
    from workers.train.calibration import calibrate_detector
    from workers.train.checkpoint import Cascade, detect_object, load_detector
    from workers.train.evaluation import true_detections
    from workers.train.training import train_detector

    textures = class_textures()
    samples = sheet_set(tmp_path / "sheets", 4, textures)
    views = config(texture_check=True, test_sizes=[64, 96], test_turns=[0, 1], view_vote=0.7)
    path = tmp_path / "model.pt"
    form = _page(seed=2)
    train_detector(samples, None, 2, views, CLASSES, path, textures=textures, lookalikes={"form": form})
    detector = load_detector(path)
    passes = []
    monkeypatch.setattr(Cascade, "again", lambda self, checked: passes.append(1) or not checked["confirmed"].any())
    fitted = calibrate_detector(detector, samples, CLASSES)
    assert len(passes) == len(samples)  # every image went through the cascade's first pass

    drawn = detect_object(detector, [sample.image_path for sample in samples], with_evidence=True)
    assert detector.texture_check().lookalikes == ["form"]
    features = np.concatenate([found["evidence"] for found in drawn])
    truths = np.concatenate(
        [true_detections(found, {"boxes": s.boxes, "labels": s.labels}) for found, s in zip(drawn, samples)]
    )
    assert fitted == fit(features, truths)
    recorded = replace(detector, meta={**detector.meta, "calibration": Calibration((9.0,) * 6, -9.0).to_dict()})
    assert calibrate_detector(recorded, samples, CLASSES) == fitted
