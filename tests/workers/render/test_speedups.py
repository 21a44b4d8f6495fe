"""The render pipeline's speed-ups keep what they replace: per-asset caches return what a fresh
computation gives, rewritten patterns match their formulas."""

from __future__ import annotations

import numpy as np
import pytest

from workers.render import compositing, raster
from workers.render.assets import load_assets, procedural_background, random_crop
from workers.render.camera import build_scene


def test_occluders_come_back_as_the_same_read_only_arrays():
    assets = load_assets()
    for name in [asset.name for asset in assets.occluders]:
        rgb, alpha = assets.occluder(name)
        again_rgb, again_alpha = assets.occluder(name)
        assert again_rgb is rgb and again_alpha is alpha
        assert not rgb.flags.writeable and rgb.flags.c_contiguous and rgb.shape[2] == 3
        decoded = next(a for a in assets.occluders if a.name == name).load()
        assert np.array_equal(rgb, decoded[:, :, :3])
        if alpha is not None:
            assert not alpha.flags.writeable and np.array_equal(alpha, decoded[:, :, 3])


def test_an_occluder_with_alpha_comes_back_split_and_cached(tmp_path):
    import cv2

    from foldwise.config import AssetsConfig

    folder = tmp_path / "occluders"
    folder.mkdir()
    bgra = np.zeros((20, 30, 4), np.uint8)
    bgra[..., 0], bgra[..., 2], bgra[5:15, 5:25, 3] = 10, 200, 255  # blue 10, red 200, a window
    cv2.imwrite(str(folder / "window.png"), bgra)
    assets = load_assets(AssetsConfig(occluders=folder))
    rgb, alpha = assets.occluder("window.png")
    assert assets.occluder("window.png")[1] is alpha
    assert rgb.shape == (20, 30, 3) and tuple(rgb[0, 0]) == (200, 0, 10)  # RGB order
    assert alpha is not None and alpha.sum() == 255 * 10 * 20 and not alpha.flags.writeable


def test_prepared_occluder_cache_matches_a_fresh_conversion_and_skips_writable_arrays():
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    alpha = rng.integers(0, 256, (40, 60), dtype=np.uint8)
    frozen_rgb, frozen_alpha = rgb.copy(), alpha.copy()
    frozen_rgb.setflags(write=False)
    frozen_alpha.setflags(write=False)
    first = compositing._prepared_occluder(frozen_rgb, frozen_alpha, limit=30)
    cached = compositing._prepared_occluder(frozen_rgb, frozen_alpha, limit=30)
    assert cached[0] is first[0]  # a hit: the same converted array
    fresh = compositing._prepared_occluder(rgb, alpha, limit=30)  # writable: computed anew
    assert fresh[0] is not first[0]
    assert np.array_equal(fresh[0], first[0]) and np.array_equal(fresh[1].mask, first[1].mask)
    assert fresh[1].pivot == first[1].pivot  # the alpha's radial profile comes with it
    assert max(first[0].shape[:2]) == 30 and first[0].dtype == np.float32
    rgb[:] = 0  # a writable array may change between calls: nothing stale comes back
    assert not compositing._prepared_occluder(rgb, alpha, limit=30)[0].any()


@pytest.mark.parametrize("kind", ["gradient", "stripes", "checker"])
def test_two_colour_patterns_match_their_broadcast_formula(kind):
    for seed in range(6):
        image = procedural_background(kind, 48, np.random.default_rng(seed))
        # The formula as first written: a weight per pixel, colours broadcast over channels.
        rng = np.random.default_rng(seed)
        colours = rng.uniform(0, 255, size=(2, 3))
        angle = rng.uniform(0, np.pi)
        xs = (np.arange(48, dtype=np.float32) / 48)[None, :]
        ys = (np.arange(48, dtype=np.float32) / 48)[:, None]
        along = np.float32(np.cos(angle)) * xs + np.float32(np.sin(angle)) * ys
        if kind == "gradient":
            weight = (along - along.min()) / max(float(np.ptp(along)), 1e-6)
        elif kind == "stripes":
            weight = (np.sin(2 * np.pi * along / rng.uniform(0.05, 0.3)) > 0).astype(np.float32)
        else:
            across = np.float32(-np.sin(angle)) * xs + np.float32(np.cos(angle)) * ys
            period = rng.uniform(0.08, 0.3)
            weight = ((np.floor(along / period) + np.floor(across / period)) % 2).astype(np.float32)
        colours = colours.astype(np.float32)
        expected = np.clip(colours[0] + (colours[1] - colours[0]) * weight[..., None] + 0.5, 0, 255).astype(np.uint8)
        assert np.array_equal(image, expected), (kind, seed)


def test_random_crop_mirrors_like_the_mirrored_crop():
    image = np.random.default_rng(0).integers(0, 256, (90, 120, 3), dtype=np.uint8)
    mirrored = 0
    for seed in range(12):
        crop = random_crop(image, 32, np.random.default_rng(seed))
        rng = np.random.default_rng(seed)  # replay the draws
        side = max(2, int(round(90 * rng.uniform(0.4, 1.0))))
        y0, x0 = int(rng.integers(0, 90 - side + 1)), int(rng.integers(0, 120 - side + 1))
        flip = rng.random() < 0.5
        mirrored += flip
        source = image[y0:y0 + side, x0:x0 + side]
        source = np.ascontiguousarray(source[:, ::-1]) if flip else source
        import cv2

        expected = cv2.resize(source, (32, 32), interpolation=cv2.INTER_AREA)
        # Area resampling is symmetric up to OpenCV's fixed-point rounding: at most one level.
        assert np.abs(crop.astype(int) - expected).max() <= 1
    assert 0 < mirrored < 12  # both paths ran


def test_unblurred_images_composite_only_the_drawn_box_with_the_same_bytes():
    rng = np.random.default_rng(5)
    background = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    linear = rng.random((40, 50, 3), dtype=np.float32) * 1.2  # some values past white
    alpha = np.zeros((40, 50), np.float32)
    alpha[10:20, 5:30] = rng.random((10, 25), dtype=np.float32)
    occluder_alpha = np.zeros((40, 50), np.float32)
    occluder_alpha[25:35, 30:45] = 0.7
    occlusion = compositing.Occlusion(
        rgb=rng.random((40, 50, 3), dtype=np.float32) * (occluder_alpha > 0)[..., None],
        alpha=occluder_alpha, mask=occluder_alpha >= 0.5, target_fraction=0.5, achieved_fraction=0.5,
    )
    for occ in (None, occlusion):
        as_float = np.multiply(background, np.float32(1.0 / 255.0), dtype=np.float32)  # as the pipeline does
        whole = compositing.composite_object(as_float, linear, alpha)
        whole = compositing.to_uint8(whole if occ is None else compositing.composite(whole, occ.rgb, occ.alpha))
        boxed = compositing.composite_to_uint8(background, linear, alpha, occ)
        assert np.array_equal(boxed, whole)
        assert np.array_equal(boxed[:10], background[:10])  # above everything drawn: untouched
    assert np.array_equal(compositing.composite_to_uint8(background, linear, np.zeros_like(alpha)), background)
