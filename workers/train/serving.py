"""Celery task ``foldwise.detect``: one image through one trained ω, for ``POST /models/{id}/detect``.

Served by ``foldwise worker detect`` (the train image, queue ``detect``), so the API stays free
of torch. The image travels base64-encoded in the message; the reply is plain JSON. A bad
image is an answer (``{"error": ...}``), not an exception: the API turns it into a 4xx.
"""

from __future__ import annotations

import base64
import binascii
import time
from functools import lru_cache
from typing import Any

from foldwise import store
from workers.app import DETECT_TASK, app

# An image larger than this is refused from its header, before decoding (a 69-byte PNG can
# claim 50000x50000 pixels; a 261 KB one holds 16384x16384 zeros, 1.5 GB decoded).
MAX_PIXELS = 4096 * 4096


@lru_cache(maxsize=4)
def _detector(path: str, modified_ns: int):
    """Loaded detectors, by file and modification time (a rewritten checkpoint is reloaded)."""
    from workers.train.checkpoint import load_detector

    return load_detector(path)


def detect_image(checkpoint: str, image: bytes, score_threshold: float = 0.0) -> dict[str, Any]:
    """Detections of the checkpoint (store-relative path) on an encoded image (PNG, JPEG...)."""
    import cv2
    import numpy as np

    from foldwise.images import ImageError, image_size
    from workers.train.checkpoint import detect_object, detection_records

    started = time.perf_counter()
    try:
        image_size(image, max_pixels=MAX_PIXELS)  # the header alone, before a pixel is decoded
    except ImageError as error:
        return {"error": str(error)}
    try:
        pixels = cv2.imdecode(np.frombuffer(image, dtype=np.uint8), cv2.IMREAD_COLOR)
    except cv2.error as error:  # OpenCV's own limits and corrupt data past the header
        return {"error": f"the image does not decode: {' '.join(str(error).split())[:300]}"}
    if pixels is None:
        return {"error": "the body is not an image OpenCV can decode (send PNG or JPEG)"}
    height, width = pixels.shape[:2]
    if height * width > MAX_PIXELS:  # a header that understated the size
        return {"error": f"image of {width}x{height} pixels is larger than {MAX_PIXELS} pixels"}
    path = store.resolve(checkpoint)
    if not path.is_file():
        return {"error": f"checkpoint {checkpoint} is not in the artifact store", "missing": True}
    detector = _detector(str(path), path.stat().st_mtime_ns)
    (found,) = detect_object(detector, [cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB)])
    classes = detector.classes
    check = detector.texture_check()
    return {
        "image": {"width": int(width), "height": int(height)},
        "classes": classes,
        "detections": detection_records(found, classes, score_threshold),
        "seconds": time.perf_counter() - started,
        "members": len(detector.meta.get("members", ())) or 1,  # an ensemble file's detectors
        "texture_check": check is not None,
        "texture_search": check is not None and check.search,
        # Whether the scores are calibrated (foldwise calibrate): the chance each box is true.
        "calibrated": check is not None and check.calibration is not None,
    }


@app.task(name=DETECT_TASK, ignore_result=False, acks_late=False)
def detect(checkpoint: str, image_base64: str, score_threshold: float = 0.0) -> dict[str, Any]:
    # acks_late off: a request that killed its worker is not worth retrying on another.
    try:
        image = base64.b64decode(image_base64, validate=True)
    except (binascii.Error, ValueError) as error:
        return {"error": f"the image is not valid base64: {error}"}
    return detect_image(checkpoint, image, score_threshold)
