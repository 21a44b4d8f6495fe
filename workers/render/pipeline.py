"""θ → image and ground truth: sheet, scene, 3D backend, 2D stages, annotation.

``render_theta`` runs, in order (each stage timed in ``RenderResult.timings``, in seconds):

1. ``sheet``: the deformed sheet (``paper_model.sample_sheet`` with θ's rulings, from θ's
   seed); a self-intersecting sheet is a rejection;
2. ``scene``: pose, scale, camera and light (camera.py);
3. ``render``: the 3D backend, ``raster`` (raster.py) or ``blender`` (blender.py);
4. ``amodal``: the whole silhouette, off-image part included (for the amodal box and the
   visible fraction);
5. ``occlusion`` (only when θ's visible fraction < 1): place the occluder; a placement
   more than ``OCCLUSION_TOLERANCE`` from θ's visible fraction is a rejection;
6. ``annotation``: visible box, amodal box, visible fraction; rejects an unusable target;
7. ``background``: sRGB encoding of the render and alpha compositing over the background;
   the occluder goes on top;
8. ``focus_blur`` then ``motion_blur`` (only when their kernels are at least 2 pixels);
9. ``encode``: to uint8. ``total`` covers everything. An image with no blur composites and
   encodes only the box where the object or occluder is drawn, inside ``background`` (no
   ``encode`` entry); the bytes are the same.

A stage whose parameter is canonical does no work and has no timing entry.
Everything random comes from θ's seed (split by purpose), so a θ renders to the same bytes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from workers.render.annotation import RenderRejected, annotate
from workers.render.parameters import check_theta, derive_seed, resample_theta

__all__ = ["RenderResult", "RenderRejected", "render_theta", "render_with_resample", "compile_kernels", "BACKENDS"]

BACKENDS = ("raster", "blender")
# How far the achieved visible fraction may be from θ's before the placement is rejected.
OCCLUSION_TOLERANCE = 0.05
# Independent random streams drawn from θ's seed, one per purpose.
_SHEET, _BACKGROUND, _OCCLUDER = 1, 2, 3


@dataclass
class RenderResult:
    image: np.ndarray  # (H, W, 3) uint8 RGB
    box: list[float]  # [x0, y0, x1, y1] pixel edges, visible target after occlusion and border crop
    amodal_box: list[float]  # the whole silhouette's box, may extend past the image
    visible_fraction: float  # visible target pixels / amodal target pixels
    label: int  # 0-based class index of the object
    timings: dict[str, float] = field(default_factory=dict)
    mask: np.ndarray | None = None  # (H, W) bool visible target mask (box = its tight box)


def _paper_model():
    from workers.render import paper_model

    return paper_model


def _rng(theta: dict, purpose: int) -> np.random.Generator:
    return np.random.default_rng(derive_seed(int(theta["seed"]), purpose))


def _backend_render(scene, backend: str, samples: int, device: str = "CPU"):
    if backend == "raster":
        from workers.render.raster import render_scene

        return render_scene(scene)
    if backend == "blender":
        from workers.render.blender import get_renderer

        return get_renderer(samples=samples, device=device).render(scene)
    raise ValueError(f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}")


def render_theta(
    theta: dict, backend: str = "raster", assets=None, samples: int = 16, device: str = "CPU"
) -> RenderResult:
    """Render one θ; RenderRejected (with a reason) when its image cannot be used."""
    from workers.render import compositing
    from workers.render.assets import load_assets
    from workers.render.camera import build_scene, sheet_size
    from workers.render.raster import amodal_extent, silhouette

    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}")
    start = time.perf_counter()
    timings: dict[str, float] = {}
    clock = [start]

    def lap(name: str) -> None:
        now = time.perf_counter()
        timings[name] = now - clock[0]
        clock[0] = now

    check_theta(theta)
    assets = assets or load_assets()
    label = assets.label(theta["object"])
    if int(theta["label"]) != label:
        raise ValueError(f"θ.label {theta['label']} does not match object {theta['object']!r} (class {label} here)")
    texture = assets.texture(theta["object"])
    size = int(theta["image_size"])

    paper_model = _paper_model()
    width_m, height_m = sheet_size(texture.shape)
    try:
        mesh = paper_model.sample_sheet(int(theta["rulings"]), _rng(theta, _SHEET), width_m, height_m)
    except paper_model.SelfIntersection as error:
        raise RenderRejected(f"self-intersecting sheet: {error}") from None
    except ValueError as error:  # no valid ruling layout found for this draw
        raise RenderRejected(f"sheet layout failed: {error}") from None
    lap("sheet")

    scene = build_scene(
        mesh.vertices,
        mesh.faces,
        mesh.uv,
        texture,
        image_size=size,
        roll=float(theta["roll"]),
        pitch=float(theta["pitch"]),
        yaw=float(theta["yaw"]),
        offset_m=float(theta["position_offset_m"]),
        offset_angle=float(theta.get("position_offset_angle", 0.0)),
        scale=float(theta["scale"]),
        irradiance=float(theta["irradiance"]),
    )
    lap("scene")

    output = _backend_render(scene, backend, samples, device)
    lap("render")

    target_mask = output.mask
    if not target_mask.any():
        raise RenderRejected("target outside the view: no pixel centre of the image falls on the sheet")
    amodal_pixels, amodal_box = amodal_extent(scene, target_mask)
    lap("amodal")

    occlusion = None
    visible_mask = target_mask
    if float(theta["visible_fraction"]) < 1.0:
        if not theta.get("occluder"):
            raise ValueError("θ.occluder: a visible fraction below 1 needs an occluder")
        occluder_rgb, occluder_alpha = assets.occluder(theta["occluder"])
        # Place the occluder on the geometric silhouette, not on the backend's own mask: the
        # placement draws a random target pixel, and a one-pixel difference between the
        # backends' anti-aliased edges would otherwise put it somewhere else entirely.
        placement_mask = target_mask if backend == "raster" else silhouette(scene)
        occlusion = compositing.place_occluder(
            placement_mask,
            amodal_pixels,
            float(theta["visible_fraction"]),
            occluder_rgb,
            occluder_alpha,
            _rng(theta, _OCCLUDER),
        )
        if occlusion is not None:
            if abs(occlusion.achieved_fraction - occlusion.target_fraction) > OCCLUSION_TOLERANCE:
                raise RenderRejected(
                    f"occluder {theta['occluder']!r} cannot hide the asked share: visible fraction "
                    f"{occlusion.achieved_fraction:.3f} instead of {occlusion.target_fraction:.3f}"
                )
            visible_mask = target_mask & ~occlusion.mask
        lap("occlusion")

    annotation = annotate(visible_mask, amodal_pixels, amodal_box)
    lap("annotation")

    background = assets.background(theta["background"], size, _rng(theta, _BACKGROUND))
    focus_blur = compositing.odd_kernel_size(float(theta["focus_blur_pct"]), size) > 0
    motion_blur = compositing.motion_kernel_pixels(float(theta["motion_blur_pct"]), size) > 1
    if not (focus_blur or motion_blur):
        # Nothing blurs: only the box where the object or occluder lies needs float and
        # encoding (same bytes as the whole-image path below).
        image_u8 = compositing.composite_to_uint8(background, output.rgb, output.alpha, occlusion)
        lap("background")
    else:
        image = compositing.composite_object(
            np.multiply(background, np.float32(1.0 / 255.0), dtype=np.float32), output.rgb, output.alpha
        )
        if occlusion is not None:
            image = compositing.composite(image, occlusion.rgb, occlusion.alpha)
        lap("background")
        if focus_blur:
            image = compositing.focus_blur(image, float(theta["focus_blur_pct"]), size)
            lap("focus_blur")
        if motion_blur:
            image = compositing.motion_blur(image, float(theta["motion_blur_pct"]), float(theta["motion_blur_angle"]), size)
            lap("motion_blur")
        image_u8 = compositing.to_uint8(image)
        lap("encode")
    timings["total"] = time.perf_counter() - start
    return RenderResult(
        image=image_u8,
        box=annotation.box,
        amodal_box=annotation.amodal_box,
        visible_fraction=annotation.visible_fraction,
        label=label,
        timings=timings,
        mask=visible_mask,
    )


def render_with_resample(
    theta: dict,
    backend: str = "raster",
    max_resamples: int = 20,
    assets=None,
    samples: int = 16,
    device: str = "CPU",
) -> tuple[RenderResult, dict, list[str]]:
    """Render θ, redrawing it (same condition, difficulty, object) while it is rejected.

    Returns (result, the θ actually rendered, the rejection reasons in order). Resample i is
    drawn from a seed derived from θ's seed and i, so the outcome is deterministic. Raises
    RenderRejected (with ``.reasons``) when θ and its ``max_resamples`` redraws all fail."""
    if max_resamples < 0:
        raise ValueError(f"max_resamples must be >= 0, got {max_resamples}")
    reasons: list[str] = []
    current = theta
    for attempt in range(max_resamples + 1):
        if attempt > 0:
            current = resample_theta(theta, attempt, assets)
        try:
            result = render_theta(current, backend=backend, assets=assets, samples=samples, device=device)
            return result, current, reasons
        except RenderRejected as rejected:
            reasons.append(rejected.reason)
    raise RenderRejected(
        f"θ and its {max_resamples} resamples were all rejected; last reason: {reasons[-1]}", reasons
    )


def compile_kernels() -> None:
    """Compile (or load from numba's cache) every kernel the raster pipeline runs: the paper
    model's, the rasteriser's and the occluder placement's, by rendering one small θ of every
    condition at its hardest. A worker image runs this at build time and the integration tests
    before they start workers, so no worker process spends its first images compiling."""
    from foldwise.conditions import load_condition_table
    from workers.render import compositing, raster
    from workers.render.assets import procedural_background
    from workers.render.parameters import generate_parameters

    raster.compile_kernels()
    compositing.compile_kernels()
    procedural_background("checker", 16, np.random.default_rng(0))  # gradient, stripes and checker share one kernel
    table = load_condition_table()
    for index, condition in enumerate(table.codes):
        for theta in generate_parameters(condition, table.difficulties[-1], 1, seed=derive_seed(2018, index), image_size=64):
            try:
                render_with_resample(theta, backend="raster", max_resamples=5)
            except RenderRejected:
                pass  # the kernels ran all the same
