"""Camera, pose, scale and lighting: from θ's numbers to a :class:`~workers.render.scene.Scene3D`.

World frame (metres): the sheet's centre at the origin; x right, y up, z towards the
canonical camera. The sheet mesh comes in its own frame (flat sheet in z = 0, centred, front
normal +z), so the canonical view looks straight at its front.

* Sheet size: the longer side is ``SHEET_LONG_SIDE_M`` = 3 m and the shorter side follows the
  texture's aspect ratio. A large sheet, so that Table 3's position offsets (up to 2 m) move
  it across the frame without throwing it out: at the canonical distance the half-frame is
  2.31 m wide, so an offset of 0.5 m shifts the sheet by 22% of the half-frame, 2 m by 87%
  (then about half of it is cropped by the border).
* Canonical view: pinhole with a 40° field of view on a square image, camera on the +z axis
  at the distance where the sheet's longer side spans ``CANONICAL_SPAN`` = 65% of the image.
* Pose (Table 3 "camera pose"): roll, pitch and yaw are the sheet's orientation relative to
  the camera, ``R = Rz(roll) @ Ry(yaw) @ Rx(pitch)`` about the sheet's centre (roll about the
  optical axis, pitch about the horizontal image axis, yaw about the vertical one); the same
  as the camera orbiting the sheet while looking at it. Rotating the camera about its own
  centre instead would turn a 30° yaw into an empty image (half the field of view is 20°).
  Pitch or yaw of π/2 shows the sheet edge-on.
* Position offset: the camera moves by ``position_offset_m`` in the plane facing it (world
  x-y, direction ``position_offset_angle`` counter-clockwise from image right), keeping its
  orientation, so the sheet slides across the frame. Not 3D: moving along the optical axis
  changes the apparent size, which is what the scale condition varies; keeping depth fixed
  keeps the two conditions apart (and a 2 m step towards the camera would nearly hit the
  sheet).
* Scale multiplies the sheet's size (its vertices, about its centre); the camera stays at the
  canonical distance. Equivalent in the image to dividing the distance, except for depth
  effects on a deformed sheet.
* Lighting: one distant light from the camera's side, a little above and to the left of
  the optical axis (``LIGHT_DIRECTION``, 23° off it), irradiance from θ, Lambertian sheet.
  ``exposure`` = 1 / cos(23°), so that a flat facet facing the canonical camera shows its
  texture unchanged at irradiance 1 (see scene.py), while bent or turned facets get brighter
  or darker: folds and pose show in the shading, as they would under a real lamp.
"""

from __future__ import annotations

import math

import numpy as np

from workers.render.scene import Camera, Scene3D

FIELD_OF_VIEW = math.radians(40.0)
SHEET_LONG_SIDE_M = 3.0
CANONICAL_SPAN = 0.65
LIGHT_DIRECTION = np.array([-0.25, 0.35, 1.0]) / np.linalg.norm([-0.25, 0.35, 1.0])
EXPOSURE = 1.0 / float(LIGHT_DIRECTION[2])
# Camera frame = OpenCV (x right, y down, z forward); the canonical camera looks along -z.
_WORLD_TO_CAMERA = np.diag([1.0, -1.0, -1.0])


def intrinsics(image_size: int, field_of_view: float = FIELD_OF_VIEW) -> np.ndarray:
    """K of a square image: principal point at the image centre (pixel edges run 0..size)."""
    focal = (image_size / 2.0) / math.tan(field_of_view / 2.0)
    return np.array([[focal, 0.0, image_size / 2.0], [0.0, focal, image_size / 2.0], [0.0, 0.0, 1.0]])


def canonical_distance(long_side: float = SHEET_LONG_SIDE_M, span: float = CANONICAL_SPAN) -> float:
    """Distance at which a fronto-parallel sheet's longer side spans ``span`` of the image."""
    return (long_side / 2.0) / (span * math.tan(FIELD_OF_VIEW / 2.0))


def sheet_size(texture_shape: tuple[int, ...], long_side: float = SHEET_LONG_SIDE_M) -> tuple[float, float]:
    """(width, height) in metres of a sheet printed with a texture of shape (rows, cols, ...)."""
    rows, cols = texture_shape[:2]
    if cols >= rows:
        return long_side, long_side * rows / cols
    return long_side * cols / rows, long_side


def pose_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(roll) @ Ry(yaw) @ Rx(pitch): the sheet's orientation relative to the canonical camera."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    return rz @ ry @ rx


def make_camera(image_size: int, offset_m: float = 0.0, offset_angle: float = 0.0) -> Camera:
    """The canonical camera, moved by ``offset_m`` in the plane facing the sheet."""
    centre = np.array(
        [offset_m * math.cos(offset_angle), offset_m * math.sin(offset_angle), canonical_distance()]
    )
    rotation = _WORLD_TO_CAMERA.copy()
    return Camera(
        K=intrinsics(image_size),
        R=rotation,
        t=-rotation @ centre,
        width=int(image_size),
        height=int(image_size),
    )


def build_scene(
    sheet_vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    texture: np.ndarray,
    *,
    image_size: int,
    roll: float = 0.0,
    pitch: float = 0.0,
    yaw: float = 0.0,
    offset_m: float = 0.0,
    offset_angle: float = 0.0,
    scale: float = 1.0,
    irradiance: float = 1.0,
) -> Scene3D:
    """A Scene3D from a sheet mesh in its own frame (``SheetMesh.vertices``) and θ's pose numbers."""
    rotation = pose_rotation(roll, pitch, yaw)
    vertices = scale * (np.asarray(sheet_vertices, np.float64) @ rotation.T)
    return Scene3D(
        vertices=vertices,
        faces=np.asarray(faces, np.int64),
        uv=np.asarray(uv, np.float64),
        texture=texture,
        camera=make_camera(image_size, offset_m, offset_angle),
        irradiance=float(irradiance),
        light_direction=LIGHT_DIRECTION.copy(),
        exposure=EXPOSURE,
    )
