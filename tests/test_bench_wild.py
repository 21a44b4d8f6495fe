"""bench/wild.py: its out-of-domain set is independent, deterministic and correctly boxed, and the
benchmark runs end to end (train, render both sets, score) and reports what the issue's goal is
read from (both mAPs and their ratio)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

pytest.importorskip("bpy", reason="the out-of-domain set is rendered by Blender (the render extra)")

from bench import wild, wild_scene, wild_scoring, wild_sets  # noqa: E402

CLASSES = ("astronaut", "coffee")


def test_the_curl_is_isometric():
    """Arc length along the sheet is kept: every mesh edge keeps its flat length."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        vertices, faces, _ = wild_scene.curled_sheet(1.0, 0.7, rng, cells=16)
        for face in faces:
            across = np.linalg.norm(vertices[face[1]] - vertices[face[0]])
            up = np.linalg.norm(vertices[face[3]] - vertices[face[0]])
            # A chord of an arc is at most a little shorter than the arc (fine mesh).
            assert 0.98 * (1.0 / 16) <= across <= 1.0 / 16 + 1e-9
            assert 0.98 * (0.7 / 16) <= up <= 0.7 / 16 + 1e-9


def test_the_ood_set_is_deterministic_and_cached(tmp_path):
    recipe = wild_scene.OodRecipe(n=4, width=64, height=48, samples=1, seed=11, negatives=0.5, classes=CLASSES)
    first = json.loads(
        (wild_sets.make_ood_set(tmp_path / "a", recipe, echo=lambda *_: None) / "annotations.json").read_text()
    )
    second = json.loads(
        (wild_sets.make_ood_set(tmp_path / "b", recipe, echo=lambda *_: None) / "annotations.json").read_text()
    )
    assert first["annotations"] == second["annotations"]
    assert [i["difficulty"] for i in first["images"]] == [i["difficulty"] for i in second["images"]]
    lines = []
    wild_sets.make_ood_set(tmp_path / "a", recipe, echo=lines.append)
    assert lines and "reusing" in lines[0]
    changed = wild_scene.OodRecipe(n=4, width=64, height=48, samples=1, seed=12, negatives=0.5, classes=CLASSES)
    assert changed.key() != recipe.key()
    for annotation in first["annotations"]:
        x, y, w, h = annotation["bbox"]
        assert 0 <= x < x + w <= 64 and 0 <= y < y + h <= 48
    negatives = [image["id"] for image in first["images"] if image["difficulty"] == "negative"]
    assert not [a for a in first["annotations"] if a["image_id"] in negatives]


def test_a_fully_visible_target_is_boxed_at_its_projected_outline():
    """The index render's box equals the bounding box of the projected mesh (within a pixel)."""
    recipe = wild_scene.OodRecipe(n=1, width=160, height=120, samples=1, seed=0, classes=CLASSES)
    scene = wild_scene.OodScene(wild_scene.load_textures(CLASSES), recipe)
    from bpy_extras.object_utils import world_to_camera_view  # importable once bpy is

    checked = 0
    for seed in range(40):
        result = scene.render(seed, negative=False)
        if result is None:
            continue
        _, objects, _ = result
        target = next(o for o in scene.scene.objects if o.pass_index == 1)
        corners = [
            world_to_camera_view(scene.scene, scene.scene.camera, target.matrix_basis @ v.co)
            for v in target.data.vertices
        ]
        xs = np.array([c.x for c in corners]) * recipe.width
        ys = (1 - np.array([c.y for c in corners])) * recipe.height
        inside = xs.min() > 2 and ys.min() > 2 and xs.max() < recipe.width - 2 and ys.max() < recipe.height - 2
        if len(objects) != 1 or objects[0][2] < 0.999 or not inside:
            continue
        box = np.array(objects[0][1])
        assert np.allclose(box, [xs.min(), ys.min(), xs.max(), ys.max()], atol=1.5), (seed, box)
        checked += 1
        if checked == 2:
            break
    assert checked == 2, "no fully visible target in 40 scenes"


def test_the_benchmark_trains_scores_every_set_and_reports_the_ratios(tmp_path):
    import yaml

    # smoke.yaml at one difficulty: each curriculum trains one stage; the in-domain set renders
    # its one (condition, difficulty) pair twice.
    config = yaml.safe_load((ROOT / "configs" / "smoke.yaml").read_text())
    config["curriculum"]["difficulties"] = ["easy"]
    (tmp_path / "smoke-easy.yaml").write_text(yaml.safe_dump(config))
    out = tmp_path / "wild.json"
    command = [
        sys.executable,
        str(ROOT / "bench" / "wild.py"),
        "--config",
        str(tmp_path / "smoke-easy.yaml"),
        "--n-ood",
        "4",
        "--ood-size",
        "64x48",
        "--ood-samples",
        "1",
        "--n-in-domain",
        "2",
        "--ood-dir",
        str(tmp_path / "ood"),
        "--in-domain-dir",
        str(tmp_path / "in"),
        "--n-ood-second",
        "3",
        "--ood-second-size",
        "48x64",
        "--ood-second-seed",
        "11",
        "--ood-second-dir",
        str(tmp_path / "ood-second"),
        "--n-ood-apart",
        "2",
        "--ood-apart-size",
        "64x48",
        "--ood-apart-dir",
        str(tmp_path / "ood-apart"),
        "--n-ood-large",
        "1",
        "--ood-large-size",
        "96x72",
        "--ood-large-dir",
        str(tmp_path / "ood-large"),
        "--n-ood-hard",
        "2",
        "--ood-hard-size",
        "64x48",
        "--ood-hard-dir",
        str(tmp_path / "ood-hard"),
        "--train-dir",
        str(tmp_path / "train"),
        "--members",
        "2",
        "--out",
        str(out),
    ]
    # --sets-only renders the sets and stops: no training, no scores; the full run then reuses them.
    rendered = subprocess.run([*command, "--sets-only"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert rendered.returncode == 0, rendered.stderr[-3000:]
    sets = json.loads(out.read_text())
    assert "model" not in sets and "in_domain" not in sets and not (tmp_path / "train").exists()
    assert sets["in_domain_set"]["dir"] == str(tmp_path / "in") and (tmp_path / "in" / "annotations.json").is_file()
    assert all(
        (tmp_path / name / "annotations.json").is_file()
        for name in ("ood", "ood-second", "ood-apart", "ood-large", "ood-hard")
    )
    finished = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert finished.returncode == 0, finished.stderr[-3000:]
    report = json.loads(out.read_text())
    assert "in-domain set: reusing" in finished.stderr and "out-of-domain set: reusing" in finished.stderr
    assert report["in_domain"]["images"] == 2 and report["out_of_domain"]["images"] == 4
    assert report["in_domain_reframed"]["images"] == 2  # the same images in 4:3 and 3:4 frames
    assert report["in_domain_rotated"]["images"] == 2  # and turned by quarter turns
    for part in ("in_domain", "out_of_domain"):
        assert 0.0 <= report[part]["map"] <= 1.0
    assert Path(report["model"]).is_file()
    assert report["training"]["members"] == 2 and Path(report["model"]).name == "ensemble.pt"  # two curricula, one file
    in_map, ood_map = report["in_domain"]["map"], report["out_of_domain"]["map"]
    assert report["ratio"] == (None if not in_map else ood_map / in_map)
    # The second out-of-domain set is drawn apart (its own seed and frame) and scored beside the first.
    second = report["out_of_domain_second"]
    assert second["images"] == 3 and 0.0 <= second["map"] <= 1.0
    assert report["ood_set_second"]["recipe"]["seed"] == 11 and report["ood_set_second"]["recipe"]["width"] == 48
    assert report["ratio_second"] == (None if not in_map else second["map"] / in_map)
    # The third set covers ground and clutter with photographs no training path reads.
    apart = report["out_of_domain_apart"]
    assert apart["images"] == 2 and 0.0 <= apart["map"] <= 1.0
    assert (
        report["ood_set_apart"]["recipe"]["photos"] == "held_apart" and report["ood_set_apart"]["recipe"]["seed"] == 11
    )
    assert report["ratio_apart"] == (None if not in_map else apart["map"] / in_map)
    # The large-frame set, asked for here, is scored and counts toward the goal like the others.
    large = report["out_of_domain_large"]
    assert (
        large["images"] == 1
        and report["ood_set_large"]["recipe"]["width"] == 96
        and report["ood_set_large"]["recipe"]["seed"] == 13
    )
    assert report["ratio_large"] == (None if not in_map else large["map"] / in_map)
    assert report["goal"]["ratio_at_least"] == 0.8
    ratios = (report["ratio"], report["ratio_second"], report["ratio_apart"], report["ratio_large"])
    assert report["goal"]["met"] == all(r is not None and r >= 0.8 for r in ratios)
    assert report["machine"]["cpu"] and report["machine"]["date"]
    # The hard set is scored with a goal of its own (its mAP), not a ratio toward the goal above.
    hard = report["out_of_domain_hard"]
    assert hard["images"] == 2 and report["ood_set_hard"]["recipe"]["hard"] is True
    # Every set: foldwise beside the keypoint recipe, each with what a user drawing boxes at the
    # threshold sees, and the seconds each took per image.
    for part in ("in_domain", "out_of_domain", "out_of_domain_hard"):
        for scored in (report[part], report[f"baseline_{part}"]):
            drawn = scored["at_threshold"]
            assert drawn["true"] <= min(drawn["drawn"], drawn["targets"])
            assert drawn["precision"] is None or 0.0 <= drawn["precision"] <= 1.0
            assert scored["seconds_per_image"] >= 0.0
    for part in ("in_domain", "out_of_domain"):  # finding the sheet is never harder than naming it too
        assert report[part]["class_agnostic"]["map_unthresholded"] >= report[part]["map_unthresholded"] - 1e-9
    # One line for the results table: every scored set, foldwise beside the recipe.
    assert report["headline"] == wild.headline(report)
    for name in ("in domain: foldwise", "out of domain hard: foldwise", "out of domain large: foldwise"):
        assert name in report["headline"]
    assert report["headline"].count(", keypoints ") == 6


def test_the_in_domain_set_is_shared_by_configs_that_render_alike(tmp_path):
    """The cache key is what the renders read: a config with another detector or training scores
    on the same images (not a re-render into the same folder); another render size re-renders."""
    from foldwise.config import load_config

    config = load_config(ROOT / "configs" / "smoke.yaml")
    out = tmp_path / "in"
    lines: list[str] = []
    wild_sets.make_in_domain_set(config, out, 1, seed=3, echo=lines.append)
    first = (out / "annotations.json").read_text()
    other_detector = config.model_copy(
        update={"detector": config.detector.model_copy(update={"test_sizes": (64, 96), "learning_rate": 0.02})}
    )
    wild_sets.make_in_domain_set(other_detector, out, 1, seed=3, echo=lines.append)
    assert lines[-1] == f"in-domain set: reusing {out}"
    assert (out / "annotations.json").read_text() == first
    larger = config.model_copy(update={"render": config.render.model_copy(update={"image_size": 48})})
    wild_sets.make_in_domain_set(larger, out, 1, seed=3, echo=lines.append)
    assert not lines[-1].startswith("in-domain set: reusing")
    coco = json.loads((out / "annotations.json").read_text())
    assert {(image["width"], image["height"]) for image in coco["images"]} == {(48, 48)}


def test_the_in_domain_set_holds_every_pair_the_loop_scores(tmp_path):
    """quick.yaml trains mixed stages only, yet its loop scores every condition at every
    difficulty besides them (``test_pairs``): so does the in-domain set, not the mixed ones alone."""
    from foldwise.config import load_config

    config = load_config(ROOT / "configs" / "quick.yaml")
    small = config.model_copy(update={"render": config.render.model_copy(update={"image_size": 32})})
    out = wild_sets.make_in_domain_set(small, tmp_path / "in", 1, seed=3, echo=lambda _line: None)
    coco = json.loads((out / "annotations.json").read_text())
    pairs = [(image["condition"], image["difficulty"]) for image in coco["images"]]
    assert sorted(pairs) == sorted(config.test_pairs())
    assert {condition for condition, _ in pairs} > {"mixed"}


def test_a_plain_scene_is_a_flat_sheet_seen_from_above_at_half_the_frame():
    """With every factor off the scene is plain: a flat, unrotated sheet straight below a 40°
    camera filling half the frame's width, and nothing else in view."""
    recipe = wild_scene.OodRecipe(n=1, width=160, height=120, samples=1, seed=0, classes=("coffee",), factors=())
    scene = wild_scene.OodScene(wild_scene.load_textures(recipe.classes), recipe)
    image, objects, info = scene.render(3, negative=False)
    assert (
        info["fill"] == 0.5 and info["fov_deg"] == pytest.approx(40.0) and info["elevation_deg"] == pytest.approx(90.0)
    )
    assert len(objects) == 1
    x0, y0, x1, y1 = objects[0][1]
    assert x1 - x0 == pytest.approx(0.5 * 160, abs=2)  # coffee is wider than tall: its width is the long side
    assert objects[0][2] == 1.0
    # Names as Blender gives them (another scene in this process may hold the plain ones).
    assert sorted(o.name.split(".")[0] for o in scene.scene.objects if o.type == "MESH") == [
        "wild-ground",
        "wild-target-0",
    ]
    with pytest.raises(ValueError, match="unknown factor"):
        wild_scene.OodRecipe(factors=("weather",))


def test_reframing_pads_to_four_by_three_and_moves_the_boxes(tmp_path):
    import cv2

    source = tmp_path / "square"
    (source / "images").mkdir(parents=True)
    for name in ("a", "b"):
        image = np.zeros((48, 48, 3), np.uint8)
        image[10:20, 5:15] = 255
        cv2.imwrite(str(source / f"images/{name}.png"), image)
    document = {
        "images": [
            {"id": i + 1, "file_name": f"images/{n}.png", "width": 48, "height": 48} for i, n in enumerate("ab")
        ],
        "annotations": [{"id": i + 1, "image_id": i + 1, "category_id": 1, "bbox": [5, 10, 10, 10]} for i in range(2)],
        "categories": [{"id": 1, "name": "coffee"}],
    }
    (source / "annotations.json").write_text(json.dumps(document))
    out = wild_sets.make_reframed_set(source, tmp_path / "framed")
    framed = json.loads((out / "annotations.json").read_text())
    assert [(i["width"], i["height"]) for i in framed["images"]] == [(64, 48), (48, 64)]
    for image, annotation in zip(framed["images"], framed["annotations"]):
        pixels = cv2.imread(str(out / image["file_name"]))
        assert pixels.shape[:2] == (image["height"], image["width"])
        x, y, w, h = annotation["bbox"]
        assert pixels[int(y) : int(y + h), int(x) : int(x + w)].min() == 255  # the white square moved with its box


def test_rotating_turns_each_image_by_quarter_turns_and_its_boxes_exactly(tmp_path):
    import cv2

    source = tmp_path / "square"
    (source / "images").mkdir(parents=True)
    names = "abc"
    for name in names:  # a 60 x 40 frame, black, a white block at x 5..15, y 10..30
        pixels = np.zeros((40, 60, 3), np.uint8)
        pixels[10:30, 5:15] = 255
        cv2.imwrite(str(source / f"images/{name}.png"), pixels)
    document = {
        "images": [
            {"id": i + 1, "file_name": f"images/{n}.png", "width": 60, "height": 40} for i, n in enumerate(names)
        ],
        "annotations": [{"id": i + 1, "image_id": i + 1, "category_id": 1, "bbox": [5, 10, 10, 20]} for i in range(3)],
        "categories": [{"id": 1, "name": "coffee"}],
    }
    (source / "annotations.json").write_text(json.dumps(document))
    out = wild_sets.make_rotated_set(source, tmp_path / "rotated")
    turned = json.loads((out / "annotations.json").read_text())
    assert [(i["width"], i["height"]) for i in turned["images"]] == [(40, 60), (60, 40), (40, 60)]
    boxes = [a["bbox"] for a in turned["annotations"]]
    assert boxes[0] == [10, 45, 20, 10]  # a quarter turn counter-clockwise: x <- y, y <- width - x - w
    assert boxes[1] == [45, 10, 10, 20]  # half a turn
    assert boxes[2] == [10, 5, 20, 10]  # three quarters
    for image, (x, y, w, h) in zip(turned["images"], boxes):
        pixels = cv2.imread(str(out / image["file_name"]), cv2.IMREAD_GRAYSCALE)
        assert pixels.shape == (image["height"], image["width"])
        assert pixels[y : y + h, x : x + w].min() == 255 and pixels.sum() == 255 * w * h  # the block is the box


def test_the_class_agnostic_score_counts_a_found_sheet_whatever_class_it_is_given():
    from workers.train.evaluation import evaluate_predictions

    target = np.array([[10, 10, 50, 40]], np.float32)
    # The sheet is class 0; the detector puts class 1 on it (0.9), and class 0 beside it, shifted (0.6).
    predictions = [
        {
            "boxes": np.array([[11, 10, 50, 41], [12, 11, 51, 40]], np.float32),
            "scores": np.array([0.9, 0.6], np.float32),
            "labels": np.array([1, 0]),
        }
    ]
    truth = [{"boxes": target, "labels": np.array([0])}]
    aware = evaluate_predictions(predictions, truth, ["a", "b"], coco=False)
    merged, merged_truth = wild_scoring.class_agnostic(predictions, truth)
    assert len(merged[0]["boxes"]) == 1 and merged[0]["scores"][0] == np.float32(0.9)  # one box per place
    agnostic = evaluate_predictions(merged, merged_truth, ["object"], coco=False)
    assert agnostic.map == 1.0  # found, at the paper's cut
    assert aware.map == 0.0 and aware.map_unthresholded == 1.0  # its right class only at 0.6, under the cut


def test_what_a_user_sees_at_the_cut_is_split_by_the_textures_confirmation():
    """Drawn boxes at the cut, and of them the ones the texture confirmed: a true confirmed box,
    a false unconfirmed one over the cut, and one under it that is not drawn."""
    predictions = [
        {
            "boxes": np.array([[10, 10, 50, 40], [60, 60, 90, 90], [0, 0, 5, 5]], np.float32),
            "scores": np.array([0.95, 0.85, 0.5], np.float32),
            "labels": np.array([0, 0, 0]),
            "confirmed": np.array([True, False, False]),
        }
    ]
    truth = [{"boxes": np.array([[10, 10, 50, 40], [0, 0, 5, 5]], np.float32), "labels": np.array([0, 0])}]
    seen = wild_scoring._at_threshold(predictions, truth, ["a"], 0.8, 0.5)
    assert (seen["drawn"], seen["true"], seen["targets"]) == (2, 1, 2)
    assert seen["confirmed"] == {"drawn": 1, "true": 1}
    unchecked = [{key: value for key, value in predictions[0].items() if key != "confirmed"}]
    assert "confirmed" not in wild_scoring._at_threshold(unchecked, truth, ["a"], 0.8, 0.5)


def test_test_sizes_are_read_as_the_config_reads_them_and_bad_ones_refused(capsys):
    assert wild._test_sizes_argument("128,256") == (128, 256)
    for bad, problem in (
        ("16", "greater than or equal to 32"),
        ("128,128", "sizes repeat"),
        ("big", "not whole numbers"),
    ):
        with pytest.raises(SystemExit):
            wild.main(["--test-sizes", bad])
        error = capsys.readouterr().err
        assert f"argument --test-sizes: {bad!r}" in error and problem in error


def test_test_turns_are_read_as_the_config_reads_them_and_bad_ones_refused(capsys):
    assert wild._test_turns_argument("0,1,2,3") == (0, 1, 2, 3)
    for bad, problem in (("5", "0, 1, 2 or 3"), ("1,1", "turns repeat"), ("left", "not whole numbers")):
        with pytest.raises(SystemExit):
            wild.main(["--test-turns", bad])
        error = capsys.readouterr().err
        assert f"argument --test-turns: {bad!r}" in error and problem in error


def test_frame_sizes_of_every_out_of_domain_set_are_read_alike_and_bad_ones_refused(capsys):
    assert wild._frame_argument("480X360") == (480, 360)
    for option in ("--ood-size", "--ood-second-size", "--ood-apart-size", "--ood-large-size"):
        for bad, problem in (
            ("480", "is not WIDTHxHEIGHT"),
            ("4x3x2", "is not WIDTHxHEIGHT"),
            ("0x240", "at least 1 pixel"),
        ):
            with pytest.raises(SystemExit):
                wild.main([option, bad])
            error = capsys.readouterr().err
            assert f"argument {option}: {bad!r}" in error and problem in error


def test_the_held_apart_photographs_are_none_of_foldwises_training_images():
    """The third set's ground and clutter share no photograph with the default catalog's
    backgrounds and occluders (by name or by pixels), and the first two sets' do: that is
    what the third one measures."""
    from workers.render.assets import load_assets

    catalog = load_assets()
    training = {asset.name for asset in catalog.backgrounds + catalog.occluders}
    ground, clutter = wild_scene.PHOTO_POOLS["held_apart"]
    assert not (set(ground) | set(clutter)) & training
    assert set(wild_scene.GROUND_PHOTOS) | set(wild_scene.CLUTTER_PHOTOS) <= training
    held_apart = wild_scene.load_textures((), "held_apart")
    training_pixels = {
        asset.name: catalog.occluder(asset.name)[0] if asset in catalog.occluders else asset.load()
        for asset in catalog.backgrounds + catalog.occluders
        if not asset.procedural
    }
    for name, pixels in held_apart.items():
        for other, other_pixels in training_pixels.items():
            assert pixels.shape != other_pixels.shape or not np.array_equal(pixels, other_pixels), (name, other)
    assert (
        wild_scene.OodRecipe(classes=CLASSES, photos="held_apart").key() != wild_scene.OodRecipe(classes=CLASSES).key()
    )
    with pytest.raises(ValueError, match="unknown photo pool"):
        wild_scene.OodRecipe(classes=CLASSES, photos="mine")


def test_the_committed_panoramas_are_what_derive_makes_from_bpys(tmp_path):
    # A process of its own: OpenCV reads OpenEXR only when enabled before its first EXR read.
    script = f"from pathlib import Path; from bench.panoramas import derive; derive(Path({str(tmp_path)!r}))"
    subprocess.run([sys.executable, "-c", script], check=True, cwd=ROOT, timeout=120)
    from bench import panoramas

    assert panoramas.NAMES == wild_scene.HELD_APART_PANORAMAS
    import cv2

    for name in panoramas.NAMES:
        # Pixels, not bytes: the tone mapping's float sums round apart on other CPUs (a few
        # hundredths of a percent of the values, by 3 at most).
        derived = cv2.imread(str(tmp_path / f"{name}.jpg")).astype(np.int16)
        committed = cv2.imread(str(panoramas.path(name))).astype(np.int16)
        assert derived.shape == committed.shape, name
        difference = np.abs(derived - committed)
        assert difference.max() <= 4 and (difference > 0).mean() < 0.01, (
            name,
            difference.max(),
            (difference > 0).mean(),
        )
    with pytest.raises(KeyError, match="unknown panorama 'beach'"):
        panoramas.path("beach")


def test_an_empty_first_set_is_refused_before_it_can_replace_a_cached_one(tmp_path, capsys):
    cached = tmp_path / "ood"
    cached.mkdir()
    (cached / "annotations.json").write_text('{"info": {"recipe": "kept"}}')
    for bad, problem in (
        ("0", "needs at least 1 image"),
        ("-3", "needs at least 1 image"),
        ("many", "not a whole number"),
    ):
        with pytest.raises(SystemExit):
            wild.main(["--n-ood", bad, "--ood-dir", str(cached)])
        error = capsys.readouterr().err
        assert "argument --n-ood: " in error and problem in error
    assert json.loads((cached / "annotations.json").read_text())["info"]["recipe"] == "kept"


def _coco_folder(samples, classes, folder: Path) -> Path:
    """The samples (images already under ``folder / 'images'``) as a COCO folder wild_scoring.score reads."""
    document = {
        "images": [
            {"id": i + 1, "file_name": f"images/{s.image_path.name}", "width": 64, "height": 64}
            for i, s in enumerate(samples)
        ],
        "annotations": [
            {"id": i + 1, "image_id": i + 1, "category_id": int(label) + 1, "bbox": [x0, y0, x1 - x0, y1 - y0]}
            for i, s in enumerate(samples)
            for (x0, y0, x1, y1), label in zip(s.boxes.tolist(), s.labels.tolist())
        ],
        "categories": [{"id": i + 1, "name": name} for i, name in enumerate(classes)],
    }
    (folder / "annotations.json").write_text(json.dumps(document))
    return folder


def test_several_checkpoints_score_as_one_ensemble(tmp_path):
    """--model given twice scores the detectors as one: each detects, the detections merge by
    per-class NMS. A model with itself is the model; models whose class lists differ are refused."""
    from tests.workers.train.training_helpers import CLASSES as COLOURS
    from tests.workers.train.training_helpers import config, synthetic_samples
    from workers.train.training import train_detector

    samples = synthetic_samples(tmp_path / "set" / "images", n=6)
    data = _coco_folder(samples, COLOURS, tmp_path / "set")
    first, second, other = tmp_path / "a.pt", tmp_path / "b.pt", tmp_path / "other.pt"
    train_detector(samples, None, 2, config(), COLOURS, first, seed=0)
    train_detector(samples, None, 2, config(), COLOURS, second, seed=1)
    alone = wild_scoring.score(first, data, 0.0, 0.5)
    with_itself = wild_scoring.score([first, first], data, 0.0, 0.5)
    assert with_itself["map"] == alone["map"] and with_itself["map_unthresholded"] == alone["map_unthresholded"]
    pair = wild_scoring.score([first, second], data, 0.0, 0.5)
    assert pair["images"] == 6 and 0.0 <= pair["map"] <= 1.0
    # The same classes in another order: its label 0 is another class, so merging would mix them.
    train_detector(samples, None, 1, config(), COLOURS[::-1], other, seed=0)
    with pytest.raises(ValueError, match="an ensemble needs one class list"):
        wild_scoring.score([first, other], data, 0.0, 0.5)


@pytest.mark.parametrize(
    "config, members",
    [(None, 2), ("configs/quick.yaml", 2), ("configs/smoke.yaml", 1), ("configs/learnability_quick.yaml", 1)],
)
def test_make_run_and_the_benchmark_train_the_same_curricula(config, members):
    """`make run` hands over two curricula of quick.yaml as one ensemble, one of any other config
    (learnability runs hand over no model to join); bench/wild.py trains what make run trains."""
    import shutil

    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    overrides = [f"CONFIG={config}"] if config else []
    # -n prints the recipe without running it; the stamp is made new so that no install is shown.
    dry = subprocess.run(
        ["make", "-n", "-W", ".venv/.installed", "run", *overrides],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert dry.returncode == 0, dry.stderr
    run_line = [line for line in dry.stdout.splitlines() if " run " in line and "foldwise" in line]
    assert run_line and run_line[-1].endswith(f"run {config or 'configs/quick.yaml'} --members {members}"), dry.stdout
    assert wild.make_run_members(ROOT / (config or "configs/quick.yaml")) == members


@pytest.mark.parametrize("bend", ["creased", "rolled"])
def test_the_hard_sets_creases_and_tubes_keep_every_length_of_the_sheet(bend):
    """A crease turns part of the sheet about a line, a tube wraps it around a cylinder: both are
    isometric, as a sheet of paper bends (every mesh edge as long as on the flat sheet)."""
    import numpy as np

    make = wild_scene.creased_sheet if bend == "creased" else wild_scene.rolled_sheet
    for seed in range(5):
        vertices, faces, uvs = make(0.7, 1.0, np.random.default_rng(seed))
        flat = np.column_stack([uvs[:, 0] * 0.7, uvs[:, 1] * 1.0])
        for face in faces[::7]:
            for a, b in zip(face, (*face[1:], face[0])):
                if bend == "creased" and (vertices[a, 2] > 0) != (vertices[b, 2] > 0):
                    continue  # an edge across the crease line is a chord of the fold, not the sheet's
                bent_length = np.linalg.norm(vertices[a] - vertices[b])
                flat_length = np.linalg.norm(flat[a] - flat[b])
                # A chord of the tube's arc is a hair shorter than the arc: within 0.5% per edge.
                assert bent_length == pytest.approx(flat_length, rel=5e-3)
        assert np.ptp(vertices[:, 2]) > 0.05  # and the sheet is bent out of its plane
