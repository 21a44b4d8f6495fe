"""θ: the small JSON-able parameter set that fully determines one rendered image.

A θ is a flat dict::

    {"version": 1, "condition": "po", "difficulty": "hard", "variant": "default",
     "seed": 123, "resample": 0, "image_size": 128,
     "object": "coffee", "label": 1, "background": "procedural:noise", "occluder": None,
     "focus_blur_pct": 0.0, "motion_blur_pct": 0.0, "motion_blur_angle": 0.0,
     "roll": -0.9, "pitch": 1.2, "yaw": 0.4, "position_offset_m": 1.7,
     "position_offset_angle": 2.1, "rulings": 2, "scale": 1.0,
     "visible_fraction": 1.0, "irradiance": 1.0}

Every Table 3 parameter is present, canonical unless its condition is under study (Table 3
lives in ``configs/conditions.yaml``). ``seed`` drives what the renderer still draws at
random (the sheet's deformation, the background crop, the occluder's shape and place), so
the same θ always gives the same bytes and box.

Sampling (``generate_parameters``): each parameter of the condition under study is drawn
uniformly in its difficulty's range; roll, pitch and yaw are magnitudes in the range with a
random sign each; the position offset is a magnitude in the range in a uniformly random
direction (``position_offset_angle``) in the plane facing the camera (see camera.py for
why not 3D); conditions with variants (scale small/large, lighting dark/bright) draw the
variant per image with equal probability. Objects are balanced: n images cycle through
shuffled rounds of all objects (the paper's "10 per object"); background (and occluder for
external occlusion) are drawn uniformly per image.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from foldwise.conditions import ConditionTable, load_condition_table
from foldwise.seeds import derive_seed

THETA_VERSION = 1
CANONICAL = "canonical"
MAX_IMAGE_SIZE = 8192

# Friendly names accepted wherever a condition is named (CLI, config files typed by hand).
_EXTRA_ALIASES = {
    "pose": "po",
    "occlusion": "eo",
    "deformation": "de",
    "deformations": "de",
    "scale": "sc",
    "lighting": "li",
    "light": "li",
}


def _normalise(name: str) -> str:
    return name.strip().lower().replace("-", "_").replace(" ", "_")


def resolve_condition(name: str, table: ConditionTable | None = None) -> str:
    """A condition code from its code (``po``) or name (``pose``, ``pose_change``, ``focus-blur``)."""
    table = table or load_condition_table()
    key = _normalise(name)
    if key in table.conditions:
        return key
    aliases = {_normalise(c.name): c.code for c in table.conditions.values()}
    aliases.update({k: v for k, v in _EXTRA_ALIASES.items() if v in table.conditions})
    if key in aliases:
        return aliases[key]
    known = ", ".join(f"{c.code} ({c.name})" for c in table.conditions.values())
    raise ValueError(f"unknown condition {name!r}; known: {known}")


def canonical_values(table: ConditionTable | None = None) -> dict[str, float | int]:
    table = table or load_condition_table()
    return {k: (int(v) if k == "rulings" else float(v)) for k, v in table.canonical.items()}


def _draw_value(spec, rng: np.random.Generator) -> float:
    if isinstance(spec, tuple):
        low, high = spec
        return float(rng.uniform(low, high)) if high > low else float(low)
    return float(spec)


def _check_variant(condition: str, spec, variant: str | None) -> None:
    if variant is not None and variant not in spec.variants:
        raise ValueError(f"condition {condition!r} has no variant {variant!r}; known: {', '.join(sorted(spec.variants))}")


def draw_theta(
    condition: str,
    difficulty: str,
    seed: int,
    *,
    object_name: str,
    label: int,
    image_size: int,
    background_names: list[str],
    occluder_names: list[str],
    table: ConditionTable | None = None,
    variant: str | None = None,
) -> dict[str, Any]:
    """One θ for (condition, difficulty), every random choice drawn from ``seed``. ``variant``
    (e.g. "dark" for lighting) fixes the variant the θ would otherwise draw; the rest of the
    draw is the same as without it."""
    table = table or load_condition_table()
    rng = np.random.default_rng(seed)
    theta: dict[str, Any] = {
        "version": THETA_VERSION,
        "condition": condition,
        "difficulty": difficulty,
        "variant": "default",
        "seed": int(seed),
        "resample": 0,
        "image_size": int(image_size),
        "object": object_name,
        "label": int(label),
        "background": background_names[int(rng.integers(len(background_names)))],
        "occluder": None,
        **canonical_values(table),
        "position_offset_angle": 0.0,
    }
    if difficulty == CANONICAL:
        return theta
    spec = table.check(condition, difficulty)
    variant_names = sorted(spec.variants)
    drawn = variant_names[int(rng.integers(len(variant_names)))] if len(variant_names) > 1 else variant_names[0]
    _check_variant(condition, spec, variant)
    variant = variant or drawn
    theta["variant"] = variant
    for parameter, value_spec in spec.variants[variant][difficulty].items():
        value = _draw_value(value_spec, rng)
        if parameter in ("roll", "pitch", "yaw"):
            value *= float(rng.choice([-1.0, 1.0]))
        if parameter == "rulings":
            value = int(round(value))
        theta[parameter] = value
    if theta["position_offset_m"] != 0.0:
        theta["position_offset_angle"] = float(rng.uniform(0.0, 2.0 * math.pi))
    if theta["visible_fraction"] < 1.0:
        theta["occluder"] = occluder_names[int(rng.integers(len(occluder_names)))]
    return theta


def balanced_objects(n: int, n_objects: int, rng: np.random.Generator) -> list[int]:
    """n object indices: shuffled rounds of every object, so counts differ by at most one."""
    rounds = [rng.permutation(n_objects) for _ in range(math.ceil(n / n_objects))]
    picked = np.concatenate(rounds)[:n] if rounds else np.zeros(0, int)
    return [int(i) for i in rng.permutation(picked)]


def generate_parameters(
    condition: str,
    difficulty: str,
    n: int,
    seed: int,
    *,
    image_size: int = 128,
    assets=None,
    variant: str | None = None,
) -> list[dict]:
    """n θ for one condition (code or name) at one difficulty (or "canonical"), from ``seed``;
    all of one ``variant`` (scale "small" or "large", lighting "dark" or "bright") when given,
    else each θ draws its variant."""
    from workers.render.assets import load_assets

    table = load_condition_table()
    code = resolve_condition(condition, table)
    if difficulty != CANONICAL:
        _check_variant(code, table.check(code, difficulty), variant)
    elif variant is not None:
        raise ValueError(f"canonical θ have no variant (asked for {variant!r}): every condition keeps its canonical value")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if not isinstance(image_size, (int, np.integer)) or not 16 <= image_size <= MAX_IMAGE_SIZE:
        raise ValueError(f"image_size must be an integer in [16, {MAX_IMAGE_SIZE}], got {image_size!r}")
    assets = assets or load_assets()
    rng = np.random.default_rng(seed)
    objects = balanced_objects(n, len(assets.objects), rng)
    seeds = rng.integers(0, 2**31 - 1, size=n)
    backgrounds = [a.name for a in assets.backgrounds]
    occluders = [a.name for a in assets.occluders]
    return [
        draw_theta(
            code,
            difficulty,
            int(s),
            object_name=assets.objects[i].name,
            label=i,
            image_size=int(image_size),
            background_names=backgrounds,
            occluder_names=occluders,
            table=table,
            variant=variant,
        )
        for i, s in zip(objects, seeds)
    ]


def _kept_variant(theta: dict) -> str | None:
    """θ's variant when it is one of its condition's (a hand-edited θ may carry another: its
    resample then draws one)."""
    if theta["difficulty"] == CANONICAL:
        return None
    variants = load_condition_table().check(theta["condition"], theta["difficulty"]).variants
    return theta.get("variant") if theta.get("variant") in variants else None


def resample_theta(theta: dict, attempt: int, assets=None) -> dict:
    """The θ redrawn for resample ``attempt`` (1, 2, ...): same condition, difficulty, variant,
    object and image size; every other choice redrawn from a seed derived from the original seed
    and attempt. The variant is kept so that rejections cannot shift a set's mix of variants
    (were dark images rejected more often, redrawing would turn them into bright ones)."""
    from workers.render.assets import load_assets

    assets = assets or load_assets()
    original_seed = int(theta.get("origin_seed", theta["seed"]))
    redrawn = draw_theta(
        theta["condition"],
        theta["difficulty"],
        derive_seed(original_seed, attempt),
        object_name=theta["object"],
        label=int(theta["label"]),
        image_size=int(theta["image_size"]),
        background_names=[a.name for a in assets.backgrounds],
        occluder_names=[a.name for a in assets.occluders],
        variant=_kept_variant(theta),
    )
    redrawn["resample"] = int(attempt)
    redrawn["origin_seed"] = original_seed
    return redrawn


_REQUIRED = ("condition", "difficulty", "seed", "image_size", "object", "label", "background")


def check_theta(theta: dict) -> dict:
    """θ with every key present and sane, or ValueError naming the bad key."""
    if not isinstance(theta, dict):
        raise ValueError(f"θ must be a dict, got {type(theta).__name__}")
    table = load_condition_table()
    missing = [k for k in _REQUIRED + tuple(table.canonical) if k not in theta]
    if missing:
        raise ValueError(f"θ lacks the key(s) {missing}")
    if theta["condition"] not in table.conditions:
        raise ValueError(f"θ.condition: unknown condition {theta['condition']!r}")
    size = theta["image_size"]
    if not isinstance(size, (int, np.integer)) or isinstance(size, bool) or not 16 <= size <= MAX_IMAGE_SIZE:
        raise ValueError(f"θ.image_size: expected an integer in [16, {MAX_IMAGE_SIZE}], got {size!r}")
    for key in ("seed", "label"):
        value = theta[key]
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 0:
            raise ValueError(f"θ.{key}: expected a non-negative integer, got {value!r}")
    for key in table.canonical:
        value = theta[key]
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not math.isfinite(value):
            raise ValueError(f"θ.{key}: expected a finite number, got {value!r}")
    checks = {
        "focus_blur_pct": theta["focus_blur_pct"] >= 0,
        "motion_blur_pct": theta["motion_blur_pct"] >= 0,
        "position_offset_m": theta["position_offset_m"] >= 0,
        "scale": theta["scale"] > 0,
        "visible_fraction": 0 < theta["visible_fraction"] <= 1,
        "irradiance": theta["irradiance"] >= 0,
        "rulings": theta["rulings"] >= 0 and float(theta["rulings"]).is_integer(),
    }
    for key, ok in checks.items():
        if not ok:
            raise ValueError(f"θ.{key}: value {theta[key]!r} out of range")
    return theta
