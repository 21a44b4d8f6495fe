"""Every extreme of Table 3 gives a valid image and box, or a recorded resample: never a
degenerate box."""

from __future__ import annotations

import math

import numpy as np
import pytest

from foldwise.sampling import generate_parameters
from workers.render import blur
from workers.render.annotation import MIN_BOX_SIDE, MIN_VISIBLE_PIXELS, tight_box
from workers.render.pipeline import render_theta, render_with_resample

SIZE = 96


def canonical(seed=0, size=SIZE, **override):
    theta = generate_parameters("po", "canonical", 1, seed=seed, image_size=size)[0]
    return theta.replace(**override) if override else theta


def assert_valid(result, size=SIZE):
    assert result.image.shape == (size, size, 3) and result.image.dtype == np.uint8
    assert result.mask.sum() >= MIN_VISIBLE_PIXELS
    assert result.box == tight_box(result.mask)
    x0, y0, x1, y1 = result.box
    assert 0 <= x0 and 0 <= y0 and x1 <= size and y1 <= size
    assert x1 - x0 >= MIN_BOX_SIDE and y1 - y0 >= MIN_BOX_SIDE
    assert 0 < result.visible_fraction <= 1


def valid_or_resampled(theta, size=SIZE):
    """Render with resampling; when θ itself was rejected, its reason is recorded."""
    result, used, reasons = render_with_resample(theta)
    assert_valid(result, size)
    if reasons:
        assert used != theta and used.resample == len(reasons)
        assert all(isinstance(reason, str) and reason for reason in reasons)
    else:
        assert used is theta
    return result, used, reasons


@pytest.mark.parametrize("angle", ["yaw", "pitch"])
def test_edge_on_pose(angle):
    for seed in range(3):
        theta = canonical(seed=seed, condition="po", difficulty="hard", **{angle: math.pi / 2})
        result, used, reasons = valid_or_resampled(theta)
        if not reasons:  # the bent sheet still shows a sliver: it must be thin along one axis
            x0, y0, x1, y1 = result.box
            assert min(x1 - x0, y1 - y0) < SIZE * 0.65


@pytest.mark.parametrize("direction", [0.0, math.pi / 2, math.pi, 1.5 * math.pi, math.pi / 4])
def test_position_offset_two_metres(direction):
    theta = canonical(condition="po", difficulty="hard", position_offset_m=2.0, position_offset_angle=direction)
    result, used, reasons = valid_or_resampled(theta)
    assert not reasons, "a 2 m offset keeps part of the sheet in view by design"
    if direction in (0.0, math.pi / 2, math.pi, 1.5 * math.pi):
        assert result.visible_fraction < 0.8  # cropped by the border
        ax0, ay0, ax1, ay1 = result.amodal_box
        assert ax0 < 0 or ay0 < 0 or ax1 > SIZE or ay1 > SIZE


def test_scale_tenth_is_valid_at_128_and_resampled_when_too_small():
    result, _, reasons = valid_or_resampled(canonical(size=128, condition="sc", difficulty="hard", scale=0.1), size=128)
    assert not reasons and result.mask.sum() < 100
    tiny = canonical(size=48, condition="sc", difficulty="hard", scale=0.1)
    result, used, reasons = valid_or_resampled(tiny, size=48)
    assert reasons and "too small" in reasons[0]


def test_scale_three_crops_at_the_border():
    result, _, reasons = valid_or_resampled(canonical(condition="sc", difficulty="hard", scale=3.0))
    assert not reasons
    assert result.box[2] - result.box[0] >= SIZE - 2
    assert result.visible_fraction < 0.6
    assert result.amodal_box[0] < 0 and result.amodal_box[2] > SIZE


def test_visible_fraction_tenth():
    for seed in range(3):
        theta = generate_parameters("eo", "hard", 1, seed=seed, image_size=SIZE)[0]
        theta = theta.replace(visible_fraction=0.1)
        result, used, reasons = valid_or_resampled(theta)
        if not reasons:
            assert result.visible_fraction == pytest.approx(0.1, abs=0.03)


@pytest.mark.parametrize("irradiance", [0.01, 10.0])
def test_irradiance_extremes(irradiance):
    sharp = render_theta(canonical())
    result, _, reasons = valid_or_resampled(canonical(condition="li", difficulty="hard", irradiance=irradiance))
    assert not reasons
    assert result.box == sharp.box  # lighting changes colours, not geometry
    inside = result.image[result.mask].astype(float).mean()
    reference = sharp.image[sharp.mask].astype(float).mean()
    if irradiance < 1:
        assert inside < 0.35 * reference
    else:
        assert inside > reference + 40
        assert (result.image[result.mask] == 255).mean() > 0.3  # mostly saturated


def test_eight_rulings():
    for seed in range(3):
        valid_or_resampled(canonical(seed=seed, condition="de", difficulty="hard", rulings=8))


@pytest.mark.parametrize("angle", [0.0, math.pi])
def test_motion_blur_hardest(angle):
    sharp = render_theta(canonical())
    theta = canonical(condition="mb", difficulty="hard", motion_blur_pct=4.88, motion_blur_angle=angle)
    result, _, reasons = valid_or_resampled(theta)
    assert not reasons
    assert result.box == sharp.box  # blur spreads colours, the box stays geometric
    assert not np.array_equal(result.image, sharp.image)
    other = render_theta(theta.replace(motion_blur_angle=math.pi - angle))
    assert other.image.tobytes() == result.image.tobytes()  # a segment at 0 and at pi is the same


def test_motion_kernel_direction_and_normalisation():
    horizontal = blur.motion_kernel(4.7, 0.0)
    vertical = blur.motion_kernel(4.7, math.pi / 2)
    diagonal = blur.motion_kernel(6.2, math.pi / 4)
    for kernel in (horizontal, vertical, diagonal):
        assert kernel.shape[0] == kernel.shape[1] and kernel.shape[0] % 2 == 1
        assert kernel.sum() == pytest.approx(1.0, abs=1e-6)
    middle = horizontal.shape[0] // 2
    assert horizontal[middle].sum() == pytest.approx(1.0, abs=1e-6)
    assert vertical[:, middle].sum() == pytest.approx(1.0, abs=1e-6)
    # 45 degrees goes up and to the right on screen: mass on the anti-diagonal, symmetric.
    np.testing.assert_allclose(diagonal, diagonal.T, atol=1e-7)
    np.testing.assert_allclose(diagonal, diagonal[::-1, ::-1], atol=1e-7)
    assert diagonal[1, -2] > 0.05 and diagonal[1, 1] == 0
    assert blur.motion_kernel(0.4, 1.0).size == 0
    assert blur.motion_kernel(1.49, 1.0).size == 0


def test_focus_blur_hardest_keeps_the_geometric_box():
    sharp = render_theta(canonical())
    result, _, reasons = valid_or_resampled(canonical(condition="fb", difficulty="hard", focus_blur_pct=2.92))
    assert not reasons and result.box == sharp.box
    assert "focus_blur" in result.timings
    difference = np.abs(result.image.astype(int) - sharp.image.astype(int))
    assert difference.max() > 20


@pytest.mark.parametrize(
    "percent, size, expected",
    [
        (0.0, 128, 0),  # canonical
        (0.39, 128, 0),  # 0.5 px rounds to 0... or 1: no blur either way
        (0.97, 128, 0),  # 1.24 px -> 1 px: the identity
        (1.2, 128, 3),  # 1.54 px -> 2 (even) -> 3
        (2.92, 128, 5),  # 3.7 px -> 4 (even) -> 5
        (2.35, 128, 3),  # 3.0 px -> 3
        (2.92, 512, 15),  # 14.95 px -> 15
        (0.39, 1024, 5),  # 3.99 px -> 4 (even) -> 5
    ],
)
def test_kernel_sizes_are_odd_or_skipped(percent, size, expected):
    assert blur.odd_kernel_size(percent, size) == expected


def test_a_kernel_rounding_to_nothing_skips_the_stage_without_a_copy():
    image = np.random.default_rng(0).random((32, 32, 3), dtype=np.float32)
    assert blur.focus_blur(image, 0.39, 128) is image
    assert blur.motion_blur(image, 0.39, 1.0, 128) is image
    theta = canonical(condition="fb", difficulty="easy", focus_blur_pct=0.39, size=128)
    result = render_theta(theta)
    assert "focus_blur" not in result.timings
    assert result.image.tobytes() == render_theta(theta.replace(focus_blur_pct=0.0)).image.tobytes()
    even = render_theta(theta.replace(focus_blur_pct=1.2))  # a 2-pixel kernel becomes 3
    assert "focus_blur" in even.timings


def test_no_degenerate_box_ever_leaves_the_pipeline():
    for code in ("po", "sc", "eo", "de"):
        for theta in generate_parameters(code, "hard", 5, seed=21, image_size=32):
            result, _, _ = render_with_resample(theta)
            assert_valid(result, size=32)
