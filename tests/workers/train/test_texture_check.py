"""The texture check confirms a box its texture's outline agrees with (the outline becoming the
box), turns a piece of a sheet into the whole, renames a box whose matches of another texture
agree on that texture's map (not a box that merely matches it more often), and
leaves what it has no evidence on on its side of the paper's cut, ranked below what it confirmed.
With the search, the texture also finds the sheets the network gave no box for."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from tests.workers.train.training_helpers import with_a_few_matches
from workers.train import texture_cache, texture_check
from workers.train.calibration import FEATURES, Calibration
from workers.train.texture_check import (
    CONFIRMED_FLOOR,
    MIN_AXIS_RATIO,
    MIN_SCORE,
    PAPER_CUT,
    SEARCH_MIN_INLIERS,
    SIFT_MAX_SIDE,
    TextureCheck,
    confirmed_score,
    sift_scale,
)

COVERAGE = FEATURES.index("coverage")

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


def test_a_confirmed_box_becomes_the_outline_raised_over_the_cut_in_its_order(checker, scene):
    image, box = scene
    slightly_off = box + np.array([6, -5, 4, 3], np.float32)  # agrees with the sheet, loosely
    checked = checker.apply(image, detections((slightly_off, 0.5, 0)), with_evidence=True)
    assert checked["evidence"][0, COVERAGE] > 0.5  # the whole sheet's keypoints agree
    assert checked["scores"][0] == pytest.approx(confirmed_score(checked["evidence"][0, COVERAGE]))
    assert checked["confirmed"].tolist() == [True]
    assert checked["labels"][0] == 0
    assert _iou(checked["boxes"][0], box) > _iou(slightly_off, box)  # the texture's outline: closer to the sheet
    surer = checker.apply(image, detections((slightly_off, 0.9, 0)))["scores"][0]
    assert surer == checked["scores"][0]  # ranked by the texture's evidence, not the network's


def test_a_piece_of_the_sheet_becomes_the_outline_and_merges_with_the_whole(checker, scene):
    image, box = scene
    x0, y0, x1, y1 = box
    piece = [x0, y0, (x0 + x1) / 2, (y0 + y1) / 2]
    alone = checker.apply(image, detections((piece, 0.9, 0)), with_evidence=True)
    assert alone["scores"][0] == pytest.approx(confirmed_score(alone["evidence"][0, COVERAGE]))
    assert _iou(alone["boxes"][0], box) > 0.8  # the whole sheet, not the piece
    found = detections((piece, 0.9, 0), (box, 0.6, 0))
    merged = checker.apply(image, found, with_evidence=True)
    assert len(merged["scores"]) == 1 and merged["scores"][0] == pytest.approx(
        confirmed_score(merged["evidence"][0, COVERAGE])
    )
    np.testing.assert_array_equal(found["boxes"][0], piece)  # the caller's arrays are left as they were


def _iou(a, b) -> float:
    import torch
    from torchvision.ops import box_iou

    return float(
        box_iou(torch.as_tensor(np.asarray(a, np.float32))[None], torch.as_tensor(np.asarray(b, np.float32))[None])
    )


def test_a_box_named_wrong_is_renamed_to_the_texture_it_matches(checker, scene):
    image, box = scene
    checked = checker.apply(image, detections((box, 0.85, 1)))  # called coffee
    assert checked["labels"][0] == 0 and checked["scores"][0] > 0.85


def _match_set(matches) -> set[tuple]:
    image_points, labels, texture_points = matches
    return {(*np.round(p, 2), int(label), *np.round(q, 2)) for p, label, q in zip(image_points, labels, texture_points)}


def test_flann_finds_nearly_every_match_brute_force_does_and_is_the_same_each_time(checker, textures, scene):
    """The KD-trees are drawn at random but seeded: two checks built apart match alike, to the
    byte. Against brute force over every texture keypoint they keep at least 90% of its matches
    through the ratio test, and the sheet is confirmed as the same outline."""
    image, box = scene
    gray = texture_check.grayscale(image)
    again = TextureCheck(textures, CLASSES)
    for ours, theirs in zip(checker._matches(gray), again._matches(gray)):
        np.testing.assert_array_equal(ours, theirs)
    exact = TextureCheck(textures, CLASSES, exact=True)
    assert exact._index is None and checker._index is not None
    brute_force, flann = _match_set(exact._matches(gray)), _match_set(checker._matches(gray))
    assert len(brute_force) > 100 and len(brute_force & flann) >= 0.9 * len(brute_force)
    found = detections((box, 0.5, 0))
    by_flann, by_brute_force = checker.apply(image, found), exact.apply(image, found)
    assert by_flann["confirmed"].tolist() == by_brute_force["confirmed"].tolist() == [True]
    np.testing.assert_allclose(by_flann["boxes"], by_brute_force["boxes"], atol=3.0)


def test_keypoints_looked_up_in_parts_on_several_threads_find_the_same_neighbours(checker, scene, monkeypatch):
    """The image's keypoints are looked up in FLANN's trees in parts, on threads of their own, and
    several checks of one image may run at once (a served detector): every way gives the
    neighbours one lookup of them all gives, to the byte."""
    from concurrent.futures import ThreadPoolExecutor

    gray = texture_check.grayscale(scene[0])
    monkeypatch.setattr(texture_check, "SEARCH_THREADS", 1)
    whole = checker._keypoints_and_matches(gray)
    assert len(whole[0]) >= 2 * texture_check.MIN_SEARCH_PART  # enough keypoints to be split
    monkeypatch.setattr(texture_check, "SEARCH_THREADS", 4)
    with ThreadPoolExecutor(3) as pool:
        at_once = list(pool.map(lambda _: checker._keypoints_and_matches(gray), range(6)))
    for parts in at_once:
        for ours, theirs in zip(parts, whole):
            np.testing.assert_array_equal(ours, theirs)


def test_a_texture_with_fewer_keypoints_than_neighbours_looked_at_is_matched_alike(monkeypatch):
    """A texture with fewer keypoints than the ratio test's NEIGHBOURS (a blurred disc, seen
    straight on only; the other class blank): FLANN is asked for no more neighbours than there
    are points, each texture keypoint's nearest is itself, and both matchers match alike."""
    monkeypatch.setattr(texture_check, "TEXTURE_TILTS", ())
    card = np.full((64, 64), 40, np.uint8)
    cv2.circle(card, (32, 32), 9, 220, -1)
    card = cv2.GaussianBlur(card, (0, 0), 2)
    matched = []
    for exact in (True, False):
        check = TextureCheck({"astronaut": card, "coffee": np.full((64, 64), 128, np.uint8)}, CLASSES, exact=exact)
        count = len(check._features.descriptors)
        assert 2 <= count < texture_check.NEIGHBOURS
        indices, distances = check._neighbours(check._features.descriptors)
        assert indices.shape == distances.shape == (count, count)
        np.testing.assert_array_equal(indices[:, 0], np.arange(count))
        np.testing.assert_allclose(distances[:, 0], 0.0, atol=1e-2)
        matched.append(check._matches(card))
    for brute_force, flann in zip(*matched):
        np.testing.assert_array_equal(brute_force, flann)


def _tilted_scene(texture: np.ndarray, tilt: float) -> tuple[np.ndarray, np.ndarray]:
    """``texture`` 200 px wide, foreshortened ``tilt`` times across (a sheet seen at arccos(1/tilt)
    off straight on), centred on a blurred noise ground; its true box."""
    rng = np.random.default_rng(3)
    ground = cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3)).astype(np.uint8), (0, 0), 3)
    affine = np.diag([200 / texture.shape[1] / tilt, 200 / texture.shape[1]])
    centre = np.array([texture.shape[1], texture.shape[0]]) @ affine.T / 2
    affine = np.hstack([affine, (np.array([160, 120]) - centre)[:, None]])
    warped = cv2.warpAffine(texture, affine, (320, 240))
    mask = cv2.warpAffine(np.full(texture.shape[:2], 255, np.uint8), affine, (320, 240)) > 0
    ys, xs = np.nonzero(mask)
    return np.where(mask[:, :, None], warped, ground), np.array([xs.min(), ys.min(), xs.max(), ys.max()], np.float32)


def test_tilted_views_of_the_texture_match_a_sheet_seen_obliquely(checker, textures, monkeypatch):
    """A sheet seen 60° off straight on matches the texture's tilted views several times as often
    as the texture itself, and one seen at 70° is confirmed only with them."""
    monkeypatch.setattr(texture_check, "TEXTURE_TILTS", ())
    straight_on_only = TextureCheck(textures, CLASSES)
    for tilt, counts in ((2.0, []), (3.0, [])):
        image, box = _tilted_scene(textures["astronaut"], tilt)
        for check in (checker, straight_on_only):
            counts.append(int((check._matches(texture_check.grayscale(image))[1] == 0).sum()))
        if tilt == 2.0:
            assert counts[0] >= 3 * counts[1] > 0
        else:
            found = detections((box, 0.5, 0))
            assert checker.apply(image, found)["confirmed"].tolist() == [True]
            assert straight_on_only.apply(image, found)["confirmed"].tolist() == [False]


def _matches_on(box, count: int, texture_side: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random points of a square texture ``texture_side`` px wide, and where a map that
    puts that texture on ``box``'s top left at the box's width takes them: matches that agree."""
    x0, y0, x1, _ = box
    texture_points = np.random.default_rng(seed).uniform(0, texture_side, (count, 2)).astype(np.float32)
    scale = (x1 - x0) / texture_side
    return texture_points, np.stack([x0 + texture_points[:, 0] * scale, y0 + texture_points[:, 1] * scale], axis=1)


def test_a_box_is_renamed_only_where_the_other_textures_matches_agree_on_a_map(checker, scene, monkeypatch):
    """Many matches of another texture scattered over a box (clutter matches the textures richest
    in keypoints most) leave its class as the network gave it; as many agreeing on one map of
    that texture rename it, confirmed."""
    image, box = scene
    texture_points, agreeing = _matches_on(box, count=30, texture_side=400, seed=1)
    scattered = np.random.default_rng(1).permutation(agreeing)  # the same places, each matched to another texture point
    found = detections((box, 0.85, 0))  # called astronaut; every match inside is coffee's
    for points, renamed in ((scattered, False), (agreeing, True)):
        monkeypatch.setattr(
            checker, "_keypoints_and_matches", lambda gray, p=points: (p, p, np.ones(len(p), np.int64), texture_points)
        )
        checked = checker.apply(image, found)
        assert checked["labels"].tolist() == [1 if renamed else 0]
        assert checked["confirmed"].tolist() == [renamed]
        assert (checked["scores"][0] >= CONFIRMED_FLOOR) == renamed


def test_without_evidence_boxes_stay_on_their_side_of_the_cut_below_the_confirmed(checker, scene, monkeypatch):
    """Boxes holding a few matches of their class and no map keep their side of the cut, below
    any box the texture confirmed."""
    image, box = scene
    card, noise = [250, 20, 300, 50], [232, 62, 308, 198]
    with_a_few_matches(monkeypatch, checker, (card, 0), (noise, 1))
    found = detections((card, 0.95, 0), (noise, 0.9, 1), (box, 0.2, 1))
    checked = checker.apply(image, found)  # a flat card, blurred noise, and a box under the floor
    for key in ("boxes", "labels"):
        np.testing.assert_array_equal(checked[key], found[key])
    assert checked["confirmed"].tolist() == [False, False, False]
    # Still over the cut and in their order, but below any confirmed box; under the cut untouched.
    assert PAPER_CUT <= checked["scores"][1] < checked["scores"][0] < CONFIRMED_FLOOR
    assert checked["scores"][2] == pytest.approx(0.2)
    with_sheet = checker.apply(image, detections(([250, 20, 300, 50], 0.99, 0), (box, 0.31, 0)))
    np.testing.assert_array_equal(with_sheet["boxes"][1], [250, 20, 300, 50])  # the sure card now ranks second
    assert with_sheet["confirmed"].tolist() == [True, False]
    assert with_sheet["scores"][0] >= CONFIRMED_FLOOR > with_sheet["scores"][1] >= PAPER_CUT
    blank = np.full((240, 320, 3), 90, np.uint8)  # no keypoint at all
    unchanged = checker.apply(blank, detections((box, 0.7, 0)))
    for key, value in detections((box, 0.7, 0)).items():
        np.testing.assert_array_equal(unchanged[key], value)
    assert unchanged["confirmed"].tolist() == [False]
    empty = checker.apply(image, detections())
    assert (
        empty["boxes"].shape == (0, 4) and len(empty["scores"]) == len(empty["labels"]) == len(empty["confirmed"]) == 0
    )


def test_a_sheet_named_again_without_evidence_drops_under_the_cut_in_its_order(checker, textures, monkeypatch):
    """A few matches of their class and no map, so no evidence: of boxes on one place, whatever
    their classes, the best scored is drawn; the same place named as another class, a piece of it
    and a box around it rank on, under the cut; a box elsewhere is drawn too."""
    blank = np.full((240, 320, 3), 90, np.uint8)
    found = detections(
        ([20, 20, 120, 120], 0.99, 0),  # the sheet
        ([25, 22, 118, 125], 0.97, 1),  # the same sheet, named as the other class
        ([30, 30, 60, 60], 0.96, 0),  # a piece of it
        ([200, 100, 300, 200], 0.95, 1),  # another sheet
        ([10, 10, 160, 150], 0.9, 1),  # a box around the first
    )
    with_a_few_matches(monkeypatch, checker, *zip(found["boxes"], found["labels"]))
    checked = checker.apply(blank, found)
    assert not checked["confirmed"].any()
    drawn = checked["scores"] >= PAPER_CUT
    np.testing.assert_array_equal(checked["boxes"][drawn], found["boxes"][[0, 3]])
    again = checked["scores"][~drawn]
    np.testing.assert_array_equal(checked["boxes"][~drawn], found["boxes"][[1, 2, 4]])
    assert np.all(again >= PAPER_CUT - (CONFIRMED_FLOOR - PAPER_CUT)) and np.all(np.diff(again) < 0)
    every_name = TextureCheck(textures, CLASSES, every_name=True)
    with_a_few_matches(monkeypatch, every_name, *zip(found["boxes"], found["labels"]))
    assert (every_name.apply(blank, found)["scores"] >= PAPER_CUT).all()  # every name over the cut
    even = Calibration(weights=(0.0,) * len(FEATURES), bias=0.0)  # every box: a chance of one half
    calibrated = TextureCheck(textures, CLASSES, calibration=even)
    assert (calibrated.apply(blank, found)["scores"] == np.float32(0.5)).all()  # the calibration's word stands


def test_a_box_whose_keypoints_match_nothing_of_its_texture_drops_under_the_cut(checker, textures):
    """Something printed that is not the sheet (a checkerboard, boxed as the astronaut) holds
    many keypoints and not one of them matches the astronaut; a blank box holds none, where the
    sheet's print would show some: evidence against both, which drop under the cut in their
    order. ``unmatched_drawn`` leaves both drawn."""
    image = np.full((240, 320, 3), 90, np.uint8)
    image[20:100, 20:140] = cv2.resize(skimage.data.checkerboard(), (120, 80))[:, :, None]
    found = detections(([20, 20, 140, 100], 0.95, 0), ([220, 150, 300, 230], 0.9, 0))
    every_keypoint, matched, _, _ = checker.matches(image)
    assert texture_check._inside(every_keypoint, found["boxes"][0]).sum() >= 10
    assert not texture_check._inside(every_keypoint, found["boxes"][1]).any()
    assert not texture_check._inside(matched, found["boxes"][0]).any()
    checked = checker.apply(image, found, with_evidence=True)
    assert not checked["confirmed"].any()
    np.testing.assert_array_equal(checked["boxes"], found["boxes"])  # in their order
    assert np.all((PAPER_CUT - (CONFIRMED_FLOOR - PAPER_CUT) <= checked["scores"]) & (checked["scores"] < PAPER_CUT))
    assert (checked["evidence"][:, FEATURES.index("match_share")] == 0).all()
    drawn = TextureCheck(textures, CLASSES, unmatched_drawn=True).apply(image, found)
    assert (drawn["scores"] >= PAPER_CUT).all()


@pytest.mark.parametrize("keypoints", [texture_check.DETAILED_KEYPOINTS - 1, texture_check.DETAILED_KEYPOINTS])
def test_a_box_in_detailed_print_that_fits_no_map_drops_under_the_cut(checker, textures, monkeypatch, keypoints):
    """A box holding ``DETAILED_KEYPOINTS`` of the image's keypoints, a few of them matching its
    class but agreeing on no map, shows print in such detail that its own sheet would have fitted
    one: it drops under the cut. One keypoint fewer, it keeps its place over the cut (too few
    matches for a map is no evidence against), and so it does with ``unmatched_drawn``."""
    rng = np.random.default_rng(0)
    box = [100, 100, 500, 400]
    every = rng.uniform((100, 100), (500, 400), (keypoints, 2)).astype(np.float32)
    matched = every[:3]  # fewer than MIN_INLIERS: no map
    texture_points = rng.uniform(0, 200, (3, 2)).astype(np.float32)
    for check in (checker, TextureCheck(textures, CLASSES, unmatched_drawn=True)):
        monkeypatch.setattr(
            check, "_keypoints_and_matches", lambda gray: (every, matched, np.zeros(3, np.int64), texture_points)
        )
        checked = check.apply(np.full((480, 640, 3), 90, np.uint8), detections((box, 0.95, 0)))
        assert not checked["confirmed"].any()
        drops = keypoints >= texture_check.DETAILED_KEYPOINTS and not check.unmatched_drawn
        assert (checked["scores"][0] < PAPER_CUT) == drops, (keypoints, check.unmatched_drawn)


def test_grayscale_images_and_textures_work_and_a_missing_texture_is_named(textures, scene):
    image, box = scene
    gray = {name: cv2.cvtColor(t, cv2.COLOR_RGB2GRAY) for name, t in textures.items()}
    checked = TextureCheck(gray, CLASSES).apply(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), detections((box, 0.5, 0)))
    assert checked["scores"][0] >= CONFIRMED_FLOOR
    with pytest.raises(ValueError, match=r"no texture for class\(es\) \['rocket'\]"):
        TextureCheck(textures, CLASSES + ["rocket"])


@pytest.mark.parametrize("flatness", [0.5, 0.25])
def test_a_mirrored_or_squashed_fit_is_no_evidence(checker, scene, monkeypatch, flatness):
    """Matches whose map mirrors the texture (a printed sheet shows its front only), or squashes
    it flatter than a sheet SIFT can match is ever seen (MIN_AXIS_RATIO), leave the box as the
    network gave it, where the same matches unmirrored confirm it, as they do squashed less."""
    image, box = scene
    x0, y0, x1, y1 = box
    texture_points, upright = _matches_on(box, count=40, texture_side=512, seed=0)
    scale = (x1 - x0) / 512
    mirrored = np.stack([x1 - texture_points[:, 0] * scale, upright[:, 1]], axis=1)
    squashed = np.stack([upright[:, 0], y0 + texture_points[:, 1] * scale * flatness], axis=1)
    found = detections((box, 0.5, 0))
    for points, raised in ((upright, True), (mirrored, False), (squashed, flatness >= MIN_AXIS_RATIO)):
        monkeypatch.setattr(
            checker, "_keypoints_and_matches", lambda gray, p=points: (p, p, np.zeros(len(p), np.int64), texture_points)
        )
        assert bool(checker.apply(image, found)["scores"][0] > 0.8) == raised


def _bent_and_chance_matches(box, count: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(texture points of the 512-px astronaut, where a sheet curled about a vertical axis on
    ``box`` shows them, where chance puts them: each 9-12 px off one flat map of the texture,
    inside RANSAC's threshold for ``box`` but no smooth bend's image)."""
    x0, y0, x1, _ = box
    rng = np.random.default_rng(seed)
    texture_points = rng.uniform(0, 512, (count, 2)).astype(np.float32)
    scale = (x1 - x0) / 512
    radius = 120.0  # px: the curl's radius in the image
    bent = np.stack(
        [x0 + radius * np.sin(texture_points[:, 0] * scale / radius), y0 + texture_points[:, 1] * scale], axis=1
    )
    angle = rng.uniform(0, 2 * np.pi, count)
    offsets = rng.uniform(9, 12, count)[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    flat = np.stack([x0 + texture_points[:, 0] * scale, y0 + texture_points[:, 1] * scale], axis=1)
    return texture_points, bent.astype(np.float32), (flat + offsets).astype(np.float32)


def test_inliers_their_neighbours_contradict_are_no_evidence(checker, scene, monkeypatch):
    """A curled sheet's matches move smoothly: each agrees with the map its neighbours in the
    texture agree on, and they confirm the box. As many matches each a few pixels off one flat
    map, inside RANSAC's threshold (another document's words near where the sheet has its own),
    agree on that map but not with their neighbours: the box is left as the network gave it. They
    would confirm it without the neighbours' say."""
    image, box = scene
    texture_points, bent, chance = _bent_and_chance_matches(box, count=60, seed=2)
    found = detections((box, 0.5, 0))
    for points, confirmed in ((bent, True), (chance, False)):
        monkeypatch.setattr(
            checker, "_keypoints_and_matches", lambda gray, p=points: (p, p, np.zeros(len(p), np.int64), texture_points)
        )
        checked = checker.apply(image, found)
        assert checked["confirmed"].tolist() == [confirmed]
        assert bool(checked["scores"][0] > PAPER_CUT) == confirmed
    monkeypatch.setattr(texture_check, "LOCAL_TOLERANCE", 1.0)  # every inlier within its neighbours' reach
    assert checker.apply(image, found)["confirmed"].tolist() == [True]


def test_an_inlier_is_judged_only_where_its_neighbours_fix_a_map_around_it():
    """One line of print: a match on the line but moved along it is off its neighbours' map; a
    match beside the line, whose neighbours all lie on it, is not judged (they fix no map across
    the line), nor is a match with too few neighbours, and matches that all share one texture
    point or are too few for any neighbours raise nothing."""
    from workers.train.texture_check import _off_their_neighbours

    diagonal = float(np.hypot(800, 800))
    line = np.stack([np.linspace(0, 800, 61), np.full(61, 400.0)], axis=1)
    sources = np.concatenate([line, [[400.0, 420.0]]])  # the last one 20 px beside the line
    targets = sources * 0.5 + 10
    targets[30, 0] += 12  # on the line, 12 px along it: off by more than 2% of the 566-px sheet
    targets[-1, 1] += 40  # beside it, far off any map: still not judged
    off = _off_their_neighbours(sources, targets, diagonal, 0.5)
    assert off.tolist() == [index == 30 for index in range(len(sources))]
    same_point = np.full((10, 2), 300.0)
    assert not _off_their_neighbours(same_point, same_point + np.arange(10)[:, None] * 50, diagonal, 0.5).any()
    assert _off_their_neighbours(sources[:4], targets[:4] + 99, diagonal, 0.5).tolist() == [False] * 4


def test_the_search_finds_no_sheet_in_matches_their_neighbours_contradict(searcher, scene, monkeypatch):
    """The search stands a sheet on the inliers their neighbours vouch for, too: the curled
    sheet's matches are found as a sheet, chance matches near one map are not."""
    image, box = scene
    texture_points, bent, chance = _bent_and_chance_matches(box, count=60, seed=3)
    for points, sheets in ((bent, 1), (chance, 0)):
        matches = (points, np.zeros(len(points), np.int64), texture_points)
        monkeypatch.setattr(searcher, "_keypoints_and_matches", lambda gray, m=matches: (m[0], *m))
        assert len(searcher.apply(image, detections())["scores"]) == sheets


@pytest.fixture(scope="module")
def searcher(textures):
    return TextureCheck(textures, CLASSES, search=True)


def _paste(image: np.ndarray, texture: np.ndarray, width: float, angle: float, at: tuple[float, float]) -> np.ndarray:
    """``texture`` turned by ``angle``° and scaled to ``width`` px, pasted into ``image`` at ``at``
    (in place); its true box."""
    affine = cv2.getRotationMatrix2D((0, 0), angle, width / texture.shape[1])
    affine[:, 2] += at
    size = (image.shape[1], image.shape[0])
    mask = cv2.warpAffine(np.full(texture.shape[:2], 255, np.uint8), affine, size) > 0
    image[mask] = cv2.warpAffine(texture, affine, size)[mask]
    ys, xs = np.nonzero(mask)
    return np.array([xs.min(), ys.min(), xs.max(), ys.max()], np.float32)


def test_the_search_finds_a_sheet_the_network_gave_no_box_for(checker, searcher, scene):
    image, box = scene
    assert len(checker.apply(image, detections())["scores"]) == 0  # the check alone looks only at boxes
    found = searcher.apply(
        image, detections(([250, 20, 300, 50], 0.2, 1)), with_evidence=True
    )  # a weak box elsewhere stays
    assert found["labels"].tolist() == [0, 1] and found["confirmed"].tolist() == [True, False]
    assert found["scores"][0] == pytest.approx(confirmed_score(found["evidence"][0, COVERAGE]))  # by its evidence
    assert float(found["scores"][0]) >= CONFIRMED_FLOOR  # in float32 too
    assert _iou(found["boxes"][0], box) > 0.8
    assert found["scores"][1] == pytest.approx(0.2)


def test_the_search_adds_nothing_to_a_sheet_the_network_found(checker, searcher, scene):
    """A found sheet the network boxed is the check's confirmed box, once; a box of the network's
    on it too weak to be checked (under the check's floor) merges into the sheet found."""
    image, box = scene
    for found in (detections((box, 0.6, 0)), detections((box, 0.6, 0), ([250, 20, 300, 50], 0.95, 1))):
        searched, checked = searcher.apply(image, found), checker.apply(image, found)
        for key in ("boxes", "scores", "labels"):
            np.testing.assert_allclose(searched[key], checked[key], atol=1e-5)
    weak = detections((box, 0.2, 0))
    assert checker.apply(image, weak)["scores"].tolist() == pytest.approx([0.2])
    lent = searcher.apply(image, weak, with_evidence=True)
    assert lent["labels"].tolist() == [0]
    assert lent["scores"][0] == pytest.approx(confirmed_score(lent["evidence"][0, COVERAGE]))
    assert lent["confirmed"].tolist() == [True]
    assert _iou(lent["boxes"][0], box) > 0.8


def test_the_search_finds_each_sheet_of_several_and_no_sheet_where_there_is_none(searcher, textures):
    rng = np.random.default_rng(5)
    image = cv2.GaussianBlur(rng.integers(0, 255, (300, 560, 3)).astype(np.uint8), (0, 0), 3)
    truth = [
        (_paste(image, textures["astronaut"], 150, 8, (20, 40)), 0),
        (_paste(image, textures["astronaut"], 130, -15, (200, 120)), 0),
        (_paste(image, textures["coffee"], 170, 0, (370, 60)), 1),
    ]
    found = searcher.apply(image, detections(), with_evidence=True)
    assert sorted(found["labels"].tolist()) == [0, 0, 1]
    for box, label in truth:
        ious = [_iou(b, box) for b, lab in zip(found["boxes"], found["labels"]) if lab == label]
        assert max(ious) > 0.7
    assert (
        found["scores"] == pytest.approx(confirmed_score(found["evidence"][:, COVERAGE])) and found["confirmed"].all()
    )
    noise = cv2.GaussianBlur(np.random.default_rng(6).integers(0, 255, (300, 560, 3)).astype(np.uint8), (0, 0), 3)
    for empty in (noise, np.full((240, 320, 3), 90, np.uint8)):
        nothing = searcher.apply(empty, detections())
        assert nothing["boxes"].shape == (0, 4) and len(nothing["scores"]) == 0


def test_the_search_refuses_a_mirrored_or_squashed_fit(searcher, scene, monkeypatch):
    """Matches that map the texture mirrored, or squashed flatter than a seen sheet can be, find
    nothing; the same matches unmirrored and unsquashed find the sheet."""
    image, _ = scene
    rng = np.random.default_rng(1)
    texture_points = rng.uniform(0, 512, (40, 2)).astype(np.float32)
    upright = 40 + texture_points * 0.3
    mirrored = np.stack([240 - texture_points[:, 0] * 0.3, upright[:, 1]], axis=1)
    squashed = np.stack([upright[:, 0], 40 + texture_points[:, 1] * 0.03], axis=1)
    few = SEARCH_MIN_INLIERS - 1  # fewer matches than the search needs, however well they agree
    for points, sources, sheets in (
        (upright, texture_points, 1),
        (mirrored, texture_points, 0),
        (squashed, texture_points, 0),
        (upright[:few], texture_points[:few], 0),
        (upright[: few + 1], texture_points[: few + 1], 1),
    ):
        matches = (points, np.zeros(len(points), np.int64), sources)
        monkeypatch.setattr(searcher, "_keypoints_and_matches", lambda gray, m=matches: (m[0], *m))
        assert len(searcher.apply(image, detections())["scores"]) == sheets


def test_a_large_photograph_is_shrunk_for_sift_and_checked_in_its_own_pixels(checker, scene):
    """SIFT runs on small images enlarged, on a photograph past SIFT_MAX_SIDE shrunk to it; the
    outline it confirms is in the photograph's own pixels either way."""
    assert sift_scale(240, 320) == 2 and sift_scale(768, 1024) == 2
    assert sift_scale(3024, 4032) == pytest.approx(SIFT_MAX_SIDE / 4032)
    image, box = scene
    factor = 10  # 3200 x 2400: past the cap even before enlarging
    large = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_LINEAR)
    checked = checker.apply(large, detections((box * factor, 0.5, 0)))
    assert checked["scores"][0] >= CONFIRMED_FLOOR
    assert _iou(checked["boxes"][0], box * factor) > 0.8


def test_sharpening_keeps_flat_regions_and_steepens_edges(textures):
    """The unsharp mask (off as built: amount 0 is the image as it is) leaves a flat image as it is
    and raises an edge's contrast on both sides, saturating at 0 and 255 instead of wrapping
    round; a negative amount is refused by name."""
    step = np.zeros((40, 40), np.uint8)
    step[:, 20:] = 200
    assert texture_check.SHARPEN_AMOUNT == 0 and texture_check.sharpen(step, 0.0) is step
    flat = np.full((40, 40), 90, np.uint8)
    np.testing.assert_array_equal(texture_check.sharpen(flat, 1.0), flat)
    sharpened = texture_check.sharpen(step, 1.0)
    assert sharpened.dtype == np.uint8 and sharpened.shape == step.shape
    assert sharpened[:, 19].max() == 0 and sharpened[:, 20].min() > 200  # darker below, brighter above the edge
    np.testing.assert_array_equal(sharpened[:, :10], step[:, :10])  # far from it, unchanged
    bright = np.full((40, 40), 250, np.uint8)
    bright[:, 20:] = 255
    assert texture_check.sharpen(bright, 1.0)[:, 20].min() == 255
    with pytest.raises(ValueError, match="sharpen must be at least 0"):
        TextureCheck(textures, CLASSES, sharpen=-0.5)


def _soft_sheet(textures, width: int, blur: float, quality: int) -> np.ndarray:
    """The astronaut texture at ``width`` px over a noise ground, softened by a Gaussian blur and
    JPEG as a lens and a camera's compression soften a photographed sheet."""
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3)).astype(np.uint8), (0, 0), 3)
    _paste(image, textures["astronaut"], width, 12, (40, 60))
    _, encoded = cv2.imencode(".jpg", cv2.GaussianBlur(image, (0, 0), blur), [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize("width,blur", [(150, 1.0), (100, 1.5), (70, 1.0)])
def test_a_soft_sheet_matches_its_texture_more_often_with_the_image_sharpened(
    checker, textures, monkeypatch, width, blur
):
    """Sharpening the image before SIFT (amount 1, the one measured in bench/README.md) brings back
    the fine detail a soft sheet lost: its own texture's matches rise by half or more, and the
    other texture's stay a few."""
    image = _soft_sheet(textures, width, blur, quality=60)

    def matches(amount: float) -> np.ndarray:
        monkeypatch.setattr(checker, "sharpen", amount)
        return np.bincount(checker._matches(texture_check.grayscale(image))[1], minlength=2)

    plain, sharpened = matches(0.0), matches(1.0)
    assert sharpened[0] >= 1.5 * plain[0] and plain[0] > 0
    assert sharpened[1] <= max(4, 0.1 * sharpened[0])


def _checked(check: TextureCheck, image: np.ndarray, box: np.ndarray) -> dict:
    return check.apply(image, detections((box + np.array([6, -5, 4, 3], np.float32), 0.5, 0), (box * 0.5, 0.85, 1)))


def _assert_same_outputs(first: dict, second: dict) -> None:
    assert sorted(first) == sorted(second)
    for name in first:
        np.testing.assert_array_equal(first[name], second[name])


def test_a_cached_check_is_read_back_instead_of_made_and_checks_alike(textures, scene, tmp_path, monkeypatch):
    """With a cache folder the textures' keypoints and KD-trees are made once: a second check of
    the same textures makes neither (SIFT over the textures and the trees' seeded build would
    fail here), and checks an image to the byte as the first and as one without a cache do."""
    image, box = scene
    made = TextureCheck(textures, CLASSES, search=True, cache_dir=tmp_path)
    stored = sorted(path.suffix for path in tmp_path.iterdir())
    assert stored == [".flann", ".npz"]

    def not_again(*_args, **_kwargs):
        raise AssertionError("made again, not read from the cache")

    with monkeypatch.context() as patched:
        patched.setattr(texture_check, "texture_features", not_again)
        patched.setattr(cv2, "setRNGSeed", not_again)  # called only to build the trees
        cached = TextureCheck(textures, CLASSES, search=True, cache_dir=tmp_path)
    for name in ("descriptors", "labels", "points"):
        np.testing.assert_array_equal(getattr(cached._features, name), getattr(made._features, name))
    assert cached._features.sizes == made._features.sizes
    uncached = TextureCheck(textures, CLASSES, search=True)
    reference = _checked(uncached, image, box)
    assert reference["confirmed"].any()
    _assert_same_outputs(_checked(cached, image, box), reference)
    _assert_same_outputs(_checked(made, image, box), reference)


def test_a_torn_or_mismatched_cache_is_made_again(textures, scene, tmp_path, caplog):
    """A keypoint file that is not one (a torn write, another program's) is made again with a
    warning, and so are trees that are not the ones the keypoints were stored with: the check
    still checks as one without a cache, and the files it writes back are read the next time."""
    image, box = scene
    TextureCheck(textures, CLASSES, cache_dir=tmp_path)
    (features,) = tmp_path.glob("*.npz")
    (trees,) = tmp_path.glob("*.flann")
    reference = _checked(TextureCheck(textures, CLASSES), image, box)

    features.write_bytes(b"PK\x03\x04 not a zip")
    with caplog.at_level("WARNING", logger=texture_cache.__name__):
        remade = TextureCheck(textures, CLASSES, cache_dir=tmp_path)
    assert "unreadable" in caplog.text and str(features) in caplog.text
    _assert_same_outputs(_checked(remade, image, box), reference)
    assert texture_cache.CheckCache(tmp_path, features.stem).load() is not None

    trees.write_bytes(trees.read_bytes()[: trees.stat().st_size // 2])  # torn: its digest no longer matches
    stored = texture_cache.CheckCache(tmp_path, features.stem).load()
    assert (
        texture_cache.CheckCache(tmp_path, features.stem).load_index(stored.features.descriptors, stored.index_digest)
        is None
    )
    rebuilt = TextureCheck(textures, CLASSES, cache_dir=tmp_path)
    _assert_same_outputs(_checked(rebuilt, image, box), reference)
    stored = texture_cache.CheckCache(tmp_path, features.stem).load()
    assert (
        texture_cache.CheckCache(tmp_path, features.stem).load_index(stored.features.descriptors, stored.index_digest)
        is not None
    )


def test_other_textures_order_or_settings_are_filed_apart(textures, monkeypatch):
    """The cache key covers what makes the keypoints and trees: one changed pixel, the classes in
    another order, or another SIFT threshold or tree count is another entry."""
    grays = [texture_check.grayscale(textures[name]) for name in CLASSES]
    key = texture_check.cache_key(grays)
    assert texture_check.cache_key([gray.copy() for gray in grays]) == key
    touched = grays[1].copy()
    touched[0, 0] ^= 1
    assert texture_check.cache_key([grays[0], touched]) != key
    assert texture_check.cache_key(grays[::-1]) != key
    monkeypatch.setattr(texture_check, "CONTRAST_THRESHOLD", 0.03)
    assert texture_check.cache_key(grays) != key
    monkeypatch.undo()
    monkeypatch.setattr(texture_check, "FLANN_TREES", 4)
    assert texture_check.cache_key(grays) != key


def test_a_cache_folder_that_cannot_be_made_only_costs_time(textures, scene, tmp_path, caplog):
    """A cache folder that cannot be made (a file stands there) is warned about, and the check
    works as without one."""
    image, box = scene
    blocked = tmp_path / "cache"
    blocked.write_text("a file, not a folder")
    with caplog.at_level("WARNING", logger=texture_cache.__name__):
        check = TextureCheck(textures, CLASSES, cache_dir=blocked)
    assert "cannot keep keypoints" in caplog.text
    _assert_same_outputs(_checked(check, image, box), _checked(TextureCheck(textures, CLASSES), image, box))


def test_the_cache_keeps_the_checks_used_last(tmp_path, monkeypatch):
    """Past CACHE_KEEP checks the ones read or written longest ago are removed, keypoints and trees
    together; reading a check makes it the newest."""
    import os

    monkeypatch.setattr(texture_cache, "CACHE_KEEP", 2)
    monkeypatch.setattr(texture_check, "TEXTURE_TILTS", ())  # small checks: the rule, not SIFT, is under test
    rng = np.random.default_rng(0)
    cards = [cv2.GaussianBlur(rng.integers(0, 255, (96, 96)).astype(np.uint8), (0, 0), 1.5) for _ in range(3)]

    def keep(card):
        TextureCheck({"astronaut": card, "coffee": 255 - card}, CLASSES, cache_dir=tmp_path)
        return texture_check.cache_key([card, 255 - card])

    def stored():
        return {path.stem for path in tmp_path.glob("*.npz")}, {path.stem for path in tmp_path.glob("*.flann")}

    first, second = keep(cards[0]), keep(cards[1])
    os.utime(tmp_path / f"{first}.npz", ns=(1, 1))  # written long ago
    os.utime(tmp_path / f"{second}.npz", ns=(2, 2))
    keep(cards[0])  # read back: now the newest
    third = keep(cards[2])
    assert stored() == ({first, third}, {first, third})


def test_of_two_confirmed_sheets_scored_alike_the_one_whose_texture_shows_more_ranks_first(checker, textures):
    """A sheet confirmed on part of its texture (as a lookalike of the same template is, on its
    letterhead) ranks below a whole one the network scored the same: coverage orders them."""
    rng = np.random.default_rng(7)
    image = cv2.GaussianBlur(rng.integers(0, 255, (300, 560, 3)).astype(np.uint8), (0, 0), 3)
    whole = _paste(image, textures["astronaut"], 200, 0, (20, 40))
    part = _paste(image, textures["astronaut"], 200, 0, (320, 40))
    image[40:260, 320 + 90 : 540] = 128  # all but the left part of the second sheet hidden
    checked = checker.apply(image, detections((part, 0.5, 0), (whole, 0.5, 0)), with_evidence=True)
    assert checked["confirmed"].all() and len(checked["scores"]) == 2
    first, second = checked["boxes"]
    assert _iou(first, whole) > 0.8 and _iou(second, part) > 0.5
    assert checked["evidence"][0, COVERAGE] > checked["evidence"][1, COVERAGE]
    assert checked["scores"][0] > checked["scores"][1] >= CONFIRMED_FLOOR


def test_of_confirmed_boxes_scored_alike_the_one_covering_more_of_its_texture_keeps_its_sheet():
    """Sheets the search found where the network had no box all score the search's floor. A loose
    fit spread over the whole frame (little of its texture covered) must not swallow the sheets
    inside it as its pieces; a piece covering less than its sheet is still dropped for it."""
    from workers.train.texture_check import _one_per_sheet

    frame = [0, 0, 1024, 768]
    sheets = [[350, 200, 670, 600], [680, 200, 980, 570]]
    boxes = np.array([frame, *sheets], np.float32)
    scores = np.full(3, CONFIRMED_FLOOR + (1 - CONFIRMED_FLOOR) * MIN_SCORE, np.float32)
    confirmed = np.ones(3, bool)
    assert _one_per_sheet(boxes, scores, confirmed, np.array([0.09, 0.55, 0.5])).tolist() == [0, 1, 2]
    piece = np.array([sheets[0], [360, 210, 600, 400]], np.float32)
    assert _one_per_sheet(piece, scores[:2], confirmed[:2], np.array([0.5, 0.2])).tolist() == [0]
