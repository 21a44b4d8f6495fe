"""The Blender (Cycles) backend: conventions, radiometry, determinism, persistence, and
agreement with the raster backend on the object mask."""

from __future__ import annotations

import importlib.util
import pickle
import shutil
import subprocess
import sys

import numpy as np
import pytest

from workers.render.scene import Camera, Scene3D

pytestmark = pytest.mark.blender

bpy = pytest.importorskip("bpy", reason="the blender backend needs bpy (pip install 'foldwise[render]')")

from workers.render.blender import (  # noqa: E402 - only importable with bpy
    BlenderError,
    camera_intrinsics,
    camera_matrix_world,
    get_renderer,
    render_scene,
)

WIDTH, HEIGHT = 96, 72
SAMPLES = 4


def srgb_to_linear(value: float) -> float:
    c = value / 255.0
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def rotation_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def make_camera(
    centre=(0.0, 0.0, 2.0),
    tilt=(0.0, 0.0, 0.0),
    focal=110.0,
    principal=(WIDTH / 2, HEIGHT / 2),
    size=(WIDTH, HEIGHT),
) -> Camera:
    """A camera above the z = 0 plane looking down −z (image up = world +y), then tilted."""
    looking_down = np.diag([1.0, -1.0, -1.0])  # OpenCV axes of a camera looking down −z, y up
    R = rotation_xyz(*tilt) @ looking_down
    t = -R @ np.asarray(centre, dtype=np.float64)
    K = np.array([[focal, 0.0, principal[0]], [0.0, focal, principal[1]], [0.0, 0.0, 1.0]])
    return Camera(K=K, R=R, t=t, width=size[0], height=size[1])


def grid_sheet(width=0.9, height=0.6, nx=1, ny=1):
    """A flat sheet at z = 0 centred on the origin, as (vertices, faces, uv), counter-clockwise."""
    u, v = np.meshgrid(np.linspace(0.0, 1.0, nx + 1), np.linspace(0.0, 1.0, ny + 1))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    vertices = np.stack([(uv[:, 0] - 0.5) * width, (uv[:, 1] - 0.5) * height, np.zeros(len(uv))], axis=1)
    index = np.arange(len(uv)).reshape(ny + 1, nx + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel(), index[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)
    return vertices, faces, uv


def uniform_texture(value: int, size=(8, 8)) -> np.ndarray:
    return np.full((*size, 3), value, dtype=np.uint8)


def flat_scene(camera=None, texture=None, grid=(1, 1), **kwargs) -> Scene3D:
    vertices, faces, uv = grid_sheet(nx=grid[0], ny=grid[1])
    return Scene3D(
        vertices=vertices,
        faces=faces,
        uv=uv,
        texture=uniform_texture(128) if texture is None else texture,
        camera=make_camera() if camera is None else camera,
        light_direction=kwargs.pop("light_direction", np.array([0.0, 0.0, 1.0])),
        **kwargs,
    )


def tight_box(mask: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    return np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=np.float64)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def interior(mask: np.ndarray, margin: int = 2) -> np.ndarray:
    """Mask pixels at least ``margin`` pixels from any uncovered pixel (no edge anti-aliasing)."""
    inside = mask.copy()
    for _ in range(margin):
        shrunk = inside.copy()
        shrunk[1:] &= inside[:-1]
        shrunk[:-1] &= inside[1:]
        shrunk[:, 1:] &= inside[:, :-1]
        shrunk[:, :-1] &= inside[:, 1:]
        inside = shrunk
    return inside


@pytest.fixture(scope="module")
def renderer():
    return get_renderer(samples=SAMPLES)


def test_get_renderer_keeps_one_renderer_per_process(renderer):
    again = get_renderer(samples=SAMPLES + 1)
    assert again is renderer
    assert renderer.samples == SAMPLES + 1
    get_renderer(samples=SAMPLES)
    assert len([s for s in bpy.data.scenes if s.name.startswith("foldwise")]) == 1
    # The module-level helper (raster.render_scene's call shape) renders with that same renderer.
    renders = renderer.stats["renders"]
    scene = flat_scene()
    assert render_scene(scene, samples=SAMPLES).rgb.tobytes() == renderer.render(scene).rgb.tobytes()
    assert renderer.stats["renders"] == renders + 2


def test_canonical_scene_gives_albedo_times_irradiance(renderer):
    out = renderer.render(flat_scene(texture=uniform_texture(128)))
    assert out.rgb.shape == (HEIGHT, WIDTH, 3) and out.rgb.dtype == np.float32
    assert out.alpha.shape == (HEIGHT, WIDTH) and out.mask.dtype == bool
    inside = interior(out.mask)
    assert inside.sum() > 1000
    # Linear colour = linearised sRGB albedo × irradiance 1 × cos 0 × exposure 1.
    np.testing.assert_allclose(out.rgb[inside], srgb_to_linear(128), rtol=1e-4)
    np.testing.assert_array_equal(out.alpha[inside], 1.0)
    assert np.all(out.rgb[out.alpha == 0] == 0) and np.all(out.alpha[~out.mask] <= 0.5)
    # Anti-aliased edge pixels carry the object's own colour (not premultiplied by coverage),
    # since compositing multiplies by alpha.
    edge = (out.alpha > 0.05) & (out.alpha < 0.95)
    assert edge.sum() > 20
    np.testing.assert_allclose(out.rgb[edge], srgb_to_linear(128), rtol=1e-4)


def test_oblique_light_and_exposure_scale_linearly(renderer):
    incidence = np.pi / 3  # cos = 0.5
    light = np.array([np.sin(incidence), 0.0, np.cos(incidence)])
    out = renderer.render(flat_scene(texture=uniform_texture(200), light_direction=light, exposure=2.0))
    inside = interior(out.mask)
    np.testing.assert_allclose(out.rgb[inside], srgb_to_linear(200) * 0.5 * 2.0, rtol=1e-4)


def test_no_shadows_follow_the_shading_model(renderer):
    # A small card floats above the sheet between it and an oblique light: the model (and
    # the raster backend) has no visibility term, so the sheet under it stays fully lit.
    sheet_vertices, sheet_faces, sheet_uv = grid_sheet()
    card_vertices, card_faces, card_uv = grid_sheet(width=0.2, height=0.2)
    card_vertices = card_vertices + [0.0, 0.0, 0.3]
    light = np.array([1.0, 0.0, 1.0])  # 45°: the card's shadow lands around x = -0.3 on the sheet
    scene = Scene3D(
        vertices=np.concatenate([sheet_vertices, card_vertices]),
        faces=np.concatenate([sheet_faces, card_faces + len(sheet_vertices)]),
        uv=np.concatenate([sheet_uv, card_uv]),
        texture=uniform_texture(128),
        camera=make_camera(),
        light_direction=light,
    )
    out = renderer.render(scene)
    shadow_spot, _ = scene.camera.project(np.array([[-0.3, 0.0, 0.0]]))
    column, row = np.floor(shadow_spot[0]).astype(int)
    np.testing.assert_allclose(
        out.rgb[row - 1 : row + 2, column - 1 : column + 2], srgb_to_linear(128) / np.sqrt(2), rtol=1e-4
    )


@pytest.mark.parametrize("irradiance", [0.01, 10.0])
def test_extreme_irradiance_gives_finite_scaled_output(renderer, irradiance):
    reference = renderer.render(flat_scene(irradiance=1.0))
    out = renderer.render(flat_scene(irradiance=irradiance))
    assert np.all(np.isfinite(out.rgb)) and np.all(out.rgb >= 0)
    np.testing.assert_array_equal(out.mask, reference.mask)  # light never changes coverage
    np.testing.assert_array_equal(out.alpha, reference.alpha)
    inside = interior(out.mask)
    np.testing.assert_allclose(out.rgb[inside], irradiance * reference.rgb[inside], rtol=1e-4)


def test_sheet_behind_the_camera_renders_nothing(renderer):
    # The camera 2 m above the sheet, turned to look up (+z): the sheet is behind it.
    looking_up = np.diag([1.0, 1.0, 1.0])
    camera = make_camera()
    away = Camera(K=camera.K, R=looking_up, t=-looking_up @ np.array([0.0, 0.0, 2.0]), width=WIDTH, height=HEIGHT)
    out = renderer.render(flat_scene(camera=away))
    assert not out.mask.any() and np.all(out.alpha == 0) and np.all(out.rgb == 0)


def test_dark_scene_keeps_its_mask(renderer):
    out = renderer.render(flat_scene(irradiance=0.0))
    assert np.all(out.rgb == 0)
    assert out.mask.sum() > 1000


def test_same_scene_renders_identical_bytes(renderer):
    texture = np.random.default_rng(3).integers(0, 256, size=(32, 24, 3), dtype=np.uint8)
    scene = flat_scene(texture=texture, camera=make_camera(tilt=(0.2, -0.1, 0.3)), grid=(3, 2))
    first = renderer.render(scene)
    renderer.render(flat_scene(irradiance=3.0, camera=make_camera(centre=(0.3, 0.1, 1.5))))
    second = renderer.render(scene)
    assert first.rgb.tobytes() == second.rgb.tobytes()
    assert first.alpha.tobytes() == second.alpha.tobytes()


def test_another_process_renders_the_same_bytes(renderer, tmp_path):
    # Render tasks may be redelivered to another worker process: the image must not change.
    texture = np.random.default_rng(5).integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    scene = flat_scene(texture=texture, camera=make_camera(tilt=(0.1, 0.2, -0.3)), grid=(2, 3), irradiance=0.8)
    with open(tmp_path / "scene.pkl", "wb") as file:
        pickle.dump(scene, file)
    child = (
        "import pickle, sys, numpy as np\n"
        "from workers.render.blender import get_renderer\n"
        "scene = pickle.load(open(sys.argv[1], 'rb'))\n"
        f"out = get_renderer(samples={SAMPLES}).render(scene)\n"
        "np.savez(sys.argv[2], rgb=out.rgb, alpha=out.alpha)\n"
    )
    subprocess.run(
        [sys.executable, "-c", child, str(tmp_path / "scene.pkl"), str(tmp_path / "out.npz")],
        check=True,
        capture_output=True,
        timeout=120,
    )
    other = np.load(tmp_path / "out.npz")
    here = renderer.render(scene)
    assert here.rgb.tobytes() == other["rgb"].tobytes()
    assert here.alpha.tobytes() == other["alpha"].tobytes()


@pytest.mark.parametrize(
    ("size", "principal", "focal", "tilt", "height_m"),
    [
        ((96, 80), (41.3, 39.7), 95.0, (-0.1, 0.08, 0.4), 1.8),  # landscape
        ((64, 96), (30.2, 50.6), 70.0, (-0.1, 0.08, 1.2), 2.2),  # portrait: shifts still in width units
    ],
)
def test_projected_corners_bound_the_rendered_mask(renderer, size, principal, focal, tilt, height_m):
    # Off-centre principal point, a non-square image and a tilted, shifted camera: every
    # convention (intrinsics, shifts in width units, R/t axes) shows in where the sheet lands.
    camera = make_camera(centre=(0.12, -0.08, height_m), tilt=tilt, focal=focal, principal=principal, size=size)
    scene = flat_scene(camera=camera)
    out = renderer.render(scene)
    corners, depth = camera.project(scene.vertices)
    assert np.all(depth > 0)
    assert np.all((corners > 1) & (corners < [camera.width - 1, camera.height - 1]))  # all edges in view
    # The sheet is convex: its mask is the polygon of the projected corners; the tight box
    # of pixel centres inside it lies within 1 px of the corners' extent.
    expected = np.array([corners[:, 0].min(), corners[:, 1].min(), corners[:, 0].max(), corners[:, 1].max()])
    np.testing.assert_allclose(tight_box(out.mask), expected, atol=1.0)


def test_texel_lands_where_the_camera_projects_it(renderer):
    # One bright texel: its rendered centroid must be the projection of its 3D point, which
    # checks UV orientation (v up, row 0 at the top) together with the camera.
    texture = np.zeros((6, 8, 3), dtype=np.uint8)
    row, col = 1, 6
    texture[row, col] = 255
    camera = make_camera(centre=(0.05, 0.02, 1.6), tilt=(0.1, 0.05, -0.2), principal=(50.0, 33.0))
    scene = flat_scene(camera=camera, texture=texture)
    out = renderer.render(scene)
    u, v = (col + 0.5) / texture.shape[1], 1.0 - (row + 0.5) / texture.shape[0]
    point = np.array([[(u - 0.5) * 0.9, (v - 0.5) * 0.6, 0.0]])  # grid_sheet's default 0.9 × 0.6 m
    expected, _ = camera.project(point)
    weight = out.rgb[..., 1].astype(np.float64)
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
    centroid = np.array([(weight * (cols + 0.5)).sum(), (weight * (rows + 0.5)).sum()]) / weight.sum()
    np.testing.assert_allclose(centroid, expected[0], atol=0.35)


def test_camera_conversion_round_trips_opencv_axes():
    camera = make_camera(centre=(0.3, -0.2, 1.5), tilt=(0.3, 0.2, -0.5))
    matrix = camera_matrix_world(camera.R, camera.t)
    # Blender's camera looks down its local −z with +y up; OpenCV's looks down +z with y down.
    np.testing.assert_allclose(matrix[:3, 3], -camera.R.T @ camera.t, atol=1e-12)
    np.testing.assert_allclose(matrix[:3, 2], -camera.R[2], atol=1e-12)
    np.testing.assert_allclose(matrix[:3, 1], -camera.R[1], atol=1e-12)
    settings = camera_intrinsics(camera.K, WIDTH, HEIGHT)
    assert settings["shift_x"] == 0.0 and settings["shift_y"] == 0.0
    assert settings["lens"] == pytest.approx(110.0 * 36.0 / WIDTH)


def test_light_change_touches_neither_mesh_nor_texture(renderer):
    scene = flat_scene(grid=(2, 2))
    renderer.render(scene)
    before = dict(renderer.stats)
    counts = (len(bpy.data.meshes), len(bpy.data.objects), len(bpy.data.images), len(bpy.data.materials))
    sheet, mesh_pointer = renderer.sheet_object, renderer.sheet_object.data.as_pointer()
    brighter = flat_scene(grid=(2, 2), irradiance=2.5, light_direction=np.array([0.2, 0.1, 1.0]))
    renderer.render(brighter)
    after = renderer.stats
    assert after["renders"] == before["renders"] + 1
    for key in ("topology_rebuilds", "geometry_updates", "texture_uploads"):
        assert after[key] == before[key], key
    assert renderer.sheet_object is sheet and sheet.data.as_pointer() == mesh_pointer
    assert counts == (len(bpy.data.meshes), len(bpy.data.objects), len(bpy.data.images), len(bpy.data.materials))


def test_topology_and_texture_changes_are_applied(renderer):
    coarse = renderer.render(flat_scene(texture=uniform_texture(60)))
    rebuilds = renderer.stats["topology_rebuilds"]
    fine = renderer.render(flat_scene(texture=uniform_texture(220), grid=(5, 4)))
    assert renderer.stats["topology_rebuilds"] == rebuilds + 1
    assert iou(coarse.mask, fine.mask) > 0.995  # same sheet, more triangles
    inside = interior(fine.mask)
    np.testing.assert_allclose(fine.rgb[inside], srgb_to_linear(220), rtol=1e-4)
    again = renderer.render(flat_scene(texture=uniform_texture(60)))
    assert again.rgb.tobytes() == coarse.rgb.tobytes()


def test_render_is_quiet(renderer, capfd):
    renderer.render(flat_scene(irradiance=0.7))
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def stretched_camera(camera: Camera) -> Camera:
    K = camera.K.copy()
    K[1, 1] *= 1.1
    return Camera(K=K, R=camera.R, t=camera.t, width=camera.width, height=camera.height)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda s: {"faces": s.faces + 100}, "faces index"),
        (lambda s: {"faces": s.faces.astype(np.float64)}, "integer"),
        (lambda s: {"vertices": np.where(np.arange(3) == 0, np.nan, s.vertices)}, "NaN"),
        (lambda s: {"uv": s.uv[:-1]}, "uv"),
        (lambda s: {"texture": s.texture.astype(np.float32)}, "uint8"),
        (lambda s: {"irradiance": -1.0}, "irradiance"),
        (lambda s: {"light_direction": np.zeros(3)}, "light_direction"),
        (lambda s: {"camera": stretched_camera(s.camera)}, "square pixels"),
    ],
)
def test_bad_scene_is_rejected_with_a_clear_error(renderer, change, message):
    scene = flat_scene()
    fields = {name: getattr(scene, name) for name in Scene3D.__dataclass_fields__}
    fields.update(change(scene))
    with pytest.raises(ValueError, match=message):
        renderer.render(Scene3D(**fields))


def test_bad_settings_are_rejected(renderer):
    with pytest.raises(ValueError, match="samples"):
        get_renderer(samples=0)
    with pytest.raises(ValueError, match="device"):
        get_renderer(samples=SAMPLES, device="TPU")
    assert renderer.samples == SAMPLES and renderer.device == "CPU"


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="this machine may have a GPU")
def test_gpu_without_a_gpu_is_a_clear_error(renderer):
    with pytest.raises(BlenderError, match="GPU"):
        get_renderer(samples=SAMPLES, device="GPU")
    assert renderer.device == "CPU"
    assert renderer.render(flat_scene()).mask.any()


# -- agreement with the raster backend ------------------------------------------------------

HAS_RASTER = importlib.util.find_spec("workers.render.raster") is not None
HAS_PAPER_MODEL = importlib.util.find_spec("workers.render.paper_model") is not None


def assert_backends_agree(renderer, scene: Scene3D) -> None:
    from workers.render.raster import render_scene  # noqa: PLC0415 - optional until it lands

    cycles = renderer.render(scene)
    raster = render_scene(scene)
    assert raster.mask.shape == cycles.mask.shape
    assert cycles.mask.sum() > 200
    assert iou(cycles.mask, raster.mask) >= 0.98
    np.testing.assert_allclose(tight_box(cycles.mask), tight_box(raster.mask), atol=1.0)
    return cycles, raster


@pytest.mark.skipif(not HAS_RASTER, reason="workers/render/raster.py has not landed yet")
def test_flat_quad_matches_raster_backend(renderer):
    scene = flat_scene(camera=make_camera(centre=(0.1, 0.05, 1.7), tilt=(0.3, -0.2, 0.5)), texture=uniform_texture(150))
    cycles, raster = assert_backends_agree(renderer, scene)
    both = interior(cycles.mask) & interior(raster.mask)
    # Same radiometry: a uniform albedo under the same light gives the same linear colour.
    np.testing.assert_allclose(cycles.rgb[both], raster.rgb[both], rtol=1e-3, atol=1e-4)


@pytest.mark.skipif(not (HAS_RASTER and HAS_PAPER_MODEL), reason="raster.py or paper_model.py has not landed yet")
def test_bent_sheet_matches_raster_backend(renderer):
    from workers.render.paper_model import sample_sheet  # noqa: PLC0415

    sheet = sample_sheet(3, np.random.default_rng(7), 0.9, 0.6)
    texture = np.random.default_rng(8).integers(0, 256, size=(24, 36, 3), dtype=np.uint8)
    scene = Scene3D(
        vertices=sheet.vertices,
        faces=sheet.faces,
        uv=sheet.uv,
        texture=texture,
        camera=make_camera(centre=(0.0, 0.0, 2.2), tilt=(0.15, 0.1, 0.0)),
        light_direction=np.array([0.0, 0.0, 1.0]),
    )
    assert_backends_agree(renderer, scene)


HAS_PIPELINE = importlib.util.find_spec("workers.render.pipeline") is not None


@pytest.mark.skipif(not HAS_PIPELINE, reason="workers/render/pipeline.py has not landed yet")
@pytest.mark.parametrize(
    ("condition", "difficulty"), [("de", "hard"), ("po", "medium"), ("eo", "hard"), ("eo", "medium")]
)
def test_render_theta_boxes_agree_between_backends(renderer, condition, difficulty):
    from foldwise.sampling import generate_parameters  # noqa: PLC0415
    from workers.render.pipeline import render_theta  # noqa: PLC0415

    theta = generate_parameters(condition, difficulty, 1, seed=4, image_size=64)[0]
    # Occluders are placed on the geometric silhouette, so both backends hide the same pixels.
    cycles = render_theta(theta, backend="blender", samples=SAMPLES)
    raster = render_theta(theta, backend="raster")
    assert cycles.image.shape == raster.image.shape == (64, 64, 3)
    np.testing.assert_allclose(cycles.box, raster.box, atol=1.0)
    # Same texture, light and background: the images differ by anti-aliasing and filtering only.
    assert np.abs(cycles.image.astype(np.int16) - raster.image.astype(np.int16)).mean() < 4.0


@pytest.mark.skipif(not HAS_PIPELINE, reason="workers/render/pipeline.py has not landed yet")
# Mean |effect difference| / mean |effect| allowed: the wrinkles' relief is finer than a
# pixel's filter footprint, which Cycles' 1.5 px filter blurs and the raster kernel does not
# (measured: 0.31-0.34 for wr, 0.03-0.11 for the others over seeds 5-7).
@pytest.mark.parametrize(("condition", "tolerance"), [("lc", 0.15), ("sh", 0.15), ("sp", 0.15), ("wr", 0.45)])
def test_lights_shadows_gloss_and_wrinkles_match_the_raster_backend(renderer, condition, tolerance):
    """The rest of the shading model (coloured lights and ambient, the caster's shadow, GGX
    gloss, the wrinkles' normal map) is rendered by Cycles, not dropped. Each backend's effect
    is its image minus the same θ with the condition's parameters at their canonical values
    (which cancels the backends' different texture filtering); on the sheet's interior the
    two effects agree (a backend that ignored the effect would show none)."""
    from foldwise.conditions import load_condition_table  # noqa: PLC0415
    from foldwise.sampling import generate_parameters  # noqa: PLC0415
    from workers.render.pipeline import render_theta  # noqa: PLC0415

    table = load_condition_table()
    theta = generate_parameters(condition, "hard", 1, seed=5, image_size=64)[0]
    parameters = {
        name
        for variant in table.conditions[condition].variants.values()
        for level in variant.values()
        for name in level
    }
    plain = theta.replace(**{name: table.canonical[name] for name in parameters})
    renderer.configure(samples=64)
    try:
        cycles = [render_theta(t, backend="blender", samples=64) for t in (theta, plain)]
    finally:
        renderer.configure(samples=SAMPLES)
    raster = [render_theta(t, backend="raster") for t in (theta, plain)]
    both = interior(cycles[0].mask) & interior(raster[0].mask) & interior(cycles[1].mask) & interior(raster[1].mask)
    assert both.sum() > 300
    effect_cycles = (cycles[0].image.astype(np.float64) - cycles[1].image)[both].ravel()
    effect_raster = (raster[0].image.astype(np.float64) - raster[1].image)[both].ravel()
    assert np.abs(effect_raster).mean() > 4.0  # the condition does something at hard
    assert np.corrcoef(effect_cycles, effect_raster)[0, 1] > 0.9
    assert np.abs(effect_cycles - effect_raster).mean() < tolerance * np.abs(effect_raster).mean()


@pytest.mark.skipif(not HAS_PIPELINE, reason="workers/render/pipeline.py has not landed yet")
def test_a_lookalike_lies_beside_the_target_in_cycles_as_in_the_raster_backend(renderer):
    """``assets.lookalikes`` on the Blender backend: the lookalike sheet is rendered by Cycles
    where the raster backend puts it, behind the target, whose box it leaves as it was."""
    from foldwise.sampling import generate_parameters  # noqa: PLC0415
    from tests.workers.render.lookalike_helpers import MAGENTA, catalog, changed, sheet  # noqa: PLC0415
    from workers.render.pipeline import render_theta  # noqa: PLC0415

    lookalikes = catalog({"other-form": sheet(MAGENTA)})
    theta = generate_parameters("po", "canonical", 1, seed=1, image_size=64)[0]
    shown = {}
    for backend in ("blender", "raster"):
        plain = render_theta(theta, backend=backend, samples=SAMPLES)
        result = render_theta(theta, backend=backend, assets=lookalikes, samples=SAMPLES)
        np.testing.assert_allclose(result.box, plain.box, atol=1e-6)
        shown[backend] = changed(result.image, plain.image) & ~np.any(result.masks, axis=0)
    assert shown["raster"].sum() >= 20
    overlap = (shown["blender"] & shown["raster"]).sum() / (shown["blender"] | shown["raster"]).sum()
    assert overlap >= 0.7
