"""θ → image and ground truth: sheets, scene, 3D backend, 2D stages, annotation.

``render_theta`` runs, in order (each stage timed in ``RenderResult.timings``, in seconds):

1. ``sheet``: the deformed sheet (``paper_model.sample_sheet`` with θ's rulings and bend
   smoothness, from θ's seed); a self-intersecting sheet is a rejection;
2. ``scene``: pose and orientation, scale, lens, camera and light (camera.py);
3. ``lights`` (θ's light, gloss, wrinkle or shadow parameters not canonical): the light rig,
   the highlight's light, the wrinkles' normal map, the shadow caster (lighting.py);
4. ``frame_crop`` (θ.frame_crop > 0): the principal point moves so that the asked share of the
   sheet leaves the frame (camera.frame_shift);
5. ``render``: the 3D backend, ``raster`` (raster.py) or ``blender`` (blender.py);
6. ``instances`` (θ.instances ≠ 1): every target sheet placed and rendered as its own layer
   (layers.py); none for an image without the object;
7. ``clutter`` (θ.clutter > 0, or lookalike sheets in the assets): the distractors and
   lookalikes, each its own layer (layers.py);
8. ``amodal``: each target's whole silhouette, off-image part included (for the amodal box and
   the visible fraction);
9. ``occlusion`` (θ's visible fraction < 1): place the occluder on the first target; a
   placement more than ``OCCLUSION_TOLERANCE`` from θ's visible fraction is a rejection;
10. ``annotation``: per target, visible box, amodal box, visible fraction (hidden by later
    layers and the occluder); rejects an unusable target;
11. ``background``: sRGB encoding of the layers and alpha compositing over the background in
    depth order; the occluder goes on top;
12. ``distortion`` (θ.distortion ≠ 0), ``focus_blur`` then ``motion_blur`` (kernels of at least
    2 pixels), ``noise`` (θ.noise_sigma > 0): the camera's 2D stages (imaging.py, blur.py);
13. ``encode``: to uint8, then ``jpeg`` (θ.jpeg_quality < 100). ``total`` covers everything.
    An image with one sheet and none of the float stages composites and encodes only the box
    where the object or occluder is drawn, inside ``background`` (no ``encode`` entry); the
    bytes are the same.

A stage whose parameters are canonical does no work and has no timing entry, so a θ of
version 1 (Table 3 alone) renders exactly as it did before version 2 existed. Everything
random comes from θ's seed, split by purpose, so a θ renders to the same bytes.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from foldwise.sampling import check_theta, resample_theta
from foldwise.seeds import derive_seed
from foldwise.theta import Theta
from workers.render.annotation import RenderRejected, annotate

__all__ = [
    "RenderResult",
    "ObjectAnnotation",
    "RenderRejected",
    "render_theta",
    "render_with_resample",
    "compile_kernels",
    "BACKENDS",
]

BACKENDS = ("raster", "blender")
# How far the achieved visible fraction may be from θ's before the placement is rejected.
OCCLUSION_TOLERANCE = 0.05
# A front distractor may hide at most this share of what a target still shows.
MAX_CLUTTER_HIDING = 0.5
# Independent random streams drawn from θ's seed, one per purpose.
_SHEET, _BACKGROUND, _OCCLUDER, _LIGHTS, _WRINKLES, _SHADOW, _INSTANCES, _CLUTTER, _NOISE = range(1, 10)


@dataclass
class ObjectAnnotation:
    """One target sheet of an image: what a detector must find."""

    object: str
    label: int  # 0-based class index of the object
    box: list[float]  # [x0, y0, x1, y1] pixel edges, visible part after occlusion and border crop
    amodal_box: list[float]  # the whole silhouette's box, may extend past the image
    visible_fraction: float  # visible pixels / amodal pixels

    def to_dict(self) -> dict:
        return {
            "object": self.object,
            "label": int(self.label),
            "box": [float(v) for v in self.box],
            "amodal_box": [float(v) for v in self.amodal_box],
            "visible_fraction": float(self.visible_fraction),
        }


@dataclass
class RenderResult:
    image: np.ndarray  # (H, W, 3) uint8 RGB
    objects: list[ObjectAnnotation]  # the targets, θ's own object first; empty: no object
    timings: dict[str, float] = field(default_factory=dict)
    masks: list[np.ndarray] = field(default_factory=list)  # (H, W) bool visible mask per object

    # The first object's annotation (None for an image without the object).
    @property
    def box(self) -> list[float] | None:
        return self.objects[0].box if self.objects else None

    @property
    def amodal_box(self) -> list[float] | None:
        return self.objects[0].amodal_box if self.objects else None

    @property
    def visible_fraction(self) -> float | None:
        return self.objects[0].visible_fraction if self.objects else None

    @property
    def label(self) -> int | None:
        return self.objects[0].label if self.objects else None

    @property
    def mask(self) -> np.ndarray | None:
        return self.masks[0] if self.masks else None


@dataclass
class _Layer:
    """A drawn sheet or shape: linear RGB (sheets) or sRGB (shapes) colour, coverage, mask."""

    rgb: np.ndarray
    alpha: np.ndarray
    mask: np.ndarray
    linear: bool = True
    target: int | None = None  # index of the target it shows, None for a distractor
    scene: object | None = None  # the Scene3D of a sheet (amodal extent, occluder placement)
    object: str | None = None  # the object a target shows


def _paper_model():
    from workers.render import paper_model

    return paper_model


def _rng(theta: Theta, purpose: int) -> np.random.Generator:
    return np.random.default_rng(derive_seed(int(theta.seed), purpose))


def _backend_render(scene, backend: str, samples: int, device: str = "CPU"):
    if backend == "raster":
        from workers.render.raster import render_scene

        return render_scene(scene)
    if backend == "blender":
        from workers.render.blender import get_renderer

        return get_renderer(samples=samples, device=device).render(scene)
    raise ValueError(f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}")


def _sheet_mesh(rulings: int, smooth_steps: int, rng: np.random.Generator, texture: np.ndarray):
    """The bent sheet of a texture's aspect, or RenderRejected."""
    from workers.render.camera import sheet_size

    paper_model = _paper_model()
    width_m, height_m = sheet_size(texture.shape)
    # The default smoothness goes through the model's default options (cached per sheet size).
    options = {} if smooth_steps == 3 else {"smooth_steps": int(smooth_steps)}
    try:
        return paper_model.sample_sheet(int(rulings), rng, width_m, height_m, **options), (width_m, height_m)
    except paper_model.SelfIntersection as error:
        raise RenderRejected(f"self-intersecting sheet: {error}") from None
    except ValueError as error:  # no valid ruling layout found for this draw
        raise RenderRejected(f"sheet layout failed: {error}") from None


def _shading(theta: Theta, scene, mesh_size, rng_lights, rng_wrinkles, rng_shadow):
    """``scene`` with θ's lights, gloss, wrinkles and shadow (lighting.py); the shading terms
    (lights, ambient, specular, roughness) every other sheet of the image shares."""
    from workers.render import lighting
    from workers.render.camera import sheet_rotation

    lights, ambient = lighting.light_rig(theta, rng_lights) if _uses_light_rig(theta) else (None, (0.0, 0.0, 0.0))
    if theta.specular > 0 and lights is not None:
        centre = -scene.camera.R.T @ scene.camera.t
        towards = lighting.highlight_direction(scene.vertices, scene.faces, centre, rng_lights)
        if towards is not None:
            lights = (dataclasses.replace(lights[0], direction=towards),) + lights[1:]
    shared = {
        "lights": lights,
        "ambient": ambient,
        "specular": float(theta.specular),
        "roughness": float(theta.roughness),
    }
    normal_map = None
    if theta.wrinkles and theta.wrinkle_depth:
        normal_map = lighting.wrinkle_normal_map(theta.wrinkles, theta.wrinkle_depth, *mesh_size, rng_wrinkles)
    shadow = None
    if theta.shadow > 0:
        key = scene.light_list()[0] if lights is None else lights[0]
        rotation = sheet_rotation(theta.roll, theta.pitch, theta.yaw, theta.rotation, theta.tilt, theta.tilt_azimuth)
        shadow = lighting.shadow_caster(theta.shadow, *mesh_size, rotation, theta.scale, key.direction, rng_shadow)
    return dataclasses.replace(scene, normal_map=normal_map, shadow=shadow, **shared), shared


def _uses_light_rig(theta: Theta) -> bool:
    return bool(
        theta.light_count != 1 or theta.light_saturation or theta.light_spread or theta.ambient or theta.specular
    )


def _uses_lighting(theta: Theta) -> bool:
    return _uses_light_rig(theta) or bool((theta.wrinkles and theta.wrinkle_depth) or theta.shadow)


def _sheet_scene(placement, mesh, texture, camera, shared: dict, image_size: int, irradiance: float):
    from workers.render.camera import build_scene

    scene = build_scene(
        mesh.vertices,
        mesh.faces,
        mesh.uv,
        texture,
        image_size=image_size,
        roll=placement.roll,
        pitch=placement.pitch,
        yaw=placement.yaw,
        scale=placement.scale,
        irradiance=irradiance,
        rotation=placement.rotation,
        tilt=placement.tilt,
        tilt_azimuth=placement.tilt_azimuth,
        translation=placement.translation,
        camera=camera,
    )
    return dataclasses.replace(scene, **shared) if shared else scene


def _instance_layers(theta: Theta, scene, shared: dict, assets, render) -> list[_Layer]:
    """θ's target sheets when it shows ``instances`` ≠ 1 of them (layers.py), far first."""
    from workers.render.layers import instance_placements

    if theta.instances == 0:
        return []
    layers = []
    for index, placement in enumerate(
        instance_placements(theta, scene.camera, assets.classes, _rng(theta, _INSTANCES))
    ):
        texture = assets.texture(placement.object)
        mesh, _ = _sheet_mesh(placement.rulings, theta.smooth_steps, np.random.default_rng(placement.seed), texture)
        sheet = _sheet_scene(placement, mesh, texture, scene.camera, shared, theta.image_size, theta.irradiance)
        if index == 0 and scene.normal_map is not None:
            sheet = dataclasses.replace(sheet, normal_map=scene.normal_map)  # θ's wrinkles are its own object's
        output = render(sheet)
        if not output.mask.any():
            raise RenderRejected(f"target instance {index} outside the view: no pixel centre falls on it")
        layers.append(_Layer(output.rgb, output.alpha, output.mask, target=index, scene=sheet, object=placement.object))
    return sorted(layers, key=lambda layer: layer.scene.vertices[:, 2].mean())


def _clutter_layers(theta: Theta, scene, shared: dict, assets, render, size: int) -> tuple[list[_Layer], list[_Layer]]:
    """θ's distractors (layers.py): those behind the targets (far first, flat shapes on the
    background first) and those in front of them (far first)."""
    import cv2

    from workers.render.assets import random_crop
    from workers.render.layers import SheetPlacement, distractor_placements
    from workers.render.occluders import random_shape

    behind: list[tuple[float, _Layer]] = []
    front: list[tuple[float, _Layer]] = []
    placements = distractor_placements(
        theta, scene.camera, assets.distractors, _rng(theta, _CLUTTER), lookalikes=assets.lookalike_sheets
    )
    for placement in placements:
        rng = np.random.default_rng(placement.seed)
        texture = assets.distractor(placement.texture, rng)
        if isinstance(placement, SheetPlacement):
            try:
                mesh, _ = _sheet_mesh(placement.rulings, 3, rng, texture)
            except RenderRejected:
                continue  # a distractor that cannot bend so is simply left out
            sheet = _sheet_scene(placement, mesh, texture, scene.camera, shared, size, theta.irradiance)
            output = render(sheet)
            if not output.mask.any():
                continue
            layer = _Layer(output.rgb, output.alpha, output.mask, scene=sheet)
            depth = float(sheet.vertices[:, 2].mean())
        else:
            side = max(int(round(placement.side)), 4)
            patch = random_crop(texture, side, rng).astype(np.float32) / np.float32(255.0)
            shape = random_shape(rng, side, side).astype(np.float32) / np.float32(255.0)
            matrix = cv2.getRotationMatrix2D((side / 2.0, side / 2.0), float(np.degrees(placement.angle)), 1.0)
            matrix[:, 2] += np.asarray(placement.centre) - side / 2.0
            rgb = cv2.warpAffine(patch, matrix, (size, size), flags=cv2.INTER_LINEAR)
            alpha = cv2.warpAffine(shape, matrix, (size, size), flags=cv2.INTER_LINEAR)
            if not (alpha >= 0.5).any():
                continue
            layer = _Layer(rgb, alpha, alpha >= 0.5, linear=False)
            depth = 1e9 if placement.front else -1e9  # flat shapes lie on top of (or under) everything
        (front if placement.front else behind).append((depth, layer))
    order = lambda item: item[0]  # noqa: E731
    return [layer for _, layer in sorted(behind, key=order)], [layer for _, layer in sorted(front, key=order)]


def render_theta(theta, backend: str = "raster", assets=None, samples: int = 16, device: str = "CPU") -> RenderResult:
    """Render one θ (a Theta or its stored dict of any version); RenderRejected (with a
    reason) when its image cannot be used."""
    from workers.render import blur, compositing, occluders
    from workers.render.assets import load_assets
    from workers.render.camera import build_scene, frame_shift, with_principal_shift
    from workers.render.raster import amodal_extent, silhouette

    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}")
    start = time.perf_counter()
    timings: dict[str, float] = {}
    clock = [start]

    def lap(name: str) -> None:
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - clock[0]
        clock[0] = now

    theta = check_theta(theta)
    assets = assets or load_assets()
    label = assets.label(theta.object)
    if theta.label != label:
        raise ValueError(f"θ.label {theta.label} does not match object {theta.object!r} (class {label} here)")
    texture = assets.texture(theta.object)
    size = int(theta.image_size)
    render = lambda scene: _backend_render(scene, backend, samples, device)  # noqa: E731

    mesh, mesh_size = _sheet_mesh(theta.rulings, theta.smooth_steps, _rng(theta, _SHEET), texture)
    lap("sheet")

    scene = build_scene(
        mesh.vertices,
        mesh.faces,
        mesh.uv,
        texture,
        image_size=size,
        roll=theta.roll,
        pitch=theta.pitch,
        yaw=theta.yaw,
        offset_m=theta.position_offset_m,
        offset_angle=theta.position_offset_angle,
        scale=theta.scale,
        irradiance=theta.irradiance,
        rotation=theta.rotation,
        tilt=theta.tilt,
        tilt_azimuth=theta.tilt_azimuth,
        field_of_view=np.radians(theta.field_of_view_deg),
    )
    lap("scene")

    shared: dict = {}
    if _uses_lighting(theta):
        scene, shared = _shading(
            theta, scene, mesh_size, _rng(theta, _LIGHTS), _rng(theta, _WRINKLES), _rng(theta, _SHADOW)
        )
        lap("lights")

    if theta.frame_crop > 0:
        scene = with_principal_shift(scene, frame_shift(scene, theta.frame_crop, theta.frame_crop_angle))
        lap("frame_crop")

    layers: list[_Layer] = []
    if theta.instances == 1:
        output = render(scene)
        lap("render")
        if not output.mask.any():
            raise RenderRejected("target outside the view: no pixel centre of the image falls on the sheet")
        layers.append(_Layer(output.rgb, output.alpha, output.mask, target=0, scene=scene, object=theta.object))
    else:
        layers += _instance_layers(theta, scene, shared, assets, render)
        lap("instances")

    if theta.clutter > 0 or assets.lookalike_sheets:
        behind, front = _clutter_layers(theta, scene, shared, assets, render, size)
        layers = behind + layers
        lap("clutter")
    else:
        front = []

    targets = sorted((layer for layer in layers if layer.target is not None), key=lambda layer: layer.target)
    amodal = [amodal_extent(layer.scene, layer.mask) for layer in targets]
    lap("amodal")

    # What later layers hide of each target; front distractors that would bury one are left out.
    hidden = [np.zeros((size, size), bool) for _ in targets]
    for index, layer in enumerate(layers):
        if layer.target is not None:
            for later in layers[index + 1 :]:
                hidden[layer.target] |= later.mask
    for layer in front:
        shown = [t.mask & ~hidden[t.target] for t in targets]
        if all(np.count_nonzero(s & layer.mask) <= MAX_CLUTTER_HIDING * np.count_nonzero(s) for s in shown):
            for t in targets:
                hidden[t.target] |= layer.mask
            layers.append(layer)

    occlusion = None
    if theta.visible_fraction < 1.0 and targets:
        if not theta.occluder:
            raise ValueError("θ.occluder: a visible fraction below 1 needs an occluder")
        first = targets[0]
        occluder_rgb, occluder_alpha = assets.occluder(theta.occluder)
        # Place the occluder on the geometric silhouette, not on the backend's own mask: the
        # placement draws a random target pixel, and a one-pixel difference between the
        # backends' anti-aliased edges would otherwise put it somewhere else entirely.
        placement_mask = first.mask if backend == "raster" else silhouette(first.scene)
        occlusion = occluders.place_occluder(
            placement_mask & ~hidden[0],
            amodal[0][0],
            float(theta.visible_fraction),
            occluder_rgb,
            occluder_alpha,
            _rng(theta, _OCCLUDER),
        )
        if occlusion is not None:
            if abs(occlusion.achieved_fraction - occlusion.target_fraction) > OCCLUSION_TOLERANCE:
                raise RenderRejected(
                    f"occluder {theta.occluder!r} cannot hide the asked share: visible fraction "
                    f"{occlusion.achieved_fraction:.3f} instead of {occlusion.target_fraction:.3f}"
                )
            for mask in hidden:
                mask |= occlusion.mask
        lap("occlusion")

    visible = [t.mask & ~hidden[i] for i, t in enumerate(targets)]
    annotations = [annotate(mask, *amodal[i]) for i, mask in enumerate(visible)]
    lap("annotation")

    background = assets.background(theta.background, size, _rng(theta, _BACKGROUND))
    focus_blur = blur.odd_kernel_size(theta.focus_blur_pct, size) > 0
    motion_blur = blur.motion_kernel_pixels(theta.motion_blur_pct, size) > 1
    distorted = theta.distortion != 0
    float_stages = focus_blur or motion_blur or distorted or theta.noise_sigma > 0
    if len(layers) == 1 and not float_stages:
        # One sheet and nothing after compositing: only the box where the object or occluder
        # lies needs float and encoding (same bytes as the whole-image path below).
        image_u8 = compositing.composite_to_uint8(background, layers[0].rgb, layers[0].alpha, occlusion)
        lap("background")
    else:
        image = np.multiply(background, np.float32(1.0 / 255.0), dtype=np.float32)
        for layer in layers:
            if layer.linear:
                image = compositing.composite_object(image, layer.rgb, layer.alpha)
            else:
                image = compositing.composite(image, layer.rgb, layer.alpha)
        if occlusion is not None:
            image = compositing.composite(image, occlusion.rgb, occlusion.alpha)
        lap("background")
        if distorted:
            from workers.render.imaging import distort, distorted_annotation

            image, visible = distort(image, visible, theta.distortion)
            annotations = [distorted_annotation(a, mask, theta.distortion) for a, mask in zip(annotations, visible)]
            lap("distortion")
        if focus_blur:
            image = blur.focus_blur(image, theta.focus_blur_pct, size)
            lap("focus_blur")
        if motion_blur:
            image = blur.motion_blur(image, theta.motion_blur_pct, theta.motion_blur_angle, size)
            lap("motion_blur")
        if theta.noise_sigma > 0:
            from workers.render.imaging import add_noise

            image = add_noise(image, theta.noise_sigma, _rng(theta, _NOISE))
            lap("noise")
        image_u8 = compositing.to_uint8(image)
        lap("encode")
    if theta.jpeg_quality < 100:
        from workers.render.imaging import jpeg_round_trip

        image_u8 = jpeg_round_trip(image_u8, theta.jpeg_quality)
        lap("jpeg")
    timings["total"] = time.perf_counter() - start
    objects = [
        ObjectAnnotation(t.object, assets.label(t.object), a.box, a.amodal_box, a.visible_fraction)
        for t, a in zip(targets, annotations)
    ]
    return RenderResult(image=image_u8, objects=objects, timings=timings, masks=visible)


def render_with_resample(
    theta,
    backend: str = "raster",
    max_resamples: int = 20,
    assets=None,
    samples: int = 16,
    device: str = "CPU",
) -> tuple[RenderResult, Theta, list[str]]:
    """Render θ, redrawing it (same condition, difficulty, object) while it is rejected.

    Returns (result, the θ actually rendered, the rejection reasons in order). Resample i is
    drawn from a seed derived from θ's seed and i, so the outcome is deterministic. Raises
    RenderRejected (with ``.reasons``) when θ and its ``max_resamples`` redraws all fail."""
    if max_resamples < 0:
        raise ValueError(f"max_resamples must be >= 0, got {max_resamples}")
    reasons: list[str] = []
    current = check_theta(theta)
    for attempt in range(max_resamples + 1):
        if attempt > 0:
            current = resample_theta(theta, attempt, assets)
        try:
            result = render_theta(current, backend=backend, assets=assets, samples=samples, device=device)
            return result, current, reasons
        except RenderRejected as rejected:
            reasons.append(rejected.reason)
    raise RenderRejected(f"θ and its {max_resamples} resamples were all rejected; last reason: {reasons[-1]}", reasons)


def compile_kernels() -> None:
    """Compile (or load from numba's cache) every kernel the raster pipeline runs: the paper
    model's, the rasteriser's and the occluder placement's, by rendering one small θ of every
    condition at its hardest, and a mixed one. A worker image runs this at build time and the
    integration tests before they start workers, so no worker process spends its first images
    compiling."""
    from foldwise.conditions import load_condition_table
    from foldwise.sampling import generate_parameters
    from foldwise.theta import MIXED
    from workers.render import compositing, occluders, raster
    from workers.render.assets import procedural_background

    raster.compile_kernels()
    compositing.compile_kernels()
    occluders.compile_kernels()
    procedural_background("checker", 16, np.random.default_rng(0))  # gradient, stripes and checker share one kernel
    table = load_condition_table()
    for index, condition in enumerate(table.codes + (MIXED,)):
        for theta in generate_parameters(
            condition, table.difficulties[-1], 1, seed=derive_seed(2018, index), image_size=64
        ):
            try:
                render_with_resample(theta, backend="raster", max_resamples=5)
            except RenderRejected:
                pass  # the kernels ran all the same
