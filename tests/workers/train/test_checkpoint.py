"""Checkpoints describe themselves, load for inference alone and are written atomically."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from foldwise.config import DetectorConfig
from workers.train import checkpoint as checkpoint_module
from workers.train.checkpoint import (
    CHECKPOINT_VERSION,
    CheckpointError,
    detect_object,
    load_detector,
    read_checkpoint,
    save_checkpoint,
    torch_threads,
)
from workers.train.data import DatasetError, Sample
from workers.train.training import train_detector

torch.set_num_threads(1)

CLASSES = ["astronaut", "coffee"]


def config(**changes) -> DetectorConfig:
    small = {
        "input_size": 64,
        "batch_size": 2,
        "num_threads": 1,
        "device": "cpu",
        "rpn_proposals_train": 40,
        "fpn_channels": 32,
        "representation_size": 64,
        "rpn_proposals_test": 20,
        "roi_samples_per_image": 32,
        "edge_boxes": 30,
        "box_score_threshold": 0.0,
        "detections_per_image": 10,
    }
    return DetectorConfig(**{**small, **changes})


def write_images(folder, n=3, size=(64, 64), seed=0):
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    paths, arrays = [], []
    for index in range(n):
        image = rng.integers(40, 120, (*size, 3)).astype(np.uint8)
        image[10:40, 12:50] = (200, 60 + 40 * index, 30)
        path = folder / f"{index}.png"
        cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        paths.append(path)
        arrays.append(image)
    return paths, arrays


@pytest.fixture(scope="module", params=["faster_rcnn", "fast_rcnn"])
def trained(request, tmp_path_factory):
    """A detector trained for two steps, its checkpoint path and some test images."""
    folder = tmp_path_factory.mktemp(request.param)
    paths, arrays = write_images(folder / "images")
    samples = [Sample(path, [[12, 10, 50, 40]], [index % 2]) for index, path in enumerate(paths)]
    path = folder / "omega.pt"
    train_detector(samples, None, 2, config(family=request.param), CLASSES, path, seed=0)
    return request.param, path, paths, arrays


def test_checkpoint_describes_itself(trained):
    family, path, _, _ = trained
    payload = read_checkpoint(path)
    assert payload["format_version"] == CHECKPOINT_VERSION
    meta = payload["meta"]
    assert meta["family"] == family and meta["backbone"] == "mobilenet_v3_large_fpn"
    assert meta["classes"] == CLASSES and meta["input_size"] == 64 and meta["iterations"] == 2
    assert DetectorConfig.model_validate(meta["config"]) == config(family=family)
    assert isinstance(meta["buffers"], dict)
    assert oct(path.stat().st_mode & 0o777) == oct(0o644)


def test_round_trip_gives_identical_detections(trained, tmp_path):
    family, path, paths, arrays = trained
    detector = load_detector(path)
    assert not detector.model.training and detector.classes == CLASSES and detector.meta["family"] == family
    first = detect_object(detector, paths, batch_size=2)
    copy = save_checkpoint(detector.model, detector.meta, tmp_path / "copy.pt")
    reloaded = load_detector(copy)
    second = detect_object(reloaded, arrays, batch_size=2)  # arrays or their files: same pixels
    assert len(first) == len(second) == 3
    for a, b in zip(first, second):
        assert len(a["boxes"]) > 0
        for key in ("boxes", "scores", "labels"):
            np.testing.assert_array_equal(a[key], b[key])
    # Another batch size batches differently: the same up to float rounding.
    for a, b in zip(first, detect_object(reloaded, arrays, batch_size=3)):
        assert a["scores"][0] == pytest.approx(b["scores"][0], abs=1e-5)


def test_an_image_detects_the_same_beside_an_image_of_another_shape(trained, tmp_path):
    """torchvision pads a batch to its largest image: a wide image batched beside a tall one
    would be padded to a square and get other boxes and scores than alone."""
    _, path, _, _ = trained
    detector = load_detector(path)
    _, (wide,) = write_images(tmp_path / "wide", n=1, size=(60, 150), seed=4)
    _, (tall,) = write_images(tmp_path / "tall", n=1, size=(150, 60), seed=5)
    alone = detect_object(detector, [wide, tall], batch_size=1)
    together = detect_object(detector, [wide, tall, wide], batch_size=3)
    for result, reference in zip(together, alone + alone[:1]):
        assert len(reference["boxes"]) > 0
        for key in ("boxes", "scores", "labels"):
            np.testing.assert_allclose(result[key], reference[key], rtol=0, atol=1e-4)


def test_detections_are_numpy_zero_based_in_original_pixels(trained, tmp_path):
    _, path, _, _ = trained
    detector = load_detector(path, device="cpu")
    paths, arrays = write_images(tmp_path / "big", n=2, size=(90, 150), seed=3)
    results = detect_object(detector, [arrays[0], paths[1]], batch_size=1)
    for result in results:
        boxes, scores, labels = result["boxes"], result["scores"], result["labels"]
        assert boxes.dtype == np.float32 and boxes.shape == (len(scores), 4)
        assert scores.dtype == np.float32 and labels.dtype == np.int64
        assert labels.min() >= 0 and labels.max() < len(CLASSES)
        assert boxes[:, 0::2].max() <= 150 and boxes[:, 1::2].max() <= 90
        assert boxes[:, 0::2].max() > 64 or boxes[:, 1::2].max() > 64  # mapped back past the 64 px input
        assert np.all(np.diff(scores) <= 0)
    assert detect_object(detector, []) == []
    with pytest.raises(DatasetError, match=r"images\[0\].*RGB"):
        detect_object(detector, [np.zeros((10, 10, 4), np.uint8)])
    with pytest.raises(ValueError, match="batch_size"):
        detect_object(detector, arrays, batch_size=0)


def test_unreadable_or_foreign_files_are_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_detector(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"definitely not torch")
    with pytest.raises(CheckpointError, match="cannot be read"):
        load_detector(tmp_path / "junk.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="not a foldwise detector checkpoint"):
        load_detector(tmp_path / "foreign.pt")


def test_other_format_version_is_refused(trained, tmp_path):
    _, path, _, _ = trained
    payload = read_checkpoint(path)
    payload["format_version"] = CHECKPOINT_VERSION + 1
    torch.save(payload, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match=f"format version {CHECKPOINT_VERSION + 1}"):
        load_detector(tmp_path / "future.pt")


def test_state_that_does_not_fit_its_meta_is_an_error(trained, tmp_path):
    _, path, _, _ = trained
    payload = read_checkpoint(path)
    payload["meta"]["classes"] = ["a", "b", "c"]  # the predictor has 2 + 1 outputs, not 3 + 1
    torch.save(payload, tmp_path / "lying.pt")
    with pytest.raises(CheckpointError, match="does not fit"):
        load_detector(tmp_path / "lying.pt")


def test_failed_write_keeps_the_previous_checkpoint_and_leaves_no_temp_file(trained, tmp_path, monkeypatch):
    _, path, _, _ = trained
    detector = load_detector(path)
    target = tmp_path / "omega.pt"
    save_checkpoint(detector.model, detector.meta, target)
    before = target.read_bytes()

    def broken_save(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(checkpoint_module.torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(detector.model, {**detector.meta, "iterations": 99}, target)
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["omega.pt"]


def test_detection_runs_with_the_configured_thread_count(trained, monkeypatch):
    _, path, _, arrays = trained
    detector = load_detector(path)
    assert detector.meta["config"]["num_threads"] == 1
    seen = []
    forward = detector.model.forward

    def spy(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return forward(*args, **kwargs)

    monkeypatch.setattr(detector.model, "forward", spy)
    torch.set_num_threads(2)
    try:
        detect_object(detector, arrays[:1])
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)


def test_imagenet_initialised_detector_reloads_and_warm_starts_without_the_weights_file(tmp_path, monkeypatch):
    import torchvision

    from workers.train.detectors.backbones import imagenet_weights_path

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    weights, _ = imagenet_weights_path("mobilenet_v3_large")
    weights.parent.mkdir(parents=True)
    torch.save(torchvision.models.mobilenet_v3_large(weights=None).state_dict(), weights)
    paths, arrays = write_images(tmp_path / "images", n=2)
    samples = [Sample(path, [[12, 10, 50, 40]], [index]) for index, path in enumerate(paths)]
    omega = tmp_path / "omega.pt"
    train_detector(samples, None, 1, config(pretrained="imagenet"), CLASSES, omega)
    before = detect_object(load_detector(omega), arrays)

    weights.unlink()  # an inference-only machine, or the next increment, has no ImageNet file
    after = detect_object(load_detector(omega), arrays)
    for a, b in zip(before, after):
        np.testing.assert_array_equal(a["scores"], b["scores"])
    train_detector(samples, omega, 1, config(pretrained="imagenet"), CLASSES, tmp_path / "next.pt")
    with pytest.raises(CheckpointError, match="pretrained: checkpoint was built with 'imagenet'"):
        train_detector(samples, omega, 1, config(pretrained="none"), CLASSES, tmp_path / "other.pt")


def test_detection_at_several_sizes_merges_each_sizes_detections(trained, tmp_path, monkeypatch):
    """test_sizes: every detection of the merged run comes from one of the single-size runs, the
    best of each size survives unless a better box of its class covers it, and the model's own
    input size is back afterwards (a failing run included)."""
    from torchvision.ops import box_iou

    _, path, paths, arrays = trained
    detector = load_detector(path)
    sizes = (64, 96, 128)
    single = {size: detect_object(detector, paths, test_sizes=(size,)) for size in sizes}
    merged = detect_object(detector, paths, test_sizes=sizes)
    assert detector.model.transform.min_size == (64,) and detector.model.transform.max_size == 64
    assert any(not np.array_equal(single[64][i]["scores"], single[128][i]["scores"]) for i in range(len(paths)))
    for index, result in enumerate(merged):
        pool = [
            (tuple(box), score, label)
            for size in sizes
            for box, score, label in zip(
                single[size][index]["boxes"], single[size][index]["scores"], single[size][index]["labels"]
            )
        ]
        assert len(result["scores"]) <= detector.config.detections_per_image
        for box, score, label in zip(result["boxes"], result["scores"], result["labels"]):
            assert any(np.allclose(box, b) and score == s and label == lab for b, s, lab in pool)
        assert result["scores"][0] == max(score for _, score, _ in pool)
        for size in sizes:
            best = single[size][index]
            if not len(best["scores"]):
                continue
            kept = [np.allclose(box, best["boxes"][0]) for box in result["boxes"]]
            same_class = result["labels"] == best["labels"][0]
            overlap = box_iou(torch.as_tensor(result["boxes"]), torch.as_tensor(best["boxes"][:1]))[:, 0].numpy()
            assert any(kept) or np.any(same_class & (overlap > 0.5) & (result["scores"] >= best["scores"][0]))
    # A detector whose config names test_sizes detects so for every caller: detect_object and
    # the model's own forward alike.
    meta = {**detector.meta, "config": {**detector.meta["config"], "test_sizes": list(sizes)}}
    multi = load_detector(save_checkpoint(detector.model, meta, tmp_path / "multi.pt"))
    assert multi.model.test_sizes == sizes and detector.model.test_sizes == ()
    with torch.no_grad(), torch_threads(1):
        direct = multi.model([torch.from_numpy(arrays[0]).permute(2, 0, 1).float() / 255])
    # One image alone against the same image in a batch of three: oneDNN may block the
    # convolutions otherwise on some CPUs (1e-8 apart), far below what one size more changes.
    np.testing.assert_allclose(direct[0]["scores"].numpy(), merged[0]["scores"], rtol=0, atol=1e-6)
    for a, b in zip(merged, detect_object(multi, paths)):
        np.testing.assert_array_equal(a["scores"], b["scores"])
    # A run that fails leaves the model at its own input size and sizes.
    heads_forward = multi.model.roi_heads.forward

    def failing_at_96(*args, **kwargs):
        if multi.model.transform.max_size == 96:
            raise RuntimeError("out of memory")
        return heads_forward(*args, **kwargs)

    monkeypatch.setattr(multi.model.roi_heads, "forward", failing_at_96)
    with pytest.raises(RuntimeError, match="out of memory"):
        detect_object(multi, paths, test_sizes=(64, 96))
    assert multi.model.transform.max_size == 64 and multi.model.test_sizes == sizes


def test_a_detector_whose_views_vote_scores_by_their_vote_and_pairs_combine_so(trained, tmp_path, monkeypatch):
    """detector.view_vote: detect_object gives the single-size runs merged by merge_detections'
    vote, for every caller; an ensemble of such detectors combines the members' votes at 1."""
    import workers.train.detectors.views as views
    from workers.train.checkpoint import save_ensemble
    from workers.train.detectors.views import merge_detections

    _, path, paths, _ = trained
    plain = load_detector(path)
    sizes = (64, 96, 128)
    meta = {**plain.meta, "config": {**plain.meta["config"], "test_sizes": list(sizes), "view_vote": 0.7}}
    voting = load_detector(save_checkpoint(plain.model, meta, tmp_path / "voting.pt"))
    assert voting.model.view_vote == 0.7 and plain.model.view_vote is None
    single = [detect_object(plain, paths, test_sizes=(size,)) for size in sizes]
    voted = detect_object(voting, paths)
    limit = voting.config.detections_per_image
    for index, result in enumerate(voted):
        expected = merge_detections([runs[index] for runs in single], 0.5, limit, vote=0.7)
        for key in ("boxes", "scores", "labels"):
            np.testing.assert_allclose(result[key], expected[key], rtol=0, atol=1e-6)
    assert not all(
        np.allclose(a["scores"], b["scores"]) for a, b in zip(voted, detect_object(plain, paths, test_sizes=sizes))
    )
    pair = load_detector(save_ensemble([tmp_path / "voting.pt", tmp_path / "voting.pt"], tmp_path / "pair.pt"))
    assert pair.model.vote == 1.0
    # Two training steps leave every score under the vote's floor: lowered, so that they vote.
    monkeypatch.setattr(views, "VOTE_FLOOR", 0.01)
    voted = detect_object(voting, paths)
    for alone, together in zip(voted, detect_object(pair, paths)):
        np.testing.assert_allclose(together["scores"], 1 - (1 - alone["scores"]) ** 2, rtol=0, atol=1e-6)


@pytest.mark.parametrize("turn", [1, 2, 3])
def test_a_box_found_on_a_turned_image_maps_back_exactly(turn):
    """turn_image turns as torch.rot90 does, and unturn_boxes undoes it on a non-square image: the
    drawn rectangle's box on the turned image comes back as its box on the image as it was."""
    from workers.train.detectors.views import turn_image, unturn_boxes

    height, width = 30, 50
    image = torch.rand(3, height, width)
    image[:, 4:11, 7:20] = 2  # rows 4-10, columns 7-19: xyxy (7, 4, 20, 11) in pixel edges
    turned = turn_image(image, turn)
    torch.testing.assert_close(turned, torch.rot90(image, turn, dims=(1, 2)), rtol=0, atol=0)
    rows, columns = torch.nonzero(turned[0] == 2, as_tuple=True)
    found = torch.tensor([[columns.min(), rows.min(), columns.max() + 1, rows.max() + 1]], dtype=torch.float32)
    np.testing.assert_array_equal(unturn_boxes(found, turn, height, width).numpy(), [[7, 4, 20, 11]])


def test_detection_on_quarter_turns_merges_each_turns_detections_mapped_back(trained, tmp_path):
    """test_turns: every merged detection is one of a single turn's detections, mapped back to the
    image as it is; the config's turns reach every caller; and with all four turns the detector
    answers alike on an image and on the same image turned (the same four views)."""
    _, path, paths, arrays = trained
    detector = load_detector(path)
    turns = (0, 1, 2, 3)
    single = {turn: detect_object(detector, paths, test_turns=(turn,)) for turn in turns}
    merged = detect_object(detector, paths, test_turns=turns)
    assert detector.model.test_turns == ()
    upright = detect_object(detector, paths)
    for a, b in zip(upright, single[0]):
        np.testing.assert_array_equal(a["scores"], b["scores"])
    assert any(not np.array_equal(single[0][i]["scores"], single[1][i]["scores"]) for i in range(len(paths)))
    for index, result in enumerate(merged):
        pool = [
            (box, score, label)
            for turn in turns
            for box, score, label in zip(
                single[turn][index]["boxes"], single[turn][index]["scores"], single[turn][index]["labels"]
            )
        ]
        for box, score, label in zip(result["boxes"], result["scores"], result["labels"]):
            assert any(np.allclose(box, b, atol=1e-4) and score == s and label == lab for b, s, lab in pool)
            assert 0 <= box[0] < box[2] <= 64 and 0 <= box[1] < box[3] <= 64  # in the image's own pixels
        assert result["scores"][0] == max(score for _, score, _ in pool)

    meta = {**detector.meta, "config": {**detector.meta["config"], "test_turns": list(turns)}}
    turning = load_detector(save_checkpoint(detector.model, meta, tmp_path / "turns.pt"))
    assert turning.model.test_turns == turns
    with torch.no_grad(), torch_threads(1):
        direct = turning.model([torch.from_numpy(arrays[0]).permute(2, 0, 1).float() / 255])
    np.testing.assert_allclose(direct[0]["scores"].numpy(), merged[0]["scores"], rtol=0, atol=1e-6)

    image = arrays[0]
    quarter = np.ascontiguousarray(np.rot90(image, 1))  # numpy's rot90 turns as torch's does here
    on_image, on_quarter = detect_object(turning, [image, quarter])
    from workers.train.detectors.views import unturn_boxes

    back = unturn_boxes(torch.as_tensor(on_quarter["boxes"]), 1, *image.shape[:2]).numpy()
    np.testing.assert_allclose(on_quarter["scores"][:3], on_image["scores"][:3], atol=1e-4)
    np.testing.assert_allclose(back[:3], on_image["boxes"][:3], atol=0.05)


@pytest.mark.parametrize(
    "changes, problem",
    [
        (
            {"family": "yolo", "backbone": "mobilenet_v3_large", "test_sizes": [64, 96]},
            "test_sizes: only read by the R-CNN families",
        ),
        ({"test_sizes": [64, 64]}, "sizes repeat"),
        ({"test_sizes": [16, 64]}, "greater than or equal to 32"),
        (
            {"family": "yolo", "backbone": "mobilenet_v3_large", "test_turns": [0, 1]},
            "test_turns: only read by the R-CNN families",
        ),
        ({"test_turns": [1, 1]}, "turns repeat"),
        ({"test_turns": [0, 4]}, "Input should be 0, 1, 2 or 3"),
        ({"view_vote": 0.0}, "view_vote\n  Input should be greater than 0"),
        ({"view_vote": 1.5}, "view_vote\n  Input should be less than or equal to 1"),
        (
            {"family": "yolo", "backbone": "mobilenet_v3_large", "view_vote": 0.7},
            "view_vote: only read by the R-CNN families",
        ),
        (
            {"texture_search": True},
            "texture_search: searches with the texture check's textures; set texture_check: true too",
        ),
    ],
)
def test_bad_test_views_are_refused_with_the_reason(changes, problem):
    with pytest.raises(ValueError, match=problem):
        config(**changes)


def second_member(trained, tmp_path):
    """Another detector of the same family and classes (other seed): another network."""
    family, _, paths, _ = trained
    samples = [Sample(path, [[12, 10, 50, 40]], [index % 2]) for index, path in enumerate(paths)]
    train_detector(samples, None, 2, config(family=family), CLASSES, tmp_path / "other.pt", seed=1)
    return tmp_path / "other.pt"


def same_detections(first, second) -> bool:
    return len(first) == len(second) and all(
        np.array_equal(a[key], b[key]) for a, b in zip(first, second) for key in ("boxes", "scores", "labels")
    )


def test_an_ensemble_file_detects_as_its_members_merged(trained, tmp_path):
    """save_ensemble holds its members whole (the file travels alone); load_detector gives one
    detector whose detections are the members' pooled by per-class NMS, each box one a member
    found; at its members' views too; and a member with itself detects as the member alone."""
    from workers.train.checkpoint import ENSEMBLE_FORMAT, detect_ensemble, save_ensemble

    _, path, paths, arrays = trained
    other = second_member(trained, tmp_path)
    ensemble_path = save_ensemble([path, other], tmp_path / "ensemble.pt")
    moved = tmp_path / "elsewhere" / "copy.pt"
    moved.parent.mkdir()
    ensemble_path.rename(moved)
    other.unlink()  # the file holds the members: nothing else is read
    payload = torch.load(moved, weights_only=True)
    assert payload["format"] == ENSEMBLE_FORMAT and len(payload["members"]) == 2
    ensemble = load_detector(moved)
    assert ensemble.classes == CLASSES and [m["family"] for m in ensemble.meta["members"]] == [trained[0]] * 2
    members = [
        load_detector(path),
        load_detector(save_checkpoint(ensemble.model.members[1], payload["members"][1]["meta"], tmp_path / "m2.pt")),
    ]
    alone = [detect_object(member, arrays) for member in members]
    together = detect_object(ensemble, arrays)
    assert all(len(result["boxes"]) <= 10 for result in together)  # the first member's cap (detections_per_image)
    for index, result in enumerate(together):
        pool = [
            (b, s, lab)
            for run in alone
            for b, s, lab in zip(run[index]["boxes"], run[index]["scores"], run[index]["labels"])
        ]
        assert len(result["boxes"]) > 0 and result["scores"][0] == max(s for _, s, _ in pool)
        for box, score, label in zip(result["boxes"], result["scores"], result["labels"]):
            assert any(np.allclose(box, b) and score == s and label == lab for b, s, lab in pool)
    listed = detect_ensemble(members, paths)  # a list of detectors: the same ensemble
    assert same_detections(together, listed)
    turned = detect_object(ensemble, arrays, test_turns=(0, 2))
    assert not same_detections(turned, together)  # the views reach every member...
    assert [member.test_turns for member in ensemble.model.members] == [(), ()]  # ...and are restored
    self_pair = load_detector(save_ensemble([path, path], tmp_path / "self.pt"))
    assert same_detections(detect_object(self_pair, arrays), alone[0])


def test_an_ensemble_is_refused_where_one_network_is_needed_and_with_other_classes(trained, tmp_path):
    from workers.train.checkpoint import save_ensemble

    _, path, paths, _ = trained
    ensemble_path = save_ensemble([path, path], tmp_path / "ensemble.pt")
    with pytest.raises(CheckpointError, match="is an ensemble of 2 detectors.*start from one of the checkpoints"):
        read_checkpoint(ensemble_path)  # warm starts and fine-tuning read one network
    with pytest.raises(CheckpointError, match="is an ensemble of 2 detectors"):
        train_detector(
            [Sample(paths[0], [[12, 10, 50, 40]], [0])],
            ensemble_path,
            1,
            config(family=trained[0]),
            CLASSES,
            tmp_path / "w.pt",
        )
    payload = read_checkpoint(path)
    payload["meta"]["classes"] = CLASSES[::-1]
    reordered = tmp_path / "reordered.pt"
    torch.save(payload, reordered)
    with pytest.raises(CheckpointError, match="an ensemble needs one class list"):
        save_ensemble([path, reordered], tmp_path / "bad.pt")
    assert not (tmp_path / "bad.pt").exists()
    broken = tmp_path / "broken.pt"
    torch.save({"format": "foldwise-ensemble", "format_version": 1, "members": [{"format": "other"}]}, broken)
    with pytest.raises(CheckpointError, match=r"broken.pt \(member 1\) is not a foldwise detector checkpoint"):
        load_detector(broken)
    torch.save({"format": "foldwise-ensemble", "format_version": 1, "members": []}, broken)
    with pytest.raises(CheckpointError, match="holds no members"):
        load_detector(broken)


def test_foldwise_threads_caps_what_the_config_asks_for(monkeypatch):
    """FOLDWISE_THREADS: a process's share of a machine others share (foldwise run --members)."""
    from foldwise.settings import get_settings

    monkeypatch.setenv("FOLDWISE_THREADS", "1")
    get_settings.cache_clear()
    try:
        torch.set_num_threads(3)
        with torch_threads(2):
            assert torch.get_num_threads() == 1
        with torch_threads(0):  # "torch's choice" within the share
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 3
        monkeypatch.setenv("FOLDWISE_THREADS", "0")
        get_settings.cache_clear()
        with torch_threads(2):
            assert torch.get_num_threads() == 2
    finally:
        get_settings.cache_clear()
        torch.set_num_threads(1)


def test_a_texture_checked_detector_carries_its_textures_and_checks_what_the_network_found(tmp_path):
    """detector.texture_check: the checkpoint holds each class's texture in grayscale (an ensemble
    of such checkpoints too); detect_object gives the network's detections passed through the
    check, texture_check=False the network's alone; a fresh start without textures is refused."""
    import skimage.data

    from workers.train.checkpoint import save_ensemble
    from workers.train.texture_check import TextureCheck

    paths, arrays = write_images(tmp_path / "images")
    samples = [Sample(path, [[12, 10, 50, 40]], [index % 2]) for index, path in enumerate(paths)]
    textures = {"astronaut": skimage.data.astronaut(), "coffee": skimage.data.coffee()}
    checked_config = config(family="faster_rcnn", texture_check=True)
    with pytest.raises(ValueError, match=r"texture_check needs each class's texture; none for \['coffee'\]"):
        train_detector(
            samples,
            None,
            1,
            checked_config,
            CLASSES,
            tmp_path / "refused.pt",
            textures={"astronaut": textures["astronaut"]},
        )
    path = tmp_path / "checked.pt"
    train_detector(samples, None, 2, checked_config, CLASSES, path, seed=0, textures=textures)
    warm = tmp_path / "warm.pt"  # a warm start keeps ω_in's textures
    train_detector(samples, path, 1, checked_config, CLASSES, warm, seed=0)
    ensemble = save_ensemble([path, warm], tmp_path / "pair.pt")
    for checkpoint in (path, warm, ensemble):
        detector = load_detector(checkpoint)
        assert sorted(detector.textures) == CLASSES
        np.testing.assert_array_equal(detector.textures["coffee"], cv2.cvtColor(textures["coffee"], cv2.COLOR_RGB2GRAY))
    detector = load_detector(path)
    network = detect_object(detector, arrays, texture_check=False)
    reference = TextureCheck(detector.textures, CLASSES)
    for image, alone, checked in zip(arrays, network, detect_object(detector, arrays)):
        for key, value in reference.apply(image, alone).items():
            np.testing.assert_array_equal(checked[key], value)
    unchecked = load_detector(
        save_checkpoint(
            detector.model, {**detector.meta, "config": config().model_dump(mode="json")}, tmp_path / "off.pt"
        )
    )
    assert unchecked.textures is None and unchecked.texture_check() is None
    assert detector.texture_check().search is False
    # detector.texture_search: the check also searches the whole image with the same textures.
    searching_config = config(family="faster_rcnn", texture_check=True, texture_search=True).model_dump(mode="json")
    searching = load_detector(
        save_checkpoint(
            detector.model, {**detector.meta, "config": searching_config}, tmp_path / "search.pt", textures=textures
        )
    )
    assert searching.texture_check().search is True
    reference = TextureCheck(searching.textures, CLASSES, search=True)
    for image, alone, checked in zip(arrays, network, detect_object(searching, arrays)):
        for key, value in reference.apply(image, alone).items():
            np.testing.assert_array_equal(checked[key], value)


@pytest.mark.parametrize("setting", ["folder", "empty"])
def test_a_detectors_texture_check_is_kept_in_the_settings_cache_folder(tmp_path, monkeypatch, setting):
    """FOLDWISE_CACHE_DIR: a detector keeps its texture check's keypoints and trees under
    texture-check/ there, so the next process reads them instead of making them; set empty,
    nothing is kept."""
    import skimage.data

    from foldwise.settings import get_settings
    from workers.train.checkpoint import Detector

    cache = tmp_path / "cache"
    monkeypatch.setenv("FOLDWISE_CACHE_DIR", str(cache) if setting == "folder" else "")
    get_settings.cache_clear()
    try:
        meta = {"classes": CLASSES, "config": config(family="faster_rcnn", texture_check=True).model_dump(mode="json")}
        textures = {"astronaut": skimage.data.astronaut(), "coffee": skimage.data.coffee()}
        assert Detector(model=torch.nn.Identity(), meta=meta, textures=textures).texture_check() is not None
    finally:
        get_settings.cache_clear()
    kept = sorted(path.suffix for path in (cache / "texture-check").glob("*")) if cache.exists() else []
    assert kept == ([".flann", ".npz"] if setting == "folder" else [])


def _views_by_hand(members, images, sizes, turns, vote, iou, limit):
    """An ensemble's views as the plainest code gives them: each member, size, turn and image
    one eval forward alone, boxes turned back, each member's views merged, then the members."""
    from torchvision.models.detection.generalized_rcnn import GeneralizedRCNN

    from workers.train.detectors.views import merge_detections, turn_image, unturn_boxes

    runs = []
    for member in members:
        saved = member.transform.min_size, member.transform.max_size
        views = []
        for turn in turns:
            for size in sizes:
                member.transform.min_size, member.transform.max_size = (size,), size
                found = []
                for image in images:
                    (output,) = GeneralizedRCNN.forward(member, [turn_image(image, turn)])
                    found.append({**output, "boxes": unturn_boxes(output["boxes"], turn, *image.shape[-2:])})
                views.append(found)
        member.transform.min_size, member.transform.max_size = saved
        heads = member.roi_heads
        runs.append(
            [merge_detections(o, heads.nms_thresh, heads.detections_per_img, member.view_vote) for o in zip(*views)]
        )
    return [merge_detections(outputs, iou, limit, vote) for outputs in zip(*runs)]


def test_an_ensembles_views_run_together_and_detect_as_each_view_alone(tmp_path, monkeypatch):
    """Members on one trunk (a frozen pretrained backbone, other heads) run it once per view for
    all of them, and the turns of one shape (0 and 2, 1 and 3) run as one batch: the detections
    are those of every member, view and image run alone, on square and non-square images."""
    import workers.train.detectors.views as views
    from workers.train.checkpoint import Cascade, save_ensemble

    paths, arrays = write_images(tmp_path / "images", n=2, size=(48, 80))
    arrays.append(write_images(tmp_path / "square", n=1)[1][0])
    samples = [Sample(path, [[12, 10, 50, 40]], [index % 2]) for index, path in enumerate(paths)]
    changes = {"family": "faster_rcnn", "test_sizes": [64, 96], "test_turns": [0, 1, 2, 3], "view_vote": 0.7}
    path = tmp_path / "first.pt"
    train_detector(samples, None, 2, config(**changes), CLASSES, path, seed=0)
    first = load_detector(path)
    # A second member on the same trunk: the first's weights with every layer after the trunk moved.
    other = first.model
    with torch.no_grad():
        for name, parameter in other.named_parameters():
            if not name.startswith("backbone.body."):
                parameter.add_(0.05 * torch.randn_like(parameter))
    save_checkpoint(other, first.meta, tmp_path / "second.pt")
    ensemble = load_detector(save_ensemble([path, tmp_path / "second.pt"], tmp_path / "pair.pt"))
    ensemble.cascade = None
    members = list(ensemble.model.members)
    assert views.shares_trunk(members)
    trunk_calls = []
    for member in members:
        body_forward = member.backbone.body.forward
        monkeypatch.setattr(
            member.backbone.body, "forward", lambda x, f=body_forward: trunk_calls.append(x.shape[0]) or f(x)
        )
    monkeypatch.setattr(views, "VOTE_FLOOR", 0.01)  # two training steps score under the vote's floor
    found = detect_object(ensemble, arrays, batch_size=1)
    # Per image: 2 sizes x 2 pairs of turns, one trunk pass each for both members, two images a pass.
    assert trunk_calls == [2] * 4 * len(arrays)
    tensors = [torch.from_numpy(image).permute(2, 0, 1).float() / 255 for image in arrays]
    with torch.no_grad(), torch_threads(1):
        expected = _views_by_hand(members, tensors, (64, 96), (0, 1, 2, 3), 1.0, 0.5, 10)
    for result, reference in zip(found, expected):
        assert len(result["scores"]) > 1
        np.testing.assert_array_equal(result["labels"], reference["labels"].numpy() - 1)
        np.testing.assert_allclose(result["scores"], reference["scores"].numpy(), rtol=0, atol=1e-5)
        np.testing.assert_allclose(result["boxes"], reference["boxes"].numpy(), rtol=0, atol=1e-3)
    # Members on trunks of their own run their views each, to the same rule.
    with torch.no_grad():
        next(members[1].backbone.body.parameters()).add_(0.01)
    assert not views.shares_trunk(members)
    trunk_calls.clear()
    found = detect_object(ensemble, arrays[:1])
    assert trunk_calls == [2] * 4 * 2
    with torch.no_grad(), torch_threads(1):
        (expected,) = _views_by_hand(members, tensors[:1], (64, 96), (0, 1, 2, 3), 1.0, 0.5, 10)
    np.testing.assert_allclose(found[0]["scores"], expected["scores"].numpy(), rtol=0, atol=1e-5)
    assert Cascade().first_size((64, 96)) == 96 and Cascade(size=64).first_size((64, 96)) == 64


def test_the_cascade_runs_every_view_only_where_one_view_leaves_the_image_unsure(tmp_path, monkeypatch):
    """detector.cascade: each image at one view (the largest size, upright) and the texture check
    first; an image the cascade's rule calls unsure then at every view, checked on the keypoints
    found once; the others keep the first pass's detections."""
    import skimage.data

    from workers.train.checkpoint import Cascade
    from workers.train.texture_check import TextureCheck

    paths, arrays = write_images(tmp_path / "images", n=4, size=(64, 80))
    samples = [Sample(path, [[12, 10, 50, 40]], [index % 2]) for index, path in enumerate(paths)]
    textures = {"astronaut": skimage.data.astronaut(), "coffee": skimage.data.coffee()}
    changes = {"family": "faster_rcnn", "test_sizes": [64, 96], "test_turns": [0, 1], "texture_check": True}
    path = tmp_path / "checked.pt"
    train_detector(samples, None, 2, config(**changes), CLASSES, path, seed=0, textures=textures)
    detector = load_detector(path)
    assert detector.cascade == Cascade()
    detector.cascade = None
    every_view = detect_object(detector, arrays)
    one_view = detect_object(detector, arrays, test_sizes=(96,), test_turns=())
    assert not all(same_detections([a], [b]) for a, b in zip(every_view, one_view))
    found_keypoints = []
    keypoints = TextureCheck._keypoints_and_matches
    monkeypatch.setattr(
        TextureCheck, "_keypoints_and_matches", lambda self, gray: found_keypoints.append(1) or keypoints(self, gray)
    )
    detector.cascade = Cascade()
    monkeypatch.setattr(Cascade, "again", lambda self, checked: True)
    assert same_detections(detect_object(detector, arrays), every_view)
    assert len(found_keypoints) == len(arrays)  # once an image, for both passes
    monkeypatch.setattr(Cascade, "again", lambda self, checked: False)
    assert same_detections(detect_object(detector, arrays), one_view)
    # Images 1 and 3 unsure: they alone go again (one forward for the two of them).
    asked = []
    monkeypatch.setattr(Cascade, "again", lambda self, checked: asked.append(1) or len(asked) % 2 == 0)
    forwards = []
    forward = type(detector.model).forward
    monkeypatch.setattr(
        type(detector.model), "forward", lambda self, images: forwards.append(len(images)) or forward(self, images)
    )
    found = detect_object(detector, arrays, batch_size=4)
    assert forwards == [4, 2] and len(asked) == 4
    expected = [one_view[0], every_view[1], one_view[2], every_view[3]]
    for result, reference in zip(found, expected):
        for key in ("boxes", "scores", "labels", "confirmed"):
            np.testing.assert_allclose(result[key], reference[key], rtol=0, atol=1e-5)
    # Views asked for, or a detector without the check: one pass at those views.
    forwards.clear()
    detect_object(detector, arrays, batch_size=4, test_turns=(0, 1))
    detect_object(detector, arrays, batch_size=4, texture_check=False)
    assert forwards == [4, 4]
    # Every view asked for in the call (foldwise detect --every-view), or by the config's
    # detector.cascade off: one pass at every view, the same detections as without a cascade.
    forwards.clear()
    assert same_detections(detect_object(detector, arrays, batch_size=4, every_view=True), every_view)
    detector.meta = {**detector.meta, "config": {**detector.meta["config"], "cascade": False}}
    assert same_detections(detect_object(detector, arrays, batch_size=4), every_view)
    assert forwards == [4, 4]


def test_the_cascades_rule_goes_on_where_nothing_is_confirmed_or_a_box_is_unsure():
    from workers.train.checkpoint import Cascade

    def checked(scores, confirmed):
        return {"scores": np.array(scores, np.float32), "confirmed": np.array(confirmed, bool)}

    assert Cascade().again(checked([], []))
    assert Cascade().again(checked([0.85, 0.4], [False, False]))
    assert not Cascade().again(checked([0.95, 0.85, 0.4], [True, False, False]))
    assert Cascade(unsure=0.8).again(checked([0.95, 0.85, 0.4], [True, False, False]))
    assert not Cascade(unsure=0.9).again(checked([0.95, 0.85, 0.4], [True, False, False]))
