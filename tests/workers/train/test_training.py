"""train_detector: seeded, warm-startable, and a non-finite step never reaches the weights."""

from __future__ import annotations

import errno
import itertools
import json
import math
import os

import cv2
import numpy as np
import pytest
import torch

from tests.workers.train.training_helpers import CLASSES, config, synthetic_samples
from workers.train import checkpoint as checkpoint_module
from workers.train import training
from workers.train.checkpoint import CheckpointError, NoRoomError, read_checkpoint
from workers.train.data import Sample
from workers.train.training import (
    TrainingDiverged,
    TrainStats,
    compute_losses,
    image_tensor,
    learning_rate_at,
    sample_batches,
    sample_target,
    train_detector,
)

torch.set_num_threads(1)


def state(path):
    return read_checkpoint(path)["state_dict"]


def assert_same_state(a, b):
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


@pytest.mark.parametrize("family", ["faster_rcnn", "fast_rcnn"])
def test_same_seed_same_weights_other_seed_other_weights(tmp_path, family):
    samples = synthetic_samples(tmp_path / "images")
    runs = [
        train_detector(samples, None, 2, config(family=family), CLASSES, tmp_path / f"{name}.pt", seed=seed)
        for name, seed in [("a", 7), ("b", 7), ("c", 8)]
    ]
    assert_same_state(state(tmp_path / "a.pt"), state(tmp_path / "b.pt"))
    assert runs[0].losses == runs[1].losses
    other = state(tmp_path / "c.pt")
    assert any(not torch.equal(value, other[key]) for key, value in state(tmp_path / "a.pt").items())
    stats = runs[0]
    assert (stats.iterations, stats.images_seen, stats.device) == (2, 4, "cpu")
    assert len(stats.losses) == 2 and all(math.isfinite(v) for v in stats.losses)
    assert stats.final_loss == pytest.approx(np.mean(stats.losses))
    assert stats.nonfinite_steps == []


def test_warm_start_continues_from_the_checkpoint_weights(tmp_path):
    samples = synthetic_samples(tmp_path / "images")
    parent = tmp_path / "parent.pt"
    train_detector(samples, None, 2, config(), CLASSES, parent, seed=1)

    # ω_in's loss on the first batch the warm start will draw, under the same seed.
    from workers.train.checkpoint import load_detector

    model = load_detector(parent).model.train()
    seed = 5
    first_batch = sample_batches(len(samples), 3, config().batch_size, seed)[0]
    torch.manual_seed(seed)
    images = [
        image_tensor(cv2.cvtColor(cv2.imread(str(samples[i].image_path)), cv2.COLOR_BGR2RGB), torch.device("cpu"))
        for i in first_batch
    ]
    targets = [sample_target(samples[i], torch.device("cpu")) for i in first_batch]
    expected = float(sum(compute_losses(model, images, targets).values()).detach())

    child = tmp_path / "child.pt"
    stats = train_detector(samples, parent, 3, config(), CLASSES, child, seed=seed)
    assert stats.losses[0] == pytest.approx(expected, rel=1e-5)
    fresh = train_detector(samples, None, 1, config(), CLASSES, tmp_path / "fresh.pt", seed=seed)
    assert fresh.losses[0] != pytest.approx(expected, rel=1e-3)  # a fresh start is a different model
    meta = read_checkpoint(child)["meta"]
    assert meta["iterations"] == 5 and meta["parent"] == str(parent)

    # ω_in may be overwritten by ω (the benchmark trains in chunks into one file).
    train_detector(samples, child, 1, config(), CLASSES, child, seed=seed)
    assert read_checkpoint(child)["meta"]["iterations"] == 6


def test_warm_start_inherits_the_parents_textures_and_lookalikes_unless_given_new_ones(tmp_path):
    """A curriculum's stage, or a finetune, starts from a checkpoint whose texture check knows its
    lookalikes: the child's check must know them too, or it confirms them again."""
    from workers.train.checkpoint import payload_textures

    samples = synthetic_samples(tmp_path / "images", n=3)
    checked = config(texture_check=True)
    textures = {name: np.full((40, 30, 3), 60 * i, np.uint8) for i, name in enumerate(CLASSES)}
    form = np.full((40, 30, 3), 200, np.uint8)
    parent = tmp_path / "parent.pt"
    train_detector(samples, None, 1, checked, CLASSES, parent, textures=textures, lookalikes={"form": form})

    inherited = tmp_path / "inherited.pt"
    train_detector(samples, parent, 1, checked, CLASSES, inherited)
    payload = read_checkpoint(inherited)
    assert set(payload_textures(payload)) == set(CLASSES)
    np.testing.assert_array_equal(payload_textures(payload, "lookalikes")["form"], form[:, :, 0])  # grey as stored

    replaced = tmp_path / "replaced.pt"
    train_detector(samples, parent, 1, checked, CLASSES, replaced, lookalikes={"letter": form[:20]})
    assert set(payload_textures(read_checkpoint(replaced), "lookalikes")) == {"letter"}


def test_warm_start_from_another_family_or_class_list_is_a_clear_error(tmp_path):
    samples = synthetic_samples(tmp_path / "images", n=3)
    parent = tmp_path / "parent.pt"
    train_detector(samples, None, 1, config(), CLASSES, parent)
    with pytest.raises(CheckpointError, match="classes: checkpoint has"):
        train_detector(samples, parent, 1, config(), ["red", "green", "cyan"], tmp_path / "x.pt")
    with pytest.raises(CheckpointError, match="family: checkpoint has 'faster_rcnn', config asks for 'fast_rcnn'"):
        train_detector(samples, parent, 1, config(family="fast_rcnn"), CLASSES, tmp_path / "y.pt")
    with pytest.raises(CheckpointError, match="does not exist"):
        train_detector(samples, tmp_path / "missing.pt", 1, config(), CLASSES, tmp_path / "z.pt")
    assert not (tmp_path / "x.pt").exists() and not (tmp_path / "y.pt").exists()


def finite_weights(path):
    return all(torch.isfinite(value).all() for value in state(path).values() if value.is_floating_point())


def inject_nan_at(monkeypatch, steps, kind="loss"):
    """Make compute_losses non-finite (its value, or only its gradient) at the given steps."""
    calls = {"n": 0}

    def patched(model, images, targets):
        losses = compute_losses(model, images, targets)
        step = calls["n"]
        calls["n"] += 1
        if step in steps:
            if kind == "loss":
                losses["loss_classifier"] = losses["loss_classifier"] * float("nan")
            else:  # finite value, non-finite gradient: d sqrt(x)/dx at x = 0 is infinite
                weight = next(p for p in model.parameters() if p.requires_grad)
                losses["poison"] = torch.sqrt((weight * 0).sum())
        return losses

    monkeypatch.setattr(training, "compute_losses", patched)


@pytest.mark.parametrize("kind", ["loss", "gradient"])
def test_nonfinite_step_is_skipped_recorded_and_halves_the_learning_rate(tmp_path, monkeypatch, kind):
    samples = synthetic_samples(tmp_path / "images")
    inject_nan_at(monkeypatch, {1, 2}, kind)
    cfg = config(lr_schedule="constant", warmup_iterations=0, learning_rate=0.02)
    stats = train_detector(samples, None, 4, cfg, CLASSES, tmp_path / "out.pt")
    assert finite_weights(tmp_path / "out.pt")
    assert [entry["step"] for entry in stats.nonfinite_steps] == [1, 2]
    assert [entry["lr"] for entry in stats.nonfinite_steps] == pytest.approx([0.02, 0.01])
    expected_reason = "non-finite loss" if kind == "loss" else "non-finite gradient"
    assert all(entry["reason"] == expected_reason for entry in stats.nonfinite_steps)
    assert set(stats.nonfinite_steps[0]["loss_terms"]) >= {"loss_classifier", "loss_box_reg"}
    assert math.isnan(stats.losses[1]) and math.isnan(stats.losses[2])
    assert math.isfinite(stats.losses[0]) and math.isfinite(stats.losses[3])
    assert math.isfinite(stats.final_loss)
    as_json = json.loads(json.dumps(stats.to_dict(), allow_nan=False))  # strict JSON: nan → null
    assert as_json["losses"][1] is None


def test_skipped_step_leaves_weights_and_batchnorm_statistics_untouched(tmp_path, monkeypatch):
    samples = synthetic_samples(tmp_path / "images")
    train_detector(samples, None, 0, config(), CLASSES, tmp_path / "start.pt", seed=3)

    def poisoned(model, images, targets):
        return compute_losses(model, [image * float("nan") for image in images], targets)

    monkeypatch.setattr(training, "compute_losses", poisoned)
    stats = train_detector(
        samples, tmp_path / "start.pt", 2, config(max_nonfinite_steps=2), CLASSES, tmp_path / "out.pt"
    )
    assert len(stats.nonfinite_steps) == 2
    assert_same_state(state(tmp_path / "start.pt"), state(tmp_path / "out.pt"))


def test_repeated_nonfinite_steps_raise_training_diverged(tmp_path, monkeypatch):
    samples = synthetic_samples(tmp_path / "images", n=3)
    inject_nan_at(monkeypatch, set(range(100)))
    with pytest.raises(TrainingDiverged, match=r"3 non-finite steps .*max_nonfinite_steps = 2"):
        train_detector(samples, None, 10, config(max_nonfinite_steps=2), CLASSES, tmp_path / "out.pt")
    assert not (tmp_path / "out.pt").exists()
    with pytest.raises(TrainingDiverged, match="1 non-finite steps"):
        train_detector(samples, None, 10, config(max_nonfinite_steps=0), CLASSES, tmp_path / "out.pt")


def test_images_without_objects_train(tmp_path):
    samples = synthetic_samples(tmp_path / "images", n=3, empty=True)
    stats = train_detector(samples, None, 2, config(), CLASSES, tmp_path / "out.pt")
    assert all(math.isfinite(v) for v in stats.losses)
    assert finite_weights(tmp_path / "out.pt")


def test_zero_iterations_writes_the_initial_model(tmp_path):
    stats = train_detector([], None, 0, config(), CLASSES, tmp_path / "init.pt")
    assert stats.iterations == 0 and stats.losses == [] and math.isnan(stats.final_loss)
    assert read_checkpoint(tmp_path / "init.pt")["meta"]["iterations"] == 0


def test_bad_training_input_is_rejected_before_work(tmp_path):
    samples = synthetic_samples(tmp_path / "images", n=2)
    with pytest.raises(ValueError, match="S_tr is empty"):
        train_detector([], None, 1, config(), CLASSES, tmp_path / "o.pt")
    with pytest.raises(ValueError, match="outside 0..1"):
        train_detector(
            [Sample(samples[0].image_path, [[1, 1, 5, 5]], [2])], None, 1, config(), ["red", "green"], tmp_path / "o.pt"
        )
    with pytest.raises(ValueError, match="degenerate"):
        train_detector(
            [Sample(samples[0].image_path, [[5, 5, 5, 9]], [0])], None, 1, config(), CLASSES, tmp_path / "o.pt"
        )
    with pytest.raises(ValueError, match="0.png.*outside the 64x64 image"):
        train_detector(
            [Sample(samples[0].image_path, [[40, 5, 70, 9]], [0])], None, 1, config(), CLASSES, tmp_path / "o.pt"
        )
    with pytest.raises(ValueError, match="duplicates"):
        train_detector(samples, None, 1, config(), ["a", "a", "b"], tmp_path / "o.pt")
    with pytest.raises(ValueError, match="iterations"):
        train_detector(samples, None, -1, config(), CLASSES, tmp_path / "o.pt")
    assert not (tmp_path / "o.pt").exists()


def test_num_threads_is_applied_during_training_and_restored(tmp_path, monkeypatch):
    samples = synthetic_samples(tmp_path / "images", n=2)
    seen = []
    original = training.compute_losses

    def spy(model, images, targets):
        seen.append(torch.get_num_threads())
        return original(model, images, targets)

    monkeypatch.setattr(training, "compute_losses", spy)
    torch.set_num_threads(2)
    try:
        train_detector(samples, None, 1, config(num_threads=1), CLASSES, tmp_path / "o.pt")
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)


def test_learning_rate_warms_up_then_decays():
    cfg = config(learning_rate=0.1, warmup_iterations=10, lr_schedule="cosine", min_lr_fraction=0.05)
    rates = [learning_rate_at(step, 100, cfg) for step in range(100)]
    assert rates[0] == pytest.approx(1e-4)
    assert rates[10] == pytest.approx(0.1)
    assert rates[-1] == pytest.approx(0.005)
    assert all(a <= b for a, b in itertools.pairwise(rates[:11]))
    assert all(a >= b for a, b in itertools.pairwise(rates[10:]))
    constant = config(learning_rate=0.1, warmup_iterations=0, lr_schedule="constant")
    assert {learning_rate_at(step, 50, constant) for step in range(50)} == {0.1}
    assert learning_rate_at(0, 1, cfg) == pytest.approx(0.1)  # one step: no room for warm-up


def test_batches_are_seeded_draws_with_replacement():
    a = sample_batches(5, 200, 4, seed=3)
    assert a.shape == (200, 4) and a.min() >= 0 and a.max() <= 4
    assert np.array_equal(a, sample_batches(5, 200, 4, seed=3))
    assert not np.array_equal(a, sample_batches(5, 200, 4, seed=4))
    assert set(np.unique(a)) == set(range(5))


def test_train_stats_to_dict_is_json():
    stats = TrainStats(
        2, 1.5, 8, float("nan"), [{"step": 0, "loss_terms": {"a": float("inf")}, "lr": 0.1}], "cpu", [float("nan"), 1.0]
    )
    data = json.loads(json.dumps(stats.to_dict(), allow_nan=False))
    assert data["final_loss"] is None and data["losses"] == [None, 1.0]
    assert data["nonfinite_steps"][0]["loss_terms"]["a"] is None


@pytest.mark.parametrize("family", ["faster_rcnn", "fast_rcnn"])
def test_loss_falls_from_random_initialisation(tmp_path, family):
    samples = synthetic_samples(tmp_path / "images", n=6)
    stats = train_detector(
        samples, None, 40, config(family=family, learning_rate=0.02), CLASSES, tmp_path / "out.pt", seed=0
    )
    assert stats.nonfinite_steps == []
    assert np.mean(stats.losses[-10:]) < 0.75 * np.mean(stats.losses[:5])


def test_training_waits_for_room_and_writes_the_checkpoint_it_trained(tmp_path, monkeypatch):
    """When the volume has no room for ω, train_detector asks on_no_room to wait and writes the
    weights it trained once there is room (tests/workers/train/test_checkpoint_writes.py: the
    write itself and the worker's waiting)."""
    samples = synthetic_samples(tmp_path / "images", n=2)
    out = tmp_path / "omega.pt"
    real_write, refusals = os.write, []

    def full_until_told(descriptor, data):
        if len(refusals) < 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(descriptor, data)

    def wait_for_room(error):
        assert error.errno == errno.ENOSPC and not out.exists()
        refusals.append(str(error))

    monkeypatch.setattr(checkpoint_module.os, "write", full_until_told)
    # No iteration: the network built and written, which is what this is about.
    train_detector(samples, None, 0, config(), CLASSES, out, on_no_room=wait_for_room)
    assert len(refusals) == 2 and "no room on the volume" in refusals[0]
    assert read_checkpoint(out)["meta"]["classes"] == CLASSES

    # Nobody to wait: the refusal is the caller's.
    refusals.clear()
    with pytest.raises(NoRoomError):
        train_detector(samples, None, 0, config(), CLASSES, tmp_path / "lost.pt")
    assert not (tmp_path / "lost.pt").exists()
