"""The rest of Table 1 (orientation, clutter, shadows, specularities, wrinkles, light colour and
sources, camera intrinsics, field-of-view crop, sensor noise and JPEG, several objects) and the
mixed stage: determinism, stages that do no work when canonical, what each stage does, and
the extreme values of every new parameter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from foldwise.conditions import load_condition_table
from foldwise.sampling import MixedDraw, generate_parameters, resample_theta
from foldwise.theta import MIXED, Theta
from workers.render import camera, imaging, lighting, pipeline, raster
from workers.render.annotation import MIN_BOX_SIDE, tight_box
from workers.render.pipeline import RenderRejected, render_theta, render_with_resample

SIZE = 96
TABLE = load_condition_table()
NEW = [code for code in TABLE.codes if code not in TABLE.table3]


def one(condition="po", difficulty="canonical", seed=0, size=SIZE, **override) -> Theta:
    theta = generate_parameters(condition, difficulty, 1, seed=seed, image_size=size)[0]
    return theta.replace(**override) if override else theta


def assert_valid(result, size=SIZE):
    assert result.image.shape == (size, size, 3) and result.image.dtype == np.uint8
    assert len(result.masks) == len(result.objects)
    for obj, mask in zip(result.objects, result.masks):
        assert obj.box == tight_box(mask)
        x0, y0, x1, y1 = obj.box
        assert 0 <= x0 < x1 <= size and 0 <= y0 < y1 <= size
        assert x1 - x0 >= MIN_BOX_SIDE and y1 - y0 >= MIN_BOX_SIDE
        assert 0 < obj.visible_fraction <= 1
        assert 0 <= obj.label < 5


def valid_or_resampled(theta):
    """A valid image and box set, or a recorded resample of θ (never a silent degenerate box)."""
    result, used, reasons = render_with_resample(theta)
    assert_valid(result)
    assert used.resample == len(reasons) and all(isinstance(r, str) and r for r in reasons)
    return result, used, reasons


# --------------------------------------------------------------------------- determinism


@pytest.mark.parametrize("condition", NEW + [MIXED])
def test_same_theta_same_bytes_and_boxes(condition):
    for seed in range(3):
        theta = one(condition, "hard", seed=seed)
        first, used, _ = render_with_resample(theta)
        again, used_again, _ = render_with_resample(Theta.parse(theta.to_dict()))
        assert used_again == used
        assert first.image.tobytes() == again.image.tobytes()
        assert [o.to_dict() for o in first.objects] == [o.to_dict() for o in again.objects]


@pytest.mark.parametrize("condition", NEW)
def test_each_condition_changes_the_image(condition):
    theta = one(condition, "hard", seed=1)
    plain = theta.replace(**{name: TABLE.canonical[name] for name in _drawn(condition)})
    changed = render_with_resample(theta)[0].image
    assert not np.array_equal(changed, render_theta(plain).image)


def _drawn(condition):
    return {p for variant in TABLE.conditions[condition].variants.values() for p in variant["hard"]}


# --------------------------------------------------------------------------- canonical: no work

_STAGES = {
    "lights": (lighting, "light_rig"),
    "wrinkles": (lighting, "wrinkle_normal_map"),
    "shadow": (lighting, "shadow_caster"),
    "frame crop": (camera, "frame_shift"),
    "instances": (pipeline, "_instance_layers"),
    "clutter": (pipeline, "_clutter_layers"),
    "per-pixel shading": (raster, "_shade_lit"),
    "distortion": (imaging, "distort"),
    "noise": (imaging, "add_noise"),
    "jpeg": (imaging, "jpeg_round_trip"),
}
# Which stage each new condition must reach (and a canonical θ must not).
_REACHES = {
    "or": [], "cl": ["clutter"], "sh": ["lights", "shadow", "per-pixel shading"], "sp": ["lights", "per-pixel shading"],
    "wr": ["wrinkles", "per-pixel shading"], "lc": ["lights", "per-pixel shading"], "ci": [],
    "fv": ["frame crop"], "sn": ["noise", "jpeg"], "mo": ["instances"],
}  # fmt: skip


def _record_calls(monkeypatch):
    calls: list[str] = []
    for name, (module, attribute) in _STAGES.items():
        original = getattr(module, attribute)

        def spy(*args, _name=name, _original=original, **kwargs):
            calls.append(_name)
            return _original(*args, **kwargs)

        monkeypatch.setattr(module, attribute, spy)
    return calls


@pytest.mark.parametrize("condition", [*TABLE.table3, "canonical"])
def test_a_canonical_stage_does_no_work(monkeypatch, condition):
    calls = _record_calls(monkeypatch)
    theta = one("po", "canonical") if condition == "canonical" else one(condition, "hard", seed=2)
    result = render_theta(theta) if condition != "eo" else render_with_resample(theta)[0]
    assert calls == []
    assert not set(result.timings) & {"lights", "frame_crop", "instances", "clutter", "distortion", "noise", "jpeg"}


@pytest.mark.parametrize("condition", NEW)
def test_a_new_condition_runs_its_own_stages_only(monkeypatch, condition):
    calls = _record_calls(monkeypatch)
    theta = one(condition, "hard", seed=3)
    if condition == "ci":
        theta = theta.replace(distortion=0.1)
    render_with_resample(theta)
    expected = set(_REACHES[condition]) | ({"distortion"} if condition == "ci" else set())
    assert set(calls) == expected, condition


# --------------------------------------------------------------------------- what each stage does


def test_orientation_turns_the_sheet_any_way():
    upright = render_theta(one())
    upside_down = render_theta(one(rotation=math.pi))
    # A half turn about the optical axis: the same sheet, pixels mirrored through the centre.
    flipped = upside_down.masks[0][::-1, ::-1]
    assert np.count_nonzero(flipped ^ upright.masks[0]) < 0.02 * upright.masks[0].sum()
    tilted = render_theta(one(tilt=1.2, tilt_azimuth=0.0))
    assert tilted.masks[0].sum() < 0.6 * upright.masks[0].sum()


def test_a_lens_keeps_the_span_and_changes_the_perspective():
    boxes = {fov: render_theta(one(field_of_view_deg=fov)).box for fov in (15.0, 40.0, 90.0)}
    widths = {fov: box[2] - box[0] for fov, box in boxes.items()}
    assert max(widths.values()) - min(widths.values()) <= 2
    tilted = {fov: render_theta(one(field_of_view_deg=fov, yaw=0.9)).masks[0] for fov in (15.0, 90.0)}
    # Seen from close by with a wide lens, the near side of a turned sheet looms larger.
    assert not np.array_equal(tilted[15.0], tilted[90.0])


@pytest.mark.parametrize("k1", [-0.3, 0.3])
def test_distortion_moves_boxes_with_the_pixels(k1):
    import cv2

    straight = render_theta(one(scale=1.3))
    bent = render_theta(one(scale=1.3, distortion=k1))
    map_x, map_y = imaging.distortion_maps(SIZE, SIZE, k1)
    moved = cv2.remap(straight.masks[0].view(np.uint8), map_x, map_y, cv2.INTER_NEAREST).astype(bool)
    assert np.array_equal(bent.masks[0], moved)
    assert bent.box == tight_box(moved)
    # Straight edges bow: barrel (k1 > 0) pushes the middle of the sheet's top edge out
    # (up, away from the centre) relative to its ends, pincushion pulls it in.
    rows = np.argmax(bent.masks[0], axis=0)
    columns = np.flatnonzero(bent.masks[0].any(axis=0))
    middle, ends = rows[SIZE // 2], (rows[columns[2]] + rows[columns[-3]]) / 2
    assert (middle < ends) == (k1 > 0)


def test_the_frame_crop_pushes_the_asked_share_out():
    whole = render_theta(one())
    for crop in (0.2, 0.5, 0.8):
        result = render_theta(one(frame_crop=crop, frame_crop_angle=1.0))
        assert result.visible_fraction == pytest.approx(1 - crop, abs=0.03)
        assert result.masks[0].sum() == pytest.approx((1 - crop) * whole.masks[0].sum(), rel=0.08)


def test_a_shadow_darkens_about_the_asked_share_of_the_sheet():
    lit = render_theta(one(ambient=0.2))
    for share in (0.2, 0.6):
        shaded = render_theta(one(ambient=0.2, shadow=share, seed=4))
        mask = lit.masks[0]
        darker = (shaded.image.astype(int).sum(axis=2) < 0.7 * lit.image.astype(int).sum(axis=2)) & mask
        assert darker.sum() / mask.sum() == pytest.approx(share, abs=0.15)


def test_coloured_light_tints_the_sheet_and_keeps_its_brightness():
    white = render_theta(one())
    tinted = render_theta(one(light_saturation=0.9, light_spread=0.3))
    mask = white.masks[0] & tinted.masks[0]
    mean_white = white.image[mask].mean(axis=0)
    mean_tinted = tinted.image[mask].mean(axis=0)
    assert np.ptp(mean_tinted - mean_white) > 20  # one channel rises, another falls
    assert abs(mean_tinted.mean() - mean_white.mean()) < 25


def test_a_highlight_lands_on_the_glossy_sheet():
    matte = render_theta(one())
    glossy = render_theta(one(specular=0.05, roughness=0.3))
    mask = matte.masks[0]
    gain = glossy.image.astype(int).sum(axis=2) - matte.image.astype(int).sum(axis=2)
    import cv2

    around = cv2.dilate(mask.view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)  # anti-aliased edge
    assert gain[mask].max() > 60 and gain[~around].max() == 0


def test_wrinkles_shade_creases_without_moving_the_outline():
    flat = render_theta(one())
    wrinkled = render_theta(one(wrinkles=16, wrinkle_depth=0.5))
    assert np.array_equal(flat.masks[0], wrinkled.masks[0])
    difference = np.abs(flat.image.astype(int) - wrinkled.image.astype(int)).sum(axis=2)
    assert np.count_nonzero(difference[flat.masks[0]] > 15) > 0.05 * flat.masks[0].sum()


def test_noise_and_jpeg_degrade_the_image_by_their_amount():
    clean = render_theta(one()).image.astype(float)
    noisy = render_theta(one(noise_sigma=8.0)).image.astype(float)
    assert (noisy - clean).std() == pytest.approx(8.0, rel=0.2)
    errors = [np.abs(render_theta(one(jpeg_quality=q)).image.astype(float) - clean).mean() for q in (90, 30, 5)]
    assert errors[0] < errors[1] < errors[2]


def test_several_objects_each_get_a_box_and_clutter_gets_none():
    result = render_theta(one(instances=4, seed=5))
    assert_valid(result)
    assert len(result.objects) == 4 and result.objects[0].object == one(seed=5).object
    for a, b in zip(result.masks, result.masks[1:]):
        assert not (a & b).any()  # visible masks never overlap: a nearer sheet hides the farther
    cluttered = render_theta(one(clutter=8, clutter_front=0.5, seed=5))
    assert_valid(cluttered)
    assert len(cluttered.objects) == 1
    assert cluttered.objects[0].visible_fraction >= 0.5 - 1e-9  # clutter never buries the object


def test_an_image_without_the_object_has_no_box():
    result = render_theta(one(instances=0, clutter=3))
    assert result.objects == [] and result.masks == [] and result.box is None
    assert result.image.shape == (SIZE, SIZE, 3)


def test_mixed_theta_records_its_conditions_and_resamples_keep_them():
    thetas = generate_parameters(MIXED, "hard", 200, seed=6, image_size=SIZE)
    assert all(2 <= len(t.components) <= 4 for t in thetas)
    assert all(len({c.condition for c in t.components}) == len(t.components) for t in thetas)
    assert {c.difficulty for t in thetas for c in t.components} == set(TABLE.difficulties)
    assert 0.05 < np.mean([t.instances == 0 for t in thetas]) < 0.17
    medium = generate_parameters(MIXED, "medium", 50, seed=6, image_size=SIZE)
    assert {c.difficulty for t in medium for c in t.components} <= {"easy", "medium"}
    theta = thetas[0]
    redrawn = resample_theta(theta, 1)
    assert redrawn.components == theta.components and redrawn.instances == theta.instances
    assert redrawn.seed != theta.seed


def test_a_held_condition_is_in_every_mixed_theta_and_the_others_are_drawn_beside_it():
    held = MixedDraw(conditions_per_image=(2, 3), always=("or",))
    thetas = generate_parameters(MIXED, "hard", 120, seed=6, image_size=SIZE, mixed=held)
    for theta in thetas:
        codes = [c.condition for c in theta.components]
        assert codes[0] == "or" and "or" not in codes[1:] and 2 <= len(codes) - 1 <= 3
    # Its difficulty is drawn like any other's, so the rotation covers every range of the table.
    assert {t.components[0].difficulty for t in thetas} == set(TABLE.difficulties)
    assert max(abs(t.rotation) for t in thetas) > math.pi / 2 and min(abs(t.rotation) for t in thetas) < math.pi / 4
    # Nothing held: the draws are the ones the stage made before the key existed.
    assert generate_parameters(MIXED, "hard", 20, seed=6, image_size=SIZE) == generate_parameters(
        MIXED, "hard", 20, seed=6, image_size=SIZE, mixed=MixedDraw(always=())
    )


# --------------------------------------------------------------------------- extremes

EXTREMES = {
    "strongest clutter": dict(clutter=16, clutter_front=1.0),
    "darkest coloured light": dict(irradiance=0.01, light_count=4, light_saturation=1.0, light_spread=1.5),
    "brightest coloured light": dict(irradiance=10.0, light_count=8, light_saturation=1.0, ambient=1.0),
    "widest lens": dict(field_of_view_deg=170.0),
    "narrowest lens": dict(field_of_view_deg=1.0),
    "strongest barrel distortion": dict(distortion=0.5),
    "strongest pincushion distortion": dict(distortion=-0.5),
    "most wrinkles": dict(wrinkles=256, wrinkle_depth=1.5),
    "JPEG at its floor": dict(jpeg_quality=1),
    "most noise": dict(noise_sigma=255.0),
    "no object at all": dict(instances=0),
    "most objects": dict(instances=8),
    "most of the sheet out of frame": dict(frame_crop=0.95),
    "deepest shadow": dict(shadow=0.99),
    "mirror gloss": dict(specular=1.0, roughness=0.01),
    "tilt nearly edge-on": dict(tilt=1.55),
    "upside down": dict(rotation=math.pi),
}


@pytest.mark.parametrize("name", list(EXTREMES))
def test_extremes_give_a_valid_image_or_a_recorded_resample(name):
    for seed in range(2):
        theta = one(seed=seed, **EXTREMES[name])
        try:
            result, _, _ = valid_or_resampled(theta)
        except RenderRejected as rejected:  # every redraw rejected: each one said why
            assert rejected.reasons and all(rejected.reasons)
            continue
        if name == "no object at all":
            assert result.objects == []
        assert np.isfinite(result.image).all()


def test_extremes_that_must_hold_an_object_do():
    # The most extreme values the table's ranges reach must still show the object.
    for condition in NEW:
        for seed in range(4):
            result, _, reasons = valid_or_resampled(one(condition, "hard", seed=seed))
            assert result.objects, (condition, seed, reasons)


@pytest.mark.parametrize("condition", ["po", "de", "sc"])
def test_per_pixel_shading_equals_per_face_shading_under_the_papers_light(condition):
    import dataclasses

    from workers.render.assets import load_assets
    from workers.render.camera import build_scene
    from workers.render.scene import Light

    theta = one(condition, "hard", seed=5)
    texture = load_assets().texture(theta.object)
    mesh, _ = pipeline._sheet_mesh(theta.rulings, theta.smooth_steps, pipeline._rng(theta, pipeline._SHEET), texture)
    scene = build_scene(
        mesh.vertices, mesh.faces, mesh.uv, texture, image_size=SIZE, roll=theta.roll, pitch=theta.pitch,
        yaw=theta.yaw, scale=theta.scale, offset_m=theta.position_offset_m, offset_angle=theta.position_offset_angle,
    )  # fmt: skip
    per_face = raster.render_scene(scene)
    per_pixel = raster.render_scene(
        dataclasses.replace(scene, lights=(Light(scene.light_direction, scene.irradiance),))
    )
    assert not dataclasses.replace(scene, lights=(Light(scene.light_direction, 1.0),)).plain
    assert np.array_equal(per_face.mask, per_pixel.mask)
    assert np.abs(per_face.rgb - per_pixel.rgb)[per_face.mask].max() < 1e-4
