"""θ sampling: Table 3 ranges, canonical values elsewhere, balance, determinism, bad input."""

from __future__ import annotations

import json
import math
from collections import Counter

import pytest

from foldwise.conditions import load_condition_table
from foldwise.sampling import (
    canonical_values,
    check_theta,
    derive_seed,
    generate_parameters,
    resample_theta,
    resolve_condition,
)
from foldwise.theta import SIGNED_PARAMETERS
from workers.render.assets import load_assets

TABLE = load_condition_table()
CANONICAL = canonical_values(TABLE)


@pytest.mark.parametrize("code", TABLE.codes)
@pytest.mark.parametrize("difficulty", TABLE.difficulties)
def test_values_lie_in_the_table_ranges_and_everything_else_is_canonical(code, difficulty):
    thetas = generate_parameters(code, difficulty, 40, seed=7)
    condition = TABLE.conditions[code]
    studied = {p for variant in condition.variants.values() for p in variant[difficulty]}
    for theta in thetas:
        assert theta.condition == code and theta.difficulty == difficulty
        ranges = condition.variants[theta.variant][difficulty]
        for parameter, spec in ranges.items():
            value = getattr(theta, parameter)
            if parameter in SIGNED_PARAMETERS:
                value = abs(value)
            if isinstance(spec, tuple):
                assert spec[0] <= value <= spec[1], (parameter, value, spec)
            else:
                assert value == spec
        for parameter, canonical in CANONICAL.items():
            if parameter not in studied:
                assert getattr(theta, parameter) == canonical, parameter
        assert (theta.occluder is not None) == (code == "eo")


def test_theta_is_json_and_fully_determined_by_the_seed():
    first = generate_parameters("po", "hard", 12, seed=3)
    again = generate_parameters("po", "hard", 12, seed=3)
    other = generate_parameters("po", "hard", 12, seed=4)
    assert first == again
    assert first != other
    assert [type(t).parse(json.loads(json.dumps(t.to_dict()))) for t in first] == first
    assert len({t.seed for t in first}) == 12


def test_pose_angles_take_both_signs_and_offsets_point_everywhere():
    thetas = generate_parameters("pose", "medium", 200, seed=0)
    for angle in ("roll", "pitch", "yaw"):
        signs = Counter(math.copysign(1, getattr(t, angle)) for t in thetas)
        assert signs[1.0] > 60 and signs[-1.0] > 60
    directions = [t.position_offset_angle for t in thetas]
    assert min(directions) < 0.5 and max(directions) > 2 * math.pi - 0.5
    assert all(0.5 <= t.position_offset_m <= 1.0 for t in thetas)


def test_variants_are_drawn_per_image():
    scales = Counter(t.variant for t in generate_parameters("sc", "hard", 100, seed=1))
    lights = Counter(t.variant for t in generate_parameters("li", "hard", 100, seed=1))
    assert set(scales) == {"small", "large"} and min(scales.values()) > 25
    assert set(lights) == {"dark", "bright"} and min(lights.values()) > 25


@pytest.mark.parametrize("code, variant", [("sc", "small"), ("sc", "large"), ("li", "dark"), ("li", "bright")])
def test_a_fixed_variant_draws_only_from_its_ranges_and_keeps_every_other_draw(code, variant):
    drawn = generate_parameters(code, "hard", 30, seed=2)
    fixed = generate_parameters(code, "hard", 30, seed=2, variant=variant)
    parameter = "scale" if code == "sc" else "irradiance"
    low, high = TABLE.conditions[code].variants[variant]["hard"][parameter]
    assert all(t.variant == variant and low <= getattr(t, parameter) <= high for t in fixed)
    for free, forced in zip(drawn, fixed):
        for key in ("seed", "object", "background"):
            assert getattr(free, key) == getattr(forced, key)
        if free.variant == variant:  # the same θ, whether the variant was drawn or asked for
            assert free == forced


def test_bad_variants_name_the_problem():
    with pytest.raises(ValueError, match="no variant 'dim'; known: bright, dark"):
        generate_parameters("li", "easy", 1, 0, variant="dim")
    with pytest.raises(ValueError, match="no variant 'small'; known: default"):
        generate_parameters("po", "easy", 1, 0, variant="small")
    with pytest.raises(ValueError, match="canonical θ have no variant"):
        generate_parameters("li", "canonical", 1, 0, variant="dark")


def test_resample_keeps_the_variant():
    # Redrawing a rejected image must not change the set's mix of variants.
    for theta in generate_parameters("li", "hard", 12, seed=4):
        for attempt in (1, 2, 3):
            assert resample_theta(theta, attempt).variant == theta.variant
    # A hand-edited θ whose variant is not its condition's draws one instead of failing.
    edited = {**generate_parameters("po", "canonical", 1, seed=4)[0].to_dict(), "condition": "sc", "difficulty": "hard"}
    assert resample_theta(edited, 1).variant in ("small", "large")


def test_objects_are_balanced_and_labels_match_the_catalog():
    assets = load_assets()
    thetas = generate_parameters("fb", "easy", 23, seed=5, assets=assets)
    counts = Counter(t.object for t in thetas)
    assert set(counts) == set(assets.classes)
    assert max(counts.values()) - min(counts.values()) <= 1
    assert all(assets.classes[t.label] == t.object for t in thetas)
    backgrounds = {t.background for t in generate_parameters("fb", "easy", 200, seed=5, assets=assets)}
    assert len(backgrounds) > len(assets.backgrounds) // 2


def test_canonical_difficulty_sets_every_parameter_canonical():
    for theta in generate_parameters("de", "canonical", 5, seed=0):
        assert all(getattr(theta, k) == v for k, v in CANONICAL.items())
        assert theta.occluder is None and theta.variant == "default"


def test_conditions_are_accepted_by_code_or_name():
    assert resolve_condition("po") == "po"
    assert resolve_condition("pose") == "po"
    assert resolve_condition("Pose change") == "po"
    assert resolve_condition("focus_blur") == "fb"
    assert resolve_condition("motion-blur") == "mb"
    assert resolve_condition("occlusion") == "eo"
    with pytest.raises(ValueError, match="unknown condition 'wobble'.*po"):
        resolve_condition("wobble")


@pytest.mark.parametrize(
    "args, message",
    [
        (("xx", "easy", 2, 0), "unknown condition"),
        (("po", "extreme", 2, 0), "unknown difficulty"),
        (("po", "easy", -1, 0), "n must be"),
    ],
)
def test_bad_requests_name_the_problem(args, message):
    with pytest.raises(ValueError, match=message):
        generate_parameters(*args)
    with pytest.raises(ValueError, match="image_size"):
        generate_parameters("po", "easy", 1, 0, image_size=8)


def test_resample_is_deterministic_and_keeps_condition_object_and_size():
    theta = generate_parameters("po", "hard", 1, seed=11, image_size=96)[0]
    first = resample_theta(theta, 1)
    assert first == resample_theta(theta, 1)
    second = resample_theta(theta, 2)
    assert first.seed != second.seed != theta.seed
    for redrawn, attempt in ((first, 1), (second, 2)):
        assert redrawn.resample == attempt
        assert redrawn.origin_seed == theta.seed
        assert redrawn.seed == derive_seed(theta.seed, attempt)
        for key in ("condition", "difficulty", "object", "label", "image_size"):
            assert getattr(redrawn, key) == getattr(theta, key)
    # A resample of a resample still derives from the original seed.
    assert resample_theta(first, 2) == second


def test_check_theta_names_the_bad_key():
    theta = generate_parameters("eo", "medium", 1, seed=0)[0].to_dict()
    assert check_theta(dict(theta)) is not None
    missing = {k: v for k, v in theta.items() if k != "scale"}
    with pytest.raises(ValueError, match="scale"):
        check_theta(missing)
    with pytest.raises(ValueError, match="visible_fraction"):
        check_theta({**theta, "visible_fraction": 0.0})
    with pytest.raises(ValueError, match="irradiance"):
        check_theta({**theta, "irradiance": float("nan")})
    with pytest.raises(ValueError, match="rulings"):
        check_theta({**theta, "rulings": 2.5})
    with pytest.raises(ValueError, match="image_size"):
        check_theta({**theta, "image_size": "128"})
    with pytest.raises(ValueError, match="seed"):
        check_theta({**theta, "seed": -1})
    with pytest.raises(ValueError, match="label"):
        check_theta({**theta, "label": 1.5})
