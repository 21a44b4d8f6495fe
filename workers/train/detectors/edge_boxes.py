"""Edge Boxes object proposals (Zitnick & Dollár 2014) for the Fast R-CNN detector.

OpenCV contrib's ``cv2.ximgproc.EdgeBoxes`` scores boxes from an edge magnitude map and an
edge orientation map. Its usual source of those maps, the Structured Edge Detector, needs a
model file that is not shipped, so the maps here come from image gradients: Sobel on a
Gaussian-smoothed image (per colour channel, strongest channel wins), orientation
``atan2(gy, gx) mod π`` (the convention of the SED's ``computeOrientation``), thin edges by
non-maximum suppression across the edge, magnitudes scaled to [0, 1].

Proposals never depend on ground truth: the Edge Boxes output plus the whole-image box.
They are cached per image content (an in-memory LRU, and optionally an ``.npz`` file beside
the image) so training and inference compute them once per image.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

DEFAULT_MAX_BOXES = 200
# Bump when the proposal algorithm changes, so stale cache files are recomputed.
_ALGORITHM_VERSION = 1
_CACHE_SUFFIX = ".edgeboxes.npz"


def edge_maps(image: np.ndarray, sigma: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Edge magnitude in [0, 1] (non-maximum suppressed) and orientation in [0, π), float32."""
    import cv2

    pixels = image.astype(np.float32) / 255.0
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if sigma > 0:
        pixels = cv2.GaussianBlur(pixels, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
        if pixels.ndim == 2:
            pixels = pixels[:, :, None]
    gx = cv2.Sobel(pixels, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(pixels, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    if gx.ndim == 2:
        gx, gy = gx[:, :, None], gy[:, :, None]
    magnitude_per_channel = np.hypot(gx, gy)
    # The colour channel with the strongest gradient defines magnitude and direction.
    strongest = np.argmax(magnitude_per_channel, axis=2)[:, :, None]
    magnitude = np.take_along_axis(magnitude_per_channel, strongest, axis=2)[:, :, 0]
    gx = np.take_along_axis(gx, strongest, axis=2)[:, :, 0]
    gy = np.take_along_axis(gy, strongest, axis=2)[:, :, 0]
    orientation = np.mod(np.arctan2(gy, gx), np.pi).astype(np.float32)

    thin = _non_maximum_suppression(magnitude, orientation)
    peak = float(np.percentile(thin[thin > 0], 99)) if np.any(thin > 0) else 0.0
    if peak <= 1e-6:
        return np.zeros_like(magnitude, dtype=np.float32), orientation
    return np.clip(thin / peak, 0.0, 1.0).astype(np.float32), orientation


def _non_maximum_suppression(magnitude: np.ndarray, orientation: np.ndarray) -> np.ndarray:
    """Keep pixels that are a maximum along the gradient direction (4 quantised directions)."""
    padded = np.pad(magnitude, 1, mode="edge")
    h, w = magnitude.shape

    def shifted(dy: int, dx: int) -> np.ndarray:
        return padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]

    # Gradient direction quantised to 0°, 45°, 90°, 135° (orientation is mod π).
    sector = np.round(orientation / (np.pi / 4)).astype(np.int64) % 4
    neighbours = {0: ((0, 1), (0, -1)), 1: ((1, 1), (-1, -1)), 2: ((1, 0), (-1, 0)), 3: ((1, -1), (-1, 1))}
    keep = np.zeros(magnitude.shape, dtype=bool)
    for index, ((dy0, dx0), (dy1, dx1)) in neighbours.items():
        is_max = (magnitude >= shifted(dy0, dx0)) & (magnitude >= shifted(dy1, dx1))
        keep |= (sector == index) & is_max
    return np.where(keep, magnitude, 0.0).astype(np.float32)


def edge_box_proposals(
    image: np.ndarray,
    max_boxes: int = DEFAULT_MAX_BOXES,
    *,
    min_box_fraction: float = 0.006,
    alpha: float = 0.65,
    beta: float = 0.75,
    sigma: float = 1.5,
    edge_min_magnitude: float = 0.3,
) -> np.ndarray:
    """Edge Boxes proposals for an (H, W, 3) uint8 RGB image, as an (n, 4) float32 xyxy array.

    Boxes are in the image's pixels, best first, and the whole-image box is always the last
    row, so even a flat image yields one proposal. ``min_box_fraction`` is the smallest box
    area as a fraction of the image area (scale-free, unlike OpenCV's absolute default).
    ``edge_min_magnitude`` drops weak (mostly texture and noise) edges before grouping: on
    textured 128 px renders it cuts the run time several-fold at no loss of recall.
    """
    import cv2

    image = np.asarray(image)
    if image.ndim not in (2, 3) or image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"edge_box_proposals: expected an (H, W, 3) image, got shape {image.shape}")
    if max_boxes < 1:
        raise ValueError(f"edge_box_proposals: max_boxes must be at least 1, got {max_boxes}")
    height, width = image.shape[:2]
    whole_image = np.array([[0.0, 0.0, float(width), float(height)]], dtype=np.float32)
    if height < 8 or width < 8:
        # Too small for edges worth grouping; the whole image is the only sensible box.
        return whole_image

    magnitude, orientation = edge_maps(image, sigma=sigma)
    if not np.any(magnitude > 0):
        return whole_image
    edge_boxes = cv2.ximgproc.createEdgeBoxes(
        alpha=alpha,
        beta=beta,
        maxBoxes=max_boxes - 1,
        minBoxArea=max(4.0, min_box_fraction * height * width),
        edgeMinMag=edge_min_magnitude,
    )
    result = edge_boxes.getBoundingBoxes(magnitude, orientation)
    boxes_xywh = result[0] if isinstance(result, tuple) else result
    boxes_xywh = np.asarray(boxes_xywh, dtype=np.float32).reshape(-1, 4)
    boxes = np.concatenate([boxes_xywh[:, :2], boxes_xywh[:, :2] + boxes_xywh[:, 2:]], axis=1)
    boxes[:, 0::2] = np.clip(boxes[:, 0::2], 0, width)
    boxes[:, 1::2] = np.clip(boxes[:, 1::2], 0, height)
    valid = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    return np.concatenate([boxes[valid], whole_image], axis=0).astype(np.float32)


def image_key(image: np.ndarray, max_boxes: int) -> str:
    """Content hash of the pixels and the proposal settings: equal keys, equal proposals."""
    digest = hashlib.sha1()
    digest.update(repr((image.shape, str(image.dtype), max_boxes, _ALGORITHM_VERSION)).encode())
    digest.update(np.ascontiguousarray(image).data)
    return digest.hexdigest()


class ProposalCache:
    """Edge Boxes proposals keyed by image content: an in-memory LRU over optional files.

    ``proposals(image, path)`` returns the cached proposals when the pixels were seen before
    (in memory, or in ``path`` + ``.edgeboxes.npz`` holding the same content hash), and
    computes and stores them otherwise. A read-only image folder only disables the file.
    """

    def __init__(self, max_boxes: int = DEFAULT_MAX_BOXES, capacity: int = 8192) -> None:
        self.max_boxes = max_boxes
        self.capacity = capacity
        self._memory: OrderedDict[str, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        self.file_hits = 0
        self.misses = 0

    def clear(self) -> None:
        """Forget every proposal held in memory (files beside images stay)."""
        with self._lock:
            self._memory.clear()

    @staticmethod
    def cache_path(image_path: str | Path) -> Path:
        image_path = Path(image_path)
        return image_path.with_name(image_path.name + _CACHE_SUFFIX)

    def proposals(self, image: np.ndarray, image_path: str | Path | None = None) -> np.ndarray:
        key = image_key(image, self.max_boxes)
        with self._lock:
            cached = self._memory.get(key)
            if cached is not None:
                self._memory.move_to_end(key)
                self.hits += 1
                return cached
        boxes = self._read_file(image_path, key) if image_path is not None else None
        if boxes is not None:
            self.file_hits += 1
        else:
            self.misses += 1
            boxes = edge_box_proposals(image, self.max_boxes)
            if image_path is not None:
                self._write_file(image_path, key, boxes)
        boxes.setflags(write=False)
        with self._lock:
            self._memory[key] = boxes
            while len(self._memory) > self.capacity:
                self._memory.popitem(last=False)
        return boxes

    def _read_file(self, image_path: str | Path, key: str) -> np.ndarray | None:
        path = self.cache_path(image_path)
        try:
            with np.load(path, allow_pickle=False) as stored:
                if str(stored["key"]) != key:
                    return None  # the image changed since: recompute
                return np.asarray(stored["boxes"], dtype=np.float32).reshape(-1, 4)
        except (OSError, KeyError, ValueError):
            return None

    def _write_file(self, image_path: str | Path, key: str, boxes: np.ndarray) -> None:
        path = self.cache_path(image_path)
        try:
            descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        except OSError:
            return  # the cache beside the image is an optimisation: an unwritable folder is no error
        try:
            with os.fdopen(descriptor, "wb") as handle:
                np.savez(handle, key=np.array(key), boxes=boxes)
            os.chmod(temporary, 0o644)
            os.replace(temporary, path)  # atomic: concurrent workers never read half a file
        except OSError:
            with contextlib.suppress(OSError):
                os.unlink(temporary)


_shared_caches: dict[int, ProposalCache] = {}


def shared_cache(max_boxes: int = DEFAULT_MAX_BOXES) -> ProposalCache:
    """The process-wide cache for a proposal budget (training and inference share it)."""
    cache = _shared_caches.get(max_boxes)
    if cache is None:
        cache = _shared_caches.setdefault(max_boxes, ProposalCache(max_boxes))
    return cache
