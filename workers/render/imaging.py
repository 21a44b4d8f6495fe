"""The camera's own 2D stages after compositing: lens distortion, sensor noise, JPEG.

* Radial distortion (``distortion`` = k1): an output pixel at normalised radius r (1 at the
  image corners, from the image centre) shows the ideal image at radius r × (1 + k1 r²) / s,
  with s = max(1, 1 + k1) so that no output pixel looks outside the rendered frame: barrel
  (k1 > 0) squeezes the edges towards the centre, pincushion (k1 < 0) stretches them. The image
  is resampled bilinearly (cv2.remap) and each object's visible mask (nearest sample of its
  coverage ≥ 0.5) with it, so boxes follow the distorted object.
* Sensor noise (``noise_sigma``): zero-mean Gaussian noise of that standard deviation in 8-bit
  levels, independent per pixel and channel, added before quantisation.
* JPEG (``jpeg_quality`` < 100): the 8-bit image is encoded and decoded at that quality
  (OpenCV's libjpeg, 4:2:0 chroma subsampling); 100 means the stage is skipped.

Each stage does nothing at its canonical value (the pipeline does not call it).
"""

from __future__ import annotations

import cv2
import numpy as np


def distortion_maps(width: int, height: int, k1: float) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap's (map_x, map_y): where each output pixel centre samples the ideal image."""
    cx, cy = width / 2.0, height / 2.0
    corner = np.hypot(cx, cy)
    x = (np.arange(width, dtype=np.float64) + 0.5 - cx) / corner
    y = (np.arange(height, dtype=np.float64) + 0.5 - cy) / corner
    gx, gy = np.meshgrid(x, y)
    factor = (1.0 + k1 * (gx * gx + gy * gy)) / max(1.0, 1.0 + k1)
    map_x = (gx * factor * corner + cx - 0.5).astype(np.float32)
    map_y = (gy * factor * corner + cy - 0.5).astype(np.float32)
    return map_x, map_y


def distort(image: np.ndarray, masks: list[np.ndarray], k1: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """The float image and the boolean masks through radial distortion ``k1``."""
    height, width = image.shape[:2]
    map_x, map_y = distortion_maps(width, height, k1)
    warped = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    warped_masks = [
        cv2.remap(mask.view(np.uint8), map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT).astype(bool)
        for mask in masks
    ]
    return warped, warped_masks


def add_noise(image: np.ndarray, sigma_levels: float, rng: np.random.Generator) -> np.ndarray:
    """``image`` (float32 sRGB in [0, 1]) plus Gaussian noise of ``sigma_levels`` / 255."""
    noise = rng.standard_normal(image.shape, dtype=np.float32) * np.float32(sigma_levels / 255.0)
    return image + noise


def jpeg_round_trip(image_u8: np.ndarray, quality: int) -> np.ndarray:
    """The uint8 RGB image as a JPEG decoder shows it after encoding at ``quality`` (1..100)."""
    ok, encoded = cv2.imencode(
        ".jpg", cv2.cvtColor(image_u8, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
    )
    if not ok:
        raise RuntimeError(f"JPEG encoding at quality {quality} failed")
    return cv2.cvtColor(cv2.imdecode(encoded, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def distort_points(points: np.ndarray, width: int, height: int, k1: float) -> np.ndarray:
    """Where ideal-image points (n, 2) land in the distorted image (the inverse of
    ``distortion_maps``' sampling, by Newton's method on the radius)."""
    points = np.asarray(points, np.float64).reshape(-1, 2)
    centre = np.array([width / 2.0, height / 2.0])
    corner = float(np.hypot(*centre))
    scale = max(1.0, 1.0 + k1)
    offset = (points - centre) / corner
    r_source = np.hypot(offset[:, 0], offset[:, 1])
    r = r_source.copy()
    for _ in range(30):  # r (1 + k r^2) / s = r_source, monotone on the radii that matter
        value = r * (1.0 + k1 * r * r) / scale - r_source
        slope = (1.0 + 3.0 * k1 * r * r) / scale
        r = np.maximum(r - value / np.where(np.abs(slope) > 1e-9, slope, 1e-9), 0.0)
    ratio = np.divide(r, r_source, out=np.ones_like(r), where=r_source > 1e-12)
    return centre + offset * ratio[:, None] * corner


def distorted_annotation(annotation, mask: np.ndarray, k1: float):
    """An Annotation of the undistorted image, carried through distortion ``k1``: the visible
    box from the distorted mask (RenderRejected when distortion left too little of it), the
    amodal box from its distorted corners and edge midpoints, the visible fraction unchanged
    (distortion moves pixels; what is hidden stays hidden)."""
    from workers.render.annotation import MIN_BOX_SIDE, MIN_VISIBLE_PIXELS, Annotation, RenderRejected, tight_box

    height, width = mask.shape
    pixels = int(np.count_nonzero(mask))
    box = tight_box(mask)
    if box is None or pixels < MIN_VISIBLE_PIXELS or min(box[2] - box[0], box[3] - box[1]) < MIN_BOX_SIDE:
        raise RenderRejected(f"target lost to lens distortion {k1:+.3f}: {pixels} visible pixels left")
    x0, y0, x1, y1 = annotation.amodal_box
    xm, ym = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    outline = np.array([[x0, y0], [xm, y0], [x1, y0], [x1, ym], [x1, y1], [xm, y1], [x0, y1], [x0, ym]])
    moved = distort_points(outline, width, height, k1)
    amodal_box = [float(v) for v in (*moved.min(axis=0), *moved.max(axis=0))]
    return Annotation(box, amodal_box, annotation.visible_fraction, pixels, annotation.amodal_pixels)
