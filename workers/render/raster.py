"""The fast backend: a z-buffered, texture-mapping rasteriser, Lambertian shading.

Three compiled passes (numba), each touching only the pixels it must:

1. Face-id buffer. For every triangle and every pixel row it crosses, the run of pixel
   centres inside it follows from its three edge functions (barycentric coordinates >= 0,
   pixel centres per scene.py, edges inclusive so shared edges leave no gaps); each pixel of
   the run keeps the nearest face (largest 1/z, which is affine on screen; the lower face
   index on an exact tie). The per-face planes come from one compiled pass over the faces.
2. Shading, over the covered pixels of the mask's bounding box: perspective-correct UVs of
   the pixel's face (u/z, v/z and 1/z are affine on screen), a bilinear fetch from the
   linear-light texture, times the face's Lambertian factor
   ``irradiance * exposure * max(0, n . l)``, with ``n`` the facet's normal turned towards
   the camera: both sides of the sheet show the texture, as Blender's single-sided plane
   does, and a side facing away from the light is black, as in Cycles.
3. Edge anti-aliasing (below).

A scene with more than the paper's one white light (``Scene3D.plain`` is false: coloured or
several lights, ambient light, a glossy layer, a normal map, a shadow caster) is shaded per
pixel instead of per face (``_shade_lit``): the pixel's world point from its depth, its normal
(the face's, tilted by the normal map in the face's tangent frame), each light's Lambertian
and GGX terms, the key light's visibility past the caster's coverage map. A plain scene never
runs it, so its bytes are those of the per-face shading.

The texture is sRGB-encoded; it is decoded to linear albedo first (a lookup table), and
downsampled in linear light (``INTER_AREA``, powers of two) to the level that matches the
sheet's footprint in the image, which keeps minified textures from aliasing.

Edges: ``mask`` is the exact pixel-centre coverage (what boxes are made of). ``alpha``
anti-aliases the silhouette for compositing: pixels along it get the share of 5 samples the
sheet covers (the centre and a rotated 4-sample grid), as Cycles' film alpha does for the
blender backend.

Triangles with a vertex closer than ``NEAR`` to the camera plane (or behind it) are dropped,
not clipped: a θ that brings the sheet that close is not part of Table 3's ranges.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import cv2
import numba
import numpy as np

from workers.render.annotation import tight_box
from workers.render.scene import BackendOutput, Camera, Scene3D

NEAR = 1e-3
_EDGE_EPS = 1e-9


def _srgb_decode_table() -> np.ndarray:
    c = np.arange(256, dtype=np.float64) / 255.0
    linear = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return linear.astype(np.float32)


SRGB_TO_LINEAR = _srgb_decode_table()


class _TexturePyramids:
    """Linear-light mip levels of the textures in use, only the levels asked for, keyed by
    array identity (a reference is kept, so an id cannot be reused while cached)."""

    def __init__(self, capacity: int = 32):
        self.capacity = capacity
        self._items: OrderedDict[int, tuple[np.ndarray, dict[int, np.ndarray]]] = OrderedDict()
        self._lock = threading.Lock()  # a threaded worker may render several scenes at once

    def level(self, texture: np.ndarray, footprint_px: float) -> np.ndarray:
        key = id(texture)
        with self._lock:
            item = self._items.get(key)
            if item is None or item[0] is not texture:
                item = (texture, {})
                self._items[key] = item
                if len(self._items) > self.capacity:
                    self._items.popitem(last=False)
            else:
                self._items.move_to_end(key)
        # The smallest power-of-two reduction still at least as large as the sheet's footprint.
        h, w = texture.shape[:2]
        index = 0
        while max(h, w) / 2.0 ** (index + 1) >= footprint_px and min(h, w) / 2.0 ** (index + 1) >= 4:
            index += 1
        levels = item[1]
        if index not in levels:
            linear = SRGB_TO_LINEAR[texture[:, :, :3]]
            if index:
                size = (-(-w // 2**index), -(-h // 2**index))
                linear = cv2.resize(linear, size, interpolation=cv2.INTER_AREA)
            levels[index] = linear
        return levels[index]


_PYRAMIDS = _TexturePyramids()


def _face_planes(pix: np.ndarray, depth: np.ndarray, faces: np.ndarray, uv: np.ndarray | None = None):
    """Per face, screen-space plane coefficients ``(a, b, c)`` (value = a*px + b*py + c) of the
    barycentrics w0, w1 and of 1/z, and (given ``uv``) of u/z and v/z, which are affine on
    screen too, so perspective-correct u = (u/z) / (1/z). Also the drawable faces (in front of
    NEAR, not degenerate on screen) and the screen coordinates of their corners.

    Returns (coverage (F, 9): w0, w1 and 1/z planes; texturing (F, 9): 1/z, u/z, v/z planes,
    None without ``uv``; usable (F,); x, y (F, 3), 0 for unusable faces)."""
    with_uv = uv is not None
    coverage, texturing, usable, x, y = _face_planes_kernel(
        np.ascontiguousarray(pix, np.float64),
        np.ascontiguousarray(depth, np.float64),
        np.ascontiguousarray(faces, np.int64),
        np.ascontiguousarray(uv, np.float64) if with_uv else np.zeros((0, 2)),
    )
    return coverage, texturing if with_uv else None, usable, x, y


@numba.njit(cache=True, nogil=True)
def _face_planes_kernel(pix, depth, faces, uv):  # pragma: no cover - compiled
    n = faces.shape[0]
    coverage = np.zeros((n, 9))
    texturing = np.zeros((n, 9))
    usable = np.zeros(n, np.bool_)
    x = np.zeros((n, 3))
    y = np.zeros((n, 3))
    values = np.zeros((3, 3))  # per corner: 1/z, u/z, v/z
    for f in range(n):
        ok = True
        for k in range(3):
            vertex = faces[f, k]
            if not (depth[vertex] > NEAR and np.isfinite(pix[vertex, 0]) and np.isfinite(pix[vertex, 1])):
                ok = False
        if not ok:
            continue
        for k in range(3):
            x[f, k] = pix[faces[f, k], 0]
            y[f, k] = pix[faces[f, k], 1]
        x0, x1, x2 = x[f, 0], x[f, 1], x[f, 2]
        y0, y1, y2 = y[f, 0], y[f, 1], y[f, 2]
        area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if not abs(area2) > 1e-10:
            x[f] = 0.0
            y[f] = 0.0
            continue
        usable[f] = True
        inv_area = 1.0 / area2
        # w0(p) = ((x1 - p.x)(y2 - p.y) - (x2 - p.x)(y1 - p.y)) / area2, expanded to a*px + b*py + c
        a0, b0, c0 = (y1 - y2) * inv_area, (x2 - x1) * inv_area, (x1 * y2 - x2 * y1) * inv_area
        a1, b1, c1 = (y2 - y0) * inv_area, (x0 - x2) * inv_area, (x2 * y0 - x0 * y2) * inv_area
        for k in range(3):
            vertex = faces[f, k]
            values[k, 0] = 1.0 / depth[vertex]
            if uv.shape[0]:
                values[k, 1] = uv[vertex, 0] * values[k, 0]
                values[k, 2] = uv[vertex, 1] * values[k, 0]
        # g = w0*g0 + w1*g1 + (1 - w0 - w1)*g2 for each interpolated quantity g.
        for q in range(3):
            d0, d1 = values[0, q] - values[2, q], values[1, q] - values[2, q]
            texturing[f, 3 * q] = d0 * a0 + d1 * a1
            texturing[f, 3 * q + 1] = d0 * b0 + d1 * b1
            texturing[f, 3 * q + 2] = d0 * c0 + d1 * c1 + values[2, q]
        coverage[f, 0], coverage[f, 1], coverage[f, 2] = a0, b0, c0
        coverage[f, 3], coverage[f, 4], coverage[f, 5] = a1, b1, c1
        coverage[f, 6], coverage[f, 7], coverage[f, 8] = texturing[f, 0], texturing[f, 1], texturing[f, 2]
    return coverage, texturing, usable, x, y


# -- compiled kernels --------------------------------------------------------------------------
# Per-pixel loops over a few thousand to a few hundred thousand pixels: compiled, they cost
# about what NumPy spends on one whole-array pass, and each pixel's work stops where it can.


@numba.njit(cache=True, nogil=True)
def _scan_faces(x, y, usable, coverage, width, height, z_test, ids, inverse_depth):  # pragma: no cover - compiled
    """Write into ``ids`` (H*W, -1 filled) the face covering each pixel centre; with ``z_test``
    the nearest one (largest 1/z; the lower face index on an exact tie), else the last drawn.
    Returns the covered pixels' bounding box (row0, row1, col0, col1), empty as (0, 0, 0, 0).

    Per face and pixel row, the three edge inequalities ``w_k(px, row centre) >= -eps`` are
    solved for px, which gives the run of covered pixel centres directly."""
    row0, row1, col0, col1 = height, -1, width, -1
    for face in range(x.shape[0]):
        if not usable[face]:
            continue
        x_min = min(x[face, 0], x[face, 1], x[face, 2])
        x_max = max(x[face, 0], x[face, 1], x[face, 2])
        first = math.ceil(min(y[face, 0], y[face, 1], y[face, 2]) - 0.5)
        last = math.floor(max(y[face, 0], y[face, 1], y[face, 2]) - 0.5)
        if last < first or last < 0 or first > height - 1 or x_max < 0.5 or x_min > width - 0.5:
            continue
        c = coverage[face]
        # Edge k: w_k = a_k px + b_k py + c_k >= -eps, with w2 = 1 - w0 - w1.
        a0, a1, a2 = c[0], c[3], -c[0] - c[3]
        for row in range(max(int(first), 0), min(int(last), height - 1) + 1):
            py = row + 0.5
            lo, hi = x_min, x_max
            empty = False
            for a_k, rhs_k in (
                (a0, -(c[1] * py + c[2]) - _EDGE_EPS),
                (a1, -(c[4] * py + c[5]) - _EDGE_EPS),
                (a2, -((1.0 - c[2] - c[5]) - (c[1] + c[4]) * py) - _EDGE_EPS),
            ):
                if a_k > 0:
                    lo = max(lo, rhs_k / a_k)
                elif a_k < 0:
                    hi = min(hi, rhs_k / a_k)
                elif rhs_k > 0:
                    empty = True
            if empty:
                continue
            start = max(math.ceil(lo - 0.5), 0.0)
            end = min(math.floor(hi - 0.5), width - 1.0)
            if end < start:
                continue
            start_col, end_col = int(start), int(end)
            base = row * width
            for col in range(start_col, end_col + 1):
                pixel = base + col
                if z_test:
                    nearness = c[6] * (col + 0.5) + c[7] * py + c[8]  # 1/z: larger is nearer
                    held = ids[pixel]
                    if held >= 0 and (
                        nearness < inverse_depth[pixel] or (nearness == inverse_depth[pixel] and face > held)
                    ):
                        continue
                    inverse_depth[pixel] = nearness
                ids[pixel] = face
            row0, row1 = min(row0, row), max(row1, row)
            col0, col1 = min(col0, start_col), max(col1, end_col)
    if row1 < 0:
        return 0, 0, 0, 0
    return row0, row1 + 1, col0, col1 + 1


@numba.njit(cache=True, nogil=True)
def _shade(face_image, box, texturing, radiance, texture, rgb):  # pragma: no cover - compiled
    """``rgb`` of every covered pixel in ``box``: the perspective-correct UV of its face
    (u/z, v/z and 1/z are affine on screen), a bilinear fetch from the linear-light
    ``texture`` (edge texels repeated outside it), times the face's radiance.

    Per run of pixels of one face, its planes are moved (in float64) to the run's row and
    scaled to texels; per pixel, float32 (a texel coordinate to ~1e-4 of a texel)."""
    th, tw = texture.shape[0], texture.shape[1]
    x_last, y_last = np.float32(tw - 1), np.float32(th - 1)
    zero, one, half = np.float32(0.0), np.float32(1.0), np.float32(0.5)
    row0, row1, col0, col1 = box
    for row in range(row0, row1):
        py = row + 0.5
        current = -1
        a_inverse = b_inverse = a_x = b_x = a_y = b_y = zero
        weight = zero
        for col in range(col0, col1):
            face = face_image[row, col]
            if face < 0:
                continue
            if face != current:
                current = face
                p = texturing[face]
                # At pixel centre (col + 0.5, py): value = a * col + b. Texel (r, c) sits at
                # u = (c + 0.5) / w, v = 1 - (r + 0.5) / h (scene.py): x = u w - 0.5, y = (1 - v) h - 0.5.
                a_inverse = np.float32(p[0])
                b_inverse = np.float32(p[0] * 0.5 + p[1] * py + p[2])
                a_x = np.float32(p[3] * tw)
                b_x = np.float32((p[3] * 0.5 + p[4] * py + p[5]) * tw)
                a_y = np.float32(p[6] * th)
                b_y = np.float32((p[6] * 0.5 + p[7] * py + p[8]) * th)
                weight = radiance[face]
            x = np.float32(col)
            depth = one / (a_inverse * x + b_inverse)
            tx = min(max((a_x * x + b_x) * depth - half, zero), x_last)
            ty = min(max(np.float32(th) - half - (a_y * x + b_y) * depth, zero), y_last)
            if not (tx == tx and ty == ty):  # NaN from a degenerate plane: the first texel
                tx = ty = zero
            x0, y0 = int(tx), int(ty)
            x1, y1 = min(x0 + 1, tw - 1), min(y0 + 1, th - 1)
            fx, fy = tx - np.float32(x0), ty - np.float32(y0)
            gx, gy = one - fx, one - fy
            w00, w01, w10, w11 = gx * gy * weight, fx * gy * weight, gx * fy * weight, fx * fy * weight
            for channel in range(3):
                rgb[row, col, channel] = (
                    texture[y0, x0, channel] * w00
                    + texture[y0, x1, channel] * w01
                    + texture[y1, x0, channel] * w10
                    + texture[y1, x1, channel] * w11
                )


# Edge anti-aliasing: a rotated 4-sample grid (x, y offsets from the pixel centre), plus the
# centre itself, whose coverage is the mask.
_AA_OFFSETS = np.array([[-0.125, -0.375], [0.375, -0.125], [0.125, 0.375], [-0.375, 0.125]])


@numba.njit(cache=True, nogil=True)
def _edge_alpha_kernel(face_image, mask, box, coverage, offsets, alpha, rgb):  # pragma: no cover - compiled
    """For each pixel whose 3x3 neighbourhood (in the image) holds both covered and uncovered
    centres (``mask``): alpha = covered share of its centre and the 4 ``offsets`` samples, testing the
    faces seen at its own and its 4 neighbours' centres; an uncovered pixel with some
    coverage takes the mean ``rgb`` of its covered 4-neighbours. ``box``: the covered
    pixels' bounding box."""
    height, width = face_image.shape
    row0, row1 = max(box[0] - 1, 0), min(box[1] + 1, height)
    col0, col1 = max(box[2] - 1, 0), min(box[3] + 1, width)
    # A 3x3 window is mixed iff it holds two 4-adjacent centres that differ (it is 4-connected):
    # mark, for each such pair, the pixels whose window holds both. Pairs lie along the
    # silhouette, so this costs one comparison pass plus work proportional to its length.
    band = np.zeros((row1 - row0, col1 - col0), np.bool_)
    for row in range(row0, row1):
        for col in range(col0, col1):
            covered = mask[row, col]
            if col + 1 < col1 and mask[row, col + 1] != covered:
                for r in range(max(row - 1, row0), min(row + 2, row1)):
                    band[r - row0, col - col0] = True
                    band[r - row0, col + 1 - col0] = True
            if row + 1 < row1 and mask[row + 1, col] != covered:
                for c in range(max(col - 1, col0), min(col + 2, col1)):
                    band[row - row0, c - col0] = True
                    band[row + 1 - row0, c - col0] = True
    candidates = np.empty(5, np.int64)
    for row in range(row0, row1):
        for col in range(col0, col1):
            if not band[row - row0, col - col0]:
                continue
            candidates[0] = face_image[row, col]
            candidates[1] = face_image[row - 1, col] if row > 0 else -1
            candidates[2] = face_image[row + 1, col] if row + 1 < height else -1
            candidates[3] = face_image[row, col - 1] if col > 0 else -1
            candidates[4] = face_image[row, col + 1] if col + 1 < width else -1
            inside = 0  # one bit per sample
            for k in range(5):
                face = candidates[k]
                if face < 0 or (k > 0 and face == candidates[0]):
                    continue
                for s in range(4):
                    sx = col + 0.5 + offsets[s, 0]
                    sy = row + 0.5 + offsets[s, 1]
                    w0 = coverage[face, 0] * sx + coverage[face, 1] * sy + coverage[face, 2]
                    w1 = coverage[face, 3] * sx + coverage[face, 4] * sy + coverage[face, 5]
                    if w0 >= -_EDGE_EPS and w1 >= -_EDGE_EPS and w0 + w1 <= 1.0 + _EDGE_EPS:
                        inside |= 1 << s
            centre = candidates[0] >= 0
            count = (inside & 1) + ((inside >> 1) & 1) + ((inside >> 2) & 1) + ((inside >> 3) & 1)
            count += 1 if centre else 0
            alpha[row, col] = count / 5.0
            if not centre and count > 0:  # no dark fringe: the covered neighbours' colour
                neighbours = 0
                red = green = blue = np.float32(0.0)
                for k in range(1, 5):
                    if candidates[k] >= 0:
                        r = row + (-1 if k == 1 else 1 if k == 2 else 0)
                        c = col + (-1 if k == 3 else 1 if k == 4 else 0)
                        red += rgb[r, c, 0]
                        green += rgb[r, c, 1]
                        blue += rgb[r, c, 2]
                        neighbours += 1
                rgb[row, col, 0] = red / neighbours
                rgb[row, col, 1] = green / neighbours
                rgb[row, col, 2] = blue / neighbours


def rasterize_face_ids(
    pix: np.ndarray,
    depth: np.ndarray,
    faces: np.ndarray,
    width: int,
    height: int,
    uv: np.ndarray | None = None,
    z_test: bool = True,
):
    """(height*width,) int32 index of the nearest face whose triangle covers each pixel centre
    (-1: none), the per-face texturing planes (None without ``uv``), coverage planes, and the
    covered pixels' bounding box (row0, row1, col0, col1; all 0 when nothing is covered).
    Without ``z_test`` the face of a covered pixel is any face covering it (for silhouettes)."""
    coverage, texturing, usable, x, y = _face_planes(pix, depth, faces, uv)
    ids = np.full(width * height, -1, dtype=np.int32)
    inverse_depth = np.empty(width * height if z_test else 0, dtype=np.float64)  # read only where ids >= 0
    box = _scan_faces(x, y, usable, coverage, int(width), int(height), bool(z_test), ids, inverse_depth)
    return ids, texturing, coverage, box


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the rasteriser's kernels for both ways the pipeline
    calls them: a textured render and a bare silhouette (part of pipeline.compile_kernels)."""
    camera = Camera(
        K=np.array([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]), R=np.eye(3), t=np.array([0.0, 0, 2]), width=8, height=8
    )
    vertices = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
    scene = Scene3D(
        vertices=vertices,
        faces=np.array([[0, 1, 2], [0, 2, 3]]),
        uv=(vertices[:, :2] + 0.5),
        texture=np.full((4, 4, 3), 128, np.uint8),
        camera=camera,
    )
    render_scene(scene)
    silhouette(scene)


def _footprint_px(pix: np.ndarray, depth: np.ndarray) -> float:
    ok = depth > NEAR
    if not ok.any():
        return 1.0
    extent = pix[ok].max(axis=0) - pix[ok].min(axis=0)
    return float(max(extent.max(), 1.0))


def render_scene(scene: Scene3D, antialias: bool = True) -> BackendOutput:
    """Render a Scene3D: linear RGB of the sheet (0 elsewhere), its pixel-centre mask, and
    alpha: the mask, with the coverage of silhouette pixels when ``antialias``."""
    camera = scene.camera
    width, height = int(camera.width), int(camera.height)
    faces = np.asarray(scene.faces, np.int64)
    pix, depth = camera.project(np.asarray(scene.vertices, np.float64))
    ids, texturing, coverage, box = rasterize_face_ids(
        pix, depth, faces, width, height, uv=np.asarray(scene.uv, np.float64)
    )
    face_image = ids.reshape(height, width)
    rgb = np.zeros((height, width, 3), np.float32)
    mask = np.zeros((height, width), bool)
    alpha = np.zeros((height, width), np.float32)
    if box[1] > box[0]:
        inside = (slice(box[0], box[1]), slice(box[2], box[3]))  # nothing is covered outside the box
        np.greater_equal(face_image[inside], 0, out=mask[inside])
        alpha[inside] = mask[inside]
        texture = _PYRAMIDS.level(scene.texture, _footprint_px(pix, depth))
        if scene.plain:
            _shade(face_image, box, texturing, _face_radiance(scene), texture, rgb)
        else:
            _shade_lit(face_image, box, texturing, texture, rgb, *_lighting_arguments(scene))
        if antialias:
            _edge_alpha_kernel(face_image, mask, box, coverage, _AA_OFFSETS, alpha, rgb)
    return BackendOutput(rgb=rgb, mask=mask, alpha=alpha)


def _face_radiance(scene: Scene3D) -> np.ndarray:
    """Per face: irradiance * exposure * max(0, n . l) (float32), n turned towards the camera."""
    light = np.asarray(scene.light_direction, np.float64)
    return _face_radiance_kernel(
        np.ascontiguousarray(scene.vertices, np.float64),
        np.ascontiguousarray(scene.faces, np.int64),
        -scene.camera.R.T @ scene.camera.t,
        light / max(float(np.linalg.norm(light)), 1e-300),
        float(scene.irradiance) * float(scene.exposure),
    )


@numba.njit(cache=True, nogil=True)
def _face_radiance_kernel(vertices, faces, camera_centre, light, scale):  # pragma: no cover - compiled
    radiance = np.zeros(faces.shape[0], np.float32)
    for f in range(faces.shape[0]):
        v0, v1, v2 = vertices[faces[f, 0]], vertices[faces[f, 1]], vertices[faces[f, 2]]
        e1 = v1 - v0
        e2 = v2 - v0
        nx = e1[1] * e2[2] - e1[2] * e2[1]
        ny = e1[2] * e2[0] - e1[0] * e2[2]
        nz = e1[0] * e2[1] - e1[1] * e2[0]
        norm = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
        towards_camera = (
            (camera_centre[0] - v0[0]) * nx + (camera_centre[1] - v0[1]) * ny + (camera_centre[2] - v0[2]) * nz
        )
        facing = 1.0 if towards_camera >= 0 else -1.0
        cosine = max(0.0, facing * (nx * light[0] + ny * light[1] + nz * light[2]) / norm)
        radiance[f] = scale * cosine
    return radiance


def face_frames(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, camera_centre: np.ndarray):
    """Per face: unit normal of the printed side (world), +1/-1 as the camera sees that side
    or the back, and the unit tangents along increasing u and v (the normal map's x and y)."""
    corners = vertices[faces]
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    normal = np.cross(e1, e2)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    facing = np.where(np.einsum("ij,ij->i", camera_centre - corners[:, 0], normal) >= 0, 1.0, -1.0)
    t = uv[faces]
    du1, dv1 = t[:, 1, 0] - t[:, 0, 0], t[:, 1, 1] - t[:, 0, 1]
    du2, dv2 = t[:, 2, 0] - t[:, 0, 0], t[:, 2, 1] - t[:, 0, 1]
    det = du1 * dv2 - du2 * dv1
    det = np.where(np.abs(det) > 1e-300, det, 1.0)
    tangent_u = (e1 * dv2[:, None] - e2 * dv1[:, None]) / det[:, None]
    tangent_v = (e2 * du1[:, None] - e1 * du2[:, None]) / det[:, None]
    tangent_u /= np.maximum(np.linalg.norm(tangent_u, axis=1, keepdims=True), 1e-300)
    tangent_v /= np.maximum(np.linalg.norm(tangent_v, axis=1, keepdims=True), 1e-300)
    return normal, facing, tangent_u, tangent_v


_NO_MAP = np.zeros((0, 0, 3), np.float32)
_NO_COVERAGE = np.zeros((0, 0), np.float32)


def _lighting_arguments(scene: Scene3D) -> tuple:
    """The per-pixel kernel's arguments for ``scene`` (see _shade_lit)."""
    camera = scene.camera
    vertices = np.asarray(scene.vertices, np.float64)
    faces = np.asarray(scene.faces, np.int64)
    centre = -camera.R.T @ camera.t
    normal, facing, tangent_u, tangent_v = face_frames(vertices, faces, np.asarray(scene.uv, np.float64), centre)
    lights = scene.light_list()
    directions = np.array([np.asarray(light.direction, np.float64) for light in lights]).reshape(-1, 3)
    directions /= np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-300)
    radiance = np.array(
        [np.asarray(light.colour, np.float64) * light.irradiance * scene.exposure for light in lights]
    ).reshape(-1, 3)
    normal_map = _NO_MAP if scene.normal_map is None else np.ascontiguousarray(scene.normal_map, np.float32)
    shadow = scene.shadow
    if shadow is None:
        caster = np.zeros((4, 3))
        coverage, extent = _NO_COVERAGE, np.zeros(4)
    else:
        u_axis, v_axis = np.asarray(shadow.u_axis, np.float64), np.asarray(shadow.v_axis, np.float64)
        caster = np.array([shadow.origin, u_axis, v_axis, np.cross(u_axis, v_axis)], np.float64)
        coverage = np.ascontiguousarray(shadow.coverage, np.float32)
        extent = np.asarray(shadow.extent, np.float64)
    return (
        np.ascontiguousarray(np.linalg.inv(camera.K)),
        np.ascontiguousarray(camera.R.T),
        np.asarray(camera.t, np.float64),
        centre,
        normal,
        facing,
        tangent_u,
        tangent_v,
        directions,
        radiance,
        np.asarray(scene.ambient, np.float64),
        float(scene.specular),
        float(scene.roughness) ** 4,  # α² with Cycles' α = roughness²
        normal_map,
        caster,
        coverage,
        extent,
    )


@numba.njit(cache=True, nogil=True)
def _bilinear(image, x, y, channel):  # pragma: no cover - compiled
    """``image[..., channel]`` at continuous texel (x, y) (texel centres at integers), edges repeated."""
    h, w = image.shape[0], image.shape[1]
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0, y0 = int(x), int(y)
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    top = image[y0, x0, channel] * (1 - fx) + image[y0, x1, channel] * fx
    bottom = image[y1, x0, channel] * (1 - fx) + image[y1, x1, channel] * fx
    return top * (1 - fy) + bottom * fy


@numba.njit(cache=True, nogil=True)
def _bilinear_plane(image, x, y):  # pragma: no cover - compiled
    """A 2D ``image`` at continuous texel (x, y), edges repeated."""
    h, w = image.shape[0], image.shape[1]
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0, y0 = int(x), int(y)
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


@numba.njit(cache=True, nogil=True)
def _ggx(nh, nl, nv, a2):  # pragma: no cover - compiled
    """π × the GGX BRDF (Smith masking, no Fresnel) times n·l: the glossy radiance per unit
    irradiance·exposure, as Cycles' Glossy BSDF lit by a sun of strength π E."""
    d = nh * nh * (a2 - 1.0) + 1.0
    distribution = a2 / (math.pi * d * d)
    g_l = 2.0 * nl / (nl + math.sqrt(a2 + (1.0 - a2) * nl * nl))
    g_v = 2.0 * nv / (nv + math.sqrt(a2 + (1.0 - a2) * nv * nv))
    return math.pi * distribution * g_l * g_v / (4.0 * nl * nv) * nl


@numba.njit(cache=True, nogil=True)
def _shade_lit(
    face_image,
    box,
    texturing,
    texture,
    rgb,
    k_inverse,
    r_transpose,
    t,
    centre,
    normal,
    facing,
    tangent_u,
    tangent_v,
    directions,
    radiance,
    ambient,
    specular,
    a2,
    normal_map,
    caster,
    coverage,
    extent,
):  # pragma: no cover - compiled
    """``rgb`` of every covered pixel in ``box`` under the full shading model of scene.py
    (several coloured lights, ambient, GGX gloss, normal map, the key light's shadow).

    Per pixel, in float64: perspective-correct texel position and depth (as _shade), the world
    point X = R^T (z K^-1 (x, y, 1) - t), the normal (the face's, tilted by the normal map in
    its tangent frame, turned towards the camera), then the lights."""
    th, tw = texture.shape[0], texture.shape[1]
    with_map = normal_map.shape[0] > 0
    with_shadow = coverage.shape[0] > 0
    n_lights = directions.shape[0]
    row0, row1, col0, col1 = box
    albedo = np.zeros(3)
    value = np.zeros(3)
    glossy = np.zeros(3)
    for row in range(row0, row1):
        py = row + 0.5
        for col in range(col0, col1):
            face = face_image[row, col]
            if face < 0:
                continue
            p = texturing[face]
            px = col + 0.5
            inverse_depth = p[0] * px + p[1] * py + p[2]
            depth = 1.0 / inverse_depth
            u = (p[3] * px + p[4] * py + p[5]) * depth
            v = (p[6] * px + p[7] * py + p[8]) * depth
            if not (u == u and v == v):
                u = v = 0.0
            tx = u * tw - 0.5
            ty = (1.0 - v) * th - 0.5
            for k in range(3):
                albedo[k] = _bilinear(texture, tx, ty, k)
            # The pixel's world point.
            cx = depth * (k_inverse[0, 0] * px + k_inverse[0, 1] * py + k_inverse[0, 2]) - t[0]
            cy = depth * (k_inverse[1, 0] * px + k_inverse[1, 1] * py + k_inverse[1, 2]) - t[1]
            cz = depth * (k_inverse[2, 0] * px + k_inverse[2, 1] * py + k_inverse[2, 2]) - t[2]
            wx = r_transpose[0, 0] * cx + r_transpose[0, 1] * cy + r_transpose[0, 2] * cz
            wy = r_transpose[1, 0] * cx + r_transpose[1, 1] * cy + r_transpose[1, 2] * cz
            wz = r_transpose[2, 0] * cx + r_transpose[2, 1] * cy + r_transpose[2, 2] * cz
            # The normal, turned towards the camera.
            nx, ny, nz = normal[face, 0], normal[face, 1], normal[face, 2]
            if with_map:
                mh, mw = normal_map.shape[0], normal_map.shape[1]
                mx = u * mw - 0.5
                my = (1.0 - v) * mh - 0.5
                a = _bilinear(normal_map, mx, my, 0)
                b = _bilinear(normal_map, mx, my, 1)
                c = _bilinear(normal_map, mx, my, 2)
                nx = a * tangent_u[face, 0] + b * tangent_v[face, 0] + c * normal[face, 0]
                ny = a * tangent_u[face, 1] + b * tangent_v[face, 1] + c * normal[face, 1]
                nz = a * tangent_u[face, 2] + b * tangent_v[face, 2] + c * normal[face, 2]
                norm = math.sqrt(nx * nx + ny * ny + nz * nz)
                nx, ny, nz = nx / norm, ny / norm, nz / norm
            sign = facing[face]
            nx, ny, nz = nx * sign, ny * sign, nz * sign
            vx, vy, vz = centre[0] - wx, centre[1] - wy, centre[2] - wz
            norm = math.sqrt(vx * vx + vy * vy + vz * vz)
            vx, vy, vz = vx / norm, vy / norm, vz / norm
            nv = nx * vx + ny * vy + nz * vz
            for k in range(3):
                value[k] = 0.0
                glossy[k] = 0.0
            for j in range(n_lights):
                lx, ly, lz = directions[j, 0], directions[j, 1], directions[j, 2]
                nl = nx * lx + ny * ly + nz * lz
                if nl <= 0.0:
                    continue
                visible = 1.0
                if j == 0 and with_shadow:
                    # Where the ray towards the light meets the caster's plane, if in front.
                    qx, qy, qz = caster[0, 0] - wx, caster[0, 1] - wy, caster[0, 2] - wz
                    along = lx * caster[3, 0] + ly * caster[3, 1] + lz * caster[3, 2]
                    if abs(along) > 1e-12:
                        s = (qx * caster[3, 0] + qy * caster[3, 1] + qz * caster[3, 2]) / along
                        if s > 0.0:
                            hx, hy, hz = (
                                wx + s * lx - caster[0, 0],
                                wy + s * ly - caster[0, 1],
                                wz + s * lz - caster[0, 2],
                            )
                            cu = hx * caster[1, 0] + hy * caster[1, 1] + hz * caster[1, 2]
                            cv = hx * caster[2, 0] + hy * caster[2, 1] + hz * caster[2, 2]
                            if extent[0] <= cu <= extent[1] and extent[2] <= cv <= extent[3]:
                                gx = (cu - extent[0]) / (extent[1] - extent[0]) * coverage.shape[1] - 0.5
                                gy = (cv - extent[2]) / (extent[3] - extent[2]) * coverage.shape[0] - 0.5
                                visible = 1.0 - _bilinear_plane(coverage, gx, gy)
                if visible <= 0.0:
                    continue
                for k in range(3):
                    value[k] += radiance[j, k] * nl * visible
                if specular > 0.0 and nv > 1e-6:
                    hx, hy, hz = lx + vx, ly + vy, lz + vz
                    norm = math.sqrt(hx * hx + hy * hy + hz * hz)
                    nh = max((nx * hx + ny * hy + nz * hz) / norm, 0.0)
                    term = _ggx(nh, nl, nv, a2) * visible
                    for k in range(3):
                        glossy[k] += radiance[j, k] * term
            for k in range(3):
                rgb[row, col, k] = (1.0 - specular) * albedo[k] * (value[k] + ambient[k]) + specular * (
                    glossy[k] + ambient[k]
                )


def silhouette(scene: Scene3D, camera: Camera | None = None) -> np.ndarray:
    """(H, W) bool mask of the sheet seen by ``camera`` (default: the scene's), geometry only."""
    camera = camera or scene.camera
    pix, depth = camera.project(np.asarray(scene.vertices, np.float64))
    faces = np.asarray(scene.faces, np.int64)
    ids, _, _, _ = rasterize_face_ids(pix, depth, faces, camera.width, camera.height, z_test=False)
    return (ids >= 0).reshape(camera.height, camera.width)


def amodal_extent(
    scene: Scene3D, image_mask: np.ndarray, max_canvas_factor: float = 16.0, max_canvas_pixels: int = 4_000_000
):
    """The sheet's whole silhouette, including what lies outside the image: (area in pixels,
    box [x0, y0, x1, y1] in image pixel-edge coordinates, or None when nothing projects).

    When the sheet's projection stays inside the image, that is ``image_mask`` itself. Otherwise
    the silhouette is rasterised again on a canvas grown to the projected bounding box, aligned
    to whole pixels so the in-image part is sampled at the same pixel centres. A canvas larger
    than ``max_canvas_factor`` times the image (or ``max_canvas_pixels``) is sampled at a
    coarser step (the area is then scaled back: an estimate good to the edge pixels of the
    coarse grid)."""
    camera = scene.camera
    width, height = camera.width, camera.height
    pix, depth = camera.project(np.asarray(scene.vertices, np.float64))
    front = depth > NEAR
    if not front.any():
        return 0.0, None
    lo = np.floor(pix[front].min(axis=0))
    hi = np.ceil(pix[front].max(axis=0))
    if lo[0] >= 0 and lo[1] >= 0 and hi[0] <= width and hi[1] <= height:
        return _mask_extent(image_mask, 0, 0, 1)
    x_lo, y_lo = int(min(lo[0], 0)), int(min(lo[1], 0))
    x_hi, y_hi = int(max(hi[0], width)), int(max(hi[1], height))
    canvas_w, canvas_h = x_hi - x_lo, y_hi - y_lo
    step = 1
    limit = min(max_canvas_factor * width * height, max_canvas_pixels)
    while (canvas_w / step) * (canvas_h / step) > limit:
        step *= 2
    K = camera.K.copy()
    K[0, 2] -= x_lo
    K[1, 2] -= y_lo
    if step > 1:
        K[:2, :] /= step
    grown = Camera(
        K=K, R=camera.R, t=camera.t, width=int(math.ceil(canvas_w / step)), height=int(math.ceil(canvas_h / step))
    )
    mask = silhouette(scene, grown)
    area, box = _mask_extent(mask, x_lo, y_lo, step)
    in_image = float(np.count_nonzero(image_mask))
    return max(area, in_image), box


def _mask_extent(mask: np.ndarray, x_offset: int, y_offset: int, step: int):
    box = tight_box(mask)
    if box is None:
        return 0.0, None
    return (
        float(cv2.countNonZero(mask.view(np.uint8))) * step * step,
        [x_offset + box[0] * step, y_offset + box[1] * step, x_offset + box[2] * step, y_offset + box[3] * step],
    )
