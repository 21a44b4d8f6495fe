"""Train-time augmentation: box-aware image transforms (torchvision.transforms.v2), per step.

Rendering already varies everything the scene holds (pose, light, clutter, lens, noise); these
transforms vary the same rendered image a little further each time it is drawn into a batch,
at no render cost: a zoom on one target (the sheet from a third of the frame to overflowing
it), a random resized crop at a random aspect ratio (objects larger, cut by the frame, and
frames that are not square), photometric
distortion (brightness, contrast, saturation, hue), greyscale, Gaussian blur, sensor noise and
JPEG, each applied with its own probability (``DetectorConfig.augmentation``), and quarter
turns. No flip: a mirrored print is not the object (foldwise detects one particular texture).
No rotation by other angles: a rotated axis-aligned box is looser than the object's (the
renderer rotates the sheet instead); a quarter turn keeps the box exact, and gives every
rendered view the other three camera rolls at no render cost.

Boxes follow the crop and are clipped to it; a box left thinner than ``MIN_BOX_SIDE`` pixels
is dropped with its label (``SanitizeBoundingBoxes``). The randomness comes from torch's
generator, which ``train_detector`` seeds: the same seed gives the same augmented batches.
Off by default (the paper trains without augmentation); the settings are recorded in every
checkpoint's metadata with the rest of the detector config.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from foldwise.config import AugmentationConfig

MIN_BOX_SIDE = 2.0
# The random crop keeps this share of the image area at least, at a width / height ratio drawn
# log-uniformly in CROP_ASPECT, and comes out at that aspect with its long side at the
# detector's input size. Renders are square; photographs are 4:3, 3:2, 16:9 or portrait, and
# a detector trained on square frames only learns where a square frame's borders are: on 4:3
# images of the same objects its boxes came out stretched (IoU < 0.5 at 0.9 confidence).
CROP_SCALE = (0.35, 1.0)
CROP_ASPECT = (9 / 16, 16 / 9)
# The object zoom frames one target so that its long side spans ZOOM_FILL of the frame's long
# side (log-uniform): from a third of the frame to half again more than it, the sheet cut by
# the borders. Renders show the sheet at 10-60% of the frame; a camera close to a print shows
# it filling or overflowing the frame, and a detector that never saw that misses it outright.
# ZOOM_CUT of the views shift the object so far that the frame cuts it, keeping ZOOM_KEEP of it.
ZOOM_FILL = (0.35, 1.5)
ZOOM_KEEP = 0.4
ZOOM_CUT = 0.3
BLUR_SIGMA = (0.3, 1.5)
NOISE_SIGMA = 0.03  # of full scale, on images in 0..1
JPEG_QUALITY = (20, 90)


def build_augmentation(config: AugmentationConfig, crop_size: tuple[int, int]):
    """A v2 transform of (image uint8 (3, H, W), {"boxes": BoundingBoxes, "labels"}), or None
    when augmentation is off. A crop comes out at ``crop_size`` (the detector's input size,
    which every image is resized to anyway)."""
    if not config.enabled:
        return None
    from torchvision.transforms import v2

    steps = []
    if config.quarter_turn > 0:
        steps.append(v2.RandomApply([_quarter_turn()], p=config.quarter_turn))
    if config.zoom > 0:
        steps.append(v2.RandomApply([_object_zoom(max(crop_size))], p=config.zoom))
    if config.crop > 0:
        steps.append(v2.RandomApply([_aspect_crop(max(crop_size))], p=config.crop))
    if config.photometric > 0:
        steps.append(v2.RandomPhotometricDistort(p=config.photometric))
    if config.grayscale > 0:
        steps.append(v2.RandomGrayscale(p=config.grayscale))
    if config.blur > 0:
        steps.append(v2.RandomApply([v2.GaussianBlur(kernel_size=5, sigma=BLUR_SIGMA)], p=config.blur))
    if config.jpeg > 0:
        steps.append(v2.RandomApply([_jpeg_transform()], p=config.jpeg))
    steps.append(v2.ToDtype(torch.float32, scale=True))
    if config.noise > 0:
        steps.append(v2.RandomApply([v2.GaussianNoise(sigma=NOISE_SIGMA, clip=True)], p=config.noise))
    # A crop's resize can leave a clipped edge a float's breadth past the frame (42.000004 in a
    # 42-px frame), which SanitizeBoundingBoxes treats as outside the image and drops the box.
    steps.append(v2.ClampBoundingBoxes())
    steps.append(v2.SanitizeBoundingBoxes(min_size=MIN_BOX_SIDE))
    return v2.Compose(steps)


def _quarter_turn():
    """A turn by one, two or three quarters anticlockwise (drawn uniformly), the frame turned
    with it: pixels move without resampling (``torch.rot90``) and boxes exactly. torchvision's
    ``rotate(expand=True)`` is not used: on an image without boxes it turns the image but leaves
    the (empty) boxes' canvas as it was, and the next transform then finds two image sizes
    ("Found multiple HxW dimensions") whenever the image is not square."""
    from torchvision import tv_tensors
    from torchvision.transforms import v2

    class RandomQuarterTurn(v2.Transform):
        def make_params(self, flat_inputs):
            return {"turns": int(torch.randint(1, 4, ()).item())}

        def transform(self, inpt, params):
            if isinstance(inpt, tv_tensors.BoundingBoxes):
                return quarter_turn_boxes(inpt, params["turns"])
            if isinstance(inpt, (tv_tensors.Image, tv_tensors.Mask)):
                return tv_tensors.wrap(torch.rot90(inpt.as_subclass(Tensor), params["turns"], dims=(-2, -1)), like=inpt)
            return inpt

    return RandomQuarterTurn()


def quarter_turn_boxes(boxes, turns: int):
    """XYXY ``BoundingBoxes`` of a (H, W) canvas after ``turns`` quarter turns anticlockwise of
    the image (``torch.rot90(image, turns, dims=(-2, -1))``), with the turned canvas size."""
    from torchvision import tv_tensors

    if boxes.format != tv_tensors.BoundingBoxFormat.XYXY:
        raise ValueError(f"quarter turns need XYXY boxes, got {boxes.format}")
    height, width = boxes.canvas_size
    x0, y0, x1, y1 = boxes.as_subclass(Tensor).unbind(-1)
    turns %= 4
    if turns == 0:
        turned, canvas = (x0, y0, x1, y1), (height, width)
    elif turns == 1:  # (x, y) -> (y, W - x)
        turned, canvas = (y0, width - x1, y1, width - x0), (width, height)
    elif turns == 2:  # (x, y) -> (W - x, H - y)
        turned, canvas = (width - x1, height - y1, width - x0, height - y0), (height, width)
    else:  # (x, y) -> (H - y, x)
        turned, canvas = (height - y1, x0, height - y0, x1), (width, height)
    return tv_tensors.wrap(torch.stack(turned, dim=-1), like=boxes, canvas_size=canvas)


def _aspect_crop(long_side: int):
    """A random crop (CROP_SCALE of the area, aspect in CROP_ASPECT, undistorted) resized so
    its long side is ``long_side``; boxes follow (torchvision's resized_crop kernels)."""
    from torchvision.transforms import v2
    from torchvision.transforms.v2 import functional as F

    class RandomAspectResizedCrop(v2.Transform):
        def make_params(self, flat_inputs):
            height, width = v2.query_size(flat_inputs)
            area = height * width * float(torch.empty(()).uniform_(*CROP_SCALE))
            log_low, log_high = np.log(CROP_ASPECT[0]), np.log(CROP_ASPECT[1])
            aspect = float(np.exp(torch.empty(()).uniform_(log_low, log_high).item()))
            crop_w = int(round(min(width, np.sqrt(area * aspect))))
            crop_h = int(round(min(height, crop_w / aspect)))
            crop_w, crop_h = max(crop_w, 1), max(crop_h, 1)
            top = int(torch.randint(0, height - crop_h + 1, ()).item())
            left = int(torch.randint(0, width - crop_w + 1, ()).item())
            scale = long_side / max(crop_h, crop_w)
            size = [max(1, int(round(crop_h * scale))), max(1, int(round(crop_w * scale)))]
            return {"top": top, "left": left, "height": crop_h, "width": crop_w, "size": size}

        def transform(self, inpt, params):
            return self._call_kernel(F.resized_crop, inpt, **params, antialias=True)

    return RandomAspectResizedCrop()


def _object_zoom(long_side: int):
    """A crop around one target (drawn at random) in which the target's long side spans
    ZOOM_FILL of the crop's long side, at an aspect in CROP_ASPECT, shifted at random so the
    target may be cut by the frame; resized so its long side is ``long_side``. The crop stays
    inside the image (no padded borders): where the image is too small for the drawn fill, the
    crop is the largest the image allows. An image without targets is left as it is."""
    from torchvision import tv_tensors
    from torchvision.transforms import v2
    from torchvision.transforms.v2 import functional as F

    class RandomObjectZoom(v2.Transform):
        def make_params(self, flat_inputs):
            height, width = v2.query_size(flat_inputs)
            boxes = next((item for item in flat_inputs if isinstance(item, tv_tensors.BoundingBoxes)), None)
            if boxes is None or len(boxes) == 0:
                return {"skip": True}
            x0, y0, x1, y1 = (float(v) for v in boxes[int(torch.randint(0, len(boxes), ()).item())])
            object_side = max(x1 - x0, y1 - y0, 1.0)
            log_fill = torch.empty(()).uniform_(float(np.log(ZOOM_FILL[0])), float(np.log(ZOOM_FILL[1])))
            crop_long = object_side / float(np.exp(log_fill.item()))
            log_aspect = torch.empty(()).uniform_(float(np.log(CROP_ASPECT[0])), float(np.log(CROP_ASPECT[1])))
            aspect = float(np.exp(log_aspect.item()))  # width / height
            crop_w, crop_h = (crop_long, crop_long / aspect) if aspect >= 1 else (crop_long * aspect, crop_long)
            shrink = min(1.0, width / crop_w, height / crop_h)
            crop_w, crop_h = max(1, int(round(crop_w * shrink))), max(1, int(round(crop_h * shrink)))
            # Mostly the crop holds the whole object (its centre moves only within the slack);
            # in ZOOM_CUT of the views it moves so far that only ZOOM_KEEP of the object's width
            # and height (or of the crop's, when the object overflows it) stays in frame: the
            # object may be cut by the frame, never cut out.
            cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
            object_w, object_h = x1 - x0, y1 - y0
            if float(torch.rand(())) < ZOOM_CUT:
                reach_x = max(0.0, (crop_w + object_w) / 2 - ZOOM_KEEP * min(object_w, crop_w))
                reach_y = max(0.0, (crop_h + object_h) / 2 - ZOOM_KEEP * min(object_h, crop_h))
            else:
                reach_x, reach_y = max(0.0, (crop_w - object_w) / 2), max(0.0, (crop_h - object_h) / 2)
            cx += float(torch.empty(()).uniform_(-reach_x, reach_x))
            cy += float(torch.empty(()).uniform_(-reach_y, reach_y))
            left = int(round(min(max(cx - crop_w / 2, 0), width - crop_w)))
            top = int(round(min(max(cy - crop_h / 2, 0), height - crop_h)))
            scale = long_side / max(crop_h, crop_w)
            size = [max(1, int(round(crop_h * scale))), max(1, int(round(crop_w * scale)))]
            return {"skip": False, "top": top, "left": left, "height": crop_h, "width": crop_w, "size": size}

        def transform(self, inpt, params):
            if params["skip"]:
                return inpt
            params = {key: value for key, value in params.items() if key != "skip"}
            return self._call_kernel(F.resized_crop, inpt, **params, antialias=True)

    return RandomObjectZoom()


def _jpeg_transform():
    """JPEG at a quality drawn uniformly from JPEG_QUALITY, through OpenCV's libjpeg (the same
    codec as the renderer's sensor stage; torchvision's own JPEG coder is deprecated)."""
    import cv2
    from torchvision import tv_tensors
    from torchvision.transforms import v2

    class OpenCVJpeg(v2.Transform):
        def make_params(self, flat_inputs):
            low, high = JPEG_QUALITY
            return {"quality": int(torch.randint(low, high + 1, ()).item())}

        def transform(self, inpt, params):
            if not isinstance(inpt, tv_tensors.Image):
                return inpt
            array = inpt.permute(1, 2, 0).contiguous().numpy()
            ok, encoded = cv2.imencode(".jpg", array[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, params["quality"]])
            decoded = cv2.imdecode(encoded, cv2.IMREAD_COLOR)[:, :, ::-1]
            return tv_tensors.wrap(torch.from_numpy(np.ascontiguousarray(decoded)).permute(2, 0, 1), like=inpt)

    return OpenCVJpeg()


def augmented(
    transform, image: np.ndarray, boxes: np.ndarray, labels: np.ndarray, device: torch.device
) -> tuple[Tensor, dict[str, Tensor]]:
    """One sample through ``transform``: the image as a float tensor in 0..1 and its
    torchvision target (labels 1-based)."""
    from torchvision import tv_tensors

    height, width = image.shape[:2]
    tensor = tv_tensors.Image(torch.from_numpy(image).permute(2, 0, 1).contiguous())
    target = {
        "boxes": tv_tensors.BoundingBoxes(
            torch.as_tensor(boxes, dtype=torch.float32).reshape(-1, 4), format="XYXY", canvas_size=(height, width)
        ),
        "labels": torch.as_tensor(labels, dtype=torch.int64).reshape(-1) + 1,
    }
    out_image, out_target = transform(tensor, target)
    return (
        out_image.as_subclass(Tensor).to(device),
        {"boxes": out_target["boxes"].as_subclass(Tensor).to(device), "labels": out_target["labels"].to(device)},
    )
