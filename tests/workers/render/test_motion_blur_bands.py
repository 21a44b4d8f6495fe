"""Motion blur with long kernels: filtered band by band (direct, not OpenCV's DFT path), it must
equal the plain correlation with reflected borders."""

import math

import cv2
import numpy as np
import pytest

from workers.render import blur


def _reference_blur(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Correlation in float64, tap by tap, over a BORDER_REFLECT_101 padded image."""
    kh, kw = kernel.shape
    padded = cv2.copyMakeBorder(image.astype(np.float64), kh // 2, kh // 2, kw // 2, kw // 2, cv2.BORDER_REFLECT_101)
    out = np.zeros(image.shape, np.float64)
    for i, j in zip(*np.nonzero(kernel)):
        out += float(kernel[i, j]) * padded[i : i + image.shape[0], j : j + image.shape[1]]
    return out


@pytest.mark.parametrize("percent", [4.0, 6.0, 15.0, 40.0])
@pytest.mark.parametrize("angle", [0.0, 0.3, math.pi / 4, math.pi / 2, 2.5])
def test_motion_blur_equals_the_plain_correlation(percent, angle):
    image = np.random.default_rng(1).random((48, 56, 3)).astype(np.float32)
    image[10:20, 5:40] = 1.0  # a hard edge, where a wrongly placed band would show
    kernel = blur.motion_kernel(percent / 100.0 * 48, angle)
    assert kernel.size > 0
    blurred = blur.motion_blur(image, percent, angle, 48)
    assert blurred.shape == image.shape and blurred.dtype == np.float32
    assert np.abs(blurred - _reference_blur(image, kernel)).max() < 1e-5


def test_kernel_bands_cover_every_tap_once_within_the_direct_limit():
    for length in (12.0, 19.5, 40.0, 90.0):
        for angle in np.linspace(0, math.pi, 9):
            kernel = blur.motion_kernel(length, float(angle))
            covered = np.zeros(kernel.shape, np.int32)
            for r0, r1, c0, c1 in blur._kernel_bands(kernel):
                assert (r1 - r0) * (c1 - c0) <= blur._DIRECT_FILTER_MAX_TAPS
                covered[r0:r1, c0:c1] += 1
            assert covered.max() == 1
            assert np.all(covered[kernel != 0] == 1)
