"""Occluder placement: the critical-scale model of each shape is right to within its tolerance,
the chosen scale hides (within a pixel) as many target pixels as asked, the achieved fraction
is measured on the returned mask, and the shape is warped only where it can be non-zero."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from workers.render import occluders


def _target(seed: int, size: int = 128) -> np.ndarray:
    """A random convex blob of roughly a quarter to half the image, maybe cut by the border."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((size, size), np.uint8)
    points = rng.uniform(-0.1 * size, 1.1 * size, (7, 2)).astype(np.float32)
    cv2.fillPoly(mask, [cv2.convexHull(points).astype(np.int32)], 1)
    if mask.sum() < size * size // 10:
        cv2.circle(mask, (size // 2, size // 2), size // 3, 1, -1)
    return mask.astype(bool)


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.ascontiguousarray(array)
    array.setflags(write=False)
    return array


OCCLUDER_RGB = _frozen(np.random.default_rng(0).integers(0, 256, (150, 200, 3), dtype=np.uint8))


def _real_scales(shape, shape_mask, offsets, angle, model):
    """Each pixel's critical scale on the drawn shape, bisected over a wide bracket."""
    cos, sin = np.float32(math.cos(angle)), np.float32(math.sin(angle))
    rotated = np.stack([cos * offsets[0] - sin * offsets[1], sin * offsets[0] + cos * offsets[1]], axis=1)
    return occluders._real_critical_scales(
        shape_mask, shape.pivot[0], shape.pivot[1], rotated, model * np.float32(0.5), model * np.float32(2.0), 30
    )


@pytest.mark.parametrize("size", [(384, 512), (191, 384), (40, 60)])
def test_random_shape_models_are_right_within_their_tolerance(size):
    height, width = size
    kinds = set()
    for seed in range(24):
        rng = np.random.default_rng(seed)
        shape = occluders._random_outline(rng, height, width)
        kinds.add(type(shape).__name__)
        shape_mask = shape.draw(height, width)
        points = np.stack(np.meshgrid(np.arange(-60, 61, 3), np.arange(-60, 61, 3)), axis=0).reshape(2, -1)
        offsets = points[:, np.any(points != 0, axis=0)].astype(np.float32)
        angle = float(rng.uniform(-math.pi, math.pi))
        model = shape.critical_scales(offsets, angle)
        real = _real_scales(shape, shape_mask, offsets, angle, model)
        assert np.all(np.abs(real / model - 1) <= shape.tolerance), (seed, type(shape).__name__)
    assert kinds == {"_Ellipse", "_ConvexPolygon"}


def test_random_shape_draws_its_outline():
    for seed in range(10):
        shape = occluders._random_outline(np.random.default_rng(seed), 120, 160)
        assert np.array_equal(occluders.random_shape(np.random.default_rng(seed), 120, 160), shape.draw(120, 160))


def test_coverage_sampling_is_opencvs_remap():
    rng = np.random.default_rng(1)
    mask = np.zeros((60, 80), np.uint8)
    cv2.ellipse(mask, ((40.0, 30.0), (70.0, 50.0), 20.0), 255, -1, cv2.LINE_AA)
    mask[:, :4] = rng.integers(0, 256, (60, 4))  # texture at the border, where zeros are read outside
    xs = rng.uniform(-2, 82, (50, 40)).astype(np.float32)
    ys = rng.uniform(-2, 62, (50, 40)).astype(np.float32)
    expected = cv2.remap(mask, xs, ys, cv2.INTER_LINEAR)
    from numba import njit

    @njit
    def sample_all(mask, xs, ys):
        out = np.empty(xs.size, np.int64)
        for i in range(xs.size):
            out[i] = occluders._coverage_at(mask, xs[i], ys[i])
        return out

    assert np.array_equal(sample_all(mask, xs.ravel(), ys.ravel()), expected.ravel())


@pytest.mark.parametrize("visible", [0.1, 0.5, 0.9])
def test_placement_hides_the_asked_share_to_a_pixel(visible):
    for seed in range(12):
        target = _target(seed)
        amodal = target.sum() * 1.1  # some of the sheet lies outside the image
        occlusion = occluders.place_occluder(target, amodal, visible, OCCLUDER_RGB, None, np.random.default_rng(seed))
        hidden = np.count_nonzero(occlusion.mask & target)
        assert occlusion.achieved_fraction == (target.sum() - hidden) / amodal  # measured on the mask returned
        assert abs(occlusion.achieved_fraction - visible) * amodal <= 2.0, seed  # within 2 pixels of the ask
        assert np.array_equal(occlusion.mask, occlusion.alpha >= 0.5)
        x, y, w, h = cv2.boundingRect((occlusion.alpha > 0).view(np.uint8))
        outside = occlusion.rgb.copy()
        outside[y : y + h, x : x + w] = 0
        assert w and h and not outside.any()  # colour only where the occluder lies


def test_placement_is_deterministic_and_keeps_to_the_warped_box():
    target = _target(3)
    first = occluders.place_occluder(target, target.sum(), 0.4, OCCLUDER_RGB, None, np.random.default_rng(9))
    again = occluders.place_occluder(target, target.sum(), 0.4, OCCLUDER_RGB, None, np.random.default_rng(9))
    for name in ("rgb", "alpha", "mask"):
        assert np.array_equal(getattr(first, name), getattr(again, name))
    # The shape is warped inside the box its outline reaches: a warp of the whole image is zero outside it.
    rng = np.random.default_rng(4)
    shape = occluders._random_outline(rng, 150, 200)
    shape_mask = shape.draw(150, 200)
    for scale in (0.05, 0.3, 1.0, 2.5):
        placement = occluders._warp_shape(shape, shape_mask, target, (60.0, 70.0), 0.7, scale)
        whole = cv2.warpAffine(shape_mask, placement.matrix, (128, 128), flags=cv2.INTER_LINEAR)
        r0, r1, c0, c1 = placement.box
        outside = whole.copy()
        outside[r0:r1, c0:c1] = 0
        assert whole.any() and not outside.any(), scale


def test_the_scale_is_as_good_as_bisecting_the_real_count():
    """For one centre and rotation, the fitted count is within a pixel of the best a fine
    bisection on the real warped count finds (the old way: ~19 warps)."""
    target = _target(5)
    points = cv2.findNonZero(target.view(np.uint8)).reshape(-1, 2)
    points_f = points.T.astype(np.float32)
    for seed in range(8):
        rng = np.random.default_rng(seed)
        shape = occluders._random_outline(rng, 150, 200)
        shape_mask = shape.draw(150, 200)
        k = int(rng.integers(len(points)))
        centre, angle = (float(points[k, 0]), float(points[k, 1])), float(rng.uniform(-math.pi, math.pi))
        offsets = points_f - points_f[:, k : k + 1]
        need = 0.3 * len(points) + 0.25
        fitted = occluders._fit_scale(
            shape, shape_mask, target, centre, angle, offsets, shape.critical_scales(offsets, angle), need, 50.0, 4
        )
        low, high = 0.0, 50.0
        for _ in range(40):
            middle = 0.5 * (low + high)
            if occluders._warp_shape(shape, shape_mask, target, centre, angle, middle).hidden < need:
                low = middle
            else:
                high = middle
        bisected = min(
            (occluders._warp_shape(shape, shape_mask, target, centre, angle, s).hidden for s in (low, high)),
            key=lambda hidden: abs(hidden - need),
        )
        assert abs(fitted.hidden - need) <= abs(bisected - need) + 1.0, seed


def _not_star_shaped() -> dict[str, np.ndarray]:
    """Occluder alphas whose centroid lies outside them (in the hole or the notch)."""
    ring = np.zeros((120, 120), np.uint8)
    cv2.ellipse(ring, (60, 60), (45, 45), 0, 40, 320, 255, 14, cv2.LINE_AA)
    letter_c = np.zeros((120, 120), np.uint8)
    letter_c[10:110, 10:35] = letter_c[10:35, 10:110] = letter_c[85:110, 10:110] = 255
    letter_l = np.zeros((120, 120), np.uint8)
    letter_l[10:110, 10:35] = letter_l[85:110, 10:110] = 255
    return {"ring": ring, "C": letter_c, "L": letter_l}


def test_own_alpha_occluders():
    square = np.zeros((60, 80), np.uint8)
    square[10:50, 15:65] = 255
    target = _target(2)
    for alpha, worst in ((square, 2.0 / target.sum()), (_not_star_shaped()["ring"], occluders._GOOD_ENOUGH)):
        rgb = _frozen(np.full(alpha.shape + (3,), 90, np.uint8))
        alpha = _frozen(alpha)
        for seed in range(6):
            occlusion = occluders.place_occluder(target, target.sum(), 0.5, rgb, alpha, np.random.default_rng(seed))
            hidden = np.count_nonzero(occlusion.mask & target)
            assert occlusion.achieved_fraction == (target.sum() - hidden) / target.sum()
            if worst is not None:
                assert abs(occlusion.achieved_fraction - 0.5) <= worst
    glass = _frozen(np.zeros((20, 20), np.uint8))
    occlusion = occluders.place_occluder(
        target, target.sum(), 0.5, _frozen(np.zeros((20, 20, 3), np.uint8)), glass, np.random.default_rng(0)
    )
    assert (
        occlusion.achieved_fraction == 1.0 and not occlusion.mask.any()
    )  # nothing to hide with: the caller rejects it


@pytest.mark.parametrize("name", ["ring", "C", "L"])
def test_occluders_that_are_not_star_shaped_still_hide_the_share_asked(name):
    # Scaled about its centroid, which lies in its hole, a ring cannot hide the pixel it is
    # centred on and its hidden count does not grow with its scale: the pivot moves into the
    # shape and a scale the model misses is searched on real warps (50 of 90 rejected before).
    alpha = _frozen(_not_star_shaped()[name])
    shape = occluders._AlphaShape(alpha)
    x, y = (int(round(v)) for v in shape.pivot)
    assert alpha[y, x] >= 128
    rgb = _frozen(np.full(alpha.shape + (3,), 90, np.uint8))
    errors = []
    # A ring's band (14 of its 104 pixels) is too thin to hide 85% of these large blobs at
    # any scale the placement allows; the pipeline rejects and resamples such an image.
    asks = (0.5, 0.8) if name == "ring" else (0.15, 0.5, 0.8)
    for seed in range(12):
        target = _target(seed)
        for visible in asks:
            occlusion = occluders.place_occluder(target, target.sum(), visible, rgb, alpha, np.random.default_rng(seed))
            hidden = np.count_nonzero(occlusion.mask & target)
            assert occlusion.achieved_fraction == (target.sum() - hidden) / target.sum()
            errors.append(abs(occlusion.achieved_fraction - visible))
    assert max(errors) <= occluders._GOOD_ENOUGH, max(errors)


def test_nothing_to_do_when_the_border_already_hides_enough():
    target = _target(1)
    amodal = target.sum() / 0.6  # 60% of the sheet is in the image
    assert occluders.place_occluder(target, amodal, 0.7, OCCLUDER_RGB, None, np.random.default_rng(0)) is None
