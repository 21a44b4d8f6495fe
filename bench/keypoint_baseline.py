"""The classical recipe a user would try first, as a baseline beside foldwise's detector.

For each class's flat texture: OpenCV SIFT keypoints, matched from the image's keypoints with
FLANN's KD-trees and Lowe's ratio test, then a homography by RANSAC; where at least
``MIN_INLIERS`` matches agree, the texture's corners mapped by it give a box. A texture is
looked for again after its inliers are taken out, so two copies of one sheet are two boxes.
No network, no training: what a keypoint pipeline gets from the same flat originals foldwise
trains on.

Every box it draws is one it is sure of (that is its rule), so its scores lie in [0.8, 1),
ranked by the number of inliers: at the paper's 0.8 cut every box counts, and the mAP ranks
them as its evidence does.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

RATIO = 0.75  # Lowe's ratio test
MIN_INLIERS = 12
RANSAC_PX = 5.0  # reprojection threshold, in the image's pixels
COPIES_PER_CLASS = 3  # sheets of one class looked for per image, one after another
FLANN_CHECKS = 64


class KeypointBaseline:
    """SIFT + FLANN + RANSAC homography per texture; :meth:`detect` gives boxes, scores, labels."""

    def __init__(self, textures: Mapping[str, np.ndarray], classes: list[str]) -> None:
        import cv2

        self.classes = list(classes)
        self._sift = cv2.SIFT_create()
        cv2.setRNGSeed(0)  # FLANN's KD-trees split at random: seeded, every run draws the same boxes
        self._textures = []
        for name in self.classes:
            gray = _gray(np.asarray(textures[name]))
            keypoints, descriptors = self._sift.detectAndCompute(gray, None)
            points = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2)
            matcher = None
            if descriptors is not None and len(descriptors) >= 2:
                matcher = cv2.FlannBasedMatcher(dict(algorithm=1, trees=4), dict(checks=FLANN_CHECKS))
                matcher.add([descriptors])
                matcher.train()
            self._textures.append((matcher, points, gray.shape[1], gray.shape[0]))

    def detect(self, image: np.ndarray) -> dict[str, np.ndarray]:
        """Boxes (n, 4) xyxy in ``image``'s pixels, scores (n,), labels (n,) 0-based class indices."""
        import cv2

        gray = _gray(image)
        height, width = gray.shape
        keypoints, descriptors = self._sift.detectAndCompute(gray, None)
        boxes, scores, labels = [], [], []
        if descriptors is not None and len(descriptors) >= 2:
            image_points = np.array([k.pt for k in keypoints], np.float32)
            for label, (matcher, texture_points, texture_width, texture_height) in enumerate(self._textures):
                if matcher is None:
                    continue
                pairs = matcher.knnMatch(descriptors, k=2)
                good = [
                    (m.queryIdx, m.trainIdx)
                    for m, *rest in (p for p in pairs if p)
                    if not rest or m.distance < RATIO * rest[0].distance
                ]
                if len(good) < MIN_INLIERS:
                    continue
                source = texture_points[[t for _, t in good]]
                target = image_points[[q for q, _ in good]]
                corners = np.array(
                    [[0, 0], [texture_width, 0], [texture_width, texture_height], [0, texture_height]], np.float32
                )
                for _ in range(COPIES_PER_CLASS):
                    if len(source) < MIN_INLIERS:
                        break
                    homography, mask = cv2.findHomography(source, target, cv2.RANSAC, RANSAC_PX)
                    if homography is None or mask is None or int(mask.sum()) < MIN_INLIERS:
                        break
                    inliers = mask.ravel().astype(bool)
                    mapped = cv2.perspectiveTransform(corners[None], homography)[0]
                    box = _plausible_box(mapped, width, height)
                    if box is not None:
                        boxes.append(box)
                        scores.append(0.8 + 0.2 * (1 - MIN_INLIERS / (int(inliers.sum()) + 1)))
                        labels.append(label)
                    source, target = source[~inliers], target[~inliers]
        return {
            "boxes": np.array(boxes, np.float32).reshape(-1, 4),
            "scores": np.array(scores, np.float32),
            "labels": np.array(labels, np.int64),
        }


def _gray(image: np.ndarray) -> np.ndarray:
    import cv2

    image = np.ascontiguousarray(image)
    return image if image.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2GRAY)


def _plausible_box(corners: np.ndarray, width: int, height: int) -> list[float] | None:
    """The mapped outline's box clipped to the frame, or None where the homography folds or
    mirrors the sheet (its outline no convex quadrilateral in the texture's order)."""
    edges = np.roll(corners, -1, axis=0) - corners
    turns = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    if not (turns > 0).all():
        return None
    x0, y0 = max(float(corners[:, 0].min()), 0.0), max(float(corners[:, 1].min()), 0.0)
    x1, y1 = min(float(corners[:, 0].max()), float(width)), min(float(corners[:, 1].max()), float(height))
    return [x0, y0, x1, y1] if x1 - x0 >= 4 and y1 - y0 >= 4 else None
