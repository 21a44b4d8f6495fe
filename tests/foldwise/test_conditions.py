"""The condition table as data: the shipped table matches the paper (Table 3, then the rest of
Table 1), it covers exactly θ's parameters, and malformed tables fail clearly."""

import math

import pytest

from foldwise.conditions import load_condition_table, parse_condition_table, parse_number
from foldwise.theta import V1_DEFAULTS, parameter_names

SHIPPED_CANONICAL = dict(load_condition_table().canonical)


def test_table_3_of_the_paper():
    table = load_condition_table()
    assert table.table3 == ("fb", "mb", "po", "de", "eo", "sc", "li")
    assert table.codes[:7] == table.table3
    assert table.difficulties == ("easy", "medium", "hard")
    fb = table.conditions["fb"].variants["default"]
    assert fb["hard"]["focus_blur_pct"] == (2.14, 2.92)
    mb = table.conditions["mb"].variants["default"]
    assert mb["hard"]["motion_blur_pct"] == (3.12, 4.88) and mb["easy"]["motion_blur_angle"] == (0.0, math.pi)
    po = table.conditions["po"].variants["default"]
    assert po["hard"]["yaw"] == (math.pi / 3, math.pi / 2) and po["hard"]["position_offset_m"] == (1.0, 2.0)
    assert [table.conditions["de"].variants["default"][d]["rulings"] for d in table.difficulties] == [3, 5, 8]
    assert table.conditions["eo"].variants["default"]["hard"]["visible_fraction"] == (0.1, 0.3)
    assert table.conditions["sc"].variants["small"]["hard"]["scale"] == (0.1, 0.5)
    assert table.conditions["sc"].variants["large"]["hard"]["scale"] == (2.25, 3.0)
    assert table.conditions["li"].variants["dark"]["hard"]["irradiance"] == (0.01, 0.05)
    assert table.conditions["li"].variants["bright"]["hard"]["irradiance"] == (5.0, 10.0)
    assert table.canonical["rulings"] == 2 and table.canonical["irradiance"] == 1.0


def test_the_rest_of_table_1_and_its_canonical_values_leave_version_1_images_alone():
    table = load_condition_table()
    names = {code: table.conditions[code].name for code in table.codes[7:]}
    assert names == {
        "or": "orientation", "cl": "clutter", "sh": "shadows", "sp": "specularities", "wr": "wrinkles",
        "lc": "light colour and sources", "ci": "camera intrinsics", "fv": "field-of-view crop",
        "sn": "sensor noise and compression", "mo": "several objects",
    }  # fmt: skip
    assert set(table.canonical) == set(parameter_names())
    # The canonical values of the new parameters are those a version-1 θ renders with.
    assert all(table.canonical[name] == value for name, value in V1_DEFAULTS.items() if name in table.canonical)
    assert table.conditions["or"].variants["default"]["hard"]["rotation"] == (math.pi / 2, math.pi)
    assert set(table.conditions["ci"].variants) == {"narrow", "wide"}


@pytest.mark.parametrize(
    ("text", "value"), [("pi", math.pi), ("pi/6", math.pi / 6), ("2*pi/3", 2 * math.pi / 3), (0.5, 0.5)]
)
def test_numbers_and_pi_expressions(text, value):
    assert parse_number(text, "x") == pytest.approx(value)


@pytest.mark.parametrize("bad", ["tau", "pi*", True, None])
def test_bad_numbers_name_their_place(bad):
    with pytest.raises(ValueError, match="here"):
        parse_number(bad, "here")


def test_malformed_table_names_the_key():
    data = {
        "difficulties": ["easy", "hard"],
        "canonical": dict(SHIPPED_CANONICAL),
        "conditions": {"fb": {"parameters": {"focus_blur_pct": {"easy": [2, 1], "hard": [1, 2]}}}},
    }
    with pytest.raises(ValueError, match=r"conditions.fb.parameters.focus_blur_pct.easy: low 2.0 above high 1.0"):
        parse_condition_table(data)
    data["conditions"]["fb"]["parameters"] = {"size": {"easy": 1, "hard": 2}}
    with pytest.raises(ValueError, match="no canonical value"):
        parse_condition_table(data)
    with pytest.raises(ValueError, match=r"canonical: \['blur'\] are not θ parameters"):
        parse_condition_table({**data, "canonical": {**SHIPPED_CANONICAL, "blur": 0}})
    short = {k: v for k, v in SHIPPED_CANONICAL.items() if k != "shadow"}
    with pytest.raises(ValueError, match=r"canonical: no value for the θ parameter\(s\) \['shadow'\]"):
        parse_condition_table({**data, "canonical": short})
    with pytest.raises(ValueError, match=r"table3: \['xx'\] are not conditions"):
        parse_condition_table({**data, "conditions": {}, "table3": ["xx"]})
    with pytest.raises(ValueError, match="names the mixed stage"):
        parse_condition_table({**data, "conditions": {"mixed": data["conditions"]["fb"]}})
    # "canonical" is the canonical baseline's stage (condition and difficulty), never the table's
    with pytest.raises(ValueError, match="names the canonical baseline's stage"):
        parse_condition_table({**data, "conditions": {"canonical": data["conditions"]["fb"]}})
    with pytest.raises(ValueError, match="difficulties: 'canonical' names images at every canonical value"):
        parse_condition_table({**data, "difficulties": ["easy", "canonical"]})


def test_unknown_condition_or_difficulty():
    table = load_condition_table()
    with pytest.raises(ValueError, match="unknown condition"):
        table.check("zz", "easy")
    with pytest.raises(ValueError, match="unknown difficulty"):
        table.check("fb", "brutal")
