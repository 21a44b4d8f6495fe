"""The Blender backend: Cycles renders the :class:`~workers.render.scene.Scene3D` contract.

One bpy scene lives per worker process (:func:`get_renderer`). It is built once: a camera,
a sun, one mesh object and one material (image texture → diffuse BSDF). Each
:meth:`BlenderRenderer.render` call updates only what the scene changes: vertex positions
(or the whole topology when it differs), the texture pixels, camera intrinsics and pose,
and the sun's strength and direction. Factory settings are never reloaded.

Conventions match ``scene.py`` and the raster backend:

* Camera: ``K`` gives the focal length in mm for a 36 mm wide sensor fitted horizontally,
  the principal point gives ``shift_x``/``shift_y`` (both in units of the image width, as
  Blender measures shift along the fitted side). OpenCV ``R, t`` (x right, y down, z
  forward) become Blender's camera frame (x right, y up, looking down −z) by flipping y, z.
* Radiometry: Cycles' diffuse BSDF returns ``albedo / π × E cos θ``, so a sun's strength is
  ``π × irradiance × exposure`` and the linear value is ``albedo × irradiance × cos θ ×
  exposure``, the model ``scene.py`` documents. Direct light only (no bounces). The paper's
  scene (``Scene3D.plain``) is one white sun of zero angular size casting no shadows and no
  world light. The rest of the model maps one to one: each of ``Scene3D.lights`` is a sun of
  its colour; ``ambient`` is a uniform world of that radiance; ``specular`` mixes a white GGX
  glossy BSDF (roughness as given: α = roughness², the raster kernel's a2 = roughness⁴) into
  the diffuse one; ``normal_map`` feeds a tangent-space Normal Map node on the UVs;
  ``shadow`` is a mesh of the caster's polygon, invisible to every ray but shadow rays, and
  only the key light (light 0) casts shadows, through a sun of the caster's angular size (the
  sheet itself casts none, as in the raster model). Both sides of the sheet show the texture;
  a side faces the light or stays black (the raster backend lights both sides by ``|n · l|``;
  they differ only on facets seen from one side and lit from the other, which a light along
  the optical axis never makes visible).
* Output: the render is written as a 32-bit float OpenEXR (no view transform reaches float
  files) and read back. ``alpha`` is the film coverage (transparent film, Cycles' 1.5 px
  Blackman-Harris pixel filter), ``mask`` is ``alpha > 0.5`` and ``rgb`` the object's linear
  colour: Cycles' premultiplied value divided by alpha, 0 where nothing is covered, so that
  compositing is ``colour × alpha + background × (1 − alpha)`` as for the raster backend.
* Determinism: fixed seed, no animated seed, no adaptive sampling, no denoiser: the same
  scene renders to the same bytes, in this process or another.
* Speed (measured at 256², 16 samples): nearly all the time is path tracing, linear in the
  samples; sync and the EXR round trip cost a few tens of ms. Shadow rays cost ~25% and
  changed no pixel of the pipeline's images (off); adaptive sampling at 16 samples changed no
  pixel either (its convergence checks start too late; off); the light tree is off (one
  light); persistent data is off (Cycles then misses edits to the texture pixels, and a
  resync is cheap); one tile per image; as many threads as the process may use.
"""

from __future__ import annotations

import atexit
import contextlib
import math
import os
import shutil
import sys
import tempfile
import threading
from collections.abc import Iterator

import numpy as np

from workers.render.scene import BackendOutput, Camera, Scene3D

# Blender's sensor width is arbitrary (only lens / sensor matters); 36 mm is its default.
SENSOR_WIDTH_MM = 36.0
DEVICES = ("CPU", "GPU")
# GPU back-ends to try, best first, when device="GPU" is asked for.
GPU_BACKENDS = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")

_NAME = "foldwise"  # prefix of every datablock this module owns


class BlenderError(RuntimeError):
    """Blender could not render (no bpy, no GPU when one was asked for, a failed render)."""


def _import_bpy():
    try:
        import bpy  # noqa: PLC0415 - heavy and optional: only the blender backend needs it
    except ImportError as error:  # pragma: no cover - depends on the install
        raise BlenderError(
            "the blender backend needs the bpy module (pip install 'foldwise[render]'): " + str(error)
        ) from error
    return bpy


def _allowed_threads() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def _quiet_fds() -> Iterator[list[str]]:
    """Silence Blender's C-level stdout/stderr (render progress, "Saved:" lines) for one call.

    Yields a list that holds what was printed once the block ends, so a failure can show it.
    """
    captured: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    with tempfile.TemporaryFile(mode="w+b") as sink:
        saved = [os.dup(1), os.dup(2)]
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            yield captured
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            captured.append(sink.read().decode("utf-8", errors="replace"))


def _validate_scene(scene: Scene3D) -> None:
    vertices = np.asarray(scene.vertices)
    faces = np.asarray(scene.faces)
    uv = np.asarray(scene.uv)
    texture = np.asarray(scene.texture)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
        raise ValueError(f"Scene3D.vertices must be (V>=3, 3), got shape {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("Scene3D.vertices contains NaN or infinite coordinates")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 1:
        raise ValueError(f"Scene3D.faces must be (F>=1, 3), got shape {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"Scene3D.faces must hold integer vertex indices, got dtype {faces.dtype}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(
            f"Scene3D.faces index vertices outside [0, {len(vertices) - 1}] (min {faces.min()}, max {faces.max()})"
        )
    if uv.shape != (len(vertices), 2) or not np.all(np.isfinite(uv)):
        raise ValueError(f"Scene3D.uv must be finite and (V, 2) = ({len(vertices)}, 2), got shape {uv.shape}")
    if texture.ndim != 3 or texture.shape[2] != 3 or texture.dtype != np.uint8 or texture.size == 0:
        raise ValueError(
            f"Scene3D.texture must be a non-empty (h, w, 3) uint8 RGB image, got {texture.shape} {texture.dtype}"
        )
    for name in ("irradiance", "exposure"):
        value = float(getattr(scene, name))
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"Scene3D.{name} must be finite and >= 0, got {value}")
    direction = np.asarray(scene.light_direction, dtype=np.float64)
    if direction.shape != (3,) or not np.all(np.isfinite(direction)) or np.linalg.norm(direction) == 0:
        raise ValueError(f"Scene3D.light_direction must be a finite non-zero 3-vector, got {direction!r}")
    _validate_camera(scene.camera)


def _validate_camera(camera: Camera) -> None:
    K = np.asarray(camera.K, dtype=np.float64)
    R = np.asarray(camera.R, dtype=np.float64)
    t = np.asarray(camera.t, dtype=np.float64)
    if int(camera.width) < 1 or int(camera.height) < 1:
        raise ValueError(f"Camera size must be positive, got {camera.width}x{camera.height}")
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"Camera K, R must be 3x3 and t a 3-vector, got {K.shape}, {R.shape}, {t.shape}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError("Camera K, R, t must be finite")
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0:
        raise ValueError(f"Camera focal lengths must be positive, got fx={fx}, fy={fy}")
    if abs(fx - fy) > 1e-9 * fx:
        raise ValueError(f"the blender backend renders square pixels only: fx={fx} != fy={fy}")
    if abs(K[0, 1]) > 1e-9 * fx or np.any(np.abs(K[2] - (0.0, 0.0, 1.0)) > 1e-12):
        raise ValueError(f"Camera K must be [[f, 0, cx], [0, f, cy], [0, 0, 1]] (no skew), got {K.tolist()}")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError("Camera R must be a rotation matrix (orthonormal, det +1)")


def camera_matrix_world(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Blender camera ``matrix_world`` (4×4) for OpenCV extrinsics ``X_cam = R X_world + t``.

    The camera centre is ``-Rᵀ t``; Blender's camera axes are OpenCV's with y and z flipped
    (y up, looking down −z).
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    matrix = np.eye(4)
    matrix[:3, :3] = R.T @ np.diag([1.0, -1.0, -1.0])
    matrix[:3, 3] = -R.T @ t
    return matrix


def camera_intrinsics(K: np.ndarray, width: int, height: int) -> dict[str, float]:
    """Blender camera data settings (lens in mm, shifts) reproducing ``K`` on a width×height image.

    With ``sensor_fit = 'HORIZONTAL'`` Blender measures both shifts in units of the image
    width; its image y runs up, OpenCV's v runs down.
    """
    K = np.asarray(K, dtype=np.float64)
    return {
        "sensor_width": SENSOR_WIDTH_MM,
        "lens": float(K[0, 0] * SENSOR_WIDTH_MM / width),
        "shift_x": float((width / 2.0 - K[0, 2]) / width),
        "shift_y": float((K[1, 2] - height / 2.0) / width),
    }


class BlenderRenderer:
    """Cycles renderer holding one persistent bpy scene; see the module docstring."""

    def __init__(self, samples: int = 16, device: str = "CPU", seed: int = 0) -> None:
        self._bpy = _import_bpy()
        self._lock = threading.Lock()  # bpy is not thread-safe: one render at a time
        self._tmpdir = tempfile.mkdtemp(prefix="foldwise-blender-")
        self._output_path = os.path.join(self._tmpdir, "render.exr")
        self._topology: tuple[int, bytes] | None = None  # (vertex count, faces bytes) now in the mesh
        self._geometry: tuple[bytes, bytes] | None = None  # (vertex, corner uv bytes) now in the mesh
        self._texture_key: tuple[tuple[int, ...], bytes] | None = None
        # What each render had to update: lets callers (and tests) see that only θ's
        # changes reach Blender.
        self.stats = {"renders": 0, "topology_rebuilds": 0, "geometry_updates": 0, "texture_uploads": 0}
        self._result_image = None
        self._build_scene(seed)
        self.configure(samples=samples, device=device)

    # -- public -------------------------------------------------------------------------

    @property
    def scene(self):
        """The bpy scene this renderer owns (for inspection; do not edit)."""
        return self._scene

    @property
    def sheet_object(self):
        """The one mesh object holding the sheet."""
        return self._sheet

    @property
    def samples(self) -> int:
        return int(self._scene.cycles.samples)

    @property
    def device(self) -> str:
        return str(self._scene.cycles.device)

    def configure(self, samples: int | None = None, device: str | None = None) -> None:
        """Change Cycles samples per pixel and/or the device ("CPU" or "GPU")."""
        if samples is not None:
            if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
                raise ValueError(f"samples must be a positive integer, got {samples!r}")
            self._scene.cycles.samples = int(samples)
        if device is not None:
            if device not in DEVICES:
                raise ValueError(f"device must be one of {DEVICES}, got {device!r}")
            if device == "GPU" and self._scene.cycles.device != "GPU":  # device discovery is slow: once
                self._enable_gpu()
            self._scene.cycles.device = device

    def render(self, scene: Scene3D) -> BackendOutput:
        """Render ``scene``: the sheet's linear RGB (not premultiplied), its mask and alpha."""
        _validate_scene(scene)
        with self._lock:
            self._update_mesh(scene)
            self._update_texture(np.asarray(scene.texture))
            self._update_camera(scene.camera, np.asarray(scene.vertices, dtype=np.float64))
            self._update_light(scene)
            self._update_material(scene)
            rgba = self._render_rgba()
            self.stats["renders"] += 1
        alpha = np.ascontiguousarray(np.clip(rgba[..., 3], 0.0, 1.0), dtype=np.float32)
        # Cycles stores colour premultiplied by coverage; the contract (and the compositing
        # stage, ``colour × alpha + background × (1 − alpha)``) wants the object's own colour.
        rgb = np.zeros(rgba.shape[:2] + (3,), dtype=np.float32)
        covered = rgba[..., 3] > 0
        rgb[covered] = rgba[covered, :3] / rgba[covered, 3:4]
        return BackendOutput(rgb=rgb, mask=alpha > 0.5, alpha=alpha)

    def close(self) -> None:
        """Remove the temporary folder (the bpy scene stays until the process ends)."""
        shutil.rmtree(self._tmpdir, ignore_errors=True)

    # -- scene construction (once) ------------------------------------------------------

    def _build_scene(self, seed: int) -> None:
        bpy = self._bpy
        scene = bpy.data.scenes.new(_NAME)
        self._scene = scene
        scene.world = None  # no environment light: the sun is the only source

        render = scene.render
        render.engine = "CYCLES"
        render.resolution_percentage = 100
        render.pixel_aspect_x = 1.0
        render.pixel_aspect_y = 1.0
        render.film_transparent = True
        render.use_border = False
        # Persistent data would keep Cycles' scene between renders, but then it misses edits
        # to the texture pixels; a resync costs little next to the samples here.
        render.use_persistent_data = False
        render.threads_mode = "FIXED"
        render.threads = _allowed_threads()
        render.filepath = self._output_path
        render.use_file_extension = False
        image_settings = render.image_settings
        image_settings.file_format = "OPEN_EXR"
        image_settings.color_mode = "RGBA"
        image_settings.color_depth = "32"
        image_settings.exr_codec = "NONE"

        view = scene.view_settings
        view.view_transform = "Standard"
        view.look = "None"
        view.exposure = 0.0
        view.gamma = 1.0

        cycles = scene.cycles
        cycles.seed = int(seed)
        cycles.use_animated_seed = False
        cycles.use_adaptive_sampling = False
        cycles.use_denoising = False
        # Direct light only: the shading model is albedo × E cos θ, no interreflection.
        cycles.max_bounces = 0
        cycles.diffuse_bounces = 0
        cycles.glossy_bounces = 0
        cycles.transmission_bounces = 0
        cycles.volume_bounces = 0
        cycles.transparent_max_bounces = 0
        cycles.caustics_reflective = False
        cycles.caustics_refractive = False
        cycles.use_light_tree = False  # one light: the tree only costs build time
        # The default threshold (0.01) randomly drops weak light samples: a dim sun
        # (irradiance 0.01) would come out as noise around the right value.
        cycles.light_sampling_threshold = 0.0
        cycles.use_auto_tile = False
        cycles.sample_clamp_direct = 0.0
        cycles.sample_clamp_indirect = 0.0

        camera_data = bpy.data.cameras.new(_NAME + "-camera")
        camera_data.type = "PERSP"
        camera_data.sensor_fit = "HORIZONTAL"
        camera_data.sensor_width = SENSOR_WIDTH_MM
        self._camera = bpy.data.objects.new(_NAME + "-camera", camera_data)
        scene.collection.objects.link(self._camera)
        scene.camera = self._camera

        sun_data = bpy.data.lights.new(_NAME + "-sun", "SUN")
        sun_data.angle = 0.0  # a parallel light, as the model's distant source
        # No shadow rays: the shading model (scene.py, the raster backend) has no visibility
        # term, and with the pipeline's light along the optical axis shadows never showed
        # (0 levels of difference on deformed and posed θ) while costing ~25% of the time.
        sun_data.use_shadow = False
        self._sun = bpy.data.objects.new(_NAME + "-sun", sun_data)
        scene.collection.objects.link(self._sun)

        mesh = bpy.data.meshes.new(_NAME + "-sheet")
        self._sheet = bpy.data.objects.new(_NAME + "-sheet", mesh)
        scene.collection.objects.link(self._sheet)

        self._texture = bpy.data.images.new(_NAME + "-texture", 1, 1, alpha=False, float_buffer=False)
        self._texture.colorspace_settings.name = "sRGB"

        material = bpy.data.materials.new(_NAME + "-paper")
        if material.node_tree is None:  # Blender < 5 creates materials without a node tree
            material.use_nodes = True
        nodes = material.node_tree.nodes
        links = material.node_tree.links
        nodes.clear()
        image_node = nodes.new("ShaderNodeTexImage")
        image_node.image = self._texture
        image_node.interpolation = "Linear"
        image_node.extension = "EXTEND"
        diffuse = nodes.new("ShaderNodeBsdfDiffuse")
        diffuse.inputs["Roughness"].default_value = 0.0  # Lambert
        # Gloss: (1 − specular) × diffuse + specular × white GGX (Cycles' α = roughness², as
        # the raster kernel's a2 = roughness⁴). At specular 0 the mix folds to the diffuse
        # closure alone: the paper's scenes render as they did before gloss existed.
        glossy = nodes.new("ShaderNodeBsdfGlossy")
        glossy.distribution = "GGX"
        glossy.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        mix = nodes.new("ShaderNodeMixShader")
        mix.inputs["Fac"].default_value = 0.0
        output = nodes.new("ShaderNodeOutputMaterial")
        output.target = "CYCLES"
        links.new(image_node.outputs["Color"], diffuse.inputs["Color"])
        links.new(diffuse.outputs["BSDF"], mix.inputs[1])
        links.new(glossy.outputs["BSDF"], mix.inputs[2])
        links.new(mix.outputs["Shader"], output.inputs["Surface"])
        # Wrinkles: a tangent-space normal map over the UVs, linked only while a scene has one.
        self._normal_image = bpy.data.images.new(_NAME + "-normals", 1, 1, alpha=False, float_buffer=True)
        self._normal_image.colorspace_settings.name = "Non-Color"
        normal_texture = nodes.new("ShaderNodeTexImage")
        normal_texture.image = self._normal_image
        normal_texture.interpolation = "Linear"
        normal_texture.extension = "EXTEND"
        normal_map = nodes.new("ShaderNodeNormalMap")
        normal_map.space = "TANGENT"
        normal_map.uv_map = "UVMap"
        links.new(normal_texture.outputs["Color"], normal_map.inputs["Color"])
        mesh.materials.append(material)
        self._material = material
        self._nodes = {"diffuse": diffuse, "glossy": glossy, "mix": mix, "normal_map": normal_map}
        self._normal_key: bytes | None = None

        # Ambient light: a uniform world of the scene's ambient radiance (a diffuse surface
        # under it receives albedo × ambient, the raster model); no world when there is none.
        self._world = bpy.data.worlds.new(_NAME + "-sky")
        if self._world.node_tree is None:
            self._world.use_nodes = True
        self._world_background = next(n for n in self._world.node_tree.nodes if n.type == "BACKGROUND")
        self._world_background.inputs["Strength"].default_value = 1.0

        # The shadow caster: seen by nobody, it only blocks the key light. The sheet casts no
        # shadow of its own (the raster model has no self-shadowing).
        self._sheet.visible_shadow = False
        caster_mesh = bpy.data.meshes.new(_NAME + "-caster")
        self._caster = bpy.data.objects.new(_NAME + "-caster", caster_mesh)
        for ray in (
            "visible_camera",
            "visible_diffuse",
            "visible_glossy",
            "visible_transmission",
            "visible_volume_scatter",
        ):
            setattr(self._caster, ray, False)
        self._caster.hide_render = True
        scene.collection.objects.link(self._caster)
        self._caster_key: bytes | None = None
        self._suns = [self._sun]

    def _enable_gpu(self) -> None:
        bpy = self._bpy
        preferences = bpy.context.preferences.addons["cycles"].preferences
        tried = []
        for backend in GPU_BACKENDS:
            try:
                preferences.compute_device_type = backend
            except TypeError:  # back-end not compiled into this build
                continue
            with _quiet_fds():
                preferences.refresh_devices()
            devices = [d for d in preferences.devices if d.type == backend]
            tried.append(f"{backend}: {len(devices)} device(s)")
            if devices:
                for candidate in preferences.devices:
                    candidate.use = candidate.type == backend
                return
        preferences.compute_device_type = "NONE"
        raise BlenderError(
            "device='GPU' was asked for but Cycles finds no GPU (" + ("; ".join(tried) or "no GPU back-end") + ")"
        )

    # -- per-render updates --------------------------------------------------------------

    def _update_mesh(self, scene: Scene3D) -> None:
        mesh = self._sheet.data
        vertices = np.ascontiguousarray(scene.vertices, dtype=np.float32)
        faces = np.ascontiguousarray(scene.faces, dtype=np.int32)
        corner_uv = np.ascontiguousarray(np.asarray(scene.uv, dtype=np.float32)[faces.ravel()])
        topology = (len(vertices), faces.tobytes())
        geometry = (vertices.tobytes(), corner_uv.tobytes())
        if topology != self._topology:
            mesh.clear_geometry()
            mesh.vertices.add(len(vertices))
            mesh.loops.add(faces.size)
            mesh.polygons.add(len(faces))
            mesh.loops.foreach_set("vertex_index", faces.ravel())
            mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
            mesh.vertices.foreach_set("co", vertices.ravel())
            mesh.update(calc_edges=True)
            mesh.shade_flat()  # each triangle is a planar piece of paper
            mesh.uv_layers.new(name="UVMap")
            self._topology = topology
            self._geometry = None
            self.stats["topology_rebuilds"] += 1
        if geometry != self._geometry:
            mesh.vertices.foreach_set("co", vertices.ravel())
            mesh.uv_layers.active.uv.foreach_set("vector", corner_uv.ravel())
            mesh.update()
            self._geometry = geometry
            self.stats["geometry_updates"] += 1

    def _update_texture(self, texture: np.ndarray) -> None:
        key = (texture.shape, texture.tobytes())
        if key == self._texture_key:
            return
        height, width = texture.shape[:2]
        image = self._texture
        if tuple(image.size) != (width, height):
            image.scale(width, height)
        rgba = np.empty((height, width, 4), dtype=np.float32)
        # Blender's pixel rows run bottom to top; ours run top to bottom (v = 1 at row 0).
        rgba[..., :3] = texture[::-1] / np.float32(255.0)
        rgba[..., 3] = 1.0
        image.pixels.foreach_set(rgba.ravel())
        image.update()
        self._texture_key = key
        self.stats["texture_uploads"] += 1

    def _update_camera(self, camera: Camera, vertices: np.ndarray) -> None:
        import mathutils  # noqa: PLC0415 - ships with bpy

        width, height = int(camera.width), int(camera.height)
        render = self._scene.render
        render.resolution_x = width
        render.resolution_y = height
        self._scene.cycles.tile_size = max(width, height)  # one tile: the image is small
        data = self._camera.data
        for name, value in camera_intrinsics(camera.K, width, height).items():
            setattr(data, name, value)
        # Clip planes only bound the rays (no depth-buffer precision in a ray tracer):
        # keep every vertex of the sheet inside them.
        _, depth = camera.project(vertices)
        data.clip_start = 1e-5
        data.clip_end = float(max(1.0, 2.0 * np.abs(depth).max() + 1.0))
        self._camera.matrix_world = mathutils.Matrix(camera_matrix_world(camera.R, camera.t).tolist())

    def _update_light(self, scene: Scene3D) -> None:
        import mathutils  # noqa: PLC0415

        lights = scene.light_list()
        while len(self._suns) < len(lights):
            data = self._bpy.data.lights.new(f"{_NAME}-sun-{len(self._suns)}", "SUN")
            data.angle = 0.0
            data.use_shadow = False
            sun = self._bpy.data.objects.new(data.name, data)
            self._scene.collection.objects.link(sun)
            self._suns.append(sun)
        for sun, light in zip(self._suns, lights):
            sun.hide_render = False
            sun.data.energy = float(math.pi * light.irradiance * scene.exposure)
            sun.data.color = tuple(float(c) for c in light.colour)
            towards_light = mathutils.Vector(np.asarray(light.direction, dtype=np.float64).tolist()).normalized()
            # A sun shines along its local −z: point its +z at the light.
            sun.rotation_mode = "QUATERNION"
            sun.rotation_quaternion = towards_light.to_track_quat("Z", "Y")
        for sun in self._suns[len(lights) :]:
            sun.hide_render = True
        # Only the key light (light 0) is blocked, and only by the caster.
        key = self._suns[0].data
        key.use_shadow = scene.shadow is not None
        key.angle = float(scene.shadow.sun_angle) if scene.shadow is not None else 0.0
        self._update_caster(scene)
        if any(scene.ambient):
            self._world_background.inputs["Color"].default_value = (*(float(c) for c in scene.ambient), 1.0)
            self._scene.world = self._world
        else:
            self._scene.world = None

    def _update_caster(self, scene: Scene3D) -> None:
        if scene.shadow is None:
            self._caster.hide_render = True
            return
        polygon = np.ascontiguousarray(scene.shadow.polygon, dtype=np.float64)
        key = polygon.tobytes()
        if key != self._caster_key:
            mesh = self._caster.data
            mesh.clear_geometry()
            fan = [(0, i, i + 1) for i in range(1, len(polygon) - 1)]
            mesh.from_pydata([tuple(v) for v in polygon.tolist()], [], fan)
            mesh.update()
            self._caster_key = key
        self._caster.hide_render = False

    def _update_material(self, scene: Scene3D) -> None:
        nodes = self._nodes
        nodes["mix"].inputs["Fac"].default_value = float(scene.specular)
        nodes["glossy"].inputs["Roughness"].default_value = float(scene.roughness)
        links = self._material.node_tree.links
        normal_input_links = [link for link in links if link.from_node == nodes["normal_map"]]
        if scene.normal_map is None:
            for link in normal_input_links:
                links.remove(link)
            return
        normals = np.asarray(scene.normal_map, dtype=np.float32)
        key = normals.tobytes() + bytes(str(normals.shape), "ascii")
        if key != self._normal_key:
            height, width = normals.shape[:2]
            image = self._normal_image
            if tuple(image.size) != (width, height):
                image.scale(width, height)
            rgba = np.ones((height, width, 4), dtype=np.float32)
            # Tangent-space normals are stored as (n + 1) / 2; rows bottom to top, as the texture.
            rgba[..., :3] = (normals[::-1] + 1.0) / 2.0
            image.pixels.foreach_set(rgba.ravel())
            image.update()
            self._normal_key = key
        if not normal_input_links:
            links.new(nodes["normal_map"].outputs["Normal"], nodes["diffuse"].inputs["Normal"])
            links.new(nodes["normal_map"].outputs["Normal"], nodes["glossy"].inputs["Normal"])

    def _render_rgba(self) -> np.ndarray:
        bpy = self._bpy
        with contextlib.suppress(FileNotFoundError):
            os.remove(self._output_path)
        try:
            with _quiet_fds() as log:
                result = bpy.ops.render.render(write_still=True, scene=self._scene.name)
        except RuntimeError as error:
            raise BlenderError(f"Cycles render failed: {error}\n{''.join(log)[-2000:]}") from error
        if "FINISHED" not in result or not os.path.exists(self._output_path):
            raise BlenderError(f"Cycles render did not write its image ({result}):\n{''.join(log)[-2000:]}")
        image = self._result_image
        if image is None:
            image = bpy.data.images.load(self._output_path, check_existing=False)
            image.name = _NAME + "-result"
            self._result_image = image
        else:
            image.reload()
        width, height = self._scene.render.resolution_x, self._scene.render.resolution_y
        if tuple(image.size) != (width, height) or image.channels != 4:
            raise BlenderError(
                f"render read back as {tuple(image.size)}x{image.channels}, expected {(width, height)}x4"
            )
        pixels = np.empty(width * height * 4, dtype=np.float32)
        image.pixels.foreach_get(pixels)
        # Blender rows run bottom to top.
        return pixels.reshape(height, width, 4)[::-1]


_renderer: BlenderRenderer | None = None
_renderer_lock = threading.Lock()


def get_renderer(samples: int = 16, device: str = "CPU") -> BlenderRenderer:
    """The process's one renderer (built on first use), set to ``samples`` and ``device``."""
    global _renderer
    with _renderer_lock:
        if _renderer is None:
            _renderer = BlenderRenderer(samples=samples, device=device)
            atexit.register(_renderer.close)
        else:
            _renderer.configure(samples=samples, device=device)
        return _renderer


def render_scene(scene: Scene3D, samples: int = 16, device: str = "CPU") -> BackendOutput:
    """Render with the process's renderer (the same call shape as ``raster.render_scene``)."""
    return get_renderer(samples=samples, device=device).render(scene)
