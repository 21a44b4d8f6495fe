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


# --------------------------------------------------------------------------- photographs

import photo_sets  # noqa: E402  (tests/workers/train is on sys.path)

from workers.train import data  # noqa: E402
from workers.train.data import load_dataset  # noqa: E402


@pytest.mark.parametrize("export", ["coco", "voc"])
def test_portrait_landscape_and_exif_turned_photos_load_with_exact_boxes(tmp_path, export):
    photos = photo_sets.photos(9)
    assert {p.orientation for p in photos} == {1, 3, 6, 8}
    assert {p.pixels.shape[0] > p.pixels.shape[1] for p in photos} == {True, False}
    where = photo_sets.write_coco(tmp_path, photos) if export == "coco" else photo_sets.write_voc(tmp_path, photos)
    samples, classes = load_dataset(where)
    assert classes == photo_sets.CLASSES or export == "voc"
    by_name = {s.image_path.stem: s for s in samples}
    for photo in photos:
        sample = by_name[photo.name]
        np.testing.assert_array_equal(
            read_image_rgb(sample.image_path), photo_sets.decoded(photo)
        )  # as displayed, exactly
        np.testing.assert_array_equal(sample.boxes, photo.boxes)
        assert [classes[i] for i in sample.labels] == [photo_sets.CLASSES[i] for i in photo.labels]


def test_a_large_photo_is_shrunk_on_load_and_its_boxes_scaled(tmp_path, monkeypatch):
    monkeypatch.setattr(data, "PHOTO_MAX_SIDE", 40)
    photos = photo_sets.photos(3)  # 80 x 48, 48 x 80, 64 x 64 (stored turned)
    samples, _ = load_dataset(photo_sets.write_coco(tmp_path, photos))
    for photo, sample in zip(photos, samples):
        pixels = read_image_rgb(sample.image_path)
        height, width = photo.pixels.shape[:2]
        assert max(pixels.shape[:2]) == 40
        ratio = np.array([pixels.shape[1] / width, pixels.shape[0] / height] * 2, np.float32)
        np.testing.assert_allclose(sample.boxes, photo.boxes * ratio, rtol=1e-6)
        x0, y0, x1, y1 = (int(round(v)) for v in sample.boxes[0])
        inside = pixels[y0 + 1 : y1 - 1, x0 + 1 : x1 - 1].reshape(-1, 3).astype(int)  # the sheet's stripes
        assert np.abs(inside - photo_sets.COLOURS[int(photo.labels[0])]).min(axis=1).mean() < 80


def test_a_photo_labelled_without_its_exif_turn_is_named(tmp_path):
    photo = photo_sets.photos(1)[0]
    path = photo_sets.write_coco(tmp_path, [photo_sets.twin(photo, 6)])
    document = json.loads(path.read_text())
    document["images"][0]["width"], document["images"][0]["height"] = 48, 80  # the stored size
    path.write_text(json.dumps(document))
    with pytest.raises(DatasetError, match="EXIF"):
        load_dataset(path)
    document["images"][0]["width"], document["images"][0]["height"] = 100, 60
    path.write_text(json.dumps(document))
    with pytest.raises(DatasetError, match="resized or replaced"):
        load_dataset(path)
    del document["images"][0]["width"], document["images"][0]["height"]  # no size: the image's own
    path.write_text(json.dumps(document))
    assert load_dataset(path)[0][0].boxes.tolist() == photo.boxes.tolist()


def test_an_image_that_is_not_one_fails_on_load_naming_it(tmp_path):
    path = photo_sets.write_coco(tmp_path, photo_sets.photos(2))
    (tmp_path / "images" / "photo01.jpg").write_bytes(b"<html>not found</html>")
    with pytest.raises(DatasetError, match=r"photo01\.jpg.*not an image"):
        load_dataset(path)


def test_labelling_tool_layouts_cvat_coco_and_label_studio_voc(tmp_path):
    """CVAT's COCO export keeps the JSON in annotations/ and the photos in images/<subset>/ (file
    names bare); Label Studio's VOC export keeps the photos in images/ instead of JPEGImages/."""
    photos = photo_sets.photos(3)
    coco = photo_sets.write_coco(tmp_path / "cvat", photos)
    document = json.loads(coco.read_text())
    (tmp_path / "cvat" / "images" / "default").mkdir()
    for image in document["images"]:
        name = image["file_name"].split("/")[-1]
        (tmp_path / "cvat" / "images" / name).rename(tmp_path / "cvat" / "images" / "default" / name)
        image["file_name"] = name
    (tmp_path / "cvat" / "annotations").mkdir()
    target = tmp_path / "cvat" / "annotations" / "instances_default.json"
    target.write_text(json.dumps(document))
    coco.unlink()
    samples, _ = load_dataset(target)
    assert [s.image_path.parent.name for s in samples] == ["default"] * 3
    np.testing.assert_array_equal(samples[2].boxes, photos[2].boxes)

    voc = photo_sets.write_voc(tmp_path / "ls", photos)
    (voc / "JPEGImages").rename(voc / "images")
    samples, _ = load_dataset(voc)
    assert [s.image_path.parent.name for s in samples] == ["images"] * 3
