"""render_theta / render_with_resample: determinism, exact boxes, skipped stages, rejections,
resampling, backends, assets."""

from __future__ import annotations

import types

import cv2
import numpy as np
import pytest

from foldwise.sampling import derive_seed, generate_parameters
from workers.render import blur, occluders, pipeline
from workers.render.annotation import tight_box
from workers.render.assets import AssetError, load_assets
from workers.render.pipeline import RenderRejected, render_theta, render_with_resample

SIZE = 64


def one(condition, difficulty="hard", seed=0, size=SIZE, **override):
    theta = generate_parameters(condition, difficulty, 1, seed=seed, image_size=size)[0]
    return theta.replace(**override) if override else theta


@pytest.mark.parametrize("condition", ["fb", "mb", "po", "de", "eo", "sc", "li"])
def test_same_theta_gives_identical_bytes_and_box(condition):
    theta = one(condition, seed=2)
    first, used, _ = render_with_resample(theta)
    second = render_theta(dict(used))
    assert first.image.dtype == np.uint8 and first.image.shape == (SIZE, SIZE, 3)
    assert first.image.tobytes() == second.image.tobytes()
    assert first.box == second.box and first.amodal_box == second.amodal_box
    assert first.visible_fraction == second.visible_fraction
    assert first.label == used.label


def test_tight_box_is_in_pixel_edges_and_none_for_an_empty_mask():
    rng = np.random.default_rng(4)
    for _ in range(20):
        mask = np.zeros((37, 53), bool)
        r0, c0 = rng.integers(0, 30), rng.integers(0, 40)
        mask[r0 : r0 + rng.integers(1, 8), c0 : c0 + rng.integers(1, 14)] = True
        mask &= rng.random(mask.shape) < 0.7
        if not mask.any():
            continue
        rows, cols = np.nonzero(mask)
        assert tight_box(mask) == [cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]
        assert tight_box(mask[:, ::-1]) == [53 - cols.max() - 1, rows.min(), 53 - cols.min(), rows.max() + 1]  # a view
    assert tight_box(np.zeros((5, 5), bool)) is None
    assert tight_box(np.ones((1, 1), bool)) == [0.0, 0.0, 1.0, 1.0]


@pytest.mark.parametrize("condition, difficulty", [("eo", "medium"), ("po", "hard"), ("sc", "hard"), ("de", "hard")])
def test_box_is_the_tight_box_of_the_visible_mask(condition, difficulty):
    for seed in range(3):
        result, _, _ = render_with_resample(one(condition, difficulty, seed=seed))
        assert result.mask.shape == (SIZE, SIZE)
        assert result.box == tight_box(result.mask)
        x0, y0, x1, y1 = result.box
        assert 0 <= x0 < x1 <= SIZE and 0 <= y0 < y1 <= SIZE
        ax0, ay0, ax1, ay1 = result.amodal_box
        assert ax0 <= x0 and ay0 <= y0 and ax1 >= x1 and ay1 >= y1
        assert 0 < result.visible_fraction <= 1


def test_occlusion_hits_the_sampled_visible_fraction():
    for theta in generate_parameters("eo", "medium", 6, seed=9, image_size=SIZE):
        result = render_theta(theta)
        assert result.visible_fraction == pytest.approx(theta.visible_fraction, abs=0.03)
        unoccluded = render_theta(theta.replace(visible_fraction=1.0, occluder=None)).mask
        assert not (result.mask & ~unoccluded).any()
        assert result.mask.sum() / unoccluded.sum() == pytest.approx(result.visible_fraction)


def test_background_fills_everything_outside_the_sheet():
    assets = load_assets()
    theta = one("fb", "canonical", seed=4)
    result = render_theta(theta, assets=assets)
    background = assets.background(theta.background, SIZE, np.random.default_rng(derive_seed(theta.seed, 2)))
    outside = ~cv2.dilate(result.mask.astype(np.uint8), None).astype(bool)  # beyond the soft edge
    assert np.array_equal(result.image[outside], background[outside])
    assert not np.array_equal(result.image[result.mask], background[result.mask])


def test_canonical_stages_do_no_work(monkeypatch):
    def forbidden(*args, **kwargs):
        raise AssertionError("a canonical stage did work")

    for module, name in ((blur, "focus_blur"), (blur, "motion_blur"), (occluders, "place_occluder")):
        monkeypatch.setattr(module, name, forbidden)
    monkeypatch.setattr(cv2, "GaussianBlur", forbidden)
    monkeypatch.setattr(cv2, "filter2D", forbidden)
    for condition in ("po", "de", "sc", "li"):  # conditions that need none of the 2D stages
        result, _, _ = render_with_resample(one(condition, "hard", seed=1))
        assert not {"focus_blur", "motion_blur", "occlusion"} & set(result.timings)
    result = render_theta(one("fb", "canonical"))
    assert {"sheet", "scene", "render", "annotation", "background", "total"} <= set(result.timings)
    # The same patches do catch a stage that runs: the test can fail.
    with pytest.raises(AssertionError, match="canonical stage"):
        render_theta(one("fb", "hard"))


def test_timings_cover_the_stages_that_ran():
    result = render_theta(one("mb", "hard"))
    assert "motion_blur" in result.timings and "focus_blur" not in result.timings
    assert result.timings["total"] >= sum(v for k, v in result.timings.items() if k != "total") * 0.99
    result = render_theta(one("eo", "hard"))
    assert "occlusion" in result.timings


def test_self_intersection_is_a_rejection(monkeypatch):
    from workers.render import paper_model

    def intersecting(*args, **kwargs):
        raise paper_model.SelfIntersection("regions 1 and 3 cross")

    monkeypatch.setattr(
        pipeline,
        "_paper_model",
        lambda: types.SimpleNamespace(sample_sheet=intersecting, SelfIntersection=paper_model.SelfIntersection),
    )
    with pytest.raises(RenderRejected) as caught:
        render_theta(one("de", "hard"))
    assert "self-intersecting" in caught.value.reason
    with pytest.raises(RenderRejected) as caught:
        render_with_resample(one("de", "hard"), max_resamples=3)
    assert len(caught.value.reasons) == 4
    assert all("self-intersecting" in reason for reason in caught.value.reasons)


def test_rejected_theta_is_resampled_deterministically_with_reasons():
    theta = one("po", "hard", seed=5, position_offset_m=40.0)  # far out of view
    with pytest.raises(RenderRejected, match="outside the view"):
        render_theta(theta)
    result, used, reasons = render_with_resample(theta)
    assert reasons and "outside the view" in reasons[0]
    assert used.resample == len(reasons)
    assert used.seed == derive_seed(theta.seed, len(reasons))
    assert used.object == theta.object and used.condition == "po"
    again, used_again, reasons_again = render_with_resample(theta)
    assert used_again == used and reasons_again == reasons
    assert again.image.tobytes() == result.image.tobytes()
    with pytest.raises(RenderRejected) as caught:
        render_with_resample(theta, max_resamples=0)
    assert caught.value.reasons == reasons[:1]


def test_bad_requests_are_errors_not_rejections():
    theta = one("po", "easy")
    with pytest.raises(ValueError, match="unknown backend 'povray'"):
        render_theta(theta, backend="povray")
    with pytest.raises(ValueError, match="label"):
        render_theta(theta.replace(label=(theta.label + 1) % 5))
    with pytest.raises(AssetError, match="unknown object 'teapot'"):
        render_theta(theta.replace(object="teapot"))
    with pytest.raises(ValueError, match="occluder"):
        render_theta(one("eo", "easy").replace(occluder=None))


def test_blender_backend_is_reached_through_get_renderer(monkeypatch):
    from workers.render import blender, raster

    calls = []

    class FakeRenderer:
        def render(self, scene):
            calls.append(scene)
            return raster.render_scene(scene)

    monkeypatch.setattr(blender, "get_renderer", lambda samples=16, device="CPU": FakeRenderer())
    theta = one("li", "hard")
    through_blender = render_theta(theta, backend="blender", samples=4)
    assert len(calls) == 1
    assert through_blender.image.tobytes() == render_theta(theta).image.tobytes()


# -- assets -----------------------------------------------------------------------------------


def _write(path, image):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)


def test_user_asset_folders(tmp_path):
    from foldwise.config import AssetsConfig

    rng = np.random.default_rng(0)
    _write(tmp_path / "objects" / "label_a.png", rng.integers(0, 255, (40, 60, 3), dtype=np.uint8))
    _write(tmp_path / "objects" / "label_b.jpg", rng.integers(0, 255, (50, 30, 3), dtype=np.uint8))
    _write(tmp_path / "backgrounds" / "sub" / "wall.png", rng.integers(0, 255, (80, 90), dtype=np.uint8))
    (tmp_path / "backgrounds" / "notes.txt").write_text("not an image, ignored")
    star = np.zeros((30, 30, 4), np.uint8)
    star[8:22, 8:22] = (0, 0, 255, 255)  # an opaque red square in a transparent frame (BGRA)
    _write(tmp_path / "occluders" / "square.png", star)
    assets = load_assets(
        AssetsConfig(
            objects=tmp_path / "objects", backgrounds=tmp_path / "backgrounds", occluders=tmp_path / "occluders"
        )
    )
    assert assets.classes == ["label_a", "label_b"]
    assert [a.name for a in assets.backgrounds] == ["sub/wall.png"]
    rgb, alpha = assets.occluder("square.png")
    assert alpha is not None and alpha[0, 0] == 0 and alpha[15, 15] == 255
    assert tuple(rgb[15, 15]) == (255, 0, 0)
    theta = generate_parameters("eo", "medium", 1, seed=0, image_size=SIZE, assets=assets)[0]
    result = render_theta(theta, assets=assets)
    assert result.visible_fraction == pytest.approx(theta.visible_fraction, abs=0.05)
    assert load_assets(AssetsConfig(objects=tmp_path / "objects")) is load_assets(
        AssetsConfig(objects=tmp_path / "objects")
    )


def test_an_occluder_that_cannot_hide_enough_is_a_rejection(tmp_path):
    from foldwise.config import AssetsConfig

    _write(tmp_path / "occluders" / "glass.png", np.zeros((20, 20, 4), np.uint8))  # fully transparent
    assets = load_assets(AssetsConfig(occluders=tmp_path / "occluders"))
    theta = generate_parameters("eo", "hard", 1, seed=0, image_size=SIZE, assets=assets)[0]
    with pytest.raises(RenderRejected, match="cannot hide the asked share"):
        render_theta(theta, assets=assets)


def test_asset_errors_name_the_folder_or_file(tmp_path):
    from foldwise.config import AssetsConfig

    (tmp_path / "empty").mkdir()
    with pytest.raises(AssetError, match="holds no images"):
        load_assets(AssetsConfig(backgrounds=tmp_path / "empty"))
    with pytest.raises(AssetError, match="does not exist"):
        load_assets(AssetsConfig(occluders=tmp_path / "missing"))
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "cover.png").write_bytes(b"this is not a PNG")
    with pytest.raises(AssetError, match="cannot read image .*cover.png"):
        load_assets(AssetsConfig(objects=broken))
