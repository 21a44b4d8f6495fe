"""Lookalikes (``assets.lookalikes``): sheets of the objects' kind that are none of them lie beside
the targets in every render and are never boxed."""

from __future__ import annotations

import numpy as np
import pytest

from foldwise.config import AssetsConfig, load_config
from foldwise.sampling import generate_parameters
from tests.workers.render.lookalike_helpers import MAGENTA, catalog, changed, sheet
from workers.render.assets import Asset, AssetCatalog, AssetError, load_assets
from workers.render.layers import LOOKALIKES_PER_IMAGE, SheetPlacement, distractor_placements
from workers.render.pipeline import render_theta
from workers.render.scene import Camera

SIZE = 128


def test_lookalikes_follow_theta_clutter_and_leave_it_as_it_was():
    theta = generate_parameters("cl", "hard", 1, seed=3, image_size=SIZE)[0]
    camera = Camera(
        K=np.array([[120.0, 0, SIZE / 2], [0, 120.0, SIZE / 2], [0, 0, 1]]),
        R=np.eye(3),
        t=np.array([0.0, 0.0, 3.0]),
        width=SIZE,
        height=SIZE,
    )
    textures = ["backgrounds/brick", "occluders/coins"]
    plain = distractor_placements(theta, camera, textures, np.random.default_rng(0))
    with_lookalikes = distractor_placements(theta, camera, textures, np.random.default_rng(0), ["lookalikes/form-b"])
    assert with_lookalikes[: len(plain)] == plain  # θ's clutter draws what it drew without them
    extra = with_lookalikes[len(plain) :]
    assert LOOKALIKES_PER_IMAGE[0] <= len(extra) <= LOOKALIKES_PER_IMAGE[1]
    for placement in extra:
        assert isinstance(placement, SheetPlacement)
        assert placement.texture == "lookalikes/form-b" and placement.object is None
        assert not placement.front  # beside or behind the targets, never hiding them


def test_every_render_shows_a_lookalike_that_gets_no_box():
    assets = catalog({"other-form": sheet(MAGENTA)})
    shown = 0
    for seed in range(6):
        theta = generate_parameters("po", "canonical", 1, seed=seed, image_size=SIZE)[0]
        assert theta.clutter == 0  # no θ clutter: whatever changed is the lookalike
        plain = render_theta(theta)
        result = render_theta(theta, assets=assets)
        assert [obj.box for obj in result.objects] == [obj.box for obj in plain.objects]
        moved = changed(result.image, plain.image)
        target = np.any(result.masks, axis=0)
        assert (moved & target).sum() <= 0.02 * target.sum()  # behind the target: it stays in full view
        shown += bool((moved & ~target).sum() >= 20)
    assert shown >= 4  # sometimes one falls behind the target or out of the frame


def test_lookalikes_are_read_from_the_config_folder(tmp_path):
    import cv2

    folder = tmp_path / "lookalikes"
    folder.mkdir()
    cv2.imwrite(str(folder / "invoice-2.png"), sheet((0, 128, 255)))
    catalog = load_assets(AssetsConfig(lookalikes=folder))
    assert catalog.lookalike_sheets == ["lookalikes/invoice-2"]
    assert catalog.distractor("lookalikes/invoice-2", np.random.default_rng(0)).shape == (96, 68, 3)
    assert set(catalog.lookalike_textures()) == {"invoice-2"}
    assert load_assets().lookalike_sheets == []


def test_a_lookalike_named_like_an_object_is_refused():
    builtin = load_assets()
    with pytest.raises(AssetError, match=r"assets.lookalikes: \['astronaut'\] share a name with an object"):
        AssetCatalog(
            builtin.objects, builtin.backgrounds, builtin.occluders, [Asset("astronaut", lambda: sheet(MAGENTA))]
        )


def test_a_missing_lookalikes_folder_is_named(tmp_path):
    from foldwise.asset_check import validate_assets

    config_file = tmp_path / "c.yaml"
    config_file.write_text(f"name: c\nassets:\n  lookalikes: {tmp_path / 'nowhere'}\n")
    config = load_config(config_file)
    with pytest.raises(AssetError, match="assets.lookalikes"):
        validate_assets(config.assets)
