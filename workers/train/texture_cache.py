"""The texture check's keypoints and FLANN trees kept on disk between processes.

Building a check (SIFT over each texture's views, then the KD-trees) takes seconds, which a
process checking one image (`foldwise detect`, a detect worker's first request) would spend
mostly there. Given a cache folder, the keypoints and the trees are kept there, keyed by
everything that makes them (``cache_key``: the textures' pixels, the SIFT and tree settings,
OpenCV's version), and read back instead of made again: the same check, to the byte.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from foldwise.store import file_sha256

log = logging.getLogger(__name__)

# Raised when what a cached check holds changes meaning (its key covers the settings above).
CACHE_VERSION = 1
# Checks kept in a cache folder (about 30 MB each for the five default textures); the ones read or
# written longest ago are removed past this, so a user trying texture after texture does not fill a disk.
CACHE_KEEP = 8


@dataclass
class TextureFeatures:
    """SIFT keypoints of every class's texture and its tilted views, in the textures' pixels."""

    descriptors: np.ndarray  # (n, 128) float32, all classes' keypoints
    labels: np.ndarray  # (n,) int64 class index of each
    points: np.ndarray  # (n, 2) float32 keypoint position in its texture
    sizes: list[tuple[int, int]]  # (width, height) of each class's texture


def cache_key(grays: list[np.ndarray], made_by: tuple) -> str:
    """What a cached check is filed under: the textures' pixels in class order, and ``made_by``,
    every setting and version that changes their keypoints or trees (with ``CACHE_VERSION``)."""
    digest = hashlib.sha256()
    digest.update(repr((CACHE_VERSION, *made_by)).encode())
    for gray in grays:
        digest.update(repr(gray.shape).encode())
        digest.update(np.ascontiguousarray(gray).tobytes())
    return digest.hexdigest()[:32]


@dataclass
class Stored:
    features: TextureFeatures
    index_digest: str  # sha256 of the trees' file written with these features ("" for none)


class CheckCache:
    """One check's keypoints (``KEY.npz``) and FLANN trees (``KEY.flann``) in a folder. Each file
    is written whole and then renamed into place, so a reader finds the old file or the new one;
    the keypoints name the trees' digest, so a pair from two writers is never read together. A
    file that cannot be read or written is made again, with a warning: the cache only saves time."""

    def __init__(self, directory: Path, key: str) -> None:
        self.directory = directory
        self.features_path = directory / f"{key}.npz"
        self.index_path = directory / f"{key}.flann"

    def load(self) -> Stored | None:
        try:
            with np.load(self.features_path) as stored:
                descriptors = stored["descriptors"].astype(np.float32)
                labels = stored["labels"].astype(np.int64)
                points = stored["points"].astype(np.float32)
                sizes = [(int(width), int(height)) for width, height in stored["sizes"].reshape(-1, 2)]
                index_digest = str(stored["index_digest"])
        except FileNotFoundError:
            return None
        except Exception as error:  # a torn or foreign file: np.load raises several kinds
            log.warning("texture check: cached keypoints %s unreadable (%s); made again", self.features_path, error)
            return None
        n = len(descriptors)
        if (
            descriptors.shape != (n, 128)
            or labels.shape != (n,)
            or points.shape != (n, 2)
            or (n and labels.max() >= len(sizes))
        ):
            log.warning("texture check: cached keypoints %s malformed; made again", self.features_path)
            return None
        try:
            os.utime(self.features_path)  # read now: the last to be removed (CACHE_KEEP)
        except OSError:
            pass
        return Stored(TextureFeatures(descriptors, labels, points, sizes), index_digest)

    def load_index(self, descriptors: np.ndarray, digest: str):
        """The stored trees over ``descriptors``, or None where there are none that match them."""
        import cv2

        try:
            if not digest or file_sha256(self.index_path) != digest:
                return None
            index = cv2.flann_Index()
            if not index.load(descriptors, str(self.index_path)):
                return None
        except (OSError, cv2.error) as error:
            log.warning("texture check: cached trees %s unreadable (%s); made again", self.index_path, error)
            return None
        return index

    def store(self, features: TextureFeatures, index) -> None:
        import cv2

        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            digest = ""
            if index is not None:
                temporary = self._temporary(".flann")
                try:
                    index.save(str(temporary))
                    digest = file_sha256(temporary)
                    os.replace(temporary, self.index_path)
                finally:
                    temporary.unlink(missing_ok=True)
            descriptors = features.descriptors
            # OpenCV's SIFT descriptors are whole numbers in [0, 255]: a byte each, a quarter the size.
            if descriptors.size and np.array_equal(descriptors, np.clip(np.round(descriptors), 0, 255)):
                descriptors = descriptors.astype(np.uint8)
            temporary = self._temporary(".npz")
            try:
                with open(temporary, "wb") as handle:
                    np.savez(
                        handle,
                        descriptors=descriptors,
                        labels=features.labels,
                        points=features.points,
                        sizes=np.array(features.sizes, np.int64).reshape(-1, 2),
                        index_digest=np.array(digest),
                    )
                os.replace(temporary, self.features_path)
            finally:
                temporary.unlink(missing_ok=True)
        except (OSError, cv2.error) as error:
            log.warning("texture check: cannot keep keypoints in %s (%s); made again next time", self.directory, error)
            return
        self._prune()

    def _prune(self) -> None:
        """Remove all but the ``CACHE_KEEP`` checks read or written last (a check another process
        is reading as it goes is made again there: the cache only saves time)."""

        def last_used(path: Path) -> int:
            try:
                return path.stat().st_mtime_ns
            except OSError:  # removed meanwhile by another process
                return -1

        kept = sorted(self.directory.glob("*.npz"), key=last_used, reverse=True)
        for features in kept[CACHE_KEEP:]:
            for path in (features, features.with_suffix(".flann")):
                try:
                    path.unlink(missing_ok=True)
                except OSError as error:
                    log.warning("texture check: cannot remove %s from the cache (%s)", path, error)

    def _temporary(self, suffix: str) -> Path:
        descriptor, name = tempfile.mkstemp(prefix=".", suffix=suffix, dir=self.directory)
        os.close(descriptor)
        return Path(name)
