"""The render pipeline's speed-ups keep what they replace: per-asset caches return what a fresh
computation gives, rewritten patterns match their formulas."""

from __future__ import annotations

import numpy as np
import pytest

from workers.render import compositing, occluders
from workers.render.assets import load_assets, procedural_background, random_crop


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
    first = occluders._prepared_occluder(frozen_rgb, frozen_alpha, limit=30)
    cached = occluders._prepared_occluder(frozen_rgb, frozen_alpha, limit=30)
    assert cached[0] is first[0]  # a hit: the same converted array
    fresh = occluders._prepared_occluder(rgb, alpha, limit=30)  # writable: computed anew
    assert fresh[0] is not first[0]
    assert np.array_equal(fresh[0], first[0]) and np.array_equal(fresh[1].mask, first[1].mask)
    assert fresh[1].pivot == first[1].pivot  # the alpha's radial profile comes with it
    assert max(first[0].shape[:2]) == 30 and first[0].dtype == np.float32
    rgb[:] = 0  # a writable array may change between calls: nothing stale comes back
    assert not occluders._prepared_occluder(rgb, alpha, limit=30)[0].any()


@pytest.mark.parametrize("size", [1, 17, 48, 256])
@pytest.mark.parametrize("kind", ["gradient", "stripes", "checker"])
def test_two_colour_patterns_match_their_broadcast_formula(kind, size):
    for seed in range(6 if size == 256 else 40):
        drawn = np.random.default_rng(seed)
        image = procedural_background(kind, size, drawn)
        assert image.shape == (size, size, 3) and image.dtype == np.uint8 and image.flags.c_contiguous
        # The formula as first written: a weight per pixel, colours broadcast over channels.
        rng = np.random.default_rng(seed)
        colours = rng.uniform(0, 255, size=(2, 3))
        angle = rng.uniform(0, np.pi)
        xs = (np.arange(size, dtype=np.float32) / size)[None, :]
        ys = (np.arange(size, dtype=np.float32) / size)[:, None]
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
        assert np.array_equal(image, expected), (kind, size, seed)
        assert drawn.random() == rng.random()  # the same draws, in the same order


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
        source = image[y0 : y0 + side, x0 : x0 + side]
        source = np.ascontiguousarray(source[:, ::-1]) if flip else source
        import cv2

        expected = cv2.resize(source, (32, 32), interpolation=cv2.INTER_AREA)
        # Area resampling is symmetric up to OpenCV's fixed-point rounding: at most one level.
        assert np.abs(crop.astype(int) - expected).max() <= 1
    assert 0 < mirrored < 12  # both paths ran


def _composite_as_written(background_f: np.ndarray, linear: np.ndarray, alpha: np.ndarray, occ=None) -> np.ndarray:
    """The float path as first written: OpenCV's blend of the sRGB-encoded object over the
    background inside the object's box, then of the occluder over everything."""
    import cv2

    image = background_f.copy()
    x, y, w, h = cv2.boundingRect((alpha > 0).view(np.uint8))
    if w and h:
        box = (slice(y, y + h), slice(x, x + w))
        a = np.ascontiguousarray(alpha[box])
        image[box] = cv2.blendLinear(compositing.linear_to_srgb(linear[box]), image[box], a, 1.0 - a)
    if occ is not None:
        image = cv2.blendLinear(occ.rgb, image, occ.alpha, 1.0 - occ.alpha)
    return image


def _composite_case(seed: int, height: int = 40, width: int = 50):
    rng = np.random.default_rng(seed)
    background = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    linear = rng.random((height, width, 3), dtype=np.float32) * 1.4 - 0.2  # some values past white and below black
    alpha = np.zeros((height, width), np.float32)
    alpha[10:20, 5:30] = rng.random((10, 25), dtype=np.float32)
    alpha[12:18, 8:25] = 1.0  # fully covered, some of it under the occluder's zero weights
    alpha[14, 10:14] = 0.0  # a hole inside the box
    occluder_alpha = np.zeros((height, width), np.float32)
    occluder_alpha[15:35, 20:45] = rng.choice(np.float32([0.0, 0.3, 0.7, 1.0]), (20, 25))
    occlusion = occluders.Occlusion(
        rgb=rng.random((height, width, 3), dtype=np.float32) * (occluder_alpha > 0)[..., None],
        alpha=occluder_alpha,
        mask=occluder_alpha >= 0.5,
        target_fraction=0.5,
        achieved_fraction=0.5,
    )
    return background, linear, alpha, occlusion


def test_composite_object_is_the_opencv_blend_of_the_encoded_object():
    for seed in range(6):
        background, linear, alpha, _ = _composite_case(seed)
        as_float = np.multiply(background, np.float32(1.0 / 255.0), dtype=np.float32)
        expected = _composite_as_written(as_float, linear, alpha)
        assert np.array_equal(compositing.composite_object(as_float.copy(), linear, alpha), expected)
        strided = np.zeros((40, 50, 4), np.float32)[:, :, :3]  # not C-ordered: modified in place all the same
        strided[...] = as_float
        assert compositing.composite_object(strided, linear, alpha) is strided and np.array_equal(strided, expected)


def test_unblurred_images_composite_only_the_drawn_box_with_the_same_bytes():
    for seed in range(6):
        background, linear, alpha, occlusion = _composite_case(seed)
        for occ in (None, occlusion):
            as_float = np.multiply(background, np.float32(1.0 / 255.0), dtype=np.float32)  # as the pipeline does
            whole = compositing.to_uint8(_composite_as_written(as_float, linear, alpha, occ))
            boxed = compositing.composite_to_uint8(background, linear, alpha, occ)
            assert np.array_equal(boxed, whole), (seed, occ is None)
            assert np.array_equal(boxed[:10], background[:10])  # above everything drawn: untouched
        assert np.array_equal(compositing.composite_to_uint8(background, linear, np.zeros_like(alpha)), background)
        only_occluder = compositing.composite_to_uint8(background, linear, np.zeros_like(alpha), occlusion)
        as_float = np.multiply(background, np.float32(1.0 / 255.0), dtype=np.float32)
        assert np.array_equal(
            only_occluder,
            compositing.to_uint8(_composite_as_written(as_float, linear, np.zeros_like(alpha), occlusion)),
        )


def test_every_level_survives_the_float_round_trip_and_zero_weight_blends():
    """Why composite_to_uint8 may leave pixels nothing covers alone."""
    import cv2

    levels = np.arange(256, dtype=np.uint8).reshape(16, 16, 1).repeat(3, axis=2)
    image = np.multiply(levels, np.float32(1.0 / 255.0), dtype=np.float32)
    zero = np.zeros((16, 16), np.float32)
    for _ in range(3):
        assert np.array_equal(compositing.to_uint8(image), levels)
        image = cv2.blendLinear(np.ones_like(image), image, zero, 1.0 - zero)
