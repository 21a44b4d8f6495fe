"""Edge Boxes proposals from gradient edges, and their per-image cache."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchvision.ops import box_iou

from workers.train.detectors.edge_boxes import ProposalCache, edge_box_proposals, edge_maps


def textured_rectangle(size=96, box=(20, 30, 70, 80), seed=0):
    """A striped, coloured rectangle on mild noise; returns (image, box xyxy)."""
    rng = np.random.default_rng(seed)
    image = rng.integers(90, 140, (size, size, 3)).astype(np.uint8)
    x0, y0, x1, y1 = box
    yy, xx = np.mgrid[y0:y1, x0:x1]
    stripes = ((xx // 6 + yy // 6) % 2).astype(np.uint8)
    image[y0:y1, x0:x1] = np.stack([230 * stripes + 20, 40 + 0 * stripes, 200 - 150 * stripes], axis=-1)
    return image, np.array([box], np.float32)


def test_proposals_are_valid_boxes_and_one_covers_the_object():
    image, truth = textured_rectangle()
    boxes = edge_box_proposals(image, max_boxes=50)
    assert boxes.dtype == np.float32 and boxes.ndim == 2 and boxes.shape[1] == 4
    assert 2 <= len(boxes) <= 50
    assert np.all(boxes[:, 2] > boxes[:, 0]) and np.all(boxes[:, 3] > boxes[:, 1])
    assert boxes.min() >= 0 and boxes[:, [0, 2]].max() <= 96 and boxes[:, [1, 3]].max() <= 96
    np.testing.assert_array_equal(boxes[-1], [0, 0, 96, 96])  # the whole image, always last
    assert box_iou(torch.from_numpy(truth), torch.from_numpy(boxes)).max() > 0.7


def test_proposals_are_deterministic_and_respect_max_boxes():
    image, _ = textured_rectangle(seed=3)
    np.testing.assert_array_equal(edge_box_proposals(image, 30), edge_box_proposals(image, 30))
    assert len(edge_box_proposals(image, 5)) <= 5
    np.testing.assert_array_equal(edge_box_proposals(image, 1), [[0, 0, 96, 96]])
    with pytest.raises(ValueError, match="max_boxes"):
        edge_box_proposals(image, 0)


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((96, 96, 3), np.uint8),  # flat black: no edge at all
        np.full((40, 70, 3), 255, np.uint8),
        np.zeros((1, 1, 3), np.uint8),
        np.zeros((2, 3, 3), np.uint8),
        np.random.default_rng(0).integers(0, 256, (5, 7, 3)).astype(np.uint8),
        np.random.default_rng(0).integers(0, 256, (9, 200, 3)).astype(np.uint8),  # thin strip
    ],
    ids=["black", "white", "1x1", "2x3", "5x7-noise", "9x200-noise"],
)
def test_degenerate_images_give_at_least_the_whole_image(image):
    height, width = image.shape[:2]
    boxes = edge_box_proposals(image)
    assert len(boxes) >= 1
    np.testing.assert_array_equal(boxes[-1], [0, 0, width, height])
    assert np.all(boxes[:, 2] > boxes[:, 0]) and np.all(boxes[:, 3] > boxes[:, 1])
    assert np.all(np.isfinite(boxes))


def test_bad_image_shape_is_an_error():
    with pytest.raises(ValueError, match="expected an"):
        edge_box_proposals(np.zeros((0, 5, 3), np.uint8))


def test_edge_maps_magnitude_and_orientation_conventions():
    image = np.zeros((32, 32, 3), np.uint8)
    image[:, 16:] = 255  # a vertical edge: the gradient points along x
    magnitude, orientation = edge_maps(image)
    assert magnitude.dtype == np.float32 and magnitude.min() >= 0 and magnitude.max() == pytest.approx(1.0)
    assert orientation.min() >= 0 and orientation.max() < np.pi
    columns = np.nonzero(magnitude[16] > 0.5)[0]
    assert set(columns) <= {15, 16}, "non-maximum suppression leaves a thin edge"
    edge_orientation = orientation[16, columns[0]]
    assert min(edge_orientation, np.pi - edge_orientation) < 0.05


def test_cache_hits_memory_then_file_and_notices_changed_pixels(tmp_path):
    image, _ = textured_rectangle(seed=5)
    path = tmp_path / "image.png"
    cache = ProposalCache(max_boxes=40)
    first = cache.proposals(image, path)
    assert (cache.misses, cache.hits) == (1, 0)
    assert ProposalCache.cache_path(path).is_file()
    again = cache.proposals(image, path)
    assert cache.hits == 1 and cache.misses == 1
    np.testing.assert_array_equal(first, again)
    assert not again.flags.writeable  # shared cache entries cannot be edited by a caller

    fresh = ProposalCache(max_boxes=40)  # a new process: memory empty, the file beside the image serves
    np.testing.assert_array_equal(fresh.proposals(image, path), first)
    assert (fresh.file_hits, fresh.misses) == (1, 0)

    changed = image.copy()
    changed[:10] = 0  # same path, other pixels: the stored key no longer matches
    fresh.proposals(changed, path)
    assert fresh.misses == 1

    other_budget = ProposalCache(max_boxes=10)  # another proposal budget never reuses the file
    assert len(other_budget.proposals(image, path)) <= 10
    assert other_budget.misses == 1


def test_cache_without_path_and_lru_capacity():
    cache = ProposalCache(max_boxes=20, capacity=2)
    images = [textured_rectangle(size=48, box=(5, 5, 30 + i, 30), seed=i)[0] for i in range(3)]
    for image in images:
        cache.proposals(image)
    assert cache.misses == 3
    cache.proposals(images[0])  # evicted by the third image
    assert cache.misses == 4
    cache.proposals(images[2])
    assert cache.hits == 1
    cache.clear()  # bench/train.py times inference on images the cache has not seen
    cache.proposals(images[2])
    assert (cache.hits, cache.misses) == (1, 5)


def test_unwritable_folder_only_disables_the_file(tmp_path):
    image, _ = textured_rectangle(seed=7)
    missing_folder = tmp_path / "does" / "not" / "exist" / "image.png"
    boxes = ProposalCache(max_boxes=20).proposals(image, missing_folder)
    assert len(boxes) >= 1
    assert not ProposalCache.cache_path(missing_folder).exists()
