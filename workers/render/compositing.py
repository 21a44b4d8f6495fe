"""The 2D stages after the 3D render, in the paper's order: external occlusion, background,
focus blur, motion blur (the paper blurs after adding the background).

Images here are float32 sRGB in [0, 1] (H, W, 3). The pipeline calls a stage only when its
parameter is not canonical, so a canonical image pays for none of them.

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
import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

_LINEAR_TO_SRGB_STEPS = 65535


def _srgb_encode_table() -> np.ndarray:
    linear = np.arange(_LINEAR_TO_SRGB_STEPS + 1, dtype=np.float64) / _LINEAR_TO_SRGB_STEPS
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    return srgb.astype(np.float32)


_SRGB_ENCODE = _srgb_encode_table()


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear light (any float, clipped to [0, 1]) to sRGB float32 in [0, 1], via a 16-bit table."""
    index = (np.clip(linear, 0.0, 1.0) * _LINEAR_TO_SRGB_STEPS + 0.5).astype(np.uint16)
    return np.take(_SRGB_ENCODE, index)  # faster than fancy indexing for one flat table


def to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


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
    while kernel.shape[0] > 1 and not kernel[0].any() and not kernel[-1].any() and not kernel[:, 0].any() and not kernel[:, -1].any():
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
        part = part[row0:row0 + height, col0:col0 + width]
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


def composite(background: np.ndarray, foreground: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``foreground`` over ``background`` with coverage ``alpha`` (H, W) in [0, 1] (float32)."""
    return cv2.blendLinear(foreground, background, alpha, 1.0 - alpha)


def composite_object(background: np.ndarray, linear_rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The rendered object (linear light, encoded to sRGB here) over the background (float32
    sRGB, modified in place and returned); work only inside the box where ``alpha > 0``."""
    x, y, w, h = cv2.boundingRect((alpha > 0).view(np.uint8))  # of the non-zero pixels
    if w == 0 or h == 0:
        return background
    region = (slice(y, y + h), slice(x, x + w))
    a = np.ascontiguousarray(alpha[region])
    background[region] = cv2.blendLinear(linear_to_srgb(linear_rgb[region]), background[region], a, 1.0 - a)
    return background


def _drawn_box(alpha: np.ndarray) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1) of the pixels where ``alpha > 0``; None when there are none."""
    x, y, w, h = cv2.boundingRect((alpha > 0).view(np.uint8))
    return (y, y + h, x, x + w) if w and h else None


def composite_to_uint8(
    background: np.ndarray, linear_rgb: np.ndarray, alpha: np.ndarray, occlusion: "Occlusion | None" = None
) -> np.ndarray:
    """The object (linear light) and then the occluder over a uint8 background, encoded to
    uint8: the same bytes as converting the whole background to float, ``composite_object``,
    ``composite`` and ``to_uint8``, but only the box where something is drawn goes through
    float (elsewhere a uint8 level survives the round trip unchanged). For images that get
    no blur; a blurred image needs the whole float image."""
    boxes = [box for box in (_drawn_box(alpha), None if occlusion is None else _drawn_box(occlusion.alpha)) if box]
    out = np.array(background, dtype=np.uint8, copy=True)
    if not boxes:
        return out
    region = (
        slice(min(b[0] for b in boxes), max(b[1] for b in boxes)),
        slice(min(b[2] for b in boxes), max(b[3] for b in boxes)),
    )
    image = composite_object(np.multiply(out[region], np.float32(1.0 / 255.0), dtype=np.float32), linear_rgb[region], alpha[region])
    if occlusion is not None:
        image = composite(image, occlusion.rgb[region], np.ascontiguousarray(occlusion.alpha[region]))
    out[region] = to_uint8(image)
    return out


@dataclass
class Occlusion:
    rgb: np.ndarray  # (H, W, 3) float32 sRGB of the occluder where it lies
    alpha: np.ndarray  # (H, W) float32 occluder coverage (anti-aliased edge)
    mask: np.ndarray  # (H, W) bool: pixels the occluder hides (alpha >= 0.5)
    target_fraction: float  # the visible fraction asked for
    achieved_fraction: float  # what this placement gives (visible target pixels / amodal area)


def random_shape(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A (height, width) uint8 mask in 0..255 of an ellipse, rotated rectangle or random convex
    polygon filling most of the box, all star-shaped about the centre."""
    mask = np.zeros((height, width), np.uint8)
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    kind = int(rng.integers(3))
    shift = 4  # sub-pixel precision of OpenCV's drawing
    if kind == 0:
        cv2.ellipse(mask, (centre, (width * 0.98, height * 0.98), 0.0), 255, -1, cv2.LINE_AA)
    elif kind == 1:
        inset = rng.uniform(0.6, 0.95)
        box = cv2.boxPoints((centre, (width * inset, height * inset), float(rng.uniform(-20, 20))))
        cv2.fillPoly(mask, [np.round(box * (1 << shift)).astype(np.int32)], 255, cv2.LINE_AA, shift)
    else:
        count = int(rng.integers(5, 10))
        # Evenly spread directions (jittered by less than half a step) keep every gap below pi,
        # so the hull always contains the centre.
        angles = (np.arange(count) + rng.uniform(-0.4, 0.4, count)) * (2 * np.pi / count)
        radii = rng.uniform(0.6, 1.0, count)
        points = np.stack(
            [centre[0] + radii * np.cos(angles) * width / 2.0, centre[1] + radii * np.sin(angles) * height / 2.0], axis=1
        )
        hull = cv2.convexHull(points.astype(np.float32))
        cv2.fillPoly(mask, [np.round(hull * (1 << shift)).astype(np.int32)], 255, cv2.LINE_AA, shift)
    return mask


def _place(pivot: tuple[float, float], centre, angle: float, scale: float) -> np.ndarray:
    """Affine map taking the occluder's ``pivot`` to ``centre``, rotated and scaled about it."""
    matrix = cv2.getRotationMatrix2D(pivot, math.degrees(angle), scale)
    matrix[0, 2] += centre[0] - pivot[0]
    matrix[1, 2] += centre[1] - pivot[1]
    return matrix


_PREPARED_CAPACITY = 16  # a 512-pixel occluder as float32 is 3 MB
_PREPARED: OrderedDict[tuple[int, int, int], tuple] = OrderedDict()
_PREPARED_LOCK = threading.Lock()


def _prepared_occluder(rgb: np.ndarray, alpha: np.ndarray | None, limit: int):
    """The occluder as place_occluder uses it: float32 colour in [0, 1] no larger than ``limit``
    pixels a side, and (its own alpha as float32, that alpha's moments) or None. Cached per
    source array when the arrays are read-only (the asset catalog's are): converting a
    512-pixel occluder per image costs more than placing it."""
    cacheable = not rgb.flags.writeable and (alpha is None or not alpha.flags.writeable)
    key = (id(rgb), id(alpha), limit)
    if cacheable:
        with _PREPARED_LOCK:
            item = _PREPARED.get(key)
            if item is not None and item[0] is rgb and item[1] is alpha:
                _PREPARED.move_to_end(key)
                return item[2]
    source = (rgb, alpha)
    oh, ow = rgb.shape[:2]
    if max(oh, ow) > limit:
        factor = limit / max(oh, ow)
        new_size = (max(2, int(ow * factor)), max(2, int(oh * factor)))
        rgb = cv2.resize(rgb, new_size, interpolation=cv2.INTER_AREA)
        if alpha is not None:
            alpha = cv2.resize(alpha, new_size, interpolation=cv2.INTER_AREA)
    rgb_f = rgb.astype(np.float32) / 255.0
    shape = None
    if alpha is not None:
        shape_f = alpha.astype(np.float32) / 255.0
        shape = (shape_f, cv2.moments(shape_f))
    prepared = (rgb_f, shape)
    if cacheable:
        with _PREPARED_LOCK:
            _PREPARED[key] = (*source, prepared)  # the sources are kept so their ids stay unique
            if len(_PREPARED) > _PREPARED_CAPACITY:
                _PREPARED.popitem(last=False)
    return prepared


def place_occluder(
    target_mask: np.ndarray,
    amodal_area: float,
    visible_fraction: float,
    occluder_rgb: np.ndarray,
    occluder_alpha: np.ndarray | None,
    rng: np.random.Generator,
    attempts: int = 4,
    steps: int = 18,
) -> Occlusion | None:
    """Size and place an occluder over the target so that about ``visible_fraction`` of the
    target's amodal area stays visible.

    Following the paper, the occluder's centre is a random pixel of the target mask. Its size
    is found by bisection (the occluded share grows with the size, as the shape is star-shaped
    about that centre); a few random centres and rotations are tried and the placement whose
    achieved fraction is closest to the target wins. ``None`` when the image border already
    hides enough of the target (nothing left to occlude)."""
    height, width = target_mask.shape
    in_image = int(np.count_nonzero(target_mask))
    need = in_image - visible_fraction * amodal_area  # target pixels the occluder must hide
    if need <= 0.5 or in_image == 0:
        return None
    occluder_f, shape_u8 = _prepared_occluder(occluder_rgb, occluder_alpha, 2 * max(height, width))
    oh, ow = occluder_f.shape[:2]
    if shape_u8 is None:
        shape_f = random_shape(rng, oh, ow).astype(np.float32) / 255.0
        moments = cv2.moments(shape_f)
    else:
        shape_f, moments = shape_u8
    # Scale about the shape's centroid: for an occluder with its own alpha the image centre
    # may be transparent.
    if moments["m00"] > 0:
        pivot = (moments["m10"] / moments["m00"], moments["m01"] / moments["m00"])
    else:
        pivot = ((ow - 1) / 2.0, (oh - 1) / 2.0)
    # The target's pixels in row-major order (as np.nonzero gives them, several times faster).
    points = cv2.findNonZero(np.ascontiguousarray(target_mask).view(np.uint8)).reshape(-1, 2)
    rows, cols = points[:, 1], points[:, 0]
    # Only target pixels count as hidden: the bisection warps the shape into the target's box.
    c0, r0, box_w, box_h = cv2.boundingRect(points)
    box_size = (box_w, box_h)
    box_mask = target_mask[r0:r0 + box_size[1], c0:c0 + box_size[0]]
    best = None
    max_scale = 4.0 * math.hypot(height, width) / max(1.0, min(oh, ow))
    for _ in range(attempts):
        k = int(rng.integers(rows.size))
        centre = (float(cols[k]), float(rows[k]))  # warpAffine puts pixel (i, j)'s centre at (j, i)
        angle = float(rng.uniform(-math.pi, math.pi))

        def hidden_at(scale: float) -> int:
            matrix = _place(pivot, (centre[0] - c0, centre[1] - r0), angle, scale)
            warped = cv2.warpAffine(shape_f, matrix, box_size, flags=cv2.INTER_LINEAR)
            return int(np.count_nonzero((warped >= 0.5) & box_mask))

        lo, hi = 0.0, max_scale
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            if hidden_at(mid) < need:
                lo = mid
            else:
                hi = mid
        scale = hi
        achieved = (in_image - hidden_at(scale)) / amodal_area
        error = abs(achieved - visible_fraction)
        if best is None or error < best[0]:
            best = (error, centre, angle, scale, achieved)
        if error < 0.01:
            break
    _, centre, angle, scale, achieved = best
    matrix = _place(pivot, centre, angle, scale)
    alpha = cv2.warpAffine(shape_f, matrix, (width, height), flags=cv2.INTER_LINEAR)
    # The occluder's colour matters only where it covers something: warp just that box.
    rgb = np.zeros((height, width, 3), np.float32)
    alpha_rows = np.flatnonzero(alpha.any(axis=1))
    if alpha_rows.size:
        alpha_cols = np.flatnonzero(alpha.any(axis=0))
        a_r0, a_c0 = int(alpha_rows[0]), int(alpha_cols[0])
        a_r1, a_c1 = int(alpha_rows[-1]) + 1, int(alpha_cols[-1]) + 1
        shifted = matrix.copy()
        shifted[0, 2] -= a_c0
        shifted[1, 2] -= a_r0
        rgb[a_r0:a_r1, a_c0:a_c1] = cv2.warpAffine(
            occluder_f, shifted, (a_c1 - a_c0, a_r1 - a_r0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
    mask = alpha >= 0.5
    return Occlusion(
        rgb=rgb,
        alpha=alpha,
        mask=mask,
        target_fraction=float(visible_fraction),
        achieved_fraction=float((in_image - np.count_nonzero(mask & target_mask)) / amodal_area),
    )
