"""Compositing, the 2D stage after the 3D render that puts the layers and the occluder over the
background (the occluder's placement is occluders.py's, the blurs that follow are blur.py's).

Images here are float32 sRGB in [0, 1] (H, W, 3). The pipeline calls a stage only when its
parameter is not canonical, so a canonical image pays for none of them.

The object's composite (sRGB encode and OpenCV's blend, in one pass and to the same bits) is a
numba kernel (``compile_kernels`` builds it ahead).
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

from workers.render.occluders import Occlusion

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


def composite(background: np.ndarray, foreground: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``foreground`` over ``background`` with coverage ``alpha`` (H, W) in [0, 1] (float32)."""
    return cv2.blendLinear(foreground, background, alpha, 1.0 - alpha)


# The object's composite, pixel by pixel, exactly as NumPy and OpenCV compute it in float32:
# linear_to_srgb's table index, then cv2.blendLinear (s1 * w1 + s2 * w2) / ((w1 + w2) + 1e-5),
# separate multiplies and adds (numba contracts nothing into an FMA without fastmath).
_BLEND_EPSILON = np.float32(1e-5)
# Where the object covers a pixel fully (alpha 1) that blend is the table value over
# (1 + 1e-5) (the background is weighted 0): per table entry, as float32, and as uint8 with
# no occluder or with one of weight 0 there (a blend at weight 0 divides by 1 + 1e-5 again).
_OPAQUE_DENOMINATOR = (np.float32(1.0) + np.float32(0.0)) + _BLEND_EPSILON
_SRGB_OPAQUE = _SRGB_ENCODE / _OPAQUE_DENOMINATOR
_SRGB_OPAQUE_UINT8 = to_uint8(_SRGB_OPAQUE)
_SRGB_OPAQUE_UNDER_NOTHING_UINT8 = to_uint8(_SRGB_OPAQUE / _OPAQUE_DENOMINATOR)


@numba.njit(cache=True, nogil=True, inline="always")
def _srgb_index(linear: float) -> int:
    clipped = min(max(linear, np.float32(0.0)), np.float32(1.0))
    return int(clipped * np.float32(_LINEAR_TO_SRGB_STEPS) + np.float32(0.5))


@numba.njit(cache=True, nogil=True, inline="always")
def _srgb_over(
    linear: float, weight: float, under: float, under_weight: float, denominator: float, table: np.ndarray
) -> float:
    return (table[_srgb_index(linear)] * weight + under * under_weight) / denominator


@numba.njit(cache=True, nogil=True)
def _composite_object_kernel(
    background: np.ndarray, linear: np.ndarray, alpha: np.ndarray, box: tuple, table: np.ndarray, opaque: np.ndarray
) -> None:
    """composite_object's blend over ``box`` (row0, row1, col0, col1), in place."""
    for r in range(box[0], box[1]):
        for c in range(box[2], box[3]):
            weight = alpha[r, c]
            if weight == 1:
                for k in range(3):
                    background[r, c, k] = opaque[_srgb_index(linear[r, c, k])]
                continue
            under_weight = np.float32(1.0) - weight
            denominator = (weight + under_weight) + _BLEND_EPSILON
            for k in range(3):
                background[r, c, k] = _srgb_over(
                    linear[r, c, k], weight, background[r, c, k], under_weight, denominator, table
                )


@numba.njit(cache=True, nogil=True)
def _composite_uint8_kernel(
    out: np.ndarray,
    linear: np.ndarray,
    alpha: np.ndarray,
    box: tuple,
    region: tuple,
    occluder_rgb: np.ndarray,
    occluder_alpha: np.ndarray,
    table: np.ndarray,
    opaque: np.ndarray,
) -> None:
    """composite_to_uint8 in one pass over ``region`` of ``out`` (uint8, in place): the object
    inside its ``box`` (composite_object's), then the occluder (when ``occluder_alpha`` is not
    empty), then to_uint8. A pixel neither covers is left alone: its level survives the round
    trip through float and blends at weight 0 unchanged (checked for all 256 levels). ``opaque``
    holds the bytes of a pixel the object covers fully and the occluder not at all."""
    has_occluder = occluder_alpha.size > 0
    to_float = np.float32(1.0 / 255.0)
    for r in range(region[0], region[1]):
        for c in range(region[2], region[3]):
            in_box = box[0] <= r < box[1] and box[2] <= c < box[3]
            weight = alpha[r, c] if in_box else np.float32(0.0)
            occluder_weight = occluder_alpha[r, c] if has_occluder else np.float32(0.0)
            if occluder_weight == 0:
                if weight == 0:
                    continue
                if weight == 1:
                    for k in range(3):
                        out[r, c, k] = opaque[_srgb_index(linear[r, c, k])]
                    continue
            under_weight = np.float32(1.0) - weight
            denominator = (weight + under_weight) + _BLEND_EPSILON
            occluder_under = np.float32(1.0) - occluder_weight
            occluder_denominator = (occluder_weight + occluder_under) + _BLEND_EPSILON
            for k in range(3):
                value = np.float32(out[r, c, k]) * to_float
                if in_box:
                    value = _srgb_over(linear[r, c, k], weight, value, under_weight, denominator, table)
                if has_occluder:
                    value = (occluder_rgb[r, c, k] * occluder_weight + value * occluder_under) / occluder_denominator
                value = min(max(value, np.float32(0.0)), np.float32(1.0))
                out[r, c, k] = np.uint8(value * np.float32(255.0) + np.float32(0.5))


_NO_OCCLUDER_RGB = np.zeros((0, 0, 3), np.float32)
_NO_OCCLUDER_ALPHA = np.zeros((0, 0), np.float32)


def _float32_c(array: np.ndarray) -> np.ndarray:
    """``array`` as C-ordered float32 (no copy when it is already): one numba signature."""
    return np.ascontiguousarray(array, dtype=np.float32)


def composite_object(background: np.ndarray, linear_rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The rendered object (linear light, encoded to sRGB here) over the background (float32
    sRGB, modified in place and returned); work only inside the box where ``alpha > 0``. The
    same values as ``cv2.blendLinear(linear_to_srgb(linear_rgb), background, alpha, 1 - alpha)``
    there, in one pass."""
    box = _drawn_box(alpha)
    if box is None:
        return background
    work = _float32_c(background)  # the background itself when it is C-ordered float32, as the pipeline's is
    _composite_object_kernel(work, _float32_c(linear_rgb), _float32_c(alpha), box, _SRGB_ENCODE, _SRGB_OPAQUE)
    if work is not background:
        background[...] = work
    return background


def _drawn_box(alpha: np.ndarray) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1) of the pixels where ``alpha > 0``; None when there are none."""
    x, y, w, h = cv2.boundingRect((alpha > 0).view(np.uint8))
    return (y, y + h, x, x + w) if w and h else None


def composite_to_uint8(
    background: np.ndarray, linear_rgb: np.ndarray, alpha: np.ndarray, occlusion: Occlusion | None = None
) -> np.ndarray:
    """The object (linear light) and then the occluder over a uint8 background, encoded to
    uint8: the same bytes as converting the whole background to float, ``composite_object``,
    ``composite`` and ``to_uint8``, in one pass over the box where something is drawn (a
    pixel nothing covers keeps its level through that float round trip). For images that get
    no blur; a blurred image needs the whole float image."""
    box = _drawn_box(alpha)
    occluder_box = None if occlusion is None else _drawn_box(occlusion.alpha)
    out = np.array(background, dtype=np.uint8, order="C", copy=True)
    boxes = [b for b in (box, occluder_box) if b]
    if not boxes:
        return out
    region = (min(b[0] for b in boxes), max(b[1] for b in boxes), min(b[2] for b in boxes), max(b[3] for b in boxes))
    if occlusion is None:
        occluder_rgb, occluder_alpha, opaque = _NO_OCCLUDER_RGB, _NO_OCCLUDER_ALPHA, _SRGB_OPAQUE_UINT8
    else:
        occluder_rgb, occluder_alpha = _float32_c(occlusion.rgb), _float32_c(occlusion.alpha)
        opaque = _SRGB_OPAQUE_UNDER_NOTHING_UINT8  # composite() blends the whole region, at weight 0 too
    _composite_uint8_kernel(
        out,
        _float32_c(linear_rgb),
        _float32_c(alpha),
        box or (0, 0, 0, 0),
        region,
        occluder_rgb,
        occluder_alpha,
        _SRGB_ENCODE,
        opaque,
    )
    return out


def compile_kernels() -> None:
    """Compile (or load from numba's cache) this module's kernels for the types the pipeline
    passes, as raster.compile_kernels does for the rasteriser's."""
    linear, alpha = np.full((4, 4, 3), 0.5, np.float32), np.full((4, 4), 0.5, np.float32)
    composite_object(np.zeros((4, 4, 3), np.float32), linear, alpha)
    occlusion = Occlusion(rgb=linear, alpha=alpha, mask=alpha >= 0.5, target_fraction=0.5, achieved_fraction=0.5)
    for occluder in (None, occlusion):
        composite_to_uint8(np.zeros((4, 4, 3), np.uint8), linear, alpha, occluder)
