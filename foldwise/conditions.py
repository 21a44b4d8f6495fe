"""The imaging conditions (Table 3 of the paper and the rest of its Table 1), read from
``configs/conditions.yaml`` (data, not code).

Every θ parameter (``foldwise.theta.parameter_names``) has a canonical value in the table, and
the table names no parameter θ does not know, so a table and the renderer cannot drift apart.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import yaml

from foldwise.settings import get_settings

_PI_EXPR = re.compile(r"^\s*(?:(?P<num>[0-9.]+)\s*\*?\s*)?pi(?:\s*/\s*(?P<den>[0-9.]+))?\s*$")

Range = tuple[float, float]
ParameterSpec = dict[str, "Range | float"]


def parse_number(value: object, where: str) -> float:
    """A float from YAML: plain numbers, or ``pi``, ``pi/6``, ``2*pi/3``."""
    if isinstance(value, bool):
        raise ValueError(f"{where}: expected a number, got {value!r}")
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, str):
        match = _PI_EXPR.match(value)
        if match:
            num = float(match["num"]) if match["num"] else 1.0
            den = float(match["den"]) if match["den"] else 1.0
            return num * math.pi / den
    raise ValueError(f"{where}: expected a number or an expression of pi, got {value!r}")


@dataclass(frozen=True)
class Condition:
    code: str
    name: str
    # variant name -> difficulty -> parameter -> (low, high) or a fixed value.
    # Conditions without variants have the single variant "default".
    variants: dict[str, dict[str, dict[str, Range | float]]]


@dataclass(frozen=True)
class ConditionTable:
    difficulties: tuple[str, ...]
    canonical: dict[str, float]
    conditions: dict[str, Condition]
    # The paper's curriculum (its Table 3), a subset of ``conditions`` in the paper's order.
    table3: tuple[str, ...] = ()

    @property
    def codes(self) -> tuple[str, ...]:
        return tuple(self.conditions)

    def name(self, code: str) -> str:
        """A condition's full name ("focus blur"); the mixed stage's is "several conditions"."""
        from foldwise.theta import MIXED

        if code == MIXED:
            return "several conditions at once"
        return self.conditions[code].name if code in self.conditions else code

    def check(self, condition: str, difficulty: str) -> Condition:
        if condition not in self.conditions:
            raise ValueError(f"unknown condition {condition!r}; known: {', '.join(self.codes)}")
        if difficulty not in self.difficulties:
            raise ValueError(f"unknown difficulty {difficulty!r}; known: {', '.join(self.difficulties)}")
        return self.conditions[condition]


def _parse_parameters(raw: dict, canonical: dict[str, float], where: str, difficulties) -> dict:
    out: dict[str, dict[str, Range | float]] = {d: {} for d in difficulties}
    for param, per_difficulty in raw.items():
        if param not in canonical:
            raise ValueError(f"{where}.{param}: no canonical value for this parameter")
        if set(per_difficulty) != set(difficulties):
            raise ValueError(f"{where}.{param}: needs exactly the difficulties {list(difficulties)}")
        for difficulty, spec in per_difficulty.items():
            key = f"{where}.{param}.{difficulty}"
            if isinstance(spec, list):
                if len(spec) != 2:
                    raise ValueError(f"{key}: a range is [low, high]")
                low, high = (parse_number(v, key) for v in spec)
                if low > high:
                    raise ValueError(f"{key}: low {low} above high {high}")
                out[difficulty][param] = (low, high)
            else:
                out[difficulty][param] = parse_number(spec, key)
    return out


def parse_condition_table(data: dict) -> ConditionTable:
    from foldwise.theta import CANONICAL, MIXED, parameter_names

    difficulties = tuple(data["difficulties"])
    if CANONICAL in difficulties:
        # θ of difficulty "canonical" vary no condition (and a canonical_baseline stage is one).
        raise ValueError(f"difficulties: {CANONICAL!r} names images at every canonical value, not a difficulty")
    canonical = {k: parse_number(v, f"canonical.{k}") for k, v in data["canonical"].items()}
    known = parameter_names()
    unknown = sorted(set(canonical) - set(known))
    if unknown:
        raise ValueError(f"canonical: {unknown} are not θ parameters; known: {', '.join(known)}")
    missing = [name for name in known if name not in canonical]
    if missing:
        raise ValueError(f"canonical: no value for the θ parameter(s) {missing}")
    conditions: dict[str, Condition] = {}
    for code, spec in data["conditions"].items():
        where = f"conditions.{code}"
        if code == MIXED:
            raise ValueError(f"{where}: {MIXED!r} names the mixed stage, not a condition")
        if code == CANONICAL:
            raise ValueError(f"{where}: {CANONICAL!r} names the canonical baseline's stage, not a condition")
        if "variants" in spec:
            variants = {
                name: _parse_parameters(params, canonical, f"{where}.variants.{name}", difficulties)
                for name, params in spec["variants"].items()
            }
        else:
            variants = {
                "default": _parse_parameters(spec["parameters"], canonical, f"{where}.parameters", difficulties)
            }
        conditions[code] = Condition(code=code, name=spec.get("name", code), variants=variants)
    table3 = tuple(data.get("table3", conditions))
    strangers = [code for code in table3 if code not in conditions]
    if strangers:
        raise ValueError(f"table3: {strangers} are not conditions of the table")
    return ConditionTable(difficulties=difficulties, canonical=canonical, conditions=conditions, table3=table3)


@lru_cache
def load_condition_table(path: Path | None = None) -> ConditionTable:
    path = path or get_settings().configs_dir / "conditions.yaml"
    with open(path) as handle:
        return parse_condition_table(yaml.safe_load(handle))
