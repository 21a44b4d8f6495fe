"""PyramidRoIAlign: torchvision's values and gradients, from a gather whose backward is cheap."""

from __future__ import annotations

from collections import OrderedDict

import pytest
import torch
from torchvision.ops import MultiScaleRoIAlign

from workers.train.detectors.roi_align import PyramidRoIAlign

# Large enough that boxes reach every level (torchvision maps a 224 px box to stride 16).
IMAGE = (512, 512)


def pyramid(seed: int, channels: int = 6) -> OrderedDict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    # Strides 8, 16, 32 of the image, two images, as the R-CNNs' pyramids are.
    return OrderedDict(
        (name, torch.randn(2, channels, size, size, generator=generator).requires_grad_())
        for name, size in (("0", 64), ("1", 32), ("2", 16))
    )


def boxes_of_every_kind(seed: int) -> list[torch.Tensor]:
    """Per image: boxes of every size (so every level is read), boxes poking past the image,
    thinner than a feature pixel, and at the far edge of the map."""
    generator = torch.Generator().manual_seed(seed)
    per_image = []
    for _ in range(2):
        corner = torch.rand(60, 2, generator=generator) * 540 - 20
        size = torch.rand(60, 2, generator=generator) ** 2 * 520 + 0.2
        edge = torch.tensor([[500.0, 500.0, 512.0, 512.0], [0.0, 0.0, 0.5, 511.9], [511.0, 3.0, 511.5, 3.2]])
        per_image.append(torch.cat([torch.cat([corner, corner + size], 1), edge]))
    return per_image


@pytest.mark.parametrize("sampling_ratio", [1, 2, 3])
def test_values_and_gradients_are_torchvisions(sampling_ratio):
    names = ["0", "1", "2"]
    ours = PyramidRoIAlign(names, 7, sampling_ratio).train()
    theirs = MultiScaleRoIAlign(names, 7, sampling_ratio)
    features = pyramid(0)
    boxes = boxes_of_every_kind(1)

    expected = theirs(features, boxes, [IMAGE, IMAGE])
    assert set(theirs.map_levels(boxes).tolist()) == {0, 1, 2}  # every level is read
    weight = torch.randn(expected.shape, generator=torch.Generator().manual_seed(2))
    expected_grads = torch.autograd.grad((expected * weight).sum(), list(features.values()))

    got = ours(features, boxes, [IMAGE, IMAGE])
    got_grads = torch.autograd.grad((got * weight).sum(), list(features.values()))

    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-4)
    for mine, reference in zip(got_grads, expected_grads):
        assert reference.abs().sum() > 0
        torch.testing.assert_close(mine, reference, rtol=1e-4, atol=1e-4)


def test_the_gather_runs_only_where_it_is_needed(monkeypatch):
    """Inference, no-grad passes and adaptive sampling are torchvision's own kernel."""
    import workers.train.detectors.roi_align as module

    calls = []
    real = module.pyramid_roi_align
    monkeypatch.setattr(module, "pyramid_roi_align", lambda *a, **k: calls.append(1) or real(*a, **k))
    features, boxes = pyramid(3), boxes_of_every_kind(4)

    PyramidRoIAlign(["0", "1", "2"], 7, 1).eval()(features, boxes, [IMAGE, IMAGE])
    with torch.no_grad():
        PyramidRoIAlign(["0", "1", "2"], 7, 1).train()(features, boxes, [IMAGE, IMAGE])
    PyramidRoIAlign(["0", "1", "2"], 7, 0).train()(features, boxes, [IMAGE, IMAGE])
    assert calls == []
    PyramidRoIAlign(["0", "1", "2"], 7, 1).train()(features, boxes, [IMAGE, IMAGE])
    assert calls == [1]


def test_no_boxes_pools_nothing_and_passes_no_gradient():
    features = pyramid(5)
    empty = [torch.zeros((0, 4)), torch.zeros((0, 4))]
    pooled = PyramidRoIAlign(["0", "1", "2"], 7, 1).train()(features, empty, [IMAGE, IMAGE])
    assert pooled.shape == (0, 6, 7, 7)
    grads = torch.autograd.grad(pooled.sum(), list(features.values()), allow_unused=True)
    assert all(g is None or not g.any() for g in grads)


def test_one_level_maps_every_box_to_it():
    features = OrderedDict([("0", torch.randn(2, 4, 64, 64, requires_grad=True))])
    boxes = boxes_of_every_kind(6)
    expected = MultiScaleRoIAlign(["0"], (5, 3), 2)(features, boxes, [IMAGE, IMAGE])
    got = PyramidRoIAlign(["0"], (5, 3), 2).train()(features, boxes, [IMAGE, IMAGE])
    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-4)
