"""Experiment configs: every shipped config loads, and errors name the offending key."""

import re
from pathlib import Path

import pytest

from foldwise.config import ConfigError, load_config, parse_config, parse_config_text
from foldwise.documents import MAX_NESTING
from foldwise.settings import REPO_ROOT
from tests.foldwise.config_fields import NUMERIC_FIELDS

CONFIGS = sorted((REPO_ROOT / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", [p for p in CONFIGS if p.name != "conditions.yaml"], ids=lambda p: p.name)
def test_shipped_configs_are_valid(path):
    config = load_config(path)
    assert config.stage_order()
    assert config.active_learning.M >= 1


def test_paper_config_has_the_papers_values():
    config = load_config(REPO_ROOT / "configs/paper.yaml")
    al = config.active_learning
    assert (al.M, al.N, al.tau, al.m, al.t) == (3, 8, 0.02, 50, 1000)
    assert config.test_set.per_stage == 150 and len(config.test_pairs()) == 21  # 3,150 test images
    assert {c for c, _ in config.test_pairs()} == set(config.curriculum.conditions)
    assert config.evaluation.score_threshold == 0.8


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"name": "x", "active_learning": {"tua": 0.1}}, "active_learning.tua: unknown key"),
        ({"name": "x", "active_learning": {"M": 0}}, "active_learning.M"),
        ({"name": "x", "active_learning": {"tau": -1}}, "active_learning.tau"),
        ({"name": "x", "curriculum": {"conditions": ["fb", "xx"]}}, "unknown condition 'xx'"),
        ({"name": "x", "curriculum": {"difficulties": ["easy", "extreme"]}}, "unknown difficulty 'extreme'"),
        ({"name": "x", "curriculum": {"conditions": ["fb", "fb"]}}, "listed twice"),
        ({"name": "x", "detector": {"family": "ssd"}}, "detector.family"),
        ({"name": "x", "render": {"backend": "eevee"}}, "render.backend"),
        ({"name": "x", "render": {"image_size": 8}}, "render.image_size"),
        ({"name": "x", "bogus": 1}, "bogus: unknown key"),
        ({"name": "x", "detector": {"learning_rate": float("inf")}}, "detector.learning_rate"),
        ({"seed": 1}, "name: Field required"),
        ({"name": "   "}, "name"),
    ],
)
def test_errors_name_the_offending_key(data, key):
    with pytest.raises(ConfigError) as error:
        parse_config(data)
    assert key in str(error.value)


def test_non_mapping_and_non_yaml_are_rejected_clearly():
    with pytest.raises(ConfigError, match="mapping"):
        parse_config_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="not YAML"):
        parse_config_text("name: [unclosed")
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(Path("/nonexistent/config.yaml"))


def test_json_is_accepted_as_yaml():
    config = parse_config_text('{"name": "j", "active_learning": {"M": 2}}')
    assert config.active_learning.M == 2


def test_config_round_trips_through_json():
    config = load_config(REPO_ROOT / "configs/smoke.yaml")
    assert parse_config(config.model_dump(mode="json")) == config


MIXED_AFTER_SINGLES = {
    "name": "m",
    "curriculum": {
        "conditions": ["fb", "sc"],
        "difficulties": ["easy", "hard"],
        "mixed": {"difficulties": ["medium", "hard"], "active_learning": {"t": 7, "max_increments": 2}},
    },
}


def test_a_mixed_stage_ends_the_curriculum_with_its_own_settings():
    config = parse_config(MIXED_AFTER_SINGLES)
    singles = [("fb", "easy"), ("fb", "hard"), ("sc", "easy"), ("sc", "hard")]
    assert config.stage_order() == [*singles, ("mixed", "medium"), ("mixed", "hard")]
    assert config.test_pairs() == config.stage_order()
    # The mixed stage's own settings apply to it alone; every other stage keeps the curriculum's.
    mixed = config.stage_active_learning("mixed")
    assert (mixed.t, mixed.max_increments) == (7, 2)
    assert mixed.m == config.active_learning.m
    assert config.stage_active_learning("fb") == config.active_learning


def test_mixed_stages_alone_still_test_every_condition():
    data = {
        **MIXED_AFTER_SINGLES,
        "curriculum": {**MIXED_AFTER_SINGLES["curriculum"], "single_condition_stages": False},
    }
    config = parse_config(data)
    assert config.stage_order() == [("mixed", "medium"), ("mixed", "hard")]
    singles = [("fb", "easy"), ("fb", "hard"), ("sc", "easy"), ("sc", "hard")]
    assert config.test_pairs() == [*singles, ("mixed", "medium"), ("mixed", "hard")]


def test_no_single_condition_stage_and_no_mixed_stage_leaves_nothing_to_train():
    with pytest.raises(ConfigError, match="single_condition_stages: false leaves no stage to train"):
        parse_config({"name": "x", "curriculum": {"single_condition_stages": False}})


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("sampling", "adversarial", "curriculum.mixed.sampling: Input should be 'uniform' or 'failure'"),
        ("failure_share", 1.5, "curriculum.mixed.failure_share: Input should be less than or equal to 1"),
    ],
)
def test_failure_sampling_settings_are_checked(key, value, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        parse_config({"name": "x", "curriculum": {"mixed": {key: value}}})


def test_the_loop_score_is_one_of_the_two_maps():
    assert parse_config({"name": "x"}).evaluation.loop_score == "map"
    with pytest.raises(ConfigError, match="evaluation.loop_score"):
        parse_config({"name": "x", "evaluation": {"loop_score": "recall"}})


@pytest.mark.parametrize(
    ("mixed", "key"),
    [
        ({"conditions_per_image": [3, 2]}, "conditions_per_image: needs 1 <= low <= high"),
        (
            {"conditions_per_image": [1, 10]},
            "curriculum.mixed.conditions_per_image.1: Input should be less than or equal to 9",
        ),
        (
            {"conditions_per_image": [0, 2]},
            "curriculum.mixed.conditions_per_image.0: Input should be greater than or equal to 1",
        ),
        ({"draw_from": ["fb", "mb"], "conditions_per_image": [1, 3]}, "only 2 to draw from"),
        ({"difficulties": ["hard", "medium", "hard"]}, "curriculum.mixed: difficulties: a difficulty is listed twice"),
        ({"draw_from": ["fb", "mb", "fb"]}, "curriculum.mixed: draw_from: a condition is listed twice"),
        ({"draw_from": ["fb", "zz"]}, "draw_from[1]: unknown condition 'zz'"),
        ({"always": ["or", "zz"]}, "always[1]: unknown condition 'zz'"),
        ({"always": ["or", "or"]}, "always: a condition is listed twice"),
        ({"draw_from": ["fb", "mb", "po"], "always": ["or"]}, "always: ['or'] not in draw_from"),
        (
            {"draw_from": ["fb", "mb", "or"], "always": ["or"], "conditions_per_image": [1, 3]},
            "only 2 to draw from besides always (or)",
        ),
        ({"difficulties": ["brutal"]}, "unknown difficulty 'brutal'"),
        ({"negatives": 0.95}, "curriculum.mixed.negatives"),
        ({"active_learning": {"t": 0}}, "curriculum.mixed.active_learning.t"),
        ({"active_learning": {"q": 1}}, "curriculum.mixed.active_learning.q: unknown key"),
    ],
)
def test_bad_mixed_stages_name_the_key(mixed, key):
    with pytest.raises(ConfigError) as caught:
        parse_config({"name": "x", "curriculum": {"mixed": mixed}})
    assert key in str(caught.value)


def test_covers_table3_all_and_curriculum():
    base = {"name": "x", "curriculum": {"conditions": ["fb"], "difficulties": ["easy"], "mixed": {}}}
    pairs = {
        covers: parse_config({**base, "test_set": {"covers": covers}}).test_pairs()
        for covers in ("table3", "all", "curriculum")
    }
    assert len(pairs["table3"]) == 21 and len(pairs["all"]) == 51
    assert pairs["curriculum"] == [("fb", "easy"), ("mixed", "hard")]


def test_a_mixed_stage_may_grow_its_training_set_while_the_others_reset():
    config = parse_config({"name": "g", "curriculum": {"mixed": {"active_learning": {"training_set": "grow"}}}})
    assert config.stage_active_learning("mixed").training_set == "grow"
    assert config.stage_active_learning("fb").training_set == "reset"
    with pytest.raises(ConfigError, match="training_set"):
        parse_config({"name": "g", "curriculum": {"mixed": {"active_learning": {"training_set": "keep"}}}})


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"active_learning": {"m": "50"}}, "active_learning.m: expected a number, got the text '50'"),
        ({"active_learning": {"m": 50.0}}, "active_learning.m: expected a whole number, got 50.0"),
        ({"active_learning": {"m": True}}, "active_learning.m: expected a number, got a boolean"),
        ({"active_learning": {"tau": "0.02"}}, "active_learning.tau: expected a number, got the text '0.02'"),
        ({"detector": {"learning_rate": False}}, "detector.learning_rate: expected a number, got a boolean"),
        ({"render": {"smooth_steps": 2.5}}, "render.smooth_steps: expected a whole number, got 2.5"),
        ({"seed": "7"}, "seed: expected a number, got the text '7'"),
        (
            {"detector": {"anchor_size_range": [0.1, "1"]}},
            "detector.anchor_size_range[1]: expected a number, got the text '1'",
        ),
        (
            {"curriculum": {"mixed": {"conditions_per_image": [2, 4.0]}}},
            "conditions_per_image[1]: expected a whole number, got 4.0",
        ),
        (
            {"curriculum": {"mixed": {"active_learning": {"t": "100"}}}},
            "curriculum.mixed.active_learning.t: expected a number",
        ),
    ],
)
def test_numbers_are_numbers(data, message):
    # pydantic alone reads "50" and 50.0 as the count 50, and true as 1.
    with pytest.raises(ConfigError) as caught:
        parse_config({"name": "x", **data})
    assert message in str(caught.value)


def test_a_whole_number_is_a_valid_float_and_none_stays_allowed():
    config = parse_config({"name": "x", "detector": {"learning_rate": 1}, "render": {"smooth_steps": None}})
    assert config.detector.learning_rate == 1.0 and config.render.smooth_steps is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("name: x\nname: y\n", "duplicate key 'name' (line 2, column 1)"),
        ("name: x\nactive_learning:\n  m: 5\n  t: 9\n  m: 6\n", "duplicate key 'm' (line 5, column 3)"),
        ("name: x\ncurriculum: {mixed: {negatives: 0.1, negatives: 0.2}}\n", "duplicate key 'negatives'"),
    ],
)
def test_a_key_given_twice_is_an_error_naming_it(text, message):
    # PyYAML keeps the last value of a repeated key without a word.
    with pytest.raises(ConfigError) as caught:
        parse_config_text(text)
    assert message in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize(
    "text",
    [
        "name: x\nbogus: " + "[" * 10_000 + "]" * 10_000 + "\n",
        "name: x\nbogus: " + "{a: " * 10_000 + "1" + "}" * 10_000 + "\n",
        "name: x\nbogus:\n" + "".join(" " * i + "- \n" for i in range(1, 2_000)),
    ],
    ids=["flow lists", "flow mappings", "block lists"],
)
def test_deep_nesting_is_a_clear_error_not_a_recursion_error(text):
    with pytest.raises(ConfigError) as caught:
        parse_config_text(text)
    assert str(caught.value).startswith(f"invalid experiment config: nested deeper than {MAX_NESTING} levels (line ")


def test_deep_nesting_through_aliases_and_aliases_that_contain_themselves():
    # Each line is shallow; the aliases chain them 40 levels deep.
    chain = "name: x\ncurriculum:\n  l0: &l0 [1]\n" + "".join(f"  l{i}: &l{i} [*l{i - 1}]\n" for i in range(1, 40))
    with pytest.raises(ConfigError, match="nested deeper than"):
        parse_config_text(chain)
    with pytest.raises(ConfigError, match="refers to the mapping or list that contains it"):
        parse_config_text("name: x\ncurriculum: &loop {conditions: [*loop]}\n")


def test_shared_aliases_are_measured_once_and_counted_as_often_as_used():
    # "Billion laughs": 10**9 leaves if walked, 100 distinct lists. Walked once, refused by what
    # it stands for before any validator walks it whole.
    text = "name: x\nassets:\n  l0: &l0 [a, a, a, a, a, a, a, a, a, a]\n" + "".join(
        f"  l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]\n" for i in range(1, 9)
    )
    with pytest.raises(ConfigError, match="invalid experiment config: more than 5,000 values"):
        parse_config_text(text)


@pytest.mark.parametrize("text", ["name: !!binary AA==\n", "name: x\nassets: {objects: !!binary L3NydgBh}\n"])
def test_binary_data_is_refused(text):
    # pydantic took the bytes as text: a NUL reached PostgreSQL through `!!binary AA==`.
    with pytest.raises(ConfigError, match=r"!!binary data has no place in a config \(line \d, column \d+\)"):
        parse_config_text(text)


def test_yaml_scalars_read_as_yaml_1_2_core():
    config = parse_config_text(
        "name: no\nseed: 010\ndetector: {learning_rate: 1e-3, weight_decay: 5E-4, grad_clip_norm: 1_000}\n"
        "evaluation: {coco: false}\nactive_learning: {t: 1_000}\n"
    )
    # YAML 1.1 reads 1e-3 as text, `no` as false and 010 as octal 8.
    assert config.detector.learning_rate == 0.001 and config.detector.weight_decay == 0.0005
    assert config.name == "no" and config.seed == 10
    assert config.detector.grad_clip_norm == 1000.0 and config.active_learning.t == 1000
    assert parse_config_text("name: 2024-01-01\n").name == "2024-01-01"  # text, not a date
    with pytest.raises(ConfigError, match="active_learning.m: expected a whole number, got 1000.0"):
        parse_config_text("name: x\nactive_learning: {m: 1e3}\n")


def test_a_long_list_of_errors_is_cut_short():
    with pytest.raises(ConfigError) as caught:
        parse_config({"name": "x", **{f"bogus{i}": 1 for i in range(100)}})
    assert str(caught.value).count("unknown key") == 20 and "and 80 more errors" in str(caught.value)


@pytest.mark.parametrize(
    ("detector", "message"),
    [
        ({"learning_rate": 10.5}, "detector.learning_rate: Input should be less than or equal to 10"),
        ({"weight_decay": 1.5}, "detector.weight_decay: Input should be less than or equal to 1"),
        ({"grad_clip_norm": 1e7}, "detector.grad_clip_norm: Input should be less than or equal to 1000000"),
    ],
)
def test_optimiser_settings_have_sane_upper_bounds(detector, message):
    with pytest.raises(ConfigError) as caught:
        parse_config({"name": "x", "detector": detector})
    assert message in str(caught.value)
    # At the bound itself the setting is accepted.
    (key, _), bound = next(iter(detector.items())), {"learning_rate": 10, "weight_decay": 1, "grad_clip_norm": 1e6}
    assert getattr(parse_config({"name": "x", "detector": {key: bound[key]}}).detector, key) == bound[key]


def test_the_bounds_are_in_the_schema():
    # Clients read the bounds from the schema (GET /openapi.json) before they send a config.
    from foldwise.config import ExperimentConfig

    definitions = ExperimentConfig.model_json_schema()["$defs"]
    detector = definitions["DetectorConfig"]["properties"]
    assert (detector["learning_rate"]["maximum"], detector["weight_decay"]["maximum"]) == (10.0, 1.0)
    assert detector["grad_clip_norm"]["maximum"] == 1e6
    per_image = definitions["MixedStageConfig"]["properties"]["conditions_per_image"]["prefixItems"]
    assert [item["maximum"] for item in per_image] == [9, 9]


def test_every_number_in_the_config_has_an_upper_bound_in_the_schema():
    from foldwise.config import ExperimentConfig

    assert len(NUMERIC_FIELDS) > 40
    schema = ExperimentConfig.model_json_schema()

    def has_maximum(node) -> bool:
        node = schema["$defs"][node["$ref"].split("/")[-1]] if "$ref" in node else node
        if "maximum" in node or "exclusiveMaximum" in node:
            return True
        if node.get("type") == "array" and "items" in node:  # a list of numbers: each bounded
            return has_maximum(node["items"])
        options = [o for o in node.get("anyOf", []) if o.get("type") != "null"]
        return bool(options) and all(has_maximum(o) for o in options)

    def property_of(key):
        *sections, name = key.split(".")
        node = schema
        for section in sections:
            ref = node["properties"][section]
            ref = next((o for o in ref.get("anyOf", [ref]) if "$ref" in o), ref)
            node = schema["$defs"][ref["$ref"].split("/")[-1]]
        return node["properties"][name]

    # anchor_size_range is bounded by its validator (0 < low < high <= 4), tested above.
    unbounded = []
    for key in NUMERIC_FIELDS:
        node = property_of(key)
        items = node.get("prefixItems")
        if key != "detector.anchor_size_range" and not (
            all(has_maximum(i) for i in items) if items else has_maximum(node)
        ):
            unbounded.append(key)
    assert unbounded == []


@pytest.mark.parametrize(
    ("family", "backbone", "known"),
    [
        ("faster_rcnn", "vgg16", "known: mobilenet_v3_large_fpn, mobilenet_v3_large_320_fpn, resnet50_fpn_v2"),
        ("fast_rcnn", "resnet18", "known: mobilenet_v3_large_fpn"),
        ("yolo", "vgg16_fpn", "known: mobilenet_v3_large, mobilenet_v3_small, resnet101"),
    ],
)
def test_a_backbone_the_family_cannot_build_is_refused_before_any_work(family, backbone, known):
    # It was found at the first training step, after the renders.
    with pytest.raises(ConfigError) as caught:
        parse_config({"name": "x", "detector": {"family": family, "backbone": backbone}})
    assert f"detector: backbone {backbone!r} is not supported by the {family} detector" in str(caught.value)
    assert known in str(caught.value)


@pytest.mark.parametrize(
    ("family", "backbone"),
    [
        ("faster_rcnn", "resnet50_fpn_v2"),
        ("fast_rcnn", "mobilenet_v3_large_320_fpn"),
        ("yolo", "resnet18"),
        ("yolo", "mobilenet_v3_large_fpn"),
    ],
)
def test_every_backbone_a_family_builds_is_accepted(family, backbone):
    assert (
        parse_config({"name": "x", "detector": {"family": family, "backbone": backbone}}).detector.backbone == backbone
    )


LEARNABILITY = {"name": "l", "kind": "learnability"}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (
            {"name": "x", "kind": "learnabilty"},
            "kind: Input should be 'active_learning', 'learnability' or 'canonical_baseline'",
        ),
        (
            {**LEARNABILITY, "learnability": {"kappa": 0}},
            "learnability.kappa: Input should be greater than or equal to 1",
        ),
        (
            {**LEARNABILITY, "learnability": {"kappa": 10**6}},
            "learnability.kappa: Input should be less than or equal to",
        ),
        ({**LEARNABILITY, "learnability": {"kapa": 3}}, "learnability.kapa: unknown key"),
        ({**LEARNABILITY, "learnability": {"kappa": True}}, "learnability.kappa: expected a number, got a boolean"),
        ({"name": "x", "learnability": {"kappa": 3}}, "learnability: only read by kind: learnability"),
        ({**LEARNABILITY, "active_learning": {"M": 2}}, "active_learning.M: kind: learnability has no stopping rule"),
        (
            {**LEARNABILITY, "active_learning": {"max_increments": 5}},
            "active_learning.max_increments: kind: learnability",
        ),
        ({**LEARNABILITY, "curriculum": {"mixed": {}}}, "curriculum.mixed: kind: learnability has no mixed stage"),
        (
            {**LEARNABILITY, "test_set": {"covers": "table3"}},
            "test_set.covers: kind: learnability tests each condition",
        ),
    ],
)
def test_kind_and_learnability_errors_name_the_key(data, message):
    with pytest.raises(ConfigError) as error:
        parse_config(data)
    assert f"\n  {message}" in str(error.value)


def test_kind_defaults_to_active_learning_and_learnability_keeps_its_kappa_through_json():
    assert parse_config({"name": "x"}).kind == "active_learning"
    config = parse_config({**LEARNABILITY, "learnability": {"kappa": 3}, "active_learning": {"m": 7, "t": 5}})
    assert config.stage_increments_cap("fb") == 3
    # the stored form holds every key, the stopping rule's defaults included: it must load again
    assert parse_config(config.model_dump(mode="json")) == config
    assert parse_config({"name": "x", "active_learning": {"max_increments": 6}}).stage_increments_cap("fb") == 6


CANONICAL_BASELINE = {"name": "b", "kind": "canonical_baseline"}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (
            {**CANONICAL_BASELINE, "canonical_baseline": {"increments": 0}},
            "canonical_baseline.increments: Input should be greater",
        ),
        ({**CANONICAL_BASELINE, "canonical_baseline": {"iterations": 3}}, "canonical_baseline.iterations: unknown key"),
        (
            {"name": "x", "canonical_baseline": {"increments": 3}},
            "canonical_baseline: only read by kind: canonical_baseline",
        ),
        (
            {**CANONICAL_BASELINE, "learnability": {"kappa": 3}},
            "learnability: only read by kind: learnability (this config's kind is canonical_baseline)",
        ),
        (
            {**CANONICAL_BASELINE, "active_learning": {"tau": 0.1}},
            "active_learning.tau: kind: canonical_baseline has no stopping rule; canonical_baseline.increments sets",
        ),
        (
            {**CANONICAL_BASELINE, "curriculum": {"mixed": {}}},
            "curriculum.mixed: kind: canonical_baseline has no mixed stage (it trains on canonical images only",
        ),
    ],
)
def test_canonical_baseline_errors_name_the_key(data, message):
    with pytest.raises(ConfigError) as error:
        parse_config(data)
    assert f"\n  {message}" in str(error.value)


def test_canonical_baseline_trains_one_canonical_stage_and_tests_the_curriculum_conditions():
    from foldwise.conditions import load_condition_table

    config = parse_config({
        **CANONICAL_BASELINE, "canonical_baseline": {"increments": 4}, "active_learning": {"m": 7, "t": 5},
        "curriculum": {"conditions": ["fb", "wr"], "difficulties": ["easy", "hard"]},
    })  # fmt: skip
    assert config.stage_order() == [("canonical", "canonical")]
    assert config.stage_increments_cap("canonical") == 4
    assert config.test_pairs() == [("fb", "easy"), ("fb", "hard"), ("wr", "easy"), ("wr", "hard")]
    assert parse_config(config.model_dump(mode="json")) == config
    # covers: all scores every condition of the table at each difficulty, as the paper's Table 2
    table = load_condition_table()
    everything = parse_config({**CANONICAL_BASELINE, "test_set": {"covers": "all"}}).test_pairs()
    assert everything == [(c, d) for c in table.codes for d in table.difficulties]


def test_canonical_baseline_quick_tests_the_papers_seven_conditions_at_three_difficulties():
    from foldwise.conditions import load_condition_table

    config = load_config(REPO_ROOT / "configs/canonical_baseline_quick.yaml")
    assert config.kind == "canonical_baseline"
    assert config.curriculum.conditions == list(load_condition_table().table3)
    assert config.stage_order() == [("canonical", "canonical")]
    assert len(config.test_pairs()) == 21


def test_learnability_quick_covers_the_papers_seven_conditions_at_three_difficulties():
    from foldwise.conditions import load_condition_table

    config = load_config(REPO_ROOT / "configs/learnability_quick.yaml")
    assert config.kind == "learnability"
    assert config.curriculum.conditions == list(load_condition_table().table3)
    assert config.curriculum.difficulties == ["easy", "medium", "hard"]
    assert len(config.test_pairs()) == 21


CANONICAL_START = {"start": "canonical", "canonical_increments": 5}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (
            {**LEARNABILITY, "learnability": {"start": "pretrained"}},
            "learnability.start: Input should be 'initial' or 'canonical'",
        ),
        (
            {**LEARNABILITY, "learnability": {"canonical_increments": 5}},
            "learnability.canonical_increments: only read with learnability.start: canonical",
        ),
        (
            {**LEARNABILITY, "learnability": {"start": "initial", "canonical_increments": 5}},
            "learnability.canonical_increments: only read with learnability.start: canonical",
        ),
        (
            {**LEARNABILITY, "learnability": {"start": "canonical"}},
            "learnability.canonical_increments: learnability.start: canonical needs",
        ),
        (
            {**LEARNABILITY, "learnability": {**CANONICAL_START, "canonical_increments": 0}},
            "learnability.canonical_increments: Input should be greater than or equal to 1",
        ),
        (
            {**LEARNABILITY, "learnability": {**CANONICAL_START, "canonical_increments": 1.5}},
            "learnability.canonical_increments: expected a whole number",
        ),
        ({"name": "x", "learnability": CANONICAL_START}, "learnability: only read by kind: learnability"),
        (
            {**CANONICAL_BASELINE, "learnability": {"start": "canonical", "canonical_increments": 3}},
            "learnability: only read by kind: learnability",
        ),
    ],
)
def test_learnability_start_errors_name_the_key(data, message):
    with pytest.raises(ConfigError) as error:
        parse_config(data)
    assert f"\n  {message}" in str(error.value)


def test_a_canonical_start_adds_one_canonical_stage_first_and_keeps_it_through_json():
    config = parse_config({**LEARNABILITY, "learnability": {"kappa": 3, **CANONICAL_START},
                           "curriculum": {"conditions": ["fb", "po"], "difficulties": ["easy", "hard"]}})  # fmt: skip
    assert config.learnability.start == "canonical" and config.starts_from_canonical
    assert config.stage_order() == [("canonical", "canonical")] + [
        (c, d) for c in ("fb", "po") for d in ("easy", "hard")
    ]
    assert config.stage_increments_cap("canonical") == 5 and config.stage_increments_cap("po") == 3
    assert config.test_pairs() == [(c, d) for c in ("fb", "po") for d in ("easy", "hard")]
    assert parse_config(config.model_dump(mode="json")) == config
    # the default: today's behaviour, no canonical stage
    plain = parse_config(LEARNABILITY)
    assert plain.learnability.start == "initial" and plain.learnability.canonical_increments is None
    assert not plain.starts_from_canonical and ("canonical", "canonical") not in plain.stage_order()
    assert parse_config(plain.model_dump(mode="json")) == plain


def test_learnability_canonical_quick_is_learnability_quick_with_a_canonical_start():
    quick = load_config(REPO_ROOT / "configs/learnability_quick.yaml").model_dump(mode="json")
    canonical = load_config(REPO_ROOT / "configs/learnability_canonical_quick.yaml")
    assert canonical.learnability.start == "canonical" and canonical.learnability.canonical_increments >= 1
    assert canonical.stage_order()[0] == ("canonical", "canonical") and len(canonical.test_pairs()) == 21
    changed = canonical.model_dump(mode="json")
    changed["learnability"] = {**changed["learnability"], "start": "initial", "canonical_increments": None}
    assert {**changed, "name": quick["name"]} == quick


def test_the_loop_scores_at_the_detectors_views_unless_told_the_trained_one():
    assert parse_config({"name": "v"}).evaluation.views == "detector"
    assert parse_config({"name": "v", "evaluation": {"views": "trained"}}).evaluation.views == "trained"
    with pytest.raises(ConfigError) as caught:
        parse_config({"name": "v", "evaluation": {"views": "all"}})
    assert "evaluation.views" in str(caught.value) and "'detector' or 'trained'" in str(caught.value)
