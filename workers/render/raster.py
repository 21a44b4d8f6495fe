"""The fast backend: a z-buffered, texture-mapping rasteriser in NumPy/OpenCV, Lambertian shading.

Two vectorised passes, no Python loop over triangles:

1. Face-id buffer. For every triangle and every pixel row it crosses, the run of pixel
   centres inside it follows from its three edge functions (barycentric coordinates >= 0,
   pixel centres per scene.py, edges inclusive so shared edges leave no gaps); the runs are
   expanded to (face, pixel) candidates with ``np.repeat``; the z-test keeps, per pixel, the
   candidate of smallest depth with one ``np.minimum.at`` on a key that packs the quantised
   depth above the face index.
2. Shading. Densely over the mask's bounding box (image-shaped remap maps, no gather or
   scatter of pixel coordinates; pixels of the box off the sheet come out black):
   perspective-correct UVs of the winning face (u/z, v/z and 1/z are affine on screen,
   evaluated in float32 from planes moved to the box's corner), one ``cv2.remap``
   (bilinear) into the linear-light texture, times the face's
   Lambertian factor ``irradiance * exposure * max(0, n . l)``, with ``n`` the facet's normal
   turned towards the camera: both sides of the sheet show the texture, as Blender's
   single-sided plane does, and a side facing away from the light is black, as in Cycles.

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
import numpy as np

from workers.render.scene import BackendOutput, Camera, Scene3D

NEAR = 1e-3
_EDGE_EPS = 1e-9
_FACE_BITS = 23  # face index in the low bits of the z-test key: up to 8M faces
_DEPTH_LEVELS = float(2**38)
_EMPTY_KEY = np.iinfo(np.int64).max


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
    NEAR, not degenerate on screen) and the screen coordinates of their corners."""
    x = pix[faces, 0]
    y = pix[faces, 1]
    z = depth[faces]
    with np.errstate(invalid="ignore"):
        usable = np.all(z > NEAR, axis=1) & np.all(np.isfinite(x) & np.isfinite(y), axis=1)
    x = np.where(usable[:, None], x, 0.0)
    y = np.where(usable[:, None], y, 0.0)
    x0, x1, x2 = x[:, 0], x[:, 1], x[:, 2]
    y0, y1, y2 = y[:, 0], y[:, 1], y[:, 2]
    area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    usable &= np.abs(area2) > 1e-10
    inv_area = np.zeros_like(area2)
    inv_area[usable] = 1.0 / area2[usable]
    # w0(p) = ((x1 - p.x)(y2 - p.y) - (x2 - p.x)(y1 - p.y)) / area2, expanded to a*px + b*py + c
    a0, b0, c0 = (y1 - y2) * inv_area, (x2 - x1) * inv_area, (x1 * y2 - x2 * y1) * inv_area
    a1, b1, c1 = (y2 - y0) * inv_area, (x0 - x2) * inv_area, (x2 * y0 - x0 * y2) * inv_area

    iz = np.where(usable[:, None], 1.0 / np.where(usable[:, None], z, 1.0), 0.0)
    # Per corner, the quantities interpolated: 1/z, then (given uv) u/z and v/z; (faces, 3, k).
    values = iz[:, :, None]
    if uv is not None:
        values = np.concatenate([values, uv[faces] * values], axis=2)
    # f = w0*f0 + w1*f1 + (1 - w0 - w1)*f2, for all k at once: (faces, k, 3) planes (a, b, c).
    d0, d1 = values[:, 0] - values[:, 2], values[:, 1] - values[:, 2]
    planes = np.stack(
        [d0 * a0[:, None] + d1 * a1[:, None], d0 * b0[:, None] + d1 * b1[:, None],
         d0 * c0[:, None] + d1 * c1[:, None] + values[:, 2]],
        axis=2,
    ).reshape(len(faces), -1)
    coverage = np.concatenate([np.stack([a0, b0, c0, a1, b1, c1], axis=1), planes[:, :3]], axis=1)
    texturing = planes if uv is not None else None
    return coverage, texturing, usable, x, y


_SCRATCH = threading.local()


def _z_buffer(size: int) -> np.ndarray:
    """This thread's empty z-test buffer of at least ``size`` keys. Reused between calls (and
    emptied by resetting only the pixels touched): filling a fresh image-sized buffer every
    call costs more than the z-test itself."""
    buffer = getattr(_SCRATCH, "z_buffer", None)
    if buffer is None or buffer.size < size:
        buffer = np.full(size, _EMPTY_KEY, dtype=np.int64)
        _SCRATCH.z_buffer = buffer
    return buffer


def rasterize_face_ids(
    pix: np.ndarray,
    depth: np.ndarray,
    faces: np.ndarray,
    width: int,
    height: int,
    uv: np.ndarray | None = None,
    z_test: bool = True,
):
    """(height*width,) int64 index of the nearest face whose triangle covers each pixel centre
    (-1: none), the per-face texturing planes (None without ``uv``) and coverage planes.
    Without ``z_test`` the face of a covered pixel is any face covering it (for silhouettes).

    Scanline spans: for every face and every pixel row its bounding box crosses, the three
    edge inequalities ``w_k(px, row centre) >= -eps`` are solved for px, which gives the run of
    covered pixel centres directly, so only covered pixels are ever generated."""
    coverage, texturing, usable, x, y = _face_planes(pix, depth, faces, uv)
    ids = np.full(width * height, -1, dtype=np.int64)
    x_min, x_max = x.min(axis=1), x.max(axis=1)
    i0 = np.ceil(y.min(axis=1) - 0.5)
    i1 = np.floor(y.max(axis=1) - 0.5)
    usable &= (i1 >= i0) & (i1 >= 0) & (i0 <= height - 1) & (x_max >= 0.5) & (x_min <= width - 0.5)
    selected = np.flatnonzero(usable)
    if selected.size == 0:
        return ids, texturing, coverage
    i0 = np.clip(i0[selected], 0, height - 1).astype(np.int64)
    i1 = np.clip(i1[selected], 0, height - 1).astype(np.int64)
    rows_per_face = i1 - i0 + 1
    n_spans = int(rows_per_face.sum())
    span_face = np.repeat(selected, rows_per_face)
    row = np.repeat(i0, rows_per_face) + (
        np.arange(n_spans, dtype=np.int64) - np.repeat(np.cumsum(rows_per_face) - rows_per_face, rows_per_face)
    )
    py = row + 0.5
    c = coverage[span_face]
    # Edge k: w_k = a_k px + b_k py + c_k >= -eps, with w2 = 1 - w0 - w1.
    a = (c[:, 0], c[:, 3], -c[:, 0] - c[:, 3])
    rhs = (
        -(c[:, 1] * py + c[:, 2]) - _EDGE_EPS,
        -(c[:, 4] * py + c[:, 5]) - _EDGE_EPS,
        -((1.0 - c[:, 2] - c[:, 5]) - (c[:, 1] + c[:, 4]) * py) - _EDGE_EPS,
    )
    lo = x_min[span_face].copy()
    hi = x_max[span_face].copy()
    empty = np.zeros(n_spans, dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for a_k, rhs_k in zip(a, rhs):
            bound = rhs_k / a_k
            lo = np.where(a_k > 0, np.maximum(lo, bound), lo)
            hi = np.where(a_k < 0, np.minimum(hi, bound), hi)
            empty |= (a_k == 0) & (rhs_k > 0)
    col_start = np.maximum(np.ceil(lo - 0.5), 0)
    col_end = np.minimum(np.floor(hi - 0.5), width - 1)
    run = np.where(empty, 0, np.maximum(col_end - col_start + 1, 0)).astype(np.int64)
    keep = np.flatnonzero(run)
    if keep.size == 0:
        return ids, texturing, coverage
    run, col_start, row, span_face, c, py = run[keep], col_start[keep].astype(np.int64), row[keep], span_face[keep], c[keep], py[keep]
    total = int(run.sum())
    local = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(run) - run, run)
    pixel = np.repeat(row * width + col_start, run) + local
    face = np.repeat(span_face, run)
    ids[pixel] = face
    # Most views of a sheet cover every pixel centre once: then each pixel's only candidate
    # is its nearest, and the z-test below would change nothing.
    if not z_test or np.count_nonzero(ids >= 0) == total:
        return ids, texturing, coverage
    # 1/z along the run: its value at the first pixel centre plus a constant step per pixel.
    start_inverse_depth = c[:, 6] * (col_start + 0.5) + c[:, 7] * py + c[:, 8]
    inverse_depth = np.repeat(start_inverse_depth, run) + np.repeat(c[:, 6], run) * local
    # z-test: nearest = smallest depth. Quantise depth into the key's high bits, face in the low bits.
    depth_at = 1.0 / np.maximum(inverse_depth, 1e-300)
    lo_depth, hi_depth = float(depth_at.min()), float(depth_at.max())
    span = max(hi_depth - lo_depth, 1e-12)
    quantised = ((depth_at - lo_depth) * ((_DEPTH_LEVELS - 1) / span)).astype(np.int64)
    keys = (quantised << _FACE_BITS) | face
    buffer = _z_buffer(width * height)
    try:
        np.minimum.at(buffer, pixel, keys)
        ids[pixel] = buffer[pixel] & ((1 << _FACE_BITS) - 1)
    finally:
        buffer[pixel] = _EMPTY_KEY  # leave the scratch buffer empty for the next call
    return ids, texturing, coverage


_SHADE_CHUNK = 1 << 18  # pixels shaded at once: a sheet filling a large image needs no gigabytes
_REMAP_MAX = 32767  # cv2.remap wants maps under 32767 rows and columns


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
    if faces.shape[0] >= 2**_FACE_BITS:
        raise ValueError(f"render_scene: {faces.shape[0]} faces, at most {2**_FACE_BITS - 1} supported")
    pix, depth = camera.project(np.asarray(scene.vertices, np.float64))
    ids, texturing, coverage = rasterize_face_ids(pix, depth, faces, width, height, uv=np.asarray(scene.uv, np.float64))
    mask = (ids >= 0).reshape(height, width)
    rgb = np.zeros((height, width, 3), np.float32)
    c0, r0, box_w, box_h = cv2.boundingRect(mask.view(np.uint8))  # of the covered pixels
    r1, c1 = r0 + box_h, c0 + box_w
    if box_w and box_h:
        # Shade the mask's bounding box densely: image-shaped maps go straight into cv2.remap
        # and the result into the image, with no per-pixel gather or scatter of coordinates.
        # Pixels of the box off the sheet get radiance 0 (face -1 picks the appended 0).
        texture = _PYRAMIDS.level(scene.texture, _footprint_px(pix, depth))
        th, tw = texture.shape[:2]
        radiance = np.append(_face_radiance(scene), np.float32(0.0))
        # Face -1 (off the sheet) picks an appended row: 1/z = 1 and u/z = v/z = 0 there, so
        # its maps stay finite and inside the texture; its radiance is 0.
        off_sheet_planes = np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
        face_image = ids.reshape(height, width)
        columns = min(c1 - c0, _REMAP_MAX - 1)
        rows_per_chunk = max(1, min(_SHADE_CHUNK // columns, _REMAP_MAX - 1))
        for left in range(c0, c1, columns):
            right = min(left + columns, c1)
            px = np.arange(right - left, dtype=np.float32)
            for top in range(r0, r1, rows_per_chunk):
                bottom = min(top + rows_per_chunk, r1)
                face = face_image[top:bottom, left:right]
                py = np.arange(bottom - top, dtype=np.float32)[:, None]
                # The planes moved (in float64) to this chunk's first pixel centre, so float32
                # suffices: the remap maps are float32 anyway, and the small local coordinates
                # keep the terms from cancelling.
                planes = np.concatenate([texturing, off_sheet_planes]).reshape(-1, 3, 3)
                planes[:-1, :, 2] += planes[:-1, :, 0] * (left + 0.5) + planes[:-1, :, 1] * (top + 0.5)
                p = np.take(planes.reshape(-1, 9).astype(np.float32), face, axis=0)
                inverse_depth = p[..., 0] * px + p[..., 1] * py + p[..., 2]
                u = (p[..., 3] * px + p[..., 4] * py + p[..., 5]) / inverse_depth
                v = (p[..., 6] * px + p[..., 7] * py + p[..., 8]) / inverse_depth
                map_x = u * np.float32(tw) - np.float32(0.5)
                map_y = (np.float32(1.0) - v) * np.float32(th) - np.float32(0.5)
                albedo = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                rgb[top:bottom, left:right] = albedo * np.take(radiance, face)[..., None]
    if not antialias or not (box_w and box_h):
        return BackendOutput(rgb=rgb, mask=mask, alpha=mask.astype(np.float32))
    alpha = _edge_alpha(ids.reshape(height, width), coverage, mask, rgb, box=(r0, r1, c0, c1))
    return BackendOutput(rgb=rgb, mask=mask, alpha=alpha)


# Edge anti-aliasing: a rotated 4-sample grid (offsets from the pixel centre), plus the centre
# itself, whose coverage is the mask; candidate faces are those seen at the pixel's own centre
# and its 4 neighbours' centres.
_AA_OFFSETS = np.array([[-0.125, -0.375], [0.375, -0.125], [0.125, 0.375], [-0.375, 0.125]])
_NEIGHBOURS = np.array([(0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)])
_POPCOUNT4 = np.array([bin(value).count("1") for value in range(16)], dtype=np.uint8)


def _edge_alpha(
    ids: np.ndarray, coverage: np.ndarray, mask: np.ndarray, rgb: np.ndarray, box: tuple[int, int, int, int] | None = None
) -> np.ndarray:
    """Coverage of the pixels along the silhouette from 5 samples each; ``rgb`` of partly
    covered pixels outside the mask (left black by the rasteriser) becomes the mean of their
    covered neighbours, so compositing shows no dark fringe. Elsewhere alpha is the mask.
    ``box``: the mask's (row0, row1, col0, col1) bounding box when the caller knows it."""
    alpha = mask.astype(np.float32)
    height, width = mask.shape
    if box is None:
        mask_rows = np.flatnonzero(mask.any(axis=1))
        if mask_rows.size == 0:
            return alpha
        mask_cols = np.flatnonzero(mask.any(axis=0))
        box = (int(mask_rows[0]), int(mask_rows[-1]) + 1, int(mask_cols[0]), int(mask_cols[-1]) + 1)
    # Work in the mask's bounding box grown by one pixel (the band reaches one pixel out).
    r0, r1 = max(box[0] - 1, 0), min(box[1] + 1, height)
    c0, c1 = max(box[2] - 1, 0), min(box[3] + 1, width)
    local_u8 = np.ascontiguousarray(mask[r0:r1, c0:c1]).view(np.uint8)
    band = cv2.compare(cv2.dilate(local_u8, None), cv2.erode(local_u8, None, borderType=cv2.BORDER_REPLICATE), cv2.CMP_NE)
    # Band pixels in row-major order, as flat indices into the box padded by one pixel of -1.
    padded_width = c1 - c0 + 2
    points = cv2.findNonZero(band)  # (n, 1, 2) x, y in row-major order, like np.nonzero; None if empty
    points = np.zeros((0, 2), np.int64) if points is None else points.reshape(-1, 2).astype(np.int64)
    local_rows, local_cols = points[:, 1], points[:, 0]
    in_padded = (local_rows + 1) * padded_width + (local_cols + 1)
    rows, cols = local_rows + r0, local_cols + c0
    padded = np.full((r1 - r0 + 2, padded_width), -1, dtype=ids.dtype)
    padded[1:-1, 1:-1] = ids[r0:r1, c0:c1]
    steps = _NEIGHBOURS[:, 0] * padded_width + _NEIGHBOURS[:, 1]
    candidates = np.take(padded, in_padded[:, None] + steps)  # (n, 5) face ids, -1 for none
    # Test each distinct (pixel, face) pair once: neighbours mostly share the pixel's own face.
    fresh = candidates >= 0
    fresh[:, 1:] &= candidates[:, 1:] != candidates[:, :1]
    pair_pixel, pair_slot = np.nonzero(fresh)  # row-major: pairs grouped by pixel, in order
    pair_face = candidates[pair_pixel, pair_slot]
    p = coverage[pair_face, :6].astype(np.float32)
    sx = (cols[pair_pixel, None] + 0.5 + _AA_OFFSETS[None, :, 0]).astype(np.float32)  # (pairs, 4) samples
    sy = (rows[pair_pixel, None] + 0.5 + _AA_OFFSETS[None, :, 1]).astype(np.float32)
    w0 = p[:, 0:1] * sx + p[:, 1:2] * sy + p[:, 2:3]
    w1 = p[:, 3:4] * sx + p[:, 4:5] * sy + p[:, 5:6]
    inside = (w0 >= -_EDGE_EPS) & (w1 >= -_EDGE_EPS) & (w0 + w1 <= 1.0 + _EDGE_EPS)
    # One bit per sample, OR-ed over each pixel's pairs, then counted.
    bits = np.packbits(inside, axis=1, bitorder="little")[:, 0]  # bit k: sample k inside
    sample_bits = np.zeros(rows.size, np.uint8)
    if pair_pixel.size:
        starts = np.concatenate([[0], np.flatnonzero(pair_pixel[1:] != pair_pixel[:-1]) + 1])
        sample_bits[pair_pixel[starts]] = np.bitwise_or.reduceat(bits, starts)
    on_sheet = candidates >= 0  # the pixel itself and its 4 neighbours on the mask (never off-image)
    centre = on_sheet[:, 0]
    counts = _POPCOUNT4[sample_bits] + centre
    fraction = counts.astype(np.float32) / 5.0
    alpha[rows, cols] = fraction
    fringe = np.flatnonzero(~centre & (counts > 0))
    if fringe.size:
        weights = on_sheet[fringe].astype(np.float32)
        total = np.maximum(weights.sum(axis=1, keepdims=True), 1.0)
        flat_rgb = rgb.reshape(-1, 3)
        # Off-image neighbours have weight 0: any in-range index will do for them.
        image_steps = _NEIGHBOURS[:, 0] * width + _NEIGHBOURS[:, 1]
        neighbours = np.clip((rows[fringe] * width + cols[fringe])[:, None] + image_steps, 0, height * width - 1)
        neighbour_rgb = np.take(flat_rgb, neighbours, axis=0)  # (m, 5, 3)
        flat_rgb[rows[fringe] * width + cols[fringe]] = (neighbour_rgb * weights[:, :, None]).sum(axis=1) / total
    return alpha


def _face_radiance(scene: Scene3D) -> np.ndarray:
    """Per face: irradiance * exposure * max(0, n . l) (float32), n turned towards the camera."""
    vertices = np.asarray(scene.vertices, np.float64)
    faces = np.asarray(scene.faces, np.int64)
    v0 = vertices[faces[:, 0]]
    e1 = vertices[faces[:, 1]] - v0
    e2 = vertices[faces[:, 2]] - v0
    normals = np.stack(
        [
            e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1],
            e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
            e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0],
        ],
        axis=1,
    )
    norms = np.maximum(np.sqrt((normals * normals).sum(axis=1)), 1e-300)
    camera_centre = -scene.camera.R.T @ scene.camera.t
    facing = np.where(((camera_centre - v0) * normals).sum(axis=1) >= 0, 1.0, -1.0)
    light = np.asarray(scene.light_direction, np.float64)
    light = light / max(float(np.linalg.norm(light)), 1e-300)
    cosine = np.maximum(0.0, facing * (normals @ light) / norms)
    return (scene.irradiance * scene.exposure * cosine).astype(np.float32)


def silhouette(scene: Scene3D, camera: Camera | None = None) -> np.ndarray:
    """(H, W) bool mask of the sheet seen by ``camera`` (default: the scene's), geometry only."""
    camera = camera or scene.camera
    pix, depth = camera.project(np.asarray(scene.vertices, np.float64))
    faces = np.asarray(scene.faces, np.int64)
    ids, _, _ = rasterize_face_ids(pix, depth, faces, camera.width, camera.height, z_test=False)
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
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return 0.0, None
    cols = np.flatnonzero(mask.any(axis=0))
    box = [
        float(x_offset + cols[0] * step),
        float(y_offset + rows[0] * step),
        float(x_offset + (cols[-1] + 1) * step),
        float(y_offset + (rows[-1] + 1) * step),
    ]
    return float(np.count_nonzero(mask)) * step * step, box
