"""θ's light and surface conditions as scene terms both backends render (scene.py's model).

* ``light_rig``: the lights (count, colour, directions) and the ambient share. At the
  canonical values (one light, white, spread 0, no ambient) it returns no rig at all and the
  scene keeps the paper's one light at camera.py's ``LIGHT_DIRECTION``. Otherwise θ's
  irradiance E is shared: the ambient share a gives a white uniform sky of a·E; the lights
  share (1 − a)·E with random weights. A light's direction lies uniformly on the cap within
  ``light_spread`` of the optical axis (or at ``LIGHT_DIRECTION`` when the spread is 0); its
  colour has saturation ``light_saturation`` and a hue within ±0.08 of one drawn per image (a
  colour cast, not a rainbow that averages to white), scaled to a mean of 1 over the channels
  (so colour does not change how much light there is).
* ``highlight_direction``: with a glossy layer, the key light is put where the mirror
  reflection of the camera off a random point of the sheet comes from, so the highlight lands
  on the sheet (a light at a random place would rarely show one on a flat sheet).
* ``wrinkle_normal_map``: ``wrinkles`` crease lines across the sheet, each a finite ridge (a
  tent profile of random width, length and side, tilting the normal by up to
  ``wrinkle_depth``), summed into a height field over the flat sheet, as a tangent-space normal
  map (x along u, y along v, z out of the printed side). Shading only: the mesh stays exact.
* ``shadow_caster``: a random polygon lifted off the sheet along the key light, sized by
  bisection so that its shadow covers the share ``shadow`` of the flat sheet; its coverage
  map has a soft edge, the penumbra of a sun of ``SHADOW_SUN_ANGLE``.

Everything random is drawn from the generator the pipeline passes (one purpose each).
"""

from __future__ import annotations

import colorsys
import math

import cv2
import numpy as np

from workers.render.camera import LIGHT_DIRECTION
from workers.render.scene import Light, ShadowCaster

# The sun's angular diameter for shadow scenes (rad): the penumbra's width is this times the
# caster's distance (the real sun is 0.0093; a lamp is wider).
SHADOW_SUN_ANGLE = math.radians(2.0)
# The caster floats this share of the sheet's longer side above it, along the light.
CASTER_LIFT = 0.25
# Coverage-map and normal-map resolution (texels along the longer side).
SHADOW_MAP_TEXELS = 256
NORMAL_MAP_TEXELS = 256


def light_rig(theta, rng: np.random.Generator) -> tuple[tuple[Light, ...] | None, tuple[float, float, float]]:
    """(lights, ambient RGB irradiance) for θ; (None, 0) at the canonical values."""
    count, saturation, spread, ambient = theta.light_count, theta.light_saturation, theta.light_spread, theta.ambient
    if count == 1 and saturation == 0 and spread == 0 and ambient == 0 and theta.specular == 0:
        return None, (0.0, 0.0, 0.0)
    total = float(theta.irradiance)
    weights = rng.uniform(0.5, 1.0, size=count)
    weights = weights / weights.sum() * (1.0 - ambient) * total
    lights = []
    # One colour cast per image: the lights' hues scatter around a common one.
    base_hue = rng.random()
    for weight in weights:
        if spread > 0:
            polar = math.acos(1.0 - rng.random() * (1.0 - math.cos(spread)))
            azimuth = rng.uniform(0.0, 2.0 * math.pi)
            direction = np.array(
                [math.sin(polar) * math.cos(azimuth), math.sin(polar) * math.sin(azimuth), math.cos(polar)]
            )
        else:
            direction = LIGHT_DIRECTION.copy()
        hue = (base_hue + rng.uniform(-0.08, 0.08)) % 1.0
        rgb = np.array(colorsys.hsv_to_rgb(hue, saturation, 1.0))
        rgb = rgb / rgb.mean()
        lights.append(Light(direction=direction, irradiance=float(weight), colour=tuple(float(c) for c in rgb)))
    level = ambient * total
    return tuple(lights), (level, level, level)


def highlight_direction(
    vertices: np.ndarray, faces: np.ndarray, camera_centre: np.ndarray, rng: np.random.Generator
) -> np.ndarray | None:
    """Towards a light whose mirror reflection off a random point of the sheet (area-weighted,
    on a face the camera sees from its front or back) reaches the camera; None when no face
    reflects anything towards it."""
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    if not area.sum() > 0:
        return None
    face = int(rng.choice(len(faces), p=area / area.sum()))
    a, b = rng.random(2)
    if a + b > 1:
        a, b = 1 - a, 1 - b
    point = corners[face, 0] + a * (corners[face, 1] - corners[face, 0]) + b * (corners[face, 2] - corners[face, 0])
    normal = cross[face] / max(np.linalg.norm(cross[face]), 1e-300)
    view = camera_centre - point
    view = view / max(np.linalg.norm(view), 1e-300)
    if normal @ view < 0:
        normal = -normal
    mirror = 2.0 * (normal @ view) * normal - view
    return mirror / max(np.linalg.norm(mirror), 1e-300)


def wrinkle_normal_map(
    wrinkles: int,
    depth: float,
    width_m: float,
    height_m: float,
    rng: np.random.Generator,
    texels: int = NORMAL_MAP_TEXELS,
) -> np.ndarray | None:
    """(rows, cols, 3) float32 tangent-space unit normals of the creases over the flat sheet
    (row 0 at the top, v = 1); None when there is nothing to show."""
    if wrinkles <= 0 or depth <= 0:
        return None
    long_side = max(width_m, height_m)
    cols = max(int(round(texels * width_m / long_side)), 8)
    rows = max(int(round(texels * height_m / long_side)), 8)
    x = (np.arange(cols) + 0.5) / cols * width_m
    y = (1.0 - (np.arange(rows) + 0.5) / rows) * height_m  # row 0 at the top of the sheet
    gx, gy = np.meshgrid(x, y)
    height = np.zeros((rows, cols))
    for _ in range(wrinkles):
        centre = rng.uniform((0.0, 0.0), (width_m, height_m))
        angle = rng.uniform(0.0, math.pi)
        along = np.array([math.cos(angle), math.sin(angle)])
        across = np.array([-along[1], along[0]])
        half_width = rng.uniform(0.02, 0.07) * long_side
        half_length = rng.uniform(0.15, 0.6) * long_side
        slope = math.tan(depth * rng.uniform(0.5, 1.0)) * rng.choice([-1.0, 1.0])
        d_across = (gx - centre[0]) * across[0] + (gy - centre[1]) * across[1]
        d_along = (gx - centre[0]) * along[0] + (gy - centre[1]) * along[1]
        ridge = np.clip(1.0 - np.abs(d_across) / half_width, 0.0, None) * half_width * slope
        # A crease fades out towards its ends (a smooth step over its last third).
        fade = np.clip((half_length - np.abs(d_along)) / (half_length / 3.0), 0.0, 1.0)
        height += ridge * fade * fade * (3.0 - 2.0 * fade)
    # Slopes in metres per metre: along u (x, columns) and v (y, up = decreasing rows).
    du = np.gradient(height, width_m / cols, axis=1)
    dv = -np.gradient(height, height_m / rows, axis=0)
    normal = np.dstack([-du, -dv, np.ones_like(height)])
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    return normal.astype(np.float32)


def _random_polygon(rng: np.random.Generator, vertices: int) -> np.ndarray:
    """A star-shaped polygon around the origin, radius about 1 (k, 2)."""
    angles = np.sort(rng.uniform(0.0, 2.0 * math.pi, size=vertices))
    radii = rng.uniform(0.55, 1.0, size=vertices)
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])


def _covered_share(polygon: np.ndarray, width_m: float, height_m: float, texels: int = 160) -> float:
    long_side = max(width_m, height_m)
    cols = max(int(round(texels * width_m / long_side)), 4)
    rows = max(int(round(texels * height_m / long_side)), 4)
    canvas = np.zeros((rows, cols), np.uint8)
    points = np.column_stack([polygon[:, 0] / width_m * cols, (1.0 - polygon[:, 1] / height_m) * rows])
    cv2.fillPoly(canvas, [np.round(points * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return float(canvas.mean())


def shadow_caster(
    share: float,
    width_m: float,
    height_m: float,
    rotation: np.ndarray,
    scale: float,
    light: np.ndarray,
    rng: np.random.Generator,
) -> ShadowCaster | None:
    """A caster whose shadow along ``light`` (world, towards the light) covers ``share`` of the
    flat sheet (posed by ``rotation`` and ``scale`` as camera.build_scene does); None when the
    share is 0 or the light grazes the sheet (no shadow to cast)."""
    if share <= 0:
        return None
    light = np.asarray(light, np.float64) / np.linalg.norm(light)
    light_in_sheet = rotation.T @ light
    if abs(light_in_sheet[2]) < 0.05:
        return None
    shape = _random_polygon(rng, int(rng.integers(5, 11)))
    centre = rng.uniform((0.2 * width_m, 0.2 * height_m), (0.8 * width_m, 0.8 * height_m))
    low, high = 0.0, 2.0 * math.hypot(width_m, height_m)
    for _ in range(30):
        radius = 0.5 * (low + high)
        if _covered_share(centre + radius * shape, width_m, height_m) < share:
            low = radius
        else:
            high = radius
    outline = centre + 0.5 * (low + high) * shape  # flat-sheet metres
    # The flat sheet's point (x, y) sits at (x - W/2, y - H/2, 0) in the sheet frame. Every
    # caster point is its flat point's world position moved towards the light by scale × lift,
    # so that a parallel projection along the light puts the outline back on the flat sheet.
    lift = CASTER_LIFT * max(width_m, height_m) / abs(light_in_sheet[2])
    u_axis, v_axis = rotation[:, 0], rotation[:, 1]
    origin = scale * (rotation @ np.array([-width_m / 2.0, -height_m / 2.0, 0.0])) + scale * lift * light
    penumbra = SHADOW_SUN_ANGLE * scale * lift  # world metres at the sheet
    margin = 3.0 * penumbra / scale + 1e-6
    u0, v0 = outline.min(axis=0) - margin
    u1, v1 = outline.max(axis=0) + margin
    long_side = max(u1 - u0, v1 - v0)
    cols = max(int(round(SHADOW_MAP_TEXELS * (u1 - u0) / long_side)), 4)
    rows = max(int(round(SHADOW_MAP_TEXELS * (v1 - v0) / long_side)), 4)
    coverage = np.zeros((rows, cols), np.float32)
    # Rows run along +v here (the kernel's map row index grows with v).
    points = np.column_stack([(outline[:, 0] - u0) / (u1 - u0) * cols, (outline[:, 1] - v0) / (v1 - v0) * rows])
    cv2.fillPoly(coverage, [np.round(points * 16).astype(np.int32)], 1.0, lineType=cv2.LINE_AA, shift=4)
    sigma = penumbra / scale / (u1 - u0) * cols / 2.0
    if sigma > 0.3:
        coverage = cv2.GaussianBlur(coverage, (0, 0), sigma)
    polygon = np.column_stack([outline, np.zeros(len(outline))]) - (width_m / 2.0, height_m / 2.0, 0.0)
    polygon_world = scale * (polygon @ rotation.T) + scale * lift * light
    return ShadowCaster(
        origin=origin,
        u_axis=u_axis.copy(),
        v_axis=v_axis.copy(),
        coverage=np.clip(coverage, 0.0, 1.0),
        extent=(float(scale * u0), float(scale * u1), float(scale * v0), float(scale * v1)),
        polygon=polygon_world,
        sun_angle=SHADOW_SUN_ANGLE,
    )
