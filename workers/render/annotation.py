"""Ground truth of a rendered image: visible box, amodal box, visible fraction; rejections.

Definitions (pixel-edge boxes as in scene.py):

* visible mask: pixels whose centre the target sheet covers (its silhouette, so parts of the
  sheet hidden behind its own folds do not count twice), inside the image, not hidden by the
  external occluder;
* ``box``: tight box of the visible mask. It is what a detector must find;
* ``amodal_box``: tight box of the whole silhouette, including what lies outside the image
  and behind the occluder (may extend past the image edges);
* ``visible_fraction`` = visible pixels / amodal pixels, where the amodal pixels count the
  whole silhouette, off-image part included (sampled at the same pixel centres on a canvas
  grown past the image border). 1 for an unoccluded sheet fully inside the image.

Blur (focus, motion) leaves all three unchanged: they describe the sharp geometry.

A target that is invisible, or smaller than ``MIN_VISIBLE_PIXELS`` visible pixels, or whose
box is thinner than ``MIN_BOX_SIDE`` pixels, is rejected with :class:`RenderRejected`, so
no degenerate box ever reaches a dataset.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

MIN_VISIBLE_PIXELS = 16
MIN_BOX_SIDE = 2.0


class RenderRejected(Exception):
    """A θ whose image cannot be used; ``reason`` says why (recorded when resampling)."""

    def __init__(self, reason: str, reasons: list[str] | None = None):
        super().__init__(reason)
        self.reason = reason
        # Every reason in order, when this ends a series of resamples.
        self.reasons = list(reasons) if reasons is not None else [reason]


@dataclass(frozen=True)
class Annotation:
    box: list[float]
    amodal_box: list[float]
    visible_fraction: float
    visible_pixels: int
    amodal_pixels: float


def tight_box(mask: np.ndarray) -> list[float] | None:
    """[x0, y0, x1, y1] in pixel edges of a boolean mask; None when it is empty."""
    x, y, width, height = cv2.boundingRect(np.ascontiguousarray(mask).view(np.uint8))  # of the non-zero pixels
    if width == 0:
        return None
    return [float(x), float(y), float(x + width), float(y + height)]


def annotate(visible_mask: np.ndarray, amodal_pixels: float, amodal_box: list[float] | None) -> Annotation:
    """The annotation of a visible target mask, or RenderRejected when it is unusable."""
    if amodal_box is None or amodal_pixels <= 0:
        raise RenderRejected("target outside the view: the sheet projects to no pixel centre")
    visible_pixels = int(np.count_nonzero(visible_mask))
    if visible_pixels == 0:
        raise RenderRejected("target invisible: no pixel of the sheet inside the image is left visible")
    if visible_pixels < MIN_VISIBLE_PIXELS:
        raise RenderRejected(f"target too small: {visible_pixels} visible pixels (minimum {MIN_VISIBLE_PIXELS})")
    box = tight_box(visible_mask)
    width, height = box[2] - box[0], box[3] - box[1]
    if min(width, height) < MIN_BOX_SIDE:
        raise RenderRejected(
            f"target too thin: visible box {width:g}x{height:g} pixels (minimum side {MIN_BOX_SIDE:g})"
        )
    fraction = min(1.0, visible_pixels / float(amodal_pixels))
    return Annotation(
        box=box,
        amodal_box=[float(v) for v in amodal_box],
        visible_fraction=float(fraction),
        visible_pixels=visible_pixels,
        amodal_pixels=float(amodal_pixels),
    )
