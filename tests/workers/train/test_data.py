"""load_coco_dataset: the dataset folder of `foldwise render --out DIR`, checked box by box."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from workers.train.data import DatasetError, Sample, as_rgb_uint8, load_coco_dataset, read_image_rgb


def write_dataset(root, images, annotations, categories, size=(48, 64)):
    """A COCO dataset folder; every image listed in `images` gets a PNG of `size` (h, w)."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    entries = []
    for image_id, name, extra in images:
        cv2.imwrite(str(root / "images" / f"{name}.png"), np.zeros((*size, 3), np.uint8))
        entries.append(
            {"id": image_id, "file_name": f"images/{name}.png", "width": size[1], "height": size[0], **extra}
        )
    document = {"images": entries, "annotations": annotations, "categories": categories}
    (root / "annotations.json").write_text(json.dumps(document))
    return root


def annotation(ann_id, image_id, category_id, bbox, **extra):
    return {"id": ann_id, "image_id": image_id, "category_id": category_id, "bbox": bbox, "iscrowd": 0, **extra}


def test_loads_boxes_as_xyxy_with_zero_based_labels_in_category_id_order(tmp_path):
    categories = [{"id": 2, "name": "coffee"}, {"id": 1, "name": "astronaut"}]  # listed out of order
    root = write_dataset(
        tmp_path,
        [(10, "a", {"condition": "fb", "difficulty": "easy"}), (11, "b", {}), (12, "empty", {})],
        [
            annotation(1, 10, 2, [4, 5, 10, 20]),
            annotation(2, 11, 1, [0, 0, 64, 48]),  # the whole image is a valid box
            annotation(3, 11, 2, [1.5, 2.5, 3, 4], iscrowd=1),  # iscrowd is ignored: still a target
        ],
        categories,
    )
    samples, classes = load_coco_dataset(root)
    assert classes == ["astronaut", "coffee"]
    assert [s.image_path.name for s in samples] == ["a.png", "b.png", "empty.png"]
    first, second, empty = samples
    np.testing.assert_array_equal(first.boxes, [[4, 5, 14, 25]])
    assert first.boxes.dtype == np.float32 and first.labels.dtype == np.int64
    assert first.labels.tolist() == [1]
    assert (first.condition, first.difficulty) == ("fb", "easy")
    np.testing.assert_allclose(second.boxes, [[0, 0, 64, 48], [1.5, 2.5, 4.5, 6.5]])
    assert second.labels.tolist() == [0, 1]
    assert second.condition is None
    assert empty.boxes.shape == (0, 4) and empty.labels.shape == (0,)
    assert all(s.image_path.is_file() for s in samples)


@pytest.mark.parametrize(
    "bbox, problem",
    [
        ([5, 5, 0, 10], "degenerate"),
        ([5, 5, 10, -1], "degenerate"),
        ([60, 5, 10, 10], "outside"),
        ([-2, 5, 10, 10], "outside"),
        ([5, 45, 10, 10], "outside"),
        ([float("nan"), 5, 10, 10], "not finite"),
    ],
)
def test_bad_box_is_an_error_naming_the_image(tmp_path, bbox, problem):
    root = write_dataset(
        tmp_path, [(1, "ok", {}), (2, "culprit", {})], [annotation(1, 2, 1, bbox)], [{"id": 1, "name": "x"}]
    )
    with pytest.raises(DatasetError, match=problem) as error:
        load_coco_dataset(root)
    assert "images/culprit.png" in str(error.value)


def test_missing_pieces_are_clear_errors(tmp_path):
    with pytest.raises(DatasetError, match="no annotations.json"):
        load_coco_dataset(tmp_path)

    root = write_dataset(tmp_path / "d1", [(1, "a", {})], [annotation(1, 1, 7, [1, 1, 2, 2])], [{"id": 1, "name": "x"}])
    with pytest.raises(DatasetError, match="unknown category_id 7"):
        load_coco_dataset(root)

    root = write_dataset(
        tmp_path / "d2", [(1, "a", {})], [annotation(1, 99, 1, [1, 1, 2, 2])], [{"id": 1, "name": "x"}]
    )
    with pytest.raises(DatasetError, match="unknown image id 99"):
        load_coco_dataset(root)

    root = write_dataset(tmp_path / "d3", [(1, "gone", {})], [], [{"id": 1, "name": "x"}])
    (root / "images" / "gone.png").unlink()
    with pytest.raises(DatasetError, match="gone.png"):
        load_coco_dataset(root)

    (tmp_path / "d4").mkdir()
    (tmp_path / "d4" / "annotations.json").write_text("{not json")
    with pytest.raises(DatasetError, match="not valid JSON"):
        load_coco_dataset(tmp_path / "d4")


def test_sample_coerces_arrays_and_rejects_mismatched_lengths(tmp_path):
    sample = Sample(str(tmp_path / "x.png"), [[1, 2, 3, 4]], [0])
    assert sample.boxes.dtype == np.float32 and sample.boxes.shape == (1, 4)
    assert sample.labels.dtype == np.int64
    empty = Sample(tmp_path / "y.png", np.zeros((0, 4)), [])
    assert empty.boxes.shape == (0, 4)
    with pytest.raises(DatasetError, match="2 boxes but 1 labels"):
        Sample(tmp_path / "z.png", [[1, 2, 3, 4], [1, 2, 3, 4]], [0])


def test_images_are_read_as_rgb(tmp_path):
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 2] = 200  # red in OpenCV's BGR order
    cv2.imwrite(str(tmp_path / "red.png"), bgr)
    rgb = read_image_rgb(tmp_path / "red.png")
    assert rgb.shape == (4, 5, 3) and rgb.dtype == np.uint8
    assert rgb[0, 0].tolist() == [200, 0, 0]
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(DatasetError, match="cannot read image"):
        read_image_rgb(tmp_path / "junk.png")


def test_as_rgb_uint8_checks_shape_and_type():
    assert as_rgb_uint8(np.zeros((3, 4), np.uint8)).shape == (3, 4, 3)
    with pytest.raises(DatasetError, match="uint8"):
        as_rgb_uint8(np.zeros((3, 4, 3), np.float32))
    with pytest.raises(DatasetError, match="RGB"):
        as_rgb_uint8(np.zeros((3, 4, 4), np.uint8))
