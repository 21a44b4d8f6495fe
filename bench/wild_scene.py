"""The out-of-domain scene of bench/wild.py: a world built in Blender (Cycles) that no training path uses.

``OodRecipe`` holds everything that decides a set's bytes (its hash names the set's cache);
``PHOTO_POOLS`` the photographs that cover the ground and the clutter; ``curled_sheet``,
``creased_sheet``, ``rolled_sheet`` and ``bent_sheet`` bend the sheet by geometry of their own,
not foldwise's ruling model; ``OodScene`` builds one scene per seed, renders it and reads each
target's visible box from an object-index render; ``load_textures`` gathers the object textures,
the photographs of a pool and the lookalike sheets (``lookalike_names``). bench/wild.py's
docstring describes the scene.
"""

from __future__ import annotations

import hashlib
import json
import math
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bench import panoramas  # no heavy imports: paths and a derivation run by hand

RECIPE_VERSION = 2
# Photographs for clutter sheets: none of them shows what one of the five default object
# textures shows (skimage's stereo_motorcycle is the motorcycle from another viewpoint, its cat
# is chelsea: a detector that finds those would be right, so they are not clutter).
CLUTTER_PHOTOS = ("immunohistochemistry", "retina", "colorwheel", "coins", "page", "camera", "moon")
GROUND_PHOTOS = ("brick", "grass", "gravel", "hubble_deep_field", "moon")
# Every photograph above is also one of foldwise's training backgrounds or occluders. The
# held-apart pool is not: three of Blender's panoramas (bench/panoramas.py), and matplotlib's and
# skimage's sample photographs that no training path reads. A detector that learnt its training
# backgrounds by heart fails there.
HELD_APART_PANORAMAS = panoramas.NAMES
HELD_APART_CLUTTER = ("grace_hopper", "Minduka_Present_Blue_Pack", "horse", "microaneurysms", *HELD_APART_PANORAMAS)
HELD_APART_GROUND = (*HELD_APART_PANORAMAS, "grace_hopper", "Minduka_Present_Blue_Pack")
PHOTO_POOLS = {  # recipe.photos -> (ground photographs, clutter photographs)
    "training": (GROUND_PHOTOS, CLUTTER_PHOTOS),
    "held_apart": (HELD_APART_GROUND, HELD_APART_CLUTTER),
}
MATPLOTLIB_PHOTOS = {"grace_hopper": "grace_hopper.jpg", "Minduka_Present_Blue_Pack": "Minduka_Present_Blue_Pack.png"}
# What makes a scene wild, each factor on its own: with one turned off, that part of the scene
# takes a plain value (see OodScene.build), so a run per factor tells which one the detector
# misses most.
FACTORS = ("camera", "scale", "curl", "light", "material", "ground", "clutter", "post")


@dataclass(frozen=True)
class OodRecipe:
    """Everything that decides the out-of-domain set's bytes (its hash names the cache)."""

    n: int = 200
    width: int = 320
    height: int = 240
    samples: int = 24
    seed: int = 2026
    negatives: float = 0.1
    classes: tuple[str, ...] = ()
    factors: tuple[str, ...] = FACTORS
    # Which photographs cover the ground and the clutter sheets (PHOTO_POOLS).
    photos: str = "training"
    # Printed lookalikes (texture names, ``load_textures(lookalikes=...)``): sheets of the same
    # kind as the targets that are none of them, one to three per image, beside the targets.
    lookalikes: tuple[str, ...] = ()
    # The hard scene (``HARD``): small sheets, tubes and sharp creases, extremes of exposure and
    # light colour, uneven 3D ground with rocks, JPEG down to quality 35.
    hard: bool = False

    def __post_init__(self) -> None:
        unknown = sorted(set(self.factors) - set(FACTORS))
        if unknown:
            raise ValueError(f"unknown factor(s) {unknown}; known: {', '.join(FACTORS)}")
        if self.photos not in PHOTO_POOLS:
            raise ValueError(f"unknown photo pool {self.photos!r}; known: {', '.join(PHOTO_POOLS)}")

    def key(self) -> str:
        fields = asdict(self)
        if self.factors == FACTORS:  # the full wild set keeps the key it had before factors existed
            del fields["factors"]
        if self.photos == "training":  # and before the held-apart pool existed
            del fields["photos"]
        for name in ("lookalikes", "hard"):  # and before lookalikes and the hard scene
            if not fields[name]:
                del fields[name]
        payload = json.dumps({"version": RECIPE_VERSION, **fields}, sort_keys=True)
        return hashlib.sha256(payload.encode()).hexdigest()[:16]


# --------------------------------------------------------------------------- geometry


def _flat_grid(width: float, height: float, cells: int):
    """A flat sheet (z = 0, centred) as a grid: points (N, 2), quad faces and UVs."""
    grid_x, grid_y = np.meshgrid(
        np.linspace(-width / 2, width / 2, cells + 1), np.linspace(-height / 2, height / 2, cells + 1)
    )
    points = np.stack([grid_x.ravel(), grid_y.ravel()], axis=1)
    corners = [row * (cells + 1) + col for row in range(cells) for col in range(cells)]
    faces = [(a, a + 1, a + cells + 2, a + cells + 1) for a in corners]
    uvs = np.column_stack([(grid_x.ravel() + width / 2) / width, (grid_y.ravel() + height / 2) / height])
    return points, faces, uvs


def _wrapped(points: np.ndarray, direction: np.ndarray, start: float, radius: float) -> np.ndarray:
    """The flat ``points`` beyond the line ``along == start`` wrapped around a cylinder of
    ``radius`` tangent there (arc length kept: developable); vertices (N, 3)."""
    along = points @ direction
    theta = np.maximum(along - start, 0.0) / radius
    lifted_along = np.where(along > start, start + radius * np.sin(theta), along)
    z = np.where(along > start, radius * (1 - np.cos(theta)), 0.0)
    return np.column_stack([points + np.outer(lifted_along - along, direction), z])


def curled_sheet(width: float, height: float, rng: np.random.Generator, cells: int = 24, flat: bool = False):
    """A flat sheet (z = 0, centred) with a cylindrical curl: isometric, unlike foldwise's rulings.

    The sheet is flat up to a line across it (random direction and offset), then wraps around
    a cylinder of radius ``r`` tangent there: arc length along the sheet is kept, so the curl
    is developable. Returns vertices (N, 3), quad faces and UVs.
    """
    points, faces, uvs = _flat_grid(width, height, cells)
    angle = rng.uniform(0, 2 * math.pi)
    direction = np.array([math.cos(angle), math.sin(angle)])
    start = rng.uniform(-0.4, 0.3) * (abs(direction[0]) * width + abs(direction[1]) * height)
    radius = rng.uniform(0.12, 0.8) * max(width, height)
    if rng.random() < 0.2 or flat:  # a flat sheet now and then
        radius = 1e9
    return _wrapped(points, direction, start, radius), faces, uvs


def creased_sheet(width: float, height: float, rng: np.random.Generator, cells: int = 24, angle: float | None = None):
    """A flat sheet folded along a line across it by ``angle`` (radians; drawn from 20-110° when
    None): the part beyond the line turns about it, out of the ground plane. Folding keeps every
    length, so the crease is developable as a real one is. Returns vertices, quad faces, UVs."""
    points, faces, uvs = _flat_grid(width, height, cells)
    heading = rng.uniform(0, 2 * math.pi)
    direction = np.array([math.cos(heading), math.sin(heading)])
    along = points @ direction
    start = rng.uniform(-0.3, 0.3) * (abs(direction[0]) * width + abs(direction[1]) * height)
    fold = math.radians(rng.uniform(20, 110)) if angle is None else angle
    beyond = np.maximum(along - start, 0.0)
    new_along = np.where(along > start, start + beyond * math.cos(fold), along)
    xy = points + np.outer(new_along - along, direction)
    return np.column_stack([xy, beyond * math.sin(fold)]), faces, uvs


def rolled_sheet(width: float, height: float, rng: np.random.Generator, cells: int = 32):
    """A sheet rolled into a tube: flat for a short run, then wrapped around a cylinder by
    180-320° (a sheet left to roll back, a poster in a tube); isometric like ``curled_sheet``."""
    points, faces, uvs = _flat_grid(width, height, cells)
    across_x = rng.random() < 0.5  # roll along the sheet's width or its height
    direction = np.array([1.0, 0.0]) if across_x else np.array([0.0, 1.0])
    length = width if across_x else height
    start = -length / 2 + rng.uniform(0.0, 0.25) * length
    wrap = math.radians(rng.uniform(180, 320))
    return _wrapped(points, direction, start, (length / 2 - start) / wrap), faces, uvs


def bent_sheet(width: float, height: float, rng: np.random.Generator, hard: bool, flat: bool = False):
    """The sheet's bend for a recipe: the curl of the wild scene; in the hard scene also tubes
    (30%) and creases (35%)."""
    if hard and not flat:
        draw = rng.random()
        if draw < 0.3:
            return rolled_sheet(width, height, rng)
        if draw < 0.65:
            return creased_sheet(width, height, rng)
    return curled_sheet(width, height, rng, flat=flat)


def look_at(location: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """Blender camera rotation matrix (camera looks down −z, y up) from a location and a target."""
    forward = target - location
    forward = forward / np.linalg.norm(forward)
    up_hint = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up_hint)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    c, s = math.cos(roll), math.sin(roll)
    right, up = c * right + s * up, -s * right + c * up
    return np.column_stack([right, up, -forward])


# --------------------------------------------------------------------------- the Blender scene


class OodScene:
    """One bpy scene, rebuilt per image from a seed: its own objects, materials and lights."""

    def __init__(self, textures: dict[str, np.ndarray], recipe: OodRecipe):
        from workers.render.blender import _import_bpy  # the import check only; no foldwise scene is used

        self.bpy = _import_bpy()
        self.recipe = recipe
        self.textures = textures
        self.tmp = Path(tempfile.mkdtemp(prefix="foldwise-wild-"))
        self._images: dict[str, object] = {}
        self.scene = None

    # -- datablocks
    def _image(self, name: str, pixels: np.ndarray):
        if name in self._images:
            return self._images[name]
        height, width = pixels.shape[:2]
        image = self.bpy.data.images.new(f"wild-{name}", width, height, alpha=True)
        # The colour space first: changing it regenerates a generated image (to black).
        image.colorspace_settings.name = "sRGB"
        rgba = np.ones((height, width, 4), dtype=np.float32)
        rgba[..., :3] = pixels[..., :3] / 255.0
        image.pixels.foreach_set(rgba[::-1].ravel())
        image.update()
        self._images[name] = image
        return image

    def _material(self, name: str, rng, image=None, colour=None, procedural: str | None = None, gloss: bool = True):
        bpy = self.bpy
        material = bpy.data.materials.new(name)
        if material.node_tree is None:
            material.use_nodes = True
        nodes, links = material.node_tree.nodes, material.node_tree.links
        nodes.clear()
        bsdf = nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Roughness"].default_value = float(rng.uniform(0.15, 0.8) if gloss else rng.uniform(0.6, 1.0))
        if "Coat Weight" in bsdf.inputs and gloss and rng.random() < 0.4:
            bsdf.inputs["Coat Weight"].default_value = float(rng.uniform(0.2, 1.0))
            bsdf.inputs["Coat Roughness"].default_value = float(rng.uniform(0.02, 0.2))
        output = nodes.new("ShaderNodeOutputMaterial")
        if image is not None:
            texture = nodes.new("ShaderNodeTexImage")
            texture.image = image
            texture.extension = "EXTEND"
            links.new(texture.outputs["Color"], bsdf.inputs["Base Color"])
        elif procedural is not None:
            kind = {
                "noise": "ShaderNodeTexNoise",
                "voronoi": "ShaderNodeTexVoronoi",
                "wave": "ShaderNodeTexWave",
                "checker": "ShaderNodeTexChecker",
                "brick": "ShaderNodeTexBrick",
                "magic": "ShaderNodeTexMagic",
            }[procedural]
            texture = nodes.new(kind)
            if "Scale" in texture.inputs:
                texture.inputs["Scale"].default_value = float(rng.uniform(2, 30))
            ramp = nodes.new("ShaderNodeValToRGB")
            elements = ramp.color_ramp.elements
            for element in elements:
                element.color = (*rng.uniform(0, 1, 3), 1.0)
            elements[0].position, elements[1].position = sorted(rng.uniform(0, 1, 2))
            source = texture.outputs["Fac"] if "Fac" in texture.outputs else texture.outputs[0]
            links.new(source, ramp.inputs["Fac"])
            links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
        else:
            bsdf.inputs["Base Color"].default_value = (*(colour if colour is not None else rng.uniform(0, 1, 3)), 1.0)
        links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
        return material

    def _mesh_object(self, name: str, vertices, faces, uvs=None, material=None):
        bpy = self.bpy
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata([tuple(v) for v in vertices], [], [tuple(f) for f in faces])
        if uvs is not None:
            layer = mesh.uv_layers.new(name="UVMap")
            loop_uvs = np.array([uvs[loop.vertex_index] for loop in mesh.loops], dtype=np.float32)
            layer.data.foreach_set("uv", loop_uvs.ravel())
        mesh.update()
        for polygon in mesh.polygons:
            polygon.use_smooth = True
        obj = bpy.data.objects.new(name, mesh)
        if material is not None:
            mesh.materials.append(material)
        self.scene.collection.objects.link(obj)
        return obj

    def _primitive(self, name: str, kind: str, size: float, material):
        import bmesh

        bm = bmesh.new()
        if kind == "cube":
            bmesh.ops.create_cube(bm, size=size)
        elif kind == "sphere":
            bmesh.ops.create_uvsphere(bm, u_segments=24, v_segments=12, radius=size / 2)
        elif kind == "cylinder":
            bmesh.ops.create_cone(bm, cap_ends=True, segments=24, radius1=size / 3, radius2=size / 3, depth=size)
        else:  # cone
            bmesh.ops.create_cone(bm, cap_ends=True, segments=24, radius1=size / 2, radius2=0.0, depth=size)
        mesh = self.bpy.data.meshes.new(name)
        bm.to_mesh(mesh)
        bm.free()
        mesh.materials.append(material)
        obj = self.bpy.data.objects.new(name, mesh)
        self.scene.collection.objects.link(obj)
        return obj

    def _reset(self) -> None:
        bpy = self.bpy
        if self.scene is not None:
            bpy.data.scenes.remove(self.scene)
        for collection in (
            bpy.data.objects,
            bpy.data.meshes,
            bpy.data.materials,
            bpy.data.lights,
            bpy.data.cameras,
            bpy.data.worlds,
        ):
            for block in list(collection):
                if block.name.startswith("wild") and block.users == 0:
                    collection.remove(block)
        self.scene = bpy.data.scenes.new("wild")

    # -- one image
    def build(self, seed: int, negative: bool):
        """Set up the scene for one image; returns the target objects and their class names.

        A factor left out of ``recipe.factors`` takes its plain value: camera straight above
        with a 40° lens and no roll (camera), the sheet at half the frame's width (scale), a
        flat sheet lying on the ground (curl), a white sun from above, a grey sky, Standard
        tone mapping (light), a matte sheet (material), a photograph for ground (ground), no
        clutter and one target (clutter), no noise or JPEG (post)."""
        bpy = self.bpy
        rng = np.random.default_rng(seed)
        self._reset()
        scene = self.scene
        recipe = self.recipe
        wild = set(recipe.factors)
        render = scene.render
        render.engine = "CYCLES"
        render.resolution_x, render.resolution_y = recipe.width, recipe.height
        render.resolution_percentage = 100
        render.use_file_extension = False
        render.threads_mode = "AUTO"
        cycles = scene.cycles
        cycles.seed = int(seed % (2**31))
        cycles.use_denoising = False
        cycles.use_adaptive_sampling = False
        cycles.max_bounces = 4
        view = scene.view_settings
        view.view_transform = str(rng.choice(["Standard", "AgX"])) if "light" in wild else "Standard"
        view.exposure = float(rng.uniform(-0.8, 0.8)) if "light" in wild else 0.0
        if recipe.hard and "light" in wild:  # under- and over-exposed photographs
            view.exposure = float(rng.choice([-1, 1]) * rng.uniform(0.8, 2.2))

        # World: a sky-like gradient or a flat colour, as ambient light of random strength.
        world = bpy.data.worlds.new("wild-world")
        if world.node_tree is None:
            world.use_nodes = True
        background = world.node_tree.nodes.get("Background") or world.node_tree.nodes.new("ShaderNodeBackground")
        tint = rng.uniform(0.4, 1.0, 3) if "light" in wild else np.ones(3)
        if recipe.hard and "light" in wild:  # strongly coloured light: tungsten, shade, neon
            tint = rng.uniform(0.15, 1.0, 3)
        background.inputs["Color"].default_value = (*tint, 1.0)
        background.inputs["Strength"].default_value = float(rng.uniform(0.05, 1.2)) if "light" in wild else 0.3
        scene.world = world

        # Ground: a photograph or a procedural texture.
        ground_size = 40.0
        ground_photos, clutter_photos = PHOTO_POOLS[recipe.photos]
        if rng.random() < 0.4 or "ground" not in wild:
            name = str(rng.choice(ground_photos))
            ground_material = self._material(
                "wild-ground", rng, image=self._image(name, self.textures[name]), gloss=False
            )
        else:
            kind = str(rng.choice(["noise", "voronoi", "wave", "checker", "brick", "magic"]))
            ground_material = self._material("wild-ground", rng, procedural=kind, gloss=rng.random() < 0.3)
        tiles = rng.uniform(4, 20)
        half = ground_size / 2
        self._mesh_object(
            "wild-ground",
            [(-half, -half, -0.002), (half, -half, -0.002), (half, half, -0.002), (-half, half, -0.002)],
            [(0, 1, 2, 3)],
            uvs=np.array([[0, 0], [tiles, 0], [tiles, tiles], [0, tiles]]),
            material=ground_material,
        )

        # Targets: one sheet, sometimes a second; none in a negative image.
        classes = [name for name in recipe.classes]
        n_targets = 0 if negative else (2 if rng.random() < 0.2 and "clutter" in wild else 1)
        targets = []
        placed: list[tuple[float, float, float]] = []
        for index in range(n_targets):
            name = str(rng.choice(classes))
            texture = self.textures[name]
            aspect = texture.shape[1] / texture.shape[0]
            width = 1.0 if aspect >= 1 else aspect
            height = width / aspect
            vertices, faces, uvs = bent_sheet(width, height, rng, recipe.hard, flat="curl" not in wild)
            material = self._material(
                f"wild-target-{index}", rng, image=self._image(name, texture), gloss="material" in wild
            )
            obj = self._mesh_object(f"wild-target-{index}", vertices, faces, uvs, material)
            offset = (0.0, 0.0) if index == 0 else tuple(rng.uniform(-1.4, 1.4, 2))
            obj.location = (*offset, 0.0)
            obj.rotation_euler = (0.0, 0.0, float(rng.uniform(0, 2 * math.pi)) if "camera" in wild else 0.0)
            if rng.random() < 0.25 and "curl" in wild:  # leaning on something: tilted out of the ground plane
                obj.rotation_euler = (
                    float(rng.uniform(-0.9, 0.9)),
                    float(rng.uniform(-0.9, 0.9)),
                    obj.rotation_euler[2],
                )
                obj.location = (*offset, 0.35)
            obj.pass_index = index + 1
            targets.append((obj, name))
            placed.append((*offset, max(width, height)))

        # Clutter: sheets of other photographs, and primitives, beside and over the target.
        for index in range(int(rng.integers(0, 4)) if "clutter" in wild else 0):
            photo = str(rng.choice(clutter_photos))
            texture = self.textures[photo]
            aspect = texture.shape[1] / texture.shape[0]
            side = rng.uniform(0.4, 1.0)
            vertices, faces, uvs = curled_sheet(side * min(aspect, 1.5), side, rng, cells=12)
            material = self._material(f"wild-clutter-sheet-{index}", rng, image=self._image(photo, texture))
            obj = self._mesh_object(f"wild-clutter-sheet-{index}", vertices, faces, uvs, material)
            obj.location = (*rng.uniform(-2.0, 2.0, 2), -0.001)
            if np.hypot(*obj.location[:2]) < 0.9:  # keep clutter sheets from covering the target
                obj.location = (obj.location[0] + 1.5, obj.location[1], -0.001)
            obj.rotation_euler = (0.0, 0.0, float(rng.uniform(0, 2 * math.pi)))
        # Printed lookalikes: sheets of the targets' kind that are none of them, beside them.
        for index in range(int(rng.integers(1, 4)) if recipe.lookalikes else 0):
            name = str(rng.choice(recipe.lookalikes))
            texture = self.textures[name]
            aspect = texture.shape[1] / texture.shape[0]
            width = 1.0 if aspect >= 1 else aspect
            vertices, faces, uvs = bent_sheet(width, width / aspect, rng, recipe.hard)
            material = self._material(
                f"wild-lookalike-{index}", rng, image=self._image(name, texture), gloss="material" in wild
            )
            obj = self._mesh_object(f"wild-lookalike-{index}", vertices, faces, uvs, material)
            heading, distance = rng.uniform(0, 2 * math.pi), rng.uniform(1.1, 2.2)
            obj.location = (distance * math.cos(heading), distance * math.sin(heading), 0.0)
            obj.rotation_euler = (0.0, 0.0, float(rng.uniform(0, 2 * math.pi)))
        # Uneven ground: rocks and mounds that cast shadows and hide parts of the scene.
        for index in range(int(rng.integers(2, 7)) if recipe.hard else 0):
            size = float(rng.uniform(0.3, 1.2))
            material = self._material(
                f"wild-rock-{index}", rng, procedural=str(rng.choice(["noise", "voronoi", "magic"])), gloss=False
            )
            obj = self._primitive(f"wild-rock-{index}", str(rng.choice(["sphere", "cube"])), size, material)
            heading, distance = rng.uniform(0, 2 * math.pi), rng.uniform(1.6, 4.0)
            obj.location = (
                distance * math.cos(heading),
                distance * math.sin(heading),
                float(rng.uniform(-0.4, 0.1)) * size,
            )
            obj.rotation_euler = tuple(float(v) for v in rng.uniform(0, math.pi, 3))
            obj.scale = tuple(float(v) for v in rng.uniform(0.5, 1.5, 3))
        for index in range(int(rng.integers(0, 7)) if "clutter" in wild else 0):
            size = float(rng.uniform(0.08, 0.45))
            material = self._material(f"wild-clutter-{index}", rng)
            obj = self._primitive(
                f"wild-clutter-{index}", str(rng.choice(["cube", "sphere", "cylinder", "cone"])), size, material
            )
            over_target = rng.random() < 0.3 and placed
            x, y = rng.uniform(-0.45, 0.45, 2) if over_target else rng.uniform(-2.2, 2.2, 2)
            obj.location = (float(x), float(y), size / 2 + (rng.uniform(0.05, 0.6) if over_target else 0.0))
            obj.rotation_euler = tuple(float(v) for v in rng.uniform(0, math.pi, 3))

        # Lights: a sun of random colour and height (real shadows), sometimes a point light.
        sun_data = bpy.data.lights.new("wild-sun", "SUN")
        sun = bpy.data.objects.new("wild-sun", sun_data)
        if "light" in wild:
            sun_data.energy = float(rng.uniform(1.0, 6.0))
            sun_data.angle = float(rng.uniform(0.0, 0.3))
            sun_data.color = tuple(rng.uniform(0.6, 1.0, 3))
            sun.rotation_euler = (float(rng.uniform(0, 1.3)), 0.0, float(rng.uniform(0, 2 * math.pi)))
        else:
            sun_data.energy, sun_data.angle = math.pi, 0.0
        scene.collection.objects.link(sun)
        if rng.random() < 0.35 and "light" in wild:
            point_data = bpy.data.lights.new("wild-point", "POINT")
            point_data.energy = float(rng.uniform(50, 400))
            point_data.color = tuple(rng.uniform(0.5, 1.0, 3))
            point = bpy.data.objects.new("wild-point", point_data)
            point.location = (*rng.uniform(-2, 2, 2), float(rng.uniform(0.8, 3)))
            scene.collection.objects.link(point)

        # Camera: anywhere on the upper hemisphere, field of view 8-100°, the sheet filling
        # 0.1-1.6 of the frame's width (log-uniform), aimed off-centre.
        camera_data = bpy.data.cameras.new("wild-camera")
        camera_data.sensor_fit = "HORIZONTAL"
        camera_data.sensor_width = 36.0
        camera_wild = "camera" in wild
        fov = math.radians(float(np.exp(rng.uniform(math.log(8), math.log(100)))) if camera_wild else 40.0)
        camera_data.angle = fov
        camera_data.clip_start = 0.005
        camera_data.clip_end = 500.0
        fill = float(np.exp(rng.uniform(math.log(0.1), math.log(1.6)))) if "scale" in wild else 0.5
        if recipe.hard and "scale" in wild:  # mostly small sheets: often ~5% of the frame
            fill = float(np.exp(rng.uniform(math.log(0.12), math.log(0.8))))
        distance = 1.0 / (fill * 2 * math.tan(fov / 2))
        elevation = float(rng.uniform(math.radians(25), math.radians(90))) if camera_wild else math.pi / 2
        azimuth = float(rng.uniform(0, 2 * math.pi)) if camera_wild else -math.pi / 2
        aim = np.array([*rng.uniform(-0.25, 0.25, 2), 0.0]) if camera_wild else np.zeros(3)
        location = aim + distance * np.array(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        camera = bpy.data.objects.new("wild-camera", camera_data)
        roll = float(rng.uniform(-math.pi, math.pi)) if camera_wild else 0.0
        camera.matrix_world = _matrix(look_at(location, aim, roll), location)
        scene.collection.objects.link(camera)
        scene.camera = camera
        post = {
            "noise_sigma": float(rng.uniform(0, 8)) if rng.random() < 0.5 and "post" in wild else 0.0,
            "jpeg_quality": int(rng.integers(35 if recipe.hard else 25, 95))
            if rng.random() < 0.7 and "post" in wild
            else None,
        }
        return targets, {"fill": fill, "fov_deg": math.degrees(fov), "elevation_deg": math.degrees(elevation), **post}

    def _render_to(self, path: Path, file_format: str, samples: int) -> None:
        scene = self.scene
        scene.cycles.samples = samples
        scene.render.filepath = str(path)
        settings = scene.render.image_settings
        settings.file_format = file_format
        if file_format == "OPEN_EXR":
            settings.color_mode = "RGBA"
            settings.color_depth = "32"
        else:
            settings.color_mode = "RGB"
            settings.color_depth = "8"
        from workers.render.blender import _quiet_fds

        with _quiet_fds():
            self.bpy.ops.render.render(write_still=True, scene=scene.name)

    def _index_render(self) -> np.ndarray:
        """Object index per pixel: an emission override of each object's pass index, one sample."""
        bpy = self.bpy
        scene = self.scene
        material = bpy.data.materials.get("wild-index") or _index_material(bpy)
        layer = scene.view_layers[0]
        saved = (
            scene.cycles.filter_width,
            scene.render.film_transparent,
            scene.view_settings.view_transform,
            scene.view_settings.exposure,
        )
        layer.material_override = material
        scene.cycles.filter_width = 0.01
        scene.render.film_transparent = True
        scene.view_settings.view_transform = "Standard"
        scene.view_settings.exposure = 0.0
        path = self.tmp / "index.exr"
        self._render_to(path, "OPEN_EXR", 1)
        layer.material_override = None
        (
            scene.cycles.filter_width,
            scene.render.film_transparent,
            scene.view_settings.view_transform,
            scene.view_settings.exposure,
        ) = saved
        image = bpy.data.images.load(str(path), check_existing=False)
        try:
            width, height = image.size
            pixels = np.empty(width * height * image.channels, dtype=np.float32)
            image.pixels.foreach_get(pixels)
        finally:
            bpy.data.images.remove(image)
        # Blender rows run bottom to top; red holds the index.
        return np.rint(pixels.reshape(height, width, -1)[::-1, :, 0]).astype(np.int32)

    def render(self, seed: int, negative: bool):
        """Render one image: (uint8 RGB, [(class, box, visible_fraction)], description) or None to redraw."""
        import cv2

        targets, info = self.build(seed, negative)
        visible = self._index_render()
        # Unoccluded extent of each target: hide everything else and render the index again.
        hidden = [obj for obj in self.scene.objects if obj.type == "MESH" and obj.pass_index == 0]
        for obj in hidden:
            obj.hide_render = True
        alone = self._index_render()
        for obj in hidden:
            obj.hide_render = False
        objects = []
        for obj, name in targets:
            mask = visible == obj.pass_index
            full = int((alone == obj.pass_index).sum())
            if full < 64:
                return None  # the target is (almost) out of view: redraw
            fraction = float(mask.sum()) / full
            if fraction < 0.3:
                return None  # too little left to be a fair target: redraw
            ys, xs = np.nonzero(mask)
            objects.append(
                (name, [float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)], fraction)
            )
        path = self.tmp / "image.png"
        self._render_to(path, "PNG", self.recipe.samples)
        image = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        rng = np.random.default_rng(seed + 1)
        if info["noise_sigma"] > 0:
            image = np.clip(image + rng.normal(0, info["noise_sigma"], image.shape), 0, 255).astype(np.uint8)
        if info["jpeg_quality"] is not None:
            ok, encoded = cv2.imencode(
                ".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, info["jpeg_quality"]]
            )
            image = cv2.cvtColor(cv2.imdecode(encoded, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        return image, objects, info


def _matrix(rotation: np.ndarray, location: np.ndarray):
    from mathutils import Matrix

    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = location
    return Matrix(matrix.tolist())


def _index_material(bpy):
    material = bpy.data.materials.new("wild-index")
    if material.node_tree is None:
        material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    nodes.clear()
    info = nodes.new("ShaderNodeObjectInfo")
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Strength"].default_value = 1.0
    output = nodes.new("ShaderNodeOutputMaterial")
    links.new(info.outputs["Object Index"], emission.inputs["Color"])
    links.new(emission.outputs["Emission"], output.inputs["Surface"])
    material.use_fake_user = True
    return material


LOOKALIKE_PREFIX = "lookalike:"


def lookalike_names(folder: Path | None) -> tuple[str, ...]:
    """The texture names of a folder of lookalike sheets (every image in it, by file stem)."""
    if folder is None:
        return ()
    from foldwise.asset_check import image_files

    return tuple(LOOKALIKE_PREFIX + path.stem for path in image_files(Path(folder), "lookalikes"))


def load_textures(
    classes, photos: str = "training", assets=None, lookalikes: Path | None = None
) -> dict[str, np.ndarray]:
    """The object textures foldwise uses (same files; ``assets``: a config's ``assets`` section, None
    for the built-in ones), the ground/clutter photographs of pool ``photos``, and each sheet of
    the ``lookalikes`` folder (as ``lookalike_names`` names them)."""
    import skimage.data

    from foldwise.asset_check import image_files
    from workers.render.assets import _file_image, _to_uint8_rgb, load_assets

    catalog = load_assets(assets)
    textures = catalog.textures(classes)
    for path in image_files(Path(lookalikes), "lookalikes") if lookalikes is not None else ():
        textures[LOOKALIKE_PREFIX + path.stem] = _file_image(str(path), False)
    ground, clutter = PHOTO_POOLS[photos]
    for name in sorted(set(ground) | set(clutter)):
        if name in panoramas.NAMES:
            textures[name] = _file_image(str(panoramas.path(name)), False)  # as foldwise reads an asset file
        elif name in MATPLOTLIB_PHOTOS:
            import matplotlib.cbook

            textures[name] = _file_image(
                str(matplotlib.cbook.get_sample_data(MATPLOTLIB_PHOTOS[name], asfileobj=False)), False
            )
        else:
            textures[name] = _to_uint8_rgb(np.asarray(getattr(skimage.data, name)()), f"skimage.data.{name}")
    return textures
