"""Scores that mean something: a detection's score as the chance that it is a true detection.

The network's score and the texture check's evidence are read together by a logistic model
(Platt scaling over several features): ``p = sigmoid(bias + weights · features)``. A user who
draws every box scoring at least 0.8 then sees boxes of which about four in five or more are
true, whatever the scene, instead of a network score that is as high on a lookalike sheet as on
the sheet itself.

The features (``FEATURES``) of one detection, as the texture check measures them:

- ``network``: the logit of the network's (voted) score; 0 for a sheet only the search found;
- ``confirmed``: 1 where the texture's matches agree on maps of the sheet (see texture_check);
- ``inliers``: log(1 + matches agreeing on those maps);
- ``coverage``: the share of the texture's keypoint-bearing cells holding one of them: a
  lookalike sheet of the same template matches its letterhead and footer, the sheet itself
  matches all over;
- ``keypoints``: log(1 + the image's SIFT keypoints inside the box): a sharp, large box;
- ``match_share``: of those keypoints, the share matching the box's class: many keypoints and
  few matches is a printed sheet that is not this one.

``fit`` learns the weights from detections labelled true or false (``bench/calibrate.py`` on a
calibration split of foldwise's out-of-domain sets, or ``foldwise calibrate`` on a user's own
labelled photographs); the result is recorded in the checkpoint (``meta["calibration"]``) and
read back by ``detect_object``, the REST answer and the ONNX export's metadata.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

SHIPPED = Path(__file__).with_name("calibration.json")  # detector.calibration: shipped
FEATURES = ("network", "confirmed", "inliers", "coverage", "keypoints", "match_share")
SCORE_EPSILON = 1e-4  # network scores are clipped to [ε, 1 − ε] before their logit
# A ridge on the weights (not the bias): where the true and false detections of a small set are
# separable, the weights stay finite instead of running off.
L2 = 1.0


@dataclass(frozen=True)
class Calibration:
    """A logistic model over ``FEATURES``: ``probability(features)`` is the chance a detection is true."""

    weights: tuple[float, ...]
    bias: float
    features: tuple[str, ...] = FEATURES
    fitted_on: str = ""  # what it was fitted on, for a reader of the checkpoint

    def __post_init__(self) -> None:
        if tuple(self.features) != FEATURES:
            raise ValueError(f"calibration: features {list(self.features)} are not this version's {list(FEATURES)}")
        if len(self.weights) != len(FEATURES):
            raise ValueError(f"calibration: {len(self.weights)} weights for {len(FEATURES)} features")
        if not all(math.isfinite(value) for value in (*self.weights, self.bias)):
            raise ValueError("calibration: weights and bias must be finite numbers")

    def probability(self, features: np.ndarray) -> np.ndarray:
        """(n,) float32 in (0, 1) for (n, len(FEATURES)) features."""
        features = np.asarray(features, np.float64).reshape(-1, len(FEATURES))
        logits = self.bias + features @ np.asarray(self.weights, np.float64)
        return (1.0 / (1.0 + np.exp(-np.clip(logits, -60, 60)))).astype(np.float32)

    def to_dict(self) -> dict:
        return {
            "features": list(self.features),
            "weights": list(self.weights),
            "bias": self.bias,
            "fitted_on": self.fitted_on,
        }

    @classmethod
    def from_dict(cls, data: Mapping) -> Calibration:
        try:
            return cls(
                weights=tuple(float(value) for value in data["weights"]),
                bias=float(data["bias"]),
                features=tuple(str(name) for name in data["features"]),
                fitted_on=str(data.get("fitted_on", "")),
            )
        except (KeyError, TypeError) as error:
            raise ValueError(f"calibration: malformed record ({error!r})") from None


@lru_cache(maxsize=1)
def shipped_calibration() -> Calibration:
    """The calibration foldwise ships (``SHIPPED``; ``bench/calibrate.py --ship`` writes it)."""
    return Calibration.from_dict(json.loads(SHIPPED.read_text(encoding="utf-8")))


def network_logit(scores: np.ndarray) -> np.ndarray:
    scores = np.clip(np.asarray(scores, np.float64), SCORE_EPSILON, 1 - SCORE_EPSILON)
    return np.log(scores / (1 - scores))


def fit(features: np.ndarray, truths: Sequence[bool], fitted_on: str = "", iterations: int = 50) -> Calibration:
    """The logistic model of ``truths`` (n,) given ``features`` (n, len(FEATURES)) by Newton's
    method on the ridge-penalised log-likelihood. Needs true and false detections both."""
    x = np.asarray(features, np.float64).reshape(-1, len(FEATURES))
    y = np.asarray(truths, np.float64).reshape(-1)
    if len(x) != len(y):
        raise ValueError(f"calibration: {len(x)} feature rows for {len(y)} labels")
    if not (0 < y.sum() < len(y)):
        raise ValueError("calibration: needs both true and false detections to fit")
    design = np.column_stack([np.ones(len(x)), x])
    theta = np.zeros(design.shape[1])
    ridge = np.full(design.shape[1], L2)
    ridge[0] = 0.0
    for _ in range(iterations):
        probability = 1.0 / (1.0 + np.exp(-np.clip(design @ theta, -60, 60)))
        gradient = design.T @ (probability - y) + ridge * theta
        hessian = (
            (design * (probability * (1 - probability))[:, None]).T @ design
            + np.diag(ridge)
            + 1e-9 * np.eye(len(theta))
        )
        step = np.linalg.solve(hessian, gradient)
        theta -= step
        if np.abs(step).max() < 1e-8:
            break
    return Calibration(weights=tuple(float(v) for v in theta[1:]), bias=float(theta[0]), fitted_on=fitted_on)


def calibrate_detector(detector, samples, classes: Sequence[str], iou: float = 0.5, fitted_on: str = "") -> Calibration:
    """A calibration fitted on labelled images (``workers.train.data.Sample``, class names
    ``classes``): the detector detects as it does when used (its views, cascade, texture check and
    lookalikes), the check measures each detection's evidence, and each detection is labelled true
    or false against the images' boxes. A calibration the detector already records is left out
    of the fit."""
    from dataclasses import replace

    from workers.train.evaluation import detector_predictions, true_detections

    if not detector.textures:
        raise ValueError("calibration: the detector carries no textures, so there is no texture evidence to calibrate")
    uncalibrated = replace(detector, meta={key: value for key, value in detector.meta.items() if key != "calibration"})
    checked, truth, _groups, _classes = detector_predictions(uncalibrated, samples, classes, with_evidence=True)
    features = [found["evidence"] for found in checked]
    truths = [true_detections(found, target, iou) for found, target in zip(checked, truth)]
    return fit(np.concatenate(features), np.concatenate(truths), fitted_on=fitted_on)
