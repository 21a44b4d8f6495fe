"""Photo backgrounds from cached pre-shrunk levels: deterministic, close to the full-resolution
crop, and the cache stays bounded."""

import cv2
import numpy as np
import pytest

from workers.render import assets as assets_module
from workers.render.assets import (
    Asset,
    AssetCatalog,
    AssetError,
    load_assets,
    procedural_background,
    random_crop,
)


def _smooth_photo(h: int, w: int, seed: int) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0, 255, (h // 40, w // 40, 3)).astype(np.float32)
    photo = cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    photo = np.clip(photo + 0.5, 0, 255).astype(np.uint8)
    photo.setflags(write=False)
    return photo


def _catalog(photos: dict[str, np.ndarray]) -> AssetCatalog:
    builtin = load_assets()
    backgrounds = [Asset(name, (lambda p=photo: p), source=name) for name, photo in photos.items()]
    return AssetCatalog(builtin.objects, backgrounds, builtin.occluders)


def test_same_seed_same_bytes_with_cold_or_warm_cache():
    photo = _smooth_photo(1200, 1000, 0)
    warm = _catalog({"big": photo})
    for seed in range(10):
        first = warm.background("big", 96, np.random.default_rng(seed))
        again = warm.background("big", 96, np.random.default_rng(seed))
        cold = _catalog({"big": photo}).background("big", 96, np.random.default_rng(seed))
        assert first.shape == (96, 96, 3) and first.dtype == np.uint8
        assert np.array_equal(first, again) and np.array_equal(first, cold), seed
    assert any(level > 0 for _, level in warm._shrunk)  # the shrunk levels were used


def _full_resolution_crop_as_drawn(catalog: AssetCatalog, name: str, size: int, seed: int) -> np.ndarray:
    """The reference for catalog.background(name, size, rng(seed)): the same window, its origin
    where the level puts it (a fraction of a photo pixel, see _level_window), cut from the full
    photo with INTER_AREA (the photo is shifted by the fraction first: bilinear at full
    resolution, far finer than the output)."""
    photo = catalog._get("backgrounds", name).load()
    h, w = photo.shape[:2]
    y0, x0, side, mirror = assets_module._crop_window(h, w, np.random.default_rng(seed))
    level = assets_module._level_for(side, size)
    level_shape = photo.shape if level == 0 else catalog._photo_level(catalog._get("backgrounds", name), level).shape
    left, top, _, _ = assets_module._level_window(photo.shape, level_shape, y0, x0, side)
    origin_x, origin_y = left * w / level_shape[1], top * h / level_shape[0]
    shift = np.array([[1.0, 0.0, origin_x], [0.0, 1.0, origin_y]])
    window = cv2.warpAffine(
        photo, shift, (side, side), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
    )
    out = cv2.resize(window, (size, size), interpolation=cv2.INTER_AREA)
    return cv2.flip(out, 1) if mirror else out


def test_close_to_the_full_resolution_crop():
    photo = _smooth_photo(1200, 1000, 1)
    catalog = _catalog({"big": photo})
    diffs, moves = [], []
    for seed in range(30):
        cached = catalog.background("big", 80, np.random.default_rng(seed))
        reference = _full_resolution_crop_as_drawn(catalog, "big", 80, seed)
        diffs.append(np.abs(cached.astype(np.int16) - reference).mean())
        # The window is the one random_crop draws, up to under half an output pixel.
        y0, x0, side, _ = assets_module._crop_window(1200, 1000, np.random.default_rng(seed))
        level = assets_module._level_for(side, 80)
        level_shape = catalog._photo_level(catalog._get("backgrounds", "big"), level).shape if level else photo.shape
        left, top, _, _ = assets_module._level_window(photo.shape, level_shape, y0, x0, side)
        moves += [abs(left * 1000 / level_shape[1] - x0) * 80 / side, abs(top * 1200 / level_shape[0] - y0) * 80 / side]
    assert np.mean(diffs) < 1.5 and max(diffs) < 3.0, diffs  # bilinear from a level vs INTER_AREA
    assert max(moves) < 0.5 and np.mean(moves) > 0.1, moves


def test_builtin_photos_stay_close_to_the_full_resolution_crop():
    catalog = load_assets()
    for name in ("retina", "hubble_deep_field", "brick"):
        diffs = [
            np.abs(
                catalog.background(name, 128, np.random.default_rng(seed)).astype(np.int16)
                - _full_resolution_crop_as_drawn(catalog, name, 128, seed)
            ).mean()
            for seed in range(8)
        ]
        assert np.mean(diffs) < 4.0, (name, diffs)
        # And from the exactly drawn window (random_crop), under half a pixel away.
        photo = catalog._get("backgrounds", name).load()
        diffs = [
            np.abs(
                catalog.background(name, 128, np.random.default_rng(seed)).astype(np.int16)
                - random_crop(photo, 128, np.random.default_rng(seed))
            ).mean()
            for seed in range(8)
        ]
        assert np.mean(diffs) < 6.0, (name, diffs)


def test_small_photo_is_enlarged_without_levels():
    photo = _smooth_photo(80, 120, 2)
    catalog = _catalog({"small": photo})
    out = catalog.background("small", 256, np.random.default_rng(0))
    assert out.shape == (256, 256, 3)
    assert not catalog._shrunk  # every crop is under the output size: nothing to shrink


def test_level_cache_is_bounded_and_eviction_keeps_bytes(monkeypatch):
    monkeypatch.setattr(assets_module, "MAX_CACHED_LEVELS", 3)
    photos = {f"p{i}": _smooth_photo(800, 800, 10 + i) for i in range(4)}
    catalog = _catalog(photos)
    first = {name: catalog.background(name, 64, np.random.default_rng(7)) for name in photos}
    for name in photos:
        catalog.background(name, 64, np.random.default_rng(8))
        assert len(catalog._shrunk) <= 3
    for name in photos:  # evicted levels are rebuilt identically
        assert np.array_equal(catalog.background(name, 64, np.random.default_rng(7)), first[name])


def test_bad_size_is_rejected():
    catalog = _catalog({"big": _smooth_photo(400, 400, 3)})
    with pytest.raises(AssetError, match="size"):
        catalog.background("big", 0, np.random.default_rng(0))


def _noise_per_octave(size: int, rng: np.random.Generator) -> np.ndarray:
    """The noise as first written: each octave enlarged to the image on its own (float32), summed."""
    rng.uniform(0, 255, size=(2, 3))  # the two colours, unused by noise
    out, amplitude, total = np.zeros((size, size, 3), np.float32), 1.0, 0.0
    for cells in (4, 8, 16, 32):
        grid = rng.uniform(0, 255, size=(cells, cells, 3)).astype(np.float32)
        out += amplitude * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total += amplitude
        amplitude *= 0.5
    return np.clip(out / total + 0.5, 0, 255).astype(np.uint8)


def test_noise_background_matches_its_formula():
    for seed in range(6):
        for size in (17, 64):
            image = procedural_background("noise", size, np.random.default_rng(seed))
            rng = np.random.default_rng(seed)  # replay the draws
            rng.uniform(0, 255, size=(2, 3))  # the two colours, unused by noise
            noise, amplitude, total = None, 1.0, 0.0
            for cells in (4, 8, 16, 32):
                grid = rng.uniform(0, 255, size=(cells, cells, 3)).astype(np.float32)
                noise = (
                    grid
                    if noise is None
                    else cv2.resize(noise, (cells, cells), interpolation=cv2.INTER_CUBIC) + np.float32(amplitude) * grid
                )
                total += amplitude
                amplitude *= 0.5
            small = np.clip(noise / np.float32(total) + 0.5, 0, 255).astype(np.uint8)
            assert np.array_equal(image, cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)), (seed, size)


def test_noise_looks_like_octaves_enlarged_one_by_one():
    """Summing the octaves on the cell grids and enlarging once keeps the look of enlarging each
    octave to the image: the same blobs, within a level or two, with the same contrast and grain."""
    for seed in range(8):
        image = procedural_background("noise", 256, np.random.default_rng(seed)).astype(np.float32)
        reference = _noise_per_octave(256, np.random.default_rng(seed)).astype(np.float32)
        difference = np.abs(image - reference)
        assert difference.mean() < 2.0 and np.percentile(difference, 99) < 8, seed
        assert abs(image.std() - reference.std()) < 0.05 * reference.std()
        grain = [np.abs(cv2.Laplacian(x, cv2.CV_32F)).mean() for x in (image, reference)]
        assert abs(grain[0] - grain[1]) < 0.1 * grain[1]
