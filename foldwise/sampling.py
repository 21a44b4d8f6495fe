"""``generate_parameters``: θ for a condition and difficulty, drawn from a seed (Algorithm 1's
Θ_tr ← generate_parameters(c, δ, m)).

Each parameter of the condition under study is drawn uniformly in its difficulty's range
(``configs/conditions.yaml``); counts uniformly among the integers of their range; the
magnitudes of signed parameters (roll, pitch, yaw, rotation, distortion) get a random sign;
a position offset, tilt or frame crop gets a uniformly random direction; a condition with
variants (scale small/large, lighting dark/bright, lens narrow/wide) draws its variant per
image with equal probability. Every other parameter keeps its canonical value. Objects are
balanced: n images cycle through shuffled rounds of all objects (the paper's "10 per
object"); the background (and the occluder of external occlusion) is drawn per image.

A *mixed* θ (``condition="mixed"``, the paper's future work: several conditions at once) holds
every condition of ``always`` and draws ``conditions_per_image`` more, distinct, from the rest of
``draw_from``, each at a difficulty drawn uniformly among the table's difficulties up to the
stage's own, and records them in ``θ.components``; where two drawn conditions set the same parameter, the later one's value
holds. A share ``negatives`` of mixed θ shows no object at all (``instances = 0``).

*Failure-driven* mixed θ (``MixedDraw.failure``) draw their (condition, difficulty) cells with
probabilities ``cell_probabilities`` gives: a share uniform, so that every cell is still seen,
the rest in proportion to how badly a scored model does on each cell (1 − its AP there), as
adversarial domain randomisation draws where the learner fails (Khirodkar et al. 2018).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from foldwise.assets import AssetNames
from foldwise.assets import asset_names as list_asset_names
from foldwise.conditions import Condition, ConditionTable, load_condition_table
from foldwise.config import AssetsConfig
from foldwise.seeds import derive_seed
from foldwise.theta import (
    CANONICAL,
    DIRECTION_OF,
    INTEGER_PARAMETERS,
    MAX_IMAGE_SIZE,
    MIXED,
    SIGNED_PARAMETERS,
    Component,
    Theta,
    parameter_names,
)

# Friendly names accepted wherever a condition is named (CLI, config files typed by hand).
_EXTRA_ALIASES = {
    "pose": "po",
    "occlusion": "eo",
    "deformation": "de",
    "deformations": "de",
    "scale": "sc",
    "lighting": "li",
    "light": "li",
    "rotation": "or",
    "noise": "sn",
    "jpeg": "sn",
    "lens": "ci",
    "intrinsics": "ci",
    "crop": "fv",
    "specular": "sp",
    "shadow": "sh",
    "objects": "mo",
}


@dataclass(frozen=True)
class MixedDraw:
    """How a mixed θ draws its conditions (see the module docstring)."""

    conditions_per_image: tuple[int, int] = (2, 4)
    draw_from: tuple[str, ...] = ()  # empty: every condition of the table
    negatives: float = 0.1
    # Conditions in every image (the wild always has some pose or roll), besides the drawn ones.
    always: tuple[str, ...] = ()
    # Failure-driven draw: (condition, difficulty, failure in 0-1) of the cells a model was scored
    # on; empty: every cell alike. failure_share: the part of the draw that follows failure.
    failure: tuple[tuple[str, str, float], ...] = ()
    failure_share: float = 0.5


def cell_probabilities(
    conditions: Sequence[str], levels: Sequence[str], failure: Mapping[tuple[str, str], float], share: float
) -> dict[tuple[str, str], float]:
    """The probability of each (condition, level) cell: ``1 - share`` spread evenly, ``share`` in
    proportion to ``failure`` (1 − AP). A cell with no score counts at the mean failure of the
    scored ones; with none scored, or no failure anywhere, the draw is uniform."""
    cells = [(c, level) for c in conditions for level in levels]
    if not cells:
        return {}
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"failure share must be in [0, 1], got {share}")
    known = [min(max(float(failure[cell]), 0.0), 1.0) for cell in cells if cell in failure]
    mean = sum(known) / len(known) if known else 0.0
    values = [min(max(float(failure[cell]), 0.0), 1.0) if cell in failure else mean for cell in cells]
    total = sum(values)
    uniform = 1.0 / len(cells)
    if total <= 0.0:
        return {cell: uniform for cell in cells}
    return {cell: (1.0 - share) * uniform + share * value / total for cell, value in zip(cells, values)}


def _normalise(name: str) -> str:
    return name.strip().lower().replace("-", "_").replace(" ", "_")


def resolve_condition(name: str, table: ConditionTable | None = None) -> str:
    """A condition code from its code (``po``) or name (``pose``, ``pose_change``, ``focus-blur``);
    ``mixed`` names the mixed stage."""
    table = table or load_condition_table()
    key = _normalise(name)
    if key in table.conditions or key == MIXED:
        return key
    aliases = {_normalise(c.name): c.code for c in table.conditions.values()}
    aliases.update({k: v for k, v in _EXTRA_ALIASES.items() if v in table.conditions})
    if key in aliases:
        return aliases[key]
    known = ", ".join(f"{c.code} ({c.name})" for c in table.conditions.values())
    raise ValueError(f"unknown condition {name!r}; known: {known}, {MIXED}")


def canonical_values(table: ConditionTable | None = None) -> dict[str, float | int]:
    table = table or load_condition_table()
    return {k: (int(v) if k in INTEGER_PARAMETERS else float(v)) for k, v in table.canonical.items()}


def _check_variant(condition: str, spec: Condition, variant: str | None) -> None:
    if variant is not None and variant not in spec.variants:
        raise ValueError(
            f"condition {condition!r} has no variant {variant!r}; known: {', '.join(sorted(spec.variants))}"
        )


def _draw_condition(
    values: dict, condition: str, difficulty: str, spec: Condition, rng: np.random.Generator, variant: str | None
) -> str:
    """Draw ``condition``'s parameters at ``difficulty`` into ``values``; returns the variant."""
    variant_names = sorted(spec.variants)
    drawn = variant_names[int(rng.integers(len(variant_names)))] if len(variant_names) > 1 else variant_names[0]
    _check_variant(condition, spec, variant)
    variant = variant or drawn
    for parameter, value_spec in spec.variants[variant][difficulty].items():
        if parameter in INTEGER_PARAMETERS:
            if isinstance(value_spec, tuple):
                low, high = math.ceil(value_spec[0]), math.floor(value_spec[1])
                value = int(rng.integers(low, high + 1)) if high > low else int(low)
            else:
                value = int(round(value_spec))
        elif isinstance(value_spec, tuple):
            low, high = value_spec
            value = float(rng.uniform(low, high)) if high > low else float(low)
        else:
            value = float(value_spec)
        if parameter in SIGNED_PARAMETERS:
            value *= float(rng.choice([-1.0, 1.0]))
        values[parameter] = value
    return variant


def draw_theta(
    condition: str,
    difficulty: str,
    seed: int,
    *,
    object_name: str,
    label: int,
    image_size: int,
    background_names: Sequence[str],
    occluder_names: Sequence[str],
    table: ConditionTable | None = None,
    variant: str | None = None,
    smooth_steps: int | None = None,
    mixed: MixedDraw | None = None,
    components: Sequence[Component] | None = None,
) -> Theta:
    """One θ for (condition, difficulty), every random choice drawn from ``seed``. ``variant``
    fixes the variant the θ would otherwise draw (the rest of the draw is unchanged);
    ``smooth_steps`` overrides the table's canonical bend smoothness; ``components`` fixes a
    mixed θ's conditions, difficulties and variants (their values are drawn)."""
    table = table or load_condition_table()
    rng = np.random.default_rng(seed)
    values: dict = {
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
        **{direction: 0.0 for direction in DIRECTION_OF},
    }
    if smooth_steps is not None:
        values["smooth_steps"] = int(smooth_steps)
    if difficulty == CANONICAL:
        return Theta.parse(values)
    if condition == MIXED and components is not None:
        for component in components:
            spec = table.check(component.condition, component.difficulty)
            _draw_condition(values, component.condition, component.difficulty, spec, rng, component.variant)
        values["components"] = [component.model_dump() for component in components]
    elif condition == MIXED:
        values["components"] = _draw_components(difficulty, rng, table, mixed or MixedDraw(), values)
    else:
        values["variant"] = _draw_condition(
            values, condition, difficulty, table.check(condition, difficulty), rng, variant
        )
    for direction, parameter in DIRECTION_OF.items():
        if values[parameter] != 0.0:
            values[direction] = float(rng.uniform(0.0, 2.0 * math.pi))
    if values["visible_fraction"] < 1.0:
        values["occluder"] = occluder_names[int(rng.integers(len(occluder_names)))]
    return Theta.parse(values)


def _draw_components(
    difficulty: str, rng: np.random.Generator, table: ConditionTable, mixed: MixedDraw, values: dict
) -> list[dict]:
    if difficulty not in table.difficulties:
        raise ValueError(f"unknown difficulty {difficulty!r}; known: {', '.join(table.difficulties)}")
    pool = [code for code in (mixed.draw_from or table.codes) if code not in mixed.always]
    low, high = mixed.conditions_per_image
    count = min(int(rng.integers(low, high + 1)), len(pool))
    reachable = table.difficulties[: table.difficulties.index(difficulty) + 1]
    cells = None
    if mixed.failure:
        failure = {(code, level): value for code, level, value in mixed.failure}
        cells = cell_probabilities([*mixed.always, *pool], reachable, failure, mixed.failure_share)
        marginal = np.array([sum(cells[code, level] for level in reachable) for code in pool])
        drawn = rng.choice(len(pool), size=count, replace=False, p=marginal / marginal.sum())
    else:
        drawn = rng.choice(len(pool), size=count, replace=False)
    # The held conditions first, so that a drawn one setting the same parameter has the last word.
    picked = [*mixed.always, *(pool[int(i)] for i in drawn)]
    components = []
    for code in picked:
        if cells is None:
            level = reachable[int(rng.integers(len(reachable)))]
        else:
            weights = np.array([cells[code, level] for level in reachable])
            level = reachable[int(rng.choice(len(reachable), p=weights / weights.sum()))]
        variant = _draw_condition(values, code, level, table.check(code, level), rng, None)
        components.append(Component(condition=code, difficulty=level, variant=variant).model_dump())
    if rng.random() < mixed.negatives:
        values["instances"] = 0
    return components


def balanced_objects(n: int, n_objects: int, rng: np.random.Generator) -> list[int]:
    """n object indices: shuffled rounds of every object, so counts differ by at most one."""
    rounds = [rng.permutation(n_objects) for _ in range(math.ceil(n / n_objects))]
    picked = np.concatenate(rounds)[:n] if rounds else np.zeros(0, int)
    return [int(i) for i in rng.permutation(picked)]


def asset_names(assets=None) -> AssetNames:
    """AssetNames from an AssetNames, an ``AssetsConfig``, an asset catalog (``.names``), or None:
    the built-in defaults. Listing names opens no image (:mod:`foldwise.assets`)."""
    if isinstance(assets, AssetNames):
        return assets
    if assets is None or isinstance(assets, AssetsConfig):
        return list_asset_names(assets)
    return assets.names


def generate_parameters(
    condition: str,
    difficulty: str,
    n: int,
    seed: int,
    *,
    image_size: int = 128,
    assets=None,
    variant: str | None = None,
    smooth_steps: int | None = None,
    mixed: MixedDraw | None = None,
) -> list[Theta]:
    """n θ for one condition (code or name; ``mixed`` for the mixed stage) at one difficulty
    (or "canonical"), from ``seed``; all of one ``variant`` when given, else each θ draws its
    variant. ``assets``: see :func:`asset_names`."""
    table = load_condition_table()
    code = resolve_condition(condition, table)
    if difficulty == CANONICAL:
        if variant is not None:
            raise ValueError(
                f"canonical θ have no variant (asked for {variant!r}): every condition keeps its canonical value"
            )
    elif code == MIXED:
        if variant is not None:
            raise ValueError(f"mixed θ have no variant of their own (asked for {variant!r})")
        if difficulty not in table.difficulties:
            raise ValueError(f"unknown difficulty {difficulty!r}; known: {', '.join(table.difficulties)}")
        draw = mixed or MixedDraw()
        for drawn in (*draw.draw_from, *draw.always):
            table.check(drawn, difficulty)
    else:
        _check_variant(code, table.check(code, difficulty), variant)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if (
        not isinstance(image_size, (int, np.integer))
        or isinstance(image_size, bool)
        or not 16 <= image_size <= MAX_IMAGE_SIZE
    ):
        raise ValueError(f"image_size must be an integer in [16, {MAX_IMAGE_SIZE}], got {image_size!r}")
    names = asset_names(assets)
    rng = np.random.default_rng(seed)
    objects = balanced_objects(n, len(names.objects), rng)
    seeds = rng.integers(0, 2**31 - 1, size=n)
    return [
        draw_theta(
            code,
            difficulty,
            int(s),
            object_name=names.objects[i],
            label=i,
            image_size=int(image_size),
            background_names=names.backgrounds,
            occluder_names=names.occluders,
            table=table,
            variant=variant,
            smooth_steps=smooth_steps,
            mixed=mixed,
        )
        for i, s in zip(objects, seeds)
    ]


def _kept_variant(theta: Theta, table: ConditionTable) -> str | None:
    """θ's variant when it is one of its condition's (a hand-edited θ may carry another: its
    resample then draws one)."""
    if theta.difficulty == CANONICAL or theta.is_mixed:
        return None
    variants = table.check(theta.condition, theta.difficulty).variants
    return theta.variant if theta.variant in variants else None


def resample_theta(theta: Theta | dict, attempt: int, assets=None) -> Theta:
    """The θ redrawn for resample ``attempt`` (1, 2, ...): same condition, difficulty, variant,
    object, image size and bend smoothness (a mixed θ: the same drawn conditions at the same
    difficulties and variants, and the same number of objects); every value redrawn from a seed
    derived from the original seed and attempt. The variant is kept so that rejections cannot
    shift a set's mix of variants (were dark images rejected more often, redrawing would turn
    them into bright ones)."""
    theta = Theta.parse(theta)
    names = asset_names(assets)
    table = load_condition_table()
    original_seed = int(theta.origin_seed if theta.origin_seed is not None else theta.seed)
    redrawn = draw_theta(
        theta.condition,
        theta.difficulty,
        derive_seed(original_seed, attempt),
        object_name=theta.object,
        label=theta.label,
        image_size=theta.image_size,
        background_names=names.backgrounds,
        occluder_names=names.occluders,
        variant=_kept_variant(theta, table),
        smooth_steps=theta.smooth_steps,
        components=theta.components if theta.is_mixed else None,
    )
    changes = {"resample": int(attempt), "origin_seed": original_seed}
    if theta.is_mixed:
        changes["instances"] = theta.instances
    return redrawn.replace(**changes)


def check_theta(theta) -> Theta:
    """θ (a Theta or its stored dict of any version) validated, or ValueError naming the bad key."""
    parsed = Theta.parse(theta)
    table = load_condition_table()
    if parsed.condition != MIXED and parsed.condition not in table.conditions:
        raise ValueError(f"θ.condition: unknown condition {parsed.condition!r}")
    return parsed


__all__ = [
    "AssetNames",
    "MixedDraw",
    "balanced_objects",
    "canonical_values",
    "check_theta",
    "derive_seed",
    "draw_theta",
    "generate_parameters",
    "parameter_names",
    "resample_theta",
    "resolve_condition",
]
