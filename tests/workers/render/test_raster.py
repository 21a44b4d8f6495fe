"""The rasteriser against geometry computed by hand: coverage at pixel centres, texture
orientation, perspective-correct texturing, z-test, Lambertian shading, off-image extent."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from workers.render.camera import EXPOSURE, LIGHT_DIRECTION, build_scene, canonical_distance, intrinsics
from workers.render.raster import SRGB_TO_LINEAR, amodal_extent, render_scene, silhouette

SIZE = 64
WIDTH_M, HEIGHT_M = 3.0, 2.0


def quad(width=WIDTH_M, height=HEIGHT_M, z=0.0, uv_box=(0.0, 0.0, 1.0, 1.0)):
    """A flat two-triangle rectangle centred on the origin at depth z, counter-clockwise."""
    w, h = width / 2, height / 2
    vertices = np.array([[-w, -h, z], [w, -h, z], [w, h, z], [-w, h, z]], float)
    u0, v0, u1, v1 = uv_box
    uv = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return vertices, faces, uv


def quadrant_texture():
    """Top-left red, top-right green, bottom-left blue, bottom-right white (8x8)."""
    texture = np.zeros((8, 8, 3), np.uint8)
    texture[:4, :4] = (255, 0, 0)
    texture[:4, 4:] = (0, 255, 0)
    texture[4:, :4] = (0, 0, 255)
    texture[4:, 4:] = (255, 255, 255)
    return texture


def flat_scene(texture=None, size=SIZE, **pose):
    vertices, faces, uv = quad()
    texture = quadrant_texture() if texture is None else texture
    return build_scene(vertices, faces, uv, texture, image_size=size, **pose)


def expected_rectangle_mask(size, width_m, height_m, distance):
    """Pixels whose centre falls inside the projected fronto-parallel rectangle."""
    focal = intrinsics(size)[0, 0]
    half_w = focal * width_m / 2 / distance
    half_h = focal * height_m / 2 / distance
    centres = np.arange(size) + 0.5
    inside_x = np.abs(centres - size / 2) <= half_w
    inside_y = np.abs(centres - size / 2) <= half_h
    return inside_y[:, None] & inside_x[None, :]


def test_coverage_is_exactly_the_pixel_centres_inside_the_projected_sheet():
    output = render_scene(flat_scene())
    expected = expected_rectangle_mask(SIZE, WIDTH_M, HEIGHT_M, canonical_distance())
    assert np.array_equal(output.mask, expected)
    assert np.array_equal(render_scene(flat_scene(), antialias=False).alpha, expected.astype(np.float32))
    # The canonical framing: the longer side spans 65% of the image.
    columns = np.flatnonzero(output.mask.any(axis=0))
    assert abs((columns[-1] + 1 - columns[0]) - 0.65 * SIZE) <= 1.0


def test_antialiased_alpha_measures_edge_coverage():
    scene = flat_scene(roll=0.2)  # slanted edges
    output = render_scene(scene)
    mask, alpha = output.mask, output.alpha
    inner = cv2.erode(mask.astype(np.uint8), None).astype(bool)
    near = cv2.dilate(mask.astype(np.uint8), None).astype(bool)
    assert (alpha[inner] == 1).all() and (alpha[~near] == 0).all()
    assert ((alpha > 0) & (alpha < 1)).sum() > 50  # a soft edge all around
    assert (alpha[mask] > 0).all() and alpha.min() >= 0 and alpha.max() <= 1
    focal = intrinsics(SIZE)[0, 0]
    true_area = (focal / canonical_distance()) ** 2 * WIDTH_M * HEIGHT_M
    assert abs(alpha.sum() - true_area) < 0.01 * true_area
    # Partly covered pixels outside the mask take their covered neighbours' colour, not black.
    fringe = (alpha > 0) & ~mask
    assert fringe.any() and (output.rgb[fringe].sum(axis=1) > 0.1).all()


def test_texture_is_upright_unmirrored_and_unchanged_on_a_front_facing_sheet():
    output = render_scene(flat_scene())
    rows = np.flatnonzero(output.mask.any(axis=1))
    cols = np.flatnonzero(output.mask.any(axis=0))
    top, bottom = rows[0] + 2, rows[-1] - 2
    left, right = cols[0] + 2, cols[-1] - 2
    red, green, blue, white = (
        output.rgb[top, left],
        output.rgb[top, right],
        output.rgb[bottom, left],
        output.rgb[bottom, right],
    )
    # Exposure makes a facet facing the canonical camera show the linear albedo exactly.
    np.testing.assert_allclose(red, [1, 0, 0], atol=1e-5)
    np.testing.assert_allclose(green, [0, 1, 0], atol=1e-5)
    np.testing.assert_allclose(blue, [0, 0, 1], atol=1e-5)
    np.testing.assert_allclose(white, [1, 1, 1], atol=1e-5)
    assert not output.rgb[~output.mask].any()


def test_srgb_texture_is_decoded_to_linear_albedo():
    texture = np.full((4, 4, 3), 128, np.uint8)
    output = render_scene(flat_scene(texture))
    centre = output.rgb[SIZE // 2, SIZE // 2]
    np.testing.assert_allclose(centre, SRGB_TO_LINEAR[128], rtol=1e-5)
    assert 0.21 < SRGB_TO_LINEAR[128] < 0.22  # linear value of sRGB 128


def test_lambertian_shading_scales_with_irradiance_and_cosine():
    texture = np.full((4, 4, 3), 255, np.uint8)
    base = render_scene(flat_scene(texture)).rgb[SIZE // 2, SIZE // 2, 0]
    dim = render_scene(flat_scene(texture, irradiance=0.01)).rgb[SIZE // 2, SIZE // 2, 0]
    bright = render_scene(flat_scene(texture, irradiance=10.0)).rgb[SIZE // 2, SIZE // 2, 0]
    assert base == pytest.approx(1.0, abs=1e-6)
    assert dim == pytest.approx(0.01, rel=1e-5)
    assert bright == pytest.approx(10.0, rel=1e-5)  # unclipped: clipping is the pipeline's job
    yaw = 0.6
    turned = render_scene(flat_scene(texture, yaw=yaw)).rgb[SIZE // 2, SIZE // 2, 0]
    normal = np.array([math.sin(yaw), 0.0, math.cos(yaw)])
    assert turned == pytest.approx(EXPOSURE * float(normal @ LIGHT_DIRECTION), rel=1e-5)


def test_texturing_is_perspective_correct():
    # Top half red, bottom half blue: under a strong pitch the boundary (v = 0.5, the sheet's
    # centre line) must land where the 3D centre projects, the image centre row. Affine
    # interpolation in screen space would move it by several pixels.
    texture = np.zeros((2, 2, 3), np.uint8)
    texture[0] = (255, 0, 0)
    texture[1] = (0, 0, 255)
    size = 128
    output = render_scene(flat_scene(texture, size=size, pitch=1.2, scale=2.5))
    column = output.rgb[:, size // 2]
    covered = output.mask[:, size // 2]
    red_rows = np.flatnonzero(covered & (column[:, 0] > column[:, 2]))
    blue_rows = np.flatnonzero(covered & (column[:, 2] > column[:, 0]))
    boundary = (red_rows.max() + 1 + blue_rows.min()) / 2
    assert abs(boundary - size / 2) <= 1.0
    # ... and the projection is really foreshortened asymmetrically (the test means something).
    assert abs((size / 2 - red_rows.min()) - (blue_rows.max() + 1 - size / 2)) >= 4


def test_nearest_surface_wins_whatever_the_face_order():
    texture = np.zeros((1, 2, 3), np.uint8)
    texture[0, 0] = (255, 0, 0)  # left half of the texture: red
    texture[0, 1] = (0, 0, 255)  # right half: blue
    back_v, back_f, back_uv = quad(z=0.0, uv_box=(0.0, 0.0, 0.5, 1.0))
    front_v, front_f, front_uv = quad(width=1.0, height=1.0, z=0.5, uv_box=(0.5, 0.0, 1.0, 1.0))
    for first, second in (
        ((back_v, back_f, back_uv), (front_v, front_f, front_uv)),
        ((front_v, front_f, front_uv), (back_v, back_f, back_uv)),
    ):
        vertices = np.vstack([first[0], second[0]])
        faces = np.vstack([first[1], second[1] + 4])
        uv = np.vstack([first[2], second[2]])
        output = render_scene(build_scene(vertices, faces, uv, texture, image_size=SIZE))
        centre = output.rgb[SIZE // 2, SIZE // 2]
        assert centre[2] > 0.5 and centre[0] < 0.01, "the nearer (blue) quad must hide the red one"
        corner_rows = np.flatnonzero(output.mask.any(axis=1))
        assert output.rgb[corner_rows[0] + 1, SIZE // 2 - 18, 0] > 0.5, "the far quad shows around the near one"


def test_edge_on_sheet_covers_nothing_and_does_not_fail():
    output = render_scene(flat_scene(yaw=math.pi / 2))
    assert not output.mask.any()
    assert np.isfinite(output.rgb).all()


def test_triangles_behind_the_camera_are_dropped():
    vertices, faces, uv = quad()
    vertices = vertices.copy()
    vertices[1, 2] = canonical_distance() + 1.0  # a corner of the first triangle only, behind the camera
    output = render_scene(build_scene(vertices, faces, uv, quadrant_texture(), image_size=SIZE))
    assert np.isfinite(output.rgb).all()
    assert output.mask.any()  # the triangle not touching that corner still renders


def test_amodal_extent_counts_the_part_outside_the_image():
    scene = flat_scene(scale=3.0)
    output = render_scene(scene)
    area, box = amodal_extent(scene, output.mask)
    focal = intrinsics(SIZE)[0, 0]
    expected_w = 3.0 * focal * WIDTH_M / canonical_distance()
    expected_h = 3.0 * focal * HEIGHT_M / canonical_distance()
    assert area == pytest.approx(expected_w * expected_h, rel=0.03)
    assert box[0] < 0 and box[2] > SIZE  # wider than the image
    assert box[2] - box[0] == pytest.approx(expected_w, abs=1.0)
    assert output.mask.sum() < area
    # A canvas too large for the budget is sampled coarser: still a close estimate.
    coarse_area, coarse_box = amodal_extent(scene, output.mask, max_canvas_pixels=3000)
    assert coarse_area == pytest.approx(expected_w * expected_h, rel=0.06)
    assert coarse_box[2] - coarse_box[0] == pytest.approx(expected_w, abs=8.0)


def test_amodal_extent_inside_the_image_is_the_mask_itself():
    scene = flat_scene()
    output = render_scene(scene)
    area, box = amodal_extent(scene, output.mask)
    assert area == output.mask.sum()
    rows = np.flatnonzero(output.mask.any(axis=1))
    cols = np.flatnonzero(output.mask.any(axis=0))
    assert box == [cols[0], rows[0], cols[-1] + 1, rows[-1] + 1]


def test_silhouette_matches_the_render_mask():
    scene = flat_scene(roll=0.3, pitch=0.4, yaw=-0.5)
    assert np.array_equal(silhouette(scene), render_scene(scene).mask)


def brute_force_face_ids(scene):
    """Reference: for every pixel centre and every triangle, barycentric inside test and
    perspective-correct depth; the nearest covering triangle wins (O(pixels x faces))."""
    camera = scene.camera
    pix, depth = camera.project(scene.vertices)
    h, w = camera.height, camera.width
    py, px = np.mgrid[0:h, 0:w] + 0.5
    best_depth = np.full((h, w), np.inf)
    best_face = np.full((h, w), -1)
    for index, (i, j, k) in enumerate(scene.faces):
        (x0, y0), (x1, y1), (x2, y2) = pix[i], pix[j], pix[k]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-10:
            continue
        w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
        w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
        w2 = 1 - w0 - w1
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        z = 1 / (w0 / depth[i] + w1 / depth[j] + w2 / depth[k])
        nearer = inside & (z < best_depth)
        best_depth[nearer] = z[nearer]
        best_face[nearer] = index
    return best_face


def test_coverage_and_z_test_match_a_brute_force_reference_on_a_folded_sheet():
    # A sheet folded over itself (a 150-degree fold seen obliquely): many slanted triangles,
    # with the folded flap hiding part of the base.
    rng = np.random.default_rng(3)
    n = 6
    xs, ys = np.meshgrid(np.linspace(-1.5, 1.5, n + 1), np.linspace(-1.0, 1.0, n + 1))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    flap = vertices[:, 0] > 0.25
    angle = math.radians(150)
    dx = vertices[flap, 0] - 0.25
    vertices[flap, 0] = 0.25 + dx * math.cos(angle)
    vertices[flap, 2] = dx * math.sin(angle)
    vertices += rng.normal(0, 0.01, vertices.shape) * [1, 1, 0]
    faces = []
    for r in range(n):
        for q in range(n):
            a = r * (n + 1) + q
            faces += [[a, a + 1, a + n + 2], [a, a + n + 2, a + n + 1]]
    uv = (vertices[:, :2] - vertices[:, :2].min(axis=0)) / np.ptp(vertices[:, :2], axis=0)
    scene = build_scene(vertices, np.array(faces), uv, quadrant_texture(), image_size=48, yaw=0.5, pitch=-0.3)
    from workers.render.raster import rasterize_face_ids

    pix, depth = scene.camera.project(scene.vertices)
    ids, _, _, _ = rasterize_face_ids(pix, depth, scene.faces, 48, 48)
    reference = brute_force_face_ids(scene)
    assert (reference >= 0).sum() > 300
    assert np.array_equal((ids >= 0).reshape(48, 48), reference >= 0)
    differ = ids.reshape(48, 48) != reference
    # Where they differ, both faces must be at the same depth (a shared edge): compare depths.
    assert differ.sum() <= 0.01 * (reference >= 0).sum()


def test_minified_texture_is_filtered_not_aliased():
    # A 1-texel checkerboard of 512x512 on a sheet about 40 pixels wide: sampling the full-size
    # texture would return a random-looking mix of black and white texels; the mip level
    # matching the footprint returns their average (linear 0.5).
    checks = (np.indices((512, 512)).sum(axis=0) % 2 * 255).astype(np.uint8)
    texture = np.repeat(checks[:, :, None], 3, axis=2)
    output = render_scene(flat_scene(texture))
    inner = cv2.erode(output.mask.astype(np.uint8), None, iterations=2).astype(bool)
    values = output.rgb[inner, 0]
    assert values.mean() == pytest.approx(0.5, abs=0.02)
    assert values.std() < 0.02


def test_a_sheet_filling_most_of_a_large_image_is_shaded_everywhere():
    output = render_scene(flat_scene(size=256, scale=1.6, texture=np.full((4, 4, 3), 255, np.uint8)))
    assert output.mask.sum() > 40_000
    np.testing.assert_allclose(output.rgb[output.mask], 1.0, atol=1e-5)


def ray_cast_reference(scene, rows, cols):
    """Linear colour at pixel centres by casting each pixel's ray onto the triangles (float64):
    the nearest hit's barycentric UV, a bilinear fetch (edge texels repeated), the facet's
    Lambertian factor. Independent of the rasteriser's screen-space planes."""
    from workers.render.raster import _face_radiance

    camera = scene.camera
    texture = SRGB_TO_LINEAR[scene.texture].astype(np.float64)
    th, tw = texture.shape[:2]
    centre = -camera.R.T @ camera.t
    pixels = np.stack([cols + 0.5, rows + 0.5, np.ones(rows.size)], axis=1)
    directions = (camera.R.T @ np.linalg.solve(camera.K, pixels.T)).T
    best_t = np.full(rows.size, np.inf)
    uv = np.zeros((rows.size, 2))
    radiance = np.zeros(rows.size)
    face_radiance = _face_radiance(scene)
    for index, (i, j, k) in enumerate(scene.faces):
        a, b, c = scene.vertices[i], scene.vertices[j], scene.vertices[k]
        e1, e2 = b - a, c - a
        p = np.cross(directions, e2)
        det = p @ e1
        with np.errstate(divide="ignore", invalid="ignore"):
            s = centre - a
            u = (p @ s) / det
            q = np.cross(s, e1)
            v = (directions * q).sum(axis=1) / det
            t = (q @ e2) / det
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < best_t)
        best_t[hit] = t[hit]
        uv[hit] = ((1 - u - v)[:, None] * scene.uv[i] + u[:, None] * scene.uv[j] + v[:, None] * scene.uv[k])[hit]
        radiance[hit] = face_radiance[index]
    tx = np.clip(uv[:, 0] * tw - 0.5, 0, tw - 1)
    ty = np.clip((1 - uv[:, 1]) * th - 0.5, 0, th - 1)
    x0, y0 = np.floor(tx).astype(int), np.floor(ty).astype(int)
    x1, y1 = np.minimum(x0 + 1, tw - 1), np.minimum(y0 + 1, th - 1)
    fx, fy = (tx - x0)[:, None], (ty - y0)[:, None]
    top = texture[y0, x0] * (1 - fx) + texture[y0, x1] * fx
    bottom = texture[y1, x0] * (1 - fx) + texture[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy) * radiance[:, None], np.isfinite(best_t)


@pytest.mark.parametrize(
    "pose", [dict(roll=0.3, pitch=0.2, yaw=0.4), dict(pitch=1.3, scale=2.0), dict(yaw=-1.1, roll=2.0)]
)
def test_shading_matches_a_ray_cast_reference_on_a_bent_sheet(pose):
    texture = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    # Two triangles not in one plane, each textured with its own perspective: a crude bend.
    vertices = np.array([[-1.5, -1.0, 0.0], [1.5, -1.0, 0.3], [1.5, 1.0, 0.0], [-1.5, 1.0, -0.3]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    scene = build_scene(vertices, faces, uv, texture, image_size=96, **pose)
    output = render_scene(scene)
    inner = output.mask & (output.alpha == 1)  # edge pixels mix in the anti-aliased fringe
    rows, cols = np.nonzero(inner)
    assert rows.size > 200
    expected, hit = ray_cast_reference(scene, rows, cols)
    assert hit.all()
    # The mip level is the full texture here (the sheet spans more pixels than it has texels).
    difference = np.abs(output.rgb[rows, cols] - expected)
    assert difference.max() < 1e-4
    assert not output.rgb[~output.mask & (output.alpha == 0)].any()  # off the sheet stays black


def test_renders_do_not_leak_into_each_other_through_reused_buffers():
    first = render_scene(flat_scene(size=48, yaw=0.3))
    render_scene(flat_scene(size=96, scale=2.0))  # a larger image, covering everything
    render_scene(flat_scene(size=32, roll=1.0))
    again = render_scene(flat_scene(size=48, yaw=0.3))
    assert np.array_equal(first.mask, again.mask)
    assert np.array_equal(first.rgb, again.rgb) and np.array_equal(first.alpha, again.alpha)


@pytest.mark.parametrize("angle, dx, dy", [(0.0, -1, 0), (math.pi / 2, 0, 1), (math.pi, 1, 0)])
def test_position_offset_moves_the_camera_in_the_plane_facing_the_sheet(angle, dx, dy):
    size = 128
    base = render_scene(flat_scene(size=size)).mask
    moved = render_scene(flat_scene(size=size, offset_m=0.5, offset_angle=angle)).mask
    shift_px = intrinsics(size)[0, 0] * 0.5 / canonical_distance()
    (y0, x0), (y1, x1) = (np.argwhere(m).mean(axis=0) for m in (base, moved))
    # The camera moves right (angle 0) or up (pi/2): the sheet slides left or down in the image.
    assert x1 - x0 == pytest.approx(dx * shift_px, abs=0.6)
    assert y1 - y0 == pytest.approx(dy * shift_px, abs=0.6)
    assert moved.sum() == pytest.approx(base.sum(), rel=0.03)  # same depth: same size


def test_scale_multiplies_the_sheet_and_roll_turns_it_about_the_optical_axis():
    size = 128

    def extent(mask):
        rows = np.flatnonzero(mask.any(axis=1))
        cols = np.flatnonzero(mask.any(axis=0))
        return cols[-1] + 1 - cols[0], rows[-1] + 1 - rows[0]

    width, height = extent(render_scene(flat_scene(size=size)).mask)
    half_w, half_h = extent(render_scene(flat_scene(size=size, scale=0.5)).mask)
    assert half_w == pytest.approx(width / 2, abs=1) and half_h == pytest.approx(height / 2, abs=1)
    rolled_w, rolled_h = extent(render_scene(flat_scene(size=size, roll=math.pi / 2)).mask)
    assert (rolled_w, rolled_h) == pytest.approx((height, width), abs=1)
