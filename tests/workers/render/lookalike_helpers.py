"""Lookalike sheets and an asset catalog holding them, for the render tests."""

from __future__ import annotations

import numpy as np

from workers.render.assets import Asset, AssetCatalog, load_assets

MAGENTA = (255, 0, 255)


def sheet(colour, size=(96, 68)) -> np.ndarray:
    image = np.empty((*size, 3), np.uint8)
    image[:] = colour
    return image


def catalog(lookalikes: dict[str, np.ndarray]) -> AssetCatalog:
    builtin = load_assets()
    return AssetCatalog(
        builtin.objects,
        builtin.backgrounds,
        builtin.occluders,
        [Asset(name, (lambda image=image: image), source=name) for name, image in lookalikes.items()],
    )


def changed(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return np.abs(image.astype(np.int32) - reference.astype(np.int32)).sum(axis=2) > 30
