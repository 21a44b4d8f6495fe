"""Out-of-domain benchmark: does the detector foldwise trains find the object in images foldwise did not render?

Trains with a config as ``make run`` does (default ``configs/quick.yaml``, two curricula handed
over as one ensemble; ``--members 1``: one) or takes a checkpoint, then scores the model, under the paper's protocol (score ≥ 0.8, IoU 0.5) and
unthresholded, on two sets:

* **in-domain**: foldwise's own renders, every (condition, difficulty) of the config's
  curriculum plus its mixed stage, drawn by ``foldwise.sampling`` and rendered by the config's
  backend (the standard test set's recipe, with a seed of its own);
* **out-of-domain**: a scene this file builds in Blender (Cycles) that no training path uses.
  Nothing of foldwise's θ, camera, sheet model, lighting, compositing or imaging code is
  called: the sheet lies on a textured ground in a 3D world and is bent by a cylindrical curl
  of its own (not foldwise's ruling model); a principled BSDF with a glossy coat; a sun of
  random colour, height and softness casting real shadows, a sky or coloured ambient world
  light, sometimes a point light; a camera anywhere on the upper hemisphere with a focal length
  from 8° to 100° of field of view (beyond the training range at both ends), the sheet filling
  from a tenth to more than the whole frame, partly outside it; primitives and sheets of
  other photographs as clutter, beside the target, over it, and casting shadows on it; a
  second target; Blender's own tone mapping (Standard or AgX) and exposure; sensor noise and
  JPEG at random quality; 10% images without the object; 4:3 frames. Boxes are the visible
  extent of each target, read from an object-index render (one sample, no pixel filter).

The set is written as a COCO folder (``--ood-dir``) and reused when its recipe is unchanged.
A second set of the same scene, drawn apart (100 images at 480×360, seed 7: ``--n-ood-second``,
``--ood-second-size``, ``--ood-second-seed``; 0 images skips it), is scored beside it, so that
no lever is judged on one set of draws (a set of 100 images moves by about ±0.05 between draws).
Both cover the ground and the clutter with photographs that are also foldwise's training
backgrounds and occluders; a third set (100 images at 320×240, seed 11: ``--n-ood-apart``,
``--ood-apart-size``, ``--ood-apart-seed``) uses photographs that no training path reads
(``PHOTO_POOLS["held_apart"]``), so a detector that knew its training backgrounds by heart
would be seen to fail there.
It is a proxy for photographs, made by independent code; it is not the held-out set that
scores foldwise's landings, and nothing in foldwise is tuned to it.

    python bench/wild.py                                  # train configs/quick.yaml, then score
    python bench/wild.py --model var/.../model.pt         # score a checkpoint
    python bench/wild.py --model M.pt --n-ood 300 --out bench/results/wild.json
    python bench/wild.py --model M.pt --test-sizes 128         # detect at one input size only
    python bench/wild.py --model M.pt --test-turns 0           # upright views only

Two more in-domain scores: ``in_domain_reframed`` puts the in-domain images in 4:3 and 3:4 frames
(mirrored borders): the same objects, other frames; ``in_domain_rotated`` turns them by
quarter turns (boxes exact): the same objects, any camera roll.

JSON out: the mAPs, the out-of-domain / in-domain ratio of each out-of-domain set (the goal,
≥ 0.8, is met only when every one reaches it), each set's class-agnostic mAP (any
class at a target counts: finding the sheet apart from naming it), the out-of-domain breakdown by scene
kind (negatives, small / medium / large / frame-filling sheets, occluded, several targets),
the time each part took and the machine.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from bench import panoramas  # noqa: E402  (no heavy imports: paths and a derivation run by hand)

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


def _scene_kind(objects, fill: float, negative: bool) -> str:
    if negative:
        return "negative"
    if len(objects) > 1:
        return "several"
    if objects[0][2] < 0.8:
        return "occluded"
    return "small" if fill < 0.25 else "medium" if fill < 0.6 else "large" if fill < 1.0 else "frame-filling"


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


def make_ood_set(out: Path, recipe: OodRecipe, echo=print, assets=None, lookalikes: Path | None = None) -> Path:
    """Render the out-of-domain set into ``out`` (COCO folder) unless the same recipe is there
    (``assets``, ``lookalikes``: where the textures of ``recipe.classes`` and ``recipe.lookalikes`` are)."""
    import cv2

    out = Path(out)
    manifest = out / "annotations.json"
    if manifest.is_file() and json.loads(manifest.read_text()).get("info", {}).get("recipe") == recipe.key():
        echo(f"out-of-domain set: reusing {out} (recipe {recipe.key()})")
        return out
    (out / "images").mkdir(parents=True, exist_ok=True)
    scene = OodScene(
        load_textures(recipe.classes, recipe.photos, assets, lookalikes if recipe.lookalikes else None), recipe
    )
    rng = np.random.default_rng(recipe.seed)
    images, annotations = [], []
    started = time.perf_counter()
    redraws = 0
    for index in range(recipe.n):
        negative = bool(rng.random() < recipe.negatives)
        seed = int(rng.integers(0, 2**62))
        for attempt in range(20):
            result = scene.render(seed + attempt, negative)
            if result is not None:
                break
            redraws += 1
        else:
            raise RuntimeError(f"out-of-domain image {index}: no valid scene in 20 draws")
        image, objects, info = result
        file_name = f"images/wild_{index:05d}.jpg"
        cv2.imwrite(str(out / file_name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 97])
        kind = _scene_kind(objects, info["fill"], negative)
        images.append(
            {
                "id": index + 1,
                "file_name": file_name,
                "width": recipe.width,
                "height": recipe.height,
                "condition": "wild",
                "difficulty": kind,
                "scene": info,
            }
        )
        for name, box, fraction in objects:
            x0, y0, x1, y1 = box
            annotations.append(
                {
                    "id": len(annotations) + 1,
                    "image_id": index + 1,
                    "category_id": recipe.classes.index(name) + 1,
                    "bbox": [x0, y0, x1 - x0, y1 - y0],
                    "area": (x1 - x0) * (y1 - y0),
                    "iscrowd": 0,
                    "visible_fraction": fraction,
                }
            )
        if (index + 1) % 25 == 0:
            echo(f"out-of-domain: {index + 1}/{recipe.n} images, {time.perf_counter() - started:.0f} s")
    coco = {
        "info": {
            "description": "foldwise out-of-domain benchmark set (bench/wild.py)",
            "recipe": recipe.key(),
            "recipe_fields": asdict(recipe),
            "redraws": redraws,
            "seconds": time.perf_counter() - started,
        },
        "images": images,
        "annotations": annotations,
        "categories": [{"id": i + 1, "name": name} for i, name in enumerate(recipe.classes)],
    }
    manifest.write_text(json.dumps(coco, indent=1))
    echo(
        f"out-of-domain: wrote {recipe.n} images to {out} in {time.perf_counter() - started:.0f} s ({redraws} redraws)"
    )
    return out


# --------------------------------------------------------------------------- training and scoring


def train_with_config(config_path: Path, data_dir: Path, echo=print, members: int = 1) -> tuple[Path, dict]:
    """Run ``foldwise run CONFIG --members N`` in a data directory of its own; return the final
    model's checkpoint (with several members, the ensemble file the run hands over)."""
    env = {**os.environ, "FOLDWISE_DATA_DIR": str(data_dir), "FOLDWISE_DATABASE_URL": ""}
    env.pop("FOLDWISE_DATABASE_URL")
    started = time.perf_counter()
    completed = subprocess.run(
        [sys.executable, "-m", "services.cli", "run", str(config_path), "--members", str(members)],
        cwd=ROOT, env=env, capture_output=True, text=True,
    )  # fmt: skip
    seconds = time.perf_counter() - started
    if completed.returncode != 0:
        raise RuntimeError(
            f"foldwise run {config_path} failed ({completed.returncode}):\n{completed.stdout[-3000:]}{completed.stderr[-3000:]}"
        )
    echo(f"trained {config_path} in {seconds:.0f} s")
    training = {"config": str(config_path), "members": members, "seconds": seconds}
    if members > 1:
        ensembles = sorted((data_dir / "studies").glob("*/ensemble.pt"), key=lambda path: path.stat().st_mtime)
        if not ensembles:
            raise RuntimeError(f"{config_path}: the run finished without an ensemble file under {data_dir / 'studies'}")
        return ensembles[-1], training
    import sqlite3

    with sqlite3.connect(data_dir / "foldwise.db") as connection:
        row = connection.execute(
            "SELECT m.checkpoint_path FROM experiments e JOIN models m ON m.id = e.final_model_id ORDER BY e.id DESC LIMIT 1"
        ).fetchone()
    if row is None or not row[0]:
        raise RuntimeError(f"{config_path}: the experiment finished without a final model")
    checkpoint = Path(row[0])
    if not checkpoint.is_absolute():
        checkpoint = data_dir / checkpoint
    return checkpoint, training


def make_run_members(config_path: Path) -> int:
    """The curricula ``make run`` trains for this config (the Makefile's MEMBERS default)."""
    return 2 if Path(config_path).resolve() == (ROOT / "configs" / "quick.yaml").resolve() else 1


def make_in_domain_set(config, out: Path, n_per_pair: int, seed: int, echo=print) -> Path:
    """foldwise's own renders of the config's curriculum (every stage, mixed included).

    The cache key holds what the renders depend on (the curriculum's conditions and
    difficulties, the render size and backend, the assets, the count and the seed), not the rest
    of the config: two configs that differ in their detector or training score on one set."""
    from workers.render.assets import load_assets
    from workers.render.cli import render_dataset

    stages = config.stage_order()
    conditions = sorted(
        {condition for condition, _ in stages if condition != "canonical"}, key=[c for c, _ in stages].index
    )
    difficulties = list(config.curriculum.difficulties)
    recipe = [
        conditions,
        difficulties,
        config.render.image_size,
        config.render.backend,
        config.assets.model_dump(mode="json"),
        n_per_pair,
        seed,
    ]
    key = hashlib.sha256(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:16]
    manifest = out / "annotations.json"
    if manifest.is_file() and json.loads(manifest.read_text()).get("info", {}).get("recipe") == key:
        echo(f"in-domain set: reusing {out}")
        return out
    assets = load_assets(config.assets)
    coco = render_dataset(
        out,
        conditions,
        difficulties,
        n_per_pair,
        seed,
        config.render.image_size,
        config.render.backend,
        assets,
        echo=lambda *_: None,
    )
    coco["info"]["recipe"] = key
    manifest.write_text(json.dumps(coco, indent=1))
    echo(f"in-domain set: {len(coco['images'])} images ({', '.join(conditions)} × {', '.join(difficulties)})")
    return out


def make_reframed_set(source: Path, out: Path) -> Path:
    """foldwise's own renders in other frames: each square image padded (mirrored edges) to 4:3
    landscape or, every other image, 3:4 portrait, boxes moved with it. The objects are the
    in-domain ones; only the frame changes, which tells framing apart from appearance."""
    import cv2

    document = json.loads((source / "annotations.json").read_text())
    (out / "images").mkdir(parents=True, exist_ok=True)
    shifts = {}
    for index, image in enumerate(document["images"]):
        pixels = cv2.imread(str(source / image["file_name"]), cv2.IMREAD_COLOR)
        height, width = pixels.shape[:2]
        if index % 2 == 0:  # landscape: pad left and right
            extra = int(round(width * 4 / 3)) - width
            left, top = extra // 2, 0
            framed = cv2.copyMakeBorder(pixels, 0, 0, left, extra - left, cv2.BORDER_REFLECT)
        else:  # portrait: pad top and bottom
            extra = int(round(height * 4 / 3)) - height
            left, top = 0, extra // 2
            framed = cv2.copyMakeBorder(pixels, top, extra - top, 0, 0, cv2.BORDER_REFLECT)
        cv2.imwrite(str(out / image["file_name"]), framed)
        image["height"], image["width"] = framed.shape[:2]
        shifts[image["id"]] = (left, top)
    for annotation in document["annotations"]:
        left, top = shifts[annotation["image_id"]]
        annotation["bbox"][0] += left
        annotation["bbox"][1] += top
        annotation.pop("amodal_bbox", None)
    (out / "annotations.json").write_text(json.dumps(document))
    return out


def make_rotated_set(source: Path, out: Path) -> Path:
    """foldwise's own renders turned by a quarter, a half and three quarters of a turn (in
    turn, image by image), boxes turned with them exactly. A camera held at any roll sees the
    sheet at any in-plane angle; the renderer turns the sheet only where a condition draws a
    rotation, so this tells whether the detector learned the object or its upright look."""
    import cv2

    document = json.loads((source / "annotations.json").read_text())
    (out / "images").mkdir(parents=True, exist_ok=True)
    turns = {}
    for index, image in enumerate(document["images"]):
        pixels = cv2.imread(str(source / image["file_name"]), cv2.IMREAD_COLOR)
        quarter = index % 3 + 1  # counter-clockwise quarter turns
        cv2.imwrite(str(out / image["file_name"]), np.ascontiguousarray(np.rot90(pixels, quarter)))
        turns[image["id"]] = (quarter, image["width"], image["height"])
        if quarter % 2:
            image["width"], image["height"] = image["height"], image["width"]
    for annotation in document["annotations"]:
        quarter, width, height = turns[annotation["image_id"]]
        x, y, w, h = annotation["bbox"]
        for _ in range(quarter):  # one counter-clockwise quarter turn: (x, y) -> (y, width - x)
            x, y, w, h = y, width - x - w, h, w
            width, height = height, width
        annotation["bbox"] = [x, y, w, h]
        annotation.pop("amodal_bbox", None)
        annotation.pop("segmentation", None)
    (out / "annotations.json").write_text(json.dumps(document))
    return out


def class_agnostic(predictions: list[dict], ground_truth: list[dict]) -> tuple[list[dict], list[dict]]:
    """The same detections and boxes with every class merged into one ("the object"): a box of
    any class at a target counts, and boxes of several classes at one place are suppressed to
    the best (IoU 0.5) so that they are not counted as false positives of each other. Scored
    beside the class-aware mAP, it splits "does not find the sheet" from "names it wrong"."""
    import torch
    from torchvision.ops import nms

    merged = []
    for prediction in predictions:
        boxes, scores = torch.as_tensor(prediction["boxes"]), torch.as_tensor(prediction["scores"])
        keep = nms(boxes, scores, 0.5).numpy() if len(boxes) else np.zeros(0, np.int64)
        merged.append(
            {
                "boxes": prediction["boxes"][keep],
                "scores": prediction["scores"][keep],
                "labels": np.zeros(len(keep), np.int64),
            }
        )
    truth = [{"boxes": item["boxes"], "labels": np.zeros(len(item["labels"]), np.int64)} for item in ground_truth]
    return merged, truth


def _at_threshold(predictions, truth, classes, score_threshold: float, iou_threshold: float) -> dict:
    """What a user who draws every box scoring at least ``score_threshold`` sees
    (``precision_recall_at``, the mAP's matching): precision, recall, and the counts."""
    from workers.train.evaluation import precision_recall_at

    result = precision_recall_at(predictions, truth, classes, score_threshold, iou_threshold)
    drawn = result.true_positives + result.false_positives
    targets = result.true_positives + result.false_negatives
    return {
        "precision": result.precision if drawn else None,
        "recall": result.recall if targets else None,
        "drawn": drawn,
        "true": result.true_positives,
        "targets": targets,
    }


def _scores(
    predictions, truth, model_classes, groups, score_threshold: float, iou_threshold: float, seconds: float
) -> dict:
    """One detector's report on one set: the paper's mAP (and unthresholded), class-agnostic mAP,
    per class and per scene kind, what a user drawing boxes at the threshold sees, and time."""
    from workers.train.evaluation import evaluate_predictions

    protocol = {"score_threshold": score_threshold, "iou_threshold": iou_threshold, "coco": False}
    payload = evaluate_predictions(predictions, truth, model_classes, groups=groups, **protocol).to_dict()
    agnostic = evaluate_predictions(*class_agnostic(predictions, truth), ["object"], **protocol).to_dict()
    by_kind = {
        name: {
            "map": group.get("map"),
            "map_unthresholded": group.get("map_unthresholded"),
            "images": group.get("num_images"),
        }
        for name, group in payload.get("breakdown", {}).get("difficulty", {}).items()
    }
    return {
        "images": len(truth),
        "map": payload["map"],
        "map_unthresholded": payload["map_unthresholded"],
        "at_threshold": _at_threshold(predictions, truth, model_classes, score_threshold, iou_threshold),
        "class_agnostic": {"map": agnostic["map"], "map_unthresholded": agnostic["map_unthresholded"]},
        "per_class": {name: entry.get("ap") for name, entry in payload["per_class"].items()},
        "by_kind": by_kind,
        "seconds": seconds,
        "seconds_per_image": seconds / max(len(truth), 1),
    }


def score_keypoint_baseline(textures: dict, data: Path, score_threshold: float, iou_threshold: float) -> dict:
    """The keypoint recipe (bench/keypoint_baseline.py) on a COCO folder, scored as ``score`` scores foldwise."""
    from bench.keypoint_baseline import KeypointBaseline
    from workers.train.data import load_coco_dataset, read_image_rgb

    samples, classes = load_coco_dataset(data)
    baseline = KeypointBaseline(textures, classes)
    started = time.perf_counter()
    predictions = [baseline.detect(read_image_rgb(sample.image_path)) for sample in samples]
    seconds = time.perf_counter() - started
    truth = [{"boxes": sample.boxes, "labels": np.asarray(sample.labels, np.int64)} for sample in samples]
    groups = [{"condition": sample.condition, "difficulty": sample.difficulty} for sample in samples]
    return _scores(predictions, truth, classes, groups, score_threshold, iou_threshold, seconds)


def score(
    checkpoint, data: Path, score_threshold: float, iou_threshold: float, test_sizes=None, test_turns=None
) -> dict:
    """The detector's scores on a COCO folder. ``checkpoint``: one path, or a list of paths whose
    detectors are scored as one (``workers.train.checkpoint.detect_ensemble``)."""
    from workers.train.checkpoint import load_detector
    from workers.train.data import load_coco_dataset
    from workers.train.evaluation import detector_predictions

    samples, classes = load_coco_dataset(data)
    checkpoints = [checkpoint] if isinstance(checkpoint, (str, Path)) else list(checkpoint)
    detectors = [load_detector(path, device="cpu") for path in checkpoints]
    started = time.perf_counter()
    predictions, truth, groups, model_classes = detector_predictions(
        detectors, samples, classes, test_sizes=test_sizes, test_turns=test_turns
    )
    return _scores(
        predictions, truth, model_classes, groups, score_threshold, iou_threshold, time.perf_counter() - started
    )


def _config_argument(parser_name: str):
    """An argparse ``type`` that reads a list as ``foldwise.config.<parser_name>`` does (imported
    when an argument is read, so ``--help`` stays cheap); its error is argparse's message."""

    def read(text: str) -> tuple[int, ...]:
        from foldwise import config

        try:
            return getattr(config, parser_name)(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    return read


def _positive_count(text: str) -> int:
    """An argparse ``type`` for the first set's size: 0 would replace a cached set by an empty one."""
    try:
        count = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if count < 1:
        raise argparse.ArgumentTypeError(f"{count}: the first out-of-domain set needs at least 1 image")
    return count


def _frame_argument(text: str) -> tuple[int, int]:
    """An argparse ``type`` for WIDTHxHEIGHT (every set's ``--…-size``): a bad one is argparse's message."""
    try:
        width, height = (int(value) for value in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT, e.g. 320x240") from None
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: width and height must be at least 1 pixel")
    return width, height


_test_sizes_argument = _config_argument("parse_test_sizes")
_test_turns_argument = _config_argument("parse_test_turns")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=ROOT / "configs/quick.yaml")
    parser.add_argument(
        "--model",
        type=Path,
        action="append",
        help="score this checkpoint instead of training; given again, the checkpoints are scored as one ensemble",
    )
    parser.add_argument(
        "--members",
        type=_positive_count,
        default=None,
        help="when training: curricula side by side, handed over as one ensemble (default: make run's, "
        "2 for configs/quick.yaml, else 1)",
    )
    parser.add_argument("--n-ood", type=_positive_count, default=200, help="out-of-domain images (at least 1)")
    parser.add_argument(
        "--ood-size", type=_frame_argument, default="320x240", help="WIDTHxHEIGHT of out-of-domain images"
    )
    parser.add_argument("--ood-samples", type=int, default=24, help="Cycles samples per out-of-domain image")
    parser.add_argument("--ood-seed", type=int, default=2026)
    parser.add_argument("--ood-dir", type=Path, default=None, help="default: var/bench/wild-ood[-FACTORS]")
    # A second out-of-domain set, drawn apart (its own seed, larger frames), so that no lever is
    # chosen on one set of draws alone: the goal is met only when both ratios reach it.
    parser.add_argument(
        "--n-ood-second", type=int, default=100, help="images of the second out-of-domain set (0: none)"
    )
    parser.add_argument(
        "--ood-second-size", type=_frame_argument, default="480x360", help="WIDTHxHEIGHT of the second set's images"
    )
    parser.add_argument("--ood-second-seed", type=int, default=7)
    parser.add_argument("--ood-second-dir", type=Path, default=None, help="default: var/bench/wild-ood-b[-FACTORS]")
    # A third set whose ground and clutter photographs no training path uses (PHOTO_POOLS): the
    # first two reuse foldwise's own background and occluder photographs.
    parser.add_argument(
        "--n-ood-apart", type=int, default=100, help="images of the held-apart-photographs set (0: none)"
    )
    parser.add_argument(
        "--ood-apart-size", type=_frame_argument, default="320x240", help="WIDTHxHEIGHT of that set's images"
    )
    parser.add_argument("--ood-apart-seed", type=int, default=11)
    parser.add_argument("--ood-apart-dir", type=Path, default=None, help="default: var/bench/wild-ood-apart[-FACTORS]")
    # A fourth, on request: larger frames (photographs are rarely as small as 320x240; a sheet then
    # holds more pixels for the network's larger views and for SIFT). Off by default: Cycles takes
    # about 10 min for 100 images at 640x480 on 2 cores.
    parser.add_argument("--n-ood-large", type=int, default=0, help="images of the large-frame set (0: none; e.g. 100)")
    parser.add_argument(
        "--ood-large-size", type=_frame_argument, default="640x480", help="WIDTHxHEIGHT of that set's images"
    )
    parser.add_argument("--ood-large-seed", type=int, default=13)
    parser.add_argument("--ood-large-dir", type=Path, default=None, help="default: var/bench/wild-ood-large[-FACTORS]")
    # The hard set: small sheets, tubes and creases, lookalikes (with --lookalikes), extremes of
    # exposure and light colour, uneven ground, JPEG down to 35 (OodRecipe.hard).
    parser.add_argument("--n-ood-hard", type=int, default=100, help="images of the hard set (0: none)")
    parser.add_argument(
        "--ood-hard-size", type=_frame_argument, default="480x360", help="WIDTHxHEIGHT of that set's images"
    )
    parser.add_argument("--ood-hard-seed", type=int, default=17)
    parser.add_argument("--ood-hard-dir", type=Path, default=None, help="default: var/bench/wild-ood-hard[-FACTORS]")
    parser.add_argument(
        "--lookalikes",
        type=Path,
        default=None,
        help="a folder of printed sheets of the targets' kind that are none of them (bench/printed_documents.py "
        "writes one): one to three lie beside the targets in every out-of-domain image",
    )
    parser.add_argument(
        "--no-baseline",
        action="store_true",
        help="skip the keypoint recipe (bench/keypoint_baseline.py) scored beside foldwise on every set",
    )
    parser.add_argument(
        "--factors",
        default="all",
        help=f"which parts of the scene are wild: all, none, or a comma list of {','.join(FACTORS)} (the rest plain)",
    )
    parser.add_argument("--n-in-domain", type=int, default=6, help="in-domain images per (condition, difficulty)")
    parser.add_argument("--in-domain-dir", type=Path, default=None)
    parser.add_argument("--train-dir", type=Path, default=None, help="data directory for the training run")
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument(
        "--test-sizes",
        type=_test_sizes_argument,
        help="comma list of inference sizes to score at (default: the model's detector.test_sizes)",
    )
    parser.add_argument(
        "--test-turns",
        type=_test_turns_argument,
        help="comma list of quarter turns to detect on too, e.g. 0 for upright only (default: the model's detector.test_turns)",
    )
    parser.add_argument("--out", type=Path)
    parser.add_argument(
        "--sets-only",
        action="store_true",
        help="render (or find) the benchmark's sets, report where they are, and stop: no training, no scoring",
    )
    args = parser.parse_args(argv)

    from foldwise.config import load_config

    def echo(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    config = load_config(args.config)
    from workers.render.assets import load_assets

    classes = tuple(load_assets(config.assets).classes)
    lookalikes = lookalike_names(args.lookalikes)
    width, height = args.ood_size
    factors = FACTORS if args.factors == "all" else () if args.factors == "none" else tuple(args.factors.split(","))
    recipe = OodRecipe(
        n=args.n_ood,
        width=width,
        height=height,
        samples=args.ood_samples,
        seed=args.ood_seed,
        classes=classes,
        factors=factors,
        lookalikes=lookalikes,
    )
    suffix = "" if factors == FACTORS else "-" + ("-".join(factors) or "plain")
    if args.ood_dir is None:
        args.ood_dir = ROOT / f"var/bench/wild-ood{suffix}"
    # Each out-of-domain set: (report key suffix, recipe, folder); a set of 0 images is skipped.
    ood_sets = [("", recipe, args.ood_dir)]
    for name, n, (frame_width, frame_height), seed, folder, photos in (
        ("second", args.n_ood_second, args.ood_second_size, args.ood_second_seed, args.ood_second_dir, "training"),
        ("apart", args.n_ood_apart, args.ood_apart_size, args.ood_apart_seed, args.ood_apart_dir, "held_apart"),
        ("large", args.n_ood_large, args.ood_large_size, args.ood_large_seed, args.ood_large_dir, "training"),
        ("hard", args.n_ood_hard, args.ood_hard_size, args.ood_hard_seed, args.ood_hard_dir, "held_apart"),
    ):
        if n:
            extra = OodRecipe(
                n=n,
                width=frame_width,
                height=frame_height,
                samples=args.ood_samples,
                seed=seed,
                classes=classes,
                factors=factors,
                photos=photos,
                lookalikes=lookalikes,
                hard=name == "hard",
            )
            default_folder = ROOT / f"var/bench/wild-ood-{'b' if name == 'second' else name}{suffix}"
            ood_sets.append((f"_{name}", extra, folder or default_folder))

    report: dict = {
        "config": str(args.config),
        "protocol": {"score_threshold": args.threshold, "iou_threshold": args.iou},
    }
    ood_dirs = []
    for key, set_recipe, folder in ood_sets:
        started = time.perf_counter()
        ood_dirs.append(make_ood_set(folder, set_recipe, echo, assets=config.assets, lookalikes=args.lookalikes))
        report[f"ood_set{key}"] = {
            "dir": str(ood_dirs[-1]),
            "recipe": asdict(set_recipe),
            "seconds": time.perf_counter() - started,
        }

    in_domain_dir = args.in_domain_dir or ROOT / f"var/bench/wild-in-domain-{config.name}"
    make_in_domain_set(config, in_domain_dir, args.n_in_domain, seed=config.seed + 7919, echo=echo)
    reframed_dir = make_reframed_set(in_domain_dir, in_domain_dir.with_name(in_domain_dir.name + "-reframed"))
    rotated_dir = make_rotated_set(in_domain_dir, in_domain_dir.with_name(in_domain_dir.name + "-rotated"))
    if args.sets_only:
        report["in_domain_set"] = {
            "dir": str(in_domain_dir),
            "reframed": str(reframed_dir),
            "rotated": str(rotated_dir),
        }
        return write_report(report, args.out)

    checkpoint = args.model  # several: scored as one ensemble
    if checkpoint is None:
        train_dir = args.train_dir or Path(tempfile.mkdtemp(prefix="foldwise-wild-train-"))
        members = args.members or make_run_members(args.config)
        trained, training = train_with_config(args.config, train_dir, echo, members=members)
        report["training"] = training
        checkpoint = [trained]
    report["model"] = str(checkpoint[0]) if len(checkpoint) == 1 else [str(path) for path in checkpoint]
    report["test_sizes"] = list(args.test_sizes) if args.test_sizes is not None else "the model's"
    report["test_turns"] = list(args.test_turns) if args.test_turns is not None else "the model's"
    views = {"test_sizes": args.test_sizes, "test_turns": args.test_turns}

    textures = load_assets(config.assets).textures(classes)

    def baseline(data: Path) -> dict | None:
        return None if args.no_baseline else score_keypoint_baseline(textures, data, args.threshold, args.iou)

    report["in_domain"] = score(checkpoint, in_domain_dir, args.threshold, args.iou, **views)
    report["baseline_in_domain"] = baseline(in_domain_dir)
    report["in_domain_reframed"] = score(checkpoint, reframed_dir, args.threshold, args.iou, **views)
    report["in_domain_rotated"] = score(checkpoint, rotated_dir, args.threshold, args.iou, **views)
    in_map = report["in_domain"]["map"]
    ratios = []
    for (key, _recipe, _folder), ood_dir in zip(ood_sets, ood_dirs):
        report[f"out_of_domain{key}"] = score(checkpoint, ood_dir, args.threshold, args.iou, **views)
        report[f"baseline_out_of_domain{key}"] = baseline(ood_dir)
        report[f"ratio{key}"] = None if not in_map else report[f"out_of_domain{key}"]["map"] / in_map
        if key != "_hard":  # the hard set has a goal of its own (its mAP), not a ratio to in domain
            ratios.append(report[f"ratio{key}"])
    report["goal"] = {"ratio_at_least": 0.8, "met": all(ratio is not None and ratio >= 0.8 for ratio in ratios)}
    report["machine"] = machine()
    return write_report(report, args.out)


def machine() -> dict:
    """The CPU, its core count, Python's version, the date and the commit, for a report's ``machine``."""
    import datetime

    from bench.render import cpu_model

    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = None
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "commit": commit,
    }


def write_report(report: dict, out: Path | None) -> dict:
    """The report as JSON on stdout, and in ``out`` where given."""
    text = json.dumps(report, indent=2, default=float)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    print(text)
    return report


if __name__ == "__main__":
    main()
