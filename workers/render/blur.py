"""The blurs after compositing, in the paper's order: focus blur, then motion blur (the paper
blurs after adding the background). Images are float32 sRGB in [0, 1] (H, W, 3).

Blur kernels: OpenCV needs odd kernel sizes of at least 1. A size in percent of the image is
rounded half up to whole pixels; 0 or 1 pixel means no blur at all (the stage is skipped: a
1-pixel kernel is the identity), an even size becomes the next odd one. Focus blur is a
Gaussian of that kernel size with OpenCV's sigma for it (``0.3 * ((k - 1) / 2 - 1) + 0.8``).
Motion blur is a straight segment of the exact (fractional) length at the given angle,
splatted with bilinear weights into the odd kernel that holds it and normalised to sum 1.
Blur spreads the object's colours over its neighbours, but the annotated box stays the
geometric box of the sharp render (a detector must find the object, not its blur halo).
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def odd_kernel_size(percent: float, image_size: int) -> int:
    """Kernel size in pixels for a size in percent of the image: rounded half up; even sizes
    go to the next odd one; 0 when the kernel would be 0 or 1 pixel (no blur to apply)."""
    pixels = math.floor(percent / 100.0 * image_size + 0.5)
    if pixels <= 1:
        return 0
    return pixels if pixels % 2 == 1 else pixels + 1


def focus_blur(image: np.ndarray, percent: float, image_size: int) -> np.ndarray:
    """Gaussian blur with a kernel of ``percent`` of the image size (see the module notes)."""
    size = odd_kernel_size(percent, image_size)
    if size == 0:
        return image
    return cv2.GaussianBlur(image, (size, size), 0, borderType=cv2.BORDER_REFLECT_101)


def motion_kernel_pixels(percent: float, image_size: int) -> int:
    """A motion of ``percent`` of the image size, rounded half up to whole pixels (<= 1: no blur)."""
    return math.floor(percent / 100.0 * image_size + 0.5)


def motion_kernel(length_px: float, angle: float) -> np.ndarray:
    """Normalised kernel of a straight motion of ``length_px`` pixels at ``angle`` radians
    (counter-clockwise from image right, as seen on screen). Odd-sized and centred; empty
    (shape (0, 0)) when the length rounds to at most one pixel."""
    size = math.floor(length_px + 0.5)
    if size <= 1:
        return np.zeros((0, 0), np.float32)
    size = size if size % 2 == 1 else size + 1
    size += 2  # room for the bilinear splat of the end points
    centre = (size - 1) / 2.0
    samples = max(int(math.ceil(length_px * 8)), 2) + 1
    t = np.linspace(-length_px / 2.0, length_px / 2.0, samples)
    x = centre + t * math.cos(angle)
    y = centre - t * math.sin(angle)  # image rows grow downwards
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    kernel = np.zeros((size, size), np.float64)
    for dx, dy, weight in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), weight)
    # Trim empty border rows/columns symmetrically so the kernel stays centred and odd.
    while (
        kernel.shape[0] > 1
        and not kernel[0].any()
        and not kernel[-1].any()
        and not kernel[:, 0].any()
        and not kernel[:, -1].any()
    ):
        kernel = kernel[1:-1, 1:-1]
    return (kernel / kernel.sum()).astype(np.float32)


def motion_blur(image: np.ndarray, percent: float, angle: float, image_size: int) -> np.ndarray:
    """Uniform linear motion blur: a segment of ``percent`` of the image size at ``angle``."""
    kernel = motion_kernel(percent / 100.0 * image_size, angle)
    if kernel.size == 0:
        return image
    if kernel.size <= _DIRECT_FILTER_MAX_TAPS:
        return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT_101)
    # OpenCV filters a float image through the DFT once the kernel has more than ~130 taps
    # (4 ms for 13 x 13 at 256 pixels, single-threaded), though a motion kernel is a thin
    # line. Correlating with bands of its rows, each trimmed to its non-zero columns and
    # anchored where it sits in the whole kernel, sums the same terms directly (~10x faster;
    # equal up to float rounding, with reflected borders handled identically).
    # The image is reflected once by the kernel's half size (OpenCV wants the anchor inside
    # each band), so every band reads real or reflected pixels, never a border of its own.
    height, width = image.shape[:2]
    half_rows, half_cols = kernel.shape[0] // 2, kernel.shape[1] // 2
    padded = cv2.copyMakeBorder(image, half_rows, half_rows, half_cols, half_cols, cv2.BORDER_REFLECT_101)
    out = None
    for row0, row1, col0, col1 in _kernel_bands(kernel):
        band = np.ascontiguousarray(kernel[row0:row1, col0:col1])
        part = cv2.filter2D(padded, -1, band, anchor=(0, 0), borderType=cv2.BORDER_REFLECT_101)
        part = part[row0 : row0 + height, col0 : col0 + width]
        out = part.copy() if out is None else cv2.add(out, part, dst=out)
    return out


_DIRECT_FILTER_MAX_TAPS = 121  # OpenCV 4.11 switches float32 filter2D to the DFT above 130 taps


def _kernel_bands(kernel: np.ndarray) -> list[tuple[int, int, int, int]]:
    """(row0, row1, col0, col1) boxes covering every non-zero tap of ``kernel``: runs of
    consecutive rows, each trimmed to its non-zero columns and kept to at most
    _DIRECT_FILTER_MAX_TAPS taps so OpenCV filters it directly."""
    nonzero = kernel != 0
    bands: list[tuple[int, int, int, int]] = []
    current = None
    for row in range(kernel.shape[0]):
        cols = np.flatnonzero(nonzero[row])
        if cols.size == 0:
            if current is not None:
                bands.append(current)
                current = None
            continue
        c0, c1 = int(cols[0]), int(cols[-1]) + 1
        if current is not None:
            r0, _, b0, b1 = current
            n0, n1 = min(b0, c0), max(b1, c1)
            if (row + 1 - r0) * (n1 - n0) <= _DIRECT_FILTER_MAX_TAPS:
                current = (r0, row + 1, n0, n1)
                continue
            bands.append(current)
        current = (row, row + 1, c0, c1)
    if current is not None:
        bands.append(current)
    return bands
