"""Train-time augmentation: off by default and in the paper's config, box-aware, seeded,
recorded in the checkpoint, and a training step actually sees augmented images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from test_training import CLASSES, config, synthetic_samples  # noqa: E402  (tests/workers/train is on sys.path)

from foldwise.config import AugmentationConfig, load_config
from foldwise.settings import REPO_ROOT
from workers.train import training
from workers.train.augment import ZOOM_FILL, augmented, build_augmentation
from workers.train.checkpoint import read_checkpoint
from workers.train.training import train_detector

torch.set_num_threads(1)
CPU = torch.device("cpu")


def _image(size=64, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (size, size, 3)).astype(np.uint8)


def test_off_by_default_and_in_the_papers_config_on_in_quick():
    assert build_augmentation(AugmentationConfig(), (64, 64)) is None
    assert not load_config(REPO_ROOT / "configs/paper.yaml").detector.augmentation.enabled
    quick = load_config(REPO_ROOT / "configs/quick.yaml").detector.augmentation
    assert quick.enabled


def test_boxes_follow_the_crop_and_a_box_cut_away_is_dropped_with_its_label():
    transform = build_augmentation(
        AugmentationConfig(enabled=True, crop=1.0, photometric=0, grayscale=0, blur=0, noise=0, jpeg=0), (64, 64)
    )
    image = np.zeros((64, 64, 3), np.uint8)
    image[10:30, 20:50] = 255  # a white box: wherever the crop puts it, the box must frame it
    boxes = np.array([[20, 10, 50, 30]], np.float32)
    kept = 0
    aspects = set()
    for seed in range(40):
        torch.manual_seed(seed)
        out, target = augmented(transform, image, boxes, np.array([1]), CPU)
        # Frames of many shapes, none distorted: the long side is the input size.
        assert max(out.shape[1:]) == 64 and out.dtype == torch.float32
        aspects.add(round(out.shape[2] / out.shape[1], 1))
        if len(target["boxes"]) == 0:
            continue
        kept += 1
        x0, y0, x1, y1 = target["boxes"][0].tolist()
        white = out.mean(0) > 0.5
        rows, cols = np.flatnonzero(white.any(1).numpy()), np.flatnonzero(white.any(0).numpy())
        assert abs(cols[0] - x0) <= 1.5 and abs(cols[-1] + 1 - x1) <= 1.5
        assert abs(rows[0] - y0) <= 1.5 and abs(rows[-1] + 1 - y1) <= 1.5
        assert target["labels"].tolist() == [2]  # 0-based 1 -> torchvision's 1-based 2
    assert 10 < kept <= 40
    assert min(aspects) < 0.8 and max(aspects) > 1.25


def test_a_quarter_turn_turns_the_frame_and_keeps_each_box_exact():
    transform = build_augmentation(
        AugmentationConfig(enabled=True, quarter_turn=1.0, crop=0, photometric=0, grayscale=0, blur=0, noise=0, jpeg=0),
        (64, 64),
    )
    image = np.zeros((40, 60, 3), np.uint8)
    image[10:30, 5:15] = 255  # a white block, its box exactly
    boxes = np.array([[5, 10, 15, 30]], np.float32)
    seen = set()
    for seed in range(30):
        torch.manual_seed(seed)
        out, target = augmented(transform, image, boxes, np.array([0]), CPU)
        white = out.mean(0) > 0.5
        rows, cols = np.flatnonzero(white.any(1).numpy()), np.flatnonzero(white.any(0).numpy())
        box = target["boxes"][0].tolist()
        assert box == [cols[0], rows[0], cols[-1] + 1, rows[-1] + 1]  # to the pixel
        assert white.sum().item() == 200 and target["labels"].tolist() == [1]
        seen.add((tuple(out.shape[1:]), tuple(box)))
    # Three turns, none the identity: a quarter (frame 60 x 40), a half, three quarters.
    assert seen == {
        ((60, 40), (10.0, 45.0, 30.0, 55.0)),
        ((40, 60), (45.0, 10.0, 55.0, 30.0)),
        ((60, 40), (10.0, 5.0, 30.0, 15.0)),
    }


def test_the_crop_keeps_the_objects_shape():
    """A square object stays square whatever the frame's aspect (no anisotropic resize)."""
    transform = build_augmentation(
        AugmentationConfig(enabled=True, crop=1.0, photometric=0, grayscale=0, blur=0, noise=0, jpeg=0), (64, 64)
    )
    image = np.zeros((64, 64, 3), np.uint8)
    image[24:40, 24:40] = 255
    boxes = np.array([[24, 24, 40, 40]], np.float32)
    checked = 0
    for seed in range(20):
        torch.manual_seed(seed)
        out, target = augmented(transform, image, boxes, np.array([0]), CPU)
        height, width = out.shape[1:]
        if len(target["boxes"]):
            x0, y0, x1, y1 = target["boxes"][0].tolist()
            if x0 > 0 and y0 > 0 and x1 < width - 1 and y1 < height - 1:  # not cut by the frame
                checked += 1
                assert abs((x1 - x0) - (y1 - y0)) <= 1.0
    assert checked >= 5


def test_photometric_steps_change_pixels_not_boxes_and_the_seed_fixes_them():
    transform = build_augmentation(
        AugmentationConfig(enabled=True, crop=0, photometric=1, blur=1, noise=1, jpeg=1), (64, 64)
    )
    boxes = np.array([[5, 5, 40, 40]], np.float32)
    outputs = []
    for seed in (3, 3, 4):
        torch.manual_seed(seed)
        out, target = augmented(transform, _image(), boxes, np.array([0]), CPU)
        assert target["boxes"].tolist() == boxes.tolist()
        outputs.append(out)
    plain = torch.from_numpy(_image()).permute(2, 0, 1).float() / 255
    assert not torch.allclose(outputs[0], plain, atol=0.02)
    assert torch.equal(outputs[0], outputs[1]) and not torch.equal(outputs[0], outputs[2])


def test_the_object_zoom_fills_the_frame_with_the_target_and_never_cuts_it_out():
    """The target's long side spans ZOOM_FILL of the frame (a larger one is cut by the frame),
    its box still frames the object's pixels, and it is never zoomed out of the frame."""
    transform = build_augmentation(
        AugmentationConfig(enabled=True, zoom=1.0, crop=0, photometric=0, grayscale=0, blur=0, noise=0, jpeg=0),
        (64, 64),
    )
    image = np.zeros((256, 256, 3), np.uint8)
    image[100:124, 60:108] = 255  # 48 x 24: a small sheet in a large frame
    boxes = np.array([[60, 100, 108, 124]], np.float32)
    whole, cut = [], 0
    for seed in range(60):
        torch.manual_seed(seed)
        out, target = augmented(transform, image, boxes, np.array([0]), CPU)
        height, width = out.shape[1:]
        assert max(height, width) == 64
        assert len(target["boxes"]) == 1  # cut by the frame at most, never cut out
        x0, y0, x1, y1 = target["boxes"][0].tolist()
        white = out.mean(0) > 0.5
        rows, cols = np.flatnonzero(white.any(1).numpy()), np.flatnonzero(white.any(0).numpy())
        assert abs(cols[0] - x0) <= 1.5 and abs(cols[-1] + 1 - x1) <= 1.5
        assert abs(rows[0] - y0) <= 1.5 and abs(rows[-1] + 1 - y1) <= 1.5
        if x0 <= 0.5 or y0 <= 0.5 or x1 >= width - 0.5 or y1 >= height - 0.5:
            cut += 1
        else:
            whole.append(max(x1 - x0, y1 - y0) / max(width, height))
    assert 5 <= cut <= 55  # some views cut the sheet at the frame, most do not
    assert ZOOM_FILL[0] - 0.05 <= min(whole) and max(whole) <= 1.0
    assert max(whole) - min(whole) > 0.3  # zoomed by different amounts, not one fixed scale


def test_an_image_without_objects_passes_through():
    transform = build_augmentation(AugmentationConfig(enabled=True, crop=1.0), (64, 64))
    out, target = augmented(transform, _image(), np.zeros((0, 4), np.float32), np.zeros(0, np.int64), CPU)
    assert max(out.shape[1:]) == 64 and target["boxes"].shape == (0, 4) and len(target["labels"]) == 0


def test_training_sees_augmented_batches_is_seeded_and_records_the_settings(tmp_path, monkeypatch):
    samples = synthetic_samples(tmp_path / "images")
    augment = AugmentationConfig(enabled=True, crop=0.5, photometric=1.0)
    seen = []
    original = training.compute_losses

    def spy(model, images, targets):
        seen.append(images[0].clone())
        return original(model, images, targets)

    monkeypatch.setattr(training, "compute_losses", spy)
    runs = [
        train_detector(samples, None, 2, config(augmentation=augment), CLASSES, tmp_path / f"{name}.pt", seed=5)
        for name in ("a", "b")
    ]
    assert runs[0].losses == runs[1].losses
    assert torch.equal(seen[0], seen[2])  # the same seed, the same augmented first batch
    plain = [training.image_tensor(training.read_image_rgb(s.image_path), CPU) for s in samples]
    assert not any(torch.equal(seen[0], p) for p in plain)
    meta = read_checkpoint(tmp_path / "a.pt")["meta"]
    assert meta["config"]["augmentation"] == augment.model_dump(mode="json")


@pytest.mark.parametrize("bad", [{"crop": 1.5}, {"noise": -0.1}, {"flip": 0.5}])
def test_bad_settings_name_the_key(bad):
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=next(iter(bad))):
        AugmentationConfig(enabled=True, **bad)


def _all_steps(**changes) -> AugmentationConfig:
    steps = dict(
        enabled=True,
        quarter_turn=0.5,
        zoom=0.5,
        crop=0.5,
        photometric=0.5,
        grayscale=0.2,
        blur=0.2,
        noise=0.2,
        jpeg=0.2,
    )
    return AugmentationConfig(**{**steps, **changes})


@pytest.mark.parametrize("shape", [(42, 64), (64, 42), (30, 30)])
def test_non_square_images_with_and_without_boxes_pass_every_step(shape):
    """A quarter turn of a non-square image without boxes used to leave the boxes' canvas
    unturned, and the next step found two image sizes (torchvision's rotate on empty boxes)."""
    transform = build_augmentation(_all_steps(quarter_turn=1.0), (48, 48))
    image = _image(64)[: shape[0], : shape[1]].copy()
    for boxes in (np.zeros((0, 4), np.float32), np.array([[2, 3, 20, 25]], np.float32)):
        for seed in range(12):
            torch.manual_seed(seed)
            out, target = augmented(transform, image, boxes, np.zeros(len(boxes), np.int64), CPU)
            assert out.shape[0] == 3 and target["boxes"].shape[1] == 4
            if len(target["boxes"]):
                assert (
                    float(target["boxes"][:, 2].max()) <= out.shape[2]
                    and float(target["boxes"][:, 3].max()) <= out.shape[1]
                )


@pytest.mark.parametrize("turns", [1, 2, 3])
def test_quarter_turn_boxes_match_rot90_of_the_pixels(turns):
    from torchvision import tv_tensors

    from workers.train.augment import quarter_turn_boxes

    mask = torch.zeros(37, 53)
    mask[4:19, 30:51] = 1
    boxes = tv_tensors.BoundingBoxes(torch.tensor([[30.0, 4.0, 51.0, 19.0]]), format="XYXY", canvas_size=(37, 53))
    turned = quarter_turn_boxes(boxes, turns)
    pixels = torch.rot90(mask, turns, dims=(-2, -1))
    rows, cols = torch.nonzero(pixels.any(1)).flatten(), torch.nonzero(pixels.any(0)).flatten()
    assert turned.tolist() == [[float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)]]
    assert turned.canvas_size == tuple(pixels.shape)


def test_training_on_portrait_and_landscape_images_with_every_step(tmp_path):
    """Mixed orientations in one batch, turned, cropped and zoomed: training runs and the
    augmented frames come in several shapes."""
    samples = []
    for index, (height, width) in enumerate([(48, 80), (80, 48), (64, 64), (40, 72)]):
        folder = tmp_path / str(index)
        sample = synthetic_samples(folder, n=1, size=max(height, width), seed=index)[0]
        image = training.read_image_rgb(sample.image_path)[:height, :width]
        cv2.imwrite(str(sample.image_path), cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR))
        x0, y0, x1, y1 = sample.boxes[0]
        clipped = np.array([[x0, y0, min(x1, width), min(y1, height)]], np.float32)
        if clipped[0, 2] - clipped[0, 0] < 4 or clipped[0, 3] - clipped[0, 1] < 4:
            clipped = np.array([[2, 2, width / 2, height / 2]], np.float32)
        samples.append(training.Sample(sample.image_path, clipped, sample.labels))
    samples.append(training.Sample(samples[0].image_path, np.zeros((0, 4), np.float32), np.zeros(0, np.int64)))
    stats = train_detector(
        samples, None, 4, config(augmentation=_all_steps(quarter_turn=1.0), batch_size=3), CLASSES, tmp_path / "m.pt"
    )
    assert stats.iterations == 4 and not stats.nonfinite_steps
