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


def test_close_to_the_full_resolution_crop():
    photo = _smooth_photo(1200, 1000, 1)
    catalog = _catalog({"big": photo})
    diffs = []
    for seed in range(30):
        cached = catalog.background("big", 80, np.random.default_rng(seed))
        reference = random_crop(photo, 80, np.random.default_rng(seed))  # same window, straight from the photo
        diffs.append(np.abs(cached.astype(np.int16) - reference).mean())
    assert np.mean(diffs) < 1.5 and max(diffs) < 3.0, diffs  # bilinear from a level vs INTER_AREA


def test_builtin_photos_stay_close_to_the_full_resolution_crop():
    catalog = load_assets()
    for name in ("retina", "hubble_deep_field", "brick"):
        photo = catalog._get("backgrounds", name).load()
        diffs = [np.abs(catalog.background(name, 128, np.random.default_rng(seed)).astype(np.int16)
                        - random_crop(photo, 128, np.random.default_rng(seed))).mean() for seed in range(8)]
        assert np.mean(diffs) < 4.0, (name, diffs)


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


def test_noise_background_matches_the_plain_numpy_formula():
    for seed in range(6):
        for size in (17, 64):
            image = procedural_background("noise", size, np.random.default_rng(seed))
            rng = np.random.default_rng(seed)  # replay the draws
            rng.uniform(0, 255, size=(2, 3))  # the two colours, unused by noise
            out, amplitude, total = np.zeros((size, size, 3), np.float32), 1.0, 0.0
            for cells in (4, 8, 16, 32):
                grid = rng.uniform(0, 255, size=(cells, cells, 3)).astype(np.float32)
                out += amplitude * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
                total += amplitude
                amplitude *= 0.5
            assert np.array_equal(image, np.clip(out / total + 0.5, 0, 255).astype(np.uint8)), (seed, size)
