"""The texture check: each detection checked against its class's own texture, as a second opinion
on the network's score (``detector.texture_check``).

foldwise's detector looks for one known printed sheet per class, so the texture it was trained
on is evidence of its own: SIFT keypoints of the image inside a detection's box, matched to the
textures (Lowe's ratio test), and an affine map from the class's texture to those keypoints fitted
by RANSAC. Where at least ``MIN_INLIERS`` matches agree on one map, the map tells where the whole
sheet lies: the texture's outline, mapped into the image and clipped to the frame.

- Such a map confirms the detection: the outline becomes its box (whether the network's box was
  the whole sheet, a piece of it or a box around more), and its score rises above every box
  without such evidence (``0.9 + 0.1 * score`` while boxes merge). Boxes of one class that now
  overlap (IoU ≥ ``NMS_IOU``: two boxes on one sheet, confirmed by one outline) are merged to
  the best, as the detector's views are. The boxes kept then rank among the confirmed by their
  evidence (``confirmed_score``: the share of the texture their inliers cover), so a sheet of a
  target's template confirmed on its letterhead ranks below the whole sheets, however sure the
  network was of it.
- A map that mirrors the texture is a false fit (a printed sheet shows its front), and so is one
  that squashes it flatter than ``MIN_AXIS_RATIO`` (a few clustered matches stretched into a
  strip across the frame): no evidence.
- A box whose keypoints match another class's texture far more often is renamed to that class
  where those matches agree on a map of its texture (which confirms it as that class): a count
  of matches alone renamed true sheets to the texture richest in keypoints, which clutter and
  grain match most (bench/README.md, "Renaming on a map").
- Every other box (too blurred or tilted for a map, a texture with few keypoints) keeps its
  class and its place against the paper's 0.8 cut: some matches but no map is not evidence
  against. Those at or above the cut rank below the confirmed ones
  (``0.8 + 0.5 * (score - 0.8)``, in [0.8, 0.9)), as the texture is the stronger evidence.
- Two exceptions, each dropping a box under the cut in its order ([0.8, 0.9) to [0.7, 0.8)): a
  box that a better-scored box of any class already covers is that sheet named again
  (``SHEET_IOU``); and a box not one of whose keypoints matches its class's texture
  (``unmatched``): one holding many shows something printed that is not its sheet, one holding
  next to none a blank surface, where the sheet's print, enlarged, would show keypoints. So
  does a box no map fits that holds ``DETAILED_KEYPOINTS``: its own print, in such detail,
  would have fitted one.

Lookalikes (``lookalikes``: the user's other sheets of the objects' kind) join the textures'
index as no class's: a keypoint one shares with an object fails the ratio test, and a box in which
a lookalike's own texture fits a map on more matches than the box's class did shows that
lookalike. It drops under the cut, confirmed or not (``_shows_lookalike``): on real photographs of
invoices the network scored such sheets high, and keypoints that passed the ratio test still
confirmed some (bench/README.md, "Real photographs of bent invoices").

What a confirmed sheet shows is checked as well (``_shown_share``): each of the image's keypoints
in the box is taken back into the texture by the map of the piece nearest to it, and of the
texture's cells holding ``SHOWN_KEYPOINTS`` of them, the share holding one of the maps' inliers
is what the maps explain. Another form of a target's template matches its letterhead, table and
footer, enough for a map, while its own names and figures show print no map explains: under
``MIN_SHOWN`` its confirmation is withdrawn and it drops under the cut, and so does any box
without evidence on it. A small or blurred sheet shows few cells in such detail, so its
confirmation stands on its matches (bench/README.md, "What the maps explain").

With ``search`` (``detector.texture_search``) the texture also finds sheets the network gave no
box for: over the whole image, each class's matches are fitted by RANSAC as above, one sheet
after another (its inliers taken out), and a map that ``SEARCH_MIN_INLIERS`` matches agree on,
not mirrored nor squashed flatter than ``MIN_AXIS_RATIO``, adds its outline as a
confirmed detection before the merge, its network score the network's best for a box of that
class on it, ``MIN_SCORE`` where it had none as high (every confirmed box has been scored at
least that by the network or the search). A sheet the network found and the check
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

The textures' keypoints and trees are kept between processes by ``texture_cache``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from workers.train import texture_cache
from workers.train.texture_cache import TextureFeatures

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
# Lower caps, and SIFT's blur halved on the image as it is (the same scale space from a quarter
# of the pixels), were faster and matched worse (bench/README.md, "Detection's speed against its
# accuracy").
SIFT_MAX_SIDE = 2048
# A box holding this many of the image's keypoints (at SIFT's scale) whose class's texture fits
# no map is no sheet of that class: it shows print in such detail that its own would have fitted
# one (on real photographs, other invoices, 3,600-7,300 keypoints and no map), while the true
# sheets the texture could not confirm, blurred, tilted or grainy, held at most 1,573 over
# bench/wild.py's six sets (bench/README.md, "Evidence against a box").
DETAILED_KEYPOINTS = 2000
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
# The image's unsharp mask before SIFT (``sharpen``; the textures are left as they are), off: it
# raised make run's pair on the smaller out-of-domain frames but lowered a 640x480 set held out of
# that choice and doubled the check's time there, and a gain that depends on the frame's size is
# no default for photographs of any size (bench/README.md, "Sharpening the image before SIFT";
# bench/texture_matching.py --sharpen measures it again).
SHARPEN_AMOUNT = 0.0
SHARPEN_SIGMA = 1.0
# Each texture's keypoints are also taken from views of it tilted (Morel & Yu's ASIFT): SIFT
# matches a sheet seen at most ~45-60° off straight on, and the wild's sheets lie on the ground,
# curl and face cameras low over it. Tilts √2 and 2 (45° and 60°) in four directions, 8 views
# beside the texture itself, for 7x the texture keypoints to match against: out of domain and in
# domain, make run's pair scored higher with them (bench/README.md, "Tilted views of the textures").
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
# Threads an image's FLANN lookups are split over, each at least MIN_SEARCH_PART keypoints.
SEARCH_THREADS = min(os.cpu_count() or 1, 4)
MIN_SEARCH_PART = 128
# A map's smaller singular value over its larger: a sheet seen flatter than this (tilted past
# about 72°) is a false fit, in the box check and the search alike. SIFT's matches rarely survive
# such foreshortening (Morel & Yu's ASIFT paper puts SIFT's limit near a tilt of 2-2.5), while
# fits on a few clustered matches give exactly such strips across the frame: on foldwise's
# out-of-domain set 7 false confirmations without it, 5 at 0.2, 1 at 0.3, for one true one
# lost (bench/README.md, "Renaming on a map").
MIN_AXIS_RATIO = 0.3
# A bent sheet (a tube, a crease) is no affine image of its texture: after the first map, up to
# LOCAL_MAPS - 1 more are fitted to the box's matches the maps so far leave out, each a piece of
# the sheet where LOCAL_MIN_INLIERS matches agree on it; their inliers count as evidence, and the
# box takes in where they lie.
LOCAL_MAPS = 3
LOCAL_MIN_INLIERS = 5
# RANSAC's threshold for a box's maps, as a fraction of the box's diagonal: room for a sheet's
# gentle curl within one map; sharper bends are the further maps' pieces.
RANSAC_FRACTION = 0.05
# A bent sheet moves its print smoothly: near any inlier, its neighbours agree on one affine map.
# So loose a threshold also lets chance matches agree (another document's words and figures in the
# same font, near where the sheet has its own): each inlier is judged by the inliers around it in
# the texture (LOCAL_RING, fractions of the texture's diagonal: past the inlier's own word, within
# a bend's reach), LOCAL_NEIGHBOURS of them fitted by least squares, and dropped where it lies off
# their map by more than LOCAL_TOLERANCE of the sheet's size in the image (at least
# LOCAL_TOLERANCE_PX). An inlier with fewer than LOCAL_MIN_NEIGHBOURS such neighbours is not
# judged: a small sheet's few matches keep their say (bench/README.md, "Inliers their
# neighbours vouch for").
LOCAL_RING = (0.03, 0.15)
LOCAL_NEIGHBOURS = 12
LOCAL_MIN_NEIGHBOURS = 4
LOCAL_TOLERANCE = 0.02
LOCAL_TOLERANCE_PX = 2.0
LOCAL_MAX_CARRIED = 1000.0  # see _off_their_neighbours: only a degenerate fit carries its noise this far
# Coverage: the texture cut into COVER_GRID x COVER_GRID cells; a map's coverage is the share of
# the cells holding texture keypoints that hold one of its inliers. A lookalike sheet of the same
# template matches its letterhead and footer; the sheet itself, all over.
COVER_GRID = 8
# A confirmed sheet whose maps' inliers lie in less than MIN_SHOWN of the coverage cells the image
# shows in detail (SHOWN_KEYPOINTS of its keypoints, taken back into the texture by the maps, in
# the cell) is another sheet sharing part of its print, a form of its template: its confirmation
# is withdrawn and it drops under the cut (``_shown_share``). MIN_SHOWN (with the inliers their
# neighbours vouch for, LOCAL_TOLERANCE) was chosen on one half of the real photographs of
# invoices, the other half held out; with fewer keypoints to a cell, grain and ground around small
# rendered sheets count as print their maps leave unexplained (bench/README.md, "What the maps
# explain", "Inliers their neighbours vouch for").
SHOWN_KEYPOINTS = 20
MIN_SHOWN = 0.5
# A box at least this much inside a better-scored box the texture confirmed is a piece of that
# sheet: one box per sheet is drawn. Of boxes scored alike, the one covering more of its texture
# counts as the better (bench/README.md, "Documents as a phone photographs them").
PIECE_INSIDE = 0.8
# Without evidence, boxes of any class overlapping a better-scored box at this IoU (or either
# PIECE_INSIDE of the other) are that sheet named again: they drop under the cut, in their order
# ([0.8, 0.9) to [0.7, 0.8)), so one box per sheet is drawn (bench/README.md, "One box per sheet").
SHEET_IOU = 0.3
SECOND_NAME_FLOOR = PAPER_CUT - (CONFIRMED_FLOOR - PAPER_CUT)


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
            mask = cv2.erode(
                cv2.resize(inside, (squeezed_width, size[1]), interpolation=cv2.INTER_NEAREST),
                np.ones((5, 5), np.uint8),
            )
            to_turned = np.diag([size[0] / squeezed_width, 1.0, 1.0])
            to_texture = np.linalg.inv(np.vstack([turn, [0, 0, 1]])) @ to_turned
            yield view, mask, to_texture[:2]


def sift_scale(height: int, width: int) -> float:
    """The factor an image is resized by before SIFT: ``UPSCALE``, or less where that would take
    its longer side past ``SIFT_MAX_SIDE`` (below 1 for photographs larger than that)."""
    return min(float(UPSCALE), SIFT_MAX_SIDE / max(height, width))


def texture_features(grays: list[np.ndarray]) -> TextureFeatures:
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
    return TextureFeatures(
        descriptors=np.concatenate(descriptors) if descriptors else np.zeros((0, 128), np.float32),
        labels=np.concatenate(labels) if labels else np.zeros(0, np.int64),
        points=np.concatenate(points) if points else np.zeros((0, 2), np.float32),
        sizes=sizes,
    )


def cache_key(grays: list[np.ndarray]) -> str:
    """What a cached check is filed under: the textures' pixels in class order, and every setting
    and version that changes their keypoints or trees."""
    import cv2

    made_by = (cv2.__version__, CONTRAST_THRESHOLD, TEXTURE_TILTS, TEXTURE_TILT_DIRECTIONS, FLANN_TREES, FLANN_SEED)
    return texture_cache.cache_key(grays, made_by)


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
        calibration=None,
        lookalikes: Mapping[str, np.ndarray] | None = None,
        every_name: bool = False,
        unmatched_drawn: bool = False,
    ) -> None:
        """``exact``: compare each image keypoint with every texture keypoint (brute force) instead of
        searching FLANN's KD-trees (bench/texture_matching.py measures the two side by side).
        ``cache_dir``: where the textures' keypoints and trees are kept between processes (None:
        made here each time). ``sharpen``: the image's unsharp mask before SIFT (0: none;
        bench/texture_matching.py --sharpen measures others). ``calibration``: a
        :class:`~workers.train.calibration.Calibration` that scores each checked detection from
        the network's score and the texture's evidence (None: the fixed tiers described above).
        ``lookalikes``: sheets of the classes' kind that are none of them (the user's other forms
        or covers): their keypoints join the index as no class's, so a keypoint a lookalike shares
        with a class's texture (a letterhead, a table head) fails the ratio test and is no
        evidence, and one that matches a lookalike best is none either. ``every_name``: leave a
        sheet named again over the cut (``SHEET_IOU``; bench/detect_speed.py measures both).
        ``unmatched_drawn``: leave a box over the cut whose keypoints match nothing of its texture,
        or that holds ``DETAILED_KEYPOINTS`` and fits no map (bench/detect_speed.py measures both)."""
        import cv2

        if not sharpen >= 0:
            raise ValueError(f"texture check: sharpen must be at least 0 (0: none), got {sharpen}")
        self.sharpen = float(sharpen)
        self.every_name = every_name
        self.unmatched_drawn = unmatched_drawn

        missing = [name for name in classes if name not in textures]
        if missing:
            raise ValueError(f"texture check: no texture for class(es) {missing}")
        self.classes = list(classes)
        self.search = search
        grays = [grayscale(np.asarray(textures[name], dtype=np.uint8)) for name in self.classes]
        self.lookalikes = sorted(lookalikes or {})
        grays += [grayscale(np.asarray(lookalikes[name], dtype=np.uint8)) for name in self.lookalikes]
        cache = texture_cache.CheckCache(Path(cache_dir), cache_key(grays)) if cache_dir is not None else None
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
        self.calibration = calibration
        # Which coverage cells of each texture hold keypoints (a blank margin is no evidence lost).
        self._cells = []
        for label, (texture_width, texture_height) in enumerate(self._features.sizes[: len(self.classes)]):
            points = self._features.points[self._features.labels == label]
            self._cells.append(np.unique(_cell_index(points, texture_width, texture_height)))

    def _matches(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(image points, class of the texture match, texture points) of the image's keypoints
        that pass the ratio test against a class's texture (not a lookalike's)."""
        _, points, labels, texture_points = self._keypoints_and_matches(gray)
        own = labels < len(self.classes)
        return points[own], labels[own], texture_points[own]

    def _keypoints_and_matches(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(every keypoint's position in the image, then ``_matches``'s three arrays with the
        matches to the lookalikes as well: label ``len(classes) + i`` is ``lookalikes[i]``)."""
        import cv2

        gray = sharpen(gray, self.sharpen)
        scale = sift_scale(*gray.shape)
        interpolation = cv2.INTER_LINEAR if scale >= 1 else cv2.INTER_AREA
        enlarged = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=interpolation) if scale != 1 else gray
        # A SIFT per call (microseconds to make): a served detector may check from several threads.
        keypoints, descriptors = cv2.SIFT_create(contrastThreshold=CONTRAST_THRESHOLD).detectAndCompute(enlarged, None)
        every = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2) / scale
        empty = (every, np.zeros((0, 2), np.float32), np.zeros(0, np.int64), np.zeros((0, 2), np.float32))
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
        return every, every[image_index], features.labels[texture_index], features.points[texture_index]

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
        # The KD-trees are only read by a search (each keeps its own heap and visited set), so the
        # image's keypoints are looked up in parts on several threads: on 2 cores 0.11 s -> 0.05 s
        # a 640x480 image, the same neighbours (bench/README.md, "The network on onnxruntime").
        parts = min(SEARCH_THREADS, max(len(descriptors) // MIN_SEARCH_PART, 1))

        def search(chunk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return self._index.knnSearch(chunk, count, params=dict(checks=FLANN_CHECKS))

        if parts > 1:
            with ThreadPoolExecutor(parts) as pool:
                searched = list(pool.map(search, np.array_split(descriptors, parts)))
        else:
            searched = [search(descriptors)]
        found = np.concatenate([part[0] for part in searched])
        squared = np.concatenate([part[1] for part in searched])
        indices = found.astype(np.int64)
        distances = np.where(indices >= 0, np.sqrt(np.maximum(squared, 0)), np.inf).astype(
            np.float32
        )  # FLANN's L2 is squared
        return indices, distances

    def matches(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The image's keypoints and their texture matches, as :meth:`apply` reads them: for a
        second ``apply`` on the same image (other detections) without finding them again."""
        return self._keypoints_and_matches(grayscale(image))

    def apply(
        self,
        image: np.ndarray,
        detections: Mapping[str, np.ndarray],
        with_evidence: bool = False,
        matches: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> dict[str, np.ndarray]:
        """``detections`` (boxes, scores, labels as ``detect_object`` gives them, in ``image``'s
        pixels) checked: new arrays, best score first, with ``confirmed`` (n,) bool: whether the
        texture confirmed each box (or the search found it). ``with_evidence``: also
        ``evidence`` (n, len(calibration.FEATURES)), what the score was read from. ``matches``:
        :meth:`matches` of this image, where already found."""
        from workers.train.calibration import FEATURES, network_logit

        coverage_column = FEATURES.index("coverage")

        boxes = np.array(detections["boxes"], dtype=np.float32, copy=True).reshape(-1, 4)
        scores = np.array(detections["scores"], dtype=np.float32, copy=True)
        labels = np.array(detections["labels"], dtype=np.int64, copy=True)
        checked = np.flatnonzero(scores >= MIN_SCORE)
        confirmed = np.zeros(len(scores), dtype=bool)
        unmatched = np.zeros(len(scores), dtype=bool)  # no keypoint of its class, or many and no map: evidence against
        # Of what the image shows of each confirmed sheet, the share its maps explain (``_shown_share``).
        shown = np.ones(len(scores), np.float32)
        evidence = np.zeros((len(scores), len(FEATURES)), np.float32)
        evidence[:, 0] = network_logit(scores)
        network = scores.copy()  # each box's own score, which a sheet shown to be another drops by
        if len(checked) or self.search:
            if matches is None:
                matches = self.matches(image)
            every, image_points, match_labels, texture_points = matches
            height, width = image.shape[:2]
            if self.search:  # scored by the network's boxes as they came, before the check below moves them
                found, found_labels, found_evidence, found_shown = self._search(
                    image_points, match_labels, texture_points, width, height, every
                )
                found_network = _network_score(found, found_labels, boxes, scores, labels)
            for index in checked:
                inside = _inside(image_points, boxes[index])
                # The image's keypoints in the box: their count is evidence, and the maps found must
                # explain them (``_shown_share``; a box on a piece of a sheet shows only that piece).
                in_box = every[_inside(every, boxes[index])]
                keypoints = len(in_box)
                counts = np.bincount(match_labels[inside], minlength=len(self.classes))[: len(self.classes)]
                label = int(labels[index])
                best = int(np.argmax(counts))
                # Another class's texture matched far more often is tried first, and renames the box
                # only where its matches agree on a map (a count alone is no evidence: clutter
                # matches the textures richest in keypoints most).
                other = (
                    best != label
                    and counts[best] >= MIN_INLIERS
                    and counts[best] >= RENAME_FACTOR * max(counts[label], 1)
                )
                for candidate in [best, label] if other else [label]:
                    outline, inliers, coverage, explained = self._fit(
                        image_points[inside],
                        match_labels[inside],
                        texture_points[inside],
                        candidate,
                        boxes[index],
                        width,
                        height,
                        in_box,
                    )
                    if outline is not None:
                        break
                # ``candidate``: the class the box ends with (its own where no map was found).
                share = counts[candidate] / max(keypoints, 1)
                evidence[index, 2:] = (np.log1p(inliers), coverage, np.log1p(keypoints), share)
                if outline is None:
                    # Not one keypoint matching its class: many show something printed that is not
                    # its sheet (which, that sharp, would match somewhere); next to none, a blank
                    # surface, as the sheet's print enlarged shows keypoints (bench/README.md,
                    # "Evidence against a box"). And print in such detail that its sheet would
                    # have fitted a map (``DETAILED_KEYPOINTS``). It drops under the cut as a
                    # second name does.
                    unmatched[index] = counts[label] == 0 or keypoints >= DETAILED_KEYPOINTS
                    continue
                labels[index] = candidate
                boxes[index] = outline
                confirmed[index] = True
                shown[index] = explained
                evidence[index, 1] = 1.0
            if self.calibration is not None:
                scores = self.calibration.probability(evidence)
            else:
                scores = np.where(
                    confirmed,
                    CONFIRMED_FLOOR + (1 - CONFIRMED_FLOOR) * scores,
                    np.where(scores >= PAPER_CUT, PAPER_CUT + (scores - PAPER_CUT) * UNCONFIRMED_SPAN, scores),
                ).astype(np.float32)
            if self.search and len(found):
                # Scored as a box the check confirmed, at the network's score for it, or at the
                # check's floor where the network had none as high (so >= 0.93 in float32 too).
                found_network = np.maximum(found_network, MIN_SCORE)
                found_evidence[:, 0] = network_logit(found_network)
                for row, outline in enumerate(found):
                    keypoints = int(_inside(every, outline).sum())
                    found_evidence[row, 4] = np.log1p(keypoints)
                    found_evidence[row, 5] = int(
                        (_inside(image_points, outline) & (match_labels == found_labels[row])).sum()
                    ) / max(keypoints, 1)
                if self.calibration is not None:
                    found_scores = self.calibration.probability(found_evidence)
                else:
                    found_scores = CONFIRMED_FLOOR + (1 - CONFIRMED_FLOOR) * found_network
                boxes = np.concatenate([boxes, found])
                scores = np.concatenate([scores, found_scores.astype(np.float32)])
                labels = np.concatenate([labels, found_labels])
                confirmed = np.concatenate([confirmed, np.ones(len(found), dtype=bool)])
                unmatched = np.concatenate([unmatched, np.zeros(len(found), dtype=bool)])
                shown = np.concatenate([shown, found_shown])
                evidence = np.concatenate([evidence, found_evidence])
                network = np.concatenate([network, found_network.astype(np.float32)])
            keep = _merge(boxes, scores, labels)
            keep = keep[_one_per_sheet(boxes[keep], scores[keep], confirmed[keep], evidence[keep, coverage_column])]
            boxes, scores, labels, confirmed, unmatched, evidence, network, shown = (
                boxes[keep],
                scores[keep],
                labels[keep],
                confirmed[keep],
                unmatched[keep],
                evidence[keep],
                network[keep],
                shown[keep],
            )
            # Another sheet: a box in which a lookalike's texture fits a map on more matches than its
            # own class's (one of the user's other sheets), or a confirmed sheet whose maps explain
            # too little of the print the image shows of it (``MIN_SHOWN``: a form of its
            # template). Whatever the network or the print they share said, it drops under the cut,
            # its confirmation withdrawn.
            another_sheet = self._shows_lookalike(
                boxes, np.expm1(evidence[:, FEATURES.index("inliers")]), image_points, match_labels, texture_points
            )
            another_sheet |= confirmed & (shown < MIN_SHOWN)
            if another_sheet.any():
                confirmed[another_sheet] = False
                scores[another_sheet] = np.minimum(
                    scores[another_sheet],
                    SECOND_NAME_FLOOR + (PAPER_CUT - SECOND_NAME_FLOOR) * network[another_sheet],
                ).astype(np.float32)
            if self.calibration is None:  # a calibrated score says what such a box is worth
                below = unmatched.copy() if not self.unmatched_drawn else np.zeros(len(scores), dtype=bool)
                # A box without evidence on another sheet's box: that sheet is accounted for.
                on_another = np.array(
                    [any(_one_sheet(box, other) for other in boxes[another_sheet]) for box in boxes], dtype=bool
                )
                below |= ~confirmed & on_another
                below &= ~another_sheet  # already under the cut
                if not self.every_name:  # a box dropped for its keypoints stands for no sheet
                    below[_named_again(boxes, scores, confirmed, standing=~(below | another_sheet))] = True
                scores[below] = np.where(
                    scores[below] >= PAPER_CUT, SECOND_NAME_FLOOR + (scores[below] - PAPER_CUT), scores[below]
                ).astype(np.float32)
                # The merges above kept the boxes the network's scores ordered; among themselves the
                # confirmed now rank by their evidence (``confirmed_score``).
                scores[confirmed] = confirmed_score(evidence[confirmed, coverage_column])
        order = np.argsort(-scores, kind="stable")
        checked_detections = {
            "boxes": boxes[order],
            "scores": scores[order],
            "labels": labels[order],
            "confirmed": confirmed[order],
        }
        if with_evidence:
            checked_detections["evidence"] = evidence[order]
        return checked_detections

    def _shows_lookalike(self, boxes, own_inliers, image_points, match_labels, texture_points) -> np.ndarray:
        """(n,) bool: the boxes in which one lookalike's matches agree on an affine map (RANSAC, as
        ``_fit``'s first map, neither mirrored nor squashed) on at least ``MIN_INLIERS`` and on
        more than the box's own class's maps did (``own_inliers``, (n,))."""
        shown = np.zeros(len(boxes), dtype=bool)
        if not self.lookalikes:
            return shown
        for index, box in enumerate(boxes):
            inside = _inside(image_points, box) & (match_labels >= len(self.classes))
            counts = np.bincount(match_labels[inside] - len(self.classes), minlength=len(self.lookalikes))
            needed = max(MIN_INLIERS, int(round(float(own_inliers[index]))) + 1)  # more than its own
            for lookalike in np.argsort(-counts):
                if counts[lookalike] < needed:
                    break  # fewer matches than the box's own inliers: no map of it can have more
                which = inside & (match_labels == len(self.classes) + lookalike)
                if _affine_map(texture_points[which], image_points[which], box, needed) is not None:
                    shown[index] = True
                    break
        return shown

    def _fit(
        self, image_points, match_labels, texture_points, label: int, box, width: int, height: int, box_keypoints
    ) -> tuple[np.ndarray | None, int, float, float]:
        """(outline, inliers, coverage, shown) of ``label``'s texture among the matches given (a box's).

        The first affine map needs ``MIN_INLIERS`` matches that agree on it and is no false fit
        (``_false_fit``); further maps (``LOCAL_MAPS``) take the matches left over, each a piece
        of a bent sheet. Each part of the texture (a ``COVER_GRID`` cell) goes where the map of
        the piece nearest to it in the texture takes it, and the outline is where all of them
        lie, clipped to the frame: a flat sheet's is its map's image of the whole texture, a
        creased or rolled one's follows its pieces. None where no first map is found.
        ``inliers`` and ``coverage`` measure the maps' evidence, ``shown`` how much of what the
        image shows of the sheet they explain (``_shown_share`` of ``box_keypoints``, the image's
        keypoints in ``box``); all 0 where there is no evidence."""

        own = np.flatnonzero(match_labels == label)
        if len(own) < MIN_INLIERS:
            return None, 0, 0.0, 0.0
        sources, targets = texture_points[own], image_points[own]
        remaining = np.ones(len(own), bool)
        pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (affine, its inliers' texture and image points)
        for piece in range(LOCAL_MAPS):
            candidates = np.flatnonzero(remaining)
            needed = MIN_INLIERS if piece == 0 else LOCAL_MIN_INLIERS
            fitted = _affine_map(sources[candidates], targets[candidates], box, needed)
            if fitted is None:
                break
            affine, agreeing = fitted
            inliers = candidates[agreeing]
            pieces.append((affine, sources[inliers], targets[inliers]))
            remaining[inliers] = False
        pieces = self._vouched_pieces(pieces, label)
        if not pieces:
            return None, 0, 0.0, 0.0
        outline = self._pieces_outline(pieces, label, width, height)
        if outline is None:
            return None, 0, 0.0, 0.0
        agreeing = np.concatenate([points for _, points, _ in pieces])
        shown = self._shown_share(pieces, box_keypoints, label)
        return outline, len(agreeing), self._coverage(agreeing, label), shown

    def _vouched_pieces(self, pieces, label: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``pieces`` (affine, inliers' texture points, their image points) without the inliers
        their neighbours contradict (``_off_their_neighbours``, over every piece's inliers): the
        first piece needs ``MIN_INLIERS`` left, each further one ``LOCAL_MIN_INLIERS``. Empty
        where the first piece falls short, or there is none."""
        if not pieces:
            return []
        sources = np.concatenate([texture for _, texture, _ in pieces])
        targets = np.concatenate([image for _, _, image in pieces])
        texture_width, texture_height = self._features.sizes[label]
        scale = float(np.sqrt(abs(np.linalg.det(pieces[0][0][:, :2]))))
        vouched = ~_off_their_neighbours(sources, targets, float(np.hypot(texture_width, texture_height)), scale)
        kept, start = [], 0
        for index, (affine, texture, image) in enumerate(pieces):
            which = vouched[start : start + len(texture)]
            start += len(texture)
            if which.sum() >= (MIN_INLIERS if index == 0 else LOCAL_MIN_INLIERS):
                kept.append((affine, texture[which], image[which]))
            elif index == 0:
                return []
        return kept

    def _shown_share(self, pieces, keypoints: np.ndarray, label: int) -> float:
        """Of the texture's cells (``COVER_GRID``) where the image shows keypoints of the sheet, the
        share holding one of the maps' inliers. Each image keypoint is taken back into the texture
        by the map of the piece whose inliers lie nearest to it; a cell counts as shown where
        ``SHOWN_KEYPOINTS`` land in it, and keypoints landing off the texture are the ground's.
        The sheet itself is explained wherever it shows print; another sheet of its template only
        on the template, its own text and figures showing keypoints no map explains. A sheet too
        small or blurred to show keypoints shows few cells, and so loses little."""
        import cv2

        if not len(keypoints):
            return 1.0
        texture_width, texture_height = self._features.sizes[label]
        verified = self._cells_hit(np.concatenate([points for _, points, _ in pieces]), label)
        if len(pieces) == 1:
            nearest = np.zeros(len(keypoints), np.int64)
        else:
            nearest = np.stack(
                [
                    np.linalg.norm(keypoints[:, None] - image_points[None], axis=2).min(1)
                    for _, _, image_points in pieces
                ]
            ).argmin(0)
        back = np.empty_like(keypoints, dtype=np.float64)
        for index, (affine, _, _) in enumerate(pieces):
            which = nearest == index
            inverse = cv2.invertAffineTransform(affine.astype(np.float64))
            back[which] = keypoints[which] @ inverse[:, :2].T + inverse[:, 2]
        on_sheet = (back[:, 0] >= 0) & (back[:, 0] < texture_width) & (back[:, 1] >= 0) & (back[:, 1] < texture_height)
        cells, counts = np.unique(_cell_index(back[on_sheet], texture_width, texture_height), return_counts=True)
        shown = np.union1d(np.intersect1d(cells[counts >= SHOWN_KEYPOINTS], self._cells[label]), verified)
        return float(len(verified)) / max(len(shown), 1)

    def _pieces_outline(self, pieces, label: int, width: int, height: int) -> np.ndarray | None:
        """Where the texture lies under its pieces' maps (see ``_fit``), xyxy clipped to the frame."""
        if len(pieces) == 1:
            return self._outline(pieces[0][0], label, width, height)
        texture_width, texture_height = self._features.sizes[label]
        steps_x = np.linspace(0, texture_width, COVER_GRID + 1)
        steps_y = np.linspace(0, texture_height, COVER_GRID + 1)
        centres = np.stack(
            np.meshgrid((steps_x[:-1] + steps_x[1:]) / 2, (steps_y[:-1] + steps_y[1:]) / 2), axis=-1
        ).reshape(-1, 2)
        nearest = np.stack(
            [np.linalg.norm(centres[:, None] - points[None], axis=2).min(1) for _, points, _ in pieces]
        ).argmin(0)
        half = np.array([texture_width, texture_height]) / COVER_GRID / 2
        mapped = []
        for index, (affine, _points, _) in enumerate(pieces):
            cells = centres[nearest == index]
            if not len(cells):
                continue
            corners = np.concatenate([cells + half * sign for sign in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
            mapped.append(corners @ affine[:, :2].T + affine[:, 2])
        return _clipped_extent(np.concatenate(mapped), width, height)

    def _coverage(self, texture_points: np.ndarray, label: int) -> float:
        """The share of ``label``'s keypoint-bearing cells (``COVER_GRID``) that ``texture_points`` fall in."""
        cells = self._cells[label]
        return float(len(self._cells_hit(texture_points, label))) / len(cells) if len(cells) else 0.0

    def _cells_hit(self, texture_points: np.ndarray, label: int) -> np.ndarray:
        """The keypoint-bearing cells of ``label``'s texture that ``texture_points`` fall in (sorted)."""
        texture_width, texture_height = self._features.sizes[label]
        return np.intersect1d(_cell_index(texture_points, texture_width, texture_height), self._cells[label])

    def _outline(self, affine: np.ndarray, label: int, width: int, height: int) -> np.ndarray | None:
        """The class's texture outline mapped by ``affine`` into the image, clipped to the frame
        (xyxy), or None where nothing of it is inside."""
        texture_width, texture_height = self._features.sizes[label]
        corners = (
            np.array([[0, 0], [texture_width, 0], [texture_width, texture_height], [0, texture_height]], np.float32)
            @ affine[:, :2].T
            + affine[:, 2]
        )
        return _clipped_extent(corners, width, height)

    def _search(
        self, image_points, match_labels, texture_points, width: int, height: int, every: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Sheets the texture alone finds over the whole image: (outlines (n, 4), class indices
        (n,), evidence (n, len(FEATURES)) with the confirmation, inliers and coverage filled in,
        the share of what the image shows of each that its map explains (``_shown_share`` of
        ``every``, the image's keypoints))."""
        import cv2

        from workers.train.calibration import FEATURES

        found, found_labels, found_evidence, found_shown = [], [], [], []
        first_threshold = max(3.0, SEARCH_RANSAC_FRACTION * float(np.hypot(width, height)))
        for label in range(len(self.classes)):
            own = match_labels == label
            points, sources = image_points[own], texture_points[own]
            for _ in range(SEARCH_SHEETS_PER_CLASS):
                if len(points) < SEARCH_MIN_INLIERS:
                    break
                affine, mask = cv2.estimateAffine2D(
                    sources, points, method=cv2.RANSAC, ransacReprojThreshold=first_threshold
                )
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
                    # All of them are spent; the sheet stands on those their neighbours vouch for.
                    vouched = self._vouched_pieces([(affine, sources[inliers], points[inliers])], label)
                    if (
                        vouched
                        and len(vouched[0][1]) >= SEARCH_MIN_INLIERS
                        and not _false_fit(affine)
                        and outline is not None
                        and min(outline[2] - outline[0], outline[3] - outline[1]) >= SEARCH_MIN_SIDE
                    ):
                        found.append(outline)
                        found_labels.append(label)
                        piece = vouched[0]
                        row = np.zeros(len(FEATURES), np.float32)
                        row[1:4] = (1.0, np.log1p(len(piece[1])), self._coverage(piece[1], label))
                        found_evidence.append(row)
                        found_shown.append(self._shown_share([piece], every[_inside(every, outline)], label))
                points, sources = points[~inliers], sources[~inliers]
        if not found:
            none = np.zeros(0, np.float32)
            return np.zeros((0, 4), np.float32), np.zeros(0, np.int64), np.zeros((0, len(FEATURES)), np.float32), none
        return (
            np.stack(found).astype(np.float32),
            np.array(found_labels, np.int64),
            np.stack(found_evidence),
            np.array(found_shown, np.float32),
        )


def confirmed_score(coverage: np.ndarray) -> np.ndarray:
    """A confirmed box's score (float32): ``CONFIRMED_FLOOR`` plus the rest in proportion to the
    share of its texture's cells its inliers cover (``COVER_GRID``). Among boxes the texture
    confirmed, the network's score says little: on photographs of printed documents, whose pages
    look alike at its input size, it scored forms of a target's template, confirmed on their
    letterhead and footer, as high as the targets, while such a form covers less of the texture
    than the whole sheet (bench/README.md, "Confirmed boxes ranked by their evidence")."""
    return (CONFIRMED_FLOOR + (1 - CONFIRMED_FLOOR) * np.clip(np.asarray(coverage, np.float64), 0.0, 1.0)).astype(
        np.float32
    )


def _affine_map(sources: np.ndarray, targets: np.ndarray, box, needed: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(affine, inlier mask) of one map from texture points to image points inside ``box``, by
    RANSAC at ``RANSAC_FRACTION`` of the box's diagonal; None where fewer than ``needed`` agree or
    the map is a false fit (``_false_fit``)."""
    import cv2

    if len(sources) < needed:
        return None
    x0, y0, x1, y1 = box
    threshold = max(3.0, RANSAC_FRACTION * float(np.hypot(x1 - x0, y1 - y0)))
    affine, mask = cv2.estimateAffine2D(sources, targets, method=cv2.RANSAC, ransacReprojThreshold=threshold)
    if affine is None or mask is None or int(mask.sum()) < needed or _false_fit(affine):
        return None
    return affine, mask.ravel().astype(bool)


def _off_their_neighbours(sources: np.ndarray, targets: np.ndarray, diagonal: float, scale: float) -> np.ndarray:
    """(n,) bool: the matches (texture ``sources`` to image ``targets``) that lie off the affine
    map their neighbours agree on: the ``LOCAL_NEIGHBOURS`` nearest in the texture within
    ``LOCAL_RING`` of the texture's ``diagonal``, fitted by least squares; off by more than
    ``LOCAL_TOLERANCE`` of the sheet's diagonal in the image (``scale`` times the texture's, the
    image's pixels per texture pixel) or ``LOCAL_TOLERANCE_PX``. A match is not judged (False)
    where fewer than ``LOCAL_MIN_NEIGHBOURS`` such neighbours surround it, or where they lie
    along one line (of print) beside it, which fixes no map across it (``LOCAL_MAX_CARRIED``)."""
    count = len(sources)
    if count <= LOCAL_MIN_NEIGHBOURS or diagonal <= 0:
        return np.zeros(count, dtype=bool)
    # Texture points in units of its diagonal, so the normal equations below are well scaled.
    sources, targets = sources.astype(np.float64) / diagonal, targets.astype(np.float64)
    distances = np.linalg.norm(sources[:, None] - sources[None], axis=2)
    distances = np.where((distances > LOCAL_RING[0]) & (distances < LOCAL_RING[1]), distances, np.inf)
    neighbours = min(LOCAL_NEIGHBOURS, count - 1)
    nearest = np.argpartition(distances, neighbours - 1, axis=1)[:, :neighbours]
    weights = np.isfinite(np.take_along_axis(distances, nearest, axis=1)).astype(np.float64)
    # Each match's neighbours' map by least squares, about the match itself: the map's constant is
    # where they put it, and only it is solved for. Normal equations, batched; the ridge keeps
    # every system solvable.
    offsets = (sources[nearest] - sources[:, None]) * weights[..., None]
    design = np.concatenate([offsets, weights[..., None]], axis=2)
    inverse = np.linalg.inv(np.einsum("nki,nkj->nij", design, design) + 1e-12 * np.eye(3))
    constants = np.einsum("nj,nkj,nki->ni", inverse[:, 2], design, targets[nearest] * weights[..., None])
    residuals = np.linalg.norm(constants - targets, axis=1)
    # How far the neighbours' noise carries into their map at the match, against one neighbour's
    # own (a few times, for neighbours around it or to one side): a map of neighbours along a
    # line of print that passes beside the match is the ridge's across that line, not theirs,
    # and carries it a trillion times (a line the match lies on still fixes where it should be).
    carried = inverse[:, 2, 2]
    judged = (weights.sum(axis=1) >= LOCAL_MIN_NEIGHBOURS) & (carried <= LOCAL_MAX_CARRIED)
    tolerance = max(LOCAL_TOLERANCE * scale * diagonal, LOCAL_TOLERANCE_PX)
    return judged & (residuals > tolerance)


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


def _merge(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The indices per-class NMS at ``NMS_IOU`` keeps, in order: a corrected box and the box it
    now repeats are one (the better scored, which holds the evidence, is kept)."""
    import torch
    from torchvision.ops import batched_nms

    keep = batched_nms(torch.from_numpy(boxes), torch.from_numpy(scores), torch.from_numpy(labels), NMS_IOU).numpy()
    keep.sort()
    return keep


def _one_per_sheet(boxes: np.ndarray, scores: np.ndarray, confirmed: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """The indices to keep so that each sheet is drawn once: a box is dropped where a better
    scored box the texture confirmed covers ``PIECE_INSIDE`` of it (a piece of that sheet, or the
    sheet named twice), whatever their classes. Of boxes scored alike (sheets the search found
    where the network had no box all score its floor), the one whose inliers cover more of its
    texture counts as the better: a loose fit spread over the frame does not swallow the
    sheets inside it."""
    order = np.lexsort((-coverage, -scores))
    areas = np.maximum(boxes[:, 2] - boxes[:, 0], 0) * np.maximum(boxes[:, 3] - boxes[:, 1], 0)
    kept: list[int] = []
    for index in order:
        box = boxes[index]
        inside = False
        for other in kept:
            if confirmed[other] and _intersection(box, boxes[other]) >= PIECE_INSIDE * max(areas[index], 1e-6):
                inside = True
                break
        if not inside:
            kept.append(int(index))
    return np.array(sorted(kept), np.int64)


def _named_again(
    boxes: np.ndarray, scores: np.ndarray, confirmed: np.ndarray, standing: np.ndarray | None = None
) -> np.ndarray:
    """The indices of boxes the texture did not confirm that a better-scored box standing for a
    sheet (of any class) already covers: IoU ≥ ``SHEET_IOU``, or either ``PIECE_INSIDE`` of the
    other. The network names one sheet as several classes, and boxes a piece of it or more
    around it; the better-scored box is kept. ``standing`` (n,) bool: the boxes that may stand
    for a sheet (None: all); the others are neither kept nor named again."""
    order = np.argsort(-scores, kind="stable")
    if standing is not None:
        order = order[standing[order]]
    kept: list[int] = []
    again: list[int] = []
    for index in order:
        named = not confirmed[index] and any(_one_sheet(boxes[index], boxes[other]) for other in kept)
        (again if named else kept).append(int(index))
    return np.array(sorted(again), np.int64)


def _one_sheet(box: np.ndarray, other: np.ndarray) -> bool:
    """Whether two xyxy boxes stand for one sheet: IoU ≥ ``SHEET_IOU``, or either ``PIECE_INSIDE`` of the other."""
    overlap = _intersection(box, other)
    if overlap <= 0:
        return False
    area = max(box[2] - box[0], 0) * max(box[3] - box[1], 0)
    other_area = max(other[2] - other[0], 0) * max(other[3] - other[1], 0)
    union = area + other_area - overlap
    return overlap >= SHEET_IOU * union or overlap >= PIECE_INSIDE * min(area, other_area)


def _intersection(box: np.ndarray, other: np.ndarray) -> float:
    """The area two xyxy boxes share (0 where they do not overlap)."""
    width = min(box[2], other[2]) - max(box[0], other[0])
    height = min(box[3], other[3]) - max(box[1], other[1])
    return float(width * height) if width > 0 and height > 0 else 0.0


def _clipped_extent(corners: np.ndarray, width: int, height: int) -> np.ndarray | None:
    """The extent (xyxy) of points in the image, clipped to its frame; None where nothing of it is inside."""
    outline = np.array(
        [
            max(corners[:, 0].min(), 0.0),
            max(corners[:, 1].min(), 0.0),
            min(corners[:, 0].max(), float(width)),
            min(corners[:, 1].max(), float(height)),
        ],
        np.float32,
    )
    return outline if outline[2] > outline[0] and outline[3] > outline[1] else None


def _inside(points: np.ndarray, box) -> np.ndarray:
    x0, y0, x1, y1 = box
    return (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)


def _cell_index(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Each texture point's coverage cell (row-major over a ``COVER_GRID`` grid)."""
    columns = np.clip((points[:, 0] / max(width, 1) * COVER_GRID).astype(np.int64), 0, COVER_GRID - 1)
    rows = np.clip((points[:, 1] / max(height, 1) * COVER_GRID).astype(np.int64), 0, COVER_GRID - 1)
    return rows * COVER_GRID + columns
