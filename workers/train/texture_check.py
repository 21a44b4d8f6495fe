"""The texture check: each detection checked against its class's own texture, as a second opinion
on the network's score (``detector.texture_check``).

foldwise's detector looks for one known printed sheet per class, so the texture it was trained
on is evidence of its own: SIFT keypoints of the image inside a detection's box, matched to the
textures (Lowe's ratio test), and an affine map from the class's texture to those keypoints fitted
by RANSAC. Where at least ``MIN_INLIERS`` matches agree on one map, the map tells where the whole
sheet lies: the texture's outline, mapped into the image and clipped to the frame.

- Such a map confirms the detection: the outline becomes its box (whether the network's box was
  the whole sheet, a piece of it or a box around more), and its score rises above every box
  without such evidence (``0.9 + 0.1 * score``, so confirmed boxes keep their order). Boxes of one
  class that now overlap (IoU ≥ ``NMS_IOU``: two boxes on one sheet, confirmed by one outline)
  are merged to the best, as the detector's views are.
- A map that mirrors the texture is a false fit (a printed sheet shows its front), and so is one
  that squashes it flatter than ``MIN_AXIS_RATIO`` (a few clustered matches stretched into a
  strip across the frame): no evidence.
- A box whose keypoints match another class's texture far more often is renamed to that class
  where those matches agree on a map of its texture (which confirms it as that class): a count
  of matches alone renamed true sheets to the texture richest in keypoints, which clutter and
  grain match most (bench/README.md, "Renaming on a map").
- Every other box (too small or blurred for keypoints, a texture with few of them, or clutter
  matching nothing) keeps its class and its place against the paper's 0.8 cut: no evidence is
  not evidence against. Those at or above the cut rank below the confirmed ones
  (``0.8 + 0.5 * (score - 0.8)``, in [0.8, 0.9)), as the texture is the stronger evidence.

With ``search`` (``detector.texture_search``) the texture also finds sheets the network gave no
box for: over the whole image, each class's matches are fitted by RANSAC as above, one sheet
after another (its inliers taken out), and a map that ``SEARCH_MIN_INLIERS`` matches agree on,
not mirrored nor squashed flatter than ``MIN_AXIS_RATIO``, adds its outline as a
confirmed detection (scored ``0.9 + 0.1 * s``, ``s`` the network's best score for a box of that
class on it, ``MIN_SCORE`` where it had none as high: every confirmed box has been scored at
least that by the network or the search) before the merge. A sheet the network found and the check
confirmed merges with it; the search only adds what the network missed.

The textures' keypoints come from each texture as it is and from 8 views of it tilted 45° and
60° (``tilted_views``, after Morel & Yu's ASIFT): SIFT alone matches a sheet seen obliquely
poorly, and a sheet on a table or the ground is mostly seen so. A point of a texture then has
several copies, so the ratio test's rival is the nearest keypoint that is another point. The
nearest are looked up in FLANN's KD-trees over all the textures' keypoints (``FLANN_TREES``).

Keypoints are found on the image enlarged ``UPSCALE`` times (its longer side at most
``SIFT_MAX_SIDE``), with SIFT's contrast threshold at half its default (textures too): small and
low-contrast sheets give too few otherwise. The image can be sharpened first (an unsharp mask,
``sharpen``; off as built): it brought back fine detail of soft sheets in foldwise's 320×240 and
480×360 out-of-domain sets, but cost more than it gained in 640×480 frames (bench/README.md,
"Sharpening the image before SIFT").

A bent sheet is not an affine image of its texture, so the outline is approximate; the RANSAC
threshold (8% of the box's diagonal) leaves room for that. The constants
were chosen on foldwise's own out-of-domain set and are stable around it (bench/README.md,
"The texture check").

Building a check (SIFT over each texture's nine views, then the KD-trees) takes seconds, which a
process checking one image (`foldwise detect`, a detect worker's first request) would spend
mostly there. Given a ``cache_dir``, the textures' keypoints and the trees are kept there, keyed
by everything that makes them (the textures' pixels, the SIFT and tree settings, OpenCV's
version), and read back instead of made again: the same check, to the byte.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

# Lowe's ratio test: a keypoint's best texture match must beat its second best by this factor.
RATIO = 0.8
# Boxes scored below this are left alone (the network's own floor for what could be an object).
MIN_SCORE = 0.3
# Matches of one class inside a box that a RANSAC affine map must agree on before its outline counts.
MIN_INLIERS = 6
# A box is tried as another class where that class has this many times its own matches in it
# (and renamed where they agree on a map: MIN_INLIERS of them).
RENAME_FACTOR = 3
PAPER_CUT = 0.8  # the paper's score cut: boxes without evidence keep their side of it
CONFIRMED_FLOOR = 0.9  # confirmed boxes score from here: above every box without evidence
# Boxes without evidence at or above the cut are squeezed into [PAPER_CUT, CONFIRMED_FLOOR).
UNCONFIRMED_SPAN = (CONFIRMED_FLOOR - PAPER_CUT) / (1 - PAPER_CUT)
# Boxes of one class overlapping this much after the check are one (the detector's merge IoU).
NMS_IOU = 0.5
UPSCALE = 2
# ... but never past this longer side: a phone's 12-MP photograph (4032x3024) enlarged twice cost
# SIFT 25 s; shrunk to this, 1.0 s for as many matches (838 against 840 on one test scene).
SIFT_MAX_SIDE = 2048
# The search over the whole image (search=True): more agreeing matches than a box's check needs,
# as nothing but the texture vouches for the sheet (at 6 or 8 it added false sheets on
# foldwise's out-of-domain sets; at 10 none: bench/README.md, "The texture search").
SEARCH_MIN_INLIERS = 10
SEARCH_SHEETS_PER_CLASS = 4  # sheets of one class looked for per image, one after another
# RANSAC's first threshold, as a fraction of the image's diagonal (the sheet's size is unknown
# yet); the fit is then redone at the box check's 8% of the found outline's diagonal.
SEARCH_RANSAC_FRACTION = 0.02
SEARCH_MIN_SIDE = 8  # px: an outline narrower than this in the frame is no sheet to report
CONTRAST_THRESHOLD = 0.02  # OpenCV's default 0.04
# The image's unsharp mask before SIFT (``sharpen``; the textures are left as they are), off: amount
# 1 at sigma 1 px raised make run's pair on foldwise's three out-of-domain sets from 0.744 / 0.807 /
# 0.735 to 0.761 / 0.832 / 0.739 (in domain 0.913 -> 0.921), but lowered the fourth, 640x480 set,
# held out of that choice, from 0.844 to 0.785 (1.5: 0.807) and doubled the check's time there: a
# gain that depends on the frame's size is no default for photographs of any size (bench/README.md,
# "Sharpening the image before SIFT"; bench/texture_matching.py --sharpen measures it again).
SHARPEN_AMOUNT = 0.0
SHARPEN_SIGMA = 1.0
# Each texture's keypoints are also taken from views of it tilted (Morel & Yu's ASIFT): SIFT
# matches a sheet seen at most ~45-60° off straight on, and the wild's sheets lie on the ground,
# curl and face cameras low over it. Tilts √2 and 2 (45° and 60°) in four directions, 8 views
# beside the texture itself: on make run's pair, out of domain 0.721 / 0.748 / 0.699 -> 0.729 /
# 0.805 / 0.729, in domain 0.912 -> 0.916, for 7x the texture keypoints to match against
# (bench/README.md, "Tilted views of the textures").
TEXTURE_TILTS = (2**0.5, 2.0)
TEXTURE_TILT_DIRECTIONS = (0.0, 45.0, 90.0, 135.0)
# Two texture keypoints closer than this in one texture are one point (the ratio test's rival is
# the nearest other point), and this many neighbours are looked at to find that rival.
SAME_POINT_PX = 6.0
NEIGHBOURS = 10
# The image's keypoints are looked up among the textures' with FLANN's randomized KD-trees rather
# than compared with every one: against the five default textures' 56,329 keypoints, 8 trees and
# 256 checks keep 98-99% of the matches brute force lets through the ratio test, and the whole
# check ran 3.7-6.9x faster on make run's detections with the same mAP or up to 0.0012 more
# (bench/README.md, "FLANN in the check"). The trees are drawn at random: seeded, every index is the same.
FLANN_TREES = 8
FLANN_CHECKS = 256
FLANN_SEED = 0
# A map's smaller singular value over its larger: a sheet seen flatter than this (tilted past
# about 72°) is a false fit, in the box check and the search alike. SIFT's matches rarely survive
# such foreshortening (Morel & Yu's ASIFT paper puts SIFT's limit near a tilt of 2-2.5), while
# fits on a few clustered matches give exactly such strips across the frame: on foldwise's
# out-of-domain set 7 false confirmations without it, 5 at 0.2, 1 at 0.3, for one true one
# lost (bench/README.md, "Renaming on a map").
MIN_AXIS_RATIO = 0.3
# Raised when what a cached check holds changes meaning (its key covers the settings above).
CACHE_VERSION = 1
# Checks kept in a cache folder (about 30 MB each for the five default textures); the ones read or
# written longest ago are removed past this, so a user trying texture after texture does not fill a disk.
CACHE_KEEP = 8


@dataclass
class _TextureFeatures:
    descriptors: np.ndarray  # (n, 128) float32, all classes' keypoints
    labels: np.ndarray  # (n,) int64 class index of each
    points: np.ndarray  # (n, 2) float32 keypoint position in its texture
    sizes: list[tuple[int, int]]  # (width, height) of each class's texture


def grayscale(image: np.ndarray) -> np.ndarray:
    """A uint8 image as one channel (RGB or RGBA converted, grayscale as it is)."""
    import cv2

    image = np.ascontiguousarray(image)
    if image.ndim == 2:
        return image
    return cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2GRAY)


def sharpen(gray: np.ndarray, amount: float) -> np.ndarray:
    """A uint8 grayscale image through an unsharp mask: ``(1 + amount) * gray - amount * blurred``
    (Gaussian, ``SHARPEN_SIGMA``), saturated to [0, 255]; at amount 0 the image itself. Flat
    regions are left as they are; edges and fine texture gain contrast."""
    import cv2

    if amount <= 0:
        return gray
    blurred = cv2.GaussianBlur(gray, (0, 0), SHARPEN_SIGMA)
    return cv2.addWeighted(gray, 1 + amount, blurred, -amount, 0)


def tilted_views(gray: np.ndarray):
    """The texture as SIFT sees it from straight on, then tilted: for each tilt ``t`` of
    ``TEXTURE_TILTS`` and direction of ``TEXTURE_TILT_DIRECTIONS``, turned by the direction and
    squeezed ``t`` times across it (anti-aliased first, as ASIFT does). Yields (view, mask of the
    texture in it, the 2x3 affine map from the view's pixels to the texture's)."""
    import cv2

    height, width = gray.shape
    yield gray, None, np.array([[1, 0, 0], [0, 1, 0]], np.float64)
    corners = np.array([[0, 0, 1], [width, 0, 1], [width, height, 1], [0, height, 1]], np.float64)
    for tilt in TEXTURE_TILTS:
        for direction in TEXTURE_TILT_DIRECTIONS:
            turn = cv2.getRotationMatrix2D((width / 2, height / 2), direction, 1.0)
            turned_corners = corners @ turn.T
            turn[:, 2] -= turned_corners.min(0)
            size = tuple(int(v) for v in np.ceil(turned_corners.max(0) - turned_corners.min(0)))
            turned = cv2.warpAffine(gray, turn, size)
            inside = cv2.warpAffine(np.full_like(gray, 255), turn, size)
            blurred = cv2.GaussianBlur(turned, (0, 0), sigmaX=0.8 * np.sqrt(tilt * tilt - 1), sigmaY=0.01)
            squeezed_width = max(1, round(size[0] / tilt))
            view = cv2.resize(blurred, (squeezed_width, size[1]), interpolation=cv2.INTER_LINEAR)
            # Keypoints only well inside the texture: its turned edges are no texture of its own.
            mask = cv2.erode(cv2.resize(inside, (squeezed_width, size[1]), interpolation=cv2.INTER_NEAREST), np.ones((5, 5), np.uint8))
            to_turned = np.diag([size[0] / squeezed_width, 1.0, 1.0])
            to_texture = np.linalg.inv(np.vstack([turn, [0, 0, 1]])) @ to_turned
            yield view, mask, to_texture[:2]


def sift_scale(height: int, width: int) -> float:
    """The factor an image is resized by before SIFT: ``UPSCALE``, or less where that would take
    its longer side past ``SIFT_MAX_SIDE`` (below 1 for photographs larger than that)."""
    return min(float(UPSCALE), SIFT_MAX_SIDE / max(height, width))


def texture_features(grays: list[np.ndarray]) -> _TextureFeatures:
    """SIFT keypoints of each class's grayscale texture and of its tilted views, in the
    texture's own pixels (class ``i`` is ``grays[i]``)."""
    import cv2

    sift = cv2.SIFT_create(contrastThreshold=CONTRAST_THRESHOLD)
    descriptors, labels, points, sizes = [], [], [], []
    for index, gray in enumerate(grays):
        for view, mask, to_texture in tilted_views(gray):
            keypoints, found = sift.detectAndCompute(view, mask)
            if found is None:
                continue
            at = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2)
            descriptors.append(found)
            labels.append(np.full(len(keypoints), index, dtype=np.int64))
            points.append((at @ to_texture[:, :2].T + to_texture[:, 2]).astype(np.float32))
        sizes.append((gray.shape[1], gray.shape[0]))
    return _TextureFeatures(
        descriptors=np.concatenate(descriptors) if descriptors else np.zeros((0, 128), np.float32),
        labels=np.concatenate(labels) if labels else np.zeros(0, np.int64),
        points=np.concatenate(points) if points else np.zeros((0, 2), np.float32),
        sizes=sizes,
    )


def cache_key(grays: list[np.ndarray]) -> str:
    """What a cached check is filed under: the textures' pixels in class order, and every setting
    and version that changes their keypoints or trees."""
    import cv2

    digest = hashlib.sha256()
    made_by = (CACHE_VERSION, cv2.__version__, CONTRAST_THRESHOLD, TEXTURE_TILTS, TEXTURE_TILT_DIRECTIONS, FLANN_TREES, FLANN_SEED)
    digest.update(repr(made_by).encode())
    for gray in grays:
        digest.update(repr(gray.shape).encode())
        digest.update(np.ascontiguousarray(gray).tobytes())
    return digest.hexdigest()[:32]


@dataclass
class _Stored:
    features: _TextureFeatures
    index_digest: str  # sha256 of the trees' file written with these features ("" for none)


class _CheckCache:
    """One check's keypoints (``KEY.npz``) and FLANN trees (``KEY.flann``) in a folder. Each file
    is written whole and then renamed into place, so a reader finds the old file or the new one;
    the keypoints name the trees' digest, so a pair from two writers is never read together. A
    file that cannot be read or written is made again, with a warning: the cache only saves time."""

    def __init__(self, directory: Path, key: str) -> None:
        self.directory = directory
        self.features_path = directory / f"{key}.npz"
        self.index_path = directory / f"{key}.flann"

    def load(self) -> _Stored | None:
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
        if descriptors.shape != (n, 128) or labels.shape != (n,) or points.shape != (n, 2) or (n and labels.max() >= len(sizes)):
            log.warning("texture check: cached keypoints %s malformed; made again", self.features_path)
            return None
        try:
            os.utime(self.features_path)  # read now: the last to be removed (CACHE_KEEP)
        except OSError:
            pass
        return _Stored(_TextureFeatures(descriptors, labels, points, sizes), index_digest)

    def load_index(self, descriptors: np.ndarray, digest: str):
        """The stored trees over ``descriptors``, or None where there are none that match them."""
        import cv2

        try:
            if not digest or _file_digest(self.index_path) != digest:
                return None
            index = cv2.flann_Index()
            if not index.load(descriptors, str(self.index_path)):
                return None
        except (OSError, cv2.error) as error:
            log.warning("texture check: cached trees %s unreadable (%s); made again", self.index_path, error)
            return None
        return index

    def store(self, features: _TextureFeatures, index) -> None:
        import cv2

        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            digest = ""
            if index is not None:
                temporary = self._temporary(".flann")
                try:
                    index.save(str(temporary))
                    digest = _file_digest(temporary)
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


def _file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


class TextureCheck:
    """SIFT features of each class's texture, and :meth:`apply` to check one image's detections."""

    def __init__(
        self,
        textures: Mapping[str, np.ndarray],
        classes: list[str],
        search: bool = False,
        exact: bool = False,
        cache_dir: str | Path | None = None,
        sharpen: float = SHARPEN_AMOUNT,
    ) -> None:
        """``exact``: compare each image keypoint with every texture keypoint (brute force) instead of
        searching FLANN's KD-trees (bench/texture_matching.py measures the two side by side).
        ``cache_dir``: where the textures' keypoints and trees are kept between processes (None:
        made here each time). ``sharpen``: the image's unsharp mask before SIFT (0: none;
        bench/texture_matching.py --sharpen measures others)."""
        import cv2

        if not sharpen >= 0:
            raise ValueError(f"texture check: sharpen must be at least 0 (0: none), got {sharpen}")
        self.sharpen = float(sharpen)

        missing = [name for name in classes if name not in textures]
        if missing:
            raise ValueError(f"texture check: no texture for class(es) {missing}")
        self.classes = list(classes)
        self.search = search
        grays = [grayscale(np.asarray(textures[name], dtype=np.uint8)) for name in self.classes]
        cache = _CheckCache(Path(cache_dir), cache_key(grays)) if cache_dir is not None else None
        stored = cache.load() if cache is not None else None
        self._features = stored.features if stored is not None else texture_features(grays)
        self._index = None
        made_index = False
        if not exact and len(self._features.descriptors) >= 2:
            if stored is not None:
                self._index = cache.load_index(self._features.descriptors, stored.index_digest)
            if self._index is None:
                cv2.setRNGSeed(FLANN_SEED)  # the KD-trees' random splits (OpenCV's RNG of this thread)
                self._index = cv2.flann_Index(self._features.descriptors, dict(algorithm=1, trees=FLANN_TREES))
                made_index = True
        if cache is not None and (stored is None or made_index):
            cache.store(self._features, self._index)
        # One search of the index at a time: a served detector may check from several threads.
        self._index_lock = threading.Lock()

    def _matches(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(image points, class of the texture match, texture points) of the image's keypoints
        that pass the ratio test."""
        import cv2

        gray = sharpen(gray, self.sharpen)
        scale = sift_scale(*gray.shape)
        interpolation = cv2.INTER_LINEAR if scale >= 1 else cv2.INTER_AREA
        enlarged = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=interpolation) if scale != 1 else gray
        # A SIFT per call (microseconds to make): a served detector may check from several threads.
        keypoints, descriptors = cv2.SIFT_create(contrastThreshold=CONTRAST_THRESHOLD).detectAndCompute(enlarged, None)
        empty = (np.zeros((0, 2), np.float32), np.zeros(0, np.int64), np.zeros((0, 2), np.float32))
        features = self._features
        if descriptors is None or len(features.descriptors) < 2:
            return empty
        # Lowe's ratio test against the nearest neighbour that is another texture point: the tilted
        # views hold one point several times, and its copies are no rival to it.
        indices, distances = self._neighbours(descriptors)
        found = indices >= 0
        nearest = np.maximum(indices, 0)  # -1 (none found) read as 0, then masked by ``found``
        labels, points = features.labels[nearest], features.points[nearest]
        offsets = points - points[:, :1]
        other_point = (labels != labels[:, :1]) | (np.hypot(offsets[..., 0], offsets[..., 1]) > SAME_POINT_PX)
        rivals = found & other_point
        rivals[:, 0] = False
        rival_distance = distances[np.arange(len(indices)), rivals.argmax(axis=1)]
        good = found[:, 0] & (~rivals.any(axis=1) | (distances[:, 0] < RATIO * rival_distance))
        if not good.any():
            return empty
        image_index, texture_index = np.flatnonzero(good), indices[good, 0]
        image_points = np.array([keypoints[i].pt for i in image_index], dtype=np.float32) / scale
        return image_points, features.labels[texture_index], features.points[texture_index]

    def _neighbours(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(indices, distances), each (n, NEIGHBOURS) nearest first: the texture keypoints nearest to
        each of the image's ``descriptors`` (L2), -1 and inf where fewer were found."""
        import cv2

        count = min(NEIGHBOURS, len(self._features.descriptors))
        if self._index is None:  # exact
            indices = np.full((len(descriptors), count), -1, np.int64)
            distances = np.full((len(descriptors), count), np.inf, np.float32)
            matcher = cv2.BFMatcher(cv2.NORM_L2)
            for row, matches in enumerate(matcher.knnMatch(descriptors, self._features.descriptors, k=count)):
                for column, match in enumerate(matches):
                    indices[row, column], distances[row, column] = match.trainIdx, match.distance
            return indices, distances
        with self._index_lock:
            found, squared = self._index.knnSearch(descriptors, count, params=dict(checks=FLANN_CHECKS))
        indices = found.astype(np.int64)
        distances = np.where(indices >= 0, np.sqrt(np.maximum(squared, 0)), np.inf).astype(np.float32)  # FLANN's L2 is squared
        return indices, distances

    def apply(self, image: np.ndarray, detections: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``detections`` (boxes, scores, labels as ``detect_object`` gives them, in ``image``'s
        pixels) checked: new arrays, best score first, with ``confirmed`` (n,) bool: whether the
        texture confirmed each box (or the search found it)."""
        boxes = np.array(detections["boxes"], dtype=np.float32, copy=True).reshape(-1, 4)
        scores = np.array(detections["scores"], dtype=np.float32, copy=True)
        labels = np.array(detections["labels"], dtype=np.int64, copy=True)
        checked = np.flatnonzero(scores >= MIN_SCORE)
        confirmed = np.zeros(len(scores), dtype=bool)
        if len(checked) or self.search:
            gray = grayscale(image)
            image_points, match_labels, texture_points = self._matches(gray)
            height, width = gray.shape
            if self.search:  # scored by the network's boxes as they came, before the check below moves them
                found, found_labels = self._search(image_points, match_labels, texture_points, width, height)
                found_network = _network_score(found, found_labels, boxes, scores, labels)
            for index in checked:
                x0, y0, x1, y1 = boxes[index]
                inside = (
                    (image_points[:, 0] >= x0) & (image_points[:, 0] <= x1)
                    & (image_points[:, 1] >= y0) & (image_points[:, 1] <= y1)
                )
                counts = np.bincount(match_labels[inside], minlength=len(self.classes))
                label = int(labels[index])
                best = int(np.argmax(counts))
                # Another class's texture matched far more often is tried first, and renames the box
                # only where its matches agree on a map (a count alone is no evidence: clutter
                # matches the textures richest in keypoints most).
                other = best != label and counts[best] >= MIN_INLIERS and counts[best] >= RENAME_FACTOR * max(counts[label], 1)
                for candidate in [best, label] if other else [label]:
                    outline = self._fit(image_points[inside], match_labels[inside], texture_points[inside], candidate, boxes[index], width, height)
                    if outline is not None:
                        break
                else:
                    continue
                labels[index] = candidate
                boxes[index] = outline
                confirmed[index] = True
            scores = np.where(
                confirmed,
                CONFIRMED_FLOOR + (1 - CONFIRMED_FLOOR) * scores,
                np.where(scores >= PAPER_CUT, PAPER_CUT + (scores - PAPER_CUT) * UNCONFIRMED_SPAN, scores),
            ).astype(np.float32)
            if self.search and len(found):
                # Scored as a box the check confirmed, at the network's score for it, or at the
                # check's floor where the network had none as high (so >= 0.93 in float32 too).
                found_scores = CONFIRMED_FLOOR + (1 - CONFIRMED_FLOOR) * np.maximum(found_network, MIN_SCORE)
                boxes = np.concatenate([boxes, found])
                scores = np.concatenate([scores, found_scores.astype(np.float32)])
                labels = np.concatenate([labels, found_labels])
                confirmed = np.concatenate([confirmed, np.ones(len(found), dtype=bool)])
            boxes, scores, labels, confirmed = _merge(boxes, scores, labels, confirmed)
        order = np.argsort(-scores, kind="stable")
        return {"boxes": boxes[order], "scores": scores[order], "labels": labels[order], "confirmed": confirmed[order]}

    def _fit(self, image_points, match_labels, texture_points, label: int, box, width: int, height: int) -> np.ndarray | None:
        """The outline of ``label``'s texture where at least ``MIN_INLIERS`` of its matches (among
        those given: a box's) agree on one affine map that is no false fit (``_false_fit``); None
        where they do not."""
        import cv2

        own = match_labels == label
        if own.sum() < MIN_INLIERS:
            return None
        x0, y0, x1, y1 = box
        diagonal = float(np.hypot(x1 - x0, y1 - y0))
        affine, mask = cv2.estimateAffine2D(
            texture_points[own], image_points[own], method=cv2.RANSAC, ransacReprojThreshold=max(3.0, 0.08 * diagonal)
        )
        if affine is None or mask is None or int(mask.sum()) < MIN_INLIERS:
            return None
        if _false_fit(affine):
            return None
        return self._outline(affine, label, width, height)

    def _outline(self, affine: np.ndarray, label: int, width: int, height: int) -> np.ndarray | None:
        """The class's texture outline mapped by ``affine`` into the image, clipped to the frame
        (xyxy), or None where nothing of it is inside."""
        texture_width, texture_height = self._features.sizes[label]
        corners = np.array(
            [[0, 0], [texture_width, 0], [texture_width, texture_height], [0, texture_height]], np.float32
        ) @ affine[:, :2].T + affine[:, 2]
        outline = np.array([
            max(corners[:, 0].min(), 0.0), max(corners[:, 1].min(), 0.0),
            min(corners[:, 0].max(), float(width)), min(corners[:, 1].max(), float(height)),
        ], np.float32)
        return outline if outline[2] > outline[0] and outline[3] > outline[1] else None

    def _search(self, image_points, match_labels, texture_points, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Sheets the texture alone finds over the whole image: (outlines (n, 4), class indices (n,))."""
        import cv2

        found, found_labels = [], []
        first_threshold = max(3.0, SEARCH_RANSAC_FRACTION * float(np.hypot(width, height)))
        for label in range(len(self.classes)):
            own = match_labels == label
            points, sources = image_points[own], texture_points[own]
            for _ in range(SEARCH_SHEETS_PER_CLASS):
                if len(points) < SEARCH_MIN_INLIERS:
                    break
                affine, mask = cv2.estimateAffine2D(sources, points, method=cv2.RANSAC, ransacReprojThreshold=first_threshold)
                if affine is None or mask is None or int(mask.sum()) < SEARCH_MIN_INLIERS:
                    break
                # Redo the fit at the box check's threshold, relative to the sheet just found.
                rough = self._outline(affine, label, width, height)
                diagonal = float(np.hypot(rough[2] - rough[0], rough[3] - rough[1])) if rough is not None else 0.0
                residuals = np.linalg.norm(sources @ affine[:, :2].T + affine[:, 2] - points, axis=1)
                inliers = residuals <= max(3.0, 0.08 * diagonal)
                if inliers.sum() < SEARCH_MIN_INLIERS:
                    inliers = mask.ravel().astype(bool)  # these matches are spent either way
                else:
                    refit, _ = cv2.estimateAffine2D(sources[inliers], points[inliers], method=cv2.LMEDS)
                    affine = refit if refit is not None else affine
                    outline = self._outline(affine, label, width, height)
                    if (
                        not _false_fit(affine)
                        and outline is not None
                        and min(outline[2] - outline[0], outline[3] - outline[1]) >= SEARCH_MIN_SIDE
                    ):
                        found.append(outline)
                        found_labels.append(label)
                points, sources = points[~inliers], sources[~inliers]
        if not found:
            return np.zeros((0, 4), np.float32), np.zeros(0, np.int64)
        return np.stack(found).astype(np.float32), np.array(found_labels, np.int64)


def _false_fit(affine: np.ndarray) -> bool:
    """Whether an affine map from a texture is no sheet: mirrored or collapsed (a printed sheet
    shows its front) or flattened past ``MIN_AXIS_RATIO`` (few clustered matches stretched into a
    strip), in the box check and the search alike."""
    if np.linalg.det(affine[:, :2]) <= 0:
        return True
    axes = np.linalg.svd(affine[:, :2], compute_uv=False)
    return bool(axes[1] < MIN_AXIS_RATIO * axes[0])


def _network_score(found: np.ndarray, found_labels: np.ndarray, boxes, scores, labels) -> np.ndarray:
    """Each found outline's network score: the best of the network's boxes of its class it
    overlaps at IoU ≥ ``NMS_IOU`` (before the check), 0 where there is none."""
    import torch
    from torchvision.ops import box_iou

    if not len(boxes):
        return np.zeros(len(found), np.float32)
    overlap = box_iou(torch.from_numpy(found), torch.from_numpy(boxes)).numpy() >= NMS_IOU
    same = found_labels[:, None] == labels[None, :]
    return np.where(overlap & same, scores[None, :], 0.0).max(1).astype(np.float32)


def _merge(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, confirmed: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-class NMS at ``NMS_IOU``: a corrected box and the box it now repeats are one (a
    confirmed box outscores every unconfirmed one, so what is kept keeps its evidence)."""
    import torch
    from torchvision.ops import batched_nms

    keep = batched_nms(torch.from_numpy(boxes), torch.from_numpy(scores), torch.from_numpy(labels), NMS_IOU).numpy()
    keep.sort()
    return boxes[keep], scores[keep], labels[keep], confirmed[keep]
