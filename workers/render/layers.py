"""Several sheets in one image: target instances (``instances`` > 1) and distractors (``clutter``).

Every extra sheet is its own layer: a Scene3D of its own (mesh, texture, pose, place) seen by
the image's one camera under its one light rig, rendered by the same backend, then composited
in depth order (painter's algorithm: sheets far from each other along the view never
interpenetrate, which the placements below keep). Flat distractor shapes are 2D layers.

* Instances: the frame is split into a grid of at least ``instances`` cells (2 × 2 up to four
  sheets, 3 × 3 up to nine); each instance takes a random cell, is shrunk to fit it
  (``INSTANCE_SCALE`` × θ's scale) and jittered within it; the first instance is θ's own object,
  bend and pose, the others draw their object uniformly, a bend of up to θ's rulings and θ's pose
  turned in-plane by a random angle. Their depth order is random, at small depth steps.
* Distractors: each is a bent sheet printed with a distractor photograph or pattern (never an
  object's texture: a lookalike, the paper's Fig. 13) or a flat random shape filled with one;
  a share ``clutter_front`` lies in front of the targets (closer to the camera), the rest behind
  them; positions are uniform over the frame, sizes from a fifth to two thirds of a target's,
  any in-plane angle, a tilt up to 60°. A front distractor that would hide more than half of
  what a target still shows is left out (the pipeline checks), so clutter never buries the
  object it is meant to distract from.
* Lookalikes (``assets.lookalikes``): sheets of the targets' kind that are none of them (the
  user's other forms or covers). One or two lie behind the targets in every image, negatives
  included, bent like a distractor sheet and sized like a target (``LOOKALIKE_SCALE`` × θ's
  scale): the detector learns that a sheet of that kind is not yet its object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from workers.render.scene import Camera

# A sheet in an instance's cell spans about this share of what it spans alone.
INSTANCE_SCALE = (0.38, 0.5)
# Depth step between stacked instances (m): enough that their bends never interleave.
INSTANCE_DEPTH_STEP = 0.35
# Behind the targets, distractors stand this far back (m); in front, this far forward.
BEHIND_DEPTHS = (0.6, 2.5)
FRONT_DEPTHS = (0.6, 1.8)
DISTRACTOR_SCALE = (0.2, 0.65)
DISTRACTOR_MAX_TILT = math.radians(60.0)
SHAPE_SIZE = (0.12, 0.4)  # flat shapes: side as a share of the image size
SHAPE_SHARE = 0.35  # of distractors, flat shapes rather than sheets
LOOKALIKES_PER_IMAGE = (1, 2)  # lookalike sheets in every image where the assets give some
LOOKALIKE_SCALE = (0.6, 1.0)  # × θ's scale: printed on the same paper as the target


@dataclass(frozen=True)
class SheetPlacement:
    """Where one sheet of a multi-sheet image goes (applied after its own pose)."""

    object: str | None  # an object's name (a target instance), or None (a distractor)
    texture: str | None  # a distractor's texture name (None for a target)
    rulings: int
    scale: float  # multiplies the sheet's canonical size
    roll: float
    pitch: float
    yaw: float
    rotation: float
    tilt: float
    tilt_azimuth: float
    translation: tuple[float, float, float]
    front: bool = False  # a distractor in front of the targets
    seed: int = 0  # of the sheet's own bend


@dataclass(frozen=True)
class ShapePlacement:
    """A flat distractor shape: its texture, centre (pixels), side (pixels), angle (rad)."""

    texture: str
    centre: tuple[float, float]
    side: float
    angle: float
    front: bool
    seed: int


def world_point(camera: Camera, pixel: tuple[float, float], depth_z: float) -> np.ndarray:
    """The world point on the plane z = ``depth_z`` that pixel (x, y) sees."""
    ray = np.linalg.solve(camera.K, np.array([pixel[0], pixel[1], 1.0]))
    direction = camera.R.T @ ray
    centre = -camera.R.T @ camera.t
    return centre + (depth_z - centre[2]) / direction[2] * direction


def _grid(count: int) -> int:
    return max(2, math.ceil(math.sqrt(count)))


def instance_placements(theta, camera: Camera, objects: list[str], rng: np.random.Generator) -> list[SheetPlacement]:
    """Where θ's ``instances`` (> 1) target sheets go: one per random grid cell (module notes)."""
    count = int(theta.instances)
    cells = _grid(count)
    chosen = rng.choice(cells * cells, size=count, replace=False)
    depths = rng.permutation(count) * INSTANCE_DEPTH_STEP
    width, height = camera.width, camera.height
    placements = []
    for index in range(count):
        row, col = divmod(int(chosen[index]), cells)
        jitter = rng.uniform(-0.15, 0.15, size=2)
        pixel = ((col + 0.5 + jitter[0]) / cells * width, (row + 0.5 + jitter[1]) / cells * height)
        depth = float(depths[index])
        shrink = rng.uniform(*INSTANCE_SCALE) * 2.0 / cells
        if index == 0:
            name, rulings, turn = theta.object, int(theta.rulings), 0.0
        else:
            name = objects[int(rng.integers(len(objects)))]
            rulings = int(rng.integers(0, max(int(theta.rulings), 2) + 1))
            turn = float(rng.uniform(-math.pi / 6, math.pi / 6))
        placements.append(
            SheetPlacement(
                object=name,
                texture=None,
                rulings=rulings,
                scale=float(theta.scale) * shrink,
                roll=float(theta.roll),
                pitch=float(theta.pitch),
                yaw=float(theta.yaw),
                rotation=float(theta.rotation) + turn,
                tilt=float(theta.tilt),
                tilt_azimuth=float(theta.tilt_azimuth),
                translation=tuple(float(v) for v in world_point(camera, pixel, depth)),
                seed=int(rng.integers(0, 2**31 - 1)),
            )
        )
    return placements


def distractor_placements(
    theta, camera: Camera, textures: list[str], rng: np.random.Generator, lookalikes: list[str] = ()
) -> list[SheetPlacement | ShapePlacement]:
    """θ's ``clutter`` distractors, then the ``lookalikes`` sheets (module notes), in drawing
    order. The lookalikes draw from ``rng`` after the clutter, so a θ renders its clutter alike
    with or without them."""
    placements: list[SheetPlacement | ShapePlacement] = []
    width, height = camera.width, camera.height
    for _ in range(int(theta.clutter)):
        texture = textures[int(rng.integers(len(textures)))]
        front = bool(rng.random() < theta.clutter_front)
        pixel = (float(rng.uniform(0.05, 0.95) * width), float(rng.uniform(0.05, 0.95) * height))
        seed = int(rng.integers(0, 2**31 - 1))
        if rng.random() < SHAPE_SHARE:
            side = float(rng.uniform(*SHAPE_SIZE) * max(width, height))
            placements.append(ShapePlacement(texture, pixel, side, float(rng.uniform(0, 2 * math.pi)), front, seed))
            continue
        depth = float(rng.uniform(*FRONT_DEPTHS) if front else -rng.uniform(*BEHIND_DEPTHS))
        at = world_point(camera, pixel, depth)
        placements.append(_loose_sheet(texture, at, 1.0, DISTRACTOR_SCALE, front, seed, rng))
    if lookalikes:
        low, high = LOOKALIKES_PER_IMAGE
        for _ in range(int(rng.integers(low, high + 1))):
            pixel = (float(rng.uniform(0.05, 0.95) * width), float(rng.uniform(0.05, 0.95) * height))
            texture = lookalikes[int(rng.integers(len(lookalikes)))]
            at = world_point(camera, pixel, -rng.uniform(*BEHIND_DEPTHS))
            seed = int(rng.integers(0, 2**31 - 1))
            placements.append(_loose_sheet(texture, at, float(theta.scale), LOOKALIKE_SCALE, False, seed, rng))
    return placements


def _loose_sheet(
    texture: str, at: np.ndarray, scale: float, scale_range: tuple[float, float], front: bool, seed: int, rng
) -> SheetPlacement:
    """A sheet that is no target (a distractor or a lookalike) at world point ``at``: its bend,
    size (``scale`` × a draw from ``scale_range``), in-plane turn and tilt drawn from ``rng``."""
    return SheetPlacement(
        object=None,
        texture=texture,
        rulings=int(rng.integers(0, 4)),
        scale=float(scale * rng.uniform(*scale_range)),
        roll=0.0,
        pitch=0.0,
        yaw=0.0,
        rotation=float(rng.uniform(-math.pi, math.pi)),
        tilt=float(rng.uniform(0.0, DISTRACTOR_MAX_TILT)),
        tilt_azimuth=float(rng.uniform(0.0, 2 * math.pi)),
        translation=tuple(float(v) for v in at),
        front=front,
        seed=seed,
    )
