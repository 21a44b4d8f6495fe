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
* Orientation (the rest of Table 1): ``rotation`` turns the sheet about the optical axis by
  any angle, and ``tilt`` turns it out of the image plane about the image-plane axis at
  ``tilt_azimuth``; applied after the pose: ``R = Rz(rotation) @ R_tilt @ R_pose``.
* Lens: ``field_of_view_deg`` sets the focal length; the camera moves to the distance where
  the sheet keeps its canonical span, so a wide lens shows strong perspective from close by
  and a narrow one a nearly affine view from afar, at the same size. ``principal_shift``
  moves the principal point (a pure translation of the image): the field-of-view crop.
* Lighting: one distant light from the camera's side, a little above and to the left of
  the optical axis (``LIGHT_DIRECTION``, 23° off it), irradiance from θ, Lambertian sheet.
  ``exposure`` = 1 / cos(23°), so that a flat facet facing the canonical camera shows its
  texture unchanged at irradiance 1 (see scene.py), while bent or turned facets get brighter
  or darker: folds and pose show in the shading, as they would under a real lamp.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from workers.render.scene import Camera, Scene3D

FIELD_OF_VIEW = math.radians(40.0)
SHEET_LONG_SIDE_M = 3.0
CANONICAL_SPAN = 0.65
LIGHT_DIRECTION = np.array([-0.25, 0.35, 1.0]) / np.linalg.norm([-0.25, 0.35, 1.0])
EXPOSURE = 1.0 / float(LIGHT_DIRECTION[2])
# Camera frame = OpenCV (x right, y down, z forward); the canonical camera looks along -z.
_WORLD_TO_CAMERA = np.diag([1.0, -1.0, -1.0])


def intrinsics(
    image_size: int, field_of_view: float = FIELD_OF_VIEW, principal_shift: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """K of a square image: principal point at the image centre (pixel edges run 0..size),
    moved by ``principal_shift`` pixels."""
    focal = (image_size / 2.0) / math.tan(field_of_view / 2.0)
    cx, cy = image_size / 2.0 + principal_shift[0], image_size / 2.0 + principal_shift[1]
    return np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])


def canonical_distance(
    long_side: float = SHEET_LONG_SIDE_M, span: float = CANONICAL_SPAN, field_of_view: float = FIELD_OF_VIEW
) -> float:
    """Distance at which a fronto-parallel sheet's longer side spans ``span`` of the image."""
    return (long_side / 2.0) / (span * math.tan(field_of_view / 2.0))


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


def orientation_rotation(rotation: float, tilt: float, tilt_azimuth: float) -> np.ndarray:
    """Rz(rotation) @ R_tilt: a turn of ``rotation`` about the optical axis after a tilt of
    ``tilt`` about the image-plane axis at ``tilt_azimuth`` (counter-clockwise from image right)."""
    axis = np.array([math.cos(tilt_azimuth), math.sin(tilt_azimuth), 0.0])
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    tilted = np.eye(3) + math.sin(tilt) * k + (1.0 - math.cos(tilt)) * (k @ k)  # Rodrigues
    cr, sr = math.cos(rotation), math.sin(rotation)
    turn = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return turn @ tilted


def make_camera(
    image_size: int,
    offset_m: float = 0.0,
    offset_angle: float = 0.0,
    field_of_view: float = FIELD_OF_VIEW,
    principal_shift: tuple[float, float] = (0.0, 0.0),
) -> Camera:
    """The canonical camera (for ``field_of_view``), moved by ``offset_m`` in the plane facing the sheet."""
    centre = np.array(
        [
            offset_m * math.cos(offset_angle),
            offset_m * math.sin(offset_angle),
            canonical_distance(field_of_view=field_of_view),
        ]
    )
    rotation = _WORLD_TO_CAMERA.copy()
    return Camera(
        K=intrinsics(image_size, field_of_view, principal_shift),
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
    rotation: float = 0.0,
    tilt: float = 0.0,
    tilt_azimuth: float = 0.0,
    field_of_view: float = FIELD_OF_VIEW,
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0),
    camera: Camera | None = None,
) -> Scene3D:
    """A Scene3D from a sheet mesh in its own frame (``SheetMesh.vertices``) and θ's pose numbers.

    ``translation`` moves the posed sheet in the world (the layout of several sheets in one
    image); ``camera`` replaces the one θ's offset and lens make (all sheets of an image share one)."""
    vertices = scale * (
        np.asarray(sheet_vertices, np.float64) @ sheet_rotation(roll, pitch, yaw, rotation, tilt, tilt_azimuth).T
    )
    if any(translation):
        vertices = vertices + np.asarray(translation, np.float64)
    return Scene3D(
        vertices=vertices,
        faces=np.asarray(faces, np.int64),
        uv=np.asarray(uv, np.float64),
        texture=texture,
        camera=camera or make_camera(image_size, offset_m, offset_angle, field_of_view),
        irradiance=float(irradiance),
        light_direction=LIGHT_DIRECTION.copy(),
        exposure=EXPOSURE,
    )


def sheet_rotation(
    roll: float, pitch: float, yaw: float, rotation: float = 0.0, tilt: float = 0.0, tilt_azimuth: float = 0.0
) -> np.ndarray:
    """The sheet's whole orientation: ``orientation_rotation @ pose_rotation`` (the pose alone
    when rotation and tilt are 0, to the bit)."""
    pose = pose_rotation(roll, pitch, yaw)
    if rotation == 0.0 and tilt == 0.0:
        return pose
    return orientation_rotation(rotation, tilt, tilt_azimuth) @ pose


def with_principal_shift(scene: Scene3D, shift: tuple[float, float]) -> Scene3D:
    """``scene`` seen with its principal point moved by ``shift`` pixels (the image translated)."""
    camera = scene.camera
    K = camera.K.copy()
    K[0, 2] += shift[0]
    K[1, 2] += shift[1]
    return dataclasses.replace(scene, camera=dataclasses.replace(camera, K=K))


def frame_shift(scene: Scene3D, crop: float, angle: float, max_canvas_pixels: int = 1_000_000) -> tuple[float, float]:
    """The principal-point shift (pixels, towards ``angle`` counter-clockwise from image right)
    that pushes the share ``crop`` of the sheet's silhouette out of the frame; (0, 0) when at
    least that share is out already. Found by bisection on the silhouette, rasterised once on
    a canvas that holds the whole sheet and the frame around it, through an integral image."""
    from workers.render.raster import silhouette

    camera = scene.camera
    width, height = camera.width, camera.height
    pix, depth = camera.project(np.asarray(scene.vertices, np.float64))
    front = depth > 1e-3
    if crop <= 0 or not front.any():
        return (0.0, 0.0)
    lo = np.floor(np.minimum(pix[front].min(axis=0), 0.0)) - max(width, height)
    hi = np.ceil(np.maximum(pix[front].max(axis=0), (width, height))) + max(width, height)
    canvas_w, canvas_h = hi - lo
    step = 1
    while (canvas_w / step) * (canvas_h / step) > max_canvas_pixels:
        step *= 2
    K = camera.K.copy()
    K[0, 2] -= lo[0]
    K[1, 2] -= lo[1]
    K[:2, :] /= step
    grown = Camera(
        K=K, R=camera.R, t=camera.t, width=int(math.ceil(canvas_w / step)), height=int(math.ceil(canvas_h / step))
    )
    mask = silhouette(scene, grown)
    total = float(np.count_nonzero(mask))
    if total == 0:
        return (0.0, 0.0)
    integral = cv2.integral(mask.view(np.uint8))
    direction = np.array([math.cos(angle), -math.sin(angle)])  # image rows grow downwards

    def inside(distance: float) -> float:
        # The content moves by +d: the frame, on the canvas, by -d.
        x0 = (-lo[0] - distance * direction[0]) / step
        y0 = (-lo[1] - distance * direction[1]) / step
        c0, r0 = int(round(min(max(x0, 0), grown.width))), int(round(min(max(y0, 0), grown.height)))
        c1 = int(round(min(max(x0 + width / step, 0), grown.width)))
        r1 = int(round(min(max(y0 + height / step, 0), grown.height)))
        return float(integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]) / total

    want = 1.0 - crop
    if inside(0.0) <= want:
        return (0.0, 0.0)
    low, high = 0.0, float(max(canvas_w, canvas_h))
    for _ in range(40):
        middle = 0.5 * (low + high)
        if inside(middle) > want:
            low = middle
        else:
            high = middle
    distance = 0.5 * (low + high)
    return (float(distance * direction[0]), float(distance * direction[1]))
